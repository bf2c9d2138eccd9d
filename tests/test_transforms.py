"""Tests of robo3d.transforms against analytic rotations and trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from robo3d.errors import TransformError
from robo3d.transforms import (
    TransformBuffer,
    euler_to_matrix,
    invert_transform,
    make_transform,
    matrix_to_quat,
    quat_slerp,
    quat_to_matrix,
    rotation_angle_deg,
    transform_points,
)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _random_rotations(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return quat_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))


def test_quaternion_round_trip_every_branch() -> None:
    # random rotations, plus rotations of ~180 degrees about x, y, z (the other three
    # Shepperd branches) and the identity
    rots = list(_random_rotations(200, seed=1))
    rots += [_axis_angle(a, np.pi - 1e-3) for a in np.eye(3)]
    rots += [_axis_angle(a, np.pi) for a in ([1, 1, 0], [0, 1, 1], [1, 0, 1])]
    rots += [np.eye(3)]
    r = np.stack(rots)
    q = matrix_to_quat(r)
    assert q.shape == (len(r), 4)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-14)
    assert np.all(q[:, 3] >= 0)
    assert np.abs(quat_to_matrix(q) - r).max() < 1e-12
    # and quaternion -> matrix -> quaternion, up to sign
    q0 = np.random.default_rng(2).normal(size=(50, 4))
    q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
    q1 = matrix_to_quat(quat_to_matrix(q0))
    assert np.abs(np.abs(np.sum(q0 * q1, axis=1)) - 1).max() < 1e-12


def test_quat_to_matrix_known_value() -> None:
    # 90 degrees about z: x -> y (the FrameTransform example of the Foxglove docs)
    s = np.sqrt(0.5)
    r = quat_to_matrix(np.array([0, 0, s, s]))
    np.testing.assert_allclose(r @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    t = make_transform(np.array([0, 0, s, s]), [1, 2, 0])
    np.testing.assert_allclose(transform_points(t, np.array([[1.0, 0, 0]])), [[1, 3, 0]],
                               atol=1e-15)


def test_slerp_midpoint_and_constant_rate() -> None:
    axis = np.array([1.0, -2.0, 0.5])
    r0 = euler_to_matrix("zyx", [0.2, 0.1, -0.3])
    theta = 1.3
    q0 = matrix_to_quat(r0)
    q1 = matrix_to_quat(r0 @ _axis_angle(axis, theta))
    alphas = np.array([0.0, 0.25, 0.5, 0.9, 1.0])
    q = quat_slerp(np.repeat(q0[None], 5, 0), np.repeat(q1[None], 5, 0), alphas)
    want = np.stack([r0 @ _axis_angle(axis, a * theta) for a in alphas])
    assert np.abs(quat_to_matrix(q) - want).max() < 1e-12
    # the shorter arc, whatever the sign of the second quaternion
    q_neg = quat_slerp(q0[None], -q1[None], np.array([0.5]))
    assert np.abs(quat_to_matrix(q_neg)[0] - want[2]).max() < 1e-12
    # nearly identical quaternions: no division by zero
    qn = quat_slerp(q0[None], q0[None], np.array([0.3]))
    assert np.all(np.isfinite(qn)) and np.abs(quat_to_matrix(qn)[0] - r0).max() < 1e-12


def test_euler_invert_angle() -> None:
    a, b, c = 0.3, -0.4, 1.1
    r = euler_to_matrix("zyx", [a, b, c])
    want = _axis_angle([0, 0, 1], a) @ _axis_angle([0, 1, 0], b) @ _axis_angle([1, 0, 0], c)
    assert np.abs(r - want).max() < 1e-15
    t = make_transform(r, [0.1, -0.2, 0.3])
    assert np.abs(invert_transform(t) @ t - np.eye(4)).max() < 1e-15
    assert rotation_angle_deg(_axis_angle([1, 2, 3], 0.7)) == pytest.approx(np.degrees(0.7),
                                                                           abs=1e-10)
    with pytest.raises(ValueError, match="axis"):
        euler_to_matrix("zyw", [0, 0, 0])


# --------------------------------------------------------------------------- buffer
T0 = 1_700_000_000_000_000_000
DT = 20_000_000
AXIS = np.array([0.0, 0.6, 0.8])
OMEGA = 1.5  # rad/s


def _flange(t_ns: np.ndarray | int) -> np.ndarray:
    s = (np.asarray(t_ns, dtype=np.int64) - T0) / 1e9
    s = np.atleast_1d(s)
    rot = np.stack([_axis_angle(AXIS, OMEGA * x) for x in s])
    return make_transform(rot, np.stack([[0.5 + 0.1 * x, -0.2 * x, 0.3] for x in s]))


T_FLANGE_CAMERA = make_transform(euler_to_matrix("zyx", [0.1, 0.2, -3.0]), [0.0, 0.05, 0.1])
T_CAMERA_LASER = make_transform(euler_to_matrix("zyx", [0.0, 0.5, 0.0]), [0.1, 0.0, 0.0])
T_WORLD_BASE = make_transform(euler_to_matrix("zyx", [1.0, 0.0, 0.0]), [2.0, 0.0, 0.0])


def _buffer(max_gap_ns: int = 50_000_000) -> TransformBuffer:
    buf = TransformBuffer(max_gap_ns=max_gap_ns, path="test.mcap")
    stamps = T0 + DT * np.arange(51)
    poses = _flange(stamps)
    buf.add("base", "flange", stamps, poses[:, :3, 3], matrix_to_quat(poses[:, :3, :3]))
    for parent, child, t in (("flange", "camera", T_FLANGE_CAMERA),
                             ("camera", "laser", T_CAMERA_LASER),
                             ("world", "base", T_WORLD_BASE)):
        buf.add(parent, child, [T0], t[:3, 3], matrix_to_quat(t[:3, :3]), static=True,
                topic="/tf_static")
    return buf


def test_lookup_multi_link_chain() -> None:
    buf = _buffer()
    times = T0 + np.array([0, 7_000_001, 333_333_333, 999_999_999, 1_000_000_000])
    flange = _flange(times)
    got = buf.lookup("base", "laser", times)
    want = flange @ T_FLANGE_CAMERA @ T_CAMERA_LASER
    assert got.shape == (5, 4, 4) and np.abs(got - want).max() < 1e-12
    # through the root and down again: world -> laser, and laser -> world (inverse)
    got = buf.lookup("world", "laser", times)
    assert np.abs(got - T_WORLD_BASE @ want).max() < 1e-12
    inv = buf.lookup("laser", "world", times)
    assert np.abs(inv @ got - np.eye(4)).max() < 1e-12
    # between two static siblings: no time dependence
    assert np.abs(buf.lookup("camera", "laser", times[2]) - T_CAMERA_LASER).max() < 1e-15
    # scalar time gives one matrix
    assert buf.lookup("flange", "flange", T0).shape == (4, 4)
    assert buf.frames == {"world", "base", "flange", "camera", "laser"}


def test_gap_and_range_errors() -> None:
    buf = _buffer(max_gap_ns=15_000_000)  # samples are 20 ms apart
    with pytest.raises(TransformError, match="20.0 ms apart, more than max_pose_gap 15.0 ms") \
            as ei:
        buf.lookup("base", "camera", T0 + 5_000_000)
    assert ei.value.time_ns == T0 + 5_000_000 and ei.value.topic == "/tf"
    assert "test.mcap" in str(ei.value)
    # exactly at a sample is fine even across a wide gap
    got = buf.lookup("base", "flange", T0 + 2 * DT)
    assert np.abs(got - _flange(T0 + 2 * DT)[0]).max() < 1e-15
    with pytest.raises(TransformError, match="time outside the samples of base -> flange"):
        _buffer().lookup("base", "flange", T0 - 1)
    with pytest.raises(TransformError, match="time outside"):
        _buffer().lookup("base", "flange", T0 + 50 * DT + 1)


def test_missing_link_names_frames() -> None:
    buf = _buffer()
    buf.add("tool", "gripper", [T0], [0, 0, 0], [0, 0, 0, 1], static=True)
    with pytest.raises(TransformError, match="missing link between 'tool' and 'world'") as ei:
        buf.lookup("camera", "gripper", T0)
    assert "tool -> gripper" in str(ei.value) and "world -> base -> flange -> camera" in \
        str(ei.value)
    with pytest.raises(TransformError, match="frame 'nowhere' is not in the transform tree"):
        buf.lookup("base", "nowhere", T0)


def test_two_parents_and_duplicates() -> None:
    buf = _buffer()
    with pytest.raises(TransformError, match="two parents"):
        buf.add("world", "flange", [T0], [0, 0, 0], [0, 0, 0, 1])
    # duplicated stamps keep the last sample; unsorted input is sorted
    b = TransformBuffer()
    b.add("a", "b", [30, 10, 20, 20], [[3, 0, 0], [1, 0, 0], [2, 0, 0], [9, 0, 0]],
          np.tile([0, 0, 0, 1.0], (4, 1)))
    stamps, t = b.link_samples("a", "b")
    assert stamps.tolist() == [10, 20, 30]
    assert t[:, 0, 3].tolist() == [1, 9, 3]
    np.testing.assert_allclose(b.lookup("a", "b", 25)[0, 3], 6.0, atol=1e-15)
