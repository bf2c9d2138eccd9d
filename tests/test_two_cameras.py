"""A recording whose views come from two cameras (``../shared/recording-format.md``: "more
cameras: any frame_id, matched by name"): each image is matched to its own calibration
and its own hand-eye by ``frame_id``.

The second camera is made from a simulated recording without rendering again: every
other view is re-sampled as seen by a camera ``camera_b`` turned 4 degrees about its
optical centre, at half the resolution, with its own calibration and its own
``flange -> camera_b`` link. A turn about the optical centre changes no line of sight, so
the new image is exact up to interpolation; its true silhouette is re-sampled the same
way. Were the images matched to the first camera's intrinsics or hand-eye, the views
would disagree by 4 degrees or a factor of two: the control, camera_b recorded with
camera's link, has the carve's agreement check flag every camera_b view."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

TURN_DEG = 4.0
SCALE = 0.5


def _turn(deg: float) -> np.ndarray:
    a = np.radians(deg)  # about the camera's y axis (image columns shift)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _second_camera(cam, scale: float):
    from robo3d.camera import CameraModel

    K = cam.K.copy()
    K[:2, :2] *= scale
    K[:2, 2] = (cam.K[:2, 2] + 0.5) * scale - 0.5  # about pixel centres
    return CameraModel("camera_b", int(round(cam.width * scale)),
                       int(round(cam.height * scale)), K, cam.D)


def _resample(img: np.ndarray, cam, cam_b, R_cam_camb: np.ndarray,
              nearest: bool = False) -> np.ndarray:
    """``img`` (taken by ``cam``) as ``cam_b`` sees it, ``cam_b`` turned by ``R_cam_camb``
    about the same optical centre: each pixel's ray, turned into ``cam``'s frame and
    projected there (both lenses' distortion)."""
    import cv2

    src = cam
    if not nearest:  # to the new size first (area average), then sample the turn
        img = cv2.resize(img, (cam_b.width, cam_b.height), interpolation=cv2.INTER_AREA)
        src = _second_camera(cam, cam_b.width / cam.width)
    v, u = np.mgrid[0:cam_b.height, 0:cam_b.width].astype(np.float64)
    rays = cam_b.rays(np.stack([u.ravel(), v.ravel()], axis=1))
    uv, _ = src.project(rays @ R_cam_camb.T)
    maps = uv.reshape(cam_b.height, cam_b.width, 2).astype(np.float32)
    return cv2.remap(img, maps[..., 0], maps[..., 1],
                     cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


def _two_camera_copy(src: Path, dst: Path, own_hand_eye: bool = True) -> Path:
    """``src`` with its odd views (in time order) from ``camera_b``; with ``own_hand_eye``
    False its link says it looks where ``camera`` does (4 degrees off the truth)."""
    import cv2
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from mcap.reader import make_reader
    from mcap.writer import Writer

    from robo3d.recording import read_recording
    from robo3d.transforms import matrix_to_quat, quat_to_matrix

    cam = next(iter(read_recording(src, roles=("views",)).calibrations.values()))
    cam_b = _second_camera(cam, SCALE)
    R = _turn(TURN_DEG)
    with open(src, "rb") as f:
        r = make_reader(f)
        msgs = list(r.iter_messages(log_time_order=False))
        metadata = list(r.iter_metadata())
        attachments = list(r.iter_attachments())
    views = sorted((CompressedImage.FromString(m.data).timestamp.ToNanoseconds(), i)
                   for i, (_, c, m) in enumerate(msgs) if c.topic == "/camera/image")
    moved = {i for k, (_, i) in enumerate(views) if k % 2}
    with open(dst, "wb") as g:
        w = Writer(g)
        w.start()
        sids: dict[int, int] = {}
        cids: dict[int, int] = {}
        for i, (sch, ch, m) in enumerate(msgs):
            if sch.id not in sids:
                sids[sch.id] = w.register_schema(sch.name, sch.encoding, sch.data)
            if ch.id not in cids:
                cids[ch.id] = w.register_channel(ch.topic, ch.message_encoding, sids[sch.id])
            data = m.data
            if i in moved:
                pb = CompressedImage.FromString(data)
                img = cv2.imdecode(np.frombuffer(pb.data, np.uint8), cv2.IMREAD_UNCHANGED)
                pb.data = cv2.imencode("." + pb.format, _resample(img, cam, cam_b, R))[1].tobytes()
                pb.frame_id = "camera_b"
                data = pb.SerializeToString()
            elif ch.topic == "/camera/calibration":
                pb = CameraCalibration.FromString(data)
                pb.frame_id, pb.width, pb.height = "camera_b", cam_b.width, cam_b.height
                pb.K[:] = cam_b.K.ravel().tolist()
                pb.P[:] = np.hstack([cam_b.K, np.zeros((3, 1))]).ravel().tolist()
                w.add_message(cids[ch.id], log_time=m.log_time, publish_time=m.publish_time,
                              data=pb.SerializeToString())
            elif ch.topic == "/tf_static":
                pb = FrameTransforms.FromString(data)
                for t in list(pb.transforms):
                    if t.child_frame_id == "camera":  # camera_b: the same centre, turned
                        q = [t.rotation.x, t.rotation.y, t.rotation.z, t.rotation.w]
                        tb = pb.transforms.add()
                        tb.CopyFrom(t)
                        tb.child_frame_id = "camera_b"
                        if own_hand_eye:
                            (tb.rotation.x, tb.rotation.y, tb.rotation.z,
                             tb.rotation.w) = matrix_to_quat(quat_to_matrix(q) @ R)
                data = pb.SerializeToString()
            w.add_message(cids[ch.id], log_time=m.log_time, data=data,
                          publish_time=m.publish_time)
        for md in metadata:
            w.add_metadata(md.name, dict(md.metadata))
        odd_ranks = {k for k in range(len(views)) if k % 2}
        for a in attachments:
            data = a.data
            if a.name.startswith("ground_truth/silhouettes/"):
                k = int(Path(a.name).stem)
                if k in odd_ranks:
                    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
                    data = cv2.imencode(".png", _resample(img, cam, cam_b, R, nearest=True)
                                        )[1].tobytes()
            w.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name,
                             media_type=a.media_type, data=data)
        w.finish()
    return dst


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from robo3d.simulate import SimulationParams, simulate_recording

    d = tmp_path_factory.mktemp("twocam")
    rec = d / "one.mcap"
    simulate_recording(rec, "blob", seed=3, params=SimulationParams.small(
        views=8, sweeps=2, sweep_frames=30))
    return rec, _two_camera_copy(rec, d / "two.mcap")


def _scores(rec: Path, res: Path) -> dict[str, float]:
    """The views' masks against the true ones (IoU by camera), the hull's volume IoU and
    the aligned points' median distance to the true surface."""
    from robo3d.artefacts import Silhouettes, load_clouds_npz
    from robo3d.evaluate import TruthSurface, silhouette_iou, volume_iou
    from robo3d.grid import VoxelGrid
    from robo3d.meshio import read_mesh
    from robo3d.recording import read_recording

    r = read_recording(rec, roles=())
    truth = TruthSurface(*read_mesh(bytes(r.attachments["ground_truth/mesh.ply"]),
                                    suffix=".ply"))
    sil = Silhouettes.load(res / "silhouettes.npz")
    iou = silhouette_iou(sil.view_masks(), {k: bytes(v) for k, v in r.attachments.items()})
    by_cam: dict[str, list[float]] = {}
    for v, c in zip(iou["per_view"], sil.cameras, strict=True):
        by_cam.setdefault(c.frame_id, []).append(v["iou"])
    g = VoxelGrid.load_npz(res / "hull.npz")
    pts = np.concatenate([c.points_base for c in load_clouds_npz(res / "aligned.npz")])
    return {"iou_" + k: min(v) for k, v in by_cam.items()} | {
        "hull_iou": volume_iou(g.occupancy, g.origin, g.voxel_size, truth),
        "aligned_median_mm": float(np.median(truth.distance(pts))) * 1e3,
        "n_views": len(sil.cameras),
        "sizes": sorted({(c.frame_id, c.width, c.height) for c in sil.cameras})}


def _flagged(res: Path) -> list[int]:
    """The views the carve's agreement check flagged."""
    import json

    rep = json.loads((res / "reports" / "carve.json").read_text())
    return sorted(rep["agreement"]["flagged"])


def test_views_of_two_cameras_each_with_its_own_calibration_and_hand_eye(
        recordings, tmp_path: Path) -> None:
    from stages_in_process import run_up_to_align

    from robo3d.config import default_config
    from robo3d.recording import read_recording

    one, two = recordings
    cams = read_recording(two, roles=("views",)).calibrations
    assert sorted(cams) == ["camera", "camera_b"]
    cfg = default_config()
    run_up_to_align(one, tmp_path / "one", cfg, "one")
    run_up_to_align(two, tmp_path / "two", cfg, "two")
    a, b = _scores(one, tmp_path / "one"), _scores(two, tmp_path / "two")
    # each view keeps its own camera: 4 at 320 x 240, 4 at 160 x 120
    assert b["sizes"] == [("camera", 320, 240), ("camera_b", 160, 120)] and b["n_views"] == 8
    # measured: one camera: masks 0.996 (worst), hull IoU 0.980, aligned median
    # 0.095 mm; two cameras: camera's masks 0.998, camera_b's (a quarter of the pixels,
    # re-sampled) 0.983, hull 0.977, aligned 0.101 mm, no view flagged
    assert b["iou_camera"] >= 0.98 and b["iou_camera_b"] >= 0.97, b
    assert b["hull_iou"] >= a["hull_iou"] - 0.02, (a, b)
    assert b["aligned_median_mm"] <= 1.3 * a["aligned_median_mm"] + 0.01, (a, b)
    assert _flagged(tmp_path / "two") == []
    # the control: camera_b's link as camera's (what taking the other camera's hand-eye
    # would do). The carve's agreement check flags exactly camera_b's four views (each
    # misses 28-39 % of the others' hull) and the hull loses (0.928)
    bad = _two_camera_copy(one, tmp_path / "bad.mcap", own_hand_eye=False)
    run_up_to_align(bad, tmp_path / "bad", cfg, "bad")
    c = _scores(bad, tmp_path / "bad")
    assert _flagged(tmp_path / "bad") == [1, 3, 5, 7]
    assert c["hull_iou"] < b["hull_iou"] - 0.02, (b, c)
