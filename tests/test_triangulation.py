"""Tests of robo3d.triangulation: seed §4.1 (eqs. 11-17) and per-sweep clouds.

Ground truth is analytic: points on the laser sheet and on a known plane, projected into
a (distorted) camera, must come back exactly; a swept plane must give its own normal.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from robo3d.artefacts import SweepCloud, load_clouds_npz, save_clouds_npz
from robo3d.camera import CameraModel
from robo3d.errors import StageError
from robo3d.stripes import StripePoints
from robo3d.transforms import make_transform, rotation_angle_deg, transform_points
from robo3d.triangulation import (
    DROP_REASONS,
    TriangulateOptions,
    laser_params_from_transform,
    laser_plane_in_camera,
    laser_transform_from_params,
    split_sweeps,
    triangulate_pixels,
    triangulate_pixels_eq17,
    triangulate_sweep,
)

K = np.array([[520.0, 0.0, 322.5], [0.0, 515.0, 241.0], [0.0, 0.0, 1.0]])
D = np.array([-0.21, 0.09, 0.0012, -0.0008, -0.015])
CAM_D = CameraModel("camera", 640, 480, K, D)
CAM = CameraModel("camera", 640, 480, K)


def _rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _rig_laser(baseline: float = 0.08, aim: float = 0.35) -> np.ndarray:
    """T_camera_laser of our rig: laser above the camera (camera -y), sheet spanning the
    camera x, beam aimed at the optical axis at ``aim`` metres."""
    z_l = np.array([0.0, baseline, aim])
    z_l /= np.linalg.norm(z_l)
    x_l = np.array([1.0, 0.0, 0.0])
    y_l = np.cross(z_l, x_l)
    return make_transform(np.stack([x_l, y_l, z_l], axis=1), [0.0, -baseline, 0.0])


def _plane_line_points(n_cam, d_cam, T_camera_laser, s):
    """Points of the line where the target plane n.x = d meets the laser sheet."""
    n_s, d_s = laser_plane_in_camera(T_camera_laser)
    b = np.cross(n_cam, n_s)
    b /= np.linalg.norm(b)
    A = np.stack([n_cam, n_s, b])
    a = np.linalg.solve(A, [d_cam, d_s, 0.0])
    return a + np.asarray(s)[:, None] * b


# ---------------------------------------------------------------------------- eq. 11
def test_eq11_equals_the_motions_applied_in_order():
    dx, dy, dz, phi, theta, psi = 0.03, -0.08, 0.01, 0.2, -0.15, 0.4

    def trans(v):
        return make_transform(np.eye(3), v)

    def rot(r):
        return make_transform(r, np.zeros(3))

    # move a frame, starting at the camera, about the camera's fixed axes, in order
    pose = np.eye(4)
    for motion in (trans([dx, 0, 0]), trans([0, dy, 0]), trans([0, 0, dz]),
                   rot(_rz(phi)), rot(_ry(theta)), rot(_rx(psi))):
        pose = motion @ pose
    T = laser_transform_from_params(dx, dy, dz, phi, theta, psi)
    np.testing.assert_allclose(T, pose, atol=1e-15)
    # the seed's product, literally
    seed = (rot(_rx(psi)) @ rot(_ry(theta)) @ rot(_rz(phi)) @ trans([0, 0, dz])
            @ trans([0, dy, 0]) @ trans([dx, 0, 0]))
    np.testing.assert_allclose(T, seed, atol=1e-15)
    # translations first: the rotations swing the laser origin
    np.testing.assert_allclose(T[:3, 3], T[:3, :3] @ [dx, dy, dz], atol=1e-15)


@pytest.mark.parametrize("params", [
    (0.03, -0.08, 0.01, 0.2, -0.15, 0.4),
    (-0.1, 0.02, 0.3, -2.9, 1.2, 3.0),
    (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
])
def test_eq11_round_trip(params):
    T = laser_transform_from_params(*params)
    back = laser_params_from_transform(T)
    np.testing.assert_allclose(back, params, atol=1e-12)
    np.testing.assert_allclose(laser_transform_from_params(*back), T, atol=1e-12)


def test_eq11_round_trip_at_gimbal_lock():
    T = laser_transform_from_params(0.01, 0.02, 0.03, 0.3, np.pi / 2, -0.2)
    np.testing.assert_allclose(laser_transform_from_params(*laser_params_from_transform(T)),
                               T, atol=1e-9)


# ---------------------------------------------------------------------------- eq. 12-15
def test_laser_plane_is_the_xz_plane_of_the_laser():
    T = laser_transform_from_params(0.03, -0.08, 0.01, 0.2, -0.15, 0.4)
    n, d = laser_plane_in_camera(T)
    np.testing.assert_allclose(n, T[:3, 1], atol=1e-15)  # the laser's +y axis
    rng = np.random.default_rng(0)
    on_sheet = rng.normal(size=(50, 3)) * [1.0, 0.0, 1.0]  # y_L = 0
    off_sheet = on_sheet + [0.0, 0.25, 0.0]
    np.testing.assert_allclose(transform_points(T, on_sheet) @ n - d, 0.0, atol=1e-14)
    np.testing.assert_allclose(transform_points(T, off_sheet) @ n - d, 0.25, atol=1e-14)


# ---------------------------------------------------------------------------- eq. 16-17
def _target_points(T_camera_laser, n_pts=200):
    """Points on the sheet and on a tilted target plane, in view of the camera."""
    n_t = np.array([0.1, -0.25, -1.0])
    n_t /= np.linalg.norm(n_t)
    point_on_target = np.array([0.0, 0.0, 0.42])
    pts = _plane_line_points(n_t, n_t @ point_on_target, T_camera_laser,
                             np.linspace(-0.2, 0.2, n_pts))
    return pts


def test_triangulate_round_trip_through_distorted_camera():
    T_cl = _rig_laser()
    pts = _target_points(T_cl)
    uv, front = CAM_D.project(pts)
    inside = front & (uv[:, 0] > 0) & (uv[:, 0] < 639) & (uv[:, 1] > 0) & (uv[:, 1] < 479)
    assert inside.sum() > 100
    pts, uv = pts[inside], uv[inside]
    back, keep, dropped = triangulate_pixels(uv, CAM_D, T_cl)
    assert keep.all() and sum(dropped.values()) == 0 and set(dropped) == set(DROP_REASONS)
    err = np.linalg.norm(back - pts, axis=1)
    assert err.max() < 1e-9, err.max()


def test_seed_eq17_equals_ray_plane_form():
    T_cl = laser_transform_from_params(0.02, -0.09, 0.005, 0.05, 0.03, -0.22)
    rng = np.random.default_rng(1)
    uv = rng.uniform([0, 0], [639, 479], size=(300, 2))
    generic, keep, _ = triangulate_pixels(uv, CAM_D, T_cl, min_angle_deg=0.0)
    seed = triangulate_pixels_eq17(uv, CAM_D, T_cl)
    np.testing.assert_allclose(seed[keep], generic[keep], rtol=1e-10, atol=1e-12)
    assert keep.sum() > 100


def test_grazing_behind_range_and_nan_are_dropped_and_counted():
    T_cl = make_transform(np.eye(3), [0.0, 0.05, 0.0])  # sheet y = 0.05 in the camera
    angles = np.radians([0.5, 1.0, 1.5, 3.0, 10.0, 30.0, -5.0, -10.0])
    v = CAM.cy + CAM.fy * np.tan(angles)
    uv = np.stack([np.full(angles.size, CAM.cx), v], axis=1)
    uv = np.vstack([uv, [[np.nan, 10.0]]])
    pts, keep, dropped = triangulate_pixels(uv, CAM, T_cl, min_angle_deg=2.0, max_range=0.5)
    assert dropped == {"non_finite": 1, "grazing": 3, "behind": 2, "out_of_range": 1}
    np.testing.assert_array_equal(np.flatnonzero(keep), [4, 5])
    assert np.all(np.isnan(pts[~keep]))
    # a kept point lies on the sheet, at range 0.05 / sin(angle)
    np.testing.assert_allclose(pts[keep][:, 1], 0.05, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(pts[keep], axis=1),
                               0.05 / np.sin(angles[[4, 5]]), rtol=1e-12)


def test_triangulate_input_errors():
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        triangulate_pixels(np.zeros((3, 3)), CAM, np.eye(4))
    with pytest.raises(ValueError, match=r"\(4, 4\)"):
        triangulate_pixels(np.zeros((3, 2)), CAM, np.eye(3))


# ---------------------------------------------------------------------------- sweeps
def test_split_sweeps():
    s = np.array([0, 10, 20, 2_000, 2_010, 5_000, 5_005], dtype=np.int64) * 1_000_000
    np.testing.assert_array_equal(split_sweeps(s, 1_000_000_000), [0, 0, 0, 1, 1, 2, 2])
    np.testing.assert_array_equal(split_sweeps(s, 10_000_000_000), np.zeros(7))
    # unsorted input: sweeps follow time order, row for row
    perm = np.array([4, 0, 6, 2, 1, 5, 3])
    np.testing.assert_array_equal(split_sweeps(s[perm], 1_000_000_000),
                                  np.array([0, 0, 0, 1, 1, 2, 2])[perm])
    # frames faster than a third of the gap: the median-interval test changes nothing
    np.testing.assert_array_equal(split_sweeps(s, 1_000_000_000, 3.0), [0, 0, 0, 1, 1, 2, 2])
    with pytest.raises(ValueError, match="intervals"):
        split_sweeps(s, 1_000_000_000, -1.0)
    assert split_sweeps(np.zeros(0, np.int64), 1).shape == (0,)
    with pytest.raises(ValueError, match="gap_ns"):
        split_sweeps(s, 0)


def test_split_sweeps_of_a_stop_and_go_cell():
    """A cell that stops for each laser frame: two sweeps of 30 frames 1.5 s apart (with
    0.2 s of jitter), 10 s between them. By the 1 s gap alone every frame was a sweep of
    its own; with the median interval's test (3 x 1.5 s) they are the two sweeps."""
    rng = np.random.default_rng(0)
    t = np.concatenate([np.arange(30) * 1.5, 43.5 + 10.0 + np.arange(30) * 1.5])
    t += rng.uniform(-0.1, 0.1, t.size)
    ns = np.round(t * 1e9).astype(np.int64)
    assert split_sweeps(ns, 1_000_000_000).max() == 59  # the gap alone
    np.testing.assert_array_equal(split_sweeps(ns, 1_000_000_000, 3.0),
                                  np.repeat([0, 1], 30))
    # a pause of only twice the interval is not told apart: one sweep (documented limit)
    t2 = np.concatenate([np.arange(30) * 1.5, 43.5 + 3.0 + np.arange(30) * 1.5])
    assert split_sweeps(np.round(t2 * 1e9).astype(np.int64), 1_000_000_000, 3.0).max() == 0
    # a slow camera (0.7 s a frame) whose sweeps the gap alone splits into runs of ten
    # frames, 2 s apart (the simulator's sweeps of 10 frames): split as the contract says
    t3 = np.concatenate([np.arange(10) * 0.697, 6.273 + 2.034 + np.arange(10) * 0.623])
    np.testing.assert_array_equal(
        split_sweeps(np.round(t3 * 1e9).astype(np.int64), 1_000_000_000, 3.0),
        np.repeat([0, 1], 10))


def _plane_sweep(n_frames=24, step=0.002, T_cl=None):
    """The rig moving along base y over a tilted plane; exact stripe pixels per column."""
    T_cl = _rig_laser() if T_cl is None else T_cl
    n_true = np.array([0.2, -0.1, 1.0])
    n_true /= np.linalg.norm(n_true)
    R_bc = np.diag([1.0, -1.0, -1.0])  # looking down at the plane
    poses, stripes = [], []
    u = np.arange(0, 640, dtype=np.float64)
    for i in range(n_frames):
        T_bc = make_transform(R_bc, [0.01, -0.02 + step * i, 0.40])
        poses.append(T_bc)
        R, t = T_bc[:3, :3], T_bc[:3, 3]
        n_c = R.T @ n_true
        d_c = n_true @ np.zeros(3) - n_true @ t  # plane through the base origin
        line = _plane_line_points(n_c, d_c, T_cl, np.zeros(1))
        a, b = line[0], _plane_line_points(n_c, d_c, T_cl, np.ones(1))[0] - line[0]
        x = (u - CAM.cx) / CAM.fx
        s = (x * a[2] - a[0]) / (b[0] - x * b[2])
        p = a + s[:, None] * b
        v = CAM.fy * p[:, 1] / p[:, 2] + CAM.cy
        ok = (v >= 0) & (v <= 479)
        stripes.append(StripePoints(u=u[ok], v=v[ok], confidence=np.full(ok.sum(), 0.9)))
    return stripes, np.stack(poses), T_cl, n_true


def test_sweep_of_a_plane_points_and_normals():
    stripes, poses, T_cl, n_true = _plane_sweep()
    cloud = triangulate_sweep(stripes, CAM, poses, T_cl, frame_indices=np.arange(24) + 100,
                              sweep=3)
    n_pix = sum(len(s) for s in stripes)
    assert len(cloud) == n_pix and cloud.report["n_points"] == n_pix
    assert cloud.sweep == 3 and set(cloud.frame_index) == set(range(100, 124))
    # on the plane
    np.testing.assert_allclose(cloud.points_base @ n_true, 0.0, atol=1e-12)
    # normals: the true normal (it faces the camera above), within 1 degree
    ang = np.degrees(np.arccos(np.clip(cloud.normals_base @ n_true, -1, 1)))
    assert ang.max() < 1.0, ang.max()
    to_cam = cloud.sensor_origin_base - cloud.points_base
    assert np.all(np.einsum("ni,ni->n", cloud.normals_base, to_cam) > 0)
    assert cloud.report["normals"]["from_grid"] > 0.9 * n_pix
    # the sensor origins are the camera centres of the frames
    np.testing.assert_allclose(cloud.sensor_origin_base,
                               poses[cloud.frame_index - 100][:, :3, 3])
    assert np.all((cloud.confidence > 0) & (cloud.confidence <= 0.9 + 1e-12))


def test_sweep_with_a_laser_pose_per_frame():
    # T_camera_laser given per frame (F, 4, 4), tangents over +-1 line
    stripes, poses, T_cl, n_true = _plane_sweep(n_frames=6)
    cloud = triangulate_sweep(stripes, CAM, poses, np.broadcast_to(T_cl, (6, 4, 4)),
                              options=TriangulateOptions(normal_span=1))
    assert np.degrees(np.arccos(np.clip(cloud.normals_base @ n_true, -1, 1))).max() < 1.0


def test_sweep_normals_fall_back_to_knn_on_holes():
    stripes, poses, T_cl, n_true = _plane_sweep(n_frames=12)
    rng = np.random.default_rng(5)
    holed = []
    for sp in stripes:  # drop 60 % of each profile at random
        keep = rng.random(len(sp)) < 0.4
        holed.append(StripePoints(u=sp.u[keep], v=sp.v[keep]))
    cloud = triangulate_sweep(holed, CAM, poses, T_cl)
    assert cloud.report["normals"]["from_knn"] > 0.05 * len(cloud)
    ang = np.degrees(np.arccos(np.clip(cloud.normals_base @ n_true, -1, 1)))
    assert ang.max() < 1.0, ang.max()


def test_sweep_normals_of_a_subset_are_those_of_the_whole():
    # the margin's pass computes only the margin's normals (grid and k-NN fallback), each
    # from all the points around it: the same values as computed for every point
    from robo3d.triangulation import _sweep_normals

    stripes, poses, T_cl, _ = _plane_sweep(n_frames=12)
    rng = np.random.default_rng(7)
    holed = []
    for sp in stripes:  # holes, so that some normals come from the k-NN fallback
        keep = rng.random(len(sp)) < 0.5
        holed.append(StripePoints(u=sp.u[keep], v=sp.v[keep]))
    cloud = triangulate_sweep(holed, CAM, poses, T_cl)
    P, O = cloud.points_base, cloud.sensor_origin_base
    fpos = cloud.frame_index - cloud.frame_index.min()
    axis = np.zeros(int(fpos.max()) + 1, dtype=np.int64)
    at = rng.random(len(P)) < 0.3
    for opts in (TriangulateOptions(), TriangulateOptions(normal_smooth=0)):
        full, n_full = _sweep_normals(P, O, fpos, cloud.line, axis, opts)
        assert n_full["from_grid"] > 0 and n_full["from_knn"] > 0
        part, n_part = _sweep_normals(P, O, fpos, cloud.line, axis, opts, at)
        np.testing.assert_array_equal(part[at], full[at])
        assert np.all(np.isnan(part[~at]))
        assert sum(n_part.values()) == int(at.sum())
        assert 0 < n_part["from_knn"] < n_full["from_knn"]


def test_sweep_normals_under_stripe_noise():
    # 0.03 px of stripe noise is ~0.1 mm of depth noise here; the grid normals are
    # averaged over 5 x 5 cells, the raw cross products (normal_smooth=0) are not
    stripes, poses, T_cl, n_true = _plane_sweep(n_frames=12)
    rng = np.random.default_rng(7)
    noisy = [StripePoints(u=sp.u, v=sp.v + rng.normal(0.0, 0.03, len(sp))) for sp in stripes]

    def err(**kw):
        c = triangulate_sweep(noisy, CAM, poses, T_cl, options=TriangulateOptions(**kw))
        return np.degrees(np.arccos(np.clip(c.normals_base @ n_true, -1, 1)))

    smooth, raw = err(), err(normal_smooth=0)
    assert np.median(smooth) < 1.0
    assert np.median(raw) > 2.0 * np.median(smooth)
    # inside the sweep (not its first/last two profiles) the 5 x 5 average is complete
    interior = np.isin(triangulate_sweep(noisy, CAM, poses, T_cl).frame_index, range(2, 10))
    assert np.percentile(smooth[interior], 95) < 2.5


def _cylinder_sweep(axis: str, radius=0.05, n_frames=30, step=0.002):
    """The rig moving along base y over a cylinder lying on z = 0 (axis along base x or
    y); exact stripe pixels per column from the ray-plane-cylinder intersection."""
    T_cl = _rig_laser()
    R_bc = np.diag([1.0, -1.0, -1.0])
    n_s, d_s = laser_plane_in_camera(T_cl)
    u = np.arange(0, 640, dtype=np.float64)
    x_n = (u - CAM.cx) / CAM.fx
    # points of the sheet on column u: x = x_n z, n_s . p = d_s -> a line a + s b
    b = np.cross(np.stack([np.ones_like(x_n), np.zeros_like(x_n), -x_n], 1), n_s)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    a = np.stack([x_n, np.zeros_like(x_n), np.ones_like(x_n)], 1)
    a = a * (d_s / (a @ n_s))[:, None]  # the point of the column plane on the sheet at y = 0
    keep_axes = [1, 2] if axis == "x" else [0, 2]
    poses, stripes = [], []
    for i in range(n_frames):
        T_bc = make_transform(R_bc, [0.003, -0.04 + step * i, 0.40])
        poses.append(T_bc)
        ab = transform_points(T_bc, a)[:, keep_axes]
        bb = (b @ R_bc.T)[:, keep_axes]
        # |ab + s bb|^2 = r^2, the upper (visible) root
        qa = np.sum(bb * bb, 1)
        qb = 2 * np.sum(ab * bb, 1)
        qc = np.sum(ab * ab, 1) - radius**2
        disc = qb * qb - 4 * qa * qc
        ok = disc > 0
        sq = np.sqrt(np.where(ok, disc, 0.0))
        roots = np.stack([(-qb - sq) / (2 * qa), (-qb + sq) / (2 * qa)], 1)
        z = ab[:, 1:2] + roots * bb[:, 1:2]
        sel = np.take_along_axis(roots, np.argmax(z, axis=1)[:, None], 1)[:, 0]
        p_cam = a + sel[:, None] * b
        v = CAM.fy * p_cam[:, 1] / p_cam[:, 2] + CAM.cy
        ok &= (v >= 0) & (v <= 479) & (np.take_along_axis(z, np.argmax(z, 1)[:, None], 1)[:, 0]
                                      > 0.2 * radius)
        stripes.append(StripePoints(u=u[ok], v=v[ok]))
    return stripes, np.stack(poses), T_cl


@pytest.mark.parametrize("axis", ["x", "y"])
def test_sweep_normals_on_a_cylinder(axis):
    # curvature across the profiles (axis x) or along them (axis y), noise-free: the
    # sweep's first and last profiles and the profile ends must not be biased
    radius = 0.05
    stripes, poses, T_cl = _cylinder_sweep(axis, radius)
    cloud = triangulate_sweep(stripes, CAM, poses, T_cl)
    p = cloud.points_base.copy()
    p[:, 0 if axis == "x" else 1] = 0.0
    np.testing.assert_allclose(np.linalg.norm(p, axis=1), radius, atol=1e-12)
    n_true = p / radius
    ang = np.degrees(np.arccos(np.clip(np.sum(cloud.normals_base * n_true, 1), -1, 1)))
    slope = np.degrees(np.arccos(np.clip(np.abs(n_true[:, 2]), 0, 1)))
    assert np.median(ang) < 0.3
    assert ang[slope < 45].max() < 1.0  # first/last profiles and profile ends included
    assert ang.max() < 2.5  # up to ~75 deg of slope, where the samples are sparse


def test_sweep_workspace_cropping():
    stripes, poses, T_cl, _ = _plane_sweep(n_frames=8)
    full = triangulate_sweep(stripes, CAM, poses, T_cl)
    box = (np.array([-1.0, -1.0, -1.0]), np.array([0.0, 1.0, 1.0]))  # keep x <= 0
    expect_out = int((full.points_base[:, 0] > 0).sum())
    assert 0 < expect_out < len(full)
    exact = TriangulateOptions(workspace_margin_m=0.0)
    crop = triangulate_sweep(stripes, CAM, poses, T_cl, workspace=box, options=exact)
    assert crop.report["dropped"]["outside_workspace"] == expect_out
    assert len(crop) == len(full) - expect_out
    assert np.all(crop.points_base[:, 0] <= 0)
    assert crop.report["n_in_margin"] == 0
    # with a margin (the default's 2 mm, and more) the points just outside are kept for
    # alignment to place, and counted
    for m in (TriangulateOptions().workspace_margin_m, 0.05):
        grown = triangulate_sweep(stripes, CAM, poses, T_cl, workspace=box,
                                  options=TriangulateOptions(workspace_margin_m=m))
        x = full.points_base[:, 0]
        assert 0 < int(((x > 0) & (x <= m)).sum()) == grown.report["n_in_margin"]
        assert len(grown) == int((x <= m).sum())
        assert grown.report["dropped"]["outside_workspace"] == int((x > m).sum())
        assert grown.report["workspace_margin_m"] == m
    with pytest.raises(ValueError, match="workspace_margin_m"):
        triangulate_sweep(stripes, CAM, poses, T_cl, workspace=box,
                          options=TriangulateOptions(workspace_margin_m=-1e-3))


def test_empty_sweep_is_a_stage_error():
    empty = [StripePoints.empty(n_lines=640, rejected={"too_weak": 640})] * 3
    poses = np.broadcast_to(np.eye(4), (3, 4, 4))
    with pytest.raises(StageError, match=r"sweep 7: no point .* too_weak=1920"):
        triangulate_sweep(empty, CAM, poses, _rig_laser(), sweep=7)
    with pytest.raises(StageError, match="no laser frame"):
        triangulate_sweep([], CAM, np.zeros((0, 4, 4)), _rig_laser())
    # everything outside the workspace is empty too
    stripes, poses, T_cl, _ = _plane_sweep(n_frames=3)
    with pytest.raises(StageError, match="outside_workspace"):
        triangulate_sweep(stripes, CAM, poses, T_cl,
                          workspace=(np.full(3, 5.0), np.full(3, 6.0)))


def test_sweep_from_rotated_rig_and_pose_errors():
    stripes, poses, T_cl, _ = _plane_sweep(n_frames=4)
    with pytest.raises(ValueError, match="F=4"):
        triangulate_sweep(stripes, CAM, poses[:3], T_cl)
    # a rigid motion of the whole scene moves the cloud with it
    M = make_transform(_rz(0.7) @ _rx(0.3), [0.5, -0.2, 0.1])
    a = triangulate_sweep(stripes, CAM, poses, T_cl)
    b = triangulate_sweep(stripes, CAM, M @ poses, T_cl)
    np.testing.assert_allclose(b.points_base, transform_points(M, a.points_base), atol=1e-12)
    np.testing.assert_allclose(b.normals_base, a.normals_base @ M[:3, :3].T, atol=1e-9)
    assert rotation_angle_deg(M[:3, :3]) > 10


def test_save_load_round_trip(tmp_path):
    stripes, poses, T_cl, _ = _plane_sweep(n_frames=5)
    c0 = triangulate_sweep(stripes[:3], CAM, poses[:3], T_cl, sweep=0)
    c1 = triangulate_sweep(stripes[3:], CAM, poses[3:], T_cl, sweep=1,
                           frame_indices=[3, 4])
    path = tmp_path / "clouds.npz"
    save_clouds_npz(path, [c0, c1])
    assert os.listdir(tmp_path) == ["clouds.npz"]  # no temporary file left behind
    back = load_clouds_npz(path)
    assert [c.sweep for c in back] == [0, 1]
    for a, b in zip([c0, c1], back, strict=True):
        assert isinstance(b, SweepCloud) and len(a) == len(b)
        for name in ("points_base", "normals_base", "frame_index", "confidence",
                     "sensor_origin_base", "line", "line_axis"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert a.report == b.report
        # each point keeps its place on the sweep's range-image grid: its frame and the
        # image line its stripe centre was found on
        g = b.grid()
        assert g.shape == (len(b), 3) and np.array_equal(g[:, 0], b.frame_index)
        lines = np.concatenate([s.line for s in (stripes[:3] if b.sweep == 0 else stripes[3:])])
        assert np.isin(g[:, 1], lines).all()
    # dropping points drops their grid places too
    c = back[0]
    n0 = len(c)
    c.drop(np.arange(n0) % 2 == 0, "test")
    assert len(c.line) == len(c.line_axis) == len(c) == n0 // 2
    # files without the lines (written before they were kept) still load, without a grid
    with np.load(path) as z:
        old = {k: z[k] for k in z.files if k not in ("line", "line_axis")}
    np.savez(tmp_path / "old.npz", **old)
    assert all(c.grid() is None for c in load_clouds_npz(tmp_path / "old.npz"))
    save_clouds_npz(path, [])
    assert load_clouds_npz(path) == []


def test_kernel_equals_the_camera_rays_on_a_large_distorted_camera():
    cam = CameraModel("camera", 1280, 960, K * 2.0 + np.diag([0.0, 0.0, -1.0]), D)
    T_cl = _rig_laser()
    rng = np.random.default_rng(3)
    uv = rng.uniform([0, 0], [1279, 959], size=(2000, 2))
    pts, keep, _ = triangulate_pixels(uv, cam, T_cl, min_angle_deg=0.0)
    rays = cam.rays(uv)  # CameraModel's own undistortion and rays
    n, d = laser_plane_in_camera(T_cl)
    ref = rays * (d / (rays @ n))[:, None]
    ok = keep & (ref[:, 2] > 0)
    assert ok.sum() > 1000
    np.testing.assert_allclose(pts[ok], ref[ok], rtol=1e-12, atol=1e-14)


def test_save_with_corrections(tmp_path):
    stripes, poses, T_cl, _ = _plane_sweep(n_frames=4)
    c0 = triangulate_sweep(stripes, CAM, poses, T_cl, sweep=0)
    path = tmp_path / "aligned.npz"
    corr = np.eye(4)[None].copy()
    corr[0, :3, 3] = [0.001, 0.0, 0.0]
    save_clouds_npz(path, [c0], corrections=corr)
    with np.load(path) as z:
        np.testing.assert_array_equal(z["corrections"], corr)
    assert len(load_clouds_npz(path)[0]) == len(c0)
    with pytest.raises(ValueError, match="corrections"):
        save_clouds_npz(path, [c0], corrections=np.eye(4))


# ---------------------------------------------------------------------------- stages
@pytest.fixture(scope="module")
def sphere_recording(tmp_path_factory):
    from robo3d.simulate import simulate_recording

    path = tmp_path_factory.mktemp("sim") / "sphere.mcap"
    # the demo camera (640 x 480): the stripe is 1.5-1.7 px wide there; at 320 x 240 it
    # would be ~1.1 px, where pixel locking costs any estimator 0.05-0.1 px
    simulate_recording(path, "sphere", views=0, sweeps=2, sweep_frames=10,
                       sweep_error_mm=(0.0, 0.0), sweep_error_deg=(0.0, 0.0))
    return path


def test_stages_on_a_simulated_sphere(sphere_recording, tmp_path):
    import json

    from robo3d.config import default_config
    from robo3d.meshio import read_point_cloud_attributes
    from robo3d.pipeline import stage_stripes, stage_triangulate
    from robo3d.stripes import REJECTION_REASONS

    cfg = default_config()
    out = {k: str(tmp_path / f) for k, f in
           (("npz", "stripes.npz"), ("report", "stripes.json"), ("rrd", "stripes.rrd"))}
    rep = stage_stripes({"recording": str(sphere_recording)}, out, cfg, "sphere", threads=2)
    assert rep["n_frames"] == 20 and rep["threads"] == 2 and rep["n_points"] > 1000
    with np.load(out["npz"]) as z:
        assert z["axis"].shape == (20,) and set(z["axis"]) == {"columns"}
        assert z["rejected"].shape == (20, len(REJECTION_REASONS))
        assert list(z["rejection_reasons"]) == list(REJECTION_REASONS)
        assert z["line"].shape == z["u"].shape
    # the same with one thread: the results do not depend on it
    out1 = {k: str(tmp_path / ("one_" + f)) for k, f in
            (("npz", "stripes.npz"), ("report", "stripes.json"), ("rrd", "stripes.rrd"))}
    stage_stripes({"recording": str(sphere_recording)}, out1, cfg, "sphere", threads=1)
    with np.load(out["npz"]) as a, np.load(out1["npz"]) as b:
        np.testing.assert_array_equal(a["v"], b["v"])

    tout = {k: str(tmp_path / f) for k, f in
            (("npz", "clouds.npz"), ("ply", "clouds.ply"), ("report", "tri.json"),
             ("rrd", "tri.rrd"))}
    trep = stage_triangulate({"stripes": out["npz"]}, tout, cfg, "sphere")
    with open(tout["report"]) as f:
        assert json.load(f)["stripe_rejected"] == rep["rejected"]  # the counts flow on
    assert trep["n_sweeps"] == 2 and trep["n_pixels"] == rep["n_points"]
    clouds = load_clouds_npz(tout["npz"])
    assert sum(len(c) for c in clouds) == trep["n_points"] > 1000
    # the margin around the box holds the table (the align stage crops it); the box's
    # points are the sphere's
    from robo3d.artefacts import in_clouds_workspace

    inb = in_clouds_workspace(clouds)
    assert sum(c.report["n_in_margin"] for c in clouds) == sum(int((~m).sum()) for m in inb)
    P = np.concatenate([c.points_base[m] for c, m in zip(clouds, inb, strict=True)])
    # the truth: a sphere of 40 mm radius at (0, 0, 40 mm) (its facets sag < 0.01 mm)
    err_mm = np.abs(np.linalg.norm(P - [0.0, 0.0, 0.04], axis=1) - 0.04) * 1e3
    assert np.median(err_mm) < 0.025 and np.percentile(err_mm, 95) < 0.1, (
        np.median(err_mm), np.percentile(err_mm, 95))
    # normals point outward, toward the camera
    N = np.concatenate([c.normals_base[m] for c, m in zip(clouds, inb, strict=True)])
    radial = (P - [0.0, 0.0, 0.04]) / np.linalg.norm(P - [0.0, 0.0, 0.04], axis=1)[:, None]
    assert np.median(np.einsum("ij,ij->i", N, radial)) > 0.99
    attrs = read_point_cloud_attributes(tout["ply"])
    assert {"sweep", "frame_index", "confidence"} <= set(attrs)
    np.testing.assert_array_equal(attrs["frame_index"],
                                  np.concatenate([c.frame_index for c in clouds]))
    # the seed's six parameters (eq. 11) of the recording's own laser pose: same cloud
    with np.load(out["npz"]) as z:
        T_cl = z["T_camera_laser"][0]
    dx, dy, dz, phi, theta, psi = laser_params_from_transform(T_cl)
    cfg6 = default_config()
    cfg6["triangulation"]["laser_params"] = [dx, dy, dz, *np.degrees([phi, theta, psi])]
    tout6 = {k: v.replace(".", "_6.") for k, v in tout.items()}
    rep6 = stage_triangulate({"stripes": out["npz"]}, tout6, cfg6, "sphere")
    assert "eq. 11" in rep6["laser_pose"]
    P6 = np.concatenate([c.points_base for c in load_clouds_npz(tout6["npz"])])
    np.testing.assert_allclose(P6, np.concatenate([c.points_base for c in clouds]), atol=1e-9)


def test_points_in_the_box_are_those_of_an_exact_crop():
    """The margin adds points; the box's own points, normals and confidences are those
    an exact crop gives (the alignment registers them as before)."""
    stripes, poses, T_cl, _ = _plane_sweep(n_frames=8)
    full = triangulate_sweep(stripes, CAM, poses, T_cl)
    x = full.points_base[:, 0]
    cut = float(np.median(x))
    box = (np.array([-1.0, -1.0, -1.0]), np.array([cut, 1.0, 1.0]))
    exact = triangulate_sweep(stripes, CAM, poses, T_cl, workspace=box,
                              options=TriangulateOptions(workspace_margin_m=0.0))
    grown = triangulate_sweep(stripes, CAM, poses, T_cl, workspace=box,
                              options=TriangulateOptions(workspace_margin_m=0.01))
    assert grown.report["n_in_margin"] > 0 and len(grown) > len(exact)
    inb = np.all((grown.points_base >= box[0]) & (grown.points_base <= box[1]), axis=1)
    np.testing.assert_array_equal(grown.points_base[inb], exact.points_base)
    np.testing.assert_array_equal(grown.normals_base[inb], exact.normals_base)
    np.testing.assert_array_equal(grown.confidence[inb], exact.confidence)


def test_a_slow_scan_keeps_its_sweeps(tmp_path):
    """A simulated scan whose laser frames come 1.4-1.6 s apart (a stop-and-go cell; two
    sweeps 8 s apart): the stripes and triangulation stages and ``robo3d info`` split it
    into its two sweeps, each with its points (by the 1 s gap alone: 24 one-frame
    sweeps, no range surface; the workflow's mesh was 0 % measured)."""
    import json

    from stages_in_process import stage_outputs

    from robo3d.config import default_config
    from robo3d.info import inspect_recording
    from robo3d.pipeline import stage_stripes, stage_triangulate
    from robo3d.simulate import SimulationParams, simulate_recording

    rec = tmp_path / "slow.mcap"
    simulate_recording(rec, "blob", seed=2, params=SimulationParams.small(
        views=0, sweeps=2, sweep_frames=12, sweep_speed=0.008, sweep_gap_s=8.0))
    assert inspect_recording(rec)["sweeps"]["frames"] == [12, 12]
    assert inspect_recording(rec, sweep_gap_intervals=0.0)["sweeps"]["count"] == 24
    cfg = default_config()
    res = tmp_path / "res"
    (res / "reports").mkdir(parents=True)
    stage_stripes({"recording": str(rec)}, stage_outputs(res, "stripes", npz="stripes.npz"),
                  cfg, "slow")
    stage_triangulate({"stripes": str(res / "stripes.npz")},
                      stage_outputs(res, "triangulate", npz="clouds.npz", ply="clouds.ply"),
                      cfg, "slow")
    rep = json.loads((res / "reports" / "triangulate.json").read_text())
    assert rep["n_sweeps"] == 2
    assert [s["frames"] for s in rep["sweeps"]] == [12, 12]
    assert all(s["points"] > 500 for s in rep["sweeps"]), rep["sweeps"]
