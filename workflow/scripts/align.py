"""Snakemake rule `align`: a thin wrapper around robo3d.pipeline.stage_align."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("align", snakemake)
