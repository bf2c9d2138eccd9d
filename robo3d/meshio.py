"""Mesh and point-cloud files: PLY (binary), STL (binary) and OBJ, written atomically.

Every writer writes to a temporary file beside the target and moves it into place with
:func:`os.replace` (:func:`robo3d.atomic.atomic_path`), so a failed or killed job never
leaves a half-written file under the target's name.

Choices
-------
- **PLY is written by robo3d itself** (a header and one packed numpy record array, binary
  little-endian). Open3D's writers refuse empty geometry (a recording with no laser points
  must still produce a valid, empty cloud) and cannot write 64-bit integers; our writer
  handles both and gives every property an exact, documented type: positions ``double``,
  normals ``float``, colours ``uchar red green blue`` (what MeshLab, CloudCompare and
  Open3D all read), faces ``list uchar int vertex_indices``.
- **Custom per-point attributes** (sweep id, frame index, confidence, ...) are written as
  extra scalar vertex properties, one per attribute, in the narrowest type that every
  reader we use accepts: ``uchar`` (bool, uint8), ``ushort`` (uint16), ``int`` (other
  integers; int64 values outside the int32 range are an error), ``float`` (float16/32),
  ``double`` (float64). :func:`read_point_cloud_attributes` reads them back with Open3D's
  tensor I/O, which keeps any extra property.
- **STL** is written by robo3d too (binary, float32 coordinates as the format stores
  them, face normals from the vertex order). **OBJ** is written by robo3d with 17
  significant digits, because Open3D's OBJ writer keeps only six (a micrometre at our
  scale); vertex colours use the common ``v x y z r g b`` extension.
- **Reading** meshes uses pymeshlab, which keeps the file's vertex order (Open3D's OBJ reader
  renumbers vertices) and merges STL's per-triangle vertices into shared ones.
"""

from __future__ import annotations

import logging
import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .errors import StageError

__all__ = [
    "read_mesh",
    "write_mesh",
    "write_point_cloud",
    "read_point_cloud",
    "read_point_cloud_attributes",
    "read_vertex_attributes",
]

log = logging.getLogger(__name__)


_MESH_SUFFIXES = (".ply", ".stl", ".obj")
_RESERVED_PLY_NAMES = {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha"}


# --------------------------------------------------------------------------- helpers


def _as_points(name: str, a: object, n: int | None = None) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got shape {arr.shape} {arr.dtype}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} must have {n} rows (one per point/vertex), got {arr.shape[0]}")
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{name} must be numeric, got {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains non-finite values")
    return arr


def _as_faces(faces: object, n_vertices: int) -> np.ndarray:
    f = np.asarray(faces)
    if f.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
        raise ValueError(f"faces must be (F, 3) integer vertex indices, got {f.shape} {f.dtype}")
    if f.min() < 0 or f.max() >= n_vertices:
        raise ValueError(
            f"faces index vertices {f.min()}..{f.max()}, but there are {n_vertices} vertices"
        )
    return f.astype(np.int64)


def _as_colors_uint8(colors: object, n: int) -> np.ndarray:
    c = np.asarray(colors)
    if c.ndim != 2 or c.shape != (n, 3):
        raise ValueError(f"colors must be ({n}, 3), got {c.shape}")
    if c.dtype == np.uint8:
        return c
    if c.dtype.kind == "f":
        if not np.all(np.isfinite(c)) or c.min() < 0.0 or c.max() > 1.0:
            raise ValueError("float colors must be finite and in [0, 1]")
        return np.round(c * 255.0).astype(np.uint8)
    if c.dtype.kind in "iu":
        if c.min() < 0 or c.max() > 255:
            raise ValueError("integer colors must be in 0..255")
        return c.astype(np.uint8)
    raise ValueError(f"colors must be uint8 or float in [0, 1], got {c.dtype}")


def _ply_scalar(name: str, a: object, n: int) -> tuple[str, np.ndarray]:
    """The PLY type name and the converted array of one custom scalar attribute."""
    arr = np.asarray(a)
    if arr.ndim == 2 and arr.shape[1] == 1:
        arr = arr[:, 0]
    if arr.shape != (n,):
        raise ValueError(f"attribute {name!r} must have shape ({n},), got {arr.shape}")
    kind = arr.dtype.kind
    if kind == "b" or arr.dtype == np.uint8:
        return "uchar", arr.astype(np.uint8)
    if arr.dtype == np.uint16:
        return "ushort", arr
    if kind in "iu":
        if arr.size and (arr.min() < np.iinfo(np.int32).min or arr.max() > np.iinfo(np.int32).max):
            raise ValueError(f"attribute {name!r} has values outside the int32 range PLY can hold")
        return "int", arr.astype(np.int32)
    if kind == "f":
        if arr.dtype == np.float64:
            return "double", arr
        return "float", arr.astype(np.float32)
    raise ValueError(f"attribute {name!r} must be bool, integer or float, got {arr.dtype}")


_PLY_NUMPY = {"uchar": "u1", "ushort": "<u2", "int": "<i4", "float": "<f4", "double": "<f8"}


def _write_ply(
    path: Path,
    vertex_props: list[tuple[str, str, np.ndarray]],
    faces: np.ndarray | None,
    comment: str | None = None,
) -> None:
    """Write a binary little-endian PLY from (name, ply_type, (N,) array) vertex properties."""
    n = vertex_props[0][2].shape[0]
    header = ["ply", "format binary_little_endian 1.0", "comment written by robo3d",
              *([f"comment {comment}"] if comment else []), f"element vertex {n}"]
    header += [f"property {ptype} {name}" for name, ptype, _ in vertex_props]
    if faces is not None:
        header += [f"element face {faces.shape[0]}", "property list uchar int vertex_indices"]
    header.append("end_header")
    vdtype = np.dtype([(name, _PLY_NUMPY[ptype]) for name, ptype, _ in vertex_props])
    vrec = np.zeros(n, dtype=vdtype)
    for name, _, arr in vertex_props:
        vrec[name] = arr
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vrec.tobytes())
        if faces is not None:
            frec = np.zeros(faces.shape[0], dtype=[("n", "u1"), ("v", "<i4", (3,))])
            frec["n"] = 3
            frec["v"] = faces
            fh.write(frec.tobytes())


def _ply_vertex_count(path: Path) -> int | None:
    """The vertex count from a PLY header, or None when the file is not a readable PLY."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return None
    if not head.startswith(b"ply"):
        return None
    for line in head.split(b"\n"):
        parts = line.split()
        if len(parts) == 3 and parts[0] == b"element" and parts[1] == b"vertex":
            try:
                return int(parts[2])
            except ValueError:
                return None
        if line.strip() == b"end_header":
            break
    return None


# --------------------------------------------------------------------------- meshes
#: Units a mesh file can be written in: the factor from metres.
_UNITS = {"m": 1.0, "mm": 1000.0}


def write_mesh(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    vertex_normals: np.ndarray | None = None,
    vertex_colors: np.ndarray | None = None,
    attributes: dict[str, np.ndarray] | None = None,
    unit: str = "m",
) -> None:
    """Write a triangle mesh, atomically, in the format its suffix names.

    Parameters
    ----------
    path : str or path-like
        Target file; ``.ply`` (binary PLY), ``.stl`` (binary STL) or ``.obj``.
    vertices : (V, 3) float64, metres
        Vertex positions.
    faces : (F, 3) int
        Vertex indices of each triangle (counter-clockwise seen from outside).
    vertex_normals : (V, 3) float, optional
        Unit normals per vertex (PLY and OBJ; STL stores face normals only).
    vertex_colors : (V, 3) uint8 or float in [0, 1], optional
        Colours per vertex (PLY and OBJ; STL has none).
    attributes : dict of str to (V,) array, optional
        Custom scalar properties per vertex (PLY only; e.g. the fusion's ``source`` and
        ``confidence``), stored with their type (bool and uint8 as ``uchar``, other
        integers as ``int``, floats as ``float``/``double``); read back with
        :func:`read_vertex_attributes`.
    unit : {"m", "mm"}
        Unit of the coordinates in the file (``vertices`` are in metres): ``mm`` scales
        them by 1000 (STL has no unit field; slicers and CAD tools read millimetres). A
        PLY in mm says so in a header comment.

    Raises
    ------
    ValueError
        On a suffix other than the three above or arrays of the wrong shape.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _MESH_SUFFIXES:
        raise ValueError(f"mesh path must end in one of {_MESH_SUFFIXES}, got {str(path)!r}")
    if unit not in _UNITS:
        raise ValueError(f"unit must be one of {tuple(_UNITS)}, got {unit!r}")
    v = _as_points("vertices", vertices).astype(np.float64) * _UNITS[unit]
    f = _as_faces(faces, v.shape[0])
    n = None if vertex_normals is None else _as_points("vertex_normals", vertex_normals, len(v))
    c = None if vertex_colors is None else _as_colors_uint8(vertex_colors, len(v))

    with atomic_path(path) as tmp:
        if suffix == ".ply":
            props = [("x", "double", v[:, 0]), ("y", "double", v[:, 1]), ("z", "double", v[:, 2])]
            if n is not None:
                props += [(k, "float", n[:, i].astype(np.float32))
                          for i, k in enumerate(("nx", "ny", "nz"))]
            if c is not None:
                props += [(k, "uchar", c[:, i]) for i, k in enumerate(("red", "green", "blue"))]
            for name, arr in (attributes or {}).items():
                if name in {p[0] for p in props} or not name.isidentifier():
                    raise ValueError(f"attribute name {name!r} is reserved or not a name")
                props.append((name, *_ply_scalar(name, arr, len(v))))
            _write_ply(tmp, props, f, comment=f"unit {unit}" if unit != "m" else None)
        elif suffix == ".obj":
            _write_obj(tmp, v, f, n, c, unit=unit)
        else:  # .stl
            _write_stl(tmp, v, f)
    log.debug("wrote mesh %s: %d vertices, %d faces", path, len(v), len(f))


def _write_obj(path: Path, v: np.ndarray, f: np.ndarray, n: np.ndarray | None,
               c: np.ndarray | None, unit: str = "m") -> None:
    with open(path, "w", encoding="ascii") as fh:
        fh.write(f"# written by robo3d; unit {unit}\n")
        if c is not None:
            np.savetxt(fh, np.hstack([v, c / 255.0]), fmt="v %.17g %.17g %.17g %.6g %.6g %.6g")
        else:
            np.savetxt(fh, v, fmt="v %.17g %.17g %.17g")
        if n is not None:
            np.savetxt(fh, n, fmt="vn %.9g %.9g %.9g")
            np.savetxt(fh, np.repeat(f + 1, 2, axis=1), fmt="f %d//%d %d//%d %d//%d")
        else:
            np.savetxt(fh, f + 1, fmt="f %d %d %d")


def _write_stl(path: Path, v: np.ndarray, f: np.ndarray) -> None:
    # Binary STL: 80-byte header, uint32 count, then per triangle normal, 3 vertices, uint16.
    tri = v[f] if len(f) else np.zeros((0, 3, 3))
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) if len(f) else np.zeros((0, 3))
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    nrm = np.divide(nrm, length, out=np.zeros_like(nrm), where=length > 0)
    rec = np.zeros(len(f), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["n"] = nrm
    rec["v"] = tri
    with open(path, "wb") as fh:
        fh.write(b"binary STL written by robo3d".ljust(80, b" "))
        fh.write(np.uint32(len(f)).tobytes())
        fh.write(rec.tobytes())


def read_mesh(
    path_or_bytes: str | os.PathLike | bytes,
    *,
    suffix: str = ".ply",
) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh from a file or from the bytes of one.

    Parameters
    ----------
    path_or_bytes : str, path-like or bytes
        A mesh file (any format pymeshlab reads: PLY, STL, OBJ, OFF, ...), or its content
        (e.g. a recording's ``ground_truth/mesh.ply`` attachment).
    suffix : str
        The format of ``path_or_bytes`` when it is bytes (``".ply"``, ``".stl"``, ...).

    Returns
    -------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int64
        Polygons are triangulated by the reader. STL's per-triangle vertices are merged.

    Raises
    ------
    FileNotFoundError
        When the path does not exist.
    StageError
        When the file cannot be parsed as a mesh.
    """
    if isinstance(path_or_bytes, bytes | bytearray | memoryview):
        if not suffix.startswith("."):
            suffix = "." + suffix
        with tempfile.TemporaryDirectory(prefix="robo3d-mesh-") as d:
            tmp = Path(d) / f"mesh{suffix.lower()}"
            tmp.write_bytes(bytes(path_or_bytes))
            return _read_mesh_file(tmp, label=f"<{len(path_or_bytes)} bytes {suffix}>")
    path = Path(path_or_bytes)
    if not path.is_file():
        raise FileNotFoundError(f"mesh file {str(path)!r} does not exist")
    return _read_mesh_file(path, label=str(path))


def _read_mesh_file(path: Path, *, label: str) -> tuple[np.ndarray, np.ndarray]:
    if path.suffix.lower() == ".ply" and _ply_vertex_count(path) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    import pymeshlab

    ms = pymeshlab.MeshSet()
    cwd = os.getcwd()
    try:
        ms.load_new_mesh(str(path.resolve()))
    except pymeshlab.PyMeshLabException as exc:
        raise StageError(f"cannot read mesh {label}: {exc}") from exc
    finally:
        # pymeshlab (2025.7) leaves the process in the file's folder when a load fails;
        # once that (temporary) folder is gone, every later os.getcwd() raises.
        os.chdir(cwd)
    m = ms.current_mesh()
    v = np.ascontiguousarray(m.vertex_matrix(), dtype=np.float64)
    f = np.ascontiguousarray(m.face_matrix(), dtype=np.int64).reshape(-1, 3)
    return v, f


# --------------------------------------------------------------------------- point clouds


def write_point_cloud(
    path: str | os.PathLike,
    points: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    colors: np.ndarray | None = None,
    attributes: Mapping[str, np.ndarray] | None = None,
) -> None:
    """Write a point cloud as binary PLY, atomically, with optional per-point attributes.

    Parameters
    ----------
    path : str or path-like
        Target ``.ply`` file.
    points : (N, 3) float, metres
        Point positions (written as ``double``).
    normals : (N, 3) float, optional
        Normals (written as ``float nx ny nz``).
    colors : (N, 3) uint8 or float in [0, 1], optional
        Colours (written as ``uchar red green blue``).
    attributes : mapping of str to (N,) array, optional
        Extra scalar properties, e.g. ``{"sweep": ..., "frame": ..., "confidence": ...}``.
        Names must be identifiers and not clash with x/y/z/nx/ny/nz/red/green/blue/alpha.
        Types: bool/uint8 -> uchar, uint16 -> ushort, other integers -> int (int32 range),
        float32 -> float, float64 -> double.

    Notes
    -----
    An empty cloud (N = 0) is written as a valid PLY with zero vertices.
    """
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise ValueError(f"point clouds are written as .ply, got {str(path)!r}")
    p = _as_points("points", points).astype(np.float64)
    n_pts = p.shape[0]
    props: list[tuple[str, str, np.ndarray]] = [
        ("x", "double", p[:, 0]), ("y", "double", p[:, 1]), ("z", "double", p[:, 2])]
    if normals is not None:
        nrm = _as_points("normals", normals, n_pts)
        props += [(k, "float", nrm[:, i].astype(np.float32))
                  for i, k in enumerate(("nx", "ny", "nz"))]
    if colors is not None:
        c = _as_colors_uint8(colors, n_pts)
        props += [(k, "uchar", c[:, i]) for i, k in enumerate(("red", "green", "blue"))]
    for name, arr in (attributes or {}).items():
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"attribute names must be identifiers, got {name!r}")
        if name in _RESERVED_PLY_NAMES:
            raise ValueError(f"attribute name {name!r} clashes with a standard PLY property")
        ptype, conv = _ply_scalar(name, arr, n_pts)
        props.append((name, ptype, conv))
    with atomic_path(path) as tmp:
        _write_ply(tmp, props, None)
    log.debug("wrote point cloud %s: %d points", path, n_pts)


def _read_tensor_cloud(path: str | os.PathLike):  # -> open3d.t.geometry.PointCloud | None
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point cloud file {str(path)!r} does not exist")
    if path.suffix.lower() == ".ply" and _ply_vertex_count(path) == 0:
        return None
    import open3d as o3d

    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pc = o3d.t.io.read_point_cloud(str(path))
    if "positions" not in pc.point or pc.point.positions.shape[0] == 0:
        raise StageError(f"cannot read a point cloud from {str(path)!r}")
    return pc


def read_point_cloud(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read the points and normals of a point-cloud file (PLY, PCD, XYZ, ...).

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    points : (N, 3) float64, metres
    normals : (N, 3) float64 or None
        None when the file has no normals.
    """
    pc = _read_tensor_cloud(path)
    if pc is None:
        return np.zeros((0, 3)), None
    pts = pc.point.positions.numpy().astype(np.float64)
    nrm = pc.point.normals.numpy().astype(np.float64) if "normals" in pc.point else None
    return pts, nrm


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "<i2",
              "int16": "<i2", "ushort": "<u2", "uint16": "<u2", "int": "<i4", "int32": "<i4",
              "uint": "<u4", "uint32": "<u4", "float": "<f4", "float32": "<f4",
              "double": "<f8", "float64": "<f8"}


def read_vertex_attributes(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every per-vertex property of a binary little-endian PLY mesh (as robo3d writes
    them) except positions, normals and colours: e.g. ``source`` and ``confidence`` of
    fused.ply and mesh.ply.

    Returns
    -------
    dict of str to (V,) array
        Each property in its stored type.

    Raises
    ------
    ValueError
        The file is not a PLY, not binary little-endian, or its vertex element has list
        properties (or it is truncated); the message names the file.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        data = fh.read()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    body = data.index(b"\n", end) + 1
    lines = data[:end].decode("ascii", "replace").splitlines()
    if not any(ln.strip() == "format binary_little_endian 1.0" for ln in lines):
        raise ValueError(f"{path}: only binary little-endian PLY is read here")
    n, props, in_vertex, before = None, [], False, True
    for ln in lines:
        parts = ln.split()
        if not parts:
            continue
        if parts[0] == "element":
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                n = int(parts[2])
                before = False
            elif before:
                raise ValueError(f"{path}: an element before the vertices is not supported")
        elif parts[0] == "property" and in_vertex:
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: vertex property {' '.join(parts[1:])!r} is not a "
                                 "scalar PLY type")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if n is None:
        raise ValueError(f"{path}: no vertex element")
    dt = np.dtype(props)
    if len(data) < body + n * dt.itemsize:
        raise ValueError(f"{path}: truncated ({len(data)} bytes, the vertices need "
                         f"{body + n * dt.itemsize})")
    rec = np.frombuffer(data, dtype=dt, count=n, offset=body)
    skip = {"x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "alpha"}
    return {name: rec[name].copy() for name, _ in props if name not in skip}


def read_point_cloud_attributes(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read every per-point property of a point-cloud file except positions and normals.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    dict of str to array
        ``"colors"`` as (N, 3) uint8 when present, and each custom scalar property as an
        (N,) array of its stored type (e.g. ``sweep`` int32, ``confidence`` float32). An
        empty file gives an empty dict.
    """
    pc = _read_tensor_cloud(path)
    if pc is None:
        return {}
    out: dict[str, np.ndarray] = {}
    for key in pc.point:
        if key in ("positions", "normals"):
            continue
        arr = pc.point[key].numpy()
        out[key] = arr[:, 0].copy() if arr.ndim == 2 and arr.shape[1] == 1 else arr.copy()
    return out
