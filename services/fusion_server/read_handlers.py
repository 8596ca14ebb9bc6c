"""The fusion server's reading RPCs: a stored fused map (``DownloadFused``, :func:`download_fused`), the statistics
over the store (``GetStats``, :func:`stats`) and the stored keyframes' poses (``GetKeyframePoses``,
:func:`keyframe_poses`).

Each function takes ``sv``, the :class:`~gausslite_services.fusion_server.servicer.FusionServicer` that answers the
call (its store, sessions and team map).
"""

from __future__ import annotations

from typing import Iterator

import grpc
import numpy as np

from gausslite_rpc import common_pb2, fusion_pb2
from gausslite_services.common.convert import intrinsics_to_proto
from gausslite_services.fusion_server.fuse_handlers import METHOD_NAMES, served
from gausslite_services.fusion_server.guards import Reject, check_agent_id, check_int64

__all__ = ["download_fused", "stats", "keyframe_poses", "STATS_PAGE_SIZE", "MAX_STATS_PAGE_SIZE"]

#: agents per GetStats page when the request leaves page_size 0, and the largest page_size accepted
STATS_PAGE_SIZE = 100
MAX_STATS_PAGE_SIZE = 1000


def download_fused(sv, request, context) -> Iterator[fusion_pb2.FusedChunk]:
    """``DownloadFused``: the chunks of the requested fused version (0: the newest, of ``request.method`` when
    set), the first with its ``FuseResult`` (its age and currency filled, :func:`served`), while the caller listens.
    Raises Reject: INVALID_ARGUMENT for an unknown method filter, NOT_FOUND for no such version."""
    method = int(request.method)
    if method and method not in METHOD_NAMES:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"unknown method filter {method}")
    found = sv.store.fused_info(check_int64(request.fused_version, "fused_version"), method)
    if found is None:
        what = f"fused version {request.fused_version}" if request.fused_version else "no fused map yet"
        raise Reject(grpc.StatusCode.NOT_FOUND, f"unknown {what}" if request.fused_version else what
                      + (f" of method {METHOD_NAMES[method]}" if method else ""))
    version, info_bytes, n = found
    info = fusion_pb2.FuseResult.FromString(info_bytes)
    served(sv, info)
    if method and request.fused_version and info.method != method:
        raise Reject(grpc.StatusCode.NOT_FOUND,
                     f"fused version {version} was made by {METHOD_NAMES.get(info.method)}, "
                     f"not {METHOD_NAMES[method]}")
    for i in range(n):
        if not context.is_active():
            return
        yield fusion_pb2.FusedChunk(fused_version=version, chunk_index=i, n_chunks=n,
                                    chunk=sv.store.fused_chunk(version, i), info=info if i == 0 else None)


def stats(sv, request) -> fusion_pb2.StatsResponse:
    """``GetStats``: one page of agents (``page_size``, default :data:`STATS_PAGE_SIZE`, at most
    :data:`MAX_STATS_PAGE_SIZE`; ``page_token``: the last agent id of the previous page) with each agent's latest
    complete subset and its sizes; the first page also lists the stored fused maps. Raises Reject (INVALID_ARGUMENT)
    for a page too large or a bad token."""
    size = int(request.page_size) or STATS_PAGE_SIZE
    if size > MAX_STATS_PAGE_SIZE:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"page_size {size} exceeds {MAX_STATS_PAGE_SIZE}")
    after = request.page_token
    if after:
        check_agent_id(after)  # the token is the last agent id of the previous page
    resp = fusion_pb2.StatsResponse()
    sessions = sv.store.sessions(after=after, limit=size + 1)
    if len(sessions) > size:
        sessions = sessions[:size]
        resp.next_page_token = sessions[-1].agent_id
    for s in sessions:
        a = fusion_pb2.AgentStats(agent_id=s.agent_id, task_text=s.task_text,
                                  keyframes=sv.store.keyframe_count(s.agent_id))
        latest, up = None, None
        for _ in range(5):  # a newer version may complete (and delete this one) between the two reads
            latest = sv.store.latest_version(s.agent_id)
            up = sv.store.upload(s.agent_id, latest) if latest is not None else None
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
    infos = [fusion_pb2.FuseResult.FromString(info) for info in sv.store.fused_infos()]
    if not after:  # bounded by the retention (fusion.fused_keep_per_method per method)
        resp.fused.extend(infos)
    resp.latest_fused_version = infos[-1].fused_version if infos else 0
    return resp


def keyframe_poses(sv, request) -> fusion_pb2.KeyframePosesResponse:
    """``GetKeyframePoses``: the pose and intrinsics of every stored keyframe of ``request.agent_id`` (its
    session must be open; Reject NOT_FOUND otherwise), or of every agent when it is empty."""
    agent = request.agent_id or None
    if agent is not None:
        sv.session_of(agent)
    resp = fusion_pb2.KeyframePosesResponse()
    for k in sv.store.keyframe_poses(agent):
        resp.keyframes.add(agent_id=k.agent_id, frame_id=k.frame_id, timestamp=k.timestamp,
                           pose=common_pb2.Pose(c2w=np.asarray(k.c2w, np.float64).reshape(-1).tolist()),
                           intrinsics=intrinsics_to_proto(k))
    return resp
