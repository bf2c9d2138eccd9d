"""Writing recordings (``recording-format.md``) with Foxglove's well-known schemas.

:class:`RecordingWriter` writes an MCAP file that any MCAP tool opens (Foxglove, rerun's
``rerun mcap convert``, ``mcap info``), in either message encoding the contract allows:

- ``protobuf`` (default): the schemas of ``foxglove-schemas-protobuf``, each stored as a
  ``FileDescriptorSet`` so that readers decode them without generated code;
- ``json``: the same messages as JSON with ``jsonschema`` schemas, ``bytes`` as base64
  and timestamps as ``{"sec", "nsec"}``, as Foxglove's JSON schemas define them.

Choices
-------
- Atomic: the file is written to a hidden temporary file beside ``path`` and renamed
  onto ``path`` by a successful :meth:`RecordingWriter.close`; an exception inside a
  ``with`` block (or :meth:`RecordingWriter.abort`) removes the temporary file, so a
  failed writer never leaves a half file under the final name.
- Deterministic: a message's MCAP log time and publish time are its own timestamp, and
  attachments carry zero times, so the same calls give the same bytes.
- One topic has one schema: writing a ``RawImage`` to a topic that already carries
  ``CompressedImage`` is a ``ValueError`` (a Foxglove channel has one schema).
- ``write_calibration`` writes ``distortion_model = "plumb_bob"`` with the five
  coefficients when the camera has distortion, else ``""`` with an empty ``D``; ``R`` is
  the identity and ``P = [K | 0]`` (a monocular camera).
"""

from __future__ import annotations

import base64
import json
import logging
import os
import tempfile
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set

from ..atomic import file_mode
from ..camera import CameraModel
from ..transforms import matrix_to_quat
from .images import COMPRESSED_ENCODINGS, RAW_ENCODINGS, encode_image, normalize_encoding

__all__ = ["RecordingWriter", "FOXGLOVE_JSON_SCHEMAS"]

_log = logging.getLogger(__name__)

_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE, "": CompressionType.NONE}

# --------------------------------------------------------------------------- JSON schemas
_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
}
_FLOATS = {"type": "array", "items": {"type": "number"}}
_VEC3 = {"type": "object", "title": "foxglove.Vector3",
         "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "title": "foxglove.Quaternion",
         "properties": {k: {"type": "number"} for k in "xyzw"}}
_FRAME_TRANSFORM = {
    "title": "foxglove.FrameTransform",
    "description": "A transform between two reference frames in 3D space",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "parent_frame_id": {"type": "string"},
        "child_frame_id": {"type": "string"},
        "translation": _VEC3,
        "rotation": _QUAT,
    },
}

#: JSON schemas (``jsonschema`` encoding) of the Foxglove messages robo3d writes.
FOXGLOVE_JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.CameraCalibration": {
        "title": "foxglove.CameraCalibration",
        "description": "Camera calibration parameters",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "width": {"type": "integer", "minimum": 0},
            "height": {"type": "integer", "minimum": 0},
            "distortion_model": {"type": "string"},
            "D": _FLOATS,
            "K": {**_FLOATS, "minItems": 9, "maxItems": 9},
            "R": {**_FLOATS, "minItems": 9, "maxItems": 9},
            "P": {**_FLOATS, "minItems": 12, "maxItems": 12},
        },
    },
    "foxglove.FrameTransform": _FRAME_TRANSFORM,
    "foxglove.FrameTransforms": {
        "title": "foxglove.FrameTransforms",
        "description": "An array of FrameTransform messages",
        "type": "object",
        "properties": {"transforms": {"type": "array", "items": _FRAME_TRANSFORM}},
    },
    "foxglove.CompressedImage": {
        "title": "foxglove.CompressedImage",
        "description": "A compressed image",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "data": {"type": "string", "contentEncoding": "base64"},
            "format": {"type": "string"},
        },
    },
    "foxglove.RawImage": {
        "title": "foxglove.RawImage",
        "description": "A raw image",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "width": {"type": "integer", "minimum": 0},
            "height": {"type": "integer", "minimum": 0},
            "encoding": {"type": "string"},
            "step": {"type": "integer", "minimum": 0},
            "data": {"type": "string", "contentEncoding": "base64"},
        },
    },
}

_PROTO_CLASSES = {
    "foxglove.CameraCalibration": CameraCalibration,
    "foxglove.FrameTransforms": FrameTransforms,
    "foxglove.CompressedImage": CompressedImage,
    "foxglove.RawImage": RawImage,
}


def _check_stamp(stamp_ns: int) -> int:
    if isinstance(stamp_ns, bool) or not isinstance(stamp_ns, int | np.integer):
        raise ValueError(f"stamp_ns must be an int (nanoseconds), got {type(stamp_ns).__name__}")
    s = int(stamp_ns)
    if s < 0 or s >= 2**63:
        raise ValueError(f"stamp_ns must be in [0, 2**63) ns, got {s}")
    return s


def _pb_time(stamp_ns: int) -> Timestamp:
    return Timestamp(seconds=stamp_ns // 1_000_000_000, nanos=stamp_ns % 1_000_000_000)


def _json_time(stamp_ns: int) -> dict[str, int]:
    return {"sec": stamp_ns // 1_000_000_000, "nsec": stamp_ns % 1_000_000_000}


class RecordingWriter:
    """Write a recording: calibrations, transforms, images, metadata, attachments.

    Use it as a context manager; the file appears under ``path`` only when the block
    ends without an exception (or on an explicit :meth:`close`).

    Parameters
    ----------
    path : str or path-like
        The ``.mcap`` file to create (replaced if it exists).
    message_encoding : {"protobuf", "json"}
        How messages are serialised (see the module docstring).
    compression : {"zstd", "lz4", "none"}
        Chunk compression.
    chunk_size : int
        Target uncompressed chunk size in bytes.

    Examples
    --------
    >>> with RecordingWriter("scan.mcap") as w:                       # doctest: +SKIP
    ...     w.add_metadata("robo3d.recording", {"kind": "scan", "units": "m"})
    ...     w.write_calibration("/camera/calibration", 0, camera)
    ...     w.write_transforms("/tf_static", 0, [("flange", "camera", T_flange_camera)])
    ...     w.write_transforms("/tf", t, [("base", "flange", T_base_flange)])
    ...     w.write_image("/camera/image", t, "camera", image_rgb)
    """

    def __init__(self, path: str | os.PathLike[str], *, message_encoding: str = "protobuf",
                 compression: str = "zstd", chunk_size: int = 1 << 20) -> None:
        if message_encoding not in ("protobuf", "json"):
            raise ValueError(f"message_encoding must be 'protobuf' or 'json', "
                             f"got {message_encoding!r}")
        if compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of zstd, lz4, none, got {compression!r}")
        if int(chunk_size) <= 0:
            raise ValueError(f"chunk_size must be a positive number of bytes, got {chunk_size}")
        self.path = Path(path)
        self.message_encoding = message_encoding
        directory = self.path.parent if str(self.path.parent) else Path(".")
        if not directory.is_dir():
            raise FileNotFoundError(f"directory of {str(self.path)!r} does not exist")
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=directory)
        self._tmp_path = Path(tmp)
        os.chmod(tmp, file_mode())  # mkstemp makes 0600; a recording is an ordinary file
        self._file = os.fdopen(fd, "wb")
        self._writer = McapWriter(self._file, chunk_size=int(chunk_size),
                                  compression=_COMPRESSION[compression])
        self._writer.start(profile="", library="robo3d")
        self._schema_ids: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}  # topic -> (channel id, schema name)
        self._closed = False

    # ------------------------------------------------------------------ context manager
    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # ------------------------------------------------------------------ plumbing
    def _check_open(self) -> None:
        if self._closed:
            raise ValueError(f"recording writer for {str(self.path)!r} is closed")

    def _channel(self, topic: str, schema_name: str, proto_class: Any = None) -> int:
        if not isinstance(topic, str) or not topic:
            raise ValueError(f"topic must be a non-empty string, got {topic!r}")
        if topic in self._channels:
            cid, existing = self._channels[topic]
            if existing != schema_name:
                raise ValueError(f"topic {topic!r} carries {existing}, cannot write a "
                                 f"{schema_name} to it")
            return cid
        sid = self._schema_ids.get(schema_name)
        if sid is None:
            if self.message_encoding == "protobuf":
                fds = build_file_descriptor_set(proto_class or _PROTO_CLASSES[schema_name])
                sid = self._writer.register_schema(schema_name, "protobuf",
                                                   fds.SerializeToString())
            else:
                data = json.dumps(FOXGLOVE_JSON_SCHEMAS[schema_name]).encode()
                sid = self._writer.register_schema(schema_name, "jsonschema", data)
            self._schema_ids[schema_name] = sid
        cid = self._writer.register_channel(topic, self.message_encoding, sid)
        self._channels[topic] = (cid, schema_name)
        return cid

    def _write(self, topic: str, schema_name: str, stamp_ns: int, pb: Any,
               js: dict[str, Any] | None) -> None:
        cid = self._channel(topic, schema_name)
        if self.message_encoding == "protobuf":
            data = pb().SerializeToString()
        else:
            data = json.dumps(js, separators=(",", ":")).encode()
        self._writer.add_message(cid, log_time=stamp_ns, data=data, publish_time=stamp_ns)

    def write_protobuf(self, topic: str, stamp_ns: int, message: Any) -> None:
        """Write any protobuf message (e.g. a ``foxglove.PointCloud`` or
        ``foxglove.SceneUpdate`` of :mod:`robo3d.foxglove`) with its schema stored as a
        ``FileDescriptorSet``, so that a reader decodes it without generated code.

        Parameters
        ----------
        topic : str
        stamp_ns : int
            The message's time, nanoseconds: its MCAP log and publish time.
        message : google.protobuf.message.Message
            Its full name (``foxglove.PointCloud``) is the schema's name.

        Raises
        ------
        ValueError
            A writer made with ``message_encoding="json"`` (robo3d keeps JSON schemas only
            for the recording contract's messages), or a topic that already carries
            another schema.
        """
        self._check_open()
        stamp = _check_stamp(stamp_ns)
        if self.message_encoding != "protobuf":
            raise ValueError("write_protobuf needs a writer with message_encoding='protobuf', "
                             f"this one writes {self.message_encoding!r}")
        descriptor = getattr(message, "DESCRIPTOR", None)
        if descriptor is None or not hasattr(message, "SerializeToString"):
            raise ValueError(f"message must be a protobuf message, got {type(message).__name__}")
        cid = self._channel(topic, descriptor.full_name, type(message))
        self._writer.add_message(cid, log_time=stamp, data=message.SerializeToString(),
                                 publish_time=stamp)

    # ------------------------------------------------------------------ records
    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Add a metadata record (e.g. ``robo3d.recording``: ``kind``, ``object``, ...).

        Parameters
        ----------
        name : str
        data : dict of str to str
            Values must be strings (MCAP metadata is string to string).
        """
        self._check_open()
        if not isinstance(name, str) or not name:
            raise ValueError(f"metadata name must be a non-empty string, got {name!r}")
        bad = {k: type(v).__name__ for k, v in dict(data).items()
               if not isinstance(k, str) or not isinstance(v, str)}
        if bad:
            raise ValueError(f"metadata {name!r} must map str to str; non-string entries: {bad}")
        self._writer.add_metadata(name, dict(data))

    def add_attachment(self, name: str, data: bytes,
                       media_type: str = "application/octet-stream") -> None:
        """Add an attachment (e.g. ``ground_truth/mesh.ply``).

        Parameters
        ----------
        name : str
        data : bytes
        media_type : str
        """
        self._check_open()
        if not isinstance(name, str) or not name:
            raise ValueError(f"attachment name must be a non-empty string, got {name!r}")
        if not isinstance(data, bytes | bytearray | memoryview):
            raise ValueError(f"attachment data must be bytes, got {type(data).__name__}")
        self._writer.add_attachment(create_time=0, log_time=0, name=name,
                                    media_type=str(media_type), data=bytes(data))

    def write_calibration(self, topic: str, stamp_ns: int, camera: CameraModel) -> None:
        """Write a ``foxglove.CameraCalibration`` of ``camera``.

        Parameters
        ----------
        topic : str
            Usually ``/camera/calibration``.
        stamp_ns : int
            Timestamp, nanoseconds.
        camera : CameraModel
            ``frame_id``, size, ``K`` and plumb_bob ``D``.
        """
        self._check_open()
        stamp = _check_stamp(stamp_ns)
        if not isinstance(camera, CameraModel):
            raise ValueError(f"camera must be a CameraModel, got {type(camera).__name__}")
        k = [float(x) for x in camera.K.reshape(-1)]
        if camera.has_distortion:
            model, d = "plumb_bob", [float(x) for x in camera.D[:5]]
        else:
            model, d = "", []
        r = [float(x) for x in np.eye(3).reshape(-1)]
        p = [float(x) for x in np.hstack([camera.K, np.zeros((3, 1))]).reshape(-1)]
        fields = dict(frame_id=camera.frame_id, width=int(camera.width),
                      height=int(camera.height), distortion_model=model, D=d, K=k, R=r, P=p)

        def pb() -> CameraCalibration:
            return CameraCalibration(timestamp=_pb_time(stamp), **fields)

        js = {"timestamp": _json_time(stamp), **fields} if self.message_encoding == "json" \
            else None
        self._write(topic, "foxglove.CameraCalibration", stamp, pb, js)

    def write_transforms(self, topic: str, stamp_ns: int,
                         transforms: list[tuple[str, str, np.ndarray]]) -> None:
        """Write one ``foxglove.FrameTransforms`` holding several links at one time.

        Parameters
        ----------
        topic : str
            ``/tf`` (moving links) or ``/tf_static`` (fixed links).
        stamp_ns : int
            Timestamp of every transform in the message, nanoseconds.
        transforms : list of (parent, child, T_parent_child)
            ``T_parent_child`` (4, 4) float64 rigid transform, metres: the pose of
            ``child`` in ``parent``.
        """
        self._check_open()
        stamp = _check_stamp(stamp_ns)
        items = []
        for i, item in enumerate(transforms):
            try:
                parent, child, t = item
            except (TypeError, ValueError):
                raise ValueError(f"transforms[{i}] must be (parent, child, T 4x4), "
                                 f"got {item!r}") from None
            t = np.asarray(t, dtype=np.float64)
            if t.shape != (4, 4) or not np.all(np.isfinite(t)):
                raise ValueError(f"transforms[{i}] ({parent} -> {child}): T must be a finite "
                                 f"(4, 4) matrix, got shape {t.shape}")
            r = t[:3, :3]
            if (np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0
                    or np.abs(t[3] - [0, 0, 0, 1]).max() > 1e-12):
                raise ValueError(f"transforms[{i}] ({parent} -> {child}): T is not a rigid "
                                 f"transform (rotation not orthonormal or last row not 0 0 0 1)")
            if not (isinstance(parent, str) and isinstance(child, str) and parent and child):
                raise ValueError(f"transforms[{i}]: frame names must be non-empty strings, "
                                 f"got {parent!r}, {child!r}")
            q = matrix_to_quat(r)
            items.append((parent, child, [float(x) for x in t[:3, 3]], [float(x) for x in q]))
        if not items:
            raise ValueError("transforms must hold at least one (parent, child, T)")

        def pb() -> FrameTransforms:
            return FrameTransforms(transforms=[
                FrameTransform(timestamp=_pb_time(stamp), parent_frame_id=p, child_frame_id=c,
                               translation=Vector3(x=tr[0], y=tr[1], z=tr[2]),
                               rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))
                for p, c, tr, q in items])

        js = None
        if self.message_encoding == "json":
            js = {"transforms": [
                {"timestamp": _json_time(stamp), "parent_frame_id": p, "child_frame_id": c,
                 "translation": dict(zip("xyz", tr, strict=True)),
                 "rotation": dict(zip("xyzw", q, strict=True))}
                for p, c, tr, q in items]}
        self._write(topic, "foxglove.FrameTransforms", stamp, pb, js)

    def write_image(self, topic: str, stamp_ns: int, frame_id: str, image: np.ndarray,
                    encoding: str = "png", jpeg_quality: int = 95) -> None:
        """Write an image as ``foxglove.CompressedImage`` or ``foxglove.RawImage``.

        Parameters
        ----------
        topic : str
            ``/camera/image`` (views) or ``/camera/laser_image`` (laser frames).
        stamp_ns : int
            The exposure time, nanoseconds (the pose is looked up at this time).
        frame_id : str
            The camera's optical frame; must match a calibration's ``frame_id``.
        image : (H, W) or (H, W, 3) uint8 / uint16
            Grey or RGB pixels.
        encoding : str
            ``png`` or ``jpeg`` (CompressedImage); ``mono8``, ``rgb8``, ``bgr8`` or
            ``mono16`` (RawImage).
        jpeg_quality : int
            JPEG quality 1..100.
        """
        self._check_open()
        stamp = _check_stamp(stamp_ns)
        if not isinstance(frame_id, str) or not frame_id:
            raise ValueError(f"frame_id must be a non-empty string, got {frame_id!r}")
        enc = normalize_encoding(encoding)
        if enc not in COMPRESSED_ENCODINGS + RAW_ENCODINGS:
            raise ValueError(f"image encoding must be one of "
                             f"{', '.join(COMPRESSED_ENCODINGS + RAW_ENCODINGS)}, "
                             f"got {encoding!r}")
        data = encode_image(image, enc, jpeg_quality)
        js: dict[str, Any] | None = None
        if enc in COMPRESSED_ENCODINGS:
            def pb() -> CompressedImage:
                return CompressedImage(timestamp=_pb_time(stamp), frame_id=frame_id,
                                       data=data, format=enc)

            if self.message_encoding == "json":
                js = {"timestamp": _json_time(stamp), "frame_id": frame_id,
                      "data": base64.b64encode(data).decode("ascii"), "format": enc}
            self._write(topic, "foxglove.CompressedImage", stamp, pb, js)
        else:
            h, w = image.shape[:2]
            step = len(data) // h

            def pb() -> RawImage:  # type: ignore[misc]
                return RawImage(timestamp=_pb_time(stamp), frame_id=frame_id, width=w,
                                height=h, encoding=enc, step=step, data=data)

            if self.message_encoding == "json":
                js = {"timestamp": _json_time(stamp), "frame_id": frame_id, "width": w,
                      "height": h, "encoding": enc, "step": step,
                      "data": base64.b64encode(data).decode("ascii")}
            self._write(topic, "foxglove.RawImage", stamp, pb, js)

    # ------------------------------------------------------------------ finishing
    def close(self) -> None:
        """Finish the file (summary, indexes) and move it onto ``path``. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self._tmp_path, self.path)
        except BaseException:
            self._discard()
            raise
        _log.debug("wrote recording %s", self.path)

    def abort(self) -> None:
        """Give up: close and delete the temporary file; ``path`` is left untouched."""
        if self._closed:
            return
        self._closed = True
        self._discard()

    def _discard(self) -> None:
        try:
            self._file.close()
        finally:
            self._tmp_path.unlink(missing_ok=True)
