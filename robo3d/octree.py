"""Octree carving of the visual hull (seed §3.1.1, Szeliski 1993), compiled with numba.

The box is the root octant; an octant is tested against each view by the pixel box that
bounds its projection, looked up in O(1) in the integral image (summed-area table) of
that view's silhouette:

* **white** (empty) when, in some view, no point of it can be kept: the whole footprint
  is background (or outside the image / behind the camera, when those are carved);
* **black** (occupied) when, in every view, every point of it is kept;
* **grey** otherwise: it is split into its eight children, down to single voxels.

A view in which an octant is black is black for all its descendants, so a child is
tested only against the views still grey for its parent; the work concentrates on the
octants crossed by a silhouette cone's surface and grows with the hull's surface, not
its volume.

Exactness (the dense carver's occupancy, to the voxel)
------------------------------------------------------
The grid's exchange type is :class:`robo3d.grid.VoxelGrid`, and the dense carver
(:func:`robo3d.carving.carve_dense`) defines a voxel by its centre. The octree therefore
tests the box spanned by the *centres* of the voxels an octant holds (half a voxel
smaller than the octant on each side), and at the finest level (one voxel, a point) it
runs the dense carver's own test with the same floating-point operations in the same
order: projection, distortion, rounding to the pixel, the image, behind-camera and
lens-fold rules. That is ``leaf_rule="centre"`` (default): the occupancy equals
:func:`~robo3d.carving.carve_dense`'s exactly (tested). ``leaf_rule="conservative"`` is
Szeliski's rule: octants are the voxels' full cubes, and grey octants of the minimum
size count as black; the result is a superset of the dense one (every voxel the dense
carver keeps is kept), larger by the voxels the silhouette rims cross.

k of n (``min_views_background = k``): a voxel is carved when at least ``k`` views
vote to carve it. An octant is white once ``k`` views are white for it, black once the
views white for it plus those still grey number fewer than ``k``, grey otherwise; a view
white for an octant is a certain vote for each of its descendants and is not tested
again below it, so each stack entry carries that count beside its grey views. The leaf
test counts votes the same way; the occupancy is the dense carver's for every ``k``
(tested against an independent per-view vote count). ``k = 1`` is the rule above.

Why the footprint bound is conservative (never carves a voxel the dense test keeps)
-----------------------------------------------------------------------------------
1. Camera coordinates are affine in the voxel indices, so the depth range of a box is
   the range over its 8 corners; the box is all in front (depth > 1e-12 m, the dense
   rule, with a 1e-9 m guard), all behind, or straddles (then grey).
2. For a box wholly in front, perspective division maps it onto the convex hull of its
   projected corners (a projective map keeps segments straight where depth > 0), so the
   normalised coordinates ``x = X/Z, y = Y/Z`` of every point lie in the bounding
   rectangle of the 8 projected corners.
3. The plumb_bob distortion is evaluated on that rectangle in interval arithmetic
   (every operation on ``[lo, hi]`` bounds, radial and tangential terms alike): the
   result contains the distorted position of every point, whether or not the lens model
   is monotonic there; no Lipschitz constant or monotonicity is assumed.
4. Pixels are ``floor(u + 0.5)`` as in the dense carver; the pixel rectangle is widened
   by 1e-6 px each side to absorb rounding (the floating-point error of the
   corner-based bounds is ~1e-13 px). The lens-fold radius (beyond it the dense carver
   counts a point as outside the image) is compared with the rectangle's radius range
   with a 1e-9 relative guard; a box across it may hold both kinds of point.
5. The integral image counts the silhouette pixels in that (clipped) rectangle: none
   means every in-image point is background, all means every one is silhouette.
The categories a box may hold (behind, outside the image, silhouette, background) are
thus a superset of those its voxel centres hold, and the box is white or black only
when every possible category carves, or keeps, under the ``outside_image`` and
``behind_camera`` policies, which mean exactly what they mean for the dense carver.

Compiled kernel
---------------
The traversal is an explicit-stack depth-first search in a numba ``njit`` function
(``cache=True``: compiled once per machine, 5-10 s, then loaded from numba's cache
in well under a second; :func:`warm_up` triggers it). Per-view parameters travel as one
float64 table; the views still grey for an octant are a bit set (64 views per word);
the view that carved the last white octant is tried first (neighbouring octants tend to
be carved by the same view). The optional parallel kernel splits the octree into
subtrees that write disjoint blocks of the occupancy, so its result does not depend on
the number of threads.

References
----------
R. Szeliski, "Rapid octree construction from image sequences", CVGIP: Image
Understanding 58(1), 23-32, 1993. F. C. Crow, "Summed-area tables for texture mapping",
SIGGRAPH 1984. R. E. Moore, "Interval Analysis", Prentice-Hall, 1966.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence

import numba
import numpy as np
from numba import njit

from .camera import CameraModel, distortion_limit_r2
from .checks import check_carve_inputs, check_choice
from .grid import VoxelGrid, carve_counts
from .transforms import invert_transform

__all__ = ["carve_octree", "warm_up", "LEAF_RULES"]

_log = logging.getLogger(__name__)

#: Accepted values of ``leaf_rule``.
LEAF_RULES = ("centre", "conservative")

_WHITE, _BLACK, _GREY = 0, 1, 2
# per-view parameter table columns
_NPAR = 27


# ---------------------------------------------------------------------------- kernels
@njit(cache=True, inline="always")
def _imul(alo, ahi, blo, bhi):
    p1 = alo * blo
    p2 = alo * bhi
    p3 = ahi * blo
    p4 = ahi * bhi
    return min(min(p1, p2), min(p3, p4)), max(max(p1, p2), max(p3, p4))


@njit(cache=True, inline="always")
def _isqr(lo, hi):
    if lo >= 0.0:
        return lo * lo, hi * hi
    if hi <= 0.0:
        return hi * hi, lo * lo
    return 0.0, max(lo * lo, hi * hi)


@njit(cache=True, inline="always")
def _iscale(c, lo, hi):
    if c >= 0.0:
        return c * lo, c * hi
    return c * hi, c * lo


@njit(cache=True)
def _classify_box(P, S, w, x0, x1, y0, y1, z0, z1, keep_out, keep_behind):
    """White/black/grey of the box [x0, x1] x [y0, y1] x [z0, z1] (grid index units)
    in view w."""
    zmin = np.inf
    zmax = -np.inf
    xmin = np.inf
    xmax = -np.inf
    ymin = np.inf
    ymax = -np.inf
    for c in range(8):
        fi = x1 if (c & 1) else x0
        fj = y1 if (c & 2) else y0
        fk = z1 if (c & 4) else z0
        X = P[w, 0] * fi + P[w, 1] * fj + P[w, 2] * fk + P[w, 9]
        Y = P[w, 3] * fi + P[w, 4] * fj + P[w, 5] * fk + P[w, 10]
        Z = P[w, 6] * fi + P[w, 7] * fj + P[w, 8] * fk + P[w, 11]
        zmin = min(zmin, Z)
        zmax = max(zmax, Z)
        if Z > 0.0:
            x = X / Z
            y = Y / Z
            xmin = min(xmin, x)
            xmax = max(xmax, x)
            ymin = min(ymin, y)
            ymax = max(ymax, y)
    tol_z = 1e-9
    if zmax <= 1e-12 - tol_z:  # every point behind the camera
        return _BLACK if keep_behind else _WHITE
    if zmin <= 1e-12 + tol_z:  # straddles the camera plane: no bound on x, y
        return _GREY
    poss_out = False
    poss_in = True
    poss_fg = False
    poss_bg = False
    if P[w, 23] > 0.5:  # the lens model folds back beyond limit_r2
        lim = P[w, 22]
        sxlo, sxhi = _isqr(xmin, xmax)
        sylo, syhi = _isqr(ymin, ymax)
        if sxhi + syhi >= lim * (1.0 - 1e-9):
            poss_out = True
        if sxlo + sylo >= lim * (1.0 + 1e-9):
            poss_in = False
    if poss_in:
        if P[w, 24] > 0.5:  # interval plumb_bob
            k1 = P[w, 17]
            k2 = P[w, 18]
            p1 = P[w, 19]
            p2 = P[w, 20]
            k3 = P[w, 21]
            sxlo, sxhi = _isqr(xmin, xmax)
            sylo, syhi = _isqr(ymin, ymax)
            r2lo = sxlo + sylo
            r2hi = sxhi + syhi
            tlo, thi = _iscale(k3, r2lo, r2hi)
            tlo, thi = _imul(r2lo, r2hi, k2 + tlo, k2 + thi)
            tlo, thi = _imul(r2lo, r2hi, k1 + tlo, k1 + thi)
            radlo = 1.0 + tlo
            radhi = 1.0 + thi
            xylo, xyhi = _imul(xmin, xmax, ymin, ymax)
            # xd = x * radial + 2 p1 x y + p2 (r2 + 2 x^2)
            alo, ahi = _imul(xmin, xmax, radlo, radhi)
            blo, bhi = _iscale(2.0 * p1, xylo, xyhi)
            clo, chi = _iscale(p2, r2lo + 2.0 * sxlo, r2hi + 2.0 * sxhi)
            xdlo = alo + blo + clo
            xdhi = ahi + bhi + chi
            # yd = y * radial + p1 (r2 + 2 y^2) + 2 p2 x y
            alo, ahi = _imul(ymin, ymax, radlo, radhi)
            blo, bhi = _iscale(p1, r2lo + 2.0 * sylo, r2hi + 2.0 * syhi)
            clo, chi = _iscale(2.0 * p2, xylo, xyhi)
            ydlo = alo + blo + clo
            ydhi = ahi + bhi + chi
        else:
            xdlo = xmin
            xdhi = xmax
            ydlo = ymin
            ydhi = ymax
        alo, ahi = _iscale(P[w, 12], xdlo, xdhi)
        blo, bhi = _iscale(P[w, 13], ydlo, ydhi)
        ulo = alo + blo + P[w, 14]
        uhi = ahi + bhi + P[w, 14]
        alo, ahi = _iscale(P[w, 15], ydlo, ydhi)
        vlo = alo + P[w, 16]
        vhi = ahi + P[w, 16]
        width = P[w, 25]
        height = P[w, 26]
        # clamp before the integer conversion (points near the camera plane)
        ulo = min(max(ulo + 0.5 - 1e-6, -2.0), width + 2.0)
        uhi = min(max(uhi + 0.5 + 1e-6, -2.0), width + 2.0)
        vlo = min(max(vlo + 0.5 - 1e-6, -2.0), height + 2.0)
        vhi = min(max(vhi + 0.5 + 1e-6, -2.0), height + 2.0)
        pu0 = int(np.floor(ulo))
        pu1 = int(np.floor(uhi))
        pv0 = int(np.floor(vlo))
        pv1 = int(np.floor(vhi))
        iw = int(width)
        ih = int(height)
        if pu0 < 0 or pv0 < 0 or pu1 >= iw or pv1 >= ih:
            poss_out = True
        cu0 = max(pu0, 0)
        cu1 = min(pu1, iw - 1)
        cv0 = max(pv0, 0)
        cv1 = min(pv1, ih - 1)
        if cu0 <= cu1 and cv0 <= cv1:
            cnt = (S[w, cv1 + 1, cu1 + 1] - S[w, cv0, cu1 + 1]
                   - S[w, cv1 + 1, cu0] + S[w, cv0, cu0])
            area = (cu1 - cu0 + 1) * (cv1 - cv0 + 1)
            poss_fg = cnt > 0
            poss_bg = cnt < area
    kept = poss_fg or (keep_out and poss_out)
    carved = poss_bg or ((not keep_out) and poss_out)
    if not kept:
        return _WHITE
    if not carved:
        return _BLACK
    return _GREY


@njit(cache=True)
def _keep_point(P, M, w, i, j, k, keep_out, keep_behind):
    """The dense carver's test of voxel (i, j, k)'s centre in view w, operation for
    operation (robo3d.carving._project_indices)."""
    fi = float(i)
    fj = float(j)
    fk = float(k)
    X = P[w, 0] * fi + P[w, 1] * fj + P[w, 2] * fk + P[w, 9]
    Y = P[w, 3] * fi + P[w, 4] * fj + P[w, 5] * fk + P[w, 10]
    Z = P[w, 6] * fi + P[w, 7] * fj + P[w, 8] * fk + P[w, 11]
    if Z <= 1e-12:
        return keep_behind
    x = X / Z
    y = Y / Z
    if P[w, 23] > 0.5:
        if not (x * x + y * y < P[w, 22]):
            return keep_out
    if P[w, 24] > 0.5:
        k1 = P[w, 17]
        k2 = P[w, 18]
        p1 = P[w, 19]
        p2 = P[w, 20]
        k3 = P[w, 21]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = xd
        y = yd
    u = np.floor(P[w, 12] * x + P[w, 13] * y + P[w, 14] + 0.5)
    v = np.floor(P[w, 15] * y + P[w, 16] + 0.5)
    if not (u >= 0 and u < P[w, 25] and v >= 0 and v < P[w, 26]):
        return keep_out
    return M[w, int(v), int(u)]


@njit(cache=True)
def _carve_subtree(i0r, j0r, k0r, levr, nx, ny, nz, P, S, M, n_views, keep_out,
                   keep_behind, conservative, k_bg, occ, stats, carved_by):
    """Depth-first Szeliski traversal of one octant; writes occ inside it only.

    k_bg: views that must vote to carve (k of n). Each stack entry carries the views
    still grey for it (bit set) and the number of views white for an ancestor (votes
    every point of it has for certain).
    stats[level] = (octants tested, white, black, grey, view tests, point tests).
    carved_by[w] = voxels removed by view w (the view that cast the k-th vote).
    """
    n_words = (n_views + 63) // 64
    cap = 8 * (levr + 2)
    st = np.zeros((cap, 5), dtype=np.int64)
    sm = np.zeros((cap, n_words), dtype=np.uint64)
    cur = np.zeros(n_words, dtype=np.uint64)
    for q in range(n_words):
        nb = min(64, n_views - 64 * q)
        if nb == 64:
            sm[0, q] = np.uint64(0xFFFFFFFFFFFFFFFF)
        else:
            sm[0, q] = (np.uint64(1) << np.uint64(nb)) - np.uint64(1)
    st[0, 0] = i0r
    st[0, 1] = j0r
    st[0, 2] = k0r
    st[0, 3] = levr
    sp = 1
    hint = 0
    one = np.uint64(1)
    while sp > 0:
        sp -= 1
        i0 = st[sp, 0]
        j0 = st[sp, 1]
        k0 = st[sp, 2]
        lev = st[sp, 3]
        cnt = st[sp, 4]
        for q in range(n_words):
            cur[q] = sm[sp, q]
        size = 1 << lev
        i1 = min(i0 + size, nx) - 1
        j1 = min(j0 + size, ny) - 1
        k1 = min(k0 + size, nz) - 1
        stats[lev, 0] += 1
        if lev == 0 and not conservative:
            keep = True
            for t in range(n_views):
                w = hint + t
                if w >= n_views:
                    w -= n_views
                if (cur[w >> 6] >> np.uint64(w & 63)) & one:
                    stats[0, 5] += 1
                    if not _keep_point(P, M, w, i0, j0, k0, keep_out, keep_behind):
                        cnt += 1
                        if cnt >= k_bg:
                            keep = False
                            carved_by[w] += 1
                            hint = w
                            break
            if keep:
                occ[i0, j0, k0] = True
                stats[0, 2] += 1
            else:
                stats[0, 1] += 1
            continue
        if conservative:
            fx0 = i0 - 0.5
            fx1 = i1 + 0.5
            fy0 = j0 - 0.5
            fy1 = j1 + 0.5
            fz0 = k0 - 0.5
            fz1 = k1 + 0.5
        else:
            fx0 = float(i0)
            fx1 = float(i1)
            fy0 = float(j0)
            fy1 = float(j1)
            fz0 = float(k0)
            fz1 = float(k1)
        white = False
        n_grey = 0
        for t in range(n_views):
            w = hint + t
            if w >= n_views:
                w -= n_views
            bit = one << np.uint64(w & 63)
            if cur[w >> 6] & bit:
                stats[lev, 4] += 1
                c = _classify_box(P, S, w, fx0, fx1, fy0, fy1, fz0, fz1, keep_out,
                                  keep_behind)
                if c == _WHITE:  # a certain vote for every point: never tested again
                    cur[w >> 6] &= ~bit
                    cnt += 1
                    if cnt >= k_bg:
                        white = True
                        hint = w
                        carved_by[w] += (i1 - i0 + 1) * (j1 - j0 + 1) * (k1 - k0 + 1)
                        break
                elif c == _BLACK:
                    cur[w >> 6] &= ~bit
                else:
                    n_grey += 1
        if white:
            stats[lev, 1] += 1
            continue
        # black: too few views left that could vote for any point; or a grey octant of
        # the minimum size
        if cnt + n_grey < k_bg or lev == 0:
            stats[lev, 2] += 1
            occ[i0:i1 + 1, j0:j1 + 1, k0:k1 + 1] = True
            continue
        stats[lev, 3] += 1
        half = size >> 1
        for c in range(7, -1, -1):  # pushed in reverse: child 0 is visited first
            ci = i0 + half * (c & 1)
            cj = j0 + half * ((c >> 1) & 1)
            ck = k0 + half * ((c >> 2) & 1)
            if ci >= nx or cj >= ny or ck >= nz:
                continue
            st[sp, 0] = ci
            st[sp, 1] = cj
            st[sp, 2] = ck
            st[sp, 3] = lev - 1
            st[sp, 4] = cnt
            for q in range(n_words):
                sm[sp, q] = cur[q]
            sp += 1


@njit(cache=True)
def _carve_roots(roots, nx, ny, nz, P, S, M, n_views, keep_out, keep_behind,
                 conservative, k_bg, occ, stats, carved_by):
    for r in range(roots.shape[0]):
        _carve_subtree(roots[r, 0], roots[r, 1], roots[r, 2], roots[r, 3], nx, ny, nz,
                       P, S, M, n_views, keep_out, keep_behind, conservative, k_bg, occ,
                       stats, carved_by)


@numba.njit(cache=True, parallel=True)
def _carve_roots_parallel(roots, nx, ny, nz, P, S, M, n_views, keep_out, keep_behind,
                          conservative, k_bg, occ, stats_r, carved_r):
    for r in numba.prange(roots.shape[0]):
        _carve_subtree(roots[r, 0], roots[r, 1], roots[r, 2], roots[r, 3], nx, ny, nz,
                       P, S, M, n_views, keep_out, keep_behind, conservative, k_bg, occ,
                       stats_r[r], carved_r[r])


# ---------------------------------------------------------------------------- set-up
def _view_table(grid: VoxelGrid, cams: list[CameraModel], T_cb: np.ndarray) -> np.ndarray:
    """Per-view parameters, (N, 27) float64, built with the dense carver's arithmetic."""
    P = np.zeros((len(cams), _NPAR), dtype=np.float64)
    for w, (cam, t) in enumerate(zip(cams, T_cb, strict=True)):
        R = t[:3, :3]
        a = R * grid.voxel_size  # exactly as robo3d.carving._project_indices
        b = R @ grid.origin + t[:3, 3]
        lim = distortion_limit_r2(cam)
        P[w, 0:9] = a.reshape(-1)
        P[w, 9:12] = b
        P[w, 12] = cam.fx
        P[w, 13] = cam.K[0, 1]
        P[w, 14] = cam.cx
        P[w, 15] = cam.fy
        P[w, 16] = cam.cy
        P[w, 17:22] = cam.D[:5]
        P[w, 22] = lim if np.isfinite(lim) else 0.0
        P[w, 23] = 1.0 if np.isfinite(lim) else 0.0
        P[w, 24] = 1.0 if cam.has_distortion else 0.0
        P[w, 25] = cam.width
        P[w, 26] = cam.height
    return P


def _mask_tables(masks: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Masks padded to one size (N, H, W) bool and their integral images
    (N, H + 1, W + 1) int32 (``S[r, c]`` = silhouette pixels in rows < r, columns < c)."""
    import cv2

    h = max(m.shape[0] for m in masks)
    w = max(m.shape[1] for m in masks)
    M = np.zeros((len(masks), h, w), dtype=np.bool_)
    S = np.zeros((len(masks), h + 1, w + 1), dtype=np.int32)
    for i, m in enumerate(masks):
        M[i, : m.shape[0], : m.shape[1]] = m
        S[i, : m.shape[0] + 1, : m.shape[1] + 1] = cv2.integral(m.view(np.uint8),
                                                                sdepth=cv2.CV_32S)
    return M, S


def _roots(shape: tuple[int, int, int], top: int, root_level: int) -> np.ndarray:
    """Octants of size 2**root_level tiling the grid, (R, 4) int64 (i0, j0, k0, level),
    in a fixed pseudo-random order (balances static thread chunks)."""
    step = 1 << root_level
    axes = [np.arange(0, n, step) for n in shape]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    roots = np.concatenate([g, np.full((len(g), 1), root_level)], axis=1).astype(np.int64)
    order = np.random.default_rng(0).permutation(len(roots))
    return np.ascontiguousarray(roots[order])


def _prefer_quiet_threading_layer() -> None:
    """Try OpenMP and numba's own workqueue before TBB (an old TBB, as some wheels
    bring, makes numba warn on every run), unless the user chose a layer."""
    if not any(k in os.environ for k in ("NUMBA_THREADING_LAYER",
                                         "NUMBA_THREADING_LAYER_PRIORITY")):
        numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]


def warm_up() -> float:
    """Compile the kernels (or load them from numba's cache) on a tiny problem.

    Returns
    -------
    float
        Seconds it took (5-10 s the first time on a machine, well under 1 s after).
    """
    t0 = time.perf_counter()
    cam = CameraModel("warm_up", 16, 16, [[20.0, 0, 7.5], [0, 20.0, 7.5], [0, 0, 1]],
                      [0.01, 0.0, 0.0, 0.0, 0.0])
    mask = np.zeros((16, 16), bool)
    mask[4:12, 4:12] = True
    T = np.eye(4)
    T[2, 3] = -1.0
    grid = VoxelGrid(np.full(3, -0.1), 0.05, np.ones((5, 5, 5), bool))
    for rule in LEAF_RULES:
        carve_octree(grid, [mask], cam, T[None], leaf_rule=rule)
    carve_octree(grid, [mask], cam, T[None], threads=2)
    return time.perf_counter() - t0


# ---------------------------------------------------------------------------- public
def carve_octree(
    grid: VoxelGrid,
    masks: Sequence[np.ndarray],
    cameras: CameraModel | Sequence[CameraModel],
    T_base_cameras: np.ndarray,
    *,
    outside_image: str = "keep",
    behind_camera: str = "carve",
    leaf_rule: str = "centre",
    threads: int = 1,
    min_views_background: int = 1,
) -> tuple[VoxelGrid, dict]:
    """Carve a voxel grid with silhouettes by Szeliski's octree (seed §3.1.1).

    Same inputs, policies and result type as :func:`robo3d.carving.carve_dense`; with
    ``leaf_rule="centre"`` the occupancy is the dense carver's, voxel for voxel, at a
    cost that grows with the hull's surface rather than the grid's volume.

    Parameters
    ----------
    grid : VoxelGrid
        The grid to carve (in ``base``); not modified. Its voxels are the octree's
        minimum octants; only its occupied voxels can stay occupied.
    masks : sequence of N (H, W) bool
        Silhouettes, one per view, sized as their camera.
    cameras : CameraModel or sequence of N
        Intrinsics with plumb_bob distortion (honoured exactly).
    T_base_cameras : (N, 4, 4) float64
        Camera poses in ``base`` at each image's time.
    outside_image : {"keep", "carve"}
        What a view does to a voxel whose centre projects outside its image (or beyond
        the radius where the lens model folds back), as in ``carve_dense``.
    behind_camera : {"carve", "keep"}
        What a view does to a voxel behind its camera, as in ``carve_dense``.
    leaf_rule : {"centre", "conservative"}
        ``"centre"``: octants are the boxes of their voxels' centres and single voxels
        get the dense carver's exact centre test (equals ``carve_dense``).
        ``"conservative"``: Szeliski's rule, octants are full cubes and grey octants of
        the minimum size count as black (a superset of ``carve_dense``).
    threads : int
        Threads of the compiled kernel (0: numba's default, all cores). The result does
        not depend on it.
    min_views_background : int
        ``k``: a voxel is carved when at least ``k`` views vote to carve it, as in
        ``carve_dense`` (1: the visual hull). An octant is white once ``k`` views are
        white for it, black once fewer than ``k`` views could still vote for any of its
        points, grey otherwise; a view white for an octant is a certain vote for all
        its descendants.

    Returns
    -------
    grid : VoxelGrid
        A new grid with the carved occupancy.
    report : dict
        ``method`` (``"octree"``), ``leaf_rule``, ``voxels_before``, ``voxels_after``,
        ``voxel_size_m``, ``volume_m3``, the policies, ``n_views``, ``levels`` (octree
        depth), ``octants`` (per level, finest first: ``size_vox``, ``tested``,
        ``white``, ``black``, ``grey``, ``view_tests``), ``view_tests`` and
        ``point_tests`` (totals), ``views`` (per view: ``carved``, the voxels its tests
        removed, i.e. where it cast the ``k``-th vote), ``min_views_background``,
        ``threads``, ``time_s`` and ``kernel_first_call`` (True when this call also
        compiled the kernel or loaded it from numba's cache, ~0.3 s, included in
        ``time_s``).

    Raises
    ------
    ValueError
        Bad policy, leaf rule, masks, cameras or poses (as ``carve_dense``).
    StageError
        No view.

    References
    ----------
    R. Szeliski, "Rapid octree construction from image sequences", CVGIP: Image
    Understanding 58(1), 1993.
    """
    check_choice("leaf_rule", leaf_rule, LEAF_RULES)
    if int(threads) != threads or threads < 0:
        raise ValueError(f"threads must be an integer >= 0, got {threads}")
    k_bg, ms, cams, T = check_carve_inputs(grid, masks, cameras, T_base_cameras,
                                           outside_image=outside_image,
                                           behind_camera=behind_camera,
                                           min_views_background=min_views_background)
    n_views = T.shape[0]
    t0 = time.perf_counter()
    T_cb = invert_transform(T)
    P = _view_table(grid, cams, T_cb)
    M, S = _mask_tables(ms)
    shape = grid.shape
    top = max(0, int(np.ceil(np.log2(max(shape)))))
    occ = np.zeros(shape, dtype=np.bool_)
    n_threads = numba.config.NUMBA_NUM_THREADS if threads == 0 else int(threads)
    n_threads = max(1, min(n_threads, numba.config.NUMBA_NUM_THREADS))
    kernel = _carve_roots if n_threads == 1 else _carve_roots_parallel
    first_call = not kernel.signatures  # this call compiles or loads it from the cache
    stats, carved = _run_kernel(shape, top, P, S, M, n_views, outside_image == "keep",
                                behind_camera == "keep", leaf_rule == "conservative", k_bg,
                                occ, n_threads)
    if grid.n_occupied != occ.size:
        occ &= grid.occupancy
    out = VoxelGrid(grid.origin.copy(), grid.voxel_size, occ, grid.frame)
    elapsed = time.perf_counter() - t0
    report = {
        "method": "octree", "leaf_rule": leaf_rule, **carve_counts(grid, out),
        "outside_image": outside_image, "behind_camera": behind_camera,
        "min_views_background": int(k_bg), "n_views": int(n_views), "levels": int(top + 1),
        "octants": _octant_rows(stats),
        "view_tests": int(stats[:, 4].sum()), "point_tests": int(stats[:, 5].sum()),
        "views": [{"view": v, "camera": cams[v].frame_id, "carved": int(carved[v])}
                  for v in range(n_views)],
        "threads": int(n_threads), "time_s": float(elapsed),
        "kernel_first_call": bool(first_call),
    }
    if report["voxels_after"] == 0:
        _log.warning("carve: every voxel was carved (inconsistent silhouettes or poses?)")
    _log.info("octree carve: %d -> %d voxels (%.3g m^3) with %d views, %d box tests and %d "
              "point tests in %.3f s", report["voxels_before"], report["voxels_after"],
              out.volume_m3, n_views, report["view_tests"], report["point_tests"], elapsed)
    return out, report


def _octant_rows(stats: np.ndarray) -> list[dict[str, int]]:
    """The report's ``octants``: per level, finest first, its size in voxels and the
    octants tested, white, black and grey, and the view tests made on them."""
    return [{"level": int(lv), "size_vox": int(1 << lv), "tested": int(stats[lv, 0]),
             "white": int(stats[lv, 1]), "black": int(stats[lv, 2]),
             "grey": int(stats[lv, 3]), "view_tests": int(stats[lv, 4] + stats[lv, 5])}
            for lv in range(len(stats))]


def _run_kernel(shape: tuple[int, int, int], top: int, P: np.ndarray, S: np.ndarray,
                M: np.ndarray, n_views: int, keep_out: bool, keep_behind: bool,
                conservative: bool, k_bg: int, occ: np.ndarray, n_threads: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Run the compiled traversal into ``occ``: the whole octree in one thread, or its
    subtrees (1/8 or 1/64 of the root, enough to balance a few threads) in
    ``n_threads``. Returns the per-level statistics ``(top + 1, 6)`` and the voxels each
    view carved ``(n_views,)``."""
    if n_threads == 1:
        roots = np.array([[0, 0, 0, top]], dtype=np.int64)
        stats = np.zeros((top + 1, 6), dtype=np.int64)
        carved = np.zeros(n_views, dtype=np.int64)
        _carve_roots(roots, shape[0], shape[1], shape[2], P, S, M, n_views, keep_out,
                     keep_behind, conservative, k_bg, occ, stats, carved)
        return stats, carved
    root_level = max(0, top - (3 if top >= 6 else 2 if top >= 3 else 0))
    roots = _roots(shape, top, root_level)
    stats_r = np.zeros((len(roots), top + 1, 6), dtype=np.int64)
    carved_r = np.zeros((len(roots), n_views), dtype=np.int64)
    _prefer_quiet_threading_layer()
    previous = numba.get_num_threads()
    numba.set_num_threads(n_threads)
    try:
        _carve_roots_parallel(roots, shape[0], shape[1], shape[2], P, S, M, n_views,
                              keep_out, keep_behind, conservative, k_bg, occ, stats_r,
                              carved_r)
    finally:
        numba.set_num_threads(previous)
    return stats_r.sum(axis=0), carved_r.sum(axis=0)
