"""The pipeline's stages, one module per Snakemake rule.

Each ``stage_<name>`` (in ``robo3d.stages.<name>``) takes its input and output paths
(dicts keyed as in the rule), the config sections it reads
(:data:`robo3d.pipeline.STAGE_CONFIG`) and the recording's name; it loads its inputs,
calls the algorithms of the library, writes every output atomically, logs what it made
to rerun and writes a JSON report of what it measured. :mod:`robo3d.stages.common` holds
what they share. :func:`robo3d.pipeline.run_from_snakemake` runs one from a rule.
"""
