"""The team map kept refined while the team maps (``fusion.team_map``; docs/sharing.md#the-team-map-while-the-team-maps).

:class:`TeamMapRefresher` runs in a thread of the fusion server. An upload that completes a subset version or stores
keyframes notifies it; once uploads have settled it votes the agents' latest subsets (under the Fuse locks, which
the vote holds for a fraction of a second) and refines the vote over every agent's uploaded views outside them
(:meth:`gausslite.fusion.engine.FuseEngine.refine`: held-out views, early stop, never worse than the vote on them),
then stores the result as a team-map version. The refinement runs in a worker process
(:class:`~gausslite_services.fusion_server.refine_worker.RefineWorker`, at ``fusion.team_map.nice``, one thread),
not in the server's interpreter: the thread only waits for it, so the gRPC handlers never wait for the interpreter
lock behind it. Uploads, downloads and other Fuse calls never wait for the refinement, and a Fuse with a joint
refinement of its own (one runs at a time) does not wait for it either: the team map's refinement stops (its process is
killed) and starts again once that Fuse is done.

Replicas: the refinement holds the store's ``team_map`` lock (:meth:`SqlFusionStore.fuse_lock`), so one replica
refines at a time; before it starts, it checks the newest stored team map, and a replica that finds it made from
the latest subsets and keyframes (by another replica) does nothing. Every replica serves the newest stored version.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from typing import Dict, Optional, Tuple

from gausslite.config import TeamMapSettings
from gausslite_rpc import fusion_pb2
from gausslite_services.fusion_server.guards import Cancelled
from gausslite_services.fusion_server.refine_worker import RefineWorker

log = logging.getLogger("gausslite_services.fusion_server.server")  # one logger for the whole service

__all__ = ["TeamMapRefresher", "GaveWay", "lower_thread_priority", "TEAM_MAP_RETENTION"]

#: the store's retention class of team maps (its ``method`` column; not a FuseMethod, which stays VOTE in their
#: FuseResult): kept apart from the Fuse results, so frequent Fuse calls never evict the team map being served
TEAM_MAP_RETENTION = 100


def lower_thread_priority(nice: int) -> bool:
    """Give the calling thread the scheduling niceness ``nice`` (Linux: niceness is per thread; threads it starts
    inherit it). Returns whether it was set (False elsewhere, or when the system refuses)."""
    if nice <= 0 or not hasattr(os, "setpriority"):
        return False
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), int(nice))
        return True
    except OSError as e:
        log.warning("team map: niceness %d not set: %s", nice, e)
        return False


class GaveWay(Exception):
    """The team map's refinement stopped for a Fuse with refinement (``FusionServicer._refining``)."""


class TeamMapRefresher:
    """Keeps the fusion server's team map refined in the background.

    Args:
        servicer: the :class:`~gausslite_services.fusion_server.servicer.FusionServicer` whose store, engine, locks and
            decoding it uses.
        settings: ``fusion.team_map``.

    Attributes:
        runs: refinements stored by this server. skipped: refreshes that found the stored team map current.
        gave_way: refinements stopped for a Fuse with refinement (each made again after it).
        last_error: the last refresh's error ("" when it succeeded).
        worker: the :class:`~gausslite_services.fusion_server.refine_worker.RefineWorker` that refines (its process
            starts with the first refinement).
    """

    def __init__(self, servicer, settings: TeamMapSettings) -> None:
        self.servicer, self.settings = servicer, settings
        self._changed = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="gausslite-team-map", daemon=True)
        self._last_start = -float("inf")
        self.runs = 0
        self.skipped = 0
        self.gave_way = 0
        self.last_error = ""
        self.busy = threading.Event()
        self.worker = RefineWorker(settings.nice, torch_threads=1)

    # ------------------------------------------------------------------ control
    def start(self) -> None:
        """Start the thread; it looks at the store at once (a restarted server refines what it holds)."""
        self._changed.set()
        self._thread.start()

    def notify(self) -> None:
        """A subset version completed or keyframes were stored: refresh once uploads settle. Never blocks."""
        self._changed.set()

    def stop(self, wait_s: float = 10.0) -> None:
        """Stop the thread and wait up to ``wait_s`` seconds for it; a running refinement ends at once (its process is
        killed)."""
        self._stop.set()
        self._changed.set()
        self.worker.kill(min(2.0, wait_s))
        if self._thread.is_alive():
            self._thread.join(wait_s)
        self.worker.kill(min(2.0, wait_s))  # one started meanwhile

    def _stopped(self) -> bool:
        return self._stop.is_set() or self.servicer._shutdown.is_set()

    # ------------------------------------------------------------------ the store's view
    def inputs(self) -> Tuple[Dict[str, int], int]:
        """(agent id → latest complete subset version, keyframes held): what a team map is made from."""
        store = self.servicer.store
        return store.latest_complete(), store.keyframe_count()

    def latest(self) -> Optional[fusion_pb2.FuseResult]:
        """The newest stored team map's result (any replica's), or None."""
        found = self.servicer.store.fused_info(0, TEAM_MAP_RETENTION)
        return None if found is None else fusion_pb2.FuseResult.FromString(found[1])

    @staticmethod
    def is_current(result: fusion_pb2.FuseResult, latest: Dict[str, int], keyframes: int) -> bool:
        """Whether ``result`` was made from exactly the subset versions ``latest`` and ``keyframes`` keyframes."""
        return ({a.agent_id: int(a.map_version) for a in result.agents} == dict(latest)
                and int(result.keyframes_seen) == int(keyframes))

    # ------------------------------------------------------------------ the thread
    def _loop(self) -> None:
        lower_thread_priority(self.settings.nice)
        while not self._stopped():
            if not self._changed.wait(0.5):
                continue
            while True:  # settle: no notification for settle_s
                self._changed.clear()
                if self._stop.wait(self.settings.settle_s):
                    return
                if not self._changed.is_set():
                    break
            wait = self._last_start + self.settings.min_interval_s - time.monotonic()
            if wait > 0:
                if self._stop.wait(wait):
                    return
                self._changed.clear()
            try:
                self.refresh()
                self.last_error = ""
            except Cancelled:
                return
            except GaveWay:  # a Fuse with refinement goes first; this map is made again once it is done
                log.info("team map: refinement stopped for a Fuse with refinement; it starts again after it")
                self._changed.set()
            except Exception as e:  # noqa: BLE001 - the thread must outlive one failed refinement
                self.last_error = f"{type(e).__name__}: {e}"
                log.exception("team map: refinement failed")

    def refresh(self) -> Optional[fusion_pb2.FuseResult]:
        """Make and store a team map from the latest subsets and keyframes unless the newest stored one is current.
        Returns its result, or None when nothing was made (current already, no subset or no keyframe yet).

        Raises:
            Cancelled: the server or the refresher is stopping. GaveWay: a Fuse with refinement came; the
            refinement stopped for it. ValueError: the vote cannot hold the maps.
        """
        latest, kfs = self.inputs()
        if not latest or not kfs:
            return None
        try:
            lock = self.servicer.store.fuse_lock(self._stopped, name="team_map")
            lock.__enter__()
        except InterruptedError:
            raise Cancelled() from None
        try:
            latest, kfs = self.inputs()
            cur = self.latest()
            if cur is not None and self.is_current(cur, latest, kfs):
                self.skipped += 1
                return None
            self.busy.set()
            try:
                result = self._make(latest, kfs)
            finally:
                self.busy.clear()
        finally:
            lock.__exit__(None, None, None)
        self.runs += 1
        return result

    def _make(self, latest: Dict[str, int], kfs: int) -> fusion_pb2.FuseResult:
        """Vote ``latest`` under the Fuse locks, refine outside them in the worker process, store (a team-map
        version)."""
        s, sv = self.settings, self.servicer
        self._last_start = t0 = time.monotonic()
        voxel = float(s.voxel_size or sv.config.default_voxel_size)
        radius = int(s.contest_radius if s.contest_radius is not None else sv.config.default_contest_radius)

        def emit(stage: str, fraction: float, message: str) -> None:
            if self._stopped():
                raise Cancelled()

        with sv.fuse_locks(self._stopped):
            maps = {a: sv.subset(a, v) for a, v in latest.items()}
            out = sv._engine.fuse(latest, maps, "vote", voxel_size=voxel, contest_radius=radius, progress=emit)
        stored = sv.store.keyframes()  # ordered by agent: the held-out views are spread over the agents
        with sv._refining(self._stopped, background=True):
            try:
                done = self.worker.refine(out.fused, stored, s.refine_iters, s.seed, sv._engine.refine_options,
                                          {"performance": {"render_threads": 1, "torch_threads": 1}},
                                          lambda: self._stopped() or sv.caller_refining())
            except InterruptedError:
                if self._stopped():
                    raise Cancelled() from None
                self.gave_way += 1
                raise GaveWay() from None
        out.fused, out.refine_report, out.keyframes_used = done.fused, done.report, done.keyframes_used
        out.first_row = None  # a refinement splits, clones and prunes rows
        out.seconds = time.monotonic() - t0
        if self._stopped():
            raise Cancelled()
        result = sv.store_fused(out, latest, maps, fusion_pb2.FUSE_METHOD_VOTE, s.refine_iters, voxel, radius,
                                team_map=True, keyframes_seen=kfs)
        log.info("team map v%d from %s, %d views (%d decoded for it): %s (%.1f s)", result.fused_version,
                 ", ".join(f"{a} v{v}" for a, v in sorted(latest.items())), out.keyframes_used, done.decoded,
                 out.refine_report.summary() if out.refine_report is not None else "not refined", out.seconds)
        return result
