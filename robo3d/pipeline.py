"""The pipeline's stages as plain functions: read inputs, call the algorithms, write outputs.

Each ``stage_<name>`` takes its input and output paths (dicts keyed as in the Snakemake
rules), the validated configuration and the recording's name; it writes every output
atomically, logs what it made to rerun and writes a JSON report of what it measured. The
workflow's scripts are one call to :func:`run_from_snakemake`; the command line and the
tests call the stages directly.

Intermediate files (``results/<rec>/``): ``silhouettes.npz`` (masks, cameras, poses),
``hull.npz`` (occupancy grid), ``stripes.npz`` (stripe pixels per laser frame with camera,
pose and laser transform), ``clouds.npz`` (one cloud per sweep), ``aligned.npz`` (the same
after ICP), and ``reports/<stage>.json``.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import dir_mode, save_npz, write_json
from .camera import CameraModel
from .errors import Robo3dError, StageError

__all__ = [
    "RecordingEntry",
    "find_recordings",
    "export_library_path",
    "recording_stages",
    "topic_map",
    "stage_silhouettes",
    "stage_carve",
    "stage_stripes",
    "stage_triangulate",
    "stage_align",
    "stage_fuse",
    "stage_simplify",
    "stage_evaluate",
    "STAGES",
    "run_from_snakemake",
]

log = logging.getLogger("robo3d.pipeline")
#: The one-line summaries of the stages (and their progress): what the terminal shows.
summary = logging.getLogger("robo3d.summary")


# ---------------------------------------------------------------------------- batch
@dataclass
class RecordingEntry:
    """One recording of a batch: its name (results/<name>/), its file and what it holds."""

    name: str
    path: str
    summary: Any = None  # robo3d.recording.reader.RecordingSummary, probed lazily
    _topics: dict[str, str] = field(default_factory=dict)


def topic_map(topics: Mapping[str, str] | None):
    """The :class:`~robo3d.recording.TopicMap` of a config's ``topics`` section."""
    from .recording import TopicMap

    return TopicMap(**dict(topics or {}))


def find_recordings(spec: str | list[str], topics: Mapping[str, str] | None = None
                    ) -> dict[str, RecordingEntry]:
    """The recordings of a batch: every ``*.mcap`` in a folder, or a list of files.

    A rosbag2 directory (``metadata.yaml`` beside an ``.mcap``) counts as one recording
    named after the directory, and so does a sub-folder holding ``<folder>_0.mcap`` without
    ``metadata.yaml`` (a bag whose recorder died before writing it: the reader reads what
    is there and says what is missing). Names must be unique (they name
    ``results/<name>/``).
    """
    from .errors import ConfigError

    paths: list[Path] = []
    items = [spec] if isinstance(spec, str) else list(spec)
    for item in items:
        p = Path(item)
        if p.is_dir():
            if _is_bag_dir(p):
                paths.append(p)
            else:
                paths += sorted(p.glob("*.mcap"))
                paths += sorted(d for d in p.iterdir() if d.is_dir() and _is_bag_dir(d))
        elif p.exists():
            paths.append(p)
        else:
            raise ConfigError(f"config key recordings: {item} does not exist")
    if not paths:
        raise ConfigError(f"config key recordings: no recording in {', '.join(map(str, items))}"
                          f" ({_what_is_there(items)}); robo3d reads MCAP files (*.mcap) "
                          "and rosbag2 folders holding them")
    out: dict[str, RecordingEntry] = {}
    for p in paths:
        name = p.stem if p.is_file() else p.name
        if name in out:
            raise ConfigError(f"config key recordings: two recordings named {name!r} "
                              f"({out[name].path} and {p}); results/<name>/ must be unique")
        out[name] = RecordingEntry(name, str(p), None, dict(topics or {}))
    return out


def _what_is_there(items: list[str]) -> str:
    """What the folders of a recordings list hold instead of recordings, in words."""
    from collections import Counter

    files = [f for it in items if Path(it).is_dir() for f in Path(it).rglob("*")
             if f.is_file()][:10000]
    if not files:
        return "it is empty" if len(items) == 1 else "they are empty"
    kinds = Counter(f.suffix.lower() or "(no suffix)" for f in files)
    found = ", ".join(f"{n} {k}" for k, n in kinds.most_common(5))
    hint = ""
    if ".db3" in kinds:
        hint = ("; .db3 files are ROS 2 bags in SQLite: convert them to MCAP with "
                "`ros2 bag convert` (storage_id mcap)")
    elif ".bag" in kinds:
        hint = "; .bag files are ROS 1 bags: convert them with `mcap convert`"
    return f"found {found}{hint}"


def _is_bag_dir(d: Path) -> bool:
    """A rosbag2 directory: its ``metadata.yaml``, or (recorder died) ``<dir>_0.mcap``."""
    return (d / "metadata.yaml").exists() or (d / f"{d.name}_0.mcap").exists()


def recording_stages(entry: RecordingEntry) -> set[str]:
    """Which halves of the pipeline a recording supports: ``hull`` (silhouette views) and
    ``laser`` (laser frames). An unreadable file gets both, so that its jobs run and fail
    with the reader's message while the rest of the batch goes on."""
    if entry.summary is None:
        from .recording.reader import probe_recording

        entry.summary = probe_recording(entry.path, topic_map(entry._topics))
    s = entry.summary
    if not getattr(s, "readable", True):
        return {"hull", "laser"}
    out = set()
    if s.n_views > 0:
        out.add("hull")
    if s.n_laser_frames > 0:
        out.add("laser")
    return out


def export_library_path(repo_root: str) -> None:
    """Put the checkout on ``PYTHONPATH`` so that every job imports this robo3d, also in
    ``--use-conda`` environments that install only the dependencies."""
    import os

    parts = [str(repo_root)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                if p and p != str(repo_root)]
    os.environ["PYTHONPATH"] = os.pathsep.join(parts)


# ---------------------------------------------------------------------------- helpers
def _read(path: str, cfg: Mapping[str, Any], roles: tuple[str, ...], require: bool = True):
    from .recording.reader import read_recording

    rec = read_recording(path, roles=roles, require=require, **_reader_options(cfg))
    return rec  # the reader has logged its warnings (rec.warnings keeps them)


def _reader_options(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The reader's keyword arguments from a config's topics, frames and timing sections:
    recorded frame names are renamed to their roles, so poses are looked up in ``base``."""
    timing = cfg.get("timing", {})
    return {"topics": topic_map(cfg.get("topics")),
            "frames": dict(cfg.get("frames") or {}),
            "base_frame": "base",
            "max_pose_gap_ns": int(round(timing.get("max_pose_gap_s", 0.05) * 1e9)),
            "stamp_source": timing.get("stamp_source", "header"),
            "image_offset_ns": int(round(timing.get("image_offset_s", 0.0) * 1e9))}


def _camera_arrays(cameras: list[CameraModel]) -> dict[str, np.ndarray]:
    return {
        "K": np.stack([c.K for c in cameras]) if cameras else np.zeros((0, 3, 3)),
        "D": np.stack([c.D[:5] for c in cameras]) if cameras else np.zeros((0, 5)),
        "image_size": np.array([[c.width, c.height] for c in cameras], dtype=np.int64
                               ).reshape(-1, 2),
        "frame_ids": np.array([c.frame_id for c in cameras], dtype=str),
    }


def _cameras_from(npz: Mapping[str, np.ndarray]) -> list[CameraModel]:
    return [CameraModel(str(f), int(s[0]), int(s[1]), k, d) for f, s, k, d in
            zip(npz["frame_ids"], npz["image_size"], npz["K"], npz["D"], strict=True)]


def _workspace_arrays(rec) -> dict[str, np.ndarray]:
    ws = rec.workspace
    if ws is None:
        return {}
    return {"workspace_min": ws[0], "workspace_max": ws[1]}


def _workspace_from(npz: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
    if "workspace_min" in npz:
        return np.asarray(npz["workspace_min"]), np.asarray(npz["workspace_max"])
    return None


def _media_type(encoding: str) -> str | None:
    return {"png": "image/png", "jpeg": "image/jpeg"}.get(encoding)


def _log_image_camera(stream, entity, msg, camera, T, **kw) -> None:
    from .viz import log_camera

    mt = _media_type(msg.encoding)
    if mt is not None:
        log_camera(stream, entity, camera, T, encoded=(msg.data, mt), **kw)
    else:
        log_camera(stream, entity, camera, T, image=msg.decode(), **kw)


class _Progress:
    """Logs progress of a loop over frames every few seconds (users watch long work)."""

    def __init__(self, what: str, total: int, every_s: float = 10.0) -> None:
        self.what, self.total, self.every = what, total, every_s
        self.t0 = self.last = time.perf_counter()

    def __call__(self, done: int) -> None:
        now = time.perf_counter()
        if now - self.last >= self.every or done == self.total:
            self.last = now
            dt = max(now - self.t0, 1e-9)
            rate = done / dt
            eta = (self.total - done) / rate if rate > 0 else float("nan")
            speed = f"{rate:.0f}/s" if rate >= 10 else f"{rate:.2g}/s" if rate >= 0.1 else \
                f"{dt / max(done, 1):.0f} s each"
            left = f", about {eta:.0f} s left" if done < self.total and eta == eta else ""
            summary.info("%s: %d/%d (%s%s)", self.what, done, self.total, speed, left)


# ---------------------------------------------------------------------------- stages
def stage_silhouettes(inputs: Mapping[str, str], outputs: Mapping[str, str],
                      cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Segment every silhouette view (seed §3.2) and keep its camera and pose.

    Outputs: ``npz`` (masks, cameras, poses, ``qa_flagged`` per view), ``report`` (per
    view: threshold, area, components, whether the silhouette touches the ROI's or the
    image's border, the ROI, whether an empty-scene image was subtracted, where the
    background was sampled, whether GrabCut refined it, and ``qa``: ``flags`` of an absurd
    mask, see :func:`robo3d.silhouettes.silhouette_qa`; ``qa_flagged_views`` lists the
    flagged views), ``rrd`` (images with their masks at their cameras) and, when given,
    ``masks``: a folder of one PNG per view (``view_000.png``, 255 = silhouette).
    A view whose segmentation fails (empty, uniform, or covering its whole region) is
    an error naming it; a mask that is merely absurd is flagged, not dropped.
    """
    from .silhouettes import segment_view
    from .viz import log_box, log_report, rerun_log, spaced_indices

    t0 = time.perf_counter()
    rec = _read(inputs["recording"], cfg, roles=("views",))
    views = sorted(rec.views, key=lambda m: m.timestamp_ns)
    cameras = [rec.camera_for(m) for m in views]
    poses = rec.camera_poses(views)
    seg = cfg["segmentation"]
    ws = rec.workspace
    backgrounds = _background_images(inputs["recording"], cfg, views, cameras, poses)
    masks, per_view = [], []
    progress = _Progress("segmenting views", len(views))
    for i, (msg, cam, T) in enumerate(zip(views, cameras, poses, strict=True)):
        image = rec.decode(msg)
        background = backgrounds[i]
        try:
            sil, roi_source = segment_view(image, cam, T, seg, ws, background)
        except StageError as exc:
            raise StageError(f"{inputs['recording']}: topic {msg.topic}, view {i} "
                             f"(t={msg.timestamp_ns} ns): {exc}") from None
        if sil.touches_image_border:
            log.warning("view %d (topic %s, t=%d ns): the silhouette touches the image border, "
                        "the object is cut off in this view; with carving.outside_image=carve "
                        "this view carves the object's hidden part away", i, msg.topic,
                        msg.timestamp_ns)
        elif sil.touches_border:
            log.warning("view %d (topic %s, t=%d ns): the silhouette touches the border of its "
                        "region of interest (%s): the object may reach beyond it and be cut "
                        "off", i, msg.topic, msg.timestamp_ns, roi_source)
        if sil.qa["flags"]:
            log.warning("view %d (topic %s, t=%d ns): absurd silhouette, QA flags %s (fill "
                        "%.2f of its region, sides touched %s); flagged in the report and in "
                        "silhouettes.npz (qa_flagged)", i, msg.topic, msg.timestamp_ns,
                        ", ".join(sil.qa["flags"]), sil.qa["fill_fraction"],
                        ", ".join(sil.qa["sides_touched"]) or "none")
        masks.append(sil.mask)
        per_view.append({"index": i, "timestamp_ns": msg.timestamp_ns,
                         "threshold": float(sil.threshold), "polarity": sil.polarity,
                         "area_px": int(sil.area_px), "n_components": int(sil.n_components),
                         "touches_border": bool(sil.touches_border),
                         "touches_image_border": bool(sil.touches_image_border),
                         "roi": [int(r) for r in sil.roi], "roi_source": roi_source,
                         "centroid_uv": [float(c) for c in sil.centroid_uv],
                         "background_subtracted": background is not None,
                         "background_sample": sil.background_sample,
                         "refined": sil.refined, "qa": sil.qa,
                         "mask_png": f"view_{i:03d}.png"})
        progress(i + 1)
    sizes = {m.shape for m in masks}
    report = {"n_views": len(views), "views": per_view,
              "n_touching_border": sum(v["touches_border"] for v in per_view),
              "n_touching_image_border": sum(v["touches_image_border"] for v in per_view),
              "views_touching_image_border": [v["index"] for v in per_view
                                              if v["touches_image_border"]],
              "n_background_subtracted": sum(v["background_subtracted"] for v in per_view),
              "qa_flagged_views": [v["index"] for v in per_view if v["qa"]["flags"]],
              "n_qa_flagged": sum(bool(v["qa"]["flags"]) for v in per_view),
              "workspace_box": None if ws is None else [ws[0].tolist(), ws[1].tolist()],
              "seconds": round(time.perf_counter() - t0, 3)}
    if len(sizes) == 1:
        mask_stack = np.stack(masks)
    else:  # cameras of different sizes: pad to the largest, sizes kept per view
        h = max(s[0] for s in sizes)
        w = max(s[1] for s in sizes)
        mask_stack = np.zeros((len(masks), h, w), dtype=bool)
        for i, m in enumerate(masks):
            mask_stack[i, : m.shape[0], : m.shape[1]] = m
    save_npz(outputs["npz"], masks=np.packbits(mask_stack, axis=-1),
             mask_shape=np.array(mask_stack.shape), T_base_camera=poses,
             stamps_ns=np.array([m.timestamp_ns for m in views], dtype=np.int64),
             qa_flagged=np.array([bool(v["qa"]["flags"]) for v in per_view], dtype=bool),
             **_camera_arrays(cameras), **_workspace_arrays(rec))
    if outputs.get("masks"):
        _write_mask_pngs(outputs["masks"], masks)
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        if ws is not None:
            log_box(rr_stream, "base/workspace", ws[0], ws[1], label="workspace")
        for i in spaced_indices(len(views), cfg["rerun"]["max_images"]):
            _log_image_camera(rr_stream, f"base/views/view_{i:03d}", views[i], cameras[i],
                              poses[i], mask=masks[i])
        log_report(rr_stream, "reports/silhouettes", report)
    write_json(outputs["report"], report)
    summary.info("segmented %d views in %.1f s; %d touch the image border, %d their region's",
             len(views), report["seconds"], report["n_touching_image_border"],
             report["n_touching_border"])
    return report


def _write_mask_pngs(directory: str, masks: list[np.ndarray]) -> None:
    """One 8-bit PNG per view (255 = silhouette) into ``directory``, atomically: written
    into a temporary folder beside it, which then replaces it."""
    import shutil
    import tempfile

    import cv2

    target = Path(directory)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    os.chmod(tmp, dir_mode())  # mkdtemp makes 0700: others of the cell must read the masks
    try:
        for i, m in enumerate(masks):
            if not cv2.imwrite(str(tmp / f"view_{i:03d}.png"), m.astype(np.uint8) * 255):
                raise StageError(f"could not write mask PNG {tmp / f'view_{i:03d}.png'}")
        if target.exists():
            shutil.rmtree(target)
        tmp.rename(target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _background_images(path: str, cfg: Mapping[str, Any], views: list, cameras: list,
                       poses: np.ndarray) -> list[np.ndarray | None]:
    """For each view, the decoded empty-scene image of ``segmentation.background_topic``
    taken nearest its pose (same camera), or None when there is none close enough."""
    from dataclasses import replace

    from .transforms import rotation_angle_deg

    seg = cfg["segmentation"]
    out: list[np.ndarray | None] = [None] * len(views)
    topic = seg.get("background_topic")
    if not topic or not views:
        return out
    from .recording.reader import read_recording

    options = _reader_options(cfg)
    options["topics"] = replace(options["topics"], views=topic)
    rec = read_recording(path, roles=("views",), require=False, **options)
    bgs = [m for m in rec.views if m.topic == topic]
    if not bgs:
        log.warning("segmentation.background_topic %s has no images in %s: segmenting "
                    "without background subtraction", topic, path)
        return out
    bg_poses = rec.camera_poses(bgs)
    max_mm, max_deg = seg["background_max_offset_mm"], seg["background_max_offset_deg"]
    decoded: dict[int, np.ndarray] = {}
    for i, (cam, T) in enumerate(zip(cameras, poses, strict=True)):
        best, best_d = None, np.inf
        for j, (msg, Tb) in enumerate(zip(bgs, bg_poses, strict=True)):
            if msg.frame_id != cam.frame_id:
                continue
            d_mm = float(np.linalg.norm(Tb[:3, 3] - T[:3, 3])) * 1e3
            d_deg = float(rotation_angle_deg(Tb[:3, :3].T @ T[:3, :3]))
            if d_mm <= max_mm and d_deg <= max_deg and d_mm + d_deg < best_d:
                best, best_d = j, d_mm + d_deg
        if best is None:
            log.warning("view %d (t=%d ns): no empty-scene image on %s within %.2f mm and "
                        "%.2f deg of its pose: segmented without background subtraction", i,
                        views[i].timestamp_ns, topic, max_mm, max_deg)
            continue
        if best not in decoded:
            decoded[best] = rec.decode(bgs[best])
        out[i] = decoded[best]
    return out


def _load_silhouettes(path: str) -> dict[str, Any]:
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    shape = tuple(d["mask_shape"])
    d["masks"] = np.unpackbits(d["masks"], axis=-1, count=shape[-1]).astype(bool)
    return d


def stage_carve(inputs: Mapping[str, str], outputs: Mapping[str, str],
                cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Place the box, check the views agree, carve the visual hull (seed §3.1–3.5), mesh it.

    Before the carve, each silhouette is scored against the hull of the other views on
    a coarse grid (:func:`robo3d.carving.flag_disagreeing_views`, ``carving.qa_*``);
    the views it flags are left out of the carve (``carving.qa_leave_out``) and named
    in the report (``views_left_out``), in ``hull.npz`` (``views_used``,
    ``views_left_out``) and in the rerun log. Views the segmentation's own checks
    flagged (``qa_flagged`` in ``silhouettes.npz``) do not define the other views'
    reference; they are left out only when they disagree too. The carving method
    (``carving.method``: Szeliski's octree or dense), its policies and ``k`` of n
    (``carving.min_views_background``) come from the config; ``hull.npz`` holds the
    occupancy with its origin, voxel size, frame and how it was carved, ``hull.ply``
    the smoothed watertight marching-cubes mesh, the report the box, the agreement
    scores, the resolution check (eq. 7–8), the volume and the hull's bounding box
    (``bbox_min``, ``bbox_max``: the outer faces of the occupied voxels, metres).
    """
    from .carving import (
        box_from_silhouettes,
        carve_visual_hull,
        hull_to_mesh,
        make_grid,
        resolution_report,
    )
    from .errors import ConfigError
    from .meshio import write_mesh
    from .viz import log_box, log_camera, log_mesh, log_report, log_voxels, rerun_log

    t0 = time.perf_counter()
    sil = _load_silhouettes(inputs["silhouettes"])
    cameras = _cameras_from(sil)
    masks = [sil["masks"][i, : c.height, : c.width] for i, c in enumerate(cameras)]
    poses = sil["T_base_camera"]
    cc = cfg["carving"]
    if cc["method"] == "dense" and cc["leaf_rule"] != "centre":
        raise ConfigError(f"config key carving.leaf_rule: {cc['leaf_rule']!r} needs "
                          "carving.method octree (the dense method tests voxel centres)")
    ws = _workspace_from(sil)
    if ws is not None:
        box_min, box_max = ws
        box_report = {"source": "workspace box of the recording"}
    else:
        box_min, box_max, box_report = box_from_silhouettes(None, masks, cameras, poses,
                                                            margin=cc["box_margin"])
        box_report = {"source": "silhouette centroid rays (seed §3.4)", **box_report}
    box_report["size_m"] = (np.asarray(box_max) - np.asarray(box_min)).tolist()
    log.info("carving box (%s): min %s, max %s, size %s mm", box_report["source"],
             np.round(box_min, 4).tolist(), np.round(box_max, 4).tolist(),
             np.round(np.asarray(box_report["size_m"]) * 1e3, 1).tolist())
    agreement = _view_agreement_check(inputs["silhouettes"], sil, masks, cameras, poses,
                                      box_min, box_max, cc)
    n_views = len(cameras)
    left_out = agreement["views_left_out"] if cc["qa_leave_out"] else []
    used = [i for i in range(n_views) if i not in set(left_out)]
    if ws is None and left_out:  # a bad mask also misplaces the box: place it again
        box_min, box_max, box_report = box_from_silhouettes(
            None, [masks[i] for i in used], [cameras[i] for i in used], poses[used],
            margin=cc["box_margin"])
        box_report = {"source": "silhouette centroid rays (seed §3.4) of the views used",
                      **box_report, "size_m": (box_max - box_min).tolist()}
    grid = make_grid(box_min, box_max, resolution=cc["resolution"])
    grid, carve_report = carve_visual_hull(grid, [masks[i] for i in used],
                                           [cameras[i] for i in used], poses[used],
                                           method=cc["method"],
                                           outside_image=cc["outside_image"],
                                           behind_camera=cc["behind_camera"],
                                           leaf_rule=cc["leaf_rule"], threads=cc["threads"],
                                           min_views_background=cc["min_views_background"])
    for v in carve_report["views"]:  # the recording's view numbers, not the subset's
        v["view"] = used[v["view"]]
    n_occ = grid.n_occupied
    if n_occ == 0:
        raise StageError(f"{inputs['silhouettes']}: carving removed every voxel: the "
                         "silhouettes do not agree with the cameras' poses (check the "
                         "calibration, the transform tree and the masks)")
    vertices, faces = hull_to_mesh(grid, smooth_sigma_vox=cc["smooth_sigma_vox"])
    res = resolution_report(grid, [cameras[i] for i in used], poses[used])
    if res.get("warning"):
        log.warning("%s", res["warning"])
    left_out_rows = [{"view": i, "reasons": agreement["reasons"].get(i, [])}
                     for i in left_out]
    occ_ijk = np.argwhere(grid.occupancy)
    half = 0.5 * grid.voxel_size  # outer faces of the occupied voxels
    bbox = (grid.index_to_points(occ_ijk.min(axis=0)) - half,
            grid.index_to_points(occ_ijk.max(axis=0)) + half)
    report = {"box": {"min": np.asarray(box_min).tolist(), "max": np.asarray(box_max).tolist(),
                      **box_report},
              "method": cc["method"], "grid_shape": list(grid.occupancy.shape),
              "voxel_size_m": grid.voxel_size, "occupied_voxels": n_occ,
              "volume_m3": grid.volume_m3, "bbox_min": bbox[0].tolist(),
              "bbox_max": bbox[1].tolist(), "n_views": n_views, "views_used": used,
              "views_left_out": left_out_rows,
              "views_flagged": agreement["flagged"],
              "agreement": agreement, "carving": carve_report, "resolution": res,
              "mesh": {"vertices": len(vertices), "faces": len(faces),
                       "volume_m3": _mesh_volume(vertices, faces)},
              "seconds": round(time.perf_counter() - t0, 3)}
    grid.save_npz(outputs["npz"], carving={k: cc[k] for k in ("method", "leaf_rule",
                                                              "outside_image",
                                                              "behind_camera",
                                                              "min_views_background")},
                  views_used=np.array(used, dtype=np.int64),
                  views_left_out=left_out_rows)
    write_mesh(outputs["ply"], vertices, faces)
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        import rerun as rr

        log_box(rr_stream, "base/carving_box", box_min, box_max, label="carving box")
        for i in used:
            log_camera(rr_stream, f"base/cameras/view_{i:03d}", cameras[i], poses[i])
        for row in left_out_rows:  # left out: their cameras, masks and why, apart
            i = row["view"]
            entity = f"base/cameras_left_out/view_{i:03d}"
            log_camera(rr_stream, entity, cameras[i], poses[i], mask=masks[i])
            rr_stream.log(f"{entity}/why", rr.TextDocument(
                f"view {i} left out of the carve: " + "; ".join(row["reasons"])), static=True)
        shell = grid.surface()
        log_voxels(rr_stream, "base/hull/voxels", grid.index_to_points(np.argwhere(shell)),
                   grid.voxel_size)
        log_mesh(rr_stream, "base/hull/mesh", vertices, faces, albedo=[120, 160, 220, 160])
        log_report(rr_stream, "reports/carve", report)
    write_json(outputs["report"], report)
    summary.info("hull (%s): %d voxels of %.2f mm, volume %.1f cm3, mesh %d faces, %d of %d "
             "views (%.1f s)", cc["method"], n_occ, grid.voxel_size * 1e3,
             report["volume_m3"] * 1e6, len(faces), len(used), n_views, report["seconds"])
    return report


def _segmentation_flags(silhouettes_npz: str, sil: Mapping[str, Any], n_views: int
                        ) -> dict[int, list[str]]:
    """Views the segmentation's own checks flagged, with its reasons: ``qa_flagged`` in
    ``silhouettes.npz`` and ``views[i]["qa"]["flags"]`` in ``reports/silhouettes.json``
    beside it, read defensively (older files have neither)."""
    import json

    flags: dict[int, list[str]] = {}
    q = sil.get("qa_flagged")
    if q is not None and np.asarray(q).shape == (n_views,):
        flags = {int(i): [] for i in np.flatnonzero(np.asarray(q, dtype=bool))}
    path = Path(silhouettes_npz).parent / "reports" / "silhouettes.json"
    try:
        with open(path, encoding="utf-8") as f:
            views = json.load(f).get("views", [])
    except (OSError, ValueError, AttributeError):
        views = []
    for pos, v in enumerate(views if isinstance(views, list) else []):
        qa = v.get("qa") if isinstance(v, dict) else None
        idx = v.get("index", pos) if isinstance(v, dict) else pos
        reasons = qa.get("flags") if isinstance(qa, dict) else qa
        if isinstance(reasons, str):
            reasons = [reasons]
        if isinstance(idx, int) and 0 <= idx < n_views and isinstance(reasons, list) \
                and reasons:
            flags[idx] = [f"segmentation: {r}" for r in reasons]
    return flags


def _view_agreement_check(silhouettes_npz: str, sil: Mapping[str, Any], masks: list,
                          cameras: list, poses: np.ndarray, box_min: np.ndarray,
                          box_max: np.ndarray, cc: Mapping[str, Any]) -> dict[str, Any]:
    """Score every view against the other views' hull and choose the views to leave out
    (see :func:`stage_carve`); with fewer than 4 views, or ``carving.qa_resolution`` 0,
    nothing is scored."""
    from .carving import flag_disagreeing_views, make_grid

    n = len(cameras)
    seg_flags = _segmentation_flags(silhouettes_npz, sil, n)
    out: dict[str, Any] = {"enabled": False, "segmentation_flagged": sorted(seg_flags),
                           "flagged": [], "views_left_out": [], "reasons": {}, "views": []}
    if cc["qa_resolution"] == 0 or n < 4:
        out["why_not"] = ("carving.qa_resolution is 0" if cc["qa_resolution"] == 0 else
                          f"{n} views: too few for the others to outvote one")
        return out
    exclude = sorted(seg_flags)
    if len(exclude) > n // 2:
        log.warning("the segmentation flagged %d of %d views: too many to leave the "
                    "reference; all views score each other", len(exclude), n)
        exclude = []
    grid = make_grid(box_min, box_max, resolution=min(cc["qa_resolution"], cc["resolution"]))
    qa = flag_disagreeing_views(grid, masks, cameras, poses, max_missing=cc["qa_max_missing"],
                                max_spurious=cc["qa_max_spurious"], exclude=exclude,
                                outside_image=cc["outside_image"],
                                behind_camera=cc["behind_camera"],
                                # the masks are scored against the others' exact hull
                                # whatever k the carve uses: a k > 1 hull is fatter than
                                # any correct mask, which would then look "missing"
                                min_views_background=1,
                                min_observers=cc["qa_min_observers"], method=cc["method"])
    reasons = {int(v): list(qa["views"][v]["reasons"]) + seg_flags.get(v, [])
               for v in qa["flagged"]}
    scores = [{k: s[k] for k in ("view", "iou", "missing_fraction", "spurious_fraction",
                                 "mask_px", "hull_px", "unknown_px", "flagged")}
              | {"segmentation_flags": seg_flags.get(s["view"], [])} for s in qa["views"]]
    ious = [s["iou"] for s in scores if s["iou"] is not None]
    out.update({"enabled": True, "resolution": int(max(grid.shape)),
                "voxel_size_m": grid.voxel_size, "flagged": qa["flagged"],
                "views_left_out": qa["flagged"] if cc["qa_leave_out"] else [],
                "reasons": reasons, "passes": qa["passes"], "capped": qa["capped"],
                "thresholds": qa["thresholds"], "min_observers": cc["qa_min_observers"],
                "iou_min": min(ious) if ious else None,
                "iou_median": float(np.median(ious)) if ious else None,
                "views": scores, "seconds": round(qa["time_s"], 3)})
    log.info("view agreement (%d^3 grid, %.1f s): IoU with the other views' hull median "
             "%.3f, worst %.3f; flagged %s", out["resolution"], qa["time_s"],
             out["iou_median"] or float("nan"), out["iou_min"] or float("nan"),
             qa["flagged"] or "none")
    return out


def _mesh_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume of a closed, outward-wound triangle mesh, cubic metres."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _laser_poses(rec, frames: list, laser_frame: str = "laser") -> np.ndarray:
    """``T_camera_laser`` (F, 4, 4) of each laser frame at its own time, looked up once per
    camera frame_id (vectorised over the frames' stamps)."""
    out = np.zeros((len(frames), 4, 4))
    if not frames:
        return out
    ids = np.array([str(m.frame_id) for m in frames])
    stamps = np.array([m.timestamp_ns for m in frames], dtype=np.int64)
    for fid in np.unique(ids):
        sel = np.nonzero(ids == fid)[0]
        out[sel] = rec.tf.lookup(str(fid), laser_frame, stamps[sel])
    return out


def _stage_threads(threads: int | None) -> int:
    """Worker threads of a stage: the job's (Snakemake's ``threads``) or 1."""
    n = 1 if threads is None else int(threads)
    if n < 1:
        raise StageError(f"threads must be >= 1, got {threads}")
    return n


def stage_stripes(inputs: Mapping[str, str], outputs: Mapping[str, str],
                  cfg: Mapping[str, Any], rec_name: str,
                  threads: int | None = None) -> dict[str, Any]:
    """Find the laser stripe's sub-pixel centres in every laser frame (seed §4.2).

    The frames are decoded and searched on ``threads`` threads (the decoder and the
    stripe kernels release the GIL); the results do not depend on the number.
    """
    from concurrent.futures import ThreadPoolExecutor

    from .stripes import (
        REJECTION_REASONS,
        centre_on_for,
        config_options,
        estimate_laser_colour,
        extract_stripe_centres,
    )
    from .viz import log_camera, log_report, rerun_log, spaced_indices

    t0 = time.perf_counter()
    n_threads = _stage_threads(threads)
    rec = _read(inputs["recording"], cfg, roles=("laser",))
    frames = sorted(rec.laser_frames, key=lambda m: m.timestamp_ns)
    cameras = [rec.camera_for(m) for m in frames]
    poses = rec.camera_poses(frames)
    T_camera_laser = _laser_poses(rec, frames)  # the reader names the role "laser"
    sc = cfg["stripes"]
    kw = config_options(sc)
    # laser-off frames: read as the "laser" role of their own topic, the nearest in time
    # subtracted from each laser frame
    rec_off, off_frames, pair = None, [], np.zeros(0, np.int64)
    if sc.get("laser_off_topic") and frames:
        topic = str(sc["laser_off_topic"])
        cfg_off = {**cfg, "topics": {**dict(cfg.get("topics") or {}), "laser": topic}}
        rec_off = _read(inputs["recording"], cfg_off, roles=("laser",), require=False)
        off_frames = sorted(rec_off.laser_frames, key=lambda m: m.timestamp_ns)
        if not off_frames:
            raise StageError(f"{inputs['recording']}: stripes.laser_off_topic {topic}: no "
                             "image on that topic (set it to null for a recording without "
                             "laser-off frames)")
        t_off = np.array([m.timestamp_ns for m in off_frames], dtype=np.int64)
        t_on = np.array([m.timestamp_ns for m in frames], dtype=np.int64)
        j = np.clip(np.searchsorted(t_off, t_on), 1, len(t_off)) - 1
        j1 = np.minimum(j + 1, len(t_off) - 1)
        pair = np.where(np.abs(t_off[j1] - t_on) < np.abs(t_on - t_off[j]), j1, j)

    def background(i: int):
        return rec_off.decode(off_frames[pair[i]]) if rec_off is not None else None

    # the region of interest: where the laser sheet inside the workspace box projects (a
    # stripe point elsewhere cannot triangulate into the box: the crop would drop it)
    tc = cfg["triangulation"]
    use_roi = bool(sc["roi_from_workspace"] and kw["detector"] == "ridge"
                   and rec.workspace is not None and tc["crop_to_workspace"])
    T_roi_laser = T_camera_laser
    if use_roi and tc["laser_params"] is not None:  # the laser the triangulation will use
        from .triangulation import laser_transform_from_params

        dx, dy, dz, phi, theta, psi = (float(x) for x in tc["laser_params"])
        T_roi_laser = np.broadcast_to(laser_transform_from_params(
            dx, dy, dz, *np.radians([phi, theta, psi])), T_camera_laser.shape)
    roi_area = np.full(len(frames), np.nan)

    def roi(i: int):
        if not use_roi:
            return None
        from .triangulation import sheet_in_workspace, sheet_roi_mask

        m = sheet_roi_mask(cameras[i], sheet_in_workspace(poses[i], T_roi_laser[i],
                                                          rec.workspace),
                           float(sc["roi_margin_px"]))
        roi_area[i] = 1.0 if m is None else float(m.mean())
        return m

    # the laser's colour, once for the recording, from a few evenly spaced frames (only
    # their regions of interest vote)
    colour_scores = None
    if kw["detector"] == "ridge" and kw["colour"] == "auto" and frames:
        sample = spaced_indices(len(frames), 12)
        kw["colour"], colour_scores = estimate_laser_colour(
            [rec.decode(frames[i]) for i in sample],
            backgrounds=[background(i) for i in sample], min_peak=kw["min_peak"],
            rois=[roi(int(i)) for i in sample])
        log.info("stripes: laser colour %s (scores: %s)", kw["colour"],
                 ", ".join(f"{k} {v:.0f}" for k, v in colour_scores.items()))

    # the centre's profile: the luma for JPEGs whose colour is stored at half resolution
    # (the laser's channel lives mostly in the blurred chroma there), else the laser's
    kw["centre_on"] = centre_on_for(kw["centre_on"], frames[0].data if frames else None)

    def work(i: int):
        ta = time.perf_counter()
        image = rec.decode(frames[i])
        bg = background(i)
        tb = time.perf_counter()
        sp = extract_stripe_centres(image, background=bg, roi=roi(i), **kw)
        return sp, tb - ta, time.perf_counter() - tb

    progress = _Progress("finding stripes", len(frames))
    found, decode_s, detect_s = [], 0.0, 0.0
    with ThreadPoolExecutor(max_workers=n_threads) as pool:
        for i, (sp, td, tx) in enumerate(pool.map(work, range(len(frames)))):
            found.append(sp)
            decode_s += td
            detect_s += tx
            progress(i + 1)
    counts = np.array([len(sp) for sp in found], dtype=np.int64)
    n_points = int(counts.sum())
    if frames and n_points == 0:
        raise StageError(f"{inputs['recording']}: topic {frames[0].topic}: no laser stripe "
                         f"found in any of {len(frames)} frames (check stripes.min_peak, "
                         "the exposure and the laser)")
    rejected = np.array([[sp.rejected[k] for k in REJECTION_REASONS] for sp in found],
                        dtype=np.int64).reshape(-1, len(REJECTION_REASONS))
    n_lines = np.array([sp.n_lines for sp in found], dtype=np.int64)
    empty = counts == 0
    # why a frame has no stripe: every line too weak (nothing lit brightly enough: the
    # sheet misses the object, or falls on the dim table only), or the lines that had a
    # stripe were all rejected for another reason
    all_weak = empty & (rejected[:, REJECTION_REASONS.index("too_weak")]
                        + rejected[:, REJECTION_REASONS.index("outside_roi")] == n_lines)
    if empty.any():
        log.warning("%d of %d laser frames have no stripe (%d with every line too weak: "
                    "the sheet misses the object or lights only the dim table)",
                    int(empty.sum()), len(frames), int(all_weak.sum()))
    s_frame = np.array([sp.s for sp in found], dtype=np.float64)
    axes = np.array([sp.axis for sp in found], dtype="<U7")
    angles = np.array([sp.angle_deg for sp in found], dtype=np.float64)
    colours = np.array([sp.colour for sp in found], dtype="<U9")
    with_stripe = ~empty
    report = {
        "n_frames": len(frames), "n_points": n_points,
        "frames_without_stripe": int(empty.sum()),
        "frames_without_stripe_all_lines_too_weak": int(all_weak.sum()),
        "rejected": {k: int(rejected[:, j].sum()) for j, k in enumerate(REJECTION_REASONS)},
        "points_per_frame_mean": n_points / max(len(frames), 1),
        "points_per_frame_with_stripe_median":
            float(np.median(counts[with_stripe])) if with_stripe.any() else 0.0,
        "brightness_s": {"median": float(np.median(s_frame[with_stripe])),
                         "min": float(s_frame[with_stripe].min()),
                         "max": float(s_frame[with_stripe].max())} if with_stripe.any()
        else None,
        "axis": {a: int((axes == a).sum()) for a in ("columns", "rows")},
        "angle_deg": {"median": float(np.median(angles[with_stripe])),
                      "min": float(np.min(angles[with_stripe])),
                      "max": float(np.max(angles[with_stripe]))}
        if np.isfinite(angles[with_stripe]).any() else None,
        "detector": sc["detector"], "laser_colour": kw["colour"],
        "centre_on": kw.get("centre_on"),
        "laser_colour_scores": colour_scores,
        "roi": {"used": use_roi, "source": "laser sheet inside the workspace box"
                if use_roi else None,
                "margin_px": float(sc["roi_margin_px"]) if use_roi else None,
                "area_fraction_median": float(np.nanmedian(roi_area))
                if use_roi and np.isfinite(roi_area).any() else None},
        "laser_off_frames": len(off_frames),
        "method": sc["method"], "reference": sc["reference"] if sc["s"] is None else "frame",
        "threads": n_threads,
        "decode_seconds_cpu": round(decode_s, 3), "detect_seconds_cpu": round(detect_s, 3),
        "seconds": round(time.perf_counter() - t0, 3)}

    def cat(name: str, dtype: type) -> np.ndarray:
        if not found:
            return np.zeros(0, dtype=dtype)
        return np.concatenate([getattr(sp, name) for sp in found]).astype(dtype)

    save_npz(outputs["npz"], u=cat("u", np.float64), v=cat("v", np.float64),
             confidence=cat("confidence", np.float64), peak=cat("peak", np.float32),
             width_px=cat("width_px", np.float32), line=cat("line", np.int32),
             offsets=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
             axis=axes, angle_deg=angles, colour=colours, s=s_frame, n_lines=n_lines,
             rejected=rejected,
             rejection_reasons=np.array(REJECTION_REASONS),
             stamps_ns=np.array([m.timestamp_ns for m in frames], dtype=np.int64),
             T_base_camera=poses, T_camera_laser=T_camera_laser,
             **_camera_arrays(cameras), **_workspace_arrays(rec))
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        # the stripe points of every frame on the "frame" timeline, the camera where it
        # was; the image itself on a few evenly spaced frames
        with_image = set(spaced_indices(len(frames), cfg["rerun"]["max_images"]).tolist())
        for i, sp in enumerate(found):
            rr_stream.set_time("frame", sequence=int(i))
            if i in with_image:
                _log_image_camera(rr_stream, "base/laser_camera", frames[i], cameras[i],
                                  poses[i], points_uv=sp.pixels_uv, static=False)
            else:
                log_camera(rr_stream, "base/laser_camera", cameras[i], poses[i],
                           points_uv=sp.pixels_uv, static=False)
        log_report(rr_stream, "reports/stripes", report)
    write_json(outputs["report"], report)
    summary.info("stripes: %d points in %d frames on %d threads (%.1f s; decoding %.1f s, "
             "detection %.1f s of CPU)", n_points, len(frames), n_threads,
             report["seconds"], decode_s, detect_s)
    return report


def _stripes_of_frame(s: Mapping[str, np.ndarray], i: int):
    """The :class:`~robo3d.stripes.StripePoints` of frame ``i`` of a ``stripes.npz``
    (older files without axis, line or rejections are read too)."""
    from .stripes import StripePoints

    a, b = int(s["offsets"][i]), int(s["offsets"][i + 1])
    opt = {}
    if "axis" in s:
        opt["axis"] = str(s["axis"][i])
    if "line" in s:
        opt["line"] = s["line"][a:b]
    for key in ("peak", "width_px"):
        if key in s:
            opt[key] = s[key][a:b]
    if "rejected" in s:
        opt["rejected"] = {str(k): int(n) for k, n in
                           zip(s["rejection_reasons"], s["rejected"][i], strict=True)}
    if "s" in s:
        opt["s"] = float(s["s"][i])
    if "n_lines" in s:
        opt["n_lines"] = int(s["n_lines"][i])
    if "angle_deg" in s:
        opt["angle_deg"] = float(s["angle_deg"][i])
    if "colour" in s:
        opt["colour"] = str(s["colour"][i])
    return StripePoints(u=s["u"][a:b], v=s["v"][a:b], confidence=s["confidence"][a:b], **opt)


def stage_triangulate(inputs: Mapping[str, str], outputs: Mapping[str, str],
                      cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Triangulate the stripe pixels against the laser sheet (seed §4.1), one cloud per
    sweep, in ``base``."""
    from .meshio import write_point_cloud
    from .triangulation import (
        DROP_REASONS,
        laser_transform_from_params,
        save_clouds_npz,
        split_sweeps,
        triangulate_sweep,
    )
    from .viz import log_points, log_report, rerun_log

    t0 = time.perf_counter()
    with np.load(inputs["stripes"]) as z:
        s = {k: z[k] for k in z.files}
    cameras = _cameras_from(s)
    stamps = s["stamps_ns"]
    tc = cfg["triangulation"]
    ws = _workspace_from(s) if tc["crop_to_workspace"] else None
    if tc["laser_params"] is not None:  # the seed's eq. 11 instead of the recording's tf
        dx, dy, dz, phi, theta, psi = (float(x) for x in tc["laser_params"])
        T_laser = laser_transform_from_params(dx, dy, dz, *np.radians([phi, theta, psi]))
        T_camera_laser = np.broadcast_to(T_laser, (len(stamps), 4, 4))
        laser_source = "config triangulation.laser_params (seed eq. 11)"
    else:
        T_camera_laser = s["T_camera_laser"]
        laser_source = "recording transforms (camera -> laser)"
    sweep_of = split_sweeps(stamps, int(round(cfg["timing"]["sweep_gap_s"] * 1e9)))
    clouds, per_sweep = [], []
    for k in np.unique(sweep_of):
        idx = np.nonzero(sweep_of == k)[0]
        stripes = [_stripes_of_frame(s, int(i)) for i in idx]
        cam = cameras[int(idx[0])]
        try:
            cloud = triangulate_sweep(stripes, cam, s["T_base_camera"][idx],
                                      T_camera_laser[idx], workspace=ws,
                                      frame_indices=idx, sweep=int(k),
                                      min_angle_deg=tc["min_angle_deg"],
                                      min_range=tc["min_range_m"], max_range=tc["max_range_m"],
                                      normal_span=tc["normal_span"],
                                      normal_smooth=tc["normal_smooth"],
                                      normal_jump=tc["normal_jump"], normal_knn=tc["normal_knn"])
        except StageError as exc:
            log.warning("sweep %d (frames %d..%d) skipped: %s", k, idx[0], idx[-1], exc)
            per_sweep.append({"sweep": int(k), "frames": len(idx), "points": 0,
                              "skipped": str(exc)})
            continue
        clouds.append(cloud)
        per_sweep.append({"sweep": int(k), "frames": len(idx), "points": len(cloud.points_base),
                          **getattr(cloud, "report", {})})
    if not clouds:
        raise StageError(f"{inputs['stripes']}: no sweep produced any point")
    dropped = {r: int(sum(p.get("dropped", {}).get(r, 0) for p in per_sweep))
               for r in (*DROP_REASONS, "outside_workspace")}
    rej_keys = [str(k) for k in s["rejection_reasons"]] if "rejection_reasons" in s else []
    report = {"n_sweeps": len(clouds), "n_points": int(sum(len(c.points_base) for c in clouds)),
              "n_pixels": int(len(s["u"])), "dropped": dropped,
              "stripe_rejected": {k: int(s["rejected"][:, j].sum())
                                  for j, k in enumerate(rej_keys)},
              "laser_pose": laser_source, "sweeps": per_sweep,
              "seconds": round(time.perf_counter() - t0, 3)}
    save_clouds_npz(outputs["npz"], clouds)
    pts = np.concatenate([c.points_base for c in clouds])
    write_point_cloud(
        outputs["ply"], pts, normals=np.concatenate([c.normals_base for c in clouds]),
        attributes={
            "sweep": np.concatenate([np.full(len(c.points_base), c.sweep)
                                     for c in clouds]).astype(np.int32),
            "frame_index": np.concatenate([c.frame_index for c in clouds]).astype(np.int32),
            "confidence": np.concatenate([c.confidence for c in clouds]).astype(np.float32)})
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        for c in clouds:
            color = _sweep_color(c.sweep)
            # the sweep's cloud grows profile by profile along the "frame" timeline
            frames_c = np.unique(c.frame_index)
            for chunk in np.array_split(frames_c, min(20, len(frames_c))):
                if len(chunk) == 0:
                    continue
                rr_stream.set_time("frame", sequence=int(chunk[-1]))
                sel = c.frame_index <= chunk[-1]
                log_points(rr_stream, f"base/sweeps/sweep_{c.sweep:02d}", c.points_base[sel],
                           colors=color, static=False)
        log_report(rr_stream, "reports/triangulate", report)
    write_json(outputs["report"], report)
    from .viz import format_counts

    summary.info("triangulated %d points in %d sweeps (%.1f s); dropped: %s", report["n_points"],
             len(clouds), report["seconds"], format_counts(dropped))
    return report


def _sweep_color(k: int) -> list[int]:
    palette = [[230, 25, 75], [60, 180, 75], [0, 130, 200], [245, 130, 48], [145, 30, 180],
               [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212], [0, 128, 128]]
    return palette[int(k) % len(palette)]


def stage_align(inputs: Mapping[str, str], outputs: Mapping[str, str],
                cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Refine each sweep's pose (seed §2.3): pairwise ICP and a pose graph, then a joint
    refinement against the neighbours and, when the recording has views, the
    silhouettes as absolute reference (:func:`robo3d.registration.align_sweeps`).

    Inputs: ``clouds``; optional ``silhouettes`` (silhouettes.npz) with ``recording``
    (the views' grey images). Each aligned cloud's report keeps ``correction``: the rigid
    ``base`` transform applied at the sweep's middle frame (what corrects the robot's
    pose there), and ``correction_model`` (rotation, translation of
    :func:`robo3d.registration.apply_correction`).
    """
    from .meshio import write_point_cloud
    from .registration import align_sweeps, correction_at
    from .triangulation import load_clouds_npz, save_clouds_npz
    from .viz import log_points, log_report, rerun_log

    t0 = time.perf_counter()
    clouds = load_clouds_npz(inputs["clouds"])
    ac = cfg["alignment"]
    views = None
    if ac["enabled"] and ac["refine"] and ac["silhouettes"] and inputs.get("silhouettes"):
        views = _silhouette_views(inputs, cfg)
    if ac["enabled"] and len(clouds) > 1:
        result = align_sweeps([c.points_base for c in clouds], [c.normals_base for c in clouds],
                              voxel_size=ac["voxel_size_m"], max_corr_dist=ac["max_corr_dist_m"],
                              max_iterations=ac["max_iterations"],
                              max_correction_mm=ac["max_correction_mm"],
                              max_correction_deg=ac["max_correction_deg"],
                              min_overlap=ac["min_overlap"], method=ac["method"],
                              seed=cfg["seed"],
                              origins=[c.sensor_origin_base for c in clouds],
                              profiles=[c.frame_index for c in clouds], refine=ac["refine"],
                              silhouettes=views, prior_mm=ac["prior_mm"],
                              prior_deg=ac["prior_deg"],
                              refine_iterations=ac["refine_iterations"],
                              rim_weight=ac["rim_weight"],
                              normal_k=ac["pair_normals_k"],
                              normal_max_spacing=ac["pair_normals_max_spacing_m"],
                              degenerate_ratio=ac["degenerate_ratio"],
                              pair_degenerate_ratio=ac["pair_degenerate_ratio"])
        align_report = {"method": result.method, "gauge": result.gauge,
                        "reference": result.reference, "pairs": result.pairs,
                        "per_sweep": result.per_sweep, "refinement": result.refinement,
                        "n_views_used": 0 if views is None else len(views.cameras)}
    else:
        result = None
        align_report = {"skipped": "alignment disabled in the config" if not ac["enabled"]
                        else "a single sweep has nothing to align to"}
    corrections = []
    for k, c in enumerate(clouds):
        mid = int(np.median(c.frame_index)) if len(c.frame_index) else 0
        o_mid = (c.sensor_origin_base[int(np.argmin(np.abs(c.frame_index - mid)))]
                 if len(c.frame_index) else np.zeros(3))
        if result is None:
            rot, tr = np.eye(3), np.zeros(3)
        elif result.rotations is not None:
            rot, tr = result.rotations[k], result.translations[k]
        else:  # rigid corrections (no refinement): the same at every frame
            C = result.corrections[k]
            rot, tr = C[:3, :3], C[:3, 3] + C[:3, :3] @ o_mid - o_mid
        if result is not None and result.rotations is None:
            p, o, n = result.apply(k, c.points_base, c.sensor_origin_base, c.normals_base)
        else:
            from .registration import apply_correction

            p, o, n = apply_correction(c.points_base, c.sensor_origin_base, rot, tr,
                                       c.normals_base)
        C_mid = correction_at(o_mid, rot, tr)
        corrections.append(C_mid)
        c.report = {**(c.report or {}), "correction": C_mid.tolist(), "correction_frame": mid,
                    "correction_model": {"rotation": np.asarray(rot).tolist(),
                                         "translation": np.asarray(tr).tolist()}}
        c.points_base, c.sensor_origin_base, c.normals_base = p, o, n
    hull_check, rejected = _reject_outside_hull(clouds, views, inputs, ac)
    report = {"n_sweeps": len(clouds), **align_report,
              "corrections": [C.tolist() for C in corrections],
              "outside_hull": hull_check,
              "seconds": round(time.perf_counter() - t0, 3)}
    save_clouds_npz(outputs["npz"], clouds)
    write_point_cloud(outputs["ply"], np.concatenate([c.points_base for c in clouds]),
                      normals=np.concatenate([c.normals_base for c in clouds]),
                      attributes={"sweep": np.concatenate([np.full(len(c.points_base), c.sweep)
                                                           for c in clouds]).astype(np.int32)})
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        for c in clouds:
            log_points(rr_stream, f"base/aligned/sweep_{c.sweep:02d}", c.points_base,
                       colors=_sweep_color(c.sweep))
        if len(rejected):
            log_points(rr_stream, "base/rejected/outside_hull", rejected,
                       colors=[255, 0, 255])
        log_report(rr_stream, "reports/align", report)
    write_json(outputs["report"], report)
    flagged = [p["sweep"] for p in align_report.get("per_sweep", []) if p.get("flagged")]
    summary.info("aligned %d sweeps (gauge: %s, %.1f s)%s", len(clouds),
             align_report.get("gauge", "-"), report["seconds"],
             f"; flagged and kept at the robot's pose: {flagged}" if flagged else "")
    return report


def _reject_outside_hull(clouds: list, views, inputs: Mapping[str, str],
                         ac: Mapping[str, Any]) -> tuple[dict[str, Any], np.ndarray]:
    """Drop the aligned points that lie outside a view's silhouette (in place).

    A point of the object cannot project outside a correct silhouette of it; a laser
    point that does is light of the laser's colour that the sheet did not put on the
    object there (the object's lit rim, a glint, a reflection) triangulated into empty
    space (:func:`robo3d.carving.outside_silhouettes`). Views flagged by the silhouettes'
    QA are not used; nor is a view whose silhouette alone would drop more than
    ``outside_hull_max_view_fraction`` of the points (the laser contradicts the mask).

    Returns the report (per sweep: points dropped) and the dropped points.
    """
    from .carving import outside_silhouettes

    if not ac["reject_outside_hull"]:
        return {"skipped": "alignment.reject_outside_hull is false"}, np.zeros((0, 3))
    if views is None:
        return {"skipped": "no silhouette views"}, np.zeros((0, 3))
    n_all = sum(len(c) for c in clouds)
    if n_all == 0:
        return {"skipped": "no points"}, np.zeros((0, 3))
    with np.load(inputs["silhouettes"]) as z:
        qa = z["qa_flagged"].astype(bool) if "qa_flagged" in z.files else None
    idx = [i for i in range(len(views.cameras)) if qa is None or not qa[i]]
    pts = np.concatenate([c.points_base for c in clouds])
    tol_px, tol_m = float(ac["outside_hull_px"]), 1e-3 * float(ac["outside_hull_mm"])
    per_view = np.zeros((len(idx), len(pts)), bool)
    for j, i in enumerate(idx):
        n_i, _ = outside_silhouettes(pts, [views.masks[i]], [views.cameras[i]],
                                     views.T_base_camera[i:i + 1], tol_px=tol_px, tol_m=tol_m)
        per_view[j] = n_i > 0
    frac = per_view.mean(axis=1) if len(idx) else np.zeros(0)
    distrust = frac > float(ac["outside_hull_max_view_fraction"])
    n_out = per_view[~distrust].sum(axis=0)
    drop = n_out >= int(ac["outside_hull_min_views"])
    starts = np.cumsum([0] + [len(c) for c in clouds])
    per_sweep = []
    for k, c in enumerate(clouds):
        d = drop[starts[k]:starts[k + 1]]
        per_sweep.append({"sweep": c.sweep, "dropped": int(d.sum()), "points": len(c)})
        if d.any():
            keep = ~d
            c.points_base, c.normals_base = c.points_base[keep], c.normals_base[keep]
            c.frame_index, c.confidence = c.frame_index[keep], c.confidence[keep]
            c.sensor_origin_base = c.sensor_origin_base[keep]
            c.report = {**(c.report or {}), "dropped_outside_hull": int(d.sum())}
    not_used = [{"view": int(idx[j]), "would_drop_fraction": round(float(frac[j]), 4)}
                for j in np.flatnonzero(distrust)]
    report = {"views_used": int(len(idx) - distrust.sum()),
              "views_not_used_qa_flagged": [i for i in range(len(views.cameras))
                                            if i not in idx],
              "views_not_used_contradict_laser": not_used,
              "tol_px": tol_px, "tol_mm": 1e3 * tol_m,
              "min_views": int(ac["outside_hull_min_views"]),
              "dropped": int(drop.sum()), "points": int(n_all),
              "dropped_fraction": float(drop.mean()), "per_sweep": per_sweep}
    log.info("alignment: %d of %d laser points (%.2f %%) lie outside a silhouette: dropped "
             "(%d views used%s)", int(drop.sum()), n_all, 100 * float(drop.mean()),
             report["views_used"],
             f"; not used, contradict the laser: {[v['view'] for v in not_used]}"
             if not_used else "")
    return report, pts[drop]


def _silhouette_views(inputs: Mapping[str, str], cfg: Mapping[str, Any]):
    """The silhouette views (grey images, masks, cameras, poses) for the alignment's
    absolute reference; None when the recording's views cannot be matched."""
    from .registration import SilhouetteViews

    sil = _load_silhouettes(inputs["silhouettes"])
    cameras = _cameras_from(sil)
    if not cameras or not inputs.get("recording"):
        return None
    rec = _read(inputs["recording"], cfg, roles=("views",))
    by_stamp = {m.timestamp_ns: m for m in rec.views}
    images = []
    for t in sil["stamps_ns"]:
        msg = by_stamp.get(int(t))
        if msg is None:
            log.warning("alignment: view at t=%d ns of the silhouettes is not in %s; the "
                        "silhouettes are not used as reference", int(t), inputs["recording"])
            return None
        images.append(rec.decode(msg))
    masks = [sil["masks"][i, : c.height, : c.width] for i, c in enumerate(cameras)]
    return SilhouetteViews(images, masks, cameras, sil["T_base_camera"])


def stage_fuse(inputs: Mapping[str, str], outputs: Mapping[str, str],
               cfg: Mapping[str, Any], rec_name: str, threads: int | None = None
               ) -> dict[str, Any]:
    """Fuse the aligned clouds into one watertight surface (seed §2.4): each sweep as range
    data into a TSDF (Curless & Levoy), holes closed from the visual hull (or screened
    Poisson, ``fusion.method``); from views alone the fused mesh is the hull's.

    The report says what fraction of the surface came from the laser and from the hull.
    """
    from .carving import VoxelGrid, hull_to_mesh
    from .fusion import (
        HULL,
        MEASURED,
        SOURCES,
        fuse_poisson,
        fuse_tsdf,
        keep_vertices,
        source_area_fractions,
    )
    from .meshio import write_mesh
    from .triangulation import load_clouds_npz
    from .viz import log_mesh, log_report, rerun_log

    t0 = time.perf_counter()
    fc = cfg["fusion"]
    hull = VoxelGrid.load_npz(inputs["hull"]) if inputs.get("hull") else None
    if inputs.get("aligned"):
        clouds = load_clouds_npz(inputs["aligned"])
        crop = hull if (hull is not None and fc["crop_to_hull"]) else None
        if fc["method"] == "tsdf":
            V, F, fuse_report, attrs = fuse_tsdf(
                [c.points_base for c in clouds], [c.normals_base for c in clouds],
                [c.sensor_origin_base for c in clouds],
                confidences=[c.confidence for c in clouds], voxel_size=fc["tsdf_voxel_m"],
                trunc_voxels=int(fc["tsdf_trunc_voxels"]), hull=crop,
                hull_margin_voxels=fc["hull_margin_voxels"], fill_holes=fc["fill_holes"],
                carve_free_space=fc["carve_free_space"], min_weight=fc["min_weight"],
                min_cos_view=fc["min_cos_view"], threads=_stage_threads(threads),
                close=fc["close"], max_fill_distance_m=1e-3 * fc["max_fill_distance_mm"],
                carve_depth_m=fc["carve_depth_m"], carve_full_line=fc["carve_full_line"],
                return_attributes=True)
            source = "laser (TSDF)" + {
                "hull": ", holes closed from the hull",
                "free_space": ", holes near measurements closed, far ones left open",
                "none": ", holes left open"}[fc["close"]] if (
                crop is not None and fc["fill_holes"]) else "laser (TSDF)"
        else:
            pts = np.concatenate([c.points_base for c in clouds])
            nrm = np.concatenate([c.normals_base for c in clouds])
            V, F, fuse_report = fuse_poisson(pts, nrm, depth=fc["poisson_depth"],
                                             density_quantile=fc["density_quantile"],
                                             hull=crop, seed=cfg["seed"])
            attrs = _poisson_provenance(V, pts, fc["tsdf_voxel_m"],
                                        1e-3 * fc["max_fill_distance_mm"])
            source = "laser (screened Poisson)"
            if crop is not None:
                cut = str(fuse_report.get("hull_cut", "applied"))
                source += ", cut to the hull" if cut == "applied" else f", hull cut {cut}"
    elif hull is not None:
        V, F = hull_to_mesh(hull, smooth_sigma_vox=cfg["carving"]["smooth_sigma_vox"])
        fuse_report = {"note": "no laser frames: the fused mesh is the visual hull's",
                       "laser_area_fraction": 0.0, "hull_area_fraction": 1.0}
        attrs = {"source": np.full(len(V), HULL, np.uint8),
                 "n_obs": np.zeros(len(V), np.uint16),
                 "incidence": np.zeros(len(V), np.float32),
                 "tsdf_weight": np.zeros(len(V), np.float32),
                 "dist_measured_m": np.full(len(V), np.inf, np.float32),
                 "confidence": np.zeros(len(V), np.float32),
                 "far_from_measured": np.ones(len(V), np.uint8)}
        source = "visual hull"
    else:
        raise StageError("fusion needs aligned clouds or a hull, got neither")
    if len(F) == 0:
        raise StageError(f"fusion produced an empty mesh from {source}")
    if isinstance(fuse_report.get("source_area_fraction"), dict):
        fuse_report.pop("source_area_fraction")
    fractions = source_area_fractions(V, F, attrs["source"])
    Vm, Fm, attrs_m = keep_vertices(V, F, attrs, attrs["source"] == MEASURED)
    report = {"source": source, "method": fc["method"] if inputs.get("aligned") else "hull",
              **fuse_report, "vertices": len(V), "faces": len(F),
              "source_area_fraction": fractions,
              "inferred_area_fraction": 1.0 - fractions["measured"],
              "inferred_far_area_fraction": _area_fraction(V, F, attrs["far_from_measured"]
                                                           > 0),
              "measured_faces": len(Fm),
              "vertex_attributes": {"source": {str(i): n for i, n in enumerate(SOURCES)},
                                    "fields": sorted(attrs)},
              "seconds": round(time.perf_counter() - t0, 3)}
    write_mesh(outputs["ply"], V, F, vertex_colors=source_colors(attrs["source"]),
               attributes=attrs)
    if outputs.get("measured"):
        write_mesh(outputs["measured"], Vm, Fm,
                   attributes={k: a for k, a in attrs_m.items() if k != "source"})
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        log_mesh(rr_stream, "base/fused", V, F, vertex_colors=source_colors(attrs["source"]))
        log_report(rr_stream, "reports/fuse", report)
    write_json(outputs["report"], report)
    lf = report.get("laser_area_fraction")
    summary.info("fused mesh from %s: %d faces%s (%.1f s)", source, len(F),
             f", {100 * lf:.1f}% of its area from the laser" if lf is not None else "",
             report["seconds"])
    return report


def _area_fraction(V: np.ndarray, F: np.ndarray, flag: np.ndarray) -> float:
    """Share of a mesh's area on faces with a flagged vertex."""
    if len(F) == 0:
        return 0.0
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                axis=1)
    total = float(area.sum())
    return float(area[np.any(flag[F], axis=1)].sum() / total) if total > 0 else 0.0


#: Vertex colours of the provenance in fused.ply and mesh.ply (and their rerun logs):
#: measured grey, inferred from the hull orange, filled yellow.
_SOURCE_RGB = np.array([[190, 190, 190], [240, 120, 30], [240, 210, 40]], dtype=np.uint8)


def source_colors(source: np.ndarray) -> np.ndarray:
    """RGB per vertex for its provenance (:data:`robo3d.fusion.SOURCES`)."""
    return _SOURCE_RGB[np.clip(np.asarray(source, np.int64), 0, len(_SOURCE_RGB) - 1)]


def _poisson_provenance(V: np.ndarray, pts: np.ndarray, voxel: float, far_m: float
                        ) -> dict[str, np.ndarray]:
    """Provenance of screened-Poisson vertices: measured within ``2 * voxel`` of a laser
    point (or twice the points' median spacing, if larger), else inferred (hull)."""
    from scipy.spatial import cKDTree

    from .fusion import HULL, MEASURED

    tree = cKDTree(pts)
    d, _ = tree.query(V, k=1)
    spacing = float(np.median(tree.query(pts[:: max(1, len(pts) // 5000)], k=2)[0][:, 1]))
    near = d <= max(2.0 * voxel, 2.0 * spacing)
    return {"source": np.where(near, MEASURED, HULL).astype(np.uint8),
            "n_obs": np.zeros(len(V), np.uint16), "incidence": np.zeros(len(V), np.float32),
            "tsdf_weight": np.zeros(len(V), np.float32),
            "dist_measured_m": d.astype(np.float32),
            "confidence": np.where(near, np.exp(-(d / (2 * voxel)) ** 2), 0.0
                                   ).astype(np.float32),
            "far_from_measured": (~near & (d > far_m)).astype(np.uint8)}


def stage_simplify(inputs: Mapping[str, str], outputs: Mapping[str, str],
                   cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Clean the fused mesh (duplicates, zero-area faces, small floating components) and
    simplify it by quadric edge collapse to ``simplify.target_faces`` and/or within
    ``simplify.max_error_m``; the Hausdorff distance to the fused mesh must stay within
    ``simplify.hausdorff_tolerance_m`` (more faces are kept until it does). Writes
    ``ply`` and, when given, ``stl`` / ``obj`` outputs."""
    from .fusion import source_area_fractions
    from .meshio import read_mesh, read_vertex_attributes, write_mesh
    from .simplify import clean_mesh, simplify_mesh, transfer_vertex_attributes
    from .viz import log_mesh, log_report, rerun_log

    t0 = time.perf_counter()
    sc = cfg["simplify"]
    V, F = read_mesh(inputs["fused"])
    attrs_in = read_vertex_attributes(inputs["fused"])
    V0 = V
    V, F, clean_report = clean_mesh(V, F, min_component_fraction=sc["min_component_fraction"])
    bound = sc["hausdorff_tolerance_m"]
    if sc["max_error_m"] is not None:
        bound = min(bound, sc["max_error_m"])
    V2, F2, simp_report = simplify_mesh(V, F, target_faces=sc["target_faces"], max_error=bound,
                                        seed=cfg["seed"])
    haus = simp_report.get("hausdorff_max_m")
    within = haus is None or haus <= sc["hausdorff_tolerance_m"]
    if not within:
        log.warning("simplified mesh departs %.3f mm from the fused one, more than the "
                    "tolerance %.3f mm", haus * 1e3, sc["hausdorff_tolerance_m"] * 1e3)
    report = {"clean": clean_report, **simp_report, "faces_in": len(F), "faces_out": len(F2),
              "hausdorff_tolerance_m": sc["hausdorff_tolerance_m"],
              "within_tolerance": bool(within),
              "exports": [k for k in ("ply", "stl", "obj") if outputs.get(k)],
              "export_unit": {"ply": "m", "stl": sc["export_unit"], "obj": sc["export_unit"]},
              "seconds": round(time.perf_counter() - t0, 3)}
    attrs = transfer_vertex_attributes(V0, attrs_in, V2)
    if "source" in attrs:
        fractions = source_area_fractions(V2, F2, attrs["source"])
        report["source_area_fraction"] = fractions
        report["inferred_area_fraction"] = 1.0 - fractions["measured"]
    colours = source_colors(attrs["source"]) if "source" in attrs else None
    for key in ("ply", "stl", "obj"):
        if outputs.get(key):
            write_mesh(outputs[key], V2, F2, vertex_colors=colours if key == "ply" else None,
                       attributes=attrs if key == "ply" else None,
                       unit="m" if key == "ply" else sc["export_unit"])
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        if colours is not None:
            log_mesh(rr_stream, "base/mesh", V2, F2, vertex_colors=colours)
        else:
            log_mesh(rr_stream, "base/mesh", V2, F2, albedo=[230, 200, 160, 255])
        log_report(rr_stream, "reports/simplify", report)
    write_json(outputs["report"], report)
    summary.info("simplified %d -> %d faces, Hausdorff %.3f mm (%.1f s)", len(F), len(F2),
             (haus or 0.0) * 1e3, report["seconds"])
    return report


def stage_evaluate(inputs: Mapping[str, str], outputs: Mapping[str, str],
                   cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Gather what every stage measured, its time and peak memory, and, when the
    recording carries ground truth, the errors against it, into ``metrics.json``; draw
    the final mesh coloured by its error (``picture``, when given).

    Accuracy of the fused and final meshes is scored on the surface inside the
    workspace box above ``evaluation.floor_margin_m`` over its floor (below it the mesh
    closes the face resting on the table, which no sensor sees); ``*_whole`` keeps it.
    Completeness counts the true surface inside the workspace box. With true
    silhouettes attached (``ground_truth/silhouettes/NNN.png``), ``evaluation.mask_iou``
    scores each view's mask (:func:`robo3d.evaluate.silhouette_iou`). A missing or
    damaged attachment skips only what needs it (``skipped`` says why). The views the
    carve's agreement check left out are listed in ``views_left_out``.
    """
    import json

    from .carving import VoxelGrid
    from .evaluate import (
        TRUE_SILHOUETTES,
        TruthSurface,
        cloud_accuracy,
        completeness,
        mesh_accuracy,
        volume_iou,
    )
    from .meshio import read_mesh
    from .triangulation import load_clouds_npz
    from .viz import log_mesh, log_report, rerun_log

    t0 = time.perf_counter()
    rec_path = inputs["recording"]
    results_dir = Path(outputs["metrics"]).parent
    metrics: dict[str, Any] = {"recording": str(rec_path), "name": rec_name,
                               "robo3d": code_version(), "skipped": {}}
    if not inputs.get("hull"):
        metrics["skipped"]["hull"] = "the recording has no silhouette views"
    if not inputs.get("aligned"):
        metrics["skipped"]["laser"] = ("the recording has no laser frames: no clouds, no "
                                       "alignment; the mesh is the visual hull's")
    stages = {}
    for p in sorted((results_dir / "reports").glob("*.json")):
        with open(p, encoding="utf-8") as f:
            stages[p.stem] = json.load(f)
    metrics["stages"] = stages
    metrics["timings"] = _stage_timings(rec_name, stages)
    fuse = stages.get("fuse", {})
    simp = stages.get("simplify", {})
    metrics["surface_sources"] = {
        "laser_area_fraction": fuse.get("laser_area_fraction"),
        "hull_area_fraction": fuse.get("hull_area_fraction"),
        # per vertex provenance (the source property of fused.ply and mesh.ply), by area
        "fused": fuse.get("source_area_fraction"),
        "mesh": simp.get("source_area_fraction"),
        "inferred_area_fraction": simp.get("inferred_area_fraction",
                                           fuse.get("inferred_area_fraction")),
        "close": cfg["fusion"]["close"]}
    carve = stages.get("carve", {})
    if isinstance(carve, dict) and "views_left_out" in carve:
        metrics["views_left_out"] = carve["views_left_out"]
    rec = _read(rec_path, cfg, roles=(), require=False)
    mesh_bytes = rec.attachments.get("ground_truth/mesh.ply")
    has_true_masks = any(k.startswith(TRUE_SILHOUETTES) for k in rec.attachments)
    ev = cfg["evaluation"]
    V_final, F_final = read_mesh(inputs["mesh"])
    vertex_error_mm = None
    truth = None
    ev_out: dict[str, Any] = {}
    if mesh_bytes is None and not has_true_masks:
        metrics["skipped"]["evaluation"] = "the recording carries no ground truth"
    elif mesh_bytes is None:
        metrics["skipped"]["surface_evaluation"] = ("the recording carries no "
                                                    "ground_truth/mesh.ply")
    else:
        try:
            Vt, Ft = read_mesh(mesh_bytes)
            truth = TruthSurface(Vt, Ft)
        except (Robo3dError, ValueError, RuntimeError, OSError) as exc:
            metrics["skipped"]["surface_evaluation"] = (f"ground_truth/mesh.ply is damaged: "
                                                        f"{exc}")
            log.warning("%s: ground_truth/mesh.ply is damaged (%s): no surface evaluation",
                        rec_path, exc)
    if truth is not None:
        region = rec.workspace
        scored = None
        if region is not None:
            scored = (np.asarray(region[0], dtype=np.float64).copy(),
                      np.asarray(region[1], dtype=np.float64))
            scored[0][2] += ev["floor_margin_m"]
        ev_out.update({"region": None if region is None else
                       [region[0].tolist(), region[1].tolist()],
                       "accuracy_region": None if scored is None else
                       [scored[0].tolist(), scored[1].tolist()]})
        if inputs.get("hull"):
            g = VoxelGrid.load_npz(inputs["hull"])
            ev_out["hull_volume_iou"] = volume_iou(g.occupancy, g.origin, g.voxel_size, truth,
                                                   region=region)
        if inputs.get("clouds"):
            raw = load_clouds_npz(inputs["clouds"])
            ali = load_clouds_npz(inputs["aligned"])
            ev_out["clouds"] = cloud_accuracy(np.concatenate([c.points_base for c in raw]), truth)
            ev_out["aligned"] = cloud_accuracy(np.concatenate([c.points_base for c in ali]),
                                               truth)
        thresholds = tuple(ev["thresholds_mm"])
        for key in ("fused", "mesh"):
            V, F = (V_final, F_final) if key == "mesh" else read_mesh(inputs[key])
            ev_out[key] = {
                **mesh_accuracy(V, F, truth, n_samples=ev["n_samples"], seed=cfg["seed"],
                                thresholds_mm=thresholds, region=scored),
                "completeness": completeness(V, F, truth, thresholds_mm=thresholds,
                                             n_samples=ev["n_samples"], region=region,
                                             seed=cfg["seed"]),
                "whole": mesh_accuracy(V, F, truth, n_samples=ev["n_samples"] // 4,
                                       seed=cfg["seed"], thresholds_mm=thresholds),
            }
        if inputs.get("measured"):
            ev_out["measured"] = _measured_evaluation(inputs["measured"], truth, ev, cfg,
                                                      scored, region)
        if inputs.get("aligned") and "ground_truth/tf.json" in rec.attachments:
            try:
                ev_out["poses"] = _pose_errors(rec, inputs)
            except (Robo3dError, ValueError, KeyError, TypeError) as exc:
                # a damaged or unknown form of the truth costs only the pose figures
                metrics["skipped"]["poses"] = (f"ground_truth/tf.json cannot be used: "
                                               f"{type(exc).__name__}: {exc}")
                log.warning("%s: %s", rec_path, metrics["skipped"]["poses"])
        elif inputs.get("aligned"):
            metrics["skipped"]["poses"] = "the recording carries no ground_truth/tf.json"
        vertex_error_mm = truth.distance(V_final) * 1e3
    _mask_evaluation(inputs, rec, has_true_masks, metrics, ev_out)
    if ev_out:
        metrics["evaluation"] = ev_out
    if outputs.get("picture"):
        from .render import error_figure

        title = (f"{rec_name}: final mesh ({len(F_final)} faces) coloured by its distance to "
                 "the true surface" if vertex_error_mm is not None else
                 f"{rec_name}: final mesh ({len(F_final)} faces), no ground truth")
        error_figure(outputs["picture"], V_final, F_final,
                     vertex_error_mm if vertex_error_mm is not None
                     else np.full(len(V_final), np.nan),
                     vmax_mm=ev["picture_vmax_mm"], title=title)
    metrics["evaluate_seconds"] = round(time.perf_counter() - t0, 3)
    if "evaluate" not in metrics["timings"]:  # its own benchmark file comes after it
        metrics["timings"]["evaluate"] = {"seconds": metrics["evaluate_seconds"],
                                          "max_rss_mb": None,
                                          "source": "measured inside the job"}
        if metrics["timings"].get("total_seconds") is not None:
            metrics["timings"]["total_seconds"] += metrics["evaluate_seconds"]
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        if truth is not None:
            log_mesh(rr_stream, "base/ground_truth", truth.vertices, truth.faces,
                     albedo=[120, 220, 120, 90])
        log_report(rr_stream, "reports/metrics", metrics.get("evaluation", {}))
    write_json(outputs["metrics"], metrics)
    _log_summary(metrics)
    return metrics


def _measured_evaluation(path: str, truth, ev: Mapping[str, Any], cfg: Mapping[str, Any],
                         scored, region) -> dict[str, Any]:
    """Accuracy and completeness of the measured surface alone (measured.ply): what an
    inspection tool compares with CAD. ``outlier_area_fraction_0_5mm`` is the share of its
    area farther than 0.5 mm from the truth (area-uniform samples)."""
    from .evaluate import completeness, mesh_accuracy, sample_surface
    from .meshio import read_mesh

    V, F = read_mesh(path)
    thresholds = tuple(ev["thresholds_mm"])
    if len(F) == 0:
        return {"n_faces": 0, "note": "nothing was measured (no laser surface)"}
    acc = mesh_accuracy(V, F, truth, n_samples=ev["n_samples"], seed=cfg["seed"],
                        thresholds_mm=thresholds, region=scored)
    samples = sample_surface(V, F, ev["n_samples"] // 4, seed=cfg["seed"])
    d = truth.distance(samples)
    area = float(0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                      axis=1).sum())
    return {**acc, "n_faces": int(len(F)), "area_m2": area,
            "outlier_area_fraction_0_5mm": float(np.mean(d > 0.5e-3)),
            "completeness": completeness(V, F, truth, thresholds_mm=thresholds,
                                         n_samples=ev["n_samples"], region=region,
                                         seed=cfg["seed"])}


def _mask_evaluation(inputs: Mapping[str, str], rec, has_true_masks: bool,
                     metrics: dict[str, Any], ev_out: dict[str, Any]) -> None:
    """``ev_out["mask_iou"]``: the silhouettes stage's masks against the true ones, or
    ``metrics["skipped"]["mask_iou"]`` saying why not."""
    from .evaluate import silhouette_iou

    sil_path = inputs.get("silhouettes") or (
        str(Path(inputs["hull"]).with_name("silhouettes.npz")) if inputs.get("hull") else None)
    if not has_true_masks:
        if sil_path:
            metrics["skipped"]["mask_iou"] = "the recording carries no ground_truth/silhouettes/"
        return
    if not sil_path or not Path(sil_path).is_file():
        metrics["skipped"]["mask_iou"] = ("no silhouettes to score (the recording has no "
                                          "silhouette views, or silhouettes.npz is missing)")
        return
    try:
        sil = _load_silhouettes(sil_path)
        cams = _cameras_from(sil)
    except (OSError, ValueError, KeyError) as exc:
        metrics["skipped"]["mask_iou"] = f"{sil_path} does not load: {exc}"
        return
    masks = [sil["masks"][i, : c.height, : c.width] for i, c in enumerate(cams)]
    result = silhouette_iou(masks, rec.attachments)
    left_out = {r["view"] for r in metrics.get("views_left_out", [])
                if isinstance(r, dict) and "view" in r}
    for v in result["per_view"]:
        v["left_out_of_carve"] = v["view"] in left_out
    if result["n_truth"] != len(masks):
        result["note"] = (f"{result['n_truth']} true silhouettes for {len(masks)} views: "
                          "views are matched by their index in time order")
    for i, why in result["skipped"].items():
        log.warning("mask IoU: view %s skipped: %s", i, why)
    for name, why in result["unmatched"].items():
        log.warning("mask IoU: attachment %s ignored: %s", name, why)
    if result["n_scored"]:
        ev_out["mask_iou"] = result
    else:
        metrics["skipped"]["mask_iou"] = ("no true silhouette could be used: "
                                          + "; ".join(f"view {k}: {v}" for k, v in
                                                      list(result["skipped"].items())[:5]))
        ev_out["mask_iou"] = result


def _stage_timings(rec_name: str, stages: Mapping[str, Any]) -> dict[str, Any]:
    """Wall time and peak memory of each stage of one recording: Snakemake's benchmark
    files (``benchmarks/<rule>/<rec>.tsv`` in the working directory: seconds, max RSS)
    where they exist, else the seconds the stage reported."""
    import csv

    out: dict[str, Any] = {}
    for stage in ("silhouettes", "carve", "stripes", "triangulate", "align", "fuse",
                  "simplify", "evaluate"):
        entry: dict[str, Any] = {}
        tsv = Path("benchmarks") / stage / f"{rec_name}.tsv"
        if tsv.exists():
            try:
                with open(tsv, encoding="utf-8") as f:
                    row = next(csv.DictReader(f, delimiter="\t"))
                entry = {"seconds": float(row["s"]), "max_rss_mb": float(row["max_rss"]),
                         "cpu_seconds": float(row.get("cpu_time") or "nan"),
                         "source": str(tsv)}
            except (StopIteration, KeyError, ValueError):
                entry = {}
        if not entry and isinstance(stages.get(stage), dict) and "seconds" in stages[stage]:
            entry = {"seconds": stages[stage]["seconds"], "max_rss_mb": None,
                     "source": "stage report (inside the job)"}
        if entry:
            out[stage] = entry
    known = [e["seconds"] for e in out.values() if isinstance(e.get("seconds"), float | int)]
    out["total_seconds"] = float(sum(known)) if known else None
    return out


def _pose_errors(rec, inputs: Mapping[str, str]) -> dict[str, Any]:
    """Per-sweep robot pose error before and after alignment, against ground_truth/tf.json.

    The pose of a sweep is its ``base -> flange`` at the sweep's middle frame: the reported
    one (before), the reported one corrected by the alignment (after: the cloud's
    ``correction``, the rigid transform the alignment applied at that frame), the true
    one. Each error is given as the rotation angle (degrees) and as two translations: of
    the flange's origin (``*_mm``: about 0.3 m from the object, so a rotation error
    ``r`` alone moves it by ``r * 0.3 m``), and of the sweep's own points (``*_obj_mm``:
    the displacement of the sweep's centroid by the pose error, what the error does to
    the scan).
    """
    from .evaluate import pose_error
    from .recording.reader import read_ground_truth_tf
    from .triangulation import load_clouds_npz

    truth_tf = read_ground_truth_tf(rec)
    clouds = load_clouds_npz(inputs["clouds"])
    aligned = load_clouds_npz(inputs["aligned"])
    stripes_path = Path(inputs["clouds"]).with_name("stripes.npz")
    with np.load(stripes_path) as z:
        stamps = z["stamps_ns"]
    out = []
    for k, c in enumerate(clouds):
        rep = aligned[k].report or {}
        C = np.asarray(rep.get("correction", np.eye(4)))
        mid = int(rep.get("correction_frame", int(np.median(c.frame_index))))
        t = int(stamps[mid])
        T_rep = rec.tf.lookup(rec.base_frame, "flange", t)
        T_true = truth_tf.lookup(rec.base_frame, "flange", t)
        centroid = c.points_base.mean(axis=0)

        before = pose_error(T_rep, T_true)
        after = pose_error(C @ T_rep, T_true)
        out.append({"sweep": int(c.sweep), "before_mm": float(before[0]),
                    "before_deg": float(before[1]),
                    "before_obj_mm": _displacement_mm(T_rep, T_true, centroid),
                    "after_mm": float(after[0]), "after_deg": float(after[1]),
                    "after_obj_mm": _displacement_mm(C @ T_rep, T_true, centroid)})

    def worst(key: str) -> float:
        return max(o[key] for o in out)

    frames = _frame_pose_errors(rec, clouds, aligned, stamps, stripes_path)
    return {"per_sweep": out, **frames,
            "worst_before_mm": worst("before_mm"), "worst_before_deg": worst("before_deg"),
            "worst_before_obj_mm": worst("before_obj_mm"),
            "worst_after_mm": worst("after_mm"), "worst_after_deg": worst("after_deg"),
            "worst_after_obj_mm": worst("after_obj_mm")}


def _frame_pose_errors(rec, clouds, aligned, stamps: np.ndarray, stripes_path: Path
                       ) -> dict[str, Any]:
    """Per laser frame, when the recording carries the true pose of every image at its
    exposure (``ground_truth/image_poses.json``, written by ``robo3d simulate``): the pose
    the pipeline used for the frame (reported pose at the stamp, times the alignment's
    correction at that frame) against the truth at the moment the image was taken, so a
    late camera clock and an error that drifts within a sweep are scored as what they do
    to the points (:func:`robo3d.evaluate.frame_displacement`). A sweep's figure is its
    worst frame; ``worst_*_frame_*`` the worst sweep. Empty without that attachment."""
    from .evaluate import frame_displacement
    from .registration import correction_at

    if "ground_truth/image_poses.json" not in rec.attachments:
        return {}
    try:
        from .simulate import image_poses

        entries = image_poses(rec)["/camera/laser_image"]
        T_true = np.stack([e["T_base_camera"] for e in entries])
    except (Robo3dError, KeyError, ValueError, TypeError) as exc:
        return {"frames_skipped": f"ground_truth/image_poses.json unusable: {exc}"}
    if len(T_true) != len(stamps):
        return {"frames_skipped": f"ground_truth/image_poses.json has {len(T_true)} laser "
                                  f"images, the stripes {len(stamps)} frames"}
    with np.load(stripes_path) as z:
        T_rep = z["T_base_camera"]
    per = []
    for c, a in zip(clouds, aligned, strict=True):
        if not len(c.points_base):
            continue
        model = (a.report or {}).get("correction_model") or {}
        R = np.asarray(model.get("rotation", np.eye(3)), dtype=np.float64)
        t = np.asarray(model.get("translation", np.zeros(3)), dtype=np.float64)
        f = np.asarray(c.frame_index, dtype=np.int64)
        first = np.unique(f, return_index=True)[1]
        C = np.tile(np.eye(4), (len(T_rep), 1, 1))
        C[f[first]] = [correction_at(o, R, t) for o in c.sensor_origin_base[first]]
        d0, r0 = frame_displacement(c.points_base, f, T_rep, T_true)
        d1, r1 = frame_displacement(a.points_base, f, C @ T_rep, T_true)
        sel = np.unique(f)
        per.append({"sweep": int(c.sweep), "frames": int(len(sel)),
                    "before_mm": float(np.nanmax(d0[sel])), "before_deg": float(r0[sel].max()),
                    "after_mm": float(np.nanmax(d1[sel])), "after_deg": float(r1[sel].max()),
                    "after_median_mm": float(np.nanmedian(d1[sel]))})
    if not per:
        return {}
    return {"per_sweep_frames": per,
            "truth_frames": "true camera pose at each laser image's exposure",
            **{f"worst_{k}_frame_{u}": max(p[f"{k}_{u}"] for p in per)
               for k in ("before", "after") for u in ("mm", "deg")}}


def _displacement_mm(T_est: np.ndarray, T_true: np.ndarray, point: np.ndarray) -> float:
    """How far a pose error ``T_est`` (vs ``T_true``) moves ``point`` (base), mm."""
    from .transforms import invert_transform

    D = T_est @ invert_transform(T_true)
    return float(np.linalg.norm(D[:3, :3] @ point + D[:3, 3] - point) * 1e3)


def _log_summary(metrics: Mapping[str, Any]) -> None:
    ev = metrics.get("evaluation")
    if not ev:
        summary.info("no ground truth; skipped: %s", "; ".join(
            f"{k} ({v})" for k, v in metrics["skipped"].items()))
        return
    parts = []
    mi = ev.get("mask_iou") or {}
    if mi.get("mean") is not None:
        parts.append(f"mask IoU mean {mi['mean']:.3f}, worst {mi['min']:.3f} (view "
                     f"{mi['worst_view']}) over {mi['n_scored']} views")
    if "hull_volume_iou" in ev:
        parts.append(f"hull IoU {ev['hull_volume_iou']:.3f}")
    if "poses" in ev:
        p = ev["poses"]
        parts.append(f"worst sweep pose error {p['worst_before_obj_mm']:.3f} -> "
                     f"{p['worst_after_obj_mm']:.3f} mm at the object, "
                     f"{p['worst_before_deg']:.3f} -> {p['worst_after_deg']:.4f} deg")
    m = ev.get("mesh") or {}
    if m.get("median_mm") is not None:
        parts.append(f"mesh median {m['median_mm']:.3f} mm, p95 {m['p95_mm']:.3f} mm")
    c = (m.get("completeness") or {}).get("within_mm") or {}
    if c:
        parts.append("completeness " + ", ".join(f"{v:.3f} at {k} mm" for k, v in c.items()
                                                 if v is not None))
    me = ev.get("measured") or {}
    if me.get("median_mm") is not None:
        parts.append(f"measured surface median {me['median_mm']:.3f} mm, p95 "
                     f"{me['p95_mm']:.3f} mm, {100 * me['outlier_area_fraction_0_5mm']:.2f} % "
                     "of its area > 0.5 mm off")
    inf = (metrics.get("surface_sources") or {}).get("inferred_area_fraction")
    if inf is not None:
        parts.append(f"{100 * inf:.1f} % of the mesh's area inferred (not measured)")
    if metrics.get("skipped"):
        parts.append("skipped: " + "; ".join(f"{k} ({v})" for k, v in metrics["skipped"].items()))
    summary.info("%s", "; ".join(parts))


STAGES: dict[str, Callable[..., dict[str, Any]]] = {
    "silhouettes": stage_silhouettes,
    "carve": stage_carve,
    "stripes": stage_stripes,
    "triangulate": stage_triangulate,
    "align": stage_align,
    "fuse": stage_fuse,
    "simplify": stage_simplify,
    "evaluate": stage_evaluate,
}


class _TerminalFilter(logging.Filter):
    """What a job shows on the terminal: its stage's summary and progress lines
    (``robo3d.summary``) and every warning or error; the log file keeps everything."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.name == "robo3d.summary" or record.levelno >= logging.WARNING


def _setup_logging(log_path: str | None, rec: str = "", stage: str = "") -> None:
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
    where = " ".join(x for x in (rec, stage) if x)
    term = logging.Formatter(f"%(asctime)s {where}: %(message)s" if where else
                             "%(asctime)s %(message)s", "%H:%M:%S")
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    for h in list(root.handlers):
        root.removeHandler(h)
    err = logging.StreamHandler(sys.stderr)
    err.setFormatter(term)
    err.addFilter(_TerminalFilter())
    root.addHandler(err)
    if log_path:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(log_path, mode="w", encoding="utf-8")
        fh.setFormatter(fmt)
        root.addHandler(fh)


#: The config sections each stage reads (its rule passes them as ``params``, so that
#: changing one re-runs exactly the stages that read it, and those after them).
STAGE_CONFIG: dict[str, tuple[str, ...]] = {
    "silhouettes": ("segmentation", "topics", "frames", "timing", "rerun", "seed"),
    "carve": ("carving", "topics", "frames", "timing", "rerun", "seed"),
    "stripes": ("stripes", "triangulation", "topics", "frames", "timing", "rerun", "seed"),
    "triangulate": ("triangulation", "topics", "frames", "timing", "rerun", "seed"),
    "align": ("alignment", "topics", "frames", "timing", "rerun", "seed"),
    "fuse": ("fusion", "carving", "rerun", "seed"),
    "simplify": ("simplify", "rerun", "seed"),
    "evaluate": ("evaluation", "fusion", "topics", "frames", "timing", "rerun", "seed"),
}


def stage_config(cfg: Mapping[str, Any], stage: str) -> dict[str, Any]:
    """The part of the (validated) config that ``stage`` reads (:data:`STAGE_CONFIG`)."""
    return {k: cfg[k] for k in STAGE_CONFIG[stage] if k in cfg}


def code_version() -> str:
    """robo3d's version and a hash of its code (every ``.py`` file of the package): part of
    every rule's params, so that an upgrade or a code change re-runs the jobs instead of
    silently keeping results the new code would not give."""
    import hashlib

    from . import __version__

    root = Path(__file__).resolve().parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return f"{__version__}+{h.hexdigest()[:16]}"


def run_from_snakemake(stage: str, smk: Any) -> None:
    """Run one stage from a Snakemake ``script:`` job (``smk`` is the injected object).

    A robo3d error (bad input, a stage that cannot produce its result) is logged as one
    clear line and ends the job with exit status 1, without a traceback from deep inside a
    library; any other exception (a bug) is logged with its traceback, so that the job's
    log always says why it failed (``robo3d status`` reads the first error line).
    Snakemake then removes the job's outputs and, with ``--keep-going``, finishes the
    other recordings. Temporary files that a killed earlier attempt left beside the
    outputs (``.<name>.*.tmp<suffix>``, never mistaken for outputs) are removed first.
    A stage that takes ``threads`` gets the job's.
    """
    import inspect

    rec = smk.wildcards.get("rec", "recording")
    _setup_logging(smk.log[0] if len(smk.log) else None, rec, stage)
    inputs = {k: str(v) for k, v in smk.input.items()}
    outputs = {k: str(v) for k, v in smk.output.items()}
    _remove_stale_temporaries(outputs.values())
    fn = STAGES[stage]
    kwargs = {}
    if "threads" in inspect.signature(fn).parameters and getattr(smk, "threads", None):
        kwargs["threads"] = int(smk.threads)
    # the rule's params hold the sections this stage reads (what triggers its re-runs);
    # the stage sees only those, so a section it reads but does not declare is a bug
    params = getattr(smk, "params", None)
    cfg = params.cfg if params is not None and hasattr(params, "cfg") else smk.config
    try:
        fn(inputs, outputs, cfg, rec, **kwargs)
    except Robo3dError as exc:
        log.error("%s failed for %s: %s", stage, rec, exc)
        logging.shutdown()
        sys.exit(1)
    except KeyboardInterrupt:  # Ctrl-C: say so, then die by the signal as expected
        import os
        import signal

        log.error("%s for %s interrupted; its outputs were not written", stage, rec)
        logging.shutdown()
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
    except Exception as exc:
        log.exception("%s failed for %s with an unexpected %s: %s (a bug in robo3d: please "
                      "report it with this log)", stage, rec, type(exc).__name__, exc)
        logging.shutdown()
        sys.exit(1)


def _remove_stale_temporaries(outputs: Iterable[str]) -> list[Path]:
    """Delete what killed jobs left of :func:`robo3d.atomic.atomic_path`'s temporaries of
    these outputs (and of mask folders); returns the paths removed."""
    import shutil

    removed = []
    for out in outputs:
        target = Path(out)
        if not target.parent.is_dir():
            continue
        patterns = (f".{target.stem}.*.tmp{target.suffix}", f".{target.name}.*")
        for pattern in patterns:
            for p in target.parent.glob(pattern):
                if p.is_dir():
                    shutil.rmtree(p, ignore_errors=True)
                else:
                    p.unlink(missing_ok=True)
                removed.append(p)
    if removed:
        log.info("removed %d temporary files left by an earlier, killed attempt: %s",
                 len(removed), ", ".join(p.name for p in removed))
    return removed
