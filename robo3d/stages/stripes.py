"""The ``stripes`` stage: the laser stripe's sub-pixel centres in every laser frame (seed §4.2;
:mod:`robo3d.stripes`).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..atomic import save_npz, write_json
from ..errors import StageError
from .common import (
    Progress,
    camera_arrays,
    laser_poses,
    log,
    log_image_camera,
    open_recording,
    stage_threads,
    summary,
    workspace_arrays,
)


def stage_stripes(inputs: Mapping[str, str], outputs: Mapping[str, str],
                  cfg: Mapping[str, Any], rec_name: str,
                  threads: int | None = None) -> dict[str, Any]:
    """Find the laser stripe's sub-pixel centres in every laser frame (seed §4.2).

    The frames are decoded and searched on ``threads`` threads (the decoder and the
    stripe kernels release the GIL); the results do not depend on the number.
    """
    from concurrent.futures import ThreadPoolExecutor

    from ..stripes import (
        REJECTION_REASONS,
        centre_on_for,
        config_options,
        estimate_laser_colour,
        extract_stripe_centres,
    )
    from ..viz import log_camera, log_report, rerun_log, spaced_indices

    t0 = time.perf_counter()
    n_threads = stage_threads(threads)
    rec = open_recording(inputs["recording"], cfg, roles=("laser",))
    frames = sorted(rec.laser_frames, key=lambda m: m.timestamp_ns)
    cameras = [rec.camera_for(m) for m in frames]
    poses = rec.camera_poses(frames)
    T_camera_laser = laser_poses(rec, frames)  # the reader names the role "laser"
    sc = cfg["stripes"]
    kw = config_options(sc)
    # laser-off frames: read as the "laser" role of their own topic, the nearest in time
    # subtracted from each laser frame
    rec_off, off_frames, pair = None, [], np.zeros(0, np.int64)
    if sc.get("laser_off_topic") and frames:
        topic = str(sc["laser_off_topic"])
        cfg_off = {**cfg, "topics": {**dict(cfg.get("topics") or {}), "laser": topic}}
        rec_off = open_recording(inputs["recording"], cfg_off, roles=("laser",), require=False)
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
        from ..triangulation import laser_transform_from_params

        dx, dy, dz, phi, theta, psi = (float(x) for x in tc["laser_params"])
        T_roi_laser = np.broadcast_to(laser_transform_from_params(
            dx, dy, dz, *np.radians([phi, theta, psi])), T_camera_laser.shape)
    roi_area = np.full(len(frames), np.nan)

    def roi(i: int):
        if not use_roi:
            return None
        from ..triangulation import sheet_in_workspace, sheet_roi_mask

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

    progress = Progress("finding stripes", len(frames))
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
             **camera_arrays(cameras), **workspace_arrays(rec))
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        # the stripe points of every frame on the "frame" timeline, the camera where it
        # was; the image itself on a few evenly spaced frames
        with_image = set(spaced_indices(len(frames), cfg["rerun"]["max_images"]).tolist())
        for i, sp in enumerate(found):
            rr_stream.set_time("frame", sequence=int(i))
            if i in with_image:
                log_image_camera(rr_stream, "base/laser_camera", frames[i], cameras[i],
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
