"""Laser triangulation: stripe pixels to 3D points, and per-sweep point clouds.

Implements the seed's §4.1 (eqs. 9–17), generalised to a calibrated camera with lens
distortion, and assembles the profiles of one sweep into a cloud in ``base`` with
normals and lines of sight.

The laser sheet
---------------
The sheet is the **x–z plane (y = 0) of the ``laser`` frame**, the beam leaving along
+z (the recording contract). The seed's text says "(x, y) plane", but its eq. 12 points
``p = (0, 0, 0)``, ``q = (1, 0, 0)``, ``r = (0, 0, 1)`` lie in the x–z plane; we follow
the contract and the equation. In the camera frame the plane is ``n · x = d`` with
``n`` the laser's +y axis and ``d = n · t`` (``t`` the laser origin in the camera frame);
:func:`laser_plane_in_camera` computes it through the seed's determinants (eqs. 13–15),
whose cross product ``(q - p) × (r - p) = x_L × z_L = -y_L``, and flips the sign so that
``n = +y_L``.

How we read eq. 11
------------------
The seed lists the motions that carry the camera frame onto the laser frame, all about
the *camera's* (fixed) axes and in this order: translate by Δx along x_c, Δy along y_c,
Δz along z_c, then rotate by φ about z_c, θ about y_c, ψ about x_c. Motions about fixed
axes compose by pre-multiplication, so the pose of the laser in the camera is the product
written in eq. 11, read right to left::

    T_camera_laser = Rx(ψ) · Ry(θ) · Rz(φ) · Tz(Δz) · Ty(Δy) · Tx(Δx)

i.e. ``R = Rx(ψ) Ry(θ) Rz(φ)`` and ``t = R (Δx, Δy, Δz)``: since the translations come
first, the rotations also swing the laser origin (it is *not* at ``(Δx, Δy, Δz)`` unless
the angles are zero). This matrix maps laser coordinates to camera coordinates, as every
``T_P_C`` of robo3d does. The seed's eq. 13 multiplies the laser points by the *inverse*
of ``[cT1]``, which would be right only if ``[cT1]`` mapped camera to laser coordinates;
that contradicts the listed order of the motions, so we follow the motions and the
contract: ``p_camera = T_camera_laser · p_laser``.
:func:`laser_params_from_transform` is the exact inverse of
:func:`laser_transform_from_params` (away from θ = ±90°).

Triangulation (eqs. 16–17)
--------------------------
The seed intersects the pinhole ray ``(x, y, z) = ((u - u0) δx t, (v - v0) δy t, f t)``
with the plane (eq. 17). We use the same ray–plane intersection on the ray through the
*undistorted* pixel (``CameraModel.rays``), ``x = t · ray`` with ``t = d / (n · ray)``;
:func:`triangulate_pixels_eq17` keeps the seed's own form (on undistorted ideal pixels)
as a check. Points are dropped, and counted (:data:`DROP_REASONS`), when the pixel is
not finite, when the ray meets the sheet at less than ``min_angle_deg`` (nearly parallel:
the depth error grows as ``1 / sin`` of that angle, and at 0 there is no intersection),
when the intersection is behind the camera (``t <= 0``), or outside
``[min_range, max_range]`` (distance from the camera centre, metres);
:func:`triangulate_sweep` also drops and counts the points outside the workspace box.

The undistortion and the intersection run in one compiled kernel (Numba, ``nogil``,
cached on disk) over all the pixels of a sweep: the same fixed-point inverse of plumb_bob
as :meth:`CameraModel.undistort_normalized` (20 iterations at most, stopping when the
update falls below 1e-15), equal to ``CameraModel.rays`` to 1e-12.

Sweep clouds
------------
A sweep is a run of laser frames without a time gap longer than ``sweep_gap``
(:func:`split_sweeps`; where that leaves sweeps of one or two frames, a stop-and-go
cell's, longer than three times the frames' median interval as well).
:func:`triangulate_sweep` maps each frame's profile into ``base`` with that frame's
camera pose, crops to the workspace box grown by ``workspace_margin_m`` (the reported
poses' error moves points across its faces; the align stage crops to the exact box once
the sweep is corrected), and gives each point a normal from the sweep's own structure:
the profiles form an organised grid (frame × image line), and the normal is the cross
product of the along-profile tangent (neighbouring lines ``±normal_span`` of the same
frame) and the across-profile tangent (the same line in the neighbouring frames), as for
organised range images. A tangent is the central difference where both neighbours exist,
else the second-order one-sided difference ``(-3 P0 + 4 P1 - P2) / 2`` (no chord bias at
the first and last profile of a sweep or the ends of a profile on a curved surface),
else the first-order one. The normals, oriented toward the camera, are then averaged
over ``(2 normal_smooth + 1)²`` grid cells taken in mirrored pairs only, so that the
average adds no first-order bias on a curved surface (what this gains is recorded in
``benchmarks/README.md``). A neighbour further than ``normal_jump`` times the sweep's
median spacing is a depth jump, not a neighbour. Points without both tangents (isolated
points, holes) get a PCA normal of their k nearest neighbours instead (Hoppe et al.);
every normal is oriented toward the camera centre of its frame.

The confidence of a point is the stripe confidence times a geometric factor
``min(1, sin α / sin 15°)``, α being the angle between the ray and the sheet.

References
----------
.. [1] The seed chapter, "Robot assisted 3D shape acquisition by optical systems",
   §4.1, eqs. 9–17.
.. [2] H. Hoppe et al., "Surface reconstruction from unorganized points", SIGGRAPH 1992
   (PCA normals oriented toward the sensor).
.. [3] B. Curless and M. Levoy, "A volumetric method for building complex models from
   range images", SIGGRAPH 1996 (lines of sight kept with each range sample).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from .artefacts import SweepCloud
from .camera import CameraModel
from .checks import check_transform
from .errors import StageError
from .options import Options
from .stripes import StripePoints
from .transforms import euler_to_matrix, matrix_to_quat, quat_slerp, quat_to_matrix

__all__ = [
    "DROP_REASONS",
    "TriangulateOptions",
    "laser_transform_from_params",
    "laser_params_from_transform",
    "laser_plane_in_camera",
    "laser_pose_from_plane",
    "six_parameters_from_pose",
    "sheet_in_workspace",
    "sheet_roi_mask",
    "triangulate_pixels",
    "triangulate_pixels_eq17",
    "rows_poses",
    "split_sweeps",
    "triangulate_sweep",
]

log = logging.getLogger(__name__)

#: Reasons a stripe pixel yields no point, as counted by :func:`triangulate_pixels`
#: (each pixel counted once, under the first reason that applies).
DROP_REASONS: tuple[str, ...] = ("non_finite", "grazing", "behind", "out_of_range")

_CONF_REF_ANGLE_DEG = 15.0


@dataclass(frozen=True)
class TriangulateOptions(Options):
    """The parameters of :func:`triangulate_sweep` (config section ``triangulation``;
    ``crop_to_workspace`` and ``laser_params`` are the stage's: they choose its inputs).

    Attributes
    ----------
    min_angle_deg : float, degrees
        Rays meeting the sheet at a smaller angle are dropped (``grazing``).
    min_range_m, max_range_m : float, metres
        Accepted distance of a point from the camera centre.
    normal_span : int
        Lines between the neighbours of the along-profile tangent (central difference
        over ``±normal_span`` lines, falling back to ``±1``).
    normal_smooth : int
        The grid normals are averaged over ``(2 normal_smooth + 1)^2`` neighbouring
        grid cells (frames x lines), 0 for none.
    normal_jump : float
        A neighbour further than ``normal_jump`` times the sweep's median spacing is a
        depth jump, not a neighbour.
    normal_knn : int
        Neighbours of the PCA fallback normal.
    workspace_margin_m : float, metres
        The crop box is the workspace box grown by this on every side: the sweep is
        placed with the robot's reported poses, whose error moves the object's points
        across the box's faces (its foot, next to the floor, below it). The points in the
        margin are kept and counted (``report["n_in_margin"]``); alignment leaves them
        out of the registration and crops to the exact box once the sweep is corrected.
    """

    section = "triangulation"
    min_angle_deg: float = 2.0
    min_range_m: float = 0.02
    max_range_m: float = 2.0
    normal_span: int = 2
    normal_smooth: int = 2
    normal_jump: float = 5.0
    normal_knn: int = 12
    workspace_margin_m: float = 0.002


# ---------------------------------------------------------------------------- eq. 11
def _rot(axis: str, a: float) -> np.ndarray:
    return euler_to_matrix(axis, [a])


def laser_transform_from_params(
    dx: float, dy: float, dz: float, phi: float, theta: float, psi: float
) -> np.ndarray:
    """Pose of the laser in the camera from the seed's six parameters (eq. 11).

    ``T_camera_laser = Rx(psi) Ry(theta) Rz(phi) Tz(dz) Ty(dy) Tx(dx)``: translations
    along the camera's x, y, z first, then rotations about the camera's z, y, x (see
    the module docstring for how we read the seed's product).

    Parameters
    ----------
    dx, dy, dz : float, metres
        Translations along the camera's x, y, z axes.
    phi, theta, psi : float, radians
        Rotations about the camera's z, y, x axes, applied in that order.

    Returns
    -------
    (4, 4) float64
        ``T_camera_laser``, mapping laser coordinates to camera coordinates.

    References
    ----------
    .. [1] The seed chapter, §4.1, eq. 11.
    """
    vals = np.array([dx, dy, dz, phi, theta, psi], dtype=np.float64)
    if not np.all(np.isfinite(vals)):
        raise ValueError(f"laser parameters must be finite, got {vals.tolist()}")
    r = _rot("x", psi) @ _rot("y", theta) @ _rot("z", phi)
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = r @ vals[:3]
    return t


def laser_params_from_transform(T_camera_laser: np.ndarray) -> tuple[float, ...]:
    """The seed's eq. 11 parameters of a laser pose: inverse of
    :func:`laser_transform_from_params`.

    Parameters
    ----------
    T_camera_laser : (4, 4) float64
        Pose of the laser in the camera.

    Returns
    -------
    (dx, dy, dz, phi, theta, psi) : floats, metres and radians
        ``theta`` in [-pi/2, pi/2]; at ``theta = ±pi/2`` (gimbal lock) ``phi`` is set
        to 0.
    """
    t = check_transform(T_camera_laser, "T_camera_laser")
    r = t[:3, :3]
    # R = Rx(psi) Ry(theta) Rz(phi): R[0] = (c_t c_p, -c_t s_p, s_t)
    theta = float(np.arctan2(r[0, 2], np.hypot(r[0, 0], r[0, 1])))
    if np.hypot(r[0, 0], r[0, 1]) > 1e-9:
        phi = float(np.arctan2(-r[0, 1], r[0, 0]))
        psi = float(np.arctan2(-r[1, 2], r[2, 2]))
    else:
        phi = 0.0
        psi = float(np.arctan2(r[2, 1], r[1, 1]))
    d = r.T @ t[:3, 3]
    return float(d[0]), float(d[1]), float(d[2]), phi, theta, psi


# ---------------------------------------------------------------------------- eq. 12-15
def laser_plane_in_camera(T_camera_laser: np.ndarray) -> tuple[np.ndarray, float]:
    """The laser sheet as a plane ``n · x = d`` in the camera frame (seed eqs. 12–15).

    The sheet is the laser frame's x–z plane; its points ``p = (0,0,0)``,
    ``q = (1,0,0)``, ``r = (0,0,1)`` (eq. 12) are mapped to the camera (eq. 13, with
    ``T_camera_laser`` rather than the seed's inverse, see the module docstring) and
    the plane's coefficients are the seed's 2x2 determinants ``(Mx, -My, Mz)`` (eq. 15),
    i.e. ``(q - p) × (r - p)``. We return the unit normal with the sign flipped so that
    ``n`` is the laser's +y axis.

    Parameters
    ----------
    T_camera_laser : (4, 4) float64
        Pose of the laser in the camera.

    Returns
    -------
    normal : (3,) float64
        Unit normal of the sheet in the camera frame (the laser's +y axis).
    d : float, metres
        Signed distance of the plane from the camera centre along ``normal``.

    References
    ----------
    .. [1] The seed chapter, §4.1, eqs. 12–15.
    """
    t = check_transform(T_camera_laser, "T_camera_laser")
    pts_l = np.array([[0.0, 0, 0, 1], [1.0, 0, 0, 1], [0.0, 0, 1, 1]])
    p, q, r = (pts_l @ t.T)[:, :3]
    a, b = q - p, r - p
    m_x = a[1] * b[2] - a[2] * b[1]
    m_y = a[0] * b[2] - a[2] * b[0]
    m_z = a[0] * b[1] - a[1] * b[0]
    n = -np.array([m_x, -m_y, m_z])  # eq. 15 coefficients, flipped to +y_L
    n /= np.linalg.norm(n)
    return n, float(n @ p)


def laser_pose_from_plane(normal: np.ndarray, offset_m: float,
                          reference: np.ndarray | None = None) -> np.ndarray:
    """A laser pose whose sheet is the plane ``normal · x = offset_m`` of the camera
    frame: the inverse of :func:`laser_plane_in_camera`, up to what a plane leaves free.

    A plane fixes three of the pose's six degrees of freedom (the direction of the
    laser's +y axis and the sheet's distance from the camera centre); the laser's
    rotation within the sheet and its origin's position in it are not seen by the
    triangulation (every point of the sheet triangulates alike). We fix them so:

    * without ``reference`` (the canonical pose): ``+y_L = ±normal`` with the sign that
      makes the offset non-negative (the normal points from the camera centre towards
      the sheet); ``+z_L`` (the beam) is the camera's +z projected onto the sheet (its
      +y when the sheet is nearly perpendicular to the optical axis, i.e. the
      projection is shorter than 0.1); ``x_L = y_L × z_L``; the origin is the foot of
      the perpendicular from the camera centre, ``offset · y_L``;
    * with ``reference`` (e.g. the recording's nominal ``T_camera_laser``): ``+y_L``
      takes the sign of the reference's y axis, ``+z_L`` is the reference's z axis
      projected onto the sheet, and the origin is the reference's origin projected
      onto the sheet, so that only what the plane measures changes.

    Parameters
    ----------
    normal : (3,) float64
        The sheet's normal in the camera frame (any length but zero).
    offset_m : float, metres
        The plane's offset along ``normal`` (``normal · x = offset_m``, after
        ``normal`` is made unit length).
    reference : (4, 4) float64, optional
        A laser pose whose in-plane choices to keep.

    Returns
    -------
    (4, 4) float64
        ``T_camera_laser`` with ``laser_plane_in_camera(T) == (±normal, ±offset)``.
    """
    n = np.asarray(normal, dtype=np.float64).reshape(-1)
    nn = float(np.linalg.norm(n)) if n.shape == (3,) else 0.0
    if not (nn > 0 and np.isfinite(nn) and np.isfinite(offset_m)):
        raise ValueError(f"normal must be a finite non-zero (3,) vector and offset_m finite, "
                         f"got {np.asarray(normal).tolist()} and {offset_m}")
    n, d = n / nn, float(offset_m) / nn
    if reference is None:
        if d < 0 or (d == 0 and n[np.argmax(np.abs(n))] < 0):
            n, d = -n, -d
        z = np.array([0.0, 0.0, 1.0]) - n[2] * n
        if np.linalg.norm(z) < 0.1:
            z = np.array([0.0, 1.0, 0.0]) - n[1] * n
        origin = d * n
    else:
        ref = check_transform(reference, "reference")
        if n @ ref[:3, 1] < 0:
            n, d = -n, -d
        z = ref[:3, 2] - (ref[:3, 2] @ n) * n
        if np.linalg.norm(z) < 0.1:  # the reference's beam along the normal: its x instead
            x_ref = ref[:3, 0] - (ref[:3, 0] @ n) * n
            z = np.cross(x_ref, n)
        origin = ref[:3, 3] - (ref[:3, 3] @ n - d) * n
    z /= np.linalg.norm(z)
    x = np.cross(n, z)
    t = np.eye(4)
    t[:3, 0], t[:3, 1], t[:3, 2], t[:3, 3] = x, n, z, origin
    return t


def six_parameters_from_pose(T_camera_laser: np.ndarray, *,
                             canonical: bool = False) -> dict[str, float]:
    """The seed's six laser parameters (eq. 11) of a laser pose, as a dict.

    The inverse of :func:`laser_transform_from_params` (through
    :func:`laser_params_from_transform`): ``laser_transform_from_params(**p)`` with
    ``p`` the first six entries gives ``T_camera_laser`` back (away from θ = ±90°).
    A sheet fitted to points fixes only its plane; with ``canonical=True`` the pose is
    first replaced by the canonical pose of its sheet (:func:`laser_pose_from_plane`
    without reference: origin at the foot of the perpendicular from the camera centre,
    beam along the camera's +z projected onto the sheet), so that the parameters depend
    on the plane alone.

    Parameters
    ----------
    T_camera_laser : (4, 4) float64
        Pose of the laser in the camera.
    canonical : bool
        Use the canonical pose of the sheet instead of ``T_camera_laser`` itself.

    Returns
    -------
    dict
        ``dx, dy, dz`` (metres), ``phi, theta, psi`` (radians) as in
        :func:`laser_transform_from_params`, and the angles again in degrees as
        ``phi_deg, theta_deg, psi_deg``.

    References
    ----------
    .. [1] The seed chapter, §4.1, eq. 11.
    """
    t = check_transform(T_camera_laser, "T_camera_laser")
    if canonical:
        t = laser_pose_from_plane(*laser_plane_in_camera(t))
    dx, dy, dz, phi, theta, psi = laser_params_from_transform(t)
    out = {"dx": dx, "dy": dy, "dz": dz, "phi": phi, "theta": theta, "psi": psi}
    out.update({f"{k}_deg": float(np.degrees(out[k])) for k in ("phi", "theta", "psi")})
    return out


def _planes(T_camera_laser: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (F, 3) = laser +y axes and offsets (F,) of a batch of laser poses."""
    n = T_camera_laser[:, :3, 1]
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    d = np.einsum("fi,fi->f", n, T_camera_laser[:, :3, 3])
    return n, d


# ---------------------------------------------------------------------------- sheet ROI
_BOX_EDGES = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7],
                       [0, 4], [1, 5], [2, 6], [3, 7]])


def sheet_in_workspace(T_base_camera: np.ndarray, T_camera_laser: np.ndarray,
                       workspace: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """The part of the laser sheet inside the workspace box, in the camera frame.

    The sheet (the laser frame's x-z plane) meets the axis-aligned box (in ``base``) in
    a convex polygon: the points where the box's 12 edges cross the plane, ordered by
    angle about their centroid in the sheet's (x, z) coordinates. A stripe pixel outside
    its projection cannot triangulate into the box.

    Parameters
    ----------
    T_base_camera, T_camera_laser : (4, 4) float64
        The camera's pose in ``base`` and the laser's in the camera, at the frame.
    workspace : (min (3,), max (3,)) metres, in ``base``

    Returns
    -------
    (M, 3) float64, metres
        The polygon's vertices in the camera frame, in order (M = 0 when the sheet
        misses the box, 3 to 6 otherwise).
    """
    lo, hi = (np.asarray(w, dtype=np.float64).reshape(3) for w in workspace)
    idx = (np.arange(8)[:, None] >> np.arange(3)) & 1  # corner i: bit k picks max on axis k
    corners = np.where(idx == 1, hi, lo)  # (8, 3) base
    T_cl = np.asarray(T_camera_laser, dtype=np.float64)
    T_bl = np.asarray(T_base_camera, dtype=np.float64) @ T_cl
    # the corners in the laser frame: p_l = R^T (p_b - t)
    c_l = (corners - T_bl[:3, 3]) @ T_bl[:3, :3]
    y = c_l[:, 1]
    ya, yb = y[_BOX_EDGES[:, 0]], y[_BOX_EDGES[:, 1]]
    cross = (ya * yb <= 0) & (ya != yb)
    t = ya[cross] / (ya[cross] - yb[cross])
    a, b = c_l[_BOX_EDGES[cross, 0]], c_l[_BOX_EDGES[cross, 1]]
    pts = a + t[:, None] * (b - a)
    if len(pts) < 3:
        return np.zeros((0, 3))
    xz = pts[:, [0, 2]]
    ang = np.arctan2(*(xz - xz.mean(axis=0)).T[::-1])
    pts = pts[np.argsort(ang)]
    pts[:, 1] = 0.0
    return pts @ T_cl[:3, :3].T + T_cl[:3, 3]


def epipolar_axis(camera: CameraModel, T_camera_laser: np.ndarray, max_deg: float
                  ) -> tuple[str | None, float]:
    """The scan axis the laser's geometry gives: ``"columns"`` (one centre per image
    column) where the laser's epipolar lines run within ``max_deg`` of the image's
    columns everywhere in the image, ``"rows"`` where they run within it of the rows, else
    None; and the largest angle between an epipolar line and that axis's lines (degrees).

    Every ray of the laser sheet lights one point, the first surface it meets, and its
    image lies on the ray's image: a line through the image of the laser's origin (the
    epipole). So the stripe crosses each epipolar line once, and depth moves it along
    them; lines of pixels that run along them each hold at most one point of the stripe,
    whatever the surface. A bright line that runs along them (a printed pattern's edge or
    gap, the object's rim) cannot be the stripe. The direction at pixel ``p`` is
    ``p O_z - (K O)_xy`` with ``O`` the laser's origin in the camera frame (pinhole: the
    lens distortion bends it by a few degrees at most, inside the margin); it is sampled
    on a 5 x 5 grid over the image. A laser whose origin is the camera's centre has no
    epipolar lines (None).
    """
    if not max_deg > 0:
        return None, float("nan")
    O = np.asarray(T_camera_laser, dtype=np.float64)[:3, 3]
    if not np.all(np.isfinite(O)) or np.linalg.norm(O) < 1e-6:
        return None, float("nan")
    K = np.asarray(camera.K, dtype=np.float64)
    u, v = np.meshgrid(np.linspace(0, camera.width - 1, 5), np.linspace(0, camera.height - 1, 5))
    p = np.stack([u.ravel(), v.ravel()], axis=1)
    d = p * O[2] - (K @ O)[:2]
    n = np.linalg.norm(d, axis=1)
    if np.any(n < 1e-9 * max(camera.width, camera.height)):  # the epipole in the image
        return None, float("nan")
    from_cols = np.degrees(np.arctan2(np.abs(d[:, 0]), np.abs(d[:, 1])))  # 0: vertical
    worst_cols, worst_rows = float(from_cols.max()), float((90.0 - from_cols).max())
    if worst_cols <= max_deg:
        return "columns", worst_cols
    if worst_rows <= max_deg:
        return "rows", worst_rows
    return None, min(worst_cols, worst_rows)


def _clip_near(P: np.ndarray, near: float) -> np.ndarray:
    """A polygon (N, 3) of the camera frame clipped to ``z >= near`` (Sutherland-Hodgman
    against one plane, a handful of vertices). A polygon wholly in front, the usual
    case, is returned as it is: the clip would give back the same vertices in the same
    order (60 us of small numpy calls per frame)."""
    z = P[:, 2] - near
    if np.all(z >= 0):
        return P
    nx = (np.arange(len(P)) + 1) % len(P)
    Q, zq = P[nx], z[nx]
    keep = P[z >= 0]
    sel = (z >= 0) != (zq >= 0)
    tt = z[sel] / (z[sel] - zq[sel])
    cut = P[sel] + tt[:, None] * (Q[sel] - P[sel])
    order = np.concatenate([np.flatnonzero(z >= 0) * 2.0, np.flatnonzero(sel) * 2.0 + 1.0])
    return np.concatenate([keep, cut])[np.argsort(order, kind="stable")]


def sheet_roi_mask(camera: CameraModel, polygon_cam: np.ndarray, margin_px: float,
                   near: float = 1e-3) -> np.ndarray | None:
    """The image region where a convex polygon of the camera frame (the sheet inside the
    workspace, :func:`sheet_in_workspace`) projects, grown by ``margin_px``.

    The polygon is clipped to ``z >= near``, projected through the pinhole, clipped
    to the undistorted image (grown by a quarter on each side: the distortion
    polynomial is not trusted far outside it), its boundary sampled every ~1/32 of
    each edge, distorted to pixels (:meth:`~robo3d.camera.CameraModel.project`), and
    the convex hull of the samples, offset by ``margin_px`` in 8 directions, filled
    with ``cv2.fillConvexPoly``. A few dozen points per frame, one polygon fill.

    Returns
    -------
    (H, W) bool or None
        The region (all False when the polygon does not reach the image); None when
        ``polygon_cam`` is empty (no region: the caller searches the whole image).
    """
    import cv2

    P = np.asarray(polygon_cam, dtype=np.float64).reshape(-1, 3)
    H, W = int(camera.height), int(camera.width)
    mask = np.zeros((H, W), np.uint8)
    if len(P) < 3:
        return None
    P = _clip_near(P, near)
    if len(P) < 3:
        return mask.view(bool)
    xy = P[:, :2] / P[:, 2:3]
    # clip to the (grown) undistorted image: a convex intersection in the normalized plane
    box = _undistorted_extent(camera)
    inter_area, inter = cv2.intersectConvexConvex(xy.astype(np.float32), box)
    if inter is None or inter_area <= 0 or len(inter) < 3:
        return mask.view(bool)
    xy = inter.reshape(-1, 2).astype(np.float64)
    nxt = xy[(np.arange(len(xy)) + 1) % len(xy)]
    dense = (xy[:, None, :] + _EDGE_STEPS[None, :, None] * (nxt - xy)[:, None, :]).reshape(-1, 2)
    uv = camera.normalized_to_pixels(camera.distort_normalized(dense)).astype(np.float32)
    uv = cv2.convexHull(uv).reshape(-1, 2)
    if margin_px > 0:
        uv = cv2.convexHull((uv[:, None, :] + float(margin_px) * _RING[None]).reshape(-1, 2))
    lim = 4.0 * max(H, W)
    hull = np.clip(np.rint(uv.reshape(-1, 2) * 16), -16 * lim, 16 * lim).astype(np.int32)
    cv2.fillConvexPoly(mask, hull, 1, lineType=cv2.LINE_8, shift=4)
    return mask.view(bool)


def _undistorted_extent(camera: CameraModel) -> np.ndarray:
    """The undistorted normalized image's bounding box, grown by a quarter on each side,
    as a (4, 2) float32 convex polygon (cached per camera model)."""
    key = (camera.width, camera.height, tuple(np.ravel(camera.K)), tuple(np.ravel(camera.D)))
    box = _EXTENT_CACHE.get(key)
    if box is None:
        W, H = camera.width, camera.height
        t = np.linspace(0.0, 1.0, 33)
        border = np.concatenate([
            np.column_stack([t * (W - 1), np.zeros_like(t)]),
            np.column_stack([t * (W - 1), np.full_like(t, H - 1)]),
            np.column_stack([np.zeros_like(t), t * (H - 1)]),
            np.column_stack([np.full_like(t, W - 1), t * (H - 1)])])
        xy = camera.undistort_normalized(camera.pixels_to_normalized(border))
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        g = 0.25 * (hi - lo)
        lo, hi = lo - g, hi + g
        box = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]],
                       np.float32)
        _EXTENT_CACHE[key] = box
    return box


_EXTENT_CACHE: dict = {}
_EDGE_STEPS = np.linspace(0.0, 1.0, 24, endpoint=False)
_RING = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [0.7071, 0.7071], [0.7071, -0.7071],
                  [-0.7071, 0.7071], [-0.7071, -0.7071]], np.float32)


# ---------------------------------------------------------------------------- eq. 16-17
#: Pixels undistorted together by :func:`_ray_plane_kernel` (see there).
_BLOCK = 8


@njit(inline="always")
def _undistort_block(uv, b0, m, kpar, dist, has_dist, x0, y0, x, y, ok, run):  # noqa: ANN001, ANN202
    """Normalised undistorted coordinates (x, y) of the pixels ``b0 .. b0 + m - 1`` of
    uv, by the fixed-point inverse of plumb_bob as CameraModel's (stop after 20 steps or
    when a step moves neither coordinate by more than 1e-15); ``ok``: the pixel is
    finite (a non-finite one is not iterated). The pixels iterate in lockstep, each with
    its own operations and its own stop (``run``), hence the same values as one pixel at
    a time; but a pixel's step no longer waits for its previous step's division: the
    block's independent steps overlap (2.6x faster on stripe centres)."""
    fx, fy, cx, cy, skew = kpar[0], kpar[1], kpar[2], kpar[3], kpar[4]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    n_run = 0
    for j in range(m):
        u = uv[b0 + j, 0]
        v = uv[b0 + j, 1]
        ok[j] = np.isfinite(u) and np.isfinite(v)
        run[j] = ok[j] and has_dist
        n_run += 1 if run[j] else 0
        y0[j] = (v - cy) / fy
        x0[j] = (u - cx - skew * y0[j]) / fx
        x[j] = x0[j]
        y[j] = y0[j]
    it = 0
    while n_run > 0 and it < 20:
        it += 1
        for j in range(m):
            if not run[j]:
                continue
            xj = x[j]
            yj = y[j]
            r2 = xj * xj + yj * yj
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2.0 * p1 * xj * yj + p2 * (r2 + 2.0 * xj * xj)
            dy = p1 * (r2 + 2.0 * yj * yj) + 2.0 * p2 * xj * yj
            inv = 1.0 / radial
            xn = (x0[j] - dx) * inv
            yn = (y0[j] - dy) * inv
            x[j] = xn
            y[j] = yn
            if abs(xn - xj) <= 1e-15 and abs(yn - yj) <= 1e-15:
                run[j] = False
                n_run -= 1


@njit(nogil=True, cache=True)
def _ray_plane_kernel(uv, plane_of, normals, offsets, kpar, dist, has_dist, min_sin,
                      min_range, max_range):  # noqa: ANN001, ANN202 - numba kernel
    """Undistort each pixel (:func:`_undistort_block`, ``_BLOCK`` pixels at a time),
    intersect its unit ray with its plane; status per pixel: 0 kept, 1 non_finite,
    2 grazing, 3 behind, 4 out_of_range (DROP_REASONS order)."""
    n = uv.shape[0]
    pts = np.full((n, 3), np.nan)
    status = np.zeros(n, np.int8)
    sin_a = np.zeros(n)
    x0 = np.zeros(_BLOCK)
    y0 = np.zeros(_BLOCK)
    xs = np.zeros(_BLOCK)
    ys = np.zeros(_BLOCK)
    ok = np.zeros(_BLOCK, np.bool_)
    run = np.zeros(_BLOCK, np.bool_)
    for b0 in range(0, n, _BLOCK):
        m = min(_BLOCK, n - b0)
        _undistort_block(uv, b0, m, kpar, dist, has_dist, x0, y0, xs, ys, ok, run)
        for j in range(m):
            i = b0 + j
            if not ok[j]:
                status[i] = 1
                continue
            x = xs[j]
            y = ys[j]
            norm = np.sqrt(x * x + y * y + 1.0)
            rx = x / norm
            ry = y / norm
            rz = 1.0 / norm
            k = plane_of[i]
            den = rx * normals[k, 0] + ry * normals[k, 1] + rz * normals[k, 2]
            sa = abs(den)
            sin_a[i] = sa
            if not (sa >= min_sin):
                status[i] = 2
                continue
            t = offsets[k] / den
            if not (t > 0):
                status[i] = 3
                continue
            if not (t >= min_range and t <= max_range):
                status[i] = 4
                continue
            pts[i, 0] = t * rx
            pts[i, 1] = t * ry
            pts[i, 2] = t * rz
    return pts, status, sin_a


#: What :func:`_camera_params` and :func:`_sheet_of` last computed, by the bytes of their
#: input: a caller triangulating frame after frame passes the same camera and laser pose
#: again and again (each a few microseconds of numpy per frame otherwise). Emptied when
#: it holds 64 entries.
_PARAMS_CACHE: dict[bytes, tuple] = {}


def _cached(key: bytes, make):  # noqa: ANN001, ANN202
    """``_PARAMS_CACHE[key]``, made by ``make()`` the first time. Its arrays are shared
    by every caller and only read (by the kernel); they are left writeable, as numba
    would compile the kernel again for read-only arrays."""
    hit = _PARAMS_CACHE.get(key)
    if hit is None:
        if len(_PARAMS_CACHE) >= 64:
            _PARAMS_CACHE.clear()
        hit = make()
        _PARAMS_CACHE[key] = hit
    return hit


def _camera_params(camera: CameraModel) -> tuple[np.ndarray, np.ndarray, bool]:
    """The kernel's intrinsics ``(fx, fy, cx, cy, skew)``, plumb_bob ``D[:5]`` and
    whether there is distortion, of a camera (cached by K and D)."""
    K, D = np.asarray(camera.K), np.asarray(camera.D)
    return _cached(b"K" + K.tobytes() + D.tobytes(), lambda: (
        np.array([camera.fx, camera.fy, camera.cx, camera.cy, camera.K[0, 1]]),
        np.ascontiguousarray(D[:5], dtype=np.float64), camera.has_distortion))


def _sheet_of(T_camera_laser: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`laser_plane_in_camera` of a checked (4, 4) float64 pose as the kernel
    takes it: normals (1, 3) and offsets (1,) (cached by the pose's bytes)."""
    def make() -> tuple[np.ndarray, np.ndarray]:
        n, d = laser_plane_in_camera(T_camera_laser)
        return n[None], np.array([d])

    return _cached(b"T" + T_camera_laser.tobytes(), make)


def _intersect(
    uv: np.ndarray, camera: CameraModel, plane_of: np.ndarray, normals: np.ndarray,
    offsets: np.ndarray, min_angle_deg: float, min_range: float, max_range: float,
) -> tuple[np.ndarray, np.ndarray, dict[str, int], np.ndarray]:
    """Rays through the (distorted) pixels uv (N, 2) meet the planes normals (F, 3),
    offsets (F,) (pixel i meets plane plane_of[i]): points (N, 3) in the camera, kept
    (N,), counts of the dropped by reason, |sin| of the ray-sheet angle (N,)."""
    kpar, dist, has_dist = _camera_params(camera)
    pts, status, sin_a = _ray_plane_kernel(
        np.ascontiguousarray(uv, dtype=np.float64), np.ascontiguousarray(plane_of, np.int64),
        np.ascontiguousarray(normals, dtype=np.float64),
        np.ascontiguousarray(offsets, dtype=np.float64), kpar, dist, has_dist,
        float(np.sin(np.radians(min_angle_deg))), float(min_range), float(max_range))
    counts = np.bincount(status, minlength=len(DROP_REASONS) + 1)
    dropped = {name: int(counts[i + 1]) for i, name in enumerate(DROP_REASONS)}
    return pts, status == 0, dropped, sin_a


def _check_pixels(pixels_uv: np.ndarray) -> np.ndarray:
    uv = np.asarray(pixels_uv, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"pixels_uv must be (N, 2) float (u, v), got shape {uv.shape}")
    return uv


def _check_ranges(min_angle_deg: float, min_range: float, max_range: float) -> None:
    if not (0.0 <= min_angle_deg < 90.0):
        raise ValueError(f"min_angle_deg must be in [0, 90), got {min_angle_deg}")
    if not (0.0 <= min_range < max_range):
        raise ValueError(f"need 0 <= min_range < max_range, got {min_range}, {max_range}")


def triangulate_pixels(
    pixels_uv: np.ndarray,
    camera: CameraModel,
    T_camera_laser: np.ndarray,
    *,
    min_angle_deg: float = 2.0,
    min_range: float = 0.0,
    max_range: float = np.inf,
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Intersect the rays through stripe pixels with the laser sheet (seed eqs. 16–17).

    Parameters
    ----------
    pixels_uv : (N, 2) float64, pixels
        Stripe centres ``(u, v)`` in the (distorted) image.
    camera : CameraModel
        Intrinsics; the rays go through the undistorted pixels.
    T_camera_laser : (4, 4) float64
        Pose of the laser in the camera.
    min_angle_deg : float, degrees
        Rays meeting the sheet at a smaller angle are dropped (``grazing``).
    min_range, max_range : float, metres
        Accepted distance of the point from the camera centre.

    Returns
    -------
    points_cam : (N, 3) float64, metres
        Points in the camera frame, row for row with ``pixels_uv``; NaN where dropped.
    keep : (N,) bool
        True where a point was made.
    dropped : dict of str to int
        Dropped pixels by reason (keys :data:`DROP_REASONS`), each counted once.

    References
    ----------
    .. [1] The seed chapter, §4.1, eqs. 16–17.
    """
    uv = _check_pixels(pixels_uv)
    t = check_transform(T_camera_laser, "T_camera_laser")
    _check_ranges(min_angle_deg, min_range, max_range)
    normals, offsets = _sheet_of(t)
    pts, keep, dropped, _ = _intersect(uv, camera, np.zeros(len(uv), np.int64), normals,
                                       offsets, min_angle_deg, min_range, max_range)
    return pts, keep, dropped


def triangulate_pixels_eq17(
    pixels_uv: np.ndarray, camera: CameraModel, T_camera_laser: np.ndarray
) -> np.ndarray:
    """The seed's eq. 17 as written, on undistorted ideal pixels; no filtering.

    With the seed's pinhole (focal length ``f``, pixel pitch ``δx, δy``) we take
    ``f = 1`` and ``δx = 1 / fx``, ``δy = 1 / fy``; the pixels are first undistorted to
    the ideal pinhole pixel ``(u0 + fx x, v0 + fy y)`` (skew ignored, as in eq. 9).
    ``p`` and ``Mx, My, Mz`` are those of eqs. 13–15 (with ``T_camera_laser``).
    Kept as the reference form that :func:`triangulate_pixels` must agree with.

    Parameters
    ----------
    pixels_uv : (N, 2) float64, pixels
    camera : CameraModel
    T_camera_laser : (4, 4) float64

    Returns
    -------
    points_cam : (N, 3) float64, metres
        ``inf``/NaN where the ray is parallel to the sheet.

    References
    ----------
    .. [1] The seed chapter, §4.1, eqs. 9–17.
    """
    uv = _check_pixels(pixels_uv)
    t = check_transform(T_camera_laser, "T_camera_laser")
    xy = camera.undistort_normalized(camera.pixels_to_normalized(uv))
    u0, v0, f = camera.cx, camera.cy, 1.0
    dx, dy = 1.0 / camera.fx, 1.0 / camera.fy
    u = u0 + camera.fx * xy[:, 0]
    v = v0 + camera.fy * xy[:, 1]
    pts_l = np.array([[0.0, 0, 0, 1], [1.0, 0, 0, 1], [0.0, 0, 1, 1]])
    p, q, r = (pts_l @ t.T)[:, :3]
    m_x = (q[1] - p[1]) * (r[2] - p[2]) - (q[2] - p[2]) * (r[1] - p[1])
    m_y = (q[0] - p[0]) * (r[2] - p[2]) - (q[2] - p[2]) * (r[0] - p[0])
    m_z = (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])
    num = p[0] * m_x - p[1] * m_y + p[2] * m_z
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = num / ((u - u0) * dx * m_x - (v - v0) * dy * m_y + f * m_z)
    return np.stack([(u - u0) * dx * tt, (v - v0) * dy * tt, f * tt], axis=-1)


# ---------------------------------------------------------------------------- sweeps
#: with the time gap alone, sweeps shorter than this (median, frames) mean a cell whose
#: frames come slower than the gap: :func:`split_sweeps` then splits by the frame interval
MIN_SWEEP_FRAMES = 3


def split_sweeps(stamps_ns: np.ndarray, gap_ns: int, intervals: float = 0.0) -> np.ndarray:
    """Sweep index of each laser frame: a time gap longer than ``gap_ns`` starts a sweep
    (the recording contract). With ``intervals`` > 0, where that leaves most sweeps
    shorter than :data:`MIN_SWEEP_FRAMES` frames (median), a gap must be longer than
    ``intervals`` times the median interval between consecutive frames as well.

    Why: a stop-and-go cell that stops the robot for each laser frame records one every
    second or two, and by the time gap alone every frame was a sweep of its own: a blob
    recorded at one frame per 1.5 s, two sweeps of 30 frames 10 s apart, became 60
    one-frame sweeps, from which no range surface could be made (the mesh 0 % measured).
    A recording whose sweeps the gap alone splits into runs of three frames or more is
    split as the contract says (a slow camera, 0.7 s a frame, whose sweeps are 2 s
    apart: two sweeps, where the interval's test alone would merge them).

    Parameters
    ----------
    stamps_ns : (N,) int64, nanoseconds
        Frame timestamps, in any order (sweeps follow time order).
    gap_ns : int, nanoseconds
        The config's ``timing.sweep_gap_s``; must be positive.
    intervals : float
        The config's ``timing.sweep_gap_intervals`` (0: the time gap alone).

    Returns
    -------
    (N,) int64
        0, 1, 2, ... in time order, row for row with ``stamps_ns``.
    """
    stamps = np.asarray(stamps_ns)
    if stamps.ndim != 1 or not (np.issubdtype(stamps.dtype, np.integer) or stamps.size == 0):
        raise ValueError(f"stamps_ns must be (N,) integer nanoseconds, got shape "
                         f"{stamps.shape} {stamps.dtype}")
    if not gap_ns > 0:
        raise ValueError(f"gap_ns must be positive, got {gap_ns}")
    if not intervals >= 0:
        raise ValueError(f"intervals must be >= 0, got {intervals}")
    stamps = stamps.astype(np.int64)
    order = np.argsort(stamps, kind="stable")
    s = stamps[order]
    d = np.diff(s)
    new = np.zeros(s.size, dtype=np.int64)
    new[1:] = (d > gap_ns).astype(np.int64)
    if intervals > 0 and len(d):
        sizes = np.diff(np.flatnonzero(np.r_[1, new[1:], 1]))
        if np.median(sizes) < MIN_SWEEP_FRAMES:  # frames slower than the gap: by interval
            limit = max(float(gap_ns), float(intervals) * float(np.median(d)))
            new[1:] = (d > limit).astype(np.int64)
    out = np.zeros(s.size, dtype=np.int64)
    out[order] = np.cumsum(new)
    return out


def rows_poses(T_start: np.ndarray, T_end: np.ndarray, frame: np.ndarray,
               fraction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A rolling shutter's pose of each point: between its frame's ``T_start`` (first row)
    and ``T_end`` (last row), at ``fraction`` (its row over the last row's, clipped to
    [0, 1]); interpolated as the recording's poses are between two ``/tf`` samples
    (translation linear, rotation by :func:`robo3d.transforms.quat_slerp`). Returns
    ((N, 3, 3) rotations, (N, 3) origins)."""
    f = np.clip(np.asarray(fraction, dtype=np.float64), 0.0, 1.0)
    q0, q1 = matrix_to_quat(T_start[:, :3, :3]), matrix_to_quat(T_end[:, :3, :3])
    R = quat_to_matrix(quat_slerp(q0[frame], q1[frame], f))
    origin = T_start[frame, :3, 3] + f[:, None] * (T_end[frame, :3, 3] - T_start[frame, :3, 3])
    return R, origin


def _unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(v, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / n[..., None], n


def _tangent(P: np.ndarray, idx0: np.ndarray, m1: np.ndarray, p1: np.ndarray,
             m2: np.ndarray, p2: np.ndarray, max_step: float) -> np.ndarray:
    """Tangent from neighbour indices at one and two steps (-1 = missing): the central
    difference where both sides exist, else the second-order one-sided difference
    ``-3 P0 + 4 P1 - P2`` where two neighbours on one side exist (no chord bias on a
    curved surface), else the first-order one; NaN without any neighbour."""
    p0 = P[idx0]

    def _nb(idx: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        ok = idx >= 0
        q = np.where(ok[:, None], P[np.maximum(idx, 0)], np.nan)
        ok &= np.linalg.norm(q - p0, axis=1) <= reach
        return q, ok

    qm1, okm1 = _nb(m1, max_step)
    qp1, okp1 = _nb(p1, max_step)
    qm2, okm2 = _nb(m2, 2.0 * max_step)
    qp2, okp2 = _nb(p2, 2.0 * max_step)
    okm2 &= okm1
    okp2 &= okp1
    tan = np.full_like(p0, np.nan)
    cases = [
        (okm1 & okp1, lambda: (qp1 - qm1) / 2.0),
        (okp2, lambda: (-3.0 * p0 + 4.0 * qp1 - qp2) / 2.0),
        (okm2, lambda: (3.0 * p0 - 4.0 * qm1 + qm2) / 2.0),
        (okp1, lambda: qp1 - p0),
        (okm1, lambda: p0 - qm1),
    ]
    done = np.zeros(len(p0), dtype=bool)
    for sel, value in cases:
        sel = sel & ~done
        if sel.any():
            tan[sel] = value()[sel]
            done |= sel
    return tan


def _median_step(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    ok = (a >= 0) & (b >= 0)
    if not ok.any():
        return np.inf
    return float(np.median(np.linalg.norm(P[a[ok]] - P[b[ok]], axis=1)))


def _grid_normals(P: np.ndarray, O: np.ndarray, frame_pos: np.ndarray, line: np.ndarray,
                  frame_axis: np.ndarray, span: int, smooth: int, jump: float,
                  at: np.ndarray | None = None) -> np.ndarray:
    """Normals from the organised (frame x line) structure, oriented toward ``O``,
    averaged over a (2 smooth + 1)^2 grid neighbourhood; NaN where not available. With
    ``at`` ((N,) bool) only those points are averaged (the others are NaN): every point
    still lends its own normal to its neighbours'."""
    n_pts = len(P)
    n_f = int(frame_pos.max()) + 1
    lmin = int(line.min())
    li = line - lmin
    n_l = int(li.max()) + 1
    pf, pl = max(2, smooth), max(2 * span, smooth)  # padding
    grid = np.full((n_f + 2 * pf, n_l + 2 * pl), -1, dtype=np.int64)
    fr, lc = frame_pos + pf, li + pl
    grid[fr, lc] = np.arange(n_pts)
    idx0 = np.arange(n_pts)

    def _along(k: int) -> np.ndarray:
        nb = grid[fr, lc + k * span]
        if span > 1:  # fall back to the nearest lines where the wide span is missing
            nb = np.where(nb >= 0, nb, grid[fr, lc + k])
        return nb

    # frames searched along different image axes are not neighbours line for line
    ax_pad = np.concatenate([np.full(pf, -1), frame_axis, np.full(pf, -1)])

    def _across(df: int) -> np.ndarray:
        return np.where(ax_pad[fr + df] == ax_pad[fr], grid[fr + df, lc], -1)

    along = {k: _along(k) for k in (-2, -1, 1, 2)}
    across = {k: _across(k) for k in (-2, -1, 1, 2)}
    step_a = _median_step(P, along[1], idx0) / max(span, 1)
    step_c = _median_step(P, across[1], idx0)
    t_a = _tangent(P, idx0, along[-1], along[1], along[-2], along[2], jump * step_a * span)
    t_c = _tangent(P, idx0, across[-1], across[1], across[-2], across[2], jump * step_c)
    cr = np.cross(t_a, t_c)
    nrm, size = _unit(cr)
    la = np.linalg.norm(t_a, axis=1)
    lc_ = np.linalg.norm(t_c, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        sin_ac = size / (la * lc_)
    bad = ~(sin_ac > 0.05)  # NaN (missing tangent) or near-parallel tangents
    nrm[bad] = np.nan
    flip = np.einsum("ni,ni->n", nrm, O - P) < 0
    nrm[flip] *= -1.0
    if smooth <= 0:
        if at is not None:
            nrm[~np.asarray(at, dtype=bool)] = np.nan
        return nrm
    # average over the grid neighbourhood, in mirrored pairs of cells only, so that on a
    # curved surface the first-order bias cancels (a profile at the end of the sweep is
    # averaged along itself, not toward its one neighbour); the loop is over the stencil
    sel = slice(None) if at is None else np.flatnonzero(at)
    own, fs, ls, ps = nrm[sel], fr[sel], lc[sel], P[sel]
    acc = np.where(np.isfinite(own), own, 0.0)
    reach = jump * smooth * max(step_a, step_c if np.isfinite(step_c) else 0.0)

    def _cell(df: int, dl: int) -> tuple[np.ndarray, np.ndarray]:
        nb = grid[fs + df, ls + dl]
        if df:
            nb = np.where(ax_pad[fs + df] == ax_pad[fs], nb, -1)
        j = np.maximum(nb, 0)
        ok = (nb >= 0) & np.all(np.isfinite(nrm[j]), axis=1)
        ok &= np.linalg.norm(P[j] - ps, axis=1) <= reach
        return j, ok

    for df in range(0, smooth + 1):
        for dl in range(-smooth, smooth + 1):
            if df == 0 and dl <= 0:
                continue  # each mirrored pair once, the centre already in
            j1, ok1 = _cell(df, dl)
            j2, ok2 = _cell(-df, -dl)
            pair = ok1 & ok2
            acc += np.where(pair[:, None], nrm[j1] + nrm[j2], 0.0)
    part = _unit(acc)[0]
    part[~np.all(np.isfinite(own), axis=1)] = np.nan  # no own grid normal: fall back
    if at is None:
        return part
    out = np.full_like(nrm, np.nan)
    out[sel] = part
    return out


def _knn_normals(P: np.ndarray, k: int, at: np.ndarray | None = None) -> np.ndarray:
    """PCA normals of the k nearest neighbours among ``P`` (Hoppe et al. 1992),
    unoriented, of the points ``P[at]`` (``at``: indices or a mask; default every
    point): only where the profile grid gave none, which on a dense scan are few, so the
    neighbours and eigenvectors of the others are not computed for nothing."""
    from scipy.spatial import cKDTree

    k = int(min(k, len(P)))
    Q = P if at is None else P[at]
    _, idx = cKDTree(P).query(Q, k=k)
    idx = idx.reshape(len(Q), k)
    nb = P[idx] - P[idx].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, evecs = np.linalg.eigh(cov)
    return evecs[:, :, 0]


def _check_sweep_inputs(F: int, T_base_camera: np.ndarray, T_camera_laser: np.ndarray,
                        frame_indices: np.ndarray | None,
                        workspace: tuple[np.ndarray, np.ndarray] | None,
                        options: TriangulateOptions):
    """The sweep's poses (F, 4, 4) each, frame indices (F,) and workspace box (or None),
    checked against its ``F`` frames."""
    tb = check_transform(T_base_camera, "T_base_camera", batch=True)
    if tb.ndim == 2:
        tb = tb[None]
    if tb.shape[0] != F:
        raise ValueError(f"T_base_camera must be (F, 4, 4) with F={F} frames, got "
                         f"{tb.shape}")
    tl = check_transform(T_camera_laser, "T_camera_laser", batch=True)
    if tl.ndim == 2:
        tl = np.broadcast_to(tl, (F, 4, 4))
    if tl.shape[0] != F:
        raise ValueError(f"T_camera_laser must be (4, 4) or (F, 4, 4) with F={F}, got "
                         f"{tl.shape}")
    if frame_indices is None:
        fidx = np.arange(F, dtype=np.int64)
    else:
        fidx = np.asarray(frame_indices, dtype=np.int64).reshape(-1)
        if fidx.size != F:
            raise ValueError(f"frame_indices must have F={F} entries, got {fidx.size}")
    _check_ranges(options.min_angle_deg, options.min_range_m, options.max_range_m)
    if not float(options.workspace_margin_m) >= 0:
        raise ValueError(f"workspace_margin_m must be >= 0, got {options.workspace_margin_m}")
    box = None
    if workspace is not None:
        box_min = np.asarray(workspace[0], dtype=np.float64).reshape(-1)
        box_max = np.asarray(workspace[1], dtype=np.float64).reshape(-1)
        if box_min.shape != (3,) or box_max.shape != (3,) or np.any(box_min >= box_max):
            raise ValueError(f"workspace must be (box_min (3,), box_max (3,)) with "
                             f"box_min < box_max, got {box_min} and {box_max}")
        box = (box_min, box_max)
    return tb, tl, fidx, box


def _sweep_pixels(stripes: Sequence[StripePoints]):
    """The stripe centres of a sweep's frames, concatenated: counts per frame (F,),
    frame position (N,), pixels (N, 2), image line (N,), confidence (N,), each frame's
    search axis (F,: 0 columns, 1 rows), the centres' skew (N,) and faint flags (N,)."""
    counts = np.array([len(s) for s in stripes], dtype=np.int64)
    frame_pos = np.repeat(np.arange(len(stripes)), counts)
    any_pixel = bool(counts.sum())
    uv = np.concatenate([s.pixels_uv for s in stripes]) if any_pixel else np.zeros((0, 2))
    line = (np.concatenate([s.line for s in stripes]) if any_pixel
            else np.zeros(0, np.int64))
    conf = np.concatenate([s.confidence for s in stripes]) if any_pixel else np.zeros(0)
    frame_axis = np.array([0 if s.axis == "columns" else 1 for s in stripes])
    skew = np.concatenate([s.skew_px for s in stripes]) if any_pixel else np.zeros(0)
    faint = (np.concatenate([s.faint for s in stripes]) if any_pixel
             else np.zeros(0, np.bool_))
    return counts, frame_pos, uv, line, conf, frame_axis, skew, faint


def _sweep_normals(P: np.ndarray, O: np.ndarray, fpos: np.ndarray, line: np.ndarray,
                   frame_axis: np.ndarray, options: TriangulateOptions,
                   at: np.ndarray | None = None) -> tuple[np.ndarray, dict[str, int]]:
    """Unit normals of a sweep's points, oriented toward their camera centres ``O``:
    from the profile grid where it has both tangents, else PCA of the ``normal_knn``
    nearest points, else facing the camera; and how many came from each. With ``at``
    ((N,) bool) only those points' normals (the others NaN, not counted), each from all
    the points around it."""
    normals = _grid_normals(P, O, fpos, line, frame_axis, max(1, int(options.normal_span)),
                            max(0, int(options.normal_smooth)), float(options.normal_jump),
                            at)
    asked = np.ones(len(P), dtype=bool) if at is None else np.asarray(at, dtype=bool)
    need = ~np.all(np.isfinite(normals), axis=1) & asked
    n_grid = int(asked.sum() - need.sum())
    n_knn = 0
    if need.any() and len(P) >= 3:
        normals[need] = _knn_normals(P, options.normal_knn, need)
        n_knn = int(need.sum())
        need[:] = False
    if need.any():  # fewer than 3 points: face the camera
        normals[need] = _unit(O[need] - P[need])[0]
    n_view = int(asked.sum() - n_grid - n_knn)
    flip = np.einsum("ni,ni->n", normals, O - P) < 0
    normals[flip] *= -1.0
    return _unit(normals)[0], {"from_grid": n_grid, "from_knn": n_knn, "from_view": n_view}


def triangulate_sweep(
    stripes: Sequence[StripePoints],
    camera: CameraModel,
    T_base_camera: np.ndarray,
    T_camera_laser: np.ndarray,
    *,
    workspace: tuple[np.ndarray, np.ndarray] | None = None,
    frame_indices: np.ndarray | None = None,
    sweep: int = 0,
    options: TriangulateOptions = TriangulateOptions(),
    T_base_camera_end: np.ndarray | None = None,
) -> SweepCloud:
    """Triangulate the stripe profiles of one sweep into a cloud in ``base``.

    Parameters
    ----------
    stripes : sequence of F StripePoints
        The stripe centres of the sweep's frames, in time order.
    camera : CameraModel
        Intrinsics of the camera that saw the stripes.
    T_base_camera : (F, 4, 4) float64
        Camera pose at each frame.
    T_camera_laser : (4, 4) or (F, 4, 4) float64
        Pose of the laser in the camera (fixed, or per frame).
    workspace : ((3,), (3,)) float64, metres, optional
        ``(box_min, box_max)`` in ``base``; points outside it grown by
        ``options.workspace_margin_m`` are dropped and counted, those in the margin kept
        and counted.
    frame_indices : (F,) int, optional
        Index of each frame in the recording (default ``0 .. F-1``), kept per point.
    sweep : int
        The sweep's index, stored in the cloud.
    options : TriangulateOptions
        The ``triangulation`` section's parameters (:class:`TriangulateOptions`).
    T_base_camera_end : (F, 4, 4) float64, optional
        A rolling shutter: the camera pose when each frame's last row was exposed
        (``T_base_camera`` being the first row's). Each point then takes the pose of its
        row, interpolated (translation linearly, rotation along the geodesic) at
        ``v / (H - 1)``, ``v`` the sensor's row (``StripePoints.v_sensor`` where set):
        the camera and the laser move together, so the point is right
        in the camera and only its place in ``base`` moves (:func:`rows_poses`).

    Returns
    -------
    SweepCloud
        Points, normals oriented toward the camera, frame index, confidence, camera
        centres and a report of what was kept and dropped.

    Raises
    ------
    StageError
        When the sweep yields no point at all (with the counts of what was dropped).
    """
    F = len(stripes)
    if F == 0:
        raise StageError(f"sweep {sweep}: no laser frame to triangulate")
    tb, tl, fidx, box = _check_sweep_inputs(F, T_base_camera, T_camera_laser, frame_indices,
                                            workspace, options)
    counts, frame_pos, uv, line, conf, frame_axis, skew, faint = _sweep_pixels(stripes)

    # all frames at once: per-point plane and pose
    n_f, d_f = _planes(tl)
    pts_cam, keep, dropped, sin_a = _intersect(uv, camera, frame_pos, n_f, d_f,
                                               options.min_angle_deg, options.min_range_m,
                                               options.max_range_m)
    if T_base_camera_end is None:
        R = tb[frame_pos, :3, :3]
        origin = tb[frame_pos, :3, 3]
    else:
        tb_end = np.asarray(T_base_camera_end, dtype=np.float64)
        if tb_end.shape != tb.shape or not np.all(np.isfinite(tb_end)):
            raise ValueError(f"T_base_camera_end must be finite {tb.shape}, got "
                             f"{tb_end.shape}")
        # the sensor's row (a rectified camera's centres were found in the raw frame)
        rows = (np.concatenate([s.v if s.v_sensor is None else s.v_sensor for s in stripes])
                if len(uv) else uv[:, 1])
        R, origin = rows_poses(tb, tb_end, frame_pos, rows / max(camera.height - 1, 1))
    pts_base = np.einsum("nij,nj->ni", R, np.nan_to_num(pts_cam)) + origin
    outside = np.zeros_like(keep)
    in_box = keep
    if box is not None:
        m = float(options.workspace_margin_m)
        inside = np.all((pts_base >= box[0] - m) & (pts_base <= box[1] + m), axis=1)
        outside = keep & ~inside
        keep = keep & inside
        in_box = keep & np.all((pts_base >= box[0]) & (pts_base <= box[1]), axis=1)
    in_margin = int(np.count_nonzero(keep & ~in_box))
    dropped["outside_workspace"] = int(outside.sum())

    report: dict = {
        "sweep": int(sweep),
        "n_frames": int(F),
        "n_frames_with_stripe": int((counts > 0).sum()),
        "n_pixels": int(counts.sum()),
        "dropped": dropped,
        "n_points": int(keep.sum()),
        **({"workspace_margin_m": float(options.workspace_margin_m), "n_in_margin": in_margin}
           if box is not None else {}),
        "stripe_rejected": {k: int(sum(s.rejected.get(k, 0) for s in stripes))
                            for k in stripes[0].rejected},
    }
    if not keep.any():
        raise StageError(
            f"sweep {sweep}: no point triangulated from {F} laser frames "
            f"({int(counts.sum())} stripe pixels; dropped: "
            + ", ".join(f"{k}={v}" for k, v in dropped.items())
            + "; stripe lines rejected: "
            + ", ".join(f"{k}={v}" for k, v in report["stripe_rejected"].items()) + ")")

    P = pts_base[keep]
    O = origin[keep]
    fpos = frame_pos[keep]
    if in_margin and in_box.any():
        # the box's points keep the normals of their neighbours in the box: the margin
        # holds the table, whose crease with the object would tilt the foot's normals
        # (10 degrees on bracket/4's walls); the margin's points see all their neighbours
        # (only theirs are computed from all: the box's would be replaced)
        b = in_box[keep]
        normals, margin = _sweep_normals(P, O, fpos, line[keep], frame_axis, options, ~b)
        normals[b], report["normals_in_box"] = _sweep_normals(
            P[b], O[b], fpos[b], line[keep][b], frame_axis, options)
        report["normals"] = {k: margin[k] + report["normals_in_box"][k] for k in margin}
    else:
        normals, report["normals"] = _sweep_normals(P, O, fpos, line[keep], frame_axis,
                                                    options)
    geo = np.clip(sin_a[keep] / np.sin(np.radians(_CONF_REF_ANGLE_DEG)), 0.0, 1.0)
    from .viz import format_counts

    log.info("sweep %d: %d points from %d frames (dropped: %s)", sweep, len(P), F,
             format_counts(dropped))
    return SweepCloud(
        points_base=P,
        normals_base=normals,
        frame_index=fidx[fpos],
        confidence=np.clip(conf[keep], 0.0, 1.0) * geo,
        sweep=int(sweep),
        sensor_origin_base=O,
        report=report,
        line=line[keep],
        line_axis=frame_axis[fpos],
        skew_px=skew[keep],
        faint=faint[keep],
    )
