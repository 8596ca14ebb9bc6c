"""The ``late`` scenario of ``bench.realtime`` (``--late F``): the task starts after the first share F of the
sequence, when the map has reached its cap and covers the task's region (``docs/realtime.md``, "Tasks that arrive
late"). Two ways a task arrives late:

- ``task`` (default): the robot is given its task mid-mission through :meth:`AgentRuntime.update_task
  <gausslite.mission.runtime.AgentRuntime.update_task>`, the product's path: nothing is relevant before F, then the
  stored keyframes get the task's relevance maps and new frames re-target the map (adoption, ROI seeds);
- ``detection``: the task's object is first detected at F: the frames before it never get its relevance.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from gausslite.mission.relevance import build_relevance
from gausslite.parser import parse_task

LATE_VIA = ("task", "detection")


def late_via(job: dict) -> str:
    """The job's way of arriving late (:data:`LATE_VIA`; ``task`` when unset)."""
    return job.get("late_via") or "task"


def late_index(job: dict, ds) -> int:
    """Index of the first frame of the ``late`` scenario's task (the first ``job["late"]`` share of ``ds`` comes
    before it)."""
    return min(len(ds) - 1, int(job["late"] * len(ds)))


def late_relevance(job: dict, ds, cfg, graph, ann, task) -> tuple[Optional[Callable], Callable]:
    """The mission's relevance source in the ``late`` scenario, and a function that binds it to the mission's
    runtime once it exists (the relevance of a detector front-end reads the runtime's map).

    Returns:
        ``(relevance_fn, bind)``: ``relevance_fn`` frame → (H, W) bool, None without ``job["late"]`` (the scene's
        own relevance); ``bind(rt)`` to call with the :class:`AgentRuntime` built with it.
    """
    if not job.get("late"):
        return None, lambda rt: None
    if late_via(job) == "task":
        # nothing is relevant before the task is given (``give_late_task``)
        return (lambda fr: np.zeros(fr.depth.shape, bool)), (lambda rt: None)
    start_id = ds[late_index(job, ds)].frame_id
    box: list = []
    fn, _ = build_relevance(cfg, graph, ann, task.id, lambda: box[0].mapper if box else None)

    def relevance_fn(fr):
        return fn(fr) if fr.frame_id >= start_id else np.zeros(fr.depth.shape, bool)

    return relevance_fn, box.append


def give_late_task(job: dict, ds, rt, task) -> Optional[Callable[[int], bool]]:
    """The task switch of the ``late`` scenario when the task is given mid-mission (``late_via`` ``task``): a function
    of the index of the next frame that gives ``rt`` its task through :meth:`AgentRuntime.update_task` once that
    index reaches the late start, and returns True then (the mapping thread applies it before its next keyframe; a
    deterministic replay calls ``rt.apply_pending_task()``). None when the scenario does not switch tasks."""
    if not job.get("late") or late_via(job) != "task":
        return None
    start, given = late_index(job, ds), []

    def give(i: int) -> bool:
        if given or i < start:
            return False
        rt.update_task(task.text, parse_task(task.text), task.id)
        given.append(i)
        return True

    return give
