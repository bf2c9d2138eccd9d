"""End-to-end: the Snakemake workflow on small simulated recordings, checked against the
ground truth the simulator attaches."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from robo3d.simulate import simulate_recording

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow

# Small but complete scans: every stage runs; a few seconds each to simulate.
SMALL = dict(width=480, height=360, views=12, sweeps=3, sweep_spacing=0.003)


def _snakemake(workdir: Path, *args: str, check: bool = True,
               quiet: bool = True) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
           str(workdir), "--cores", "2", *(["--quiet", "all"] if quiet else []), *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n"
                             f"{proc.stderr[-6000:]}")
    return proc


@pytest.fixture(scope="module")
def batch(tmp_path_factory) -> Path:
    """A batch of three recordings: a full scan, a views-only set, a laser-only scan."""
    work = tmp_path_factory.mktemp("workflow")
    recs = work / "recs"
    recs.mkdir()
    simulate_recording(recs / "block.mcap", "dimple_block", seed=3, **SMALL)
    simulate_recording(recs / "views_only.mcap", "vase", seed=4, width=480, height=360,
                       views=12, sweeps=0)
    simulate_recording(recs / "laser_only.mcap", "sphere", seed=5, width=480, height=360,
                       views=0, sweeps=3, sweep_spacing=0.003)
    _snakemake(work, "--config", f"recordings={recs}")
    return work


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


def test_deterministic_outputs(batch, tmp_path):
    """Same recording and config give the same mesh."""
    recs = tmp_path / "recs"
    recs.mkdir()
    shutil.copy(batch / "recs" / "laser_only.mcap", recs / "laser_only.mcap")
    _snakemake(tmp_path, "--config", f"recordings={recs}")
    a = (batch / "results" / "laser_only" / "mesh.ply").read_bytes()
    b = (tmp_path / "results" / "laser_only" / "mesh.ply").read_bytes()
    assert a == b
    ma = _metrics(batch, "laser_only")["evaluation"]["mesh"]
    mb = _metrics(tmp_path, "laser_only")["evaluation"]["mesh"]
    assert np.isclose(ma["mean_mm"], mb["mean_mm"])
