"""Plausibility bounds of Gaussians pushed to the fusion server (``docs/security.md``, "Hostile bytes").

The wire codec checks that a subset is well formed and finite; it cannot know that a value is absurd. One robot
(compromised, or a map that diverged) pushing a Gaussian a kilometre wide, or centred a thousand kilometres away,
would lie over every other robot's region in every fused map (the vote bins Gaussians by their mean: a splat that
large is never contested). The fusion server therefore bounds what it accepts.
"""

from __future__ import annotations

import numpy as np

__all__ = ["check_plausible"]


def check_plausible(arrays, max_abs_mean_m: float = 1.0e4, max_scale_m: float = 10.0,
                    max_abs_opacity_logit: float = 30.0) -> None:
    """Check a set of Gaussians against plausibility bounds.

    Args:
        arrays: ``GaussianArrays`` (N rows; means (N, 3) metres in the world frame, log_scales (N, 3) natural log of
            the per-axis standard deviation in metres, opacity_logits (N,)).
        max_abs_mean_m: largest |coordinate| of a mean (metres, > 0).
        max_scale_m: largest per-axis standard deviation (metres, > 0).
        max_abs_opacity_logit: largest |opacity logit| (> 0).

    A negative κ (``arrays.kappa``, an optimisation count) is refused too: the vote sums κ per voxel and rejects
    negative counts, so one robot's negative κ would fail every later ``Fuse`` of the team.

    Raises:
        ValueError: the first bound broken, with the row and its value.
    """
    kappa = np.asarray(arrays.kappa).reshape(-1)
    if len(kappa) and kappa.min() < 0:
        i = int(np.argmin(kappa))
        raise ValueError(f"Gaussian {i}: kappa {int(kappa[i])} is negative (an optimisation count is >= 0; "
                         f"{int((kappa < 0).sum())} such rows)")
    checks = (("mean", np.abs(np.asarray(arrays.means, np.float64)).max(axis=1), max_abs_mean_m, "m from the origin"),
              ("scale", np.exp(np.asarray(arrays.log_scales, np.float64)).max(axis=1), max_scale_m,
               "m standard deviation"),
              ("opacity logit", np.abs(np.asarray(arrays.opacity_logits, np.float64)), max_abs_opacity_logit, ""))
    for name, vals, bound, unit in checks:
        if len(vals) == 0:
            continue
        bad = np.flatnonzero(~(vals <= bound))
        if len(bad):
            i = int(bad[0])
            raise ValueError(f"Gaussian {i}: {name} {float(vals[i]):.4g}{' ' + unit if unit else ''} beyond the "
                             f"server's bound {bound:g} ({len(bad)} such rows)")
