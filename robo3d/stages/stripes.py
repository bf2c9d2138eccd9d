"""The ``stripes`` stage: the laser stripe's sub-pixel centres in every laser frame (seed §4.2;
:mod:`robo3d.stripes`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from ..artefacts import Stripes
from ..atomic import write_json
from ..errors import StageError
from .common import (
    Progress,
    laser_poses,
    log,
    open_recording,
    stage_threads,
    summary,
    sweeps_of,
)

if TYPE_CHECKING:
    from ..stripes import StripeOptions


def stage_stripes(inputs: Mapping[str, str], outputs: Mapping[str, str],
                  cfg: Mapping[str, Any], rec_name: str,
                  threads: int | None = None) -> dict[str, Any]:
    """Find the laser stripe's sub-pixel centres in every laser frame (seed §4.2).

    Outputs: ``npz`` (:class:`robo3d.artefacts.Stripes`: the centres of every frame with
    its camera, pose and laser pose), ``report`` (counts, rejections, the laser colour,
    the region of interest, timings) and ``rrd`` (the stripe points on the frames).
    The frames are decoded and searched on ``threads`` threads (the decoder and the
    stripe kernels release the GIL); the results do not depend on the number.
    """
    from ..stripes import StripeOptions, centre_on_for

    t0 = time.perf_counter()
    n_threads = stage_threads(threads)
    rec = open_recording(inputs["recording"], cfg, roles=("laser",),
                         calibration=inputs.get("calibration"))
    frames = sorted(rec.laser_frames, key=lambda m: m.timestamp_ns)
    cameras = [rec.camera_for(m) for m in frames]
    poses = rec.camera_poses(frames)
    T_camera_laser = laser_poses(rec, frames)  # the reader names the role "laser"
    sc = cfg["stripes"]
    options = StripeOptions.from_config(sc)
    background, n_off = _laser_off_frames(inputs["recording"], cfg, frames)
    roi, use_roi, roi_area = _sheet_rois(rec, cfg, cameras, poses, T_camera_laser,
                                         options.detector == "ridge")
    # the scan axis: fixed by the laser's geometry where its epipolar lines run along the
    # columns or the rows (a bright line across them cannot be the stripe), else per frame
    axes, axis_report = _laser_axes(cfg, cameras, T_camera_laser, options)
    # the laser's colour, once for the recording, from a few evenly spaced frames (only
    # their regions of interest vote, along their axes)
    colour_scores = colour_check = None
    if options.detector == "ridge" and options.colour == "auto" and frames:
        views = _views_for_colour(inputs["recording"], cfg, inputs.get("calibration"), frames,
                                  T_camera_laser, axes, options.detector == "ridge")
        colour, colour_scores, colour_check = _laser_colour(
            rec, frames, background, roi, options, axes, views if n_off == 0 else None, cfg)
        options = options.replace(colour=colour)
    # the centre's profile: the luma for JPEGs whose colour is stored at half resolution
    # (the laser's channel lives mostly in the blurred chroma there), else the laser's
    options = options.replace(centre_on=centre_on_for(options.centre_on,
                                                      frames[0].data if frames else None))
    found, decode_s, detect_s = _detect(rec, frames, background, roi, options, n_threads,
                                        axes, inputs["recording"])
    readout_s = float(cfg["timing"].get("rolling_shutter_s") or 0.0)
    poses_end, n_extrapolated = (_readout_end_poses(rec, frames, poses, readout_s)
                                 if readout_s > 0 and frames else (None, 0))
    stripes = Stripes.from_frames(found, [m.timestamp_ns for m in frames], poses,
                                  T_camera_laser, cameras, rec.workspace, poses_end)
    if frames and len(stripes.u) == 0:
        raise StageError(f"{inputs['recording']}: topic {frames[0].topic}: no laser stripe "
                         f"found in any of {len(frames)} frames{_colour_why(colour_check)} "
                         "(check stripes.min_peak, the exposure and the laser)")
    report = _report(stripes, sc, options, colour_scores, use_roi, roi_area, n_off)
    report["axis_from_laser"] = axis_report
    report["laser_colour_check"] = colour_check
    if rec.rectifiers:  # searched in the raw frames, the centres moved to the pinhole camera
        report["rectified"] = {fid: r.describe() for fid, r in rec.rectifiers.items()}
    if readout_s > 0:
        report["rolling_shutter"] = {"readout_s": readout_s,
                                     "frames_end_pose_extrapolated": n_extrapolated}
    # centres found only in the frame averaged along the stripe (faint, noisy frames)
    n_faint = [int(np.count_nonzero(sp.faint)) for sp in found]
    report["faint_points"] = int(sum(n_faint))
    report["frames_with_faint_points"] = int(sum(n > 0 for n in n_faint))
    report.update({"threads": n_threads, "decode_seconds_cpu": round(decode_s, 3),
                   "detect_seconds_cpu": round(detect_s, 3),
                   "seconds": round(time.perf_counter() - t0, 3)})
    stripes.save(outputs["npz"])
    _log_rerun(outputs["rrd"], rec_name, frames, cameras, poses, found, report,
               cfg["rerun"]["max_images"], sweeps_of([m.timestamp_ns for m in frames], cfg),
               rec.decode)
    write_json(outputs["report"], report)
    summary.info("stripes: %d points in %d frames on %d threads (%.1f s; decoding %.1f s, "
             "detection %.1f s of CPU)", report["n_points"], len(frames), n_threads,
             report["seconds"], decode_s, detect_s)
    return report


def _readout_end_poses(rec, frames: list, poses: np.ndarray, readout_s: float
                       ) -> tuple[np.ndarray, int]:
    """Each laser frame's camera pose when its last row was exposed (``timing.
    rolling_shutter_s`` after the stamp, the first row's), and how many were extrapolated:
    where the pose stream ends within the readout, the motion from ``readout_s`` before
    the stamp is carried on (constant velocity), else the frame keeps its stamp's pose."""
    from ..errors import TransformError

    r_ns = int(round(readout_s * 1e9))
    shifted = [dataclasses.replace(m, timestamp_ns=m.timestamp_ns + r_ns) for m in frames]
    try:
        return rec.camera_poses(shifted), 0
    except TransformError:
        pass
    out = poses.copy()
    n_ex = 0
    for i, m in enumerate(frames):  # one lookup per frame: only when the stream ends early
        try:
            out[i] = rec.camera_poses([shifted[i]])[0]
        except TransformError:
            try:
                before = rec.camera_poses([dataclasses.replace(
                    m, timestamp_ns=m.timestamp_ns - r_ns)])[0]
                out[i] = poses[i] @ np.linalg.inv(before) @ poses[i]
                n_ex += 1
            except TransformError:
                n_ex += 1  # no motion known: the stamp's pose for every row
    return out, n_ex


def _laser_off_frames(path: str, cfg: Mapping[str, Any], frames: list
                      ) -> tuple[Callable[[int, np.ndarray], np.ndarray | None], int]:
    """The laser-off frame of each laser frame (``stripes.laser_off_topic``: read as the
    "laser" role of its own topic, the nearest in time), as a function of the frame's
    index and its decoded image that decodes the laser-off frame and checks that it is
    that camera's image of the same size (None without such a topic), and the number of
    laser-off frames."""
    sc = cfg["stripes"]
    if not (sc.get("laser_off_topic") and frames):
        return (lambda i, image, raw=False: None), 0
    topic = str(sc["laser_off_topic"])
    cfg_off = {**cfg, "topics": {**dict(cfg.get("topics") or {}), "laser": topic}}
    rec_off = open_recording(path, cfg_off, roles=("laser",), require=False)
    off_frames = sorted(rec_off.laser_frames, key=lambda m: m.timestamp_ns)
    if not off_frames:
        raise StageError(f"{path}: stripes.laser_off_topic {topic}: no image on that topic "
                         "(set it to null for a recording without laser-off frames)")
    t_off = np.array([m.timestamp_ns for m in off_frames], dtype=np.int64)
    t_on = np.array([m.timestamp_ns for m in frames], dtype=np.int64)
    j = np.clip(np.searchsorted(t_off, t_on), 1, len(t_off)) - 1
    j1 = np.minimum(j + 1, len(t_off) - 1)
    pair = np.where(np.abs(t_off[j1] - t_on) < np.abs(t_on - t_off[j]), j1, j)

    def background(i: int, image: np.ndarray, raw: bool = False) -> np.ndarray:
        # subtracted pixel by pixel: another camera's topic, or mono beside RGB, is a
        # configuration error, named before the detector sees it; ``raw``: as recorded,
        # for a laser frame searched unrectified
        off = off_frames[pair[i]]
        bg = rec_off.decode_raw(off) if raw else rec_off.decode(off)
        if bg.shape != image.shape:
            raise StageError(f"{path}: stripes.laser_off_topic {topic}: its image at t="
                             f"{off.timestamp_ns} ns is {_shape(bg)}, the laser frame it "
                             f"belongs to ({frames[i].topic}, t={frames[i].timestamp_ns} "
                             f"ns) {_shape(image)}: laser-off frames must be the same "
                             "camera's images of the same size")
        return bg

    return background, len(off_frames)


def _rectified(sp, rect):
    """The stripe centres found in a raw frame, moved to the rectified pinhole camera
    (:meth:`robo3d.camera.Rectifier.raw_to_rectified`); a centre whose ray the lens model
    cannot invert (beyond a fisheye's reach) is dropped, with a warning, and counted as
    outside the region the frame is searched in (``robo3d.stripes._subset``)."""
    from ..stripes import _subset

    uv = rect.raw_to_rectified(sp.pixels_uv)
    ok = np.all(np.isfinite(uv), axis=1)
    # the raw row stays: a rolling shutter exposes the sensor's rows, not the rectified
    sensor_v = sp.v if sp.v_sensor is None else sp.v_sensor
    if not ok.all():
        log.warning("stripes: %d of %d centres of a frame lie where the %s lens model of %r "
                    "has no inverse; dropped", int((~ok).sum()), len(ok), rect.model,
                    rect.frame_id)
    return _subset(dataclasses.replace(sp, u=uv[:, 0], v=uv[:, 1], v_sensor=sensor_v), ok,
                   "outside_roi")


def _shape(image: np.ndarray) -> str:
    h, w = image.shape[:2]
    return f"{w} x {h} " + ("mono" if image.ndim == 2 or image.shape[2] == 1 else
                            f"{image.shape[2]} channels") + f" {image.dtype}"


def _sheet_rois(rec, cfg: Mapping[str, Any], cameras: list, poses: np.ndarray,
                T_camera_laser: np.ndarray, ridge: bool
                ) -> tuple[Callable[[int], np.ndarray | None], bool, np.ndarray]:
    """The region of interest of each frame: where the laser sheet inside the workspace
    box projects (a stripe point elsewhere cannot triangulate into the box: the crop would
    drop it), as a function of the frame's index (None when not used); whether it is used
    (``stripes.roi_from_workspace``, the ridge detector, a box and
    ``triangulation.crop_to_workspace``); and the fraction of each frame's image it
    covers (NaN until computed)."""
    sc, tc = cfg["stripes"], cfg["triangulation"]
    use_roi = bool(sc["roi_from_workspace"] and ridge and rec.workspace is not None
                   and tc["crop_to_workspace"])
    T_roi_laser = _triangulation_laser(cfg, T_camera_laser) if use_roi else T_camera_laser
    roi_area = np.full(len(cameras), np.nan)

    def roi(i: int) -> np.ndarray | None:
        if not use_roi:
            return None
        from ..triangulation import sheet_in_workspace, sheet_roi_mask

        m = sheet_roi_mask(cameras[i], sheet_in_workspace(poses[i], T_roi_laser[i],
                                                          rec.workspace),
                           float(sc["roi_margin_px"]))
        # the share of the image it covers: counted (a bool mean converts every pixel
        # to float64 first, 0.46 ms at 1280 x 960 against 0.035; the same value)
        roi_area[i] = 1.0 if m is None else np.count_nonzero(m) / m.size
        return m

    return roi, use_roi, roi_area


def _triangulation_laser(cfg: Mapping[str, Any], T_camera_laser: np.ndarray) -> np.ndarray:
    """Each frame's laser pose in the camera as the triangulation will use it: the
    recording's, or ``triangulation.laser_params`` where the user gives them."""
    tc = cfg["triangulation"]
    if tc["laser_params"] is None:
        return T_camera_laser
    from ..triangulation import laser_transform_from_params

    dx, dy, dz, phi, theta, psi = (float(x) for x in tc["laser_params"])
    return np.broadcast_to(laser_transform_from_params(
        dx, dy, dz, *np.radians([phi, theta, psi])), T_camera_laser.shape)


def _laser_axes(cfg: Mapping[str, Any], cameras: list, T_camera_laser: np.ndarray,
                options: StripeOptions) -> tuple[list, dict[str, Any]]:
    """Each frame's scan axis where the laser's geometry fixes it
    (:func:`robo3d.triangulation.epipolar_axis`, with ``axis: auto`` and
    ``stripes.axis_from_laser_within_deg``), else None (the frame's own stripe decides);
    and what the report says about it."""
    from ..triangulation import epipolar_axis

    limit = float(cfg["stripes"]["axis_from_laser_within_deg"])
    if options.axis != "auto" or not limit > 0 or not cameras:
        return [None] * len(cameras), {"frames": 0, "within_deg": limit}
    T = _triangulation_laser(cfg, T_camera_laser)
    memo: dict[tuple, tuple[str | None, float]] = {}
    axes, worst = [], []
    for cam, T_i in zip(cameras, T, strict=True):
        key = (id(cam), np.asarray(T_i).tobytes())
        if key not in memo:
            memo[key] = epipolar_axis(cam, T_i, limit)
        axes.append(memo[key][0])
        worst.append(memo[key][1])
    n = sum(a is not None for a in axes)
    fixed = [w for a, w in zip(axes, worst, strict=True) if a is not None]
    return axes, {"frames": n, "within_deg": limit,
                  "epipolar_angle_deg_max": round(max(fixed), 2) if fixed else None,
                  "columns": sum(a == "columns" for a in axes),
                  "rows": sum(a == "rows" for a in axes)}


def _laser_colour(rec, frames: list, background: Callable, roi: Callable,
                  options: StripeOptions, axes: list,
                  views: Callable[[], tuple[list, list, list, str | None]] | None,
                  cfg: Mapping[str, Any]) -> tuple[str, dict[str, float], dict[str, Any] | None]:
    """The recording's laser colour from 12 evenly spaced frames
    (:func:`robo3d.stripes.estimate_laser_colour`, each along its axis where the laser's
    geometry fixes it), each contrast's score, and the check against the views where two
    colours are close (:func:`robo3d.stripes.laser_colour_contested`) or the lightness
    won over a colour that scored (:func:`robo3d.stripes.lightness_contested`; ``views`` loads
    up to 12 of them with their regions of interest and axes; None: laser-off frames
    already took the scene away): the colour that the laser frames show beyond the views
    (:func:`robo3d.stripes.laser_colour_beyond_scene`). Without views the laser frames
    check it themselves: the colour whose ridges move with the camera, not with the
    scene (:func:`_colour_by_motion`). The check is None when neither holds."""
    from ..stripes import (
        estimate_laser_colour,
        image_level,
        laser_colour_beyond_scene,
        laser_colour_contested,
        lightness_contested,
    )
    from ..viz import spaced_indices

    sample = spaced_indices(len(frames), 12)
    images = [rec.decode(frames[i]) for i in sample]
    rois = [roi(int(i)) for i in sample]
    colour, scores = estimate_laser_colour(
        images, backgrounds=[background(i, im) for i, im in zip(sample, images, strict=True)],
        min_peak=options.min_peak, rois=rois, axes=[axes[int(i)] for i in sample])
    log.info("stripes: laser colour %s (scores: %s)", colour, _scores_text(scores))
    with_lightness = colour == "lightness" and lightness_contested(scores)
    if not (with_lightness or (colour != "lightness" and laser_colour_contested(scores))):
        return colour, scores, None
    check: dict[str, Any] = {"contested": True, "colour_by_laser_frames": colour}
    if views is None:
        check["skipped"] = "laser-off frames subtracted: the scene is already taken away"
        return colour, scores, check
    v_images, v_rois, v_axes, why_not = views()
    if not v_images:
        check["skipped"] = why_not or "no views in the recording"
        return _colour_by_motion(rec, frames, roi, options, axes, scores, colour, check,
                                 cfg)
    _, v_scores = estimate_laser_colour(v_images, min_peak=options.min_peak, rois=v_rois,
                                        axes=v_axes)
    best, detail = laser_colour_beyond_scene(
        scores, image_level(images, rois), len(images), v_scores,
        image_level(v_images, v_rois), len(v_images), lightness=with_lightness)
    check.update(views=len(v_images), **detail)
    if best is not None and best != colour:
        log.warning("stripes: laser contrast %s, not %s: the views, without the laser, "
                    "show %s ridges as strongly as the laser frames (the scene's "
                    "texture); excess over the views: %s", best, colour, colour,
                    _scores_text(detail["excess"]))
        colour = best
    check["colour"] = colour
    return colour, scores, check


#: The motion check's pairs: up to this many, each a frame and the nearest one of its
#: sweep (this many frames later, or earlier at a sweep's end) over which the scene moved
#: far enough in the image to tell (the stripe itself moves less the nearer the frames).
_MOTION_PAIRS = 24
_MOTION_OFFSETS = (1, 2, 4, 8)


def _colour_by_motion(rec, frames: list, roi: Callable, options: StripeOptions, axes: list,
                      scores: dict[str, float], colour: str, check: dict[str, Any],
                      cfg: Mapping[str, Any]) -> tuple[str, dict[str, float], dict[str, Any]]:
    """A contested colour without views to check it by: the laser frames' own check, the
    contrast whose ridges move with the camera (:func:`robo3d.stripes.laser_colour_by_motion`)
    on up to :data:`_MOTION_PAIRS` pairs of frames of one sweep and one camera."""
    from ..stripes import _MOTION_MIN_PX, laser_colour_by_motion, scene_motion
    from ..viz import spaced_indices

    sweep = sweeps_of(np.array([m.timestamp_ns for m in frames], dtype=np.int64), cfg)
    n = len(frames)

    def partner(i: int, d: int) -> int | None:
        for j in (i + d, i - d):
            if 0 <= j < n and sweep[j] == sweep[i] and frames[j].frame_id == frames[i].frame_id:
                return j
        return None

    pairs, rois, pair_axes, motions = [], [], [], []
    for i in (int(k) for k in spaced_indices(n, _MOTION_PAIRS)):
        a = rec.decode(frames[i])
        for d in _MOTION_OFFSETS:
            j = partner(i, d)
            if j is None:
                continue
            b = rec.decode(frames[j])
            m = scene_motion(a, b)
            if float(np.hypot(*m)) >= _MOTION_MIN_PX:
                pairs.append((a, b))
                rois.append((roi(i), roi(j)))
                pair_axes.append(axes[i] if axes[i] == axes[j] else None)
                motions.append(m)
                break
    best, detail = laser_colour_by_motion(pairs, scores, colour, rois=rois, axes=pair_axes,
                                          options=options, motions=motions)
    check["motion"] = detail
    if best is not None:
        log.warning("stripes: laser contrast %s, not %s: without views to check the vote "
                    "(%s), the laser frames' %s ridges stay put between frames of a sweep, "
                    "as the laser's do (it is rigid with the camera), and the %s ridges do "
                    "not (the scene's texture): %s", best, colour, _scores_text(scores), best,
                    colour, _motion_text(detail))
        colour = best
    else:
        log.info("stripes: laser colour %s is close to another (%s); no views to check it "
                 "by (%s); by motion: %s", colour, _scores_text(scores), check["skipped"],
                 _motion_text(detail))
    check["colour"] = colour
    return colour, scores, check


def _motion_text(detail: Mapping[str, Any]) -> str:
    """``"24 pairs of frames, the scene moved 5.0 px: red moves with the scene (static
    6.0 px, shifted by the scene 1.0 px); ..."``: the check by motion, for the log."""
    parts = []
    for c, e in detail["contrasts"].items():
        if e["static_px"] is None:
            parts.append(f"{c} too few centres in {detail['pairs']} pairs")
        else:
            how = f"moves with the {e['moves_with']}" if e["moves_with"] else "unclear"
            parts.append(f"{c} {how} (static {e['static_px']:.1f} px, shifted by the "
                         f"scene {e['flowed_px']:.1f} px)")
    return (f"{detail['pairs']} pairs of frames, the scene moved {detail['scene_motion_px']}"
            f" px: " + "; ".join(parts)) if detail["pairs"] else (
            "the scene moved too little in the image between frames to tell")


def _colour_why(check: Mapping[str, Any] | None) -> str:
    """For the no-stripe error: the laser contrast searched, where the views' check (or,
    without views, the check by motion) chose it over the laser frames' own vote (else
    "")."""
    if not check or check.get("colour") in (None, check.get("colour_by_laser_frames")):
        return ""
    if "motion" in check:
        return (f" in the {check['colour']} contrast: the {check['colour_by_laser_frames']} "
                "ridges do not stay put between frames of a sweep (the scene's texture), "
                f"the {check['colour']} ones do, as the laser's "
                f"({_motion_text(check['motion'])}), and the {check['colour']} laser is too "
                "faint there to be found")
    return (f" in the {check['colour']} contrast: the {check['colour_by_laser_frames']} "
            "ridges of the laser sheet's band are the scene's texture (the views, without "
            f"the laser, show them as well; excess over the views: "
            f"{_scores_text(check['excess'])}), and the {check['colour']} laser is too "
            "faint there to be found")


def _scores_text(scores: Mapping[str, float]) -> str:
    """``"red 979, green 0, ..."``: a contrast's scores for the log."""
    return ", ".join(f"{k} {v:.0f}" for k, v in scores.items())


def _views_for_colour(path: str, cfg: Mapping[str, Any], calibration: str | None,
                      frames: list, T_camera_laser: np.ndarray, axes: list, ridge: bool
                      ) -> Callable[[], tuple[list, list, list, str | None]]:
    """A loader of up to 12 evenly spaced views of the recording, decoded, each with its
    region of interest (where the laser sheet inside the workspace box would project
    from the view's pose, the laser where it is at its camera's first laser frame,
    :func:`_sheet_rois`) and its camera's scan axis: the scene
    without the laser, for the laser colour's check. Views of a camera that recorded no
    laser frame are left out. Returns empty lists and the reason when there are none or
    their poses or images cannot be read (the silhouettes stage names such a view)."""
    from ..errors import RecordingError, TransformError
    from ..viz import spaced_indices

    def load() -> tuple[list, list, list, str | None]:
        try:
            vrec = open_recording(path, cfg, roles=("views",), require=False,
                                  calibration=calibration)
            first: dict[str, int] = {}
            for i, m in enumerate(frames):
                first.setdefault(str(m.frame_id), i)
            views = [m for m in sorted(vrec.views, key=lambda m: m.timestamp_ns)
                     if str(m.frame_id) in first]
            if not views:
                return [], [], [], "no views of the laser's camera in the recording"
            views = [views[int(i)] for i in spaced_indices(len(views), 12)]
            idx = [first[str(m.frame_id)] for m in views]
            roi, _, _ = _sheet_rois(vrec, cfg, [vrec.camera_for(m) for m in views],
                                    vrec.camera_poses(views), T_camera_laser[idx], ridge)
            return ([vrec.decode(m) for m in views], [roi(k) for k in range(len(views))],
                    [axes[i] for i in idx], None)
        except (RecordingError, TransformError, ValueError) as e:
            log.warning("stripes: the views could not be read for the laser colour's "
                        "check: %s", e)
            return [], [], [], f"views not readable: {e}"

    return load


def _detect(rec, frames: list, background: Callable, roi: Callable,
            options: StripeOptions, n_threads: int, axes: list, path: str = "recording"
            ) -> tuple[list, float, float]:
    """Every frame decoded and searched (:func:`robo3d.stripes.extract_stripe_centres`)
    on ``n_threads`` threads, along its axis where ``axes`` gives one: the frames' stripe
    points, in order, and the CPU seconds of decoding and of detection."""
    by_axis = {a: options.replace(axis=a) for a in ("columns", "rows")}
    from concurrent.futures import ThreadPoolExecutor

    from ..stripes import extract_stripe_centres

    def work(i: int):
        ta = time.perf_counter()
        # a rational_polynomial camera's stripe is found in the raw image and its centres
        # moved to the rectified camera exactly (robo3d.camera.Rectifier): resampling the
        # frame first would lower a narrow stripe's peak and shift its centre
        rect = rec.rectifiers.get(frames[i].frame_id)
        image = rec.decode(frames[i]) if rect is None else rec.decode_raw(frames[i])
        bg = background(i, image, raw=rect is not None)
        region = roi(i)
        if rect is not None and region is not None:
            region = rect.raw_mask(region)
        tb = time.perf_counter()
        try:
            sp = extract_stripe_centres(image, background=bg, roi=region,
                                        options=by_axis.get(axes[i], options))
            if rect is not None and len(sp):
                sp = _rectified(sp, rect)
        except ValueError as exc:  # the frame itself (or its laser-off frame): named
            raise StageError(f"{path}: topic {frames[i].topic}, frame {i} (t="
                             f"{frames[i].timestamp_ns} ns"
                             f"{', with its laser-off frame' if bg is not None else ''}): "
                             f"{exc}") from None
        return sp, tb - ta, time.perf_counter() - tb

    progress = Progress("finding stripes", len(frames))
    found, decode_s, detect_s = [], 0.0, 0.0
    with ThreadPoolExecutor(max_workers=n_threads) as pool:
        for i, (sp, td, tx) in enumerate(pool.map(work, range(len(frames)))):
            found.append(sp)
            decode_s += td
            detect_s += tx
            progress(i + 1)
    return found, decode_s, detect_s


def _report(stripes: Stripes, sc: Mapping[str, Any], options: StripeOptions, colour_scores,
            use_roi: bool, roi_area: np.ndarray, n_off: int) -> dict[str, Any]:
    """The stage's report (without the timings): counts, why frames have no stripe, the
    stripes' brightness, axes and angles, the detector's settings and the region used;
    warns about frames without a stripe."""
    from ..stripes import REJECTION_REASONS

    counts = stripes.counts
    n_frames, n_points = len(counts), int(counts.sum())
    rejected, n_lines = stripes.rejected, stripes.n_lines
    empty = counts == 0
    # why a frame has no stripe: every line too weak (nothing lit brightly enough: the
    # sheet misses the object, or falls on the dim table only), or the lines that had a
    # stripe were all rejected for another reason
    all_weak = empty & (rejected[:, REJECTION_REASONS.index("too_weak")]
                        + rejected[:, REJECTION_REASONS.index("outside_roi")] == n_lines)
    if empty.any():
        log.warning("%d of %d laser frames have no stripe (%d with every line too weak: "
                    "the sheet misses the object or lights only the dim table)",
                    int(empty.sum()), n_frames, int(all_weak.sum()))
    s_frame, axes, angles = stripes.s, stripes.axis, stripes.angle_deg
    with_stripe = ~empty
    return {
        "n_frames": n_frames, "n_points": n_points,
        "frames_without_stripe": int(empty.sum()),
        "frames_without_stripe_all_lines_too_weak": int(all_weak.sum()),
        "rejected": {k: int(rejected[:, j].sum()) for j, k in enumerate(REJECTION_REASONS)},
        "points_per_frame_mean": n_points / max(n_frames, 1),
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
        "detector": sc["detector"], "laser_colour": options.colour,
        "centre_on": options.centre_on,
        "laser_colour_scores": colour_scores,
        "roi": {"used": use_roi, "source": "laser sheet inside the workspace box"
                if use_roi else None,
                "margin_px": float(sc["roi_margin_px"]) if use_roi else None,
                "area_fraction_median": float(np.nanmedian(roi_area))
                if use_roi and np.isfinite(roi_area).any() else None},
        "laser_off_frames": n_off,
        "method": sc["method"], "reference": sc["reference"] if sc["s"] is None else "frame"}


def _log_rerun(path: str, rec_name: str, frames: list, cameras: list, poses: np.ndarray,
               found: list, report: dict, max_images: int, sweep_of: np.ndarray,
               decode) -> None:
    """The laser camera (``base/stripes/camera``) on a few evenly spaced frames that hold a
    stripe, each with its image (brightened for the screen: laser frames are dim) and its
    stripe pixels over it (the faint search's in :data:`robo3d.viz.FAINT_STRIPE_RGB`),
    along the ``time``, ``frame`` and ``sweep`` timelines; the
    stripe points of every frame as a scalar (``metrics/stripes/points``); the report."""
    import cv2

    from ..viz import (
        FAINT_STRIPE_RGB,
        STRIPE_RGB,
        display_gain,
        display_image,
        log_camera,
        log_report,
        log_scalar,
        rerun_log,
        set_image_time,
        spaced_indices,
    )

    with_stripe = np.array([i for i, sp in enumerate(found) if len(sp.pixels_uv)], dtype=int)
    pool = with_stripe if len(with_stripe) else np.arange(len(frames))
    chosen = pool[spaced_indices(len(pool), max_images)]
    images = {int(i): decode(frames[i]) for i in chosen}  # rectified where the camera is
    gain = display_gain(list(images.values()))
    with rerun_log(path, rec_name) as rr_stream:
        for i, sp in enumerate(found):
            set_image_time(rr_stream, frames[i].timestamp_ns, frame=i, sweep=int(sweep_of[i]))
            log_scalar(rr_stream, "metrics/stripes/points", len(sp.pixels_uv))
            if i not in images:
                continue
            shown = display_image(images[i], gain)
            if shown.ndim == 3:  # the decoder's RGB; the encoder takes BGR
                shown = shown[..., ::-1]
            ok, jpeg = cv2.imencode(".jpg", shown, [cv2.IMWRITE_JPEG_QUALITY, 90])
            # the faint search's centres (stripes module, step 9) in their own colour
            colors = np.where(sp.faint[:, None], np.array(FAINT_STRIPE_RGB, np.uint8),
                              np.array(STRIPE_RGB, np.uint8))
            log_camera(rr_stream, "base/stripes/camera", cameras[i], poses[i],
                       encoded=(jpeg.tobytes(), "image/jpeg") if ok else None,
                       points_uv=sp.pixels_uv, static=False, points_color=colors)
        log_report(rr_stream, "reports/stripes", {**report, "display_gain": round(gain, 2)})
