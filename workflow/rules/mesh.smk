# Where the halves meet (seed §2.4): fusion, then simplification.


rule fuse:
    input:
        unpack(get_fuse_inputs),
    output:
        ply="results/{rec}/fused.ply",
        report="results/{rec}/reports/fuse.json",
        rrd="results/{rec}/fuse.rrd",
    log:
        "logs/fuse/{rec}.log",
    benchmark:
        "benchmarks/fuse/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: 1
    resources:
        mem_mb=6000,
    script:
        "../scripts/fuse.py"


rule simplify:
    input:
        fused="results/{rec}/fused.ply",
    output:
        ply="results/{rec}/mesh.ply",
        report="results/{rec}/reports/simplify.json",
        rrd="results/{rec}/simplify.rrd",
    log:
        "logs/simplify/{rec}.log",
    benchmark:
        "benchmarks/simplify/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: 1
    resources:
        mem_mb=2000,
    script:
        "../scripts/simplify.py"
