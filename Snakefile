# robo3d: recordings in, measured meshes out. See README.md and workflow/rules/.
import os
import sys

from snakemake.utils import min_version

min_version("9.0")


configfile: os.path.join(workflow.basedir, "config", "config.yaml")


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/silhouettes.smk"
include: "workflow/rules/laser.smk"
include: "workflow/rules/mesh.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/foxglove.smk"
include: "workflow/rules/calibration.smk"


rule all:
    input:
        get_all_outputs(),
    default_target: True


onsuccess:
    from robo3d.info import batch_summary, format_run_summary, write_batch_summary

    # results/batch.csv: every recording's figures and, when one failed, its failure
    write_batch_summary(batch_summary("results", "logs", RECORDINGS), "results/batch.csv")
    print("\n" + format_run_summary("results", "logs", RECORDINGS), file=sys.stderr)


onerror:
    from robo3d.info import (
        batch_status,
        batch_summary,
        format_batch_status,
        write_batch_summary,
    )

    rows = batch_summary("results", "logs", RECORDINGS)
    write_batch_summary(rows, "results/batch.csv")
    print(format_batch_status(batch_status("results", "logs", RECORDINGS)), file=sys.stderr)
    if RECORDINGS:  # the overview and batch.html with the failures: snakemake --report
        from robo3d.overview import write_unfinished_batch_report

        try:
            write_unfinished_batch_report(sorted(RECORDINGS), rows=rows, jobs=REPORT_JOBS,
                                          vmax_mm=config["evaluation"]["picture_vmax_mm"])
        except Exception as e:  # never hide the run's own error behind this one
            print(f"robo3d: the overview of the unfinished batch was not written: {e}",
                  file=sys.stderr)
