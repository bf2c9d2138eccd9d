"""Calibration in the workflow (issue 13, items 1-3): the calibration file's round trip and
checks, the quality gates' verdicts and messages, a scan using a calibration instead of
its own, and the DAG: re-calibrating re-runs the scans that use that calibration, only
those."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from robo3d.calibration.gates import (
    board_scale_from_motion,
    check_gates,
    evaluate_gates,
    tilt_spread_deg,
)
from robo3d.calibration.io import (
    CalibrationFile,
    apply_calibration,
    read_calibration,
    write_calibration,
)
from robo3d.camera import CameraModel
from robo3d.config import default_config
from robo3d.errors import CalibrationError, ConfigError
from robo3d.recording import RecordingWriter
from robo3d.transforms import euler_to_matrix, invert_transform, make_transform

REPO = Path(__file__).resolve().parents[1]
W, H = 64, 48
K_REC = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])  # the recordings' placeholder


def _T(angles_deg, t) -> np.ndarray:
    return make_transform(euler_to_matrix("zyx", np.radians(angles_deg)), np.asarray(t, float))


X_REC = _T([0, 0, 0], [0, 0, 0.05])            # recorded (nominal) flange -> camera
L_REC = _T([0, 0, -30], [0.1, 0, 0])           # recorded camera -> laser


def _calibration_file(name="calA", K=None, X=None, L=None) -> CalibrationFile:
    K = np.array([[104.0, 0, 31.5], [0, 103.5, 24.5], [0, 0, 1]]) if K is None else K
    cam = CameraModel("camera", W, H, K, np.array([-0.1, 0.02, 0.001, -0.001, 0.0]))
    X = _T([1.0, -0.5, 0.3], [0.002, -0.001, 0.052]) if X is None else X
    L = _T([0.5, 0.2, -29.0], [0.098, 0.001, 0.002]) if L is None else L
    return CalibrationFile(
        name=name, camera=cam, T_flange_camera=X, T_camera_laser=L,
        laser_sheet={"normal": L[:3, 1].tolist(), "offset_m": float(L[:3, 1] @ L[:3, 3]),
                     "rms_mm": 0.1},
        quality={"rms_px": 0.12, "views_left_out": {3: "not found"}, "board_scatter_mm": 0.4},
        gates={"max_rms_px": {"value": 0.12, "limit": 0.5, "passed": True}},
        source={"recording": f"/data/{name}.mcap", "code": "test"})


def _write_recording(path: Path, kind: str, *, laser_parent: str = "camera",
                     n: int = 3) -> None:
    """A tiny recording (64x48 images): ``n`` views and laser frames, a robot moving the
    camera, the hand-eye and the laser on /tf_static."""
    cam = CameraModel("camera", W, H, K_REC)
    with RecordingWriter(path) as w:
        w.add_metadata("robo3d.recording", {"kind": kind, "object": "test", "units": "m"})
        if kind == "calibration":
            w.add_metadata("robo3d.target", {"type": "checkerboard", "cols": "5", "rows": "4",
                                             "square": "0.02"})
        w.write_calibration("/camera/calibration", 0, cam)
        L = L_REC if laser_parent == "camera" else X_REC @ L_REC
        w.write_transforms("/tf_static", 0, [("flange", "camera", X_REC),
                                             (laser_parent, "laser", L)])
        img = np.zeros((H, W), np.uint8)
        stripe = np.zeros((H, W, 3), np.uint8)  # a red laser line down the middle
        stripe[..., 0] = (220 * np.exp(-0.5 * ((np.arange(W) - 30.3) / 1.2) ** 2)).astype(np.uint8)
        for i in range(n):
            t = (i + 1) * 100_000_000
            w.write_transforms("/tf", t - 1_000_000, [("base", "flange",
                                                       _T([10 * i, 0, 0], [0.3, 0.01 * i, 0.4]))])
            w.write_transforms("/tf", t + 1_000_000, [("base", "flange",
                                                       _T([10 * i, 0, 0], [0.3, 0.01 * i, 0.4]))])
            w.write_image("/camera/image", t, "camera", img)
            w.write_image("/camera/laser_image", t + 500_000, "camera", stripe)


# ---------------------------------------------------------------------------- the file
def test_calibration_file_round_trip(tmp_path):
    calib = _calibration_file()
    path = tmp_path / "calibration" / "calA.yaml"
    write_calibration(path, calib)
    back = read_calibration(path)
    assert back.name == "calA" and back.path == str(path)
    np.testing.assert_array_equal(back.camera.K, calib.camera.K)  # bit-exact through YAML
    np.testing.assert_array_equal(back.camera.D, calib.camera.D)
    np.testing.assert_array_equal(back.T_flange_camera, calib.T_flange_camera)
    np.testing.assert_array_equal(back.T_camera_laser, calib.T_camera_laser)
    assert back.quality["views_left_out"] == {3: "not found"}
    assert back.gates["max_rms_px"]["passed"] is True
    assert back.laser_sheet["rms_mm"] == 0.1
    # a fixed rig: no hand-eye
    write_calibration(path, _calibration_file(X=None) if False else
                      CalibrationFile("rig", calib.camera, None, calib.T_camera_laser))
    assert read_calibration(path).T_flange_camera is None


@pytest.mark.parametrize("edit, key", [
    (lambda d: d.pop("T_camera_laser"), "T_camera_laser"),
    (lambda d: d["camera"].pop("K"), "camera.K"),
    (lambda d: d["camera"].__setitem__("width", -3), "camera.width"),
    (lambda d: d.__setitem__("T_flange_camera", [[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
     "T_flange_camera"),
    (lambda d: d["T_flange_camera"][0].__setitem__(0, 2.0), "T_flange_camera"),
    (lambda d: d["camera"]["D"].__setitem__(0, float("nan")), "camera.D"),
    (lambda d: d["laser_sheet"].__setitem__("normal", [0, 2, 0]), "laser_sheet.normal"),
])
def test_a_bad_calibration_file_names_the_file_and_the_key(tmp_path, edit, key):
    import yaml

    doc = _calibration_file().as_dict()
    edit(doc)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationError) as exc:
        read_calibration(path)
    assert str(path) in str(exc.value) and f"key {key}:" in str(exc.value)


def test_a_calibration_that_cannot_be_read_back_is_not_written(tmp_path):
    calib = _calibration_file()
    calib.laser_sheet["normal"] = [0.0, 3.0, 0.0]
    path = tmp_path / "calA.yaml"
    with pytest.raises(CalibrationError, match="laser_sheet.normal"):
        write_calibration(path, calib)
    assert list(tmp_path.iterdir()) == []  # neither the file nor a temporary


# ---------------------------------------------------------------------------- applying
def test_apply_calibration_replaces_camera_hand_eye_and_laser(tmp_path):
    from robo3d.stages.common import laser_poses, open_recording

    rec_path = tmp_path / "scan.mcap"
    _write_recording(rec_path, "scan")
    yaml_path = tmp_path / "calA.yaml"
    calib = _calibration_file()
    write_calibration(yaml_path, calib)
    cfg = default_config()
    own = open_recording(str(rec_path), cfg, roles=("views", "laser"))
    rec = open_recording(str(rec_path), cfg, roles=("views", "laser"),
                         calibration=str(yaml_path))
    v = rec.views[0]
    np.testing.assert_array_equal(own.camera_for(v).K, K_REC)
    np.testing.assert_array_equal(rec.camera_for(v).K, calib.camera.K)
    np.testing.assert_array_equal(rec.camera_for(v).D, calib.camera.D)
    T_bf = own.tf.lookup("base", "flange", v.timestamp_ns)
    np.testing.assert_allclose(own.camera_poses([v])[0], T_bf @ X_REC, atol=1e-12)
    np.testing.assert_allclose(rec.camera_poses([v])[0], T_bf @ calib.T_flange_camera,
                               atol=1e-12)
    np.testing.assert_allclose(laser_poses(rec, rec.laser_frames),
                               np.broadcast_to(calib.T_camera_laser, (3, 4, 4)), atol=1e-12)
    # replaced, not added: the same links, each static one a single sample
    assert sorted(own.tf.links()) == sorted(rec.tf.links())
    assert {(p, c): n for p, c, _, n in rec.tf.links()}[("flange", "camera")] == 1
    assert rec.metadata["robo3d.calibration"]["file"] == str(yaml_path)
    assert "flange->camera" in rec.metadata["robo3d.calibration"]["replaced"]
    # the recording read without it is unchanged
    np.testing.assert_allclose(own.camera_poses([v])[0], T_bf @ X_REC, atol=1e-12)


def test_apply_calibration_with_the_laser_on_the_flange(tmp_path):
    from robo3d.recording import read_recording

    rec_path = tmp_path / "scan.mcap"
    _write_recording(rec_path, "scan", laser_parent="flange")
    calib = _calibration_file()
    rec = apply_calibration(read_recording(rec_path), calib)
    # the chain flange -> laser now gives the calibrated camera -> laser
    np.testing.assert_allclose(rec.tf.lookup("camera", "laser", 0), calib.T_camera_laser,
                               atol=1e-12)
    assert ("flange", "laser") in {(p, c) for p, c, _, _ in rec.tf.links()}


def test_apply_calibration_describes_the_raw_images_of_a_rational_camera(tmp_path):
    """A rational_polynomial camera is rectified as it is read; a calibration from the
    calibrate stage, which estimates plumb_bob from the raw images, replaces it and its
    images are then read raw."""
    from dataclasses import replace

    from robo3d.camera import Rectifier
    from robo3d.recording import encode_image, read_recording

    rec_path = tmp_path / "scan.mcap"
    _write_recording(rec_path, "scan")
    rec = read_recording(rec_path)
    cam = rec.calibrations["camera"]
    rect = Rectifier("camera", cam.width, cam.height, cam.K,
                     np.r_[cam.D, 0.2, 0.0, 0.0])
    rec = replace(rec, calibrations={**rec.calibrations, "camera": rect.camera},
                  rectifiers={"camera": rect})
    noise = np.random.default_rng(0).integers(0, 256, (cam.height, cam.width), np.uint8)
    msg = replace(rec.views[0], data=encode_image(noise, "png"))
    np.testing.assert_array_equal(rec.decode_raw(msg), noise)
    np.testing.assert_array_equal(rec.decode(msg), rect(noise))
    assert not np.array_equal(rect(noise), noise)
    out = apply_calibration(rec, _calibration_file())
    assert out.rectifiers == {} and rec.rectifiers == {"camera": rect}
    np.testing.assert_array_equal(out.decode(msg), noise)


def test_apply_calibration_refuses_another_resolution(tmp_path):
    from robo3d.recording import read_recording

    rec_path = tmp_path / "scan.mcap"
    _write_recording(rec_path, "scan")
    calib = _calibration_file()
    calib.camera = CameraModel("camera", 2 * W, 2 * H, calib.camera.K)
    with pytest.raises(CalibrationError, match=r"128x96 images.*64x48"):
        apply_calibration(read_recording(rec_path), calib)


def test_the_stage_sees_the_calibration_and_metrics_name_it(tmp_path):
    """The stripes stage on a recording with a scan_calibration: the cameras, poses and
    laser poses of its output are the calibration's; the metrics say which file."""
    from robo3d.artefacts import Stripes
    from robo3d.stages.evaluate import _stage_metrics
    from robo3d.stages.stripes import stage_stripes

    rec_path = tmp_path / "scan.mcap"
    _write_recording(rec_path, "scan")
    yaml_path = tmp_path / "calA.yaml"
    calib = _calibration_file()
    write_calibration(yaml_path, calib)
    cfg = default_config()
    out = {k: str(tmp_path / f"s.{k}") for k in ("npz", "report", "rrd")}
    out["npz"] = str(tmp_path / "stripes.npz")
    stage_stripes({"recording": str(rec_path), "calibration": str(yaml_path)}, out, cfg,
                  "scan")
    s = Stripes.load(out["npz"])
    assert len(s.u) > 0 and len(s.cameras) == 3  # the stripe was found in the frames
    for cam in s.cameras:
        np.testing.assert_array_equal(cam.K, calib.camera.K)
        np.testing.assert_array_equal(cam.D, calib.camera.D)
    np.testing.assert_allclose(s.T_camera_laser, np.broadcast_to(calib.T_camera_laser,
                                                                 (3, 4, 4)), atol=1e-12)
    T_bf = np.stack([_T([10 * i, 0, 0], [0.3, 0.01 * i, 0.4]) for i in range(3)])
    np.testing.assert_allclose(s.T_base_camera, T_bf @ calib.T_flange_camera, atol=1e-9)
    m = _stage_metrics({"recording": str(rec_path), "calibration": str(yaml_path)},
                       tmp_path, cfg, "scan")
    assert m["calibration"]["file"] == str(yaml_path)
    assert m["calibration"]["recording"] == "/data/calA.mcap"


# ---------------------------------------------------------------------------- gates
def _result(n=12, square_scale=1.0, tilt=True, bad_view=None, seed=1):
    """A synthetic robot-cell calibration: consistent poses of a static board, the
    figures a good calibration has (0.12 px, board scatter 0.4 mm). ``square_scale``:
    the board's true size over the metadata's (the camera then sees it nearer by that
    factor); ``bad_view``: (index, rms_px, edge width factor)."""
    rng = np.random.default_rng(seed)
    X = _T([2, -1, 0.5], [0.01, -0.02, 0.08])
    T_bt = _T([180, 0, 0], [0.6, 0.0, 0.0])
    T_bf, T_ct = [], []
    for i in range(n):
        a = rng.uniform(-25, 25, 3) if tilt else np.zeros(3)
        T_bc = T_bt @ invert_transform(_T(a, [0.02 * i - 0.1, 0.01 * (i % 3), 0.5]))
        T_bf.append(T_bc @ invert_transform(X))
        T_ct.append(invert_transform(T_bc) @ T_bt)
    T_ct = np.array(T_ct)
    T_ct[:, :3, 3] /= square_scale
    per_view = np.full(n, 0.12)
    width = np.full(n, 2.0)
    if bad_view is not None:
        per_view[bad_view[0]] = bad_view[1]
        width[bad_view[0]] *= bad_view[2]
    return SimpleNamespace(
        camera=CameraModel("camera", W, H, K_REC), rms_px=float(np.sqrt(np.mean(per_view ** 2))),
        per_view_rms_px=per_view, views_used=np.arange(n), views_left_out={n: "not found"},
        T_camera_target=T_ct, view_stamps_ns=np.arange(n + 1) * 1_000_000_000,
        edge_width_px=np.append(width, np.nan), intrinsics_std={"fx": 0.05},
        T_base_flange=np.array(T_bf), T_flange_camera=X, handeye_rms_px=0.3,
        handeye_per_view_rms_px=np.full(n, 0.3),
        board_scatter_mm=0.4 if square_scale == 1 else 6.0,
        target=SimpleNamespace(square=0.02), T_camera_laser=L_REC, sheet_rms_mm=0.2,
        sheet_frames_used=np.arange(5), sheet_left_out={}, sheet_per_frame_rms_mm=np.full(5, .2))


GATES = default_config()["calibration_gates"]


def test_good_figures_pass_every_gate():
    gates = check_gates(_result(), GATES)
    assert all(g.passed for g in gates), [g.line() for g in gates if not g.passed]
    assert {g.name for g in gates} == set(GATES)


def test_the_defaults_pass_the_real_figures_of_opencv():
    """The issue's independent OpenCV runs: kuka_1 0.117 px with the board scattering by
    1.75 mm in base; srv 0.137 px with a 0.45 mm laser plane."""
    r = _result()
    r.rms_px, r.board_scatter_mm, r.sheet_rms_mm = 0.117, 1.75, 0.45
    assert all(g.passed is not False for g in evaluate_gates(r, GATES))
    r.rms_px, r.T_flange_camera, r.sheet_rms_mm = 0.137, None, 0.45  # the fixed rig
    gates = {g.name: g for g in evaluate_gates(r, GATES)}
    assert all(g.passed is not False for g in gates.values())
    assert gates["max_board_scatter_mm"].passed is None  # no hand-eye: does not apply


def test_board_scale_from_motion_recovers_a_wrong_square_size():
    for s in (1.0, 1.05, 0.8):
        r = _result(square_scale=s)
        est = board_scale_from_motion(r.T_base_flange, r.T_camera_target,
                                      r.T_flange_camera[:3, :3])
        assert est == pytest.approx(s, abs=1e-9)


def test_a_wrong_square_size_is_named_with_the_likely_size():
    with pytest.raises(CalibrationError) as exc:
        check_gates(_result(square_scale=1.05), GATES, where="/data/kuka.mcap")
    msg = str(exc.value)
    assert msg.startswith("/data/kuka.mcap: ")
    assert "gate max_board_scatter_mm: 6 mm, limit <= 3 mm (3 mm over it, 2.00 times" in msg
    assert "gate max_scale_error: 0.05" in msg
    assert "wrong square size" in msg and "target.square is likely 21.000 mm, not 20.000 mm" \
        in msg
    assert "max_rms_px" not in msg  # the intrinsics are fine


def test_a_blurred_view_is_named():
    with pytest.raises(CalibrationError) as exc:
        check_gates(_result(bad_view=(4, 2.5, 3.0)), GATES)
    msg = str(exc.value)
    assert "gate max_view_rms_px: 2.5 px, limit <= 1 px (1.5 px over it" in msg
    assert "view 4 (t=4.000000 s) reprojects at 2.5 px against a median of 0.12 px" in msg
    assert "it is blurred (board edges 6.00 px wide against a median of 2.00 px)" in msg


def test_too_few_tilted_views_are_named():
    r = _result(tilt=False)
    assert tilt_spread_deg(r.T_camera_target) == pytest.approx(0, abs=1e-6)
    with pytest.raises(CalibrationError) as exc:
        check_gates(r, GATES)
    msg = str(exc.value)
    assert "gate min_tilt_spread_deg: " in msg and "limit >= 15 deg" in msg
    assert "too few tilted views" in msg
    assert tilt_spread_deg(_result().T_camera_target) > 30


def test_too_few_views_and_sheet_frames_say_what_was_left_out():
    r = _result(n=5)
    r.views_left_out = {5: "not found", 6: "blurred: board edges 9.1 px wide > 8 px",
                        7: "not found"}
    r.sheet_frames_used, r.sheet_left_out = np.arange(2), {2: "too few points on the board"}
    with pytest.raises(CalibrationError) as exc:
        check_gates(r, GATES)
    msg = str(exc.value)
    assert "gate min_views: 5 views, limit >= 10 views" in msg
    assert ("5 of 8 views were used; left out: 2 not found (views 5, 7); 1 blurred (view 6: "
            "board edges 9.1 px wide > 8 px)") in msg
    assert "gate min_sheet_frames: 2 frames, limit >= 3" in msg
    assert "1 too few points on the board (frame 2)" in msg


# ---------------------------------------------------------------------------- the workflow
def test_calibration_recordings_are_apart_from_scans(tmp_path):
    from robo3d.pipeline import find_recordings, scan_calibrations, split_by_kind

    for n in ("calA", "calB"):
        _write_recording(tmp_path / f"{n}.mcap", "calibration")
    for n in ("s1", "s2"):
        _write_recording(tmp_path / f"{n}.mcap", "scan")
    scans, calibs = split_by_kind(find_recordings(str(tmp_path)))
    assert sorted(scans) == ["s1", "s2"] and sorted(calibs) == ["calA", "calB"]
    assert sorted(find_recordings(str(tmp_path), kind="calibration")) == ["calA", "calB"]
    assert scan_calibrations(None, scans, calibs) == {"s1": None, "s2": None}
    assert scan_calibrations("calB", scans, calibs) == {"s1": "calB", "s2": "calB"}
    assert scan_calibrations({"s2": "calA"}, scans, calibs) == {"s1": None, "s2": "calA"}
    with pytest.raises(ConfigError, match=r"scan_calibration\.s1: no calibration recording "
                       r"named 'calC'; calibration recordings: calA, calB"):
        scan_calibrations({"s1": "calC"}, scans, calibs)
    with pytest.raises(ConfigError, match=r"scan_calibration: 's9' is not a scan"):
        scan_calibrations({"s9": "calA"}, scans, calibs)
    with pytest.raises(ConfigError, match="no calibration recording named 'calA'; "
                       "calibration recordings: none"):
        scan_calibrations("calA", scans, {})
    _write_recording(tmp_path / "calibration.mcap", "scan")
    with pytest.raises(ConfigError, match="a scan named 'calibration'"):
        split_by_kind(find_recordings(str(tmp_path)))


def _summary(work: Path, cfg: Path) -> dict[str, tuple[str, str]]:
    """Snakemake's plan for every output file: ``file -> (rule, plan)``."""
    proc = subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
         str(work), "--cores", "1", "--configfile", str(cfg), "--summary"],
        capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [ln.split("\t") for ln in proc.stdout.splitlines() if "\t" in ln][1:]
    return {r[0]: (r[2], r[5]) for r in rows}


def test_re_calibrating_re_runs_the_scans_using_it_and_only_those(tmp_path):
    """Two calibrations, three scans: s1 uses calA, s2 calB, s3 its own. With every output
    up to date, a new calA.yaml plans s1's jobs (and the batch table), none of s2's or
    s3's, and no calibration job (were the outputs not up to date, s2 and s3 would be
    planned too)."""
    recs = tmp_path / "recs"
    recs.mkdir()
    for n in ("calA", "calB"):
        _write_recording(recs / f"{n}.mcap", "calibration")
    for n in ("s1", "s2", "s3"):
        _write_recording(recs / f"{n}.mcap", "scan")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"recordings: {recs}\nscan_calibration: {{s1: calA, s2: calB}}\n")
    plan = _summary(tmp_path, cfg)
    rules = {(f.split("/")[1], r) for f, (r, _) in plan.items() if "/" in f}
    assert ("calibration", "calibrate") in rules
    assert {r for f, r in rules if f == "s3"} >= {"silhouettes", "stripes", "evaluate"}
    assert not {f for f, _ in rules} & {"calA", "calB"}  # calibrations are not scanned
    # mark every output as made, in the order of the rules (none older than its inputs
    # or than the rules' scripts)
    order = ["calibrate", "stripes", "triangulate", "silhouettes", "carve", "align", "fuse",
             "simplify", "evaluate", "foxglove", "pictures", "batch_table"]
    t0 = time.time() + 10
    for r in recs.iterdir():
        os.utime(r, (t0 - 100, t0 - 100))
    for f, (rule, _) in plan.items():
        p = tmp_path / f
        p.parent.mkdir(parents=True, exist_ok=True)
        p.mkdir() if f.endswith("/masks") else p.touch()
        os.utime(p, (t0 + 10 * order.index(rule),) * 2)
    new = time.time() + 1000  # calA re-calibrated
    os.utime(tmp_path / "results" / "calibration" / "calA.yaml", (new, new))
    pending = {f for f, (_, pl) in _summary(tmp_path, cfg).items() if pl != "no update"}
    assert "results/s1/stripes.npz" in pending and "results/s1/silhouettes.npz" in pending
    assert "results/s1/mesh.ply" in pending and "results/s1/metrics.json" in pending
    assert {f.split("/")[1] for f in pending} == {"s1", "batch.tsv", "batch.html",
                                                 "overview.html"}


# ---------------------------------------------------------------------------- the rule
@pytest.fixture(scope="module")
def cell_recording(tmp_path_factory) -> Path:
    """The simulator's small robot-cell calibration recording (320 x 240, 12 views, a
    few laser frames; its published K is a placeholder, its mounts nominal)."""
    from robo3d.simulate import simulate_calibration

    path = tmp_path_factory.mktemp("calsim") / "recs" / "cell.mcap"
    path.parent.mkdir()
    simulate_calibration(path, rig="robot", small=True, seed=1)
    return path


def _snakemake(work: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
         str(work), "--cores", "1", *args], capture_output=True, text=True, timeout=600)


def test_the_calibrate_rule_writes_a_checked_calibration_or_fails_on_a_gate(cell_recording,
                                                                            tmp_path):
    import json

    from robo3d.transforms import rotation_angle_deg

    recs = cell_recording.parent
    out = tmp_path / "results" / "calibration"
    proc = _snakemake(tmp_path, "--config", f"recordings={recs}")  # rule all: every calibration
    assert proc.returncode == 0, proc.stderr[-3000:]
    calib = read_calibration(out / "cell.yaml")
    from robo3d.recording import read_recording

    truth = json.loads(read_recording(cell_recording, roles=()).attachments[
        "ground_truth/calibration.json"])
    K_true = np.array(truth["camera"]["K"]).reshape(3, 3)
    assert calib.camera.fx == pytest.approx(K_true[0, 0], rel=0.01)  # published: a placeholder
    E = invert_transform(np.array(truth["T_flange_camera"])) @ calib.T_flange_camera
    assert np.linalg.norm(E[:3, 3]) < 0.003 and rotation_angle_deg(E[:3, :3]) < 0.3
    n_true = np.array(truth["T_camera_laser"])[:3, 1]
    assert abs(calib.laser_sheet["normal"] @ n_true) > np.cos(np.radians(0.3))
    assert all(g["passed"] is not False for g in calib.gates.values())
    assert calib.gates["max_board_scatter_mm"]["passed"] is True
    report = json.loads((out / "cell_report.json").read_text())
    assert report["passed"] and len(report["views"]) == 12
    left = {v["index"]: v["left_out"] for v in report["views"] if not v["used"]}
    assert left and all(left.values())  # every view left out says why
    assert (out / "cell_detections.png").stat().st_size > 10_000
    # a gate it cannot pass: the rule fails, says which gate and why, leaves no yaml
    strict = tmp_path / "strict.yaml"
    strict.write_text("calibration_gates: {max_rms_px: 0.01}\n")
    proc = _snakemake(tmp_path, "--configfile", str(strict), "--config", f"recordings={recs}")
    assert proc.returncode != 0
    log = (tmp_path / "logs" / "calibrate" / "cell.log").read_text()
    assert "quality gate(s), max_rms_px" in log and "gate max_rms_px: " in log
    assert "limit <= 0.01 px" in log and "likely cause: " in log
    assert not (out / "cell.yaml").exists()
    failed = json.loads((out / "cell_report.failed.json").read_text())
    assert failed["passed"] is False and failed["gates"]["max_rms_px"]["passed"] is False


def test_robo3d_status_lists_calibrations_apart_from_scans(tmp_path):
    from robo3d.cli import main
    from robo3d.info import batch_status, format_batch_status

    res, logs = tmp_path / "results", tmp_path / "logs"
    write_calibration(res / "calibration" / "calA.yaml", _calibration_file())
    (logs / "calibrate").mkdir(parents=True)
    (logs / "calibrate" / "calB.log").write_text(
        "01:02:03 INFO robo3d.calibration.target: board found in 4 of 12 views\n"
        "01:02:09 ERROR robo3d.pipeline: calibrate failed for calB: /d/calB.mcap: calibration "
        "failed 1 quality gate(s), min_views (config calibration_gates):\n"
        "  gate min_views: 4 views, limit >= 10 views (6 views under it, 40% of the limit); "
        "likely cause: ...\n")
    (res / "s1" / "reports").mkdir(parents=True)
    (res / "s1" / "metrics.json").write_text("{}")
    st = batch_status(res, logs)
    assert set(st["recordings"]) == {"s1"}  # results/calibration/ is not a scan
    assert st["calibrations"]["calA"]["status"] == "done"
    assert st["calibrations"]["calB"]["status"] == "failed"
    assert "min_views" in st["calibrations"]["calB"]["error"]
    text = format_batch_status(st)
    assert "calibration calA: done" in text and "calibration calB: failed: " in text
    assert main(["status", "--results", str(res), "--logs", str(logs)]) == 1


def test_apply_calibration_through_a_fixed_mount_and_onto_a_fixed_rig():
    """A camera hanging from the flange through a fixed mount gets the calibrated
    hand-eye through the chain; a camera without a flange refuses a hand-eye."""
    from robo3d.recording.model import Recording
    from robo3d.transforms import TransformBuffer, matrix_to_quat

    def link(buf, parent, child, T, static=True, t=0):
        buf.add(parent, child, [t], T[:3, 3], matrix_to_quat(T[:3, :3]), static=static,
                topic="/tf_static" if static else "/tf")

    buf = TransformBuffer()
    link(buf, "base", "flange", _T([5, 0, 0], [0.3, 0, 0.4]), static=False)
    link(buf, "flange", "mount", _T([0, 90, 0], [0, 0, 0.02]))
    link(buf, "mount", "camera", _T([0, -90, 0], [0, 0, 0.03]))
    link(buf, "camera", "laser", L_REC)
    rec = Recording(path="cell.mcap", calibrations={"camera": CameraModel("camera", W, H,
                                                                          K_REC)}, tf=buf)
    calib = _calibration_file()
    out = apply_calibration(rec, calib)
    np.testing.assert_allclose(out.tf.lookup("flange", "camera", 0), calib.T_flange_camera,
                               atol=1e-12)
    np.testing.assert_allclose(out.tf.lookup("flange", "mount", 0),  # the mount is kept
                               buf.lookup("flange", "mount", 0), atol=1e-12)
    rig = TransformBuffer()
    link(rig, "base", "camera", _T([0, 0, 0], [0, 0, 0.5]))
    link(rig, "camera", "laser", L_REC)
    rec_rig = Recording(path="rig.mcap", calibrations=rec.calibrations, tf=rig)
    with pytest.raises(CalibrationError, match=r"rig.mcap: .*'camera' hangs from 'base', which "
                       r"is not fixed to 'flange'"):
        apply_calibration(rec_rig, calib)
    calib.T_flange_camera = None  # a fixed rig's calibration: intrinsics and laser only
    out = apply_calibration(rec_rig, calib)
    np.testing.assert_allclose(out.tf.lookup("camera", "laser", 0), calib.T_camera_laser,
                               atol=1e-12)
    np.testing.assert_allclose(out.tf.lookup("base", "camera", 0), rig.lookup("base", "camera", 0))


def test_a_wrong_square_size_is_found_from_the_robot_motion(cell_recording):
    """The simulator's session with its board metadata 5 % too large (and without a
    published calibration, which the calibration does not need): the intrinsics fit as
    well as ever, the gate on the board's scale fails and says the true square size."""
    import re

    from robo3d.calibration.calibrate import GateFailure, calibrate_recording
    from robo3d.recording import read_recording

    rec = read_recording(cell_recording, roles=("views", "laser"), require=False)
    rec.calibrations = {}
    square = float(rec.metadata["robo3d.target"]["square"])
    rec.metadata["robo3d.target"] = {**rec.metadata["robo3d.target"],
                                     "square": repr(square * 1.05)}
    with pytest.raises(GateFailure) as exc:
        calibrate_recording(rec, default_config())
    msg = str(exc.value)
    assert "quality gate(s), max_scale_error" in msg and "a wrong square size" in msg
    assert exc.value.result.rms_px < 0.2  # the intrinsics do not see it
    likely = float(re.search(r"target.square is likely ([0-9.]+) mm", msg).group(1))
    assert likely == pytest.approx(square * 1e3, rel=0.015)
