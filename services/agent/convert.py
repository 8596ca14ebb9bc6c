"""The agent service's messages made from the mission library's results: a mission's status
(:func:`status_proto`), its Finish summary (:func:`summary_proto`) and the views its final map was scored at
(:func:`views_proto`).
"""

from __future__ import annotations

import numpy as np

from gausslite.mission import MissionState, MissionSummaryData
from gausslite_rpc import agent_pb2, common_pb2

__all__ = ["STATES", "status_proto", "summary_proto", "views_proto"]

#: mission state → its ``MissionState`` enum value on the wire
STATES = {
    MissionState.MAPPING: agent_pb2.MISSION_STATE_MAPPING,
    MissionState.REPLAY_DONE: agent_pb2.MISSION_STATE_REPLAY_DONE,
    MissionState.FINISHING: agent_pb2.MISSION_STATE_FINISHING,
    MissionState.FINISHED: agent_pb2.MISSION_STATE_FINISHED,
    MissionState.FAILED: agent_pb2.MISSION_STATE_FAILED,
}


def views_proto(views: dict) -> list:
    """frame id → :class:`gausslite.evaluation.TrackedView` (pose (4, 4) camera-to-world, metres; exposure (6,)) as
    ``TrackedPose`` messages, by frame id."""
    return [agent_pb2.TrackedPose(frame_id=int(i), pose=common_pb2.Pose(
        c2w=np.asarray(v.c2w, np.float64).reshape(-1).tolist()), exposure=np.asarray(v.theta).tolist())
        for i, v in sorted(views.items())]


def status_proto(st: dict) -> agent_pb2.MissionStatus:
    """A mission's status (:meth:`AgentRuntime.status <gausslite.mission.runtime.AgentRuntime.status>`'s dict) as the
    ``MissionStatus`` message (an unknown state: ``MISSION_STATE_UNSPECIFIED``)."""
    d = dict(st)
    d["state"] = STATES.get(d["state"], agent_pb2.MISSION_STATE_UNSPECIFIED)
    return agent_pb2.MissionStatus(**d)


def summary_proto(s: MissionSummaryData) -> agent_pb2.MissionSummary:
    """A Finish summary as the ``MissionSummary`` message: its status, share, bytes, scores (None as ``has_*``
    False and 0), pushes, views and scoring protocols."""
    return agent_pb2.MissionSummary(
        status=status_proto(s.status), final_push_ok=s.final_push_ok, n_shared=s.n_shared,
        share_pct=s.share_pct, bytes_on_wire=s.bytes_on_wire, bytes_per_gaussian=s.bytes_per_gaussian,
        has_roi_psnr=s.roi_psnr is not None, roi_psnr=s.roi_psnr or 0.0, psnr=s.psnr or 0.0,
        seconds_per_frame=s.seconds_per_frame, has_roi_psnr_all_frames=s.roi_psnr_all_frames is not None,
        roi_psnr_all_frames=s.roi_psnr_all_frames or 0.0, frames_all=s.frames_all,
        total_upload_bytes=s.total_upload_bytes,
        final_subset_bytes=s.final_subset_bytes, view_bytes=s.view_bytes, views_sent=s.views_sent,
        views_unsent=s.views_unsent,
        tracked_views=views_proto(s.tracked_views), predicted_views=views_proto(s.predicted_views),
        pushes=[agent_pb2.PushInfo(version=p["version"], n_shared=p["n_shared"], n_total=p["n_total"],
                                   bytes_sent=p["bytes_on_wire"], delta=p["delta"], records=p["records"],
                                   removed=p["removed"], frames_mapped=p["frames_mapped"],
                                   unchanged=p.get("unchanged", False))
                for p in s.pushes],
        protocols={name: agent_pb2.ProtocolScore(
            has_roi_psnr=v.get("roi_psnr") is not None, roi_psnr=v.get("roi_psnr") or 0.0,
            psnr=v.get("psnr") or 0.0, ssim=v.get("ssim") or 0.0, frames_scored=int(v.get("frames_scored", 0)),
            roi_frames=int(v.get("roi_frames", 0)),
            roi_psnr_per_frame={int(k): float(x) for k, x in (v.get("roi_psnr_per_frame") or {}).items()})
            for name, v in s.protocols.items()})
