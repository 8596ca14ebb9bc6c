"""Statistics over random seeds and frames: every quality comparison is a mean over seeds with its spread, every
gain a mean of paired per-frame differences with its 95 % interval (:func:`paired_gain`).

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


def _keyed(values) -> dict:
    """``{key: value}`` of a mapping, or of a sequence of mappings (one per run): keys ``(run index, key)``."""
    if isinstance(values, Mapping):
        return {_pair_key(k): v for k, v in values.items()}
    return {(i, _pair_key(k)): v for i, m in enumerate(values) for k, v in (m or {}).items()}


def paired_gain(treated, baseline, level: float = 0.95) -> dict:
    """Mean of the paired differences ``treated[k] − baseline[k]`` over the keys both hold a finite value for, with
    its two-sided Student-t interval (``level``): every gain of a report (GaussLite − uniform, fused − own) is this,
    per frame (a frame scored by both maps is one pair).

    Args:
        treated, baseline: key → value (e.g. frame id → ROI PSNR in dB; keys read from JSON as strings pair with int
            keys), or a sequence of such mappings, one per run, paired by position (keys ``(run, frame id)``: the
            interval is then over runs × frames).
        level: the interval's coverage.
    Returns:
        ``{"gain": mean, "ci_low", "ci_high", "half_width", "std": sample std of the differences, "n": pairs}``; the
        interval is None below two pairs, every figure None without a pair. The interval treats the pairs as
        independent: frames of one run are not, so it is narrower than a spread over runs (report both).
    Raises:
        ValueError: ``level`` outside (0, 1), or one side a sequence and the other a mapping of another length.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if not isinstance(treated, Mapping) and not isinstance(baseline, Mapping) and len(treated) != len(baseline):
        raise ValueError(f"paired runs need equal lengths, got {len(treated)} and {len(baseline)}")
    t, b = _keyed(treated), _keyed(baseline)
    d = np.array([t[k] - b[k] for k in t if k in b and t[k] is not None and b[k] is not None
                  and math.isfinite(t[k]) and math.isfinite(b[k])], dtype=np.float64)
    out = {"gain": None, "ci_low": None, "ci_high": None, "half_width": None, "std": None, "n": int(d.size)}
    if d.size == 0:
        return out
    out["gain"] = float(d.mean())
    if d.size > 1:
        # lazy: SciPy only where an interval is computed
        from scipy.stats import t as student_t

        s = float(d.std(ddof=1))
        hw = float(student_t.ppf(0.5 + level / 2.0, d.size - 1)) * s / math.sqrt(d.size)
        out.update(std=s, half_width=hw, ci_low=out["gain"] - hw, ci_high=out["gain"] + hw)
    return out


def fmt_gain(g: Optional[Mapping], digits: int = 2) -> str:
    """A :func:`paired_gain` as ``"+1.23 [+0.80, +1.66]"`` (mean, 95 % interval), ``"+1.23"`` with one pair, ``"–"``
    without any."""
    if not g or g.get("gain") is None:
        return "–"
    if g.get("ci_low") is None:
        return f"{g['gain']:+.{digits}f}"
    return f"{g['gain']:+.{digits}f} [{g['ci_low']:+.{digits}f}, {g['ci_high']:+.{digits}f}]"


def significant(g: Optional[Mapping]) -> bool:
    """Whether a :func:`paired_gain`'s interval excludes zero."""
    return bool(g and g.get("ci_low") is not None and (g["ci_low"] > 0 or g["ci_high"] < 0))
