"""What a recording holds and whether the pipeline can use it (``robo3d info``), and what
a batch run made and where it failed (``robo3d status``).

:func:`inspect_recording` is what a user runs first on a new file: it reads the
recording as the pipeline would (images kept encoded; a few decoded) and returns a plain
dict: the files, every topic with its schema, count, rate and time span, the frames and
the transform tree (recorded names beside their roles), the calibrations, the pose
stream's rate, jitter and gaps, the clocks (each topic's stamps against the recorder's
log time: offset and drift), how images pair with poses (the worst time offset to the
nearest pose sample, images without a pose), the sweeps, and for every stage of the
workflow whether the file is fit for it, with the reasons. :func:`format_info` renders
the dict as text; the command line prints it and exits non-zero when a stage the data
calls for cannot run.

:func:`batch_status` looks at ``results/`` and ``logs/`` after a batch: per recording,
which stages finished, which failed (with the first error line of their log) and which
never ran; :func:`format_batch_status` renders it. :func:`batch_summary` is the batch's
table, one row per recording, failed ones included (status, failed stage, first error line
beside the figures), and :func:`write_batch_summary` writes it as CSV
(``results/batch.csv``, at the end of every run).

Choices
-------
- Stage fitness: a stage is ``ok``, ``unfit`` (its data is there but unusable, with the
  reasons) or ``not applicable`` (the recording has no data for it: no laser frames for
  the laser stages). ``fit`` is true when no stage is unfit and at least one can run.
  Checks: messages on the role's topic, a calibration for every image's ``frame_id``, a
  transform chain from ``base`` (and, for laser frames, to ``laser``), a pose at every
  image's time (``max_pose_gap``), the first, middle and last image of each role decode
  at their calibration's size, and two views at least for carving.
- A topic's rate is its average over its span of log times (what the recorder
  received, whatever the stamps say).
- Clock drift is the slope of (stamp - log time) against log time, least squares, in
  parts per million; it is reported for every stamped topic with three messages or more.
- A moving link's rate is the inverse of its median period and its jitter the standard
  deviation of the periods up to ``max_pose_gap``; wider periods are counted as gaps
  (harmless where no image falls in one: stop-and-go cells pause between views).
  Transport latency makes the offsets of different topics differ by milliseconds; a
  difference beyond ``max_pose_gap`` between an image topic and ``/tf`` is flagged as
  clocks that are not the same clock.
- A stage is marked done in :func:`batch_status` by the report it writes last
  (``reports/<stage>.json``, ``metrics.json`` for evaluation): Snakemake removes the
  outputs of a failed job, and every output is written atomically.
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .errors import Robo3dError
from .recording.model import FRAME_ROLES, Recording, TopicMap

__all__ = [
    "STAGES",
    "STAGE_MARKERS",
    "JOBS",
    "JOB_MARKERS",
    "finished_recordings",
    "inspect_recording",
    "inspect_with_config",
    "format_info",
    "batch_status",
    "calibration_status",
    "format_batch_status",
    "batch_summary",
    "write_batch_summary",
]

_log = logging.getLogger(__name__)

#: The workflow's stages in order (the rule names).
STAGES = ("silhouettes", "carve", "stripes", "triangulate", "align", "fuse", "simplify",
          "evaluate")
#: The file each stage writes last, relative to ``results/<rec>/``.
STAGE_MARKERS = {s: f"reports/{s}.json" for s in STAGES[:-1]} | {"evaluate": "metrics.json"}
#: Every per-recording job of the workflow: the stages, then the report's pictures and the
#: Foxglove file (``foxglove.enabled``), with the file each writes last.
JOBS = (*STAGES, "pictures", "foxglove")
JOB_MARKERS = STAGE_MARKERS | {"pictures": "pictures/thumbnail.png",
                               "foxglove": "results.mcap"}
_HULL, _LASER = ("silhouettes", "carve"), ("stripes", "triangulate", "align")


def finished_recordings(recordings: Iterable[str],
                        results_dir: str | os.PathLike[str] = "results",
                        jobs: Iterable[str] = ("evaluate", "pictures")) -> list[str]:
    """The recordings whose ``jobs`` all wrote their last file (:data:`JOB_MARKERS`;
    ``evaluate`` runs after every stage), sorted: what a report can show of a batch."""
    res = Path(results_dir)
    jobs = tuple(jobs)
    return [n for n in sorted(recordings)
            if all((res / n / JOB_MARKERS[j]).is_file() for j in jobs)]
_OK, _UNFIT, _NA = "ok", "unfit", "not applicable"
_DEFAULT_TOPICS = TopicMap()


# =========================================================================== inspect
def inspect_with_config(path: str | os.PathLike[str], cfg: Mapping[str, Any]) -> dict[str, Any]:
    """:func:`inspect_recording` with the topics, frames and timing of a config.

    Parameters
    ----------
    path : str or path-like
        An ``.mcap`` file or a rosbag2 directory.
    cfg : mapping
        A validated configuration (:func:`robo3d.config.load_config`); its ``topics``,
        ``frames`` and ``timing`` sections apply.

    Returns
    -------
    dict
        As :func:`inspect_recording`.
    """
    timing = cfg.get("timing", {})
    return inspect_recording(
        path, topics=TopicMap(**dict(cfg.get("topics") or {})),
        frames=dict(cfg.get("frames") or {}),
        max_pose_gap_ns=int(round(timing.get("max_pose_gap_s", 0.05) * 1e9)),
        sweep_gap_ns=int(round(timing.get("sweep_gap_s", 1.0) * 1e9)),
        sweep_gap_intervals=float(timing.get("sweep_gap_intervals", 3.0)),
        stamp_source=timing.get("stamp_source", "header"),
        image_offset_ns=int(round(timing.get("image_offset_s", 0.0) * 1e9)))


def inspect_recording(path: str | os.PathLike[str], *, topics: TopicMap = _DEFAULT_TOPICS,
                      frames: Mapping[str, str] | None = None,
                      max_pose_gap_ns: int = 50_000_000, sweep_gap_ns: int = 1_000_000_000,
                      stamp_source: str = "header", image_offset_ns: int = 0,
                      sweep_gap_intervals: float = 3.0) -> dict[str, Any]:
    """Everything a user needs to know about a recording before running the pipeline.

    Parameters
    ----------
    path : str or path-like
        An ``.mcap`` file or a rosbag2 directory.
    topics, frames, max_pose_gap_ns, stamp_source, image_offset_ns
        As :func:`robo3d.recording.read_recording` (the config's ``topics``, ``frames``,
        ``timing``).
    sweep_gap_ns, sweep_gap_intervals
        How laser frames split into sweeps, as the pipeline splits them
        (:func:`robo3d.triangulation.split_sweeps`, the config's ``timing``).

    Returns
    -------
    dict
        Keys ``path``, ``files``, ``fit`` (bool), ``problems`` (why not fit),
        ``warnings``, ``time``, ``topics``, ``metadata``, ``attachments``, ``frames``,
        ``calibrations``, ``pose_stream``, ``clock``, ``pairing``, ``sweeps``,
        ``joint_states``, ``stages`` (stage -> {"status", "reasons"}). Times in ns,
        durations in ms or s as the key says. Never raises on a bad recording.
    """
    from .recording.reader import bag_files, probe_recording, read_recording

    spath = os.fspath(path)
    out: dict[str, Any] = {"path": spath, "files": [], "fit": False, "problems": [],
                           "warnings": [], "time": None, "topics": [], "metadata": {},
                           "attachments": [], "frames": {}, "calibrations": [],
                           "pose_stream": [], "clock": [], "pairing": {}, "sweeps": None,
                           "joint_states": None, "stages": {}}
    frames = {**{r: r for r in FRAME_ROLES}, **dict(frames or {})}
    try:
        files, _ = bag_files(spath)
        out["files"] = [{"path": f, "bytes": os.path.getsize(f)} for f in files]
        rec = read_recording(spath, topics=topics, roles=("views", "laser"),
                             max_pose_gap_ns=max_pose_gap_ns, require=False, frames=frames,
                             stamp_source=stamp_source, image_offset_ns=image_offset_ns,
                             joint_states=True)
    except (Robo3dError, ValueError) as exc:
        out["problems"].append(str(exc))
        summary = probe_recording(spath, topics)
        out["topics"] = [{"topic": t, "schema": s, "encoding": e, "count": n,
                          "role": _role_of(t, topics)} for t, (s, e, n) in
                         sorted(summary.topics.items())]
        out["stages"] = {s: {"status": _UNFIT, "reasons": [str(exc)]} for s in STAGES}
        return out
    out["warnings"] = list(rec.warnings)
    out["metadata"] = rec.metadata
    out["attachments"] = sorted(rec.attachments)
    out["topics"], out["time"] = _topics(rec, topics)
    out["warnings"] += _bag_counts(spath, rec)
    out["frames"] = _frames(rec, frames)
    out["calibrations"] = _calibrations(rec)
    out["pose_stream"] = _pose_stream(rec, max_pose_gap_ns)
    out["clock"], clock_warnings = _clock(rec, topics, max_pose_gap_ns)
    out["warnings"] += clock_warnings
    out["pairing"] = {role: _pairing(rec, msgs, max_pose_gap_ns) for role, msgs in
                      (("views", rec.views), ("laser", rec.laser_frames)) if msgs}
    out["sweeps"] = _sweeps(rec, sweep_gap_ns, sweep_gap_intervals)
    out["workspace"] = _workspace(rec)
    if rec.joint_states is not None:
        js = rec.joint_states
        out["joint_states"] = {"topic": js.topic, "names": js.names,
                               "count": len(js.stamps_ns), "rate_hz": _rate(js.stamps_ns)}
    out["stages"] = _stages(rec, topics)
    statuses = [v["status"] for v in out["stages"].values()]
    out["fit"] = _UNFIT not in statuses and _OK in statuses
    for stage, v in out["stages"].items():
        if v["status"] == _UNFIT:
            out["problems"] += [f"{stage}: {r}" for r in v["reasons"]]
    if _OK not in statuses and _UNFIT not in statuses:
        out["problems"].append(f"no stage can run: no images on {topics.views} or "
                               f"{topics.laser}")
    if rec.info.get("kind") == "calibration" and "robo3d.target" not in rec.metadata:
        out["problems"].append("kind=calibration without a robo3d.target metadata record "
                               "(type, cols, rows, square): the calibrate rule needs it")
        out["fit"] = False
    return out


def _workspace(rec) -> dict[str, Any]:
    """The workspace box and where the pipeline gets it: the recording's metadata, or,
    without one, the views' hull standing on the table the laser saw
    (``alignment.workspace_from_hull``), or without views the object the laser measured
    (``alignment.workspace_from_laser``)."""
    if rec.workspace is not None:
        return {"box": [rec.workspace[0].tolist(), rec.workspace[1].tolist()],
                "source": "the recording's metadata"}
    if rec.views and rec.laser_frames:
        return {"box": None, "source": "none in the recording: the alignment takes the "
                "visual hull's box, standing on the table the laser saw "
                "(alignment.workspace_from_hull), or the laser's own box when the views "
                "that carved the hull disagree (alignment.hull_box_views_disagree_iou) or "
                "the hull's box holds little of the laser's object "
                "(alignment.hull_box_min_laser_share)"}
    if rec.laser_frames:
        return {"box": None, "source": "none, and no views to take one from: the alignment "
                "takes the box of the object the laser measured, standing on the table it "
                "measured beside it (alignment.workspace_from_laser)"}
    return {"box": None, "source": "none in the recording (the carve places its box from "
            "the silhouettes)"}


def _role_of(topic: str, topics: TopicMap) -> str | None:
    for role in ("tf", "tf_static", "calibration", "views", "laser", "joint_states"):
        if getattr(topics, role) == topic:
            return role
    return None


def _rate(times_ns: np.ndarray) -> float | None:
    t = np.sort(np.asarray(times_ns, dtype=np.int64))
    if len(t) < 2 or t[-1] == t[0]:
        return None
    return float((len(t) - 1) / ((t[-1] - t[0]) / 1e9))


def _topics(rec: Recording, topics: TopicMap) -> tuple[list[dict[str, Any]], dict | None]:
    rows, lo, hi = [], None, None
    for name, st in sorted(rec.topics.items()):
        lt = st.log_times_ns
        row: dict[str, Any] = {"topic": name, "schema": st.schema, "encoding": st.encoding,
                               "count": st.count, "role": _role_of(name, topics),
                               "rate_hz": _rate(lt)}
        if st.count:
            row["first_ns"], row["last_ns"] = int(lt.min()), int(lt.max())
            lo = row["first_ns"] if lo is None else min(lo, row["first_ns"])
            hi = row["last_ns"] if hi is None else max(hi, row["last_ns"])
        if st.stamps_ns is not None and st.count:
            row["stamps_first_ns"] = int(st.stamps_ns.min())
            row["stamps_last_ns"] = int(st.stamps_ns.max())
            d = np.diff(st.stamps_ns)
            row["stamps_out_of_order"] = int(np.sum(d < 0))
            row["stamps_duplicated"] = int(st.count - len(np.unique(st.stamps_ns)))
        rows.append(row)
    span = None if lo is None else {"first_ns": lo, "last_ns": hi,
                                    "duration_s": (hi - lo) / 1e9}
    return rows, span


def _bag_counts(path: str, rec: Recording) -> list[str]:
    """A rosbag2 directory's metadata.yaml counts against what was read intact."""
    meta = Path(path) / "metadata.yaml"
    if not meta.is_file():
        return []
    try:
        import yaml

        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        listed = {t["topic_metadata"]["name"]: int(t["message_count"])
                  for t in info.get("topics_with_message_count") or []}
    except Exception:  # reported by the reader already
        return []
    out = []
    for topic, n in sorted(listed.items()):
        got = rec.topics[topic].count if topic in rec.topics else 0
        if got < n:
            out.append(f"{topic}: metadata.yaml counts {n} messages, {got} are intact "
                       f"({n - got} lost)")
    return out


def _frames(rec: Recording, frames: Mapping[str, str]) -> dict[str, Any]:
    links = rec.tf.links()
    children: dict[str, list[tuple[str, bool, int]]] = {}
    for parent, child, static, n in links:
        children.setdefault(parent, []).append((child, static, n))
    all_frames = rec.tf.frames
    roots = sorted(f for f in all_frames if f not in {c for _, c, _, _ in links})
    recorded = {role: name for role, name in rec.frame_names.items()}
    rates = {}
    for parent, child, static, _ in links:
        if not static:
            stamps, _ = rec.tf.link_samples(parent, child)
            med = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.0
            rates[child] = 1e9 / med if med > 0 else None

    def label(f: str) -> str:
        return f"{f} ({recorded[f]})" if f in recorded else f

    lines: list[str] = []

    def walk(f: str, prefix: str, last: bool, top: bool) -> None:
        if top:
            lines.append(label(f))
        kids = sorted(children.get(f, []))
        for i, (c, static, n) in enumerate(kids):
            end = i == len(kids) - 1
            what = "static" if static else f"{n} samples" + (
                f", {rates[c]:.0f} Hz" if rates.get(c) else "")
            lines.append(f"{prefix}{'└─ ' if end else '├─ '}{label(c)}  [{what}]")
            walk(c, prefix + ("   " if end else "│  "), end, False)

    for r in roots:
        walk(r, "", True, True)
    missing = [role for role in FRAME_ROLES if role not in all_frames]
    return {"mapping": dict(frames), "renamed": recorded,
            "links": [{"parent": p, "child": c, "static": s, "samples": n}
                      for p, c, s, n in sorted(links)],
            "roots": roots, "tree_text": "\n".join(lines), "roles_missing": missing}


def _calibrations(rec: Recording) -> list[dict[str, Any]]:
    out = []
    images = rec.views + rec.laser_frames
    for fid, cam in sorted(rec.calibrations.items()):
        rect = rec.rectifiers.get(fid)  # a rational_polynomial or fisheye camera: rectified
        dist = "plumb_bob" if np.any(cam.D) else "none"
        if rect is not None:
            dist = (f"none: rectified from {rect.model} D = "
                    f"{np.round(rect.D_raw, 6).tolist()} (raw fx {rect.K_raw[0, 0]:.1f}), "
                    f"{100 * rect.kept_fraction:.1f} % of the raw image kept")
        out.append({"frame_id": fid, "width": cam.width, "height": cam.height,
                    "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                    "distortion": dist, "D": cam.D.tolist(),
                    "hfov_deg": float(np.degrees(2 * np.arctan(cam.width / (2 * cam.fx)))),
                    "vfov_deg": float(np.degrees(2 * np.arctan(cam.height / (2 * cam.fy)))),
                    "images": sum(1 for m in images if m.frame_id == fid)})
    return out


def _pose_stream(rec: Recording, max_gap_ns: int) -> list[dict[str, Any]]:
    rows = []
    for parent, child, static, n in sorted(rec.tf.links()):
        if static:
            continue
        stamps, _ = rec.tf.link_samples(parent, child)
        row: dict[str, Any] = {"link": f"{parent} -> {child}", "samples": int(n),
                               "rate_hz": None}
        if n >= 2:
            period = np.diff(stamps) / 1e6
            k = int(np.argmax(period))
            within = period[period <= max_gap_ns / 1e6]
            med = float(np.median(period))
            row.update({"rate_hz": 1e3 / med if med > 0 else None, "period_median_ms": med,
                        "jitter_ms": float(np.std(within)) if len(within) else None,
                        "period_p99_ms": float(np.percentile(period, 99)),
                        "max_gap_ms": float(period[k]), "max_gap_at_ns": int(stamps[k]),
                        "gaps_over_max_pose_gap": int(np.sum(period > max_gap_ns / 1e6))})
        rows.append(row)
    return rows


def _clock(rec: Recording, topics: TopicMap, max_gap_ns: int
           ) -> tuple[list[dict[str, Any]], list[str]]:
    rows, offsets = [], {}
    for name, st in sorted(rec.topics.items()):
        if st.stamps_ns is None or st.count < 3 or name == topics.tf_static:
            continue
        lt = st.log_times_ns.astype(np.float64)
        off = (st.stamps_ns - st.log_times_ns).astype(np.float64)
        x = (lt - lt[0]) / 1e9
        if np.ptp(x) > 0:
            slope, icpt = np.polyfit(x, off, 1)
            resid = off - (slope * x + icpt)
        else:
            slope, resid = 0.0, off - off.mean()
        med = float(np.median(off)) / 1e6
        offsets[name] = med
        rows.append({"topic": name, "offset_median_ms": med,
                     "offset_min_ms": float(off.min()) / 1e6,
                     "offset_max_ms": float(off.max()) / 1e6,
                     "drift_ppm": float(slope) / 1e3,  # ns per s -> ppm
                     "residual_ms": float(np.std(resid)) / 1e6})
    warnings = []
    ref = offsets.get(topics.tf)
    if ref is not None:
        for t in (topics.views, topics.laser):
            if t in offsets and abs(offsets[t] - ref) > max_gap_ns / 1e6:
                warnings.append(
                    f"{t}: stamps are {offsets[t] - ref:+.1f} ms off {topics.tf}'s relative to "
                    f"the recorder's clock (more than max_pose_gap): the camera's clock is not "
                    f"the robot's; set timing.stamp_source: log_time or timing.image_offset_s")
    for r in rows:
        span_s = None
        st = rec.topics[r["topic"]]
        if st.count > 1:
            span_s = (st.log_times_ns.max() - st.log_times_ns.min()) / 1e9
        if span_s and abs(r["drift_ppm"]) * span_s / 1e3 > max_gap_ns / 1e6 / 2:
            warnings.append(f"{r['topic']}: stamps drift {r['drift_ppm']:+.0f} ppm against the "
                            f"recorder's clock ({r['drift_ppm'] * span_s / 1e3:+.1f} ms over "
                            f"the recording)")
    return rows, warnings


def _chain_links(rec: Recording, parent: str, child: str) -> list[tuple[str, str]]:
    """The moving links between two frames (empty if they do not connect)."""
    up = {c: (p, s) for p, c, s, _ in rec.tf.links()}

    def to_root(f: str) -> list[str]:
        chain = [f]
        while chain[-1] in up and up[chain[-1]][0] not in chain:
            chain.append(up[chain[-1]][0])
        return chain

    a, b = to_root(child), to_root(parent)
    common = next((f for f in a if f in b), None)
    if common is None:
        return []
    frames_ = a[: a.index(common)] + b[: b.index(common)]
    return [(up[f][0], f) for f in frames_ if not up[f][1]]


def _pairing(rec: Recording, msgs: list, max_gap_ns: int) -> dict[str, Any]:
    stamps = np.array([m.timestamp_ns for m in msgs], dtype=np.int64)
    fids = np.array([m.frame_id for m in msgs])
    nearest = np.zeros(len(msgs))
    bracket = np.zeros(len(msgs))
    no_pose = np.zeros(len(msgs), dtype=bool)
    from .recording.reader import chain_problem as _chain_problem

    for fid in np.unique(fids):
        sel = fids == fid
        if _chain_problem(rec.tf, rec.base_frame, str(fid)):
            nearest[sel], bracket[sel], no_pose[sel] = np.inf, np.inf, True
            continue
        for parent, child in _chain_links(rec, rec.base_frame, str(fid)):
            s, _ = rec.tf.link_samples(parent, child)
            t = stamps[sel]
            i = np.clip(np.searchsorted(s, t), 1, max(len(s) - 1, 1))
            if len(s) == 1:
                d = np.abs(t - s[0]).astype(np.float64)
                gap = np.where(d == 0, 0.0, np.inf)
                bad = d > max_gap_ns
            else:
                d = np.minimum(np.abs(t - s[i - 1]), np.abs(s[i] - t)).astype(np.float64)
                outside = (t < s[0]) | (t > s[-1])
                gap = np.where(outside, np.inf, (s[i] - s[i - 1]).astype(np.float64))
                exact = (t == s[i - 1]) | (t == s[i])
                bad = outside | ((gap > max_gap_ns) & ~exact)
            nearest[sel] = np.maximum(nearest[sel], d)
            bracket[sel] = np.maximum(bracket[sel], gap)
            no_pose[sel] |= bad
    k = int(np.argmax(nearest))

    def ms(x: float) -> float | None:
        return float(x) / 1e6 if np.isfinite(x) else None

    out = {"images": len(msgs), "topic": msgs[0].topic,
           "worst_offset_ms": ms(nearest[k]), "worst_offset_at_ns": int(stamps[k]),
           "median_offset_ms": ms(np.median(nearest)),
           "widest_bracket_ms": (float(np.max(bracket)) / 1e6
                                 if np.isfinite(bracket).all() else None),
           "without_pose": int(no_pose.sum())}
    if no_pose.any():
        out["first_without_pose_ns"] = int(stamps[np.argmax(no_pose)])
    return out


def _sweeps(rec: Recording, sweep_gap_ns: int, intervals: float = 3.0
            ) -> dict[str, Any] | None:
    from .triangulation import split_sweeps

    if not rec.laser_frames:
        return None
    t = np.array([m.timestamp_ns for m in rec.laser_frames], dtype=np.int64)
    sizes = np.bincount(split_sweeps(t, sweep_gap_ns, intervals))
    return {"count": len(sizes), "frames": sizes.tolist()}


def _stages(rec: Recording, topics: TopicMap) -> dict[str, dict[str, Any]]:
    from .recording.reader import chain_problem as _chain_problem

    def check(msgs: list, role: str) -> tuple[str, list[str]]:
        topic = topics.views if role == "views" else topics.laser
        if not msgs:
            return _NA, [f"no images on {topic}"]
        reasons: list[str] = []
        fids = sorted({m.frame_id for m in msgs})
        for fid in fids:
            if fid not in rec.calibrations:
                known = ", ".join(sorted(rec.calibrations)) or "none"
                reasons.append(f"no calibration for frame_id {fid!r} (calibrated: {known}; "
                               f"topic {topics.calibration})")
            problem = _chain_problem(rec.tf, rec.base_frame, fid)
            if problem:
                reasons.append(f"no pose for frame_id {fid!r} in {rec.base_frame!r}: {problem}")
            elif role == "laser":
                lp = _chain_problem(rec.tf, fid, "laser")
                if lp:
                    reasons.append(f"no laser pose for frame_id {fid!r}: {lp} (frames.laser "
                                   f"names the laser emitter's frame)")
        if not reasons:
            try:
                rec.camera_poses(msgs)
                if role == "laser":
                    for fid in fids:
                        sel = [m.timestamp_ns for m in msgs if m.frame_id == fid]
                        rec.tf.lookup(fid, "laser", np.array(sel, dtype=np.int64))
            except Robo3dError as exc:
                reasons.append(str(exc))
        for i in sorted({0, len(msgs) // 2, len(msgs) - 1}):
            if msgs[i].frame_id not in rec.calibrations:
                break
            try:
                rec.decode(msgs[i])
            except Robo3dError as exc:
                reasons.append(str(exc))
        if role == "views" and len(msgs) < 2:
            reasons.append(f"carving needs 2 views at least, {topic} has {len(msgs)}")
        return (_UNFIT if reasons else _OK), reasons

    hull, hull_r = check(rec.views, "views")
    laser, laser_r = check(rec.laser_frames, "laser")
    out = {s: {"status": hull, "reasons": hull_r} for s in _HULL}
    out |= {s: {"status": laser, "reasons": laser_r} for s in _LASER}
    if _UNFIT in (hull, laser):  # the workflow fuses every half the recording has
        bad = [n for n, s in (("the hull", hull), ("the laser clouds", laser)) if s == _UNFIT]
        mesh = {"status": _UNFIT, "reasons": [f"needs {' and '.join(bad)}, which cannot be "
                                              f"made"]}
    elif _OK in (hull, laser):
        mesh = {"status": _OK, "reasons": []}
    else:
        mesh = {"status": _NA, "reasons": ["no images"]}
    out["fuse"] = dict(mesh)
    out["simplify"] = dict(mesh)
    ev = dict(mesh)
    if ev["status"] == _OK:
        has_truth = "ground_truth/mesh.ply" in rec.attachments
        ev["reasons"] = [] if has_truth else ["no ground truth: reports what the stages "
                                              "measured, no errors"]
    out["evaluate"] = ev
    return out


# =========================================================================== format
def _ms(x: float | None, digits: int = 1) -> str:
    return "-" if x is None else f"{x:.{digits}f}"


def _titled(lines: list[str], title: str, rows: list[str]) -> None:
    """Append a titled block to ``lines``: a blank line, ``title``, the rows indented by
    two spaces; nothing when there are no rows."""
    if rows:
        lines += ["", title] + [f"  {r}" for r in rows]


def format_info(info: Mapping[str, Any]) -> str:
    """The dict of :func:`inspect_recording` as text for a terminal."""
    L: list[str] = []
    add = L.append
    add(f"recording  {info['path']}")
    for f in info["files"]:
        add(f"  file     {f['path']}  ({f['bytes'] / 1e6:.2f} MB)")
    t = info.get("time")
    if t:
        add(f"  time     {t['first_ns'] / 1e9:.3f} .. {t['last_ns'] / 1e9:.3f} s "
            f"({t['duration_s']:.2f} s)")
    md = info.get("metadata", {}).get("robo3d.recording")
    if md:
        add("  metadata " + ", ".join(f"{k}={v}" for k, v in md.items()))
    if info.get("attachments"):
        add("  attached " + ", ".join(info["attachments"]))
    ws = info.get("workspace")
    if ws:
        box = ws.get("box")
        add("  workspace " + (f"{[round(x, 4) for x in box[0]]} .. "
                              f"{[round(x, 4) for x in box[1]]} m, from " if box else "")
            + ws["source"])
    if info["topics"]:
        add("")
        add("topics")
        w = max(len(r["topic"]) for r in info["topics"])
        for r in info["topics"]:
            rate = f"{r['rate_hz']:.1f} Hz" if r.get("rate_hz") else ""
            role = f"[{r['role']}]" if r.get("role") else ""
            extra = []
            if r.get("stamps_out_of_order"):
                extra.append(f"{r['stamps_out_of_order']} stamps out of order")
            if r.get("stamps_duplicated"):
                extra.append(f"{r['stamps_duplicated']} duplicated stamps")
            add(f"  {r['topic']:<{w}}  {r['count']:>7}  {rate:>10}  {r['schema']} "
                f"({r['encoding']}) {role} {'; '.join(extra)}".rstrip())
    fr = info.get("frames")
    if fr and fr.get("tree_text"):
        add("")
        add("transform tree" + (" (recorded names in brackets)" if fr["renamed"] else ""))
        add("\n".join("  " + line for line in fr["tree_text"].splitlines()))
        if fr["roles_missing"]:
            add(f"  roles not in the tree: {', '.join(fr['roles_missing'])} (config frames: "
                + ", ".join(f"{k}={v}" for k, v in fr["mapping"].items()) + ")")
    _titled(L, "calibration", [
        f"{c['frame_id']}: {c['width']}x{c['height']}, fx {c['fx']:.1f} fy {c['fy']:.1f} "
        f"cx {c['cx']:.1f} cy {c['cy']:.1f}, {c['distortion']}, fov {c['hfov_deg']:.1f}x"
        f"{c['vfov_deg']:.1f} deg, {c['images']} images"
        for c in info.get("calibrations") or []])
    _titled(L, "pose stream", [
        f"{p['link']}: {p['samples']} samples, {_ms(p.get('rate_hz'))} Hz, period "
        f"{_ms(p.get('period_median_ms'), 2)} ms (jitter {_ms(p.get('jitter_ms'), 2)} ms), "
        f"widest gap {_ms(p.get('max_gap_ms'))} ms, {p.get('gaps_over_max_pose_gap', 0)} "
        "gaps over max_pose_gap (where no image falls, harmless)"
        for p in info.get("pose_stream") or []])
    _titled(L, "clocks (stamp - log time)", [
        f"{c['topic']}: {c['offset_median_ms']:+.2f} ms (range {c['offset_min_ms']:+.2f} .. "
        f"{c['offset_max_ms']:+.2f}), drift {c['drift_ppm']:+.1f} ppm"
        for c in info.get("clock") or []])
    _titled(L, "images and poses", [
        f"{role} ({p['topic']}): {p['images']} images, nearest pose sample at most "
        f"{_ms(p['worst_offset_ms'], 2)} ms away (t={p['worst_offset_at_ns']}), median "
        f"{_ms(p['median_offset_ms'], 2)} ms; {p['without_pose']} without a pose"
        for role, p in (info.get("pairing") or {}).items()])
    if info.get("sweeps"):
        s = info["sweeps"]
        add(f"  laser sweeps: {s['count']} ({', '.join(map(str, s['frames']))} frames)")
    js = info.get("joint_states")
    if js:
        add(f"  joint states ({js['topic']}): {js['count']} messages, "
            f"{_ms(js['rate_hz'])} Hz, joints {', '.join(js['names'])}")
    _titled(L, "warnings", [f"- {w}" for w in info.get("warnings") or []])
    add("")
    add("stages")
    groups: dict[tuple[str, tuple[str, ...]], list[str]] = {}
    for stage, v in info["stages"].items():  # stages sharing a verdict on one line
        groups.setdefault((v["status"], tuple(v["reasons"])), []).append(stage)
    for (status, reasons), stages in groups.items():
        add(f"  {', '.join(stages)}: {status}")
        for r in reasons:
            add(f"      {r}")
    add("")
    if (info.get("metadata") or {}).get("robo3d.recording", {}).get("kind") == "calibration":
        t = info["metadata"].get("robo3d.target", {})
        try:
            square = f"{float(t.get('square', 'nan')) * 1e3:g} mm"
        except ValueError:
            square = repr(t.get("square"))
        board = (f"a {t.get('cols')} x {t.get('rows')} checkerboard of {square} squares"
                 f"{', moved by hand' if str(t.get('moving')).lower() == 'true' else ''}"
                 if t else "no robo3d.target record")
        add(f"kind=calibration ({board}): the calibrate rule makes "
            "results/calibration/<name>.yaml from it; it is not scanned")
    if info["fit"]:
        add("fit for the pipeline")
    else:
        add("NOT fit for the pipeline (see the stages above)")
    return "\n".join(L)


# =========================================================================== batch status
def _first_error(log: Path) -> str | None:
    """The first error line of a job's log (robo3d's one-line error, or a traceback's
    last line)."""
    try:
        lines = log.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return None
    for line in lines:
        if " ERROR " in line or line.startswith("ERROR"):
            return line.split(" ERROR ", 1)[-1].strip()
    for i, line in enumerate(lines):
        if line.startswith("Traceback"):
            tail = [x for x in lines[i:] if x and not x.startswith(" ")]
            return tail[-1].strip() if tail else line
    return None


def batch_status(results_dir: str | os.PathLike[str] = "results",
                 logs_dir: str | os.PathLike[str] = "logs",
                 recordings: Iterable[str] | None = None) -> dict[str, Any]:
    """What a batch run made, per recording and stage, and why jobs failed.

    Parameters
    ----------
    results_dir, logs_dir : path-like
        The workflow's ``results/`` and ``logs/`` folders.
    recordings : iterable of str, optional
        The batch's recording names (default: every name found in either folder).

    Returns
    -------
    dict
        ``{"recordings": {name: {"status": "done" | "failed" | "incomplete" |
        "not started", "stages": {stage: {"status": "done" | "failed" | "incomplete" |
        "not run", "error": str | None, "log": str | None}}, "outputs": [file names]}},
        "failed": [names], "done": [names]}``, ``stages`` keyed by every job of
        :data:`JOBS` (the stages, ``pictures`` and ``foxglove``). A job is ``incomplete``
        when its log exists without an error and its last file (:data:`JOB_MARKERS`) does
        not (killed, or still running).
    """
    results, logs = Path(results_dir), Path(logs_dir)
    names = set(recordings) if recordings is not None else set()
    if recordings is None:
        if results.is_dir():  # results/calibration/ holds the calibrations, not a scan
            names |= {d.name for d in results.iterdir() if d.is_dir() and d.name != "calibration"}
        if logs.is_dir():
            names |= {f.stem for s in JOBS if (logs / s).is_dir()
                      for f in (logs / s).glob("*.log")}
    out: dict[str, Any] = {"recordings": {}, "failed": [], "done": []}
    for name in sorted(names):
        stages: dict[str, dict[str, Any]] = {}
        for stage in JOBS:
            log = logs / stage / f"{name}.log"
            done = (results / name / JOB_MARKERS[stage]).is_file()
            err = None
            if done:
                status = "done"
            elif log.is_file():
                err = _first_error(log)
                status = "failed" if err else "incomplete"
            else:
                status = "not run"
            stages[stage] = {"status": status, "error": err,
                             "log": str(log) if log.is_file() else None}
        st = [v["status"] for v in stages.values()]
        if "failed" in st:
            rec_status = "failed"
        elif stages["evaluate"]["status"] == "done":
            rec_status = "done"
        elif all(s == "not run" for s in st):
            rec_status = "not started"
        else:
            rec_status = "incomplete"
        outputs = sorted(p.name for p in (results / name).iterdir()
                         if p.is_file() and not p.name.startswith(".")) \
            if (results / name).is_dir() else []
        out["recordings"][name] = {"status": rec_status, "stages": stages, "outputs": outputs}
        if rec_status == "failed":
            out["failed"].append(name)
        elif rec_status == "done":
            out["done"].append(name)
    out["calibrations"] = calibration_status(results, logs)
    return out


def _stage_benchmark(benchmarks: Path, stage: str, name: str) -> tuple[float | None,
                                                                       float | None]:
    """A job's wall time (s) and peak resident memory (MB) from its Snakemake
    ``benchmark:`` file, or Nones."""
    try:
        head, row = (benchmarks / stage / f"{name}.tsv").read_text().splitlines()[:2]
        rec = dict(zip(head.split("\t"), row.split("\t"), strict=False))
        return float(rec["s"]), float(rec["max_rss"])
    except (OSError, ValueError, KeyError):
        return None, None


def batch_summary(results_dir: str | os.PathLike[str] = "results",
                  logs_dir: str | os.PathLike[str] = "logs",
                  recordings: Iterable[str] | None = None,
                  benchmarks_dir: str | os.PathLike[str] = "benchmarks",
                  ) -> list[dict[str, Any]]:
    """The batch's table: one row per recording, whether it finished or failed.

    Parameters
    ----------
    results_dir, logs_dir, recordings
        As :func:`batch_status`.
    benchmarks_dir : path-like
        The workflow's ``benchmarks/`` folder (the jobs' ``benchmark:`` files).

    Returns
    -------
    list of dict
        ``recording``, ``status`` (as :func:`batch_status`), ``failed_stage``, ``error``
        (its first error line) and ``log`` (None when nothing failed), then the figures of
        :func:`robo3d.evaluate.batch_rows` when the recording has its ``metrics.json``;
        without one (failed, not finished), ``<stage>_s`` and ``<stage>_mb`` of the stages
        that ran, from their benchmark files.
    """
    from .evaluate import batch_rows

    results, benchmarks = Path(results_dir), Path(benchmarks_dir)
    rows = []
    for name, r in batch_status(results_dir, logs_dir, recordings)["recordings"].items():
        failed = next(((s, v) for s, v in r["stages"].items() if v["status"] == "failed"),
                      None)
        row: dict[str, Any] = {"recording": name, "status": r["status"],
                               "failed_stage": failed[0] if failed else None,
                               "error": failed[1]["error"] if failed else None,
                               "log": failed[1]["log"] if failed else None}
        try:
            metrics = json.loads((results / name / "metrics.json").read_text())
        except (OSError, ValueError):
            metrics = None
        if metrics is not None:
            row.update({k: v for k, v in batch_rows([metrics])[0].items() if k != "recording"})
        else:
            for stage in JOBS:
                row[f"{stage}_s"], row[f"{stage}_mb"] = _stage_benchmark(benchmarks, stage, name)
        rows.append(row)
    return rows


def write_batch_summary(rows: Iterable[Mapping[str, Any]],
                        csv_path: str | os.PathLike[str]) -> None:
    """:func:`batch_summary`'s rows as CSV (the union of their columns in order of
    appearance; empty cells: not measured), written atomically."""
    import csv
    import io

    from .atomic import atomic_path

    rows = list(rows)
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None else f"{v:.6g}" if isinstance(v, float) else v)
                    for k, v in r.items()})
    with atomic_path(csv_path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")


def calibration_status(results_dir: str | os.PathLike[str] = "results",
                       logs_dir: str | os.PathLike[str] = "logs") -> dict[str, Any]:
    """The calibrate rule's jobs (``results/calibration/<calib>.yaml``,
    ``logs/calibrate/<calib>.log``): ``{name: {"status": "done" | "failed" | "incomplete",
    "error": first error line (the failed quality gates) or None, "log", "file"}}``."""
    results, logs = Path(results_dir) / "calibration", Path(logs_dir) / "calibrate"
    names = {p.stem for p in results.glob("*.yaml")} if results.is_dir() else set()
    names |= {p.stem for p in logs.glob("*.log")} if logs.is_dir() else set()
    out: dict[str, Any] = {}
    for name in sorted(names):
        log, yaml = logs / f"{name}.log", results / f"{name}.yaml"
        err = None if yaml.is_file() or not log.is_file() else _first_error(log)
        status = "done" if yaml.is_file() else "failed" if err else "incomplete"
        out[name] = {"status": status, "error": err,
                     "log": str(log) if log.is_file() else None,
                     "file": str(yaml) if yaml.is_file() else None}
    return out


def format_batch_status(status: Mapping[str, Any]) -> str:
    """The dict of :func:`batch_status` as text."""
    L = []
    recs = status["recordings"]
    L.append(f"{len(recs)} recordings: {len(status['done'])} done, {len(status['failed'])} "
             f"failed, {len(recs) - len(status['done']) - len(status['failed'])} other")
    for name, r in recs.items():
        L.append(f"{name}: {r['status']}")
        for stage, s in r["stages"].items():
            if s["status"] == "failed":
                L.append(f"  {stage} failed: {s['error']}  (log: {s['log']})")
            elif s["status"] == "incomplete":
                L.append(f"  {stage} incomplete: its log has no error and its outputs are "
                         f"missing (killed, or still running; rerun to finish)  "
                         f"(log: {s['log']})")
        if r["status"] != "done":
            done = [s for s, v in r["stages"].items() if v["status"] == "done"]
            L.append(f"  done: {', '.join(done) or 'nothing'}; outputs: "
                     f"{', '.join(r['outputs']) or 'none'}")
    for name, c in (status.get("calibrations") or {}).items():
        L.append(f"calibration {name}: {c['status']}"
                 + (f": {c['error']}  (log: {c['log']})" if c["error"] else
                    f" ({c['file']})" if c["file"] else ""))
    return "\n".join(L)


def format_run_summary(results_dir: str | os.PathLike[str] = "results",
                       logs_dir: str | os.PathLike[str] = "logs",
                       recordings: Iterable[str] | None = None) -> str:
    """The end of a run, for the terminal: one row per recording (status, faces, the
    measured share of the mesh, and against ground truth the mesh's median and p95 error
    and the measured surface's), where its results are, and the command to inspect them.
    Reads each recording's ``metrics.json``; a recording without one shows its status."""
    results = Path(results_dir)
    status = batch_status(results_dir, logs_dir, recordings)
    rows = [("recording", "status", "faces", "measured", "mesh median / p95",
             "measured median / p95", "time")]
    for name, r in status["recordings"].items():
        m: dict[str, Any] = {}
        try:
            m = json.loads((results / name / "metrics.json").read_text())
        except (OSError, ValueError):
            pass
        ev = m.get("evaluation") or {}
        src = m.get("surface_sources") or {}
        faces = ((m.get("stages") or {}).get("simplify") or {}).get("faces_out")
        inf = src.get("inferred_area_fraction")

        def pair(d: Mapping[str, Any] | None) -> str:
            d = d or {}
            if d.get("median_mm") is None:
                return "-"
            return f"{d['median_mm']:.3f} / {d['p95_mm']:.3f} mm"

        total = (m.get("timings") or {}).get("total_seconds")
        rows.append((name, r["status"], "-" if faces is None else str(faces),
                     "-" if inf is None else f"{100 * (1 - inf):.1f} %",
                     pair(ev.get("mesh")), pair(ev.get("measured")),
                     "-" if total is None else f"{total:.0f} s"))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip()
             for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    done = status["done"]
    lines.append("")
    lines.append(f"{len(done)} of {len(status['recordings'])} recordings done; results in "
                 f"{results}/<recording>/ (mesh.ply, measured.ply, metrics.json), the batch "
                 f"table in {results}/batch.tsv")
    if done:
        # robo3d view: the designed layout, on localhost, with rerun's analytics off
        where = "" if str(results) == "results" else f" --results {results}"
        lines.append(f"inspect: .venv/bin/robo3d view {done[0]}{where}  (--web without a "
                     "display)")
    if status["failed"]:
        lines.append(f"failed: {', '.join(status['failed'])} (robo3d status says why)")
    for name, c in (status.get("calibrations") or {}).items():
        lines.append(f"calibration {name}: {c['status']}"
                     + (f" ({c['file']})" if c["file"] else " (robo3d status says why)"))
    return "\n".join(lines)
