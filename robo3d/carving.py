"""Shape from silhouettes: the workspace box, dense voxel carving and the hull mesh.

Seed §3.1–3.5. A box known to contain the object is divided into voxels; the centre of
every voxel still occupied is projected into each view (eq. 1–2, ``M_i = K [R | t]`` plus
the lens distortion), and the voxel is removed when its pixel lies outside that view's
silhouette (eq. 3–6). Only the survivors of one view are tested against the next (the
seed's "recursive" space carving), so the work shrinks view by view. What is left is the
visual hull sampled at the voxel centres.

Choices where the seed is silent (all written here so that a result can be explained):

* **Grid.** :class:`~robo3d.grid.VoxelGrid` (axis-aligned in ``base``, voxel centres at
  ``origin + voxel_size * (i, j, k)``, see :mod:`robo3d.grid`) is the exchange type of
  every carver: the dense carver here and Szeliski's octree
  (:func:`robo3d.octree.carve_octree`), which reads and writes the same grid at its
  finest level; :func:`carve_visual_hull` selects either.
* **Pixel of a voxel.** A projected point ``(u, v)`` falls in pixel
  ``(floor(u + 0.5), floor(v + 0.5))`` (pixel centres at integers, origin at the centre of
  the top-left pixel; ties round up). It is *in the image* when that pixel exists, i.e.
  ``-0.5 <= u < W - 0.5`` and likewise for ``v``.
* **Outside the image** (``outside_image``): a voxel whose centre projects outside a
  view's image is a configuration choice, never carved by accident: ``"keep"`` (default:
  the view says nothing about it — right when the object may be cut off by the frame) or
  ``"carve"`` (the strict visual hull: the object is fully inside every view).
  A centre further off-axis than the radius where the lens model stays monotonic (see
  :func:`robo3d.camera.distortion_limit_r2`) would fold back to a bogus pixel,
  possibly inside the image; it counts as outside the image.
* **In too few images** (``min_views_in_image``, default 2): under ``"keep"`` a voxel
  that no view has in its image is never tested, and one that a single view has is
  bounded only by that silhouette's cone, at any depth. Such a voxel is not hull
  (:func:`in_enough_images`, after the carve, both methods); with fewer views than
  that, every view must have it. 1 keeps them, the policy's hull as it stands.
* **Behind the camera** (``behind_camera``, ``z <= 0`` in the camera frame): no ray of the
  view passes through it, so the strict visual hull excludes it: ``"carve"`` by default,
  ``"keep"`` on request. Counted separately from ``outside_image``.
* **Memory.** Carving runs over chunks of the grid (``chunk_voxels`` voxels each); inside
  a chunk it goes view by view over the survivors. The result is the same as view by
  view over the whole grid; the peak memory is a few hundred bytes per chunk voxel.
* **Mesh.** :func:`hull_to_mesh` runs marching cubes at level 0.5 on the occupancy,
  padded with empty voxels (so the surface closes) and lightly Gaussian-smoothed (so the
  staircase becomes a smooth surface rather than a field of cube faces). It uses the
  classic (Lorensen) case table of scikit-image, not its Lewiner variant (which makes
  non-manifold edges where voxels touch along an edge).
* **Options.** :class:`CarveOptions` (method, leaf rule, threads, policies, ``k``) and
  :class:`AgreementOptions` (the ``qa_*`` thresholds) are made from the config's
  ``carving`` section by name (:mod:`robo3d.options`).
* **Resolution** (eq. 7–8): the voxel size against the pixel footprint ``w / f`` at the
  grid centre's depth in each view; voxels finer than the best view resolves are flagged.
* **k of n** (``min_views_background``): the seed's hull removes a voxel as soon as one
  view sees background there, so one bad mask carves the object away. With ``k > 1`` a
  voxel goes only when ``k`` views vote so (a vote is what the policies call carving:
  background, or outside the image / behind the camera when those carve); ``k = 1`` is
  the seed's hull and the default.
* **Agreement of the views** (:func:`view_agreement`, :func:`flag_disagreeing_views`):
  the seed assumes every silhouette is right. Before the carve, each view's mask is
  compared with the hull of the *other* views projected into it (leave one out, on a
  coarse grid): the fraction of the projected hull the mask misses (it would carve that
  away) and the fraction of the mask outside it (spurious foreground). The projection
  is compared only inside the view's own image (an object cut off by the frame is no
  disagreement), and only where enough other views saw the space (a region few views
  see, e.g. beyond most frames under ``outside_image="keep"``, has a fat hull and is
  left unscored). The others' hull is never tighter than the object and is loose where
  few views see a thin wall or a concavity, so a mask that misses part of it is flagged
  only when its carving also costs other views' silhouettes their hull (their pixels
  left with no voxel on the ray: it cut the object, not the hull's excess) or its
  foreground also lies outside it. Views past the thresholds are flagged and left out
  of the carve.

References
----------
R. Szeliski, "Rapid octree construction from image sequences", CVGIP: Image
Understanding 58(1), 1993. A. Laurentini, "The visual hull concept for silhouette-based
image understanding", IEEE PAMI 16(2), 1994. W. E. Lorensen and H. E. Cline, "Marching
cubes", SIGGRAPH 1987.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from .camera import CameraModel, distortion_limit_r2, pixel_rays, project_points
from .checks import check_carve_inputs, check_choice, check_grid, check_min_views, check_views
from .errors import StageError
from .grid import VoxelGrid, carve_counts, make_grid, shell_voxels
from .octree import carve_octree
from .options import Options
from .transforms import invert_transform

__all__ = [
    "VoxelGrid",  # re-exported: its home is robo3d.grid
    "make_grid",  # likewise
    "box_from_silhouettes",
    "laser_box",
    "share_under",
    "support_height",
    "carve_dense",
    "carve_visual_hull",
    "CarveOptions",
    "AgreementOptions",
    "CARVING_METHODS",
    "hull_to_mesh",
    "view_agreement",
    "flag_disagreeing_views",
    "outside_silhouettes",
    "resolution_report",
]

_log = logging.getLogger(__name__)

#: Accepted values of ``method`` in :func:`carve_visual_hull`.
CARVING_METHODS = ("octree", "dense")


# ---------------------------------------------------------------------- the box
def hull_box(hull: VoxelGrid, margin: float = 0.05, min_margin_m: float = 0.002
             ) -> tuple[np.ndarray, np.ndarray] | None:
    """The bounding box of a visual hull's occupied voxels (their outer faces), grown on
    every side by ``margin`` times its largest side, at least ``min_margin_m``: a
    workspace box for a recording without one. None when the hull is empty.

    The hull contains the object wherever the silhouettes do, and its box is more
    forgiving still (a view whose mask misses a thin part cuts the hull, not the box
    around the other views' extent). Where no view sees under the object the hull runs
    down to the carving box's floor, so the box's floor lies at or below the table."""
    if not np.isfinite(margin) or margin < 0 or not np.isfinite(min_margin_m) or \
            min_margin_m < 0:
        raise ValueError(f"margin and min_margin_m must be >= 0, got {margin}, {min_margin_m}")
    bounds = hull.occupied_bounds
    if bounds is None:
        return None
    lo, hi = bounds
    grow = max(float(margin) * float((hi - lo).max()), float(min_margin_m))
    return lo - grow, hi + grow


def hull_pieces(occupancy: np.ndarray, min_fraction: float = 0.01) -> dict[str, Any]:
    """The hull's 26-connected pieces (``scipy.ndimage.label``).

    Parameters
    ----------
    occupancy : (X, Y, Z) bool
        The carved grid's occupied voxels.
    min_fraction : float
        A piece counts in ``n_over_min`` when it holds at least this share of them.

    Returns
    -------
    dict
        ``n`` (pieces), ``largest_fraction`` (the largest piece's share of the occupied
        voxels, None for an empty grid) and ``n_over_min``.

    Notes
    -----
    Silhouettes of one object carve one piece, or one with specks beside it (20 of the
    24 hulls of stop 62's random scenes: a largest share of 0.991-1.00; the real
    templeSparseRing 1.00), or with a part that few views see (the real DTU scan 24,
    views from above only: 0.92 and 0.07). Masks that disagree about the object's shape,
    each taking other parts of the background, carve it into shards: random scene 784
    (a grey checker block on a checker table, views only, no box) 53 pieces, the
    largest 20 % (volume IoU with the object 0.06); scenes 773 and 778 0.63 and 0.66
    (0.20, 0.43); scene 769 0.78 (0.79).
    """
    _, sizes = _voxel_pieces(np.asarray(occupancy, dtype=bool))
    if not len(sizes):
        return {"n": 0, "largest_fraction": None, "n_over_min": 0}
    total = float(sizes.sum())
    return {"n": len(sizes), "largest_fraction": float(sizes.max() / total),
            "n_over_min": int(np.count_nonzero(sizes >= min_fraction * total))}


def _voxel_pieces(occ: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 26-connected pieces of a boolean grid: (labels, 0 outside and 1..n in the
    pieces; the voxel count of pieces 1..n)."""
    from scipy import ndimage

    labels, n = ndimage.label(occ, structure=np.ones((3, 3, 3), dtype=bool))
    return labels, np.bincount(labels.reshape(-1), minlength=n + 1)[1:]


def reference_box(grid: VoxelGrid, masks: Sequence[np.ndarray],
                  cameras: CameraModel | Sequence[CameraModel], T_base_cameras: np.ndarray,
                  views: Sequence[int], *, margin: float = 0.1, min_seen: float = 0.5
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """The box of the hull that ``views``' silhouettes carve on ``grid``: a box that
    holds the object where those views agree, for segmenting a view that does not.

    The hull is carved (seed §3.1.2, every voxel kept outside a view's image) by
    ``views`` alone; only the voxels inside the image of at least ``min_seen`` of all
    the views (at least two) count, since voxels beyond most frames are kept for want
    of evidence, not for being object; of those, the largest 26-connected component is
    the object. Its box is grown by ``margin`` (:func:`hull_box`). None when nothing is
    left.
    """
    masks, cams, poses = check_views(masks, cameras, T_base_cameras)
    views = [int(v) for v in views]
    if not views:
        return None
    carved, _ = carve_dense(grid, [masks[v] for v in views], [cams[v] for v in views],
                            poses[views], outside_image="keep", warn=False)
    ijk = np.nonzero(carved.occupancy)
    if not len(ijk[0]):
        return None
    seen = np.zeros(len(ijk[0]), np.int32)
    for cam, T in zip(cams, poses, strict=True):
        seen += _project_indices(ijk, grid, cam, invert_transform(T),
                                 distortion_limit_r2(cam))[1]
    keep = seen >= max(2, int(np.ceil(min_seen * len(cams))))
    occ = np.zeros(grid.shape, bool)
    occ[tuple(a[keep] for a in ijk)] = True
    labels, sizes = _voxel_pieces(occ)
    if not len(sizes):
        return None
    largest = 1 + int(np.argmax(sizes))
    return hull_box(VoxelGrid(grid.origin, grid.voxel_size, labels == largest, grid.frame),
                    margin=margin)


def up_axis(points: np.ndarray, sensor_origins: np.ndarray, *, max_points: int = 20_000
            ) -> tuple[np.ndarray, dict[str, Any]]:
    """The axis of ``base`` that points up, away from the table the object stands on,
    from where the sensors were: ``+z`` (ROS REP 103, every upright robot) unless the
    sensors say otherwise.

    Sensors look at an object on a table from above, never from under the table. ``d``
    is the mean unit direction from each point to the sensor that measured it (at most
    ``max_points`` points, evenly spread). When ``d`` has no upward ``z`` (``d_z <= 0``:
    a robot hanging from the ceiling, ``base`` upside down) or hardly any (``|d_z| <
    0.2``) while another axis holds more than half of it (a converter's world frame with
    ``y`` up), the signed axis nearest ``d`` is up. Otherwise ``+z``: a single sweep
    from one side, low over the table, leans ``d`` toward that side, and is no reason to
    leave the base's own convention.

    Returns
    -------
    up : (3,) float64
        A signed unit axis of ``base``.
    report : dict
        ``up`` (e.g. ``"+z"``), ``sensor_direction`` (``d``), ``how``.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    o = np.asarray(sensor_origins, dtype=np.float64).reshape(-1, 3)
    step = max(1, len(p) // max(1, int(max_points)))
    v = (o - p)[::step]
    norm = np.linalg.norm(v, axis=1)
    v = v[np.isfinite(norm) & (norm > 0)] / norm[np.isfinite(norm) & (norm > 0), None]
    up, how = np.array([0.0, 0.0, 1.0]), "+z: the base frame's convention"
    d = v.mean(axis=0) if len(v) else np.zeros(3)
    k = int(np.argmax(np.abs(d)))
    if len(v) and (d[2] <= 0 or (abs(d[2]) < 0.2 and abs(d[k]) > 0.5)) and abs(d[k]) > 0:
        up = np.sign(d[k]) * np.eye(3)[k]
        how = ("the sensors looked from below the object along base z: the signed axis "
               "nearest their mean direction") if d[2] <= 0 else (
               "the sensors looked level in base z, along another axis from above")
    name = "+-"[int(up.sum() < 0)] + "xyz"[int(np.argmax(np.abs(up)))]
    return up, {"up": name, "sensor_direction": [round(float(x), 4) for x in d],
                "how": how}


def level_rotation(up: np.ndarray) -> np.ndarray:
    """A rotation ``P`` (3 x 3) from ``base`` to a frame whose ``z`` is ``up`` (a signed
    axis keeps axis-aligned boxes axis-aligned): ``P @ up = (0, 0, 1)``."""
    u = np.asarray(up, dtype=np.float64).reshape(3)
    u = u / np.linalg.norm(u)
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    a = a - (a @ u) * u
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(u, a), u])


def turn_box(R: np.ndarray, box: tuple[np.ndarray, np.ndarray]
             ) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box around ``box`` turned by ``R`` (exact for a signed axis
    permutation)."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in box)
    corners = np.array([[(lo, hi)[(i >> j) & 1][j] for j in range(3)] for i in range(8)])
    turned = corners @ np.asarray(R, dtype=np.float64).T
    return turned.min(axis=0), turned.max(axis=0)


def _facing_z(n: np.ndarray, max_tilt_deg: float) -> np.ndarray:
    """Which normals ``(N, 3)`` lie within ``max_tilt_deg`` of ``+z`` or ``-z``."""
    return np.abs(n[:, 2]) >= np.cos(np.radians(max_tilt_deg)) * np.linalg.norm(n, axis=1)


def table_height(points: np.ndarray, normals: np.ndarray, footprint_min: np.ndarray,
                 footprint_max: np.ndarray, *, max_tilt_deg: float = 20.0,
                 bin_m: float = 0.0005, min_points: int = 200) -> float | None:
    """The height (``z`` in ``base``) of the table an object stands on, from the laser
    points beside it: those outside the object's footprint (``footprint_min`` ..
    ``footprint_max`` in ``x``, ``y``), below its top, on a surface facing up or down
    (normal within ``max_tilt_deg`` of ``z``); the most populated ``bin_m`` slab of
    their heights, refined to the median of the points within two bins of it. None when
    fewer than ``min_points`` such points lie in the slab (no table in the laser's view,
    or a base frame whose ``z`` is not vertical)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    lo, hi = np.asarray(footprint_min, float), np.asarray(footprint_max, float)
    outside = ~np.all((p[:, :2] >= lo[:2]) & (p[:, :2] <= hi[:2]), axis=1)
    flat = _facing_z(n, max_tilt_deg)
    z = p[outside & flat & (p[:, 2] < hi[2]), 2]
    if len(z) < min_points:
        return None
    k = np.floor((z - z.min()) / bin_m).astype(np.int64)
    counts = np.bincount(k)
    top = int(np.argmax(counts))
    near = np.abs(k - top) <= 2
    if int(near.sum()) < min_points:
        return None
    return float(np.median(z[near]))


#: a height with more than this share of the laser's points on an object's sides more than
#: 2 mm under it (:func:`share_under`) is no table: nothing stands under the table
TABLE_MAX_SHARE_UNDER = 0.2


def support_height(points: np.ndarray, normals: np.ndarray, *, max_tilt_deg: float = 20.0,
                   bin_m: float = 0.0005, min_points: int = 200, min_share: float = 0.3,
                   below_m: float = 0.002, max_below_share: float = TABLE_MAX_SHARE_UNDER
                   ) -> float | None:
    """The height (``z`` in ``base``) of the table an object stands on, from laser points
    alone (no footprint known): among the points on surfaces facing up or down (normal
    within ``max_tilt_deg`` of ``z``), the ``bin_m`` slabs of their heights that hold at
    least ``min_share`` of the most populated slab's points (and ``min_points``), the
    lowest, refined to the median of the points within two bins of it. The lowest, not
    the most populated: a bracket's plate or a box's lid can hold more of the laser's
    points than the table beside it, never lie below it. None without such a slab, and
    None when more than ``max_below_share`` of all the points lie more than ``below_m``
    under it on surfaces not facing up or down: nothing stands under the table an object
    stands on, so that slab is a lid, a shoulder or a rim seen with no table in the
    laser's view (random scene 579, a vase without a box or views: its top taken for the
    table and 88 % of its points dropped as lying under it, ``benchmarks/README.md``,
    stop 57)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(p), axis=1)
    facing = _facing_z(n, max_tilt_deg)
    z = p[facing & finite, 2]
    if len(z) < min_points:
        return None
    k = np.floor((z - z.min()) / bin_m).astype(np.int64)
    counts = np.bincount(k)
    # a slab and its neighbours: a table tilted by a fraction of a degree spreads over two
    near = np.convolve(counts, np.ones(5, np.int64), mode="same")
    ok = np.flatnonzero(near >= max(min_points, min_share * near.max()))
    if not len(ok):
        return None
    first = int(ok[0])  # the lowest such slab: its most populated bin
    top = first + int(np.argmax(counts[first:first + 5]))
    sel = np.abs(k - top) <= 2
    if int(sel.sum()) < min_points:
        return None
    z0 = float(np.median(z[sel]))
    under = share_under(p, n, z0, max_tilt_deg=max_tilt_deg, below_m=below_m)
    return None if under > max_below_share else z0


def share_under(points: np.ndarray, normals: np.ndarray, z0: float, *,
                max_tilt_deg: float = 20.0, below_m: float = 0.002) -> float:
    """The share of the (finite) points that lie more than ``below_m`` under the height
    ``z0`` on surfaces not facing up or down (normal more than ``max_tilt_deg`` from
    ``z``): an object's sides. Under the table an object stands on it is about 0 (the
    laser sees nothing through the table); under a lid or a shoulder it is most of them."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(p), axis=1)
    if not finite.any():
        return 0.0
    side = finite & ~_facing_z(n, max_tilt_deg)
    return float(np.count_nonzero(side & (p[:, 2] < z0 - below_m))) / float(finite.sum())


def _height_above(p: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """Heights of points ``(N, 3)`` above the plane ``z = a x + b y + c``."""
    return p[:, 2] - (p[:, 0] * coef[0] + p[:, 1] * coef[1] + coef[2])


def _table_plane(p: np.ndarray, n: np.ndarray, tol_m: float = 0.001
                 ) -> tuple[np.ndarray, float] | None:
    """The plane ``z = a x + b y + c`` of the table in one sweep's points (its
    :func:`support_height`, refined by least squares over the up-facing points within
    ``tol_m`` of it, twice), and the robust spread of those points about it (1.4826 x
    their median absolute residual); None without a table."""
    z0 = support_height(p, n)
    if z0 is None:
        return None
    flat = _facing_z(n, 20.0)
    coef = np.array([0.0, 0.0, z0])
    for _ in range(2):
        sel = flat & (np.abs(_height_above(p, coef)) <= tol_m)
        if int(sel.sum()) < 3:
            break
        A = np.c_[p[sel, :2], np.ones(int(sel.sum()))]
        coef = np.linalg.lstsq(A, p[sel, 2], rcond=None)[0]
    res = _height_above(p, coef)
    sel = flat & (np.abs(res) <= tol_m)
    spread = 1.4826 * float(np.median(np.abs(res[sel]))) if sel.any() else 0.0
    return coef, spread


def laser_box(points: np.ndarray, normals: np.ndarray, frames: np.ndarray,
              sweeps: np.ndarray | None = None, *, margin: float = 0.05,
              min_margin_m: float = 0.002, floor_m: float = 0.0005,
              above_table_m: float = 0.001, min_cell_m: float = 0.002,
              max_cell_m: float = 0.008, min_points: int = 50, dense_share: float = 0.2,
              link_share: float = 0.25, object_share: float = 0.05
              ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]] | None:
    """A workspace box for laser points without one and without views: the object the
    laser measured, standing on the table it measured beside it.

    1. The table, in each sweep's own points (a sweep's robot error lifts or tilts its
       table by as much as a millimetre against the others'): the plane through its
       lowest wide horizontal surface (:func:`support_height`, refined by least
       squares). Only points more than ``above_table_m`` (or 5 times the table points'
       spread about their plane) above their sweep's table are the object's candidates.
    2. The candidates are binned into cells of ``max(min_cell_m, 1.5 x`` the profiles'
       spacing ``)`` (:func:`robo3d.fusion.profile_spacing` from ``frames``), so that
       consecutive profiles of a surface touch. A cell is occupied where at least
       ``dense_share`` of a typical point's cell count lies (a surface crosses it), not
       where a few stray points do (the laser's reflections off a glossy object land on
       the table as sparse points above it). The occupied cells are split into
       26-connected components (``scipy.ndimage.label``); the object is the largest
       component over the middle of the table (the median of the table's points) of
       those that hold ``min_points`` and ``object_share`` of the largest one's points
       (a clump of stray points is not the object; small, since the laser's line on a
       wall may hold several times the object's points; the largest of all when none
       is), with any other that has most of its points in its box grown by a quarter (a
       part the laser's gaps cut off): the laser's line on a wall is another component.
    3. The object's points' box, grown by ``margin`` times its largest side (at least
       ``min_margin_m``), its floor ``floor_m`` above the table (the sweeps' median
       height under the box), as a recording's box has it; with no table, ``floor_m``
       under the object's lowest point.

    Parameters
    ----------
    points, normals : (N, 3) float64
        The laser points (and their normals) in ``base``, metres.
    frames : (N,) int
        Each point's laser frame (its profile), for the profiles' spacing.
    sweeps : (N,) int, optional
        Each point's sweep (one sweep when not given).

    Returns
    -------
    (lo, hi, info) or None
        The box and what it was made from (``table_z_m``, ``cell_m``, ``components``,
        ``object_points``, ``candidates``); None when fewer than ``min_points`` points
        are left for the object.
    """
    from scipy import ndimage

    from .fusion import profile_spacing

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(frames).reshape(-1)
    s = np.zeros(len(p), np.int64) if sweeps is None else np.asarray(sweeps).reshape(-1)
    if not (len(p) == len(n) == len(f) == len(s)):
        raise ValueError(f"points, normals, frames and sweeps must have the same length, "
                         f"got {len(p)}, {len(n)}, {len(f)}, {len(s)}")
    finite = np.all(np.isfinite(p), axis=1) & np.all(np.isfinite(n), axis=1)
    p, n, f, s = p[finite], n[finite], f[finite], s[finite]
    cand = np.ones(len(p), bool)
    on_table = np.zeros(len(p), bool)
    planes = {}
    for k in np.unique(s):  # a few sweeps
        m = s == k
        got = _table_plane(p[m], n[m])
        if got is None:
            continue
        coef, spread = got
        planes[int(k)] = coef
        h, cut = _height_above(p[m], coef), max(float(above_table_m), 5.0 * spread)
        cand[m] = h > cut
        on_table[m] = np.abs(h) <= cut
    q, fq = p[cand], f[cand]
    if len(q) < min_points:
        return None
    spacing = profile_spacing([q], [fq[:, None]])
    cell = min(max(float(min_cell_m), 1.5 * spacing if spacing is not None else 0.0),
               float(max_cell_m))
    lo = q.min(axis=0)
    idx = np.floor((q - lo) / cell).astype(np.int64)
    shape = idx.max(axis=0) + 1
    if int(np.prod(shape)) > 200_000_000:  # a scene metres wide at a fine cell: coarser
        cell *= float((np.prod(shape) / 200_000_000) ** (1 / 3)) * 1.01
        idx = np.floor((q - lo) / cell).astype(np.int64)
        shape = idx.max(axis=0) + 1
    shape_t = tuple(int(x) for x in shape)
    flat_idx = np.ravel_multi_index(idx.T, shape_t)
    cells, inv, per_cell = np.unique(flat_idx, return_inverse=True, return_counts=True)
    dense = per_cell >= max(2.0, dense_share * float(np.median(per_cell[inv])))
    occ = np.zeros(shape_t, dtype=bool)
    occ.reshape(-1)[cells[dense]] = True
    labels, n_comp = ndimage.label(occ, structure=np.ones((3, 3, 3), dtype=bool))
    lab = labels.reshape(-1)[flat_idx]
    counts = np.bincount(lab, minlength=n_comp + 1)
    counts[0] = 0
    if n_comp == 0:
        return None
    # the object's core: the largest component over the middle of the table the laser
    # saw (the median of its points: the sweeps are planned around the object, and a
    # turntable turns it about its middle; all the points without a table) of those that
    # could be the object (``min_points`` and a share of the largest: a clump of stray
    # points is not), else the largest. Random scene 868: a sweep saw far more table on
    # one side of the block; 3 strays stood over the table's middle and were taken for
    # the object, not the block's 2,560 points beside it, no box was found, and the whole
    # table was delivered as measured surface. (Not the one nearest the middle: on random
    # scene 479 that is a fragment of the block's 908 points, the largest holds 3,374.)
    c_lo = np.full((n_comp + 1, 2), np.iinfo(np.int64).max, dtype=np.int64)
    c_hi = np.full((n_comp + 1, 2), -1, dtype=np.int64)
    for a in range(2):
        np.minimum.at(c_lo[:, a], lab, idx[:, a])
        np.maximum.at(c_hi[:, a], lab, idx[:, a])
    around = p[on_table] if on_table.any() else p
    mid = np.floor((np.median(around[:, :2], axis=0) - lo[:2]) / cell).astype(np.int64)
    over = np.all((c_lo - 1 <= mid) & (c_hi + 1 >= mid), axis=1)
    over &= counts >= max(float(min_points), float(object_share) * float(counts.max()))
    over[0] = False
    main = int(np.argmax(np.where(over, counts, -1))) if over.any() else int(np.argmax(counts))
    # with the others that have most of their points in its box grown by a quarter of
    # its largest side: the parts that the laser's gaps cut off (a cup's rim from its
    # inside) join; the laser's line on a wall, long and mostly beyond, does not, nor do
    # most of the stray points on the table (a dark marker's edge biases the stripe)
    m_idx = idx[lab == main]
    m_lo, m_hi = m_idx.min(axis=0), m_idx.max(axis=0)
    link = max(2, int(np.ceil(link_share * float((m_hi - m_lo).max() + 1))))
    inside = np.all((idx >= m_lo - link) & (idx <= m_hi + link), axis=1)
    share = np.bincount(lab, weights=inside, minlength=n_comp + 1) / np.maximum(counts, 1)
    member = share >= 0.5
    member[0] = False
    obj = q[member[lab]]
    if len(obj) < min_points:
        return None
    b_lo, b_hi = obj.min(axis=0), obj.max(axis=0)
    grow = max(float(margin) * float((b_hi - b_lo).max()), float(min_margin_m))
    centre = 0.5 * (b_lo + b_hi)
    table = (float(np.median([-_height_above(np.r_[centre[:2], 0.0][None], c)[0]
                              for c in planes.values()])) if planes else None)
    lowest = float(b_lo[2])
    b_lo, b_hi = b_lo - grow, b_hi + grow
    # with no table, the object's lowest point, not a margin below it: nothing measured
    # lies under it, and the table's few points there (a dim table the laser barely saw,
    # too few to be found as one) stay at the floor, where fusion takes up-facing points
    # for the table's and not for measured surface (random scene 579: 107 such points fused
    # as measured surface, 26.8 mm from the vase at the p95)
    b_lo[2] = table + floor_m if table is not None else lowest - floor_m
    info = {"table_z_m": table, "sweeps_with_table": len(planes), "cell_m": cell,
            "components": int(n_comp), "object_components": int(member.sum()),
            "object_points": int(len(obj)), "candidates": int(len(q)), "points": int(len(p))}
    return b_lo, b_hi, info


def box_from_silhouettes(
    silhouettes_centroids_uv: np.ndarray | None,
    masks: Sequence[np.ndarray],
    cameras: CameraModel | Sequence[CameraModel],
    T_base_cameras: np.ndarray,
    margin: float = 0.1,
    *,
    min_ray_angle_deg: float = 5.0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The workspace box from the silhouettes' centroids and extents (seed §3.4).

    The box centre is the least-squares intersection of the rays through the silhouette
    centroids: the point ``p`` minimising ``sum_i |(I - d_i d_i^T)(p - o_i)|^2`` over the
    rays ``o_i + t d_i``. Its half-size: each mask's bounding box is back-projected to
    the plane at the centre's depth in that view; the largest half-extent over the views,
    times ``1 + margin``, gives a cube around the centre.

    Parameters
    ----------
    silhouettes_centroids_uv : (N, 2) float64, pixels, or None
        :attr:`Silhouette.centroid_uv` of each view; None computes them from ``masks``
        (the mean pixel of each).
    masks : sequence of N (H, W) bool
        The silhouettes (for their bounding boxes).
    cameras : CameraModel or sequence of N
    T_base_cameras : (N, 4, 4) float64
        Camera poses in ``base``.
    margin : float
        Relative growth of the half-size (0.1 = 10 %).
    min_ray_angle_deg : float
        Rays closer to parallel than this (the spread angle of the set, equal to the angle
        between the rays for two views) cannot fix a point: error.

    Returns
    -------
    box_min, box_max : (3,) float64, metres, in ``base``
    report : dict
        ``centre``, ``half_size_m``, ``n_views``, ``ray_spread_deg``, ``ray_residual_m``
        (per view: distance of the centre from the view's ray), ``half_extent_m`` (per
        view), ``depth_m`` (per view).

    Raises
    ------
    StageError
        Fewer than 2 views, rays nearly parallel, or a centre behind a camera.
    """
    if not np.isfinite(margin) or margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    ms, cams, T = check_views(masks, cameras, T_base_cameras)
    n = T.shape[0]
    for i, m in enumerate(ms):
        if not m.any():
            raise StageError(f"silhouette {i} is empty: it cannot place the workspace box")
    if silhouettes_centroids_uv is None:
        c_uv = np.array([np.argwhere(m)[:, ::-1].mean(axis=0) for m in ms]).reshape(-1, 2)
    else:
        c_uv = np.asarray(silhouettes_centroids_uv, dtype=np.float64)
    if c_uv.ndim != 2 or c_uv.shape[1] != 2 or not np.all(np.isfinite(c_uv)):
        raise ValueError(f"silhouettes_centroids_uv must be finite (N, 2), got {c_uv.shape}")
    if c_uv.shape[0] != n:
        raise ValueError(f"got {c_uv.shape[0]} centroids for {n} poses")
    if n < 2:
        raise StageError(f"the workspace box needs the silhouettes of at least 2 views, got {n}")

    origins = T[:, :3, 3].copy()
    dirs = np.stack([pixel_rays(c_uv[i], cams[i], T[i])[1] for i in range(n)])
    proj = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # (N, 3, 3)
    A = proj.sum(axis=0)
    b = np.einsum("nij,nj->i", proj, origins)
    eig = np.linalg.eigvalsh(A)
    spread = float(np.degrees(2.0 * np.arcsin(np.sqrt(np.clip(eig[0] / n, 0.0, 1.0)))))
    if spread < min_ray_angle_deg:
        raise StageError(f"the rays through the silhouette centroids of {n} views are nearly "
                         f"parallel (spread {spread:.2f} deg < {min_ray_angle_deg} deg): views "
                         "from more different directions are needed to place the box")
    centre = np.linalg.solve(A, b)
    rel = centre - origins
    t = np.einsum("ni,ni->n", rel, dirs)
    resid = np.linalg.norm(rel - t[:, None] * dirs, axis=1)

    halves = np.zeros(n)
    depths = np.zeros(n)
    for i in range(n):
        t_cb = invert_transform(T[i])
        pc = t_cb[:3, :3] @ centre + t_cb[:3, 3]
        if pc[2] <= 0:
            raise StageError(f"the estimated box centre {centre} lies behind camera {i} "
                             f"({cams[i].frame_id!r}): the views' poses or silhouettes are "
                             "inconsistent")
        depths[i] = pc[2]
        m = ms[i]
        rows = np.flatnonzero(m.any(axis=1))
        cols = np.flatnonzero(m.any(axis=0))
        # pixel edges of the bounding box (pixel centres are integers)
        corners_uv = np.array([[cols[0] - 0.5, rows[0] - 0.5], [cols[-1] + 0.5, rows[0] - 0.5],
                               [cols[0] - 0.5, rows[-1] + 0.5], [cols[-1] + 0.5, rows[-1] + 0.5]])
        d = cams[i].rays(corners_uv)
        p = d / d[:, 2:3] * pc[2]
        halves[i] = float(np.abs(p[:, :2] - pc[:2]).max())
    half = float(halves.max() * (1.0 + margin))
    box_min, box_max = centre - half, centre + half
    report = {
        "centre": centre.tolist(),
        "half_size_m": half,
        "box_min": box_min.tolist(),
        "box_max": box_max.tolist(),
        "n_views": int(n),
        "ray_spread_deg": spread,
        "ray_residual_m": resid.tolist(),
        "half_extent_m": halves.tolist(),
        "depth_m": depths.tolist(),
        "margin": float(margin),
    }
    if resid.max() > half:
        _log.warning("box: the ray of view %d misses the box centre by %.4f m (half size "
                     "%.4f m): poses or silhouettes may be inconsistent",
                     int(resid.argmax()), resid.max(), half)
    _log.info("box: centre %s, half size %.4f m from %d views (ray spread %.1f deg)",
              np.round(centre, 4).tolist(), half, n, spread)
    return box_min, box_max, report


# ---------------------------------------------------------------------- carving
def _project_indices(ijk: tuple[np.ndarray, np.ndarray, np.ndarray], grid: VoxelGrid,
                     camera: CameraModel, T_camera_base: np.ndarray, limit_r2: float):
    """Pixels of voxel centres in one view.

    Returns ``(flat_pixel (N,) int64, in_image (N,) bool, behind (N,) bool)``;
    ``flat_pixel = v * W + u``, meaningful only where ``in_image``.
    """
    R = T_camera_base[:3, :3]
    a = R * grid.voxel_size  # camera coords = a @ ijk + b
    b = R @ grid.origin + T_camera_base[:3, 3]
    i, j, k = ijk
    X = a[0, 0] * i + a[0, 1] * j + a[0, 2] * k + b[0]
    Y = a[1, 0] * i + a[1, 1] * j + a[1, 2] * k + b[1]
    Z = a[2, 0] * i + a[2, 1] * j + a[2, 2] * k + b[2]
    behind = Z <= 1e-12
    Zs = np.where(behind, 1.0, Z)
    x = X / Zs
    y = Y / Zs
    ok = ~behind
    if np.isfinite(limit_r2):
        ok &= x * x + y * y < limit_r2
    if camera.has_distortion:
        xy = camera.distort_normalized(np.stack([x, y], axis=-1))
        x, y = xy[:, 0], xy[:, 1]
    u = np.floor(camera.fx * x + camera.K[0, 1] * y + camera.cx + 0.5)
    v = np.floor(camera.fy * y + camera.cy + 0.5)
    ok &= (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    flat = np.where(ok, v * camera.width + u, 0).astype(np.int64)
    return flat, ok, behind


def carve_dense(
    grid: VoxelGrid,
    masks: Sequence[np.ndarray],
    cameras: CameraModel | Sequence[CameraModel],
    T_base_cameras: np.ndarray,
    *,
    outside_image: str = "keep",
    behind_camera: str = "carve",
    min_views_background: int = 1,
    chunk_voxels: int = 1 << 19,
    warn: bool = True,
) -> tuple[VoxelGrid, dict]:
    """Carve a voxel grid with silhouettes: the visual hull (seed §3.1.2, §3.4, eq. 1–6).

    Every occupied voxel's centre is projected (distortion included) into each view; it
    is removed when its pixel is background in ``min_views_background`` views (1: in any
    view, the seed's exact hull). Views are applied in order to the survivors of the
    previous ones.

    Parameters
    ----------
    grid : VoxelGrid
        The grid to carve (in ``base``); not modified.
    masks : sequence of N (H, W) bool
        Silhouettes, one per view, sized as their camera.
    cameras : CameraModel or sequence of N
    T_base_cameras : (N, 4, 4) float64
        Camera poses in ``base``.
    outside_image : {"keep", "carve"}
        What a view does to a voxel whose centre projects outside its image (see the
        module notes).
    behind_camera : {"carve", "keep"}
        What a view does to a voxel behind its camera.
    min_views_background : int
        ``k``: a voxel is carved when at least ``k`` views vote to carve it (background
        there, or outside the image / behind the camera under a carving policy). 1 is
        the visual hull; ``k > 1`` survives ``k - 1`` views that wrongly carve the
        object away, at the price of a fatter hull where few views disagree.
    chunk_voxels : int
        Voxels per processing chunk (bounds the memory).
    warn : bool
        Warn about views that keep most voxels only because they lie outside the image
        (False where that is expected, as on a box much wider than the views).

    Returns
    -------
    grid : VoxelGrid
        A new grid with the carved occupancy.
    report : dict
        ``voxels_before``, ``voxels_after``, ``volume_m3``, ``time_s``, the policies,
        ``min_views_background``, and ``views``: per view ``tested`` (survivors it saw),
        ``carved`` (voxels this view's vote removed: the ``k``-th vote), ``after``,
        ``votes`` (its votes to carve, those that removed a voxel included),
        ``outside_image`` and ``behind_camera`` (how many tested voxels were so),
        ``kept_outside_image`` and ``kept_behind_camera`` (how many of those the policy
        kept).

    References
    ----------
    R. Szeliski, CVGIP: Image Understanding 58(1), 1993; A. Laurentini, IEEE PAMI 16(2),
    1994.
    """
    if int(chunk_voxels) < 1:
        raise ValueError(f"chunk_voxels must be >= 1, got {chunk_voxels}")
    k_bg, ms, cams, T = check_carve_inputs(grid, masks, cameras, T_base_cameras,
                                           outside_image=outside_image,
                                           behind_camera=behind_camera,
                                           min_views_background=min_views_background)
    n_views = T.shape[0]
    t0 = time.perf_counter()
    T_cb = invert_transform(T)
    limits = [distortion_limit_r2(c) for c in cams]
    flat_masks = [np.ascontiguousarray(m).reshape(-1) for m in ms]
    keep_out = outside_image == "keep"
    keep_behind = behind_camera == "keep"
    counts = np.zeros((len(_DENSE_COUNTS), n_views), dtype=np.int64)
    view_time = np.zeros(n_views)
    occ_in = grid.occupancy.reshape(-1)
    occ_out = np.zeros(occ_in.size, dtype=bool)
    step = int(chunk_voxels)
    for start in range(0, occ_in.size, step):
        idx = start + np.flatnonzero(occ_in[start:start + step])
        idx = _carve_chunk(idx, grid, cams, T_cb, limits, flat_masks, keep_out, keep_behind,
                           k_bg, counts, view_time)
        occ_out[idx] = True

    out = VoxelGrid(grid.origin.copy(), grid.voxel_size, occ_out.reshape(grid.shape),
                    grid.frame)
    tested, carved, n_votes, n_out, n_behind = counts
    views = [{"view": v, "camera": cams[v].frame_id, "tested": int(tested[v]),
              "carved": int(carved[v]), "after": int(tested[v] - carved[v]),
              "votes": int(n_votes[v]), "outside_image": int(n_out[v]),
              "behind_camera": int(n_behind[v]),
              "kept_outside_image": int(n_out[v]) if keep_out else 0,
              "kept_behind_camera": int(n_behind[v]) if keep_behind else 0,
              "time_s": float(view_time[v])} for v in range(n_views)]
    elapsed = time.perf_counter() - t0
    report = {**carve_counts(grid, out), "outside_image": outside_image,
              "behind_camera": behind_camera, "min_views_background": int(k_bg),
              "n_views": int(n_views), "views": views, "time_s": float(elapsed)}
    for v in views if warn else ():
        if v["tested"] and v["kept_outside_image"] > 0.5 * v["tested"]:
            _log.warning("carve: view %d kept %d of %d voxels only because they project "
                         "outside its image", v["view"], v["kept_outside_image"], v["tested"])
    if report["voxels_after"] == 0:
        _log.warning("carve: every voxel was carved (inconsistent silhouettes or poses?)")
    _log.info("carve: %d -> %d voxels (%.3g m^3) with %d views in %.2f s",
              report["voxels_before"], report["voxels_after"], out.volume_m3, n_views, elapsed)
    return out, report


#: The rows of carve_dense's per-view counts (tested, carved, votes, outside the image,
#: behind the camera).
_DENSE_COUNTS = ("tested", "carved", "votes", "outside_image", "behind_camera")


def _carve_chunk(idx: np.ndarray, grid: VoxelGrid, cams: list[CameraModel],
                 T_cb: np.ndarray, limits: list[float], flat_masks: list[np.ndarray],
                 keep_out: bool, keep_behind: bool, k_bg: int, counts: np.ndarray,
                 view_time: np.ndarray) -> np.ndarray:
    """Carve one chunk of the grid (flat voxel indices ``idx``) view by view, each view
    testing the survivors of the previous ones; returns the survivors and adds to
    ``counts`` (rows :data:`_DENSE_COUNTS`, columns views) and ``view_time``."""
    votes = np.zeros(idx.size, dtype=np.int32) if k_bg > 1 else None
    for v in range(len(cams)):
        if idx.size == 0:
            break
        tv = time.perf_counter()
        ijk = np.unravel_index(idx, grid.shape)
        flat, in_img, behind = _project_indices(ijk, grid, cams[v], T_cb[v], limits[v])
        outside = ~in_img & ~behind
        inside_sil = flat_masks[v][flat] & in_img
        keep = inside_sil
        if keep_out:
            keep = keep | outside
        if keep_behind:
            keep = keep | behind
        counts[0, v] += idx.size
        counts[3, v] += int(np.count_nonzero(outside))
        counts[4, v] += int(np.count_nonzero(behind))
        counts[2, v] += idx.size - int(np.count_nonzero(keep))
        if votes is not None:  # k-of-n: carved once k views have voted so
            votes += ~keep
            keep = votes < k_bg
        n_keep = int(np.count_nonzero(keep))
        counts[1, v] += idx.size - n_keep
        if n_keep != idx.size:
            idx = idx[keep]
            if votes is not None:
                votes = votes[keep]
        view_time[v] += time.perf_counter() - tv
    return idx


@dataclass(frozen=True)
class CarveOptions(Options):
    """How the visual hull is carved: the config's ``carving`` keys that
    :func:`carve_visual_hull` uses, under the same names (``CarveOptions.from_config(
    cfg["carving"])``). The section's other keys are the stage's: the grid
    (``resolution``), the box (``box_margin``), the mesh (``smooth_sigma_vox``) and the
    agreement check (:class:`AgreementOptions`).

    Attributes
    ----------
    method : {"octree", "dense"}
        Szeliski's octree (:func:`robo3d.octree.carve_octree`, seed §3.1.1) or the dense
        voxel-by-voxel test (:func:`carve_dense`, seed §3.1.2). With
        ``leaf_rule="centre"`` both give the same occupancy; the octree is far faster.
    leaf_rule : {"centre", "conservative"}
        Octree only (see :func:`robo3d.octree.carve_octree`); the dense method accepts
        only ``"centre"``, the rule it implements.
    threads : int
        Octree only: threads of the compiled kernel (0: all cores); the result does not
        depend on it.
    outside_image, behind_camera : {"keep", "carve"}
        What a view does to a voxel outside its image or behind its camera
        (:func:`carve_dense`), for both methods.
    min_views_background : int
        Votes to carve a voxel (k of n; 1 = the visual hull), for both methods.
    min_views_in_image : int
        Under ``outside_image="keep"``: a voxel that fewer views than this (or than the
        views there are) have in their image, in front of the camera, is not hull
        (:func:`in_enough_images`); 1 keeps the seed's hull as the policy leaves it.
    """

    section = "carving"

    method: str = "octree"
    leaf_rule: str = "centre"
    threads: int = 1
    outside_image: str = "keep"
    behind_camera: str = "carve"
    min_views_background: int = 1
    min_views_in_image: int = 2


@dataclass(frozen=True)
class AgreementOptions(Options):
    """The check of the views against each other before the carve: the config's
    ``carving.qa_*`` keys, under the same names (``AgreementOptions.from_config(
    cfg["carving"])``).

    Attributes
    ----------
    qa_resolution : int
        Voxels along the box's longest side of the check's coarse grid (0: no check).
    qa_max_missing, qa_max_spurious : float
        Flag thresholds of :func:`flag_disagreeing_views`.
    qa_min_unexplained : float
        ``min_unexplained`` of :func:`view_agreement`: a mask missing more than
        ``qa_max_missing`` of the others' hull is flagged only when it also leaves more
        than this fraction of two other views' silhouettes with no hull behind them.
    qa_min_observers : float
        ``min_observers`` of :func:`view_agreement`.
    qa_leave_out : bool
        Whether the flagged views are left out of the carve (the stage's choice).
    """

    section = "carving"

    qa_resolution: int = 64
    qa_max_missing: float = 0.1
    qa_max_spurious: float = 0.1
    qa_min_unexplained: float = 0.05
    qa_min_observers: float = 0.3
    qa_leave_out: bool = True


def carve_visual_hull(
    grid: VoxelGrid,
    masks: Sequence[np.ndarray],
    cameras: CameraModel | Sequence[CameraModel],
    T_base_cameras: np.ndarray,
    options: CarveOptions = CarveOptions(),
) -> tuple[VoxelGrid, dict]:
    """Carve the visual hull with the method the options select.

    Parameters
    ----------
    grid, masks, cameras, T_base_cameras
        As :func:`carve_dense`.
    options : CarveOptions
        The method and its policies.

    Returns
    -------
    grid : VoxelGrid
    report : dict
        The method's report, with ``method`` set.

    References
    ----------
    R. Szeliski, CVGIP: Image Understanding 58(1), 1993.
    """
    o = options
    check_choice("method", o.method, CARVING_METHODS)
    check_min_views(o.min_views_in_image, "min_views_in_image")
    if o.method == "dense":
        if o.leaf_rule != "centre":
            raise ValueError(f"the dense method tests voxel centres only (leaf_rule "
                             f"'centre'), got leaf_rule={o.leaf_rule!r}")
        out, report = carve_dense(grid, masks, cameras, T_base_cameras,
                                  outside_image=o.outside_image, behind_camera=o.behind_camera,
                                  min_views_background=o.min_views_background)
        report = {"method": "dense", **report}
    else:
        out, report = carve_octree(grid, masks, cameras, T_base_cameras,
                                   outside_image=o.outside_image, behind_camera=o.behind_camera,
                                   leaf_rule=o.leaf_rule, threads=o.threads,
                                   min_views_background=o.min_views_background)
    need = min(o.min_views_in_image, int(report["n_views"]))
    if o.outside_image != "keep" or need <= 1 or out.n_occupied == 0:
        return out, report
    seen = in_enough_images(out, cameras, T_base_cameras, need)
    n_before = out.n_occupied
    out.occupancy[out.occupancy] = seen
    removed = n_before - out.n_occupied
    report["in_images"] = {"min_views": need, "removed": int(removed),
                           "removed_fraction": float(removed / n_before),
                           "voxels_after": int(out.n_occupied), "volume_m3": out.volume_m3}
    if removed:
        _log.info("carve: %d of %d voxels (%.1f %%) lie in fewer than %d views' images: not "
                  "hull (no view, or one alone, bounds them)", removed, n_before,
                  100.0 * removed / n_before, need)
    return out, report


def in_enough_images(grid: VoxelGrid, cameras: CameraModel | Sequence[CameraModel],
                     T_base_cameras: np.ndarray, need: int) -> np.ndarray:
    """(N,) bool over the grid's occupied voxels (in ``np.argwhere`` order): whether at
    least ``need`` views have the voxel's centre in their image, in front of the camera
    (the carve's own pixel rule, :func:`_project_indices`).

    Why: under ``outside_image="keep"`` a view says nothing of a voxel outside its
    image, so a voxel inside no image is never tested and one inside a single image is
    bounded by that view's silhouette cone alone, at any depth. Such voxels were hull:
    random scene 552 (a blob, 4 views, no workspace box): 18 % of the hull in no image
    and 12 % in one, fused as slabs up to 11 cm from the object (the mesh's median
    51.6 mm from the truth); DTU scan 24 (49 real views): 16 % of the hull in fewer than
    two images (``benchmarks/README.md``, stop 56)."""
    _, cams, T = check_views(None, cameras, T_base_cameras, need_masks=False)
    ijk = np.nonzero(grid.occupancy)
    count = np.zeros(len(ijk[0]), dtype=np.int32)
    todo = np.arange(len(count))
    for cam, T_cb in zip(cams, invert_transform(T), strict=True):
        if not len(todo):
            break
        _, ok, _ = _project_indices(tuple(a[todo] for a in ijk), grid, cam, T_cb,
                                    distortion_limit_r2(cam))
        count[todo] += ok
        todo = todo[count[todo] < need]
    return count >= need


# ---------------------------------------------------------------------- view agreement
def _voxel_uv(ijk: np.ndarray, grid: VoxelGrid, camera: CameraModel, T_camera_base: np.ndarray,
              limit_r2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel ``u, v`` (N,), depth ``z`` (N,) metres and ``valid`` (N,) bool (in front
    of the camera and inside the lens model's monotonic radius) of voxel centres."""
    pts = grid.index_to_points(ijk)
    pc = pts @ T_camera_base[:3, :3].T + T_camera_base[:3, 3]
    z = pc[:, 2]
    valid = z > 1e-12
    zs = np.where(valid, z, 1.0)
    xy = pc[:, :2] / zs[:, None]
    if np.isfinite(limit_r2):
        valid &= np.einsum("ij,ij->i", xy, xy) < limit_r2
    if camera.has_distortion:
        xy = camera.distort_normalized(xy)
    u = camera.fx * xy[:, 0] + camera.K[0, 1] * xy[:, 1] + camera.cx
    v = camera.fy * xy[:, 1] + camera.cy
    return u, v, z, valid


def _voxel_squares(ijk: np.ndarray, grid: VoxelGrid, camera: CameraModel,
                   T_camera_base: np.ndarray, limit_r2: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Voxel centres as the squares :func:`_splat_voxels` draws: sub-pixel ``u, v``, the
    half side ``half`` (half the voxel's footprint at its depth, pixels) and ``valid``."""
    u, v, z, valid = _voxel_uv(ijk, grid, camera, T_camera_base, limit_r2)
    half = 0.5 * grid.voxel_size * 0.5 * (camera.fx + camera.fy) / np.where(valid, z, 1.0)
    return u, v, half, valid


def _splat_voxels(u: np.ndarray, v: np.ndarray, half_px: np.ndarray, width: int,
                  height: int) -> np.ndarray:
    """Pixels covered by the squares ``[u - h, u + h] x [v - h, v + h]`` (pixel centres at
    integers; at least the pixel of the centre), ``(height, width)`` bool.

    Summed-area splatting: +1/-1 at each square's corners of a difference image, whose
    2-D cumulative sum counts the squares over each pixel (no loop over voxels).
    """
    cu = np.floor(u + 0.5)
    cv = np.floor(v + 0.5)
    u0 = np.minimum(np.ceil(u - half_px), cu)
    u1 = np.maximum(np.floor(u + half_px), cu)
    v0 = np.minimum(np.ceil(v - half_px), cv)
    v1 = np.maximum(np.floor(v + half_px), cv)
    u0 = np.clip(u0, 0, width).astype(np.int64)
    u1 = np.clip(u1 + 1, 0, width).astype(np.int64)
    v0 = np.clip(v0, 0, height).astype(np.int64)
    v1 = np.clip(v1 + 1, 0, height).astype(np.int64)
    ok = (u1 > u0) & (v1 > v0)
    u0, u1, v0, v1 = u0[ok], u1[ok], v0[ok], v1[ok]
    w1 = width + 1
    idx = np.concatenate([v0 * w1 + u0, v0 * w1 + u1, v1 * w1 + u0, v1 * w1 + u1])
    wts = np.concatenate([np.ones(len(u0)), -np.ones(len(u0)), -np.ones(len(u0)),
                          np.ones(len(u0))])
    diff = np.bincount(idx, weights=wts, minlength=(height + 1) * w1)
    diff = diff.astype(np.float32).reshape(height + 1, w1)
    # cv2.integral is the 2-D cumulative sum (with a leading zero row and column); the
    # counts are small integers, exact in float32
    return cv2.integral(diff, sdepth=cv2.CV_32F)[1:height + 1, 1:width + 1] > 0.5


def view_agreement(
    grid: VoxelGrid,
    masks: Sequence[np.ndarray],
    cameras: CameraModel | Sequence[CameraModel],
    T_base_cameras: np.ndarray,
    *,
    reference: Sequence[int] | None = None,
    carve: CarveOptions = CarveOptions(),
    min_observers: float = 0.3,
    min_unexplained: float = 0.05,
    explain_above: float = -1.0,
) -> list[dict]:
    """How well each view's silhouette agrees with the hull of the other views.

    For view ``i``, the reference is the hull carved by the reference views other than
    ``i`` (leave one out; the same ``k``-of-``n`` rule as the carve), sampled at the
    centres of ``grid``'s voxels, projected into view ``i`` (each voxel a square of its
    footprint ``voxel_size * f / depth``) and compared with ``i``'s mask.

    Three kinds of pixel: *hull* (the projection of a voxel the others keep and
    enough of them (``min_observers``) see inside their image), *unknown* (only voxels the
    others keep without seeing them enough: the others say nothing there, e.g. beyond
    their frames under ``outside_image="keep"``) and *empty* (every voxel on the ray is
    carved by the others, or there is none). Unknown pixels are not scored. A mask cut
    off by its own image border is compared only inside the image, so a cut-off object
    is not a disagreement.

    Parameters
    ----------
    grid : VoxelGrid
        The (coarse) grid the reference hulls are carved on; its resolution bounds the
        scores' precision (about half a voxel footprint at every silhouette edge).
    masks, cameras, T_base_cameras
        As :func:`carve_dense`.
    reference : sequence of int, optional
        Views that make the reference hulls (default: all). A view outside it is scored
        against the hull of all the reference views.
    carve : CarveOptions
        The carve's method, policies and ``k`` (the carver of the candidate voxels,
        those with at most ``k`` votes).
    min_observers : float
        Fraction of the other reference views (at least 2 views) that must see a voxel
        in their image for it to count as hull rather than unknown. Where few views see
        a region (the object cut off by most frames, as in DTU), their hull there is
        the intersection of few cones, much fatter than the object: scoring a mask
        against it would call a correct mask "missing". The default 0.3 was chosen on
        DTU scan 24 (the figures: ``benchmarks/README.md``, "Notes moved from
        robo3d/carving.py").
    min_unexplained : float
        ``unexplained_views`` counts the other views that lose more than this fraction
        of their silhouette's pixels (:func:`_unexplained`).
    explain_above : float
        The unexplained pixels are counted only for the views whose
        ``missing_fraction`` exceeds this (default: every view); the others' three
        ``unexplained_*`` values are None.

    Returns
    -------
    list of dict, one per view
        ``view``; ``iou`` (mask against projected hull, on scored pixels);
        ``spurious_fraction`` (of the mask's scored pixels, those farther than
        ``tolerance_px`` from the others' projected hull: foreground the other views rule
        out); ``missing_fraction`` (of the projected hull, the pixels farther than
        ``tolerance_px`` from the mask: object this view would carve away);
        ``tolerance_px`` (one voxel footprint in this view: the grid places no outline
        closer, and a band that thin would dominate small or cut-off silhouettes);
        ``mask_px``, ``hull_px``, ``unknown_px`` (pixel counts). The fractions are None
        when there is nothing to divide (an empty mask, or no hull in view).
        ``unexplained_fraction``, ``unexplained_max``, ``unexplained_views``: what
        this view's carving costs the other reference views' silhouettes (the share of
        their mask pixels left with no hull voxel on their ray, pooled and in the worst
        view, and the views losing more than ``min_unexplained``): zero for a correct
        mask however loose the others' hull, so a mask that only cuts the hull's excess
        is told from one that cuts the object (:func:`_unexplained`).

    Notes
    -----
    One dense pass over the candidate voxels gives every view's votes and observations;
    each leave-one-out hull is then the candidates whose vote count without view ``i``
    stays below ``k``, so the cost is one carve plus one projection per view.
    """
    outside_image = check_choice("outside_image", carve.outside_image)
    behind_camera = check_choice("behind_camera", carve.behind_camera)
    k = check_min_views(carve.min_views_background)
    ms, cams, T = check_views(masks, cameras, T_base_cameras)
    n = T.shape[0]
    ref = np.zeros(n, dtype=bool)
    ref[list(range(n)) if reference is None else [int(r) for r in reference]] = True
    if n == 0 or not ref.any():
        raise StageError("the agreement check needs at least one reference view")
    ref_idx = np.flatnonzero(ref)
    cand, _ = carve_visual_hull(grid, [ms[r] for r in ref_idx], [cams[r] for r in ref_idx],
                                T[ref_idx], CarveOptions(method=carve.method,
                                                         outside_image=outside_image,
                                                         behind_camera=behind_camera,
                                                         min_views_background=k + 1,
                                                         min_views_in_image=1))
    ijk = np.argwhere(cand.occupancy)
    T_cb = invert_transform(T)
    limits = [distortion_limit_r2(c) for c in cams]
    votes, seen = _votes_and_sight(ijk, cand, ms, cams, T_cb, limits, outside_image,
                                   behind_camera)
    ref_votes = votes[ref].sum(axis=0)
    ref_seen = seen[ref].sum(axis=0)
    n_ref = int(ref.sum())
    vol = np.zeros(grid.shape, dtype=bool)
    flat_vol = vol.reshape(-1)
    flat_ijk = np.ravel_multi_index(tuple(ijk.T), grid.shape)
    out = []
    for i in range(n):
        cam = cams[i]
        others_votes = ref_votes - (votes[i] if ref[i] else 0)
        others_seen = ref_seen - (seen[i] if ref[i] else 0)
        need = max(2, int(np.ceil(min_observers * (n_ref - int(ref[i])))))
        kept = others_votes < k
        hull = kept & (others_seen >= need)
        # only the shells project to the outlines: hull pixels are those of the hull's
        # shell, unknown ones those of the shell of all kept voxels not covered by hull
        flat_vol[:] = False
        flat_vol[flat_ijk[hull]] = True
        hull_shell = hull & shell_voxels(vol).reshape(-1)[flat_ijk]
        flat_vol[flat_ijk[kept]] = True
        unknown = kept & ~hull & shell_voxels(vol).reshape(-1)[flat_ijk]
        hull = hull_shell
        sel = np.flatnonzero(hull | unknown)
        u, vv, half, valid = _voxel_squares(ijk[sel], cand, cam, T_cb[i], limits[i])
        h = hull[sel] & valid
        un = unknown[sel] & valid
        hull_px = _splat_voxels(u[h], vv[h], half[h], cam.width, cam.height)
        unk_px = _splat_voxels(u[un], vv[un], half[un], cam.width, cam.height) & ~hull_px
        # disagreement beyond one voxel footprint of the other's edge: the grid cannot
        # place an outline closer, and a thin band would dominate small silhouettes
        tol = int(np.ceil(2.0 * np.median(half[h]))) if h.any() else 1
        out.append({"view": i, **_mask_scores(ms[i], hull_px, unk_px, tol),
                    "reference": bool(ref[i])})
    explain = [s["missing_fraction"] is not None and s["missing_fraction"] > explain_above
               for s in out]
    lost = _unexplained(grid, ms, cams, T_cb, limits, ref, k, outside_image, behind_camera,
                        np.array(explain, dtype=bool), min_unexplained)
    for s, row in zip(out, lost, strict=True):
        s.update(row)
    return out


def _unexplained(grid: VoxelGrid, ms: list[np.ndarray], cams: list[CameraModel],
                 T_cb: np.ndarray, limits: list[float], ref: np.ndarray, k: int,
                 outside_image: str, behind_camera: str, explain: np.ndarray,
                 min_unexplained: float) -> list[dict]:
    """Per view ``i`` with ``explain[i]``: the other views' silhouette pixels that view
    ``i`` leaves with no hull on their ray (``unexplained_fraction``: their share of the
    other reference views' mask pixels; ``unexplained_max``: the largest share in one
    other view; ``unexplained_views``: how many other views lose more than
    ``min_unexplained``). None for the other views.

    The hull never fits a silhouette from inside: whatever the views, it contains the
    object, so every correct mask's pixel has a hull voxel on its ray. A mask that lost
    part of the object carves that part away, and the other views' pixels that saw it
    lose their voxels. A correct mask that carves away the *excess* of the others' hull
    (a thin wall seen edge-on, a cup's opening, few views) leaves every other correct
    mask explained. So this, unlike ``missing_fraction`` (how much of the others'
    projected hull a mask leaves out, which is also the others' hull's excess), tells a
    mask that cuts the object from one that cuts a loose hull.

    On the coarse grid a thin part may fall between voxel centres; the test therefore
    carves with every mask grown by a voxel's half diagonal (at the depth of the box's
    nearer corners, plus a pixel) and counts a mask pixel only farther than one voxel
    footprint (at the box centre's depth) from the hull's projection. A part thinner
    than that goes unseen.
    """
    n = len(ms)
    out: list[dict] = [{"unexplained_fraction": None, "unexplained_max": None,
                        "unexplained_views": None} for _ in range(n)]
    ref_idx = np.flatnonzero(ref)
    if len(ref_idx) < 2 or not explain.any():
        return out
    # each mask grown by a voxel's half diagonal at the box's near depth in its view; the
    # tolerance of a pixel left unexplained: one voxel footprint at the box centre's depth
    corners = grid.index_to_points(np.argwhere(np.ones((2, 2, 2), dtype=bool))
                                   * (np.array(grid.shape) - 1))
    centre = corners.mean(axis=0)
    grown, tol = [], []
    for v in range(n):
        z = corners @ T_cb[v][2, :3] + T_cb[v][2, 3]
        z_near = max(float(np.percentile(z[z > 0], 10)) if (z > 0).any() else 1.0, 1e-3)
        z_mid = max(float(centre @ T_cb[v][2, :3] + T_cb[v][2, 3]), z_near)
        f = 0.5 * (cams[v].fx + cams[v].fy)
        r = int(np.ceil(0.87 * grid.voxel_size * f / z_near)) + 1
        kern = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        grown.append(cv2.dilate(ms[v].view(np.uint8), kern) > 0)
        tol.append(max(1.0, grid.voxel_size * f / z_mid))
    cand, _ = carve_visual_hull(grid, [grown[r] for r in ref_idx], [cams[r] for r in ref_idx],
                                invert_transform(T_cb[ref_idx]),
                                CarveOptions(method="octree", outside_image=outside_image,
                                             behind_camera=behind_camera,
                                             min_views_background=k + 1,
                                             min_views_in_image=1))
    ijk = np.argwhere(cand.occupancy)
    if not len(ijk):
        return out
    votes, _seen = _votes_and_sight(ijk, cand, grown, cams, T_cb, limits, outside_image,
                                    behind_camera)
    ref_votes = votes[ref].sum(axis=0)
    hull = ref_votes < k
    vol = np.zeros(grid.shape, dtype=bool)
    flat = vol.reshape(-1)
    flat_ijk = np.ravel_multi_index(tuple(ijk.T), grid.shape)

    def cover(sel: np.ndarray, v: int) -> np.ndarray:
        """The pixels of view ``v`` that the voxels ``sel`` (bool over ``ijk``) cover."""
        flat[:] = False
        flat[flat_ijk[sel]] = True
        sh = sel & shell_voxels(vol).reshape(-1)[flat_ijk]
        u, vv, half, valid = _voxel_squares(ijk[sh], cand, cams[v], T_cb[v], limits[v])
        return _splat_voxels(u[valid], vv[valid], half[valid], cams[v].width, cams[v].height)

    def lost_pixels(covered: np.ndarray, v: int) -> np.ndarray:
        """Mask pixels of view ``v`` farther than a voxel footprint from ``covered``."""
        if not ms[v].any() or not covered.any():
            return ms[v]
        d = cv2.distanceTransform((~covered).view(np.uint8), cv2.DIST_L2, 3)
        return ms[v] & (d > tol[v])

    n_px = np.array([np.count_nonzero(m) for m in ms], dtype=np.int64)
    base = {int(j): lost_pixels(cover(hull, j), j) for j in ref_idx if n_px[j]}
    for i in np.flatnonzero(explain):
        if ref[i]:
            drop = ((ref_votes - votes[i]) < k) & ~hull
            unexpl = base
        else:
            drop = hull & ~((ref_votes + votes[i]) < k)
            unexpl = ({j: lost_pixels(cover(hull & ~drop, j), j) for j in base}
                      if drop.any() else base)
        lost = {j: (int(np.count_nonzero(cover(drop, j) & u)) if drop.any() and u.any()
                    else 0) for j, u in unexpl.items() if j != i}
        if not lost:
            continue
        frac = {j: c / n_px[j] for j, c in lost.items()}
        out[i] = {"unexplained_fraction": float(sum(lost.values())
                                                / max(int(sum(n_px[j] for j in lost)), 1)),
                  "unexplained_max": float(max(frac.values())),
                  "unexplained_views": int(sum(f > min_unexplained for f in frac.values()))}
    return out


def _votes_and_sight(ijk: np.ndarray, grid: VoxelGrid, masks: list[np.ndarray],
                     cams: list[CameraModel], T_cb: np.ndarray, limits: list[float],
                     outside_image: str, behind_camera: str) -> tuple[np.ndarray, np.ndarray]:
    """Each view's vote to carve each voxel ``ijk`` (M, 3), and whether the voxel's centre
    is in its image: two (N views, M) bool arrays (one vectorised pass per view)."""
    votes = np.zeros((len(cams), len(ijk)), dtype=bool)
    seen = np.zeros((len(cams), len(ijk)), dtype=bool)
    for v in range(len(cams)):
        flat, in_img, behind = _project_indices(tuple(ijk.T), grid, cams[v], T_cb[v],
                                                limits[v])
        keep = masks[v].reshape(-1)[flat] & in_img
        if outside_image == "keep":
            keep |= ~in_img & ~behind
        if behind_camera == "keep":
            keep |= behind
        votes[v] = ~keep
        seen[v] = in_img
    return votes, seen


def _mask_scores(mask: np.ndarray, hull_px: np.ndarray, unknown_px: np.ndarray, tol: int
                 ) -> dict[str, float | int | None]:
    """One mask against the other views' projected hull, on the pixels not unknown:
    ``iou``, ``spurious_fraction`` and ``missing_fraction`` (beyond ``tol`` pixels of
    the other's outline; None when there is nothing to divide), the pixel counts and
    ``tolerance_px``."""
    m = mask & ~unknown_px
    n_mask = int(np.count_nonzero(m))
    n_hull = int(np.count_nonzero(hull_px))
    inter = int(np.count_nonzero(m & hull_px))
    union = n_mask + n_hull - inter
    near_mask = cv2.distanceTransform((~m).view(np.uint8), cv2.DIST_L2, 3) <= tol
    near_hull = cv2.distanceTransform((~hull_px).view(np.uint8), cv2.DIST_L2, 3) <= tol
    n_missing = int(np.count_nonzero(hull_px & ~near_mask))
    n_spurious = int(np.count_nonzero(m & ~near_hull))
    return {"iou": float(inter / union) if union else None,
            "spurious_fraction": float(n_spurious / n_mask) if n_mask else None,
            "missing_fraction": float(n_missing / n_hull) if n_hull else None,
            "mask_px": n_mask, "hull_px": n_hull,
            "unknown_px": int(np.count_nonzero(unknown_px)), "tolerance_px": tol}


def reference_suspects(masks: Sequence[np.ndarray], flagged: Sequence[int]
                       ) -> tuple[list[int], bool]:
    """The views kept out of the agreement check's reference (``exclude`` of
    :func:`flag_disagreeing_views`): those the segmentation's own checks ``flagged``,
    unless more than half were (then every view with a mask scores the others), and those
    with an empty mask. Returns them sorted, and whether the flagged ones were too many."""
    n = len(masks)
    flagged = {int(v) for v in flagged}
    too_many = len(flagged) > n // 2
    empty = {i for i in range(n) if not np.asarray(masks[i]).any()}
    return sorted((set() if too_many else flagged) | empty), too_many


def flag_disagreeing_views(
    grid: VoxelGrid,
    masks: Sequence[np.ndarray],
    cameras: CameraModel | Sequence[CameraModel],
    T_base_cameras: np.ndarray,
    *,
    options: AgreementOptions = AgreementOptions(),
    carve: CarveOptions = CarveOptions(),
    exclude: Sequence[int] = (),
    max_passes: int = 6,
) -> dict:
    """Flag the views whose silhouettes disagree with the other views' hull.

    Every pass scores the views against the hull of the views not flagged so far
    (:func:`view_agreement`). First, masks that miss more than ``qa_max_missing`` of the
    others' hull are flagged: they would carve true object away (inverted, shifted, a
    part lost); but only when their carving also leaves more than
    ``qa_min_unexplained`` of two other views' silhouettes (one, when only one other
    view has a mask) with no hull behind them, or their foreground also lies outside the
    others' hull (more than ``qa_max_spurious``: an inverted or shifted mask, whose
    carving can leave the loose hull's corners to explain the other views). The others'
    hull is never tighter than the object, and where few views see a thin wall, a cup's
    opening or a bracket's inside, it is much looser: a correct mask then "misses" a
    fifth to two fifths of it (simulated scenes of 6 and 8 views; 2 of 24 views of a
    1.8 mm fin), and without the second test the views that carve most were left out and
    the hull's volume IoU with the truth fell to 0.24 (``benchmarks/README.md``, stop
    34). Such a mask also shrinks the reference of every other view, so a pass
    flags only the clearly worst of them (a missing fraction at least half the
    largest), and the next pass scores again without them. When no more are found,
    masks with more than ``qa_max_spurious`` of their foreground outside the others' hull
    (a blob, a shadow, the table) are flagged too, until a pass finds nothing new. The
    order matters: a spurious mask harms no other view's score (the others carve its
    excess away), a mask that loses a part makes its neighbours' masks look spurious
    there.

    At most half of the views are flagged: when more disagree, the silhouettes disagree
    broadly (calibration, poses, or one segmentation failure everywhere) and leaving the
    majority out would not help; the worst ones are flagged and a warning says so.

    Parameters
    ----------
    grid, masks, cameras, T_base_cameras
        As :func:`view_agreement`.
    options : AgreementOptions
        The flag thresholds ``qa_max_missing``, ``qa_max_spurious`` (on
        ``missing_fraction`` and ``spurious_fraction``) and ``qa_min_observers``
        (``min_observers`` of :func:`view_agreement`).
    carve : CarveOptions
        As :func:`view_agreement`.
    exclude : sequence of int
        Views already suspect (e.g. flagged by the segmentation's own checks): never in
        the reference, scored and flagged like the others when they disagree.
    max_passes : int
        Scoring passes at most.

    Returns
    -------
    dict
        ``views``: the last pass's scores per view with ``flagged`` (bool) and
        ``reasons`` (list of str); ``flagged``: the flagged views (sorted);
        ``passes`` (scoring passes run); ``thresholds``; ``capped`` (True when more
        views disagreed than may be flagged); ``time_s``.
    """
    t0 = time.perf_counter()
    max_missing, max_spurious = options.qa_max_missing, options.qa_max_spurious
    for name, val in (("qa_max_missing", max_missing), ("qa_max_spurious", max_spurious)):
        if not 0.0 <= val <= 1.0:
            raise ValueError(f"{name} must be in [0, 1], got {val}")
    n = len(masks)
    known_bad = {int(e) for e in exclude}
    cap = n // 2
    flagged: dict[int, list[str]] = {}
    capped = False
    scores: list[dict] = []
    passes = 0
    reference_done: list[int] | None = None
    spurious_phase = False

    def n_evidence(v: int) -> int:
        """The other reference views with a mask: the most that can lose pixels."""
        return sum(1 for r in reference if r != v and masks[r].any())

    for _ in range(4 * max(1, int(max_passes))):
        reference = [v for v in range(n) if v not in flagged and v not in known_bad]
        if not reference:
            break
        if reference != reference_done:
            if passes >= max(1, int(max_passes)):
                break
            scores = view_agreement(grid, masks, cameras, T_base_cameras,
                                    reference=reference, carve=carve,
                                    min_observers=options.qa_min_observers,
                                    min_unexplained=options.qa_min_unexplained,
                                    explain_above=max_missing)
            reference_done = reference
            passes += 1
        new: dict[int, tuple[float, list[str]]] = {}
        for s in scores:
            v = s["view"]
            if v in flagged:
                continue
            mf, sf = s["missing_fraction"], s["spurious_fraction"]
            reasons, excess = [], 0.0
            n_lost = s.get("unexplained_views")
            cuts = n_lost is not None and n_lost >= min(2, n_evidence(v))
            both_ways = sf is not None and sf > max_spurious
            if (s["hull_px"] and (mf is None or mf > max_missing)
                    and (n_lost is None or cuts or both_ways)):
                mf = 1.0 if mf is None else mf
                why = f"misses {mf:.0%} of the other views' hull (> {max_missing:.0%})"
                if cuts and n_lost:
                    why += (f" and leaves up to {s['unexplained_max']:.0%} of {n_lost} other "
                            f"views' silhouettes with no hull behind them")
                elif both_ways:
                    why += f" and {sf:.0%} of its foreground lies outside it"
                reasons.append(why)
                excess = mf
            if spurious_phase and sf is not None and sf > max_spurious:
                reasons.append(f"{sf:.0%} of its foreground lies outside the other views' "
                               f"hull (> {max_spurious:.0%})")
            if reasons:
                new[v] = (excess, reasons)
        if not spurious_phase and new:  # the clearly worst: they damage the others' scores
            worst = max(e for e, _r in new.values())
            new = {v: er for v, er in new.items() if er[0] >= 0.5 * worst}
        room = cap - len(flagged)
        if len(new) > room:
            capped = True
            new = dict(sorted(new.items(), key=lambda kv: -kv[1][0])[:max(room, 0)])
        if not new:
            if spurious_phase:
                break
            spurious_phase = True
            continue
        for v, (_e, reasons) in new.items():
            flagged[v] = reasons
    for s in scores:
        s["flagged"] = s["view"] in flagged
        s["reasons"] = flagged.get(s["view"], [])
    if capped:
        _log.warning("agreement check: more than half of the %d silhouettes disagree with "
                     "the others' hull; flagged the worst %d only (check the calibration, "
                     "the poses and the segmentation)", n, len(flagged))
    for v in sorted(flagged):
        _log.warning("agreement check: view %d flagged: %s", v, "; ".join(flagged[v]))
    return {"views": scores, "flagged": sorted(flagged), "passes": passes,
            "thresholds": {"max_missing": float(max_missing),
                           "max_spurious": float(max_spurious)},
            "capped": capped, "time_s": float(time.perf_counter() - t0)}


# ---------------------------------------------------------------------- mesh
def outside_silhouettes(points: np.ndarray, masks, cameras, T_base_cameras, *,
                        tol_px: float = 2.0, tol_m: float = 0.0005
                        ) -> tuple[np.ndarray, np.ndarray]:
    """How far outside each view's silhouette a set of points lies: the visual hull's
    test for measured points (a point of the object cannot project outside any correct
    silhouette of it).

    A point is *outside* view ``i`` when its projection falls in the image and farther
    from the silhouette than ``tol_px`` pixels plus ``tol_m`` (the poses' and the
    calibration's error, metres at the object) seen at the point's depth. The distance
    is the exact Euclidean distance transform of the silhouette's complement
    (OpenCV), read at the projected pixel. Points that project outside a view's image or
    behind its camera are not judged by it.

    Parameters
    ----------
    points : (N, 3) float
        Points in ``base``.
    masks, cameras, T_base_cameras
        The views, as in :func:`carve_dense`.
    tol_px : float, pixels
        Tolerated distance from the silhouette for the masks' own edge error.
    tol_m : float, metres
        Tolerated distance at the object for the views' and the points' pose error.

    Returns
    -------
    n_outside : (N,) int32
        The number of views whose silhouette the point lies outside of.
    worst_m : (N,) float64
        The largest distance outside a silhouette, in metres at the point (0 inside all).
    """
    ms, cams, T = check_views(masks, cameras, T_base_cameras)
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n_out = np.zeros(len(p), np.int32)
    worst = np.zeros(len(p))
    if len(p) == 0:
        return n_out, worst
    for m, cam, t in zip(ms, cams, T, strict=True):
        if m.all():
            continue
        dist = cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        uv, front = project_points(p, cam, t)
        t_inv = invert_transform(t)
        z = p @ t_inv[2, :3] + t_inv[2, 3]
        col = np.floor(uv[:, 0] + 0.5)
        row = np.floor(uv[:, 1] + 0.5)
        ok = front & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        d_px = np.zeros(len(p), np.float32)
        d_px[ok] = dist[row[ok].astype(np.int64), col[ok].astype(np.int64)]
        px_m = np.where(ok, z, 0.0) / np.sqrt(cam.fx * cam.fy)  # one pixel at the point
        d_m = d_px * px_m
        n_out += (ok & (d_m > tol_m + tol_px * px_m)).astype(np.int32)
        np.maximum(worst, d_m, out=worst)
    return n_out, worst


def hull_to_mesh(grid: VoxelGrid, *, smooth_sigma_vox: float = 0.8
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangle mesh of the occupied voxels (marching cubes at level 0.5).

    The occupancy is padded with empty voxels, so that the surface closes where the
    object touches the grid's side, and smoothed with a Gaussian of ``smooth_sigma_vox``
    voxels (0 for none) before marching cubes; the iso-surface at 0.5 then passes half a
    voxel outside the occupied centres, i.e. through the faces of the voxels.

    Parameters
    ----------
    grid : VoxelGrid
    smooth_sigma_vox : float
        Gaussian sigma in voxels.

    Returns
    -------
    vertices : (V, 3) float64, metres, in ``grid.frame``
    faces : (F, 3) int32
        Counter-clockwise seen from outside (normals point out of the object).

    Raises
    ------
    StageError
        The grid has no occupied voxel.

    References
    ----------
    W. E. Lorensen and H. E. Cline, "Marching cubes: a high resolution 3D surface
    construction algorithm", SIGGRAPH 1987 (scikit-image's ``marching_cubes``).
    """
    from scipy.ndimage import gaussian_filter
    from skimage.measure import marching_cubes

    check_grid(grid)
    if not np.isfinite(smooth_sigma_vox) or smooth_sigma_vox < 0:
        raise ValueError(f"smooth_sigma_vox must be >= 0, got {smooth_sigma_vox}")
    if grid.n_occupied == 0:
        raise StageError("the carved grid is empty: no hull to mesh")
    pad = 2 + int(np.ceil(4.0 * smooth_sigma_vox))
    # crop to the occupied block first: the smoothing and marching cost follow the object
    nz = np.argwhere(grid.occupancy)
    lo, hi = nz.min(axis=0), nz.max(axis=0) + 1
    sub = grid.occupancy[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    binary = np.pad(sub.astype(np.float32), pad, mode="constant", constant_values=0.0)
    vol = binary
    if smooth_sigma_vox > 0:
        vol = gaussian_filter(binary, sigma=float(smooth_sigma_vox), mode="constant", cval=0.0)
        if vol.max() <= 0.5:
            _log.warning("hull mesh: smoothing with sigma %.2f voxels removes every part of "
                         "the hull (thinner than the blur); meshing the unsmoothed voxels",
                         smooth_sigma_vox)
            vol = binary
    # keep values off the iso-level exactly, so that no vertex lands on a grid point
    vol[np.abs(vol - 0.5) < 1e-6] = 0.5 - 1e-6
    # The classic table: on binary volumes (voxels touching along an edge) skimage's
    # Lewiner variant shares vertices between sheets and yields non-manifold edges
    # (benchmarks/README.md, "Notes moved from robo3d/carving.py").
    verts, faces, _normals, _values = marching_cubes(vol, level=0.5, method="lorensen",
                                                     gradient_direction="descent")
    verts = grid.origin + grid.voxel_size * (verts.astype(np.float64) + (lo - pad))
    # skimage's winding with "descent" makes normals point towards lower values, out of
    # the object, but we check it on the signed volume and flip if needed
    faces = faces.astype(np.int32)
    if _signed_volume(verts, faces) < 0:
        faces = faces[:, ::-1].copy()
    return verts, faces


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed triangle mesh (positive when faces wind outward)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


# ---------------------------------------------------------------------- resolution
def resolution_report(
    grid: VoxelGrid,
    cameras: CameraModel | Sequence[CameraModel],
    T_base_cameras: np.ndarray,
) -> dict:
    """Voxel size against what the cameras resolve (seed §3.5, eq. 7–8).

    Eq. 7: the grid resolution per axis ``a = l / Delta`` (box side over voxel count),
    which is the voxel size. Eq. 8: the footprint of one pixel at the object's distance,
    ``w / f`` with ``w`` the depth of the grid centre in the view and ``f`` the focal
    length in pixels. Voxels smaller than the smallest footprint over the views are finer
    than any camera resolves: they cost time and memory and add nothing.

    Parameters
    ----------
    grid : VoxelGrid
    cameras : CameraModel or sequence of N
    T_base_cameras : (N, 4, 4) float64

    Returns
    -------
    dict
        ``voxel_size_m``, ``axis_resolution_m`` (eq. 7, per axis), ``extent_m``,
        ``shape``, ``depth_m`` and ``pixel_footprint_m`` per view (eq. 8; NaN for views
        with the grid centre behind them), ``min_pixel_footprint_m``,
        ``median_pixel_footprint_m``, ``voxel_over_footprint`` (voxel size over the
        smallest footprint), ``finer_than_cameras`` (bool) and ``warning`` (a sentence
        when they are, else None).
    """
    check_grid(grid)
    _ms, cams, T = check_views(None, cameras, T_base_cameras, need_masks=False)
    centre = grid.centre
    T_cb = invert_transform(T)
    depth = np.einsum("nj,j->n", T_cb[:, 2, :3], centre) + T_cb[:, 2, 3]
    foot = np.array([float(c.pixel_footprint(d)) if d > 0 else np.nan
                     for c, d in zip(cams, depth, strict=True)])
    lo, hi = grid.bounds
    extent = hi - lo
    valid = foot[np.isfinite(foot)]
    fmin = float(valid.min()) if valid.size else float("nan")
    fmed = float(np.median(valid)) if valid.size else float("nan")
    ratio = grid.voxel_size / fmin if valid.size else float("nan")
    finer = bool(valid.size and grid.voxel_size < fmin)
    warning = None
    if finer:
        warning = (f"voxels of {grid.voxel_size:.3g} m are finer than the best pixel "
                   f"footprint {fmin:.3g} m (seed eq. 8): a coarser grid gives the same hull "
                   "faster")
        _log.info("resolution: %s", warning)
    return {
        "voxel_size_m": float(grid.voxel_size),
        "axis_resolution_m": (extent / np.array(grid.shape)).tolist(),
        "extent_m": extent.tolist(),
        "shape": list(grid.shape),
        "depth_m": depth.tolist(),
        "pixel_footprint_m": [float(x) for x in foot],
        "min_pixel_footprint_m": fmin,
        "median_pixel_footprint_m": fmed,
        "voxel_over_footprint": float(ratio),
        "finer_than_cameras": finer,
        "warning": warning,
    }

