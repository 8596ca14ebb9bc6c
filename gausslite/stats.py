"""Statistics over random seeds: every quality comparison is a mean over seeds with its spread.

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
