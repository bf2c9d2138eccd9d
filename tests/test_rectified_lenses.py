"""``rational_polynomial`` and ``equidistant`` (fisheye) cameras read as they are.

Their images are rectified to a pinhole camera (:class:`robo3d.camera.Rectifier`): the
views are resampled, the laser frames are searched raw and their stripe centres moved
exactly. OpenCV's own models are the oracle of the unit tests. The rational bag test uses
a lens model that equals the simulated camera's plumb_bob exactly while its k4 is not zero
(the radial term ``(1 + a s + b s^2)(1 + k4 s) / (1 + k4 s)`` with ``s = r^2``), so the
recorded pixels are right for it as they are; dropping its k4..k6 (the control) is then
a wrong lens. The fisheye bag's frames are the simulated ones resampled into the fisheye
camera (no model equals plumb_bob), which costs a little accuracy of its own.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from robo3d.camera import Rectifier
from robo3d.errors import CalibrationError

K = np.array([[600.0, 0.0, 322.5], [0.0, 605.0, 241.0], [0.0, 0.0, 1.0]])
D8 = np.array([-0.25, 0.08, 0.001, -0.0008, 0.01, 0.3, 0.05, 0.002])
D_FISHEYE = np.array([-0.1, 0.02, -0.004, 0.001])
#: OpenCV's full model: the rational terms, thin prism s1..s4 and a tilted sensor
D14 = np.r_[D8, 0.002, -0.001, 0.001, 0.0005, 0.003, -0.002]
LENSES = {"rational_polynomial": ("rational_polynomial", D8),
          "rational_polynomial, 14 coefficients": ("rational_polynomial", D14),
          "equidistant": ("equidistant", D_FISHEYE)}


def _points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-0.28, 0.28, (n, 2)), np.full(n, 0.5)]


def _raw_pixels(p: np.ndarray, model: str, d: np.ndarray) -> np.ndarray:
    """OpenCV's projection of camera-frame points through the lens."""
    if model == "equidistant":
        return cv2.fisheye.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                         d)[0].reshape(-1, 2)
    return cv2.projectPoints(p, np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)


@pytest.mark.parametrize("lens", sorted(LENSES))
def test_rectifier_moves_raw_pixels_exactly_and_resamples_images(lens: str) -> None:
    model, d = LENSES[lens]
    rect = Rectifier("camera", 640, 480, K, d, model)
    cam = rect.camera
    assert not cam.has_distortion and (cam.width, cam.height) == (640, 480)
    assert 0.5 < rect.kept_fraction < 1.0  # alpha 0: the raw image's rim is cut, no border
    p = _points(400)
    raw = _raw_pixels(p, model, d)
    inside = (raw[:, 0] > 0) & (raw[:, 0] < 639) & (raw[:, 1] > 0) & (raw[:, 1] < 479)
    want, _ = cam.project(p)
    np.testing.assert_allclose(rect.raw_to_rectified(raw[inside]), want[inside], atol=1e-5)
    # a raw image of small Gaussian dots: rectified, each dot's centre where the pinhole
    # camera sees its point (the remap's bilinear interpolation, 1/32 px tables; near the
    # rim the lens stretches a dot unevenly, which moves its centroid: 0.062 px at most)
    clear = inside & np.all((want > 8) & (want < [631, 471]), axis=1)
    sel = np.nonzero(clear)[0][:12]
    u, v = np.meshgrid(np.arange(640.0), np.arange(480.0))
    img = np.zeros((480, 640))
    for a, b in raw[sel]:
        img += 200.0 * np.exp(-((u - a) ** 2 + (v - b) ** 2) / (2 * 1.2 ** 2))
    out = rect(np.clip(img, 0, 255).astype(np.uint8)).astype(np.float64)
    for (a, b), (pa, pb) in zip(raw[sel], want[sel], strict=True):
        r0, c0 = int(round(pb)), int(round(pa))
        win = out[r0 - 4:r0 + 5, c0 - 4:c0 + 5]
        wv, wu = np.mgrid[r0 - 4:r0 + 5, c0 - 4:c0 + 5]
        cu, cv = (win * wu).sum() / win.sum(), (win * wv).sum() / win.sum()
        assert abs(cu - pa) < 0.1 and abs(cv - pb) < 0.1, ((a, b), (cu, cv), (pa, pb))
    # a region drawn on the rectified image, on the raw one: around the same points
    region = np.zeros((480, 640), bool)
    for pa, pb in want[sel]:
        cv2.circle(region.view(np.uint8), (int(round(pa)), int(round(pb))), 3, 1, -1)
    raw_region = rect.raw_mask(region)
    assert raw_region[np.rint(raw[sel, 1]).astype(int), np.rint(raw[sel, 0]).astype(int)].all()
    assert abs(int(raw_region.sum()) - int(region.sum())) < 0.5 * region.sum()


def test_rectifier_needs_the_models_finite_coefficients() -> None:
    with pytest.raises(CalibrationError, match="needs 8 or 12 or 14 coefficients"):
        Rectifier("camera", 640, 480, K, D8[:7])
    with pytest.raises(CalibrationError, match="needs 4 coefficients"):
        Rectifier("camera", 640, 480, K, D8[:5], "equidistant")
    with pytest.raises(CalibrationError, match="not finite"):
        Rectifier("camera", 640, 480, K, np.r_[D8[:7], np.nan])
    with pytest.raises(CalibrationError, match="no rectification for lens model"):
        Rectifier("camera", 640, 480, K, D_FISHEYE, "kannala_brandt")
    # a fisheye seeing 240 degrees across: no pinhole camera shows it
    wide = np.array([[150.0, 0.0, 319.5], [0.0, 150.0, 239.5], [0.0, 0.0, 1.0]])
    with pytest.raises(CalibrationError, match="field of view is too wide"):
        Rectifier("camera", 640, 480, wide, np.zeros(4), "equidistant")
    # a wide one that a pinhole camera still shows, with much of its frame cut (the reader
    # warns below 60 %)
    k250 = np.array([[250.0, 0.0, 319.5], [0.0, 250.0, 239.5], [0.0, 0.0, 1.0]])
    assert 0.6 < Rectifier("camera", 640, 480, k250, np.zeros(4),
                           "equidistant").kept_fraction < 0.8  # measured 0.727


# ------------------------------------------------------------------------------ a ROS bag
rosbags = pytest.importorskip("rosbags")


@pytest.fixture(scope="module")
def native(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from test_ros2 import SMALL

    from robo3d.simulate import simulate_recording

    p = tmp_path_factory.mktemp("rational") / "sphere.mcap"
    simulate_recording(p, "sphere", seed=7, **{**SMALL, "width": 320, "height": 240})
    return p


def _equal_rational(D5: np.ndarray, k4: float) -> np.ndarray:
    """The rational_polynomial coefficients with this k4 (k5 = k6 = 0) that equal the
    plumb_bob ``D5`` (k3 = 0) exactly: numerator ``(1 + k1 s + k2 s^2)(1 + k4 s)``."""
    k1, k2, p1, p2, k3 = D5
    assert k3 == 0
    return np.array([k1 + k4, k2 + k1 * k4, p1, p2, k2 * k4, k4, 0.0, 0.0])


def _stripe_points(bag: Path, cfg: dict, out: Path) -> tuple[np.ndarray, np.ndarray]:
    from robo3d.artefacts import load_clouds_npz
    from robo3d.pipeline import stage_stripes, stage_triangulate

    out.mkdir(parents=True, exist_ok=True)
    stage_stripes({"recording": str(bag)}, {"npz": str(out / "stripes.npz"),
                                            "rrd": str(out / "st.rrd"),
                                            "report": str(out / "stripes.json")}, cfg, "x")
    stage_triangulate({"stripes": str(out / "stripes.npz")},
                      {"npz": str(out / "clouds.npz"), "ply": str(out / "clouds.ply"),
                       "rrd": str(out / "t.rrd"), "report": str(out / "tri.json")}, cfg, "x")
    clouds = load_clouds_npz(str(out / "clouds.npz"))
    return np.concatenate([c.points_base for c in clouds]), \
        np.concatenate([c.normals_base for c in clouds])


def test_a_rational_polynomial_camera_is_rectified_and_measures_as_its_lens_is(
        native: Path, tmp_path: Path) -> None:
    from scipy.spatial import cKDTree
    from test_ros2 import read_ros, ros_config, write_ros2_bag

    from robo3d.artefacts import Silhouettes
    from robo3d.evaluate import silhouette_iou
    from robo3d.pipeline import stage_silhouettes
    from robo3d.recording import read_recording

    want = read_recording(native)
    cam0 = want.calibrations["camera"]
    d8 = _equal_rational(cam0.D, 0.5)
    bags = {"native": write_ros2_bag(native, tmp_path / "native", views="rgb8", laser="rgb8"),
            "rational": write_ros2_bag(native, tmp_path / "rational", views="rgb8",
                                       laser="rgb8", camera_info={
                                           "d": d8, "distortion_model": "rational_polynomial"}),
            "control": write_ros2_bag(native, tmp_path / "control", views="rgb8",
                                      laser="rgb8", camera_info={
                                          "d": np.r_[d8[:5], 0, 0, 0],
                                          "distortion_model": "rational_polynomial"})}
    rec = read_ros(bags["rational"])
    rect = rec.rectifiers["camera"]
    assert rec.calibrations["camera"] is rect.camera and not rect.camera.has_distortion
    raw, shown = rec.decode_raw(rec.views[0]), rec.decode(rec.views[0])
    assert raw.shape == shown.shape and not np.array_equal(raw, shown)
    np.testing.assert_array_equal(raw, want.decode(want.views[0]))
    assert read_ros(bags["control"]).rectifiers == {}  # k4..k6 zero: plumb_bob

    cfg = ros_config()
    pts = {k: _stripe_points(b, cfg, tmp_path / f"out_{k}") for k, b in bags.items()}
    p0, n0 = pts["native"]
    tree = cKDTree(p0)

    def off_mm(p: np.ndarray) -> np.ndarray:  # to the native points' tangent planes
        _, i = tree.query(p)
        return np.abs(np.einsum("ij,ij->i", p - p0[i], n0[i])) * 1e3

    # the stripe is searched in the raw frames: the same centres, moved exactly (measured:
    # identical to 1e-14 mm); the control's lens puts them 0.07 mm (median), 0.8 mm (p95) off
    assert len(pts["rational"][0]) == len(p0)
    assert np.percentile(off_mm(pts["rational"][0]), 95) < 1e-6
    assert np.percentile(off_mm(pts["control"][0]), 95) > 0.2
    # the views resampled: their masks against the true silhouettes resampled alike
    # (measured: mean IoU 0.990 against 0.998 for the raw views)
    out = tmp_path / "sil"
    stage_silhouettes({"recording": str(bags["rational"])},
                      {"npz": str(out / "sil.npz"), "rrd": str(out / "s.rrd"),
                       "report": str(out / "sil.json")}, cfg, "x")
    sil = Silhouettes.load(str(out / "sil.npz"))
    masks = sil.view_masks()
    iou = silhouette_iou(masks, want.attachments, rectify=[rect] * len(masks))
    assert iou["n_scored"] == len(masks) and iou["min"] > 0.97, iou
    assert silhouette_iou(masks, want.attachments)["mean"] < iou["mean"]  # not rectified


def test_a_rolling_shutter_times_a_rectified_centre_by_its_sensor_row(
        tmp_path: Path, monkeypatch) -> None:
    """A rolling shutter exposes the sensor's (raw) rows: a rectified camera's centre
    takes the pose of the raw row it was found in, not of its rectified row, which the
    lens and the rectified camera's new K move by up to a tenth of the frame. The
    recording is the plumb_bob one read as a rational_polynomial lens equal to it (the
    frames need not be rendered with a rolling shutter: both readings get the same
    pixels and the same readout in the config)."""
    from test_ros2 import SMALL, ros_config, write_ros2_bag

    import robo3d.simulate as sim
    from robo3d.artefacts import Stripes
    from robo3d.camera import CameraModel
    from robo3d.recording import read_recording
    from robo3d.simulate import simulate_recording

    def wide(width: int, height: int, frame_id: str = "camera") -> CameraModel:
        c = sim_camera(width, height, frame_id)  # a shorter focal length, a stronger lens
        return CameraModel(c.frame_id, c.width, c.height, c.K * [[0.6], [0.6], [1.0]],
                           np.array([-0.3, 0.1, 7e-4, -5e-4, 0.0]))

    sim_camera = sim.default_camera
    monkeypatch.setattr(sim, "default_camera", wide)
    native = tmp_path / "plumb_bob.mcap"
    simulate_recording(native, "sphere", seed=7, sweep_speed=0.1,
                       **{**SMALL, "width": 320, "height": 240, "views": 0})
    d8 = _equal_rational(read_recording(native, roles=("laser",)).calibrations["camera"].D,
                         0.5)
    bags = {"native": write_ros2_bag(native, tmp_path / "native", laser="rgb8"),
            "rational": write_ros2_bag(native, tmp_path / "rational", laser="rgb8",
                                       camera_info={"d": d8, "distortion_model":
                                                    "rational_polynomial"})}
    cfg = ros_config(timing={"rolling_shutter_s": 0.03})
    pts = {k: _stripe_points(b, cfg, tmp_path / f"out_{k}")[0] for k, b in bags.items()}
    st = Stripes.load(str(tmp_path / "out_rational" / "stripes.npz"))
    assert Stripes.load(str(tmp_path / "out_native" / "stripes.npz")).v_sensor is None
    # the rectified rows are not the sensor's (measured: up to 5.1 px of 240)
    assert np.abs(st.v_sensor - st.v).max() > 3.0, np.abs(st.v_sensor - st.v).max()
    # the same points as the plumb_bob reading (measured: 3e-12 mm apart; timed by the
    # rectified rows instead, 0.061 mm at most: the camera moves 3 mm in the readout)
    assert len(pts["rational"]) == len(pts["native"])
    assert np.abs(pts["rational"] - pts["native"]).max() * 1e3 < 1e-6, \
        np.abs(pts["rational"] - pts["native"]).max() * 1e3


def test_a_fisheye_camera_is_rectified_and_measures_as_its_lens_is(
        native: Path, tmp_path: Path) -> None:
    """The simulated frames resampled into an equidistant (fisheye) camera of the same
    focal length, its CameraInfo saying so; the control reads the same frames as a
    pinhole camera."""
    import dataclasses

    from scipy.spatial import cKDTree
    from test_ros2 import ROS_TOPICS, read_ros, ros_config, write_ros2_bag

    from robo3d.recording import read_recording

    cam0 = read_recording(native, roles=()).calibrations["camera"]
    w, h = cam0.width, cam0.height
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    # each fisheye pixel shows the ray that the simulated camera shows at this pixel
    xy = cv2.fisheye.undistortPoints(np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2),
                                     cam0.K, D_FISHEYE).reshape(-1, 2)
    src = cam0.normalized_to_pixels(cam0.distort_normalized(xy)).astype(np.float32)
    mx, my = src[:, 0].reshape(h, w), src[:, 1].reshape(h, w)

    def fisheye(topic: str, msg):
        if topic in (ROS_TOPICS["views"], ROS_TOPICS["laser"]) and hasattr(msg, "encoding"):
            px = msg.data.reshape(msg.height, msg.width, 3)
            out = cv2.remap(px, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            msg = dataclasses.replace(msg, data=np.ascontiguousarray(out).reshape(-1))
        return msg

    bags = {"native": write_ros2_bag(native, tmp_path / "native", views="rgb8", laser="rgb8"),
            "fisheye": write_ros2_bag(native, tmp_path / "fisheye", views="rgb8",
                                      laser="rgb8", mutate=fisheye, camera_info={
                                          "d": D_FISHEYE, "distortion_model": "equidistant"}),
            "control": write_ros2_bag(native, tmp_path / "control", views="rgb8",
                                      laser="rgb8", mutate=fisheye, camera_info={
                                          "d": np.zeros(5), "distortion_model": "plumb_bob"})}
    rec = read_ros(bags["fisheye"])
    assert rec.rectifiers["camera"].model == "equidistant"
    cfg = ros_config()
    pts = {k: _stripe_points(b, cfg, tmp_path / f"out_{k}") for k, b in bags.items()}
    p0, n0 = pts["native"]
    tree = cKDTree(p0)

    def off_mm(p: np.ndarray) -> np.ndarray:
        _, i = tree.query(p)
        return np.abs(np.einsum("ij,ij->i", p - p0[i], n0[i])) * 1e3

    fish, ctrl = off_mm(pts["fisheye"][0]), off_mm(pts["control"][0])
    # measured (off the native points' tangent planes): fisheye median 0.021 / p95 0.087 mm
    # (the frames' resampling into the fisheye camera), the control 0.040 / 0.269 mm (a
    # lens error along the stripe slides points along the surface: only its part across
    # the stripe shows here)
    assert np.median(fish) < 0.05 and np.percentile(fish, 95) < 0.2, (np.median(fish),)
    assert np.percentile(ctrl, 95) > 2.5 * np.percentile(fish, 95), (np.percentile(ctrl, 95),)


def test_centres_the_lens_cannot_invert_are_dropped_with_their_attributes(caplog) -> None:
    """A stripe centre whose ray the lens model gives no inverse for (NaN from OpenCV,
    beyond a fisheye's reach) is dropped with everything measured about it, and said."""
    from types import SimpleNamespace

    from robo3d.stages.stripes import _rectified
    from robo3d.stripes import StripePoints

    sp = StripePoints(u=np.array([10.0, 320.0, 600.0]), v=np.array([10.0, 240.0, 470.0]),
                      axis="rows", confidence=np.array([0.9, 0.8, 0.7]),
                      peak=np.array([30.0, 40.0, 50.0]))
    nan_middle = SimpleNamespace(model="equidistant", frame_id="camera",
                                 raw_to_rectified=lambda uv: np.where(
                                     np.arange(len(uv))[:, None] == 1, np.nan, uv + 0.5))
    out = _rectified(sp, nan_middle)
    np.testing.assert_array_equal(out.u, [10.5, 600.5])
    np.testing.assert_array_equal(out.confidence, [0.9, 0.7])
    np.testing.assert_array_equal(out.peak, [30.0, 50.0])
    np.testing.assert_array_equal(out.line, [10, 470])
    assert out.rejected["outside_roi"] == 1
    assert "1 of 3 centres" in caplog.text
    # a fisheye's own inversion: every centre of the image is finite and kept
    rect = Rectifier("camera", 640, 480, np.array([[300.0, 0.0, 319.5], [0.0, 300.0, 239.5],
                                                   [0.0, 0.0, 1.0]]), np.zeros(4),
                     "equidistant")
    assert len(_rectified(sp, rect)) == 3
