"""Poses stay rigid by construction: every pose the tracker, the pose graph and the map's corrections compose is
projected back onto SE(3) (:func:`gausslite.camera.nearest_rigid`), so thousands of composed corrections never trip a
rigidity check, and a check that does trip means a bug."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from gausslite.camera import RIGID_DRIFT_MAX, nearest_rigid
from gausslite.mapping.poses import PoseRefiner, correction_moves
from gausslite.mission.pose_follow import MapFollower


def _pose(rng: np.random.Generator, trans_m: float = 2.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-trans_m, trans_m, 3)
    return T


def _small(rng: np.random.Generator, scale: float) -> np.ndarray:
    """A small rigid motion: rotation vector and translation of about ``scale`` (radians, metres) per axis."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(scale * rng.standard_normal(3)).as_matrix()
    T[:3, 3] = scale * rng.standard_normal(3)
    return T


def _rigidity(T: np.ndarray) -> float:
    R = T[:3, :3]
    return max(float(np.abs(R @ R.T - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0))


def _float32(T: np.ndarray) -> np.ndarray:
    """``T`` as a registration computed in float32 hands it back (Open3D's odometry): rigid to about 1e-7."""
    return T.astype(np.float32).astype(np.float64)


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), noise=st.floats(0.0, 1e-3))
def test_the_nearest_rigid_transform_is_rigid_and_near(seed, noise):
    rng = np.random.default_rng(seed)
    T = _pose(rng)
    off = T.copy()
    off[:3, :3] += noise * rng.standard_normal((3, 3))
    got = nearest_rigid(off)
    assert _rigidity(got) < 1e-12
    assert np.array_equal(got[3], [0.0, 0.0, 0.0, 1.0]) and np.array_equal(got[:3, 3], T[:3, 3])
    assert np.abs(got[:3, :3] - T[:3, :3]).max() <= 10 * noise + 1e-12  # the projection stays near the input
    assert np.allclose(nearest_rigid(got), got, rtol=0.0, atol=1e-14)  # a rigid pose is its own projection


@pytest.mark.parametrize("bad, match", [
    (np.diag([1.0, 1.0, -1.0, 1.0]), "not a proper rotation"),  # a reflection
    (np.diag([1.0, 1.0, 1.5, 1.0]), "not a proper rotation"),  # a scale: no rounding gets there
    (np.full((4, 4), np.nan), "NaN or infinite"),
    (np.eye(3), "expected a 4x4 matrix"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), "last row"),
])
def test_what_is_no_pose_raises_and_names_it(bad, match):
    with pytest.raises(ValueError, match=match):
        nearest_rigid(bad, what="frame 48")
    with pytest.raises(ValueError, match="frame 48"):
        nearest_rigid(bad, what="frame 48")


def test_rounding_drift_is_projected_but_more_is_a_bug():
    R = np.eye(4)
    R[0, 1] = 0.5 * RIGID_DRIFT_MAX  # R Rᵀ off the identity by RIGID_DRIFT_MAX / 2: drift
    assert _rigidity(nearest_rigid(R)) < 1e-12
    R[0, 1] = 2.0 * RIGID_DRIFT_MAX
    with pytest.raises(ValueError):
        nearest_rigid(R)


def test_a_chain_of_float32_registrations_drifts_unless_projected():
    """The mechanism behind a rejected correction: a tracker chains each frame onto its keyframe, c2w = c2w_ref · T,
    with T from a float32 solver. Unprojected, 5,000 such products leave SO(3) far past a 1e-6 check; projected,
    every product is rigid to rounding."""
    rng = np.random.default_rng(1)
    steps = [_float32(_small(rng, 0.01)) for _ in range(5000)]
    raw, projected = np.eye(4), np.eye(4)
    for T in steps:
        raw = raw @ T
        projected = nearest_rigid(projected @ T)
    assert _rigidity(raw) > 1e-6  # what the map's correction rejected mid-mission
    assert _rigidity(projected) < 1e-12
    assert np.abs(projected[:3, 3] - raw[:3, 3]).max() < 1e-2  # the same trajectory, not another one


class _Graph:
    def __init__(self, poses):
        self.nodes = {fid: type("Node", (), {"c2w": c2w})() for fid, c2w in poses.items()}


class _Odometry:
    def __init__(self, poses):
        self.graph = _Graph(poses)
        self.on_correction = None


class _Mapper:
    """The part of the Mapper a loop closure touches: its frames' poses, moved by :func:`correction_moves`."""

    def __init__(self, poses):
        self.poses = dict(poses)
        self.moved = 0

    def keyframe_poses(self):
        return dict(self.poses)

    def apply_pose_corrections(self, new):
        moves = correction_moves(new, self.poses)
        for fid, (_, pose) in moves.items():
            self.poses[fid] = pose
        self.moved += len(moves)
        return len(moves)


def test_thousands_of_loop_closures_move_the_map_and_none_is_rejected():
    """A long camera-only mission: 1,000 pose-graph corrections, each moving 5 keyframes by a small float32-rounded
    transform, composed into the map's poses by the map follower. Every correction applies; every pose stays rigid
    (each keyframe's poses are a chain of 1,000 corrections of their own: more keyframes are more of the same)."""
    rng = np.random.default_rng(2)
    kf_poses = {fid: _pose(rng) for fid in range(5)}
    odo = _Odometry({fid: T.copy() for fid, T in kf_poses.items()})
    follower = MapFollower(odo)
    mapper = _Mapper(kf_poses)
    for fid, T in kf_poses.items():
        result = type("R", (), {"anchor": fid, "T_anchor": np.eye(4), "c2w": T})()
        follower.record(fid, result)
        follower.mapped(fid)
    for _ in range(1000):
        for node in odo.graph.nodes.values():
            step = _small(rng, 1e-3)
            node.c2w = _float32(step @ node.c2w)  # a pose graph's output, rounded as a float32 solver leaves it
        follower.on_correction({})
        assert follower.apply(mapper) == len(kf_poses)
    assert follower.n_rejected == 0 and follower.n_corrections == 1000
    assert max(_rigidity(T) for T in mapper.poses.values()) < 1e-12
    for fid, node in odo.graph.nodes.items():  # the map follows its keyframes to rounding
        assert np.abs(mapper.poses[fid] - node.c2w).max() < 1e-5


def test_a_correction_that_is_no_pose_is_counted_skipped_and_the_rest_apply():
    rng = np.random.default_rng(3)
    kf_poses = {fid: _pose(rng) for fid in range(3)}
    odo = _Odometry({fid: T.copy() for fid, T in kf_poses.items()})
    follower, mapper = MapFollower(odo), _Mapper(kf_poses)
    for fid, T in kf_poses.items():
        follower.record(fid, type("R", (), {"anchor": fid, "T_anchor": np.eye(4), "c2w": T})())
        follower.mapped(fid)
    odo.graph.nodes[0].c2w = np.full((4, 4), np.nan)
    odo.graph.nodes[1].c2w = kf_poses[1] @ _small(rng, 1e-2)
    follower.on_correction({})
    assert follower.apply(mapper) == 1
    assert follower.n_rejected == 1 and np.array_equal(mapper.poses[0], kf_poses[0])
    assert np.allclose(mapper.poses[1], odo.graph.nodes[1].c2w, atol=1e-12)


def test_thousands_of_refinement_steps_keep_the_keyframe_pose_rigid():
    refiner = PoseRefiner(lr_rot=1e-2, lr_trans=1e-2)
    refiner.register(7, np.eye(4))
    c2w = torch.from_numpy(_pose(np.random.default_rng(4)))
    g = torch.Generator().manual_seed(0)
    for _ in range(5000):
        c2w = refiner.step(7, torch.randn(6, dtype=torch.float64, generator=g), c2w)
    assert _rigidity(c2w.numpy()) < 1e-12 and _rigidity(refiner.corrections[7]) < 1e-12
