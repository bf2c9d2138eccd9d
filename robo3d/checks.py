"""Input checks shared by the algorithms: each says what it expected and what came.

The library's functions check their arguments at the boundary (``ValueError`` for a
caller's mistake, naming the argument, the expected shape and dtype and what was
given); the checks more than one module needs live here, under public names:

* :func:`check_views`: the per-view inputs of the carvers and the agreement check
  (masks, cameras, rigid ``T_base_camera`` poses), normalised to lists and an
  ``(N, 4, 4)`` array;
* :func:`check_choice` and :func:`check_min_views`: a policy string among its values,
  a vote count ``k >= 1``;
* :func:`check_grid` and :func:`check_carve_inputs`: a :class:`~robo3d.grid.VoxelGrid`,
  and everything the carvers (dense and octree) check alike;
* :func:`check_points`: an ``(N, 3)`` float64 array of points;
* :func:`check_mesh`: a triangle mesh (finite vertices, faces that index them);
* :func:`check_transform`: a finite ``(4, 4)`` transform, or a batch of them;
* :func:`check_region`: an optional ``(box_min, box_max)`` pair (a box that must be
  given and finite, as the carving box, is :func:`robo3d.grid.check_box`).

Errors about the *data* (a recording, a silhouette that cannot place a box) are
robo3d's own (:mod:`robo3d.errors`) and are raised where the data is understood.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .camera import CameraModel
from .errors import StageError
from .grid import VoxelGrid

__all__ = ["check_views", "check_choice", "check_min_views", "check_points", "check_region",
           "check_mesh", "check_transform", "check_grid", "check_carve_inputs", "POLICIES"]

#: The carvers' policies for a voxel outside a view's image or behind its camera.
POLICIES = ("keep", "carve")


def check_views(masks: object, cameras: CameraModel | Sequence[CameraModel],
                T_base_cameras: object, *, need_masks: bool = True
                ) -> tuple[list[np.ndarray], list[CameraModel], np.ndarray]:
    """The per-view inputs as lists of masks and cameras and an (N, 4, 4) pose array.

    Parameters
    ----------
    masks : sequence of N (H, W) bool, or one (H, W) bool
        Each sized as its camera (ignored with ``need_masks=False``).
    cameras : CameraModel or sequence of N
        One camera for every view, or one per view.
    T_base_cameras : (N, 4, 4) or (4, 4) float64
        Rigid camera poses (rotation orthonormal to 1e-6).
    need_masks : bool
        False: check the cameras and poses only (the masks come back empty).

    Returns
    -------
    masks : list of N (H, W) bool
    cameras : list of N CameraModel
    T_base_cameras : (N, 4, 4) float64

    Raises
    ------
    ValueError
        A shape, dtype or count that does not match, a non-finite or non-rigid pose.
    """
    T = np.asarray(T_base_cameras, dtype=np.float64)
    if T.ndim == 2:
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"T_base_cameras must be (N, 4, 4), got {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError("T_base_cameras has non-finite values")
    R = T[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2)) if len(T) else []
    bad = np.flatnonzero(np.asarray(err) > 1e-6)
    if bad.size:
        raise ValueError(f"T_base_cameras[{bad[0]}] is not a rigid transform (its rotation "
                         f"is off orthonormal by {err[bad[0]]:.2g})")
    n = T.shape[0]
    if isinstance(cameras, CameraModel):
        cams = [cameras] * n
    else:
        cams = list(cameras)
        if len(cams) != n:
            raise ValueError(f"got {len(cams)} cameras for {n} poses")
        for c in cams:
            if not isinstance(c, CameraModel):
                raise ValueError(f"cameras must be CameraModel, got {type(c).__name__}")
    ms: list[np.ndarray] = []
    if need_masks:
        if isinstance(masks, np.ndarray) and masks.ndim == 2:
            masks = [masks]
        ms = [np.asarray(m) for m in masks]  # type: ignore[union-attr]
        if len(ms) != n:
            raise ValueError(f"got {len(ms)} masks for {n} poses")
        for i, (m, c) in enumerate(zip(ms, cams, strict=True)):
            if m.dtype != np.bool_ or m.shape != (c.height, c.width):
                raise ValueError(f"mask {i} must be ({c.height}, {c.width}) bool (camera "
                                 f"{c.frame_id!r}), got {tuple(m.shape)} {m.dtype}")
    return ms, cams, T


def check_choice(name: str, value: object, allowed: Sequence[str] = POLICIES) -> str:
    """``value`` when it is one of ``allowed`` (default: the carvers' :data:`POLICIES`),
    else ``ValueError`` naming ``name``."""
    if value not in allowed:
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}")
    return value  # type: ignore[return-value]


def check_min_views(k: object, name: str = "min_views_background") -> int:
    """A vote count: an integer ``>= 1`` (bools refused), as int."""
    if isinstance(k, bool) or int(k) != k or k < 1:  # type: ignore[call-overload]
        raise ValueError(f"{name} must be an integer >= 1, got {k!r}")
    return int(k)


def check_points(points: object, name: str = "points") -> np.ndarray:
    """Points as an ``(N, 3)`` float64 array; ``ValueError`` naming ``name`` otherwise."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got {p.shape}")
    return p


def check_mesh(vertices: object, faces: object) -> tuple[np.ndarray, np.ndarray]:
    """Validate a triangle mesh: ``(V, 3)`` finite float64 vertices and ``(F, 3)`` int64
    faces that index them (an empty face list is ``(0, 3)``); ``ValueError`` otherwise."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {v.shape}")
    if f.size == 0:
        f = np.zeros((0, 3), dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
        raise ValueError(f"faces must be (F, 3) integer, got {f.shape} {f.dtype}")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"faces index vertices {f.min()}..{f.max()} of {len(v)}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices contain non-finite values")
    return v, f.astype(np.int64)


def check_transform(t: object, name: str, batch: bool = False) -> np.ndarray:
    """A rigid transform as a finite ``(4, 4)`` float64 array (or ``(F, 4, 4)`` with
    ``batch``); ``ValueError`` naming ``name`` otherwise."""
    t = np.asarray(t, dtype=np.float64)
    ok = t.shape == (4, 4) or (batch and t.ndim == 3 and t.shape[1:] == (4, 4))
    if not ok:
        want = "(4, 4) or (F, 4, 4)" if batch else "(4, 4)"
        raise ValueError(f"{name} must be {want} float, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name} has non-finite entries")
    return t


def check_region(region: object, name: str = "region"
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """An optional axis-aligned box ``(box_min (3,), box_max (3,))`` with ``max > min``
    (unlike :func:`robo3d.grid.check_box`, a side may be infinite: "everything above the
    floor"); None stays None (no region: everything counts)."""
    if region is None:
        return None
    lo, hi = (np.asarray(r, dtype=np.float64) for r in region)  # type: ignore[union-attr]
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
        raise ValueError(f"{name} must be (box_min (3,), box_max (3,)) with max > min, got "
                         f"{lo} and {hi}")
    return lo, hi


def check_grid(grid: object) -> VoxelGrid:
    """``grid`` when it is a :class:`~robo3d.grid.VoxelGrid`, else ``ValueError``."""
    if not isinstance(grid, VoxelGrid):
        raise ValueError(f"grid must be a VoxelGrid, got {type(grid).__name__}")
    return grid


def check_carve_inputs(grid: object, masks: object,
                       cameras: CameraModel | Sequence[CameraModel], T_base_cameras: object,
                       *, outside_image: str, behind_camera: str, min_views_background: object
                       ) -> tuple[int, list[np.ndarray], list[CameraModel], np.ndarray]:
    """What every carver checks: the policies (:data:`POLICIES`), the grid, ``k`` and the
    views (:func:`check_views`); at least one view (else
    :class:`~robo3d.errors.StageError`).

    Returns
    -------
    k : int
    masks, cameras, T_base_cameras
        As :func:`check_views`.
    """
    check_choice("outside_image", outside_image)
    check_choice("behind_camera", behind_camera)
    check_grid(grid)
    k = check_min_views(min_views_background)
    ms, cams, T = check_views(masks, cameras, T_base_cameras)
    if T.shape[0] == 0:
        raise StageError("carving needs at least one view, got none")
    return k, ms, cams, T
