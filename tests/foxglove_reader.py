"""``results.mcap`` read back by a reader that shares no code with the one that wrote it.

The writer is robo3d's (Python: the ``mcap`` package's writer, Protobuf messages from
``foxglove-schemas-protobuf``, numpy-built wire bytes). The reader here is rerun's MCAP
importer (``rerun.chunk.McapReader``, Rust: the ``mcap`` crate for the container,
``prost-reflect`` on the ``FileDescriptorSet`` each schema record embeds for the
messages), the same code as ``rerun mcap convert``, already a dependency of the project
(rerun-sdk). It reads the file twice:

- with all its decoders: ``foxglove.PointCloud`` through its Foxglove decoder, which
  interprets the packed fields as a Foxglove viewer does (positions from ``x y z``,
  colours from ``red green blue alpha``), every other message by reflection;
- with the ``protobuf`` decoder alone: every message by reflection, so that a
  ``PointCloud``'s field layout, stride and frame are seen as written.

Other readers were weighed: the ``mcap`` CLI (Go) is not on PyPI; ``foxglove-sdk``
(PyPI) writes MCAP but has no reader; ``pybag`` reads ROS 2 (CDR) messages, not Protobuf;
the ``mcap`` Python package's own readers share the writer's package.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc


@dataclass
class Cloud:
    """One ``foxglove.PointCloud`` message as the reader decoded it."""

    topic: str
    log_time_ns: int
    stamp_ns: int
    frame_id: str
    positions: np.ndarray  # (N, 3) float32, from the Foxglove decoder
    colors_rgba: np.ndarray  # (N,) uint32 0xRRGGBBAA, from the Foxglove decoder
    fields: list[tuple[str, int, str]]  # (name, offset, numeric type) as written
    point_stride: int


@dataclass
class Mesh:
    """One ``foxglove.SceneUpdate`` message: its entities' triangle lists."""

    topic: str
    log_time_ns: int
    stamp_ns: int
    frame_id: str
    entity_id: str
    n_vertices: int
    n_triangles: int
    n_vertex_colors: int
    color: dict | None
    metadata: dict[str, str]


@dataclass
class Results:
    """What the reader found in a results.mcap."""

    schemas: dict[str, str]  # topic -> schema name
    encodings: dict[str, str]  # topic -> message encoding
    counts: dict[str, int]  # topic -> messages
    start_ns: int
    end_ns: int
    clouds: list[Cloud] = field(default_factory=list)
    meshes: list[Mesh] = field(default_factory=list)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    other: dict[str, int] = field(default_factory=dict)  # topic -> rows of other messages


def _ns(column: pa.ChunkedArray) -> np.ndarray:
    return np.asarray(column.cast(pa.int64()).to_numpy(zero_copy_only=False), dtype=np.int64)


def _stamp(ts: dict | None) -> int:
    return int(ts["seconds"]) * 1_000_000_000 + int(ts["nanos"]) if ts else 0


def _scene_updates(topic: str, rb: pa.RecordBatch) -> list[Mesh]:
    """The triangle lists of a chunk of SceneUpdate rows; vertex and index lists are
    counted with Arrow's list kernels, never turned into Python objects."""
    out = []
    log_times = _ns(rb.column("message_log_time"))
    messages = rb.column("foxglove.SceneUpdate:message")
    for row in range(rb.num_rows):
        for msg in messages[row].values:  # the row's messages (one)
            for entity in msg["entities"].values:
                tris = entity["triangles"].values
                pts = pc.list_value_length(tris.field("points"))
                idx = pc.list_value_length(tris.field("indices"))
                cols = pc.list_value_length(tris.field("colors"))
                colour = tris.field("color")[0].as_py() if len(tris) else None
                meta = {kv["key"].as_py(): kv["value"].as_py()
                        for kv in (entity["metadata"].values or [])}
                out.append(Mesh(topic, int(log_times[row]),
                                _stamp(entity["timestamp"].as_py()),
                                entity["frame_id"].as_py(), entity["id"].as_py(),
                                int(pc.sum(pts).as_py() or 0),
                                int(pc.sum(idx).as_py() or 0) // 3,
                                int(pc.sum(cols).as_py() or 0), colour, meta))
    return out


def read_results(path: str | Path) -> Results:
    """Read every message of a results.mcap with rerun's MCAP reader (module docstring)."""
    from rerun.chunk import McapReader

    info = McapReader(path).info()
    res = Results(schemas={c.topic: c.schema.name for c in info.channels},
                  encodings={c.topic: c.message_encoding for c in info.channels},
                  counts={c.topic: int(c.message_count) for c in info.channels},
                  start_ns=int(info.message_start_time_ns),
                  end_ns=int(info.message_end_time_ns))
    layouts: dict[tuple[str, int], tuple[list, int, str, int]] = {}
    clouds = [t for t, s in res.schemas.items() if s == "foxglove.PointCloud"]
    for chunk in McapReader(path, decoders=["protobuf"], include_topic_regex=[
            "^(" + "|".join(map(re.escape, clouds)) + ")$"]).stream() if clouds else []:
        rb = chunk.to_record_batch()
        if "foxglove.PointCloud:message" not in rb.schema.names:
            continue
        log_times = _ns(rb.column("message_log_time"))
        # one message per row; its data bytes are left in Arrow (not decoded again here)
        msgs = pc.list_flatten(rb.column("foxglove.PointCloud:message"))
        for row in range(rb.num_rows):
            m = msgs[row]
            fields = [(f["name"].as_py(), f["offset"].as_py(), f["type"]["name"].as_py())
                      for f in m["fields"].values]
            layouts[(chunk.entity_path, int(log_times[row]))] = (
                fields, m["point_stride"].as_py(), m["frame_id"].as_py(),
                _stamp(m["timestamp"].as_py()))
    for chunk in McapReader(path).stream():
        rb = chunk.to_record_batch()
        names = rb.schema.names
        topic = chunk.entity_path
        if chunk.entity_path == "/__mcap_metadata":
            for name in names:
                if not name.startswith("rerun."):
                    res.metadata[name] = {kv["first"]: kv["second"]
                                          for kv in rb.column(name)[0].as_py()[0]}
        elif "Points3D:positions" in names:
            log_times = _ns(rb.column("message_log_time"))
            stamps = _ns(rb.column("timestamp"))
            for row in range(rb.num_rows):
                fields, stride, frame, stamp = layouts[(topic, int(log_times[row]))]
                pos = rb.column("Points3D:positions")[row].values
                col = rb.column("Points3D:colors")[row].values
                res.clouds.append(Cloud(
                    topic, int(log_times[row]), int(stamps[row]), frame,
                    np.asarray(pc.list_flatten(pos).to_numpy(), np.float32).reshape(-1, 3)
                    if pos is not None else np.zeros((0, 3), np.float32),
                    np.asarray(col.to_numpy() if col is not None else [], np.uint32),
                    fields, stride))
                assert stamp == int(stamps[row]), "the two decoders disagree on a stamp"
        elif "foxglove.SceneUpdate:message" in names:
            res.meshes += _scene_updates(topic, rb)
        elif "message_log_time" in names:
            res.other[topic] = res.other.get(topic, 0) + rb.num_rows
    return res
