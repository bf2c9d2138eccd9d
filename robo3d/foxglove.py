"""A recording's results as Foxglove messages (``results/<rec>/results.mcap``).

Opened in Foxglove together with the recording it came from, ``results.mcap`` shows the
scan where it was made: the laser clouds appear sweep by sweep at the times their frames
were taken, the meshes at the end of the acquisition, all in the robot's ``base`` frame,
which the recording's own ``/tf`` places among the robot's links.

- :func:`point_cloud` packs points, colours and per-point scalars into one
  ``foxglove.PointCloud``;
- :func:`scene_update` puts a triangle mesh with per-vertex (or one) colour into one
  ``foxglove.SceneUpdate`` entity;
- :func:`sweep_cloud_messages` makes a sweep cloud file's messages: each sweep's whole
  cloud at its last frame's time (one topic per sweep, so that Foxglove, which draws the
  latest message of a topic, keeps every finished sweep on screen) and, on request, each
  laser frame's profile at the frame's own time;
- :func:`write_results_mcap` writes them in time order through
  :class:`robo3d.recording.writer.RecordingWriter` (Protobuf, schemas embedded, atomic).

Choices
-------
- Coordinates are ``float32`` in ``base``, metres, as Foxglove draws them: 0.1 µm steps
  at 1 m from the base, far below the laser's noise.
- A cloud's colour is packed as ``red``, ``green``, ``blue``, ``alpha`` ``uint8`` fields
  (Foxglove's "RGBA (separate fields)" colour mode, which rerun's MCAP importer reads
  too); its ``confidence`` and ``sweep`` are fields as well, to colour by in Foxglove.
- A mesh is one ``TriangleListPrimitive`` with shared vertices and ``indices``. Its
  repeated ``Point3`` and ``Color`` messages are written as Protobuf wire bytes by numpy
  (every element has the same fixed layout) and parsed back by the Protobuf runtime,
  which checks them: a Python object per vertex would cost seconds on a real mesh.
- Every pose is written explicitly as the identity, so that no reader has to guess what
  a missing quaternion means.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.TriangleListPrimitive_pb2 import TriangleListPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp

from .artefacts import SweepCloud
from .options import Options

__all__ = ["FoxgloveOptions", "ResultMessage", "point_cloud", "scene_update", "thin",
           "sweep_cloud_messages", "write_results_mcap"]

#: numpy dtype -> foxglove.PackedElementField.NumericType
_NUMERIC_TYPE = {np.dtype(np.uint8): PackedElementField.UINT8,
                 np.dtype(np.int8): PackedElementField.INT8,
                 np.dtype(np.uint16): PackedElementField.UINT16,
                 np.dtype(np.int16): PackedElementField.INT16,
                 np.dtype(np.uint32): PackedElementField.UINT32,
                 np.dtype(np.int32): PackedElementField.INT32,
                 np.dtype(np.float32): PackedElementField.FLOAT32,
                 np.dtype(np.float64): PackedElementField.FLOAT64}
_RGBA = ("red", "green", "blue", "alpha")


@dataclass(frozen=True)
class FoxgloveOptions(Options):
    """How the clouds are written (config section ``foxglove``).

    Attributes
    ----------
    max_points : int
        At most this many points per cloud message, thinned evenly (0: every point).
    profiles : bool
        Also one message per laser frame holding that frame's points, at its time.
    """

    section = "foxglove"
    max_points: int = 0
    profiles: bool = True


@dataclass(frozen=True)
class ResultMessage:
    """One message of ``results.mcap``: its topic, its time (ns, the recording's clock)
    and the protobuf message."""

    topic: str
    stamp_ns: int
    message: Any


def _timestamp(stamp_ns: int) -> Timestamp:
    s = int(stamp_ns)
    return Timestamp(seconds=s // 1_000_000_000, nanos=s % 1_000_000_000)


def _identity_pose() -> Pose:
    return Pose(position=Vector3(x=0.0, y=0.0, z=0.0),
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def _rgba(colors: Any, n: int, name: str) -> np.ndarray:
    """(n, 4) uint8 from (3,), (4,), (n, 3) or (n, 4) integer colours in 0..255 (alpha
    255 added)."""
    c = np.asarray(colors)
    if c.dtype.kind not in "ui" or c.shape[-1:] not in ((3,), (4,)) or c.ndim not in (1, 2) \
            or (c.ndim == 2 and len(c) != n) or (c.size and (c.min() < 0 or c.max() > 255)):
        raise ValueError(f"{name} must be integers 0..255 of shape (3,), (4,), ({n}, 3) or "
                         f"({n}, 4), got {c.shape} {c.dtype}")
    c = c.astype(np.uint8)
    if c.shape[-1] == 3:
        c = np.concatenate([c, np.full(c.shape[:-1] + (1,), 255, np.uint8)], axis=-1)
    return np.broadcast_to(c, (n, 4))


def point_cloud(points_base: np.ndarray, colors: Any, stamp_ns: int, *,
                frame_id: str = "base",
                fields: Mapping[str, np.ndarray] | None = None) -> PointCloud:
    """One ``foxglove.PointCloud``: ``x y z`` float32, ``red green blue alpha`` uint8,
    then one field per entry of ``fields`` in its own type.

    Parameters
    ----------
    points_base : (N, 3) float, metres
        In ``frame_id``.
    colors : (3,), (4,), (N, 3) or (N, 4) uint8
        One colour, or one per point.
    stamp_ns : int
        The message's ``timestamp``, nanoseconds.
    frame_id : str
    fields : mapping of name to (N,) array, optional
        Extra per-point scalars (uint8 ... float64), e.g. ``confidence``, ``sweep``.

    Returns
    -------
    PointCloud
        ``point_stride`` is the packed record's size; the pose is the identity.
    """
    pts = np.asarray(points_base, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise ValueError(f"points_base must be finite (N, 3), got {pts.shape}")
    n = len(pts)
    rgba = _rgba(colors, n, "colors")
    extra = {k: np.asarray(v) for k, v in dict(fields or {}).items()}
    for k, v in extra.items():
        if k in ("x", "y", "z", *_RGBA) or v.shape != (n,) or v.dtype not in _NUMERIC_TYPE:
            raise ValueError(f"field {k!r} must be a new name and ({n},) of a numeric type "
                             f"({', '.join(map(str, _NUMERIC_TYPE))}), got {v.shape} {v.dtype}")
    layout = [(c, np.float32) for c in "xyz"] + [(c, np.uint8) for c in _RGBA] \
        + [(k, v.dtype) for k, v in extra.items()]
    record = np.zeros(n, dtype=np.dtype(layout))  # packed: offsets as listed
    for i, c in enumerate("xyz"):
        record[c] = pts[:, i]
    for i, c in enumerate(_RGBA):
        record[c] = rgba[:, i]
    for k, v in extra.items():
        record[k] = v
    dt = record.dtype
    packed = [PackedElementField(name=name, offset=dt.fields[name][1],
                                 type=_NUMERIC_TYPE[dt.fields[name][0]])
              for name in dt.names]
    return PointCloud(timestamp=_timestamp(stamp_ns), frame_id=frame_id,
                      pose=_identity_pose(), point_stride=dt.itemsize, fields=packed,
                      data=record.tobytes())


def _varint(value: int) -> bytes:
    """Protobuf base-128 varint of a non-negative int."""
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _repeated_doubles(field_number: int, values: np.ndarray) -> bytes:
    """A repeated message field whose elements hold only doubles in fields 1, 2, ...
    (``foxglove.Point3``, ``foxglove.Color``), as wire bytes: every element has the same
    layout (tag, length, then per value a tag and 8 little-endian bytes)."""
    n, k = values.shape
    layout = [("tag", "u1"), ("len", "u1")]
    for j in range(k):
        layout += [(f"t{j}", "u1"), (f"v{j}", "<f8")]
    rec = np.zeros(n, dtype=np.dtype(layout))
    rec["tag"] = (field_number << 3) | 2
    rec["len"] = 9 * k  # < 128: one varint byte
    for j in range(k):
        rec[f"t{j}"] = ((j + 1) << 3) | 1
        rec[f"v{j}"] = values[:, j]
    return rec.tobytes()


def _triangle_list(vertices: np.ndarray, faces: np.ndarray, rgba: np.ndarray | None,
                   color: np.ndarray | None) -> TriangleListPrimitive:
    """A ``TriangleListPrimitive`` with shared vertices, ``indices`` and per-vertex
    ``colors`` (or one ``color``), built from wire bytes (see the module's Choices)."""
    idx = np.ascontiguousarray(faces, dtype="<u4").reshape(-1)
    parts = [_repeated_doubles(2, vertices)]
    if rgba is not None:
        parts.append(_repeated_doubles(4, rgba.astype(np.float64) / 255.0))
    if len(idx):
        parts += [bytes([(5 << 3) | 2]), _varint(4 * len(idx)), idx.tobytes()]
    tri = TriangleListPrimitive()
    tri.MergeFromString(b"".join(parts))
    tri.pose.CopyFrom(_identity_pose())
    if color is not None:
        r, g, b, a = (float(x) / 255.0 for x in color)
        tri.color.r, tri.color.g, tri.color.b, tri.color.a = r, g, b, a
    return tri


def scene_update(entity_id: str, vertices: np.ndarray, faces: np.ndarray, stamp_ns: int, *,
                 colors: Any = (190, 190, 190), frame_id: str = "base",
                 metadata: Mapping[str, str] | None = None) -> SceneUpdate:
    """One ``foxglove.SceneUpdate`` holding a triangle mesh as entity ``entity_id``.

    Parameters
    ----------
    entity_id : str
        The entity's id (a later update with the same id replaces it).
    vertices : (V, 3) float, metres
    faces : (F, 3) int
        Indices into ``vertices``.
    stamp_ns : int
    colors : (3,), (4,), (V, 3) or (V, 4) uint8
        One colour for the whole mesh (its ``color``) or one per vertex (``colors``).
    frame_id : str
    metadata : mapping of str to str, optional
        Shown by Foxglove when the entity is selected.

    Returns
    -------
    SceneUpdate
        One entity, ``frame_locked`` (it stays where it is in ``frame_id``), lifetime 0
        (until replaced).
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
        raise ValueError(f"vertices must be finite (V, 3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or (F.size and (F.min() < 0 or F.max() >= len(V))):
        raise ValueError(f"faces must be (F, 3) indices into {len(V)} vertices, got {F.shape}")
    c = np.asarray(colors)
    if c.ndim == 2:  # one colour per vertex
        tri = _triangle_list(V, F, _rgba(c, len(V), "colors"), None)
    else:
        tri = _triangle_list(V, F, None, _rgba(c, 1, "colors")[0])
    entity = SceneEntity(timestamp=_timestamp(stamp_ns), frame_id=frame_id, id=entity_id,
                         frame_locked=True, triangles=[tri],
                         metadata=[KeyValuePair(key=k, value=v)
                                   for k, v in dict(metadata or {}).items()])
    return SceneUpdate(entities=[entity])


def thin(n: int, max_points: int) -> np.ndarray:
    """Indices of at most ``max_points`` of ``n`` points, evenly spread (all for 0)."""
    if max_points <= 0 or n <= max_points:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, max_points).round().astype(np.int64))


def sweep_cloud_messages(clouds: Sequence[SweepCloud], stamps_ns: np.ndarray, topic: str,
                         palette: np.ndarray, *, frame_id: str = "base",
                         options: FoxgloveOptions = FoxgloveOptions(),
                         profile_topic: str | None = None) -> list[ResultMessage]:
    """The messages of one sweep cloud file (``clouds.npz`` or ``aligned.npz``).

    Parameters
    ----------
    clouds : sequence of SweepCloud
        In ``base``; ``frame_index`` indexes ``stamps_ns``.
    stamps_ns : (F,) int64
        The laser frames' times (``stripes.npz``), nanoseconds.
    topic : str
        Each sweep's whole cloud goes to ``{topic}/sweep_{k:02d}``, stamped at its last
        frame's time.
    palette : (K, 3) uint8
        Sweep ``k``'s colour is ``palette[k % K]``.
    frame_id : str
    options : FoxgloveOptions
        ``max_points`` thins every message; with ``profiles`` and ``profile_topic``,
        each frame's points also go to ``profile_topic`` at the frame's time.
    profile_topic : str, optional

    Returns
    -------
    list of ResultMessage
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    pal = np.asarray(palette, dtype=np.uint8).reshape(-1, 3)
    out: list[ResultMessage] = []
    for c in clouds:
        if len(c) == 0:
            continue
        if c.frame_index.min() < 0 or c.frame_index.max() >= len(stamps):
            raise ValueError(f"sweep {c.sweep}: frame_index outside the {len(stamps)} laser "
                             "frames' stamps")
        colour = pal[c.sweep % len(pal)]
        fields = {"confidence": c.confidence.astype(np.float32),
                  "sweep": np.full(len(c), c.sweep, np.uint32)}
        keep = thin(len(c), options.max_points)
        out.append(ResultMessage(f"{topic}/sweep_{c.sweep:02d}",
                                 int(stamps[c.frame_index.max()]),
                                 point_cloud(c.points_base[keep], colour,
                                             int(stamps[c.frame_index.max()]),
                                             frame_id=frame_id,
                                             fields={k: v[keep] for k, v in fields.items()})))
        if not (options.profiles and profile_topic):
            continue
        order = np.argsort(c.frame_index, kind="stable")
        frames, starts = np.unique(c.frame_index[order], return_index=True)
        for f, sel in zip(frames, np.split(order, starts[1:]), strict=True):
            sel = sel[thin(len(sel), options.max_points)]
            out.append(ResultMessage(profile_topic, int(stamps[f]), point_cloud(
                c.points_base[sel], colour, int(stamps[f]), frame_id=frame_id,
                fields={k: v[sel] for k, v in fields.items()})))
    return out


def write_results_mcap(path: str | os.PathLike[str], messages: Iterable[ResultMessage], *,
                       metadata: Mapping[str, Mapping[str, str]] | None = None,
                       static_links: Sequence[tuple[str, str]] = (),
                       static_stamp_ns: int = 0) -> dict[str, int]:
    """Write ``results.mcap``: the messages in time order, atomically.

    Parameters
    ----------
    path : str or path-like
    messages : iterable of ResultMessage
    metadata : mapping of record name to str -> str, optional
        MCAP metadata records (what the file holds, where it came from).
    static_links : sequence of (parent, child)
        Identity transforms written once on ``/results/tf_static`` at
        ``static_stamp_ns``: e.g. ``("base_link", "base")`` when the recording calls its
        base frame otherwise, so that ``base`` joins the recording's transform tree.
    static_stamp_ns : int

    Returns
    -------
    dict
        Messages per topic.
    """
    from .recording.writer import RecordingWriter

    msgs = sorted(messages, key=lambda m: (m.stamp_ns, m.topic))
    counts: dict[str, int] = {}
    with RecordingWriter(path) as w:
        for name, record in dict(metadata or {}).items():
            w.add_metadata(name, dict(record))
        if static_links:
            w.write_transforms("/results/tf_static", int(static_stamp_ns),
                               [(p, c, np.eye(4)) for p, c in static_links])
            counts["/results/tf_static"] = 1
        for m in msgs:
            w.write_protobuf(m.topic, m.stamp_ns, m.message)
            counts[m.topic] = counts.get(m.topic, 0) + 1
    return counts
