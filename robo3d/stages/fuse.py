"""The ``fuse`` stage: one surface from the aligned sweeps (TSDF or screened Poisson,
:mod:`robo3d.fusion`), with every vertex's provenance, and the measured surface alone.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..atomic import write_json
from ..errors import NoUsablePoints, StageError
from ..fusion import source_colors
from .common import log, stage_threads, summary


def stage_fuse(inputs: Mapping[str, str], outputs: Mapping[str, str],
               cfg: Mapping[str, Any], rec_name: str, threads: int | None = None
               ) -> dict[str, Any]:
    """Fuse the aligned clouds into one watertight surface (seed §2.4): each sweep as range
    data into a TSDF (Curless & Levoy), holes closed from the visual hull (or screened
    Poisson, ``fusion.method``); from views alone the fused mesh is the hull's, as it is
    when the laser measured nothing usable on the object (all of it labelled inferred).

    The report says what fraction of the surface came from the laser and from the hull.
    """
    from ..artefacts import load_clouds_npz, table_points
    from ..carving import hull_to_mesh
    from ..fusion import (
        HULL,
        MEASURED,
        SOURCES,
        FuseOptions,
        keep_vertices,
        source_area_fractions,
    )
    from ..meshio import write_mesh
    from ..viz import log_mesh, log_report, rerun_log

    t0 = time.perf_counter()
    fc = cfg["fusion"]
    opts = FuseOptions.from_config(fc, seed=cfg["seed"])
    hull = _hull(inputs)
    table = clouds = None  # the laser's clouds, its points on the table (no laser: none)
    unusable = None  # why the laser's points made no surface, when the hull is used instead
    if inputs.get("aligned"):
        clouds = load_clouds_npz(inputs["aligned"])
        crop = hull if (hull is not None and fc["crop_to_hull"]) else None
        table = table_points(clouds, cfg["triangulation"])
        try:
            V, F, fuse_report, attrs, source = _fuse_laser(clouds, table, crop, fc, opts,
                                                           threads)
        except NoUsablePoints as exc:
            if hull is None:
                raise
            # the laser lit nothing of the object (random scene 1163: one sweep whose
            # line lay on the table beside a thin wall; eight right masks): the views'
            # hull is the whole surface there is, and none of it is measured
            unusable = str(exc)
            log.warning("fusion: the laser measured nothing usable on the object (%s): the "
                        "fused mesh is the visual hull's, all of it inferred", unusable)
    if unusable is not None or not inputs.get("aligned"):
        if hull is None:
            raise StageError("fusion needs aligned clouds or a hull, got neither")
        V, F = hull_to_mesh(hull, smooth_sigma_vox=cfg["carving"]["smooth_sigma_vox"])
        note = ("no laser frames: the fused mesh is the visual hull's" if unusable is None
                else "the laser measured nothing usable on the object: the fused mesh is "
                     "the visual hull's, all of it inferred")
        fuse_report = {"note": note, "laser_area_fraction": 0.0, "hull_area_fraction": 1.0,
                       **({"laser_unusable": unusable} if unusable is not None else {})}
        attrs = {"source": np.full(len(V), HULL, np.uint8),
                 "n_obs": np.zeros(len(V), np.uint16),
                 "incidence": np.zeros(len(V), np.float32),
                 "tsdf_weight": np.zeros(len(V), np.float32),
                 "dist_measured_m": np.full(len(V), np.inf, np.float32),
                 "confidence": np.zeros(len(V), np.float32),
                 "far_from_measured": np.ones(len(V), np.uint8)}
        source = "visual hull"
    if len(F) == 0:
        raise StageError(f"fusion produced an empty mesh from {source}"
                         + _why_empty(fuse_report, clouds, table, hull))
    # sweeps the alignment flagged (kept at the robot's pose, checked by nothing)
    laser = clouds if inputs.get("aligned") else []
    flags = [bool((c.report or {}).get("flagged")) for c in laser]
    attrs["flagged_sweep"] = (_flagged_sweep(V, attrs["source"] == MEASURED, laser, flags)
                              if any(flags) else np.zeros(len(V), np.uint8))
    if isinstance(fuse_report.get("source_area_fraction"), dict):
        fuse_report.pop("source_area_fraction")
    fractions = source_area_fractions(V, F, attrs["source"])
    Vm, Fm, attrs_m = keep_vertices(V, F, attrs, attrs["source"] == MEASURED)
    report = {"source": source,
              "method": fc["method"] if inputs.get("aligned") and unusable is None else "hull",
              **fuse_report, "vertices": len(V), "faces": len(F),
              "source_area_fraction": fractions,
              "inferred_area_fraction": 1.0 - fractions["measured"],
              "inferred_far_area_fraction": _area_fraction(V, F, attrs["far_from_measured"]
                                                           > 0),
              "flagged_sweep_area_fraction": _area_fraction(V, F, attrs["flagged_sweep"] > 0),
              "flagged_sweeps": [int(c.sweep) for c, f in zip(laser, flags, strict=True) if f],
              "measured_faces": len(Fm),
              "table_points": _table_report(table, cfg["triangulation"]),
              "vertex_attributes": {"source": {str(i): n for i, n in enumerate(SOURCES)},
                                    "fields": sorted(attrs)},
              "seconds": round(time.perf_counter() - t0, 3)}
    write_mesh(outputs["ply"], V, F, vertex_colors=source_colors(attrs["source"]),
               attributes=attrs)
    if outputs.get("measured"):
        write_mesh(outputs["measured"], Vm, Fm,
                   attributes={k: a for k, a in attrs_m.items() if k != "source"})
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        log_mesh(rr_stream, "base/fuse/mesh", V, F,
                 vertex_colors=source_colors(attrs["source"]))
        log_report(rr_stream, "reports/fuse", report)
    write_json(outputs["report"], report)
    lf = report.get("laser_area_fraction")
    grid = ""
    if report.get("voxel_size") is not None:
        grid = f", voxel {report['voxel_size'] * 1e3:.2f} mm"
        if report.get("voxel_from") == "point footprint":
            grid += (f" ({opts.tsdf_voxel_per_footprint:g} x sqrt(the points' spacing "
                     f"{report['point_spacing_m'] * 1e3:.2f} mm x the profiles' "
                     f"{report['profile_spacing_m'] * 1e3:.2f} mm))")
        elif report.get("voxel_from") == "point spacing":
            grid += (f" ({opts.tsdf_voxel_per_spacing:g} x the points' spacing "
                     f"{report['point_spacing_m'] * 1e3:.2f} mm)")
    summary.info("fused mesh from %s: %d faces%s%s%s (%.1f s)", source, len(F),
             f", {100 * lf:.1f}% of its area from the laser" if lf is not None else "",
             grid, _bridges_note(report, opts.max_frame_span), report["seconds"])
    return report


def _fuse_laser(clouds: list, table: list[np.ndarray] | None, crop: Any,
                fc: Mapping[str, Any], opts: Any, threads: int | None
                ) -> tuple[np.ndarray, np.ndarray, dict[str, Any], dict[str, np.ndarray], str]:
    """The laser's clouds fused (TSDF or screened Poisson, ``fusion.method``), holes
    closed from the hull ``crop`` (None: not cropped): vertices, faces, the fusion's report,
    per-vertex attributes and the report's ``source``. Raises
    :class:`~robo3d.errors.NoUsablePoints` when no point is usable."""
    from ..artefacts import clouds_workspace
    from ..fusion import fuse_poisson, fuse_tsdf

    if fc["method"] == "tsdf":
        V, F, fuse_report, attrs = fuse_tsdf(
            [c.points_base for c in clouds], [c.normals_base for c in clouds],
            [c.sensor_origin_base for c in clouds], options=opts,
            confidences=[c.confidence for c in clouds], grids=[c.grid() for c in clouds],
            hull=crop, workspace=clouds_workspace(clouds), carve_only=table,
            max_voxels=int(fc["max_voxels"]), threads=stage_threads(threads),
            return_attributes=True)
        source = _tsdf_source(crop is not None and fc["fill_holes"], fc["close"],
                              bool(fuse_report.get("hull_contradicted")))
        return V, F, fuse_report, attrs, source
    off = ~np.concatenate(table) if table else np.ones(0, bool)
    pts = np.concatenate([c.points_base for c in clouds])[off]
    nrm = np.concatenate([c.normals_base for c in clouds])[off]
    V, F, fuse_report = fuse_poisson(pts, nrm, options=opts, hull=crop)
    attrs = _poisson_provenance(V, pts, opts.tsdf_voxel_m, 1e-3 * opts.max_fill_distance_mm)
    source = "laser (screened Poisson)"
    if crop is not None:
        cut = str(fuse_report.get("hull_cut", "applied"))
        source += ", cut to the hull" if cut == "applied" else f", hull cut {cut}"
    return V, F, fuse_report, attrs, source


def _hull(inputs: Mapping[str, str]):
    """The visual hull, or None: no views, or with laser frames an empty hull (the carve
    left none, its report says why), which closes nothing and is not a hull that
    contradicts the laser, as one with every measured point outside it."""
    from ..carving import VoxelGrid

    hull = VoxelGrid.load_npz(inputs["hull"]) if inputs.get("hull") else None
    if hull is not None and hull.n_occupied == 0 and inputs.get("aligned"):
        log.info("fusion: the visual hull is empty (the carve's report says why): nothing "
                 "is closed from it")
        return None
    return hull


def _tsdf_source(closes: bool, close: str, contradicted: bool) -> str:
    """The report's ``source`` of a TSDF fusion: what closed its holes (``closes``: a
    hull was given and ``fusion.fill_holes``; ``close``: ``fusion.close``); a hull that
    contradicted the laser closed nothing (it said "closed from the hull")."""
    if not closes:
        return "laser (TSDF)"
    if contradicted:
        return "laser (TSDF), nothing closed: the hull contradicts the laser"
    return "laser (TSDF)" + {
        "hull": ", holes closed from the hull",
        "free_space": ", holes near measurements closed, far ones left open",
        "none": ", holes left open"}[close]


def _bridges_note(report: Mapping[str, Any], max_span: int) -> str:
    """The summary's word on range triangles dropped for joining laser frames more than
    ``max_span`` apart, when they are at least 1 % of the scans' triangles (a scan whose
    stripe came and went: the surface between was not seen); else nothing."""
    n = int(report.get("n_range_triangles_over_frames") or 0)
    total = sum(int(s.get("n_triangles_delaunay", 0))
                for s in report.get("range_surfaces") or [] if isinstance(s, Mapping))
    if not n or n < 0.01 * total:
        return ""
    return (f"; {100 * n / total:.0f}% of the range triangles joined laser frames more "
            f"than {max_span} apart, over frames without a stripe there: not measured")


def _table_report(table: list[np.ndarray] | None, tc: Mapping[str, Any]) -> dict[str, Any]:
    """What the report says of the table's points
    (:func:`robo3d.artefacts.table_points`)."""
    if table is None:
        return {"skipped": "no laser points"}
    if not float(tc["table_above_floor_mm"]) > 0:
        return {"skipped": "triangulation.table_above_floor_mm is 0"}
    n = int(sum(int(t.sum()) for t in table))
    if n:
        log.info("fusion: %d laser points lie on the table (within %.1f mm above the "
                 "workspace box's floor, facing up): they carve free space, they are not "
                 "measured surface", n, float(tc["table_above_floor_mm"]))
    return {"above_floor_mm": float(tc["table_above_floor_mm"]),
            "max_tilt_deg": float(tc["table_max_tilt_deg"]), "carve_only": n,
            "per_sweep": [int(t.sum()) for t in table]}


def _flagged_sweep(V: np.ndarray, measured: np.ndarray, clouds: list, flags: list[bool]
                   ) -> np.ndarray:
    """1 on measured vertices whose nearest laser point comes from a sweep the alignment
    flagged (``flags``, per cloud: kept at the robot's pose, no accepted pair and no view
    checked it; the aligned cloud's report ``flagged``), else 0. Such surface is
    measured, but where it lies rests on the robot's pose alone; when every sweep is
    flagged the laser points may not be one surface at all (random scene 142 of stop 33:
    a stripe the detector did not find, a printed pattern's gaps taken instead). Costs
    nothing when no sweep is flagged."""
    out = np.zeros(len(V), np.uint8)
    if not any(flags) or not measured.any():
        return out
    if all(flags):
        out[measured] = 1
        return out
    from scipy.spatial import cKDTree

    pts = np.concatenate([c.points_base for c in clouds])
    of = np.concatenate([np.full(len(c.points_base), f) for c, f in zip(clouds, flags,
                                                                         strict=True)])
    if not len(pts):
        return out
    _, idx = cKDTree(pts).query(V[measured], workers=-1)
    out[measured] = of[idx].astype(np.uint8)
    return out


def _area_fraction(V: np.ndarray, F: np.ndarray, flag: np.ndarray) -> float:
    """Share of a mesh's area on faces with a flagged vertex."""
    if len(F) == 0:
        return 0.0
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                axis=1)
    total = float(area.sum())
    return float(area[np.any(flag[F], axis=1)].sum() / total) if total > 0 else 0.0


def _poisson_provenance(V: np.ndarray, pts: np.ndarray, voxel: float, far_m: float
                        ) -> dict[str, np.ndarray]:
    """Provenance of screened-Poisson vertices: measured within ``2 * voxel`` of a laser
    point (or twice the points' median spacing, if larger), else inferred (hull)."""
    from scipy.spatial import cKDTree

    from ..fusion import HULL, MEASURED, point_spacing

    d, _ = cKDTree(pts).query(V, k=1)
    spacing = point_spacing([pts]) or 0.0
    near = d <= max(2.0 * voxel, 2.0 * spacing)
    return {"source": np.where(near, MEASURED, HULL).astype(np.uint8),
            "n_obs": np.zeros(len(V), np.uint16), "incidence": np.zeros(len(V), np.float32),
            "tsdf_weight": np.zeros(len(V), np.float32),
            "dist_measured_m": d.astype(np.float32),
            "confidence": np.where(near, np.exp(-(d / (2 * voxel)) ** 2), 0.0
                                   ).astype(np.float32),
            "far_from_measured": (~near & (d > far_m)).astype(np.uint8)}


def _why_empty(report: Mapping[str, Any], clouds: list | None, table: list | None,
               hull: Any) -> str:
    """What an empty fused mesh was made of, for its error: the laser points fused, those
    on the table, the voxels observed, and why nothing closes it (random scene 844: a
    black thin wall under a green laser seen by a monochrome camera, 48 points on the
    object in 40 frames, 4 voxels observed, no views)."""
    if clouds is None:
        return ""
    n_all = int(sum(len(c.points_base) for c in clouds))
    n_table = int(sum(int(np.count_nonzero(t)) for t in table)) if table else 0
    used = report.get("n_points_used", n_all - n_table)
    frames = int(sum(len(np.unique(c.frame_index)) for c in clouds))
    seen = report.get("n_voxels_observed")
    seen_s = "" if seen is None else f", {seen} voxels observed"
    closes = ("the views' hull is empty or contradicts the laser" if hull is not None
              else "there is no visual hull (no views) to close it")
    return (f": {used} laser points on the object from {frames} frames of {len(clouds)} "
            f"sweep(s) ({n_table} more on the table){seen_s}: "
            f"too little of the object was measured to make a surface, and {closes}. The "
            "aligned points (aligned.ply) are what the laser measured; a dark or absorbing "
            "surface returns a weak stripe: more laser power or exposure, a laser colour the "
            "object reflects, more sweeps, or views for a hull")
