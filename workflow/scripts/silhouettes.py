"""Snakemake rule `silhouettes`: a thin wrapper around robo3d.pipeline.stage_silhouettes."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("silhouettes", snakemake)
