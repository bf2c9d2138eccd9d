"""The typed artefacts that the stages hand each other, each with its own save and load.

One place for what a stage writes and the next reads, so that a file's layout is defined
once: the silhouettes (``silhouettes.npz``), the visual hull (``hull.npz``, a
:class:`~robo3d.grid.VoxelGrid`), the stripes (``stripes.npz``) and the sweep clouds
(``clouds.npz``, ``aligned.npz``). Every save is atomic (:mod:`robo3d.atomic`); every load
checks what it reads and names the file when something is missing or malformed.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .atomic import save_npz
from .grid import VoxelGrid  # noqa: F401 - the visual hull's artefact, re-exported

# --- silhouettes (silhouettes.npz) ---------------------------------------------------

# --- visual hull (hull.npz) ----------------------------------------------------------
# The hull's artefact is robo3d.grid.VoxelGrid itself (imported above): VoxelGrid.save_npz
# writes hull.npz atomically (occupancy, origin, voxel_size, frame, and the carve's
# extras: carving, views_used, views_left_out, dicts as JSON strings);
# VoxelGrid.load_npz(path, return_extra=True) reads it back and names the file when it
# is not a voxel grid. Its home is robo3d.grid, beside make_grid, so that the carvers
# (robo3d.carving, robo3d.octree) share it without importing each other.

# --- stripes (stripes.npz) -----------------------------------------------------------

# --- sweep clouds (clouds.npz, aligned.npz) ------------------------------------------
_CLOUDS_FORMAT = "robo3d.sweep_clouds/1"


@dataclass
class SweepCloud:
    """The points triangulated from one sweep, in ``base``
    (:func:`robo3d.triangulation.triangulate_sweep`; aligned by the ``align`` stage).

    Attributes
    ----------
    points_base : (N, 3) float64, metres
    normals_base : (N, 3) float64
        Unit normals, oriented toward ``sensor_origin_base``.
    frame_index : (N,) int64
        Index of the laser frame each point came from (as given to
        :func:`~robo3d.triangulation.triangulate_sweep`).
    confidence : (N,) float64 in [0, 1]
    sweep : int
        The sweep's index in the recording.
    sensor_origin_base : (N, 3) float64, metres
        Camera centre at the point's frame (its line of sight ends at the point).
    report : dict
        What the triangulation measured (JSON-serialisable).
    """

    points_base: np.ndarray
    normals_base: np.ndarray
    frame_index: np.ndarray
    confidence: np.ndarray
    sweep: int
    sensor_origin_base: np.ndarray
    report: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points_base = np.asarray(self.points_base, dtype=np.float64).reshape(-1, 3)
        n = len(self.points_base)
        self.normals_base = np.asarray(self.normals_base, dtype=np.float64).reshape(-1, 3)
        self.sensor_origin_base = np.asarray(self.sensor_origin_base,
                                             dtype=np.float64).reshape(-1, 3)
        self.frame_index = np.asarray(self.frame_index, dtype=np.int64).reshape(-1)
        self.confidence = np.asarray(self.confidence, dtype=np.float64).reshape(-1)
        for name in ("normals_base", "sensor_origin_base", "frame_index", "confidence"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"SweepCloud.{name} must have {n} rows like points_base, "
                                 f"got {len(getattr(self, name))}")
        self.sweep = int(self.sweep)

    def __len__(self) -> int:
        return len(self.points_base)


def save_clouds_npz(path: str | os.PathLike[str], clouds: Sequence[SweepCloud], *,
                    corrections: np.ndarray | None = None) -> None:
    """Write sweep clouds to one NPZ file, atomically.

    The clouds are concatenated (``cloud`` gives each point's cloud); the reports are
    stored as JSON text, so that the file loads without pickle.

    Parameters
    ----------
    path : str or path-like
        Target file; written to a temporary file in the same directory, then renamed.
    clouds : sequence of SweepCloud
    corrections : (K, 4, 4) float64, optional
        One rigid correction per cloud (the alignment's), stored as ``corrections``.
    """
    import json

    clouds = list(clouds)
    n = [len(c) for c in clouds]

    def _cat(name: str, shape: tuple[int, ...], dtype: type) -> np.ndarray:
        if not clouds:
            return np.zeros(shape, dtype=dtype)
        return np.concatenate([getattr(c, name) for c in clouds]).astype(dtype)

    arrays = {
        "format": np.array(_CLOUDS_FORMAT),
        "frame": np.array("base"),
        "points_base": _cat("points_base", (0, 3), np.float64),
        "normals_base": _cat("normals_base", (0, 3), np.float64),
        "frame_index": _cat("frame_index", (0,), np.int64),
        "confidence": _cat("confidence", (0,), np.float64),
        "sensor_origin_base": _cat("sensor_origin_base", (0, 3), np.float64),
        "cloud": np.repeat(np.arange(len(clouds), dtype=np.int64), n),
        "sweeps": np.array([c.sweep for c in clouds], dtype=np.int64),
        "reports_json": np.array(json.dumps([c.report for c in clouds])),
    }
    if corrections is not None:
        corr = np.asarray(corrections, dtype=np.float64)
        if corr.shape != (len(clouds), 4, 4):
            raise ValueError(f"corrections must be (K, 4, 4) with K={len(clouds)} clouds, "
                             f"got shape {corr.shape}")
        arrays["corrections"] = corr
    save_npz(path, **arrays)


def load_clouds_npz(path: str | os.PathLike[str]) -> list[SweepCloud]:
    """Read the sweep clouds written by :func:`save_clouds_npz`, in the order they were
    saved (a ValueError naming the file when it is not such a file)."""
    import json

    with np.load(path, allow_pickle=False) as z:
        fmt = str(z["format"]) if "format" in z.files else ""
        if fmt != _CLOUDS_FORMAT:
            raise ValueError(f"{path}: not a robo3d sweep-cloud file (format {fmt!r}, "
                             f"expected {_CLOUDS_FORMAT!r})")
        d = {k: z[k] for k in z.files}
    reports = json.loads(str(d["reports_json"]))
    out = []
    for i, sweep in enumerate(d["sweeps"]):
        sel = d["cloud"] == i
        out.append(SweepCloud(
            points_base=d["points_base"][sel], normals_base=d["normals_base"][sel],
            frame_index=d["frame_index"][sel], confidence=d["confidence"][sel],
            sweep=int(sweep), sensor_origin_base=d["sensor_origin_base"][sel],
            report=reports[i]))
    return out
