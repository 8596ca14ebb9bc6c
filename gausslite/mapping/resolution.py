"""The mapping resolution a live agent can afford: the image downscale at which a keyframe gets enough iterations
under its time budget (docs/live.md, "Mapping resolution").

A keyframe budget (``mapper.keyframe_budget_s``, paper Sec. IV-A: a matched real-time per-frame budget) buys a
number of iterations that falls with the image's pixels: at a RealSense's native 640×480 a 0.5 s budget on two
cores gives a keyframe about 2 iterations, and the map is not a map. :func:`choose_downscale` picks the smallest
downscale whose predicted iterations per keyframe reach a target (the work model of
:class:`~gausslite.mapping.budget.WorkCost`); :class:`ResolutionGovernor` applies it to every frame and corrects it
from the iterations keyframes actually got, once per level, never past ``max_downscale``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional

import numpy as np

from gausslite.datasets.base import Frame
from gausslite.datasets.common import downscale_frame
from gausslite.mapping.budget import WorkCost

__all__ = ["ResolutionChoice", "predict_iters", "coarsest_level", "choose_downscale", "downscale_frame",
           "ResolutionGovernor"]

log = logging.getLogger(__name__)

#: the map size a prediction assumes without a Gaussian cap (a room-sized scene budget early in a mission)
NOMINAL_GAUSSIANS = 20_000


@dataclass
class ResolutionChoice:
    """One choice of mapping resolution.

    Attributes:
        factor: image downscale (1 = native); width / height: the mapped image size in pixels.
        predicted_iters: iterations per keyframe the work model predicts at this size (None when pinned without a
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


class ResolutionGovernor:
    """Applies the mapping resolution to a live mission's frames and corrects it from what keyframes got.

    The first frame's size fixes the choice (:func:`choose_downscale` with the work model, or a pinned factor);
    then, unless pinned, when the mean iterations of the last ``adapt_after`` keyframes (the mission's first keyframe,
    which seeds twice as much, not counted) fall below ``tolerance`` × the target, the factor steps to the next coarser
    level (logged as a warning): a level holds while its keyframes get most of the target, so run-to-run noise around
    it does not halve the image. Where even the coarsest level falls short, it says so once, as an error log line.

    Args:
        target_iters: iterations per keyframe to reach. max_downscale: coarsest level. pinned: a user's factor, or
            None (automatic). adapt_after: keyframes measured per decision. cost: the work model.
        min_width: the narrowest mapped image (pixels) an automatic level may give. tolerance: the share of the target
            a level must keep (0 < tolerance ≤ 1).
    Attributes:
        choice: the current :class:`ResolutionChoice` (None before the first frame). changes: level changes so far.
        measured_iters: mean iterations of the keyframes measured at the current level (None before any).
    """

    def __init__(self, target_iters: float = 10.0, max_downscale: int = 4, pinned: Optional[float] = None,
                 adapt_after: int = 5, cost: Optional[WorkCost] = None, min_width: int = 160,
                 tolerance: float = 0.5) -> None:
        if not 0 < tolerance <= 1:
            raise ValueError(f"tolerance must be in (0, 1], got {tolerance}")
        self.tolerance = float(tolerance)
        self._seen = 0
        self.target_iters, self.max_downscale, self.pinned = float(target_iters), int(max_downscale), pinned
        self.min_width = int(min_width)
        self.adapt_after = max(1, int(adapt_after))
        self.cost = cost or WorkCost()
        self.choice: Optional[ResolutionChoice] = None
        self.budget_s: Optional[float] = None
        self.native: Optional[tuple[int, int]] = None
        self.changes = 0
        self.measured_iters: Optional[float] = None
        self._iters: list[int] = []
        self._warned = False

    def start(self, width: int, height: int, budget_s: Optional[float], cap: Optional[int],
              renders_per_iter: float = 1.0) -> ResolutionChoice:
        """Choose from the first frame's size (native pixels) and log the choice."""
        self.native = (int(width), int(height))
        self.budget_s = budget_s
        self.max_downscale = coarsest_level(width, self.max_downscale, self.min_width)
        self.choice = choose_downscale(width, height, budget_s, cap, self.cost, self.target_iters,
                                       self.max_downscale, self.pinned, renders_per_iter, self.min_width)
        c = self.choice
        log.info("mapping resolution %dx%d (downscale %g of %dx%d): %s", c.width, c.height, c.factor, width, height,
                 c.reason)
        if not c.reaches_target:
            self._say_unreachable(c.predicted_iters)
        return c

    @property
    def factor(self) -> float:
        """The downscale in force (1 before the first frame)."""
        return 1.0 if self.choice is None else self.choice.factor

    def apply(self, frame: Frame) -> Frame:
        """``frame`` at the mapping resolution (:func:`downscale_frame`)."""
        return downscale_frame(frame, self.factor)

    def record(self, iters: int) -> Optional[ResolutionChoice]:
        """Record one mapped keyframe's iterations; returns the new choice when the level changed, else None. Without
        a keyframe budget (a fixed iteration count) there is nothing to correct."""
        if self.choice is None or self.budget_s is None:
            return None
        self._seen += 1
        if self._seen == 1:
            return None  # the first keyframe seeds twice as much: not a measure of the level
        self._iters.append(int(iters))
        if len(self._iters) < self.adapt_after:
            return None
        self.measured_iters = float(np.mean(self._iters[-self.adapt_after:]))
        floor = self.tolerance * self.target_iters
        if self.measured_iters >= floor or self.choice.pinned:
            self.choice.reaches_target = self.measured_iters >= floor
            if not self.choice.reaches_target:
                self._say_unreachable(self.measured_iters)
            return None
        if self.choice.factor >= self.max_downscale:
            self.choice.reaches_target = False
            self._say_unreachable(self.measured_iters)
            return None
        f = float(int(self.choice.factor) + 1)
        w, h = self.native
        self.choice = ResolutionChoice(f, max(1, int(w // f)), max(1, int(h // f)), None, self.target_iters, True,
                                       False, f"measured {self.measured_iters:.1f} iterations per keyframe "
                                       f"< {floor:.1f} ({self.tolerance:g} of {self.target_iters:g}) at downscale "
                                       f"{f - 1:g}")
        self.changes += 1
        self._iters = []
        log.warning("mapping resolution lowered to %dx%d (downscale %g): %s", self.choice.width, self.choice.height,
                    f, self.choice.reason)
        return self.choice

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
        """Status fields: ``mapping_width``, ``mapping_height``, ``mapping_downscale``, ``resolution_pinned``,
        ``resolution_predicted_iters``, ``resolution_measured_iters``, ``resolution_reaches_target`` and
        ``resolution_changes`` (zeros / False before the first frame)."""
        c = self.choice
        return {"mapping_width": c.width if c else 0, "mapping_height": c.height if c else 0,
                "mapping_downscale": c.factor if c else 0.0, "resolution_pinned": bool(self.pinned is not None),
                "resolution_predicted_iters": float(c.predicted_iters or 0.0) if c else 0.0,
                "resolution_measured_iters": float(self.measured_iters or 0.0),
                "resolution_reaches_target": bool(c.reaches_target) if c else False,
                "resolution_changes": self.changes}
