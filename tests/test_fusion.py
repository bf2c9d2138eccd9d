"""fuse_poisson on sampled spheres: accuracy against the analytic surface, the density trim,
the hull cut."""

from __future__ import annotations

import numpy as np
import pytest

from robo3d.errors import StageError
from robo3d.fusion import FuseOptions, crop_mesh_to_hull, fuse_poisson, fuse_tsdf, remove_vertices

R = 0.03
C = np.array([0.5, 0.1, 0.1])


def _sphere_points(n=6000, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return C + R * d, d


def _radial_error(v):
    return np.abs(np.linalg.norm(v - C, axis=1) - R)


def _area(v, f):
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                axis=1).sum()


def _hull(keep_upper_only: bool, vs=2e-3):
    origin = C - 0.04
    shape = (41, 41, 41)
    centres = origin + np.indices(shape).reshape(3, -1).T * vs
    occ = np.linalg.norm(centres - C, axis=1) < R + vs
    if keep_upper_only:
        occ &= centres[:, 2] > C[2]
    return {"origin": origin, "voxel_size": vs, "occupancy": occ.reshape(shape)}


def test_poisson_sphere_accuracy():
    p, n = _sphere_points()
    v, f, rep = fuse_poisson(p, n, options=FuseOptions(poisson_depth=7))
    err = _radial_error(v)
    assert err.mean() < 0.1e-3  # measured ~0.01 mm
    assert err.max() < 0.3e-3
    # a closed sphere less the 2 % least supported vertices: nearly all the area
    assert _area(v, f) == pytest.approx(4 * np.pi * R**2, rel=0.05)
    assert rep["n_points"] == 6000 and rep["n_faces"] == len(f) and rep["n_vertices"] == len(v)
    assert rep["n_vertices_low_density"] == pytest.approx(0.02 * rep["n_vertices_poisson"],
                                                          abs=2)
    assert f.dtype == np.int64 and f.max() < len(v)


def test_density_trim_removes_unsupported_surface():
    # points on the upper cap only (z > 2 mm): Poisson extends the surface below, unsupported
    p, n = _sphere_points(8000, seed=1)
    up = p[:, 2] > C[2] + 2e-3
    cap_area = 2 * np.pi * R * (R - 2e-3)

    def area_below(v, f):
        return _area(v, f[v[f].mean(axis=1)[:, 2] < C[2] - 5e-3])

    v0, f0, rep0 = fuse_poisson(p[up], n[up], options=FuseOptions(poisson_depth=6,
                                                                    density_quantile=0.0))
    v1, f1, rep1 = fuse_poisson(p[up], n[up], options=FuseOptions(poisson_depth=6,
                                                                    density_quantile=0.1))
    assert area_below(v0, f0) > 0.05 * cap_area and rep0["n_vertices_low_density"] == 0
    assert area_below(v1, f1) == 0.0 and rep1["n_vertices_low_density"] > 0
    assert _area(v1, f1) > 0.95 * cap_area  # the measured cap stays


def test_hull_cut_removes_surface_outside_hull():
    p, n = _sphere_points()
    hull = _hull(keep_upper_only=True)
    # half the points lie outside this hull: forced cut (the guard is tested below)
    v, f, rep = fuse_poisson(p, n, options=FuseOptions(poisson_depth=6), hull=hull,
                             cut_margin_voxels=1, max_outside_fraction=1.0)
    assert rep["hull_cut"] == "applied"
    # nothing below the upper half-space dilated by one voxel (+ half a voxel rounding)
    assert v[:, 2].min() >= C[2] - 1.5 * hull["voxel_size"]
    # and the upper half is all there
    assert v[:, 2].max() > C[2] + R - 0.1e-3
    assert _area(v, f) == pytest.approx(2 * np.pi * R**2, rel=0.1)
    assert rep["n_vertices_outside_hull"] > 0.4 * rep["n_vertices_poisson"]
    # a full hull cuts nothing
    _, _, rep_full = fuse_poisson(p, n, options=FuseOptions(poisson_depth=6),
                                  hull=_hull(keep_upper_only=False))
    assert rep_full["n_vertices_outside_hull"] == 0
    assert rep_full["hull_points_outside_fraction"] == 0.0


def test_hull_cut_trims_extrapolation_and_is_guarded():
    p, n = _sphere_points(8000, seed=1)
    up = p[:, 2] > C[2] + 2e-3  # measured: the upper cap; Poisson extrapolates below
    hull = _hull(keep_upper_only=True)
    v, f, rep = fuse_poisson(p[up], n[up], options=FuseOptions(
        poisson_depth=6, density_quantile=0.0), hull=hull)
    assert rep["hull_cut"] == "applied" and rep["hull_points_outside_fraction"] == 0.0
    assert v[:, 2].min() >= C[2] - 1.5 * hull["voxel_size"]
    assert rep["n_vertices_outside_hull"] > 0
    # the guard: when the laser points disagree with the hull, the hull does not cut
    v2, f2, rep2 = fuse_poisson(p, n, options=FuseOptions(poisson_depth=6), hull=hull)
    assert rep2["hull_cut"].startswith("skipped")
    assert rep2["hull_points_outside_fraction"] == pytest.approx(0.5, abs=0.03)
    assert rep2["n_vertices"] == rep2["n_vertices_poisson"] - rep2["n_vertices_low_density"]
    assert v2[:, 2].min() < C[2] - R + 0.5e-3


def test_crop_mesh_to_hull_off_grid_and_object_hull():
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [5.0, 5.0, 5.0]])
    f = np.array([[0, 1, 2], [1, 2, 3]])

    class Grid:  # attribute access, like robo3d's VoxelGrid
        origin = np.zeros(3)
        voxel_size = 1.0
        occupancy = np.ones((2, 2, 1), dtype=bool)

    v2, f2, n_out = crop_mesh_to_hull(v, f, Grid(), margin_voxels=0)
    assert n_out == 1
    np.testing.assert_array_equal(v2, v[:3])
    np.testing.assert_array_equal(f2, [[0, 1, 2]])


def test_remove_vertices_renumbers():
    v = np.arange(15, dtype=float).reshape(5, 3)
    f = np.array([[0, 1, 2], [2, 3, 4], [0, 2, 4]])
    v2, f2 = remove_vertices(v, f, np.array([True, False, True, True, True]))
    np.testing.assert_array_equal(v2, v[[0, 2, 3, 4]])
    np.testing.assert_array_equal(v2[f2], v[f[1:]])


def test_lists_reproducible_and_errors():
    p, n = _sphere_points(3000)
    a = fuse_poisson([p[:1000], p[1000:]], [n[:1000], n[1000:]],
                     options=FuseOptions(poisson_depth=6))
    b = fuse_poisson(p, n, options=FuseOptions(poisson_depth=6))
    np.testing.assert_array_equal(a[0], b[0])  # single-threaded Poisson: bit-identical
    np.testing.assert_array_equal(a[1], b[1])
    with pytest.raises(StageError, match="at least 10"):
        fuse_poisson(p[:5], n[:5])
    with pytest.raises(ValueError, match="normals must match"):
        fuse_poisson(p, n[:10])
    with pytest.raises(ValueError, match="hull must have"):
        fuse_poisson(p, n, options=FuseOptions(poisson_depth=5), hull={"origin": C})
    with pytest.raises(ValueError, match="density_quantile"):
        fuse_poisson(p, n, options=FuseOptions(density_quantile=1.0))


def _views_of_sphere(n_per_view=15000, axes=None, seed=0):
    """Points of the sphere visible from sensors 0.3 m away along the given axes."""
    rng = np.random.default_rng(seed)
    axes = np.vstack([np.eye(3), -np.eye(3)]) if axes is None else np.asarray(axes, float)
    pts, nrm, org = [], [], []
    for ax in axes:
        o = C + 0.3 * ax
        d = rng.normal(size=(n_per_view, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        p = C + R * d
        vis = np.einsum("ij,ij->i", o - p, d) > 0
        pts.append(p[vis])
        nrm.append(d[vis])
        org.append(np.repeat(o[None], vis.sum(), axis=0))
    return pts, nrm, org


def _signed_volume(v, f):
    t = v[f] - C
    return np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6


def _exact_hull(vs=2e-3):
    origin = C - 0.04
    shape = (41, 41, 41)
    centres = origin + np.indices(shape).reshape(3, -1).T * vs
    return {"origin": origin, "voxel_size": vs,
            "occupancy": (np.linalg.norm(centres - C, axis=1) < R).reshape(shape)}


def _edge_uses(f):
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def test_tsdf_sphere_from_six_views():
    from robo3d.fusion import FuseOptions, fuse_tsdf

    pts, nrm, org = _views_of_sphere()
    v, f, rep = fuse_tsdf(pts, nrm, org, max_edge_factor=3.0,
                          options=FuseOptions(tsdf_voxel_m=1e-3, tsdf_trunc_voxels=3))
    err = _radial_error(v)
    assert err.mean() < 0.03e-3  # measured 0.019 mm with 1 mm voxels
    assert err.max() < 0.25e-3  # measured 0.18 mm
    # closed and facing outward: the signed volume is the sphere's
    assert _signed_volume(v, f) == pytest.approx(4 / 3 * np.pi * R**3, rel=0.01)
    assert _area(v, f) == pytest.approx(4 * np.pi * R**2, rel=0.01)
    assert np.all(_edge_uses(f) == 2)
    assert 0.8 * rep["n_points"] < rep["n_points_used"] <= rep["n_points"]
    assert rep["laser_area_fraction"] == 1.0 and rep["n_faces"] == len(f)
    assert rep["n_scans"] == 6 and len(rep["range_surfaces"]) == 6


def test_tsdf_invents_no_surface_where_nothing_was_seen():
    from robo3d.fusion import FuseOptions, fuse_tsdf

    # one sensor above: only the upper cap is seen (grazing parts dropped by min_cos_view)
    pts, nrm, org = _views_of_sphere(20000, axes=[[0.0, 0.0, 1.0]])
    v, f, rep = fuse_tsdf(pts, nrm, org, options=FuseOptions(tsdf_voxel_m=0.5e-3, min_cos_view=0.3))
    assert _radial_error(v).mean() < 0.02e-3  # measured 0.006 mm
    # cos >= 0.3 keeps roughly z > 0.3 R: nothing below
    assert v[:, 2].min() > C[2] + 0.2 * R
    assert _area(v, f) < 2 * np.pi * R**2 * 0.75
    assert "no hull" in rep["hull_fill"]
    # zero confidence removes a view entirely: the bottom cap, which only the -z view
    # sees at cos >= 0.3, opens
    pts6, nrm6, org6 = _views_of_sphere(8000)
    opts = FuseOptions(tsdf_voxel_m=1e-3, min_cos_view=0.3)
    v1, _, _ = fuse_tsdf(pts6, nrm6, org6, options=opts)
    assert v1[:, 2].min() < C[2] - 0.99 * R
    conf = [np.full(len(p), 1.0 if k != 5 else 0.0) for k, p in enumerate(pts6)]
    v2, _, rep2 = fuse_tsdf(pts6, nrm6, org6, options=opts, confidences=conf)
    assert v2[:, 2].min() > C[2] - 0.97 * R
    assert rep2["n_points_used"] < rep2["n_points"] - len(pts6[5]) * 0.99


def test_tsdf_single_grazing_view_makes_no_surface():
    """The minimum-weight guard: one view of a plane at cos 0.2 stays below min_weight
    0.3 everywhere; with a lower guard the same view makes surface."""
    from robo3d.fusion import FuseOptions, fuse_tsdf

    rng = np.random.default_rng(0)
    n = 20000
    p = np.c_[rng.uniform(-0.02, 0.02, (n, 2)), np.zeros(n)] + C
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    ang = np.arccos(0.2)
    o = np.tile(C + 0.3 * np.array([np.sin(ang), 0.0, np.cos(ang)]), (n, 1))
    v, f, rep = fuse_tsdf([p], [nrm], [o], options=FuseOptions(tsdf_voxel_m=0.5e-3, min_weight=0.3))
    assert len(f) == 0 and rep["n_voxels_observed"] == 0
    v, f, _ = fuse_tsdf([p], [nrm], [o], options=FuseOptions(tsdf_voxel_m=0.5e-3, min_weight=0.1))
    assert len(f) > 1000 and np.abs(v[:, 2] - C[2]).max() < 0.05e-3


def test_tsdf_holes_closed_from_the_hull():
    """Seen from above only, with the sphere's hull: a closed mesh, the seen cap from the
    laser (exact), the rest from the hull (within its 2 mm voxels)."""
    from robo3d.fusion import FuseOptions, fuse_tsdf

    pts, nrm, org = _views_of_sphere(20000, axes=[[0.0, 0.0, 1.0]])
    v, f, rep = fuse_tsdf(pts, nrm, org, options=FuseOptions(tsdf_voxel_m=1e-3), hull=_exact_hull(),
                          max_edge_factor=3.0)
    assert np.all(_edge_uses(f) == 2)  # watertight
    err = _radial_error(v)
    assert err[v[:, 2] > C[2] + 0.5 * R].max() < 0.08e-3  # laser: measured 0.036 mm
    low = v[:, 2] < C[2] - 0.3 * R
    assert err[low].mean() < 0.4e-3  # hull: measured 0.20 mm with 2 mm hull voxels
    assert _signed_volume(v, f) == pytest.approx(4 / 3 * np.pi * R**3, rel=0.04)
    # the report says what came from where: about the cap seen at cos >= 0.1
    assert 0.2 < rep["laser_area_fraction"] < 0.45  # measured 0.28
    assert rep["hull_area_fraction"] == pytest.approx(1 - rep["laser_area_fraction"])
    assert "closed from the hull" in rep["hull_fill"]


def test_tsdf_a_hull_the_laser_contradicts_closes_nothing():
    """Silhouettes that failed in many views carve a hull far smaller than the object:
    most of what the laser measured lies outside it. Such a hull bounds nothing; it
    closes nothing (the mesh is the measured cap, labelled so), where a hull that holds
    the measurements closes the sphere."""
    from robo3d.fusion import FuseOptions, fuse_tsdf

    pts, nrm, org = _views_of_sphere(20000, axes=[[0.0, 0.0, 1.0]])
    small = _exact_hull()
    origin, vs = small["origin"], small["voxel_size"]
    centres = origin + np.indices(small["occupancy"].shape).reshape(3, -1).T * vs
    small["occupancy"] = (np.linalg.norm(centres - C, axis=1) < 0.4 * R).reshape(
        small["occupancy"].shape)  # a hull 40 % of the object's size, inside it
    opts = FuseOptions(tsdf_voxel_m=1e-3)
    v, f, rep = fuse_tsdf(pts, nrm, org, options=opts, hull=small, max_edge_factor=3.0)
    assert rep["hull_contradicted"] is True and rep["close"] == "none"
    assert rep["observed_solid_outside_hull_fraction"] > 0.9
    assert "contradicts the laser" in rep["hull_fill"]
    assert rep["laser_area_fraction"] == 1.0 and rep["hull_area_fraction"] == 0.0
    assert v[:, 2].min() > C[2]  # the seen cap only: nothing closed below
    assert _radial_error(v).mean() < 0.03e-3
    v2, f2, rep2 = fuse_tsdf(pts, nrm, org, options=opts, hull=_exact_hull(),
                             max_edge_factor=3.0)
    assert not rep2.get("hull_contradicted") and rep2["observed_solid_outside_hull_fraction"] < 0.2
    assert np.all(_edge_uses(f2) == 2) and v2[:, 2].min() < C[2] - 0.9 * R
    # a lenient bound lets the small hull close the mesh
    v3, _, rep3 = fuse_tsdf(pts, nrm, org, options=FuseOptions(
        tsdf_voxel_m=1e-3, max_outside_hull_fraction=1.0), hull=small, max_edge_factor=3.0)
    assert not rep3.get("hull_contradicted") and rep3["hull_area_fraction"] > 0


def test_range_surface_cuts_depth_jumps():
    from robo3d.fusion import range_surface

    # two parallel squares 10 mm apart in depth, side by side as seen from the sensor
    g = np.stack(np.meshgrid(np.arange(40), np.arange(20)), -1).reshape(-1, 2) * 0.5e-3
    near = np.c_[g[:, 0], g[:, 1], np.zeros(len(g))]
    far = np.c_[g[:, 0] + 20.5e-3, g[:, 1], np.full(len(g), -10e-3)]
    p = np.vstack([near, far])
    o = np.tile([0.01, 0.005, 0.3], (len(p), 1))
    faces, rep = range_surface(p, o)
    assert rep["n_triangles"] < rep["n_triangles_delaunay"]
    z = p[faces][:, :, 2]
    assert np.all(z.max(axis=1) - z.min(axis=1) < 1e-9)  # no triangle bridges the jump
    # every kept triangle faces the sensor
    v0, v1, v2 = (p[faces[:, k]] for k in range(3))
    assert np.all(np.cross(v1 - v0, v2 - v0)[:, 2] > 0)


def _grazing_scan(cos_view=0.07, step_frame=3e-3, step_line=1.5e-3, frames=20, lines=20):
    """One sweep of the plane z = C_z on its range-image grid (frame x line), seen from a
    sensor at a grazing angle (``cos_view`` between its sight lines and the normal), as
    a cup's inner wall is from above: sampled ``step_frame`` apart between profiles."""
    f, l = np.meshgrid(np.arange(frames), np.arange(lines), indexing="ij")
    f, l = f.ravel(), l.ravel()
    p = C + np.c_[f * step_frame, l * step_line, np.zeros(len(f))] - [0.03, 0.015, 0.0]
    ang = np.arccos(cos_view)
    o = p + 0.3 * np.array([-np.sin(ang), 0.0, cos_view])
    nrm = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    return p, nrm, o, np.c_[f, l, np.zeros(len(f), np.int64)]


def test_range_surface_on_the_grid_keeps_grazing_surface_and_cuts_jumps():
    """On the range-image grid a surface seen at 86 degrees, sampled 3 mm apart, is a
    surface (the local sampling, not the scan's, says what a jump is); projected along
    the mean sight line it is not. A depth jump between grid neighbours stays cut."""
    from robo3d.fusion import range_surface

    p, n, o, g = _grazing_scan()
    # the rest of the scan: a frontal square sampled 0.5 mm apart, on later frames
    ff, ll = np.meshgrid(np.arange(40), np.arange(40), indexing="ij")
    q = np.c_[ff.ravel() * 0.5e-3, ll.ravel() * 0.5e-3, np.full(ff.size, 0.05)] + C
    pts = np.vstack([p, q])
    org = np.vstack([o, q + [0.0, 0.0, 0.3]])
    grid = np.vstack([g, np.c_[ff.ravel() + 100, ll.ravel(), np.zeros(ff.size, np.int64)]])
    nrm = np.vstack([n, np.tile([0.0, 0.0, 1.0], (ff.size, 1))])
    n_cells = 2 * 19 * 19
    faces, rep = range_surface(pts, org, grid=grid, normals=nrm, min_cos_view=0.03)
    on_plane = np.all(faces < len(p), axis=1)
    assert on_plane.sum() >= 0.95 * n_cells
    # without the points' normals a triangle longer than the scan's threshold is not
    # trusted (a bridge over a jump can be sparse on both sides too)
    faces_nn, _ = range_surface(pts, org, grid=grid, min_cos_view=0.03)
    assert np.all(faces_nn < len(p), axis=1).sum() < 0.2 * n_cells
    # nor where the points' normals disagree with the triangles' (a bridge's are steep)
    tilted = nrm.copy()
    tilted[: len(p)] = [np.sin(0.6), 0.0, np.cos(0.6)]  # 34 degrees off
    faces_t, _ = range_surface(pts, org, grid=grid, normals=tilted, min_cos_view=0.03)
    assert np.all(faces_t < len(p), axis=1).sum() < 0.2 * n_cells
    faces_proj, _ = range_surface(pts, org, normals=nrm, min_cos_view=0.03)
    assert np.all(faces_proj < len(p), axis=1).sum() < 0.2 * n_cells
    # a 10 mm depth jump between neighbouring lines of every frame
    gg = np.stack(np.meshgrid(np.arange(30), np.arange(40), indexing="ij"), -1).reshape(-1, 2)
    z = np.where(gg[:, 1] < 20, 0.0, -10e-3)
    p2 = np.c_[gg[:, 0] * 1e-3, gg[:, 1] * 0.5e-3, z]
    o2 = np.tile([0.015, 0.01, 0.3], (len(p2), 1))
    g2 = np.c_[gg, np.zeros(len(gg), np.int64)]
    n2 = np.tile([0.0, 0.0, 1.0], (len(p2), 1))
    faces2, _ = range_surface(p2, o2, grid=g2, normals=n2, min_cos_view=0.03)
    zz = p2[faces2][:, :, 2]
    assert len(faces2) > 0.9 * 2 * 29 * 38
    assert np.all(zz.max(axis=1) - zz.min(axis=1) < 1e-9)  # no triangle bridges it
    # frames searched along the other image axis are not joined line for line
    g3 = g2.copy()
    g3[gg[:, 0] >= 15, 2] = 1
    faces3, _ = range_surface(p2, o2, grid=g3, normals=n2, min_cos_view=0.03)
    ax = g3[faces3, 2]
    assert np.all(ax.min(axis=1) == ax.max(axis=1))
    with pytest.raises(ValueError, match="grid"):
        range_surface(p2, o2, grid=g2[:, :2])


def test_range_surface_does_not_bridge_frames_that_saw_nothing():
    """A frontal plane swept 1 mm a frame: frames 0-9 found the stripe but frame 4, the
    later ones only every fifth frame (a black band that returns the laser now and then).
    Between those the laser did not see the plane, and the scan there is sparse
    everywhere, so the depth-jump test (against the local sampling) keeps the 5 mm
    bridges: with ``max_frame_span`` 2 no range triangle joins frames more than 2 apart
    and fusion measures nothing between them, while the missing frame 4 is still bridged.
    With any span (0) the bridges are fused as measured surface (random scene 299)."""
    from robo3d.fusion import MEASURED, range_surface

    frames = [f for f in range(10) if f != 4] + list(range(14, 40, 5))
    ff, ll = np.meshgrid(frames, np.arange(30), indexing="ij")
    ff, ll = ff.ravel(), ll.ravel()
    p = C + np.c_[ff * 1e-3, ll * 0.5e-3, np.zeros(len(ff))]
    o = p + [0.0, 0.0, 0.3]
    nrm = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    g = np.c_[ff, ll, np.zeros(len(ff), np.int64)]
    faces, rep = range_surface(p, o, grid=g, normals=nrm, min_cos_view=0.03,
                               max_frame_span=2)
    lo, hi = g[faces, 0].min(axis=1), g[faces, 0].max(axis=1)
    assert (hi - lo).max() == 2 and rep["n_triangles_over_frames"] > 0
    assert np.any((lo == 3) & (hi == 5)) and not np.any(hi >= 14)
    faces_any, rep_any = range_surface(p, o, grid=g, normals=nrm, min_cos_view=0.03)
    assert "n_triangles_over_frames" not in rep_any
    assert np.any((g[faces_any, 0].min(axis=1) == 24) & (g[faces_any, 0].max(axis=1) == 29))
    opts = dict(tsdf_voxel_m=0.4e-3, tsdf_voxel_per_spacing=0)
    for span_opt, bridged in ((2, False), (0, True)):
        v, f, _, a = fuse_tsdf([p], [nrm], [o], grids=[g], return_attributes=True,
                               options=FuseOptions(**opts, max_frame_span=span_opt))
        x = (v[:, 0] - C[0]) * 1e3
        meas = a["source"] == MEASURED
        assert np.any(meas & (np.abs(x - 4.0) < 0.3))  # the missing frame 4
        assert np.any(meas & (x > 25.5) & (x < 27.5)) == bridged
        assert np.abs(v[meas, 2] - C[2]).max() < 0.05e-3


def test_the_fuse_summary_names_many_dropped_bridges_only():
    """The stage's summary line says what share of the range triangles the frame-span rule
    dropped when it is 1 % or more (random scene 299: 22 %), and nothing for the few a
    dense scan loses (cup/4: 11 of 130,000)."""
    from robo3d.stages.fuse import _bridges_note

    sweeps = [{"n_triangles_delaunay": 573}, {"n_triangles_delaunay": 560}]
    note = _bridges_note({"n_range_triangles_over_frames": 255, "range_surfaces": sweeps}, 2)
    assert note.startswith("; 23% of the range triangles joined laser frames more than 2")
    assert _bridges_note({"n_range_triangles_over_frames": 11,
                          "range_surfaces": [{"n_triangles_delaunay": 130_000}]}, 2) == ""
    assert _bridges_note({"range_surfaces": sweeps}, 2) == ""  # Poisson, or no laser
    assert _bridges_note({}, 2) == ""


def test_tsdf_measures_a_surface_seen_only_at_a_grazing_angle():
    """A plane that one sweep saw only at 86 degrees (cos 0.07), 3 mm between profiles:
    the voxels within the band along its normal get their distance, so the surface is
    measured (labelled so) and lies on the plane; with the lines of sight's own band
    (trunc * cos: a tenth of a voxel) it would be left to the hull."""
    from robo3d.fusion import MEASURED, FuseOptions, fuse_tsdf

    p, nrm, o, g = _grazing_scan()
    v, f, rep, a = fuse_tsdf([p], [nrm], [o], grids=[g], return_attributes=True,
                             options=FuseOptions(tsdf_voxel_m=0.4e-3))
    meas = a["source"] == MEASURED
    assert meas.all() and len(f) > 0
    assert np.abs(v[:, 2] - C[2]).max() < 0.05e-3
    # much of the strip (57 x 28.5 mm; the border ramp and the 1.9 mm voxels, 1.25 x the
    # 1.5 mm sampling, take its rim): measured 46 % on an Intel Xeon, 31.8 % on an AMD
    # EPYC (stop 32: the same with the plane moved off the voxel grid, with numpy 2.3,
    # scipy 1.16 or scikit-image 0.25, and on one thread; the CPU's own floating point on
    # rays this oblique, not followed further). Left to the hull it would be none.
    assert _area(v, f) > 0.25 * (19 * 3e-3) * (19 * 1.5e-3)
    with pytest.raises(ValueError, match="grids"):
        fuse_tsdf([p], [nrm], [o], grids=[g[:10]])


def test_tsdf_keeps_what_only_a_scans_edge_saw():
    """A strip two profiles wide (every point on its range surface's border: a thin
    wall's face seen by one sweep's last frames) is measured, on the plane; with Curless
    & Levoy's ramp to zero at the border (``border_weight_floor`` 0) it weighs nothing
    and no surface is left."""
    from robo3d.fusion import MEASURED, FuseOptions, fuse_tsdf

    p, nrm, o, g = _grazing_scan(cos_view=0.5, step_frame=1.0e-3, step_line=0.5e-3,
                                 frames=2, lines=40)
    opts = dict(tsdf_voxel_m=0.2e-3, tsdf_voxel_per_spacing=0)
    v, f, rep, a = fuse_tsdf([p], [nrm], [o], grids=[g], return_attributes=True,
                             options=FuseOptions(**opts))
    assert (a["source"] == MEASURED).all() and np.abs(v[:, 2] - C[2]).max() < 0.02e-3
    assert _area(v, f) > 0.8 * 1e-3 * 19.5e-3  # the strip, 1 x 19.5 mm (measured 23 mm2)
    v0, f0, rep0 = fuse_tsdf([p], [nrm], [o], grids=[g],
                             options=FuseOptions(**opts, border_weight_floor=0.0))
    assert len(f0) == 0 and rep0["n_voxels_observed"] == 0
    with pytest.raises(ValueError, match="border_weight_floor"):
        fuse_tsdf([p], [nrm], [o], grids=[g], options=FuseOptions(border_weight_floor=1.5))


def test_tsdf_nothing_below_the_workspace_floor():
    """The object stands on the workspace's floor: space below it is empty, so no
    surface (measured or inferred) reaches under it, and the cut is closed from the
    hull and labelled inferred, not measured."""
    from robo3d.fusion import HULL, MEASURED, FuseOptions, fuse_tsdf

    pts, nrm, org = _views_of_sphere(8000)
    floor = C[2] - 0.5 * R
    box = (C - [0.05, 0.05, 0.5 * R], C + 0.05)  # the workspace box: its floor cuts the sphere
    v, f, rep, a = fuse_tsdf(pts, nrm, org, options=FuseOptions(tsdf_voxel_m=1e-3),
                             hull=_exact_hull(), workspace=box, return_attributes=True)
    assert v[:, 2].min() > floor - 1e-3  # within a voxel of the floor
    assert v[a["source"] == MEASURED, 2].min() > floor
    assert np.all(_edge_uses(f) == 2)  # closed across the floor
    disk_r = np.sqrt(R**2 - (0.5 * R) ** 2)
    cut = (v[:, 2] < floor + 0.5e-3) & (np.hypot(v[:, 0] - C[0], v[:, 1] - C[1]) < 0.8 * disk_r)
    assert cut.sum() > 100 and np.all(a["source"][cut] == HULL)
    assert rep["n_observed_voxels_outside_workspace"] > 0  # the bands reached below it
    v0, _, _ = fuse_tsdf(pts, nrm, org, options=FuseOptions(tsdf_voxel_m=1e-3),
                         hull=_exact_hull())
    assert v0[:, 2].min() < C[2] - 0.99 * R


def test_tsdf_errors():
    from robo3d.fusion import FuseOptions, fuse_tsdf

    pts, nrm, org = _views_of_sphere(500, axes=[[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="sensor_origins"):
        fuse_tsdf(pts, nrm, [o[:10] for o in org])
    with pytest.raises(StageError, match="no point is usable"):
        fuse_tsdf(pts, [-n for n in nrm], org)  # normals facing away from the sensor
    with pytest.raises(ValueError, match="min_weight"):
        fuse_tsdf(pts, nrm, org, options=FuseOptions(min_weight=0.0))


def test_tsdf_grid_too_large_is_fused_coarser_and_says_so():
    """A scene larger than the grid allows at the voxel asked for (a loose hull from few
    views, the laser's line far across a table) is fused at a coarser voxel, reported,
    instead of failing the job (random scenes 227, 233 and 238 without their workspace
    box: grids of 68-286 million voxels)."""
    from robo3d.fusion import FuseOptions, fuse_tsdf

    pts, nrm, org = _views_of_sphere(4000)
    opts = FuseOptions(tsdf_voxel_m=2e-4, tsdf_voxel_per_spacing=0.0)
    v, f, rep = fuse_tsdf(pts, nrm, org, options=opts, max_voxels=300_000)
    assert rep["voxel_coarsened_from"] == pytest.approx(2e-4)
    assert rep["voxel_size"] > 2e-4 and np.prod(rep["grid_shape"]) <= 300_000
    assert "would have had" in rep["voxel_coarsened_why"]
    assert rep["voxel_from"] == "max_voxels" and not rep["voxel_from_spacing"]
    d = np.abs(np.linalg.norm(v - C, axis=1) - R)
    assert len(f) > 1000 and np.median(d) < 0.25 * rep["voxel_size"]
    _, _, fine = fuse_tsdf(pts, nrm, org, options=opts.replace(tsdf_voxel_m=1e-3))
    assert "voxel_coarsened_from" not in fine  # within the limit: as asked
    assert fine["voxel_from"] == "tsdf_voxel_m"


def test_tsdf_provenance_per_vertex_and_close_modes():
    """Seen from above only, with the sphere's hull: every vertex says where it came
    from; the measured cap is the laser's (and identical whatever is done below it); the
    hull's part is labelled, far from any measurement, and left out on request."""
    from robo3d.fusion import CLOSE_MODES, HULL, MEASURED, FuseOptions, face_source, fuse_tsdf

    pts, nrm, org = _views_of_sphere(20000, axes=[[0.0, 0.0, 1.0]])
    out = {}
    for close in CLOSE_MODES:
        out[close] = fuse_tsdf(pts, nrm, org, options=FuseOptions(
            tsdf_voxel_m=1e-3, close=close, max_fill_distance_mm=3.0), hull=_exact_hull(),
            max_edge_factor=3.0, return_attributes=True)
    v, f, rep, a = out["hull"]
    assert set(a) == {"source", "n_obs", "incidence", "tsdf_weight", "dist_measured_m",
                      "confidence", "far_from_measured"}
    assert np.array_equal(a["far_from_measured"] > 0,
                          (a["source"] != MEASURED) & (a["dist_measured_m"] > 3e-3))
    assert a["far_from_measured"][v[:, 2] < C[2] - 0.5 * R].all()
    assert all(len(x) == len(v) for x in a.values())
    meas = a["source"] == MEASURED
    err = _radial_error(v)
    # measured vertices are on the seen cap; hull vertices below, 2 mm voxels. The cap
    # reaches 81 degrees from the top (77 before the distances were taken along the
    # normal); with 1 mm voxels median 0.006 mm, p99 0.085, worst 0.23 mm at 72 degrees,
    # where one voxel in front is weighted 0.04 and the tangent plane at its ray's hit
    # passes closer than the curved surface (before: 0.010, 0.067 and 0.105 mm); with the
    # border ramp's floor (0.1, was 0: that voxel's scan edge now weighs a little) the
    # same vertex is 0.31 mm off, 49 vertices of 6,479 more than 0.1 mm (46 before)
    assert v[meas, 2].min() > C[2] - 0.1 * R and np.degrees(np.arccos(
        (v[meas, 2].min() - C[2]) / R)) > 79
    assert np.median(err[meas]) < 0.01e-3 and np.percentile(err[meas], 99) < 0.1e-3
    assert err[meas].max() < 0.35e-3
    assert np.all(a["source"][v[:, 2] < C[2] - 0.3 * R] == HULL)
    assert np.all(a["n_obs"][meas] >= 1) and np.all(a["confidence"][~meas] == 0)
    assert np.all((a["incidence"][meas] > 0) & (a["incidence"][meas] <= 1))
    assert np.median(a["dist_measured_m"][meas]) < 1e-3  # 1 mm voxels
    assert a["dist_measured_m"][v[:, 2] < C[2] - 0.5 * R].min() > 5e-3  # far below
    fs = face_source(f, a["source"])
    assert rep["source_area_fraction"]["measured"] == pytest.approx(
        rep["laser_area_fraction"], abs=1e-9)
    assert np.all(fs[np.all(meas[f], axis=1)] == MEASURED)
    # free_space: the part far from any measurement is left open, the rest kept
    v2, f2, rep2, a2 = out["free_space"]
    assert a2["dist_measured_m"][a2["source"] != MEASURED].max() <= 3e-3
    assert rep2["n_vertices_left_open_far_from_measured"] > 0
    assert len(f2) < len(f) and np.any(_edge_uses(f2) == 1)  # open
    # none: only the measured surface
    v3, f3, _, a3 = out["none"]
    assert np.all(a3["source"] == MEASURED) and len(f3) < len(f2)
    # inferred surface never moves measured surface: the measured vertices that every
    # mode keeps are at the same places
    for vv, aa in ((v2, a2), (v3, a3)):
        m = vv[aa["source"] == MEASURED]
        common = np.isin(m.round(9).view("f8,f8,f8"), v[meas].round(9).view("f8,f8,f8"))
        assert common.mean() > 0.95
    with pytest.raises(ValueError, match="close"):
        fuse_tsdf(pts, nrm, org, options=FuseOptions(close="everything"))


def test_tsdf_lines_of_sight_open_a_deep_cavity_the_hull_closes():
    """A block with a 40 mm deep open pocket, seen from above: the laser measures the top
    and the pocket's floor; the hull (the views cannot see into the pocket) is the full
    block. The lines of sight that saw the floor pass through the opening: carved to
    their end they keep the pocket open; carved 20 mm only, the hull's lid closes it."""
    from robo3d.fusion import MEASURED, FuseOptions, fuse_tsdf

    rng = np.random.default_rng(1)
    top, floor, half, pocket = 0.05, 0.01, 0.03, 0.015  # z of top and floor; half sizes
    n = 25000
    xy = rng.uniform(-half, half, (n, 2))
    on_top = np.any(np.abs(xy) > pocket, axis=1)
    p_top = np.c_[xy[on_top], np.full(on_top.sum(), top)]
    xy2 = rng.uniform(-pocket + 1e-3, pocket - 1e-3, (n // 3, 2))
    p_floor = np.c_[xy2, np.full(len(xy2), floor)]
    p = np.vstack([p_top, p_floor])
    o = np.tile([0.0, 0.0, 0.35], (len(p), 1))
    nrm = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    vs = 2e-3
    shape = (40, 40, 34)
    origin = np.array([-0.039, -0.039, -0.007])
    centres = origin + np.indices(shape).reshape(3, -1).T * vs
    occ = (np.all(np.abs(centres[:, :2]) < half, axis=1) & (centres[:, 2] > 0)
           & (centres[:, 2] < top)).reshape(shape)
    hull = {"origin": origin, "voxel_size": vs, "occupancy": occ}
    lid = {}
    for full in (True, False):
        v, f, rep, a = fuse_tsdf([p], [nrm], [o], options=FuseOptions(
            tsdf_voxel_m=1.5e-3, carve_depth_m=0.02, carve_full_line=full), hull=hull,
            return_attributes=True)
        inside = np.all(np.abs(v[:, :2]) < pocket - 3e-3, axis=1)
        lid[full] = int(np.count_nonzero(inside & (v[:, 2] > floor + 0.01)))
        meas = a["source"] == MEASURED
        # the measured floor and top are the laser's either way
        assert np.abs(v[meas & inside, 2] - floor).max() < 0.2e-3
        assert np.count_nonzero(meas & inside) > 100
    assert lid[True] == 0  # the opening stays open: no surface above the floor
    assert lid[False] > 100  # carved 20 mm only: the hull's lid across the opening


def test_tsdf_voxel_no_finer_than_the_data():
    """Sparse scans (points about 1.2 mm apart): the grid follows the data (1.5 x the
    spacing) instead of the 0.4 mm floor; a twentieth of the faces, as close to the
    sphere on average (measured 0.068 against 0.067 mm), the sphere still closed."""
    from robo3d.fusion import data_voxel, fuse_tsdf

    pts, nrm, org = _views_of_sphere(n_per_view=2000)
    nn = []
    for p in pts:  # the spacing, brute force: the nearest other point of the same scan
        d = np.linalg.norm(p[:, None] - p[None], axis=2)
        np.fill_diagonal(d, np.inf)
        nn.append(d.min(axis=1))
    spacing = float(np.median(np.concatenate(nn)))
    fine, coarse = (FuseOptions(tsdf_voxel_m=0.4e-3, tsdf_voxel_per_spacing=k)
                    for k in (0.0, 1.5))
    assert data_voxel(pts, fine) == (0.4e-3, None)
    voxel, got = data_voxel(pts, coarse)
    assert got == pytest.approx(spacing, rel=0.01) and voxel == pytest.approx(1.5 * got)
    v0, f0, rep0 = fuse_tsdf(pts, nrm, org, max_edge_factor=3.0, options=fine)
    v1, f1, rep1 = fuse_tsdf(pts, nrm, org, max_edge_factor=3.0, options=coarse)
    assert rep0["voxel_size"] == 0.4e-3 and not rep0["voxel_from_spacing"]
    # (fusion measures the spacing of the points it uses: those seen from the front)
    assert rep1["voxel_size"] == pytest.approx(voxel, rel=0.01) and rep1["voxel_from_spacing"]
    assert rep1["point_spacing_m"] == pytest.approx(spacing, rel=0.01)
    assert len(f1) < len(f0) / 10
    e0, e1 = _radial_error(v0), _radial_error(v1)
    assert e1.mean() < 1.2 * e0.mean() and e1.max() < 0.5e-3
    assert _area(v1, f1) == pytest.approx(4 * np.pi * R**2, rel=0.01)
    assert np.all(_edge_uses(f1) == 2)
    # dense scans keep the floor: the demos' and the objects benchmark's grids
    dense = _views_of_sphere(n_per_view=60000)[0]
    assert data_voxel(dense, coarse)[0] == 0.4e-3


def test_tsdf_threads_do_not_change_the_mesh():
    """With threads the scans are integrated in parallel and their sums added in the
    scans' order: the same float32 sums, so the same mesh to the bit."""
    from robo3d.fusion import FuseOptions, fuse_tsdf

    pts6, nrm6, org6 = _views_of_sphere(8000)
    opts = FuseOptions(tsdf_voxel_m=1e-3, min_cos_view=0.3)
    v1, f1, r1 = fuse_tsdf(pts6, nrm6, org6, options=opts, threads=1)
    v2, f2, r2 = fuse_tsdf(pts6, nrm6, org6, options=opts, threads=2)
    assert len(f1) > 1000 and r1["n_scans"] == 6
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_array_equal(f1, f2)
    assert r1["range_surfaces"] == r2["range_surfaces"]


def test_surface_measured_by_a_flagged_sweep_is_labelled():
    """``flagged_sweep``: measured vertices whose nearest laser point comes from a sweep
    the alignment flagged (kept at the robot's pose, checked by nothing) are 1; inferred
    vertices and the other sweeps' surface 0; nothing flagged costs nothing."""
    from types import SimpleNamespace

    from robo3d.stages.fuse import _flagged_sweep

    rng = np.random.default_rng(3)
    a = rng.uniform(0, 0.01, (500, 3))  # sweep 0: x in [0, 10] mm
    b = a + [0.02, 0, 0]  # sweep 1: x in [20, 30] mm
    V = np.r_[a[:50] + 1e-4, b[:50] - 1e-4, [[0.005, 0.005, 0.05]]]
    measured = np.r_[np.ones(100, bool), False]

    def clouds(f0, f1):
        return [SimpleNamespace(points_base=a, sweep=0, report={"flagged": f0}),
                SimpleNamespace(points_base=b, sweep=1, report={"flagged": f1})]

    def flagged(cs):
        return _flagged_sweep(V, measured, cs, [bool((c.report or {}).get("flagged"))
                                                 for c in cs])

    out = flagged(clouds(False, True))
    assert out.dtype == np.uint8
    assert not out[:50].any() and out[50:100].all() and out[100] == 0
    assert not flagged(clouds(False, False)).any()
    both = flagged(clouds(True, True))
    assert both[:100].all() and both[100] == 0
    # older aligned.npz files have no "flagged" in their reports: nothing is labelled
    old = [SimpleNamespace(points_base=a, sweep=0, report=None)]
    assert not flagged(old).any()


def _sparse_cylinder_sweep(step_frame=6e-3, step_line=0.3e-3, length=0.06, radius=0.02):
    """One sweep over the top of a cylinder lying along x (radius ``radius``), seen from
    above: profiles across it ``step_frame`` apart, points ``step_line`` apart along each
    (a sweep of few frames); (points, normals, sensor origins, grid)."""
    xs = np.arange(0.0, length + 1e-9, step_frame)
    th = np.arange(-1.0, 1.0, step_line / radius)
    f, l = np.meshgrid(np.arange(len(xs)), np.arange(len(th)), indexing="ij")
    f, l = f.ravel(), l.ravel()
    p = np.c_[xs[f], radius * np.sin(th[l]), radius * np.cos(th[l])]
    n = np.c_[np.zeros(len(f)), np.sin(th[l]), np.cos(th[l])]
    o = np.c_[xs[f], np.zeros(len(f)), np.full(len(f), 0.3)]
    return p, n, o, np.c_[f, l, np.zeros(len(f), np.int64)]


def test_voxel_follows_the_profiles_spacing_of_a_sparse_sweep():
    """Profiles 6 mm apart with points 0.3 mm apart along them: each point stands for a
    0.3 x 6 mm footprint, and the grid is 0.5 x sqrt(0.3 x 6) = 0.67 mm, not 0.4 mm: a
    third of the faces, the surface as close (the cylinder is straight between its
    profiles). Profiles 1.2 mm apart (the objects benchmark's sweeps) keep 0.4 mm."""
    from robo3d.fusion import MEASURED, data_voxel, fuse_tsdf, profile_spacing

    R = 0.02
    p, n, o, g = _sparse_cylinder_sweep(radius=R)
    assert profile_spacing([p], [g]) == pytest.approx(6e-3, rel=1e-6)
    assert profile_spacing([p], [None]) is None
    # a missing frame: the next profile present is the neighbour (12 mm there)
    gap = g[:, 0] != 3
    assert profile_spacing([p[gap]], [g[gap]]) == pytest.approx(6e-3, rel=1e-6)
    opts = FuseOptions()
    voxel, spacing = data_voxel([p], opts, profile_spacing_m=6e-3)
    assert spacing == pytest.approx(0.3e-3, rel=0.02)
    assert voxel == pytest.approx(0.5 * np.sqrt(spacing * 6e-3))
    dense = _sparse_cylinder_sweep(step_frame=1.2e-3, radius=R)
    assert data_voxel([dense[0]], opts,
                      profile_spacing_m=profile_spacing([dense[0]], [dense[3]]))[0] == 0.4e-3
    got = {}
    for k in (0.0, 0.5):
        v, f, rep, a = fuse_tsdf([p], [n], [o], grids=[g], return_attributes=True,
                                 options=FuseOptions(tsdf_voxel_per_footprint=k))
        inner = ((a["source"] == MEASURED) & (v[:, 0] > 0.006) & (v[:, 0] < 0.054)
                 & (np.abs(v[:, 1]) < 0.015))
        err = np.abs(np.hypot(v[inner, 1], v[inner, 2]) - R)
        got[k] = (rep, len(f), err)
    rep0, n0, e0 = got[0.0]
    rep1, n1, e1 = got[0.5]
    assert rep0["voxel_size"] == 0.4e-3 and rep0["profile_spacing_m"] is None
    assert rep1["voxel_size"] == pytest.approx(voxel, rel=0.01)
    assert rep1["profile_spacing_m"] == pytest.approx(6e-3, rel=1e-6)
    assert rep1["voxel_from"] == "point footprint" and rep0["voxel_from"] == "tsdf_voxel_m"
    assert n1 < n0 / 2.5
    assert len(e1) > 100 and e1.mean() < 2e-6 and e1.max() < 10e-6


def test_far_query_tree_options_find_the_same_neighbours():
    """``KD_FAR`` (an unbalanced tree whose nodes keep their split boxes) only changes how
    fast far queries run: laser lines dense along themselves and queries centimetres
    away get the same nearest points and distances as SciPy's default tree."""
    from scipy.spatial import cKDTree

    from robo3d.fusion import KD_FAR

    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 0.05, 4000)
    lines = np.concatenate([np.c_[t, np.full_like(t, y), 0.001 * np.sin(60 * t)]
                            for y in np.arange(0.0, 0.01, 0.0015)])
    queries = np.concatenate([rng.uniform([-0.02, -0.03, -0.02], [0.07, 0.04, 0.03],
                                          (3000, 3)), lines[::7] + 1e-5])
    d0, i0 = cKDTree(lines).query(queries, k=1)
    d1, i1 = cKDTree(lines, **KD_FAR).query(queries, k=1)
    np.testing.assert_array_equal(d0, d1)
    np.testing.assert_array_equal(i0, i1)


def test_the_hull_field_is_scipys_trilinear_interpolation():
    """``_hull_field`` interpolates the hull's smoothed occupancy one axis at a time; it
    must be what ``scipy.ndimage.map_coordinates(order=1, mode="constant")`` gives at the
    fusion voxels' centres, 0 off the hull's grid, for grids that overlap it partly, at
    finer and coarser voxels, and for a hull one voxel thin."""
    from scipy import ndimage

    from robo3d.carving import VoxelGrid
    from robo3d.fusion import _dilated_hull, _hull_field

    rng = np.random.default_rng(5)
    for occ_shape, vs, shift in (((9, 7, 5), 0.4, (-0.7, 0.3, 1.1)),
                                 ((6, 1, 8), 1.7, (0.25, 0.0, -2.0)),
                                 ((12, 10, 9), 0.33, (2.0, -1.0, 0.5))):
        occ = rng.random(occ_shape) < 0.5
        hull = VoxelGrid(origin=np.zeros(3), voxel_size=1.0, occupancy=occ)
        shape = tuple(int(n / vs) + 4 for n in occ_shape)
        origin = np.array(shift)
        for margin, sigma in ((0, 0.0), (1, 1.0)):
            got = _hull_field(hull, origin, vs, shape, margin, sigma)
            h_origin, h_vs, docc = _dilated_hull(hull, margin)
            field = (ndimage.gaussian_filter(docc.astype(np.float32), sigma) if sigma > 0
                     else docc.astype(np.float32))
            idx = np.indices(shape, dtype=np.float64).reshape(3, -1)
            idx = (origin[:, None] + idx * vs - h_origin[:, None]) / h_vs
            want = ndimage.map_coordinates(field, idx, order=1, mode="constant",
                                           cval=0.0).reshape(shape)
            # the same everywhere but where a value lies within float32 rounding of 0.5
            near = np.abs(want - 0.5) < 1e-5
            assert np.array_equal(got[~near], (want > 0.5)[~near])
            assert got.any() and not got.all()
