"""The mapping resolution a live agent can afford (gausslite.mapping.resolution): chosen from the work model so that a
keyframe gets the target iterations under its budget, pinned by the user, lowered from measured iterations, and said
loudly when even the coarsest level falls short."""

import logging

import numpy as np
import pytest

from gausslite.mapping.budget import WorkCost
from gausslite.mapping.resolution import (ResolutionGovernor, choose_downscale, downscale_frame, predict_iters)
from tests._scenes import plane_frame


def test_a_larger_image_buys_fewer_iterations():
    cost = WorkCost()
    assert predict_iters(640, 480, 0.5, 6000, cost) < predict_iters(320, 240, 0.5, 6000, cost) / 2.5


def test_the_smallest_downscale_that_reaches_the_target_is_chosen():
    """At 0.5 s per keyframe and a 6,000 cap, the CI machine's model gives a 640x480 keyframe under 10 iterations
    and a 320x240 one over 10: a RealSense stream maps at half its size, the TUM bench's 320x240 at its own."""
    cost = WorkCost()
    c = choose_downscale(640, 480, 0.5, 6000, cost, target_iters=10)
    assert (c.factor, c.width, c.height, c.reaches_target, c.pinned) == (2.0, 320, 240, True, False)
    assert c.predicted_iters >= 10
    assert choose_downscale(320, 240, 0.5, 6000, cost, 10).factor == 1.0
    short = choose_downscale(640, 480, 0.02, 6000, cost, 10, max_downscale=3)
    assert short.factor == 3.0 and not short.reaches_target and "coarsest" in short.reason
    assert choose_downscale(640, 480, None, 6000, cost, 10).factor == 1.0  # offline: no budget, native size
    pinned = choose_downscale(640, 480, 0.5, 6000, cost, 10, pinned=1.0)
    assert pinned.pinned and pinned.factor == 1.0 and not pinned.reaches_target
    with pytest.raises(ValueError):
        choose_downscale(640, 480, 0.5, 6000, cost, 10, pinned=0.5)


def test_downscaled_frames_keep_pixel_centres_and_pose():
    fr = plane_frame(3, 0.1, 40, 56)
    half = downscale_frame(fr, 2)
    assert half.rgb.shape == (20, 28, 3) and half.depth.shape == (20, 28)
    assert (half.intrinsics.width, half.intrinsics.height) == (28, 20)
    assert half.intrinsics.fx == pytest.approx(25.0) and half.intrinsics.cx == pytest.approx((fr.intrinsics.cx + .5) / 2 - .5)
    assert np.array_equal(half.c2w, fr.c2w) and half.frame_id == 3 and downscale_frame(fr, 1) is fr


def test_the_governor_lowers_the_level_from_measured_iterations_and_warns_once_at_the_coarsest(caplog):
    g = ResolutionGovernor(target_iters=10, max_downscale=2, adapt_after=2, min_width=64, tolerance=1.0)
    with caplog.at_level(logging.INFO, logger="gausslite.mapping.resolution"):
        first = g.start(320, 240, 0.5, 6000)
    assert first.factor == 1.0 and "mapping resolution 320x240" in caplog.text
    assert g.record(2) is None  # the first keyframe is never counted
    assert g.record(4) is None  # one keyframe is not a measurement yet
    changed = g.record(5)
    assert changed is not None and changed.factor == 2.0 and (changed.width, changed.height) == (160, 120)
    assert g.changes == 1 and g.apply(plane_frame(0, 0.0, 40, 56)).rgb.shape == (20, 28, 3)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="gausslite.mapping.resolution"):
        for _ in range(6):
            assert g.record(3) is None  # coarsest level: no further change
    errors = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1 and "below the target" in errors[0].getMessage()
    st = g.status()
    assert st["mapping_downscale"] == 2.0 and st["resolution_changes"] == 1 and not st["resolution_reaches_target"]
    assert st["resolution_measured_iters"] == pytest.approx(3.0)


def test_a_pinned_resolution_is_never_changed():
    g = ResolutionGovernor(target_iters=10, pinned=1.0, adapt_after=1)
    g.start(640, 480, 0.5, 6000)
    for _ in range(5):
        assert g.record(2) is None
    assert g.factor == 1.0 and g.changes == 0 and g.status()["resolution_pinned"]


def test_automatic_levels_never_map_narrower_than_the_floor():
    cost = WorkCost()
    assert choose_downscale(64, 48, 0.001, 6000, cost, 10).factor == 1.0  # already narrow: native, said unreachable
    assert choose_downscale(640, 480, 0.001, 6000, cost, 10, max_downscale=8).factor == 4.0  # 160 px wide at most


def test_a_level_holds_while_its_keyframes_get_most_of_the_target():
    """Run-to-run noise around the target (a 320x240 TUM mission gets 9-13 iterations at 0.5 s) keeps the level;
    the level drops below ``tolerance`` × target."""
    g = ResolutionGovernor(target_iters=10, adapt_after=3, min_width=64, tolerance=0.75)
    g.start(320, 240, 0.5, 6000)
    for it in (3, 9, 8, 10, 9, 8):
        assert g.record(it) is None
    assert g.factor == 1.0 and g.status()["resolution_reaches_target"]
    for it in (5, 6, 7):
        g.record(it)
    assert g.factor == 2.0
