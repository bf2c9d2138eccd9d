"""Stripe centres on JPEG frames whose colour is stored at half resolution (4:2:0).

A red or blue laser lives mostly in a JPEG's chroma, which the encoder keeps on a 2-pixel
grid and the decoder interpolates: the laser channel's centre then moves with the
stripe's phase on that grid. The luma is stored at full resolution; ``centre_on="luma"``
takes the centre there. The truth is the stripe drawn (its exact sub-pixel rows).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from robo3d.recording.images import chroma_subsampled
from robo3d.stripes import StripeOptions, centre_on_for, extract_stripe_centres

H, W = 160, 320
#: The simulator's sensor responses of a red and a blue laser (LASER_RGB).
LASERS = {"red": (1.0, 0.12, 0.06), "blue": (0.10, 0.38, 1.0)}
#: The stripe detector as :func:`extract_stripe_centres` defaulted to before its options:
#: ``min_peak`` at 4 % of the full scale.
BASE = StripeOptions(min_peak=None)


def _jpeg(rgb: np.ndarray, sampling: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, 80, cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                            sampling])
    assert ok
    return buf.tobytes()


def _frame(colour: str, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A room-lit grey-blue surface and a laser line sloping through every phase."""
    rng = np.random.default_rng(seed)
    u = np.arange(W)
    vc = 60.0 + 0.013 * u + 3.0 * np.sin(u / 45.0)  # ~4 px drift: all phases mod 2
    rows = np.arange(H, dtype=np.float64)[:, None]
    g = np.exp(-2.0 * ((rows - vc[None]) / 2.6) ** 2)  # 1/e^2 half-width 2.6 px
    room = np.array([70.0, 80.0, 95.0]) * (1.0 + 0.1 * np.sin(u / 23.0))[None, :, None]
    img = room * np.ones((H, W, 1)) + 150.0 * g[..., None] * np.array(LASERS[colour])
    img += rng.normal(0.0, 1.5, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), vc


def test_chroma_subsampling_is_read_from_the_jpeg_header():
    rgb = _frame("blue")[0]
    assert chroma_subsampled(_jpeg(rgb, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420))
    assert chroma_subsampled(_jpeg(rgb, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422))
    assert not chroma_subsampled(_jpeg(rgb, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444))
    assert not chroma_subsampled(cv2.imencode(".jpg", rgb[..., 0])[1].tobytes())  # grey
    assert not chroma_subsampled(cv2.imencode(".png", rgb)[1].tobytes())
    assert not chroma_subsampled(b"\xff\xd8\xff")  # truncated: no frame header
    assert not chroma_subsampled(b"")
    assert centre_on_for("auto", _jpeg(rgb, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420)) == "luma"
    assert centre_on_for("auto", cv2.imencode(".png", rgb)[1].tobytes()) == "laser"
    assert centre_on_for("auto", None) == "laser"
    assert centre_on_for("laser", _jpeg(rgb, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420)) == "laser"


@pytest.mark.parametrize("colour", ["red", "blue"])
def test_luma_centre_removes_the_chroma_grid_bias(colour):
    rgb, vc = _frame(colour)
    jpg = cv2.cvtColor(cv2.imdecode(np.frombuffer(
        _jpeg(rgb, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420), np.uint8), cv2.IMREAD_COLOR),
        cv2.COLOR_BGR2RGB)
    err = {}
    for mode in ("laser", "luma"):
        sp = extract_stripe_centres(jpg, options=BASE.replace(colour=colour, axis="columns",
                                                              centre_on=mode))
        assert sp.axis == "columns" and sp.colour == colour
        assert len(sp) >= 0.95 * W
        err[mode] = np.abs(sp.v - vc[sp.line])
    # measured (median, p95): red 0.051, 0.158 -> 0.023, 0.065 px; blue 0.072, 0.198 ->
    # 0.022, 0.066 px; the lossless frame 0.012 px
    assert np.median(err["luma"]) < 0.035
    assert np.median(err["luma"]) < 0.6 * np.median(err["laser"])
    assert np.percentile(err["luma"], 95) < np.percentile(err["laser"], 95)
    # on the lossless frame both profiles are unbiased: luma changes nothing much
    sp = extract_stripe_centres(rgb, options=BASE.replace(colour=colour, axis="columns",
                                                          centre_on="laser"))
    assert np.median(np.abs(sp.v - vc[sp.line])) < 0.02


def test_centre_on_is_checked():
    with pytest.raises(ValueError, match="centre_on"):
        extract_stripe_centres(np.zeros((8, 8, 3), np.uint8),
                               options=BASE.replace(centre_on="chroma"))
