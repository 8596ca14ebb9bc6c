"""Thin orchestrator: Dataset → Mapper → Evaluator (Gaussian-SLAM's separation of concerns).

``run_mapping`` maps a sequence with a config and optional task, evaluates on the mapped (training)
views and, when frames were skipped or withheld, on held-out views, and writes ``map.ply``, ``metrics.json`` and
render/ground-truth PNGs.

It maps on one of two schedules (docs/mapper.md, "Running it"):

- a fixed number of Adam iterations on every frame (``time_budget=None``; ``ablate``'s matched-budget comparisons,
  ``gausslite map --time-budget none``);
- a total time budget (:class:`TimeBudget`, ``gausslite map``'s default), spent as the live agent spends its
  mission: keyframes chosen by its rule (:mod:`gausslite.mapping.keyframes`), the mapping resolution by its governor
  (:mod:`gausslite.mapping.resolution`), each keyframe an equal share of the time left
  (``Mapper.map_frame(time_budget_s=...)``, at most ``iters_per_frame`` iterations' worth), then a final pass and the
  scoring inside the same budget.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch
from tqdm import tqdm

from gausslite.datasets.base import Frame, RGBDDataset
from gausslite.datasets.subset import withheld_indices
from gausslite.evaluation import evaluate, score_view
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.keyframes import KeyframeRule, KeyframeSelector
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.resolution import NOMINAL_GAUSSIANS, ResolutionGovernor, uses_detail

log = logging.getLogger(__name__)

RelevanceFn = Callable[[Frame], np.ndarray]

#: at most this many frames between two keyframes are handed to ``map_frame`` (the live agent's bound)
BETWEEN_MAX = 64
#: keyframes whose measured seconds per iteration estimate the next one's (the map grows, so a recent window)
ITER_WINDOW = 10


def gt_roi_fn(dataset: RGBDDataset, task_id: str) -> RelevanceFn:
    """Ground-truth relevance: pixels whose depth point lies in one of the task's boxes (paper Sec. IV).

    Raises:
        ValueError: the dataset has no annotations. KeyError: unknown task id (lists the known ones).
    """
    ann = dataset.annotations
    if ann is None:
        raise ValueError(f"{dataset.path}: no objects.json/tasks.json found; a task id needs annotations")
    ann.task_by_id(task_id)  # raises KeyError with the available ids

    def fn(frame: Frame) -> np.ndarray:
        return ann.roi_mask(task_id, frame.depth, frame.c2w, frame.intrinsics)

    return fn


@dataclass
class TimeBudget:
    """A total time budget for one offline mapping run (``gausslite map --time-budget``; docs/mapper.md, "Running
    it"), spent as the live agent spends a mission (docs/live.md): keyframes by its rule, the mapping resolution by
    its governor, a per-keyframe budget, then a final pass and the scoring.

    The budget covers the whole run: ``spent_s`` (what the caller spent before :func:`run_mapping`: loading, odometry)
    is taken off first, the scoring of every view is reserved, and the rest goes to the keyframes and the final pass in
    the proportion of the fixed schedule's iterations (``iters_per_frame`` per frame, ``final_iters`` +
    ``final_iters_per_keyframe`` per keyframe). Times are read on the mapper's clock (``budget_clock``: wall time, or
    its deterministic twin for tests).

    Attributes:
        total_s: the budget, seconds (> 0).
        spent_s: seconds already spent before mapping (≥ 0).
        rule: the keyframe rule (the live agent's ``keyframe_translation_m``, ``keyframe_rotation_deg``,
            ``keyframe_max_interval_s``).
        governor: the mapping resolution's governor (the live agent's ``agent.resolution``); its first choice is made
            at the first keyframe from that keyframe's budget.
        score_reserve_s: seconds kept for scoring; None: estimated from one scored view, timed after the first
            keyframe, times the views to score (the render's share grown to the full map by the work model).
    Raises:
        ValueError: ``total_s`` not > 0, or ``spent_s`` < 0, or a negative ``score_reserve_s``.
    """

    total_s: float
    spent_s: float = 0.0
    rule: KeyframeRule = field(default_factory=KeyframeRule)
    governor: ResolutionGovernor = field(default_factory=ResolutionGovernor)
    score_reserve_s: Optional[float] = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.total_s) and self.total_s > 0) or not self.spent_s >= 0:
            raise ValueError(f"a time budget needs total_s > 0 and spent_s >= 0, got {self.total_s}, {self.spent_s}")
        if self.score_reserve_s is not None and not self.score_reserve_s >= 0:
            raise ValueError(f"score_reserve_s must be >= 0, got {self.score_reserve_s}")


def select_keyframes(poses: np.ndarray, times: Sequence[float], rule: KeyframeRule) -> list[int]:
    """The frames the live agent's keyframe rule (:class:`~gausslite.mapping.keyframes.KeyframeSelector`) takes from
    a recorded sequence when its mapper is always free: the first frame, then each frame that moved more than
    ``rule.translation_m`` or turned more than ``rule.rotation_deg`` since the last keyframe, or came
    ``rule.max_interval_s`` after it. Dense frames thin out; frames far apart all become keyframes.

    Args:
        poses: (N, 4, 4) float64 c2w, metres. times: N frame times, seconds. rule: the thresholds.
    Returns:
        positions into ``poses`` (ascending; the first is 0 when N > 0).
    Raises:
        ValueError: ``poses`` and ``times`` of different lengths, or a pose or time that is not finite.
    """
    if len(poses) != len(times):
        raise ValueError(f"{len(poses)} poses but {len(times)} times")
    sel = KeyframeSelector(rule)
    out = []
    for k, (c2w, t) in enumerate(zip(poses, times)):
        if sel.offer(k, c2w, float(t))[0]:
            out.append(sel.take())
    return out


def keyframe_share(left_s: float, keyframes_left: int, iter_s: Optional[float], iters_per_frame: int) -> float:
    """The next keyframe's budget: an equal share of the mapping time left, and no more than ``iters_per_frame``
    iterations' worth (a short sequence under a long budget maps as the fixed schedule would, and ends early).

    Args:
        left_s: mapping seconds left for the remaining keyframes (may be ≤ 0 once over budget).
        keyframes_left: keyframes still to map, this one included (≥ 1). iter_s: estimated seconds per iteration
            (seeding included), or None (no cap). iters_per_frame: the fixed schedule's iterations per frame.
    Returns:
        seconds (≥ 1e-3: a keyframe over budget still gets its seeding and one iteration, ``Mapper.map_frame``).
    """
    share = max(1e-3, left_s / max(1, keyframes_left))
    return share if iter_s is None else min(share, max(1e-3, iters_per_frame * iter_s))


def final_share(cfg: MapperConfig, n_keyframes: int) -> float:
    """The final pass's share of the mapping time under a total budget: its share of the fixed schedule's iterations,
    ``F / (iters_per_frame × K + F)`` with ``F = final_iters + final_iters_per_keyframe × K`` over ``K`` keyframes
    (the rendered profile: 5 / 35; the hand-held one: 20 / 50)."""
    k = max(1, int(n_keyframes))
    final = cfg.final_iters + cfg.final_iters_per_keyframe * k
    return float(final / (cfg.iters_per_frame * k + final)) if final > 0 else 0.0


def run_mapping(
    dataset: RGBDDataset,
    cfg: MapperConfig,
    *,
    task_id: Optional[str] = None,
    relevance_fn: Optional[RelevanceFn] = None,
    stride: int = 1,
    withhold_every: Optional[int] = None,
    out_dir: Optional[Path] = None,
    n_images: int = 3,
    progress: bool = True,
    desc: str = "mapping",
    eval_task_ids: Optional[list[str]] = None,
    time_budget: Optional[TimeBudget] = None,
) -> tuple[Mapper, dict]:
    """Map ``dataset`` (every ``stride``-th frame) and evaluate.

    Args:
        dataset: posed RGB-D sequence; with a ``pose_ok`` array (odometry), the frames whose tracking failed are
            neither mapped nor scored (``metrics["n_frames_lost"]``).
        cfg: mapper config. In ``gausslite`` mode a relevance source is required.
        task_id: task in the dataset's ``tasks.json``: gives the ground-truth ROI for the ROI
            metrics, and the relevance map when ``relevance_fn`` is None.
        relevance_fn: frame → (H, W) bool relevance map w (e.g. from the attention front-end).
        stride: map every ``stride``-th frame; the others are held-out views.
        withhold_every: also withhold every k-th frame from the mapper (from ``k // 2``,
            :func:`~gausslite.datasets.subset.withheld_indices`: the live ``novel`` protocol's split), scored as
            held-out views; None: none.
        out_dir: where ``map.ply``, ``metrics.json`` and PNGs go (None: write nothing).
        eval_task_ids: also score the mapped views on each of these tasks' ground-truth ROIs:
            ``metrics["per_task"][task]`` holds psnr, ssim, depth_l1, roi_psnr, roi_ssim, roi_fraction
            (for a map that does not depend on the task, such as uniform mapping).
        time_budget: None: ``cfg.iters_per_frame`` iterations on every frame (``cfg.keyframe_budget_s`` seconds when
            set), then the full final pass. A :class:`TimeBudget`: keyframes, resolution, per-keyframe budgets and the
            final pass fitted to it (``metrics["time_budget"]`` says what was decided). Either way every frame to map
            is scored at the size ``dataset`` gives (``n_frames``; ``n_keyframes`` of them were mapped).
    Returns:
        (mapper, metrics dict).
    Raises:
        ValueError: ``gausslite`` mode without task or relevance source; empty dataset; ``withhold_every`` < 2.
        KeyError: an unknown task id in ``eval_task_ids``.
    """
    if len(dataset) == 0:
        raise ValueError(f"{dataset.path}: no frames")
    roi_fn = gt_roi_fn(dataset, task_id) if task_id is not None else None
    if relevance_fn is None:
        relevance_fn = roi_fn
    if cfg.mode == "gausslite" and relevance_fn is None:
        raise ValueError("mode 'gausslite' needs a task (--task-id) or a relevance source")
    t_enter = time.perf_counter()
    train_idx, test_idx, lost = split_frames(dataset, stride, withhold_every)

    torch.manual_seed(cfg.seed)
    mapper = Mapper(cfg)
    t0 = time.perf_counter()
    if time_budget is None:
        map_every_frame(mapper, dataset, train_idx, relevance_fn, progress, desc)
        mapper.finalize()
        decided = None
    else:
        if cfg.budget_clock == "wall":  # building the mapper (the renderer's first load) is part of the budget too
            time_budget = dataclasses.replace(time_budget, spent_s=time_budget.spent_s + t0 - t_enter)
        decided = map_within_budget(mapper, dataset, train_idx, len(test_idx), relevance_fn, roi_fn, time_budget,
                                    progress, desc)
    map_seconds = time.perf_counter() - t0
    metrics = score_mapping(mapper, dataset, train_idx, test_idx, roi_fn, out_dir, n_images, eval_task_ids)
    metrics.update(mode=cfg.mode, task_id=task_id, map_seconds=map_seconds,
                   score_seconds=time.perf_counter() - t0 - map_seconds, n_frames_lost=len(lost), stride=stride,
                   withhold_every=withhold_every, n_keyframes=len(mapper.stats))
    if decided is not None:
        decided["elapsed_s"] = time_budget.spent_s + mapper.clock.now() - decided.pop("clock_start")
        metrics["time_budget"] = decided
    metrics = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in metrics.items()}
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        mapper.gmap.save_ply(out_dir / "map.ply")
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
        (out_dir / "config.json").write_text(cfg.model_dump_json(indent=2))
    return mapper, metrics


def split_frames(dataset: RGBDDataset, stride: int = 1,
                 withhold_every: Optional[int] = None) -> tuple[list[int], list[int], set[int]]:
    """``(to_map, held_out, lost)`` frame indices of ``dataset``: every ``stride``-th frame is to map, the others and
    every ``withhold_every``-th (:func:`~gausslite.datasets.subset.withheld_indices`) are held out, and the frames the
    odometry lost (``pose_ok`` False) are in neither (they carry the last good pose, not theirs).

    Raises:
        ValueError: nothing left to map; ``withhold_every`` < 2.
    """
    lost = set(np.flatnonzero(~np.asarray(dataset.pose_ok)).tolist()) if hasattr(dataset, "pose_ok") else set()
    if lost:
        log.warning("%s: %d frames lost by the odometry are neither mapped nor scored", dataset.path, len(lost))
    held = set(withheld_indices(len(dataset), withhold_every)) if withhold_every is not None else set()
    train_idx = [i for i in range(0, len(dataset), stride) if i not in lost and i not in held]
    test_idx = [i for i in range(len(dataset)) if (i % stride != 0 or i in held) and i not in lost]
    if not train_idx:
        raise ValueError(f"{dataset.path}: every frame to map was lost by the odometry or withheld")
    return train_idx, test_idx, lost


def map_every_frame(mapper: Mapper, dataset: RGBDDataset, train_idx: Sequence[int],
                    relevance_fn: Optional[RelevanceFn], progress: bool = True, desc: str = "mapping") -> None:
    """The fixed schedule: ``mapper.map_frame`` on every frame of ``train_idx`` (``iters_per_frame`` iterations, or
    ``keyframe_budget_s`` seconds when the config sets it), at the dataset's size, with a progress bar."""
    bar = tqdm(train_idx, desc=desc, disable=not progress, unit="frame")
    for i in bar:
        fr = dataset[i]
        w = relevance_fn(fr) if relevance_fn is not None else None
        st = mapper.map_frame(fr, w)
        bar.set_postfix(gaussians=st.n_gaussians, loss=f"{st.loss:.3f}", s=f"{st.seconds:.2f}")


def poses_and_times(dataset: RGBDDataset, idx: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """``((len(idx), 4, 4) c2w float64, (len(idx),) seconds)`` of the frames ``idx``: from the dataset's ``poses`` and
    ``timestamps`` arrays when it has them (no image is read), else from its frames."""
    poses, times = getattr(dataset, "poses", None), getattr(dataset, "timestamps", None)
    if poses is not None and times is not None and len(poses) == len(dataset) == len(times):
        poses = np.asarray(poses, np.float64)
        return poses[list(idx)], np.asarray(times, np.float64)[list(idx)]
    frames = [dataset[i] for i in idx]
    return (np.stack([np.asarray(f.c2w, np.float64) for f in frames]) if frames else np.zeros((0, 4, 4)),
            np.array([f.timestamp for f in frames], np.float64))


def mmss(seconds: float) -> str:
    """``m:ss`` of a duration in seconds (negative: ``-m:ss``)."""
    s = int(round(abs(seconds)))
    return f"{'-' if seconds < 0 else ''}{s // 60}:{s % 60:02d}"


def map_within_budget(mapper: Mapper, dataset: RGBDDataset, train_idx: Sequence[int], n_held_out: int,
                      relevance_fn: Optional[RelevanceFn], roi_fn: Optional[RelevanceFn], budget: TimeBudget,
                      progress: bool = True, desc: str = "mapping") -> dict:
    """Map the keyframes of ``train_idx`` under a total time budget (:class:`TimeBudget`), with a progress bar over
    the keyframes whose postfix shows the time left of the budget, then the final pass inside it.

    Args:
        mapper: a fresh mapper. dataset: the sequence. train_idx: frame indices to map (keyframes are chosen among
            them). n_held_out: held-out views to score afterwards (their scoring is reserved). relevance_fn: frame →
            (H, W) bool relevance at the mapping resolution, or None. roi_fn: ground-truth ROI for the scoring
            estimate, or None. budget: the budget. progress: show the bar. desc: its label.
    Returns:
        what was decided and done (``metrics["time_budget"]``): keyframes, the resolution, per-keyframe budgets and
        iterations, the final pass, the scoring reserve; ``clock_start`` is the mapper clock's reading at the start.
    """
    run = BudgetedMapping(mapper, dataset, train_idx, len(train_idx) + n_held_out, relevance_fn, roi_fn, budget)
    bar = tqdm(total=len(run.keyframes), desc=f"{desc} ({mmss(budget.total_s)} budget)", unit="keyframe",
               disable=not progress)
    for k in range(len(run.keyframes)):
        st = run.map_keyframe(k)
        bar.update(1)
        bar.set_postfix(gaussians=st.n_gaussians, it=st.iters, left=mmss(run.budget_left()))
    bar.close()
    run.final_pass()
    return run.report()


class BudgetedMapping:
    """One run of :func:`map_within_budget`: the keyframes chosen up front, then mapped one by one, each with its
    share of the mapping time left (:func:`keyframe_share`), on the mapper's clock.

    Args: as :func:`map_within_budget`; ``n_scored``: views scored after mapping.
    Attributes:
        keyframes: dataset indices of the keyframes (:func:`select_keyframes` over ``train_idx``).
        budgets, iters: each mapped keyframe's budget (seconds) and iterations.
        reserve: seconds kept for scoring (None until estimated at the first keyframe).
    """

    def __init__(self, mapper: Mapper, dataset: RGBDDataset, train_idx: Sequence[int], n_scored: int,
                 relevance_fn: Optional[RelevanceFn], roi_fn: Optional[RelevanceFn], budget: TimeBudget) -> None:
        self.mapper, self.dataset, self.budget = mapper, dataset, budget
        self.train_idx, self.n_scored = list(train_idx), int(n_scored)
        self.relevance_fn, self.roi_fn = relevance_fn, roi_fn
        poses, times = poses_and_times(dataset, self.train_idx)
        self.keyframes = [self.train_idx[k] for k in select_keyframes(poses, times, budget.rule)]
        cfg = mapper.cfg
        self.final_share = final_share(cfg, len(self.keyframes))
        self.uses_between = cfg.sensor.motion_every_frame or (cfg.roi_views.enabled and cfg.effective().roi)
        self.uses_detail = uses_detail(cfg)  # the task region at its own level (mapper.detail)
        self.cap = cfg.budget.max_gaussians or NOMINAL_GAUSSIANS
        self.reserve = budget.score_reserve_s
        self.provisional = 0.0  # the scoring reserve until it is timed (start_resolution)
        self.start = mapper.clock.now()
        self.avail = budget.total_s - budget.spent_s
        self.budgets: list[float] = []
        self.iters: list[int] = []
        self.measured: list[tuple[float, int]] = []  # (clock seconds, iterations) of each keyframe's map_frame
        self.final_iters, self.final_planned, self.over_budget = 0, 0, 0
        log.info("time budget %s (%s spent before mapping): %d keyframes of %d frames (keyframe rule: %g m, %g°, %s s)",
                 mmss(budget.total_s), mmss(budget.spent_s), len(self.keyframes), len(self.train_idx),
                 budget.rule.translation_m, budget.rule.rotation_deg, budget.rule.max_interval_s)

    def budget_left(self) -> float:
        """Seconds of the whole budget left (scoring included), on the mapper's clock."""
        return self.start + self.avail - self.mapper.clock.now()

    def mapping_left(self) -> float:
        """Seconds left for the keyframes: the budget less the scoring reserve and the final pass's share."""
        end = self.start + (self.avail - self.scoring_reserve()) * (1.0 - self.final_share)
        return end - self.mapper.clock.now()

    def scoring_reserve(self) -> float:
        """Seconds kept for scoring: the budget's, the timed estimate, or the provisional one before it."""
        return self.reserve if self.reserve is not None else self.provisional

    def iter_seconds(self) -> Optional[float]:
        """Seconds per iteration (seeding included) of the recent keyframes after the first; None before the second.
        The first keyframe is never measured against: it seeds twice as much, and on a fresh install its time holds
        the renderer's one-time kernel compilation, which would shrink every later keyframe's share (until then the
        work model's estimate, :meth:`first_iter_seconds`, stands in)."""
        m = self.measured[1:][-ITER_WINDOW:]
        return sum(s for s, _ in m) / max(1, sum(n for _, n in m)) if m else None

    def map_keyframe(self, k: int):
        """Read, scale and map keyframe ``k`` with its share of the time left (under ``mapper.detail``, with the
        keyframe at the task region's level: :meth:`ResolutionGovernor.detail_view`); returns its ``FrameStats``."""
        mapper, gov, i = self.mapper, self.budget.governor, self.keyframes[k]
        t_read = time.perf_counter()
        frame = self.dataset[i]
        t_read = time.perf_counter() - t_read
        n_left = len(self.keyframes) - k
        if k == 0:
            self.start_resolution(frame, t_read)
        if self.mapping_left() <= 0:
            self.over_budget += 1
        b = keyframe_share(self.mapping_left(), n_left, self.iter_seconds() or self.first_iter_seconds(),
                           mapper.cfg.iters_per_frame)
        native, frame = frame, gov.apply(frame)
        native_between = self.between(k)
        between = [gov.apply(f) for f in native_between]
        w = self.relevance_fn(frame) if self.relevance_fn is not None else None
        detail = gov.detail_view(native, w, native_between) if self.uses_detail else None
        c = mapper.clock.now()
        st = mapper.map_frame(frame, w, time_budget_s=b, between=between,
                              **({} if detail is None else {"detail": detail}))
        self.measured.append((mapper.clock.now() - c, max(1, st.iters)))
        shows_region = w is not None and bool(np.any(w)) and bool(mapper.model.active.any())
        gov.record(st.iters, st.active_iters if shows_region else None, st.n_gaussians, st.detail_px)
        self.budgets.append(b)
        self.iters.append(st.iters)
        if k == 0 and self.reserve is None and len(mapper.model):
            self.reserve = self.score_seconds(i)
        return st

    def start_resolution(self, frame: Frame, t_read: float) -> None:
        """Choose the mapping resolution at the first keyframe: the governor, from that keyframe's uncapped share. Until
        the scoring is timed (:meth:`score_seconds`) a provisional reserve stands for it: the frame's read time plus a
        work-model render of the full map, per view to score."""
        intr, gov = frame.intrinsics, self.budget.governor
        self.provisional = self.n_scored * (t_read + gov.cost.render(intr.width * intr.height, self.cap, grad=False))
        share = keyframe_share(self.mapping_left(), len(self.keyframes), None, 1)
        gov.start(intr.width, intr.height, share, self.mapper.cfg.budget.max_gaussians, region=self.uses_detail)

    def first_iter_seconds(self) -> float:
        """The work model's seconds per iteration of the first keyframe at the mapping resolution (its seeds: twice
        ``seeds_per_frame`` unless ``first_frame_seeds`` is set)."""
        c, cfg, cost = self.budget.governor.choice, self.mapper.cfg, self.budget.governor.cost
        n = cfg.seeding.first_frame_seeds or 2 * cfg.seeding.seeds_per_frame
        return cost.render(c.width * c.height, n) + cost.step(n)

    def between(self, k: int) -> list:
        """The frames to map between keyframe ``k - 1`` and ``k`` (at most :data:`BETWEEN_MAX`, at the dataset's
        size), read only when the mapper uses them (``sensor.motion_every_frame``, ``roi_views``)."""
        if not self.uses_between or k == 0:
            return []
        lo, hi = self.keyframes[k - 1], self.keyframes[k]
        idx = [i for i in self.train_idx if lo < i < hi][-BETWEEN_MAX:]
        return [self.dataset[i] for i in idx]

    def score_seconds(self, i: int) -> float:
        """Seconds the scoring will take: one view per view to score, timed on frame ``i`` (read, rendered at the
        dataset's size, scored; the faster of two tries), its render grown to the full map's by the work model."""
        tries = []
        for _ in range(2):
            t = time.perf_counter()
            fr = self.dataset[i]
            t_render = time.perf_counter()
            out = self.mapper.render_frame(fr)
            t_render = time.perf_counter() - t_render
            score_view(out, fr, self.roi_fn(fr) if self.roi_fn is not None else None)
            tries.append((time.perf_counter() - t, t_render))
        total, render = min(tries)
        n, px, cost = len(self.mapper.model), fr.intrinsics.width * fr.intrinsics.height, self.budget.governor.cost
        growth = cost.render(px, max(n, self.cap), grad=False) / cost.render(px, n, grad=False)
        return self.n_scored * (total + render * (growth - 1.0))

    def final_pass(self) -> int:
        """``Mapper.finalize`` in the time left before the scoring reserve (none when nothing is left); returns its
        iterations."""
        cfg = self.mapper.cfg
        self.final_planned = cfg.final_iters + round(cfg.final_iters_per_keyframe * len(self.mapper.keyframes))
        left = self.budget_left() - self.scoring_reserve()
        if self.final_planned > 0 and left > 0:
            self.final_iters = self.mapper.finalize(max_seconds=left)
        elif self.final_planned > 0:
            log.warning("time budget: no time left for the final pass (%d iterations planned)", self.final_planned)
        return self.final_iters

    def report(self) -> dict:
        """What was decided and done, for ``metrics["time_budget"]``."""
        gov, rule = self.budget.governor, self.budget.rule
        c = gov.choice
        b, it = np.asarray(self.budgets or [0.0]), np.asarray(self.iters or [0])
        return {"total_s": self.budget.total_s, "spent_before_s": self.budget.spent_s,
                "score_reserve_s": self.scoring_reserve(), "final_share": self.final_share,
                "clock": self.mapper.cfg.budget_clock, "clock_start": self.start,
                "n_frames_offered": len(self.train_idx), "n_keyframes": len(self.keyframes),
                "keyframe_ids": [int(i) for i in self.keyframes],
                "keyframe_rule": {"translation_m": rule.translation_m, "rotation_deg": rule.rotation_deg,
                                  "max_interval_s": rule.max_interval_s},
                "keyframe_budget_s": {"first": float(b[0]), "mean": float(b.mean()), "min": float(b.min()),
                                      "max": float(b.max())},
                "keyframe_iters": {"total": int(it.sum()), "mean": float(it.mean()), "min": int(it.min()),
                                   "max": int(it.max())},
                "keyframes_over_budget": self.over_budget,
                "final_iters": self.final_iters, "final_iters_planned": self.final_planned,
                "resolution": {**gov.status(), "reason": c.reason if c is not None else ""}}


def score_mapping(mapper: Mapper, dataset: RGBDDataset, train_idx: Sequence[int], test_idx: Sequence[int],
                  roi_fn: Optional[RelevanceFn], out_dir: Optional[Path], n_images: int = 3,
                  eval_task_ids: Optional[list[str]] = None) -> dict:
    """Score the map on the frames to map (``train_idx``) and on the held-out ones (``heldout_*``), each at the
    dataset's size and the mapper's refined pose (held-out views: the nearest keyframe's correction), and write
    ``n_images`` side-by-side PNGs under ``out_dir/renders`` (None: none).

    Returns:
        the metrics (train means, ``n_gaussians``, ``n_active``, ``seconds_per_frame`` of ``map_frame``,
        ``n_frames``, ``heldout_*``, ``per_task``, ``per_frame``).
    Raises:
        KeyError: an unknown task id in ``eval_task_ids``.
    """
    img_dir = out_dir / "renders" if out_dir is not None else None
    pick = [train_idx[j] for j in np.linspace(0, len(train_idx) - 1, min(n_images, len(train_idx))).round().astype(int)]
    pick_ids = [dataset[i].frame_id for i in pick] if img_dir is not None else []
    task_rois = {t: gt_roi_fn(dataset, t) for t in (eval_task_ids or [])}
    train = evaluate(mapper.render_frame, (dataset[i] for i in train_idx), roi_fn, img_dir, pick_ids,
                     tag="train_", extra_rois=task_rois)
    metrics: dict = {
        **train.as_dict(),
        "n_gaussians": len(mapper.model),
        "n_active": int(mapper.model.active.sum()),
        "seconds_per_frame": float(np.mean([s.seconds for s in mapper.stats])),
        "n_frames": len(train_idx),
    }
    if test_idx:
        test_pick = [dataset[test_idx[len(test_idx) // 2]].frame_id] if img_dir is not None else []
        test = evaluate(mapper.render_frame, (dataset[i] for i in test_idx), roi_fn, img_dir, test_pick, tag="heldout_")
        metrics.update(test.as_dict(prefix="heldout_"))
    if eval_task_ids:
        # one map scored on several tasks' ROIs (a map that does not depend on the task: uniform)
        metrics["per_task"] = {t: {k: (None if isinstance(v, float) and math.isnan(v) else v)
                                   for k, v in sm.as_dict().items()} for t, sm in train.per_roi.items()}
    metrics["per_frame"] = [asdict(s) for s in train.scores]
    return metrics
