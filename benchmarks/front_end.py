"""Front-end benchmark (issue 10): segmentation and laser stripes on real and realistic
recordings, alignment under a robot error that the alignment does not model, and the
stripes stage's speed on ambient-lit frames.

Run from the repository root::

    .venv/bin/python benchmarks/front_end.py              # everything (about 15 min on 2 cores)
    .venv/bin/python benchmarks/front_end.py --keep /tmp/fe          # keep the work folders
    .venv/bin/python benchmarks/front_end.py --keep /tmp/fe --reuse  # re-measure only
    .venv/bin/python benchmarks/front_end.py --only dtu,cells        # some parts

Every recording runs through the Snakemake workflow with the DEFAULT configuration
(``config/config.yaml``), in a fresh work folder, ``--cores 2``. Parts:

``dtu``
    ``../shared/real/dtu_scan24.mcap`` (49 real photos of a model house on a bright
    table; its published masks attached as ``ground_truth/silhouettes/NNN.png``): every
    mask of the silhouettes stage against the published one (IoU over the whole image),
    mean and worst view; the hull's size and the views the carving QA left out.
``cells``
    Simulated cells as real ones look (``SimulationParams.cell``: room light in the laser
    frames, a coloured textured glossy object on a bright ArUco table before a wall, JPEG
    80, webcam noise and vignetting), one per laser colour, with EXACT robot poses (no
    pose error, no clock lag), so that what is scored is the front end alone (the workflow
    runs up to the silhouettes and the aligned clouds):

    * masks: every view's mask against the true silhouette (``ground_truth/silhouettes``);
    * stripe points: the points the pipeline delivers (``aligned.npz``: the
      triangulated clouds after the alignment, which has little to correct with exact
      poses, and after its test against the silhouettes that drops points triangulated
      into empty space) against the true surface: median, 95th percentile, and the
      outliers (the fraction of points more than 1 mm off); the raw triangulated
      clouds (``clouds.npz``) are scored beside them (``triangulated_*``);
    * recall: for every laser frame the truth of the visible stripe
      (:func:`robo3d.simulate.stripe_truth`: the object points lit by the sheet and seen
      by the camera, at the true exposure pose) is cut into one-pixel bins along the
      stripe; a bin counts as visible when its expected signal is at least
      ``stripes.min_peak`` and it lies 3 px or more inside the image, as found when a
      detected centre lies within 1.5 px of it. Recall = found / visible bins, over all
      frames (``stripe_recall`` per colour, ``stripe_recall_min`` the worst colour).
``speckle`` (not in the default run)
    The three cells of ``cells`` with laser speckle (:data:`SPECKLE`: contrast 0.5, grains
    of 1.5 px, a new pattern per frame; an error the detector does not model), scored
    alike: how far the stripe points degrade when the laser's light is grainy, as a real
    laser's is (``details.speckle``; not a headline figure).
``srv``
    ``../shared/real/srv_laser_calibration.mcap``: the stripe on the hand-held board
    (``benchmarks/laser.py``'s ``srv_board_figures``: an OpenCV oracle for the
    intrinsics and each board's plane, the pipeline's detector for the stripe, one laser
    plane through the stripe's points on the boards; its RMS residual).
``drift``
    The demo block (demo settings: 24 views, 7 sweeps, 1.1 mm profiles) with the robot
    error the alignment does not model (``robot_error="drift"``: the per-sweep error
    times a smooth drift within the sweep plus a pose-dependent term, views included) and
    a camera clock 4 ms late. The pose error is scored per laser FRAME, at the pose the
    pipeline used for it: ``C_f T_reported(stamp)`` against the true camera pose at the
    frame's exposure (``ground_truth/image_poses.json``), ``C_f`` the alignment's
    correction at that frame (its motion model): the rotation angle and the largest
    displacement of the frame's own points (the workflow's own evaluation,
    ``metrics.json`` -> ``evaluation.poses.worst_*_frame_*``). A sweep's error is its worst frame;
    ``pose_err_after_*`` is the worst sweep. The final mesh is scored by the workflow's
    own evaluation (``metrics.json``): completeness counts the true surface in the
    workspace box ("what the sensors could observe": the box starts just above the table).
``speed``
    ``benchmarks/laser.py``'s ``ambient_speed`` on ambient-lit 1280x960 RGB frames:
    detection + triangulation frames/s on 2 threads, the stripes stage over decoding
    alone (PNG; JPEG beside it), and the vectorised-numpy peer of the same method.

Writes ``benchmarks/results/front_end.json`` (keys as issue 10 names them, plus
``details``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
REAL = REPO.parent / "shared" / "real"
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from common import fresh_workdir, previous_results, run_workflow  # noqa: E402 (after the path setup)

TARGETS = {"dtu24_mask_iou_mean": (">=", 0.97), "dtu24_mask_iou_min": (">=", 0.93),
           "sim_mask_iou_min": (">=", 0.99), "stripe_median_mm": ("<=", 0.05),
           "stripe_p95_mm": ("<=", 0.2), "stripe_recall_min": (">=", 0.95),
           "stripe_outlier_fraction": ("<", 0.005), "srv_board_plane_rms_mm": ("<=", 0.5),
           "pose_err_after_mm": ("<=", 0.05), "pose_err_after_deg": ("<=", 0.02),
           "mesh_median_mm": ("<=", 0.05), "mesh_p95_mm": ("<=", 0.2),
           "completeness_0_5mm": (">=", 0.99), "fps_ambient_1280x960": (">=", 1000.0),
           "stage_over_decode_ambient": ("<=", 1.5)}

#: The cell scenes: laser colour -> (object, object colour), coloured objects on the bright
#: marker table (a red laser on an orange object, whose lit rim is a red ridge too).
CELLS = {"red": ("vase", "orange"), "green": ("blob", "green"), "blue": ("dimple_block", "blue")}
#: Known limit, measured and reported apart (silhouettes only): a white object on the
#: white-and-black marker table, which colour alone cannot separate.
WHITE_CELL = ("blue", "dimple_block", "white")
CELL_SIZE = dict(width=640, height=480, views=12, sweeps=4, sweep_frames=60,
                 mesh_faces=30_000, mesh_voxel=0.0009)
EXACT = dict(sweep_error_mm=(0.0, 0.0), sweep_error_deg=(0.0, 0.0),
             view_error_mm=(0.0, 0.0), view_error_deg=(0.0, 0.0), view_jitter=0.0)
DRIFT = dict(seed=1, sweep_spacing=0.0011, robot_error="drift", clock_lag_ms=4.0)
#: Laser speckle of the ``speckle`` part: a webcam's partly averaged speckle (stop 63)
SPECKLE = dict(laser_speckle=0.5, speckle_grain_px=1.5)


def _in_box(clouds) -> np.ndarray:
    """The triangulated points in the workspace box (not the triangulation's margin
    around it, which the align stage crops once the sweeps are corrected)."""
    from robo3d.artefacts import crop_clouds_to_workspace

    crop_clouds_to_workspace(clouds)
    return np.concatenate([c.points_base for c in clouds])


def _simulated(base: Path, name: str, make) -> Path:
    """``base/recordings/{name}.mcap``, simulated by ``make(path)`` unless already there
    (the simulator is deterministic: the same file on every run)."""
    path = base / "recordings" / f"{name}.mcap"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        print(f"== {name}: simulating ...", flush=True)
        t0 = time.perf_counter()
        make(path)
        print(f"   {path.stat().st_size / 1e6:.1f} MB in {time.perf_counter() - t0:.0f} s",
              flush=True)
    return path


def _prepared(work: Path, reuse: bool) -> bool:
    """True when ``work`` holds a finished run to reuse; else an empty ``work``."""
    if reuse and (work / "done.json").exists():
        return True
    fresh_workdir(work)
    return False


def mask_ious(rec, silhouettes_npz: Path) -> list[float]:
    """IoU of every segmented mask with the recording's true silhouette, in view order
    (:func:`robo3d.evaluate.silhouette_iou`, as the workflow's evaluation scores them)."""
    from robo3d.evaluate import silhouette_iou

    with np.load(silhouettes_npz) as z:
        shape = tuple(int(x) for x in z["mask_shape"])
        masks = np.unpackbits(z["masks"], axis=-1, count=shape[2]).astype(bool)
    r = silhouette_iou(list(masks), rec.attachments)
    if r["n_scored"] != len(masks):
        raise KeyError(f"{rec.path}: only {r['n_scored']} of {len(masks)} views have a usable "
                       f"true silhouette ({r['skipped']})")
    return [float(v["iou"]) for v in r["per_view"]]


def _overlay(image: np.ndarray, mask: np.ndarray, truth: np.ndarray, path: Path) -> None:
    """Mask outline (green) and true outline (red) over the image, for a person to look at."""
    import cv2

    img = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=2)
    out = cv2.cvtColor(np.ascontiguousarray(img[..., :3]).astype(np.uint8), cv2.COLOR_RGB2BGR)
    for m, colour in ((truth, (0, 0, 255)), (mask, (0, 255, 0))):
        cs, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, cs, -1, colour, 1)
    cv2.imwrite(str(path), out)


# --------------------------------------------------------------------------- dtu
def part_dtu(base: Path, reuse: bool) -> dict[str, Any]:
    from robo3d.recording.reader import read_recording

    path = REAL / "dtu_scan24.mcap"
    if not path.exists():
        return {"skipped": f"{path} not found"}
    work = base / "dtu_scan24"
    if not _prepared(work, reuse):
        e2e = run_workflow(path, work)
        (work / "done.json").write_text(json.dumps({"end_to_end_s": e2e}))
    e2e = json.loads((work / "done.json").read_text())["end_to_end_s"]
    res = work / "results" / "dtu_scan24"
    rec = read_recording(path, roles=("views",))
    ious = mask_ious(rec, res / "silhouettes.npz")
    carve = json.loads((res / "reports" / "carve.json").read_text())
    _pictures(rec, res / "silhouettes.npz", ious, work / "pictures")
    print(f"   DTU scan24: mask IoU mean {np.mean(ious):.4f}, worst {min(ious):.4f} "
          f"(view {int(np.argmin(ious))}); pictures in {work / 'pictures'}", flush=True)
    return {"mask_iou_mean": float(np.mean(ious)), "mask_iou_min": float(min(ious)),
            "worst_view": int(np.argmin(ious)), "mask_iou_per_view": ious,
            "hull": {**{k: carve.get(k) for k in ("occupied_voxels", "volume_m3", "bbox_min",
                                                   "bbox_max", "views_left_out")},
                     "agreement": {k: carve.get("agreement", {}).get(k)
                                   for k in ("flagged", "iou_min", "iou_median")}},
            "end_to_end_s": e2e}


def _pictures(rec, silhouettes_npz: Path, ious: list[float], folder: Path) -> None:
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    views = sorted(rec.views, key=lambda m: m.timestamp_ns)
    with np.load(silhouettes_npz) as z:
        shape = tuple(int(x) for x in z["mask_shape"])
        masks = np.unpackbits(z["masks"], axis=-1, count=shape[2]).astype(bool)
    order = np.argsort(ious)
    for i in sorted({*order[:3].tolist(), *range(0, len(views), max(1, len(views) // 6))}):
        t = cv2.imdecode(np.frombuffer(rec.attachments[f"ground_truth/silhouettes/{i:03d}.png"],
                                       np.uint8), cv2.IMREAD_GRAYSCALE) > 127
        _overlay(rec.decode(views[i]), masks[i], t, folder / f"view_{i:03d}_iou{ious[i]:.3f}.png")


# --------------------------------------------------------------------------- cells
def part_cells(base: Path, reuse: bool, speckle: dict[str, Any] | None = None
               ) -> dict[str, Any]:
    """The ``cells`` part; with ``speckle`` (:data:`SPECKLE`) the ``speckle`` part's cells."""
    from robo3d.simulate import SimulationParams, simulate_recording

    out: dict[str, Any] = {}
    for colour, (obj, obj_colour) in CELLS.items():
        name = f"{'speckle' if speckle else 'cell'}_{colour}"
        work = base / name
        rec_path = _simulated(base, name, lambda p, o=obj, c=colour, oc=obj_colour:
                              simulate_recording(p, o, params=SimulationParams.cell(
                                  laser=c, object_color=oc, **CELL_SIZE, **EXACT, seed=10,
                                  **(speckle or {})), threads=0))
        if not _prepared(work, reuse):
            print(f"== {name}: {obj} ({obj_colour}), workflow up to the clouds ...", flush=True)
            e2e = run_workflow(rec_path, work, (f"results/{name}/silhouettes.npz",
                                                f"results/{name}/aligned.npz"))
            (work / "done.json").write_text(json.dumps({"end_to_end_s": e2e}))
        out[colour] = score_cell(rec_path, work / "results" / name)
        out[colour]["object"], out[colour]["object_colour"] = obj, obj_colour
        c = out[colour]
        print(f"   {name}: mask IoU min {c['mask_iou_min']:.4f}; stripe points median "
              f"{c['stripe_median_mm']:.4f} p95 {c['stripe_p95_mm']:.4f} mm, outliers "
              f"{c['stripe_outlier_fraction']:.4%}; recall {c['stripe_recall']:.4f}", flush=True)
    if speckle:
        out["speckle"] = dict(speckle)
        return out
    # the known limit: a white object on the white-and-black marker table (masks only)
    from robo3d.silhouettes import score_recording_silhouettes

    laser, obj, obj_colour = WHITE_CELL
    path = _simulated(base, "cell_blue_white", lambda p: simulate_recording(
        p, obj, params=SimulationParams.cell(laser=laser, object_color=obj_colour,
                                             **CELL_SIZE, **EXACT, seed=10), threads=0))
    r = score_recording_silhouettes(str(path))
    out["known_limit_white_object"] = {"object": obj, "object_colour": obj_colour,
                                       "mask_iou_mean": r["iou_mean"],
                                       "mask_iou_min": r["iou_min"],
                                       "qa_flags": r["qa_flags"]}
    print(f"   known limit, white {obj} on the marker table: mask IoU mean "
          f"{r['iou_mean']:.3f}, worst {r['iou_min']:.3f}", flush=True)
    return out


def score_cell(rec_path: Path, res: Path) -> dict[str, Any]:
    from scipy.spatial import cKDTree

    from robo3d.artefacts import load_clouds_npz
    from robo3d.config import default_config
    from robo3d.evaluate import TruthSurface
    from robo3d.meshio import read_mesh
    from robo3d.recording.reader import read_recording
    from robo3d.simulate import image_poses, stripe_truth, truth_scene

    cfg = default_config()
    rec = read_recording(rec_path)
    ious = mask_ious(rec, res / "silhouettes.npz")
    _pictures(rec, res / "silhouettes.npz", ious, res.parent.parent / "pictures")
    Vt, Ft = read_mesh(rec.attachments["ground_truth/mesh.ply"])
    truth = TruthSurface(Vt, Ft)
    # the points the pipeline delivers (aligned.npz: after the alignment, which with exact
    # poses has little to correct, and its test against the silhouettes); the
    # triangulation's raw points are reported beside them
    pts = np.concatenate([c.points_base for c in load_clouds_npz(res / "aligned.npz")])
    d_mm = truth.distance(pts) * 1e3
    raw = _in_box(load_clouds_npz(res / "clouds.npz"))
    d_raw = truth.distance(raw) * 1e3
    # recall against the true visible stripe
    scene = truth_scene(rec, threads=2)
    poses = image_poses(rec)
    with np.load(res / "stripes.npz") as z:
        s = {k: z[k] for k in ("u", "v", "offsets", "stamps_ns")}
    stamps = [int(e["stamp_ns"]) for e in poses["/camera/laser_image"]]
    frame_of = {t: i for i, t in enumerate(s["stamps_ns"].tolist())}
    cam = rec.camera_for(rec.laser_frames[0])
    min_signal = float(cfg["stripes"]["min_peak"])
    visible = found = 0
    per_frame = []
    for k, t in enumerate(stamps):
        tr = stripe_truth(rec, k, scene=scene, poses=poses)
        uv = tr.pixels_uv[tr.on_object & (tr.signal_dn >= min_signal)]
        inside = ((uv[:, 0] >= 3) & (uv[:, 0] <= cam.width - 4) & (uv[:, 1] >= 3)
                  & (uv[:, 1] <= cam.height - 4))
        uv = uv[inside]
        if len(uv) < 2:
            continue
        # one-pixel bins along the stripe's own direction (its principal axis)
        centred = uv - uv.mean(axis=0)
        axis = np.linalg.svd(centred, full_matrices=False)[2][0]
        along = np.floor(centred @ axis).astype(np.int64)
        i = frame_of.get(t)
        if i is None:
            det = np.zeros((0, 2))
        else:
            a, b = int(s["offsets"][i]), int(s["offsets"][i + 1])
            det = np.column_stack([s["u"][a:b], s["v"][a:b]])
        hit = (cKDTree(det).query(uv, k=1)[0] <= 1.5) if len(det) else np.zeros(len(uv), bool)
        bins = np.unique(along)
        bins_found = np.unique(along[hit])
        visible += len(bins)
        found += len(bins_found)
        per_frame.append(len(bins_found) / len(bins))
    recall = found / visible if visible else float("nan")
    return {"mask_iou_min": float(min(ious)), "mask_iou_mean": float(np.mean(ious)),
            "stripe_median_mm": float(np.median(d_mm)),
            "stripe_p95_mm": float(np.percentile(d_mm, 95)),
            "stripe_outlier_fraction": float(np.mean(d_mm > 1.0)),
            "stripe_points": int(len(d_mm)), "stripe_recall": float(recall),
            "triangulated_median_mm": float(np.median(d_raw)),
            "triangulated_p95_mm": float(np.percentile(d_raw, 95)),
            "triangulated_outlier_fraction": float(np.mean(d_raw > 1.0)),
            "triangulated_points": int(len(d_raw)),
            "stripe_recall_worst_frame": float(min(per_frame)) if per_frame else None,
            "visible_bins": int(visible), "found_bins": int(found)}


# --------------------------------------------------------------------------- drift
def part_drift(base: Path, reuse: bool) -> dict[str, Any]:
    from robo3d.simulate import DEMOS, SimulationParams, simulate_recording

    name = "drift_block"
    work = base / name
    obj, demo = DEMOS["dimple_block"]
    rec_path = _simulated(base, name, lambda p: simulate_recording(
        p, obj, params=SimulationParams(**{**demo, **DRIFT}), threads=0))
    if not _prepared(work, reuse):
        print(f"== {name}: the demo block with drifting robot error and a clock "
              f"{DRIFT['clock_lag_ms']:g} ms late, workflow ...", flush=True)
        e2e = run_workflow(rec_path, work)
        (work / "done.json").write_text(json.dumps({"end_to_end_s": e2e}))
    res = work / "results" / name
    e2e = json.loads((work / "done.json").read_text())["end_to_end_s"]
    m = json.loads((res / "metrics.json").read_text())
    ev = m["evaluation"]
    p = ev["poses"]
    out = {"end_to_end_s": e2e,
           **{f"pose_err_{k}_{u}": p[f"worst_{k}_frame_{u}"]
              for k in ("before", "after") for u in ("mm", "deg")},
           "per_sweep": p["per_sweep_frames"], "limits": view_pose_limits(rec_path, res),
           "mesh_median_mm": ev["mesh"]["median_mm"], "mesh_p95_mm": ev["mesh"]["p95_mm"],
           "completeness_0_5mm": ev["mesh"]["completeness"]["within_mm"]["0.5"],
           "aligned_median_mm": ev["aligned"]["median_mm"],
           "raw_median_mm": ev["clouds"]["median_mm"],
           "workflow_pose_errors": {k: v for k, v in p.items() if k.startswith("worst")}}
    print(f"   {name}: worst sweep (worst frame) {out['pose_err_before_mm']:.3f} mm "
          f"{out['pose_err_before_deg']:.4f} deg -> {out['pose_err_after_mm']:.4f} mm "
          f"{out['pose_err_after_deg']:.4f} deg; mesh median {out['mesh_median_mm']:.4f} "
          f"p95 {out['mesh_p95_mm']:.4f} mm, complete {out['completeness_0_5mm']:.4f}",
          flush=True)
    return out


def view_pose_limits(rec_path: Path, res: Path) -> dict[str, Any]:
    """What limits the absolute position: the silhouette views (the refinement's absolute
    reference) carry pose errors of their own; their mean at the object is a bias that no
    alignment against them can remove."""
    from robo3d.artefacts import load_clouds_npz
    from robo3d.recording.reader import read_recording
    from robo3d.simulate import image_poses
    from robo3d.transforms import invert_transform, rotation_angle_deg

    rec = read_recording(rec_path)
    views = sorted(rec.views, key=lambda m: m.timestamp_ns)
    if not views:
        return {}
    centre = _in_box(load_clouds_npz(res / "clouds.npz")).mean(axis=0)
    truth = [e["T_base_camera"] for e in image_poses(rec)["/camera/image"]]
    disp, deg = [], []
    for A, B in zip(rec.camera_poses(views), truth, strict=True):
        D = A @ invert_transform(B)
        disp.append((D[:3, :3] @ centre + D[:3, 3] - centre) * 1e3)
        deg.append(float(rotation_angle_deg(D[:3, :3])))
    disp = np.asarray(disp)
    return {"views_mean_displacement_mm": disp.mean(axis=0).round(4).tolist(),
            "views_mean_displacement_norm_mm": float(np.linalg.norm(disp.mean(axis=0))),
            "views_rms_displacement_mm": float(np.sqrt((disp**2).sum(axis=1).mean())),
            "views_max_deg": max(deg)}


# --------------------------------------------------------------------------- srv, speed
def part_srv() -> dict[str, Any]:
    import laser

    path = REAL / "srv_laser_calibration.mcap"
    if not path.exists():
        return {"skipped": f"{path} not found"}
    return laser.srv_board_figures(path, log=lambda *a, **k: None)


def part_speed() -> dict[str, Any]:
    import laser

    return laser.ambient_speed(log=lambda *a, **k: None)


# --------------------------------------------------------------------------- main
def _print_flat(d: dict[str, Any]) -> None:
    print("   " + json.dumps({k: v for k, v in d.items() if not isinstance(v, (list, dict))}),
          flush=True)


def _check(key: str, value: Any) -> bool | None:
    from common import check_target

    return check_target(TARGETS, key, value)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", default=None, help="keep the work folders under this folder")
    ap.add_argument("--reuse", action="store_true", help="with --keep: reuse finished runs")
    ap.add_argument("--only", default="dtu,cells,srv,drift,speed",
                    help="comma-separated parts (dtu, cells, srv, drift, speed, speckle)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "front_end.json"))
    args = ap.parse_args()
    parts = set(args.only.split(","))
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="robo3d-fe-"))
    base.mkdir(parents=True, exist_ok=True)
    out_path = Path(args.out)
    old = previous_results(out_path)
    details: dict[str, Any] = dict(old.get("details", {}))
    if "dtu" in parts:
        print("== dtu_scan24 (real) ...", flush=True)
        details["dtu"] = part_dtu(base, args.reuse)
    if "cells" in parts:
        details["cells"] = part_cells(base, args.reuse)
    if "speckle" in parts:
        details["speckle"] = part_cells(base, args.reuse, SPECKLE)
    if "srv" in parts:
        print("== srv_laser_calibration (real) ...", flush=True)
        details["srv"] = part_srv()
        _print_flat(details["srv"])
    if "drift" in parts:
        details["drift"] = part_drift(base, args.reuse)
    if "speed" in parts:
        print("== speed, ambient-lit 1280x960 ...", flush=True)
        details["speed"] = part_speed()
        _print_flat(details["speed"])

    def get(part: str, key: str) -> Any:
        return details.get(part, {}).get(key)

    coloured = {k: v for k, v in details.get("cells", {}).items() if k in CELLS}
    res: dict[str, Any] = {
        "dtu24_mask_iou_mean": get("dtu", "mask_iou_mean"),
        "dtu24_mask_iou_min": get("dtu", "mask_iou_min"),
        "sim_mask_iou_min": min((c["mask_iou_min"] for c in coloured.values()), default=None),
        "stripe_median_mm": {k: c["stripe_median_mm"] for k, c in coloured.items()},
        "stripe_p95_mm": {k: c["stripe_p95_mm"] for k, c in coloured.items()},
        "stripe_recall_min": min((c["stripe_recall"] for c in coloured.values()),
                                 default=None),
        "stripe_outlier_fraction": max((c["stripe_outlier_fraction"]
                                        for c in coloured.values()), default=None),
        "srv_board_plane_rms_mm": get("srv", "srv_board_plane_rms_mm"),
        "pose_err_after_mm": get("drift", "pose_err_after_mm"),
        "pose_err_after_deg": get("drift", "pose_err_after_deg"),
        "mesh_median_mm": get("drift", "mesh_median_mm"),
        "mesh_p95_mm": get("drift", "mesh_p95_mm"),
        "completeness_0_5mm": get("drift", "completeness_0_5mm"),
        "fps_ambient_1280x960": get("speed", "fps_ambient_1280x960"),
        # the issue asks for both JPEG and PNG: the worse of the two
        "stage_over_decode_ambient": max((x for x in (
            get("speed", "stage_over_decode_ambient"),
            get("speed", "stage_over_decode_ambient_jpeg")) if x is not None), default=None),
    }
    checks = {}
    for k, v in res.items():
        if isinstance(v, dict):
            checks[k] = {c: _check(k, x) for c, x in v.items()}
        else:
            checks[k] = _check(k, v)
    res["targets"] = {k: f"{op} {b}" for k, (op, b) in TARGETS.items()}
    res["met"] = checks
    res["notes"] = old.get("notes", "")
    res["details"] = details
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(res, indent=2) + "\n")
    print("\n== figures (target, met)")
    for k in TARGETS:
        v = res.get(k)
        print(f"   {k:28s} {json.dumps(v):40s} {' '.join(TARGETS[k][0:1])} {TARGETS[k][1]:<8g}"
              f" {checks.get(k)}")
    print(f"\nwrote {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
