"""The ridge detector's hysteresis (robo3d.stripes, step 3b): a kept curve goes on where
the stripe's colour is lost (a JPEG's half-resolution chroma on an object of the laser's
own colour) but not onto grey or white things beside it."""

from __future__ import annotations

import numpy as np
import pytest

from robo3d.stripes import StripeOptions, extract_stripe_centres

H, W = 90, 200
OPTS = StripeOptions(colour="green", axis="columns", centre_on="laser", follow=True)


def _scene(tail: str, seed: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A green laser stripe along a gentle curve on a green object (columns 0-199);
    from column 110 on the stripe has lost its colour (all three channels rise alike,
    as a thin stripe in a 4:2:0 JPEG). ``tail``: "object" (the tail on the green
    object), "wall" (the tail's columns are a grey wall: the rise there is a white line,
    no laser). Returns the uint8 image and the true centre row of every column."""
    rng = np.random.default_rng(seed)
    u = np.arange(W, dtype=np.float64)
    vc = 45.3 + 8.0 * np.sin(u / 60.0)
    prof = np.exp(-0.5 * ((np.arange(H)[:, None] - vc[None, :]) / 1.3) ** 2)
    img = np.empty((H, W, 3))
    img[:] = (22.0, 56.0, 26.0)  # the green object in room light
    tail_cols = u >= 110
    if tail == "wall":
        img[:, tail_cols] = (100.0, 100.0, 100.0)
    coloured = prof * ~tail_cols
    grey = prof * tail_cols
    img += coloured[..., None] * np.array([6.0, 40.0, 8.0])  # the laser's own colour
    img += grey[..., None] * np.array([50.0, 50.0, 50.0])  # its colour lost: luma only
    img += rng.normal(0.0, 1.5, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), vc


def test_a_curve_goes_on_where_the_stripe_loses_its_colour():
    img, vc = _scene("object")
    sp = extract_stripe_centres(img, options=OPTS)
    lines = sp.line.astype(int)
    err = np.abs(sp.v - vc[lines])
    assert np.all(err < 0.5), err.max()
    head = (lines >= 10) & (lines < 105)
    tail = (lines >= 115) & (lines < W - 10)
    assert head.sum() >= 90
    # the colourless tail is the curve's continuation: found and centred
    assert tail.sum() >= 0.95 * (W - 10 - 115), tail.sum()
    assert np.median(err[tail]) < 0.1
    # the same tail alone (no coloured curve to continue) is no laser: nothing
    alone = img.copy()
    alone[:, :110] = (22, 56, 26)
    assert len(extract_stripe_centres(alone, options=OPTS)) == 0
    # the continuation's heights are read the same way in 16 bits (the generic kernels)
    wide = extract_stripe_centres(img.astype(np.uint16) * 257,
                                  options=OPTS.replace(min_peak=8.0 * 257))
    np.testing.assert_array_equal(wide.line, sp.line)
    np.testing.assert_allclose(wide.v, sp.v, atol=1e-6)


def test_a_curve_is_not_continued_onto_a_white_line_on_a_grey_wall():
    img, vc = _scene("wall")
    sp = extract_stripe_centres(img, options=OPTS)
    assert sp.line.max() < 112, sp.line.max()  # it stops at the wall
    assert np.all(np.abs(sp.v - vc[sp.line.astype(int)]) < 0.5)


@pytest.mark.parametrize("overshoot", [10.0, 28.0])
def test_a_curve_is_not_continued_along_an_edge_s_ringing(overshoot):
    """The stripe ends where a green object meets a bright green wall above it; a JPEG's
    ringing leaves a thin overshoot on the wall's side of the edge: not followed."""
    rng = np.random.default_rng(3)
    img = np.empty((H, W, 3))
    img[:] = (22.0, 56.0, 26.0)
    edge = 40
    img[:edge, 100:] = (80.0, 190.0, 90.0)  # the brighter wall (of the laser's colour)
    img[edge - 1, 100:] += overshoot  # the ringing's overshoot on the edge's bright side
    u = np.arange(W, dtype=np.float64)
    vc = np.full(W, edge - 1.0)
    prof = np.exp(-0.5 * ((np.arange(H)[:, None] - vc[None, :]) / 1.3) ** 2) * (u < 100)
    img += prof[..., None] * np.array([6.0, 40.0, 8.0])
    img += rng.normal(0.0, 1.5, img.shape)
    img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    sp = extract_stripe_centres(img, options=OPTS)
    assert len(sp) > 70 and sp.line.max() < 102, sp.line.max()
