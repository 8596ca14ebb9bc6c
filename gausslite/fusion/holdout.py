"""Held-out validation of the fused-map refinement: its settings, the split of the keyframe pool and the report.

The joint refinement (:func:`gausslite.fusion.refine.refine_map`) trains on the keyframes the robots uploaded, often
a handful, and would otherwise memorise them: it fits the views it trains on and loses on every other view. It
therefore holds some uploaded keyframes out of training, scores the map on them as it trains and keeps the best
state, the vote itself when no state beats it (``docs/sharing.md``, "The refinement's held-out check").

This module holds what needs no torch (the fusion server's light install imports it): the settings
(:class:`RefineValidation`, the ``fusion.refine_validation`` group of :mod:`gausslite.config`), the split
(:func:`split_views`), the iteration count (:func:`scaled_iters`) and the record of a run (:class:`RefineReport`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Hashable, List, Optional, Sequence, Tuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

__all__ = ["RefineValidation", "RefineReport", "split_views", "scaled_iters", "DEFAULT_HOLDOUT_FRACTION",
           "DEFAULT_CHECK_EVERY", "DEFAULT_PATIENCE", "DEFAULT_PER_VIEW_ITERS"]

#: share of the uploaded keyframes held out of training (at least one view from two views on)
DEFAULT_HOLDOUT_FRACTION = 0.25
#: iterations between two held-out scores
DEFAULT_CHECK_EVERY = 10
#: held-out scores in a row without a new best before the refinement stops
DEFAULT_PATIENCE = 3
#: iterations per training view: the refinement runs min(requested, this × training views). 25 keeps the 300
#: iterations of the offline simulation (2 robots × 8 uploaded keyframes, 12 of them trained on) and cuts a live
#: fuse over 4 uploaded keyframes (3 trained on) to 75
DEFAULT_PER_VIEW_ITERS = 25


class RefineValidation(BaseModel):
    """How the fused-map refinement validates itself (``fusion.refine_validation``; the keyword arguments of
    :func:`gausslite.fusion.refine.refine_map` of the same names, :meth:`options`)."""

    model_config = ConfigDict(extra="forbid")
    holdout_fraction: float = Field(
        DEFAULT_HOLDOUT_FRACTION, ge=0, le=0.5,
        description="share of the uploaded keyframes held out of training and scored instead (spread over the "
                    "robots and along each robot's keyframes; at least one from two keyframes on; 0 = no held-out "
                    "check, the refinement returns its last state)")
    check_every: int = Field(
        DEFAULT_CHECK_EVERY, ge=1, description="iterations between two scores of the held-out keyframes")
    patience: int = Field(
        DEFAULT_PATIENCE, ge=1,
        description="held-out scores in a row without a new best after which the refinement stops early")
    per_view_iters: int = Field(
        DEFAULT_PER_VIEW_ITERS, ge=0,
        description="iterations per training keyframe: the refinement runs min(requested iterations, this × "
                    "training keyframes), so few keyframes get a short refinement (0 = the requested iterations)")

    def options(self) -> dict:
        """``{"holdout_fraction", "check_every", "patience", "per_view_iters"}``: keyword arguments of
        :func:`gausslite.fusion.refine.refine_map`."""
        return self.model_dump()


@dataclass
class RefineReport:
    """What one refinement did (:func:`gausslite.fusion.refine.refine_map` fills it when given one).

    Losses are the photometric loss of training (paper Eq. 1: L1 colour + λ_d L1 depth + λ_s (1 − SSIM), unitless)
    averaged over the held-out keyframes, on the pixels the vote renders (within each keyframe's ROI when the
    refinement restricts its loss to it). They are None when nothing was held out (``validated`` False).

    Attributes:
        iters_requested: iterations asked for.
        iters_planned: iterations after scaling to the training views (:func:`scaled_iters`).
        iters_run: iterations run (fewer than planned when stopped early).
        train_views, heldout_views: keyframes trained on / held out.
        validated: whether held-out keyframes were scored (False with a single keyframe, ``holdout_fraction`` 0, or
            when the vote draws no pixel of any held-out keyframe; then the last state is returned). A held-out
            keyframe without such a pixel is trained on and counted in ``train_views``.
        vote_loss: held-out loss of the input map (the vote).
        best_loss: lowest held-out loss seen (``vote_loss`` when nothing beat the vote).
        best_iter: iteration after which ``best_loss`` was reached (0 = the vote).
        last_loss: held-out loss at the last score.
        checks: held-out scores taken (the vote's included).
        stopped_early: stopped after ``patience`` scores without a new best.
        rolled_back: the vote itself was returned (no state beat it on the held-out keyframes).
        gaussians: Gaussians in the returned map.
    """

    iters_requested: int = 0
    iters_planned: int = 0
    iters_run: int = 0
    train_views: int = 0
    heldout_views: int = 0
    validated: bool = False
    vote_loss: Optional[float] = None
    best_loss: Optional[float] = None
    best_iter: int = 0
    last_loss: Optional[float] = None
    checks: int = 0
    stopped_early: bool = False
    rolled_back: bool = False
    gaussians: int = 0

    def as_dict(self) -> dict:
        """The fields as a plain dict (JSON-ready)."""
        return dataclasses.asdict(self)

    def summary(self) -> str:
        """One line for logs and progress messages."""
        head = (f"{self.train_views} train / {self.heldout_views} held-out keyframes, {self.iters_run} of "
                f"{self.iters_planned} iterations ({self.iters_requested} requested)")
        if not self.validated:
            return f"{head}; no held-out check (too few keyframes or none held out): last state kept"
        if self.rolled_back:
            end = f"nothing beat the vote (held-out loss {self.vote_loss:.4f}): vote kept"
        else:
            end = (f"held-out loss {self.vote_loss:.4f} (vote) -> {self.best_loss:.4f} at iteration "
                   f"{self.best_iter}: that state kept")
        return f"{head}{', stopped early' if self.stopped_early else ''}; {end}"


def split_views(n: int, sources: Optional[Sequence[Hashable]] = None, fraction: float = DEFAULT_HOLDOUT_FRACTION,
                seed: int = 0) -> Tuple[List[int], List[int]]:
    """Split ``n`` keyframes into training and held-out ones, deterministically by ``seed``.

    ``max(1, round(n × fraction))`` keyframes are held out from two keyframes on (``fraction`` > 0), none below. They
    are shared among the sources in proportion to their keyframes (largest remainders, ties in a seeded order), and
    each source holds out every (its keyframes / its share)-th keyframe of its own sequence from a seeded offset: the
    held-out keyframes are spread over the robots and along each robot's trajectory.

    Args:
        n: number of keyframes (>= 0).
        sources: one label per keyframe (e.g. the uploading agent's id); None = one source.
        fraction: share held out, in [0, 0.5] (so at least half are trained on).
        seed: RNG seed of the offsets and the ties.

    Returns:
        ``(train, held_out)``: sorted keyframe indices in ``range(n)``, disjoint, together all of them.

    Raises:
        ValueError: ``n`` < 0, ``fraction`` outside [0, 0.5], or ``sources`` of another length than ``n``.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if not 0 <= fraction <= 0.5:
        raise ValueError(f"holdout fraction must be in [0, 0.5], got {fraction}")
    if sources is not None and len(sources) != n:
        raise ValueError(f"sources has {len(sources)} labels for {n} keyframes")
    if n < 2 or fraction == 0:
        return list(range(n)), []
    labels = list(sources) if sources is not None else [0] * n
    members: dict = {}  # source -> its keyframes, in order (sources in order of first appearance)
    for i, s in enumerate(labels):
        members.setdefault(s, []).append(i)
    groups = list(members.values())
    k = max(1, int(round(n * fraction)))
    rng = np.random.default_rng([int(seed), 0x4F1D])
    exact = [k * len(g) / n for g in groups]
    quota = [int(e) for e in exact]
    tie = rng.permutation(len(groups))
    for gi in sorted(range(len(groups)), key=lambda g: (quota[g] - exact[g], tie[g]))[:k - sum(quota)]:
        quota[gi] += 1
    held = []
    for g, q in zip(groups, quota):
        if q:
            stride = len(g) / q
            start = float(rng.random()) * stride
            held += [g[int(start + j * stride)] for j in range(q)]
    held_set = set(held)
    return [i for i in range(n) if i not in held_set], sorted(held)


def scaled_iters(iters: int, train_views: int, per_view_iters: int = DEFAULT_PER_VIEW_ITERS) -> int:
    """Iterations of a refinement over ``train_views`` training keyframes: ``min(iters, per_view_iters ×
    train_views)``, or ``iters`` when ``per_view_iters`` is 0. Raises ValueError on a negative argument."""
    if iters < 0 or train_views < 0 or per_view_iters < 0:
        raise ValueError(f"iters, train_views and per_view_iters must be >= 0, got {iters}, {train_views}, "
                         f"{per_view_iters}")
    return iters if per_view_iters == 0 else min(iters, per_view_iters * train_views)
