# Calibration (seed §3.3; issue 13): a kind=calibration recording -> intrinsics, hand-eye and
# laser sheet in results/calibration/{calib}.yaml, checked by the quality gates
# (calibration_gates). Scans that name it in scan_calibration read it instead of their own.


rule calibrate:
    input:
        recording=get_calibration_recording,
    output:
        yaml="results/calibration/{calib}.yaml",
        report="results/calibration/{calib}_report.json",
        picture="results/calibration/{calib}_detections.png",
    params:
        **stage_params("calibrate"),
    log:
        "logs/calibrate/{calib}.log",
    benchmark:
        "benchmarks/calibrate/{calib}.tsv"
    conda:
        "../envs/robo3d.yaml"
    threads: 1
    resources:
        mem_mb=lambda wc, attempt: 4000 * attempt,
        runtime=lambda wc, attempt: 30 * attempt,
    script:
        "../scripts/calibrate.py"
