"""Starting and stopping a mission's threads, each once (:class:`MissionLifecycle`): the resume of a checkpoint, the
relevance worker, the mapping worker and the pusher at start; the share worker when the mission starts streaming or
replaying (``share.worker_start: mission``); the replay thread; and all of them at close. A failure anywhere ends the
mission through :meth:`MissionLifecycle.fail`.
"""

from __future__ import annotations

import logging
import threading
from typing import Callable, Optional

from gausslite.mission.errors import MissionError
from gausslite.mission.replay import Replay

log = logging.getLogger("gausslite.mission.runtime")  # the mission's one logger

__all__ = ["MissionLifecycle"]


class MissionLifecycle:
    """The threads of one mission, started and stopped once each.

    Args:
        runtime: the :class:`~gausslite.mission.runtime.AgentRuntime` whose parts it starts and stops (they are read
            when a thread starts or stops).

    Attributes:
        started: :meth:`start` ran. share_started: :meth:`start_share` ran.
        replayed: the :class:`~gausslite.mission.replay.Replay` feeding frames (None: no replay).
    """

    def __init__(self, runtime) -> None:
        self.rt = runtime
        self.started = self.share_started = False
        self.replayed: Optional[Replay] = None
        self._lock = threading.Lock()

    def start(self) -> None:
        """Start the mission once: resume the checkpoint when its folder holds one, then start the relevance worker,
        the mapping thread and the pusher.

        Raises:
            ValueError: the checkpoint is unreadable, or another agent's, mission's, task's or world frame's.
            MissionError: the mission was closed.
        """
        rt = self.rt
        with self._lock:
            if self.started:
                return
            if rt.progress.stop.is_set():
                raise MissionError(f"mission {rt.mission_id} is closed: it cannot start")
            if rt.checkpoint is not None and rt.checkpoint.exists():
                rt.checkpoint.resume()
            rt.task.start()
            rt.worker.start()
            rt.pusher.start()
            self.started = True

    def ensure_started(self) -> None:
        """:meth:`start` a mission that is neither started nor closed."""
        if not self.started and not self.rt.progress.stop.is_set():
            self.start()

    def start_share(self, live: bool) -> None:
        """Under ``share.worker_start: mission``, start the share worker as the mission starts
        (:meth:`ShareSession.start`): a ``live`` mission's at ``push.nice``, an every-frame mission's at the
        mapper's priority (it has no keyframe budget to protect; below a mapper that maps as fast as it can, the
        worker would get no processor until mapping ends). By default (``first_push``) it starts at the first push."""
        rt = self.rt
        with rt.progress.lock:
            if self.share_started:
                return
            self.share_started = True
        if rt.fusion is not None and rt.config.share.worker_start == "mission":
            rt.share.start(rt.config.push.nice if live else 0)

    def replay(self, dataset, report: Optional[Callable[[int, int], None]] = None) -> threading.Thread:
        """Feed every frame of ``dataset`` into the mission from a thread (:class:`~gausslite.mission.replay.Replay`;
        :meth:`AgentRuntime.replay <gausslite.mission.runtime.AgentRuntime.replay>`), ``report(sent, total)`` after
        each frame. Returns the thread."""
        rt = self.rt
        self.replayed = rp = Replay(dataset, rt.config, rt.T_world_map)
        rt.poses.records = True  # a replay is scored at the odometry's poses (evaluate_protocols)
        with rt.progress.lock:
            rt.ingest.online = rp.realtime
        self.start_share(rp.realtime)
        return rp.start(submit=lambda fr: rt.submit(fr, _replay=True), progress=rt.progress, poses=rt.poses,
                        join=rt.ingest.queue.join, fail=self.fail, report=report,
                        name=f"agent-{rt.agent_id}-replay")

    @property
    def replaying(self) -> bool:
        """True while a replay thread is feeding frames."""
        return self.replayed is not None and self.replayed.running

    @property
    def replay_frames(self) -> int:
        """Frames of the replayed dataset (0: no replay)."""
        return 0 if self.replayed is None else self.replayed.frames

    @property
    def replay_thread(self) -> Optional[threading.Thread]:
        """The replay's feeding thread (None: no replay)."""
        return None if self.replayed is None else self.replayed.thread

    def fail(self, msg: str) -> None:
        """The mission failed with ``msg``: logged, state ``FAILED``, and a Finish waiting for the final push ends."""
        rt = self.rt
        log.error("agent %s mission %s: %s", rt.agent_id, rt.mission_id, msg)
        rt.progress.fail(msg)
        rt.pusher.final_done.set()

    def close(self) -> None:
        """Stop the threads (pending frames are dropped); a closed mission does not start. Safe to call more than
        once."""
        rt = self.rt
        p = rt.progress
        with self._lock:
            with p.lock:
                p.closed_for_input = True
            p.stop.set()
            started = self.started
        rt.pusher.stop()  # a push waiting to retry ends now
        rt.ingest.drop_queued()
        if started:
            rt.worker.stop(5.0)
        rt.pusher.close(5.0)
        rt.task.close()
        rt.poses.close()
        rt.share.close()
