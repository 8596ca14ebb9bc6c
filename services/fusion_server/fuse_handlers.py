"""The fusion server's answers to ``Fuse`` that the servicer's fuse job does not make: the checks of a request
(:func:`check_fuse_request`, into a :class:`FuseJob`), the team map's answer to ``Fuse(team_map=true)``
(:func:`served_team_map`), and the serving fields of a stored result (:func:`served`, also for ``DownloadFused``).

Each function takes ``sv``, the :class:`~gausslite_services.fusion_server.servicer.FusionServicer` that answers the
call (its store, settings, fuse modes and team map).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Dict, Optional

import grpc

from gausslite_rpc import fusion_pb2
from gausslite_services.fusion_server.guards import Reject, check_agent_id

__all__ = ["FuseJob", "check_fuse_request", "served", "served_team_map", "METHOD_NAMES"]

#: fuse method → its name in messages and logs
METHOD_NAMES = {fusion_pb2.FUSE_METHOD_VOTE: "vote", fusion_pb2.FUSE_METHOD_CONCAT: "concat"}


@dataclass(frozen=True)
class FuseJob:
    """A checked ``Fuse`` request: what the fuse job fuses and how.

    Attributes:
        latest: agent id → the version of its latest complete subset (every agent with one).
        method: ``FUSE_METHOD_VOTE`` or ``FUSE_METHOD_CONCAT``. voxel: the vote's voxel edge (metres).
        refine: run the joint refinement, with ``iters`` iterations at most and seed ``seed``.
        radius: the vote's neighbourhood radius in voxels (0..8). for_agent: the agent the map is made for, or None.
    """

    latest: Dict[str, int]
    method: int
    voxel: float
    refine: bool
    iters: int
    seed: int
    radius: int
    for_agent: Optional[str]


def check_fuse_request(sv, request) -> FuseJob:
    """The :class:`FuseJob` a ``FuseRequest`` asks ``sv`` for, the server's defaults filling what it leaves unset
    (``fusion.default_voxel_size``, ``default_contest_radius``, ``default_refine_iters``).

    Raises:
        Reject: INVALID_ARGUMENT (unknown method, bad voxel size, radius or iteration count, ``for_agent`` with
            CONCAT), FAILED_PRECONDITION (refinement this install cannot run, nothing complete to fuse, refinement
            without keyframes, ``for_agent`` without a complete subset), NOT_FOUND (``for_agent`` unknown).
    """
    method = request.method or fusion_pb2.FUSE_METHOD_VOTE
    if method not in METHOD_NAMES:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"unknown fuse method {request.method}")
    if request.refine and sv.fuse_modes()["refine"]:
        raise Reject(grpc.StatusCode.FAILED_PRECONDITION, f"refine=true: {sv.fuse_modes()['refine']}")
    voxel = float(request.voxel_size) or sv.config.default_voxel_size
    if not (math.isfinite(voxel) and voxel > 0):
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"voxel_size must be finite and > 0, got {voxel}")
    radius = (int(request.contest_radius) if request.HasField("contest_radius")
              else int(sv.config.default_contest_radius))
    if radius > 8:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"contest_radius must be in 0..8, got {radius}")
    iters = int(request.refine_iters) or sv.config.default_refine_iters
    if request.refine and iters > sv.config.max_refine_iters:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                     f"refine_iters {iters} exceeds the server limit {sv.config.max_refine_iters}")
    latest = sv.store.latest_complete()
    if not latest:
        raise Reject(grpc.StatusCode.FAILED_PRECONDITION,
                     "no agent has uploaded a complete subset yet; nothing to fuse")
    for_agent = None
    if request.for_agent:
        for_agent = check_agent_id(request.for_agent)
        if method != fusion_pb2.FUSE_METHOD_VOTE:
            raise Reject(grpc.StatusCode.INVALID_ARGUMENT, "for_agent needs method VOTE")
        if for_agent not in latest:
            raise Reject(grpc.StatusCode.NOT_FOUND if sv.store.session(for_agent) is None
                         else grpc.StatusCode.FAILED_PRECONDITION,
                         f"agent {for_agent!r} has no complete subset on this server")
    if request.refine and sv.store.keyframe_count() == 0:
        raise Reject(grpc.StatusCode.FAILED_PRECONDITION, "refine=true but no keyframes were uploaded")
    return FuseJob(latest, method, voxel, bool(request.refine), iters, int(request.seed), radius, for_agent)


def served(sv, result: fusion_pb2.FuseResult) -> None:
    """Fill a stored result's serving fields: its age, and for a team map whether it is current."""
    result.age_s = max(0.0, time.time() - result.created_unix)
    if result.team_map and sv.team_map is not None:
        result.team_map_current = sv.team_map.is_current(result, *sv.team_map.inputs())


def served_team_map(sv) -> fusion_pb2.FuseProgress:
    """The ``Fuse(team_map=true)`` answer: the newest stored team map's result, with its age and whether it is
    current. Raises Reject: FAILED_PRECONDITION when this server keeps no team map, NOT_FOUND before the first."""
    if sv.team_map is None:
        why = sv.fuse_modes()["refine"] if sv.config.team_map.enabled else "fusion.team_map.enabled is false"
        raise Reject(grpc.StatusCode.FAILED_PRECONDITION, f"this server keeps no team map ({why})")
    result = sv.team_map.latest()
    if result is None:
        raise Reject(grpc.StatusCode.NOT_FOUND, "no team map yet: it is made once a subset and keyframes are in"
                     + (f" (last refinement failed: {sv.team_map.last_error})" if sv.team_map.last_error
                        else ""))
    served(sv, result)
    return fusion_pb2.FuseProgress(stage="done", fraction=1.0, done=True, result=result,
                                   message=f"team map version {result.fused_version}")
