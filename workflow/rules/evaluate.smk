# Evaluation against the ground truth a simulated recording carries, the per-recording
# summary of what every stage measured (with its time and peak memory), a picture of the
# final mesh coloured by its error, and the batch table of all recordings.


rule evaluate:
    input:
        unpack(get_evaluate_inputs),
    output:
        metrics="results/{rec}/metrics.json",
        picture=report(
            "results/{rec}/mesh_error.png",
            caption="../report/mesh_error.rst",
            category="Meshes",
            subcategory="{rec}",
            labels={"recording": "{rec}", "figure": "final mesh, error"},
        ),
        rrd="results/{rec}/evaluate.rrd",
    params:
        **stage_params("evaluate"),
    log:
        "logs/evaluate/{rec}.log",
    benchmark:
        "benchmarks/evaluate/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: 1
    resources:
        mem_mb=4000,
    script:
        "../scripts/evaluate.py"


rule batch_table:
    input:
        metrics=expand("results/{rec}/metrics.json", rec=sorted(RECORDINGS)),
    output:
        tsv="results/batch.tsv",
        html=report(
            "results/batch.html",
            caption="../report/batch.rst",
            category="Batch",
            labels={"table": "all recordings"},
        ),
    log:
        "logs/batch_table.log",
    conda:
        "../envs/robo3d.yaml"
    threads: 1
    resources:
        mem_mb=500,
    script:
        "../scripts/batch_table.py"
