"""Quality gates of a calibration (config section ``calibration_gates``).

A calibration that fails a gate stops its rule: :func:`check_gates` raises a
:class:`~robo3d.errors.CalibrationError` that names every failed gate, its value against
its limit, by how much it misses, and the likely cause, read off the data:

* one view much worse than the others (reprojection RMS, sharpness): that view is
  named, blurred or misdetected;
* the board's normals spanning too small an angle: too few tilted views (Zhang 2000:
  views of parallel boards leave the focal length undetermined);
* intrinsics fine but the robot chain disagreeing (hand-eye residual, the board's
  scatter in ``base``): the board's scale the robot's motion implies
  (:func:`board_scale_from_motion`) says whether the target's ``square`` is wrong, else
  the robot's poses or clock are;
* a laser-sheet residual or too few stripes on the board.

Gates that do not apply (no hand-eye on a fixed-camera rig, no laser frames) are listed
with ``passed: null``. Defaults pass good real data with margin: the kuka_1 set
(OpenCV's RMS 0.117 px, the board scattering by 1.75 mm in ``base``) and the srv rig
(0.137 px, laser plane 0.45 mm RMS); see ``config/schema.yaml``.

References
----------
Z. Zhang, "A flexible new technique for camera calibration", IEEE PAMI 22(11), 2000.
R. Y. Tsai and R. K. Lenz, "A new technique for fully autonomous and efficient 3D robotics
hand/eye calibration", IEEE T-RA 5(3), 1989 (rotations about two non-parallel axes are
needed). N. Andreff, R. Horaud, B. Espiau, "Robot hand-eye calibration using
structure-from-motion", IJRR 20(3), 2001 (the scale of the camera's motion as an unknown
of the hand-eye's translation equations, used here to diagnose a wrong square size).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import CalibrationError
from ..transforms import invert_transform

__all__ = ["GateResult", "evaluate_gates", "check_gates", "failure_message", "gate_table",
           "tilt_spread_deg", "rotation_spread_deg", "board_scale_from_motion"]


@dataclass
class GateResult:
    """One gate: its value against its limit (``kind`` max or min), whether it passed
    (None: it does not apply to this calibration) and, when it failed, why it likely
    did."""

    name: str
    value: float | None
    limit: float
    kind: str  # "max": value <= limit passes; "min": value >= limit passes
    unit: str
    passed: bool | None
    cause: str = ""

    def miss(self) -> str:
        """By how much the value misses its limit, in words."""
        if self.value is None or self.passed is not False:
            return ""
        d = self.value - self.limit
        u = f" {self.unit}" if self.unit else ""
        if u.endswith("s") and abs(d) == 1:
            u = u[:-1]  # 1 view, 1 frame
        if not self.limit:
            rel = ""
        elif self.kind == "max":
            rel = f", {self.value / self.limit:.2f} times the limit"
        else:
            rel = f", {self.value / self.limit:.0%} of the limit"
        return f"{abs(d):.3g}{u} {'over' if d > 0 else 'under'} it{rel}"

    def line(self) -> str:
        """``gate <name>: <value>, limit <= <limit> (<miss>); likely cause: <cause>``."""
        op = "<=" if self.kind == "max" else ">="
        u = f" {self.unit}" if self.unit else ""
        value = "n/a" if self.value is None else f"{self.value:.4g}"
        return (f"gate {self.name}: {value}{u}, limit {op} {self.limit:g}{u} "
                f"({self.miss()}); likely cause: {self.cause}")


# ---------------------------------------------------------------------------- figures
def tilt_spread_deg(T_camera_target: np.ndarray) -> float:
    """Largest angle between two views' board normals in the camera frame, degrees."""
    T = np.asarray(T_camera_target, dtype=np.float64).reshape(-1, 4, 4)
    if len(T) < 2:
        return 0.0
    n = T[:, :3, 2]
    c = np.clip(n @ n.T, -1.0, 1.0)
    return float(np.degrees(np.arccos(c.min())))


def rotation_spread_deg(T: np.ndarray) -> float:
    """Largest rotation angle between two of the poses ``(N, 4, 4)``, degrees."""
    R = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)[:, :3, :3]
    if len(R) < 2:
        return 0.0
    rel = np.einsum("iba,jbc->ijac", R, R)  # R_i^T R_j
    c = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))).max())


def board_scale_from_motion(T_base_flange: np.ndarray, T_camera_target: np.ndarray,
                            R_flange_camera: np.ndarray) -> float:
    """The factor by which the board's true size exceeds the one assumed, from the robot.

    With ``A = T_flange_j^-1 T_flange_i`` (the flange's motion, from the robot) and
    ``B = T_camera_target_j T_camera_target_i^-1`` (the camera's, from the board, in the
    board's assumed units), the hand-eye's translation equations ``(R_A - I) t_X =
    s R_X t_B - t_A`` are linear in ``t_X`` and the scale ``s`` (Andreff et al. 2001);
    the rotation ``R_X`` does not depend on the scale. Solved by least squares over all
    pairs of views. ``s = 1.05`` means the squares are 5 % larger than the metadata says.

    Parameters
    ----------
    T_base_flange, T_camera_target : (N, 4, 4) float64
        Per view, the robot's flange pose and the board's pose in the camera.
    R_flange_camera : (3, 3) float64
        The hand-eye's rotation.

    Returns
    -------
    float
        NaN with fewer than three views or motions too small to tell.
    """
    A_ = np.asarray(T_base_flange, dtype=np.float64).reshape(-1, 4, 4)
    B_ = np.asarray(T_camera_target, dtype=np.float64).reshape(-1, 4, 4)
    RX = np.asarray(R_flange_camera, dtype=np.float64).reshape(3, 3)
    n = len(A_)
    if n < 3 or len(B_) != n:
        return float("nan")
    i, j = np.triu_indices(n, 1)
    A = invert_transform(A_[j]) @ A_[i]
    B = B_[j] @ invert_transform(B_[i])
    M = np.zeros((len(i), 3, 4))
    M[:, :, :3] = A[:, :3, :3] - np.eye(3)
    M[:, :, 3] = -np.einsum("ab,nb->na", RX, B[:, :3, 3])
    rhs = -A[:, :3, 3]
    sol, _, rank, _ = np.linalg.lstsq(M.reshape(-1, 4), rhs.reshape(-1), rcond=None)
    return float(sol[3]) if rank == 4 else float("nan")


# ---------------------------------------------------------------------------- gates
def _view_name(result: Any, k: int) -> str:
    """``view 7 (t=1.234567 s)``: the k-th used view, by its index among the images."""
    idx = int(np.asarray(result.views_used)[k])
    stamps = getattr(result, "view_stamps_ns", None)
    t = f" (t={int(stamps[idx]) / 1e9:.6f} s)" if stamps is not None and len(stamps) > idx \
        else ""
    return f"view {idx}{t}"


def _sharpness_note(result: Any, k: int) -> str:
    """``; it is blurred (...)`` when the k-th used view's board edges are much wider than
    the others' (``edge_width_px``: OpenCV's ``estimateChessboardSharpness``, per view)."""
    width = getattr(result, "edge_width_px", None)
    if width is None or len(width) == 0:
        return ""
    width = np.asarray(width, dtype=np.float64)
    idx = int(np.asarray(result.views_used)[k])
    if idx >= len(width) or not np.isfinite(width[idx]) or not np.any(np.isfinite(width)):
        return ""
    med = float(np.nanmedian(width))
    if med > 0 and width[idx] > 1.5 * med:
        return (f"; it is blurred (board edges {width[idx]:.2f} px wide against a median of "
                f"{med:.2f} px)")
    return ""


def _worst_view_cause(result: Any, per_view: np.ndarray, what: str) -> str:
    k = int(np.argmax(per_view))
    med = float(np.median(per_view))
    blur = _sharpness_note(result, k)
    if per_view[k] > 3 * max(med, 1e-9):
        return (f"{_view_name(result, k)} {what} at {per_view[k]:.3g} px against a median of "
                f"{med:.3g} px: a blurred view or a wrong detection there{blur} (leave it "
                "out or retake it)")
    return ""


def _rms_cause(result: Any) -> str:
    per_view = np.asarray(result.per_view_rms_px, dtype=np.float64)
    worst = _worst_view_cause(result, per_view, "reprojects") if len(per_view) else ""
    return worst or ("every view is off alike: a lens the plumb_bob model does not fit "
                     "(fisheye), rescaled images, a board that is not flat, or the wrong "
                     "cols/rows in the target metadata")


def _chain_cause(result: Any, cfg: Mapping[str, Any]) -> str:
    """Why the robot chain disagrees with the board although the intrinsics fit."""
    s = float("nan")
    if getattr(result, "T_base_flange", None) is not None and result.T_flange_camera is not None:
        s = board_scale_from_motion(result.T_base_flange, result.T_camera_target,
                                    np.asarray(result.T_flange_camera)[:3, :3])
    tol = float(cfg["max_scale_error"])
    rms_ok = result.rms_px <= float(cfg["max_rms_px"])
    square = getattr(getattr(result, "target", None), "square", None)
    if np.isfinite(s) and abs(s - 1) > tol:
        likely = (f" (target.square is likely {s * square * 1e3:.3f} mm, not "
                  f"{square * 1e3:.3f} mm)" if square else "")
        return (f"a wrong square size: the reprojection RMS is "
                f"{'fine' if rms_ok else 'high too'} ({result.rms_px:.3g} px) but the robot's "
                f"motion makes the board {s:.4f} times the size its metadata says{likely}")
    per = getattr(result, "handeye_per_view_rms_px", None)
    worst = ""
    if per is not None and len(per):
        worst = _worst_view_cause(result, np.asarray(per, dtype=np.float64),
                                  "disagrees with the robot")
    scale = f"the board's scale agrees with the robot's motion ({s:.4f}); " \
        if np.isfinite(s) else ""
    return (worst or (f"{scale}the robot's poses do not match the images: a clock offset "
                      "between images and /tf (timing.image_offset_s, robo3d info's clock "
                      "section), a board that moved during the recording, or a robot "
                      "reporting inaccurate poses"))


def evaluate_gates(result: Any, cfg: Mapping[str, Any]) -> list[GateResult]:
    """Every gate of ``cfg`` (the ``calibration_gates`` section) on a calibration.

    Parameters
    ----------
    result : robo3d.calibration.calibrate.CalibrationResult
    cfg : mapping
        ``max_rms_px``, ``max_view_rms_px``, ``min_views``, ``min_tilt_spread_deg``,
        ``max_focal_std_rel``, ``max_handeye_rms_px``, ``max_board_scatter_mm``,
        ``min_rotation_spread_deg``, ``max_scale_error``, ``max_sheet_rms_mm``,
        ``min_sheet_frames``.

    Returns
    -------
    list of GateResult
    """
    out: list[GateResult] = []

    def gate(name: str, value: float | None, kind: str, unit: str, cause) -> None:
        limit = float(cfg[name])
        if value is None or not np.isfinite(value):
            out.append(GateResult(name, None, limit, kind, unit, None))
            return
        ok = value <= limit if kind == "max" else value >= limit
        out.append(GateResult(name, float(value), limit, kind, unit, bool(ok),
                              "" if ok else cause()))

    per_view = np.asarray(result.per_view_rms_px, dtype=np.float64)
    n_used = len(result.views_used)
    n_all = n_used + len(result.views_left_out)
    gate("max_rms_px", result.rms_px, "max", "px", lambda: _rms_cause(result))
    gate("max_view_rms_px", float(per_view.max()) if len(per_view) else None, "max", "px",
         lambda: _worst_view_cause(result, per_view, "reprojects") or
         f"{_view_name(result, int(np.argmax(per_view)))} is the worst: a blurred view or a "
         f"wrong detection{_sharpness_note(result, int(np.argmax(per_view)))}")
    gate("min_views", n_used, "min", "views",
         lambda: f"{n_used} of {n_all} views were used; left out: "
         f"{_reasons(result.views_left_out)} (record more views, the whole board sharp "
         "in each)")
    gate("min_tilt_spread_deg", tilt_spread_deg(result.T_camera_target), "min", "deg",
         lambda: "too few tilted views: the board's normals span only this angle, which "
         "leaves the focal length and the principal point poorly determined (tilt the board "
         "by 20-40 degrees about both of its axes)")
    fstd = None
    std = getattr(result, "intrinsics_std", None) or {}
    if "fx" in std and result.camera is not None:
        fstd = float(std["fx"]) / result.camera.fx
    gate("max_focal_std_rel", fstd, "max", "",
         lambda: "the focal length is poorly determined: too few views, or views too alike "
         "(vary the distance and the tilt)")
    robot = result.T_flange_camera is not None
    gate("max_handeye_rms_px", result.handeye_rms_px if robot else None, "max", "px",
         lambda: _chain_cause(result, cfg))
    gate("max_board_scatter_mm", result.board_scatter_mm if robot else None, "max", "mm",
         lambda: _chain_cause(result, cfg))
    rspread = None
    if robot and getattr(result, "T_base_flange", None) is not None:
        rspread = rotation_spread_deg(result.T_base_flange)
    gate("min_rotation_spread_deg", rspread, "min", "deg",
         lambda: "the robot turned the camera too little: the hand-eye's rotation is "
         "undetermined (Tsai and Lenz 1989: rotate the flange about two different axes, "
         "by 30 degrees or more)")
    scale = None
    if robot and getattr(result, "T_base_flange", None) is not None:
        scale = abs(board_scale_from_motion(result.T_base_flange, result.T_camera_target,
                                            np.asarray(result.T_flange_camera)[:3, :3]) - 1)
    gate("max_scale_error", scale, "max", "", lambda: _chain_cause(result, cfg))
    sheet = result.T_camera_laser is not None
    gate("max_sheet_rms_mm", result.sheet_rms_mm if sheet else None, "max", "mm",
         lambda: "the laser points do not lie on one plane: the stripe fell on something "
         "other than the board (a hand, the room behind), or the board poses of the laser "
         "frames are off" + _sheet_worst(result))
    n_sheet = len(result.sheet_frames_used) if sheet else None
    gate("min_sheet_frames", n_sheet, "min", "frames",
         lambda: f"the stripe was found on the board in {n_sheet} laser frames; one board "
         "pose gives one line, a plane needs several non-parallel ones; left out: "
         f"{_reasons(result.sheet_left_out, 'frame')}")
    return out


def _sheet_worst(result: Any) -> str:
    res = getattr(result, "sheet_per_frame_rms_mm", None)
    if res is None or len(res) == 0:
        return ""
    res = np.asarray(res, dtype=np.float64)
    k = int(np.nanargmax(res))
    return (f"; the worst is laser frame {int(np.asarray(result.sheet_frames_used)[k])} at "
            f"{res[k]:.3g} mm (median {float(np.nanmedian(res)):.3g} mm)")


def _reasons(left_out: Mapping[int, str], what: str = "view") -> str:
    """Why views (or laser frames) were left out, grouped by the reason's kind (its words
    before ``:`` or ``(``), each with the indices and the first one's figures:
    ``2 blurred (views 2, 4: board edges 9.0 px wide > 8 px ...); 1 not found (view 7)``."""
    if not left_out:
        return "none"
    import re

    groups: dict[str, list[tuple[int, str]]] = {}
    for k, r in sorted(left_out.items()):
        key = re.split(r"[:(]", str(r), maxsplit=1)[0].strip() or str(r)
        groups.setdefault(key, []).append((int(k), str(r)))
    parts = []
    for key, items in sorted(groups.items(), key=lambda kv: -len(kv[1])):
        idx = [i for i, _ in items]
        names = ", ".join(map(str, idx[:8])) + (", ..." if len(idx) > 8 else "")
        detail = items[0][1][len(key):].strip(" :")
        parts.append(f"{len(idx)} {key} ({what}{'s' if len(idx) > 1 else ''} {names}"
                     f"{': ' + detail if detail else ''})")
    return "; ".join(parts)


def gate_table(gates: list[GateResult]) -> dict[str, dict[str, Any]]:
    """The gates as the calibration file's ``gates`` mapping."""
    return {g.name: {"value": g.value, "limit": g.limit, "kind": g.kind, "unit": g.unit,
                     "passed": g.passed, **({"cause": g.cause} if g.cause else {})}
            for g in gates}


def check_gates(result: Any, cfg: Mapping[str, Any], where: str | None = None
                ) -> list[GateResult]:
    """:func:`evaluate_gates`, raising when any gate fails.

    Raises
    ------
    CalibrationError
        One line per failed gate: which, value against limit, by how much, likely cause;
        ``where`` (the calibration recording) is named.
    """
    gates = evaluate_gates(result, cfg)
    failed = [g for g in gates if g.passed is False]
    if failed:
        raise CalibrationError(failure_message(failed), path=where)
    return gates


def failure_message(failed: list[GateResult]) -> str:
    """The message of a failed calibration: the gates' names on its first line (what
    ``robo3d status`` shows), then one line per gate (:meth:`GateResult.line`)."""
    return (f"calibration failed {len(failed)} quality gate(s), "
            f"{', '.join(g.name for g in failed)} (config calibration_gates):\n"
            + "\n".join("  " + g.line() for g in failed))
