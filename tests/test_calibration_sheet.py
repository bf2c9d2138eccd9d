"""The laser sheet calibration (robo3d.calibration.sheet) and the six parameters of a sheet
(robo3d.triangulation): analytic ground truth (points on a known plane, rendered board
frames with a known sheet), the degenerate cases, round trips, and the real
``srv_laser_calibration`` recording (skipped without ``../shared``)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from robo3d.calibration.sheet import (
    SheetOptions,
    board_border_region,
    board_point_mask,
    board_poses_from_handeye,
    calibrate_sheet,
    fit_plane_robust,
    sheet_points,
    still_views,
)
from robo3d.camera import CameraModel
from robo3d.errors import CalibrationError
from robo3d.transforms import euler_to_matrix, invert_transform
from robo3d.triangulation import (
    laser_plane_in_camera,
    laser_pose_from_plane,
    laser_transform_from_params,
    six_parameters_from_pose,
)

SRV = Path(__file__).resolve().parents[2] / "shared" / "real" / "srv_laser_calibration.mcap"


@dataclass(frozen=True)
class _Board:
    cols: int = 8
    rows: int = 6
    square: float = 0.02


BOARD = _Board()
CAM = CameraModel("camera", 640, 480, np.array([[600.0, 0, 321.3], [0, 598.0, 238.7],
                                                [0, 0, 1]]),
                  np.array([-0.08, 0.05, 0.0005, -0.0003, 0.0]))
# the true sheet: through (0.1, 0, 0) and (0, 0, 0.4), tilted a little about the optical axis
N_TRUE = np.array([0.4, -0.03, 0.1]) / np.linalg.norm([0.4, -0.03, 0.1])
D_TRUE = float(N_TRUE @ [0.1, 0.0, 0.0])


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(a @ b) / np.linalg.norm(a)
                                              / np.linalg.norm(b), -1, 1))))


def _pose(rx: float, ry: float, rz: float, centre: np.ndarray) -> np.ndarray:
    """Board pose whose pattern centre is at ``centre`` (camera frame), z into the board."""
    r = euler_to_matrix("xyz", np.radians([rx, ry, rz]))
    c_board = np.array([(BOARD.cols - 1) / 2, (BOARD.rows - 1) / 2, 0.0]) * BOARD.square
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = centre - r @ c_board
    return t


def _on_sheet(z: float, y: float = 0.0) -> np.ndarray:
    """The point of the true sheet at depth z and height y, in the x-z direction."""
    x = (D_TRUE - N_TRUE[1] * y - N_TRUE[2] * z) / N_TRUE[0]
    return np.array([x, y, z])


# boards at several depths and tilts; the line falls on the white border and the pattern
_POSE_TABLE = [(10, -20, 3, 0.36, 0.00, 0.07), (-15, 10, -5, 0.40, 0.01, -0.08),
               (20, 25, 0, 0.44, -0.01, 0.10), (-5, -30, 8, 0.33, 0.02, 0.02),
               (25, 5, -10, 0.42, -0.02, -0.03), (0, 15, 4, 0.38, 0.0, 0.09),
               (-20, -10, 0, 0.46, 0.01, -0.10), (8, 30, -6, 0.35, -0.01, 0.05)]
POSES = [_pose(rx, ry, rz, _on_sheet(z, y) + np.array([dx, 0, 0]))
         for rx, ry, rz, z, y, dx in _POSE_TABLE]


_RAYS: dict[str, np.ndarray] = {}


def _pixel_rays() -> np.ndarray:
    """The ray of every pixel centre, (H, W, 3), computed once."""
    if "r" not in _RAYS:
        v, u = np.mgrid[0:CAM.height, 0:CAM.width].astype(np.float64)
        _RAYS["r"] = CAM.rays(np.stack([u, v], -1).reshape(-1, 2)).reshape(
            CAM.height, CAM.width, 3)
    return _RAYS["r"]


def _render(T_camera_target: np.ndarray, n_sheet: np.ndarray, d_sheet: float,
            rng: np.random.Generator, sigma_m: float = 0.0008,
            border: tuple[float, float] = (3.5, 2.5), room: float = 35.0) -> np.ndarray:
    """A laser frame: a checkerboard with a white border (``border`` squares beyond the
    inner corners), lit by room light and a green line laser (Gaussian across the sheet,
    ``sigma_m``), over a room of grey ``room``; 1 DN noise."""
    rays = _pixel_rays()
    n_b, d_b = T_camera_target[:3, 2], T_camera_target[:3, 2] @ T_camera_target[:3, 3]
    s = d_b / (rays @ n_b)
    X = rays * s[..., None]
    t_tc = invert_transform(T_camera_target)
    xy = (X @ t_tc[:3, :3].T + t_tc[:3, 3])[..., :2] / BOARD.square
    bx, by = border
    on_board = ((xy[..., 0] > -bx) & (xy[..., 0] < BOARD.cols - 1 + bx)
                & (xy[..., 1] > -by) & (xy[..., 1] < BOARD.rows - 1 + by) & (s > 0))
    pattern = ((xy[..., 0] > -1) & (xy[..., 0] < BOARD.cols)
               & (xy[..., 1] > -1) & (xy[..., 1] < BOARD.rows))
    dark = (np.floor(xy[..., 0]) + np.floor(xy[..., 1])) % 2 == 0
    refl = np.where(on_board, np.where(pattern & dark, 0.08, 0.85), 0.0)
    delta = X @ n_sheet - d_sheet
    laser = 150.0 * np.exp(-0.5 * (delta / sigma_m) ** 2)
    grey = np.where(on_board, refl * 180.0, room)
    rgb = np.stack([grey, grey + refl * laser, grey], -1)
    rgb += rng.normal(0, 1.0, rgb.shape)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------- six parameters
def test_six_parameters_round_trip():
    p = dict(dx=0.12, dy=-0.03, dz=0.05, phi=0.3, theta=-0.4, psi=0.2)
    T = laser_transform_from_params(**p)
    six = six_parameters_from_pose(T)
    for k, v in p.items():
        assert six[k] == pytest.approx(v, abs=1e-12)
    assert six["theta_deg"] == pytest.approx(np.degrees(-0.4))
    back = laser_transform_from_params(*(six[k] for k in ("dx", "dy", "dz", "phi", "theta", "psi")))
    np.testing.assert_allclose(back, T, atol=1e-12)


def test_pose_from_plane_has_the_plane_and_canonical_choices():
    n, d = laser_plane_in_camera(laser_transform_from_params(0.1, 0.02, -0.03, 0.2, -0.5, 0.1))
    T = laser_pose_from_plane(n, d)
    n2, d2 = laser_plane_in_camera(T)
    np.testing.assert_allclose(n2, n, atol=1e-12)
    assert d2 == pytest.approx(d, abs=1e-12)
    # canonical: origin at the foot of the perpendicular, beam = camera z projected
    np.testing.assert_allclose(T[:3, 3], d * n, atol=1e-12)
    z = np.array([0, 0, 1.0]) - n[2] * n
    np.testing.assert_allclose(T[:3, 2], z / np.linalg.norm(z), atol=1e-12)
    # the same sheet from the flipped normal gives the same pose (d >= 0 picks the sign)
    np.testing.assert_allclose(laser_pose_from_plane(-n, -d), T, atol=1e-12)
    # two poses with one sheet (moved and turned within it): the same canonical parameters
    T_a = laser_transform_from_params(0.1, 0.02, -0.03, 0.2, -0.5, 0.1)
    slide = np.eye(4)
    slide[:3, :3] = euler_to_matrix("y", [0.3])  # about the laser's y: within the sheet
    slide[:3, 3] = [0.02, 0.0, -0.05]
    T_b = T_a @ slide
    a, b = (six_parameters_from_pose(t, canonical=True) for t in (T_a, T_b))
    assert six_parameters_from_pose(T_a)["dx"] != pytest.approx(six_parameters_from_pose(T_b)["dx"])
    for k in a:
        assert a[k] == pytest.approx(b[k], abs=1e-12)


def test_pose_from_plane_keeps_the_reference_in_plane():
    ref = laser_transform_from_params(0.15, -0.02, 0.06, np.radians(-100), np.radians(-25),
                                      np.radians(-5))
    n, d = laser_plane_in_camera(ref)
    # the plane itself: the reference comes back unchanged
    np.testing.assert_allclose(laser_pose_from_plane(n, d, ref), ref, atol=1e-12)
    # a tilted plane: the new pose's origin is the reference's projected onto it
    n2 = n + np.array([0.0, 0.03, -0.02])
    n2 /= np.linalg.norm(n2)
    T = laser_pose_from_plane(-n2, -(d + 0.004), ref)
    assert T[:3, 1] @ ref[:3, 1] > 0.99
    assert T[:3, 1] @ T[:3, 3] == pytest.approx(d + 0.004, abs=1e-12)
    delta = T[:3, 3] - ref[:3, 3]
    assert np.linalg.norm(np.cross(delta, n2)) < 1e-12  # moved along the normal only


def test_pose_from_plane_rejects_a_zero_normal():
    with pytest.raises(ValueError, match="non-zero"):
        laser_pose_from_plane(np.zeros(3), 0.1)


# ---------------------------------------------------------------------------- plane fit
def _line_pixels(T: np.ndarray, n: np.ndarray, d: float, count: int = 600) -> np.ndarray:
    """Pixels of the line where the sheet meets the board's plane (within the border)."""
    n_b, d_b = T[:3, 2], T[:3, 2] @ T[:3, 3]
    u = np.cross(n, n_b)
    u /= np.linalg.norm(u)
    x0 = np.linalg.lstsq(np.stack([n, n_b]), np.array([d, d_b]), rcond=None)[0]
    X = x0 + np.linspace(-0.15, 0.15, count)[:, None] * u
    uv, front = CAM.project(X)
    ok = front & (uv[:, 0] > 0) & (uv[:, 0] < 639) & (uv[:, 1] > 0) & (uv[:, 1] < 479)
    return uv[ok]


def test_fit_plane_robust_recovers_a_known_sheet_from_noisy_points():
    rng = np.random.default_rng(3)
    pts = []
    for T in POSES:
        uv = _line_pixels(T, N_TRUE, D_TRUE)
        uv = uv + rng.normal(0.0, 0.1, uv.shape)  # stripe centre noise, pixels
        pts.append(sheet_points(uv, CAM, T))
    P = np.concatenate(pts)
    # 5 % gross outliers (the room's stripe cast onto the board plane)
    bad = rng.choice(len(P), len(P) // 20, replace=False)
    P[bad] += rng.normal(0, 0.02, (len(bad), 3))
    fit = fit_plane_robust(P, SheetOptions(), seed=0)
    assert _angle_deg(fit.normal, N_TRUE) < 0.03
    assert abs(fit.offset_m - D_TRUE) * 1e3 < 0.03
    assert fit.normal @ N_TRUE > 0 and fit.offset_m > 0
    assert fit.inliers[bad].mean() < 0.2
    assert 0.02 < fit.rms_mm < 0.2  # the 0.15 px noise at ~0.4 m, not zero
    # seeded: the same result twice
    again = fit_plane_robust(P, SheetOptions(), seed=0)
    np.testing.assert_array_equal(again.normal, fit.normal)


def test_fit_plane_robust_rejects_too_few_or_collinear_points():
    with pytest.raises(ValueError, match="at least 3"):
        fit_plane_robust(np.zeros((2, 3)))
    line = np.outer(np.linspace(0, 1, 50), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="one line"):
        fit_plane_robust(line)


def test_sheet_points_lie_on_the_board_plane_and_project_back():
    T = POSES[2]
    uv = np.array([[100.0, 120.0], [320.0, 240.0], [600.0, 400.0]])
    P = sheet_points(uv, CAM, T)
    np.testing.assert_allclose(P @ T[:3, 2], T[:3, 2] @ T[:3, 3], atol=1e-12)
    np.testing.assert_allclose(CAM.project(P)[0], uv, atol=1e-6)


def test_board_point_mask_keeps_the_border_and_white_squares_only():
    T = _pose(0, 0, 0, np.array([0.0, 0.0, 0.4]))
    sq = BOARD.square
    xy = np.array([[-2.0, 1.5],   # white border: kept
                   [-4.0, 1.5],   # beyond the region (3 squares): dropped
                   [0.5, 0.5],    # square (0, 0): dark ((c + r) even)
                   [1.5, 0.5],    # square (1, 0): white, centre: kept
                   [1.05, 0.5]])  # white but 0.05 squares from an edge: dropped
    P = np.c_[xy * sq, np.zeros(len(xy))] @ T[:3, :3].T + T[:3, 3]
    image = _render(T, N_TRUE, -1.0, np.random.default_rng(0))  # no laser in view
    keep = board_point_mask(P, T, BOARD, image, CAM, SheetOptions())
    assert keep.tolist() == [True, False, False, True, False]
    # without an image only the edges count; a negative edge keeps the whole pattern
    assert board_point_mask(P, T, BOARD, None, CAM).tolist() == [True, False, True, True, False]
    every = SheetOptions(pattern_edge_squares=-1.0)
    assert board_point_mask(P, T, BOARD, image, CAM, every).tolist() == [True, False, True,
                                                                        True, True]


def test_board_border_region_ends_where_the_border_ends():
    T = _pose(5, -10, 2, np.array([0.0, 0.0, 0.45]))  # the whole board in view
    # a narrow border (2 squares beyond the inner corners: 1 beyond the pattern) on a
    # table only 10 % darker than it, as the simulator's board lies
    image = _render(T, N_TRUE, D_TRUE, np.random.default_rng(2), border=(2.0, 2.0),
                    room=0.9 * 0.85 * 180.0)
    x0, x1, y0, y1 = board_border_region(image, T, BOARD, CAM, SheetOptions())
    # the border ends at -2 and cols - 1 + 2 (a quarter square inside, one band of slack)
    assert -1.75 - 0.13 <= x0 <= -1.75 + 0.01 and 8.75 - 0.01 <= x1 <= 8.75 + 0.13
    assert -1.75 - 0.13 <= y0 <= -1.75 + 0.01 and 6.75 - 0.01 <= y1 <= 6.75 + 0.13
    # a wide border: the configured margins
    wide = _render(T, N_TRUE, D_TRUE, np.random.default_rng(2))
    assert board_border_region(wide, T, BOARD, CAM, SheetOptions()) == (-3.0, 10.0, -2.0, 7.0)


def test_board_poses_from_handeye_chain():
    rng = np.random.default_rng(1)
    X = laser_transform_from_params(0.01, 0.02, 0.1, 0.1, 0.2, 0.3)  # any rigid transform
    T_bt = laser_transform_from_params(0.5, 0.1, 0.0, 1.0, 0.1, -0.2)
    T_bf = np.stack([laser_transform_from_params(*rng.normal(0, 0.3, 6)) for _ in range(4)])
    T_ct = board_poses_from_handeye(T_bf, X, T_bt)
    for k in range(4):
        np.testing.assert_allclose(T_bf[k] @ X @ T_ct[k], T_bt, atol=1e-12)


def test_still_views_picks_the_view_with_the_board_at_the_same_place():
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(9) * 20.0 + 100, np.arange(6) * 20.0 + 80),
                    -1).reshape(-1, 2)
    frame = grid + rng.normal(0, 0.05, grid.shape)
    frame[[10, 11, 12]] += 2.0  # the corners under the line moved
    frames = [frame, frame + 50.0, frame, None]
    s = 1_000_000_000
    t_frames = np.array([10, 20, 30, 40]) * s
    still = grid + rng.normal(0, 0.05, grid.shape)
    views = [still,                              # 0.25 s before frame 0, same place
             grid + [0.8, 0.0],                  # frame 0's time too, the board moved 0.8 px
             frame + 50.0 + [0.3, 0.0],          # beside frame 1: within 0.5 px
             still,                              # 2 s before frame 2: too long ago
             still,                              # frame 3: its board not found
             still, None]                        # None: not a candidate
    t_views = np.array([9.75, 10.1, 20.25, 28.0, 39.9, 30.1, 30.0]) * s
    t_views[5] = 33 * s  # out of frame 2's window
    got = still_views(t_frames, frames, t_views, views, max_s=1.0, max_px=0.5)
    np.testing.assert_array_equal(got, [0, 2, -1, -1])
    assert (still_views(t_frames, frames, t_views, views, max_s=0.0, max_px=0.5) == -1).all()
    assert still_views(t_frames, frames, t_views, views, max_s=1.0, max_px=0.2)[1] == -1


# ---------------------------------------------------------------------------- calibrate_sheet
def _frames(poses, seed: int = 0):
    rng = np.random.default_rng(seed)
    return [_render(T, N_TRUE, D_TRUE, rng) for T in poses]


def test_calibrate_sheet_on_rendered_frames_recovers_the_sheet(tmp_path):
    images = _frames(POSES) + [np.zeros((480, 640), np.uint8)]
    poses = list(POSES) + [None]  # a frame whose board was not found
    ref = laser_pose_from_plane(N_TRUE, D_TRUE)
    res = calibrate_sheet(iter(images), CAM, poses, SheetOptions(), target=BOARD,
                          reference=ref, source="synthetic.mcap")
    assert _angle_deg(res.plane.normal, N_TRUE) < 0.03
    assert abs(res.plane.offset_m - D_TRUE) * 1e3 < 0.03
    assert res.rms_mm < 0.1
    assert res.left_out == {len(POSES): "board not found"}
    assert res.used == list(range(len(POSES)))
    assert res.tilt_spread_deg > 20
    # the pose: its sheet is the plane, the six parameters are its eq. 11 parameters
    n, d = laser_plane_in_camera(res.T_camera_laser)
    np.testing.assert_allclose(n, res.plane.normal * np.sign(n @ res.plane.normal), atol=1e-12)
    six = res.six_parameters
    back = laser_transform_from_params(*(six[k] for k in ("dx", "dy", "dz", "phi", "theta",
                                                          "psi")))
    np.testing.assert_allclose(back, res.T_camera_laser, atol=1e-9)
    assert res.summary()["n_inliers"] > 500


def test_calibrate_sheet_leaves_out_a_frame_with_a_wrong_board_pose():
    images = _frames(POSES)
    poses = list(POSES)
    wrong = poses[3].copy()
    wrong[:3, 3] += wrong[:3, 2] * 0.004  # the board 4 mm farther than it is
    poses[3] = wrong
    res = calibrate_sheet(images, CAM, poses, target=BOARD, source="synthetic.mcap")
    assert "frame residual outlier" in res.left_out[3]
    assert _angle_deg(res.plane.normal, N_TRUE) < 0.03
    assert abs(res.plane.offset_m - D_TRUE) * 1e3 < 0.03


def test_calibrate_sheet_boards_in_one_plane_is_degenerate():
    # the board slid within one plane: every stripe is the same line of the sheet
    base = POSES[0]
    poses = []
    for s in (-0.02, 0.0, 0.02, 0.04):
        t = base.copy()
        t[:3, 3] += s * base[:3, 1]  # along the board's own y axis
        poses.append(t)
    with pytest.raises(CalibrationError, match=r"synthetic\.mcap.*frames \[0, 1, 2, 3\].*one "
                       r"line.*more tilts"):
        calibrate_sheet(_frames(poses), CAM, poses, target=BOARD, source="synthetic.mcap")


def test_calibrate_sheet_too_few_frames_names_the_reasons():
    poses = [POSES[0], None, None]
    images = _frames([POSES[0]]) + [np.zeros((480, 640, 3), np.uint8)] * 2
    with pytest.raises(CalibrationError, match=r"1 usable laser frames.*board not found 2"):
        calibrate_sheet(images, CAM, poses, target=BOARD, source="synthetic.mcap")
    with pytest.raises(ValueError, match="target"):
        calibrate_sheet(images, CAM, poses)


# ---------------------------------------------------------------------------- real srv file
@pytest.mark.skipif(not SRV.exists(), reason=f"real recording {SRV} not present (it lives "
                    "in the shared folder, outside the project)")
def test_real_srv_laser_plane():
    """Intrinsics from every 6th board view (OpenCV), the board's pose in every other laser
    frame (detected there, solvePnP), then our sheet: within the independent run's 0.45 mm,
    from more boards than its 25, and 2.6 deg from the published nominal laser (the
    README: the nominal is off by 2.6 deg). Measured: 0.134 px from 26 views, 39 boards,
    0.27 mm RMS, 0.08 deg from the whole recording's sheet, 2.38 deg from the nominal.

    The board is found with OpenCV's classic detector directly (fast check, cornerSubPix):
    robo3d.calibration.target.detect_board (sector-based refinement) takes ~0.5 s a frame
    here, beyond this test's budget; the workflow's run with it on all frames gives
    0.327 mm from 76 boards."""
    cv2 = pytest.importorskip("cv2")
    from robo3d.config import default_config
    from robo3d.recording.reader import read_recording
    from robo3d.stripes import StripeOptions

    rec = read_recording(SRV, roles=("views", "laser"))
    board = _Board(8, 6, 0.04)
    g = np.mgrid[0:board.rows, 0:board.cols]
    obj = np.c_[g[1].ravel(), g[0].ravel(), np.zeros(board.cols * board.rows)] * board.square
    flags = (cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
             | cv2.CALIB_CB_FAST_CHECK)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)

    def corners(image):
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        ok, c = cv2.findChessboardCorners(grey, (board.cols, board.rows), flags)
        return cv2.cornerSubPix(grey, c, (5, 5), (-1, -1), crit) if ok else None

    found = [c for c in (corners(rec.decode(m)) for m in rec.views[::6]) if c is not None]
    rms, K, D, _, _ = cv2.calibrateCamera([obj.astype(np.float32)] * len(found), found,
                                          (640, 480), None, None)
    assert rms < 0.3
    cam = CameraModel("camera", 640, 480, K, D.ravel())
    frames = rec.laser_frames[::2]
    images = [rec.decode(m) for m in frames]
    poses = []
    for im in images:
        c = corners(im)
        if c is None:
            poses.append(None)
            continue
        _, rv, tv = cv2.solvePnP(obj, c, K, D)
        t = np.eye(4)
        t[:3, :3], t[:3, 3] = cv2.Rodrigues(rv)[0], tv.ravel()
        poses.append(t)
    nominal = rec.tf.lookup("camera", "laser", np.array([frames[0].timestamp_ns]))[0]
    res = calibrate_sheet(images, cam, poses, SheetOptions(), target=board,
                          stripe_options=StripeOptions.from_config(default_config()["stripes"]),
                          encoded=frames[0].data, reference=nominal, source=str(SRV),
                          frame_ids=range(0, len(rec.laser_frames), 2))
    assert res.colour == "green"
    assert res.rms_mm < 0.45
    assert len(res.used) >= 25
    assert res.plane.rms_all_mm < 0.6
    assert 2.2 < _angle_deg(res.plane.normal, laser_plane_in_camera(nominal)[0]) < 3.0
    # the whole recording's sheet (all 121 frames, SB detector, measured once):
    # n = (0.90992, -0.13986, 0.39049), d = 167.02 mm
    assert _angle_deg(res.plane.normal, np.array([0.90992, -0.13986, 0.39049])) < 0.2
    assert abs(res.plane.offset_m * 1e3 - 167.02) < 1.0
    assert all(i % 2 == 0 for i in res.left_out)
