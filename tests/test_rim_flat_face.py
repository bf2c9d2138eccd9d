"""The silhouette term on a flat face seen at a grazing angle (issue 11: the bracket; random
scene 677, a user's box).

A block is seen from above, nearly along its +y face, so that the silhouette's far
side is the block's top edge and the +y face is back-facing at about 7 degrees from
edge-on. Laser profiles run across that face parallel to the edge, 1.1 mm apart: every
one of them has the grazing normal and continues along the contour, but none passes
over the edge, and nothing of the sweep says how far above the last of them the face
ends. At the true pose the rim residuals must not put the face inside the silhouette:
without the test of each border cell's most outward profile they did (mean -2.6 px, the
deepest -4.6 px: 19 profiles down the face); with it, -0.9 and -1.6 px from the 5
topmost profiles, and the refinement pushed such sweeps outward until the mean agreed
(the bracket's upright ended 0.7 mm outward on both faces; a box's sweep 1.4 mm from its
true pose). Now a face's profiles count only where the sweep passes over the contour
generator (``test_rim_passes_contour``): these give none.
"""

from __future__ import annotations

import numpy as np

from robo3d.camera import CameraModel, pixel_rays
from robo3d.registration import _RIM, _RIM_CELL_PX, SilhouetteViews, _rim_residuals, _view_fields
from robo3d.sim.rig import look_at

LO, HI = np.array([-0.03, -0.02, 0.0]), np.array([0.03, 0.02, 0.05])  # a block, metres
SS = 3  # supersampling of the rendered view (anti-aliased edges)


def _view():
    cam = CameraModel("camera", 320, 240, [[450.0, 0, 159.5], [0, 450.0, 119.5], [0, 0, 1]],
                      np.zeros(5))
    T = look_at(np.array([0.0, -0.018, 0.37]), np.array([0.0, 0.0, 0.025]))
    v, u = np.mgrid[0:cam.height * SS, 0:cam.width * SS]
    uv = (np.stack([u.ravel(), v.ravel()], 1) + 0.5) / SS - 0.5
    o, d = pixel_rays(uv, cam, T)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (LO - o) / d, (HI - o) / d
    hit = (np.nanmax(np.minimum(t1, t2), axis=1) <= np.nanmin(np.maximum(t1, t2), axis=1))
    cover = hit.reshape(cam.height, SS, cam.width, SS).mean(axis=(1, 3))
    grey = 30.0 + 150.0 * cover
    return SilhouetteViews([grey], [cover >= 0.5], [cam], T[None])


def test_profiles_across_a_grazing_flat_face_do_not_bias_the_silhouette_term():
    views = _view()
    x, z = np.meshgrid(np.arange(-0.025, 0.025, 2e-4), HI[2] - 1.1e-3 * (np.arange(40) + 0.3))
    pts = np.stack([x.ravel(), np.full(x.size, HI[1]), z.ravel()], axis=1)
    nrm = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
    profile = np.repeat(np.arange(40), x.shape[1])
    field = _view_fields(views, _RIM_CELL_PX, 1.0)[0]
    idx, _, _, _, _ = _rim_residuals(field, pts, nrm, profile, **_RIM)
    assert len(idx) == 0
    # without the test of the sweep passing the contour: the topmost profiles, inside
    idx, r, _, _, _ = _rim_residuals(field, pts, nrm, profile, **{**_RIM, "crossing": False})
    assert len(idx) >= 5 and len(np.unique(profile[idx])) <= 6
    assert np.mean(r) < -0.5  # px; the true contour is at 0


def test_several_sweeps_in_one_call_give_each_sweeps_own_result():
    """The refinement searches each view once for all sweeps (``group``): each sweep's
    residuals must be exactly those of a call with its points alone, although the sweeps
    use the same profile numbers and reach the same border cells."""
    views = _view()
    field = _view_fields(views, _RIM_CELL_PX, 1.0)[0]
    x, z = np.meshgrid(np.arange(-0.025, 0.025, 2e-4), HI[2] - 1.1e-3 * (np.arange(40) + 0.3))
    face = np.stack([x.ravel(), np.full(x.size, HI[1]), z.ravel()], axis=1)
    profile = np.repeat(np.arange(40), x.shape[1])
    # three sweeps: the face as it is, lifted by 0.3 mm, and shifted sideways by 0.5 mm
    # and thinned (other positions, other point counts), all with profiles 0-39
    sweeps = [face, face + [0.0, 0.0, 3e-4], (face + [5e-4, 0.0, 0.0])[::3]]
    profiles = [profile, profile, profile[::3]]
    nrm = [np.tile([0.0, 1.0, 0.0], (len(p), 1)) for p in sweeps]
    rim = {**_RIM, "crossing": False}  # the grouping (with the test, no residual here)
    alone = [_rim_residuals(field, p, n, g, **rim)
             for p, n, g in zip(sweeps, nrm, profiles, strict=True)]
    grp = np.repeat(np.arange(3), [len(p) for p in sweeps])
    together = _rim_residuals(field, np.concatenate(sweeps), np.concatenate(nrm),
                              np.concatenate(profiles), **rim, group=grp)
    first = np.r_[0, np.cumsum([len(p) for p in sweeps])[:-1]]
    for k in range(3):
        assert len(alone[k][0]) >= 3
        sel = grp[together[0]] == k
        np.testing.assert_array_equal(together[0][sel] - first[k], alone[k][0])
        np.testing.assert_array_equal(together[4][sel], alone[k][4])  # the cells
        # the values to rounding: a matrix product's last bit may depend on its size
        for a, b in zip(together[1:4], alone[k][1:4], strict=True):
            np.testing.assert_allclose(a[sel], b, rtol=1e-7, atol=0.0)
    # without the groups, the sweeps' profiles 0-39 are taken as one sweep's: fewer kept
    merged = _rim_residuals(field, np.concatenate(sweeps), np.concatenate(nrm),
                            np.concatenate(profiles), **rim)
    assert len(merged[0]) < len(together[0])
