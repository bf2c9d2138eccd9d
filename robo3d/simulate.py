"""The simulator: synthetic scan recordings with ground truth (``robo3d simulate``).

A robot carries a camera and a line laser around an object resting on a table. The
simulator writes one MCAP recording that follows ``recording-format.md``:

- ``/camera/calibration`` (once), ``/tf_static`` (``flange -> camera`` hand-eye,
  ``flange -> laser`` mount), ``/tf`` (``base -> flange`` as the robot reports it);
- ``/camera/image``: ``views`` ambient-lit views on rings around the object (laser off),
  the robot stop-and-go (four ``/tf`` samples 20 ms apart around each image);
- ``/camera/laser_image``: ``sweeps`` straight constant-velocity passes of the laser
  sheet across the object (``/tf`` streamed at ``tf_rate_hz`` while moving, image stamps
  between samples), separated by ``sweep_gap_s`` seconds;
- metadata ``robo3d.recording`` (kind, object, units, workspace box) and
  ``robo3d.simulation`` (the seed and every parameter, JSON-encoded values);
- attachments ``ground_truth/mesh.ply`` (the object in ``base``, the very mesh the
  images were rendered from) and ``ground_truth/tf.json`` (the true ``base -> flange``
  samples, one per ``/tf`` sample, which carries the simulated robot error; plus the
  true ``flange -> camera`` and ``flange -> laser`` as entries with ``"static": true``,
  so the file alone resolves true camera poses).

Choices
-------
- Deterministic: every random draw comes from ``numpy.random.default_rng`` seeded with
  ``[seed, stream, index...]`` (one stream per purpose, so changing the number of views
  does not change the sweeps' errors or noise), and time starts at a constant
  ``start_time_ns`` (1 700 000 000 s); the same arguments give a byte-identical file.
- Robot error: each sweep's reported flange pose is ``T_true @ E`` with one constant
  random rigid ``E`` per sweep (``sweep_error_mm``, ``sweep_error_deg`` ranges); each
  view gets its own much smaller ``E`` (``view_error_mm``, ``view_error_deg``). The
  injected errors are listed in ``robo3d.simulation`` (``sweep_errors``, ``view_errors``:
  translation mm and rotation degrees).
- The workspace box is the object's bounding box grown by ``workspace_margin`` (10 mm),
  except its floor, ``workspace_floor`` (0.5 mm) above the table so the table is out.
- Sweeps: one from straight above (``sweep_top``) and ``sweeps - 1`` side passes on two
  rings: up to ``sweep_low_count`` low ones at ``sweep_low_elevation_deg`` (diagonal
  azimuths from ``sweep_low_azimuth0_deg``: each sees two faces of a box, and the low
  angle reaches steep walls, side pockets and the rounded edges near the table), the
  rest at ``sweep_elevation_deg`` (from ``sweep_azimuth0_deg``: the top's walls and
  grooves); ``sweep_low_elevation_deg = None`` puts every side pass on the one ring.
  The demos' plan (7 sweeps) was chosen so that each demo's true surface is seen by the
  laser nearly everywhere above the table (issue 5); each sweep moves along the laser
  sheet's normal by ``sweep_spacing`` per frame (2.2 mm by default, 1.1 mm in the
  demos) at ``sweep_speed``; ``sweep_frames`` (tests) instead fixes the number of
  frames and stretches the spacing to cover the object.
- Laser frames are quiet by design (object ``laser_ambient_dn`` = 1 DN, read noise
  0.12 DN, shot noise at 0.025 DN per electron), so their PNGs compress to a few kB.
- Realism (issue 10), all options off in the demos: room-lit RGB laser frames of a
  red, green or blue laser, coloured textured glossy objects, a bright table with
  printed markers, a wall, JPEG at webcam quality, a cheap sensor's noise and
  vignetting (``SimulationParams.cell``); a robot error that drifts within a sweep and
  depends on the pose (``robot_error="drift"``); a late camera clock (``clock_lag_ms``);
  a user's mesh file as the object (``object_mesh``, ``mesh_unit``).
- Ground truth of non-demo recordings follows ``recording-format.md``:
  ``ground_truth/tf.json`` as a ``foxglove.FrameTransforms`` JSON message (the true
  ``base -> flange`` samples; the mounts are exact, ``/tf_static`` is their truth),
  ``ground_truth/silhouettes/NNN.png`` (the object hits of the pixel-centre rays at the
  view's true pose, 255 on the object), and ``ground_truth/image_poses.json`` (the
  true camera and laser pose of every image at its exposure, for stripe truth:
  :func:`stripe_truth`). The demos (``demo_format``, :func:`write_demos`) keep the
  first ``tf.json`` form and no other attachments, so that their bytes do not change.
- Ray casting runs on ``threads`` Open3D threads (1 by default; 0 for all cores) with
  BLAS limited to one thread (its idle spinning otherwise costs more than it gives on
  these small matrix products); the output does not depend on either.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import logging
import os
import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .errors import Robo3dError
from .recording.images import encode_image
from .sim.calibration import (
    CalibrationCell,
    CalibrationOptions,
    CalibrationSimResult,
    Checkerboard,
    write_calibration_recording,
)
from .sim.render import (
    LEGACY_FIELDS,
    Appearance,
    SimScene,
    StripeTruth,
    render_laser_frame,
    render_view,
    sensor_noise,
    speckle_gain,
    vignetting,
    visible_stripe_points,
)
from .sim.rig import (
    PoseDependentError,
    default_camera,
    default_hand_eye,
    default_laser_mount,
    drift_error,
    look_at,
    random_drift,
    random_rigid_error,
    sweep_poses,
    view_poses,
)
from .sim.shapes import OBJECTS, TriangleMesh, make_object, mesh_to_ply_bytes
from .transforms import invert_transform, matrix_to_quat, rotation_angle_deg

__all__ = [
    "SimulationParams",
    "SimulationResult",
    "DEMOS",
    "OBJECT_NAMES",
    "simulate_recording",
    "write_demos",
    "object_mesh",
    "load_object_mesh",
    "truth_scene",
    "image_poses",
    "stripe_truth",
    "SMALL_PRESET",
    "CELL_SENSOR",
    "MESH_UNITS",
    "ROBOT_ERROR_MODELS",
    "SILHOUETTES",
    "IMAGE_POSES",
    "calibration_cell",
    "simulate_calibration",
    "CalibrationOptions",
    "CalibrationSimResult",
    "Checkerboard",
]

_log = logging.getLogger(__name__)

#: Objects the simulator knows.
OBJECT_NAMES: tuple[str, ...] = tuple(OBJECTS)

#: Attachment prefix of the true silhouettes (``NNN.png``, the NNN-th view in time order).
SILHOUETTES = "ground_truth/silhouettes/"
#: Attachment of the true camera (and laser) pose of every image at its exposure.
IMAGE_POSES = "ground_truth/image_poses.json"

_VIEW_TOPIC = "/camera/image"
_LASER_TOPIC = "/camera/laser_image"
#: Topic of the laser-off frames (``SimulationParams.laser_off``).
LASER_OFF_TOPIC = "/camera/laser_off"
_CAL_TOPIC = "/camera/calibration"


@dataclass(frozen=True)
class SimulationParams:
    """Every parameter of a simulated recording (defaults: the demo recordings).

    Lengths in metres, angles in degrees, times in seconds unless the name says
    otherwise; error ranges are ``(lo, hi)`` magnitudes (uniform).

    Attributes
    ----------
    seed : int
        Seeds every random draw (view jitter, robot errors, sensor noise).
    width, height : int
        Image size, pixels (the focal length scales with the width).
    views, view_elevations_deg, view_distance, view_jitter, view_period_s
        Number of silhouette views, their rings, camera-to-object distance, random
        perturbation scale (0: exact rings) and time between views.
    view_encoding, jpeg_quality, view_read_noise_dn
        Views' encoding (``jpeg``, ``png``, ``rgb8``, ``bgr8``), JPEG quality, read noise.
    sweeps, sweep_elevation_deg, sweep_azimuth0_deg, sweep_top
        Number of laser sweeps, elevation and first azimuth of the (upper ring of) side
        sweeps, whether the last sweep looks from straight above.
    sweep_low_elevation_deg, sweep_low_count, sweep_low_azimuth0_deg, sweep_low_roll_deg
        The lower ring of side sweeps (``None``: no lower ring): elevation, how many of
        the side sweeps it takes at most, first azimuth, and the camera's turn about its
        axis (90: the laser beside the camera rather than above it, so that it reaches
        the down-facing surface near the table that the camera sees).
    sweep_spacing, sweep_frames, sweep_speed, sweep_margin, sweep_gap_s, tf_rate_hz
        Camera travel per frame (or ``sweep_frames`` per sweep), speed (m/s), overshoot
        past the object's box, pause between sweeps, ``/tf`` rate while moving.
    laser_encoding, laser_read_noise_dn, gain_dn_per_electron
        Laser frames' encoding (``png``, ``mono8``, ``jpeg``), read noise, shot noise gain.
        ``mono8`` in a scene with a coloured laser is a monochrome camera (no colour
        filters): each pixel sees the mean of the rendered channels, the laser's and the
        room light's alike.
    baseline, crossing
        Camera-to-laser distance; depth where the sheet crosses the optical axis.
    sweep_error_mm, sweep_error_deg, view_error_mm, view_error_deg
        Ranges of the robot's pose error per sweep and per view.
    mesh_faces, mesh_voxel
        Truth mesh: triangles after decimation, marching-cubes grid spacing.
    workspace_margin, workspace_floor
        Workspace box: margin around the object; floor height above the table.
    start_time_ns : int
        Time of the first message (calibration, static transforms).
    appearance : Appearance
        Materials, lights, laser and supersampling (:class:`robo3d.sim.render.Appearance`;
        :meth:`Appearance.cell` is a real-looking cell: room light in the laser frames,
        a red, green or blue laser on RGB frames, a coloured textured glossy object on a
        bright marker table before a wall).

    The fields below were added for issue 10; at their defaults the recording is the
    demo cell's, unchanged (see :meth:`cell` and :meth:`small` for presets).

    vignetting : float
        Fraction of the light lost in the image corners (``1 - v (r / r_corner)^2``),
        views and laser frames; 0: none.
    robot_error : {"constant", "drift"}
        ``constant``: one rigid error per sweep (per view). ``drift``: that error times a
        smooth drift within the sweep and a flange-position-dependent term
        (:mod:`robo3d.sim.rig`), which the per-sweep rigid alignment does not model.
    drift_mm, drift_deg : (lo, hi)
        ``drift``: magnitudes of the within-sweep translation and rotation drift.
    pose_error_mm_per_m, pose_error_deg_per_m : float
        ``drift``: gradients of the pose-dependent error (per metre from the object's
        centre); it applies to the views too.
    clock_lag_ms : float
        The camera clock is late by this much: an image stamped ``t`` is rendered at the
        robot's pose at ``t + lag`` (``|lag| <= 30`` ms).
    rolling_shutter_ms : float
        A rolling-shutter camera: a laser frame's rows are exposed one after the other,
        the first at the frame's time and the last this much later (a webcam: about 30
        ms), each at the robot's pose then (rendered in bands of
        :data:`ROLLING_BAND_ROWS` rows). The views are taken at rest and unaffected. 0:
        a global shutter.
    laser_speckle, speckle_grain_px : float
        Laser speckle in the laser frames (:func:`robo3d.sim.render.speckle_gain`): the
        stripe's light times a random factor of mean 1 and this standard deviation (0:
        none; 1: fully developed), correlated over about ``speckle_grain_px`` pixels, a
        new pattern in every frame. The room light is not affected.
    object_mesh : str or None
        A mesh file (STL, PLY, OBJ) to scan instead of a named object
        (:func:`load_object_mesh`).
    mesh_unit : str
        Unit of ``object_mesh``'s coordinates (:data:`MESH_UNITS`).
    turntable : bool
        A turntable rig instead of a robot: the camera and the laser stand still in the
        room, looking at the object from ``sweep_elevation_deg`` (the laser beside the
        upright camera, its sheet upright through the turntable's axis: the stripe runs
        down the image), while the object and the
        table (its plate, 0.04 m wider than the object on every side) turn about the
        vertical axis through the object's centre. ``base`` turns with the object, so the
        camera circles it in ``base``; the wall and the directional light stay in the
        room and turn in ``base``. Each sweep is one revolution (``sweep_frames``
        frames, or one every ``sweep_spacing`` at the object's rim), the sweeps' start
        angles interleaved; the views are taken on the turntable too (their rings'
        elevations, the camera moved between rings). The rig's error (``sweep_error_*``
        per revolution, ``view_error_*`` per view) is a rigid error in ``base`` (the
        turntable's angle read off, the object nudged on its plate), not in the flange.
    workspace_box : bool
        Write the workspace box into the recording's metadata (False: none, as a ROS
        bag has none; the truth attachments stay).
    laser_off : bool
        After each laser frame, a laser-off frame on :data:`LASER_OFF_TOPIC`, 1 ms later
        and at the same pose (a strobed laser or a robot that holds still for the pair),
        with its own sensor noise: what ``stripes.laser_off_topic`` subtracts.
    """

    seed: int = 0
    width: int = 640
    height: int = 480
    # silhouette views
    views: int = 24
    view_elevations_deg: tuple[float, ...] = (20.0, 42.0, 65.0)
    view_distance: float = 0.30
    view_jitter: float = 1.0
    view_period_s: float = 1.5
    view_encoding: str = "jpeg"
    jpeg_quality: int = 92
    view_read_noise_dn: float = 1.0
    # laser sweeps
    sweeps: int = 7
    sweep_elevation_deg: float = 55.0
    sweep_azimuth0_deg: float = 0.0
    sweep_top: bool = True
    sweep_low_elevation_deg: float | None = 10.0
    sweep_low_count: int = 4
    sweep_low_azimuth0_deg: float = 45.0
    sweep_low_roll_deg: float = 90.0
    sweep_spacing: float = 0.0022
    sweep_frames: int | None = None
    sweep_speed: float = 0.02
    sweep_margin: float = 0.006
    sweep_gap_s: float = 2.0
    tf_rate_hz: float = 60.0
    laser_encoding: str = "png"
    laser_read_noise_dn: float = 0.12
    gain_dn_per_electron: float = 0.025
    # rig
    baseline: float = 0.08
    crossing: float = 0.27
    # robot error
    sweep_error_mm: tuple[float, float] = (0.2, 0.4)
    sweep_error_deg: tuple[float, float] = (0.1, 0.3)
    view_error_mm: tuple[float, float] = (0.01, 0.03)
    view_error_deg: tuple[float, float] = (0.005, 0.015)
    # truth mesh
    mesh_faces: int = 40_000
    mesh_voxel: float = 0.0006
    # metadata
    workspace_margin: float = 0.01
    workspace_floor: float = 0.0005
    start_time_ns: int = 1_700_000_000_000_000_000
    appearance: Appearance = field(default_factory=Appearance)
    # ---- realism (issue 10); the defaults give the demo recordings exactly
    vignetting: float = 0.0
    robot_error: str = "constant"
    drift_mm: tuple[float, float] = (0.02, 0.05)
    drift_deg: tuple[float, float] = (0.005, 0.015)
    pose_error_mm_per_m: float = 0.3
    pose_error_deg_per_m: float = 0.05
    clock_lag_ms: float = 0.0
    rolling_shutter_ms: float = 0.0
    laser_speckle: float = 0.0
    speckle_grain_px: float = 1.5
    object_mesh: str | None = None
    mesh_unit: str = "m"
    turntable: bool = False
    workspace_box: bool = True
    laser_off: bool = False

    @classmethod
    def cell(cls, laser: str | tuple[float, float, float] = "red",
             object_color: str | tuple[float, float, float] = "orange",
             texture: str = "blotches", markers: str = "aruco", wall: bool = True,
             small: bool = False, **overrides: Any) -> SimulationParams:
        """A real-looking cell (``robo3d simulate --scene cell``).

        Room light in the laser frames, a coloured laser (RGB laser frames), a coloured
        textured glossy object on a bright marker table before a wall
        (:meth:`Appearance.cell`), JPEG quality 80 for views and laser frames, a cheap
        camera's noise (read noise 2 DN, 0.25 DN per electron, 25 % vignetting).

        Parameters
        ----------
        laser, object_color, texture, markers, wall
            As :meth:`robo3d.sim.render.Appearance.cell`.
        small : bool
            Start from :data:`SMALL_PRESET` (320 x 240, 10 views, 3 sweeps of 40 frames).
        **overrides
            Any field (``appearance`` replaces the whole appearance).
        """
        kw: dict[str, Any] = dict(SMALL_PRESET) if small else {}
        kw.update(CELL_SENSOR)
        kw["appearance"] = Appearance.cell(laser=laser, object_color=object_color,
                                           texture=texture, markers=markers, wall=wall)
        kw.update(overrides)
        return cls(**kw)

    @classmethod
    def small(cls, **overrides: Any) -> SimulationParams:
        """The demo cell's look at test size (:data:`SMALL_PRESET`)."""
        return cls(**{**SMALL_PRESET, **overrides})

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first parameter out of range."""
        checks = [
            ("width", self.width >= 16), ("height", self.height >= 16),
            ("views", self.views >= 0), ("sweeps", self.sweeps >= 0),
            ("views", self.views + self.sweeps > 0),  # views and sweeps both zero
            ("view_distance", self.view_distance > 0), ("sweep_spacing", self.sweep_spacing > 0),
            ("sweep_speed", self.sweep_speed > 0), ("tf_rate_hz", self.tf_rate_hz >= 20),
            ("sweep_gap_s", self.sweep_gap_s > 0), ("view_period_s", self.view_period_s >= 0.1),
            ("jpeg_quality", 1 <= self.jpeg_quality <= 100),
            ("sweep_frames", self.sweep_frames is None or self.sweep_frames >= 2),
            ("sweep_low_elevation_deg", self.sweep_low_elevation_deg is None
             or 0 < self.sweep_low_elevation_deg < 90),
            ("sweep_low_count", self.sweep_low_count >= 0),
            ("view_elevations_deg", len(self.view_elevations_deg) >= 1
             and all(0 < e < 90 for e in self.view_elevations_deg)),
            ("view_encoding", self.view_encoding in ("jpeg", "png", "rgb8", "bgr8")),
            ("laser_encoding", self.laser_encoding in ("png", "jpeg", "mono8")),
            ("view_read_noise_dn", self.view_read_noise_dn >= 0),
            ("laser_read_noise_dn", self.laser_read_noise_dn >= 0),
            ("gain_dn_per_electron", self.gain_dn_per_electron >= 0),
            ("sweep_error_mm", 0 <= self.sweep_error_mm[0] <= self.sweep_error_mm[1]),
            ("sweep_error_deg", 0 <= self.sweep_error_deg[0] <= self.sweep_error_deg[1]),
            ("view_error_mm", 0 <= self.view_error_mm[0] <= self.view_error_mm[1]),
            ("view_error_deg", 0 <= self.view_error_deg[0] <= self.view_error_deg[1]),
            ("start_time_ns", self.start_time_ns >= 10_000_000_000),
            ("vignetting", 0 <= self.vignetting < 1),
            ("robot_error", self.robot_error in ROBOT_ERROR_MODELS),
            ("drift_mm", 0 <= self.drift_mm[0] <= self.drift_mm[1]),
            ("drift_deg", 0 <= self.drift_deg[0] <= self.drift_deg[1]),
            ("pose_error_mm_per_m", self.pose_error_mm_per_m >= 0),
            ("pose_error_deg_per_m", self.pose_error_deg_per_m >= 0),
            ("clock_lag_ms", abs(self.clock_lag_ms) <= 30),
            ("rolling_shutter_ms", 0 <= self.rolling_shutter_ms <= 100),
            ("laser_speckle", 0 <= self.laser_speckle <= 1),
            ("speckle_grain_px", 0.5 <= self.speckle_grain_px <= 20),
            ("mesh_unit", self.mesh_unit in MESH_UNITS),
        ]
        for name, ok in checks:
            if not ok:
                raise ValueError(f"simulation parameter {name} out of range: "
                                 f"{getattr(self, name)!r}")

    def to_metadata(self, full: bool = True) -> dict[str, str]:
        """Every parameter as ``{name: JSON string}`` (appearance fields prefixed).

        Parameters
        ----------
        full : bool
            False: the parameters added for issue 10 only where they differ from their
            defaults (how the demo recordings are written, so that they stay
            byte-identical to those written before the options existed).
        """
        out: dict[str, str] = {}
        d = SimulationParams()
        for k, v in dataclasses.asdict(self).items():
            if k == "appearance":
                for ka, va in v.items():
                    if (full or ka in _LEGACY_APPEARANCE
                            or va != getattr(d.appearance, ka)):
                        out[f"appearance.{ka}"] = json.dumps(va)
            elif full or k not in _NEW_FIELDS or getattr(self, k) != getattr(d, k):
                out[k] = json.dumps(v)
        return out


#: Robot error models (``SimulationParams.robot_error``).
ROBOT_ERROR_MODELS: tuple[str, ...] = ("constant", "drift")
#: Length units of a user's mesh file (``--mesh-unit``), metres per unit.
MESH_UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "um": 1e-6, "in": 0.0254}
#: The small, fast scene for tests and benchmarks (a cell scene in a few seconds).
SMALL_PRESET: dict[str, Any] = dict(width=320, height=240, views=10, sweeps=3,
                                    sweep_frames=40, mesh_faces=20_000, mesh_voxel=0.0012)
#: The sensor of :meth:`SimulationParams.cell`: a cheap webcam's JPEG and noise.
CELL_SENSOR: dict[str, Any] = dict(view_encoding="jpeg", laser_encoding="jpeg",
                                   jpeg_quality=80, view_read_noise_dn=2.0,
                                   laser_read_noise_dn=2.0, gain_dn_per_electron=0.25,
                                   vignetting=0.25)
_NEW_FIELDS = frozenset({"laser_off", "vignetting", "robot_error", "drift_mm", "drift_deg",
                         "pose_error_mm_per_m", "pose_error_deg_per_m", "clock_lag_ms",
                         "object_mesh", "mesh_unit", "rolling_shutter_ms", "turntable",
                         "workspace_box", "laser_speckle", "speckle_grain_px"})
#: rows of a rolling-shutter laser frame rendered at one pose (``rolling_shutter_ms``): a
#: 960-row frame with a 30 ms readout at 20 mm/s moves 5 micrometres within a band
ROLLING_BAND_ROWS = 8
_LEGACY_APPEARANCE = frozenset(LEGACY_FIELDS)


@dataclass
class SimulationResult:
    """What :func:`simulate_recording` wrote.

    Attributes
    ----------
    path : Path
    object_name : str
    n_views, n_laser_frames : int
    frames_per_sweep : list of int
    sweep_errors : (K, 4, 4) float64
        The injected flange-frame error ``E`` of each sweep.
    view_errors : (N, 4, 4) float64
    T_flange_camera, T_flange_laser : (4, 4) float64
    size_bytes : int
    seconds : float
        Wall time of the run (not written into the file).
    """

    path: Path
    object_name: str
    n_views: int
    n_laser_frames: int
    frames_per_sweep: list[int]
    sweep_errors: np.ndarray
    view_errors: np.ndarray
    T_flange_camera: np.ndarray
    T_flange_laser: np.ndarray
    size_bytes: int
    seconds: float


#: The demo recordings: file stem -> (object, parameter overrides).
#: Their laser profiles are 1.1 mm apart (half the default spacing): alignment and the
#: final mesh gain from it (issue 5), and the files (about 7 MB each) are generated on
#: the first ``./run.sh demo`` instead of being kept in the repository.
DEMOS: dict[str, tuple[str, dict[str, Any]]] = {
    "dimple_block": ("dimple_block", {"seed": 1, "sweep_spacing": 0.0011}),
    "vase": ("vase", {"seed": 2, "sweep_spacing": 0.0011}),
}


@lru_cache(maxsize=8)
def object_mesh(name: str, voxel: float = 0.0006, faces: int = 40_000) -> TriangleMesh:
    """The ground-truth mesh of a named object (cached; arrays read-only).

    Parameters
    ----------
    name : str
        One of :data:`OBJECT_NAMES`.
    voxel : float, metres
    faces : int
    """
    mesh = make_object(name, voxel=voxel, faces=faces)
    mesh.vertices.setflags(write=False)
    mesh.faces.setflags(write=False)
    return mesh


def load_object_mesh(path: str | os.PathLike[str], unit: str = "m") -> TriangleMesh:
    """A user's mesh file as the simulated object (``--object-mesh``).

    The mesh is scaled from ``unit`` to metres and placed standing on the table: its
    lowest vertex at ``z = 0``, its bounding box centred on the base's z axis (the
    workspace's centre). Vertices are rounded to float32 (the truth is what is rendered);
    unused vertices are dropped, and a mesh whose faces are wound inward (negative
    volume) is turned outward, as shading and the laser's incidence need.

    Parameters
    ----------
    path : str or path-like
        STL, PLY or OBJ (any format :func:`robo3d.meshio.read_mesh` reads).
    unit : str
        One of :data:`MESH_UNITS` (``m``, ``cm``, ``mm``, ``um``, ``in``).

    Raises
    ------
    Robo3dError
        The file is missing, unreadable, empty, non-finite or flat, naming the file.
    """
    from .meshio import read_mesh

    if unit not in MESH_UNITS:
        raise ValueError(f"unknown mesh unit {unit!r}; expected one of {', '.join(MESH_UNITS)}")
    try:
        v, f = read_mesh(path)
    except FileNotFoundError as exc:
        raise Robo3dError(f"object mesh {str(path)!r}: no such file") from exc
    except Robo3dError as exc:
        raise Robo3dError(f"object mesh {str(path)!r}: cannot be read ({exc})") from exc
    if len(v) == 0 or len(f) == 0:
        raise Robo3dError(f"object mesh {str(path)!r} is empty ({len(v)} vertices, "
                          f"{len(f)} faces)")
    if not np.all(np.isfinite(v)):
        raise Robo3dError(f"object mesh {str(path)!r} has non-finite vertex coordinates")
    used = np.unique(f)
    v = v[used] * MESH_UNITS[unit]
    f = np.searchsorted(used, f)
    lo, hi = v.min(axis=0), v.max(axis=0)
    if np.any(hi - lo < 1e-4):
        raise Robo3dError(f"object mesh {str(path)!r} is flat or tiny: its box is "
                          f"{(hi - lo) * 1e3} mm (unit {unit!r}; wrong --mesh-unit?)")
    if np.any(hi - lo > 1.0):
        raise Robo3dError(f"object mesh {str(path)!r} is {(hi - lo).max():.2f} m across "
                          f"(unit {unit!r}; wrong --mesh-unit?); the simulated table is "
                          "1.2 m wide")
    v = v - np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2]])
    mesh = TriangleMesh(v.astype(np.float32).astype(np.float64), f.astype(np.int64))
    if mesh.volume() < 0:  # faces wound inward (some exporters): shading needs outward
        _log.info("object mesh %s: faces wound inward, flipped", path)
        mesh = TriangleMesh(mesh.vertices, np.ascontiguousarray(mesh.faces[:, ::-1]))
    return mesh


def truth_scene(recording: Any, threads: int = 1) -> SimScene:
    """The scene a simulated recording was rendered from (for stripe truth).

    Rebuilt from the ``ground_truth/mesh.ply`` attachment and the ``appearance.*`` entries
    of the ``robo3d.simulation`` metadata (a recording written with ``demo_format``
    lists the demo's appearance completely too).

    Parameters
    ----------
    recording : robo3d.recording.Recording
    threads : int
    """
    from .meshio import read_mesh

    meta = recording.metadata.get("robo3d.simulation")
    data = recording.attachments.get("ground_truth/mesh.ply")
    if meta is None or data is None:
        raise Robo3dError(f"{recording.path}: not a simulated recording (needs metadata "
                          "robo3d.simulation and attachment ground_truth/mesh.ply)")
    kw = {}
    for k, v in meta.items():
        if k.startswith("appearance."):
            val = json.loads(v)
            kw[k.split(".", 1)[1]] = tuple(val) if isinstance(val, list) else val
    fields = {f.name for f in dataclasses.fields(Appearance)}
    v, f = read_mesh(bytes(data), suffix=".ply")
    return SimScene(TriangleMesh(v, f), Appearance(**{k: x for k, x in kw.items()
                                                      if k in fields}), threads=threads)


def image_poses(recording: Any) -> dict[str, Any]:
    """The ``ground_truth/image_poses.json`` attachment, poses as ``(4, 4)`` arrays.

    Returns
    -------
    dict
        ``clock_lag_ns`` and per image topic a list of ``{"index", "stamp_ns",
        "exposure_ns", "T_base_camera", ("T_base_laser", "sweep", "frame")}``: the TRUE
        poses at the moment each image was taken (its stamp plus the clock lag).
    """
    data = recording.attachments.get(IMAGE_POSES)
    if data is None:
        raise Robo3dError(f"{recording.path}: no {IMAGE_POSES} attachment (a recording "
                          "simulated with demo_format, or not simulated)")
    doc = json.loads(data)
    for topic in (_VIEW_TOPIC, _LASER_TOPIC):
        for e in doc.get(topic, []):
            for key in ("T_base_camera", "T_base_laser"):
                if key in e:
                    e[key] = np.asarray(e[key], dtype=np.float64).reshape(4, 4)
    return doc


def stripe_truth(recording: Any, index: int, scene: SimScene | None = None,
                 poses: dict[str, Any] | None = None) -> StripeTruth:
    """The true visible stripe of the ``index``-th laser frame of a simulated recording.

    Parameters
    ----------
    recording : robo3d.recording.Recording
    index : int
        Position of the frame on ``/camera/laser_image`` in time order.
    scene, poses : optional
        :func:`truth_scene` and :func:`image_poses` of the recording (pass them when
        calling for many frames).

    Returns
    -------
    StripeTruth
        See :func:`robo3d.sim.render.visible_stripe_points`.
    """
    scene = scene or truth_scene(recording)
    poses = poses or image_poses(recording)
    e = poses[_LASER_TOPIC][index]
    camera = next(iter(recording.calibrations.values()))
    return visible_stripe_points(scene, camera, e["T_base_camera"], e["T_base_laser"])


def _blas_one_thread() -> contextlib.AbstractContextManager[Any]:
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional speed-up
        return contextlib.nullcontext()
    return threadpool_limits(1, user_api="blas")


def _error_summary(errors: np.ndarray) -> list[dict[str, float]]:
    return [{"translation_mm": round(float(np.linalg.norm(e[:3, 3])) * 1e3, 6),
             "rotation_deg": round(float(rotation_angle_deg(e[:3, :3])), 6)} for e in errors]


def _sweep_plan(p: SimulationParams) -> list[tuple[float, float, float]]:
    """(azimuth, elevation, roll) in degrees of each sweep."""
    if p.sweeps == 0:
        return []
    n_side = p.sweeps - 1 if (p.sweep_top and p.sweeps >= 2) else p.sweeps
    n_low = 0 if p.sweep_low_elevation_deg is None else min(p.sweep_low_count, n_side)
    n_high = n_side - n_low
    plan = [(p.sweep_low_azimuth0_deg + 360.0 * k / n_low, float(p.sweep_low_elevation_deg),
             p.sweep_low_roll_deg) for k in range(n_low)]
    plan += [(p.sweep_azimuth0_deg + 360.0 * k / n_high, p.sweep_elevation_deg, 0.0)
             for k in range(n_high)]
    if n_side < p.sweeps:
        plan.append((p.sweep_azimuth0_deg, 90.0, 0.0))
    return plan


def simulate_recording(path: str | os.PathLike[str], object_name: str | None = "dimple_block",
                       *, params: SimulationParams | None = None, threads: int = 1,
                       message_encoding: str = "protobuf", demo_format: bool = False,
                       **overrides: Any) -> SimulationResult:
    """Simulate a scan of one object and write it as an MCAP recording.

    Parameters
    ----------
    path : str or path-like
        The ``.mcap`` file to write (atomically).
    object_name : str or None
        One of :data:`OBJECT_NAMES`; ignored when ``object_mesh`` is set (the recording
        then names the object after the mesh file's stem).
    params : SimulationParams, optional
        All parameters (defaults: the demo settings).
    threads : int
        Ray-casting threads (0: all cores); the output does not depend on it.
    message_encoding : {"protobuf", "json"}
    demo_format : bool
        Write the ground truth as the demo recordings have it (``ground_truth/tf.json`` in
        robo3d's first form, no silhouettes or image poses, the issue-10 parameters in
        the metadata only where not default), so that :func:`write_demos` gives files
        byte-identical to earlier versions. Otherwise the attachments follow
        ``recording-format.md`` (see ``recordings/README.md``).
    **overrides
        Any :class:`SimulationParams` field, e.g. ``views=8, sweeps=2, width=320``;
        ``appearance`` fields may be given as ``appearance=Appearance(...)``.

    Returns
    -------
    SimulationResult

    Examples
    --------
    >>> simulate_recording("s.mcap", "sphere", width=320, height=240, views=8,
    ...                    sweeps=2, sweep_frames=20)                  # doctest: +SKIP
    """
    p = params or SimulationParams()
    unknown = set(overrides) - {f.name for f in dataclasses.fields(SimulationParams)}
    if unknown:
        raise ValueError(f"unknown simulation parameter(s): {', '.join(sorted(unknown))}")
    p = dataclasses.replace(p, **overrides)
    if p.object_mesh is not None:
        p = dataclasses.replace(p, object_mesh=str(p.object_mesh))
        object_name = Path(p.object_mesh).stem
    elif object_name not in OBJECTS:
        raise ValueError(f"unknown object {object_name!r}; expected one of "
                         f"{', '.join(OBJECT_NAMES)} (or a mesh file: object_mesh)")
    for name in ("view_elevations_deg", "sweep_error_mm", "sweep_error_deg",
                 "view_error_mm", "view_error_deg", "drift_mm",
                 "drift_deg"):  # lists from JSON/CLI -> tuples
        p = dataclasses.replace(p, **{name: tuple(float(x) for x in getattr(p, name))})
    p.validate()
    wall = time.perf_counter()
    with _blas_one_thread():
        result = _simulate(Path(path), str(object_name), p, threads, message_encoding,
                           legacy=demo_format)
    result.seconds = time.perf_counter() - wall
    _log.info("simulated %s (%s): %d views, %d laser frames in %d sweeps (%s frames), "
              "%.2f MB, %.1f s", result.path, object_name, result.n_views,
              result.n_laser_frames, len(result.frames_per_sweep),
              ", ".join(map(str, result.frames_per_sweep)) or "no", result.size_bytes / 1e6,
              result.seconds)
    return result


def _simulate(path: Path, object_name: str, p: SimulationParams, threads: int,
              message_encoding: str, legacy: bool = False) -> SimulationResult:
    from .recording.writer import RecordingWriter

    if p.object_mesh is not None:
        mesh = load_object_mesh(p.object_mesh, p.mesh_unit)
    else:
        mesh = object_mesh(object_name, p.mesh_voxel, p.mesh_faces)
    lo, hi = mesh.bounds
    target = 0.5 * (lo + hi)
    if p.turntable:  # the plate turns with the object; the wall and the light stay
        plate = float(np.max(np.abs(np.r_[lo[:2], hi[:2]]))) + 0.04
        scene = SimScene(mesh, p.appearance, table_half_size=plate, threads=threads,
                         turntable=True)
    else:
        scene = SimScene(mesh, p.appearance, threads=threads)
    off_scene = None
    if p.laser_off:  # the same scene and room light, the laser dark
        off_scene = copy.copy(scene)
        off_scene.appearance = dataclasses.replace(p.appearance, laser_peak_dn=0.0)
    camera = default_camera(p.width, p.height)
    t_flange_camera = default_hand_eye()
    t_camera_laser = default_laser_mount(p.baseline, p.crossing)
    if p.turntable:  # the laser beside the upright camera, its sheet upright
        turn = np.eye(4)
        turn[:3, :3] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
        t_camera_laser = turn @ t_camera_laser
    t_flange_laser = t_flange_camera @ t_camera_laser
    t_camera_flange = invert_transform(t_flange_camera)
    t0 = int(p.start_time_ns)
    ms = 1_000_000
    drift = p.robot_error == "drift"
    lag_ns = int(round(p.clock_lag_ms * 1e6))
    pose_err = (PoseDependentError(np.random.default_rng([p.seed, 5]), p.pose_error_mm_per_m,
                                   p.pose_error_deg_per_m, target) if drift else None)
    vig = (vignetting(p.height, p.width, p.vignetting) if p.vignetting > 0 else None)
    # room-lit images: shot noise from its normal approximation (the demo cell: Poisson)
    fast_noise = p.appearance.laser_ambient_fraction is not None

    # ---------------------------------------------------------------- views
    # (a turntable's views are these too: the camera's rings about the object in base)
    view_cams = (view_poses(p.views, target, p.view_distance, p.view_elevations_deg,
                            np.random.default_rng([p.seed, 1]), p.view_jitter)
                 if p.views else np.zeros((0, 4, 4)))
    rng_ve = np.random.default_rng([p.seed, 3])
    view_err = np.stack([random_rigid_error(rng_ve, tuple(np.array(p.view_error_mm) * 1e-3),
                                            p.view_error_deg) for _ in range(p.views)]) \
        if p.views else np.zeros((0, 4, 4))
    if pose_err is not None and p.views:  # the robot's pose-dependent error, at each view
        view_err = view_err @ pose_err((view_cams @ t_camera_flange)[:, :3, 3])
    view_stamps = t0 + 1000 * ms + np.arange(p.views, dtype=np.int64) * int(p.view_period_s * 1e9)
    tf_true: list[tuple[int, np.ndarray]] = []
    tf_reported: list[tuple[int, np.ndarray]] = []
    for i in range(p.views):
        t_true = view_cams[i] @ t_camera_flange
        for off in (-27, -7, 13, 33):  # stop-and-go: a few samples around the image
            tf_true.append((int(view_stamps[i]) + off * ms, t_true))
            tf_reported.append((int(view_stamps[i]) + off * ms,
                                _reported(t_true, view_err[i], p.turntable)))
    t_next = int(view_stamps[-1]) + 1000 * ms if p.views else t0 + 1000 * ms

    # ---------------------------------------------------------------- sweeps
    rng_se = np.random.default_rng([p.seed, 2])
    plan = _sweep_plan(p)
    sweep_err = np.stack([random_rigid_error(rng_se, tuple(np.array(p.sweep_error_mm) * 1e-3),
                                             p.sweep_error_deg) for _ in plan]) \
        if plan else np.zeros((0, 4, 4))
    rng_drift = np.random.default_rng([p.seed, 4])
    tf_period = int(round(1e9 / p.tf_rate_hz))
    laser_frames: list[tuple[int, int, int, np.ndarray]] = []  # (stamp, sweep, frame, T_cam)
    laser_velocity: list[np.ndarray] = []  # the camera's velocity at each frame, m/s
    frames_per_sweep: list[int] = []
    error_span: list[dict[str, float]] = []
    for k, (az, el, roll) in enumerate(plan):
        ts = t_next
        if p.turntable:  # one revolution: the camera circles the object in base
            rim = float(np.max(np.linalg.norm(np.array(
                [[x, y] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])]) - target[:2],
                axis=1)))
            n = (int(p.sweep_frames) if p.sweep_frames is not None
                 else int(np.ceil(2 * np.pi * rim / p.sweep_spacing)))
            frame_period = int(round(2 * np.pi * rim / n / p.sweep_speed * 1e9))
            omega = 2 * np.pi / (n * frame_period * 1e-9)  # rad/s
            start = 2 * np.pi * k / (n * max(len(plan), 1))  # the sweeps interleaved

            def pose_at(t_ns: int, _s=start, _w=omega, _ts=ts) -> np.ndarray:
                return _turntable_camera(target, p.crossing, p.sweep_elevation_deg,
                                         _s + _w * (int(t_ns) - _ts) * 1e-9)

            def velocity_at(cam: np.ndarray, _w=omega) -> np.ndarray:
                r = cam[:3, 3] - target
                return _w * np.array([-r[1], r[0], 0.0])
        else:
            t_start_cam, direction, length = sweep_poses(
                az, el, target, p.crossing, t_camera_laser, lo, hi, p.sweep_spacing,
                p.sweep_margin, roll_deg=roll)
            if p.sweep_frames is not None:
                n = int(p.sweep_frames)
            else:
                n = int(round(length / p.sweep_spacing)) + 1
            spacing = length / (n - 1) if p.sweep_frames is not None else p.sweep_spacing
            frame_period = int(round(spacing / p.sweep_speed * 1e9))

            def pose_at(t_ns: int, _c=t_start_cam, _d=direction, _ts=ts) -> np.ndarray:
                cam = _c.copy()  # nanoseconds as integers: exact differences
                cam[:3, 3] += _d * p.sweep_speed * (int(t_ns) - _ts) * 1e-9
                return cam

            def velocity_at(cam: np.ndarray, _d=direction) -> np.ndarray:
                return _d * p.sweep_speed
        frame_t = ts + np.arange(n, dtype=np.int64) * frame_period
        # /tf from 40 ms before the first frame to 40 ms after the last, on a grid a
        # third of a period off the frames' (so every image falls between two samples)
        tf_t = np.arange(ts - 40 * ms - tf_period // 3, frame_t[-1] + 40 * ms, tf_period,
                         dtype=np.int64)
        for j, tj in enumerate(frame_t):
            # a late camera clock: the image stamped tj was taken lag_ns later
            cam = pose_at(int(tj) + lag_ns)
            laser_frames.append((int(tj), k, j, cam))
            laser_velocity.append(velocity_at(cam))
        trues = [pose_at(int(tj)) @ t_camera_flange for tj in tf_t]
        if drift:
            frac = (tf_t - tf_t[0]) / max(int(tf_t[-1] - tf_t[0]), 1)
            d_k = random_drift(rng_drift, tuple(np.array(p.drift_mm) * 1e-3), p.drift_deg)
            errs = (sweep_err[k] @ drift_error(d_k, frac)
                    @ pose_err(np.stack([t[:3, 3] for t in trues])))
            mid = errs[len(errs) // 2]
            rel = invert_transform(mid) @ errs
            error_span.append({
                "translation_mm": round(float(np.linalg.norm(rel[:, :3, 3], axis=1).max())
                                        * 1e3, 6),
                "rotation_deg": round(max(float(rotation_angle_deg(r[:3, :3])) for r in rel),
                                      6)})
        else:
            errs = np.broadcast_to(sweep_err[k], (len(tf_t), 4, 4))
        for tj, t_true, e in zip(tf_t, trues, errs, strict=True):
            tf_true.append((int(tj), t_true))
            tf_reported.append((int(tj), _reported(t_true, e, p.turntable)))
        frames_per_sweep.append(n)
        t_next = int(tf_t[-1]) + int(p.sweep_gap_s * 1e9)

    # ---------------------------------------------------------------- events in time order
    events: list[tuple[int, int, int]] = []  # (stamp, priority, index)
    events += [(s, 0, i) for i, (s, _) in enumerate(tf_reported)]
    events += [(int(s), 1, i) for i, s in enumerate(view_stamps)]
    events += [(f[0], 2, i) for i, f in enumerate(laser_frames)]
    events.sort()

    ws_lo = lo - p.workspace_margin
    ws_hi = hi + p.workspace_margin
    ws_lo[2] = p.workspace_floor
    info = {"kind": "scan", "object": object_name, "units": "m"}
    if p.workspace_box:
        info.update({"workspace_min": " ".join(f"{x:.4f}" for x in ws_lo),
                     "workspace_max": " ".join(f"{x:.4f}" for x in ws_hi)})
    model = ("T_base_flange_reported = T_base_flange_true @ E "
             "(E constant per sweep / per view)")
    if p.turntable:
        model = ("T_base_flange_reported = E @ T_base_flange_true (E rigid in base, "
                 "constant per revolution / per view: a turntable)")
    if drift:
        model = ("T_base_flange_reported = T_base_flange_true @ E(t), E(t) = E_k @ D_k(s) "
                 "@ P(x): E_k constant per sweep (sweep_errors), D_k a smooth drift within "
                 "the sweep, P the flange-position-dependent error (robo3d.sim.rig); views: "
                 "E_i @ P(x)")
    sim_meta = {"generator": f"robo3d {__version__} simulate", "object": object_name,
                **p.to_metadata(full=not legacy),
                "sweep_plan_deg": json.dumps([[round(a, 6), round(e, 6), round(r, 6)]
                                              for a, e, r in plan]),
                "frames_per_sweep": json.dumps(frames_per_sweep),
                "sweep_errors": json.dumps(_error_summary(sweep_err)),
                "view_errors": json.dumps(_error_summary(view_err)),
                "robot_error_model": model}
    if drift:
        sim_meta["sweep_error_span"] = json.dumps(error_span)
    order = np.argsort([s for s, _ in tf_true], kind="stable")
    if legacy:
        truth = _legacy_truth(tf_true, order, t0, t_flange_camera, t_flange_laser)
    else:
        truth = _contract_truth(tf_true, order)

    with RecordingWriter(path, message_encoding=message_encoding) as w:
        w.add_metadata("robo3d.recording", info)
        w.add_metadata("robo3d.simulation", sim_meta)
        w.add_attachment("ground_truth/mesh.ply", mesh_to_ply_bytes(mesh), "application/x-ply")
        w.add_attachment("ground_truth/tf.json",
                         json.dumps(truth, separators=(",", ":")).encode(), "application/json")
        if not legacy:
            w.add_attachment(IMAGE_POSES, _image_poses_json(
                view_stamps, view_cams, laser_frames, t_camera_laser, lag_ns),
                "application/json")
        w.write_calibration(_CAL_TOPIC, t0, camera)
        w.write_transforms("/tf_static", t0, [("flange", "camera", t_flange_camera),
                                              ("flange", "laser", t_flange_laser)])
        for stamp, kind, i in events:
            if kind == 0:
                w.write_transforms("/tf", stamp, [("base", "flange", tf_reported[i][1])])
            elif kind == 1:
                if p.turntable:
                    scene.set_room_pose(_room_pose(view_cams[i], target))
                signal, sil = render_view(scene, camera, view_cams[i], return_silhouette=True)
                if vig is not None:
                    signal = signal * vig[..., None]
                img = sensor_noise(signal, np.random.default_rng([p.seed, 10, i]),
                                   p.gain_dn_per_electron, p.view_read_noise_dn, fast_noise)
                w.write_image(_VIEW_TOPIC, stamp, camera.frame_id, img, p.view_encoding,
                              p.jpeg_quality)
                if not legacy:  # the true silhouette, at the pose the image was taken
                    w.add_attachment(f"{SILHOUETTES}{i:03d}.png",
                                     encode_image(sil.astype(np.uint8) * 255, "png"),
                                     "image/png")
            else:
                _, k, j, cam = laser_frames[i]
                if p.turntable:
                    scene.set_room_pose(_room_pose(cam, target))
                    if off_scene is not None:
                        off_scene.set_room_pose(_room_pose(cam, target))
                img = _laser_image(scene, camera, cam, t_camera_laser, p, vig,
                                   np.random.default_rng([p.seed, 11, k, j]), fast_noise,
                                   laser_velocity[i],
                                   speckle=np.random.default_rng([p.seed, 13, k, j]))
                w.write_image(_LASER_TOPIC, stamp, camera.frame_id, img, p.laser_encoding,
                              p.jpeg_quality)
                if p.laser_off:  # the same camera's frame with the laser dark, own noise
                    off = _laser_image(off_scene, camera, cam, t_camera_laser, p, vig,
                                       np.random.default_rng([p.seed, 12, k, j]), fast_noise,
                                       laser_velocity[i])
                    w.write_image(LASER_OFF_TOPIC, stamp + 1_000_000, camera.frame_id, off,
                                  p.laser_encoding, p.jpeg_quality)
    return SimulationResult(path=path, object_name=object_name, n_views=p.views,
                            n_laser_frames=len(laser_frames), frames_per_sweep=frames_per_sweep,
                            sweep_errors=sweep_err, view_errors=view_err,
                            T_flange_camera=t_flange_camera, T_flange_laser=t_flange_laser,
                            size_bytes=path.stat().st_size, seconds=0.0)


def _reported(t_true: np.ndarray, error: np.ndarray, turntable: bool) -> np.ndarray:
    """The reported ``base -> flange`` of a true one with a rig error: a robot's error
    lies in its flange (``T @ E``); a turntable's in ``base`` (``E @ T``: the turntable's
    angle read off by a fraction of a degree, the object nudged on its plate between
    revolutions), which moves a revolution's points rigidly, as a robot's error moves a
    straight sweep's."""
    return error @ t_true if turntable else t_true @ error


def _turntable_camera(target: np.ndarray, distance: float, elevation_deg: float,
                      azimuth: float) -> np.ndarray:
    """``T_base_camera`` of a turntable rig's camera when the turntable has turned by
    ``-azimuth`` radians: at ``distance`` from ``target`` (where the laser's sheet
    crosses the optical axis) at ``elevation_deg``, looking at it, upright (the laser
    beside it, its sheet upright through the turntable's axis)."""
    e = np.radians(elevation_deg)
    eye = np.asarray(target, np.float64) + distance * np.array(
        [np.cos(e) * np.cos(azimuth), np.cos(e) * np.sin(azimuth), np.sin(e)])
    return look_at(eye, target)


def _room_pose(T_base_camera: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``T_base_room`` of a turntable scene: the room (its wall and its light, the
    camera at azimuth 0 in it) turned about the vertical axis through ``target`` by the
    camera's azimuth in ``base``."""
    r = T_base_camera[:3, 3] - target
    a = float(np.arctan2(r[1], r[0]))
    c, s = np.cos(a), np.sin(a)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    T[:2, 3] = target[:2] - T[:2, :2] @ target[:2]
    return T


def _laser_image(scene: SimScene, camera: Any, cam: np.ndarray, t_camera_laser: np.ndarray,
                 p: SimulationParams, vig: np.ndarray | None, rng: np.random.Generator,
                 fast_noise: bool, velocity: np.ndarray | None = None,
                 speckle: np.random.Generator | None = None) -> np.ndarray:
    """One laser frame as the camera records it: rendered at camera pose ``cam``
    (``scene``'s laser; dark for a laser-off frame), its light speckled
    (``p.laser_speckle``, drawn from ``speckle``), row band by row band at the poses
    of their exposure with a rolling shutter (``p.rolling_shutter_ms``, the camera moving
    at ``velocity``), averaged to grey for a monochrome camera, vignetted, with sensor
    noise drawn from ``rng``."""
    gain = (speckle_gain(camera.height, camera.width, p.laser_speckle, p.speckle_grain_px,
                         speckle) if p.laser_speckle > 0 and speckle is not None else None)
    if p.rolling_shutter_ms > 0 and velocity is not None:
        signal = _rolling_signal(scene, camera, cam, t_camera_laser,
                                 p.rolling_shutter_ms * 1e-3, np.asarray(velocity), gain)
    else:
        signal = render_laser_frame(scene, camera, cam, cam @ t_camera_laser, gain)
    if signal.ndim == 3 and p.laser_encoding == "mono8":
        signal = signal.mean(axis=2)  # a monochrome camera: no colour filters
    if vig is not None:
        signal = signal * (vig if signal.ndim == 2 else vig[..., None])
    return sensor_noise(signal, rng, p.gain_dn_per_electron, p.laser_read_noise_dn,
                        fast_noise)


def _rolling_signal(scene: SimScene, camera: Any, cam: np.ndarray, t_camera_laser: np.ndarray,
                    readout_s: float, velocity: np.ndarray,
                    gain: np.ndarray | None = None) -> np.ndarray:
    """A rolling shutter's laser frame: row ``r`` exposed ``r / (H - 1) * readout_s`` after
    the first, the camera (and the laser on its flange) moved on by ``velocity`` times
    that; each band of :data:`ROLLING_BAND_ROWS` rows rendered at its middle row's pose
    through a camera cropped to those rows and one more on each side (the same lens: only
    the principal point's row moves; the room light's edge test sees its neighbours), so
    the frame costs 1.4-1.5 global renders (320 x 240). With no motion it is the global
    shutter's frame."""
    from .camera import CameraModel

    h = camera.height
    bands = []
    for r0 in range(0, h, ROLLING_BAND_ROWS):
        r1 = min(r0 + ROLLING_BAND_ROWS, h)
        a, b = max(r0 - 1, 0), min(r1 + 1, h)  # a row more each side: the edges' test
        K = camera.K.copy()
        K[1, 2] -= a
        crop = CameraModel(camera.frame_id, camera.width, b - a, K, camera.D)
        moved = cam.copy()
        moved[:3, 3] += velocity * readout_s * (0.5 * (r0 + r1 - 1)) / max(h - 1, 1)
        bands.append(render_laser_frame(scene, crop, moved, moved @ t_camera_laser,
                                        None if gain is None else gain[a:b])[r0 - a:r1 - a])
    return np.concatenate(bands, axis=0)


def _legacy_truth(tf_true: list[tuple[int, np.ndarray]], order: np.ndarray, t0: int,
                  t_flange_camera: np.ndarray, t_flange_laser: np.ndarray) -> dict[str, Any]:
    """``ground_truth/tf.json`` in robo3d's first form (the demos keep it, byte for byte)."""
    truth: dict[str, Any] = {"transforms": [{
        "parent": "base", "child": "flange",
        "stamps_ns": [tf_true[i][0] for i in order],
        # nanometre / 1e-12 resolution keeps the JSON short and far below any error
        "translations": [[round(float(x), 9) for x in tf_true[i][1][:3, 3]] for i in order],
        "quaternions": [[round(float(x), 12) for x in matrix_to_quat(tf_true[i][1][:3, :3])]
                        for i in order]}]}
    for child, t_fc in (("camera", t_flange_camera), ("laser", t_flange_laser)):
        # the true mounts (the simulated cell has no hand-eye error: equal to /tf_static)
        truth["transforms"].append({
            "parent": "flange", "child": child, "static": True, "stamps_ns": [t0],
            "translations": [[round(float(x), 9) for x in t_fc[:3, 3]]],
            "quaternions": [[round(float(x), 12) for x in matrix_to_quat(t_fc[:3, :3])]]})
    return truth


def _contract_truth(tf_true: list[tuple[int, np.ndarray]], order: np.ndarray) -> dict[str, Any]:
    """``ground_truth/tf.json`` as ``recording-format.md`` defines it: a
    ``foxglove.FrameTransforms`` message in JSON with the true ``base -> flange`` samples
    (the static mounts carry no error: ``/tf_static`` is their truth)."""
    out = []
    for i in order:
        stamp, t = tf_true[i]
        q = matrix_to_quat(t[:3, :3])
        out.append({"timestamp": {"sec": int(stamp) // 1_000_000_000,
                                  "nsec": int(stamp) % 1_000_000_000},
                    "parent_frame_id": "base", "child_frame_id": "flange",
                    "translation": dict(zip("xyz", (round(float(x), 9) for x in t[:3, 3]),
                                            strict=True)),
                    "rotation": dict(zip("xyzw", (round(float(x), 12) for x in q),
                                         strict=True))})
    return {"transforms": out}


def _image_poses_json(view_stamps: np.ndarray, view_cams: np.ndarray,
                      laser_frames: list[tuple[int, int, int, np.ndarray]],
                      t_camera_laser: np.ndarray, lag_ns: int) -> bytes:
    def flat(t: np.ndarray) -> list[float]:
        return [round(float(x), 12) for x in np.asarray(t).ravel()]

    doc = {"clock_lag_ns": lag_ns,
           _VIEW_TOPIC: [{"index": i, "stamp_ns": int(s), "exposure_ns": int(s) + lag_ns,
                          "T_base_camera": flat(view_cams[i])}
                         for i, s in enumerate(view_stamps)],
           _LASER_TOPIC: [{"index": i, "stamp_ns": s, "exposure_ns": s + lag_ns,
                           "sweep": k, "frame": j, "T_base_camera": flat(cam),
                           "T_base_laser": flat(cam @ t_camera_laser)}
                          for i, (s, k, j, cam) in enumerate(laser_frames)]}
    return json.dumps(doc, separators=(",", ":")).encode()


def write_demos(directory: str | os.PathLike[str], *, threads: int = 1,
                names: list[str] | None = None, missing_only: bool = False
                ) -> list[SimulationResult]:
    """Regenerate the demo recordings (:data:`DEMOS`) into ``directory``.

    Parameters
    ----------
    directory : str or path-like
        Created if missing.
    threads : int
        Ray-casting threads (0: all cores).
    names : list of str, optional
        A subset of :data:`DEMOS` (default: all).
    missing_only : bool
        Only those not already in ``directory`` (the files are deterministic: an
        existing one is what would be written).

    Returns
    -------
    list of SimulationResult
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    todo = names or list(DEMOS)
    bad = [n for n in todo if n not in DEMOS]
    if bad:
        raise ValueError(f"unknown demo(s) {', '.join(bad)}; expected {', '.join(DEMOS)}")
    if missing_only:
        todo = [n for n in todo if not (d / f"{n}.mcap").exists()]
    return [simulate_recording(d / f"{n}.mcap", DEMOS[n][0], threads=threads, demo_format=True,
                               **DEMOS[n][1]) for n in todo]


# --------------------------------------------------------------------------- calibration
def calibration_cell(params: SimulationParams | None = None) -> CalibrationCell:
    """The true cell of a scan simulation, for a calibration recording of it.

    The camera (:func:`robo3d.sim.rig.default_camera` at ``width x height``), hand-eye
    (:func:`~robo3d.sim.rig.default_hand_eye`), laser mount
    (:func:`~robo3d.sim.rig.default_laser_mount` at ``baseline``, ``crossing``),
    appearance, sensor and robot error of ``params`` are exactly those
    :func:`simulate_recording` uses with the same ``params``: a calibration recording
    and a scan recording of one ``SimulationParams`` share the true camera, hand-eye and
    laser sheet.

    Parameters
    ----------
    params : SimulationParams, optional
        Default: :meth:`SimulationParams.cell` (room light, red laser, JPEG 80, a webcam's
        noise).
    """
    p = params or SimulationParams.cell()
    return CalibrationCell(
        camera=default_camera(p.width, p.height), T_flange_camera=default_hand_eye(),
        T_camera_laser=default_laser_mount(p.baseline, p.crossing), appearance=p.appearance,
        view_encoding=p.view_encoding, laser_encoding=p.laser_encoding,
        jpeg_quality=p.jpeg_quality, view_read_noise_dn=p.view_read_noise_dn,
        laser_read_noise_dn=p.laser_read_noise_dn,
        gain_dn_per_electron=p.gain_dn_per_electron, vignetting=p.vignetting,
        view_error_mm=tuple(p.view_error_mm), view_error_deg=tuple(p.view_error_deg),
        robot_error=p.robot_error, pose_error_mm_per_m=p.pose_error_mm_per_m,
        pose_error_deg_per_m=p.pose_error_deg_per_m, start_time_ns=p.start_time_ns)


#: The small calibration session for tests (with :meth:`SimulationParams.cell`'s
#: ``small=True``: 320 x 240).
SMALL_CALIBRATION: dict[str, Any] = dict(views=8, laser_frames=4)


def simulate_calibration(path: str | os.PathLike[str], *, rig: str = "robot",
                         seed: int | None = None, params: SimulationParams | None = None,
                         small: bool = False, threads: int = 1,
                         message_encoding: str = "protobuf",
                         **options: Any) -> CalibrationSimResult:
    """Simulate a calibration recording (``kind=calibration``) of the scan cell.

    See :mod:`robo3d.sim.calibration` for what is recorded, how it is rendered and the
    ``ground_truth/calibration.json`` it carries. To calibrate from one recording and
    scan with another, give both the same ``params``::

        p = SimulationParams.cell(seed=3)
        simulate_calibration("cal.mcap", params=p)         # the truth: calibration.json
        simulate_recording("scan.mcap", "vase", params=p)  # the same camera, hand-eye, laser

    Parameters
    ----------
    path : str or path-like
        The ``.mcap`` file to write (atomically).
    rig : {"robot", "fixed"}
        A robot-carried camera over a static board, or a fixed camera (``base``) and a
        hand-held board (``robo3d.target`` ``moving=true``).
    seed : int, optional
        Seeds every draw of the session (poses, noise, robot and published errors);
        default ``params.seed``.
    params : SimulationParams, optional
        The cell (:func:`calibration_cell`); default :meth:`SimulationParams.cell`
        (``small=True``: its 320 x 240 preset).
    small : bool
        A small session for tests (:data:`SMALL_CALIBRATION`, 320 x 240 when ``params``
        is not given).
    threads : int
        Ray-casting threads of the background (0: all cores).
    message_encoding : {"protobuf", "json"}
    **options
        Any :class:`robo3d.sim.calibration.CalibrationOptions` field (``views``,
        ``laser_frames``, ``board=Checkerboard(...)``, ``defects``, ...).

    Returns
    -------
    CalibrationSimResult
    """
    p = params or SimulationParams.cell(small=small)
    known = {f.name for f in dataclasses.fields(CalibrationOptions)}
    unknown = set(options) - known
    if unknown:
        raise ValueError(f"unknown calibration simulation option(s): "
                         f"{', '.join(sorted(unknown))}")
    kw = {**(SMALL_CALIBRATION if small else {}), **options, "rig": rig}
    for name in ("defects", "distance_m", "nominal_error_mm", "nominal_error_deg",
                 "focal_error"):  # lists from JSON / the CLI -> tuples
        if name in kw:
            kw[name] = tuple(kw[name])
    with _blas_one_thread():
        return write_calibration_recording(path, calibration_cell(p), CalibrationOptions(**kw),
                                           seed=p.seed if seed is None else int(seed),
                                           threads=threads, message_encoding=message_encoding)
