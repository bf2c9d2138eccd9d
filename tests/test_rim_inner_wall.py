"""The silhouette term on a thin-walled cup and across sweeps (issue 11: the cup, the fin).

A cup (outer radius 30 mm, a 2.5 mm wall) is seen from straight above: its silhouette
is the disc of the rim's outer circle. Laser profiles run round the wall, 1.1 mm apart,
on the outer face (normals outward) and on the inner face (normals inward). Both faces'
points are grazing; the inner face's project 3.3 px inside the silhouette with their
normal pointing INTO the mask, and no contour of this view lies there: before the test
that the projected normal faces out of the mask they were matched to the outer edge
(the cup with 4 sweeps: its top sweep ended 1.29 mm off).
"""

from __future__ import annotations

import numpy as np

from robo3d.camera import CameraModel
from robo3d.registration import (
    _RIM,
    _RIM_CELL_PX,
    SilhouetteViews,
    _outermost_across_sweeps,
    _rim_residuals,
    _view_fields,
)
from robo3d.sim.rig import look_at

R_OUT, WALL, TOP, EYE_Z = 0.030, 0.0025, 0.050, 0.400  # metres
SS = 4  # supersampling of the rendered view (anti-aliased edge)


def _view():
    cam = CameraModel("camera", 320, 240, [[450.0, 0, 159.5], [0, 450.0, 119.5], [0, 0, 1]],
                      np.zeros(5))
    T = look_at(np.array([0.0, 0.0, EYE_Z]), np.zeros(3))
    v, u = np.mgrid[0:cam.height * SS, 0:cam.width * SS]
    uv = (np.stack([u.ravel(), v.ravel()], 1) + 0.5) / SS - 0.5
    rho = np.hypot(uv[:, 0] - 159.5, uv[:, 1] - 119.5)
    cover = (rho <= 450.0 * R_OUT / (EYE_Z - TOP)).reshape(
        cam.height, SS, cam.width, SS).mean(axis=(1, 3))
    return SilhouetteViews([25.0 + 160.0 * cover], [cover >= 0.5], [cam], T[None])


def _rings(radius: float, sign: float):
    a = np.arange(0.0, 2 * np.pi, 2e-4 / radius)
    z = TOP - 1.1e-3 * (np.arange(8) + 0.3)
    aa, zz = np.meshgrid(a, z)
    pts = np.stack([radius * np.cos(aa.ravel()), radius * np.sin(aa.ravel()), zz.ravel()], 1)
    nrm = sign * np.stack([np.cos(aa.ravel()), np.sin(aa.ravel()), np.zeros(aa.size)], 1)
    return pts, nrm, np.repeat(np.arange(8), len(a))


def test_inner_wall_is_no_contour_and_outer_wall_sits_on_the_edge():
    field = _view_fields(_view(), _RIM_CELL_PX, 0.7)[0]
    # the rings do not pass over the rim's edge (nothing of them says how far up the
    # wall goes: ``test_rim_flat_face``), so the default test takes none; the test of
    # the normal's side is checked here without it
    rim = {**_RIM, "crossing": False}
    p_in, n_in, g_in = _rings(R_OUT - WALL, -1.0)
    idx, r, _, _, _ = _rim_residuals(field, p_in, n_in, g_in, **rim)
    assert len(idx) == 0, f"{len(idx)} inner-wall points taken for contour points"
    p_out, n_out, g_out = _rings(R_OUT, 1.0)
    assert len(_rim_residuals(field, p_out, n_out, g_out, **_RIM)[0]) == 0
    idx, r, _, _, _ = _rim_residuals(field, p_out, n_out, g_out, **rim)
    assert len(idx) > 50  # the contour round the rim is found
    # the topmost profile lies 0.04 px inside the edge: its residuals must say so; the
    # deeper ones are kept within the border cells' tolerance (0.5 px) and no further
    top = g_out[idx] == 0
    truth = 450.0 * R_OUT / (EYE_Z - TOP + 0.33e-3) - 450.0 * R_OUT / (EYE_Z - TOP)
    assert top.sum() > 10 and abs(float(np.median(r[top])) - truth) < 0.15
    assert r.min() > -0.75


def test_a_sweep_short_of_the_contour_gives_way_to_one_that_reaches_it():
    # one view, one border cell (7) reached by sweep 0's profile on the edge (residual
    # -0.05 px) and by sweep 1's, which stops 1.7 px inside; sweep 1 alone reaches cell 9
    z3 = np.zeros((1, 3))
    found = [(0, np.array([3, 4]), np.array([-0.05, 0.1]), np.vstack([z3, z3]),
              np.full(2, 1e-3), np.array([7, 7])),
             (1, np.array([5, 6]), np.array([-1.7, -1.2]), np.vstack([z3, z3]),
              np.full(2, 1e-3), np.array([7, 9]))]
    kept = {s: (list(idx), list(r)) for s, idx, r, _, _ in _outermost_across_sweeps(found, 0.75)}
    assert kept[0][0] == [3, 4]
    assert kept[1][0] == [6]  # the one inside cell 7 is dropped, cell 9's is kept
