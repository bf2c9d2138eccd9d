"""Headless ray-cast pictures (robo3d.render): the mesh lands where the camera looks, the
colours follow the values, the figure file is a PNG."""

from __future__ import annotations

import numpy as np
import pytest

from robo3d.render import colormap, error_figure, render_mesh


def _sphere():
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(0.03, resolution=20)
    return np.asarray(m.vertices) + [0.5, 0.1, 0.1], np.asarray(m.triangles)


def test_colormap_ends_and_nan():
    c = colormap(np.array([0.0, 1.0, 5.0, np.nan]), vmax=1.0)
    assert c.shape == (4, 3)
    assert c[0, 2] > c[0, 0]  # blue end
    assert c[1, 0] > c[1, 2] and np.allclose(c[1], c[2])  # red end, clamped
    assert np.allclose(c[3], 0.6)
    with pytest.raises(ValueError, match="vmax"):
        colormap(np.zeros(2), vmax=0.0)


def test_render_centres_the_mesh_and_colours_it():
    v, f = _sphere()
    img = render_mesh(v, f, vertex_colors=np.tile([1.0, 0.0, 0.0], (len(v), 1)),
                      width=64, height=48, background=1.0)
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    hit = ~np.all(img == 255, axis=2)
    ys, xs = np.nonzero(hit)
    # the sphere is framed in the middle, and red where hit
    assert abs(xs.mean() - 31.5) < 2 and abs(ys.mean() - 23.5) < 2
    assert 0.1 < hit.mean() < 0.6
    assert np.all(img[hit][:, 1] < 10) and np.all(img[hit][:, 0] > 50)
    empty = render_mesh(v, f[:0], width=16, height=16)
    assert np.all(empty == 255)


def test_error_figure_writes_a_png(tmp_path):
    import cv2

    v, f = _sphere()
    out = error_figure(tmp_path / "e.png", v, f, np.linspace(0, 0.3, len(v)), vmax_mm=0.2,
                       title="test", width=80, height=60)
    img = cv2.imread(str(out))
    assert img is not None and img.shape[1] == 4 * 80 and img.shape[0] > 60
    with pytest.raises(ValueError, match="errors_mm"):
        error_figure(tmp_path / "x.png", v, f, np.zeros(3))
