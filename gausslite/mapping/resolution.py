"""The mapping resolutions a live agent can afford: the image downscale at which a keyframe gets enough iterations
under its time budget, and a finer one for the task region (docs/live.md, "Mapping resolution").

A keyframe budget (``mapper.keyframe_budget_s``, paper Sec. IV-A: a matched real-time per-frame budget) buys a
number of iterations that falls with the image's pixels: at a RealSense's native 640×480 a 0.5 s budget on two
cores gives a keyframe about 2 iterations, and the map is not a map. :func:`choose_downscale` picks the smallest
downscale whose predicted iterations per keyframe reach a target (the work model of
:class:`~gausslite.mapping.budget.WorkCost`); :class:`ResolutionGovernor` applies it to every frame and corrects it
from the iterations keyframes actually got, both ways (:class:`AdaptiveLevel`), never past ``max_downscale``. With
the mapper's detail layer (``mapper.detail``) it also keeps the task region's own level, at least as fine, corrected
from the ROI-phase iterations, and builds the :class:`~gausslite.mapping.detail.DetailView` of each keyframe.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from gausslite.datasets.base import Frame
from gausslite.datasets.common import downscale_frame
from gausslite.mapping.budget import WorkCost

__all__ = ["ResolutionChoice", "predict_iters", "coarsest_level", "choose_downscale", "downscale_frame",
           "nearest_mask", "uses_detail", "AdaptiveLevel", "ResolutionGovernor", "RECENT_KEYFRAMES", "ROI_SHARE"]

log = logging.getLogger(__name__)

#: the map size a prediction assumes without a Gaussian cap (a room-sized scene budget early in a mission)
NOMINAL_GAUSSIANS = 20_000
#: keyframes of the recent means the status reports (``keyframe_iters_recent``, ``roi_iters_recent``)
RECENT_KEYFRAMES = 10
#: the ROI phase's share of a keyframe's time under the default schedule (``mapper.warmup_iters`` 10 of
#: ``iters_per_frame`` 30 full-image): the task region's iteration target is this share of the keyframe's by default
ROI_SHARE = 2.0 / 3.0


@dataclass
class ResolutionChoice:
    """One choice of mapping resolution.

    Attributes:
        factor: image downscale (1 = native); width / height: the mapped image size in pixels.
        predicted_iters: iterations per keyframe the work model predicts at this size: from the budget at the first
            choice, from the iterations measured at the previous level after a change (None when pinned without a
            budget). target_iters: the target. reaches_target: whether the prediction (or, once measured, the
            measurement) reaches it. pinned: set by the user, never changed. reason: one line for logs and status.
    """

    factor: float
    width: int
    height: int
    predicted_iters: Optional[float]
    target_iters: float
    reaches_target: bool
    pinned: bool
    reason: str


def predict_iters(width: int, height: int, budget_s: float, cap: int, cost: WorkCost, renders_per_iter: float = 1.0) -> float:
    """Iterations per keyframe a budget buys at an image size (the work model's full-image iteration, the costlier
    kind: a differentiable render of every pixel over the Gaussian cap and an Adam step over it), after the
    keyframe's seeding render.

    Args:
        width, height: mapped image size, pixels. budget_s: seconds per keyframe. cap: Gaussian cap (the map's size
            once full). cost: the machine's work model. renders_per_iter: renders per view (motion blur renders a
            view several times).
    Returns:
        predicted iterations (float, ≥ 0).
    """
    px = int(width) * int(height)
    it = renders_per_iter * cost.render(px, cap) + cost.step(cap)
    return max(0.0, budget_s - cost.render(px, cap, grad=False)) / it


def coarsest_level(width: int, max_downscale: int, min_width: int) -> int:
    """The coarsest integer downscale allowed for an image ``width`` pixels wide: at most ``max_downscale``, and
    never below ``min_width`` pixels (1 when the image is that narrow already)."""
    return max(1, min(int(max_downscale), int(width) // max(1, int(min_width))))


def choose_downscale(width: int, height: int, budget_s: Optional[float], cap: Optional[int], cost: WorkCost,
                     target_iters: float, max_downscale: int = 4, pinned: Optional[float] = None,
                     renders_per_iter: float = 1.0, min_width: int = 160) -> ResolutionChoice:
    """The smallest integer downscale in ``1 … max_downscale`` (never narrower than ``min_width`` pixels,
    :func:`coarsest_level`) whose predicted iterations per keyframe
    (:func:`predict_iters`) reach ``target_iters``; the coarsest when none does. A ``pinned`` factor is taken as
    given. Without a budget (offline mapping: a fixed iteration count) the native size.

    Args:
        width, height: native image size, pixels. budget_s: keyframe budget in seconds, or None. cap: Gaussian cap
            (None: the map follows the scene; predicted at :data:`NOMINAL_GAUSSIANS`, and measured iterations correct
            the choice as it grows). cost: the machine's work model. target_iters: iterations
            per keyframe to reach. max_downscale: coarsest level. pinned: a user's factor (≥ 1), or None.
    Returns:
        :class:`ResolutionChoice`.
    Raises:
        ValueError: a pinned factor below 1, a target below 1, or ``max_downscale`` below 1.
    """
    if target_iters < 1 or max_downscale < 1:
        raise ValueError(f"target_iters and max_downscale must be >= 1, got {target_iters}, {max_downscale}")
    cap = NOMINAL_GAUSSIANS if cap is None else int(cap)
    max_downscale = coarsest_level(width, max_downscale, min_width)

    def size(f: float) -> tuple[int, int]:
        return max(1, int(width // f)), max(1, int(height // f))

    def predicted(f: float) -> Optional[float]:
        return None if budget_s is None else predict_iters(*size(f), budget_s, cap, cost, renders_per_iter)

    if pinned is not None:
        if pinned < 1:
            raise ValueError(f"a pinned downscale must be >= 1, got {pinned}")
        p = predicted(pinned)
        return ResolutionChoice(float(pinned), *size(pinned), p, target_iters, p is None or p >= target_iters, True,
                                f"pinned at {pinned:g}")
    if budget_s is None:
        return ResolutionChoice(1.0, width, height, None, target_iters, True, False, "no keyframe budget: native size")
    for f in range(1, max_downscale + 1):
        p = predicted(f)
        if p >= target_iters:
            return ResolutionChoice(float(f), *size(f), p, target_iters, True, False,
                                    f"{p:.1f} predicted iterations per keyframe >= {target_iters:g}")
    f = float(max_downscale)
    p = predicted(f)
    return ResolutionChoice(f, *size(f), p, target_iters, False, False,
                            f"only {p:.1f} predicted iterations per keyframe at the coarsest level {max_downscale}")



def nearest_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``mask`` resampled to ``shape`` by nearest neighbour of pixel centres (a task region carried from the mapping
    resolution to the region's finer one: each fine pixel takes the coarse pixel its centre falls in).

    Args:
        mask: (h, w) bool (or 0/1) mask. shape: (H, W) of the output, pixels.
    Returns:
        (H, W) bool.
    """
    m = np.asarray(mask).astype(bool, copy=False)
    h, w = m.shape
    H, W = int(shape[0]), int(shape[1])
    rows = np.minimum(((np.arange(H) + 0.5) * (h / H)).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(W) + 0.5) * (w / W)).astype(np.int64), w - 1)
    return m[rows[:, None], cols[None, :]]


def uses_detail(cfg) -> bool:
    """Whether a mapper of config ``cfg`` (:class:`~gausslite.mapping.config.MapperConfig`) maps the task region at
    its own level: ``mapper.detail.enabled`` and a mode with the ROI phase (GaussLite)."""
    return bool(cfg.detail.enabled and cfg.effective().roi)


class AdaptiveLevel:
    """One image downscale corrected from the iterations measured at it, both ways: the rule
    :class:`ResolutionGovernor` applies to the background and, separately, to the task region.

    Coarser by one integer level when the mean of the last ``adapt_after`` keyframes measured at the level falls below
    ``tolerance`` × ``target`` (never past ``coarsest``). Finer by one level when that mean, carried to the finer level
    by the work model (for the map once full), still reaches ``finer_share`` × ``target`` (``finer_share`` is taken as at least ``tolerance``,
    so a finer level is only taken when it is predicted to hold), and at least ``hold`` keyframes were measured since
    the last change. A coarser step that undoes a finer one within 2 × ``hold`` keyframes doubles ``hold`` (up to 8 ×
    its start): a pair of levels the work model misjudges is retried ever more rarely instead of alternating.

    Args:
        factor: the starting downscale (≥ 1). coarsest: the coarsest integer level. target: iterations per keyframe.
        tolerance: 0 < tolerance ≤ 1. finer_share: see above. adapt_after: keyframes per measurement (≥ 1).
        hold: keyframes between a change and a finer step (≥ 1). pinned: never moves. finer: False: coarser steps only.
    Attributes:
        factor, coarsest; measured: mean of the last window (None before one); changes: moves so far; hold.
    Raises:
        ValueError: a tolerance outside (0, 1] or a factor below 1.
    """

    def __init__(self, factor: float, coarsest: int, target: float, tolerance: float = 0.5, finer_share: float = 0.75,
                 adapt_after: int = 5, hold: int = 10, pinned: bool = False, finer: bool = True) -> None:
        if not 0 < tolerance <= 1 or factor < 1:
            raise ValueError(f"need 0 < tolerance <= 1 and factor >= 1, got {tolerance}, {factor}")
        self.factor, self.coarsest = float(factor), max(1, int(coarsest))
        self.target, self.tolerance = float(target), float(tolerance)
        self.finer_share = max(float(finer_share), self.tolerance)
        self.adapt_after = max(1, int(adapt_after))
        self.hold = self.hold_start = max(1, int(hold))
        self.pinned, self.finer = bool(pinned), bool(finer)
        self.window: list[float] = []
        self.since = 0  # keyframes measured since the last change
        self.last_move = 0  # +1 coarser, -1 finer, 0 none or forced
        self.changes = 0
        self.measured: Optional[float] = None

    @property
    def floor(self) -> float:
        """Iterations per keyframe a level must keep: ``tolerance`` × ``target``."""
        return self.tolerance * self.target

    def finer_level(self) -> Optional[float]:
        """The next finer integer level, or None at native (1)."""
        f = math.ceil(self.factor) - 1.0
        return f if f >= 1 else None

    def measure(self, iters: float) -> Optional[float]:
        """Add one keyframe's iterations; returns the mean of the last ``adapt_after`` at this level once there are
        that many (also kept as ``measured``), else None."""
        self.since += 1
        self.window = (self.window + [float(iters)])[-self.adapt_after:]
        if len(self.window) < self.adapt_after:
            return None
        self.measured = float(np.mean(self.window))
        return self.measured

    def proposal(self, at_finer: Callable[[float, float], float]) -> float:
        """The level the last measurement asks for: one coarser, one finer, or this one.

        Args:
            at_finer: ``(iterations at this level, finer level) -> iterations predicted there`` (the work model).
        """
        m = self.measured
        if self.pinned or m is None or len(self.window) < self.adapt_after:
            return self.factor
        if m < self.floor:
            return float(int(self.factor) + 1) if int(self.factor) + 1 <= self.coarsest else self.factor
        g = self.finer_level()
        if self.finer and g is not None and self.since >= self.hold and at_finer(m, g) >= self.finer_share * self.target:
            return g
        return self.factor

    def move(self, to: float, forced: bool = False) -> None:
        """Go to level ``to``; ``forced``: not a measured decision (the background moved the region's bounds)."""
        if to > self.factor and self.last_move < 0 and self.since < 2 * self.hold:
            self.hold = min(2 * self.hold, 8 * self.hold_start)
        self.last_move = 0 if forced else (1 if to > self.factor else -1)
        self.factor = float(to)
        self.window, self.since = [], 0
        self.changes += 1


class ResolutionGovernor:
    """Applies the mapping resolutions to a live mission's frames and corrects them from what keyframes got.

    The background: the first frame's size fixes the first choice (:func:`choose_downscale` with the work model, or a
    pinned factor); then, unless pinned, the level follows the mean iterations of the last ``adapt_after`` keyframes
    (the mission's first keyframe, which seeds twice as much, not counted) both ways (:class:`AdaptiveLevel`): one
    level coarser below ``tolerance`` × the target (a warning line), one finer when the work model carries the measured
    iterations to the finer level and the full map (the Gaussian cap, or :data:`NOMINAL_GAUSSIANS`, or the map's size
    when larger) at ``finer_share`` × the target or more, ``hold_keyframes`` after the last change (an info line). A level holds while its keyframes get most of the target, so run-to-run noise around it does not
    halve the image. Where even the coarsest level falls short, it says so once, as an error log line.

    The task region (``start(..., region=True)``: the mapper's detail layer with a task region): its own level,
    ``roi_factor``, starts at native (or the pinned ``roi_pinned``) and follows the ROI-phase iterations per keyframe
    (``FrameStats.active_iters``, counted on keyframes that show the region) against ``roi_target_iters`` by the same
    rule, its cost carried between levels by the crop's pixels. It is never coarser than the background and, by
    automatic steps, at least ``roi_ratio`` times finer (linear) than a background stepped down; a background step
    that leaves it coarser than that takes it finer. A region that gets fewer ROI iterations than its target is
    warned about once per level. Without a region level ``roi_factor`` is the background's.

    Args:
        target_iters: iterations per keyframe to reach. max_downscale: coarsest level. pinned: a user's factor, or
            None (automatic). adapt_after: keyframes measured per decision. cost: the work model.
        min_width: the narrowest mapped image (pixels) an automatic level may give. tolerance: the share of the target
            a level must keep (0 < tolerance ≤ 1). finer: take finer levels when iterations recover. finer_share: the
            share of the target a finer level must be predicted to get. hold_keyframes: keyframes between a change and
            a finer step. roi_target_iters: the region's ROI-phase iterations per keyframe (None: :data:`ROI_SHARE` ×
            ``target_iters``). roi_pinned: a user's region factor, or None. roi_ratio: see above (≥ 1).
    Attributes:
        choice: the background's :class:`ResolutionChoice` (None before the first frame). background, region: their
            :class:`AdaptiveLevel` (region None without a region level). measured_iters: mean iterations of the last
            keyframes measured at the background's level (None before any). recent, roi_recent: the last
            :data:`RECENT_KEYFRAMES` keyframes' iterations and ROI-phase iterations.
    Raises:
        ValueError: a tolerance outside (0, 1], a ``roi_ratio`` below 1 or a ``roi_pinned`` below 1.
    """

    def __init__(self, target_iters: float = 10.0, max_downscale: int = 4, pinned: Optional[float] = None,
                 adapt_after: int = 5, cost: Optional[WorkCost] = None, min_width: int = 160,
                 tolerance: float = 0.5, *, finer: bool = True, finer_share: float = 0.75, hold_keyframes: int = 10,
                 roi_target_iters: Optional[float] = None, roi_pinned: Optional[float] = None,
                 roi_ratio: float = 2.0) -> None:
        if not 0 < tolerance <= 1:
            raise ValueError(f"tolerance must be in (0, 1], got {tolerance}")
        if roi_ratio < 1 or (roi_pinned is not None and roi_pinned < 1):
            raise ValueError(f"roi_ratio and a pinned region downscale must be >= 1, got {roi_ratio}, {roi_pinned}")
        self.tolerance = float(tolerance)
        self.target_iters, self.max_downscale, self.pinned = float(target_iters), int(max_downscale), pinned
        self.min_width = int(min_width)
        self.adapt_after = max(1, int(adapt_after))
        self.finer, self.finer_share, self.hold_keyframes = bool(finer), float(finer_share), int(hold_keyframes)
        self.roi_target_iters = (max(1.0, ROI_SHARE * self.target_iters) if roi_target_iters is None
                                 else float(roi_target_iters))
        self.roi_pinned, self.roi_ratio = roi_pinned, float(roi_ratio)
        self.cost = cost or WorkCost()
        self.choice: Optional[ResolutionChoice] = None
        self.background: Optional[AdaptiveLevel] = None
        self.region: Optional[AdaptiveLevel] = None
        self.budget_s: Optional[float] = None
        self.native: Optional[tuple[int, int]] = None
        self.cap: Optional[int] = None
        self.renders_per_iter = 1.0
        self.measured_iters: Optional[float] = None
        self.recent: "deque[int]" = deque(maxlen=RECENT_KEYFRAMES)
        self.roi_recent: "deque[int]" = deque(maxlen=RECENT_KEYFRAMES)
        self._roi_px: "deque[float]" = deque(maxlen=self.adapt_after)
        self._seen = 0
        self._warned = False
        self._roi_warned: set = set()

    def start(self, width: int, height: int, budget_s: Optional[float], cap: Optional[int],
              renders_per_iter: float = 1.0, region: bool = False) -> ResolutionChoice:
        """Choose from the first frame's size (native pixels) and log the choice; with ``region`` (the mapper maps the
        task region at its own level: ``mapper.detail`` on, a mode with a task region) also the region's first level."""
        self.native = (int(width), int(height))
        self.budget_s, self.cap, self.renders_per_iter = budget_s, cap, float(renders_per_iter)
        self.max_downscale = coarsest_level(width, self.max_downscale, self.min_width)
        self.choice = choose_downscale(width, height, budget_s, cap, self.cost, self.target_iters,
                                       self.max_downscale, self.pinned, renders_per_iter, self.min_width)
        c = self.choice
        self.background = AdaptiveLevel(c.factor, max(self.max_downscale, math.ceil(c.factor)), self.target_iters,
                                        self.tolerance, self.finer_share, self.adapt_after, self.hold_keyframes,
                                        pinned=c.pinned or budget_s is None, finer=self.finer)
        log.info("mapping resolution %dx%d (downscale %g of %dx%d): %s", c.width, c.height, c.factor, width, height,
                 c.reason)
        if not c.reaches_target:
            self._say_unreachable(c.predicted_iters)
        if region:
            start = min(float(self.roi_pinned or 1.0), c.factor)
            self.region = AdaptiveLevel(start, self.region_coarsest(), self.roi_target_iters, self.tolerance,
                                        self.finer_share, self.adapt_after, self.hold_keyframes,
                                        pinned=self.roi_pinned is not None or budget_s is None, finer=self.finer)
            rw, rh = self.size(self.roi_factor)
            log.info("task region resolution %dx%d (downscale %g%s), target %g ROI iterations per keyframe", rw, rh,
                     self.roi_factor, ", pinned" if self.roi_pinned is not None else "", self.roi_target_iters)
        return c

    @property
    def factor(self) -> float:
        """The background's downscale in force (1 before the first frame)."""
        return 1.0 if self.choice is None else self.choice.factor

    @property
    def roi_factor(self) -> float:
        """The task region's downscale in force: its own level, never coarser than the background's; the background's
        without a region level (1 before the first frame)."""
        return self.factor if self.region is None else min(self.region.factor, self.factor)

    @property
    def changes(self) -> int:
        """The background's level changes so far (both ways)."""
        return 0 if self.background is None else self.background.changes

    def region_coarsest(self) -> int:
        """The coarsest automatic level of the task region: ``roi_ratio`` times finer than the background, at least
        native."""
        return max(1, int(self.factor // self.roi_ratio))

    def size(self, factor: float) -> tuple[int, int]:
        """(width, height) in pixels of the native image at downscale ``factor`` ((0, 0) before the first frame)."""
        if self.native is None:
            return 0, 0
        w, h = self.native
        return max(1, int(w // factor)), max(1, int(h // factor))

    def apply(self, frame: Frame) -> Frame:
        """``frame`` at the mapping resolution (:func:`downscale_frame`)."""
        return downscale_frame(frame, self.factor)

    def apply_roi(self, frame: Frame) -> Frame:
        """``frame`` at the task region's resolution (:func:`downscale_frame`)."""
        return downscale_frame(frame, self.roi_factor)

    def detail_view(self, native: Frame, relevance: Optional[np.ndarray], between: Sequence = ()):
        """The keyframe at the task region's resolution for ``Mapper.map_frame(detail=...)``.

        Args:
            native: the keyframe at its native size. relevance: (h, w) bool task region at the mapping resolution,
                carried to the region's size by nearest neighbour (:func:`nearest_mask`), or None.
            between: the frames since the previous keyframe at their native size; those that are decoded
                :class:`~gausslite.datasets.base.Frame` objects come along at the region's size.
        Returns:
            a :class:`~gausslite.mapping.detail.DetailView`, or None when the region has no level finer than the
            background's (no region level, or both at native) or there is no relevance map.
        """
        if self.region is None or relevance is None or self.roi_factor >= self.factor:
            return None
        # lazy: the detail layer loads only for missions that use it
        from gausslite.mapping.detail import DetailView

        f = self.roi_factor
        frame = downscale_frame(native, f)
        return DetailView(frame, nearest_mask(relevance, frame.depth.shape),
                          [downscale_frame(b, f) for b in between if isinstance(b, Frame)])

    def iter_seconds(self, pixels: float, gaussians: int) -> float:
        """The work model's seconds of one iteration over ``pixels`` pixels and ``gaussians`` Gaussians."""
        return self.renders_per_iter * self.cost.render(int(pixels), gaussians) + self.cost.step(gaussians)

    def record(self, iters: int, roi_iters: Optional[int] = None, gaussians: Optional[int] = None,
               roi_px: Optional[float] = None) -> Optional[ResolutionChoice]:
        """Record one mapped keyframe; returns the background's new choice when its level changed, else None. Without
        a keyframe budget (a fixed iteration count) there is nothing to correct.

        Args:
            iters: the keyframe's iterations (``FrameStats.iters``). roi_iters: its ROI-phase iterations
                (``FrameStats.active_iters``), or None when the keyframe did not show the region. gaussians: the map's
                size after it (None: the cap, or :data:`NOMINAL_GAUSSIANS`). roi_px: pixels of the region's crop at
                the region's level (``FrameStats.detail_px``; None or 0: the whole image's).
        """
        if self.choice is None:
            return None
        self._seen += 1
        if self._seen == 1:
            return None  # the first keyframe seeds twice as much: not a measure of the level
        self.recent.append(int(iters))
        if roi_iters is not None:
            self.roi_recent.append(int(roi_iters))
        if self.budget_s is None:
            return None
        full = int(self.cap or NOMINAL_GAUSSIANS)
        n = int(gaussians or full)
        # iterations measured on the map as it is are carried to another level for the map once full (at the cap, as
        # the first choice is made): a map still growing does not buy a finer level it cannot keep
        cost = (n, max(n, full))
        if self.region is not None and roi_iters is not None:
            self._follow_region(roi_iters, cost, roi_px)
        return self._follow_background(iters, cost)

    def _follow_background(self, iters: int, n: tuple[int, int]) -> Optional[ResolutionChoice]:
        bg = self.background
        m = bg.measure(iters)
        if m is None:
            return None
        self.measured_iters = m
        px = self.size(bg.factor)[0] * self.size(bg.factor)[1]

        def carried(m: float, f: float) -> float:  # iterations at level f for m at this level, by the work model
            w, h = self.size(f)
            return m * self.iter_seconds(px, n[0]) / self.iter_seconds(w * h, n[1])

        to = bg.proposal(carried)
        self.choice.reaches_target = m >= bg.floor
        if to == bg.factor:
            if m < bg.floor:
                self._say_unreachable(m)
            return None
        old = bg.factor
        pred = carried(m, to)
        bg.move(to)
        w, h = self.size(to)
        if to > old:
            reason = (f"measured {m:.1f} iterations per keyframe < {bg.floor:.1f} ({self.tolerance:g} of "
                      f"{self.target_iters:g}) at downscale {old:g}")
        else:
            reason = (f"measured {m:.1f} iterations per keyframe at downscale {old:g}, {pred:.1f} predicted at this "
                      f"size >= {bg.finer_share * self.target_iters:.1f} ({bg.finer_share:g} of {self.target_iters:g})")
        self.choice = ResolutionChoice(to, w, h, pred, self.target_iters, True, False, reason)
        if to > old:
            log.warning("mapping resolution lowered to %dx%d (downscale %g): %s", w, h, to, reason)
        else:
            log.info("mapping resolution raised to %dx%d (downscale %g): %s", w, h, to, reason)
        r = self.region
        if r is not None:
            r.coarsest = self.region_coarsest()
            if r.factor > r.coarsest and not r.pinned:
                self._set_region(r.coarsest, f"the background maps at downscale {to:g}, the task region at least "
                                 f"{self.roi_ratio:g} times finer", forced=True)
        return self.choice

    def _follow_region(self, roi_iters: int, n: tuple[int, int], roi_px: Optional[float]) -> None:
        r = self.region
        if roi_px:
            self._roi_px.append(float(roi_px))
        m = r.measure(roi_iters)
        if m is None:
            return
        f = self.roi_factor
        w, h = self.size(f)
        if m < self.roi_target_iters and f not in self._roi_warned:
            self._roi_warned.add(f)
            if r.pinned:
                why = "; its resolution is pinned (agent.resolution.roi_downscale)"
            elif r.factor >= r.coarsest:
                why = (f"; it is at its coarsest level ({self.roi_ratio:g} times finer than the background): give each "
                       "keyframe more time (mapper.keyframe_budget_s) or a smaller Gaussian cap")
            else:
                why = ""
            log.warning("the task region gets %.1f ROI iterations per keyframe at %dx%d (downscale %g), below its "
                        "target of %g%s", m, w, h, f, self.roi_target_iters, why)
        px = float(np.mean(self._roi_px)) if self._roi_px else float(w * h)

        def carried(m: float, g: float) -> float:  # the crop at level g holds (f / g)² as many pixels
            return m * self.iter_seconds(px, n[0]) / self.iter_seconds(px * (f / g) ** 2, n[1])

        to = r.proposal(carried)
        if to == r.factor:
            return
        if to > r.factor:
            reason = (f"measured {m:.1f} ROI iterations per keyframe < {r.floor:.1f} ({self.tolerance:g} of "
                      f"{self.roi_target_iters:g}) at downscale {f:g}")
        else:
            reason = (f"measured {m:.1f} ROI iterations per keyframe at downscale {f:g}, {carried(m, to):.1f} "
                      f"predicted at this size >= {r.finer_share * self.roi_target_iters:.1f}")
        self._set_region(to, reason)

    def _set_region(self, to: float, reason: str, forced: bool = False) -> None:
        r = self.region
        coarser = to > r.factor
        r.move(to, forced)
        self._roi_px.clear()
        w, h = self.size(self.roi_factor)
        (log.warning if coarser else log.info)("task region resolution %s to %dx%d (downscale %g): %s",
                                               "lowered" if coarser else "raised", w, h, self.roi_factor, reason)

    def _say_unreachable(self, iters: Optional[float]) -> None:
        if self._warned:
            return
        self._warned = True
        c = self.choice
        log.error("keyframes get %s iterations at %dx%d (downscale %g), below the target of %g: the map will be "
                  "poor. Give each keyframe more time (mapper.keyframe_budget_s), a smaller Gaussian cap, or allow a "
                  "coarser level (agent.resolution.max_downscale)%s",
                  "?" if iters is None else f"{iters:.1f}", c.width, c.height, c.factor, self.target_iters,
                  "" if not c.pinned else "; the resolution is pinned (agent.resolution.downscale)")

    def status(self) -> dict:
        """Status fields (zeros / False before the first frame).

        The background: ``mapping_width``, ``mapping_height`` (pixels), ``mapping_downscale``, ``resolution_pinned``,
        ``resolution_predicted_iters`` (the work model's iterations per keyframe at the current level),
        ``resolution_measured_iters`` (mean of the last ``adapt_after`` keyframes at the level),
        ``resolution_reaches_target`` (they get ``tolerance`` × the target), ``resolution_changes`` (both ways).
        Every keyframe: ``keyframe_iters_recent`` and ``roi_iters_recent`` (means over the last
        :data:`RECENT_KEYFRAMES` keyframes; ROI-phase iterations over those that showed the region). The task region:
        ``region_width``, ``region_height``, ``region_downscale`` (the background's without a region level),
        ``region_detail`` (it maps finer than the background), ``region_target_iters``, ``region_measured_iters``
        (mean of the last ``adapt_after`` keyframes at its level, else the recent mean), ``region_reaches_target``
        (that reaches the target) and ``region_changes``.
        """
        c, r = self.choice, self.region
        rf = self.roi_factor if c else 0.0
        rw, rh = self.size(rf) if c else (0, 0)
        roi_recent = float(np.mean(self.roi_recent)) if self.roi_recent else None
        roi_measured = r.measured if r is not None and r.measured is not None else roi_recent
        return {"mapping_width": c.width if c else 0, "mapping_height": c.height if c else 0,
                "mapping_downscale": c.factor if c else 0.0, "resolution_pinned": bool(self.pinned is not None),
                "resolution_predicted_iters": float(c.predicted_iters or 0.0) if c else 0.0,
                "resolution_measured_iters": float(self.measured_iters or 0.0),
                "resolution_reaches_target": bool(c.reaches_target) if c else False,
                "resolution_changes": self.changes,
                "keyframe_iters_recent": float(np.mean(self.recent)) if self.recent else 0.0,
                "roi_iters_recent": roi_recent or 0.0,
                "region_width": rw, "region_height": rh, "region_downscale": rf,
                "region_detail": bool(c is not None and rf < self.factor),
                "region_target_iters": self.roi_target_iters,
                "region_measured_iters": float(roi_measured or 0.0),
                "region_reaches_target": bool(roi_measured is not None and roi_measured >= self.roi_target_iters),
                "region_changes": 0 if r is None else r.changes}
