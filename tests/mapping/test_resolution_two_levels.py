"""Two mapping resolutions decided separately (gausslite.mapping.resolution, docs/live.md "Mapping resolution"): the
background's level and the task region's, each corrected from the iterations it measures, both ways, without
alternating between two levels, the region staying at least twice as fine as a background that stepped down; the
keyframe at the region's level handed to the mapper as a DetailView (the runtime and the offline budgeted path)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from gausslite.mapping.budget import WorkCost
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.detail import DetailView
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.resolution import AdaptiveLevel, ResolutionGovernor, nearest_mask, uses_detail
from gausslite.mission.config import AgentConfig, ResolutionConfig
from gausslite.pipeline import TimeBudget, run_mapping
from tests._scenes import plane_frame

LOGGER = "gausslite.mapping.resolution"


def _model_machine(g: ResolutionGovernor, load: float, budget_s: float = 0.5, n: int = 6000) -> int:
    """Iterations a keyframe gets at the governor's level when the machine is the work model slowed ``load`` times."""
    w, h = g.size(g.factor)
    return int(budget_s / (load * g.iter_seconds(w * h, n)))


def test_the_background_steps_coarser_under_load_and_finer_again_when_it_goes(caplog):
    """A 640x480 stream at 0.5 s maps at 320x240 (14 iterations a keyframe on the work model's machine); four times
    the load takes it to 160x120, and when the load goes it comes back level by level to 320x240 and stays there:
    native would get 5.7 iterations by the model, short of 0.75 x 10."""
    g = ResolutionGovernor(target_iters=10, adapt_after=3, min_width=64, hold_keyframes=6)
    assert g.start(640, 480, 0.5, 6000).factor == 2.0
    g.record(_model_machine(g, 1.0))  # the first keyframe is never counted
    levels = []
    with caplog.at_level(logging.INFO, logger=LOGGER):
        for load in [1.0] * 30 + [4.0] * 30 + [1.0] * 60:
            g.record(_model_machine(g, load), gaussians=6000)
            levels.append(g.factor)
    assert set(levels[:30]) == {2.0}  # alone: it holds
    assert max(levels[30:60]) == 4.0 and levels[59] == 4.0  # loaded: down to 160x120
    assert set(levels[-40:]) == {2.0}  # the load gone: back to 320x240, and it stays
    assert g.changes == 4  # 2 -> 3 -> 4 -> 3 -> 2: no level left and taken again
    lowered = [r for r in caplog.records if "lowered" in r.getMessage()]
    raised = [r for r in caplog.records if "raised" in r.getMessage()]
    assert len(lowered) == len(raised) == 2
    assert {r.levelno for r in lowered} == {logging.WARNING} and {r.levelno for r in raised} == {logging.INFO}
    st = g.status()
    assert (st["mapping_width"], st["mapping_height"], st["resolution_changes"]) == (320, 240, 4)
    assert st["keyframe_iters_recent"] == pytest.approx(_model_machine(g, 1.0))


def test_a_finer_level_the_work_model_misjudges_is_retried_ever_more_rarely():
    """The model predicts 8.9 iterations at 320x240 from 14 at 160x120, but the machine gives 4 there: each finer step
    is undone, and the hold before the next one doubles (6, 12, 24, 48 keyframes), so in 200 keyframes the governor
    tries 320x240 five times instead of twenty-two."""
    g = ResolutionGovernor(target_iters=10, adapt_after=3, min_width=64, hold_keyframes=6)
    g.start(320, 240, 0.5, 6000)
    assert g.factor == 1.0
    machine = {1.0: 4, 2.0: 14}
    g.record(machine[g.factor])
    finer_at = []
    for k in range(200):
        before = g.factor
        g.record(machine[g.factor], gaussians=6000)
        if g.factor < before:
            finer_at.append(k)
    gaps = np.diff(finer_at)
    assert 4 <= len(finer_at) <= 5 and g.changes <= 2 * len(finer_at) + 1
    assert list(gaps[:3]) == sorted(gaps[:3]) and gaps[2] >= 2 * gaps[0]  # the hold grows
    assert g.background.hold == 48  # 8 x its start at most


def test_the_levels_hold_at_constant_load_and_finer_steps_can_be_turned_off():
    g = ResolutionGovernor(target_iters=10, adapt_after=3, min_width=64, hold_keyframes=6, finer=False)
    g.start(640, 480, 0.5, 6000)
    for load in [4.0] * 20 + [1.0] * 40:
        g.record(_model_machine(g, load))
    assert g.factor == 4.0 and g.changes == 2  # the one-way rule: never back
    level = AdaptiveLevel(2.0, 4, target=10, tolerance=0.5, finer_share=0.3, adapt_after=2, hold=1)
    assert level.finer_share == 0.5  # a finer level is only taken when it is predicted to hold
    with pytest.raises(ValueError):
        AdaptiveLevel(0.5, 4, target=10)


def test_the_region_has_its_own_level_and_stays_twice_as_fine_as_a_background_that_stepped_down(caplog):
    g = ResolutionGovernor(target_iters=10, adapt_after=2, min_width=64, hold_keyframes=4, roi_target_iters=6)
    g.start(640, 480, 0.5, 6000, region=True)
    st = g.status()
    assert (g.factor, g.roi_factor) == (2.0, 1.0)  # the region starts at native
    assert (st["region_width"], st["region_height"], st["region_detail"]) == (640, 480, True)
    g.record(10, 6)  # the first keyframe is never counted
    with caplog.at_level(logging.INFO, logger=LOGGER):
        for _ in range(4):  # the background starves, the region gets its iterations: only the background steps
            g.record(3, 8, gaussians=6000)
        assert (g.factor, g.roi_factor) == (4.0, 1.0)
        st = g.status()
        assert (st["mapping_width"], st["region_width"]) == (160, 640) and st["region_changes"] == 0
        for _ in range(6):  # now the region starves: one level down, to half the background's downscale at most
            g.record(6, 2, gaussians=6000)
        assert (g.factor, g.roi_factor) == (4.0, 2.0)
        st = g.status()
        assert (st["region_width"], st["region_height"]) == (320, 240) == (2 * st["mapping_width"],
                                                                              2 * st["mapping_height"])
        assert st["region_changes"] == 1 and not st["region_reaches_target"] and st["region_measured_iters"] == 2.0
        short = [r for r in caplog.records if "the task region gets" in r.getMessage()]
        assert len(short) == 2 and {r.levelno for r in short} == {logging.WARNING}  # once per level, not per frame
        assert "640x480" in short[0].getMessage() and "320x240" in short[1].getMessage()
        assert "coarsest" in short[1].getMessage()
        caplog.clear()
        g.record(30, 8, gaussians=6000)  # the load goes: the background steps finer ...
    assert g.factor == 3.0 and g.roi_factor == 1.0  # ... and the region, at least twice as fine, goes with it
    assert any("task region resolution raised to 640x480" in r.getMessage() for r in caplog.records)
    assert g.status()["region_changes"] == 2 and g.roi_recent[-1] == 8


def test_a_pinned_level_is_kept_and_the_region_never_coarser_than_the_background():
    g = ResolutionGovernor(target_iters=10, adapt_after=2, min_width=64, pinned=4, roi_target_iters=6)
    g.start(640, 480, 0.5, 6000, region=True)
    for _ in range(6):
        g.record(2, 1)
    assert (g.factor, g.roi_factor, g.changes) == (4.0, 2.0, 0)  # the region moved, the pinned background did not
    r = ResolutionGovernor(target_iters=10, adapt_after=2, min_width=64, pinned=2, roi_pinned=3)
    r.start(640, 480, 0.5, 6000, region=True)
    for _ in range(6):
        r.record(2, 1)
    assert (r.factor, r.roi_factor, r.status()["region_changes"]) == (2.0, 2.0, 0)
    assert not r.status()["region_detail"]
    with pytest.raises(ValueError):
        ResolutionGovernor(roi_ratio=0.5)


def test_without_a_region_level_the_region_is_the_background_and_nothing_changes_there():
    g = ResolutionGovernor(target_iters=10, adapt_after=2, min_width=64)
    g.start(640, 480, 0.5, 6000)
    g.record(10, 4)
    for _ in range(4):
        g.record(3, 1)
    st = g.status()
    assert g.region is None and g.roi_factor == g.factor == 4.0
    assert (st["region_width"], st["region_downscale"], st["region_detail"]) == (160, 4.0, False)
    assert st["roi_iters_recent"] == 1.0 and st["region_changes"] == 0
    assert g.detail_view(plane_frame(0, 0.0, 48, 64), np.ones((12, 16), bool)) is None


def test_the_detail_view_is_the_native_keyframe_with_its_region_carried_over():
    g = ResolutionGovernor(target_iters=10, pinned=2, min_width=16)
    g.start(64, 48, 0.5, 2000, region=True)
    native = plane_frame(5, 0.0, 48, 64)
    w = np.zeros((24, 32), bool)
    w[5:11, 7:20] = True
    between = [plane_frame(3, 0.0, 48, 64), object(), plane_frame(4, 0.0, 48, 64)]
    d = g.detail_view(native, w, between)
    assert isinstance(d, DetailView) and d.frame is native  # the region at native size: the frame as it came
    assert d.relevance.shape == (48, 64) and d.relevance.dtype == bool
    assert np.array_equal(d.relevance, np.kron(w, np.ones((2, 2), bool)))
    assert [f.frame_id for f in d.between] == [3, 4]  # only decoded frames come along
    assert g.detail_view(native, None) is None
    assert np.array_equal(nearest_mask(np.eye(2, dtype=bool), (4, 6)), np.repeat(np.repeat(np.eye(2, dtype=bool),
                                                                                            2, 0), 3, 1))


def test_the_config_builds_both_levels():
    rc = ResolutionConfig(roi_downscale=1, finer_share=0.9, hold_keyframes=7, roi_ratio=3)
    g = rc.governor(MapperConfig(warmup_iters=10, iters_per_frame=30))
    assert (g.roi_pinned, g.finer_share, g.hold_keyframes, g.roi_ratio) == (1.0, 0.9, 7, 3.0)
    # one-way by default (docs/live.md, "Mapping resolution": the finer step does not pay on real data)
    assert ResolutionConfig().finer is False and not g.finer and ResolutionConfig(finer=True).governor(
        MapperConfig()).finer
    assert g.roi_target_iters == pytest.approx(10 * 2 / 3)  # the ROI phase's share of the keyframe's target
    assert ResolutionConfig(roi_target_iters=4).roi_target(MapperConfig()) == 4.0
    assert AgentConfig().resolution.governor(MapperConfig()).cost == WorkCost(**MapperConfig().work_cost.model_dump())
    with pytest.raises(ValueError):
        ResolutionConfig(roi_downscale=0.5)
    assert not uses_detail(MapperConfig(mode="gausslite"))
    assert uses_detail(MapperConfig(mode="gausslite", detail={"enabled": True}))
    assert not uses_detail(MapperConfig(mode="uniform", detail={"enabled": True}))


class _Frames:
    """Eight plane frames 10 cm apart (every one a keyframe), 48x64."""

    path = "planes"
    annotations = None

    def __len__(self):
        return 8

    def __getitem__(self, i):
        return plane_frame(i, 0.1 * i, 48, 64)


@pytest.mark.parametrize("enabled", [False, True])
def test_the_budgeted_offline_path_hands_the_mapper_a_detail_view_only_with_the_detail_layer(monkeypatch, enabled):
    seen = []
    orig = Mapper.map_frame

    def spy(self, frame, relevance=None, **kw):
        seen.append(kw.get("detail"))
        return orig(self, frame, relevance, **kw)

    monkeypatch.setattr(Mapper, "map_frame", spy)
    cfg = MapperConfig(mode="gausslite", budget_clock="work", iters_per_frame=3, warmup_iters=1,
                       detail={"enabled": enabled})
    gov = ResolutionGovernor(pinned=2, min_width=16)
    region = np.zeros((24, 32), bool)
    region[6:18, 8:24] = True
    _, m = run_mapping(_Frames(), cfg, relevance_fn=lambda fr: nearest_mask(region, fr.depth.shape),
                       progress=False, time_budget=TimeBudget(5.0, governor=gov, score_reserve_s=0.0))
    assert len(seen) == m["n_keyframes"] > 0
    res = m["time_budget"]["resolution"]
    if enabled:
        assert all(isinstance(d, DetailView) and d.frame.intrinsics.width == 64 for d in seen)
        assert (res["region_width"], res["region_detail"], res["mapping_width"]) == (64, True, 32)
    else:
        assert seen == [None] * len(seen)
        assert (res["region_width"], res["region_detail"]) == (32, False)
