"""A mission's shared progress: its state, counters and latencies under the one lock every part of the mission takes
(:class:`gausslite.mission.runtime.AgentRuntime` and its parts: ingest, mapping worker, task, checkpoint).

One lock for all of them keeps each status snapshot consistent (a frame counted as received is never missing from
the keyframes plus skipped frames it adds to) and lets the parts update several counters as one step.
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

from gausslite.mission.errors import MissionError
from gausslite.mission.state import MissionState

__all__ = ["MissionProgress", "CHECKPOINT_COUNTERS", "RECENT_FRAMES", "percentile"]

#: the counters a checkpoint keeps (a resumed mission continues counting from them)
CHECKPOINT_COUNTERS = ("frames_received", "frames_mapped", "frames_keyframed", "frames_skipped", "seconds_mapping",
                       "idle_iterations", "keyframe_iterations")
RECENT_FRAMES = 1800  #: frames of ``accept_latency_ms_p99_recent`` (a minute at 30 Hz)
LATENCIES_KEPT = 100_000  #: latencies kept for the percentiles (bounded over a long mission)


def percentile(values, q: float) -> float:
    """The ``q``-th percentile (0 to 100) of ``values`` (a sequence of numbers) as a float; 0.0 when it is empty."""
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) else 0.0


class MissionProgress:
    """The mission's state, counters and latencies (fields named as the ``MissionStatus`` keys), guarded by
    :attr:`lock`: a part reads or changes several fields as one step inside ``with progress.lock``.

    Attributes:
        lock: the mission's lock (also guards the ingest queue's hand-over, the keyframe selector and the pending task).
        stop: set when the mission closes: its threads end and no frame is accepted.
        state: :class:`~gausslite.mission.state.MissionState`.
        closed_for_input: Finish or close began: streamed frames are refused.
        accept_ms: accept latency of each frame (ms, arrival to accepted); keyframe_latency_s: arrival to mapped (s).
    """

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.state = MissionState.MAPPING
        self.closed_for_input = False
        self.last_error = ""
        self.frames_received = 0
        self.frames_mapped = 0
        self.frames_keyframed = 0
        self.frames_skipped = 0
        self.frames_rejected = 0
        self.frames_failed = 0
        self.seconds_mapping = 0.0
        self.idle_iterations = 0
        self.keyframe_iterations = 0
        self.checkpoints = 0
        self.resumed_keyframes = 0
        self.n_gaussians = 0
        self.n_active = 0
        self.accept_ms: "deque[float]" = deque(maxlen=LATENCIES_KEPT)
        self.keyframe_latency_s: "deque[float]" = deque(maxlen=LATENCIES_KEPT)

    def fail(self, msg: str) -> None:
        """The mission failed: state ``FAILED``, ``last_error`` = ``msg``."""
        with self.lock:
            self.state = MissionState.FAILED
            self.last_error = msg

    def frame_failed(self, msg: str) -> None:
        """One frame's step failed (the mission maps on): ``frames_failed`` + 1, ``last_error`` = ``msg``."""
        with self.lock:
            self.frames_failed += 1
            self.last_error = msg

    def set_error(self, msg: str) -> None:
        """Set ``last_error`` (the pusher reports "" after each acknowledged push)."""
        with self.lock:
            self.last_error = msg

    def check_accepts(self, mission_id: str, streamed: bool) -> None:
        """Raise unless the mission takes a frame now (call with :attr:`lock` held).

        Args:
            mission_id: the mission's id (for the message).
            streamed: a frame from outside (True) or from the mission's own replay (False: a replay's frames are
                still taken while Finish waits for the replay to end).
        Raises:
            MissionError: the mission is finished, failed or closed, or (``streamed``) finishing.
        """
        closed = (self.state in (MissionState.FINISHED, MissionState.FAILED) or self.stop.is_set()
                  or (streamed and (self.closed_for_input or self.state == MissionState.FINISHING)))
        if closed:
            raise MissionError(f"mission {mission_id} is {self.state.lower()}: no more frames accepted"
                               + (f" ({self.last_error})" if self.state == MissionState.FAILED else ""))

    def begin_finish(self) -> bool:
        """Finish begins: frames from outside are refused from now on, and a mission still mapping is
        ``FINISHING``. Returns whether this is the first close for input (Finish or :meth:`close
        <gausslite.mission.runtime.AgentRuntime.close>` did not run before)."""
        with self.lock:
            first = not self.closed_for_input
            self.closed_for_input = True
            if self.state in (MissionState.MAPPING, MissionState.REPLAY_DONE):
                self.state = MissionState.FINISHING
            return first

    def end_finish(self) -> None:
        """Finish ended: the mission is ``FINISHED`` (a failed one stays ``FAILED``)."""
        with self.lock:
            if self.state != MissionState.FAILED:
                self.state = MissionState.FINISHED

    def restore(self, counters: dict) -> None:
        """Continue from a checkpoint's ``counters`` (name → value): those of :data:`CHECKPOINT_COUNTERS` are set,
        other names are ignored."""
        with self.lock:
            for k in CHECKPOINT_COUNTERS:
                if k in counters:
                    setattr(self, k, counters[k])

    def counter_status(self) -> dict:
        """The counters and latencies of ``MissionStatus`` after ``last_error`` (call with :attr:`lock` held):
        ``seconds_mapping``, ``frames_keyframed``, ``frames_skipped``, ``accept_latency_ms_p99`` (ms, over the
        mission), ``accept_latency_ms_p99_recent`` (the last :data:`RECENT_FRAMES` frames), ``keyframe_latency_s_p95``
        (s), ``idle_iterations``, ``checkpoints``, ``resumed_keyframes``, ``frames_rejected``, ``frames_failed``,
        ``keyframe_iterations``."""
        return {"seconds_mapping": self.seconds_mapping,
                "frames_keyframed": self.frames_keyframed, "frames_skipped": self.frames_skipped,
                "accept_latency_ms_p99": percentile(self.accept_ms, 99),
                "accept_latency_ms_p99_recent": percentile(list(self.accept_ms)[-RECENT_FRAMES:], 99),
                "keyframe_latency_s_p95": percentile(self.keyframe_latency_s, 95),
                "idle_iterations": self.idle_iterations, "checkpoints": self.checkpoints,
                "resumed_keyframes": self.resumed_keyframes, "frames_rejected": self.frames_rejected,
                "frames_failed": self.frames_failed,
                "keyframe_iterations": self.keyframe_iterations}
