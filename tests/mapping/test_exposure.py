"""Per-keyframe exposure compensation (gausslite.mapping.exposure; MonoGS-style affine response)."""

import dataclasses

import numpy as np
import torch

from gausslite.evaluation import render_map, score_view
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.exposure import ExposureModel, apply_exposure, invert_exposure
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.poses import VectorAdam
from tests._scenes import plane_frame

H, W = 40, 56


def test_apply_and_invert_are_inverse_and_differentiable():
    rgb = np.random.default_rng(0).uniform(0.2, 0.6, (5, 7, 3)).astype(np.float32)
    theta = np.array([0.2, -0.1, 0.05, 0.03, -0.02, 0.0])
    seen = apply_exposure(torch.from_numpy(rgb), torch.tensor(theta)).numpy()
    np.testing.assert_allclose(seen[..., 0], rgb[..., 0] * np.exp(0.2) + 0.03, rtol=1e-6)
    np.testing.assert_allclose(invert_exposure(seen, theta), rgb, atol=1e-6)
    th = torch.zeros(6, requires_grad=True)
    apply_exposure(torch.from_numpy(rgb), th).sum().backward()
    # d/da_c at 0 = sum of channel c; d/db_c = pixel count
    np.testing.assert_allclose(th.grad[:3].numpy(), rgb.reshape(-1, 3).sum(0), rtol=1e-5)
    np.testing.assert_allclose(th.grad[3:].numpy(), [35.0] * 3)


def test_model_gauge_inheritance_nearest_and_state():
    ex = ExposureModel(lr=0.1)
    ex.register(0, ex.initial(0), fixed=True)
    ex.step(0, torch.ones(6))  # the gauge keyframe does not move
    np.testing.assert_array_equal(ex.params[0], np.zeros(6))
    ex.register(2, ex.initial(2))
    ex.step(2, torch.tensor([1.0, -1.0, 0.0, 0.0, 0.0, 2.0]))
    np.testing.assert_allclose(ex.params[2], [-0.1, 0.1, 0.0, 0.0, 0.0, -0.1], atol=1e-9)  # Adam's first step: lr·sign
    ex.step(2, torch.tensor([float("nan")] * 6))  # a non-finite gradient changes nothing
    np.testing.assert_allclose(ex.params[2], [-0.1, 0.1, 0.0, 0.0, 0.0, -0.1], atol=1e-9)
    ex.register(5, ex.initial(5))
    np.testing.assert_array_equal(ex.params[5], ex.params[2])  # a new keyframe starts from the latest
    np.testing.assert_array_equal(ex.of(3), ex.params[2])  # a non-keyframe takes the nearest keyframe's
    ex.step(99, torch.ones(6))  # unknown keyframe: nothing
    assert 99 not in ex.params
    other = ExposureModel(lr=0.1)
    other.load_state_dict(ex.state_dict())
    assert other.fixed == {0} and set(other.params) == {0, 2, 5}
    np.testing.assert_array_equal(other.params[2], ex.params[2])


def test_a_frame_between_keyframes_takes_the_interpolated_response():
    ex = ExposureModel(interpolate=True)
    ex.register(0, np.zeros(6), fixed=True)
    ex.register(4, np.array([0.4, 0.0, -0.4, 0.1, 0.0, 0.0]))
    np.testing.assert_allclose(ex.of(1), [0.1, 0.0, -0.1, 0.025, 0.0, 0.0])  # a quarter of the way
    np.testing.assert_array_equal(ex.of(4), ex.params[4])
    np.testing.assert_array_equal(ex.of(9), ex.params[4])  # after the last keyframe: the last one's
    ex.interpolate = False
    np.testing.assert_array_equal(ex.of(1), ex.params[0])


def test_vector_adam_matches_torch_adam():
    adam = VectorAdam(np.full(3, 0.05))
    p = torch.zeros(3, requires_grad=True)
    opt = torch.optim.Adam([p], lr=0.05, eps=1e-12)
    mine = np.zeros(3)
    for k in range(5):
        g = np.array([1.0, -2.0, 0.5]) * (k + 1)
        mine += adam.delta(7, g)
        p.grad = torch.tensor(g, dtype=torch.float32)
        opt.step()
    np.testing.assert_allclose(mine, p.detach().numpy(), atol=1e-6)


def _darkened(i: int, gain: float):
    fr = plane_frame(i, 0.02 * i, H, W)
    rgb = np.clip(fr.rgb.astype(np.float32) * gain, 0, 255).round().astype(np.uint8)
    return dataclasses.replace(fr, rgb=rgb)


def _map(exposure: bool, pose_refine: bool = False):
    cfg = MapperConfig(mode="uniform", seeding={"seeds_per_frame": 1500}, iters_per_frame=40, backend="warp",
                       sensor={"exposure_comp": exposure, "exposure_lr": 0.02}, pose={"refine": pose_refine}, seed=0)
    cfg.densify.enabled = False
    m = Mapper(cfg)
    frames = [_darkened(0, 1.0), _darkened(1, 1.0), _darkened(2, 0.6), _darkened(3, 0.6)]
    for fr in frames:
        m.map_frame(fr)
    m.optimize(n_iters=120)
    return m, frames


def test_mapper_learns_a_darker_keyframe_and_keeps_the_first_exposure():
    """Frames 2–3 are the plane at 0.6× brightness (auto-exposure). With compensation their response
    learns a gain near log 0.6 while the map keeps frame 0's colours; without it the shared colours are
    pulled between the two exposures, and both the bright and the dark frames score worse."""
    m_on, frames = _map(True)
    m_off, _ = _map(False)
    assert m_on.sensor.exposure.fixed == {0}
    np.testing.assert_array_equal(m_on.sensor.exposure.params[0], np.zeros(6))
    gain3 = np.exp(m_on.sensor.exposure.params[3][:3])
    assert np.all(np.abs(gain3 - 0.6) < 0.12), gain3
    assert np.all(np.abs(np.exp(m_on.sensor.exposure.params[1][:3]) - 1.0) < 0.12)
    psnr_on = [score_view(m_on.render_frame(fr), fr).psnr for fr in frames]
    psnr_off = [score_view(m_off.render_frame(fr), fr).psnr for fr in frames]
    assert np.mean(psnr_on) > np.mean(psnr_off) + 3.0, (psnr_on, psnr_off)
    assert min(psnr_on[0], psnr_on[3]) > max(psnr_off[0], psnr_off[3]), (psnr_on, psnr_off)
    # the map itself stays in frame 0's exposure: its plain render (no response) matches frame 0
    assert score_view(m_on.render(frames[0].c2w, frames[0].intrinsics.K, W, H), frames[0]).psnr > psnr_off[0]


def test_exposure_survives_checkpoint_restore():
    m, frames = _map(True)
    state = m.state_dict()
    m2 = Mapper(m.cfg)
    m2.load_state_dict(state)
    assert m2.sensor.exposure.fixed == {0}
    for fid, th in m.sensor.exposure.params.items():
        np.testing.assert_array_equal(m2.sensor.exposure.params[fid], th)
    a = m.render_frame(frames[3]).color
    b = m2.render_frame(frames[3]).color
    torch.testing.assert_close(a, b)


def test_another_map_seen_by_this_camera_gets_the_robots_exposure_and_corrections():
    """``Mapper.seen_by_this_camera``: a map rendered through the robot's camera model (its exposure response,
    refined corrections, sensor model) is rendered exactly as the robot renders its own map for scoring; the same
    map at the bare sensor pose without the response is not (the darker frame then scores worse)."""
    m, frames = _map(True, pose_refine=True)
    other = m.gmap  # e.g. a team map holding this robot's rows: here the robot's own map, copied
    seen = m.seen_by_this_camera(other)
    for fr in frames:
        np.testing.assert_allclose(seen(fr).color.numpy(), m.render_frame(fr).color.numpy(), atol=1e-6)
    bare = score_view(render_map(other, frames[3]), frames[3]).psnr  # how a fused map is scored at the sensor's pose
    assert score_view(seen(frames[3]), frames[3]).psnr > bare + 2.0
    # the renderer holds a copy of the map: changing the map it was given does not change what it renders
    before = seen(frames[1]).color.clone()
    with torch.no_grad():
        other.colors.zero_()
    np.testing.assert_array_equal(seen(frames[1]).color.numpy(), before.numpy())

