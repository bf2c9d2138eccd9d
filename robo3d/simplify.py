"""Mesh cleaning and simplification with pymeshlab (MeshLab's filters) and
fast_simplification (the error-bounded collapses).

:func:`clean_mesh` removes what fusion leaves behind: exactly duplicated vertices and faces,
zero-area faces, unreferenced vertices, and small floating components (fewer faces than a
fraction of the mesh: islands of noise, or shreds left by the density and hull cuts).

:func:`simplify_mesh` is quadric edge-collapse decimation (Garland & Heckbert 1997) with
optimal vertex placement, boundary and normal preservation. It stops at a face count
(``target_faces``) or at a geometric error (``max_error``), or both (the fewest faces, not
below ``target_faces``, whose error stays within ``max_error``). Quadric decimation has no
error-driven stop in pymeshlab, so the error-bounded mode decimates *progressively*
(a quarter of the input's faces first, then steps sized by how far within the bound the
last one stayed, each decimating the previous result: about one decimation of the input in
all) and measures the two-sided distance of the last step to the input
(Open3D/Embree point-to-triangle distances of the vertices and of area samples: fast);
where a step goes beyond the bound, the places where it does are kept at the resolution
they have (the faces around them are left out of the collapse) and the step is made
again, so that one or two spots do not hold the whole mesh at hundreds of thousands of
faces; a step still beyond the bound ends the steps, and a search between the last
step within it and that one follows (bisection on a log scale, each trial decimating the
kept step). Told which vertices are inferred (hull-closed or hole-filled: no sensor saw
that surface, and the hull it came from is known to its voxel, about a millimetre), the
check holds the inferred faces to their own, looser bound (``inferred_tolerance_m``,
0.5 mm, or half the hull's voxel where that is more: :attr:`SimplifyOptions.inferred_bound_m`):
on a simulated cup scanned with three sweeps (87 % of its area inferred) the
0.2 mm bound everywhere kept 831 places at the fused resolution and 46,552 faces, the
inferred bound 212 and 25,940 (``benchmarks/README.md``, stop 29). The reported Hausdorff
distance of the result is measured the same way with more samples
(:func:`hausdorff_distance`, the sampling of Metro, Cignoni et al. 1998; pymeshlab's own
measure took 5 of a small scan's 20 s).

The error-bounded mode's collapses are Fast-Quadric-Mesh-Simplification's
(``fast_simplification``, :func:`_fast_decimate`): the same quadric error metric, edges
collapsed in passes of rising threshold rather than from a priority queue, about ten times
faster than MeshLab's collapse, which ran on one core and was two thirds of the stage
(simulated cup/4, 656,888 fused faces: collapses 9.0 s of MeshLab's, in four slabs on
two processes, against about 1.5 s; ``benchmarks/README.md``, stop 58). Every step it makes
is checked against the bound, as MeshLab's were. MeshLab's collapse remains for the face
target alone (no bound: nothing checks the result, and its priority queue is the more
careful), without held open borders, and when the fast one throws a vertex far out.

Units: both quadric collapses have absolute thresholds inside (a mesh decimates
differently in metres and in millimetres, ``benchmarks/README.md``), so meshes are scaled
to a 100-unit bounding box diagonal before every pymeshlab filter, and to the error bound
for the fast collapse, and scaled back after.

The Hausdorff distance reported is measured on samples (all vertices plus points on the
faces), so it is a slight underestimate of the exact maximum; reported in metres.

References
----------
Garland, M. & Heckbert, P. S. (1997). Surface simplification using quadric error metrics.
SIGGRAPH.
Cignoni, P., Rocchini, C. & Scopigno, R. (1998). Metro: measuring error on simplified
surfaces. Computer Graphics Forum 17(2).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .checks import check_mesh
from .options import Options

__all__ = ["SimplifyOptions", "clean_mesh", "simplify_mesh", "hausdorff_distance",
           "transfer_vertex_attributes"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimplifyOptions(Options):
    """The parameters of :func:`clean_mesh` and :func:`simplify_mesh` (config section
    ``simplify``; ``export`` and ``export_unit`` are the stage's), and the recording's
    seed.

    Attributes
    ----------
    target_faces : int or None
        Decimate to at most this many faces (unless the error bound forbids it); None
        (not from the config): no face target.
    max_error_m : float or None, metres
        The fewest faces whose two-sided Hausdorff distance to the input stays within
        this (None: only ``hausdorff_tolerance_m`` bounds it).
    hausdorff_tolerance_m : float or None, metres
        The simplified mesh must stay within this of the input: the error bound is the
        smaller of this and ``max_error_m``. None (not from the config): no bound.
    inferred_tolerance_m : float or None, metres
        The bound on the inferred surface (hull-closed or hole-filled, when
        :func:`simplify_mesh` is told which it is), never tighter than the error bound;
        None: the error bound.
    min_component_fraction : float in [0, 1)
        :func:`clean_mesh`: connected components with fewer faces than this fraction of
        all faces are removed (0 keeps every component).
    seed : int
        The recording's seed (config ``seed``): the search's area samples.
    hull_voxel_m : float or None, metres
        The voxel of the visual hull the inferred surface was closed from (not a config
        key: the stage reads it from ``hull.npz``); the inferred bound is never tighter
        than half of it (:attr:`inferred_bound_m`). None: no hull.
    threads : int
        Threads of the distance queries (the job's, not a config key; the distances do
        not depend on it). The quadric collapse runs on one.
    """

    section = "simplify"
    not_in_config = ("seed", "threads", "hull_voxel_m")
    target_faces: int | None = 20000
    max_error_m: float | None = None
    hausdorff_tolerance_m: float | None = 0.0002
    inferred_tolerance_m: float | None = 0.0005
    min_component_fraction: float = 0.01
    seed: int = 0
    threads: int = 1
    hull_voxel_m: float | None = None

    @property
    def error_bound_m(self) -> float | None:
        """The error bound of the simplification: the smaller of
        ``hausdorff_tolerance_m`` and ``max_error_m`` (None: neither)."""
        bounds = [b for b in (self.hausdorff_tolerance_m, self.max_error_m) if b is not None]
        return min(bounds) if bounds else None

    @property
    def inferred_bound_m(self) -> float | None:
        """The error bound on inferred surface: ``inferred_tolerance_m``, never below
        :attr:`error_bound_m` nor below half the hull's voxel (``hull_voxel_m``: the
        hull it was closed from is known no better; holding it tighter only keeps
        faces) (None: no bound).

        Why the voxel: the real DTU scan 24 (49 photos, a hull of 3.6 mm voxels, the mesh
        the hull's alone) was held to 0.5 mm: its simplification kept 4,692 places at
        the fused resolution, 63,280 faces, and took 49 s of a 82 s run
        (``benchmarks/README.md``, stop 44)."""
        bound = self.error_bound_m
        if bound is None or self.inferred_tolerance_m is None:
            return bound
        voxel = _HULL_VOXEL_FRACTION * float(self.hull_voxel_m or 0.0)
        return max(bound, float(self.inferred_tolerance_m), voxel)


#: the inferred surface's bound is at least this fraction of the hull's voxel
_HULL_VOXEL_FRACTION = 0.5


def _check_mesh(vertices: object, faces: object) -> tuple[np.ndarray, np.ndarray]:
    v, f = check_mesh(vertices, faces)
    return v, f.astype(np.int32)


def _meshset(v: np.ndarray, f: np.ndarray):
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f))
    return ms


def _arrays(ms) -> tuple[np.ndarray, np.ndarray]:
    m = ms.current_mesh()
    return (np.ascontiguousarray(m.vertex_matrix(), dtype=np.float64),
            np.ascontiguousarray(m.face_matrix(), dtype=np.int64).reshape(-1, 3))


def clean_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    options: SimplifyOptions = SimplifyOptions(),
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Remove duplicates, degenerate faces, unreferenced vertices and small components.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int
    options : SimplifyOptions
        ``min_component_fraction``: connected components with fewer faces than this
        fraction of all faces are removed (0 keeps every component).

    Returns
    -------
    vertices : (V', 3) float64
    faces : (F', 3) int64
    report : dict
        ``n_vertices_in``, ``n_faces_in``, ``n_duplicate_vertices``,
        ``n_duplicate_faces``, ``n_null_faces``, ``n_unreferenced_vertices``,
        ``min_component_faces``, ``n_component_faces_removed``, ``n_vertices``,
        ``n_faces``.
    """
    v, f = _check_mesh(vertices, faces)
    min_component_fraction = options.min_component_fraction
    if not 0 <= min_component_fraction < 1:
        raise ValueError(f"min_component_fraction must be in [0, 1), got "
                         f"{min_component_fraction}")
    report: dict[str, Any] = dict(n_vertices_in=int(len(v)), n_faces_in=int(len(f)))
    if len(f) == 0:
        report.update(n_duplicate_vertices=0, n_duplicate_faces=0, n_null_faces=0,
                      n_unreferenced_vertices=int(len(v)), min_component_faces=0,
                      n_component_faces_removed=0, n_vertices=0, n_faces=0)
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), report
    ms = _meshset(v, f)

    def counts() -> tuple[int, int]:
        m = ms.current_mesh()
        return m.vertex_number(), m.face_number()

    nv, nf = counts()
    ms.meshing_remove_duplicate_vertices()
    nv2, _ = counts()
    ms.meshing_remove_duplicate_faces()
    _, nf2 = counts()
    ms.meshing_remove_null_faces()
    _, nf3 = counts()
    ms.meshing_remove_unreferenced_vertices()
    nv3, _ = counts()
    min_faces = math.ceil(min_component_fraction * nf3)
    if min_faces > 1:
        ms.meshing_remove_connected_component_by_face_number(mincomponentsize=min_faces,
                                                             removeunref=True)
    nv4, nf4 = counts()
    v_out, f_out = _arrays(ms)
    report.update(n_duplicate_vertices=nv - nv2, n_duplicate_faces=nf - nf2,
                  n_null_faces=nf2 - nf3, n_unreferenced_vertices=nv2 - nv3,
                  min_component_faces=int(min_faces), n_component_faces_removed=nf3 - nf4,
                  n_vertices=int(len(v_out)), n_faces=int(len(f_out)))
    log.info("clean_mesh: %d -> %d faces (%d in small components)", len(f), len(f_out),
             nf3 - nf4)
    return v_out, f_out, report


def _distances_to(v: np.ndarray, f: np.ndarray, points: np.ndarray,
                  shift: np.ndarray | None = None, threads: int = 1) -> np.ndarray:
    """Unsigned distance of each point to the nearest point of the mesh (Open3D's
    RaycastingScene, Embree's closest-point query: exact per triangle), metres; computed
    in float32 about ``shift`` (default: the mesh's mean vertex), on ``threads``."""
    import open3d as o3d

    from .evaluate import open3d_threads

    shift = v.mean(axis=0) if shift is None else shift
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((v - shift).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(f, dtype=np.int64).astype(np.uint32)))
    with open3d_threads(threads):
        return scene.compute_distance(o3d.core.Tensor(
            (points - shift).astype(np.float32))).numpy().astype(np.float64)


def _measure_samples(v: np.ndarray, f: np.ndarray, n: int, seed: int, faces: bool = False
                     ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """The points a mesh is measured at: its vertices, then area samples up to ``n`` in
    all (the search's checks and the report use the same, :class:`_Distance`); with
    ``faces`` also the face of each area sample."""
    from .evaluate import sample_surface

    pts, on = sample_surface(v, f, max(0, n - len(v)), seed=seed, return_faces=True)
    out = np.concatenate([v, pts])
    return (out, on) if faces else out


def _stats(d: np.ndarray) -> dict[str, float]:
    return {"max": float(d.max()), "mean": float(d.mean()), "rms": float(np.sqrt(np.mean(d * d)))}


def _one_way(v_from: np.ndarray, f_from: np.ndarray, v_to: np.ndarray, f_to: np.ndarray,
             n: int, seed: int, threads: int = 1) -> dict[str, float]:
    return _stats(_distances_to(v_to, f_to, _measure_samples(v_from, f_from, n, seed),
                                threads=threads))


def hausdorff_distance(vertices_a: np.ndarray, faces_a: np.ndarray,
                       vertices_b: np.ndarray, faces_b: np.ndarray, *,
                       n_samples: int | None = None, seed: int = 0, threads: int = 1
                       ) -> dict[str, Any]:
    """Two-sided sampled Hausdorff distance between two meshes, in metres: from every
    vertex and area samples of each mesh to the nearest point of the other (Open3D's
    exact point-to-triangle distance; the sampling of Metro, Cignoni et al. 1998).

    Parameters
    ----------
    vertices_a, vertices_b : (V, 3) float64, metres
    faces_a, faces_b : (F, 3) int
    n_samples : int, optional
        Samples on each sampled mesh (its vertices, then points spread over its area up to
        this number). Default: vertices + 2 per face of the sampled mesh, at least 10,000,
        at most 2,000,000.
    seed : int
        Seed of the area samples.
    threads : int
        Threads of the distance queries (the result does not depend on it).

    Returns
    -------
    dict
        ``a_to_b`` and ``b_to_a``: {``max``, ``mean``, ``rms``} in metres, and ``max``:
        the larger of the two maxima (the Hausdorff distance).
    """
    va, fa = _check_mesh(vertices_a, faces_a)
    vb, fb = _check_mesh(vertices_b, faces_b)
    if len(fa) == 0 or len(fb) == 0:
        raise ValueError("both meshes need faces to measure a Hausdorff distance")

    def n_for(v: np.ndarray, f: np.ndarray) -> int:
        if n_samples is not None:
            return int(n_samples)
        return int(min(max(len(v) + 2 * len(f), 10_000), 2_000_000))

    ab = _one_way(va, fa, vb, fb, n_for(va, fa), seed, threads)
    ba = _one_way(vb, fb, va, fa, n_for(vb, fb), seed + 1, threads)
    return {"a_to_b": ab, "b_to_a": ba, "max": max(ab["max"], ba["max"])}


def _scale_of(v: np.ndarray) -> float:
    """Factor that brings a mesh to a 100-unit bounding-box diagonal (see module notes)."""
    if len(v) == 0:
        return 1.0
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    return 100.0 / diag if diag > 0 else 1.0


def _quadric_options(target: int, preserve_boundary: bool, preserve_normal: bool,
                     selected: bool, optimal: bool = True) -> dict[str, Any]:
    """The arguments of pymeshlab's quadric edge collapse (:func:`_decimate`): towards
    ``target`` faces (of the selected faces when ``selected``), optimal placement (unless
    not ``optimal``: each new vertex on the collapsed edge), planar quadrics, quality
    threshold 0.3."""
    return dict(targetfacenum=int(target), qualitythr=0.3,
                preserveboundary=preserve_boundary, boundaryweight=1.0,
                preservenormal=preserve_normal, preservetopology=False,
                optimalplacement=bool(optimal), planarquadric=True, autoclean=True,
                selected=selected)


#: a collapse that puts a vertex farther than this share of its input's bounding-box
#: diagonal outside that box is made again without optimal placement (:func:`_flew`)
_FLY_FRACTION = 0.01


def _flew(v_in: np.ndarray, v_out: np.ndarray) -> bool:
    """Whether a collapse of ``v_in`` put a vertex of ``v_out`` more than
    :data:`_FLY_FRACTION` of the input's bounding-box diagonal outside that box. The
    quadric's optimal placement can do that where its system is nearly singular: on the
    simulated cup/7 cut into eight slabs, one slab's collapse put a vertex 310 mm below the
    table, the check found the mesh 124 mm off, and the locks then kept 60,298 faces where
    20,000 do (``benchmarks/README.md``, stop 46). No surface within any sensible bound
    moves that far."""
    if not len(v_in) or not len(v_out):
        return False
    lo, hi = v_in.min(axis=0), v_in.max(axis=0)
    tol = _FLY_FRACTION * float(np.linalg.norm(hi - lo))
    return bool(np.any(v_out < lo - tol) or np.any(v_out > hi + tol))


def _guarded(collapse: Callable[[bool], tuple[np.ndarray, np.ndarray]], v_in: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, bool]:
    """``collapse(optimal)`` of a mesh with vertices ``v_in``, with optimal placement, and
    again without it when that threw a vertex far out (:func:`_flew`): (vertices, faces,
    whether it was made again)."""
    out_v, out_f = collapse(True)
    if not _flew(v_in, out_v):
        return out_v, out_f, False
    return (*collapse(False), True)


def _decimate(v: np.ndarray, f: np.ndarray, target: int, preserve_boundary: bool,
              preserve_normal: bool, keep: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Quadric collapse of (v, f) towards ``target`` faces; ``keep``: (F,) bool, faces
    left as they are (only the others are selected for the collapse). A collapse that
    throws a vertex far out (:func:`_flew`) is made again without optimal placement."""
    import pymeshlab

    scale = _scale_of(v)
    vs = v * scale
    locked = keep is not None and bool(np.any(keep))

    def collapse(optimal: bool) -> tuple[np.ndarray, np.ndarray]:
        if locked:
            ms = pymeshlab.MeshSet()
            ms.add_mesh(pymeshlab.Mesh(vertex_matrix=vs, face_matrix=f,
                                       f_scalar_array=(~keep).astype(np.float64)))
            ms.compute_selection_by_condition_per_face(condselect="fq > 0.5")
        else:
            ms = _meshset(vs, f)
        kw = _quadric_options(target, preserve_boundary, preserve_normal, selected=locked,
                              optimal=optimal)
        ms.meshing_decimation_quadric_edge_collapse(**kw)
        # the collapse may stop a few faces above the target on meshes with many
        # boundaries
        tries = 0
        while ms.current_mesh().face_number() > target and tries < 3 and not locked:
            ms.meshing_decimation_quadric_edge_collapse(**kw)
            tries += 1
        return _arrays(ms)

    out_v, out_f, again = _guarded(collapse, vs)
    if again:
        log.warning("simplify: the quadric collapse put a vertex far outside the mesh "
                    "(optimal placement); made again without it")
    return out_v / scale, _drop_double_faces(out_f)


#: the fast collapse's aggressiveness (fast_simplification's ``agg``): its pass ``i`` of
#: 100 collapses the edges whose quadric error is below 1e-9 (i + 3)^agg, in the mesh's
#: squared units (:func:`_fast_decimate`). 2: on the simulated cup/4 (656,888 fused faces
#: to 20,000 within 0.2 mm) agg 1, 2 and 3 took 7, 8 and 9 checked trials, but agg 1
#: stopped short of the target where the bound allowed it (random scene 641: 21,196 faces
#: where agg 2 reached 20,000; ``benchmarks/README.md``, stop 58)
_FAST_AGG = 2.0
#: the length the error bound is expressed as for the fast collapse: the mesh is scaled by
#: this over the bound, so that its passes sweep errors from about half the bound to a few
#: times it, whatever the unit and the bound
_FAST_BOUND_UNITS = 2e-4


def _drop_double_faces(f: np.ndarray) -> np.ndarray:
    """``f`` without faces that use the same three vertices as another, in pairs (of an odd
    number, the first stays): a collapse that closes a thin fold or fin leaves such a
    pair (its two sides, flat on each other), whose edge with the rest then has four
    faces; without the pair it has two again (the sphere of the tests: two such pairs in
    1,500 faces from the fast collapse; MeshLab's collapses left one or two in some
    simulated scans' meshes as well, ``benchmarks/README.md``, stop 58)."""
    if not len(f):
        return f
    _, first, inv, count = np.unique(np.sort(f, axis=1), axis=0, return_index=True,
                                     return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    keep = (count[inv] == 1) | ((count[inv] % 2 == 1) & (first[inv] == np.arange(len(f))))
    return f if keep.all() else f[keep]


def _fast_decimate(v: np.ndarray, f: np.ndarray, target: int, bound: float,
                   keep: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fast quadric collapse (Fast-Quadric-Mesh-Simplification, ``fast_simplification``)
    of the faces of (v, f) not in ``keep`` ((F,) bool: left as they are) towards
    ``target`` of them, for the error-bounded mode, where every result is checked.

    The free faces are collapsed as a mesh of their own whose open border is held (no
    collapse touches a border vertex): the vertices they share with the kept faces lie on
    that border, so the two weld exactly, and the mesh's own open borders stay put, as
    MeshLab's ``preserveboundary`` keeps them. Collapses that would flip a face are
    refused, as MeshLab's ``preservenormal`` refuses them. The mesh is expressed in units
    where ``bound`` is about :data:`_FAST_BOUND_UNITS` (its thresholds are absolute). A collapse
    that throws a vertex far out (:func:`_flew`) is made by MeshLab's instead
    (:func:`_decimate`).

    Why not MeshLab's: see the module notes."""
    import fast_simplification

    f = np.asarray(f, dtype=np.int64)
    locked = keep is not None and bool(np.any(keep))
    free = f[~keep] if locked else f
    if target >= len(free) or not len(free):
        return v, f
    # a power of two: the border's vertices come back with the same bits
    scale = 2.0 ** round(math.log2(_FAST_BOUND_UNITS / bound))
    used, inv = np.unique(free, return_inverse=True)
    sub_v = v[used]
    out_v, out_f = fast_simplification.simplify(
        sub_v * scale, inv.reshape(-1, 3).astype(np.int32), target_count=int(target),
        agg=_FAST_AGG, preserve_border=True)
    out_v = np.asarray(out_v, dtype=np.float64) / scale
    out_f = np.asarray(out_f, dtype=np.int64).reshape(-1, 3)
    if _flew(sub_v, out_v):
        log.warning("simplify: the fast collapse put a vertex far outside the mesh; "
                    "made by MeshLab's instead")
        return _decimate(v, f, target + (len(f) - len(free)), True, True, keep)
    out_f = _drop_double_faces(out_f)
    if not locked:
        return out_v, out_f
    # weld: the border's vertices did not move; the kept faces' vertices are matched to
    # them by position
    kept = f[keep]
    k_used, k_inv = np.unique(kept, return_inverse=True)
    all_v = np.concatenate([out_v, v[k_used]])
    all_f = np.concatenate([out_f, k_inv.reshape(-1, 3) + len(out_v)])
    uniq, weld = np.unique(all_v, axis=0, return_inverse=True)
    return uniq, weld.reshape(-1)[all_f]


class _Distance:
    """Fast two-sided distance between a fixed mesh and candidates (Open3D/Embree), on
    the samples of :func:`hausdorff_distance` with ``n_samples`` (each mesh's vertices,
    then area samples up to that many; the same seeds), so that a candidate within the
    bound here is within it in the reported measure too.

    With ``loose`` ((F,) bool: the fixed mesh's inferred faces, all three vertices
    inferred) the samples on inferred surface have the bound ``loose_bound`` instead of
    the candidate's: a fixed mesh's sample by its face, a candidate's by the face of the
    fixed mesh nearest to it."""

    def __init__(self, v: np.ndarray, f: np.ndarray, n_samples: int, seed: int,
                 threads: int = 1, loose: np.ndarray | None = None,
                 loose_bound: float | None = None) -> None:
        import open3d as o3d

        self.shift = v.mean(axis=0)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor((v - self.shift).astype(np.float32)),
                                 o3d.core.Tensor(f.astype(np.uint32)))
        self.samples, on_face = _measure_samples(v, f, n_samples, seed, faces=True)
        self.n_samples, self.seed, self.threads = n_samples, seed, threads
        self.loose = None
        if loose is not None and loose_bound is not None and np.any(loose):
            self.loose, self.loose_bound = np.asarray(loose, dtype=bool), float(loose_bound)
            # a vertex is loose when every face around it is; an area sample by its face
            tight_v = np.zeros(len(v), dtype=bool)
            tight_v[f[~self.loose].ravel()] = True
            self.samples_loose = np.concatenate([~tight_v, self.loose[on_face]])
            self.all_loose = bool(self.loose.all())

    def _loose_at(self, points: np.ndarray) -> np.ndarray:
        """Whether the fixed mesh's face nearest to each point is inferred."""
        import open3d as o3d

        from .evaluate import open3d_threads

        if not len(points):
            return np.zeros(0, dtype=bool)
        with open3d_threads(self.threads):
            prim = self.scene.compute_closest_points(o3d.core.Tensor(
                (points - self.shift).astype(np.float32)))["primitive_ids"].numpy()
        return self.loose[prim.astype(np.int64)]

    def _split_max(self, q: np.ndarray, d: np.ndarray, bound: float
                   ) -> tuple[float, float, np.ndarray, np.ndarray]:
        """The candidate's samples ``q`` at distances ``d`` from the fixed mesh, split by the
        fixed mesh's nearest face: (measured max, inferred max, the indices whose face
        was looked up, their looseness). Only the samples beyond ``bound`` or near the
        largest distance are looked up (the rest are within either bound), and more, a
        halved threshold at a time, while one surface's maximum is still unknown. When
        every face of the fixed mesh is inferred (a hull alone) none is looked up: the
        search for a measured one went down to every sample, four times a check, 4.5 s
        of DTU scan 24's 10.8 s simplification (stop 58)."""
        if self.all_loose:
            return 0.0, float(d.max(initial=0.0)), np.arange(len(d)), np.ones(len(d), bool)
        t = min(bound, 0.5 * float(d.max(initial=0.0)))
        for t_k in (t, t / 2, t / 4, t / 8, t / 16, -np.inf):  # -inf: every sample
            idx = np.nonzero(d > t_k)[0]
            lo = self._loose_at(q[idx])
            known_m, known_i = bool(np.any(~lo)), bool(np.any(lo))
            if known_m and known_i:
                break
        return (float(d[idx][~lo].max()) if known_m else 0.0,
                float(d[idx][lo].max()) if known_i else 0.0, idx, lo)

    def __call__(self, v: np.ndarray, f: np.ndarray, bound: float = np.inf
                 ) -> tuple[float, np.ndarray, dict[str, Any]]:
        """(the two-sided distance, the samples of either mesh farther than ``bound``
        from the other, :func:`hausdorff_distance`'s dict of the fixed mesh as ``a``).
        With inferred faces the distance is scaled to ``bound``'s units (an inferred
        sample's distance times ``bound / loose_bound``), the samples beyond their own
        bound are returned, and the dict has ``measured_max`` and ``inferred_max`` (the
        unscaled maxima on either surface). The dict's ``tail`` is the larger of the two
        sides' :func:`_tail` (scaled like the distance), what the next step is sized by."""
        import open3d as o3d

        from .evaluate import open3d_threads

        a = _distances_to(v, f, self.samples, self.shift, self.threads)
        q = _measure_samples(v, f, self.n_samples, self.seed + 1)  # b_to_a's seed
        with open3d_threads(self.threads):
            b = self.scene.compute_distance(o3d.core.Tensor(
                (q - self.shift).astype(np.float32))).numpy()
        b = b.astype(np.float64)
        stats = {"a_to_b": _stats(a), "b_to_a": _stats(b), "max": float(max(a.max(), b.max()))}
        if self.loose is None:
            far = np.concatenate([self.samples[a > bound], q[b > bound]])
            stats["tail"] = max(_tail(a), _tail(b))
            return stats["max"], far, stats
        la = self.samples_loose
        mb, ib, idx, lb = self._split_max(q, b, bound)
        ma = float(a[~la].max()) if np.any(~la) else 0.0
        ia = float(a[la].max()) if np.any(la) else 0.0
        stats["measured_max"], stats["inferred_max"] = max(ma, mb), max(ia, ib)
        scale = bound / self.loose_bound if np.isfinite(bound) else 1.0
        sa = np.where(la, a * scale, a)
        sb = b.copy()
        sb[idx[lb]] *= scale
        far = np.concatenate([self.samples[sa > bound], q[sb > bound]])
        stats["tail"] = max(_tail(sa), _tail(sb))
        return float(max(sa.max(), sb.max())), far, stats


def _tail(d: np.ndarray) -> float:
    """The distance that all but 1 in 10,000 samples stay within (the 99.99th percentile,
    the upper order statistic): how far a step went over the mesh as a whole, apart from
    the few places where it went farther."""
    if not len(d):
        return 0.0
    k = min(len(d) - 1, int(math.ceil(0.9999 * (len(d) - 1))))
    return float(np.partition(d, k)[k])


#: the first step's factor (no distance known yet): a fused TSDF mesh samples its surface
#: at the fusion voxel, far more densely than its shape needs (simulated cup/4: a quarter
#: of its 656,978 faces stays within 0.017 mm of it at all but 1 in 10,000 samples)
_FIRST_STEP = 4.0
#: the step's aim: its tail (:func:`_tail`) at this share of the bound, the error taken
#: as inversely proportional to the face count (measured: cup/4's tail 0.0069 / 0.0141 /
#: 0.034 / 0.072 / 0.140 mm at 328k / 165k / 83k / 42k / 22k faces)
_STEP_AIM = 0.35
#: the step's factor is kept within these (at least a halving, at most an eighth)
_STEP_MIN, _STEP_MAX = 2.0, 8.0


def _step_factor(tail: float | None, bound: float) -> float:
    """How many times fewer faces the next step asks for: :data:`_FIRST_STEP` at first,
    then what brings the last step's tail to :data:`_STEP_AIM` of the bound if the error
    grows as the face count falls (halving at least, an eighth at most). The tail, not
    the maximum: the maximum sits at the one or two places that the locks then keep, and
    it said nothing of the rest (cup/4: 0.155 mm at every step from 328k to 83k faces,
    where the tail went 0.007 -> 0.034 mm), so a step far within the bound elsewhere
    stayed a halving."""
    if tail is None:
        return _FIRST_STEP
    return min(_STEP_MAX, max(_STEP_MIN, _STEP_AIM * bound / max(tail, 1e-12)))


#: rounds of :func:`_decimate_within`'s local locks per step before it gives the step up
_LOCK_ROUNDS = 4
#: :func:`_decimate_within`'s attempts at the target straight away: the collapse, and
#: once more with the places where it went beyond the bound kept
_DIRECT_ROUNDS = 2
#: faces of the mesh being decimated within this many times the error bound of a place
#: where a step went beyond it are kept as they are (0.2 mm: 2 mm)
_LOCK_RADIUS_BOUNDS = 10.0


def _places(points: np.ndarray, radius: float) -> np.ndarray:
    """The distinct places among ``points``: the mean of each cell of a grid of
    ``radius / 2`` (a point lies within 0.45 ``radius`` of its place)."""
    if not len(points):
        return points
    cell = np.floor(points / (0.5 * radius)).astype(np.int64)
    _, inv = np.unique(cell, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = int(inv.max()) + 1
    out = np.zeros((n, 3))
    np.add.at(out, inv, points)
    return out / np.bincount(inv, minlength=n)[:, None]


#: at least this many faces nearest to each place are kept, however large the faces
_LOCK_MIN_FACES = 12


def _locked_faces(v: np.ndarray, f: np.ndarray, places: np.ndarray, radius: float
                  ) -> np.ndarray | None:
    """(F,) bool: the faces whose centre lies within ``radius`` of one of ``places``, and
    the :data:`_LOCK_MIN_FACES` nearest to each place (where faces are larger than the
    radius: a hull of 3.6 mm voxels, whose places beyond the bound kept 1 face each and
    failed again, the halving stopped at 63,000 faces)."""
    from scipy.spatial import cKDTree

    if not len(places):
        return None
    centres = v[f].mean(axis=1)
    d, idx = cKDTree(places).query(centres, distance_upper_bound=radius)
    keep = np.isfinite(d)
    k = min(_LOCK_MIN_FACES, len(f))
    few = np.bincount(idx[keep], minlength=len(places)) < k
    if np.any(few):  # only there: the tree of every face's centre costs a mesh's worth
        _, near = cKDTree(centres).query(places[few], k=k)
        keep[np.asarray(near).ravel()] = True
    return keep


def _decimate_within(v: np.ndarray, f: np.ndarray, target: int, max_error: float,
                     preserve_boundary: bool, preserve_normal: bool, tolerance: float,
                     n_check: int, seed: int, threads: int = 1,
                     loose: np.ndarray | None = None, loose_error: float | None = None):
    """The error-bounded mode of :func:`simplify_mesh`: the target straight away, once
    more with the places where that went beyond ``max_error`` kept as they are (below)
    when it did so at a few places only (the tail, all but 1 in 10,000 samples, within
    the bound); else, or when that too went beyond, from the fused mesh again (those
    places not kept), progressive steps towards
    ``target``, each checked as it is made: a quarter of the faces first, then as many
    times fewer as bring the last step's tail (all but 1 in 10,000 samples) to
    :data:`_STEP_AIM` of the bound, between a halving and an eighth (:func:`_step_factor`;
    halving every step, as before stop 46, took the simulated cup/4 11 checked trials and
    25.4-27.8 s of the stage, these steps 7 trials and 19.1-19.3 s, runs alternating).
    Where a step
    goes beyond ``max_error`` the places where it does (the samples of either mesh
    farther than that from the other) are remembered and the step is made again with the
    faces around every such place kept as they are (``_LOCK_RADIUS_BOUNDS`` times the
    bound), up to ``_LOCK_ROUNDS`` times; a step still beyond it ends the steps, and a
    log-scale search between the last step within the bound and that one follows (the
    same places kept), each trial decimating the last mesh found within the bound;
    (vertices, faces, the search's distance of the result, trials, places kept, the
    result's :func:`hausdorff_distance` dict from its check, None for the input).

    Why locks: the bound is global, and one or two spots decide it. On the simulated
    cup/4 a flap of a few fused vertices went 0.28 mm off when the 656,000-face mesh was
    halved once, and the search ended at 601,674 faces; with such places kept (31 by the
    end) the halving reaches the 20,000 target (22,282 faces, 2,282 kept as they were), within
    0.2 mm everywhere (``benchmarks/README.md``).

    Why this order: on a fused TSDF mesh (hundreds of thousands of faces at
    ``fusion.tsdf_voxel_m``) the bound usually stops the search far above ``target``.
    Halving all the way down first and then decimating every trial from the last good
    step cost about twice as many quadric collapses (a small simulated scan: 556,450 faces
    in, 151,702 out, 29 s before, ``benchmarks/README.md``).

    Why the target first: where the bound allows it (the objects benchmark's fused meshes
    of 200,000-700,000 faces at 0.2 mm: every one, some with a few places kept) one
    collapse from the fused mesh does it, where the steps took 4-8 checked trials: on the
    bumpy blob / 7, the bottle / 7, the user's bracket / 7, cup / 7 and cup / 4 the stage
    5.5 / 5.4 / 5.7 / 10.5 / 12.6 s -> 3.2 / 2.9 / 4.3 / 6.6 / 7.7 s, the meshes 0.0001 mm
    nearer to the truth at the median or within 0.001 mm of it (one collapse from the
    fused mesh keeps its quadrics); on a mesh the bound stops far above the target it
    costs one more trial (stop 61)."""
    n_trials = 0
    dist = _Distance(v, f, n_check, seed, threads, loose, loose_error)
    radius = _LOCK_RADIUS_BOUNDS * max_error
    places = np.zeros((0, 3))
    good = (v, f.astype(np.int64), 0.0, None)
    bad_n = None
    n = len(f)

    def attempt(count: int) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, dict]:
        nonlocal n_trials
        keep = _locked_faces(good[0], good[1], places, radius)
        if preserve_boundary:
            cand_v, cand_f = _fast_decimate(good[0], good[1], count, max_error, keep)
        else:  # the fast collapse holds every open border
            cand_v, cand_f = _decimate(good[0], good[1], count, preserve_boundary,
                                       preserve_normal, keep)
        n_trials += 1
        d, far, stats = dist(cand_v, cand_f, max_error)
        return cand_v, np.asarray(cand_f, dtype=np.int64), d, far, stats

    good_tail = None
    for _ in range(_DIRECT_ROUNDS if n > target else 0):  # the target straight away
        cand_v, cand_f, d, far, stats = attempt(target)
        if d <= max_error:
            return cand_v, cand_f, d, n_trials, places, stats
        places = _places(np.concatenate([places, far]), radius)
        if stats["tail"] > max_error:  # too coarse as a whole, not at a few places
            break
    places = np.zeros((0, 3))  # the steps find their own
    while n > target and bad_n is None:  # progressive steps, checked as they go
        n = max(target, int(n / _step_factor(good_tail, max_error)))
        for k in range(_LOCK_ROUNDS + 1):
            cand_v, cand_f, d, far, stats = attempt(n)
            if d <= max_error:
                good = (cand_v, cand_f, d, stats)
                good_tail = stats["tail"]
                break
            if k < _LOCK_ROUNDS:
                places = _places(np.concatenate([places, far]), radius)
        else:
            bad_n = len(cand_f)
    if bad_n is not None:  # search between the last good count and the failing one
        lo, hi = bad_n, len(good[1])
        while hi > lo * (1.0 + tolerance) and hi - lo > 1:
            mid = int(round(math.sqrt(lo * hi)))
            mid = min(max(mid, lo + 1), hi - 1)
            cand_v, cand_f, d, _, stats = attempt(mid)
            if d <= max_error:
                good, hi = (cand_v, cand_f, d, stats), mid
            else:
                lo = mid
    return good[0], good[1], good[2], n_trials, places, good[3]


def simplify_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    options: SimplifyOptions = SimplifyOptions(),
    preserve_boundary: bool = True,
    preserve_normal: bool = True,
    tolerance: float = 0.1,
    n_samples: int = 200_000,
    inferred: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Quadric edge-collapse decimation to a face count and/or within an error bound.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int
    options : SimplifyOptions
        ``target_faces``: decimate to at most this many faces (unless the error bound
        forbids it); the error bound (:attr:`SimplifyOptions.error_bound_m`, the smaller
        of ``hausdorff_tolerance_m`` and ``max_error_m``): the largest allowed two-sided
        Hausdorff distance between input and result, i.e. the fewest faces, not below
        ``target_faces``, whose distance stays within it (progressive decimation and a
        log-scale search, see the module notes); ``seed``.
    preserve_boundary, preserve_normal : bool
        Quadric options: keep open borders in place; refuse collapses that flip a face.
    tolerance : float
        Relative precision of the face-count search (stop when hi / lo < 1 + tolerance).
    n_samples : int
        Area samples of the input for the search's distance checks (plus its vertices),
        seeded with ``options.seed``.
    inferred : (V,) bool, optional
        The input's vertices on inferred surface (hull-closed, hole-filled). A face whose
        three vertices are inferred, and the samples on it or nearest to it, are held to
        :attr:`SimplifyOptions.inferred_bound_m` in the error-bounded mode instead of the
        error bound: surface that no sensor measured is not kept at the measurement's
        precision.

    Returns
    -------
    vertices : (V', 3) float64
    faces : (F', 3) int64
    report : dict
        ``n_faces_in``, ``n_vertices_in``, ``n_faces``, ``n_vertices``,
        ``target_faces``, ``max_error_m``, ``n_trials``, ``search_distance_m`` (the fast
        check of the result), ``hausdorff_max_m`` (the two-sided sampled Hausdorff
        distance, metres) and ``hausdorff_m``: {``fused_to_simplified``: {max, mean,
        rms}, ``simplified_to_fused``: {...}, ``max``} in metres; in the error-bounded
        mode also ``kept_places`` (where a step went beyond the bound) and
        ``kept_faces`` (the result's faces around them, left at the input's resolution);
        with ``inferred`` also ``inferred_error_m`` (its bound),
        ``hausdorff_measured_max_m`` and ``hausdorff_inferred_max_m`` (the distance's
        maximum on either surface).

    Raises
    ------
    ValueError
        When there is neither a face target nor an error bound, or they are not positive.

    References
    ----------
    Garland & Heckbert (1997); Cignoni, Rocchini & Scopigno (1998).
    """
    v, f = _check_mesh(vertices, faces)
    target_faces, max_error, seed = options.target_faces, options.error_bound_m, options.seed
    if target_faces is None and max_error is None:
        raise ValueError("give target_faces, max_error_m or hausdorff_tolerance_m, or both")
    if target_faces is not None and int(target_faces) < 1:
        raise ValueError(f"target_faces must be >= 1, got {target_faces}")
    if max_error is not None and not max_error > 0:
        raise ValueError(f"max_error_m and hausdorff_tolerance_m must be > 0 metres, got "
                         f"{max_error}")
    report: dict[str, Any] = dict(n_faces_in=int(len(f)), n_vertices_in=int(len(v)),
                                  target_faces=target_faces, max_error_m=max_error)
    if len(f) == 0:
        report.update(n_faces=0, n_vertices=int(len(v)), n_trials=0, hausdorff_max_m=None,
                      hausdorff_m=None, search_distance_m=None)
        return v, f.astype(np.int64), report
    target = int(target_faces) if target_faces is not None else max(4, len(f) // 1000)
    n_trials = 0
    search_d = searched = None
    n_check = min(len(v) + n_samples, 2_000_000)  # samples on each side, both measures
    if max_error is None or target >= len(f):
        ov, of = (_decimate(v, f, target, preserve_boundary, preserve_normal)
                  if target < len(f) else (v, f.astype(np.int64)))
        n_trials = 1
    else:
        loose = None
        if inferred is not None:
            inferred = np.asarray(inferred, dtype=bool)
            if inferred.shape != (len(v),):
                raise ValueError(f"inferred must have one flag per vertex ({len(v)}), got "
                                 f"shape {inferred.shape}")
            loose = inferred[f].all(axis=1)
            report["inferred_error_m"] = options.inferred_bound_m
        ov, of, search_d, n_trials, places, searched = _decimate_within(
            v, f, target, max_error, preserve_boundary, preserve_normal, tolerance,
            n_check, seed, options.threads, loose, options.inferred_bound_m)
        if searched is not None:  # unscaled: the largest distance on either surface
            search_d = searched["max"]
        kept = _locked_faces(ov, of, places, _LOCK_RADIUS_BOUNDS * max_error)
        report.update(kept_places=int(len(places)),
                      kept_faces=int(kept.sum()) if kept is not None else 0)
    # the search's last check is the measure itself (the same samples, both ways)
    hd = (searched if searched is not None else
          hausdorff_distance(v, f, ov, of, n_samples=n_check, seed=seed,
                             threads=options.threads)
          if len(of) < len(f) else {"a_to_b": _zero(), "b_to_a": _zero(), "max": 0.0})
    if "measured_max" in hd:
        report.update(hausdorff_measured_max_m=hd["measured_max"],
                      hausdorff_inferred_max_m=hd["inferred_max"])
    report.update(n_faces=int(len(of)), n_vertices=int(len(ov)), n_trials=n_trials,
                  search_distance_m=search_d, hausdorff_max_m=hd["max"],
                  hausdorff_m={"fused_to_simplified": hd["a_to_b"],
                               "simplified_to_fused": hd["b_to_a"], "max": hd["max"]})
    log.info("simplify_mesh: %d -> %d faces, Hausdorff %.3g m (%d trials)", len(f), len(of),
             hd["max"], n_trials)
    return ov, np.asarray(of, dtype=np.int64), report


def _zero() -> dict[str, float]:
    return {"max": 0.0, "mean": 0.0, "rms": 0.0}


def transfer_vertex_attributes(vertices_from: np.ndarray, attributes: dict[str, np.ndarray],
                               vertices_to: np.ndarray, *, tree: Any = None, threads: int = 1
                               ) -> dict[str, np.ndarray]:
    """Per-vertex attributes (e.g. the fusion's provenance and confidence) carried from a
    mesh to its cleaned / simplified version: each new vertex takes those of the nearest
    original vertex (quadric collapse places a vertex on the surface it replaces, within
    the Hausdorff tolerance, so its nearest original vertex lies in the same region).

    Parameters
    ----------
    vertices_from : (V, 3) float
        The original mesh's vertices, one row per entry of each attribute.
    attributes : dict of str to (V,) array
    vertices_to : (W, 3) float
    tree : scipy.spatial.cKDTree, optional
        The tree of ``vertices_from`` when the caller has it (the simplify stage asks
        twice with the same original vertices); built here otherwise.
    threads : int
        Threads of the nearest-vertex query (the result does not depend on it).

    Returns
    -------
    dict of str to (W,) array
        Same keys and dtypes; empty when ``attributes`` is.
    """
    from scipy.spatial import cKDTree

    if not attributes:
        return {}
    v0 = np.asarray(vertices_from, np.float64).reshape(-1, 3)
    v1 = np.asarray(vertices_to, np.float64).reshape(-1, 3)
    for k, a in attributes.items():
        if len(a) != len(v0):
            raise ValueError(f"attribute {k!r} has {len(a)} values for {len(v0)} vertices")
    if len(v1) == 0 or len(v0) == 0:
        return {k: np.zeros(len(v1), a.dtype) for k, a in attributes.items()}
    _, nn = (cKDTree(v0) if tree is None else tree).query(v1, k=1,
                                                          workers=max(1, int(threads)))
    return {k: np.asarray(a)[nn] for k, a in attributes.items()}
