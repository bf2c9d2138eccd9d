"""Input that is bad in every way a real cell produces it: each case builds the bad file
and checks what robo3d says about it. ROS 2 bags are written with ``rosbags`` (an
independent writer); native recordings with robo3d's writer. A property-based test
mutates valid recordings at random: the reader reads them or raises robo3d's own error,
never anything else.
"""

from __future__ import annotations

import re
import struct
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robo3d.camera import CameraModel
from robo3d.config import default_config
from robo3d.errors import (
    CalibrationError,
    ImageDecodeError,
    RecordingError,
    Robo3dError,
    StageError,
    TransformError,
)
from robo3d.recording import RecordingWriter, TopicMap, probe_recording, read_recording
from robo3d.transforms import euler_to_matrix, make_transform, matrix_to_quat

pytest.importorskip("rosbags")

T0 = 1_700_000_000_000_000_000
W, H = 32, 24
K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]])
FRAMES = {"base": "base_link", "flange": "tool0", "camera": "camera_optical", "laser": "laser_link"}
TOPICS = TopicMap(calibration="/cam/camera_info", views="/cam/image", laser="/laser_cam/image",
                  joint_states="/joint_states")
VIEW_T = [T0 + 200_000_000 + i * 150_000_000 for i in range(4)]
LASER_T = [T0 + 805_000_000 + i * 20_000_000 for i in range(6)]
T_FLANGE_CAMERA = make_transform(euler_to_matrix("zyx", [0.1, 0.2, 3.0]), [0.0, 0.05, 0.1])


def t_base_flange(t: int) -> np.ndarray:
    s = (t - T0) / 1e9
    return make_transform(euler_to_matrix("zyx", [0.4 * s, 0.1, -0.2]),
                          [0.5 + 0.1 * s, -0.1, 0.4 - 0.05 * s])


def _image(i: int) -> np.ndarray:
    rng = np.random.default_rng(i)
    return rng.integers(0, 256, (H, W), dtype=np.uint8)


# =========================================================================== ROS 2 bag
class Bag:
    """The messages of a small, valid ROS 2 bag as (topic, type, message, log time); tests
    edit the list, then :meth:`write` it with ``rosbags``."""

    def __init__(self) -> None:
        from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.T = self.ts.types
        self.messages: list[tuple[str, str, Any, int]] = []
        self.messages.append((TOPICS.calibration, "sensor_msgs/msg/CameraInfo",
                              self.camera_info(T0), T0))
        self.messages.append(("/tf_static", "tf2_msgs/msg/TFMessage", self.tf_msg(
            T0, [("tool0", "camera_optical", T_FLANGE_CAMERA),
                 ("tool0", "laser_link", make_transform(np.eye(3), [0.08, 0.0, 0.1]))]), T0))
        for i in range(101):  # 100 Hz over 1 s
            t = T0 + i * 10_000_000
            self.messages.append(("/tf", "tf2_msgs/msg/TFMessage",
                                  self.tf_msg(t, [("base_link", "tool0", t_base_flange(t))]), t))
        for i, t in enumerate(VIEW_T):
            self.messages.append((TOPICS.views, "sensor_msgs/msg/Image",
                                  self.image(t, _image(i)), t))
        for i, t in enumerate(LASER_T):
            self.messages.append((TOPICS.laser, "sensor_msgs/msg/CompressedImage",
                                  self.compressed(t, _image(10 + i)), t))
        self.messages.sort(key=lambda m: m[3])

    def header(self, t: int, frame: str) -> Any:
        T = self.T
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
            sec=t // 10**9, nanosec=t % 10**9), frame_id=frame)

    def tf_msg(self, t: int, links: list[tuple[str, str, np.ndarray]],
               quat: np.ndarray | None = None) -> Any:
        T = self.T
        out = []
        for parent, child, M in links:
            q = matrix_to_quat(M[:3, :3]) if quat is None else quat
            out.append(T["geometry_msgs/msg/TransformStamped"](
                header=self.header(t, parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2],
                                                               w=q[3]))))
        return T["tf2_msgs/msg/TFMessage"](transforms=out)

    def camera_info(self, t: int, width: int = W, height: int = H) -> Any:
        T = self.T
        return T["sensor_msgs/msg/CameraInfo"](
            header=self.header(t, "camera_optical"), height=height, width=width,
            distortion_model="plumb_bob", d=np.zeros(5), k=K.reshape(-1).copy(),
            r=np.eye(3).reshape(-1), p=np.hstack([K, np.zeros((3, 1))]).reshape(-1),
            binning_x=0, binning_y=0,
            roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0,
                                                      width=0, do_rectify=False))

    def image(self, t: int, img: np.ndarray, encoding: str = "mono8") -> Any:
        return self.T["sensor_msgs/msg/Image"](
            header=self.header(t, "camera_optical"), height=img.shape[0], width=img.shape[1],
            encoding=encoding, is_bigendian=0, step=img.shape[1],
            data=np.ascontiguousarray(img).reshape(-1))

    def compressed(self, t: int, img: np.ndarray) -> Any:
        ok, buf = cv2.imencode(".png", img)
        return self.T["sensor_msgs/msg/CompressedImage"](
            header=self.header(t, "camera_optical"), format="mono8; png compressed",
            data=buf.reshape(-1))

    def write(self, path: Path, *, sort: bool = False) -> Path:
        """A bare ``.mcap`` file (CDR, uncompressed chunks without CRCs, as rosbags writes)."""
        import shutil

        from rosbags.rosbag2 import StoragePlugin, Writer

        d = path.with_suffix(".bagdir")
        shutil.rmtree(d, ignore_errors=True)
        conns: dict[str, Any] = {}
        msgs = sorted(self.messages, key=lambda m: m[3]) if sort else self.messages
        with Writer(d, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            for topic, msgtype, msg, log_time in msgs:
                if topic not in conns:
                    conns[topic] = w.add_connection(topic, msgtype, typestore=self.ts)
                w.write(conns[topic], log_time, self.ts.serialize_cdr(msg, msgtype))
        shutil.move(str(next(d.glob("*.mcap"))), path)
        shutil.rmtree(d)
        return path

    def drop(self, pred: Callable[[str, int], bool]) -> Bag:
        self.messages = [m for m in self.messages if not pred(m[0], m[3])]
        return self


def read(path: Path, **kw: Any):
    kw.setdefault("topics", TOPICS)
    kw.setdefault("frames", FRAMES)
    return read_recording(path, **kw)


def with_crcs(path: Path) -> Path:
    """Fill in the CRCs of a file's uncompressed chunks (rosbags leaves them 0)."""
    raw = bytearray(path.read_bytes())
    pos = 8
    while pos < len(raw) - 8:
        op, ln = struct.unpack_from("<BQ", raw, pos)
        if op == 0x06:
            body = pos + 9
            n = struct.unpack_from("<I", raw, body + 28)[0]
            assert raw[body + 32: body + 32 + n] == b""  # uncompressed
            size = struct.unpack_from("<Q", raw, body + 32 + n)[0]
            data = bytes(raw[body + 40 + n: body + 40 + n + size])
            struct.pack_into("<I", raw, body + 24, zlib.crc32(data))
        pos += 9 + ln
    path.write_bytes(bytes(raw))
    return path


def rechunk(src: Path, dst: Path, chunk_size: int = 512) -> Path:
    """The same records in small CRC-checked chunks (mcap's own writer; a recorder with a
    small cache), so that damage loses little."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f:
        msgs = list(make_reader(f).iter_messages(log_time_order=False))
    with open(dst, "wb") as f:
        w = Writer(f, chunk_size=chunk_size)
        w.start(profile="ros2")
        ids: dict[str, int] = {}
        for sch, ch, m in msgs:
            if ch.topic not in ids:
                sid = w.register_schema(sch.name, sch.encoding, sch.data)
                ids[ch.topic] = w.register_channel(ch.topic, ch.message_encoding, sid)
            w.add_message(ids[ch.topic], log_time=m.log_time, data=m.data,
                          publish_time=m.publish_time)
        w.finish()
    return dst


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return Bag().write(tmp_path_factory.mktemp("good") / "good.mcap")


def test_the_reference_bag_is_good(good: Path) -> None:
    rec = read(good)
    assert rec.warnings == [] and len(rec.views) == 4 and len(rec.laser_frames) == 6
    poses = rec.camera_poses(rec.views)
    want = np.stack([t_base_flange(t) @ T_FLANGE_CAMERA for t in VIEW_T])
    assert np.abs(poses - want).max() < 2e-4  # linear/slerp between 10 ms samples
    np.testing.assert_array_equal(rec.decode(rec.views[2]), _image(2))
    np.testing.assert_array_equal(rec.decode(rec.laser_frames[5]), _image(15))


# =========================================================================== the cases
def test_not_an_mcap(tmp_path: Path) -> None:
    for name, data in (("text.mcap", b"hello, world\n"), ("empty.mcap", b""),
                       ("sqlite.mcap", b"SQLite format 3\x00" + bytes(100))):
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(RecordingError, match="not an MCAP file") as ei:
            read(p)
        assert ei.value.path == str(p)
        s = probe_recording(p)
        assert not s.readable and "not an MCAP file" in s.problem
    # a rosbag2 directory whose .mcap is not one
    d = tmp_path / "bag"
    d.mkdir()
    (d / "bag_0.mcap").write_bytes(b"PK\x03\x04 a zip file")
    with pytest.raises(RecordingError, match=r"bag_0\.mcap: not an MCAP file"):
        read(d)


def test_truncated_at_any_byte(good: Path, tmp_path: Path) -> None:
    """Cut the bag at 150 offsets over its whole length: every cut either reads what is
    intact (saying so) or says the file is truncated, and never loses what remains."""
    # rosbags' own output is one chunk of up to 1 MB: a cut inside it loses the chunk
    raw = good.read_bytes()
    p = tmp_path / "one_chunk.mcap"
    p.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(RecordingError, match=r"required topic /cam/image has no messages.*"
                                             r"the file is truncated or damaged at byte 43 of "
                                             rf"{len(raw) // 2} \(a chunk record claims"):
        read(p)
    full = rechunk(good, tmp_path / "small_chunks.mcap").read_bytes()
    whole = read(good)
    n_tf = whole.topics["/tf"].count
    outcomes = []
    for off in np.unique(np.linspace(0, len(full) - 1, 150).astype(int)):
        p = tmp_path / "cut.mcap"
        p.write_bytes(full[:off])
        try:
            rec = read(p, require=False)
        except RecordingError as exc:
            assert str(p) in str(exc)
            assert off < 8 or "truncated" in str(exc) or "not an MCAP" in str(exc)
            outcomes.append("error")
            continue
        w = [x for x in rec.warnings if "truncated" in x]
        assert w, off
        # what was read is intact: exactly the first messages of the file
        n = rec.topics["/tf"].count if "/tf" in rec.topics else 0
        assert n <= n_tf
        stamps = [m.timestamp_ns for m in rec.views]
        assert stamps == VIEW_T[: len(stamps)]
        for m in rec.views:
            np.testing.assert_array_equal(rec.decode(m), _image(VIEW_T.index(m.timestamp_ns)))
        outcomes.append("read")
    assert "read" in outcomes and "error" in outcomes
    # a cut in the summary section only: every message intact, and the pipeline's check
    # passes; a cut in the middle loses the end and says from which byte
    data_end = full.rfind(bytes([0x0F]) + (4).to_bytes(8, "little"))
    p = tmp_path / "tail.mcap"
    p.write_bytes(full[: data_end + 20])
    rec = read(p)
    assert len(rec.laser_frames) == 6 and any("every message is intact" in w
                                              for w in rec.warnings)
    first_laser = full.find(b"\x89PNG")  # inside the first laser frame's chunk
    p.write_bytes(full[:first_laser])
    with pytest.raises(RecordingError, match=r"required topic /laser_cam/image has no "
                                             r"messages.*the file is truncated or damaged at "
                                             r"byte \d+ of \d+.*the last logged at"):
        read(p)
    rec = read(p, roles=("views",))  # what the views need is intact: usable
    assert len(rec.views) == 4 and rec.camera_poses(rec.views).shape == (4, 4, 4)


def test_corrupted_chunk_is_skipped(tmp_path: Path) -> None:
    """A chunk whose CRC fails is skipped with a warning naming its byte and time range;
    the messages of the other chunks are read. When what is lost was needed, the error
    says a chunk was skipped."""
    # rosbags writes this small bag as one chunk (without a CRC: filled in here)
    p = with_crcs(Bag().write(tmp_path / "crc.mcap"))
    raw = bytearray(p.read_bytes())
    raw[raw.find(_image(1).tobytes()[:16]) + 5] ^= 0xFF
    p.write_bytes(bytes(raw))
    with pytest.raises(RecordingError, match=r"required topic /cam/image has no messages.*"
                                             r"damaged records were skipped: chunk at byte "
                                             r"\d+ \(messages logged .*\) fails its CRC check"):
        read(p)
    # the same messages in chunks of 512 bytes: one chunk is lost, the rest read
    q = rechunk(Bag().write(tmp_path / "src.mcap"), tmp_path / "chunks.mcap")
    raw = bytearray(q.read_bytes())
    raw[raw.find(_image(1).tobytes()[:16]) + 5] ^= 0xFF
    q.write_bytes(bytes(raw))
    rec = read(q)
    crc = [w for w in rec.warnings if "fails its CRC check" in w]
    assert len(crc) == 1 and "chunk at byte" in crc[0] and "messages logged" in crc[0]
    assert [m.timestamp_ns for m in rec.views] == [VIEW_T[0], VIEW_T[2], VIEW_T[3]]
    assert len(rec.laser_frames) == 6


def test_missing_topic(good: Path) -> None:
    with pytest.raises(RecordingError, match=r"required topic /camera/image has no messages "
                                             r"\(views; topics with messages: "
                                             r"/cam/camera_info, /cam/image.*topics section") \
            as ei:
        read_recording(good, frames=FRAMES)
    assert ei.value.topic == "/camera/image"


def test_images_with_no_pose_nearby(tmp_path: Path) -> None:
    """/tf drops out for 0.1 s around the third view: that view has no pose, and the
    error names the topic and the image's time."""
    p = Bag().drop(lambda topic, t: topic == "/tf" and abs(t - VIEW_T[2]) < 50_000_000
                   ).write(tmp_path / "gap.mcap")
    rec = read(p)
    with pytest.raises(TransformError, match=r"samples of base -> flange around this time are "
                                             r"100.0 ms apart, more than max_pose_gap 50.0 ms") \
            as ei:
        rec.camera_poses(rec.views)
    assert ei.value.topic == TOPICS.views and ei.value.time_ns == VIEW_T[2]
    assert rec.camera_poses(rec.views[:2]).shape == (2, 4, 4)  # the others are fine
    # an image after the end of the pose stream
    p = Bag().drop(lambda topic, t: topic == "/tf" and t > LASER_T[3] + 10_000_000
                   ).write(tmp_path / "e.mcap")
    rec = read(p)
    with pytest.raises(TransformError, match="time outside the samples") as ei:
        rec.camera_poses(rec.laser_frames)
    assert ei.value.time_ns == LASER_T[4]


@pytest.mark.parametrize(("quat", "match"), [
    ([np.nan, 0.0, 0.0, 1.0], r"transform base -> flange is not finite"),
    ([0.0, 0.0, 0.0, 2.0], r"is not a unit quaternion \(norm 2"),
    ([0.0, 0.0, 0.0, 0.0], r"is not a unit quaternion \(norm 0"),
])
def test_nan_or_non_unit_quaternion(tmp_path: Path, quat: list[float], match: str) -> None:
    bag = Bag()
    i = next(k for k, m in enumerate(bag.messages) if m[0] == "/tf" and m[3] == T0 + 500_000_000)
    topic, msgtype, _, t = bag.messages[i]
    bag.messages[i] = (topic, msgtype, bag.tf_msg(t, [("base_link", "tool0", np.eye(4))],
                                                  quat=np.array(quat)), t)
    with pytest.raises(TransformError, match=match) as ei:
        read(bag.write(tmp_path / "q.mcap"))
    assert ei.value.topic == "/tf" and ei.value.time_ns == T0 + 500_000_000


def test_calibration_size_differs_from_images(tmp_path: Path) -> None:
    bag = Bag()
    bag.messages[0] = (TOPICS.calibration, "sensor_msgs/msg/CameraInfo",
                       bag.camera_info(T0, width=40), T0)
    rec = read(bag.write(tmp_path / "size.mcap"))
    with pytest.raises(ImageDecodeError, match=r"is 32x24 pixels but its calibration "
                                               r"\('camera'\) is 40x24") as ei:
        rec.decode(rec.views[1])
    assert ei.value.topic == TOPICS.views and ei.value.time_ns == VIEW_T[1]
    from robo3d.info import inspect_recording

    info = inspect_recording(tmp_path / "size.mcap", topics=TOPICS, frames=FRAMES)
    assert not info["fit"] and info["stages"]["silhouettes"]["status"] == "unfit"
    assert any("40x24" in r for r in info["stages"]["stripes"]["reasons"])


def test_unknown_image_encoding(tmp_path: Path) -> None:
    bag = Bag()
    i = next(k for k, m in enumerate(bag.messages) if m[0] == TOPICS.views)
    topic, msgtype, _, t = bag.messages[i]
    bag.messages[i] = (topic, msgtype, bag.image(t, _image(0), encoding="nv21"), t)
    with pytest.raises(ImageDecodeError, match=r"raw image encoding 'nv21' is unsupported "
                                               r"\(supported: mono8, rgb8, bgr8, mono16") as ei:
        read(bag.write(tmp_path / "enc.mcap"))
    assert ei.value.topic == TOPICS.views and ei.value.time_ns == t
    # a compressed format OpenCV cannot read: at decode, naming topic and time
    bag = Bag()
    i = next(k for k, m in enumerate(bag.messages) if m[0] == TOPICS.laser)
    topic, msgtype, msg, t = bag.messages[i]
    bag.messages[i] = (topic, msgtype, bag.T["sensor_msgs/msg/CompressedImage"](
        header=msg.header, format="h264", data=np.frombuffer(b"\x00\x00\x00\x01gd", np.uint8)),
        t)
    rec = read(bag.write(tmp_path / "h264.mcap"))
    with pytest.raises(ImageDecodeError, match=r"image \(h264, .*does not decode") as ei:
        rec.decode(rec.laser_frames[0])
    assert ei.value.time_ns == LASER_T[0]


def test_transform_chain_with_a_missing_link(tmp_path: Path) -> None:
    bag = Bag()
    bag.messages[1] = ("/tf_static", "tf2_msgs/msg/TFMessage", bag.tf_msg(
        T0, [("tool0", "laser_link", np.eye(4))]), T0)  # the hand-eye link is missing
    with pytest.raises(TransformError, match=r"no pose for images of frame_id 'camera' in "
                                             r"'base': frame 'camera' is not in the transform "
                                             r"tree \(frames: base, flange, laser\).*frames "
                                             r"renamed from the recording: base_link -> base"):
        read(bag.write(tmp_path / "link.mcap"))
    # two pieces that do not meet: the missing link is named
    bag = Bag()
    bag.messages[1] = ("/tf_static", "tf2_msgs/msg/TFMessage", bag.tf_msg(
        T0, [("camera_link", "camera_optical", np.eye(4))]), T0)
    with pytest.raises(TransformError, match=r"the chain does not connect: camera_link -> "
                                             r"camera and base have no common frame \(missing "
                                             r"link between 'camera_link' and 'base'\)"):
        read(bag.write(tmp_path / "link2.mcap"))


def test_duplicated_and_out_of_order_timestamps(tmp_path: Path) -> None:
    """Messages written out of order, a /tf sample and a view repeated: accepted, sorted,
    warned about, and the poses are those of the clean bag."""
    clean = read(Bag().write(tmp_path / "clean.mcap"))
    bag = Bag()
    rng = np.random.default_rng(3)
    order = rng.permutation(len(bag.messages))
    bag.messages = [bag.messages[i] for i in order]
    tf5 = next(m for m in bag.messages if m[0] == "/tf" and m[3] == T0 + 50_000_000)
    view = next(m for m in bag.messages if m[0] == TOPICS.views and m[3] == VIEW_T[1])
    bag.messages += [tf5, view]
    p = bag.write(tmp_path / "order.mcap")
    rec = read(p)
    assert any("/tf:" in w and "out of order" in w and "sorted them" in w for w in rec.warnings)
    assert any(f"{TOPICS.views}:" in w and "out of order" in w for w in rec.warnings)
    assert any("repeat the timestamp and frame_id" in w for w in rec.warnings)
    assert [m.timestamp_ns for m in rec.views] == VIEW_T
    np.testing.assert_array_equal(rec.camera_poses(rec.views), clean.camera_poses(clean.views))
    # the same stamp with different values: the last kept, and said
    bag = Bag()
    bag.messages.append(("/tf", "tf2_msgs/msg/TFMessage", bag.tf_msg(
        T0 + 50_000_000, [("base_link", "tool0", np.eye(4))]), T0 + 2_000_000_000))
    rec = read(bag.write(tmp_path / "dup.mcap"))
    assert any("duplicated timestamps of transform base -> flange carry different values"
               in w for w in rec.warnings)


# =========================================================================== stage level
def _native(path: Path, views: list[np.ndarray] = (), laser: list[np.ndarray] = ()) -> Path:
    cam = CameraModel("camera", 64, 48, np.array([[60.0, 0, 31.5], [0, 60, 23.5], [0, 0, 1]]))
    with RecordingWriter(path) as w:
        w.write_calibration("/camera/calibration", T0, cam)
        w.write_transforms("/tf_static", T0, [("base", "camera", np.eye(4)),
                                               ("camera", "laser", np.eye(4))])
        for i, img in enumerate(views):
            w.write_image("/camera/image", T0 + i * 10**8, "camera", img, "png")
        for i, img in enumerate(laser):
            w.write_image("/camera/laser_image", T0 + i * 10**7, "camera", img, "png")
    return path


def _object() -> np.ndarray:
    img = np.full((48, 64), 20, np.uint8)
    img[15:35, 20:45] = 200
    return img


def _stripes(columns: list[int]) -> np.ndarray:
    img = np.zeros((48, 64), np.uint8)
    for c in columns:
        img[:, c] = 200
        img[:, [c - 1, c + 1]] = 120
    return img


@pytest.mark.parametrize(("bad", "match"), [
    (np.zeros((48, 64), np.uint8), r"view 2 \(t=1700000000200000000 ns\): silhouette: the image "
                                   r"is uniform \(grey 0.0\)"),
    (np.full((48, 64), 255, np.uint8), r"view 2 .*: silhouette: the image is uniform "
                                       r"\(grey 255.0\)"),
    (np.pad(np.full((2, 2), 255, np.uint8), ((5, 41), (5, 57))),
     r"view 2 .*silhouette is empty: all 1 foreground components are smaller than 200 px"),
])
def test_empty_or_all_white_silhouette(tmp_path: Path, bad: np.ndarray, match: str,
                                      caplog: pytest.LogCaptureFixture) -> None:
    """A view that cannot be segmented is named and flagged with an empty mask, and the
    others go on; when more than half fail, the stage fails naming the first."""
    from robo3d.pipeline import stage_silhouettes

    p = _native(tmp_path / "v.mcap", views=[_object(), _object(), bad])
    out = {k: str(tmp_path / f"s.{k}") for k in ("npz", "rrd", "report")}
    with caplog.at_level("WARNING"):
        report = stage_silhouettes({"recording": str(p)}, out, default_config(), "v")
    assert re.search(rf"{p}: topic /camera/image, {match}.*flagged and not used", caplog.text)
    assert report["views_failed"] == [2] and report["qa_flagged_views"] == [2]
    assert report["views"][2]["qa"]["flags"][0].startswith("segmentation failed: ")
    with np.load(out["npz"]) as z:
        assert z["qa_flagged"].tolist() == [False, False, True]
        assert not z["masks"][2].any() and z["masks"][0].any()
    # the views side by side: the same masks and report, the failure in its place
    out_t = {k: str(tmp_path / f"t.{k}") for k in ("npz", "rrd", "report")}
    report_t = stage_silhouettes({"recording": str(p)}, out_t, default_config(), "v",
                                 threads=2)
    assert ({k: v for k, v in report_t.items() if k != "seconds"}
            == {k: v for k, v in report.items() if k != "seconds"})
    with np.load(out["npz"]) as a, np.load(out_t["npz"]) as b:
        assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
    # two of three: no longer the odd view out
    p2 = _native(tmp_path / "v2.mcap", views=[_object(), bad, bad])
    out2 = {k: str(tmp_path / f"s2.{k}") for k in ("npz", "rrd", "report")}
    with pytest.raises(StageError, match=rf"2 of 3 views could not be segmented .*the first: "
                                         rf"{p2}: topic /camera/image, view 1 .*"):
        stage_silhouettes({"recording": str(p2)}, out2, default_config(), "v", threads=2)
    assert not any(Path(f).exists() for f in out2.values())  # nothing half made
    # in a scan with laser frames the laser goes on alone: no view is used, and the
    # report says why (the hull is then empty: test_carving's has_laser cases)
    with caplog.at_level("WARNING"):
        report = stage_silhouettes({"recording": str(p2)}, out2, default_config(), "v",
                                   has_laser=True)
    assert report["views_failed"] == [0, 1, 2] and report["qa_flagged_views"] == [0, 1, 2]
    assert report["silhouettes_failed"].startswith("2 of 3 views could not be segmented")
    assert "the scan goes on from the laser alone" in caplog.text
    assert report["views"][0]["qa"]["flags"] == [
        "segmentation failed: most views of the recording could not be segmented"]
    with np.load(out2["npz"]) as z:
        assert z["qa_flagged"].all() and not z["masks"].any()
    assert stage_silhouettes({"recording": str(p)}, out, default_config(), "v",
                             has_laser=True)["silhouettes_failed"] is None


def test_laser_frame_with_no_stripe_or_two(tmp_path: Path) -> None:
    from robo3d.pipeline import stage_stripes

    cfg = default_config()
    out = {k: str(tmp_path / f"t.{k}") for k in ("npz", "rrd", "report")}
    one, two, none = _stripes([30]), _stripes([10, 30]), np.zeros((48, 64), np.uint8)
    # one frame without a stripe, one with two: both skipped, counted, and the rest kept
    p = _native(tmp_path / "l.mcap", laser=[one, none, two, one])
    report = stage_stripes({"recording": str(p)}, out, cfg, "l")
    assert report["frames_without_stripe"] == 2
    assert report["frames_without_stripe_all_lines_too_weak"] == 1
    assert report["rejected"]["two_blobs"] == 48  # every row of the two-stripe frame
    assert report["n_points"] == 2 * 48
    with np.load(out["npz"]) as z:
        counts = np.diff(z["offsets"])
        np.testing.assert_allclose(z["u"], 30.0, atol=1e-6)
    np.testing.assert_array_equal(counts, [48, 0, 0, 48])
    # no frame with a usable stripe: the stage fails, naming the file and topic
    for frames in ([none, none], [two, two]):
        p = _native(tmp_path / "n.mcap", laser=frames)
        with pytest.raises(StageError, match=rf"{p}: topic /camera/laser_image: no laser "
                                             rf"stripe found in any of 2 frames"):
            stage_stripes({"recording": str(p)}, out, cfg, "n")


# =========================================================================== property
def _tiny_native(path: Path, encoding: str, crc: bool) -> Path:
    cam = CameraModel("camera", 8, 6, np.array([[8.0, 0, 3.5], [0, 8.0, 2.5], [0, 0, 1]]),
                      np.array([0.01, 0, 0, 0, 0]))
    with RecordingWriter(path, message_encoding=encoding, compression="zstd" if crc else "none",
                         chunk_size=300) as w:
        w.add_metadata("robo3d.recording", {"kind": "scan", "workspace_min": "-1 -1 0",
                                            "workspace_max": "1 1 1"})
        w.write_calibration("/camera/calibration", T0, cam)
        w.write_transforms("/tf_static", T0, [("flange", "camera", T_FLANGE_CAMERA),
                                               ("flange", "laser", np.eye(4))])
        for i in range(12):
            t = T0 + i * 10_000_000
            w.write_transforms("/tf", t, [("base", "flange", t_base_flange(t))])
        rng = np.random.default_rng(0)
        for i in range(3):
            img = rng.integers(0, 256, (6, 8), dtype=np.uint8)
            w.write_image("/camera/image", T0 + 15_000_000 + i * 30_000_000, "camera", img,
                          "mono8")
            w.write_image("/camera/laser_image", T0 + 17_000_000 + i * 30_000_000, "camera",
                          img, "png")
    if not crc:  # zero the chunk CRCs so that mutations reach the message decoders
        raw = bytearray(path.read_bytes())
        pos = 8
        while pos < len(raw) - 8:
            op, ln = struct.unpack_from("<BQ", raw, pos)
            if op == 0x06:
                struct.pack_into("<I", raw, pos + 9 + 24, 0)
            pos += 9 + ln
        path.write_bytes(bytes(raw))
    return path


@pytest.fixture(scope="module")
def seeds(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[bytes, dict]]:
    d = tmp_path_factory.mktemp("seeds")
    bag = Bag()
    bag.messages = [m for m in bag.messages if m[0] != "/tf" or m[3] <= T0 + 120_000_000]
    bag.messages = [m for m in bag.messages if m[0] not in (TOPICS.views, TOPICS.laser)]
    for i in range(2):
        t = T0 + 20_000_000 + i * 40_000_000
        bag.messages.append((TOPICS.views, "sensor_msgs/msg/Image",
                             bag.image(t, _image(i)[:6, :8]), t))
        bag.messages.append((TOPICS.laser, "sensor_msgs/msg/CompressedImage",
                             bag.compressed(t + 1, _image(i)[:6, :8]), t + 1))
    bag.messages[0] = (TOPICS.calibration, "sensor_msgs/msg/CameraInfo",
                       bag.camera_info(T0, 8, 6), T0)
    ros = {"topics": TOPICS, "frames": FRAMES}
    return {
        "protobuf+crc": (_tiny_native(d / "a.mcap", "protobuf", True).read_bytes(), {}),
        "protobuf": (_tiny_native(d / "b.mcap", "protobuf", False).read_bytes(), {}),
        "json": (_tiny_native(d / "c.mcap", "json", False).read_bytes(), {}),
        "ros2": (bag.write(d / "r.mcap", sort=True).read_bytes(), ros),
    }


_mutation = st.one_of(
    st.tuples(st.just("flip"), st.floats(0, 1), st.integers(1, 255)),
    st.tuples(st.just("overwrite"), st.floats(0, 1), st.binary(min_size=1, max_size=16)),
    st.tuples(st.just("truncate"), st.floats(0, 1), st.just(b"")),
    st.tuples(st.just("delete"), st.floats(0, 1), st.integers(1, 64)),
    st.tuples(st.just("insert"), st.floats(0, 1), st.binary(min_size=1, max_size=16)),
)


def _mutate(data: bytes, mutations: list[tuple]) -> bytes:
    b = bytearray(data)
    for kind, where, arg in mutations:
        i = min(int(where * len(b)), max(len(b) - 1, 0))
        if kind == "flip" and b:
            b[i] ^= arg
        elif kind == "overwrite":
            b[i: i + len(arg)] = arg
        elif kind == "truncate":
            del b[i:]
        elif kind == "delete":
            del b[i: i + arg]
        elif kind == "insert":
            b[i:i] = arg
    return bytes(b)


@settings(max_examples=300, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.sampled_from(["protobuf+crc", "protobuf", "json", "ros2"]),
       mutations=st.lists(_mutation, min_size=1, max_size=3))
def test_random_damage_reads_or_raises_robo3d_errors(seeds: dict, tmp_path: Path, seed: str,
                                                     mutations: list[tuple]) -> None:
    data, kw = seeds[seed]
    p = tmp_path / f"m_{seed}.mcap"
    p.write_bytes(_mutate(data, mutations))
    try:
        rec = read_recording(p, **kw)
    except Robo3dError as exc:
        assert str(exc)
    else:
        for msgs in (rec.views, rec.laser_frames):  # what a stage does next
            try:
                rec.camera_poses(msgs)
            except Robo3dError:
                pass
            for m in msgs:
                if m.encoding in ("mono8", "rgb8", "bgr8", "mono16") or m.encoding == "png":
                    try:
                        rec.decode(m)
                    except Robo3dError:
                        pass
        try:
            _ = rec.workspace
        except Robo3dError:
            pass
    s = probe_recording(p, kw.get("topics", TopicMap()))
    assert isinstance(s.readable, bool)


def test_error_types_are_robo3d_errors() -> None:
    for cls in (RecordingError, TransformError, CalibrationError, ImageDecodeError, StageError):
        assert issubclass(cls, Robo3dError)


def test_a_recordings_folder_without_recordings_fails_early_and_says_what_is_there(tmp_path):
    from robo3d.errors import ConfigError
    from robo3d.pipeline import find_recordings

    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match=r"no recording in .*empty \(it is empty\)"):
        find_recordings(str(tmp_path / "empty"))
    bag = tmp_path / "bags" / "scan_0"
    bag.mkdir(parents=True)
    (bag / "scan_0.db3").write_bytes(b"SQLite format 3\x00")
    with pytest.raises(ConfigError, match=r"1 \.db3.*ROS 2 bags in SQLite.*ros2 bag convert"):
        find_recordings([str(tmp_path / "bags")])


def test_status_without_results_and_version(tmp_path, monkeypatch, capsys):
    from robo3d import __version__
    from robo3d.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["status"]) == 1
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and __version__ in capsys.readouterr().out
