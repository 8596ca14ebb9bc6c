"""Keyframe placement against the frozen map (gausslite.mapping.tracking; ``pose.track_*``)."""

import logging

import numpy as np
import torch

from gausslite.mapping.config import MapperConfig, deep_merge
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.tracking import FrameTracker, robust_weights, tracking_factor
from tests._scenes import plane_frame

H, W = 40, 56
TRUE_X = 0.12


def _cfg(**kw) -> MapperConfig:
    base = dict(mode="uniform", seeding={"seeds_per_frame": 1500}, iters_per_frame=20, warmup_iters=15,
                backend="warp", densify={"enabled": False},
                pose={"track_iters": 40, "track_lr_rot": 5e-3, "track_lr_trans": 5e-3})
    return MapperConfig.model_validate(deep_merge(base, kw))


def _three_frames(cfg: MapperConfig) -> Mapper:
    m = Mapper(cfg)
    for i in range(3):
        m.map_frame(plane_frame(i, 0.04 * i, H, W))
    return m


def _off_by(dx: float):
    """Frame 3 of the plane (true camera x = TRUE_X) given ``dx`` metres off along x."""
    fr = plane_frame(3, TRUE_X, H, W)
    fr.c2w[0, 3] = TRUE_X + dx
    return fr


def test_placement_pulls_a_wrong_pose_to_the_map_before_seeding_without_refinement():
    """Refinement off, placement on: frame 3's 5 cm error is tracked out before it seeds (the map is frozen
    meanwhile), the correction is kept in the record every render of the frame reads, and the training step refines
    nothing."""
    m = _three_frames(_cfg())
    assert m.step.poses is None and m.poses is not None
    means = m.model.params["means"].detach().clone()
    fr = _off_by(0.05)
    res = m.tracker.track(fr)
    assert torch.equal(m.model.params["means"], means)  # the map is frozen while tracking
    assert res.accepted and res.iters > 0 and res.loss < res.loss0
    assert abs(res.c2w[0, 3] - TRUE_X) < 0.01, res.c2w[0, 3]
    m.map_frame(fr)
    st = m.stats[-1]
    assert st.track_accepted and st.track_iters > 0 and 0.04 < st.track_trans_m < 0.06
    assert abs(m.pose_of(3, fr.c2w)[0, 3] - TRUE_X) < 0.01
    np.testing.assert_allclose(m.keyframes[3].c2w.numpy(), m.pose_of(3, fr.c2w))


def test_the_gate_rejects_a_large_correction_and_keeps_the_input_pose(caplog):
    m = _three_frames(_cfg(pose={"track_max_trans_m": 0.02}))
    fr = _off_by(0.05)
    with caplog.at_level(logging.INFO, logger="gausslite.mapping.tracking"):
        m.map_frame(fr)
    st = m.stats[-1]
    assert st.track_accepted is False and st.track_trans_m > 0.02
    np.testing.assert_array_equal(m.pose_of(3, fr.c2w), fr.c2w)
    assert any("exceeds the gate" in r.getMessage() for r in caplog.records)


def test_tracking_stops_at_the_deadline_and_on_convergence():
    m = _three_frames(_cfg())
    fr = _off_by(0.05)
    res = m.tracker.track(fr, deadline=m.clock.now())  # the deadline has passed: one step only
    assert res.iters == 1 and res.stop == "deadline"
    at_truth = m.tracker.track(plane_frame(3, TRUE_X, H, W))
    assert at_truth.stop == "converged" and at_truth.iters < 40
    assert at_truth.trans_m < 0.01


def test_a_keyframe_budget_gives_the_tracker_its_share_of_the_time():
    """Under a keyframe budget on the deterministic clock, tracking stops at pose.track_budget_frac of it."""
    cfg = _cfg(budget_clock="work", pose={"track_iters": 200, "track_budget_frac": 0.1, "track_converge": 0.0})
    m = _three_frames(cfg)
    m.map_frame(_off_by(0.05), time_budget_s=0.05)
    short = m.stats[-1].track_iters
    m2 = _three_frames(cfg.model_copy(update={"pose": cfg.pose.model_copy(update={"track_budget_frac": 0.5})}))
    m2.map_frame(_off_by(0.05), time_budget_s=0.05)
    assert 1 <= short < m2.stats[-1].track_iters < 200


def test_placement_at_a_reduced_resolution():
    """A 112×80 view tracked at 56×40 (track_width 56) still finds the pose."""
    assert tracking_factor(320, 160) == 2 and tracking_factor(160, 160) == 1 and tracking_factor(56, None) == 1
    m = Mapper(_cfg(pose={"track_width": 56}))
    for i in range(3):
        m.map_frame(plane_frame(i, 0.04 * i, 2 * H, 2 * W))
    fr = plane_frame(3, TRUE_X, 2 * H, 2 * W)
    fr.c2w[0, 3] = TRUE_X + 0.05
    kf = m.tracker.view(fr, None)
    assert (kf.width, kf.height) == (W, H)
    res = m.tracker.track(fr)
    assert res.accepted and abs(res.c2w[0, 3] - TRUE_X) < 0.01, res.c2w[0, 3]


def test_robust_weights_down_weight_outliers_and_the_task_region_weighs_more_in_gausslite_mode():
    r = torch.full((4, 4), 0.01)
    r[0, 0] = 1.0
    mask = torch.ones(4, 4, dtype=torch.bool)
    w = robust_weights(r, mask, 3.0)
    assert float(w[0, 0]) < 0.01 and float(w[1, 1]) > 0.9
    assert torch.equal(robust_weights(r, mask, 0.0), torch.ones(4, 4))
    roi = np.zeros((H, W), bool)
    roi[10:20, 10:30] = True
    fr = plane_frame(0, 0.0, H, W)
    g = Mapper(_cfg(mode="gausslite"))
    u = Mapper(_cfg())
    assert bool(g.tracker.view(fr, roi).roi.any()) and u.tracker.view(fr, roi).roi is None
    # the task's pixels count 1 + track_roi_weight times: a residual only there moves the loss more with the weight
    m = _three_frames(_cfg(mode="gausslite"))
    kf = m.tracker.view(fr, roi)
    with torch.no_grad():
        out = m.sensor.render_view(kf.c2w, kf.K, kf.width, kf.height, 0, None)
    out.color[torch.from_numpy(roi)] += 0.2
    losses = []
    for wt in (0.0, 4.0):
        tracker = FrameTracker(m.cfg.model_copy(update={"pose": m.cfg.pose.model_copy(
            update={"track_roi_weight": wt, "track_robust_k": 0.0})}), m.sensor, m.clock)
        losses.append(float(tracker.loss(out, kf)[0]))
    assert losses[1] > losses[0] * 1.5
