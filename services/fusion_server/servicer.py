"""The ``gausslite.v1.Fusion`` servicer: sessions, resumable subset and keyframe uploads, fuse jobs
(:class:`gausslite.fusion.engine.FuseEngine`), downloads and statistics over the store (module docstring of
:mod:`gausslite_services.fusion_server.server`).

:class:`FusionServicer` holds what the calls share (the store, the wire limits, the decoded subsets, the fuse and
refinement locks, the team map), answers ``OpenSession`` and runs the fuse jobs; the other calls are answered by
handler modules it delegates to: the uploads by :mod:`~gausslite_services.fusion_server.upload_handlers`, the checks
of a ``Fuse`` request and the team map's answer by :mod:`~gausslite_services.fusion_server.fuse_handlers`, the reads
(fused maps, statistics, keyframe poses) by :mod:`~gausslite_services.fusion_server.read_handlers`.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from typing import Dict, Iterator, Optional

import grpc
import numpy as np

from gausslite.config import FusionSettings
from gausslite.core import extras
from gausslite.core.arrays import GaussianArrays
from gausslite.errors import ExtraUnavailable
from gausslite.fusion.engine import FuseEngine
from gausslite.fusion.guard import RoiView
from gausslite.wire.decode import assemble
from gausslite.wire.encode import encode_subset
from gausslite.wire.format import LOSSLESS, WireLimits
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.auth import Authenticator, AuthError
from gausslite_services.common.server import peer_host
from gausslite_services.fusion_server.fuse_handlers import METHOD_NAMES, check_fuse_request, served_team_map
from gausslite_services.fusion_server.guards import (Cancelled, intrinsics_from_proto, Reject, stream_guard,
                                                     unary_guard, check_agent_id, check_int64, decode_roi,
                                                     UploadStreams)
from gausslite_services.fusion_server.read_handlers import MAX_STATS_PAGE_SIZE, STATS_PAGE_SIZE  # noqa: F401 - re-exported
from gausslite_services.fusion_server.read_handlers import download_fused, keyframe_poses, stats
from gausslite_services.fusion_server.refine_worker import decode_keyframe, keyframe_key
from gausslite_services.fusion_server.store import Session, SqlFusionStore
from gausslite_services.fusion_server.team_map import TEAM_MAP_RETENTION, TeamMapRefresher
from gausslite_services.fusion_server.upload_handlers import upload_ack, upload_keyframes, upload_subset

log = logging.getLogger("gausslite_services.fusion_server.server")  # one logger for the whole service

SERVICE_NAME = "gausslite.v1.Fusion"
FUSED_AGENT_ID = "fused"
#: bytes an ``UploadSubsetRequest`` adds around its chunk (field tag and length, 6 at most, with margin): a chunk fits
#: in one message when it is at most ``max_message_bytes - CHUNK_ENVELOPE_BYTES`` (``SessionInfo.max_chunk_bytes``)
CHUNK_ENVELOPE_BYTES = 16
#: largest row count of one chunk the server accepts (the wire format's own bound, ``docs/wire-format.md`` §8)
MAX_CHUNK_GAUSSIANS = 1 << 20
#: smallest message bound the server runs with: a fused chunk (64 KiB at least) and its ``FuseResult`` must fit
MIN_MESSAGE_BYTES = 128 * 1024


class FusionServicer(fusion_pb2_grpc.FusionServicer):
    """Implements ``gausslite.v1.Fusion`` on top of a :class:`SqlFusionStore`.

    Args:
        store (SqlFusionStore): persistent state (SQLite or PostgreSQL).
        config (FusionSettings): limits and defaults (the ``fusion`` section, :mod:`gausslite.config`).
        max_message_bytes (int): the server's gRPC message bound in bytes (>= :data:`MIN_MESSAGE_BYTES`); a chunk may
            take it minus :data:`CHUNK_ENVELOPE_BYTES`.
        auth (Authenticator | None): identifies callers for the write checks (None: every caller may
            write every agent's data, as on a server without credentials).
        handler_threads (int | None): the gRPC server's handler threads; upload streams are capped at half of them
            (and at ``config.max_upload_streams``) so stalled uploads leave threads for everything else.
    Raises:
        ValueError: ``max_message_bytes`` below :data:`MIN_MESSAGE_BYTES`.
    """

    def __init__(self, store: SqlFusionStore, config: FusionSettings, max_message_bytes: int,
                 auth: Optional[Authenticator] = None, handler_threads: Optional[int] = None):
        self.auth = auth
        cap = int(config.max_upload_streams)
        if handler_threads is not None:
            cap = min(cap, max(1, int(handler_threads) // 2))
        self.uploads = UploadStreams(cap, min(cap, int(config.max_upload_streams_per_caller)),
                                     float(config.stream_idle_s), float(config.stream_evict_idle_s))
        self.store = store
        self.config = config
        self.max_message_bytes = int(max_message_bytes)
        if self.max_message_bytes < MIN_MESSAGE_BYTES:
            raise ValueError(f"the fusion server's max_message_bytes must be >= {MIN_MESSAGE_BYTES}, "
                             f"got {self.max_message_bytes}")
        # the limits a client sees in SessionInfo (docs/robot-integration.md, "Limits")
        self.limits = WireLimits(max_chunk_bytes=self.max_message_bytes - CHUNK_ENVELOPE_BYTES,
                                 max_total_gaussians=int(config.max_subset_gaussians),
                                 max_chunk_gaussians=min(MAX_CHUNK_GAUSSIANS, int(config.max_subset_gaussians)),
                                 max_agent_id_bytes=64)
        # fused chunks leave 64 KiB for the FusedChunk envelope and the FuseResult of the first message, so every
        # DownloadFused message fits the server's bound and gRPC's default 4 MiB receive limit of a client
        self.fused_chunk_bytes = min(4 << 20, self.max_message_bytes) - 64 * 1024
        self._cache: Dict[tuple, GaussianArrays] = {}
        self._cache_lock = threading.Lock()
        # decoded keyframes of Fuse's refinement, by refine_worker.keyframe_key: a refinement decodes only the
        # keyframes stored since the last one (the team map's worker process keeps its own)
        self._decoded: Dict[tuple, object] = {}
        self._fuse_lock = threading.Lock()
        self._refine_lock = threading.Lock()  # one joint refinement at a time in this server (Fuse's or the team map's)
        self._refine_callers = 0  # Fuse calls waiting for or holding the refinement lock (the team map gives way)
        self._refine_callers_lock = threading.Lock()
        # keeps the voted map current (under the fuse locks); refine_options take precedence over the held-out check's
        self._engine = FuseEngine({**config.refine_validation.options(), **config.refine_options})
        # what this install can fuse: refinement and the ROI guard need the 'mapper' extra (torch, the rasterizer)
        self._unavailable = {f: extras.unavailable(f) for f in ("refine", "roi_guard")}
        self._shutdown = threading.Event()
        self._workers: "set[threading.Thread]" = set()
        self.team_map: Optional[TeamMapRefresher] = None
        if config.team_map.enabled:
            if self._unavailable["refine"]:
                log.warning("this install cannot refine (%s): no team map is kept (Fuse with team_map is "
                            "FAILED_PRECONDITION); install the 'mapper' extra, or set fusion.team_map.enabled: false "
                            "to silence this", self._unavailable["refine"])
            else:
                self.team_map = TeamMapRefresher(self, config.team_map)
                self.team_map.start()

    def shutdown(self, wait_s: float = 10.0) -> None:
        """Stop running Fuse work (after the gRPC grace period) and wait up to ``wait_s`` for it.

        A refinement notices the request at its next progress report (about every 1/20 of its
        iterations).
        """
        self._shutdown.set()
        deadline = time.monotonic() + wait_s
        if self.team_map is not None:
            self.team_map.stop(wait_s)
        for t in list(self._workers):
            t.join(max(0.0, deadline - time.monotonic()))

    def fuse_modes(self) -> Dict[str, Optional[str]]:
        """The fuse modes and whether this install runs them: mode → None when it does, else why not (the extra it
        needs, ``gausslite.core.extras``). Modes: ``vote`` and ``concat`` (always), ``for_agent`` (a robot's team
        map; over ROI keyframes its ROI guard renders them), ``refine`` (the joint refinement)."""
        return {"vote": None, "concat": None, "for_agent": self._unavailable["roi_guard"],
                "refine": self._unavailable["refine"]}

    def describe_fuse_modes(self) -> str:
        """One line for the startup log: the modes available, and each unavailable one with the reason."""
        modes = self.fuse_modes()
        line = "fuse modes available: " + ", ".join(m for m, why in modes.items() if why is None)
        off = [f"{m} ({why})" for m, why in modes.items() if why is not None]
        return line + ("; unavailable: " + "; ".join(off) if off else "")

    # ------------------------------------------------------------------ shared by the handlers
    def check_writer(self, context, agent_id: str) -> None:
        """Raise Reject(PERMISSION_DENIED) unless the caller may write ``agent_id``'s data
        (UNAUTHENTICATED when its credential was revoked since the call began)."""
        if self.auth is None or not self.auth.enabled:
            return
        try:
            self.auth.identify_context(context).check_write(agent_id)
        except AuthError as e:
            raise Reject(e.code, e.message) from None

    def _caller(self, context) -> Optional[str]:
        """Who holds an upload stream, for the per-caller bound: the authenticated agent id; the peer host for a
        team member that may write nothing (a viewer opening uploads that can only be refused); None (no per-caller
        bound) for a caller that may write every agent's data (an open server, the team-wide fleet token)."""
        if self.auth is None or not self.auth.enabled:
            return None
        try:
            principal = self.auth.identify_context(context)
        except AuthError:  # revoked since the call began: its writes will be refused
            return f"peer {peer_host(context.peer())}"
        if principal.agent_id:
            return f"agent {principal.agent_id}"
        return None if principal.may_write_any else f"peer {peer_host(context.peer())}"

    def session_of(self, agent_id: str) -> Session:
        """The open session of ``agent_id``. Raises Reject: INVALID_ARGUMENT for a bad id, NOT_FOUND without one."""
        check_agent_id(agent_id)
        s = self.store.session(agent_id)
        if s is None:
            raise Reject(grpc.StatusCode.NOT_FOUND, f"agent {agent_id!r} has no open session; call OpenSession first")
        return s

    def subset(self, agent_id: str, version: int) -> GaussianArrays:
        """The complete subset ``version`` of ``agent_id`` decoded (kept decoded, :meth:`cache_put`).

        Raises:
            gausslite.wire.format.WireError: stored chunks that do not assemble (within the server's limits).
        """
        key = (agent_id, version)
        with self._cache_lock:
            hit = self._cache.get(key)
        if hit is not None:
            return hit
        arrays, _ = assemble(self.store.chunk_data(agent_id, version), self.limits)
        self.cache_put(agent_id, version, arrays)
        return arrays

    def cache_put(self, agent_id: str, version: int, arrays: GaussianArrays) -> None:
        """Keep ``arrays`` as the decoded subset of ``agent_id``, one version per agent (the newest a delta is
        built on): a long mission pushes a new version every few keyframes."""
        with self._cache_lock:
            for k in [k for k in self._cache if k[0] == agent_id and k[1] != version]:
                del self._cache[k]
            self._cache[(agent_id, version)] = arrays

    # ------------------------------------------------------------------ RPCs
    @unary_guard
    def OpenSession(self, request, context):  # noqa: N802
        agent = check_agent_id(request.agent_id)
        self.check_writer(context, agent)
        if len(request.task_text.encode("utf-8")) > self.config.max_task_text_bytes:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                         f"task_text longer than {self.config.max_task_text_bytes} UTF-8 bytes")
        if "\x00" in request.task_text:  # PostgreSQL text cannot hold NUL; refused by every store alike
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "task_text contains a NUL character")
        if not request.HasField("intrinsics"):
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "intrinsics are required")
        k = intrinsics_from_proto(request.intrinsics, "intrinsics")
        created = self.store.open_session(Session(agent, request.task_text, k.fx, k.fy, k.cx, k.cy,
                                                  int(k.width), int(k.height)))
        latest = self.store.latest_version(agent)
        log.info("session %s %s", agent, "opened" if created else "re-opened")
        return fusion_pb2.SessionInfo(agent_id=agent, created=created, latest_map_version=latest or 0,
                                      has_complete_subset=latest is not None,
                                      keyframes=self.store.keyframe_count(agent),
                                      max_keyframes=self.config.max_keyframes_per_agent,
                                      max_message_bytes=self.max_message_bytes,
                                      max_chunk_bytes=self.limits.max_chunk_bytes,
                                      max_chunk_gaussians=self.limits.max_chunk_gaussians,
                                      max_subset_gaussians=self.limits.max_total_gaussians,
                                      max_chunks=self.limits.max_chunks)

    @unary_guard
    def UploadSubset(self, request_iterator, context):  # noqa: N802
        with self.uploads.open(request_iterator, context, "UploadSubset", self._caller(context)) as messages:
            return upload_subset(self, messages, context)

    @unary_guard
    def GetUploadStatus(self, request, context):  # noqa: N802
        self.session_of(request.agent_id)
        return upload_ack(self, request.agent_id, check_int64(request.map_version, "map_version"))

    @unary_guard
    def UploadKeyframes(self, request_iterator, context):  # noqa: N802
        with self.uploads.open(request_iterator, context, "UploadKeyframes", self._caller(context)) as messages:
            return upload_keyframes(self, messages, context)

    @stream_guard
    def Fuse(self, request, context):  # noqa: N802
        if request.team_map:
            yield served_team_map(self)
            return
        job = check_fuse_request(self, request)
        events: "queue.Queue[tuple]" = queue.Queue()
        cancel = threading.Event()
        context.add_callback(cancel.set)
        worker = threading.Thread(target=self._fuse_work, name="gausslite-fuse", daemon=True,
                                  args=(job.latest, job.method, job.voxel, job.refine, job.iters, job.seed,
                                        events, cancel, job.radius, job.for_agent))
        self._workers.add(worker)
        worker.start()
        try:
            while True:
                try:
                    kind, payload = events.get(timeout=0.2)
                except queue.Empty:
                    if not context.is_active():
                        cancel.set()
                        log.info("Fuse cancelled by the client (or its deadline)")
                        return
                    continue
                if kind == "progress":
                    yield payload
                elif kind == "done":
                    yield payload
                    return
                elif kind == "cancelled":
                    return
                else:  # error
                    if isinstance(payload, ExtraUnavailable):
                        raise Reject(grpc.StatusCode.FAILED_PRECONDITION, str(payload))
                    if isinstance(payload, ValueError):
                        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"fusion failed: {payload}")
                    raise payload
        finally:
            cancel.set()  # no-op when the work finished; stops it when the stream was closed early

    def _fuse_work(self, latest: Dict[str, int], method: int, voxel: float, refine: bool, iters: int,
                   seed: int, events: "queue.Queue[tuple]", cancel: threading.Event, radius: int = 0,
                   for_agent: Optional[str] = None) -> None:
        """Fuse worker (own thread): pushes ("progress"|"done"|"cancelled"|"error", payload) events."""
        stage = {"name": "load"}

        def emit(name: str, fraction: float, message: str) -> None:
            if cancel.is_set() or self._shutdown.is_set():
                raise Cancelled()
            stage["name"] = name
            events.put(("progress", fusion_pb2.FuseProgress(stage=name, fraction=float(fraction), message=message)))

        def stopped() -> bool:
            return cancel.is_set() or self._shutdown.is_set()

        try:
            with self.fuse_locks(stopped):
                emit("load", 0.0, f"loading the subsets of {len(latest)} agent(s)")
                maps = {a: self.subset(a, v) for a, v in latest.items()}
                with self._refining(stopped) if refine else contextlib.nullcontext():
                    out = self._engine.fuse(latest, maps, METHOD_NAMES[method], voxel_size=voxel,
                                            contest_radius=radius, refine_iters=iters if refine else 0,
                                            keyframes=self._refine_keyframes, seed=seed, progress=emit,
                                            for_agent=for_agent, roi_views=self._roi_views)
                emit("store", 0.9, f"storing {len(out.fused)} Gaussians")
                if stopped():
                    raise Cancelled()
                result = self.store_fused(out, latest, maps, method, iters if refine else 0, voxel, radius,
                                          for_agent=for_agent or "")
                events.put(("done", fusion_pb2.FuseProgress(stage="done", fraction=1.0, done=True, result=result,
                                                            message=f"fused version {result.fused_version}")))
        except Cancelled:
            log.info("Fuse work stopped during stage %r (cancelled)", stage["name"])
            events.put(("cancelled", None))
        except Reject as r:
            events.put(("error", ValueError(r.message)))
        except ImportError as e:  # an extra this install lacks (FAILED_PRECONDITION), else a broken install
            feature = "refine" if refine else "roi_guard" if for_agent else None
            missing = extras.unavailable_from(e, extras.FEATURES[feature].what if feature else "this Fuse")
            if missing is None:
                log.exception("Fuse work failed")
            events.put(("error", missing or e))
        except Exception as e:  # noqa: BLE001 - reported to the caller as a status
            log.exception("Fuse work failed")
            events.put(("error", e))
        finally:
            self._workers.discard(threading.current_thread())

    @contextlib.contextmanager
    def fuse_locks(self, stopped) -> Iterator[None]:
        """Hold the locks of Fuse work: this server's, then the store's (every replica on the store), waiting until
        they are free. Raises :class:`Cancelled` when ``stopped()`` turns true while waiting."""
        while not self._fuse_lock.acquire(timeout=0.2):
            if stopped():
                raise Cancelled()
        try:
            try:
                cm = self.store.fuse_lock(stopped)  # serialises Fuse across every replica on the store
                cm.__enter__()
            except InterruptedError:
                raise Cancelled() from None
            try:
                yield
            finally:
                cm.__exit__(None, None, None)
        finally:
            self._fuse_lock.release()

    @contextlib.contextmanager
    def _refining(self, stopped, *, background: bool = False) -> Iterator[None]:
        """Hold this server's refinement lock: one joint refinement at a time, a Fuse's or the team map's.

        A Fuse (``background`` false) goes ahead of the team map's refinement (``background`` true): while it waits
        for the lock or holds it, :meth:`caller_refining` is true, which stops a running team-map refinement
        (:meth:`TeamMapRefresher._make`) and keeps the next one from taking the lock. Raises :class:`Cancelled` when
        ``stopped()`` turns true while waiting."""
        if not background:
            with self._refine_callers_lock:
                self._refine_callers += 1
        try:
            while True:
                if stopped():
                    raise Cancelled()
                if background and self.caller_refining():
                    time.sleep(0.2)
                elif self._refine_lock.acquire(timeout=0.2):
                    if not (background and self.caller_refining()):
                        break
                    self._refine_lock.release()
            try:
                yield
            finally:
                self._refine_lock.release()
        finally:
            if not background:
                with self._refine_callers_lock:
                    self._refine_callers -= 1

    def caller_refining(self) -> bool:
        """Whether a Fuse with a joint refinement is waiting for the refinement lock or holds it (the team map's
        background refinement gives way to it: :meth:`_refining`)."""
        return self._refine_callers > 0

    def store_fused(self, out, latest: Dict[str, int], maps: Dict[str, GaussianArrays], method: int, iters: int,
                    voxel: float, radius: int, *, for_agent: str = "", team_map: bool = False,
                    keyframes_seen: int = 0) -> fusion_pb2.FuseResult:
        """Store the fused map of ``out`` (:class:`gausslite.fusion.engine.FuseOutcome`, from the subsets ``maps`` at
        ``latest`` versions) as a new version and return its ``FuseResult``. ``iters`` > 0: it was refined with that
        many iterations at most. Team maps (``team_map``) are kept apart, ``fusion.team_map.keep`` of them."""
        fused = out.fused
        agents = [fusion_pb2.AgentContribution(agent_id=a, map_version=latest[a], received=len(maps[a]),
                                               kept=int(out.kept.get(a, 0)),
                                               first_row=None if out.first_row is None else out.first_row[a])
                  for a in sorted(maps)]
        rep = out.refine_report
        record = None if rep is None else fusion_pb2.RefineRecord(**{
            k: (v if v is not None else 0.0) for k, v in rep.as_dict().items() if k not in ("last_loss", "checks",
                                                                                        "gaussians")})

        def info(version: int, nbytes: int) -> bytes:
            return fusion_pb2.FuseResult(
                fused_version=version, n_gaussians=len(fused), seconds=out.seconds, agents=agents, method=method,
                refined=bool(iters), refine_iters=iters, voxel_size=voxel, keyframes_used=out.keyframes_used,
                bytes=nbytes, created_unix=time.time(), vote_seconds=out.vote_seconds,
                agents_revoted=out.agents_revoted, incremental=out.incremental,
                contest_radius=radius if method == fusion_pb2.FUSE_METHOD_VOTE else 0, for_agent=for_agent,
                refine_record=record, team_map=team_map, keyframes_seen=keyframes_seen).SerializeToString()

        version = self.store.put_fused(
            info, TEAM_MAP_RETENTION if team_map else method,
            keep=self.config.team_map.keep if team_map else self.config.fused_keep_per_method,
            chunks_fn=lambda v: encode_subset(fused, FUSED_AGENT_ID, v, max_chunk_bytes=self.fused_chunk_bytes,
                                              quant=LOSSLESS))
        result = fusion_pb2.FuseResult.FromString(self.store.fused_info(version)[1])
        log.info("fused version %d: %s%s, %d Gaussians, refine=%s, %.2fs", version, METHOD_NAMES[method],
                 " (team map)" if team_map else "", len(fused), bool(iters), result.seconds)
        return result

    def _roi_views(self, agent: str) -> list:
        """``agent``'s stored keyframes that carry an ROI, as :class:`gausslite.fusion.guard.RoiView` (pose,
        intrinsics and the decoded ROI mask only: the colour and depth images stay encoded)."""
        out = []
        for k in self.store.keyframes([agent]):
            if not k.roi:
                continue
            K = np.array([[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]])
            roi = decode_roi(k.roi, (k.height, k.width), f"stored keyframe {k.frame_id}")
            out.append(RoiView(K, int(k.width), int(k.height), np.asarray(k.c2w, np.float64), roi))
        return out

    def _refine_keyframes(self) -> Dict[str, list]:
        """The stored keyframes of every agent, decoded for the refinement: agent id → its
        :class:`gausslite.mapping.views.Keyframe` list (the refinement spreads its held-out keyframes over the
        agents)."""
        kfs: Dict[str, list] = {}
        keep: Dict[tuple, object] = {}
        for k in self.store.keyframes():
            key = keyframe_key(k)
            with self._cache_lock:
                kf = self._decoded.get(key)
            if kf is None:
                kf = decode_keyframe(k)
            keep[key] = kf
            kfs.setdefault(k.agent_id, []).append(kf)
        with self._cache_lock:  # only what the store still holds (evicted keyframes leave the cache)
            self._decoded = keep
        return kfs

    @stream_guard
    def DownloadFused(self, request, context):  # noqa: N802
        yield from download_fused(self, request, context)

    @unary_guard
    def GetStats(self, request, context):  # noqa: N802
        return stats(self, request)

    @unary_guard
    def GetKeyframePoses(self, request, context):  # noqa: N802
        return keyframe_poses(self, request)
