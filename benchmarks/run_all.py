"""Every benchmark, one after the other, then the table of their results.

Run from the repository root::

    .venv/bin/python benchmarks/run_all.py                  # everything (hours: see below)
    .venv/bin/python benchmarks/run_all.py --only carving,laser
    .venv/bin/python benchmarks/run_all.py --skip objects    # all but the longest
    .venv/bin/python benchmarks/run_all.py --table-only      # only rebuild RESULTS.md

Each benchmark is its own script in ``benchmarks/`` (run in its own process, with its
default options, so that each measures what its section of ``benchmarks/README.md``
describes) and writes ``benchmarks/results/<name>.json``; then ``benchmarks/table.py``
writes ``benchmarks/RESULTS.md``: every headline figure with its target, whether it is
met, and the peer measured in the same run with the ratio. A benchmark that fails is
reported and the others still run (its previous results stay, and the table says when
each was measured); the exit status is 1 when any failed.

The benchmarks that need ``../shared/real/`` (the real recordings) measure those parts
only when it is there. About how long each takes on this project's 2-core machine, when
nothing else runs: carving 10 min (Open3D at 512^3 measured: about 10 GB), laser 3 min,
pipeline 5 min, front_end 30 min, hard_scenes 15 min, random_scenes 10 min, determinism
20 min, calibration 15 min, batch 15 min, objects 1-2 h. Run it on a quiet machine: the
figures are wall-clock times.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

#: The benchmarks in the order they run (quick ones first), each a script in benchmarks/.
BENCHMARKS = ("carving", "laser", "pipeline", "calibration", "front_end", "hard_scenes",
              "random_scenes", "determinism", "batch", "objects")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default=None, help="comma-separated benchmarks to run")
    ap.add_argument("--skip", default="", help="comma-separated benchmarks not to run")
    ap.add_argument("--table-only", action="store_true", help="only rebuild RESULTS.md")
    args = ap.parse_args(argv)
    chosen = args.only.split(",") if args.only else list(BENCHMARKS)
    unknown = sorted((set(chosen) | set(filter(None, args.skip.split(",")))) - set(BENCHMARKS))
    if unknown:
        ap.error(f"unknown benchmark(s) {', '.join(unknown)}; known: {', '.join(BENCHMARKS)}")
    chosen = [b for b in BENCHMARKS if b in chosen and b not in args.skip.split(",")]
    failed = []
    if not args.table_only:
        for name in chosen:
            script = HERE / f"{name}.py"
            if not script.exists():
                print(f"== {name}: {script} is missing; skipped", flush=True)
                failed.append(name)
                continue
            print(f"== {name} (load average {os.getloadavg()[0]:.1f}) ...", flush=True)
            t0 = time.perf_counter()
            rc = subprocess.call([sys.executable, str(script)], cwd=REPO)
            print(f"== {name}: {'done' if rc == 0 else f'FAILED (exit {rc})'} in "
                  f"{time.perf_counter() - t0:.0f} s", flush=True)
            if rc != 0:
                failed.append(name)
    rc = subprocess.call([sys.executable, str(HERE / "table.py")], cwd=REPO)
    if failed:
        print(f"failed: {', '.join(failed)} (their previous results, if any, are in the "
              "table)", flush=True)
    return 1 if failed or rc else 0


if __name__ == "__main__":
    raise SystemExit(main())
