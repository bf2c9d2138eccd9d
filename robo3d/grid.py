"""The voxel grid that carries the visual hull, the box it covers, and their checks.

:class:`VoxelGrid` is the exchange type of the carvers (:mod:`robo3d.carving`,
:mod:`robo3d.octree`) and the visual-hull artefact (``hull.npz``, written by
:meth:`VoxelGrid.save_npz`, read by :meth:`VoxelGrid.load_npz`). It lives apart from
the carvers so that both import it without importing each other.

Choices (the seed, §3.4, fixes only "a box divided into voxels"):

* axis-aligned in ``frame`` (``base``): voxel ``(i, j, k)`` has its centre at
  ``origin + voxel_size * (i, j, k)``; cubic voxels; ``occupancy`` a dense
  ``(nx, ny, nz)`` bool array in C order;
* :func:`make_grid` centres the grid on the box and covers it
  (``n = ceil(extent / voxel_size)`` per axis), so it may overhang the box by less than
  one voxel on each axis; a dense grid of more than 2**30 voxels is refused as a
  configuration mistake;
* the file is a compressed NPZ of plain arrays (no pickles), extra dicts stored as JSON.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import save_npz

__all__ = ["VoxelGrid", "make_grid", "shell_voxels", "check_box", "carve_counts", "MAX_VOXELS"]

#: Voxels a dense grid may hold (1 GiB of bool): beyond this it is a configuration mistake.
MAX_VOXELS = 1 << 30
_RESERVED = ("origin", "voxel_size", "occupancy", "frame", "_json_keys")


def check_box(box_min: object, box_max: object) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box's corners as finite (3,) float64 arrays, ``max > min`` on every
    axis; ``ValueError`` otherwise."""
    lo = np.asarray(box_min, dtype=np.float64).reshape(-1)
    hi = np.asarray(box_max, dtype=np.float64).reshape(-1)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo) & np.isfinite(hi)):
        raise ValueError(f"box_min and box_max must be finite (3,) arrays, got {lo} and {hi}")
    if np.any(hi <= lo):
        raise ValueError(f"box_max must exceed box_min on every axis, got {lo} and {hi}")
    return lo, hi


@dataclass
class VoxelGrid:
    """A dense, axis-aligned voxel grid with binary occupancy.

    Attributes
    ----------
    origin : (3,) float64, metres
        Centre of voxel ``(0, 0, 0)`` in ``frame``.
    voxel_size : float, metres
        Edge of the (cubic) voxels.
    occupancy : (nx, ny, nz) bool
        True = occupied (opaque). Voxel ``(i, j, k)`` is centred at
        ``origin + voxel_size * (i, j, k)``.
    frame : str
        The frame the grid lives in (``"base"``).
    """

    origin: np.ndarray
    voxel_size: float
    occupancy: np.ndarray
    frame: str = "base"

    def __post_init__(self) -> None:
        o = np.asarray(self.origin, dtype=np.float64).reshape(-1)
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            raise ValueError(f"origin must be a finite (3,) array, got {self.origin!r}")
        s = float(self.voxel_size)
        if not np.isfinite(s) or s <= 0:
            raise ValueError(f"voxel_size must be a positive number of metres, got {s}")
        occ = np.asarray(self.occupancy)
        if occ.ndim != 3 or occ.dtype != np.bool_ or min(occ.shape) < 1:
            raise ValueError(f"occupancy must be (nx, ny, nz) bool with every n >= 1, "
                             f"got {tuple(occ.shape)} {occ.dtype}")
        self.origin = o
        self.voxel_size = s
        self.occupancy = np.ascontiguousarray(occ)

    # ------------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, int, int]:
        """``(nx, ny, nz)``."""
        return tuple(int(n) for n in self.occupancy.shape)  # type: ignore[return-value]

    @property
    def n_occupied(self) -> int:
        """Number of occupied voxels."""
        return int(np.count_nonzero(self.occupancy))

    @property
    def volume_m3(self) -> float:
        """Occupied volume, cubic metres (occupied voxels times voxel volume)."""
        return self.n_occupied * self.voxel_size ** 3

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Outer faces of the grid: ``(min (3,), max (3,))``, metres."""
        half = 0.5 * self.voxel_size
        lo = self.origin - half
        hi = self.origin + self.voxel_size * (np.array(self.shape) - 1) + half
        return lo, hi

    @property
    def occupied_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Outer faces of the occupied voxels: ``(min (3,), max (3,))``, metres; None
        when no voxel is occupied."""
        occ = np.asarray(self.occupancy, dtype=bool)
        if not occ.any():
            return None
        idx = [np.flatnonzero(occ.any(axis=tuple(a for a in range(3) if a != j)))
               for j in range(3)]
        half = 0.5 * self.voxel_size
        return (self.index_to_points(np.array([i[0] for i in idx])) - half,
                self.index_to_points(np.array([i[-1] for i in idx])) + half)

    @property
    def centre(self) -> np.ndarray:
        """Centre of the grid, (3,) metres."""
        lo, hi = self.bounds
        return 0.5 * (lo + hi)

    def index_to_points(self, ijk: np.ndarray) -> np.ndarray:
        """Voxel centres ``(N, 3)`` metres from integer indices ``(N, 3)``."""
        ijk = np.asarray(ijk)
        return self.origin + self.voxel_size * ijk.astype(np.float64)

    def points_to_index(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices ``(N, 3)`` int64 of the voxels containing points ``(N, 3)`` metres,
        and ``(N,)`` bool telling which points lie inside the grid."""
        p = np.asarray(points, dtype=np.float64)
        ijk = np.floor((p - self.origin) / self.voxel_size + 0.5).astype(np.int64)
        inside = np.all((ijk >= 0) & (ijk < np.array(self.shape)), axis=-1)
        return ijk, inside

    def centres(self, occupied_only: bool = True) -> np.ndarray:
        """Centres ``(N, 3)`` float64 metres of the occupied (or of all) voxels, C order."""
        if occupied_only:
            ijk = np.argwhere(self.occupancy)
        else:
            ijk = np.indices(self.shape).reshape(3, -1).T
        return self.index_to_points(ijk)

    def surface(self) -> np.ndarray:
        """The occupied voxels with an empty 6-neighbour (outside the grid counts as
        empty): the hull's shell, ``(nx, ny, nz)`` bool."""
        return shell_voxels(self.occupancy)

    def copy(self) -> VoxelGrid:
        """A deep copy."""
        return VoxelGrid(self.origin.copy(), self.voxel_size, self.occupancy.copy(), self.frame)

    # ------------------------------------------------------------------ files
    def save_npz(self, path: str | os.PathLike, **extra) -> None:
        """Write the grid (and ``extra`` arrays or JSON-able dicts) to ``path`` atomically.

        The file is a compressed NPZ with arrays ``origin``, ``voxel_size``,
        ``occupancy``, ``frame`` plus the extras; dicts and lists are stored as JSON
        strings and come back as such from :meth:`load_npz`. The data is written to a
        temporary file in the same directory and renamed, so a killed job leaves no
        half file.
        """
        path = Path(path)
        arrays: dict[str, np.ndarray] = {
            "origin": self.origin,
            "voxel_size": np.float64(self.voxel_size),
            "occupancy": self.occupancy,
            "frame": np.str_(self.frame),
        }
        json_keys = []
        for key, value in extra.items():
            if key in _RESERVED:
                raise ValueError(f"extra key {key!r} is reserved (reserved: {_RESERVED})")
            if isinstance(value, dict | list | tuple):
                arrays[key] = np.str_(json.dumps(value))
                json_keys.append(key)
                continue
            a = np.asarray(value)
            if a.dtype == object:
                raise ValueError(f"extra {key!r} must be an array or a JSON-able dict/list, "
                                 f"got {type(value).__name__}")
            arrays[key] = a
        arrays["_json_keys"] = np.array(json_keys, dtype=np.str_)
        save_npz(path, **arrays)

    @classmethod
    def load_npz(cls, path: str | os.PathLike, *, return_extra: bool = False):
        """Read a grid written by :meth:`save_npz`.

        Returns
        -------
        grid : VoxelGrid
        extra : dict
            Only with ``return_extra=True``: the extra arrays (JSON ones decoded).
        """
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: not a voxel-grid NPZ ({exc})") from exc
        missing = [k for k in ("origin", "voxel_size", "occupancy") if k not in data]
        if missing:
            raise ValueError(f"{path}: not a voxel-grid NPZ, missing {missing}")
        grid = cls(origin=data["origin"], voxel_size=float(data["voxel_size"]),
                   occupancy=data["occupancy"].astype(bool),
                   frame=str(data["frame"]) if "frame" in data else "base")
        if not return_extra:
            return grid
        json_keys = {str(k) for k in data.get("_json_keys", np.array([], dtype=np.str_))}
        extra = {}
        for k, v in data.items():
            if k in _RESERVED:
                continue
            extra[k] = json.loads(str(v)) if k in json_keys else v
        return grid, extra


def shell_voxels(occ: np.ndarray) -> np.ndarray:
    """The occupied voxels of ``occ`` (3-D bool) with an empty 6-neighbour (outside the
    array counts as empty), ``occ.shape`` bool."""
    inner = occ.copy()
    inner[0, :, :] = inner[-1, :, :] = False
    inner[:, 0, :] = inner[:, -1, :] = False
    inner[:, :, 0] = inner[:, :, -1] = False
    core = inner[1:-1, 1:-1, 1:-1]
    core &= occ[:-2, 1:-1, 1:-1] & occ[2:, 1:-1, 1:-1]
    core &= occ[1:-1, :-2, 1:-1] & occ[1:-1, 2:, 1:-1]
    core &= occ[1:-1, 1:-1, :-2] & occ[1:-1, 1:-1, 2:]
    return occ & ~inner


def make_grid(
    box_min: np.ndarray,
    box_max: np.ndarray,
    *,
    resolution: int | None = None,
    voxel_size: float | None = None,
    frame: str = "base",
) -> VoxelGrid:
    """A fully occupied grid covering a box (seed §3.4, fig. 12).

    Parameters
    ----------
    box_min, box_max : (3,) float64, metres
        The box, in ``frame``.
    resolution : int, optional
        Voxels along the box's longest side (``voxel_size = longest / resolution``).
    voxel_size : float, optional, metres
        Give this instead of ``resolution``.
    frame : str

    Returns
    -------
    VoxelGrid
        ``n = max(1, ceil(extent / voxel_size))`` voxels per axis, centred on the box;
        every voxel occupied.

    Raises
    ------
    ValueError
        Neither or both of ``resolution`` and ``voxel_size``, a degenerate box, or more
        than 2**30 voxels.
    """
    lo, hi = check_box(box_min, box_max)
    if (resolution is None) == (voxel_size is None):
        raise ValueError("give exactly one of resolution and voxel_size, got "
                         f"resolution={resolution}, voxel_size={voxel_size}")
    extent = hi - lo
    if resolution is not None:
        if int(resolution) != resolution or resolution < 1:
            raise ValueError(f"resolution must be a positive integer, got {resolution}")
        s = float(extent.max()) / int(resolution)
    else:
        s = float(voxel_size)  # type: ignore[arg-type]
        if not np.isfinite(s) or s <= 0:
            raise ValueError(f"voxel_size must be a positive number of metres, got {s}")
    # a relative tolerance keeps e.g. 0.3 / 0.01 from becoming 31 voxels
    n = np.maximum(1, np.ceil(extent / s - 1e-9)).astype(np.int64)
    total = int(np.prod(n))
    if total > MAX_VOXELS:
        raise ValueError(f"grid of {n.tolist()} = {total} voxels exceeds the dense limit of "
                         f"{MAX_VOXELS}; use a coarser resolution")
    origin = 0.5 * (lo + hi) - 0.5 * s * (n - 1)
    return VoxelGrid(origin=origin, voxel_size=s,
                     occupancy=np.ones(tuple(int(x) for x in n), dtype=bool), frame=frame)


def carve_counts(before: VoxelGrid, after: VoxelGrid) -> dict[str, float | int]:
    """The figures every carver reports of its grid: ``voxels_before``,
    ``voxels_after``, ``voxel_size_m`` and the carved ``volume_m3``."""
    return {"voxels_before": int(before.n_occupied), "voxels_after": int(after.n_occupied),
            "voxel_size_m": float(before.voxel_size), "volume_m3": float(after.volume_m3)}
