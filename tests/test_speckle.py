"""Laser speckle, simulated (robo3d.sim.render.speckle_gain) and measured against the stripe
detector: an error our algorithms do not model (a laser's coherent light on a rough surface
makes the stripe grainy and moves its centre of gravity), which real cells record."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from robo3d.config import default_config
from robo3d.recording.reader import read_recording
from robo3d.sim.render import speckle_gain
from robo3d.simulate import (
    SimulationParams,
    image_poses,
    simulate_recording,
    stripe_truth,
    truth_scene,
)
from robo3d.stripes import StripeOptions, extract_stripe_centres


def _lag1(g: np.ndarray) -> float:
    """Correlation of neighbouring pixels' values (along the rows)."""
    a, b = g[:, :-1].ravel() - g.mean(), g[:, 1:].ravel() - g.mean()
    return float(np.mean(a * b) / np.mean(a * a))


@pytest.mark.parametrize("contrast", [0.3, 0.6, 1.0])
def test_speckle_has_the_asked_contrast_and_grain(contrast):
    g = speckle_gain(240, 320, contrast, 2.0, np.random.default_rng(1))
    assert g.min() >= 0.0
    assert abs(g.mean() - 1.0) < 0.03
    assert abs(g.std() / contrast - 1.0) < 0.15, g.std()
    assert _lag1(g) > 0.4  # grains of about 2 px: neighbours alike
    fine = speckle_gain(240, 320, contrast, 0.5, np.random.default_rng(1))
    assert _lag1(fine) < 0.3  # grains smaller than a pixel: neighbours independent
    again = speckle_gain(240, 320, contrast, 2.0, np.random.default_rng(1))
    np.testing.assert_array_equal(g, again)  # from its generator alone
    np.testing.assert_array_equal(speckle_gain(4, 5, 0.0, 2.0, np.random.default_rng(1)),
                                  np.ones((4, 5)))


def _errors(path) -> tuple[np.ndarray, int]:
    """Each detected centre's distance to the true stripe (px), over all laser frames of a
    recording (the pipeline's stripe options, its laser colour), and how many lie within
    1 px of the stripe on the object."""
    rec = read_recording(path, roles=("laser",))
    scene, poses = truth_scene(rec), image_poses(rec)
    opts = StripeOptions.from_config(default_config()["stripes"]).replace(colour="green")
    frames = sorted(rec.laser_frames, key=lambda m: m.timestamp_ns)
    dist, on_object = [], 0
    for k, msg in enumerate(frames):
        sp = extract_stripe_centres(msg.decode(), options=opts)
        tr = stripe_truth(rec, k, scene=scene, poses=poses)
        if not len(sp.u) or not len(tr.pixels_uv):
            continue
        d, i = cKDTree(tr.pixels_uv).query(np.column_stack([sp.u, sp.v]))
        dist.append(d)
        on_object += int(np.sum((d <= 1.0) & tr.on_object[i]))
    return np.concatenate(dist), on_object


#: A grey bump under a green laser in room light, JPEG, exact poses: 12 frames, 320 x 240.
_SCENE = dict(laser="green", object_color="grey", texture="none", width=320, height=240,
              views=0, sweeps=1, sweep_frames=12, seed=3, sweep_error_mm=(0.0, 0.0),
              sweep_error_deg=(0.0, 0.0))


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> tuple[np.ndarray, int]:
    path = tmp_path_factory.mktemp("speckle") / "clean.mcap"
    simulate_recording(path, "bumpy_blob", params=SimulationParams.cell(**_SCENE))
    return _errors(path)


@pytest.mark.parametrize(("contrast", "found", "median_px", "p95_px"), [
    (0.5, 0.90, 0.20, 0.8),  # a webcam's pixels and lens: partly averaged
    (1.0, 0.75, 0.30, 1.1),  # fully developed: a small aperture
])
def test_a_speckled_stripe_is_still_found_and_centred_to_a_fraction_of_a_pixel(
        tmp_path, clean, contrast, found, median_px, p95_px):
    """Speckle of 2-pixel grains: the centres scatter more, as the grains move them, but
    stay within a fraction of a pixel of the true stripe, and the stripe is found in most
    of the lines where it was found without speckle. Measured (benchmarks/README.md, stop
    63): the clean frames' centres 0.099 px from the truth at the median, 628 within 1 px
    on the object; contrast 0.5 0.136 px and 599; fully developed 0.198 px and 519 (the
    dark grains break the stripe into pieces shorter than ``stripes.min_run``)."""
    d0, n0 = clean
    path = tmp_path / "speckle.mcap"
    simulate_recording(path, "bumpy_blob", params=SimulationParams.cell(
        **_SCENE, laser_speckle=contrast, speckle_grain_px=2.0))
    meta = read_recording(path, roles=()).metadata["robo3d.simulation"]
    assert float(meta["laser_speckle"]) == contrast  # the recording says how it was made
    d1, n1 = _errors(path)
    assert n0 > 12 * 40  # the clean stripe: tens of centres on the object in every frame
    # the speckle is there, and it moves the centres ...
    assert np.median(d1) > np.median(d0) + 0.02, (np.median(d0), np.median(d1))
    # ... by a fraction of a pixel
    assert np.median(d1) < median_px, np.median(d1)
    assert np.percentile(d1, 95) < p95_px, np.percentile(d1, 95)
    assert np.mean(d1 > 2.0) < 0.03
    # and the stripe is found in most of the lines where it was without it
    assert n1 > found * n0, (n0, n1)
