"""The ``gausslite.v1.Fusion`` servicer: sessions, resumable subset and keyframe uploads, fuse jobs
(:class:`gausslite.fusion.engine.FuseEngine`), downloads and statistics over the store (module docstring of
:mod:`gausslite_services.fusion_server.server`)."""

from __future__ import annotations

import contextlib
import logging
import math
import queue
import threading
import time
from typing import Dict, Iterator, Optional

import grpc
import numpy as np

from gausslite.camera import Intrinsics, check_rigid
from gausslite.config import FusionSettings
from gausslite.core import extras
from gausslite.core.arrays import GaussianArrays
from gausslite.errors import CapacityExceeded, ExtraUnavailable, PreconditionFailed
from gausslite.fusion.engine import FuseEngine
from gausslite.fusion.guard import RoiView
from gausslite.fusion.plausible import check_plausible
from gausslite.fusion.uploads import check_delta_base, check_not_superseded, complete_delta_upload
from gausslite.wire.decode import assemble, decode_chunk, peek_header
from gausslite.wire.encode import encode_subset
from gausslite.wire.format import LOSSLESS, DeltaMismatch, LimitExceeded, WireError, WireLimits
from gausslite_rpc import common_pb2, fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.auth import Authenticator, AuthError
from gausslite_services.common.convert import intrinsics_to_proto
from gausslite_services.common.errors import status_for
from gausslite_services.common.server import peer_host
from gausslite_services.fusion_server.guards import (Cancelled, intrinsics_from_proto, Reject, stream_guard,
                                                     unary_guard, check_agent_id, check_int64, decode_color,
                                                     decode_depth, decode_roi, UploadStreams)
from gausslite_services.fusion_server.refine_worker import decode_keyframe, keyframe_key
from gausslite_services.fusion_server.store import ChunkConflict, Session, SqlFusionStore, StoredKeyframe
from gausslite_services.fusion_server.team_map import TEAM_MAP_RETENTION, TeamMapRefresher

log = logging.getLogger("gausslite_services.fusion_server.server")  # one logger for the whole service

SERVICE_NAME = "gausslite.v1.Fusion"
FUSED_AGENT_ID = "fused"
#: agents per GetStats page when the request leaves page_size 0, and the largest page_size accepted
STATS_PAGE_SIZE = 100
MAX_STATS_PAGE_SIZE = 1000
_METHOD_NAMES = {fusion_pb2.FUSE_METHOD_VOTE: "vote", fusion_pb2.FUSE_METHOD_CONCAT: "concat"}
#: bytes an ``UploadSubsetRequest`` adds around its chunk (field tag and length, 6 at most, with margin): a chunk fits
#: in one message when it is at most ``max_message_bytes - CHUNK_ENVELOPE_BYTES`` (``SessionInfo.max_chunk_bytes``)
CHUNK_ENVELOPE_BYTES = 16
#: largest row count of one chunk the server accepts (the wire format's own bound, ``docs/wire-format.md`` §8)
MAX_CHUNK_GAUSSIANS = 1 << 20
#: smallest message bound the server runs with: a fused chunk (64 KiB at least) and its ``FuseResult`` must fit
MIN_MESSAGE_BYTES = 128 * 1024


#: the library's refusals of an upload (:mod:`gausslite.fusion.uploads`)
_UPLOAD_REFUSALS = (PreconditionFailed, CapacityExceeded, DeltaMismatch)


@contextlib.contextmanager
def _upload_refusals() -> Iterator[None]:
    """Answer the library's refusals of an upload (:data:`_UPLOAD_REFUSALS`) raised in the block with the status
    :func:`gausslite_services.common.errors.status_for` gives their type, and their message."""
    try:
        yield
    except _UPLOAD_REFUSALS as e:
        raise Reject(status_for(e), str(e)) from None


def _ordinal(n: int) -> str:
    """1 → "1st", 2 → "2nd", 11 → "11th", 23 → "23rd" (a count in client-facing messages, never an index)."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


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

    # ------------------------------------------------------------------ helpers
    def _check_writer(self, context, agent_id: str) -> None:
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

    def _session(self, agent_id: str) -> Session:
        check_agent_id(agent_id)
        s = self.store.session(agent_id)
        if s is None:
            raise Reject(grpc.StatusCode.NOT_FOUND, f"agent {agent_id!r} has no open session; call OpenSession first")
        return s

    def _ack(self, agent_id: str, map_version: int, newly: int = 0) -> fusion_pb2.UploadAck:
        up = self.store.upload(agent_id, map_version)
        latest = self.store.latest_version(agent_id)
        ack = fusion_pb2.UploadAck(agent_id=agent_id, map_version=map_version, newly_stored=newly,
                                   is_latest=latest is not None and latest == map_version,
                                   superseded_by=latest if latest is not None and latest > map_version else 0)
        if up is not None:
            ack.n_chunks = up.n_chunks
            ack.stored.extend(up.stored)
            ack.missing.extend(up.missing)
            ack.complete = up.complete
            ack.n_gaussians = up.n_gaussians
            ack.bytes_on_wire = up.wire_bytes
            ack.stored_bytes = up.stored_bytes
        return ack

    def _subset(self, agent_id: str, version: int) -> GaussianArrays:
        key = (agent_id, version)
        with self._cache_lock:
            hit = self._cache.get(key)
        if hit is not None:
            return hit
        arrays, _ = assemble(self.store.chunk_data(agent_id, version), self.limits)
        self._cache_put(agent_id, version, arrays)
        return arrays

    def _cache_put(self, agent_id: str, version: int, arrays: GaussianArrays) -> None:
        """Keep ``arrays`` as the decoded subset of ``agent_id``, one version per agent (the newest a delta is
        built on): a long mission pushes a new version every few keyframes."""
        with self._cache_lock:
            for k in [k for k in self._cache if k[0] == agent_id and k[1] != version]:
                del self._cache[k]
            self._cache[(agent_id, version)] = arrays

    def _rebuild_delta(self, agent: str, version: int) -> None:
        """When every chunk of a delta upload is stored: rebuild and store the full subset
        (:func:`gausslite.fusion.uploads.complete_delta_upload`) and keep it decoded."""
        with _upload_refusals():
            done = complete_delta_upload(self.store, agent, version, self.limits, self._subset)
        if done is None:
            return
        self._cache_put(agent, version, done.subset)
        log.info("subset %s v%d rebuilt from base v%d + delta (%d records, %d removed, κ shift %d): %d Gaussians",
                 agent, version, done.meta.base_version, done.records, done.removed, done.meta.kappa_shift,
                 len(done.subset))

    # ------------------------------------------------------------------ RPCs
    @unary_guard
    def OpenSession(self, request, context):  # noqa: N802
        agent = check_agent_id(request.agent_id)
        self._check_writer(context, agent)
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
            return self._upload_subset(messages, context)

    def _upload_subset(self, request_iterator, context) -> fusion_pb2.UploadAck:
        it = iter(request_iterator)
        first = next(it, None)
        if first is None or first.WhichOneof("payload") != "header":
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "the first UploadSubset message must be the header")
        h = first.header
        agent, version, n_chunks = h.agent_id, check_int64(h.map_version, "map_version"), int(h.n_chunks)
        self._check_writer(context, check_agent_id(agent))
        self._session(agent)
        if n_chunks < 1:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "n_chunks must be >= 1")
        if n_chunks > self.limits.max_chunks:
            raise Reject(grpc.StatusCode.RESOURCE_EXHAUSTED, f"n_chunks {n_chunks} exceeds {self.limits.max_chunks}")
        with _upload_refusals():
            check_not_superseded(agent, version, self.store.latest_version(agent))
        try:
            self.store.begin_upload(agent, version, n_chunks, check_int64(h.full_map_gaussians, "full_map_gaussians"),
                                    check_int64(h.full_map_bytes, "full_map_bytes"))
        except ValueError as e:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, str(e)) from None
        newly = 0
        for pos, msg in enumerate(it, start=1):
            if msg.WhichOneof("payload") != "chunk":
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                             f"the {_ordinal(pos)} message after the header is a second header; send the header "
                             "once, first, then only chunks")
            data = msg.chunk
            # chunks are named by their 0-based chunk index (as in UploadAck.stored / missing) once their header is
            # read; before that, by their place in this call's stream
            unread = f"the {_ordinal(pos)} chunk of this call (chunk index unreadable)"
            try:
                hdr = peek_header(data, self.limits)
            except LimitExceeded as e:
                raise Reject(grpc.StatusCode.RESOURCE_EXHAUSTED, f"{unread}: LimitExceeded: {e}") from None
            except WireError as e:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"{unread}: {type(e).__name__}: {e}") from None
            idx = hdr.chunk_index
            if hdr.delta:
                base_version = check_int64(hdr.base_version, "delta base_version")
                with _upload_refusals():
                    check_delta_base(self.store, agent, version, base_version)
            if hdr.agent_id != agent or hdr.map_version != version:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                             f"chunk index {idx} belongs to agent {hdr.agent_id!r} v{hdr.map_version}, the upload "
                             f"header to {agent!r} v{version}")
            if hdr.chunk_count != n_chunks:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                             f"chunk index {idx} says its version has {hdr.chunk_count} chunks, the upload header {n_chunks}")
            if h.full_map_gaussians and hdr.total_count > h.full_map_gaussians:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                             f"chunk index {idx}: subset of {hdr.total_count} Gaussians exceeds full_map_gaussians "
                             f"{h.full_map_gaussians}")
            try:
                dc = decode_chunk(data, self.limits)
            except WireError as e:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"chunk index {idx}: {type(e).__name__}: {e}") from None
            try:
                c = self.config
                check_plausible(dc.arrays, c.max_abs_mean_m, c.max_scale_m, c.max_abs_opacity_logit)
            except ValueError as e:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"chunk index {idx}: {e}") from None
            try:
                new, _ = self.store.put_chunk(agent, version, idx, bytes(data), dc.digest, hdr.count,
                                              hdr.total_count, hdr.lossless, defer_complete=hdr.delta)
            except ChunkConflict as e:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT, str(e)) from None
            except ValueError as e:
                if self.store.upload(agent, version) is None:  # superseded meanwhile
                    raise Reject(grpc.StatusCode.FAILED_PRECONDITION,
                                 f"map_version {version} of {agent!r} was superseded during the upload") from None
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT, str(e)) from None
            newly += int(new)
        self._rebuild_delta(agent, version)
        ack = self._ack(agent, version, newly)
        if ack.complete and newly:
            log.info("subset %s v%d complete: %d Gaussians, %d chunks, %d bytes received, %d bytes stored", agent,
                     version, ack.n_gaussians, ack.n_chunks, ack.bytes_on_wire, ack.stored_bytes)
            if self.team_map is not None:
                self.team_map.notify()
        return ack

    @unary_guard
    def GetUploadStatus(self, request, context):  # noqa: N802
        self._session(request.agent_id)
        return self._ack(request.agent_id, check_int64(request.map_version, "map_version"))

    @unary_guard
    def UploadKeyframes(self, request_iterator, context):  # noqa: N802
        with self.uploads.open(request_iterator, context, "UploadKeyframes", self._caller(context)) as messages:
            return self._upload_keyframes(messages, context)

    def _upload_keyframes(self, request_iterator, context) -> fusion_pb2.KeyframeAck:
        received = stored = dups = evicted = 0
        agent = ""
        allowed = set()
        for msg in request_iterator:
            received += 1
            agent = msg.agent_id
            if agent not in allowed:
                self._check_writer(context, check_agent_id(agent))
                allowed.add(agent)
            session = self._session(agent)
            what = f"keyframe {msg.frame_id} of {agent!r}"
            if msg.HasField("intrinsics"):
                k = intrinsics_from_proto(msg.intrinsics, what)
            else:
                k = Intrinsics(session.fx, session.fy, session.cx, session.cy, session.width, session.height)
            if len(msg.pose.c2w) != 16:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"{what}: pose needs 16 values, got {len(msg.pose.c2w)}")
            try:
                c2w = check_rigid(np.asarray(msg.pose.c2w, np.float64).reshape(4, 4), what=f"{what} pose")
            except ValueError as e:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT, str(e)) from None
            scale = float(msg.depth_scale)
            if not (math.isfinite(scale) and scale > 0):
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"{what}: depth_scale must be finite and > 0")
            size = (int(k.height), int(k.width))
            if size[0] * size[1] > self.config.max_keyframe_pixels:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                             f"{what}: {size[1]}x{size[0]} pixels exceed the server's keyframe limit of "
                             f"{self.config.max_keyframe_pixels} pixels")
            # sizes from the headers first: a small file may declare a huge image (decompression bomb)
            decode_color(msg.color, what, size)
            decode_depth(msg.depth_png, scale, what, size)
            if msg.roi_png:
                decode_roi(msg.roi_png, size, what)
            new, ev = self.store.put_keyframe(
                StoredKeyframe(agent, int(msg.frame_id), bytes(msg.color), bytes(msg.depth_png), scale, c2w,
                               k.fx, k.fy, k.cx, k.cy, int(k.width), int(k.height), float(msg.timestamp),
                               bytes(msg.roi_png)),
                self.config.max_keyframes_per_agent)
            stored += int(new)
            dups += int(not new)
            evicted += ev
        if received == 0:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "empty keyframe stream")
        if stored and self.team_map is not None:
            self.team_map.notify()
        return fusion_pb2.KeyframeAck(agent_id=agent, received=received, stored=stored, duplicates=dups,
                                      evicted=evicted, buffered=self.store.keyframe_count(agent))

    def _served_team_map(self) -> fusion_pb2.FuseProgress:
        """The ``Fuse(team_map=true)`` answer: the newest stored team map's result, with its age and whether it is
        current. Raises Reject: FAILED_PRECONDITION when this server keeps no team map, NOT_FOUND before the first."""
        if self.team_map is None:
            why = self._unavailable["refine"] if self.config.team_map.enabled else "fusion.team_map.enabled is false"
            raise Reject(grpc.StatusCode.FAILED_PRECONDITION, f"this server keeps no team map ({why})")
        result = self.team_map.latest()
        if result is None:
            raise Reject(grpc.StatusCode.NOT_FOUND, "no team map yet: it is made once a subset and keyframes are in"
                         + (f" (last refinement failed: {self.team_map.last_error})" if self.team_map.last_error
                            else ""))
        self._served(result)
        return fusion_pb2.FuseProgress(stage="done", fraction=1.0, done=True, result=result,
                                       message=f"team map version {result.fused_version}")

    def _served(self, result: fusion_pb2.FuseResult) -> None:
        """Fill a stored result's serving fields: its age, and for a team map whether it is current."""
        result.age_s = max(0.0, time.time() - result.created_unix)
        if result.team_map and self.team_map is not None:
            result.team_map_current = self.team_map.is_current(result, *self.team_map.inputs())

    @stream_guard
    def Fuse(self, request, context):  # noqa: N802
        if request.team_map:
            yield self._served_team_map()
            return
        method = request.method or fusion_pb2.FUSE_METHOD_VOTE
        if method not in _METHOD_NAMES:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"unknown fuse method {request.method}")
        if request.refine and self._unavailable["refine"]:
            raise Reject(grpc.StatusCode.FAILED_PRECONDITION, f"refine=true: {self._unavailable['refine']}")
        voxel = float(request.voxel_size) or self.config.default_voxel_size
        if not (math.isfinite(voxel) and voxel > 0):
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"voxel_size must be finite and > 0, got {voxel}")
        radius = (int(request.contest_radius) if request.HasField("contest_radius")
                  else int(self.config.default_contest_radius))
        if radius > 8:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"contest_radius must be in 0..8, got {radius}")
        iters = int(request.refine_iters) or self.config.default_refine_iters
        if request.refine and iters > self.config.max_refine_iters:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                         f"refine_iters {iters} exceeds the server limit {self.config.max_refine_iters}")
        latest = self.store.latest_complete()
        if not latest:
            raise Reject(grpc.StatusCode.FAILED_PRECONDITION,
                         "no agent has uploaded a complete subset yet; nothing to fuse")
        for_agent = None
        if request.for_agent:
            for_agent = check_agent_id(request.for_agent)
            if method != fusion_pb2.FUSE_METHOD_VOTE:
                raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "for_agent needs method VOTE")
            if for_agent not in latest:
                raise Reject(grpc.StatusCode.NOT_FOUND if self.store.session(for_agent) is None
                             else grpc.StatusCode.FAILED_PRECONDITION,
                             f"agent {for_agent!r} has no complete subset on this server")
        if request.refine and self.store.keyframe_count() == 0:
            raise Reject(grpc.StatusCode.FAILED_PRECONDITION, "refine=true but no keyframes were uploaded")

        events: "queue.Queue[tuple]" = queue.Queue()
        cancel = threading.Event()
        context.add_callback(cancel.set)
        worker = threading.Thread(target=self._fuse_work, name="gausslite-fuse", daemon=True,
                                  args=(latest, method, voxel, bool(request.refine), iters, int(request.seed),
                                        events, cancel, radius, for_agent))
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
                maps = {a: self._subset(a, v) for a, v in latest.items()}
                with self._refining(stopped) if refine else contextlib.nullcontext():
                    out = self._engine.fuse(latest, maps, _METHOD_NAMES[method], voxel_size=voxel,
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
    def _refining(self, stopped) -> Iterator[None]:
        """Hold this server's refinement lock (one joint refinement at a time: a Fuse's or the team map's)."""
        while not self._refine_lock.acquire(timeout=0.2):
            if stopped():
                raise Cancelled()
        try:
            yield
        finally:
            self._refine_lock.release()

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
        log.info("fused version %d: %s%s, %d Gaussians, refine=%s, %.2fs", version, _METHOD_NAMES[method],
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
        method = int(request.method)
        if method and method not in _METHOD_NAMES:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"unknown method filter {method}")
        found = self.store.fused_info(check_int64(request.fused_version, "fused_version"), method)
        if found is None:
            what = f"fused version {request.fused_version}" if request.fused_version else "no fused map yet"
            raise Reject(grpc.StatusCode.NOT_FOUND, f"unknown {what}" if request.fused_version else what
                          + (f" of method {_METHOD_NAMES[method]}" if method else ""))
        version, info_bytes, n = found
        info = fusion_pb2.FuseResult.FromString(info_bytes)
        self._served(info)
        if method and request.fused_version and info.method != method:
            raise Reject(grpc.StatusCode.NOT_FOUND,
                         f"fused version {version} was made by {_METHOD_NAMES.get(info.method)}, "
                         f"not {_METHOD_NAMES[method]}")
        for i in range(n):
            if not context.is_active():
                return
            yield fusion_pb2.FusedChunk(fused_version=version, chunk_index=i, n_chunks=n,
                                        chunk=self.store.fused_chunk(version, i), info=info if i == 0 else None)

    @unary_guard
    def GetStats(self, request, context):  # noqa: N802
        size = int(request.page_size) or STATS_PAGE_SIZE
        if size > MAX_STATS_PAGE_SIZE:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"page_size {size} exceeds {MAX_STATS_PAGE_SIZE}")
        after = request.page_token
        if after:
            check_agent_id(after)  # the token is the last agent id of the previous page
        resp = fusion_pb2.StatsResponse()
        sessions = self.store.sessions(after=after, limit=size + 1)
        if len(sessions) > size:
            sessions = sessions[:size]
            resp.next_page_token = sessions[-1].agent_id
        for s in sessions:
            a = fusion_pb2.AgentStats(agent_id=s.agent_id, task_text=s.task_text,
                                      keyframes=self.store.keyframe_count(s.agent_id))
            latest, up = None, None
            for _ in range(5):  # a newer version may complete (and delete this one) between the two reads
                latest = self.store.latest_version(s.agent_id)
                up = self.store.upload(s.agent_id, latest) if latest is not None else None
                if latest is None or up is not None:
                    break
            if up is not None:
                a.latest_map_version = latest
                a.has_complete_subset = True
                a.gaussians_received = up.n_gaussians
                a.bytes_on_wire = up.wire_bytes
                a.stored_bytes = up.stored_bytes
                a.chunks = len(up.stored)
                a.full_map_gaussians = up.full_map_gaussians
                a.full_map_bytes = up.full_map_bytes
                a.share_pct = 100.0 * up.n_gaussians / up.full_map_gaussians if up.full_map_gaussians else 0.0
                a.bytes_per_gaussian = up.stored_bytes / up.n_gaussians if up.n_gaussians else 0.0
            resp.agents.append(a)
        infos = [fusion_pb2.FuseResult.FromString(info) for info in self.store.fused_infos()]
        if not after:  # bounded by the retention (fusion.fused_keep_per_method per method)
            resp.fused.extend(infos)
        resp.latest_fused_version = infos[-1].fused_version if infos else 0
        return resp

    @unary_guard
    def GetKeyframePoses(self, request, context):  # noqa: N802
        agent = request.agent_id or None
        if agent is not None:
            self._session(agent)
        resp = fusion_pb2.KeyframePosesResponse()
        for k in self.store.keyframe_poses(agent):
            resp.keyframes.add(agent_id=k.agent_id, frame_id=k.frame_id, timestamp=k.timestamp,
                               pose=common_pb2.Pose(c2w=np.asarray(k.c2w, np.float64).reshape(-1).tolist()),
                               intrinsics=intrinsics_to_proto(k))
        return resp
