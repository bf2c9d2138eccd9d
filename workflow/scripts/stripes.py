"""Snakemake rule `stripes`: a thin wrapper around robo3d.pipeline.stage_stripes."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("stripes", snakemake)
