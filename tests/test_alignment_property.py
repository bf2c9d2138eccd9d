"""Property test of the alignment (issue 11): on many small random scans of the simulator's
objects (shapes, 2-5 sweeps, 0/4/8 silhouette views, seeds) ``align_sweeps`` never raises
anything but robo3d's own errors, and the aligned sweeps are never worse than the robot's
poses by more than a small margin against the truth.

The scans are made directly from the simulator's ray caster (no images of the laser, no
front end, so that the whole test runs in well under a minute): per laser frame the true
lit points (:func:`robo3d.sim.render.visible_stripe_points`) at 320 x 240 with the
simulated lens distortion, their true normals from the mesh, placed in ``base`` by a
robot pose carrying a constant per-sweep error (0.2-0.4 mm and 0.1-0.3 degrees at the
camera, as ``robo3d simulate`` draws it), and, for views, the rendered grey images and
their true silhouettes at the views' (exact) poses.

Scoring: each sweep's RMS displacement of its points from the truth, before (the robot's
poses) and after alignment. With views the figure is absolute; without, the common motion
is free (the gauge), so both figures are taken after the rigid motion that best puts the
reference sweep on its truth.
"""

from __future__ import annotations

import dataclasses
import functools
import json

import numpy as np
import pytest

from robo3d.errors import Robo3dError
from robo3d.registration import AlignOptions, SilhouetteViews, align_sweeps

sim_render = pytest.importorskip("robo3d.sim.render")
from robo3d.sim import rig, shapes  # noqa: E402

WIDTH, HEIGHT = 320, 240
MARGIN_MM = 0.05  # an aligned sweep may be this much worse than at the robot's pose


@functools.cache
def _scene(name: str):
    mesh = shapes.make_object(name, voxel=0.0012, faces=8000)
    return sim_render.SimScene(mesh)


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rigid (4, 4) that best maps points a onto b."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    r = vt.T @ d @ u.T
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = r, cb - r @ ca
    return out


def _scan(name: str, n_sweeps: int, n_views: int, frames: int, seed: int,
          robot_error: bool = True):
    """Sweeps (placed points, normals, origins, profiles, true points) and views; without
    ``robot_error`` every sweep at its true pose."""
    import open3d as o3d

    rng = np.random.default_rng(seed)
    scene = _scene(name)
    cam = rig.default_camera(WIDTH, HEIGHT)
    t_cl = rig.default_laser_mount()
    v = scene.mesh.vertices
    lo, hi = v.min(axis=0), v.max(axis=0)
    target = 0.5 * (lo + hi)
    closest = o3d.t.geometry.RaycastingScene()
    closest.add_triangles(o3d.core.Tensor(np.ascontiguousarray(v, np.float32)),
                          o3d.core.Tensor(np.ascontiguousarray(scene.mesh.faces, np.uint32)))
    az0 = rng.uniform(0, 360)
    out = []
    for s in range(n_sweeps):
        top = n_sweeps > 2 and s == n_sweeps - 1
        az = az0 + 360.0 * s / max(n_sweeps - (1 if n_sweeps > 2 else 0), 1)
        el = 90.0 if top else rng.uniform(30, 55)
        t0, direction, length = rig.sweep_poses(az, el, target, 0.27, t_cl, lo, hi, 1e-3)
        steps = np.linspace(0.0, length, frames)
        # the robot's constant error of this sweep, in the camera frame
        axis = rng.normal(size=3)
        ang = np.radians(rng.uniform(0.1, 0.3))
        shift = rng.normal(size=3)
        err = np.eye(4)
        err[:3, :3] = _rot(axis, ang)
        err[:3, 3] = rng.uniform(0.2e-3, 0.4e-3) * shift / np.linalg.norm(shift)
        if not robot_error:
            err = np.eye(4)
        pts, tru, org, prof = [], [], [], []
        for f, d in enumerate(steps):
            t_true = t0.copy()
            t_true[:3, 3] += d * direction
            st = sim_render.visible_stripe_points(scene, cam, t_true, t_true @ t_cl,
                                                  n_rays=4 * WIDTH)
            x = st.points_base[st.on_object]
            if not len(x):
                continue
            t_rep = t_true @ err
            placed = x @ (t_rep @ np.linalg.inv(t_true))[:3, :3].T + (
                t_rep @ np.linalg.inv(t_true))[:3, 3]
            pts.append(placed)
            tru.append(x)
            org.append(np.broadcast_to(t_rep[:3, 3], x.shape))
            prof.append(np.full(len(x), f))
        if pts:
            p, x = np.concatenate(pts), np.concatenate(tru)
            o, g = np.concatenate(org), np.concatenate(prof)
        else:
            p = x = o = np.zeros((0, 3))
            g = np.zeros(0, np.int64)
        n = np.zeros((0, 3))
        if len(x):
            ans = closest.compute_closest_points(o3d.core.Tensor(x.astype(np.float32)))
            n = ans["primitive_normals"].numpy().astype(np.float64).reshape(-1, 3)
        n = n @ err_rot(err, t0).T  # normals as placed
        n *= np.where(np.einsum("ij,ij->i", n, o - p) < 0, -1.0, 1.0)[:, None]
        out.append((p, n, o, g, x))
    views = None
    if n_views:
        poses = rig.view_poses(n_views, target, 0.3, (25.0, 55.0), rng)
        imgs, masks = [], []
        for t in poses:
            img, sil = sim_render.render_view(scene, cam, t, return_silhouette=True)
            imgs.append(np.asarray(img).mean(axis=2))
            masks.append(sil)
        views = SilhouetteViews(imgs, masks, [cam] * n_views, np.asarray(poses))
    return out, views


def err_rot(err: np.ndarray, t0: np.ndarray) -> np.ndarray:
    """The base-frame rotation of a camera-frame error (the sweep does not turn)."""
    return t0[:3, :3] @ err[:3, :3] @ t0[:3, :3].T


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _cases(n: int = 10):
    rng = np.random.default_rng(11)
    names = list(shapes.OBJECTS)
    out = [("sphere", 3, 8, 30, 1), ("sphere", 4, 0, 20, 2), ("dimple_block", 3, 8, 30, 1)]
    while len(out) < n:
        out.append((names[int(rng.integers(len(names)))], int(rng.integers(2, 6)),
                    int(rng.choice([0, 4, 8])), int(rng.integers(20, 31)),
                    int(rng.integers(100))))
    return out


@pytest.mark.parametrize("name,n_sweeps,n_views,frames,seed", _cases())
def test_alignment_never_crashes_and_never_makes_poses_worse(name, n_sweeps, n_views,
                                                             frames, seed):
    sweeps, views = _scan(name, n_sweeps, n_views, frames, seed)
    pts = [s[0] for s in sweeps]
    try:
        res = align_sweeps(pts, [s[1] for s in sweeps], origins=[s[2] for s in sweeps],
                           profiles=[s[3] for s in sweeps], silhouettes=views,
                           options=AlignOptions(seed=seed))
    except Robo3dError:
        return  # robo3d's own, named error: allowed
    aligned = [res.apply(k, s[0], s[2])[0] for k, s in enumerate(sweeps)]
    truth = [s[4] for s in sweeps]
    fix_b = fix_a = np.eye(4)
    absolute = res.gauge == "silhouettes"
    if not absolute:  # the gauge is free: compare after putting the reference on its truth
        g = res.reference
        if len(truth[g]) >= 3:
            fix_b = _kabsch(pts[g], truth[g])
            fix_a = _kabsch(aligned[g], truth[g])

    def rms(p, fix, x):
        q = p @ fix[:3, :3].T + fix[:3, 3]
        return float(np.sqrt(np.mean(np.sum((q - x) ** 2, axis=1)))) * 1e3 if len(x) else 0.0

    before = [rms(p, fix_b, x) for p, x in zip(pts, truth, strict=True)]
    after = [rms(a, fix_a, x) for a, x in zip(aligned, truth, strict=True)]
    for e in res.per_sweep:  # every sweep's report says what its data fixed
        assert e["flagged"] or "unconstrained" in e or res.refinement is None, e
    worse = [(s, round(b, 3), round(a, 3)) for s, (b, a) in enumerate(zip(before, after,
                                                                         strict=True))
             if a > b + MARGIN_MM]
    assert not worse, f"sweeps worse than at the robot's poses (sweep, before, after mm): " \
                      f"{worse}; gauge {res.gauge}"


def test_threads_do_not_change_the_result():
    """Pairs and views run on worker threads (the align job's); each task runs Open3D on
    one thread and the terms are summed in a fixed order, so the corrections are the same
    bits at any thread count."""
    sweeps, views = _scan("dimple_block", 4, 8, 30, 3)
    kw = dict(origins=[s[2] for s in sweeps], profiles=[s[3] for s in sweeps],
              silhouettes=views)
    one = align_sweeps([s[0] for s in sweeps], [s[1] for s in sweeps],
                       options=AlignOptions(seed=3, threads=1), **kw)
    two = align_sweeps([s[0] for s in sweeps], [s[1] for s in sweeps],
                       options=AlignOptions(seed=3, threads=2), **kw)
    assert sum(p["accepted"] for p in one.pairs) >= 2  # the pairs did run
    assert one.refinement is not None and one.gauge == "silhouettes"
    np.testing.assert_array_equal(np.asarray(one.rotations), np.asarray(two.rotations))
    np.testing.assert_array_equal(np.asarray(one.translations), np.asarray(two.translations))
    assert json.dumps(one.pairs) == json.dumps(two.pairs)  # NaN-safe


def _sweep_errors_mm(res, sweeps) -> list[float]:
    return [float(np.sqrt(np.mean(np.sum((res.apply(k, s[0], s[2])[0] - s[4]) ** 2, axis=1))))
            * 1e3 for k, s in enumerate(sweeps)]


def test_refinement_also_starts_from_the_robot_poses_and_keeps_the_clearly_better_end(
        monkeypatch):
    """The refinement runs from the pose graph's corrections and from the robot's poses
    (``robot_start``). Where both end in the same minimum the pose graph's is kept (the
    report holds both RMS); where the pose graph's start ends worse (here: it stops
    before it converges, as a start in a poor basin does) the robot start's end is taken,
    and the sweeps land on their true poses instead of being kept at the robot's."""
    import robo3d.registration as reg

    sweeps, views = _scan("dimple_block", 4, 8, 30, 3)
    kw = dict(origins=[s[2] for s in sweeps], profiles=[s[3] for s in sweeps],
              silhouettes=views)
    pts, nrm = [s[0] for s in sweeps], [s[1] for s in sweeps]
    before = [float(np.sqrt(np.mean(np.sum((s[0] - s[4]) ** 2, axis=1)))) * 1e3
              for s in sweeps]
    same = align_sweeps(pts, nrm, options=AlignOptions(seed=3, threads=2), **kw)
    st = same.refinement["starts"]
    assert st["taken"] == "pose_graph"
    assert abs(st["robot_rim_rms_px"] / st["pose_graph_rim_rms_px"] - 1) < 0.05
    assert max(_sweep_errors_mm(same, sweeps)) < 0.2 * min(before)  # 0.11 against 0.73 mm

    real = reg._refine_from

    def stalled(problem, initial, options):  # the pose graph's start stalls
        if initial is not None:
            options = dataclasses.replace(options, refine_iterations=2)
        return real(problem, initial, options)

    monkeypatch.setattr(reg, "_refine_from", stalled)
    only = align_sweeps(pts, nrm, options=AlignOptions(seed=3, threads=2, robot_start=False),
                        **kw)
    assert not only.refinement["converged"]  # without the second start: robot poses
    np.testing.assert_allclose(_sweep_errors_mm(only, sweeps), before, rtol=1e-9)
    both = align_sweeps(pts, nrm, options=AlignOptions(seed=3, threads=2), **kw)
    st = both.refinement["starts"]
    assert st["taken"] == "robot" and not st["pose_graph_converged"], st
    assert both.refinement["converged"]
    assert max(_sweep_errors_mm(both, sweeps)) < 0.2 * min(before)


def test_a_sweep_the_pose_graph_turned_beyond_the_bounds_is_refined_from_the_robot_pose(
        monkeypatch):
    """The pose graph puts a sweep beyond the bounds (here: sweep 0's pairs' ICP turned 5
    degrees about the vertical, as ICP slides about a near-symmetric body's axis; issue
    11's near_symmetric/4 at 1280 x 960: 5.1 degrees, its top sweep kept at the robot's
    0.46 mm). Without views it stays at the robot's pose, flagged. With views (an absolute
    reference) the refinement takes it from the robot's pose with the others, and it
    lands on its true pose."""
    import robo3d.registration as reg

    sweeps, views = _scan("dimple_block", 4, 8, 30, 3)
    pts, nrm = [s[0] for s in sweeps], [s[1] for s in sweeps]
    kw = dict(origins=[s[2] for s in sweeps], profiles=[s[3] for s in sweeps])
    before = [_rms_mm(s[0], s[4]) for s in sweeps]
    real = reg._register_pairs
    turn = np.eye(4)
    turn[:3, :3] = _rot(np.array([0.0, 0.0, 1.0]), np.radians(5.0))

    def sliding(*a, **k):  # every pair with sweep 0 turned about the vertical
        pairs, edges = real(*a, **k)
        for (i, j), e in edges.items():
            if 0 in (i, j):
                e["T"] = e["T"] @ (turn if i == 0 else turn.T)
        return pairs, edges

    monkeypatch.setattr(reg, "_register_pairs", sliding)
    alone = align_sweeps(pts, nrm, options=AlignOptions(seed=3, threads=2), **kw)
    e = alone.per_sweep[0]
    assert e["flagged"] and e["reason"].startswith("correction "), e
    assert _sweep_errors_mm(alone, sweeps)[0] == pytest.approx(before[0])
    res = align_sweeps(pts, nrm, options=AlignOptions(seed=3, threads=2), silhouettes=views,
                       **kw)
    assert res.gauge == "silhouettes" and not any(p["flagged"] for p in res.per_sweep)
    after = _sweep_errors_mm(res, sweeps)
    assert after[0] < 0.2 * before[0], (before, after)  # 0.88 -> 0.11 mm, as the others


def _rms_mm(p: np.ndarray, x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((p - x) ** 2, axis=1)))) * 1e3


@pytest.mark.parametrize("name,n_views,seed", [("vase", 6, 2), ("blob", 8, 1),
                                               ("bracket", 8, 1)])
def test_one_sweep_is_refined_against_the_views(name, n_views, seed):
    """A one-sweep scan with views: the views alone correct the sweep's robot error
    (measured: 0.74-1.10 mm -> 0.04-0.25 mm on the smooth objects, never worse); where
    they give no contour residual (the bracket's flat faces) it stays at the robot's
    pose, flagged. (The vase with 4 views: 27 residuals at the true pose since the
    sweep must pass over the contour generator, fewer than the gauge needs: kept at
    the robot's pose.)"""
    sweeps, views = _scan(name, 1, n_views, 30, seed)
    s = sweeps[0]
    res = align_sweeps([s[0]], [s[1]], origins=[s[2]], profiles=[s[3]], silhouettes=views,
                       options=AlignOptions(seed=seed))
    before, after = _rms_mm(s[0], s[4]), _rms_mm(res.apply(0, s[0], s[2])[0], s[4])
    e = res.per_sweep[0]
    if name == "bracket":
        assert e["flagged"] and e["n_rim"] == 0 and after == pytest.approx(before)
    else:
        assert res.gauge == "silhouettes" and not e["flagged"], e
        assert before > 0.7 and after < 0.1, (before, after)  # vase 1.03 -> 0.08, blob 0.74 -> 0.06


def test_one_sweep_stays_at_the_robot_pose_when_the_views_do_not_confirm_it():
    """Each view's image and mask moved by a few pixels, each its own way (masks and
    edges that miss the object's outline): the contour residuals of the refined sweep
    stay at 2 px RMS, above ``views_only_max_rim_rms_px``, and with nothing else to check
    it the sweep keeps its robot pose, flagged, the reason in its report."""
    sweeps, views = _scan("vase", 1, 8, 30, 3)
    rng = np.random.default_rng(0)
    offs = [tuple(int(x) for x in rng.integers(-4, 5, 2)) for _ in range(8)]
    bad = SilhouetteViews([np.roll(im, o, axis=(0, 1)) for im, o in zip(views.images, offs,
                                                                        strict=True)],
                          [np.roll(m, o, axis=(0, 1)) for m, o in zip(views.masks, offs,
                                                                     strict=True)],
                          views.cameras, views.T_base_camera)
    s = sweeps[0]
    kw = dict(origins=[s[2]], profiles=[s[3]], silhouettes=bad)
    res = align_sweeps([s[0]], [s[1]], options=AlignOptions(seed=3), **kw)
    e = res.per_sweep[0]
    assert e["flagged"] and "the views do not confirm the pose" in e["reason"], e
    assert res.refinement["skipped"].startswith("sweep 0: refined against the views alone")
    np.testing.assert_allclose(res.apply(0, s[0], s[2])[0], s[0], atol=1e-12)
    # a looser bound takes the refined pose (here: no better than the robot's)
    loose = align_sweeps([s[0]], [s[1]], options=AlignOptions(
        seed=3, views_only_max_rim_rms_px=5.0), **kw)
    assert not loose.per_sweep[0]["flagged"]
    assert 1.0 < loose.per_sweep[0]["rim_rms_px"] < 5.0


def test_sweeps_without_a_pair_and_too_few_contour_residuals_say_why(monkeypatch):
    """No pair of sweeps overlaps (a sparse scan) and their refinement against the views
    finds too few contour residuals to hold the gauge (the bracket's flat faces): every
    sweep stays at the robot's pose, and the report says that the refinement ran and
    why it was not used, not that every sweep was flagged before it (random scene 290,
    stop 44, where the views' own verdicts on two of its sweeps were lost too: they now
    follow the pose graph's reason)."""
    import robo3d.registration as reg

    sweeps, views = _scan("bracket", 2, 8, 30, 1)
    pts, nrm = [s[0] for s in sweeps], [s[1] for s in sweeps]
    kw = dict(origins=[s[2] for s in sweeps], profiles=[s[3] for s in sweeps])
    real = reg._register_pairs

    def apart(*a, **k):  # as if the sweeps did not overlap
        pairs, _ = real(*a, **k)
        for p in pairs:
            p.update(accepted=False, used=False, reason="overlap 0.002 < min_overlap 0.05")
        return pairs, {}

    monkeypatch.setattr(reg, "_register_pairs", apart)
    res = align_sweeps(pts, nrm, options=AlignOptions(seed=1), silhouettes=views, **kw)
    before = [_rms_mm(s[0], s[4]) for s in sweeps]
    after = [_rms_mm(res.apply(k, s[0], s[2])[0], s[4]) for k, s in enumerate(sweeps)]
    assert after == pytest.approx(before)  # the robot's poses
    assert all(p["flagged"] and p["reason"].startswith("no accepted pair")
               for p in res.per_sweep), res.per_sweep
    why = res.refinement["skipped"]
    assert "refined against the views" in why and "contour residuals" in why, why
    assert "had 10 silhouette contour residuals (fewer than 30" in why, why


def test_the_robots_start_is_taken_when_it_is_better_on_one_sweep_and_worse_on_none():
    """The blue cell of the front-end benchmark (exact poses, stop 59): the pose graph's
    start put sweep 0 1.56 mm off, 0.484 px against 0.445 px from the robot's start, the
    other sweeps equal or better from the robot's too, but overall only 2.9 % lower,
    short of the 3 % margin."""
    from robo3d.registration import _robot_start_better

    pg, rb = [0.484, 0.394, 0.431, 0.477], [0.445, 0.393, 0.411, 0.474]
    assert _robot_start_better(0.4380, 0.4252, pg, rb, 0.03)
    assert not _robot_start_better(0.4380, 0.4252, pg, rb[:3] + [0.50], 0.03)  # one worse
    assert not _robot_start_better(0.4380, 0.4252, pg, [x * 0.99 for x in pg], 0.03)
    assert _robot_start_better(0.50, 0.47, [0.5], [0.47], 0.03)  # overall, as before
    assert not _robot_start_better(0.50, 0.49, [0.5], [0.45], 0.03)  # one sweep: overall


def _moved_mm(res, sweeps) -> list[float]:
    """How far the alignment moved each sweep's true points (RMS, mm)."""
    return [_rms_mm(res.apply(k, s[4], s[2])[0], s[4]) for k, s in enumerate(sweeps)]


def test_noisy_profiles_do_not_push_the_sweeps_off_their_true_poses():
    """Points that scatter about their profiles, as laser speckle makes them (an error
    the simulator renders and the alignment does not model), at the TRUE poses: the
    silhouette term takes a profile's most outward point, and the most outward of noisy
    points lies beyond the surface, so it pushed every sweep outward (measured here:
    0.08 / 0.15 mm of noise along the laser camera's rays, 0.075 / 0.14 px in the views,
    moved the sweeps 0.066-0.073 / 0.14-0.16 mm). Points moved toward their fit along
    the profiles (registration._rim_points): 0.004-0.017 / 0.015-0.033 mm. Without the
    noise the measured points are taken, as before."""
    sweeps, views = _scan("blob", 3, 8, 40, 3, robot_error=False)
    args = dict(origins=[s[2] for s in sweeps], profiles=[s[3] for s in sweeps],
                silhouettes=views, options=AlignOptions(seed=1))
    for sigma, most in ((0.08e-3, 0.03), (0.15e-3, 0.05)):
        rng = np.random.default_rng(7)
        noisy = []
        for p, _n, o, _g, _x in sweeps:
            ray = (p - o) / np.linalg.norm(p - o, axis=1, keepdims=True)
            noisy.append(p + rng.normal(0.0, sigma, (len(p), 1)) * ray)
        res = align_sweeps(noisy, [s[1] for s in sweeps], **args)
        shares = [e["rim_fit_share"] for e in res.per_sweep]
        assert min(shares) > 0.8, [e["profile_noise_px"] for e in res.per_sweep]
        assert max(_moved_mm(res, sweeps)) < most, _moved_mm(res, sweeps)
    clean = align_sweeps([s[0] for s in sweeps], [s[1] for s in sweeps], **args)
    assert all(e["rim_fit_share"] == 0 for e in clean.per_sweep)
    assert max(_moved_mm(clean, sweeps)) < 0.01  # measured 0.006
    # a caller's profiles whose points are not in order along them: no fit (a quadratic
    # through random points of the profile is no fit of it), the measured points
    order = [np.lexsort((rng.random(len(s[3])), s[3])) for s in sweeps]
    mixed = [tuple(a[k] for a in s) for s, k in zip(sweeps, order, strict=True)]
    res = align_sweeps([p[k] for p, k in zip(noisy, order, strict=True)],
                       [s[1] for s in mixed], origins=[s[2] for s in mixed],
                       profiles=[s[3] for s in mixed], silhouettes=views,
                       options=AlignOptions(seed=1))
    assert all(e["rim_fit_share"] == 0 and e["profile_noise_mm"] is None
               for e in res.per_sweep)
    assert max(_moved_mm(res, mixed)) < 0.25  # the measured points' outward push


def test_the_profile_fit_keeps_a_parabola_and_survives_degenerate_profiles():
    """registration._profile_quadratic: a parabola sampled along a profile is returned where
    it is (its apex too: the term's contour points lie there), points without two
    neighbours on a side keep their place, and repeated or constant points give finite
    positions; a shuffled profile is told apart from an ordered one."""
    from robo3d.registration import _profile_quadratic, _profiles_in_order

    t = np.linspace(-3e-3, 3e-3, 61)
    g = np.zeros(len(t), np.int64)
    x = np.c_[t, -40.0 * t**2, np.zeros_like(t)]
    fit = _profile_quadratic(x, g, np.arange(len(t)), 5)
    # (a quadratic in chord length, not in t: 9 nm off where the slope is 0.24, 0.6 nm at
    # the apex, against some 300,000 nm a pixel in the views)
    assert np.abs(fit - x).max() < 2e-8 and np.abs(fit[30] - x[30]).max() < 2e-9
    noisy = x + np.random.default_rng(2).normal(0.0, 2e-5, x.shape) * [0, 1, 0]
    fit = _profile_quadratic(noisy, g, np.arange(len(t)), 5)
    assert np.abs(fit - x)[2:-2, 1].std() < 0.6 * np.abs(noisy - x)[2:-2, 1].std()
    np.testing.assert_array_equal(fit[:2], noisy[:2])  # one neighbour on a side: kept
    flat = np.repeat(x[:1], len(t), axis=0)
    assert np.isfinite(_profile_quadratic(flat, g, np.arange(len(t)), 5)).all()
    stuck = x.copy()
    stuck[20:30] = stuck[20]
    assert np.isfinite(_profile_quadratic(stuck, g, np.arange(len(t)), 5)).all()
    two = np.concatenate([x, x + [0, 0, 1e-3]])
    g2 = np.repeat([0, 1], len(t))
    assert _profiles_in_order(two, g2)
    mixed = np.lexsort((np.random.default_rng(3).random(len(g2)), g2))
    assert not _profiles_in_order(two[mixed], g2[mixed])
