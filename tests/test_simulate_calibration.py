"""Simulated calibration recordings (issue 13, item 4): they read as ``kind=calibration``
recordings, carry the truth in the contract's form, share the scan simulator's cell, and
their images are right: OpenCV's corners land on the true projection of the board and
the laser stripe on the true sheet-board line."""

import json

import cv2
import numpy as np
import pytest

from robo3d.camera import CameraModel
from robo3d.cli import main
from robo3d.recording.reader import read_ground_truth_tf, read_recording
from robo3d.sim.calibration import DEFECTS, Checkerboard, sheet_board_line
from robo3d.sim.rig import default_camera, default_hand_eye, default_laser_mount
from robo3d.simulate import SimulationParams, simulate_calibration, simulate_recording
from robo3d.transforms import invert_transform, rotation_angle_deg

CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    path = tmp_path_factory.mktemp("cal") / "robot.mcap"
    res = simulate_calibration(path, rig="robot", seed=4, small=True, views=6, laser_frames=3)
    return res, read_recording(path)


@pytest.fixture(scope="module")
def fixed(tmp_path_factory):
    path = tmp_path_factory.mktemp("cal") / "fixed.mcap"
    assert main(["simulate-calibration", str(path), "--rig", "fixed", "--small", "--seed", "5",
                 "--views", "3", "--laser-frames", "2", "--defects"]) == 0
    return read_recording(path)


def _truth(rec):
    return json.loads(rec.attachments["ground_truth/calibration.json"])


def _camera(truth):
    c = truth["camera"]
    return CameraModel(c["frame_id"], c["width"], c["height"], np.reshape(c["K"], (3, 3)),
                       np.array(c["D"]))


def _board(truth):
    t = truth["target"]
    return Checkerboard(t["cols"], t["rows"], t["square"], t["margin"])


def _rigid(t):
    t = np.asarray(t)
    return t.shape == (4, 4) and np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-9)


def _detect(image, board):
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    ok, corners = cv2.findChessboardCorners(grey, (board.cols, board.rows),
                                            cv2.CALIB_CB_ADAPTIVE_THRESH
                                            | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    return cv2.cornerSubPix(grey, corners, (4, 4), (-1, -1), CRITERIA).reshape(-1, 2)


def _true_corners(truth, view):
    t = np.asarray(truth["views"][view]["T_camera_target"])
    uv, front = _camera(truth).project(_board(truth).corners() @ t[:3, :3].T + t[:3, 3])
    assert front.all()
    return uv


def _corner_errors(found, true_uv):
    """Offsets found - true, in the detector's order or reversed (OpenCV may start the
    board at either end)."""
    a, b = found - true_uv, found[::-1] - true_uv
    return a if np.abs(a).mean() < np.abs(b).mean() else b


def test_robot_recording_reads_as_a_calibration(robot):
    res, rec = robot
    assert rec.metadata["robo3d.recording"]["kind"] == "calibration"
    target = rec.metadata["robo3d.target"]
    assert target == {"type": "checkerboard", "cols": "9", "rows": "6", "square": "0.015"}
    assert len(rec.views) == 6 + 3 and len(rec.laser_frames) == 3 == res.n_laser_frames
    assert sorted(res.defects.values()) == sorted(DEFECTS) and max(res.defects) < 6
    # the published calibration is a placeholder: rounded f, image centre, no distortion
    cam = rec.calibrations["camera"]
    assert cam.width == 320 and cam.height == 240
    assert cam.fx == cam.fy and cam.fx % 10 == 0 and not cam.has_distortion
    assert (cam.cx, cam.cy) == (159.5, 119.5)
    true = default_camera(320, 240)
    assert 0.015 <= abs(cam.fx / true.fx - 1) <= 0.06
    poses = rec.camera_poses(rec.views)  # every image has a pose through the robot
    assert len(poses) == len(rec.views)


def test_truth_is_in_the_contract_form_and_consistent(robot):
    _, rec = robot
    truth = _truth(rec)
    assert truth["camera"]["distortion_model"] == "plumb_bob"
    assert len(truth["camera"]["K"]) == 9 and len(truth["camera"]["D"]) == 5
    for key in ("T_flange_camera", "T_camera_laser", "T_base_target"):
        assert _rigid(truth[key]), key
    assert [v["timestamp_ns"] for v in truth["views"]] == [m.timestamp_ns for m in rec.views]
    assert [f["timestamp_ns"] for f in truth["laser_frames"]] == \
        [m.timestamp_ns for m in rec.laser_frames]
    # the board is static in base: T_camera_target = inv(T_base_camera_true) @ T_base_target,
    # with the true camera pose from ground_truth/tf.json alone
    gt = read_ground_truth_tf(rec)
    t_bt = np.asarray(truth["T_base_target"])
    for entry in truth["views"] + truth["laser_frames"]:
        t_bc = gt.lookup("base", "camera", entry["timestamp_ns"])
        np.testing.assert_allclose(invert_transform(t_bc) @ t_bt, entry["T_camera_target"],
                                   atol=1e-7)
    # the robot's reported poses carry a small error; the published mounts a larger one
    t = truth["views"][0]["timestamp_ns"]
    err = invert_transform(gt.lookup("base", "flange", t)) @ rec.tf.lookup("base", "flange", t)
    assert 0.005e-3 < np.linalg.norm(err[:3, 3]) < 0.05e-3
    for name, parent, child in (("T_flange_camera", "flange", "camera"),
                                ("T_camera_laser", "camera", "laser")):
        e = invert_transform(np.asarray(truth[name])) @ rec.tf.lookup(parent, child, t)
        assert 1.9e-3 <= np.linalg.norm(e[:3, 3]) <= 5.1e-3, name
        assert 0.95 <= rotation_angle_deg(e[:3, :3]) <= 3.05, name
        np.testing.assert_allclose(gt.lookup(parent, child, t), truth[name], atol=1e-8)


def test_calibration_and_scan_recordings_share_the_cell(robot, tmp_path):
    """The benchmark calibrates from one recording and scans with the other: the scan
    simulator's true camera, hand-eye and laser are the calibration's truth."""
    _, rec = robot
    truth = _truth(rec)
    p = SimulationParams.cell(small=True)
    np.testing.assert_allclose(np.reshape(truth["camera"]["K"], (3, 3)), default_camera(320, 240).K,
                               atol=1e-12)
    np.testing.assert_allclose(truth["T_flange_camera"], default_hand_eye(), atol=1e-12)
    np.testing.assert_allclose(truth["T_camera_laser"], default_laser_mount(p.baseline, p.crossing),
                               atol=1e-12)
    scan = tmp_path / "scan.mcap"
    simulate_recording(scan, "sphere", params=p, views=1, sweeps=1, sweep_frames=2,
                       width=320, height=240)
    srec = read_recording(scan)
    cam = srec.calibrations["camera"]
    np.testing.assert_allclose(cam.K.ravel(), truth["camera"]["K"])
    np.testing.assert_allclose(cam.D, truth["camera"]["D"])
    t = srec.views[0].timestamp_ns
    np.testing.assert_allclose(srec.tf.lookup("flange", "camera", t), truth["T_flange_camera"],
                               atol=1e-8)
    np.testing.assert_allclose(srec.tf.lookup("camera", "laser", t), truth["T_camera_laser"],
                               atol=1e-8)


def test_rendered_corners_are_the_true_projection(robot):
    """OpenCV's sub-pixel corners on the noisy JPEG views land on the board points
    projected through the true (distorted) camera: the renderer is right."""
    _, rec = robot
    truth = _truth(rec)
    board = _board(truth)
    errs = []
    for i, v in enumerate(truth["views"]):
        found = _detect(rec.decode(rec.views[i]), board)
        if v["defect"] == "out_of_frame":
            assert found is None
            continue
        if v["defect"] is not None:
            continue
        assert found is not None, f"view {i}: board not found"
        errs.append(_corner_errors(found, _true_corners(truth, i)))
    e = np.concatenate(errs)
    assert len(errs) >= 5
    rms = float(np.sqrt((e ** 2).sum(axis=1).mean()))
    assert rms < 0.1, rms
    assert np.abs(e.mean(axis=0)).max() < 0.03, e.mean(axis=0)  # no bias


def test_laser_stripe_lies_on_the_true_sheet_board_line(robot):
    """The stripe (laser frame minus its companion view, laser channel) peaks on the
    projection of the true sheet's line on the board."""
    _, rec = robot
    truth = _truth(rec)
    cam, board = _camera(truth), _board(truth)
    t_cl = np.asarray(truth["T_camera_laser"])
    offsets = []
    for k, lf in enumerate(truth["laser_frames"]):
        img = rec.decode(rec.laser_frames[k]).astype(float)
        sig = img[..., 0] - img[..., 1]  # the red laser over the grey board
        line = sheet_board_line(np.asarray(lf["T_camera_target"]), t_cl, board, n=1000)
        uv, _ = cam.project(line)
        uv = uv[np.argsort(uv[:, 0])]
        cols = np.arange(int(uv[0, 0]) + 3, int(uv[-1, 0]) - 3)
        v_true = np.interp(cols, uv[:, 0], uv[:, 1])
        rows = np.rint(v_true).astype(int)[:, None] + np.arange(-5, 6)[None, :]
        prof = sig[rows, cols[:, None]]
        strong = prof.max(axis=1) > 25  # the stripe on white squares
        peak = np.argmax(prof, axis=1)
        win = np.clip(peak[:, None] + np.arange(-2, 3)[None, :], 0, 10)
        wts = np.maximum(np.take_along_axis(prof, win, axis=1), 0)
        centre = rows[:, 0] + (win * wts).sum(axis=1) / np.maximum(wts.sum(axis=1), 1e-9)
        assert strong.sum() > 40, k
        offsets.append((centre - v_true)[strong])
    e = np.concatenate(offsets)
    assert abs(np.median(e)) < 0.1, np.median(e)
    assert np.median(np.abs(e)) < 0.3, np.median(np.abs(e))


def test_fixed_rig_has_a_moving_board_and_no_robot(fixed):
    rec = fixed
    truth = _truth(rec)
    assert rec.metadata["robo3d.target"]["moving"] == "true"
    assert "/tf" not in {t for t, s in rec.topics.items() if s.count}
    t = rec.views[0].timestamp_ns
    np.testing.assert_allclose(rec.tf.lookup("base", "camera", t), np.eye(4))
    assert truth["T_flange_camera"] is None and truth["T_base_target"] is None
    assert len(rec.views) == 3 + 2 and len(rec.laser_frames) == 2
    assert not any(v["defect"] for v in truth["views"])
    # the board moves: its poses differ
    poses = np.array([v["T_camera_target"] for v in truth["views"]])
    assert np.linalg.norm(poses[1:, :3, 3] - poses[:-1, :3, 3], axis=1).min() > 0.005
    gt = read_ground_truth_tf(rec)
    np.testing.assert_allclose(gt.lookup("camera", "laser", rec.laser_frames[0].timestamp_ns),
                               truth["T_camera_laser"], atol=1e-8)
    board = _board(truth)
    found = _detect(rec.decode(rec.views[0]), board)
    assert found is not None
    e = _corner_errors(found, _true_corners(truth, 0))
    assert np.sqrt((e ** 2).sum(axis=1).mean()) < 0.12


def test_bad_options_are_named(tmp_path):
    with pytest.raises(ValueError, match="rig"):
        simulate_calibration(tmp_path / "x.mcap", rig="turntable", small=True)
    with pytest.raises(ValueError, match="unknown calibration simulation option"):
        simulate_calibration(tmp_path / "x.mcap", small=True, view=3)
    assert main(["simulate-calibration", str(tmp_path / "y.mcap"), "--views", "-2"]) == 1
    assert not (tmp_path / "x.mcap").exists() and not (tmp_path / "y.mcap").exists()
