"""evaluate: distances, sampling, completeness, volume IoU and pose errors against
analytic spheres."""

from __future__ import annotations

import numpy as np
import pytest

from robo3d.evaluate import (
    TruthSurface,
    cloud_accuracy,
    completeness,
    distance_stats,
    mesh_accuracy,
    pose_error,
    sample_surface,
    volume_iou,
)
from robo3d.transforms import euler_to_matrix, make_transform

R = 0.03
C = np.array([0.5, 0.1, 0.08])


def icosphere(radius=R, centre=C, subdivisions=4):
    """Vertices on the sphere; returns (V, F, sagitta), sagitta = largest gap between a
    face's plane and the sphere."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_midpoint(subdivisions)
    v = np.asarray(m.vertices)
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    f = np.asarray(m.triangles).astype(np.int64)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    plane_dist = np.abs(np.einsum("ij,ij->i", n / np.linalg.norm(n, axis=1, keepdims=True),
                                  v[f[:, 0]]))
    sag = radius * (1.0 - plane_dist.min())
    return v * radius + centre, f, sag


@pytest.fixture(scope="module")
def sphere():
    v, f, sag = icosphere()
    return TruthSurface(v, f), v, f, sag


def _directions(n, seed):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_distance_matches_analytic(sphere):
    truth, _, _, sag = sphere
    assert sag < 0.05e-3  # the polyhedron is within 50 um of the sphere
    d = _directions(5000, 0)
    off = np.random.default_rng(1).uniform(-5e-3, 5e-3, 5000)
    pts = C + d * (R + off)[:, None]
    dist = truth.distance(pts)
    assert dist.shape == (5000,) and dist.dtype == np.float64
    # the polyhedron lies between the sphere and the sphere shrunk by sag
    lo = np.where(off >= 0, off, np.maximum(-off - sag, 0.0))
    hi = np.where(off >= 0, off + sag, np.maximum(-off, sag + off))
    assert np.all(dist >= lo - 2e-7) and np.all(dist <= hi + 2e-7)


def test_inside(sphere):
    truth, *_, sag = sphere
    d = _directions(4000, 2)
    inner = C + d * (R - sag - 0.2e-3)
    outer = C + d * (R + 0.2e-3)
    assert truth.inside(inner).all()
    assert not truth.inside(outer).any()
    assert truth.inside(C[None]).all()


def test_sample_is_uniform_and_seeded(sphere):
    truth, v, f, sag = sphere
    s = truth.sample(20000, seed=3)
    assert s.shape == (20000, 3)
    r = np.linalg.norm(s - C, axis=1)
    assert np.all(r <= R + 1e-12) and np.all(r >= R - sag - 1e-12)
    # Archimedes: a slab of height h holds h / (2R) of a sphere's area
    z = s[:, 2] - C[2]
    frac = np.mean((z > -0.3 * R) & (z < 0.5 * R))
    assert frac == pytest.approx(0.4, abs=0.015)  # 3 sigma = 0.0104
    np.testing.assert_array_equal(s, truth.sample(20000, seed=3))
    assert not np.array_equal(s, truth.sample(20000, seed=4))
    assert sample_surface(v, f[:0], 10).shape == (0, 3)


def test_distance_stats():
    st = distance_stats(np.array([1e-3, 2e-3, 3e-3, 4e-3]))
    assert st["mean_mm"] == pytest.approx(2.5)
    assert st["median_mm"] == pytest.approx(2.5)
    assert st["max_mm"] == pytest.approx(4.0)
    assert st["rms_mm"] == pytest.approx(np.sqrt(7.5))
    assert st["p95_mm"] == pytest.approx(3.85)
    assert st["n"] == 4
    empty = distance_stats(np.zeros(0))
    assert empty["n"] == 0 and empty["mean_mm"] is None
    with pytest.raises(ValueError, match="non-finite"):
        distance_stats(np.array([np.inf]))


def test_cloud_and_mesh_accuracy(sphere):
    truth, v, f, sag = sphere
    pts = C + _directions(3000, 5) * (R + 0.2e-3)
    acc = cloud_accuracy(pts, truth)
    assert acc["mean_mm"] == pytest.approx(0.2, abs=sag * 1e3 + 1e-3)
    assert acc["within_mm"] == {"0.1": 0.0, "0.5": 1.0, "1": 1.0}
    # a sphere mesh 0.5 mm too big
    big = C + (v - C) * (R + 0.5e-3) / R
    m = mesh_accuracy(big, f, truth, n_samples=20000)
    assert 0.5 - 0.1 < m["mean_mm"] < 0.5 + sag * 1e3 + 0.01
    assert m["n"] == 20000
    same = mesh_accuracy(v, f, truth, n_samples=5000)
    assert same["max_mm"] < 1e-3


def test_completeness_of_half_sphere(sphere):
    truth, v, f, _ = sphere
    centroid_z = v[f].mean(axis=1)[:, 2]
    upper = f[centroid_z > C[2]]
    comp = completeness(v, upper, truth, n_samples=40000, seed=1)
    for t in ("0.1", "0.5", "1"):
        assert comp["within_mm"][t] == pytest.approx(0.5, abs=0.02)
    assert comp["n_samples"] == 40000
    # counting only the upper half (the region box), the upper half is complete
    # (above the zig-zag border of the kept triangles, one edge ~2 mm high)
    box = (np.array([C[0] - 1.01 * R, C[1] - 1.01 * R, C[2] + 3e-3]), C + 1.01 * R)
    comp_box = completeness(v, upper, truth, n_samples=40000, region=box)
    assert comp_box["within_mm"]["0.1"] == 1.0
    assert comp_box["n_samples"] == pytest.approx(40000 * (R - 3e-3) / (2 * R), rel=0.03)
    # nothing reconstructed
    empty = completeness(v[:0], f[:0], truth, n_samples=100)
    assert empty["within_mm"]["0.5"] == 0.0 and empty["distance"]["n"] == 0


def _iou_spheres(d):
    v = 4 / 3 * np.pi * R**3
    inter = np.pi * (4 * R + d) * (2 * R - d) ** 2 / 12
    return inter / (2 * v - inter)


def test_volume_iou(sphere):
    truth, *_ = sphere
    vs = 1e-3
    origin = C - 0.04
    idx = np.indices((81, 81, 81)).reshape(3, -1).T
    centres = origin + idx * vs
    occ = (np.linalg.norm(centres - C, axis=1) < R).reshape(81, 81, 81)
    assert volume_iou(occ, origin, vs, truth) > 0.99
    shift = 6e-3
    occ_shift = (np.linalg.norm(centres - C - [shift, 0, 0], axis=1) < R).reshape(occ.shape)
    iou = volume_iou(occ_shift, origin, vs, truth)
    assert iou == pytest.approx(_iou_spheres(shift), abs=0.01)
    assert iou < 0.9
    # the region: only the upper half counts; the vertical shift cancels nothing there
    region = (C - [0.05, 0.05, 0.0], C + 0.05)
    assert volume_iou(occ, origin, vs, truth, region=region) > 0.99
    assert volume_iou(np.zeros_like(occ), origin, vs, truth) == 0.0
    with pytest.raises(ValueError, match="bool"):
        volume_iou(occ.astype(np.uint8), origin, vs, truth)


def test_pose_error():
    a = make_transform(euler_to_matrix("zyx", np.radians([10.0, 5.0, -3.0])), [0.4, 0.1, 0.3])
    rot = euler_to_matrix("zyx", [0.0, 0.0, np.radians(2.0)])
    b = a @ make_transform(rot, [0.0, 0.0, 0.0])
    b[:3, 3] += [0.003, 0.0, -0.004]
    t, r = pose_error(b, a)
    assert t == pytest.approx(5.0)
    assert r == pytest.approx(2.0)
    tt, rr = pose_error(np.stack([a, b]), np.stack([a, a]))
    np.testing.assert_allclose(tt, [0.0, 5.0], atol=1e-9)
    np.testing.assert_allclose(rr, [0.0, 2.0], atol=1e-5)
    with pytest.raises(ValueError, match="4, 4"):
        pose_error(np.eye(3), np.eye(3))


def test_bad_inputs(sphere):
    truth, v, f, _ = sphere
    with pytest.raises(ValueError, match="no faces"):
        TruthSurface(v, f[:0])
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        truth.distance(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="region"):
        completeness(v, f, truth, region=(C, C))
    with pytest.raises(ValueError, match="faces index"):
        mesh_accuracy(v, f + len(v), truth)


def test_mesh_accuracy_in_a_region(sphere):
    """Only the reconstruction inside the region is scored (e.g. above the closure of the
    face on the table): a lower half pushed 1 mm out does not count when cut away."""
    truth, v, f, sag = sphere
    bad = v.copy()
    low = bad[:, 2] < C[2]
    bad[low] = C + (bad[low] - C) * (R + 1e-3) / R
    whole = mesh_accuracy(bad, f, truth, n_samples=20000)
    box = (C - 1.1 * R + np.array([0, 0, 1.1 * R + 2e-3]), C + 1.1 * R)
    upper = mesh_accuracy(bad, f, truth, n_samples=20000, region=box)
    assert whole["p95_mm"] > 0.9
    assert upper["max_mm"] < sag * 1e3 + 1e-3
    assert upper["fraction_scored"] == pytest.approx((R - 2e-3) / (2 * R), abs=0.03)


def test_batch_table(tmp_path):
    import json

    from robo3d.evaluate import batch_rows, write_batch_table

    m1 = {"name": "a", "evaluation": {"hull_volume_iou": 0.9, "mesh": {
        "median_mm": 0.02, "p95_mm": 0.1, "completeness": {"within_mm": {"0.5": 0.99}}},
        "poses": {"worst_before_obj_mm": 1.2, "worst_before_deg": 0.3,
                  "worst_after_obj_mm": 0.04, "worst_after_mm": 0.1, "worst_after_deg": 0.02}},
        "surface_sources": {"laser_area_fraction": 0.8},
        "stages": {"simplify": {"faces_out": 20000, "hausdorff_max_m": 1e-4}},
        "timings": {"fuse": {"seconds": 7.0, "max_rss_mb": 500.0}, "total_seconds": 40.0}}
    m2 = {"name": "b", "skipped": {"evaluation": "no ground truth"}}
    rows = batch_rows([m1, m2])
    assert rows[0]["recording"] == "a" and rows[0]["complete_0.5mm"] == 0.99
    assert rows[0]["hausdorff_mm"] == pytest.approx(0.1) and rows[0]["fuse_mb"] == 500.0
    assert rows[1]["mesh_median_mm"] is None and rows[1]["fuse_s"] is None
    paths = []
    for k, m in enumerate((m1, m2)):
        p = tmp_path / f"m{k}.json"
        p.write_text(json.dumps(m))
        paths.append(str(p))
    write_batch_table(paths, str(tmp_path / "b.tsv"), str(tmp_path / "b.html"))
    lines = (tmp_path / "b.tsv").read_text().splitlines()
    assert len(lines) == 3 and lines[0].startswith("recording\thull_iou")
    assert lines[2].split("\t")[0] == "b"
    html = (tmp_path / "b.html").read_text()
    assert "<table>" in html and "2 recording(s)" in html


# ---------------------------------------------------------------------- mask IoU
def _png(mask: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255)
    assert ok
    return buf.tobytes()


def _disc(h, w, cx, cy, r):
    yy, xx = np.mgrid[0:h, 0:w]
    return np.hypot(xx - cx, yy - cy) <= r


def test_silhouette_iou_scores_good_and_skips_bad_attachments():
    """Exact IoUs where the truth is usable; a damaged, resized, 16-bit, missing or
    unmatched attachment is skipped with its reason, never stopping the rest."""
    import cv2

    from robo3d.evaluate import TRUE_SILHOUETTES, silhouette_iou

    h, w = 60, 80
    truth = [_disc(h, w, 40, 30, 15) for _ in range(7)]
    masks = [t.copy() for t in truth]
    masks[1] = np.roll(truth[1], 4, axis=1)  # shifted by 4 px
    masks[2][:] = False  # empty
    att = {f"{TRUE_SILHOUETTES}{i:03d}.png": _png(t) for i, t in enumerate(truth)}
    att[f"{TRUE_SILHOUETTES}003.png"] = b"\x89PNG not really"
    att[f"{TRUE_SILHOUETTES}004.png"] = _png(np.zeros((h + 1, w), bool))
    att[f"{TRUE_SILHOUETTES}005.png"] = cv2.imencode(".png", truth[5].astype(np.uint16) * 999
                                                     )[1].tobytes()
    del att[f"{TRUE_SILHOUETTES}006.png"]
    att[f"{TRUE_SILHOUETTES}009.png"] = _png(truth[0])
    att[f"{TRUE_SILHOUETTES}notes.txt"] = b"x"
    att["ground_truth/mesh.ply"] = b"unrelated"
    colour = cv2.cvtColor(truth[0].astype(np.uint8) * 200, cv2.COLOR_GRAY2BGR)
    att[f"{TRUE_SILHOUETTES}000.png"] = cv2.imencode(".png", colour)[1].tobytes()
    r = silhouette_iou(masks, att)
    shifted = np.count_nonzero(masks[1] & truth[1]) / np.count_nonzero(masks[1] | truth[1])
    assert r["per_view"][0]["iou"] == 1.0  # a grey mask saved as colour is accepted
    assert r["per_view"][1]["iou"] == pytest.approx(shifted) and 0.7 < shifted < 0.9
    assert r["per_view"][2]["iou"] == 0.0 and r["per_view"][2]["missed_px"] == truth[2].sum()
    assert "does not decode" in r["skipped"]["3"]
    assert r["skipped"]["4"] == "is 80x61 px, the view is 80x60"
    assert "8-bit" in r["skipped"]["5"]
    assert r["skipped"]["6"] == "no ground_truth/silhouettes/006.png"
    assert [v["iou"] for v in r["per_view"][3:]] == [None] * 4
    assert set(r["unmatched"]) == {f"{TRUE_SILHOUETTES}009.png", f"{TRUE_SILHOUETTES}notes.txt"}
    assert r["n_scored"] == 3 and r["n_views"] == 7 and r["n_truth"] == 6
    assert r["mean"] == pytest.approx((1.0 + shifted + 0.0) / 3)
    assert r["min"] == 0.0 and r["worst_view"] == 2
    none = silhouette_iou(masks, {})
    assert none["mean"] is None and none["n_scored"] == 0 and len(none["skipped"]) == 7


def _sphere_recording(path, tmp, *, damage_mesh=True):
    """A views-only recording of a bright sphere on black, 8 views written out of time
    order, with the true silhouettes attached in time order (view 2's damaged) and a
    damaged ground_truth/mesh.ply."""
    from robo3d.camera import CameraModel, pixel_rays
    from robo3d.recording.writer import RecordingWriter
    from robo3d.sim.rig import look_at

    centre, radius = np.array([0.0, 0.0, 0.05]), 0.04
    cam = CameraModel("camera", 120, 90, [[110, 0, 59.5], [0, 110, 44.5], [0, 0, 1]])
    t0 = 1_700_000_000_000_000_000
    views = []
    for i in range(8):
        a = 2 * np.pi * i / 8
        # each view aimed a little lower: the sphere 3 px higher in the image per view,
        # so that a view matched to another's true silhouette scores IoU < 0.8
        T = look_at(centre + 0.35 * np.array([np.cos(a), np.sin(a), 0.6 * (-1) ** i]),
                    centre - [0.0, 0.0, 0.012 * (i - 3.5)])
        v, u = np.mgrid[0:cam.height, 0:cam.width]
        o, d = pixel_rays(np.stack([u.ravel(), v.ravel()], 1).astype(float), cam, T)
        oc = o - centre
        b = d @ oc
        disc = b * b - (oc @ oc - radius**2)
        hit = (disc >= 0) & (-b - np.sqrt(np.maximum(disc, 0.0)) > 0)
        views.append((T, hit.reshape(cam.height, cam.width)))
    with RecordingWriter(path) as w:
        w.add_metadata("robo3d.recording", {"kind": "scan", "object": "sphere", "units": "m"})
        w.write_calibration("/camera/calibration", t0, cam)
        w.write_transforms("/tf_static", t0, [("flange", "camera", np.eye(4))])
        for i in (3, 0, 7, 1, 5, 2, 6, 4):  # out of time order on the topic
            T, sil = views[i]
            t = t0 + (i + 1) * 1_000_000_000
            for dt in (-20_000_000, 20_000_000):
                w.write_transforms("/tf", t + dt, [("base", "flange", T)])
            img = np.where(sil, 220, 12).astype(np.uint8)
            w.write_image("/camera/image", t, "camera", np.dstack([img] * 3), "png")
        for i, (_T, sil) in enumerate(views):
            w.add_attachment(f"ground_truth/silhouettes/{i:03d}.png",
                             b"\x89PNG\r\n damaged" if i == 2 else _png(sil), "image/png")
        if damage_mesh:
            w.add_attachment("ground_truth/mesh.ply", b"ply\nformat nonsense\n")
    return cam, views


def test_stage_evaluate_reports_mask_iou_and_skips_damaged_attachments(tmp_path):
    """End to end on a recording with true silhouettes: the views are matched to
    ``NNN.png`` by time order (the file holds them out of order), the damaged mask and
    the damaged mesh are skipped with their reasons, every other view is scored."""
    import json

    from robo3d.config import load_config
    from robo3d.pipeline import stage_carve, stage_evaluate, stage_silhouettes

    rec = tmp_path / "sphere.mcap"
    _sphere_recording(rec, tmp_path)
    res = tmp_path / "results"
    (res / "reports").mkdir(parents=True)
    cfg = load_config(overrides={"carving": {"resolution": 32, "qa_resolution": 24}})
    stage_silhouettes({"recording": str(rec)},
                      {"npz": str(res / "silhouettes.npz"), "rrd": str(res / "s.rrd"),
                       "report": str(res / "reports/silhouettes.json")}, cfg, "sphere")
    stage_carve({"silhouettes": str(res / "silhouettes.npz")},
                {"npz": str(res / "hull.npz"), "ply": str(res / "hull.ply"),
                 "report": str(res / "reports/carve.json"), "rrd": str(res / "c.rrd")},
                cfg, "sphere")
    metrics = stage_evaluate({"recording": str(rec), "hull": str(res / "hull.npz"),
                              "mesh": str(res / "hull.ply"), "fused": str(res / "hull.ply")},
                             {"metrics": str(res / "metrics.json"),
                              "rrd": str(res / "e.rrd")}, cfg, "sphere")
    with open(res / "metrics.json", encoding="utf-8") as f:
        assert json.load(f)["evaluation"]["mask_iou"]["n_scored"] == 7
    mi = metrics["evaluation"]["mask_iou"]
    assert mi["n_views"] == 8 and mi["n_truth"] == 8 and mi["n_scored"] == 7
    assert "does not decode" in mi["skipped"]["2"]
    scored = [v for v in mi["per_view"] if v["iou"] is not None]
    assert all(v["iou"] > 0.9 for v in scored)  # matched in time order
    from robo3d.evaluate import silhouette_iou
    from robo3d.recording.reader import read_recording
    from robo3d.stages.common import load_silhouettes

    masks = list(load_silhouettes(str(res / "silhouettes.npz"))["masks"])
    off_by_one = silhouette_iou(masks[1:] + masks[:1], read_recording(rec, roles=()).attachments)
    assert off_by_one["mean"] < 0.8  # the test can tell a wrong order
    assert mi["min"] == min(v["iou"] for v in scored) and mi["mean"] >= mi["min"]
    assert metrics["skipped"]["surface_evaluation"].startswith("ground_truth/mesh.ply is "
                                                               "damaged")
    assert "evaluation" not in metrics["skipped"] and "mask_iou" not in metrics["skipped"]
    assert metrics["views_left_out"] == []
    assert all(v["left_out_of_carve"] is False for v in scored)
    from robo3d.evaluate import batch_rows

    row = batch_rows([metrics])[0]
    assert row["mask_iou_mean"] == mi["mean"] and row["mask_iou_min"] == mi["min"]
    assert row["views_left_out"] == 0


def test_frame_displacement_is_what_each_frames_error_does_to_its_points():
    """Frame 0 used a pose 0.1 mm off along x, frame 1 one turned by 0.02 degrees about z
    (its points 0.3 m from the axis move by 0.3 m * 0.02 deg), frame 2 the true pose."""
    from robo3d.evaluate import frame_displacement

    rng = np.random.default_rng(0)
    T_true = np.stack([make_transform(euler_to_matrix("xyz", rng.normal(size=3) * 0.3),
                                      rng.normal(size=3) * 0.1) for _ in range(3)])
    err = [make_transform(np.eye(3), [1e-4, 0, 0]),
           make_transform(euler_to_matrix("xyz", np.radians([0, 0, 0.02])), [0, 0, 0]),
           np.eye(4)]
    # T_used = E T_true, so the points placed with it are E times the true ones
    T_used = np.stack([e @ t for e, t in zip(err, T_true, strict=True)])
    true_pts = np.array([[0.3, 0.0, 0.1], [0.0, 0.3, -0.2], [0.1, 0.1, 0.1]])
    frame = np.array([0, 1, 2])
    placed = np.stack([(err[f] @ np.append(p, 1.0))[:3] for f, p in zip(frame, true_pts,
                                                                        strict=True)])
    disp, deg = frame_displacement(placed, frame, T_used, T_true)
    np.testing.assert_allclose(disp, [0.1, 0.3e3 * np.radians(0.02), 0.0], atol=1e-9)
    np.testing.assert_allclose(deg, [0.0, 0.02, 0.0], atol=1e-9)
    with pytest.raises(ValueError, match="frame_index"):
        frame_displacement(placed, np.array([0, 1, 3]), T_used, T_true)


