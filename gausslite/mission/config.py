"""Settings of an agent's mission (YAML section ``agent`` of a GaussLite configuration plus its ``mapper`` section;
``docs/live.md``, ``docs/sharing.md``)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Literal, Optional, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from gausslite.camera import check_rigid, nearest_rigid
from gausslite.datasets.bag import BagOptions
from gausslite.odometry.rgbd import OdometryConfig, PoseSource
from gausslite.mapping.config import MapperConfig, migrate_flat_names

__all__ = ["OnnxRelevanceConfig", "ScoringConfig", "FrameConfig", "ShareConfig", "PushConfig", "AgentConfig",
           "AgentSections", "OLD_AGENT_NAMES"]

#: tolerance of a T_world_map's rigidity check (orthonormal rotation, det +1, last row 0 0 0 1), as for frame poses
RIGID_ATOL = 1e-3


class ScoringConfig(BaseModel):
    """How a replayed mission's final map is scored over every frame of its sequence at Finish, and how the
    simulation scores the team's fused maps (``agent.scoring`` in YAML; docs/realtime.md#scoring-protocols).

    Attributes:
        protocols: which to score (``sensor`` is always scored: the summary's ``roi_psnr_all_frames``). At the pose
            the robot gives, with what the map learned: ``sensor`` (every frame at the sensor's pose with its
            keyframe's refined correction and exposure response), ``keyframes`` (the mapped keyframes at their refined
            pose and exposure) and ``novel`` (the frames a replay withholds from the mapper, every ``novel_every``-th,
            at the pose and exposure the map predicts for them, as ``sensor`` renders every frame: the map at the pose
            a robot would use, on views it never trained on). At a pose fitted to each frame against the map (how well
            a robot could localise against it, and the map from there): ``tracked`` (every ``track_stride``-th frame,
            MonoGS's protocol) and ``novel-tracked`` (the withheld frames).
        track_iters: Adam steps of the tracked protocols' tracker per frame (fixed, the same for every map).
        track_stride: the ``tracked`` protocol scores every this many frames (MonoGS: every 5th).
        novel_every: with ``novel`` or ``novel-tracked`` among the protocols, a replay withholds every this many
            frames from the mapper (never a keyframe, never a training view).
        track_fused: the simulation also fits each ``tracked`` / ``novel-tracked`` frame's pose against every fused
            map. Off, a fused map is scored under those protocols at the views its robot tracked against its own
            map (``tracked@own`` / ``novel-tracked@own``, render only): a robot localises against its own map, and a
            team map that holds task regions only tracks worse (docs/sharing.md#what-to-read-in-a-report).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    protocols: List[Literal["sensor", "keyframes", "novel", "tracked", "novel-tracked"]] = [
        "sensor", "keyframes", "novel", "tracked", "novel-tracked"]
    track_iters: int = Field(30, ge=0)
    track_stride: int = Field(5, ge=1)
    novel_every: int = Field(10, ge=2)
    track_fused: bool = False

    def chosen(self) -> tuple:
        """The protocols to score, ``sensor`` first and always."""
        return tuple(dict.fromkeys(["sensor", *self.protocols]))

    def withholds(self) -> bool:
        """Whether a replay withholds every ``novel_every``-th frame from the mapper (``novel`` or ``novel-tracked``
        is scored)."""
        return any(p in ("novel", "novel-tracked") for p in self.protocols)


class ResolutionConfig(BaseModel):
    """The mapping resolutions of a live agent (``agent.resolution`` in YAML; :mod:`gausslite.mapping.resolution`,
    docs/live.md#mapping-resolution): the image downscale at which a keyframe gets ``target_iters`` iterations
    under its budget (``mapper.keyframe_budget_s``), chosen from the first frame and corrected one level coarser at a
    time when keyframes fall short (finer again too with ``finer``); with the mapper's detail layer
    (``mapper.detail.enabled``) the
    task region's own, finer level, corrected from its ROI-phase iterations.

    Attributes:
        downscale: ``auto``, or a factor ≥ 1 that pins it (a user's choice, never changed; 1 = native).
        target_iters: iterations per keyframe to reach (the live TUM figures were measured at 12-23).
        max_downscale: the coarsest automatic level.
        min_width: an automatic level never maps images narrower than this (pixels).
        adapt_after: keyframes measured before each correction (the first keyframe is never counted).
        tolerance: a level holds while its keyframes get this share of ``target_iters``; below it, one level coarser.
        finer: take a finer level again when iterations recover (False, the default: after the first choice only
            ever coarser; measured on TUM fr1/rpy given at 640×480, docs/live.md#mapping-resolution: stepping finer
            mid-mission to native size left GaussLite's region no sharper and the whole image 0.7 dB lower).
        finer_share: one level finer when the iterations measured at this level, carried to the finer level by the
            work model (``mapper.work_cost``), reach this share of the target (taken as at least ``tolerance``).
        hold_keyframes: keyframes measured at a level before a finer step (doubled after a finer step that had to be
            undone).
        roi_downscale: the task region's level: ``auto`` (starts at native, follows its ROI iterations), or a factor
            ≥ 1 that pins it (never coarser than the background's).
        roi_target_iters: ROI-phase iterations per keyframe the region should get; None: ``target_iters`` × the ROI
            phase's share of a keyframe (1 − ``mapper.warmup_iters`` / ``mapper.iters_per_frame``).
        roi_ratio: an automatic region level stays at least this many times finer (linear) than a background that
            stepped down (never finer than native).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    downscale: Union[Literal["auto"], float] = "auto"
    target_iters: float = Field(10.0, ge=1)
    max_downscale: int = Field(4, ge=1, le=16)
    min_width: int = Field(160, ge=16)
    adapt_after: int = Field(5, ge=1)
    tolerance: float = Field(0.5, gt=0, le=1)
    finer: bool = False
    finer_share: float = Field(0.75, gt=0, le=4)
    hold_keyframes: int = Field(10, ge=1)
    roi_downscale: Union[Literal["auto"], float] = "auto"
    roi_target_iters: Optional[float] = Field(None, ge=1)
    roi_ratio: float = Field(2.0, ge=1)

    @model_validator(mode="after")
    def _check(self) -> "ResolutionConfig":
        for name in ("downscale", "roi_downscale"):
            v = getattr(self, name)
            if v != "auto" and float(v) < 1:
                raise ValueError(f"agent.resolution.{name} must be 'auto' or >= 1, got {v}")
        return self

    @property
    def pinned(self) -> Optional[float]:
        """The pinned factor, or None when automatic."""
        return None if self.downscale == "auto" else float(self.downscale)

    @property
    def roi_pinned(self) -> Optional[float]:
        """The task region's pinned factor, or None when automatic."""
        return None if self.roi_downscale == "auto" else float(self.roi_downscale)

    def roi_target(self, mapper: MapperConfig) -> float:
        """The task region's ROI-phase iterations per keyframe: ``roi_target_iters``, or ``target_iters`` × the ROI
        phase's share of a keyframe under ``mapper`` (at least 1)."""
        if self.roi_target_iters is not None:
            return float(self.roi_target_iters)
        share = 1.0 - mapper.warmup_iters / mapper.iters_per_frame
        return max(1.0, self.target_iters * share)

    def governor(self, mapper: MapperConfig):
        """A fresh :class:`~gausslite.mapping.resolution.ResolutionGovernor` of these settings, with ``mapper``'s work
        model (``mapper.work_cost``) and the region's target (:meth:`roi_target`)."""
        # lazy: keeps gausslite.mission.config importable without OpenCV
        from gausslite.mapping.budget import WorkCost
        from gausslite.mapping.resolution import ResolutionGovernor

        return ResolutionGovernor(self.target_iters, self.max_downscale, self.pinned, self.adapt_after,
                                  WorkCost(**mapper.work_cost.model_dump()), self.min_width, self.tolerance,
                                  finer=self.finer, finer_share=self.finer_share, hold_keyframes=self.hold_keyframes,
                                  roi_target_iters=self.roi_target(mapper), roi_pinned=self.roi_pinned,
                                  roi_ratio=self.roi_ratio)


class RefineViewsConfig(BaseModel):
    """The views an agent sends for the fusion server's joint refinement (``agent.refine_views`` in YAML;
    :mod:`gausslite.fusion.views`, docs/sharing.md#the-views-the-refinement-fits).

    Attributes:
        crop: send the crop around the task ROI of each keyframe (``margin_px`` around the ROI's box) instead of
            the whole keyframe: the refinement fits ROI pixels only, so a crop carries what it needs in a fraction
            of the bytes. A keyframe without ROI pixels is then not sent.
        margin_px: pixels around the ROI's bounding box in a crop.
        between: a live mission also offers crops of the frames it sees between keyframes (their ROI is the
            keyframe's carried over by depth, :func:`gausslite.fusion.views.region_points`); every ``between_every``-th
            of them.
        between_every: see ``between``.
        budget_ratio: the bytes of all views sent over a mission are at most this multiple of the latest shared
            subset's bytes (:class:`gausslite.fusion.views.ViewBudget`; the farthest views first when it is short);
            null = no bound.
        min_roi_px: a view whose ROI has fewer pixels is not offered.
        reserve: share of the budget held back until the mission's final push, where it buys the waiting views
            farthest from those sent, chosen over the whole mission (:class:`gausslite.fusion.views.ViewBudget`);
            0 = spend it as views arrive. Waiting views are bounded by ``upload_backlog_max``.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    crop: bool = True
    margin_px: int = Field(8, ge=0)
    between: bool = True
    between_every: int = Field(2, ge=1)
    budget_ratio: Optional[float] = Field(8.0, gt=0)
    min_roi_px: int = Field(64, ge=1)
    reserve: float = Field(0.0, ge=0, lt=1)


class FrameConfig(BaseModel):
    """Where this robot's poses sit in the team's world frame (``agent.frame`` in YAML; docs/team.md). The fusion
    server votes per voxel in the coordinates it receives and aligns nothing, so every robot of a team gives its
    Gaussians, keyframes and task regions in one world frame.

    Attributes:
        T_world_map: the fixed rigid transform from this robot's own map (or odometry) frame into the team's world
            frame (REP 103/105 naming: it maps points given in ``map`` into ``world``), as a 4 × 4 matrix of four rows
            (row-major; rotation block and translation in metres; last row ``[0, 0, 0, 1]``). Every frame's pose
            becomes ``T_world_map @ c2w`` before mapping, and the scene annotations' boxes go through the same
            transform. Null (default): the robot's map frame is the world frame. A ``StartMission`` may override it
            per mission (``StartMissionRequest.T_world_map``).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    T_world_map: Optional[List[List[float]]] = None

    @field_validator("T_world_map")
    @classmethod
    def _rigid(cls, v: Optional[List[List[float]]]) -> Optional[List[List[float]]]:
        if v is None:
            return v
        if len(v) != 4 or any(len(row) != 4 for row in v):
            raise ValueError(f"T_world_map must be a 4 x 4 matrix given as four rows of four numbers, got "
                             f"{len(v)} rows of {[len(row) for row in v]} numbers")
        check_rigid(np.asarray(v, np.float64), atol=RIGID_ATOL, what="T_world_map")
        return [[float(x) for x in row] for row in v]

    def matrix(self) -> Optional[np.ndarray]:
        """``T_world_map`` as a (4, 4) float64 array whose rotation block is the nearest proper rotation to the one
        given (the setting is rigid within 1e-3; the projection keeps every transformed pose exactly rigid), or
        None when unset (identity)."""
        if self.T_world_map is None:
            return None
        return nearest_rigid(self.T_world_map, "T_world_map", max_drift=RIGID_ATOL)


class OnnxRelevanceConfig(BaseModel):
    """ONNX attention backends of the agent (``agent.onnx`` in YAML; paper Sec. III-B).

    Attributes:
        detector_path: Grounding-DINO-style ``.onnx`` (:class:`gausslite.attention.OnnxGroundingDetector`).
        vocab_path: its BERT WordPiece ``vocab.txt``.
        segmenter_path: FastSAM / YOLOv8-seg ``.onnx`` (:class:`gausslite.attention.OnnxFastSAMSegmenter`).
        box_threshold, text_threshold: detector thresholds (paper 0.20 / 0.25).
        seg_conf, seg_iou: segmenter candidate score and NMS IoU thresholds (paper 0.4 / 0.9).
        threads: ONNX Runtime intra-op threads of each model (None: one per core; docs/perception.md).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    detector_path: Optional[str] = None
    vocab_path: Optional[str] = None
    segmenter_path: Optional[str] = None
    box_threshold: float = Field(0.20, ge=0, le=1)
    text_threshold: float = Field(0.25, ge=0, le=1)
    seg_conf: float = Field(0.4, ge=0, le=1)
    seg_iou: float = Field(0.9, ge=0, le=1)
    threads: Optional[int] = Field(None, ge=1)

    def missing(self) -> List[str]:
        """What is missing for the ONNX backend: unset options and files that do not exist."""
        out = []
        for name in ("detector_path", "vocab_path", "segmenter_path"):
            v = getattr(self, name)
            if not v:
                out.append(f"agent.onnx.{name} is not set")
            elif not Path(v).is_file():
                out.append(f"agent.onnx.{name} {v} does not exist")
        return out


class ShareConfig(BaseModel):
    """What an agent shares and where the work runs (``agent.share`` in YAML; :mod:`gausslite.sharing`,
    docs/sharing.md#the-shared-subset). The defaults are the measured settings.
    :func:`gausslite.sharing.select_task_subset` takes the selection's fields (``kappa_threshold`` to ``held_weight``;
    it is a :class:`gausslite.sharing.ShareRule`).

    Attributes:
        rule: which Gaussians are pushed: ``active`` (a = 1), ``kappa`` (κ >= ``kappa_threshold``) or ``task`` (a = 1
            and κ >= ``kappa_threshold`` inside the task's 3D region, compacted by ROI contribution:
            :func:`gausslite.sharing.select_task_subset`).
        kappa_threshold: minimum κ of a shared Gaussian (``kappa``, and with ``a = 1`` for ``task``).
        region_voxel_m: voxel size of the task region (metres).
        region_dilate: dilation of the task region in voxels (26-neighbourhood per step).
        min_opacity: Gaussians below this opacity are not shared (near-transparent).
        coverage: keep the fewest Gaussians (by decreasing ROI contribution) carrying this fraction of the total ROI
            blending weight; 1.0 keeps every Gaussian with a positive contribution.
        candidates: ``active`` (the paper's a = 1 and κ inside the task region, then compaction) or ``rendered``
            (every Gaussian that draws the ROI competes in the compaction, whatever its flag: what a map fitted with
            ``mapper.roi_update: visible`` needs, where inactive Gaussians render the task region too).
        max_fraction: at most this fraction of the map is shared (largest ROI contribution first); null = no bound.
            A bandwidth bound for maps still being trained, where a coverage rule alone keeps many small,
            overlapping Gaussians.
        held_weight: the rows the fusion server holds rank with their ROI contribution times this (>= 1), so a
            bounded subset keeps them rather than trading rows of nearly equal contribution at every push, each of
            which a delta push must carry (1 = off).
        finetune_iters: ``rule: task``: before each push, fine-tune a copy of the shared subset rendered alone on
            the ROI keyframes for this many iterations (:func:`gausslite.sharing.finetune_subset`; 0 = push the map's
            rows as they are). The agent's own map is untouched, so it can map with ``roi_render: context`` (its best
            own map) and still share a subset that renders the ROI on its own.
        refresh: with fine-tuning and delta pushes: share of the rows the server already holds that one push may
            change (:func:`gausslite.sharing.update_shared_subset`); the others stay as the server has them, so a
            delta carries the new rows and this share of the old ones. 1 = every row may move at every push (each
            delta re-sends about the whole subset).
        outside_alpha: with fine-tuning: weight of the fine-tune's penalty on the subset's alpha outside the ROI of
            each keyframe (``mapper.roi_outside_alpha`` of the fine-tune), so the subset draws its ROI and nothing
            beside it, where other robots' regions lie in a fused map (0 = off).
        worker: where ``rule: task`` selection and fine-tuning run: ``process`` (a worker process of its own, at
            ``agent.push.nice``: no interpreter lock shared with mapping, which a thread of the agent's process
            would hold against the mapping thread) or ``thread`` (the pusher thread itself).
        worker_start: when the worker process starts: ``first_push`` or ``mission`` (with the mission, warmed up, so
            a short mission's periodic subsets reach the server while it maps; an every-frame mission's then at the
            mapper's priority). Measured, ``mission`` makes the team map worse: early pushes fix young rows on the
            server, and ``refresh`` lets later pushes move only a share of them (room0 sim vote −5 dB, live
            synthetic team vote −0.6 to −1.8 dB; docs/sharing.md#how-much-to-share).

    Raises:
        pydantic.ValidationError (a ValueError): a value outside its range, e.g. ``max_fraction`` outside (0, 1] or
            ``held_weight`` < 1.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    rule: Literal["active", "kappa", "task"] = "task"
    kappa_threshold: int = Field(1, ge=0)
    region_voxel_m: float = Field(0.05, gt=0)
    region_dilate: int = Field(1, ge=0)
    min_opacity: float = Field(0.02, ge=0, le=1)
    coverage: float = Field(0.99, gt=0, le=1)
    candidates: Literal["active", "rendered"] = "rendered"
    max_fraction: Optional[float] = Field(0.25, gt=0, le=1)
    held_weight: float = Field(1.0, ge=1)
    finetune_iters: int = Field(200, ge=0)
    refresh: float = Field(0.05, ge=0, le=1)
    outside_alpha: float = Field(0.0, ge=0)
    worker: Literal["process", "thread"] = "process"
    worker_start: Literal["first_push", "mission"] = "first_push"


class PushConfig(BaseModel):
    """When and how an agent pushes its shared subset to the fusion server (``agent.push`` in YAML; docs/live.md,
    docs/sharing.md#how-a-push-travels). The defaults are the measured settings.

    Attributes:
        every: push a subset every this many mapped frames (and always at the end).
        delta: push only the Gaussians new or changed beyond quantisation since the version the server
            acknowledged, plus the removed rows (wire delta chunks); a full upload when the server lacks the base
            (FAILED_PRECONDITION) or the delta would not be smaller.
        delta_tolerance: multiple of one code step that counts as "changed" (:mod:`gausslite.wire.delta`).
        final_timeout_s: retry the final push for up to this many seconds (a fusion-server restart).
        backoff_s, max_backoff_s: exponential backoff between retries of a push (seconds); a periodic push is retried
            until acknowledged or replaced by a newer snapshot (no give-up: the link may be down for minutes), the
            final one up to ``final_timeout_s``.
        nice: scheduling niceness of the pusher thread and of the share worker (Linux; 0 = the mapper's own
            priority): at 19 the kernel gives mapping the cores whenever both want them (docs/realtime.md). Live
            missions only: an every-frame mission's share worker runs at the mapper's priority (docs/sharing.md).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    every: int = Field(5, ge=1)
    delta: bool = True
    delta_tolerance: float = Field(1.0, ge=0)
    chunk_gaussians: int = Field(20000, ge=1)
    final_timeout_s: float = Field(120.0, gt=0)
    backoff_s: float = Field(0.2, gt=0)
    max_backoff_s: float = Field(5.0, gt=0)
    nice: int = Field(19, ge=0, le=19)


#: agent settings renamed so that each name says what it bounds and means one thing across the configuration tree:
#: old key → new key, dotted within the ``agent`` section (the odometry's settings included; AgentConfig migrates them
#: with :func:`gausslite.mapping.config.migrate_flat_names`, which warns; docs/reference.md#old-setting-names)
OLD_AGENT_NAMES: dict[str, str] = {
    "keyframe_every": "upload_keyframe_every",
    "max_keyframes": "upload_backlog_max",
    "odometry.max_keyframes": "odometry.reference_keyframes_max",
    "odometry.loop.max_keyframes": "odometry.loop.keyframe_images_max",
    # the share rule given as the value of ``share`` itself (a rule name, not a section)
    "share": "share.rule",
    "kappa_threshold": "share.kappa_threshold",
    "share_coverage": "share.coverage",
    "share_candidates": "share.candidates",
    "share_max_fraction": "share.max_fraction",
    "share_held_weight": "share.held_weight",
    "share_finetune_iters": "share.finetune_iters",
    "share_refresh": "share.refresh",
    "share_outside_alpha": "share.outside_alpha",
    "share_worker": "share.worker",
    "share_worker_start": "share.worker_start",
    "push_every": "push.every",
    "delta_push": "push.delta",
    "delta_tolerance": "push.delta_tolerance",
    "chunk_gaussians": "push.chunk_gaussians",
    "final_push_timeout_s": "push.final_timeout_s",
    "backoff_s": "push.backoff_s",
    "max_backoff_s": "push.max_backoff_s",
    "pusher_nice": "push.nice",
}


class AgentConfig(BaseModel):
    """Agent mission settings (YAML section ``agent`` plus the mapper section ``mapper``).

    Attributes:
        relevance: ``attention`` (task graph grounded by the attention front-end with the scene's offline
            annotation backend, paper Sec. III-B) or ``gt`` (ground-truth ROI of ``task_id``, for ablations).
        share: what is pushed and where its selection and fine-tune run (:class:`ShareConfig`: the share rule,
            its coverage and bound, the fine-tune, the share worker).
        push: when and how it is pushed (:class:`PushConfig`: every how many frames, delta pushes, retries, the
            pusher's niceness).
        downscale, max_frames, stride: applied to replayed datasets (``load_dataset``).
        bag: ROS bag options (topics, frames, tolerances; ``gausslite.datasets.bag.BagOptions``) for a
            replayed bag, e.g. ``agent.bag.rgb_topic=/camera/color/image_raw``; ignored for folders.
        queue_size: frames buffered between the stream and the mapping worker.
        upload_keyframe_every: every k-th mapped keyframe is uploaded (as a refinement view) for the fusion
            refinement.
        upload_backlog_max: at most this many refinement views wait for upload (the oldest dropped first while the
            link is down; ``GetStatus``'s ``keyframes_backlog``).
        jpeg_quality: keyframe JPEG quality on the wire (``keyframe_format: jpeg``).
        keyframe_format: ``png`` (lossless colour, the default: the fusion refinement fits the uploaded
            colours; measured: docs/results.md) or ``jpeg``.
        attention_rendered_depth: give the attention front-end the depth rendered from the current map.
        eval_max_frames: frames kept for the ROI PSNR of the Finish summary.
        ingest: streamed frames go through keyframe selection with a one-frame pending slot and never
            block the sender (``keyframes``, :mod:`gausslite.mapping.keyframes`), or are all queued and
            mapped with back-pressure (``every_frame``, the offline behaviour; non-realtime replays always
            map every frame).
        keyframe_translation_m, keyframe_rotation_deg, keyframe_max_interval_s: keyframe rule
            (:class:`gausslite.mapping.keyframes.KeyframeRule`; None interval = never).
        idle_optimize: with keyframe ingest, keep optimising over the stored keyframes (MVO) while no
            keyframe is pending, in chunks of ``idle_chunk_s`` seconds (a new keyframe waits at most one chunk).
        realtime: replays send frames at the dataset's clock (frame timestamps scaled by ``1 / rate``)
            through keyframe ingest instead of mapping every frame; ``fps``: clock of Replica / 7-Scenes
            replays (frame index / fps; default the loader's 30 Hz).
        checkpoint_every: with a data dir, write the mission checkpoint every this many mapped keyframes
            (0 = never).
        final_pass_s: at Finish, the mapper's final pass over every keyframe (``mapper.final_iters`` +
            ``mapper.final_iters_per_keyframe`` × keyframes; the hand-held profile sets 20 per keyframe) stops
            after this many seconds, so a long mission's Finish stays bounded.
        relevance_backend: where the attention front-end's detector/segmenter come from: ``annotation``
            (the scene's ``objects.json``), ``onnx`` (models in ``onnx``) or ``onnx_cost`` (timing experiments:
            the models in ``onnx`` run on every call for their compute time, the relevance comes from
            ``objects.json``; :mod:`gausslite.attention.timing`).
        onnx: ONNX detector/segmenter paths and thresholds (``relevance_backend: onnx``).
        relevance_max_wait_s: null = relevance runs in the mapping thread before each keyframe (its whole latency
            counts in the keyframe budget); a number = relevance runs in a thread of its own and a keyframe waits at
            most this many seconds for its mask, then maps with the newest earlier mask re-projected into it
            (:class:`gausslite.attention.worker.RelevanceWorker`; the front-end then uses the sensor depth, not the
            map's rendered depth, since the map is being optimised meanwhile).
        scoring: how Finish scores a replayed mission's final map over every frame (:class:`ScoringConfig`; also
            the protocols the simulation scores the fused maps under).
        resolution: the live mapping resolution (:class:`ResolutionConfig`).
        refine_views: the views sent for the fusion refinement (:class:`RefineViewsConfig`): ROI crops, frames
            between keyframes, the byte budget.
        frame: this robot's map frame in the team's world frame (:class:`FrameConfig`, ``frame.T_world_map``).
        pose_source: a :data:`~gausslite.odometry.rgbd.PoseSource`: ``given`` (each frame's own pose) or
            ``odometry``: every streamed or replayed frame is tracked by RGB-D odometry
            (:mod:`gausslite.odometry.rgbd`) as it arrives, beside the mapper; the keyframe selection uses the
            estimate, and a frame whose tracking fails is logged, counted (``frames_rejected``) and not mapped; the
            tracker's state is saved with the mission's checkpoint.
        odometry: the odometry's settings (:class:`~gausslite.odometry.rgbd.OdometryConfig`).
        mapper: the mapper configuration (default mode ``gausslite``).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    relevance: Literal["attention", "gt"] = "attention"
    share: ShareConfig = ShareConfig()
    push: PushConfig = PushConfig()
    downscale: float = Field(2.0, ge=1.0)
    max_frames: Optional[int] = Field(None, ge=1)
    stride: int = Field(1, ge=1)
    bag: BagOptions = BagOptions()
    queue_size: int = Field(4, ge=1)
    upload_keyframe_every: int = Field(1, ge=1)
    upload_backlog_max: int = Field(64, ge=1)
    jpeg_quality: int = Field(95, ge=1, le=100)
    keyframe_format: Literal["png", "jpeg"] = "png"
    attention_rendered_depth: bool = True
    eval_max_frames: int = Field(200, ge=1)
    ingest: Literal["keyframes", "every_frame"] = "keyframes"
    keyframe_translation_m: float = Field(0.05, gt=0)
    keyframe_rotation_deg: float = Field(5.0, gt=0)
    keyframe_max_interval_s: Optional[float] = Field(1.0, gt=0)
    idle_optimize: bool = True
    idle_chunk_s: float = Field(0.25, gt=0)
    realtime: bool = False
    rate: float = Field(1.0, gt=0)
    fps: Optional[float] = Field(None, gt=0)
    checkpoint_every: int = Field(5, ge=0)
    final_pass_s: float = Field(60.0, gt=0)
    relevance_backend: Literal["annotation", "onnx", "onnx_cost"] = "annotation"
    onnx: OnnxRelevanceConfig = OnnxRelevanceConfig()
    relevance_max_wait_s: Optional[float] = Field(None, ge=0)
    scoring: ScoringConfig = ScoringConfig()
    resolution: ResolutionConfig = ResolutionConfig()
    refine_views: RefineViewsConfig = RefineViewsConfig()
    frame: FrameConfig = FrameConfig()
    pose_source: PoseSource = "given"
    odometry: OdometryConfig = OdometryConfig()
    mapper: MapperConfig = MapperConfig(mode="gausslite")

    @model_validator(mode="before")
    @classmethod
    def _renamed_settings(cls, data):
        """Old names of renamed settings to their new keys (:data:`OLD_AGENT_NAMES`; ``migrate_flat_names`` warns).
        ``share`` is an old name only when its value is a rule name (``share: task`` → ``share.rule: task``)."""
        if not isinstance(data, dict):
            return data
        if isinstance(data.get("share"), str):
            # first, so that the old flat share_* names then move into the section it becomes
            return migrate_flat_names({"share": data["share"], **data}, OLD_AGENT_NAMES, "agent")
        return migrate_flat_names(data, {k: v for k, v in OLD_AGENT_NAMES.items() if k != "share"}, "agent")


class AgentSections(BaseModel):
    """The ``agent`` and ``mapper`` sections of a GaussLite YAML file. In YAML the mapper is a top-level section;
    here it is ``agent.mapper``, the agent's copy, which the YAML's ``mapper`` section sets. The whole file's
    tree, :class:`gausslite.config.GaussLiteConfig`, extends this with its other sections."""

    model_config = ConfigDict(extra="forbid")
    agent: AgentConfig = AgentConfig()

    @model_validator(mode="before")
    @classmethod
    def _mapper_into_agent(cls, data):
        if isinstance(data, dict) and "mapper" in data:
            data = dict(data)
            mapper = data.pop("mapper")
            agent = dict(data.get("agent") or {})
            if mapper is not None:
                if not isinstance(mapper, MapperConfig):
                    mapper = MapperConfig.model_validate({"mode": "gausslite", **dict(mapper)})
                agent["mapper"] = mapper
            data["agent"] = agent
        return data

    @property
    def mapper(self) -> MapperConfig:
        """The mapper section."""
        return self.agent.mapper

