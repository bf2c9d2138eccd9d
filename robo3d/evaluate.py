"""Evaluation against ground truth: distances to the true surface, completeness, volume
overlap of the visual hull, and pose errors.

Conventions
-----------
- Distances are computed in metres and *reported in millimetres*: every statistics dict
  has the keys ``mean_mm``, ``median_mm``, ``rms_mm``, ``p95_mm``, ``max_mm`` and ``n``
  (the number of distances). With ``n == 0`` the statistics are ``None`` (valid JSON).
- **Accuracy** (``cloud_accuracy``, ``mesh_accuracy``) measures reconstruction -> truth:
  how far what we built lies from the true surface. **Completeness** measures truth ->
  reconstruction: the fraction of the true surface that lies within a threshold of what we
  built (Seitz et al. 2006, Aanæs et al. 2016).
- The face of the object resting on the table, below the workspace box's ``min z``, can
  never be observed. Pass the workspace box as ``region`` to :func:`completeness` and
  :func:`volume_iou` so that only the true surface (or volume) *inside the box* counts;
  surface samples outside the box are dropped before the fractions are computed. The
  number kept is reported.
- Surfaces are sampled uniformly by area with an explicit seed, so the numbers are
  reproducible.
- **Mask IoU** (:func:`silhouette_iou`): each view's silhouette against the recording's
  true one (``ground_truth/silhouettes/NNN.png``, ``NNN`` the 0-based index of the image
  on the views topic in time order, the order the silhouettes stage keeps). An
  attachment that is missing, does not decode, is not 8-bit or has another size than
  its view is skipped with the reason; the other views are still scored. Two empty
  masks agree (IoU 1).
- Distance and inside/outside queries use Open3D's ``RaycastingScene`` (Embree), which
  works in float32: coordinates are shifted to the truth mesh's centroid first, so the
  float32 resolution is that of the object's size (~0.01 µm for a 0.1 m object), not of
  its distance from the robot base.

References
----------
Seitz, S. M., Curless, B., Diebel, J., Scharstein, D. & Szeliski, R. (2006). A comparison
and evaluation of multi-view stereo reconstruction algorithms. CVPR.
Aanæs, H., Jensen, R. R., Vogiatzis, G., Tola, E. & Dahl, A. B. (2016). Large-scale data
for multiple-view stereopsis. IJCV 120.
"""

from __future__ import annotations

import contextlib
import logging
from typing import Any

import numpy as np

from .checks import check_mesh, check_points, check_region
from .transforms import rotation_angle_deg

__all__ = [
    "TruthSurface",
    "sample_surface",
    "distance_stats",
    "cloud_accuracy",
    "mesh_accuracy",
    "completeness",
    "volume_iou",
    "silhouette_iou",
    "frame_displacement",
    "TRUE_SILHOUETTES",
    "pose_error",
    "batch_rows",
    "write_batch_table",
]

log = logging.getLogger(__name__)


@contextlib.contextmanager
def open3d_threads(n: int):
    """Open3D's thread count raised to ``n`` inside the block, for queries whose results do
    not depend on it: closest-point distances (each point's query is independent, no
    reduction; the stages pin Open3D to one thread for ICP's and TSDF's sums, see
    :func:`robo3d.stages.common.pin_open3d_threads`). ``n`` <= 1 changes nothing."""
    import open3d as o3d

    before = o3d.utility.get_max_threads()
    if int(n) > 1:
        o3d.utility.set_max_threads(int(n))
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)


def _in_box(p: np.ndarray, box: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray:
    if box is None:
        return np.ones(len(p), dtype=bool)
    return np.all((p >= box[0]) & (p <= box[1]), axis=1)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, *, seed: int = 0,
                   return_faces: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Points spread uniformly over a triangle mesh's area.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int
    n : int
        Number of samples.
    seed : int
        Seed of the random generator (reproducible samples).
    return_faces : bool
        Also return the face of each sample.

    Returns
    -------
    (n, 3) float64, metres
        Empty (0, 3) when the mesh has no area.
    (n,) int64
        With ``return_faces``: the face each sample lies on.
    """
    v, f = check_mesh(vertices, faces)
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    none = (np.zeros((0, 3)), np.zeros(0, np.int64))
    if len(f) == 0 or n == 0:
        return none if return_faces else none[0]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = area.sum()
    if not total > 0:
        return none if return_faces else none[0]
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(f), size=n, p=area / total)
    r1 = np.sqrt(rng.random(n))
    r2 = rng.random(n)
    w_a, w_b, w_c = 1.0 - r1, r1 * (1.0 - r2), r1 * r2
    pts = w_a[:, None] * a[tri] + w_b[:, None] * b[tri] + w_c[:, None] * c[tri]
    return (pts, tri.astype(np.int64)) if return_faces else pts


class TruthSurface:
    """A ground-truth triangle mesh for distance, sampling and inside/outside queries.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
        The truth mesh in ``base``.
    faces : (F, 3) int
        Its triangles. ``inside`` needs it to be watertight.

    Notes
    -----
    Built on Open3D's ``RaycastingScene``; queries are shifted to the mesh's centroid to
    keep float32 precision (see the module docstring).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        import open3d as o3d

        v, f = check_mesh(vertices, faces)
        if len(f) == 0:
            raise ValueError("the truth mesh has no faces")
        self.vertices = v
        self.faces = f
        self._shift = v.mean(axis=0)
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor((v - self._shift).astype(np.float32)),
            o3d.core.Tensor(f.astype(np.uint32)),
        )

    def _q(self, points: np.ndarray):
        import open3d as o3d

        return o3d.core.Tensor((points - self._shift).astype(np.float32))

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance of each point to the truth surface.

        Parameters
        ----------
        points : (N, 3) float64, metres

        Returns
        -------
        (N,) float64, metres
        """
        p = check_points(points)
        if len(p) == 0:
            return np.zeros(0)
        return self._scene.compute_distance(self._q(p)).numpy().astype(np.float64)

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Whether each point lies inside the (watertight) truth mesh.

        Parameters
        ----------
        points : (N, 3) float64, metres

        Returns
        -------
        (N,) bool
            Majority vote of three ray-parity tests (robust to rays grazing an edge).
        """
        p = check_points(points)
        if len(p) == 0:
            return np.zeros(0, dtype=bool)
        occ = self._scene.compute_occupancy(self._q(p), nsamples=3)
        return occ.numpy() > 0.5

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """``n`` points uniform over the truth surface's area (seeded): (n, 3) metres."""
        return sample_surface(self.vertices, self.faces, n, seed=seed)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min (3,), max (3,)) corners of the truth mesh's bounding box, metres."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


def distance_stats(d: np.ndarray) -> dict[str, Any]:
    """Summary statistics of distances, reported in millimetres.

    Parameters
    ----------
    d : (N,) float, metres
        Distances (non-finite values are an error).

    Returns
    -------
    dict
        ``mean_mm``, ``median_mm``, ``rms_mm``, ``p95_mm``, ``max_mm`` (floats, or None
        when ``n == 0``) and ``n`` (int).
    """
    d = np.asarray(d, dtype=np.float64).ravel()
    if not np.all(np.isfinite(d)):
        raise ValueError("distances contain non-finite values")
    keys = ("mean_mm", "median_mm", "rms_mm", "p95_mm", "max_mm")
    if d.size == 0:
        return {**{k: None for k in keys}, "n": 0}
    mm = d * 1e3
    return {
        "mean_mm": float(mm.mean()),
        "median_mm": float(np.median(mm)),
        "rms_mm": float(np.sqrt(np.mean(mm**2))),
        "p95_mm": float(np.percentile(mm, 95)),
        "max_mm": float(mm.max()),
        "n": int(d.size),
    }


def cloud_accuracy(points: np.ndarray, truth: TruthSurface, *,
                   thresholds_mm: tuple[float, ...] = (0.1, 0.5, 1.0)) -> dict[str, Any]:
    """Distances of measured points to the true surface.

    Parameters
    ----------
    points : (N, 3) float64, metres
    truth : TruthSurface
    thresholds_mm : tuple of float
        Also report the fraction of points within each of these distances.

    Returns
    -------
    dict
        :func:`distance_stats` keys plus ``within_mm``: {"0.1": fraction, ...}.
    """
    d = truth.distance(points)
    out = distance_stats(d)
    out["within_mm"] = _fractions(d, thresholds_mm)
    return out


def _fractions(d: np.ndarray, thresholds_mm: tuple[float, ...]) -> dict[str, float | None]:
    return {f"{t:g}": (float(np.mean(d <= t * 1e-3)) if d.size else None)
            for t in thresholds_mm}


def mesh_accuracy(vertices: np.ndarray, faces: np.ndarray, truth: TruthSurface, *,
                  n_samples: int = 200_000, seed: int = 0,
                  thresholds_mm: tuple[float, ...] = (0.1, 0.5, 1.0),
                  region: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, Any]:
    """Distances from a reconstructed mesh's surface to the true surface.

    The reconstruction is sampled uniformly by area (``n_samples`` points, ``seed``), so
    that large triangles weigh as much as the area they cover.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int
    truth : TruthSurface
    n_samples : int
    seed : int
    thresholds_mm : tuple of float
    region : (box_min (3,), box_max (3,)), metres, optional
        Score only the reconstruction inside this box (e.g. above the closure of the
        face resting on the table, which no sensor sees).

    Returns
    -------
    dict
        :func:`distance_stats` keys (``n == 0`` for an empty mesh), ``within_mm`` and
        ``fraction_scored`` (of the samples, those in the region).
    """
    box = check_region(region)
    p = sample_surface(vertices, faces, n_samples, seed=seed)
    inb = _in_box(p, box)
    d = truth.distance(p[inb])
    out = distance_stats(d)
    out["within_mm"] = _fractions(d, thresholds_mm)
    out["fraction_scored"] = float(inb.mean()) if len(p) else None
    return out


def completeness(vertices: np.ndarray, faces: np.ndarray, truth: TruthSurface, *,
                 thresholds_mm: tuple[float, ...] = (0.1, 0.5, 1.0),
                 n_samples: int = 200_000,
                 region: tuple[np.ndarray, np.ndarray] | None = None,
                 seed: int = 0) -> dict[str, Any]:
    """Fraction of the true surface that the reconstruction covers.

    The truth is sampled uniformly by area; each sample's distance to the reconstructed
    mesh is compared with each threshold.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
        The reconstruction (may be empty: completeness 0).
    faces : (F, 3) int
    truth : TruthSurface
    thresholds_mm : tuple of float
    n_samples : int
        Samples drawn on the whole truth surface (before ``region`` drops some).
    region : (box_min (3,), box_max (3,)), metres, optional
        Count only the true surface inside this box, e.g. the workspace box, which leaves
        out the face resting on the table (unobservable).
    seed : int

    Returns
    -------
    dict
        ``within_mm``: {"0.1": fraction, ...}; ``n_samples`` (samples counted, i.e. in the
        region); ``distance``: :func:`distance_stats` of truth -> reconstruction (None
        values when the reconstruction is empty).
    """
    box = check_region(region)
    v, f = check_mesh(vertices, faces)
    samples = truth.sample(n_samples, seed=seed)
    samples = samples[_in_box(samples, box)]
    if len(f) == 0 or len(samples) == 0:
        fr = {f"{t:g}": (0.0 if len(samples) else None) for t in thresholds_mm}
        return {"within_mm": fr, "n_samples": int(len(samples)),
                "distance": distance_stats(np.zeros(0))}
    recon = TruthSurface(v, f)
    d = recon.distance(samples)
    return {"within_mm": _fractions(d, thresholds_mm), "n_samples": int(len(samples)),
            "distance": distance_stats(d)}


def volume_iou(occupancy: np.ndarray, origin: np.ndarray, voxel_size: float,
               truth: TruthSurface, *,
               region: tuple[np.ndarray, np.ndarray] | None = None) -> float:
    """Intersection over union of an occupancy grid and the truth's volume.

    Both volumes are sampled at the voxel centres: a voxel is in the truth when its centre
    is inside the (watertight) truth mesh. Truth volume outside the grid is not counted.

    Parameters
    ----------
    occupancy : (nx, ny, nz) bool
        E.g. the visual hull.
    origin : (3,) float64, metres
        Centre of voxel (0, 0, 0).
    voxel_size : float, metres
    truth : TruthSurface
    region : (box_min (3,), box_max (3,)), metres, optional
        Count only voxels whose centres lie in this box.

    Returns
    -------
    float
        |H ∩ T| / |H ∪ T| over voxel centres; 0.0 when both are empty.
    """
    occ = np.asarray(occupancy)
    if occ.ndim != 3 or occ.dtype != bool:
        raise ValueError(f"occupancy must be (nx, ny, nz) bool, got {occ.shape} {occ.dtype}")
    origin = np.asarray(origin, dtype=np.float64)
    if origin.shape != (3,):
        raise ValueError(f"origin must be (3,), got {origin.shape}")
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    box = check_region(region)
    # Only voxels inside the truth's bounding box can be inside the truth.
    tmin, tmax = truth.bounds
    lo = np.maximum(np.floor((tmin - origin) / voxel_size).astype(int), 0)
    hi = np.minimum(np.ceil((tmax - origin) / voxel_size).astype(int) + 1, occ.shape)
    truth_occ = np.zeros_like(occ)
    if np.all(hi > lo):
        axes = [np.arange(lo[k], hi[k]) * voxel_size + origin[k] for k in range(3)]
        gx, gy, gz = np.meshgrid(*axes, indexing="ij")
        centres = np.stack([gx.ravel(), gy.ravel(), gz.ravel()], axis=1)
        truth_occ[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = truth.inside(centres).reshape(
            gx.shape)
    mask = np.ones_like(occ)
    if box is not None:
        axes = [np.arange(occ.shape[k]) * voxel_size + origin[k] for k in range(3)]
        inb = [(a >= box[0][k]) & (a <= box[1][k]) for k, a in enumerate(axes)]
        mask = inb[0][:, None, None] & inb[1][None, :, None] & inb[2][None, None, :]
    inter = np.count_nonzero(occ & truth_occ & mask)
    union = np.count_nonzero((occ | truth_occ) & mask)
    return float(inter / union) if union else 0.0


#: Prefix of the true silhouettes among a recording's attachments.
TRUE_SILHOUETTES = "ground_truth/silhouettes/"


def _decode_truth_mask(data: bytes, shape: tuple[int, int], rectify=None
                       ) -> tuple[np.ndarray | None, str]:
    """A true silhouette (object > 127) from PNG bytes, or None and why not; with
    ``rectify`` (a :class:`~robo3d.camera.Rectifier`) resampled as its view was."""
    import cv2

    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        return None, f"does not decode ({exc.msg.strip() if hasattr(exc, 'msg') else exc})"
    if img is None:
        return None, f"does not decode as an image ({len(data)} bytes)"
    if img.dtype != np.uint8:
        return None, f"is {img.dtype}, expected 8-bit"
    if img.ndim == 3:  # accepted: a grey mask saved as colour
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else
                           cv2.COLOR_BGR2GRAY)
    if img.shape != shape:
        return None, (f"is {img.shape[1]}x{img.shape[0]} px, the view is "
                      f"{shape[1]}x{shape[0]}")
    if rectify is not None:
        img = rectify(img)
    return img > 127, ""


def silhouette_iou(masks: list[np.ndarray], attachments: dict[str, bytes], *,
                   prefix: str = TRUE_SILHOUETTES, rectify: list | None = None
                   ) -> dict[str, Any]:
    """Intersection over union of each view's silhouette with the true one.

    Parameters
    ----------
    masks : list of N (H_i, W_i) bool
        The silhouettes, in the order of the views (time order on the views topic).
    attachments : dict of str -> bytes
        The recording's attachments; ``<prefix>NNN.png`` is the true silhouette of view
        ``NNN`` (0-based), 8-bit, object > 127, the view's size.
    prefix : str
    rectify : list of N Rectifier or None, optional
        Per view, how its image was resampled before it was segmented (a
        ``rational_polynomial`` camera, :class:`robo3d.camera.Rectifier`): its true
        silhouette, drawn on the raw image, is resampled alike.

    Returns
    -------
    dict
        ``per_view``: one entry per view, ``{"view", "iou", "mask_px", "truth_px",
        "missed_px", "spurious_px"}`` or ``{"view", "iou": None, "skipped": reason}``;
        ``mean`` and ``min`` (over the scored views, None if none), ``worst_view``,
        ``n_views``, ``n_scored``, ``n_truth`` (true silhouettes attached),
        ``skipped`` (view -> reason, as strings), ``unmatched`` (attachment names that
        name no view, with why).
    """
    import re

    truth: dict[int, bytes] = {}
    unmatched: dict[str, str] = {}
    for name, data in attachments.items():
        if not name.startswith(prefix):
            continue
        m = re.fullmatch(r"(\d+)\.png", name[len(prefix):], flags=re.IGNORECASE)
        if m is None:
            unmatched[name] = "not NNN.png"
        elif int(m.group(1)) >= len(masks):
            unmatched[name] = f"names view {int(m.group(1))}, the recording has {len(masks)}"
        elif int(m.group(1)) in truth:
            unmatched[name] = f"a second true silhouette of view {int(m.group(1))}"
        else:
            truth[int(m.group(1))] = data
    per_view: list[dict[str, Any]] = []
    skipped: dict[str, str] = {}
    for i, mask in enumerate(masks):
        mask = np.asarray(mask, dtype=bool)
        if i not in truth:
            reason = f"no {prefix}{i:03d}.png"
            t = None
        else:
            t, reason = _decode_truth_mask(truth[i], mask.shape,
                                           rectify[i] if rectify is not None else None)
        if t is None:
            per_view.append({"view": i, "iou": None, "skipped": reason})
            skipped[str(i)] = reason
            continue
        inter = int(np.count_nonzero(mask & t))
        union = int(np.count_nonzero(mask | t))
        per_view.append({"view": i, "iou": float(inter / union) if union else 1.0,
                         "mask_px": int(np.count_nonzero(mask)),
                         "truth_px": int(np.count_nonzero(t)),
                         "missed_px": int(np.count_nonzero(t & ~mask)),
                         "spurious_px": int(np.count_nonzero(mask & ~t))})
    scored = [(v["iou"], v["view"]) for v in per_view if v["iou"] is not None]
    worst = min(scored) if scored else None
    return {"per_view": per_view,
            "mean": float(np.mean([s[0] for s in scored])) if scored else None,
            "min": worst[0] if worst else None,
            "worst_view": worst[1] if worst else None,
            "n_views": len(masks), "n_scored": len(scored), "n_truth": len(truth),
            "skipped": skipped, "unmatched": unmatched}


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[Any, Any]:
    """Translation and rotation error between estimated and true poses.

    Parameters
    ----------
    T_est, T_true : (4, 4) or (N, 4, 4) float64
        Rigid transforms (translations in metres).

    Returns
    -------
    translation_mm : float or (N,) float64
        ``|t_est - t_true|`` in millimetres (distance between the two frame origins).
    rotation_deg : float or (N,) float64
        Angle of ``R_true^T R_est`` in degrees.
    """
    a = np.asarray(T_est, dtype=np.float64)
    b = np.asarray(T_true, dtype=np.float64)
    if a.shape[-2:] != (4, 4) or a.shape != b.shape or a.ndim not in (2, 3):
        raise ValueError(f"T_est and T_true must both be (4, 4) or (N, 4, 4), got {a.shape} "
                         f"and {b.shape}")
    t = np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1) * 1e3
    r = rotation_angle_deg(np.swapaxes(b[..., :3, :3], -1, -2) @ a[..., :3, :3])
    if a.ndim == 2:
        return float(t), float(r)
    return t, r


def frame_displacement(points_base: np.ndarray, frame_index: np.ndarray,
                       T_used: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What each frame's pose error does to that frame's own points.

    A laser frame's points are triangulated in the camera and placed in ``base`` with the
    pose the pipeline used for it (``T_used``: the robot's reported pose at the image's
    stamp, times the alignment's correction at that frame); placed with the true pose at
    the frame's exposure (``T_true``) they would be ``T_true T_used^-1`` times where they
    are. The error is the largest displacement of a frame's points and the angle of that
    transform.

    Parameters
    ----------
    points_base : (N, 3) float64, metres
        The points as placed (with ``T_used``).
    frame_index : (N,) int
        Each point's frame, an index into ``T_used`` and ``T_true``.
    T_used, T_true : (F, 4, 4) float64
        ``base -> camera`` of each frame: as used, and the truth at its exposure.

    Returns
    -------
    displacement_mm : (F,) float64
        Largest displacement of a frame's points (NaN for a frame without points).
    rotation_deg : (F,) float64
        Rotation angle of the frame's pose error.
    """
    p = check_points(points_base, "points_base")
    f = np.asarray(frame_index, dtype=np.int64).reshape(-1)
    a = np.asarray(T_used, dtype=np.float64)
    b = np.asarray(T_true, dtype=np.float64)
    if a.ndim != 3 or a.shape[1:] != (4, 4) or a.shape != b.shape:
        raise ValueError(f"T_used and T_true must both be (F, 4, 4), got {a.shape} and {b.shape}")
    if f.size != len(p) or (f.size and (f.min() < 0 or f.max() >= len(a))):
        raise ValueError(f"frame_index must give one frame in 0..{len(a) - 1} per point")
    # D_f = T_true_f T_used_f^-1 maps the placed points to the true ones
    R_used_T = np.swapaxes(a[:, :3, :3], 1, 2)
    R = b[:, :3, :3] @ R_used_T
    t = b[:, :3, 3] - np.einsum("fij,fj->fi", R, a[:, :3, 3])
    moved = np.einsum("nij,nj->ni", R[f], p) + t[f]
    d = np.linalg.norm(moved - p, axis=1) * 1e3
    disp = np.full(len(a), -np.inf)
    np.maximum.at(disp, f, d)
    disp[~np.isfinite(disp)] = np.nan
    return disp, rotation_angle_deg(R)


_STAGES = ("silhouettes", "carve", "stripes", "triangulate", "align", "fuse", "simplify",
           "evaluate")


def _get(d: Any, *keys: str) -> Any:
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return None
        d = d[k]
    return d


def batch_rows(metrics: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One flat row per recording from its ``metrics.json`` (missing values None).

    Parameters
    ----------
    metrics : list of dict
        The recordings' metrics, as written by the evaluate stage.

    Returns
    -------
    list of dict
        Keys: ``recording``, ``hull_iou``, ``mask_iou_mean`` and ``mask_iou_min``
        (silhouettes against the true ones), ``views_left_out`` (how many views the
        agreement check left out of the carve), ``pose_before_mm`` / ``pose_before_deg``
        (worst sweep, displacement at the object / rotation), ``pose_after_mm``,
        ``pose_after_flange_mm``, ``pose_after_deg``, ``mesh_median_mm``,
        ``mesh_p95_mm``, ``complete_<t>mm`` per threshold, ``laser_fraction``,
        ``faces``, ``hausdorff_mm``, ``total_s``, ``<stage>_s`` and ``<stage>_mb`` (peak
        resident memory) per stage.
    """
    rows = []
    for m in metrics:
        ev = m.get("evaluation") or {}
        row: dict[str, Any] = {"recording": m.get("name"),
                               "hull_iou": ev.get("hull_volume_iou"),
                               "mask_iou_mean": _get(ev, "mask_iou", "mean"),
                               "mask_iou_min": _get(ev, "mask_iou", "min"),
                               "views_left_out": (None if m.get("views_left_out") is None
                                                  else len(m["views_left_out"])),
                               "pose_before_mm": _get(ev, "poses", "worst_before_obj_mm"),
                               "pose_before_deg": _get(ev, "poses", "worst_before_deg"),
                               "pose_after_mm": _get(ev, "poses", "worst_after_obj_mm"),
                               "pose_after_flange_mm": _get(ev, "poses", "worst_after_mm"),
                               "pose_after_deg": _get(ev, "poses", "worst_after_deg"),
                               "mesh_median_mm": _get(ev, "mesh", "median_mm"),
                               "mesh_p95_mm": _get(ev, "mesh", "p95_mm")}
        for t, v in (_get(ev, "mesh", "completeness", "within_mm") or {}).items():
            row[f"complete_{t}mm"] = v
        row["laser_fraction"] = _get(m, "surface_sources", "laser_area_fraction")
        row["faces"] = _get(m, "stages", "simplify", "faces_out")
        h = _get(m, "stages", "simplify", "hausdorff_max_m")
        row["hausdorff_mm"] = None if h is None else h * 1e3
        row["total_s"] = _get(m, "timings", "total_seconds")
        for st in _STAGES:
            row[f"{st}_s"] = _get(m, "timings", st, "seconds")
            row[f"{st}_mb"] = _get(m, "timings", st, "max_rss_mb")
        rows.append(row)
    return rows


def write_batch_table(metrics_paths: list[str], tsv_path: str, html_path: str | None) -> None:
    """Write the batch table of several recordings' ``metrics.json`` as TSV and HTML.

    Parameters
    ----------
    metrics_paths : list of str
    tsv_path, html_path : str
        Outputs (written atomically). The TSV's columns are :func:`batch_rows`' keys (for
        tools); ``html_path`` None writes no HTML (the workflow's ``batch.html``, with
        the columns named in words, is :func:`robo3d.overview.batch_html`'s).
    """
    import html
    import json

    from .atomic import atomic_path

    metrics = []
    for p in metrics_paths:
        with open(p, encoding="utf-8") as f:
            metrics.append(json.load(f))
    rows = batch_rows(metrics)
    cols: list[str] = []
    for r in rows:
        cols += [k for k in r if k not in cols]

    def fmt(v: Any) -> str:
        if v is None:
            return ""
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    with atomic_path(tsv_path) as tmp:
        lines = ["\t".join(cols)] + ["\t".join(fmt(r.get(c)) for c in cols) for r in rows]
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    if html_path is None:
        return
    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(fmt(r.get(c)))}</td>" for c in cols)
                   + "</tr>" for r in rows)
    page = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>robo3d batch</title>"
            "<style>body{font-family:sans-serif}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:3px 6px;text-align:right}"
            "th{background:#eee}</style></head><body><h1>robo3d batch: "
            f"{len(rows)} recording(s)</h1><p>Mask IoU: the silhouettes against the "
            "recording's true ones, mean and worst view; views left out: by the carve's "
            "agreement check. Pose errors: worst sweep, displacement of "
            "its points (mm) and rotation (deg); mesh: distance of the final mesh to the "
            "true surface; complete: fraction of the true surface within the threshold; "
            "times in seconds, memory in MB (peak resident).</p>"
            f"<table><tr>{head}</tr>{body}</table></body></html>\n")
    with atomic_path(html_path) as tmp:
        tmp.write_text(page, encoding="utf-8")
