"""Scoring a mission's map at Finish (docs/realtime.md): the PSNR over the keyframes it kept, and for a replay the
final map over every frame of the sequence under each scoring protocol (``agent.scoring``,
:func:`gausslite.evaluation.score_live_map`); and :class:`MissionSummaryData`, what Finish returns.

Frames and poses are in the team's world frame; PSNR in dB.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, Iterable, List, Optional

import numpy as np

from gausslite.datasets.annotations import task_roi
from gausslite.mission.config import ScoringConfig
from gausslite.mission.share import select_shared

__all__ = ["MissionSummaryData", "score_kept_frames", "score_protocols", "summarise"]


@dataclass
class MissionSummaryData:
    """What :meth:`AgentRuntime.finish <gausslite.mission.runtime.AgentRuntime.finish>` returns (mirrors the
    ``MissionSummary`` message)."""

    status: dict
    final_push_ok: bool
    n_shared: int
    share_pct: float
    bytes_on_wire: int
    bytes_per_gaussian: float
    roi_psnr: Optional[float]
    psnr: Optional[float]
    seconds_per_frame: float
    roi_psnr_all_frames: Optional[float] = None
    frames_all: int = 0
    #: replays: the final map over the sequence under each scoring protocol (``agent.scoring``; docs/realtime.md):
    #: ``{protocol: {"roi_psnr", "psnr", "ssim", "frames_scored", "roi_frames"}}``
    protocols: dict = field(default_factory=dict)
    total_upload_bytes: int = 0
    final_subset_bytes: int = 0
    pushes: List[dict] = field(default_factory=list)
    #: the views sent for the fusion refinement (``agent.refine_views``): bytes on the wire, views sent, views unsent
    view_bytes: int = 0
    views_sent: int = 0
    views_unsent: int = 0
    #: replays: frame id → :class:`gausslite.evaluation.TrackedView` of each ``tracked`` / ``novel-tracked`` frame
    #: scored (its pose and exposure fitted against this map)
    tracked_views: dict = field(default_factory=dict)
    #: replays: frame id → :class:`gausslite.evaluation.TrackedView` of each ``novel`` frame scored: the pose and
    #: exposure this map predicts for it (a team map is scored at them)
    predicted_views: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        """JSON-ready dict (``tracked_views``, ``predicted_views``: frame id → ``{"c2w": 4 × 4 list, "exposure": 6
        floats}``)."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        for key in ("tracked_views", "predicted_views"):
            out[key] = {int(i): {"c2w": np.asarray(v.c2w).tolist(), "exposure": np.asarray(v.theta).tolist()}
                        for i, v in getattr(self, key).items()}
        return out


def score_kept_frames(mapper, frames: Iterable, annotations=None,
                      task_id: Optional[str] = None) -> tuple[Optional[float], Optional[float]]:
    """(full-image PSNR, ROI PSNR) in dB of ``mapper``'s map, mean over ``frames`` (mapped frames, rendered at their
    refined pose under ``pose_refine``, as ``map`` scores them); ROI PSNR is None without ``annotations`` and
    ``task_id`` or when no frame shows the ROI; both None without frames. Call while nothing maps."""
    # lazy: keeps gausslite.mission importable without Warp, torch
    from gausslite.evaluation import score_view

    ps, rps = [], []
    for fr in frames:
        out = mapper.render_frame(fr)
        roi = None
        if annotations is not None and task_id is not None:
            roi = annotations.roi_mask(task_id, fr.depth, fr.c2w, fr.intrinsics)
        s = score_view(out, fr, roi)
        ps.append(s.psnr)
        if not math.isnan(s.roi_psnr):
            rps.append(s.roi_psnr)
    return (float(np.mean(ps)) if ps else None, float(np.mean(rps)) if rps else None)


def score_protocols(mapper, dataset, annotations, task_id: str, scoring: ScoringConfig, factor: float, *,
                    protocols: Optional[Iterable[str]] = None, novel_ids: Optional[frozenset] = None,
                    estimated_poses: Optional[Dict[int, np.ndarray]] = None, record: Optional[dict] = None,
                    predicted: Optional[dict] = None) -> dict:
    """``mapper``'s map over every frame of the replayed ``dataset`` under the protocols of ``scoring`` (or
    ``protocols``): ``sensor`` always; ``keyframes``: the mapped keyframes at their refined pose and exposure;
    ``novel``: the withheld frames at the pose and exposure the map predicts for them, nothing fitted; ``tracked`` /
    ``novel-tracked``: every ``track_stride``-th / every withheld frame at a pose and exposure fitted against the
    frozen map (:func:`gausslite.evaluation.score_live_map`).

    Args:
        mapper: the mission's mapper (frozen while scoring: call while nothing maps).
        dataset: the replayed frames (world frame), scored at the mapping downscale ``factor``.
        annotations, task_id: the scene's annotations and the task whose ROI is scored.
        scoring: ``agent.scoring`` (protocols, ``track_iters``, ``track_stride``).
        novel_ids: the frame ids the replay withheld from the mapper; None: none (``novel`` and ``novel-tracked``
            are then left out).
        estimated_poses: frame id → (4, 4) float64 c2w the odometry estimated (``agent.pose_source: odometry``):
            every protocol starts from those poses, with the ROI of the given ones; a frame without one is not
            scored. None: the dataset's poses.
        record, predicted: filled with frame id → :class:`gausslite.evaluation.TrackedView` of the fitted and of the
            predicted views.
    Returns:
        ``{protocol: {"roi_psnr", "psnr", "ssim", "frames_scored", "roi_frames", "roi_psnr_per_frame",
        "psnr_per_frame"}}`` (dB; ROI PSNR over the frames that show the ROI, None when none does; per frame: frame
        id → dB).
    """
    # lazy: keeps gausslite.mission importable without Warp, torch
    from gausslite.datasets.subset import EstimatedPoses, ScaledFrames
    from gausslite.evaluation import score_live_map

    chosen = scoring.chosen() if protocols is None else tuple(protocols)
    if novel_ids is None:
        chosen = tuple(p for p in chosen if p not in ("novel", "novel-tracked"))
    # scored at the mapping resolution: the map's own detail, and minutes instead of tens of minutes at 640x480
    frames = ScaledFrames(dataset, factor)
    roi = task_roi(annotations, task_id)
    if estimated_poses is not None:
        # at the poses the odometry estimated, as the robot uses its map; the ROI from the given poses (the
        # image's ground truth); a frame whose tracking failed has no pose to be scored at
        frames = EstimatedPoses(frames, estimated_poses)
        roi = frames.roi_fn(annotations, task_id)
    return score_live_map(mapper, frames, roi, chosen, track_iters=scoring.track_iters,
                          track_stride=scoring.track_stride, novel_ids=novel_ids, record=record, predicted=predicted)


def summarise(status: dict, pusher, mapper, config, *, pushed: bool, psnr: Optional[float],
              roi_psnr: Optional[float], protocols: dict, frames_all: int, tracked_views: dict,
              predicted_views: dict) -> MissionSummaryData:
    """Finish's summary of a mission.

    Args:
        status: the mission's final status (``AgentRuntime.status()``: ``n_gaussians``, ``frames_mapped``,
            ``seconds_mapping`` are read from it).
        pusher: the mission's :class:`~gausslite.mission.pusher.Pusher` (pushes, bytes, views).
        mapper, config: the mission's mapper and ``AgentConfig`` (the share rule counts the shared Gaussians when
            nothing was pushed).
        pushed: Finish asked for the final push.
        psnr, roi_psnr: :func:`score_kept_frames`'s (dB, or None). protocols: :func:`score_protocols`'s (or {}).
        frames_all: frames in the replayed dataset (0: a streamed mission).
        tracked_views, predicted_views: frame id → ``TrackedView`` of the protocols' fitted and predicted views.
    """
    last = pusher.pushes[-1] if pusher.pushes else None
    n_gaussians = status["n_gaussians"]
    n_shared = last.n_shared if last else int(
        select_shared(mapper.gmap, config.share.rule, config.share.kappa_threshold).sum())
    return MissionSummaryData(
        status=status, final_push_ok=bool(pusher.final_push_ok and pushed),
        n_shared=int(n_shared), share_pct=100.0 * n_shared / max(n_gaussians, 1) if n_gaussians else 0.0,
        bytes_on_wire=pusher.final_subset_bytes,
        bytes_per_gaussian=(pusher.final_subset_bytes / last.n_shared) if last and last.n_shared else 0.0,
        roi_psnr=roi_psnr, psnr=psnr,
        seconds_per_frame=status["seconds_mapping"] / max(status["frames_mapped"], 1),
        roi_psnr_all_frames=protocols["sensor"]["roi_psnr"] if protocols else None, frames_all=frames_all,
        protocols=protocols,
        total_upload_bytes=pusher.total_upload_bytes, final_subset_bytes=pusher.final_subset_bytes,
        pushes=[dict(p.__dict__) for p in pusher.pushes], view_bytes=pusher.views.sent_bytes,
        views_sent=pusher.views.sent, views_unsent=pusher.views_unsent(), tracked_views=dict(tracked_views),
        predicted_views=dict(predicted_views))
