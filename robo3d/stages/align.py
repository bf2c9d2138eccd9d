"""The ``align`` stage: sweep poses refined by ICP, a pose graph and a joint refinement against
the silhouettes (:mod:`robo3d.registration`), then the aligned points tested against the
silhouettes.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..atomic import write_json
from .common import log, silhouette_views, stage_threads, summary, sweep_color


def stage_align(inputs: Mapping[str, str], outputs: Mapping[str, str],
                cfg: Mapping[str, Any], rec_name: str, threads: int | None = None
                ) -> dict[str, Any]:
    """Refine each sweep's pose (seed §2.3): pairwise ICP and a pose graph, then a joint
    refinement against the neighbours and, when the recording has views, the
    silhouettes as absolute reference (:func:`robo3d.registration.align_sweeps`).

    Inputs: ``clouds``; optional ``silhouettes`` (silhouettes.npz) with ``recording``
    (the views' grey images). ``threads``: the job's (pairs and views in parallel; the
    result does not depend on it). Each aligned cloud's report keeps ``correction``: the rigid
    ``base`` transform applied at the sweep's middle frame (what corrects the robot's
    pose there), and ``correction_model`` (rotation, translation of
    :func:`robo3d.registration.apply_correction`).
    """
    from ..artefacts import in_clouds_workspace, load_clouds_npz, save_clouds_npz
    from ..meshio import write_point_cloud
    from ..registration import AlignOptions, align_sweeps
    from ..viz import log_points, log_report, rerun_log

    t0 = time.perf_counter()
    clouds = load_clouds_npz(inputs["clouds"])
    ac = cfg["alignment"]
    hull_ws = _workspace_from_hull(clouds, inputs, cfg)
    if hull_ws is not None and "skipped" in hull_ws and "laser" not in hull_ws:
        # no views, or no hull from them
        hull_ws = {**hull_ws, "laser": _workspace_from_laser(clouds, cfg)}
    centres = _turning_centres(clouds, float(ac["rigid_turn_deg"]))
    views = None
    if ac["enabled"] and ac["refine"] and ac["silhouettes"] and inputs.get("silhouettes"):
        views = silhouette_views(inputs, cfg)
    # one sweep is aligned when there are views: they alone correct its robot error
    # (the twelve one-sweep random scenes with views: measured median 0.15-0.92 ->
    # 0.03-0.20 mm on seven, a box 0.47 -> 0.54 mm, the others kept at the robot's
    # pose: no contour residual, or registration._unconfirmed_by_views; stop 36)
    if ac["enabled"] and (len(clouds) > 1 or views is not None):
        # the points in the triangulation's margin around the box (the table, mostly) are
        # placed by the corrections but do not drive them. The table inside the box
        # (artefacts.table_points) does: it is rigid with the object, and without it
        # bracket/4 of the objects benchmark (a flat plate on the table) went from 0.136
        # to 0.262 mm (thin_wall/7 from 0.289 to 0.230; stop 35)
        reg = in_clouds_workspace(clouds)
        # a sweep whose camera turned (a turntable's revolution, a robot's arc) is
        # corrected as a rigid body about its centre, not as a sensor turned about its
        # position at each frame (the model of a straight sweep's robot error)
        sub = [(c.points_base[m], c.normals_base[m],
                c.sensor_origin_base[m] if centres[k] is None
                else np.broadcast_to(centres[k], c.points_base[m].shape),
                c.frame_index[m]) for k, (c, m) in enumerate(zip(clouds, reg, strict=True))]
        opts = AlignOptions.from_config(ac, seed=cfg["seed"], threads=stage_threads(threads))
        result = align_sweeps([s[0] for s in sub], [s[1] for s in sub], options=opts,
                              origins=[s[2] for s in sub], profiles=[s[3] for s in sub],
                              silhouettes=views)
        align_report = {"workspace_from_hull": hull_ws,
                        "method": result.method, "gauge": result.gauge,
                        "points_in_margin_not_registered": int(sum(
                            len(m) - int(m.sum()) for m in reg)),
                        "reference": result.reference, "pairs": result.pairs,
                        "per_sweep": result.per_sweep, "refinement": result.refinement,
                        "n_views_used": 0 if views is None else len(views.cameras)}
    else:
        result = None
        align_report = {"workspace_from_hull": hull_ws,
                        "skipped": "alignment disabled in the config" if not ac["enabled"]
                        else "a single sweep and no views: nothing to align it to"}
    corrections = _apply_corrections(clouds, result, centres)
    if result is None and ac["enabled"]:  # one sweep, no views: nothing checked it
        align_report["per_sweep"] = _lone_sweep_flagged(clouds)
    ws_check = _crop_to_workspace(clouds)
    hull_check, rejected = _reject_outside_hull(clouds, views, inputs, ac)
    skew_check, skewed = _drop_skewed(clouds, ac)
    report = {"n_sweeps": len(clouds), **align_report,
              "corrections": [C.tolist() for C in corrections],
              "outside_workspace": ws_check,
              "outside_hull": hull_check,
              "skewed_centres": skew_check,
              "seconds": round(time.perf_counter() - t0, 3)}
    save_clouds_npz(outputs["npz"], clouds)
    write_point_cloud(outputs["ply"], np.concatenate([c.points_base for c in clouds]),
                      normals=np.concatenate([c.normals_base for c in clouds]),
                      attributes={"sweep": np.concatenate([np.full(len(c.points_base), c.sweep)
                                                           for c in clouds]).astype(np.int32)})
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        for c in clouds:  # each sweep in its colour (the legend: reports/summary)
            log_points(rr_stream, f"base/align/sweep_{c.sweep:02d}", c.points_base,
                       colors=sweep_color(c.sweep))
        if len(rejected):  # dropped: outside a view's silhouette
            log_points(rr_stream, "base/align/rejected", rejected, colors=[255, 0, 255])
        if len(skewed):  # dropped: the stripe's centre pulled off it
            log_points(rr_stream, "base/align/skewed", skewed, colors=[255, 140, 0])
        log_report(rr_stream, "reports/align", report)
    write_json(outputs["report"], report)
    flagged = [p["sweep"] for p in align_report.get("per_sweep", []) if p.get("flagged")]
    starts = (align_report.get("refinement") or {}).get("starts")
    summary.info("aligned %d sweeps (gauge: %s, %.1f s)%s%s", len(clouds),
                 align_report.get("gauge", "-"), report["seconds"],
                 f"; flagged and kept at the robot's pose: {flagged}" if flagged else "",
                 "" if not starts else (
                     f"; refined from the {starts['taken'].replace('_', ' ')}'s start "
                     f"(silhouette RMS {_px(starts['pose_graph_rim_rms_px'])} px from the "
                     f"pose graph's, {_px(starts['robot_rim_rms_px'])} px from the robot's)"))
    return report


def _apply_corrections(clouds: list, result, centres: list) -> list[np.ndarray]:
    """Correct each cloud in place (points, sensor origins, normals) by the alignment's
    result (None: no alignment, the identity), keep the correction in its report
    (``correction`` at the sweep's middle frame, ``correction_model``, ``flagged``), and
    return the corrections at the middle frames. A turning sweep (``centres[k]`` not
    None) is corrected as a rigid body about its centre (:func:`_turning_centres`)."""
    from ..registration import apply_correction
    from ..transforms import correction_at

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
        about = None
        if result is not None and result.rotations is None:
            p, o, n = result.apply(k, c.points_base, c.sensor_origin_base, c.normals_base)
        elif centres[k] is not None:  # a turning sweep: rigid about its centre
            about = centres[k]
            at = np.broadcast_to(about, c.points_base.shape)
            p, _, n = apply_correction(c.points_base, at, rot, tr, c.normals_base)
            o = apply_correction(c.sensor_origin_base,
                                 np.broadcast_to(about, c.sensor_origin_base.shape), rot,
                                 tr)[0]
            o_mid = about
        else:
            p, o, n = apply_correction(c.points_base, c.sensor_origin_base, rot, tr,
                                       c.normals_base)
        C_mid = correction_at(o_mid, rot, tr)
        corrections.append(C_mid)
        c.report = {**(c.report or {}), "correction": C_mid.tolist(), "correction_frame": mid,
                    "correction_model": {"rotation": np.asarray(rot).tolist(),
                                         "translation": np.asarray(tr).tolist(),
                                         **({} if about is None else
                                            {"about": np.asarray(about).tolist()})}}
        if result is not None and k < len(result.per_sweep or []):
            # kept at the robot's pose, checked against no other sweep or view: fusion
            # labels the surface it measured (``flagged_sweep``)
            c.report["flagged"] = bool(result.per_sweep[k].get("flagged"))
        c.points_base, c.sensor_origin_base, c.normals_base = p, o, n
    return corrections


def _lone_sweep_flagged(clouds: list) -> list[dict[str, Any]]:
    """A single sweep without views rests on the robot's poses alone, as a sweep that the
    alignment flags does (kept at the robot's pose, checked against no other sweep or
    view): flagged in its cloud's report, so that fusion labels the surface it measured
    (``flagged_sweep``), and in the align report's ``per_sweep``.

    Why: with views, such a sweep is refined against them or flagged ("no other sweep
    left to align with"); without, the alignment was skipped and nothing said so. Random
    scene 148 (a blue laser read as red off an orange checker, one sweep, no views):
    measured median 20 mm, labelled measured with nothing flagged."""
    reason = "a single sweep and no views: its robot pose is checked by nothing"
    for c in clouds:
        c.report = {**(c.report or {}), "flagged": True}
    return [{"sweep": c.sweep, "n_points": len(c), "translation_mm": 0.0, "rotation_deg": 0.0,
             "converged": False, "flagged": True, "reason": reason} for c in clouds]


def _turning_centres(clouds: list, max_turn_deg: float) -> list[np.ndarray | None]:
    """Per sweep, the centre about which its correction turns it as a rigid body (the
    centroid of its points) when its camera turned by more than ``max_turn_deg`` during
    it (``sensor_turn_deg`` of the triangulation's report: a turntable's revolution, a
    robot's arc), else None (the sensor turned about its position at each frame).

    Why: the refinement's motion model, ``x' = R (x - o) + o + t``, is a constant pose
    error in the sensor's frame for a sweep that translates without turning. On a
    turntable's revolution it fits neither the turntable's error (its angle read off,
    the object nudged on its plate: rigid in ``base``) nor anything else, and the views'
    silhouettes pulled the revolutions off: a simulated two-revolution blob, worst sweep
    0.37 -> 0.56 mm (``benchmarks/README.md``, stop 52)."""
    out: list[np.ndarray | None] = []
    for c in clouds:
        turn = float((c.report or {}).get("sensor_turn_deg") or 0.0)
        if turn > max_turn_deg and len(c.points_base):
            out.append(np.asarray(c.points_base, dtype=np.float64).mean(axis=0))
        else:
            out.append(None)
    return out


def _px(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def _workspace_from_hull(clouds: list, inputs: Mapping[str, str],
                         cfg: Mapping[str, Any]) -> dict[str, Any] | None:
    """A recording without a workspace box, with views: the visual hull's box
    (:func:`robo3d.carving.hull_box`, grown by ``alignment.workspace_from_hull_margin``,
    at least ``triangulation.workspace_margin_m``) becomes the clouds' workspace (each
    report's ``workspace``, ``workspace_source: "visual hull"``), so that the laser
    points outside it do not drive the alignment and are dropped after it, as with a
    recording's own box. What it was, or why there is none; None when the recording has
    a box.

    Why: a ROS bag carries no box. On a small simulated room-lit cell (a blob on a marker
    table before a wall, 3 sweeps) the laser's line on the table and the wall was 77 % of
    the points; the silhouettes' test would drop them, but so many points outside the
    hull read as silhouettes that contradict the laser, so none was dropped: the table
    became measured surface, the measured surface's median 33.6 mm from the truth
    (0.24 mm with the recording's box; ``benchmarks/README.md``, stop 40).

    A hull whose views disagree with each other (:func:`_hull_views_disagree`), whose box
    holds little of the object the laser found (:func:`_laser_object_outside_hull`), or
    whose top lies under the table the laser saw, does not place it when the laser finds
    its own object (:func:`_workspace_from_laser`)."""
    from ..artefacts import clouds_up, clouds_workspace
    from ..carving import (
        TABLE_MAX_SHARE_UNDER,
        VoxelGrid,
        hull_box,
        level_rotation,
        share_under,
        support_height,
        table_height,
        turn_box,
    )

    if clouds_workspace(clouds) is not None:
        return None
    ac = cfg["alignment"]
    if not ac["workspace_from_hull"]:
        return {"skipped": "alignment.workspace_from_hull is false"}
    if not inputs.get("hull"):
        return {"skipped": "no views: no hull"}
    margin_m = float(cfg["triangulation"]["workspace_margin_m"])
    hull, extra = VoxelGrid.load_npz(inputs["hull"], return_extra=True)
    box = hull_box(hull, margin=float(ac["workspace_from_hull_margin"]), min_margin_m=margin_m)
    if box is None:
        return {"skipped": "the hull is empty"}
    disagree = _hull_views_disagree(clouds, extra, cfg)
    if disagree is not None and "laser" in disagree:
        return disagree
    elsewhere = _laser_object_outside_hull(clouds, box, cfg)
    if elsewhere is not None and "laser" in elsewhere:
        return elsewhere
    # the floor: where no view sees under the object the hull runs below the table, and
    # closing the surface from it would add a skirt down there; the table the laser saw
    # beside the box is the floor, as a recording's box has it (half a millimetre up)
    # heights along the base's up axis (a ceiling robot's base has z down)
    up, up_report = clouds_up(clouds)
    P = level_rotation(up)
    pts = np.concatenate([c.points_base for c in clouds]) @ P.T
    nrm = np.concatenate([c.normals_base for c in clouds]) @ P.T
    lvl = turn_box(P, box)
    table = table_height(pts, nrm, lvl[0], lvl[1])
    beside = "from the laser points beside the box"
    if table is None:  # no point beside a box as wide as the scene (bad masks): the
        # lowest wide horizontal surface the laser saw (random scene 466 of stop 52: the
        # table fused as measured surface, 23.9 mm from the object at the median)
        table = support_height(pts, nrm)
        beside = "the lowest wide horizontal surface the laser saw"
    under = None
    if table is not None and lvl[1][2] <= table + margin_m:
        # a hull whose top lies under the table the laser saw holds no object standing
        # on it: masks that took the table's pattern carve under it (random scene 968: a
        # white torus on a marker table, 3 views of IoU 0.02, 0.86 and 0.08; the hull's
        # box, 11 mm under the table, cropped 35,251 of the 39,692 points away, the
        # object's among them: measured surface 3.6 mm from the truth at the median)
        why = (f"the visual hull lies under the table the laser saw (its top "
               f"{lvl[1][2]:.4f} m, the table {table:.4f} m, along {up_report['up']})")
        under = _laser_instead_of_hull(clouds, cfg, why)
        if "laser" in under:
            return under
    floor = "the hull's"
    # the table in the hull box's lower half, or anywhere in it with nothing of the
    # object's sides under it (masks that took the table in carve a hull far below it:
    # random scene 602, a box from 144 mm under the table to 126 mm over it, the table's
    # points above the hull's floor fused as measured surface, 4.8 mm off at the median)
    if table is not None and lvl[0][2] < table and (
            table < 0.5 * (lvl[0][2] + lvl[1][2])
            or share_under(pts, nrm, table) <= TABLE_MAX_SHARE_UNDER):
        box = turn_box(P.T, (np.array([lvl[0][0], lvl[0][1], table + 0.0005]), lvl[1]))
        floor = f"the table's ({up_report['up']} = {table:.4f} m, {beside})"
    for c in clouds:
        c.report = {**(c.report or {}), "workspace": [box[0].tolist(), box[1].tolist()],
                    "workspace_source": "visual hull", "workspace_margin_m": margin_m}
    log.info("alignment: the recording has no workspace box; the visual hull's, %s .. %s m "
             "(floor: %s), takes its place", np.round(box[0], 4).tolist(),
             np.round(box[1], 4).tolist(), floor)
    return {"box_min": box[0].tolist(), "box_max": box[1].tolist(), "floor": floor,
            "table_z_m": table, "margin": float(ac["workspace_from_hull_margin"]),
            "min_margin_m": margin_m, "up": up_report,
            **({"views_disagree": disagree} if disagree is not None else {}),
            **({"laser_object_outside": elsewhere} if elsewhere is not None else {}),
            **({"hull_under_table": under} if under is not None else {})}


def _hull_views_disagree(clouds: list, extra: Mapping[str, Any], cfg: Mapping[str, Any]
                         ) -> dict[str, Any] | None:
    """None when the views that carved the hull agree with each other well enough to
    place the workspace (the median of their IoUs with the other views' hull, from the
    carve's agreement check, ``hull.npz`` ``views_agreement``, at least
    ``alignment.hull_box_views_disagree_iou``), or when that was not measured (fewer than
    three of them, an older hull). Otherwise what the laser gives instead: with
    ``laser`` (the laser's own box, :func:`_workspace_from_laser`) and ``skipped`` when
    it found the object, else only the views' agreement (the hull's box is kept: there is
    nothing better).

    Why: masks that failed in most views can still carve a hull, a few hundred voxels
    where no object is. Its box then cropped the laser's object away and kept the table
    as measured surface (random scenes 463 and 546: a black torus and a blob on a marker
    table, median IoU of the views used 0.05; measured surface 8.7 and 36.1 mm from the
    truth, 0.21 and 0.48 mm when the carve had left no hull and the laser's box took its
    place). Scenes whose masks are right score 0.57-0.94 (``benchmarks/README.md``,
    stop 57)."""
    agree = (extra.get("views_agreement") or {}).get("iou_median")
    limit = cfg["alignment"]["hull_box_views_disagree_iou"]
    if agree is None or limit is None or float(agree) >= float(limit):
        return None
    why = (f"the views that carved the hull disagree with each other (median IoU "
           f"{float(agree):.2f} with the others' hull, below "
           f"alignment.hull_box_views_disagree_iou {float(limit):.2f})")
    return {"views_iou_median": float(agree), "limit": float(limit),
            **_laser_instead_of_hull(clouds, cfg, why)}


def _laser_object_outside_hull(clouds: list, box: tuple[np.ndarray, np.ndarray],
                               cfg: Mapping[str, Any]) -> dict[str, Any] | None:
    """None when the hull's ``box`` (base frame) holds at least
    ``alignment.hull_box_min_laser_share`` of the points in the box of the object the laser
    found (:func:`robo3d.artefacts.clouds_laser_box`), or when the laser found none (it
    lit only the table: the hull is all there is) or the share is not asked for. Otherwise
    what the laser gives instead (:func:`_laser_instead_of_hull`), with the share.

    Why: masks wrong in most views carve a hull where no object is, and when few views
    carved it (fewer than three: the views' agreement, :func:`_hull_views_disagree`, is not
    measured) or those few agree with each other, nothing else says so. Random scene
    1118 (a black striped blob on a table printed with black markers, six views): a hull
    from three views of IoU 0.04 against the truth, whose box held 56 of the 2,226 points
    of the laser's object and cropped 19,030 of 19,193 laser points away; fusion then had
    nothing to make a surface of (``benchmarks/README.md``, stop 69)."""
    from ..artefacts import clouds_laser_box

    share = cfg["alignment"]["hull_box_min_laser_share"]
    if share is None or not cfg["alignment"]["workspace_from_laser"]:
        return None
    got = clouds_laser_box(clouds, margin=float(cfg["alignment"]["workspace_from_hull_margin"]),
                           min_margin_m=float(cfg["triangulation"]["workspace_margin_m"]))
    if got is None:
        return None
    lo, hi, _, P = got
    pts = np.concatenate([c.points_base for c in clouds])
    level = pts @ P.T
    of_laser = np.all((level >= lo) & (level <= hi), axis=1)
    n = int(np.count_nonzero(of_laser))
    held = int(np.count_nonzero(of_laser & np.all((pts >= box[0]) & (pts <= box[1]), axis=1)))
    if n == 0 or held >= float(share) * n:
        return None
    why = (f"the visual hull's box holds {held} of the {n} points of the object the laser "
           f"measured (less than alignment.hull_box_min_laser_share {float(share):g})")
    return {"laser_points": n, "in_hull_box": held, "min_share": float(share),
            **_laser_instead_of_hull(clouds, cfg, why, got)}


def _laser_instead_of_hull(clouds: list, cfg: Mapping[str, Any], why: str,
                           got: tuple | None = None) -> dict[str, Any]:
    """The box of the object the laser measured (:func:`_workspace_from_laser`) in place
    of a hull that cannot place the workspace (``why``): ``skipped`` (why, and that the
    laser's box is the workspace) and ``laser`` when the laser found the object; else
    ``hull_kept`` (why it could not) and ``laser_skipped`` (why the laser gives no box),
    and the hull's box is kept: there is nothing better. ``got``: the laser's box, when
    the caller found it already (:func:`_workspace_from_laser`)."""
    laser = _workspace_from_laser(clouds, cfg, got)
    if "skipped" in laser:
        log.warning("alignment: %s, but the laser gives no box of its own (%s): the "
                    "hull's box is kept", why, laser["skipped"])
        return {"hull_kept": why, "laser_skipped": laser["skipped"]}
    log.warning("alignment: %s: the box of the object the laser measured is the "
                "workspace, not the hull's", why)
    return {"skipped": f"{why}: the laser's own box is the workspace", "laser": laser}


def _workspace_from_laser(clouds: list, cfg: Mapping[str, Any], got: tuple | None = None
                          ) -> dict[str, Any]:
    """A recording without a workspace box and without views (laser frames alone, a ROS
    bag of a laser cell), or whose views gave no hull (too few could be segmented): the
    box of the object the laser measured, standing on the table
    it measured beside it (:func:`robo3d.carving.laser_box`), becomes the clouds'
    workspace (``workspace_source: "laser"``), as the hull's does with views. What it
    was, or why there is none. ``got``: :func:`robo3d.artefacts.clouds_laser_box`'s
    result with this config's margins, when the caller found it already.

    Why: without it every laser point was kept, the table and the wall with the object.
    A small simulated room-lit cell (a blob on a marker table, 3 sweeps, no views): the
    final mesh 30.4 mm from the truth at the median, 100 % of it labelled measured
    (``benchmarks/README.md``, stop 52)."""
    from ..artefacts import clouds_laser_box
    from ..carving import turn_box

    ac = cfg["alignment"]
    if not ac["workspace_from_laser"]:
        return {"skipped": "alignment.workspace_from_laser is false"}
    margin_m = float(cfg["triangulation"]["workspace_margin_m"])
    if got is None:
        got = clouds_laser_box(clouds, margin=float(ac["workspace_from_hull_margin"]),
                               min_margin_m=margin_m)
    if got is None:
        return {"skipped": "too few laser points above the table to find the object",
                "object_found": False}
    lo, hi, info, P = got
    up_report = info["up"]
    lo, hi = turn_box(P.T, (lo, hi))
    for c in clouds:
        c.report = {**(c.report or {}), "workspace": [lo.tolist(), hi.tolist()],
                    "workspace_source": "laser", "workspace_margin_m": margin_m}
    floor = (f"the table's ({up_report['up']} = {info['table_z_m']:.4f} m)"
             if info["table_z_m"] is not None else "the object's lowest point (no table seen)")
    log.warning("alignment: the recording has no workspace box, nor do its views give "
                "one; the box of the object the laser measured, %s .. %s m (floor: %s; %d "
                "of %d points above the table in it), takes its place: points outside it "
                "are dropped",
                np.round(lo, 4).tolist(), np.round(hi, 4).tolist(), floor,
                info["object_points"], info["candidates"])
    return {"box_min": lo.tolist(), "box_max": hi.tolist(), "floor": floor,
            "margin": float(ac["workspace_from_hull_margin"]), "min_margin_m": margin_m,
            **info}


def _crop_to_workspace(clouds: list) -> dict[str, Any]:
    """Drop the aligned points outside the workspace box (in place; the box is in each
    cloud's report, ``workspace``).

    The triangulation places each sweep with the robot's reported poses and crops to the
    box grown by ``triangulation.workspace_margin_m``: a pose error moves the object's
    points across the box's faces (bracket/4 of the objects benchmark: its foot up to
    1.4 mm below the floor) and the table's into it. Once the sweep is corrected the
    exact box applies. Table points left in became measured surface on the table (the
    objects benchmark's user_mesh/7: 0.7 % of measured.ply's area, 0.5-1.5 mm from the
    object). Returns the report (per sweep: points dropped)."""
    from ..artefacts import clouds_workspace, crop_clouds_to_workspace

    box = clouds_workspace(clouds)
    if box is None:
        return {"skipped": "the clouds were not cropped to a workspace box"}
    lo, hi = box
    points = [len(c.points_base) for c in clouds]
    per_sweep = [{"sweep": c.sweep, "points": n, "dropped": d} for c, n, d in
                 zip(clouds, points, crop_clouds_to_workspace(clouds), strict=True)]
    n = sum(p["dropped"] for p in per_sweep)
    if n:
        log.info("alignment: %d aligned laser points lie outside the workspace box "
                 "(the table below its floor, mostly): dropped", n)
    return {"box_min": lo.tolist(), "box_max": hi.tolist(), "dropped": int(n),
            "per_sweep": per_sweep}


def _drop_skewed(clouds: list, ac: Mapping[str, Any]) -> tuple[dict[str, Any], np.ndarray]:
    """Drop the aligned points whose stripe centre lies more than
    ``max_centre_skew_px`` from its profile's top (in place; 0 keeps them all).

    A stripe's centre of gravity lies at the middle of its profile's top however wide or
    saturated the stripe (:attr:`robo3d.stripes.StripePoints.skew_px`); one that does
    not was pulled off the stripe by what lies beside it: a faint stripe along an edge
    above a face lit as brightly in the laser's channel (the blue cell's block), a
    square's edge beside the stripe on a checkerboard, a reflection merging into it. On
    the front-end benchmark's cells (exact poses) the points more than 1 mm from the
    truth have a median skew of 1.5-2.4 px, the points within 0.3 mm a 99th percentile
    of 0.6-0.7 px: the test at 2 px takes the share of points more than 1 mm off from
    0.654 to 0.428 % (blue) and 0.471 to 0.309 % (red), 0.3-0.4 % of the points in all;
    the objects benchmark's grey objects lose at most 5 points a run
    (``benchmarks/README.md``, stop 32). It runs after the alignment, on the delivered
    points only: the alignment's silhouette term uses the grazing profiles' outermost
    points, and a test before it moved the alignment (the width test, stop 31).

    The skew is taken from the recording's median skew, so that a laser whose profile is
    lopsided everywhere (a side lobe, a colour fringe) shifts every centre alike and
    loses none; and when more than ``max_centre_skew_fraction`` of the points would go,
    the test does not describe this recording's stripes: none is dropped, and the
    report says so (``not_applied``).

    Returns the report (per sweep: points dropped) and the dropped points."""
    from ..stripes import skewed_centres

    limit = float(ac["max_centre_skew_px"])
    if limit <= 0:
        return {"skipped": "alignment.max_centre_skew_px is 0"}, np.zeros((0, 3))
    if any(c.skew_px is None for c in clouds):
        return ({"skipped": "the clouds do not hold their stripe centres' skew (written by "
                 "an older robo3d)"}, np.zeros((0, 3)))
    n_all = sum(len(c) for c in clouds)
    skews = np.concatenate([c.skew_px for c in clouds]) if clouds else np.zeros(0)
    if not np.isfinite(skews).any():
        return {"skipped": "no point's skew is known"}, np.zeros((0, 3))
    cap = float(ac["max_centre_skew_fraction"])
    bad, centre, applied = skewed_centres(skews, limit, cap)
    would = int(np.count_nonzero(np.abs(skews - centre) > limit))
    report: dict[str, Any] = {"max_skew_px": limit, "median_skew_px": round(centre, 4),
                              "would_drop_fraction": round(would / n_all, 6) if n_all else 0.0}
    if not applied:
        log.warning("alignment: %.1f %% of the laser points come from stripe centres more "
                    "than %.1f px off their profile's top (more than "
                    "alignment.max_centre_skew_fraction, %.0f %%): the stripe's profile is "
                    "lopsided throughout, not pulled off locally; every point is kept",
                    100.0 * would / n_all, limit, 100.0 * cap)
        return {**report, "not_applied": True, "dropped": 0}, np.zeros((0, 3))
    starts = np.cumsum([0] + [len(c) for c in clouds])
    parts = [bad[starts[k]:starts[k + 1]] for k in range(len(clouds))]
    dropped = [c.points_base[b] for c, b in zip(clouds, parts, strict=True)]
    per_sweep = [{"sweep": c.sweep, "points": len(c), "dropped": c.drop(b, "skewed_centre")}
                 for c, b in zip(clouds, parts, strict=True)]
    n = int(bad.sum())
    if n:
        log.info("alignment: %d laser points (%.2f %%) came from stripe centres more than "
                 "%.1f px off their profile's top (pulled off the stripe): dropped", n,
                 100.0 * n / max(n_all, 1), limit)
    return ({**report, "not_applied": False, "dropped": n, "per_sweep": per_sweep},
            np.concatenate(dropped) if dropped else np.zeros((0, 3)))


def _above_floor(clouds: list, pts: np.ndarray) -> np.ndarray:
    """Which of the clouds' points ``pts`` lie above the workspace box's floor by more
    than the triangulation's margin (``workspace_margin_m``, 2 mm when not reported): not
    the table; all of them without a box."""
    from ..artefacts import clouds_floor

    floor = clouds_floor(clouds)
    if floor is None:
        return np.ones(len(pts), bool)
    up, height = floor
    margin = max([float((c.report or {}).get("workspace_margin_m", 0.002)) for c in clouds]
                 or [0.002])
    return pts @ up > height + margin


def _silhouette_flags(path: str) -> tuple[np.ndarray | None, list[int]]:
    """From ``silhouettes.npz``: the views the QA flagged (None in older files) and the
    views segmented again from the laser's points (``laser_seeded``)."""
    with np.load(path) as z:
        qa = z["qa_flagged"].astype(bool) if "qa_flagged" in z.files else None
        seeded = (np.flatnonzero(z["laser_seeded"]).tolist() if "laser_seeded" in z.files
                  else [])
    return qa, seeded


def _laser_seeded_skip(seeded: list[int], n_all: int) -> dict[str, Any]:
    """The report of the silhouette test skipped because views were segmented again from
    the laser's points (their first masks left many outside): the views proved unable to
    judge the laser in this recording (their other masks are as doubtful), as when they
    contradict it as a whole."""
    return {"skipped": f"{len(seeded)} view(s) were segmented again from the laser's "
                       "points, which their first masks contradicted: the silhouettes do "
                       "not judge the laser here; none is dropped",
            "laser_seeded_views": seeded, "dropped": 0, "points": n_all}


def _views_agreement(clouds: list, views, idx: list[int], resolution: int
                     ) -> dict[str, Any] | None:
    """How well the views ``idx`` agree with each other: each mask against the hull of
    the others (:func:`robo3d.carving.view_agreement`, leave one out, on a grid of
    ``resolution`` voxels along the clouds' workspace box's longest side; the carve's
    agreement check): ``iou_median``, ``iou_min`` and ``per_view``. None without a box, with fewer
    than three views (two views' cones bound nothing of each other) or ``resolution`` 0.

    Why: masks wrong in every view (specks, holes where the object has the background's
    colours) disagree (median IoU 0.0-0.3), while right masks agree (0.83-0.92), also
    when the laser's points are what is wrong (random scene 379: a blue laser on an orange
    checker torus whose stripe lies on the table beside the box; the detector took 162
    points from the checker's edges, 10 mm off, 92 % outside the masks of IoU 0.94)."""
    from ..artefacts import clouds_workspace
    from ..carving import CarveOptions, make_grid, view_agreement

    box = clouds_workspace(clouds)
    if box is None or len(idx) < 3 or int(resolution) <= 0:
        return None
    grid = make_grid(box[0], box[1], resolution=int(resolution))
    rows = view_agreement(grid, [views.masks[i] for i in idx],
                          [views.cameras[i] for i in idx], views.T_base_camera[idx],
                          carve=CarveOptions(min_views_in_image=1))
    ious = [float(r["iou"]) if r["iou"] is not None else 0.0 for r in rows]
    return {"iou_median": float(np.median(ious)), "iou_min": float(min(ious)),
            "per_view": [{"view": int(idx[j]), "iou": round(v, 4)}
                         for j, v in enumerate(ious)],
            "resolution": int(resolution), "overrules": False}


def _contradicted(would: float, disputed: float, ac: Mapping[str, Any]) -> dict[str, Any]:
    """Said (a warning) and reported: the silhouettes contradict the laser, which is kept
    whole; ``would`` and ``disputed``: the shares of the points they would drop, and
    that fewer than half of the views would."""
    log.warning("alignment: the silhouettes would drop %.1f %% of the laser points, %.1f %% "
                "outside fewer than half of the views (limits "
                "alignment.outside_hull_max_fraction %.0f %%, outside_hull_max_total_fraction "
                "%.0f %%): they contradict the laser, which is kept whole; the masks are "
                "likely wrong (see pictures/masks.png)", 100 * would, 100 * disputed,
                100 * float(ac["outside_hull_max_fraction"]),
                100 * float(ac["outside_hull_max_total_fraction"]))
    return {"skipped": "the silhouettes contradict the laser: they would drop "
                       f"{100 * would:.1f} % of the laser points, {100 * disputed:.1f} % "
                       "outside fewer than half of the views (more than "
                       "alignment.outside_hull_max_fraction, or more than "
                       "outside_hull_max_total_fraction above the floor); none is dropped",
            "contradicted": True, "would_drop_fraction": would,
            "max_fraction": float(ac["outside_hull_max_fraction"]),
            "max_total_fraction": float(ac["outside_hull_max_total_fraction"])}


def _views_overrule(clouds: list, views, idx: list[int], ac: Mapping[str, Any],
                    would: float, disputed: float) -> dict[str, Any] | None:
    """The views' agreement (:func:`_views_agreement`) where the silhouettes would
    contradict the laser, ``overrules`` set (and said) when it reaches
    ``alignment.outside_hull_views_agree_iou``; None when it is not measured."""
    agreement = _views_agreement(clouds, views, idx, int(ac["outside_hull_agree_resolution"]))
    limit_iou = ac["outside_hull_views_agree_iou"]
    if (agreement is not None and limit_iou is not None
            and agreement["iou_median"] >= float(limit_iou)):
        agreement["overrules"] = True
        log.warning("alignment: the silhouettes would drop %.1f %% of the laser points (%.1f "
                    "%% outside fewer than half of the views), but the views agree with each "
                    "other (median IoU %.2f with the others' hull, at least "
                    "alignment.outside_hull_views_agree_iou %.2f): the points are not on the "
                    "object and are dropped", 100 * would, 100 * disputed,
                    agreement["iou_median"], float(limit_iou))
    return agreement


def _reject_outside_hull(clouds: list, views, inputs: Mapping[str, str],
                         ac: Mapping[str, Any]) -> tuple[dict[str, Any], np.ndarray]:
    """Drop the aligned points that lie outside a view's silhouette (in place).

    A point of the object cannot project outside a correct silhouette of it; a laser
    point that does is light of the laser's colour that the sheet did not put on the
    object there (the object's lit rim, a glint, a reflection) triangulated into empty
    space (:func:`robo3d.carving.outside_silhouettes`). Views flagged by the silhouettes'
    QA are not used; nor is a view that would drop more than
    ``outside_hull_max_view_fraction`` of the points where at most a quarter of the views
    (at least one) see them outside (the laser contradicts the mask: the others see the
    points inside). When more than ``outside_hull_max_fraction`` of the points would be
    dropped by fewer than half of the views, or more than
    ``outside_hull_max_total_fraction`` (half) of the points above the box's floor (the
    table lit inside the box next to it is no evidence), the
    silhouettes contradict the laser as a whole (masks that failed alike in many views):
    no point is dropped, and the report says so (``contradicted``); unless three or more
    views agree with each other (:func:`_views_agreement`, median IoU at least
    ``outside_hull_views_agree_iou``): masks that agree are not what failed, the points
    are, and they are dropped as by any silhouette (``views_agreement`` in the report).
    Stray points are few or seen outside by most views: the cells of the front-end
    benchmark (the laser on the table and the wall inside the box) drop 1.7-6 %, 0.7-3.9 %
    by fewer than half of the views (``disputed_fraction`` in the report); a
    near-symmetric orange body under a red laser, its masks right (0.995 IoU), 10.1 %: the
    lit rim and glints of a glossy object. Masks that missed parts of a grey bracket on a
    grey table (0.76 IoU) would have dropped 22 % of its points, 91 % of them within
    0.3 mm of the true surface.

    Returns the report (per sweep: points dropped) and the dropped points.
    """
    from ..carving import outside_silhouettes

    if not ac["reject_outside_hull"]:
        return {"skipped": "alignment.reject_outside_hull is false"}, np.zeros((0, 3))
    if views is None:
        return {"skipped": "no silhouette views"}, np.zeros((0, 3))
    n_all = sum(len(c) for c in clouds)
    if n_all == 0:
        return {"skipped": "no points"}, np.zeros((0, 3))
    qa, seeded = _silhouette_flags(inputs["silhouettes"])
    if seeded:  # masks segmented again from the laser's points cannot judge them
        return _laser_seeded_skip(seeded, n_all), np.zeros((0, 3))
    idx = [i for i in range(len(views.cameras)) if qa is None or not qa[i]]
    pts = np.concatenate([c.points_base for c in clouds])
    tol_px, tol_m = float(ac["outside_hull_px"]), 1e-3 * float(ac["outside_hull_mm"])
    per_view = np.stack([outside_silhouettes(
        pts, [views.masks[i]], [views.cameras[i]], views.T_base_camera[i:i + 1],
        tol_px=tol_px, tol_m=tol_m)[0] > 0 for i in idx]) if idx else np.zeros((0, len(pts)), bool)
    # a view contradicts the laser when it drops many points that (almost) no other
    # view drops: its own mask is wrong there. Points that most views see outside their
    # silhouettes (the table or the wall lit by the laser and triangulated within the
    # workspace, a reflection) are no evidence against a view: counting them made every
    # view untrusted when they were more than 10 % of the points (a 7-sweep scan whose
    # last sweeps lit the table: 23 of 24 views left out, the table kept as measured)
    few = max(1, len(idx) // 4)
    alone = per_view & (per_view.sum(axis=0) <= few)
    frac = alone.mean(axis=1) if len(idx) else np.zeros(0)
    distrust = frac > float(ac["outside_hull_max_view_fraction"])
    n_out = per_view[~distrust].sum(axis=0)
    drop = n_out >= int(ac["outside_hull_min_views"])
    # points that at least half of the views see outside are stray by consensus (the
    # table lit inside the box: a third of a scan's points, outside every view); the
    # others each only some views drop
    disputed = float((drop & (n_out < max(1, (len(idx) - int(distrust.sum())) / 2))).mean())
    # ... and masks that are wrong everywhere (an object of the background's colours
    # segmented as a few specks per view) put every point outside most of them: more
    # than half of what the laser measured above the box's floor is never stray light
    # (the table lit inside the box, next to the floor, can be most of a scan's points)
    above = _above_floor(clouds, pts)
    would = float(drop.mean())
    contradicted = (disputed > float(ac["outside_hull_max_fraction"])
                    or (above.any() and float(drop[above].mean())
                        > float(ac["outside_hull_max_total_fraction"])))
    # ... unless the views agree with each other: then the points are what is wrong (a
    # stripe taken from a texture's edges where the laser left no trace)
    agreement = _views_overrule(clouds, views, idx, ac, would, disputed) if contradicted \
        else None
    contradicted = contradicted and not (agreement or {}).get("overrules")
    if contradicted:
        # the silhouettes as a whole contradict the laser: segmentation that failed
        # together in many views (a white cup on a black-and-white checker table: every
        # mask missed its white patches; 84 % of the laser points lay outside some of
        # them, each outside fewer than half)
        drop = np.zeros_like(drop)
    starts = np.cumsum([0] + [len(c) for c in clouds])
    per_sweep = []
    for k, c in enumerate(clouds):
        per_sweep.append({"sweep": c.sweep, "points": len(c),
                          "dropped": c.drop(drop[starts[k]:starts[k + 1]], "outside_hull")})
    not_used = [{"view": int(idx[j]), "would_drop_alone_fraction": round(float(frac[j]), 4)}
                for j in np.flatnonzero(distrust)]
    report = {"views_used": int(len(idx) - distrust.sum()),
              "views_not_used_qa_flagged": [i for i in range(len(views.cameras))
                                            if i not in idx],
              "views_not_used_contradict_laser": not_used,
              "tol_px": tol_px, "tol_mm": 1e3 * tol_m,
              "min_views": int(ac["outside_hull_min_views"]),
              "dropped": int(drop.sum()), "points": int(n_all),
              "dropped_fraction": float(drop.mean()), "disputed_fraction": disputed,
              "per_sweep": per_sweep}
    if agreement is not None:
        report["views_agreement"] = agreement
    if contradicted:
        report.update(_contradicted(would, disputed, ac))
    log.info("alignment: %d of %d laser points (%.2f %%) lie outside a silhouette: dropped "
             "(%d views used%s)", int(drop.sum()), n_all, 100 * float(drop.mean()),
             report["views_used"],
             f"; not used, contradict the laser: {[v['view'] for v in not_used]}"
             if not_used else "")
    return report, pts[drop]
