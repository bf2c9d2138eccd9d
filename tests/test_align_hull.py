"""The alignment stage's test of the laser points against the silhouettes: points
triangulated into empty space are dropped and counted, measured points are kept, and a
view whose mask contradicts the laser is not trusted (and named)."""

from __future__ import annotations

import numpy as np

from robo3d.artefacts import SweepCloud
from robo3d.camera import CameraModel, pixel_rays
from robo3d.config import default_config
from robo3d.registration import SilhouetteViews
from robo3d.sim.rig import look_at
from robo3d.stages.align import _reject_outside_hull, _views_agreement

CENTRE, RADIUS, F = np.array([0.0, 0.0, 0.1]), 0.04, 300.0


def ring_cameras(n: int, centre: np.ndarray, rise: float = 0.6):
    """A 240 x 180 camera (f = 300 px) at ``n`` poses on a ring around ``centre``, 0.35 m
    out and ``rise`` x 0.35 m up, looking at it: the camera and the poses."""
    cam = CameraModel("camera", 240, 180, [[F, 0, 119.5], [0, F, 89.5], [0, 0, 1]],
                      np.zeros(5))
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    eyes = centre + 0.35 * np.stack([np.cos(ang), np.sin(ang), np.full(n, rise)], 1)
    return cam, np.stack([look_at(e, centre) for e in eyes])


def _views(n: int = 10):
    cam, Ts = ring_cameras(n, CENTRE)
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    masks = []
    for T in Ts:
        o, d = pixel_rays(uv, cam, T)
        b = d @ (o - CENTRE)
        masks.append((b * b - ((o - CENTRE) @ (o - CENTRE) - RADIUS**2) >= 0)
                     .reshape(cam.height, cam.width))
    return cam, Ts, masks


def _cloud(points: np.ndarray, sweep: int) -> SweepCloud:
    n = len(points)
    return SweepCloud(points, np.tile([0.0, 0.0, 1.0], (n, 1)), np.arange(n) // 50,
                      np.ones(n), sweep, np.tile([0.0, 0.0, 0.5], (n, 1)))


def test_points_in_empty_space_are_dropped_and_counted(tmp_path):
    cam, Ts, masks = _views()
    rng = np.random.default_rng(0)
    d = rng.normal(size=(600, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = CENTRE + RADIUS * d[:500]
    space = CENTRE + (RADIUS + 0.008) * d[500:]  # 8 mm off the object
    clouds = [_cloud(np.concatenate([surface[:250], space[:60]]), 0),
              _cloud(np.concatenate([surface[250:], space[60:]]), 1)]
    bad = [m.copy() for m in masks]
    bad[3][:] = False  # a wrong (empty) mask: it would drop every point
    npz = tmp_path / "silhouettes.npz"
    np.savez(npz, qa_flagged=np.array([False] * 9 + [True]))  # the QA flagged view 9
    views = SilhouetteViews([m.astype(float) for m in bad], bad, [cam] * len(Ts), Ts)
    report, dropped = _reject_outside_hull(clouds, views, {"silhouettes": str(npz)},
                                           default_config()["alignment"])
    assert report["points"] == 600
    assert [s["dropped"] for s in report["per_sweep"]] == [60, 40]
    assert len(clouds[0]) == 250 and len(clouds[1]) == 250
    np.testing.assert_allclose(np.linalg.norm(np.concatenate(
        [c.points_base for c in clouds]) - CENTRE, axis=1), RADIUS)
    assert len(dropped) == 100
    assert [v["view"] for v in report["views_not_used_contradict_laser"]] == [3]
    assert report["views_not_used_qa_flagged"] == [9]
    assert report["views_used"] == 8
    assert clouds[0].report["dropped_outside_hull"] == 60
    # the arrays of a cloud stay consistent
    assert len(clouds[1].frame_index) == len(clouds[1].confidence) == 250


def test_without_views_or_when_off_nothing_is_dropped(tmp_path):
    cloud = _cloud(CENTRE + np.array([[1.0, 0.0, 0.0]]), 0)
    report, dropped = _reject_outside_hull([cloud], None, {}, default_config()["alignment"])
    assert "skipped" in report and len(dropped) == 0 and len(cloud) == 1
    cam, Ts, masks = _views(4)
    views = SilhouetteViews([m.astype(float) for m in masks], masks, [cam] * 4, Ts)
    off = {**default_config()["alignment"], "reject_outside_hull": False}
    report, dropped = _reject_outside_hull([cloud], views, {}, off)
    assert "skipped" in report and len(cloud) == 1


def test_masks_segmented_again_from_the_laser_do_not_judge_it(tmp_path):
    """Views whose first masks left many laser points outside and were segmented again
    from those points (``laser_seeded`` in silhouettes.npz): the masks of that recording
    drop no laser point (without the flag, the points 8 mm off are dropped)."""
    cam, Ts, masks = _views()
    rng = np.random.default_rng(2)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = np.concatenate([CENTRE + RADIUS * d[:250], CENTRE + (RADIUS + 0.008) * d[250:]])
    views = SilhouetteViews([m.astype(float) for m in masks], masks, [cam] * len(Ts), Ts)
    for seeded, dropped_expected in ((np.zeros(len(Ts), bool), 50),
                                     (np.eye(len(Ts), dtype=bool)[2], 0)):
        npz = tmp_path / "silhouettes.npz"
        np.savez(npz, qa_flagged=np.zeros(len(Ts), bool), laser_seeded=seeded)
        clouds = [_cloud(pts.copy(), 0)]
        report, dropped = _reject_outside_hull(clouds, views, {"silhouettes": str(npz)},
                                               default_config()["alignment"])
        assert report["dropped"] == dropped_expected and len(dropped) == dropped_expected
        if seeded.any():
            assert "skipped" in report and report["laser_seeded_views"] == [2]
            assert len(clouds[0]) == 300


def test_points_that_every_view_sees_outside_do_not_make_the_views_untrusted(tmp_path):
    """The table lit by the laser within the workspace: a third of the points, outside
    every silhouette. Each view would drop them all, but so would the others: every view
    stays trusted and the table's points are dropped (before, a view that would drop
    more than 10 % of the points was left out, so all were and the table was kept)."""
    cam, Ts, masks = _views()
    rng = np.random.default_rng(1)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = CENTRE + RADIUS * d
    xy = rng.uniform(-0.09, 0.09, size=(600, 2))
    xy = xy[np.linalg.norm(xy, axis=1) > RADIUS + 0.01][:200]
    table = np.column_stack([xy, np.full(len(xy), CENTRE[2] - 0.02)])
    clouds = [_cloud(np.concatenate([surface, table]), 0)]
    npz = tmp_path / "silhouettes.npz"
    np.savez(npz, qa_flagged=np.zeros(len(Ts), bool))
    views = SilhouetteViews([m.astype(float) for m in masks], masks, [cam] * len(Ts), Ts)
    report, dropped = _reject_outside_hull(clouds, views, {"silhouettes": str(npz)},
                                           default_config()["alignment"])
    assert len(table) == 200 and report["points"] == 600
    assert report["views_not_used_contradict_laser"] == [] and report["views_used"] == 10
    assert report["dropped"] == 200 and len(clouds[0]) == 400
    np.testing.assert_allclose(np.linalg.norm(clouds[0].points_base - CENTRE, axis=1), RADIUS)


def test_aligned_points_that_fell_below_the_floor_are_dropped_and_counted():
    """The triangulation cropped with the reported poses; after alignment the table's
    points lie below the workspace floor again: dropped, counted per sweep."""
    from robo3d.stages.align import _crop_to_workspace

    box = [[-0.05, -0.05, 0.0005], [0.05, 0.05, 0.06]]
    obj = np.column_stack([np.zeros(5), np.zeros(5), np.linspace(0.001, 0.05, 5)])
    table = np.array([[0.03, 0.0, 0.0001], [0.0, 0.03, -0.0002]])
    a, b = _cloud(np.concatenate([obj, table]), 0), _cloud(obj.copy(), 1)
    a.report = b.report = {"workspace": box}
    report = _crop_to_workspace([a, b])
    assert report["dropped"] == 2 and [s["dropped"] for s in report["per_sweep"]] == [2, 0]
    np.testing.assert_array_equal(a.points_base, obj)
    assert len(a.frame_index) == len(a.confidence) == len(a.sensor_origin_base) == 5
    c = _cloud(table, 2)  # no box: nothing is cropped
    assert "skipped" in _crop_to_workspace([c]) and len(c) == 2


def test_margin_points_are_placed_by_alignment_not_used_by_it(tmp_path, monkeypatch):
    """The triangulation keeps the points in a margin around the workspace box (a robot
    pose error put the object's foot below the floor). The registration sees only the
    points in the box; the corrections move every point; the exact box applies after
    them: the foot the correction lifts into the box is kept, the table is not."""
    import robo3d.registration as registration
    from robo3d.artefacts import load_clouds_npz, save_clouds_npz
    from robo3d.registration import AlignmentResult
    from robo3d.stages.align import stage_align

    box = [[-0.05, -0.05, 0.0005], [0.05, 0.05, 0.06]]
    wall = np.column_stack([np.full(40, 0.01), np.zeros(40), np.linspace(0.002, 0.03, 40)])
    lift = 0.0012  # sweep 0 was placed 1.2 mm too low
    foot = np.column_stack([np.full(6, 0.01), np.zeros(6), np.linspace(0.0006, 0.0019, 6)])
    table = np.column_stack([np.linspace(0.015, 0.03, 8), np.zeros(8), np.zeros(8)])
    a = _cloud(np.concatenate([wall - [0, 0, lift], foot - [0, 0, lift], table - [0, 0, lift]]), 0)
    b = _cloud(wall.copy(), 1)
    for c in (a, b):
        c.report = {"workspace": box, "workspace_margin_m": 0.002}
    save_clouds_npz(tmp_path / "clouds.npz", [a, b])
    seen = {}

    def fake_align(points, normals, *, options, origins, profiles, silhouettes):
        seen["n"] = [len(p) for p in points]
        seen["min_z"] = [float(p[:, 2].min()) for p in points]
        C = np.tile(np.eye(4), (2, 1, 1))
        C[0, 2, 3] = lift
        return AlignmentResult(corrections=C, per_sweep=[{"sweep": 0}, {"sweep": 1}],
                               reference=1)

    monkeypatch.setattr(registration, "align_sweeps", fake_align)
    out = {"npz": str(tmp_path / "aligned.npz"), "ply": str(tmp_path / "aligned.ply"),
           "rrd": str(tmp_path / "align.rrd"), "report": str(tmp_path / "align.json")}
    cfg = default_config()
    cfg["alignment"]["reject_outside_hull"] = False
    report = stage_align({"clouds": str(tmp_path / "clouds.npz")}, out, cfg, "t")
    # registration: only the points inside the box at the reported poses
    n_in_a = int(np.sum(wall[:, 2] - lift >= 0.0005) + np.sum(foot[:, 2] - lift >= 0.0005))
    assert seen["n"] == [n_in_a, 40] and min(seen["min_z"]) >= 0.0005
    assert report["points_in_margin_not_registered"] == len(a) - n_in_a
    aligned = load_clouds_npz(out["npz"])
    # after the correction: the whole wall and foot, none of the table
    np.testing.assert_allclose(aligned[0].points_base, np.concatenate([wall, foot]), atol=1e-12)
    assert report["outside_workspace"]["dropped"] == len(table)
    assert len(aligned[1]) == 40


def _boxed(cloud: SweepCloud) -> SweepCloud:
    """The cloud with the workspace box the triangulation reports (the views' agreement
    is measured in it)."""
    cloud.report = {"workspace": [(CENTRE - 0.06).tolist(), (CENTRE + 0.06).tolist()]}
    return cloud


def test_silhouettes_that_contradict_the_laser_as_a_whole_drop_nothing(tmp_path):
    """Masks that failed alike in many views (a white cup on a checker table: each mask
    missed the cup's white patches) together drop most of the measured points, each
    point by a few views, and no single view is the odd one out: the laser is kept whole
    and the report says why. Such masks disagree with each other (median IoU with the
    other views' hull 0.29; specks 0.0), so the views do not overrule the laser."""
    cam, Ts, masks = _views()
    rng = np.random.default_rng(2)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = CENTRE + RADIUS * d
    clouds = [_boxed(_cloud(surface.copy(), 0))]
    npz = tmp_path / "silhouettes.npz"
    np.savez(npz, qa_flagged=np.zeros(len(Ts), bool))
    half = []  # each mask misses a third of its 12-px blocks (its white patches)
    for _ in masks:
        keep = rng.random((180 // 12 + 1, 240 // 12 + 1)) > 1 / 3
        half.append(np.kron(keep, np.ones((12, 12), bool))[:180, :240])
    half = [m & k for m, k in zip(masks, half, strict=True)]
    views = SilhouetteViews([m.astype(float) for m in half], half, [cam] * len(Ts), Ts)
    report, dropped = _reject_outside_hull(clouds, views, {"silhouettes": str(npz)},
                                           default_config()["alignment"])
    assert report["contradicted"] is True and report["dropped"] == 0 and len(dropped) == 0
    assert report["disputed_fraction"] > 0.2 and "contradict the laser" in report["skipped"]
    assert report["views_agreement"]["iou_median"] < 0.5
    assert report["views_agreement"]["overrules"] is False
    assert len(clouds[0]) == 500
    # masks that are specks in every view: every point outside most of them
    specks = [np.zeros_like(m) for m in masks]
    for m in specks:
        m[80:84, 100:104] = True
    views_s = SilhouetteViews([m.astype(float) for m in specks], specks, [cam] * len(Ts), Ts)
    clouds = [_boxed(_cloud(surface.copy(), 0))]
    report, dropped = _reject_outside_hull(clouds, views_s, {"silhouettes": str(npz)},
                                           default_config()["alignment"])
    assert report["contradicted"] is True and report["would_drop_fraction"] > 0.9
    assert report["views_agreement"]["iou_median"] < 0.1
    assert report["disputed_fraction"] < 0.2 and len(clouds[0]) == 500
    # the same masks with a lenient cap drop what they see outside: the test is the cap
    lenient = {**default_config()["alignment"], "outside_hull_max_fraction": 0.9,
               "outside_hull_max_total_fraction": 0.95}
    clouds = [_cloud(surface.copy(), 0)]
    report, dropped = _reject_outside_hull(clouds, views, {"silhouettes": str(npz)}, lenient)
    assert report["dropped"] == len(dropped) > 200 and len(clouds[0]) < 300


def test_views_that_agree_overrule_a_laser_read_off_a_texture(tmp_path):
    """Right masks, and a laser that left no trace on the object: the detector read a
    texture's edges, 4-15 mm off the surface, and a few points on it (random scene 379: a
    blue laser on an orange checker torus, 92 % of its points outside masks of IoU 0.94).
    The masks would drop most of the points, which read as masks that failed everywhere;
    but ten views that agree with each other are not what failed: the points off the
    object are dropped, those on it kept. With the override off (null) the laser is kept
    whole, as before."""
    cam, Ts, masks = _views()
    rng = np.random.default_rng(5)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = CENTRE + RADIUS * d[:60]
    off = CENTRE + (RADIUS + rng.uniform(0.004, 0.015, size=(340, 1))) * d[60:]
    npz = tmp_path / "silhouettes.npz"
    np.savez(npz, qa_flagged=np.zeros(len(Ts), bool))
    views = SilhouetteViews([m.astype(float) for m in masks], masks, [cam] * len(Ts), Ts)
    ac = default_config()["alignment"]
    clouds = [_boxed(_cloud(np.concatenate([surface, off]), 0))]
    report, dropped = _reject_outside_hull(clouds, views, {"silhouettes": str(npz)},
                                           {**ac, "outside_hull_views_agree_iou": None})
    assert report["contradicted"] is True and len(clouds[0]) == 400
    assert report["would_drop_fraction"] > 0.5 > report["disputed_fraction"]
    clouds = [_boxed(_cloud(np.concatenate([surface, off]), 0))]
    report, dropped = _reject_outside_hull(clouds, views, {"silhouettes": str(npz)}, ac)
    assert "contradicted" not in report
    agree = report["views_agreement"]
    assert agree["overrules"] is True and agree["iou_median"] > 0.85
    assert len(agree["per_view"]) == 10
    r = np.linalg.norm(clouds[0].points_base - CENTRE, axis=1)
    assert len(clouds[0]) >= 60 and np.all(np.abs(r - RADIUS) < 0.003)  # the surface kept
    assert report["dropped"] == len(dropped) > 300  # the texture's points dropped
    # two views bound nothing of each other, nor is anything measured without a box
    assert _views_agreement(clouds, views, [0, 1], 64) is None
    assert _views_agreement([_cloud(surface, 0)], views, list(range(10)), 64) is None
    assert _views_agreement(clouds, views, list(range(10)), 0) is None


def test_the_lit_table_next_to_the_floor_does_not_make_the_silhouettes_contradicted(tmp_path):
    """A box whose floor is the table: the laser on the table inside it can be most of a
    scan's points, all outside every silhouette. They are dropped; the rule that more
    than half of the points dropped means wrong masks counts the points above the floor
    only."""
    cam, Ts, masks = _views()
    rng = np.random.default_rng(4)
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    surface = CENTRE + RADIUS * d
    floor = CENTRE[2] - RADIUS - 0.001  # the box's floor, just below the sphere
    xy = rng.uniform(-0.09, 0.09, size=(2000, 2))
    xy = xy[np.linalg.norm(xy, axis=1) > RADIUS + 0.01][:400]
    table = np.column_stack([xy, np.full(len(xy), floor + 0.0005)])  # in the box
    cloud = _cloud(np.concatenate([surface, table]), 0)
    cloud.report = {"workspace": [[-0.1, -0.1, floor], [0.1, 0.1, 0.2]],
                    "workspace_margin_m": 0.002}
    npz = tmp_path / "silhouettes.npz"
    np.savez(npz, qa_flagged=np.zeros(len(Ts), bool))
    views = SilhouetteViews([m.astype(float) for m in masks], masks, [cam] * len(Ts), Ts)
    report, dropped = _reject_outside_hull([cloud], views, {"silhouettes": str(npz)},
                                           default_config()["alignment"])
    assert len(table) == 400 and "contradicted" not in report  # two thirds are the table
    assert report["dropped"] == 400 and len(cloud) == 200
    np.testing.assert_allclose(np.linalg.norm(cloud.points_base - CENTRE, axis=1), RADIUS)


def test_points_whose_stripe_centre_was_pulled_off_the_stripe_are_dropped(tmp_path):
    """After the alignment the points whose stripe centre lies more than
    ``alignment.max_centre_skew_px`` from its profile's top (taken from the recording's
    median skew) are dropped, counted per sweep, and returned for the rerun log; a skew
    not known (NaN) keeps the point; a stripe lopsided everywhere (more than
    ``max_centre_skew_fraction`` would go) keeps every point and says so; 0 keeps all;
    clouds written before the skew was kept are left as they are. The skew survives
    clouds.npz."""
    from robo3d.artefacts import load_clouds_npz, save_clouds_npz
    from robo3d.stages.align import _drop_skewed

    rng = np.random.default_rng(0)
    # every centre 0.5 px off its top (a lopsided profile), four pulled 2.6-5 px further
    skews = [0.5 + rng.uniform(-0.8, 0.8, 120), 0.5 + rng.uniform(-0.8, 0.8, 80)]
    skews[0][[7, 30]] = [0.5 - 3.0, 0.5 + 2.6]
    skews[0][50] = np.nan
    skews[1][[3, 60]] = [0.5 + 5.0, 0.5 - 2.7]
    clouds = []
    for k, sk in enumerate(skews):
        c = _cloud(rng.normal(size=(len(sk), 3)), k)
        c.skew_px = sk.astype(np.float32)
        clouds.append(c)
    save_clouds_npz(tmp_path / "c.npz", clouds)
    back = load_clouds_npz(tmp_path / "c.npz")
    np.testing.assert_array_equal(back[1].skew_px, clouds[1].skew_px)
    assert np.isnan(back[0].skew_px[50])
    expect = np.concatenate([clouds[0].points_base[[7, 30]], clouds[1].points_base[[3, 60]]])
    cfg = default_config()["alignment"]
    assert cfg["max_centre_skew_px"] == 2.0 and cfg["max_centre_skew_fraction"] == 0.05
    report, dropped = _drop_skewed(back, cfg)
    assert report["not_applied"] is False and abs(report["median_skew_px"] - 0.5) < 0.1
    assert report["dropped"] == 4 and [p["dropped"] for p in report["per_sweep"]] == [2, 2]
    np.testing.assert_array_equal(dropped, expect)
    assert [len(c) for c in back] == [118, 78]
    assert np.isnan(back[0].skew_px).sum() == 1  # not known: kept
    assert back[0].report["dropped_skewed_centre"] == 2
    # a limit of 0.6 px would take more than 5 % of the points (the profile's own spread
    # of 0.8 px): the test does not describe this stripe, so none goes
    strict = {**cfg, "max_centre_skew_px": 0.6}
    report, dropped = _drop_skewed(clouds, strict)
    assert report["not_applied"] is True and report["would_drop_fraction"] > 0.05
    assert report["dropped"] == 0 and len(dropped) == 0 and len(clouds[0]) == 120
    off = {**cfg, "max_centre_skew_px": 0.0}
    report, dropped = _drop_skewed(clouds, off)
    assert "skipped" in report and len(dropped) == 0 and len(clouds[0]) == 120
    old = [_cloud(rng.normal(size=(5, 3)), 0)]  # no skew kept (an older clouds.npz)
    report, dropped = _drop_skewed(old, cfg)
    assert "older" in report["skipped"] and len(old[0]) == 5


def test_a_single_sweep_without_views_is_flagged(tmp_path):
    """One sweep and no views: nothing to align it to, and nothing checks its robot
    pose. It is flagged as a sweep that the alignment keeps at the robot's pose is
    (random scene 148: a stripe read off an orange checker, 20 mm off, labelled measured
    with nothing flagged), in the report and in the aligned cloud, whose surface fusion
    then labels ``flagged_sweep``. With the alignment turned off in the config nothing is
    flagged: the user chose it."""
    from robo3d.artefacts import load_clouds_npz, save_clouds_npz
    from robo3d.stages.align import stage_align

    rng = np.random.default_rng(3)
    d = rng.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    save_clouds_npz(tmp_path / "clouds.npz", [_boxed(_cloud(CENTRE + RADIUS * d, 0))])
    out = {"npz": str(tmp_path / "aligned.npz"), "ply": str(tmp_path / "aligned.ply"),
           "rrd": str(tmp_path / "align.rrd"), "report": str(tmp_path / "align.json")}
    report = stage_align({"clouds": str(tmp_path / "clouds.npz")}, out, default_config(), "t")
    assert report["skipped"] == "a single sweep and no views: nothing to align it to"
    sweep, = report["per_sweep"]
    assert sweep["flagged"] and "checked by nothing" in sweep["reason"]
    assert sweep["n_points"] == 300
    aligned, = load_clouds_npz(out["npz"])
    assert aligned.report["flagged"] is True and len(aligned) == 300
    cfg = default_config()
    cfg["alignment"]["enabled"] = False
    report = stage_align({"clouds": str(tmp_path / "clouds.npz")}, out, cfg, "t")
    assert "per_sweep" not in report
    assert not load_clouds_npz(out["npz"])[0].report.get("flagged")
