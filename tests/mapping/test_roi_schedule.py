"""The ROI schedule (gausslite.mapping.schedule, docs/mapper.md "The ROI schedule"): the warm-up and the ROI phase
scale with the iterations a keyframe really gets, and a keyframe that gets few still gives the task region
``roi_min_iters`` of them, also when few keyframes see the region."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.mapping.config import MapperConfig, deep_merge
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.schedule import RoiSchedule
from tests._scenes import plane_frame, plane_roi

H, W = 40, 56


def _roi() -> np.ndarray:
    return plane_roi(H, W)


def _cfg(**kw) -> MapperConfig:
    """The mapper on the work clock (deterministic budgets), a window of 2 keyframes."""
    cfg = MapperConfig(**deep_merge(dict(seeding={"seeds_per_frame": 300}, iters_per_frame=30, warmup_iters=10,
                                         window=2, recent_prob=0.5, backend="warp", mode="gausslite",
                                         budget_clock="work"), kw))
    cfg.densify.enabled = False
    return cfg


@pytest.mark.parametrize("warmup, per_frame, owed, expected", [
    (10, 30, 2, 10),  # the paper's schedule is untouched at rich compute
    (10, 11, 2, 9),  # shortened to leave the region its iterations
    (3, 3, 2, 1),  # but never below one full-image iteration for the new seeds
    (0, 30, 2, 0),  # no warm-up stays none
    (4, 5, 0, 4),  # the rule off: the plain split
])
def test_a_fixed_count_warm_up_leaves_the_region_its_iterations(warmup, per_frame, owed, expected):
    assert RoiSchedule(warmup, per_frame, owed).warm_iters == expected


def test_a_budgeted_warm_up_ends_early_when_the_iterations_left_would_starve_the_region():
    s = RoiSchedule(10, 30, 2)
    assert s.warm_share == pytest.approx(1 / 3)
    assert s.warm_in_time(0, False, 0.5)  # the first iteration is always full-image
    assert s.warm_in_time(1, True, None)  # no prediction yet: the time split decides
    assert s.warm_in_time(1, True, 3.0) and not s.warm_in_time(1, True, 2.5)  # 3 left: this one and 2 owed
    assert not s.warm_in_time(1, False, 100.0)  # past the split
    assert not RoiSchedule(0, 30, 2).warm_in_time(0, True, 100.0)
    assert RoiSchedule.iters_left(0.3, 0.1) == pytest.approx(3.0) and RoiSchedule.iters_left(-1.0, 0.1) == 0.0
    assert RoiSchedule.iters_left(0.3, None) is None


def _mission(owed: int, budget: float = 0.02, frames: int = 12):
    """Keyframes on the work clock at about 4 iterations each; only the first two see the task region."""
    m = Mapper(_cfg(roi_min_iters=owed))
    empty = np.zeros((H, W), bool)
    return [m.map_frame(plane_frame(i, 0.02 * i, H, W), _roi() if i < 2 else empty, time_budget_s=budget)
            for i in range(frames)]


def test_at_four_iterations_per_keyframe_every_keyframe_still_fits_the_region():
    owed = _mission(2)
    plain = _mission(0)
    assert {s.iters for s in owed} == {s.iters for s in plain} == {4}  # the same compute either way
    # every keyframe: one full-image iteration at least and the region's two, though 10 of 12 keyframes miss it
    assert all(s.active_iters >= 2 and s.iters - s.active_iters >= 1 for s in owed), [s.active_iters for s in owed]
    # the plain split leaves some keyframes without a single region iteration
    assert min(s.active_iters for s in plain) == 0
    assert sum(s.active_iters for s in owed) > sum(s.active_iters for s in plain)


def test_roi_iterations_count_only_views_that_show_the_region():
    """An ROI-phase iteration drawn on a keyframe without ROI pixels is a full-image iteration (Mapper.step), and it
    is not counted as an ROI iteration: the agent's status and the resolution governor read this count."""
    m = Mapper(_cfg(roi_min_iters=0, window=1, recent_prob=1.0))
    empty = np.zeros((H, W), bool)
    m.map_frame(plane_frame(0, 0.0, H, W), _roi(), time_budget_s=0.02)
    st = m.map_frame(plane_frame(1, 0.02, H, W), empty, time_budget_s=0.02)  # the window: this keyframe alone
    assert st.iters >= 2 and st.active_iters == 0
