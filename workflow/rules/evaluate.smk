# Evaluation against the ground truth a simulated recording carries, the per-recording
# summary of what every stage measured (with its time and peak memory), the report's
# pictures of every stage, and the batch's overview and tables (snakemake --report).


# the batch table reads the recordings' metrics.json: on a cluster it runs on the host
# that submits the jobs, not as a job of its own
localrules:
    batch_table,


rule evaluate:
    input:
        unpack(get_evaluate_inputs),
    output:
        metrics="results/{rec}/metrics.json",
        rrd="results/{rec}/evaluate.rrd",
    params:
        **stage_params("evaluate"),
    log:
        "logs/evaluate/{rec}.log",
    benchmark:
        "benchmarks/evaluate/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: stage_threads(2)  # distances to the truth; a lone recording's last stage
    resources:
        mem_mb=lambda wc, attempt: 1500 * attempt,
        runtime=lambda wc, attempt: 15 * attempt,
    script:
        "../scripts/evaluate.py"


rule pictures:
    input:
        unpack(get_pictures_inputs),
    output:
        masks=report(
            "results/{rec}/pictures/masks.png",
            caption="../report/masks.rst",
            category="Recordings",
            subcategory="{rec}",
            labels={"figure": "1. masks over their images", "recording": "{rec}"},
        ),
        stripes=report(
            "results/{rec}/pictures/stripes.png",
            caption="../report/stripes.rst",
            category="Recordings",
            subcategory="{rec}",
            labels={"figure": "2. laser stripes over their frames", "recording": "{rec}"},
        ),
        hull=report(
            "results/{rec}/pictures/hull.png",
            caption="../report/hull.rst",
            category="Recordings",
            subcategory="{rec}",
            labels={"figure": "3. visual hull", "recording": "{rec}"},
        ),
        clouds=report(
            "results/{rec}/pictures/clouds.png",
            caption="../report/clouds.rst",
            category="Recordings",
            subcategory="{rec}",
            labels={"figure": "4. aligned clouds by sweep", "recording": "{rec}"},
        ),
        mesh=report(
            "results/{rec}/pictures/mesh.png",
            caption="../report/mesh.rst",
            category="Recordings",
            subcategory="{rec}",
            labels={"figure": "5. final mesh", "recording": "{rec}"},
        ),
        timings=report(
            "results/{rec}/pictures/timings.png",
            caption="../report/timings.rst",
            category="Recordings",
            subcategory="{rec}",
            labels={"figure": "6. stage timings and memory", "recording": "{rec}"},
        ),
        thumbnail="results/{rec}/pictures/thumbnail.png",
    params:
        **stage_params("pictures"),
    log:
        "logs/pictures/{rec}.log",
    benchmark:
        "benchmarks/pictures/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: 1
    resources:
        mem_mb=lambda wc, attempt: 1500 * attempt,
        runtime=lambda wc, attempt: 5 * attempt,
    script:
        "../scripts/pictures.py"


rule batch_table:
    input:
        metrics=expand("results/{rec}/metrics.json", rec=batch_recordings()),
        pictures=expand("results/{rec}/pictures/thumbnail.png", rec=batch_recordings()),
    output:
        tsv="results/batch.tsv",
        html=report(
            "results/batch.html",
            caption="../report/batch.rst",
            category="Tables",
            labels={"table": "every figure, time and memory of every recording"},
        ),
        overview=report(
            "results/overview.html",
            caption="../report/overview.rst",
            category="Overview",
            labels={"page": "status, key figures against their targets, one picture"},
        ),
    params:
        vmax_mm=config["evaluation"]["picture_vmax_mm"],
    log:
        "logs/batch_table.log",
    conda:
        "../envs/robo3d.yaml"
    threads: 1
    resources:
        mem_mb=lambda wc, attempt: 500 * attempt,
        runtime=lambda wc, attempt: 5 * attempt,
    script:
        "../scripts/batch_table.py"
