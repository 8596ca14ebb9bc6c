"""The fusion server's upload RPCs: ``UploadSubset`` (:func:`upload_subset`: a version's chunks checked one by one and
stored, a delta rebuilt into its full subset once its last chunk is in), the ``UploadAck`` it and ``GetUploadStatus``
answer (:func:`upload_ack`), and ``UploadKeyframes`` (:func:`upload_keyframes`).

Each function takes ``sv``, the :class:`~gausslite_services.fusion_server.servicer.FusionServicer` that answers the
call: its store, wire limits and settings, its write check (``check_writer``), sessions (``session_of``) and decoded
subsets (``subset``, ``cache_put``).
"""

from __future__ import annotations

import contextlib
import logging
import math
from typing import Iterator

import grpc
import numpy as np

from gausslite.camera import Intrinsics, check_rigid
from gausslite.errors import CapacityExceeded, PreconditionFailed
from gausslite.fusion.plausible import check_plausible
from gausslite.fusion.uploads import check_delta_base, check_not_superseded, complete_delta_upload
from gausslite.wire.decode import decode_chunk, peek_header
from gausslite.wire.format import DeltaMismatch, LimitExceeded, WireError
from gausslite_rpc import fusion_pb2
from gausslite_services.common.errors import status_for
from gausslite_services.fusion_server.guards import (Reject, check_agent_id, check_int64, decode_color, decode_depth,
                                                     decode_roi, intrinsics_from_proto)
from gausslite_services.fusion_server.store import ChunkConflict, StoredKeyframe

log = logging.getLogger("gausslite_services.fusion_server.server")  # one logger for the whole service

__all__ = ["upload_subset", "upload_keyframes", "upload_ack", "rebuild_delta", "upload_refusals", "UPLOAD_REFUSALS"]

#: the library's refusals of an upload (:mod:`gausslite.fusion.uploads`)
UPLOAD_REFUSALS = (PreconditionFailed, CapacityExceeded, DeltaMismatch)


@contextlib.contextmanager
def upload_refusals() -> Iterator[None]:
    """Answer the library's refusals of an upload (:data:`UPLOAD_REFUSALS`) raised in the block with the status
    :func:`gausslite_services.common.errors.status_for` gives their type, and their message."""
    try:
        yield
    except UPLOAD_REFUSALS as e:
        raise Reject(status_for(e), str(e)) from None


def ordinal(n: int) -> str:
    """1 → "1st", 2 → "2nd", 11 → "11th", 23 → "23rd" (a count in client-facing messages, never an index)."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def upload_subset(sv, request_iterator, context) -> fusion_pb2.UploadAck:
    """One ``UploadSubset`` stream (``request_iterator``: the header, then chunks) for ``sv``
    (:class:`~gausslite_services.fusion_server.servicer.FusionServicer`): the caller may write the agent, its session is
    open, the version is not superseded; each chunk's header, delta base, agent, version, counts, decoding and
    plausibility are checked before it is stored; a delta complete with this call is rebuilt into its full subset.
    Returns the version's ``UploadAck``. Raises Reject with the status of the first refusal."""
    it = iter(request_iterator)
    first = next(it, None)
    if first is None or first.WhichOneof("payload") != "header":
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "the first UploadSubset message must be the header")
    h = first.header
    agent, version, n_chunks = h.agent_id, check_int64(h.map_version, "map_version"), int(h.n_chunks)
    sv.check_writer(context, check_agent_id(agent))
    sv.session_of(agent)
    if n_chunks < 1:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "n_chunks must be >= 1")
    if n_chunks > sv.limits.max_chunks:
        raise Reject(grpc.StatusCode.RESOURCE_EXHAUSTED, f"n_chunks {n_chunks} exceeds {sv.limits.max_chunks}")
    with upload_refusals():
        check_not_superseded(agent, version, sv.store.latest_version(agent))
    try:
        sv.store.begin_upload(agent, version, n_chunks, check_int64(h.full_map_gaussians, "full_map_gaussians"),
                                check_int64(h.full_map_bytes, "full_map_bytes"))
    except ValueError as e:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, str(e)) from None
    newly = 0
    for pos, msg in enumerate(it, start=1):
        if msg.WhichOneof("payload") != "chunk":
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                         f"the {ordinal(pos)} message after the header is a second header; send the header "
                         "once, first, then only chunks")
        data = msg.chunk
        # chunks are named by their 0-based chunk index (as in UploadAck.stored / missing) once their header is
        # read; before that, by their place in this call's stream
        unread = f"the {ordinal(pos)} chunk of this call (chunk index unreadable)"
        try:
            hdr = peek_header(data, sv.limits)
        except LimitExceeded as e:
            raise Reject(grpc.StatusCode.RESOURCE_EXHAUSTED, f"{unread}: LimitExceeded: {e}") from None
        except WireError as e:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"{unread}: {type(e).__name__}: {e}") from None
        idx = hdr.chunk_index
        if hdr.delta:
            base_version = check_int64(hdr.base_version, "delta base_version")
            with upload_refusals():
                check_delta_base(sv.store, agent, version, base_version)
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
            dc = decode_chunk(data, sv.limits)
        except WireError as e:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"chunk index {idx}: {type(e).__name__}: {e}") from None
        try:
            c = sv.config
            check_plausible(dc.arrays, c.max_abs_mean_m, c.max_scale_m, c.max_abs_opacity_logit)
        except ValueError as e:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"chunk index {idx}: {e}") from None
        try:
            new, _ = sv.store.put_chunk(agent, version, idx, bytes(data), dc.digest, hdr.count,
                                          hdr.total_count, hdr.lossless, defer_complete=hdr.delta)
        except ChunkConflict as e:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, str(e)) from None
        except ValueError as e:
            if sv.store.upload(agent, version) is None:  # superseded meanwhile
                raise Reject(grpc.StatusCode.FAILED_PRECONDITION,
                             f"map_version {version} of {agent!r} was superseded during the upload") from None
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, str(e)) from None
        newly += int(new)
    rebuild_delta(sv, agent, version)
    ack = upload_ack(sv, agent, version, newly)
    if ack.complete and newly:
        log.info("subset %s v%d complete: %d Gaussians, %d chunks, %d bytes received, %d bytes stored", agent,
                 version, ack.n_gaussians, ack.n_chunks, ack.bytes_on_wire, ack.stored_bytes)
        if sv.team_map is not None:
            sv.team_map.notify()
    return ack


def upload_ack(sv, agent_id: str, map_version: int, newly: int = 0) -> fusion_pb2.UploadAck:
    """The server's ``UploadAck`` of (``agent_id``, ``map_version``) in ``sv``'s store: whether it is the
    latest and what supersedes it, and once the upload is known its chunks stored and missing, sizes and completeness;
    ``newly``: chunks this call stored."""
    up = sv.store.upload(agent_id, map_version)
    latest = sv.store.latest_version(agent_id)
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


def rebuild_delta(sv, agent: str, version: int) -> None:
    """When every chunk of a delta upload is stored: rebuild and store the full subset
    (:func:`gausslite.fusion.uploads.complete_delta_upload`) and keep it decoded."""
    with upload_refusals():
        done = complete_delta_upload(sv.store, agent, version, sv.limits, sv.subset)
    if done is None:
        return
    sv.cache_put(agent, version, done.subset)
    log.info("subset %s v%d rebuilt from base v%d + delta (%d records, %d removed, κ shift %d): %d Gaussians",
             agent, version, done.meta.base_version, done.records, done.removed, done.meta.kappa_shift,
             len(done.subset))

# ------------------------------------------------------------------ RPCs


def upload_keyframes(sv, request_iterator, context) -> fusion_pb2.KeyframeAck:
    """One ``UploadKeyframes`` stream for ``sv``: each keyframe's writer, session, intrinsics (its own,
    or the session's), pose (16 values, rigid), depth scale, pixel count and image headers (sizes before decoding:
    a small file may declare a huge image) are checked, then it is stored (the oldest beyond
    ``max_keyframes_per_agent`` evicted). Returns the ``KeyframeAck``. Raises Reject on the first bad keyframe or an
    empty stream."""
    received = stored = dups = evicted = 0
    agent = ""
    allowed = set()
    for msg in request_iterator:
        received += 1
        agent = msg.agent_id
        if agent not in allowed:
            sv.check_writer(context, check_agent_id(agent))
            allowed.add(agent)
        session = sv.session_of(agent)
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
        if size[0] * size[1] > sv.config.max_keyframe_pixels:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                         f"{what}: {size[1]}x{size[0]} pixels exceed the server's keyframe limit of "
                         f"{sv.config.max_keyframe_pixels} pixels")
        # sizes from the headers first: a small file may declare a huge image (decompression bomb)
        decode_color(msg.color, what, size)
        decode_depth(msg.depth_png, scale, what, size)
        if msg.roi_png:
            decode_roi(msg.roi_png, size, what)
        new, ev = sv.store.put_keyframe(
            StoredKeyframe(agent, int(msg.frame_id), bytes(msg.color), bytes(msg.depth_png), scale, c2w,
                           k.fx, k.fy, k.cx, k.cy, int(k.width), int(k.height), float(msg.timestamp),
                           bytes(msg.roi_png)),
            sv.config.max_keyframes_per_agent)
        stored += int(new)
        dups += int(not new)
        evicted += ev
    if received == 0:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "empty keyframe stream")
    if stored and sv.team_map is not None:
        sv.team_map.notify()
    return fusion_pb2.KeyframeAck(agent_id=agent, received=received, stored=stored, duplicates=dups,
                                  evicted=evicted, buffered=sv.store.keyframe_count(agent))
