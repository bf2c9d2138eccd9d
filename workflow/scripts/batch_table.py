"""Snakemake rule `batch_table`: a thin wrapper around robo3d.evaluate.write_batch_table."""

from robo3d.evaluate import write_batch_table

write_batch_table(list(snakemake.input.metrics), snakemake.output.tsv, snakemake.output.html)
