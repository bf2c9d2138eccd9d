"""Snakemake rule `pictures`: a thin wrapper around robo3d.stages.pictures.stage_pictures."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("pictures", snakemake)
