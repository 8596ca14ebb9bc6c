"""gausslite.stats: the paired gain every report gives, with its per-frame interval over one run's frames and its
run-clustered interval over several runs."""

import math

import numpy as np
import pytest

from gausslite.stats import fmt_gain, paired_gain, significant


def test_one_runs_gain_is_the_mean_of_its_per_frame_differences_with_a_t_interval():
    rng = np.random.default_rng(0)
    base = {i: float(v) for i, v in enumerate(rng.normal(20.0, 2.0, 40))}
    diff = rng.normal(1.0, 0.5, 40)
    treated = {str(i): base[i] + float(d) for i, d in enumerate(diff)}  # keys read back from JSON pair with ints
    treated["99"] = 50.0  # a frame only one map scored is no pair
    g = paired_gain(treated, base)
    assert g["n"] == 40 and g["gain"] == pytest.approx(diff.mean())
    assert g["interval"] == "per-frame" and g["runs"] == 1
    from scipy import stats

    lo, hi = stats.t.interval(0.95, 39, loc=diff.mean(), scale=diff.std(ddof=1) / math.sqrt(40))
    assert (g["ci_low"], g["ci_high"]) == (pytest.approx(lo), pytest.approx(hi))
    assert significant(g) and fmt_gain(g) == f"{diff.mean():+.2f} [{lo:+.2f}, {hi:+.2f}]"
    # the frames' own spread cancels in the pairs: unpaired, the spread of the two maps' means would swamp the gain
    assert g["half_width"] < 0.5


def test_several_runs_give_the_t_interval_over_the_per_run_gains_not_over_runs_x_frames():
    """Frames of one run share its map: a run whose gain is 3 dB and another whose gain is 0 dB are two observations
    of the gain, whatever their frame counts. The pooled interval over runs × frames would exclude zero here."""
    rng = np.random.default_rng(1)
    run_gains = [3.0, 0.1, 1.5, -0.4]
    base, treated = [], []
    for r, gain in enumerate(run_gains):
        b = {i: float(v) for i, v in enumerate(rng.normal(20.0, 2.0, 30))}
        noise = rng.normal(0.0, 0.3, 30)
        noise -= noise.mean()  # each run's mean difference is exactly its gain
        base.append(b)
        treated.append({str(i): b[i] + gain + float(e) for i, e in enumerate(noise)})
    g = paired_gain(treated, base)
    from scipy import stats

    m, s = float(np.mean(run_gains)), float(np.std(run_gains, ddof=1))
    lo, hi = stats.t.interval(0.95, len(run_gains) - 1, loc=m, scale=s / math.sqrt(len(run_gains)))
    assert g["interval"] == "run-clustered" and g["runs"] == 4 and g["n"] == 120
    assert g["run_gains"] == [pytest.approx(x) for x in run_gains]
    assert g["gain"] == pytest.approx(m) and g["std"] == pytest.approx(s)
    assert (g["ci_low"], g["ci_high"]) == (pytest.approx(lo), pytest.approx(hi))
    assert g["ci_low"] < 0 < g["ci_high"] and not significant(g)
    # what the runs × frames pooling reported: the same mean, an interval that wrongly excludes zero
    pooled = paired_gain({(r, k): v for r, t in enumerate(treated) for k, v in t.items()},
                         {(r, str(k)): v for r, b in enumerate(base) for k, v in b.items()})
    assert pooled["n"] == 120 and pooled["ci_low"] > 0 and pooled["half_width"] < g["half_width"] / 3


def test_runs_weigh_the_same_whatever_their_pair_counts_and_missing_figures_are_no_pairs():
    a = [{0: 21.0, 1: 22.0}, {0: 20.0, 1: None}, None]
    b = [{0: 20.0, 1: 20.0}, {0: 20.5, 1: 19.0}, {0: 20.0}]
    g = paired_gain(a, b)
    assert g["n"] == 3 and g["runs"] == 2 and g["run_gains"] == [1.5, -0.5]
    assert g["gain"] == pytest.approx(0.5) and g["interval"] == "run-clustered"
    # one run in a sequence is one run: its per-frame interval, said so
    single = paired_gain([a[0]], [b[0]])
    assert single["interval"] == "per-frame" and single["runs"] == 1 and single["ci_low"] is not None
    one = paired_gain({0: 2.0}, {0: 1.0})
    assert one["gain"] == 1.0 and one["ci_low"] is None and not significant(one) and fmt_gain(one) == "+1.00"
    none = paired_gain({}, {0: 1.0})
    assert none["gain"] is None and none["n"] == 0 and none["runs"] == 0 and fmt_gain(none) == "–"
    with pytest.raises(ValueError):
        paired_gain([{}], [{}, {}])
    with pytest.raises(ValueError):
        paired_gain([{0: 1.0}], {0: 1.0})
    with pytest.raises(ValueError):
        paired_gain({0: 1.0}, {0: 1.0}, level=1.0)


def test_the_unpaired_gain_is_the_difference_of_means_with_welchs_interval():
    from scipy import stats

    from gausslite.stats import unpaired_gain

    g, u = [22.1, 23.4, 21.9, 22.8], [21.0, 20.2, 21.5]
    got = unpaired_gain(g, u + [None, float("nan")])
    want = stats.ttest_ind(g, u, equal_var=False).confidence_interval(0.95)
    assert got["gain"] == pytest.approx(sum(g) / 4 - sum(u) / 3) and got["interval"] == "unpaired"
    assert (got["ci_low"], got["ci_high"]) == (pytest.approx(want.low), pytest.approx(want.high))
    assert (got["n_treated"], got["n_baseline"]) == (4, 3)
    one = unpaired_gain([22.0], u)
    assert one["gain"] == pytest.approx(22.0 - sum(u) / 3) and one["ci_low"] is None
    assert unpaired_gain([], u)["gain"] is None
    with pytest.raises(ValueError, match="level"):
        unpaired_gain(g, u, level=1.0)
