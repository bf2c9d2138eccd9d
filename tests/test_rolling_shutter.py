"""A rolling shutter: a laser frame's rows exposed one after the other while the robot
moves. The simulator renders it (``SimulationParams.rolling_shutter_ms``); the
triangulation takes one camera pose per frame unless ``timing.rolling_shutter_s`` gives
the readout time, and then each point takes the pose of its row.

Without motion the banded rendering is the global shutter's frame; with it the stripe's
points land off the object by up to the distance the camera moved during the readout,
and back on it with the readout time in the config."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stages_in_process import laser_point_distances_mm  # noqa: E402


def test_without_motion_the_bands_make_the_global_shutter_frame():
    from robo3d.camera import CameraModel
    from robo3d.sim.render import Appearance, SimScene, render_laser_frame
    from robo3d.simulate import _rolling_signal, object_mesh
    from robo3d.transforms import make_transform

    cam = CameraModel("camera", 320, 240, np.array([[450.0, 0, 160], [0, 450, 120], [0, 0, 1]]),
                      np.array([-0.1, 0.05, 0, 0, 0]))
    T = make_transform(np.diag([1.0, -1.0, -1.0]), [0.0, 0.0, 0.35])
    a = np.radians(15)  # the laser 9 cm beside the camera, its sheet across the view
    Ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    Rz = np.array([[0, -1.0, 0], [1, 0, 0], [0, 0, 1]])
    T_cl = make_transform(Rz @ Ry, [-0.09, 0, 0])
    scene = SimScene(object_mesh("blob"), Appearance.cell(laser="green"))
    full = render_laser_frame(scene, cam, T, T @ T_cl)
    assert full.max() > 200  # the stripe is in the frame
    bands = _rolling_signal(scene, cam, T, T_cl, 0.03, np.zeros(3))
    np.testing.assert_allclose(bands, full, atol=1e-9)
    moved = _rolling_signal(scene, cam, T, T_cl, 0.03, np.array([0.02, 0.0, 0.0]))
    assert np.abs(moved - full)[:8].max() < np.abs(moved - full)[-8:].max()  # later rows


def _distances_mm(rec_path: Path, out: Path, readout_s: float = 0.0) -> np.ndarray:
    """The stripes and triangulation stages (default config but ``timing.
    rolling_shutter_s``, exact poses): each point's distance to the true surface, mm."""
    from robo3d.config import load_config

    cfg = load_config(None, {"timing": {"rolling_shutter_s": readout_s}})
    return laser_point_distances_mm(rec_path, out, cfg, 5001)


@pytest.mark.parametrize("readout_ms", [30.0])
def test_a_rolling_shutter_puts_the_stripe_where_the_camera_was_later(tmp_path, readout_ms):
    from robo3d.simulate import SimulationParams, simulate_recording

    base = dataclasses.replace(SimulationParams.small(), views=0, sweeps=2, seed=3,
                               sweep_error_mm=(0.0, 0.0), sweep_error_deg=(0.0, 0.0))
    d = {}
    for ms in (0.0, readout_ms):
        path = tmp_path / f"rs{ms:g}.mcap"
        simulate_recording(path, "dimple_block",
                           params=dataclasses.replace(base, rolling_shutter_ms=ms))
        d[ms] = _distances_mm(path, tmp_path / f"out{ms:g}")
    glob, roll = d[0.0], d[readout_ms]
    fixed = _distances_mm(tmp_path / f"rs{readout_ms:g}.mcap", tmp_path / "fixed",
                          readout_ms * 1e-3)
    # measured (320 x 240, 20 mm/s: the camera moves 0.6 mm during the readout): median
    # 0.104 -> 0.144 mm, p95 0.316 -> 0.420 mm; with the readout in the config 0.1045 mm,
    # p95 0.3167 mm
    assert np.median(roll) > 1.2 * np.median(glob), (np.median(glob), np.median(roll))
    assert np.percentile(roll, 95) > 1.15 * np.percentile(glob, 95)
    move_mm = base.sweep_speed * readout_ms  # mm: m/s x ms
    assert np.median(roll) < np.median(glob) + move_mm
    assert np.median(fixed) < 1.05 * np.median(glob), (np.median(glob), np.median(fixed))
    assert np.percentile(fixed, 95) < 1.05 * np.percentile(glob, 95)


def test_rows_poses_between_the_first_and_the_last_row():
    from robo3d.transforms import make_transform
    from robo3d.triangulation import rows_poses

    a = np.radians(0.3)  # the camera turns 0.3 degrees about z and moves 0.6 mm in x
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    T0 = make_transform(np.eye(3), [0.1, 0.0, 0.3])[None]
    T1 = make_transform(Rz, [0.1006, 0.0, 0.3])[None]
    R, o = rows_poses(T0, T1, np.zeros(4, int), np.array([0.0, 0.5, 1.0, 1.5]))
    np.testing.assert_allclose(R[0], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(R[2], Rz, atol=1e-15)
    np.testing.assert_allclose(R[3], Rz, atol=1e-15)  # clipped to the last row
    h = a / 2
    np.testing.assert_allclose(R[1], [[np.cos(h), -np.sin(h), 0], [np.sin(h), np.cos(h), 0],
                                      [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(o[:, 0], [0.1, 0.1003, 0.1006, 0.1006], atol=1e-15)
    R, o = rows_poses(T0, T0, np.zeros(2, int), np.array([0.2, 0.9]))  # no motion
    np.testing.assert_allclose(R, np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-15)


def _tf_cut(src: Path, dst: Path, end_ns: int) -> Path:
    """``src`` without its ``/tf`` messages after ``end_ns`` (a pose stream that ends just
    after the last laser frame)."""
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from mcap_copy import copy_recording

    def keep(topic: str, data: bytes) -> bool:
        return topic != "/tf" or FrameTransforms.FromString(
            data).transforms[0].timestamp.ToNanoseconds() <= end_ns

    return copy_recording(src, dst, keep=keep, attachments=False)


def test_the_last_rows_pose_where_the_pose_stream_ends_first(tmp_path):
    """A pose stream that ends 20 ms after the last laser frame cannot give that frame's
    last-row pose 30 ms on: the motion of the 30 ms before the stamp is carried on, and
    counted. The sweep moves in a straight line at constant speed, so the carried-on pose
    is the one the whole stream gives."""
    import json

    from stages_in_process import stage_outputs

    from robo3d.artefacts import Stripes
    from robo3d.config import load_config
    from robo3d.pipeline import STAGES
    from robo3d.recording.reader import read_recording
    from robo3d.simulate import SimulationParams, simulate_recording

    rec = tmp_path / "one.mcap"
    simulate_recording(rec, "blob", seed=4, params=SimulationParams.small(
        views=0, sweeps=1, sweep_frames=12))
    last = max(m.timestamp_ns for m in read_recording(rec, roles=("laser",)).laser_frames)
    cut = _tf_cut(rec, tmp_path / "cut.mcap", last + 20_000_000)
    cfg = load_config(None, {"timing": {"rolling_shutter_s": 0.03}})
    ends, reps = [], []
    for r in (rec, cut):
        out = tmp_path / r.stem
        (out / "reports").mkdir(parents=True)
        s = stage_outputs(out, "stripes", npz="stripes.npz")
        STAGES["stripes"]({"recording": str(r)}, s, cfg, r.stem, threads=1)
        ends.append(Stripes.load(s["npz"]).T_base_camera_end)
        reps.append(json.loads(Path(s["report"]).read_text())["rolling_shutter"])
    assert reps[0] == {"readout_s": 0.03, "frames_end_pose_extrapolated": 0}
    assert reps[1]["frames_end_pose_extrapolated"] >= 1
    np.testing.assert_allclose(ends[1], ends[0], atol=1e-7)  # 0.1 um
