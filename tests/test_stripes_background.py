"""Laser-off frames subtracted (seed §4.2's laser-on minus laser-off difference): the
difference keeps the frame's own type, so the detector's colour test and saturation level
are those of the camera's frames."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from stages_in_process import stage_outputs  # noqa: E402

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


@pytest.fixture(scope="module")
def off_cell(tmp_path_factory):
    """A small room-lit cell (red laser, grey sphere, printed dots on the table) seen by a
    monochrome camera, with a laser-off frame beside every laser frame
    (``SimulationParams.laser_off``)."""
    from robo3d.simulate import SimulationParams, simulate_recording

    path = tmp_path_factory.mktemp("laser_off") / "cell.mcap"
    params = SimulationParams.cell(laser="red", object_color="grey", texture="none",
                                   markers="dots", small=True, width=320, height=240,
                                   views=0, sweeps=1, sweep_frames=12,
                                   laser_encoding="mono8", laser_off=True)
    simulate_recording(path, "sphere", params=params)
    return path


def _stage(rec: Path, out: Path, laser_off_topic: str | None) -> tuple[dict, np.ndarray]:
    """The stripes stage with the default config (and ``laser_off_topic``): its report,
    and per centre its distance to the frame's true stripe (px)."""
    from scipy.spatial import cKDTree

    from robo3d.config import default_config
    from robo3d.pipeline import STAGES
    from robo3d.recording.reader import read_recording
    from robo3d.simulate import image_poses, stripe_truth, truth_scene

    cfg = default_config()
    cfg["stripes"]["laser_off_topic"] = laser_off_topic
    (out / "reports").mkdir(parents=True)
    outputs = stage_outputs(out, "stripes", npz="stripes.npz")
    report = STAGES["stripes"]({"recording": str(rec)}, outputs, cfg, "cell", threads=1)
    r = read_recording(rec, roles=("laser",))
    scene, poses = truth_scene(r), image_poses(r)
    with np.load(out / "stripes.npz") as z:
        u, v, off = z["u"], z["v"], z["offsets"]
    d = []
    for i in range(len(off) - 1):
        det = np.column_stack([u[off[i]:off[i + 1]], v[off[i]:off[i + 1]]])
        if len(det):
            truth = stripe_truth(r, i, scene=scene, poses=poses).pixels_uv
            d.append(cKDTree(truth).query(det)[0] if len(truth) else np.full(len(det), np.inf))
    return report, np.concatenate(d) if d else np.zeros(0)


def test_the_stage_subtracts_the_laser_off_frames_without_taking_their_noise(off_cell,
                                                                              tmp_path):
    """``stripes.laser_off_topic``: each laser frame less its laser-off frame. Measured
    on this cell: without the pedestal of :func:`robo3d.stripes._subtract_background`
    (the difference clipped at zero) 212 of 1105 centres lay more than 1 px off the true
    stripe, in the frames where it is short (noise ridges); with it none of 533. Without
    subtraction 707 of 712 lie on it: a second noisy frame costs the difference
    sqrt(2) in noise, and the region of interest already keeps the printed dots out."""
    from robo3d.simulate import LASER_OFF_TOPIC

    report, d_off = _stage(off_cell, tmp_path / "off", LASER_OFF_TOPIC)
    _, d_plain = _stage(off_cell, tmp_path / "plain", None)
    assert report["laser_off_frames"] == 12
    assert len(d_off) > 0.5 * len(d_plain) > 150
    assert np.mean(d_off <= 1.0) > 0.995, np.sort(d_off)[-10:]
    assert np.median(d_off) < 0.3


def test_a_missing_laser_off_topic_is_a_clear_error(off_cell, tmp_path):
    from robo3d.errors import Robo3dError

    with pytest.raises(Robo3dError, match=r"cell\.mcap.*laser_off_topic /camera/nothing"):
        _stage(off_cell, tmp_path / "missing", "/camera/nothing")


def test_a_laser_off_topic_of_other_images_is_a_clear_error(tmp_path):
    """A laser-off topic whose images are not the laser frames' (here the views: RGB
    beside a monochrome laser camera) is named with both shapes, before any work."""
    from robo3d.errors import StageError
    from robo3d.simulate import SimulationParams, simulate_recording

    path = tmp_path / "views.mcap"
    params = SimulationParams.cell(laser="red", object_color="grey", texture="none",
                                   markers="none", small=True, width=96, height=72,
                                   views=2, sweeps=1, sweep_frames=4,
                                   laser_encoding="mono8")
    simulate_recording(path, "sphere", params=params)
    with pytest.raises(StageError, match=r"views\.mcap: stripes\.laser_off_topic "
                       r"/camera/image: .* 96 x 72 3 channels uint8, .* 96 x 72 mono uint8"):
        _stage(path, tmp_path / "out", "/camera/image")
