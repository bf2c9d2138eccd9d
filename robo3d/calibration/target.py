"""The calibration target (a checkerboard) and its detection in images.

A calibration recording names its target in the metadata record ``robo3d.target``
(``recording-format.md``): ``type = checkerboard``, ``cols`` and ``rows`` inner corners,
``square`` in metres, and ``moving = true`` when the board is moved in front of a fixed
camera instead of standing still in ``base``.

The board frame (``target``)
----------------------------
Corner ``k = r * cols + c`` (row ``r`` in ``0..rows-1``, column ``c`` in ``0..cols-1``) is at
``(c * square, r * square, 0)``: the origin is an inner corner, ``x`` runs along the
``cols`` corners of a row, ``y`` along the rows, and ``z = x × y`` points *into* the board,
away from a camera that sees its printed side (as OpenCV's own board frames do). The
squares: the square between corners ``(c, r)`` and ``(c + 1, r + 1)`` is dark when
``c + r`` is even, so the square diagonally outside corner 0 (``c = r = -1``) is dark too.

Corner order: every view in the same order
------------------------------------------
OpenCV's detectors do not agree on where they start: the classic detector and the
sector-based one (``findChessboardCornersSB``) return the same board from opposite
corners (measured on ``rwhe_kuka1``), and either may run a row backwards. The corners of
every detection are therefore put into one canonical order, in two steps, both
vectorised over the grid:

1. *Handedness.* The board's ``x`` and ``y`` directions in the image (mean steps along a
   row and along a column) must turn like the image's ``u`` and ``v`` (positive 2-D
   cross product): ``z`` then points away from the camera. Otherwise the rows are
   reversed.
2. *The 180° turn.* A board with ``cols + rows`` odd (``rwhe_kuka1``: 28 x 17) is not
   symmetric under a half turn: the squares that must be dark by the colour rule
   above are compared with the others (mean grey value at the centres of the inner
   squares, each the mean of its four corners); if they are brighter, the order is turned
   by 180°. This is a property of the physical board, so it holds for any viewpoint.
   A board with ``cols + rows`` even (``srv``: 8 x 6) looks the same after a half turn;
   there the choice is made in the image: the board's ``x`` axis points to the image's
   right (``u`` component of the mean row step ≥ 0). Two views of such a board rolled
   by more than 90° against each other get frames turned by 180° against each other;
   for intrinsics and for the laser sheet (the board's plane) that does not matter; for
   a static board's hand-eye :func:`robo3d.calibration.handeye.resolve_board_flips`
   turns such views back to the first view's reading (the flange and the camera must
   rotate by the same angle between two views). Boards with ``cols + rows`` odd need
   none of this.

Square boards (``cols == rows``) also allow a quarter turn and are refused.

Detection
---------
The classic detector (``findChessboardCorners`` with adaptive threshold and image
normalisation) runs on the image downscaled so that its longer side is at most
``detect_max_side_px`` (fast on 2-megapixel images: 40 ms on kuka_1's 1928 x 1208); when
it fails, OpenCV's sector-based detector (``findChessboardCornersSB``, exhaustive,
accuracy mode; Duda & Frese 2018) runs on the same image. The corners are then refined
at full resolution (``corner_refine``): ``sb`` runs the sector-based detector in its
accuracy mode on a crop around the board (two squares of margin) and keeps its corners
where it finds the same grid (each within a third of the spacing of the first
detection's); elsewhere, and with ``subpix``, ``cornerSubPix`` with a window half-size
of ``0.4`` of the smallest corner spacing in pixels (at most ``subpix_max_window_px``),
so it never reaches a neighbouring corner. ``sb`` is the default because it is more
precise, measured: on rendered boards 0.023 against 0.036 px RMS corner error (both
unbiased); calibrateCamera's RMS on kuka_1 0.074 against 0.109 px (OpenCV's README run:
0.117 px), on srv 0.133 against 0.140 px on the same 142 views. It costs time: 0.6 s per
kuka_1 view against 0.05 s. ``BoardDetection.method`` says which ran: ``"classic+sb"``,
``"classic+subpix"``, ``"sb+sb"``, ``"sb+subpix"``.

A view is bad, with a reason, when: no board is found (``"not found"``, with
``"blurred: ..."`` when the image's Laplacian variance is below ``blur_laplacian_var``);
the board's edges are wider than ``max_edge_width_px`` (OpenCV's
``estimateChessboardSharpness``: ``"blurred: ..."``); corners lie within the refinement
window of the image border (``"partial board: ..."``); the corner grid is not a smooth
grid (the second difference of neighbouring corners exceeds ``max_grid_bend`` of their
spacing: ``"corner grid inconsistent: ..."``, a mis-ordered or merged detection); or the
grid folds over (``"corner order flipped: ..."``, steps of opposite handedness in one view).

References
----------
Zhang, Z. "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000.
Duda, A., Frese, U. "Accurate Detection and Localization of Checkerboard Corners for
Calibration", BMVC 2018 (``findChessboardCornersSB``).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..errors import RecordingError
from ..options import Options

__all__ = [
    "Target",
    "BoardDetection",
    "DetectOptions",
    "target_from_recording",
    "board_points",
    "detect_board",
    "detect_boards",
    "to_gray8",
]

_log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Target:
    """A checkerboard.

    Parameters
    ----------
    cols, rows : int
        Inner corners along a row (OpenCV's pattern width) and along a column.
    square : float, metres
        Side of a square.
    moving : bool
        True when the board is moved in front of a fixed camera (no hand-eye).
    """

    cols: int
    rows: int
    square: float
    moving: bool = False

    def __post_init__(self) -> None:
        if int(self.cols) != self.cols or int(self.rows) != self.rows:
            raise ValueError(f"cols and rows must be integers, got {self.cols}, {self.rows}")
        if self.cols < 2 or self.rows < 2:
            raise ValueError(f"a checkerboard needs at least 2 x 2 inner corners, got "
                             f"{self.cols} x {self.rows}")
        if self.cols == self.rows:
            raise ValueError(f"square boards ({self.cols} x {self.rows} inner corners) allow "
                             f"a quarter turn of the corner order; use cols != rows")
        if not (np.isfinite(self.square) and self.square > 0):
            raise ValueError(f"square must be a positive length in metres, got {self.square}")

    @property
    def n_corners(self) -> int:
        """``cols * rows``."""
        return int(self.cols * self.rows)

    @property
    def symmetric(self) -> bool:
        """True when the board looks the same after a half turn (``cols + rows`` even)."""
        return (self.cols + self.rows) % 2 == 0


@dataclasses.dataclass(frozen=True)
class DetectOptions(Options):
    """Board detection's parameters (config section ``calibration``).

    Attributes
    ----------
    detect_max_side_px : int, pixels
        The search runs on the image downscaled to this longer side (refinement at full size).
    subpix_max_window_px : int, pixels
        Largest half-size of ``cornerSubPix``'s window.
    max_edge_width_px : float, pixels
        A board whose edges (``estimateChessboardSharpness``) are wider is blurred.
    blur_laplacian_var : float
        Below this Laplacian variance an image where no board was found is called blurred.
    max_grid_bend : float
        Largest second difference of neighbouring corners, as a fraction of their spacing.
    corner_refine : {"sb", "subpix"}
        Full-resolution refinement: the sector-based detector's accuracy mode on a crop
        around the board (falls back to ``cornerSubPix`` where it fails), or ``cornerSubPix``.
    """

    section = "calibration"

    detect_max_side_px: int = 1280
    subpix_max_window_px: int = 11
    max_edge_width_px: float = 8.0
    blur_laplacian_var: float = 20.0
    max_grid_bend: float = 0.25
    corner_refine: str = "sb"


@dataclasses.dataclass(frozen=True)
class BoardDetection:
    """One view's detection.

    Attributes
    ----------
    corners : (N, 2) float64 pixels or None
        In the order of :func:`board_points`; None when the view is bad.
    method : str
        Search detector and refinement, ``"classic+sb"``, ``"classic+subpix"``,
        ``"sb+sb"``, ``"sb+subpix"``, or ``""`` (nothing found).
    reason : str
        Empty for a good view, otherwise why it is bad.
    sharpness : float, pixels
        Mean width of the board's edges (``estimateChessboardSharpness``; nan if not found).
    laplacian_var : float
        Variance of the image's Laplacian (a global focus measure).
    """

    corners: np.ndarray | None
    method: str
    reason: str
    sharpness: float = float("nan")
    laplacian_var: float = float("nan")

    @property
    def ok(self) -> bool:
        """True when the view has corners and no reason against it."""
        return self.corners is not None and not self.reason


def target_from_recording(recording: Any) -> Target:
    """The board described by a recording's ``robo3d.target`` metadata.

    Parameters
    ----------
    recording : robo3d.recording.model.Recording

    Raises
    ------
    RecordingError
        Missing record, unsupported type, or bad ``cols``/``rows``/``square``/``moving``,
        naming the file.
    """
    path = getattr(recording, "path", None)
    meta = getattr(recording, "metadata", {}).get("robo3d.target")
    if meta is None:
        raise RecordingError("no metadata record robo3d.target: a calibration recording must "
                             "name its target (type, cols, rows, square)", path=path)
    kind = meta.get("type", "checkerboard")
    if kind != "checkerboard":
        raise RecordingError(f"metadata robo3d.target: type {kind!r} is not supported "
                             f"(checkerboard only)", path=path)
    try:
        cols, rows = int(meta["cols"]), int(meta["rows"])
        square = float(meta["square"])
    except KeyError as exc:
        raise RecordingError(f"metadata robo3d.target lacks {exc.args[0]!r} (has "
                             f"{sorted(meta)})", path=path) from None
    except ValueError as exc:
        raise RecordingError(f"metadata robo3d.target: cols/rows must be integers and square "
                             f"a number in metres ({exc})", path=path) from None
    moving_s = str(meta.get("moving", "false")).strip().lower()
    if moving_s not in ("true", "false", "1", "0", "yes", "no"):
        raise RecordingError(f"metadata robo3d.target: moving must be true or false, got "
                             f"{meta['moving']!r}", path=path)
    try:
        return Target(cols, rows, square, moving_s in ("true", "1", "yes"))
    except ValueError as exc:
        raise RecordingError(f"metadata robo3d.target: {exc}", path=path) from None


def board_points(target: Target) -> np.ndarray:
    """The board's inner corners in the target frame, in detection order.

    Returns
    -------
    (cols * rows, 3) float64, metres
        Corner ``r * cols + c`` at ``(c * square, r * square, 0)``.
    """
    r, c = np.mgrid[0:target.rows, 0:target.cols]
    return np.stack([c.ravel() * target.square, r.ravel() * target.square,
                     np.zeros(target.n_corners)], axis=1).astype(np.float64)


def to_gray8(image: np.ndarray) -> np.ndarray:
    """An ``(H, W)`` uint8 grey image from grey or RGB, uint8 or uint16."""
    import cv2

    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    elif img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got {img.shape} {img.dtype}")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise ValueError(f"image must be uint8 or uint16, got {img.dtype}")
    return np.ascontiguousarray(img)


def _canonical(grid: np.ndarray, gray: np.ndarray, target: Target) -> tuple[np.ndarray, str]:
    """Corners ``(rows, cols, 2)`` put in the canonical order (module docstring), and a
    reason string when the grid folds over (empty otherwise)."""
    sx = grid[:, 1:] - grid[:, :-1]          # steps along a row (board x)
    sy = grid[1:, :] - grid[:-1, :]          # steps along a column (board y)
    # handedness per cell from the two steps at its first corner
    cross = sx[:-1, :, 0] * sy[:, :-1, 1] - sx[:-1, :, 1] * sy[:, :-1, 0]
    pos = np.count_nonzero(cross > 0)
    neg = np.count_nonzero(cross < 0)
    if pos and neg:
        return grid, (f"corner order flipped: {min(pos, neg)} of {cross.size} cells turn the "
                      f"other way (the grid folds over)")
    if neg:
        grid = grid[::-1]
    if not target.symmetric:
        # grey value at the inner squares' centres; dark where (c + r) is even
        centres = 0.25 * (grid[:-1, :-1] + grid[:-1, 1:] + grid[1:, :-1] + grid[1:, 1:])
        h, w = gray.shape
        u = np.clip(np.rint(centres[..., 0]).astype(int), 0, w - 1)
        v = np.clip(np.rint(centres[..., 1]).astype(int), 0, h - 1)
        g = gray[v, u].astype(np.float64)
        r, c = np.mgrid[0:target.rows - 1, 0:target.cols - 1]
        dark = (r + c) % 2 == 0
        if g[dark].mean() > g[~dark].mean():
            grid = grid[::-1, ::-1]
    else:
        if np.mean(grid[:, 1:, 0] - grid[:, :-1, 0]) < 0:
            grid = grid[::-1, ::-1]
    return grid, ""


def _grid_bend(grid: np.ndarray) -> float:
    """Largest second difference of neighbouring corners over their mean spacing."""
    d2 = []
    if grid.shape[1] >= 3:
        d2.append(np.linalg.norm(grid[:, 2:] - 2 * grid[:, 1:-1] + grid[:, :-2], axis=-1).ravel())
    if grid.shape[0] >= 3:
        d2.append(np.linalg.norm(grid[2:] - 2 * grid[1:-1] + grid[:-2], axis=-1).ravel())
    if not d2:
        return 0.0
    sx = np.linalg.norm(grid[:, 1:] - grid[:, :-1], axis=-1)
    sy = np.linalg.norm(grid[1:] - grid[:-1], axis=-1)
    spacing = min(float(np.median(sx)), float(np.median(sy)))
    return float(np.max(np.concatenate(d2)) / max(spacing, 1e-9))


def _refine_sb(gray: np.ndarray, pts: np.ndarray, spacing: float,
               target: Target) -> np.ndarray | None:
    """The corners found again by the sector-based detector in full resolution on a crop
    around the first detection (its accuracy mode: Duda & Frese 2018), as a
    ``(rows, cols, 2)`` grid in the first detection's order; None when it fails there or
    disagrees with the first detection by more than a third of the corner spacing."""
    import cv2

    h, w = gray.shape
    m = 2.0 * spacing
    x0 = max(0, int(np.floor(pts[:, 0].min() - m)))
    y0 = max(0, int(np.floor(pts[:, 1].min() - m)))
    x1, y1 = (min(w, int(np.ceil(pts[:, 0].max() + m)) + 1),
              min(h, int(np.ceil(pts[:, 1].max() + m)) + 1))
    crop = np.ascontiguousarray(gray[y0:y1, x0:x1])
    ok, found = cv2.findChessboardCornersSB(crop, (int(target.cols), int(target.rows)),
                                            flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    if not ok or found is None or len(found) != target.n_corners:
        return None
    ref = found.reshape(-1, 2).astype(np.float64) + np.array([x0, y0])
    # the same corner for each index: nearest of the first detection's corners
    d2 = np.sum((pts[:, None, :] - ref[None, :, :]) ** 2, axis=-1)
    nearest = np.argmin(d2, axis=1)
    if (len(np.unique(nearest)) != len(pts)
            or np.sqrt(d2[np.arange(len(pts)), nearest].max()) > spacing / 3.0):
        return None
    return ref[nearest].reshape(target.rows, target.cols, 2)


def detect_board(image: np.ndarray, target: Target,
                 options: DetectOptions | None = None) -> BoardDetection:
    """Find the board's inner corners in one image.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8/uint16
        Grey or RGB.
    target : Target
    options : DetectOptions, optional
        Defaults: the schema's.

    Returns
    -------
    BoardDetection
        ``corners`` ``(cols * rows, 2)`` float64 pixels in the order of
        :func:`board_points` (see the module docstring), or None with ``reason`` saying why.
    """
    import cv2

    opts = options or DetectOptions()
    gray = to_gray8(image)
    h, w = gray.shape
    lap_var = float(cv2.Laplacian(gray, cv2.CV_32F).var())
    pattern = (int(target.cols), int(target.rows))
    scale = min(1.0, float(opts.detect_max_side_px) / max(h, w))
    search = gray if scale >= 1.0 else cv2.resize(gray, (max(1, round(w * scale)),
                                                         max(1, round(h * scale))),
                                                  interpolation=cv2.INTER_AREA)
    sx, sy = search.shape[1] / w, search.shape[0] / h
    ok, found = cv2.findChessboardCorners(
        search, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    method = "classic"
    if not ok:
        ok, found = cv2.findChessboardCornersSB(
            search, pattern, flags=cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
        method = "sb"
    if not ok or found is None or len(found) != target.n_corners:
        reason = "not found"
        if lap_var < opts.blur_laplacian_var:
            reason += (f" (blurred: Laplacian variance {lap_var:.1f} < "
                       f"{opts.blur_laplacian_var:g})")
        return BoardDetection(None, "", reason, float("nan"), lap_var)
    pts = found.reshape(-1, 2).astype(np.float64)
    # search-image pixel centres to full-resolution pixel centres
    pts = (pts + 0.5) / np.array([sx, sy]) - 0.5
    grid = pts.reshape(target.rows, target.cols, 2)
    spacing = min(float(np.min(np.linalg.norm(grid[:, 1:] - grid[:, :-1], axis=-1))),
                  float(np.min(np.linalg.norm(grid[1:] - grid[:-1], axis=-1))))
    win = int(max(2, min(opts.subpix_max_window_px, np.floor(0.4 * spacing))))
    grid = None
    if opts.corner_refine == "sb":
        grid = _refine_sb(gray, pts, spacing, target)
        if grid is not None:
            method += "+sb"
    if grid is None:
        crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
        ref = cv2.cornerSubPix(gray, pts.astype(np.float32).reshape(-1, 1, 2), (win, win),
                               (-1, -1), crit).reshape(-1, 2).astype(np.float64)
        grid = ref.reshape(target.rows, target.cols, 2)
        method += "+subpix"
    grid, reason = _canonical(grid, gray, target)
    corners = np.ascontiguousarray(grid.reshape(-1, 2))
    try:
        sharp = float(cv2.estimateChessboardSharpness(
            gray, pattern, corners.astype(np.float32).reshape(-1, 1, 2))[0][0])
    except cv2.error:
        sharp = float("nan")
    if not reason:
        margin = win + 1
        near = ((corners[:, 0] < margin) | (corners[:, 1] < margin)
                | (corners[:, 0] > w - 1 - margin) | (corners[:, 1] > h - 1 - margin))
        bend = _grid_bend(grid)
        if np.any(near):
            reason = (f"partial board: {int(near.sum())} corners within {margin} px of the "
                      f"image border")
        elif bend > opts.max_grid_bend:
            reason = (f"corner grid inconsistent: second difference {bend:.2f} of the corner "
                      f"spacing > {opts.max_grid_bend:g}")
        elif np.isfinite(sharp) and sharp > opts.max_edge_width_px:
            reason = (f"blurred: board edges {sharp:.1f} px wide > {opts.max_edge_width_px:g} "
                      f"px (Laplacian variance {lap_var:.1f})")
    return BoardDetection(corners, method, reason, sharp, lap_var)


def detect_boards(images: Sequence[np.ndarray], target: Target,
                  options: DetectOptions | None = None) -> list[BoardDetection]:
    """:func:`detect_board` for each image (a sequence, or any iterable of images,
    e.g. a generator decoding a recording's views one at a time)."""
    out = [detect_board(img, target, options) for img in images]
    bad = sum(not d.ok for d in out)
    if bad:
        _log.info("board found in %d of %d views", len(out) - bad, len(out))
    return out
