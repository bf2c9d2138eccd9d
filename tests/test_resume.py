"""Nothing lost: a job killed mid-write leaves no output that looks complete, Snakemake
resumes after Ctrl-C or a crash and redoes only what is missing, and one bad recording
in a batch fails its own jobs (said by ``robo3d status``) while the others finish.

The workflow runs for real (Snakemake, one job per stage) on a tiny views-only scan and a
file that is not a recording. Jobs are interrupted at a chosen point by a
``sitecustomize`` hook put on the jobs' ``PYTHONPATH``: it wraps ``os.replace`` (the
atomic rename every robo3d writer ends with) in the ``carve`` job, and when the job is
about to publish ``hull.ply`` (after ``hull.npz``) it either waits to be interrupted or
kills itself with SIGKILL.
"""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from robo3d.info import batch_status, format_batch_status

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow

#: What the batch documentation asks for: finish every other recording when one fails,
#: redo jobs that an interruption left incomplete.
BATCH_FLAGS = ("--keep-going", "--rerun-incomplete")

HOOK = '''
import os, signal, sys, time
_mode = os.environ.get("ROBO3D_TEST_HOOK", "")
if _mode and any(a.endswith(".carve.py") for a in sys.argv):
    _real = os.replace
    def _replace(src, dst, *a, **k):
        if str(dst).endswith("hull.ply"):
            open(os.environ["ROBO3D_TEST_MARK"], "w").close()
            if _mode == "kill":
                os.kill(os.getpid(), signal.SIGKILL)
            time.sleep(120)
        return _real(src, dst, *a, **k)
    os.replace = _replace
'''


def _snakemake(work: Path, *args: str, hook: str = "", interrupt: bool = False,
               ) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(work / "hook"), ROBO3D_TEST_HOOK=hook,
               ROBO3D_TEST_MARK=str(work / "mark"))
    (work / "mark").unlink(missing_ok=True)
    # the rule blocks are parsed below: the default profile keeps them off the terminal
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
           str(work), "--cores", "2", "--configfile", str(work / "config.yaml"),
           "--quiet", "host", *args]
    # Ctrl-C must reach the jobs even when the tests themselves were started in the
    # background (a non-interactive shell starts `cmd &` with SIGINT ignored, and the
    # children inherit that): the workflow gets the default disposition
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    if interrupt:  # Ctrl-C in the terminal: SIGINT to the whole process group
        t0 = time.monotonic()
        while not (work / "mark").exists() and proc.poll() is None:
            assert time.monotonic() - t0 < 300, "the carve job never reached hull.ply"
            time.sleep(0.05)
        assert (work / "mark").exists(), "snakemake ended before the carve job was interrupted"
        os.killpg(proc.pid, signal.SIGINT)
    out, _ = proc.communicate(timeout=600)
    return subprocess.CompletedProcess(cmd, proc.returncode, out, "")


def _planned(work: Path, *args: str) -> set[tuple[str, str]]:
    """(rule, recording) of every job a dry run would run."""
    out = _snakemake(work, "-n", *args).stdout
    jobs, rule = set(), None
    for line in out.splitlines():
        m = re.match(r"^\s*(?:local)?rule (\w+):", line)  # indented inside a group job
        if m:
            rule = m.group(1)
        m = re.search(r"wildcards: rec=(\S+)", line)
        if m and rule:
            jobs.add((rule, m.group(1)))
    return jobs


def _all_whole(results: Path) -> list[str]:
    """Every visible file under results/ opens completely; returns their names."""
    names = []
    for p in sorted(results.rglob("*")):
        if not p.is_file() or any(part.startswith(".") for part in p.relative_to(results).parts):
            continue
        if p.suffix == ".npz":
            with np.load(p) as z:
                for k in z.files:
                    z[k]
        elif p.suffix == ".json":
            json.loads(p.read_text())
        elif p.suffix == ".ply":
            from robo3d.meshio import read_mesh

            read_mesh(p)
        names.append(str(p.relative_to(results)))
    return names


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from robo3d.simulate import simulate_recording

    w = tmp_path_factory.mktemp("resume")
    (w / "recs").mkdir()
    simulate_recording(w / "recs" / "good.mcap", "sphere", seed=2, width=160, height=120,
                       views=8, sweeps=0)
    (w / "recs" / "bad.mcap").write_bytes(b"this was a recording until the disk filled\n")
    (w / "config.yaml").write_text(f"recordings: {w / 'recs'}\ncarving: {{resolution: 32}}\n"
                                   "evaluation: {n_samples: 2000}\n")
    (w / "hook").mkdir()
    (w / "hook" / "sitecustomize.py").write_text(HOOK)
    return w


def test_interrupt_crash_resume_and_a_bad_recording(work: Path) -> None:
    res = work / "results"
    good = res / "good"
    # ---- 1. Ctrl-C while carve publishes its outputs (hull.npz done, hull.ply not yet)
    proc = _snakemake(work, *BATCH_FLAGS, hook="wait", interrupt=True)
    assert proc.returncode != 0
    assert "carve for good interrupted" in (work / "logs/carve/good.log").read_text()
    assert not (good / "hull.ply").exists() and not (good / "reports/carve.json").exists()
    assert not list(good.glob(".hull.*"))  # the interrupted writer removed its temporary
    whole = _all_whole(res)  # whatever is there is whole ...
    assert "good/silhouettes.npz" in whole
    # ... and a file of the interrupted job is not taken as done: the plain command (the
    # workflow profile sets --rerun-incomplete) plans the interrupted job again
    out = _snakemake(work, "-n").stdout
    assert "rule carve:" in out
    sil_mtime = (good / "silhouettes.npz").stat().st_mtime_ns
    # a resume redoes only what is missing: not the silhouettes
    plan = _planned(work, *BATCH_FLAGS)
    good_jobs = {r for r, rec in plan if rec == "good"}
    assert good_jobs == {"carve", "fuse", "simplify", "evaluate", "foxglove",
                         "pictures"}, plan

    # ---- 2. the resumed carve job is killed (SIGKILL) as it publishes hull.ply
    proc = _snakemake(work, *BATCH_FLAGS, hook="kill")
    assert proc.returncode != 0 and "SIGKILL" in proc.stdout
    assert not (good / "hull.ply").exists() and not (good / "hull.npz").exists()
    stale = list(good.glob(".hull.*.tmp.ply"))
    assert len(stale) == 1  # the killed job's temporary: hidden, never an output's name
    _all_whole(res)
    assert (good / "silhouettes.npz").stat().st_mtime_ns == sil_mtime
    st = batch_status(res, work / "logs")
    assert st["recordings"]["good"]["stages"]["carve"]["status"] == "incomplete"

    # ---- 3. resume: the good recording finishes, the bad one fails its own jobs
    proc = _snakemake(work, *BATCH_FLAGS)
    assert proc.returncode != 0  # the batch has a failure ...
    for f in ("hull.ply", "fused.ply", "mesh.ply", "metrics.json"):  # ... the rest finished
        assert (good / f).stat().st_size > 0, f
    assert (good / "silhouettes.npz").stat().st_mtime_ns == sil_mtime  # not redone
    assert not list(good.glob(".hull.*"))  # the stale temporary was cleaned up
    metrics = json.loads((good / "metrics.json").read_text())
    assert metrics["evaluation"]["hull_volume_iou"] > 0.5
    assert not (res / "bad" / "mesh.ply").exists()
    # ---- the report says so
    st = batch_status(res, work / "logs", recordings=["good", "bad"])
    assert st["done"] == ["good"] and st["failed"] == ["bad"]
    bad = st["recordings"]["bad"]["stages"]
    for stage in ("silhouettes", "stripes"):
        assert bad[stage]["status"] == "failed"
        assert "not an MCAP file" in bad[stage]["error"], bad[stage]
    assert bad["carve"]["status"] == "not run" and bad["evaluate"]["status"] == "not run"
    text = format_batch_status(st)
    assert "bad: failed" in text and "silhouettes failed: " in text and "good: done" in text
    cli = subprocess.run([sys.executable, "-m", "robo3d.cli", "status", "--results", str(res),
                          "--logs", str(work / "logs")], capture_output=True, text=True)
    assert cli.returncode == 1 and "not an MCAP file" in cli.stdout
    # ---- so does the batch table (results/batch.csv, written at the end of every run):
    # the good recording's figures, the bad one's failure with its first error line
    with open(res / "batch.csv", newline="") as f:
        rows = {r["recording"]: r for r in csv.DictReader(f)}
    assert rows["good"]["status"] == "done" and float(rows["good"]["hull_iou"]) > 0.5
    assert float(rows["good"]["carve_s"]) > 0 and not rows["good"]["error"]
    assert rows["bad"]["status"] == "failed" and rows["bad"]["failed_stage"] == "silhouettes"
    assert "not an MCAP file" in rows["bad"]["error"] and not rows["bad"]["hull_iou"]
    # ---- and so does the report (snakemake --report after the failed run): the good
    # recording's pictures, the bad one in the overview and batch.html with its failure
    proc = _snakemake(work, "--report", str(work / "report.html"))
    assert proc.returncode == 0, proc.stdout[-4000:]
    page = (work / "report.html").read_text()
    overview = (res / "overview.html").read_text()
    for text in (overview, page):
        assert "failed in the silhouettes stage" in text and "not an MCAP file" in text
    assert "<h2>good</h2>" in overview and "<h2>bad</h2>" in overview
    assert "1 failed, " in overview and "logs/silhouettes/bad.log" in overview
    assert "failed in the silhouettes stage" in (res / "batch.html").read_text()
    assert "good/pictures/mesh.png" in page or "mesh.png" in page
    # ---- and nothing is left to do for the good recording
    assert {rec for _, rec in _planned(work, *BATCH_FLAGS)} == {"bad"}
