"""Calibration core (robo3d.calibration: target, intrinsics, hand-eye) against a truth we
generate: a known camera with plumb_bob distortion, a known board pose in ``base``, a
known hand-eye and robot poses; corners projected by OpenCV (the independent oracle) with
noise, or a board rendered into an image for the detector."""

from __future__ import annotations

import types

import numpy as np
import pytest

from robo3d.calibration import (
    BoardDetection,
    DetectOptions,
    HandEyeOptions,
    IntrinsicsOptions,
    Target,
    board_points,
    board_scatter_mm,
    calibrate_intrinsics,
    detect_board,
    handeye_closed_form,
    project_plumb_bob,
    refine_handeye,
    target_from_recording,
)
from robo3d.calibration.intrinsics import rvec_tvec_to_T
from robo3d.errors import CalibrationError, RecordingError

cv2 = pytest.importorskip("cv2")

W, H = 1280, 960
K_TRUE = np.array([[1400.0, 0.0, 645.3], [0.0, 1395.0, 478.9], [0.0, 0.0, 1.0]])
D_TRUE = np.array([-0.12, 0.08, 0.0007, -0.0005, -0.02])
TARGET = Target(12, 9, 0.02)             # cols + rows odd: no half-turn symmetry
NOISE_PX = 0.07                          # per coordinate (0.1 px RMS): SB corners on real boards


def _rot(axis, deg):
    return rvec_tvec_to_T(np.asarray(axis, float)[None] / np.linalg.norm(axis)
                          * np.radians(deg), np.zeros((1, 3)))[0]


def _look_at(eye, centre, roll_deg):
    """T_base_camera of a camera at ``eye`` looking at ``centre`` (optical z forward)."""
    z = centre - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1) @ _rot([0, 0, 1], roll_deg)[:3, :3]
    T[:3, 3] = eye
    return T


@pytest.fixture(scope="module")
def cell():
    """A robot cell: board standing in base, camera on the flange, 20 views."""
    rng = np.random.default_rng(7)
    T_bt = np.eye(4)  # board upright, facing -x of base, 0.6 m in front of the robot
    T_bt[:3, :3] = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]).T @ np.eye(3)
    T_bt[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float).T.T
    T_bt[:3, 3] = [0.9, 0.12, 0.6]
    X = _rot([0.3, -0.2, 1.0], 95.0)
    X[:3, 3] = [0.045, -0.032, 0.11]
    centre = T_bt[:3, :3] @ np.array([5.5 * 0.02, 4 * 0.02, 0.0]) + T_bt[:3, 3]
    normal = -T_bt[:3, 2]  # from the board towards the cameras
    T_bf, T_ct = [], []
    while len(T_bf) < 25:
        d = normal + rng.normal(0, 0.45, 3)
        d /= np.linalg.norm(d)
        if d @ normal < np.cos(np.radians(40)):
            continue
        eye = centre + d * rng.uniform(0.35, 0.6)
        T_bc = _look_at(eye, centre + rng.normal(0, 0.02, 3), rng.uniform(-40, 40))
        Tct = np.linalg.inv(T_bc) @ T_bt
        uv = cv2.projectPoints(board_points(TARGET), cv2.Rodrigues(Tct[:3, :3])[0],
                               Tct[:3, 3], K_TRUE, D_TRUE)[0].reshape(-1, 2)
        if uv.min() < 20 or uv[:, 0].max() > W - 20 or uv[:, 1].max() > H - 20:
            continue
        T_bf.append(T_bc @ np.linalg.inv(X))
        T_ct.append(Tct)
    T_bf, T_ct = np.array(T_bf), np.array(T_ct)
    obj = board_points(TARGET)
    uv_true = np.stack([cv2.projectPoints(obj, cv2.Rodrigues(t[:3, :3])[0], t[:3, 3], K_TRUE,
                                          D_TRUE)[0].reshape(-1, 2) for t in T_ct])
    uv = uv_true + rng.normal(0, NOISE_PX, uv_true.shape)
    # the robot reports its poses with a small error (0.05 mm, 0.005 deg)
    noise = rvec_tvec_to_T(rng.normal(0, np.radians(0.005), (len(T_bf), 3)),
                           rng.normal(0, 0.05e-3, (len(T_bf), 3)))
    return types.SimpleNamespace(T_bt=T_bt, X=X, T_bf=T_bf, T_bf_reported=T_bf @ noise,
                                 T_ct=T_ct, uv=uv, uv_true=uv_true)


def _dets(uv):
    return [BoardDetection(u.copy(), "synthetic", "") for u in uv]


def _pose_error(T, T_ref):
    dR = T[:3, :3].T @ T_ref[:3, :3]
    ang = np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(T[:3, 3] - T_ref[:3, 3]) * 1000), float(ang)


# ---------------------------------------------------------------------------- target
def test_board_points_shape_and_order():
    p = board_points(TARGET)
    assert p.shape == (108, 3)
    assert np.allclose(p[1], [0.02, 0, 0]) and np.allclose(p[12], [0, 0.02, 0])
    assert np.all(p[:, 2] == 0)


def test_target_from_recording_errors_name_the_file():
    rec = types.SimpleNamespace(path="/x/calib.mcap", metadata={})
    with pytest.raises(RecordingError, match=r"/x/calib.mcap.*robo3d.target"):
        target_from_recording(rec)
    rec.metadata = {"robo3d.target": {"type": "checkerboard", "cols": "8", "rows": "x",
                                      "square": "0.04"}}
    with pytest.raises(RecordingError, match="/x/calib.mcap"):
        target_from_recording(rec)
    rec.metadata["robo3d.target"].update(rows="6", moving="true")
    t = target_from_recording(rec)
    assert (t.cols, t.rows, t.square, t.moving) == (8, 6, 0.04, True)
    with pytest.raises(ValueError, match="square boards"):
        Target(7, 7, 0.02)


def _render(Hm_board_to_image, target, ss=4, sq_px=24):
    """A board image: texture (squares of sq_px, dark where c + r is even, see
    robo3d.calibration.target) warped by a homography, supersampled, blurred, noisy;
    returns the image and the true corners (pixels)."""
    S = sq_px * ss
    cols, rows = target.cols, target.rows
    Wt, Ht = (cols + 3) * S, (rows + 3) * S
    yy, xx = np.mgrid[0:Ht, 0:Wt]
    a, b = xx // S - 2, yy // S - 2
    dark = ((a + b) % 2 == 0) & (a >= -1) & (a <= cols - 1) & (b >= -1) & (b <= rows - 1)
    tex = np.where(dark, 35, 215).astype(np.uint8)
    # texture continuous coords (corner (c, r) at ((c+2) S, (r+2) S)) -> image continuous
    A = Hm_board_to_image @ np.diag([1.0 / S, 1.0 / S, 1.0]) @ np.array(
        [[1, 0, -2 * S], [0, 1, -2 * S], [0, 0, 1.0]])
    Tt = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1.0]])
    Hss = np.linalg.inv(Tt) @ np.diag([ss, ss, 1.0]) @ A @ Tt
    big = cv2.warpPerspective(tex, Hss, (640 * ss, 480 * ss), flags=cv2.INTER_LINEAR,
                              borderValue=120)
    img = cv2.GaussianBlur(cv2.resize(big, (640, 480), interpolation=cv2.INTER_AREA), (0, 0), 0.7)
    img = np.clip(img + np.random.default_rng(3).normal(0, 2, img.shape), 0, 255).astype(np.uint8)
    grid = np.concatenate([board_points(target)[:, :2] / target.square,
                           np.ones((target.n_corners, 1))], axis=1)
    q = grid @ Hm_board_to_image.T
    return img, q[:, :2] / q[:, 2:] - 0.5


@pytest.mark.parametrize(("roll_deg", "refine"), [(10.0, "sb"), (170.0, "subpix"), (-100.0, "sb")])
def test_detection_accuracy_and_canonical_order(roll_deg, refine):
    """The detected corners lie on the true ones, in board_points order, whichever way the
    board is turned in the image (the classic detector starts at either end)."""
    tg = Target(9, 6, 0.03)
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    sc = 38.0  # pixels per square
    Hm = np.array([[sc * c, -sc * s, 0], [sc * s, sc * c, 0], [0.0002, 0.0001, 1.0]])
    centre = Hm @ np.array([4.0, 2.5, 1.0])
    Hm[:2, 2] = np.array([320.0, 240.0]) * (Hm[2] @ [4.0, 2.5, 1.0]) - (centre[:2] - Hm[:2, 2] * 1)
    img, truth = _render(Hm, tg)
    det = detect_board(img, tg, DetectOptions(corner_refine=refine))
    assert det.ok, det.reason
    err = np.linalg.norm(det.corners - truth, axis=1)
    assert err.max() < 0.25 and np.sqrt(np.mean(err ** 2)) < 0.1
    assert det.method.endswith(refine)


def test_detection_reasons():
    tg = Target(9, 6, 0.03)
    blank = np.full((120, 160), 128, np.uint8)
    det = detect_board(blank, tg)
    assert det.corners is None and det.reason.startswith("not found") and "blurred" in det.reason
    # a board cut by the image border
    Hm = np.array([[40.0, 0, -30], [0, 40.0, 100], [0, 0, 1]])
    img, _ = _render(Hm, tg)
    det = detect_board(img, tg)
    assert not det.ok and det.reason


# ------------------------------------------------------------------------- intrinsics
def test_intrinsics_recover_the_camera(cell):
    uv = cell.uv.copy()
    uv[5] += np.random.default_rng(1).normal(0, 3.0, uv[5].shape)  # a bad view
    dets = _dets(uv)
    dets.append(BoardDetection(None, "", "not found"))
    res = calibrate_intrinsics(dets, TARGET, (W, H), IntrinsicsOptions())
    assert 5 in res.rejected and "outlier" in res.rejected[5]
    assert res.rejected[len(uv)] == "not found"
    assert len(res.used) == len(uv) - 1 and 5 not in res.used
    f_err = np.abs(np.diag(res.K)[:2] / np.diag(K_TRUE)[:2] - 1)
    assert f_err.max() < 1e-3
    assert np.linalg.norm(res.K[:2, 2] - K_TRUE[:2, 2]) < 1.0
    assert abs(res.rms_px - NOISE_PX * np.sqrt(2)) < 0.02  # the corners' noise, no model error
    assert res.per_view_rms.shape == (len(uv) - 1,)
    assert res.std["fx"] > 0 and abs(res.K[0, 0] - K_TRUE[0, 0]) < 5 * res.std["fx"]
    # the board's pose in each used view
    for k, i in enumerate(res.used):
        mm, deg = _pose_error(res.T_camera_target[k], cell.T_ct[i])
        assert mm < 1.0 and deg < 0.1


def test_intrinsics_degenerate_input(cell):
    with pytest.raises(CalibrationError, match=r"calib.mcap.*2 usable board views"):
        calibrate_intrinsics(_dets(cell.uv[:2]) + [BoardDetection(None, "", "not found")],
                             TARGET, (W, H), recording="calib.mcap")
    # the same board, parallel to the image in every view, only moved
    obj = board_points(TARGET)
    uv = [cv2.projectPoints(obj, np.zeros(3), np.array([x, y, z]), K_TRUE, D_TRUE)[0]
          .reshape(-1, 2) for x, y, z in [(-0.15, -0.1, 0.6), (0.0, -0.05, 0.7),
                                          (-0.1, 0.0, 0.5), (-0.05, -0.1, 0.8)]]
    with pytest.raises(CalibrationError, match="parallel"):
        calibrate_intrinsics(_dets(np.array(uv)), TARGET, (W, H), recording="calib.mcap")


# --------------------------------------------------------------------------- hand-eye
@pytest.mark.parametrize("method", ["tsai", "park"])
def test_closed_form_exact(cell, method):
    X = handeye_closed_form(cell.T_bf, cell.T_ct, method)
    mm, deg = _pose_error(X, cell.X)
    assert mm < 1e-6 and deg < 1e-5


def test_handeye_recovered_from_noisy_views(cell):
    intr = calibrate_intrinsics(_dets(cell.uv), TARGET, (W, H))
    res = refine_handeye(cell.T_bf_reported, cell.uv, TARGET, intr.K, intr.D,
                         intr.T_camera_target, HandEyeOptions())
    mm, deg = _pose_error(res.T_flange_camera, cell.X)
    assert mm < 0.3 and deg < 0.05
    cf_mm, cf_deg = _pose_error(res.closed_form["T_flange_camera"], cell.X)
    assert cf_mm < 1.0 and cf_deg < 0.1
    bt_mm, bt_deg = _pose_error(res.T_base_target, cell.T_bt)
    assert bt_mm < 0.3 and bt_deg < 0.05
    # through the robot chain: the corners' noise and the robot's (0.05 mm, 0.005 deg)
    assert res.rms_px < 0.35 and res.per_view_rms.shape == (len(cell.uv),)
    assert res.board_scatter_mm <= res.closed_form["board_scatter_mm"] + 1e-6
    assert res.board_scatter_mm < 0.2
    # with intrinsics refined too
    res2 = refine_handeye(cell.T_bf_reported, cell.uv, TARGET, intr.K, intr.D,
                          intr.T_camera_target, HandEyeOptions(refine_intrinsics=True))
    assert np.abs(np.diag(res2.K)[:2] / np.diag(K_TRUE)[:2] - 1).max() < 1e-3
    assert _pose_error(res2.T_flange_camera, cell.X)[0] < 0.3


def test_board_scatter_definition():
    rng = np.random.default_rng(0)
    p = rng.normal(0, 1e-3, (10, 3))
    Tbf = np.repeat(np.eye(4)[None], 10, axis=0)
    Tct = np.repeat(np.eye(4)[None], 10, axis=0)
    Tct[:, :3, 3] = p
    assert board_scatter_mm(Tbf, np.eye(4), Tct) == pytest.approx(
        np.sqrt(np.sum(np.var(p, axis=0))) * 1000)


def test_handeye_degenerate_motions(cell):
    # pure translations: no rotation at all
    Tbf = np.repeat(cell.T_bf[:1], 6, axis=0).copy()
    Tbf[:, :3, 3] += np.random.default_rng(0).normal(0, 0.05, (6, 3))
    Tct = np.linalg.inv(Tbf @ cell.X) @ cell.T_bt
    with pytest.raises(CalibrationError, match=r"k.mcap.*too few rotations"):
        handeye_closed_form(Tbf, Tct, recording="k.mcap")
    # rotations about one axis only (a turntable-like motion of the flange)
    Tbf = np.array([cell.T_bf[0] @ _rot([0, 0, 1], a) for a in (0, 10, 25, 40, 60)])
    Tct = np.linalg.inv(Tbf @ cell.X) @ cell.T_bt
    with pytest.raises(CalibrationError, match="nearly parallel"):
        handeye_closed_form(Tbf, Tct, recording="k.mcap")
    with pytest.raises(CalibrationError, match="at least 3"):
        handeye_closed_form(cell.T_bf[:2], cell.T_ct[:2])


def test_projection_matches_opencv(cell):
    obj = board_points(TARGET)
    T = cell.T_ct[3]
    ours = project_plumb_bob(obj @ T[:3, :3].T + T[:3, 3], K_TRUE, D_TRUE)
    assert np.abs(ours - cell.uv_true[3]).max() < 1e-9


def test_every_corner_order_becomes_the_canonical_one():
    """Whatever corner a detector starts at and whichever way it runs the rows, the
    canonical order is the same (colour rule for an asymmetric board, handedness)."""
    from robo3d.calibration.target import _canonical

    tg = Target(9, 6, 0.03)
    Hm = np.array([[36.0, 4.0, 150.0], [-3.0, 35.0, 120.0], [0.0001, 0.0002, 1.0]])
    img, truth = _render(Hm, tg)
    grid = truth.reshape(tg.rows, tg.cols, 2)
    for g in (grid, grid[::-1], grid[:, ::-1], grid[::-1, ::-1]):
        out, reason = _canonical(g.copy(), img, tg)
        assert not reason
        assert np.array_equal(out.reshape(-1, 2), truth)
    # a symmetric board (cols + rows even): the x axis points to the image's right
    ts = Target(8, 6, 0.03)
    img_s, truth_s = _render(Hm, ts)
    gs = truth_s.reshape(ts.rows, ts.cols, 2)
    outs = [_canonical(g.copy(), img_s, ts)[0] for g in (gs, gs[::-1], gs[:, ::-1], gs[::-1, ::-1])]
    assert all(np.array_equal(o, outs[0]) for o in outs)
    assert outs[0][0, -1, 0] > outs[0][0, 0, 0]
    # a folded grid is refused with a reason
    bad = grid.copy()
    bad[:, :4] = bad[::-1, :4]
    assert "flipped" in _canonical(bad, img, tg)[1]


def test_opencv_reference_is_opencv_intrinsics_with_tsai(cell):
    from robo3d.calibration import opencv_reference

    ref = opencv_reference(cell.T_bf_reported, cell.uv, TARGET, (W, H))
    assert ref["handeye"] == ("cv2.calibrateHandEye" if hasattr(cv2, "calibrateHandEye")
                              else "robo3d tsai")
    mm, deg = _pose_error(ref["T_flange_camera"], cell.X)
    assert mm < 1.0 and deg < 0.1
    assert abs(ref["rms_px"] - NOISE_PX * np.sqrt(2)) < 0.02
    assert 0 < ref["board_scatter_mm"] < 0.3


def test_symmetric_board_read_turned_in_some_views_is_made_consistent(cell):
    """A half-turn symmetric board (cols + rows even) read from the other end in some
    views: the flips are found from the robot's motion and undone before the hand-eye."""
    from robo3d.calibration import half_turn, resolve_board_flips

    sym = Target(12, 8, 0.02)
    obj = board_points(sym)
    turned = np.zeros(len(cell.T_ct), bool)
    turned[[3, 7, 8, 15]] = True
    Tct = cell.T_ct.copy()
    Tct[turned] = Tct[turned] @ half_turn(sym)[None]
    assert np.array_equal(resolve_board_flips(cell.T_bf, Tct, sym), turned)
    assert not resolve_board_flips(cell.T_bf, Tct, TARGET).any()  # asymmetric: never
    # corners of the turned views in their (reversed) reading: refine_handeye undoes it
    uv = np.stack([cv2.projectPoints(obj, cv2.Rodrigues(t[:3, :3])[0], t[:3, 3], K_TRUE,
                                     D_TRUE)[0].reshape(-1, 2) for t in cell.T_ct])
    uv[turned] = uv[turned][:, ::-1]
    res = refine_handeye(cell.T_bf, uv, sym, K_TRUE, D_TRUE, Tct)
    assert np.array_equal(res.flipped, turned)
    mm, deg = _pose_error(res.T_flange_camera, cell.X)
    assert mm < 1e-3 and deg < 1e-4
