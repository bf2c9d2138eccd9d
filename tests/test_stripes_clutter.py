"""The ridge detector against clutter of the laser's colour (robo3d.stripes, step 1): a
JPEG's chroma fringe along a colour edge is no stripe (it has no luma ridge)."""

from __future__ import annotations

import numpy as np

from robo3d.stripes import StripeOptions, extract_stripe_centres

H, W = 120, 240
BLUE_LASER = np.array([0.10, 0.38, 1.0])  # the simulator's blue laser on an RGB sensor


def _fringe_scene(fringe: float, seed: int = 4) -> tuple[np.ndarray, float]:
    """A white wall (rows < 40) over a blue object; the wall's row next to the edge
    carries the object's blue as a JPEG's half-resolution chroma leaves it (blue up by
    ``fringe``, green down so that the luma stays); a blue laser stripe at row 80.4 on
    the object's columns 120-239 only. Returns the uint8 image and the stripe's row."""
    rng = np.random.default_rng(seed)
    img = np.empty((H, W, 3))
    img[:40] = (100.0, 100.0, 92.0)
    img[40:] = (14.0, 30.0, 70.0)
    img[39] += (0.0, -fringe * 0.114 / 0.587, fringe)
    row = 80.4
    prof = np.exp(-0.5 * ((np.arange(H) - row) / 1.2) ** 2)
    img[:, 120:] += prof[:, None, None] * 45.0 * BLUE_LASER
    img += rng.normal(0.0, 1.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), row


def test_a_chroma_fringe_along_a_colour_edge_is_not_a_stripe():
    opts = StripeOptions(colour="blue", axis="columns", centre_on="laser")
    img, row = _fringe_scene(26.0)
    # the fringe is a ridge of the blue channel, higher than the blue rise of the others
    col = img[:, 60].astype(float)
    assert col[39, 2] - max(col[36, 2], col[42, 2]) > 20
    assert col[39, 2] - col[39, 0] > 8  # and of the laser's colour (blue over red)
    sp = extract_stripe_centres(img, options=opts)
    # nothing along the edge, in the columns without laser or with it
    assert not np.any(np.abs(sp.v - 39.0) < 3.0), np.unique(np.round(sp.v))
    # the stripe itself is found and centred in its columns
    lines = sp.line.astype(int)
    on = (lines >= 125) & (lines < W - 5)
    assert on.sum() >= 0.95 * (W - 5 - 125), on.sum()
    assert np.median(np.abs(sp.v[on] - row)) < 0.1
    assert not np.any(lines < 115)
    # a wall without the fringe: the same stripe, the same centres
    clean, _ = _fringe_scene(0.0)
    sc = extract_stripe_centres(clean, options=opts)
    np.testing.assert_array_equal(sc.line, sp.line)
    np.testing.assert_allclose(sc.v, sp.v, atol=0.02)

