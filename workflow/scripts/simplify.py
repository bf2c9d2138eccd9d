"""Snakemake rule `simplify`: a thin wrapper around robo3d.pipeline.stage_simplify."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("simplify", snakemake)
