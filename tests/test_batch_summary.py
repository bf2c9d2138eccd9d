"""The batch table with failures (results/batch.csv, robo3d.info.batch_summary): every
recording of the batch has a row, a finished one with its figures, a failed one with the
stage that failed, its first error line and the time and memory of the stages that ran.
(tests/test_resume.py checks the same on a real run with a file that is not a recording.)
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

from robo3d.info import STAGE_MARKERS, batch_summary, write_batch_summary

BENCH_HEAD = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"


def _batch(root: Path) -> None:
    res, logs, bench = root / "results", root / "logs", root / "benchmarks"
    for stage, marker in STAGE_MARKERS.items():  # "good" finished every stage
        (res / "good" / marker).parent.mkdir(parents=True, exist_ok=True)
        (res / "good" / marker).write_text("{}")
        (logs / stage).mkdir(parents=True, exist_ok=True)
        (logs / stage / "good.log").write_text("12:00:00 INFO robo3d.summary: done\n")
    metrics = {"name": "good", "evaluation": {"hull_volume_iou": 0.93,
                                              "mesh": {"median_mm": 0.02, "p95_mm": 0.08}},
               "timings": {"total_seconds": 40.0, "carve": {"seconds": 2.5,
                                                             "max_rss_mb": 350.0}}}
    (res / "good" / "metrics.json").write_text(json.dumps(metrics))
    # "bad": silhouettes finished, carve failed with a robo3d error, the rest never ran
    (res / "bad" / "reports").mkdir(parents=True)
    (res / "bad" / STAGE_MARKERS["silhouettes"]).write_text("{}")
    (logs / "silhouettes" / "bad.log").write_text("12:00:00 INFO robo3d.summary: 8 masks\n")
    (logs / "carve" / "bad.log").write_text(
        "12:00:01 INFO robo3d.carve: carving\n"
        "12:00:02 ERROR robo3d: carve for bad: every voxel carved away, check the masks\n")
    (bench / "silhouettes").mkdir(parents=True)
    (bench / "silhouettes" / "bad.tsv").write_text(
        BENCH_HEAD + "3.21\t0:00:03\t224.5\t900\t200\t210\t1\t2\t80\t2.9\n")


def test_every_recording_has_a_row_with_its_figures_or_its_failure(tmp_path):
    _batch(tmp_path)
    rows = {r["recording"]: r for r in batch_summary(
        tmp_path / "results", tmp_path / "logs", ["good", "bad", "never"],
        tmp_path / "benchmarks")}
    assert set(rows) == {"good", "bad", "never"}
    good, bad, never = rows["good"], rows["bad"], rows["never"]
    assert good["status"] == "done" and good["error"] is None
    assert good["hull_iou"] == 0.93 and good["mesh_median_mm"] == 0.02
    assert good["carve_s"] == 2.5 and good["carve_mb"] == 350.0
    assert bad["status"] == "failed" and bad["failed_stage"] == "carve"
    assert bad["error"].endswith("carve for bad: every voxel carved away, check the masks")
    assert bad["log"].endswith("logs/carve/bad.log")
    assert bad["silhouettes_s"] == 3.21 and bad["silhouettes_mb"] == 224.5
    assert bad["carve_s"] is None  # the failed job's benchmark file is not written
    assert never["status"] == "not started" and never["failed_stage"] is None

    out = tmp_path / "results" / "batch.csv"
    write_batch_summary(rows.values(), out)
    with open(out, newline="") as f:
        back = {r["recording"]: r for r in csv.DictReader(f)}
    assert list(back) == ["bad", "good", "never"]  # by name, as robo3d status
    assert back["bad"]["error"] == bad["error"]  # a comma in the message stays in its cell
    assert back["bad"]["failed_stage"] == "carve" and back["bad"]["hull_iou"] == ""
    assert float(back["good"]["hull_iou"]) == 0.93 and back["good"]["error"] == ""
