"""Frames into a mission: each frame's pose (given or tracked, moved into the team's world frame), the image size
check, and the hand-over to the mapping worker (``docs/live.md``).

* Keyframe ingest (``ingest: keyframes``, realtime replays): :meth:`Ingest.accept` never blocks; the keyframe
  selector (:mod:`gausslite.mapping.keyframes`) keeps only the newest pending candidate, and the queue holds a
  :data:`SLOT` marker while it does. The frames that do not become keyframes are kept (bounded,
  :data:`BETWEEN_MAX`) for the next keyframe when the mapper uses them (their motion, their ROI crops).
* Every-frame ingest (offline replays, ``ingest: every_frame``): a bounded queue; :meth:`Ingest.accept` blocks
  while it is full (gRPC flow control back-pressure).

The queue's items are ``(frame, arrival)`` pairs, :data:`SLOT`, and the markers the runtime adds at Finish and close.
"""

from __future__ import annotations

import logging
import queue
import time
from collections import deque
from typing import Callable, Optional

import numpy as np

from gausslite.mapping.keyframes import KeyframeRule, KeyframeSelector
from gausslite.mission.config import AgentConfig
from gausslite.mission.errors import FrameSizeMismatch
from gausslite.mission.progress import MissionProgress
from gausslite.mission.state import MissionState
from gausslite.mission.team_frame import frame_to_world
from gausslite.mission.tracking import MissionPoses

log = logging.getLogger("gausslite.mission.runtime")  # one logger for the whole mission loop

__all__ = ["Ingest", "SLOT", "BETWEEN_MAX", "between_use"]

SLOT = object()  #: queue item: "the keyframe selector holds a pending candidate"
#: frames between keyframes held for the next keyframe: a second at 60 Hz
BETWEEN_MAX = 64


def between_use(config: AgentConfig) -> tuple:
    """How a mission uses the frames between keyframes: ``(sends, decodes, keeps)``: their ROI crops are sent for the
    fusion refinement (``refine_views.crop`` and ``.between``); they are decoded for ROI crops (the mapper's
    ``roi_views`` in a mode with a task region, or those views); they are kept at all (also for their motion alone,
    ``mapper.sensor.motion_every_frame``)."""
    m = config.mapper
    sends = config.refine_views.crop and config.refine_views.between
    keeps = (m.roi_views.enabled and m.effective().roi) or sends
    return sends, keeps, keeps or m.sensor.motion_every_frame


class Ingest:
    """The mission's frames in (module docstring).

    Args:
        agent_id, mission_id: the agent's and the mission's ids (messages).
        config: the mission's ``AgentConfig`` (``ingest``, ``queue_size``, ``keyframe_translation_m``,
            ``keyframe_rotation_deg``, ``keyframe_max_interval_s``, ``refine_views``, ``mapper``).
        progress: the mission's :class:`~gausslite.mission.progress.MissionProgress` (state, counters, lock).
        poses: the mission's :class:`~gausslite.mission.tracking.MissionPoses`.
        T_world_map: (4, 4) float64 from the robot's map frame into the team's world frame, or None (the same frame).

    Attributes:
        queue: what the mapping worker takes (module docstring).
        selector: the :class:`~gausslite.mapping.keyframes.KeyframeSelector` of keyframe ingest.
        online: keyframe ingest (``ingest: keyframes``; a replay sets it from ``realtime``).
        intrinsics: the first frame's intrinsics (every later frame has its image size), None before it.
        sends_between: the frames between keyframes are sent as refinement views (:func:`between_use`).
    """

    def __init__(self, agent_id: str, mission_id: str, config: AgentConfig, progress: MissionProgress,
                 poses: MissionPoses, T_world_map: Optional[np.ndarray]) -> None:
        self.agent_id, self.mission_id, self.progress = agent_id, mission_id, progress
        self.poses, self.T_world_map = poses, T_world_map
        self.queue: "queue.Queue" = queue.Queue(maxsize=config.queue_size)
        self.selector = KeyframeSelector(KeyframeRule(config.keyframe_translation_m, config.keyframe_rotation_deg,
                                                      config.keyframe_max_interval_s))
        self.online = config.ingest == "keyframes"
        self.intrinsics = None
        #: frames that did not become keyframes since the last one (oldest first, bounded)
        self._between: "deque" = deque(maxlen=BETWEEN_MAX)
        self.sends_between, self._decodes_between, self._keeps_between = between_use(config)

    def posed(self, frame, replayed: bool):
        """``frame`` with its pose in the world frame: the odometry's (``agent.pose_source: odometry``, decoded for
        it), moved by ``T_world_map`` unless ``replayed`` (a replay's frames are in the world frame already); None
        when the odometry lost it (counted, :meth:`MissionPoses.track`)."""
        if self.poses.tracks:
            frame = self.poses.track(frame, None if replayed else self.T_world_map)
            if frame is None:
                return None
        return frame if replayed else frame_to_world(frame, self.T_world_map)

    def accept(self, frame, arrival: float, streamed: bool, timeout: Optional[float] = None) -> bool:
        """Queue ``frame`` (posed in the world frame, :meth:`posed`) for the mapping worker.

        Args:
            frame: a :class:`~gausslite.datasets.base.Frame` or a validated not yet decoded one (``frame_id``,
                ``c2w``, ``intrinsics``, ``materialize() -> Frame``).
            arrival: ``time.perf_counter()`` when it arrived (the accept latency is measured from it).
            streamed: a frame from outside (refused while finishing), not from the mission's replay.
            timeout: every-frame ingest only: how long to wait for queue space (None: as long as it takes).
        Returns:
            True when the frame was queued or became the pending keyframe candidate, False when skipped.
        Raises:
            MissionError: the mission no longer accepts frames (:meth:`MissionProgress.check_accepts`).
            FrameSizeMismatch: the frame's image size differs from the first frame's.
            queue.Full: ``timeout`` expired (every-frame ingest).
        """
        p = self.progress
        with p.lock:
            p.check_accepts(self.mission_id, streamed)
            self._check_size(frame)
            if self.online:
                return self._offer(frame, arrival)
        self.queue.put((frame, arrival), timeout=timeout)
        with p.lock:
            p.frames_received += 1
            p.accept_ms.append(1e3 * (time.perf_counter() - arrival))
        return True

    def _check_size(self, frame) -> None:
        """The first frame fixes the mission's intrinsics; a later frame of another image size raises
        FrameSizeMismatch (call with the lock held)."""
        intr, first = frame.intrinsics, self.intrinsics
        if first is not None and (intr.width, intr.height) != (first.width, first.height):
            raise FrameSizeMismatch(f"frame {frame.frame_id}: image size {intr.width}x{intr.height} differs "
                                    f"from the mission's {first.width}x{first.height}")
        if first is None:
            self.intrinsics = intr

    def _offer(self, frame, arrival: float) -> bool:
        """Keyframe ingest of ``frame`` (call with the lock held): offered to the selector; the candidate it replaces
        and a frame it does not take are kept as frames between keyframes and counted as skipped."""
        p = self.progress
        pending, replaced = self.selector.offer((frame, arrival), frame.c2w, arrival)
        if self._keeps_between:
            if replaced is not None:
                self._between.append(replaced[0])
            if not pending:
                self._between.append(frame)
        p.frames_received += 1
        p.frames_skipped += int(not pending) + int(replaced is not None)
        if pending and replaced is None:
            self.queue.put_nowait(SLOT)  # at most one SLOT is queued at a time
        p.accept_ms.append(1e3 * (time.perf_counter() - arrival))
        return pending

    def take_keyframe(self) -> Optional[tuple]:
        """The pending keyframe candidate ``(frame, arrival)`` (for a :data:`SLOT`), or None when there is none."""
        with self.progress.lock:
            return self.selector.take()

    def take_between(self, frame_id: int) -> list:
        """The frames seen before keyframe ``frame_id`` since the last keyframe (oldest first), for
        :meth:`Mapper.map_frame <gausslite.mapping.mapper.Mapper.map_frame>`'s ``between``: decoded when the mapper
        or the refinement views use their ROI crops, otherwise as they came (their pose and time are what the
        motion models need). A frame whose images do not decode is left out and logged."""
        with self.progress.lock:
            taken = [f for f in self._between if f.frame_id < frame_id]
            rest = [f for f in self._between if f.frame_id > frame_id]
            self._between.clear()
            self._between.extend(rest)
        if not self._decodes_between:
            return taken
        out = []
        for f in taken:
            if hasattr(f, "materialize"):
                try:
                    f = f.materialize()
                except ValueError as e:
                    log.warning("agent %s mission %s: frame %d between keyframes not decoded: %s", self.agent_id,
                                self.mission_id, f.frame_id, e)
                    continue
            out.append(f)
        return out

    def wait_mapped(self, timeout_s: Optional[float] = None, busy: Callable[[], bool] = lambda: False) -> bool:
        """Wait until every queued item is done and ``busy()`` (checked under the lock; e.g. "a replay is still
        feeding frames") is false, or the mission failed (True), or ``timeout_s`` seconds pass (False)."""
        p = self.progress
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            with p.lock:
                idle = self.queue.unfinished_tasks == 0 and not busy()
            if idle or p.state == MissionState.FAILED:
                return True
            if deadline is not None and time.monotonic() > deadline:
                return False
            time.sleep(0.05)

    def drop_queued(self) -> None:
        """Drop every queued item (close: pending frames are not mapped), marking each done."""
        try:
            while True:
                self.queue.get_nowait()
                self.queue.task_done()
        except queue.Empty:
            pass
