"""What an agent shares, and the state behind its pushes (paper Sec. III-E; ``docs/sharing.md``).

:class:`ShareSession` owns, for one mission: the share rule (``agent.share.rule``), the share worker process that runs
the task selection and the fine-tune at low priority, the fine-tune cache, the delta push planner and the copy of
the subset the fusion server acknowledged last. The mission loop (:class:`gausslite.mission.runtime.AgentRuntime`)
calls :meth:`ShareSession.capture` from its mapping thread, and the other methods from its pusher thread.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import multiprocessing
import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Optional

import numpy as np

from gausslite.core.arrays import GaussianArrays
from gausslite.mapping.config import MapperConfig
from gausslite.mission.config import AgentConfig, ShareConfig
from gausslite.mission.heap import trim_heap
from gausslite.wire.delta import PushPlanner

log = logging.getLogger(__name__)

__all__ = ["select_shared", "ShareSession", "Captured"]


def select_shared(gmap, rule: str = "active", kappa_threshold: int = 1) -> np.ndarray:
    """Boolean mask (N,) of the Gaussians an agent shares (paper Sec. III-E).

    Args:
        gmap: ``GaussianMap`` (or anything with ``active`` and ``kappa`` arrays/tensors).
        rule: ``active`` (a = 1) or ``kappa`` (κ >= ``kappa_threshold``); ``task`` without views is a = 1 and κ
            (:class:`ShareSession` adds the task region and the compaction); ``agent.share.rule``.
    Raises:
        ValueError: unknown ``rule``.
    """
    active = np.asarray(gmap.active.cpu().numpy() if hasattr(gmap.active, "cpu") else gmap.active, dtype=bool)
    kappa = np.asarray(gmap.kappa.cpu().numpy() if hasattr(gmap.kappa, "cpu") else gmap.kappa)
    if rule == "active":
        return active
    if rule == "kappa":
        return kappa >= int(kappa_threshold)
    if rule == "task":
        return active & (kappa >= int(kappa_threshold))
    raise ValueError(f"unknown share rule {rule!r} (use 'active', 'kappa' or 'task')")


def _worker_init(nice: int) -> None:
    """Initialiser of the share worker process: lower its priority, one torch thread."""
    # lazy: keeps gausslite.mission.share importable without torch
    import torch

    if nice and hasattr(os, "nice"):
        try:
            os.nice(nice)
        except OSError:
            pass
    torch.set_num_threads(1)


def _warm() -> int:
    """The share worker's first job, sent at mission start (:meth:`ShareSession.start`): import what selection and
    fine-tuning run (torch, the rasterizer's kernels, :mod:`gausslite.sharing`), so the first push does not wait for a
    process start. Returns the worker's pid."""
    import os

    import gausslite.render  # noqa: F401 - loads the rasterizer's compiled kernels
    import gausslite.sharing  # noqa: F401

    return os.getpid()


def _trimmed(fn, *args):
    """``fn(*args)`` in the share worker, then its freed memory back to the OS (:func:`~gausslite.mission.heap.trim_heap`):
    each job unpickles a map copy and the ROI keyframes, and without this the worker's resident memory creeps up
    over a long mission."""
    try:
        return fn(*args)
    finally:
        trim_heap(collect=True)


def _select(gmap, views, share_cfg: ShareConfig, backend: str, held=None):
    """``rule: task`` selection (:func:`gausslite.sharing.select_task_subset` with ``share_cfg``, the mission's
    ``agent.share``, and the rows the server holds); runs in the share worker."""
    # lazy: keeps gausslite.mission.share importable without torch
    from gausslite.sharing import select_task_subset

    return select_task_subset(gmap, views, share_cfg, backend=backend, held=held)


def _finetune(arrays, ids, base, base_ids, kfs, iters: int, refresh: float, cfg: MapperConfig, seed: int):
    """The shared subset fine-tuned alone on the compact ROI keyframes ``kfs``
    (:func:`gausslite.sharing.update_shared_subset`, which decodes each keyframe when it draws it); runs in the
    share worker."""
    # lazy: keeps gausslite.mission.share importable without torch
    from gausslite.sharing import update_shared_subset

    return update_shared_subset(arrays, ids, base, base_ids, kfs, iters, refresh, cfg, seed=seed)


@dataclasses.dataclass
class Captured:
    """What the mapping thread captured for one push.

    Attributes:
        gaussians: the subset to push (``GaussianArrays``), or None until :meth:`ShareSession.select` ran.
        ids: (N,) int64 stable ids of its rows (of every map row until selected).
        n_total: Gaussians in the map.
        select: ``share.rule: task``: (map copy, ROI views, keyframe poses, ROI keyframes or None).
        finetune: (cache key, compact ROI keyframes) once selected, when the subset is fine-tuned before the push.
    """

    gaussians: object
    ids: np.ndarray
    n_total: int
    select: object = None
    finetune: object = None


class ShareSession:
    """The share side of one mission (module docstring).

    Args:
        agent_id: the agent's id (logs, the push planner's chunk headers).
        config: the mission's ``AgentConfig`` (``share``; of ``push``: ``nice``, ``delta``, ``delta_tolerance``,
            ``chunk_gaussians``).
    """

    def __init__(self, agent_id: str, config: AgentConfig) -> None:
        self.agent_id, self.config = agent_id, config
        self.planner = None  # gausslite.wire.delta.PushPlanner, created at the first push
        self.pool = None  # the share worker process (share.worker: process), started by start() or on first use
        self.warm = None  # Future of the worker's warm-up job (its pid), sent when the worker starts
        self.finetune_cache = None  # (hash of the subset and keyframes, fine-tuned subset, ids) of the last push
        self._acked = None  # (version, subset, ids) the server acknowledged last (the planner's base)
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ mapping thread
    def capture(self, mapper) -> Captured:
        """What the next push needs, taken from the mapper (mapping thread). With ``share: task`` that is a copy of
        the map, the ROI keyframes and their poses: the selection (which renders every ROI keyframe) and the
        fine-tune then run in the share worker (:meth:`select`, :meth:`finetuned`), so a push takes no time from
        the keyframe budget."""
        gmap, share = mapper.gmap, self.config.share
        if share.rule != "task":
            mask = select_shared(gmap, share.rule, share.kappa_threshold)
            return Captured(GaussianArrays.from_any(gmap).take(mask), mapper.model.ids.numpy()[mask], len(gmap))
        store = mapper.keyframes
        # the ROI keyframes with poses of their own (mapping refines the store's in place), compact
        views = [dataclasses.replace(kf, c2w=kf.c2w.clone()) for kf in store if kf.roi is not None]
        poses = [(int(kf.frame_id), kf.c2w.cpu().numpy().copy()) for kf in store]
        # only the keyframes that see the ROI take part in the fine-tune: the same copies (neither step changes them)
        kfs = [kf for kf in views if kf.sees_roi] if share.finetune_iters > 0 else None
        return Captured(None, mapper.model.ids.numpy().copy(), len(gmap), (gmap.clone(), views, poses, kfs))

    # ------------------------------------------------------------------ pusher thread
    def select(self, cap: Captured, backend: str = "auto") -> Captured:
        """``share.rule: task``: ``cap`` with its task subset selected
        (:func:`gausslite.sharing.select_task_subset` with ``agent.share``) and, with fine-tuning, its fine-tune
        inputs."""
        gmap, views, poses, kfs = cap.select
        share = self.config.share
        acked = self.acknowledged()
        held = np.isin(cap.ids, acked[2]) if acked is not None and share.held_weight != 1.0 else None
        mask, st = self.call(_select, gmap, views, share, backend, held)
        log.info("agent %s share: %s of %d (%d ROI keyframes)", self.agent_id, st, len(gmap), len(views))
        arrays = GaussianArrays.from_any(gmap).take(mask)
        ids = cap.ids[mask]
        finetune = self.finetune_inputs(arrays, ids, poses, kfs) if kfs is not None and len(arrays) else None
        return dataclasses.replace(cap, gaussians=arrays, ids=ids, finetune=finetune, select=None)

    @staticmethod
    def finetune_inputs(arrays, ids, poses, kfs) -> tuple:
        """What the fine-tune of a subset needs: the cache key of (subset, ids, keyframe ids and poses) and the
        compact stored keyframes that see the ROI, with poses of their own (``poses``: (frame id, c2w) of every
        stored keyframe, ``kfs`` the ROI keyframes, as captured by the mapping thread). Nothing is decoded here:
        :meth:`finetuned` decodes them on a cache miss."""
        h = hashlib.blake2b(digest_size=16)
        for name in GaussianArrays.FIELDS:
            h.update(np.ascontiguousarray(getattr(arrays, name)).tobytes())
        for fid, c2w in poses:
            h.update(np.asarray([fid], np.int64).tobytes() + np.ascontiguousarray(c2w).tobytes())
        h.update(ids.tobytes())
        return h.digest(), kfs

    def finetuned(self, arrays, ids, key, kfs, mapper_cfg: MapperConfig):
        """The shared subset fine-tuned alone on the ROI keyframes ``kfs`` (compact), against the copy the server
        acknowledged (:func:`gausslite.sharing.update_shared_subset`, ``share.refresh``; seeded by
        ``mapper_cfg.seed``). Without delta pushes every push is fine-tuned from the agent's values alone. The same
        subset and keyframes as at the last push (``key``, :meth:`finetune_inputs`) give the last result again
        without work (whatever the server acknowledged since), so an unchanged map (e.g. the final push right after
        a periodic one) stays unchanged on the wire and its delta is empty."""
        if self.finetune_cache is not None and self.finetune_cache[0] == key:
            return self.finetune_cache[1]
        with self._lock:
            acked = self._acked if self._acked is not None and self.config.push.delta else (None, None, None)
        base_version, base, base_ids = acked
        t0 = time.perf_counter()
        # one rasterizer thread: in the pusher thread (share.worker: thread) the rasterizer's band pool is shared with
        # the mapper and runs at its priority, so a multi-threaded fine-tune would queue ahead of mapping work; the
        # worker process, at low priority, takes at most the one core mapping leaves idle
        share = self.config.share
        fcfg = mapper_cfg.model_copy(
            update={"performance": mapper_cfg.performance.model_copy(update={"render_threads": 1}),
                    "roi_outside_alpha": share.outside_alpha})
        out, st = self.call(_finetune, arrays, ids, base, base_ids, kfs, share.finetune_iters, share.refresh, fcfg,
                            mapper_cfg.seed)
        log.info("agent %s: shared subset of %d fine-tuned alone on %d ROI keyframes, %d iterations, against "
                 "server v%s (%s), %.2f s", self.agent_id, len(arrays), len(kfs),
                 share.finetune_iters, base_version, st, time.perf_counter() - t0)
        self.finetune_cache = (key, out, ids)
        return out

    def start(self, nice: Optional[int] = None) -> None:
        """Start the share worker process now and warm it up (imports, rasterizer kernels) without waiting: a mission
        that shares calls this when it starts, so its first push finds the worker ready. Starting a process and
        importing torch and the rasterizer takes seconds to tens of seconds on a loaded robot computer; started at
        the first push instead, the worker would still be starting while the next subsets are mapped, and those
        would be superseded before any reached the fusion server. No-op under ``share.worker: thread``, for a share
        rule other than ``task``, or when the worker runs already.

        Args:
            nice: the worker's niceness above the agent's (default ``push.nice``; 0: the mapper's priority).
        """
        share = self.config.share
        if share.worker != "process" or share.rule != "task" or self.pool is not None:
            return  # only ``rule: task`` selects and fine-tunes in the worker
        self._pool(nice)

    def _pool(self, nice: Optional[int] = None):
        """The share worker's pool, started (and sent :func:`_warm`, which also tells its pid) when there is none."""
        if self.pool is None:
            self.pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                            initializer=_worker_init,
                                            initargs=(self.config.push.nice if nice is None else int(nice),))
            self.warm = self.pool.submit(_warm)
        return self.pool

    def call(self, fn, *args):
        """Run ``fn(*args)`` in the share worker process (``share.worker: process``, started by :meth:`start` or on
        first use, with the ``spawn`` method: forking a process that runs rasterizer threads is unsafe), or here
        (``thread``)."""
        if self.config.share.worker != "process":
            return fn(*args)
        return self._pool().submit(_trimmed, fn, *args).result()

    # ------------------------------------------------------------------ delta planning
    @property
    def holds_base(self) -> bool:
        """Whether a subset was acknowledged in this mission (the planner's base)."""
        return self.planner is not None and self.planner.base is not None

    def plan(self, ids, gaussians, version: int):
        """The push of ``gaussians`` (rows ``ids``) as ``version``: a delta against the acknowledged base when there
        is one (:class:`gausslite.wire.delta.PushPlanner`)."""
        if self.planner is None:
            push = self.config.push
            self.planner = PushPlanner(self.agent_id, chunk_gaussians=push.chunk_gaussians,
                                       tolerance=push.delta_tolerance, delta=push.delta)
        return self.planner.plan(ids, gaussians, version)

    def acknowledge(self, plan) -> None:
        """The server holds ``plan``'s subset: it is the next delta's base and the next fine-tune's start."""
        self.planner.acknowledge(plan)
        with self._lock:
            self._acked = (plan.version, plan.subset, plan.ids)
        if self.planner.last_stats:
            log.info("agent %s delta plan v%d: %s (sent %s)", self.agent_id, plan.version, self.planner.last_stats,
                     "delta" if plan.is_delta else "full")

    def forget(self) -> None:
        """The server lost the base (a rejected delta): the next push is full."""
        if self.planner is not None:
            self.planner.forget()
        with self._lock:
            self._acked = None

    def acknowledged(self) -> Optional[tuple]:
        """(version, subset ``GaussianArrays``, ids) the server acknowledged last, or None."""
        with self._lock:
            return self._acked

    def close(self) -> None:
        """Stop the share worker process: its pending jobs are cancelled and the process is terminated, not waited
        for. It holds nothing to save (a job's result comes back through the pool), and its interpreter's teardown,
        at the worker's lowered priority, held the agent's own exit: the interpreter joins the pool's processes at
        exit, and a worker with torch loaded took 2 s to end at nice 0 and 12 s at nice 10 on a loaded 2-core
        machine."""
        if self.pool is None:
            return
        pid = None
        if self.warm is not None and self.warm.done() and not self.warm.cancelled() and self.warm.exception() is None:
            pid = self.warm.result()
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.pool = None
        if pid is not None:
            try:
                os.kill(pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
