"""Snakemake rule `calibrate`: a thin wrapper around robo3d.pipeline.stage_calibrate."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("calibrate", snakemake)
