"""Simulated calibration recordings (issue 13, item 4): a checkerboard seen by the scan
simulator's camera, with its laser, in a robot cell or on a fixed-camera rig.

:func:`write_calibration_recording` writes one ``kind=calibration`` MCAP recording
(``recording-format.md``) of a :class:`CalibrationCell` (the true camera, hand-eye and
laser mount; :func:`robo3d.simulate.calibration_cell` builds it from the scan
simulator's :class:`~robo3d.simulate.SimulationParams`, so that a calibration recording
and a scan recording made from the same parameters share one true camera, hand-eye and
laser sheet: calibrate from one, scan with the other):

- ``rig="robot"``: the board lies static on the table (``T_base_target``); the robot
  moves the camera through ``views`` stops (tilts up to ``tilt_max_deg`` about varied
  axes, turns about the optical axis up to ``roll_max_deg``, so that hand-eye is well
  conditioned) and ``laser_frames`` further stops where the laser sheet crosses the
  board at different board-to-sheet tilts (distinct lines in the sheet, which fix the
  plane). ``/tf`` carries ``base -> flange`` as the robot reports it (with error),
  stop and go (samples every 20 ms from 27 ms before an image to 33 ms after it).
- ``rig="fixed"``: ``robo3d.target`` has ``moving=true``; ``base`` is the camera
  (``base -> camera`` identity on ``/tf_static``), no robot, no ``/tf``; the board is
  held by hand at random tilted poses in front of it (a hand and thumb on its margin).

Both: ``/camera/image`` views (laser off) and ``/camera/laser_image`` laser frames, each
laser frame preceded by a view at the same still pose 0.25 s earlier (its companion:
the board's pose for the stripe can come from it, or from the robot). The published
``/camera/calibration`` is a placeholder (``f`` from the lens's nominal focal length,
a few per cent off and rounded to 10 px, principal point at the image centre, no
distortion) and the published ``flange -> camera`` and ``camera -> laser`` are nominal
(the truth moved by ``nominal_error_mm`` / ``nominal_error_deg``), as real cells publish
them; ``ground_truth/calibration.json`` holds the truth (the form of
``/work/notes/calib_plan.md``, below).

Rendering
---------
- The board is drawn analytically through the true (distorted) camera: every pixel
  centre's ray (:meth:`robo3d.camera.CameraModel.rays`, the exact inverse of plumb_bob)
  is cut with the board plane, giving board coordinates ``(x, y)`` and, by central
  differences over neighbouring pixels, their Jacobian in ``(u, v)``. Pixels whose
  footprint reaches a square's edge, the plate's border, the hand or the laser sheet are
  supersampled (``supersample x supersample`` sub-pixels, board coordinates linear in the
  sub-pixel offset: the error of that linearisation is below 1e-3 px), others take
  their centre's value. The squares' edges and the stripe are therefore area-integrated
  (anti-aliased) and their positions unbiased.
- Board colours: black ink albedo 0.045, white 0.85 (a matte print), lit by the cell's
  room light (``Appearance``: ambient plus the directional light with Lambert's
  cosine); a ``glare`` view adds the Blinn-Phong mirror image of a lamp (Blinn 1977)
  whose highlight falls on the board and saturates it.
- Background: the scan simulator's scene (:class:`robo3d.sim.render.SimScene`: the table
  with its printed markers, the wall, clutter objects on the table) rendered by
  :func:`~robo3d.sim.render.render_view` / :func:`~robo3d.sim.render.render_laser_frame`
  at half resolution and resized (it is out of focus and unused); the board is
  composited over it by coverage where no clutter is in front of it. On the fixed rig
  the board's laser shadow on the background is cut out.
- Laser on the board: ``laser_peak_dn * albedo_at_laser * exp(-2 d^2 / w^2) * cos(theta)
  * r_ref / r`` (``d`` the distance to the sheet, as :mod:`robo3d.sim.render`), its
  colour ``laser_rgb``; room light in laser frames is the view's times
  ``laser_ambient_fraction`` (or the demo cell's dimmed ``laser_ambient_dn``), times
  ``laser_exposure``.
- Optics and sensor: a slight defocus (Gaussian, ``defocus_sigma_px``), vignetting,
  shot and read noise (:func:`~robo3d.sim.render.sensor_noise`), JPEG (the cell's
  encodings and quality).
- Bad views, as real sessions have them (``defects``): ``motion_blur`` (the robot still
  moving: a ``motion_blur_px`` line kernel), ``out_of_frame`` (part of the board outside
  the image), ``glare`` (the lamp's highlight on the board). They are listed in the
  truth (``views[i]["defect"]``).

Robot error: each stop's reported flange pose is ``T_true @ E`` with ``E`` drawn as the
scan simulator's views' (``view_error_mm``, ``view_error_deg``; times the
position-dependent ``P(x)`` of :mod:`robo3d.sim.rig` with ``robot_error="drift"``).

``ground_truth/tf.json`` (``recording-format.md``'s form) holds the true samples of
every link whose published value carries error, at the ``/tf`` stamps: ``base ->
flange``, ``flange -> camera`` and ``camera -> laser`` (robot; fixed rig: ``camera ->
laser`` around each image), so that :func:`robo3d.recording.read_ground_truth_tf`
resolves the true camera and laser pose of every image (it would otherwise take the
nominal ``/tf_static`` as true).

``ground_truth/calibration.json`` (all metres, 4 x 4 row-major nested lists)::

    {"camera": {"frame_id", "width", "height", "K": [9], "D": [5],
                "distortion_model": "plumb_bob"},
     "T_flange_camera": 4x4 | null, "T_camera_laser": 4x4,
     "T_base_target": 4x4 | null, "T_base_camera": 4x4 | null (fixed rig: identity),
     "views": [{"index", "timestamp_ns", "T_camera_target", "defect", "laser_frame"}],
     "laser_frames": [{"index", "timestamp_ns", "T_camera_target", "view"}],
     "target": {"type", "cols", "rows", "square", "margin", "moving", "frame"},
     "published": {"K", "D", "T_flange_camera", "T_camera_laser"},
     "rig", "seed"}

(``views[i]["laser_frame"]``: the laser frame a companion view belongs to, else null;
``laser_frames[k]["view"]``: its companion view.)

The target frame (``T_camera_target``): origin at the first inner corner, ``x`` along
the ``cols`` inner corners, ``y`` along the ``rows``, ``z = x cross y`` pointing into
the board (the camera sees the printed face from ``-z``, as OpenCV's object points
``(i * square, j * square, 0)``, ``i`` fastest); the square at ``x < 0, y < 0`` of the
first corner is black.

Choices
-------
- The board (9 x 6 inner corners of 15 mm, a 15 mm white margin) is sized for the scan
  cell's working distance (0.27-0.30 m, a field of about 0.21 x 0.16 m): it fills
  40-70 % of the image and stays whole under 40 degree tilts and turns; a 20-25 mm
  board would not fit at that distance.
- Poses are drawn by rejection (every inner corner at least ``edge_px`` inside the
  image, the printed face toward the camera); the ``out_of_frame`` view keeps 35-80 %
  of the corners.
- Laser frames: robot stops where the sheet cuts the board's squares over at least
  half the board's width with the laser on the printed side, at 0.85-1.3 times the
  sheet's crossing depth and tilts of 5-36 degrees (distinct lines in the sheet);
  fixed rig: the board through a point of the sheet at 0.88-1.2 times that depth.
  Every laser frame's board is whole in the image (its companion view finds it).
- Speed: the board is computed only inside its projected bounding box; the fixed rig's
  background is rendered once. About 0.3 s of CPU per 640 x 480 image.
- Deterministic: ``numpy.random.default_rng([seed, stream, index])``; the same
  arguments give the same file.

References
----------
Blinn, J. F. (1977). Models of light reflection for computer synthesized pictures.
SIGGRAPH '77. Zhang, Z. (2000). A flexible new technique for camera calibration. IEEE
PAMI 22(11) (the planar target and its frame).
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

from ..camera import CameraModel
from ..transforms import invert_transform, make_transform, matrix_to_quat
from .render import (
    Appearance,
    SimScene,
    render_laser_frame,
    render_view,
    sensor_noise,
    vignetting,
)
from .rig import PoseDependentError, look_at, random_rigid_error, rotation_about_axis
from .shapes import TriangleMesh

__all__ = [
    "RIGS",
    "DEFECTS",
    "Checkerboard",
    "CalibrationCell",
    "CalibrationOptions",
    "CalibrationSimResult",
    "BoardLayer",
    "board_layer",
    "placeholder_camera",
    "nominal_transform",
    "sheet_board_line",
    "write_calibration_recording",
    "CALIBRATION_TRUTH",
]

_log = logging.getLogger(__name__)

#: The two rigs: a robot-carried camera over a static board, a fixed camera and a
#: hand-held board.
RIGS: tuple[str, ...] = ("robot", "fixed")
#: Kinds of bad views.
DEFECTS: tuple[str, ...] = ("motion_blur", "out_of_frame", "glare")
#: The truth attachment.
CALIBRATION_TRUTH = "ground_truth/calibration.json"

_VIEW_TOPIC = "/camera/image"
_LASER_TOPIC = "/camera/laser_image"
_CAL_TOPIC = "/camera/calibration"
_SKIN = (0.78, 0.55, 0.44)
_LASER_DELAY_NS = 250_000_000  # a laser frame after its companion view


@dataclass(frozen=True)
class Checkerboard:
    """A printed checkerboard on a flat plate.

    Attributes
    ----------
    cols, rows : int
        Inner corners along the target's x and y.
    square : float, metres
    margin : float, metres
        White border around the outer squares.
    black, white : float
        Albedo of the ink and of the paper.
    thickness : float, metres
        The plate's thickness (robot cell: its printed face is this far above the table).
    """

    cols: int = 9
    rows: int = 6
    square: float = 0.015
    margin: float = 0.015
    black: float = 0.045
    white: float = 0.85
    thickness: float = 0.003

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"checkerboard needs at least 2 x 2 inner corners, got "
                             f"{self.cols} x {self.rows}")
        if not (self.square > 0 and self.margin >= 0):
            raise ValueError(f"checkerboard square must be > 0 and margin >= 0 m, got "
                             f"{self.square}, {self.margin}")

    @property
    def plate(self) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)``: the plate's extent in the target frame, metres."""
        s, m = self.square, self.margin
        return (-s - m, self.cols * s + m, -s - m, self.rows * s + m)

    @property
    def centre(self) -> np.ndarray:
        """Centre of the inner corners ``(3,)`` in the target frame."""
        return np.array([(self.cols - 1) * self.square / 2, (self.rows - 1) * self.square / 2,
                         0.0])

    def corners(self) -> np.ndarray:
        """Inner corners ``(cols * rows, 3)`` in the target frame (``x`` fastest)."""
        i, j = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        return np.stack([i.ravel() * self.square, j.ravel() * self.square,
                         np.zeros(i.size)], axis=1)

    def outline(self) -> np.ndarray:
        """The outer squares' four corners ``(4, 3)`` in the target frame."""
        s = self.square
        x0, x1, y0, y1 = -s, self.cols * s, -s, self.rows * s
        return np.array([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], dtype=float)


class _Hand(NamedTuple):
    """Ellipses ``(cx, cy, ax, ay)`` in the target plane, metres: palm and thumb."""

    ellipses: np.ndarray


def _board_albedo(board: Checkerboard, x: np.ndarray, y: np.ndarray,
                  hand: _Hand | None) -> tuple[np.ndarray, np.ndarray]:
    """RGB albedo ``(N, 3)`` and coverage ``(N,)`` bool at target-plane points."""
    x0, x1, y0, y1 = board.plate
    inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    s = board.square
    squares = (x >= -s) & (x < board.cols * s) & (y >= -s) & (y < board.rows * s)
    black = squares & ((np.floor(x / s).astype(np.int64) + np.floor(y / s).astype(np.int64))
                       % 2 == 0)
    grey = np.where(black, board.black, board.white)
    rgb = np.repeat(grey[:, None], 3, axis=1)
    if hand is not None:
        skin = np.zeros(len(x), dtype=bool)
        for cx, cy, ax, ay in hand.ellipses:
            skin |= ((x - cx) / ax) ** 2 + ((y - cy) / ay) ** 2 <= 1.0
        rgb[skin] = _SKIN
        inside = inside | skin
    return rgb, inside


@dataclass(frozen=True)
class CalibrationCell:
    """The true cell and its sensor (what a calibration should recover, and how the
    camera records).

    Attributes
    ----------
    camera : CameraModel
        The true intrinsics (plumb_bob).
    T_flange_camera, T_camera_laser : (4, 4) float64
        The true hand-eye and laser mount.
    appearance : Appearance
        Lights, table, wall, laser (:class:`robo3d.sim.render.Appearance`).
    view_encoding, laser_encoding : str
    jpeg_quality : int
    view_read_noise_dn, laser_read_noise_dn, gain_dn_per_electron, vignetting : float
    view_error_mm, view_error_deg : (lo, hi)
        The robot's per-stop pose error ranges.
    robot_error : {"constant", "drift"}
    pose_error_mm_per_m, pose_error_deg_per_m : float
        ``drift``: the position-dependent error's gradients.
    start_time_ns : int
    """

    camera: CameraModel
    T_flange_camera: np.ndarray
    T_camera_laser: np.ndarray
    appearance: Appearance = field(default_factory=Appearance)
    view_encoding: str = "jpeg"
    laser_encoding: str = "jpeg"
    jpeg_quality: int = 80
    view_read_noise_dn: float = 2.0
    laser_read_noise_dn: float = 2.0
    gain_dn_per_electron: float = 0.25
    vignetting: float = 0.25
    view_error_mm: tuple[float, float] = (0.01, 0.03)
    view_error_deg: tuple[float, float] = (0.005, 0.015)
    robot_error: str = "constant"
    pose_error_mm_per_m: float = 0.3
    pose_error_deg_per_m: float = 0.05
    start_time_ns: int = 1_700_000_000_000_000_000


@dataclass(frozen=True)
class CalibrationOptions:
    """What the calibration session records (defaults: a good session with three bad
    views).

    Attributes
    ----------
    rig : {"robot", "fixed"}
    views : int
        Target views (laser off), bad ones included, companions of laser frames not.
    laser_frames : int
        Laser frames (each with a companion view at the same pose).
    board : Checkerboard
    defects : tuple of str
        One bad view of each kind listed (:data:`DEFECTS`), spread over the session.
    tilt_max_deg, roll_max_deg : float
        Largest tilt of the optical axis from the board's normal, largest turn about it.
    distance_m : (lo, hi)
        Camera-to-board distance of the views (laser frames: where the sheet crosses
        the board, about the laser's crossing depth).
    edge_px : float
        Every inner corner this far inside the image (good views).
    defocus_sigma_px, motion_blur_px : float
        Defocus blur of every image; length of the motion-blurred view's smear.
    laser_exposure : float
        Scale of the laser frames' light (room light and stripe).
    nominal_error_mm, nominal_error_deg : (lo, hi)
        How far the published ``flange -> camera`` and ``camera -> laser`` are from the
        truth.
    focal_error : (lo, hi)
        Relative error of the placeholder focal length (before rounding to 10 px).
    supersample : int
        Sub-pixels per side on the board's edges and the stripe.
    view_period_s : float
        Time between stops.
    """

    rig: str = "robot"
    views: int = 25
    laser_frames: int = 15
    board: Checkerboard = field(default_factory=Checkerboard)
    defects: tuple[str, ...] = DEFECTS
    tilt_max_deg: float = 40.0
    roll_max_deg: float = 45.0
    distance_m: tuple[float, float] = (0.26, 0.36)
    edge_px: float = 8.0
    defocus_sigma_px: float = 0.6
    motion_blur_px: float = 9.0
    laser_exposure: float = 0.7
    nominal_error_mm: tuple[float, float] = (2.0, 5.0)
    nominal_error_deg: tuple[float, float] = (1.0, 3.0)
    focal_error: tuple[float, float] = (0.02, 0.05)
    supersample: int = 6
    view_period_s: float = 1.5

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first option out of range."""
        checks = [
            ("rig", self.rig in RIGS), ("views", self.views >= 0),
            ("laser_frames", self.laser_frames >= 0),
            ("views", self.views + self.laser_frames > 0),
            ("defects", all(d in DEFECTS for d in self.defects)
             and len(self.defects) <= max(self.views - 3, 0)),
            ("tilt_max_deg", 0 <= self.tilt_max_deg <= 60),
            ("roll_max_deg", 0 <= self.roll_max_deg <= 180),
            ("distance_m", 0.05 < self.distance_m[0] <= self.distance_m[1]),
            ("edge_px", self.edge_px >= 0), ("defocus_sigma_px", self.defocus_sigma_px >= 0),
            ("motion_blur_px", self.motion_blur_px >= 1),
            ("laser_exposure", self.laser_exposure > 0),
            ("supersample", 1 <= self.supersample <= 16),
            ("view_period_s", self.view_period_s >= 0.5),
            ("nominal_error_mm", 0 <= self.nominal_error_mm[0] <= self.nominal_error_mm[1]),
            ("nominal_error_deg", 0 <= self.nominal_error_deg[0] <= self.nominal_error_deg[1]),
            ("focal_error", 0 <= self.focal_error[0] <= self.focal_error[1] < 0.5),
        ]
        for name, ok in checks:
            if not ok:
                raise ValueError(f"calibration simulation option {name} out of range: "
                                 f"{getattr(self, name)!r}")


@dataclass
class CalibrationSimResult:
    """What :func:`write_calibration_recording` wrote.

    Attributes
    ----------
    path : Path
    rig : str
    n_views, n_laser_frames : int
        Images on ``/camera/image`` (companions included) and ``/camera/laser_image``.
    defects : dict of int to str
        Index on ``/camera/image`` -> kind of the bad views.
    truth : dict
        The ``ground_truth/calibration.json`` document.
    published : CameraModel
        The placeholder calibration on ``/camera/calibration``.
    size_bytes : int
    seconds : float
    """

    path: Path
    rig: str
    n_views: int
    n_laser_frames: int
    defects: dict[int, str]
    truth: dict[str, Any]
    published: CameraModel
    size_bytes: int
    seconds: float


# =========================================================================== rendering
class BoardLayer(NamedTuple):
    """The board's contribution to one image (flat ``(H * W, ...)`` arrays).

    Attributes
    ----------
    coverage : (N,) float64
        Fraction of each pixel covered by the plate (or the hand).
    albedo : (N, 3) float64
        RGB albedo premultiplied by coverage (the pixel's mean of albedo x inside).
    laser : (N,) float64
        The pixel's mean of ``albedo_at_laser * exp(-2 d^2 / w^2)`` over the plate,
        times ``cos(theta) * r_ref / r`` (0 without a laser).
    depth : (N,) float64, metres
        Distance along the pixel centre's ray to the board plane (``inf``: none).
    """

    coverage: np.ndarray
    albedo: np.ndarray
    laser: np.ndarray
    depth: np.ndarray


def board_layer(camera: CameraModel, rays_camera: np.ndarray, T_camera_target: np.ndarray,
                board: Checkerboard, *, T_camera_laser: np.ndarray | None = None,
                appearance: Appearance | None = None, supersample: int = 8,
                hand: _Hand | None = None) -> BoardLayer:
    """Render the board (and the laser on it) at every pixel, anti-aliased.

    Parameters
    ----------
    camera : CameraModel
        The true camera.
    rays_camera : (H * W, 3) float64
        Unit rays of the pixel centres in the camera frame (row-major,
        :func:`robo3d.sim.render.pixel_grid_rays`).
    T_camera_target : (4, 4) float64
        The board's pose.
    board : Checkerboard
    T_camera_laser : (4, 4) float64, optional
        The laser (its sheet is the x-z plane); None: no laser.
    appearance : Appearance, optional
        Laser width, fan, reference range and colour (needed with a laser).
    supersample : int
        Sub-pixels per side where the footprint meets an edge or the sheet.
    hand : optional
        Skin-coloured ellipses in the target plane (a hand holding the board).

    Returns
    -------
    BoardLayer
    """
    H, W = camera.height, camera.width
    t_ct = np.asarray(T_camera_target, dtype=np.float64)
    o, ex, ey, nz = t_ct[:3, 3], t_ct[:3, 0], t_ct[:3, 1], t_ct[:3, 2]
    full_cov, full_alb = np.zeros(H * W), np.zeros((H * W, 3))
    full_las, full_depth = np.zeros(H * W), np.full(H * W, np.inf)
    box = _board_pixel_box(camera, t_ct, board, hand)
    if box is None:
        return BoardLayer(full_cov, full_alb, full_las, full_depth)
    laser_on = T_camera_laser is not None
    a = appearance or Appearance()
    t_cl = np.asarray(T_camera_laser if laser_on else np.eye(4), dtype=np.float64)
    lo, ln = t_cl[:3, 3], t_cl[:3, 1]
    r0, r1, c0, c1 = box
    h, w = r1 - r0, c1 - c0
    crop = (np.arange(r0, r1)[:, None] * W + np.arange(c0, c1)[None, :]).ravel()
    d = np.asarray(rays_camera, dtype=np.float64)[crop]
    proj = d @ np.stack([ex, ey, nz, ln], axis=1)  # ray . axis, (N, 4)
    dn = proj[:, 2]
    valid = dn > 1e-9  # the printed face (normal -z) toward the camera: n . d > 0
    depth = np.where(valid, (o @ nz) / np.where(valid, dn, 1.0), np.inf)
    valid &= depth > 0
    depth[~valid] = np.inf
    dep0 = np.where(valid, depth, 0.0)
    x = (dep0 * proj[:, 0] - o @ ex).reshape(h, w)
    y = (dep0 * proj[:, 1] - o @ ey).reshape(h, w)
    vmap = valid.reshape(h, w)
    # Jacobian of the board coordinates in pixels (central differences)
    x_v, x_u = np.gradient(x)
    y_v, y_u = np.gradient(y)
    hx = 0.5 * (np.abs(x_u) + np.abs(x_v)) * 1.05 + 1e-9
    hy = 0.5 * (np.abs(y_u) + np.abs(y_v)) * 1.05 + 1e-9
    x0, x1, y0, y1 = board.plate
    s = board.square
    near_plate = vmap & (x > x0 - hx) & (x < x1 + hx) & (y > y0 - hy) & (y < y1 + hy)
    in_sq_x = (x > -s - hx) & (x < board.cols * s + hx)
    in_sq_y = (y > -s - hy) & (y < board.rows * s + hy)
    gx = np.abs(x / s - np.round(x / s)) * s < hx
    gy = np.abs(y / s - np.round(y / s)) * s < hy
    edge = near_plate & ((gx & in_sq_x & in_sq_y) | (gy & in_sq_x & in_sq_y)
                         | (np.abs(x - x0) < hx) | (np.abs(x - x1) < hx)
                         | (np.abs(y - y0) < hy) | (np.abs(y - y1) < hy))
    if hand is not None:
        for cx, cy, ax, ay in hand.ellipses:
            edge |= vmap & (np.abs(x - cx) < ax + hx) & (np.abs(y - cy) < ay + hy)
    if laser_on:
        ds = (dep0 * proj[:, 3] - lo @ ln).reshape(h, w)
        ds_v, ds_u = np.gradient(ds)
        hs = 0.5 * (np.abs(ds_u) + np.abs(ds_v))
        edge |= vmap & (np.abs(ds) < 2.5 * a.laser_width + hs) & near_plate
    xf, yf = x.ravel(), y.ravel()
    rgb, inside = _board_albedo(board, np.where(valid, xf, 1e9), np.where(valid, yf, 1e9),
                                hand)
    cov = inside.astype(np.float64)
    alb = rgb * cov[:, None]
    las_w = np.zeros(h * w)
    if laser_on:  # pixel centres near the sheet (the supersampled ones are redone below)
        lit = np.flatnonzero(np.abs(ds.ravel()) < 3.0 * a.laser_width)
        g = np.exp(-2.0 * (ds.ravel()[lit] / a.laser_width) ** 2)
        las_w[lit] = _albedo_at_laser(rgb[lit], a) * g * cov[lit]
    idx = np.flatnonzero(edge.ravel())
    if len(idx):
        n = max(int(supersample), 1)
        offs = (np.arange(n) + 0.5) / n - 0.5
        du, dv = (m.ravel()[None, :] for m in np.meshgrid(offs, offs))
        xs = (xf[idx, None] + x_u.ravel()[idx, None] * du + x_v.ravel()[idx, None] * dv)
        ys = (yf[idx, None] + y_u.ravel()[idx, None] * du + y_v.ravel()[idx, None] * dv)
        srgb, sin_ = _board_albedo(board, xs.ravel(), ys.ravel(), hand)
        sin_f = sin_.astype(np.float64)
        cov[idx] = sin_f.reshape(len(idx), -1).mean(axis=1)
        alb[idx] = (srgb * sin_f[:, None]).reshape(len(idx), -1, 3).mean(axis=1)
        if laser_on:
            dss = (ds.ravel()[idx, None] + ds_u.ravel()[idx, None] * du
                   + ds_v.ravel()[idx, None] * dv).ravel()
            gs = np.exp(-2.0 * (dss / a.laser_width) ** 2)
            las_w[idx] = (_albedo_at_laser(srgb, a) * gs * sin_f).reshape(len(idx), -1
                                                                          ).mean(axis=1)
    if laser_on:
        nz_ = np.flatnonzero(las_w)
        las_w[nz_] *= (_laser_geometry(d[nz_] * dep0[nz_, None], t_ct, t_cl, a)
                       * valid[nz_])
    full_cov[crop], full_alb[crop], full_las[crop] = cov * valid, alb * valid[:, None], las_w
    full_depth[crop] = depth
    return BoardLayer(full_cov, full_alb, full_las, full_depth)


def _board_pixel_box(camera: CameraModel, t_ct: np.ndarray, board: Checkerboard,
                     hand: _Hand | None) -> tuple[int, int, int, int] | None:
    """Rows ``r0:r1`` and columns ``c0:c1`` holding the plate's (and hand's) image."""
    x0, x1, y0, y1 = board.plate
    if hand is not None:
        e = hand.ellipses
        x0 = min(x0, float((e[:, 0] - e[:, 2]).min()))
        x1 = max(x1, float((e[:, 0] + e[:, 2]).max()))
        y0 = min(y0, float((e[:, 1] - e[:, 3]).min()))
        y1 = max(y1, float((e[:, 1] + e[:, 3]).max()))
    s = np.linspace(0.0, 1.0, 33)
    one = np.ones(33)
    xs = np.concatenate([x0 + (x1 - x0) * s, x1 * one, x1 - (x1 - x0) * s, x0 * one])
    ys = np.concatenate([y0 * one, y0 + (y1 - y0) * s, y1 * one, y1 - (y1 - y0) * s])
    p = np.stack([xs, ys, np.zeros_like(xs)], axis=1) @ t_ct[:3, :3].T + t_ct[:3, 3]
    if np.any(p[:, 2] <= 1e-3):  # reaches behind the camera: the whole image
        return 0, camera.height, 0, camera.width
    uv, _ = camera.project(p)
    c0 = int(np.clip(np.floor(uv[:, 0].min()) - 3, 0, camera.width))
    c1 = int(np.clip(np.ceil(uv[:, 0].max()) + 4, 0, camera.width))
    r0 = int(np.clip(np.floor(uv[:, 1].min()) - 3, 0, camera.height))
    r1 = int(np.clip(np.ceil(uv[:, 1].max()) + 4, 0, camera.height))
    if c1 - c0 < 3 or r1 - r0 < 3:
        return None
    return r0, r1, c0, c1


def _albedo_at_laser(rgb: np.ndarray, a: Appearance) -> np.ndarray:
    if a.laser_rgb is None:
        return rgb.mean(axis=1)
    return rgb[:, int(np.argmax(a.laser_rgb))]


def _laser_geometry(pts: np.ndarray, t_ct: np.ndarray, t_cl: np.ndarray,
                    a: Appearance) -> np.ndarray:
    """``cos(theta) * r_ref / r`` of the laser at board points (0 outside the fan, or
    where the laser is behind the board's printed face)."""
    lo = t_cl[:3, 3]
    vec = pts - lo
    r = np.maximum(np.linalg.norm(vec, axis=1), 1e-9)
    front = -t_ct[:3, 2]  # the printed face's normal
    cos = np.maximum(-(vec @ front) / r, 0.0)
    p_l = vec @ t_cl[:3, :3]
    fan = (p_l[:, 2] > 0) & (np.abs(np.arctan2(p_l[:, 0], p_l[:, 2]))
                             <= np.radians(a.laser_fan_deg))
    return cos * (a.laser_reference_range / r) * fan


def _board_radiance(layer: BoardLayer, rays: np.ndarray, t_world_camera: np.ndarray,
                    t_ct: np.ndarray, a: Appearance, glare_lamp: np.ndarray | None
                    ) -> np.ndarray:
    """Room-lit RGB DN ``(N, 3)`` of the board, premultiplied by coverage."""
    light = np.asarray(a.light_dir, dtype=np.float64)
    light /= np.linalg.norm(light)
    front_world = -(t_world_camera[:3, :3] @ t_ct[:3, 2])
    irr = a.ambient + a.direct * max(float(front_world @ light), 0.0)
    out = layer.albedo * (irr * a.view_exposure_dn)
    if glare_lamp is not None:  # Blinn-Phong image of a lamp on the laminated board
        p = rays * np.where(np.isfinite(layer.depth), layer.depth, 0.0)[:, None]
        to_l = glare_lamp - p
        to_l /= np.maximum(np.linalg.norm(to_l, axis=1, keepdims=True), 1e-9)
        to_c = -p / np.maximum(np.linalg.norm(p, axis=1, keepdims=True), 1e-9)
        hv = to_l + to_c
        hv /= np.maximum(np.linalg.norm(hv, axis=1, keepdims=True), 1e-9)
        nh = np.maximum(hv @ (-t_ct[:3, 2]), 0.0)
        out += (2.0 * a.view_exposure_dn * nh ** 800 * layer.coverage)[:, None]
    return out


def _glare_lamp(t_ct: np.ndarray, board: Checkerboard, rng: np.random.Generator) -> np.ndarray:
    """A lamp (camera frame) whose mirror image falls on the board's squares."""
    s = board.square
    q = np.array([rng.uniform(0.2, 0.8) * (board.cols - 1) * s,
                  rng.uniform(0.25, 0.75) * (board.rows - 1) * s, 0.0])
    p = t_ct[:3, :3] @ q + t_ct[:3, 3]
    n = -t_ct[:3, 2]
    v = p / np.linalg.norm(p)  # camera -> point
    r = v - 2 * (v @ n) * n  # mirrored
    return p + 1.2 * r


def _half_camera(camera: CameraModel) -> CameraModel:
    """The same lens at half resolution (pixel centres: ``u_half = (u + 0.5) / 2 - 0.5``)."""
    k = camera.K.copy()
    k[:2, :] *= 0.5
    k[0, 2] -= 0.25
    k[1, 2] -= 0.25
    return CameraModel(camera.frame_id, (camera.width + 1) // 2, (camera.height + 1) // 2, k,
                       camera.D)


class _Background:
    """The scene behind the board, rendered at half resolution and resized."""

    def __init__(self, scene: SimScene, camera: CameraModel) -> None:
        self.scene = scene
        self.camera = camera
        self.half = _half_camera(camera)

    def _up(self, img: np.ndarray) -> np.ndarray:
        c = self.camera
        return cv2.resize(img.astype(np.float32), (c.width, c.height),
                          interpolation=cv2.INTER_LINEAR).astype(np.float64)

    def view(self, t_world_camera: np.ndarray) -> np.ndarray:
        return self._up(render_view(self.scene, self.half, t_world_camera))

    def laser(self, t_world_camera: np.ndarray, t_world_laser: np.ndarray) -> np.ndarray:
        return self._up(render_laser_frame(self.scene, self.half, t_world_camera,
                                           t_world_laser))

    def depth(self, t_world_camera: np.ndarray, rays_camera: np.ndarray,
              idx: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Whether the scene hides the board at pixels ``idx`` (its hit is nearer).

        Only the clutter can (the table is below the board, the wall behind it): rays
        are cast only for the pixels inside the image of the clutter's bounding box.
        """
        out = np.zeros(len(idx), dtype=bool)
        lo, hi = self.scene.mesh.bounds
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                            for z in (lo[2], hi[2])])
        t_cw = invert_transform(t_world_camera)
        pc = corners @ t_cw[:3, :3].T + t_cw[:3, 3]
        if len(idx) == 0 or np.all(pc[:, 2] <= 0):
            return out
        if np.all(pc[:, 2] > 1e-3):
            uv, _ = self.camera.project(pc)
            u, v = idx % self.camera.width, idx // self.camera.width
            near = ((u >= uv[:, 0].min() - 2) & (u <= uv[:, 0].max() + 2)
                    & (v >= uv[:, 1].min() - 2) & (v <= uv[:, 1].max() + 2))
        else:
            near = np.ones(len(idx), dtype=bool)
        sel = idx[near]
        if len(sel) == 0:
            return out
        dirs = rays_camera[sel] @ t_world_camera[:3, :3].T
        f = self.scene.first_hit_distance(t_world_camera[:3, 3], dirs * depth[sel, None])
        out[near] = f < 1.0 - 1e-6
        return out


def _clutter_mesh() -> TriangleMesh:
    """Clutter on the table beside the board: a small box and a can (closed, outward)."""
    def box(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1])
                      for x in (lo[0], hi[0])], dtype=float)
        f = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                      [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
        return v, f

    def can(c: np.ndarray, r: float, hgt: float, n: int = 40) -> tuple[np.ndarray, np.ndarray]:
        a = 2 * np.pi * np.arange(n) / n
        ring = np.stack([c[0] + r * np.cos(a), c[1] + r * np.sin(a)], axis=1)
        v = np.concatenate([np.c_[ring, np.zeros(n)], np.c_[ring, np.full(n, hgt)],
                            [[c[0], c[1], 0.0], [c[0], c[1], hgt]]])
        i = np.arange(n)
        j = (i + 1) % n
        side = np.concatenate([np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1)])
        bottom = np.stack([np.full(n, 2 * n), j, i], 1)
        top = np.stack([np.full(n, 2 * n + 1), n + i, n + j], 1)
        return v, np.concatenate([side, bottom, top])

    v1, f1 = box(np.array([0.135, 0.085, 0.0]), np.array([0.185, 0.125, 0.030]))
    v2, f2 = can(np.array([0.205, 0.035]), 0.022, 0.060)
    mesh = TriangleMesh(np.concatenate([v1, v2]).astype(np.float32).astype(np.float64),
                        np.concatenate([f1, f2 + len(v1)]).astype(np.int64))
    return mesh


# =========================================================================== poses
def _inner_corners_uv(camera: CameraModel, t_ct: np.ndarray,
                      board: Checkerboard) -> tuple[np.ndarray, np.ndarray]:
    p = board.corners() @ t_ct[:3, :3].T + t_ct[:3, 3]
    return camera.project(p)


def _fraction_inside(camera: CameraModel, t_ct: np.ndarray, board: Checkerboard,
                     edge: float) -> float:
    """Fraction of the inner corners that project inside the image (``edge`` px in)."""
    uv, front = _inner_corners_uv(camera, t_ct, board)
    ok = (front & (uv[:, 0] >= edge) & (uv[:, 0] <= camera.width - 1 - edge)
          & (uv[:, 1] >= edge) & (uv[:, 1] <= camera.height - 1 - edge))
    return float(ok.mean())


def _all_inside(camera: CameraModel, t_ct: np.ndarray, board: Checkerboard,
                edge: float) -> bool:
    pts = np.concatenate([board.corners(), board.outline()])
    uv, front = camera.project(pts @ t_ct[:3, :3].T + t_ct[:3, 3])
    return bool(np.all(front & (uv[:, 0] >= edge) & (uv[:, 0] <= camera.width - 1 - edge)
                       & (uv[:, 1] >= edge) & (uv[:, 1] <= camera.height - 1 - edge))
                and t_ct[:3, 3] @ t_ct[:3, 2] > 0)


def sheet_board_line(T_camera_target: np.ndarray, T_camera_laser: np.ndarray,
                     board: Checkerboard, n: int = 200) -> np.ndarray:
    """Points ``(M, 3)`` (camera frame) of the laser sheet's line on the board's squares.

    The sheet (the laser frame's x-z plane) cut with the board plane, clipped to the
    squares' rectangle; ``M = 0`` when they miss.
    """
    t_ct = np.asarray(T_camera_target, dtype=np.float64)
    t_cl = np.asarray(T_camera_laser, dtype=np.float64)
    ln, lo = t_cl[:3, 1], t_cl[:3, 3]
    o, ex, ey = t_ct[:3, 3], t_ct[:3, 0], t_ct[:3, 1]
    a0, b, c = (o - lo) @ ln, ex @ ln, ey @ ln  # a0 + b x + c y = 0
    s = board.square
    xr, yr = (-s, board.cols * s), (-s, board.rows * s)
    if abs(b) >= abs(c):
        yy = np.linspace(*yr, n)
        xx = -(a0 + c * yy) / b
    else:
        xx = np.linspace(*xr, n)
        yy = -(a0 + b * xx) / c
    keep = (xx >= xr[0]) & (xx <= xr[1]) & (yy >= yr[0]) & (yy <= yr[1])
    return o + xx[keep, None] * ex + yy[keep, None] * ey


def _robot_pose(rng: np.random.Generator, camera: CameraModel, t_world_target: np.ndarray,
                board: Checkerboard, o: CalibrationOptions, k: int, n: int,
                defect: str | None, t_camera_laser: np.ndarray | None) -> np.ndarray:
    """``T_world_camera`` of one robot stop (rejection sampling, see the notes)."""
    centre = t_world_target[:3, :3] @ board.centre + t_world_target[:3, 3]
    golden = np.pi * (3 - np.sqrt(5))
    for _ in range(400):
        frac = np.sqrt((k + rng.uniform(0.2, 0.8)) / max(n, 1))  # tilts spread over the disc
        tilt = np.radians(o.tilt_max_deg) * min(frac, 1.0)
        az = k * golden + rng.uniform(-0.3, 0.3)
        dist = rng.uniform(*o.distance_m)
        if t_camera_laser is not None:  # the sheet near the board's centre
            dist = rng.uniform(0.85, 1.3) * _crossing(t_camera_laser)
            tilt = np.radians(rng.uniform(5.0, o.tilt_max_deg * 0.9))
        aim = centre + np.r_[rng.uniform(-0.012, 0.012, 2), 0.0]
        if defect == "out_of_frame":
            aim = centre + np.r_[rng.uniform(-1, 1, 2) * 0.07, 0.0]
        eye = aim + dist * np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az),
                                     np.cos(tilt)])
        roll = np.radians(rng.uniform(-o.roll_max_deg, o.roll_max_deg))
        t_wc = look_at(eye, aim, roll=roll, up=np.array([0.0, 1.0, 0.0]))
        t_ct = invert_transform(t_wc) @ t_world_target
        if _pose_ok(camera, t_ct, board, o, defect, t_camera_laser):
            return t_wc
    raise ValueError(f"no camera pose found for stop {k} (board too large for the image "
                     f"at distance {o.distance_m} m?)")


def _crossing(t_camera_laser: np.ndarray) -> float:
    """Depth at which the laser sheet crosses the optical axis."""
    ln, lo = t_camera_laser[:3, 1], t_camera_laser[:3, 3]
    return float((lo @ ln) / ln[2]) if abs(ln[2]) > 1e-9 else 0.3


def _pose_ok(camera: CameraModel, t_ct: np.ndarray, board: Checkerboard,
             o: CalibrationOptions, defect: str | None,
             t_camera_laser: np.ndarray | None) -> bool:
    """Whether a sampled board pose is what its stop asks for: an out-of-frame defect
    shows 35-80 % of the board; any other pose shows all of it ``edge_px`` inside the
    image, and (a laser frame) a stripe across it from the laser's side."""
    if defect == "out_of_frame":
        return 0.35 <= _fraction_inside(camera, t_ct, board, 0.0) <= 0.8
    if not _all_inside(camera, t_ct, board, o.edge_px):
        return False
    return t_camera_laser is None or _stripe_ok(t_ct, t_camera_laser, board)


def _stripe_ok(t_ct: np.ndarray, t_cl: np.ndarray, board: Checkerboard) -> bool:
    line = sheet_board_line(t_ct, t_cl, board)
    if len(line) < 2:
        return False
    span = np.linalg.norm(line[-1] - line[0])
    front = -t_ct[:3, 2]
    laser_side = (t_cl[:3, 3] - t_ct[:3, 3]) @ front > 0
    return bool(laser_side and span >= 0.5 * min(board.cols + 1, board.rows + 1)
                * board.square)


def _fixed_pose(rng: np.random.Generator, camera: CameraModel, board: Checkerboard,
                o: CalibrationOptions, defect: str | None,
                t_camera_laser: np.ndarray | None) -> np.ndarray:
    """``T_camera_target`` of a hand-held board (rejection sampling)."""
    for _ in range(400):
        if t_camera_laser is not None:  # a point of the sheet, then the board around it
            z = rng.uniform(0.88, 1.2) * _crossing(t_camera_laser)
            ln, lo = t_camera_laser[:3, 1], t_camera_laser[:3, 3]
            xq = rng.uniform(-0.02, 0.02)
            yq = (lo @ ln - ln[0] * xq - ln[2] * z) / ln[1]
            target_pt = np.array([xq, yq, z])
        else:
            z = rng.uniform(*o.distance_m)
            target_pt = np.array([rng.uniform(-0.25, 0.25) * z, rng.uniform(-0.2, 0.2) * z, z])
        axis_az = rng.uniform(0, 2 * np.pi)
        tilt = np.radians(rng.uniform(0.0, o.tilt_max_deg))
        r = (rotation_about_axis(np.array([np.cos(axis_az), np.sin(axis_az), 0.0]), tilt)
             @ rotation_about_axis(np.array([0.0, 0.0, 1.0]),
                                   np.radians(rng.uniform(-o.roll_max_deg, o.roll_max_deg))))
        shift = np.r_[rng.uniform(-0.3, 0.3, 2) * [board.cols, board.rows] * board.square, 0]
        if defect == "out_of_frame":
            shift = np.r_[rng.uniform(-1, 1, 2) * 0.07, 0.0]
        t_ct = make_transform(r, target_pt - r @ (board.centre + shift))
        if _pose_ok(camera, t_ct, board, o, defect, t_camera_laser):
            return t_ct
    raise ValueError("no board pose found (board too large for the image?)")


# =========================================================================== published
def placeholder_camera(camera: CameraModel, rng: np.random.Generator,
                       focal_error: tuple[float, float] = (0.02, 0.05)) -> CameraModel:
    """The calibration a cell publishes before it is calibrated: ``f`` from the lens's
    nominal focal length (``focal_error`` off, either sign, rounded to 10 px), the
    principal point at the image centre, no distortion."""
    err = rng.uniform(*focal_error) * rng.choice([-1.0, 1.0])
    f = round(0.5 * (camera.fx + camera.fy) * (1 + err) / 10.0) * 10.0
    k = np.array([[f, 0, (camera.width - 1) / 2], [0, f, (camera.height - 1) / 2], [0, 0, 1]])
    return CameraModel(camera.frame_id, camera.width, camera.height, k, np.zeros(5))


def nominal_transform(T: np.ndarray, rng: np.random.Generator,
                      error_mm: tuple[float, float], error_deg: tuple[float, float]
                      ) -> np.ndarray:
    """A nominal value of a mount: the truth times a random rigid error of the given
    sizes (translation mm, rotation degrees)."""
    e = random_rigid_error(rng, (error_mm[0] * 1e-3, error_mm[1] * 1e-3), error_deg)
    return np.asarray(T, dtype=np.float64) @ e


# =========================================================================== writer
def _flat(t: np.ndarray | None) -> list[list[float]] | None:
    if t is None:
        return None
    return [[round(float(x), 12) for x in row] for row in np.asarray(t)]


def _tf_json(samples: list[tuple[int, str, str, np.ndarray]]) -> bytes:
    """``ground_truth/tf.json`` (``recording-format.md``): a ``foxglove.FrameTransforms``
    message in JSON of ``(stamp, parent, child, T)`` samples."""
    out = []
    for stamp, parent, child, t in sorted(samples, key=lambda s: (s[0], s[1], s[2])):
        q = matrix_to_quat(t[:3, :3])
        out.append({"timestamp": {"sec": int(stamp) // 1_000_000_000,
                                  "nsec": int(stamp) % 1_000_000_000},
                    "parent_frame_id": parent, "child_frame_id": child,
                    "translation": dict(zip("xyz", (round(float(x), 9) for x in t[:3, 3]),
                                            strict=True)),
                    "rotation": dict(zip("xyzw", (round(float(x), 12) for x in q),
                                         strict=True))})
    return json.dumps({"transforms": out}, separators=(",", ":")).encode()


def _schedule(o: CalibrationOptions) -> tuple[list[str | None], list[int]]:
    """Defect of each target view; where among the views the bad ones go."""
    defects: list[str | None] = [None] * o.views
    n = len(o.defects)
    for j, d in enumerate(o.defects):
        defects[int(round((j + 1) * o.views / (n + 1)))] = d
    return defects, [i for i, d in enumerate(defects) if d]


def write_calibration_recording(path: str | os.PathLike[str], cell: CalibrationCell,
                                options: CalibrationOptions | None = None, *, seed: int = 0,
                                threads: int = 1, message_encoding: str = "protobuf"
                                ) -> CalibrationSimResult:
    """Simulate one calibration session and write it as an MCAP recording.

    Parameters
    ----------
    path : str or path-like
        The ``.mcap`` file (written atomically).
    cell : CalibrationCell
        The true cell (:func:`robo3d.simulate.calibration_cell`).
    options : CalibrationOptions, optional
    seed : int
        Seeds every random draw.
    threads : int
        Ray-casting threads of the background (0: all cores).
    message_encoding : {"protobuf", "json"}

    Returns
    -------
    CalibrationSimResult
    """
    from ..recording.writer import RecordingWriter

    o = options or CalibrationOptions()
    o.validate()
    wall = time.perf_counter()
    cam, a, board = cell.camera, cell.appearance, o.board
    robot = o.rig == "robot"
    t_cl = np.asarray(cell.T_camera_laser, dtype=np.float64)
    t_fc = np.asarray(cell.T_flange_camera, dtype=np.float64)
    scene = SimScene(_clutter_mesh(), a, threads=threads)
    bg = _Background(scene, cam)
    rays = scene.pixel_rays(cam)
    vig = vignetting(cam.height, cam.width, cell.vignetting) if cell.vignetting > 0 else None
    defects, _ = _schedule(o)
    # ------------------------------------------------------------ the world and the board
    yaw = np.radians(8.0)
    t_world_target = make_transform(
        rotation_about_axis(np.array([0.0, 0.0, 1.0]), yaw) @ np.diag([1.0, -1.0, -1.0]),
        np.array([0.0, 0.0, board.thickness]))
    t_world_target[:3, 3] -= t_world_target[:3, :3] @ board.centre
    t_world_target[2, 3] = board.thickness
    t_world_fixed_cam = look_at(np.array([0.55, -0.06, 0.24]), np.array([-0.10, 0.0, 0.10]))
    hand = None
    if not robot:
        x0, _, y0, y1 = board.plate
        ym = 0.5 * (y0 + y1)
        hand = _Hand(np.array([[x0 - 0.035, ym, 0.040, 0.028],
                               [x0 + 0.002, ym + 0.010, 0.0085, 0.0065]]))
    # ------------------------------------------------------------ poses
    stops: list[dict[str, Any]] = []  # one per image pair or view
    for i in range(o.views):
        rng = np.random.default_rng([seed, 20, i])
        if robot:
            t_wc = _robot_pose(rng, cam, t_world_target, board, o, i, o.views, defects[i], None)
            t_ct = invert_transform(t_wc) @ t_world_target
        else:
            t_ct = _fixed_pose(rng, cam, board, o, defects[i], None)
            t_wc = t_world_fixed_cam
        stops.append({"kind": "view", "T_world_camera": t_wc, "T_camera_target": t_ct,
                      "defect": defects[i]})
    for k in range(o.laser_frames):
        rng = np.random.default_rng([seed, 21, k])
        if robot:
            t_wc = _robot_pose(rng, cam, t_world_target, board, o, k, o.laser_frames, None,
                               t_cl)
            t_ct = invert_transform(t_wc) @ t_world_target
        else:
            t_ct = _fixed_pose(rng, cam, board, o, None, t_cl)
            t_wc = t_world_fixed_cam
        stops.append({"kind": "laser", "T_world_camera": t_wc, "T_camera_target": t_ct,
                      "defect": None})
    # ------------------------------------------------------------ time and robot error
    t0 = int(cell.start_time_ns)
    ms = 1_000_000
    period = int(o.view_period_s * 1e9)
    pose_err = None
    if robot and cell.robot_error == "drift":
        pose_err = PoseDependentError(np.random.default_rng([seed, 5]), cell.pose_error_mm_per_m,
                                      cell.pose_error_deg_per_m, t_world_target[:3, 3])
    tf_true: list[tuple[int, np.ndarray]] = []
    tf_rep: list[tuple[int, np.ndarray]] = []
    t_cf = invert_transform(t_fc)
    for j, st in enumerate(stops):
        stamp = t0 + 1000 * ms + j * period
        st["stamp"] = stamp
        if not robot:
            continue
        t_bf = st["T_world_camera"] @ t_cf
        e = random_rigid_error(np.random.default_rng([seed, 3, j]),
                               (cell.view_error_mm[0] * 1e-3, cell.view_error_mm[1] * 1e-3),
                               cell.view_error_deg)
        if pose_err is not None:
            e = e @ pose_err(t_bf[None, :3, 3])[0]
        st["error"] = e
        end = stamp + (_LASER_DELAY_NS if st["kind"] == "laser" else 0)
        for ts in range(stamp - 27 * ms, end + 34 * ms, 20 * ms):
            tf_true.append((ts, t_bf))
            tf_rep.append((ts, t_bf @ e))
    # ------------------------------------------------------------ published calibration
    rng_pub = np.random.default_rng([seed, 30])
    pub_cam = placeholder_camera(cam, rng_pub, o.focal_error)
    pub_fc = nominal_transform(t_fc, rng_pub, o.nominal_error_mm, o.nominal_error_deg)
    pub_cl = nominal_transform(t_cl, rng_pub, o.nominal_error_mm, o.nominal_error_deg)
    # ------------------------------------------------------------ truth
    # /camera/image in time order: the target views, then the laser frames' companions
    views_truth: list[dict[str, Any]] = []
    laser_truth: list[dict[str, Any]] = []
    for st in stops:
        entry = {"index": len(views_truth), "timestamp_ns": st["stamp"],
                 "T_camera_target": _flat(st["T_camera_target"]), "defect": st["defect"],
                 "laser_frame": None}
        if st["kind"] == "laser":
            entry["laser_frame"] = len(laser_truth)
            laser_truth.append({"index": len(laser_truth),
                                "timestamp_ns": st["stamp"] + _LASER_DELAY_NS,
                                "T_camera_target": entry["T_camera_target"],
                                "view": len(views_truth)})
        views_truth.append(entry)
    truth = {
        "camera": {"frame_id": cam.frame_id, "width": cam.width, "height": cam.height,
                   "K": [float(x) for x in cam.K.ravel()],
                   "D": [float(x) for x in cam.D[:5]], "distortion_model": "plumb_bob"},
        "T_flange_camera": _flat(t_fc) if robot else None,
        "T_camera_laser": _flat(t_cl),
        "T_base_target": _flat(t_world_target) if robot else None,
        "T_base_camera": None if robot else _flat(np.eye(4)),
        "views": views_truth,
        "laser_frames": laser_truth,
        "target": {"type": "checkerboard", "cols": board.cols, "rows": board.rows,
                   "square": board.square, "margin": board.margin, "moving": not robot,
                   "frame": "origin at the first inner corner, x along cols, y along rows, "
                            "z into the board (OpenCV object points)"},
        "published": {"K": [float(x) for x in pub_cam.K.ravel()], "D": [],
                      "T_flange_camera": _flat(pub_fc) if robot else None,
                      "T_camera_laser": _flat(pub_cl)},
        "rig": o.rig, "seed": int(seed),
    }
    defect_map = {v["index"]: v["defect"] for v in views_truth if v["defect"]}
    meta_target = {"type": "checkerboard", "cols": str(board.cols), "rows": str(board.rows),
                   "square": repr(float(board.square))}
    if not robot:
        meta_target["moving"] = "true"
    sim_meta = {"generator": "robo3d simulate-calibration", "rig": o.rig, "seed": str(seed),
                "views": str(o.views), "laser_frames": str(o.laser_frames),
                "defects": json.dumps({str(k): v for k, v in defect_map.items()}),
                "robot_error_model": "T_base_flange_reported = T_base_flange_true @ E "
                                     "(E per stop)" if robot else "none (no robot)",
                "published_errors": json.dumps(_published_errors(cam, pub_cam, t_fc, pub_fc,
                                                                 t_cl, pub_cl, robot))}
    # ------------------------------------------------------------ write
    p = Path(path)
    with RecordingWriter(p, message_encoding=message_encoding) as w:
        w.add_metadata("robo3d.recording", {"kind": "calibration", "object": "checkerboard",
                                            "units": "m"})
        w.add_metadata("robo3d.target", meta_target)
        w.add_metadata("robo3d.simulation", sim_meta)
        w.add_attachment(CALIBRATION_TRUTH,
                         json.dumps(truth, separators=(",", ":")).encode(), "application/json")
        # the truth of every link that carries error: base -> flange (robot), and the
        # mounts (published nominal), sampled with it so that the file alone resolves
        # the true camera and laser poses (robo3d.recording.read_ground_truth_tf)
        truth_tf: list[tuple[int, str, str, np.ndarray]] = []
        if robot:
            for ts, t_bf in tf_true:
                truth_tf += [(ts, "base", "flange", t_bf), (ts, "flange", "camera", t_fc),
                             (ts, "camera", "laser", t_cl)]
        else:
            for st in stops:
                end = st["stamp"] + (_LASER_DELAY_NS if st["kind"] == "laser" else 0)
                truth_tf += [(ts, "camera", "laser", t_cl)
                             for ts in range(st["stamp"] - 27 * ms, end + 34 * ms, 20 * ms)]
        w.add_attachment("ground_truth/tf.json", _tf_json(truth_tf), "application/json")
        w.write_calibration(_CAL_TOPIC, t0, pub_cam)
        static = ([("flange", "camera", pub_fc)] if robot
                  else [("base", "camera", np.eye(4))]) + [("camera", "laser", pub_cl)]
        w.write_transforms("/tf_static", t0, static)
        events: list[tuple[int, int, int]] = [(s, 0, i) for i, (s, _) in enumerate(tf_rep)]
        for j, st in enumerate(stops):
            events.append((st["stamp"], 1, j))
            if st["kind"] == "laser":
                events.append((st["stamp"] + _LASER_DELAY_NS, 2, j))
        events.sort()
        fixed_bg: dict[str, Any] = {}
        for stamp, kind, i in events:
            if kind == 0:
                w.write_transforms("/tf", stamp, [("base", "flange", tf_rep[i][1])])
                continue
            st = stops[i]
            laser = kind == 2
            img = _render_image(st, laser, cam, cell, o, bg, rays, t_cl, hand, vig, seed, i,
                                fixed_bg if not robot else None)
            if laser:
                w.write_image(_LASER_TOPIC, stamp, cam.frame_id, img, cell.laser_encoding,
                              cell.jpeg_quality)
            else:
                w.write_image(_VIEW_TOPIC, stamp, cam.frame_id, img, cell.view_encoding,
                              cell.jpeg_quality)
    seconds = time.perf_counter() - wall
    n_views = len(truth["views"])
    _log.info("simulated calibration %s (%s rig): %d views (%d bad), %d laser frames, "
              "%.2f MB, %.1f s", p, o.rig, n_views, len(defect_map), len(laser_truth),
              p.stat().st_size / 1e6, seconds)
    return CalibrationSimResult(p, o.rig, n_views, len(laser_truth), defect_map, truth,
                                pub_cam, p.stat().st_size, seconds)


def _published_errors(cam: CameraModel, pub: CameraModel, t_fc: np.ndarray,
                      pub_fc: np.ndarray, t_cl: np.ndarray, pub_cl: np.ndarray,
                      robot: bool) -> dict[str, float]:
    from ..transforms import rotation_angle_deg

    def err(a_: np.ndarray, b_: np.ndarray) -> tuple[float, float]:
        d = invert_transform(a_) @ b_
        return (round(float(np.linalg.norm(d[:3, 3])) * 1e3, 4),
                round(float(rotation_angle_deg(d[:3, :3])), 4))

    out = {"focal_px": round(pub.fx - cam.fx, 3),
           "principal_px": round(float(np.hypot(pub.cx - cam.cx, pub.cy - cam.cy)), 3)}
    if robot:
        out["flange_camera_mm"], out["flange_camera_deg"] = err(t_fc, pub_fc)
    out["camera_laser_mm"], out["camera_laser_deg"] = err(t_cl, pub_cl)
    return out


def _render_image(st: dict[str, Any], laser: bool, cam: CameraModel, cell: CalibrationCell,
                  o: CalibrationOptions, bg: _Background, rays: np.ndarray, t_cl: np.ndarray,
                  hand: _Hand | None, vig: np.ndarray | None, seed: int, i: int,
                  fixed_bg: dict[str, Any] | None) -> np.ndarray:
    """One noisy 8-bit image: background, board (and laser), optics, sensor."""
    a = cell.appearance
    t_wc, t_ct = st["T_world_camera"], st["T_camera_target"]
    h, w = cam.height, cam.width
    # background (the fixed rig's is the same for every image: rendered once)
    key = "laser" if laser else "view"
    if fixed_bg is not None and key in fixed_bg:
        back = fixed_bg[key]
    else:
        back = bg.laser(t_wc, t_wc @ t_cl) if laser else bg.view(t_wc)
        if fixed_bg is not None:
            fixed_bg[key] = back
    grey = back.ndim == 2
    back = back.reshape(h * w, -1)
    layer = board_layer(cam, rays, t_ct, o.board, T_camera_laser=t_cl if laser else None,
                        appearance=a, supersample=o.supersample, hand=hand)
    cov = layer.coverage.copy()
    idx = np.flatnonzero(cov > 0)
    hidden = bg.depth(t_wc, rays, idx, layer.depth)
    cov[idx[hidden]] = 0.0
    keep = cov > 0
    glare = None
    if st["defect"] == "glare" and not laser:
        glare = _glare_lamp(t_ct, o.board, np.random.default_rng([seed, 22, i]))
    rad = _board_radiance(layer, rays, t_wc, t_ct, a, glare) * keep[:, None]
    if grey:
        rad = rad.mean(axis=1, keepdims=True)
    if laser:
        frac = (a.laser_ambient_fraction if a.laser_ambient_fraction is not None
                else a.laser_ambient_dn / (a.view_exposure_dn * float(np.mean(a.object_albedo))))
        if fixed_bg is not None:  # the board's laser shadow on the background
            back = _shadowed(back, fixed_bg, bg, t_wc, t_ct, t_cl, o.board, frac)
        colour = np.ones(1) if grey else np.asarray(a.laser_rgb, dtype=np.float64)
        peak = a.laser_peak_dn
        if a.laser_rgb is None and a.laser_ambient_fraction is None:  # the demo cell's
            peak /= float(np.mean(a.object_albedo))  # scale (robo3d.sim.render)
        rad = rad * frac + (layer.laser * keep * peak)[:, None] * colour
    sig = back * (1.0 - cov)[:, None] + rad
    if laser:
        sig = sig * o.laser_exposure
    sig = sig.reshape(h, w, -1).astype(np.float32)
    if st["defect"] == "motion_blur" and not laser:
        sig = _motion_blur(sig, o.motion_blur_px, np.random.default_rng([seed, 23, i]))
    if o.defocus_sigma_px > 0:
        sig = cv2.GaussianBlur(sig, (0, 0), o.defocus_sigma_px).reshape(h, w, -1)
    if vig is not None:
        sig = sig * vig[..., None]
    noise = cell.laser_read_noise_dn if laser else cell.view_read_noise_dn
    img = sensor_noise(sig.astype(np.float64), np.random.default_rng([seed, 10 + laser, i]),
                       cell.gain_dn_per_electron, noise, gaussian_shot=True)
    return img[..., 0] if img.shape[2] == 1 else img


def _motion_blur(sig: np.ndarray, length: float, rng: np.random.Generator) -> np.ndarray:
    """Smear along a random direction (the camera still moving during the exposure)."""
    n = int(np.ceil(length)) | 1
    k = np.zeros((n, n), np.float32)
    ang = rng.uniform(0, np.pi)
    c = (n - 1) / 2
    for s in np.linspace(-length / 2, length / 2, 4 * n):
        k[int(round(c + s * np.sin(ang))), int(round(c + s * np.cos(ang)))] += 1
    k /= k.sum()
    out = cv2.filter2D(sig, -1, k, borderType=cv2.BORDER_REFLECT)
    return out.reshape(sig.shape)


def _shadowed(back: np.ndarray, fixed_bg: dict[str, Any], bg: _Background,
              t_wc: np.ndarray, t_ct: np.ndarray, t_cl: np.ndarray, board: Checkerboard,
              frac: float) -> np.ndarray:
    """The fixed rig's laser frame background without the laser where the board shadows
    it (the laser's light on the background is the laser frame minus the room light)."""
    if "stripe" not in fixed_bg:
        room = fixed_bg.get("view")
        if room is None:
            room = bg.view(t_wc)
            fixed_bg["view"] = room
        room = room.reshape(back.shape[0], -1)
        room_l = room * frac if back.shape[1] == room.shape[1] else \
            room.mean(axis=1, keepdims=True) * frac
        stripe = np.maximum(back - room_l, 0.0)
        lit = np.flatnonzero(stripe.max(axis=1) > 0.5)
        dirs = bg.scene.pixel_rays(bg.camera)[lit] @ t_wc[:3, :3].T
        hits = bg.scene.cast(t_wc[:3, 3], dirs, normals=False)
        pts_w = hits.points
        pts_c = (pts_w - t_wc[:3, 3]) @ t_wc[:3, :3]
        fixed_bg["stripe"] = (stripe, lit, pts_c, np.isfinite(hits.t))
    stripe, lit, pts_c, ok = fixed_bg["stripe"]
    lo = t_cl[:3, 3]
    n, o = t_ct[:3, 2], t_ct[:3, 3]
    vec = pts_c - lo
    den = vec @ n
    s = np.where(np.abs(den) > 1e-12, ((o - lo) @ n) / np.where(np.abs(den) > 1e-12, den, 1),
                 -1.0)
    cut = lo + s[:, None] * vec
    rel = cut - o
    x, y = rel @ t_ct[:3, 0], rel @ t_ct[:3, 1]
    x0, x1, y0, y1 = board.plate
    blocked = ok & (s > 0) & (s < 1) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
    out = back.copy()
    out[lit[blocked]] -= stripe[lit[blocked]]
    return out
