"""The silhouette term takes a profile's most outward point as a point of the contour
generator only where the sweep passes over it (issue 11; random scene 677, a user's box).

A cylinder (radius 30 mm, axis vertical) is seen from the side and above. Laser profiles
lie on its wall, normals radial:

- vertical profiles, 1.1 mm apart round the wall, that pass the contour generator (those
  before it face the view, those after it face away): those nearest to it touch the
  silhouette, and their residuals say so;
  (no profile's normals turn along it: the test along the profiles alone lost them);
- horizontal profiles round the wall, each over the contour generator (its normals turn
  from facing the view to facing away along it): found, on the edge.
"""

from __future__ import annotations

import numpy as np

from robo3d.camera import CameraModel, pixel_rays
from robo3d.registration import _RIM, _RIM_CELL_PX, SilhouetteViews, _rim_residuals, _view_fields
from robo3d.sim.rig import look_at

R, H = 0.030, 0.050  # metres
EYE = np.array([0.0, -0.40, 0.20])
SS = 3  # supersampling of the rendered view (anti-aliased edges)
#: the contour generator on the +x side: the wall's normal is perpendicular to the line
#: of sight where R + EYE_y sin(phi) = 0 (the normal has no z); before it (smaller phi)
#: the wall faces the view
PHI_G = np.arcsin(R / EYE[1])


def _view() -> SilhouetteViews:
    cam = CameraModel("camera", 320, 240, [[450.0, 0, 159.5], [0, 450.0, 119.5], [0, 0, 1]],
                      np.zeros(5))
    T = look_at(EYE, np.array([0.0, 0.0, 0.025]))
    v, u = np.mgrid[0:cam.height * SS, 0:cam.width * SS]
    uv = (np.stack([u.ravel(), v.ravel()], 1) + 0.5) / SS - 0.5
    o, d = pixel_rays(uv, cam, T)
    o = np.broadcast_to(o, d.shape)
    # the wall: |o + t d|_xy = R, 0 <= z <= H; the top: z = H, |xy| <= R
    a = d[:, 0] ** 2 + d[:, 1] ** 2
    b = 2 * (o[:, 0] * d[:, 0] + o[:, 1] * d[:, 1])
    c = o[:, 0] ** 2 + o[:, 1] ** 2 - R**2
    disc = b * b - 4 * a * c
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / (2 * a)
    z = o[:, 2] + t * d[:, 2]
    wall = (disc >= 0) & (z >= 0) & (z <= H)
    t_top = (H - o[:, 2]) / d[:, 2]
    p_top = o + t_top[:, None] * d
    top = np.hypot(p_top[:, 0], p_top[:, 1]) <= R
    cover = (wall | top).reshape(cam.height, SS, cam.width, SS).mean(axis=(1, 3))
    return SilhouetteViews([30.0 + 150.0 * cover], [cover >= 0.5], [cam], T[None])


def _wall(phi: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ring = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
    return R * ring + np.stack([0 * phi, 0 * phi, z], axis=1), ring


def _vertical_profiles(k_max: int):
    """Profiles along z at 1.1 mm steps round the wall, numbered in that order, from 10
    steps before the contour generator to ``k_max`` steps after it."""
    ks = np.arange(-10, k_max + 1)
    z = np.arange(0.005, 0.045, 2e-4)
    kk, zz = np.meshgrid(ks, z, indexing="ij")
    pts, nrm = _wall(PHI_G + kk.ravel() * 1.1e-3 / R, zz.ravel())
    return pts, nrm, (kk.ravel() + 10)


def test_vertical_profiles_that_pass_the_contour_generator_find_it():
    field = _view_fields(_view(), _RIM_CELL_PX, 0.7)[0]
    pts, nrm, prof = _vertical_profiles(5)
    idx, r, _, _, _ = _rim_residuals(field, pts, nrm, prof, **_RIM)
    assert len(idx) >= 4
    assert set(np.unique(prof[idx])) <= set(range(6, 16))  # within 4 steps of it
    assert np.abs(r).max() < 0.5  # px: on the edge (the search's 0.25 px steps)


def test_horizontal_profiles_over_the_contour_generator_find_it():
    field = _view_fields(_view(), _RIM_CELL_PX, 0.7)[0]
    z = 0.005 + 1.1e-3 * np.arange(36)
    phi = PHI_G + np.arange(-0.2, 0.2, 2e-4 / R)
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    pts, nrm = _wall(pp.ravel(), zz.ravel())
    prof = np.repeat(np.arange(len(z)), len(phi))
    idx, r, _, _, _ = _rim_residuals(field, pts, nrm, prof, **_RIM)
    assert len(idx) >= 20
    assert abs(float(np.median(r))) < 0.25 and np.abs(r).max() < 0.6  # px

