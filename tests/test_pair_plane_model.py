"""The alignment's pair residuals (:func:`robo3d.registration._pair_residuals`) against
exact geometry.

On a sphere, two exact surface points with their true normals: the residual along one
point's normal is the sagitta between them, ``R (1 - cos a)``, whatever the poses (the
pull a point-to-plane term along one normal exerts on a rounded edge); along the sum of
the two normals it is zero (Rusinkiewicz 2019), and the plane-model error the alignment
weighs each correspondence by is that sagitta. On a plane both are zero, so the weights
of flat faces do not change.
"""

from __future__ import annotations

import numpy as np

from robo3d.registration import _pair_residuals


def _sphere_points(rng, n: int, radius: float, spread: float):
    """Pairs of points on a sphere of ``radius`` at most about ``spread`` apart, with
    their true normals."""
    a = rng.normal(size=(n, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = a + rng.uniform(-1.0, 1.0, size=(n, 3)) * spread / radius
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    return radius * a, a, radius * b, b


def test_symmetric_residual_is_exact_on_a_sphere_and_the_model_is_its_sagitta():
    rng = np.random.default_rng(0)
    for radius in (0.0008, 0.005, 0.04):  # a rounded edge, a fillet, a vase
        x, nx, y, ny = _sphere_points(rng, 2000, radius, 0.0011)
        r, n, model = _pair_residuals(x, y, nx, ny)
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-12)
        assert np.max(np.abs(r)) < 1e-12 * radius / 1e-3 + 1e-15
        one_sided = np.einsum("ij,ij->i", x - y, ny)  # along the target's normal alone
        np.testing.assert_allclose(model, np.abs(one_sided), rtol=1e-9, atol=1e-15)
        if radius < 0.001:  # a rounded edge at the profiles' spacing: tens of micrometres
            assert np.percentile(model, 90) > 50e-6


def test_flat_face_has_no_model_error():
    rng = np.random.default_rng(1)
    x = np.c_[rng.uniform(-0.02, 0.02, (500, 2)), np.zeros(500)]
    y = x + np.c_[rng.uniform(-0.001, 0.001, (500, 2)), np.full(500, 3e-5)]
    nz = np.tile([0.0, 0.0, 1.0], (500, 1))
    r, n, model = _pair_residuals(x, y, nz, nz)
    assert np.all(model == 0.0)
    np.testing.assert_allclose(r, -3e-5, rtol=1e-9)  # the offset between the two faces
