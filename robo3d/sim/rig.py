"""Geometry of the simulated cell: camera, hand-eye, laser mount, robot paths and errors.

Frames follow ``recording-format.md``: ``base`` (the object and table are static in it,
the table is the plane ``z = 0``), ``flange`` (moves), ``camera`` (optical) and ``laser``
(the sheet is its x-z plane, the beam leaves along +z).

Choices
-------
- The camera is designed first (where it looks), and the flange pose follows from the
  hand-eye: ``T_base_flange = T_base_camera @ inv(T_flange_camera)``.
- The laser sits ``baseline`` metres from the camera along the camera's ``-y`` axis
  (above it in the image), its x axis along the camera's x, and its beam tilted so the
  sheet crosses the optical axis at ``crossing`` metres; a small extra rotation keeps
  the mount from being perfectly aligned (as a real one is not).
- A sweep is a straight, constant-velocity move of the camera along the sheet's normal,
  its orientation fixed, long enough for the sheet to pass over the object's bounding
  box with a margin.
- Robot error is a constant rigid transform ``E`` per sweep (or per view), applied in
  the flange frame: ``T_base_flange_reported = T_base_flange_true @ E``. Its translation
  and rotation magnitudes are drawn uniformly from the given ranges, along uniformly
  random directions/axes.
- The ``drift`` model (issue 10: an error the per-sweep rigid alignment does not
  assume) multiplies two more factors onto it: ``E(t) = E_k @ D_k(s) @ P(x)``.
  ``D_k(s)`` drifts smoothly within sweep ``k`` (``s`` in [0, 1] from its first to its
  last ``/tf`` sample): a ramp ``a (2 s - 1) u`` plus a wave ``b sin(2 pi f s + phi) w``
  of its translation and likewise of its rotation vector (``a``, ``b`` each half of a
  magnitude drawn from the range, ``f`` 0.5-1.5 cycles per sweep). ``P(x)`` depends on
  where the flange is (a stand-in for the joint configuration, as a robot's kinematic
  errors do): translation ``G (x - x_ref)`` and rotation vector ``H (x - x_ref)`` with
  random matrices of spectral norm ``mm_per_m`` and ``deg_per_m``, ``x_ref`` the
  object's centre; the views get ``P`` too.
"""

from __future__ import annotations

import numpy as np

from ..camera import CameraModel
from ..transforms import euler_to_matrix, invert_transform, make_transform

__all__ = [
    "default_camera",
    "default_hand_eye",
    "default_laser_mount",
    "look_at",
    "view_poses",
    "sweep_poses",
    "random_rigid_error",
    "rotation_about_axis",
    "PoseDependentError",
    "random_drift",
    "drift_error",
]


def default_camera(width: int = 640, height: int = 480, frame_id: str = "camera") -> CameraModel:
    """The simulated camera: ``fx ~ fy ~ 900 px`` at 640 x 480 (scaled with the width, so
    smaller images keep the field of view), principal point a few pixels off-centre,
    plumb_bob ``k1 = -0.08, k2 = 0.05, p1 = 7e-4, p2 = -5e-4``.

    Parameters
    ----------
    width, height : int
        Image size, pixels.
    frame_id : str
        The camera's optical frame.
    """
    if width < 16 or height < 16:
        raise ValueError(f"image must be at least 16 x 16 pixels, got {width} x {height}")
    s = width / 640.0
    k = np.array([[900.0 * s, 0.0, (width - 1) / 2.0 + 3.7 * s],
                  [0.0, 902.0 * s, (height - 1) / 2.0 - 2.6 * s],
                  [0.0, 0.0, 1.0]])
    return CameraModel(frame_id, int(width), int(height), k,
                       np.array([-0.08, 0.05, 7e-4, -5e-4, 0.0]))


def default_hand_eye() -> np.ndarray:
    """``T_flange_camera`` (4, 4): the camera 71 mm from the flange, looking along the
    flange's z axis, turned 90 degrees about it and tilted by a few degrees."""
    r = euler_to_matrix("zxy", np.radians([90.0, 4.0, -3.0]))
    return make_transform(r, np.array([0.045, 0.004, 0.055]))


def default_laser_mount(baseline: float = 0.08, crossing: float = 0.27) -> np.ndarray:
    """``T_camera_laser`` (4, 4): the laser ``baseline`` metres along the camera's ``-y``,
    its sheet spanning the camera's x direction and crossing the optical axis at
    ``crossing`` metres (then turned by 0.4 degrees about its beam and 0.3 degrees about
    its x axis, a slightly imperfect mount).

    Parameters
    ----------
    baseline : float, metres
        Camera-to-laser distance (70-90 mm in the designed cell).
    crossing : float, metres
        Depth at which the sheet crosses the optical axis (about the working distance).
    """
    if baseline <= 0 or crossing <= 0:
        raise ValueError(f"baseline and crossing must be > 0 m, got {baseline}, {crossing}")
    origin = np.array([0.0015, -baseline, -0.002])
    z = np.array([0.0, 0.0, crossing]) - origin
    z /= np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0])
    x = x - z * (x @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z], axis=1) @ euler_to_matrix("zx", np.radians([0.4, 0.3]))
    return make_transform(r, origin)


def look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0,
            up: np.ndarray | None = None) -> np.ndarray:
    """``T_base_camera`` (4, 4) of an optical camera at ``eye`` looking at ``target``.

    The image's "up" (``-y``) is as close as possible to ``up`` (base +z by default, or
    base +y when looking straight down), then the camera is rolled by ``roll`` radians
    about its optical axis.

    Parameters
    ----------
    eye, target : (3,) float64, metres
    roll : float, radians
    up : (3,) float64, optional
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    n = np.linalg.norm(z)
    if n < 1e-9:
        raise ValueError("eye and target coincide")
    z /= n
    up_ = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    x = np.cross(z, up_)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z], axis=1) @ euler_to_matrix("z", [roll])
    return make_transform(r, eye)


def rotation_about_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix (3, 3) of ``angle`` radians about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def view_poses(n_views: int, target: np.ndarray, distance: float,
               elevations_deg: tuple[float, ...], rng: np.random.Generator,
               jitter: float = 1.0) -> np.ndarray:
    """Camera poses of the silhouette views: rings of equal-azimuth views at a few
    elevations, looking at ``target``, staggered between rings.

    Parameters
    ----------
    n_views : int
        Number of views, spread as evenly as possible over the rings.
    target : (3,) float64, metres
        The point looked at (the object's centre).
    distance : float, metres
        Camera-to-target distance.
    elevations_deg : tuple of float, degrees
        One ring per elevation.
    rng : numpy Generator
        For small random perturbations (azimuth +-3 deg, elevation +-2 deg, distance
        +-3 %, roll +-4 deg, aim +-3 mm), each scaled by ``jitter``.
    jitter : float
        0 for exact rings.

    Returns
    -------
    (n_views, 4, 4) float64
        ``T_base_camera`` of each view.
    """
    if n_views < 1:
        raise ValueError(f"n_views must be >= 1, got {n_views}")
    rings = len(elevations_deg)
    counts = np.full(rings, n_views // rings)
    counts[: n_views % rings] += 1
    poses = []
    for k, (el, cnt) in enumerate(zip(elevations_deg, counts, strict=True)):
        for j in range(int(cnt)):
            az = 2 * np.pi * (j + 0.5 * (k % 2) + 0.17 * k) / max(int(cnt), 1)
            dj = rng.uniform(-1, 1, 6) * jitter
            a = az + np.radians(3.0) * dj[0]
            e = np.radians(el + 2.0 * dj[1])
            d = distance * (1 + 0.03 * dj[2])
            eye = np.asarray(target) + d * np.array([np.cos(e) * np.cos(a),
                                                     np.cos(e) * np.sin(a), np.sin(e)])
            aim = np.asarray(target) + 0.003 * np.array([dj[3], dj[4], 0.0])
            poses.append(look_at(eye, aim, roll=np.radians(4.0) * dj[5]))
    return np.stack(poses)


def sweep_poses(azimuth_deg: float, elevation_deg: float, target: np.ndarray,
                crossing: float, T_camera_laser: np.ndarray, box_lo: np.ndarray,
                box_hi: np.ndarray, spacing: float, margin: float = 0.006,
                roll_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The straight sweep of one laser pass over the object.

    The centre pose looks at ``target`` from ``crossing`` metres (so the sheet passes
    through the target there); the camera then moves along the sheet's normal so the
    sheet covers the box ``[box_lo, box_hi]`` with ``margin`` on both sides.

    Parameters
    ----------
    azimuth_deg, elevation_deg : float, degrees
        Direction from the target to the camera.
    target : (3,) float64, metres
    crossing : float, metres
        Distance at which the sheet crosses the optical axis.
    T_camera_laser : (4, 4) float64
    box_lo, box_hi : (3,) float64, metres
        The object's bounding box in ``base``.
    spacing : float, metres
        Camera travel between two frames.
    margin : float, metres
    roll_deg : float, degrees
        Turn of the camera (and the laser with it) about its optical axis: 0 puts the
        laser above the camera (the sheet spans the image's width), 90 beside it (the
        sheet upright, sweeping sideways: at low elevation the laser then sees as far
        down the object's sides as the camera does).

    Returns
    -------
    T_start : (4, 4) float64
        ``T_base_camera`` at the first frame.
    direction : (3,) float64
        Unit direction of travel in ``base`` (the sheet normal).
    length : float
        Travel from the first to the last frame, metres (a multiple of ``spacing``).
    """
    if spacing <= 0:
        raise ValueError(f"sweep spacing must be > 0 m, got {spacing}")
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    target = np.asarray(target, dtype=np.float64)
    eye = target + crossing * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    up = None
    if elevation_deg > 89.0:  # from above: image up along the azimuth's horizontal direction
        up = -np.array([np.cos(a), np.sin(a), 0.0])
    t_centre = look_at(eye, target, roll=np.radians(roll_deg), up=up)
    t_base_laser = t_centre @ T_camera_laser
    normal = t_base_laser[:3, 1]
    # signed offsets of the box corners from the sheet at the centre pose
    corners = np.array([[x, y, z] for x in (box_lo[0], box_hi[0]) for y in (box_lo[1], box_hi[1])
                        for z in (box_lo[2], box_hi[2])])
    off = (corners - t_base_laser[:3, 3]) @ normal
    s0, s1 = off.min() - margin, off.max() + margin
    n = int(np.ceil((s1 - s0) / spacing))
    t_start = t_centre.copy()
    t_start[:3, 3] += s0 * normal
    return t_start, normal, n * spacing


def random_rigid_error(rng: np.random.Generator, translation_range: tuple[float, float],
                       rotation_range_deg: tuple[float, float]) -> np.ndarray:
    """A random rigid transform (4, 4) of bounded size.

    Parameters
    ----------
    rng : numpy Generator
    translation_range : (lo, hi), metres
        Magnitude of the translation, uniform in the range; direction uniform.
    rotation_range_deg : (lo, hi), degrees
        Angle of the rotation, uniform in the range; axis uniform.
    """
    t_dir = rng.normal(size=3)
    t_dir /= np.linalg.norm(t_dir)
    r_axis = rng.normal(size=3)
    r_axis /= np.linalg.norm(r_axis)
    t_mag = rng.uniform(*translation_range)
    angle = np.radians(rng.uniform(*rotation_range_deg))
    return make_transform(rotation_about_axis(r_axis, angle), t_dir * t_mag)


def _flange_from_camera(T_base_camera: np.ndarray, T_flange_camera: np.ndarray) -> np.ndarray:
    return np.asarray(T_base_camera) @ invert_transform(T_flange_camera)


def _exp_se3(rotvec: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` rigid transforms from rotation vectors and translations ``(N, 3)``."""
    rv = np.atleast_2d(np.asarray(rotvec, dtype=np.float64))
    tr = np.atleast_2d(np.asarray(translation, dtype=np.float64))
    theta = np.linalg.norm(rv, axis=1)
    axis = rv / np.where(theta > 0, theta, 1.0)[:, None]
    k = np.zeros((len(rv), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = axis[:, 2], -axis[:, 1], axis[:, 0]
    s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    out = np.tile(np.eye(4), (len(rv), 1, 1))
    out[:, :3, :3] = np.eye(3) + s * k + (1 - c) * (k @ k)
    out[:, :3, 3] = tr
    return out


class PoseDependentError:
    """A robot error that depends on where the flange is: ``P(x)``, see the module notes.

    Parameters
    ----------
    rng : numpy Generator
    mm_per_m, deg_per_m : float
        Spectral norms of the translation and rotation gradients.
    reference : (3,) float64, metres
        Where the error is zero (the object's centre).
    """

    def __init__(self, rng: np.random.Generator, mm_per_m: float, deg_per_m: float,
                 reference: np.ndarray) -> None:
        def gradient(scale: float) -> np.ndarray:
            m = rng.normal(size=(3, 3))
            return scale * m / np.linalg.norm(m, 2)

        self.G = gradient(mm_per_m * 1e-3)
        self.H = gradient(np.radians(deg_per_m))
        self.reference = np.asarray(reference, dtype=np.float64)

    def __call__(self, positions: np.ndarray) -> np.ndarray:
        """``(N, 4, 4)`` error at flange positions ``(N, 3)`` (metres, in ``base``)."""
        d = np.atleast_2d(np.asarray(positions, dtype=np.float64)) - self.reference
        return _exp_se3(d @ self.H.T, d @ self.G.T)


def random_drift(rng: np.random.Generator, translation_range: tuple[float, float],
                 rotation_range_deg: tuple[float, float]) -> dict[str, np.ndarray]:
    """The random parameters of one sweep's drift ``D_k(s)`` (see the module notes).

    Parameters
    ----------
    rng : numpy Generator
    translation_range : (lo, hi), metres
    rotation_range_deg : (lo, hi), degrees
    """
    def unit() -> np.ndarray:
        v = rng.normal(size=3)
        return v / np.linalg.norm(v)

    out = {}
    for name, (lo, hi), scale in (("t", translation_range, 1.0),
                                  ("r", rotation_range_deg, np.pi / 180)):
        out[f"{name}_ramp"] = 0.5 * scale * rng.uniform(lo, hi) * unit()
        out[f"{name}_wave"] = 0.5 * scale * rng.uniform(lo, hi) * unit()
    out["freq"] = np.array(rng.uniform(0.5, 1.5))
    out["phase"] = np.array(rng.uniform(0.0, 2 * np.pi))
    return out


def drift_error(drift: dict[str, np.ndarray], s: np.ndarray) -> np.ndarray:
    """``(N, 4, 4)`` drift ``D_k(s)`` at sweep fractions ``s`` ``(N,)`` in [0, 1]."""
    s = np.atleast_1d(np.asarray(s, dtype=np.float64))[:, None]
    wave = np.sin(2 * np.pi * drift["freq"] * s + drift["phase"])
    return _exp_se3(drift["r_ramp"] * (2 * s - 1) + drift["r_wave"] * wave,
                    drift["t_ramp"] * (2 * s - 1) + drift["t_wave"] * wave)
