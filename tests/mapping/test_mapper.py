"""Mapper contracts (paper III-C/III-D): κ counting, active flags and inheritance, ROI-only
rendering and loss, MVO view sampling, matched budget, and that mapping actually fits a scene."""

import numpy as np
import pytest
import torch

import gausslite.mapping.loss as loss_mod
import gausslite.mapping.mapper as mapper_mod
import gausslite.mapping.sensor as sensor_mod
import gausslite.mapping.step as step_mod
import gausslite.mapping.views as views_mod
from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.mapping.config import MapperConfig, deep_merge
from gausslite.mapping.iterations import pick_view
from gausslite.mapping.mapper import Mapper
from tests._scenes import plane_frame

H, W = 40, 56


def _frame(i: int, shift: float = 0.0) -> Frame:
    return plane_frame(i, shift, H, W)


def _roi() -> np.ndarray:
    r = np.zeros((H, W), bool)
    r[10:26, 14:34] = True
    return r


def _cfg(**kw) -> MapperConfig:
    base = dict(seeding={"seeds_per_frame": 300}, iters_per_frame=8, warmup_iters=3, window=4, backend="warp",
                mode="gausslite")
    base = deep_merge(base, kw)  # a group given as a keyword is merged key by key
    cfg = MapperConfig(**base)
    cfg.densify.enabled = False  # tests that need density control switch it on
    return cfg


def test_kappa_counts_active_iterations_and_active_comes_from_w():
    m = Mapper(_cfg())
    st = m.map_frame(_frame(0), _roi())
    assert st.active_iters == 8 - 3
    act = m.model.active
    assert act.any() and (~act).any()
    # κ: exactly one per active-phase iteration for active Gaussians, zero for background
    assert torch.all(m.model.kappa[act] == 5)
    assert torch.all(m.model.kappa[~act] == 0)
    # a_i from w at the seed pixel: active Gaussians sit over the ROI rectangle (z = 2 plane)
    fr = _frame(0)
    K = fr.intrinsics
    mu = m.model.params["means"].detach().numpy()
    u = np.round(mu[:, 0] / mu[:, 2] * K.fx + K.cx).astype(int)
    v = np.round(mu[:, 1] / mu[:, 2] * K.fy + K.cy).astype(int)
    assert np.array_equal(_roi()[v, u], act.numpy())
    # the keyframe's stats count the task Gaussians it left and their median largest-axis scale
    largest = torch.exp(m.model.params["log_scales"].detach()[act].max(dim=1).values)
    assert st.n_active == int(act.sum()) and st.active_scale_m == pytest.approx(float(largest.median()))


@pytest.mark.parametrize("mode", ["context", "active", "alternate"])
def test_roi_phase_renders_the_roi_box_and_updates_only_active(monkeypatch, mode):
    calls = []
    real = sensor_mod.rasterize

    def spy(*a, **kw):
        calls.append((None if kw.get("subset") is None else kw["subset"].clone(), kw["width"], kw["height"]))
        return real(*a, **kw)

    monkeypatch.setattr(sensor_mod, "rasterize", spy)
    # roi_cull off: which Gaussians a render draws is the point here (the crop's culling: test below)
    m = Mapper(_cfg(iters_per_frame=6, warmup_iters=2, roi_render=mode, roi_crop_pad=3, performance={"roi_cull": False},
                    roi_update="active"))  # the paper's rule: the ROI phase updates the active rows alone
    fr = _frame(0)
    m.seed_frame(fr, _roi())  # seed, then drive the iterations by hand to inspect parameters
    kf = views_mod.keyframe_from_frame(fr, m.device, _roi())
    m.window.append(kf)
    m.step(kf, active_phase=False)
    before = {k: v.detach().clone() for k, v in m.model.params.items()}
    m.step(kf, active_phase=True)
    assert calls[0] == (None, W, H)
    subset, w, h = calls[1]
    assert (w, h) == (34 - 14 + 2 * 3, 26 - 10 + 2 * 3)  # ROI box [14,34)×[10,26) grown by 3 px
    if mode == "active":
        assert torch.equal(subset, m.model.active)
    else:
        assert subset is None  # inactive Gaussians are rendered, as occluders and background
    act = m.model.active
    for name, p in m.model.params.items():
        # background Gaussians frozen (Adam momentum from the warm-up must not move them)
        assert torch.equal(p.detach()[~act], before[name][~act]), name
    assert not torch.equal(m.model.params["colors"].detach()[act], before["colors"][act])
    m.step(kf, active_phase=True)
    m.step(kf, active_phase=False)  # warm-up iterations do not advance the alternation
    m.step(kf, active_phase=True)
    kinds = ["all" if c[0] is None else "active" for c in calls[1:]]  # ROI, ROI, warm-up, ROI
    assert kinds == {"context": ["all", "all", "all", "all"], "active": ["active", "active", "all", "active"],
                     "alternate": ["all", "active", "all", "all"]}[mode]


def test_roi_update_visible_fits_every_gaussian_the_crop_draws_and_counts_kappa_on_active_ones():
    """``roi_update='visible'``: an ROI-phase step updates the Gaussians the crop's render draws, inactive ones
    covering ROI pixels included; Gaussians outside the crop keep their values (no drift from Adam momentum);
    κ still counts active Gaussians only."""
    m = Mapper(_cfg(roi_update="visible", roi_crop_pad=0))
    fr = _frame(0)
    m.seed_frame(fr, _roi())
    kf = views_mod.keyframe_from_frame(fr, m.device, _roi())
    m.step(kf, active_phase=False)  # Adam moments everywhere
    before = {k: v.detach().clone() for k, v in m.model.params.items()}
    crop = views_mod.crop_keyframe(kf, 0)
    drawn = torch.zeros(len(m.model), dtype=torch.bool)
    out = m.render(crop.c2w, crop.K, crop.width, crop.height)
    drawn[out.ids[out.radii > 0]] = True
    m.step(kf, active_phase=True)
    act = m.model.active
    moved = ~torch.isclose(m.model.params["colors"].detach(), before["colors"]).all(dim=1)
    assert bool((moved & ~act).any())  # inactive Gaussians inside the crop are fitted too
    assert not bool((moved & ~drawn).any())  # nothing outside the crop moves
    for name, p in m.model.params.items():
        assert torch.equal(p.detach()[~drawn], before[name][~drawn]), name
    assert torch.all(m.model.kappa[act] == 1) and torch.all(m.model.kappa[~act] == 0)


@pytest.mark.parametrize("roi_loss", ["roi", "crop"])
def test_roi_loss_restricts_the_roi_phase_loss_to_roi_pixels_or_the_whole_crop(monkeypatch, roi_loss):
    seen = []
    real = step_mod.photometric_loss

    def spy(out, kf, *a, **kw):
        mask = a[2] if len(a) > 2 else kw.get("mask")
        seen.append((kf.width, kf.height, None if mask is None else int(mask.sum())))
        return real(out, kf, *a, **kw)

    monkeypatch.setattr(step_mod, "photometric_loss", spy)
    m = Mapper(_cfg(roi_loss=roi_loss, roi_crop_pad=3))
    fr = _frame(0)
    m.seed_frame(fr, _roi())
    kf = views_mod.keyframe_from_frame(fr, m.device, _roi())
    m.step(kf, active_phase=True)
    w, h, n = seen[-1]
    assert (w, h) == (20 + 6, 16 + 6)  # the crop: ROI box grown by 3 px
    if roi_loss == "crop":
        assert n is None  # every crop pixel
    else:
        assert 0 < n <= 20 * 16  # ROI pixels inside the footprint


def test_roi_cull_renders_the_same_crop():
    """``roi_cull``: an ROI-phase crop renders only the Gaussians that reach its frustum, whatever the map size,
    and the crop's render is the same."""
    fr = _frame(0)
    outs = []
    for cull in (False, True):
        m = Mapper(_cfg(performance={"roi_cull": cull, "frustum_cull_min": 10**9}))
        m.seed_frame(fr, _roi())
        kf = views_mod.keyframe_from_frame(fr, m.device, _roi())
        crop = views_mod.crop_keyframe(kf, 2)
        outs.append(m.sensor.render_view(crop.c2w, crop.K, crop.width, crop.height, crop.frame_id, None, cull=cull))
    assert len(outs[1].ids) < len(outs[0].ids)
    assert torch.allclose(outs[0].color, outs[1].color, atol=1e-5)
    assert torch.allclose(outs[0].alpha, outs[1].alpha, atol=1e-5)


def test_roi_phase_views_roi_draws_roi_keyframes_only():
    """``roi_phase_views='roi'``: ROI-phase iterations draw among the keyframes that see the ROI."""
    m = Mapper(_cfg(roi_phase_views="roi", window=2, recent_prob=0.5))
    empty = np.zeros((H, W), bool)
    for i in range(6):
        m.map_frame(_frame(i), _roi() if i in (0, 3) else empty)
    picks = {pick_view(m, m.keyframes.load(5, m.device), roi_phase=True).frame_id for _ in range(60)}
    assert picks == {0, 3}
    anyp = {pick_view(m, m.keyframes.load(5, m.device), roi_phase=False).frame_id for _ in range(200)}
    assert len(anyp) > 2


def test_roi_crop_renders_the_same_pixels_as_the_full_image():
    m = Mapper(_cfg())
    fr = _frame(0)
    m.seed_frame(fr, _roi())
    kf = views_mod.keyframe_from_frame(fr, m.device, _roi())
    assert kf.roi_box == (14, 10, 34, 26)
    crop = views_mod.crop_keyframe(kf, pad=4)
    assert (crop.width, crop.height) == (28, 24) and crop.roi_box == (4, 4, 24, 20)
    assert torch.equal(crop.rgb, kf.rgb[6:30, 10:38]) and torch.equal(crop.roi, kf.roi[6:30, 10:38])
    full = m.render(kf.c2w, kf.K, W, H)
    part = m.render(crop.c2w, crop.K, crop.width, crop.height)
    for name, tol in (("color", 5e-3), ("alpha", 5e-3), ("depth", 5e-3)):
        # equal up to the EWA Jacobian clamp, which follows the image bounds (Kerbl et al. 2023):
        # Gaussians centred far outside the crop are clamped differently (measured ≤ 2.8e-3 here)
        d = (getattr(part, name) - getattr(full, name)[6:30, 10:38]).abs()
        assert float(d.max()) < tol and float(d.mean()) < tol / 10, (name, float(d.max()), float(d.mean()))
    # the pad is clipped at the image border
    big = views_mod.crop_keyframe(kf, pad=100)
    assert (big.width, big.height) == (W, H) and big.roi_box == kf.roi_box
    with pytest.raises(ValueError):
        views_mod.crop_keyframe(views_mod.keyframe_from_frame(fr, m.device, np.zeros((H, W), bool)), 2)


def test_random_window_shows_the_full_render_pixels():
    """A full-image iteration's random window (full_crop_fraction < 1): fraction of the area at the image's
    aspect, clipped to the image, every pixel covered about equally often, and its render equals the full
    render's pixels up to the EWA clamp."""
    m = Mapper(_cfg())
    fr = _frame(0)
    m.seed_frame(fr, _roi())
    kf = views_mod.keyframe_from_frame(fr, m.device, _roi())
    full = m.render(kf.c2w, kf.K, W, H)
    rng = np.random.default_rng(0)
    seen = np.zeros((H, W))
    for i in range(2000):
        v = views_mod.random_window(kf, 0.5, rng)
        x0, y0 = int(round(float(kf.K[0, 2] - v.K[0, 2]))), int(round(float(kf.K[1, 2] - v.K[1, 2])))
        assert v.width * v.height <= 0.6 * W * H and min(v.width, v.height) >= 8
        assert 0 <= x0 and x0 + v.width <= W and 0 <= y0 and y0 + v.height <= H
        assert torch.equal(v.rgb, kf.rgb[y0:y0 + v.height, x0:x0 + v.width])
        seen[y0:y0 + v.height, x0:x0 + v.width] += 1
        if i < 10:
            part = m.render(v.c2w, v.K, v.width, v.height)
            d = (part.color - full.color[y0:y0 + v.height, x0:x0 + v.width]).abs()
            assert float(d.max()) < 5e-3
    # about equally often everywhere: corners are not starved (a window kept inside the image would cover
    # a corner pixel 1/221 as often as the centre here)
    corner, centre = seen[:4, :4].mean(), seen[H // 2 - 2:H // 2 + 2, W // 2 - 2:W // 2 + 2].mean()
    assert corner > 0.5 * centre, (corner, centre)
    with pytest.raises(ValueError):
        views_mod.window_keyframe(kf, 5, 5, 5, 9)


def test_active_phase_on_a_view_without_roi_is_a_full_image_iteration(monkeypatch):
    """Nothing to fit in the ROI: no zero-loss Adam step (its momentum would still move the
    active Gaussians) and no κ; the iteration trains the whole map on the full image instead."""
    sizes = []
    real = sensor_mod.rasterize
    monkeypatch.setattr(sensor_mod, "rasterize",
                        lambda *a, **kw: sizes.append((kw.get("subset"), kw["width"])) or real(*a, **kw))
    m = Mapper(_cfg())
    fr = _frame(0)
    m.seed_frame(fr, _roi())
    kf = views_mod.keyframe_from_frame(fr, m.device, np.zeros((H, W), bool))
    assert kf.roi_box is None
    before = m.model.params["colors"].detach().clone()
    loss = m.step(kf, active_phase=True)
    assert sizes == [(None, W)] and loss > 0
    assert int(m.model.kappa.sum()) == 0
    assert not torch.equal(m.model.params["colors"].detach()[~m.model.active], before[~m.model.active])


def test_roi_loss_restricted_to_roi_and_footprint():
    """Changing the ground truth outside the ROI does not change the active-phase loss."""
    m = Mapper(_cfg())
    fr = _frame(0)
    m.seed_frame(fr, _roi())
    kf = views_mod.keyframe_from_frame(fr, m.device, _roi())
    p = m.model.params
    out = sensor_mod.rasterize(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"],
                               K=kf.K, width=W, height=H, c2w=kf.c2w, subset=m.model.active, backend="warp")
    mask = kf.roi & (out.alpha.detach() > m.cfg.footprint_alpha)
    assert mask.any() and (~kf.roi & (out.alpha > 0.5)).sum() < mask.sum()
    l1 = loss_mod.photometric_loss(out, kf, 1.0, 0.2, mask)
    kf2 = views_mod.keyframe_from_frame(fr, m.device, _roi())
    far = torch.ones_like(kf2.roi)
    far[5:31, 9:39] = False  # beyond the SSIM window (5 px) around the ROI
    kf2.rgb[far] = 0.0
    kf2.depth[far] = 7.0
    l2 = loss_mod.photometric_loss(out, kf2, 1.0, 0.2, mask)
    assert torch.isclose(l1, l2)
    l_full = loss_mod.photometric_loss(out, kf2, 1.0, 0.2, None)
    assert not torch.isclose(l1, l_full)


@pytest.mark.parametrize("active_stats", [False, True])
def test_densify_statistics_come_from_full_image_iterations(active_stats):
    """ROI-phase iterations (loss on the ROI only) do not feed clone/split by default."""
    cfg = _cfg()
    cfg.densify.enabled = True
    cfg.densify.active_phase_stats = active_stats
    cfg.roi_render = "active"  # the active subset alone: inactive Gaussians get no gradient to count
    m = Mapper(cfg)
    fr = _frame(0)
    m.seed_frame(fr, _roi())
    kf = views_mod.keyframe_from_frame(fr, m.device, _roi())
    m.window.append(kf)
    m.step(kf, active_phase=False)
    after_warmup = (m.strategy.grad_accum.clone(), m.strategy.grad_count.clone())
    assert after_warmup[1].sum() > 0  # full-image iteration counted every visible Gaussian
    m.step(kf, active_phase=True)
    if active_stats:
        act = m.model.active
        assert torch.all(m.strategy.grad_count[act] > after_warmup[1][act])
        assert torch.equal(m.strategy.grad_count[~act], after_warmup[1][~act])
    else:
        assert torch.equal(m.strategy.grad_accum, after_warmup[0]) and torch.equal(m.strategy.grad_count, after_warmup[1])


def test_uniform_mode_never_uses_the_roi_phase(monkeypatch):
    subsets = []
    real = sensor_mod.rasterize
    monkeypatch.setattr(sensor_mod, "rasterize", lambda *a, **kw: subsets.append(kw.get("subset")) or real(*a, **kw))
    m = Mapper(_cfg(mode="uniform"))
    st = m.map_frame(_frame(0), _roi())
    assert st.active_iters == 0 and all(s is None for s in subsets)
    assert int(m.model.kappa.sum()) == 0


def test_mvo_draws_views_uniformly_from_the_window(monkeypatch):
    picked = []
    m = Mapper(_cfg(iters_per_frame=400, warmup_iters=0, window=4))
    m.step = lambda kf, active_phase, **kw: picked.append(kf.frame_id) or 0.0
    for i in range(4):
        picked.clear()
        m.map_frame(_frame(i, 0.02 * i), _roi())
    counts = np.bincount(picked, minlength=4)
    assert np.all(np.abs(counts / 400 - 0.25) < 0.07)
    # without MVO the current frame dominates (current_frame_prob = 0.5 plus its window share)
    m2 = Mapper(_cfg(iters_per_frame=400, warmup_iters=0, window=4, components={"mvo": False}))
    m2.step = m.step
    for i in range(4):
        picked.clear()
        m2.map_frame(_frame(i, 0.02 * i), _roi())
    assert np.bincount(picked, minlength=4)[3] / 400 > 0.55


def test_budget_cap_is_enforced_through_seeding_and_densification():
    cfg = _cfg(budget={"max_gaussians": 500}, seeding={"seeds_per_frame": 300})
    cfg.densify.enabled = True
    cfg.densify.every = 2
    cfg.densify.grad_threshold = 1e-9  # densify everything it can
    m = Mapper(cfg)
    for i in range(3):
        st = m.map_frame(_frame(i, 0.02 * i), _roi())
        assert st.n_gaussians <= 500
    assert len(m.model) == 500


def test_densified_daughters_inherit_active_and_kappa():
    cfg = _cfg(iters_per_frame=6, warmup_iters=2)
    cfg.densify.enabled = True
    cfg.densify.every = 6
    cfg.densify.grad_threshold = 1e-9
    cfg.densify.prune_opacity = 0.0
    m = Mapper(cfg)
    m.map_frame(_frame(0), _roi())
    n_active_seeds = int(m.stats[0].n_roi_seeds)
    act = m.model.active
    assert int(act.sum()) > n_active_seeds  # clones/splits of active Gaussians are active
    # every active Gaussian carries the 4 active iterations of its parent; background none
    assert torch.all(m.model.kappa[act] == 4) and torch.all(m.model.kappa[~act] == 0)


def test_mapping_fits_the_scene():
    """A few frames of mapping reproduce the textured plane well (training-view PSNR)."""
    from gausslite.metrics import psnr

    cfg = _cfg(mode="uniform", seeding={"seeds_per_frame": 1500}, iters_per_frame=40)
    cfg.densify.enabled = True
    m = Mapper(cfg)
    frames = [_frame(i, 0.03 * i) for i in range(3)]
    for fr in frames:
        m.map_frame(fr)
    fr = frames[1]
    out = m.render(fr.c2w, fr.intrinsics.K, W, H)
    gt = torch.from_numpy(fr.rgb).float() / 255
    assert float(psnr(out.color.clamp(0, 1), gt)) > 22.0
    valid = out.alpha > 0.9
    assert valid.float().mean() > 0.95
    assert float((out.depth[valid] - 2.0).abs().mean()) < 0.05


def test_relevance_shape_checked():
    m = Mapper(_cfg())
    with pytest.raises(ValueError, match="relevance"):
        m.map_frame(_frame(0), np.zeros((3, 3), bool))


def test_default_budget_is_per_pixel_and_new_seeds_replace_at_the_cap():
    cfg = _cfg(mode="uniform", seeding={"seeds_per_frame": 1500}, iters_per_frame=2, warmup_iters=0,
               budget={"mode": "image", "evict": "opacity"})
    assert cfg.budget.max_gaussians is None
    m = Mapper(cfg)
    m.map_frame(_frame(0))
    assert m.budget == H * W  # gaussians_per_pixel = 1.0
    assert len(m.model) == H * W  # first frame asks for 3000 seeds, capped at the budget
    # a frame looking at a new part of the plane (shifted 3 m): its seeds must enter the full map
    m.map_frame(_frame(1, shift=3.0))
    assert len(m.model) == H * W
    x = m.model.params["means"].detach()[:, 0]
    assert int((x > 1.5).sum()) == 1500  # every seed of the new view (x in [1.9, 4.1] m) entered the map


@pytest.mark.parametrize("clone", [False, True])
def test_density_control_clones_only_when_enabled(clone):
    """``densify.clone`` (off by default): high-gradient Gaussians below ``split_scale_m`` are cloned only
    when it is on; large ones split either way."""
    cfg = _cfg(densify={"clone": clone}, budget={"max_gaussians": 100_000})  # room for every candidate
    m = Mapper(cfg)
    m.map_frame(_frame(0))
    n = len(m.model)
    smax = m.model.to_map().log_scales.exp().max(dim=1).values
    cfg.densify.split_scale_m = float(smax.median())
    big = smax > cfg.densify.split_scale_m
    assert 0 < int(big.sum()) < n  # both kinds present
    m.strategy.grad_accum.fill_(1.0)
    m.strategy.grad_count.fill_(1.0)
    st = m.strategy.densify_and_prune()
    assert st["split"] == int(big.sum())
    assert st["clone"] == (n - int(big.sum()) if clone else 0)


def test_ground_truth_ssim_statistics_are_cached_per_view_with_the_same_map(monkeypatch):
    """Keyframes loaded from the store and ROI crops are new objects at every draw: the mapper keeps their
    ground-truth SSIM statistics (``ssim_cache_views``), computing each view's once, and maps exactly as
    without the cache."""
    calls = []
    orig = loss_mod.ssim_gt_stats

    def counting(gt, *a, **k):
        calls.append(tuple(gt.shape))
        return orig(gt, *a, **k)

    monkeypatch.setattr(loss_mod, "ssim_gt_stats", counting)
    maps, counts = [], []
    for n in (0, 32):
        calls.clear()
        m = Mapper(_cfg(performance={"ssim_cache_views": n, "render_threads": 1}, iters_per_frame=12))
        for i in range(4):
            m.map_frame(_frame(i, 0.02 * i), _roi())
        maps.append(m.gmap)
        counts.append(len(calls))
    assert counts[1] <= 4 * 2  # at most one full view and one ROI crop per keyframe
    assert counts[0] >= 4 * counts[1]  # without the cache: recomputed at most iterations
    for k in ("means", "quats", "log_scales", "opacity_logits", "colors", "kappa"):
        assert torch.equal(getattr(maps[0], k), getattr(maps[1], k)), k
    small = Mapper(_cfg(performance={"ssim_cache_views": 1, "render_threads": 1}))
    for i in range(3):
        small.map_frame(_frame(i), _roi())
    assert len(small.step.ssim_cache) == 1  # bounded


class _FakeClock:
    """``time`` stand-in for the mapper module: perf_counter advances only when told (deterministic budgets)."""

    def __init__(self):
        self.t = 100.0

    def perf_counter(self):
        return self.t

    now = perf_counter  # the mapper's budget clock interface (gausslite.mapping.budget)
    charges = False  # a wall clock: no modelled work


def test_time_budget_keeps_the_roi_phase_and_density_control(monkeypatch):
    """A keyframe budget shorter than ``warmup_iters`` iterations still gets ROI-phase iterations (κ, and so
    the shared subset): the warm-up is the first warmup_iters / iters_per_frame of the time, the first
    iteration full-image; density control counts budgeted iterations across calls (live agent)."""
    clock = _FakeClock()
    monkeypatch.setattr(mapper_mod, "time", clock)
    cfg = _cfg(iters_per_frame=30, warmup_iters=10)  # the deployed agent's schedule
    cfg.densify.enabled = True
    cfg.densify.every = 20
    m = Mapper(cfg)
    m.clock = clock
    phases, dc = [], []
    real_iterate, real_dc = m.step, m.strategy.densify_and_prune

    def iterate(view, active_phase, **kw):
        phases.append(active_phase)
        clock.t += 0.01  # every iteration costs 10 ms of the budget
        return real_iterate(view, active_phase, **kw)

    def densify():
        dc.append(m.n_budget_iters)
        return real_dc()

    m.step, m.strategy.densify_and_prune = iterate, densify
    st = m.map_frame(_frame(0), _roi(), time_budget_s=0.1)
    # 10 iterations fit: the fixed rule (it >= warmup_iters = 10) would have given none in the ROI phase
    assert st.iters == len(phases) == 10
    assert phases[:4] == [False] * 4 and all(phases[4:])  # warm-up: the first 1/3 of 0.1 s
    assert st.active_iters == 6
    act = m.model.active
    assert act.any() and torch.all(m.model.kappa[act] == 6) and torch.all(m.model.kappa[~act] == 0)
    assert dc == []  # 10 budgeted iterations so far: no density control yet
    for i in (1, 2):
        m.map_frame(_frame(i), _roi(), time_budget_s=0.1)
    assert dc == [20] and m.n_budget_iters == 30  # once every 20 budgeted iterations, across calls
    # a budget already spent by seeding: one full-image iteration for the new seeds
    phases.clear()
    st = m.map_frame(_frame(3), _roi(), time_budget_s=1e-9)
    assert phases == [False] and st.active_iters == 0
    # without warm-up (warmup_iters = 0) every budgeted iteration is in the ROI phase once Gaussians are active
    m0 = Mapper(_cfg(iters_per_frame=30, warmup_iters=0))
    m0.map_frame(_frame(0), _roi())
    m0.clock = clock
    seen = []
    real0 = m0.step

    def iterate0(view, active_phase, **kw):
        seen.append(active_phase)
        clock.t += 0.01
        return real0(view, active_phase, **kw)

    m0.step = iterate0
    m0.map_frame(_frame(1), _roi(), time_budget_s=0.05)
    assert seen and all(seen)
    # the counter survives a checkpoint
    m.step = real_iterate
    m2 = Mapper(cfg)
    m2.load_state_dict(m.state_dict())
    assert m2.n_budget_iters == m.n_budget_iters


@pytest.mark.parametrize("mode", ["gausslite", "uniform"])
def test_roi_grad_factor_densifies_active_gaussians_at_a_lower_threshold(mode):
    """``densify.roi_grad_factor`` (gausslite mode): an active Gaussian splits once its mean view-space gradient
    reaches grad_threshold × the factor, a background one only at grad_threshold; uniform mode ignores it."""
    cfg = _cfg(mode=mode, iters_per_frame=2, warmup_iters=0)
    cfg.densify.prune_opacity = 0.0
    cfg.densify.split_scale_m = 1e-6  # every Gaussian is large enough to split
    cfg.densify.roi_grad_factor = 0.25
    m = Mapper(cfg)
    m.map_frame(_frame(0), _roi() if mode == "gausslite" else None)
    n = len(m.model)
    act = m.model.active.clone()
    if mode == "uniform":
        act[: n // 2] = True  # uniform maps have no active Gaussians; mark some to show the factor is ignored
        m.model.active[:] = act
    assert 0 < int(act.sum()) < n
    m.strategy.reset_stats()
    m.strategy.budget = 10 * n
    thr = cfg.densify.grad_threshold
    m.strategy.grad_accum[:] = 0.5 * thr  # between the ROI threshold (0.25 thr) and the background one
    m.strategy.grad_count[:] = 1.0
    stats = m.strategy.densify_and_prune()
    expect = int(act.sum()) if mode == "gausslite" else 0
    assert stats["split"] == expect
    assert len(m.model) == n + expect


@pytest.mark.parametrize("threshold", [0.0, 0.05])
def test_pruning_removes_the_gaussians_the_keyframes_never_draw(threshold):
    """``budget.prune_contribution``: 200 Gaussians hidden 1 m behind the plane (alpha 0.88 or more) contribute
    under 0.05 pixel to its keyframes and go once they are ``prune_after`` keyframes old; the plane's own stay, the
    counter and the checkpoint state follow. Off (0), nothing is pruned."""
    from gausslite.gaussians import GaussianMap

    cfg = _cfg(mode="uniform", seeding={"seeds_per_frame": 1500}, iters_per_frame=10,
               budget={"prune_contribution": threshold, "prune_after": 2})
    m = Mapper(cfg)
    m.map_frame(_frame(0))
    g = torch.Generator().manual_seed(0)
    hidden = GaussianMap.from_points(torch.cat([torch.rand(200, 2, generator=g) - 0.5, torch.full((200, 1), 3.0)], 1),
                                     torch.rand(200, 3, generator=g), 0.01, 0.9)
    n_plane = len(m.model)
    m.load_map(m.model.to_map().detach().clone().append(hidden))
    assert m.strategy.age.tolist() == [0] * (n_plane + 200)
    m.map_frame(_frame(1, 0.01))
    assert int((m.model.params["means"].detach()[:, 2] > 2.5).sum()) == 200  # one keyframe old: kept
    m.map_frame(_frame(2, 0.02))
    behind = int((m.model.params["means"].detach()[:, 2] > 2.5).sum())
    if threshold == 0:
        assert behind == 200 and m.strategy.pruned == 0
        return
    assert behind == 0 and 200 <= m.strategy.pruned < 200 + 0.1 * n_plane  # the plane keeps 90 % or more
    assert len(m.strategy.age) == len(m.model) == len(m.strategy.contribution)
    state = m.strategy.state_dict()
    assert state["pruned"] == m.strategy.pruned and torch.equal(state["age"], m.strategy.age)


def test_pruning_needs_eviction_by_contribution():
    """Pruning reads the contribution that only ``evict: contribution`` accumulates: asked for with ``evict:
    opacity`` it is refused, at construction and on assignment, instead of silently doing nothing."""
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="evict: contribution"):
        _cfg(budget={"prune_contribution": 5.0, "evict": "opacity"})
    cfg = _cfg(budget={"prune_contribution": 5.0})
    with pytest.raises(ValidationError, match="evict: contribution"):
        cfg.budget.evict = "opacity"
    assert _cfg(budget={"evict": "opacity"}).budget.prune_contribution == 0.0
