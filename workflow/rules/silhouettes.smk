# The passive half (seed §3): silhouettes -> carved volume.


rule silhouettes:
    input:
        unpack(get_silhouettes_inputs),
    output:
        npz="results/{rec}/silhouettes.npz",
        masks=directory("results/{rec}/masks"),
        report="results/{rec}/reports/silhouettes.json",
        rrd="results/{rec}/silhouettes.rrd",
    params:
        **stage_params("silhouettes"),
        # with laser frames, most views failing leaves no view used, not an error
        has_laser=has_laser,
    log:
        "logs/silhouettes/{rec}.log",
    benchmark:
        "benchmarks/silhouettes/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: stage_threads(2)  # views segmented side by side
    resources:
        mem_mb=lambda wc, attempt: 1000 * attempt,
        runtime=lambda wc, attempt: 10 * attempt,
    script:
        "../scripts/silhouettes.py"


rule carve:
    input:
        silhouettes="results/{rec}/silhouettes.npz",
    output:
        npz="results/{rec}/hull.npz",
        ply="results/{rec}/hull.ply",
        report="results/{rec}/reports/carve.json",
        rrd="results/{rec}/carve.rrd",
    params:
        **stage_params("carve"),
        # with laser frames, silhouettes that carve nothing leave an empty hull, not an error
        has_laser=has_laser,
    log:
        "logs/carve/{rec}.log",
    benchmark:
        "benchmarks/carve/{rec}.tsv"
    conda:
        "../envs/robo3d.yaml"
    # the octree kernel's threads (carving.threads, 0 = all cores)
    threads: stage_threads(config["carving"]["threads"] or workflow.cores)
    resources:
        mem_mb=lambda wc, attempt: 1000 * attempt,
        runtime=lambda wc, attempt: 10 * attempt,
    script:
        "../scripts/carve.py"
