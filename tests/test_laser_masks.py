"""Masks that the laser's points contradict, segmented again from where the laser measured
the object (:func:`robo3d.silhouettes.resegment_laser_contradicted`): a grey sphere on a
grey table printed with black dots, whose colour model failed in two views."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_align_hull import ring_cameras  # noqa: E402

from robo3d.camera import pixel_rays  # noqa: E402
from robo3d.silhouettes import laser_cover, resegment_laser_contradicted  # noqa: E402

CENTRE, RADIUS = np.array([0.0, 0.0, 0.04]), 0.04


def _scene(n: int = 6):
    """Cameras around a grey sphere on a grey dotted table: the cameras, their poses, the
    true masks and the images (shaded sphere, the table's grey with black dots, noise)."""
    cam, Ts = ring_cameras(n, CENTRE, rise=0.7)
    v, u = np.mgrid[0:cam.height, 0:cam.width]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    light = np.array([0.3, -0.4, 0.87]) / np.linalg.norm([0.3, -0.4, 0.87])
    rng = np.random.default_rng(3)
    masks, images = [], []
    for T in Ts:
        o, d = pixel_rays(uv, cam, T)
        oc = o - CENTRE
        b = d @ oc
        disc = b * b - (oc @ oc - RADIUS**2)
        hit = disc >= 0
        t = -b - np.sqrt(np.where(hit, disc, 0))
        n_ = (o + t[:, None] * d - CENTRE) / RADIUS
        shade = 70 + 120 * np.clip(n_ @ light, 0, 1)
        # the table (z = 0) where the ray meets it: grey with black dots 6 mm apart
        tz = -o[2] / np.where(np.abs(d[:, 2]) > 1e-9, d[:, 2], -1e-9)
        p = o + tz[:, None] * d
        dots = np.hypot((p[:, 0] % 0.006) - 0.003, (p[:, 1] % 0.006) - 0.003) < 0.0012
        table = np.where(dots, 25.0, 128.0)
        img = np.where(hit, shade, table).reshape(cam.height, cam.width)
        img = np.clip(np.rint(img + rng.normal(0, 3, img.shape)), 0, 255).astype(np.uint8)
        masks.append(hit.reshape(cam.height, cam.width))
        images.append(np.repeat(img[..., None], 3, axis=2))
    return cam, Ts, masks, images


def _profiles(spacing: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """Laser profiles over the sphere as sensors above it see it (down to 54 degrees below
    its equator): planes x = const ``spacing`` apart, each a frame; points 0.5 mm apart
    along them."""
    pts, frames = [], []
    for k, x in enumerate(np.arange(-0.9 * RADIUS, 0.9 * RADIUS, spacing)):
        r = np.sqrt(RADIUS**2 - x**2)
        a = np.arange(-0.3 * np.pi, 1.3 * np.pi, 0.0005 / r)
        pts.append(CENTRE + np.stack([np.full_like(a, x), r * np.cos(a), r * np.sin(a)], 1))
        frames.append(np.full(len(a), k))
    return np.concatenate(pts), np.concatenate(frames)


def _iou(a, b):
    return np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1)


def test_views_the_laser_contradicts_are_segmented_again_from_its_points():
    cam, Ts, truth, images = _scene()
    points, frames = _profiles()
    masks = [m.copy() for m in truth]
    masks[1][:] = False  # the colour model failed: an empty mask
    masks[2] = (images[2][..., 0] > 165) & truth[2]  # and here it took the lit cap alone
    assert _iou(masks[2], truth[2]) < 0.5
    new, rep = resegment_laser_contradicted(masks, [cam] * len(Ts), Ts, points, frames,
                                            lambda v: images[v], [None] * len(Ts))
    assert sorted(new) == [1, 2]
    for v in (1, 2):
        c = rep["candidates"][v]
        assert c["accepted"] and c["outside_before"] > 0.5 and c["outside_after"] < 0.05
        assert _iou(new[v], truth[v]) > 0.93, (v, _iou(new[v], truth[v]))
    # the right masks leave (almost) no point outside and are not touched
    assert all(rep["outside"][v] < 0.02 for v in (0, 3, 4, 5))
    assert set(rep["candidates"]) == {1, 2}


def test_laser_cover_bridges_the_gap_between_profiles():
    """Profiles drawn as lines ``gap`` pixels apart across a 60 x 40 px patch: the disc
    bridges them, and the cover is the patch, not more."""
    for gap, radius_expected in ((3, 3), (8, 5), (14, 8)):
        rows = np.arange(20, 60 + 1, gap)
        u = np.arange(30, 90 + 1)
        px = np.stack([np.tile(u, len(rows)), np.repeat(rows, len(u))], 1)
        frames = np.repeat(np.arange(len(rows)), len(u))
        cover, radius = laser_cover(px, frames, (100, 120))
        assert radius == radius_expected
        patch = np.zeros((100, 120), bool)
        patch[rows[0]:rows[-1] + 1, 30:91] = True
        # all of it but its corners, rounded
        assert np.count_nonzero(cover & patch) >= 0.9 * np.count_nonzero(patch)
        assert np.count_nonzero(cover & ~patch) == 0
    cover, radius = laser_cover(np.zeros((0, 2), np.int64), np.zeros(0), (10, 10))
    assert not cover.any() and radius == 0


def test_right_masks_stay_when_the_laser_measured_something_else():
    """The laser's points in the wrong place (a stripe read off a marker's edge: a small
    patch beside the sphere) leave the right masks' view of them outside; the region they
    cover is far smaller than the mask, so no mask is replaced by it."""
    cam, Ts, truth, images = _scene()
    y, z = np.meshgrid(np.arange(-0.006, 0.006, 0.0005), np.arange(0.004, 0.014, 0.0005))
    patch = np.stack([np.full(y.size, 0.065), y.ravel(), z.ravel()], 1)
    frames = np.repeat(np.arange(z.shape[0]), z.shape[1])
    new, rep = resegment_laser_contradicted(truth, [cam] * len(Ts), Ts, patch, frames,
                                            lambda v: images[v], [None] * len(Ts))
    assert new == {}
    # seen beside the sphere in most views (in front of it or behind it in the others)
    assert sum(o is not None and o > 0.9 for o in rep["outside"]) >= 3
    assert all(not c["accepted"] and c["area_ratio"] < 0.5 for c in rep["candidates"].values())


def test_masks_reaching_far_beyond_the_lasers_box_are_segmented_again_inside_it():
    """Without a workspace box, a mask that took the table around the sphere (most of it
    outside the box of what the laser measured) is segmented again inside that box and
    replaced; a right mask is not; a segmentation that fails keeps the first mask."""
    from robo3d.silhouettes import resegment_outside_box

    cam, Ts, truth, _ = _scene(4)
    box = (CENTRE - RADIUS - 0.004, CENTRE + RADIUS + 0.004)
    masks = [m.copy() for m in truth]
    masks[0][100:, :] = True  # the table's lower half taken for object
    masks[3][100:, :] = True
    calls = []

    def segment(v):
        calls.append(v)
        return None if v == 3 else truth[v]

    new, rep = resegment_outside_box(masks, [cam] * 4, Ts, box, segment)
    assert sorted(new) == [0] and calls == [0, 3]
    assert np.array_equal(new[0], truth[0])
    assert rep["outside"][0] > 0.5 and all(rep["outside"][v] < 0.01 for v in (1, 2))
    assert rep["candidates"][0]["accepted"] and rep["candidates"][0]["outside_after"] < 0.01
    assert not rep["candidates"][3]["accepted"] and rep["candidates"][3]["outside_after"] is None


def test_the_laser_seeds_the_views_that_failed_unless_most_did(tmp_path, monkeypatch):
    """The silhouettes stage on a small simulated scan (a sphere, six views, two sweeps)
    whose colour model is made to fail in some views: one failed view of six is segmented
    again from the laser's points (its mask then mostly the object's); four of six are more than
    half, and the laser does not make their masks (random scene 539 of stop 55: masks
    seeded from a black block's top alone, a hull through the block): the recording's
    silhouettes are given up, every mask empty, the scan goes on from the laser."""
    from stages_in_process import stage_outputs

    from robo3d.artefacts import Silhouettes
    from robo3d.config import default_config
    from robo3d.errors import StageError
    from robo3d.pipeline import stage_silhouettes, stage_stripes, stage_triangulate
    from robo3d.simulate import simulate_recording
    from robo3d.stages import silhouettes as stage_module

    rec = tmp_path / "sphere.mcap"
    simulate_recording(rec, "sphere", seed=7, width=160, height=120, views=6, sweeps=2,
                       sweep_frames=20)
    cfg = default_config()
    res = tmp_path / "res"
    (res / "reports").mkdir(parents=True)
    stage_stripes({"recording": str(rec)}, stage_outputs(res, "stripes", npz="stripes.npz"),
                  cfg, "sphere", threads=1)
    stage_triangulate({"stripes": str(res / "stripes.npz")},
                      stage_outputs(res, "triangulate", npz="clouds.npz", ply="clouds.ply"),
                      cfg, "sphere")
    segment_one = stage_module._segment_one

    def run(name: str, failing: set[int]) -> tuple[dict, list[np.ndarray]]:
        def one(path, rec_, i, *args):
            if i in failing:
                raise StageError(f"view {i}: silhouette is empty (made to fail)")
            return segment_one(path, rec_, i, *args)

        monkeypatch.setattr(stage_module, "_segment_one", one)
        out = stage_outputs(res, name, npz=f"{name}.npz")
        report = stage_silhouettes({"recording": str(rec), "clouds": str(res / "clouds.npz")},
                                   out, cfg, "sphere", has_laser=True)
        return report, list(Silhouettes.load(out["npz"]).masks)

    right, right_masks = run("right", set())
    assert right["silhouettes_failed"] is None and right["laser_seeded"]["checked"]
    assert not right["laser_seeded"]["candidates"]  # right masks are not touched
    one_failed, masks = run("one_failed", {1})
    assert one_failed["silhouettes_failed"] is None and one_failed["views_failed"] == []
    assert one_failed["laser_seeded"]["candidates"][1]["accepted"]
    # 0.78 against the colour model's own mask (two sweeps of 20 frames cover it sparsely)
    assert _iou(masks[1], right_masks[1]) > 0.7, _iou(masks[1], right_masks[1])
    most_failed, masks = run("most_failed", {0, 1, 2, 3})
    assert "4 of 6 views could not be segmented" in most_failed["silhouettes_failed"]
    assert most_failed["laser_seeded"]["checked"] is False
    assert not any(m.any() for m in masks)
    assert most_failed["views_failed"] == list(range(6))


def test_masks_inside_the_frame_are_not_cut_to_a_partial_laser_box():
    """The laser's box of the object is only what it measured (one sweep over a part of
    the object): a right mask that ends inside the frame is not segmented again inside
    it (random scene 542 of stop 55: a cup's masks cut to the sliver one sweep measured);
    a mask that runs out of the frame (the table taken for object) still is."""
    from robo3d.silhouettes import resegment_outside_box

    cam, Ts, truth, _ = _scene(4)
    assert not any(m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any()
                   for m in truth)
    sliver = (CENTRE + np.array([-0.01, -0.04, -0.01]), CENTRE + np.array([0.0, 0.04, 0.04]))
    calls = []

    def segment(v):
        calls.append(v)
        return truth[v] & (np.arange(truth[v].shape[1]) < 10)[None, :]

    masks = [m.copy() for m in truth]
    masks[2][100:, :] = True  # the table's lower half taken for object, out of the frame
    new, rep = resegment_outside_box(masks, [cam] * 4, Ts, sliver, segment)
    assert calls == [2] and 2 in rep["candidates"]
    assert sorted(rep["inside_frame"]) == [v for v in (0, 1, 3) if rep["outside"][v] > 0.1]
    assert len(rep["inside_frame"]) >= 2  # most right masks reach beyond the sliver
    assert all(v not in new for v in (0, 1, 3))
