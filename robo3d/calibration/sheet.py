"""Laser sheet calibration: the laser plane in the camera from the stripe on a board.

Seed §3.3 calibrates the cell with a target in known positions and a least-squares fit;
for the laser (§4.1) that means: in each laser frame the board's pose is known, so the
stripe pixels that fall on the board are points of a known plane; cast as rays
through the calibrated camera (:meth:`robo3d.camera.CameraModel.rays`, lens distortion
undone) and cut with that plane, they are 3D points of the laser sheet. One plane fitted
to the points of all frames is the sheet (issue 13).

Per frame (:func:`calibrate_sheet`)
-----------------------------------
* The board's pose ``T_camera_target`` comes from the caller: from the board detected in
  the laser frame itself (fixed camera, moving board: ``srv_laser_calibration``'s
  laser frames are separate hand-held poses, not paired with the views, and the board is
  found in them despite the line), or from the hand-eye chain
  ``inv(T_base_flange X) T_base_target`` in a robot cell (:func:`board_poses_from_handeye`).
  A frame without it is left out ("board not found"). With a moving board, a laser-off
  view within ``still_view_max_s`` of the frame whose corners lie within
  ``still_view_max_px`` (median) of the frame's shows the board held still, and its
  corners give the pose (:func:`still_views`): the laser frame's are worse (the dimmed
  exposure, the line across the pattern). On the simulator's fixed rig (seeds 0-2)
  the laser frames' corners left the board's tilt off by up to 0.16 deg (the views':
  0.044 deg) and the sheet's offset by 0.047 / 0.039 / 0.005 mm; the views' corners
  0.000 / 0.017 / 0.017 mm (the true poses: 0.007 / 0.017 / 0.011 mm). The board's
  depth error is the same either way (+-0.1 mm per frame, its mean following the
  focal length's error), so tilt, not scale, was the laser frames' share.
* The stripe is found with the project's detector (:mod:`robo3d.stripes`, the config's
  ``stripes`` section, the laser colour found once for the recording as the stripes
  stage does) inside the board's region only (its region of interest): the detector keeps
  one centre per image line, and a line that crosses the board and the room must give
  the board's.
* The board's region is a rectangle of the board's plane: the inner corners' grid grown
  by ``board_margin_x_squares`` along the columns and ``board_margin_y_squares`` along
  the rows. Their defaults (3.0, 2.0) cover the white border of ``srv``'s board around
  the printed pattern (measured on its frames: the white reaches ~3.3 squares beyond
  the outer inner corners sideways and ~2.3 up and down): the fixed laser line falls
  mostly on that border, rarely on the pattern. A target that knows its border (an
  attribute ``margin``, metres beyond the outer squares, as the simulator's boards
  have) limits the region to a quarter square inside the board's edge. A region beyond
  the physical board casts the room's stripe onto the board's plane: those points
  leave the sheet, and the line test and RANSAC drop them. So in each frame the
  border's extent is also read from the image (:func:`board_border_region`): on each
  side the region ends where the border gets darker than next to the pattern by
  ``border_contrast`` (the simulator's board lies on a table only 10 % darker than its
  1-square border, 3 mm below it: without this test that table's stripe, cast onto the
  board's plane, passed the line test and RANSAC and moved the robot cell's sheet by
  0.2 mm).
* On the printed pattern the stripe is only trusted on white squares away from their
  edges (``pattern_edge_squares``): a black square absorbs the laser, and its edges
  are ridges in the luma on which the detector's centres zig-zag (seen on srv's frames
  48, 109, 110: centres 1-3 px off the line on every black square's edge). The default
  0.25 squares: on sharp rendered boards (tests) 0.15 left the frames crossing the
  pattern at 0.1-0.17 mm RMS against 0.01 mm for the others (the detector's window
  reaching the neighbouring black square), 0.25 brings all to 0.01-0.02 mm; on the
  simulator's calibration recordings (true board poses) 0.15 / 0.2 / 0.25 / 0.3 give
  normals within 0.004 / 0.002 / 0.002 / 0.006 deg and offsets within 0.016 / 0.001 /
  0.007 / 0.031 mm of the truth (robot cell; fewer points as it grows); srv's figures
  do not change.
* The sheet meets the board's plane in a straight line, which the camera sees as a
  straight line of the undistorted image: per frame a line is fitted to the kept
  pixels (RANSAC on pairs, then total least squares) and pixels farther than
  ``line_tolerance_px`` from it are dropped (the zig-zag beside the pattern's black
  squares that the square test misses, a stray reflection).
* The kept pixels are cut with the board's plane (:func:`sheet_points`). A frame with
  fewer than ``min_points_per_frame`` of them is left out ("too few pixels").

The fit (:func:`fit_plane_robust`)
----------------------------------
RANSAC (Fischler & Bolles 1981) on minimal triples with a seeded generator, inliers
within ``ransac_threshold_mm``, then total least squares (SVD of the centred inliers)
repeated three times with the inlier set re-selected. A frame whose residual RMS exceeds
``frame_outlier_factor`` times the median frame's (and 0.2 mm) is left out as a frame
residual outlier (a wrong board pose, a blurred frame) and the fit repeated once.
``rms_mm`` is the RMS distance of the inliers to the plane (the figure the independent
srv run reports); ``rms_all_mm`` that of every point of the frames used.

Degenerate input: a plane is not determined by one line. When the points' spread
across their main direction (second principal standard deviation) is below
``min_spread_mm`` — every board in one plane, or all frames showing the same line —
:class:`~robo3d.errors.CalibrationError` names the recording and the frames and asks for
more board tilts and positions.

The result is a plane ``normal · x = offset_m`` in the camera frame, the laser pose
``T_camera_laser`` (the sheet = the laser's x-z plane, its +y = the normal;
:func:`robo3d.triangulation.laser_pose_from_plane`: canonical, or keeping the nominal
pose's in-plane choices when given) and the seed's six parameters of that pose
(:func:`robo3d.triangulation.six_parameters_from_pose`).

References
----------
.. [1] The seed chapter, §3.3 (calibration by a target and a least-squares fit) and §4.1
   (the laser sheet, eqs. 9-17).
.. [2] M. A. Fischler and R. C. Bolles, "Random sample consensus", CACM 24(6), 1981.
.. [3] Z. Zhang, "A flexible new technique for camera calibration", IEEE PAMI 22(11),
   2000 (the board's pose from its corners).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ..camera import CameraModel
from ..checks import check_transform
from ..errors import CalibrationError
from ..options import Options
from ..transforms import invert_transform

__all__ = [
    "SheetOptions",
    "PlaneFit",
    "SheetResult",
    "fit_plane_robust",
    "sheet_points",
    "board_region_mask",
    "board_point_mask",
    "board_border_region",
    "board_poses_from_handeye",
    "still_views",
    "find_sheet_stripes",
    "calibrate_sheet",
]

log = logging.getLogger(__name__)

#: Reasons a laser frame is left out of the fit.
LEFT_OUT_REASONS: tuple[str, ...] = ("board not found", "no stripe on board",
                                     "too few pixels", "frame residual outlier")


class _Board(Protocol):
    cols: int
    rows: int
    square: float


@dataclass(frozen=True)
class SheetOptions(Options):
    """The parameters of the laser sheet calibration (config section ``laser_sheet``).

    Attributes
    ----------
    board_margin_x_squares, board_margin_y_squares : float, squares
        The board region: the inner corners' grid grown by this many squares along the
        columns (target x) and along the rows (target y); negative shrinks it.
    border_contrast : float
        The board's border ends, in the frame, where it gets darker by more than this
        fraction (:func:`board_border_region`); 0: the margins' rectangle as it is.
    pattern_edge_squares : float, squares
        On the printed pattern only pixels on white squares at least this far from the
        squares' edges are used; a negative value uses every pixel of the pattern.
    line_tolerance_px : float, pixels
        The board's stripe pixels farther than this from their frame's straight line
        (in the undistorted image) are dropped; 0 keeps them all.
    min_points_per_frame : int
        A frame with fewer usable stripe pixels on the board is left out.
    ransac_threshold_mm : float, mm
        RANSAC inlier distance to the plane.
    ransac_iterations : int
        RANSAC minimal samples drawn.
    frame_outlier_factor : float
        A frame whose residual RMS exceeds this times the median frame's is left out.
    min_frames : int
        Fewest frames the fit needs.
    min_spread_mm : float, mm
        Least spread of the points across their main direction (else one line).
    still_view_max_s : float, seconds
        Moving board: a view at most this far in time from a laser frame may give the
        board's pose (:func:`still_views`); 0: always the laser frame's own detection.
    still_view_max_px : float, pixels
        ... when its corners lie within this (median) of the laser frame's.
    """

    section = "laser_sheet"
    board_margin_x_squares: float = 3.0
    board_margin_y_squares: float = 2.0
    border_contrast: float = 0.05
    pattern_edge_squares: float = 0.25
    line_tolerance_px: float = 1.0
    min_points_per_frame: int = 30
    ransac_threshold_mm: float = 2.0
    ransac_iterations: int = 500
    frame_outlier_factor: float = 3.0
    min_frames: int = 3
    min_spread_mm: float = 5.0
    still_view_max_s: float = 1.0
    still_view_max_px: float = 0.5


@dataclass(frozen=True)
class PlaneFit:
    """A plane ``normal · x = offset_m`` fitted to points.

    Attributes
    ----------
    normal : (3,) float64, unit
    offset_m : float, metres
    rms_mm : float, mm
        RMS distance of the inliers to the plane.
    rms_all_mm : float, mm
        RMS distance of every point.
    inliers : (N,) bool
    spread_mm : (2,) float, mm
        Standard deviations of the inliers along their two in-plane principal axes.
    """

    normal: np.ndarray
    offset_m: float
    rms_mm: float
    rms_all_mm: float
    inliers: np.ndarray
    spread_mm: np.ndarray


@dataclass
class SheetResult:
    """The laser sheet calibrated from a recording's laser frames.

    Attributes
    ----------
    plane : PlaneFit
        The sheet in the camera frame, its normal the laser's +y.
    T_camera_laser : (4, 4) float64
        A laser pose with that sheet (:func:`robo3d.triangulation.laser_pose_from_plane`).
    six_parameters : dict
        The seed's eq. 11 parameters of ``T_camera_laser``
        (:func:`robo3d.triangulation.six_parameters_from_pose`).
    rms_mm : float, mm
        Inlier RMS residual (``plane.rms_mm``).
    per_frame_rms_mm : dict of int to float, mm
        Residual RMS of every frame that reached the fit (those left out as outliers too).
    used : list of int
        Frames of the final fit.
    left_out : dict of int to str
        Frames not used, and why (:data:`LEFT_OUT_REASONS`, with figures).
    tilt_spread_deg : float, degrees
        Largest angle between the board normals of the frames used.
    points_camera : (N, 3) float64, metres
        The sheet points of the frames used; ``point_frame`` (N,) their frame,
        ``plane.inliers`` which are inliers.
    pixels_uv : dict of int to (n, 2) float64
        The stripe pixels on the board of each frame that reached the fit (the frame
        residual outliers too), for pictures.
    colour : str
        The laser colour the stripes were found in.
    """

    plane: PlaneFit
    T_camera_laser: np.ndarray
    six_parameters: dict[str, float]
    rms_mm: float
    per_frame_rms_mm: dict[int, float]
    used: list[int]
    left_out: dict[int, str]
    tilt_spread_deg: float
    points_camera: np.ndarray
    point_frame: np.ndarray
    pixels_uv: dict[int, np.ndarray] = field(default_factory=dict)
    colour: str = ""

    @property
    def rejected(self) -> dict[int, str]:
        """The frames left out and why (``left_out``)."""
        return self.left_out

    def summary(self) -> dict[str, Any]:
        """The figures as plain types (for a report or the calibration yaml)."""
        return {
            "normal": self.plane.normal.tolist(), "offset_m": float(self.plane.offset_m),
            "six_parameters": {k: float(v) for k, v in self.six_parameters.items()},
            "rms_mm": float(self.rms_mm), "rms_all_mm": float(self.plane.rms_all_mm),
            "n_points": int(len(self.points_camera)),
            "n_inliers": int(self.plane.inliers.sum()),
            "frames_used": [int(i) for i in self.used],
            "frames_left_out": {int(k): v for k, v in self.left_out.items()},
            "per_frame_rms_mm": {int(k): float(v) for k, v in self.per_frame_rms_mm.items()},
            "tilt_spread_deg": float(self.tilt_spread_deg),
            "spread_mm": [float(s) for s in self.plane.spread_mm],
            "T_camera_laser": self.T_camera_laser.tolist(), "colour": self.colour,
        }


# ---------------------------------------------------------------------------- plane fit
def _tls_plane(p: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Total least squares plane of (N, 3) points: unit normal, offset, singular values
    over sqrt(N) (the principal standard deviations, largest first)."""
    c = p.mean(axis=0)
    _, s, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2]
    return n, float(n @ c), s / np.sqrt(len(p))


def fit_plane_robust(points: np.ndarray, options: SheetOptions = SheetOptions(),
                     seed: int = 0) -> PlaneFit:
    """A plane through 3D points with outliers: RANSAC, then least squares on the inliers.

    Parameters
    ----------
    points : (N, 3) float64, metres
        N >= 3 points.
    options : SheetOptions
        ``ransac_threshold_mm`` and ``ransac_iterations`` are used.
    seed : int
        Seed of the minimal samples (the result is reproducible).

    Returns
    -------
    PlaneFit
        The normal's sign is chosen so that the offset is non-negative.

    Raises
    ------
    ValueError
        Fewer than 3 finite points, or all of them on one line.

    References
    ----------
    .. [1] M. A. Fischler and R. C. Bolles, "Random sample consensus", CACM 24(6), 1981.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {p.shape}")
    p = p[np.all(np.isfinite(p), axis=1)]
    if len(p) < 3:
        raise ValueError(f"a plane needs at least 3 finite points, got {len(p)}")
    tol = float(options.ransac_threshold_mm) * 1e-3
    rng = np.random.default_rng(seed)
    n_it = max(1, int(options.ransac_iterations))
    idx = rng.integers(0, len(p), size=(n_it, 3))
    a, b, c = p[idx[:, 0]], p[idx[:, 1]], p[idx[:, 2]]
    nrm = np.cross(b - a, c - a)
    ln = np.linalg.norm(nrm, axis=1)
    ok = ln > 1e-12
    if not ok.any():
        raise ValueError(f"all {len(p)} points lie on one line: no plane")
    nrm, a = nrm[ok] / ln[ok, None], a[ok]
    off = np.einsum("ij,ij->i", nrm, a)
    best, best_count = None, -1
    for k in range(0, len(nrm), 64):  # blocks of hypotheses: (64, N) distances at a time
        cnt = (np.abs(p @ nrm[k:k + 64].T - off[k:k + 64]) < tol).sum(axis=0)
        j = int(np.argmax(cnt))
        if cnt[j] > best_count:
            best_count, best = int(cnt[j]), k + j
    inl = np.abs(p @ nrm[best] - off[best]) < tol
    n, d, s = nrm[best], float(off[best]), np.zeros(3)
    for _ in range(3):
        if inl.sum() < 3:
            break
        n, d, s = _tls_plane(p[inl])
        inl = np.abs(p @ n - d) < tol
    if d < 0:
        n, d = -n, -d
    res = p @ n - d
    rms = float(np.sqrt(np.mean(res[inl] ** 2))) * 1e3 if inl.any() else float("nan")
    return PlaneFit(normal=n, offset_m=d, rms_mm=rms,
                    rms_all_mm=float(np.sqrt(np.mean(res ** 2))) * 1e3, inliers=inl,
                    spread_mm=np.asarray(s[:2]) * 1e3)


# ---------------------------------------------------------------------------- geometry
def sheet_points(stripe_uv: np.ndarray, camera_model: CameraModel,
                 T_camera_target: np.ndarray) -> np.ndarray:
    """Stripe pixels cast onto the board's plane: 3D points in the camera frame.

    The ray through each (distorted) pixel (:meth:`CameraModel.rays`) is cut with the
    board's plane, the target's z = 0 plane at ``T_camera_target``.

    Parameters
    ----------
    stripe_uv : (N, 2) float64, pixels
    camera_model : CameraModel
    T_camera_target : (4, 4) float64
        The board's pose in the camera.

    Returns
    -------
    (N, 3) float64, metres
        NaN where the ray is parallel to the board or meets it behind the camera.
    """
    uv = np.asarray(stripe_uv, dtype=np.float64).reshape(-1, 2)
    t = check_transform(T_camera_target, "T_camera_target")
    n, d = t[:3, 2], float(t[:3, 2] @ t[:3, 3])
    rays = camera_model.rays(uv)
    den = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(np.abs(den) > 1e-9, d / den, np.nan)
    s = np.where(s > 0, s, np.nan)
    return rays * s[:, None]


def _board_xy(points_cam: np.ndarray, T_camera_target: np.ndarray, square: float) -> np.ndarray:
    """(N, 2) target-frame coordinates of camera-frame points, in squares."""
    t_tc = invert_transform(T_camera_target)
    q = points_cam @ t_tc[:3, :3].T + t_tc[:3, 3]
    return q[:, :2] / square


def _region(target: _Board, options: SheetOptions) -> tuple[float, float, float, float]:
    """The board's region in squares, target frame: (x0, x1, y0, y1)."""
    mx, my = float(options.board_margin_x_squares), float(options.board_margin_y_squares)
    margin = getattr(target, "margin", None)  # the white border beyond the outer squares
    if margin is not None and np.isfinite(margin):
        edge = 1.0 + float(margin) / float(target.square) - 0.25
        mx, my = min(mx, edge), min(my, edge)
    return -mx, target.cols - 1 + mx, -my, target.rows - 1 + my


def board_region_mask(camera_model: CameraModel, T_camera_target: np.ndarray,
                      target: _Board, options: SheetOptions = SheetOptions(),
                      region: tuple[float, float, float, float] | None = None) -> np.ndarray:
    """The board's region in the image: the inner corners' grid grown by
    ``board_margin_x_squares`` and ``board_margin_y_squares``, its edges sampled (64
    points each), projected with lens distortion and filled (``cv2.fillPoly``).

    ``region`` (x0, x1, y0, y1) in squares, target frame, replaces the options'
    rectangle (e.g. :func:`board_border_region`'s).

    Returns
    -------
    (H, W) bool
        All False when the board is behind the camera.
    """
    import cv2

    x0, x1, y0, y1 = _region(target, options) if region is None else region
    s = np.linspace(0.0, 1.0, 64, endpoint=False)
    edges = np.concatenate([
        np.stack([x0 + (x1 - x0) * s, np.full_like(s, y0)], 1),
        np.stack([np.full_like(s, x1), y0 + (y1 - y0) * s], 1),
        np.stack([x1 - (x1 - x0) * s, np.full_like(s, y1)], 1),
        np.stack([np.full_like(s, x0), y1 - (y1 - y0) * s], 1)]) * float(target.square)
    t = check_transform(T_camera_target, "T_camera_target")
    pts = np.c_[edges, np.zeros(len(edges))] @ t[:3, :3].T + t[:3, 3]
    mask = np.zeros((camera_model.height, camera_model.width), np.uint8)
    if np.any(pts[:, 2] <= 1e-6):
        front = pts[pts[:, 2] > 1e-6]
        if len(front) < 3:
            return mask.astype(bool)
        pts = front
    uv, _ = camera_model.project(pts)
    uv = np.clip(uv, -4 * camera_model.width, 5 * camera_model.width)
    cv2.fillPoly(mask, [np.round(uv * 16).astype(np.int32)], 1, cv2.LINE_8, shift=4)
    return mask.astype(bool)


def board_point_mask(points_cam: np.ndarray, T_camera_target: np.ndarray, target: _Board,
                     image: np.ndarray | None, camera_model: CameraModel,
                     options: SheetOptions = SheetOptions(),
                     region: tuple[float, float, float, float] | None = None) -> np.ndarray:
    """Which sheet points (on the board's plane) may be used: inside the board's region,
    and on the printed pattern only on white squares, ``pattern_edge_squares`` from
    their edges (see the module docstring).

    Parameters
    ----------
    points_cam : (N, 3) float64, metres
        Points on the board's plane (:func:`sheet_points`), NaN for none.
    T_camera_target : (4, 4) float64
    target : board with ``cols``, ``rows`` (inner corners) and ``square`` (metres)
    image : (H, W[, 3]) array or None
        The frame, to tell black squares from white; None: every square counts as
        white (only the edges are avoided).
    camera_model : CameraModel
    options : SheetOptions
    region : (x0, x1, y0, y1), squares, optional
        The board's region in the target frame (default: the options' rectangle).

    Returns
    -------
    (N,) bool
    """
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    xy = _board_xy(np.nan_to_num(p), T_camera_target, float(target.square))
    x0, x1, y0, y1 = _region(target, options) if region is None else region
    ok = np.all(np.isfinite(p), axis=1)
    ok &= (xy[:, 0] >= x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= y0) & (xy[:, 1] <= y1)
    e = float(options.pattern_edge_squares)
    if e < 0:
        return ok
    # the printed pattern spans one square beyond the inner corners
    on_pattern = ((xy[:, 0] > -1 - e) & (xy[:, 0] < target.cols + e)
                  & (xy[:, 1] > -1 - e) & (xy[:, 1] < target.rows + e))
    frac = xy - np.floor(xy)
    near_edge = np.any((frac < e) | (frac > 1 - e), axis=1)
    parity = (np.floor(xy[:, 0]) + np.floor(xy[:, 1])).astype(np.int64) % 2
    black = parity == _black_parity(image, T_camera_target, target, camera_model)
    return ok & ~(on_pattern & (near_edge | black))


def _grey(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    return img.mean(axis=2) if img.ndim == 3 else img


def _sample(grey: np.ndarray, uv: np.ndarray, front: np.ndarray) -> np.ndarray:
    """Grey values at the nearest pixels (NaN outside the image or behind the camera)."""
    u = np.rint(np.nan_to_num(uv[..., 0], nan=-1.0)).astype(np.int64)
    v = np.rint(np.nan_to_num(uv[..., 1], nan=-1.0)).astype(np.int64)
    inside = front & (u >= 0) & (u < grey.shape[1]) & (v >= 0) & (v < grey.shape[0])
    out = np.full(uv.shape[:-1], np.nan)
    out[inside] = grey[v[inside], u[inside]]
    return out


def board_border_region(image: np.ndarray, T_camera_target: np.ndarray, target: _Board,
                        camera_model: CameraModel, options: SheetOptions = SheetOptions(),
                        step: float = 0.125) -> tuple[float, float, float, float]:
    """The board's border as seen in the frame: how far beyond the printed pattern each
    of its four sides keeps the border's own brightness.

    On each side, bands parallel to the pattern's edge (every ``step`` squares from the
    edge outward, up to the options' margins) are sampled at 33 points along the
    pattern's extent, and each band's median grey is taken (the stripe crossing a band
    is a few samples and does not move it). The border's brightness is the median of
    the bands 0.125-0.375 squares from the pattern; the first band farther out whose
    median is darker by more than ``border_contrast`` (a fraction) is beyond the board
    (the room, the table the board lies on, a hand), and the region ends a quarter
    square before it. Only darker bands count: a band along the stripe is brighter
    (on srv the near-vertical line runs inside the left side's bands).

    Returns
    -------
    (x0, x1, y0, y1) : floats, squares, target frame
        The region (never beyond the options' rectangle).
    """
    x0, x1, y0, y1 = _region(target, options)
    grey = _grey(image)
    t = check_transform(T_camera_target, "T_camera_target")
    sq = float(target.square)

    def project(xy: np.ndarray) -> np.ndarray:
        p = np.concatenate([xy * sq, np.zeros(xy.shape[:-1] + (1,))], -1) @ t[:3, :3].T
        uv, front = camera_model.project(p + t[:3, 3])
        return _sample(grey, uv, front)

    along_x = np.linspace(-1.0, float(target.cols), 33)
    along_y = np.linspace(-1.0, float(target.rows), 33)
    out = []
    # the four sides: (outward sign, axis, pattern edge, configured bound)
    for sign, axis, edge, bound in ((-1, 0, -1.0, x0), (1, 0, float(target.cols), x1),
                                    (-1, 1, -1.0, y0), (1, 1, float(target.rows), y1)):
        reach = sign * (bound - edge) + 0.25
        d = np.arange(step / 2, max(reach, 0.5) + 1e-9, step)  # band centres
        along = along_y if axis == 0 else along_x
        pos = edge + sign * d
        xy = (np.stack(np.broadcast_arrays(pos[:, None], along[None, :]), -1) if axis == 0
              else np.stack(np.broadcast_arrays(along[None, :], pos[:, None]), -1))
        vals = project(xy)
        near = vals[(d > 0.1) & (d < 0.4)]
        if reach <= 0 or not np.isfinite(near).any():
            out.append(bound)
            continue
        ref = float(np.nanmedian(near))
        has = np.isfinite(vals).any(axis=1)  # bands outside the image stop nothing
        med = np.full(len(vals), ref)
        med[has] = np.nanmedian(vals[has], axis=1)
        off = (d > 0.4) & (med < (1.0 - float(options.border_contrast)) * ref)
        hit = np.flatnonzero(off)
        out.append(edge + sign * (d[hit[0]] - step / 2 - 0.25) if len(hit) else bound)
    # never beyond the configured rectangle
    return (max(out[0], x0), min(out[1], x1), max(out[2], y0), min(out[3], y1))


def _black_parity(image: np.ndarray | None, T_camera_target: np.ndarray, target: _Board,
                  camera_model: CameraModel) -> int:
    """The parity ``(i + j) % 2`` of the black squares ``[i, i+1] x [j, j+1]`` (in
    squares, target frame), from the mean grey at the squares' centres in ``image``
    (-1: none is black, without an image)."""
    if image is None:
        return -1
    i, j = np.meshgrid(np.arange(-1, target.cols), np.arange(-1, target.rows))
    c = np.c_[(i.ravel() + 0.5), (j.ravel() + 0.5), np.zeros(i.size)] * float(target.square)
    t = check_transform(T_camera_target, "T_camera_target")
    uv, front = camera_model.project(c @ t[:3, :3].T + t[:3, 3])
    grey = _grey(image)
    u = np.rint(uv[:, 0]).astype(np.int64)
    v = np.rint(uv[:, 1]).astype(np.int64)
    inside = front & (u >= 0) & (u < grey.shape[1]) & (v >= 0) & (v < grey.shape[0])
    par = ((i.ravel() + j.ravel()) % 2)[inside]
    val = grey[v[inside], u[inside]].astype(np.float64)
    if not (np.any(par == 0) and np.any(par == 1)):
        return -1
    return 0 if val[par == 0].mean() < val[par == 1].mean() else 1


def _on_straight_line(uv: np.ndarray, keep: np.ndarray, camera_model: CameraModel,
                      tol_px: float, seed: int, iterations: int = 200) -> np.ndarray:
    """Which of the ``keep`` pixels lie within ``tol_px`` of one straight line of the
    undistorted image (the sheet meets the board's plane in a line): RANSAC on pairs,
    then a total least squares line on the inliers, twice. (N,) bool."""
    out = np.zeros(len(uv), bool)
    idx = np.flatnonzero(keep)
    if tol_px <= 0 or len(idx) < 2:
        out[idx] = True
        return out
    f = float(np.sqrt(camera_model.fx * camera_model.fy))
    q = camera_model.undistort_normalized(camera_model.pixels_to_normalized(uv[idx])) * f
    rng = np.random.default_rng(seed)
    pair = rng.integers(0, len(q), size=(iterations, 2))
    a, b = q[pair[:, 0]], q[pair[:, 1]]
    d = b - a
    ln = np.linalg.norm(d, axis=1)
    good = ln > 1e-9
    if not good.any():
        out[idx] = True
        return out
    nrm = np.stack([-d[good, 1], d[good, 0]], 1) / ln[good, None]
    off = np.einsum("ij,ij->i", nrm, a[good])
    cnt = (np.abs(q @ nrm.T - off) < tol_px).sum(axis=0)
    j = int(np.argmax(cnt))
    inl = np.abs(q @ nrm[j] - off[j]) < tol_px
    for _ in range(2):
        if inl.sum() < 2:
            break
        c = q[inl].mean(axis=0)
        n = np.linalg.svd(q[inl] - c, full_matrices=False)[2][1]
        inl = np.abs((q - c) @ n) < tol_px
    out[idx[inl]] = True
    return out


def board_poses_from_handeye(T_base_flange: np.ndarray, T_flange_camera: np.ndarray,
                             T_base_target: np.ndarray) -> np.ndarray:
    """The board's pose in the camera at each robot pose of a robot cell (static board):
    ``T_camera_target = inv(T_base_flange T_flange_camera) T_base_target``.

    Parameters
    ----------
    T_base_flange : (F, 4, 4) float64
    T_flange_camera, T_base_target : (4, 4) float64

    Returns
    -------
    (F, 4, 4) float64
    """
    tbf = check_transform(T_base_flange, "T_base_flange", batch=True).reshape(-1, 4, 4)
    tfc = check_transform(T_flange_camera, "T_flange_camera")
    tbt = check_transform(T_base_target, "T_base_target")
    tbc = tbf @ tfc
    return np.einsum("fij,jk->fik", invert_transform(tbc), tbt)


def still_views(frame_stamps_ns: np.ndarray, frame_corners: Sequence[np.ndarray | None],
                view_stamps_ns: np.ndarray, view_corners: Sequence[np.ndarray | None],
                max_s: float, max_px: float) -> np.ndarray:
    """For each laser frame, a view that shows the board at the same place, if any.

    A moving board held still for a laser frame is often also seen in a laser-off view
    just before or after (the simulator's fixed rig writes one 0.25 s before each laser
    frame). The view's detection is the better one: in the laser frame the exposure is
    dimmed for the line and the line crosses the pattern, which moves the corners near
    it (measured on the simulator's fixed rig, seeds 0-2: up to 0.9-2.1 px at single
    corners, median 0.05-0.13 px, the board's tilt off by up to 0.16 deg from the laser
    frame's corners against at most 0.044 deg from the view's).

    Parameters
    ----------
    frame_stamps_ns : (F,) int
        The laser frames' time stamps.
    frame_corners : sequence of (N, 2) float or None
        The board's corners detected in each laser frame (None: not found).
    view_stamps_ns : (V,) int
        The views' time stamps.
    view_corners : sequence of (N, 2) float or None
        The corners of each view that may stand in (None: not a candidate).
    max_s : float, seconds
        Only views at most this far in time from the frame are candidates; 0: none.
    max_px : float, pixels
        The view stands in when the median distance between its corners and the laser
        frame's is at most this (the median: a few corners under the line move).

    Returns
    -------
    (F,) int
        Index of the view (the candidate with the smallest median distance) per frame,
        -1 where none qualifies (or the frame's board was not found: without its corners
        nothing says the board had not moved).
    """
    ts = np.asarray(frame_stamps_ns, dtype=np.int64)
    tv = np.asarray(view_stamps_ns, dtype=np.int64)
    out = np.full(len(ts), -1, dtype=int)
    if max_s <= 0 or len(tv) == 0:
        return out
    cand = [j for j, c in enumerate(view_corners) if c is not None]
    for f, fc in enumerate(frame_corners):
        if fc is None:
            continue
        near = [j for j in cand if abs(int(tv[j]) - int(ts[f])) <= max_s * 1e9
                and np.shape(view_corners[j]) == np.shape(fc)]
        if not near:
            continue
        med = np.median(np.linalg.norm(np.stack([view_corners[j] for j in near])
                                       - np.asarray(fc)[None], axis=2), axis=1)
        best = int(np.argmin(med))
        if med[best] <= max_px:
            out[f] = near[best]
    return out


# ---------------------------------------------------------------------------- stripes
def find_sheet_stripes(images: Sequence[np.ndarray | None], rois: Sequence[np.ndarray | None],
                       stripe_options: Any = None, encoded: bytes | None = None,
                       ) -> tuple[list, str]:
    """The stripe in each laser frame, inside its board region (the detector's region of
    interest), with the project's detector (:func:`robo3d.stripes.extract_stripe_centres`).

    ``colour="auto"`` is resolved once for all frames from 12 evenly spaced ones with a
    region (:func:`robo3d.stripes.estimate_laser_colour`) and ``centre_on="auto"`` from
    one frame's encoded bytes (:func:`robo3d.stripes.centre_on_for`), as the stripes
    stage does.

    Parameters
    ----------
    images : sequence of (H, W[, 3]) arrays or None
        Decoded laser frames (None: skipped, no stripe).
    rois : sequence of (H, W) bool or None
        Each frame's board region (None: skipped).
    stripe_options : StripeOptions, optional
        Default: the project's (``StripeOptions()``).
    encoded : bytes, optional
        One frame's recorded bytes (JPEG or PNG), for ``centre_on="auto"``.

    Returns
    -------
    stripes : list of StripePoints or None
    colour : str
    """
    from ..stripes import (
        StripeOptions,
        centre_on_for,
        estimate_laser_colour,
        extract_stripe_centres,
    )

    o = StripeOptions() if stripe_options is None else stripe_options
    todo = [k for k, (im, r) in enumerate(zip(images, rois, strict=True))
            if im is not None and r is not None and r.any()]
    if o.colour == "auto" and todo:
        from ..viz import spaced_indices

        pick = [todo[int(k)] for k in spaced_indices(len(todo), 12)]
        colour, _ = estimate_laser_colour([images[k] for k in pick], min_peak=o.min_peak,
                                          rois=[rois[k] for k in pick])
        o = o.replace(colour=colour)
    o = o.replace(centre_on=centre_on_for(o.centre_on, encoded))
    out: list = [None] * len(images)
    for k in todo:
        out[k] = extract_stripe_centres(images[k], roi=rois[k], options=o)
    return out, o.colour


# ---------------------------------------------------------------------------- calibration
def calibrate_sheet(laser_images: Iterable[np.ndarray], camera_model: CameraModel,
                    T_camera_target: Sequence[np.ndarray | None],
                    options: SheetOptions | None = None, *, target: _Board | None = None,
                    stripe_options: Any = None,
                    encoded: bytes | None = None, reference: np.ndarray | None = None,
                    seed: int = 0, source: str = "laser frames",
                    frame_ids: Sequence[int] | None = None) -> SheetResult:
    """The laser sheet from the stripe on the board in a recording's laser frames.

    Parameters
    ----------
    laser_images : iterable of F (H, W[, 3]) arrays
        The decoded laser frames (a generator is read once).
    camera_model : CameraModel
        The calibrated camera (intrinsics and distortion).
    T_camera_target : sequence of F (4, 4) float64 or None
        The board's pose in each frame (None: not found there).
    options : SheetOptions, optional
        The ``laser_sheet`` section (default: the schema's defaults).
    target : :class:`robo3d.calibration.target.Target`
        The board (``cols``, ``rows`` inner corners, ``square`` metres); required.
    stripe_options : StripeOptions, optional
        The ``stripes`` section (default: the project's defaults).
    encoded : bytes, optional
        One laser frame's recorded bytes (for ``centre_on="auto"``).
    reference : (4, 4) float64, optional
        A nominal ``T_camera_laser`` whose in-plane choices the result keeps
        (:func:`robo3d.triangulation.laser_pose_from_plane`); None: the canonical pose.
    seed : int
        RANSAC's seed.
    source : str
        Names the recording (and topic) in errors.
    frame_ids : sequence of F int, optional
        The frames' indices in the recording (default ``0 .. F-1``), used in results
        and messages.

    Returns
    -------
    SheetResult

    Raises
    ------
    CalibrationError
        Fewer than ``min_frames`` usable frames, or points that do not determine a
        plane (one line: all boards in one plane); the message names ``source``, the
        frames and why the others were left out.
    """
    from ..triangulation import laser_pose_from_plane, six_parameters_from_pose

    if target is None:
        raise ValueError("calibrate_sheet needs the target (cols, rows, square) for the "
                         "board's region")
    options = SheetOptions() if options is None else options
    laser_images = list(laser_images)
    F = len(laser_images)
    T_camera_target = list(T_camera_target)
    if len(T_camera_target) != F:
        raise ValueError(f"need one board pose (or None) per laser frame: {F} frames, "
                         f"{len(T_camera_target)} poses")
    ids = list(range(F)) if frame_ids is None else [int(i) for i in frame_ids]
    left_out: dict[int, str] = {}
    rois: list = [None] * F
    regions: list = [None] * F
    for k in range(F):
        if T_camera_target[k] is None:
            left_out[ids[k]] = "board not found"
        else:
            if options.border_contrast > 0:
                regions[k] = board_border_region(laser_images[k], T_camera_target[k],
                                                 target, camera_model, options)
            rois[k] = board_region_mask(camera_model, T_camera_target[k], target, options,
                                        regions[k])
    stripes, colour = find_sheet_stripes(laser_images, rois, stripe_options, encoded)

    pts, frm, uv_used, normals = [], [], {}, {}
    for k in range(F):
        if rois[k] is None:
            continue
        sp = stripes[k]
        if sp is None or len(sp) == 0:
            left_out[ids[k]] = "no stripe on board"
            continue
        uv = sp.pixels_uv
        p = sheet_points(uv, camera_model, T_camera_target[k])
        keep = board_point_mask(p, T_camera_target[k], target, laser_images[k],
                                camera_model, options, regions[k])
        if keep.sum() < options.min_points_per_frame:
            left_out[ids[k]] = (f"too few pixels ({int(keep.sum())} of {len(sp)} stripe "
                                f"pixels on the board, < {options.min_points_per_frame})")
            continue
        keep &= _on_straight_line(uv, keep, camera_model, options.line_tolerance_px, seed)
        if keep.sum() < options.min_points_per_frame:
            left_out[ids[k]] = (f"too few pixels ({int(keep.sum())} of {len(sp)} stripe "
                                f"pixels on the board's line, < {options.min_points_per_frame})")
            continue
        pts.append(p[keep])
        frm.append(np.full(int(keep.sum()), ids[k]))
        uv_used[ids[k]] = uv[keep]
        normals[ids[k]] = np.asarray(T_camera_target[k])[:3, 2]
    fit, P, fr, per_frame = _fit_frames(pts, frm, left_out, options, seed, source)
    used = sorted(int(i) for i in np.unique(fr))
    n_b = np.array([normals[i] for i in used])
    cosang = np.clip(np.abs(n_b @ n_b.T), -1.0, 1.0)
    tilt = float(np.degrees(np.arccos(cosang.min())))
    T = laser_pose_from_plane(fit.normal, fit.offset_m, reference)
    six = six_parameters_from_pose(T)
    log.info("%s: laser sheet from %d frames (%d points): RMS %.3f mm, %d frames left out",
             source, len(used), len(P), fit.rms_mm, len(left_out))
    return SheetResult(plane=fit, T_camera_laser=T, six_parameters=six, rms_mm=fit.rms_mm,
                       per_frame_rms_mm=per_frame, used=used,
                       left_out=dict(sorted(left_out.items())), tilt_spread_deg=tilt,
                       points_camera=P, point_frame=fr,
                       pixels_uv=uv_used, colour=colour)


def _fit_frames(pts: list, frm: list, left_out: dict[int, str], options: SheetOptions,
                seed: int, source: str):
    """The robust plane of the frames' points, a frame residual outlier left out once and
    the fit repeated; checks the degenerate cases. Returns the fit, the points and their
    frames, and every fitted frame's residual RMS (mm)."""
    per_frame: dict[int, float] = {}
    for attempt in range(2):
        _check_enough(frm, left_out, options, source)
        P, fr = np.concatenate(pts), np.concatenate(frm)
        _check_spread(P, fr, left_out, options, source)
        fit = fit_plane_robust(P, options, seed)
        res = P @ fit.normal - fit.offset_m
        frames = np.unique(fr)
        rms_f = np.array([np.sqrt(np.mean(res[fr == i] ** 2)) for i in frames]) * 1e3
        per_frame.update({int(i): float(r) for i, r in zip(frames, rms_f, strict=True)})
        limit = max(float(options.frame_outlier_factor) * float(np.median(rms_f)), 0.2)
        bad = frames[rms_f > limit]
        if attempt == 1 or not len(bad):
            return fit, P, fr, per_frame
        for i in bad:
            left_out[int(i)] = (f"frame residual outlier (RMS {per_frame[int(i)]:.2f} mm > "
                                f"{limit:.2f} mm, {options.frame_outlier_factor:g} x the "
                                "median frame's)")
        keep = [j for j, f in enumerate(frm) if f[0] not in set(bad.tolist())]
        pts, frm = [pts[j] for j in keep], [frm[j] for j in keep]
    raise AssertionError("unreachable")  # pragma: no cover


def _check_enough(frm: list, left_out: dict[int, str], options: SheetOptions,
                  source: str) -> None:
    if len(frm) >= max(int(options.min_frames), 1):
        return
    reasons: dict[str, int] = {}
    for r in left_out.values():
        key = r.split(" (")[0]
        reasons[key] = reasons.get(key, 0) + 1
    raise CalibrationError(
        f"laser sheet: {len(frm)} usable laser frames, at least {options.min_frames} "
        f"needed ({len(left_out)} left out: "
        + ", ".join(f"{k} {v}" for k, v in reasons.items())
        + "); record more laser frames with the line across the board", path=source)


def _check_spread(P: np.ndarray, fr: np.ndarray, left_out: dict[int, str],
                  options: SheetOptions, source: str) -> None:
    _, _, s = _tls_plane(P)
    spread = float(s[1]) * 1e3
    if spread >= float(options.min_spread_mm):
        return
    frames = sorted(int(i) for i in np.unique(fr))
    raise CalibrationError(
        f"laser sheet: the stripe points of frames {frames} lie on one line (spread "
        f"across it {spread:.2f} mm < laser_sheet.min_spread_mm = "
        f"{options.min_spread_mm:g} mm): a plane is not determined by one line; the "
        "boards were all in one plane (or all frames show the same line). Record the "
        "board at more tilts and distances", path=source)
