"""Fine alignment of laser sweeps: symmetric point-to-plane ICP between overlapping sweeps,
then a pose graph (multiway registration) that spreads the pairwise constraints over all
sweeps, then a joint refinement in the sensor's motion model with the silhouettes as
absolute reference.

The robot's poses already place every sweep in ``base`` to within its positioning error
(typically a few tenths of a millimetre); alignment removes the remaining misfit between
sweeps. It never replaces the robot's poses: it computes one small *correction* per sweep
(rigid, ``C[s]`` applied on the left, ``points_aligned = C[s] @ points_base``; after the
refinement the sensor turned about its position and shifted, :func:`apply_correction`).
The parameters are :class:`AlignOptions` (config section ``alignment``); the record of
what was measured when these choices were made is in ``benchmarks/README.md`` ("Notes
moved from robo3d/registration.py").

Method
------
1. Each sweep is thinned on a voxel grid (``voxel_size_m``) by keeping *one measured point
   per voxel* with its own normal, and, past ``max_points`` points, randomly subsampled
   with ``seed``. Choice: selecting, not averaging a voxel's points (Open3D's
   ``voxel_down_sample``): averaged points leave a curved surface and bias ICP.
2. For every pair of sweeps the *overlap* is the larger of the two fractions of points with
   a partner within ``max_corr_dist_m`` in the other sweep, at the robot's poses. Pairs
   with ``overlap >= min_overlap`` are registered from the identity (the robot's relative
   pose) by Open3D's *symmetric* point-to-plane ICP (Rusinkiewicz 2019), coarse to fine:
   the correspondence distance is halved from ``max_corr_dist_m`` down to
   ``max(voxel_size_m, max_corr_dist_m / 4)`` (at most three levels); plain
   point-to-plane ICP at a single distance is biased where the overlap ends and between
   differently sampled curved surfaces. A pairwise result is rejected if ICP has not
   converged (one more iteration at the finest distance still moves it by more than 1 % of
   ``voxel_size_m`` or 0.005 degrees, unless the iterations cycle within a tenth of the
   voxel and 0.05 degrees of it: the pair's ``icp_cycle``, used only for a sweep that
   no other accepted pair joins), if its fitness falls below ``min_overlap``, or if the
   relative correction exceeds twice the per-sweep bounds.
3. ``method="pose_graph"``: the accepted pairs form the edges of an Open3D pose graph
   (nodes = sweep corrections, initial value identity; edges weighted by the information
   matrix of their correspondences), optimised by Levenberg–Marquardt (Choi, Zhou & Koltun
   2015). Edges of the maximum-overlap spanning tree are marked certain, the others (loop
   closures) uncertain, so that Open3D's line process can prune an inconsistent loop
   closure. ``method="sequential"``: sweeps are visited in order of the maximum-overlap
   spanning tree from the reference and each is registered (ICP) against the union of its
   already-aligned neighbours; errors accumulate along the tree, which is what the pose
   graph avoids.
4. Gauge (the free global rigid motion every multiway registration has): by default
   (``gauge="reference"``) the reference sweep -- the one with the largest summed overlap
   with the others, lowest index on ties -- keeps its robot pose (``C[ref] = I``). With
   ``gauge="mean"`` the corrections of the aligned sweeps are re-expressed so their mean
   is the identity (mean rotation by SVD projection of the mean rotation matrix, mean
   displacement of the object's centroid zero), which averages the robots' pose errors.
5. Guards: a sweep whose correction exceeds ``max_correction_mm`` (displacement of the
   sweep's centroid) or ``max_correction_deg`` is removed from the graph, kept at its
   robot pose (``C = I``) and flagged with the reason; the graph is then optimised again
   without it (worst offender first, one at a time). Sweeps with no accepted pair, or not
   connected to the reference through accepted pairs, are flagged the same way. A flagged
   sweep is never bent into place.

6. Refinement (``refine``, the pipeline's default; :func:`refine_sweeps`). The pose
   graph corrects each sweep rigidly; but the robot's error is a constant pose error of
   the moving sensor, and turning a sensor that translates along a sweep shears the
   sweep's points (``rotation error x travel``), which no rigid transform undoes. All
   sweeps are therefore refined jointly in that motion model (the sensor turned about its
   own position at every frame, and shifted: :func:`apply_correction`), by Gauss-Newton
   on the point-to-plane distances of every overlapping pair, the distance of each
   silhouette view's contour-generator points to that view's image edge, and a prior on
   each correction (the robot's expected error, ``prior_mm``, ``prior_deg``). Relative
   ICP cannot say where the object is: with the pose graph's reference gauge the gauge
   sweep keeps its own robot error. The silhouette views are taken at rest, their poses
   about ten times more accurate than a moving sweep's: they are the absolute reference.
   Without views the sweeps' priors hold the gauge (no sweep is fixed: the solution
   averages the sweeps' robot errors). Contour points come from the laser clouds
   (extremal points of each laser profile whose normal is perpendicular to the line of
   sight, the profile continuing on both sides), their residual from the grey image's
   own edge (the largest gradient along the silhouette's normal, or a distinct one
   outward of it: :func:`_outline_edge`), not from the segmented
   mask (which is eroded by a fraction of a pixel, more on shaded sides). The pair term's
   normals are principal axes over three adjacent profiles (:func:`_pair_normals`),
   points whose grid normal disagrees left out; a correspondence whose two normals differ
   by more than 60 degrees is left out too (the two sides of a thin wall lie within the
   correspondence distance); the silhouette term weighs ``rim_weight`` times its robust
   scale. When the correspondences cycle near the optimum the steps are shortened and
   the cycle's mean taken. The refinement settles in a minimum near its start, so with
   views it also runs from the robot's poses (``robot_start``) and that end is taken
   when its silhouette residuals are clearly lower (``robot_start_margin``): a pose graph
   that rests on a pair of little overlap can start it far off
   (:func:`_refine_two_starts`). The bounds are checked again on the refined
   corrections; if the refinement does not converge, every sweep stays at its robot
   pose, flagged.

7. Directions the data do not constrain (issue 11: flat faces, symmetric bodies, few
   sweeps). Both the pairwise ICP and the refinement whiten their normal equations by
   the prior (the robot's expected error), so that an eigenvalue is the data's
   information along its eigenvector in units of the prior's; directions below
   ``degenerate_ratio`` (refinement) / ``pair_degenerate_ratio`` (pairs) are taken out
   of the data's equations and held at the robot's pose (:func:`_solve_held`,
   :func:`_held_icp`; Zhang, Kaess & Singh 2016). The threshold is not 1: point-to-plane
   information is overstated by the noise of the normals (a noisy normal is never
   parallel to a sphere's radius, so the sphere's exactly free turns show information)
   and by residuals that are correlated along a profile; the thresholds were chosen
   between the information of held and constrained directions on simulated scans. A pair
   with a held direction, or whose ICP slid off the overlap, is registered by
   :func:`_held_icp` from the robot's relative pose; its convergence is judged on the
   held step. So is a pair that sees the two sides of a thin wall (more than 2 % of its
   points' nearest partners within ``max_corr_dist_m`` with an opposed normal,
   :func:`_opposed_fraction`, at the robot's poses): Open3D's ICP pairs the two faces,
   _held_icp leaves correspondences whose normals differ by more than 60 degrees out; such
   a pair skips Open3D's ICP, whose result _held_icp would not use. With silhouette
   views a sweep with no accepted pair still takes part in the refinement (against the
   views, with its overlapping pairs). Each sweep's report (``per_sweep``) gives
   ``constrained`` (translation along / rotation about the principal axes of its points:
   fixed by the data or not), ``unconstrained`` (the held directions in plain words: a
   rotation about an axis through a point, base mm, or a translation) and
   ``information`` (its block's whitened eigenvalues), with silhouettes also
   ``profile_noise_mm`` / ``_px`` (its points' scatter about their profiles) and
   ``rim_fit_share`` (how far the silhouette term's points were moved toward their fit
   along the profiles: :func:`_rim_points`); each pair ``held_directions``,
   ``min_information`` and ``registered_by`` (which ICP, and why), and ``icp_cycle``
   (``period``, ``span_mm``, ``span_deg``) where its ICP converged to a cycle.

All computations run in a frame centred on the centroid of all points (better conditioned
than ``base``, whose origin may be half a metre away); results are returned in ``base``.
Reproducibility: Open3D's registration runs on one thread here (its parallel reductions
differ in the last bit from run to run); the same input gives the same corrections, bit
for bit.

References
----------
Besl, P. J. & McKay, N. D. (1992). A method for registration of 3-D shapes. IEEE PAMI 14(2).
Chen, Y. & Medioni, G. (1992). Object modelling by registration of multiple range images.
Image and Vision Computing 10(3) (point-to-plane ICP).
Rusinkiewicz, S. (2019). A symmetric objective function for ICP. ACM TOG 38(4).
Choi, S., Zhou, Q.-Y. & Koltun, V. (2015). Robust reconstruction of indoor scenes. CVPR
(pose graph with line-process pruning, as implemented in Open3D).
Triggs, B., McLauchlan, P., Hartley, R. & Fitzgibbon, A. (2000). Bundle adjustment - a
modern synthesis. Vision Algorithms: Theory and Practice (robust Gauss-Newton, priors).
Cipolla, R. & Giblin, P. (2000). Visual Motion of Curves and Surfaces. CUP (contour
generators and silhouettes).
Zhang, J., Kaess, M. & Singh, S. (2016). On degeneracy of optimization-based state
estimation problems. ICRA (degenerate directions from the normal equations' eigenvalues,
solution remapping).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from .options import Options
from .transforms import correction_at, invert_transform, rotation_angle_deg

__all__ = ["AlignOptions", "AlignmentResult", "RefinementResult", "SilhouetteViews",
           "align_sweeps",
           "apply_correction", "correction_at", "refine_sweeps"]


@njit(inline="always", cache=True)
def distort_xy(x, y, k1, k2, p1, p2, k3):  # noqa: ANN001, ANN202 - numba helper
    """Plumb_bob distortion of one normalised point, operation for operation as
    :meth:`robo3d.camera.CameraModel.distort_normalized`, for compiled kernels:
    ``(xd, yd)``. Here, not in :mod:`robo3d.camera`, so that importing the camera model
    does not import numba (0.17 s in every workflow job)."""
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
            y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)


log = logging.getLogger(__name__)

_MIN_POINTS = 10


@dataclass(frozen=True)
class AlignOptions(Options):
    """The parameters of :func:`align_sweeps` and :func:`refine_sweeps` (config section
    ``alignment``; ``enabled``, ``silhouettes`` and the ``outside_hull_*`` keys are the
    stage's), and the recording's seed.

    Attributes
    ----------
    method : {"pose_graph", "sequential"}
        Multiway pose-graph optimisation, or one sweep after another along the
        maximum-overlap spanning tree.
    voxel_size_m : float, metres
        Grid on which each sweep is thinned (one measured point per voxel) before
        registration; also the finest ICP correspondence distance (0 disables).
    max_corr_dist_m : float, metres
        Largest point-to-point distance of an ICP correspondence, and of the overlap test.
    max_iterations : int
        ICP iterations per registration.
    max_correction_mm, max_correction_deg : float
        Bounds on a sweep's correction (displacement of its centroid; rotation angle).
        Larger corrections are refused: the sweep stays at its robot pose, flagged.
    min_overlap : float in (0, 1]
        Smallest overlap (fraction of points with a partner) for a pair to be registered.
    refine : bool
        After the pose graph, refine all sweeps jointly (:func:`refine_sweeps`).
    prior_mm, prior_deg : float
        The robot's expected per-sweep error (the refinement's prior, and the whitening
        of the pairs' information).
    refine_iterations : int
        Gauss-Newton iterations of the refinement at most.
    rim_weight : float
        Weight of the silhouette term relative to its residuals' robust scale.
    pair_normals_k : int
        Neighbours per profile of the refinement's pair-term normals (0: the
        triangulation's normals).
    pair_normals_max_spacing_m : float, metres
        Those normals only for sweeps whose profiles are at most this far apart.
    degenerate_ratio, pair_degenerate_ratio : float
        Least whitened information of a direction the refinement / a pair's ICP takes
        from the data (the others are held at the robot's pose).
    robot_start : bool
        With the silhouettes as reference, run the refinement from the robot's poses as
        well as from the pose graph's, and take that result when its silhouette
        residuals' RMS is lower by more than ``robot_start_margin`` (a fraction).
    views_only_max_rim_rms_px : float, pixels
        A sweep refined against the views alone (no pair with another sweep: a one-sweep
        scan) keeps its refined pose only when its contour residuals' RMS is at most
        this; else it stays at the robot's pose, flagged.
    seed : int
        The recording's seed (config ``seed``): the subsamples.
    threads : int
        Worker threads (the job's, not a config key): the pairs are registered and the
        views' contour residuals found in parallel; the result does not depend on it
        (each task runs Open3D on one thread, and the terms are summed in a fixed order).
    """

    section = "alignment"
    not_in_config = ("seed", "threads")
    method: Literal["pose_graph", "sequential"] = "pose_graph"
    voxel_size_m: float = 0.0005
    max_corr_dist_m: float = 0.002
    max_iterations: int = 50
    max_correction_mm: float = 5.0
    max_correction_deg: float = 3.0
    min_overlap: float = 0.05
    refine: bool = True
    prior_mm: float = 0.5
    prior_deg: float = 0.3
    refine_iterations: int = 30
    rim_weight: float = 3.0
    pair_normals_k: int = 8
    pair_normals_max_spacing_m: float = 0.0015
    degenerate_ratio: float = 200.0
    pair_degenerate_ratio: float = 10.0
    robot_start: bool = True
    robot_start_margin: float = 0.03
    views_only_max_rim_rms_px: float = 1.0
    seed: int = 0
    threads: int = 1


@dataclass
class AlignmentResult:
    """Result of :func:`align_sweeps`.

    Attributes
    ----------
    corrections : (S, 4, 4) float64
        Rigid corrections applied on the left: ``points_aligned = C[s] @ points_base`` for
        the points of sweep ``s``. Identity for the reference (``gauge="reference"``) and
        for every flagged sweep.
    pairs : list of dict
        One entry per pair of sweeps that overlap at all: ``i``, ``j``, ``overlap`` (at the
        robot's poses), ``fitness`` (the same fraction after pairwise ICP) and ``rmse_mm``
        (RMS point-to-plane distance of the correspondences within ICP's finest
        correspondence distance), ``rmse_before_mm`` (the same at the robot's poses),
        ``converged``,
        ``accepted``, ``reason`` (why rejected, "" if accepted), ``used`` (an edge of the
        final optimised graph), ``residual_mm`` / ``residual_deg`` (disagreement between
        the pairwise ICP result and the final corrections). Values that were not measured
        (a pair not registered, an edge not used) are None.
    per_sweep : list of dict
        One entry per sweep: ``sweep``, ``n_points``, ``n_used``, ``translation_mm``
        (displacement of the sweep's centroid), ``max_displacement_mm`` (largest
        displacement of any of its points), ``rotation_deg``, ``converged``, ``flagged``,
        ``reason``.
    reference : int
        The reference sweep (-1 when there are no sweeps).
    method : str
        ``"pose_graph"`` or ``"sequential"``.
    gauge : str
        ``"reference"`` or ``"mean"``.
    """

    corrections: np.ndarray
    pairs: list[dict[str, Any]] = field(default_factory=list)
    per_sweep: list[dict[str, Any]] = field(default_factory=list)
    reference: int = -1
    method: str = "pose_graph"
    gauge: str = "reference"
    rotations: np.ndarray | None = None
    translations: np.ndarray | None = None
    refinement: dict[str, Any] | None = None

    def apply(self, s: int, points: np.ndarray, origins: np.ndarray | None = None,
              normals: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """Correct sweep ``s``: (points, origins, normals) as aligned.

        After refinement the sensor model of :func:`apply_correction` is used (it needs
        ``origins``); otherwise the rigid ``corrections[s]``.
        """
        p = np.asarray(points, dtype=np.float64)
        if self.rotations is not None and origins is not None:
            return apply_correction(p, origins, self.rotations[s], self.translations[s],
                                    normals)
        c = self.corrections[s]
        o = (None if origins is None
             else np.asarray(origins, dtype=np.float64) @ c[:3, :3].T + c[:3, 3])
        nn = (None if normals is None
              else np.asarray(normals, dtype=np.float64) @ c[:3, :3].T)
        return p @ c[:3, :3].T + c[:3, 3], o, nn

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready summary (corrections as nested lists)."""
        out = {
            "method": self.method,
            "gauge": self.gauge,
            "reference": int(self.reference),
            "corrections": self.corrections.tolist(),
            "pairs": [_jsonable(p) for p in self.pairs],
            "per_sweep": [_jsonable(p) for p in self.per_sweep],
        }
        if self.rotations is not None:
            out["rotations"] = self.rotations.tolist()
            out["translations"] = self.translations.tolist()
            out["refinement"] = self.refinement
        return out


def _jsonable(d: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, np.generic):
            v = v.item()
        if isinstance(v, float) and not np.isfinite(v):
            v = None
        out[k] = v
    return out


# --------------------------------------------------------------------------- helpers


def _check_inputs(points: list, normals: list) -> tuple[list[np.ndarray], list[np.ndarray]]:
    if not isinstance(points, list | tuple) or not isinstance(normals, list | tuple):
        raise ValueError("points and normals must be lists of (N, 3) arrays, one per sweep")
    if len(points) != len(normals):
        raise ValueError(f"got {len(points)} point arrays but {len(normals)} normal arrays")
    pts, nrms = [], []
    for s, (p, n) in enumerate(zip(points, normals, strict=True)):
        p = np.asarray(p, dtype=np.float64)
        n = np.asarray(n, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points[{s}] must be (N, 3), got {p.shape}")
        if n.shape != p.shape:
            raise ValueError(f"normals[{s}] must be {p.shape} like points[{s}], got {n.shape}")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(n))):
            raise ValueError(f"sweep {s} has non-finite points or normals")
        pts.append(p)
        nrms.append(n)
    return pts, nrms


def _to_o3d(p: np.ndarray, n: np.ndarray):
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(p)
    pc.normals = o3d.utility.Vector3dVector(n)
    return pc


def _reduce(p: np.ndarray, n: np.ndarray, voxel_size: float, max_points: int,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Keep one measured point per voxel (the first), normalise normals, cap the size.

    Selecting rather than averaging keeps every point on the measured surface with its own
    normal: averaging a voxel's points pulls them off a curved surface and biases ICP.
    """
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-12
    p, n = p[ok], n[ok] / length[ok, None]
    if len(p) and voxel_size > 0:
        key = np.floor((p - p.min(axis=0)) / voxel_size).astype(np.int64)
        dims = key.max(axis=0) + 1
        flat = np.ravel_multi_index(key.T, dims) if np.prod(dims.astype(float)) < 2**62 else (
            np.unique(key, axis=0, return_inverse=True)[1])
        _, first = np.unique(flat, return_index=True)
        first.sort()
        p, n = p[first], n[first]
    if len(p) > max_points:
        keep = np.sort(rng.choice(len(p), size=max_points, replace=False))
        p, n = p[keep], n[keep]
    return p, n


def _conj(t: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Express a transform given in the frame centred at ``c`` in the original frame."""
    shift = np.eye(4)
    shift[:3, 3] = c
    unshift = np.eye(4)
    unshift[:3, 3] = -c
    return shift @ t @ unshift


def _motion(t: np.ndarray, centroid: np.ndarray) -> tuple[float, float]:
    """(displacement of ``centroid`` in mm, rotation in degrees) of a rigid transform."""
    moved = t[:3, :3] @ centroid + t[:3, 3]
    return float(np.linalg.norm(moved - centroid) * 1e3), float(rotation_angle_deg(t[:3, :3]))


def _icp_distances(max_corr_dist: float, fine_dist: float) -> list[float]:
    """The correspondence distances of coarse-to-fine ICP: halved from ``max_corr_dist``
    while not below ``fine_dist``, three at most."""
    dists = [max_corr_dist]
    while dists[-1] / 2 >= fine_dist * (1 - 1e-9) and len(dists) < 3:
        dists.append(dists[-1] / 2)
    return dists


def _icp(src, tgt, max_corr_dist: float, fine_dist: float, init: np.ndarray,
         max_iterations: int, centroid: np.ndarray, voxel_size: float):
    """Coarse-to-fine symmetric ICP; returns the result, whether it converged and, when
    its iterations cycle, the cycle (:func:`_icp_settled`)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    est = reg.TransformationEstimationSymmetric()
    crit = reg.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9,
                                      max_iteration=max_iterations)
    dists = _icp_distances(max_corr_dist, fine_dist)
    t = np.asarray(init, dtype=np.float64)
    res = None
    for d in dists:
        res = reg.registration_symmetric_icp(src, tgt, d, t, est, crit)
        t = np.asarray(res.transformation)
    converged, cycle = _icp_settled(src, tgt, dists[-1], t, centroid, voxel_size)
    return res, converged, cycle


#: :func:`_icp_settled` looks this many iterations beyond ICP's result for a cycle ...
_CYCLE_ITERATIONS = 16
#: ... whose iterates stray from the result by at most this share of the voxel and
#: these degrees
_CYCLE_SPAN_VOXELS = 0.1
_CYCLE_SPAN_DEG = 0.05


def _icp_settled(src, tgt, dist: float, t: np.ndarray, centroid: np.ndarray,
                 voxel_size: float) -> tuple[bool, dict[str, Any] | None]:
    """Whether ICP has converged at ``t``: one more iteration at the finest distance
    moves it by at most 1 % of ``voxel_size`` (or 0.1 um) and 0.005 degrees
    (:func:`_step_small`), or its iterations cycle: within :data:`_CYCLE_ITERATIONS` they
    come back to ``t`` (within that step) without straying farther than
    :data:`_CYCLE_SPAN_VOXELS` of the voxel and :data:`_CYCLE_SPAN_DEG` from it. Then
    ``(True, {"period", "span_mm", "span_deg"})``.

    Why: the correspondences of two sampled surfaces can flip between two sets, and
    ICP then steps back and forth for ever. On the objects benchmark 4 of the 5 pairs
    rejected as not converged in the runs looked at did so, with periods of 2 and 10,
    0.007-0.010 mm and up to 0.014 degrees apart, far within their RMS residuals of
    0.05-0.10 mm; a demo bracket scanned with two sweeps lost its only pair to it and
    kept the robot's poses (``benchmarks/README.md``, stop 66). A pair that keeps
    sliding does not come back and stays not converged.

    A cycle is weaker evidence than a clean convergence: on a thin wall the
    correspondences can flip between its two faces, and such a pair of the objects
    benchmark's thin wall (4 sweeps), 1.5 mm off the other pairs, pulled the pose graph
    and the sweeps off (worst sweep 0.07 -> 0.29 mm). So :func:`_register_pairs` uses a
    cycled pair only for a sweep that no cleanly converged pair joins."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    est = reg.TransformationEstimationSymmetric()
    one = reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=1)
    inv_t = invert_transform(t)
    cur, span_m, span_deg = t, 0.0, 0.0
    for k in range(1, _CYCLE_ITERATIONS + 1):
        cur = np.asarray(reg.registration_symmetric_icp(src, tgt, dist, cur, est,
                                                        one).transformation)
        away = cur @ inv_t
        if _step_small(away, centroid, voxel_size):
            return True, (None if k == 1 else {"period": k, "span_mm": span_m * 1e3,
                                                "span_deg": span_deg})
        mm, deg = _motion(away, centroid)
        if mm * 1e-3 > _CYCLE_SPAN_VOXELS * voxel_size or deg > _CYCLE_SPAN_DEG:
            return False, None
        span_m, span_deg = max(span_m, mm * 1e-3), max(span_deg, deg)
    return False, None


def _fit(src: tuple[np.ndarray, np.ndarray], tgt: tuple[np.ndarray, np.ndarray], tree,
         t: np.ndarray, max_dist: float) -> tuple[float, float]:
    """(fraction of source points with a target point within ``max_dist`` after ``t``,
    RMS point-to-plane distance of those pairs along the target normals, metres)."""
    p = src[0] @ t[:3, :3].T + t[:3, 3]
    d, idx = tree.query(p, k=1, distance_upper_bound=max_dist)
    ok = np.isfinite(d)
    if not np.any(ok):
        return 0.0, float("nan")
    r = np.einsum("ij,ij->i", p[ok] - tgt[0][idx[ok]], tgt[1][idx[ok]])
    return float(np.mean(ok)), float(np.sqrt(np.mean(r**2)))


def _twist(t: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(rotation vector, displacement of ``c``) of a rigid transform: its twist about c."""
    return np.r_[_log_so3(t[:3, :3]), t[:3, :3] @ c + t[:3, 3] - c]


def _from_twist(u: np.ndarray, c: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = _exp_so3(u[:3])
    out[:3, 3] = c + u[3:] - out[:3, :3] @ c
    return out


def _pair_info(src: tuple[np.ndarray, np.ndarray], tgt: tuple[np.ndarray, np.ndarray], tree,
               t: np.ndarray, max_dist: float, c: np.ndarray, prior_sd: np.ndarray,
               voxel_size: float):
    """Whitened point-to-plane normal equations of a pair at ``t`` (twist about ``c``).

    Returns (eigenvalues, eigenvectors, gradient) of ``S J^T J S / sigma^2`` and of
    ``S J^T r / sigma^2`` (``S = diag(prior_sd)``), or None with fewer than 6
    correspondences. The normal of a correspondence is the sum of the two (symmetric
    ICP's); ``sigma`` is the RMS residual, at least a tenth of the voxel, and each
    correspondence's scale adds its plane model's error (:func:`_pair_residuals`).
    """
    p = src[0] @ t[:3, :3].T + t[:3, 3]
    d, idx = tree.query(p, k=1, distance_upper_bound=max_dist)
    ok = np.isfinite(d)
    n_src = src[1] @ t[:3, :3].T
    # the two sides of a thin wall lie within the correspondence distance: a pair of
    # points whose normals disagree by more than 60 degrees is not one surface
    ok[ok] = np.einsum("ij,ij->i", n_src[ok], tgt[1][idx[ok]]) > 0.5
    if np.count_nonzero(ok) < 6:
        return None
    x, y = p[ok], tgt[0][idx[ok]]
    r, n, model = _pair_residuals(x, y, n_src[ok], tgt[1][idx[ok]])
    sigma = max(float(np.sqrt(np.mean(r**2))), 0.1 * voxel_size, 1e-6)
    jac = np.hstack([np.cross(x - c, n), n]) * prior_sd
    s = np.sqrt(sigma**2 + model**2)  # the plane model's own error
    w = _huber(r / s, 2.0) / s**2
    hw = jac.T @ (jac * w[:, None])
    lam, vec = np.linalg.eigh(0.5 * (hw + hw.T))
    return lam, vec, jac.T @ (w * r)


def _opposed_fraction(src: tuple[np.ndarray, np.ndarray], tgt: tuple[np.ndarray, np.ndarray],
                      tree, max_dist: float) -> float:
    """Fraction of ``src``'s points whose nearest ``tgt`` point within ``max_dist`` has an
    opposed normal (more than 120 degrees apart): the other side of a thin wall."""
    if not len(src[0]):
        return 0.0
    d, idx = tree.query(src[0], k=1, distance_upper_bound=max_dist)
    ok = np.isfinite(d)
    if not np.any(ok):
        return 0.0
    dots = np.einsum("ij,ij->i", src[1][ok], tgt[1][idx[ok]])
    return float(np.count_nonzero(dots < -0.5)) / len(src[0])


def _held_icp(src, tgt, tree, max_corr_dist: float, fine_dist: float, c: np.ndarray,
              prior_sd: np.ndarray, ratio: float, voxel_size: float, max_iterations: int
              ) -> tuple[np.ndarray, np.ndarray]:
    """Point-to-plane ICP (symmetric normals) from the robot's relative pose in which
    the directions the overlap does not constrain stay at it (Zhang, Kaess & Singh 2016,
    solution remapping): each Gauss-Newton step is taken in the subspace whose whitened
    information is at least ``ratio``, and the estimate is projected onto it. Coarse to
    fine like :func:`_icp`. Returns the result and its last step."""
    dists = _icp_distances(max_corr_dist, fine_dist)
    u = np.zeros(6)  # whitened twist about c
    t = np.eye(4)
    step = np.eye(4)
    damping, last = 1.0, np.inf
    for d in dists:
        for _ in range(max_iterations):
            got = _pair_info(src, tgt, tree, t, d, c, prior_sd, voxel_size)
            if got is None:
                return t, np.eye(4) * np.nan
            lam, vec, g = got
            keep = vec[:, lam >= ratio]
            if keep.shape[1] == 0:
                return np.eye(4), np.eye(4)
            du = -keep @ ((keep.T @ g) / lam[lam >= ratio])
            # sparse profiles: the correspondences may flip between two sets and the
            # steps cycle; shorten them once they grow (as in refine_sweeps)
            size = float(np.linalg.norm(du))
            if size > last:
                damping = max(damping * 0.5, 1 / 16)
            last = size
            du = du * damping
            u_new = keep @ (keep.T @ (u + du))
            t_new = _from_twist(prior_sd * u_new, c)
            step = t_new @ invert_transform(t)
            u, t = u_new, t_new
            if np.linalg.norm(prior_sd[3:] * du[3:]) < 1e-7 and np.linalg.norm(
                    prior_sd[:3] * du[:3]) < 1e-6:
                break
    return t, step


def _step_small(step: np.ndarray, centroid: np.ndarray, voxel_size: float) -> bool:
    mm, deg = _motion(step, centroid)
    return mm * 1e-3 <= max(0.01 * voxel_size, 1e-7) and deg <= 0.005


def _max_spanning_tree(n: int, edges: list[tuple[int, int, float]], root: int
                       ) -> tuple[list[int], list[int], set[tuple[int, int]]]:
    """Prim's algorithm from ``root``: (visit order, parent per node or -1, tree edges)."""
    adj: dict[int, list[tuple[float, int]]] = {k: [] for k in range(n)}
    for i, j, w in edges:
        adj[i].append((w, j))
        adj[j].append((w, i))
    order = [root]
    parent = [-1] * n
    seen = {root}
    tree: set[tuple[int, int]] = set()
    while True:
        best = None
        for u in order:
            for w, v in adj[u]:
                if v not in seen and (best is None or w > best[0] or
                                      (w == best[0] and (v, u) < (best[1], best[2]))):
                    best = (w, v, u)
        if best is None:
            break
        _, v, u = best
        seen.add(v)
        order.append(v)
        parent[v] = u
        tree.add((min(u, v), max(u, v)))
    return order, parent, tree


def _mean_transform(ts: np.ndarray) -> np.ndarray:
    """Chordal mean of rigid transforms (mean rotation projected onto SO(3), mean t)."""
    r = ts[:, :3, :3].mean(axis=0)
    u, _, vt = np.linalg.svd(r)
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    out = np.eye(4)
    out[:3, :3] = u @ d @ vt
    out[:3, 3] = ts[:, :3, 3].mean(axis=0)
    return out


# --------------------------------------------------------------------------- main


def _check_align_options(o: AlignOptions, gauge: str, max_points: int) -> None:
    if o.method not in ("pose_graph", "sequential"):
        raise ValueError(f"method must be 'pose_graph' or 'sequential', got {o.method!r}")
    if gauge not in ("reference", "mean"):
        raise ValueError(f"gauge must be 'reference' or 'mean', got {gauge!r}")
    for name, val in (("max_corr_dist_m", o.max_corr_dist_m),
                      ("max_correction_mm", o.max_correction_mm),
                      ("max_correction_deg", o.max_correction_deg)):
        if not val > 0:
            raise ValueError(f"{name} must be > 0, got {val}")
    if o.voxel_size_m < 0:
        raise ValueError(f"voxel_size_m must be >= 0, got {o.voxel_size_m}")
    if not 0 < o.min_overlap <= 1:
        raise ValueError(f"min_overlap must be in (0, 1], got {o.min_overlap}")
    if o.max_iterations < 1 or max_points < _MIN_POINTS:
        raise ValueError("max_iterations must be >= 1 and max_points >= 10, got "
                         f"{o.max_iterations} and {max_points}")


def align_sweeps(
    points: list[np.ndarray],
    normals: list[np.ndarray],
    *,
    options: AlignOptions = AlignOptions(),
    gauge: Literal["reference", "mean"] = "reference",
    max_points: int = 100_000,
    origins: list[np.ndarray] | None = None,
    profiles: list[np.ndarray] | None = None,
    silhouettes: SilhouetteViews | None = None,
) -> AlignmentResult:
    """Align laser sweeps to each other, starting from the robot's poses.

    Parameters
    ----------
    points : list of (N_s, 3) float64, metres
        Each sweep's points in ``base``, as placed by the robot's poses.
    normals : list of (N_s, 3) float64
        Unit normals of those points, oriented the same way in every sweep (toward the
        sensor, i.e. out of the object): symmetric ICP adds the two normals of a pair.
    options : AlignOptions
        The ``alignment`` section's parameters and the seed (:class:`AlignOptions`):
        the thinning voxel, ICP's distances and iterations, the bounds, the minimum
        overlap, the method, and whether (and how) to refine.
    gauge : {"reference", "mean"}
        What stays fixed: the reference sweep (most overlap), or the mean correction.
    max_points : int
        Cap on the points per sweep used for registration (random subsample with
        ``options.seed``).
    origins : list of (N_s, 3) float64, metres, optional
        Sensor position at each point's frame (needed by the refinement's motion model;
        without it each sweep turns about its centroid).
    profiles : list of (N_s,) int, optional
        Laser frame of each point (the silhouette term groups points by it); a frame's
        points in order along its stripe, as the triangulation writes them (else the
        term takes noisy points as measured: :func:`_rim_points`).
    silhouettes : SilhouetteViews, optional
        Views for the absolute reference (refinement only).

    Returns
    -------
    AlignmentResult

    Notes
    -----
    The method, the gauge and the guards are described in the module docstring. With
    ``options.refine`` the pose graph's result is refined jointly
    (:func:`refine_sweeps`) with the sensor motion model, the silhouettes as absolute
    reference and the robot's expected error as prior; the bounds are then checked on
    the refined corrections.

    References
    ----------
    Chen & Medioni (1992) point-to-plane ICP; Choi, Zhou & Koltun (2015) pose graph.
    """
    import open3d as o3d

    pts_in, nrm_in = _check_inputs(points, normals)
    _check_align_options(options, gauge, max_points)
    n_sweeps = len(pts_in)
    corrections = np.tile(np.eye(4), (n_sweeps, 1, 1))
    if n_sweeps == 0:
        return AlignmentResult(corrections=corrections.reshape(0, 4, 4),
                               method=options.method, gauge=gauge)

    if origins is not None and (len(origins) != len(pts_in) or any(
            np.shape(o) != p.shape for o, p in zip(origins, pts_in, strict=True))):
        raise ValueError("origins must hold one (N_s, 3) array per sweep, like points")
    # Open3D's ICP and pose graph reduce over points in parallel (TBB): on more than one
    # thread their results vary by ~1e-16 from run to run, which the simplification
    # downstream turns into a different mesh; on one thread they are bit-identical
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            result = _align(pts_in, nrm_in, corrections, options, gauge, max_points)
    finally:
        o3d.utility.set_max_threads(threads)
    if options.refine and (n_sweeps > 1 or silhouettes is not None):
        _refine_guarded(result, pts_in, nrm_in, origins, profiles, silhouettes, options)
    return result


def _rescue_with_views(result: AlignmentResult, n_s: int, active: list[int],
                       pairs: list[tuple[int, int]], min_overlap: float
                       ) -> tuple[list[int], list[tuple[int, int]], dict[int, str]]:
    """With an absolute reference a sweep does not need an accepted pair: one whose
    pairs ICP could not settle (sparse profiles cycle between correspondence sets) is
    refined against the views, and those pairs take part with the refinement's robust
    weights and held directions; only grossly inconsistent pairs stay out. So is one that
    the pose graph moved beyond the bounds: refined from the robot's pose with the others,
    its weak directions held there, it is judged by the refinement's own bounds (ICP had
    turned the top sweep of a near-symmetric bottle 5.1 degrees about its axis, issue
    11's settings: kept at the robot's 0.46 mm; refined, 0.03 mm). Returns the active
    sweeps, the pairs and the rescued sweeps' pose-graph reasons."""
    rescued = [s for s in range(n_s) if result.per_sweep[s]["flagged"]
               and result.per_sweep[s]["n_used"] >= _MIN_POINTS
               and result.per_sweep[s]["reason"].startswith(("no accepted pair",
                                                              "not connected",
                                                              "no other sweep",
                                                              "correction "))]
    saved = {s: result.per_sweep[s]["reason"] for s in rescued}
    if rescued:
        log.info("refinement: sweeps %s were flagged by the pose graph (%s); refined "
                 "against the silhouettes", rescued, "; ".join(saved[s] for s in rescued))
        for s in rescued:
            result.per_sweep[s].update(flagged=False, reason="")
        active = sorted(active + rescued)
        pairs = [(p["i"], p["j"]) for p in result.pairs
                 if p["accepted"] or (p["overlap"] >= min_overlap and not str(
                     p["reason"]).startswith("relative correction"))]
    return active, pairs, saved


#: the views hold the refinement's gauge with at least this many contour residuals
_MIN_RIM_GAUGE = 30


def _keep_all(result: AlignmentResult, n_s: int, why: str | None = None) -> None:
    """Every sweep flagged (before the refinement, or by its guards): all stay at the
    robot's poses."""
    result.rotations = np.tile(np.eye(3), (n_s, 1, 1))
    result.translations = np.zeros((n_s, 3))
    result.corrections = np.tile(np.eye(4), (n_s, 1, 1))
    result.refinement = {"converged": False, "iterations": 0, "gauge": "none",
                         "skipped": why or ("every sweep was flagged before the refinement "
                                            "(no accepted pair): all kept at the robot's "
                                            "poses")}
    result.pairs = [_jsonable(p) for p in result.pairs]
    result.per_sweep = [_jsonable(p) for p in result.per_sweep]


def _unconfirmed_by_views(ref: RefinementResult, active: list[int],
                          pairs: list[tuple[int, int]], o: AlignOptions) -> tuple[int, str]:
    """The active sweep refined against the views alone (no pair with another active
    sweep: a one-sweep scan, or the last one left) whose contour residuals do not
    confirm its pose (RMS above ``o.views_only_max_rim_rms_px``, or none), the worst
    first; (-1, "") for none. Such a sweep has nothing else to check it: masks that
    miss the object's outline move it (random scene 149 of stop 34: a green box on a
    green-striped table, 34 contour residuals of 1.75 px RMS, the refinement moved the
    sweep 0.5 mm further from its true pose; the seven one-sweep scenes with views that
    came closer had 0.24-0.87 px; benchmarks/README.md, stop 36)."""
    paired = {s for p in pairs if p[0] in active and p[1] in active for s in p}
    worst, worst_rms = -1, o.views_only_max_rim_rms_px
    for s in active:
        if s in paired:
            continue
        rms = ref.per_sweep[s].get("rim_rms_px")
        rms = np.inf if rms is None else float(rms)
        if rms > worst_rms:
            worst, worst_rms = s, rms
    if worst < 0:
        return -1, ""
    what = ("no contour residual: nothing of it lies on the views' outlines"
            if not np.isfinite(worst_rms) else
            f"contour residuals of {worst_rms:.2f} px RMS (more than "
            f"{o.views_only_max_rim_rms_px} px)")
    return worst, (f"refined against the views alone, with {what}: the views do not "
                   f"confirm the pose")


def _worst_refined(pts, origins, ref: RefinementResult, active: list[int],
                   o: AlignOptions) -> tuple[int, dict[int, tuple[float, float, float]]]:
    """The active sweep whose refined correction exceeds the bounds most (-1: none), and
    each active sweep's (centroid displacement mm, largest displacement mm, degrees)."""
    worst, worst_ratio, motion = -1, 1.0, {}
    for s in active:
        moved, _, _ = apply_correction(pts[s], origins[s], ref.rotations[s],
                                       ref.translations[s])
        disp = np.linalg.norm(moved - pts[s], axis=1) if len(pts[s]) else np.zeros(1)
        cen = float(np.linalg.norm(moved.mean(axis=0) - pts[s].mean(axis=0))) * 1e3 if len(
            pts[s]) else 0.0
        deg = float(rotation_angle_deg(ref.rotations[s]))
        motion[s] = (cen, float(disp.max()) * 1e3, deg)
        ratio = max(cen / o.max_correction_mm, deg / o.max_correction_deg)
        if ratio > worst_ratio:
            worst, worst_ratio = s, ratio
    return worst, motion


def _refine_guarded(result: AlignmentResult, pts, nrms, origins, profiles, silhouettes,
                    o: AlignOptions) -> None:
    """Run :func:`refine_sweeps` on the pose graph's result and apply the guards: a sweep
    whose refined correction is out of bounds is flagged, kept at its robot pose and the
    others refined again without it."""
    n_s = len(pts)
    if origins is None:  # no sensor positions: each sweep turns about its centroid
        origins = [np.broadcast_to(p.mean(axis=0) if len(p) else np.zeros(3), p.shape)
                   for p in pts]
    origins = [np.asarray(x, dtype=np.float64) for x in origins]
    active = [s for s in range(n_s) if not result.per_sweep[s]["flagged"]]
    pairs = [(p["i"], p["j"]) for p in result.pairs if p["accepted"]]
    saved: dict[int, str] = {}
    pg = (list(active), list(pairs))
    if silhouettes is not None:
        # without enough contour points this falls back below
        active, pairs, saved = _rescue_with_views(result, n_s, active, pairs, o.min_overlap)
    if not active:  # every sweep flagged by the pose graph: nothing to refine
        _keep_all(result, n_s)
        return
    while True:
        kw = dict(profiles=profiles, initial=result.corrections, active=active, options=o)
        ref, starts = None, None
        if silhouettes is not None:
            ref, starts = _refine_two_starts(pts, nrms, origins, pairs, silhouettes, kw, o)
            if ref.gauge != "silhouettes":  # too few contour points: no absolute reference
                n_rim = int(ref.silhouettes.get("n_rim") or 0)
                ref = None
                if saved:  # the rescued sweeps go back to the pose graph's verdict
                    for s_, why in saved.items():  # (and the views' on them, if any)
                        then = result.per_sweep[s_].get("reason") or ""
                        result.per_sweep[s_].update(flagged=True, reason=why + (
                            f"; against the views: {then}" if then else ""))
                    active = [s_ for s_ in pg[0] if s_ in active]
                    pairs, saved = pg[1], {}
                    if not active:
                        # not "flagged before the refinement": it ran, and what the
                        # views confirmed was too little to hold the gauge alone
                        why = (f"refined against the views, the sweeps left had "
                               f"{n_rim} silhouette contour residuals (fewer than "
                               f"{_MIN_RIM_GAUGE}: no absolute reference) and no "
                               f"accepted pair: every sweep kept at the robot's pose")
                        log.warning("refinement: %s", why)
                        _keep_all(result, n_s, why)
                        return
                    kw["active"] = active
                log.warning("refinement: too few silhouette residuals; the sweeps' priors "
                            "hold the gauge")
        if ref is None:
            # no absolute reference: every sweep's prior (the robot's expected error)
            # holds the gauge, which averages the sweeps' errors; fixing one sweep would
            # give every sweep that sweep's error (benchmarks/README.md)
            ref = refine_sweeps(pts, nrms, origins, pairs, fixed=[], **kw)
        worst, motion = _worst_refined(pts, origins, ref, active, o)
        if worst >= 0:
            cen, _, deg = motion[worst]
            why = (f"refined correction {cen:.3f} mm / {deg:.3f} deg exceeds the bounds "
                   f"{o.max_correction_mm} mm / {o.max_correction_deg} deg")
        elif ref.gauge == "silhouettes":
            worst, why = _unconfirmed_by_views(ref, active, pairs, o)
        if worst < 0:
            break
        result.per_sweep[worst].update(flagged=True, converged=False, reason=why)
        active = [s for s in active if s != worst]
        if not active:
            _keep_all(result, n_s, f"sweep {worst}: {why}: kept at the robot's pose")
            return
    rot, trans, corr = _take_refined(result, ref, origins, active, motion)
    _final_pair_stats(result, pts, nrms, origins, rot, trans, o)
    result.rotations, result.translations, result.corrections = rot, trans, corr
    result.gauge = ref.gauge
    result.refinement = {"converged": bool(ref.converged), "iterations": int(ref.iterations),
                         "gauge": ref.gauge, "silhouettes": ref.silhouettes,
                         "pair_sigma_mm": ref.pair_sigma_mm,
                         "model": "sensor turned about its position at each frame, and shifted",
                         "prior_mm": o.prior_mm, "prior_deg": o.prior_deg,
                         "rim_weight": o.rim_weight, "normal_k": o.pair_normals_k,
                         "normal_max_spacing": o.pair_normals_max_spacing_m,
                         "degenerate_ratio": o.degenerate_ratio}
    if starts is not None:
        result.refinement["starts"] = starts
    result.pairs = [_jsonable(p) for p in result.pairs]
    result.per_sweep = [_jsonable(p) for p in result.per_sweep]


def _refine_two_starts(pts, nrms, origins, pairs, silhouettes, kw: dict, o: AlignOptions
                       ) -> tuple[RefinementResult, dict[str, Any] | None]:
    """:func:`refine_sweeps` against the views from the pose graph's corrections and,
    with ``o.robot_start``, from the robot's poses too; the robot's start is taken when
    its silhouette residuals' RMS is lower by more than ``o.robot_start_margin``.

    Why: the refinement ends in a local minimum near where it starts. A pose graph that
    rests on a pair of little overlap can start it 0.3-0.5 mm off, and it then settles
    in a worse minimum (the blue cell of ``benchmarks/front_end.py`` with
    ``stripes.follow``: silhouette RMS 0.489 px against 0.451 px from the robot's poses,
    the worst sweeps 0.56 against 0.44-0.50 px; the delivered points' p95 0.78 against
    0.17 mm). Where both starts end in the same minimum the RMS differs by at most 2.6 %
    (the twelve runs of ``benchmarks/objects.py``), the silhouette term's own bias on
    flat faces being larger than that, so the pose graph's start is kept unless the
    other is clearly better. Both runs share their set-up (:class:`_RefineProblem`) and
    run side by side. Returns the result taken and what was compared (None: one start
    only)."""
    act = kw["active"]
    if not o.robot_start or np.allclose(kw["initial"][act], np.eye(4), rtol=0.0, atol=1e-12):
        return refine_sweeps(pts, nrms, origins, pairs, silhouettes=silhouettes, **kw), None
    # the two runs side by side, each on one of the job's threads (the pair terms are
    # single-threaded numpy and KD-tree queries: 1.5x the time of one run, not 2x); the
    # result does not depend on the thread count
    pr = _refine_problem(pts, nrms, origins, pairs, silhouettes=silhouettes,
                         **{k: v for k, v in kw.items() if k != "initial"}, fixed=None,
                         max_points=_REFINE_MAX_POINTS)
    one = dataclasses.replace(o, threads=1) if o.threads > 1 else o
    ref, alt = _map_threads(min(o.threads, 2), lambda init: _refine_from(pr, init, one),
                            [kw["initial"], None])
    if ref.gauge != "silhouettes":
        return ref, None
    a, b = ref.silhouettes["rms_px"], alt.silhouettes["rms_px"]
    take = (alt.gauge == "silhouettes" and alt.converged and b is not None
            and (not ref.converged or a is None or _robot_start_better(
                a, b, [e["rim_rms_px"] for e in ref.per_sweep],
                [e["rim_rms_px"] for e in alt.per_sweep], o.robot_start_margin)))
    starts = {"pose_graph_rim_rms_px": a, "robot_rim_rms_px": b,
              "pose_graph_converged": bool(ref.converged), "robot_converged": bool(alt.converged),
              "pose_graph_sweep_rim_rms_px": [e["rim_rms_px"] for e in ref.per_sweep],
              "robot_sweep_rim_rms_px": [e["rim_rms_px"] for e in alt.per_sweep],
              "taken": "robot" if take else "pose_graph", "margin": o.robot_start_margin}
    if take:
        log.info("refinement: the start from the robot's poses ends with silhouette "
                 "residuals of %.3f px RMS, the pose graph's %.3f px: the robot's taken", b, a)
    return (alt if take else ref), starts


def _robot_start_better(a: float, b: float, per_a: list, per_b: list, margin: float) -> bool:
    """Whether the refinement from the robot's poses (silhouette residuals' RMS ``b``
    overall, ``per_b`` per sweep, None for a sweep without) ended better than the one from
    the pose graph's (``a``, ``per_a``): lower overall by more than ``margin`` (a
    fraction), or lower overall and lower by more than the margin on one sweep while
    worse by more than it on none.

    Why per sweep: a pose graph that rests on one pair of little overlap can start one
    sweep of several far off, and the overall RMS drowns that sweep in the others'. The
    blue cell of ``benchmarks/front_end.py`` (exact poses, stop 59): sweep 0 ended 1.56 mm
    off from the pose graph's start, its RMS 0.484 px against 0.445 px from the robot's,
    the other sweeps within 0.5 % or better from the robot's too; overall 0.4252 against
    0.4380 px, 2.9 %, short of the 3 % margin."""
    if b < (1.0 - margin) * a:
        return True
    per = [(x, y) for x, y in zip(per_a, per_b, strict=True) if x is not None and y is not None]
    return (b < a and len(per) > 1 and all(y <= (1.0 + margin) * x for x, y in per)
            and any(y < (1.0 - margin) * x for x, y in per))


def _take_refined(result: AlignmentResult, ref: RefinementResult, origins, active: list[int],
                  motion: dict[int, tuple[float, float, float]]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The refined corrections of the sweeps that stayed active (rotations, translations
    and the rigid correction at each sweep's mean sensor position), each sweep's report
    updated; every sweep at its robot pose, flagged, when the refinement did not
    converge."""
    n_s = len(origins)
    rot = np.tile(np.eye(3), (n_s, 1, 1))
    trans = np.zeros((n_s, 3))
    corr = np.tile(np.eye(4), (n_s, 1, 1))
    for s in range(n_s):
        # one sweep left: only the views can have checked it (the guards of
        # _refine_guarded); without them nothing did
        if s in active and (len(active) > 1 or ref.gauge == "silhouettes"):
            rot[s], trans[s] = ref.rotations[s], ref.translations[s]
            o_ref = origins[s].mean(axis=0) if len(origins[s]) else np.zeros(3)
            corr[s] = correction_at(o_ref, rot[s], trans[s])
            cen, mx, deg = motion[s]
            result.per_sweep[s].update(
                translation_mm=cen, max_displacement_mm=mx, rotation_deg=deg,
                sensor_shift_mm=float(np.linalg.norm(trans[s]) * 1e3),
                converged=bool(ref.converged), flagged=False, reason="")
        elif not result.per_sweep[s]["flagged"]:
            result.per_sweep[s].update(flagged=True, converged=False,
                                       reason="no other sweep left to align with")
        result.per_sweep[s].update(
            n_rim=ref.per_sweep[s]["n_rim"], rim_rms_px=ref.per_sweep[s]["rim_rms_px"])
        for key in ("constrained", "unconstrained", "information", "profile_noise_mm",
                    "profile_noise_px", "rim_fit_share"):
            if key in ref.per_sweep[s]:
                result.per_sweep[s][key] = ref.per_sweep[s][key]
        if not ref.converged and s in active:
            result.per_sweep[s]["reason"] = (
                f"refinement did not converge in {ref.iterations} iterations")
    if not ref.converged:
        # not converged: every sweep stays at its robot pose, flagged
        log.warning("refinement did not converge in %d iterations: sweeps kept at the "
                    "robot's poses", ref.iterations)
        rot[:] = np.eye(3)
        trans[:] = 0.0
        corr[:] = np.eye(4)
        for s in range(n_s):
            result.per_sweep[s].update(flagged=True, translation_mm=0.0, rotation_deg=0.0,
                                       max_displacement_mm=0.0)
    return rot, trans, corr


def _final_pair_stats(result: AlignmentResult, pts, nrms, origins, rot: np.ndarray,
                      trans: np.ndarray, o: AlignOptions) -> None:
    """Each pair's fitness and RMS distance at the final poses (``fitness_final``,
    ``rmse_final_mm``)."""
    n_s = len(pts)
    moved = [apply_correction(pts[s], origins[s], rot[s], trans[s], nrms[s])
             for s in range(n_s)]
    fine = max(o.voxel_size_m, o.max_corr_dist_m / 4)
    rng = np.random.default_rng(o.seed)
    red = [_reduce(m[0], m[2], o.voxel_size_m, 100_000, rng) for m in moved]
    trees = {}
    for p in result.pairs:
        i, j = p["i"], p["j"]
        if j not in trees:
            trees[j] = cKDTree(red[j][0]) if len(red[j][0]) else None
        if trees[j] is None or not len(red[i][0]):
            continue
        fit = _fit(red[i], red[j], trees[j], np.eye(4), o.max_corr_dist_m)[0]
        rmse = _fit(red[i], red[j], trees[j], np.eye(4), fine)[1]
        p.update(fitness_final=fit, rmse_final_mm=None if not np.isfinite(rmse) else rmse * 1e3)


def _reduce_sweeps(pts_in, nrm_in, o: AlignOptions, max_points: int, rng, centre):
    """Step 1: each sweep thinned and centred (arrays and Open3D clouds), its centroid,
    its report entry, and whether it has enough points to register."""
    red = [_reduce(p - centre, n, o.voxel_size_m, max_points, rng) for p, n in zip(
        pts_in, nrm_in, strict=True)]
    clouds = [_to_o3d(p, n) for p, n in red]
    cents = [p.mean(axis=0) if len(p) else np.zeros(3) for p, _ in red]
    n_sweeps = len(pts_in)
    per_sweep: list[dict[str, Any]] = [
        dict(sweep=s, n_points=len(pts_in[s]), n_used=len(red[s][0]), translation_mm=0.0,
             max_displacement_mm=0.0, rotation_deg=0.0, converged=False, flagged=False,
             reason="") for s in range(n_sweeps)]
    usable = [len(red[s][0]) >= _MIN_POINTS for s in range(n_sweeps)]
    for s in range(n_sweeps):
        if not usable[s]:
            per_sweep[s].update(flagged=True, reason=(
                f"too few points to register ({len(red[s][0])} after reduction, "
                f"need {_MIN_POINTS})"))
    return red, clouds, cents, per_sweep, usable


def _register_pair(i: int, j: int, red, clouds, trees, cents, o: AlignOptions,
                   prior_sd: np.ndarray, fine_dist: float, overlap: float,
                   pair: dict[str, Any]) -> dict[str, Any] | None:
    """Step 2 for one overlapping pair: ICP (or :func:`_held_icp`) from the robot's
    relative pose, the result judged; the pose-graph edge when accepted, else None
    (``pair`` updated either way)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    eye = np.eye(4)
    d_fine = _icp_distances(o.max_corr_dist_m, fine_dist)[-1]
    # the two sides of a thin wall within the correspondence distance (normals opposed):
    # Open3D's ICP pairs them and pulls one sweep onto the other's face; _held_icp
    # leaves such correspondences out. Such a pair goes to _held_icp straight away (it
    # starts from the robot's pose, not from ICP's result: ICP would be thrown away)
    thin_wall = _opposed_fraction(red[i], red[j], trees[j], o.max_corr_dist_m) > 0.02
    n_held = None
    if not thin_wall:
        res, converged, cycle = _icp(clouds[i], clouds[j], o.max_corr_dist_m, fine_dist,
                                     eye, o.max_iterations, cents[i], o.voxel_size_m)
        t = np.asarray(res.transformation).copy()  # maps sweep i onto sweep j
        # directions the pair's overlap does not constrain (a flat face: the slide in its
        # plane and the turn about its normal; a sphere: every turn about its centre),
        # from its whitened point-to-plane information at ICP's result (none left there:
        # it slid off the overlap, as on a sphere): ICP slides along them, so such a pair
        # is registered by :func:`_held_icp`, which holds them there. (Open3D's
        # get_information_matrix_from_point_clouds is point-to-point, of full rank on a
        # plane: it hides the slide.)
        got = _pair_info(red[i], red[j], trees[j], t, d_fine, cents[i], prior_sd,
                         o.voxel_size_m)
        n_held = int(np.count_nonzero(got[0] < o.pair_degenerate_ratio)) if got else 6
    if thin_wall or n_held:
        t, step = _held_icp(red[i], red[j], trees[j], o.max_corr_dist_m, fine_dist,
                            cents[i], prior_sd, o.pair_degenerate_ratio, o.voxel_size_m,
                            o.max_iterations)
        converged, cycle = _step_small(step, cents[i], o.voxel_size_m), None
    fin = _pair_info(red[i], red[j], trees[j], t, d_fine, cents[i], prior_sd,
                     o.voxel_size_m)
    if n_held is None:  # the thin wall's pair: the directions held at _held_icp's result
        n_held = int(np.count_nonzero(fin[0] < o.pair_degenerate_ratio)) if fin else 6
    held = {"held_directions": n_held,
            "min_information": float(fin[0][0]) if fin else None,
            "registered_by": ("held ICP: both sides of a thin wall in reach" if thin_wall
                              else "held ICP: directions the overlap does not fix"
                              if n_held else "symmetric ICP")}
    info = np.asarray(reg.get_information_matrix_from_point_clouds(
        clouds[i], clouds[j], d_fine, t)).copy()
    fit = _fit(red[i], red[j], trees[j], t, o.max_corr_dist_m)[0]
    rmse = _fit(red[i], red[j], trees[j], t, d_fine)[1]
    pair.update(fitness=fit, rmse_mm=rmse * 1e3,
                rmse_before_mm=_fit(red[i], red[j], trees[j], eye, d_fine)[1] * 1e3,
                converged=converged, **held)
    if cycle is not None:  # converged to a cycle of ICP's iterations (_icp_settled)
        pair["icp_cycle"] = cycle
    rel_mm, rel_deg = _motion(t, cents[i])
    if not pair["converged"]:
        pair["reason"] = "ICP did not converge"
    elif fit < o.min_overlap:
        pair["reason"] = f"fitness {fit:.3f} < min_overlap {o.min_overlap}"
    elif rel_mm > 2 * o.max_correction_mm or rel_deg > 2 * o.max_correction_deg:
        pair["reason"] = (f"relative correction {rel_mm:.3f} mm / {rel_deg:.3f} deg "
                          "exceeds twice the per-sweep bounds")
    elif cycle is not None:  # weaker evidence: used only where nothing else joins a sweep
        pair["reason"] = (f"ICP cycled (period {cycle['period']}, {cycle['span_mm']:.4f} mm / "
                          f"{cycle['span_deg']:.4f} deg): used only for a sweep that no "
                          "other pair joins")
        return dict(T=t, info=info, weight=overlap, pair=pair)
    else:
        pair["accepted"] = True
        return dict(T=t, info=info, weight=overlap, pair=pair)
    return None


def _register_pairs(red, clouds, cents, usable, o: AlignOptions, prior_sd: np.ndarray,
                    fine_dist: float):
    """Step 2: the overlap of every pair of usable sweeps at the robot's poses, and the
    pairwise registration of those that overlap enough: (pairs, accepted edges)."""
    n_sweeps = len(red)
    lo = [p.min(axis=0) - o.max_corr_dist_m if len(p) else None for p, _ in red]
    hi = [p.max(axis=0) + o.max_corr_dist_m if len(p) else None for p, _ in red]
    trees = [cKDTree(p) for p, _ in red]
    pairs: list[dict[str, Any]] = []
    edges: dict[tuple[int, int], dict[str, Any]] = {}
    todo: list[tuple[int, int, float, dict[str, Any]]] = []
    eye = np.eye(4)
    for i in range(n_sweeps):
        for j in range(i + 1, n_sweeps):
            if not (usable[i] and usable[j]):
                continue
            if np.any(lo[i] > hi[j]) or np.any(lo[j] > hi[i]):
                continue
            f_ij = _fit(red[i], red[j], trees[j], eye, o.max_corr_dist_m)[0]
            f_ji = _fit(red[j], red[i], trees[i], eye, o.max_corr_dist_m)[0]
            overlap = float(max(f_ij, f_ji))
            if overlap <= 0.0:
                continue
            pair: dict[str, Any] = dict(i=i, j=j, overlap=overlap, fitness=float("nan"),
                                        rmse_mm=float("nan"), rmse_before_mm=float("nan"),
                                        converged=False, accepted=False,
                                        reason="", used=False, residual_mm=float("nan"),
                                        residual_deg=float("nan"))
            pairs.append(pair)
            if overlap < o.min_overlap:
                pair["reason"] = f"overlap {overlap:.3f} < min_overlap {o.min_overlap}"
                continue
            todo.append((i, j, overlap, pair))
    # the pairs are independent: registered in parallel, gathered in their order
    got = _map_threads(o.threads, lambda a: _register_pair(
        a[0], a[1], red, clouds, trees, cents, o, prior_sd, fine_dist, a[2], a[3]), todo)
    cycled = {}
    for (i, j, _, _), edge in zip(todo, got, strict=True):
        if edge is not None:
            (cycled if "icp_cycle" in edge["pair"] else edges)[(i, j)] = edge
    # a pair whose ICP converged to a cycle (_icp_settled) joins a sweep that no other
    # pair joins; elsewhere the cleaner pairs decide (why: _icp_settled)
    joined = {s for k in edges for s in k}
    for (i, j), edge in cycled.items():
        if i not in joined or j not in joined:
            edge["pair"].update(accepted=True, reason="")
            edges[(i, j)] = edge
    return pairs, edges


def _map_threads(threads: int, fn, items: list) -> list:
    """``[fn(x) for x in items]``, on ``threads`` worker threads when more than one (the
    results in the items' order). For tasks that spend their time in Open3D, SciPy and
    NumPy calls, which release the GIL."""
    if int(threads) <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=min(int(threads), len(items))) as pool:
        return list(pool.map(fn, items))


def _choose_reference(n_sweeps: int, usable, edges, pairs, per_sweep
                      ) -> tuple[int, set[int], np.ndarray]:
    """Step 3: the reference (largest summed accepted overlap, lowest index on ties),
    the active sweeps (those with an accepted pair; the others flagged with the reason)
    and each sweep's score."""
    score = np.zeros(n_sweeps)
    for (i, j), e in edges.items():
        score[i] += e["weight"]
        score[j] += e["weight"]
    cand = [s for s in range(n_sweeps) if usable[s]]
    reference = int(max(cand, key=lambda s: (score[s], -s))) if cand else 0
    active = {s for s in cand}
    for s in cand:
        if not any(s in k for k in edges) and n_sweeps > 1:
            active.discard(s)
            near = [p for p in pairs if s in (p["i"], p["j"])]
            why = ("no overlapping sweep within max_corr_dist" if not near else
                   "no accepted pair: " + "; ".join(
                       f"with {p['j'] if p['i'] == s else p['i']}: {p['reason']}"
                       for p in near))
            per_sweep[s].update(flagged=True, reason=why)
    if reference not in active and cand:
        active.add(reference)
    return reference, active, score


def _solve_guarded(n_sweeps: int, edges, reference: int, active: set[int], score,
                   clouds, red, cents, per_sweep, o: AlignOptions, gauge: str,
                   fine_dist: float):
    """Step 4: solve (pose graph or sequential), refuse the out-of-bounds sweeps one at a
    time (worst first), solve again: (solution per sweep, edges used, reference)."""
    sol: dict[int, np.ndarray] = {}
    used: set[tuple[int, int]] = set()
    for _ in range(n_sweeps + 1):
        act_edges = [(i, j, e["weight"]) for (i, j), e in edges.items()
                     if i in active and j in active]
        order, parent, tree = _max_spanning_tree(n_sweeps, act_edges, reference)
        connected = set(order)
        for s in sorted(active - connected):
            active.discard(s)
            per_sweep[s].update(flagged=True, reason=(
                f"not connected to the reference sweep {reference} through accepted pairs"))
        if o.method == "pose_graph":
            sol, used = _solve_pose_graph(order, edges, tree, reference, o.max_corr_dist_m)
        else:
            sol, used = _solve_sequential(order, parent, edges, clouds, red,
                                          o.max_corr_dist_m, fine_dist, o.max_iterations,
                                          o.voxel_size_m, per_sweep)
            active &= set(sol)
        if gauge == "mean" and len(sol) > 1:
            m = _mean_transform(np.stack(list(sol.values())))
            m_inv = invert_transform(m)
            sol = {s: m_inv @ t for s, t in sol.items()}
        worst, worst_ratio = -1, 1.0
        for s in sol:
            mm, deg = _motion(sol[s], cents[s])
            ratio = max(mm / o.max_correction_mm, deg / o.max_correction_deg)
            if ratio > worst_ratio and (s != reference or gauge == "mean"):
                worst, worst_ratio = s, ratio
        if worst < 0:
            break
        mm, deg = _motion(sol[worst], cents[worst])
        per_sweep[worst].update(flagged=True, reason=(
            f"correction {mm:.3f} mm / {deg:.3f} deg exceeds the bounds "
            f"{o.max_correction_mm} mm / {o.max_correction_deg} deg"))
        active.discard(worst)
        sol = {}
        if not active:
            break
        if worst == reference:
            reference = int(max(active, key=lambda s: (score[s], -s)))
    return sol, used, reference


def _align(pts_in, nrm_in, corrections, o: AlignOptions, gauge: str, max_points: int
           ) -> AlignmentResult:
    """The pairwise registrations and the pose graph (steps 1-5 of the module
    docstring), with the bounds' guards."""
    # the relative pose of two sweeps: the difference of two robot errors
    prior_sd = np.sqrt(2.0) * np.r_[np.full(3, np.radians(o.prior_deg)),
                                    np.full(3, o.prior_mm * 1e-3)]
    rng = np.random.default_rng(o.seed)
    n_sweeps = len(pts_in)
    fine_dist = max(o.voxel_size_m, o.max_corr_dist_m / 4)
    nonempty = [p for p in pts_in if len(p)]
    centre = np.concatenate(nonempty).mean(axis=0) if nonempty else np.zeros(3)
    red, clouds, cents, per_sweep, usable = _reduce_sweeps(pts_in, nrm_in, o, max_points,
                                                           rng, centre)
    pairs, edges = _register_pairs(red, clouds, cents, usable, o, prior_sd, fine_dist)
    reference, active, score = _choose_reference(n_sweeps, usable, edges, pairs, per_sweep)
    sol, used, reference = _solve_guarded(n_sweeps, edges, reference, active, score, clouds,
                                          red, cents, per_sweep, o, gauge, fine_dist)
    # --- 5. collect
    for s, t in sol.items():
        if per_sweep[s]["flagged"]:
            continue
        corrections[s] = _conj(t, centre)
        mm, deg = _motion(t, cents[s])
        if len(pts_in[s]):
            moved = pts_in[s] @ corrections[s][:3, :3].T + corrections[s][:3, 3]
            max_disp = float(np.linalg.norm(moved - pts_in[s], axis=1).max() * 1e3)
        else:
            max_disp = 0.0
        conv = s == reference or any(
            e["pair"]["converged"] and s in k and k in used for k, e in edges.items())
        per_sweep[s].update(translation_mm=mm, rotation_deg=deg, max_displacement_mm=max_disp,
                            converged=bool(conv) or len(sol) == 1)
    for (i, j), e in edges.items():
        if (i, j) in used and i in sol and j in sol:
            # T_ij should equal C_j^-1 C_i
            d = invert_transform(sol[j] @ e["T"]) @ sol[i]
            mm, deg = _motion(d, cents[i])
            e["pair"].update(used=True, residual_mm=mm, residual_deg=deg)
    pairs = [_jsonable(p) for p in pairs]  # NaN (not measured) -> None: valid JSON
    n_flag = sum(p["flagged"] for p in per_sweep)
    log.info("aligned %d sweeps (%s, reference %d): %d pairs accepted, %d sweeps flagged",
             n_sweeps, o.method, reference, len(edges), n_flag)
    return AlignmentResult(corrections=corrections, pairs=pairs, per_sweep=per_sweep,
                           reference=reference, method=o.method, gauge=gauge)


def _solve_pose_graph(order, edges, tree, reference, max_corr_dist):
    import open3d as o3d

    reg = o3d.pipelines.registration
    local = {s: k for k, s in enumerate(order)}
    graph = reg.PoseGraph()
    for _ in order:
        graph.nodes.append(reg.PoseGraphNode(np.eye(4)))
    keys = []
    for (i, j), e in edges.items():
        if i in local and j in local:
            graph.edges.append(reg.PoseGraphEdge(local[i], local[j], e["T"], e["info"],
                                                 uncertain=(i, j) not in tree))
            keys.append((i, j))
    if len(order) > 1:
        option = reg.GlobalOptimizationOption(max_correspondence_distance=max_corr_dist,
                                              edge_prune_threshold=0.25,
                                              preference_loop_closure=1.0,
                                              reference_node=local[reference])
        reg.global_optimization(graph, reg.GlobalOptimizationLevenbergMarquardt(),
                                reg.GlobalOptimizationConvergenceCriteria(), option)
    sol = {s: np.asarray(graph.nodes[local[s]].pose).copy() for s in order}
    kept = {(order[e.source_node_id], order[e.target_node_id]) for e in graph.edges}
    used = {k for k in keys if k in kept or (k[1], k[0]) in kept}
    return sol, used


def _solve_sequential(order, parent, edges, clouds, red, max_corr_dist, fine_dist,
                      max_iterations, voxel_size, per_sweep):
    """Register sweeps one after another along the spanning tree; flags non-convergence."""
    sol = {order[0]: np.eye(4)}
    used: set[tuple[int, int]] = set()
    for s in order[1:]:
        nbrs = [t for t in sol if (min(s, t), max(s, t)) in edges]
        if not nbrs:
            per_sweep[s].update(flagged=True, reason=(
                "its neighbours on the path to the reference could not be aligned"))
            continue
        tgt_p = np.concatenate([red[t][0] @ sol[t][:3, :3].T + sol[t][:3, 3] for t in nbrs])
        tgt_n = np.concatenate([red[t][1] @ sol[t][:3, :3].T for t in nbrs])
        init = sol[parent[s]] if parent[s] in sol else sol[nbrs[0]]
        res, converged, _ = _icp(clouds[s], _to_o3d(tgt_p, tgt_n), max_corr_dist, fine_dist,
                                 init, max_iterations, red[s][0].mean(axis=0), voxel_size)
        if not converged:
            per_sweep[s].update(flagged=True, reason="sequential ICP did not converge")
            continue
        sol[s] = np.asarray(res.transformation).copy()
        used.update((min(s, t), max(s, t)) for t in nbrs)
    return sol, used


# --------------------------------------------------------------------------- refinement
@dataclass
class SilhouetteViews:
    """Calibrated silhouette views: the absolute reference of :func:`refine_sweeps`.

    Attributes
    ----------
    images : list of (H, W) float
        Grey images of the views (any scale; colour images are averaged to grey).
    masks : list of (H, W) bool
        Their segmented silhouettes (used to find and group contour points; the
        residuals come from the images' own edges).
    cameras : list of CameraModel
    T_base_camera : (V, 4, 4) float64
        Each view's camera pose (the robot's, for views much more accurate than for
        sweeps).
    """

    images: list[np.ndarray]
    masks: list[np.ndarray]
    cameras: list[Any]
    T_base_camera: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.cameras)
        self.T_base_camera = np.asarray(self.T_base_camera, dtype=np.float64).reshape(-1, 4, 4)
        if not (len(self.images) == len(self.masks) == len(self.T_base_camera) == n):
            raise ValueError(f"SilhouetteViews needs one image, mask and pose per camera; got "
                             f"{len(self.images)} images, {len(self.masks)} masks, "
                             f"{len(self.T_base_camera)} poses, {n} cameras")
        imgs, msks = [], []
        for k, (im, m, cam) in enumerate(zip(self.images, self.masks, self.cameras,
                                             strict=True)):
            im = np.asarray(im, dtype=np.float32)
            if im.ndim == 3:
                im = im.mean(axis=2)
            m = np.asarray(m, dtype=bool)[: cam.height, : cam.width]
            if im.shape != (cam.height, cam.width) or m.shape != im.shape:
                raise ValueError(f"view {k}: image {im.shape} and mask {m.shape} must be "
                                 f"({cam.height}, {cam.width}) like its camera")
            imgs.append(im)
            msks.append(m)
        self.images, self.masks = imgs, msks


@dataclass
class _ViewField:
    """Per-view precomputations for the rim residuals."""

    sdf: np.ndarray        # (H, W) float32, px: signed distance to the mask border (+ out)
    bucket: np.ndarray     # (H, W) int64: cell of the nearest mask-border pixel
    grey: np.ndarray       # (H, W) float32: image blurred for edge search
    camera: Any
    T_camera_base: np.ndarray


#: :func:`_view_fields` computes each view's fields in the mask's bounding box grown by
#: this many pixels: the rim residuals read them within ``2 search_px + 2`` px of the mask
#: border (the gate, then the edge search along the outward normal), the blur reaches 3
#: px more; outside it the signed distance is set to this margin (a lower bound).
_FIELD_MARGIN_PX = 32


def _view_fields(views: SilhouetteViews, cell_px: int, blur_px: float) -> list[_ViewField]:
    """Per view: the mask's signed distance, the cell of the nearest border pixel and the
    blurred grey image, each computed in the mask's bounding box grown by
    :data:`_FIELD_MARGIN_PX` only (exact there: every mask pixel, and every background
    pixel nearest to one, lies in it; a 1280 x 960 view's three distance transforms
    took 0.18 s over the whole image); the same values as over the whole image where
    the residuals read them."""
    from scipy import ndimage

    out = []
    for im, m, cam, T in zip(views.images, views.masks, views.cameras, views.T_base_camera,
                             strict=True):
        h, w = m.shape
        rows, cols = np.nonzero(m.any(axis=1))[0], np.nonzero(m.any(axis=0))[0]
        if len(rows):
            r0, r1 = max(rows[0] - _FIELD_MARGIN_PX, 0), min(rows[-1] + _FIELD_MARGIN_PX + 1, h)
            c0, c1 = max(cols[0] - _FIELD_MARGIN_PX, 0), min(cols[-1] + _FIELD_MARGIN_PX + 1, w)
        else:
            r0, r1, c0, c1 = 0, h, 0, w
        mc = m[r0:r1, c0:c1]
        d_out = ndimage.distance_transform_edt(~mc)
        d_in = ndimage.distance_transform_edt(mc)
        sdf = np.full((h, w), _FIELD_MARGIN_PX, dtype=np.float32)
        sdf[r0:r1, c0:c1] = np.where(mc, -(d_in - 0.5), d_out - 0.5)
        border = mc ^ ndimage.binary_erosion(mc)
        if not border.any():
            border[0, 0] = True
        _, (bv, bu) = ndimage.distance_transform_edt(~border, return_indices=True)
        nbu = w // cell_px + 1
        bucket = np.zeros((h, w), dtype=np.int64)
        bucket[r0:r1, c0:c1] = ((bv + r0) // cell_px) * nbu + (bu + c0) // cell_px
        grey = np.asarray(im, dtype=np.float32)
        if blur_px > 0:
            grey = grey.copy()
            grey[r0:r1, c0:c1] = ndimage.gaussian_filter(grey[r0:r1, c0:c1], blur_px)
        out.append(_ViewField(sdf, bucket, grey, cam, invert_transform(T)))
    return out


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    h, w = img.shape
    u = np.clip(u, 0.0, w - 1.001)
    v = np.clip(v, 0.0, h - 1.001)
    u0 = np.floor(u).astype(np.int64)
    v0 = np.floor(v).astype(np.int64)
    a, b = u - u0, v - v0
    return (img[v0, u0] * (1 - a) * (1 - b) + img[v0, u0 + 1] * a * (1 - b)
            + img[v0 + 1, u0] * (1 - a) * b + img[v0 + 1, u0 + 1] * a * b)


def _project(f: _ViewField, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pc = x @ f.T_camera_base[:3, :3].T + f.T_camera_base[:3, 3]
    uv, front = f.camera.project(pc)
    return uv, pc[:, 2] * front


@njit(nogil=True, cache=True)
def _rim_front(x, n, centre, R, t, intr, D, sdf, cos_pre, search, cosg, uv, depth,
               d):  # noqa: ANN001, ANN202 - numba kernel
    """:func:`_rim_residuals`' first pass, point by point: ``cosg = n . ray`` (signed:
    negative where the normal faces the camera); where ``|cosg|`` is below ``cos_pre`` the
    distorted pixel and depth (as ``CameraModel.project``), and
    where that pixel lies in front of the camera and ``search + 2`` px inside the image,
    ``d`` = the mask's signed distance there (bilinear, as :func:`_bilinear`)."""
    h, w = sdf.shape
    fx, skew, cx, fy, cy = intr[0], intr[1], intr[2], intr[3], intr[4]
    k1, k2, p1, p2, k3 = D[0], D[1], D[2], D[3], D[4]
    for i in range(x.shape[0]):
        r0 = x[i, 0] - centre[0]
        r1 = x[i, 1] - centre[1]
        r2_ = x[i, 2] - centre[2]
        c = (r0 * n[i, 0] + r1 * n[i, 1] + r2_ * n[i, 2]) / np.sqrt(
            r0 * r0 + r1 * r1 + r2_ * r2_)
        cosg[i] = c
        if not abs(c) < cos_pre:
            continue
        p0 = R[0, 0] * x[i, 0] + R[0, 1] * x[i, 1] + R[0, 2] * x[i, 2] + t[0]
        p1_ = R[1, 0] * x[i, 0] + R[1, 1] * x[i, 1] + R[1, 2] * x[i, 2] + t[1]
        z = R[2, 0] * x[i, 0] + R[2, 1] * x[i, 1] + R[2, 2] * x[i, 2] + t[2]
        front = z > 1e-12
        zs = z if front else 1.0
        xd, yd = distort_xy(p0 / zs, p1_ / zs, k1, k2, p1, p2, k3)
        u = fx * xd + skew * yd + cx
        v = fy * yd + cy
        uv[i, 0] = u
        uv[i, 1] = v
        dep = z if front else 0.0
        depth[i] = dep
        if not (dep > 0 and u > search + 2 and u < w - search - 3 and v > search + 2
                and v < h - search - 3):
            continue
        uc = min(max(u, 0.0), w - 1.001)
        vc = min(max(v, 0.0), h - 1.001)
        u0 = int(np.floor(uc))
        v0 = int(np.floor(vc))
        a = uc - u0
        b = vc - v0
        d[i] = (sdf[v0, u0] * (1 - a) * (1 - b) + sdf[v0, u0 + 1] * a * (1 - b)
                + sdf[v0 + 1, u0] * (1 - a) * b + sdf[v0 + 1, u0 + 1] * a * b)


def _turn_across(profile: np.ndarray, cell: np.ndarray, reach: np.ndarray,
                 facing: np.ndarray) -> np.ndarray:
    """(G,) bool, per group (a profile's points near one mask-border cell, of one
    sweep): whether the groups of its cell on either side of the most outward one (by
    ``reach``; in profile order) face opposite ways (the sign of ``facing``, their mean
    cosine between normal and line of sight): the sweep passed over the contour
    generator between those profiles."""
    _, inv = np.unique(cell, return_inverse=True)
    inv = inv.reshape(-1)
    m = int(inv.max()) + 1 if len(inv) else 0
    order = np.lexsort((reach, inv))
    last = np.r_[np.nonzero(np.diff(inv[order]))[0], len(order) - 1]
    p_top = np.empty(m, dtype=np.int64)
    p_top[inv[order][last]] = profile[order][last]
    side = np.sign(profile - p_top[inv])
    # per cell: a group before the top facing the view, before it facing away, after
    # it facing the view, after it facing away
    flags = np.zeros((m, 4), dtype=bool)
    for k, (sd, towards) in enumerate(((-1, True), (-1, False), (1, True), (1, False))):
        flags[inv[(side == sd) & ((facing < 0) == towards)], k] = True
    ok = (flags[:, 0] & flags[:, 3]) | (flags[:, 1] & flags[:, 2])
    return ok[inv]


def _row_medians(x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Each row's median of its entries where ``mask`` (every row has one), as
    ``np.nanmedian`` of the others set to NaN gives it, several times faster."""
    v = np.where(mask, x, np.inf)
    v.sort(axis=1)
    k = np.count_nonzero(mask, axis=1)
    rows = np.arange(len(v))
    return (v[rows, (k - 1) // 2] + v[rows, k // 2]) / 2


def _rim_residuals(f: _ViewField, x: np.ndarray, n: np.ndarray, profile: np.ndarray, *,
                   cos_max: float, side_px: float, search_px: float, min_contrast: float,
                   cell_tol_px: float = np.inf, group: np.ndarray | None = None,
                   crossing: bool = False
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Contour-generator points of one view and their distance to the image's edge.

    Candidates are points whose normal is nearly perpendicular to their line of sight
    (``|n . ray| < cos_max``) and which project near the mask border. They are grouped
    by laser profile (``profile``) and by the cell of the nearest mask-border pixel; the
    most outward point of a group is its profile's closest approach to the silhouette,
    kept only if the profile continues on both sides of it along the contour (by
    ``side_px``): a profile that stops short of the contour generator is no evidence.
    For each kept point the grey image is searched along the silhouette's outward normal
    (the projected surface normal) for the object-background edge (the largest gradient
    or a distinct edge outward of it, :func:`_outline_edge`; parabolic sub-pixel peak,
    within ``±search_px``); the residual is the point's signed
    distance beyond that edge, in pixels.

    Of the profiles that reach one mask-border cell, only those whose residual is within
    ``cell_tol_px`` of the cell's second most outward one (or beyond it) are kept (the
    sweep's own points, so its pose error is common to all of them): a profile that
    passes the contour inside it, without reaching the contour generator, has the
    normal test's grazing normal too. On a flat face seen at a grazing angle (a
    bracket's plate, a fin) every profile across the face does, each one profile
    spacing times the sine of that angle further in; kept, they pulled the sweep
    outward until their mean residual was zero (bracket, 4 sweeps: both faces of the
    6 mm upright ended 0.7 mm outward; at the true poses the mean rim residual of the
    sweep seeing the back face was -1.24 px, -0.39 px with this test; on the bumpy
    blob -0.11 to -0.23 px per sweep, +0.02 to +0.04 px with it).

    With ``crossing``, a group counts only where the sweep passes over the contour
    generator: along the profile (its points' normals turn from facing the view to
    facing away: a rounded body, or a crease between a face seen and one not seen,
    both grazing), or across the profiles (in profile order, those of the cell before
    the most outward one face one way and those after it the other: a profile along a
    cylinder's contour). Profiles on a flat face seen at a grazing angle do neither: the
    face continues outward beyond the last of them, to an edge that no measured point
    lies on, and the tests above do not see it where the profiles run along the
    contour (a user's box, random scene 677: 38 residuals of -1.4 px median at the true
    poses moved a sweep 1.4 mm away from them; the objects benchmark's bracket, whose
    aligned clouds lay 0.049 / 0.081 mm from the truth at the median with 4 / 7 sweeps,
    0.032 / 0.035 mm without those residuals; ``benchmarks/README.md``, stop 59).

    ``group`` (K,) int >= 0, optional: the points of several sweeps in one call, each
    point's sweep. Profiles and cells are then those of a sweep, and each sweep's result
    is what a call with its points alone returns, in the same order (the groups in
    ascending order): one call per view instead of one per view and sweep.

    Returns
    -------
    idx : (K,) int
        Indices of the kept points.
    r : (K,) float64, px
    grad : (K, 3) float64, px per metre
        Derivative of ``r`` with respect to the point's position.
    scale : (K,) float64, metres per px
        Depth over focal length at each point.
    cell : (K,) int
        The mask-border cell of each kept point (for the test across sweeps of
        :func:`_add_rim_terms`).
    """
    empty = (np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3)), np.zeros(0),
             np.zeros(0, np.int64))
    cam = f.camera
    centre = -f.T_camera_base[:3, :3].T @ f.T_camera_base[:3, 3]
    # one compiled pass over the sweep (no GIL): the grazing test, and for near-grazing
    # points (twice cos_max) the projection and the mask's signed distance there
    h, w = f.sdf.shape
    cosg = np.empty(len(x))
    uv = np.zeros((len(x), 2))
    depth = np.zeros(len(x))
    d = np.full(len(x), np.inf)
    _rim_front(np.ascontiguousarray(x, dtype=np.float64),
               np.ascontiguousarray(n, dtype=np.float64), centre,
               np.ascontiguousarray(f.T_camera_base[:3, :3]), f.T_camera_base[:3, 3].copy(),
               np.array([cam.fx, cam.K[0, 1], cam.cx, cam.fy, cam.cy]),
               np.asarray(cam.D[:5], dtype=np.float64), f.sdf, 2 * cos_max, float(search_px),
               cosg, uv, depth, d)
    gate = search_px + 1.0
    cand = np.nonzero(np.abs(d) < gate)[0]
    if len(cand) == 0:
        return empty
    ui = np.clip(np.round(uv[cand, 0]).astype(np.int64), 0, w - 1)
    vi = np.clip(np.round(uv[cand, 1]).astype(np.int64), 0, h - 1)
    n_cells = int(f.bucket.max()) + 1
    key = profile[cand] * n_cells + f.bucket[vi, ui]
    if group is not None:  # the sweep first: each sweep's groups in their own order
        key = key + group[cand] * ((int(profile.max()) + 1) * n_cells)
    order = np.lexsort((d[cand], key))
    k = key[order]
    c_o = cand[order]
    new = np.r_[True, k[1:] != k[:-1]]
    starts = np.nonzero(new)[0]
    last = np.r_[starts[1:] - 1, len(k) - 1]
    grp = np.cumsum(new) - 1
    top = c_o[last]
    ut = uv[top]
    gu = _bilinear(f.sdf, ut[:, 0] + 0.5, ut[:, 1]) - _bilinear(f.sdf, ut[:, 0] - 0.5, ut[:, 1])
    gv = _bilinear(f.sdf, ut[:, 0], ut[:, 1] + 0.5) - _bilinear(f.sdf, ut[:, 0], ut[:, 1] - 0.5)
    tang = np.stack([-gv, gu], axis=1)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True) + 1e-12
    s_t = np.einsum("ij,ij->i", uv[c_o] - ut[grp], tang[grp])
    lo = np.minimum.reduceat(s_t, starts)
    hi = np.maximum.reduceat(s_t, starts)
    keep = (lo < -side_px) & (hi > side_px) & (np.abs(cosg[top]) < cos_max)
    if crossing:  # the sweep passes over the contour generator there (docstring)
        facing = cosg[c_o]  # signed: the kernel's n . ray
        along = (np.minimum.reduceat(facing, starts) < 0) & (
            np.maximum.reduceat(facing, starts) > 0)
        mean = np.add.reduceat(facing, starts) / np.diff(np.r_[starts, len(facing)])
        p_g = profile[top].astype(np.int64)
        keep &= along | _turn_across(p_g, k[starts] - p_g * n_cells, d[top], mean)
    idx = top[keep]
    if len(idx) == 0:
        return empty
    # outward direction of the silhouette: the projected surface normal
    eps = 1e-4
    uv_n, _ = _project(f, x[idx] + eps * n[idx])
    m = uv_n - uv[idx]
    m /= np.linalg.norm(m, axis=1, keepdims=True) + 1e-12
    # ... which must point out of the mask (the mask's outward normal: the contour
    # tangent above, turned): on an occluding contour the surface normal is the
    # silhouette's outward normal. A grazing point whose normal points into the mask lies
    # on a cup's inner wall or on a face seen from behind a thin strip's far edge
    outward = np.stack([tang[keep, 1], -tang[keep, 0]], axis=1)
    facing = np.einsum("ij,ij->i", m, outward) > 0.5
    idx, m = idx[facing], m[facing]
    if len(idx) == 0:
        return empty
    step = 0.25
    s = np.arange(-search_px, search_px + 0.5 * step, step)
    q = uv[idx][:, None, :] + s[None, :, None] * m[:, None, :]
    prof = _bilinear(f.grey, q[..., 0].ravel(), q[..., 1].ravel()).reshape(len(idx), len(s))
    # the search stays on this side of the silhouette: inward only to the strip's middle
    # (where the mask's signed distance along the line is least; beyond it lies the far
    # edge of a strip thinner than the search, 3-4 px for a 1.8 mm fin seen end-on) and
    # outward only to the middle of a gap (the largest distance; beyond it another part)
    sd = _bilinear(f.sdf, q[..., 0].ravel(), q[..., 1].ravel()).reshape(len(idx), len(s))
    mid = len(s) // 2
    lo_k = np.argmin(sd[:, : mid + 1], axis=1)
    hi_k = mid + np.argmax(sd[:, mid:], axis=1)
    kpos = np.arange(len(s))[None, :]
    near = (kpos >= lo_k[:, None]) & (kpos <= hi_k[:, None])
    # the object may be brighter or darker than its background: the edge is the
    # largest change of either sign, and its sign must agree with the mask's side
    grad = (prof[:, 2:] - prof[:, :-2]) / (2 * step)
    ins = near & (sd < -0.75)
    outs = near & (sd > 0.75)
    both = ins.any(axis=1) & outs.any(axis=1)
    # which side is brighter: from the samples on either side of the mask's border along
    # the search (the first and second half of the search when one side has none)
    inside_brighter = np.median(prof[:, :mid], axis=1) >= np.median(prof[:, mid + 1:], axis=1)
    if both.any():
        med_in = _row_medians(prof[both], ins[both])
        med_out = _row_medians(prof[both], outs[both])
        inside_brighter[both] = med_in >= med_out
    grad = np.where(inside_brighter[:, None], -grad, grad)
    g_near = np.where(near[:, 1:-1], grad, -np.inf)
    kk_raw = _outline_edge(g_near, sd[:, 1:-1] <= _EDGE_MASK_REACH_PX)
    kk = np.clip(kk_raw, 1, grad.shape[1] - 2)
    rows = np.arange(len(idx))
    a, b, c = grad[rows, kk - 1], grad[rows, kk], grad[rows, kk + 1]
    den = a - 2 * b + c
    off = np.where(np.abs(den) > 1e-12, 0.5 * (a - c) / np.where(den == 0, 1, den), 0.0)
    edge = s[1:-1][kk] + np.clip(off, -1, 1) * step
    # a peak on the search's limit is no edge found
    valid = (b >= min_contrast) & (kk_raw > 0) & (kk_raw < grad.shape[1] - 1) & (
        kk_raw + 1 > lo_k) & (kk_raw + 1 < hi_k)
    idx, r, m, edge = idx[valid], -edge[valid], m[valid], edge[valid]
    if len(idx) == 0:
        return empty
    # only the most outward profiles of each mask-border cell touch the contour generator;
    # the reference is the cell's second most outward profile, so that one stray point
    # beyond the edge does not discard the cell's good ones
    cell = f.bucket[np.clip(np.round(uv[idx, 1]).astype(np.int64), 0, h - 1),
                    np.clip(np.round(uv[idx, 0]).astype(np.int64), 0, w - 1)]
    outer = _near_cell_outermost(r, cell if group is None else cell + group[idx] * n_cells,
                                 cell_tol_px)
    idx, r, m, cell = idx[outer], r[outer], m[outer], cell[outer]
    # d r / d x = m . d uv / d x (numerical, exact through the lens distortion)
    base_uv = uv[idx]
    jac = np.zeros((len(idx), 3))
    h_m = 1e-6
    for k3 in range(3):
        dx = np.zeros(3)
        dx[k3] = h_m
        uvk, _ = _project(f, x[idx] + dx)
        jac[:, k3] = np.einsum("ij,ij->i", m, (uvk - base_uv) / h_m)
    scale = depth[idx] / np.sqrt(cam.fx * cam.fy)
    return idx, r, jac, scale, cell


#: :func:`_outline_edge`: an edge outward of the strongest one is the outline when it is at
#: least this share of the strongest's gradient ...
_EDGE_OUTER_SHARE = 0.5
#: ... and the gradient between the two falls below this share of the weaker one ...
_EDGE_VALLEY_SHARE = 0.95
#: ... and it lies at most this far outside the segmented mask (px): the segmentation
#: places the outline to about a pixel; farther out, a second peak is the background's
_EDGE_MASK_REACH_PX = 1.5


def _outline_edge(g: np.ndarray, reach: np.ndarray | None = None) -> np.ndarray:
    """Per row of ``g`` (the gradient along a search line, inside to outside, signed so
    that the object-background change is positive; ``-inf`` off the search), the index
    of the object's outline: the strongest edge, unless a distinct edge lies outward of
    it, a local maximum of at least ``_EDGE_OUTER_SHARE`` of the strongest's gradient
    with a valley between the two below ``_EDGE_VALLEY_SHARE`` of the weaker one (the
    outermost such), where ``reach`` (bool, like ``g``) allows it: within
    ``_EDGE_MASK_REACH_PX`` of the segmented mask in :func:`_rim_residuals`.

    Why: a flat face seen nearly edge-on and away from the light projects to a dark
    strip between the lit face beside it and the background. The strongest change is
    then the lit face's edge, inside the outline by the strip's width, and the contour
    point was measured against the wrong edge: on the simulated bracket/4 the image
    edge lay 0.55 px inside the true outline on the unlit side (median at the true
    poses), 0.13 px on the lit side, and the two pushed its sweeps the same way. Taking
    the outer edge: 0.55 -> 0.36 px, the side's residual median +0.30 -> +0.09 px. The
    valley keeps a single blurred step with a shoulder (shading falling toward a smooth
    rim) on its strongest point: with it the blob's and the bottle's alignment is
    unchanged to 0.0001 mm, without it they moved by up to 0.0035 mm; 0.95 rather than
    0.8 took more of the bracket's strips (aligned median 0.049 -> 0.046 mm on
    bracket/4) and cup/4's worst sweep 0.111 -> 0.064 mm in replays of the align stage
    (``benchmarks/README.md``, stop 37). The reach: on the real DTU scan 24 photos, at
    points of the published outlines, the outer edge differed from the strongest at 1.9 %
    of them, and without a reach it wandered into the dark background where the strongest
    edge was weak (a noise bump at half its height): where the two differed the published
    outline lay 1.14 px from the outer edge and 2.25 px from the strongest (median), the
    outer one closer in 58 %; with the reach of 1.5 px 0.64 against 3.0 px, closer in
    73 %."""
    k_max = np.argmax(g, axis=1)
    n = g.shape[1]
    if n < 3 or len(g) == 0:
        return k_max
    rows = np.arange(len(g))
    g_max = g[rows, k_max]
    peak = np.zeros(g.shape, dtype=bool)
    peak[:, 1:-1] = (g[:, 1:-1] >= g[:, :-2]) & (g[:, 1:-1] >= g[:, 2:])
    kpos = np.arange(n)[None, :]
    peak &= np.isfinite(g) & (g >= _EDGE_OUTER_SHARE * g_max[:, None]) & (kpos > k_max[:, None])
    if reach is not None:
        peak &= reach
    has = peak.any(axis=1)
    if not has.any():
        return k_max
    outer = n - 1 - np.argmax(peak[:, ::-1], axis=1)  # the outermost candidate
    r = rows[has]
    between = (kpos > k_max[r, None]) & (kpos < outer[r, None])
    valley = np.where(between, g[r], np.inf).min(axis=1)
    distinct = valley < _EDGE_VALLEY_SHARE * np.minimum(g_max[r], g[r, outer[r]])
    out = k_max.copy()
    out[r[distinct]] = outer[r[distinct]]
    return out


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _exp_so3(w: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(w))
    k = _skew(w)
    if th < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + np.sin(th) / th * k + (1 - np.cos(th)) / th**2 * (k @ k)


def _log_so3(r: np.ndarray) -> np.ndarray:
    c = np.clip((np.trace(r) - 1) / 2, -1.0, 1.0)
    th = np.arccos(c)
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if th < 1e-9:
        return 0.5 * v
    return th / (2 * np.sin(th)) * v


def apply_correction(points: np.ndarray, origins: np.ndarray, rotation: np.ndarray,
                     translation: np.ndarray, normals: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Apply one sweep's correction (the motion model of :func:`refine_sweeps`).

    ``x' = R (x - o) + o + t``: the sweep's sensor is turned by ``R`` about its position
    at each frame and moved by ``t``, i.e. a constant pose correction in the sensor's
    frame for a sweep that translates without turning.

    Parameters
    ----------
    points : (N, 3) float64, metres
    origins : (N, 3) float64, metres
        Sensor position at each point's frame.
    rotation : (3, 3) float64
    translation : (3,) float64, metres
    normals : (N, 3) float64, optional

    Returns
    -------
    points : (N, 3) float64
    origins : (N, 3) float64
        ``o + t``.
    normals : (N, 3) float64 or None
        ``R n``.
    """
    p = np.asarray(points, dtype=np.float64)
    o = np.asarray(origins, dtype=np.float64)
    r = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64).reshape(3)
    if p.shape != o.shape or p.ndim != 2 or p.shape[1] != 3 or r.shape != (3, 3):
        raise ValueError(f"points and origins must both be (N, 3) and rotation (3, 3), got "
                         f"{p.shape}, {o.shape}, {r.shape}")
    out = (p - o) @ r.T + o + t
    nn = None if normals is None else np.asarray(normals, dtype=np.float64) @ r.T
    return out, o + t, nn


@dataclass
class RefinementResult:
    """Result of :func:`refine_sweeps`.

    Attributes
    ----------
    rotations : (S, 3, 3) float64
    translations : (S, 3) float64, metres
        Each sweep's correction, applied by :func:`apply_correction`; identity / zero for
        flagged and excluded sweeps.
    converged : bool
    iterations : int
    gauge : str
        ``"silhouettes"`` (absolute reference), ``"fixed sweeps [...]"`` (those keep
        their initial correction) or ``"prior"`` (held by the prior alone).
    per_sweep : list of dict
        ``sweep``, ``n_rim`` (rim residuals), ``rim_rms_px``, ``rim_median_px``; with
        views also ``profile_noise_mm``, ``profile_noise_px`` and ``rim_fit_share``
        (:func:`_rim_points`).
    silhouettes : dict
        ``n_views``, ``n_rim``, ``rms_px``, ``median_px``, ``sigma_px``.
    pair_sigma_mm : float
    """

    rotations: np.ndarray
    translations: np.ndarray
    converged: bool
    iterations: int
    gauge: str
    per_sweep: list[dict[str, Any]]
    silhouettes: dict[str, Any]
    pair_sigma_mm: float


def _pair_normals(p: np.ndarray, n: np.ndarray, profile: np.ndarray, m: int, max_deg: float,
                  reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Normals for the pair term, and which points may take part in it.

    The triangulation's normals come from tangents on the profile grid and are accurate
    to a few tenths of a degree on most of a surface, but off by far more where a
    neighbouring profile is broken (occlusion, a crease, the first and last profiles
    over a face; ``benchmarks/README.md``). A
    point-to-plane residual carries the normal's error times the distance to the
    neighbour (up to half the profile spacing), so such points bias the sweep's
    rotation. Here each point's normal is the least principal axis (Hoppe et al. 1992)
    of its ``m`` nearest points on its own profile and on each of the two adjacent
    profiles (within ``reach``), so that the neighbourhood always spans the surface in
    both directions however far apart the profiles are, oriented like ``n``; where the
    profiles are at most twice as far apart as the points along them (a fast camera),
    three profiles would be a thin strip, and the ``3 m`` nearest points are taken
    instead. A point is usable when its neighbourhood spans two directions (neighbours
    on its own and at least one adjacent profile; second principal axis at least 5 % of
    the first) and the two normals agree within ``max_deg``.

    Parameters
    ----------
    p, n : (N, 3) float64
        One sweep's points and unit normals.
    profile : (N,) int
        Laser frame of each point (consecutive frames are adjacent profiles).
    m : int
        Neighbours per profile.
    max_deg : float
    reach : float, metres

    Returns
    -------
    normals : (N, 3) float64
        The principal-axis normals where usable, ``n`` elsewhere.
    usable : (N,) bool
    """
    n_pts = len(p)
    m = int(m)
    if n_pts < 5 or m < 2:
        return n, np.zeros(n_pts, dtype=bool)
    prof = np.asarray(profile, dtype=np.int64)
    order = np.argsort(prof, kind="stable")
    ids, first, counts = np.unique(prof[order], return_index=True, return_counts=True)
    members = [order[f:f + c] for f, c in zip(first, counts, strict=True)]
    trees = [cKDTree(p[mb]) for mb in members]
    nbr = np.full((n_pts, 3, m), -1, dtype=np.int64)
    gap = np.full((n_pts, 2), np.inf)  # nearest other point: on the own / an adjacent profile
    for j, mb in enumerate(members):  # loop over profiles (tens per sweep), not points
        for slot, jj in ((0, j), (1, j - 1), (2, j + 1)):
            if not (0 <= jj < len(ids)) or abs(int(ids[jj]) - int(ids[j])) != (slot > 0):
                continue
            kk = min(m, len(members[jj]))
            d, nb = trees[jj].query(p[mb], k=kk, distance_upper_bound=reach)
            d, nb = d.reshape(len(mb), kk), nb.reshape(len(mb), kk)
            ok = np.isfinite(d)
            nbr[mb, slot, :kk] = np.where(ok, members[jj][np.minimum(nb, len(members[jj]) - 1)],
                                          -1)
            if slot == 0 and kk > 1:  # d[:, 0] is the point itself
                gap[mb, 0] = d[:, 1]
            elif slot > 0:
                gap[mb, 1] = np.minimum(gap[mb, 1], d[:, 0])
    own, adj = gap[np.isfinite(gap[:, 0]), 0], gap[np.isfinite(gap[:, 1]), 1]
    if len(own) and len(adj) and np.median(adj) <= 2.0 * np.median(own):
        # profiles as close as the points along them (a fast camera): m points on three
        # profiles would be a thin strip across them; a plain 3 m-neighbourhood is round
        d, nb = cKDTree(p).query(p, k=min(3 * m, n_pts), distance_upper_bound=reach)
        flat = np.where(np.isfinite(d), nb, -1)
        valid = flat >= 0
        spans = valid.sum(axis=1) >= 6
    else:
        valid = nbr >= 0
        per_slot = valid.sum(axis=2)
        spans = (per_slot[:, 0] >= 3) & ((per_slot[:, 1] >= 3) | (per_slot[:, 2] >= 3))
        flat = nbr.reshape(n_pts, -1)
        valid = valid.reshape(n_pts, -1)
    w = valid.astype(np.float64)
    q = p[np.maximum(flat, 0)]
    cnt = np.maximum(w.sum(axis=1), 1.0)
    mean = np.einsum("nk,nki->ni", w, q) / cnt[:, None]
    q = (q - mean[:, None, :]) * w[..., None]
    lam, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", q, q))
    pca = vec[:, :, 0]
    cos = np.einsum("ij,ij->i", pca, n)
    pca[cos < 0] *= -1.0
    usable = spans & (lam[:, 1] > 0.05 * lam[:, 2]) & (
        np.abs(cos) >= np.cos(np.radians(max_deg)))
    return np.where(usable[:, None], pca, n), usable


def _profile_spacing(origins: np.ndarray, profile: np.ndarray) -> float:
    """Median distance (metres) the sensor moved between consecutive profiles of a
    sweep, per frame step (inf with fewer than two profiles)."""
    ids, first = np.unique(np.asarray(profile, dtype=np.int64), return_index=True)
    if len(ids) < 2:
        return float("inf")
    step = np.linalg.norm(np.diff(origins[first], axis=0), axis=1) / np.diff(ids)
    return float(np.median(step))


def _mean_poses(history: list[tuple[np.ndarray, np.ndarray]]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Mean of a few nearby estimates (rotations (S, 3, 3), translations (S, 3)):
    rotation vectors averaged about the last estimate."""
    r_last, _ = history[-1]
    rot = np.empty_like(r_last)
    for s in range(len(r_last)):  # a handful of sweeps
        w = np.mean([_log_so3(r[s] @ r_last[s].T) for r, _ in history], axis=0)
        rot[s] = _exp_so3(w) @ r_last[s]
    trans = np.mean([t for _, t in history], axis=0)
    return rot, trans


def _solve_held(H: np.ndarray, b: np.ndarray, prior_b: np.ndarray, prior_sd: np.ndarray,
                free: np.ndarray, ratio: float) -> tuple[np.ndarray, dict[str, Any]]:
    """One Gauss-Newton step in which the directions the data do not constrain are left
    to the prior alone.

    The data's normal equations ``H delta = -b`` are whitened by the prior (parameters
    in units of the prior's standard deviations, ``u = delta / prior_sd``), so that an
    eigenvalue of ``S H S`` (``S = diag(prior_sd)``) is the data's information along its
    eigenvector in units of the prior's. Directions below ``ratio`` (the data know them
    less than ``ratio`` times as well as the robot does) are removed from the data's
    equations, information and gradient alike (Zhang, Kaess & Singh 2016, "solution
    remapping"): there the step is the prior's alone, which holds the correction at the
    robot's pose instead of letting residual noise, normal noise and the sliding of
    correspondences drift it.

    Parameters
    ----------
    H : (n, n) float64
        Data information (pair and rim terms).
    b : (n,) float64
        Data gradient.
    prior_b : (n,) float64
        Prior gradient (``current / prior_sd**2``).
    prior_sd : (n,) float64
        Prior standard deviation of each parameter.
    free : (n,) bool
        Parameters to solve for (the others keep their value: step 0).
    ratio : float
        Least data-to-prior information ratio of a constrained direction.

    Returns
    -------
    delta : (n,) float64
    info : dict
        ``eigenvalues`` (k,), ``vectors`` (k, k) (whitened, over the free parameters),
        ``weak`` (k,) bool, ``free`` (k,) int (their indices).
    """
    n = len(b)
    delta = np.zeros(n)
    f = np.flatnonzero(free)
    if len(f) == 0:
        return delta, {"eigenvalues": np.zeros(0), "vectors": np.zeros((0, 0)),
                       "weak": np.zeros(0, bool), "free": f}
    sd = prior_sd[f]
    hw = sd[:, None] * H[np.ix_(f, f)] * sd[None, :]
    lam, vec = np.linalg.eigh(0.5 * (hw + hw.T))
    weak = lam < ratio
    gw = sd * b[f]
    strong = vec[:, ~weak]
    # (S H S)' = V_s diag(lam_s) V_s^T and g' = V_s V_s^T g: the data's part in the
    # constrained subspace only; the identity is the prior's information
    g_data = strong @ (strong.T @ gw)
    u_strong = -(strong.T @ (g_data + sd * prior_b[f])) / (lam[~weak] + 1.0)
    u_weak = -(vec[:, weak].T @ (sd * prior_b[f]))
    delta[f] = sd * (strong @ u_strong + vec[:, weak] @ u_weak)
    if not np.all(np.isfinite(delta)):
        raise np.linalg.LinAlgError("non-finite step")
    return delta, {"eigenvalues": lam, "vectors": vec, "weak": weak, "free": f,
                   "ratio": ratio}


def _direction_report(info: dict[str, Any], k0: int, prior_sd: np.ndarray,
                      points: np.ndarray, origin: np.ndarray) -> dict[str, Any]:
    """Which directions one sweep's data fixed, from the whitened eigen-decomposition of
    the normal equations (:func:`_solve_held`).

    ``k0`` is the sweep's first parameter (6 per sweep: rotation about the sensor,
    shift). The basic directions are the translations along, and the rotations about,
    the principal axes of the sweep's points; from the sweep's block of the data
    information that was used (held directions removed), a translation is
    ``constrained`` when the data see it at least ``ratio`` times as well as the prior
    does, a rotation when they tell it apart from every accompanying translation that
    well (the Schur complement: a flat face fixes neither its in-plane shifts nor the
    turn about its normal, a sphere no turn at all). ``unconstrained`` describes, in
    plain words, each direction of the sweep that the data left to the prior: a
    rotation about an axis (direction and a point on it, base, mm) or a translation.
    """
    f = info["free"]
    rows = np.flatnonzero((f >= k0) & (f < k0 + 6))
    if len(rows) < 6:
        return {"constrained": None, "unconstrained": ["held fixed (the gauge)"],
                "information": None}
    weakv = info["vectors"][rows][:, info["weak"]]  # this sweep's share of held directions
    m = weakv @ weakv.T  # (6, 6): fraction of a whitened direction that is held
    c = points.mean(axis=0) if len(points) else origin
    if len(points) >= 3:
        _, _, axes = np.linalg.svd(points - c, full_matrices=False)
    else:
        axes = np.eye(3)
    if np.linalg.det(axes) < 0:
        axes[2] *= -1
    sd = prior_sd[:6]

    # the sweep's own block of the data information that was used (held directions
    # removed), in the twist about its centroid (rotation w, centroid shift v): the
    # sensor model's shift is t = v + [c - o]x w
    lam, vec, weak = info["eigenvalues"], info["vectors"], info["weak"]
    hw = (vec[rows][:, ~weak] * lam[~weak]) @ vec[rows][:, ~weak].T
    h_d = hw / np.outer(sd, sd)
    h_p = np.diag(1.0 / sd**2)
    mm = np.eye(6)
    mm[3:, :3] = _skew(c - origin)
    h_d, h_p = mm.T @ h_d @ mm, mm.T @ h_p @ mm

    def marginal(h: np.ndarray, a: np.ndarray) -> float:
        # information of a turn about a when any shift may accompany it (Schur)
        return float(a @ (h[:3, :3] - h[:3, 3:] @ np.linalg.pinv(h[3:, 3:]) @ h[3:, :3]) @ a)

    ratio = info.get("ratio", 1.0)
    # a shift along a: seen by the data (turns held); a turn about a: told apart from
    # every shift. A flat face: shifts in its plane and the turn about its normal are
    # not fixed; a sphere: no turn is
    trans = [bool(a @ h_d[3:, 3:] @ a >= ratio * (a @ h_p[3:, 3:] @ a)) for a in axes]
    rots = [bool(marginal(h_d, a) >= ratio * marginal(h_p, a)) for a in axes]
    lam_s, vec_s = np.linalg.eigh(0.5 * (m + m.T))
    words = []
    for val, u in zip(lam_s[::-1], vec_s[:, ::-1].T, strict=True):
        if val < 0.5:
            break
        d = u * sd
        w, t = d[:3], d[3:]
        v_c = np.cross(w, c - origin) + t  # displacement of the centroid
        nw = np.linalg.norm(w)
        spread = float(np.sqrt(np.mean(np.sum((points - c) ** 2, axis=1)))) if len(
            points) else 0.0
        if nw * max(spread, 1e-3) > 0.2 * np.linalg.norm(v_c):
            a = w / nw
            p = c + np.cross(w, v_c) / nw**2
            words.append(f"rotation about the axis ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f}) "
                         f"through ({p[0] * 1e3:.1f}, {p[1] * 1e3:.1f}, {p[2] * 1e3:.1f}) mm")
        else:
            a = v_c / np.linalg.norm(v_c)
            words.append(f"translation along ({a[0]:.2f}, {a[1]:.2f}, {a[2]:.2f})")
    # the sweep's own block: information of its directions, others held fixed
    blk = info["vectors"][rows] * info["eigenvalues"][None, :] @ info["vectors"][rows].T
    return {"constrained": {"translation": trans, "rotation": rots,
                            "axes": np.round(axes, 4).tolist()},
            "unconstrained": words,
            "information": np.round(np.linalg.eigvalsh(0.5 * (blk + blk.T)), 3).tolist()}


def _huber(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))


#: Fixed parameters of the refinement (not config keys; see :func:`refine_sweeps`):
#: the silhouette term's largest ``|n . ray|`` of a contour-generator point, extent of
#: its profile on both sides (px), edge search half-width (px), least edge gradient
#: (grey levels per px), how far inside its cell's second most outward profile a
#: profile may be and still count (px), whether the sweep must pass over the contour
#: generator (:func:`_rim_residuals`), and grouping cell (px); the convergence tolerances (metres);
#: the pair term's normals' largest disagreement (degrees) and neighbourhood (metres).
_RIM = dict(cos_max=0.15, side_px=1.5, search_px=5.0, min_contrast=2.0, cell_tol_px=0.5,
            crossing=True)
#: :func:`_outermost_across_sweeps`' tolerance: a sweep's own cell tolerance plus what the
#: sweeps may still disagree by once the pose graph has run (a few hundredths of a mm)
_RIM_CROSS_TOL_PX = 0.75
_RIM_CELL_PX = 10
#: points per sweep the refinement's terms use at most (a seeded subsample)
_REFINE_MAX_POINTS = 30_000
_TOL, _SETTLE_TOL = 1e-6, 3e-5
_NORMAL_MAX_DEG, _NORMAL_REACH = 10.0, 4e-3


#: The silhouette term on noisy profiles (:func:`_rim_points`): a sweep whose points
#: scatter about their profiles (px, in the views) by up to the first value keeps its
#: measured points, from the second on takes them fitted over ``_RIM_FIT_HALF``
#: neighbours on either side, in between a linear blend of the two
_RIM_NOISY_PX = (0.04, 0.08)
_RIM_FIT_HALF = 5


def _profiles_in_order(x: np.ndarray, profile: np.ndarray) -> bool:
    """Whether each profile's points come in order along it (the stripe's lines, as the
    triangulation writes them), which :func:`_profile_quadratic` takes for granted: the
    median step from a point to the next of its profile at most twice the median
    distance to its nearest neighbour of the profile (about 1 in order; shuffled, the
    steps span the profile). Judged on every k-th profile, about 20,000 points."""
    _, rank = np.unique(profile, return_inverse=True)
    rank = rank.reshape(-1)
    pick = rank % max(1, len(x) // 20_000) == 0
    x, rank = x[pick], rank[pick]
    same = rank[1:] == rank[:-1]
    if same.sum() < 10:
        return True
    step = np.linalg.norm(np.diff(x, axis=0), axis=1)[same]
    # the profile as a fourth coordinate, far apart: neighbours within a profile only
    far = 1e3 * (float(np.ptp(x, axis=0).max()) + 1.0)
    xr = np.c_[x, rank * far]
    d, _ = cKDTree(xr).query(xr, k=2)
    return bool(np.median(step) <= 2.0 * np.median(d[:, 1]))


def _profile_noise(x: np.ndarray, n: np.ndarray, profile: np.ndarray) -> float:
    """The points' scatter about their profile (metres, along their normals): the robust
    standard deviation of each point's distance to the quadratic through it and its two
    neighbours on either side (:func:`_profile_quadratic`), over the fit's own share
    (a 5-point quadratic's centre residual has 0.717 of the noise's deviation), at up to
    20,000 of the points (evenly spread)."""
    if len(x) < 5:
        return 0.0
    at = np.arange(0, len(x), max(1, len(x) // 20_000))
    fit = _profile_quadratic(x, profile, at, 2)
    dev = np.abs(np.einsum("ij,ij->i", x[at] - fit, n[at]))
    moved = dev > 0  # points without two neighbours on each side keep their position
    return float(1.4826 * np.median(dev[moved]) / 0.717) if moved.sum() >= 5 else 0.0


def _profile_scatter(x: np.ndarray, n: np.ndarray, profile: np.ndarray) -> float | None:
    """A sweep's scatter about its profiles (:func:`_profile_noise`, metres), or None where
    its profiles' points are not in order along them (:func:`_profiles_in_order`): no fit
    for the silhouette term then (:func:`_rim_points`)."""
    return _profile_noise(x, n, profile) if _profiles_in_order(x, profile) else None


def _profile_quadratic(x: np.ndarray, profile: np.ndarray, idx: np.ndarray, half: int
                       ) -> np.ndarray:
    """(M, 3): the points ``x[idx]`` replaced by a least-squares quadratic through their
    profile's ``half`` neighbours on either side (in array order: a profile's points in
    stripe order), parametrised by chord length, within one run of the profile (no step
    over 3x the profile's median step); points with fewer than 2 neighbours on a side
    keep their position. A quadratic fit leaves a parabola's apex where it is (a moving
    average pulls it inward): the points of a profile near a contour generator lie on
    one."""
    K = len(x)
    step = np.linalg.norm(np.diff(x, axis=0), axis=1)
    same_next = profile[1:] == profile[:-1]
    if not same_next.any():
        return x[idx].copy()
    med = np.median(step[same_next])
    if not med > 0:  # most points repeat their predecessor: no profile to fit
        return x[idx].copy()
    brk = ~same_next | (step > 3 * med)
    seg = np.r_[0, np.cumsum(brk)]
    t = np.r_[0.0, np.cumsum(np.where(brk, 0.0, step))]
    offs = np.arange(-half, half + 1)
    j = idx[:, None] + offs[None, :]
    jc = np.clip(j, 0, K - 1)
    ok = (j >= 0) & (j < K) & (seg[jc] == seg[idx][:, None])
    good = ((ok[:, :half].sum(axis=1) >= 2) & (ok[:, half + 1:].sum(axis=1) >= 2))
    out = x[idx].copy()
    if not good.any():
        return out
    ok, jc, ig = ok[good], jc[good], idx[good]
    w = ok.astype(np.float64)
    tr = np.where(ok, (t[jc] - t[ig][:, None]) / med, 0.0)  # in steps: well conditioned
    # the normal equations of the weighted quadratic, solved for its value at t = 0
    # (Cramer's rule, one 3 x 3 system per point)
    t2 = tr * tr
    s0, s1, s2 = w.sum(axis=1), (w * tr).sum(axis=1), (w * t2).sum(axis=1)
    s3, s4 = (w * t2 * tr).sum(axis=1), (w * t2 * t2).sum(axis=1)
    xj = x[jc]  # (M, W, 3)
    b0 = np.einsum("mw,mwk->mk", w, xj)
    b1 = np.einsum("mw,mwk->mk", w * tr, xj)
    b2 = np.einsum("mw,mwk->mk", w * t2, xj)
    m00 = s2 * s4 - s3 * s3
    det = s0 * m00 - s1 * (s1 * s4 - s3 * s2) + s2 * (s1 * s3 - s2 * s2)
    num = (b0 * m00[:, None] - s1[:, None] * (b1 * s4[:, None] - s3[:, None] * b2)
           + s2[:, None] * (b1 * s3[:, None] - s2[:, None] * b2))
    solved = np.abs(det) > 1e-9 * np.maximum(s0 * m00, 1e-300)
    fit = out[good]
    fit[solved] = num[solved] / det[solved, None]
    out[good] = fit
    return out


def _refine_inputs(points, normals, origins, profiles, max_points: int, rng,
                   scatter: bool = True):
    """The sweeps' points, unit normals, origins and profile keys (subsampled to
    ``max_points``, seeded); and per sweep, from all of its points, its scatter about its
    profiles (:func:`_profile_noise`, metres; with ``scatter``, else 0: only the
    silhouette term uses it) and what :func:`_rim_points` fits the kept points along
    their profiles with (all points, profile keys, the kept ones' indices)."""
    n_s = len(points)
    P, Nn, O, G, full, noise = [], [], [], [], [], []
    for s in range(n_s):
        p = np.asarray(points[s], dtype=np.float64)
        nrm = np.asarray(normals[s], dtype=np.float64)
        o = np.asarray(origins[s], dtype=np.float64)
        if p.shape != nrm.shape or p.shape != o.shape:
            raise ValueError(f"sweep {s}: points, normals and origins must have one shape, "
                             f"got {p.shape}, {nrm.shape}, {o.shape}")
        g = (np.zeros(len(p), np.int64) if profiles is None
             else np.asarray(profiles[s], dtype=np.int64).reshape(-1))
        if len(g) != len(p):
            raise ValueError(f"sweep {s}: profiles must have {len(p)} entries, got {len(g)}")
        length = np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm = nrm / np.maximum(length, 1e-12)
        noise.append(_profile_scatter(p, nrm, g) if scatter and profiles is not None
                     else 0.0)
        keep = np.arange(len(p))
        p_all, g_all = p, g
        if len(p) > max_points:
            keep = np.sort(rng.choice(len(p), size=max_points, replace=False))
            p, nrm, o, g = p[keep], nrm[keep], o[keep], g[keep]
        P.append(p)
        Nn.append(nrm)
        O.append(o)
        G.append(g + (s << 32))
        full.append((p_all, g_all, keep))
    return P, Nn, O, G, full, noise


def _pair_subsets(P, Nn, O, G, o: AlignOptions) -> list[np.ndarray]:
    """The points of each sweep that take part in the pair term, thinned to one measured
    point per voxel; ``Nn`` replaced (in place) by :func:`_pair_normals` for sweeps whose
    profiles are close enough."""
    red_idx = []
    for s in range(len(P)):
        cand = np.arange(len(P[s]))
        if (o.pair_normals_k and len(P[s])
                and _profile_spacing(O[s], G[s]) <= o.pair_normals_max_spacing_m):
            Nn[s], usable = _pair_normals(P[s], Nn[s], G[s], o.pair_normals_k,
                                          _NORMAL_MAX_DEG, _NORMAL_REACH)
            cand = cand[usable]
        if len(cand) == 0 or o.voxel_size_m <= 0:
            red_idx.append(cand)
            continue
        key = np.floor((P[s][cand] - P[s][cand].min(axis=0)) / o.voxel_size_m).astype(np.int64)
        _, first = np.unique(key, axis=0, return_index=True)
        red_idx.append(cand[np.sort(first)])
    return red_idx


def _pair_residuals(x: np.ndarray, y: np.ndarray, nx: np.ndarray, ny: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Symmetric point-to-plane residuals of correspondences ``x`` -> ``y`` (metres),
    their normals (the normalised sum of the two unit normals) and each one's plane-model
    error (metres).

    Along the sum of the two normals, the residual of two points on one sphere or
    cylinder is zero whatever their distance (Rusinkiewicz 2019); along one of them it is
    the sagitta between them, ``R (1 - cos a)`` for normals ``a`` apart: 0.2 mm on a
    rounded edge at the profiles' spacing, a pull that does not depend on the poses.

    Where the two normals disagree, the surface turns between the points, or the normals
    (estimated from profiles a millimetre apart) are wrong there: on a rounded edge or a
    thin ridge both happen, and no residual along them is exact. Each correspondence's
    plane-model error is taken as half the distance times the chord between the normals
    (the sagitta above: what the residual may be off by), and it is added to the
    residuals' robust scale, so that such correspondences weigh what they know; on a flat
    face it is zero. Measured on the objects benchmark's thin fin (7 sweeps, the TRUE
    poses, one pair of the low sweeps): residuals of 9 um median where the normals agree
    within 2 degrees, 57 / 87 um where they disagree by 10-20 / 20-40 degrees; the 1.5 mm
    gusset's ridge and the base's rounded ends held 74 % of that pair's information along
    the fin, ICP slid 1.5 mm along it, and the refinement turned a sweep 0.40 degrees
    away from its true pose (``benchmarks/README.md``, stop 60)."""
    n = nx + ny
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    r = np.einsum("ij,ij->i", x - y, n)
    model = 0.5 * np.linalg.norm(x - y, axis=1) * np.linalg.norm(nx - ny, axis=1)
    return r, n, model


def _add_pair_terms(H: np.ndarray, b: np.ndarray, pairs, cur, cur_n, org, red_idx,
                    index: dict[int, int], sigma_p: float, d_max: float) -> list[np.ndarray]:
    """Add the symmetric point-to-plane terms of every pair (both directions,
    Huber-weighted, each on the robust scale plus its plane model's error,
    :func:`_pair_residuals`) to the normal equations ``H``, ``b`` (in place); returns the
    residuals."""
    pair_r = []
    trees = {}
    for i, j in pairs:
        for a_, b_ in ((i, j), (j, i)):
            if b_ not in trees:
                trees[b_] = cKDTree(cur[b_][red_idx[b_]])
            xa = cur[a_][red_idx[a_]]
            dist, nb = trees[b_].query(xa, k=1, distance_upper_bound=d_max)
            ok = np.isfinite(dist)
            # the two sides of a thin wall lie within the correspondence distance:
            # points whose normals disagree by more than 60 degrees are not one
            # surface (as in _pair_info)
            ok[ok] = np.einsum("ij,ij->i", cur_n[a_][red_idx[a_][ok]],
                               cur_n[b_][red_idx[b_][nb[ok]]]) > 0.5
            if not np.any(ok):
                continue
            ia = red_idx[a_][ok]
            ib = red_idx[b_][nb[ok]]
            x, y = cur[a_][ia], cur[b_][ib]
            r, nrm, model = _pair_residuals(x, y, cur_n[a_][ia], cur_n[b_][ib])
            s = np.sqrt(sigma_p**2 + model**2)
            w = _huber(r / s, 2.0) / s**2
            ja = np.hstack([np.cross(x - org[a_][ia], nrm), nrm])
            jb = -np.hstack([np.cross(y - org[b_][ib], nrm), nrm])
            ka, kb = 6 * index[a_], 6 * index[b_]
            H[ka:ka + 6, ka:ka + 6] += ja.T @ (ja * w[:, None])
            H[kb:kb + 6, kb:kb + 6] += jb.T @ (jb * w[:, None])
            H[ka:ka + 6, kb:kb + 6] += ja.T @ (jb * w[:, None])
            H[kb:kb + 6, ka:ka + 6] += jb.T @ (ja * w[:, None])
            b[ka:ka + 6] += ja.T @ (w * r)
            b[kb:kb + 6] += jb.T @ (w * r)
            pair_r.append(r)
    return pair_r


def _add_rim_terms(H: np.ndarray, b: np.ndarray, fields, act, cur, cur_n, org, G,
                   index: dict[int, int], gate: float, sigma_s: float, rim_weight: float,
                   threads: int = 1) -> list[tuple[int, np.ndarray]]:
    """Add each view's contour-generator residuals (:func:`_rim_residuals`, the most
    outward of all sweeps: :func:`_outermost_across_sweeps`) within ``gate`` px,
    Huber-weighted and weighed by ``rim_weight``, to ``H``, ``b`` (in place); returns
    (sweep, residuals) per view and sweep. The views are searched on ``threads`` threads
    and their terms added in the views' order (the same sums at any thread count)."""

    if not act:
        return []
    # every active sweep's points in one call per view (the sweep as each point's group)
    x_all = np.concatenate([cur[s] for s in act])
    n_all = np.concatenate([cur_n[s] for s in act])
    g_all = np.concatenate([G[s] for s in act])
    sizes = [len(cur[s]) for s in act]
    grp = np.repeat(np.arange(len(act)), sizes)
    first = np.r_[0, np.cumsum(sizes)[:-1]]

    def contour(f) -> list:
        per_view = []
        idx_a, r_a, jac_a, scl_a, cell_a = _rim_residuals(f, x_all, n_all, g_all, **_RIM,
                                                          group=grp)
        g_of = grp[idx_a]
        for k, s in enumerate(act):
            sel = (g_of == k) & (np.abs(r_a) < gate)
            if sel.any():
                per_view.append((s, idx_a[sel] - first[k], r_a[sel], jac_a[sel], scl_a[sel],
                                 cell_a[sel]))
        return _outermost_across_sweeps(per_view, _RIM_CROSS_TOL_PX)

    rims = []
    for found in _map_threads(threads, contour, list(fields)):
        for s, idx, r, jac, _ in found:
            x = cur[s][idx]
            js = np.hstack([np.cross(x - org[s][idx], jac), jac])
            w = rim_weight * _huber(r / sigma_s, 1.5) / sigma_s**2
            k = 6 * index[s]
            H[k:k + 6, k:k + 6] += js.T @ (js * w[:, None])
            b[k:k + 6] += js.T @ (w * r)
            rims.append((s, r))
    return rims


def _near_cell_outermost(r: np.ndarray, cell: np.ndarray, tol_px: float) -> np.ndarray:
    """Mask of the residuals ``r`` (px, outward positive) within ``tol_px`` of their
    ``cell``'s second most outward one, or beyond it (the most outward when the cell has
    one): one stray point beyond the edge does not discard the cell's good ones."""
    _, inv = np.unique(cell, return_inverse=True)
    order = np.lexsort((-r, inv))
    starts = np.nonzero(np.r_[True, inv[order][1:] != inv[order][:-1]])[0]
    sizes = np.diff(np.r_[starts, len(order)])
    ref = r[order][np.where(sizes > 1, starts + 1, starts)]
    return r >= ref[inv] - tol_px


def _outermost_across_sweeps(found: list, tol_px: float) -> list:
    """Of one view's contour-generator residuals of all sweeps ``(sweep, idx, r, jac,
    scale, cell)``, keep those within ``tol_px`` of their mask-border cell's second most outward
    residual over all sweeps (the most outward when the cell has one).

    :func:`_rim_residuals` compares a sweep's profiles with each other only. Where none
    of a sweep's profiles reaches the contour generator (it ends on a face seen at a
    grazing angle, short of the rounded edge), its most outward one is still inside the
    silhouette, and it pulled the sweep outward (the thin-wall object, 7 sweeps: the base's
    top edge seen from the low views, one sweep's profiles 1.7 px inside while the
    others' reached the edge). The sweeps agree to a few hundredths of a millimetre once
    the pose graph has run, well within ``tol_px``.
    """
    if not found:
        return []
    keep = _near_cell_outermost(np.concatenate([f[2] for f in found]),
                                np.concatenate([f[5] for f in found]), tol_px)
    out, k0 = [], 0
    for s, idx, r, jac, scl, _ in found:
        kk = keep[k0:k0 + len(r)]
        k0 += len(r)
        if kk.any():
            out.append((s, idx[kk], r[kk], jac[kk], scl[kk]))
    return out


def _largest_step(delta: np.ndarray, act, index, cur, org) -> float:
    """The largest step of any active sweep's points: shift plus rotation times the
    sensor's distance from its points (metres)."""
    full = 0.0
    for s in act:
        k = 6 * index[s]
        lever = float(np.linalg.norm(cur[s].mean(axis=0) - org[s].mean(axis=0))) if len(
            cur[s]) else 0.0
        full = max(full, float(np.linalg.norm(delta[k + 3:k + 6]))
                   + float(np.linalg.norm(delta[k:k + 3])) * lever)
    return full


def _refinement_result(rot, trans, converged: bool, it: int, rim_stats, degen, index, act,
                       fixed, fields, sigma_s: float, sigma_p: float, prior_sd, P, O
                       ) -> RefinementResult:
    """The :class:`RefinementResult`: per sweep its rim residuals and the directions its
    data fixed (:func:`_direction_report`), the silhouette term, the gauge; sweeps not
    refined at the identity."""
    n_s = len(P)
    all_rim = np.concatenate(list(rim_stats.values())) if rim_stats else np.zeros(0)
    per_sweep = []
    for s in range(n_s):
        r = rim_stats.get(s, np.zeros(0))
        entry = {"sweep": s, "n_rim": int(len(r)),
                 "rim_rms_px": float(np.sqrt(np.mean(r**2))) if len(r) else None,
                 "rim_median_px": float(np.median(r)) if len(r) else None}
        if s in index and degen:
            o_mean = O[s].mean(axis=0) if len(O[s]) else np.zeros(3)
            entry.update(_direction_report(degen, 6 * index[s], prior_sd, P[s], o_mean))
        per_sweep.append(entry)
    sil = {"n_views": len(fields), "n_rim": int(len(all_rim)),
           "rms_px": float(np.sqrt(np.mean(all_rim**2))) if len(all_rim) else None,
           "median_px": float(np.median(all_rim)) if len(all_rim) else None,
           "sigma_px": float(sigma_s) if len(all_rim) else None}
    gauge = ("silhouettes" if len(all_rim) >= _MIN_RIM_GAUGE else
             f"fixed sweeps {fixed}" if fixed else "prior")
    for s in range(n_s):
        if s not in act:
            rot[s] = np.eye(3)
            trans[s] = 0.0
    return RefinementResult(rotations=rot, translations=trans, converged=converged,
                            iterations=it, gauge=gauge, per_sweep=per_sweep,
                            silhouettes=sil, pair_sigma_mm=float(sigma_p * 1e3))


def _gauss_newton_step(rot, trans, P, Nn, O, G, pairs, red_idx, fields, act, index,
                       it: int, sigma_p: float, sigma_s: float, o: AlignOptions,
                       prior_sd: np.ndarray, free: np.ndarray, P_rim=None):
    """One Gauss-Newton step of :func:`refine_sweeps` at the current corrections: the
    pair and rim terms, the prior, the step with the held directions
    (:func:`_solve_held`). Returns (step, eigen-decomposition, its largest point
    displacement, pair residuals, rim residuals); LinAlgError when singular."""
    n_s, n_par = len(P), 6 * len(act)
    cur = [((P[s] - O[s]) @ rot[s].T + O[s] + trans[s]) for s in range(n_s)]
    cur_n = [Nn[s] @ rot[s].T for s in range(n_s)]
    org = [O[s] + trans[s] for s in range(n_s)]
    H = np.zeros((n_par, n_par))
    b = np.zeros(n_par)
    d_max = max(o.max_corr_dist_m / 2 ** (it - 1), 3 * sigma_p, o.voxel_size_m)
    pair_r = _add_pair_terms(H, b, pairs, cur, cur_n, org, red_idx, index, sigma_p, d_max)
    gate = (max(_RIM["search_px"] - 1.0, 1.5) if it <= 2 else max(1.5, 4 * sigma_s))
    # the silhouette term at the points fitted along noisy profiles (_rim_points): one
    # frame's points share their origin, so the fit moves with the correction
    cur_rim = cur if P_rim is None else [
        ((P_rim[s] - O[s]) @ rot[s].T + O[s] + trans[s]) for s in range(n_s)]
    rims = _add_rim_terms(H, b, fields, act, cur_rim, cur_n, org, G, index, gate, sigma_s,
                          o.rim_weight, o.threads)
    # prior on each correction (rotation vector, sensor shift): its information and
    # gradient, kept apart from the data's so that the directions the data do not
    # constrain can be left to it alone
    prior_b = np.zeros(n_par)
    for s in act:
        k = 6 * index[s]
        prior_b[k:k + 3] = _log_so3(rot[s]) / prior_sd[0]**2
        prior_b[k + 3:k + 6] = trans[s] / prior_sd[3]**2
    delta, degen = _solve_held(H, b, prior_b, np.tile(prior_sd, len(act)), free,
                               o.degenerate_ratio)
    log.debug("refine it %d: whitened data information %s", it,
              np.array2string(degen["eigenvalues"], precision=3))
    return delta, degen, _largest_step(delta, act, index, cur, org), pair_r, rims


def _robust_scales(pair_r, rims, act, sigma_p: float, sigma_s: float
                   ) -> tuple[float, float, dict[int, np.ndarray]]:
    """The pair residuals' (metres) and rim residuals' (px) robust scales after a step,
    and each sweep's rim residuals."""
    if pair_r:
        rr = np.concatenate(pair_r)
        sigma_p = max(1.4826 * float(np.median(np.abs(rr))), 1e-6)
    rim_stats = {}
    if rims:
        allr = np.concatenate([r for _, r in rims])
        sigma_s = float(np.clip(1.4826 * np.median(np.abs(allr - np.median(allr))), 0.1, 2))
        for s in act:
            rs = [r for ss, r in rims if ss == s]
            rim_stats[s] = np.concatenate(rs) if rs else np.zeros(0)
    return sigma_p, sigma_s, rim_stats


def _iterate(rot, trans, sigma_p: float, sigma_s: float, P, Nn, O, G, pairs, red_idx,
             fields, act, index, o: AlignOptions, prior_sd: np.ndarray, free: np.ndarray,
             P_rim=None):
    """The Gauss-Newton iterations of :func:`refine_sweeps` from ``rot``, ``trans`` and
    the residuals' robust scales, with the damping of cycling steps and the two
    convergence tests: (rotations, translations, converged, iterations, rim residuals
    per sweep, last eigen-decomposition, pair scale, rim scale)."""
    degen: dict[str, np.ndarray] = {}
    converged = False
    it = 0
    rim_stats: dict[int, np.ndarray] = {}
    steps: list[float] = []
    history: list[tuple[np.ndarray, np.ndarray]] = []
    full_steps: list[float] = []
    damping = 1.0
    for it in range(1, o.refine_iterations + 1):
        try:
            delta, degen, full, pair_r, rims = _gauss_newton_step(
                rot, trans, P, Nn, O, G, pairs, red_idx, fields, act, index, it, sigma_p,
                sigma_s, o, prior_sd, free, P_rim)
        except np.linalg.LinAlgError:
            log.warning("refinement: singular normal equations at iteration %d", it)
            break
        # a full step larger than one already taken, once the estimate is near the
        # optimum, is the correspondences (pairs, contour points) switching back and
        # forth: shorten the steps from then on, so that the iterates settle in the
        # middle of the cycle instead of jumping across it
        if it > 4 and full > min(full_steps[3:] or [np.inf]):
            damping = max(damping * 0.6, 1 / 16)
        full_steps.append(full)
        delta = delta * damping
        biggest = full * damping
        for s in act:
            k = 6 * index[s]
            rot[s] = _exp_so3(delta[k:k + 3]) @ rot[s]
            trans[s] = trans[s] + delta[k + 3:k + 6]
        sigma_p, sigma_s, rim_stats = _robust_scales(pair_r, rims, act, sigma_p, sigma_s)
        log.debug("refine it %d: step %.2e m, pair sigma %.2e m, rim sigma %.3f px", it,
                  biggest, sigma_p, sigma_s)
        steps.append(biggest)
        history.append((rot.copy(), trans.copy()))
        if it >= 4 and biggest < _TOL:
            converged = True
            break
        if it >= 6 and max(steps[-4:]) < _SETTLE_TOL:
            # settled: the correspondences cycle between nearly equal sets, each step far
            # below the residuals' scale; the estimate is the centre of the last four
            rot, trans = _mean_poses(history[-4:])
            converged = True
            break
    return rot, trans, converged, it, rim_stats, degen, sigma_p, sigma_s


def _check_refine_inputs(points, normals, origins, profiles, o: AlignOptions) -> None:
    n_s = len(points)
    if not (len(normals) == len(origins) == n_s):
        raise ValueError("points, normals and origins need one array per sweep")
    if profiles is not None and len(profiles) != n_s:
        raise ValueError("profiles needs one array per sweep")
    if not (o.prior_mm > 0 and o.prior_deg > 0):
        raise ValueError(f"prior_mm and prior_deg must be > 0, got {o.prior_mm}, "
                         f"{o.prior_deg}")


def refine_sweeps(
    points: list[np.ndarray],
    normals: list[np.ndarray],
    origins: list[np.ndarray],
    pairs: list[tuple[int, int]],
    *,
    options: AlignOptions = AlignOptions(),
    profiles: list[np.ndarray] | None = None,
    initial: np.ndarray | None = None,
    active: list[int] | None = None,
    fixed: list[int] | None = None,
    silhouettes: SilhouetteViews | None = None,
    max_points: int = _REFINE_MAX_POINTS,
) -> RefinementResult:
    """Joint refinement of all sweep corrections against each other and the silhouettes.

    The unknowns are one correction per sweep in the motion model of
    :func:`apply_correction` (the sensor turned about its own position at every frame
    and shifted): exact for a pose error that is constant in the flange frame while the
    robot translates, which a rigid transform of the sweep's points is not (it leaves a
    shear of ``rotation error x travel``). Gauss-Newton minimises, with Huber weights,

    - symmetric point-to-plane distances between every overlapping pair (both
      directions, nearest neighbours within a distance shrinking from
      ``max_corr_dist_m`` to three robust standard deviations; each weighed by its
      plane model's error, :func:`_pair_residuals`),
    - with ``silhouettes``: the distance of each view's contour-generator points to the
      image edge of that view's silhouette (:func:`_rim_residuals`), which fixes the
      absolute position the sweeps cannot give each other: the views are taken at rest,
      their poses about ten times more accurate than a moving sweep's,
    - a prior on each correction (``prior_mm``, ``prior_deg``: the robot's expected
      error), which only decides what neither of the above determines (without views:
      the gauge, i.e. the least correction that makes the sweeps agree).

    Parameters
    ----------
    points, normals, origins : list of (N_s, 3) float64
        Each sweep's points (metres, ``base``, at the robot's poses), unit normals, and
        sensor position at each point's frame.
    pairs : list of (i, j)
        Overlapping pairs to use.
    options : AlignOptions
        ``prior_mm``, ``prior_deg`` (the robot's per-sweep error), ``voxel_size_m``
        (the pair term's thinning), ``max_corr_dist_m``, ``refine_iterations``,
        ``pair_normals_k``, ``pair_normals_max_spacing_m`` (:func:`_pair_normals`),
        ``rim_weight``, ``degenerate_ratio`` (:func:`_solve_held`) and ``seed``.
    profiles : list of (N_s,) int, optional
        Laser profile (frame) of each point, a profile's points in order along it;
        needed for the silhouette term.
    initial : (S, 4, 4) float64, optional
        Rigid corrections to start from (e.g. the pose graph's).
    active : list of int, optional
        Sweeps to refine (others keep the identity and take no part).
    fixed : list of int, optional
        Active sweeps that keep their initial correction (a gauge without silhouettes).
    silhouettes : SilhouetteViews, optional
    max_points : int
        Cap on points per sweep for the pair and silhouette terms (seeded subsample).

    Returns
    -------
    RefinementResult

    Notes
    -----
    Converged when the largest step of any sweep's points (shift plus rotation times
    the sensor's distance) falls below 1 micrometre, or "settled" when the last four
    steps all fall below 30 micrometres: near the optimum the correspondences may cycle
    between nearly equal sets, and the result is the mean of the cycle's last four
    estimates. Steps that grow again after the fourth iteration (the cycle) are
    shortened from then on (by 0.6 each time, to 1/16 at least). A point whose pair-term
    normal differs by more than 10 degrees from the triangulation's own takes no part in
    the pair term (a crease, a stripe broken by occlusion).

    References
    ----------
    Chen & Medioni (1992), point-to-plane residuals; Rusinkiewicz (2019), A symmetric
    objective function for ICP (the sum of the two normals); Triggs et al. (2000), Bundle
    adjustment -- a modern synthesis (Gauss-Newton with robust weights and priors);
    Cipolla & Giblin (2000), Visual motion of curves and surfaces (contour generators).
    """
    problem = _refine_problem(points, normals, origins, pairs, options=options,
                              profiles=profiles, active=active, fixed=fixed,
                              silhouettes=silhouettes, max_points=max_points)
    return _refine_from(problem, initial, options)


@dataclass
class _RefineProblem:
    """What :func:`refine_sweeps` computes before it iterates, the same from any start
    (the subsampled sweeps, the pair term's thinning and normals, the views' fields)."""

    P: list[np.ndarray]
    Nn: list[np.ndarray]
    O: list[np.ndarray]
    G: list[np.ndarray]
    red_idx: list[np.ndarray]
    pairs: list[tuple[int, int]]
    fields: list[_ViewField]
    act: list[int]
    fixed: list[int]
    index: dict[int, int]
    prior_sd: np.ndarray
    free: np.ndarray
    P_rim: list[np.ndarray]
    rim_info: list[dict[str, Any]]


def _refine_problem(points, normals, origins, pairs, *, options: AlignOptions, profiles,
                    active, fixed, silhouettes, max_points: int) -> _RefineProblem:
    o = options
    n_s = len(points)
    _check_refine_inputs(points, normals, origins, profiles, o)
    rng = np.random.default_rng(o.seed)
    act = sorted(set(range(n_s) if active is None else active))
    fixed = sorted(set(fixed or []) & set(act))
    fields = (_view_fields(silhouettes, _RIM_CELL_PX, 0.7)
              if silhouettes is not None and profiles is not None else [])
    P, Nn, O, G, full, noise = _refine_inputs(points, normals, origins, profiles,
                                              max_points, rng, scatter=bool(fields))
    red_idx = _pair_subsets(P, Nn, O, G, o)  # pair term on thinned copies
    pairs = [(int(i), int(j)) for i, j in pairs if i in act and j in act and i != j]
    P_rim, rim_info = _rim_points(P, full, noise, fields)
    index = {s: k for k, s in enumerate(act)}
    prior_sd = np.r_[np.full(3, np.radians(o.prior_deg)), np.full(3, o.prior_mm * 1e-3)]
    free = np.ones(6 * len(act), dtype=bool)
    for s in fixed:  # gauge: these sweeps keep their initial correction
        free[6 * index[s]:6 * index[s] + 6] = False
    return _RefineProblem(P, Nn, O, G, red_idx, pairs, fields, act, fixed, index, prior_sd,
                          free, P_rim, rim_info)


def _rim_points(P, full, noise: list, fields) -> tuple[list, list[dict[str, Any]]]:
    """The points the silhouette term meets the views' edges with: a sweep's measured
    points ``P``, or, where they scatter about their profiles in the views (their scatter
    ``noise`` over the views' median metres per pixel at them) by more than
    ``_RIM_NOISY_PX[0]``, moved toward the points fitted along their profiles
    (:func:`_profile_quadratic` over all of the sweep's points, ``full``: all points,
    profile keys, the indices of ``P``'s), all the way from ``_RIM_NOISY_PX[1]`` on; and
    per sweep what was measured and taken
    (``profile_noise_mm``, ``profile_noise_px``, ``rim_fit_share``; no scatter, no fit,
    where the profiles' points are not in order along them: :func:`_profiles_in_order`).

    Why: the term takes a profile's most outward point near the outline, and the most
    outward of noisy points lies outward of the surface. Laser speckle (front-end cells,
    contrast 0.5, exact poses): the points scatter 0.33-0.36 px about their profiles, the
    contour points lay +0.59 px beyond the true outline, and the alignment moved every
    sweep 0.24-0.27 mm away from its true pose (green: delivered points 0.196 mm from
    the surface at the median, 0.121 mm before the alignment). Fitted over 5 neighbours
    on either side: +0.05 px, 0.126 mm. Why not always: the clean cells' points scatter
    0.03-0.06 px, and there the most outward point's small outward bias offsets the
    edge's own, about 0.09 px inward (:func:`_outline_edge`); fitted, the green cell's
    sweeps moved (0.0274 -> 0.0317 mm; 0.0302 mm fitted over 2 neighbours), blended as
    here 0.0281 mm. A blob scanned at its true poses with 0.075 px of scatter (0.08 mm
    along the laser camera's rays): moved 0.07 mm with the measured points, 0.004-0.017
    mm blended (``tests/test_alignment_property.py``; ``benchmarks/README.md``, stop 64)."""
    P_rim, info = [], []
    for s in range(len(P)):
        m_per_px = []
        for f in fields if noise[s] is not None else []:  # no scatter: nothing to scale
            sub = P[s][:: max(1, len(P[s]) // 2000)]
            _, depth = _project(f, sub)
            depth = depth[depth > 0]
            if len(depth):
                m_per_px.append(float(f.camera.pixel_footprint(np.median(depth))))
        if noise[s] is None and fields:
            log.warning("sweep %d: its points are not in order along their profiles; the "
                        "silhouette term takes them as measured", s)
        px = noise[s] / float(np.median(m_per_px)) if m_per_px else None
        lo, hi = _RIM_NOISY_PX
        share = float(np.clip((px - lo) / (hi - lo), 0.0, 1.0)) if px is not None else 0.0
        P_rim.append(P[s])
        if share > 0:
            p_all, g_all, keep = full[s]
            fit = _profile_quadratic(p_all, g_all, keep, _RIM_FIT_HALF)
            P_rim[-1] = P[s] + share * (fit - P[s])
            log.info("sweep %d: its points scatter %.3f px about their profiles in the views "
                     "(%.4f mm): the silhouette term takes them %.0f %% of the way to their "
                     "fit along the profiles", s, px, noise[s] * 1e3, 100 * share)
        info.append({"profile_noise_mm": (round(noise[s] * 1e3, 5) if noise[s] is not None
                                          else None),
                     "profile_noise_px": round(px, 4) if px is not None else None,
                     "rim_fit_share": round(share, 3)})
    return P_rim, info


def _refine_from(pr: _RefineProblem, initial, o: AlignOptions) -> RefinementResult:
    """The Gauss-Newton iterations of :func:`refine_sweeps` from the rigid ``initial``
    corrections (None: the robot's poses), converted to rotations and sensor shifts at
    each active sweep's mean sensor position."""
    n_s = len(pr.P)
    rot = np.tile(np.eye(3), (n_s, 1, 1))
    trans = np.zeros((n_s, 3))
    if initial is not None:
        for s in pr.act:
            c = np.asarray(initial[s], dtype=np.float64)
            rot[s] = c[:3, :3]
            mean_o = pr.O[s].mean(axis=0) if len(pr.O[s]) else np.zeros(3)
            trans[s] = c[:3, 3] + c[:3, :3] @ mean_o - mean_o
    sigma_p = max(o.voxel_size_m, 1e-6)  # robust scale of the pair residuals (metres)
    sigma_s = 0.5                        # ... of the rim residuals (px)
    rot, trans, converged, it, rim_stats, degen, sigma_p, sigma_s = _iterate(
        rot, trans, sigma_p, sigma_s, pr.P, pr.Nn, pr.O, pr.G, pr.pairs, pr.red_idx,
        pr.fields, pr.act, pr.index, o, pr.prior_sd, pr.free, pr.P_rim)
    res = _refinement_result(rot, trans, converged, it, rim_stats, degen, pr.index, pr.act,
                             pr.fixed, pr.fields, sigma_s, sigma_p, pr.prior_sd, pr.P, pr.O)
    if pr.fields:
        for entry in res.per_sweep:
            entry.update(pr.rim_info[entry["sweep"]])
    return res
