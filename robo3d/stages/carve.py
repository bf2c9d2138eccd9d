"""The ``carve`` stage: the visual hull from the silhouettes (seed §3.1-3.5;
:mod:`robo3d.carving`, :mod:`robo3d.octree`), after each view's agreement with the others'
hull.

It reads ``silhouettes.npz``, places the carving box (the recording's workspace box, else
the silhouettes' centroid rays), scores the views against each other
(:class:`~robo3d.carving.AgreementOptions`), carves with the views that agree
(:class:`~robo3d.carving.CarveOptions`, both from the ``carving`` section by name), and
writes ``hull.npz`` (a :class:`~robo3d.grid.VoxelGrid`), ``hull.ply``,
``reports/carve.json`` and ``carve.rrd``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import write_json
from ..errors import StageError
from ..grid import VoxelGrid
from .common import cameras_from, load_silhouettes, log, mesh_volume, summary, workspace_from


def stage_carve(inputs: Mapping[str, str], outputs: Mapping[str, str],
                cfg: Mapping[str, Any], rec_name: str, has_laser: bool = False
                ) -> dict[str, Any]:
    """Place the box, check the views agree, carve the visual hull (seed §3.1–3.5), mesh it.

    Before the carve, each silhouette is scored against the hull of the other views on
    a coarse grid (:func:`robo3d.carving.flag_disagreeing_views`, ``carving.qa_*``);
    the views it flags are left out of the carve (``carving.qa_leave_out``) and named
    in the report (``views_left_out``), in ``hull.npz`` (``views_used``,
    ``views_left_out``) and in the rerun log. Views the segmentation's own checks
    flagged (``qa_flagged`` in ``silhouettes.npz``) do not define the other views'
    reference; they are left out only when they disagree too. An empty mask (a view whose
    segmentation failed) is always left out. The carving method
    (``carving.method``: Szeliski's octree or dense), its policies and ``k`` of n
    (``carving.min_views_background``) come from the config
    (:class:`~robo3d.carving.CarveOptions`); ``hull.npz`` holds the occupancy with its
    origin, voxel size, frame and how it was carved, ``hull.ply`` the smoothed
    watertight marching-cubes mesh, the report the box, the agreement scores, the
    resolution check (eq. 7–8), the volume and the hull's bounding box (``bbox_min``,
    ``bbox_max``: the outer faces of the occupied voxels, metres). Silhouettes that leave
    nothing to carve, or carve every voxel, or (without a box in the recording) leave too
    few views to place the carving box, are an error, except in a scan with laser
    frames (``has_laser``, the rule's ``params.has_laser``): there the hull is empty
    (``empty`` and ``reason`` in the report and ``hull.npz``), and fusion closes nothing;
    so is a hull that only views the segmentation flagged would carve, in such a scan
    (masks of the surroundings agree with each other, and their hull is the table's
    slab: :func:`robo3d.silhouettes.surrounding_views`).
    """
    from ..carving import CarveOptions, carve_visual_hull, hull_to_mesh, make_grid
    from ..errors import ConfigError
    from ..meshio import write_mesh

    t0 = time.perf_counter()
    sil = load_silhouettes(inputs["silhouettes"])
    cameras = cameras_from(sil)
    masks = [sil["masks"][i, : c.height, : c.width] for i, c in enumerate(cameras)]
    poses = sil["T_base_camera"]
    cc = cfg["carving"]
    opts = CarveOptions.from_config(cc)
    if opts.method == "dense" and opts.leaf_rule != "centre":
        raise ConfigError(f"config key carving.leaf_rule: {opts.leaf_rule!r} needs "
                          "carving.method octree (the dense method tests voxel centres)")
    ws = workspace_from(sil)

    def no_hull(why: str, **kw: Any) -> dict[str, Any]:
        if has_laser:  # the laser's measurement does not depend on the silhouettes
            return _no_hull(outputs, rec_name, sil, why, t0, **kw)
        raise StageError(f"{inputs['silhouettes']}: {why}")

    # an empty mask (a view the segmentation could not do) would carve every voxel
    empty = [i for i in range(len(cameras)) if not masks[i].any()]
    if cameras and len(empty) == len(cameras):
        return no_hull(f"no view is left to carve: all {len(cameras)} masks are empty")
    try:
        box_min, box_max, box_report = _carving_box(
            ws, masks, cameras, poses, cc,
            [i for i in range(len(cameras)) if i not in empty] if empty else None)
    except StageError as exc:  # no box in the recording, too few masks to place one
        return no_hull(f"no carving box: {exc}")
    n_views = len(cameras)
    seg_flags = _segmentation_flags(inputs["silhouettes"], sil, n_views)
    agreement = _view_agreement_check(seg_flags, masks, cameras, poses, box_min, box_max, cc)
    left_out = agreement["views_left_out"] if cc["qa_leave_out"] else []
    for i in empty:
        agreement["reasons"].setdefault(i, []).append("empty mask: the segmentation "
                                                      "failed in this view")
    left_out = sorted(set(left_out) | set(empty))
    used = [i for i in range(n_views) if i not in set(left_out)]
    left_out_rows = [{"view": i, "reasons": agreement["reasons"].get(i, [])}
                     for i in left_out]
    # an empty hull still says which views were left out and flagged, and why
    views_kw = dict(left_out_rows=left_out_rows, flagged=agreement["flagged"])
    if not used:
        return no_hull(f"no view is left to carve: {n_views} views, all with empty or "
                       "disagreeing masks", **views_kw)
    absurd = _only_flagged(seg_flags, used) if has_laser else None
    if absurd:
        return no_hull(absurd, **views_kw)
    if ws is None and left_out:  # a bad mask also misplaces the box: place it again
        try:
            box_min, box_max, box_report = _carving_box(ws, masks, cameras, poses, cc, used)
        except StageError as exc:  # random scene 463 of stop 52: one view left, no box
            return no_hull(f"no carving box from the {len(used)} view(s) left: {exc}",
                           **views_kw)
    agreement["used"] = _used_views_agreement(agreement, used)
    grid = make_grid(box_min, box_max, resolution=cc["resolution"])
    grid, carve_report = carve_visual_hull(grid, [masks[i] for i in used],
                                           [cameras[i] for i in used], poses[used], opts)
    for v in carve_report["views"]:  # the recording's view numbers, not the subset's
        v["view"] = used[v["view"]]
    if grid.n_occupied == 0:
        return no_hull("carving removed every voxel: the silhouettes do not agree with the "
                       "cameras' poses (check the calibration, the transform tree and the "
                       "masks)", grid=grid, views_used=used, **views_kw)
    vertices, faces = hull_to_mesh(grid, smooth_sigma_vox=cc["smooth_sigma_vox"])
    report = _hull_report(grid, vertices, faces, [cameras[i] for i in used], poses[used],
                          box=(box_min, box_max, box_report), method=opts.method,
                          n_views=n_views, used=used, left_out_rows=left_out_rows,
                          agreement=agreement, carve_report=carve_report)
    report["pieces"] = _pieces(grid, cc)
    report["seconds"] = round(time.perf_counter() - t0, 3)
    grid.save_npz(outputs["npz"], carving={k: getattr(opts, k) for k in (
                      "method", "leaf_rule", "outside_image", "behind_camera",
                      "min_views_background", "min_views_in_image")},
                  views_used=np.array(used, dtype=np.int64),
                  views_left_out=left_out_rows, views_agreement=agreement["used"])
    write_mesh(outputs["ply"], vertices, faces)
    _log_hull(outputs["rrd"], rec_name, grid, vertices, faces, report, box_min, box_max,
              cameras, poses, masks, used, left_out_rows)
    write_json(outputs["report"], report)
    summary.info("hull (%s): %d voxels of %.2f mm, volume %.1f cm3, mesh %d faces, %d of %d "
             "views (%.1f s)", opts.method, grid.n_occupied, grid.voxel_size * 1e3,
             report["volume_m3"] * 1e6, len(faces), len(used), n_views, report["seconds"])
    return report


def _no_hull(outputs: Mapping[str, str], rec_name: str, sil: Mapping[str, Any], why: str,
             t0: float, grid: VoxelGrid | None = None,
             views_used: list[int] | None = None,
             left_out_rows: list[dict[str, Any]] | None = None,
             flagged: list[int] | None = None) -> dict[str, Any]:
    """A scan with laser frames whose silhouettes carve nothing (objects of the
    background's colours, masks that fail in every view): the laser's measurement does
    not depend on them. An empty hull (``hull.npz`` with no occupied voxel, ``empty``;
    an empty ``hull.ply``) and a report that says why; fusion then closes nothing."""
    from ..carving import make_grid
    from ..meshio import write_mesh
    from ..viz import log_report, rerun_log

    log.warning("no visual hull: %s; the scan goes on with the laser alone (the mesh "
                "will be the measured surface, nothing closed)", why)
    if grid is None:
        ws = workspace_from(sil)
        lo, hi = ws if ws is not None else (np.zeros(3), np.full(3, 1e-3))
        grid = make_grid(lo, hi, resolution=8)
    grid.occupancy[...] = False
    report = {"empty": True, "reason": why, "occupied_voxels": 0, "volume_m3": 0.0,
              "n_views": int(len(sil["masks"])), "views_used": views_used or [],
              "views_left_out": left_out_rows or [], "views_flagged": flagged or [],
              "mesh": {"vertices": 0, "faces": 0, "volume_m3": 0.0},
              "seconds": round(time.perf_counter() - t0, 3)}
    grid.save_npz(outputs["npz"], views_used=np.array(views_used or [], dtype=np.int64),
                  views_left_out=left_out_rows or [], empty=why)
    write_mesh(outputs["ply"], np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        log_report(rr_stream, "reports/carve", report)
    write_json(outputs["report"], report)
    summary.info("no visual hull (%s)", why)
    return report


def _carving_box(workspace: tuple[np.ndarray, np.ndarray] | None, masks: list,
                 cameras: list, poses: np.ndarray, cc: Mapping[str, Any],
                 views: list[int] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """The carving box: the recording's workspace box, else the box of the silhouette
    centroid rays (seed §3.4; of ``views`` only, when given), with its report."""
    from ..carving import box_from_silhouettes

    if workspace is not None:
        box_min, box_max = workspace
        box_report: dict[str, Any] = {"source": "workspace box of the recording"}
    else:
        source = "silhouette centroid rays (seed §3.4)"
        if views is not None:
            masks, cameras, poses = ([masks[i] for i in views], [cameras[i] for i in views],
                                     poses[views])
            source += " of the views used"
        box_min, box_max, box_report = box_from_silhouettes(None, masks, cameras, poses,
                                                            margin=cc["box_margin"])
        box_report = {"source": source, **box_report}
    box_report["size_m"] = (np.asarray(box_max) - np.asarray(box_min)).tolist()
    log.info("carving box (%s): min %s, max %s, size %s mm", box_report["source"],
             np.round(box_min, 4).tolist(), np.round(box_max, 4).tolist(),
             np.round(np.asarray(box_report["size_m"]) * 1e3, 1).tolist())
    return box_min, box_max, box_report


def _pieces(grid: VoxelGrid, cc: Mapping[str, Any]) -> dict[str, Any]:
    """The hull's connected pieces (:func:`robo3d.carving.hull_pieces`), with a
    ``warning`` (logged, and shown in the overview and the hull's picture) when the largest
    holds less than ``carving.qa_largest_piece`` of its volume: masks that disagree about
    the object's shape carve it into shards, which fusion would close as inferred
    surface and a views-only scan delivers as its mesh."""
    from ..carving import hull_pieces

    out = hull_pieces(grid.occupancy)
    limit = cc.get("qa_largest_piece")
    share = out["largest_fraction"]
    if limit is not None and share is not None and share < float(limit):
        out["warning"] = (f"the hull falls apart into {out['n_over_min']} pieces of 1 % of "
                          f"its volume or more ({out['n']} in all), the largest "
                          f"{100 * share:.0f} %: the views' masks disagree about the "
                          "object's shape, or the scene holds more than one object")
        log.warning("carve: %s", out["warning"])
    return out


def _hull_report(grid: VoxelGrid, vertices: np.ndarray, faces: np.ndarray, cameras: list,
                 poses: np.ndarray, *, box: tuple, method: str, n_views: int,
                 used: list[int], left_out_rows: list[dict], agreement: dict[str, Any],
                 carve_report: dict[str, Any]) -> dict[str, Any]:
    """The carve stage's report (see :func:`stage_carve`), without ``seconds``; the
    resolution check (eq. 7–8) is made here, on the cameras of the views used."""
    from ..carving import resolution_report

    res = resolution_report(grid, cameras, poses)
    if res.get("warning"):
        log.warning("%s", res["warning"])
    box_min, box_max, box_report = box
    bbox = grid.occupied_bounds  # not None: an empty hull ends the stage before this
    return {"box": {"min": np.asarray(box_min).tolist(), "max": np.asarray(box_max).tolist(),
                    **box_report},
            "method": method, "grid_shape": list(grid.occupancy.shape),
            "voxel_size_m": grid.voxel_size, "occupied_voxels": grid.n_occupied,
            "volume_m3": grid.volume_m3, "bbox_min": bbox[0].tolist(),
            "bbox_max": bbox[1].tolist(), "n_views": n_views, "views_used": used,
            "views_left_out": left_out_rows,
            "views_flagged": agreement["flagged"],
            "agreement": agreement, "carving": carve_report, "resolution": res,
            "mesh": {"vertices": len(vertices), "faces": len(faces),
                     "volume_m3": mesh_volume(vertices, faces)}}


def _log_hull(rrd: str, rec_name: str, grid: VoxelGrid, vertices: np.ndarray, faces: np.ndarray,
              report: dict[str, Any], box_min: np.ndarray, box_max: np.ndarray,
              cameras: list, poses: np.ndarray, masks: list, used: list[int],
              left_out_rows: list[dict]) -> None:
    """The carve to rerun: the box, the cameras used, those left out (with their masks
    and why), the hull's shell voxels and mesh, the report."""
    from ..viz import log_box, log_camera, log_mesh, log_report, log_voxels, rerun_log

    with rerun_log(rrd, rec_name) as rr_stream:
        import rerun as rr

        log_box(rr_stream, "base/carve/box", box_min, box_max, label="carving box")
        for i in used:  # every camera that carved, at once (hidden in the designed view)
            log_camera(rr_stream, f"base/carve/cameras/view_{i:03d}", cameras[i], poses[i])
        for row in left_out_rows:  # left out: their cameras, masks and why, apart
            i = row["view"]
            entity = f"base/carve/left_out/view_{i:03d}"
            log_camera(rr_stream, entity, cameras[i], poses[i], mask=masks[i])
            rr_stream.log(f"{entity}/why", rr.TextDocument(
                f"view {i} left out of the carve: " + "; ".join(row["reasons"])), static=True)
        shell = grid.surface()
        log_voxels(rr_stream, "base/carve/voxels", grid.index_to_points(np.argwhere(shell)),
                   grid.voxel_size)
        # the hull is inferred surface: the orange of "inferred from the hull" in the
        # fused and final meshes, translucent so the laser's clouds show through it
        log_mesh(rr_stream, "base/carve/hull", vertices, faces, albedo=[240, 120, 30, 110])
        log_report(rr_stream, "reports/carve", report)


def _only_flagged(seg_flags: Mapping[int, list[str]], used: list[int]) -> str | None:
    """Why no hull is carved when every view in ``used`` is one the segmentation itself
    flagged (``seg_flags``: :func:`_segmentation_flags`); None otherwise.

    Why: masks of the table around a black object, each touching the whole frame, agree
    with each other, and their hull, the table's slab, took the workspace's place and
    closed the mesh (random scene 517 of stop 52: 99.4 % of the mesh closed from it, 59 mm
    from the truth at the median; 711 of stop 61: the table kept as measured surface,
    56.7 mm)."""
    if not used or not all(i in seg_flags for i in used):
        return None
    return (f"every view left to carve ({len(used)}) has a silhouette the segmentation "
            f"flagged as absurd (view {used[0]}: {', '.join(seg_flags[used[0]]) or 'flagged'})")


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


def _used_views_agreement(agreement: Mapping[str, Any], used: list[int]) -> dict[str, Any]:
    """How well the views that carve the hull agree with each other: the median of their
    IoUs with the other views' hull from the agreement check (``iou_median``, None when
    it scored nothing or fewer than three of them: two views' cones bound nothing of each
    other), and how many (``n_views``). Kept in ``hull.npz`` (``views_agreement``) for the
    align stage, which does not let a hull its views disagree on place a workspace
    (:func:`robo3d.stages.align._workspace_from_hull`)."""
    by_view = {int(s["view"]): s["iou"] for s in agreement.get("views", [])}
    ious = [float(by_view[i] or 0.0) for i in used if i in by_view]
    return {"iou_median": float(np.median(ious)) if len(ious) >= 3 else None,
            "n_views": len(ious)}


def _view_agreement_check(seg_flags: Mapping[int, list[str]], masks: list, cameras: list,
                          poses: np.ndarray, box_min: np.ndarray, box_max: np.ndarray,
                          cc: Mapping[str, Any]) -> dict[str, Any]:
    """Score every view against the other views' hull and choose the views to leave out
    (see :func:`stage_carve`; ``seg_flags``: the views the segmentation flagged,
    :func:`_segmentation_flags`); with fewer than 4 views, or ``carving.qa_resolution``
    0, nothing is scored."""
    from ..carving import (
        AgreementOptions,
        CarveOptions,
        flag_disagreeing_views,
        make_grid,
        reference_suspects,
    )

    qa_opts = AgreementOptions.from_config(cc)
    n = len(cameras)
    out: dict[str, Any] = {"enabled": False, "segmentation_flagged": sorted(seg_flags),
                           "flagged": [], "views_left_out": [], "reasons": {}, "views": []}
    if qa_opts.qa_resolution == 0 or n < 4:
        out["why_not"] = ("carving.qa_resolution is 0" if qa_opts.qa_resolution == 0 else
                          f"{n} views: too few for the others to outvote one")
        return out
    exclude, too_many = reference_suspects(masks, seg_flags)
    if too_many:
        log.warning("the segmentation flagged %d of %d views: too many to leave the "
                    "reference; all views with a mask score each other", len(seg_flags), n)
    grid = make_grid(box_min, box_max, resolution=min(qa_opts.qa_resolution,
                                                      cc["resolution"]))
    # the masks are scored against the others' exact hull whatever k the carve uses: a
    # k > 1 hull is fatter than any correct mask, which would then look "missing"
    carve = CarveOptions.from_config(cc).replace(min_views_background=1)
    qa = flag_disagreeing_views(grid, masks, cameras, poses, options=qa_opts, carve=carve,
                                exclude=exclude)
    reasons = {int(v): list(qa["views"][v]["reasons"]) + seg_flags.get(v, [])
               for v in qa["flagged"]}
    scores = [{k: s[k] for k in ("view", "iou", "missing_fraction", "spurious_fraction",
                                 "unexplained_fraction", "unexplained_max",
                                 "unexplained_views", "mask_px", "hull_px", "unknown_px",
                                 "flagged")}
              | {"segmentation_flags": seg_flags.get(s["view"], [])} for s in qa["views"]]
    ious = [s["iou"] for s in scores if s["iou"] is not None]
    out.update({"enabled": True, "resolution": int(max(grid.shape)),
                "voxel_size_m": grid.voxel_size, "flagged": qa["flagged"],
                "views_left_out": qa["flagged"] if qa_opts.qa_leave_out else [],
                "reasons": reasons, "passes": qa["passes"], "capped": qa["capped"],
                "thresholds": qa["thresholds"], "min_observers": qa_opts.qa_min_observers,
                "iou_min": min(ious) if ious else None,
                "iou_median": float(np.median(ious)) if ious else None,
                "views": scores, "seconds": round(qa["time_s"], 3)})
    log.info("view agreement (%d^3 grid, %.1f s): IoU with the other views' hull median "
             "%.3f, worst %.3f; flagged %s", out["resolution"], qa["time_s"],
             out["iou_median"] or float("nan"), out["iou_min"] or float("nan"),
             qa["flagged"] or "none")
    return out
