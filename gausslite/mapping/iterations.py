"""The mapper's iterations: how many Adam iterations run, on which view and in which phase, for a new keyframe
(:func:`keyframe_iterations`: warm-up then ROI phase, under an iteration count or a time budget; paper Sec. III-D.1),
between keyframes (:func:`between_keyframes`: MVO over the stored keyframes; III-D.2) and in the final pass
(:func:`final_pass`), each view drawn by :func:`pick_view`.

Each function takes the :class:`~gausslite.mapping.mapper.Mapper` whose iterations they are, and reads its parts
when called (``mapper.step``, ``mapper.clock``, the keyframe and ROI-view stores, its generator), so a part replaced
on the mapper is the one used; the schedule counters that span calls are the mapper's (``n_idle_iters``,
``n_budget_iters``). One iteration on one view is :class:`~gausslite.mapping.step.TrainStep`'s; the split of a
keyframe's iterations between the phases is :class:`~gausslite.mapping.schedule.RoiSchedule`'s.
"""

from __future__ import annotations

from typing import Optional

from gausslite.mapping.schedule import RoiSchedule
from gausslite.mapping.views import Keyframe

__all__ = ["keyframe_iterations", "between_keyframes", "final_pass", "pick_view", "roi_view_draw"]


def keyframe_iterations(mapper, kf: Keyframe, t0: float, budget: Optional[float]) -> tuple[float, int, int, dict]:
    """The iterations of one :meth:`Mapper.map_frame <gausslite.mapping.mapper.Mapper.map_frame>` call on
    keyframe ``kf`` (started at clock time ``t0``, ``budget`` seconds or None for ``iters_per_frame``): warm-up then
    ROI phase, density control on schedule. Returns (last loss, ROI-phase iterations, iterations, summed
    density-control counts)."""
    cfg, sw = mapper.cfg, mapper.cfg.effective()
    loss = 0.0
    active_iters = 0
    n_iters = 0
    dstats: dict = {}
    has_active = bool(mapper.model.active.any())
    schedule = RoiSchedule(cfg.warmup_iters, cfg.iters_per_frame, cfg.roi_min_iters if sw.roi else 0)
    warm_until = t_it = None
    if budget is not None:
        # the paper's warm-up → ROI-phase schedule in time: the first warmup_iters / iters_per_frame of
        # the time left after seeding is full-image, the rest ROI-phase (a fixed warm-up count would
        # outlast a short budget and leave the ROI phase, κ and the shared subset empty)
        t_it = mapper.clock.now()
        warm_until = t_it + max(0.0, budget - (t_it - t0)) * schedule.warm_share
    roi_draws = 0
    for it in iteration_indices(mapper, t0, budget):
        if warm_until is None:
            warm = it < schedule.warm_iters
        else:
            now = mapper.clock.now()
            left = schedule.iters_left(t0 + budget - now, (now - t_it) / it if it else None)
            warm = schedule.warm_in_time(it, now < warm_until, left)
        roi_phase = sw.roi and not warm and has_active
        view = pick_view(mapper, kf, roi_phase=roi_phase, owed=roi_phase and roi_draws < schedule.roi_min_iters)
        roi_draws += int(roi_phase)
        active_phase = roi_phase and view.roi is not None
        loss = mapper.step(view, active_phase, coarse=it < cfg.performance.coarse_iters)
        active_iters += int(active_phase and view.roi_box is not None)  # an empty ROI: a full-image iteration
        n_iters += 1
        if warm_until is not None:  # a budget may give fewer than densify.every iterations per call
            mapper.n_budget_iters += 1
            dc_due = mapper.n_budget_iters % cfg.densify.every == 0
        else:
            dc_due = (it + 1) % cfg.densify.every == 0
        if cfg.densify.enabled and dc_due:
            for k, v in mapper.strategy.densify_and_prune().items():
                dstats[k] = dstats.get(k, 0) + v
            has_active = bool(mapper.model.active.any())
    return loss, active_iters, n_iters, dstats


def iteration_indices(mapper, t0: float, budget: Optional[float]):
    """Iteration indices of one keyframe (:func:`keyframe_iterations`): ``iters_per_frame`` (``budget`` None),
    or as many as fit ``budget`` seconds after ``t0``."""
    if budget is None:
        yield from range(mapper.cfg.iters_per_frame)
        return
    it = 0
    while it == 0 or mapper.clock.now() - t0 < budget:
        yield it
        it += 1


def between_keyframes(mapper, max_seconds: Optional[float] = None, n_iters: Optional[int] = None) -> int:
    """The iterations of :meth:`Mapper.optimize <gausslite.mapping.mapper.Mapper.optimize>` between keyframes
    (its arguments, result and errors): each on a view drawn from the stored keyframes, in the phase of the
    ``iters_per_frame`` schedule that continues across calls (``mapper.n_idle_iters``), density control on
    schedule."""
    if max_seconds is None and n_iters is None:
        raise ValueError("optimize needs max_seconds or n_iters")
    if (max_seconds is not None and not max_seconds > 0) or (n_iters is not None and n_iters < 1):
        raise ValueError(f"optimize bounds must be > 0, got max_seconds={max_seconds}, n_iters={n_iters}")
    if len(mapper.keyframes) == 0 or len(mapper.model) == 0:
        return 0
    cfg, sw = mapper.cfg, mapper.cfg.effective()
    roi_w = cfg.roi_covis_weight if sw.mvo else 0.0
    t0 = mapper.clock.now()
    done = 0
    while (n_iters is None or done < n_iters) and (done == 0 or max_seconds is None
                                                   or mapper.clock.now() - t0 < max_seconds):
        i = mapper.keyframes.sample_index(mapper.rng, cfg.window, cfg.recent_prob, roi_w)
        phase = mapper.n_idle_iters % cfg.iters_per_frame
        active_phase = (sw.roi and phase >= cfg.warmup_iters and mapper.keyframes[i].roi is not None
                        and bool(mapper.model.active.any()))
        view = ((roi_view_draw(mapper) if active_phase and mapper.keyframes[i].sees_roi else None)
                or mapper.keyframes.load(i, mapper.device))
        mapper.step(view, active_phase)
        mapper.n_idle_iters += 1
        done += 1
        if cfg.densify.enabled and mapper.n_idle_iters % cfg.densify.every == 0:
            mapper.strategy.densify_and_prune()
    return done


def final_pass(mapper, max_seconds: Optional[float] = None) -> int:
    """The final pass of :meth:`Mapper.finalize <gausslite.mapping.mapper.Mapper.finalize>` (its arguments,
    result and errors): uniform draws over the stored keyframes, full-image or on the mapping schedule."""
    if max_seconds is not None and not max_seconds > 0:
        raise ValueError(f"max_seconds must be > 0, got {max_seconds}")
    cfg = mapper.cfg
    n = len(mapper.keyframes)
    total = cfg.final_iters + round(cfg.final_iters_per_keyframe * n)
    roi_schedule = cfg.final_schedule == "mapping" and cfg.effective().roi and bool(mapper.model.active.any())
    t0 = mapper.clock.now()
    done = 0
    for it in range(total if n else 0):
        if max_seconds is not None and mapper.clock.now() - t0 >= max_seconds:
            break
        view = mapper.keyframes.load(int(mapper.rng.integers(n)), mapper.device)
        # a keyframe without ROI pixels gets a full-image iteration (TrainStep)
        mapper.step(view, active_phase=roi_schedule and it % cfg.iters_per_frame >= cfg.warmup_iters)
        done += 1
    return done


def pick_view(mapper, current: Keyframe, roi_phase: bool = False, owed: bool = False) -> Keyframe:
    """The view of one iteration: from the recent window or the whole mission (see
    ``KeyframeStore.sample_index``); without MVO the current frame with ``current_frame_prob``. ``roi_phase``
    with ``roi_phase_views='roi'``, or ``owed`` (an ROI-phase iteration the ROI schedule owes the region,
    ``roi_min_iters``): among the keyframes that see the ROI."""
    cfg, sw = mapper.cfg, mapper.cfg.effective()
    n = len(mapper.keyframes)
    if not sw.mvo and not owed and (n <= 1 or mapper.rng.random() < cfg.current_frame_prob):
        return current
    roi_w = cfg.roi_covis_weight if sw.mvo else 0.0
    i = mapper.keyframes.sample_index(mapper.rng, cfg.window, cfg.recent_prob, roi_w,
                                      roi_only=roi_phase and (owed or cfg.roi_phase_views == "roi"))
    if roi_phase and mapper.keyframes[i].sees_roi:
        v = roi_view_draw(mapper)
        if v is not None:
            return v
    if i == n - 1 and mapper.keyframes[i].frame_id == current.frame_id:
        return current
    return mapper.keyframes.load(i, mapper.device)


def roi_view_draw(mapper) -> Optional[Keyframe]:
    """For an ROI-phase iteration whose drawn keyframe sees the region: a stored ROI view instead, with
    probability ``roi_views.draw`` × views / (views + ROI keyframes) (``roi_views``); None: keep the keyframe."""
    nv = len(mapper.roi_views)
    if nv == 0 or not mapper.cfg.roi_views.enabled:
        return None
    n_roi = sum(1 for k in mapper.keyframes if k.sees_roi)
    if mapper.rng.random() >= mapper.cfg.roi_views.draw * nv / (nv + n_roi):
        return None
    return mapper.roi_views.load(int(mapper.rng.integers(nv)), mapper.device)
