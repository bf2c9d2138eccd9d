"""The ``evaluate`` stage: what every stage measured, its time and memory, and the errors
against the ground truth a recording carries, into ``metrics.json``
(:mod:`robo3d.evaluate`).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import write_json
from ..errors import Robo3dError
from .common import (
    cameras_from,
    code_version,
    environment,
    load_silhouettes,
    log,
    open_recording,
    stage_threads,
    summary,
)


def stage_evaluate(inputs: Mapping[str, str], outputs: Mapping[str, str],
                   cfg: Mapping[str, Any], rec_name: str,
                   threads: int | None = None) -> dict[str, Any]:
    """Gather what every stage measured, its time and peak memory, and, when the
    recording carries ground truth, the errors against it, into ``metrics.json`` (the
    report's pictures are rule ``pictures``', :mod:`robo3d.stages.pictures`).

    Accuracy of the fused and final meshes is scored on the surface inside the
    workspace box above ``evaluation.floor_margin_m`` over its floor (below it the mesh
    closes the face resting on the table, which no sensor sees); ``*_whole`` keeps it.
    Completeness counts the true surface inside the workspace box (a recording without
    one: the box the alignment took from the hull and the table). With true
    silhouettes attached (``ground_truth/silhouettes/NNN.png``), ``evaluation.mask_iou``
    scores each view's mask (:func:`robo3d.evaluate.silhouette_iou`). A missing or
    damaged attachment skips only what needs it (``skipped`` says why). The views the
    carve's agreement check left out are listed in ``views_left_out``. ``threads``: the
    job's, for the distances to the truth (point-wise queries: the figures do not depend
    on it).
    """
    from ..evaluate import TRUE_SILHOUETTES, open3d_threads
    from ..meshio import read_mesh

    t0 = time.perf_counter()
    rec_path = inputs["recording"]
    metrics = _stage_metrics(inputs, Path(outputs["metrics"]).parent, cfg, rec_name)
    rec = open_recording(rec_path, cfg, roles=(), require=False)
    has_true_masks = any(k.startswith(TRUE_SILHOUETTES) for k in rec.attachments)
    ev = cfg["evaluation"]
    V_final, F_final = read_mesh(inputs["mesh"])
    vertex_error_mm = None
    truth = _truth_surface(rec, rec_path, has_true_masks, metrics)
    ev_out: dict[str, Any] = {}
    if truth is not None:
        with open3d_threads(stage_threads(threads)):
            ev_out = _surface_evaluation(inputs, rec, truth, cfg, (V_final, F_final),
                                         metrics)
            vertex_error_mm = truth.distance(V_final) * 1e3
    _mask_evaluation(inputs, rec, has_true_masks, metrics, ev_out)
    if ev_out:
        metrics["evaluation"] = ev_out
    metrics["evaluate_seconds"] = round(time.perf_counter() - t0, 3)
    if "evaluate" not in metrics["timings"]:  # its own benchmark file comes after it
        metrics["timings"]["evaluate"] = {"seconds": metrics["evaluate_seconds"],
                                          "max_rss_mb": None,
                                          "source": "measured inside the job"}
        if metrics["timings"].get("total_seconds") is not None:
            metrics["timings"]["total_seconds"] += metrics["evaluate_seconds"]
    _log_rerun(outputs["rrd"], rec_name, metrics, truth, (V_final, F_final), vertex_error_mm,
               float(ev["picture_vmax_mm"]))
    write_json(outputs["metrics"], metrics)
    _log_summary(metrics)
    return metrics


def _stage_metrics(inputs: Mapping[str, str], results_dir: Path, cfg: Mapping[str, Any],
                   rec_name: str) -> dict[str, Any]:
    """The start of ``metrics.json``: the recording, the code's version, what the
    recording has no data for (``skipped``), every stage's report
    (``results/<rec>/reports/*.json``), their timings, where the surface came from and
    the views the carve left out."""
    import json

    metrics: dict[str, Any] = {"recording": str(inputs["recording"]), "name": rec_name,
                               "robo3d": code_version(), "environment": environment(),
                               "skipped": {}}
    if inputs.get("calibration"):  # config scan_calibration: not the recording's own
        from ..calibration.io import calibration_note

        metrics["calibration"] = calibration_note(inputs["calibration"])
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
        "close": fuse.get("close", cfg["fusion"]["close"]),
        "hull_contradicted": bool(fuse.get("hull_contradicted", False))}
    missing = _object_not_found(stages.get("align"))
    if missing:
        metrics["surface_sources"]["object_not_found"] = missing
    if fuse.get("laser_unusable"):  # the mesh is the views' hull: nothing measured
        metrics["surface_sources"]["laser_unusable"] = str(fuse["laser_unusable"])
    carve = stages.get("carve", {})
    if isinstance(carve, dict) and "views_left_out" in carve:
        metrics["views_left_out"] = carve["views_left_out"]
    return metrics


def _object_not_found(align: Any) -> str | None:
    """Why nothing locates the object, from ``align.json``: no workspace box, no hull of
    the views, and the laser's points stand on the table with too few above it; None
    when something does. The points are then kept as they are, and the measured surface
    is what the laser saw: the table, most likely (random scene 688, stop 59: a black
    bracket the red laser did not show and no view could segment; its mesh, the table's,
    lay 61.5 mm from the object, labelled measured and nothing else)."""
    wfh = align.get("workspace_from_hull") if isinstance(align, Mapping) else None
    laser = wfh.get("laser") if isinstance(wfh, Mapping) else None
    if not isinstance(laser, Mapping) or laser.get("object_found") is not False:
        return None
    return (f"no object found: the recording has no workspace box, no hull of its views "
            f"({wfh.get('skipped', 'none')}), and {laser.get('skipped')}: the measured "
            "surface is what the laser saw, most likely the table")


def _truth_surface(rec, rec_path: str, has_true_masks: bool, metrics: dict[str, Any]):
    """The recording's true surface (:class:`robo3d.evaluate.TruthSurface` of
    ``ground_truth/mesh.ply``), or None with ``metrics["skipped"]`` saying why."""
    from ..evaluate import TruthSurface
    from ..meshio import read_mesh

    mesh_bytes = rec.attachments.get("ground_truth/mesh.ply")
    if mesh_bytes is None and not has_true_masks:
        metrics["skipped"]["evaluation"] = "the recording carries no ground truth"
        return None
    if mesh_bytes is None:
        metrics["skipped"]["surface_evaluation"] = ("the recording carries no "
                                                    "ground_truth/mesh.ply")
        return None
    try:
        Vt, Ft = read_mesh(mesh_bytes)
        return TruthSurface(Vt, Ft)
    except (Robo3dError, ValueError, RuntimeError, OSError) as exc:
        metrics["skipped"]["surface_evaluation"] = (f"ground_truth/mesh.ply is damaged: "
                                                    f"{exc}")
        log.warning("%s: ground_truth/mesh.ply is damaged (%s): no surface evaluation",
                    rec_path, exc)
        return None


def _surface_evaluation(inputs: Mapping[str, str], rec, truth, cfg: Mapping[str, Any],
                        final_mesh: tuple[np.ndarray, np.ndarray],
                        metrics: dict[str, Any]) -> dict[str, Any]:
    """The errors against the true surface: the hull's volume IoU, the clouds' accuracy
    before and after the alignment, accuracy and completeness of the fused, final and
    measured meshes, and the sweeps' pose errors (``metrics["skipped"]["poses"]`` when
    ``ground_truth/tf.json`` is missing or cannot be used)."""
    from ..artefacts import clouds_up, clouds_workspace, load_clouds_npz
    from ..carving import level_rotation, turn_box
    from ..evaluate import cloud_accuracy, completeness, mesh_accuracy, volume_iou
    from ..grid import VoxelGrid
    from ..meshio import read_mesh

    ev = cfg["evaluation"]
    rec_path = inputs["recording"]
    ali = load_clouds_npz(inputs["aligned"]) if inputs.get("aligned") else None
    region, region_source = rec.workspace, "the recording's workspace box"
    if region is None and ali is not None:
        # no box in the recording: the one the alignment took from the hull and the table
        region = clouds_workspace(ali)
        source = next(((c.report or {}).get("workspace_source") for c in ali
                       if (c.report or {}).get("workspace_source")), "visual hull")
        region_source = ("the box of the object the laser measured (align.json "
                         "workspace_from_hull.laser)" if source == "laser" else
                         "the visual hull's box (align.json workspace_from_hull)")
    scored = None
    if region is not None:
        # the floor raised: the box's face down the base's up axis (+z unless the sensors
        # say otherwise: a ceiling robot's base has z down), in the level frame
        P = level_rotation(clouds_up(ali)[0] if ali else np.array([0.0, 0.0, 1.0]))
        lo, hi = turn_box(P, region)
        scored = turn_box(P.T, (lo + np.array([0.0, 0.0, ev["floor_margin_m"]]), hi))
    ev_out: dict[str, Any] = {
        "region": None if region is None else [region[0].tolist(), region[1].tolist()],
        "region_source": None if region is None else region_source,
        "accuracy_region": None if scored is None else [scored[0].tolist(),
                                                        scored[1].tolist()]}
    if inputs.get("hull"):
        g = VoxelGrid.load_npz(inputs["hull"])
        ev_out["hull_volume_iou"] = volume_iou(g.occupancy, g.origin, g.voxel_size, truth,
                                               region=region)
    if inputs.get("clouds") and ali is not None:
        raw = _raw_clouds(inputs["clouds"])
        ev_out["clouds"] = cloud_accuracy(np.concatenate([c.points_base for c in raw]), truth)
        ev_out["aligned"] = cloud_accuracy(np.concatenate([c.points_base for c in ali]),
                                           truth)
    thresholds = tuple(ev["thresholds_mm"])
    for key in ("fused", "mesh"):
        V, F = final_mesh if key == "mesh" else read_mesh(inputs[key])
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
    return ev_out


def _measured_evaluation(path: str, truth, ev: Mapping[str, Any], cfg: Mapping[str, Any],
                         scored, region) -> dict[str, Any]:
    """Accuracy and completeness of the measured surface alone (measured.ply): what an
    inspection tool compares with CAD. ``outlier_area_fraction_0_5mm`` is the share of its
    area farther than 0.5 mm from the truth (area-uniform samples)."""
    from ..evaluate import completeness, mesh_accuracy, sample_surface
    from ..meshio import read_mesh

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
    from ..evaluate import silhouette_iou

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
        sil = load_silhouettes(sil_path)
        cams = cameras_from(sil)
    except (OSError, ValueError, KeyError) as exc:
        metrics["skipped"]["mask_iou"] = f"{sil_path} does not load: {exc}"
        return
    masks = [sil["masks"][i, : c.height, : c.width] for i, c in enumerate(cams)]
    # a rational_polynomial camera's views were segmented rectified: so is their truth
    rects = [rec.rectifiers.get(c.frame_id) for c in cams]
    result = silhouette_iou(masks, rec.attachments,
                            rectify=rects if any(r is not None for r in rects) else None)
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
    from ..artefacts import in_clouds_workspace, load_clouds_npz
    from ..evaluate import pose_error
    from ..recording.reader import read_ground_truth_tf

    truth_tf = read_ground_truth_tf(rec)
    clouds = load_clouds_npz(inputs["clouds"])  # the margin's points too: every frame
    aligned = load_clouds_npz(inputs["aligned"])
    stripes_path = Path(inputs["clouds"]).with_name("stripes.npz")
    with np.load(stripes_path) as z:
        stamps = z["stamps_ns"]
    inside = in_clouds_workspace(clouds)
    out = []
    for k, c in enumerate(clouds):
        rep = aligned[k].report or {}
        C = np.asarray(rep.get("correction", np.eye(4)))
        mid = int(rep.get("correction_frame", int(np.median(c.frame_index))))
        t = int(stamps[mid])
        T_rep = rec.tf.lookup(rec.base_frame, "flange", t)
        T_true = truth_tf.lookup(rec.base_frame, "flange", t)
        centroid = c.points_base[inside[k]].mean(axis=0) if inside[k].any() else (
            c.points_base.mean(axis=0))

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


def _raw_clouds(path: str) -> list:
    """The triangulated clouds as scored: the points in the workspace box, not those in
    the triangulation's margin around it (``triangulation.workspace_margin_m``: kept
    for alignment to place, cropped by it)."""
    from ..artefacts import crop_clouds_to_workspace, load_clouds_npz

    clouds = load_clouds_npz(path)
    crop_clouds_to_workspace(clouds)
    return clouds


def _frame_pose_errors(rec, clouds, aligned, stamps: np.ndarray, stripes_path: Path
                       ) -> dict[str, Any]:
    """Per laser frame, when the recording carries the true pose of every image at its
    exposure (``ground_truth/image_poses.json``, written by ``robo3d simulate``): the pose
    the pipeline used for the frame (reported pose at the stamp, times the alignment's
    correction at that frame) against the truth at the moment the image was taken, so a
    late camera clock and an error that drifts within a sweep are scored as what they do
    to the points (:func:`robo3d.evaluate.frame_displacement`). A sweep's figure is its
    worst frame; ``worst_*_frame_*`` the worst sweep. Empty without that attachment."""
    from ..evaluate import frame_displacement
    from ..transforms import correction_at

    if "ground_truth/image_poses.json" not in rec.attachments:
        return {}
    try:
        from ..simulate import image_poses

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
        about = model.get("about")  # a turning sweep, corrected as a rigid body
        C[f[first]] = [correction_at(o if about is None else np.asarray(about, float), R, t)
                       for o in c.sensor_origin_base[first]]
        # the aligned cloud may have fewer points (those outside a silhouette dropped)
        fa = np.asarray(a.frame_index, dtype=np.int64)
        d0, r0 = frame_displacement(c.points_base, f, T_rep, T_true)
        sel = np.unique(f)
        sel1 = np.unique(fa)
        if len(sel1) == 0:
            continue
        d1, r1 = frame_displacement(a.points_base, fa, C @ T_rep, T_true)
        per.append({"sweep": int(c.sweep), "frames": int(len(sel)),
                    "before_mm": float(np.nanmax(d0[sel])), "before_deg": float(r0[sel].max()),
                    "after_mm": float(np.nanmax(d1[sel1])), "after_deg": float(r1[sel1].max()),
                    "after_median_mm": float(np.nanmedian(d1[sel1]))})
    if not per:
        return {}
    return {"per_sweep_frames": per,
            "truth_frames": "true camera pose at each laser image's exposure",
            **{f"worst_{k}_frame_{u}": max(p[f"{k}_{u}"] for p in per)
               for k in ("before", "after") for u in ("mm", "deg")}}


def _displacement_mm(T_est: np.ndarray, T_true: np.ndarray, point: np.ndarray) -> float:
    """How far a pose error ``T_est`` (vs ``T_true``) moves ``point`` (base), mm."""
    from ..transforms import invert_transform

    D = T_est @ invert_transform(T_true)
    return float(np.linalg.norm(D[:3, :3] @ point + D[:3, 3] - point) * 1e3)


def _log_rerun(rrd: str, rec_name: str, metrics: dict[str, Any], truth, final: tuple,
               vertex_error_mm: np.ndarray | None, vmax_mm: float) -> None:
    """To rerun: the ground truth (``base/evaluate/ground_truth``), the final mesh coloured
    by its distance to it (``base/evaluate/mesh_error``, blue 0 to red ``vmax_mm``), each
    sweep's pose error after alignment on the ``sweep`` timeline, and the scan's key
    figures as a short text (``reports/summary``)."""
    from ..render import colormap
    from ..viz import (
        log_mesh,
        log_scalar,
        log_text,
        rerun_log,
        scan_summary_markdown,
        set_image_time,
    )

    with rerun_log(rrd, rec_name) as rr_stream:
        if truth is not None:
            log_mesh(rr_stream, "base/evaluate/ground_truth", truth.vertices, truth.faces,
                     albedo=[120, 220, 120, 90])
        if vertex_error_mm is not None:
            colours = (colormap(vertex_error_mm, vmax_mm) * 255).round().astype(np.uint8)
            log_mesh(rr_stream, "base/evaluate/mesh_error", *final, vertex_colors=colours)
        poses = (metrics.get("evaluation", {}).get("poses", {}) or {}).get("per_sweep", [])
        for row in poses or []:
            set_image_time(rr_stream, sweep=int(row["sweep"]))
            for key in ("before_mm", "after_mm"):
                if row.get(key) is not None:
                    log_scalar(rr_stream, f"metrics/evaluate/pose_error_{key}", row[key])
        log_text(rr_stream, "reports/summary", scan_summary_markdown(
            rec_name, metrics, error_vmax_mm=vmax_mm if vertex_error_mm is not None else None))


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
    missing = (metrics.get("surface_sources") or {}).get("object_not_found")
    if missing:
        parts.append(str(missing))
    if (metrics.get("surface_sources") or {}).get("laser_unusable"):
        parts.append("the laser measured nothing usable on the object: the mesh is the "
                     "visual hull's")
    if metrics.get("skipped"):
        parts.append("skipped: " + "; ".join(f"{k} ({v})" for k, v in metrics["skipped"].items()))
    summary.info("%s", "; ".join(parts))
