"""Snakemake rule `carve`: a thin wrapper around robo3d.pipeline.stage_carve."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("carve", snakemake)
