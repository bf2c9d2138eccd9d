"""Batch throughput: N small simulated recordings through the workflow on 1 core and on 2.

The recordings are issue 14's small scans (320 x 240, 8 views, 3 sweeps of 40 frames),
objects taken in turn from the simulator's set, each with its own seed; they are
simulated once into ``<work>/recs`` (kept with ``--keep``, reused when present). The
workflow then runs with the default config and the workflow profile (``profiles/default``)
twice, each in its own folder: ``--cores 1`` and ``--cores 2``. The machine is shared, so
the 1-minute load average is sampled every 5 s during each run and reported beside it.

Figures: wall time, throughput (recordings per minute), parallel efficiency
(``T1 / (2 * T2)``), the sum of the jobs' wall times (their ``benchmark:`` files) against
the run's wall time, and per stage the mean job time, CPU time and peak resident memory.

Scheduler: Snakemake's ILP and greedy schedulers timed on a DAG shaped like the workflow's
(``--scheduler-recordings`` x 8 stages with the rules' dependencies, threads and mem_mb, each
job a ``touch``; 125 recordings = 1,000 jobs) with ``--cores 2``: what the profiles'
``scheduler:`` choice rests on.

Writes ``benchmarks/results/batch.json``.

    .venv/bin/python benchmarks/batch.py [--n 20] [--keep DIR] [--cores 1 2]
                                         [--scheduler-recordings 125 | 0 to skip]
"""

from __future__ import annotations

import argparse
import csv
import json
import multiprocessing
import os
import shutil
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, run_workflow  # noqa: E402

#: issue 14's small recordings
SMALL = dict(width=320, height=240, views=8, sweeps=3, sweep_frames=40)
OBJECTS = ("dimple_block", "vase", "blob", "bracket", "cup")
STAGES = ("silhouettes", "carve", "stripes", "triangulate", "align", "fuse", "simplify",
          "evaluate")


def simulate(recs: Path, n: int) -> list[Path]:
    """The batch's recordings (simulated when missing, two at a time)."""
    from robo3d.simulate import simulate_recording

    recs.mkdir(parents=True, exist_ok=True)
    paths = [recs / f"r{i:02d}_{OBJECTS[i % len(OBJECTS)]}.mcap" for i in range(n)]
    todo = [(i, p) for i, p in enumerate(paths) if not p.exists()]
    if todo:
        print(f"simulating {len(todo)} recordings into {recs} ...", flush=True)
        with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
            for f in [pool.submit(simulate_recording, p, OBJECTS[i % len(OBJECTS)],
                                  seed=100 + i, **SMALL) for i, p in todo]:
                f.result()
    return paths


class LoadSampler(threading.Thread):
    """The 1-minute load average every ``period`` seconds while a run lasts."""

    def __init__(self, period: float = 5.0):
        super().__init__(daemon=True)
        self.period, self.samples, self._done = period, [], threading.Event()

    def run(self) -> None:
        while not self._done.is_set():
            self.samples.append(os.getloadavg()[0])
            self._done.wait(self.period)

    def stop(self) -> dict[str, float]:
        self._done.set()
        self.join()
        s = self.samples or [os.getloadavg()[0]]
        return {"mean": round(sum(s) / len(s), 2), "max": round(max(s), 2)}


def job_times(work: Path) -> dict[str, dict[str, float]]:
    """Per stage, over the recordings: mean wall s, mean CPU s, max peak RSS (MB) of its
    jobs (Snakemake's ``benchmark:`` files), and the jobs' total wall time."""
    out: dict[str, dict[str, float]] = {}
    for stage in STAGES:
        rows = []
        for f in sorted((work / "benchmarks" / stage).glob("*.tsv")):
            with open(f) as fh:
                rows += list(csv.DictReader(fh, delimiter="\t"))
        if not rows:
            continue

        def num(r: dict, k: str) -> float:
            try:
                return float(r[k])
            except (KeyError, ValueError):
                return float("nan")

        s = [num(r, "s") for r in rows]
        out[stage] = {"jobs": len(rows), "mean_s": round(sum(s) / len(s), 2),
                      "total_s": round(sum(s), 1),
                      "mean_cpu_s": round(sum(num(r, "cpu_time") for r in rows) / len(rows), 2),
                      "max_rss_mb": round(max(num(r, "max_rss") for r in rows), 0)}
    return out


def measure(paths: list[Path], root: Path, cores: int) -> dict[str, Any]:
    """One workflow run of the batch on ``cores`` cores, in ``root/cores<N>``."""
    work = root / f"cores{cores}"
    shutil.rmtree(work, ignore_errors=True)  # a run kept by --keep would be resumed, not timed
    work.mkdir(parents=True)
    print(f"run on {cores} core(s) in {work} (load {os.getloadavg()[0]:.2f}) ...", flush=True)
    load = LoadSampler()
    load.start()
    wall = run_workflow(paths, work, cores=cores)
    loadavg = load.stop()
    stages = job_times(work)
    jobs_s = sum(v["total_s"] for v in stages.values())
    n = len(paths)
    r = {"wall_s": round(wall, 1), "recordings_per_min": round(60 * n / wall, 3),
         "job_time_s": round(jobs_s, 1), "job_time_per_recording_s": round(jobs_s / n, 1),
         "busy_fraction": round(jobs_s / (cores * wall), 3), "load_1min": loadavg,
         "stages": stages}
    print(f"  {wall:.0f} s, {r['recordings_per_min']:.2f} recordings/min, jobs "
          f"{jobs_s:.0f} s ({jobs_s / n:.1f} s per recording), load {loadavg['mean']} mean "
          f"/ {loadavg['max']} max", flush=True)
    return r


#: the workflow's DAG per recording, each job a touch: (rule, inputs, threads, mem_mb)
DAG = (("silhouettes", (), 1, 1000), ("carve", ("silhouettes",), 1, 1000),
       ("stripes", (), 2, 1000), ("triangulate", ("stripes",), 1, 1000),
       ("align", ("triangulate", "silhouettes"), 1, 1500), ("fuse", ("align", "carve"), 2, 2500),
       ("simplify", ("fuse",), 1, 1500), ("evaluate", ("simplify",), 1, 1500))


def scheduler_overhead(root: Path, n_recordings: int) -> dict[str, Any]:
    """Wall time of a run of trivial jobs shaped like the workflow's DAG, per scheduler."""
    import subprocess

    work = root / "scheduler"
    work.mkdir(parents=True, exist_ok=True)
    rules = [f"R = [f'r{{i:03d}}' for i in range({n_recordings})]",
             "rule all:\n    input: expand('out/{r}/evaluate', r=R)"]
    for name, inputs, threads, mem in DAG:
        ins = ", ".join(f"'out/{{r}}/{i}'" for i in inputs)
        rules.append(f"rule {name}:\n" + (f"    input: {ins}\n" if ins else "")
                     + f"    output: 'out/{{r}}/{name}'\n    threads: {threads}\n"
                     f"    resources: mem_mb={mem}\n    shell: 'touch {{output}}'")
    (work / "Snakefile").write_text("\n".join(rules) + "\n")
    out: dict[str, Any] = {"jobs": n_recordings * len(DAG), "cores": 2}
    for sched in ("greedy", "ilp"):
        for d in ("out", ".snakemake"):
            shutil.rmtree(work / d, ignore_errors=True)
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "--resources",
                        "mem_mb=24000", "--scheduler", sched, "--quiet", "all"], cwd=work,
                       check=True, capture_output=True)
        out[f"{sched}_s"] = round(time.perf_counter() - t0, 1)
        out[f"{sched}_load_1min"] = round((load0 + os.getloadavg()[0]) / 2, 2)
        print(f"scheduler {sched}: {out[f'{sched}_s']} s for {out['jobs']} trivial jobs "
              f"(load {out[f'{sched}_load_1min']})", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=20, help="recordings (default 20)")
    ap.add_argument("--keep", type=Path, help="work in this folder and keep it")
    ap.add_argument("--cores", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--scheduler-recordings", type=int, default=125,
                    help="recordings of the scheduler comparison's DAG (0: skip it)")
    ap.add_argument("--no-write", action="store_true", help="do not write results/batch.json")
    args = ap.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="robo3d-batch-"))
    paths = simulate(root / "recs", args.n)
    runs = {c: measure(paths, root, c) for c in args.cores}
    result: dict[str, Any] = {
        "recordings": args.n, "recording": dict(SMALL, objects=list(OBJECTS)),
        "runs": {f"cores_{c}": r for c, r in runs.items()}, "cpus": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d"), "data": "simulated",
    }
    if 1 in runs and 2 in runs:
        eff = runs[1]["wall_s"] / (2 * runs[2]["wall_s"])
        result["speedup_2_cores"] = round(runs[1]["wall_s"] / runs[2]["wall_s"], 3)
        result["parallel_efficiency"] = round(eff, 3)
        # the same, had each job taken as long two at a time as alone: the workflow's own
        # parallelism, apart from how much the machine's cores slow each other
        per_job = runs[2]["job_time_s"] / runs[1]["job_time_s"]
        result["speedup_2_cores_job_time_scaled"] = round(
            result["speedup_2_cores"] * per_job, 3)
        print(f"2 cores: {result['speedup_2_cores']:.2f} x one core's throughput, parallel "
              f"efficiency {100 * eff:.0f} %; the jobs took {per_job:.2f} x as long two at a "
              f"time: {result['speedup_2_cores_job_time_scaled']:.2f} x scaled by job time")
    for stage, v in (runs.get(2) or runs[args.cores[0]])["stages"].items():
        print(f"  {stage:12s} {v['mean_s']:6.2f} s per job (CPU {v['mean_cpu_s']:.2f} s), "
              f"peak {v['max_rss_mb']:.0f} MB")
    if args.scheduler_recordings:
        result["scheduler"] = scheduler_overhead(root, args.scheduler_recordings)
    if not args.no_write:
        out = REPO / "benchmarks" / "results" / "batch.json"
        out.write_text(json.dumps(result, indent=2) + "\n")
        print(f"wrote {out}")


if __name__ == "__main__":
    main()
