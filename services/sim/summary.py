"""An agent's status and Finish summary as the library reads them: the ``MissionStatus`` message as the mission's
status dict (:func:`status_from_proto`, which :func:`gausslite.team.harness.run_team` follows) and the
``MissionSummary`` message as the library's :class:`gausslite.mission.scoring.MissionSummaryData`
(:func:`summary_from_proto`, which the team's report, :mod:`gausslite.team`, reads)."""

from __future__ import annotations

from typing import Dict

import numpy as np

from gausslite.evaluation import TrackedView
from gausslite.mission.scoring import MissionSummaryData
from gausslite_rpc import agent_pb2
from gausslite_services.agent.convert import STATES

#: ``MissionState`` enum value on the wire → the mission's state
_STATE_OF = {v: k for k, v in STATES.items()}


def _views(poses) -> Dict[int, TrackedView]:
    """frame id → :class:`gausslite.evaluation.TrackedView` of repeated ``TrackedPose`` messages (nothing fitted)."""
    return {int(t.frame_id): TrackedView(np.asarray(t.pose.c2w, np.float64).reshape(4, 4),
                                         np.asarray(t.exposure, np.float64), 0.0, 0.0, 0.0, 0)
            for t in poses}


def status_from_proto(msg: agent_pb2.MissionStatus) -> dict:
    """A ``MissionStatus`` message as the mission's status dict (:meth:`AgentRuntime.status
    <gausslite.mission.runtime.AgentRuntime.status>`'s keys), ``state`` a :class:`~gausslite.mission.state.MissionState`
    (None for ``MISSION_STATE_UNSPECIFIED``)."""
    st = {f.name: getattr(msg, f.name) for f in msg.DESCRIPTOR.fields}
    st["state"] = _STATE_OF.get(msg.state)
    return st


def summary_from_proto(msg: agent_pb2.MissionSummary) -> MissionSummaryData:
    """The library's Finish summary of an agent's ``MissionSummary`` message.

    Args:
        msg: the agent service's answer to ``Finish``.
    Returns:
        ``status``: the ``MissionStatus`` fields by name (:func:`status_from_proto`); the ROI PSNRs (dB) None where
        the message says it has none (``has_roi_psnr``, ``has_roi_psnr_all_frames``); ``pushes``: one record per push
        as the mission keeps them (``bytes_on_wire``: the push's bytes sent); ``protocols``: protocol →
        ``{"roi_psnr" (None without one), "psnr", "ssim", "frames_scored", "roi_frames", "roi_psnr_per_frame"}``;
        ``tracked_views`` / ``predicted_views``: frame id → :class:`gausslite.evaluation.TrackedView` (the pose,
        camera-to-world (4, 4) float64, and exposure each ``tracked`` / ``novel`` frame was scored at on the robot's
        own map).
    """
    status = status_from_proto(msg.status)
    pushes = [{"version": q.version, "n_shared": q.n_shared, "n_total": q.n_total, "bytes_on_wire": q.bytes_sent,
               "delta": q.delta, "records": q.records, "removed": q.removed, "frames_mapped": q.frames_mapped,
               "unchanged": q.unchanged} for q in msg.pushes]
    protocols = {q: {"roi_psnr": v.roi_psnr if v.has_roi_psnr else None, "psnr": v.psnr, "ssim": v.ssim,
                     "frames_scored": v.frames_scored, "roi_frames": v.roi_frames,
                     "roi_psnr_per_frame": {int(k): float(x) for k, x in v.roi_psnr_per_frame.items()}}
                 for q, v in msg.protocols.items()}
    return MissionSummaryData(
        status=status, final_push_ok=msg.final_push_ok, n_shared=msg.n_shared, share_pct=msg.share_pct,
        bytes_on_wire=msg.bytes_on_wire, bytes_per_gaussian=msg.bytes_per_gaussian,
        roi_psnr=msg.roi_psnr if msg.has_roi_psnr else None, psnr=msg.psnr, seconds_per_frame=msg.seconds_per_frame,
        roi_psnr_all_frames=msg.roi_psnr_all_frames if msg.has_roi_psnr_all_frames else None,
        frames_all=msg.frames_all, protocols=protocols, total_upload_bytes=msg.total_upload_bytes,
        final_subset_bytes=msg.final_subset_bytes, pushes=pushes, view_bytes=msg.view_bytes,
        views_sent=msg.views_sent, views_unsent=msg.views_unsent, tracked_views=_views(msg.tracked_views),
        predicted_views=_views(msg.predicted_views))
