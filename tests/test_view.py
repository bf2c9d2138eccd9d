"""The rerun view (issue 14, item 4): the stages' logs read back with rerun's own reader
(entities, their counts, their timelines), the designed layout (blueprint) read back from
its ``.rbl`` file, ``rerun rrd verify`` on every file, and ``robo3d view --web`` serving the
web viewer on 127.0.0.1 and stopping when told.

One tiny simulated scan (a sphere: 4 views, 2 sweeps of 8 frames at 320 x 240) runs
through every stage's function once for the module; each test reads its logs.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stages_in_process import run_up_to_align, stage_outputs  # noqa: E402

STAGES = ("silhouettes", "carve", "stripes", "triangulate", "align", "fuse", "simplify",
          "evaluate")
N_VIEWS, N_SWEEPS, N_FRAMES = 4, 2, 8


@pytest.fixture(scope="module")
def scan(tmp_path_factory) -> Path:
    """``results/tiny/`` of a tiny simulated sphere scan, every stage run in process."""
    from robo3d.config import load_config
    from robo3d.pipeline import stage_evaluate, stage_fuse, stage_simplify
    from robo3d.simulate import simulate_recording

    work = tmp_path_factory.mktemp("view")
    rec = work / "tiny.mcap"
    simulate_recording(rec, "sphere", width=320, height=240, views=N_VIEWS,
                       view_elevations_deg=(40.0,), sweeps=N_SWEEPS, sweep_low_count=0,
                       sweep_frames=N_FRAMES, mesh_faces=4000)
    res = work / "results" / "tiny"
    cfg = load_config(overrides={"carving": {"resolution": 48, "qa_resolution": 24},
                                 "fusion": {"tsdf_voxel_m": 0.001},
                                 "simplify": {"target_faces": 2000}})

    def out(stage: str, **files: str) -> dict[str, str]:
        return stage_outputs(res, stage, **files)

    r = str(rec)
    run_up_to_align(rec, res, cfg, "tiny", threads=1)
    stage_fuse({"aligned": str(res / "aligned.npz"), "hull": str(res / "hull.npz")},
               out("fuse", ply="fused.ply", measured="measured.ply"), cfg, "tiny")
    stage_simplify({"fused": str(res / "fused.ply")}, out("simplify", ply="mesh.ply"), cfg,
                   "tiny")
    stage_evaluate({"recording": r, "mesh": str(res / "mesh.ply"),
                    "fused": str(res / "fused.ply"), "measured": str(res / "measured.ply"),
                    "hull": str(res / "hull.npz"), "silhouettes": str(res / "silhouettes.npz"),
                    "clouds": str(res / "clouds.npz"), "aligned": str(res / "aligned.npz")},
                   {"metrics": str(res / "metrics.json"), "rrd": str(res / "evaluate.rrd")},
                   cfg, "tiny")
    return res


# ---------------------------------------------------------------------------- helpers
def _rows(path: Path) -> dict[str, int]:
    from robo3d.view import entity_rows

    return dict(entity_rows(path))


def _column(path: Path, entity: str, column: str) -> list:
    """Every value of one component column of one entity, in logging order."""
    from rerun.chunk import RrdReader

    out: list = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path.lstrip("/") == entity:
            batch = chunk.to_record_batch()
            if column in batch.schema.names:
                out += batch.column(column).to_pylist()
    return out


def _timelines(path: Path) -> set[str]:
    from rerun.chunk import RrdReader

    return {t for chunk in RrdReader(path).stream() for t in chunk.timeline_names}


def _processes_naming(text: str) -> list[str]:
    """Command lines of running processes that contain ``text`` (Linux; [] elsewhere)."""
    found = []
    for f in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            line = f.read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if text in line:
            found.append(line)
    return found


def _rgb(packed: int) -> tuple[int, int, int]:
    """A rerun colour (0xRRGGBBAA) as RGB."""
    return (packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255


def _blueprint(path: Path) -> dict:
    """The views (class, name, origin), hidden entity paths and containers of a ``.rbl``
    file, read back with rerun's reader."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    (store,) = reader.blueprints()
    comps: dict[str, dict] = {}
    for chunk in reader.stream(store=store):
        batch = chunk.to_record_batch()
        entry = comps.setdefault(chunk.entity_path.lstrip("/"), {})
        for name in batch.schema.names:
            if ":" in name:
                entry[name] = batch.column(name).to_pylist()[-1]
    views = {e: (c["ViewBlueprint:class_identifier"], c["ViewBlueprint:display_name"],
                 c["ViewBlueprint:space_origin"])
             for e, c in comps.items() if "ViewBlueprint:class_identifier" in c}
    hidden = {m.group(1) for e, c in comps.items()
              if (m := re.search(r"/overrides/(.+)/visualizers$", e))
              and c.get("EntityBehavior:visible") == [False]}
    containers = {e: c for e, c in comps.items() if "ContainerBlueprint:container_kind" in c}
    return {"application_id": store.application_id, "views": views, "hidden": hidden,
            "containers": containers, "panels": comps}


# ---------------------------------------------------------------------------- the logs
def test_every_stage_logs_its_own_tree_with_the_expected_counts(scan):
    """Each stage's 3D results sit under ``base/<stage>/``; the current view and laser
    frame are one entity each, with one image per logged frame and its overlay; reports
    are short text; scalars along the timelines; no wall-clock timeline."""
    rows = {stage: _rows(scan / f"{stage}.rrd") for stage in STAGES}
    for stage, ents in rows.items():
        for e in ents:
            if e.startswith("base/"):
                assert e.startswith(f"base/{stage}/"), (stage, e)
        assert ents.get(f"reports/{stage}" if stage != "evaluate" else "reports/summary") == 1
    s = rows["silhouettes"]
    assert s["base/silhouettes/camera/image"] == N_VIEWS
    assert s["base/silhouettes/camera/mask"] == N_VIEWS
    assert s["base/silhouettes/workspace"] == 1
    c = rows["carve"]
    assert len([e for e in c if re.fullmatch(r"base/carve/cameras/view_\d{3}", e)]) == N_VIEWS
    assert c["base/carve/hull"] == 1 and c["base/carve/voxels"] == 1
    st = rows["stripes"]
    n_frames = N_SWEEPS * N_FRAMES
    assert st["metrics/stripes/points"] == n_frames  # one scalar per frame
    with_stripe = sum(v > 0 for v in (x[0] for x in _column(
        scan / "stripes.rrd", "metrics/stripes/points", "Scalars:scalars")))
    assert st["base/stripes/camera/image"] == st["base/stripes/camera/points"] == with_stripe
    t = rows["triangulate"]
    assert {e for e in t if e.startswith("base/")} == {
        f"base/triangulate/sweep_{k:02d}" for k in range(N_SWEEPS)}
    assert t["metrics/triangulate/sweep_points"] == N_SWEEPS
    a = rows["align"]
    assert all(a[f"base/align/sweep_{k:02d}"] == 1 for k in range(N_SWEEPS))
    assert rows["fuse"]["base/fuse/mesh"] == 1
    assert rows["simplify"]["base/simplify/mesh"] == 1
    ev = rows["evaluate"]
    assert ev["base/evaluate/ground_truth"] == 1 and ev["base/evaluate/mesh_error"] == 1
    assert ev["metrics/evaluate/pose_error_after_mm"] == N_SWEEPS
    assert _timelines(scan / "stripes.rrd") == {"time", "frame", "sweep"}
    assert _timelines(scan / "silhouettes.rrd") == {"time", "view"}
    for stage in STAGES:  # short text, not raw JSON
        name = "summary" if stage == "evaluate" else stage
        (text,) = _column(scan / f"{stage}.rrd", f"reports/{name}", "TextDocument:text")
        text = text[0] if isinstance(text, list) else text
        assert "```" not in text and text.startswith("### ") and len(text) < 4000, stage


def test_one_recording_id_for_every_stage(scan):
    from rerun.chunk import RrdReader

    ids = {(s.application_id, s.recording_id)
           for stage in STAGES for s in RrdReader(scan / f"{stage}.rrd").recordings()}
    assert len(ids) == 1 and next(iter(ids))[0] == "robo3d"


def test_clouds_and_meshes_carry_colours_that_mean_something(scan):
    """Clouds by sweep (the sweep palette), the fused and final meshes by provenance,
    the final mesh by its error against the ground truth (not one colour)."""
    from robo3d.fusion import SOURCE_RGB as _SOURCE_RGB
    from robo3d.stages.common import sweep_color

    for k in range(N_SWEEPS):
        for stage in ("triangulate", "align"):
            cols = _column(scan / f"{stage}.rrd", f"base/{stage}/sweep_{k:02d}",
                           "Points3D:colors")
            assert {_rgb(c) for batch in cols for c in batch} == {tuple(sweep_color(k))}
    palette = {tuple(int(v) for v in rgb) for rgb in _SOURCE_RGB}
    for stage, entity in (("fuse", "base/fuse/mesh"), ("simplify", "base/simplify/mesh")):
        (cols,) = _column(scan / f"{stage}.rrd", entity, "Mesh3D:vertex_colors")
        used = {_rgb(c) for c in cols}
        assert used <= palette and (170, 170, 170) not in used, stage
    (err,) = _column(scan / "evaluate.rrd", "base/evaluate/mesh_error", "Mesh3D:vertex_colors")
    assert len({_rgb(c) for c in err}) > 5  # a ramp, not one colour


def test_rrd_verify_passes_on_every_file(scan, tmp_path):
    from robo3d.view import logged_entities, save_blueprint, stage_logs

    rbl = save_blueprint(tmp_path / "view.rbl", logged_entities(stage_logs(scan)))
    rerun = Path(sys.executable).with_name("rerun")
    for path in [*sorted(scan.glob("*.rrd")), rbl]:
        proc = subprocess.run([str(rerun), "rrd", "verify", str(path)], capture_output=True,
                              text=True, timeout=60)
        assert proc.returncode == 0, (path.name, proc.stdout[-2000:], proc.stderr[-2000:])


# ---------------------------------------------------------------------------- the layout
def test_blueprint_lays_out_the_scan(scan, tmp_path):
    """``robo3d view --save-blueprint``: one large 3D view in ``base`` (two thirds of the
    width), the current view with its mask and the laser frame with its stripe, the
    summary as text and the scalars as a plot, no view of raw data that is not there,
    the clutter hidden, the recording's clock as the timeline."""
    from robo3d.cli import main
    from robo3d.view import HIDDEN_AT_FIRST

    rbl = tmp_path / "view.rbl"
    assert main(["view", "tiny", "--results", str(scan.parent), "--save-blueprint",
                 str(rbl)]) == 0
    bp = _blueprint(rbl)
    assert bp["application_id"] == "robo3d"
    flat = {tuple(x[0] for x in v) for v in bp["views"].values()}  # (class, name, origin)
    assert ("3D", "scan in base", "base") in flat
    assert ("2D", "view + mask", "base/silhouettes/camera") in flat
    assert ("2D", "laser frame + stripe", "base/stripes/camera") in flat
    assert ("TextDocument", "summary", "reports/summary") in flat
    assert ("TimeSeries", "per frame, per sweep", "metrics") in flat
    assert len([v for v in flat if v[0] == "3D"]) == 1
    assert {v[2] for v in flat if v[0] == "TextDocument"} <= {
        "reports/summary", *(f"reports/{s}" for s in STAGES)}
    # hidden at first: every cluttering subtree that was logged (no view was left out of
    # this carve), and the final mesh by provenance (the one coloured by its error shows)
    assert bp["hidden"] == (set(HIDDEN_AT_FIRST) - {"base/carve/left_out"}) | {
        "base/simplify/mesh"}
    shares = [c["ContainerBlueprint:col_shares"] for c in bp["containers"].values()
              if "ContainerBlueprint:col_shares" in c]
    assert shares == [[2.0, 1.0]]
    assert bp["panels"]["time_panel"]["TimePanelBlueprint:timeline"] == ["time"]
    assert bp["panels"]["viewport"]["ViewportBlueprint:auto_views"] == [False]


def test_blueprint_without_ground_truth_shows_the_mesh_by_provenance():
    from robo3d.view import scan_blueprint

    ents = {"base/simplify/mesh", "base/align/sweep_00", "reports/simplify"}
    bp = scan_blueprint(ents)
    assert bp is not None  # built for what is there: no 2D view, no summary
    from robo3d.view import _present

    assert not _present(ents, "base/evaluate/mesh_error")


# ---------------------------------------------------------------------------- the viewer
def test_rerun_environment_turns_analytics_off(tmp_path):
    """The installed rerun reads the private config we give it: analytics disabled."""
    import json

    from robo3d.view import rerun_environment

    env = rerun_environment(tmp_path / "cfg")
    rerun = Path(sys.executable).with_name("rerun")
    out = subprocess.run([str(rerun), "analytics", "config"], env=env, capture_output=True,
                         text=True, timeout=30, check=True).stdout
    assert json.loads(out)["analytics_enabled"] is False
    assert rerun_environment(tmp_path / "x", analytics=True).get("XDG_CONFIG_HOME") == \
        os.environ.get("XDG_CONFIG_HOME")


def test_view_without_display_asks_for_web(scan, monkeypatch):
    from robo3d.errors import Robo3dError
    from robo3d.view import view_recording

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(Robo3dError, match="--web"):
        view_recording(scan)


def test_view_web_serves_on_localhost_and_stops(scan):
    """``robo3d view --web`` on free ports: prints an address on 127.0.0.1 that answers
    over HTTP with rerun's web viewer under a policy that lets the page connect to this
    machine only, listens on no other interface, and stops (with rerun) on SIGTERM;
    bounded in time throughout."""
    import queue
    import threading

    cmd = [sys.executable, "-m", "robo3d.cli", "view", str(scan), "--web", "--web-port", "0",
           "--grpc-port", "0"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                            start_new_session=True)
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in proc.stdout], daemon=True).start()
    try:
        line = lines.get(timeout=60)
        m = re.search(r"(http://127\.0\.0\.1:(\d+)/?\?url=(\S+))", line)
        assert m, line
        assert "127.0.0.1" in m.group(3) and "localhost" not in m.group(3)
        with urllib.request.urlopen(f"http://127.0.0.1:{m.group(2)}/", timeout=20) as r:
            assert r.status == 200 and b"re_viewer" in r.read()
            # no usage data from the browser: the page may connect to this machine only
            grpc = re.search(r"127\.0\.0\.1%3A(\d+)", m.group(3)).group(1)
            assert (f"connect-src 'self' http://127.0.0.1:{grpc};"
                    in r.headers["Content-Security-Policy"])
        if Path("/proc/net/tcp").exists():  # listening sockets: 127.0.0.1 only
            listening = [ln.split()[1] for ln in Path("/proc/net/tcp").read_text().splitlines()[1:]
                         if ln.split()[3] == "0A"]
            port_hex = f"{int(m.group(2)):04X}"
            assert [a for a in listening if a.endswith(":" + port_hex)] == [
                f"0100007F:{port_hex}"]
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    time.sleep(1)  # rerun went with it: no process of this scan's logs left behind
    assert not _processes_naming(str(scan))
    t0 = time.monotonic()
    with pytest.raises(OSError):
        urllib.request.urlopen(f"http://127.0.0.1:{m.group(2)}/", timeout=5)
    assert time.monotonic() - t0 < 10
