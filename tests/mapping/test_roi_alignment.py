"""ROI-phase iterations align their own views (pose and exposure, ``pose.roi_phase``), and tasks that reach a region
the map already covers join it (``seeding.adopt``): a task first seen after the map reached its cap, a new task."""

import dataclasses

import numpy as np
import pytest

from gausslite.mapping.config import MapperConfig, deep_merge
from gausslite.mapping.mapper import Mapper
from tests._scenes import plane_frame

H, W = 40, 56


def _roi(h=H, w=W) -> np.ndarray:
    r = np.zeros((h, w), bool)
    r[10:30, 14:42] = True
    return r


def _cfg(roi_phase: bool = True, roi_lr_scale: float = 1.0, pose_refine: bool = True, exposure_comp: bool = True,
         **kw) -> MapperConfig:
    base = dict(mode="gausslite", seeding={"seeds_per_frame": 800}, iters_per_frame=10, warmup_iters=10, backend="warp",
                pose={"refine": pose_refine, "lr_rot": 2e-3, "lr_trans": 4e-3, "roi_phase": roi_phase,
                      "roi_lr_scale": roi_lr_scale},
                sensor={"exposure_comp": exposure_comp})
    base = deep_merge(base, kw)  # a group given as a keyword is merged key by key
    cfg = MapperConfig(**base)
    cfg.densify.enabled = False
    return cfg


def _mapped_with_a_wrong_pose_and_exposure(cfg: MapperConfig):
    """Frames 0–2 of the plane at their true poses, then frame 3 given 6 cm off along x and 20 % darker."""
    m = Mapper(cfg)
    for i in range(3):
        m.map_frame(plane_frame(i, 0.04 * i, H, W), _roi())
    fr = plane_frame(3, 0.12, H, W)
    fr.rgb[:] = (fr.rgb * 0.8).astype(np.uint8)
    fr.c2w[0, 3] = 0.12 + 0.06
    m.map_frame(fr, _roi())
    return m, fr


@pytest.mark.parametrize("roi_phase", [True, False])
def test_roi_phase_iterations_step_the_pose_and_exposure_of_their_view(roi_phase):
    """ROI-phase steps on frame 3 alone: with ``pose.roi_phase`` its pose moves towards the truth and its exposure
    darkens; without, ROI-phase steps leave both where the full-image warm-up left them. Frame 0 never moves."""
    m, fr = _mapped_with_a_wrong_pose_and_exposure(_cfg(roi_phase=roi_phase))
    i3 = [k.frame_id for k in m.keyframes].index(3)
    err0 = abs(m.pose_of(3, fr.c2w)[0, 3] - 0.12)
    theta0 = m.sensor.exposure.of(3).copy()
    for _ in range(60):
        m.step(m.keyframes.load(i3, m.device), active_phase=True)
    err1 = abs(m.pose_of(3, fr.c2w)[0, 3] - 0.12)
    theta1 = m.sensor.exposure.of(3)
    if roi_phase:
        assert err1 < 0.6 * err0, (err0, err1)
        assert theta1[:3].mean() < theta0[:3].mean() - 0.02  # the view is darker than the map: log gain < 0
    else:
        assert err1 == err0 and np.array_equal(theta1, theta0)
    np.testing.assert_array_equal(m.pose_of(0, np.eye(4)), np.eye(4))  # the gauge keyframe
    np.testing.assert_array_equal(m.sensor.exposure.of(0), np.zeros(6))
    # the refined pose reaches the keyframe store (the fine-tune and keyframe uploads read it)
    np.testing.assert_allclose(m.keyframes[i3].c2w.numpy(), m.pose_of(3, fr.c2w))


def test_roi_lr_scale_shrinks_roi_phase_pose_steps():
    moved = {}
    for scale in (1.0, 0.1):
        m, fr = _mapped_with_a_wrong_pose_and_exposure(_cfg(roi_lr_scale=scale))
        i3 = [k.frame_id for k in m.keyframes].index(3)
        before = m.pose_of(3, fr.c2w)[0, 3]
        for _ in range(5):
            m.step(m.keyframes.load(i3, m.device), active_phase=True)
        moved[scale] = abs(m.pose_of(3, fr.c2w)[0, 3] - before)
    assert 0 < moved[0.1] < 0.3 * moved[1.0]


def _cap_cfg(**kw) -> MapperConfig:
    return _cfg(pose_refine=False, exposure_comp=False, seeding={"seeds_per_frame": 300}, budget={"max_gaussians": 500},
                warmup_iters=5, **kw)


def _late_mapper(cfg: MapperConfig) -> Mapper:
    """Six frames without a task: the map reaches its cap of 500 with no task Gaussian."""
    m = Mapper(cfg)
    for i in range(6):
        m.map_frame(plane_frame(i, 0.01 * i, H, W), None)
    assert len(m.model) == 500 and not bool(m.model.active.any())
    return m


def test_a_task_first_seen_at_the_cap_adopts_the_gaussians_drawing_it_and_seeds_it():
    """The held-out failure: the task's object comes into view after the map reached its cap. Adoption makes the
    Gaussians that draw its pixels task Gaussians, gap seeds replace background at the cap, and the next keyframe
    runs ROI-phase iterations and counts κ."""
    m = _late_mapper(_cap_cfg(performance={"render_threads": 2}))  # the band split this scene was tuned with
    st = m.map_frame(plane_frame(6, 0.06, H, W), _roi())
    assert st.n_adopted > 0 and st.n_gap_seeds > 0
    assert st.n_evicted >= st.n_gap_seeds  # at the cap the ROI seeds replaced background
    assert len(m.model) == 500
    assert st.active_iters > 0  # already this keyframe runs ROI-phase iterations
    st2 = m.map_frame(plane_frame(7, 0.07, H, W), _roi())
    assert st2.active_iters > 0 and int(m.model.kappa.max()) > 0
    # the task's Gaussians cover the ROI now: no further adoption or gap seeds
    assert st2.n_gap_seeds == 0 and st2.n_adopted == 0
    roi_px = m.render(plane_frame(7, 0.07, H, W).c2w, plane_frame(0).intrinsics.K, W, H,
                      subset=m.model.active).alpha.numpy()[_roi()]
    assert float(np.mean(roi_px > 0.5)) > 0.9


def test_without_adoption_a_late_task_never_engages():
    """``seeding.adopt: false`` reproduces the failure: the ROI is covered by the map, so no ROI seed, no task
    Gaussian, no ROI-phase iteration."""
    cfg = _cap_cfg()
    cfg.seeding.adopt = False
    m = _late_mapper(cfg)
    st = m.map_frame(plane_frame(6, 0.06, H, W), _roi())
    st2 = m.map_frame(plane_frame(7, 0.07, H, W), _roi())
    assert st.n_roi_seeds == 0 and st2.n_roi_seeds == 0
    assert not bool(m.model.active.any()) and st.active_iters == st2.active_iters == 0


def test_adoption_leaves_large_background_splats_and_uniform_mode_out():
    m = _late_mapper(_cap_cfg())
    # one huge splat over the whole view: most of its weight falls outside the ROI, so it is not adopted
    import torch

    p = m.model.params
    with torch.no_grad():
        p["log_scales"][0] = np.log(3.0)
        p["opacity_logits"][0] = 5.0
        p["means"][0] = torch.tensor([0.0, 0.0, 1.0])
    m.map_frame(plane_frame(6, 0.06, H, W), _roi())
    assert not bool(m.model.active[0])
    u = _late_mapper(_cap_cfg(mode="uniform"))
    st = u.map_frame(plane_frame(6, 0.06, H, W), _roi())
    assert st.n_adopted == 0 and st.n_gap_seeds == 0 and not bool(u.model.active.any())


def test_retarget_forgets_the_task_and_keeps_the_map():
    m = Mapper(_cap_cfg())
    for i in range(3):
        m.map_frame(plane_frame(i, 0.02 * i, H, W), _roi())
    n, means = len(m.model), m.model.params["means"].detach().clone()
    assert bool(m.model.active.any()) and int(m.model.kappa.max()) > 0
    assert any(k.sees_roi for k in m.keyframes)
    m.retarget()
    assert len(m.model) == n and bool((m.model.params["means"] == means).all())
    assert not bool(m.model.active.any()) and int(m.model.kappa.max()) == 0
    assert not any(k.sees_roi for k in m.keyframes)
    # the new task's region joins through adoption on the next frame
    other = np.zeros((H, W), bool)
    other[2:12, 2:20] = True
    st = m.map_frame(plane_frame(3, 0.06, H, W), other)
    assert st.n_adopted + st.n_gap_seeds > 0 and bool(m.model.active.any())


def test_keyframe_store_roi_replacement_checks_the_size():
    m = Mapper(_cap_cfg())
    m.map_frame(plane_frame(0, 0.0, H, W), None)
    m.keyframes.set_roi(0, _roi())
    assert m.keyframes[0].roi_box == (14, 10, 42, 30)
    with pytest.raises(ValueError, match="does not match"):
        m.keyframes.set_roi(0, np.ones((H + 1, W), bool))
    m.keyframes.set_roi(0, np.zeros((H, W), bool))
    assert m.keyframes[0].roi is None and not m.keyframes[0].sees_roi


def test_roi_phase_exposure_can_stay_with_full_image_iterations():
    """``pose.roi_phase_exposure: false``: ROI-phase steps move the pose but leave the exposure response alone."""
    cfg = _cfg()
    cfg.pose.roi_phase_exposure = False
    m, fr = _mapped_with_a_wrong_pose_and_exposure(cfg)
    i3 = [k.frame_id for k in m.keyframes].index(3)
    pose0, theta0 = m.pose_of(3, fr.c2w).copy(), m.sensor.exposure.of(3).copy()
    for _ in range(10):
        m.step(m.keyframes.load(i3, m.device), active_phase=True)
    assert not np.array_equal(m.pose_of(3, fr.c2w), pose0)
    assert np.array_equal(m.sensor.exposure.of(3), theta0)
