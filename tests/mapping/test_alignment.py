"""Keyframe alignment (``pose.align: depth``, gausslite.mapping.alignment): a keyframe's depth registered to the
depth of the keyframes before it, against exact depth ray-cast in a room of boxes."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.camera import Intrinsics, rotation_angle
from gausslite.datasets.base import Frame
from gausslite.mapping.alignment import KeyframeAligner, depth_cloud
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.poses import pose_delta_np

K = Intrinsics(fx=160.0, fy=160.0, cx=79.5, cy=59.5, width=160, height=120)
ROOM = (np.array([-2.0, -1.2, -2.0]), np.array([2.0, 1.2, 3.0]))  # the camera is inside: depth where rays leave it
BOXES = [(np.array([-0.6, 0.2, 1.0]), np.array([0.1, 1.2, 1.6])),  # solid boxes: depth where rays enter them
         (np.array([0.5, -0.3, 1.8]), np.array([1.1, 1.2, 2.3])),
         (np.array([-1.5, 0.6, 0.2]), np.array([-1.0, 1.2, 0.7]))]


def raycast(c2w: np.ndarray) -> np.ndarray:
    """(H, W) float32 depth (metres along the camera z) of the room of boxes seen from ``c2w``."""
    v, u = np.mgrid[0:K.height, 0:K.width]
    d_cam = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones_like(u, float)], -1).reshape(-1, 3)
    d = d_cam @ c2w[:3, :3].T
    o = c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (ROOM[0] - o) / d, (ROOM[1] - o) / d
        t = np.nanmin(np.maximum(t1, t2), axis=1)  # leaving the room
        for lo, hi in BOXES:
            a, b = (lo - o) / d, (hi - o) / d
            tn, tf = np.nanmax(np.minimum(a, b), axis=1), np.nanmin(np.maximum(a, b), axis=1)
            hit = (tn <= tf) & (tn > 0)
            t = np.where(hit & (tn < t), tn, t)
    return (t * d_cam[:, 2]).reshape(K.height, K.width).astype(np.float32)


def look(eye, target) -> np.ndarray:
    """(4, 4) c2w at ``eye`` looking at ``target`` (OpenCV axes, world y down)."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


def frame(i: int, c2w_true: np.ndarray, c2w_given: np.ndarray) -> Frame:
    rgb = np.full((K.height, K.width, 3), 128, np.uint8)
    return Frame(i, i / 2.0, rgb, raycast(c2w_true), np.asarray(c2w_given, np.float64), K)


def path(n: int = 8) -> list[np.ndarray]:
    return [look(np.array([-0.4 + 0.1 * i, 0.0, -0.8]), np.array([0.2 * i - 0.5, 0.5, 2.0])) for i in range(n)]


def error(P: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    D = np.linalg.inv(T) @ P
    return float(np.linalg.norm(D[:3, 3])), float(np.degrees(rotation_angle(D[:3, :3])))


def test_depth_cloud_points_lie_on_the_surface_with_normals_facing_the_camera():
    c2w = look(np.zeros(3), np.array([0.0, 0.3, 2.0]))
    pts, nrm = depth_cloud(frame(0, c2w, c2w), 2)
    assert len(pts) > 1000 and pts.shape == nrm.shape
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-9)
    assert np.all(np.einsum("ij,ij->i", nrm, pts) < 0)
    # the back wall (world z = 3) seen head-on: its points' normals point back along the view
    w = pts @ c2w[:3, :3].T + c2w[:3, 3]
    back = np.abs(w[:, 2] - 3.0) < 1e-6
    assert back.sum() > 100
    # all but the corners where it meets another surface (a neighbour within 5 % of the depth)
    assert np.mean(np.abs((nrm[back] @ c2w[:3, :3].T)[:, 2] + 1.0) < 1e-6) > 0.99
    with pytest.raises(ValueError):
        depth_cloud(frame(0, c2w, c2w), 0)


@pytest.mark.parametrize("dt, drot_deg", [(0.01, 0.5), (0.03, 1.5)])
def test_a_keyframe_a_centimetre_off_is_aligned_to_a_millimetre(dt, drot_deg):
    poses = path(3)
    al = KeyframeAligner(voxel_m=0.02, width=80)
    for i in range(2):
        al.add(frame(i, poses[i], poses[i]))
    rng = np.random.default_rng(0)
    xi = np.concatenate([rng.normal(size=3), rng.normal(size=3)])
    xi[:3] *= np.radians(drot_deg) / np.linalg.norm(xi[:3])
    xi[3:] *= dt / np.linalg.norm(xi[3:])
    given = poses[2] @ pose_delta_np(xi)
    assert error(given, poses[2])[0] > 0.9 * dt
    res = al.align(frame(2, poses[2], given), given, lambda k: poses[k])
    assert res.accepted and res.fitness > 0.8
    t, r = error(res.c2w, poses[2])
    assert t < 2e-3 and r < 0.1
    assert res.trans_m > 0.5 * dt  # the correction it reports is the one it made


def test_no_model_no_overlap_or_a_correction_beyond_the_gate_keeps_the_start_pose():
    poses = path(3)
    al = KeyframeAligner()
    first = al.align(frame(0, poses[0], poses[0]), poses[0], lambda k: poses[k])
    assert not first.accepted and np.array_equal(first.c2w, poses[0])
    al.add(frame(0, poses[0], poses[0]))
    away = poses[0].copy()
    away[:3, 3] += [30.0, 0.0, 0.0]  # a view of nothing the model holds
    far = al.align(frame(1, away, away), away, lambda k: poses[k])
    assert not far.accepted and np.array_equal(far.c2w, away)
    tight = KeyframeAligner(max_trans_m=0.002)
    tight.add(frame(0, poses[0], poses[0]))
    off = poses[1].copy()
    off[:3, 3] += [0.02, 0.0, 0.0]
    res = tight.align(frame(1, poses[1], off), off, lambda k: poses[k])
    assert not res.accepted and np.array_equal(res.c2w, off) and res.trans_m > 0.01


def test_the_model_follows_the_poses_the_map_holds():
    """A stored keyframe placed elsewhere (a pose graph moved it) moves the model with it: the new keyframe is
    aligned to where the model now is."""
    poses = path(2)
    al = KeyframeAligner()
    al.add(frame(0, poses[0], poses[0]))
    shift = np.eye(4)
    shift[:3, 3] = [0.03, -0.01, 0.02]
    moved = {0: shift @ poses[0]}
    res = al.align(frame(1, poses[1], poses[1]), poses[1], lambda k: moved[k])
    assert res.accepted
    t, r = error(res.c2w, shift @ poses[1])
    assert t < 2e-3 and r < 0.1


def test_state_dict_round_trip_and_the_keyframe_bound():
    poses = path(4)
    al = KeyframeAligner(max_keyframes=2)
    for i in range(4):
        al.add(frame(i, poses[i], poses[i]))
    assert sorted(al.clouds) == [0, 3]  # the first keyframe (the gauge) and the newest
    other = KeyframeAligner()
    other.load_state_dict(al.state_dict())
    assert sorted(other.clouds) == [0, 3]
    for k in (0, 3):
        np.testing.assert_allclose(other.clouds[k][0], al.clouds[k][0], atol=1e-6)
    with pytest.raises(ValueError):
        other.load_state_dict({"clouds": {0: (np.zeros((3, 3)), np.zeros((2, 3)))}})


def test_the_mapper_aligns_keyframes_records_their_corrections_and_resumes():
    poses = path(4)
    rng = np.random.default_rng(1)
    cfg = MapperConfig(mode="uniform", iters_per_frame=2, warmup_iters=2, seed=0,
                       pose={"align": "depth"})
    m = Mapper(cfg)
    given = [poses[0]] + [p @ pose_delta_np(np.r_[rng.normal(0, 0.005, 3), rng.normal(0, 0.008, 3)])
                          for p in poses[1:]]
    for i in range(3):
        st = m.map_frame(frame(i, poses[i], given[i]))
        assert (st.align_accepted is None) == (i == 0)
    for i in (1, 2):
        t, r = error(m.pose_of(i, m.input_poses[i]), poses[i])
        assert t < 2e-3 and r < 0.1, (i, t, r)
    resumed = Mapper(cfg)
    resumed.load_state_dict(m.state_dict())
    assert sorted(resumed.aligner.clouds) == [0, 1, 2]
    st = resumed.map_frame(frame(3, poses[3], given[3]))
    assert st.align_accepted
    t, r = error(resumed.pose_of(3, resumed.input_poses[3]), poses[3])
    assert t < 2e-3 and r < 0.1


def test_alignment_off_leaves_the_poses_as_given():
    poses = path(2)
    m = Mapper(MapperConfig(mode="uniform", iters_per_frame=1, warmup_iters=1, seed=0))
    assert m.aligner is None
    off = poses[1].copy()
    off[:3, 3] += 0.01
    for i, p in enumerate((poses[0], off)):
        st = m.map_frame(frame(i, poses[i], p))
        assert st.align_accepted is None
    np.testing.assert_array_equal(m.pose_of(1, m.input_poses[1]), off)
