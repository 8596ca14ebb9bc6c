"""Keyframe anchors: every Gaussian records the mapped frame that seeded it, and the map follows corrected keyframe
poses (``Mapper.apply_pose_corrections``)."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from gausslite.gaussians import GaussianMap
from gausslite.mapping.config import LearningRates, MapperConfig, deep_merge
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.model import GaussianModel
from tests._scenes import plane_frame

H, W = 40, 56


def _cfg(**kw) -> MapperConfig:
    base = dict(mode="uniform", seeding={"seeds_per_frame": 400, "coverage": False}, iters_per_frame=8, warmup_iters=4,
                backend="warp", densify={"enabled": False})
    return MapperConfig.model_validate(deep_merge(base, kw))


def _mapped(cfg: MapperConfig, n: int = 3) -> Mapper:
    m = Mapper(cfg)
    for i in range(n):
        m.map_frame(plane_frame(i, 0.04 * i, H, W))
    return m


def _rigid(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def test_seeds_are_anchored_to_their_frame_and_anchors_survive_eviction_and_checkpoints():
    m = _mapped(_cfg(budget={"max_gaussians": 700}))  # the budget binds: later seeds evict earlier Gaussians
    anchors, ids = m.model.anchors, m.model.ids
    assert anchors.shape == (len(m.model),) and set(anchors.tolist()) <= {0, 1, 2}
    assert sum(s.n_evicted for s in m.stats) > 0
    before = dict(zip(ids.tolist(), anchors.tolist()))
    m.map_frame(plane_frame(3, 0.12, H, W))
    for i, a in zip(m.model.ids.tolist(), m.model.anchors.tolist()):
        assert a == before.get(i, 3)  # kept rows keep their anchor, new seeds take frame 3
    assert int((m.model.anchors == 3).sum()) == m.stats[-1].n_seeds
    m2 = Mapper(_cfg(budget={"max_gaussians": 700}))
    m2.load_state_dict(m.state_dict())
    assert torch.equal(m2.model.anchors, m.model.anchors)
    assert m2.input_poses.keys() == m.input_poses.keys()
    m2.load_map(m.gmap)  # a map from outside: unanchored
    assert bool((m2.model.anchors == -1).all())


def test_density_control_children_inherit_their_parents_anchor():
    m = _mapped(_cfg(densify={"enabled": True, "split_scale_m": 1e-6, "grad_threshold": 1e-9}), n=1)
    n = len(m.model)
    m.model.anchors = torch.arange(n, dtype=torch.int64)  # a distinct anchor per row
    m.strategy.grad_accum = torch.ones(n)
    m.strategy.grad_count = torch.ones(n)
    m.strategy.budget = 10 * n
    stats = m.strategy.densify_and_prune()
    assert stats["split"] == n
    counts = torch.bincount(m.model.anchors, minlength=n)
    assert torch.equal(counts, torch.full((n,), 2)) or (stats["prune"] and bool((counts <= 2).all()))
    model = GaussianModel(LearningRates())
    model.set_map(m.gmap.subset(slice(0, 2)), None, new_anchor=5)
    model.set_map(model.to_map().append(m.gmap.subset(slice(0, 1))), torch.tensor([1, 0, -1]), new_anchor=7)
    assert model.anchors.tolist() == [5, 5, 7]


@pytest.mark.parametrize("refine", [False, True])
def test_moved_keyframes_gaussians_render_identically_from_the_moved_camera(refine):
    """Keyframe 1 moved by a known rigid transform: its anchored Gaussians (made anisotropic and turned first, so
    that their rotations matter) render from the new pose exactly as they did from the old one; the other keyframes'
    Gaussians do not move; the keyframe store, the correction record and ``keyframe_poses`` take the new pose."""
    m = _mapped(_cfg(pose={"refine": refine}))
    assert (m.poses is None) == (not refine)
    rows = m.model.anchors == 1
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        m.model.params["quats"][rows] = torch.randn(int(rows.sum()), 4, generator=g)
        m.model.params["log_scales"][rows] = torch.log(torch.tensor([0.06, 0.02, 0.005])).expand(int(rows.sum()), 3)
    old = m.keyframe_poses()[1]
    new = _rigid([0.05, -0.12, 0.08], [0.1, -0.05, 0.2]) @ old
    intr = plane_frame(1).intrinsics
    before = m.render(old, intr.K, W, H, subset=rows)
    others = m.model.params["means"][~rows].detach().clone()
    others_q = m.model.params["quats"][~rows].detach().clone()
    assert float(before.alpha.mean()) > 0.25  # the test sees the keyframe's Gaussians (about 0.3)
    assert m.apply_pose_corrections({1: new}) == int(rows.sum())
    after = m.render(new, intr.K, W, H, subset=rows)
    np.testing.assert_allclose(after.color.numpy(), before.color.numpy(), atol=2e-3)
    np.testing.assert_allclose(after.alpha.numpy(), before.alpha.numpy(), atol=2e-3)
    np.testing.assert_allclose(after.depth.numpy(), before.depth.numpy(), atol=5e-3)
    assert not np.allclose(m.render(old, intr.K, W, H, subset=rows).color.numpy(), before.color.numpy(), atol=0.05)
    assert torch.equal(m.model.params["means"][~rows], others)
    assert torch.equal(m.model.params["quats"][~rows], others_q)
    np.testing.assert_allclose(m.keyframe_poses()[1], new, atol=1e-12)
    np.testing.assert_allclose(m.pose_of(1, m.input_poses[1]), new, atol=1e-12)
    np.testing.assert_allclose(m.keyframes[1].c2w.numpy(), new, atol=1e-12)
    np.testing.assert_allclose(m.keyframe_poses()[0], m.input_poses[0], atol=1e-12)
    assert m.apply_pose_corrections({1: new, 0: m.keyframe_poses()[0]}) == 0  # nothing changed: nothing moves
    m.map_frame(plane_frame(3, 0.12, H, W))  # mapping goes on after a correction
    assert m.optimize(n_iters=3) == 3


def test_pose_corrections_reject_unknown_frames_and_non_rigid_poses():
    m = _mapped(_cfg(), n=2)
    with pytest.raises(KeyError):
        m.apply_pose_corrections({7: np.eye(4)})
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError):
        m.apply_pose_corrections({1: bad})
    with pytest.raises(ValueError):
        m.apply_pose_corrections({1: np.full((4, 4), np.nan)})


def test_moving_rows_turns_them_and_restarts_their_adam_moments():
    model = GaussianModel(LearningRates())
    g = GaussianMap.from_points(torch.tensor([[1.0, 0.0, 2.0], [0.0, 1.0, 2.0]]), torch.rand(2, 3), 0.05)
    model.set_map(g)
    model.params["means"].grad = torch.ones(2, 3)
    model.params["quats"].grad = torch.ones(2, 4)
    model.step()
    T = _rigid([0.0, 0.0, np.pi / 2], [0.5, 0.0, 0.0])
    moved_from = model.params["means"][0].detach().clone()
    model.move_rows(torch.tensor([0]), T)
    np.testing.assert_allclose(model.params["means"][0].detach().numpy(),
                               T[:3, :3] @ moved_from.numpy() + T[:3, 3], atol=1e-6)
    R = Rotation.from_quat(np.roll(model.params["quats"][0].detach().numpy(), -1)).as_matrix()
    q1 = np.roll(model.params["quats"][1].detach().numpy(), -1)
    np.testing.assert_allclose(R, T[:3, :3] @ Rotation.from_quat(q1).as_matrix(), atol=1e-5)
    st = model.optimizer.state[model.params["means"]]
    assert float(st["exp_avg"][0].abs().sum()) == 0.0 and float(st["exp_avg"][1].abs().sum()) > 0.0
    with pytest.raises(ValueError):
        model.move_rows(torch.tensor([0]), np.diag([1.0, 1.0, 2.0, 1.0]))
