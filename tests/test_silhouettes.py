"""Tests of robo3d.silhouettes: thresholding segmentation (seed §3.2) and the box ROI.

Ground truth: a disc rasterised at pixel centres, drawn bright on a dark, textured, noisy
background, with dark "holes" inside it (texture the segmentation must fill).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from robo3d.camera import CameraModel
from robo3d.errors import StageError
from robo3d.silhouettes import (
    SegmentOptions,
    Silhouette,
    _distortion_limit_r2,
    colour_difference,
    find_roi,
    refine_edges,
    refine_with_grabcut,
    roi_from_box,
    segment_silhouette,
    silhouette_qa,
    to_grey,
)
from robo3d.sim.rig import look_at
from robo3d.transforms import invert_transform

H, W = 160, 200
CX, CY, R = 110.3, 75.6, 40.0
HOLES = [(-15, -10, 6), (12, 5, 5), (0, 20, 4), (18, -18, 5)]
#: The segmentation without the pipeline's refinements and speck and hole rules: Otsu's
#: threshold, every hole filled (the seed's rule), specks under 50 px removed.
PLAIN = SegmentOptions(min_component_px=50, max_hole_fraction=1.0, grabcut=False,
                       edge_refine_px=0)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b) / np.count_nonzero(a | b))


def _disc(cx=CX, cy=CY, r=R) -> np.ndarray:
    v, u = np.mgrid[0:H, 0:W]
    return (u - cx) ** 2 + (v - cy) ** 2 <= r * r


def _scene(seed: int = 0, cx=CX, cy=CY) -> tuple[np.ndarray, np.ndarray]:
    """(image uint8, true disc mask): bright textured disc with dark holes."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(float)
    disc = _disc(cx, cy)
    bg = 60 + 15 * np.sin(u / 7.0) * np.cos(v / 11.0) + rng.normal(0, 6, (H, W))
    obj = 190 + 12 * np.sin((u + v) / 5.0) + rng.normal(0, 6, (H, W))
    img = np.where(disc, obj, bg)
    for dx, dy, hr in HOLES:
        hole = (u - cx - dx) ** 2 + (v - cy - dy) ** 2 <= hr * hr
        img[hole] = 35 + rng.normal(0, 6, int(hole.sum()))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), disc


# ---------------------------------------------------------------------- feature
@pytest.mark.parametrize("threshold", [None, 125.0])
def test_bright_disc(threshold):
    img, disc = _scene()
    sil = segment_silhouette(img, options=PLAIN.replace(polarity="brighter", threshold=threshold))
    assert isinstance(sil, Silhouette)
    assert sil.mask.dtype == np.bool_ and sil.mask.shape == (H, W)
    assert _iou(sil.mask, disc) >= 0.99
    assert sil.polarity == "brighter"
    if threshold is None:
        assert 90 < sil.threshold < 160  # Otsu between the two populations
    else:
        assert sil.threshold == threshold
    assert sil.area_px == np.count_nonzero(sil.mask)
    assert np.abs(sil.centroid_uv - [CX, CY]).max() < 0.3
    vs, us = np.nonzero(disc)
    assert abs(sil.bbox[0] - us.min()) <= 1 and abs(sil.bbox[2] - (us.max() + 1)) <= 1
    assert abs(sil.bbox[1] - vs.min()) <= 1 and abs(sil.bbox[3] - (vs.max() + 1)) <= 1
    assert sil.n_components == 1 and not sil.touches_border


@pytest.mark.parametrize("threshold", [None, 130.0])
def test_dark_disc(threshold):
    img, disc = _scene(seed=1)
    sil = segment_silhouette(255 - img,
                             options=PLAIN.replace(polarity="darker", threshold=threshold))
    assert _iou(sil.mask, disc) >= 0.99
    assert sil.polarity == "darker"


def test_holes_filled_only_when_asked():
    img, disc = _scene()
    holed = segment_silhouette(img, options=PLAIN.replace(fill_holes=False))
    assert _iou(holed.mask, disc) < 0.98  # the dark texture does punch holes
    assert _iou(segment_silhouette(img, options=PLAIN).mask, disc) >= 0.99


def test_rgb_uint16_and_float_inputs_agree():
    img, disc = _scene(seed=2)
    ref = segment_silhouette(img, options=PLAIN).mask
    rgb = np.stack([img, img, img], axis=-1)
    assert np.array_equal(segment_silhouette(rgb, options=PLAIN).mask, ref)
    wide = img.astype(np.uint16) * 257
    assert np.array_equal(segment_silhouette(wide, options=PLAIN).mask, ref)
    assert _iou(segment_silhouette(img / 255.0, options=PLAIN).mask, disc) >= 0.99
    tinted = np.stack([img, (img * 0.8).astype(np.uint8), (img * 0.6).astype(np.uint8)], -1)
    assert _iou(segment_silhouette(tinted, options=PLAIN).mask, disc) >= 0.99
    assert to_grey(rgb) == pytest.approx(img.astype(np.float32), abs=1e-3)


def test_roi_excludes_a_distractor():
    img, disc = _scene(seed=3)
    img[5:25, 5:35] = 200  # a bright thing beside the object (600 px)
    whole = segment_silhouette(img, options=PLAIN)
    assert whole.n_components == 2 and _iou(whole.mask, disc) < 0.95
    vs, us = np.nonzero(disc)
    roi = (us.min() - 10, vs.min() - 10, us.max() + 11, vs.max() + 11)
    sil = segment_silhouette(img, roi=roi, options=PLAIN)
    assert _iou(sil.mask, disc) >= 0.99
    assert sil.n_components == 1 and not sil.touches_border
    # an ROI that cuts the object: nothing outside it, and the cut is reported (grey
    # threshold: the automatic polarity would take the object outside it as background)
    cut = segment_silhouette(img, roi=(0, 0, int(CX), H),
                             options=PLAIN.replace(polarity="brighter"))
    assert not cut.mask[:, int(CX):].any() and cut.touches_border


def test_specks_removed():
    img, disc = _scene(seed=4)
    rng = np.random.default_rng(5)
    placed = 0
    while placed < 10:
        u, v = rng.integers(3, W - 6), rng.integers(3, H - 6)
        if not _disc(CX, CY, R + 8)[v:v + 3, u:u + 3].any():
            img[v:v + 3, u:u + 3] = 255
            placed += 1
    sil = segment_silhouette(img, options=PLAIN)
    assert sil.n_components == 11
    assert _iou(sil.mask, disc) >= 0.99
    kept = segment_silhouette(img, options=PLAIN.replace(min_component_px=0,
                                                         min_component_fraction=0.0))
    assert _iou(kept.mask, disc) < 0.99


def test_background_subtraction():
    rng = np.random.default_rng(6)
    v, u = np.mgrid[0:H, 0:W]
    background = np.where((u // 10) % 2 == 0, 30.0, 220.0)  # stripes: both brighter and
    disc = _disc()                                           # darker than the object
    img = background.copy()
    img[disc] = 125 + 8 * np.sin(u[disc] / 3.0)
    hole = (u - CX - 10) ** 2 + (v - CY) ** 2 <= 36  # object matching the scene: a hole
    img[hole] = background[hole]
    noisy = lambda a: np.clip(np.rint(a + rng.normal(0, 4, a.shape)), 0, 255).astype(np.uint8)  # noqa: E731
    img, background = noisy(img), noisy(background)
    plain = segment_silhouette(img, options=PLAIN)
    assert _iou(plain.mask, disc) < 0.9  # thresholding alone cannot do it
    sil = segment_silhouette(img, background=background, options=PLAIN)
    assert sil.polarity == "difference"
    assert _iou(sil.mask, disc) >= 0.99


def test_touches_border():
    img, disc = _scene(cx=30.0, cy=80.0)  # cut by the left side; the holes stay inside
    # grey threshold: the border ring holds the cut object, as flat and noisy as the
    # background here, so the automatic polarity could not tell them apart
    sil = segment_silhouette(img, options=PLAIN.replace(polarity="brighter"))
    assert sil.touches_border and sil.bbox[0] == 0
    assert sil.touches_image_border
    assert _iou(sil.mask, disc) >= 0.99
    s = sil.summary()
    assert s["touches_border"] is True and s["touches_image_border"] is True
    assert s["roi"] == [0, 0, W, H]
    # an ROI cutting the object: its border is touched, not the image's
    img, disc = _scene()
    cut = segment_silhouette(img, roi=(0, 0, int(CX), H),
                             options=PLAIN.replace(polarity="brighter"))
    assert cut.touches_border and not cut.touches_image_border
    assert cut.roi == (0, 0, int(CX), H)
    whole = segment_silhouette(img, options=PLAIN)
    assert not whole.touches_border and not whole.touches_image_border


def test_find_roi_around_the_object_excludes_clutter():
    img, disc = _scene(seed=3)
    img[5:25, 5:35] = 200  # a bright thing beside the object, as in the test above
    roi = find_roi(img, options=PLAIN.replace(roi_margin_px=10))
    vs, us = np.nonzero(disc)
    # the disc's box grown by max(10 px, 10 % of its size) = 10 px on each side
    assert roi == (us.min() - 10, vs.min() - 10, us.max() + 11, vs.max() + 11)
    sil = segment_silhouette(img, roi=roi, options=PLAIN)
    assert _iou(sil.mask, disc) >= 0.99 and sil.n_components == 1
    # near the image's side the region is clipped to the image
    img2, disc2 = _scene(seed=2, cx=30.0, cy=80.0)
    roi2 = find_roi(img2, options=PLAIN.replace(roi_margin_px=25))
    assert roi2[0] == 0 and roi2[2] <= W
    with pytest.raises(ValueError, match="roi_margin_px"):
        find_roi(img, options=PLAIN.replace(roi_margin_px=-1))
    with pytest.raises(StageError, match="empty"):
        find_roi(np.full((H, W), 40, np.uint8),
                 options=PLAIN.replace(polarity="brighter", threshold=100))


# ---------------------------------------------------------------------- exceptions
def test_empty_and_full_silhouettes_raise():
    dark = np.full((H, W), 40, np.uint8)
    with pytest.raises(StageError, match="silhouette is empty"):
        segment_silhouette(dark, options=PLAIN.replace(polarity="brighter", threshold=128))
    bright = np.full((H, W), 230, np.uint8)
    with pytest.raises(StageError, match="covers every pixel"):
        segment_silhouette(bright, options=PLAIN.replace(polarity="brighter", threshold=128))
    with pytest.raises(StageError, match="uniform"):
        segment_silhouette(dark, options=PLAIN)
    img, _ = _scene()
    with pytest.raises(StageError, match="covers every pixel"):
        segment_silhouette(img, roi=(75, 65, 85, 75),  # ROI inside the disc
                           options=PLAIN.replace(polarity="brighter", threshold=125))
    specks = dark.copy()
    specks[10:13, 10:13] = 250
    with pytest.raises(StageError, match="smaller than 50 px"):
        segment_silhouette(specks, options=PLAIN.replace(polarity="brighter", threshold=128))


def test_bad_inputs_raise():
    img, _ = _scene()
    with pytest.raises(ValueError, match=r"uint8, uint16 or float32/float64.*int32"):
        segment_silhouette(img.astype(np.int32), options=PLAIN)
    with pytest.raises(ValueError, match=r"\(H, W\) grey or \(H, W, 3\) RGB.*\(160, 200, 4\)"):
        segment_silhouette(np.zeros((H, W, 4), np.uint8), options=PLAIN)
    with pytest.raises(ValueError, match=r"\(H, W\) grey.*\(200,\)"):
        segment_silhouette(np.zeros(200, np.uint8), options=PLAIN)
    with pytest.raises(ValueError, match="polarity must be one of"):
        segment_silhouette(img, options=PLAIN.replace(polarity="lighter"))
    with pytest.raises(ValueError, match="leaves no pixel"):
        segment_silhouette(img, roi=(300, 0, 400, 50), options=PLAIN)
    with pytest.raises(ValueError, match="background must have the image's size"):
        segment_silhouette(img, background=img[:-1], options=PLAIN)
    with pytest.raises(ValueError, match="non-finite"):
        segment_silhouette(np.full((H, W), np.nan), options=PLAIN)


# ---------------------------------------------------------------------- the box ROI
def _cam(D=(0.0, 0.0, 0.0, 0.0, 0.0)) -> CameraModel:
    return CameraModel("camera", 320, 240, [[300, 0, 159.5], [0, 300, 119.5], [0, 0, 1]],
                       np.asarray(D, float))


def test_roi_from_box_contains_the_box_image():
    cam = _cam([-0.3, 0.1, 0.002, -0.001, 0.0])
    T = look_at([0.05, -0.5, 0.2], [0.0, 0.0, 0.0])
    lo, hi = np.array([-0.05, -0.04, -0.03]), np.array([0.05, 0.04, 0.06])
    roi = roi_from_box(lo, hi, cam, T, margin_px=10)
    t_cb = invert_transform(T)
    rvec, _ = cv2.Rodrigues(t_cb[:3, :3])
    pts = lo + np.random.default_rng(0).random((2000, 3)) * (hi - lo)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    uv, _ = cv2.projectPoints(np.concatenate([pts, corners])[:, None], rvec,
                              t_cb[:3, 3].copy(), cam.K, cam.D)
    pix = np.floor(uv.reshape(-1, 2) + 0.5)
    assert np.all(pix[:, 0] >= roi[0] + 10) and np.all(pix[:, 0] < roi[2] - 10)
    assert np.all(pix[:, 1] >= roi[1] + 10) and np.all(pix[:, 1] < roi[3] - 10)
    # and not much looser than the corners' bounds (the edges may bulge a little)
    c = pix[-8:]
    assert roi[0] >= c[:, 0].min() - 10 - 3 and roi[2] <= c[:, 0].max() + 11 + 3
    assert roi[1] >= c[:, 1].min() - 10 - 3 and roi[3] <= c[:, 1].max() + 11 + 3
    assert 0 <= roi[0] < roi[2] <= 320 and 0 <= roi[1] < roi[3] <= 240


def test_roi_from_box_special_cases():
    cam = _cam()
    lo, hi = np.array([-0.05, -0.05, -0.05]), np.array([0.05, 0.05, 0.05])
    away = look_at([0.0, -0.5, 0.0], [0.0, -1.0, 0.0])
    with pytest.raises(StageError, match="entirely behind camera"):
        roi_from_box(lo, hi, cam, away)
    inside = look_at([0.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    assert roi_from_box(lo, hi, cam, inside) == (0, 0, 320, 240)
    aside = look_at([0.0, -0.5, 0.0], [0.6, 0.1, 0.0])
    with pytest.raises(StageError, match="projects outside"):
        roi_from_box(lo, hi, cam, aside, margin_px=0)
    with pytest.raises(ValueError, match="box_max must exceed box_min"):
        roi_from_box(hi, lo, cam, inside)


def test_distortion_limit():
    assert _distortion_limit_r2(_cam()) == np.inf
    assert _distortion_limit_r2(_cam([-0.4, 0, 0, 0, 0])) == pytest.approx(1 / 1.2)
    # k1 = -0.3, k2 = 0.1: 1 - 0.9 s + 0.5 s^2 has no real root: monotonic everywhere
    assert _distortion_limit_r2(_cam([-0.3, 0.1, 0, 0, 0])) == np.inf
    # the limit is where d r_d / d r = 0
    s = _distortion_limit_r2(_cam([-0.2, -0.05, 0, 0, 0.01]))
    assert 1 + 3 * -0.2 * s + 5 * -0.05 * s**2 + 7 * 0.01 * s**3 == pytest.approx(0, abs=1e-9)


def test_large_enclosed_gap_stays_background_small_marking_is_filled():
    """A see-through gap (an annulus' inside, a temple's columns) is not a hole to fill;
    a dark marking on the object is."""
    h, w = 200, 240
    vv, uu = np.mgrid[0:h, 0:w]
    r = np.hypot(uu - 120, vv - 100)
    image = np.full((h, w), 20, np.uint8)
    image[(r < 80) & (r > 40)] = 200          # a ring: its inside (r < 40) is background
    image[(np.abs(uu - 120) < 4) & (np.abs(vv - 40) < 4)] = 20   # a small dark marking on it
    grey = PLAIN.replace(polarity="brighter", threshold=100, blur_sigma_px=0)
    sil = segment_silhouette(image, options=grey.replace(max_hole_fraction=0.05))
    assert not sil.mask[100, 120]              # the gap stays background
    assert sil.mask[40, 120]                   # the marking is filled
    truth = (r < 80) & (r > 40)
    assert (sil.mask ^ truth).sum() < 0.01 * truth.sum()
    every = segment_silhouette(image, options=grey.replace(max_hole_fraction=1.0))
    assert every.mask[100, 120]                # the seed's rule fills every hole


def test_shaded_side_is_kept_with_automatic_threshold():
    """Three modes (dark table, shaded side, lit side): plain Otsu cuts between shade and
    light; the background cap keeps the shaded side in the silhouette."""
    rng = np.random.default_rng(7)
    h, w = 240, 320
    image = rng.normal(15, 3, (h, w))                       # dark textured table
    image[60:180, 80:160] = rng.normal(200, 4, (120, 80))   # lit face
    image[60:180, 160:240] = rng.normal(70, 4, (120, 80))   # shaded face
    image = np.clip(image, 0, 255).astype(np.uint8)
    truth = np.zeros((h, w), bool)
    truth[60:180, 80:240] = True
    sil = segment_silhouette(image, roi=(40, 30, 280, 210), options=PLAIN)
    iou = (sil.mask & truth).sum() / (sil.mask | truth).sum()
    assert iou > 0.99, iou
    assert sil.threshold < 70


def test_large_shadowed_pocket_is_filled_but_see_through_gap_is_not():
    """Two large enclosed regions: one as dark as the table (a gap one sees through),
    one darker than the object but brighter than any background (a pocket in shadow)."""
    rng = np.random.default_rng(3)
    h, w = 240, 320
    image = rng.normal(15, 2, (h, w))
    image[40:200, 40:280] = rng.normal(190, 3, (160, 240))
    image[80:160, 70:130] = rng.normal(15, 2, (80, 60))     # gap: background seen through
    image[80:160, 190:250] = rng.normal(70, 3, (80, 60))    # pocket: object in shadow
    image = np.clip(image, 0, 255).astype(np.uint8)
    sil = segment_silhouette(image, options=PLAIN.replace(max_hole_fraction=0.02))
    assert not sil.mask[120, 100]
    assert sil.mask[120, 220]


# ---------------------------------------------------------------------- the pipeline stage
def _write_views_recording(path, images, backgrounds, bg_offsets_m):
    """A views-only recording of a static camera rig: one view per image, and on
    ``/camera/background`` an empty-scene image per view, taken ``bg_offsets_m[i]``
    metres from that view's camera position."""
    from robo3d.recording.writer import RecordingWriter

    cam = CameraModel("camera", W, H, [[200, 0, (W - 1) / 2], [0, 200, (H - 1) / 2], [0, 0, 1]])
    t0 = 1_700_000_000_000_000_000
    with RecordingWriter(path) as w:
        w.add_metadata("robo3d.recording", {"kind": "scan", "object": "disc", "units": "m"})
        w.write_calibration("/camera/calibration", t0, cam)
        w.write_transforms("/tf_static", t0, [("flange", "camera", np.eye(4))])
        for i, (img, bg, off) in enumerate(zip(images, backgrounds, bg_offsets_m, strict=True)):
            T = look_at([0.3 * np.cos(i), 0.3 * np.sin(i), 0.2], [0.0, 0.0, 0.0])
            Tb = T.copy()
            Tb[0, 3] += off
            tv = t0 + (2 * i + 1) * 1_000_000_000
            tb = tv + 500_000_000
            for t, pose in ((tv, T), (tb, Tb)):
                for d in (-20_000_000, 20_000_000):
                    w.write_transforms("/tf", t + d, [("base", "flange", pose)])
            w.write_image("/camera/image", tv, "camera", img, "png")
            w.write_image("/camera/background", tb, "camera", bg, "png")
    return cam


def test_stage_silhouettes_background_topic_and_mask_pngs(tmp_path, caplog):
    """Views whose background is both brighter and darker than the object: subtracting
    the empty scene of the same pose segments them; a view whose empty-scene image was
    taken elsewhere is segmented without it (and says so); every mask is written as a
    PNG beside the NPZ."""
    from robo3d.config import load_config
    from robo3d.pipeline import stage_silhouettes
    from robo3d.stages.common import load_silhouettes

    rng = np.random.default_rng(9)
    v, u = np.mgrid[0:H, 0:W]
    background = np.where((u // 10) % 2 == 0, 30.0, 220.0)
    disc = _disc()
    images, bgs = [], []
    for _ in range(3):
        img = background.copy()
        img[disc] = 125 + 8 * np.sin(u[disc] / 3.0)
        images.append(np.clip(np.rint(img + rng.normal(0, 3, img.shape)), 0, 255)
                      .astype(np.uint8))
        bgs.append(np.clip(np.rint(background + rng.normal(0, 3, img.shape)), 0, 255)
                   .astype(np.uint8))
    rec = tmp_path / "discs.mcap"
    _write_views_recording(rec, images, bgs, [0.0, 0.0002, 0.05])
    out = {"npz": str(tmp_path / "silhouettes.npz"), "masks": str(tmp_path / "masks"),
           "report": str(tmp_path / "silhouettes.json"), "rrd": str(tmp_path / "s.rrd")}
    cfg = load_config(overrides={"segmentation": {"background_topic": "/camera/background",
                                                  "min_component_px": 20,
                                                  "polarity": "brighter"}})
    report = stage_silhouettes({"recording": str(rec)}, out, cfg, "discs")
    views = report["views"]
    assert [v["background_subtracted"] for v in views] == [True, True, False]
    assert report["n_background_subtracted"] == 2
    assert "no empty-scene image on /camera/background within 1.00 mm" in caplog.text
    masks = load_silhouettes(out["npz"])["masks"]
    assert _iou(masks[0], disc) >= 0.99 and _iou(masks[1], disc) >= 0.99
    assert _iou(masks[2], disc) < 0.9  # thresholding alone cannot separate them
    assert all(v["roi_source"] == "automatic" for v in views)  # no workspace box
    pngs = sorted((tmp_path / "masks").iterdir())
    assert [p.name for p in pngs] == ["view_000.png", "view_001.png", "view_002.png"]
    for p, m in zip(pngs, masks, strict=True):
        png = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint8 and np.array_equal(png == 255, m)
        assert set(np.unique(png)) <= {0, 255}
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".masks")]
    # a view cut by the image's side is flagged and named
    caplog.clear()
    edge = [np.clip(np.rint(np.where(_disc(20.0, 80.0), 200.0, 40.0)), 0, 255).astype(np.uint8)]
    rec2 = tmp_path / "edge.mcap"
    _write_views_recording(rec2, edge, edge, [0.0])
    cfg2 = load_config(overrides={"segmentation": {"min_component_px": 20}})
    report = stage_silhouettes({"recording": str(rec2)}, out, cfg2, "edge")
    assert report["views_touching_image_border"] == [0]
    assert report["views"][0]["touches_image_border"] is True
    assert "view 0 (topic /camera/image" in caplog.text and "image border" in caplog.text
    assert len(list((tmp_path / "masks").iterdir())) == 1  # the folder was replaced


# ---------------------------------------------------------------------- colour (auto polarity)
def _cell_scene(obj_rgb, table_rgb, wall_rgb=(0.35, 0.35, 0.37), seed=0):
    """(image uint8 RGB, true mask, roi): a rounded box standing on a table with printed
    dark markers before a wall, room light varying across the image, a lit top and a
    shaded side, a shadow on the table, sensor noise and JPEG (quality 85). The ROI is
    the object's box grown by 25 px, as a projected workspace box would be."""
    h, w = 240, 320
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w].astype(float)
    img = np.empty((h, w, 3))
    img[:] = wall_rgb
    table = v >= 70
    img[table] = table_rgb
    depth = (v - 70) / (h - 70)
    x = (u - w / 2) / (0.6 + 0.8 * depth)
    markers = table & (np.mod(x, 46) < 14) & (np.mod(np.sqrt(np.maximum(v - 70, 0)) * 6, 16) < 5)
    img[markers] = 0.06
    cx, cy, ax, ay = 165.3, 128.7, 58.0, 52.0
    body = (np.abs(u - cx) / ax) ** 4 + (np.abs(v - cy) / ay) ** 4 <= 1
    shade = np.clip(0.55 + 0.45 * np.cos(np.clip((v - cy + ay) / (2 * ay), 0, 1) * np.pi / 2)
                    * (1.0 - 0.35 * (u > cx + 0.4 * ax)), 0.3, 1.0)
    shadow = table & ~body & (((u - cx - 30) / ax) ** 2 + ((v - cy - 44) / 18) ** 2 <= 1)
    img[shadow] *= 0.72
    img[body] = np.asarray(obj_rgb) * (shade * (1 + 0.06 * np.sin(u / 5 + v / 7)))[body][:, None]
    img *= (0.8 + 0.25 * u / w - 0.1 * v / h)[..., None] * 235
    img = np.clip(np.rint(img + rng.normal(0, 3.0, img.shape)), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img[..., ::-1]),
                           [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    img = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    roi = (int(cx - ax - 25), int(cy - ay - 25), int(cx + ax + 26), int(cy + ay + 26))
    return np.ascontiguousarray(img), body, roi


def _segment_as_configured(img, roi=None, **kw):
    """segment_silhouette with the project's default segmentation settings (some
    changed by ``kw``)."""
    from robo3d.config import load_config

    options = SegmentOptions.from_config(load_config()["segmentation"]).replace(**kw)
    return segment_silhouette(img, roi=roi, options=options)


ORANGE, BLUE, GREY, WHITE = (0.86, 0.40, 0.10), (0.14, 0.30, 0.72), (0.55, 0.55, 0.55), \
    (0.95, 0.95, 0.93)
BRIGHT_TABLE, GREY_TABLE = (0.82, 0.81, 0.78), (0.45, 0.45, 0.46)


@pytest.mark.parametrize(("obj", "table", "wall"), [
    (ORANGE, BRIGHT_TABLE, (0.35, 0.35, 0.37)),
    (BLUE, BRIGHT_TABLE, (0.35, 0.35, 0.37)),
    (ORANGE, GREY_TABLE, (0.35, 0.35, 0.37)),
    (BLUE, GREY_TABLE, (0.35, 0.35, 0.37)),
    (WHITE, GREY_TABLE, (0.35, 0.35, 0.37)),
], ids=["orange-bright", "blue-bright", "orange-grey", "blue-grey", "white-grey"])
def test_auto_polarity_coloured_objects_on_a_marker_table(obj, table, wall):
    """The default segmentation finds coloured, white and grey objects on bright and grey
    marker tables in room light, where no grey threshold of one polarity can (the table
    is brighter than some objects and darker than others, the markers darker than all)."""
    img, truth, roi = _cell_scene(obj, table, wall)
    sil = _segment_as_configured(img, roi=roi)
    assert sil.polarity == "auto" and sil.background_sample == "outside roi"
    assert _iou(sil.mask, truth) >= 0.985   # orange on grey: 0.987 (a marker at its foot)
    assert sil.qa["flags"] == []
    rules = PLAIN.replace(min_component_px=200, max_hole_fraction=0.02)
    grey = segment_silhouette(img, roi=roi, options=rules.replace(polarity="brighter"))
    darker = segment_silhouette(img, roi=roi, options=rules.replace(polarity="darker"))
    assert max(_iou(grey.mask, truth), _iou(darker.mask, truth)) < 0.97


_KNOWN_LIMIT = pytest.mark.xfail(
    strict=True, reason="known limit: an object whose colours are the background's (a white "
    "object on a white table, a grey one whose shaded side is the wall's or the shadow's "
    "grey) is not told apart by colour")


@pytest.mark.parametrize(("obj", "table", "wall"), [
    pytest.param(WHITE, BRIGHT_TABLE, (0.35, 0.35, 0.37), marks=_KNOWN_LIMIT),
    pytest.param(GREY, GREY_TABLE, (0.35, 0.35, 0.37), marks=_KNOWN_LIMIT),
    pytest.param(GREY, BRIGHT_TABLE, (0.35, 0.35, 0.37), marks=_KNOWN_LIMIT),
    (GREY, BRIGHT_TABLE, (0.85, 0.85, 0.85)),
], ids=["white-on-bright", "grey-on-grey", "grey-on-bright", "grey-on-bright-light-wall"])
def test_auto_polarity_object_in_the_background_colours(obj, table, wall):
    """Objects in the background's colours. A grey object on a bright table before a light
    wall is found (full-resolution GrabCut and the edge refinement recover what the
    colour threshold drops: IoU 1.000); the others stay known limits."""
    img, truth, roi = _cell_scene(obj, table, wall)
    assert _iou(_segment_as_configured(img, roi=roi).mask, truth) >= 0.985


@pytest.mark.parametrize("roi", [None, "box"])
def test_auto_polarity_dark_backdrop(roi):
    """A plaster-coloured object on a dark cloth with folds (Middlebury's temple): with
    the box's surroundings or, without a box, the image border as background."""
    rng = np.random.default_rng(11)
    h, w = 200, 260
    v, u = np.mgrid[0:h, 0:w].astype(float)
    cloth = 18 + 10 * np.sin(u / 23.0 + 0.4 * np.sin(v / 17.0)) ** 2
    img = np.repeat(cloth[..., None], 3, axis=2) * np.array([1.0, 0.95, 0.9])
    truth = ((u - 130.4) / 70) ** 2 + ((v - 96.2) / 50) ** 2 <= 1
    gap = ((u - 130.4) / 30) ** 2 + ((v - 96.2) / 14) ** 2 <= 1   # see-through, cloth behind
    truth &= ~gap
    lit = 0.6 + 0.4 * np.clip((150 - u) / 120, 0, 1)           # a shaded right side
    img[truth] = (np.array([205, 180, 140]) * lit[truth][:, None]
                  * (1 + 0.05 * np.sin(u[truth] / 3.0))[:, None])
    img = np.clip(np.rint(img + rng.normal(0, 2.5, img.shape)), 0, 255).astype(np.uint8)
    box = (40, 25, 221, 168) if roi == "box" else None
    sil = _segment_as_configured(img, roi=box)
    assert sil.background_sample == ("outside roi" if roi else "image border")
    assert _iou(sil.mask, truth) >= 0.99
    assert not sil.mask[96, 130]            # the gap stays background


def test_colour_background_subtraction():
    """The empty scene has stripes of two colours of the object's grey: the grey
    difference to it shows nothing, the colour difference shows the object."""
    rng = np.random.default_rng(12)
    v, u = np.mgrid[0:H, 0:W]
    a, c = np.array([100, 140, 100.0]), np.array([120, 125, 150.0])  # about equal grey
    b = np.array([155, 110, 130.0])                                   # ... and the object's
    scene = np.where(((u // 12) % 2 == 0)[..., None], a, c)
    disc = _disc()
    img = scene.copy()
    img[disc] = b
    noisy = lambda x: np.clip(np.rint(x + rng.normal(0, 2, x.shape)), 0, 255).astype(np.uint8)  # noqa: E731
    img, scene = noisy(img), noisy(scene)
    sil = segment_silhouette(img, background=scene, options=PLAIN)
    assert sil.polarity == "difference"
    # 0.977: the object differs from the two stripes by two amounts, and its outline is
    # cut midway to the larger, a pixel inside on the other stripes
    assert _iou(sil.mask, disc) >= 0.97
    with pytest.raises(StageError):        # grey difference: nothing stands out
        segment_silhouette(img, background=scene,
                           options=PLAIN.replace(polarity="brighter", threshold=20))


def test_grabcut_refinement_follows_the_colour_edge():
    """A blue object on a bright marker table: the threshold leaves its dark shaded foot
    short of the outline; GrabCut, seeded by that mask, follows the colour edge there.
    GrabCut never adds anything outside the ROI, and an empty seed stays empty."""
    img, truth, roi = _cell_scene(BLUE, BRIGHT_TABLE)
    plain = _segment_as_configured(img, roi=roi, grabcut=False, edge_refine_px=0)
    refined = _segment_as_configured(img, roi=roi, grabcut=True, edge_refine_px=0)
    assert not plain.refined and refined.refined
    assert _iou(plain.mask, truth) < 0.99 <= 0.995 <= _iou(refined.mask, truth)
    wide = np.zeros_like(truth)
    wide[roi[1] - 10:roi[3] + 10, roi[0] - 10:roi[2] + 10] = True
    out = refine_with_grabcut(img, wide, roi)
    assert not out[: roi[1]].any() and not out[:, : roi[0]].any()
    assert not refine_with_grabcut(img, np.zeros_like(truth), roi).any()



def test_grabcut_keeps_a_shadow_beside_a_dark_face_background(tmp_path):
    """The front-end benchmark's blue cell (a blue block on the ArUco table, room light,
    JPEG; its views only, the block's mesh at the simulator's default size): in view 10
    the block's unlit face meets its own shadow and a black marker. The colour threshold
    drops the shadow as a blend of table and ink; GrabCut took it back (its mixtures gave
    the dark greys to the dark face: IoU 0.971). Those blends are sure background to
    GrabCut now, and every view reaches 0.99."""
    from robo3d.silhouettes import score_recording_silhouettes
    from robo3d.simulate import SimulationParams, simulate_recording

    path = tmp_path / "blue.mcap"
    exact = dict(sweep_error_mm=(0.0, 0.0), sweep_error_deg=(0.0, 0.0),
                 view_error_mm=(0.0, 0.0), view_error_deg=(0.0, 0.0), view_jitter=0.0)
    simulate_recording(path, "dimple_block", params=SimulationParams.cell(
        laser="blue", object_color="blue", width=640, height=480, views=12, sweeps=1,
        sweep_frames=3, seed=10, **exact), threads=0)
    r = score_recording_silhouettes(str(path))
    assert r["n_scored"] == 12
    assert r["iou_min"] >= 0.99, r["iou"]   # measured 0.9932 (view 7); before 0.9714 (view 10)
    assert r["iou"][10] >= 0.995             # measured 0.9978


def _marker_edge_scene(seed: int = 3, squares: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """An orange disc with a dark shaded side on white paper (with printed black squares,
    or plain), drawn at 4 x 4 samples per pixel (each pixel the mean of its samples: the
    true blend), blurred like a lens and noisy; truth: the disc at pixel centres."""
    rng = np.random.default_rng(seed)
    k = 4
    v, u = (np.mgrid[0:H * k, 0:W * k] + 0.5) / k - 0.5
    ink = ((np.floor(u / 23.0) + np.floor(v / 19.0)) % 2 == 0) & squares
    img = np.where(ink[..., None], np.float32(0.06), np.float32(0.85)) * np.ones(3, np.float32)
    inside = (u - CX) ** 2 + (v - CY) ** 2 <= R * R
    shade = np.clip(0.35 + 0.65 * (CX + R - u) / (2 * R), 0.2, 1.0)[..., None]
    img = np.where(inside[..., None], np.array(ORANGE, np.float32) * shade, img)
    img = img.reshape(H, k, W, k, 3).mean(axis=(1, 3))
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.6)
    img = np.clip(img + rng.normal(0, 0.01, img.shape), 0, 1)
    return np.rint(img * 255).astype(np.uint8), _disc()


def test_refine_edges_puts_the_outline_on_the_pixel_centre_edge():
    """On plain paper a mask 2 px too wide or too narrow all round (IoU 0.90) comes back
    onto the true outline (lit and dark shaded side alike), also from a grey image; on
    printed squares finer than the band's reach only where each side's nearest sure
    colour is the one it blends with (measured: narrow 0.993, wide 0.905 -> 0.952); a
    mask farther off than ``reach_px`` moves at most that far; nothing leaves the ROI; a
    flat image keeps the mask."""
    disc5 = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    plain, truth = _marker_edge_scene(squares=False)
    wide = cv2.dilate(truth.view(np.uint8), disc5).astype(bool)
    narrow = cv2.erode(truth.view(np.uint8), disc5).astype(bool)
    assert _iou(wide, truth) < 0.91 and _iou(narrow, truth) < 0.91
    grey = cv2.cvtColor(plain, cv2.COLOR_RGB2GRAY)
    for start in (wide, narrow):  # measured 0.994 / 0.995, grey 0.994 / 0.994
        assert _iou(refine_edges(plain, start, reach_px=3), truth) >= 0.99
        assert _iou(refine_edges(grey, start), truth) >= 0.99
    marked, _ = _marker_edge_scene()
    assert _iou(refine_edges(marked, narrow), truth) >= 0.99
    assert _iou(refine_edges(marked, wide), truth) >= 0.95
    far = cv2.dilate(truth.view(np.uint8), np.ones((13, 13), np.uint8)).astype(bool)
    moved = refine_edges(plain, far, reach_px=3)
    assert moved[far & ~truth].mean() > 0.3 and not (moved & ~far).any()
    roi = (0, 0, int(CX), H)
    assert not refine_edges(plain, wide, roi)[:, int(CX):].any()
    flat = np.full_like(plain, 128)
    assert np.array_equal(refine_edges(flat, wide), wide)
    assert np.array_equal(refine_edges(plain, wide, reach_px=0), wide)


def test_edge_refinement_in_the_default_segmentation():
    """The default segmentation (GrabCut, then the edge refinement) of the disc on plain
    paper matches the pixel-centre truth; a negative reach is refused."""
    img, truth = _marker_edge_scene(seed=4, squares=False)
    roi = (int(CX - R - 20), int(CY - R - 20), int(CX + R + 21), int(CY + R + 21))
    refined = _segment_as_configured(img, roi=roi)
    assert _iou(refined.mask, truth) >= 0.995
    with pytest.raises(ValueError, match="edge_refine_px"):
        segment_silhouette(img, options=PLAIN.replace(edge_refine_px=-1))


@pytest.mark.xfail(strict=True, reason="known limit: GrabCut takes in black squares that "
                   "touch the object (measured 0.967; the threshold alone 0.993), and the "
                   "edge refinement moves the outline by at most reach_px")
def test_default_segmentation_object_on_printed_squares():
    img, truth = _marker_edge_scene(seed=4)
    roi = (int(CX - R - 20), int(CY - R - 20), int(CX + R + 21), int(CY + R + 21))
    assert _iou(_segment_as_configured(img, roi=roi).mask, truth) >= 0.99


def test_colour_difference_border_sample_keeps_flat_modes_only():
    """With the image border as the sample, a textured object cut off by the frame does
    not become a background mode: it stays far from the background."""
    rng = np.random.default_rng(13)
    h, w = 160, 200
    v, u = np.mgrid[0:h, 0:w].astype(float)
    img = np.full((h, w, 3), 250.0)                   # a white table, flat
    obj = (u < 120) & (v > 30)                        # cut off by the left and bottom sides
    brick = np.where((np.mod(v, 6) < 1) | (np.mod(u + 6 * (np.mod(v // 6, 2)), 12) < 1),
                     200.0, 1.0)                     # mortar lines on red brick
    img[obj] = np.stack([150 * brick[obj] / 200 + 120 * (brick[obj] < 2),
                         45 + 0 * brick[obj], 40 + 0 * brick[obj]], 1)
    img = np.clip(np.rint(img + rng.normal(0, 1.5, img.shape)), 0, 255).astype(np.uint8)
    ring = np.zeros((h, w), bool)
    ring[:4] = ring[-4:] = True
    ring[:, :4] = ring[:, -4:] = True
    d = colour_difference(img, ring, border_sample=True)
    assert np.median(d[obj]) > 10 * max(np.median(d[~obj]), 1.0)
    d_all = colour_difference(img, ring, border_sample=False)  # every mode: brick is one
    assert np.median(d_all[obj]) < np.median(d[obj]) / 3


# ---------------------------------------------------------------------- QA
def test_surrounding_views_only_when_most_views_surround_theirs():
    from robo3d.silhouettes import surrounding_views

    h, w = 100, 120
    obj = np.zeros((h, w), bool)
    obj[30:70, 40:80] = True
    around = ~obj                                     # the table with the object a hole
    big = np.zeros((h, w), bool)                      # an object larger than the frame
    big[0:80, :] = True
    big[80:, 30:60] = True
    cross = np.zeros((h, w), bool)                    # on all four sides, 0.33 of it
    cross[40:60, :] = True
    cross[:, 50:70] = True
    empty = np.zeros((h, w), bool)                    # a failed view: not counted
    assert surrounding_views([around, around, around, obj]) == [0, 1, 2]
    assert surrounding_views([around, big, empty]) == [0, 1]
    assert surrounding_views([big, obj, obj]) == []   # one close-up among whole views
    assert surrounding_views([around, around, obj, obj]) == []   # half is not most
    assert surrounding_views([cross, cross, cross]) == []
    assert surrounding_views([empty, empty]) == []


def test_silhouette_qa_flags():
    h, w = 100, 120
    roi = (10, 10, 110, 90)
    good = np.zeros((h, w), bool)
    good[30:70, 40:80] = True
    assert silhouette_qa(good, roi)["flags"] == []
    full = np.zeros((h, w), bool)
    full[10:90, 10:110] = True
    full[50, 50] = False
    qa = silhouette_qa(full, roi)
    assert qa["flags"] == ["fills_region", "touches_all_sides"]
    assert qa["fill_fraction"] > 0.99 and qa["sides_touched"] == ["left", "top", "right",
                                                                  "bottom"]
    frame = np.zeros((h, w), bool)                      # a ring along the region's sides
    frame[10:90, 10:110] = True
    frame[20:80, 20:100] = False
    assert silhouette_qa(frame, roi)["flags"] == ["touches_all_sides"]
    # the whole image as the region: an object larger than the frame is no flag
    big = np.zeros((h, w), bool)
    big[0:80, 0:w] = True
    big[80:, 30:60] = True
    assert silhouette_qa(big, None)["flags"] == []
    # inverted: the mask holds what looks like the background
    difference = np.where(good, 30.0, 1.0)
    assert silhouette_qa(good, roi, difference)["flags"] == []
    inv = np.zeros((h, w), bool)
    inv[10:90, 10:110] = ~good[10:90, 10:110]
    qa = silhouette_qa(inv, roi, difference)
    assert "inverted" in qa["flags"]
    assert qa["difference_inside"] == 1.0 and qa["difference_outside"] == 30.0


def test_turntable_wrong_polarity_is_flagged_auto_is_not():
    """An orange object on a white turntable, a dark surround (issue 10): the grey
    threshold 'brighter' selects the turntable, which reaches every side of the box's
    region and is flagged; the automatic polarity finds the object."""
    rng = np.random.default_rng(14)
    h, w = 240, 320
    v, u = np.mgrid[0:h, 0:w].astype(float)
    img = np.full((h, w, 3), 25.0)
    disc = ((u - 160) / 150) ** 2 + ((v - 150) / 70) ** 2 <= 1       # the turntable
    img[disc] = 235
    obj = ((u - 160) / 40) ** 2 + ((v - 120) / 60) ** 2 <= 1
    img[obj] = (225, 110, 30)
    img = np.clip(np.rint(img + rng.normal(0, 3, img.shape)), 0, 255).astype(np.uint8)
    roi = (100, 45, 221, 196)
    wrong = _segment_as_configured(img, roi=roi, polarity="brighter")
    assert _iou(wrong.mask, obj) < 0.5
    assert "inverted" in wrong.qa["flags"]  # the mask holds a colour of the background
    right = _segment_as_configured(img, roi=roi)
    assert right.qa["flags"] == [] and _iou(right.mask, obj) >= 0.99


def test_blend_distance_to_segments_between_background_modes():
    """Analytic: distance of colours to the segments paper-ink and paper-wall."""
    from robo3d.silhouettes import _blend_distance

    modes = [(np.array([95.0, 0.0, 2.0]), None), (np.array([5.0, 0.0, 0.0]), None),
             (np.array([40.0, 0.0, -10.0]), None)]
    x = np.array([[50.0, 0.0, 1.0],      # midway paper-ink: 0
                  [50.0, 6.0, 1.0],      # 6 off that segment, in a
                  [120.0, 0.0, 2.0],     # beyond paper: 25 from its end
                  [40.0, 0.0, -10.0],    # the wall mode itself
                  [60.0, 40.0, 50.0]])   # orange: far from every segment
    d = _blend_distance(x, modes)
    assert d[:4] == pytest.approx([0.0, 6.0, 25.0, 0.0], abs=0.9)  # colours binned to 1 unit
    assert d[4] > 40


def test_shadow_and_marker_rims_are_background():
    """A long dark shadow cast across the markers of a bright table, and markers right at
    the object's foot: the silhouette is the object's alone."""
    img, truth, roi = _cell_scene(ORANGE, BRIGHT_TABLE)
    v, u = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    shadow = (v > 150) & (np.abs(u - 205 - 0.5 * (v - 150)) < 30) & ~truth
    img = img.copy()
    img[shadow] = (img[shadow] * 0.5).astype(np.uint8)
    sil = _segment_as_configured(img, roi=roi)
    assert _iou(sil.mask, truth) >= 0.99
    near = cv2.dilate(truth.view(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert not (sil.mask & shadow & ~near).any()   # none of it beyond the outline's blur


def test_silhouettes_artefact_pads_views_and_reads_back(tmp_path):
    """silhouettes.npz (robo3d.artefacts.Silhouettes): masks of cameras of two sizes are
    padded to the larger and cropped back exactly; a file that is not one names itself."""
    from robo3d.artefacts import ArtefactError, Silhouettes
    from robo3d.stages.common import load_silhouettes

    rng = np.random.default_rng(5)
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    cams = [CameraModel("a", 101, 80, K), CameraModel("b", 64, 90, K)]
    masks = [rng.random((c.height, c.width)) > 0.5 for c in cams]
    poses = np.stack([np.eye(4), look_at(np.array([0.3, 0.0, 0.2]), np.zeros(3))])
    art = Silhouettes.from_views(masks, poses, [3, 9], cams, [False, True])
    assert art.masks.shape == (2, 90, 101)
    art.save(tmp_path / "silhouettes.npz")
    back = Silhouettes.load(tmp_path / "silhouettes.npz")
    for m, b in zip(masks, back.view_masks(), strict=True):
        assert b.shape == m.shape and np.array_equal(b, m)
    assert not back.masks[0, 80:].any() and not back.masks[1, :, 64:].any()
    assert back.qa_flagged.tolist() == [False, True] and back.workspace is None
    assert np.array_equal(back.T_base_camera, poses) and back.stamps_ns.tolist() == [3, 9]
    old = load_silhouettes(str(tmp_path / "silhouettes.npz"))  # the former dict
    assert np.array_equal(old["masks"], back.masks) and list(old["frame_ids"]) == ["a", "b"]
    np.savez(tmp_path / "other.npz", masks=np.packbits(art.masks, axis=-1))
    with pytest.raises(ArtefactError, match=r"other\.npz: no mask_shape"):
        Silhouettes.load(tmp_path / "other.npz")


@pytest.mark.parametrize(("obj", "colour", "markers", "seed"), [
    ("sphere", "orange", "aruco", 1), ("bumpy_blob", "green", "aruco", 4)])
def test_views_without_a_workspace_box_in_a_room_lit_cell(tmp_path, obj, colour, markers,
                                                          seed):
    """A recording without a workspace box (a ROS bag carries none): each view is first
    segmented against its image border. In a room-lit cell the border is the wall along
    the top and the marker table, darkened by 25 % vignetting, along the other sides; the
    table's paper is rough at the flatness test's scale (printed marks), was not taken as
    background, and the table's bright middle came out as the object: mean IoU 0.66
    (sphere) and 0.68 (blob), worst views 0.18 and 0.21. A mode that runs around the
    image is background now: 0.979 / 0.985, as with the box (0.988 / 0.986)."""
    from robo3d.config import load_config
    from robo3d.recording import read_recording
    from robo3d.silhouettes import segment_view
    from robo3d.simulate import SimulationParams, simulate_recording

    path = tmp_path / f"{obj}.mcap"
    simulate_recording(path, obj, seed=seed, params=SimulationParams.cell(
        laser="red", object_color=colour, texture="checker" if obj == "bumpy_blob"
        else "blotches", markers=markers, small=True, sweeps=1, sweep_frames=4))
    rec = read_recording(path, roles=("views",))
    views = sorted(rec.views, key=lambda m: m.timestamp_ns)
    poses = rec.camera_poses(views)
    names = sorted(k for k in rec.attachments if k.startswith("ground_truth/silhouettes/"))
    options = SegmentOptions.from_config(load_config()["segmentation"])
    iou = []
    for k, msg in enumerate(views):
        truth = cv2.imdecode(np.frombuffer(bytes(rec.attachments[names[k]]), np.uint8),
                             cv2.IMREAD_GRAYSCALE) > 127
        sil, source = segment_view(rec.decode(msg), rec.camera_for(msg), poses[k], None,
                                   options=options)
        assert source == "automatic"
        iou.append(_iou(sil.mask, truth))
    assert len(iou) == 10
    assert np.mean(iou) >= 0.97 and min(iou) >= 0.9, np.round(iou, 3)


def test_scoring_a_recording_scores_a_failed_view_as_the_stage_leaves_it(tmp_path, monkeypatch):
    """A view whose segmentation fails is an empty mask in the stage (flagged, the others
    go on); the scoring function scored nothing then and raised. It now scores the view
    as the empty mask (IoU 0) and says why."""
    import robo3d.silhouettes as sil
    from robo3d.errors import StageError
    from robo3d.simulate import SimulationParams, simulate_recording

    path = tmp_path / "six.mcap"
    simulate_recording(path, "dimple_block", params=SimulationParams.cell(
        small=True, views=6, sweeps=0, seed=3))
    real, calls = sil.segment_view, []

    def flaky(image, *a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise StageError("no pixel passes the threshold")
        return real(image, *a, **k)

    monkeypatch.setattr(sil, "segment_view", flaky)
    r = sil.score_recording_silhouettes(str(path))
    assert r["n_scored"] == 6 and r["iou"][2] == 0.0 and r["worst_view"] == 2
    assert "no pixel passes" in r["failed"][2] and list(r["failed"]) == [2]
    assert min(v for i, v in r["iou"].items() if i != 2) > 0.9, r["iou"]


def _shadow_scene(obj_rgb, seed: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(RGB image, true object, its shadow): a disc of colour ``obj_rgb`` (0-1, lit from
    the upper left, its lower right side shaded) on a plain light table, its shadow cast
    to the lower right (the table at 45 % of its light, as the simulator's room light
    leaves it), a little sensor noise."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W].astype(float)
    obj = _disc()
    shadow = ((u - CX - 14) ** 2 + (v - CY - 10) ** 2 <= R * R) & ~obj
    shade = np.clip(1.0 - 0.5 * ((u - CX) + (v - CY)) / (2 * R), 0.45, 1.0)
    table = np.array([0.80, 0.79, 0.76])
    img = np.where(obj[..., None], np.asarray(obj_rgb) * shade[..., None], table)
    img[shadow] *= 0.45
    img = img + rng.normal(0, 0.01, img.shape)
    return np.clip(np.rint(255 * img), 0, 255).astype(np.uint8), obj, shadow


def test_a_shadow_on_a_plain_table_is_background_beside_a_coloured_object():
    """A coloured object's shadow on a plain table is the table's colour darkened (no
    ink mode to blend towards): it was object (random scenes on plain tables, mean view
    IoU 0.83-0.93 -> 0.93-0.998 with it dropped, ``benchmarks/README.md`` stop 53); so
    does a black object's. A grey object shades through the same colours itself, so
    beside it the shadow stays."""
    roi = (40, 15, 190, 150)
    opts = SegmentOptions(edge_refine_px=0)
    keep = opts.replace(shadow_darkest=1.0)
    green, obj, shadow = _shadow_scene([0.15, 0.55, 0.2])
    dropped = segment_silhouette(green, roi=roi, options=opts).mask
    kept = segment_silhouette(green, roi=roi, options=keep).mask
    assert _iou(dropped, obj) > 0.97, _iou(dropped, obj)
    assert kept[shadow].mean() > 0.8 and _iou(kept, obj) < 0.85, _iou(kept, obj)
    # a black object is far darker than any shadow: its shadow goes too
    black, obj, shadow = _shadow_scene([0.05, 0.05, 0.05])
    assert _iou(segment_silhouette(black, roi=roi, options=opts).mask, obj) > 0.97
    assert segment_silhouette(black, roi=roi, options=keep).mask[shadow].mean() > 0.8
    # a grey object: the same masks with and without the shadow model
    grey, obj, shadow = _shadow_scene([0.45, 0.45, 0.44])
    assert np.array_equal(segment_silhouette(grey, roi=roi, options=opts).mask,
                          segment_silhouette(grey, roi=roi, options=keep).mask)
    with pytest.raises(ValueError, match="shadow_darkest"):
        segment_silhouette(grey, roi=roi, options=opts.replace(shadow_darkest=0.0))


def test_scoring_keeps_the_first_mask_when_segmenting_again_fails(tmp_path, monkeypatch):
    """The box-less turntable cup's plate views are segmented again inside the others'
    hull; when that fails, the scoring function (like the stage) keeps the first mask
    instead of raising (it raised on a hard scene of a black bracket on a black-marker
    table)."""
    import robo3d.silhouettes as sil
    from robo3d.config import default_config
    from robo3d.errors import StageError
    from robo3d.simulate import SimulationParams, simulate_recording

    rec = tmp_path / "cup.mcap"
    simulate_recording(rec, "cup", seed=34, params=SimulationParams.cell(
        object_color="red", markers="aruco", small=True, views=16, sweeps=0,
        turntable=True, workspace_box=False))
    real = sil.segment_view

    def no_second_try(image, camera, pose, workspace=None, *a, **k):
        if workspace is not None:
            raise StageError("no pixel passes the threshold")
        return real(image, camera, pose, workspace, *a, **k)

    monkeypatch.setattr(sil, "segment_view", no_second_try)
    got = sil.score_recording_silhouettes(str(rec))
    cfg = default_config()
    cfg["segmentation"]["resegment_spurious"] = False
    first = sil.score_recording_silhouettes(str(rec), cfg)
    assert got["iou"] == first["iou"] and got["iou_min"] < 0.6 and not got["failed"]


def test_a_white_table_with_black_dots_is_background_without_a_box(tmp_path):
    """Without a workspace box the background is modelled from the image border, where
    only flat colour modes count (the object may be cut off there). A sensor's shot
    noise grows with the light: white paper printed with black dots measured 3.8 times
    the flat limit, the ink 1.3, so only the ink was kept, the paper became the object
    and the object its holes (random scene 1163: IoU 0.05-0.13 in all eight views). A
    near-neutral mode whose roughness a 1 px Gaussian cuts by 3 or more is pixel noise,
    and flat when it is flat so smoothed (the paper: 1.0 after smoothing)."""
    import numpy as np

    from robo3d.silhouettes import score_recording_silhouettes
    from robo3d.simulate import SimulationParams, simulate_recording

    rec = tmp_path / "wall.mcap"
    simulate_recording(rec, "thin_wall", seed=1163, params=SimulationParams.cell(
        laser="blue", object_color="orange", texture="blotches", markers="dots",
        workspace_box=False, view_encoding="png", small=True, views=6, sweeps=0))
    got = score_recording_silhouettes(str(rec))
    iou = np.array(list(got["iou"].values()))
    # measured: mean 0.986, worst 0.961 (before: 0.087 and 0.0)
    assert len(iou) == 6 and iou.mean() > 0.95 and iou.min() > 0.9, got["iou"]
