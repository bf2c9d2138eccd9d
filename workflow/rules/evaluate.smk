# Evaluation against the ground truth a simulated recording carries, and the per-recording
# summary of what every stage measured and what was skipped.


rule evaluate:
    input:
        unpack(get_evaluate_inputs),
    output:
        metrics="results/{rec}/metrics.json",
        rrd="results/{rec}/evaluate.rrd",
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
