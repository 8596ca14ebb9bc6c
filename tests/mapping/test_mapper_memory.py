"""Long-mission mapper contracts: coverage-driven seeding, the scene-following budget,
contribution eviction with ROI protection, the mission-wide keyframe store and its sampler."""

import numpy as np
import pytest
import torch

from gausslite.camera import Intrinsics
from gausslite.mapping.config import MapperConfig, deep_merge
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.views import keyframe_from_frame
from gausslite.camera import backproject
from gausslite.mapping.memory import KeyframeStore, SurfaceVoxels, pack_voxel_keys, unexplained_mask
from tests._scenes import plane_frame

H, W = 40, 56


def _cfg(**kw) -> MapperConfig:
    base = dict(seeding={"seeds_per_frame": 300}, iters_per_frame=20, warmup_iters=0, window=4, backend="warp",
                mode="uniform")
    base = deep_merge(base, kw)  # a group given as a keyword is merged key by key
    cfg = MapperConfig(**base)
    cfg.densify.enabled = False
    return cfg


def _roi() -> np.ndarray:
    r = np.zeros((H, W), bool)
    r[10:26, 14:34] = True
    return r


# ---------------------------------------------------------------- coverage-driven seeding
def test_unexplained_mask_follows_silhouette_and_depth_rule():
    gt = np.full((4, 5), 2.0, np.float32)
    gt[0, 0] = 0.0  # invalid depth is never a candidate
    alpha = np.full((4, 5), 0.9, np.float32)
    alpha[1, 1] = 0.2  # hole in the silhouette
    dr = gt + np.random.default_rng(0).uniform(-0.001, 0.001, gt.shape).astype(np.float32)
    dr[2, 2] = 3.0  # rendered surface far behind the observation: new geometry in front
    dr[3, 3] = 1.0  # rendered surface in front of the observation: not new geometry (SplaTAM)
    m = unexplained_mask(gt, alpha, dr)
    assert m[1, 1] and m[2, 2]
    assert not m[0, 0] and not m[3, 3]
    assert int(m.sum()) == 2


def test_no_seeds_where_the_map_already_explains_the_frame():
    m = Mapper(_cfg(iters_per_frame=40))
    m.cfg.densify.enabled = True
    st0 = m.map_frame(plane_frame(0))
    assert st0.n_seeds == 600  # first frame: 2N on every valid pixel
    st1 = m.map_frame(plane_frame(1))  # the same view again: the map explains it
    assert st1.unexplained < 0.05
    assert st1.n_seeds <= int(np.ceil(300 * st1.unexplained))
    # half of the next view is new plane (shifted 1.12 m = half the 2.24 m field of view)
    n0 = len(m.model)
    seeded = m.seed_frame(plane_frame(2, shift=1.12), None)
    assert 0.4 < seeded.unexplained < 0.65
    assert seeded.n_seeds == int(np.ceil(300 * seeded.unexplained))
    means = m.model.params["means"].detach()[n0:]  # new rows are appended after the old ones
    assert means.shape[0] == seeded.n_seeds
    assert float((means[:, 0] > 1.12 - 0.1).float().mean()) > 0.95  # seeds sit on the new half


def test_coverage_seeding_off_seeds_every_frame_fully():
    m = Mapper(_cfg(seeding={"coverage": False}))
    m.map_frame(plane_frame(0))
    assert m.map_frame(plane_frame(1)).n_seeds == 300


# ---------------------------------------------------------------- budget and eviction
def test_scene_budget_grows_with_observed_voxels_and_is_capped():
    m = Mapper(_cfg(budget={"gaussians_per_voxel": 10.0, "voxel_m": 0.1, "cap": 10_000}, iters_per_frame=2))
    m.map_frame(plane_frame(0))
    b0, v0 = m.budget, len(m.strategy.voxels)
    assert v0 >= 100 and b0 == round(10.0 * v0)
    m.map_frame(plane_frame(1, shift=2.0))  # a new stretch of wall
    assert len(m.strategy.voxels) > 1.5 * v0 and m.budget > b0
    m2 = Mapper(_cfg(budget={"gaussians_per_voxel": 100.0, "voxel_m": 0.1, "cap": 700}, iters_per_frame=2))
    m2.map_frame(plane_frame(0))
    assert m2.budget == 700


def test_surface_voxels_count_a_plane():
    intr = Intrinsics(50.0, 50.0, 27.5, 19.5, 56, 40)
    sv = SurfaceVoxels(0.1, pixel_stride=1)
    depth = np.full((40, 56), 2.0, np.float32)
    sv.add_frame(depth, intr, np.eye(4))
    # the plane spans 2.24 m × 1.6 m at z = 2 m: about 23 × 17 voxels of 10 cm (one layer)
    assert 300 < len(sv) < 500
    assert sv.add_frame(depth, intr, np.eye(4)) == 0  # the same view adds nothing
    pts = backproject(depth, intr, np.eye(4)).reshape(-1, 3)
    keys = np.unique(pack_voxel_keys(np.floor(pts / 0.1).astype(np.int64)))
    assert len(keys) == len(sv)  # every pixel counted once at stride 1
    assert len(np.unique(pack_voxel_keys(np.array([[-3, 5, 7], [-3, 5, 7], [3, -5, 7]])))) == 2


def test_contribution_is_the_alpha_blending_weight():
    """Σ_i contribution_i = Σ_pixels alpha (the weights w_i = T_i α_i of a pixel sum to its alpha)."""
    m = Mapper(_cfg(budget={"evict": "contribution"}, iters_per_frame=5))
    fr = plane_frame(0)
    m.map_frame(fr)
    c_before = m.strategy.contribution.clone()
    kf = keyframe_from_frame(fr, m.device)
    m.accumulate_contribution(kf)
    added = m.strategy.contribution - c_before
    out = m.render(fr.c2w, fr.intrinsics.K, W, H)
    assert float(added.sum()) == pytest.approx(float(out.alpha.sum()), rel=1e-3)
    assert torch.all(added >= 0)
    # Gaussians outside the view get nothing
    far = Mapper(_cfg(iters_per_frame=1))
    far.map_frame(fr)
    far.strategy.contribution.zero_()
    far.accumulate_contribution(keyframe_from_frame(plane_frame(1, shift=50.0), far.device))
    assert float(far.strategy.contribution.abs().sum()) == 0.0


def test_eviction_by_contribution_and_roi_protection():
    cfg = _cfg(mode="gausslite", budget={"max_gaussians": 700, "roi_protect": 4.0}, iters_per_frame=1, warmup_iters=0,
               seeding={"coverage": False, "seeds_per_frame": 300, "first_frame_seeds": 600})
    m = Mapper(cfg)
    m.map_frame(plane_frame(0), _roi())
    n = len(m.model)
    assert 500 < n <= 600
    # hand-set contributions: background rows 1..k, active rows low but protected ×4
    act = m.model.active.clone()
    n_bg = int((~act).sum())
    assert n - 400 < n_bg  # the evictions can all come from the background
    contrib = torch.empty(n)
    contrib[~act] = torch.arange(1, n_bg + 1, dtype=torch.float32)  # background: 1 … n_bg
    contrib[act] = 50.25  # low, but ×4 = 201 ranks above every background row that goes
    m.strategy.contribution = contrib.clone()
    means_before = m.model.params["means"].detach().clone()
    seeded = m.seed_frame(plane_frame(1, shift=3.0), None)  # 300 new seeds must enter: n - 400 evicted
    assert len(m.model) == 700 and seeded.n_evicted == n - 400
    kept = means_before[:n]
    now = m.model.params["means"].detach()
    survived = torch.tensor([bool((now == row).all(dim=1).any()) for row in kept])
    score = contrib.clone()
    score[act] *= 4.0
    expected = torch.zeros(n, dtype=torch.bool)
    expected[torch.argsort(score, descending=True)[:400]] = True
    assert torch.equal(survived, expected)
    assert bool(survived[act].all())  # protected active Gaussians all survived
    # the same contributions without protection: the active ones (score 10) go first
    m2 = Mapper(cfg.model_copy(update={"budget": cfg.budget.model_copy(update={"roi_protect": 1.0})}))
    m2.map_frame(plane_frame(0), _roi())
    m2.strategy.contribution = contrib.clone()
    m2.seed_frame(plane_frame(1, shift=3.0), None)
    assert int(m2.model.active.sum()) < int(act.sum())


def test_contribution_follows_densification_parents():
    cfg = _cfg(iters_per_frame=4, budget={"max_gaussians": 5000})
    cfg.densify.enabled = True
    cfg.densify.every = 4
    cfg.densify.grad_threshold = 1e-9
    cfg.densify.prune_opacity = 0.0
    m = Mapper(cfg)
    m.map_frame(plane_frame(0))
    assert m.strategy.contribution.shape[0] == len(m.model)
    m.strategy.contribution = torch.arange(len(m.model), dtype=torch.float32)
    before = m.strategy.contribution.clone()
    m.step(keyframe_from_frame(plane_frame(0), m.device), active_phase=False)  # gradient statistics
    m.strategy.densify_and_prune()
    assert m.strategy.contribution.shape[0] == len(m.model) > before.shape[0]
    # the first rows keep their own contribution; daughters copy their parent's
    n_old = before.shape[0]
    assert m.strategy.contribution.shape[0] == len(m.model)
    assert set(m.strategy.contribution.tolist()) <= set(before.tolist())  # every row carries a parent's value
    assert len(m.model) > n_old


# ---------------------------------------------------------------- mission-wide keyframes
def _store_with(n: int, roi_every: int = 0) -> KeyframeStore:
    st = KeyframeStore(stored_keyframes_max=10_000, protect_recent=4)
    for i in range(n):
        roi = _roi() if roi_every and i % roi_every == 0 else np.zeros((H, W), bool)
        st.add(keyframe_from_frame(plane_frame(i, 0.05 * i), torch.device("cpu"), roi))
    return st


def test_sampler_reaches_the_whole_mission_and_weights_roi_views():
    st = _store_with(40, roi_every=4)
    rng = np.random.default_rng(0)
    draws = np.array([st.sample_index(rng, window=4, recent_prob=0.5, roi_weight=0.0) for _ in range(8000)])
    counts = np.bincount(draws, minlength=40)
    assert counts[:36].min() > 0  # every old keyframe is revisited
    assert abs(counts[36:].sum() / 8000 - (0.5 + 0.5 * 4 / 40)) < 0.03  # window share
    old = counts[:36]
    assert old.max() / old.min() < 2.0  # uniform over the mission
    rng = np.random.default_rng(1)
    draws = np.array([st.sample_index(rng, window=4, recent_prob=0.0, roi_weight=3.0) for _ in range(8000)])
    c = np.bincount(draws, minlength=40)
    roi_mean = c[0:40:4].mean()
    other = np.delete(c, np.arange(0, 40, 4)).mean()
    assert 3.0 < roi_mean / other < 5.0  # weight 1 + 3 = 4


def test_mapper_views_come_from_old_keyframes(monkeypatch):
    picked = []
    m = Mapper(_cfg(iters_per_frame=200, window=2, recent_prob=0.5, components={"mvo": True}, mode="gausslite"))
    m.step = lambda kf, active_phase, **kw: picked.append(kf.frame_id) or 0.0
    for i in range(12):
        picked.clear()
        m.map_frame(plane_frame(i, 0.02 * i), _roi())
    counts = np.bincount(picked, minlength=12)
    assert counts[:10].sum() > 60  # ~half of 200 iterations go to the ten older keyframes
    assert counts[:10].min() > 0


def test_keyframe_store_is_compact_and_bounded():
    st = KeyframeStore(stored_keyframes_max=6, protect_recent=2)
    frames = [plane_frame(i, 0.1 * i) for i in range(10)]
    frames[3] = plane_frame(3, 0.2 + 1e-4)  # nearly a duplicate of keyframe 2: most redundant
    for fr in frames:
        st.add(keyframe_from_frame(fr, torch.device("cpu"), _roi()))
    assert len(st) == 6 and st.n_dropped == 4
    ids = [k.frame_id for k in st]
    assert ids[0] == 0 and ids[-2:] == [8, 9]  # first and the protected window survive
    assert 3 not in ids
    # compact: uint8 colour + float16 depth + bool ROI = 6 B/pixel (float32 tensors: 20)
    assert st.nbytes == 6 * (H * W * 6)
    kf = st.load(len(st) - 1, torch.device("cpu"))
    fr = frames[9]
    assert torch.allclose(kf.rgb, torch.from_numpy(fr.rgb).float() / 255, atol=1 / 255)
    assert torch.allclose(kf.depth, torch.from_numpy(fr.depth), atol=2e-3)
    assert kf.roi_box == (14, 10, 34, 26)


def test_mapper_keyframe_memory_stays_bounded():
    m = Mapper(_cfg(stored_keyframes_max=5, iters_per_frame=1, window=2))
    for i in range(9):
        m.map_frame(plane_frame(i, 0.03 * i))
    assert len(m.keyframes) == 5
    assert m.keyframes.nbytes <= 5 * H * W * 5


def test_blend_weights_agree_between_warp_and_the_torch_reference():
    from gausslite.render import blend_weights

    m = Mapper(_cfg(iters_per_frame=3))
    fr = plane_frame(0)
    m.map_frame(fr)
    p = {k: v.detach() for k, v in m.model.params.items()}
    args = (p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"])
    kw = dict(K=fr.intrinsics.K, width=W, height=H, c2w=fr.c2w)
    w_warp = blend_weights(*args, backend="warp", **kw)
    w_ref = blend_weights(*args, backend="torch", **kw)
    assert torch.allclose(w_warp, w_ref.float(), atol=1e-3, rtol=1e-3)
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[:, : W // 2] = True
    left = blend_weights(*args, backend="warp", pixel_mask=mask, **kw)
    right = blend_weights(*args, backend="warp", pixel_mask=~mask, **kw)
    assert torch.allclose(left + right, w_warp, atol=1e-3)


def test_final_pass_runs_every_iteration_offline_and_stops_at_a_time_bound():
    m = Mapper(_cfg(iters_per_frame=2, final_iters=3, final_iters_per_keyframe=2.0))
    for i in range(3):
        m.map_frame(plane_frame(i, 0.02 * i))
    assert m.finalize() == 3 + 2 * 3  # offline: all of them
    m.cfg.final_iters = 100_000
    assert 1 <= m.finalize(max_seconds=0.2) < 100_000  # the agent's Finish bound (final_pass_s)
    with pytest.raises(ValueError, match="max_seconds"):
        m.finalize(max_seconds=0)


def test_final_schedule_mapping_gives_gausslite_roi_phase_iterations_and_uniform_full_ones():
    """``final_schedule: mapping``: in gausslite mode the final pass follows the mapping schedule (warm-up
    full-image, then ROI-phase iterations that raise κ of the active Gaussians only); ``full`` (default) and
    uniform mode leave κ alone. The default draws the same views as before (same map from the same seed)."""
    def mapped(**kw):
        m = Mapper(_cfg(mode="gausslite", iters_per_frame=4, warmup_iters=2, final_iters=8, **kw))
        for i in range(3):
            m.map_frame(plane_frame(i, 0.02 * i), _roi())
        return m

    full, sched = mapped(), mapped(final_schedule="mapping")
    assert torch.equal(full.model.kappa, sched.model.kappa)  # same mapping up to the final pass
    k0 = full.model.kappa.clone()
    assert full.finalize() == 8 and sched.finalize() == 8
    assert torch.equal(full.model.kappa, k0)  # full-image final pass: no κ
    active = sched.model.active
    assert bool(active.any()) and bool((sched.model.kappa[active] == k0[active] + 4).all())  # 2 per 4, twice
    assert torch.equal(sched.model.kappa[~active], k0[~active])
    u = Mapper(_cfg(mode="uniform", iters_per_frame=4, warmup_iters=2, final_iters=8, final_schedule="mapping"))
    for i in range(3):
        u.map_frame(plane_frame(i, 0.02 * i))
    ku = u.model.kappa.clone()
    assert u.finalize() == 8 and torch.equal(u.model.kappa, ku)
