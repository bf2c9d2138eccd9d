"""What a person reads first: the batch's overview and tables, in words and units.

- :data:`KEY_FIGURES`: the figures a scan is judged by, where each is in
  ``metrics.json``, its unit and its target (the one table of targets the report uses;
  each target is the one our benchmarks hold the pipeline to, named in ``source``).
- :func:`recording_status`: a recording's status in a few words, and what to look at.
- :data:`TABLE_GROUPS`: the batch table's columns (:func:`robo3d.evaluate.batch_rows`
  keys) with names a person understands and their units.
- :func:`write_batch_report`: ``batch.tsv`` (machine-readable keys, as before),
  ``batch.html`` (the figures and, apart, the time and peak memory of every stage) and
  ``overview.html`` (per recording: status, key figures against their targets, one
  picture), the overview self-contained (pictures inlined) so that the Snakemake
  report's landing page can show it as it is. A recording that did not finish (a stage
  failed, or the run stopped) has its card and its row too, with the stage that failed,
  its first error line and its log.
- :func:`write_unfinished_batch_report`: the same pages after a run in which recordings
  failed (the workflow's ``onerror``; rule ``batch_table`` cannot run then), so that
  ``snakemake --report`` shows the finished recordings and the failures.
"""

from __future__ import annotations

import base64
import html
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["KeyFigure", "KEY_FIGURES", "TABLE_GROUPS", "STAGE_NAMES", "key_figures",
           "recording_status", "batch_html", "overview_html", "write_batch_report",
           "write_unfinished_batch_report"]


@dataclass(frozen=True)
class KeyFigure:
    """One figure of the overview.

    Attributes
    ----------
    label : str
        What it is, in words.
    unit : str
        Its unit as shown ("mm", "%", "" for a ratio).
    paths : tuple of tuple of str
        Where it is in ``metrics.json``: the first path present is used.
    op : {"<=", ">=", "<", None}
        How the value must compare with ``target`` (None: no target).
    target : float or None
        In the shown unit.
    scale : float
        Shown value = stored value * scale (e.g. 100 for a fraction shown in %).
    digits : int
        Decimals shown.
    source : str
        Where the target comes from.
    """

    label: str
    unit: str
    paths: tuple[tuple[str, ...], ...]
    op: str | None = None
    target: float | None = None
    scale: float = 1.0
    digits: int = 3
    source: str = ""


_SIM = "benchmarks/results/pipeline.json and objects.json (simulated scans)"
#: The key figures of a recording, in the overview's order (targets in the shown unit).
KEY_FIGURES: tuple[KeyFigure, ...] = (
    KeyFigure("Mask IoU with the true silhouettes, mean of the views", "",
              (("evaluation", "mask_iou", "mean"),), ">=", 0.97,
              source="benchmarks/results/front_end.json (DTU scan 24)"),
    KeyFigure("Mask IoU, worst view", "", (("evaluation", "mask_iou", "min"),), ">=", 0.93,
              source="benchmarks/results/front_end.json (DTU scan 24)"),
    KeyFigure("Visual hull volume IoU with the true object", "",
              (("evaluation", "hull_volume_iou"),), source="no target: a hull is bigger "
              "than a concave object by design"),
    KeyFigure("Worst pose error after alignment: displacement of a laser frame's points",
              "mm",
              (("evaluation", "poses", "worst_after_frame_mm"),
               ("evaluation", "poses", "worst_after_obj_mm")), "<=", 0.05, source=_SIM),
    KeyFigure("Worst pose error after alignment: rotation", "deg",
              (("evaluation", "poses", "worst_after_frame_deg"),
               ("evaluation", "poses", "worst_after_deg")), "<=", 0.02, digits=4, source=_SIM),
    KeyFigure("Final mesh to the true surface, median", "mm",
              (("evaluation", "mesh", "median_mm"),), "<=", 0.05, source=_SIM),
    KeyFigure("Final mesh to the true surface, 95th percentile", "mm",
              (("evaluation", "mesh", "p95_mm"),), "<=", 0.2, source=_SIM),
    KeyFigure("True surface covered by the mesh within 0.5 mm", "%",
              (("evaluation", "mesh", "completeness", "within_mm", "0.5"),), ">=", 99.0,
              scale=100.0, digits=1, source=_SIM),
    KeyFigure("Measured surface farther than 0.5 mm from the truth", "% of its area",
              (("evaluation", "measured", "outlier_area_fraction_0_5mm"),), "<", 0.1,
              scale=100.0, digits=2, source="benchmarks/results/objects.json"),
    KeyFigure("Surface measured by the laser (the rest inferred from the hull)", "% of area",
              (("surface_sources", "mesh", "measured"),
               ("surface_sources", "laser_area_fraction")), scale=100.0, digits=1,
              source="no target: depends on what the sweeps could see"),
    KeyFigure("Time of all stages (job time, one core each)", "s",
              (("timings", "total_seconds"),), "<=", 60.0, digits=1,
              source="benchmarks/results/pipeline.json (end to end, demo recordings)"),
)

#: The pipeline's stages as a person names them (batch table, timings).
STAGE_NAMES = {"silhouettes": "silhouettes", "carve": "carve (hull)", "stripes": "stripes",
               "triangulate": "triangulate", "align": "align", "fuse": "fuse",
               "simplify": "simplify", "evaluate": "evaluate"}

#: The batch table: (group, [(batch_rows key, column name, unit, scale, decimals)]).
TABLE_GROUPS: tuple[tuple[str, tuple[tuple[str, str, str, float, int], ...]], ...] = (
    ("Silhouettes and hull", (
        ("mask_iou_mean", "mask IoU, mean", "", 1.0, 3),
        ("mask_iou_min", "mask IoU, worst view", "", 1.0, 3),
        ("views_left_out", "views left out of the hull", "", 1.0, 0),
        ("hull_iou", "hull volume IoU", "", 1.0, 3))),
    ("Worst sweep pose error", (
        ("pose_before_mm", "before alignment", "mm", 1.0, 3),
        ("pose_before_deg", "before alignment", "deg", 1.0, 3),
        ("pose_after_mm", "after, at the object", "mm", 1.0, 3),
        ("pose_after_flange_mm", "after, at the flange", "mm", 1.0, 3),
        ("pose_after_deg", "after alignment", "deg", 1.0, 4))),
    ("Final mesh against the true surface", (
        ("mesh_median_mm", "distance, median", "mm", 1.0, 3),
        ("mesh_p95_mm", "distance, 95th percentile", "mm", 1.0, 3),
        ("complete_*", "true surface covered within {t} mm", "%", 100.0, 1))),
    ("Final mesh", (
        ("laser_fraction", "area measured by the laser", "%", 100.0, 1),
        ("faces", "faces", "", 1.0, 0),
        ("hausdorff_mm", "simplification error, max", "mm", 1.0, 3),
        ("total_s", "time of all stages", "s", 1.0, 1))),
)


def _get(d: Any, path: Sequence[str]) -> Any:
    for k in path:
        if not isinstance(d, Mapping) or k not in d:
            return None
        d = d[k]
    return d


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and v == v


def key_figures(metrics: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The recording's :data:`KEY_FIGURES`: one dict per figure with ``label``, ``unit``,
    ``value`` (shown unit, None when not measured), ``target`` (text, "" without one),
    ``met`` (True, False, or None: no target or no value) and ``source``."""
    out = []
    for k in KEY_FIGURES:
        raw = next((v for p in k.paths if _number(v := _get(metrics, p))), None)
        value = None if raw is None else float(raw) * k.scale
        met = None
        if value is not None and k.op is not None:
            met = {"<=": value <= k.target, ">=": value >= k.target,
                   "<": value < k.target}[k.op]
        shown = {"<=": "≤", ">=": "≥", "<": "<"}.get(k.op or "", "")
        target = "" if k.op is None else f"{shown} {k.target:g}"
        out.append({"label": k.label, "unit": k.unit, "value": value, "digits": k.digits,
                    "target": target, "met": met, "source": k.source})
    return out


def recording_status(metrics: Mapping[str, Any]) -> tuple[str, list[str]]:
    """A recording's status in a few words and the notes a person should read: what
    was skipped and why, targets missed, views the carve left out, sweeps the
    alignment flagged, a simplification beyond its tolerance."""
    figs = key_figures(metrics)
    skipped = metrics.get("skipped") or {}
    missed = [f["label"] for f in figs if f["met"] is False]
    judged = [f for f in figs if f["met"] is not None]
    parts = ["done"]
    if "evaluation" in skipped:
        parts.append("no ground truth, so no error against it")
    elif "surface_evaluation" in skipped:
        parts.append("no true surface, so no mesh error (see the notes)")
    if missed:
        parts.append(f"{len(missed)} of {len(judged)} targets missed")
    elif judged:
        parts.append("all targets met" if len(judged) > 1 else "its one target met")
    status = "; ".join(parts)
    notes = [f"{k}: {v}" for k, v in skipped.items() if k not in ("mask_iou", "evaluation")]
    left = metrics.get("views_left_out") or []
    if left:
        notes.append(f"{len(left)} view(s) left out of the hull by the agreement check")
    seeded = _get(metrics, ("stages", "silhouettes", "laser_seeded", "candidates")) or {}
    n_seeded = sum(bool(isinstance(c, dict) and c.get("accepted")) for c in seeded.values())
    if n_seeded:
        notes.append(f"{n_seeded} view(s) segmented again from where the laser measured "
                     "the object (the colour model's masks left its points outside)")
    failed = _get(metrics, ("stages", "silhouettes", "views_failed")) or []
    if failed:
        notes.append(f"{len(failed)} view(s) gave no silhouette and were not used")
    if _get(metrics, ("stages", "carve", "empty")):
        # the carve's own reason (every voxel carved, every mask empty, only flagged views)
        why = _get(metrics, ("stages", "carve", "reason"))
        notes.append(f"no visual hull: {why}" if isinstance(why, str) and why
                     else "no visual hull: the silhouettes carved every voxel")
    pieces = _get(metrics, ("stages", "carve", "pieces", "warning"))
    if isinstance(pieces, str) and pieces:
        notes.append(pieces)
    if _get(metrics, ("stages", "align", "outside_hull", "contradicted")):
        notes.append("the silhouettes contradict the laser: no laser point was dropped "
                     "by them")
    if _get(metrics, ("stages", "align", "outside_hull", "views_agreement", "overrules")):
        share = _get(metrics, ("stages", "align", "outside_hull", "dropped_fraction"))
        notes.append("the views agree with each other and overrule the laser: "
                     + (f"{100 * share:.0f} % of its points" if _number(share) else "its points")
                     + " outside them dropped as not on the object")
    if _get(metrics, ("surface_sources", "hull_contradicted")):
        notes.append("the hull contradicts the laser: nothing closed, the mesh is the "
                     "measured surface")
    if _get(metrics, ("surface_sources", "object_not_found")):
        notes.append("no object found: no box, no hull, and the laser saw too little above "
                     "the table; the mesh is what it saw, most likely the table")
    if _get(metrics, ("surface_sources", "laser_unusable")):
        notes.append("the laser measured nothing usable on the object: the mesh is the "
                     "visual hull's, all of it inferred")
    colour_note = _laser_colour_note(_get(metrics, ("stages", "stripes")))
    if colour_note:
        notes.append(colour_note)
    flagged = [s.get("sweep") for s in _get(metrics, ("stages", "align", "per_sweep")) or []
               if isinstance(s, Mapping) and s.get("flagged")]
    if flagged:
        share = _get(metrics, ("stages", "fuse", "flagged_sweep_area_fraction"))
        notes.append(f"alignment flagged sweep(s) {', '.join(map(str, flagged))}" + (
            f": {100 * share:.0f} % of the mesh's area rests on their robot poses alone "
            "(flagged_sweep in the PLY files)" if _number(share) and share > 0 else ""))
    if _get(metrics, ("stages", "simplify", "within_tolerance")) is False:
        notes.append("the simplified mesh is not within its Hausdorff tolerance")
    return status, notes


def _laser_colour_note(stripes: Any) -> str | None:
    """The stripes stage's laser colour check in words, where a person should know of it:
    the colour was changed from the laser frames' own vote (by the views, or without them
    by motion), or it was close to another and nothing could check it (its stripe points
    may be a coloured texture's edges, labelled measured); None otherwise."""
    if not isinstance(stripes, Mapping):
        return None
    check = stripes.get("laser_colour_check")
    if not isinstance(check, Mapping) or not check.get("contested"):
        return None
    vote, colour = check.get("colour_by_laser_frames"), check.get("colour")
    if colour and vote and colour != vote:
        by = ("the laser frames' motion (its ridges stay put between frames, the "
              f"{vote} ones move with the scene)" if "motion" in check else
              f"the views (they show the {vote} ridges without the laser)")
        return f"laser colour {colour}, not the laser frames' vote {vote}: told by {by}"
    if "views" in check or "motion" not in check:
        return None  # the views kept it, or laser-off frames took the scene away
    moves = _get(check, ("motion", "contrasts", str(vote), "moves_with"))
    if moves == "camera":  # the frames' motion confirms it
        return None
    why = check.get("skipped") or "not checked"
    return (f"laser colour {vote} was close to another and could not be checked ({why}; "
            "nor by the frames' motion): its stripe points may be a coloured texture's "
            "edges (laser_colour_check in reports/stripes.json)")


def _fmt(v: Any, digits: int, scale: float = 1.0) -> str:
    if not _number(v):
        return "" if v is None else str(v)
    return f"{float(v) * scale:,.{digits}f}"


_CSS = """<style>
.items-center:has(.robo3d-overview){align-items:flex-start}
.max-w-lg:has(.robo3d-overview){max-width:60rem}
.robo3d-overview{font-family:system-ui,sans-serif;font-size:14px;color:#222}
.robo3d-overview h1{font-size:20px;margin:4px 0 8px}
.robo3d-overview h2{font-size:16px;margin:14px 0 4px}
.robo3d-overview .status{margin:0 0 6px;color:#444}
.robo3d-overview .card{border:1px solid #ddd;border-radius:6px;padding:8px 10px;
  margin:10px 0;overflow:auto}
.robo3d-overview img{float:left;margin:0 12px 6px 0!important;width:240px;height:auto}
.robo3d-overview table{border-collapse:collapse;font-size:13px;margin:0;width:auto}
.robo3d-overview td,.robo3d-overview th{border-bottom:1px solid #eee;padding:2px 6px;
  text-align:left;vertical-align:top}
.robo3d-overview td.num{text-align:right;white-space:nowrap}
.robo3d-overview .ok{color:#1a7f37}.robo3d-overview .miss{color:#c62828;font-weight:600}
.robo3d-overview .none{color:#888}
.robo3d-overview .key{font-size:12px;color:#555;clear:left;padding-top:4px}
.robo3d-overview .sw{display:inline-block;width:11px;height:11px;margin:0 3px 0 8px;
  vertical-align:-1px}
.robo3d-overview ul{margin:4px 0 0 18px;padding:0}
</style>"""


def _colour_key(metrics: Mapping[str, Any], vmax_mm: float | None) -> str:
    """What the picture's colours mean, in HTML."""
    if _get(metrics, ("evaluation", "mesh", "median_mm")) is not None:
        top = f"{vmax_mm:g} mm" if vmax_mm else "the colour bar's end"
        return ("Colour: distance to the true surface, blue 0 mm to red at or beyond "
                f"{top}.")
    sw = "".join(f"<span class='sw' style='background:rgb({r * 255:.0f},{g * 255:.0f},"
                 f"{b * 255:.0f})'></span>{html.escape(label)}"
                 for (r, g, b), label in (((0.72, 0.72, 0.72), "measured by the laser"),
                                          ((0.95, 0.55, 0.15), "inferred from the hull"),
                                          ((0.95, 0.85, 0.25), "filled")))
    return f"No ground truth: coloured by where the surface came from:{sw}."


def _card(metrics: Mapping[str, Any], picture: bytes | None, vmax_mm: float | None) -> str:
    name = html.escape(str(metrics.get("name", "?")))
    status, notes = recording_status(metrics)
    rows = []
    for f in key_figures(metrics):
        if f["value"] is None:
            continue
        mark = {True: "<span class='ok'>met</span>", False: "<span class='miss'>missed</span>",
                None: "<span class='none'>no target</span>"}[f["met"]]
        unit = f" {html.escape(f['unit'])}" if f["unit"] else ""
        rows.append(f"<tr><td>{html.escape(f['label'])}</td><td class='num'>"
                    f"{_fmt(f['value'], f['digits'])}{unit}</td><td class='num'>"
                    f"{html.escape(f['target'])}</td><td>{mark}</td></tr>")
    if not rows:
        rows.append("<tr><td colspan='4'>no figure to judge (no ground truth)</td></tr>")
    img = ("" if picture is None else "<img alt='final mesh of " + name + "' src='data:image/"
           "png;base64," + base64.b64encode(picture).decode("ascii") + "'>")
    note = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
    return (f"<div class='card'><h2>{name}</h2><p class='status'>{html.escape(status)}</p>"
            f"{img}<table><tr><th>figure</th><th>value</th><th>target</th><th></th></tr>"
            f"{''.join(rows)}</table><div class='key'>{_colour_key(metrics, vmax_mm)}"
            f"{'<ul>' + note + '</ul>' if note else ''}</div></div>")


def _failure_text(row: Mapping[str, Any]) -> str:
    """What happened to a recording that did not finish, in a line."""
    if row.get("status") == "failed":
        stage = STAGE_NAMES.get(row.get("failed_stage"), row.get("failed_stage"))
        return f"failed in the {stage} stage" + (f": {row['error']}" if row.get("error") else "")
    return {"incomplete": "not finished: a stage was stopped before it ended",
            "not started": "not started"}.get(str(row.get("status")),
                                              f"not finished ({row.get('status')})")


def _failed_card(row: Mapping[str, Any]) -> str:
    name = html.escape(str(row.get("recording", "?")))
    log = (f"<div class='key'>Log: {html.escape(str(row['log']))}. Re-run the workflow "
           "after fixing it: what finished is kept.</div>") if row.get("log") else ""
    return (f"<div class='card'><h2>{name}</h2><p class='status miss'>"
            f"{html.escape(_failure_text(row))}</p>{log}</div>")


def overview_html(metrics: Sequence[Mapping[str, Any]], pictures: Sequence[bytes | None],
                  vmax_mm: float | None = None,
                  failures: Sequence[Mapping[str, Any]] = ()) -> str:
    """The overview page: per recording its status, key figures against their targets
    and one picture (PNG bytes, inlined). Self-contained: its styles are scoped to
    ``.robo3d-overview`` so that the page can also be placed inside another (two rules
    widen and top-align the Snakemake report's landing column when it holds the
    overview, and do nothing elsewhere). ``failures``: rows of
    :func:`robo3d.info.batch_summary` of the recordings that did not finish, each a card
    with the stage that failed, its error and its log, first."""
    cards = "".join(_failed_card(r) for r in failures) + "".join(
        _card(m, p, vmax_mm) for m, p in zip(metrics, pictures, strict=True))
    missed = sum(any(f["met"] is False for f in key_figures(m)) for m in metrics)
    failed = sum(r.get("status") == "failed" for r in failures)
    unfinished = (f"{failed} failed, " if failed else "") + (
        f"{len(failures) - failed} not finished, " if len(failures) > failed else "")
    return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>robo3d overview"
            f"</title>{_CSS}</head><body><div class='robo3d-overview'>"
            f"<h1>robo3d: {len(metrics) + len(failures)} recording(s)</h1><p class='status'>"
            f"{unfinished}{len(metrics) - missed} without a missed target, {missed} with. "
            "Targets: "
            "what the benchmarks hold the pipeline to (robo3d/overview.py). Every "
            "stage's pictures are under <b>Recordings</b>, every figure under <b>Tables"
            f"</b>.</p>{cards}</div></body></html>\n")


def _columns(rows: Sequence[Mapping[str, Any]]) -> list[tuple[str, list[tuple[str, str, float,
                                                                                int]]]]:
    """The table's groups with the columns the rows have (``complete_*`` expanded)."""
    keys = [k for r in rows for k in r]
    out = []
    for group, cols in TABLE_GROUPS:
        have = []
        for key, label, unit, scale, digits in cols:
            if key == "complete_*":
                ts = sorted({k for k in keys if k.startswith("complete_")},
                            key=lambda k: float(k[len("complete_"):-2]))
                have += [(k, label.format(t=k[len("complete_"):-2]) + f" ({unit})", scale,
                          digits) for k in ts]
            elif key in keys:
                have.append((key, label + (f" ({unit})" if unit else ""), scale, digits))
        if have:
            out.append((group, have))
    return out


def _mb(v: Any) -> str:
    return f"{_fmt(v, 0)} MB" if _number(v) else "memory not measured"


def batch_html(rows: Sequence[Mapping[str, Any]],
               failures: Sequence[Mapping[str, Any]] = ()) -> str:
    """``batch.html``: every recording's figures (grouped, named in words with their
    units, a target row where a figure has one) and, apart, each stage's time and peak
    memory. ``failures`` (rows of :func:`robo3d.info.batch_summary` of recordings that did
    not finish): a row each saying what failed, and the time and memory of the stages
    that ran."""
    groups = _columns(rows)
    width = max(1, sum(len(c) for _, c in groups))
    head1 = "<th rowspan='2'>recording</th>" + "".join(
        f"<th colspan='{len(c)}'>{html.escape(g)}</th>" for g, c in groups)
    head2 = "".join(f"<th>{html.escape(lab)}</th>" for _, c in groups for _, lab, _, _ in c)
    body = "".join("<tr><td>" + html.escape(str(r.get("recording"))) + "</td>" + "".join(
        f"<td class='num'>{_fmt(r.get(k), d, s)}</td>" for _, c in groups for k, _, s, d in c)
        + "</tr>" for r in rows) + "".join(
        "<tr><td>" + html.escape(str(r.get("recording"))) + f"</td><td colspan='{width}' "
        "class='fail'>" + html.escape(_failure_text(r)) + "</td></tr>" for r in failures)
    rows = [*rows, *failures]
    stages = [s for s in STAGE_NAMES if any(r.get(f"{s}_s") is not None for r in rows)]
    t_head = "".join(f"<th>{html.escape(STAGE_NAMES[s])}</th>" for s in stages)
    t_body = "".join("<tr><td>" + html.escape(str(r.get("recording"))) + "</td>" + "".join(
        f"<td class='num'>{_fmt(r.get(f'{s}_s'), 1)} s<br>{_mb(r.get(f'{s}_mb'))}</td>"
        if r.get(f"{s}_s") is not None else "<td></td>" for s in stages) + "</tr>"
        for r in rows)
    css = ("<style>body{font-family:system-ui,sans-serif;font-size:13px;color:#222}"
           "table{border-collapse:collapse;margin:6px 0 16px}td,th{border:1px solid #ddd;"
           "padding:3px 6px}th{background:#f3f3f3;font-weight:600;font-size:12px}"
           "td.num{text-align:right;white-space:nowrap}td.fail{color:#c62828}</style>")
    return ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>robo3d batch</title>"
            f"{css}</head><body><h1>robo3d batch: {len(rows)} recording(s)</h1>"
            "<p>Pose errors: the worst sweep; at the object: the displacement of the "
            "sweep's own points, at the flange: of the robot's flange (about 0.3 m from "
            "the object). Mesh distances: the final mesh to the true surface, scored "
            "above the table. Empty cells: not measured (no ground truth, no laser frames, "
            "no views). Targets: see the overview.</p>"
            f"<table><tr>{head1}</tr><tr>{head2}</tr>{body}</table>"
            "<h2>Time and peak memory of every stage</h2><p>Wall time of the stage's job "
            "and its peak resident memory (Snakemake's benchmark files).</p>"
            f"<table><tr><th>recording</th>{t_head}</tr>{t_body}</table></body></html>\n")


def write_batch_report(metrics_paths: Sequence[str], picture_paths: Sequence[str],
                       tsv_path: str, html_path: str, overview_path: str,
                       vmax_mm: float | None = None,
                       failures: Sequence[Mapping[str, Any]] = ()) -> None:
    """Write ``batch.tsv`` (:func:`robo3d.evaluate.write_batch_table`), ``batch.html``
    (:func:`batch_html`) and ``overview.html`` (:func:`overview_html`, one picture per
    recording: ``picture_paths`` in the order of ``metrics_paths``), atomically;
    ``failures`` as :func:`overview_html` (the TSV holds the finished recordings' figures;
    ``results/batch.csv`` every recording's, failures too)."""
    from .atomic import atomic_path
    from .evaluate import batch_rows, write_batch_table

    if len(picture_paths) != len(metrics_paths):
        raise ValueError(f"one picture per recording: {len(metrics_paths)} metrics, "
                         f"{len(picture_paths)} pictures")
    metrics = [json.loads(Path(p).read_text(encoding="utf-8")) for p in metrics_paths]
    write_batch_table(list(metrics_paths), tsv_path, None)
    pictures = [Path(p).read_bytes() if Path(p).is_file() else None for p in picture_paths]
    for path, text in ((html_path, batch_html(batch_rows(metrics), failures)),
                       (overview_path, overview_html(metrics, pictures, vmax_mm, failures))):
        with atomic_path(path) as tmp:
            tmp.write_text(text, encoding="utf-8")


def write_unfinished_batch_report(recordings: Sequence[str], results_dir: str = "results",
                                  logs_dir: str = "logs", benchmarks_dir: str = "benchmarks",
                                  vmax_mm: float | None = None,
                                  jobs: Sequence[str] = ("evaluate", "pictures"),
                                  rows: Sequence[Mapping[str, Any]] | None = None
                                  ) -> list[str]:
    """The batch's pages (``batch.tsv``, ``batch.html``, ``overview.html`` in
    ``results_dir``) after a run that did not finish every recording: the finished ones
    (:func:`robo3d.info.finished_recordings` with ``jobs``) with their figures, the others
    with what failed (``rows``: :func:`robo3d.info.batch_summary`'s, computed when not
    given). Rule ``batch_table`` needs every recording, so the workflow's ``onerror``
    writes these instead. The files get a modification time of 1970: they stand in for the
    rule's outputs, and the next run that can run the rule re-makes them. Returns the
    finished recordings' names."""
    import os

    from .info import batch_summary, finished_recordings

    res = Path(results_dir)
    done = finished_recordings(recordings, results_dir, jobs)
    if rows is None:
        rows = batch_summary(results_dir, logs_dir, recordings, benchmarks_dir)
    failures = [r for r in rows if r["recording"] not in done]
    paths = [str(res / n) for n in ("batch.tsv", "batch.html", "overview.html")]
    write_batch_report([str(res / n / "metrics.json") for n in done],
                       [str(res / n / "pictures" / "thumbnail.png") for n in done],
                       *paths, vmax_mm=vmax_mm, failures=failures)
    for p in paths:
        os.utime(p, (0, 0))
    return done
