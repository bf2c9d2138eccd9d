"""Tests of robo3d.stripes: seed §4.2 (eqs. 18-20) and sub-pixel stripe centres.

Ground truth is analytic: synthetic Gaussian stripes with a known sub-pixel centre per
column, rendered with noise and quantised to uint8.
"""

from __future__ import annotations

import numpy as np
import pytest

from robo3d.stripes import (
    REJECTION_REASONS,
    StripePoints,
    brightness_coefficient,
    extract_stripe_centres,
    extract_stripes_batch,
    lightness,
)

H, W = 96, 128


def _centres(w: int = W, h: int = H, seed: int = 0) -> np.ndarray:
    """A smooth stripe path with arbitrary sub-pixel offsets (one row per column)."""
    u = np.arange(w)
    rng = np.random.default_rng(seed)
    return h / 2 + 0.2 * h * np.sin(u / 17.0) + rng.uniform(-0.5, 0.5)


def _profile(vc: np.ndarray, h: int, sigma: float) -> np.ndarray:
    rows = np.arange(h, dtype=np.float64)[:, None]
    return np.exp(-0.5 * ((rows - vc[None, :]) / sigma) ** 2)


def _stripe_image(vc: np.ndarray, *, amp: float = 200.0, bg: float = 12.0,
                  sigma: float = 1.6, noise: float = 2.0, seed: int = 1,
                  h: int = H) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = bg + amp * _profile(vc, h, sigma) + rng.normal(0.0, noise, (h, vc.size))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


# ---------------------------------------------------------------------------- eq. 18, 19
def test_lightness_eq19_hand_made_rgb():
    img = np.array([[[200, 50, 100], [100, 150, 20]],
                    [[0, 0, 0], [255, 255, 255]]], dtype=np.uint8)
    L = lightness(img)
    assert L.dtype == np.float32 and L.shape == (2, 2)
    np.testing.assert_array_equal(L, [[125.0, 85.0], [0.0, 255.0]])
    mono = np.array([[3, 7]], dtype=np.uint16)
    np.testing.assert_array_equal(lightness(mono), [[3.0, 7.0]])


def test_brightness_coefficient_eq18_samples():
    img = np.zeros((4, 5, 3), dtype=np.uint8)
    img[1, 2] = (200, 50, 100)
    img[3, 4] = (100, 150, 20)
    # mean R, G, B over the two samples: (150, 100, 60) -> s = (150 + 60) / 2
    mask = np.zeros((4, 5), dtype=bool)
    mask[1, 2] = mask[3, 4] = True
    assert brightness_coefficient(img, sample=mask) == pytest.approx(105.0)
    # the same samples as (u, v) pixels
    uv = np.array([[2.0, 1.0], [4.0, 3.0]])
    assert brightness_coefficient(img, sample=uv) == pytest.approx(105.0)
    # automatic samples: the 2 brightest pixels of 20 are exactly these two
    assert brightness_coefficient(img, top_fraction=2 / 20) == pytest.approx(105.0)
    # with a laser-off frame, the samples are taken on the difference
    off = np.full_like(img, 10)
    assert brightness_coefficient(img + off, sample=mask, background=off) == pytest.approx(
        105.0)


def test_brightness_coefficient_mono_and_errors():
    img = np.zeros((3, 3), dtype=np.uint8)
    img[1, 1] = 90
    assert brightness_coefficient(img, top_fraction=1 / 9) == pytest.approx(90.0)
    with pytest.raises(ValueError, match="outside"):
        brightness_coefficient(img, sample=np.array([[5.0, 0.0]]))
    with pytest.raises(ValueError, match="top_fraction"):
        brightness_coefficient(img, top_fraction=0.0)


# ---------------------------------------------------------------------------- centres
@pytest.mark.parametrize("method", ["cog", "gaussian"])
@pytest.mark.parametrize("sigma", [1.0, 1.6, 2.5])
def test_gaussian_stripe_subpixel_accuracy(method, sigma):
    vc = _centres()
    img = _stripe_image(vc, sigma=sigma)
    sp = extract_stripe_centres(img, method=method)
    assert len(sp) == W, sp.rejected
    np.testing.assert_array_equal(sp.u, np.arange(W))
    err = sp.v - vc[sp.line]
    assert _rms(err) < 0.05, (method, sigma, _rms(err))
    assert np.abs(err).max() < 0.2
    # FWHM of a Gaussian is 2.355 sigma (the stripe is slanted: a column cuts it wider)
    assert np.median(sp.width_px) == pytest.approx(2.3548 * sigma, rel=0.2)
    assert np.all((sp.confidence > 0.5) & (sp.confidence <= 1.0))
    assert np.median(sp.peak) == pytest.approx(200.0, rel=0.05)


@pytest.mark.parametrize("method", ["cog", "gaussian"])
def test_saturated_stripe(method):
    # peak far above full scale: a flat top clipped at 255, well above the band
    vc = _centres()
    img = _stripe_image(vc, amp=400.0, sigma=1.6)
    assert (img == 255).sum() > W
    sp = extract_stripe_centres(img, method=method)
    assert len(sp) == W
    assert _rms(sp.v - vc) < 0.05


def test_noise_free_float_image_is_nearly_exact():
    vc = _centres()
    img = (0.8 * _profile(vc, H, 1.5)).astype(np.float32)
    for method, tol in (("cog", 0.01), ("gaussian", 1e-4)):
        sp = extract_stripe_centres(img, method=method)
        assert len(sp) == W
        assert np.abs(sp.v - vc).max() < tol, method


def test_band_clipping_the_peak_does_not_bias():
    # s well below the peak: the eq. 20 band only holds the stripe's flanks
    vc = _centres()
    img = _stripe_image(vc, amp=200.0, sigma=2.0)
    sp = extract_stripe_centres(img, s=0.6 * 212.0)
    assert len(sp) == W
    assert _rms(sp.v - vc) < 0.05


@pytest.mark.parametrize("channel", [0, 1, 2])
def test_any_laser_colour(channel):
    vc = _centres()
    stripe = _stripe_image(vc, amp=220.0, bg=0.0)
    img = np.full((H, W, 3), 25, dtype=np.uint8)  # grey scene
    img[..., channel] = np.maximum(stripe, 25)
    sp = extract_stripe_centres(img)
    assert len(sp) == W, sp.rejected
    assert _rms(sp.v - vc) < 0.05


def test_rows_axis_and_auto():
    vc = _centres(w=W, h=H)
    img = _stripe_image(vc)
    ref = extract_stripe_centres(img, axis="columns")
    rows = extract_stripe_centres(np.ascontiguousarray(img.T), axis="rows")
    assert rows.axis == "rows" and len(rows) == len(ref)
    np.testing.assert_allclose(rows.u, ref.v, atol=1e-9)
    np.testing.assert_array_equal(rows.v, ref.u)
    np.testing.assert_array_equal(rows.line, np.arange(W))
    assert extract_stripe_centres(img.T, axis="auto").axis == "rows"
    assert extract_stripe_centres(img, axis="auto").axis == "columns"
    # a frame rebuilt from its stored centres keeps its axis and lines
    rebuilt = StripePoints(u=rows.u, v=rows.v)
    assert rebuilt.axis == "rows"
    np.testing.assert_array_equal(rebuilt.line, rows.line)
    assert StripePoints(u=ref.u, v=ref.v).axis == "columns"


def test_two_blobs_and_too_weak_columns_are_rejected():
    vc = np.full(W, 40.3)
    base = 12.0 + 200.0 * _profile(vc, H, 1.5)
    # columns 10..14: a reflection, a second stripe as bright as the first
    base[:, 10:15] += 200.0 * _profile(np.full(5, 75.0), H, 1.5)
    # columns 30..33: washed out by ambient light (stripe 5 levels above 200)
    base[:, 30:34] = 200.0 + 5.0 * _profile(vc[:4], H, 1.5)
    img = np.clip(np.rint(base), 0, 255).astype(np.uint8)
    sp = extract_stripe_centres(img, s=212.0)
    assert sp.rejected["two_blobs"] == 5
    assert sp.rejected["too_weak"] == 4
    assert len(sp) == W - 9
    assert not np.isin(sp.line, np.r_[10:15, 30:34]).any()
    assert np.abs(sp.v - 40.3).max() < 0.05


def test_highlight_brighter_than_band_is_ignored_beside_the_stripe():
    vc = _centres()
    img = _stripe_image(vc, amp=200.0, sigma=1.5)
    on_stripe = np.zeros((H, W), dtype=bool)
    on_stripe[np.rint(vc).astype(int), np.arange(W)] = True
    s = brightness_coefficient(img, sample=on_stripe)  # the seed's user-picked samples
    assert 190.0 < s < 215.0
    lit = img.copy()
    lit[5:12, 20:40] = 255  # a white specular highlight, above the band, sharp edges
    sp = extract_stripe_centres(lit, s=s)
    assert len(sp) == W and sp.rejected["two_blobs"] == 0
    assert _rms(sp.v - vc) < 0.05


def test_too_wide_and_at_border():
    vc = np.full(W, 48.0)
    img = _stripe_image(vc, sigma=8.0, noise=0.0)  # FWHM 18.8 px > 15 px
    sp = extract_stripe_centres(img)
    assert len(sp) == 0 and sp.rejected["too_wide"] == W
    assert len(extract_stripe_centres(img, max_width_px=30.0)) == W

    edge = _stripe_image(np.full(W, 0.2), sigma=1.5, noise=0.0)  # cut by row 0
    sp = extract_stripe_centres(edge)
    assert len(sp) == 0 and sp.rejected["at_border"] == W


def test_background_frame_is_subtracted():
    vc = _centres()
    rng = np.random.default_rng(3)
    ambient = np.clip(60 + 0.8 * np.arange(H)[:, None] + rng.normal(0, 2, (H, W)), 0, 255)
    on = np.clip(ambient + 150.0 * _profile(vc, H, 1.6), 0, 255)
    sp = extract_stripe_centres(on.astype(np.float32) / 255.0,
                                background=ambient.astype(np.float32) / 255.0)
    assert len(sp) == W
    assert _rms(sp.v - vc) < 0.02


def test_empty_image_gives_zero_points_with_reason():
    black = np.zeros((H, W), dtype=np.uint8)
    sp = extract_stripe_centres(black)
    assert len(sp) == 0 and sp.u.shape == (0,) and sp.pixels_uv.shape == (0, 2)
    assert sp.n_lines == W and sp.rejected["too_weak"] == W
    assert set(sp.rejected) == set(REJECTION_REASONS)
    none = extract_stripe_centres(np.zeros((0, 0, 3), dtype=np.uint8))
    assert len(none) == 0
    # uniform noise, no stripe: whatever passes must be rare
    noisy = np.random.default_rng(0).integers(0, 8, (H, W)).astype(np.uint8)
    assert len(extract_stripe_centres(noisy)) == 0


def test_batch_matches_single_frames():
    frames = np.stack([_stripe_image(_centres(seed=i), seed=i) for i in range(3)])
    out = extract_stripes_batch(frames)
    assert len(out) == 3
    for f, sp in zip(frames, out, strict=True):
        ref = extract_stripe_centres(f)
        np.testing.assert_array_equal(sp.v, ref.v)
    assert len(extract_stripes_batch(list(frames), method="gaussian")) == 3
    with pytest.raises(ValueError, match="single RGB"):
        extract_stripes_batch(np.zeros((H, W, 3), dtype=np.uint8))


def test_input_errors():
    with pytest.raises(ValueError, match=r"\(H, W\) mono or \(H, W, 3\) RGB"):
        extract_stripe_centres(np.zeros((4, 4, 2), dtype=np.uint8))
    with pytest.raises(ValueError, match="axis"):
        extract_stripe_centres(np.zeros((4, 4), dtype=np.uint8), axis="diagonal")
    with pytest.raises(ValueError, match="method"):
        extract_stripe_centres(np.zeros((4, 4), dtype=np.uint8), method="steger")
    with pytest.raises(ValueError, match="background"):
        extract_stripe_centres(np.zeros((4, 4), dtype=np.uint8),
                               background=np.zeros((4, 5), dtype=np.uint8))
    with pytest.raises(ValueError, match="same length"):
        StripePoints(u=np.zeros(3), v=np.zeros(2))
