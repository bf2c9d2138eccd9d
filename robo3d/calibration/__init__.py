"""Calibration of a robot cell from a calibration recording (issue 13): the target and its
detection (:mod:`.target`), intrinsics (:mod:`.intrinsics`), hand-eye (:mod:`.handeye`).

Frames: ``T_a_b`` maps points in frame ``b`` to frame ``a`` (4 x 4, metres), as everywhere
in robo3d; ``target`` is the board frame of :func:`~robo3d.calibration.target.board_points`.
"""

from .handeye import (
    HandEyeOptions,
    HandEyeResult,
    board_positions_base,
    board_scatter_mm,
    half_turn,
    handeye_closed_form,
    opencv_reference,
    pnp_poses,
    project_plumb_bob,
    refine_handeye,
    resolve_board_flips,
    rotation_axis_spread_deg,
)
from .intrinsics import IntrinsicsOptions, IntrinsicsResult, calibrate_intrinsics, tilt_spread_deg
from .target import (
    BoardDetection,
    DetectOptions,
    Target,
    board_points,
    detect_board,
    detect_boards,
    target_from_recording,
)

__all__ = [
    "Target",
    "BoardDetection",
    "DetectOptions",
    "target_from_recording",
    "board_points",
    "detect_board",
    "detect_boards",
    "IntrinsicsOptions",
    "IntrinsicsResult",
    "calibrate_intrinsics",
    "tilt_spread_deg",
    "HandEyeOptions",
    "HandEyeResult",
    "handeye_closed_form",
    "refine_handeye",
    "board_scatter_mm",
    "board_positions_base",
    "rotation_axis_spread_deg",
    "opencv_reference",
    "pnp_poses",
    "project_plumb_bob",
    "half_turn",
    "resolve_board_flips",
]
