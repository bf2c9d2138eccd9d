# The results for Foxglove: a recording's clouds and meshes as one MCAP file beside its
# other results, in base and on the recording's clock, to open with the recording
# (README "Foxglove"). config foxglove.enabled: false leaves it out of rule all.


rule foxglove:
    input:
        unpack(get_foxglove_inputs),
    output:
        mcap="results/{rec}/results.mcap",
    params:
        **stage_params("foxglove"),
    log:
        "logs/foxglove/{rec}.log",
    benchmark:
        "benchmarks/foxglove/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: 1
    resources:
        mem_mb=lambda wc, attempt: 1000 * attempt,
        runtime=lambda wc, attempt: 5 * attempt,
    script:
        "../scripts/foxglove.py"
