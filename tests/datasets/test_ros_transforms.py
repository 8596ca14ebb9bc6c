"""TF buffer, quaternions and pose interpolation (gausslite.ros.transforms)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gausslite.ros.transforms import (
    R_BODY_OPTICAL,
    TFBuffer,
    TFError,
    interpolate_transform,
    invert,
    make_transform,
    quat_to_rot,
    rot_to_quat,
    slerp,
    transform_to_tq,
)


def _rz(a):
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1.0]])


def _T(R, t):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def test_quaternion_round_trip_all_branches():
    rng = np.random.default_rng(0)
    qs = list(rng.normal(size=(50, 4))) + [np.array([1.0, 0, 0, 0]), np.array([0, 1.0, 0, 0]),
                                           np.array([0, 0, 1.0, 0]), np.array([0, 0, 0, 1.0])]
    for q in qs:
        q = q / np.linalg.norm(q)
        R = quat_to_rot(q)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.linalg.det(R) == pytest.approx(1.0)
        q2 = rot_to_quat(R)
        assert np.allclose(q2, q if q[3] >= 0 else -q, atol=1e-12)
    with pytest.raises(ValueError, match="invalid quaternion"):
        quat_to_rot([0, 0, 0, 0])


def test_slerp_and_interpolation_are_exact_for_constant_rate_rotation():
    T0 = _T(_rz(0.0), [0, 0, 0])
    T1 = _T(_rz(1.2), [2.0, -1.0, 0.5])
    for a in (0.0, 0.25, 0.5, 1.0):
        T = interpolate_transform(T0, T1, a)
        assert np.allclose(T[:3, :3], _rz(1.2 * a), atol=1e-12)
        assert np.allclose(T[:3, 3], [2.0 * a, -a, 0.5 * a], atol=1e-12)
    q0, q1 = rot_to_quat(_rz(0.1)), rot_to_quat(_rz(0.1 + 1e-5))  # nearly equal: linear branch
    assert np.allclose(quat_to_rot(slerp(q0, q1, 0.5)), _rz(0.1 + 5e-6), atol=1e-9)
    # shortest arc: q and -q are the same rotation
    assert np.allclose(quat_to_rot(slerp(q0, -rot_to_quat(_rz(0.5)), 0.5)), _rz(0.3), atol=1e-12)


def test_optical_rotation_matches_rep103():
    # optical z (forward) is body x, optical x (right) is body -y, optical y (down) is body -z
    assert np.allclose(R_BODY_OPTICAL @ [0, 0, 1], [1, 0, 0])
    assert np.allclose(R_BODY_OPTICAL @ [1, 0, 0], [0, -1, 0])
    assert np.allclose(R_BODY_OPTICAL @ [0, 1, 0], [0, 0, -1])
    t, q = transform_to_tq(_T(R_BODY_OPTICAL, [0, 0, 0]))
    assert np.allclose(q, [-0.5, 0.5, -0.5, 0.5])  # the quaternion static_transform_publisher writes


def test_tf_buffer_composes_static_and_dynamic_edges_along_the_tree():
    buf = TFBuffer()
    T_map_odom = _T(_rz(0.3), [1.0, 2.0, 0.0])
    T_base_cam = _T(R_BODY_OPTICAL, [0.1, 0.0, 0.5])
    buf.add("/map", "odom", 0.0, T_map_odom, static=True)  # leading slash of ROS 1 recordings
    buf.add("base_link", "camera_optical", 0.0, T_base_cam, static=True)
    buf.add("odom", "base_link", 10.0, _T(_rz(0.0), [0, 0, 0]))
    buf.add("odom", "base_link", 11.0, _T(_rz(1.0), [1.0, 0, 0]))
    buf.add("map", "landmark", 0.0, _T(np.eye(3), [5.0, 0, 0]), static=True)
    assert buf.frames == ["base_link", "camera_optical", "landmark", "map", "odom"]
    T = buf.lookup("map", "camera_optical", 10.5, tolerance=0.6)
    expect = T_map_odom @ _T(_rz(0.5), [0.5, 0, 0]) @ T_base_cam
    assert np.allclose(T, expect, atol=1e-12)
    # lookup between two branches goes through the common ancestor
    T_l_c = buf.lookup("landmark", "camera_optical", 10.5, tolerance=0.6)
    assert np.allclose(T_l_c, invert(_T(np.eye(3), [5.0, 0, 0])) @ expect, atol=1e-12)
    assert np.allclose(buf.lookup("camera_optical", "map", 10.5, 0.6), invert(expect), atol=1e-12)
    # a stamp just outside the samples takes the nearest within tolerance
    assert np.allclose(buf.lookup("odom", "base_link", 11.02, 0.05), _T(_rz(1.0), [1.0, 0, 0]))


def test_tf_buffer_out_of_order_samples_are_sorted():
    buf = TFBuffer()
    buf.add("odom", "base", 2.0, _T(_rz(0.2), [2, 0, 0]))
    buf.add("odom", "base", 1.0, _T(_rz(0.1), [1, 0, 0]))
    assert np.allclose(buf.lookup("odom", "base", 1.5, 0.6)[:3, 3], [1.5, 0, 0])


def test_tf_buffer_errors_name_frames_and_gaps():
    buf = TFBuffer()
    buf.add("map", "odom", 0.0, np.eye(4), static=True)
    buf.add("odom", "base_link", 1.0, np.eye(4))
    buf.add("odom", "base_link", 2.0, np.eye(4))
    buf.add("world", "camera", 0.0, np.eye(4), static=True)
    with pytest.raises(TFError, match=r"does not connect.*'camera' is in the tree rooted at 'world'"):
        buf.lookup("map", "camera", 1.0)
    with pytest.raises(TFError, match=r"'nope' is not in the TF tree"):
        buf.lookup("map", "nope", 1.0)
    with pytest.raises(TFError, match=r"no transform 'odom' -> 'base_link' within 0.05 s of t=5.000000 \(nearest sample 3.000"):
        buf.lookup("map", "base_link", 5.0, tolerance=0.05)
    with pytest.raises(TFError, match="two parents"):
        buf.add("map", "base_link", 1.0, np.eye(4))
    with pytest.raises(TFError, match="both /tf and /tf_static"):
        buf.add("odom", "base_link", 1.0, np.eye(4), static=True)
    assert not buf.can_transform("map", "camera") and buf.can_transform("base_link", "map")
    assert "odom -> base_link (2 samples)" in buf.describe() and "map -> odom (static)" in buf.describe()


def test_make_transform_inverse():
    T = make_transform([1, 2, 3], [0.1, 0.2, 0.3, 0.9])
    assert np.allclose(T @ invert(T), np.eye(4), atol=1e-12)
