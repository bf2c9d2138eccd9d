"""Reading recordings (``recording-format.md``) into a :class:`~.model.Recording`.

:func:`read_recording` reads any MCAP recording that follows the contract, whoever wrote
it: robo3d's simulator, a converter, or a real cell's ROS 2 bag; :func:`probe_recording`
summarises one cheaply and never raises (the workflow calls it for every recording of a
batch while it builds the DAG); :func:`bag_files` lists the MCAP files of a recording;
:func:`read_ground_truth_tf` reads a simulated recording's true ``base -> flange`` samples.

What is read
------------
- Foxglove schemas encoded as Protobuf (``protobuf``; decoded generically from the
  schema's own ``FileDescriptorSet``, so other builds of the schemas read too) or as JSON
  (``json`` / ``jsonschema``; ``bytes`` base64, timestamps ``{"sec", "nsec"}``; the
  protobuf-style ``{"seconds", "nanos"}`` is accepted too):
  ``foxglove.FrameTransforms`` / ``foxglove.FrameTransform`` on the tf topics,
  ``foxglove.CameraCalibration`` on the calibration topic, ``foxglove.CompressedImage``
  (png/jpeg) and ``foxglove.RawImage`` (mono8, rgb8, bgr8, mono16) on the image topics.
- ROS 2 messages as a ROS 2 cell records them (``cdr`` with ``ros2msg`` schemas, decoded
  by ``mcap-ros2-support`` from the schema text in the file, no conversion step):
  ``tf2_msgs/msg/TFMessage`` (or ``geometry_msgs/msg/TransformStamped``) on the tf
  topics, ``sensor_msgs/msg/CameraInfo`` on the calibration topic,
  ``sensor_msgs/msg/Image`` (mono8, rgb8, bgr8, mono16 and the aliases 8UC1, 8UC3,
  16UC1; big-endian mono16 is byte-swapped) and ``sensor_msgs/msg/CompressedImage``
  (png/jpeg, image_transport's ``"rgb8; jpeg compressed bgr8"`` style formats, and
  ``compressedDepth`` PNGs) on the image topics, and, when asked
  (``joint_states=True``), ``sensor_msgs/msg/JointState``. ROS 1 style names
  (``sensor_msgs/Image``) are accepted; ``ros2idl`` schemas are not (mcap-ros2-support
  reads ``ros2msg`` only).
- Other topics are skipped unread (their counts and log times are kept in
  :attr:`Recording.topics`). A role topic with any other schema or encoding is a
  :class:`~robo3d.errors.RecordingError` naming the topic and the schema.
- A recording is one ``.mcap`` file or a rosbag2 directory: ``metadata.yaml`` and the
  ``.mcap`` files it lists (a split bag), read in order as one recording. A directory
  without ``metadata.yaml`` (the recorder died before writing it) is read from its
  ``.mcap`` files in split order with a warning; files listed but missing are reported
  and skipped. rosbag2's own file or message compression and non-MCAP storage
  (``sqlite3``) are errors that say how to convert.

Frames and times
----------------
- ``frames`` maps roles to recorded frame names (the config's ``frames`` section, e.g.
  ``{"base": "base_link", "flange": "tool0", "camera": "camera_color_optical_frame",
  "laser": "laser_link"}``). The recorded names are renamed to the roles in the
  transform tree, in images' ``frame_id`` and in calibrations, so the pipeline sees only
  roles. A recording that uses the role names themselves reads unchanged with the same
  map (one config serves a batch of ROS bags and native recordings); one that has both
  a role's recorded name and the role's own name is an error (which one is meant is
  ambiguous). A leading ``/`` on a frame name is dropped, as tf2 does.
- The time of a message is its own stamp (the ``timestamp`` field; ROS 2's
  ``header.stamp``), not the MCAP log time. A message without one (an unset protobuf
  field, a JSON message without the key, a ROS 2 stamp of exactly 0) falls back to its
  log time, with a warning (not for ``/tf_static``, whose stamps do not matter).
  ``stamp_source="log_time"`` uses the log time (the recorder's receive time) for every
  message, for cells whose camera clock is not the robot's; ``image_offset_ns`` is added
  to every image stamp (a known constant latency between the camera's and the robot's
  clocks). Stamps must lie in ``[0, 2**63)`` ns.

Choices
-------
- The file is scanned record by record with robo3d's own framing loop (the record layout
  of the MCAP specification; ``mcap``'s record classes parse the rare records), so that
  damage is located to the byte:

  * a file that ends early (truncated, or whose framing breaks) is read up to the last
    intact record; a warning says how many bytes were lost, from which byte, and the log
    time of the last intact message. If what remains lacks a required role, the
    :class:`RecordingError` says the file was truncated.
  * a chunk whose CRC does not match (or that does not decompress) is **skipped with a
    warning** naming its byte offset and log-time range. Skipping is robust because a
    chunk's framing (its length) is independent of its content, and the schemas and
    channels it may have carried are repeated in the summary section. Anything the lost
    messages leave missing is still caught: a role without messages, a pose gap wider
    than ``max_pose_gap`` at lookup. Decompression is streamed and bounded by the
    chunk's declared size, so a damaged size field cannot exhaust memory.
  * an attachment whose CRC does not match is skipped with a warning.
- Transforms: non-finite values, or a quaternion whose norm is off by more than 1e-3,
  are errors naming topic, link and time; a smaller deviation is renormalised.
  Timestamps out of order on a link are sorted with a warning; duplicated stamps keep
  the last sample (with a warning when the values differ).
- Images are kept encoded. Out-of-order timestamps on an image topic are sorted with a
  warning; an exact duplicate (same topic, frame_id and stamp) keeps the last one.
- Calibrations are keyed by ``frame_id``; when a frame is calibrated more than once
  with different values, the last calibration is kept and a warning says so.
  ``distortion_model``: ``plumb_bob`` (4 or 5 coefficients), ``rational_polynomial``
  (k4..k6 must be zero: kept as plumb_bob, else unsupported), or empty with an empty or
  all-zero ``D`` (no distortion; an empty model with 5 coefficients is read as
  plumb_bob with a warning, as some ROS drivers leave the name empty). ``R`` and ``P``
  are ignored: images are the raw (distorted, unrectified) images that ``K`` and ``D``
  describe. A ROS ``CameraInfo`` with binning or a region of interest is unsupported
  (its ``K`` describes another image than the one recorded).
- ``require=True`` checks completeness: each requested role has messages; when there
  are images, a calibration for each image's ``frame_id`` and a transform chain from
  ``base_frame`` to it (the chain's structure only: whether a pose exists at each
  image's time is checked by :meth:`Recording.camera_poses`). ``require=False`` skips
  these checks (damaged or non-finite data are errors either way).
"""

from __future__ import annotations

import base64
import io
import json
import logging
import math
import os
import re
import struct
import zlib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Metadata,
    MetadataIndex,
    Statistics,
)
from mcap.records import Schema as McapSchema

from ..camera import CameraModel
from ..errors import CalibrationError, ImageDecodeError, RecordingError, TransformError
from ..transforms import TransformBuffer
from .images import RAW_ENCODINGS, normalize_encoding
from .model import FRAME_ROLES, ImageMessage, JointStates, Recording, TopicMap, TopicStats

__all__ = [
    "RecordingSummary",
    "read_recording",
    "probe_recording",
    "bag_files",
    "read_ground_truth_tf",
    "GROUND_TRUTH_TF",
    "STAMP_SOURCES",
]

_log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
#: Name of the attachment holding the true ``base -> flange`` samples.
GROUND_TRUTH_TF = "ground_truth/tf.json"
#: Where a message's time comes from: its own stamp, or the MCAP log time.
STAMP_SOURCES = ("header", "log_time")

_TF_SCHEMAS = ("foxglove.FrameTransforms", "foxglove.FrameTransform")
_CALIB_SCHEMAS = ("foxglove.CameraCalibration",)
_IMAGE_SCHEMAS = ("foxglove.CompressedImage", "foxglove.RawImage")
_ROS_TF = ("tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped")
_ROS_CALIB = ("sensor_msgs/msg/CameraInfo",)
_ROS_IMAGE = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_ROS_JOINTS = ("sensor_msgs/msg/JointState",)
_ROLES = ("views", "laser")
_QUAT_TOL = 1e-3
_MAX_STAMP = 2**63 - 1
_DEFAULT_TOPICS = TopicMap()  # the contract's default topic names (frozen)


def _ros_type(name: str) -> str:
    """``sensor_msgs/Image`` -> ``sensor_msgs/msg/Image`` (ROS 1 style names)."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


# =========================================================================== scanning
class _Schema(NamedTuple):
    id: int
    name: str
    encoding: str
    data: bytes


class _Channel(NamedTuple):
    id: int
    schema_id: int
    topic: str
    message_encoding: str


@dataclass
class _Scan:
    """What a record-by-record pass over a file found."""

    path: str
    size: int
    schemas: dict[int, _Schema] = field(default_factory=dict)
    channels: dict[int, _Channel] = field(default_factory=dict)
    # (channel id, log time, data) in file order, for the kept channels
    messages: list[tuple[int, int, bytes]] = field(default_factory=list)
    counts: dict[int, int] = field(default_factory=dict)  # messages per channel id
    log_times: dict[int, list[int]] = field(default_factory=dict)  # per channel, file order
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    truncated: str | None = None  # description of what was lost, if anything
    damaged: list[str] = field(default_factory=list)  # records skipped as corrupt
    data_end_seen: bool = False
    last_log_time: int | None = None


class _Corrupt(Exception):
    """A record whose framing is intact but whose content is not."""


def _str(mv: memoryview, off: int) -> tuple[str, int]:
    (n,) = struct.unpack_from("<I", mv, off)
    off += 4
    if off + n > len(mv):
        raise _Corrupt("string runs past the end of its record")
    return bytes(mv[off: off + n]).decode("utf-8"), off + n


def _parse_schema(mv: memoryview) -> _Schema:
    (sid,) = struct.unpack_from("<H", mv, 0)
    name, off = _str(mv, 2)
    enc, off = _str(mv, off)
    (n,) = struct.unpack_from("<I", mv, off)
    off += 4
    if off + n > len(mv):
        raise _Corrupt("schema data runs past the end of its record")
    return _Schema(sid, name, enc, bytes(mv[off: off + n]))


def _parse_channel(mv: memoryview) -> _Channel:
    cid, sid = struct.unpack_from("<HH", mv, 0)
    topic, off = _str(mv, 4)
    enc, off = _str(mv, off)
    return _Channel(cid, sid, topic, enc)


def _opname(opcode: int) -> str:
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"unknown (opcode 0x{opcode:02x})"


def _fmt_time(t: int | None) -> str:
    return "none" if t is None else f"{t} ns ({t / 1e9:.6f} s)"


class _Scanner:
    """Record-by-record reader of one MCAP file (the framing of the MCAP spec)."""

    def __init__(self, path: str, keep_topic: Callable[[str], bool],
                 keep_attachment_data: bool = True) -> None:
        self.keep_topic = keep_topic
        self.keep_attachment_data = keep_attachment_data
        self.scan = _Scan(path=path, size=0)
        self._pending: list[tuple[int, int, bytes]] = []  # messages of not-yet-known channels
        self._n_messages = 0
        self._bad_log_times = 0

    # ------------------------------------------------------------------ records
    def _message(self, mv: memoryview) -> None:
        if len(mv) < 22:
            raise _Corrupt(f"message record of {len(mv)} bytes is shorter than its header")
        cid, _seq, log_time, _pub = struct.unpack_from("<HIQQ", mv, 0)
        s = self.scan
        if log_time > _MAX_STAMP:  # a damaged header: no time can be that late
            self._bad_log_times += 1
            return
        s.counts[cid] = s.counts.get(cid, 0) + 1
        lt = s.log_times.get(cid)
        if lt is None:
            s.log_times[cid] = [log_time]
        else:
            lt.append(log_time)
        self._n_messages += 1
        if s.last_log_time is None or log_time > s.last_log_time:
            s.last_log_time = log_time
        ch = s.channels.get(cid)
        if ch is None:
            self._pending.append((cid, log_time, bytes(mv[22:])))
        elif self.keep_topic(ch.topic):
            s.messages.append((cid, log_time, bytes(mv[22:])))

    def _inner(self, opcode: int, mv: memoryview) -> None:
        if opcode == Opcode.MESSAGE:
            self._message(mv)
        elif opcode == Opcode.SCHEMA:
            sch = _parse_schema(mv)
            self.scan.schemas[sch.id] = sch
        elif opcode == Opcode.CHANNEL:
            ch = _parse_channel(mv)
            self.scan.channels[ch.id] = ch

    def _chunk(self, mv: memoryview, pos: int) -> None:
        start, end, usize, crc = struct.unpack_from("<QQQI", mv, 0)
        compression, off = _str(mv, 28)
        (n,) = struct.unpack_from("<Q", mv, off)
        off += 8
        if off + n > len(mv):
            raise _Corrupt("chunk data runs past the end of its record")
        raw = mv[off: off + n]
        where = f"chunk at byte {pos} (messages logged {start} .. {end} ns)"
        try:
            if compression == "zstd":
                data = _zstd_bounded(raw, usize)
            elif compression == "lz4":
                import lz4.frame

                data = lz4.frame.LZ4FrameDecompressor().decompress(bytes(raw),
                                                                    max_length=usize + 1)
            elif compression == "":
                data = bytes(raw)
            else:
                raise RecordingError(f"{where} uses compression {compression!r}, which this "
                                     f"reader does not support (zstd, lz4 or none)",
                                     path=self.scan.path)
        except ImportError as exc:
            raise RecordingError(f"{where} is {compression}-compressed and the module to "
                                 f"decompress it is missing ({exc}); pip install zstandard lz4",
                                 path=self.scan.path) from None
        except RecordingError:
            raise
        except Exception as exc:
            raise _Corrupt(f"{where} does not decompress ({type(exc).__name__}: {exc})") from None
        if len(data) != usize:
            raise _Corrupt(f"{where} decompresses to {len(data)} bytes, its header says {usize}")
        if crc != 0 and zlib.crc32(data) != crc:
            raise _Corrupt(f"{where} fails its CRC check (expected 0x{crc:08x}, "
                           f"got 0x{zlib.crc32(data):08x})")
        dmv = memoryview(data)
        o = 0
        records: list[tuple[int, memoryview]] = []
        while o < len(dmv):
            if o + 9 > len(dmv):
                raise _Corrupt(f"{where}: a record header runs past the end of the chunk")
            op, ln = struct.unpack_from("<BQ", dmv, o)
            if o + 9 + ln > len(dmv):
                raise _Corrupt(f"{where}: a {_opname(op)} record runs past the end of the chunk")
            records.append((op, dmv[o + 9: o + 9 + ln]))
            o += 9 + ln
        for op, rec in records:  # all-or-nothing: framing checked first
            self._inner(op, rec)

    def _attachment(self, body: bytes, pos: int) -> None:
        att = Attachment.read(_stream(body))
        (crc,) = struct.unpack_from("<I", body, len(body) - 4)
        if self.keep_attachment_data and crc != 0 and zlib.crc32(body[:-4]) != crc:
            raise _Corrupt(f"attachment {att.name!r} at byte {pos} fails its CRC check")
        self.scan.attachments[att.name] = att.data if self.keep_attachment_data else b""

    # ------------------------------------------------------------------ main loop
    def run(self) -> _Scan:
        s = self.scan
        path = s.path
        try:
            s.size = os.path.getsize(path)
            f = open(path, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            raise RecordingError(f"cannot open the recording: {exc.strerror or exc}",
                                 path=path) from None
        with f:
            magic = f.read(8)
            if magic != MAGIC:
                if magic and len(magic) < 8 and MAGIC.startswith(magic):
                    raise RecordingError(f"truncated: the file has only {len(magic)} bytes, "
                                         f"part of the MCAP magic", path=path)
                raise RecordingError(f"not an MCAP file (it starts with {magic!r}, an MCAP "
                                     f"file starts with {MAGIC!r})", path=path)
            pos = 8
            footer_seen = False
            while pos < s.size:
                hdr = f.read(9)
                if len(hdr) < 9:
                    self._truncated(pos, f"a record header needs 9 bytes, "
                                         f"{len(hdr)} remain")
                    break
                opcode, length = struct.unpack("<BQ", hdr)
                remain = s.size - pos - 9
                if length > remain:
                    self._truncated(pos, f"a {_opname(opcode)} record claims {length} bytes, "
                                         f"{remain} remain")
                    break
                body = f.read(length)
                try:
                    self._record(opcode, body, pos)
                except _Corrupt as exc:
                    self._warn(f"{exc}; skipped it (its content is lost)")
                    s.damaged.append(str(exc))
                except RecordingError:
                    raise
                except Exception as exc:  # struct/unicode/mcap errors of a damaged record
                    text = (f"the {_opname(opcode)} record at byte {pos} is corrupt "
                            f"({type(exc).__name__}: {exc})")
                    self._warn(f"{text}; skipped it")
                    s.damaged.append(text)
                pos += 9 + length
                if opcode == Opcode.FOOTER:
                    footer_seen = True
                    tail = f.read(8)
                    if tail != MAGIC:
                        self._warn("the file ends without the closing MCAP magic after its "
                                   "footer (truncated in the last bytes; no data lost)")
                    break
            else:
                if not footer_seen:
                    self._truncated(pos, "the file ends before its footer")
        # messages whose channel record came later (or only in the summary section)
        for cid, log_time, data in self._pending:
            ch = s.channels.get(cid)
            if ch is not None and self.keep_topic(ch.topic):
                s.messages.append((cid, log_time, data))
        if self._bad_log_times:
            text = (f"{self._bad_log_times} messages have a log time beyond 2**63 ns (damaged "
                    f"message headers); skipped them")
            self._warn(text)
            s.damaged.append(text)
        lost = sorted({cid for cid, _, _ in self._pending if cid not in s.channels})
        if lost:
            n = sum(1 for cid, _, _ in self._pending if cid not in s.channels)
            self._warn(f"{n} messages on channel ids {lost} have no channel record "
                       f"(lost with a damaged chunk or summary); skipped them")
        return s

    def _record(self, opcode: int, body: bytes, pos: int) -> None:
        s = self.scan
        if opcode == Opcode.CHUNK:
            self._chunk(memoryview(body), pos)
        elif opcode in (Opcode.MESSAGE, Opcode.SCHEMA, Opcode.CHANNEL):
            self._inner(opcode, memoryview(body))
        elif opcode == Opcode.METADATA:
            md = Metadata.read(_stream(body))
            s.metadata.setdefault(md.name, {}).update(md.metadata)
        elif opcode == Opcode.ATTACHMENT:
            self._attachment(body, pos)
        elif opcode == Opcode.DATA_END:
            s.data_end_seen = True

    def _warn(self, text: str) -> None:
        self.scan.warnings.append(text)

    def _truncated(self, pos: int, what: str) -> None:
        s = self.scan
        lost = s.size - pos
        if s.data_end_seen:
            text = (f"the file is truncated in its summary section at byte {pos} of {s.size} "
                    f"({what}); every message is intact")
            self._warn(text)
            return
        text = (f"the file is truncated or damaged at byte {pos} of {s.size} ({what}): its "
                f"last {lost} bytes are unusable and at least one record and the summary "
                f"section are lost; read {self._n_messages} intact messages, the last logged "
                f"at {_fmt_time(s.last_log_time)}")
        s.truncated = text
        self._warn(text)


def _zstd_bounded(raw: memoryview, usize: int) -> bytes:
    """Decompress one zstd frame, never producing more than ``usize + 1`` bytes (a damaged
    size field or frame header must not allocate gigabytes)."""
    import zstandard

    reader = zstandard.ZstdDecompressor().stream_reader(bytes(raw))
    parts, total = [], 0
    while total <= usize:
        piece = reader.read(min(1 << 24, usize + 1 - total))
        if not piece:
            break
        parts.append(piece)
        total += len(piece)
    return b"".join(parts)


def _stream(body: bytes) -> Any:
    from mcap.data_stream import ReadDataStream

    return ReadDataStream(io.BytesIO(body))


def _scan_file(path: str, keep_topic: Callable[[str], bool],
               keep_attachment_data: bool = True) -> _Scan:
    return _Scanner(path, keep_topic, keep_attachment_data).run()


# =========================================================================== files
def bag_files(path: str | os.PathLike[str]) -> tuple[list[str], list[str]]:
    """The MCAP files of a recording, in order, and warnings about the set.

    Parameters
    ----------
    path : str or path-like
        An ``.mcap`` file, or a rosbag2 directory (``metadata.yaml`` and its ``.mcap``
        files; without ``metadata.yaml``, every ``.mcap`` in it in split order).

    Returns
    -------
    files : list of str
    warnings : list of str
        Files listed in ``metadata.yaml`` but missing, a missing or unreadable
        ``metadata.yaml``, ``.mcap`` files present but not listed.

    Raises
    ------
    RecordingError
        No such file or directory; a directory without ``.mcap`` files; a bag with
        another storage (``sqlite3``) or with rosbag2's own compression.
    """
    spath = os.fspath(path)
    if os.path.isfile(spath):
        return [spath], []
    if not os.path.isdir(spath):
        raise RecordingError("no such file or directory", path=spath)
    warnings: list[str] = []
    present = sorted((f for f in os.listdir(spath) if f.endswith(".mcap")), key=_split_key)
    meta_path = os.path.join(spath, "metadata.yaml")
    info = None
    if os.path.isfile(meta_path):
        try:
            import yaml

            with open(meta_path, encoding="utf-8") as f:
                doc = yaml.safe_load(f)
            info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
            if not isinstance(info, dict):
                raise ValueError("no rosbag2_bagfile_information mapping")
        except Exception as exc:  # yaml errors, bad structure: fall back to the files
            warnings.append(f"metadata.yaml is unreadable ({type(exc).__name__}: {exc}); "
                            f"read the .mcap files in split order")
            info = None
    elif present:
        warnings.append("the rosbag2 directory has no metadata.yaml (the recorder did not "
                        "finish); read its .mcap files in split order")
    if info is not None:
        storage = str(info.get("storage_identifier", "mcap") or "mcap")
        if storage != "mcap":
            raise RecordingError(f"rosbag2 storage {storage!r} is not supported: robo3d reads "
                                 f"MCAP bags (convert with `ros2 bag convert` to "
                                 f"storage_id mcap)", path=spath)
        mode = str(info.get("compression_mode", "") or "")
        if mode:
            fmt = info.get("compression_format", "")
            raise RecordingError(f"rosbag2 compression (mode {mode!r}, format {fmt!r}) is not "
                                 f"supported: record with MCAP's own chunk compression "
                                 f"(`ros2 bag record -s mcap --storage-preset-profile "
                                 f"zstd_fast`), or decompress the files first "
                                 f"(`zstd -d`, then fix metadata.yaml)", path=spath)
        listed = [str(p) for p in (info.get("relative_file_paths") or [])]
        files = []
        for rel in listed:
            full = os.path.join(spath, rel)
            if os.path.isfile(full):
                files.append(full)
            else:
                warnings.append(f"{rel} is listed in metadata.yaml but missing; its "
                                f"messages are lost")
        extra = [f for f in present if os.path.join(spath, f) not in files]
        if extra:
            warnings.append(f"{', '.join(extra)} not listed in metadata.yaml; read too")
            files += [os.path.join(spath, f) for f in extra]
    else:
        files = [os.path.join(spath, f) for f in present]
    if not files:
        raise RecordingError("a directory without .mcap files (a recording is an .mcap file "
                             "or a rosbag2 directory with metadata.yaml and .mcap files)",
                             path=spath)
    return files, warnings


def _split_key(name: str) -> tuple[str, int]:
    """Split bags number their files ``<bag>_0.mcap``, ``<bag>_1.mcap``, ... ``_10``."""
    m = re.match(r"^(.*?)(\d+)\.mcap$", name)
    return (m.group(1), int(m.group(2))) if m else (name, -1)


# =========================================================================== decoding
_Decoder = tuple[Callable[[bytes], Any], str]  # (decode function, kind)


def _decoder_for(scan: _Scan, ch: _Channel, factories: dict[str, Any]) -> _Decoder:
    """The decoder of a channel and its kind: ``protobuf``, ``json`` or ``ros2``."""
    sch = scan.schemas.get(ch.schema_id)
    sname = sch.name if sch is not None else "(no schema)"
    senc = sch.encoding if sch is not None else ""
    if ch.message_encoding == "protobuf" and sch is not None and senc == "protobuf":
        try:
            dec = factories["protobuf"].decoder_for(
                "protobuf", McapSchema(id=sch.id, name=sch.name, encoding=sch.encoding,
                                       data=sch.data))
        except Exception as exc:
            raise RecordingError(f"the protobuf schema {sname!r} does not load "
                                 f"({type(exc).__name__}: {exc})", path=scan.path,
                                 topic=ch.topic) from None
        if dec is None:  # pragma: no cover - the factory handles every protobuf schema
            raise RecordingError(f"no protobuf decoder for schema {sname!r}", path=scan.path,
                                 topic=ch.topic)
        return dec, "protobuf"
    if ch.message_encoding == "json" and senc in ("jsonschema", ""):
        return json.loads, "json"
    if ch.message_encoding == "cdr" and sch is not None and senc == "ros2msg":
        try:
            dec = factories["ros2"].decoder_for(
                "cdr", McapSchema(id=sch.id, name=sch.name, encoding=sch.encoding,
                                  data=sch.data))
        except Exception as exc:  # parse errors of the message definition text
            raise RecordingError(f"the ROS 2 schema {sname!r} does not parse "
                                 f"({type(exc).__name__}: {exc})", path=scan.path,
                                 topic=ch.topic) from None
        if dec is None:  # pragma: no cover - checked above
            raise RecordingError(f"no ROS 2 decoder for schema {sname!r}", path=scan.path,
                                 topic=ch.topic)
        return dec, "ros2"
    if ch.message_encoding == "cdr":
        raise RecordingError(
            f"ROS 2 schema {sname!r} is encoded as {senc or '(none)'!r}: robo3d decodes CDR "
            f"messages with ros2msg schemas (mcap-ros2-support); record with a ROS 2 "
            f"distribution that writes ros2msg definitions", path=scan.path, topic=ch.topic)
    raise RecordingError(
        f"unsupported message encoding {ch.message_encoding!r} (schema {sname!r}, schema "
        f"encoding {senc!r}): robo3d reads Foxglove schemas encoded as protobuf or json and "
        f"ROS 2 messages encoded as cdr", path=scan.path, topic=ch.topic)


def _get(obj: Any, is_json: bool, name: str, default: Any = None) -> Any:
    if is_json:
        return obj.get(name, default) if isinstance(obj, dict) else default
    return getattr(obj, name, default)


def _stamp(obj: Any, is_json: bool) -> int | None:
    """The ``timestamp`` field in nanoseconds, or None when absent."""
    if is_json:
        ts = obj.get("timestamp") if isinstance(obj, dict) else None
        if ts is None:
            return None
        if isinstance(ts, dict):
            sec = ts.get("sec", ts.get("seconds"))
            nsec = ts.get("nsec", ts.get("nanos", 0))
            if isinstance(sec, int | float) and isinstance(nsec, int | float):
                return int(sec) * 1_000_000_000 + int(nsec)
        raise ValueError(f"timestamp must be {{'sec': int, 'nsec': int}}, got {ts!r}")
    if not obj.HasField("timestamp"):
        return None
    return obj.timestamp.seconds * 1_000_000_000 + obj.timestamp.nanos


def _bytes(obj: Any, is_json: bool, name: str) -> bytes:
    v = _get(obj, is_json, name, b"" if not is_json else "")
    if is_json:
        if not isinstance(v, str):
            raise ValueError(f"field {name!r} must be a base64 string, got {type(v).__name__}")
        return base64.b64decode(v, validate=True)
    return bytes(v)


def _vec(obj: Any, is_json: bool, keys: str) -> list[float]:
    if obj is None:
        return [math.nan] * len(keys)
    out = []
    for k in keys:
        v = _get(obj, is_json, k, 0.0)
        out.append(float(v) if v is not None else math.nan)
    return out


def _ros(obj: Any, *names: str, default: Any = None) -> Any:
    """A field of a decoded ROS message under its ROS 2 or ROS 1 name."""
    for n in names:
        v = getattr(obj, n, None)
        if v is not None:
            return v
    return default


@dataclass
class _TfSamples:
    topic: str
    parent: str
    child: str
    stamps: list[int] = field(default_factory=list)
    values: list[list[float]] = field(default_factory=list)  # tx ty tz qx qy qz qw


@dataclass
class _TopicTimes:
    schema: str
    encoding: str
    log_times: list[int] = field(default_factory=list)
    stamps: list[int] = field(default_factory=list)


def _check_frames(frames: Mapping[str, str] | None) -> dict[str, str]:
    """Validate a role -> recorded-name map; returns it as a plain dict."""
    if frames is None:
        return {}
    out = {str(k): str(v) for k, v in dict(frames).items()}
    bad = [k for k in out if k not in FRAME_ROLES]
    if bad:
        raise ValueError(f"frames keys must be roles among {FRAME_ROLES}, got {sorted(bad)}")
    empty = [k for k, v in out.items() if not v.strip("/")]
    if empty:
        raise ValueError(f"frames must map each role to a non-empty frame name, got "
                         f"{ {k: out[k] for k in empty} }")
    out = {k: (v[1:] if v.startswith("/") else v) for k, v in out.items()}
    names = list(out.values())
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"frames maps two roles to the same frame name(s) {dup}: {out}")
    return out


class _Reader:
    def __init__(self, path: str, topics: TopicMap, roles: tuple[str, ...],
                 max_pose_gap_ns: int, base_frame: str, frames: dict[str, str],
                 stamp_source: str, image_offset_ns: int) -> None:
        self.path = path  # the file being decoded, named in errors
        self.topics = topics
        self.roles = roles
        self.max_gap = max_pose_gap_ns
        self.base_frame = base_frame
        self.frames = frames
        self.rename = {rec: role for role, rec in frames.items() if rec != role}
        self.raw_frames: set[str] = set()
        self.use_log_time = stamp_source == "log_time"
        self.image_offset = int(image_offset_ns)
        self.warnings: list[str] = []
        self.tf_links: dict[tuple[str, str, str], _TfSamples] = {}
        self.calibs: dict[str, tuple[CameraModel, str, int]] = {}
        self.n_calib_msgs = 0
        self.images: dict[str, list[ImageMessage]] = {}
        self.no_stamp: dict[str, int] = {}
        self.joints: list[tuple[int, list[str], list[float]]] = []
        self.times: dict[str, _TopicTimes] = {}

    def warn(self, text: str) -> None:
        self.warnings.append(text)

    def frame(self, name: str) -> str:
        """A recorded frame name as the pipeline sees it (leading ``/`` dropped, renamed
        to its role)."""
        n = name[1:] if name.startswith("/") else name
        self.raw_frames.add(n)
        return self.rename.get(n, n)

    def _check_time(self, st: int, topic: str, log_time: int) -> int:
        if not 0 <= st <= _MAX_STAMP:
            raise RecordingError(f"timestamp {st} ns is outside 0 .. 2**63 ns", path=self.path,
                                 topic=topic, time_ns=log_time if 0 <= log_time else None)
        return st

    # ------------------------------------------------------------------ stamps
    def _time(self, obj: Any, is_json: bool, topic: str, log_time: int) -> int:
        if self.use_log_time:
            return log_time
        st = _stamp(obj, is_json)
        if st is None:
            self.no_stamp[topic] = self.no_stamp.get(topic, 0) + 1
            return log_time
        return self._check_time(st, topic, log_time)

    def _ros_time(self, header: Any, topic: str, log_time: int) -> int:
        if self.use_log_time:
            return log_time
        stamp = getattr(header, "stamp", None)
        if stamp is None:
            raise ValueError("the message has no header.stamp")
        st = int(_ros(stamp, "sec", "secs", default=0)) * 1_000_000_000 + \
            int(_ros(stamp, "nanosec", "nsecs", default=0))
        if st == 0:  # unset by the driver
            if topic != self.topics.tf_static:
                self.no_stamp[topic] = self.no_stamp.get(topic, 0) + 1
            return log_time
        return self._check_time(st, topic, log_time)

    def _record_time(self, topic: str, schema: str, encoding: str, log_time: int,
                     stamp: int | None) -> None:
        t = self.times.get(topic)
        if t is None:
            t = self.times[topic] = _TopicTimes(schema, encoding)
        t.log_times.append(log_time)
        t.stamps.append(log_time if stamp is None else stamp)

    # ------------------------------------------------------------------ common sinks
    def _add_tf(self, topic: str, st: int, parent: str, child: str, t: list[float],
                q: list[float]) -> None:
        if not parent or not child:
            raise TransformError(f"a transform has an empty frame name (parent "
                                 f"{parent!r}, child {child!r})", path=self.path,
                                 topic=topic, time_ns=st)
        parent, child = self.frame(parent), self.frame(child)
        key = (topic, parent, child)
        link = self.tf_links.get(key)
        if link is None:
            link = self.tf_links[key] = _TfSamples(topic, parent, child)
        link.stamps.append(st)
        link.values.append(t + q)

    def _add_calibration(self, topic: str, st: int, fid: str, k_raw: Any, d_raw: Any,
                         width: int, height: int, model: str) -> None:
        self.n_calib_msgs += 1
        recorded = fid

        def fail(what: str) -> CalibrationError:
            return CalibrationError(f"calibration of frame_id {recorded!r}: {what}",
                                    path=self.path, topic=topic, time_ns=st)

        try:
            k = np.array([float(x) for x in (k_raw if k_raw is not None else [])])
            d = np.array([float(x) for x in (d_raw if d_raw is not None else [])])
        except (TypeError, ValueError) as exc:
            raise fail(f"K and D must be numbers ({exc})") from None
        model = model.strip()
        if not fid:
            raise fail("frame_id is empty")
        fid = self.frame(fid)
        if k.size != 9:
            raise fail(f"K must have 9 values, got {k.size}")
        if not (np.all(np.isfinite(k)) and np.all(np.isfinite(d))):
            raise fail(f"non-finite values (K={k.tolist()}, D={d.tolist()})")
        if k[0] == 0:
            raise fail("K[0] is 0: the camera is uncalibrated")
        if model == "":
            if d.size == 0 or not np.any(d):
                d = np.zeros(5)
            elif d.size == 5:
                self.warn(f"{topic}: calibration of {recorded!r} has an empty "
                          f"distortion_model with 5 coefficients; read as plumb_bob")
            else:
                raise fail(f"empty distortion_model with {d.size} non-zero coefficients")
        elif model == "plumb_bob":
            if d.size == 0:
                d = np.zeros(5)
            elif d.size not in (4, 5):
                raise fail(f"plumb_bob needs 5 coefficients (k1 k2 p1 p2 k3), got {d.size}")
        elif model == "rational_polynomial":
            if d.size < 5 or np.any(d[5:] != 0):
                raise fail(f"distortion_model rational_polynomial with non-zero k4..k6 "
                           f"(D={d.tolist()}) is unsupported; robo3d models plumb_bob "
                           f"(k1 k2 p1 p2 k3)")
            d = d[:5]
        else:
            raise fail(f"distortion_model {model!r} is unsupported (plumb_bob, "
                       f"rational_polynomial with k4..k6 = 0, or empty for none)")
        try:
            cam = CameraModel(fid, width, height, k.reshape(3, 3), d)
        except CalibrationError as exc:
            raise fail(exc.reason) from None
        old = self.calibs.get(fid)
        if old is not None:
            o = old[0]
            if not ((o.width, o.height) == (cam.width, cam.height)
                    and np.array_equal(o.K, cam.K) and np.array_equal(o.D, cam.D)):
                self.warn(f"{topic}: frame_id {recorded!r} is calibrated more than once with "
                          f"different values (t={old[2]} and t={st} ns); kept the latest")
                if st < old[2]:
                    return
        self.calibs[fid] = (cam, topic, st)

    def _add_image(self, topic: str, st: int, log_time: int, fid: str, compressed: bool,
                   encoding: str, data: bytes, width: int = 0, height: int = 0,
                   step: int = 0) -> None:
        st = st + self.image_offset
        if not 0 <= st <= _MAX_STAMP:
            raise RecordingError(f"image stamp {st} ns (after timing offset "
                                 f"{self.image_offset} ns) is outside 0 .. 2**63 ns",
                                 path=self.path, topic=topic, time_ns=log_time)
        fid = self.frame(fid) if fid else fid
        if compressed:
            msg = ImageMessage(topic=topic, timestamp_ns=st, frame_id=fid,
                               encoding=normalize_encoding(encoding) if encoding else "",
                               data=data, path=self.path, log_time_ns=log_time)
        else:
            enc = normalize_encoding(encoding)
            if enc not in RAW_ENCODINGS:
                raise ImageDecodeError(f"raw image encoding {encoding!r} is unsupported "
                                       f"(supported: {', '.join(RAW_ENCODINGS)}, and 8UC1, "
                                       f"8UC3, 16UC1)", path=self.path, topic=topic,
                                       time_ns=st)
            msg = ImageMessage(topic=topic, timestamp_ns=st, frame_id=fid, encoding=enc,
                               data=data, width=int(width), height=int(height),
                               step=int(step), path=self.path, log_time_ns=log_time)
        self.images.setdefault(topic, []).append(msg)

    # ------------------------------------------------------------------ foxglove messages
    def tf(self, obj: Any, is_json: bool, schema: str, topic: str, log_time: int) -> int:
        if schema == "foxglove.FrameTransforms":
            items = _get(obj, is_json, "transforms", []) or []
        else:
            items = [obj]
        first = log_time
        for n, tr in enumerate(items):
            if is_json:
                st = self._time(tr, is_json, topic, log_time)
                parent = _get(tr, is_json, "parent_frame_id", "")
                child = _get(tr, is_json, "child_frame_id", "")
                t = _vec(_get(tr, is_json, "translation"), is_json, "xyz")
                q = _vec(_get(tr, is_json, "rotation"), is_json, "xyzw")
            else:  # the hot path (up to 1 kHz): plain attribute access
                if tr.HasField("timestamp") and not self.use_log_time:
                    ts = tr.timestamp
                    st = self._check_time(ts.seconds * 1_000_000_000 + ts.nanos, topic,
                                          log_time)
                else:
                    st = self._time(tr, is_json, topic, log_time)
                parent, child = tr.parent_frame_id, tr.child_frame_id
                v, r = tr.translation, tr.rotation
                t = [v.x, v.y, v.z]
                q = [r.x, r.y, r.z, r.w]
            if n == 0:
                first = st
            self._add_tf(topic, st, str(parent or ""), str(child or ""), t, q)
        return first

    def calibration(self, obj: Any, is_json: bool, topic: str, log_time: int) -> int:
        st = self._time(obj, is_json, topic, log_time)
        self._add_calibration(topic, st, str(_get(obj, is_json, "frame_id", "") or ""),
                              _get(obj, is_json, "K", []) or [],
                              _get(obj, is_json, "D", []) or [],
                              int(_get(obj, is_json, "width", 0) or 0),
                              int(_get(obj, is_json, "height", 0) or 0),
                              str(_get(obj, is_json, "distortion_model", "") or ""))
        return st

    def image(self, obj: Any, is_json: bool, schema: str, topic: str, log_time: int) -> int:
        st = self._time(obj, is_json, topic, log_time)
        fid = str(_get(obj, is_json, "frame_id", "") or "")
        data = _bytes(obj, is_json, "data")
        if schema == "foxglove.CompressedImage":
            self._add_image(topic, st, log_time, fid, True,
                            str(_get(obj, is_json, "format", "") or ""), data)
        else:
            self._add_image(topic, st, log_time, fid, False,
                            str(_get(obj, is_json, "encoding", "") or ""), data,
                            int(_get(obj, is_json, "width", 0) or 0),
                            int(_get(obj, is_json, "height", 0) or 0),
                            int(_get(obj, is_json, "step", 0) or 0))
        return st

    # ------------------------------------------------------------------ ROS 2 messages
    def ros_tf(self, obj: Any, schema: str, topic: str, log_time: int) -> int:
        items = obj.transforms if schema == "tf2_msgs/msg/TFMessage" else [obj]
        first = log_time
        for n, tr in enumerate(items):
            st = self._ros_time(tr.header, topic, log_time)
            if n == 0:
                first = st
            x = tr.transform
            v, r = x.translation, x.rotation
            self._add_tf(topic, st, str(tr.header.frame_id or ""), str(tr.child_frame_id or ""),
                         [float(v.x), float(v.y), float(v.z)],
                         [float(r.x), float(r.y), float(r.z), float(r.w)])
        return first

    def ros_calibration(self, obj: Any, topic: str, log_time: int) -> int:
        st = self._ros_time(obj.header, topic, log_time)
        fid = str(obj.header.frame_id or "")
        width, height = int(obj.width), int(obj.height)
        bx = int(_ros(obj, "binning_x", default=0) or 0)
        by = int(_ros(obj, "binning_y", default=0) or 0)
        roi = _ros(obj, "roi")
        rw = int(getattr(roi, "width", 0) or 0) if roi is not None else 0
        rh = int(getattr(roi, "height", 0) or 0) if roi is not None else 0
        if bx > 1 or by > 1 or ((rw or rh) and (rw, rh) != (width, height)):
            raise CalibrationError(f"calibration of frame_id {fid!r}: CameraInfo with binning "
                                   f"{bx}x{by} or region of interest {rw}x{rh} (image "
                                   f"{width}x{height}) is unsupported: record full-resolution "
                                   f"images, or publish K for the binned/cropped image",
                                   path=self.path, topic=topic, time_ns=st)
        self._add_calibration(topic, st, fid, list(_ros(obj, "k", "K", default=[])),
                              list(_ros(obj, "d", "D", default=[])), width, height,
                              str(obj.distortion_model or ""))
        return st

    def ros_image(self, obj: Any, schema: str, topic: str, log_time: int) -> int:
        st = self._ros_time(obj.header, topic, log_time)
        fid = str(obj.header.frame_id or "")
        data = bytes(obj.data)
        if schema == "sensor_msgs/msg/CompressedImage":
            fmt = str(obj.format or "")
            if "compresseddepth" in fmt.lower() and data[12:20] == b"\x89PNG\r\n\x1a\n":
                data = data[12:]  # image_transport's compressedDepth: a 12-byte header
            self._add_image(topic, st, log_time, fid, True, fmt, data)
            return st
        enc = str(obj.encoding or "")
        if int(obj.is_bigendian or 0) and normalize_encoding(enc) == "mono16":
            step = int(obj.step)
            if step % 2 or len(data) % 2:
                raise ImageDecodeError(f"big-endian mono16 image with odd step {step} or odd "
                                       f"length {len(data)}", path=self.path, topic=topic,
                                       time_ns=st)
            data = np.frombuffer(data, ">u2").astype("<u2").tobytes()
        self._add_image(topic, st, log_time, fid, False, enc, data, int(obj.width),
                        int(obj.height), int(obj.step))
        return st

    def ros_joint_state(self, obj: Any, topic: str, log_time: int) -> int:
        st = self._ros_time(obj.header, topic, log_time)
        names = [str(n) for n in (obj.name or [])]
        pos = [float(x) for x in (obj.position or [])]
        if pos and len(pos) != len(names):
            raise ValueError(f"JointState has {len(names)} names and {len(pos)} positions")
        self.joints.append((st, names, pos))
        return st

    # ------------------------------------------------------------------ assembling
    def check_frame_names(self) -> None:
        for role, rec in self.frames.items():
            if rec != role and rec in self.raw_frames and role in self.raw_frames:
                raise TransformError(
                    f"frames.{role} maps the recorded frame {rec!r} to the role {role!r}, but "
                    f"the recording also has a frame named {role!r}: which one is the "
                    f"{role} is ambiguous (rename the role's frame in the config to the one "
                    f"meant)", path=self.path)

    def build_tf(self) -> TransformBuffer:
        buf = TransformBuffer(max_gap_ns=self.max_gap, path=self.path)
        for (topic, parent, child), link in self.tf_links.items():
            stamps = np.asarray(link.stamps, dtype=np.int64)
            v = np.asarray(link.values, dtype=np.float64).reshape(-1, 7)
            what = f"transform {parent} -> {child}"
            finite = np.all(np.isfinite(v), axis=1)
            if not np.all(finite):
                i = int(np.argmin(finite))
                raise TransformError(f"{what} is not finite (translation {v[i, :3].tolist()}, "
                                     f"rotation {v[i, 3:].tolist()})", path=self.path,
                                     topic=topic, time_ns=int(stamps[i]))
            norm = np.linalg.norm(v[:, 3:], axis=1)
            bad = np.abs(norm - 1.0) > _QUAT_TOL
            if np.any(bad):
                i = int(np.argmax(bad))
                raise TransformError(f"{what}: rotation {v[i, 3:].tolist()} is not a unit "
                                     f"quaternion (norm {norm[i]:.6g}, tolerance {_QUAT_TOL})",
                                     path=self.path, topic=topic, time_ns=int(stamps[i]))
            v[:, 3:] /= norm[:, None]
            if len(stamps) > 1:
                dif = np.diff(stamps)
                n_back = int(np.sum(dif < 0))
                if n_back:
                    self.warn(f"{topic}: {n_back} timestamps of {what} are out of order "
                              f"(e.g. t={int(stamps[1:][dif < 0][0])} ns after a later one); "
                              f"sorted them")
                order = np.argsort(stamps, kind="stable")
                ss, vs = stamps[order], v[order]
                dup = ss[1:] == ss[:-1]
                if np.any(dup):
                    differ = dup & np.any(vs[1:] != vs[:-1], axis=1)
                    if np.any(differ):
                        self.warn(f"{topic}: {int(np.sum(differ))} duplicated timestamps of "
                                  f"{what} carry different values (e.g. t="
                                  f"{int(ss[1:][differ][0])} ns); kept the last")
            static = topic == self.topics.tf_static
            if static and len(stamps) > 1 and np.ptp(v, axis=0).max() > 1e-12:
                self.warn(f"{topic}: static {what} is published {len(stamps)} times with "
                          f"different values; kept the first")
            buf.add(parent, child, stamps, v[:, :3], v[:, 3:], static=static, topic=topic)
        return buf

    def sorted_images(self, topic: str) -> list[ImageMessage]:
        msgs = self.images.get(topic, [])
        if not msgs:
            return []
        stamps = np.array([m.timestamp_ns for m in msgs], dtype=np.int64)
        dif = np.diff(stamps)
        if np.any(dif < 0):
            self.warn(f"{topic}: {int(np.sum(dif < 0))} image timestamps are out of order; "
                      f"sorted them")
        order = np.argsort(stamps, kind="stable")
        msgs = [msgs[i] for i in order]
        out: list[ImageMessage] = []
        n_dup = 0
        for m in msgs:  # a loop over images (views/frames), not pixels
            if out and out[-1].timestamp_ns == m.timestamp_ns and out[-1].frame_id == m.frame_id:
                out[-1] = m
                n_dup += 1
            else:
                out.append(m)
        if n_dup:
            self.warn(f"{topic}: {n_dup} images repeat the timestamp and frame_id of another; "
                      f"kept the last of each")
        return out

    def joint_states(self, topic: str) -> JointStates | None:
        if not self.joints:
            return None
        names: list[str] = []
        index: dict[str, int] = {}
        for _, ns, _ in self.joints:  # a loop over messages
            for n in ns:
                if n not in index:
                    index[n] = len(names)
                    names.append(n)
        order = sorted(range(len(self.joints)), key=lambda i: self.joints[i][0])
        pos = np.full((len(self.joints), len(names)), np.nan)
        for row, i in enumerate(order):
            _, ns, p = self.joints[i]
            if p:
                pos[row, [index[n] for n in ns]] = p
        stamps = np.array([self.joints[i][0] for i in order], dtype=np.int64)
        return JointStates(topic=topic, names=names, stamps_ns=stamps, positions=pos)


def _chain_problem(tf: TransformBuffer, parent: str, child: str) -> str | None:
    """Why ``child`` cannot be expressed in ``parent`` (structure only), or None."""
    parents = {c: p for p, c, _, _ in tf.links()}
    frames = tf.frames
    for f in (parent, child):
        if f not in frames:
            return (f"frame {f!r} is not in the transform tree (frames: "
                    f"{', '.join(sorted(frames)) or 'none'})")

    def up(f: str) -> list[str]:
        chain, seen = [f], {f}
        while chain[-1] in parents and parents[chain[-1]] not in seen:
            chain.append(parents[chain[-1]])
            seen.add(chain[-1])
        return chain

    a, b = up(child), up(parent)
    if set(a) & set(b):
        return None
    return (f"the chain does not connect: {' -> '.join(reversed(a))} and "
            f"{' -> '.join(reversed(b))} have no common frame (missing link between "
            f"{a[-1]!r} and {b[-1]!r})")


def _role_topics(topics: TopicMap, roles: Iterable[str]) -> dict[str, str]:
    return {r: getattr(topics, r) for r in roles}


def _check_roles(roles: Iterable[str]) -> tuple[str, ...]:
    if isinstance(roles, str):
        roles = (roles,)
    out = tuple(roles)
    bad = [r for r in out if r not in _ROLES]
    if bad:
        raise ValueError(f"roles must be among {_ROLES}, got {out!r}")
    return out


def _allowed(kind: str, role: str) -> tuple[str, ...]:
    if kind == "ros2":
        return {"tf": _ROS_TF, "calibration": _ROS_CALIB, "image": _ROS_IMAGE,
                "joints": _ROS_JOINTS}[role]
    return {"tf": _TF_SCHEMAS, "calibration": _CALIB_SCHEMAS, "image": _IMAGE_SCHEMAS,
            "joints": ()}[role]


def _decode_scan(scan: _Scan, rd: _Reader, topics: TopicMap, image_topics: set[str],
                 joints_topic: str | None) -> None:
    """Decode the kept messages of one scanned file into ``rd``."""
    from mcap_protobuf.decoder import DecoderFactory as PbFactory
    from mcap_ros2.decoder import DecoderFactory as Ros2Factory

    factories = {"protobuf": PbFactory(), "ros2": Ros2Factory()}  # fresh: ids are per file
    rd.path = scan.path
    tf_topics = {topics.tf, topics.tf_static}
    decoders: dict[int, tuple[Callable[[bytes], Any], str, str, str, str]] = {}
    for cid, log_time, data in scan.messages:
        dec = decoders.get(cid)
        ch = scan.channels[cid]
        if dec is None:
            fn, kind = _decoder_for(scan, ch, factories)
            sch = scan.schemas.get(ch.schema_id)
            sname = sch.name if sch is not None else ""
            if kind == "ros2":
                sname = _ros_type(sname)
            if not sname and kind == "json" and ch.topic in tf_topics:
                sname = "foxglove.FrameTransforms"
            role = ("tf" if ch.topic in tf_topics else
                    "calibration" if ch.topic == topics.calibration else
                    "image" if ch.topic in image_topics else "joints")
            allowed = _allowed(kind, role)
            if sname not in allowed:
                if role == "joints":  # informational: never stops a reading
                    rd.warn(f"{ch.topic}: joint states with schema {sname or '(none)'!r} "
                            f"({ch.message_encoding}) are not read (expected "
                            f"{' or '.join(_ROS_JOINTS)})")
                    decoders[cid] = (fn, kind, "", ch.topic, "skip")
                    continue
                every = _allowed("protobuf", role) + _allowed("ros2", role)
                raise RecordingError(f"schema {sname or '(none)'!r} ({ch.message_encoding}) "
                                     f"is not supported on this topic (expected "
                                     f"{' or '.join(every)})", path=scan.path, topic=ch.topic)
            dec = decoders[cid] = (fn, kind, sname, ch.topic, role)
        fn, kind, sname, topic, role = dec
        if role == "skip":
            continue
        try:
            obj = fn(data)
            if kind == "ros2":
                if role == "tf":
                    st = rd.ros_tf(obj, sname, topic, log_time)
                elif role == "calibration":
                    st = rd.ros_calibration(obj, topic, log_time)
                elif role == "image":
                    st = rd.ros_image(obj, sname, topic, log_time)
                else:
                    st = rd.ros_joint_state(obj, topic, log_time)
            else:
                is_json = kind == "json"
                if is_json and not isinstance(obj, dict):
                    raise ValueError(f"a JSON message must be an object, got "
                                     f"{type(obj).__name__}")
                if role == "tf":
                    st = rd.tf(obj, is_json, sname, topic, log_time)
                elif role == "calibration":
                    st = rd.calibration(obj, is_json, topic, log_time)
                else:
                    st = rd.image(obj, is_json, sname, topic, log_time)
        except RecordingError:
            raise
        except Exception as exc:  # protobuf/CDR decode errors, JSON errors, base64, types
            raise RecordingError(f"a {sname} message does not decode "
                                 f"({type(exc).__name__}: {exc}); time is its log time",
                                 path=scan.path, topic=topic, time_ns=log_time) from None
        rd._record_time(topic, sname, ch.message_encoding, log_time, st)


def _topic_stats(scans: list[_Scan], rd: _Reader) -> dict[str, TopicStats]:
    out: dict[str, TopicStats] = {}
    lt: dict[str, list[int]] = {}
    for scan in scans:
        for cid, ch in scan.channels.items():
            sch = scan.schemas.get(ch.schema_id)
            name = sch.name if sch is not None else ""
            if ch.topic not in out:
                out[ch.topic] = TopicStats(ch.topic, name, ch.message_encoding)
            lt.setdefault(ch.topic, []).extend(scan.log_times.get(cid, []))
        for cid, times in scan.log_times.items():  # messages whose channel was lost
            if cid not in scan.channels:
                key = f"(channel id {cid}, no channel record)"
                out.setdefault(key, TopicStats(key, "", ""))
                lt.setdefault(key, []).extend(times)
    for topic, st in out.items():
        st.log_times_ns = np.asarray(lt.get(topic, []), dtype=np.int64)
        st.count = len(st.log_times_ns)
        t = rd.times.get(topic)
        if t is not None and len(t.stamps) == st.count:
            st.log_times_ns = np.asarray(t.log_times, dtype=np.int64)  # decode order
            st.stamps_ns = np.asarray(t.stamps, dtype=np.int64)
    return out


def read_recording(path: str | os.PathLike[str], *, topics: TopicMap = _DEFAULT_TOPICS,
                   roles: Iterable[str] = ("views", "laser"),
                   max_pose_gap_ns: int = 50_000_000, base_frame: str = "base",
                   require: bool = True, frames: Mapping[str, str] | None = None,
                   stamp_source: str = "header", image_offset_ns: int = 0,
                   joint_states: bool = False) -> Recording:
    """Read a recording into memory, images still encoded.

    Parameters
    ----------
    path : str or path-like
        An MCAP file following ``recording-format.md`` (Foxglove schemas or ROS 2 CDR),
        or a rosbag2 directory.
    topics : TopicMap
        Which topic carries which role.
    roles : iterable of {"views", "laser"}
        Image roles to load. Calibration and transforms are always read.
    max_pose_gap_ns : int
        Widest gap between two pose samples to interpolate across, nanoseconds (the
        config's ``max_pose_gap``), given to the :class:`TransformBuffer`.
    base_frame : str
        The fixed frame poses are expressed in, as the pipeline names it (after
        ``frames`` renamed the recorded names to roles).
    require : bool
        Check completeness (see the module docstring): every requested role has
        messages, every image a calibration and a transform chain to ``base_frame``.
    frames : mapping of role -> recorded frame name, optional
        Roles among ``base``, ``flange``, ``camera``, ``laser`` (the config's
        ``frames``); recorded names are renamed to the roles.
    stamp_source : {"header", "log_time"}
        A message's time: its own stamp (the contract) or its MCAP log time.
    image_offset_ns : int
        Added to every image's time (views and laser frames), nanoseconds.
    joint_states : bool
        Also read ``sensor_msgs/msg/JointState`` on ``topics.joint_states`` into
        :attr:`Recording.joint_states` (informational; a problem there is a warning).

    Returns
    -------
    Recording
        With ``warnings`` listing everything accepted but suspicious (truncation, skipped
        chunks, sorted timestamps, ...); each is also logged.

    Raises
    ------
    RecordingError
        Not an MCAP file, unsupported schema/encoding on a role topic, undecodable message,
        a required role without messages (saying so when the file is truncated).
    TransformError
        Non-finite or non-unit transforms, a chain from ``base_frame`` to an image's
        frame that does not connect, no transforms at all, an ambiguous frame name.
    CalibrationError
        Missing, unsupported or non-finite calibration.
    ImageDecodeError
        A raw image encoding that is not supported.
    ValueError
        Bad arguments (roles, frames, stamp_source, max_pose_gap_ns).
    """
    spath = os.fspath(path)
    roles = _check_roles(roles)
    if max_pose_gap_ns <= 0:
        raise ValueError(f"max_pose_gap_ns must be positive, got {max_pose_gap_ns}")
    if stamp_source not in STAMP_SOURCES:
        raise ValueError(f"stamp_source must be one of {STAMP_SOURCES}, got {stamp_source!r}")
    frame_map = _check_frames(frames)
    role_topics = _role_topics(topics, roles)
    tf_topics = {topics.tf, topics.tf_static}
    image_topics = set(role_topics.values())
    wanted = tf_topics | {topics.calibration} | image_topics
    joints_topic = topics.joint_states if joint_states else None
    if joints_topic:
        wanted.add(joints_topic)
    files, file_warnings = bag_files(spath)
    rd = _Reader(spath, topics, roles, max_pose_gap_ns, base_frame, frame_map, stamp_source,
                 image_offset_ns)
    rd.warnings.extend(file_warnings)
    scans: list[_Scan] = []
    for f in files:
        scan = _scan_file(f, wanted.__contains__)
        prefix = f"{os.path.basename(f)}: " if len(files) > 1 else ""
        rd.warnings.extend(prefix + w for w in scan.warnings)
        _decode_scan(scan, rd, topics, image_topics, joints_topic)
        scans.append(scan)
    rd.path = files[-1] if len(files) == 1 else spath
    for topic, n in rd.no_stamp.items():
        rd.warn(f"{topic}: {n} messages have no timestamp (absent, or 0 in a ROS header); "
                f"used their log time")
    rd.check_frame_names()
    tf = rd.build_tf()
    metadata: dict[str, dict[str, str]] = {}
    attachments: dict[str, bytes] = {}
    for scan in scans:
        for name, md in scan.metadata.items():
            metadata.setdefault(name, {}).update(md)
        attachments.update(scan.attachments)
    rec = Recording(path=spath, metadata=metadata,
                    calibrations={fid: c[0] for fid, c in rd.calibs.items()}, tf=tf,
                    views=rd.sorted_images(topics.views) if "views" in roles else [],
                    laser_frames=rd.sorted_images(topics.laser) if "laser" in roles else [],
                    attachments=attachments, warnings=rd.warnings, base_frame=base_frame,
                    topics=_topic_stats(scans, rd),
                    joint_states=rd.joint_states(joints_topic) if joints_topic else None,
                    frame_names={role: name for role, name in frame_map.items()
                                 if name != role and name in rd.raw_frames},
                    files=files)
    if require:
        _check_complete(rec, scans, topics, role_topics)
    for w in rec.warnings:
        _log.warning("%s: %s", spath, w)
    return rec


def _check_complete(rec: Recording, scans: list[_Scan], topics: TopicMap,
                    role_topics: dict[str, str]) -> None:
    path = rec.path
    lost = [s.truncated for s in scans if s.truncated]
    trunc = f" (the file is truncated: {'; '.join(lost)})" if lost else ""
    damaged = [d for s in scans for d in s.damaged]
    if damaged:
        trunc += (f" ({len(damaged)} damaged records were skipped: {damaged[0]}"
                  + (", ..." if len(damaged) > 1 else "") + ")")
    present = sorted(t for t, st in rec.topics.items() if st.count)
    for role, topic in role_topics.items():
        n = len(rec.views if role == "views" else rec.laser_frames)
        if n == 0:
            raise RecordingError(f"required topic {topic} has no messages ({role}; topics "
                                 f"with messages: {', '.join(present) or 'none'}; map the "
                                 f"cell's topic names in the config's topics section){trunc}",
                                 path=path, topic=topic)
    images = rec.views + rec.laser_frames
    if not images:
        return
    if not rec.calibrations:
        raise CalibrationError(f"no calibration: topic {topics.calibration} has no messages, "
                               f"but the recording has {len(images)} images{trunc}",
                               path=path, topic=topics.calibration)
    if not rec.tf.links():
        raise TransformError(f"no transforms: topics {topics.tf} and {topics.tf_static} have "
                             f"no messages, but the recording has {len(images)} images{trunc}",
                             path=path, topic=topics.tf)
    checked: set[str] = set()
    for m in images:  # a loop over images, stopping at each new frame_id
        if m.frame_id in checked:
            continue
        rec.camera_for(m)  # CalibrationError naming topic, time and frame_id
        problem = _chain_problem(rec.tf, rec.base_frame, m.frame_id)
        if problem:
            hints = []
            if rec.frame_names:
                hints.append("frames renamed from the recording: " + ", ".join(
                    f"{n} -> {r}" for r, n in sorted(rec.frame_names.items())))
            static = rec.topics.get(topics.tf_static)
            if static is None or static.count == 0:
                hints.append(f"topic {topics.tf_static} has no messages: a bag recorded "
                             f"after the static transforms were latched misses them (record "
                             f"{topics.tf_static} with transient_local durability)")
            hint = f" ({'; '.join(hints)})" if hints else ""
            raise TransformError(f"no pose for images of frame_id {m.frame_id!r} in "
                                 f"{rec.base_frame!r}: {problem}{hint}{trunc}", path=path,
                                 topic=m.topic, time_ns=m.timestamp_ns)
        checked.add(m.frame_id)


# =========================================================================== probing
@dataclass
class RecordingSummary:
    """What :func:`probe_recording` learnt about a recording without reading it all.

    Attributes
    ----------
    path : str
    readable : bool
        False when the file cannot be used at all (then ``problem`` says why).
    problem : str or None
        Why it is unreadable, or a warning about a readable file (e.g. truncated).
    n_views, n_laser_frames, n_calibrations, n_tf : int
        Messages on the views, laser, calibration and tf (+ tf_static) topics.
    has_ground_truth : bool
        Some attachment's name starts with ``ground_truth/``.
    kind : str or None
        ``kind`` of the ``robo3d.recording`` metadata (``scan`` or ``calibration``).
    metadata : dict
        Every metadata record, name to dict.
    topics : dict
        Topic to ``(schema name, message encoding, message count)``.
    attachments : list of str
        Attachment names.
    files : list of str
        The MCAP files (several for a split rosbag2 directory).
    """

    path: str
    readable: bool
    problem: str | None = None
    n_views: int = 0
    n_laser_frames: int = 0
    n_calibrations: int = 0
    n_tf: int = 0
    has_ground_truth: bool = False
    kind: str | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    topics: dict[str, tuple[str, str, int]] = field(default_factory=dict)
    attachments: list[str] = field(default_factory=list)
    files: list[str] = field(default_factory=list)


def _read_summary(path: str) -> _Scan | None:
    """The summary section of an intact file as a :class:`_Scan` without messages, or None
    when the file has no usable summary (no statistics, or anything amiss)."""
    size = os.path.getsize(path)
    footer_len = 1 + 8 + 20
    if size < 8 + footer_len + 8:
        return None
    with open(path, "rb") as f:
        f.seek(size - 8 - footer_len)
        tail = f.read(footer_len + 8)
        if tail[-8:] != MAGIC or tail[0] != Opcode.FOOTER:
            return None
        summary_start, _offsets, _crc = struct.unpack_from("<QQI", tail, 9)
        if summary_start == 0 or summary_start >= size - 8 - footer_len:
            return None
        f.seek(summary_start)
        body = f.read(size - 8 - footer_len - summary_start)
        scan = _Scan(path=path, size=size)
        stats = None
        md_index: list[MetadataIndex] = []
        o = 0
        mv = memoryview(body)
        while o < len(body):
            op, ln = struct.unpack_from("<BQ", body, o)
            if o + 9 + ln > len(body):
                return None
            rec = bytes(mv[o + 9: o + 9 + ln])
            if op == Opcode.SCHEMA:
                s = _parse_schema(memoryview(rec))
                scan.schemas[s.id] = s
            elif op == Opcode.CHANNEL:
                c = _parse_channel(memoryview(rec))
                scan.channels[c.id] = c
            elif op == Opcode.STATISTICS:
                stats = Statistics.read(_stream(rec))
            elif op == Opcode.ATTACHMENT_INDEX:
                ai = AttachmentIndex.read(_stream(rec))
                scan.attachments[ai.name] = b""
            elif op == Opcode.METADATA_INDEX:
                md_index.append(MetadataIndex.read(_stream(rec)))
            o += 9 + ln
        if stats is None:
            return None
        scan.counts = dict(stats.channel_message_counts)
        for mi in md_index:
            f.seek(mi.offset)
            hdr = f.read(9)
            op, ln = struct.unpack("<BQ", hdr)
            if op != Opcode.METADATA:
                return None
            md = Metadata.read(_stream(f.read(ln)))
            scan.metadata.setdefault(md.name, {}).update(md.metadata)
        return scan


def probe_recording(path: str | os.PathLike[str],
                    topics: TopicMap = _DEFAULT_TOPICS) -> RecordingSummary:
    """Summarise a recording cheaply; never raises.

    Uses the MCAP summary section (statistics, channels, attachment and metadata indexes)
    when the file has an intact one, and a record-by-record scan (no message decoding)
    otherwise.

    Parameters
    ----------
    path : str or path-like
    topics : TopicMap

    Returns
    -------
    RecordingSummary
        ``readable=False`` with ``problem`` set for a file that is missing, not MCAP,
        carries an unsupported schema or encoding on a role topic, or has no images.
    """
    spath = os.fspath(path)
    try:
        return _probe(spath, topics)
    except Exception as exc:  # the contract: one bad file must not stop a batch
        reason = str(exc) if isinstance(exc, RecordingError) else \
            f"{spath}: {type(exc).__name__}: {exc}"
        return RecordingSummary(path=spath, readable=False, problem=reason)


def _probe(path: str, topics: TopicMap) -> RecordingSummary:
    if not os.path.exists(path):
        return RecordingSummary(path=path, readable=False, problem=f"{path}: no such file")
    files, file_warnings = bag_files(path)
    scans = []
    for f in files:
        scan = None
        try:
            scan = _read_summary(f)
        except Exception:  # damaged summary: scan instead
            scan = None
        if scan is None:
            scan = _scan_file(f, lambda _t: False, keep_attachment_data=False)
        scans.append(scan)
    by_topic: dict[str, tuple[str, str, int]] = {}
    attachments: set[str] = set()
    metadata: dict[str, dict[str, str]] = {}
    for scan in scans:
        for cid, ch in scan.channels.items():
            sch = scan.schemas.get(ch.schema_id)
            name = sch.name if sch is not None else ""
            n = scan.counts.get(cid, 0)
            old = by_topic.get(ch.topic)
            by_topic[ch.topic] = (name, ch.message_encoding, n + (old[2] if old else 0))
        attachments.update(scan.attachments)
        for name, md in scan.metadata.items():
            metadata.setdefault(name, {}).update(md)

    def count(t: str) -> int:
        return by_topic.get(t, ("", "", 0))[2]

    summary = RecordingSummary(
        path=path, readable=True,
        n_views=count(topics.views), n_laser_frames=count(topics.laser),
        n_calibrations=count(topics.calibration),
        n_tf=count(topics.tf) + count(topics.tf_static),
        has_ground_truth=any(a.startswith("ground_truth/") for a in attachments),
        kind=metadata.get("robo3d.recording", {}).get("kind"),
        metadata=metadata, topics=by_topic, attachments=sorted(attachments), files=files)
    problems = []
    expect = {topics.tf: "tf", topics.tf_static: "tf", topics.calibration: "calibration",
              topics.views: "image", topics.laser: "image"}
    for topic, role in expect.items():
        if topic not in by_topic or by_topic[topic][2] == 0:
            continue
        name, enc, _ = by_topic[topic]
        ok = ((enc == "protobuf" and name in _allowed("protobuf", role))
              or (enc == "json" and (name in _allowed("json", role) or name == ""))
              or (enc == "cdr" and _ros_type(name) in _allowed("ros2", role)))
        if not ok:
            every = _allowed("protobuf", role) + _allowed("ros2", role)
            problems.append(f"topic {topic} carries {name or '(no schema)'!r} encoded as "
                            f"{enc!r}; supported: {' or '.join(every)} (Foxglove schemas as "
                            f"protobuf or json, ROS 2 types as cdr)")
    if problems:
        summary.readable = False
        summary.problem = f"{path}: " + "; ".join(problems)
        return summary
    truncated = [s.truncated for s in scans if s.truncated]
    if summary.n_views == 0 and summary.n_laser_frames == 0:
        summary.readable = False
        present = sorted(t for t, v in by_topic.items() if v[2])
        summary.problem = (f"{path}: no images on {topics.views} or {topics.laser} (topics "
                           f"with messages: {', '.join(present) or 'none'})"
                           + (f" ({'; '.join(truncated)})" if truncated else ""))
        return summary
    warnings = file_warnings + [w for s in scans for w in s.warnings]
    if warnings:
        summary.problem = f"{path}: " + "; ".join(warnings)
    return summary


# =========================================================================== ground truth
def read_ground_truth_tf(recording: Recording) -> TransformBuffer:
    """The true transforms of a recording (attachment ``ground_truth/tf.json``).

    Two forms are read:

    - the contract's (``recording-format.md``): a ``foxglove.FrameTransforms`` message in
      JSON, ``{"transforms": [{"timestamp": {"sec", "nsec"}, "parent_frame_id",
      "child_frame_id", "translation": {"x", "y", "z"}, "rotation": {"x", "y", "z",
      "w"}}, ...]}``, one entry per sample (the protobuf-style ``{"seconds", "nanos"}``
      timestamp is accepted too). The truth names only the links that carry error; every
      static link of the recording (``/tf_static``) that the truth does not name is
      taken as true and added;
    - robo3d's first form (the demo recordings): ``{"transforms": [{"parent", "child",
      "stamps_ns": [N], "translations": [[x, y, z]] * N, "quaternions": [[x, y, z, w]] *
      N}, ...]}`` (an optional ``"static": true`` marks a fixed link).

    Metres, nanoseconds. Evaluation only: the pipeline must never use it to measure.

    Parameters
    ----------
    recording : Recording

    Returns
    -------
    TransformBuffer
        With the same ``max_gap_ns`` as ``recording.tf``.

    Raises
    ------
    RecordingError
        The attachment is absent or malformed (non-finite, non-unit quaternions, ragged
        arrays).
    """
    path = recording.path
    data = recording.attachments.get(GROUND_TRUTH_TF)
    if data is None:
        raise RecordingError(f"no {GROUND_TRUTH_TF} attachment (attachments: "
                             f"{', '.join(sorted(recording.attachments)) or 'none'})", path=path)

    def fail(what: str) -> RecordingError:
        return RecordingError(f"attachment {GROUND_TRUTH_TF}: {what}", path=path)

    try:
        doc = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise fail(f"is not valid JSON ({exc})") from None
    entries = doc.get("transforms") if isinstance(doc, dict) else None
    if not isinstance(entries, list):
        raise fail('must be {"transforms": [...]}')
    buf = TransformBuffer(max_gap_ns=recording.tf.max_gap_ns, path=path)
    if entries and isinstance(entries[0], dict) and "child_frame_id" in entries[0]:
        from ..transforms import matrix_to_quat

        _ground_truth_frame_transforms(entries, buf, fail)
        named = {child for _, child, _, _ in buf.links()}
        for parent, child, static, _ in recording.tf.links():
            if static and child not in named:
                st, t = recording.tf.link_samples(parent, child)
                buf.add(parent, child, st, t[:, :3, 3], matrix_to_quat(t[:, :3, :3]),
                        static=True, topic="/tf_static")
        return buf
    for i, e in enumerate(entries):
        try:
            parent, child = str(e["parent"]), str(e["child"])
            stamps = np.asarray(e["stamps_ns"], dtype=np.int64).reshape(-1)
            tr = np.asarray(e["translations"], dtype=np.float64)
            q = np.asarray(e["quaternions"], dtype=np.float64)
            static = bool(e.get("static", False))
        except (KeyError, TypeError, ValueError, OverflowError) as exc:
            raise fail(f"transforms[{i}] needs parent, child, stamps_ns, translations, "
                       f"quaternions ({type(exc).__name__}: {exc})") from None
        n = len(stamps)
        if n == 0 or tr.shape != (n, 3) or q.shape != (n, 4):
            raise fail(f"transforms[{i}] ({parent} -> {child}): expected {n} stamps, (N, 3) "
                       f"translations and (N, 4) quaternions, got {tr.shape} and {q.shape}")
        if not (np.all(np.isfinite(tr)) and np.all(np.isfinite(q))):
            raise fail(f"transforms[{i}] ({parent} -> {child}) has non-finite values")
        norm = np.linalg.norm(q, axis=1)
        if np.any(np.abs(norm - 1) > _QUAT_TOL):
            raise fail(f"transforms[{i}] ({parent} -> {child}) has non-unit quaternions "
                       f"(norms {norm.min():.6g} .. {norm.max():.6g})")
        buf.add(parent, child, stamps, tr, q, static=static, topic=GROUND_TRUTH_TF)
    return buf


def _ground_truth_frame_transforms(entries: list[Any], buf: TransformBuffer,
                                   fail: Callable[[str], RecordingError]) -> None:
    """Add the samples of a ``foxglove.FrameTransforms`` JSON truth to ``buf``, per link."""
    links: dict[tuple[str, str], tuple[list[int], list[list[float]], list[list[float]]]] = {}
    for i, e in enumerate(entries):
        try:
            parent, child = str(e["parent_frame_id"]), str(e["child_frame_id"])
            ts = e["timestamp"]
            if "sec" in ts:
                stamp = int(ts["sec"]) * 1_000_000_000 + int(ts.get("nsec", 0))
            else:
                stamp = int(ts["seconds"]) * 1_000_000_000 + int(ts.get("nanos", 0))
            tr = [float(e["translation"][k]) for k in "xyz"]
            q = [float(e["rotation"][k]) for k in "xyzw"]
        except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:
            raise fail(f"transforms[{i}] needs timestamp {{sec, nsec}}, parent_frame_id, "
                       f"child_frame_id, translation {{x, y, z}}, rotation {{x, y, z, w}} "
                       f"({type(exc).__name__}: {exc})") from None
        if not (np.all(np.isfinite(tr)) and np.all(np.isfinite(q))):
            raise fail(f"transforms[{i}] ({parent} -> {child}) has non-finite values")
        if abs(float(np.linalg.norm(q)) - 1) > _QUAT_TOL:
            raise fail(f"transforms[{i}] ({parent} -> {child}) has a non-unit quaternion "
                       f"(norm {np.linalg.norm(q):.6g})")
        if stamp < 0:
            raise fail(f"transforms[{i}] ({parent} -> {child}) has a negative timestamp")
        s_, t_, q_ = links.setdefault((parent, child), ([], [], []))
        s_.append(stamp)
        t_.append(tr)
        q_.append(q)
    for (parent, child), (st, tr, q) in links.items():
        buf.add(parent, child, np.array(st, dtype=np.int64), np.array(tr), np.array(q),
                topic=GROUND_TRUTH_TF)
