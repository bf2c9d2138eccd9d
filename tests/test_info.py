"""``robo3d info`` (what a recording holds, whether each stage can use it) and
``robo3d status`` (what a batch made, why jobs failed), against recordings whose rates,
gaps, offsets and clock drift are known by construction."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_bad_input import FRAMES, TOPICS, VIEW_T, Bag, W, _image, _native

from robo3d.cli import main
from robo3d.info import batch_status, format_batch_status, format_info, inspect_recording

T0 = 1_700_000_000_000_000_000
JOINTS = ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint"]


def _with_joints(bag: Bag) -> Bag:
    for i in range(50):  # 50 Hz
        t = T0 + i * 20_000_000
        bag.messages.append((TOPICS.joint_states, "sensor_msgs/msg/JointState",
                             bag.T["sensor_msgs/msg/JointState"](
                                 header=bag.header(t, ""), name=JOINTS,
                                 position=np.array([0.1, 0.2, 0.3]) * i, velocity=np.zeros(0),
                                 effort=np.zeros(0)), t))
    bag.messages.sort(key=lambda m: m[3])
    return bag


def _info(path: Path, **kw):
    kw.setdefault("topics", TOPICS)
    kw.setdefault("frames", FRAMES)
    return inspect_recording(path, **kw)


def _cli(*args: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    rc = main(list(args))
    return rc, capsys.readouterr().out


ROS_ARGS = ["--topic", f"calibration={TOPICS.calibration}", "--topic", f"views={TOPICS.views}",
            "--topic", f"laser={TOPICS.laser}", "--topic",
            f"joint_states={TOPICS.joint_states}"] + [
    a for role, name in FRAMES.items() for a in ("--frame", f"{role}={name}")]


# =========================================================================== a good bag
@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _with_joints(Bag()).write(tmp_path_factory.mktemp("info") / "good.mcap")


def test_good_bag_is_described_and_fit(good: Path, capsys: pytest.CaptureFixture[str]) -> None:
    info = _info(good)
    assert info["fit"] and info["problems"] == [] and info["warnings"] == []
    topics = {r["topic"]: r for r in info["topics"]}
    assert topics["/tf"]["count"] == 101 and topics["/tf"]["schema"] == "tf2_msgs/msg/TFMessage"
    assert topics["/tf"]["rate_hz"] == pytest.approx(100.0)
    assert topics[TOPICS.views]["role"] == "views" and topics[TOPICS.views]["count"] == 4
    assert topics[TOPICS.joint_states]["rate_hz"] == pytest.approx(50.0)
    assert info["time"]["duration_s"] == pytest.approx(1.0)
    # the tree, with the recorded names beside the roles
    fr = info["frames"]
    assert fr["renamed"] == FRAMES and fr["roots"] == ["base"] and fr["roles_missing"] == []
    assert fr["tree_text"].splitlines()[0] == "base (base_link)"
    assert "└─ flange (tool0)  [101 samples, 100 Hz]" in fr["tree_text"]
    assert "camera (camera_optical)  [static]" in fr["tree_text"]
    # calibration: a 32 px wide image at fx = 30 px
    (cal,) = info["calibrations"]
    assert (cal["width"], cal["height"], cal["fx"], cal["images"]) == (32, 24, 30.0, 10)
    assert cal["hfov_deg"] == pytest.approx(np.degrees(2 * np.arctan(W / 60)))
    # 100 Hz exactly: no jitter, no gap
    (ps,) = info["pose_stream"]
    assert ps["link"] == "base -> flange" and ps["rate_hz"] == pytest.approx(100.0)
    assert ps["jitter_ms"] == pytest.approx(0.0, abs=1e-9)
    assert ps["max_gap_ms"] == pytest.approx(10.0) and ps["gaps_over_max_pose_gap"] == 0
    # views fall on /tf samples (multiples of 10 ms), laser frames 5 ms from one
    assert info["pairing"]["views"]["worst_offset_ms"] == pytest.approx(0.0)
    lp = info["pairing"]["laser"]
    assert lp["worst_offset_ms"] == pytest.approx(5.0) and lp["without_pose"] == 0
    assert lp["widest_bracket_ms"] == pytest.approx(10.0)
    assert info["sweeps"] == {"count": 1, "frames": [6]}
    assert info["joint_states"]["names"] == JOINTS and info["joint_states"]["count"] == 50
    assert all(r["offset_median_ms"] == 0 and r["drift_ppm"] == 0 for r in info["clock"])
    assert all(v["status"] == "ok" for v in info["stages"].values())
    assert "no ground truth" in info["stages"]["evaluate"]["reasons"][0]
    # the command line: text, exit 0; JSON, the same dict
    rc, out = _cli("info", str(good), *ROS_ARGS, capsys=capsys)
    assert rc == 0 and out.rstrip().endswith("fit for the pipeline")
    assert "transform tree (recorded names in brackets)" in out and "base (base_link)" in out
    # a bag has no workspace box: where the pipeline takes one from
    assert info["workspace"]["box"] is None
    assert "alignment takes the visual hull's box" in info["workspace"]["source"]
    assert "  workspace none in the recording: the alignment takes" in format_info(info)
    rc, out = _cli("info", str(good), *ROS_ARGS, "--json", capsys=capsys)
    assert rc == 0 and json.loads(out)["pairing"]["laser"]["worst_offset_ms"] == 5.0
    assert format_info(info) in _cli("info", str(good), *ROS_ARGS, capsys=capsys)[1]


def test_jitter_gaps_and_images_without_pose(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """Every other /tf sample 1 ms late (periods of 11 and 9 ms in turn: 1 ms jitter), and
    a 100 ms drop-out around the third view."""
    bag = Bag()
    out = []
    for topic, msgtype, msg, t in bag.messages:
        if topic == "/tf":
            k = (t - T0) // 10_000_000
            if abs(t - VIEW_T[2]) < 50_000_000:
                continue
            if k % 2:
                t2 = t + 1_000_000
                tr = msg.transforms[0]
                tr.header.stamp.nanosec = t2 % 10**9
                t = t2
        out.append((topic, msgtype, msg, t))
    bag.messages = out
    p = bag.write(tmp_path / "gap.mcap")
    info = _info(p)
    (ps,) = info["pose_stream"]
    assert ps["jitter_ms"] == pytest.approx(1.0, rel=1e-6)
    assert ps["period_median_ms"] == pytest.approx(11.0)  # 45 x 9 ms, 45 x 11 ms, 1 x 100 ms
    assert ps["gaps_over_max_pose_gap"] == 1
    assert ps["max_gap_ms"] == pytest.approx(100.0) and ps["max_gap_at_ns"] == T0 + 451_000_000
    vp = info["pairing"]["views"]
    assert vp["without_pose"] == 1 and vp["first_without_pose_ns"] == VIEW_T[2]
    assert vp["worst_offset_ms"] == pytest.approx(50.0, abs=1.01)
    assert not info["fit"]
    st = info["stages"]
    assert st["silhouettes"]["status"] == "unfit" and st["carve"]["status"] == "unfit"
    assert "more than max_pose_gap 50.0 ms" in st["silhouettes"]["reasons"][0]
    assert st["stripes"]["status"] == "ok"
    assert st["fuse"]["status"] == "unfit" and "the hull" in st["fuse"]["reasons"][0]
    rc, out = _cli("info", str(p), *ROS_ARGS, capsys=capsys)
    assert rc == 1 and "NOT fit for the pipeline" in out and "silhouettes, carve: unfit" in out
    # a wider max_pose_gap interpolates across the drop-out: fit again
    assert _info(p, max_pose_gap_ns=150_000_000)["fit"]


def test_camera_clock_offset_and_drift(tmp_path: Path) -> None:
    """Image stamps from a camera clock 300 ms ahead that gains 200 ppm on the
    recorder's: both measured, and the mismatch with /tf flagged."""
    bag = Bag()
    for k, (topic, msgtype, msg, t) in enumerate(bag.messages):
        if topic in (TOPICS.views, TOPICS.laser):
            s = t + 300_000_000 + round((t - T0) * 200e-6)
            msg.header.stamp.sec, msg.header.stamp.nanosec = s // 10**9, s % 10**9
            bag.messages[k] = (topic, msgtype, msg, t)
    p = bag.write(tmp_path / "clock.mcap")
    info = _info(p)
    clock = {c["topic"]: c for c in info["clock"]}
    for topic in (TOPICS.views, TOPICS.laser):
        assert clock[topic]["drift_ppm"] == pytest.approx(200.0, rel=1e-3)
        assert clock[topic]["offset_median_ms"] == pytest.approx(300.1, abs=0.1)
    assert clock["/tf"]["drift_ppm"] == 0 and clock["/tf"]["offset_median_ms"] == 0
    assert any(w.startswith(f"{TOPICS.views}: stamps are +300") and "stamp_source: log_time"
               in w for w in info["warnings"])
    assert not info["fit"]  # the laser frames fall after the end of /tf
    # the receive time brings them back
    assert _info(p, stamp_source="log_time")["fit"]


def test_views_only_and_no_laser_frame(tmp_path: Path) -> None:
    p = _native(tmp_path / "v.mcap", views=[_image(0)[:48 // 2, :32] for _ in range(1)])
    info = inspect_recording(p)
    st = info["stages"]
    assert st["stripes"]["status"] == "not applicable"
    assert st["silhouettes"]["status"] == "unfit"  # one view cannot carve
    assert any("2 views at least" in r for r in st["carve"]["reasons"])
    assert any("is 32x24 pixels but its calibration" in r for r in st["carve"]["reasons"])
    # laser frames whose laser frame is not mapped: named, with the config key
    bag = Bag()
    bag.messages[1] = ("/tf_static", "tf2_msgs/msg/TFMessage", bag.tf_msg(
        T0, [("tool0", "camera_optical", np.eye(4)), ("tool0", "line_laser", np.eye(4))]), T0)
    info = _info(bag.write(tmp_path / "l.mcap"))
    reasons = info["stages"]["stripes"]["reasons"]
    assert info["stages"]["silhouettes"]["status"] == "ok"
    assert any("frame 'laser' is not in the transform tree" in r and "frames.laser" in r
               for r in reasons)


def test_unreadable_and_truncated(good: Path, tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "x.mcap"
    p.write_bytes(b"not a recording")
    info = inspect_recording(p)
    assert not info["fit"] and "not an MCAP file" in info["problems"][0]
    assert {v["status"] for v in info["stages"].values()} == {"unfit"}
    rc, out = _cli("info", str(p), capsys=capsys)
    assert rc == 1 and "silhouettes, carve, stripes, triangulate, align, fuse, simplify, " \
                       "evaluate: unfit" in out
    rc, out = _cli("info", str(tmp_path / "missing.mcap"), capsys=capsys)
    assert rc == 1 and "no such file or directory" in out
    # a rosbag2 directory cut short: metadata.yaml's counts against what is intact
    d = tmp_path / "bag"
    d.mkdir()
    meta = {"rosbag2_bagfile_information": {
        "version": 9, "storage_identifier": "mcap", "relative_file_paths": ["bag_0.mcap"],
        "topics_with_message_count": [
            {"topic_metadata": {"name": "/tf", "type": "tf2_msgs/msg/TFMessage",
                                "serialization_format": "cdr"}, "message_count": 101}]}}
    (d / "metadata.yaml").write_text(yaml.safe_dump(meta))
    from test_bad_input import rechunk

    full = rechunk(good, tmp_path / "chunks.mcap").read_bytes()
    (d / "bag_0.mcap").write_bytes(full[: int(len(full) * 0.6)])
    info = _info(d)
    n_tf = next(r["count"] for r in info["topics"] if r["topic"] == "/tf")
    assert 0 < n_tf < 101
    assert any("truncated or damaged at byte" in w for w in info["warnings"])
    assert f"/tf: metadata.yaml counts 101 messages, {n_tf} are intact ({101 - n_tf} lost)" \
        in info["warnings"]


# =========================================================================== batch status
def _fake_batch(root: Path) -> tuple[Path, Path]:
    results, logs = root / "results", root / "logs"
    from robo3d.info import STAGE_MARKERS, STAGES

    for stage in STAGES:  # "good": every stage done
        (results / "good" / STAGE_MARKERS[stage]).parent.mkdir(parents=True, exist_ok=True)
        (results / "good" / STAGE_MARKERS[stage]).write_text("{}")
        (logs / stage).mkdir(parents=True, exist_ok=True)
        (logs / stage / "good.log").write_text("12:00:00 INFO robo3d.pipeline: done\n")
    (results / "good" / "mesh.ply").write_text("ply")
    # "bad": silhouettes failed with robo3d's one-line error, stripes crashed (a bug)
    (logs / "silhouettes" / "bad.log").write_text(
        "12:00:01 INFO robo3d.recording: reading\n12:00:02 ERROR robo3d.pipeline: silhouettes "
        "failed for bad: bad.mcap: not an MCAP file\n")
    (logs / "stripes" / "bad.log").write_text(
        "Traceback (most recent call last):\n  File \"x.py\", line 1\nKeyError: 'u'\n")
    # "cut": carve killed mid-run (its log has no error, its report is missing)
    (results / "cut" / "reports").mkdir(parents=True)
    (results / "cut" / "reports" / "silhouettes.json").write_text("{}")
    (results / "cut" / ".hull.abc.tmp.npz").write_text("")  # a killed job's temporary
    (logs / "silhouettes" / "cut.log").write_text("12:00:00 INFO ok\n")
    (logs / "carve" / "cut.log").write_text("12:00:00 INFO carving\n")
    return results, logs


def test_batch_status(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    results, logs = _fake_batch(tmp_path)
    s = batch_status(results, logs, recordings=["good", "bad", "cut", "never"])
    recs = s["recordings"]
    assert s["done"] == ["good"] and s["failed"] == ["bad"]
    assert recs["good"]["status"] == "done"
    assert recs["good"]["outputs"] == ["mesh.ply", "metrics.json"]
    bad = recs["bad"]["stages"]
    assert bad["silhouettes"] == {"status": "failed", "log": str(logs / "silhouettes/bad.log"),
                                  "error": "robo3d.pipeline: silhouettes failed for bad: "
                                           "bad.mcap: not an MCAP file"}
    assert bad["stripes"]["status"] == "failed" and bad["stripes"]["error"] == "KeyError: 'u'"
    assert bad["carve"]["status"] == "not run"
    assert recs["cut"]["status"] == "incomplete" and recs["cut"]["outputs"] == []
    assert recs["cut"]["stages"]["carve"]["status"] == "incomplete"
    assert recs["never"]["status"] == "not started"
    text = format_batch_status(s)
    assert text.splitlines()[0] == "4 recordings: 1 done, 1 failed, 2 other"
    assert "  silhouettes failed: robo3d.pipeline: silhouettes failed for bad: bad.mcap: not " \
           "an MCAP file" in text
    assert "  carve incomplete:" in text
    # every name found when none are given; the command line's exit status
    assert set(batch_status(results, logs)["recordings"]) == {"good", "bad", "cut"}
    rc, out = _cli("status", "--results", str(results), "--logs", str(logs), capsys=capsys)
    assert rc == 1 and "bad: failed" in out
    shutil.rmtree(logs / "silhouettes")
    shutil.rmtree(logs / "stripes")
    rc, out = _cli("status", "--results", str(results), "--logs", str(logs), "--json",
                   capsys=capsys)
    assert rc == 0 and json.loads(out)["failed"] == []


def test_pairing_with_a_single_static_pose(tmp_path: Path) -> None:
    """A rig without a robot: base -> camera once on /tf_static. Every image has a pose
    (offset 0), however far in time."""
    p = _native(tmp_path / "rig.mcap", views=[_image(i) for i in range(3)],
                laser=[_image(5)])
    info = inspect_recording(p)
    assert info["pose_stream"] == []
    assert info["pairing"]["views"]["worst_offset_ms"] == 0.0
    assert info["pairing"]["views"]["without_pose"] == 0
    assert info["pairing"]["laser"]["images"] == 1


def test_run_summary_table_reads_the_metrics(tmp_path):
    import json

    from robo3d.info import format_run_summary

    res = tmp_path / "results" / "part"
    (res / "reports").mkdir(parents=True)
    metrics = {"stages": {"simplify": {"faces_out": 20000}},
               "surface_sources": {"inferred_area_fraction": 0.25},
               "evaluation": {"mesh": {"median_mm": 0.0123, "p95_mm": 0.0711},
                              "measured": {"median_mm": 0.011, "p95_mm": 0.049}},
               "timings": {"total_seconds": 61.2}}
    (res / "metrics.json").write_text(json.dumps(metrics))
    text = format_run_summary(tmp_path / "results", tmp_path / "logs")
    row = next(ln for ln in text.splitlines() if ln.startswith("part"))
    for want in ("20000", "75.0 %", "0.012 / 0.071 mm", "0.011 / 0.049 mm", "61 s"):
        assert want in row, (want, row)
    assert "results in" in text


def test_workspace_box_of_a_recording_and_of_a_laser_only_bag(tmp_path: Path) -> None:
    """Where the pipeline's workspace box comes from: the recording's metadata (a
    simulated scan has one), or, for a bag of laser frames alone, nowhere (every laser
    point is kept)."""
    from robo3d.simulate import simulate_recording

    sim = tmp_path / "sphere.mcap"
    simulate_recording(sim, "sphere", seed=1, width=160, height=120, views=4, sweeps=1,
                       sweep_frames=4)
    ws = inspect_recording(sim)["workspace"]
    assert ws["source"] == "the recording's metadata" and len(ws["box"]) == 2
    bag = Bag()
    bag.messages = [m for m in bag.messages if m[0] != TOPICS.views]
    info = _info(bag.write(tmp_path / "laser_only.mcap"))
    assert info["workspace"]["box"] is None
    assert "no views to take one from" in info["workspace"]["source"]
