"""gausslite.stats: the paired per-frame gain every report gives, with its Student-t interval."""

import math

import numpy as np
import pytest

from gausslite.stats import fmt_gain, paired_gain, significant


def test_a_paired_gain_is_the_mean_of_per_frame_differences_with_a_t_interval():
    rng = np.random.default_rng(0)
    base = {i: float(v) for i, v in enumerate(rng.normal(20.0, 2.0, 40))}
    diff = rng.normal(1.0, 0.5, 40)
    treated = {str(i): base[i] + float(d) for i, d in enumerate(diff)}  # keys read back from JSON pair with ints
    treated["99"] = 50.0  # a frame only one map scored is no pair
    g = paired_gain(treated, base)
    assert g["n"] == 40 and g["gain"] == pytest.approx(diff.mean())
    from scipy import stats

    lo, hi = stats.t.interval(0.95, 39, loc=diff.mean(), scale=diff.std(ddof=1) / math.sqrt(40))
    assert (g["ci_low"], g["ci_high"]) == (pytest.approx(lo), pytest.approx(hi))
    assert significant(g) and fmt_gain(g) == f"{diff.mean():+.2f} [{lo:+.2f}, {hi:+.2f}]"
    # the frames' own spread cancels in the pairs: unpaired, the spread of the two maps' means would swamp the gain
    assert g["half_width"] < 0.5


def test_runs_pair_by_position_over_runs_and_frames_and_missing_figures_are_no_pairs():
    a = [{0: 21.0, 1: 22.0}, {0: 20.0, 1: None}]
    b = [{0: 20.0, 1: 20.0}, {0: 20.5, 1: 19.0}]
    g = paired_gain(a, b)
    assert g["n"] == 3 and g["gain"] == pytest.approx((1.0 + 2.0 - 0.5) / 3)
    one = paired_gain({0: 2.0}, {0: 1.0})
    assert one["gain"] == 1.0 and one["ci_low"] is None and not significant(one) and fmt_gain(one) == "+1.00"
    none = paired_gain({}, {0: 1.0})
    assert none["gain"] is None and none["n"] == 0 and fmt_gain(none) == "–"
    with pytest.raises(ValueError):
        paired_gain([{}], [{}, {}])
    with pytest.raises(ValueError):
        paired_gain({0: 1.0}, {0: 1.0}, level=1.0)
