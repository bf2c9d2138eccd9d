"""Snakemake rule `fuse`: a thin wrapper around robo3d.pipeline.stage_fuse."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("fuse", snakemake)
