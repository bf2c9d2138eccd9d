"""Camera intrinsics and distortion from board views (Zhang 2000, through OpenCV).

:func:`calibrate_intrinsics` runs OpenCV's ``calibrateCameraExtended`` (plumb_bob:
``k1 k2 p1 p2 k3``; OpenCV 5.0's default sparse Levenberg-Marquardt with the Schur
complement) on the views whose detection is good, and then, robustly, again without the
views whose reprojection RMS is an outlier: above ``outlier_factor`` times the median
view's *and* above ``outlier_min_px`` (both, so a calibration whose views are all good
to 0.1 px does not lose its worst ones for being 3x the median). At most
``max_outlier_rounds`` rounds; each left-out view is listed with its reason, as are the
views whose detection failed.

Per-view and overall RMS are recomputed here from ``projectPoints`` (the overall one is
OpenCV's definition: the root of the mean squared 2-D residual norm over all corners). The
parameters' uncertainty is OpenCV's (1 sigma from the Jacobian at the solution, scaled by
the residual), named ``fx fy cx cy k1 k2 p1 p2 k3``.

Degenerate input is refused with a :class:`~robo3d.errors.CalibrationError` that names
the recording when the caller gives it: fewer than ``min_views`` good views, or views
whose board normals in the camera all lie within ``min_tilt_spread_deg`` of each other
(parallel boards: Zhang's method cannot separate the focal length from the distance).

References
----------
Zhang, Z. "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000.
Brown, D. C. "Decentering distortion of lenses", Photogrammetric Engineering 32(3), 1966
(the plumb_bob model).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence

import numpy as np

from ..errors import CalibrationError
from ..options import Options
from .target import BoardDetection, Target, board_points

__all__ = ["IntrinsicsOptions", "IntrinsicsResult", "calibrate_intrinsics", "rvec_tvec_to_T",
           "tilt_spread_deg", "STD_NAMES"]

_log = logging.getLogger(__name__)

#: Names of the intrinsic parameters in :attr:`IntrinsicsResult.std`.
STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")


@dataclasses.dataclass(frozen=True)
class IntrinsicsOptions(Options):
    """Intrinsic calibration's parameters (config section ``calibration``).

    Attributes
    ----------
    min_views : int
        Fewest good views to calibrate from.
    outlier_factor : float
        A view whose RMS exceeds this multiple of the median view's (and ``outlier_min_px``)
        is left out.
    outlier_min_px : float, pixels
        ... but only when its RMS is above this too.
    max_outlier_rounds : int
        Rounds of leaving out outliers and calibrating again.
    fix_k3 : bool
        Keep ``k3 = 0`` (narrow lenses, where ``k3`` is poorly determined).
    min_tilt_spread_deg : float, degrees
        The board normals of the views must spread by at least this much.
    """

    section = "calibration"

    min_views: int = 3
    outlier_factor: float = 3.0
    outlier_min_px: float = 0.5
    max_outlier_rounds: int = 5
    fix_k3: bool = False
    min_tilt_spread_deg: float = 5.0


@dataclasses.dataclass
class IntrinsicsResult:
    """Result of :func:`calibrate_intrinsics`.

    Attributes
    ----------
    K : (3, 3) float64
    D : (5,) float64
        plumb_bob ``k1 k2 p1 p2 k3``.
    image_size : (width, height)
    rms_px : float
        Overall reprojection RMS of the used views.
    per_view_rms : (M,) float64
        Per used view, in the order of ``used``.
    std : dict of str -> float
        1-sigma uncertainty of ``fx fy cx cy k1 k2 p1 p2 k3``.
    used : (M,) int
        Indices (into the detections) of the views used.
    rejected : dict of int -> str
        Every other view with its reason.
    T_camera_target : (M, 4, 4) float64
        The board's pose in the camera per used view.
    tilt_spread_deg : float
        Largest angle between two used views' board normals.
    """

    K: np.ndarray
    D: np.ndarray
    image_size: tuple[int, int]
    rms_px: float
    per_view_rms: np.ndarray
    std: dict[str, float]
    used: np.ndarray
    rejected: dict[int, str]
    T_camera_target: np.ndarray
    tilt_spread_deg: float
    rounds: int = 1


def rvec_tvec_to_T(rvecs: np.ndarray, tvecs: np.ndarray) -> np.ndarray:
    """``(M, 4, 4)`` transforms from ``(M, 3)`` rotation vectors and translations
    (Rodrigues' formula, vectorised)."""
    r = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
    t = np.asarray(tvecs, dtype=np.float64).reshape(-1, 3)
    theta = np.linalg.norm(r, axis=1)
    small = theta < 1e-12
    k = r / np.where(small, 1.0, theta)[:, None]
    kx = np.zeros((len(r), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    kx[:, 1, 0], kx[:, 2, 0], kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    R = np.eye(3) + s * kx + (1 - c) * (kx @ kx)
    T = np.zeros((len(r), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T


def tilt_spread_deg(T_camera_target: np.ndarray) -> float:
    """Largest angle between two views' board normals (``z`` axes) in the camera."""
    n = np.asarray(T_camera_target)[:, :3, 2]
    if len(n) < 2:
        return 0.0
    cos = np.clip(n @ n.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(cos.min())))


def _where(recording: str | None) -> dict:
    return {"path": recording} if recording else {}


def _per_view_rms(obj: np.ndarray, img: list[np.ndarray], rvecs, tvecs, K, D) -> np.ndarray:
    import cv2

    out = np.zeros(len(img))
    for i, (uv, r, t) in enumerate(zip(img, rvecs, tvecs, strict=True)):
        p = cv2.projectPoints(obj, r, t, K, D)[0].reshape(-1, 2)
        out[i] = np.sqrt(np.mean(np.sum((p - uv) ** 2, axis=1)))
    return out


def calibrate_intrinsics(detections: Sequence[BoardDetection], target: Target,
                         image_size: tuple[int, int],
                         options: IntrinsicsOptions | None = None, *,
                         recording: str | None = None) -> IntrinsicsResult:
    """Intrinsics and distortion from the good views, leaving out outliers.

    Parameters
    ----------
    detections : sequence of BoardDetection
        One per view (:func:`~robo3d.calibration.target.detect_boards`).
    target : Target
    image_size : (width, height), pixels
    options : IntrinsicsOptions, optional
    recording : str, optional
        The recording's path, named in errors.

    Returns
    -------
    IntrinsicsResult

    Raises
    ------
    CalibrationError
        Fewer than ``min_views`` good views (the reasons of the bad ones summarised), views
        all parallel, or OpenCV failing.
    """
    import cv2

    opts = options or IntrinsicsOptions()
    w, h = int(image_size[0]), int(image_size[1])
    rejected: dict[int, str] = {i: d.reason or "not found" for i, d in enumerate(detections)
                                if not d.ok}
    used = np.array([i for i, d in enumerate(detections) if d.ok], dtype=int)
    obj = board_points(target).astype(np.float32)

    def too_few(n: int, what: str) -> CalibrationError:
        reasons: dict[str, int] = {}
        for r in rejected.values():
            key = r.split(":")[0].split(" (")[0]
            reasons[key] = reasons.get(key, 0) + 1
        summary = ", ".join(f"{k}: {v}" for k, v in sorted(reasons.items())) or "none"
        return CalibrationError(
            f"intrinsics: {n} usable board views{what}, at least {opts.min_views} needed "
            f"({len(detections)} views; left out: {summary})", **_where(recording))

    if len(used) < max(3, opts.min_views):
        raise too_few(len(used), "")
    flags = cv2.CALIB_FIX_K3 if opts.fix_k3 else 0
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    rounds = 0
    while True:
        rounds += 1
        img = [np.ascontiguousarray(detections[i].corners, dtype=np.float32) for i in used]
        try:
            _, K, D, rvecs, tvecs, std_i, _, _ = cv2.calibrateCameraExtended(
                [obj] * len(img), img, (w, h), None, None, flags=flags, criteria=crit)
        except cv2.error as exc:
            raise CalibrationError(f"intrinsics: OpenCV calibrateCamera failed on {len(img)} "
                                   f"views: {str(exc).strip().splitlines()[-1]}",
                                   **_where(recording)) from None
        rvecs = np.asarray(rvecs, dtype=np.float64).reshape(-1, 3)
        tvecs = np.asarray(tvecs, dtype=np.float64).reshape(-1, 3)
        K = np.asarray(K, dtype=np.float64)
        D = np.asarray(D, dtype=np.float64).ravel()[:5]
        per_view = _per_view_rms(obj.astype(np.float64), [x.astype(np.float64) for x in img],
                                 rvecs, tvecs, K, D)
        med = float(np.median(per_view))
        bad = (per_view > opts.outlier_factor * med) & (per_view > opts.outlier_min_px)
        if not bad.any() or rounds > opts.max_outlier_rounds:
            break
        if len(used) - int(bad.sum()) < max(3, opts.min_views):
            break
        for i, r in zip(used[bad], per_view[bad], strict=True):
            rejected[int(i)] = (f"reprojection outlier: RMS {r:.3f} px > {opts.outlier_factor:g}"
                                f" x median {med:.3f} px and > {opts.outlier_min_px:g} px")
        used = used[~bad]
    T = rvec_tvec_to_T(rvecs, tvecs)
    spread = tilt_spread_deg(T)
    if spread < opts.min_tilt_spread_deg:
        raise CalibrationError(
            f"intrinsics: the {len(used)} board views are all parallel (their normals spread "
            f"by {spread:.2f} deg < {opts.min_tilt_spread_deg:g} deg): the focal length is "
            f"not determined; tilt the board (or the camera) by 10-45 deg in several "
            f"directions", **_where(recording))
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(D))):
        raise CalibrationError("intrinsics: OpenCV returned non-finite K or D",
                               **_where(recording))
    rms = float(np.sqrt(np.mean(per_view ** 2)))  # every view has the same corner count
    std_v = np.asarray(std_i, dtype=np.float64).ravel()
    std = {n: float(std_v[k]) if k < std_v.size else float("nan")
           for k, n in enumerate(STD_NAMES)}
    _log.info("intrinsics from %d views: RMS %.3f px, f = %.1f / %.1f, pp = (%.1f, %.1f)",
              len(used), rms, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    return IntrinsicsResult(K=K, D=D, image_size=(w, h), rms_px=rms, per_view_rms=per_view,
                            std=std, used=used, rejected=dict(sorted(rejected.items())),
                            T_camera_target=T, tilt_spread_deg=spread, rounds=rounds)
