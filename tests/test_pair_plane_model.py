"""The plane model's error that the alignment adds to each point-to-plane correspondence
(:func:`robo3d.registration._plane_model_sd`), against exact geometry.

On a sphere the point-to-plane residual of two exact surface points along the target's
true normal is the sphere's sagitta between them, ``R (1 - cos a)``, whatever the poses;
the model (half the distance times the chord of the normals) is exactly that. On a plane
it is zero, so the weights of flat faces do not change.
"""

from __future__ import annotations

import numpy as np

from robo3d.registration import _plane_model_sd


def _sphere_points(rng, n: int, radius: float, spread: float):
    """Pairs of points on a sphere of ``radius`` at most ``spread`` apart (true normals)."""
    a = rng.normal(size=(n, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = a + rng.uniform(-1.0, 1.0, size=(n, 3)) * spread / radius
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    return radius * a, a, radius * b, b


def test_model_is_the_true_residual_on_a_sphere():
    rng = np.random.default_rng(0)
    for radius in (0.0008, 0.005, 0.04):  # a rounded edge, a fillet, a vase
        x, nx, y, ny = _sphere_points(rng, 2000, radius, 0.0011)
        r = np.einsum("ij,ij->i", x - y, ny)  # the refinement's residual, exact poses
        model = _plane_model_sd(x, y, nx, ny)
        np.testing.assert_allclose(model, np.abs(r), rtol=1e-9, atol=1e-15)
        # the error is real on a tight radius: tens of micrometres at the profiles' spacing
        if radius < 0.001:
            assert np.percentile(model, 90) > 50e-6


def test_model_is_zero_on_a_plane():
    rng = np.random.default_rng(1)
    x = np.c_[rng.uniform(-0.02, 0.02, (500, 2)), np.zeros(500)]
    y = x + np.c_[rng.uniform(-0.001, 0.001, (500, 2)), np.zeros(500)]
    n = np.tile([0.0, 0.0, 1.0], (500, 1))
    assert np.all(_plane_model_sd(x, y, n, n) == 0.0)
