"""End-to-end: the Snakemake workflow on small simulated recordings, checked against the
ground truth the simulator attaches."""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import signal
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from robo3d.simulate import simulate_recording

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow

# Small but complete scans: every stage runs; a few seconds each to simulate.
SMALL = dict(width=480, height=360, views=12, sweeps=3, sweep_spacing=0.003)
#: A Snakemake run that takes longer than this (seconds) has hung.
TIMEOUT = 1800


def _command(workdir: Path, *args: str, quiet: bool = True, cores: int = 2) -> list[str]:
    return [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
            str(workdir), "--cores", str(cores), *(["--quiet", "all"] if quiet else []), *args]


def _check(proc: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    if proc.returncode != 0:
        raise AssertionError(f"snakemake failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n"
                             f"{proc.stderr[-6000:]}")
    return proc


def _snakemake(workdir: Path, *args: str, check: bool = True,
               quiet: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run(_command(workdir, *args, quiet=quiet), capture_output=True,
                          text=True, timeout=TIMEOUT)
    return _check(proc) if check else proc


def _stop(proc: subprocess.Popen) -> None:
    """End a Snakemake started in its own session, and its jobs."""
    os.killpg(proc.pid, signal.SIGTERM)
    proc.communicate()


#: The batch's recordings: (file, object, simulation options). The laser-only scan is
#: simulated first: the determinism check's separate run of it starts while the others
#: are still being simulated.
RECORDINGS = (
    ("laser_only.mcap", "sphere", dict(seed=5, width=480, height=360, views=0, sweeps=3,
                                       sweep_spacing=0.003)),
    ("block.mcap", "dimple_block", dict(seed=3, **SMALL)),
    ("views_only.mcap", "vase", dict(seed=4, width=480, height=360, views=12, sweeps=0)),
)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path]:
    """Two working directories: a batch of three recordings (a full scan, a views-only
    set, a laser-only scan) and, for the determinism check, a separate run of the same
    laser-only file with the same config on one core (the batch runs on two).

    The recordings are simulated in two processes, and the separate run is a second
    Snakemake started as soon as its file exists, concurrently with the batch: the two
    cores are kept busy instead of waiting for one run after the other (the runs share
    nothing but the source tree and numba's cache in it)."""
    work = tmp_path_factory.mktemp("workflow")
    again = tmp_path_factory.mktemp("workflow_again")
    recs, again_recs = work / "recs", again / "recs"
    recs.mkdir()
    again_recs.mkdir()
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        jobs = [pool.submit(simulate_recording, recs / name, obj, **kw)
                for name, obj, kw in RECORDINGS]
        jobs[0].result()
        shutil.copy(recs / "laser_only.mcap", again_recs / "laser_only.mcap")
        second = subprocess.Popen(_command(again, "--config", f"recordings={again_recs}",
                                           cores=1),
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                  start_new_session=True)
        try:
            for job in jobs[1:]:
                job.result()
        except BaseException:
            _stop(second)
            raise
    try:
        _snakemake(work, "--config", f"recordings={recs}")
        out, err = second.communicate(timeout=TIMEOUT)
    finally:
        if second.poll() is None:  # the batch failed: stop the other run too
            _stop(second)
    _check(subprocess.CompletedProcess(second.args, second.returncode, out, err))
    return work, again


@pytest.fixture(scope="module")
def batch(runs) -> Path:
    """The batch's working directory (recordings in ``recs/``, outputs in ``results/``)."""
    return runs[0]


def _metrics(work: Path, name: str) -> dict:
    with open(work / "results" / name / "metrics.json") as f:
        return json.load(f)


def test_full_scan_produces_every_output_accurately(batch):
    out = batch / "results" / "block"
    for f in ("hull.ply", "aligned.ply", "fused.ply", "mesh.ply", "metrics.json"):
        assert (out / f).stat().st_size > 0, f
    for stage in ("silhouettes", "carve", "stripes", "triangulate", "align", "fuse",
                  "simplify", "evaluate"):
        assert (out / f"{stage}.rrd").stat().st_size > 0, stage
    ev = _metrics(batch, "block")["evaluation"]
    # the visual hull of a concave object is bigger than the object, but not by much
    assert 0.75 < ev["hull_volume_iou"] <= 1.0
    # the final mesh against the true surface, a ~90 mm object
    assert ev["mesh"]["mean_mm"] < 0.5
    # (p95 is the hull-closed third of this 3-sweep scan's surface: 1.51-1.52 mm with the
    # colour segmentation and the ridge stripe detector, under 1.5 before them)
    assert ev["mesh"]["p95_mm"] < 1.6
    # three sweeps see only part of the block (tighten with issue 5's coverage work)
    assert ev["mesh"]["completeness"]["within_mm"]["1"] > 0.4
    # the laser points themselves are far more accurate than the hull
    assert ev["aligned"]["median_mm"] < 0.3
    # aligning the sweeps to each other brings the cloud closer to the truth
    assert ev["aligned"]["mean_mm"] < ev["clouds"]["mean_mm"]
    assert len(ev["poses"]["per_sweep"]) == 3
    # what it was computed with: the numeric packages' versions and the CPU
    import numpy

    env = _metrics(batch, "block")["environment"]
    assert env["packages"]["numpy"] == numpy.__version__ and env["packages"]["open3d"]
    assert env["cpu"] and env["python"].count(".") == 2
    # the points whose stripe centre was pulled off the stripe are counted, not hidden
    skew = _metrics(batch, "block")["stages"]["align"]["skewed_centres"]
    assert skew["max_skew_px"] == 2.0 and skew["dropped"] == sum(
        p["dropped"] for p in skew["per_sweep"])


def test_views_only_recording_gets_the_hull_as_its_mesh(batch):
    out = batch / "results" / "views_only"
    assert (out / "hull.ply").exists() and (out / "mesh.ply").exists()
    assert not (out / "aligned.ply").exists()
    m = _metrics(batch, "views_only")
    assert "laser" in m["skipped"]
    assert m["stages"]["fuse"]["source"] == "visual hull"
    assert m["evaluation"]["hull_volume_iou"] > 0.8
    # the hull's surface: exact where the silhouettes touch it, too big over concavities
    assert m["evaluation"]["mesh"]["median_mm"] < 0.6
    assert m["evaluation"]["mesh"]["completeness"]["within_mm"]["1"] > 0.7


def test_laser_only_recording_gets_everything_but_the_hull(batch):
    out = batch / "results" / "laser_only"
    assert not (out / "hull.ply").exists()
    assert (out / "aligned.ply").exists() and (out / "mesh.ply").exists()
    m = _metrics(batch, "laser_only")
    assert "hull" in m["skipped"]
    assert m["evaluation"]["mesh"]["median_mm"] < 0.3


def test_rerun_logs_share_one_recording_id(batch):
    from robo3d.viz import recording_id

    rid = recording_id("block").encode()
    for rrd in (batch / "results" / "block").glob("*.rrd"):
        assert rid in rrd.read_bytes(), rrd.name


def test_second_run_has_nothing_to_do(batch):
    proc = _snakemake(batch, "--config", f"recordings={batch / 'recs'}", "-n", quiet=False)
    assert "Nothing to be done" in proc.stdout + proc.stderr


def test_bad_config_fails_before_any_job(tmp_path):
    proc = _snakemake(tmp_path, "--config", "carving={resolution: fine}",
                      f"recordings={tmp_path}", check=False, quiet=False)
    assert proc.returncode != 0
    assert "carving.resolution" in proc.stdout + proc.stderr
    assert not (tmp_path / "results").exists()


def test_deterministic_outputs(runs):
    """Same recording and config give the same results, whatever the number of cores: a
    separate run on one core in its own working directory, concurrently with the batch on
    two (see the ``runs`` fixture).

    Every result file byte for byte, and metrics.json without its wall-clock and CPU
    times and the stripes stage's thread count (1 here, 2 in the batch). (Before Open3D
    was pinned to one thread, :func:`robo3d.stages.common.pin_open3d_threads`, the
    alignment differed between two processes by 1e-16 m and quadric decimation made
    another triangulation of it.)"""
    from robo3d.pipeline import without_run_details

    batch, again = runs
    assert (again / "recs" / "laser_only.mcap").read_bytes() == \
        (batch / "recs" / "laser_only.mcap").read_bytes()
    res_a, res_b = batch / "results" / "laser_only", again / "results" / "laser_only"
    compared = 0
    for f in ("stripes.npz", "clouds.npz", "aligned.npz", "aligned.ply", "fused.ply",
              "measured.ply", "mesh.ply", "mesh.stl", "results.mcap"):
        if (res_a / f).exists() or (res_b / f).exists():
            assert (res_a / f).read_bytes() == (res_b / f).read_bytes(), f
            compared += 1
    assert compared >= 8
    ma = without_run_details(_metrics(batch, "laser_only"))
    mb = without_run_details(_metrics(again, "laser_only"))
    assert ma["evaluation"]["mesh"]["median_mm"] > 0  # scored, not an empty comparison
    assert ma.pop("recording") != mb.pop("recording")  # the files' paths: two folders
    assert ma == mb


def test_measured_surface_is_labelled_and_scored_apart(batch):
    """measured.ply is the laser-measured surface; every vertex of fused.ply and mesh.ply
    says where it came from; metrics.json scores the measured surface apart."""
    from robo3d.fusion import HULL, MEASURED
    from robo3d.meshio import read_mesh, read_vertex_attributes

    out = batch / "results" / "block"
    Vm, Fm = read_mesh(out / "measured.ply")
    V, F = read_mesh(out / "mesh.ply")
    assert len(Fm) > 1000
    a = read_vertex_attributes(out / "mesh.ply")
    assert {"source", "confidence", "n_obs", "dist_measured_m", "far_from_measured",
            "flagged_sweep"} <= set(a)
    assert len(a["source"]) == len(V) and set(np.unique(a["source"])) <= {0, 1, 2}
    assert np.all(a["confidence"][a["source"] != MEASURED] == 0)
    assert (a["source"] == MEASURED).any() and (a["source"] == HULL).any()
    m = _metrics(batch, "block")
    # surface measured by a sweep the alignment flagged is labelled (none is here)
    flagged = [s["sweep"] for s in m["stages"]["align"]["per_sweep"] if s["flagged"]]
    assert m["stages"]["fuse"]["flagged_sweeps"] == flagged
    assert bool(a["flagged_sweep"].any()) == bool(flagged)
    assert not np.any(a["flagged_sweep"][a["source"] != MEASURED])
    src = m["surface_sources"]
    assert 0.1 < src["inferred_area_fraction"] < 0.9  # 3 sweeps see part of the block
    assert src["mesh"]["measured"] == pytest.approx(1 - src["inferred_area_fraction"])
    me = m["evaluation"]["measured"]
    # the measured surface is as accurate as the laser points, far better than the whole
    assert me["median_mm"] < 0.3 and me["p95_mm"] < m["evaluation"]["mesh"]["p95_mm"]
    assert me["outlier_area_fraction_0_5mm"] < 0.05
    # a views-only recording measured nothing: its mesh is all inferred
    v = _metrics(batch, "views_only")
    assert v["surface_sources"]["inferred_area_fraction"] == pytest.approx(1.0)
    assert len(read_mesh(batch / "results" / "views_only" / "measured.ply")[1]) == 0


def _planned(batch: Path, tmp_path: Path, change: str) -> set[str]:
    cfg = tmp_path / "change.yaml"
    cfg.write_text(change)
    proc = _snakemake(batch, "--configfile", str(cfg), "--config",
                      f"recordings={batch / 'recs'}", "-n", quiet=False)
    text = proc.stdout + proc.stderr
    if "Nothing to be done" in text:
        return set()
    table = text.split("Job stats:", 1)[1].split("total", 1)[0]
    return {ln.split()[0] for ln in table.splitlines()[3:] if ln.strip()}


@pytest.mark.parametrize("change, planned", [
    ("segmentation: {edge_refine_px: 2}",
     {"silhouettes", "carve", "align", "fuse", "simplify", "evaluate", "foxglove"}),
    ("carving: {resolution: 64}", {"carve", "fuse", "simplify", "evaluate", "foxglove"}),
    # the laser's points test the masks (segmentation.laser_reseed): new clouds, new masks
    ("stripes: {min_peak: 9.0}", {"stripes", "triangulate", "silhouettes", "carve", "align",
                                  "fuse", "simplify", "evaluate", "foxglove"}),
    ("alignment: {prior_mm: 0.4}", {"align", "fuse", "simplify", "evaluate", "foxglove"}),
    ("simplify: {target_faces: 15000}", {"simplify", "evaluate", "foxglove"}),
    ("evaluation: {n_samples: 100000}", {"evaluate"}),
    ("report: {tile_px: 200}", {"pictures", "batch_table"}),
    ("foxglove: {max_points: 5000}", {"foxglove"}),
])
def test_a_changed_parameter_re_runs_exactly_its_stages(batch, tmp_path, change, planned):
    """Each rule's params are the config sections its stage reads: a change plans that
    stage and what depends on its outputs (plus the batch table after a new evaluation),
    nothing else."""
    also = {"pictures", "batch_table"} if "evaluate" in planned else set()
    assert _planned(batch, tmp_path, change) == planned | also | {"all"}


def test_results_mcap_holds_each_recordings_clouds_and_meshes(batch):
    """results.mcap beside each recording's results, read by rerun's MCAP importer (not
    the writer's code; tests/foxglove_reader.py): in base, inside the recording's own
    time range, every point of clouds.npz and aligned.npz, mesh.ply's and hull.ply's
    triangles, and only what the recording has (no hull without views, no clouds
    without laser frames)."""
    from foxglove_reader import read_results
    from rerun.chunk import McapReader

    from robo3d.artefacts import load_clouds_npz
    from robo3d.meshio import read_mesh

    for name in ("block", "views_only", "laser_only"):
        out = batch / "results" / name
        res = read_results(out / "results.mcap")
        rec = McapReader(batch / "recs" / f"{name}.mcap").info()
        assert rec.message_start_time_ns <= res.start_ns <= res.end_ns <= \
            rec.message_end_time_ns, name
        assert {c.frame_id for c in res.clouds} <= {"base"}
        assert {m.frame_id for m in res.meshes} == {"base"}
        for key, topic in (("clouds", "/results/raw/"), ("aligned", "/results/aligned/sweep")):
            got = sum(len(c.positions) for c in res.clouds if c.topic.startswith(topic))
            want = sum(len(c) for c in load_clouds_npz(out / f"{key}.npz")) \
                if (out / f"{key}.npz").exists() else 0
            assert got == want, (name, key)
        meshes = {m.entity_id: m.n_triangles for m in res.meshes}
        assert meshes["mesh"] == len(read_mesh(out / "mesh.ply")[1])
        assert meshes.get("hull", 0) == (len(read_mesh(out / "hull.ply")[1])
                                         if (out / "hull.ply").exists() else 0)
        assert (name == "views_only") == (not res.clouds)


def test_report_opens_on_the_overview_with_every_stages_pictures(batch, tmp_path):
    """snakemake --report: the landing page holds the overview (each recording's status,
    key figures against their targets, a picture); each recording has its six pictures,
    and a stage the recording has no data for says so instead of drawing nothing."""
    import cv2

    proc = _snakemake(batch, "--config", f"recordings={batch / 'recs'}", "--report",
                      str(tmp_path / "report.html"))
    assert proc.returncode == 0
    page = (tmp_path / "report.html").read_text()
    assert "robo3d-overview" in page and "against their targets" in page
    for name in ("block", "views_only", "laser_only"):
        pics = batch / "results" / name / "pictures"
        shapes = {p.stem: cv2.imread(str(p)).shape for p in pics.glob("*.png")}
        assert set(shapes) == {"masks", "stripes", "hull", "clouds", "mesh", "timings",
                               "thumbnail"}, name
        assert all(s[1] <= 1400 for s in shapes.values()), shapes  # a few hundred px a tile
        assert f"<h2>{name}</h2>" in (batch / "results" / "overview.html").read_text()
    # a placeholder (one line of text, 60 px high) where the recording has no data
    assert cv2.imread(str(batch / "results/views_only/pictures/stripes.png")).shape[0] == 60
    assert cv2.imread(str(batch / "results/laser_only/pictures/masks.png")).shape[0] == 60
    assert cv2.imread(str(batch / "results/block/pictures/masks.png")).shape[0] > 200


def test_a_damaged_ground_truth_tf_costs_only_the_pose_figures(batch, tmp_path, monkeypatch):
    import robo3d.stages.evaluate as ev_stage
    from robo3d.config import default_config
    from robo3d.stages.common import open_recording

    out = batch / "results" / "block"
    rec_path = str(batch / "recs" / "block.mcap")
    cfg = default_config()

    def damaged(path, c, roles, require=True):
        rec = open_recording(path, c, roles, require)
        rec.attachments["ground_truth/tf.json"] = b'{"transforms": [{"parent": 3}]}'
        return rec

    monkeypatch.setattr(ev_stage, "open_recording", damaged)
    names = ("mesh.ply", "fused.ply", "measured.ply", "hull.npz", "silhouettes.npz",
             "clouds.npz", "aligned.npz")
    inputs = {"recording": rec_path, **{n.split(".")[0]: str(out / n) for n in names}}
    res = tmp_path / "results" / "block"
    shutil.copytree(out / "reports", res / "reports")
    outputs = {"metrics": str(res / "metrics.json"), "rrd": str(res / "evaluate.rrd")}
    m = ev_stage.stage_evaluate(inputs, outputs, cfg, "block")
    assert "tf.json" in m["skipped"]["poses"]
    assert "poses" not in m["evaluation"]
    assert m["evaluation"]["mesh"]["median_mm"] == pytest.approx(
        _metrics(batch, "block")["evaluation"]["mesh"]["median_mm"])
