"""Tests of robo3d.stripes: seed §4.2 (eqs. 18-20) and sub-pixel stripe centres.

Ground truth is analytic: synthetic Gaussian stripes with a known sub-pixel centre per
column, rendered with noise and quantised to uint8.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from robo3d.stripes import (
    REJECTION_REASONS,
    StripeOptions,
    StripePoints,
    _noise_sigma,
    brightness_coefficient,
    estimate_laser_colour,
    extract_stripe_centres,
    extract_stripes_batch,
    lightness,
)

H, W = 96, 128
#: The project's stripe options but ``min_peak`` at 4 % of each image's full scale (10.2
#: grey levels for uint8), so that one threshold fits the uint8, uint16 and float images.
BASE = StripeOptions(min_peak=None)


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
@pytest.mark.parametrize("sigma", [1.0, 1.6, 2.5, 4.0])
def test_gaussian_stripe_subpixel_accuracy(method, sigma):
    vc = _centres()
    img = _stripe_image(vc, sigma=sigma)
    sp = extract_stripe_centres(img, options=BASE.replace(method=method))
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
    sp = extract_stripe_centres(img, options=BASE.replace(method=method))
    assert len(sp) == W
    assert _rms(sp.v - vc) < 0.05


def test_noise_free_float_image_is_nearly_exact():
    vc = _centres()
    img = (0.8 * _profile(vc, H, 1.5)).astype(np.float32)
    # the band's flat baseline is exactly 0 here; the ridge detector's linear baseline
    # through the window's two sides takes the Gaussian's tails (1e-6) with it
    for detector, method, tol in (("band", "cog", 0.01), ("band", "gaussian", 1e-4),
                                  ("ridge", "cog", 0.01), ("ridge", "gaussian", 3e-4)):
        sp = extract_stripe_centres(img, options=BASE.replace(method=method, detector=detector))
        assert len(sp) == W
        assert np.abs(sp.v - vc).max() < tol, (detector, method)


def test_band_clipping_the_peak_does_not_bias():
    # s well below the peak: the eq. 20 band only holds the stripe's flanks
    vc = _centres()
    img = _stripe_image(vc, amp=200.0, sigma=2.0)
    sp = extract_stripe_centres(img, options=BASE.replace(s=0.6 * 212.0))
    assert len(sp) == W
    assert _rms(sp.v - vc) < 0.05


@pytest.mark.parametrize("channel", [0, 1, 2])
def test_any_laser_colour(channel):
    vc = _centres()
    stripe = _stripe_image(vc, amp=220.0, bg=0.0)
    img = np.full((H, W, 3), 25, dtype=np.uint8)  # grey scene
    img[..., channel] = np.maximum(stripe, 25)
    sp = extract_stripe_centres(img, options=BASE)
    assert len(sp) == W, sp.rejected
    assert _rms(sp.v - vc) < 0.05


def test_rows_axis_and_auto():
    vc = _centres(w=W, h=H)
    img = _stripe_image(vc)
    ref = extract_stripe_centres(img, options=BASE.replace(axis="columns"))
    rows = extract_stripe_centres(np.ascontiguousarray(img.T), options=BASE.replace(axis="rows"))
    assert rows.axis == "rows" and len(rows) == len(ref)
    np.testing.assert_allclose(rows.u, ref.v, atol=1e-9)
    np.testing.assert_array_equal(rows.v, ref.u)
    np.testing.assert_array_equal(rows.line, np.arange(W))
    assert extract_stripe_centres(img.T, options=BASE.replace(axis="auto")).axis == "rows"
    assert extract_stripe_centres(img, options=BASE.replace(axis="auto")).axis == "columns"
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
    sp = extract_stripe_centres(img, options=BASE.replace(s=212.0, detector="band"))
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
    for detector in ("band", "ridge"):
        sp = extract_stripe_centres(lit, options=BASE.replace(s=s, detector=detector))
        assert len(sp) == W and sp.rejected["two_blobs"] == 0
        assert _rms(sp.v - vc) < 0.05


def test_too_wide_and_at_border():
    vc = np.full(W, 48.0)
    img = _stripe_image(vc, sigma=8.0, noise=0.0)  # FWHM 18.8 px > 15 px
    sp = extract_stripe_centres(img, options=BASE)
    assert len(sp) == 0 and sp.rejected["too_wide"] == W
    assert len(extract_stripe_centres(img, options=BASE.replace(max_width_px=30.0))) == W

    edge = _stripe_image(np.full(W, 0.2), sigma=1.5, noise=0.0)  # cut by row 0
    sp = extract_stripe_centres(edge, options=BASE.replace(detector="band"))
    assert len(sp) == 0 and sp.rejected["at_border"] == W
    # the ridge detector needs the baseline on both sides: no candidate there at all
    sp = extract_stripe_centres(edge, options=BASE)
    assert len(sp) == 0 and sp.rejected["too_weak"] == W


def test_centre_spread_over_a_bright_face_beside_the_stripe_is_dropped():
    """Where a faint stripe runs along an edge beside a face as bright in its channel,
    the run spreads over the face and the centre moves onto it: a centre more than
    ``max_width_rel`` times its frame's median width is dropped (``too_wide``). A stripe
    that is wide everywhere (seen obliquely) keeps every centre."""
    vc = _centres()
    img = _stripe_image(vc, sigma=1.2, noise=0.0).astype(np.float64)
    rows = np.arange(H)[:, None]
    face = np.zeros((H, W), bool)
    cols = slice(40, 64)
    face[:, cols] = (rows >= vc[None, cols] + 1.5) & (rows <= vc[None, cols] + 13)
    img[face] = 12.0 + 0.9 * 200.0
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    off = extract_stripe_centres(img, options=BASE)
    err = np.abs(off.v - vc[off.line])
    moved = err > 2.0  # without the test: centres spread onto the face, 8 px off
    assert moved.sum() >= 5 and np.all(np.isin(off.line[moved], np.arange(40, 64)))
    assert np.all(off.width_px[moved] > 3 * np.median(off.width_px))
    assert BASE.max_width_rel == 0.0  # off by default (the alignment uses wide rim points)
    sp = extract_stripe_centres(img, options=BASE.replace(max_width_rel=3.0))
    assert sp.rejected["too_wide"] == off.rejected["too_wide"] + int(moved.sum())
    np.testing.assert_array_equal(sp.line, off.line[~moved])  # only those go
    assert np.abs(sp.v - vc[sp.line]).max() < 0.5  # what stays is on the line
    oblique = _stripe_image(vc, sigma=4.0, noise=0.0)  # FWHM 9.4 px in every column
    assert len(extract_stripe_centres(oblique, options=BASE.replace(max_width_rel=3.0))) == W
    with pytest.raises(ValueError, match="max_width_rel"):
        extract_stripe_centres(img, options=BASE.replace(max_width_rel=0.5))


def test_skew_tells_a_centre_pulled_onto_a_lit_face_from_a_wide_or_saturated_stripe():
    """``skew_px``: the centre's distance from the middle of its profile's top. A stripe
    along an edge above a face lit in its channel (the blue cell's block: a shoulder
    that starts at three quarters of the peak and fades over 10 px) pulls the centre of
    gravity 2.5-3.5 px onto the face, and the skew says so (the align stage drops such
    points, ``alignment.max_centre_skew_px``); a stripe seen obliquely (wide) or
    saturated (a flat top) keeps its centre at its top: in the grey image, in a laser
    colour, and searched along rows alike."""
    vc = _centres()
    rows = np.arange(H, dtype=np.float64)[:, None]
    d = rows - vc[None, :]
    shoulder = np.where(d >= 1.0, 0.75 * 120.0 * np.exp(-(d - 1.0) / 10.0), 0.0)
    shoulder[:, :40] = shoulder[:, 64:] = 0.0
    img = np.maximum(20.0 + 120.0 * _profile(vc, H, 1.2), 20.0 + shoulder)
    img += np.random.default_rng(0).normal(0.0, 1.0, img.shape)
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    rgb = np.full((H, W, 3), 12, np.uint8)
    rgb[..., 2] = img  # a blue laser above a face as blue
    face = np.arange(40, 64)
    for frame, transposed in ((img, False), (rgb, False), (img.T, True)):
        sp = extract_stripe_centres(np.ascontiguousarray(frame), options=BASE)
        c, line = (sp.u, sp.v) if transposed else (sp.v, sp.u)
        line = np.rint(line).astype(int)
        err = c - vc[line]
        on_face = np.isin(line, face)
        assert on_face.sum() == face.size and len(sp) == W
        assert np.all(err[on_face] > 2.0)  # pulled onto the face ...
        assert np.all(sp.skew_px[on_face] > 2.0)  # ... and far from the top
        np.testing.assert_allclose(sp.skew_px[on_face], err[on_face], atol=0.6)
        assert np.abs(err[~on_face]).max() < 0.3 and np.abs(sp.skew_px[~on_face]).max() < 0.6
    oblique = extract_stripe_centres(_stripe_image(vc, sigma=4.0, noise=0.0), options=BASE)
    assert len(oblique) == W and np.median(oblique.width_px) > 9
    assert np.abs(oblique.skew_px).max() < 0.6
    flat = np.clip(_stripe_image(vc, amp=600.0, sigma=2.0, noise=2.0), 0, 255).astype(np.uint8)
    sat = extract_stripe_centres(flat, options=BASE)  # 4-6 px of 255 across the line
    assert len(sat) >= W - 2 and np.sum(flat == 255, axis=0).min() >= 4
    assert np.abs(sat.skew_px).max() < 0.8
    assert np.abs(sat.v - vc[sat.line]).max() < 0.3
    band = extract_stripe_centres(img, options=BASE.replace(detector="band"))
    assert len(band) > W // 2 and np.all(np.isfinite(band.skew_px))
    on_face = np.isin(band.line, face)
    assert np.all(band.skew_px[on_face] > 2.0)


def test_background_frame_is_subtracted():
    vc = _centres()
    rng = np.random.default_rng(3)
    ambient = np.clip(60 + 0.8 * np.arange(H)[:, None] + rng.normal(0, 2, (H, W)), 0, 255)
    on = np.clip(ambient + 150.0 * _profile(vc, H, 1.6), 0, 255)
    sp = extract_stripe_centres(on.astype(np.float32) / 255.0,
                                background=ambient.astype(np.float32) / 255.0, options=BASE)
    assert len(sp) == W
    assert _rms(sp.v - vc) < 0.02


def test_empty_image_gives_zero_points_with_reason():
    black = np.zeros((H, W), dtype=np.uint8)
    sp = extract_stripe_centres(black, options=BASE)
    assert len(sp) == 0 and sp.u.shape == (0,) and sp.pixels_uv.shape == (0, 2)
    assert sp.n_lines == W and sp.rejected["too_weak"] == W
    assert set(sp.rejected) == set(REJECTION_REASONS)
    none = extract_stripe_centres(np.zeros((0, 0, 3), dtype=np.uint8), options=BASE)
    assert len(none) == 0
    # uniform noise, no stripe: whatever passes must be rare
    noisy = np.random.default_rng(0).integers(0, 8, (H, W)).astype(np.uint8)
    assert len(extract_stripe_centres(noisy, options=BASE)) == 0


def test_batch_matches_single_frames():
    frames = np.stack([_stripe_image(_centres(seed=i), seed=i) for i in range(3)])
    out = extract_stripes_batch(frames, options=BASE)
    assert len(out) == 3
    for f, sp in zip(frames, out, strict=True):
        ref = extract_stripe_centres(f, options=BASE)
        np.testing.assert_array_equal(sp.v, ref.v)
    assert len(extract_stripes_batch(list(frames), options=BASE.replace(method="gaussian"))) == 3
    with pytest.raises(ValueError, match="single RGB"):
        extract_stripes_batch(np.zeros((H, W, 3), dtype=np.uint8), options=BASE)


def test_input_errors():
    with pytest.raises(ValueError, match=r"\(H, W\) mono or \(H, W, 3\) RGB"):
        extract_stripe_centres(np.zeros((4, 4, 2), dtype=np.uint8), options=BASE)
    with pytest.raises(ValueError, match="axis"):
        extract_stripe_centres(np.zeros((4, 4), dtype=np.uint8),
                               options=BASE.replace(axis="diagonal"))
    with pytest.raises(ValueError, match="method"):
        extract_stripe_centres(np.zeros((4, 4), dtype=np.uint8),
                               options=BASE.replace(method="steger"))
    with pytest.raises(ValueError, match="background"):
        extract_stripe_centres(np.zeros((4, 4), dtype=np.uint8),
                               background=np.zeros((4, 5), dtype=np.uint8), options=BASE)
    with pytest.raises(ValueError, match="same length"):
        StripePoints(u=np.zeros(3), v=np.zeros(2))
    with pytest.raises(ValueError, match="reference"):
        extract_stripe_centres(np.zeros((4, 4), dtype=np.uint8),
                               options=BASE.replace(reference="global"))
    with pytest.raises(ValueError, match="reference_lines"):
        extract_stripe_centres(np.zeros((4, 4), dtype=np.uint8),
                               options=BASE.replace(reference_lines=-1))
    with pytest.raises(ValueError, match="s must be"):
        extract_stripe_centres(np.zeros((4, 4), dtype=np.uint8), options=BASE.replace(s=-3.0))
    with pytest.raises(ValueError, match="non-finite"):
        extract_stripe_centres(np.full((4, 4), np.nan), options=BASE)
    with pytest.raises(ValueError, match="threads"):
        extract_stripes_batch([np.zeros((4, 4), dtype=np.uint8)], threads=0, options=BASE)


# ---------------------------------------------------------------------------- the band
def _varying_stripe(amp_left: float, amp_right: float, *, sigma: float = 1.2,
                    seed: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A stripe whose brightness falls linearly along the frame (incidence, albedo)."""
    vc = _centres(seed=seed)
    amp = np.linspace(amp_left, amp_right, W)
    rng = np.random.default_rng(seed)
    img = 6.0 + amp[None, :] * _profile(vc, H, sigma) + rng.normal(0.0, 1.0, (H, W))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), vc


def test_local_reference_keeps_a_stripe_of_varying_brightness():
    img, vc = _varying_stripe(230.0, 40.0)
    local = extract_stripe_centres(img, options=BASE.replace(detector="band"))
    assert len(local) == W, local.rejected
    assert _rms(local.v - vc) < 0.05
    ridge = extract_stripe_centres(img, options=BASE)
    assert len(ridge) == W and _rms(ridge.v - vc) < 0.05
    # the seed's one band around the frame's s loses the dim end (and the bright one is
    # kept only because a lone blob brighter than the band is still the stripe)
    frame = extract_stripe_centres(img, options=BASE.replace(reference="frame", detector="band"))
    assert 100.0 < frame.s < 160.0
    assert frame.rejected["no_band"] > 0.25 * W
    assert len(frame) < 0.75 * W
    assert np.all(frame.peak > 0.8 * frame.s)
    # the confidence follows the stripe's contrast against the frame's s
    assert local.confidence[-1] < 0.6 < local.confidence[0]


def test_sweep_end_rim_of_the_object_beside_the_dim_table_stripe():
    # the sheet lights a rim of the object (columns 50-70, bright) and the table
    # (everywhere, 10 x dimmer, below min_peak): the rim must be found, the table not
    rows = np.arange(H, dtype=np.float64)[:, None]
    table = 12.0 * np.exp(-0.5 * ((rows - 30.0) / 1.0) ** 2) * np.ones((1, W))
    vc = np.full(W, 60.37)
    obj = np.zeros((H, W))
    obj[:, 50:71] = 90.0 * _profile(vc[50:71], H, 0.8)
    img = np.clip(np.rint(2.0 + table + obj), 0, 255).astype(np.uint8)
    sp = extract_stripe_centres(img, options=BASE.replace(min_peak=20.0))
    np.testing.assert_array_equal(sp.line, np.arange(50, 71))
    assert np.abs(sp.v - 60.37).max() < 0.05
    assert sp.rejected["too_weak"] == W - 21
    # eq. 18 on the samples: the rim's brightest pixels, row 60 (0.37 px off the centre)
    assert sp.s == pytest.approx(np.rint(2.0 + 90.0 * np.exp(-0.5 * (0.37 / 0.8) ** 2)))


def test_highlight_brighter_than_the_band_is_ignored_with_the_local_reference():
    vc = _centres()
    img = _stripe_image(vc, amp=200.0, sigma=1.5)
    lit = img.copy()
    lit[5:12, 20:28] = 255  # a white highlight over 8 columns (< reference_lines)
    sp = extract_stripe_centres(lit, options=BASE)
    assert len(sp) == W and sp.rejected["two_blobs"] == 0
    assert _rms(sp.v - vc) < 0.05


def test_reflection_inside_the_band_is_rejected_with_the_local_reference():
    vc = np.full(W, 40.3)
    base = 12.0 + 200.0 * _profile(vc, H, 1.5)
    base[:, 10:15] += 180.0 * _profile(np.full(5, 75.0), H, 1.5)  # 90 % as bright
    base[:, 60:65] += 100.0 * _profile(np.full(5, 75.0), H, 1.5)  # 50 %: below the band
    img = np.clip(np.rint(base), 0, 255).astype(np.uint8)
    sp = extract_stripe_centres(img, options=BASE.replace(detector="band"))
    assert sp.rejected["two_blobs"] == 5
    assert not np.isin(sp.line, np.r_[10:15]).any()
    assert np.isin(np.r_[60:65], sp.line).all()  # the dim reflection is ignored
    assert np.abs(sp.v - 40.3).max() < 0.05


def _integrated_stripe(vc: np.ndarray, sigma: float, *, h: int = H, amp: float = 200.0,
                       noise: float = 1.0, seed: int = 5) -> np.ndarray:
    """A pixel-integrated Gaussian stripe (what a sensor records), uint8."""
    r = np.arange(h, dtype=np.float64)[:, None]

    def cdf(x: np.ndarray) -> np.ndarray:
        return 0.5 * (1.0 + erf(x / (np.sqrt(2.0) * sigma)))

    prof = cdf(r + 0.5 - vc[None, :]) - cdf(r - 0.5 - vc[None, :])
    prof /= prof.max(axis=0, keepdims=True)
    rng = np.random.default_rng(seed)
    img = 8.0 + amp * prof + rng.normal(0.0, noise, prof.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("method", ["cog", "gaussian"])
@pytest.mark.parametrize("sigma", [0.35, 0.5])
def test_narrow_pixel_integrated_stripe(method, sigma):
    # FWHM 1.2-1.5 px, as in the simulated frames: pixel locking stays below 0.03 px
    vc = _centres()
    sp = extract_stripe_centres(_integrated_stripe(vc, sigma), options=BASE.replace(method=method))
    assert len(sp) == W
    err = sp.v - vc
    assert _rms(err) < 0.03 and abs(err.mean()) < 0.01, (_rms(err), err.mean())
    assert np.median(sp.width_px) == pytest.approx(1.2 if sigma == 0.35 else 1.5, abs=0.15)


def test_rgb_mono_and_other_dtypes_agree():
    vc = _centres()
    img = _stripe_image(vc, sigma=1.3)
    ref = extract_stripe_centres(img, options=BASE)
    grey = extract_stripe_centres(np.repeat(img[..., None], 3, axis=2), options=BASE)
    np.testing.assert_allclose(grey.v, ref.v, atol=1e-9)
    # 16 bits and floats: the same centres (min_peak in the image's own units)
    wide = extract_stripe_centres(img.astype(np.uint16) * 257,
                                  options=BASE.replace(min_peak=10.2 * 257))
    np.testing.assert_allclose(wide.v, ref.v, atol=1e-6)
    flt = extract_stripe_centres(img / 255.0, options=BASE.replace(min_peak=0.04))
    np.testing.assert_allclose(flt.v, ref.v, atol=1e-5)
    # a red laser on a grey scene, by eq. 19
    red = np.stack([img, np.full_like(img, 10), np.full_like(img, 10)], axis=-1)
    sp = extract_stripe_centres(red, options=BASE.replace(min_peak=5.0))
    assert len(sp) == W and _rms(sp.v - vc) < 0.05
    assert sp.s == pytest.approx(brightness_coefficient(red, sample=sp.pixels_uv), rel=0.1)


def test_noise_sigma_estimate():
    rng = np.random.default_rng(7)
    img = np.clip(np.rint(100.0 + rng.normal(0.0, 5.0, (240, 320))), 0, 255).astype(np.uint8)
    sigma = _noise_sigma(img[..., None], 1)
    assert sigma == pytest.approx(5.0, rel=0.1)
    # and the threshold keeps the centres of a stripe in that noise unbiased
    vc = _centres()
    sp = extract_stripe_centres(_stripe_image(vc, noise=5.0, sigma=1.6), options=BASE)
    assert len(sp) >= W - 2 and _rms(sp.v - vc[sp.line]) < 0.1


def test_auto_axis_counts_lines():
    vc = _centres(w=W, h=H)
    img = _stripe_image(vc)
    assert extract_stripe_centres(img, options=BASE.replace(axis="auto")).axis == "columns"
    tall = np.ascontiguousarray(img.T)  # a vertical stripe: more rows than columns lit
    sp = extract_stripe_centres(tall, options=BASE.replace(axis="auto"))
    assert sp.axis == "rows" and len(sp) == W
    np.testing.assert_allclose(sp.u, vc, atol=0.2)
    np.testing.assert_array_equal(sp.v, np.arange(W))


def test_batch_on_threads_equals_serial():
    frames = [_stripe_image(_centres(seed=i), seed=i) for i in range(6)]
    one = extract_stripes_batch(frames, options=BASE)
    two = extract_stripes_batch(frames, threads=2, options=BASE.replace(method="cog"))
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a.v, b.v)
        assert a.rejected == b.rejected


# ---------------------------------------------------------------------------- real light
#: What a laser of each colour adds per channel (a webcam sees a green laser in all three).
LASER_RGB = {"red": (1.0, 0.12, 0.10), "green": (0.40, 1.0, 0.45), "blue": (0.20, 0.35, 1.0)}


def _room_scene(colour: str, angle_deg: float, *, h: int = 240, w: int = 320,
                seed: int = 0, amp: float = 160.0, sigma: float = 1.3,
                reflection: float = 0.35) -> tuple[np.ndarray, dict]:
    """A room-lit RGB frame with a laser line of ``colour`` at ``angle_deg`` (from u
    towards v) through the image centre: an illumination gradient, white, grey and
    coloured patches (albedo per channel), texture, clutter (thin white and coloured
    lines, laser-coloured dots) and a weaker parallel line 22 px away (a reflection)
    over half of the line. The laser's light is scaled by the surface's albedo.
    Returns the uint8 image and the truth: the line's unit normal n and offset c
    (n . (u, v) = c), the reflection's offset."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    th = np.radians(angle_deg)
    n = np.array([-np.sin(th), np.cos(th)])
    c = float(n @ [w / 2 + 0.37, h / 2 - 0.21])
    dist = xx * n[0] + yy * n[1] - c
    albedo = np.full((h, w, 3), 0.55)
    albedo += 0.04 * np.sin(xx / 7.0 + yy / 11.0)[..., None]  # texture
    patches = [(0.95, 0.95, 0.92), (0.9, 0.22, 0.18), (0.2, 0.7, 0.25), (0.2, 0.3, 0.85),
               (0.9, 0.85, 0.2), (0.15, 0.15, 0.15), (0.95, 0.95, 0.95)]
    near = np.abs(dist) < 6.0
    for i, col in enumerate(patches):
        for _ in range(50):  # no patch edge running along the line (crossing it is fine)
            y0, x0 = rng.integers(0, h - 40), rng.integers(0, w - 50)
            y1, x1 = y0 + rng.integers(30, 90), x0 + rng.integers(40, 110)
            edge = np.zeros((h, w), bool)
            edge[y0:y1, x0:x1] = True
            edge[y0 + 1:y1 - 1, x0 + 1:x1 - 1] = False
            if (edge & near).sum() < 20:
                break
        albedo[y0:y1, x0:x1] = col
        if i == 0:  # a white patch under the centre of the line
            albedo[h // 2 - 30:h // 2 + 30, w // 2 - 40:w // 2 + 40] = col
    light = 150.0 + 90.0 * (xx / w) - 40.0 * (yy / h)  # room light, varying
    img = albedo * light[..., None]
    # clutter: thin white, grey and coloured lines, laser-coloured dots
    for _ in range(14):
        for _ in range(50):  # crossing the line is fine, running along it beside it is not
            a = rng.uniform(0, np.pi)
            cu, cv = rng.uniform(0, w), rng.uniform(0, h)
            d = np.abs(-(xx - cu) * np.sin(a) + (yy - cv) * np.cos(a))
            t = np.abs((xx - cu) * np.cos(a) + (yy - cv) * np.sin(a))
            seg = (d < 1.0) & (t < rng.uniform(10, 40))
            if (seg & (np.abs(dist) < 10.0)).sum() < 0.3 * max(seg.sum(), 1):
                break
        prof = np.exp(-0.5 * (d / 0.9) ** 2) * (t < t[seg].max() + 0.5 if seg.any() else 0)
        tint = [(255, 255, 255), (200, 200, 200), (170, 70, 60), (70, 160, 80),
                (70, 90, 180)][rng.integers(0, 5)]
        img = img * (1 - prof[..., None]) + prof[..., None] * np.array(tint, float)
    lrgb = np.array(LASER_RGB[colour])
    for _ in range(10):
        cu, cv = rng.uniform(0, w), rng.uniform(0, h)
        dot = np.exp(-0.5 * ((xx - cu) ** 2 + (yy - cv) ** 2) / 1.2 ** 2)
        img += 120.0 * dot[..., None] * lrgb
    # the laser line and its reflection
    along = xx * np.cos(th) + yy * np.sin(th)
    line = amp * np.exp(-0.5 * (dist / sigma) ** 2)
    c_refl = c + 22.0
    refl = reflection * amp * np.exp(-0.5 * ((dist - 22.0) / sigma) ** 2)
    refl *= along > float(np.median(along))
    img += albedo * ((line + refl)[..., None] * lrgb * 1.6)
    img += rng.normal(0.0, 1.5, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), {"n": n, "c": c, "c_refl": c_refl}


def _line_errors(sp, truth: dict) -> np.ndarray:
    """Perpendicular distance (px) of each centre from the true line."""
    return sp.pixels_uv @ truth["n"] - truth["c"]


def _visible_lines(truth: dict, axis: str, h: int, w: int, margin: int = 10) -> np.ndarray:
    """The lines (rows or columns) whose crossing with the true line lies inside the image
    at least ``margin`` px from its border."""
    n, c = truth["n"], truth["c"]
    if axis == "rows":
        v = np.arange(h, dtype=float)
        u = (c - n[1] * v) / n[0]
        ok = (u >= margin) & (u < w - margin) & (v >= margin) & (v < h - margin)
        return v[ok].astype(int)
    u = np.arange(w, dtype=float)
    v = (c - n[0] * u) / n[1]
    ok = (v >= margin) & (v < h - margin) & (u >= margin) & (u < w - margin)
    return u[ok].astype(int)


@pytest.mark.parametrize("colour", ["red", "green", "blue"])
@pytest.mark.parametrize("angle", [0.0, 30.0, 45.0, 90.0, 120.0])
def test_laser_line_in_room_light_any_colour_any_angle(colour, angle):
    """A laser line of any colour and direction on a room-lit, cluttered frame: found in
    its own colour (found automatically), one centre per line across it, sub-pixel on
    the true line, its reflection and the clutter rejected, its direction reported."""
    img, truth = _room_scene(colour, angle, seed=int(angle) + len(colour))
    h, w = img.shape[:2]
    sp = extract_stripe_centres(img, options=BASE)
    assert sp.colour == colour
    # the stripe's direction decides the lines: within 45 degrees of vertical, rows
    assert sp.axis == ("rows" if 45.0 < angle < 135.0 else "columns") or angle == 45.0
    d_ang = (sp.angle_deg - angle + 90.0) % 180.0 - 90.0
    assert abs(d_ang) < 1.0, sp.angle_deg
    err = _line_errors(sp, truth)
    on_line = np.abs(err) < 1.0
    assert np.median(np.abs(err[on_line])) < 0.1, np.median(np.abs(err[on_line]))
    # recall: the lines the stripe crosses (away from the border) have their centre
    lines = _visible_lines(truth, sp.axis, h, w)
    found = np.isin(lines, sp.line[on_line])
    assert found.mean() >= 0.9, (found.mean(), sp.rejected)
    # the reflection: no centre on it; the clutter: cables of the laser's own colour as
    # long as min_run lines are pieces of stripe to the detector (left to the workspace
    # crop; measured: 0-7 % of the centres, 23 % in one frame with two 50 px cables)
    near_refl = np.abs(sp.pixels_uv @ truth["n"] - truth["c_refl"]) < 3.0
    assert near_refl.sum() <= 2
    assert (~on_line).mean() < 0.25, (sp.pixels_uv[~on_line], sp.rejected)
    assert sp.rejected["second_line"] + sp.rejected["isolated"] > 0  # and counted
    assert np.all((sp.confidence > 0) & (sp.confidence <= 1))


def test_second_line_is_rejected_not_averaged():
    """A reflection as bright as 80 % of the stripe, parallel and over half of it: each
    of those lines keeps the stripe's centre, and counts the second line."""
    img, truth = _room_scene("red", 10.0, seed=3, reflection=0.8)
    sp = extract_stripe_centres(img, options=BASE)
    err = _line_errors(sp, truth)
    assert np.median(np.abs(err)) < 0.1 and (np.abs(err) < 0.5).mean() > 0.9
    near_refl = np.abs(sp.pixels_uv @ truth["n"] - truth["c_refl"]) < 3.0
    assert not near_refl.any()
    assert sp.rejected["second_line"] > 0.3 * len(sp)


def test_isolated_peaks_are_rejected():
    """Laser-coloured dots and short dashes alone in a frame: no stripe."""
    rng = np.random.default_rng(5)
    img = np.full((120, 160, 3), 90.0) + rng.normal(0, 1.5, (120, 160, 3))
    yy, xx = np.mgrid[0:120, 0:160]
    for cu, cv in np.stack(np.meshgrid(np.arange(15, 150, 20.0), np.arange(15, 110, 25.0)),
                           axis=-1).reshape(-1, 2) + rng.uniform(-4, 4, (28, 2)):
        img[..., 1] += 120.0 * np.exp(-0.5 * ((xx - cu) ** 2 + (yy - cv) ** 2) / 1.2 ** 2)
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    sp = extract_stripe_centres(img, options=BASE.replace(colour="green"))
    assert len(sp) == 0 and sp.rejected["isolated"] > 0
    # the same dots along a line, 3 px apart: a (dotted) stripe, kept
    line = img.copy().astype(np.float64)
    for cu in np.arange(10, 150, 3.0):
        line[..., 1] += 120.0 * np.exp(-0.5 * ((xx - cu) ** 2 + (yy - 60.4) ** 2) / 1.2 ** 2)
    sp = extract_stripe_centres(np.clip(np.rint(line), 0, 255).astype(np.uint8),
                                options=BASE.replace(colour="green"))
    assert len(sp) > 100 and np.median(np.abs(sp.v - 60.4)) < 0.1


def test_white_and_coloured_surfaces_are_not_the_laser():
    """Without a laser, a cluttered room-lit frame (white lines, grey joints between red
    tiles, coloured cables) gives no stripe in any laser colour."""
    img, _ = _room_scene("green", 0.0, seed=9, amp=0.0, reflection=0.0)
    tiles = img.copy()
    tiles[:, :, 0], tiles[:, :, 1], tiles[:, :, 2] = 170, 80, 60  # red tiles ...
    tiles[::20] = (200, 190, 180)  # ... with light grey joints every 20 rows
    tiles[1::20] = (200, 190, 180)
    for colour in ("red", "green", "blue"):
        for frame in (tiles,):
            sp = extract_stripe_centres(frame, options=BASE.replace(colour=colour))
            assert len(sp) == 0, (colour, len(sp))


def test_a_line_where_one_channel_falls_is_not_the_laser():
    """A laser only adds light. On an orange surface under a blue laser the stripe may be
    invisible; a grey edge line there rises in blue and green but falls in red (random
    scene 144: red -8, green +5, blue +16 levels, taken as 28 centres 4-24 mm off the
    surface until the fall came off the height). It is no stripe; a faint blue stripe
    that adds light in every channel on the same surface is one."""
    rng = np.random.default_rng(11)
    h, w = 120, 160
    yy, xx = np.mgrid[0:h, 0:w]
    orange = np.array([86.0, 38.0, 5.0])
    base = np.broadcast_to(orange, (h, w, 3)).copy()
    prof = np.exp(-0.5 * ((yy - 60.3) / 0.9) ** 2)[..., None]
    edge = base + prof * np.array([-9.0, 8.0, 20.0])  # a grey line: red falls
    stripe = base + prof * np.array([3.0, 3.0, 20.0])  # added blue light
    opts = BASE.replace(colour="blue")
    for img, want in ((edge, False), (stripe, True)):
        img = np.clip(np.rint(img + rng.normal(0.0, 1.0, img.shape)), 0, 255).astype(np.uint8)
        sp = extract_stripe_centres(img, options=opts)
        if want:
            assert len(sp) > 0.9 * w - 20 and np.median(np.abs(sp.v - 60.3)) < 0.15
        else:
            assert len(sp) == 0, len(sp)


def test_laser_colour_of_a_recording():
    frames = [_room_scene("blue", a, seed=i)[0] for i, a in enumerate((0.0, 60.0, 100.0))]
    colour, scores = estimate_laser_colour(frames)
    assert colour == "blue" and scores["blue"] > scores["red"]
    grey = [np.repeat(f.mean(axis=2, keepdims=True).astype(np.uint8), 3, axis=2)
            for f in frames]
    assert estimate_laser_colour(grey)[0] == "lightness"
    assert estimate_laser_colour([f[..., 2] for f in frames])[0] == "lightness"


# The cost of a busy frame against a clean one is a speed figure: benchmarks/laser.py
# (ambient_speed, "busy_over_clean") measures it; tests do not assert times.


# ---------------------------------------------------------------------------- region
def _with_ridge(img: np.ndarray, v0: float, rgb: tuple[float, float, float],
                amp: float, sigma: float = 1.4) -> np.ndarray:
    """``img`` with a horizontal ridge of colour ``rgb`` along row ``v0`` over the whole
    width (an object's lit rim, the line on the wall)."""
    h = img.shape[0]
    prof = amp * np.exp(-0.5 * ((np.arange(h) - v0) / sigma) ** 2)
    out = img.astype(np.float64) + prof[:, None, None] * np.asarray(rgb)[None, None, :]
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _band_roi(truth: dict, h: int, w: int, half: float, u0: int, u1: int) -> np.ndarray:
    """The convex region within ``half`` px of the true line, columns u0..u1-1 (what the
    laser sheet inside a workspace box projects to, grown by a margin)."""
    yy, xx = np.mgrid[0:h, 0:w]
    d = xx * truth["n"][0] + yy * truth["n"][1] - truth["c"]
    return (np.abs(d) <= half) & (xx >= u0) & (xx < u1)


def test_region_of_interest_keeps_the_stripe_and_ignores_a_stronger_ridge_outside():
    """A green laser line in room light and, 80 px above it, a brighter ridge of the
    laser's colour over the whole width (longer than the stripe): on the whole image the
    ridge wins; searched only in the sheet's band, the stripe is found (sub-pixel, every
    line of the band) and nothing on the ridge; the lines off the band are counted."""
    img, truth = _room_scene("green", 8.0, seed=21)
    h, w = img.shape[:2]
    v_ridge = 40.0
    img = _with_ridge(img, v_ridge, (0.1, 1.0, 0.1), 230.0)
    roi = _band_roi(truth, h, w, 30.0, 24, w - 16)
    plain = extract_stripe_centres(img, options=BASE.replace(colour="green"))
    on_ridge = np.abs(plain.v - v_ridge) < 2.0
    assert on_ridge.mean() > 0.8, on_ridge.mean()  # the test can fail without the region
    sp = extract_stripe_centres(img, roi=roi, options=BASE.replace(colour="green"))
    assert sp.axis == "columns"
    err = _line_errors(sp, truth)
    on_line = np.abs(err) < 1.0
    assert on_line.mean() > 0.95, sp.rejected
    assert np.median(np.abs(err[on_line])) < 0.1
    assert not (np.abs(sp.v - v_ridge) < 5.0).any()
    lines = _visible_lines(truth, "columns", h, w)
    lines = lines[(lines >= 24) & (lines < w - 16)]
    assert np.isin(lines, sp.line[on_line]).mean() >= 0.95
    assert sp.rejected["outside_roi"] == 24 + 16
    # the whole image as the region: as without one
    full = extract_stripe_centres(img, roi=np.ones((h, w), bool),
                                  options=BASE.replace(colour="green"))
    np.testing.assert_array_equal(full.v, plain.v)
    assert full.rejected["outside_roi"] == 0
    with pytest.raises(ValueError, match="roi"):
        extract_stripe_centres(img, roi=roi[:-1], options=BASE)


def test_laser_colour_votes_only_inside_the_region():
    """Green laser frames with an orange object's lit rim (a long red ridge, brighter
    than the stripe) outside the sheet's band: the whole frames vote red, the bands
    green."""
    frames, rois = [], []
    for i, a in enumerate((0.0, 12.0, -10.0)):
        img, truth = _room_scene("green", a, seed=30 + i, reflection=0.0)
        h, w = img.shape[:2]
        frames.append(_with_ridge(img, 30.0 + 5 * i, (1.0, 0.35, 0.05), 200.0))
        rois.append(_band_roi(truth, h, w, 30.0, 0, w))
    assert estimate_laser_colour(frames)[0] == "red"
    colour, scores = estimate_laser_colour(frames, rois=rois)
    assert colour == "green" and scores["green"] > 2 * scores["red"], scores


def _look_down_rig() -> tuple:
    """A camera 0.3 m above a 60 mm box looking down, a laser 80 mm beside it whose
    sheet crosses the box (mild lens distortion)."""
    from robo3d.camera import CameraModel

    cam = CameraModel("camera", 320, 240, np.array([[300.0, 0, 159.5], [0, 300.0, 119.5],
                                                    [0, 0, 1]]),
                      np.array([-0.08, 0.02, 0.0005, -0.0003, 0.0]))
    T_bc = np.eye(4)
    T_bc[:3, :3] = np.diag([1.0, -1.0, -1.0])  # optical axis down
    T_bc[:3, 3] = (0.004, -0.002, 0.3)
    z_l = np.array([0.0, -0.08, 0.3]) / np.hypot(0.08, 0.3)
    x_l = np.array([1.0, 0.0, 0.0])
    T_cl = np.eye(4)
    T_cl[:3, :3] = np.column_stack([x_l, np.cross(z_l, x_l), z_l])
    T_cl[:3, 3] = (0.0, 0.08, 0.0)
    box = (np.array([-0.03, -0.03, 0.0]), np.array([0.03, 0.03, 0.06]))
    return cam, T_bc, T_cl, box


def test_sheet_inside_the_workspace_and_its_image_region():
    """The sheet-box polygon lies on the sheet and in the box; its image region (grown
    by the margin) holds the projection of every sheet point inside the box and none of
    the sheet points that project farther than the margin from it."""
    from scipy.spatial import cKDTree

    from robo3d.camera import project_points
    from robo3d.triangulation import sheet_in_workspace, sheet_roi_mask

    cam, T_bc, T_cl, box = _look_down_rig()
    poly = sheet_in_workspace(T_bc, T_cl, box)
    assert 3 <= len(poly) <= 6
    in_laser = (poly - T_cl[:3, 3]) @ T_cl[:3, :3]
    np.testing.assert_allclose(in_laser[:, 1], 0.0, atol=1e-12)
    in_base = poly @ T_bc[:3, :3].T + T_bc[:3, 3]
    assert np.all((in_base >= box[0] - 1e-9) & (in_base <= box[1] + 1e-9))
    margin = 3.0
    roi = sheet_roi_mask(cam, poly, margin)
    assert roi.shape == (240, 320) and 0.02 < roi.mean() < 0.8
    # points of the sheet (laser x-z plane), in the box and around it
    rng = np.random.default_rng(0)
    xz = rng.uniform([-0.1, 0.1], [0.1, 0.45], (100_000, 2))
    p_l = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
    p_b = (p_l @ T_cl[:3, :3].T + T_cl[:3, 3]) @ T_bc[:3, :3].T + T_bc[:3, 3]
    uv, front = project_points(p_b, cam, T_bc)
    seen = front & np.all((uv >= 0) & (uv <= [319, 239]), axis=1)
    inside = np.all((p_b >= box[0]) & (p_b <= box[1]), axis=1)
    px = np.rint(uv).astype(int)
    assert (seen & inside).sum() > 500
    assert roi[px[seen & inside, 1], px[seen & inside, 0]].all()
    # outside: farther than the margin (+ rounding) from the in-box points' image
    far = cKDTree(uv[seen & inside]).query(uv[seen & ~inside])[0] > margin + 2.0
    assert far.sum() > 500
    out_px = px[seen & ~inside][far]
    assert not roi[out_px[:, 1], out_px[:, 0]].any()
    # a sheet that misses the box: no polygon, no region (the caller searches everywhere)
    T_far = T_cl.copy()
    T_far[:3, 3] = (0.0, 0.6, 0.0)
    assert len(sheet_in_workspace(T_bc, T_far, box)) == 0
    assert sheet_roi_mask(cam, sheet_in_workspace(T_bc, T_far, box), margin) is None


def test_a_ridge_where_the_other_channels_fall_is_no_laser_light():
    """A thin line brighter in red only while green and blue fall (a JPEG edge's
    ringing, an orange object's dark rim) is no red laser; the same red rise with green
    and blue rising a little (a laser's light in the overlapping filters) is."""
    rng = np.random.default_rng(4)
    h, w = 80, 120
    prof = np.exp(-0.5 * ((np.arange(h) - 40.3) / 1.4) ** 2)[:, None, None]
    base = np.full((h, w, 3), 100.0) + rng.normal(0, 1.0, (h, w, 3))
    for others, found in ((-12.0, False), (4.0, True)):
        img = base + prof * np.array([40.0, others, others])
        sp = extract_stripe_centres(np.clip(np.rint(img), 0, 255).astype(np.uint8),
                                    options=BASE.replace(colour="red"))
        if found:
            assert len(sp) > 0.9 * w - 20 and np.median(np.abs(sp.v - 40.3)) < 0.1
        else:
            assert len(sp) == 0, len(sp)


def test_stripes_artefact_round_trip_and_damage(tmp_path):
    """stripes.npz as the stage writes it (robo3d.artefacts.Stripes): read back array for
    array; a file without the centres, or with offsets that do not fit, names itself."""
    from robo3d.artefacts import ArtefactError, Stripes
    from robo3d.camera import CameraModel

    frames = [_stripe_image(_centres(), sigma=1.6), np.zeros((H, W), np.uint8)]
    found = [extract_stripe_centres(f, options=BASE) for f in frames]
    assert len(found[0]) > 0.9 * W and len(found[1]) == 0
    cam = CameraModel("camera", W, H, np.array([[100.0, 0, W / 2], [0, 100.0, H / 2],
                                                 [0, 0, 1]]))
    poses = np.stack([np.eye(4), np.eye(4)])
    box = (np.zeros(3), np.ones(3))
    art = Stripes.from_frames(found, [5, 7], poses, poses, [cam, cam], box)
    assert list(art.counts) == [len(found[0]), 0]
    art.save(tmp_path / "stripes.npz")
    back = Stripes.load(tmp_path / "stripes.npz")
    a, b = art.as_arrays(), back.as_arrays()
    assert list(a) == list(b) and "skew_px" in b
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].tobytes() == b[k].tobytes(), k
    assert [(c.frame_id, c.width, c.height) for c in back.cameras] == [("camera", W, H)] * 2
    assert np.array_equal(back.cameras[1].K, cam.K) and back.workspace[1].tolist() == [1] * 3
    assert np.array_equal(back.v[: len(found[0])], found[0].v)
    no_u = {k: v for k, v in a.items() if k != "u"}
    np.savez(tmp_path / "bad.npz", **no_u)
    with pytest.raises(ArtefactError, match=r"bad\.npz: no u"):
        Stripes.load(tmp_path / "bad.npz")
    np.savez(tmp_path / "short.npz", **{**a, "offsets": a["offsets"][:-1]})
    with pytest.raises(ArtefactError, match="offsets"):
        Stripes.load(tmp_path / "short.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ArtefactError, match=r"junk\.npz: not a readable stripes\.npz"):
        Stripes.load(tmp_path / "junk.npz")


def test_auto_axis_takes_the_consistent_axis_for_a_u_shaped_stripe():
    """The laser's arc inside a cup is a U: its steep arms make the probe's strongest
    curve along the rows, where every row crosses the stripe twice (simulated cup/4,
    frames 389-390: 6-7 centres, 130 lines rejected as two blobs or a second line). The
    other axis crosses it once per column: auto searches it too and keeps it."""
    from scipy.spatial import cKDTree

    h, w, a, half = 480, 640, 0.012, 150.0
    us = np.linspace(320 - half, 320 + half, 20000)
    vs = 400 - a * (us - 320) ** 2
    gain = 1 + np.clip(np.abs(2 * a * (us - 320)) / 3, 0, 1)  # the steep arms brighter
    pix = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2)
    d, j = cKDTree(np.c_[us, vs]).query(pix, distance_upper_bound=6)
    val = np.zeros(len(pix))
    m = np.isfinite(d)
    val[m] = 60 * gain[j[m]] * np.exp(-0.5 * (d[m] / 1.2) ** 2)
    img = (np.random.default_rng(0).normal(20, 2, (h, w)) + val.reshape(h, w))
    img = img.clip(0, 255).astype(np.uint8)
    opts = StripeOptions(colour="lightness")
    rows = extract_stripe_centres(img, options=opts.replace(axis="rows"))
    assert len(rows.u) < 20 and rows.rejected["two_blobs"] > 200  # the probe's choice
    sp = extract_stripe_centres(img, options=opts)
    assert sp.axis == "columns" and len(sp.u) > 0.85 * 2 * half
    truth_v = 400 - a * (sp.u - 320) ** 2
    assert np.median(np.abs(sp.v - truth_v)) < 0.2


def _line_of_changing_width(seed: int) -> np.ndarray:
    """A green line down a room-lit scene, its width changing from row to row (every
    other row's profile needs the detector's wide window, the next one's does not), a
    surface edge 14 px right of it (the background steps down)."""
    rng = np.random.default_rng(seed)
    h, w = 160, 200
    rows = np.arange(h)[:, None]
    cols = np.arange(w)[None, :]
    uc = 80 + 0.15 * rows + 3 * np.sin(rows / 9.0)
    sigma = np.where(rows % 2 == 0, 3.5, 1.2) + rng.uniform(0, 0.4, (h, 1))
    bg = 90 + 0.2 * cols - 60 * (cols > uc + 14) + rng.normal(0, 3, (h, w))
    line = rng.uniform(40, 120, (h, 1)) * np.exp(-0.5 * ((cols - uc) / sigma) ** 2)
    img = np.stack([bg + 0.2 * line, bg + line, bg + 0.25 * line], -1)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("centre_on", ["laser", "luma"])
def test_a_line_centre_does_not_depend_on_the_line_before(centre_on):
    """Each line's centre comes from its own profile only: the frame upside down gives
    the same centres on the same rows. (The right side's baseline walk once read past
    its window into what the line before had left in the shared buffer: up to 1 px.)"""
    o = StripeOptions(colour="green", axis="rows", centre_on=centre_on)
    for seed in range(3):
        img = _line_of_changing_width(seed)
        a = extract_stripe_centres(img, options=o)
        b = extract_stripe_centres(np.ascontiguousarray(img[::-1]), options=o)
        assert a.u.size == b.u.size >= 150
        ia, ib = np.argsort(a.v), np.argsort(-b.v)
        np.testing.assert_array_equal(a.v[ia], img.shape[0] - 1 - b.v[ib])
        np.testing.assert_array_equal(a.u[ia], b.u[ib])
