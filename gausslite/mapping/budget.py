"""Clocks of the per-keyframe time budget: the wall clock of a live robot, and its deterministic twin.

A live mapper gives every keyframe ``keyframe_budget_s`` seconds of wall time (paper Sec. IV-A, Baselines: a
matched real-time per-frame budget). Wall time depends on the machine and on whatever else runs on it, so
behaviour under a budget (how many iterations fit, how the warm-up/ROI split falls, how many Gaussians a
mission holds) cannot be pinned by tests on it. :class:`WorkClock` is its deterministic twin: it advances by
the modelled cost of the work the mapper did (:class:`WorkCost`, a linear model per render and per Adam step,
fitted on a machine by :func:`fit_work_cost`), so the same mission spends the same budget the same way on any
machine and under any load (``MapperConfig.budget_clock = "work"``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

__all__ = ["WorkCost", "WallClock", "WorkClock", "fit_work_cost"]


@dataclass(frozen=True)
class WorkCost:
    """Modelled seconds of the mapper's work on one machine (defaults: this project's 2-core x86-64 CI
    machine, one mapper with two rasterizer threads, fitted by ``python -m bench.realtime --calibrate``).

    A differentiable render of ``p`` pixels over ``n`` Gaussians costs ``render_s + pixel_s·p + gaussian_s·n``
    (forward and backward); a render without gradients ``no_grad_factor`` of that; an Adam step over ``n``
    Gaussians ``step_s + step_gaussian_s·n``.

    Raises:
        ValueError: a negative coefficient.
    """

    render_s: float = 1.9e-3
    pixel_s: float = 2.2e-7
    gaussian_s: float = 9.3e-7
    step_s: float = 2.0e-3
    step_gaussian_s: float = 1.4e-6
    no_grad_factor: float = 0.4

    def __post_init__(self) -> None:
        if min(self.render_s, self.pixel_s, self.gaussian_s, self.step_s, self.step_gaussian_s,
               self.no_grad_factor) < 0:
            raise ValueError(f"work cost coefficients must be >= 0: {self}")

    def render(self, pixels: int, gaussians: int, grad: bool = True) -> float:
        """Seconds of one render of ``pixels`` pixels over ``gaussians`` Gaussians."""
        t = self.render_s + self.pixel_s * pixels + self.gaussian_s * gaussians
        return t if grad else self.no_grad_factor * t

    def step(self, gaussians: int) -> float:
        """Seconds of one Adam step over ``gaussians`` Gaussians."""
        return self.step_s + self.step_gaussian_s * gaussians


class WallClock:
    """The live clock: ``now()`` is ``time.perf_counter()`` (seconds). ``charges`` False: the mapper reports no work
    to it (clocks that count work set it and provide ``charge_render`` / ``charge_step``)."""

    charges = False

    def now(self) -> float:
        return time.perf_counter()


class WorkClock:
    """Deterministic twin of :class:`WallClock`: ``now()`` is the modelled seconds of the work charged so far.

    Args:
        cost: the machine's cost model.
    """

    charges = True

    def __init__(self, cost: WorkCost) -> None:
        self.cost = cost
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def charge_render(self, pixels: int, gaussians: int, grad: bool = True) -> None:
        self.t += self.cost.render(pixels, gaussians, grad)

    def charge_step(self, gaussians: int) -> None:
        self.t += self.cost.step(gaussians)

    def charge_fixed(self, seconds: float) -> None:
        """Charge work of a modelled fixed cost (e.g. storing an ROI view, ``roi_views.view_cost_s``)."""
        self.t += float(seconds)


def fit_work_cost(samples: list[tuple[int, int, int, int, float]]) -> WorkCost:
    """Least-squares :class:`WorkCost` from measured iterations.

    Args:
        samples: per iteration ``(renders, pixels, gaussian_renders, gaussians_stepped, seconds)``: its number
            of differentiable renders, their summed pixels, the summed Gaussian count over its renders, the
            Gaussians of its Adam step, and its measured wall time.
    Returns:
        The fitted model (coefficients clipped at 0; ``no_grad_factor`` keeps its default).
    Raises:
        ValueError: fewer than 5 samples.
    """
    if len(samples) < 5:
        raise ValueError(f"need at least 5 timed iterations to fit the work cost, got {len(samples)}")
    a = np.asarray(samples, dtype=np.float64)
    # seconds = render_s·renders + pixel_s·pixels + gaussian_s·gaussian_renders + step_s + step_gaussian_s·n
    X = np.column_stack([a[:, 0], a[:, 1], a[:, 2], np.ones(len(a)), a[:, 3]])
    coef, *_ = np.linalg.lstsq(X, a[:, 4], rcond=None)
    coef = np.clip(coef, 0.0, None)
    return WorkCost(render_s=float(coef[0]), pixel_s=float(coef[1]), gaussian_s=float(coef[2]),
                    step_s=float(coef[3]), step_gaussian_s=float(coef[4]))
