"""Fine alignment of laser sweeps: symmetric point-to-plane ICP between overlapping sweeps,
then a pose graph (multiway registration) that spreads the pairwise constraints over all
sweeps.

The robot's poses already place every sweep in ``base`` to within its positioning error
(typically a few tenths of a millimetre); alignment removes the remaining misfit between
sweeps. It never replaces the robot's poses: it computes one small rigid *correction*
``C[s]`` per sweep, applied on the left, ``points_aligned = C[s] @ points_base`` (the
points of sweep ``s`` as the robot's poses placed them).

Method
------
1. Each sweep is thinned on a voxel grid (``voxel_size``) by keeping *one measured point
   per voxel* with its own normal, and, past ``max_points`` points, randomly subsampled
   with ``seed``. Averaging the points of a voxel (Open3D's ``voxel_down_sample``) was
   measured to bias the result: averaged points leave a curved surface.
2. For every pair of sweeps the *overlap* is the larger of the two fractions of points with
   a partner within ``max_corr_dist`` in the other sweep, at the robot's poses. Pairs with
   ``overlap >= min_overlap`` are registered from the identity (the robot's relative pose)
   by Open3D's *symmetric* point-to-plane ICP (Rusinkiewicz 2019), coarse to fine: the
   correspondence distance is halved from ``max_corr_dist`` down to
   ``max(voxel_size, max_corr_dist / 4)`` (at most three levels). Both choices were
   measured on the bumpy test surface of ``tests/test_registration.py``: plain
   point-to-plane ICP at a single distance left 0.1–0.5 degree errors (source points past
   the edge of the overlap pair with the target's border and pull; the point-to-plane
   residual between differently sampled curved surfaces is biased), the symmetric,
   coarse-to-fine variant 0.001–0.003 degree. A pairwise result is rejected if ICP has not
   converged (one more iteration at the finest distance still moves it by more than 1 % of
   ``voxel_size`` or 0.005 degrees), if its fitness falls below ``min_overlap``, or if the
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

All computations run in a frame centred on the centroid of all points (better conditioned
than ``base``, whose origin may be half a metre away); results are returned in ``base``.

References
----------
Besl, P. J. & McKay, N. D. (1992). A method for registration of 3-D shapes. IEEE PAMI 14(2).
Chen, Y. & Medioni, G. (1992). Object modelling by registration of multiple range images.
Image and Vision Computing 10(3) (point-to-plane ICP).
Rusinkiewicz, S. (2019). A symmetric objective function for ICP. ACM TOG 38(4).
Choi, S., Zhou, Q.-Y. & Koltun, V. (2015). Robust reconstruction of indoor scenes. CVPR
(pose graph with line-process pruning, as implemented in Open3D).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree

from .transforms import invert_transform, rotation_angle_deg

__all__ = ["AlignmentResult", "align_sweeps"]

log = logging.getLogger(__name__)

_MIN_POINTS = 10


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

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready summary (corrections as nested lists)."""
        return {
            "method": self.method,
            "gauge": self.gauge,
            "reference": int(self.reference),
            "corrections": self.corrections.tolist(),
            "pairs": [_jsonable(p) for p in self.pairs],
            "per_sweep": [_jsonable(p) for p in self.per_sweep],
        }


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


def _icp(src, tgt, max_corr_dist: float, fine_dist: float, init: np.ndarray,
         max_iterations: int):
    """Coarse-to-fine symmetric ICP; returns the result and the step one more iteration
    would still take (to judge convergence)."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    est = reg.TransformationEstimationSymmetric()
    crit = reg.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9,
                                      max_iteration=max_iterations)
    dists = [max_corr_dist]
    while dists[-1] / 2 >= fine_dist * (1 - 1e-9) and len(dists) < 3:
        dists.append(dists[-1] / 2)
    t = np.asarray(init, dtype=np.float64)
    res = None
    for d in dists:
        res = reg.registration_symmetric_icp(src, tgt, d, t, est, crit)
        t = np.asarray(res.transformation)
    one = reg.ICPConvergenceCriteria(relative_fitness=0.0, relative_rmse=0.0, max_iteration=1)
    nxt = reg.registration_symmetric_icp(src, tgt, dists[-1], t, est, one)
    return res, dists[-1], np.asarray(nxt.transformation) @ invert_transform(t)


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


def align_sweeps(
    points: list[np.ndarray],
    normals: list[np.ndarray],
    *,
    voxel_size: float = 0.5e-3,
    max_corr_dist: float = 2e-3,
    max_iterations: int = 50,
    max_correction_mm: float = 5.0,
    max_correction_deg: float = 3.0,
    min_overlap: float = 0.05,
    method: Literal["pose_graph", "sequential"] = "pose_graph",
    gauge: Literal["reference", "mean"] = "reference",
    max_points: int = 100_000,
    seed: int = 0,
) -> AlignmentResult:
    """Align laser sweeps to each other, starting from the robot's poses.

    Parameters
    ----------
    points : list of (N_s, 3) float64, metres
        Each sweep's points in ``base``, as placed by the robot's poses.
    normals : list of (N_s, 3) float64
        Unit normals of those points, oriented the same way in every sweep (toward the
        sensor, i.e. out of the object): symmetric ICP adds the two normals of a pair.
    voxel_size : float, metres
        Grid on which each sweep is thinned (one measured point per voxel) before
        registration; also the finest ICP correspondence distance (0 disables).
    max_corr_dist : float, metres
        Largest point-to-point distance of an ICP correspondence, and of the overlap test.
    max_iterations : int
        ICP iterations per registration.
    max_correction_mm, max_correction_deg : float
        Bounds on a sweep's correction (displacement of its centroid; rotation angle).
        Larger corrections are refused: the sweep stays at its robot pose, flagged.
    min_overlap : float in (0, 1]
        Smallest overlap (fraction of points with a partner) for a pair to be registered.
    method : {"pose_graph", "sequential"}
        Multiway pose-graph optimisation, or one sweep after another along the
        maximum-overlap spanning tree.
    gauge : {"reference", "mean"}
        What stays fixed: the reference sweep (most overlap), or the mean correction.
    max_points : int
        Cap on the points per sweep used for registration (random subsample with ``seed``).
    seed : int
        Seed of that subsample.

    Returns
    -------
    AlignmentResult

    Notes
    -----
    The method, the gauge and the guards are described in the module docstring.

    References
    ----------
    Chen & Medioni (1992) point-to-plane ICP; Choi, Zhou & Koltun (2015) pose graph.
    """
    import open3d as o3d

    pts_in, nrm_in = _check_inputs(points, normals)
    if method not in ("pose_graph", "sequential"):
        raise ValueError(f"method must be 'pose_graph' or 'sequential', got {method!r}")
    if gauge not in ("reference", "mean"):
        raise ValueError(f"gauge must be 'reference' or 'mean', got {gauge!r}")
    for name, val in (("max_corr_dist", max_corr_dist), ("max_correction_mm", max_correction_mm),
                      ("max_correction_deg", max_correction_deg)):
        if not val > 0:
            raise ValueError(f"{name} must be > 0, got {val}")
    if voxel_size < 0:
        raise ValueError(f"voxel_size must be >= 0, got {voxel_size}")
    if not 0 < min_overlap <= 1:
        raise ValueError(f"min_overlap must be in (0, 1], got {min_overlap}")
    if max_iterations < 1 or max_points < _MIN_POINTS:
        raise ValueError("max_iterations must be >= 1 and max_points >= 10, got "
                         f"{max_iterations} and {max_points}")

    n_sweeps = len(pts_in)
    corrections = np.tile(np.eye(4), (n_sweeps, 1, 1))
    if n_sweeps == 0:
        return AlignmentResult(corrections=corrections.reshape(0, 4, 4), method=method,
                               gauge=gauge)

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        return _align(pts_in, nrm_in, corrections, voxel_size=voxel_size,
                      max_corr_dist=max_corr_dist, max_iterations=max_iterations,
                      max_correction_mm=max_correction_mm,
                      max_correction_deg=max_correction_deg, min_overlap=min_overlap,
                      method=method, gauge=gauge, max_points=max_points, seed=seed)


def _align(pts_in, nrm_in, corrections, *, voxel_size, max_corr_dist, max_iterations,
           max_correction_mm, max_correction_deg, min_overlap, method, gauge, max_points,
           seed) -> AlignmentResult:
    import open3d as o3d

    reg = o3d.pipelines.registration
    rng = np.random.default_rng(seed)
    n_sweeps = len(pts_in)
    fine_dist = max(voxel_size, max_corr_dist / 4)
    nonempty = [p for p in pts_in if len(p)]
    centre = np.concatenate(nonempty).mean(axis=0) if nonempty else np.zeros(3)

    # --- 1. reduce, centre
    red = [_reduce(p - centre, n, voxel_size, max_points, rng) for p, n in zip(
        pts_in, nrm_in, strict=True)]
    clouds = [_to_o3d(p, n) for p, n in red]
    cents = [p.mean(axis=0) if len(p) else np.zeros(3) for p, _ in red]
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

    # --- 2. overlaps and pairwise ICP
    lo = [p.min(axis=0) - max_corr_dist if len(p) else None for p, _ in red]
    hi = [p.max(axis=0) + max_corr_dist if len(p) else None for p, _ in red]
    trees = [cKDTree(p) for p, _ in red]
    pairs: list[dict[str, Any]] = []
    edges: dict[tuple[int, int], dict[str, Any]] = {}
    eye = np.eye(4)
    for i in range(n_sweeps):
        for j in range(i + 1, n_sweeps):
            if not (usable[i] and usable[j]):
                continue
            if np.any(lo[i] > hi[j]) or np.any(lo[j] > hi[i]):
                continue
            f_ij = _fit(red[i], red[j], trees[j], eye, max_corr_dist)[0]
            f_ji = _fit(red[j], red[i], trees[i], eye, max_corr_dist)[0]
            overlap = float(max(f_ij, f_ji))
            if overlap <= 0.0:
                continue
            pair: dict[str, Any] = dict(i=i, j=j, overlap=overlap, fitness=float("nan"),
                                        rmse_mm=float("nan"), rmse_before_mm=float("nan"),
                                        converged=False, accepted=False,
                                        reason="", used=False, residual_mm=float("nan"),
                                        residual_deg=float("nan"))
            pairs.append(pair)
            if overlap < min_overlap:
                pair["reason"] = f"overlap {overlap:.3f} < min_overlap {min_overlap}"
                continue
            res, d_fine, step = _icp(clouds[i], clouds[j], max_corr_dist, fine_dist, eye,
                                     max_iterations)
            t = np.asarray(res.transformation).copy()  # maps sweep i onto sweep j
            info = np.asarray(reg.get_information_matrix_from_point_clouds(
                clouds[i], clouds[j], d_fine, t)).copy()
            fit = _fit(red[i], red[j], trees[j], t, max_corr_dist)[0]
            rmse = _fit(red[i], red[j], trees[j], t, d_fine)[1]
            pair.update(fitness=fit, rmse_mm=rmse * 1e3,
                        rmse_before_mm=_fit(red[i], red[j], trees[j], eye, d_fine)[1] * 1e3,
                        converged=_step_small(step, cents[i], voxel_size))
            rel_mm, rel_deg = _motion(t, cents[i])
            if not pair["converged"]:
                pair["reason"] = "ICP did not converge"
            elif fit < min_overlap:
                pair["reason"] = f"fitness {fit:.3f} < min_overlap {min_overlap}"
            elif rel_mm > 2 * max_correction_mm or rel_deg > 2 * max_correction_deg:
                pair["reason"] = (f"relative correction {rel_mm:.3f} mm / {rel_deg:.3f} deg "
                                  "exceeds twice the per-sweep bounds")
            else:
                pair["accepted"] = True
                edges[(i, j)] = dict(T=t, info=info, weight=overlap, pair=pair)

    # --- 3. reference: largest summed accepted overlap
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

    # --- 4. solve, refuse out-of-bounds sweeps one at a time, solve again
    sol: dict[int, np.ndarray] = {}
    for _ in range(n_sweeps + 1):
        act_edges = [(i, j, e["weight"]) for (i, j), e in edges.items()
                     if i in active and j in active]
        order, parent, tree = _max_spanning_tree(n_sweeps, act_edges, reference)
        connected = set(order)
        for s in sorted(active - connected):
            active.discard(s)
            per_sweep[s].update(flagged=True, reason=(
                f"not connected to the reference sweep {reference} through accepted pairs"))
        if method == "pose_graph":
            sol, used = _solve_pose_graph(order, edges, tree, reference, max_corr_dist)
        else:
            sol, used = _solve_sequential(order, parent, edges, clouds, red, max_corr_dist,
                                          fine_dist, max_iterations, voxel_size, per_sweep)
            active &= set(sol)
        if gauge == "mean" and len(sol) > 1:
            m = _mean_transform(np.stack(list(sol.values())))
            m_inv = invert_transform(m)
            sol = {s: m_inv @ t for s, t in sol.items()}
        worst, worst_ratio = -1, 1.0
        for s in sol:
            mm, deg = _motion(sol[s], cents[s])
            ratio = max(mm / max_correction_mm, deg / max_correction_deg)
            if ratio > worst_ratio and (s != reference or gauge == "mean"):
                worst, worst_ratio = s, ratio
        if worst < 0:
            break
        mm, deg = _motion(sol[worst], cents[worst])
        per_sweep[worst].update(flagged=True, reason=(
            f"correction {mm:.3f} mm / {deg:.3f} deg exceeds the bounds "
            f"{max_correction_mm} mm / {max_correction_deg} deg"))
        active.discard(worst)
        sol = {}
        if not active:
            break
        if worst == reference:
            reference = int(max(active, key=lambda s: (score[s], -s)))

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
             n_sweeps, method, reference, len(edges), n_flag)
    return AlignmentResult(corrections=corrections, pairs=pairs, per_sweep=per_sweep,
                           reference=reference, method=method, gauge=gauge)


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
        res, _, step = _icp(clouds[s], _to_o3d(tgt_p, tgt_n), max_corr_dist, fine_dist, init,
                            max_iterations)
        if not _step_small(step, red[s][0].mean(axis=0), voxel_size):
            per_sweep[s].update(flagged=True, reason="sequential ICP did not converge")
            continue
        sol[s] = np.asarray(res.transformation).copy()
        used.update((min(s, t), max(s, t)) for t in nbrs)
    return sol, used
