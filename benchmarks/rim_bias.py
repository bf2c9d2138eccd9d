"""Where the alignment's silhouette term puts its zero, measured at the TRUE poses of a
simulated recording (a diagnostic of issue 11; stop 28 in ``benchmarks/README.md``).

Run from the repository root, on a recording and the results folder of a finished run
(``<work>/results/<stem>``, e.g. one that ``objects.py --keep`` kept)::

    .venv/bin/python benchmarks/rim_bias.py REC.mcap RESULTS_DIR [REC.mcap RESULTS_DIR ...]
    .venv/bin/python benchmarks/rim_bias.py --objects /tmp/obj      # every run objects.py kept

Each sweep's points are moved to where they truly are: every laser frame's points by the
true camera pose at its exposure (``ground_truth/image_poses.json``) times the inverse of
the reported one (``stripes.npz``). The silhouette term's contour residuals
(:func:`robo3d.registration._rim_residuals`, the most outward of all sweeps, as the
alignment takes them) are then split in two along each residual's search line:

- ``point``: the contour point's distance beyond the TRUE outline (negative: inside). The
  outline is where rays cast every 0.02 px along the line stop hitting the true mesh.
- ``edge_inside``: how far inside the true outline the image edge was detected.

The residual is ``point + edge_inside`` (px, outward positive). The points are those the
refinement meets the edges with: moved toward their fit along the profiles where they
scatter (:func:`robo3d.registration._rim_points`, stop 64; each sweep's scatter and share
printed). Both are printed by the
side the contour faces and by how nearly edge-on the surface is seen there
(``|n . ray|``). ``--out FILE`` writes them as JSON. Nothing is scored against a target:
this says what a change to the term would have to correct.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))
from common import laser_frame_poses  # noqa: E402 (after the path setup)

STEP_PX = 0.02
COS_BINS = (0.0, 0.03, 0.06, 0.09, 0.12, 0.15)


def true_points(rec, res: Path) -> tuple[list, list, list, list]:
    """The sweeps' points at their true places, their normals (rotated alike), and the
    profile keys, from ``clouds.npz`` and ``stripes.npz``."""
    from robo3d.artefacts import load_clouds_npz

    clouds = load_clouds_npz(res / "clouds.npz")
    T_true, T_rep = laser_frame_poses(rec, res)
    if len(T_true) != len(T_rep):
        raise SystemExit(f"{rec.path}: {len(T_true)} true laser poses, {len(T_rep)} frames")
    C = T_true @ np.linalg.inv(T_rep)  # the frame's correction, base -> base
    pts, nrm, prof = [], [], []
    for c in clouds:
        f = np.asarray(c.frame_index, dtype=np.int64)
        R, t = C[f, :3, :3], C[f, :3, 3]
        pts.append(np.einsum("nij,nj->ni", R, c.points_base) + t)
        nrm.append(np.einsum("nij,nj->ni", R, c.normals_base))
        prof.append(f)
    return pts, nrm, prof, [c.sweep for c in clouds]


def decompose(rec_path: Path, res: Path) -> dict[str, Any]:
    """The contour residuals at the true poses and their two parts (see the module)."""
    import robo3d.registration as RG
    from robo3d.config import default_config
    from robo3d.recording.reader import read_recording
    from robo3d.simulate import truth_scene
    from robo3d.stages.common import silhouette_views

    rec = read_recording(str(rec_path))
    views = silhouette_views({"silhouettes": str(res / "silhouettes.npz"),
                              "recording": str(rec_path)}, default_config())
    pts, nrm, prof, _ = true_points(rec, res)
    scene = truth_scene(rec)
    fields = RG._view_fields(views, RG._RIM_CELL_PX, 0.7)
    # the points the term meets the edges with, as the refinement takes them (noisy
    # profiles moved toward their fit: registration._rim_points)
    noise = [RG._profile_scatter(p, n, np.asarray(g)) for p, n, g in zip(pts, nrm, prof,
                                                                         strict=True)]
    full = [(p, np.asarray(g), np.arange(len(p))) for p, g in zip(pts, prof, strict=True)]
    pts, fit_info = RG._rim_points(pts, full, noise, fields)
    s_line = np.arange(-5.0, 5.0 + STEP_PX / 2, STEP_PX)
    k0 = len(s_line) // 2
    rows = []
    for vi, f in enumerate(fields):
        found = []
        for s in range(len(pts)):
            idx, r, jac, scl, cell = RG._rim_residuals(f, pts[s], nrm[s], prof[s], **RG._RIM)
            ok = np.abs(r) < 4
            if ok.any():
                found.append((s, idx[ok], r[ok], jac[ok], scl[ok], cell[ok]))
        T = views.T_base_camera[vi]
        centre = T[:3, 3]
        for s, idx, r, _, _ in RG._outermost_across_sweeps(found, RG._RIM_CROSS_TOL_PX):
            x, n = pts[s][idx], nrm[s][idx]
            uv, _ = RG._project(f, x)
            uv_n, _ = RG._project(f, x + 1e-4 * n)
            m = uv_n - uv
            m /= np.linalg.norm(m, axis=1, keepdims=True)
            q = uv[:, None, :] + s_line[None, :, None] * m[:, None, :]
            d = f.camera.rays(q.reshape(-1, 2)) @ T[:3, :3].T
            obj = (scene.cast(centre, d, normals=False).kind == 1).reshape(len(idx), -1)
            # the true outline: the first sample off the object outward from the point
            # (from the point's own sample when it is on the object, else from the
            # outermost object sample inside it)
            out_from = np.where(obj[:, k0], k0, 0)
            off = ~obj & (np.arange(len(s_line))[None, :] >= out_from[:, None])
            inner = obj[:, :k0]
            has_inner = inner.any(axis=1)
            last_inner = k0 - 1 - np.argmax(inner[:, ::-1], axis=1)
            edge = np.where(obj[:, k0],
                            np.where(off.any(axis=1), s_line[np.argmax(off, axis=1)] - STEP_PX / 2,
                                     np.nan),
                            np.where(has_inner, s_line[last_inner] + STEP_PX / 2, np.nan))
            ray = x - centre
            ray /= np.linalg.norm(ray, axis=1, keepdims=True)
            cos = np.abs(np.einsum("ij,ij->i", ray, n))
            rows.append(np.c_[r, -edge, n, cos])
    a = np.concatenate(rows) if rows else np.zeros((0, 6))
    a = a[np.isfinite(a[:, 1])]
    r, point, n, cos = a[:, 0], a[:, 1], a[:, 2:5], a[:, 5]
    edge_inside = r - point

    def stats(sel: np.ndarray) -> dict[str, Any]:
        if sel.sum() < 3:
            return {"n": int(sel.sum())}
        return {"n": int(sel.sum()), "residual_median_px": float(np.median(r[sel])),
                "point_median_px": float(np.median(point[sel])),
                "edge_inside_median_px": float(np.median(edge_inside[sel])),
                "edge_inside_mean_px": float(np.mean(edge_inside[sel]))}

    sides = {name: stats(sel) for name, sel in (
        ("+x", n[:, 0] > 0.7), ("-x", n[:, 0] < -0.7), ("+y", n[:, 1] > 0.7),
        ("-y", n[:, 1] < -0.7), ("+z", n[:, 2] > 0.7), ("oblique", np.abs(n).max(1) <= 0.7))}
    bins = {f"{lo:.2f}-{hi:.2f}": stats((cos >= lo) & (cos < hi))
            for lo, hi in zip(COS_BINS[:-1], COS_BINS[1:], strict=True)}
    return {"recording": rec_path.name, "all": stats(np.ones(len(r), bool)),
            "by_side": sides, "by_abs_n_dot_ray": bins, "rim_points": fit_info}


def _print(d: dict[str, Any]) -> None:
    def line(name: str, s: dict[str, Any]) -> str:
        if "point_median_px" not in s:
            return f"  {name:>10s}: n {s['n']}"
        return (f"  {name:>10s}: n {s['n']:5d}  residual {s['residual_median_px']:+.3f}  "
                f"point {s['point_median_px']:+.3f}  edge inside {s['edge_inside_median_px']:+.3f}")
    print(f"== {d['recording']} (median px at the true poses; each sweep's scatter about "
          "its profiles, px, and how far its points were moved toward their fit: "
          + ", ".join(f"{e['profile_noise_px']} / {e['rim_fit_share']}" for e in d["rim_points"])
          + ")")
    print(line("all", d["all"]))
    for k, s in d["by_side"].items():
        print(line(f"n {k}", s))
    for k, s in d["by_abs_n_dot_ray"].items():
        print(line(f"|n.r| {k}", s))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pairs", nargs="*", help="REC.mcap RESULTS_DIR, repeated")
    ap.add_argument("--objects", help="an objects.py --keep folder: every run it kept")
    ap.add_argument("--out", help="write the figures as JSON here")
    args = ap.parse_args()
    pairs = [(Path(a), Path(b)) for a, b in zip(args.pairs[::2], args.pairs[1::2], strict=True)]
    if args.objects:
        base = Path(args.objects)
        for rec in sorted((base / "recordings").glob("*.mcap")):
            res = base / "work" / rec.stem / "results" / rec.stem
            if (res / "clouds.npz").exists():
                pairs.append((rec, res))
    if not pairs:
        ap.error("no recording given")
    out = []
    for rec, res in pairs:
        d = decompose(rec, res)
        _print(d)
        out.append(d)
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
