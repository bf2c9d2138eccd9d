"""Laser-off frames subtracted (seed §4.2's laser-on minus laser-off difference): the
difference keeps the frame's own type, so the detector's colour test and saturation level
are those of the camera's frames."""

from __future__ import annotations

import numpy as np

from robo3d.stripes import StripeOptions, extract_stripe_centres


def _frames(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A red stripe (v = 100 + 0.1 u) over a grey scene, occluded for u >= 200, and a
    thin white line at rows 150-151 there that the laser-off frame does not have (a
    cable moved between the two exposures); and the laser-off frame."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:240, 0:320]
    stripe = 120.0 * np.exp(-0.5 * ((yy - 100.0 - 0.1 * xx) / 1.5) ** 2)
    base = np.full((240, 320, 3), 60.0) + rng.normal(0.0, 2.0, (240, 320, 3))
    img = base.copy()
    img[..., 0] += stripe
    img[..., 1:] += 0.1 * stripe[..., None]
    img[:, 200:] = base[:, 200:]
    img[150:152, 200:, :] += 120.0
    return (np.clip(img, 0, 255).astype(np.uint8), np.clip(base, 0, 255).astype(np.uint8))


def test_a_white_line_is_not_the_stripe_with_or_without_the_laser_off_frame():
    img, off = _frames()
    o = StripeOptions()
    for bg in (None, off, off.astype(np.float64)):
        sp = extract_stripe_centres(img, background=bg, options=o)
        on_stripe = np.abs(sp.v - (100.0 + 0.1 * sp.u)) < 1.0
        assert on_stripe.all(), (None if bg is None else bg.dtype,
                                 np.round(sp.v[~on_stripe][:5], 1))
        assert on_stripe.sum() >= 195  # the stripe's 200 columns, less the border's


def test_a_zero_background_changes_nothing():
    img, _ = _frames(1)
    o = StripeOptions()
    a = extract_stripe_centres(img, options=o)
    b = extract_stripe_centres(img, background=np.zeros_like(img), options=o)
    assert len(a.u) > 150
    np.testing.assert_array_equal(a.u, b.u)
    np.testing.assert_array_equal(a.v, b.v)
