# Where the halves meet (seed §2.4): alignment (the silhouettes give the sweeps their
# absolute place), fusion (the hull bounds what the laser did not see), simplification.


rule align:
    input:
        unpack(get_align_inputs),
    output:
        npz="results/{rec}/aligned.npz",
        ply="results/{rec}/aligned.ply",
        report="results/{rec}/reports/align.json",
        rrd="results/{rec}/align.rrd",
    params:
        **stage_params("align"),
    log:
        "logs/align/{rec}.log",
    benchmark:
        "benchmarks/align/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: stage_threads(2)  # pairs and views in parallel; alignment waits for the front end
    resources:
        mem_mb=lambda wc, attempt: 1500 * attempt,
        runtime=lambda wc, attempt: 20 * attempt,
    script:
        "../scripts/align.py"


rule fuse:
    input:
        unpack(get_fuse_inputs),
    output:
        ply="results/{rec}/fused.ply",
        measured="results/{rec}/measured.ply",  # the laser-measured surface only
        report="results/{rec}/reports/fuse.json",
        rrd="results/{rec}/fuse.rrd",
    params:
        **stage_params("fuse"),
    log:
        "logs/fuse/{rec}.log",
    benchmark:
        "benchmarks/fuse/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: stage_threads(2)  # ray casting; fusion waits for alignment, so a lone recording has both cores
    resources:
        mem_mb=lambda wc, attempt: 2500 * attempt,
        runtime=lambda wc, attempt: 20 * attempt,
    script:
        "../scripts/fuse.py"


rule simplify:
    input:
        unpack(get_simplify_inputs),
    output:
        ply="results/{rec}/mesh.ply",
        # simplify.export: the same mesh as STL and/or OBJ too
        **{ext: f"results/{{rec}}/mesh.{ext}" for ext in config["simplify"]["export"]},
        report="results/{rec}/reports/simplify.json",
        rrd="results/{rec}/simplify.rrd",
    params:
        **stage_params("simplify"),
    log:
        "logs/simplify/{rec}.log",
    benchmark:
        "benchmarks/simplify/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: stage_threads(2)  # the distance checks (the collapses run on one)
    resources:
        mem_mb=lambda wc, attempt: 1500 * attempt,
        runtime=lambda wc, attempt: 20 * attempt,
    script:
        "../scripts/simplify.py"
