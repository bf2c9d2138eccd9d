"""Random small scenes through the whole workflow with the default config: does each one
complete, how long does it take, and what is its measured surface worth?

Run from the repository root::

    .venv/bin/python benchmarks/random_scenes.py                  # 16 scenes (about 10 min)
    .venv/bin/python benchmarks/random_scenes.py --n 28 --start 100 --keep /tmp/rs
    .venv/bin/python benchmarks/random_scenes.py --scenes 148 466 --out /tmp/again.json

Scene ``k`` is drawn from a generator seeded with ``1000 + k`` (the same scene on every
run): one of the simulator's objects or a user's mesh file (a PLY box in metres, an STL
torus in millimetres, written here with Open3D), the demo or the cell scene, 320 x 240 or
640 x 480, 2-12 views, 1-4 sweeps of 20-60 frames, every laser colour, nine object
colours, four textures, four table patterns, with and without the wall, a drifting robot
error, a camera clock 2-10 ms late, PNG / JPEG views, PNG / mono / JPEG laser frames,
laser-only and photo-only recordings; from scene 460 on, turntable rigs and recordings
without a workspace box too; from scene 831 on, laser speckle in half the scenes with laser
frames. Each is run through the Snakemake workflow with the
DEFAULT configuration, ``--cores 2``, in a fresh work folder.

The one target is that every scene completes (``completed`` = ``n_scenes``); the figures
beside it have none: small scenes of few views and sweeps are not expected to reach the
demos' accuracy. They show where time goes on scans nobody designed (stop 29 found the
simplification holding hull-inferred surface at the measurement's precision this way).

Writes ``benchmarks/results/random_scenes.json``: ``n_scenes``, ``completed``,
``end_to_end_s_max``, ``targets``, ``met``, ``notes`` and ``details`` (per scene: its
``robo3d simulate`` arguments, ``completed``, ``end_to_end_s``, the slowest stage and its
seconds, and for scenes with laser frames and a true surface ``measured_median_mm``,
``measured_p95_mm``, and with a true surface the whole mesh's ``mesh_median_mm``,
``mesh_p95_mm`` and its ``inferred_area_fraction``, from the run's own ``metrics.json``;
a failed run's error).
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import sys
import tempfile
from datetime import date
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import REPO, fresh_workdir, previous_results, run_workflow, simulate_cli  # noqa: E402

OBJECTS = ["dimple_block", "vase", "blob", "sphere", "bracket", "cup", "bumpy_blob",
           "near_symmetric", "thin_wall", "user_box", "user_torus"]
COLOURS = ["grey", "white", "orange", "red", "green", "blue", "yellow", "brown", "black"]
TARGETS = {"completed": "== n_scenes"}


def user_meshes(base: Path) -> dict[str, list[str]]:
    """The user's mesh files (written once into ``base``) as ``robo3d simulate`` options."""
    import open3d as o3d

    base.mkdir(parents=True, exist_ok=True)
    box, torus = base / "box_m.ply", base / "torus_mm.stl"
    if not box.exists():
        m = o3d.geometry.TriangleMesh.create_box(0.04, 0.03, 0.05)
        m.compute_triangle_normals()
        o3d.io.write_triangle_mesh(str(box), m)
    if not torus.exists():
        m = o3d.geometry.TriangleMesh.create_torus(torus_radius=25, tube_radius=8,
                                                   radial_resolution=60,
                                                   tubular_resolution=30)
        m.compute_triangle_normals()
        o3d.io.write_triangle_mesh(str(torus), m)
    return {"user_box": ["--object-mesh", str(box)],
            "user_torus": ["--object-mesh", str(torus), "--mesh-unit", "mm"]}


def scene(k: int) -> tuple[str, list[str]]:
    """Scene ``k``: its object and its ``robo3d simulate`` options (module docstring)."""
    rnd = random.Random(1000 + k)
    obj = rnd.choice(OBJECTS)
    kind = rnd.choice(["cell", "cell", "demo"])
    a = ["--scene", kind, "--seed", str(k), "--views", str(rnd.choice([4, 6, 8, 12])),
         "--sweeps", str(rnd.choice([2, 3, 4])), "--width", "320", "--height", "240",
         "--sweep-frames", str(rnd.choice([20, 40, 60])), "--threads", "0"]
    if kind == "cell":
        a += ["--laser", rnd.choice(["red", "green", "blue"]),
              "--object-color", rnd.choice(COLOURS),
              "--object-texture", rnd.choice(["none", "blotches", "checker", "stripes"]),
              "--table-markers", rnd.choice(["none", "aruco", "checker", "dots"])]
        if rnd.random() < 0.3:
            a += ["--no-wall"]
    if rnd.random() < 0.4:
        a += ["--robot-error", "drift"]
    if rnd.random() < 0.3:
        a += ["--clock-lag-ms", str(rnd.choice([2, 5, 10]))]
    if rnd.random() < 0.2:
        a += ["--view-encoding", "png"]
    if rnd.random() < 0.3:
        a += ["--laser-encoding", rnd.choice(["png", "mono8", "jpeg"])]
    u = rnd.random()
    if u < 0.12:
        a += ["--no-views"]
    elif u < 0.22:
        a += ["--no-laser"]
    if rnd.random() < 0.15:
        a[a.index("--sweeps") + 1] = "1"
    if rnd.random() < 0.15:
        a[a.index("--views") + 1] = rnd.choice(["2", "3"])
    if rnd.random() < 0.2:
        a[a.index("--width") + 1], a[a.index("--height") + 1] = "640", "480"
    if k >= 460:  # stop 52: turntable rigs and recordings without a box (the scenes
        # before keep their draws)
        if rnd.random() < 0.3:
            a += ["--turntable", "--sweep-elevation", str(rnd.choice([15, 25, 40]))]
        if rnd.random() < 0.25:
            a += ["--no-box"]
    if k >= 831 and "--no-laser" not in a and rnd.random() < 0.5:  # stop 63: speckle
        a += ["--laser-speckle", str(rnd.choice([0.3, 0.5, 0.8, 1.0])),
              "--speckle-grain", str(rnd.choice([1.0, 1.5, 2.5]))]
    return obj, a


def run_scene(name: str, obj: str, a: list[str], base: Path, meshes: dict[str, list[str]]
              ) -> dict[str, Any]:
    """Simulate a scene (unless its recording is there), run the workflow, score it."""
    rec = base / "recordings" / f"{name}.mcap"
    rec.parent.mkdir(parents=True, exist_ok=True)
    out: dict[str, Any] = {"object": obj, "args": a}
    if not rec.exists():
        err = simulate_cli(rec, [*([obj] if obj not in meshes else []), str(rec),
                                 *meshes.get(obj, []), *a])
        if err is not None:
            return {**out, "completed": 0, "failed": "simulation: " + err}
    work = fresh_workdir(base / "work" / name)
    try:
        e2e = run_workflow(rec, work)
    except RuntimeError as exc:
        return {**out, "completed": 0, "failed": str(exc)[-2000:]}
    m = json.loads((work / "results" / name / "metrics.json").read_text())
    times = {k_: (v["seconds"] if isinstance(v, dict) else v)
             for k_, v in m.get("timings", {}).items() if k_ != "total_seconds"}
    slow = max(times, key=times.get) if times else None
    meas = m.get("evaluation", {}).get("measured") or {}
    mesh = m.get("evaluation", {}).get("mesh") or {}
    return {**out, "completed": 1, "end_to_end_s": e2e, "slowest_stage": slow,
            "slowest_stage_s": times.get(slow) if slow else None,
            "measured_median_mm": meas.get("median_mm"), "measured_p95_mm": meas.get("p95_mm"),
            "mesh_median_mm": mesh.get("median_mm"), "mesh_p95_mm": mesh.get("p95_mm"),
            "inferred_area_fraction": (m.get("surface_sources") or {}).get(
                "inferred_area_fraction")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=16, help="number of scenes")
    ap.add_argument("--start", type=int, default=0, help="first scene's number")
    ap.add_argument("--scenes", type=int, nargs="+", default=None,
                    help="run these scene numbers instead of --n from --start (again, after a fix)")
    ap.add_argument("--keep", default=None, help="keep recordings and work folders here")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "random_scenes.json"))
    args = ap.parse_args()
    if args.n < 1 or args.start < 0 or min(args.scenes or [0]) < 0:
        ap.error("--n must be >= 1, --start and --scenes >= 0")
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="robo3d-random-"))
    out_path = Path(args.out)
    old = previous_results(out_path)
    meshes = user_meshes(base / "meshes")
    details: dict[str, Any] = {}
    for k in args.scenes or range(args.start, args.start + args.n):
        obj, a = scene(k)
        print(f"== scene {k} ({obj}): {' '.join(a)}", flush=True)
        name = f"scene{k:03d}_{obj}"
        details[name] = d = run_scene(name, obj, a, base, meshes)
        if d["completed"]:
            med = d["measured_median_mm"]
            print(f"   completed in {d['end_to_end_s']:.1f} s (slowest: {d['slowest_stage']} "
                  f"{d['slowest_stage_s']:.1f} s)"
                  + (f"; measured median {med:.3f} mm" if med is not None else ""), flush=True)
        else:
            print(f"   FAILED: {d['failed'][-600:]}", flush=True)
    done = sum(d["completed"] for d in details.values())
    e2e = [d["end_to_end_s"] for d in details.values() if d["completed"]]
    result = {"n_scenes": len(details), "completed": done,
              "end_to_end_s_max": max(e2e) if e2e else None,
              "targets": TARGETS,
              "met": {"completed": done == len(details)},
              "details": details, "date": str(date.today()),
              "notes": old.get("notes", "")}
    out_path.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(f"{done} of {len(details)} scenes completed; wrote {out_path}")
    if not args.keep:
        shutil.rmtree(base, ignore_errors=True)
    return 0 if done == len(details) else 1


if __name__ == "__main__":
    raise SystemExit(main())
