"""The benchmarks' results in one table: ``benchmarks/RESULTS.md`` from ``results/*.json``.

Run from the repository root::

    .venv/bin/python benchmarks/table.py          # rewrite benchmarks/RESULTS.md, print it

Every row is one headline figure of one benchmark's ``results/<name>.json`` (the keys the
issues name): what it measures, on what data (simulated or real), the figure, its target,
whether it is met, and, where the benchmark measured a peer in the same run, the peer's
figure and the ratio (how many times better ours is: the peer over ours where lower is
better, ours over the peer where higher is better). Nothing here is measured: the table
only reads what the benchmarks wrote, so it says what was measured, when (each file's
``date``/``code`` where it has them) and under what conditions (each benchmark's
``notes``). ``benchmarks/run_all.py`` runs every benchmark and then this.

Targets are the issues' (the benchmarks that write a ``targets`` dict carry their own;
the others are listed in :data:`ROWS` with the issue they come from).
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).resolve().parent / "results"
OUT = Path(__file__).resolve().parent / "RESULTS.md"


@dataclass(frozen=True)
class Row:
    """One headline figure: ``key`` of ``results/<bench>.json`` (a dotted path)."""

    bench: str
    key: str
    what: str
    unit: str = ""
    target: str | None = None  # e.g. "<= 0.05", ">= 1000", "< 0.5", "== true"
    peer: str | None = None    # dotted key of the peer's figure in the same file
    peer_name: str = ""
    data: str = "simulated"


#: Figures of the benchmarks that carry no ``targets`` dict of their own, with the targets
#: of the issue that asked for them (issue 3: carving, 4: laser, 12: determinism,
#: 13: calibration, 14: batch, whose 'close to twice' is
#: read as 1.8).
ROWS: tuple[Row, ...] = (
    Row("carving", "octree_256_s", "visual hull, octree carving at 256^3, 36 views", "s",
        "< 0.5", "open3d_256_s", "Open3D VoxelGrid.carve_silhouette"),
    Row("carving", "octree_512_s", "visual hull, octree carving at 512^3, 36 views", "s",
        "< 2", "open3d_512_s", "Open3D VoxelGrid.carve_silhouette"),
    Row("carving", "peak_mb_512", "peak memory of the 512^3 carving process", "MB", "< 1000"),
    Row("carving", "iou_vs_exact_hull_256", "hull from the segmented masks vs the exact hull",
        "IoU", ">= 0.99"),
    Row("carving", "mask_iou_min", "segmented masks vs the true silhouettes, worst view",
        "IoU", ">= 0.99"),
    Row("laser", "fps_1280x960", "stripe detection + triangulation, 1280x960 mono",
        "frames/s", ">= 1000", "fps_naive_1280x960", "per-column Python loop"),
    Row("laser", "stage_over_decode", "stripes stage over decoding alone (PNG)", "x",
        "<= 1.3"),
    Row("laser", "median_mm", "stripe points vs the true surface, median", "mm", "<= 0.05"),
    Row("laser", "p95_mm", "stripe points vs the true surface, 95th percentile", "mm",
        "<= 0.2"),
    Row("laser", "centre_rms_px", "sub-pixel centre RMS error, FWHM 1.5 px", "px"),
    Row("laser", "srv_board_plane_rms_mm", "real srv board: stripe points to one plane",
        "mm", "<= 0.5", data="real"),
    Row("determinism", "identical_files", "demo on 1 and 2 cores: every result file",
        "", "== true"),
    Row("determinism", "identical_metrics", "demo on 1 and 2 cores: metrics.json", "",
        "== true"),
    Row("batch", "speedup_2_cores", "batch of small scans: 2 cores over 1 core's throughput",
        "x", ">= 1.8"),
    Row("batch", "parallel_efficiency", "batch of small scans: parallel efficiency on 2 cores",
        ""),
    Row("batch", "speedup_2_cores_job_time_scaled", "batch of small scans: the same, scaled "
        "by the jobs' time two at a time against alone (the cores' mutual slow-down apart)",
        "x"),
    Row("random_scenes", "met.completed", "random small scenes (default config): every one "
        "completes", "", "== true"),
    Row("random_scenes", "end_to_end_s_max", "random small scenes: the slowest, end to end",
        "s"),
    Row("calibration", "rms_px", "intrinsics reprojection RMS, worst seed and rig", "px",
        "<= 0.2"),
    Row("calibration", "focal_rel_err", "focal length relative error", "", "<= 0.001"),
    Row("calibration", "principal_px", "principal point error", "px", "<= 1"),
    Row("calibration", "handeye_mm", "hand-eye translation error", "mm", "<= 0.3"),
    Row("calibration", "handeye_deg", "hand-eye rotation error", "deg", "<= 0.05"),
    Row("calibration", "sheet_normal_deg", "laser sheet normal error", "deg", "<= 0.03"),
    Row("calibration", "sheet_offset_mm", "laser sheet offset error", "mm", "<= 0.03"),
    Row("calibration", "scan_error_ratio", "scan error with the estimate / with the truth",
        "x", "<= 1.2"),
    Row("calibration", "kuka1_board_scatter_mm", "real KUKA hand-eye: board scatter", "mm",
        None, "kuka1_board_scatter_opencv_mm", "OpenCV calibrateCamera + Tsai", "real"),
    Row("calibration", "srv_rms_px", "real srv intrinsics RMS (data set's README: 0.137)",
        "px", data="real"),
    Row("calibration", "srv_plane_rms_mm", "real srv sheet residual (data set's README: 0.45)",
        "mm", data="real"),
)

#: Benchmarks whose files carry their own ``targets``: what each key measures and its unit.
DESCRIBED: dict[str, dict[str, tuple[str, str, str]]] = {
    "front_end": {
        "dtu24_mask_iou_mean": ("DTU scan 24 masks vs the published ones, mean", "IoU", "real"),
        "dtu24_mask_iou_min": ("DTU scan 24 masks vs the published ones, worst view", "IoU",
                               "real"),
        "sim_mask_iou_min": ("room-lit cells: masks vs the truth, worst view", "IoU",
                             "simulated"),
        "stripe_median_mm": ("room-lit cells: delivered stripe points, median", "mm",
                             "simulated"),
        "stripe_p95_mm": ("room-lit cells: delivered stripe points, p95", "mm", "simulated"),
        "stripe_recall_min": ("room-lit cells: visible stripe found, worst colour", "",
                              "simulated"),
        "stripe_outlier_fraction": ("room-lit cells: points > 1 mm off, worst colour", "",
                                    "simulated"),
        "srv_board_plane_rms_mm": ("real srv board: stripe points to one plane", "mm", "real"),
        "pose_err_after_mm": ("drifting robot error: worst sweep after alignment", "mm",
                              "simulated"),
        "pose_err_after_deg": ("drifting robot error: worst sweep after alignment", "deg",
                               "simulated"),
        "mesh_median_mm": ("drifting robot error: final mesh, median", "mm", "simulated"),
        "mesh_p95_mm": ("drifting robot error: final mesh, p95", "mm", "simulated"),
        "completeness_0_5mm": ("drifting robot error: completeness at 0.5 mm", "",
                               "simulated"),
        "fps_ambient_1280x960": ("room-lit 1280x960 RGB: detection + triangulation, 2 threads",
                                 "frames/s", "simulated"),
        "stage_over_decode_ambient": ("room-lit frames: stripes stage over decoding", "x",
                                      "simulated"),
    },
    "pipeline": {
        "pose_err_after_mm": ("worst sweep after alignment, at the object", "mm", "simulated"),
        "pose_err_after_deg": ("worst sweep after alignment, rotation", "deg", "simulated"),
        "mesh_median_mm": ("final mesh vs the truth, median", "mm", "simulated"),
        "mesh_p95_mm": ("final mesh vs the truth, p95", "mm", "simulated"),
        "completeness_0_5mm": ("completeness at 0.5 mm", "", "simulated"),
        "end_to_end_s": ("end to end, one recording, --cores 2", "s", "simulated"),
    },
    "hard_scenes": {
        "completed": ("objects of the background's colours: the scan completes", "",
                      "simulated"),
        "mask_iou_mean": ("masks vs the truth, mean (known limit)", "IoU", "simulated"),
        "measured_median_mm": ("measured surface, median", "mm", "simulated"),
        "measured_completeness_0_5mm": ("observable surface within 0.5 mm", "",
                                        "simulated"),
        "inferred_area_fraction": ("inferred share of the mesh's area", "", "simulated"),
        "mesh_median_mm": ("whole mesh, median", "mm", "simulated"),
    },
    "objects": {
        "aligned_median_mm": ("aligned clouds vs the truth, median", "mm", "simulated"),
        "pose_err_after_mm": ("worst sweep after alignment", "mm", "simulated"),
        "pose_err_after_deg": ("worst sweep after alignment", "deg", "simulated"),
        "measured_median_mm": ("measured surface, median", "mm", "simulated"),
        "measured_p95_mm": ("measured surface, p95", "mm", "simulated"),
        "measured_outlier_area_fraction": ("measured area > 0.5 mm off", "", "simulated"),
        "measured_completeness_0_5mm": ("observable surface within 0.5 mm", "", "simulated"),
        "inferred_area_fraction": ("inferred share of the mesh's area", "", "simulated"),
        "mesh_median_mm": ("whole mesh, median", "mm", "simulated"),
        "mesh_p95_mm": ("whole mesh, p95", "mm", "simulated"),
        "end_to_end_s": ("end to end, --cores 2", "s", "simulated"),
    },
}
#: objects.py --setting issue: the same figures at issue 11's settings (1280 x 960, 150
#: frames per sweep, exact views)
DESCRIBED["objects_issue"] = {k: (what, unit, "simulated, issue 11's settings")
                              for k, (what, unit, _) in DESCRIBED["objects"].items()}


def _get(d: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        if not isinstance(d, dict) or part not in d:
            return None
        d = d[part]
    return d


def _num(x: Any) -> str:
    if isinstance(x, bool):
        return "true" if x else "false"
    if not isinstance(x, (int, float)) or not math.isfinite(x):
        return "—" if x is None else str(x)
    a = abs(x)
    if a == 0 or 0.01 <= a < 10_000:
        return f"{x:.4g}" if a < 10 else f"{x:.1f}" if a < 1000 else f"{x:.0f}"
    return f"{x:.3g}"


def _met(value: Any, target: str | None) -> str:
    """'yes' / '**no**' / '' for a value against a target such as '<= 0.05' or '== true'."""
    if target is None or value is None:
        return ""
    op, _, rhs = str(target).partition(" ")
    if op == "==":
        ok = str(value).lower() == rhs.lower()
    else:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return ""
        t = float(rhs)
        ok = {"<=": value <= t, "<": value < t, ">=": value >= t, ">": value > t}.get(op)
        if ok is None:
            return ""
    return "yes" if ok else "**no**"


def _ratio(value: Any, peer: Any, target: str | None, unit: str) -> str:
    """How many times better ours is than the peer (direction from the target or unit)."""
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and x > 0
               for x in (value, peer)):
        return ""
    higher_better = (target or "").startswith(">") or unit == "frames/s"
    r = value / peer if higher_better else peer / value
    return f"{r:.3g}x"


def _target_of(key: str, t: Any) -> str | None:
    """A target as the files give it: a string such as '>= 0.99', or a bare number (the
    pipeline's), an upper bound except for the figures where more is better."""
    if t is None:
        return None
    if isinstance(t, str):
        return t
    more_is_better = any(w in key for w in ("completeness", "iou", "recall", "fps"))
    return f"{'>=' if more_is_better else '<='} {t}"


def _rows_fixed(data: dict[str, dict]) -> list[list[str]]:
    out = []
    for r in ROWS:
        d = data.get(r.bench)
        if d is None:
            continue
        v = _get(d, r.key)
        p = _get(d, r.peer) if r.peer else None
        out.append([r.bench, r.what, r.data, f"`{r.key}`", _num(v), r.unit, r.target or "",
                    _met(v, r.target), f"{_num(p)} ({r.peer_name})" if r.peer else "",
                    _ratio(v, p, r.target, r.unit) if r.peer else ""])
    return out


def _rows_targeted(data: dict[str, dict]) -> list[list[str]]:
    """front_end (flat keys, some per laser colour), pipeline and objects (per entry)."""
    out = []
    for bench, described in DESCRIBED.items():
        d = data.get(bench)
        if d is None:
            continue
        targets = d.get("targets", {})
        entries = ([(None, d)] if bench == "front_end" else
                   [(k, v) for k, v in d.items() if isinstance(v, dict)
                    and k not in ("targets", "met", "details")])
        for entry, vals in entries:
            for key, (what, unit, kind) in described.items():
                v = vals.get(key)
                if v is None:
                    continue
                t = _target_of(key, targets.get(key))
                parts = v.items() if isinstance(v, dict) else [(None, v)]
                for sub, x in parts:
                    label = what + (f" ({sub})" if sub else "")
                    name = f"{bench} {entry}" if entry else bench
                    out.append([name, label, kind, f"`{key}`", _num(x), unit, t or "",
                                _met(x, t), "", ""])
    return out


def _when(name: str, d: dict) -> str:
    bits = [str(d[k]) for k in ("date", "code") if d.get(k)]
    return f"{name}: " + (", ".join(bits) if bits else "see its notes")


def build(results: Path = RESULTS) -> str:
    """The Markdown table of every ``results/*.json`` the benchmarks wrote."""
    data = {}
    for p in sorted(results.glob("*.json")):
        try:
            data[p.stem] = json.loads(p.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise SystemExit(f"{p}: not readable as JSON ({e})") from e
    head = ["benchmark", "what", "data", "key", "measured", "unit", "target", "met",
            "peer (same run)", "ours vs peer"]
    rows = _rows_fixed(data) + _rows_targeted(data)
    lines = ["# Benchmark results", "",
             "Written by `benchmarks/table.py` from `benchmarks/results/*.json` (run every "
             "benchmark and then this: `.venv/bin/python benchmarks/run_all.py`). Each "
             "figure was measured by its benchmark on this project's 2-core machine; the "
             "data column says whether on simulated recordings (the simulator knows the "
             "truth) or on real ones (`../shared/real/`). Ratios compare with a peer "
             "measured in the same run (how many times better ours is). What each "
             "benchmark does, and the conditions of its last run (load, code version), are "
             "in `benchmarks/README.md` and in each file's `notes`.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    lines += ["", "Measured at: " + "; ".join(_when(k, v) for k, v in data.items()) + "."]
    missing = sorted(({r.bench for r in ROWS} | set(DESCRIBED)) - set(data))
    if missing:
        lines += ["", "Not measured yet: " + ", ".join(missing) + "."]
    others = sorted(set(data) - {r.bench for r in ROWS} - set(DESCRIBED))
    if others:
        lines += ["", "Also in `results/` (no headline rows here yet): "
                  + ", ".join(f"`{o}.json`" for o in others) + "."]
    return "\n".join(lines) + "\n"


def main() -> int:
    text = build()
    OUT.write_text(text)
    sys.stdout.write(text)
    print(f"\nwrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
