"""Task-region and compaction rules of the shared subset (gausslite.sharing; docs/sharing.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gausslite.gaussians import GaussianMap
from gausslite.mapping.views import Keyframe, roi_box
from gausslite.mission.config import ShareConfig
from gausslite.sharing import in_region, roi_contribution, select_task_subset, task_region

K = np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]])

#: the paper's share rule (a = 1 and κ in the task region, no bound); the agent's defaults are ``rendered``, 25 %
PAPER = {"candidates": "active", "max_fraction": None}


def _view(box=(24, 16, 40, 32), depth=2.0) -> Keyframe:
    roi = np.zeros((48, 64), bool)
    x0, y0, x1, y1 = box
    roi[y0:y1, x0:x1] = True
    return Keyframe(0, torch.zeros(48, 64, 3), torch.full((48, 64), depth), torch.eye(4, dtype=torch.float64),
                    torch.tensor(K, dtype=torch.float32), 64, 48, torch.from_numpy(roi), roi_box(roi))


def _map(means, opacity, scales, active=True) -> GaussianMap:
    n = len(means)
    g = GaussianMap.from_points(torch.tensor(means, dtype=torch.float32), torch.full((n, 3), 0.5),
                                torch.tensor(scales, dtype=torch.float32), opacity=0.5,
                                active=torch.full((n,), active))
    g.opacity_logits[:] = torch.logit(torch.tensor(opacity, dtype=torch.float32))
    g.kappa[:] = 5
    return g


def test_task_region_back_projects_roi_depth_and_dilates():
    v = _view()
    r0 = task_region([v], voxel_m=0.05, dilate=0)
    # ROI pixels at 2 m span x in [-8/60·2, 8/60·2) = ±0.27 m: about 11 x 11 voxels in one z slab
    inside = in_region(np.array([[0.0, 0.0, 2.01], [0.2, 0.2, 2.01]]), r0, 0.05)
    outside = in_region(np.array([[0.6, 0.0, 2.01], [0.0, 0.0, 2.2], [0.0, 0.0, 1.9]]), r0, 0.05)
    assert inside.all() and not outside.any()
    r1 = task_region([v], voxel_m=0.05, dilate=1)
    assert in_region(np.array([[0.0, 0.0, 2.06], [0.0, 0.0, 1.96]]), r1, 0.05).all()
    assert not in_region(np.array([[0.0, 0.0, 2.2]]), r1, 0.05).any()
    assert len(task_region([_view(box=(0, 0, 0, 0))])) == 0
    with pytest.raises(ValueError):
        task_region([v], voxel_m=0)


def test_contribution_is_the_roi_blending_weight_and_compaction_prunes_occluded_and_transparent():
    # 0: opaque, in front, in the ROI; 1: right behind 0 (occluded); 2: near-transparent in the ROI;
    # 3: outside the task region (seen outside the ROI); 4: inactive
    g = _map([[0, 0, 1.98], [0, 0, 2.02], [0.1, 0.05, 2.0], [0.8, 0.5, 2.0], [-0.1, 0, 2.0]],
             [0.99, 0.99, 0.01, 0.99, 0.99], [0.08, 0.02, 0.04, 0.04, 0.04])
    g.active[4] = False
    v = _view()
    c = roi_contribution(g, [v])
    assert c.shape == (5,) and c[0] > 5 * c[1] > 0 and c[3] == pytest.approx(0.0, abs=1e-6)
    # the weights add up to the rendered ROI alpha
    from gausslite.render import rasterize

    out = rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, K=K, width=64, height=48,
                    c2w=np.eye(4), background=torch.zeros(3))
    assert c.sum() == pytest.approx(float(out.alpha[v.roi].sum()), rel=1e-3)
    mask, st = select_task_subset(g, [v], ShareConfig(coverage=1.0, **PAPER))
    assert mask.tolist() == [True, True, False, False, False]  # region, opacity, active rules
    assert st == {"active_kappa": 4, "in_region": 3, "opaque": 2, "shared": 2}
    assert c[0] / (c[0] + c[1]) > 0.8
    mask, st = select_task_subset(g, [v], ShareConfig(coverage=0.8, **PAPER))
    assert mask.tolist() == [True, False, False, False, False]  # the occluded one is redundant
    # no ROI pixels at all: the task flag and κ rule alone
    mask, _ = select_task_subset(g, [_view(box=(0, 0, 0, 0))], ShareConfig(**PAPER))
    assert mask.tolist() == [True, True, True, True, False]


def test_rendered_candidates_rank_every_gaussian_that_draws_the_roi_and_max_fraction_bounds_the_share():
    """The live share rule (``candidates: rendered``, ``max_fraction``): flags, κ and the task region do not
    decide; the ROI blending weight does, and the bound keeps the largest contributions."""
    # 0: opaque, in front, in the ROI; 1: behind 0 (occluded); 2: near-transparent; 3: outside the ROI's view;
    # 4: inactive, κ 0, in the ROI (a Gaussian the ROI phase fitted under roi_update: visible)
    g = _map([[0, 0, 1.98], [0, 0, 2.02], [0.1, 0.05, 2.0], [0.8, 0.5, 2.0], [-0.1, 0, 2.0]],
             [0.99, 0.99, 0.01, 0.99, 0.99], [0.08, 0.02, 0.04, 0.04, 0.04])
    g.active[4] = False
    g.kappa[4] = 0
    v = _view()
    c = roi_contribution(g, [v])
    mask, st = select_task_subset(g, [v], ShareConfig(coverage=1.0, candidates="rendered", max_fraction=None))
    # every opaque Gaussian with a positive ROI weight, the inactive one included; not the one outside the ROI
    assert mask.tolist() == [True, True, False, False, True]
    assert st["shared"] == 3 and st["active_kappa"] == 4
    # the paper's rule on the same map leaves the inactive one out
    paper = select_task_subset(g, [v], ShareConfig(coverage=1.0, **PAPER))[0]
    assert paper.tolist() == [True, True, False, False, False]
    # at most floor(0.4 * 5) = 2 Gaussians: the two largest contributions
    mask, st = select_task_subset(g, [v], ShareConfig(coverage=1.0, candidates="rendered", max_fraction=0.4))
    top2 = set(np.argsort(-c)[:2].tolist())
    assert set(np.nonzero(mask)[0].tolist()) == top2 and st["shared"] == 2
    # the bound applies to the paper's rule as well
    assert select_task_subset(g, [v], ShareConfig(coverage=1.0, candidates="active", max_fraction=0.2))[0].sum() == 1
    # hysteresis: a held row ranks with its contribution times held_weight, so it stays in a bounded subset
    third = int(np.argsort(-c)[2])
    held = np.zeros(5, bool)
    held[third] = True
    mask, _ = select_task_subset(g, [v], ShareConfig(coverage=1.0, candidates="rendered", max_fraction=0.4,
                                                     held_weight=1e6), held=held)
    assert mask[third] and mask.sum() == 2
    with pytest.raises(ValueError):
        ShareConfig(held_weight=0.5)
    # no ROI seen yet: nothing draws the task region, nothing is shared
    assert not select_task_subset(g, [_view(box=(0, 0, 0, 0))], ShareConfig(candidates="rendered"))[0].any()
    with pytest.raises(ValueError):
        ShareConfig(candidates="everything")
    with pytest.raises(ValueError):
        ShareConfig(max_fraction=0.0)


def _roi_keyframe(color=(200, 30, 30), box=(20, 12, 44, 36)):
    """A 64×48 keyframe at the origin looking down +z at a plane 2 m away; ``box`` of it is the ROI
    and shows ``color`` (uint8 RGB), the rest grey."""
    from gausslite.camera import Intrinsics
    from gausslite.datasets.base import Frame
    from gausslite.mapping.views import keyframe_from_frame

    rgb = np.full((48, 64, 3), 90, np.uint8)
    x0, y0, x1, y1 = box
    rgb[y0:y1, x0:x1] = color
    roi = np.zeros((48, 64), bool)
    roi[y0:y1, x0:x1] = True
    fr = Frame(0, 0.0, rgb, np.full((48, 64), 2.0, np.float32), np.eye(4), Intrinsics.from_K(K, 64, 48))
    return keyframe_from_frame(fr, torch.device("cpu"), roi), roi


def _roi_l1(g, kf, roi):
    from gausslite.render import rasterize

    out = rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, K=K, width=64, height=48,
                    c2w=np.eye(4), background=torch.zeros(3))
    return float((out.color - kf.rgb).abs()[torch.from_numpy(roi)].mean())


def test_finetune_subset_fits_the_subset_alone_to_the_roi_and_keeps_rows_kappa_and_flags():
    from gausslite.sharing import finetune_subset

    kf, roi = _roi_keyframe()
    xs, ys = np.meshgrid(np.linspace(-0.3, 0.3, 4), np.linspace(-0.3, 0.3, 4))  # the ROI spans ±0.4 m
    means = np.stack([xs.ravel(), ys.ravel(), np.full(16, 2.0)], 1)
    sub = _map(means, [0.4] * 16, [0.1] * 16)  # grey, translucent: in the map, the background filled it
    sub.kappa[:] = torch.arange(16) + 3
    sub.active[5] = False  # flags come back as they were, even though every row is optimised
    before = {k: getattr(sub, k).clone() for k in ("means", "colors", "kappa", "active")}
    l1_0 = _roi_l1(sub, kf, roi)
    out = finetune_subset(sub, [kf], iters=120, seed=0)
    l1_1 = _roi_l1(out, kf, roi)
    assert l1_1 < 0.4 * l1_0, (l1_0, l1_1)
    assert len(out) == 16
    # row order kept (ids stay aligned): every Gaussian stays near where it was
    assert float((out.means - before["means"]).norm(dim=1).max()) < 0.05
    assert torch.equal(out.kappa, before["kappa"]) and torch.equal(out.active, before["active"])
    # the input is not modified
    assert torch.equal(sub.means, before["means"]) and torch.equal(sub.colors, before["colors"])
    # the colour moved towards the ROI's red
    assert float(out.colors[:, 0].mean()) > float(before["colors"][:, 0].mean()) + 0.1
    # no iterations / no ROI keyframe: values unchanged
    for same in (finetune_subset(sub, [kf], iters=0),
                 finetune_subset(sub, [_roi_keyframe(box=(0, 0, 0, 0))[0]], iters=10)):
        assert torch.equal(same.means, sub.means) and torch.equal(same.colors, sub.colors)
    with pytest.raises(ValueError):
        finetune_subset(sub, [kf], iters=-1)


def test_finetune_with_the_outside_penalty_keeps_the_subset_off_the_pixels_beside_its_roi():
    """A subset fitted alone on its ROI spreads over the pixels beside it (nothing there is in its loss); with
    ``roi_outside_alpha`` (the share fine-tune's ``agent.share.outside_alpha``) it draws the ROI and little else."""
    from gausslite.mapping.config import MapperConfig
    from gausslite.render import rasterize
    from gausslite.sharing import finetune_subset

    kf, roi = _roi_keyframe(box=(24, 16, 40, 32))
    xs, ys = np.meshgrid(np.linspace(-0.4, 0.4, 4), np.linspace(-0.4, 0.4, 4))  # wider than the ROI (±0.27 m)
    sub = _map(np.stack([xs.ravel(), ys.ravel(), np.full(16, 2.0)], 1), [0.6] * 16, [0.12] * 16)
    grown = torch.nn.functional.max_pool2d(torch.from_numpy(roi).float()[None, None], 5, 1, 2)[0, 0] > 0

    def scores(g):
        out = rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, K=K, width=64, height=48,
                        c2w=np.eye(4), background=torch.zeros(3))
        return float(out.alpha[~grown].mean()), float((out.color - kf.rgb).abs()[torch.from_numpy(roi)].mean())

    free = scores(finetune_subset(sub, [kf], iters=120, seed=0))
    clipped = scores(finetune_subset(sub, [kf], iters=120, seed=0, cfg=MapperConfig(roi_outside_alpha=1.0)))
    assert clipped[0] < 0.5 * free[0], (free, clipped)
    assert clipped[1] < free[1] + 0.05, (free, clipped)  # the ROI itself is fitted as well


def test_finetune_subset_decodes_compact_keyframes_one_draw_at_a_time(monkeypatch):
    """Compact (stored) keyframes give the same fit as their float forms, and each is decoded only when drawn:
    the fine-tune holds one float keyframe, not all of them (a share worker fine-tuning on 200 ROI keyframes
    held 245 MB of float images at once)."""
    from gausslite.mapping.views import StoredKeyframe
    from gausslite.sharing import finetune_subset

    stored = [_roi_keyframe(color=c)[0].compact() for c in ((200, 30, 30), (180, 40, 20), (210, 20, 40))]
    decoded = [kf.to_keyframe(torch.device("cpu")) for kf in stored]
    calls = []
    orig = StoredKeyframe.to_keyframe
    monkeypatch.setattr(StoredKeyframe, "to_keyframe", lambda self, device: calls.append(self.frame_id)
                        or orig(self, device))
    sub = _grid_subset()
    a = finetune_subset(sub, stored, iters=30, seed=3)
    assert len(calls) == 30  # one decode per drawn keyframe, none up front
    b = finetune_subset(sub, decoded, iters=30, seed=3)
    for k in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k


def _grid_subset(n_side=4, z=2.0):
    xs, ys = np.meshgrid(np.linspace(-0.3, 0.3, n_side), np.linspace(-0.3, 0.3, n_side))
    means = np.stack([xs.ravel(), ys.ravel(), np.full(n_side * n_side, z)], 1)
    sub = _map(means, [0.4] * len(means), [0.1] * len(means))
    sub.kappa[:] = torch.arange(len(means)) + 3
    return sub


def test_finetune_subset_keeps_frozen_rows_and_fits_the_free_ones_around_them():
    from gausslite.sharing import finetune_subset

    kf, roi = _roi_keyframe()
    sub = _grid_subset()
    frozen = np.zeros(16, bool)
    frozen[::2] = True
    out = finetune_subset(sub, [kf], iters=120, seed=0, frozen=frozen)
    fz = torch.from_numpy(frozen)
    for k in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        assert torch.equal(getattr(out, k)[fz], getattr(sub, k)[fz]), k
        assert not torch.equal(getattr(out, k)[~fz], getattr(sub, k)[~fz]), k
    assert _roi_l1(out, kf, roi) < 0.8 * _roi_l1(sub, kf, roi)
    # all frozen: nothing to fit
    same = finetune_subset(sub, [kf], iters=20, frozen=np.ones(16, bool))
    assert torch.equal(same.colors, sub.colors)
    with pytest.raises(ValueError, match="frozen"):
        finetune_subset(sub, [kf], iters=5, frozen=np.ones(15, bool))


def test_update_shared_subset_changes_only_new_and_refreshed_rows_of_the_servers_copy():
    """The server holds rows 0..11 (ids 100..111) at known values; the agent's subset drops id 100 and
    adds ids 200..204. Only the new rows and ⌊refresh × held⌋ held rows may differ from the server's
    copy (κ aside: every held row carries the agent's κ), and a delta push of the result carries exactly
    those, with the κ growth of the others as the delta's κ shift, so the server's κ is the agent's."""
    from gausslite.sharing import update_shared_subset
    from gausslite.wire.codec import GaussianArrays
    from gausslite.wire.delta import PushPlanner

    kf, roi = _roi_keyframe()
    server = GaussianArrays.from_any(_grid_subset())  # 16 rows
    planner = PushPlanner("a")
    first = planner.plan(np.arange(100, 116), server, version=1)
    planner.acknowledge(first)
    base, base_ids = first.subset, first.ids
    # the agent's current values: every held row has drifted (as the mapper moves them), 5 new rows
    agent_ids = np.concatenate([np.arange(101, 116), np.arange(200, 205)])
    order = np.argsort(base_ids)
    held = base.take(order[np.searchsorted(base_ids, np.arange(101, 116), sorter=order)])
    drift = GaussianArrays(**{k: getattr(held, k) for k in GaussianArrays.FIELDS})
    drift.colors[:] = np.clip(drift.colors + 0.05, 0, 1)
    drift.kappa[:] += 40
    new = GaussianArrays.from_any(_grid_subset(n_side=3, z=1.95)).take(np.arange(5))
    agent = GaussianArrays(**{k: np.concatenate([getattr(drift, k), getattr(new, k)]) for k in GaussianArrays.FIELDS})
    for refresh, n_refresh in ((0.0, 0), (0.2, 3), (1.0, 15)):
        out, st = update_shared_subset(agent, agent_ids, base, base_ids, [kf], iters=40, refresh=refresh, seed=0)
        assert st == {"base": 15, "new": 5, "refreshed": n_refresh}
        assert len(out) == 20
        srv = base.take(order[np.searchsorted(base_ids, agent_ids[:15], sorter=order)])
        same = np.all([np.all(getattr(out, k)[:15].reshape(15, -1) == getattr(srv, k).reshape(15, -1), axis=1)
                       for k in GaussianArrays.FIELDS if k != "kappa"], axis=0)
        assert int((~same).sum()) <= n_refresh and int(same.sum()) >= 15 - n_refresh
        if refresh < 1.0:
            assert int((~same).sum()) == n_refresh
        # every held row carries the agent's κ
        assert np.array_equal(out.kappa[:15], drift.kappa)
        p = PushPlanner("a")
        p.acknowledge(first)
        plan = p.plan(agent_ids, out, version=2, measure_full=False)
        assert plan.is_delta and plan.n_removed == 1 and plan.n_records == 5 + int((~same).sum())
        if refresh < 1.0:
            assert p.last_stats["kappa_shift"] == 40
        # the server's rebuilt copy (the planner mirrors it) holds the agent's κ on every row
        ix = np.argsort(plan.ids)
        assert np.array_equal(plan.subset.kappa[ix][np.searchsorted(plan.ids[ix], agent_ids)], out.kappa)
    # no base: the plain fine-tune of the agent's values
    out, st = update_shared_subset(agent, agent_ids, None, None, [kf], iters=10, refresh=0.1, seed=0)
    assert st == {"base": 0, "new": 20, "refreshed": 0} and len(out) == 20
    with pytest.raises(ValueError):
        update_shared_subset(agent, agent_ids, base, base_ids, [kf], iters=10, refresh=1.5)
    with pytest.raises(ValueError):
        update_shared_subset(agent, agent_ids[:-1], base, base_ids, [kf], iters=10)


def test_the_share_rule_has_one_set_of_defaults_the_agents():
    """``ShareConfig()`` is what an agent shares with (``agent.share``): the measured rule, rendered candidates
    bounded at 25 % of the map."""
    from gausslite.mission.config import AgentConfig

    assert ShareConfig() == AgentConfig().share
    assert (ShareConfig().rule, ShareConfig().candidates, ShareConfig().max_fraction) == ("task", "rendered", 0.25)
