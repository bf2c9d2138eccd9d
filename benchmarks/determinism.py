"""Determinism: the demo run twice, on 2 cores and on 1, gives the same results.

Each run works in its own folder with the default config on the demo recordings
(``recordings/*.mcap``, written by ``./run.sh demo`` or ``robo3d simulate --demo``). The
two runs' ``metrics.json`` are compared with every wall-clock and CPU-time figure and
the stages' thread counts taken out (they describe the run, not the scan),
and every result file (arrays, clouds, meshes) is compared byte for byte.

Writes ``benchmarks/results/determinism.json``: ``identical_metrics``,
``identical_files`` (all recordings), and per recording the metrics keys and the files
that differ.

    .venv/bin/python benchmarks/determinism.py [--keep DIR] [--recordings A.mcap B.mcap]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, run_workflow  # noqa: E402

from robo3d.pipeline import RUN_DETAIL_KEYS, without_run_details  # noqa: E402

#: the result files compared byte for byte
RESULT_FILES = ("silhouettes.npz", "hull.npz", "hull.ply", "stripes.npz", "clouds.npz",
                "aligned.npz", "aligned.ply", "fused.ply", "measured.ply", "mesh.ply")


def differences(a: Any, b: Any, path: str = "") -> list[str]:
    """The key paths where two JSON values differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{path}.{k}")
            else:
                out += differences(a[k], b[k], f"{path}.{k}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True))
                for d in differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [path or "."]


def compare(run_a: Path, run_b: Path, name: str) -> dict[str, Any]:
    """What differs between two runs' results of one recording."""
    ra, rb = run_a / "results" / name, run_b / "results" / name
    ma = without_run_details(json.loads((ra / "metrics.json").read_text()))
    mb = without_run_details(json.loads((rb / "metrics.json").read_text()))
    files = [f for f in RESULT_FILES if (ra / f).exists() or (rb / f).exists()]
    differ = [f for f in files if not ((ra / f).exists() and (rb / f).exists()
                                      and (ra / f).read_bytes() == (rb / f).read_bytes())]
    return {"metrics_keys_differing": differences(ma, mb), "files_compared": files,
            "files_differing": differ}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keep", type=Path, help="work in this folder and keep it")
    ap.add_argument("--recordings", type=Path, nargs="*",
                    default=sorted((REPO / "recordings").glob("*.mcap")))
    args = ap.parse_args()
    if not args.recordings:
        sys.exit("no recordings: run ./run.sh demo (or robo3d simulate --demo recordings/)")
    root = args.keep or Path(tempfile.mkdtemp(prefix="robo3d-determinism-"))
    walls = {}
    for cores in (2, 1):
        work = root / f"cores{cores}"
        work.mkdir(parents=True, exist_ok=True)
        print(f"run on {cores} core(s) in {work} ...", flush=True)
        walls[cores] = run_workflow([p.resolve() for p in args.recordings], work, cores=cores)
        print(f"  {walls[cores]:.0f} s", flush=True)
    per = {p.stem: compare(root / "cores2", root / "cores1", p.stem) for p in args.recordings}
    for name, r in per.items():
        print(f"{name}: metrics keys differing: {r['metrics_keys_differing'] or 'none'}; "
              f"files differing: {r['files_differing'] or 'none'} "
              f"(of {len(r['files_compared'])})")
    result = {
        "identical_metrics": all(not r["metrics_keys_differing"] for r in per.values()),
        "identical_files": all(not r["files_differing"] for r in per.values()),
        "recordings": per, "wall_s": {f"cores_{k}": round(v, 1) for k, v in walls.items()},
        "data": "simulated (the demo recordings, default config)",
        "date": time.strftime("%Y-%m-%d"),
        "notes": "metrics.json compared without its times and thread counts "
                 f"(pattern {RUN_DETAIL_KEYS.pattern!r}); result files byte for byte.",
    }
    print(f"identical metrics: {result['identical_metrics']}, identical files: "
          f"{result['identical_files']}")
    out = REPO / "benchmarks" / "results" / "determinism.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
