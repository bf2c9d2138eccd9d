"""The ``triangulate`` stage: stripe pixels to points in ``base``, one cloud per sweep (seed
§4.1, §4.3; :mod:`robo3d.triangulation`).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..atomic import write_json
from ..errors import StageError
from .common import cameras_from, log, summary, sweep_color, sweeps_of, workspace_from


def _turn_deg(T: np.ndarray) -> float:
    """The largest angle (degrees) between a sweep's camera orientations and its middle
    frame's."""
    from ..transforms import rotation_angle_deg

    R = np.asarray(T, dtype=np.float64)[:, :3, :3]
    if not len(R):
        return 0.0
    rel = np.einsum("ji,njk->nik", R[len(R) // 2], R)  # R_mid^T R_f
    return round(float(np.max(rotation_angle_deg(rel))), 4)


def _stripes_of_frame(s: Mapping[str, np.ndarray], i: int):
    """The :class:`~robo3d.stripes.StripePoints` of frame ``i`` of a ``stripes.npz``
    (older files without axis, line or rejections are read too)."""
    from ..stripes import StripePoints

    a, b = int(s["offsets"][i]), int(s["offsets"][i + 1])
    opt = {}
    if "axis" in s:
        opt["axis"] = str(s["axis"][i])
    if "line" in s:
        opt["line"] = s["line"][a:b]
    for key in ("peak", "width_px", "skew_px", "faint", "v_sensor"):
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
    from ..artefacts import save_clouds_npz
    from ..meshio import write_point_cloud
    from ..triangulation import (
        DROP_REASONS,
        TriangulateOptions,
        laser_transform_from_params,
        triangulate_sweep,
    )
    from ..viz import log_points, log_report, log_scalar, rerun_log, set_image_time

    t0 = time.perf_counter()
    from ..artefacts import Stripes

    s = Stripes.load(inputs["stripes"]).as_arrays()  # the file's arrays, checked
    cameras = cameras_from(s)
    stamps = s["stamps_ns"]
    tc = cfg["triangulation"]
    ws = workspace_from(s) if tc["crop_to_workspace"] else None
    if tc["laser_params"] is not None:  # the seed's eq. 11 instead of the recording's tf
        dx, dy, dz, phi, theta, psi = (float(x) for x in tc["laser_params"])
        T_laser = laser_transform_from_params(dx, dy, dz, *np.radians([phi, theta, psi]))
        T_camera_laser = np.broadcast_to(T_laser, (len(stamps), 4, 4))
        laser_source = "config triangulation.laser_params (seed eq. 11)"
    else:
        T_camera_laser = s["T_camera_laser"]
        laser_source = "recording transforms (camera -> laser)"
    opts = TriangulateOptions.from_config(tc)
    sweep_of = sweeps_of(stamps, cfg)
    # a rolling shutter: the poses of the frames' last rows, from the stripes stage
    end = s.get("T_base_camera_end")
    clouds, per_sweep = [], []
    for k in np.unique(sweep_of):
        idx = np.nonzero(sweep_of == k)[0]
        stripes = [_stripes_of_frame(s, int(i)) for i in idx]
        cam = cameras[int(idx[0])]
        try:
            cloud = triangulate_sweep(stripes, cam, s["T_base_camera"][idx],
                                      T_camera_laser[idx], workspace=ws,
                                      frame_indices=idx, sweep=int(k), options=opts,
                                      T_base_camera_end=end[idx] if end is not None else None)
        except StageError as exc:
            log.warning("sweep %d (frames %d..%d) skipped: %s", k, idx[0], idx[-1], exc)
            per_sweep.append({"sweep": int(k), "frames": len(idx), "points": 0,
                              "skipped": str(exc)})
            continue
        if ws is not None:  # the box it was cropped to: alignment crops to it again
            cloud.report = {**(getattr(cloud, "report", None) or {}),
                            "workspace": [np.asarray(ws[0], float).tolist(),
                                          np.asarray(ws[1], float).tolist()]}
        # how far the camera turned during the sweep (a turntable's revolution, a robot's
        # arc): the alignment's motion model depends on it
        cloud.report = {**(getattr(cloud, "report", None) or {}),
                        "sensor_turn_deg": _turn_deg(s["T_base_camera"][idx])}
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
            color = sweep_color(c.sweep)
            # the sweep's raw cloud (before alignment) grows profile by profile along the
            # "frame" and "time" timelines, in the sweep's colour
            frames_c = np.unique(c.frame_index)
            for chunk in np.array_split(frames_c, min(20, len(frames_c))):
                if len(chunk) == 0:
                    continue
                set_image_time(rr_stream, int(stamps[chunk[-1]]), frame=int(chunk[-1]),
                               sweep=c.sweep)
                sel = c.frame_index <= chunk[-1]
                log_points(rr_stream, f"base/triangulate/sweep_{c.sweep:02d}",
                           c.points_base[sel], colors=color, static=False)
            log_scalar(rr_stream, "metrics/triangulate/sweep_points", len(c.points_base))
        log_report(rr_stream, "reports/triangulate", report)
    write_json(outputs["report"], report)
    from ..viz import format_counts

    summary.info("triangulated %d points in %d sweeps (%.1f s); dropped: %s", report["n_points"],
             len(clouds), report["seconds"], format_counts(dropped))
    return report
