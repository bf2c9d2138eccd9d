"""Hand-eye calibration of a robot cell: a static board in ``base``, the camera on the flange.

Unknown: ``X = T_flange_camera``. Every view ``i`` has the robot's ``T_base_flange_i``
and the board's pose in the camera ``T_camera_target_i`` (PnP), and the board does not
move: ``T_base_target = T_base_flange_i X T_camera_target_i`` for all ``i``.

Closed forms (written here; OpenCV 5.0's wheel has no ``calibrateHandEye``)
---------------------------------------------------------------------------
Every pair ``i < j`` of views (all pairs, vectorised, as OpenCV's own implementation
does) gives ``A X = X B`` with the flange's motion ``A = T_base_flange_j^-1
T_base_flange_i`` and the camera's ``B = T_camera_target_j T_camera_target_i^-1``.

- Tsai & Lenz (1989): with the modified Rodrigues vectors ``P = 2 sin(θ/2) k`` of ``A``
  and ``B``, ``skew(P_A + P_B) P' = P_B - P_A`` (least squares over the pairs), then
  ``P_X = 2 P' / sqrt(1 + |P'|²)``.
- Park & Martin (1994): with the rotation vectors ``α = log R_A``, ``β = log R_B``,
  ``M = Σ β αᵀ`` and ``R_X = (MᵀM)^(-1/2) Mᵀ``.
- Translation, both: ``(R_A - I) t_X = R_X t_B - t_A``, least squares over the pairs.

Proof against an independent truth: ``tests/test_calibration_core.py`` recovers a known
``X`` from exact synthetic motions (to 1e-6 mm and 1e-5 deg) and to the required
0.3 mm / 0.05° from noisy ones. Against OpenCV 4.x's ``calibrateHandEye``
(``opencv-python-headless`` 4.14.0 in a separate virtualenv, not a project dependency),
on the same noisy synthetic views and on kuka_1, our Tsai and Park agree with OpenCV's
``CALIB_HAND_EYE_TSAI`` / ``_PARK`` to the figures in :data:`OPENCV4_AGREEMENT`
(Park to rounding; Tsai to a few hundredths of a millimetre, the same distance from
the truth as OpenCV's). Where ``cv2.calibrateHandEye`` exists (a 4.x
install), :func:`opencv_reference` uses it.

Joint refinement
----------------
:func:`refine_handeye` minimises the reprojection error of every corner of every view
(``scipy.optimize.least_squares``, trust region reflective, finite-difference Jacobian)
over ``X`` (6), ``T_base_target`` (6) and, with ``refine_intrinsics``, ``K`` (4) and
``D`` (5): the corners of view ``i`` are projected through
``T_camera_target_i = X^-1 T_base_flange_i^-1 T_base_target``. Its start is the closed
form and the mean of the views' ``T_base_target``. ``loss`` (e.g. ``soft_l1``) with
``f_scale_px`` bounds the weight of corners, and views, that a bad detection puts far off.

The robot's reported poses are not exact (``rwhe_kuka1``: the residuals through the robot
chain are 2.4 px RMS against 0.07 px within a view, the board's position in ``base``
varies by millimetres with the robot's position): with pixel noise alone as the model,
the fit trades millimetres of robot error in far views against fewer in near ones and
keeps the board *less* constant than the closed form (kuka_1: 1.90 against 1.76 mm).
So each view's robot pose gets a correction ``δ_i`` (flange frame, rotation and
translation) with a Gaussian prior (``robot_sigma_deg``, ``robot_sigma_mm``) weighed
against the corners' noise (``corner_sigma_px``): the residuals of view ``i`` are
``[r_i + J_i δ_i ; W δ_i]`` with ``δ_i`` the minimiser of their squared norm for the
current ``X``, ``T_base_target`` (``J_i = ∂r_i/∂δ_i`` by finite differences; linearised,
exact for the millimetre corrections at stake). This eliminates the 6 M nuisance
parameters in closed form (variable projection: Golub & Pereyra 1973), so the outer
problem keeps its 12 (21) unknowns. It is the maximum-likelihood estimate under both
noises; with ``robot_sigma_mm = robot_sigma_deg = 0`` it is the pure reprojection fit.
Measured on kuka_1 (30 views): board scatter 1.707 mm (Tsai closed form 1.764 mm; OpenCV
``calibrateCamera`` + Tsai, the README's run, 1.751 mm); ``robot_sigma_deg`` 0.02 / 0.2
gives 1.722 / 1.827 mm, ``robot_sigma_mm`` 2 (and 0.1 deg) 1.706 mm.

Board scatter (``rwhe_kuka1``'s README): the board origin's position in ``base`` per view,
``T_base_flange_i X T_camera_target_i`` with that view's own PnP board pose (with the
calibration's ``K``, ``D``), and its spread: the root of the summed variances of ``x``,
``y``, ``z`` (the RMS distance from the mean position), in millimetres.

Degenerate input (a :class:`~robo3d.errors.CalibrationError` naming the recording when
known): fewer than 3 views; fewer than 2 view pairs rotating by ``min_rotation_deg``; or
rotation axes that spread by less than ``min_axis_spread_deg`` (then the translation of
``X`` along the common axis is not determined).

References
----------
Tsai, R. Y., Lenz, R. K. "A new technique for fully autonomous and efficient 3D robotics
hand/eye calibration", IEEE Trans. Robotics and Automation 5(3), 1989.
Park, F. C., Martin, B. J. "Robot sensor calibration: solving AX = XB on the Euclidean
group", IEEE Trans. Robotics and Automation 10(5), 1994.
Golub, G. H., Pereyra, V. "The differentiation of pseudo-inverses and nonlinear least
squares problems whose variables separate", SIAM J. Numer. Anal. 10(2), 1973.
Ali, I., Suominen, O., Gotchev, A., Ruiz Morales, E. "Methods for Simultaneous
Robot-World-Hand-Eye Calibration: A Comparative Study", Sensors 19(12), 2019 (kuka_1).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..errors import CalibrationError
from ..options import Options
from .intrinsics import rvec_tvec_to_T
from .target import Target, board_points

__all__ = [
    "HandEyeOptions",
    "HandEyeResult",
    "handeye_closed_form",
    "refine_handeye",
    "board_scatter_mm",
    "board_positions_base",
    "rotation_axis_spread_deg",
    "opencv_reference",
    "project_plumb_bob",
    "pnp_poses",
    "OPENCV4_AGREEMENT",
    "half_turn",
    "resolve_board_flips",
]

_log = logging.getLogger(__name__)

#: Our closed forms against OpenCV 4.12's calibrateHandEye on the same noisy synthetic
#: views (filled in from the measurement described in the module docstring).
OPENCV4_AGREEMENT = (
    "opencv-python-headless 4.14.0, calibrateHandEye on the same inputs: Park identical "
    "(2e-13 mm synthetic, 5e-8 mm / 2e-6 deg kuka_1); Tsai within 7e-4 mm / 1e-4 deg on "
    "the synthetic cell of tests/test_calibration_core.py (both 0.178 mm / 0.0174 deg from "
    "the truth) and 0.041 mm / 0.0027 deg on kuka_1 (30 views)")

METHODS = ("tsai", "park")
LOSSES = ("linear", "soft_l1", "huber", "cauchy", "arctan")


@dataclasses.dataclass(frozen=True)
class HandEyeOptions(Options):
    """Hand-eye calibration's parameters (config section ``calibration``).

    Attributes
    ----------
    handeye_method : {"tsai", "park"}
        Closed form that starts the refinement.
    refine_intrinsics : bool
        Refine ``K`` and ``D`` together with the hand-eye and the board's pose.
    loss : {"linear", "soft_l1", "huber", "cauchy", "arctan"}
        Robust loss of the refinement (scipy's names).
    f_scale_px : float, pixels
        The loss's scale: residuals beyond it weigh less.
    robot_sigma_mm, robot_sigma_deg : float
        The robot's pose error (1 sigma) allowed per view; both 0: robot poses exact.
    corner_sigma_px : float, pixels
        The corners' detection noise, weighing reprojection against the robot's error.
    min_rotation_deg : float, degrees
        View pairs rotating less than this do not count as a rotation.
    min_axis_spread_deg : float, degrees
        The rotation axes of the view pairs must spread by at least this much.
    max_nfev : int
        Most function evaluations of the refinement.
    """

    section = "calibration"

    handeye_method: str = "tsai"
    refine_intrinsics: bool = False
    loss: str = "soft_l1"
    f_scale_px: float = 1.0
    robot_sigma_mm: float = 1.0
    robot_sigma_deg: float = 0.05
    corner_sigma_px: float = 0.1
    min_rotation_deg: float = 2.0
    min_axis_spread_deg: float = 5.0
    max_nfev: int = 200


@dataclasses.dataclass
class HandEyeResult:
    """Result of :func:`refine_handeye`.

    Attributes
    ----------
    T_flange_camera, T_base_target : (4, 4) float64, metres
        The refined hand-eye and the board's pose in ``base``.
    K : (3, 3), D : (5,)
        The intrinsics used (refined when ``refine_intrinsics``).
    rms_px : float
        Overall reprojection RMS of the joint model.
    per_view_rms : (M,) float64
        Per view, in the order given.
    board_scatter_mm : float
        With the refined hand-eye, ``K``, ``D`` and each view's own PnP.
    closed_form : dict
        The closed form's figures beside it: ``method``, ``T_flange_camera``,
        ``T_base_target``, ``rms_px``, ``per_view_rms``, ``board_scatter_mm``.
    rotation_axis_spread_deg : float
    flipped : (M,) bool
        Views of a symmetric board whose reading was turned by 180° to agree with view 0
        (:func:`resolve_board_flips`); their corners count reversed.
    robot_correction_mm, robot_correction_deg : (M,) float64
        Per view, the correction of the robot's pose the refinement's robot-error model
        implies (translation and rotation; zeros when ``robot_sigma_*`` are 0).
    nfev, success : the optimiser's.
    """

    T_flange_camera: np.ndarray
    T_base_target: np.ndarray
    K: np.ndarray
    D: np.ndarray
    rms_px: float
    per_view_rms: np.ndarray
    board_scatter_mm: float
    closed_form: dict
    rotation_axis_spread_deg: float
    robot_correction_mm: np.ndarray | None = None
    robot_correction_deg: np.ndarray | None = None
    flipped: np.ndarray | None = None
    nfev: int = 0
    success: bool = True


# ------------------------------------------------------------------ rotations, vectorised
def _skew(v: np.ndarray) -> np.ndarray:
    s = np.zeros(v.shape[:-1] + (3, 3))
    s[..., 0, 1], s[..., 0, 2], s[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    s[..., 1, 0], s[..., 2, 0], s[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return s


def _log_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation vectors ``(..., 3)`` of rotation matrices ``(..., 3, 3)`` (robust near π)."""
    R = np.asarray(R, dtype=np.float64)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    w = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], axis=-1)
    s = np.sin(theta)
    small = theta < 1e-7
    factor = np.where(small, 0.5, theta / (2.0 * np.where(small, 1.0, s)))
    out = w * factor[..., None]
    near_pi = theta > np.pi - 1e-3
    if np.any(near_pi):  # axis from the symmetric part
        Rp = R[near_pi]
        B = (Rp + np.swapaxes(Rp, -1, -2)) / 2.0 - np.cos(theta[near_pi])[:, None, None] * np.eye(3)
        k = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        axis = B[np.arange(len(Rp)), k]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        sign = np.sign(np.sum(axis * w[near_pi], axis=-1))
        sign[sign == 0] = 1.0
        out[near_pi] = axis * (sign * theta[near_pi])[:, None]
    return out


def _exp_rotation(r: np.ndarray) -> np.ndarray:
    return rvec_tvec_to_T(r.reshape(-1, 3), np.zeros((len(r.reshape(-1, 3)), 3)))[:, :3, :3]


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _check_poses(name: str, T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name} must be (N, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{name} has non-finite values")
    return T


def _where(recording: str | None) -> dict:
    return {"path": recording} if recording else {}


def _pairs(T_base_flange: np.ndarray, T_camera_target: np.ndarray):
    i, j = np.triu_indices(len(T_base_flange), k=1)
    A = _inv(T_base_flange[j]) @ T_base_flange[i]
    B = T_camera_target[j] @ _inv(T_camera_target[i])
    return A, B


def rotation_axis_spread_deg(R: np.ndarray, min_rotation_deg: float = 2.0) -> tuple[float, int]:
    """How far apart the rotation axes of some motions are, and how many rotate enough.

    Parameters
    ----------
    R : (P, 3, 3)
        Rotations (e.g. the flange's motions between pairs of views).
    min_rotation_deg : float
        Smaller rotations are left out.

    Returns
    -------
    spread_deg : float
        ``2 atan(sqrt(λ2 / λ1))`` of the axes' scatter matrix ``Σ a aᵀ`` (sign-free): the
        angle between the axes for two axes, 0 for one.
    n : int
        Motions rotating by at least ``min_rotation_deg``.
    """
    r = _log_rotation(R)
    th = np.linalg.norm(r, axis=-1)
    keep = th >= np.radians(min_rotation_deg)
    if keep.sum() < 1:
        return 0.0, 0
    a = r[keep] / th[keep, None]
    lam = np.sort(np.linalg.eigvalsh(a.T @ a))[::-1]
    return float(np.degrees(2.0 * np.arctan(np.sqrt(max(lam[1], 0.0) / lam[0])))), int(keep.sum())


# --------------------------------------------------------------------------- closed forms
def handeye_closed_form(T_base_flange: np.ndarray, T_camera_target: np.ndarray,
                        method: str = "tsai", *, min_rotation_deg: float = 2.0,
                        min_axis_spread_deg: float = 5.0,
                        recording: str | None = None) -> np.ndarray:
    """``T_flange_camera`` from robot poses and board poses (static board), in closed form.

    Parameters
    ----------
    T_base_flange : (N, 4, 4) float64, metres
    T_camera_target : (N, 4, 4) float64, metres
    method : {"tsai", "park"}
        Tsai & Lenz (1989) or Park & Martin (1994), over all pairs of views.
    min_rotation_deg, min_axis_spread_deg : float, degrees
        Degeneracy limits (module docstring).
    recording : str, optional
        Named in errors.

    Returns
    -------
    (4, 4) float64
        ``T_flange_camera``.

    Raises
    ------
    CalibrationError
        Fewer than 3 views, too few rotations, rotation axes nearly parallel.
    """
    Tbf = _check_poses("T_base_flange", T_base_flange)
    Tct = _check_poses("T_camera_target", T_camera_target)
    if len(Tbf) != len(Tct):
        raise ValueError(f"T_base_flange has {len(Tbf)} poses, T_camera_target {len(Tct)}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if len(Tbf) < 3:
        raise CalibrationError(f"hand-eye: {len(Tbf)} views with a board, at least 3 needed "
                               f"(two motions about different axes)", **_where(recording))
    A, B = _pairs(Tbf, Tct)
    spread, n_rot = rotation_axis_spread_deg(A[:, :3, :3], min_rotation_deg)
    if n_rot < 2:
        raise CalibrationError(
            f"hand-eye: too few rotations: {n_rot} of {len(A)} view pairs rotate the flange "
            f"by {min_rotation_deg:g} deg or more; rotate the camera between views (about "
            f"two different axes)", **_where(recording))
    if spread < min_axis_spread_deg:
        raise CalibrationError(
            f"hand-eye: the flange's rotation axes are nearly parallel (they spread by "
            f"{spread:.2f} deg < {min_axis_spread_deg:g} deg): the hand-eye translation "
            f"along that axis is not determined; rotate about a second axis too",
            **_where(recording))
    RA, RB = A[:, :3, :3], B[:, :3, :3]
    if method == "tsai":
        ra, rb = _log_rotation(RA), _log_rotation(RB)
        ta, tb = np.linalg.norm(ra, axis=-1), np.linalg.norm(rb, axis=-1)
        pa = ra * (2.0 * np.sin(ta / 2.0) / np.where(ta > 0, ta, 1.0))[:, None]
        pb = rb * (2.0 * np.sin(tb / 2.0) / np.where(tb > 0, tb, 1.0))[:, None]
        M = _skew(pa + pb).reshape(-1, 3)
        p_prime = np.linalg.lstsq(M, (pb - pa).reshape(-1), rcond=None)[0]
        px = 2.0 * p_prime / np.sqrt(1.0 + p_prime @ p_prime)
        n2 = px @ px
        RX = ((1.0 - n2 / 2.0) * np.eye(3)
              + 0.5 * (np.outer(px, px) + np.sqrt(max(4.0 - n2, 0.0)) * _skew(px)))
    else:
        alpha, beta = _log_rotation(RA), _log_rotation(RB)
        M = beta.T @ alpha  # Σ β αᵀ
        w, V = np.linalg.eigh(M.T @ M)
        RX = V @ np.diag(1.0 / np.sqrt(np.maximum(w, 1e-300))) @ V.T @ M.T
    U, _, Vt = np.linalg.svd(RX)  # nearest rotation
    RX = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    C = (RA - np.eye(3)).reshape(-1, 3)
    d = (np.einsum("ij,pj->pi", RX, B[:, :3, 3]) - A[:, :3, 3]).reshape(-1)
    tX = np.linalg.lstsq(C, d, rcond=None)[0]
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = RX, tX
    return X


# ------------------------------------------------------------- symmetric boards' half turn
def half_turn(target: Target) -> np.ndarray:
    """``T_target_turned``: the board frame turned by 180° about its centre's normal, whose
    corner ``k`` is the original corner ``N - 1 - k`` (a symmetric board's other reading)."""
    F = np.diag([-1.0, -1.0, 1.0, 1.0])
    F[:2, 3] = [(target.cols - 1) * target.square, (target.rows - 1) * target.square]
    return F


def resolve_board_flips(T_base_flange: np.ndarray, T_camera_target: np.ndarray,
                        target: Target) -> np.ndarray:
    """Which views of a static, half-turn symmetric board (``cols + rows`` even) read the
    board turned by 180° against the first view (see :mod:`robo3d.calibration.target`).

    For a consistent reading, each pair ``(0, i)`` rotates the flange and the camera by the
    same angle (``A X = X B`` makes ``R_A`` and ``R_B`` similar, whatever ``X`` is); a view
    read turned changes ``R_B`` by the half turn. Each view takes the reading whose angle
    is closer to the flange's.

    Returns
    -------
    (N,) bool
        True where ``T_camera_target_i @ half_turn(target)`` (and the corners reversed) is
        the reading consistent with view 0; all False for an asymmetric board.
    """
    Tbf = _check_poses("T_base_flange", T_base_flange)
    Tct = _check_poses("T_camera_target", T_camera_target)
    flips = np.zeros(len(Tct), dtype=bool)
    if not target.symmetric or len(Tct) < 2:
        return flips
    A = _inv(Tbf[1:]) @ Tbf[:1]
    ang_a = np.linalg.norm(_log_rotation(A[:, :3, :3]), axis=-1)
    ang = []
    for Tc in (Tct[1:], Tct[1:] @ half_turn(target)[None]):
        B = Tc @ _inv(Tct[:1])
        ang.append(np.abs(np.linalg.norm(_log_rotation(B[:, :3, :3]), axis=-1) - ang_a))
    flips[1:] = ang[1] < ang[0]
    return flips


# ----------------------------------------------------------------------------- figures
def board_positions_base(T_base_flange: np.ndarray, T_flange_camera: np.ndarray,
                         T_camera_target: np.ndarray) -> np.ndarray:
    """The board's pose in ``base`` per view, ``(N, 4, 4)``: robot pose, hand-eye, PnP."""
    return (np.asarray(T_base_flange) @ np.asarray(T_flange_camera)[None]
            @ np.asarray(T_camera_target))


def board_scatter_mm(T_base_flange: np.ndarray, T_flange_camera: np.ndarray,
                     T_camera_target: np.ndarray) -> float:
    """Spread of the board origin's position in ``base`` over the views, millimetres.

    Parameters
    ----------
    T_base_flange : (N, 4, 4), T_flange_camera : (4, 4), T_camera_target : (N, 4, 4)
        Metres; ``T_camera_target`` from each view's own board detection.

    Returns
    -------
    float
        ``sqrt(var(x) + var(y) + var(z))`` of the positions (population variances), mm.
    """
    p = board_positions_base(T_base_flange, T_flange_camera, T_camera_target)[:, :3, 3]
    return float(np.sqrt(np.sum(np.var(p, axis=0))) * 1000.0)


def project_plumb_bob(points_cam: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Project camera-frame points ``(..., 3)`` with ``K`` and plumb_bob ``D`` (as OpenCV's
    ``projectPoints``): pixels ``(..., 2)``."""
    X = np.asarray(points_cam, dtype=np.float64)
    x, y = X[..., 0] / X[..., 2], X[..., 1] / X[..., 2]
    k1, k2, p1, p2, k3 = (np.asarray(D, dtype=np.float64).ravel().tolist() + [0.0] * 5)[:5]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=-1)


def pnp_poses(corners_uv: np.ndarray, target: Target, K: np.ndarray,
              D: np.ndarray) -> np.ndarray:
    """Each view's own board pose ``T_camera_target`` ``(M, 4, 4)`` from its corners
    ``(M, N, 2)`` (OpenCV ``solvePnP``, iterative, from the homography start)."""
    import cv2

    obj = board_points(target)
    rv, tv = [], []
    for uv in np.asarray(corners_uv, dtype=np.float64):
        _, r, t = cv2.solvePnP(obj, uv, K, D, flags=cv2.SOLVEPNP_ITERATIVE)
        rv.append(r.ravel())
        tv.append(t.ravel())
    return rvec_tvec_to_T(np.array(rv), np.array(tv))


def _mean_pose(T: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(np.sum(T[:, :3, :3], axis=0))
    out = np.eye(4)
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[:3, 3] = T[:, :3, 3].mean(axis=0)
    return out


def _residual_model(T_base_flange, X, Tbt, K, D, obj):
    Tct = _inv(X)[None] @ _inv(T_base_flange) @ Tbt[None]
    pc = np.einsum("mij,nj->mni", Tct[:, :3, :3], obj) + Tct[:, None, :3, 3]
    return project_plumb_bob(pc, K, D)


def _per_view(res_uv: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(np.sum(res_uv ** 2, axis=-1), axis=-1))


# --------------------------------------------------------------------------- refinement
def refine_handeye(T_base_flange: np.ndarray, corners_uv: np.ndarray, target: Target,
                   K: np.ndarray, D: np.ndarray, T_camera_target: np.ndarray | None = None,
                   options: HandEyeOptions | None = None, *,
                   recording: str | None = None) -> HandEyeResult:
    """Hand-eye by closed form, refined jointly with the board's pose (and optionally the
    intrinsics) by minimising the reprojection error of every corner of every view.

    Parameters
    ----------
    T_base_flange : (M, 4, 4) float64, metres
        Robot poses of the views.
    corners_uv : (M, N, 2) float64, pixels
        Each view's corners in :func:`~robo3d.calibration.target.board_points` order.
    target : Target
    K : (3, 3), D : (5,)
        Intrinsics (e.g. :func:`~robo3d.calibration.intrinsics.calibrate_intrinsics`'s).
    T_camera_target : (M, 4, 4), optional
        The views' board poses for the closed form (default: PnP with ``K``, ``D``).
    options : HandEyeOptions, optional
    recording : str, optional
        Named in errors.

    Returns
    -------
    HandEyeResult
        With the closed form's figures in ``closed_form``.
    """
    from scipy.optimize import least_squares

    opts = options or HandEyeOptions()
    if opts.loss not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {opts.loss!r}")
    Tbf = _check_poses("T_base_flange", T_base_flange)
    uv = np.asarray(corners_uv, dtype=np.float64)
    if uv.shape != (len(Tbf), target.n_corners, 2):
        raise ValueError(f"corners_uv must be ({len(Tbf)}, {target.n_corners}, 2), got "
                         f"{uv.shape}")
    K = np.asarray(K, dtype=np.float64)
    D = np.asarray(D, dtype=np.float64).ravel()[:5]
    obj = board_points(target)
    Tct0 = pnp_poses(uv, target, K, D) if T_camera_target is None else _check_poses(
        "T_camera_target", T_camera_target)
    flips = resolve_board_flips(Tbf, Tct0, target)
    if flips.any():  # a symmetric board read turned in some views: one reading for all
        _log.info("hand-eye: %d views of the symmetric board read turned by 180 deg against "
                  "view 0; their corners are reversed", int(flips.sum()))
        uv = uv.copy()
        uv[flips] = uv[flips][:, ::-1]
        Tct0 = Tct0.copy()
        Tct0[flips] = Tct0[flips] @ half_turn(target)[None]
    X0 = handeye_closed_form(Tbf, Tct0, opts.handeye_method,
                             min_rotation_deg=opts.min_rotation_deg,
                             min_axis_spread_deg=opts.min_axis_spread_deg, recording=recording)
    A, _ = _pairs(Tbf, Tct0)
    spread, _ = rotation_axis_spread_deg(A[:, :3, :3], opts.min_rotation_deg)
    Tbt0 = _mean_pose(board_positions_base(Tbf, X0, Tct0))
    res0 = _residual_model(Tbf, X0, Tbt0, K, D, obj) - uv
    closed = {"method": opts.handeye_method, "T_flange_camera": X0, "T_base_target": Tbt0,
              "rms_px": float(np.sqrt(np.mean(np.sum(res0 ** 2, axis=-1)))),
              "per_view_rms": _per_view(res0),
              "board_scatter_mm": board_scatter_mm(Tbf, X0, Tct0)}

    M = len(Tbf)
    robot = opts.robot_sigma_mm > 0 or opts.robot_sigma_deg > 0
    # prior residuals in pixel-equivalents: delta / sigma_robot * sigma_corner
    w_t = opts.corner_sigma_px / max(opts.robot_sigma_mm * 1e-3, 1e-12)
    w_r = opts.corner_sigma_px / max(np.radians(opts.robot_sigma_deg), 1e-12)

    def unpack(p):
        X = rvec_tvec_to_T(p[0:3][None], p[3:6][None])[0]
        Tbt = rvec_tvec_to_T(p[6:9][None], p[9:12][None])[0]
        if opts.refine_intrinsics:
            Kp = np.array([[p[12], 0.0, p[14]], [0.0, p[13], p[15]], [0.0, 0.0, 1.0]])
            Dp = p[16:21]
        else:
            Kp, Dp = K, D
        return X, Tbt, Kp, Dp

    steps = np.array([1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6])
    perturb = rvec_tvec_to_T(np.eye(6)[:, :3] * steps[:, None], np.eye(6)[:, 3:] * steps[:, None])
    wd2 = np.array([w_r, w_r, w_r, w_t, w_t, w_t]) ** 2

    def corrections(X, Tbt, Kp, Dp):
        """Reprojection residuals (M, 2N) with each view's robot pose corrected by the
        delta that minimises |r + J delta|^2 + |W delta|^2 (linearised), and the deltas."""
        pred = _residual_model(Tbf, X, Tbt, Kp, Dp, obj)
        r0 = (pred - uv).reshape(M, -1)
        if not robot:
            return r0, np.zeros((M, 6))
        J = np.stack([(_residual_model(Tbf @ perturb[k], X, Tbt, Kp, Dp, obj) - pred)
                      .reshape(M, -1) / steps[k] for k in range(6)], axis=-1)
        H = np.einsum("mrk,mrl->mkl", J, J) + np.diag(wd2)[None]
        g = np.einsum("mrk,mr->mk", J, r0)
        delta = -np.linalg.solve(H, g[..., None])[..., 0]
        return r0 + np.einsum("mrk,mk->mr", J, delta), delta

    def fun(p):
        r, delta = corrections(*unpack(p))
        if not robot:
            return r.ravel()
        return np.concatenate([r.ravel(), (delta * np.sqrt(wd2)).ravel()])

    p0 = np.concatenate([_log_rotation(X0[:3, :3]), X0[:3, 3], _log_rotation(Tbt0[:3, :3]),
                         Tbt0[:3, 3]])
    if opts.refine_intrinsics:
        p0 = np.concatenate([p0, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], D])
    sol = least_squares(fun, p0, method="trf", loss=opts.loss, f_scale=opts.f_scale_px,
                        x_scale="jac", max_nfev=opts.max_nfev)
    X, Tbt, Kr, Dr = unpack(sol.x)
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Kr))):
        raise CalibrationError("hand-eye refinement diverged (non-finite result)",
                               **_where(recording))
    res = _residual_model(Tbf, X, Tbt, Kr, Dr, obj) - uv
    _, delta = corrections(X, Tbt, Kr, Dr)
    Tct = pnp_poses(uv, target, Kr, Dr)
    out = HandEyeResult(
        T_flange_camera=X, T_base_target=Tbt, K=Kr, D=Dr,
        rms_px=float(np.sqrt(np.mean(np.sum(res ** 2, axis=-1)))), per_view_rms=_per_view(res),
        board_scatter_mm=board_scatter_mm(Tbf, X, Tct), closed_form=closed,
        rotation_axis_spread_deg=spread,
        robot_correction_mm=np.linalg.norm(delta[:, 3:], axis=1) * 1000.0,
        robot_correction_deg=np.degrees(np.linalg.norm(delta[:, :3], axis=1)), flipped=flips,
        nfev=int(sol.nfev), success=bool(sol.success))
    _log.info("hand-eye: closed form (%s) RMS %.3f px, scatter %.3f mm; refined RMS %.3f px, "
              "scatter %.3f mm", opts.handeye_method, closed["rms_px"],
              closed["board_scatter_mm"], out.rms_px, out.board_scatter_mm)
    return out


def opencv_reference(T_base_flange: np.ndarray, corners_uv: np.ndarray, target: Target,
                     image_size: tuple[int, int]) -> dict:
    """OpenCV's hand-eye figure, as ``rwhe_kuka1``'s README ran it: ``calibrateCamera``
    on all the given views, then Tsai's hand-eye (``cv2.calibrateHandEye`` where this
    OpenCV has it, else our Tsai, which equals it: module docstring), and the board
    scatter through each view's ``calibrateCamera`` extrinsics.

    Returns
    -------
    dict
        ``rms_px``, ``K``, ``D``, ``T_flange_camera``, ``board_scatter_mm``, ``handeye``
        (``"cv2.calibrateHandEye"`` or ``"robo3d tsai"``).
    """
    import cv2

    uv = np.asarray(corners_uv, dtype=np.float32)
    obj = board_points(target).astype(np.float32)
    rms, K, D, rvecs, tvecs = cv2.calibrateCamera([obj] * len(uv), list(uv),
                                                  tuple(int(v) for v in image_size), None, None)
    Tct = rvec_tvec_to_T(np.asarray(rvecs).reshape(-1, 3), np.asarray(tvecs).reshape(-1, 3))
    Tbf = _check_poses("T_base_flange", T_base_flange)
    if hasattr(cv2, "calibrateHandEye"):
        R, t = cv2.calibrateHandEye(list(Tbf[:, :3, :3]), list(Tbf[:, :3, 3]),
                                    list(Tct[:, :3, :3]), list(Tct[:, :3, 3]),
                                    method=cv2.CALIB_HAND_EYE_TSAI)
        X = np.eye(4)
        X[:3, :3], X[:3, 3] = R, np.asarray(t).ravel()
        how = "cv2.calibrateHandEye"
    else:
        X = handeye_closed_form(Tbf, Tct, "tsai", min_rotation_deg=0.0, min_axis_spread_deg=0.0)
        how = "robo3d tsai"
    return {"rms_px": float(rms), "K": np.asarray(K), "D": np.asarray(D).ravel()[:5],
            "T_flange_camera": X, "board_scatter_mm": board_scatter_mm(Tbf, X, Tct),
            "handeye": how}
