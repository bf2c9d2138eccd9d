"""Message decoding: the role topics' messages as plain values (``recording-format.md``).

:func:`decode_scan` decodes the kept messages of one scanned file
(:mod:`~robo3d.recording.framing`) into a :class:`MessageDecoder`: transform samples per
link, calibrations as :class:`~robo3d.camera.CameraModel`, images as
:class:`~robo3d.recording.model.ImageMessage` (still encoded), joint states, and each
topic's stamps. Checks that need every message (transform values, ordering, completeness)
are the reader's (:mod:`~robo3d.recording.reader`).

What is read
------------
- Foxglove schemas (https://docs.foxglove.dev/docs/visualization/message-schemas)
  encoded as Protobuf (``protobuf``; decoded generically from the schema's own
  ``FileDescriptorSet`` by ``mcap-protobuf-support``, so other builds of the schemas
  read too) or as JSON (``json`` / ``jsonschema``; ``bytes`` base64, timestamps
  ``{"sec", "nsec"}``; the protobuf-style ``{"seconds", "nanos"}`` is accepted too):
  ``foxglove.FrameTransforms`` / ``foxglove.FrameTransform`` on the tf topics,
  ``foxglove.CameraCalibration`` on the calibration topic, ``foxglove.CompressedImage``
  (png/jpeg) and ``foxglove.RawImage`` (mono8, rgb8, bgr8, mono16, and what
  ``images.READ_RAW_ENCODINGS`` adds) on the image topics.
- ROS 2 messages as a ROS 2 cell records them (``cdr`` with ``ros2msg`` schemas, decoded
  by ``mcap-ros2-support`` from the schema text in the file, no conversion step; the
  message definitions of ``tf2_msgs``, ``geometry_msgs`` and ``sensor_msgs``, ROS 2
  Humble): ``tf2_msgs/msg/TFMessage`` (or ``geometry_msgs/msg/TransformStamped``) on the
  tf topics, ``sensor_msgs/msg/CameraInfo`` on the calibration topic,
  ``sensor_msgs/msg/Image`` (mono8, rgb8, bgr8, mono16, colour with alpha or 16 bits,
  the four Bayer mosaics in 8 and 16 bits, YUV 4:2:2 and the ``nUCk`` aliases:
  ``images.READ_RAW_ENCODINGS``; big-endian 16-bit data is byte-swapped) and
  ``sensor_msgs/msg/CompressedImage``
  (png/jpeg, image_transport's ``"rgb8; jpeg compressed bgr8"`` style formats, and
  ``compressedDepth`` PNGs) on the image topics, and, when asked,
  ``sensor_msgs/msg/JointState``. ROS 1 style names (``sensor_msgs/Image``) are
  accepted; ``ros2idl`` schemas are not (mcap-ros2-support reads ``ros2msg`` only).
- A role topic with any other schema or encoding is a
  :class:`~robo3d.errors.RecordingError` naming the topic and the schema; a joint-state
  topic with another schema is a warning (joint states are informational). A message that
  does not decode is an error naming the topic and its log time.

Frames and times
----------------
- Recorded frame names are renamed to their roles as they are read (the reader's
  ``frames`` map), in transforms, images' ``frame_id`` and calibrations; a leading ``/``
  is dropped, as tf2 does.
- The time of a message is its own stamp (the ``timestamp`` field; ROS 2's
  ``header.stamp``), not the MCAP log time. A message without one (an unset protobuf
  field, a JSON message without the key, a ROS 2 stamp of exactly 0) falls back to its
  log time and is counted (:attr:`MessageDecoder.no_stamp`; not for ``/tf_static``,
  whose stamps do not matter). ``stamp_source="log_time"`` uses the log time for every
  message; ``image_offset_ns`` is added to every image stamp. Stamps must lie in
  ``[0, 2**63)`` ns.

Calibrations
------------
Keyed by ``frame_id``; when a frame is calibrated more than once with different values,
the last calibration is kept and a warning says so. ``distortion_model``: ``plumb_bob``
(4 or 5 coefficients), ``rational_polynomial`` (8 coefficients, or OpenCV's 12 or 14;
with only zeros past k3 it is plumb_bob, else the frame's images are rectified to a
pinhole camera as they are decoded, :class:`~robo3d.camera.Rectifier`), ``equidistant``
(ROS's fisheye model, 4 coefficients, always rectified; ``kannala_brandt``, Foxglove's
name for the same OpenCV model, is read as it), or empty with an empty or
all-zero ``D`` (no distortion; an empty model with 5 coefficients is read as plumb_bob
with a warning, as some ROS drivers leave the name empty). ``R`` and ``P`` are ignored:
images are the raw (distorted, unrectified) images that ``K`` and ``D`` describe. A ROS
``CameraInfo`` with binning or a region of interest (REP 104: ``K`` of the full sensor,
the image its binned ROI) is read as the camera of the recorded image
(:func:`_binned_k`); a frame whose ROI changes between images is not (the last
calibration is kept, with the warning above).
"""

from __future__ import annotations

import base64
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from mcap.records import Schema as McapSchema

from ..camera import CameraModel, Rectifier
from ..errors import CalibrationError, ImageDecodeError, RecordingError, TransformError
from .framing import MAX_STAMP, Channel, Scan
from .images import READ_RAW_ENCODINGS, normalize_encoding, raw_bytes_per_channel
from .model import ImageMessage, TopicMap

__all__ = ["QUAT_TOL", "MessageDecoder", "TfSamples", "TopicTimes", "decode_scan",
           "allowed_schemas", "ros_type"]

_TF_SCHEMAS = ("foxglove.FrameTransforms", "foxglove.FrameTransform")
_CALIB_SCHEMAS = ("foxglove.CameraCalibration",)
_IMAGE_SCHEMAS = ("foxglove.CompressedImage", "foxglove.RawImage")
_ROS_TF = ("tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped")
_ROS_CALIB = ("sensor_msgs/msg/CameraInfo",)
_ROS_IMAGE = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
_ROS_JOINTS = ("sensor_msgs/msg/JointState",)
#: How far a quaternion's norm may be from 1 before a transform is an error (below it,
#: the quaternion is renormalised).
QUAT_TOL = 1e-3


def ros_type(name: str) -> str:
    """``sensor_msgs/Image`` -> ``sensor_msgs/msg/Image`` (ROS 1 style names)."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


# =========================================================================== decoders and fields
_Decoder = tuple[Callable[[bytes], Any], str]  # (decode function, kind)


def _decoder_for(scan: Scan, ch: Channel, factories: dict[str, Any]) -> _Decoder:
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


def _binned_k(k: Any, x0: int, y0: int, bx: int, by: int) -> list[float]:
    """``K`` of a ROS camera's binned region of interest, from the full sensor's: a pixel
    of the binned image covers ``b`` sensor pixels, whose centre lies at ``b u + (b - 1) /
    2`` after the offset (pixel centres at integers, as everywhere in robo3d; ROS's
    image_geometry leaves out the ``(b - 1) / 2``, a quarter pixel at 2x2). The lens's
    ``D`` acts on normalised coordinates and stays."""
    try:
        kk = [float(x) for x in k]
    except (TypeError, ValueError):
        return list(k)  # left for _add_calibration's own message
    if len(kk) != 9:
        return kk
    fx, skew, cx, _, fy, cy = kk[0], kk[1], kk[2], kk[3], kk[4], kk[5]
    return [fx / bx, skew / bx, (cx - x0 - (bx - 1) / 2) / bx,
            0.0, fy / by, (cy - y0 - (by - 1) / 2) / by, 0.0, 0.0, 1.0]


def _ros(obj: Any, *names: str, default: Any = None) -> Any:
    """A field of a decoded ROS message under its ROS 2 or ROS 1 name."""
    for n in names:
        v = getattr(obj, n, None)
        if v is not None:
            return v
    return default


@dataclass
class TfSamples:
    """The samples of one link on one topic, in file order (values ``tx ty tz qx qy qz
    qw``, unchecked)."""

    topic: str
    parent: str
    child: str
    stamps: list[int] = field(default_factory=list)
    values: list[list[float]] = field(default_factory=list)  # tx ty tz qx qy qz qw


@dataclass
class TopicTimes:
    """Log times and stamps of the decoded messages of one topic, in decode order."""

    schema: str
    encoding: str
    log_times: list[int] = field(default_factory=list)
    stamps: list[int] = field(default_factory=list)


# =========================================================================== the decoder
class MessageDecoder:
    """Decodes the messages of the role topics into plain values and collects them.

    One decoder serves every file of a recording (:func:`decode_scan` is called once per
    file, in order). Frame names are renamed to their roles as they are read (``frames``:
    role -> recorded name; a leading ``/`` is dropped), stamps are taken from the messages
    (or their log times, ``stamp_source="log_time"``), and ``image_offset_ns`` is added to
    every image stamp.

    Attributes
    ----------
    path : str
        The file being decoded, named in errors.
    warnings : list of str
        Everything accepted but suspicious, in the order found.
    tf_links : dict
        ``(topic, parent, child)`` -> :class:`TfSamples`, in order of first appearance.
    calibs : dict
        ``frame_id`` -> ``(CameraModel, topic, stamp)``: the kept calibration of each frame.
    rectifiers : dict
        ``frame_id`` -> :class:`~robo3d.camera.Rectifier` of the frames whose kept
        calibration is ``rational_polynomial`` with non-zero ``k4..k6`` (their
        ``calibs`` camera is the rectified pinhole camera).
    images : dict
        Topic -> :class:`~.model.ImageMessage` list, in file order.
    joints : list
        ``(stamp, names, positions)`` of each joint state message.
    times : dict
        Topic -> :class:`TopicTimes`: log times and stamps of every decoded message.
    no_stamp : dict
        Topic -> number of messages without a stamp (their log time was used).
    raw_frames : set of str
        Every frame name as recorded (before renaming).
    """

    def __init__(self, path: str, topics: TopicMap, frames: dict[str, str],
                 stamp_source: str, image_offset_ns: int) -> None:
        self.path = path  # the file being decoded, named in errors
        self.topics = topics
        self.frames = frames
        self.rename = {rec: role for role, rec in frames.items() if rec != role}
        self.raw_frames: set[str] = set()
        self.use_log_time = stamp_source == "log_time"
        self.image_offset = int(image_offset_ns)
        self.warnings: list[str] = []
        self.tf_links: dict[tuple[str, str, str], TfSamples] = {}
        self.calibs: dict[str, tuple[CameraModel, str, int]] = {}
        self.rectifiers: dict[str, Rectifier] = {}
        self._rectifier_cache: dict[tuple, Rectifier] = {}
        self.images: dict[str, list[ImageMessage]] = {}
        self.no_stamp: dict[str, int] = {}
        self.joints: list[tuple[int, list[str], list[float]]] = []
        self.times: dict[str, TopicTimes] = {}

    def warn(self, text: str) -> None:
        self.warnings.append(text)

    def frame(self, name: str) -> str:
        """A recorded frame name as the pipeline sees it (leading ``/`` dropped, renamed
        to its role)."""
        n = name[1:] if name.startswith("/") else name
        self.raw_frames.add(n)
        return self.rename.get(n, n)

    def _check_time(self, st: int, topic: str, log_time: int) -> int:
        if not 0 <= st <= MAX_STAMP:
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
            t = self.times[topic] = TopicTimes(schema, encoding)
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
            link = self.tf_links[key] = TfSamples(topic, parent, child)
        link.stamps.append(st)
        link.values.append(t + q)

    def _add_calibration(self, topic: str, st: int, fid: str, k_raw: Any, d_raw: Any,
                         width: int, height: int, model: str) -> None:
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
        if model == "kannala_brandt":  # Foxglove's name for OpenCV's fisheye model
            model = "equidistant"
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
        elif model == "rational_polynomial":  # 8, or OpenCV's 12 / 14 (thin prism, tilt)
            if d.size not in (5, 8, 12, 14):
                raise fail(f"rational_polynomial needs 8 coefficients (k1 k2 p1 p2 k3 k4 "
                           f"k5 k6; 12 or 14 with OpenCV's thin-prism and tilt terms), got "
                           f"{d.size}")
        elif model == "equidistant":  # ROS's fisheye model: always rectified
            if d.size != 4:
                raise fail(f"equidistant (fisheye) needs 4 coefficients (k1 k2 k3 k4), got "
                           f"{d.size}")
        else:
            raise fail(f"distortion_model {model!r} is unsupported (plumb_bob, "
                       f"rational_polynomial, equidistant or kannala_brandt, or empty for "
                       f"none)")
        rect = None
        try:
            if model == "equidistant" or (d.size > 5 and np.any(d[5:] != 0)):
                # resampled to a pinhole camera (views) or mapped to it (stripe centres);
                # one per distinct calibration: ROS drivers publish CameraInfo with every
                # image, and each Rectifier costs tens of milliseconds to make
                key = (fid, width, height, model, k.tobytes(), d.tobytes())
                rect = self._rectifier_cache.get(key)
                if rect is None:
                    rect = self._rectifier_cache[key] = Rectifier(
                        fid, width, height, k.reshape(3, 3), d, model)
                cam = rect.camera
            else:
                cam = CameraModel(fid, width, height, k.reshape(3, 3), d[:5])
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
        if rect is not None:
            self.rectifiers[fid] = rect
        else:
            self.rectifiers.pop(fid, None)

    def _add_image(self, topic: str, st: int, log_time: int, fid: str, compressed: bool,
                   encoding: str, data: bytes, width: int = 0, height: int = 0,
                   step: int = 0) -> None:
        st = st + self.image_offset
        if not 0 <= st <= MAX_STAMP:
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
            if enc not in READ_RAW_ENCODINGS:
                raise ImageDecodeError(f"raw image encoding {encoding!r} is unsupported "
                                       f"(supported: {', '.join(READ_RAW_ENCODINGS)}, and "
                                       f"8UC1, 8UC3, 8UC4, 16UC1, 16UC3, 16UC4)",
                                       path=self.path, topic=topic, time_ns=st)
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
        bx = max(int(_ros(obj, "binning_x", default=0) or 0), 1)  # 0 and 1: none
        by = max(int(_ros(obj, "binning_y", default=0) or 0), 1)
        roi = _ros(obj, "roi")
        x0 = int(getattr(roi, "x_offset", 0) or 0) if roi is not None else 0
        y0 = int(getattr(roi, "y_offset", 0) or 0) if roi is not None else 0
        rw = int(getattr(roi, "width", 0) or 0) if roi is not None else 0
        rh = int(getattr(roi, "height", 0) or 0) if roi is not None else 0
        k = list(_ros(obj, "k", "K", default=[]))
        if bx > 1 or by > 1 or rw or rh or x0 or y0:
            # REP 104: K describes the full sensor (width x height); the image is its
            # region of interest (all of it when the ROI is zero), binned
            rw, rh = (rw or width - x0), (rh or height - y0)
            if (x0 < 0 or y0 < 0 or rw <= 0 or rh <= 0 or x0 + rw > width
                    or y0 + rh > height or rw % bx or rh % by):
                raise CalibrationError(
                    f"calibration of frame_id {fid!r}: region of interest {rw}x{rh} at "
                    f"({x0}, {y0}) with binning {bx}x{by} does not fit the {width}x{height} "
                    "sensor (or is not a whole number of bins)", path=self.path,
                    topic=topic, time_ns=st)
            k = _binned_k(k, x0, y0, bx, by)
            width, height = rw // bx, rh // by
        self._add_calibration(topic, st, fid, k,
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
        if int(obj.is_bigendian or 0) and raw_bytes_per_channel(enc) == 2:
            step = int(obj.step)
            if step % 2 or len(data) % 2:
                raise ImageDecodeError(f"big-endian {enc} image with odd step {step} or odd "
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


# =========================================================================== one file
def allowed_schemas(kind: str, role: str) -> tuple[str, ...]:
    """The schema names read on a role's topic (``tf``, ``calibration``, ``image``,
    ``joints``) for a decoder kind (``protobuf`` or ``json``: Foxglove; ``ros2``)."""
    if kind == "ros2":
        return {"tf": _ROS_TF, "calibration": _ROS_CALIB, "image": _ROS_IMAGE,
                "joints": _ROS_JOINTS}[role]
    return {"tf": _TF_SCHEMAS, "calibration": _CALIB_SCHEMAS, "image": _IMAGE_SCHEMAS,
            "joints": ()}[role]


def decode_scan(scan: Scan, out: MessageDecoder, topics: TopicMap, image_topics: set[str],
                joints_topic: str | None) -> None:
    """Decode the kept messages of one scanned file into ``out``.

    Parameters
    ----------
    scan : Scan
        A file scanned with :func:`~robo3d.recording.framing.scan_file`.
    out : MessageDecoder
        Collects what is decoded (shared by the files of one recording).
    topics : TopicMap
    image_topics : set of str
        The image topics asked for.
    joints_topic : str or None
        The joint-state topic, when asked for.

    Raises
    ------
    RecordingError
        A role topic with an unsupported schema or encoding, or a message that does not
        decode (named by topic and log time); and the errors of :class:`MessageDecoder`
        (:class:`~robo3d.errors.TransformError`, :class:`~robo3d.errors.CalibrationError`,
        :class:`~robo3d.errors.ImageDecodeError`).
    """
    from mcap_protobuf.decoder import DecoderFactory as PbFactory
    from mcap_ros2.decoder import DecoderFactory as Ros2Factory

    factories = {"protobuf": PbFactory(), "ros2": Ros2Factory()}  # fresh: ids are per file
    out.path = scan.path
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
                sname = ros_type(sname)
            if not sname and kind == "json" and ch.topic in tf_topics:
                sname = "foxglove.FrameTransforms"
            role = ("tf" if ch.topic in tf_topics else
                    "calibration" if ch.topic == topics.calibration else
                    "image" if ch.topic in image_topics else "joints")
            allowed = allowed_schemas(kind, role)
            if sname not in allowed:
                if role == "joints":  # informational: never stops a reading
                    out.warn(f"{ch.topic}: joint states with schema {sname or '(none)'!r} "
                            f"({ch.message_encoding}) are not read (expected "
                            f"{' or '.join(_ROS_JOINTS)})")
                    decoders[cid] = (fn, kind, "", ch.topic, "skip")
                    continue
                every = allowed_schemas("protobuf", role) + allowed_schemas("ros2", role)
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
                    st = out.ros_tf(obj, sname, topic, log_time)
                elif role == "calibration":
                    st = out.ros_calibration(obj, topic, log_time)
                elif role == "image":
                    st = out.ros_image(obj, sname, topic, log_time)
                else:
                    st = out.ros_joint_state(obj, topic, log_time)
            else:
                is_json = kind == "json"
                if is_json and not isinstance(obj, dict):
                    raise ValueError(f"a JSON message must be an object, got "
                                     f"{type(obj).__name__}")
                if role == "tf":
                    st = out.tf(obj, is_json, sname, topic, log_time)
                elif role == "calibration":
                    st = out.calibration(obj, is_json, topic, log_time)
                else:
                    st = out.image(obj, is_json, sname, topic, log_time)
        except RecordingError:
            raise
        except Exception as exc:  # protobuf/CDR decode errors, JSON errors, base64, types
            raise RecordingError(f"a {sname} message does not decode "
                                 f"({type(exc).__name__}: {exc}); time is its log time",
                                 path=scan.path, topic=topic, time_ns=log_time) from None
        out._record_time(topic, sname, ch.message_encoding, log_time, st)
