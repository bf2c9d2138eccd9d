"""Tests of robo3d.camera: OpenCV agreement and project/unproject round trips."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from robo3d.camera import CameraModel, pixel_rays, project_points
from robo3d.errors import CalibrationError
from robo3d.transforms import euler_to_matrix, invert_transform, make_transform

K = np.array([[612.5, 0.0, 319.2], [0.0, 610.1, 241.7], [0.0, 0.0, 1.0]])
D = np.array([-0.21, 0.08, 0.0012, -0.0009, -0.015])  # an ordinary lens


def _points_in_view(cam: CameraModel, n: int, seed: int) -> np.ndarray:
    """Camera-frame points whose pixels lie inside the image (with a margin)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform([5, 5], [cam.width - 5, cam.height - 5], size=(n, 2))
    depth = rng.uniform(0.2, 3.0, size=n)
    x, y = (uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy
    return np.stack([x, y, np.ones(n)], axis=1) * depth[:, None]


def test_project_matches_opencv() -> None:
    cam = CameraModel("camera", 640, 480, K, D)
    pts = _points_in_view(cam, 500, seed=0)
    uv, front = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)
    assert front.all()
    assert np.abs(uv - ref.reshape(-1, 2)).max() < 1e-9
    # with a pose: project_points(points_base, camera, T_base_camera)
    t_base_cam = make_transform(euler_to_matrix("zyx", [0.3, -0.1, 2.9]), [0.2, 0.1, 0.8])
    pts_base = pts @ t_base_cam[:3, :3].T + t_base_cam[:3, 3]
    t_cam_base = invert_transform(t_base_cam)
    rvec, _ = cv2.Rodrigues(t_cam_base[:3, :3])
    ref, _ = cv2.projectPoints(pts_base, rvec, t_cam_base[:3, 3], K, D)
    uv2, _ = project_points(pts_base, cam, t_base_cam)
    assert np.abs(uv2 - ref.reshape(-1, 2)).max() < 1e-9


def test_project_then_rays_round_trip() -> None:
    for d in (D, np.zeros(5)):
        cam = CameraModel("camera", 640, 480, K, d)
        pts = _points_in_view(cam, 500, seed=1)
        uv, _ = cam.project(pts)
        rays = cam.rays(uv)
        want = pts / np.linalg.norm(pts, axis=1, keepdims=True)
        np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-15)
        assert np.abs(rays - want).max() < 1e-9
    # in the base frame: the ray from the camera centre passes through the point
    t_base_cam = make_transform(euler_to_matrix("zyx", [0.7, 0.2, -0.4]), [1.0, -0.5, 0.3])
    pts_base = pts @ t_base_cam[:3, :3].T + t_base_cam[:3, 3]
    uv, _ = project_points(pts_base, cam, t_base_cam)
    origin, dirs = pixel_rays(uv, cam, t_base_cam)
    v = pts_base - origin
    cross = np.cross(dirs, v / np.linalg.norm(v, axis=1, keepdims=True))
    assert np.abs(cross).max() < 1e-9


def test_distortion_round_trip_and_undistort_matches_opencv() -> None:
    cam = CameraModel("camera", 640, 480, K, D)
    xy = cam.pixels_to_normalized(np.random.default_rng(2).uniform([0, 0], [640, 480], (300, 2)))
    und = cam.undistort_normalized(xy)
    assert np.abs(cam.distort_normalized(und) - xy).max() < 1e-9
    uv = cam.normalized_to_pixels(xy)
    ref = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, D, None, None, None,
                              (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15))
    assert np.abs(und - ref.reshape(-1, 2)).max() < 1e-8


def test_behind_camera_and_footprint() -> None:
    cam = CameraModel("camera", 640, 480, K)
    _, front = cam.project(np.array([[0.0, 0, 1], [0, 0, -1], [0, 0, 0]]))
    assert front.tolist() == [True, False, False]
    # seed eq. 8: one pixel at depth z covers z / f metres
    assert cam.pixel_footprint(2.0) == pytest.approx(2.0 / np.sqrt(612.5 * 610.1), rel=1e-15)


def test_bad_calibrations() -> None:
    with pytest.raises(CalibrationError, match="focal lengths must be positive"):
        CameraModel("c", 640, 480, np.diag([0.0, 1.0, 1.0]))
    with pytest.raises(CalibrationError, match="not finite"):
        CameraModel("c", 640, 480, K, np.array([np.nan, 0, 0, 0, 0]))
    with pytest.raises(CalibrationError, match="5 coefficients"):
        CameraModel("c", 640, 480, K, np.zeros(6))
    with pytest.raises(CalibrationError, match="image size"):
        CameraModel("c", 0, 480, K)
    # rational_polynomial: only its plumb_bob part is modelled; k4..k6 must be zero
    cam = CameraModel("c", 640, 480, K, np.concatenate([D, [0.0, 0.0, 0.0]]))
    np.testing.assert_array_equal(cam.D, D)
    with pytest.raises(CalibrationError, match="k4..k6"):
        CameraModel("c", 640, 480, K, np.concatenate([D, [0.1, 0.0, 0.0]]))
    assert CameraModel("c", 640, 480, K, np.zeros(4)).D.shape == (5,)
