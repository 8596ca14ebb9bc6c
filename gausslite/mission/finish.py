"""How a mission finishes (:class:`MissionFinish`): frames are refused from then on, what is queued is mapped, the
final push is made, the final map is scored (over the kept keyframes, and for a replay over every frame under each
scoring protocol, :mod:`gausslite.mission.scoring`) and summarised in a
:class:`~gausslite.mission.scoring.MissionSummaryData`; the mission's ``on_finished`` hook runs last.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Optional

from gausslite.mission.scoring import MissionSummaryData, score_kept_frames, score_protocols, summarise
from gausslite.mission.worker import DRAIN, FINISH

log = logging.getLogger("gausslite.mission.runtime")  # the mission's one logger

__all__ = ["MissionFinish"]


class MissionFinish:
    """Finish of one mission, run once (later calls return the same summary).

    Args:
        runtime: the :class:`~gausslite.mission.runtime.AgentRuntime` it finishes (its parts, replay, status and
            ``on_finished`` hook are read when Finish runs).

    Attributes:
        summary: the :class:`~gausslite.mission.scoring.MissionSummaryData` of the Finish done (None before).
        tracked_views, predicted_views: frame id → ``TrackedView`` of the tracked / novel-tracked frames, and of the
            novel ones (predicted), as last scored (:meth:`evaluate_protocols`).
    """

    def __init__(self, runtime) -> None:
        self.rt = runtime
        self.summary: Optional[MissionSummaryData] = None
        self.tracked_views: dict = {}
        self.predicted_views: dict = {}
        self._lock = threading.Lock()

    def finish(self, push: bool = True, evaluate: bool = True, timeout_s: Optional[float] = None) -> MissionSummaryData:
        """Stop accepting frames, map what is queued, do the final push, evaluate; idempotent (one Finish at a time;
        a later one returns the first one's summary).

        Args:
            push: do the final push (retried up to ``push.final_timeout_s``).
            evaluate: compute full-image and ROI PSNR over the kept mapped frames (ROI needs annotations
                and a task id), and for a replay every scoring protocol over all its frames.
            timeout_s: overall bound on waiting for another Finish, mapping and the final push (None: unbounded).
        Returns:
            MissionSummaryData.
        Raises:
            TimeoutError: another Finish, mapping or the final push did not complete within ``timeout_s``.
        """
        if not self._lock.acquire(timeout=-1 if timeout_s is None else max(0.0, timeout_s)):
            raise TimeoutError(f"mission {self.rt.mission_id}: another Finish still running after {timeout_s} s")
        try:
            return self.summary if self.summary is not None else self._finish(push, evaluate, timeout_s)
        finally:
            self._lock.release()

    def _finish(self, push: bool, evaluate: bool, timeout_s: Optional[float]) -> MissionSummaryData:
        rt = self.rt
        first = rt.progress.begin_finish()
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        left = lambda: None if deadline is None else max(0.0, deadline - time.monotonic())  # noqa: E731
        if first:
            if rt.lifecycle.replayed is not None:  # a replay still running completes: Finish maps the rest, then pushes
                rt.lifecycle.replayed.wait(deadline)
            # both markers queue behind the pending keyframe; the worker stops optimising between keyframes
            rt.ingest.queue.put(FINISH if push else DRAIN)
        if not rt.pusher.final_done.wait(left()):
            raise TimeoutError(f"mission {rt.mission_id}: mapping/final push not done within {timeout_s} s")
        rt.wait_mapped(left())
        scored = evaluate and rt.progress.frames_mapped
        psnr, roi_psnr = rt.evaluate() if scored else (None, None)
        protocols = rt.evaluate_protocols() if scored and rt.lifecycle.replayed is not None else {}
        rt.progress.end_finish()
        self.summary = summarise(rt.status(), rt.pusher, rt.mapper, rt.config, pushed=push, psnr=psnr,
                                 roi_psnr=roi_psnr, protocols=protocols, frames_all=rt.replay_frames,
                                 tracked_views=self.tracked_views, predicted_views=self.predicted_views)
        if protocols:
            # lazy: keeps gausslite.mission importable without torch (scoring imported it already)
            from gausslite.evaluation import protocol_line

            log.info("agent %s final map, ROI PSNR (dB): %s", rt.agent_id, protocol_line(protocols))
        if rt.on_finished is not None:
            try:
                rt.on_finished(rt)
            except Exception as e:  # saving results must not lose the summary
                log.warning("agent %s: on_finished hook failed: %s", rt.agent_id, e)
        return self.summary

    def evaluate(self) -> tuple[Optional[float], Optional[float]]:
        """(full-image PSNR, ROI PSNR) in dB of the current map, mean over the kept mapped frames; ROI PSNR is
        None without annotations/task id or when no frame shows the ROI. Call only while the worker is idle."""
        rt = self.rt
        return score_kept_frames(rt.mapper, rt.worker.eval_frames, rt.annotations, rt.task.task_id)

    def evaluate_protocols(self, protocols: Optional[tuple] = None) -> dict:
        """The current map over every frame of the replayed dataset under the scoring protocols of
        ``config.scoring``, or of ``protocols``: :func:`gausslite.mission.scoring.score_protocols`'s result (at the
        odometry's estimated poses under ``agent.pose_source: odometry``), ``{}`` without a replayed dataset,
        annotations or task id. Fills :attr:`tracked_views` and :attr:`predicted_views`. Call while the worker is
        idle."""
        rt = self.rt
        rp, task_id = rt.lifecycle.replayed, rt.task.task_id
        if rp is None or rt.annotations is None or task_id is None:
            return {}
        self.tracked_views, self.predicted_views = {}, {}
        return score_protocols(rt.mapper, rp.dataset, rt.annotations, task_id, rt.config.scoring,
                               rt.resolution.factor, protocols=protocols, novel_ids=rp.novel_ids,
                               estimated_poses=rt.poses.estimated_poses if rt.poses.tracks else None,
                               record=self.tracked_views, predicted=self.predicted_views)
