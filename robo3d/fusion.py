"""Geometric fusion: one surface from the aligned laser points, bounded by the visual hull.

:func:`fuse_poisson` is screened Poisson surface reconstruction (Kazhdan & Hoppe 2013, the
authors' implementation as shipped in Open3D) of the oriented points, followed by two cuts:

1. **Density trim.** Poisson closes the surface everywhere, also where no point was
   measured (e.g. the face resting on the table). Open3D reports, per vertex, the density
   of input samples that supported it; vertices whose density is below the
   ``density_quantile`` quantile are removed with the triangles that use them.
2. **Hull cut.** Where a visual hull is given, surface outside the hull dilated by
   ``hull_margin_voxels`` voxels is removed: the true surface lies inside the hull
   (Laurentini 1994), so anything outside is an extrapolation. A vertex is outside when the
   voxel whose centre is nearest to it is empty in the dilated hull, or lies off the grid.
   The dilation absorbs the hull's half-voxel discretisation and calibration error.
   The cut is *guarded*: when more than ``max_outside_fraction`` (5 %) of the laser points
   themselves lie outside the dilated hull, hull and laser disagree (a calibration or
   carving fault) and the cut would delete measured surface, so it is skipped and the
   report says why. The laser is the accurate measurement; the hull only trims
   extrapolation.

The input normals must point *out of* the object. The laser's normals are oriented toward
the sensor, which for an object scanned from outside is outward.

Reproducibility: Poisson runs single-threaded by default (``n_threads=1``) because Open3D's
multi-threaded solver does not give bit-identical vertices from run to run.

:func:`fuse_tsdf` is volumetric fusion after Curless & Levoy (1996): a truncated signed
distance field accumulated along each point's line of sight with view-angle weights, then
marching cubes. It needs the sensor origin of every point. It does not yet use the hull
to carve free space or fill holes (a later step); the hull only cuts the result, as for
Poisson.

References
----------
Curless, B. & Levoy, M. (1996). A volumetric method for building complex models from range
images. SIGGRAPH.
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
Laurentini, A. (1994). The visual hull concept for silhouette-based image understanding.
IEEE PAMI 16(2).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from .errors import StageError

__all__ = ["fuse_poisson", "fuse_tsdf", "crop_mesh_to_hull", "remove_vertices"]

log = logging.getLogger(__name__)


def _stack(name: str, a: object) -> np.ndarray:
    if isinstance(a, list | tuple):
        parts = [np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in a]
        arr = np.concatenate(parts) if parts else np.zeros((0, 3))
    else:
        arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3) or a list of (N_s, 3) arrays, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return arr


def _hull_arrays(hull: Any) -> tuple[np.ndarray, float, np.ndarray]:
    """(origin, voxel_size, occupancy) from a VoxelGrid-like object or a mapping."""
    get = hull.__getitem__ if isinstance(hull, dict) else (lambda k: getattr(hull, k))
    try:
        origin = np.asarray(get("origin"), dtype=np.float64)
        voxel_size = float(get("voxel_size"))
        occ = np.asarray(get("occupancy"))
    except (KeyError, AttributeError) as exc:
        raise ValueError("hull must have origin (3,), voxel_size and occupancy (nx, ny, nz) "
                         f"bool; missing {exc}") from exc
    if origin.shape != (3,) or not voxel_size > 0 or occ.ndim != 3 or occ.dtype != bool:
        raise ValueError(f"hull must have origin (3,), voxel_size > 0 and occupancy "
                         f"(nx, ny, nz) bool; got {origin.shape}, {voxel_size}, "
                         f"{occ.shape} {occ.dtype}")
    return origin, voxel_size, occ


def remove_vertices(vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices (and every triangle that uses one), renumbering the rest.

    Parameters
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int
    keep : (V,) bool
        Vertices to keep.

    Returns
    -------
    vertices : (V', 3) float64
        The kept vertices still used by a kept triangle, in their original order.
    faces : (F', 3) int64
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != (len(v),):
        raise ValueError(f"keep must be ({len(v)},) bool, got {keep.shape}")
    f = f[np.all(keep[f], axis=1)]
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    new_index = np.cumsum(used) - 1
    return v[used], new_index[f].astype(np.int64)


def _dilated_hull(hull: Any, margin_voxels: int) -> tuple[np.ndarray, float, np.ndarray]:
    from scipy import ndimage

    origin, vs, occ = _hull_arrays(hull)
    if margin_voxels < 0:
        raise ValueError(f"margin_voxels must be >= 0, got {margin_voxels}")
    if margin_voxels > 0:
        occ = ndimage.binary_dilation(occ, structure=np.ones((3, 3, 3), bool),
                                      iterations=margin_voxels)
    return origin, vs, occ


def _inside(points: np.ndarray, origin: np.ndarray, vs: float, occ: np.ndarray) -> np.ndarray:
    """Whether each point's nearest voxel centre is occupied (False off the grid)."""
    idx = np.round((points - origin) / vs).astype(np.int64)
    on_grid = np.all((idx >= 0) & (idx < np.array(occ.shape)), axis=1)
    inside = np.zeros(len(points), dtype=bool)
    ii = idx[on_grid]
    inside[on_grid] = occ[ii[:, 0], ii[:, 1], ii[:, 2]]
    return inside


def crop_mesh_to_hull(vertices: np.ndarray, faces: np.ndarray, hull: Any, *,
                      margin_voxels: int = 1) -> tuple[np.ndarray, np.ndarray, int]:
    """Remove the surface that lies outside a (dilated) voxel hull.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int
    hull : VoxelGrid-like
        ``origin`` (3,) (centre of voxel 0), ``voxel_size`` (metres), ``occupancy``
        (nx, ny, nz) bool; an object with those attributes or a dict with those keys.
    margin_voxels : int
        Dilation of the hull (26-connected), in voxels, before the test.

    Returns
    -------
    vertices : (V', 3) float64
    faces : (F', 3) int64
    n_outside : int
        Number of input vertices found outside the dilated hull.
    """
    origin, vs, occ = _dilated_hull(hull, margin_voxels)
    v = np.asarray(vertices, dtype=np.float64)
    inside = _inside(v, origin, vs, occ)
    v2, f2 = remove_vertices(v, faces, inside)
    return v2, f2, int(np.count_nonzero(~inside))


def _cut_to_hull(v: np.ndarray, f: np.ndarray, points: np.ndarray, hull: Any,
                 margin_voxels: int, max_outside_fraction: float, report: dict[str, Any]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The hull cut, guarded: skipped when the laser points disagree with the hull."""
    origin, vs, occ = _dilated_hull(hull, margin_voxels)
    frac = float(np.mean(~_inside(points, origin, vs, occ))) if len(points) else 0.0
    report["hull_points_outside_fraction"] = frac
    if frac > max_outside_fraction:
        report["hull_cut"] = (f"skipped: {frac:.1%} of the laser points lie outside the "
                              f"hull dilated by {margin_voxels} voxel(s) (more than "
                              f"{max_outside_fraction:.1%}); the hull and the laser disagree")
        report["n_vertices_outside_hull"] = 0
        log.warning("hull cut %s", report["hull_cut"])
        return v, f
    inside = _inside(v, origin, vs, occ)
    report["hull_cut"] = "applied"
    report["n_vertices_outside_hull"] = int(np.count_nonzero(~inside))
    return remove_vertices(v, f, inside)


def fuse_poisson(
    points: np.ndarray | list[np.ndarray],
    normals: np.ndarray | list[np.ndarray],
    *,
    depth: int = 9,
    density_quantile: float = 0.02,
    hull: Any = None,
    hull_margin_voxels: int = 1,
    max_outside_fraction: float = 0.05,
    scale: float = 1.1,
    linear_fit: bool = False,
    n_threads: int = 1,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Screened Poisson surface from oriented points, trimmed by density and by the hull.

    Parameters
    ----------
    points : (N, 3) float64, metres, or a list of per-sweep (N_s, 3) arrays
        Aligned laser points in ``base``.
    normals : (N, 3) float64, or a list like ``points``
        Outward unit normals.
    depth : int
        Octree depth: the finest cells are ``scale * extent / 2**depth`` wide.
    density_quantile : float in [0, 1)
        Vertices whose support density is below this quantile are removed (0 keeps all).
    hull : VoxelGrid-like, optional
        ``origin``, ``voxel_size``, ``occupancy``: surface outside it is cut away.
    hull_margin_voxels : int
        Dilation of the hull before the cut.
    max_outside_fraction : float
        The cut is skipped (and the report says why) when more than this fraction of the
        input points lie outside the dilated hull: hull and laser then disagree.
    scale : float
        Ratio of the reconstruction cube to the points' bounding cube (Poisson's ``scale``).
    linear_fit : bool
        Place iso-vertices by linear interpolation (more accurate on smooth surfaces).
    n_threads : int
        Poisson solver threads; 1 (default) is reproducible bit for bit, -1 uses all cores.
    seed : int
        Unused by the solver (deterministic); accepted for a uniform stage signature.

    Returns
    -------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int64
    report : dict
        ``n_points``, ``depth``, ``n_vertices_poisson``, ``n_faces_poisson``,
        ``density_threshold``, ``n_vertices_low_density``, ``hull_cut`` ("no hull",
        "applied" or why it was skipped), ``hull_points_outside_fraction`` (with a hull),
        ``n_vertices_outside_hull``, ``n_vertices``, ``n_faces``.

    Raises
    ------
    StageError
        With fewer than 10 points (nothing to reconstruct).

    References
    ----------
    Kazhdan & Hoppe (2013), Screened Poisson surface reconstruction.
    """
    import open3d as o3d

    p = _stack("points", points)
    n = _stack("normals", normals)
    if n.shape != p.shape:
        raise ValueError(f"normals must match points {p.shape}, got {n.shape}")
    if not 1 <= depth <= 14:
        raise ValueError(f"depth must be in 1..14, got {depth}")
    if not 0 <= density_quantile < 1:
        raise ValueError(f"density_quantile must be in [0, 1), got {density_quantile}")
    length = np.linalg.norm(n, axis=1)
    good = length > 1e-12
    p, n = p[good], n[good] / length[good, None]
    if len(p) < 10:
        raise StageError(f"Poisson fusion needs at least 10 oriented points, got {len(p)}")

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(p)
    pc.normals = o3d.utility.Vector3dVector(n)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pc, depth=depth, scale=scale, linear_fit=linear_fit, n_threads=n_threads)
    v = np.asarray(mesh.vertices).copy()
    f = np.asarray(mesh.triangles).astype(np.int64)
    dens = np.asarray(dens, dtype=np.float64)
    report: dict[str, Any] = dict(n_points=int(len(p)), depth=int(depth),
                                  n_vertices_poisson=int(len(v)), n_faces_poisson=int(len(f)))

    thr = float(np.quantile(dens, density_quantile)) if density_quantile > 0 and len(v) else 0.0
    keep = dens >= thr
    report.update(density_threshold=thr, n_vertices_low_density=int(np.count_nonzero(~keep)))
    v, f = remove_vertices(v, f, keep)

    report.update(hull_cut="no hull", n_vertices_outside_hull=0)
    if hull is not None:
        v, f = _cut_to_hull(v, f, p, hull, hull_margin_voxels, max_outside_fraction, report)
    report.update(n_vertices=int(len(v)), n_faces=int(len(f)))
    log.info("Poisson fusion: %d points -> %d vertices, %d faces (%d low density, %d outside "
             "hull)", len(p), len(v), len(f), report["n_vertices_low_density"],
             report["n_vertices_outside_hull"])
    return v, f, report


def fuse_tsdf(
    points: np.ndarray | list[np.ndarray],
    normals: np.ndarray | list[np.ndarray],
    sensor_origins: np.ndarray | list[np.ndarray],
    *,
    voxel_size: float = 0.5e-3,
    trunc_voxels: int = 4,
    confidences: np.ndarray | list[np.ndarray] | None = None,
    hull: Any = None,
    hull_margin_voxels: int = 1,
    max_outside_fraction: float = 0.05,
    min_weight: float = 0.5,
    min_cos_view: float = 0.1,
    max_voxels: int = 64_000_000,
    chunk_points: int = 50_000,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Volumetric fusion: a truncated signed distance field over the lines of sight, then
    marching cubes (Curless & Levoy 1996).

    Each measured point ``p`` (normal ``n`` toward the sensor, seen from ``o``) updates the
    voxels along its line of sight within ``±trunc`` of ``p`` (``trunc = trunc_voxels *
    voxel_size``): the ray is sampled every voxel and each sample splats into the 8 voxels
    around it (each voxel once per ray), so that the band is covered laterally as well.
    The value given to voxel centre ``x`` is the distance to the point's tangent plane,
    ``(x - p) . n``, clipped to ``±trunc``: positive in front of the surface (free space),
    negative behind it. Its weight is ``confidence * cos(view angle)`` (the angle between
    ``n`` and the direction to the sensor: grazing measurements are the least accurate),
    tapered linearly to 0 between ``-trunc/2`` and ``-trunc`` behind the surface. Points
    seen at ``cos < min_cos_view`` are dropped. The fused field is the weighted mean; a voxel
    is observed when its weight sum is at least ``min_weight``. The zero level set is
    extracted with scikit-image's marching cubes (Lewiner), where the voxels are
    observed, so no surface is invented between observed and unobserved space: a vertex is
    kept only when both voxels of the grid edge it lies on are observed.

    Parameters
    ----------
    points : (N, 3) float64, metres, or a list of per-sweep arrays
    normals : (N, 3) float64 (or list)
        Unit normals oriented toward the sensor (out of the object).
    sensor_origins : (N, 3) float64 (or list)
        Camera centre in ``base`` when each point was measured.
    voxel_size : float, metres
    trunc_voxels : int
        Half-width of the band around the surface, in voxels.
    confidences : (N,) float in [0, 1] (or list), optional
        Per-point confidence, multiplied into the weights (default 1).
    hull : VoxelGrid-like, optional
        Surface outside the hull (dilated by ``hull_margin_voxels``) is cut away.
    hull_margin_voxels : int
    max_outside_fraction : float
        As for :func:`fuse_poisson`: the cut is skipped when the points disagree with it.
    min_weight : float
        Smallest weight sum of an observed voxel.
    min_cos_view : float
        Points seen more obliquely than this cosine are not fused.
    max_voxels : int
        Largest dense grid allowed (memory: 16 bytes per voxel).
    chunk_points : int
        Points processed per vectorised batch (bounds memory).

    Returns
    -------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int64
        Triangles counter-clockwise seen from outside (normals point out of the object).
    report : dict
        ``n_points``, ``n_points_used``, ``voxel_size``, ``trunc``, ``grid_shape``,
        ``n_voxels_observed``, ``hull_cut``, ``hull_points_outside_fraction``,
        ``n_vertices_outside_hull``, ``n_vertices``, ``n_faces``.

    Raises
    ------
    StageError
        With no usable point, or a grid larger than ``max_voxels``.

    References
    ----------
    Curless, B. & Levoy, M. (1996). A volumetric method for building complex models from
    range images. SIGGRAPH.
    Lewiner, T. et al. (2003). Efficient implementation of marching cubes' cases with
    topological guarantees. Journal of Graphics Tools 8(2).
    """
    from skimage import measure

    p = _stack("points", points)
    n = _stack("normals", normals)
    o = _stack("sensor_origins", sensor_origins)
    if n.shape != p.shape or o.shape != p.shape:
        raise ValueError(f"normals and sensor_origins must match points {p.shape}, got "
                         f"{n.shape} and {o.shape}")
    if confidences is None:
        conf = np.ones(len(p))
    else:
        conf = (np.concatenate([np.asarray(c, dtype=np.float64).ravel() for c in confidences])
                if isinstance(confidences, list | tuple) else
                np.asarray(confidences, dtype=np.float64).ravel())
        if conf.shape != (len(p),) or not np.all(np.isfinite(conf)) or np.any(conf < 0):
            raise ValueError(f"confidences must be ({len(p)},) finite and >= 0, got "
                             f"{conf.shape}")
    if not voxel_size > 0 or trunc_voxels < 1:
        raise ValueError(f"voxel_size must be > 0 and trunc_voxels >= 1, got {voxel_size} "
                         f"and {trunc_voxels}")
    if not min_weight > 0:
        raise ValueError(f"min_weight must be > 0, got {min_weight}")

    ray = p - o
    dist = np.linalg.norm(ray, axis=1)
    nlen = np.linalg.norm(n, axis=1)
    ok = (dist > 0) & (nlen > 1e-12)
    d = np.zeros_like(ray)
    d[ok] = ray[ok] / dist[ok, None]
    nn = np.zeros_like(n)
    nn[ok] = n[ok] / nlen[ok, None]
    cos_view = -np.einsum("ij,ij->i", nn, d)
    use = ok & (cos_view >= min_cos_view) & (conf > 0)
    p, nn, d, w_pt = p[use], nn[use], d[use], (conf * cos_view)[use]
    report: dict[str, Any] = dict(n_points=int(len(use)), n_points_used=int(len(p)),
                                  voxel_size=float(voxel_size))
    if len(p) == 0:
        raise StageError("TSDF fusion: no point is usable (none seen from its sensor at "
                         f"cos(view angle) >= {min_cos_view} with confidence > 0)")

    trunc = trunc_voxels * voxel_size
    margin = trunc + 2 * voxel_size
    origin = p.min(axis=0) - margin
    shape = np.ceil((p.max(axis=0) + margin - origin) / voxel_size).astype(np.int64) + 1
    n_vox = int(np.prod(shape))
    if n_vox > max_voxels:
        raise StageError(f"TSDF grid {tuple(shape)} has {n_vox} voxels > max_voxels "
                         f"{max_voxels}; use a larger voxel_size")
    report.update(trunc=float(trunc), grid_shape=[int(x) for x in shape])

    sum_w = np.zeros(n_vox)
    sum_wd = np.zeros(n_vox)
    steps = np.arange(-trunc_voxels, trunc_voxels + 1) * voxel_size  # (K,)
    corners = np.indices((2, 2, 2)).reshape(3, -1).T  # (8, 3)
    for start in range(0, len(p), chunk_points):
        sl = slice(start, start + chunk_points)
        pc, nc, dc, wc = p[sl], nn[sl], d[sl], w_pt[sl]
        samples = pc[:, None, :] + steps[None, :, None] * dc[:, None, :]  # (M, K, 3)
        base_idx = np.floor((samples - origin) / voxel_size).astype(np.int64)
        vox = (base_idx[:, :, None, :] + corners[None, None]).reshape(len(pc), -1, 3)
        lin = np.ravel_multi_index((vox[..., 0], vox[..., 1], vox[..., 2]), tuple(shape))
        lin.sort(axis=1)
        first = np.ones_like(lin, dtype=bool)
        first[:, 1:] = lin[:, 1:] != lin[:, :-1]  # each voxel once per ray
        rows = np.nonzero(first)[0]
        lin_u = lin[first]
        x = origin + np.stack(np.unravel_index(lin_u, tuple(shape)), axis=1) * voxel_size
        sdf = np.einsum("ij,ij->i", x - pc[rows], nc[rows])
        w = wc[rows] * np.clip((sdf + trunc) / (0.5 * trunc), 0.0, 1.0)
        sdf = np.clip(sdf, -trunc, trunc)
        keep = w > 0
        sum_w += np.bincount(lin_u[keep], weights=w[keep], minlength=n_vox)
        sum_wd += np.bincount(lin_u[keep], weights=(w * sdf)[keep], minlength=n_vox)

    observed = (sum_w >= min_weight).reshape(tuple(shape))
    tsdf = np.full(n_vox, trunc)
    obs_flat = observed.ravel()
    tsdf[obs_flat] = sum_wd[obs_flat] / sum_w[obs_flat]
    tsdf = tsdf.reshape(tuple(shape))
    report["n_voxels_observed"] = int(np.count_nonzero(observed))
    has_surface = bool(np.any(tsdf[observed] < 0) and np.any(tsdf[observed] > 0))
    if not has_surface:
        v = np.zeros((0, 3))
        f = np.zeros((0, 3), dtype=np.int64)
    else:
        # (marching cubes' "descent": values decrease into the object; here they are
        # negative inside, and measured, this orientation gives outward normals)
        v, f, _, _ = measure.marching_cubes(tsdf, level=0.0, gradient_direction="descent",
                                            allow_degenerate=False)
        f = f.astype(np.int64)
        # keep only vertices on grid edges whose two voxels are both observed: unobserved
        # voxels hold a placeholder (+trunc) whose crossings are not surface
        q = v.astype(np.float64)  # voxel index coordinates
        lo = np.clip(np.floor(q + 1e-3).astype(np.int64), 0, shape - 1)
        hi = np.clip(np.ceil(q - 1e-3).astype(np.int64), 0, shape - 1)
        good = (observed[lo[:, 0], lo[:, 1], lo[:, 2]] & observed[hi[:, 0], hi[:, 1], hi[:, 2]])
        v, f = remove_vertices(origin + q * voxel_size, f, good)
    report.update(hull_cut="no hull", n_vertices_outside_hull=0)
    if hull is not None:
        v, f = _cut_to_hull(v, f, p, hull, hull_margin_voxels, max_outside_fraction, report)
    report.update(n_vertices=int(len(v)), n_faces=int(len(f)))
    log.info("TSDF fusion: %d points, grid %s, %d observed voxels -> %d vertices, %d faces",
             len(p), tuple(shape), report["n_voxels_observed"], len(v), len(f))
    return v, f, report
