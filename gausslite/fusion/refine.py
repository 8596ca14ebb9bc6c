"""Optional joint refinement of a fused map (paper Sec. III-E).

After the voxel vote, a short joint optimisation over keyframes drawn uniformly from the union of the
agents' keyframe buffers smooths the seams between the agents' contributions. It uses the mapper's
loss (Eq. 1) and adaptive density control, with every Gaussian treated as active (full-image
rendering, all Gaussians updated). By default the loss covers the map's rendered footprint, since a
fused map holds only ROI subsets, and within it the keyframe's ROI when the agent sent one: the
footprint alone also covers the fringes of the subsets outside the ROI, and fitting those cost the ROI
1.6-1.7 dB on room0 (``bench.share_finetune``, retired: docs/history.md#share_finetune-and-share_refresh) and 0.8-0.9
dB on the synthetic sim scene. κ and the
active flags are carried through unchanged (daughters inherit them), so a refined map can be voted
again.

A few uploaded keyframes are easily memorised (live, four keyframes: +14 to +17 dB on them, -2.7 dB on every other
frame against the vote), so the refinement holds some keyframes out of training (:mod:`gausslite.fusion.holdout`),
scores the map on them as it trains, stops when the score no longer improves and returns the best state seen: the
vote itself when no state beat it. Its length scales with the keyframes it trains on.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Callable, Hashable, List, Optional, Sequence

import numpy as np
import torch

from gausslite.core.arrays import GaussianArrays
from gausslite.fusion.holdout import (DEFAULT_CHECK_EVERY, DEFAULT_HOLDOUT_FRACTION, DEFAULT_PATIENCE,
                                      DEFAULT_PER_VIEW_ITERS, RefineReport, scaled_iters, split_views)
from gausslite.mapping.config import MapperConfig, deep_merge
from gausslite.mapping.loss import photometric_loss
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.model import cosine_lr_factor
from gausslite.mapping.views import Keyframe

log = logging.getLogger(__name__)

#: longest wait (s) between two progress reports of a refinement: how long a cancellation (a server stopping) may
#: take to reach it
PROGRESS_PERIOD_S = 0.5

__all__ = ["refine_map", "RefineReport"]

ProgressFn = Callable[[float, str], None]


def refine_map(
    gaussians,
    keyframes: Sequence[Keyframe],
    iters: int,
    progress: Optional[ProgressFn] = None,
    seed: int = 0,
    cfg: Optional[MapperConfig] = None,
    footprint_only: bool = True,
    final_lr: float = 1.0,
    roi_loss: bool = True,
    holdout_fraction: float = DEFAULT_HOLDOUT_FRACTION,
    check_every: int = DEFAULT_CHECK_EVERY,
    patience: int = DEFAULT_PATIENCE,
    per_view_iters: int = DEFAULT_PER_VIEW_ITERS,
    sources: Optional[Sequence[Hashable]] = None,
    report: Optional[RefineReport] = None,
    **overrides,
):
    """Jointly optimise a (fused) map over a keyframe pool, validated on held-out keyframes.

    Args:
        gaussians: ``GaussianArrays`` or ``GaussianMap`` (any container ``GaussianArrays.from_any`` takes).
        keyframes: the union of the agents' keyframes (:class:`~gausslite.mapping.views.Keyframe`, e.g. from
            :func:`~gausslite.mapping.views.keyframe_from_frame` with the agent's ROI); each iteration draws one of
            the training keyframes uniformly. Their frame ids need not be unique (each agent counts its own).
        iters: number of Adam iterations asked for (0 returns the input unchanged); at most
            ``per_view_iters`` × training keyframes are run (:func:`~gausslite.fusion.holdout.scaled_iters`).
        progress: optional callback ``(fraction in [0,1], message)``, called about 20 times, at least every
            :data:`PROGRESS_PERIOD_S` seconds, and once at 1.0; an exception it raises (a cancellation) stops the
            refinement within that period.
        seed: RNG seed for view sampling and the train / held-out split.
        footprint_only: restrict the loss to pixels the map renders (alpha > ``footprint_alpha``).
            A fused map holds only the agents' ROI subsets: a full-image loss would make those
            Gaussians explain background they do not cover (measured on Replica room0: refine 0.2 dB
            below vote with the full-image loss).
        cfg: mapper config supplying learning rates, loss weights and density control (default
            ``MapperConfig()``); ``overrides`` are applied on top (e.g. ``lambda_ssim=0.0``; a group is merged key by
            key, ``budget={"max_gaussians": N}``).
        roi_loss: with ``footprint_only``, restrict the loss of a keyframe that carries an ROI to it
            (room0, 3 seeds, ``bench.share_finetune``, retired: docs/history.md#share_finetune-and-share_refresh;
            synthetic sim scene seed 0: 26.81 / 27.14 dB with
            it against 25.95 / 26.31 without).
        final_lr: the learning rates follow a cosine from the mapper's down to ``final_lr`` × them (1 =
            constant, the default). Measured with 100 iterations on the vote of two fine-tuned subsets
            (``bench.share_finetune``, retired: docs/history.md#share_finetune-and-share_refresh): on room0 0.05
            gains (seeds 0/1/2, pick-plant 35.39/35.92/35.49 dB
            constant against 35.95/36.62/36.40; find-ottoman 37.62/37.75/37.98 against 38.36/39.14/39.02),
            on the synthetic sim scene it loses (seed 0: 25.95/26.31 against 25.04/25.92), so the default
            stays constant.
        holdout_fraction: share of the keyframes held out of training, in [0, 0.5]
            (:func:`~gausslite.fusion.holdout.split_views`: spread over ``sources`` and along each source's
            keyframes; at least one from two keyframes on). 0 = no held-out check (the last state is returned).
        check_every: iterations between two scores of the held-out keyframes (>= 1); the vote is scored first.
            The score is the training loss (Eq. 1, no gradients) on the pixels the input map renders, within each
            keyframe's ROI under ``roi_loss``: fixed at the input's footprint, so erasing pixels cannot lower it.
        patience: scores in a row without a new best (lower loss) after which the refinement stops (>= 1).
        per_view_iters: iterations per training keyframe (0 = ``iters`` whatever the keyframes).
        sources: one label per keyframe (the uploading agent's id), to spread the held-out keyframes over the
            agents; None = one pool (the server's pool is ordered by agent, which spreads them too).
        report: a :class:`~gausslite.fusion.holdout.RefineReport` filled in place (losses, iterations, views,
            early stop, rollback), or None.
    Returns:
        ``GaussianArrays`` of the refined map: with held-out keyframes, the state with the lowest held-out loss
        among the vote and the states scored, so never worse than the input on them; the input itself when nothing
        beat it.
    Raises:
        ValueError: ``iters`` < 0, no keyframes while ``iters`` > 0, ``final_lr`` outside (0, 1],
            ``holdout_fraction`` outside [0, 0.5], ``check_every`` or ``patience`` < 1, ``per_view_iters`` < 0,
            ``sources`` of another length than ``keyframes``, or a malformed keyframe.
    """
    if iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    if not 0 < final_lr <= 1:
        raise ValueError(f"final_lr must be in (0, 1], got {final_lr}")
    if check_every < 1 or patience < 1 or per_view_iters < 0:
        raise ValueError(f"check_every and patience must be >= 1 and per_view_iters >= 0, got {check_every}, "
                         f"{patience}, {per_view_iters}")
    rep = report if report is not None else RefineReport()
    arrays = GaussianArrays.from_any(gaussians)
    rep.iters_requested, rep.gaussians = int(iters), len(arrays)
    if iters == 0 or len(arrays) == 0:
        return arrays
    if not keyframes:
        raise ValueError("refinement needs at least one keyframe")
    train_idx, held_idx = split_views(len(keyframes), sources, holdout_fraction, seed)
    mapper, cfg = _refine_mapper(arrays, seed, cfg, overrides)
    # the pool's own numbering (two agents' frame ids may coincide: the mapper caches SSIM statistics by view)
    kfs = [dataclasses.replace(k.to(mapper.device), frame_id=i,
                               **({} if roi_loss else {"roi": None, "roi_box": None}))
           for i, k in enumerate(keyframes)]
    held = _Heldout(mapper, kfs, held_idx, footprint_only and roi_loss, footprint_only)
    # a held-out keyframe of which the vote draws no pixel cannot be scored: it is trained on
    train_idx, held_idx = sorted(set(train_idx) | (set(held_idx) - set(held.index))), held.index
    rep.train_views, rep.heldout_views, rep.validated = len(train_idx), len(held_idx), bool(held_idx)
    rep.iters_planned = scaled_iters(iters, len(train_idx), per_view_iters)
    best = _train(mapper, cfg, [kfs[i] for i in train_idx], held if held_idx else None, rep, seed, progress,
                  footprint_only, roi_loss, final_lr, check_every, patience)
    out = arrays if rep.rolled_back else (best if best is not None else GaussianArrays.from_any(mapper.gmap))
    rep.gaussians = len(out)
    return out


def _refine_mapper(arrays: GaussianArrays, seed: int, cfg: Optional[MapperConfig], overrides: dict):
    """A mapper holding ``arrays`` (its config: ``cfg`` or the default, with ``seed``, a budget that holds the map and
    ``overrides``), and that config."""
    base = cfg or MapperConfig()
    data = base.model_dump()
    data["seed"] = seed
    data["budget"]["max_gaussians"] = max(base.budget.max_gaussians or 0, len(arrays))
    cfg = MapperConfig.model_validate(deep_merge(data, overrides))
    mapper = Mapper(cfg)
    mapper.load_map(arrays.to_gaussian_map(cfg.device))
    return mapper, cfg


class _Heldout:
    """The held-out keyframes' score: the training loss (Eq. 1), no gradients, averaged over the keyframes
    ``kfs[i]``, ``i`` in ``index``, each on the pixels the map renders when built (alpha > ``footprint_alpha``; within
    the keyframe's ROI with ``roi``), or on the whole image without ``footprint``. Keyframes on which that leaves no
    pixel are left out (``index`` holds those scored)."""

    def __init__(self, mapper: Mapper, kfs: List[Keyframe], index: List[int], roi: bool, footprint: bool) -> None:
        self.mapper = mapper
        self.index: List[int] = []
        self.views: List[Keyframe] = []
        self.masks: List[Optional[torch.Tensor]] = []
        fa = mapper.cfg.footprint_alpha
        for i in index:
            v = kfs[i]
            mask = None
            if footprint:
                mask = self._render(v).alpha > fa
                if roi and v.roi is not None and v.roi_box is not None:  # empty ROI: the footprint
                    mask = mask & v.roi
                if not bool(mask.any()):
                    continue
            self.index.append(i)
            self.views.append(v)
            self.masks.append(mask)

    def _render(self, v: Keyframe):
        with torch.no_grad():
            return self.mapper.sensor.render_view(v.c2w, v.K, v.width, v.height, v.frame_id, None)

    def loss(self) -> float:
        """Mean held-out loss of the mapper's current map (unitless, >= 0)."""
        cfg = self.mapper.cfg
        vals = []
        with torch.no_grad():
            for v, mask in zip(self.views, self.masks):
                out = self._render(v)
                vals.append(float(photometric_loss(out, v, cfg.lambda_depth, cfg.lambda_ssim, mask,
                                                   cfg.performance.reference_paths)))
        return float(np.mean(vals))


def _copy(mapper: Mapper) -> GaussianArrays:
    """The mapper's current map as ``GaussianArrays`` that share no memory with it (Adam updates in place)."""
    return GaussianArrays.concat([GaussianArrays.from_any(mapper.gmap)])


def _train(mapper: Mapper, cfg: MapperConfig, train: List[Keyframe], held: Optional[_Heldout], rep: RefineReport,
           seed: int, progress: Optional[ProgressFn], footprint_only: bool, roi_loss: bool, final_lr: float,
           check_every: int, patience: int) -> Optional[GaussianArrays]:
    """Run up to ``rep.iters_planned`` iterations over ``train``, scoring ``held`` every ``check_every`` (the vote
    first) and stopping after ``patience`` scores without a new best. Fills ``rep``; returns a copy of the best
    scored state after the vote, or None (no held-out keyframes: the mapper's last state is the result; or nothing
    beat the vote: ``rep.rolled_back``)."""
    n_iters = rep.iters_planned
    rng = np.random.default_rng(seed)
    every = max(1, n_iters // 20)
    reported = time.monotonic()
    best: Optional[GaussianArrays] = None
    if held is not None:
        rep.vote_loss = rep.best_loss = rep.last_loss = held.loss()
        rep.checks = 1
    stale = 0
    for it in range(n_iters):
        mapper.model.set_lr_scale(cosine_lr_factor(it, n_iters, final_lr))  # density control resets the rates
        kf = train[int(rng.integers(len(train)))]
        loss = mapper.step(kf, active_phase=False, footprint_only=footprint_only, footprint_roi=roi_loss)
        if cfg.densify.enabled and (it + 1) % cfg.densify.every == 0 and it + 1 < n_iters:
            mapper.strategy.densify_and_prune()
        rep.iters_run = it + 1
        if held is not None and ((it + 1) % check_every == 0 or it + 1 == n_iters):
            rep.last_loss = held.loss()
            rep.checks += 1
            if rep.last_loss < rep.best_loss:
                rep.best_loss, rep.best_iter, stale = rep.last_loss, it + 1, 0
                best = _copy(mapper)
            else:
                stale += 1
        rep.stopped_early = stale >= patience and it + 1 < n_iters
        if progress is not None and ((it + 1) % every == 0 or it + 1 == n_iters
                                     or time.monotonic() - reported >= PROGRESS_PERIOD_S):
            reported = time.monotonic()
            progress((it + 1) / n_iters, f"refine {it + 1}/{n_iters} loss {loss:.4f} gaussians {len(mapper.model)}"
                     + ("" if rep.last_loss is None else f" held-out {rep.last_loss:.4f}"))
        if rep.stopped_early:
            break
    rep.rolled_back = held is not None and best is None
    if progress is not None and rep.stopped_early:
        progress(1.0, f"refine stopped early at {rep.iters_run}/{n_iters}: no better held-out loss in {patience} "
                 "scores")
    return best
