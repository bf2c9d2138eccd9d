"""What the benchmarks share: one Snakemake run of a recording, a figure against its
target."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def repo_config() -> dict[Any, Any]:
    """The repository's ``config/config.yaml``, validated: the configuration the
    workflow runs with by default."""
    import yaml

    from robo3d.config import validate_config

    return validate_config(yaml.safe_load((REPO / "config" / "config.yaml").read_text()))


def chosen(ap: Any, text: str, known: Any, what: str) -> list[str]:
    """The comma-separated names of ``text`` (``--only``), each one of ``known``; an
    argparse error naming the unknown ones otherwise."""
    names = [n for n in text.split(",") if n]
    bad = [n for n in names if n not in known]
    if bad:
        ap.error(f"unknown {what}(s) {', '.join(bad)}; expected {', '.join(known)}")
    return names


def previous_results(path: Path) -> dict[str, Any]:
    """The results file a run updates (its notes and the parts not run are kept), or {}."""
    import json

    return json.loads(path.read_text()) if path.exists() else {}


def laser_frame_poses(rec: Any, res: Path) -> tuple[Any, Any]:
    """Each laser frame's TRUE camera pose at its exposure (``ground_truth/image_poses.json``)
    and the pose the pipeline used (``stripes.npz``), ``(N, 4, 4)`` each; the caller
    checks that the counts agree."""
    import numpy as np

    from robo3d.simulate import image_poses

    with np.load(res / "stripes.npz") as z:
        T_rep = z["T_base_camera"]
    return np.stack([e["T_base_camera"] for e in image_poses(rec)["/camera/laser_image"]]), T_rep


def simulate_cli(path: Path, args: list[str]) -> str | None:
    """``robo3d simulate <args>`` writing ``path`` (the recording's place among ``args``
    is the caller's); None, or the tail of its stderr when it failed."""
    import subprocess
    import sys

    cmd = [str(Path(sys.executable).with_name("robo3d")), "simulate", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    return proc.stderr[-2000:] if proc.returncode else None


def fresh_workdir(work: Path) -> Path:
    """``work``, emptied (a previous run's outputs would be reused by Snakemake)."""
    import shutil

    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    return work


_WARM = False


def run_workflow(recording: Path | list[Path], work: Path, targets: tuple[str, ...] = ("all",),
                 cores: int = 2) -> float:
    """One Snakemake run on one recording (or a list) in ``work`` with the default config,
    on ``cores`` cores, its output kept in ``work/snakemake.log``; the wall time in
    seconds. Before the first run of a benchmark the numba kernels are compiled into the
    checkout's cache (``robo3d warm-up``, as ``./run.sh`` does), so that a fresh
    checkout's first run does not time the compiler (stop 33: 62 s of a first scene's
    stripes stage)."""
    global _WARM
    if not _WARM:
        from robo3d.warmup import compile_kernels

        compile_kernels()
        _WARM = True
    recs = recording if isinstance(recording, list) else [recording]
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "--directory",
           str(work), "--cores", str(cores), *targets, "--quiet", "all",
           "--config", f"recordings=[{','.join(str(r) for r in recs)}]"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    (work / "snakemake.log").write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        raise RuntimeError(f"snakemake failed on {recording} (see {work}/snakemake.log):\n"
                           f"{proc.stderr[-3000:]}")
    return dt


def check_target(targets: dict[str, tuple[str, float]], key: str, value: Any) -> bool | None:
    """Whether ``value`` meets ``targets[key]`` (``(">=" | "<=" | "<", bound)``); None when
    the key has no target or the figure was not measured."""
    if key not in targets or value is None:
        return None
    op, bound = targets[key]
    return bool(value >= bound if op == ">=" else value <= bound if op == "<=" else value < bound)
