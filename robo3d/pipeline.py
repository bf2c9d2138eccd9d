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
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import save_npz, write_json
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
    named after the directory. Names must be unique (they name ``results/<name>/``).
    """
    from .errors import ConfigError

    paths: list[Path] = []
    items = [spec] if isinstance(spec, str) else list(spec)
    for item in items:
        p = Path(item)
        if p.is_dir():
            if (p / "metadata.yaml").exists():
                paths.append(p)
            else:
                paths += sorted(p.glob("*.mcap"))
                paths += sorted(d for d in p.iterdir()
                                if d.is_dir() and (d / "metadata.yaml").exists())
        elif p.exists():
            paths.append(p)
        else:
            raise ConfigError(f"config key recordings: {item} does not exist")
    out: dict[str, RecordingEntry] = {}
    for p in paths:
        name = p.stem if p.is_file() else p.name
        if name in out:
            raise ConfigError(f"config key recordings: two recordings named {name!r} "
                              f"({out[name].path} and {p}); results/<name>/ must be unique")
        out[name] = RecordingEntry(name, str(p), None, dict(topics or {}))
    return out


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

    rec = read_recording(path, topics=topic_map(cfg["topics"]), roles=roles,
                         max_pose_gap_ns=int(round(cfg["timing"]["max_pose_gap_s"] * 1e9)),
                         base_frame=cfg["frames"]["base"], require=require)
    return rec  # the reader has logged its warnings (rec.warnings keeps them)


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

    def __init__(self, what: str, total: int, every_s: float = 2.0) -> None:
        self.what, self.total, self.every = what, total, every_s
        self.t0 = self.last = time.perf_counter()

    def __call__(self, done: int) -> None:
        now = time.perf_counter()
        if now - self.last >= self.every or done == self.total:
            self.last = now
            rate = done / max(now - self.t0, 1e-9)
            log.info("%s: %d/%d (%.0f/s)", self.what, done, self.total, rate)


# ---------------------------------------------------------------------------- stages
def stage_silhouettes(inputs: Mapping[str, str], outputs: Mapping[str, str],
                      cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Segment every silhouette view (seed §3.2) and keep its camera and pose."""
    from .silhouettes import roi_from_box, segment_silhouette
    from .viz import log_box, log_report, rerun_log, spaced_indices

    t0 = time.perf_counter()
    rec = _read(inputs["recording"], cfg, roles=("views",))
    views = sorted(rec.views, key=lambda m: m.timestamp_ns)
    cameras = [rec.camera_for(m) for m in views]
    poses = rec.camera_poses(views)
    seg = cfg["segmentation"]
    ws = rec.workspace
    masks, per_view = [], []
    progress = _Progress("segmenting views", len(views))
    for i, (msg, cam, T) in enumerate(zip(views, cameras, poses, strict=True)):
        image = rec.decode(msg) if hasattr(rec, "decode") else msg.decode()
        roi = None
        if ws is not None and seg["roi_from_workspace"]:
            roi = roi_from_box(ws[0], ws[1], cam, T, margin_px=seg["roi_margin_px"])
        try:
            sil = segment_silhouette(image, polarity=seg["polarity"], threshold=seg["threshold"],
                                     roi=roi, blur_sigma_px=seg["blur_sigma_px"],
                                     min_component_px=seg["min_component_px"],
                                     fill_holes=seg["fill_holes"],
                                     max_hole_fraction=seg["max_hole_fraction"])
        except StageError as exc:
            raise StageError(f"{inputs['recording']}: topic {msg.topic}, view {i} "
                             f"(t={msg.timestamp_ns} ns): {exc}") from None
        if sil.touches_border:
            log.warning("view %d (t=%d ns) silhouette touches the image border: the object "
                        "may be cut off and the hull carved too much", i, msg.timestamp_ns)
        masks.append(sil.mask)
        per_view.append({"index": i, "timestamp_ns": msg.timestamp_ns,
                         "threshold": float(sil.threshold), "area_px": int(sil.area_px),
                         "n_components": int(sil.n_components),
                         "touches_border": bool(sil.touches_border)})
        progress(i + 1)
    sizes = {m.shape for m in masks}
    report = {"n_views": len(views), "views": per_view,
              "n_touching_border": sum(v["touches_border"] for v in per_view),
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
             **_camera_arrays(cameras), **_workspace_arrays(rec))
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        if ws is not None:
            log_box(rr_stream, "base/workspace", ws[0], ws[1], label="workspace")
        for i in spaced_indices(len(views), cfg["rerun"]["max_images"]):
            _log_image_camera(rr_stream, f"base/views/view_{i:03d}", views[i], cameras[i],
                              poses[i], mask=masks[i])
        log_report(rr_stream, "reports/silhouettes", report)
    write_json(outputs["report"], report)
    log.info("segmented %d views in %.1f s; %d touch the border", len(views),
             report["seconds"], report["n_touching_border"])
    return report


def _load_silhouettes(path: str) -> dict[str, Any]:
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    shape = tuple(d["mask_shape"])
    d["masks"] = np.unpackbits(d["masks"], axis=-1, count=shape[-1]).astype(bool)
    return d


def stage_carve(inputs: Mapping[str, str], outputs: Mapping[str, str],
                cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Place the box and carve the visual hull (seed §3.1–3.5), then mesh it."""
    from .carving import (
        box_from_silhouettes,
        carve_dense,
        hull_to_mesh,
        make_grid,
        resolution_report,
    )
    from .meshio import write_mesh
    from .viz import log_box, log_mesh, log_report, log_voxels, rerun_log

    t0 = time.perf_counter()
    sil = _load_silhouettes(inputs["silhouettes"])
    cameras = _cameras_from(sil)
    masks = [sil["masks"][i, : c.height, : c.width] for i, c in enumerate(cameras)]
    poses = sil["T_base_camera"]
    cc = cfg["carving"]
    ws = _workspace_from(sil)
    if ws is not None:
        box_min, box_max = ws
        box_report = {"source": "workspace box of the recording"}
    else:
        box_min, box_max, box_report = box_from_silhouettes(None, masks, cameras, poses,
                                                            margin=cc["box_margin"])
        box_report = {"source": "silhouette centroid rays (seed §3.4)", **box_report}
    grid = make_grid(box_min, box_max, resolution=cc["resolution"])
    grid, carve_report = carve_dense(grid, masks, cameras, poses,
                                     outside_image=cc["outside_image"],
                                     behind_camera=cc["behind_camera"])
    n_occ = int(grid.occupancy.sum())
    if n_occ == 0:
        raise StageError(f"{inputs['silhouettes']}: carving removed every voxel: the "
                         "silhouettes do not agree with the cameras' poses (check the "
                         "calibration, the transform tree and the masks)")
    vertices, faces = hull_to_mesh(grid, smooth_sigma_vox=cc["smooth_sigma_vox"])
    res = resolution_report(grid, cameras, poses)
    if res.get("warning"):
        log.warning("%s", res["warning"])
    report = {"box": {"min": np.asarray(box_min).tolist(), "max": np.asarray(box_max).tolist(),
                      **box_report},
              "grid_shape": list(grid.occupancy.shape), "voxel_size_m": grid.voxel_size,
              "occupied_voxels": n_occ, "volume_m3": n_occ * grid.voxel_size ** 3,
              "carving": carve_report, "resolution": res,
              "mesh": {"vertices": len(vertices), "faces": len(faces)},
              "seconds": round(time.perf_counter() - t0, 3)}
    grid.save_npz(outputs["npz"])
    write_mesh(outputs["ply"], vertices, faces)
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        log_box(rr_stream, "base/carving_box", box_min, box_max, label="carving box")
        log_voxels(rr_stream, "base/hull/voxels", grid.centres(), grid.voxel_size)
        log_mesh(rr_stream, "base/hull/mesh", vertices, faces, albedo=[120, 160, 220, 160])
        log_report(rr_stream, "reports/carve", report)
    write_json(outputs["report"], report)
    log.info("hull: %d voxels of %.2f mm, volume %.1f cm3, mesh %d faces (%.1f s)", n_occ,
             grid.voxel_size * 1e3, report["volume_m3"] * 1e6, len(faces), report["seconds"])
    return report


def stage_stripes(inputs: Mapping[str, str], outputs: Mapping[str, str],
                  cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Find the laser stripe's sub-pixel centres in every laser frame (seed §4.2)."""
    from .stripes import extract_stripe_centres
    from .viz import log_report, rerun_log, spaced_indices

    t0 = time.perf_counter()
    rec = _read(inputs["recording"], cfg, roles=("laser",))
    frames = sorted(rec.laser_frames, key=lambda m: m.timestamp_ns)
    cameras = [rec.camera_for(m) for m in frames]
    poses = rec.camera_poses(frames)
    laser_frame = "laser"
    T_camera_laser = np.stack([
        rec.tf.lookup(str(m.frame_id), laser_frame, m.timestamp_ns) for m in frames
    ]) if frames else np.zeros((0, 4, 4))
    sc = cfg["stripes"]
    us, vs, confs, offsets = [], [], [], [0]
    rejected: dict[str, int] = {}
    progress = _Progress("finding stripes", len(frames))
    empty_frames = 0
    for i, msg in enumerate(frames):
        image = rec.decode(msg) if hasattr(rec, "decode") else msg.decode()
        sp = extract_stripe_centres(image, band=sc["band"], axis=sc["axis"],
                                    min_peak=sc["min_peak"], max_width_px=sc["max_width_px"],
                                    method=sc["method"])
        us.append(sp.u)
        vs.append(sp.v)
        confs.append(sp.confidence)
        offsets.append(offsets[-1] + len(sp.u))
        empty_frames += len(sp.u) == 0
        for k, n in getattr(sp, "rejected", {}).items():
            rejected[k] = rejected.get(k, 0) + int(n)
        progress(i + 1)
    n_points = offsets[-1]
    if frames and n_points == 0:
        raise StageError(f"{inputs['recording']}: topic {frames[0].topic}: no laser stripe "
                         f"found in any of {len(frames)} frames (check stripes.min_peak, "
                         "the exposure and the laser)")
    if empty_frames:
        log.warning("%d of %d laser frames have no stripe", empty_frames, len(frames))
    report = {"n_frames": len(frames), "n_points": n_points, "frames_without_stripe":
              empty_frames, "rejected": rejected,
              "points_per_frame_mean": n_points / max(len(frames), 1),
              "seconds": round(time.perf_counter() - t0, 3)}
    cat = np.concatenate
    save_npz(outputs["npz"], u=cat(us) if us else np.zeros(0), v=cat(vs) if vs else np.zeros(0),
             confidence=cat(confs) if confs else np.zeros(0),
             offsets=np.array(offsets, dtype=np.int64),
             stamps_ns=np.array([m.timestamp_ns for m in frames], dtype=np.int64),
             T_base_camera=poses, T_camera_laser=T_camera_laser,
             **_camera_arrays(cameras), **_workspace_arrays(rec))
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        for i in spaced_indices(len(frames), cfg["rerun"]["max_images"]):
            rr_stream.set_time("frame", sequence=int(i))
            uv = np.stack([us[i], vs[i]], axis=1)
            _log_image_camera(rr_stream, "base/laser_camera", frames[i], cameras[i], poses[i],
                              points_uv=uv, static=False)
        log_report(rr_stream, "reports/stripes", report)
    write_json(outputs["report"], report)
    log.info("stripes: %d points in %d frames (%.1f s)", n_points, len(frames),
             report["seconds"])
    return report


def stage_triangulate(inputs: Mapping[str, str], outputs: Mapping[str, str],
                      cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Triangulate the stripe pixels against the laser sheet (seed §4.1), one cloud per
    sweep, in ``base``."""
    from .meshio import write_point_cloud
    from .stripes import StripePoints
    from .triangulation import save_clouds_npz, split_sweeps, triangulate_sweep
    from .viz import log_points, log_report, rerun_log

    t0 = time.perf_counter()
    with np.load(inputs["stripes"]) as z:
        s = {k: z[k] for k in z.files}
    cameras = _cameras_from(s)
    off = s["offsets"]
    stamps = s["stamps_ns"]
    tc = cfg["triangulation"]
    ws = _workspace_from(s) if tc["crop_to_workspace"] else None
    sweep_of = split_sweeps(stamps, int(round(cfg["timing"]["sweep_gap_s"] * 1e9)))
    clouds, per_sweep = [], []
    for k in np.unique(sweep_of):
        idx = np.nonzero(sweep_of == k)[0]
        stripes = [StripePoints(u=s["u"][off[i]:off[i + 1]], v=s["v"][off[i]:off[i + 1]],
                                confidence=s["confidence"][off[i]:off[i + 1]])
                   for i in idx]
        cam = cameras[int(idx[0])]
        try:
            cloud = triangulate_sweep(stripes, cam, s["T_base_camera"][idx],
                                      s["T_camera_laser"][idx], workspace=ws,
                                      frame_indices=idx, sweep=int(k),
                                      min_angle_deg=tc["min_angle_deg"],
                                      min_range=tc["min_range_m"], max_range=tc["max_range_m"])
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
    report = {"n_sweeps": len(clouds), "sweeps": per_sweep,
              "n_points": int(sum(len(c.points_base) for c in clouds)),
              "seconds": round(time.perf_counter() - t0, 3)}
    save_clouds_npz(outputs["npz"], clouds)
    pts = np.concatenate([c.points_base for c in clouds])
    write_point_cloud(outputs["ply"], pts, normals=np.concatenate([c.normals_base for c in clouds]),
                      attributes={"sweep": np.concatenate([np.full(len(c.points_base), c.sweep)
                                                           for c in clouds]).astype(np.int32)})
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        for c in clouds:
            color = _sweep_color(c.sweep)
            # the sweep's cloud grows profile by profile along the "frame" timeline
            for chunk in np.array_split(np.unique(c.frame_index), min(20, len(c.frame_index))):
                if len(chunk) == 0:
                    continue
                rr_stream.set_time("frame", sequence=int(chunk[-1]))
                sel = c.frame_index <= chunk[-1]
                log_points(rr_stream, f"base/sweeps/sweep_{c.sweep:02d}", c.points_base[sel],
                           colors=color, static=False)
        log_report(rr_stream, "reports/triangulate", report)
    write_json(outputs["report"], report)
    log.info("triangulated %d points in %d sweeps (%.1f s)", report["n_points"], len(clouds),
             report["seconds"])
    return report


def _sweep_color(k: int) -> list[int]:
    palette = [[230, 25, 75], [60, 180, 75], [0, 130, 200], [245, 130, 48], [145, 30, 180],
               [70, 240, 240], [240, 50, 230], [210, 245, 60], [250, 190, 212], [0, 128, 128]]
    return palette[int(k) % len(palette)]


def stage_align(inputs: Mapping[str, str], outputs: Mapping[str, str],
                cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Refine each sweep's pose with ICP against its neighbours (seed §2.3)."""
    from .meshio import write_point_cloud
    from .registration import align_sweeps
    from .transforms import transform_points
    from .triangulation import load_clouds_npz, save_clouds_npz
    from .viz import log_points, log_report, rerun_log

    t0 = time.perf_counter()
    clouds = load_clouds_npz(inputs["clouds"])
    ac = cfg["alignment"]
    if ac["enabled"] and len(clouds) > 1:
        result = align_sweeps([c.points_base for c in clouds], [c.normals_base for c in clouds],
                              voxel_size=ac["voxel_size_m"], max_corr_dist=ac["max_corr_dist_m"],
                              max_iterations=ac["max_iterations"],
                              max_correction_mm=ac["max_correction_mm"],
                              max_correction_deg=ac["max_correction_deg"],
                              min_overlap=ac["min_overlap"], method=ac["method"],
                              seed=cfg["seed"])
        corrections = np.asarray(result.corrections)
        align_report = {"pairs": result.pairs, "per_sweep": result.per_sweep,
                        "reference": getattr(result, "reference", None)}
    else:
        corrections = np.tile(np.eye(4), (len(clouds), 1, 1))
        align_report = {"skipped": "alignment disabled in the config" if not ac["enabled"]
                        else "a single sweep has nothing to align to"}
    for c, C in zip(clouds, corrections, strict=True):
        c.report = {**(c.report or {}), "correction": C.tolist()}
        c.points_base = transform_points(C, c.points_base)
        c.normals_base = c.normals_base @ C[:3, :3].T
        c.sensor_origin_base = transform_points(C, c.sensor_origin_base)
    report = {"n_sweeps": len(clouds), **align_report,
              "corrections": [C.tolist() for C in corrections],
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
        log_report(rr_stream, "reports/align", report)
    write_json(outputs["report"], report)
    log.info("aligned %d sweeps (%.1f s)", len(clouds), report["seconds"])
    return report


def stage_fuse(inputs: Mapping[str, str], outputs: Mapping[str, str],
               cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Fuse the aligned clouds into one surface (seed §2.4), bounded by the hull; from
    views alone the fused mesh is the hull's."""
    from .carving import VoxelGrid, hull_to_mesh
    from .fusion import fuse_poisson, fuse_tsdf
    from .meshio import write_mesh
    from .triangulation import load_clouds_npz
    from .viz import log_mesh, log_report, rerun_log

    t0 = time.perf_counter()
    fc = cfg["fusion"]
    hull = VoxelGrid.load_npz(inputs["hull"]) if inputs.get("hull") else None
    if inputs.get("aligned"):
        clouds = load_clouds_npz(inputs["aligned"])
        pts = np.concatenate([c.points_base for c in clouds])
        nrm = np.concatenate([c.normals_base for c in clouds])
        crop = hull if (hull is not None and fc["crop_to_hull"]) else None
        if fc["method"] == "tsdf":
            origins = np.concatenate([c.sensor_origin_base for c in clouds])
            V, F, fuse_report = fuse_tsdf(pts, nrm, origins, voxel_size=fc["tsdf_voxel_m"],
                                          trunc_voxels=fc["tsdf_trunc_voxels"], hull=crop)
        else:
            V, F, fuse_report = fuse_poisson(pts, nrm, depth=fc["poisson_depth"],
                                             density_quantile=fc["density_quantile"],
                                             hull=crop, seed=cfg["seed"])
        source = f"laser ({fc['method']})"
        if crop is not None:
            cut = str(fuse_report.get("hull_cut", "applied"))
            source += ", cut to the hull" if cut == "applied" else f", hull cut {cut}"
    elif hull is not None:
        V, F = hull_to_mesh(hull, smooth_sigma_vox=cfg["carving"]["smooth_sigma_vox"])
        fuse_report = {"note": "no laser frames: the fused mesh is the visual hull's"}
        source = "visual hull"
    else:
        raise StageError("fusion needs aligned clouds or a hull, got neither")
    if len(F) == 0:
        raise StageError(f"fusion produced an empty mesh from {source}")
    report = {"source": source, **fuse_report, "vertices": len(V), "faces": len(F),
              "seconds": round(time.perf_counter() - t0, 3)}
    write_mesh(outputs["ply"], V, F)
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        log_mesh(rr_stream, "base/fused", V, F, albedo=[200, 200, 200, 255])
        log_report(rr_stream, "reports/fuse", report)
    write_json(outputs["report"], report)
    log.info("fused mesh from %s: %d faces (%.1f s)", source, len(F), report["seconds"])
    return report


def stage_simplify(inputs: Mapping[str, str], outputs: Mapping[str, str],
                   cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Clean and simplify the fused mesh (quadric edge collapse)."""
    from .meshio import read_mesh, write_mesh
    from .simplify import clean_mesh, simplify_mesh
    from .viz import log_mesh, log_report, rerun_log

    t0 = time.perf_counter()
    V, F = read_mesh(inputs["fused"])
    V, F, clean_report = clean_mesh(V, F)
    sc = cfg["simplify"]
    V2, F2, simp_report = simplify_mesh(V, F, target_faces=sc["target_faces"])
    haus = simp_report.get("hausdorff_max_m")
    if haus is not None and haus > sc["hausdorff_tolerance_m"]:
        log.warning("simplified mesh departs %.3f mm from the fused one, more than the "
                    "tolerance %.3f mm", haus * 1e3, sc["hausdorff_tolerance_m"] * 1e3)
    report = {"clean": clean_report, **simp_report, "faces_in": len(F), "faces_out": len(F2),
              "seconds": round(time.perf_counter() - t0, 3)}
    write_mesh(outputs["ply"], V2, F2)
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        log_mesh(rr_stream, "base/mesh", V2, F2, albedo=[230, 200, 160, 255])
        log_report(rr_stream, "reports/simplify", report)
    write_json(outputs["report"], report)
    log.info("simplified %d -> %d faces (%.1f s)", len(F), len(F2), report["seconds"])
    return report


def stage_evaluate(inputs: Mapping[str, str], outputs: Mapping[str, str],
                   cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Gather what every stage measured and, when the recording carries ground truth,
    the errors against it, into ``metrics.json``."""
    import json

    from .carving import VoxelGrid
    from .evaluate import TruthSurface, cloud_accuracy, completeness, mesh_accuracy, volume_iou
    from .meshio import read_mesh
    from .triangulation import load_clouds_npz
    from .viz import log_mesh, log_report, rerun_log

    t0 = time.perf_counter()
    rec_path = inputs["recording"]
    results_dir = Path(outputs["metrics"]).parent
    metrics: dict[str, Any] = {"recording": str(rec_path), "name": rec_name, "skipped": {}}
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
    rec = _read(rec_path, cfg, roles=(), require=False)
    mesh_bytes = rec.attachments.get("ground_truth/mesh.ply")
    ev = cfg["evaluation"]
    if mesh_bytes is None:
        metrics["skipped"]["evaluation"] = "the recording carries no ground truth"
    else:
        from .meshio import read_mesh as _read_mesh

        Vt, Ft = _read_mesh(mesh_bytes)
        truth = TruthSurface(Vt, Ft)
        region = rec.workspace
        ev_out: dict[str, Any] = {"region": None if region is None else
                                  [region[0].tolist(), region[1].tolist()]}
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
        for key in ("fused", "mesh"):
            V, F = read_mesh(inputs[key])
            ev_out[key] = {
                **mesh_accuracy(V, F, truth, n_samples=ev["n_samples"], seed=cfg["seed"]),
                "completeness": completeness(V, F, truth, thresholds_mm=ev["thresholds_mm"],
                                             n_samples=ev["n_samples"], region=region,
                                             seed=cfg["seed"]),
            }
        if inputs.get("aligned") and "ground_truth/tf.json" in rec.attachments:
            ev_out["poses"] = _pose_errors(rec, inputs)
        metrics["evaluation"] = ev_out
    metrics["evaluate_seconds"] = round(time.perf_counter() - t0, 3)
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        if mesh_bytes is not None:
            log_mesh(rr_stream, "base/ground_truth", Vt, Ft, albedo=[120, 220, 120, 90])
        log_report(rr_stream, "reports/metrics", metrics.get("evaluation", {}))
    write_json(outputs["metrics"], metrics)
    _log_summary(metrics)
    return metrics


def _pose_errors(rec, inputs: Mapping[str, str]) -> dict[str, Any]:
    """Per-sweep robot pose error before and after alignment, against ground_truth/tf.json.

    The pose of a sweep is its base->flange at the sweep's mid frame: the reported one
    (before), the reported one corrected by the alignment (after), the true one.
    """
    from .evaluate import pose_error
    from .recording.reader import read_ground_truth_tf
    from .triangulation import load_clouds_npz

    truth_tf = read_ground_truth_tf(rec)
    clouds = load_clouds_npz(inputs["clouds"])
    corrections = [np.asarray(c.report.get("correction", np.eye(4)))
                   for c in load_clouds_npz(inputs["aligned"])]
    stripes_path = Path(inputs["clouds"]).with_name("stripes.npz")
    with np.load(stripes_path) as z:
        stamps = z["stamps_ns"]
    out = []
    for k, c in enumerate(clouds):
        mid = int(np.median(c.frame_index))
        t = int(stamps[mid])
        T_rep = rec.tf.lookup(rec.base_frame, "flange", t)
        T_true = truth_tf.lookup(rec.base_frame, "flange", t)
        C = corrections[k]
        before = pose_error(T_rep, T_true)
        after = pose_error(C @ T_rep, T_true)
        out.append({"sweep": int(c.sweep), "before_mm": float(before[0]),
                    "before_deg": float(before[1]), "after_mm": float(after[0]),
                    "after_deg": float(after[1])})
    return {"per_sweep": out,
            "worst_before_mm": max(o["before_mm"] for o in out),
            "worst_after_mm": max(o["after_mm"] for o in out),
            "worst_after_deg": max(o["after_deg"] for o in out)}


def _log_summary(metrics: Mapping[str, Any]) -> None:
    ev = metrics.get("evaluation")
    if not ev:
        log.info("%s: no ground truth; skipped: %s", metrics["name"], metrics["skipped"])
        return
    parts = []
    if "hull_volume_iou" in ev:
        parts.append(f"hull IoU {ev['hull_volume_iou']:.3f}")
    m = ev["mesh"]
    parts.append(f"mesh mean {m['mean_mm']:.3f} mm, p95 {m['p95_mm']:.3f} mm")
    log.info("%s: %s", metrics["name"], "; ".join(parts))


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


def _setup_logging(log_path: str | None) -> None:
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    for h in list(root.handlers):
        root.removeHandler(h)
    err = logging.StreamHandler(sys.stderr)
    err.setFormatter(fmt)
    root.addHandler(err)
    if log_path:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(log_path, mode="w", encoding="utf-8")
        fh.setFormatter(fmt)
        root.addHandler(fh)


def run_from_snakemake(stage: str, smk: Any) -> None:
    """Run one stage from a Snakemake ``script:`` job (``smk`` is the injected object).

    A robo3d error (bad input, a stage that cannot produce its result) is logged as one
    clear line and ends the job with exit status 1, without a traceback from deep inside a
    library; Snakemake then removes the job's outputs and, with ``--keep-going``, finishes
    the other recordings.
    """
    _setup_logging(smk.log[0] if len(smk.log) else None)
    inputs = {k: str(v) for k, v in smk.input.items()}
    outputs = {k: str(v) for k, v in smk.output.items()}
    rec = smk.wildcards.get("rec", "recording")
    try:
        STAGES[stage](inputs, outputs, smk.config, rec)
    except Robo3dError as exc:
        log.error("%s failed for %s: %s", stage, rec, exc)
        logging.shutdown()
        sys.exit(1)
