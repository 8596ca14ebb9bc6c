"""The mapping worker: the mission's thread that maps keyframes (paper Sec. III-B to III-D; ``docs/live.md``).

It takes the ingest queue's items (:mod:`gausslite.mission.ingest`) in order. For each keyframe it decodes the frame
(a ``PendingFrame`` of a live stream), chooses or corrects the mapping resolution, computes the relevance map, maps
it (``mapper.keyframe_budget_s`` per keyframe, decoding and relevance included, or fixed iterations), every
``upload_keyframe_every`` mapped frames uploads the keyframe, every ``push.every`` hands a snapshot of the ROI subset
to the pusher and every ``checkpoint_every`` writes a checkpoint. Between keyframes it applies a new task
(:class:`gausslite.mission.task.MissionTask`), returns a push's freed memory to the OS (:mod:`gausslite.mission.heap`,
at the mapper's priority, never the niced pusher's), follows the odometry's loop closures, and, under live ingest
with ``idle_optimize``, optimises over its keyframes while none is pending.

The markers :data:`FINISH` (final pass and final push) and :data:`DRAIN` (Finish without a push) end the mission's
mapping; :data:`STOP` ends the thread.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from typing import Callable, List, Optional

import numpy as np

from gausslite.datasets.base import Frame
from gausslite.mission.config import AgentConfig
from gausslite.mission.errors import stops_the_mission
from gausslite.mission.heap import trim_heap
from gausslite.mission.ingest import SLOT, Ingest
from gausslite.mission.progress import MissionProgress
from gausslite.mission.state import MissionState
from gausslite.mission.tracking import MissionPoses
from gausslite.mission.uploads import KeyframeUploads

log = logging.getLogger("gausslite.mission.runtime")  # one logger for the whole mission loop

__all__ = ["MappingWorker", "FINISH", "DRAIN", "STOP"]

FINISH = object()  #: queue item: the final pass, then the final push
DRAIN = object()  #: queue item: Finish without a push (everything before it is mapped)
STOP = None  #: queue item: the thread ends (close)


class MappingWorker:
    """The mapping thread of one mission (module docstring); :meth:`start` starts it.

    Args:
        agent_id, mission_id: the agent's and the mission's ids (thread name ``agent-<agent_id>-map``, logs).
        config: the mission's ``AgentConfig``.
        progress: the mission's :class:`~gausslite.mission.progress.MissionProgress` (counters, state, lock).
        ingest: the mission's :class:`~gausslite.mission.ingest.Ingest` (queue, keyframe candidate, frames between).
        poses: the mission's :class:`~gausslite.mission.tracking.MissionPoses` (loop closures the map follows).
        task: the mission's :class:`~gausslite.mission.task.MissionTask` (relevance, pending task).
        mapper: the mission's :class:`~gausslite.mapping.mapper.Mapper`.
        resolution: the mission's resolution governor (:class:`gausslite.mapping.resolution.ResolutionGovernor`).
        maps_detail: the mapper maps the task region at its own level (``mapper.detail``).
        uploads: the mission's :class:`~gausslite.mission.uploads.KeyframeUploads`.
        pusher: the mission's :class:`~gausslite.mission.pusher.Pusher`.
        share: the mission's :class:`~gausslite.mission.share.ShareSession` (snapshots for the pusher).
        checkpoint: the mission's :class:`~gausslite.mission.checkpoint.MissionCheckpoint`, or None.
        fail: ``(message) -> None``: the mission failed (the worker goes on taking items, maps nothing more).

    Attributes:
        eval_frames: the first ``eval_max_frames`` keyframes as mapped (Finish's PSNR over the kept frames).
    """

    def __init__(self, agent_id: str, mission_id: str, config: AgentConfig, *, progress: MissionProgress,
                 ingest: Ingest, poses: MissionPoses, task, mapper, resolution, maps_detail: bool,
                 uploads: KeyframeUploads, pusher, share, checkpoint, fail: Callable[[str], None]) -> None:
        self.agent_id, self.mission_id, self.config = agent_id, mission_id, config
        self.progress, self.ingest, self.poses, self.task = progress, ingest, poses, task
        self.mapper, self.resolution, self.maps_detail = mapper, resolution, maps_detail
        self.uploads, self.pusher, self.share, self.checkpoint = uploads, pusher, share, checkpoint
        self.fail = fail
        self.eval_frames: List[Frame] = []
        self.thread = threading.Thread(target=self.run, name=f"agent-{agent_id}-map", daemon=True)

    def start(self) -> None:
        """Start the thread (once)."""
        self.thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Queue :data:`STOP` and wait up to ``timeout_s`` for the thread (which must have been started)."""
        self.ingest.queue.put(STOP)
        self.thread.join(timeout_s)

    # ------------------------------------------------------------------ the loop
    def run(self) -> None:
        """The thread's loop: between items the housekeeping (module docstring), then one item."""
        q = self.ingest.queue
        while True:
            self._between_items()
            idle = self._idle()
            try:
                # a blocking wait wakes up now and then to apply a new task (MissionTask.request)
                item = q.get(block=False) if idle else q.get(timeout=0.5)
            except queue.Empty:
                if idle:
                    self._optimise_idle()
                continue
            try:
                if item is STOP:
                    return
                self._take(item)
            finally:
                q.task_done()

    def _between_items(self) -> None:
        """Apply a new task, and return a push's freed memory to the OS."""
        try:
            self.task.apply_pending(self.mapper, self.pusher)
        except Exception as e:
            self.fail(f"switching to the new task failed: {type(e).__name__}: {e}")
        if self.pusher.trim_due.is_set():  # a push's copies back to the OS, at the mapper's priority
            self.pusher.trim_due.clear()
            trim_heap()

    def _idle(self) -> bool:
        """Whether to optimise between keyframes instead of blocking on the queue."""
        p = self.progress
        return (self.ingest.online and self.config.idle_optimize and p.frames_mapped > 0
                and p.state == MissionState.MAPPING and not p.closed_for_input and not p.stop.is_set())

    def _optimise_idle(self) -> None:
        """One ``idle_chunk_s`` of optimisation over the stored keyframes (the map first follows a loop closure); a
        failed chunk is logged and counted as one step's failure (:meth:`step_failed`), and the mission maps on."""
        try:
            self.poses.follow(self.mapper)  # a loop closed while the mapper waits for a keyframe
            n = self.mapper.optimize(max_seconds=self.config.idle_chunk_s)
        except Exception as e:
            self.step_failed("optimising between keyframes", e)
            time.sleep(self.config.idle_chunk_s)  # no busy loop of failures
            return
        with self.progress.lock:
            self.progress.idle_iterations += n
        if n == 0:
            time.sleep(0.01)

    def _take(self, item) -> None:
        """Act on one queue item: a Finish marker, a keyframe candidate (:data:`SLOT`) or a queued frame."""
        if item is FINISH:
            self._finish()
            return
        if item is DRAIN:
            self.pusher.final_done.set()
            return
        if item is SLOT:
            item = self.ingest.take_keyframe()
            if item is None:
                return
        if self.progress.state == MissionState.FAILED:
            return
        self.map_keyframe(*item)

    def _finish(self) -> None:
        """The final pass (after every loop closure is checked and followed) and the final push; a failed mission
        only ends its Finish."""
        if self.progress.state == MissionState.FAILED:
            self.pusher.final_done.set()
            return
        if self.progress.frames_mapped:
            if self.poses.follower is not None:  # every loop checked, then the map follows them
                self.poses.odometry.flush(self.config.final_pass_s)
                self.poses.follow(self.mapper)
            n = self.mapper.finalize(max_seconds=self.config.final_pass_s)
            log.info("agent %s: final pass, %d iterations", self.agent_id, n)
        self.offer_snapshot(final=True)

    # ------------------------------------------------------------------ one keyframe
    def step_failed(self, what: str, e: Exception) -> None:
        """One frame's step raised ``e``: out of memory or a full disk fails the mission
        (:func:`~gausslite.mission.errors.stops_the_mission`); any other error is logged with its traceback, counted
        (``frames_failed``, ``last_error``) and the mission maps on with the next frame."""
        msg = f"{what} failed: {type(e).__name__}: {e}"
        if stops_the_mission(e):
            self.fail(msg)
            return
        log.warning("agent %s mission %s: %s; the frame is skipped and the mission maps on", self.agent_id,
                    self.mission_id, msg, exc_info=e)
        self.progress.frame_failed(msg)

    def map_keyframe(self, frame, t_arrival: float) -> None:
        """Map one keyframe: decode, resolution, relevance, mapper, counters, uploads, pushes, checkpoint. Corrupt
        image data found only now is logged and counted as rejected; an error of any other step is the frame's alone
        (:meth:`step_failed`: logged, counted in ``frames_failed``, the mission maps on), unless it is out of memory
        or a full disk, which fail the mission.

        Args:
            frame: a :class:`~gausslite.datasets.base.Frame` (world-frame pose) or a not yet decoded one
                (``materialize() -> Frame``).
            t_arrival: ``time.perf_counter()`` when it arrived (the keyframe latency is measured from it).
        """
        t0 = time.perf_counter()
        native = self._decoded(frame)
        if native is None:
            return
        try:
            item, w, between, st = self._map(native, t0)
        except Exception as e:
            self.step_failed(f"mapping frame {native.frame_id}", e)
            return
        upload = self._count(item, st, t0, t_arrival)
        try:
            if upload:
                self.pusher.add_keyframe(*self.uploads.keyframe(native, item, w))
            if self.ingest.sends_between and between and w is not None:  # no relevance, no task region to carry over
                for view in self.uploads.between_views(item, w, between):
                    self.pusher.add_keyframe(*view)
        except Exception as e:  # the frame is mapped; only its upload is lost
            self.step_failed(f"uploading frame {native.frame_id}", e)
        log.debug("agent %s mapped frame %d: %d Gaussians (%d active), %.2f s", self.agent_id,
                  item.frame_id, st.n_gaussians, self.progress.n_active, st.seconds)
        self._periodic()

    def _decoded(self, frame) -> Optional[Frame]:
        """``frame`` decoded, or None (logged, counted as rejected) when its image data is corrupt."""
        if not hasattr(frame, "materialize"):
            return frame
        try:
            return frame.materialize()
        except ValueError as e:
            log.warning("agent %s mission %s: frame rejected at decoding: %s", self.agent_id, self.mission_id, e)
            with self.progress.lock:
                self.progress.frames_rejected += 1
                self.progress.last_error = f"rejected frame: {e}"
            return None

    def _map(self, native: Frame, t0: float) -> tuple:
        """Map ``native`` (decoded) at the mapping resolution; ``t0`` when the keyframe's work began. Returns ``(the
        keyframe as mapped, its relevance (H, W) bool, the frames between as mapped, FrameStats)``."""
        cfg = self.config
        if self.resolution.choice is None:
            intr = native.intrinsics
            self.resolution.start(intr.width, intr.height, cfg.mapper.keyframe_budget_s,
                                  cfg.mapper.budget.max_gaussians, region=self.maps_detail)
            self.uploads.fix()
        item = self.resolution.apply(native)
        native_between = self.ingest.take_between(item.frame_id)
        between = [self.resolution.apply(f) if isinstance(f, Frame) else f for f in native_between]
        w = self.task.relevance(item)
        # the task region at its own level (mapper.detail): the keyframe and its frames at the region's size
        detail = self.resolution.detail_view(native, w, native_between) if self.maps_detail else None
        self.poses.follow(self.mapper)  # a loop closure since the last keyframe: the map follows it first
        # the per-keyframe budget covers decoding and relevance too: the mapper gets what is left
        b = cfg.mapper.keyframe_budget_s
        left = None if b is None else max(1e-6, b - (time.perf_counter() - t0))
        st = self.mapper.map_frame(item, w, time_budget_s=left, between=between,
                                   **({} if detail is None else {"detail": detail}))
        self._record_iterations(st, w)
        if self.poses.follower is not None:
            self.poses.follower.mapped(item.frame_id)
        return item, w, between, st

    def _record_iterations(self, st, w: Optional[np.ndarray]) -> None:
        """Hand the resolution governor what keyframe ``st`` (``FrameStats``) got: its iterations, and its ROI-phase
        iterations when it showed the task region (relevance ``w``) and the map had task Gaussians to fit."""
        shows_region = w is not None and bool(np.any(w)) and bool(self.mapper.model.active.any())
        self.resolution.record(st.iters, st.active_iters if shows_region else None, st.n_gaussians, st.detail_px)

    def _count(self, item: Frame, st, t0: float, t_arrival: float) -> bool:
        """Count the mapped keyframe ``item`` (``FrameStats`` ``st``; ``t0`` when its work began, ``t_arrival`` when it
        arrived) and keep it for Finish's PSNR; returns whether it is uploaded (every ``upload_keyframe_every``-th)."""
        p, cfg = self.progress, self.config
        with p.lock:
            p.frames_mapped += 1
            p.frames_keyframed += 1
            p.keyframe_iterations += st.iters
            p.seconds_mapping += time.perf_counter() - t0
            p.keyframe_latency_s.append(time.perf_counter() - t_arrival)
            p.n_gaussians = st.n_gaussians
            p.n_active = int(self.mapper.model.active.sum())
            if len(self.eval_frames) < cfg.eval_max_frames:
                self.eval_frames.append(item)
            return (p.frames_mapped - 1) % cfg.upload_keyframe_every == 0

    def _periodic(self) -> None:
        """Every ``push.every`` mapped frames a snapshot for the pusher; every ``checkpoint_every`` a checkpoint (a
        failure is logged: a full disk must not stop mapping)."""
        cfg, mapped = self.config, self.progress.frames_mapped
        if mapped % cfg.push.every == 0:
            try:
                self.offer_snapshot(final=False)
            except Exception as e:  # this push is lost; the next one carries the map
                self.step_failed(f"taking the snapshot after frame {mapped}", e)
        if self.checkpoint is not None and cfg.checkpoint_every and mapped % cfg.checkpoint_every == 0:
            try:
                self.checkpoint.save()
            except Exception as e:
                log.warning("agent %s: checkpoint failed: %s: %s", self.agent_id, type(e).__name__, e)

    def offer_snapshot(self, final: bool) -> None:
        """Hand the pusher what the next push needs (:meth:`ShareSession.capture
        <gausslite.mission.share.ShareSession.capture>`) and record the version handed over in the checkpoint
        folder."""
        self.pusher.offer(self.share.capture(self.mapper), self.progress.frames_mapped, final)
        if self.checkpoint is not None:
            self.checkpoint.record_version()
