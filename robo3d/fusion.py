"""Geometric fusion: one surface from the aligned laser points, bounded by the visual hull.

:func:`fuse_poisson` is screened Poisson surface reconstruction (Kazhdan & Hoppe 2013, the
authors' implementation as shipped in Open3D) of the oriented points, followed by two cuts:

1. **Density trim.** Poisson closes the surface everywhere, also where no point was
   measured (e.g. the face resting on the table). Open3D reports, per vertex, the density
   of input samples that supported it; vertices whose density is below the
   ``density_quantile`` quantile are removed with the triangles that use them.
2. **Hull cut.** Where a visual hull is given, surface outside the hull dilated by
   ``cut_margin_voxels`` voxels is removed: the true surface lies inside the hull
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

:func:`fuse_tsdf` (the pipeline's default) is volumetric fusion after Curless & Levoy
(1996): each sweep is range data, triangulated into its range surface
(:func:`range_surface`); every voxel near it gets the signed distance to it along the line
of sight (ray cast through the voxel, Open3D/Embree), weighted by the cosine of the view
angle, the points' confidence and a ramp at the range surface's border; a voxel is
observed when its summed weight reaches ``min_weight`` (no surface from a single grazing
view). The lines of sight carve the space in front of the surface. Where the laser saw
nothing, the visual hull bounds the space and closes the holes: unobserved voxels inside
the hull that were not seen empty are solid (C & L's hole filling with the hull as the
"unseen" boundary), so the mesh is watertight; the report gives the fraction of its area
from the laser and from the hull. Marching cubes (Lewiner) extracts the surface. Laser
points outside the hull are kept (the laser is the accurate measurement; the hull may be
eroded by a segmentation error): their count is reported.

In steps (:func:`fuse_tsdf`):

1. Each scan (one laser sweep) is triangulated into its range surface
   (:func:`range_surface`).
2. For every voxel (:func:`data_voxel`: ``tsdf_voxel_m``, or coarser where the laser
   sampled coarser) within ``±trunc`` (``tsdf_trunc_voxels`` voxels) of a scan, the
   signed distance to that scan's range surface is found *along the line of sight*
   (the sight line of the nearest measured point), by casting a ray through the voxel
   centre (Open3D / Embree), and stored as the distance along the surface's normal
   (point-to-plane: the ray's distance times ``cos`` of the view angle at the hit):
   positive in front of the surface, negative behind. The ray starts ``trunc / cos`` in
   front, so that a surface seen at a grazing angle still gives the voxels within
   ``trunc`` of it a distance (along the line of sight alone it reaches ``trunc * cos``
   of them, less than a voxel at 85 degrees: a cup's inner wall, seen only that way, was
   left to the hull). Scans seen at different angles then agree on one distance.
3. Its weight is ``cos(view angle)`` at the hit (grazing views count little) times the
   points' confidence and a ramp that falls to ``border_weight_floor`` (0.1) at the range
   surface's border (over ``border_ramp_m`` or one sample step, whichever is longer: where
   scans overlap, the one whose interior it is outweighs the one whose edge it is; not to
   0, which threw away surface that only one scan's edge saw: a strip of a thin wall one
   or two profiles wide, thin_wall/4 of the objects benchmark missing 1.1 % of what the
   laser could observe), tapered to 0 behind the
   surface between half and all of ``trunc * cos`` (as deep as the line of sight
   says; at least one voxel: two moved a thin wall's other face, user_mesh/7 0.08 %
   of the measured area > 0.5 mm off against 0.02 %). The TSDF is the weighted mean
   over scans; a voxel is *observed* when its weight sum reaches ``min_weight``
   (0.003: in effect, when any scan saw it at ``cos >= min_cos_view``, 88 degrees; the
   weights decide between scans that disagree, not whether a lone grazing measurement
   counts: on the objects benchmark the cup's inner wall, seen only at 84-88 degrees by
   one sweep, measured 0.03 mm median and was labelled inferred at 0.05;
   ``benchmarks/README.md``).
4. Space carving: voxels along each line of sight in front of the surface are seen
   empty (``carve_free_space``).
5. Hole filling (``fill_holes``, with a hull): an unobserved voxel is empty when it
   was seen empty or lies outside the hull, and solid otherwise, so that where the
   laser saw nothing the surface is the boundary between the space seen empty and the
   hull; the solid/empty indicator is smoothed over one voxel for a smooth surface.
   Without a hull no surface is made where nothing was observed. Space outside the
   workspace box (``workspace``: the box the laser points were cropped to; below its
   floor lies the table) is empty and never observed, so the face on the table is
   closed at the floor, inferred. A hull that more than ``max_outside_hull_fraction`` of
   the measured solid voxels lies outside is no bound on the object (silhouettes that
   failed alike in many views) and closes nothing (``hull_contradicted`` in the report).
6. Marching cubes (Lewiner) at level 0. Each vertex gets its provenance
   (:data:`SOURCES`): *measured* when it lies on a grid edge between two observed
   voxels, else *inferred*: from the hull when one of the edge's voxels lies within
   two voxels of the outside of the hull (the surface there is the hull's, moved by
   the one-voxel smoothing), else *filled* (a gap closed between
   the space seen empty and the solid, next to measurements). And its evidence: the
   number of scans that observed it, their weighted mean incidence ``cos``, the TSDF
   weight, the distance to the nearest measured point, and a ``confidence`` in
   [0, 1] (0 for inferred vertices, see :func:`_vertex_confidence`).
7. ``close`` chooses what is done where the laser saw nothing: ``hull`` closes every
   hole (step 5, watertight); ``free_space`` closes only what lies within
   ``max_fill_distance_mm`` of a measured point and leaves the mesh open farther away
   (an inferred patch that far is invention; in the other modes it is kept and
   marked ``far_from_measured``); ``none`` keeps only measured surface.
   Inferred surface never moves measured surface: observed voxels keep their TSDF.

Why not Open3D's own TSDF: its integration takes depth images from pinhole cameras and
weighs every observation 1 (no view-angle weights); a laser sweep is a push-broom scan
whose lines of sight change along the sweep, and a single stripe image is a one-pixel
wide depth image. ``benchmarks/pipeline.py`` measures Open3D's tensor ``VoxelBlockGrid``
on the same sweeps rendered into depth images, for speed and accuracy.

Choice: the range surface is triangulated on the sweep's range-image grid (frame x image
line, kept per point by the triangulation: the order in which the sensor sampled the
surface), as Curless & Levoy triangulate a range image; where the clouds do not carry it,
after a parallel projection along the sweep's mean line of sight. A triangle whose longest
edge exceeds twice the local sampling (the median longest edge of the triangles at its
sparsest-sampled vertex, or of the whole scan where that is larger) bridges a depth jump
and is dropped: a surface seen at a grazing angle is sampled 3 mm apart where the rest of
the scan is 1 mm apart, and is not a jump. A triangle longer than twice the scan's median
is kept only where its normal agrees with its points' (within 25 degrees): a bridge
between a thin wall and what lies behind it can be sparse on both sides too. A triangle
that joins laser frames more than ``max_frame_span`` (2) apart is dropped as well: the
frames between found no stripe there, so the laser did not see what it spans; where a
scan is sparse everywhere (a black cup returning the stripe in half its frames), the
local sampling is no test of that.

References
----------
Curless, B. & Levoy, M. (1996). A volumetric method for building complex models from range
images. SIGGRAPH.
Kazhdan, M. & Hoppe, H. (2013). Screened Poisson surface reconstruction. ACM TOG 32(3).
Lewiner, T. et al. (2003). Efficient implementation of marching cubes' cases with
topological guarantees. Journal of Graphics Tools 8(2).
Laurentini, A. (1994). The visual hull concept for silhouette-based image understanding.
IEEE PAMI 16(2).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from .errors import NoUsablePoints, StageError
from .options import Options

__all__ = ["FuseOptions", "fuse_poisson", "fuse_tsdf", "data_voxel", "point_spacing",
           "profile_spacing", "range_surface", "crop_mesh_to_hull", "remove_vertices",
           "SOURCES", "CLOSE_MODES", "face_source", "source_area_fractions", "keep_vertices"]

#: SciPy KD-tree options for nearest-point queries from far away (fused vertices on
#: hull-closed surface centimetres from the laser's dense lines): the default tree
#: (balanced, nodes shrunk to their points) took 5.1 s for the 337,123 vertices of issue
#: 11's cup/4 at 1280 x 960, these 0.6 s, with the same neighbours (exact either way;
#: ``benchmarks/README.md``, stop 48). Queries near the points gain nothing from them.
KD_FAR = {"balanced_tree": False, "compact_nodes": False}

#: Provenance of a fused vertex (the ``source`` vertex property of fused.ply and mesh.ply):
#: its index here. ``measured``: on the laser's observed surface; ``hull``: inferred, the
#: visual hull's surface where the laser saw nothing; ``filled``: inferred, a gap closed
#: between the laser's observed and seen-empty space.
SOURCES: tuple[str, ...] = ("measured", "hull", "filled")
MEASURED, HULL, FILLED = 0, 1, 2
#: Vertex colours of each provenance (:data:`SOURCES`) wherever a mesh is coloured by it:
#: fused.ply and mesh.ply, their rerun logs, results.mcap and the report's pictures:
#: measured grey, inferred from the hull orange, filled yellow.
SOURCE_RGB = np.array([[190, 190, 190], [240, 120, 30], [240, 210, 40]], dtype=np.uint8)


def source_colors(source: np.ndarray) -> np.ndarray:
    """RGB (uint8) per vertex for its provenance (:data:`SOURCES`; an unknown code takes
    the last colour)."""
    return SOURCE_RGB[np.clip(np.asarray(source, np.int64), 0, len(SOURCE_RGB) - 1)]
#: Coarsening of the grid on which the lines of sight carve beyond ``carve_depth_m``.
_FAR = 4
#: What fusion does where the laser saw nothing (``fusion.close``).
CLOSE_MODES: tuple[str, ...] = ("hull", "free_space", "none")


@dataclass(frozen=True)
class FuseOptions(Options):
    """The parameters of :func:`fuse_tsdf` and :func:`fuse_poisson` (config section
    ``fusion``; ``method`` and ``crop_to_hull`` are the stage's: they choose the
    algorithm and whether it gets the hull), and the recording's seed.

    Attributes
    ----------
    tsdf_voxel_m : float, metres
        The TSDF grid's finest voxel: the voxel is the largest of this,
        ``tsdf_voxel_per_spacing`` times the laser points' spacing and
        ``tsdf_voxel_per_footprint`` times the square root of each point's footprint.
    tsdf_voxel_per_spacing : float
        The voxel is at least this many times the median distance between neighbouring
        laser points of a scan (the sensor's sampling along its line); 0: always
        ``tsdf_voxel_m``. A grid finer than the data adds faces, not detail: see
        :func:`data_voxel`.
    tsdf_voxel_per_footprint : float
        The voxel is at least this many times ``sqrt(spacing x profile spacing)``, the
        side of the square each laser point stands for (the profile spacing: the median
        distance from a point to the next laser frame's profile, :func:`profile_spacing`);
        0: no such bound (nor with ``tsdf_voxel_per_spacing`` 0, which measures no
        spacing). Sweeps of few frames leave their profiles millimetres apart.
    tsdf_trunc_voxels : int
        Half-width of the band around each range surface, in voxels.
    min_weight : float
        Least weight sum of an observed voxel (module docstring, step 3).
    min_cos_view : float
        Points and range triangles seen more obliquely are not used (0.03: 88 degrees).
    max_frame_span : int
        A range triangle joins laser frames at most this many frames apart (2: one frame
        without a stripe there is bridged); a wider one bridges surface the laser did
        not see and is not measured (:func:`range_surface`). 0: any.
    border_weight_floor : float in [0, 1]
        The weight ramp at a range surface's border starts at this (step 3; 0 is Curless
        & Levoy's ramp to zero, which drops what only a scan's edge saw).
    fill_holes : bool
        With a hull: unobserved space inside it and not seen empty is solid (step 5).
    close : {"hull", "free_space", "none"}
        Where the laser saw nothing: close from the hull, close only near measurements,
        or leave open (step 7).
    max_fill_distance_mm : float, millimetres
        Inferred surface farther than this from every measured point is marked
        ``far_from_measured`` (and, with ``close="free_space"``, left out).
    max_outside_hull_fraction : float in (0, 1]
        When more than this share of the measured solid voxels lies outside the hull,
        the hull contradicts the laser (silhouettes that failed in many views) and
        closes nothing: the mesh is the measured surface (step 5).
    carve_depth_m : float, metres
        How far in front of the surface the lines of sight carve at the grid's
        resolution.
    carve_full_line : bool
        Beyond ``carve_depth_m`` the lines of sight carve on to the sensor or the grid's
        border, on a grid 4 times coarser (a cup's opening: the lines that saw its
        inside pass through it; the hull would close it). Only where the laser observed
        nothing is carved space used, so a coarse voxel carved beside a line moves
        inferred surface only (by at most 1.5 fine voxels).
    carve_free_space : bool
        The lines of sight carve the space in front of the surface (step 4).
    hull_margin_voxels : int
        Dilation of the hull (hull voxels) before the TSDF uses it.
    poisson_depth : int
        Octree depth of screened Poisson.
    density_quantile : float in [0, 1)
        Low-density Poisson vertices trimmed.
    seed : int
        The recording's seed (config ``seed``; both methods are deterministic).
    """

    section = "fusion"
    not_in_config = ("seed",)
    tsdf_voxel_m: float = 0.0004
    tsdf_voxel_per_spacing: float = 1.25
    tsdf_voxel_per_footprint: float = 0.5
    tsdf_trunc_voxels: int = 4
    min_weight: float = 0.003
    min_cos_view: float = 0.03
    max_frame_span: int = 2
    border_weight_floor: float = 0.1
    fill_holes: bool = True
    close: Literal["hull", "free_space", "none"] = "hull"
    max_fill_distance_mm: float = 3.0
    max_outside_hull_fraction: float = 0.2
    carve_depth_m: float = 0.02
    carve_full_line: bool = True
    carve_free_space: bool = True
    hull_margin_voxels: int = 0
    poisson_depth: int = 9
    density_quantile: float = 0.02
    seed: int = 0

log = logging.getLogger(__name__)

#: Least depth of the band behind a range surface, in voxels (step 3): a line of sight at
#: a grazing angle reaches only ``trunc * cos`` behind the surface, less than a voxel.
_BEHIND_MIN_VOXELS = 1.0

#: Least |cos| between a sparse-sampled range triangle's normal and its points' normals
#: (25 degrees; :func:`range_surface`).
_RELAXED_MIN_NORMAL_COS = 0.9


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
    options: FuseOptions = FuseOptions(),
    hull: Any = None,
    cut_margin_voxels: int = 1,
    max_outside_fraction: float = 0.05,
    scale: float = 1.1,
    linear_fit: bool = False,
    n_threads: int = 1,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Screened Poisson surface from oriented points, trimmed by density and by the hull.

    Parameters
    ----------
    points : (N, 3) float64, metres, or a list of per-sweep (N_s, 3) arrays
        Aligned laser points in ``base``.
    normals : (N, 3) float64, or a list like ``points``
        Outward unit normals.
    options : FuseOptions
        ``poisson_depth`` (octree depth: the finest cells are ``scale * extent /
        2**depth`` wide) and ``density_quantile`` (vertices whose support density is
        below this quantile are removed, 0 keeps all).
    hull : VoxelGrid-like, optional
        ``origin``, ``voxel_size``, ``occupancy``: surface outside it is cut away.
    cut_margin_voxels : int
        Dilation of the hull before the cut. Not the config's ``hull_margin_voxels``
        (the TSDF's, whose hull is smoothed and taken at its 0.5 level): the cut tests
        the nearest voxel of the hull as carved and needs a voxel of slack
        (``benchmarks/README.md``).
    max_outside_fraction : float
        The cut is skipped (and the report says why) when more than this fraction of the
        input points lie outside the dilated hull: hull and laser then disagree.
    scale : float
        Ratio of the reconstruction cube to the points' bounding cube (Poisson's ``scale``).
    linear_fit : bool
        Place iso-vertices by linear interpolation (more accurate on smooth surfaces).
    n_threads : int
        Poisson solver threads; 1 (default) is reproducible bit for bit, -1 uses all cores.

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
    NoUsablePoints
        With fewer than 10 points (nothing to reconstruct; a StageError).

    References
    ----------
    Kazhdan & Hoppe (2013), Screened Poisson surface reconstruction.
    """
    import open3d as o3d

    depth, density_quantile = options.poisson_depth, options.density_quantile
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
        raise NoUsablePoints(f"Poisson fusion needs at least 10 oriented points, got {len(p)}")

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
        v, f = _cut_to_hull(v, f, p, hull, cut_margin_voxels, max_outside_fraction, report)
    report.update(n_vertices=int(len(v)), n_faces=int(len(f)))
    log.info("Poisson fusion: %d points -> %d vertices, %d faces (%d low density, %d outside "
             "hull)", len(p), len(v), len(f), report["n_vertices_low_density"],
             report["n_vertices_outside_hull"])
    return v, f, report


def _as_list(name: str, a: object, dims: int) -> list[np.ndarray]:
    """A list of per-sweep arrays (one array = one sweep)."""
    items = list(a) if isinstance(a, list | tuple) else [a]
    out = []
    for k, x in enumerate(items):
        arr = np.asarray(x, dtype=np.float64)
        arr = arr.reshape(-1, 3) if dims == 2 and arr.size == 0 else arr
        if dims == 2 and (arr.ndim != 2 or arr.shape[1] != 3):
            raise ValueError(f"{name}[{k}] must be (N, 3), got {arr.shape}")
        if dims == 1:
            arr = arr.reshape(-1)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name}[{k}] contains non-finite values")
        out.append(arr)
    return out


def range_surface(points: np.ndarray, sensor_origins: np.ndarray, *,
                  grid: np.ndarray | None = None, normals: np.ndarray | None = None,
                  max_edge_factor: float = 2.0, min_cos_view: float = 0.1,
                  max_frame_span: int = 0
                  ) -> tuple[np.ndarray, dict[str, Any]]:
    """Triangulate one range scan (a sweep) into its range surface.

    The points are triangulated in 2D (Delaunay) on the scan's range-image grid
    ``grid`` when given, else after a parallel projection along the scan's mean line of
    sight. A triangle is dropped when an edge is longer than ``max_edge_factor`` times
    the median longest edge (a depth jump: two surfaces that only look adjacent; with
    ``grid`` and ``normals``, of the triangles at its sparsest-sampled vertex where that is
    longer and the triangle's normal is within 25 degrees of its points'), or when it is
    seen at a grazing angle (``|cos| < min_cos_view``, steep triangles bridge
    jumps too). With ``grid`` and ``max_frame_span``, a triangle joining laser frames
    more than that many frames apart is dropped too: the frames between them have no
    stripe there, the laser did not see that surface, and a bridge over them is a guess
    (random scene 299, a black cup that returned the stripe in 20 of a sweep's 40
    frames: its second sweep's triangles over 6-32 frames covered 5,093 mm2, 80 % of
    that area more than 0.5 mm off; on the simulated cup/4, 4.6 of 31,200 mm2 span more
    than 2 frames).

    Parameters
    ----------
    points : (N, 3) float64, metres
    sensor_origins : (N, 3) float64, metres
        Sensor position at each point's frame.
    grid : (N, 3) int, optional
        Each point's laser frame, image line and that frame's search axis
        (:meth:`robo3d.artefacts.SweepCloud.grid`); triangles join points of one axis.
    normals : (N, 3) float, optional
        The points' unit normals (the triangulation's), for the sparse-sampling test.
    max_edge_factor : float
    min_cos_view : float
    max_frame_span : int
        Largest difference of laser frames in one triangle (``grid``'s first column);
        0: any (:attr:`FuseOptions.max_frame_span`).

    Returns
    -------
    faces : (T, 3) int64
        Indices into ``points``, counter-clockwise seen from the sensor.
    report : dict
        ``n_triangles_delaunay``, ``n_triangles``, ``max_edge_m`` and, with
        ``max_frame_span`` (and ``grid``), ``n_triangles_over_frames`` (those it
        dropped).

    References
    ----------
    Curless & Levoy (1996), section 4 (range images triangulated into range surfaces).
    """
    from scipy.spatial import Delaunay

    p = np.asarray(points, dtype=np.float64)
    o = np.asarray(sensor_origins, dtype=np.float64)
    if p.shape != o.shape or p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points and sensor_origins must both be (N, 3), got {p.shape} and "
                         f"{o.shape}")
    empty = np.zeros((0, 3), dtype=np.int64)
    if len(p) < 3:
        return empty, {"n_triangles_delaunay": 0, "n_triangles": 0, "max_edge_m": None}
    if grid is not None:
        g = np.asarray(grid, dtype=np.int64)
        if g.shape != (len(p), 3):
            raise ValueError(f"grid must be (N, 3) (frame, line, axis) like points, got "
                             f"{g.shape}")
        uv = g[:, :2].astype(np.float64)
    else:
        los = p - o
        los /= np.maximum(np.linalg.norm(los, axis=1, keepdims=True), 1e-12)
        w = los.mean(axis=0)
        w /= np.linalg.norm(w)
        a = np.cross(w, [1.0, 0.0, 0.0] if abs(w[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(w, a)
        uv = np.stack([p @ a, p @ b], axis=1)
    try:
        tri = Delaunay(uv - uv.mean(axis=0)).simplices.astype(np.int64)
    except Exception:  # degenerate input (collinear): no surface
        return empty, {"n_triangles_delaunay": 0, "n_triangles": 0, "max_edge_m": None}
    if grid is not None:  # frames searched along other image axes are not neighbours
        ax = g[tri, 2]
        tri = tri[(ax[:, 0] == ax[:, 1]) & (ax[:, 1] == ax[:, 2])]
        if not len(tri):
            return empty, {"n_triangles_delaunay": 0, "n_triangles": 0, "max_edge_m": None}
    v0, v1, v2 = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    longest = _longest_edge(p, tri)
    max_edge = float(max_edge_factor * np.median(longest))
    nrm = np.cross(v1 - v0, v2 - v0)
    area2 = np.linalg.norm(nrm, axis=1)
    nrm = nrm / np.maximum(area2, 1e-30)[:, None]
    sight = (o[tri[:, 0]] + o[tri[:, 1]] + o[tri[:, 2]]) / 3 - (v0 + v1 + v2) / 3
    sight /= np.maximum(np.linalg.norm(sight, axis=1, keepdims=True), 1e-12)
    cos = np.einsum("ij,ij->i", nrm, sight)
    short = longest <= max_edge
    long_ = ~short
    if grid is not None and normals is not None and long_.any():
        # a triangle longer than the scan's threshold is kept where the local sampling
        # is that sparse AND it lies along its points' surface: normals (the
        # triangulation's, from the range-image grid) within 25 degrees of its own; a
        # bridge over a depth jump does not (thin_wall/7: 0.09 % of the measured area
        # > 0.5 mm off without)
        local = max_edge_factor * _local_edge_scale(tri, longest, len(p))[long_]
        agree = np.min(np.abs(np.einsum("tkj,tj->tk", np.asarray(normals)[tri[long_]],
                                        nrm[long_])), axis=1)
        short[long_] = (longest[long_] <= local) & (agree >= _RELAXED_MIN_NORMAL_COS)
    keep = short & (np.abs(cos) >= min_cos_view) & (area2 > 0)
    extra = {}
    if grid is not None and max_frame_span > 0:
        fr = g[tri, 0]
        over = fr.max(axis=1) - fr.min(axis=1) > int(max_frame_span)
        extra["n_triangles_over_frames"] = int(np.count_nonzero(keep & over))
        keep &= ~over
    faces = tri[keep]
    flip = cos[keep] < 0  # wind counter-clockwise as seen from the sensor
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return faces, {"n_triangles_delaunay": int(len(tri)), "n_triangles": int(len(faces)),
                   "max_edge_m": max_edge, **extra}


def _longest_edge(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Length of each triangle's longest edge."""
    v0, v1, v2 = p[tri[:, 0]], p[tri[:, 1]], p[tri[:, 2]]
    return np.max(np.stack([np.linalg.norm(v1 - v0, axis=1), np.linalg.norm(v2 - v1, axis=1),
                            np.linalg.norm(v0 - v2, axis=1)]), axis=0)


def _local_edge_scale(tri: np.ndarray, longest: np.ndarray, n: int) -> np.ndarray:
    """Per triangle, the smallest over its vertices of the median longest edge of the
    triangles at a vertex: the sampling the scan has there (at a depth jump one side's
    vertices keep their neighbours' short edges, so the jump's triangles stay long)."""
    return _vertex_median(tri, longest, n)[tri].min(axis=1)


def _vertex_median(tri: np.ndarray, value: np.ndarray, n: int) -> np.ndarray:
    """Per vertex, the LOWER median of a per-triangle ``value`` over the triangles at it
    (inf where no triangle uses it). The lower one, not scipy's ``ndimage.median``
    (the mean of the two middle values): at a vertex with as many bridging triangles as
    regular ones it stays the regular length, so the bridges stay cut (with the mean,
    thin_wall/7's measured area > 0.5 mm off went 0.006 % -> 0.04 %)."""
    vv = tri.ravel()
    ll = np.repeat(value, 3)
    order = np.lexsort((ll, vv))
    count = np.bincount(vv, minlength=n)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    vmed = np.full(n, np.inf)
    has = count > 0
    vmed[has] = ll[order][start[has] + (count[has] - 1) // 2]
    return vmed


def _boundary_ramp(points: np.ndarray, faces: np.ndarray, ramp: float,
                   floor: float = 0.0) -> np.ndarray:
    """Per-vertex weight rising from ``floor`` on the range surface's border to 1 at
    ``ramp`` metres inside it (Curless & Levoy: weights fall off toward the edges of a
    scan); 0 for the vertices of no triangle."""
    from scipy.spatial import cKDTree

    w = np.zeros(len(points))
    if len(faces) == 0:
        return w
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e.sort(axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    border = np.unique(uniq[count == 1].ravel())
    used = np.unique(faces.ravel())
    if ramp <= 0 or len(border) == 0:
        w[used] = 1.0
        return w
    d, _ = cKDTree(points[border]).query(points[used], k=1)
    # at least one sample step where the scan is sparse (a surface seen at a grazing
    # angle): else every vertex of a sparse strip would lie on the ramp, weighing ~0
    ramp = np.maximum(ramp, _vertex_median(faces, _longest_edge(points, faces),
                                           len(points))[used])
    w[used] = floor + (1.0 - floor) * np.clip(d / ramp, 0.0, 1.0)
    return w


def _hull_field(hull: Any, grid_origin: np.ndarray,
                voxel_size: float, shape: tuple[int, int, int], margin_voxels: int,
                smooth_sigma: float) -> np.ndarray:
    """Whether each voxel of the fusion grid is inside the hull, from the hull's smoothed
    occupancy (0.5 level, trilinear), dilated by ``margin_voxels`` hull voxels."""
    from scipy import ndimage

    h_origin, h_vs, occ = _dilated_hull(hull, margin_voxels)
    field = ndimage.gaussian_filter(occ.astype(np.float32), smooth_sigma) if smooth_sigma > 0 \
        else occ.astype(np.float32)
    # both grids are axis-aligned, so the trilinear interpolation is three linear ones,
    # one axis at a time (what scipy.ndimage.map_coordinates(order=1, mode="constant")
    # gives, 0 off the hull's grid): the simulated cup/4's 11.4 million fusion voxels in
    # 0.16 s instead of 1.5 s, 3 voxels of 5.6 million inside flipping at the 0.5 level
    # (map_coordinates' coordinates were float32)
    for k in range(3):  # fusion voxel index -> hull voxel coordinates
        c = (grid_origin[k] + np.arange(shape[k], dtype=np.float64) * voxel_size
             - h_origin[k]) / h_vs
        field = _linear_along(field, k, c)
    return field > 0.5


def _linear_along(f: np.ndarray, axis: int, c: np.ndarray) -> np.ndarray:
    """``f`` sampled along ``axis`` at the fractional indices ``c`` by linear
    interpolation, 0 outside ``[0, n - 1]`` (float32)."""
    n = f.shape[axis]
    valid = (c >= 0.0) & (c <= n - 1)
    i0 = np.clip(np.floor(c).astype(np.int64), 0, max(n - 2, 0))
    i1 = np.minimum(i0 + 1, n - 1)
    t = np.clip(c - i0, 0.0, 1.0)
    shape = [1] * f.ndim
    shape[axis] = -1
    w0 = np.where(valid, 1.0 - t, 0.0).astype(np.float32).reshape(shape)
    w1 = np.where(valid, t, 0.0).astype(np.float32).reshape(shape)
    return np.take(f, i0, axis=axis) * w0 + np.take(f, i1, axis=axis) * w1


def fuse_tsdf(
    points: np.ndarray | list[np.ndarray],
    normals: np.ndarray | list[np.ndarray],
    sensor_origins: np.ndarray | list[np.ndarray],
    *,
    options: FuseOptions = FuseOptions(),
    confidences: np.ndarray | list[np.ndarray] | None = None,
    grids: list[np.ndarray | None] | None = None,
    hull: Any = None,
    workspace: tuple[np.ndarray, np.ndarray] | None = None,
    carve_only: list[np.ndarray] | None = None,
    threads: int = 1,
    return_attributes: bool = False,
    hull_smooth_vox: float = 0.8,
    max_edge_factor: float = 2.0,
    border_ramp_m: float = 1.0e-3,
    interp_sigma_m: float = 0.0,
    interp_floor: float = 0.05,
    max_voxels: int = 64_000_000,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]] | tuple[np.ndarray, np.ndarray,
                                                           dict[str, Any], dict[str, np.ndarray]]:
    """Volumetric fusion of range scans after Curless & Levoy (1996), bounded and closed by
    the visual hull: the steps 1-7 of the module docstring.

    Parameters
    ----------
    points : (N, 3) float64, metres, or a list of per-sweep arrays
        One array per range scan (sweep).
    normals : like ``points``
        Unit normals (used for the view-angle check of the points; the weights use the
        range surface's own normals).
    sensor_origins : like ``points``
        Sensor position when each point was measured.
    options : FuseOptions
        The ``fusion`` section's parameters (:class:`FuseOptions`): ``tsdf_voxel_m``,
        ``tsdf_trunc_voxels`` (half-width of the band around each range surface, in
        voxels), ``hull_margin_voxels``, ``fill_holes``, ``carve_free_space``,
        ``min_weight``, ``min_cos_view``, ``carve_depth_m``, ``carve_full_line``,
        ``close`` and ``max_fill_distance_mm`` (steps 2-7).
    confidences : (N,) float in [0, 1] or list, optional
        Per-point confidence (default 1); 0 removes a point.
    grids : list of (N, 3) int or None, optional
        Per scan, its points' range-image grid (:meth:`~robo3d.artefacts.SweepCloud.grid`)
        for the range surface (:func:`range_surface`); None where unknown.
    hull : VoxelGrid-like, optional
        ``origin``, ``voxel_size``, ``occupancy``: bounds and closes the surface.
    workspace : ((3,), (3,)) float, metres, optional
        The workspace box ``(min, max)`` in ``base`` the points were cropped to: space
        outside it is empty and makes no surface (a sweep's band behind the surface
        reaches beyond it; on the objects benchmark it left a flap of inferred surface
        under the cup's bottom edge, below the box's floor).
    carve_only : list of (N,) bool, optional
        Per scan, the points that only carve: their lines of sight carve the space in
        front of them (step 4), but they add no signed distance (no measured surface)
        and are not measurements for ``dist_measured_m`` (the table the object stands
        on, lit inside the box: it says where space is empty, it is not the object).
    hull_smooth_vox : float
        Gaussian smoothing of the hull's occupancy (hull voxels) before its 0.5 level.
    max_edge_factor : float
        Range-surface depth-jump threshold (:func:`range_surface`).
    border_ramp_m : float, metres
        Width of the weight ramp at range-surface borders.
    interp_sigma_m, interp_floor : float
        Weight of a hit falls as ``floor + (1 - floor) exp(-(d / sigma)^2)`` with its
        distance ``d`` to the nearest measured point of its triangle (0 disables).
    max_voxels : int
        Largest grid allowed (memory: about 10 bytes per voxel). A larger one is fused at
        a coarser voxel that fits (``report["voxel_coarsened_from"]``, a warning).
    threads : int
        Ray-casting and nearest-neighbour threads (results do not depend on it).
    return_attributes : bool
        Also return the per-vertex attributes (step 6).

    Returns
    -------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int64
        Counter-clockwise seen from outside.
    attributes : dict of str to (V,) array, with ``return_attributes``
        ``source`` (uint8, :data:`SOURCES`), ``n_obs`` (uint16), ``incidence``,
        ``tsdf_weight``, ``dist_measured_m``, ``confidence`` (float32), and
        ``far_from_measured`` (uint8: inferred and farther than ``max_fill_distance_mm``
        from every measured point).
    report : dict
        ``n_points``, ``n_points_used``, ``n_scans``, ``voxel_size``, ``trunc``,
        ``grid_shape``, ``n_voxels_observed``, ``n_voxels_seen_empty``,
        ``laser_area_fraction``, ``hull_area_fraction``, ``hull_fill`` (what was done),
        ``n_observed_voxels_outside_hull``, ``range_surfaces`` (per scan),
        ``n_range_triangles_over_frames`` (dropped by ``max_frame_span``), ``seconds``
        per step, ``n_vertices``, ``n_faces``.

    Raises
    ------
    NoUsablePoints
        With no usable point (a :class:`~robo3d.errors.StageError`).

    References
    ----------
    Curless & Levoy (1996); Lewiner et al. (2003), marching cubes with topological
    guarantees; Laurentini (1994): the module's references.
    """
    import time

    clock: dict[str, float] = {}
    t_start = time.perf_counter()
    o = options
    P, N, O, Cf, G, n_total = _tsdf_inputs(points, normals, sensor_origins, confidences,
                                           grids, o, carve_only)
    # the measured points (a carve-only point has weight 0: no surface of its own)
    Pm = [p[c > 0] for p, c in zip(P, Cf, strict=True)]
    n_used = int(sum(len(p) for p in Pm))
    n_carve = int(sum(len(p) for p in P)) - n_used
    if n_used == 0:
        raise NoUsablePoints("TSDF fusion: no point is usable (none seen from its sensor at "
                         f"cos(view angle) >= {o.min_cos_view} with confidence > 0)")
    across = (profile_spacing(Pm, [None if g is None else g[c > 0]
                                   for g, c in zip(G, Cf, strict=True)])
              if o.tsdf_voxel_per_footprint > 0 and o.tsdf_voxel_per_spacing > 0 else None)
    voxel_size, spacing = data_voxel(Pm, o, threads=threads, profile_spacing_m=across)
    bounds = _voxel_bounds(o, spacing, across)
    voxel_from = max(bounds, key=bounds.__getitem__)
    trunc_voxels = o.tsdf_trunc_voxels
    report: dict[str, Any] = dict(n_points=n_total, n_points_used=n_used,
                                  n_points_carve_only=n_carve, n_scans=len(P),
                                  voxel_size=float(voxel_size), point_spacing_m=spacing,
                                  profile_spacing_m=across,
                                  voxel_from_spacing=voxel_from != "tsdf_voxel_m",
                                  voxel_from=voxel_from)
    trunc = trunc_voxels * voxel_size
    allp = np.concatenate(P)
    origin, shape, shift = _tsdf_grid(allp, hull, voxel_size, trunc)
    n_vox = int(np.prod(shape))
    if n_vox > max_voxels:
        # a scene larger than the grid allows at this voxel (a loose hull from few views,
        # the laser's line far across the table): a coarser voxel, said so, not a failure
        fine, n = voxel_size, n_vox
        for _ in range(8):  # the margin grows with the voxel: a few steps settle it
            voxel_size *= (1.02 * n / max_voxels) ** (1.0 / 3.0)
            trunc = trunc_voxels * voxel_size
            origin, shape, shift = _tsdf_grid(allp, hull, voxel_size, trunc)
            n = int(np.prod(shape))
            if n <= max_voxels:
                break
        else:  # pragma: no cover - a grid whose margin alone exceeds the limit
            raise StageError(f"TSDF grid {shape} has {n} voxels > max_voxels {max_voxels}; "
                             "use a larger voxel_size")
        report.update(voxel_size=float(voxel_size), voxel_coarsened_from=float(fine),
                      voxel_from="max_voxels", voxel_from_spacing=False,
                      voxel_coarsened_why=f"the grid at {fine * 1e3:.3f} mm would have had "
                      f"{n_vox} voxels, more than max_voxels {max_voxels}")
        log.warning("TSDF fusion: the points and the hull span a grid of %d voxels at "
                    "%.3f mm, more than %d: fused at %.3f mm instead", n_vox, fine * 1e3,
                    max_voxels, voxel_size * 1e3)
    report.update(trunc=float(trunc), grid_shape=list(shape), grid_origin=origin.tolist())
    clock["setup"] = time.perf_counter() - t_start
    acc, scans = _integrate_scans(P, N, O, Cf, G, origin, shape, shift, voxel_size, o, threads,
                                  clock,
                                  max_edge_factor=max_edge_factor, border_ramp_m=border_ramp_m,
                                  interp_sigma_m=interp_sigma_m, interp_floor=interp_floor)
    ta = time.perf_counter()
    tsdf, observed, inside, filled = _tsdf_field(acc, shape, trunc, hull, origin, voxel_size,
                                                 hull_smooth_vox, o, scans, report,
                                                 workspace)
    clock["field"] = time.perf_counter() - ta
    ta = time.perf_counter()
    v, f, attrs = _extract_surface(tsdf, observed, inside, filled, acc, shape, origin,
                                   np.concatenate(Pm), voxel_size, threads, o, report)
    clock["marching_cubes"] = time.perf_counter() - ta
    lf = _laser_area_fraction(v, f, attrs["source"] == MEASURED)
    report.update(laser_area_fraction=lf, hull_area_fraction=(1.0 - lf) if len(f) else 0.0,
                  n_vertices=int(len(v)), n_faces=int(len(f)),
                  seconds_by_step={k: round(t, 3) for k, t in clock.items()})
    report.update(source_area_fraction=source_area_fractions(v, f, attrs["source"]))
    log.info("TSDF fusion: %d scans, %d points, grid %s, %d observed voxels -> %d faces "
             "(%.1f%% of the area from the laser)", len(P), n_used, shape,
             report["n_voxels_observed"], len(f), 100 * lf)
    if return_attributes:
        return v, f, report, attrs
    return v, f, report


def data_voxel(points: list[np.ndarray], options: FuseOptions, *, threads: int = 1,
               profile_spacing_m: float | None = None) -> tuple[float, float | None]:
    """The TSDF voxel for these scans: the largest of ``tsdf_voxel_m``,
    ``tsdf_voxel_per_spacing`` times the points' spacing, the median over all points of
    the distance to the nearest other point of the same scan (in a laser sweep: the
    sensor's sampling along its line, finer than the profiles' spacing), and, given the
    profiles' spacing (:func:`profile_spacing`), ``tsdf_voxel_per_footprint`` times
    ``sqrt(spacing x profile spacing)``; (voxel, spacing in metres, None when no scan
    has two points or the factor is 0).

    Why: a grid finer than the data adds faces, not detail. On issue 14's small scans
    (320 x 240 pixels, points 0.55 mm apart along the line, profiles about 2 mm apart) the
    0.4 mm grid gave fused meshes of 0.5-1.5 million faces from about 10,000 points, and
    simplifying them took half of each recording's job time. At 1.25 times the spacing
    (0.69-0.78 mm) the fused meshes have 84k-286k faces, and more of their area is
    measured rather than filled from the hull, because neighbouring profiles meet in the
    grid (``benchmarks/README.md``). The factor: at 1.4 the objects benchmark's bracket,
    thin wall, blob and user mesh (640 x 480: 0.29-0.31 mm) would leave the 0.4 mm grid,
    and the bracket lost a little (measured p95 0.092 -> 0.098 mm); at 1.25 the demos
    (0.27 mm) and every object stay on ``tsdf_voxel_m`` (at most 0.39 mm).

    The footprint: at 640 x 480 the points lie 0.27-0.29 mm apart along the line, so the
    spacing keeps the 0.4 mm grid, but sweeps of 20-40 frames leave their profiles 2.4-8.5
    mm apart: scans of about 10,000 points fused into 0.7-1.4 million faces. Measured on
    18 random scenes (``benchmarks/README.md``, stop 48): where the footprint coarsens the
    grid most (scenes 187, 332, 340, 349: 0.40-0.69 -> 0.53-1.03 mm) the simplification
    took 4.6-16.5 s instead of 14.3-56.4 s; the measured surface's median moved by at most
    0.004 mm on 17 of the 18 (the 18th, a vase of which 5 % was measured: 0.255 -> 0.303
    mm), its completeness by +0.003 to -0.014. At 0.625 the 320 x 240 scenes, whose
    spacing already sets 0.7 mm, went to 1.0-1.3 mm, and a bracket's measured completeness
    fell 0.856 -> 0.824 (0.842 at 0.5). The objects benchmark's profiles lie 1.15-1.28 mm
    apart: at most 0.31 mm, its grid stays 0.4 mm.
    """
    if not options.tsdf_voxel_per_spacing > 0:
        return float(options.tsdf_voxel_m), None
    spacing = point_spacing(points, threads=threads)
    if spacing is None:
        return float(options.tsdf_voxel_m), None
    return float(max(_voxel_bounds(options, spacing, profile_spacing_m).values())), spacing


def _voxel_bounds(o: FuseOptions, spacing: float | None, profile_spacing_m: float | None
                  ) -> dict[str, float]:
    """:func:`data_voxel`'s lower bounds on the voxel by what sets them, the floor first
    (so that a tie names it): the voxel is the largest, the report's ``voxel_from`` its
    name."""
    bounds = {"tsdf_voxel_m": float(o.tsdf_voxel_m)}
    if spacing is not None and o.tsdf_voxel_per_spacing > 0:
        bounds["point spacing"] = o.tsdf_voxel_per_spacing * spacing
        if profile_spacing_m is not None and o.tsdf_voxel_per_footprint > 0:
            bounds["point footprint"] = o.tsdf_voxel_per_footprint * math.sqrt(
                spacing * max(profile_spacing_m, spacing))
    return bounds


def profile_spacing(scans: list[np.ndarray], grids: list[np.ndarray | None]) -> float | None:
    """The laser profiles' spacing: the median over all points of the distance to the
    nearest point of the next laser frame's profile in the same scan (``grids``: each
    point's (frame, line, axis), :func:`range_surface`), metres; None when no scan has
    two frames with points (or no grid). A sweep of 20 frames over an object leaves its
    profiles 4-9 mm apart while its points lie 0.3 mm apart along the line (the random
    scenes at 640 x 480, ``benchmarks/README.md`` stop 48); the objects benchmark's sweeps
    1.2 mm."""
    from scipy.spatial import cKDTree

    d = []
    for p, g in zip(scans, grids, strict=True):
        if g is None or len(p) < 2:
            continue
        # the frames' ranks as a fourth coordinate, far apart (``gap`` exceeds the scan's
        # extent tenfold): a point's nearest neighbour at the next rank is the nearest
        # point of the next profile present, at its true distance
        _, rank = np.unique(np.asarray(g)[:, 0], return_inverse=True)
        rank = rank.reshape(-1).astype(np.float64)
        p = np.asarray(p, dtype=np.float64)
        gap = 10.0 * float(np.linalg.norm(p.max(axis=0) - p.min(axis=0))) + 1.0
        tree = cKDTree(np.c_[p, gap * rank])
        dist, _ = tree.query(np.c_[p, gap * (rank + 1)], k=1, distance_upper_bound=0.5 * gap)
        d.append(dist[np.isfinite(dist)])
    d = np.concatenate(d) if d else np.zeros(0)
    return float(np.median(d)) if len(d) else None


def point_spacing(scans: list[np.ndarray], *, threads: int = 1) -> float | None:
    """The points' spacing: the median over all points of the distance to the nearest other
    point of the same scan (coincident points left out), metres; None when no scan has
    two points."""
    from scipy.spatial import cKDTree

    nn = [cKDTree(p).query(p, k=2, workers=max(1, threads))[0][:, 1] for p in scans
          if len(p) >= 2]
    if not nn:
        return None
    d = np.concatenate(nn)
    return float(np.median(d[d > 0])) if np.any(d > 0) else 0.0


def _tsdf_inputs(points, normals, sensor_origins, confidences, grids, o: FuseOptions,
                 carve_only=None):
    """The scans' points, normals, origins, confidences and range-image grids (None
    where unknown), checked, keeping the points seen from the front (normal toward the
    sensor at ``cos >= min_cos_view``) with confidence > 0, and the ``carve_only``
    points seen from the front with confidence 0; and the number of points given."""
    P = _as_list("points", points, 2)
    N = _as_list("normals", normals, 2)
    O = _as_list("sensor_origins", sensor_origins, 2)
    if not (len(P) == len(N) == len(O)) or any(
            n.shape != p.shape or o_.shape != p.shape for p, n, o_ in zip(P, N, O,
                                                                         strict=True)):
        raise ValueError("normals and sensor_origins must match points (per scan), got "
                         f"{[p.shape for p in P]}, {[n.shape for n in N]} and "
                         f"{[o_.shape for o_ in O]}")
    Cf = ([np.ones(len(p)) for p in P] if confidences is None
          else _as_list("confidences", confidences, 1))
    if len(Cf) != len(P) or any(len(c) != len(p) or np.any(c < 0) for c, p in zip(Cf, P,
                                                                              strict=True)):
        raise ValueError("confidences must hold one value >= 0 per point, like points")
    C = ([np.zeros(len(p), bool) for p in P] if carve_only is None
         else [np.asarray(c, dtype=bool).reshape(-1) for c in carve_only])
    if len(C) != len(P) or any(len(c) != len(p) for c, p in zip(C, P, strict=True)):
        raise ValueError("carve_only must hold one bool per point, like points")
    Cf = [np.where(c, 0.0, cf) for c, cf in zip(C, Cf, strict=True)]
    G = [None] * len(P) if grids is None else list(grids)
    if len(G) != len(P) or any(g is not None and np.shape(g) != (len(p), 3)
                               for g, p in zip(G, P, strict=True)):
        raise ValueError("grids must hold one (N, 3) array (frame, line, axis) or None per "
                         "scan, like points")
    if not o.tsdf_voxel_m > 0 or o.tsdf_trunc_voxels < 1 or o.tsdf_voxel_per_spacing < 0:
        raise ValueError(f"tsdf_voxel_m must be > 0, tsdf_trunc_voxels >= 1 and "
                         f"tsdf_voxel_per_spacing >= 0, got {o.tsdf_voxel_m}, "
                         f"{o.tsdf_trunc_voxels} and {o.tsdf_voxel_per_spacing}")
    if not o.min_weight > 0:
        raise ValueError(f"min_weight must be > 0, got {o.min_weight}")
    if not 0.0 <= o.border_weight_floor <= 1.0:
        raise ValueError(f"border_weight_floor must be in [0, 1], got {o.border_weight_floor}")
    if o.close not in CLOSE_MODES:
        raise ValueError(f"close must be one of {CLOSE_MODES}, got {o.close!r}")
    n_total = int(sum(len(p) for p in P))
    for k in range(len(P)):
        los = O[k] - P[k]
        los /= np.maximum(np.linalg.norm(los, axis=1, keepdims=True), 1e-12)
        nl = np.linalg.norm(N[k], axis=1)
        cos = np.einsum("ij,ij->i", N[k], los) / np.maximum(nl, 1e-12)
        ok = (cos >= o.min_cos_view) & ((Cf[k] > 0) | C[k])
        P[k], N[k], O[k], Cf[k] = P[k][ok], N[k][ok], O[k][ok], Cf[k][ok]
        if G[k] is not None:
            G[k] = np.asarray(G[k], dtype=np.int64)[ok]
    return P, N, O, Cf, G, n_total


def _tsdf_grid(allp: np.ndarray, hull: Any, voxel_size: float, trunc: float
               ) -> tuple[np.ndarray, tuple[int, int, int], np.ndarray]:
    """The fusion grid around the points and the hull: (origin, shape, the centre of
    their box, about which the rays are cast in float32)."""
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    if hull is not None:
        h_origin, h_vs, h_occ = _hull_arrays(hull)
        if h_occ.any():
            idx = np.argwhere(h_occ)
            lo = np.minimum(lo, h_origin + idx.min(axis=0) * h_vs)
            hi = np.maximum(hi, h_origin + idx.max(axis=0) * h_vs)
    margin = trunc + 3 * voxel_size
    origin = lo - margin
    shape = tuple(int(x) for x in np.ceil((hi + margin - origin) / voxel_size).astype(np.int64)
                  + 1)
    shift = 0.5 * (lo + hi)  # float32 ray casting in a frame centred on the object
    return origin, shape, shift


@dataclass
class _Accumulator:
    """What the scans add up on the fusion grid (flat arrays): weight, weight x signed
    distance, weight x cos (the mean incidence), scans that reached the voxel, seen
    empty, and seen empty on the coarse far grid."""

    sum_w: np.ndarray
    sum_wd: np.ndarray
    sum_wc: np.ndarray
    n_obs: np.ndarray
    seen_empty: np.ndarray
    far_empty: np.ndarray
    far_shape: tuple[int, ...]
    carve_far: bool

    @classmethod
    def empty(cls, shape: tuple[int, ...], carve_far: bool) -> _Accumulator:
        n_vox = int(np.prod(shape))
        far_shape = tuple(-(-n // _FAR) for n in shape)
        return cls(np.zeros(n_vox, dtype=np.float32), np.zeros(n_vox, dtype=np.float32),
                   np.zeros(n_vox, dtype=np.float32), np.zeros(n_vox, dtype=np.uint16),
                   np.zeros(n_vox, dtype=bool),
                   np.zeros(int(np.prod(far_shape)) if carve_far else 0, dtype=bool),
                   far_shape, carve_far)


def _integrate_scans(P, N, O, Cf, G, origin: np.ndarray, shape: tuple[int, ...], shift: np.ndarray,
                     voxel_size: float, o: FuseOptions, threads: int,
                     clock: dict[str, float], *,
                     max_edge_factor: float, border_ramp_m: float, interp_sigma_m: float,
                     interp_floor: float) -> tuple[_Accumulator, list[dict[str, Any]]]:
    """Steps 1-4 for every scan: its range surface, its signed distances and weights
    added up, its lines of sight carved; (the sums, each range surface's report);
    ``clock`` gets the time of each step (summed over the scans).

    With ``threads`` > 1 the scans are worked on in parallel, one per thread, and their
    sums added in the scans' order (the same float32 sums as one after another); the
    carving only sets flags, in any order."""
    import time

    trunc_voxels = o.tsdf_trunc_voxels
    trunc = trunc_voxels * voxel_size
    acc = _Accumulator.empty(shape, bool(o.carve_free_space and o.carve_full_line))
    outer = max(1, min(int(threads), len(P)))
    inner = max(1, int(threads) // outer)

    def one(k: int):
        ta = time.perf_counter()
        faces, rs = range_surface(P[k], O[k], grid=G[k], normals=N[k],
                                  max_edge_factor=max_edge_factor,
                                  min_cos_view=o.min_cos_view,
                                  max_frame_span=o.max_frame_span)
        t = [time.perf_counter() - ta, 0.0, 0.0]
        if len(faces) == 0:
            return rs, None, t
        ta = time.perf_counter()
        # a triangle with a carve-only corner (weight 0: the table) makes no surface: its
        # hits would spread the object's weight onto the table beside it
        measured = np.all(Cf[k][faces] > 0, axis=1)
        terms = None
        if measured.any():
            terms = _scan_terms(P[k], N[k], O[k],
                                Cf[k] * _boundary_ramp(P[k], faces, border_ramp_m,
                                                       o.border_weight_floor),
                                faces if measured.all() else faces[measured], origin, shape,
                                shift, voxel_size, trunc_voxels, interp_sigma_m,
                                interp_floor, inner, o.min_cos_view)
        t[1] = time.perf_counter() - ta
        if o.carve_free_space:
            ta = time.perf_counter()
            _carve_scan(acc, P[k], O[k], faces, origin, shape, voxel_size, trunc,
                        o.carve_depth_m)
            t[2] = time.perf_counter() - ta
        return rs, terms, t

    if outer == 1:
        done = (one(k) for k in range(len(P)))
    else:
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(max_workers=outer)
        done = pool.map(one, range(len(P)))
    scans = []
    t_sum = np.zeros(3)
    try:
        for rs, terms, t in done:  # in the scans' order
            scans.append(rs)
            t_sum += t
            if terms is not None:
                _add_scan_terms(acc, *terms)
    finally:
        if outer > 1:
            pool.shutdown()
    clock.update(range_surfaces=float(t_sum[0]), rays=float(t_sum[1]),
                 carve=float(t_sum[2]))
    return acc, scans


def _add_scan_terms(acc: _Accumulator, lk: np.ndarray, w: np.ndarray, wd: np.ndarray,
                    wc: np.ndarray, empty: np.ndarray) -> None:
    """Step 3's sums of one scan (:func:`_scan_terms`) added to ``acc`` (in place); the
    band's voxels are unique within one scan: one addition each."""
    acc.sum_w[lk] += w
    acc.sum_wd[lk] += wd
    acc.sum_wc[lk] += wc
    acc.n_obs[lk] += 1
    acc.seen_empty[empty] = True


def _scan_terms(p: np.ndarray, n: np.ndarray, o: np.ndarray, vw: np.ndarray,
                faces: np.ndarray, origin: np.ndarray, shape: tuple[int, ...],
                shift: np.ndarray, voxel_size: float, trunc_voxels: int,
                interp_sigma_m: float, interp_floor: float, threads: int, min_cos: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps 2-3 for one scan: the signed distance (found along the line of sight, along
    the surface's normal) of every voxel within the band around its range surface
    ``faces`` (rays cast through the voxel centres, Open3D / Embree; ``n``: the points'
    normals, for how far in front a ray starts), weighted by cos, the vertex weights
    ``vw`` and the taper behind the surface: (voxels, w, w x sdf, w x cos as float32,
    voxels seen empty), for :func:`_add_scan_terms`."""
    import open3d as o3d
    from scipy import ndimage
    from scipy.spatial import cKDTree

    trunc = trunc_voxels * voxel_size
    # the band: voxels within trunc of the range surface (surface samples dilated)
    v0, v1, v2 = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    samples = np.concatenate([p, (v0 + v1 + v2) / 3, (v0 + v1) / 2, (v1 + v2) / 2,
                              (v2 + v0) / 2])
    ii = np.round((samples - origin) / voxel_size).astype(np.int64)
    # in the scan's own box (its samples' bounds and the band's reach), not the whole
    # grid: a sweep covers a part of the object (the same voxels, in the same order)
    lo = np.maximum(ii.min(axis=0) - trunc_voxels, 0)
    hi = np.minimum(ii.max(axis=0) + trunc_voxels + 1, shape)
    occ = np.zeros(tuple(hi - lo), dtype=bool)
    occ[ii[:, 0] - lo[0], ii[:, 1] - lo[1], ii[:, 2] - lo[2]] = True
    band = ndimage.maximum_filter(occ, size=2 * trunc_voxels + 1)
    ijk = np.stack(np.nonzero(band), axis=1) + lo
    lin = np.ravel_multi_index(tuple(ijk.T), shape)
    x = origin + ijk * voxel_size
    _, nb = cKDTree(p).query(x, k=1, workers=int(threads))
    d = p[nb] - o[nb]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    scene = o3d.t.geometry.RaycastingScene(nthreads=int(threads))
    scene.add_triangles(o3d.core.Tensor((p - shift).astype(np.float32)),
                        o3d.core.Tensor(faces.astype(np.uint32)))
    # the ray starts far enough in front that a voxel within trunc of the surface (along
    # its normal) is reached at the point's incidence: trunc / cos along the line of sight
    c_pt = np.abs(np.einsum("ij,ij->i", n[nb], d)) / np.maximum(
        np.linalg.norm(n[nb], axis=1), 1e-12)
    L = trunc / np.maximum(c_pt, min_cos)
    rays = np.hstack([x - shift - L[:, None] * d, d]).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))
    t_hit = hit["t_hit"].numpy().astype(np.float64)
    good = t_hit <= 2 * L
    prim = hit["primitive_ids"].numpy()
    uvh = hit["primitive_uvs"].numpy().astype(np.float64)
    nh = hit["primitive_normals"].numpy().astype(np.float64)
    cos = -np.einsum("ij,ij->i", nh, d)  # range triangles face their sensor
    good &= cos > 0
    lin, t_hit, d, cos, x, L = lin[good], t_hit[good], d[good], cos[good], x[good], L[good]
    prim, uvh = prim[good], uvh[good]
    tri = faces[prim.astype(np.int64)]
    wv = (vw[tri[:, 0]] * (1 - uvh[:, 0] - uvh[:, 1]) + vw[tri[:, 1]] * uvh[:, 0]
          + vw[tri[:, 2]] * uvh[:, 1])
    sdf = (t_hit - L) * cos  # along the surface's normal (point-to-plane)
    if interp_sigma_m > 0:
        # interpolated range is less certain than measured range: the weight falls
        # with the hit's distance to the nearest measured point of its triangle
        hp = x - L[:, None] * d + t_hit[:, None] * d
        dv = np.min(np.stack([np.linalg.norm(hp - p[tri[:, m]], axis=1)
                              for m in range(3)]), axis=0)
        wv = wv * (interp_floor + (1 - interp_floor) * np.exp(-(dv / interp_sigma_m) ** 2))
    # behind the surface the band reaches trunc along the line of sight (as far as the
    # sight line's depth says something; a thin wall's other face keeps its own
    # distances), at least one voxel (a grazing sight line reaches a tenth of one)
    behind = np.maximum(trunc * cos, _BEHIND_MIN_VOXELS * voxel_size)
    w = cos * wv * np.clip((sdf + behind) / (0.5 * behind), 0.0, 1.0)
    keep = (w > 0) & (sdf <= trunc)
    return (lin[keep], w[keep].astype(np.float32), (w * sdf)[keep].astype(np.float32),
            (w * cos)[keep].astype(np.float32), lin[sdf > 0.5 * voxel_size])


def _carve_scan(acc: _Accumulator, p: np.ndarray, o: np.ndarray, faces: np.ndarray,
                origin: np.ndarray, shape: tuple[int, ...], voxel_size: float, trunc: float,
                carve_depth_m: float) -> None:
    """Step 4 for one scan: the lines of sight carve the space in front of the surface
    (to ``carve_depth_m`` at the grid's resolution, then on to the sensor or the grid's
    border on the coarse grid), in ``acc`` (in place)."""
    # from the range surface's vertices and triangle centres (dense enough that,
    # dilated by one voxel, the carved lines leave no gaps between profiles)
    v0, v1, v2 = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    cen = (v0 + v1 + v2) / 3
    o_c = (o[faces[:, 0]] + o[faces[:, 1]] + o[faces[:, 2]]) / 3
    _carve_lines_of_sight(acc.seen_empty, np.concatenate([p, cen]),
                          np.concatenate([o, o_c]), origin, voxel_size, shape,
                          start=trunc + voxel_size, depth=carve_depth_m)
    if acc.carve_far:  # beyond carve_depth_m, to the grid's border, on a coarse grid
        _carve_lines_of_sight(acc.far_empty, p, o, origin + 0.5 * (_FAR - 1) * voxel_size,
                              _FAR * voxel_size, acc.far_shape, start=carve_depth_m,
                              depth=np.inf)


def _tsdf_field(acc: _Accumulator, shape: tuple[int, ...], trunc: float, hull: Any,
                origin: np.ndarray, voxel_size: float, hull_smooth_vox: float,
                o: FuseOptions, scans: list[dict[str, Any]], report: dict[str, Any],
                workspace: tuple[np.ndarray, np.ndarray] | None = None):
    """Steps 4-5: the TSDF of the observed voxels and, with a hull and ``fill_holes``,
    the solid/empty indicator elsewhere: (tsdf, observed, inside the hull or None,
    whether holes were filled); ``report`` updated. Voxels outside ``workspace`` are
    empty and not observed."""
    from scipy import ndimage

    seen_empty = acc.seen_empty
    if o.carve_free_space:
        seen_empty = ndimage.binary_dilation(seen_empty.reshape(shape)).ravel()
        if acc.carve_far:
            up = acc.far_empty.reshape(acc.far_shape)
            for ax in range(3):
                up = np.repeat(up, _FAR, axis=ax)
            seen_empty |= up[: shape[0], : shape[1], : shape[2]].ravel()
            report["n_voxels_seen_empty_far"] = int(np.count_nonzero(up))
    observed = acc.sum_w >= o.min_weight
    tsdf = np.full(len(acc.sum_w), trunc, dtype=np.float32)
    tsdf[observed] = acc.sum_wd[observed] / acc.sum_w[observed]
    observed = observed.reshape(shape)
    tsdf = tsdf.reshape(shape)
    outside = None
    if workspace is not None:  # the box the points were cropped to: below it, the table
        lo, hi = (np.asarray(b, dtype=np.float64) for b in workspace)
        axes = [origin[k] + np.arange(shape[k]) * voxel_size for k in range(3)]
        out_k = [(a < lo[k]) | (a > hi[k]) for k, a in enumerate(axes)]
        outside = (out_k[0][:, None, None] | out_k[1][None, :, None]
                   | out_k[2][None, None, :])
        report["n_observed_voxels_outside_workspace"] = int(np.count_nonzero(
            observed & outside))
        observed = observed & ~outside
        tsdf[outside] = trunc
    seen_empty = seen_empty.reshape(shape) & ~observed
    report.update(n_voxels_observed=int(observed.sum()), n_voxels_seen_empty=int(
        seen_empty.sum()), range_surfaces=scans)
    bridges = sum(s.get("n_triangles_over_frames", 0) for s in scans)
    report["n_range_triangles_over_frames"] = bridges
    if bridges:
        log.info("TSDF fusion: %d range triangles joined laser frames more than %d apart "
                 "(the frames between saw no stripe there): not fused, not measured",
                 bridges, o.max_frame_span)
    filled = False
    inside = None
    fill_holes = o.fill_holes and o.close != "none"
    if hull is not None:
        inside = _hull_field(hull, origin, voxel_size, shape, o.hull_margin_voxels,
                             hull_smooth_vox)
        if outside is not None:
            inside = inside & ~outside
        solid_obs = observed & (tsdf < 0)
        n_out_hull = int(np.count_nonzero(solid_obs & ~inside))
        frac_out = n_out_hull / max(1, int(np.count_nonzero(solid_obs)))
        report["n_observed_voxels_outside_hull"] = n_out_hull
        report["observed_solid_outside_hull_fraction"] = round(float(frac_out), 4)
        if frac_out > o.max_outside_hull_fraction:
            # the hull is no bound on the object: silhouettes that failed alike in many
            # views (a white cup on a checker table: 45 % of the measured solid outside
            # its hull, whose closure then made 70 % of the mesh)
            log.warning("fusion: %.0f %% of the measured solid lies outside the visual "
                        "hull (more than fusion.max_outside_hull_fraction %.0f %%): the "
                        "hull contradicts the laser and closes nothing; the mesh is the "
                        "measured surface", 100 * frac_out, 100 * o.max_outside_hull_fraction)
            report["hull_contradicted"] = True
            report["hull_fill"] = (f"the hull contradicts the laser ({100 * frac_out:.0f} % "
                                   "of the measured solid outside it): not used, no surface "
                                   "where the laser saw nothing")
            return tsdf, observed, None, False
        if fill_holes:
            solid = np.where(observed, tsdf < 0, inside & ~seen_empty)
            smooth = ndimage.gaussian_filter(solid.astype(np.float32), 1.0)
            tsdf = np.where(observed, tsdf, (1.0 - 2.0 * smooth) * trunc).astype(np.float32)
            filled = True
            report["hull_fill"] = ("unobserved space inside the hull and not seen empty is "
                                   "solid: holes closed from the hull")
        else:
            report["hull_fill"] = "disabled"
    else:
        report["hull_fill"] = "no hull: no surface where the laser saw nothing"
    return tsdf, observed, inside, filled


def _extract_surface(tsdf: np.ndarray, observed: np.ndarray, inside: np.ndarray | None,
                     filled: bool, acc: _Accumulator, shape: tuple[int, ...],
                     origin: np.ndarray, allp: np.ndarray, voxel_size: float, threads: int,
                     o: FuseOptions, report: dict[str, Any]):
    """Steps 6-7: marching cubes (Lewiner) at level 0, each vertex's provenance and
    evidence, and what ``close`` leaves: (vertices, faces, attributes); ``report``
    updated."""
    from scipy import ndimage
    from scipy.spatial import cKDTree
    from skimage import measure

    sum_w, sum_wc, n_obs = (x.reshape(shape) for x in (acc.sum_w, acc.sum_wc, acc.n_obs))
    # the hull's boundary as the inferred surface sees it: within 2 voxels of outside (the
    # solid indicator is smoothed over one voxel, which moves the crossing by about one)
    near_out = None if inside is None else ndimage.binary_dilation(~inside, iterations=2)
    if not (np.any(tsdf < 0) and np.any(tsdf > 0)):
        v = np.zeros((0, 3))
        f = np.zeros((0, 3), dtype=np.int64)
        attrs = _vertex_attributes(np.zeros((0, 3), np.int64), np.zeros((0, 3), np.int64),
                                   observed, sum_w, sum_wc, n_obs, near_out)
    else:
        v, f, _, _ = measure.marching_cubes(tsdf, level=0.0, gradient_direction="descent",
                                            allow_degenerate=False)
        f = f.astype(np.int64)
        q = v.astype(np.float64)
        lo_i = np.clip(np.floor(q + 1e-3).astype(np.int64), 0, np.array(shape) - 1)
        hi_i = np.clip(np.ceil(q - 1e-3).astype(np.int64), 0, np.array(shape) - 1)
        attrs = _vertex_attributes(lo_i, hi_i, observed, sum_w, sum_wc, n_obs, near_out)
        v = origin + q * voxel_size
        if not filled:  # crossings next to unobserved voxels are not surface
            v, f, attrs = keep_vertices(v, f, attrs, attrs["source"] == MEASURED)
    if len(v):
        attrs["dist_measured_m"] = cKDTree(allp, **KD_FAR).query(
            v, k=1, workers=int(threads))[0].astype(np.float32)
    else:
        attrs["dist_measured_m"] = np.zeros(0, np.float32)
    far = ((attrs["source"] != MEASURED)
           & (attrs["dist_measured_m"] > 1e-3 * o.max_fill_distance_mm))
    attrs["far_from_measured"] = far.astype(np.uint8)
    n_far = 0
    if filled and o.close == "free_space":
        n_far = int(far.sum())
        v, f, attrs = keep_vertices(v, f, attrs, ~far)
    attrs["confidence"] = _vertex_confidence(attrs, voxel_size)
    report["close"] = "none" if report.get("hull_contradicted") else o.close
    report["n_vertices_left_open_far_from_measured"] = n_far
    return v, f, attrs


def _laser_area_fraction(v: np.ndarray, f: np.ndarray, laser_v: np.ndarray) -> float:
    """Share of the mesh's area on faces whose three vertices are measured."""
    if not len(f):
        return 0.0
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                axis=1)
    from_laser = np.all(laser_v[f], axis=1)
    total = float(area.sum())
    return float(area[from_laser].sum() / total) if total > 0 else 0.0


def _vertex_attributes(lo_i: np.ndarray, hi_i: np.ndarray, observed: np.ndarray,
                       sum_w: np.ndarray, sum_wc: np.ndarray, n_obs: np.ndarray,
                       near_outside: np.ndarray | None) -> dict[str, np.ndarray]:
    """Provenance and evidence of marching-cubes vertices on the grid edges ``lo_i`` -
    ``hi_i`` (fuse_tsdf, step 6); ``near_outside``: voxels at the hull's boundary."""
    a = tuple(lo_i.T)
    b = tuple(hi_i.T)
    measured = observed[a] & observed[b]
    source = np.full(len(lo_i), FILLED, np.uint8)
    if near_outside is not None:
        source[near_outside[a] | near_outside[b]] = HULL
    source[measured] = MEASURED
    w = 0.5 * (sum_w[a] + sum_w[b])
    with np.errstate(invalid="ignore", divide="ignore"):
        inc = np.where(w > 0, 0.5 * (sum_wc[a] + sum_wc[b]) / w, 0.0)
    return {"source": source,
            "n_obs": np.maximum(n_obs[a], n_obs[b]).astype(np.uint16),
            "incidence": inc.astype(np.float32),
            "tsdf_weight": w.astype(np.float32)}


def _vertex_confidence(attrs: dict[str, np.ndarray], voxel_size: float) -> np.ndarray:
    """Confidence of a vertex in [0, 1]: 0 for inferred surface; for measured surface
    ``(1 - exp(-W))`` (TSDF weight ``W``: about one frontal observation gives 0.63) times
    ``exp(-(d / 2 voxels)^2)`` with ``d`` the distance to the nearest measured point
    (between profiles the range surface is a chord)."""
    w = attrs["tsdf_weight"].astype(np.float64)
    d = attrs["dist_measured_m"].astype(np.float64)
    c = (1.0 - np.exp(-w)) * np.exp(-(d / (2.0 * voxel_size)) ** 2)
    return np.where(attrs["source"] == MEASURED, c, 0.0).astype(np.float32)


def keep_vertices(v: np.ndarray, f: np.ndarray, attrs: dict[str, np.ndarray],
                   keep: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """:func:`remove_vertices` that carries the per-vertex attributes along."""
    keep = np.asarray(keep, dtype=bool)
    f_in = np.asarray(f, dtype=np.int64).reshape(-1, 3)
    used = np.zeros(len(v), dtype=bool)
    used[f_in[np.all(keep[f_in], axis=1)].ravel()] = True  # what remove_vertices keeps
    v2, f2 = remove_vertices(v, f, keep)
    return v2, f2, {k: x[used] for k, x in attrs.items()}


def source_area_fractions(vertices: np.ndarray, faces: np.ndarray, source: np.ndarray
                          ) -> dict[str, float]:
    """Area fraction of a mesh per provenance (:data:`SOURCES`): a face is *measured*
    when its three vertices are; else it takes its vertices' least trustworthy source
    (hull over filled)."""
    out = {name: 0.0 for name in SOURCES}
    if len(faces) == 0:
        return out
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                axis=1)
    fs = face_source(f, source)
    total = float(area.sum())
    for i, name in enumerate(SOURCES):
        out[name] = float(area[fs == i].sum() / total) if total > 0 else 0.0
    return out


def face_source(faces: np.ndarray, source: np.ndarray) -> np.ndarray:
    """Provenance of each face (:data:`SOURCES` index): measured when all three vertices
    are, hull when any is, else filled."""
    s = np.asarray(source)[np.asarray(faces, np.int64)]
    out = np.full(len(s), FILLED, np.uint8)
    out[np.all(s == MEASURED, axis=1)] = MEASURED
    out[np.any(s == HULL, axis=1)] = HULL
    return out


def _carve_lines_of_sight(seen_empty: np.ndarray, p: np.ndarray, o: np.ndarray,
                          origin: np.ndarray, voxel_size: float, shape: tuple[int, ...],
                          *, start: float, depth: float, chunk: int = 20_000) -> None:
    """Mark the voxels along each line of sight, from ``start`` to ``depth`` in front of
    the point (or where the line leaves the grid), as seen empty (flat grid, in place)."""
    if len(p) == 0:
        return
    d = o - p
    dist = np.linalg.norm(d, axis=1)
    d /= dist[:, None]
    ext = np.array(shape) * voxel_size
    # distance from the point to the grid's border along d (slab method)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = np.where(d > 0, (origin + ext - p) / d, np.where(d < 0, (origin - p) / d, np.inf))
    t_exit = np.minimum(np.minimum(t1.min(axis=1), dist), depth)
    n_steps = int(np.ceil(max(float(t_exit.max()) - start, 0.0) / voxel_size)) + 1
    steps = start + np.arange(n_steps) * voxel_size
    dims = np.array(shape)
    for a in range(0, len(p), chunk):
        sl = slice(a, a + chunk)
        q = p[sl, None, :] + steps[None, :, None] * d[sl, None, :]
        valid = steps[None, :] <= t_exit[sl, None]
        ii = np.round((q - origin) / voxel_size).astype(np.int64)
        valid &= np.all((ii >= 0) & (ii < dims), axis=2)
        ii = ii[valid]
        seen_empty[np.ravel_multi_index((ii[:, 0], ii[:, 1], ii[:, 2]), shape)] = True
