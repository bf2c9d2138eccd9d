"""A calibration recording in, a checked calibration out (issue 13, items 1 and 2).

:func:`calibrate_recording` runs the parts in order and hands each the previous one's
result:

* **robot cell** (static board in ``base``, the robot moves the camera): board detection
  in every view (:mod:`robo3d.calibration.target`), intrinsics and distortion
  (:mod:`robo3d.calibration.intrinsics`), hand-eye ``flange -> camera`` refined jointly
  with the board's pose in ``base`` (:mod:`robo3d.calibration.handeye`), then the laser
  sheet from the stripe on the board in the laser frames, each frame's board pose coming
  from the chain ``base -> flange -> camera`` (:mod:`robo3d.calibration.sheet`);
* **fixed camera, moving board** (``robo3d.target`` ``moving = true``): intrinsics, then
  the laser sheet from the boards detected in the laser frames themselves; no hand-eye.

Then the quality gates (:mod:`robo3d.calibration.gates`). :func:`calibration_report`
is the report (per-view RMS, the views left out and why, the gate table) and
:func:`to_calibration_file` the calibration file's content
(:mod:`robo3d.calibration.io`).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ..camera import CameraModel
from ..errors import CalibrationError, RecordingError
from .gates import GateResult, evaluate_gates, failure_message, gate_table, tilt_spread_deg
from .io import CalibrationFile

__all__ = ["CalibrationResult", "calibrate_recording", "calibration_report",
           "to_calibration_file", "detection_picture", "GateFailure"]


@dataclass
class CalibrationResult:
    """Everything one calibration found, and the figures the gates judge.

    Attributes
    ----------
    name, recording : str
        The calibration's name (``results/calibration/<name>.yaml``) and its file.
    kind : str
        ``robot_cell`` (static board, hand-eye) or ``moving_target`` (fixed camera).
    target : robo3d.calibration.target.Target
    camera : CameraModel
        The calibrated intrinsics.
    rms_px : float
        Reprojection RMS of the intrinsics' fit over the used views, pixels.
    per_view_rms_px : (M,) float64
        Per used view.
    views_used : (M,) int
        Indices (into the views in time order) of the views the fit used.
    views_left_out : dict
        Index -> reason, for every view not used.
    T_camera_target : (M, 4, 4) float64
        The board's pose in the camera per used view.
    view_stamps_ns : (V,) int64
        Every view's time.
    edge_width_px : (V,) float64
        Every view's board edge width (``estimateChessboardSharpness``; NaN: not found).
    intrinsics_std : dict
        1-sigma uncertainty of ``fx, fy, cx, cy, k1, ...``.
    T_base_flange : (M, 4, 4) float64 or None
        The robot's flange pose at each used view (robot cell).
    T_flange_camera, T_base_target : (4, 4) float64 or None
        Hand-eye and the board's pose in ``base`` (robot cell).
    handeye_rms_px : float or None
        Reprojection RMS through the robot chain after the joint refinement.
    handeye_per_view_rms_px : (M,) float64 or None
    board_scatter_mm : float or None
        Standard deviation of the board origin's position in ``base`` over the views.
    handeye_closed_form : dict
        The closed form's figures (method, RMS, scatter) beside the refined ones.
    T_camera_laser : (4, 4) float64 or None
    laser_sheet : dict or None
        ``normal``, ``offset_m``, ``six_parameters``, ``rms_mm``.
    sheet_rms_mm : float or None
    sheet_frames_used : (L,) int
        Indices (into the laser frames in time order) of the frames the plane used.
    sheet_left_out : dict
        Index -> reason.
    sheet_per_frame_rms_mm : (L,) float64
    gates : list of GateResult
    notes : list of str
    seconds : float
    view_corners : dict of int to (N, 2) float64
        The detected corners of every view where the board was found (for the picture).
    sheet_pixels_uv : dict of int to (n, 2) float64
        The stripe pixels of each laser frame the sheet used.
    """

    name: str
    recording: str
    kind: str
    target: Any
    camera: CameraModel
    rms_px: float
    per_view_rms_px: np.ndarray
    views_used: np.ndarray
    views_left_out: dict[int, str]
    T_camera_target: np.ndarray
    view_stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    edge_width_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    intrinsics_std: dict[str, float] = field(default_factory=dict)
    T_base_flange: np.ndarray | None = None
    T_flange_camera: np.ndarray | None = None
    T_base_target: np.ndarray | None = None
    handeye_rms_px: float | None = None
    handeye_per_view_rms_px: np.ndarray | None = None
    board_scatter_mm: float | None = None
    handeye_closed_form: dict[str, Any] = field(default_factory=dict)
    T_camera_laser: np.ndarray | None = None
    laser_sheet: dict[str, Any] | None = None
    sheet_rms_mm: float | None = None
    sheet_frames_used: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    sheet_left_out: dict[int, str] = field(default_factory=dict)
    sheet_per_frame_rms_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    gates: list[GateResult] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0
    view_corners: dict[int, np.ndarray] = field(default_factory=dict)
    sheet_pixels_uv: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def failed_gates(self) -> list[GateResult]:
        return [g for g in self.gates if g.passed is False]


class GateFailure(CalibrationError):
    """A calibration that failed a quality gate; ``result`` keeps what was found (for the
    report of a failed calibration)."""

    def __init__(self, message: str, result: CalibrationResult, *, path: str | None = None):
        super().__init__(message, path=path)
        self.result = result


# ---------------------------------------------------------------------------- orchestration
def _sorted_images(msgs: list) -> list:
    return sorted(msgs, key=lambda m: m.timestamp_ns)


def _camera_frame(recording) -> tuple[str, CameraModel]:
    """The calibrated camera: the frame_id of the views (one camera per recording) and
    its published model; without one (nothing to trust anyway), a placeholder at the
    first view's size (f = the longer side, the image centre), which only sets the image
    size and OpenCV's starting point."""
    views = recording.views
    if not views:
        raise RecordingError("a calibration recording needs views of the target on the views "
                             "topic; it has none", path=recording.path)
    fids = sorted({m.frame_id for m in views})
    if len(fids) > 1:
        raise RecordingError(f"the views come from {len(fids)} cameras ({', '.join(fids)}); "
                             "robo3d calibrates one camera per recording", path=recording.path)
    if fids[0] in recording.calibrations:
        return fids[0], recording.calibrations[fids[0]]
    h, w = views[0].decode().shape[:2]
    f = float(max(w, h))
    return fids[0], CameraModel(fids[0], w, h, np.array([[f, 0, (w - 1) / 2],
                                                         [0, f, (h - 1) / 2], [0, 0, 1]]))


def _detect(recording, msgs: list, target, options) -> list:
    from .target import detect_boards

    return detect_boards((recording.decode(m) for m in msgs), target, options)


def calibrate_recording(recording, cfg: Mapping[str, Any], name: str | None = None,
                        check: bool = True) -> CalibrationResult:
    """Calibrate from a ``kind=calibration`` recording and judge the result.

    Parameters
    ----------
    recording : robo3d.recording.Recording
        Read with views (the target) and, when it has them, laser frames.
    cfg : mapping
        The validated config (sections ``calibration``, ``laser_sheet``,
        ``calibration_gates``, ``frames``, ``seed``).
    name : str, optional
        The calibration's name; the recording's file name by default.
    check : bool
        Raise :class:`GateFailure` when a gate fails (else only record it in ``gates``).

    Returns
    -------
    CalibrationResult

    Raises
    ------
    RecordingError
        Not a calibration recording (``kind``), no target metadata, no views.
    GateFailure
        A quality gate failed (``check``); its message names every failed gate.
    """
    from pathlib import Path

    from .target import DetectOptions, target_from_recording

    t0 = time.perf_counter()
    kind = recording.info.get("kind")
    if kind != "calibration":
        raise RecordingError(f"metadata robo3d.recording kind is {kind!r}: only kind="
                             "calibration recordings are calibrated from", path=recording.path)
    target = target_from_recording(recording)
    # the lens model is estimated from the images as recorded: a published
    # rational_polynomial or fisheye camera's images are not rectified here
    # (robo3d.camera.Rectifier)
    raw_note = ([f"the images of {', '.join(sorted(recording.rectifiers))} are read as "
                 "recorded (not rectified from the published lens model): "
                 "the calibrated plumb_bob model describes the raw images"]
                if recording.rectifiers else [])
    recording = replace(recording, rectifiers={})
    frame_id, published = _camera_frame(recording)
    if frame_id not in recording.calibrations:  # decode() checks sizes against it
        recording = replace(recording, calibrations={**recording.calibrations,
                                                     frame_id: published})
    views = _sorted_images([m for m in recording.views if m.frame_id == frame_id])
    stamps = np.array([m.timestamp_ns for m in views], dtype=np.int64)
    detections = _detect(recording, views, target, DetectOptions.from_config(cfg["calibration"]))
    res = _intrinsics(detections, target, published, cfg, str(recording.path))
    result = CalibrationResult(
        name=name or Path(recording.path).stem, recording=str(recording.path),
        kind="moving_target" if target.moving else "robot_cell", target=target,
        camera=res.camera, rms_px=float(res.rms_px),
        per_view_rms_px=np.asarray(res.per_view_rms, dtype=np.float64),
        views_used=np.asarray(res.used, dtype=int),
        views_left_out={int(k): str(v) for k, v in res.rejected.items()},
        T_camera_target=np.asarray(res.T_camera_target, dtype=np.float64).reshape(-1, 4, 4),
        view_stamps_ns=stamps,
        edge_width_px=np.array([d.sharpness for d in detections], dtype=np.float64),
        intrinsics_std={k: float(v) for k, v in dict(res.std).items()},
        view_corners={i: d.corners for i, d in enumerate(detections) if d.corners is not None})
    result.notes.extend(raw_note)
    if not target.moving:
        _handeye(recording, result, detections, cfg)
    lasers = _sorted_images([m for m in recording.laser_frames if m.frame_id == frame_id])
    if lasers:
        _sheet(recording, result, lasers, cfg)
    else:
        result.notes.append("no laser frames: no laser sheet calibrated")
    result.gates = evaluate_gates(result, cfg["calibration_gates"])
    result.seconds = round(time.perf_counter() - t0, 3)
    failed = result.failed_gates
    if check and failed:
        raise GateFailure(failure_message(failed), result, path=recording.path)
    return result


def _intrinsics(detections: list, target, published: CameraModel, cfg: Mapping[str, Any],
                path: str):
    """Intrinsics (:func:`robo3d.calibration.intrinsics.calibrate_intrinsics`), with the
    camera model attached as ``camera``."""
    from .intrinsics import IntrinsicsOptions, calibrate_intrinsics

    res = calibrate_intrinsics(detections, target, (published.width, published.height),
                               IntrinsicsOptions.from_config(cfg["calibration"]),
                               recording=path)
    res.camera = CameraModel(published.frame_id, published.width, published.height,
                             np.asarray(res.K), np.asarray(res.D))
    return res


def _handeye(recording, result: CalibrationResult, detections: list,
             cfg: Mapping[str, Any]) -> None:
    """Hand-eye and the board in ``base`` (robot cell), refined jointly with the
    intrinsics (:func:`robo3d.calibration.handeye.refine_handeye`)."""
    from .handeye import HandEyeOptions, refine_handeye

    t_used = result.view_stamps_ns[result.views_used]
    T_bf = recording.tf.lookup(recording.base_frame, "flange", t_used)
    result.T_base_flange = T_bf
    corners = np.stack([detections[int(i)].corners for i in result.views_used])
    cam = result.camera
    out = refine_handeye(T_bf, corners, result.target, cam.K, cam.D,
                         T_camera_target=result.T_camera_target,
                         options=HandEyeOptions.from_config(cfg["calibration"]),
                         recording=str(recording.path))
    result.T_flange_camera = np.asarray(out.T_flange_camera, dtype=np.float64)
    result.T_base_target = np.asarray(out.T_base_target, dtype=np.float64)
    result.handeye_rms_px = float(out.rms_px)
    result.handeye_per_view_rms_px = np.asarray(out.per_view_rms, dtype=np.float64)
    result.board_scatter_mm = float(out.board_scatter_mm)
    result.handeye_closed_form = {**dict(out.closed_form or {}),
                                  "rotation_axis_spread_deg": out.rotation_axis_spread_deg}
    # the joint refinement refines the intrinsics too (calibration.refine_intrinsics)
    result.camera = CameraModel(cam.frame_id, cam.width, cam.height, np.asarray(out.K),
                                np.asarray(out.D))


def _sheet(recording, result: CalibrationResult, lasers: list, cfg: Mapping[str, Any]) -> None:
    """The laser sheet from the stripe on the board
    (:func:`robo3d.calibration.sheet.calibrate_sheet`): the board's pose in each laser
    frame from the robot chain (static board) or from the board detected in the frame."""
    from ..stripes import StripeOptions
    from .sheet import SheetOptions, board_poses_from_handeye, calibrate_sheet

    stamps = np.array([m.timestamp_ns for m in lasers], dtype=np.int64)
    if result.T_flange_camera is not None and result.T_base_target is not None:
        T_bf = recording.tf.lookup(recording.base_frame, "flange", stamps)
        poses: list[np.ndarray | None] = list(board_poses_from_handeye(
            T_bf, result.T_flange_camera, result.T_base_target))
        source = "the robot chain"
    else:
        poses, n_still = _board_poses_in_frames(recording, lasers, result, cfg)
        source = "the board detected in each laser frame"
        if n_still:
            source += f" ({n_still} of {len(lasers)}: in a view at the same place)"
    reference = None  # the recorded (nominal) laser keeps its in-plane choices
    if "laser" in recording.tf.frames:
        try:
            reference = recording.tf.lookup(result.camera.frame_id, "laser", int(stamps[0]))
        except RecordingError:
            reference = None
    out = calibrate_sheet((recording.decode(m) for m in lasers), result.camera, poses,
                          SheetOptions.from_config(cfg["laser_sheet"]), target=result.target,
                          stripe_options=StripeOptions.from_config(cfg["stripes"]),
                          encoded=lasers[0].data, reference=reference,
                          seed=int(cfg.get("seed", 0)),
                          source=f"{recording.path}: topic {lasers[0].topic}")
    result.T_camera_laser = np.asarray(out.T_camera_laser, dtype=np.float64)
    result.sheet_rms_mm = float(out.rms_mm)
    result.sheet_frames_used = np.asarray(out.used, dtype=int)
    result.sheet_left_out = {int(k): str(v) for k, v in dict(out.left_out).items()}
    result.sheet_pixels_uv = {int(k): np.asarray(v) for k, v in dict(out.pixels_uv).items()}
    result.sheet_per_frame_rms_mm = np.array(
        [out.per_frame_rms_mm.get(int(i), np.nan) for i in out.used], dtype=np.float64)
    six = dict(out.six_parameters)
    result.laser_sheet = {
        "normal": np.asarray(out.plane.normal, dtype=np.float64).tolist(),
        "offset_m": float(out.plane.offset_m),
        "six_parameters": {k: float(six[k]) for k in ("dx", "dy", "dz", "phi_deg",
                                                      "theta_deg", "psi_deg") if k in six},
        "rms_mm": float(out.rms_mm), "frames_used": len(out.used),
        "tilt_spread_deg": float(out.tilt_spread_deg), "colour": str(out.colour),
        "board_poses_from": source}


def _board_poses_in_frames(recording, lasers: list, result: CalibrationResult,
                           cfg: Mapping[str, Any]) -> tuple[list[np.ndarray | None], int]:
    """The board's pose in each laser frame (moving target): detected, then solvePnP with
    the calibrated camera (None where the board is not found), and the number of frames
    whose pose came from a view.

    Where a view the intrinsics used shows the board at the same place shortly before or
    after the frame (:func:`robo3d.calibration.sheet.still_views`: the board held still),
    PnP runs on that view's corners instead: in the laser frame the exposure is dimmed
    and the line crosses the pattern. Measured on the simulator's fixed rig (seeds 0-2,
    every frame has such a view): the sheet's offset error 0.047 / 0.039 / 0.005 mm from
    the laser frames' corners, 0.000 / 0.025 / 0.017 mm from the views' (0.007 / 0.017 /
    0.011 mm with the true board poses); srv's laser frames have no such view (unchanged).
    ``result.notes`` says how many frames took a view's corners.
    """
    import cv2

    from .sheet import SheetOptions, still_views
    from .target import DetectOptions, board_points

    dets = _detect(recording, lasers, result.target, DetectOptions.from_config(cfg["calibration"]))
    opts = SheetOptions.from_config(cfg["laser_sheet"])
    used = set(int(i) for i in result.views_used)
    n_views = len(result.view_stamps_ns)
    cand = [result.view_corners.get(j) if j in used else None for j in range(n_views)]
    pick = still_views(np.array([m.timestamp_ns for m in lasers], dtype=np.int64),
                       [d.corners if d.ok else None for d in dets], result.view_stamps_ns,
                       cand, float(opts.still_view_max_s), float(opts.still_view_max_px))
    n_still = int((pick >= 0).sum())
    if n_still:
        result.notes.append(f"laser sheet: {n_still} of {len(lasers)} laser frames take the "
                            "board's pose from a view at the same place (corners within "
                            f"{opts.still_view_max_px} px, {opts.still_view_max_s} s)")
    obj = board_points(result.target)
    K, D = result.camera.K, result.camera.D
    out: list[np.ndarray | None] = []
    for d, j in zip(dets, pick, strict=True):
        if not d.ok:
            out.append(None)
            continue
        corners = cand[j] if j >= 0 else d.corners
        ok, rvec, tvec = cv2.solvePnP(obj, corners, K, D, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            out.append(None)
            continue
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(rvec)[0]
        T[:3, 3] = tvec.ravel()
        out.append(T)
    return out, n_still


# ---------------------------------------------------------------------------- outputs
def to_calibration_file(result: CalibrationResult, code: str = "") -> CalibrationFile:
    """The calibration file of a result (:func:`robo3d.calibration.io.write_calibration`)."""
    t = result.target
    quality = {
        "rms_px": result.rms_px,
        "per_view_rms_px": np.round(result.per_view_rms_px, 5).tolist(),
        "views_used": [int(i) for i in result.views_used],
        "views_left_out": {int(k): v for k, v in sorted(result.views_left_out.items())},
        "tilt_spread_deg": tilt_spread_deg(result.T_camera_target),
        "intrinsics_std": result.intrinsics_std,
        "handeye_rms_px": result.handeye_rms_px,
        "board_scatter_mm": result.board_scatter_mm,
        "handeye_closed_form": result.handeye_closed_form or None,
        "T_base_target": result.T_base_target,
        "sheet_rms_mm": result.sheet_rms_mm,
        "sheet_frames_used": [int(i) for i in result.sheet_frames_used],
        "sheet_left_out": {int(k): v for k, v in sorted(result.sheet_left_out.items())},
    }
    source = {"recording": result.recording, "kind": result.kind,
              "target": {"cols": int(t.cols), "rows": int(t.rows), "square_m": float(t.square),
                         "moving": bool(t.moving)},
              "code": code, "notes": list(result.notes)}
    return CalibrationFile(name=result.name, camera=result.camera,
                           T_flange_camera=result.T_flange_camera,
                           T_camera_laser=result.T_camera_laser,
                           laser_sheet=result.laser_sheet, quality=quality,
                           gates=gate_table(result.gates), source=source)


def calibration_report(result: CalibrationResult) -> dict[str, Any]:
    """The report: every view (used or left out, why, its RMS), every laser frame the sheet
    left out, the gate table, the figures beside the closed form's."""
    n_views = len(result.view_stamps_ns)
    rms = dict(zip(map(int, result.views_used), result.per_view_rms_px.tolist(), strict=True))
    he = {}
    if result.handeye_per_view_rms_px is not None:
        he = dict(zip(map(int, result.views_used), result.handeye_per_view_rms_px.tolist(),
                      strict=True))
    views = [{"index": i, "t_s": int(result.view_stamps_ns[i]) / 1e9,
              "used": i in rms, "rms_px": rms.get(i), "handeye_rms_px": he.get(i),
              "edge_width_px": (float(result.edge_width_px[i])
                                if i < len(result.edge_width_px)
                                and np.isfinite(result.edge_width_px[i]) else None),
              "left_out": result.views_left_out.get(i)} for i in range(n_views)]
    cam = result.camera
    return {
        "name": result.name, "recording": result.recording, "kind": result.kind,
        "passed": not result.failed_gates,
        "gates": gate_table(result.gates),
        "failed_gates": [g.line() for g in result.failed_gates],
        "intrinsics": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                       "D": cam.D.tolist(), "std": result.intrinsics_std,
                       "rms_px": result.rms_px, "n_views": n_views,
                       "n_used": len(result.views_used),
                       "tilt_spread_deg": tilt_spread_deg(result.T_camera_target)},
        "handeye": None if result.T_flange_camera is None else {
            "T_flange_camera": result.T_flange_camera, "T_base_target": result.T_base_target,
            "rms_px": result.handeye_rms_px, "board_scatter_mm": result.board_scatter_mm,
            "closed_form": result.handeye_closed_form},
        "laser_sheet": result.laser_sheet,
        "laser_frames_left_out": {int(k): v for k, v in sorted(result.sheet_left_out.items())},
        "views": views,
        "views_left_out": {int(k): v for k, v in sorted(result.views_left_out.items())},
        "notes": result.notes, "seconds": result.seconds,
    }


def _dots(image: np.ndarray, uv: np.ndarray, colour: tuple[int, int, int]) -> None:
    """Paint 3 x 3-pixel dots of ``colour`` at the pixels ``uv`` (N, 2) of an (H, W, 3)
    image, in place: one mask, dilated, instead of a circle per point."""
    import cv2

    h, w = image.shape[:2]
    p = np.rint(np.asarray(uv, dtype=np.float64).reshape(-1, 2)).astype(np.int64)
    p = p[(p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)]
    mask = np.zeros((h, w), np.uint8)
    mask[p[:, 1], p[:, 0]] = 1
    image[cv2.dilate(mask, np.ones((3, 3), np.uint8)) > 0] = colour


def detection_picture(path: str, recording, result: CalibrationResult, max_views: int = 12,
                      max_laser: int = 4, tile_px: int = 320) -> None:
    """A PNG of the detections: views with their corners (green: used, orange: found but
    left out, red frame: not found, each with its RMS or the reason), then laser frames
    with the stripe pixels the sheet used (magenta). Evenly spaced samples, tiles
    ``tile_px`` wide."""
    import cv2

    from ..atomic import atomic_path
    from .target import to_gray8

    views = _sorted_images([m for m in recording.views
                            if m.frame_id == result.camera.frame_id])
    lasers = _sorted_images([m for m in recording.laser_frames
                             if m.frame_id == result.camera.frame_id])
    rms = dict(zip(map(int, result.views_used), result.per_view_rms_px.tolist(), strict=True))
    pick = np.unique(np.linspace(0, len(views) - 1, min(max_views, len(views))).astype(int)) \
        if views else np.zeros(0, int)
    left = sorted(result.views_left_out)[:4]  # always show some of the left-out views
    pick = np.unique(np.concatenate([pick, left]).astype(int))[:max_views + 4]
    used_l = sorted(result.sheet_pixels_uv)
    lpick = [used_l[i] for i in np.unique(np.linspace(0, len(used_l) - 1, min(max_laser,
                                                                                len(used_l))
                                                        ).astype(int))] if used_l else []
    tiles = []

    def tile(img: np.ndarray, draw) -> np.ndarray:
        g = cv2.cvtColor(to_gray8(img), cv2.COLOR_GRAY2BGR)
        s = tile_px / g.shape[1]
        g = cv2.resize(g, (tile_px, max(1, round(g.shape[0] * s))), interpolation=cv2.INTER_AREA)
        draw(g, s)
        return g

    for i in pick:
        i = int(i)

        def draw(g, s, i=i):
            c = result.view_corners.get(i)
            colour = (0, 200, 0) if i in rms else (0, 140, 255)
            if c is not None:
                _dots(g, c * s, colour)
            text = f"view {i}: {rms[i]:.2f} px" if i in rms else \
                f"view {i}: {result.views_left_out.get(i, '')}"[:48]
            if c is None:
                cv2.rectangle(g, (0, 0), (g.shape[1] - 1, g.shape[0] - 1), (0, 0, 230), 3)
            cv2.putText(g, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1,
                        cv2.LINE_AA)
        tiles.append(tile(recording.decode(views[i]), draw))
    for k in lpick:
        def draw_l(g, s, k=k):
            _dots(g, result.sheet_pixels_uv[k] * s, (255, 0, 255))
            cv2.putText(g, f"laser frame {k}", (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                        (255, 255, 255), 1, cv2.LINE_AA)
        if 0 <= k < len(lasers):
            tiles.append(tile(recording.decode(lasers[k]), draw_l))
    if not tiles:
        tiles = [np.zeros((tile_px * 3 // 4, tile_px, 3), np.uint8)]
    h = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, h - t.shape[0]), (0, 0), (0, 0))) for t in tiles]
    cols = 4
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[r:r + cols], axis=1) for r in range(0, len(tiles), cols)]
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.concatenate(rows, axis=0)):
            raise OSError(f"cannot write {path}")
