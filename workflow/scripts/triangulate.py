"""Snakemake rule `triangulate`: a thin wrapper around robo3d.pipeline.stage_triangulate."""

from robo3d.pipeline import run_from_snakemake

run_from_snakemake("triangulate", snakemake)
