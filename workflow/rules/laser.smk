# The active half (seed §4): stripe pixels -> triangulated clouds (aligned in mesh.smk,
# where the silhouettes serve as the alignment's absolute reference).


rule stripes:
    input:
        unpack(get_scan_inputs),
    output:
        npz="results/{rec}/stripes.npz",
        report="results/{rec}/reports/stripes.json",
        rrd="results/{rec}/stripes.rrd",
    params:
        **stage_params("stripes"),
    log:
        "logs/stripes/{rec}.log",
    benchmark:
        "benchmarks/stripes/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: stage_threads(2)  # frames are decoded and searched in parallel
    resources:
        mem_mb=lambda wc, attempt: 1000 * attempt,
        runtime=lambda wc, attempt: 15 * attempt,
    script:
        "../scripts/stripes.py"


rule triangulate:
    input:
        stripes="results/{rec}/stripes.npz",
    output:
        npz="results/{rec}/clouds.npz",
        ply="results/{rec}/clouds.ply",
        report="results/{rec}/reports/triangulate.json",
        rrd="results/{rec}/triangulate.rrd",
    params:
        **stage_params("triangulate"),
    log:
        "logs/triangulate/{rec}.log",
    benchmark:
        "benchmarks/triangulate/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: 1
    resources:
        mem_mb=lambda wc, attempt: 1000 * attempt,
        runtime=lambda wc, attempt: 10 * attempt,
    script:
        "../scripts/triangulate.py"
