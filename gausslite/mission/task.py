"""A mission's task and its swaps: the task's text, graph and id, the relevance source built for it
(:func:`gausslite.mission.relevance.build_relevance`), and a new task given to a running mission, built at once and
applied by the mapping thread between keyframes (``docs/live.md#changing-the-task``).
"""

from __future__ import annotations

import logging
import threading
from typing import Callable, Optional

import numpy as np

from gausslite.attention.worker import RelevanceWorker
from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.mission.config import AgentConfig
from gausslite.mission.progress import MissionProgress
from gausslite.mission.relevance import build_relevance

log = logging.getLogger("gausslite.mission.runtime")  # one logger for the whole mission loop

__all__ = ["MissionTask", "task_id_of"]


def task_id_of(annotations, task_id: Optional[str], task_text: str) -> Optional[str]:
    """The annotations' id of a mission's task: ``task_id`` checked against them, or, without one, the id of the
    annotated task whose text is ``task_text`` (case and surrounding space ignored); None without annotations or a
    match (``task_id`` as given without annotations).

    Raises:
        KeyError: ``task_id`` is not one of the annotations' tasks (the message lists the known ids).
    """
    if annotations is None:
        return task_id
    if task_id is None:
        return next((t.id for t in getattr(annotations, "tasks", []) or []
                     if t.text.strip().lower() == task_text.strip().lower()), None)
    annotations.task_by_id(task_id)  # KeyError with the known ids
    return task_id


class MissionTask:
    """The mission's current task, its relevance source, and a pending new task.

    Args:
        agent_id, mission_id: the agent's and the mission's ids (logs).
        config: the mission's ``AgentConfig`` (``relevance``, ``relevance_backend``, ``relevance_max_wait_s``, ...).
        text: the task. graph: its parsed graph (``targets``, ``anchors``, ``relations``).
        task_id: its id in the annotations' ``tasks.json`` (None: looked up by text, :func:`task_id_of`).
        annotations: ``SceneAnnotations`` in the world frame, or None.
        relevance_fn: ``frame -> (H, W) bool`` to use instead of building one, or None.
        mapper_of: ``() -> Mapper``: the mission's mapper at call time (the attention front-end's rendered depth).
        progress: the mission's :class:`~gausslite.mission.progress.MissionProgress` (its lock guards the task's
            fields; ``n_active`` restarts at 0 with a new task).
    Raises:
        ValueError: a relevance source that cannot be built (:func:`~gausslite.mission.relevance.build_relevance`).
        KeyError: an unknown task id.

    Attributes:
        text, graph, task_id: the current task. relevance_fn: its ``frame -> (H, W) bool``. frontend: its attention
        front-end (``relevance: attention``), or None.
    """

    def __init__(self, agent_id: str, mission_id: str, config: AgentConfig, text: str, graph, task_id: Optional[str],
                 annotations, relevance_fn: Optional[Callable], mapper_of: Callable, progress: MissionProgress) -> None:
        self.agent_id, self.mission_id, self.config = agent_id, mission_id, config
        self.annotations, self._mapper_of, self.progress = annotations, mapper_of, progress
        self.text, self.graph = text, graph
        self.task_id = task_id_of(annotations, task_id, text)
        self.frontend = None
        if relevance_fn is None:
            relevance_fn, self.frontend = build_relevance(config, graph, annotations, self.task_id, mapper_of)
        self.relevance_fn = relevance_fn
        self._pending = None  # (text, graph, task id, relevance fn, front-end) left by request()
        self._worker: Optional[RelevanceWorker] = None  # the relevance thread (relevance_max_wait_s), once started
        self._start_lock = threading.Lock()
        self._closed = False

    def start(self) -> None:
        """Start the relevance thread when ``relevance_max_wait_s`` asks for one (once; :meth:`relevance` starts it
        too)."""
        with self._start_lock:
            if self.config.relevance_max_wait_s is not None and self._worker is None and not self._closed:
                self._worker = RelevanceWorker(self.relevance_fn, self.config.relevance_max_wait_s)

    def relevance(self, frame: Frame) -> np.ndarray:
        """The relevance map w of ``frame`` for the current task: (H, W) bool, from the relevance thread under
        ``relevance_max_wait_s`` (started here if :meth:`start` did not run), otherwise computed here."""
        if self._worker is None and self.config.relevance_max_wait_s is not None:
            self.start()
        if self._worker is not None:
            return self._worker.relevance(frame)
        return self.relevance_fn(frame)

    def request(self, text: str, graph, task_id: Optional[str] = None) -> None:
        """Build the relevance source of a new task now and leave it for :meth:`apply_pending` (a later request
        replaces one not applied yet).

        Args:
            text: the new task. graph: its parsed graph. task_id: its id in ``tasks.json``, or None (by text).
        Raises:
            ValueError: its relevance source cannot be built. KeyError: an unknown task id.
        """
        task_id = task_id_of(self.annotations, task_id, text)
        fn, frontend = build_relevance(self.config, graph, self.annotations, task_id, self._mapper_of)
        with self.progress.lock:
            self._pending = (text, graph, task_id, fn, frontend)
        log.info("agent %s mission %s: new task %r (applied before the next keyframe)", self.agent_id,
                 self.mission_id, text)

    def apply_pending(self, mapper, pusher) -> bool:
        """Switch to the task :meth:`request` left, if any: every task flag and κ of ``mapper`` restart at zero
        (:meth:`Mapper.retarget <gausslite.mapping.mapper.Mapper.retarget>`), its stored keyframes get the new task's
        relevance maps, and ``pusher`` opens its next fusion session under the new task.

        Returns:
            True when a new task was applied.
        """
        with self.progress.lock:
            pending, self._pending = self._pending, None
        if pending is None:
            return False
        text, graph, task_id, fn, frontend = pending
        if self._worker is not None:
            self._worker.close()
            self._worker = RelevanceWorker(fn, self.config.relevance_max_wait_s)
        self.relevance_fn, self.frontend = fn, frontend
        mapper.retarget()
        store = mapper.keyframes
        for i in range(len(store)):
            st = store[i]
            frame = Frame(st.frame_id, 0.0, st.rgb.numpy(), st.depth.float().numpy(), st.c2w.numpy(),
                          Intrinsics.from_K(st.K.numpy(), st.width, st.height))
            store.set_roi(i, fn(frame))
        with self.progress.lock:
            self.text, self.graph, self.task_id = text, graph, task_id
            self.progress.n_active = 0
        pusher.set_task(text)
        log.info("agent %s mission %s: now mapping for task %r (%d stored keyframes re-targeted)", self.agent_id,
                 self.mission_id, text, len(store))
        return True

    def close(self) -> None:
        """Stop the relevance thread, if any; none starts afterwards. Safe to call more than once."""
        with self._start_lock:
            self._closed = True
        if self._worker is not None:
            self._worker.close()
