"""Tests of robo3d.recording: writer -> reader round trips and every contract error.

Ground truth is analytic: a base -> flange trajectory with linear translation and a
constant-rate rotation about a fixed axis, which linear interpolation + slerp reproduce
exactly between samples; images are known arrays.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set
from mcap_protobuf.writer import Writer as PbWriter

from robo3d.camera import CameraModel, project_points
from robo3d.errors import (
    CalibrationError,
    ImageDecodeError,
    RecordingError,
    TransformError,
)
from robo3d.recording import (
    RecordingWriter,
    TopicMap,
    decode_checked,
    decode_image,
    encode_image,
    probe_recording,
    read_ground_truth_tf,
    read_recording,
)
from robo3d.transforms import euler_to_matrix, make_transform, matrix_to_quat

W, H = 32, 24
T0 = 1_700_000_000_000_000_000  # a realistic epoch in ns: precision must survive it
TF_DT = 10_000_000  # 100 Hz
N_TF = 101  # 1 s of /tf
AXIS = np.array([1.0, 2.0, 2.0]) / 3.0
OMEGA = 0.9  # rad/s
R0 = euler_to_matrix("zyx", [0.3, -0.2, 0.1])
P0 = np.array([0.4, -0.1, 0.5])
V = np.array([0.05, 0.02, -0.03])  # m/s
T_FLANGE_CAMERA = make_transform(euler_to_matrix("zyx", [0.05, 0.1, -3.0]), [0.01, 0.02, 0.1])
T_FLANGE_LASER = make_transform(euler_to_matrix("zyx", [0.0, 0.4, 0.0]), [0.08, 0.0, 0.05])
REAL = Path(__file__).resolve().parents[2] / "shared" / "real" / "middlebury_templeSparseRing.mcap"

CAMERA = CameraModel("camera", W, H, np.array([[40.0, 0, 15.5], [0, 41.0, 11.5], [0, 0, 1]]),
                     np.array([-0.12, 0.03, 0.001, -0.002, 0.004]))


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def t_base_flange(t_ns: int) -> np.ndarray:
    """The analytic trajectory at absolute time ``t_ns``."""
    s = (t_ns - T0) / 1e9
    return make_transform(R0 @ _axis_angle(AXIS, OMEGA * s), P0 + V * s)


def _images() -> dict[str, np.ndarray]:
    yy, xx = np.mgrid[0:H, 0:W]
    rgb = np.stack([xx * 7, yy * 9, (xx + yy) * 3], axis=-1).astype(np.uint8)
    rng = np.random.default_rng(7)
    noise = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    return {
        "png": noise,
        "jpeg": rgb,  # smooth: JPEG error stays small
        "mono8": noise[..., 0].copy(),
        "rgb8": noise,
        "bgr8": noise[..., ::-1].copy(),
        "mono16": (rng.integers(0, 65536, (H, W))).astype(np.uint16),
    }


IMAGE_STAMPS = {enc: T0 + 123_456_789 + i * 97_000_001 for i, enc in enumerate(_images())}
COMPRESSED = ("png", "jpeg")


def write_reference(path: Path, message_encoding: str = "protobuf", **kw: object) -> Path:
    """A complete recording: metadata, attachment, calibration, tf, every image encoding."""
    imgs = _images()
    with RecordingWriter(path, message_encoding=message_encoding, **kw) as w:
        w.add_metadata("robo3d.recording", {"kind": "scan", "object": "cube", "units": "m",
                                            "workspace_min": "-1 -1 0", "workspace_max": "1 1 1"})
        w.add_attachment("ground_truth/mesh.ply", b"ply\nformat ascii 1.0\nend_header\n",
                         "text/plain")
        w.write_calibration("/camera/calibration", T0, CAMERA)
        w.write_transforms("/tf_static", T0, [("flange", "camera", T_FLANGE_CAMERA),
                                               ("flange", "laser", T_FLANGE_LASER)])
        for i in range(N_TF):
            t = T0 + i * TF_DT
            w.write_transforms("/tf", t, [("base", "flange", t_base_flange(t))])
        for enc, img in imgs.items():
            topic = "/camera/image" if enc in COMPRESSED else "/camera/laser_image"
            w.write_image(topic, IMAGE_STAMPS[enc], "camera", img, enc)
    return path


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("ref")
    return {e: write_reference(d / f"ref_{e}.mcap", e) for e in ("protobuf", "json")}


# =========================================================================== round trips
@pytest.mark.parametrize("encoding", ["protobuf", "json"])
def test_round_trip(reference: dict[str, Path], encoding: str) -> None:
    rec = read_recording(reference[encoding])
    assert rec.warnings == []
    # metadata and attachments: exact
    assert rec.info["kind"] == "scan" and rec.info["object"] == "cube"
    lo, hi = rec.workspace
    np.testing.assert_array_equal(lo, [-1, -1, 0])
    np.testing.assert_array_equal(hi, [1, 1, 1])
    assert rec.attachments == {"ground_truth/mesh.ply": b"ply\nformat ascii 1.0\nend_header\n"}
    # calibration: exact
    cam = rec.calibrations["camera"]
    assert (cam.width, cam.height) == (W, H)
    np.testing.assert_array_equal(cam.K, CAMERA.K)
    np.testing.assert_array_equal(cam.D, CAMERA.D)
    # tf: links and interpolation at the image stamps against the analytic trajectory
    assert sorted(rec.tf.links()) == [("base", "flange", False, N_TF),
                                      ("flange", "camera", True, 1),
                                      ("flange", "laser", True, 1)]
    msgs = rec.views + rec.laser_frames
    poses = rec.camera_poses(msgs)
    truth = np.stack([t_base_flange(m.timestamp_ns) @ T_FLANGE_CAMERA for m in msgs])
    assert np.abs(poses - truth).max() < 1e-9
    stamps = np.array([m.timestamp_ns for m in msgs])
    laser = rec.tf.lookup("base", "laser", stamps)
    truth_l = np.stack([t_base_flange(int(t)) @ T_FLANGE_LASER for t in stamps])
    assert np.abs(laser - truth_l).max() < 1e-9
    # images: every encoding; exact except JPEG
    imgs = _images()
    assert [m.encoding for m in rec.views] == ["png", "jpeg"]
    assert [m.encoding for m in rec.laser_frames] == ["mono8", "rgb8", "bgr8", "mono16"]
    for m in msgs:
        assert m.timestamp_ns == IMAGE_STAMPS[m.encoding] and m.frame_id == "camera"
        got = rec.decode(m)
        want = imgs[m.encoding]
        if m.encoding == "bgr8":  # given RGB, stored as BGR bytes, decoded back to RGB
            assert m.data == want[..., ::-1].tobytes()
        assert got.shape == want.shape and got.dtype == want.dtype
        if m.encoding == "jpeg":
            err = np.abs(got.astype(int) - want.astype(int))
            assert err.mean() < 2.0 and err.max() < 24
        else:
            np.testing.assert_array_equal(got, want)


def test_png_mono16_and_mono8_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    img16 = rng.integers(0, 65536, (H, W)).astype(np.uint16)
    img8 = rng.integers(0, 256, (H, W)).astype(np.uint8)
    p = tmp_path / "a.mcap"
    with RecordingWriter(p) as w:
        w.write_calibration("/camera/calibration", T0, CAMERA)
        w.write_transforms("/tf", T0, [("base", "camera", np.eye(4))])
        w.write_image("/camera/image", T0, "camera", img16, "png")
        w.write_image("/camera/image", T0 + 1, "camera", img8, "png")
    rec = read_recording(p, roles=("views",))
    np.testing.assert_array_equal(rec.decode(rec.views[0]), img16)
    np.testing.assert_array_equal(rec.decode(rec.views[1]), img8)


def test_writer_is_deterministic(tmp_path: Path) -> None:
    a = write_reference(tmp_path / "a.mcap").read_bytes()
    b = write_reference(tmp_path / "b.mcap").read_bytes()
    assert a == b


def test_writer_is_atomic(tmp_path: Path) -> None:
    p = tmp_path / "x.mcap"
    w = RecordingWriter(p)
    w.write_calibration("/camera/calibration", T0, CAMERA)
    assert not p.exists()  # nothing under the final name before close
    w.close()
    assert p.exists()
    q = tmp_path / "y.mcap"
    with pytest.raises(RuntimeError), RecordingWriter(q) as w:
        w.write_calibration("/camera/calibration", T0, CAMERA)
        raise RuntimeError("simulator crashed")
    assert not q.exists()
    assert sorted(f.name for f in tmp_path.iterdir()) == ["x.mcap"]  # no temp left
    with pytest.raises(ValueError, match="closed"):
        w.write_calibration("/camera/calibration", T0, CAMERA)


def test_writer_rejects_bad_input(tmp_path: Path) -> None:
    with RecordingWriter(tmp_path / "w.mcap") as w:
        with pytest.raises(ValueError, match="rigid"):
            w.write_transforms("/tf", T0, [("base", "flange", np.diag([1.0, 1, 2, 1]))])
        with pytest.raises(ValueError, match="finite"):
            w.write_transforms("/tf", T0, [("base", "flange", np.full((4, 4), np.nan))])
        with pytest.raises(ValueError, match=r"mono8 image must be \(H, W\) uint8"):
            w.write_image("/camera/image", T0, "camera", np.zeros((H, W, 3), np.uint8), "mono8")
        with pytest.raises(ValueError, match="encoding must be one of"):
            w.write_image("/camera/image", T0, "camera", np.zeros((H, W), np.uint8), "webp")
        with pytest.raises(ValueError, match="stamp_ns"):
            w.write_calibration("/camera/calibration", -5, CAMERA)
        w.write_image("/camera/image", T0, "camera", np.zeros((H, W), np.uint8), "png")
        with pytest.raises(ValueError, match="carries foxglove.CompressedImage"):
            w.write_image("/camera/image", T0, "camera", np.zeros((H, W), np.uint8), "mono8")
        with pytest.raises(ValueError, match="str to str"):
            w.add_metadata("robo3d.recording", {"cols": 7})  # type: ignore[dict-item]
    with pytest.raises(ValueError, match="message_encoding"):
        RecordingWriter(tmp_path / "v.mcap", message_encoding="cdr")


def test_encode_decode_helpers() -> None:
    from robo3d.recording import ImageMessage

    img = _images()["rgb8"]
    for enc in ("png", "rgb8", "bgr8"):
        data = encode_image(img, enc)
        msg = ImageMessage("/t", 5, "camera", enc, data, W, H, 0 if enc == "png" else W * 3)
        np.testing.assert_array_equal(decode_image(msg), img)
    # a raw image with padded rows (step > width * 3) is read honouring step
    padded = np.zeros((H, W * 3 + 5), np.uint8)
    padded[:, : W * 3] = img.reshape(H, W * 3)
    msg = ImageMessage("/t", 5, "camera", "rgb8", padded.tobytes(), W, H, W * 3 + 5)
    np.testing.assert_array_equal(decode_image(msg), img)
    # 16UC1 alias, little-endian
    img16 = _images()["mono16"]
    msg = ImageMessage("/t", 5, "camera", "16UC1", img16.astype("<u2").tobytes(), W, H, W * 2)
    np.testing.assert_array_equal(decode_image(msg), img16)
    np.testing.assert_array_equal(decode_checked(msg, CAMERA), img16)


# =========================================================================== other writers
def _stamp(t: int) -> Timestamp:
    return Timestamp(seconds=t // 10**9, nanos=t % 10**9)


def _tf_msg(t: int, parent: str, child: str, T: np.ndarray,  # noqa: N803
            q: np.ndarray | None = None) -> FrameTransforms:
    q = matrix_to_quat(T[:3, :3]) if q is None else q
    return FrameTransforms(transforms=[FrameTransform(
        timestamp=_stamp(t), parent_frame_id=parent, child_frame_id=child,
        translation=Vector3(x=T[0, 3], y=T[1, 3], z=T[2, 3]),
        rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))])


def _calib_msg(t: int, frame_id: str = "camera", model: str = "plumb_bob",
               D: list[float] | None = None, K: list[float] | None = None,  # noqa: N803
               width: int = W, height: int = H) -> CameraCalibration:
    return CameraCalibration(timestamp=_stamp(t), frame_id=frame_id, width=width,
                             height=height, distortion_model=model,
                             D=list(CAMERA.D) if D is None else D,
                             K=list(CAMERA.K.reshape(-1)) if K is None else K)


def _png(img: np.ndarray | None = None) -> bytes:
    return encode_image(_images()["png"] if img is None else img, "png")


def _img_msg(t: int, frame_id: str = "camera", data: bytes | None = None,
             fmt: str = "png") -> CompressedImage:
    return CompressedImage(timestamp=_stamp(t), frame_id=frame_id,
                           data=_png() if data is None else data, format=fmt)


def craft(path: Path, messages: list[tuple[str, object]], *, calib: bool = True,
          tf: bool = True) -> Path:
    """A recording written with mcap-protobuf's own writer (not ours): (topic, message);
    by default with a calibration and a static base -> camera transform."""
    with open(path, "wb") as f:
        w = PbWriter(f)
        if calib:
            w.write_message("/camera/calibration", _calib_msg(T0), log_time=T0, publish_time=T0)
        if tf:
            w.write_message("/tf_static", _tf_msg(T0, "base", "camera", np.eye(4)),
                            log_time=T0, publish_time=T0)
        for i, (topic, msg) in enumerate(messages):
            w.write_message(topic, msg, log_time=T0 + i, publish_time=T0 + i)
        w.finish()
    return path


def test_json_from_another_writer(tmp_path: Path) -> None:
    """Hand-made JSON: a schema that is just a title, image/png format, padded raw rows,
    FrameTransform (singular) on /tf, timestamps as {sec, nsec}."""
    p = tmp_path / "j.mcap"
    img = _images()["rgb8"]
    padded = np.zeros((H, W * 3 + 4), np.uint8)
    padded[:, : W * 3] = img.reshape(H, W * 3)
    with open(p, "wb") as f:
        w = McapWriter(f)
        w.start()

        def chan(topic: str, name: str) -> int:
            sid = w.register_schema(name, "jsonschema", json.dumps({"title": name}).encode())
            return w.register_channel(topic, "json", sid)

        cc, ct, ci, cl = (chan("/camera/calibration", "foxglove.CameraCalibration"),
                          chan("/tf", "foxglove.FrameTransform"),
                          chan("/camera/image", "foxglove.CompressedImage"),
                          chan("/camera/laser_image", "foxglove.RawImage"))
        ts = {"sec": T0 // 10**9, "nsec": 5}

        def put(cid: int, obj: dict) -> None:
            w.add_message(cid, log_time=0, data=json.dumps(obj).encode(), publish_time=0)

        put(cc, {"timestamp": ts, "frame_id": "camera", "width": W, "height": H,
                 "distortion_model": "plumb_bob", "D": CAMERA.D.tolist(),
                 "K": CAMERA.K.reshape(-1).tolist()})
        for k in range(3):
            put(ct, {"timestamp": {"sec": T0 // 10**9 - 1 + k, "nsec": 0},
                     "parent_frame_id": "base", "child_frame_id": "camera",
                     "translation": {"x": 1.0 * k, "y": 0, "z": 0},
                     "rotation": {"x": 0, "y": 0, "z": 0, "w": 1}})
        put(ci, {"timestamp": ts, "frame_id": "camera", "format": "image/png",
                 "data": base64.b64encode(_png(img)).decode()})
        put(cl, {"timestamp": ts, "frame_id": "camera", "width": W, "height": H,
                 "encoding": "bgr8", "step": W * 3 + 4,
                 "data": base64.b64encode(padded[:, : W * 3 + 4].tobytes()).decode()})
        w.finish()
    rec = read_recording(p, max_pose_gap_ns=2_000_000_000)
    assert rec.warnings == []
    assert rec.views[0].timestamp_ns == T0 - T0 % 10**9 + 5  # its own stamp, not log time 0
    np.testing.assert_array_equal(rec.decode(rec.views[0]), img)
    np.testing.assert_array_equal(rec.decode(rec.laser_frames[0]), img[..., ::-1])
    pose = rec.camera_poses(rec.views)[0]
    np.testing.assert_allclose(pose[:3, 3], [1.0 + 5e-9, 0, 0], atol=1e-12)


def test_frame_transform_singular_and_missing_timestamp(tmp_path: Path) -> None:
    """FrameTransform (singular) on /tf; a message without timestamp falls back to log
    time with a warning."""
    ft = FrameTransform(parent_frame_id="base", child_frame_id="camera",
                        translation=Vector3(x=1.0), rotation=Quaternion(w=1.0))
    p = craft(tmp_path / "s.mcap", [("/tf", ft), ("/camera/image", _img_msg(T0 + 1))], tf=False)
    rec = read_recording(p, roles=("views",))
    assert rec.tf.links() == [("base", "camera", False, 1)]
    stamps, _ = rec.tf.link_samples("base", "camera")
    assert stamps.tolist() == [T0]  # the log time craft() gave it
    assert any("no timestamp" in w for w in rec.warnings)


# =========================================================================== errors
def test_not_an_mcap_file(tmp_path: Path) -> None:
    p = tmp_path / "x.mcap"
    p.write_bytes(b"PK\x03\x04 this is a zip, not an mcap" * 10)
    with pytest.raises(RecordingError, match="not an MCAP file") as ei:
        read_recording(p)
    assert str(p) in str(ei.value)
    s = probe_recording(p)
    assert not s.readable and "not an MCAP file" in s.problem
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        read_recording(empty)
    assert not probe_recording(tmp_path / "missing.mcap").readable
    assert not probe_recording(tmp_path).readable  # a directory


def test_truncated_at_many_offsets(tmp_path: Path) -> None:
    full = write_reference(tmp_path / "full.mcap", chunk_size=2048).read_bytes()
    n_views = 2
    data_end = full.rfind(bytes([0x0F]) + (4).to_bytes(8, "little"))  # DataEnd record
    offsets = sorted({1, 7, 8, 9, 40, 200, len(full) // 4, len(full) // 2, 3 * len(full) // 4,
                      data_end - 1, data_end + 13, len(full) - 40, len(full) - 8, len(full) - 1})
    outcomes = {}
    for off in offsets:
        p = tmp_path / f"cut_{off}.mcap"
        p.write_bytes(full[:off])
        try:
            rec = read_recording(p, roles=("views",))
        except RecordingError as exc:  # any other exception fails the test
            assert str(p) in str(exc)
            if off >= 8:
                assert "truncated" in str(exc)
            outcomes[off] = "error"
        else:
            assert any("truncated" in w for w in rec.warnings), off
            assert 0 < len(rec.views) <= n_views
            outcomes[off] = len(rec.views)
            if off > data_end:  # only the summary was cut: everything is intact
                assert len(rec.views) == n_views
                assert any("every message is intact" in w or "no data lost" in w
                           for w in rec.warnings)
            else:
                w = next(w for w in rec.warnings if "truncated" in w)
                assert f" of {off} (" in w and "bytes are unusable" in w and "lost" in w
        s = probe_recording(p)  # never raises
        assert isinstance(s.readable, bool)
    assert outcomes[1] == "error" and outcomes[len(full) - 1] == n_views
    assert outcomes[40] == "error"


def test_truncated_missing_role_says_truncated(tmp_path: Path) -> None:
    full = write_reference(tmp_path / "full.mcap", chunk_size=1024).read_bytes()
    first_laser = full.find(b"mono8")  # inside the first laser image's chunk
    p = tmp_path / "cut.mcap"
    p.write_bytes(full[:first_laser])
    with pytest.raises(RecordingError, match="required topic /camera/laser_image has no "
                                             "messages.*truncated"):
        read_recording(p)


def test_corrupt_chunk_is_skipped_with_warning(tmp_path: Path) -> None:
    p = tmp_path / "c.mcap"
    with RecordingWriter(p, compression="none", chunk_size=64) as w:
        w.write_calibration("/camera/calibration", T0, CAMERA)
        w.write_transforms("/tf_static", T0, [("base", "camera", np.eye(4))])
        for i in range(5):
            w.write_image("/camera/image", T0 + i * 1000, "camera", _images()["png"], "png")
    raw = bytearray(p.read_bytes())
    pngs = [i for i in range(len(raw)) if raw.startswith(b"\x89PNG", i)]
    assert len(pngs) == 5
    for k in (0, 2):
        raw[pngs[k] + 20] ^= 0xFF
    # the first image's chunk also holds the topic's channel record (damaged here too): the
    # later images are matched to the channel repeated in the summary section
    chan = raw.find(b"/camera/image")
    assert pngs[0] - 200 < chan < pngs[0]
    raw[chan + 3] ^= 0xFF
    p.write_bytes(bytes(raw))
    rec = read_recording(p, roles=("views",))
    assert [m.timestamp_ns - T0 for m in rec.views] == [1000, 3000, 4000]
    crc = [w for w in rec.warnings if "CRC" in w]
    assert len(crc) == 2 and "messages logged" in crc[0]


def test_missing_topic(reference: dict[str, Path], tmp_path: Path) -> None:
    p = craft(tmp_path / "v.mcap", [("/camera/image", _img_msg(T0))])
    with pytest.raises(RecordingError, match="required topic /camera/laser_image has no "
                                             "messages") as ei:
        read_recording(p)
    assert ei.value.topic == "/camera/laser_image"
    assert len(read_recording(p, roles=("views",)).views) == 1
    assert len(read_recording(p, require=False).views) == 1
    # a remapped topic name is honoured
    topics = TopicMap(views="/cam0/image")
    with pytest.raises(RecordingError, match="required topic /cam0/image"):
        read_recording(p, roles=("views",), topics=topics)


def test_no_calibration_for_frame_id(tmp_path: Path) -> None:
    p = craft(tmp_path / "f.mcap", [("/camera/image", _img_msg(T0 + 77, frame_id="cam_b"))])
    with pytest.raises(CalibrationError, match="no calibration for frame_id 'cam_b'") as ei:
        read_recording(p, roles=("views",))
    assert ei.value.topic == "/camera/image" and ei.value.time_ns == T0 + 77
    p = craft(tmp_path / "n.mcap", [("/camera/image", _img_msg(T0))], calib=False)
    with pytest.raises(CalibrationError, match="topic /camera/calibration has no messages"):
        read_recording(p, roles=("views",))


def test_no_tf_at_all(tmp_path: Path) -> None:
    p = craft(tmp_path / "t.mcap", [("/camera/image", _img_msg(T0))], tf=False)
    with pytest.raises(TransformError, match="no transforms"):
        read_recording(p, roles=("views",))


def test_chain_that_does_not_connect(tmp_path: Path) -> None:
    msgs = [("/tf_static", _tf_msg(T0, "flange", "laser", np.eye(4))),
            ("/tf_static", _tf_msg(T0, "tool", "camera", np.eye(4))),
            ("/tf", _tf_msg(T0, "base", "flange", np.eye(4))),
            ("/camera/image", _img_msg(T0))]
    p = craft(tmp_path / "c.mcap", msgs, tf=False)
    with pytest.raises(TransformError, match="missing link between 'tool' and 'base'") as ei:
        read_recording(p, roles=("views",))
    assert ei.value.topic == "/camera/image" and "camera" in str(ei.value)


def test_image_that_does_not_decode(tmp_path: Path) -> None:
    p = craft(tmp_path / "d.mcap", [("/camera/image", _img_msg(T0 + 9, data=b"\x89PNG garbage"))])
    rec = read_recording(p, roles=("views",))  # kept encoded: decoding is later
    with pytest.raises(ImageDecodeError, match="does not decode") as ei:
        rec.decode(rec.views[0])
    assert ei.value.topic == "/camera/image" and ei.value.time_ns == T0 + 9
    assert str(p) in str(ei.value)
    raw = RawImage(timestamp=_stamp(T0), frame_id="camera", width=W, height=H,
                   encoding="mono8", step=W, data=b"\x00" * (W * H - 1))
    rec = read_recording(craft(tmp_path / "r.mcap", [("/camera/laser_image", raw)]),
                         roles=("laser",))
    with pytest.raises(ImageDecodeError, match="bytes of data"):
        rec.decode(rec.laser_frames[0])
    raw.encoding = "32FC1"  # a depth image on the laser topic
    with pytest.raises(ImageDecodeError, match="'32FC1' is unsupported"):
        read_recording(craft(tmp_path / "y.mcap", [("/camera/laser_image", raw)]),
                       roles=("laser",))


def test_image_size_differs_from_calibration(tmp_path: Path) -> None:
    small = _png(_images()["png"][: H // 2, : W // 2])
    p = craft(tmp_path / "s.mcap", [("/camera/image", _img_msg(T0, data=small))])
    rec = read_recording(p, roles=("views",))
    assert decode_image(rec.views[0]).shape == (H // 2, W // 2, 3)
    with pytest.raises(ImageDecodeError, match=f"is {W // 2}x{H // 2} pixels but its "
                                               f"calibration .* is {W}x{H}"):
        rec.decode(rec.views[0])


@pytest.mark.parametrize("bad", ["nan", "inf", "quat"])
def test_non_finite_or_non_unit_tf(tmp_path: Path, bad: str) -> None:
    T = np.eye(4)  # noqa: N806
    q = np.array([0.0, 0.0, 0.0, 1.0])
    if bad == "nan":
        T[1, 3] = np.nan
    elif bad == "inf":
        q[0] = np.inf
    else:
        q[3] = 1.01
    msgs = [("/tf", _tf_msg(T0 + k * TF_DT, "base", "flange", np.eye(4))) for k in range(3)]
    msgs.insert(2, ("/tf", _tf_msg(T0 + 15_000_000, "base", "flange", T, q)))
    p = craft(tmp_path / "n.mcap", msgs + [("/camera/image", _img_msg(T0))])
    with pytest.raises(TransformError, match="not finite" if bad != "quat" else
                       "not a unit quaternion") as ei:
        read_recording(p, roles=("views",))
    assert ei.value.topic == "/tf" and ei.value.time_ns == T0 + 15_000_000


def test_slightly_non_unit_quaternion_is_renormalised(tmp_path: Path) -> None:
    r = euler_to_matrix("zyx", [0.4, 0.2, -0.1])
    q = matrix_to_quat(r) * 1.0005
    tf = _tf_msg(T0, "base", "camera", make_transform(r, [0, 0, 0]), q)
    p = craft(tmp_path / "q.mcap", [("/tf", tf), ("/camera/image", _img_msg(T0))], tf=False)
    rec = read_recording(p, roles=("views",))
    assert np.abs(rec.camera_poses(rec.views)[0][:3, :3] - r).max() < 1e-12


def test_out_of_order_timestamps_sorted_and_warned(tmp_path: Path) -> None:
    p = tmp_path / "o.mcap"
    stamps = [T0 + i * TF_DT for i in range(N_TF)]
    order = list(range(N_TF))
    order[10], order[11] = order[11], order[10]
    order[50], order[40] = order[40], order[50]
    img_t = [IMAGE_STAMPS["png"], T0 + 50_000_000, T0 + 20_000_001]
    with RecordingWriter(p) as w:
        w.write_calibration("/camera/calibration", T0, CAMERA)
        w.write_transforms("/tf_static", T0, [("flange", "camera", T_FLANGE_CAMERA)])
        for i in order:
            w.write_transforms("/tf", stamps[i], [("base", "flange", t_base_flange(stamps[i]))])
        w.write_transforms("/tf", stamps[30], [("base", "flange", t_base_flange(stamps[30]))])
        for t in img_t:
            w.write_image("/camera/image", t, "camera", _images()["png"], "png")
    rec = read_recording(p, roles=("views",))
    assert any("/tf: 4 timestamps of transform base -> flange are out of order" in x
               for x in rec.warnings)
    assert any("/camera/image: 2 image timestamps are out of order" in x for x in rec.warnings)
    assert [m.timestamp_ns for m in rec.views] == sorted(img_t)
    s, _ = rec.tf.link_samples("base", "flange")
    assert np.all(np.diff(s) > 0) and len(s) == N_TF  # sorted, duplicate merged
    poses = rec.camera_poses(rec.views)
    truth = np.stack([t_base_flange(m.timestamp_ns) @ T_FLANGE_CAMERA for m in rec.views])
    assert np.abs(poses - truth).max() < 1e-9


def test_image_outside_pose_stream_names_topic_and_time(reference: dict[str, Path]) -> None:
    rec = read_recording(reference["protobuf"], max_pose_gap_ns=5_000_000)
    with pytest.raises(TransformError, match="max_pose_gap") as ei:
        rec.camera_poses(rec.views)
    assert ei.value.topic == "/camera/image" and ei.value.time_ns == rec.views[0].timestamp_ns


@pytest.mark.parametrize(("model", "D", "ok"), [
    ("rational_polynomial", [-0.1, 0.01, 0.001, 0.0, 0.002, 0.0, 0.0, 0.0], True),
    # with k4..k6: rectified to a pinhole camera (tests/test_rectified_lenses.py)
    ("rational_polynomial", [-0.1, 0.01, 0.001, 0.0, 0.002, 0.3, 0.0, 0.0], "rectified"),
    ("rational_polynomial", [-0.1, 0.01, 0.001, 0.0, 0.002, 0.3, 0.0], False),
    # OpenCV's 14 (thin prism, tilt): rectified; with only zeros past k3, plumb_bob
    ("rational_polynomial", [-0.1, 0.01, 0.001, 0.0, 0.002, 0.3] + [0.0] * 7 + [0.001],
     "rectified"),
    ("rational_polynomial", [-0.1, 0.01, 0.001, 0.0, 0.002] + [0.0] * 9, True),
    ("equidistant", [0.0, 0.0, 0.0, 0.0], "rectified"),  # ROS's fisheye model
    ("kannala_brandt", [0.1, 0.01, 0.0, 0.0], "rectified"),  # Foxglove's name for it
    ("kannala_brandt", [0.1, 0.01, 0.0, 0.0, 0.0], False),
    ("fisheye62", [0.1, 0.01, 0.0, 0.0, 0.0, 0.0], False),  # Project Aria's: no OpenCV model
    ("equidistant", [0.1, 0.0, 0.0, 0.0, 0.0], False),
    ("plumb_bob", [0.1, np.nan, 0.0, 0.0, 0.0], False),
    ("plumb_bob", [0.1, 0.0, 0.0], False),
    ("", [], True),
    ("", [0.1, 0.0, 0.0, 0.0, 0.0], True),
])
def test_distortion_models(tmp_path: Path, model: str, D: list[float], ok: bool) -> None:  # noqa: N803
    msgs = [("/camera/calibration", _calib_msg(T0, model=model, D=D)),
            ("/camera/image", _img_msg(T0))]
    p = craft(tmp_path / "d.mcap", msgs, calib=False)
    if ok:
        rec = read_recording(p, roles=("views",))
        cam = rec.calibrations["camera"]
        want = np.zeros(5) if not D or ok == "rectified" else np.array(D[:5])
        np.testing.assert_array_equal(cam.D, want)
        assert ("camera" in rec.rectifiers) == (ok == "rectified")
        if ok == "rectified":  # its images as the pinhole camera sees them
            raw, img = rec.decode_raw(rec.views[0]), rec.decode(rec.views[0])
            assert img.shape == raw.shape and img.dtype == raw.dtype
    else:
        with pytest.raises(CalibrationError) as ei:
            read_recording(p, roles=("views",))
        assert ei.value.topic == "/camera/calibration"
        assert "unsupported" in str(ei.value) or "finite" in str(ei.value) or \
            "coefficients" in str(ei.value)


def test_kannala_brandt_is_read_as_the_equidistant_fisheye(tmp_path: Path) -> None:
    """Foxglove's CameraCalibration names OpenCV's fisheye model ``kannala_brandt``, ROS
    names it ``equidistant``: the same lens, the same pinhole camera and pixels."""
    recs = {}
    for model in ("kannala_brandt", "equidistant"):
        msgs = [("/camera/calibration", _calib_msg(T0, model=model, D=[0.1, 0.01, 0.0, 0.0])),
                ("/camera/image", _img_msg(T0))]
        recs[model] = read_recording(craft(tmp_path / f"{model}.mcap", msgs, calib=False),
                                     roles=("views",))
    kb, eq = recs["kannala_brandt"], recs["equidistant"]
    assert kb.rectifiers["camera"].fisheye and kb.rectifiers["camera"].model == "equidistant"
    np.testing.assert_array_equal(kb.calibrations["camera"].K, eq.calibrations["camera"].K)
    np.testing.assert_array_equal(kb.decode(kb.views[0]), eq.decode(eq.views[0]))
    # the fisheye moved the pixels: the rectified image is not the raw one
    assert not np.array_equal(kb.decode(kb.views[0]), kb.decode_raw(kb.views[0]))


def test_a_calibration_published_with_every_image_makes_one_rectifier(
        tmp_path: Path, monkeypatch) -> None:
    """ROS drivers publish CameraInfo with every image; a rational_polynomial camera is
    rectified once, not once per message (each Rectifier costs tens of milliseconds)."""
    import robo3d.recording.decoding as dec

    made = []
    real = dec.Rectifier

    def counting(*a, **k):
        made.append(a[0])
        return real(*a, **k)

    monkeypatch.setattr(dec, "Rectifier", counting)
    D = [-0.1, 0.01, 0.001, 0.0, 0.002, 0.3, 0.0, 0.0]  # noqa: N806
    msgs = [("/camera/calibration", _calib_msg(T0 + i, model="rational_polynomial", D=D))
            for i in range(50)] + [("/camera/image", _img_msg(T0))]
    rec = read_recording(craft(tmp_path / "many.mcap", msgs, calib=False), roles=("views",))
    assert made == ["camera"] and rec.warnings == []
    assert rec.calibrations["camera"] is rec.rectifiers["camera"].camera


def test_non_finite_or_uncalibrated_K(tmp_path: Path) -> None:  # noqa: N802
    k = list(CAMERA.K.reshape(-1))
    k[2] = np.inf
    for kk, match in ((k, "non-finite"), ([0.0] * 9, "uncalibrated")):
        p = craft(tmp_path / "k.mcap", [("/camera/calibration", _calib_msg(T0, K=kk)),
                                        ("/camera/image", _img_msg(T0))], calib=False)
        with pytest.raises(CalibrationError, match=match):
            read_recording(p, roles=("views",))


def test_unsupported_encoding_and_schema(tmp_path: Path) -> None:
    p = tmp_path / "cbor.mcap"
    with open(p, "wb") as f:
        w = McapWriter(f)
        w.start()
        sid = w.register_schema("foxglove.CompressedImage", "", b"")
        cid = w.register_channel("/camera/image", "cbor", sid)
        w.add_message(cid, log_time=T0, data=b"\x00\x01\x00\x00", publish_time=T0)
        w.finish()
    with pytest.raises(RecordingError, match="unsupported message encoding 'cbor'.*"
                                             "foxglove.CompressedImage") as ei:
        read_recording(p, roles=("views",))
    assert ei.value.topic == "/camera/image"
    s = probe_recording(p)
    assert not s.readable and "'cbor'" in s.problem
    # ROS 2 CDR with an IDL schema: named, with what is read instead
    p = tmp_path / "idl.mcap"
    with open(p, "wb") as f:
        w = McapWriter(f)
        w.start(profile="ros2")
        sid = w.register_schema("sensor_msgs/msg/CompressedImage", "ros2idl", b"module x {};")
        cid = w.register_channel("/camera/image", "cdr", sid)
        w.add_message(cid, log_time=T0, data=b"\x00\x01\x00\x00", publish_time=T0)
        w.finish()
    with pytest.raises(RecordingError, match="'sensor_msgs/msg/CompressedImage' is encoded "
                                             "as 'ros2idl'.*ros2msg"):
        read_recording(p, roles=("views",))
    # a CDR message that does not decode against its schema: wrapped, with its time
    p = tmp_path / "cdr.mcap"
    with open(p, "wb") as f:
        w = McapWriter(f)
        w.start(profile="ros2")
        sid = w.register_schema("sensor_msgs/msg/CompressedImage", "ros2msg", b"string format")
        cid = w.register_channel("/camera/image", "cdr", sid)
        w.add_message(cid, log_time=T0, data=b"\x00\x01\x00\x00", publish_time=T0)
        w.finish()
    with pytest.raises(RecordingError, match="CompressedImage message does not decode") as ei:
        read_recording(p, roles=("views",))
    assert ei.value.topic == "/camera/image" and ei.value.time_ns == T0
    # a Foxglove schema, but the wrong one for the topic
    p = craft(tmp_path / "w.mcap", [("/tf", _img_msg(T0)), ("/camera/image", _img_msg(T0))])
    with pytest.raises(RecordingError, match="schema 'foxglove.CompressedImage'.*not supported "
                                             "on this topic") as ei:
        read_recording(p, roles=("views",))
    assert ei.value.topic == "/tf"


def test_undecodable_protobuf_message_is_wrapped(tmp_path: Path) -> None:
    p = tmp_path / "u.mcap"
    with open(p, "wb") as f:
        w = McapWriter(f)
        w.start()
        sid = w.register_schema("foxglove.CompressedImage", "protobuf",
                                build_file_descriptor_set(CompressedImage).SerializeToString())
        cid = w.register_channel("/camera/image", "protobuf", sid)
        w.add_message(cid, log_time=T0 + 3, data=b"\xff\xff\xff\xff", publish_time=T0)
        w.finish()
    with pytest.raises(RecordingError, match="does not decode") as ei:
        read_recording(p, roles=("views",), require=False)
    assert ei.value.topic == "/camera/image" and ei.value.time_ns == T0 + 3


# =========================================================================== probe, ground truth
def test_probe(reference: dict[str, Path], tmp_path: Path) -> None:
    for enc, p in reference.items():
        s = probe_recording(p)
        assert s.readable and s.problem is None, enc
        assert (s.n_views, s.n_laser_frames, s.n_calibrations, s.n_tf) == (2, 4, 1, N_TF + 1)
        assert s.kind == "scan" and s.has_ground_truth
    # no usable summary (truncated in the data section): falls back to a scan
    full = reference["protobuf"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full[: int(len(full) * 0.9)])
    s = probe_recording(cut)
    assert s.readable and "truncated" in s.problem
    assert s.kind == "scan" and s.has_ground_truth and s.n_calibrations == 1
    assert s.n_views <= 2 and s.n_tf >= N_TF // 2
    # no images at all
    p = craft(tmp_path / "noimg.mcap", [])
    s = probe_recording(p)
    assert not s.readable and "no images" in s.problem


def test_read_ground_truth_tf(tmp_path: Path) -> None:
    stamps = [T0 + i * TF_DT for i in range(N_TF)]
    poses = [t_base_flange(t) for t in stamps]
    doc = {"transforms": [{"parent": "base", "child": "flange", "stamps_ns": stamps,
                           "translations": [p[:3, 3].tolist() for p in poses],
                           "quaternions": [matrix_to_quat(p[:3, :3]).tolist() for p in poses]}]}
    p = tmp_path / "g.mcap"
    with RecordingWriter(p) as w:
        w.add_attachment("ground_truth/tf.json", json.dumps(doc).encode(), "application/json")
        w.write_calibration("/camera/calibration", T0, CAMERA)
        w.write_transforms("/tf", T0, [("base", "camera", np.eye(4))])
        w.write_image("/camera/image", T0, "camera", _images()["png"], "png")
    rec = read_recording(p, roles=("views",), max_pose_gap_ns=12_000_000)
    assert probe_recording(p).has_ground_truth
    gt = read_ground_truth_tf(rec)
    assert gt.max_gap_ns == 12_000_000
    t = T0 + 333_333_333
    assert np.abs(gt.lookup("base", "flange", t) - t_base_flange(t)).max() < 1e-9
    del rec.attachments["ground_truth/tf.json"]
    with pytest.raises(RecordingError, match="no ground_truth/tf.json attachment"):
        read_ground_truth_tf(rec)
    rec.attachments["ground_truth/tf.json"] = b'{"transforms": [{"parent": "base"}]}'
    with pytest.raises(RecordingError, match="needs parent, child"):
        read_ground_truth_tf(rec)


# =========================================================================== speed, real data
def test_read_300_frames_with_1khz_poses(tmp_path: Path) -> None:
    p = tmp_path / "big.mcap"
    img = _images()["png"]
    with RecordingWriter(p) as w:
        w.write_calibration("/camera/calibration", T0, CAMERA)
        w.write_transforms("/tf_static", T0, [("flange", "camera", T_FLANGE_CAMERA)])
        for i in range(3001):  # 1 kHz over the 3 s of the sweep
            t = T0 + i * 1_000_000
            w.write_transforms("/tf", t, [("base", "flange", t_base_flange(t))])
        for i in range(300):
            w.write_image("/camera/laser_image", T0 + i * 10_000_000 + 500, "camera", img, "png")
    rec = read_recording(p, roles=("laser",))
    assert len(rec.laser_frames) == 300


@pytest.mark.skipif(not REAL.exists(), reason=f"real recording {REAL} not present "
                    "(it lives in the shared folder, outside the project)")
def test_middlebury_real_recording() -> None:
    """Seitz et al., CVPR 2006, templeSparseRing: 16 views on a ring, one calibration."""
    rec = read_recording(REAL, roles=("views",))
    assert len(rec.views) == 16 and list(rec.calibrations) == ["camera"]
    cam = rec.calibrations["camera"]
    assert (cam.width, cam.height) == (640, 480) and not cam.has_distortion
    poses = rec.camera_poses(rec.views)
    r = poses[:, :3, :3]
    assert np.abs(r @ np.swapaxes(r, 1, 2) - np.eye(3)).max() < 1e-9
    lo, hi = rec.workspace
    centre = (lo + hi) / 2
    for pose in poses:  # the object's centre is in front of every camera, inside the image
        uv, front = project_points(centre[None], cam, pose)
        assert front[0] and 0 <= uv[0, 0] < 640 and 0 <= uv[0, 1] < 480
    # the ring: camera centres all at about the same distance from the object
    dist = np.linalg.norm(poses[:, :3, 3] - centre, axis=1)
    assert dist.std() / dist.mean() < 0.05
    img = rec.decode(rec.views[0])
    assert img.shape == (480, 640, 3) and img.dtype == np.uint8
    s = probe_recording(REAL)
    assert s.readable and (s.n_views, s.n_calibrations, s.kind) == (16, 1, "scan")

