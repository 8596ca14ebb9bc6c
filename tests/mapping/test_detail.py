"""The task region at its own resolution (gausslite.mapping.detail): a keyframe keeps a detail crop of its region,
ROI-phase iterations fit it, the region's seeds and ROI views come from the finer pixels, one map."""

import numpy as np
import pytest
import torch

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.datasets.common import downscale_frame
from gausslite.mapping.config import MapperConfig, deep_merge
from gausslite.mapping.detail import DetailView, coarse_index, cut_detail
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.memory import KeyframeStore
from gausslite.mapping.views import keyframe_from_frame

HN, WN = 80, 112  # the detail (native) resolution; the map's is half of it
BOX = (28, 20, 68, 52)  # the region's box at the native resolution (x0, y0, x1, y1), even: whole coarse pixels


def native_frame(i: int, shift: float = 0.0) -> Frame:
    """A finely textured plane at z = 2 m seen head-on (focal 100 px), camera shifted along world x by ``shift``."""
    intr = Intrinsics(100.0, 100.0, (WN - 1) / 2, (HN - 1) / 2, WN, HN)
    c2w = np.eye(4)
    c2w[0, 3] = shift
    u, v = np.meshgrid(np.arange(WN), np.arange(HN))
    xw = (u - intr.cx) / intr.fx * 2.0 + shift
    yw = (v - intr.cy) / intr.fy * 2.0
    checker = ((np.floor(xw / 0.1) + np.floor(yw / 0.1)) % 2).astype(np.float32)
    rgb = np.stack([0.2 + 0.6 * checker, 0.5 + 0.3 * np.sin(xw * 25), 0.3 + 0.4 * (yw > 0)], -1)
    return Frame(i, i / 30.0, (rgb * 255).astype(np.uint8), np.full((HN, WN), 2.0, np.float32), c2w, intr)


def native_roi() -> np.ndarray:
    r = np.zeros((HN, WN), bool)
    r[BOX[1]:BOX[3], BOX[0]:BOX[2]] = True
    return r


def inputs(i: int, shift: float = 0.0, between=()):
    """(coarse frame, coarse relevance, detail view) of frame ``i``."""
    fine = native_frame(i, shift)
    return (downscale_frame(fine, 2), native_roi()[::2, ::2].copy(),
            DetailView(fine, native_roi(), [native_frame(j, s) for j, s in between]))


def _cfg(enabled: bool = True, **kw) -> MapperConfig:
    base = dict(mode="gausslite", seeding={"seeds_per_frame": 600}, iters_per_frame=6, warmup_iters=2,
                backend="warp", detail={"enabled": enabled})
    return MapperConfig(**deep_merge(base, kw))


def test_without_a_detail_view_or_with_detail_off_the_map_is_bit_for_bit_the_same():
    """Same seed, same frames: no detail view, a detail view with detail.enabled off, and detail.enabled on without
    a view give the same map, poses, exposure responses and ROI views."""
    kw = dict(pose={"refine": True}, sensor={"exposure_comp": True}, densify={"every": 3},
              roi_views={"enabled": True, "min_roi_px": 16})
    runs = []
    for enabled, give in ((False, False), (False, True), (True, False)):
        m = Mapper(_cfg(enabled, **kw))
        for i, shift, between in ((0, 0.0, ()), (4, 0.04, ((1, 0.01), (2, 0.02), (3, 0.03)))):
            frame, rel, det = inputs(i, shift, between)
            coarse_between = [downscale_frame(f, 2) for f in det.between]
            m.map_frame(frame, rel, between=coarse_between, detail=det if give else None)
        runs.append(m)
    ref = runs[0]
    assert len(ref.model) > 0 and len(ref.roi_views) > 0 and ref.stats[-1].active_iters > 0
    for m in runs[1:]:
        for k, v in ref.model.params.items():
            assert torch.equal(v, m.model.params[k]), k
        assert torch.equal(ref.model.active, m.model.active) and torch.equal(ref.model.kappa, m.model.kappa)
        assert all(np.array_equal(ref.poses.corrections[f], m.poses.corrections[f]) for f in ref.poses.corrections)
        assert all(np.array_equal(ref.sensor.exposure.params[f], m.sensor.exposure.params[f])
                   for f in ref.sensor.exposure.params)
        assert m.roi_views.frame_ids == ref.roi_views.frame_ids
        assert [s.detail_px for s in m.stats] == [0, 0] and all(k.detail is None for k in m.keyframes)


def test_a_keyframe_stores_its_detail_crop_with_the_crops_intrinsics():
    m = Mapper(_cfg())
    frame, rel, det = inputs(0)
    st = m.map_frame(frame, rel, detail=det)
    kf = m.keyframes[0]
    d = kf.detail
    pad = 2 * m.cfg.roi_crop_pad  # roi_crop_pad coarse pixels at twice the resolution
    x0, y0 = BOX[0] - pad, BOX[1] - pad
    assert (d.width, d.height) == (BOX[2] - BOX[0] + 2 * pad, BOX[3] - BOX[1] + 2 * pad) == (72, 64)
    K = det.frame.intrinsics
    assert float(d.K[0, 0]) == pytest.approx(K.fx) == pytest.approx(2 * float(kf.K[0, 0]))  # the detail focal
    assert float(d.K[0, 2]) == pytest.approx(K.cx - x0) and float(d.K[1, 2]) == pytest.approx(K.cy - y0)
    assert d.roi_box == (pad, pad, pad + 40, pad + 32) and d.frame_id == kf.frame_id
    assert d.c2w is kf.c2w  # one pose tensor
    assert np.array_equal(d.rgb.numpy(), det.frame.rgb[y0:y0 + 64, x0:x0 + 72])
    assert st.detail_px == 72 * 64
    assert m.keyframes.detail_nbytes == 72 * 64 * 6 and m.keyframes.nbytes == 56 * 40 * 6 + 72 * 64 * 6


def test_roi_phase_iterations_fit_the_detail_crop_and_uniform_maps_ignore_it(monkeypatch):
    """Every ROI-phase iteration renders the 72 × 64 detail crop (every keyframe here has one), never the 36 × 32
    coarse crop (the region's box + 8 px at the map's resolution); a uniform map never renders either."""
    sizes, active = {}, {}
    for mode in ("gausslite", "uniform"):
        m = Mapper(_cfg(mode=mode, iters_per_frame=10))
        seen = sizes.setdefault(mode, [])
        render = m.sensor.render_view
        monkeypatch.setattr(m.sensor, "render_view",
                            lambda *a, seen=seen, render=render, **k: seen.append((a[2], a[3])) or render(*a, **k))
        for i in range(2):
            frame, rel, det = inputs(i, 0.02 * i)
            st = m.map_frame(frame, rel, detail=det)
        assert st.detail_px == (72 * 64 if mode == "gausslite" else 0)
        active[mode] = sum(s.active_iters for s in m.stats)
    assert active["gausslite"] > 0 and sizes["gausslite"].count((72, 64)) == active["gausslite"]
    assert (36, 32) not in sizes["gausslite"]
    assert active["uniform"] == 0 and set(sizes["uniform"]) == {(56, 40)}


def test_detail_crops_follow_pose_refinement_and_corrections_and_leave_with_the_task():
    m = Mapper(_cfg(pose={"refine": True}))
    for i in range(2):
        frame, rel, det = inputs(i, 0.02 * i)
        m.map_frame(frame, rel, detail=det)
    view = m.keyframes.load(1, m.device)
    before = m.keyframes[1].c2w.clone()
    for _ in range(3):
        m.step(view, active_phase=True)  # the detail crop, aligned (pose.roi_phase)
    assert not torch.equal(before, m.keyframes[1].c2w)
    assert torch.equal(m.keyframes[1].detail.c2w, m.keyframes[1].c2w)
    new = m.keyframe_poses()[1].copy()
    new[0, 3] += 0.05
    m.apply_pose_corrections({1: new})
    assert np.allclose(m.keyframes[1].detail.c2w.numpy(), new, atol=1e-12)
    assert np.allclose(m.keyframes.load(1, m.device).detail.c2w.numpy(), new, atol=1e-12)
    m.retarget()
    assert all(k.detail is None for k in m.keyframes) and m.keyframes.detail_nbytes == 0


def test_a_checkpoint_carries_the_detail_crops_and_one_without_them_still_loads():
    m = Mapper(_cfg())
    frame, rel, det = inputs(0)
    m.map_frame(frame, rel, detail=det)
    state = m.state_dict()
    again = Mapper(_cfg())
    again.load_state_dict(state)
    a, b = m.keyframes[0].detail, again.keyframes[0].detail
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.depth, b.depth) and torch.equal(a.K, b.K)
    assert a.roi_box == b.roi_box and b.c2w is again.keyframes[0].c2w  # the pose tensor is shared again
    new = torch.eye(4, dtype=torch.float64)
    new[1, 3] = 0.3
    again.keyframes.set_pose(0, new)
    assert torch.equal(again.keyframes[0].detail.c2w, new)
    for d in state["keyframes"]:
        d.pop("detail")
    old = Mapper(_cfg())
    old.load_state_dict(state)
    assert old.keyframes[0].detail is None and len(old.model) == len(m.model)


def test_the_regions_seeds_come_from_the_detail_pixels():
    """ρ × 1200 = 480 ROI seeds wanted: the coarse region has 320 pixels, the detail one 1280. The detail seeds sit
    on native pixel centres (integer native coordinates); coarse pixel centres fall between them (x.5)."""
    frame, rel, det = inputs(0)
    runs = {}
    for with_detail in (False, True):
        m = Mapper(_cfg())
        crop = cut_detail(det, frame.c2w, frame.intrinsics, None, m.cfg.roi_crop_pad) if with_detail else None
        s = m.seed_frame(frame, rel, crop)
        means = m.model.params["means"].detach().numpy()
        K = det.frame.intrinsics
        u = means[:, 0] / means[:, 2] * K.fx + K.cx  # native pixel coordinates
        active = m.model.active.numpy()
        runs[with_detail] = (s, u, active, m.model.params["log_scales"].detach().exp().numpy())
    s0, u0, a0, _ = runs[False]
    s1, u1, a1, _ = runs[True]
    assert s0.n_roi == 320 and s1.n_roi == 480  # the coarse pool runs short, the finer one does not
    # the rest of the 1200 go to the background (SIS: at most one per grid cell with a candidate)
    assert 0 < s0.n_seeds - s0.n_roi <= 1200 - 320 and 0 < s1.n_seeds - s1.n_roi <= 1200 - 480
    assert np.allclose(u1[a1], np.round(u1[a1]), atol=1e-3)  # region: native pixel centres
    assert np.allclose(u1[~a1] - 0.5, np.round(u1[~a1] - 0.5), atol=1e-3)  # background: coarse pixel centres
    assert np.allclose(u0[a0] - 0.5, np.round(u0[a0] - 0.5), atol=1e-3)
    assert np.median(runs[True][3][a1]) < np.median(runs[False][3][a0])  # finer spacing, smaller initial scale


def test_roi_views_are_cut_from_the_detail_frames_between_keyframes():
    m = Mapper(_cfg(roi_views={"enabled": True, "min_roi_px": 16}))
    frame, rel, det = inputs(0)
    m.map_frame(frame, rel, detail=det)
    frame, rel, det = inputs(3, 0.03, between=((1, 0.01), (2, 0.02)))
    m.map_frame(frame, rel, between=[downscale_frame(f, 2) for f in det.between], detail=det)
    assert m.roi_views.frame_ids == [1, 2]
    v = m.roi_views[0]
    assert float(v.K[0, 0]) == pytest.approx(100.0) and v.width > 40 and v.height > 32  # at the native resolution


def test_detail_crops_are_bounded_by_bytes_and_checked():
    crop_bytes = 72 * 64 * 6
    store = KeyframeStore(stored_keyframes_max=10, protect_recent=2, max_detail_bytes=2 * crop_bytes)
    for i, shift in enumerate([0.0, 0.3, 0.301, 0.6]):  # keyframes 1 and 2 are nearly the same pose
        frame, rel, det = inputs(i, shift)
        kf = keyframe_from_frame(frame, "cpu", rel)
        crop = cut_detail(det, frame.c2w, frame.intrinsics, None, 8)
        kf.detail = keyframe_from_frame(crop.frame, "cpu", crop.relevance)
        store.add(kf)
    assert len(store) == 4 and store.detail_nbytes <= 2 * crop_bytes and store.n_detail_dropped == 2
    assert store[3].detail is not None and store[1].detail is None  # the newest kept; the older of the close pair
    # a detail pixel maps to the coarse pixel that sees it (the crop's first and last pixel)
    frame, rel, det = inputs(0)
    crop = cut_detail(det, frame.c2w, frame.intrinsics, None, 8)
    idx = coarse_index(crop, np.array([0, crop.pixels - 1]), frame.intrinsics)
    assert list(np.divmod(idx, 56)[1]) == [crop.box[0] // 2, (crop.box[2] - 1) // 2]
    assert list(np.divmod(idx, 56)[0]) == [crop.box[1] // 2, (crop.box[3] - 1) // 2]
    m = Mapper(_cfg())
    bad = DetailView(native_frame(5), native_roi())
    with pytest.raises(ValueError, match="frame 5"):
        m.map_frame(frame, rel, detail=bad)
    with pytest.raises(ValueError, match="relevance"):
        m.map_frame(frame, rel, detail=DetailView(det.frame, rel))
