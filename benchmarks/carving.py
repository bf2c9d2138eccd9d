"""Carving benchmark: accuracy and speed of the visual hull, against Open3D.

Run from the repository root (one command, a few minutes on 2 cores)::

    .venv/bin/python benchmarks/carving.py            # full run, writes results/carving.json
    .venv/bin/python benchmarks/carving.py --quick    # 128^3 and 256^3 only, fewer repeats

Two fixed synthetic scenes of the simulator's ``dimple_block`` (seeded; nothing random
between runs), 36 views of 640 x 480 on three rings at 0.30 m:

Accuracy (the simulator's distorted camera)
    Each view is rendered (shading, shadows, table), given sensor noise, JPEG-compressed
    at quality 92 as the simulator writes it, and segmented by the pipeline's own
    segmentation with the default configuration (ROI from the workspace box). Each mask
    is compared with the true silhouette (the pixels whose centre ray hits the object
    mesh): ``mask_iou_min``. The octree hull at 256^3 from those masks is compared with
    the *exact* visual hull of the same 36 views, sampled at the same voxel centres: a
    centre is inside it when the ray from every camera centre through it hits the true
    mesh (Open3D ray casting; no pixels, no masks). The exact hull is cast in a band of
    +-3 voxels around the carved hulls' surfaces and taken from the carved hull outside
    it; a random sample of voxels outside the band is cast too, to check that.
Speed (a distortion-free camera, since Open3D's carving ignores distortion)
    The true silhouettes (ray cast), the same masks and cameras for every method:
    our octree (numba; 1 and 2 threads), our dense carver (numpy) and Open3D's
    ``VoxelGrid.carve_silhouette`` at 128^3, 256^3 and 512^3 (voxels along the box's
    longest side). Each measurement runs in its own process (peak memory is that
    process's ``VmHWM``: interpreter, libraries, inputs and the carving); times are
    the best of several runs (wall clock, and CPU seconds of the process), because the
    machine is shared. Open3D at 512^3 is measured too (its dense hash-map grid needs about
    10 GB and minutes; this machine has 24 GB): every peer figure in the results is
    measured, not extrapolated (issue 14). ``--no-open3d-512`` skips it for a quick look;
    it is then extrapolated from 128^3 and 256^3 with the measured growth, and the notes
    say so.
Numba compile time
    The octree's kernel is compiled on first use and cached on disk (``cache=True``).
    Reported: the first call in a process with an empty cache (compile), with a filled
    cache (load), and warm calls (the headline times).

Writes ``benchmarks/results/carving.json`` with the headline figures and every
measurement.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

OBJECT = "dimple_block"
N_VIEWS = 36
WIDTH, HEIGHT = 640, 480
DISTANCE = 0.30
ELEVATIONS = (20.0, 42.0, 65.0)
SEED = 7
BAND = 3  # voxels around the carved surfaces where the exact hull is ray cast


# ---------------------------------------------------------------------------- scenes
def _workspace(mesh) -> tuple[np.ndarray, np.ndarray]:
    """The simulator's workspace box: the object's bounds + 10 mm, floor 0.5 mm."""
    lo, hi = mesh.bounds
    lo, hi = lo - 0.01, hi + 0.01
    lo[2] = 0.0005
    return lo, hi


def _poses(mesh) -> np.ndarray:
    from robo3d.sim.rig import view_poses

    lo, hi = mesh.bounds
    return view_poses(N_VIEWS, 0.5 * (lo + hi), DISTANCE, ELEVATIONS,
                      np.random.default_rng([SEED, 1]), 1.0)


def _true_masks(scene, camera, poses) -> list[np.ndarray]:
    from robo3d.sim.render import OBJECT as HIT_OBJECT

    rays = scene.pixel_rays(camera)
    out = []
    for T in poses:
        hits = scene.cast(T[:3, 3], rays @ T[:3, :3].T, normals=False)
        out.append((hits.kind == HIT_OBJECT).reshape(camera.height, camera.width))
    return out


def _segmented_masks(scene, camera, poses, box) -> list[np.ndarray]:
    """Render, add noise, JPEG round trip, segment as the pipeline does."""
    import cv2

    from robo3d.config import load_config
    from robo3d.silhouettes import SegmentOptions, roi_from_box, segment_silhouette
    from robo3d.sim.render import render_view, sensor_noise

    seg = load_config()["segmentation"]
    # the threshold without GrabCut and the edge refinement (the figures of this
    # benchmark were measured so)
    options = SegmentOptions.from_config(seg).replace(grabcut=False, edge_refine_px=0)
    out = []
    for i, T in enumerate(poses):
        signal = render_view(scene, camera, T)
        img = sensor_noise(signal, np.random.default_rng([SEED, 10, i]), 0.025, 1.0)
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img[..., ::-1]),
                               [cv2.IMWRITE_JPEG_QUALITY, 92])
        assert ok
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
        roi = roi_from_box(box[0], box[1], camera, T, margin_px=seg["roi_margin_px"])
        sil = segment_silhouette(img, roi=roi, options=options)
        out.append(sil.mask)
    return out


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1))


def exact_hull(grid, hulls: list[np.ndarray], mesh, poses, rng) -> tuple[np.ndarray, dict]:
    """The exact visual hull of the views at the grid's voxel centres (see the module
    notes): ray cast in a band around ``hulls``' surfaces, checked on a sample outside."""
    import open3d as o3d
    from scipy.ndimage import binary_dilation, binary_erosion

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    union = np.logical_or.reduce(hulls)
    inter = np.logical_and.reduce(hulls)
    ball = np.ones((3, 3, 3), bool)
    band = (binary_dilation(union, ball, iterations=BAND)
            & ~binary_erosion(inter, ball, iterations=BAND, border_value=0))

    def inside(ijk: np.ndarray) -> np.ndarray:
        keep = np.ones(len(ijk), bool)
        idx = np.arange(len(ijk))
        pts = grid.index_to_points(ijk)
        for T in poses:
            if idx.size == 0:
                break
            o = T[:3, 3]
            d = pts[idx] - o
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            rays = np.concatenate([np.broadcast_to(o, d.shape), d], axis=1).astype(np.float32)
            hit = scene.test_occlusions(o3d.core.Tensor(rays), nthreads=0).numpy()
            keep[idx[~hit]] = False
            idx = idx[hit]
        return keep

    ijk_band = np.argwhere(band)
    exact = union.copy()  # outside the band every hull agrees; union == intersection there
    exact[band] = False
    exact[tuple(ijk_band[inside(ijk_band)].T)] = True
    outside = np.flatnonzero(~band.reshape(-1))
    sample = rng.choice(outside, size=min(20000, outside.size), replace=False)
    ijk_s = np.stack(np.unravel_index(sample, grid.shape), axis=1)
    disagree = int(np.count_nonzero(inside(ijk_s) != union.reshape(-1)[sample]))
    return exact, {"band_voxels": int(band.sum()), "check_sample": int(sample.size),
                   "check_disagreements": disagree}


# ---------------------------------------------------------------------------- workers
def _worker(spec: dict) -> dict:
    """One measurement in a fresh process: load inputs, carve ``repeats`` times."""
    from robo3d.camera import CameraModel
    from robo3d.carving import make_grid

    z = np.load(spec["inputs"])
    cam = CameraModel("camera", int(z["size"][0]), int(z["size"][1]), z["K"], z["D"])
    poses, masks = z["poses"], list(z["masks"])
    grid = make_grid(z["box_min"], z["box_max"], resolution=spec["resolution"])
    base_rss = _peak_rss_mb()
    out: dict = {"shape": list(grid.shape), "voxel_size_m": grid.voxel_size}
    walls, cpus = [], []
    occ = None
    if spec["method"] in ("octree", "dense"):
        from robo3d.carving import carve_dense
        from robo3d.octree import carve_octree

        def run():
            if spec["method"] == "dense":
                return carve_dense(grid, masks, cam, poses)[0].occupancy
            return carve_octree(grid, masks, cam, poses, threads=spec["threads"])[0].occupancy

        for r in range(spec["repeats"] + (1 if spec["method"] == "octree" else 0)):
            t, c = time.perf_counter(), time.process_time()
            occ = run()
            wall, cpu = time.perf_counter() - t, time.process_time() - c
            if spec["method"] == "octree" and r == 0:
                out["first_call_s"] = wall  # compile or cache load, plus one run
                continue
            walls.append(wall)
            cpus.append(cpu)
    else:  # open3d
        import open3d as o3d

        params = []
        # float32: Open3D 0.20's Image.FloatValueAt reads no other dtype, and with a uint8
        # mask carve_silhouette finds no valid pixel (keeping, or carving, every voxel)
        images = [o3d.geometry.Image(m.astype(np.float32)) for m in masks]
        for T in poses:
            p = o3d.camera.PinholeCameraParameters()
            p.intrinsic = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, cam.fx,
                                                            cam.fy, cam.cx, cam.cy)
            p.extrinsic = np.linalg.inv(T)
            params.append(p)
        s = grid.voxel_size
        n = np.array(grid.shape)
        for _ in range(spec["repeats"]):
            t = time.perf_counter()
            vg = o3d.geometry.VoxelGrid.create_dense(grid.origin - 0.5 * s, np.zeros(3), s,
                                                     *(n * s))
            out["create_s"] = time.perf_counter() - t
            # same grid: the last voxel on each axis exists, the next one does not
            last = grid.origin + s * (n - 1)
            probe = np.array([last, *(last + s * np.eye(3))])
            assert vg.check_if_included(o3d.utility.Vector3dVector(probe)) == [True] + [False] * 3
            t, c = time.perf_counter(), time.process_time()
            for img, p in zip(images, params, strict=True):
                vg.carve_silhouette(img, p, keep_voxels_outside_image=True)
            walls.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
        # read the result back at every voxel centre (get_voxels() would build millions
        # of Python objects)
        occ = np.zeros(grid.occupancy.size, bool)
        step = 1 << 22
        for a in range(0, occ.size, step):
            ijk = np.stack(np.unravel_index(np.arange(a, min(a + step, occ.size)), grid.shape), 1)
            pts = o3d.utility.Vector3dVector(grid.index_to_points(ijk))
            occ[a:a + len(ijk)] = vg.check_if_included(pts)
        occ = occ.reshape(grid.shape)
    out.update(wall_s=min(walls), cpu_s=min(cpus), walls=walls, voxels=int(occ.sum()),
               base_rss_mb=base_rss, peak_rss_mb=_peak_rss_mb())
    if spec.get("save"):
        np.save(spec["save"], occ)
    return out


def _peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM), MB. (``ru_maxrss`` would not do: on
    Linux a child started by fork + exec inherits its parent's peak.)"""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _measure(spec: dict, env: dict | None = None) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, **(env or {})})
    if proc.returncode != 0:
        raise RuntimeError(f"worker {spec} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------------------- main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="128^3 and 256^3 only")
    ap.add_argument("--no-open3d-512", dest="open3d_512", action="store_false",
                    help="skip Open3D at 512^3 (about 10 GB and minutes): extrapolated then")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(_worker(json.loads(args.worker))))
        return

    from robo3d.camera import CameraModel
    from robo3d.carving import make_grid
    from robo3d.octree import carve_octree
    from robo3d.sim.render import SimScene
    from robo3d.sim.rig import default_camera
    from robo3d.simulate import object_mesh

    t_start = time.perf_counter()
    rng = np.random.default_rng(SEED)
    mesh = object_mesh(OBJECT)
    box = _workspace(mesh)
    poses = _poses(mesh)
    scene = SimScene(mesh, threads=0)
    results: dict = {"object": OBJECT, "views": N_VIEWS, "image": [WIDTH, HEIGHT],
                     "cpu_count": os.cpu_count(), "load_avg_start": os.getloadavg()}

    # ------------------------------------------------------------------ accuracy
    print(f"accuracy: rendering and segmenting {N_VIEWS} views of {WIDTH}x{HEIGHT} "
          "(distorted camera) ...", flush=True)
    cam_d = default_camera(WIDTH, HEIGHT)
    true_d = _true_masks(scene, cam_d, poses)
    seg_d = _segmented_masks(scene, cam_d, poses, box)
    mask_iou = [_iou(a, b) for a, b in zip(seg_d, true_d, strict=True)]
    grid = make_grid(*box, resolution=256)
    ours, _ = carve_octree(grid, seg_d, cam_d, poses)
    ours_true, _ = carve_octree(grid, true_d, cam_d, poses)
    exact, check = exact_hull(grid, [ours.occupancy, ours_true.occupancy], mesh, poses, rng)
    acc = {"mask_iou_min": min(mask_iou), "mask_iou_mean": float(np.mean(mask_iou)),
           "iou_vs_exact_hull_256": _iou(ours.occupancy, exact),
           "iou_true_masks_vs_exact_hull_256": _iou(ours_true.occupancy, exact),
           "exact_hull_voxels": int(exact.sum()), "hull_voxels": ours.n_occupied,
           "exact_hull_check": check, "grid_shape": list(grid.shape),
           "voxel_size_mm": grid.voxel_size * 1e3,
           "pixel_footprint_mm": DISTANCE / cam_d.fx * 1e3}
    results["accuracy"] = acc
    print(f"  mask IoU vs true silhouettes: min {acc['mask_iou_min']:.4f}, mean "
          f"{acc['mask_iou_mean']:.4f}")
    print(f"  hull IoU vs exact visual hull at 256^3: {acc['iou_vs_exact_hull_256']:.4f} "
          f"(segmented masks), {acc['iou_true_masks_vs_exact_hull_256']:.4f} (true masks); "
          f"band check {check['check_disagreements']}/{check['check_sample']} disagree")

    # ------------------------------------------------------------------ speed
    cam = CameraModel("camera", WIDTH, HEIGHT, cam_d.K, np.zeros(5))
    masks = _true_masks(scene, cam, poses)
    work = Path(tempfile.mkdtemp(prefix="robo3d_carving_bench_"))
    inputs = work / "inputs.npz"
    np.savez(inputs, K=cam.K, D=cam.D, size=np.array([WIDTH, HEIGHT]), poses=poses,
             masks=np.stack(masks), box_min=box[0], box_max=box[1])
    resolutions = [128, 256] if args.quick else [128, 256, 512]

    print("numba: compile (empty cache), cache load, warm ...", flush=True)
    cache = work / "numba_cache"
    env = {"NUMBA_CACHE_DIR": str(cache)}
    spec = {"inputs": str(inputs), "method": "octree", "resolution": 128, "threads": 1,
            "repeats": 3}
    cold = _measure(spec, env)
    loaded = _measure(spec, env)
    results["numba"] = {"first_call_empty_cache_s": cold["first_call_s"],
                        "first_call_cached_s": loaded["first_call_s"],
                        "warm_s": loaded["wall_s"],
                        "compile_s": cold["first_call_s"] - cold["wall_s"],
                        "cache_load_s": loaded["first_call_s"] - loaded["wall_s"]}
    print(f"  first call {cold['first_call_s']:.2f} s with an empty cache, "
          f"{loaded['first_call_s']:.2f} s with the cache, warm {loaded['wall_s']:.3f} s")

    speed: dict = {}
    repeats = {"octree": 5, "dense": {128: 3, 256: 2, 512: 1}, "open3d": {128: 2, 256: 1,
                                                                       512: 1}}
    for res in resolutions:
        row = {}
        for name, method, threads in (("octree", "octree", 1), ("octree_2t", "octree", 2),
                                      ("dense", "dense", 1), ("open3d", "open3d", 1)):
            if method == "open3d" and res == 512 and not args.open3d_512:
                continue
            n = repeats[method] if method == "octree" else repeats[method][res]
            save = str(work / f"{name}_{res}.npy")
            print(f"  {name:9s} {res}^3 (best of {n}) ...", end=" ", flush=True)
            row[name] = _measure({"inputs": str(inputs), "method": method, "resolution": res,
                                  "threads": threads, "repeats": n, "save": save})
            print(f"{row[name]['wall_s']:.3f} s wall, {row[name]['cpu_s']:.3f} s CPU, "
                  f"peak {row[name]['peak_rss_mb']:.0f} MB, {row[name]['voxels']} voxels",
                  flush=True)
        occ = {k: np.load(work / f"{k}_{res}.npy") for k in row}
        row["octree_equals_dense"] = bool(np.array_equal(occ["octree"], occ["dense"])
                                          and np.array_equal(occ["octree_2t"], occ["dense"]))
        if "open3d" in occ:
            row["open3d_extra_voxels"] = occ["open3d"].sum() / occ["dense"].sum() - 1
            row["open3d_misses_dense_voxels"] = int((occ["dense"] & ~occ["open3d"]).sum())
            if res <= 256:
                g = make_grid(*box, resolution=res)
                ex, chk = exact_hull(g, [occ["dense"], occ["open3d"]], mesh, poses, rng)
                row["iou_vs_exact"] = {"octree": _iou(occ["octree"], ex),
                                       "open3d": _iou(occ["open3d"], ex), "check": chk}
        speed[res] = row

    # ------------------------------------------------------------------ summary
    o3d_meas = {r: speed[r]["open3d"]["wall_s"] for r in speed if "open3d" in speed[r]}
    growth = o3d_meas[256] / o3d_meas[128]
    notes = [f"machine: {os.cpu_count()} cores shared with other work (load average "
             f"{os.getloadavg()[0]:.1f} at the end); times are best-of-N wall clock",
             "octree figures are warm calls (kernel compiled and cached), 1 thread unless "
             "named _2t; Open3D's carve_silhouette is single-threaded",
             "speed scene: distortion-free camera, true silhouettes, the same masks and "
             "cameras for every method; Open3D timed without create_dense"]
    o3d_512 = o3d_meas.get(512)
    if o3d_512 is None and not args.quick:
        o3d_512 = o3d_meas[256] * growth
        notes.append(f"open3d_512_s is extrapolated from 256^3 with the measured 128->256 "
                     f"growth x{growth:.2f} (its dense hash-map grid at 512^3 needs several "
                     "GB); run without --no-open3d-512 to measure it")
    print("\nresolution  octree   oct_2t   dense    open3d   dense/oct  open3d/oct  "
          "oct_peak_MB")
    for res, row in speed.items():
        o = row["octree"]["wall_s"]
        o3 = row["open3d"]["wall_s"] if "open3d" in row else (o3d_512 or float("nan"))
        mark = "" if "open3d" in row else "*"
        print(f"{res:>6}^3  {o:8.3f} {row['octree_2t']['wall_s']:8.3f} "
              f"{row['dense']['wall_s']:8.3f} {o3:8.3f}{mark:1s} "
              f"{row['dense']['wall_s'] / o:9.1f} {o3 / o:10.1f}  "
              f"{row['octree']['peak_rss_mb']:8.0f}")
    if any("open3d" not in r for r in speed.values()):
        print("  * extrapolated")
    rs = sorted(speed)
    growth_rows = {}
    for a, b in zip(rs[:-1], rs[1:], strict=True):
        growth_rows[f"{a}->{b}"] = {
            m: speed[b][m]["wall_s"] / speed[a][m]["wall_s"]
            for m in ("octree", "dense", "open3d") if m in speed[a] and m in speed[b]}
    print("cost growth per doubling (volume x8, surface x4):",
          {k: {m: round(v, 2) for m, v in g.items()} for k, g in growth_rows.items()})
    for res, row in speed.items():
        line = f"  {res}^3: octree == dense: {row['octree_equals_dense']}"
        if "open3d_extra_voxels" in row:
            line += f"; Open3D keeps {100 * row['open3d_extra_voxels']:+.1f} % voxels"
        if "iou_vs_exact" in row:
            line += (f"; IoU vs exact hull: octree {row['iou_vs_exact']['octree']:.4f}, "
                     f"Open3D {row['iou_vs_exact']['open3d']:.4f}")
        print(line)

    head = {
        "octree_256_s": speed[256]["octree"]["wall_s"],
        "octree_512_s": speed[512]["octree"]["wall_s"] if 512 in speed else None,
        "dense_256_s": speed[256]["dense"]["wall_s"],
        "open3d_256_s": o3d_meas[256],
        "open3d_512_s": o3d_512,
        "speedup_vs_open3d_256": o3d_meas[256] / speed[256]["octree"]["wall_s"],
        "speedup_vs_open3d_512": (o3d_512 / speed[512]["octree"]["wall_s"]
                                  if 512 in speed and o3d_512 else None),
        "peak_mb_512": speed[512]["octree"]["peak_rss_mb"] if 512 in speed else None,
        "iou_vs_exact_hull_256": acc["iou_vs_exact_hull_256"],
        "mask_iou_min": acc["mask_iou_min"],
        "notes": "; ".join(notes),
    }
    results["speed"] = {str(k): v for k, v in speed.items()}
    results["growth"] = growth_rows
    results["seconds"] = time.perf_counter() - t_start
    out = {**head, "details": results}
    path = ROOT / "benchmarks" / "results" / "carving.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2, default=_plain) + "\n", encoding="utf-8")
    targets = [("octree 256^3 < 0.5 s", head["octree_256_s"] < 0.5),
               ("IoU vs exact hull >= 0.99", head["iou_vs_exact_hull_256"] >= 0.99),
               ("mask IoU >= 0.99", head["mask_iou_min"] >= 0.99)]
    if 512 in speed:
        targets += [("octree 512^3 < 2 s", head["octree_512_s"] < 2.0),
                    ("20x faster than Open3D at 512^3", head["speedup_vs_open3d_512"] >= 20),
                    ("peak memory 512^3 < 1 GB", head["peak_mb_512"] < 1024)]
    print("\n" + "\n".join(f"  [{'x' if ok else ' '}] {t}" for t, ok in targets))
    print(f"wrote {path.relative_to(ROOT)} ({results['seconds']:.0f} s)")


def _plain(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return str(obj)


if __name__ == "__main__":
    main()
