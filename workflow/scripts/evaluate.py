"""Snakemake rule `evaluate`: a thin wrapper around robo3d.pipeline.stage_evaluate."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("evaluate", snakemake)
