"""Statistics over random seeds and frames: every quality comparison is a mean over seeds with its spread, every
gain a mean of paired per-frame differences with its 95 % interval (:func:`paired_gain`: over one run's frames, or
run-clustered over several runs).

Single mapping runs swing by up to 2 dB (seeding, view sampling, and even the floating-point
summation order of the rasterizer's threads), so figures are reported as mean ± sample standard
deviation over seeds, and a gain counts only when it exceeds twice its standard deviation.
"""

from __future__ import annotations

import math
from typing import Iterable, Mapping, Optional, Sequence

import numpy as np


def mean_std(values: Iterable[Optional[float]]) -> tuple[Optional[float], Optional[float]]:
    """Mean and sample standard deviation (ddof=1; 0 for one value) of the finite values.

    Returns:
        (None, None) when no value is finite.
    """
    v = np.array([x for x in values if x is not None and math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return None, None
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else 0.0


def aggregate(runs: Sequence[Mapping], keys: Iterable[str]) -> dict:
    """``{key: mean, key_std: std}`` over ``runs`` (one dict per seed) for each scalar ``key``.

    List-valued keys (equal lengths) are aggregated element-wise into lists.
    """
    out: dict = {}
    for k in keys:
        vals = [r.get(k) for r in runs]
        if vals and all(isinstance(v, (list, tuple)) for v in vals):
            cols = list(zip(*vals))
            pairs = [mean_std(c) for c in cols]
            out[k] = [p[0] for p in pairs]
            out[k + "_std"] = [p[1] for p in pairs]
        else:
            out[k], out[k + "_std"] = mean_std(vals)
    return out


def gain(treated: Sequence[Optional[float]], baseline: Sequence[Optional[float]]) -> dict:
    """Paired gain ``treated − baseline`` per seed: mean, std, and whether it is significant
    (mean > 2 × std, with at least two seeds).

    Raises:
        ValueError: the two sequences differ in length.
    """
    if len(treated) != len(baseline):
        raise ValueError(f"paired gain needs equal lengths, got {len(treated)} and {len(baseline)}")
    diffs = [t - b for t, b in zip(treated, baseline) if t is not None and b is not None]
    m, s = mean_std(diffs)
    significant = m is not None and len(diffs) >= 2 and m > 2.0 * (s or 0.0)
    return {"gain": m, "gain_std": s, "n": len(diffs), "significant": bool(significant)}


def fmt(mean: Optional[float], std: Optional[float], digits: int = 2) -> str:
    """``"m ± s"`` (or ``"m"`` without a spread, ``"–"`` without a value)."""
    if mean is None:
        return "–"
    if std is None:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


def _pair_key(k):
    """A pairing key as written by either side: frame ids read back from JSON are strings, fresh ones ints."""
    if isinstance(k, tuple):
        return tuple(_pair_key(x) for x in k)
    try:
        return int(k)
    except (TypeError, ValueError):
        return k


def _differences(treated: Mapping, baseline: Mapping) -> np.ndarray:
    """(n,) float64 ``treated[k] − baseline[k]`` over the keys both hold a finite value for (keys read from JSON as
    strings pair with int keys)."""
    t = {_pair_key(k): v for k, v in (treated or {}).items()}
    b = {_pair_key(k): v for k, v in (baseline or {}).items()}
    return np.array([t[k] - b[k] for k in t if k in b and t[k] is not None and b[k] is not None
                     and math.isfinite(t[k]) and math.isfinite(b[k])], dtype=np.float64)


def _t_interval(x: np.ndarray, level: float) -> tuple[float, float]:
    """(sample std, half-width) of the two-sided Student-t interval of the mean of ``x`` (at least two values)."""
    # lazy: SciPy only where an interval is computed
    from scipy.stats import t as student_t

    s = float(x.std(ddof=1))
    return s, float(student_t.ppf(0.5 + level / 2.0, x.size - 1)) * s / math.sqrt(x.size)


def paired_gain(treated, baseline, level: float = 0.95) -> dict:
    """Mean of the paired differences ``treated[k] − baseline[k]`` with its two-sided ``level`` interval: every gain
    of a report (GaussLite − uniform, fused − own) is this.

    - **One run** (two mappings, frame id → value): the pairs are that run's frames and the interval is the
      Student-t interval over them (``"interval": "per-frame"``). It says how precisely this run's gain is measured
      on these frames, not how another run would come out.
    - **Several runs** (two sequences of mappings, paired by position: run ``i`` of ``treated`` with run ``i`` of
      ``baseline``): frames of one run share its map, seed and timing, so they are not independent pairs and
      pooling runs × frames under one t-interval makes it far too narrow. Each run is reduced to its own gain, the
      mean of its paired per-frame differences, and the interval is the Student-t interval over those per-run gains
      with ``runs − 1`` degrees of freedom (``"interval": "run-clustered"``): inference at the level of the cluster
      means, which stays valid with as few as three clusters when their means are about normal (Donald & Lang 2007,
      "Inference with Difference-in-Differences and Other Panel Data", Rev. Econ. Stat. 89(2); Cameron & Miller
      2015, "A Practitioner's Guide to Cluster-Robust Inference", J. Human Resources 50(2), Sec. VI, few clusters).
      A cluster bootstrap (Field & Welsh 2007, JRSS-B 69(3)) is not used: over 3–6 runs it has a handful of distinct
      resamples and undercovers. ``gain`` is then the mean of the per-run gains (each run weighs the same, the
      centre of that interval; equal to the pooled frame mean when every run has as many pairs). A sequence with a
      single run holding pairs is one run: its per-frame interval (``"per-frame"``).

    Args:
        treated, baseline: key → value (e.g. frame id → ROI PSNR in dB; keys read from JSON as strings pair with int
            keys; None or non-finite values are no pair), or two sequences of such mappings, one per run (a None
            entry: a run without figures).
        level: the interval's coverage.
    Returns:
        ``{"gain", "ci_low", "ci_high", "half_width", "std", "n", "runs", "run_gains", "interval"}``: ``n`` the
        frame pairs, ``runs`` the runs holding at least one pair (1 for two mappings), ``run_gains`` each such
        run's mean difference, ``std`` the sample std of the units the interval is over (frames of one run, or the
        per-run gains), ``interval`` ``"per-frame"`` or ``"run-clustered"``. The interval is None below two units;
        every figure None without a pair.
    Raises:
        ValueError: ``level`` outside (0, 1), one side a mapping and the other a sequence, or sequences of different
            lengths.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if isinstance(treated, Mapping) != isinstance(baseline, Mapping):
        raise ValueError("paired_gain needs two mappings (one run) or two sequences of mappings (runs)")
    per_run = [treated] if isinstance(treated, Mapping) else list(treated)
    base_runs = [baseline] if isinstance(baseline, Mapping) else list(baseline)
    if len(per_run) != len(base_runs):
        raise ValueError(f"paired runs need equal lengths, got {len(per_run)} and {len(base_runs)}")
    diffs = [d for d in (_differences(t, b) for t, b in zip(per_run, base_runs)) if d.size]
    run_gains = [float(d.mean()) for d in diffs]
    out = {"gain": None, "ci_low": None, "ci_high": None, "half_width": None, "std": None,
           "n": int(sum(d.size for d in diffs)), "runs": len(diffs), "run_gains": run_gains,
           "interval": "run-clustered" if len(diffs) > 1 else "per-frame"}
    if not diffs:
        return out
    units = np.array(run_gains) if len(diffs) > 1 else diffs[0]
    out["gain"] = float(units.mean())
    if units.size > 1:
        s, hw = _t_interval(units, level)
        out.update(std=s, half_width=hw, ci_low=out["gain"] - hw, ci_high=out["gain"] + hw)
    return out


def unpaired_gain(treated: Sequence[Optional[float]], baseline: Sequence[Optional[float]],
                  level: float = 0.95) -> dict:
    """Difference of the means ``mean(treated) − mean(baseline)`` of two independent samples (e.g. each mode's
    per-run ROI PSNR in dB, when the runs cannot be paired), with its two-sided Welch interval (Student t with the
    Welch–Satterthwaite degrees of freedom; Welch 1947, Biometrika 34): the figure for a comparison whose runs
    mapped under different conditions, wider than a paired one.

    Args:
        treated, baseline: the values (None or non-finite ones are left out).
        level: the interval's coverage.
    Returns:
        ``{"gain", "ci_low", "ci_high", "half_width", "n_treated", "n_baseline", "interval": "unpaired"}``; the
        interval None unless both samples hold at least two values (or both have no spread); every figure None
        when a sample is empty.
    Raises:
        ValueError: ``level`` outside (0, 1).
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    t = np.array([v for v in treated if v is not None and math.isfinite(v)], dtype=np.float64)
    b = np.array([v for v in baseline if v is not None and math.isfinite(v)], dtype=np.float64)
    out = {"gain": None, "ci_low": None, "ci_high": None, "half_width": None, "n_treated": int(t.size),
           "n_baseline": int(b.size), "interval": "unpaired"}
    if not t.size or not b.size:
        return out
    out["gain"] = float(t.mean() - b.mean())
    if t.size < 2 or b.size < 2:
        return out
    vt, vb = t.var(ddof=1) / t.size, b.var(ddof=1) / b.size
    se = math.sqrt(vt + vb)
    if se == 0.0:
        hw = 0.0
    else:
        # lazy: SciPy only where an interval is computed
        from scipy.stats import t as student_t

        dof = (vt + vb) ** 2 / (vt ** 2 / (t.size - 1) + vb ** 2 / (b.size - 1))
        hw = float(student_t.ppf(0.5 + level / 2.0, dof)) * se
    out.update(half_width=hw, ci_low=out["gain"] - hw, ci_high=out["gain"] + hw)
    return out


def fmt_gain(g: Optional[Mapping], digits: int = 2) -> str:
    """A :func:`paired_gain` as ``"+1.23 [+0.80, +1.66]"`` (mean, 95 % interval: per-frame or run-clustered, as its
    ``interval`` says), ``"+1.23"`` without an interval, ``"–"`` without any pair."""
    if not g or g.get("gain") is None:
        return "–"
    if g.get("ci_low") is None:
        return f"{g['gain']:+.{digits}f}"
    return f"{g['gain']:+.{digits}f} [{g['ci_low']:+.{digits}f}, {g['ci_high']:+.{digits}f}]"


def significant(g: Optional[Mapping]) -> bool:
    """Whether a :func:`paired_gain`'s interval excludes zero."""
    return bool(g and g.get("ci_low") is not None and (g["ci_low"] > 0 or g["ci_high"] < 0))
