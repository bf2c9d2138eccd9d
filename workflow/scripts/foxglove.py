"""Snakemake rule `foxglove`: a thin wrapper around robo3d.pipeline.stage_foxglove."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("foxglove", snakemake)
