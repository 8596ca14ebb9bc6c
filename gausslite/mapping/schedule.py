"""The ROI schedule of one keyframe: how its iterations split between the warm-up and the ROI phase (paper Sec.
III-D.1), scaled to the iterations the keyframe really gets (docs/mapper.md, "The ROI schedule").

The paper's schedule is a count: ``warmup_iters`` full-image iterations, then the ROI phase, out of ``iters_per_frame``.
Under a keyframe time budget the count is unknown in advance, so the split is in time (the first ``warmup_iters /
iters_per_frame`` of the time after seeding is full-image). Two rules keep the region from starving when the budget
buys few iterations:

- the warm-up ends early when the iterations predicted to be left (time left over this keyframe's mean iteration
  time so far) would leave the ROI phase fewer than ``roi_min_iters``; it still has at least one iteration, for the
  new seeds;
- the ROI phase's first ``roi_min_iters`` iterations draw among the keyframes that see the ROI, so the region gets
  them even where a draw over every keyframe would mostly miss it (a region seen by few keyframes).

At rich compute (30 iterations, 20 ROI-phase) both rules change little; at 5 they decide whether the region is
fitted at all.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

__all__ = ["RoiSchedule"]


@dataclass(frozen=True)
class RoiSchedule:
    """The warm-up / ROI-phase split of a keyframe's iterations.

    Attributes:
        warmup_iters: full-image iterations of the paper's fixed schedule (``mapper.warmup_iters``, ≥ 0).
        iters_per_frame: iterations of the fixed schedule (``mapper.iters_per_frame``, ≥ 1).
        roi_min_iters: ROI-phase iterations owed to the region (``mapper.roi_min_iters``; 0 in modes without an ROI
            phase, and to switch the rules off).
    """

    warmup_iters: int
    iters_per_frame: int
    roi_min_iters: int = 0

    @property
    def warm_share(self) -> float:
        """The warm-up's share of a keyframe's time under a budget: ``warmup_iters / iters_per_frame``."""
        return self.warmup_iters / self.iters_per_frame

    @property
    def warm_iters(self) -> int:
        """Full-image iterations of a fixed-count keyframe: ``warmup_iters``, shortened to leave ``roi_min_iters``
        for the ROI phase, and at least one while ``warmup_iters`` > 0."""
        if self.warmup_iters <= 0:
            return 0
        return max(1, min(self.warmup_iters, self.iters_per_frame - self.roi_min_iters))

    @staticmethod
    def iters_left(seconds_left: float, seconds_per_iter: Optional[float]) -> Optional[float]:
        """Iterations predicted to start before a budget runs out: ``seconds_left`` (clock seconds, clipped at 0) over
        the mean seconds per iteration so far (None before the first iteration: no prediction)."""
        if seconds_per_iter is None or seconds_per_iter <= 0:
            return None
        return max(0.0, seconds_left) / seconds_per_iter

    def warm_in_time(self, it: int, before_split: bool, iters_left: Optional[float]) -> bool:
        """Whether iteration ``it`` (0-based) of a budgeted keyframe is full-image.

        Args:
            it: the iteration's index in this keyframe. before_split: the clock is still before the time split
                (``warm_share`` of the time after seeding). iters_left: :meth:`iters_left` at the iteration's start,
                this one included (None: unknown).
        Returns:
            True for the first iteration (the new seeds' gradient, unless ``warmup_iters`` is 0), then while before
            the split and the iterations left after this one still cover ``roi_min_iters``.
        """
        if self.warmup_iters <= 0:
            return False
        if it == 0:
            return True
        return before_split and (iters_left is None or iters_left - 1.0 >= self.roi_min_iters)
