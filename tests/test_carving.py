"""Tests of robo3d.carving: the box, dense carving, the hull mesh and the resolution check.

Ground truth is analytic: a sphere seen by calibrated synthetic cameras. Its silhouettes
are rasterised exactly (each pixel centre's ray tested against the sphere), and its
visual hull is known in closed form: a point is inside view i's silhouette cone when the
angle between its direction and the sphere centre's, seen from the camera centre, is at
most ``asin(R / distance)``. Carving samples that hull at voxel centres and pixel
centres, so it must agree with it everywhere except within a pixel of a cone's boundary.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from robo3d.camera import CameraModel, distortion_limit_r2, pixel_rays
from robo3d.carving import (
    box_from_silhouettes,
    carve_dense,
    hull_to_mesh,
    outside_silhouettes,
    resolution_report,
)
from robo3d.errors import StageError
from robo3d.grid import VoxelGrid, make_grid
from robo3d.sim.rig import look_at
from robo3d.transforms import invert_transform

CENTRE = np.array([0.1, -0.05, 0.3])
RADIUS = 0.05
DIST = 0.4
F = 300.0
SPHERE_VOLUME = 4.0 / 3.0 * np.pi * RADIUS**3


# ---------------------------------------------------------------------- synthetic scene
def _fib_dirs(n: int) -> np.ndarray:
    """n unit vectors spread evenly over the sphere (Fibonacci lattice)."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)


def _render_sphere(camera: CameraModel, T: np.ndarray, centre, radius) -> np.ndarray:
    """Exact silhouette: pixels whose centre ray (distortion undone) meets the sphere."""
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    o, d = pixel_rays(uv, camera, T)
    oc = o - centre
    b = d @ oc
    disc = b * b - (oc @ oc - radius * radius)
    hit = (disc >= 0) & (-b - np.sqrt(np.maximum(disc, 0.0)) > 0)
    return hit.reshape(camera.height, camera.width)


def _cone_margin(points, Ts, centre, radius) -> np.ndarray:
    """min over views of (cone half-angle - angle off the cone axis), radians.

    >= 0 exactly for the points of the analytic visual hull of the sphere.
    """
    margin = np.full(len(points), np.inf)
    for T in Ts:
        o = T[:3, 3]
        a = points - o
        dc = centre - o
        cosang = a @ dc / np.linalg.norm(a, axis=1) / np.linalg.norm(dc)
        ang = np.arccos(np.clip(cosang, -1.0, 1.0))
        margin = np.minimum(margin, np.arcsin(radius / np.linalg.norm(dc)) - ang)
    return margin


def _cv2_pixels(points, camera: CameraModel, T_base_camera) -> np.ndarray:
    """Independent projection with OpenCV (distortion included), (N, 2)."""
    t_cb = invert_transform(T_base_camera)
    rvec, _ = cv2.Rodrigues(t_cb[:3, :3])
    uv, _ = cv2.projectPoints(np.asarray(points, float).reshape(-1, 1, 3), rvec,
                              t_cb[:3, 3].copy(), camera.K, camera.D)
    return uv.reshape(-1, 2)


def _camera(D=None, size=(320, 240)) -> CameraModel:
    w, h = size
    K = [[F, 0, (w - 1) / 2], [0, F, (h - 1) / 2], [0, 0, 1]]
    return CameraModel("camera", w, h, K, np.zeros(5) if D is None else np.asarray(D))


@pytest.fixture(scope="module")
def sphere_views():
    cam = _camera()
    Ts = np.stack([look_at(CENTRE + DIST * d, CENTRE) for d in _fib_dirs(24)])
    masks = [_render_sphere(cam, T, CENTRE, RADIUS) for T in Ts]
    return cam, Ts, masks


@pytest.fixture(scope="module")
def sphere_hull(sphere_views):
    cam, Ts, masks = sphere_views
    grid = make_grid(CENTRE - 0.06, CENTRE + 0.06, resolution=80)
    carved, report = carve_dense(grid, masks, cam, Ts)
    return grid, carved, report


# ---------------------------------------------------------------------- carving: feature
def test_carve_sphere_matches_analytic_visual_hull(sphere_views, sphere_hull):
    cam, Ts, _ = sphere_views
    grid, carved, _ = sphere_hull
    margin = _cone_margin(grid.centres(occupied_only=False), Ts, CENTRE, RADIUS)
    truth = margin >= 0
    got = carved.occupancy.reshape(-1)
    wrong = got != truth
    # every disagreement is a voxel centre within one pixel (angle 1/f) of a cone's
    # boundary: pixel rounding (at most 0.71 px) decides those
    assert np.abs(margin[wrong]).max() * F < 1.0
    assert wrong.sum() < 0.03 * truth.sum()
    # and the analytic hull itself is only a little larger than the sphere
    hull_volume = truth.sum() * grid.voxel_size**3
    assert 1.0 <= hull_volume / SPHERE_VOLUME < 1.02


def test_carve_sphere_volume(sphere_hull):
    grid, carved, report = sphere_hull
    ratio = carved.volume_m3 / SPHERE_VOLUME
    # measured 0.993: the visual hull of 24 views exceeds the sphere by 0.3 %, and
    # sampling each cone at rounded pixels erodes the surface by about a tenth of a pixel
    assert abs(ratio - 1.0) < 0.03, ratio
    assert report["volume_m3"] == pytest.approx(carved.volume_m3)
    assert carved.origin == pytest.approx(grid.origin)
    assert carved.voxel_size == grid.voxel_size
    assert grid.n_occupied == 80**3  # the input is not modified


def test_carve_report_counts_chain(sphere_hull):
    grid, carved, report = sphere_hull
    views = report["views"]
    assert report["voxels_before"] == grid.n_occupied
    assert report["voxels_after"] == carved.n_occupied
    assert views[0]["tested"] == grid.n_occupied
    for a, b in zip(views[:-1], views[1:], strict=True):
        assert a["after"] == b["tested"]  # only survivors go on to the next view
        assert b["tested"] <= a["tested"]
    assert views[-1]["after"] == carved.n_occupied
    assert sum(v["carved"] for v in views) == grid.n_occupied - carved.n_occupied
    # the whole grid is in every view and in front of every camera
    assert all(v["outside_image"] == 0 and v["behind_camera"] == 0 for v in views)
    assert report["time_s"] > 0


def test_carve_chunked_equals_whole(sphere_views, sphere_hull):
    cam, Ts, masks = sphere_views
    grid, carved, report = sphere_hull
    again, rep2 = carve_dense(grid, masks, cam, Ts, chunk_voxels=40_009)
    assert np.array_equal(again.occupancy, carved.occupancy)
    keys = ("tested", "carved", "after", "outside_image", "behind_camera")
    for a, b in zip(report["views"], rep2["views"], strict=True):
        assert all(a[k] == b[k] for k in keys)


def test_carve_with_distortion_matches_truth():
    """Masks rendered through a distorted lens carve the true hull only if the carver
    projects with the same distortion; ignoring it carves far off the truth."""
    D = np.array([-0.3, 0.1, 0.002, -0.001, 0.0])
    cam = _camera(D, size=(320, 320))
    rng = np.random.default_rng(7)
    Ts = []
    for d in _fib_dirs(16):
        # aim beside the sphere so it appears ~80 px off-centre, where the lens bends it
        side = np.cross(d, rng.normal(size=3))
        side /= np.linalg.norm(side)
        Ts.append(look_at(CENTRE + DIST * d, CENTRE + 0.11 * side))
    Ts = np.stack(Ts)
    masks = [_render_sphere(cam, T, CENTRE, RADIUS) for T in Ts]
    assert not any(m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()
                   for m in masks)
    grid = make_grid(CENTRE - 0.06, CENTRE + 0.06, resolution=48)
    margin = _cone_margin(grid.centres(occupied_only=False), Ts, CENTRE, RADIUS)
    truth = margin >= 0

    carved, report = carve_dense(grid, masks, cam, Ts, outside_image="carve")
    wrong = carved.occupancy.reshape(-1) != truth
    # barrel distortion makes an edge pixel span up to ~1.15 pixels' worth of angle
    assert np.abs(margin[wrong]).max() * F < 1.2
    assert wrong.sum() < 0.03 * truth.sum()
    assert all(v["outside_image"] == 0 for v in report["views"])

    pinhole = _camera(None, size=(320, 320))
    naive, _ = carve_dense(grid, masks, pinhole, Ts, outside_image="carve")
    wrong_naive = naive.occupancy.reshape(-1) != truth
    assert np.abs(margin[wrong_naive]).max() * F > 3.0
    assert wrong_naive.sum() > 3 * wrong.sum()


def test_voxel_pixels_match_opencv():
    """The carver's pixel of a voxel is OpenCV's projection rounded (distortion on)."""
    D = np.array([-0.25, 0.08, 0.001, 0.002, -0.01])
    cam = _camera(D)
    T = look_at([0.0, -0.5, 0.2], [0.02, 0.0, 0.0])
    grid = make_grid([-0.08, -0.08, -0.08], [0.08, 0.08, 0.08], resolution=24)
    uv = _cv2_pixels(grid.centres(False), cam, T)
    pix = np.floor(uv + 0.5).astype(int)
    inside = ((pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0)
              & (pix[:, 1] < cam.height))
    # a random mask keeps exactly the voxels whose OpenCV pixel is set in it
    mask = np.random.default_rng(11).random((cam.height, cam.width)) < 0.5
    carved, rep = carve_dense(grid, [mask], cam, T[None], outside_image="carve")
    expect = np.zeros(len(pix), bool)
    expect[inside] = mask[pix[inside, 1], pix[inside, 0]]
    assert inside.sum() > 1000
    assert np.array_equal(carved.occupancy.reshape(-1), expect)


# ------------------------------------------------------- outside the image, behind the camera
def _partial_view():
    """A narrow camera that sees only the middle of a grid in front of it."""
    cam = CameraModel("narrow", 64, 48, [[100, 0, 31.5], [0, 100, 23.5], [0, 0, 1]])
    T = look_at([0.0, 0.0, -0.3], [0.0, 0.0, 0.0], up=(0.0, -1.0, 0.0))
    grid = make_grid([-0.1, -0.1, -0.1], [0.1, 0.1, 0.1], resolution=20)
    uv = _cv2_pixels(grid.centres(False), cam, T)
    pix = np.floor(uv + 0.5).astype(int)
    inside = ((pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0)
              & (pix[:, 1] < cam.height))
    return cam, T, grid, pix, inside


def test_outside_image_keep_vs_carve():
    cam, T, grid, pix, inside = _partial_view()
    assert 0.1 < inside.mean() < 0.9  # the view sees part of the grid only
    mask = np.zeros((cam.height, cam.width), bool)
    mask[10:30, 20:50] = True
    in_sil = np.zeros(len(pix), bool)
    in_sil[inside] = mask[pix[inside, 1], pix[inside, 0]]

    kept, rep = carve_dense(grid, [mask], cam, T[None], outside_image="keep")
    assert np.array_equal(kept.occupancy.reshape(-1), in_sil | ~inside)
    v = rep["views"][0]
    assert v["outside_image"] == v["kept_outside_image"] == int((~inside).sum())
    assert v["after"] == int((in_sil | ~inside).sum())

    strict, rep = carve_dense(grid, [mask], cam, T[None], outside_image="carve")
    assert np.array_equal(strict.occupancy.reshape(-1), in_sil)
    assert rep["views"][0]["kept_outside_image"] == 0
    assert rep["views"][0]["outside_image"] == int((~inside).sum())


def test_a_voxel_in_fewer_than_two_images_is_not_hull():
    """Four views on a ring around the sphere, a box three times its size: under
    ``outside_image="keep"`` the box's corners lie in no image and the silhouette cones
    run on out of the other frames. The default keeps only the voxels that two views or
    more have in their image (counted here with OpenCV's projection); the sphere itself,
    in every image, is kept whole."""
    from robo3d.carving import CarveOptions, carve_visual_hull, in_enough_images

    cam = _camera(size=(160, 120))
    ring = [np.array([np.cos(a), np.sin(a), 0.3]) / np.hypot(1.0, 0.3)
            for a in np.radians([0.0, 90.0, 180.0, 270.0])]
    Ts = np.stack([look_at(CENTRE + DIST * d, CENTRE) for d in ring])
    masks = [_render_sphere(cam, T, CENTRE, RADIUS) for T in Ts]
    grid = make_grid(CENTRE - 3 * RADIUS, CENTRE + 3 * RADIUS, resolution=48)
    seed_hull, _ = carve_visual_hull(grid, masks, cam, Ts, CarveOptions(min_views_in_image=1))
    hull, report = carve_visual_hull(grid, masks, cam, Ts)
    centres = grid.centres(False)
    n_in = np.zeros(len(centres), int)
    for T in Ts:
        pix = np.floor(_cv2_pixels(centres, cam, T) + 0.5).astype(int)
        front = (centres - T[:3, 3]) @ T[:3, 2] > 0
        n_in += front & (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) \
            & (pix[:, 1] < cam.height)
    old, new = seed_hull.occupancy.reshape(-1), hull.occupancy.reshape(-1)
    assert np.mean(n_in[old] < 2) > 0.2  # the seed's hull: a fifth or more in < 2 images
    assert np.array_equal(new, old & (n_in >= 2))
    assert report["in_images"]["min_views"] == 2
    assert report["in_images"]["removed"] == int(old.sum() - new.sum())
    assert np.array_equal(in_enough_images(seed_hull, cam, Ts, 2), (n_in >= 2)[old])
    in_sphere = np.linalg.norm(centres - CENTRE, axis=1) < RADIUS - grid.voxel_size
    assert new[in_sphere].all()
    # the seed's hull: 18 times the sphere's volume, 93 % of it more than 2 R from its
    # centre; now 1.5 times, a quarter that far (two opposite views bound no depth)
    n_sphere = SPHERE_VOLUME / grid.voxel_size**3
    far = np.linalg.norm(centres - CENTRE, axis=1) > 2 * RADIUS
    assert old.sum() > 10 * n_sphere and far[old].mean() > 0.9
    assert new.sum() < 2 * n_sphere and far[new].mean() < 0.3
    # one view: it alone is every view there is; outside_image "carve": nothing to add
    one, rep1 = carve_visual_hull(grid, masks[:1], cam, Ts[:1])
    assert "in_images" not in rep1
    assert np.array_equal(one.occupancy, carve_dense(grid, masks[:1], cam, Ts[:1])[0].occupancy)
    strict, rep_s = carve_visual_hull(grid, masks, cam, Ts, CarveOptions(outside_image="carve"))
    assert "in_images" not in rep_s and not (strict.occupancy & ~hull.occupancy).any()
    with pytest.raises(ValueError, match="min_views_in_image"):
        carve_visual_hull(grid, masks, cam, Ts, CarveOptions(min_views_in_image=0))


def test_behind_camera_keep_vs_carve():
    cam = _camera()
    grid = make_grid([-0.1, -0.1, -0.1], [0.1, 0.1, 0.1], resolution=20)
    T = look_at([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], up=(0.0, -1.0, 0.0))  # inside the grid
    z = grid.centres(False)[:, 2]
    assert not np.any(z == 0)
    full = np.ones((cam.height, cam.width), bool)
    # every voxel in front is either in the (all-foreground) silhouette or outside the
    # image (kept); so only the behind-camera policy decides
    carved, rep = carve_dense(grid, [full], cam, T[None], behind_camera="carve")
    assert np.array_equal(carved.occupancy.reshape(-1), z > 0)
    assert rep["views"][0]["behind_camera"] == int((z < 0).sum())
    kept, rep = carve_dense(grid, [full], cam, T[None], behind_camera="keep")
    assert kept.n_occupied == grid.n_occupied
    assert rep["views"][0]["kept_behind_camera"] == int((z < 0).sum())


def test_folded_distortion_counts_as_outside_image():
    """Far off-axis, a strong barrel model folds back into the image; such voxels are
    outside the view and must not be carved when the policy keeps them."""
    cam = _camera([-0.4, 0.0, 0.0, 0.0, 0.0])
    assert distortion_limit_r2(cam) == pytest.approx(1.0 / 1.2)
    T = np.eye(4)
    # a slab of voxels at normalised x = 1.5 (56 deg off-axis), z = 0.2 m
    grid = VoxelGrid(origin=np.array([0.3, -0.01, 0.2]), voxel_size=0.002,
                     occupancy=np.ones((3, 10, 3), bool))
    uv, in_front = cam.project(grid.centres())
    assert np.all(in_front)
    folded = ((uv[:, 0] >= -0.5) & (uv[:, 0] < cam.width - 0.5)
              & (uv[:, 1] >= -0.5) & (uv[:, 1] < cam.height - 0.5))
    assert folded.all()  # the naive projection lands in the image
    empty = np.zeros((cam.height, cam.width), bool)
    kept, rep = carve_dense(grid, [empty], cam, T[None], outside_image="keep")
    assert kept.n_occupied == grid.n_occupied
    assert rep["views"][0]["outside_image"] == grid.n_occupied
    strict, _ = carve_dense(grid, [empty], cam, T[None], outside_image="carve")
    assert strict.n_occupied == 0


# ---------------------------------------------------------------------- carving: exceptions
def test_carve_input_errors(sphere_views):
    cam, Ts, masks = sphere_views
    grid = make_grid(CENTRE - 0.06, CENTRE + 0.06, resolution=8)
    with pytest.raises(ValueError, match="outside_image must be one of"):
        carve_dense(grid, masks, cam, Ts, outside_image="maybe")
    with pytest.raises(ValueError, match="behind_camera must be one of"):
        carve_dense(grid, masks, cam, Ts, behind_camera="drop")
    bad = [m.astype(np.uint8) for m in masks]
    with pytest.raises(ValueError, match=r"mask 0 must be \(240, 320\) bool.*uint8"):
        carve_dense(grid, bad, cam, Ts)
    with pytest.raises(ValueError, match=r"mask 3 must be \(240, 320\) bool.*\(240, 319\)"):
        carve_dense(grid, masks[:3] + [masks[3][:, :-1]] + masks[4:], cam, Ts)
    with pytest.raises(ValueError, match="got 23 masks for 24 poses"):
        carve_dense(grid, masks[:-1], cam, Ts)
    with pytest.raises(ValueError, match=r"T_base_cameras must be \(N, 4, 4\)"):
        carve_dense(grid, masks, cam, Ts[:, :3])
    skewed = Ts.copy()
    skewed[5, :3, :3] *= 1.01
    with pytest.raises(ValueError, match=r"T_base_cameras\[5\] is not a rigid transform"):
        carve_dense(grid, masks, cam, skewed)
    with pytest.raises(StageError, match="at least one view"):
        carve_dense(grid, [], cam, np.zeros((0, 4, 4)))


# ---------------------------------------------------------------------- the hull mesh
def _edges_closed_and_oriented(faces: np.ndarray) -> bool:
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    _, n_dir = np.unique(directed, axis=0, return_counts=True)
    _, n_und = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    return bool(np.all(n_und == 2) and np.all(n_dir == 1))


def _signed_volume(v, f) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def test_hull_mesh_watertight_on_sphere(sphere_hull):
    import open3d as o3d

    _, carved, _ = sphere_hull
    V, Fc = hull_to_mesh(carved)
    assert V.dtype == np.float64 and V.shape[1] == 3
    assert Fc.dtype == np.int32 and Fc.shape[1] == 3
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V),
                                     o3d.utility.Vector3iVector(Fc))
    # watertight = closed 2-manifold. (Open3D's is_watertight adds a self-intersection
    # test that is slow here and flags touching, non-intersecting marching-cubes
    # triangles: isl-org/Open3D#1171.)
    assert mesh.is_edge_manifold(allow_boundary_edges=False)
    assert mesh.is_vertex_manifold()
    assert _edges_closed_and_oriented(Fc)
    n_edges = 3 * len(Fc) // 2
    assert len(V) - n_edges + len(Fc) == 2  # one sphere-like surface (genus 0)
    # on the sphere within a voxel (measured: within 0.7 voxel)
    err = np.linalg.norm(V - CENTRE, axis=1) - RADIUS
    assert np.abs(err).max() < carved.voxel_size
    # outward normals; the enclosed volume is the voxels' volume
    vol = _signed_volume(V, Fc)
    assert vol == pytest.approx(carved.volume_m3, rel=0.02)


def test_hull_mesh_closes_at_grid_side_and_lies_on_voxel_faces():
    occ = np.ones((5, 6, 7), bool)
    grid = VoxelGrid(origin=np.array([0.1, 0.2, 0.3]), voxel_size=0.01, occupancy=occ)
    V, Fc = hull_to_mesh(grid, smooth_sigma_vox=0.0)
    assert _edges_closed_and_oriented(Fc)
    lo, hi = grid.bounds
    assert V.min(axis=0) == pytest.approx(lo, abs=1e-9)
    assert V.max(axis=0) == pytest.approx(hi, abs=1e-9)
    assert _signed_volume(V, Fc) > 0


def test_hull_mesh_thin_hull_falls_back_to_unsmoothed(caplog):
    occ = np.zeros((5, 5, 5), bool)
    occ[2, 2, 2] = True  # one voxel: a blur of sigma 1 leaves nothing above 0.5
    grid = VoxelGrid(origin=np.zeros(3), voxel_size=0.01, occupancy=occ)
    V, Fc = hull_to_mesh(grid, smooth_sigma_vox=1.0)
    assert "meshing the unsmoothed voxels" in caplog.text
    assert _edges_closed_and_oriented(Fc)
    assert np.abs(V - 0.02).max() <= 0.005 + 1e-12


def test_hull_mesh_empty_raises():
    grid = VoxelGrid(np.zeros(3), 0.01, np.zeros((4, 4, 4), bool))
    with pytest.raises(StageError, match="empty"):
        hull_to_mesh(grid)
    with pytest.raises(ValueError, match="smooth_sigma_vox"):
        hull_to_mesh(make_grid(np.zeros(3), np.ones(3), resolution=2), smooth_sigma_vox=-1)


# ---------------------------------------------------------------------- the box
def test_box_from_silhouettes_recovers_sphere_centre():
    cam = _camera()
    rng = np.random.default_rng(3)
    dirs = _fib_dirs(12)
    # the cameras aim up to 2 cm beside the sphere: its silhouette is off-centre and
    # perspective shifts the silhouette centroid off the centre's projection
    Ts = np.stack([look_at(CENTRE + DIST * d, CENTRE + rng.uniform(-0.02, 0.02, 3))
                   for d in dirs])
    masks = [_render_sphere(cam, T, CENTRE, RADIUS) for T in Ts]
    centroids = np.array([np.argwhere(m)[:, ::-1].mean(axis=0) for m in masks])
    box_min, box_max, rep = box_from_silhouettes(centroids, masks, cam, Ts, margin=0.1)
    assert np.linalg.norm(np.asarray(rep["centre"]) - CENTRE) < 1e-3
    assert np.all(box_min <= CENTRE - RADIUS) and np.all(box_max >= CENTRE + RADIUS)
    # not much bigger than needed: the silhouette at the centre depth is ~R D/sqrt(D^2-R^2)
    assert rep["half_size_m"] < 1.1 * RADIUS * 1.05
    assert rep["n_views"] == 12 and len(rep["ray_residual_m"]) == 12
    assert max(rep["ray_residual_m"]) < 2e-3
    assert rep["ray_spread_deg"] > 60
    # without centroids, the masks' own mean pixels are used
    b2_min, b2_max, _ = box_from_silhouettes(None, masks, cam, Ts, margin=0.1)
    assert b2_min == pytest.approx(box_min) and b2_max == pytest.approx(box_max)


def test_box_from_silhouettes_errors(sphere_views):
    cam, Ts, masks = sphere_views
    c = np.array([np.argwhere(m)[:, ::-1].mean(axis=0) for m in masks])
    with pytest.raises(StageError, match="at least 2 views"):
        box_from_silhouettes(c[:1], masks[:1], cam, Ts[:1])
    # two cameras 1 cm apart looking the same way: rays ~1.4 deg apart
    T0 = look_at(CENTRE + [0.0, -DIST, 0.0], CENTRE)
    T1 = T0.copy()
    T1[:3, 3] += [0.01, 0.0, 0.0]
    pair = np.stack([T0, T1])
    pm = [_render_sphere(cam, T, CENTRE, RADIUS) for T in pair]
    pc = np.array([np.argwhere(m)[:, ::-1].mean(axis=0) for m in pm])
    with pytest.raises(StageError, match="nearly parallel"):
        box_from_silhouettes(pc, pm, cam, pair)
    with pytest.raises(ValueError, match="got 3 centroids for 24 poses"):
        box_from_silhouettes(c[:3], masks, cam, Ts)
    empty = [np.zeros_like(masks[0])] + masks[1:]
    with pytest.raises(StageError, match="silhouette 0 is empty"):
        box_from_silhouettes(c, empty, cam, Ts)


# ---------------------------------------------------------------------- the grid
def test_make_grid_resolution_and_voxel_size():
    g = make_grid([0.0, 0.0, 0.0], [0.3, 0.15, 0.1], resolution=60)
    assert g.voxel_size == pytest.approx(0.005)
    assert g.shape == (60, 30, 20)
    lo, hi = g.bounds
    assert lo == pytest.approx([0, 0, 0]) and hi == pytest.approx([0.3, 0.15, 0.1])
    assert g.n_occupied == 60 * 30 * 20
    assert g.volume_m3 == pytest.approx(0.3 * 0.15 * 0.1)
    # a voxel size that does not divide the box: the grid covers it, centred
    g = make_grid([0.0, 0.0, 0.0], [0.1, 0.1, 0.1], voxel_size=0.03)
    assert g.shape == (4, 4, 4)
    lo, hi = g.bounds
    assert lo == pytest.approx([-0.01] * 3) and hi == pytest.approx([0.11] * 3)
    assert g.centre == pytest.approx([0.05] * 3)


def test_make_grid_errors():
    with pytest.raises(ValueError, match="exactly one of resolution and voxel_size"):
        make_grid(np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="exactly one of resolution and voxel_size"):
        make_grid(np.zeros(3), np.ones(3), resolution=4, voxel_size=0.1)
    with pytest.raises(ValueError, match="box_max must exceed box_min"):
        make_grid(np.zeros(3), [1.0, 0.0, 1.0], resolution=4)
    with pytest.raises(ValueError, match="exceeds the dense limit"):
        make_grid(np.zeros(3), np.ones(3), resolution=2000)
    with pytest.raises(ValueError, match="resolution must be a positive integer"):
        make_grid(np.zeros(3), np.ones(3), resolution=0)


def test_voxel_grid_index_round_trip_and_validation():
    g = make_grid([-0.1, 0.0, 0.2], [0.1, 0.1, 0.3], resolution=20)
    ijk = np.argwhere(g.occupancy)[::97]
    back, inside = g.points_to_index(g.index_to_points(ijk))
    assert np.array_equal(back, ijk) and inside.all()
    _, inside = g.points_to_index(np.array([[5.0, 5.0, 5.0]]))
    assert not inside[0]
    assert g.centres().shape == (g.n_occupied, 3)
    with pytest.raises(ValueError, match=r"occupancy must be \(nx, ny, nz\) bool.*uint8"):
        VoxelGrid(np.zeros(3), 0.01, np.ones((2, 2, 2), np.uint8))
    with pytest.raises(ValueError, match="voxel_size must be a positive"):
        VoxelGrid(np.zeros(3), 0.0, np.ones((2, 2, 2), bool))


def test_grid_npz_round_trip(tmp_path):
    g = make_grid([0.0, 0.0, 0.0], [0.1, 0.2, 0.3], resolution=16)
    g.occupancy[::2, 1::3] = False
    path = tmp_path / "sub" / "hull.npz"
    g.save_npz(path, report={"voxels_after": 12, "views": [1, 2]}, weights=np.arange(3.0))
    assert sorted(p.name for p in path.parent.iterdir()) == ["hull.npz"]  # no temp left
    h, extra = VoxelGrid.load_npz(path, return_extra=True)
    assert np.array_equal(h.occupancy, g.occupancy)
    assert h.origin == pytest.approx(g.origin) and h.voxel_size == g.voxel_size
    assert h.frame == "base"
    assert extra["report"] == {"voxels_after": 12, "views": [1, 2]}
    assert np.array_equal(extra["weights"], np.arange(3.0))
    assert isinstance(VoxelGrid.load_npz(path), VoxelGrid)
    with pytest.raises(ValueError, match="reserved"):
        g.save_npz(path, origin=np.zeros(3))
    bad = tmp_path / "bad.npz"
    np.savez(bad, something=np.zeros(2))
    with pytest.raises(ValueError, match="missing"):
        VoxelGrid.load_npz(bad)


# ---------------------------------------------------------------------- resolution
def test_resolution_report(sphere_views):
    cam, Ts, _ = sphere_views
    fine = make_grid(CENTRE - 0.06, CENTRE + 0.06, voxel_size=0.001)
    rep = resolution_report(fine, cam, Ts)
    # every camera looks at the grid centre from DIST: footprint = DIST / f (eq. 8)
    assert rep["pixel_footprint_m"] == pytest.approx([DIST / F] * len(Ts))
    assert rep["depth_m"] == pytest.approx([DIST] * len(Ts))
    assert rep["axis_resolution_m"] == pytest.approx([0.001] * 3)  # eq. 7
    assert rep["finer_than_cameras"] is True and "finer than" in rep["warning"]
    assert rep["voxel_over_footprint"] == pytest.approx(0.001 / (DIST / F))
    coarse = make_grid(CENTRE - 0.06, CENTRE + 0.06, voxel_size=0.002)
    rep = resolution_report(coarse, cam, Ts)
    assert rep["finer_than_cameras"] is False and rep["warning"] is None


def test_surface_is_the_shell():
    occ = np.zeros((6, 7, 8), bool)
    occ[1:5, 1:6, 1:7] = True
    occ[0, 3, 3] = True  # a voxel on the grid's side
    g = VoxelGrid(np.zeros(3), 0.01, occ)
    shell = g.surface()
    inner = np.zeros_like(occ)
    inner[2:4, 2:5, 2:6] = True
    inner[1, 3, 3] = True  # enclosed once the voxel on the side covers it
    assert np.array_equal(shell, occ & ~inner)
    full = VoxelGrid(np.zeros(3), 0.01, np.ones((3, 3, 3), bool))
    assert full.surface().sum() == 26  # only the centre voxel is enclosed
    assert VoxelGrid(np.zeros(3), 0.01, np.ones((1, 4, 4), bool)).surface().all()


# ---------------------------------------------------------------------- the pipeline stage
def _silhouettes_npz(path, cam, Ts, masks, workspace=None):
    from robo3d.atomic import save_npz
    from robo3d.stages.common import camera_arrays

    stack = np.stack(masks)
    box = {} if workspace is None else {"workspace_min": np.asarray(workspace[0]),
                                        "workspace_max": np.asarray(workspace[1])}
    save_npz(path, masks=np.packbits(stack, axis=-1), mask_shape=np.array(stack.shape),
             T_base_camera=Ts, stamps_ns=np.arange(len(Ts), dtype=np.int64),
             **camera_arrays([cam] * len(Ts)), **box)


@pytest.mark.parametrize("method", ["octree", "dense"])
def test_stage_carve_places_the_box_and_carves(tmp_path, sphere_views, method):
    """Without a workspace box the box comes from the silhouettes (seed §3.4); both
    methods write the same hull, with its mesh, volume and resolution check."""
    from robo3d.config import load_config
    from robo3d.pipeline import stage_carve

    cam, Ts, masks = sphere_views
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, masks)
    out = {"npz": str(tmp_path / f"hull_{method}.npz"), "ply": str(tmp_path / "hull.ply"),
           "report": str(tmp_path / "carve.json"), "rrd": str(tmp_path / "carve.rrd")}
    cfg = load_config(overrides={"carving": {"method": method, "resolution": 48}})
    report = stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s")
    box = report["box"]
    assert box["source"].startswith("silhouette centroid rays")
    assert np.linalg.norm(np.asarray(box["centre"]) - CENTRE) < 1e-3
    assert np.all(np.asarray(box["size_m"]) > 2 * RADIUS)
    grid, extra = VoxelGrid.load_npz(out["npz"], return_extra=True)
    assert extra["carving"]["method"] == method and grid.frame == "base"
    assert report["carving"]["method"] == method
    assert report["volume_m3"] == pytest.approx(SPHERE_VOLUME, rel=0.05)
    assert report["mesh"]["volume_m3"] == pytest.approx(report["volume_m3"], rel=0.03)
    assert len(report["resolution"]["pixel_footprint_m"]) == len(Ts)
    expect, _ = carve_dense(make_grid(np.asarray(box["min"]), np.asarray(box["max"]),
                                      resolution=48), masks, cam, Ts)
    assert np.array_equal(grid.occupancy, expect.occupancy)


def test_stage_carve_rejects_conservative_dense(tmp_path, sphere_views):
    from robo3d.config import load_config
    from robo3d.errors import ConfigError
    from robo3d.pipeline import stage_carve

    cam, Ts, masks = sphere_views
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, masks)
    cfg = load_config(overrides={"carving": {"method": "dense", "leaf_rule": "conservative"}})
    with pytest.raises(ConfigError, match="carving.leaf_rule"):
        stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")},
                    {k: str(tmp_path / k) for k in ("npz", "ply", "report", "rrd")}, cfg, "s")


# ---------------------------------------------------------------------- view agreement
def _ring_views(n=12, size=(160, 120), f=150.0, aim=None):
    """n views of the sphere from evenly spread directions; ``aim(d)`` (optional) moves
    each camera's target (to cut the sphere off at the frame)."""
    w, h = size
    cam = CameraModel("camera", w, h, [[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    Ts = np.stack([look_at(CENTRE + DIST * d, CENTRE if aim is None else aim(d))
                   for d in _fib_dirs(n)])
    return cam, Ts, [_render_sphere(cam, T, CENTRE, RADIUS) for T in Ts]


def _iou(a, b) -> float:
    return float(np.count_nonzero(a & b) / np.count_nonzero(a | b))


def _corrupt(kind: str, m: np.ndarray) -> np.ndarray:
    v, u = np.nonzero(m)
    if kind == "inverted":
        return ~m
    if kind == "shifted":  # by a third of the silhouette's width
        return np.roll(m, (u.max() - u.min()) // 3, axis=1)
    if kind == "blob":  # as large as the object, beside it
        yy, xx = np.mgrid[0:m.shape[0], 0:m.shape[1]]
        r = 0.5 * (u.max() - u.min())
        return m | (np.hypot(yy - v.mean(), xx - (u.min() - r)) < r)
    if kind == "part missing":  # the top 40 % of the silhouette lost
        out = m.copy()
        out[: int(v.min() + 0.4 * (v.max() - v.min())), :] = False
        return out
    raise ValueError(kind)


@pytest.fixture(scope="module")
def ring():
    cam, Ts, masks = _ring_views()
    grid = make_grid(CENTRE - 0.06, CENTRE + 0.06, resolution=40)
    exact, _ = carve_dense(grid, masks, cam, Ts)
    return cam, Ts, masks, grid, exact


def test_agreement_of_true_silhouettes(ring):
    """Exact silhouettes agree with the others' hull up to the grid's resolution."""
    from robo3d.carving import view_agreement

    cam, Ts, masks, grid, _ = ring
    scores = view_agreement(grid, masks, cam, Ts)
    assert [s["view"] for s in scores] == list(range(len(Ts)))
    for s in scores:
        assert s["iou"] > 0.9 and s["missing_fraction"] < 0.08
        assert s["spurious_fraction"] < 0.05  # the others' hull contains the sphere
        assert s["unknown_px"] == 0 and s["mask_px"] == np.count_nonzero(masks[s["view"]])


@pytest.mark.parametrize("kind", ["inverted", "shifted", "blob", "part missing"])
def test_agreement_flags_the_bad_view_and_leaving_it_out_restores_the_hull(ring, kind):
    from robo3d.carving import flag_disagreeing_views

    cam, Ts, masks, grid, exact = ring
    bad = 5
    ms = list(masks)
    ms[bad] = _corrupt(kind, masks[bad])
    qa = flag_disagreeing_views(grid, ms, cam, Ts)
    assert qa["flagged"] == [bad], qa["flagged"]
    s = qa["views"][bad]
    assert s["flagged"] and s["reasons"]
    assert all(not v["flagged"] for v in qa["views"] if v["view"] != bad)
    if kind == "blob":
        assert s["spurious_fraction"] > 0.3 and s["missing_fraction"] < 0.1
    else:
        assert s["missing_fraction"] > 0.2
    with_bad, _ = carve_dense(grid, ms, cam, Ts)
    used = [i for i in range(len(Ts)) if i not in qa["flagged"]]
    without, _ = carve_dense(grid, [ms[i] for i in used], cam, Ts[used])
    assert _iou(without.occupancy, exact.occupancy) > 0.97
    if kind != "blob":  # the others carve a blob away; the rest carve the sphere away
        assert _iou(with_bad.occupancy, exact.occupancy) < 0.8


def test_agreement_two_bad_views_and_the_cap():
    """Two bad views are both found (the worse first, then the other against a clean
    reference); when most views disagree, at most half are flagged."""
    from robo3d.carving import flag_disagreeing_views

    cam, Ts, masks = _ring_views()
    grid = make_grid(CENTRE - 0.06, CENTRE + 0.06, resolution=40)
    ms = list(masks)
    ms[2] = _corrupt("inverted", masks[2])
    ms[9] = _corrupt("part missing", masks[9])
    qa = flag_disagreeing_views(grid, ms, cam, Ts)
    assert qa["flagged"] == [2, 9] and not qa["capped"] and qa["passes"] >= 2
    ms = [_corrupt("shifted", m) if i % 4 else m for i, m in enumerate(masks)]  # 9 of 12
    qa = flag_disagreeing_views(grid, ms, cam, Ts)
    assert qa["capped"] and len(qa["flagged"]) == 6


def test_agreement_object_cut_off_by_the_frame_is_not_a_disagreement():
    """Half of the views aim beside the sphere, which the frame cuts off (outside_image
    keep, as on DTU): their masks end at the border; none is flagged."""
    from robo3d.carving import flag_disagreeing_views

    def aim(d):
        side = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
        return CENTRE + 0.24 * side / np.linalg.norm(side)  # 90 px beside the centre

    cam, Ts_c, masks_c = _ring_views(aim=aim)
    _, Ts_f, masks_f = _ring_views()
    Ts = np.concatenate([Ts_c[1::2], Ts_f[::2]])
    masks = masks_c[1::2] + masks_f[::2]
    cut = [i for i, m in enumerate(masks) if m[:, 0].any() or m[:, -1].any()
           or m[0].any() or m[-1].any()]
    assert cut == [0, 1, 2, 3, 4, 5]  # cut off by the frame: a third to two thirds seen
    assert all(0.25 < masks[i].sum() / masks[-1].sum() < 0.75 for i in cut)
    grid = make_grid(CENTRE - 0.06, CENTRE + 0.06, resolution=40)
    qa = flag_disagreeing_views(grid, masks, cam, Ts)
    assert qa["flagged"] == []
    for i in cut:
        assert qa["views"][i]["missing_fraction"] < 0.05
        assert qa["views"][i]["spurious_fraction"] < 0.05


def _render_boxes(cam, T, boxes):
    """Exact silhouette of a union of axis-aligned boxes (each the convex hull of its
    projected corners; no distortion)."""
    m = np.zeros((cam.height, cam.width), np.uint8)
    T_cb = invert_transform(T)
    for lo, hi in boxes:
        c = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                      for z in (lo[2], hi[2])])
        pc = c @ T_cb[:3, :3].T + T_cb[:3, 3]
        uv = np.stack([cam.fx * pc[:, 0] / pc[:, 2] + cam.cx,
                       cam.fy * pc[:, 1] / pc[:, 2] + cam.cy], axis=1)
        cv2.fillConvexPoly(m, cv2.convexHull(np.round(uv * 16).astype(np.int32)), 1, shift=4)
    return m > 0


def test_agreement_keeps_a_correct_view_that_cuts_a_loose_hull():
    """A 2 mm fin on a block, five views: the four others' hull is fat around the fin,
    and the view that sees the fin edge-on "misses" more than a third of it, which is
    what a correct mask does to a loose hull. Its carving leaves every other silhouette
    explained, so it is not flagged (leaving it out would double the hull around the
    fin); a view that lost its top 40 % still is."""
    from robo3d.carving import flag_disagreeing_views, view_agreement

    w, h, f = 160, 120, 150.0
    cam = CameraModel("camera", w, h, [[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]])
    boxes = [(CENTRE + [-0.045, -0.02, -0.03], CENTRE + [0.045, 0.02, -0.015]),
             (CENTRE + [-0.045, -0.001, -0.015], CENTRE + [0.045, 0.001, 0.035])]
    az, el = np.radians(np.arange(5) * 72.0), np.radians(25.0)
    dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az),
                     np.full(5, np.sin(el))], axis=1)
    Ts = np.stack([look_at(CENTRE + DIST * d, CENTRE) for d in dirs])
    masks = [_render_boxes(cam, T, boxes) for T in Ts]
    grid = make_grid(CENTRE - 0.06, CENTRE + 0.06, resolution=40)
    scores = view_agreement(grid, masks, cam, Ts)
    assert scores[0]["missing_fraction"] > 0.3  # past qa_max_missing: flagged until stop 34
    assert all(s["unexplained_max"] < 0.01 for s in scores)
    assert flag_disagreeing_views(grid, masks, cam, Ts)["flagged"] == []
    fine = make_grid(CENTRE - 0.06, CENTRE + 0.06, resolution=60)
    every, _ = carve_dense(fine, masks, cam, Ts)
    without, _ = carve_dense(fine, masks[1:], cam, Ts[1:])
    assert without.n_occupied > 1.5 * every.n_occupied
    ms = list(masks)
    ms[2] = _corrupt("part missing", masks[2])
    qa = flag_disagreeing_views(grid, ms, cam, Ts)
    assert qa["flagged"] == [2]
    assert qa["views"][2]["unexplained_views"] >= 2
    assert "no hull behind them" in qa["views"][2]["reasons"][0]


def test_k2_keeps_the_object_despite_a_view_that_carves_it_away(ring):
    """k = 2: a voxel goes only when two views see background there, so one view that
    lost part of the object carves nothing the others keep."""
    cam, Ts, masks, grid, exact = ring
    ms = list(masks)
    ms[4] = _corrupt("part missing", masks[4])
    k1, _ = carve_dense(grid, ms, cam, Ts)
    k2, rep = carve_dense(grid, ms, cam, Ts, min_views_background=2)
    assert _iou(k1.occupancy, exact.occupancy) < 0.8  # the seed's hull loses a part
    assert np.all(k2.occupancy[exact.occupancy])  # every voxel of the true hull kept
    assert _iou(k2.occupancy, exact.occupancy) > 0.85  # a little fatter
    assert rep["min_views_background"] == 2
    assert sum(v["carved"] for v in rep["views"]) == grid.n_occupied - k2.n_occupied


def test_stage_carve_leaves_a_flagged_view_out_and_says_so(tmp_path, ring):
    import json

    from robo3d.config import load_config
    from robo3d.pipeline import stage_carve

    cam, Ts, masks, _grid, exact = ring
    ms = list(masks)
    ms[7] = _corrupt("inverted", masks[7])
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, ms)
    out = {"npz": str(tmp_path / "hull.npz"), "ply": str(tmp_path / "hull.ply"),
           "report": str(tmp_path / "carve.json"), "rrd": str(tmp_path / "carve.rrd")}
    cfg = load_config(overrides={"carving": {"resolution": 40, "qa_resolution": 40}})
    report = stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s")
    assert [r["view"] for r in report["views_left_out"]] == [7]
    assert "misses" in report["views_left_out"][0]["reasons"][0]
    assert report["views_used"] == [i for i in range(12) if i != 7]
    assert report["agreement"]["views"][7]["flagged"]
    assert {v["view"] for v in report["carving"]["views"]} == set(report["views_used"])
    grid, extra = VoxelGrid.load_npz(out["npz"], return_extra=True)
    assert extra["views_left_out"][0]["view"] == 7
    assert extra["views_used"].tolist() == report["views_used"]
    assert report["volume_m3"] == pytest.approx(SPHERE_VOLUME, rel=0.1)
    lo, hi = np.asarray(report["bbox_min"]), np.asarray(report["bbox_max"])
    assert np.all(np.abs(lo - (CENTRE - RADIUS)) < 2 * grid.voxel_size)
    assert np.all(np.abs(hi - (CENTRE + RADIUS)) < 2 * grid.voxel_size)
    with open(out["report"], encoding="utf-8") as f:
        assert json.load(f)["views_left_out"][0]["view"] == 7
    # turned off: every view carves, and the inverted one removes the sphere's core
    cfg = load_config(overrides={"carving": {"resolution": 40, "qa_leave_out": False}})
    report = stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s")
    assert report["views_left_out"] == [] and report["views_flagged"] == [7]
    assert report["volume_m3"] < 0.5 * SPHERE_VOLUME


def test_stage_carve_always_leaves_an_empty_mask_out(tmp_path, ring):
    """A view the segmentation could not do has an empty mask, which would carve every
    voxel: it is left out even with the agreement check off, and named."""
    from robo3d.config import load_config
    from robo3d.pipeline import stage_carve

    cam, Ts, masks, _grid, _exact = ring
    ms = list(masks)
    ms[5] = np.zeros_like(masks[5])
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, ms)
    out = {k: str(tmp_path / f"hull.{k}") for k in ("npz", "ply", "rrd")}
    out["report"] = str(tmp_path / "carve.json")
    for carving in ({"qa_leave_out": False}, {"qa_resolution": 0}, {}):
        cfg = load_config(overrides={"carving": {"resolution": 40, **carving}})
        report = stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg,
                             "s")
        assert [r["view"] for r in report["views_left_out"]] == [5], carving
        assert any("empty mask" in r for r in report["views_left_out"][0]["reasons"])
        assert 5 not in report["views_used"]
        assert report["volume_m3"] == pytest.approx(SPHERE_VOLUME, rel=0.1)
    ms = [np.zeros_like(m) for m in masks]
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, ms)
    with pytest.raises(StageError, match="no view is left to carve"):
        stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s")


def test_stage_carve_with_laser_frames_leaves_an_empty_hull_not_an_error(tmp_path, ring):
    """Silhouettes that carve every voxel (masks of the wrong part in every view) stop a
    photo set; a scan with laser frames goes on with an empty hull, which says why."""
    from robo3d.config import load_config
    from robo3d.meshio import read_mesh
    from robo3d.pipeline import stage_carve

    cam, Ts, masks, _grid, _exact = ring
    ms = []  # each mask a square in a corner of its image, far off the workspace box
    for _ in range(len(masks)):
        m = np.zeros_like(masks[0])
        m[:8, :8] = True
        ms.append(m)
    box = (CENTRE - 1.2 * RADIUS, CENTRE + 1.2 * RADIUS)
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, ms, box)
    out = {k: str(tmp_path / f"hull.{k}") for k in ("npz", "ply", "rrd")}
    out["report"] = str(tmp_path / "carve.json")
    cfg = load_config(overrides={"carving": {"resolution": 40}})
    with pytest.raises(StageError, match="carving removed every voxel"):
        stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s")
    assert not any(Path(f).exists() for f in out.values())
    report = stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s",
                         has_laser=True)
    assert report["empty"] is True and "removed every voxel" in report["reason"]
    grid, extra = VoxelGrid.load_npz(out["npz"], return_extra=True)
    assert grid.n_occupied == 0 and "removed every voxel" in str(extra["empty"])
    V, F = read_mesh(out["ply"])
    assert len(V) == 0 and len(F) == 0
    # the views left out before carving are still named in an empty hull's report and
    # hull.npz (before, an empty hull listed none: random scene 299, stop 44)
    ms3 = list(ms)
    ms3[3] = np.zeros_like(ms[3])
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, ms3, box)
    report = stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s",
                         has_laser=True)
    assert report["empty"] is True and 3 not in report["views_used"]
    rows = {r["view"]: r["reasons"] for r in report["views_left_out"]}
    assert any("empty mask" in r for r in rows[3]), rows
    assert not set(rows) & set(report["views_used"])  # the others' verdicts too
    _grid, extra = VoxelGrid.load_npz(out["npz"], return_extra=True)
    assert "empty mask" in str(extra["views_left_out"])
    # every mask empty: the same
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, [np.zeros_like(m) for m in ms], box)
    report = stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s",
                         has_laser=True)
    assert report["empty"] is True and "all 12 masks are empty" in report["reason"]


def test_stage_carve_reads_the_segmentation_flags(tmp_path, ring):
    """Views the segmentation flagged leave the reference; one that still agrees with
    the others carves, one that disagrees is left out with both reasons."""
    import json

    from robo3d.config import load_config
    from robo3d.pipeline import stage_carve

    cam, Ts, masks, _grid, _exact = ring
    ms = list(masks)
    ms[4] = _corrupt("part missing", masks[4])
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, ms)
    (tmp_path / "reports").mkdir()
    views = [{"index": i, "qa": {"flags": ["touches_all_sides"] if i in (2, 4) else []}}
             for i in range(len(Ts))]
    (tmp_path / "reports" / "silhouettes.json").write_text(json.dumps({"views": views}))
    out = {k: str(tmp_path / f"hull.{k}") for k in ("npz", "ply", "rrd")}
    out["report"] = str(tmp_path / "carve.json")
    cfg = load_config(overrides={"carving": {"resolution": 40, "qa_resolution": 40}})
    report = stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s")
    assert report["agreement"]["segmentation_flagged"] == [2, 4]
    assert [r["view"] for r in report["views_left_out"]] == [4]
    reasons = report["views_left_out"][0]["reasons"]
    assert any("misses" in r for r in reasons) and "segmentation: touches_all_sides" in reasons
    assert 2 in report["views_used"]


def test_stage_carve_no_hull_from_flagged_views_alone_with_laser(tmp_path, ring):
    """Every view the segmentation flagged (masks of the surroundings agree with each
    other): a scan with laser frames gets no hull from them, and says why; without laser
    frames the hull is all there is and is carved."""
    import json

    from robo3d.config import load_config
    from robo3d.pipeline import stage_carve

    cam, Ts, masks, _grid, _exact = ring
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts, list(masks))
    (tmp_path / "reports").mkdir()
    views = [{"index": i, "qa": {"flags": ["surrounds_view"]}} for i in range(len(Ts))]
    (tmp_path / "reports" / "silhouettes.json").write_text(json.dumps({"views": views}))
    out = {k: str(tmp_path / f"hull.{k}") for k in ("npz", "ply", "rrd")}
    out["report"] = str(tmp_path / "carve.json")
    cfg = load_config(overrides={"carving": {"resolution": 40, "qa_resolution": 40}})
    sil = {"silhouettes": str(tmp_path / "silhouettes.npz")}
    report = stage_carve(sil, out, cfg, "s", has_laser=True)
    assert report["empty"] is True
    assert "flagged as absurd" in report["reason"] and "surrounds_view" in report["reason"]
    report = stage_carve(sil, out, cfg, "s", has_laser=False)
    assert not report.get("empty") and report["occupied_voxels"] > 0
    # one view not flagged: it carves with the others, as before
    views[3]["qa"]["flags"] = []
    (tmp_path / "reports" / "silhouettes.json").write_text(json.dumps({"views": views}))
    report = stage_carve(sil, out, cfg, "s", has_laser=True)
    assert not report.get("empty") and report["occupied_voxels"] > 0


# ---------------------------------------------------------------------- real data
DTU = Path(__file__).resolve().parents[2] / "shared" / "real" / "dtu_scan24.mcap"


@pytest.mark.skipif(not DTU.exists(), reason="../shared/real/dtu_scan24.mcap not present")
def test_agreement_on_dtu_published_masks():
    """DTU scan 24 with its published masks: the house is cut off by many frames and
    outside_image is keep; no correct mask may be flagged. Two of them spoiled (one
    inverted, one missing its left half) are flagged, and only they."""
    from robo3d.carving import flag_disagreeing_views
    from robo3d.recording.reader import read_recording

    rec = read_recording(DTU, roles=("views",))
    views = sorted(rec.views, key=lambda m: m.timestamp_ns)
    cams = [rec.camera_for(m) for m in views]
    poses = rec.camera_poses(views)
    masks = [cv2.imdecode(np.frombuffer(rec.attachments[f"ground_truth/silhouettes/{i:03d}.png"],
                                        np.uint8), cv2.IMREAD_GRAYSCALE) > 127
             for i in range(len(views))]
    cut = sum(m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any() for m in masks)
    assert cut > len(masks) // 2  # most views cut the house off
    grid = make_grid(*rec.workspace, resolution=48)
    qa = flag_disagreeing_views(grid, masks, cams, poses)
    assert qa["flagged"] == []
    assert max(v["missing_fraction"] for v in qa["views"]) < 0.08
    assert max(v["spurious_fraction"] for v in qa["views"]) < 0.02
    masks[7] = ~masks[7]
    masks[33] = masks[33] & (np.arange(masks[33].shape[1]) >= masks[33].shape[1] // 2)
    assert flag_disagreeing_views(grid, masks, cams, poses)["flagged"] == [7, 33]


# ---------------------------------------------------------------------- points vs. the hull
def test_points_outside_the_silhouettes(sphere_views):
    """Points on the sphere lie inside every silhouette; points off it by more than the
    tolerance lie outside some, by about their true distance (seen at their depth)."""
    cam, Ts, masks = sphere_views
    rng = np.random.default_rng(3)
    dirs = rng.normal(size=(400, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    on = CENTRE + RADIUS * dirs
    n_on, worst_on = outside_silhouettes(on, masks, cam, Ts, tol_px=1.0, tol_m=0.0)
    assert n_on.max() == 0
    # one pixel at the sphere is DIST / F = 1.3 mm: mask edges are exact to about that
    assert worst_on.max() < 1.5 * DIST / F
    off = CENTRE + (RADIUS + 0.006) * dirs  # 6 mm off: outside the silhouette of views
    n_off, worst_off = outside_silhouettes(off, masks, cam, Ts, tol_px=1.0, tol_m=0.0005)
    assert n_off.min() >= 1 and np.median(n_off) >= 6
    # the farthest a view sees it outside is close to the true 6 mm (depth of the point)
    assert np.all((worst_off > 0.004) & (worst_off < 0.0075))
    # a tolerance larger than the offset keeps them all
    n_tol, _ = outside_silhouettes(off, masks, cam, Ts, tol_px=1.0, tol_m=0.008)
    assert n_tol.max() == 0
    # a point is judged only by the views it projects into (in front of the camera)
    far = CENTRE + np.array([0.0, 0.0, 50.0])
    sees = [(invert_transform(T)[2, :3] @ far + invert_transform(T)[2, 3]) > 0
            and 0 <= _cv2_pixels(far, cam, T)[0, 0] < cam.width
            and 0 <= _cv2_pixels(far, cam, T)[0, 1] < cam.height for T in Ts]
    n_far, _ = outside_silhouettes(far[None], masks, cam, Ts)
    assert n_far[0] == sum(sees) < len(Ts)
    assert outside_silhouettes(np.zeros((0, 3)), masks, cam, Ts)[0].shape == (0,)


def test_the_workflow_tells_the_carve_whether_the_scan_has_laser_frames(tmp_path, ring,
                                                                        monkeypatch):
    """The rule's ``params.has_laser`` reaches the stage (what lets a scan's carve leave
    an empty hull); a rule without it runs the stage as before."""
    from types import SimpleNamespace

    import robo3d.pipeline as pipeline
    from robo3d.config import load_config

    seen = []
    monkeypatch.setattr(pipeline, "_setup_logging", lambda *a, **k: None)  # pytest's own
    monkeypatch.setitem(pipeline.STAGES, "carve",
                        lambda i, o, c, r, has_laser=False: seen.append(has_laser))

    class _Named(dict):
        def items(self):  # snakemake's Namedlist
            return super().items()

    cfg = load_config()
    for params, want in ((SimpleNamespace(cfg=cfg, has_laser=True), True),
                         (SimpleNamespace(cfg=cfg), False)):
        smk = SimpleNamespace(wildcards={"rec": "r"}, log=[str(tmp_path / "carve.log")],
                              input=_Named(silhouettes="s.npz"), output=_Named(npz="h.npz"),
                              threads=1, params=params, config=cfg)
        pipeline.run_from_snakemake("carve", smk)
        assert seen[-1] is want


def test_stage_carve_without_a_box_and_one_usable_view(tmp_path, sphere_views):
    """No box in the recording and one mask left (the others empty: their segmentation
    failed): no carving box can be placed (seed §3.4 needs two views). An error in a
    photo set; in a scan with laser frames an empty hull, so that the laser goes on
    (random scene 463 of stop 52 failed the whole recording here)."""
    from robo3d.config import load_config
    from robo3d.errors import StageError
    from robo3d.pipeline import stage_carve

    cam, Ts, masks = sphere_views
    few = [masks[0]] + [np.zeros_like(m) for m in masks[1:4]]
    _silhouettes_npz(tmp_path / "silhouettes.npz", cam, Ts[:4], few)
    out = {"npz": str(tmp_path / "hull.npz"), "ply": str(tmp_path / "hull.ply"),
           "report": str(tmp_path / "carve.json"), "rrd": str(tmp_path / "carve.rrd")}
    cfg = load_config(overrides={"carving": {"resolution": 32}})
    with pytest.raises(StageError, match="at least 2 views"):
        stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s")
    report = stage_carve({"silhouettes": str(tmp_path / "silhouettes.npz")}, out, cfg, "s",
                         has_laser=True)
    assert report["empty"] and "no carving box" in report["reason"]
    grid = VoxelGrid.load_npz(out["npz"])
    assert grid.n_occupied == 0


def test_hull_pieces_counts_the_connected_pieces():
    from robo3d.carving import hull_pieces

    occ = np.zeros((20, 20, 20), bool)
    occ[1:9, 1:9, 1:9] = True  # 512 voxels
    occ[12:16, 12:16, 12:16] = True  # 64
    occ[18, 18, 18] = True  # a speck
    occ[9, 9, 9] = True  # touches the first cube at a corner only: 26-connected to it
    p = hull_pieces(occ)
    assert p["n"] == 3 and p["n_over_min"] == 2
    assert p["largest_fraction"] == pytest.approx(513 / 578)
    assert hull_pieces(np.zeros((3, 3, 3), bool)) == {"n": 0, "largest_fraction": None,
                                                      "n_over_min": 0}


def test_stage_carve_says_when_the_hull_falls_apart(tmp_path, sphere_views):
    """One object's silhouettes carve one piece, with no warning; silhouettes that carve
    two equal pieces (here two spheres side by side: masks that disagree about an
    object's shape carve it into shards the same way, random scene 784) are named in the
    report, the log and the overview's notes."""
    from robo3d.config import load_config
    from robo3d.overview import recording_status
    from robo3d.pipeline import stage_carve

    cam, Ts, masks = sphere_views
    cfg = load_config(overrides={"carving": {"resolution": 48}})
    out = {k: str(tmp_path / f"hull_one.{k}") for k in ("npz", "ply", "report", "rrd")}
    _silhouettes_npz(tmp_path / "one.npz", cam, Ts, masks)
    one = stage_carve({"silhouettes": str(tmp_path / "one.npz")}, out, cfg, "s")
    assert one["pieces"]["n_over_min"] == 1 and one["pieces"]["largest_fraction"] > 0.99
    assert "warning" not in one["pieces"]
    shift = np.array([0.7 * RADIUS, 0.0, 0.0])
    two = [_render_sphere(cam, T, CENTRE - shift, 0.5 * RADIUS)
           | _render_sphere(cam, T, CENTRE + shift, 0.5 * RADIUS) for T in Ts]
    _silhouettes_npz(tmp_path / "two.npz", cam, Ts, two)
    out = {k: str(tmp_path / f"hull_two.{k}") for k in ("npz", "ply", "report", "rrd")}
    rep = stage_carve({"silhouettes": str(tmp_path / "two.npz")}, out, cfg, "s")
    p = rep["pieces"]
    assert p["n_over_min"] == 2 and 0.45 < p["largest_fraction"] < 0.55
    assert p["warning"].startswith("the hull falls apart into 2 pieces")
    _, notes = recording_status({"stages": {"carve": rep}})
    assert p["warning"] in notes
    off = load_config(overrides={"carving": {"resolution": 48, "qa_largest_piece": None}})
    out = {k: str(tmp_path / f"hull_off.{k}") for k in ("npz", "ply", "report", "rrd")}
    rep = stage_carve({"silhouettes": str(tmp_path / "two.npz")}, out, off, "s")
    assert rep["pieces"]["n_over_min"] == 2 and "warning" not in rep["pieces"]
