"""The agent's pusher: the thread that sends each map version's shared subset to the fusion server (paper
Sec. III-E; ``docs/live.md``, ``docs/sharing.md``).

The mapping thread hands it what a push needs (:meth:`Pusher.offer`, a :class:`gausslite.mission.share.Captured`)
and the keyframes to upload with it (:meth:`Pusher.add_keyframe`); neither call waits for the network. The
pusher thread then, for the newest offer only (an older pending one is superseded):

1. selects the task subset and fine-tunes it in the share worker (:class:`gausslite.mission.share.ShareSession`);
2. plans a delta against the subset the server acknowledged last, or a full upload, and sends it in chunks;
3. uploads the keyframes not yet sent (at most ``upload_backlog_max`` wait);
4. on failure retries with exponential backoff (``push.backoff_s`` doubling up to ``push.max_backoff_s``, kept across
   offers while the link is down). A periodic push is retried until it is acknowledged or a newer offer
   replaces it, so at most two subsets are held however long the link is down, and the newest goes out when
   it returns; the final one is retried for ``push.final_timeout_s``.

The pusher is the one layer that retries a push: the fusion port beneath it makes one attempt per call
(``gausslite_services.fusion_server.client.FusionClient`` sends each call once, with its deadline, and raises the
call's error), so an attempt costs at most its calls' deadlines and the backoff alone spaces the attempts. Each
attempt resumes the upload: ``upload_chunks`` asks which chunks the server holds and sends the others.

:meth:`Pusher.status` gives the backlog and the last acknowledged version (``GetStatus``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, List, Optional

import numpy as np

from gausslite.fusion.views import ViewBudget, roi_crop, view_bytes
from gausslite.mission.errors import PreconditionFailed
from gausslite.mission.config import AgentConfig
from gausslite.mission.ports import FusionPort
from gausslite.mission.share import Captured, ShareSession

log = logging.getLogger(__name__)

__all__ = ["Pusher", "PushRecord", "Snapshot"]


@dataclass
class PushRecord:
    """One successful push: ``version``, ``n_shared`` Gaussians of ``n_total``, wire bytes sent, chunk
    count; ``delta`` (a delta push carrying ``records`` Gaussians and ``removed`` row removals),
    ``frames_mapped`` when the snapshot was taken."""

    version: int
    n_shared: int
    n_total: int
    bytes_on_wire: int
    n_chunks: int
    keyframes: int
    seconds: float
    delta: bool = False
    records: int = 0
    removed: int = 0
    frames_mapped: int = 0
    unchanged: bool = False  #: nothing changed since ``version`` (acknowledged before): no subset upload


@dataclass
class WaitingView:
    """A refinement view queued for upload: the frame (an ROI crop with ``refine_views.crop``), its (H, W) bool
    relevance (sent with it; None: none) and its bytes on the wire (:func:`gausslite.fusion.views.view_bytes`),
    measured once by the push thread (None until then: a view may wait through many pushes)."""

    frame: Any
    roi: Optional[np.ndarray]
    size: Optional[int] = None


@dataclass
class Snapshot:
    """One map version on its way to the fusion server."""

    version: int
    gaussians: Any  # GaussianArrays
    n_total: int
    final: bool = False
    ids: Any = None  # (N,) int64 stable Gaussian ids of the rows
    frames_mapped: int = 0
    #: (cache key, compact ROI keyframes) captured with the subset: the pusher thread fine-tunes it before
    #: the push (``share.finetune_iters``), so the mapping thread never waits for a fine-tune; None = push as is
    finetune: Any = None
    #: ``share.rule: task``: (map copy, ROI views, keyframe poses, ROI keyframes or None) from which the pusher thread
    #: selects the subset (``gaussians`` None and ``ids`` every row's until then)
    select: Any = None


class Pusher:
    """The push side of one mission (module docstring); :meth:`start` starts its thread.

    Args:
        agent_id: the agent's id on the fusion server.
        task_text: the mission's task (sent when a fusion session opens).
        config: the mission's ``AgentConfig`` (``upload_backlog_max``; of ``push``: ``backoff_s``,
            ``max_backoff_s``, ``final_timeout_s``, ``nice``; ``jpeg_quality``, ``keyframe_format``).
        fusion: the fusion side (:class:`gausslite.mission.ports.FusionPort`: the gRPC client or an in-process
            stand-in; a rejected delta base raises :class:`gausslite.mission.errors.PreconditionFailed`), or None:
            offers are dropped.
        share: the mission's :class:`gausslite.mission.share.ShareSession`.
        mapper: the mission's mapper (its config drives the fine-tune).
        intrinsics: ``() -> Intrinsics`` of the mission's frames (sent when a fusion session opens).
        report: ``(message) -> None``, called with each push failure and with "" after each acknowledged push
            (the mission's ``last_error``).
    """

    def __init__(self, agent_id: str, task_text: str, config: AgentConfig, fusion: Optional[FusionPort],
                 share: ShareSession, mapper, intrinsics: Callable[[], Any], report: Callable[[str], None]) -> None:
        self.agent_id, self.task_text, self.config = agent_id, task_text, config
        self.fusion, self.share, self.mapper = fusion, share, mapper
        self._intrinsics, self._report = intrinsics, report
        self._lock = threading.Lock()
        self._cv = threading.Condition(self._lock)
        self._stop = threading.Event()
        #: set once the final push ended (acknowledged or not; ``final_push_ok`` tells) or the mission gave up
        self.final_done = threading.Event()
        #: set after each push: the push's temporary copies are garbage, and the mission's owner should return them
        #: to the OS (:func:`~gausslite.mission.heap.trim_heap`) from a thread at the mapper's priority. The pusher
        #: never trims itself: at ``push.nice`` a thread holding the interpreter lock (``gc.collect``) or the
        #: allocator's locks (``malloc_trim``) is descheduled whenever a CPU-bound process wants the cores, and
        #: every thread of the agent then waits for it (measured beside an all-core load: the mapper stalled for
        #: 9-11 s at a time, docs/live.md "Beside other processes").
        self.trim_due = threading.Event()
        self.final_push_ok = False
        self.pushes: List[PushRecord] = []
        self.push_failures = 0
        self.keyframes_uploaded = 0
        self.total_upload_bytes = 0  # bytes of subset chunks sent over the mission (all pushes)
        self.final_subset_bytes = 0  # the last pushed subset encoded whole
        self._version = 0  # newest map version offered (or resumed)
        self._pending: Optional[Snapshot] = None
        self._inflight: Optional[int] = None  # version of the snapshot being worked on
        self._abandoned = False  # the last selected snapshot was superseded before its fine-tune
        self._session_open = False
        self._retry_delay = config.push.backoff_s  # next backoff; kept across snapshots while the link is down
        self._link_down_since: Optional[float] = None  # monotonic time of the first failure since the last ack
        self._kf_pending: List[WaitingView] = []  # views to upload with the next push (oldest first)
        #: bytes of the refinement views sent over the mission, bounded by agent.refine_views.budget_ratio
        self.views = ViewBudget(config.refine_views.budget_ratio, config.refine_views.reserve)
        self.thread = threading.Thread(target=self._loop, name=f"agent-{agent_id}-push", daemon=True)

    def start(self) -> None:
        """Start the pusher thread (once)."""
        self.thread.start()

    # ------------------------------------------------------------------ mapping thread
    @property
    def version(self) -> int:
        """The newest map version offered (what a checkpoint records; the next offer is one above)."""
        with self._lock:
            return self._version

    def resume(self, version: int) -> None:
        """Continue a resumed mission above ``version`` (never reuse a version the fusion server may hold)."""
        with self._lock:
            self._version = max(self._version, int(version))

    def offer(self, cap: Captured, frames_mapped: int, final: bool) -> int:
        """Hand the pusher map version ``version + 1`` (``cap`` from :meth:`ShareSession.capture`); a pending
        older one is dropped. Returns the new version. Does not wait."""
        with self._lock:
            self._version += 1
            self._pending = Snapshot(self._version, cap.gaussians, cap.n_total, final, cap.ids, frames_mapped,
                                     None, cap.select)
            self._cv.notify_all()
            return self._version

    def add_keyframe(self, frame, roi: Optional[np.ndarray]) -> bool:
        """Upload ``frame`` (with its (H, W) bool relevance ``roi``, or None) with the next push, as a refinement
        view: whole, or its ROI crop with ``agent.refine_views.crop`` (:func:`gausslite.fusion.views.roi_crop`; a
        frame whose ROI has fewer than ``refine_views.min_roi_px`` pixels is then dropped). Only the newest
        ``upload_backlog_max`` wait. Returns whether the view was queued."""
        keep, rv = self.config.upload_backlog_max, self.config.refine_views
        if rv.crop:
            if roi is None or int(np.count_nonzero(roi)) < rv.min_roi_px:
                return False
            frame, roi = roi_crop(frame, roi, rv.margin_px)
        with self._lock:
            self._kf_pending.append(WaitingView(frame, None if roi is None else np.asarray(roi, bool)))
            del self._kf_pending[:-keep]
        return True

    def status(self) -> dict:
        """The push keys of ``MissionStatus``: pushes, failures, last acknowledged and newest versions, backlog,
        keyframes waiting and uploaded, seconds the link has been down."""
        with self._lock:
            return {"pushes": len(self.pushes), "push_failures": self.push_failures,
                    "last_pushed_version": self.pushes[-1].version if self.pushes else 0,
                    "newest_map_version": self._version,
                    "push_backlog": int(self._pending is not None) + int(self._inflight is not None),
                    "keyframes_backlog": len(self._kf_pending),
                    "link_down_s": (0.0 if self._link_down_since is None
                                    else time.monotonic() - self._link_down_since),
                    "keyframes_uploaded": self.keyframes_uploaded}

    def stop(self) -> None:
        """Ask the thread to stop: a push waiting to retry ends now, one in flight at its next check."""
        self._stop.set()
        with self._lock:
            self._cv.notify_all()

    def close(self, timeout_s: float = 5.0) -> None:
        """:meth:`stop`, then wait up to ``timeout_s`` for the thread. Safe to call more than once."""
        self.stop()
        if self.thread.is_alive() and self.thread is not threading.current_thread():
            self.thread.join(timeout_s)

    # ------------------------------------------------------------------ pusher thread
    def _lower_priority(self) -> None:
        """Give the pusher thread ``push.nice`` niceness; threads it starts inherit it."""
        nice = self.config.push.nice
        if not nice or not hasattr(os, "setpriority"):
            return
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
        except OSError as e:  # not permitted in some containers: the pusher keeps the mapper's priority
            log.warning("agent %s: cannot lower the pusher's priority: %s", self.agent_id, e)

    def _loop(self) -> None:
        self._lower_priority()
        while True:
            with self._lock:
                while self._pending is None and not self._stop.is_set():
                    self._cv.wait(0.5)
                if self._stop.is_set() and self._pending is None:
                    return
                snap, self._pending = self._pending, None
                self._inflight = snap.version
            try:
                self.push_snapshot(snap)
            finally:
                with self._lock:
                    self._inflight = None
                self.trim_due.set()  # the owner trims at its own priority (trim_due)

    def _final(self, ok: bool) -> None:
        self.final_push_ok = ok
        self.final_done.set()

    def push_snapshot(self, snap: Snapshot) -> None:
        """Select, fine-tune and push one snapshot (pusher thread); ends the final one (``final_done``)."""
        if self.fusion is None:
            if snap.final:
                self._final(False)
            return
        if snap.select is not None:
            if self._superseded(snap):  # a newer snapshot waits: select that one
                return
            try:
                cap = self.share.select(Captured(snap.gaussians, snap.ids, snap.n_total, snap.select),
                                        self.config.mapper.backend)
                snap = dataclasses.replace(snap, gaussians=cap.gaussians, ids=cap.ids, finetune=cap.finetune,
                                           select=None)
            except Exception as e:  # keep pushing later snapshots; a failed final one is reported
                log.exception("agent %s: task selection of v%d failed: %s", self.agent_id, snap.version, e)
                self._report(f"share selection failed: {type(e).__name__}: {e}")
                if snap.final:
                    self._final(False)
                return
        if snap.finetune is not None:
            # a newer snapshot waits: spend the fine-tune on that one, but never twice in a row (when a selection
            # takes longer than the keyframes between pushes, every selected snapshot would be superseded and a
            # long live mission would stop pushing)
            if self._superseded(snap) and not self._abandoned:
                self._abandoned = True
                log.info("agent %s: v%d superseded after its selection; the next one is pushed", self.agent_id,
                         snap.version)
                return
            self._abandoned = False
            try:
                out = self.share.finetuned(snap.gaussians, snap.ids, *snap.finetune, self.mapper.cfg)
            except Exception as e:  # a fine-tune failure must not lose the push: send the rows as mapped
                log.exception("agent %s: fine-tune of v%d failed, pushing the subset as mapped: %s",
                              self.agent_id, snap.version, e)
                out = snap.gaussians
            snap = dataclasses.replace(snap, gaussians=out, finetune=None)
        ok = self._push_with_retries(snap, self.config.push.final_timeout_s if snap.final else None)
        if snap.final:
            self._final(ok)

    def _superseded(self, snap: Snapshot) -> bool:
        with self._lock:
            return (not snap.final) and self._pending is not None

    def _push_with_retries(self, snap: Snapshot, budget_s: Optional[float]) -> bool:
        """Push ``snap`` until acknowledged (True). Gives up (False) when the pusher stops, when a newer
        snapshot is pending (it carries the newer map), or, with ``budget_s`` (seconds; the final push), when
        the next attempt would start after it. The backoff doubles up to ``push.max_backoff_s`` and is kept across
        snapshots while the link stays down, so a long outage costs one attempt every ``push.max_backoff_s``. Each
        attempt is one :meth:`push_once` (the fusion port makes each of its calls once: no retries beneath)."""
        deadline = None if budget_s is None else time.monotonic() + budget_s
        attempt = 0
        while True:
            attempt += 1
            try:
                self.push_once(snap)
                return True
            except Exception as e:  # grpc.RpcError, ConnectionError, client-side errors
                msg = f"push v{snap.version} attempt {attempt} failed: {type(e).__name__}: {_short(e)}"
                with self._lock:
                    self.push_failures += 1
                    self._session_open = False  # re-open after a server restart
                    if self._link_down_since is None:
                        self._link_down_since = time.monotonic()
                    delay = self._retry_delay
                    self._retry_delay = min(delay * 2.0, self.config.push.max_backoff_s)
                self._report(msg)
                log.warning("agent %s: %s (next attempt in %.1f s)", self.agent_id, msg, delay)
            if self._stop.is_set() or self._superseded(snap):
                return False
            if deadline is not None and time.monotonic() + delay > deadline:
                return False
            with self._lock:  # a newer snapshot or close() ends the wait early
                self._cv.wait_for(lambda: self._stop.is_set() or (not snap.final and self._pending is not None),
                                  timeout=delay)

    def _acknowledged(self, rec: PushRecord, n_keyframes: int) -> None:
        """Record the server's acknowledgement of a push (``rec``, with ``n_keyframes`` keyframes uploaded) as one
        change of :meth:`status`: the push counted, no snapshot in flight, the link up and its backoff reset. A reader
        never sees the version acknowledged while the backlog or the outage still shows it."""
        with self._lock:
            if self._link_down_since is not None:
                log.info("agent %s: fusion link back after %.1f s; v%d acknowledged", self.agent_id,
                         time.monotonic() - self._link_down_since, rec.version)
            self.total_upload_bytes += rec.bytes_on_wire
            self.pushes.append(rec)
            self.keyframes_uploaded += n_keyframes
            self._inflight = None
            self._retry_delay = self.config.push.backoff_s
            self._link_down_since = None
        self._report("")

    def _refined(self, frame):
        """``frame`` at its refined pose (the mapper's keyframe correction, ``pose.refine``; full-image and ROI-phase
        iterations align it) as the fusion refinement should see it; unchanged without a correction."""
        poses = getattr(self.mapper, "poses", None)
        E = poses.corrections.get(int(frame.frame_id)) if poses is not None else None
        return frame if E is None else dataclasses.replace(frame, c2w=np.asarray(frame.c2w, np.float64) @ E)

    def _upload_pending_keyframes(self, c: FusionPort, final: bool = False) -> tuple[list, int]:
        """Upload the keyframes not yet sent (with their ROI) that the view budget allows (:attr:`views`: the
        farthest first; the others wait for a larger subset, and the budget's reserve for the ``final`` push);
        returns (keyframes sent, count acknowledged)."""
        cfg = self.config
        with self._lock:
            waiting = list(self._kf_pending)
        if not waiting:
            return [], 0
        refined = [self._refined(w.frame) for w in waiting]
        for w in waiting:  # encoded once: a view may wait through many pushes
            if w.size is None:
                w.size = view_bytes(w.frame, w.roi, cfg.keyframe_format, cfg.jpeg_quality)
        before = dataclasses.replace(self.views, poses=list(self.views.poses))
        chosen = self.views.choose([w.size for w in waiting], [f.c2w for f in refined], self.final_subset_bytes,
                                   final)
        n_kf = 0
        if chosen:
            try:
                n_kf = int(c.upload_keyframes(self.agent_id, [refined[i] for i in chosen],
                                              jpeg_quality=cfg.jpeg_quality, color_format=cfg.keyframe_format,
                                              rois=[waiting[i].roi for i in chosen]) or 0)
            except Exception:
                self.views = before  # nothing of this upload counts as sent
                raise
            with self._lock:
                sent = {id(waiting[i]) for i in chosen}
                self._kf_pending = [w for w in self._kf_pending if id(w) not in sent]
        return [waiting[i].frame for i in chosen], n_kf

    def views_unsent(self) -> int:
        """Refinement views queued and never sent (the budget was short, or the link down)."""
        with self._lock:
            return len(self._kf_pending)

    def set_task(self, task_text: str) -> None:
        """The mission's task changed: the next push re-opens the fusion session under ``task_text``."""
        with self._lock:
            self.task_text = task_text
            self._session_open = False

    def push_once(self, snap: Snapshot) -> None:
        """One attempt at pushing the selected (and fine-tuned) ``snap``: open the fusion session if needed,
        upload the delta or full subset, then the pending keyframes. Raises what the fusion client raises."""
        t0 = time.perf_counter()
        c = self.fusion
        if not self._session_open:
            info = c.open_session(self.agent_id, self.task_text, self._intrinsics())
            self._session_open = True
            latest = int(getattr(info, "latest_map_version", 0) or 0)
            if latest >= snap.version and not self.share.holds_base:
                # the server holds this agent's versions from an earlier mission (or from before a crash that lost
                # the version file): never reuse one, or the resumable upload would take the old chunks for ours
                with self._lock:
                    self._version = max(self._version, latest) + 1
                    snap = dataclasses.replace(snap, version=self._version)
                log.warning("agent %s: the fusion server holds v%d of this agent; pushing as v%d", self.agent_id,
                            latest, snap.version)
        plan = self.share.plan(snap.ids, snap.gaussians, snap.version)
        if plan.is_noop:
            # the server holds exactly this subset already (e.g. the final push right after a periodic one):
            # no upload (an empty delta is still 270 B of headers); pending keyframes still go
            self.final_subset_bytes = plan.full_bytes if plan.full_bytes is not None else self.final_subset_bytes
            kfs, _ = self._upload_pending_keyframes(c, snap.final)
            rec = PushRecord(plan.base_version, len(snap.gaussians), snap.n_total, 0, 0, len(kfs),
                             time.perf_counter() - t0, True, 0, 0, snap.frames_mapped, unchanged=True)
            self._acknowledged(rec, len(kfs))
            log.info("agent %s: subset unchanged since v%d; no upload", self.agent_id, plan.base_version)
            return
        try:
            r = c.upload_chunks(self.agent_id, plan.version, plan.chunks, n_gaussians=plan.n_records,
                                full_map_gaussians=snap.n_total)
        except PreconditionFailed as e:
            if not plan.is_delta:
                raise
            # the server lacks the delta's base (restarted without its data, or superseded): full upload
            log.warning("agent %s: delta v%d rejected (%s); uploading the full subset", self.agent_id,
                        plan.version, _short(e))
            self.share.forget()
            with self._lock:
                self._version += 1
                version = self._version
            plan = self.share.plan(snap.ids, snap.gaussians, version)
            r = c.upload_chunks(self.agent_id, plan.version, plan.chunks, n_gaussians=plan.n_records,
                                full_map_gaussians=snap.n_total)
        if not getattr(r, "complete", True):
            raise RuntimeError(f"subset v{plan.version} upload incomplete ({getattr(r, 'n_chunks', '?')} chunks)")
        self.share.acknowledge(plan)
        self.final_subset_bytes = plan.full_bytes if plan.full_bytes is not None else plan.nbytes
        kfs, n_kf = self._upload_pending_keyframes(c, snap.final)
        rec = PushRecord(plan.version, len(snap.gaussians), snap.n_total, int(getattr(r, "bytes_sent", 0)),
                         int(getattr(r, "n_chunks", 0)), len(kfs), time.perf_counter() - t0, plan.is_delta,
                         plan.n_records, plan.n_removed, snap.frames_mapped)
        self._acknowledged(rec, len(kfs))
        log.info("agent %s pushed v%d: %d/%d Gaussians, %d B, %d keyframes (%d acknowledged)", self.agent_id,
                 rec.version, rec.n_shared, rec.n_total, rec.bytes_on_wire, len(kfs), n_kf)


def _short(e: BaseException) -> str:
    """A short message for an exception: ``CODE: details`` of a gRPC error, else its text (300 characters)."""
    details = getattr(e, "details", None)
    if callable(details):
        try:
            code = e.code()  # type: ignore[attr-defined]
            return f"{getattr(code, 'name', code)}: {details()}"
        except Exception:
            pass
    return str(e)[:300]
