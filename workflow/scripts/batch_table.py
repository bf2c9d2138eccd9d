"""Snakemake rule `batch_table`: a thin wrapper around robo3d.overview.write_batch_report."""

from robo3d.overview import write_batch_report

write_batch_report(list(snakemake.input.metrics), list(snakemake.input.pictures),
                   snakemake.output.tsv, snakemake.output.html, snakemake.output.overview,
                   vmax_mm=snakemake.params.vmax_mm)
