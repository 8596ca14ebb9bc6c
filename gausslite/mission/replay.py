"""A dataset replayed into a mission from a background thread (``AgentRuntime.replay``; docs/realtime.md).

With ``agent.realtime`` the frames are sent at the dataset's clock (``frame.timestamp`` relative to the first frame,
divided by ``agent.rate``) through keyframe ingest, as a robot would stream them; otherwise every frame is mapped
(offline behaviour). Under ``agent.scoring`` with withheld frames (``novel_every``) those never reach the mapper;
with the odometry they are still tracked in order, at their own time, as a robot's odometry tracks every frame
(their estimated poses are where they are scored).
"""

from __future__ import annotations

import threading
import time
from typing import Callable, Optional

import numpy as np

from gausslite.mission.config import AgentConfig
from gausslite.mission.errors import MissionError
from gausslite.mission.progress import MissionProgress
from gausslite.mission.state import MissionState
from gausslite.mission.team_frame import WorldFrames
from gausslite.mission.tracking import MissionPoses

__all__ = ["Replay"]


class Replay:
    """One replayed dataset: its frames in the world frame, the ones withheld, and the thread feeding them.

    Args:
        dataset: indexable frames (``len``, ``[i] -> Frame``) with poses in the robot's map frame.
        config: the mission's ``AgentConfig`` (``realtime``, ``rate``, ``scoring``).
        T_world_map: (4, 4) float64 map-to-world transform, or None (the poses are world poses already).

    Attributes:
        frames: frames in the dataset (``replay_frames``).
        dataset: the frames in the world frame (:class:`~gausslite.mission.team_frame.WorldFrames`).
        held: indices withheld from the mapper. novel_ids: their frame ids, None when none is withheld by rule.
        realtime: frames are sent at the dataset's clock through keyframe ingest.
        thread: the feeding thread, once :meth:`start` ran.
    """

    def __init__(self, dataset, config: AgentConfig, T_world_map: Optional[np.ndarray]) -> None:
        self.frames = len(dataset)
        self.dataset = dataset if T_world_map is None else WorldFrames(dataset, T_world_map)
        self.rate = config.rate
        self.realtime = bool(config.realtime)
        self.held: frozenset = frozenset()
        self.novel_ids: Optional[frozenset] = None
        sc = config.scoring
        if sc.withholds():
            # lazy: keeps gausslite.mission importable without the dataset loaders
            from gausslite.datasets.subset import withheld_indices

            self.held = frozenset(withheld_indices(len(dataset), sc.novel_every))
            self.novel_ids = frozenset(int(self.dataset[i].frame_id) for i in self.held)
        self.thread: Optional[threading.Thread] = None

    @property
    def running(self) -> bool:
        """The feeding thread is alive."""
        return self.thread is not None and self.thread.is_alive()

    def wait(self, deadline: Optional[float] = None) -> None:
        """Wait until the feeding thread has sent every frame (none started: at once).

        Args:
            deadline: ``time.monotonic()`` bound (None: none).
        Raises:
            TimeoutError: the thread still runs at ``deadline``.
        """
        t = self.thread
        while t is not None and t.is_alive():
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError("replay still running at the Finish deadline")
            t.join(0.1)

    def start(self, *, submit: Callable, progress: MissionProgress, poses: MissionPoses, join: Callable[[], None],
              fail: Callable[[str], None], report: Optional[Callable[[int, int], None]] = None,
              name: str = "replay") -> threading.Thread:
        """Start feeding the frames.

        Args:
            submit: ``(frame) -> bool``: hands one frame (world frame) to the mission.
            progress: the mission's :class:`~gausslite.mission.progress.MissionProgress` (``stop`` ends the replay;
                the state becomes ``REPLAY_DONE`` once every frame is mapped).
            poses: the mission's :class:`~gausslite.mission.tracking.MissionPoses` (withheld frames are tracked).
            join: ``() -> None``: returns once every queued frame is mapped.
            fail: ``(message) -> None``: the replay failed (an unreadable frame).
            report: ``(sent, total) -> None`` after each frame sent (total: frames not withheld).
            name: the thread's name.
        Returns:
            the started thread.
        """
        self.thread = threading.Thread(target=self._run, args=(submit, progress, poses, join, fail, report),
                                       name=name, daemon=True)
        self.thread.start()
        return self.thread

    def _run(self, submit, progress: MissionProgress, poses: MissionPoses, join, fail, report) -> None:
        ds, held, stop = self.dataset, self.held, progress.stop
        n, sent = len(ds) - len(held), 0
        t_start, ts0 = time.perf_counter(), None
        try:
            for i in range(len(ds)):
                if stop.is_set():
                    return
                if i in held and not poses.tracks:
                    continue
                fr = ds[i]
                if self.realtime:
                    ts0 = fr.timestamp if ts0 is None else ts0
                    wait = t_start + (fr.timestamp - ts0) / self.rate - time.perf_counter()
                    if wait > 0 and stop.wait(wait):
                        return
                if i in held:
                    poses.track(fr)
                    continue
                submit(fr)
                sent += 1
                if report:
                    report(sent, n)
            join()
            with progress.lock:
                if progress.state == MissionState.MAPPING:
                    progress.state = MissionState.REPLAY_DONE
        except MissionError:
            return
        except Exception as e:  # unreadable frame etc.
            fail(f"replay failed: {type(e).__name__}: {e}")
