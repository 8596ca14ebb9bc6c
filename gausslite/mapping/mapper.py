"""Online mapper with known poses: uniform baseline and task-conditioned GaussLite.

Per mapped frame (paper Sec. III-C/III-D):
1. seeding: the current map is rendered at the new frame; only the pixels it does not explain
   (SplaTAM Eq. 9: silhouette < 0.5 or new geometry in front, ``coverage_seeding``) are candidates,
   and the seed count is N × their share of the valid pixels. Within that pool: uniform, or SB/SIS/GFD
   with a relevance map w; initial scale log(s0·m) with s0 the local median nearest-neighbour
   distance. The Gaussian budget follows the observed scene (``budget_mode='scene'``: Gaussians per
   observed coarse voxel, hard-capped); at the budget new seeds replace the Gaussians with the lowest
   accumulated alpha-blending weight over the keyframes that saw them, ROI Gaussians protected;
2. a fixed number of Adam iterations; each iteration's view is drawn from the recent window or from
   the whole mission's keyframes (:class:`~gausslite.mapping.memory.KeyframeStore`; MVO weights the
   mission-wide draw towards keyframes that see the ROI; without MVO the current frame is taken with
   probability ``current_frame_prob``); loss L1_colour + λ_d L1_depth + λ_s (1 − SSIM); for hand-held
   sensors the rendered view carries the keyframe's exposure response (``exposure_comp``,
   :mod:`~gausslite.mapping.exposure`), the camera's motion blur (``motion_blur``,
   :mod:`~gausslite.mapping.blur`) and its rolling shutter (``rolling_shutter_s``,
   :mod:`~gausslite.mapping.shutter`);
3. ROI: after ``warmup_iters`` full-image iterations (under a keyframe time budget: the first
   ``warmup_iters / iters_per_frame`` of the time), the rest update only active Gaussians with
   colour/depth/SSIM restricted to ROI ∩ rendered footprint, rendering only the ROI's bounding box
   (``roi_render``: the active subset alone, the paper's wording; or every Gaussian with the
   inactive ones frozen; or the two in turn); κ += 1 per active iteration for every active Gaussian. Live agents
   fit every Gaussian the ROI crop draws instead (``roi_update='visible'``, docs/realtime.md), and under a time
   budget the clock is wall time or its deterministic twin (``budget_clock``, :mod:`gausslite.mapping.budget`);
4. standard 3DGS clone/split/prune every ``densify.every`` iterations, under the global budget; the
   view-space gradient statistics come from full-image iterations only (``densify.active_phase_stats``).

With ``detail.enabled`` and a :class:`~gausslite.mapping.detail.DetailView` (the same keyframe at a finer resolution),
the task region has its own resolution in the one map (:mod:`gausslite.mapping.detail`): the keyframe keeps a detail
crop of the region, ROI-phase iterations fit it instead of the coarse crop, the region's seeds and ROI views come from
the finer pixels.

Before seeding, under ``pose.track_iters`` a new keyframe is placed against the frozen map
(:class:`~gausslite.mapping.tracking.FrameTracker`). Every Gaussian records the mapped frame that seeded it (its
keyframe anchor, :attr:`GaussianModel.anchors <gausslite.mapping.model.GaussianModel.anchors>`), so that
:meth:`Mapper.apply_pose_corrections` can move it with its keyframe when a pose graph corrects the poses.

The mapper does not care where w came from (ground truth or the attention front-end).

Parts (gsplat style; each with its own ``state_dict`` / ``load_state_dict``, gathered by :meth:`Mapper.state_dict`):

- :class:`~gausslite.mapping.model.GaussianModel`: the parameters, κ, task flags, stable ids and Adam;
- :class:`~gausslite.mapping.strategy.DensityStrategy`: budget, eviction and density control;
- :class:`~gausslite.mapping.sensor.SensorRenderer`: the map rendered as the sensor took a view (exposure,
  motion blur, rolling shutter);
- :class:`~gausslite.mapping.step.TrainStep`: one Adam iteration on one view (``mapper.step``);
- :class:`~gausslite.mapping.memory.KeyframeStore`, :class:`~gausslite.mapping.poses.PoseRefiner`;
- :class:`~gausslite.mapping.seeder.FrameSeeder`: seeding one frame (``mapper.seeder``; it keeps no state).

:class:`Mapper` coordinates them: :meth:`~Mapper.map_frame` (place the keyframe, seed, store, then iterate under an
iteration count or a time budget), :meth:`~Mapper.optimize` (between keyframes) and :meth:`~Mapper.finalize`; the
iterations themselves (how many, on which view, in which phase) are :mod:`gausslite.mapping.iterations`'.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Mapping, Optional

import numpy as np
import torch

from gausslite.datasets.base import Frame
from gausslite.gaussians import GaussianMap
from gausslite.mapping.alignment import AlignResult, KeyframeAligner
from gausslite.mapping.budget import WallClock, WorkClock, WorkCost
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.detail import DetailCrop, DetailView, check_detail, cut_detail, detail_pad, detail_scale
from gausslite.mapping.iterations import between_keyframes, final_pass, keyframe_iterations
from gausslite.mapping.memory import KeyframeStore
from gausslite.mapping.model import GaussianModel
from gausslite.mapping.poses import PoseRefiner, correction_moves
from gausslite.mapping.roi_views import RoiViewStore, project_roi, roi_view_of, window_points
from gausslite.mapping.seeder import FrameSeeder, SeedStats
from gausslite.mapping.sensor import SensorRenderer
from gausslite.mapping.step import TrainStep
from gausslite.mapping.strategy import DensityStrategy
from gausslite.mapping.tracking import FrameTracker, TrackResult
from gausslite.mapping.views import Keyframe, keyframe_from_frame, roi_box
from gausslite.render import RenderOutput

__all__ = ["FrameStats", "Mapper", "SeedStats"]


@dataclass
class FrameStats:
    """What one ``map_frame`` call did (for logs and metrics.json)."""

    frame_id: int
    seconds: float
    n_seeds: int
    n_roi_seeds: int
    n_gaussians: int
    loss: float
    active_iters: int
    densify: dict = field(default_factory=dict)
    iters: int = 0  #: Adam iterations of this call (iters_per_frame, or what fit the time budget)
    unexplained: float = 1.0  #: share of valid pixels the map did not explain before seeding
    budget: int = 0  #: Gaussian budget in force after this frame
    n_evicted: int = 0  #: existing Gaussians replaced by this frame's seeds at the budget
    n_adopted: int = 0  #: existing Gaussians that joined the task in this frame (``seeding.adopt``)
    n_gap_seeds: int = 0  #: ROI seeds on relevant pixels the task's Gaussians left uncovered
    track_iters: int = 0  #: keyframe placement: Adam steps of the frame-to-map tracker (``pose.track_iters``)
    #: keyframe placement: the tracked pose was kept (None: not tracked; False: no coverage, or the gate rejected it)
    track_accepted: Optional[bool] = None
    track_rot_deg: float = 0.0  #: keyframe placement: the tracked correction's rotation, degrees (rejected or not)
    track_trans_m: float = 0.0  #: keyframe placement: the tracked correction's translation, metres
    detail_px: int = 0  #: pixels (w × h) of the detail crop the keyframe stored (``detail``; 0: none)
    #: keyframe alignment (``pose.align``): the aligned pose was kept (None: not aligned; False: the gates rejected it)
    align_accepted: Optional[bool] = None
    align_fitness: float = 0.0  #: keyframe alignment: share of the keyframe's sampled points with a correspondence
    align_rot_deg: float = 0.0  #: keyframe alignment: the correction's rotation from its start pose, degrees
    align_trans_m: float = 0.0  #: keyframe alignment: the correction's translation, metres
    align_s: float = 0.0  #: keyframe alignment: wall time, seconds
    n_active: int = 0  #: task Gaussians (``active``) after this frame
    active_scale_m: float = 0.0  #: their median largest-axis standard deviation, metres (0: none)


class Mapper:
    """The online mapper (one global map, known poses).

    Args:
        cfg: mapper configuration (mode, budgets, switches, learning rates).
    Attributes:
        model: the Gaussians (:class:`~gausslite.mapping.model.GaussianModel`).
        strategy: budget, eviction and density control (:class:`~gausslite.mapping.strategy.DensityStrategy`).
        sensor: the sensor renderer (:class:`~gausslite.mapping.sensor.SensorRenderer`).
        step: one Adam iteration on one view, ``mapper.step(view, active_phase=...)``
            (:class:`~gausslite.mapping.step.TrainStep`).
        seeder: seeds a frame (:class:`~gausslite.mapping.seeder.FrameSeeder`).
        keyframes: every keyframe of the mission, compact and bounded (MVO draws from it).
        poses: per-keyframe pose corrections (refined under ``cfg.pose.refine``, set by keyframe placement under
            ``cfg.pose.track_iters`` and by :meth:`apply_pose_corrections`); None while none of them is on.
        tracker: keyframe placement against the frozen map (:class:`~gausslite.mapping.tracking.FrameTracker`).
        input_poses: frame id → (4, 4) float64 pose each mapped frame came with (the anchors of
            :meth:`apply_pose_corrections`).
        clock: clock of the keyframe budget and the idle/final time bounds (wall time, or its deterministic twin).
        stats: one :class:`FrameStats` per :meth:`map_frame` call.
    """

    def __init__(self, cfg: MapperConfig) -> None:
        self.cfg = cfg
        self.device = torch.device(cfg.device)
        if cfg.performance.torch_threads:
            torch.set_num_threads(cfg.performance.torch_threads)  # process-wide (PerformanceConfig.torch_threads)
        self.model = GaussianModel(cfg.lr, self.device)
        self.rng = np.random.default_rng(cfg.seed)
        self.clock = (WorkClock(WorkCost(**cfg.work_cost.model_dump())) if cfg.budget_clock == "work"
                      else WallClock())
        self.torch_gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
        self.keyframes = KeyframeStore(cfg.stored_keyframes_max, protect_recent=cfg.window,
                                       max_detail_bytes=cfg.detail.max_bytes)
        # the per-keyframe corrections: refined with the map (pose.refine), set by keyframe placement
        # (pose.track_iters), or by a pose graph (apply_pose_corrections)
        self.poses: Optional[PoseRefiner] = (self._new_pose_record() if cfg.pose.refine or cfg.pose.track_iters
                                             or cfg.pose.align != "off" else None)
        pc = cfg.pose
        #: keyframe alignment to the depth of the keyframes before it (``pose.align``), or None
        self.aligner: Optional[KeyframeAligner] = (
            KeyframeAligner(pc.align_voxel_m, pc.align_width, pc.align_min_fitness, pc.track_max_trans_m,
                            pc.track_max_rot_deg, max_keyframes=pc.align_max_keyframes)
            if pc.align != "off" else None)
        #: frame id → (4, 4) float64 pose each mapped frame came with (before any correction), the anchor frames
        self.input_poses: dict[int, np.ndarray] = {}
        #: ROI crops of the frames between keyframes (``roi_views``), drawn by ROI-phase iterations
        self.roi_views = RoiViewStore(cfg.roi_views.max_views, cfg.roi_views.max_bytes)
        self.strategy = DensityStrategy(cfg, self.model, self.torch_gen)
        self.sensor = SensorRenderer(cfg, self.model, self.clock)
        self.tracker = FrameTracker(cfg, self.sensor, self.clock)
        self.step = TrainStep(cfg, self.model, self.sensor, self.strategy, self.keyframes,
                              self.poses if cfg.pose.refine else None, self.clock, self.rng, views=self.roi_views)
        self.seeder = FrameSeeder(cfg, self.model, self.strategy, self.sensor, self.rng)
        self.n_mapped = 0
        self.stats: list[FrameStats] = []
        self.n_idle_iters = 0  # iterations of optimize() between keyframes
        #: iterations of time-budgeted map_frame calls (their density-control schedule spans calls)
        self.n_budget_iters = 0

    def _new_pose_record(self) -> PoseRefiner:
        pc = self.cfg.pose
        return PoseRefiner(pc.lr_rot, pc.lr_trans, pc.between_keyframes == "interpolate")

    @property
    def window(self) -> list[Keyframe]:
        """The ``cfg.window`` newest keyframes, as float tensors on the mapper's device."""
        n = len(self.keyframes)
        return [self.keyframes.load(i, self.device) for i in range(max(0, n - self.cfg.window), n)]

    # ------------------------------------------------------------------ map access
    @property
    def gmap(self) -> GaussianMap:
        """Detached snapshot of the current map."""
        return self.model.to_map()

    @property
    def budget(self) -> Optional[int]:
        """Gaussian budget in force (``max_gaussians``, or the scene/image rule; see MapperConfig)."""
        return self.strategy.budget

    def render(self, c2w: torch.Tensor | np.ndarray, K: torch.Tensor | np.ndarray, width: int, height: int,
               subset: Optional[torch.Tensor] = None) -> RenderOutput:
        """Render the current map (no gradients) from a camera-to-world pose ``c2w`` (4,4), intrinsics ``K`` (3,3)
        pixels, at ``width`` × ``height``; ``subset`` (N,) bool or int64 rows (None: all)."""
        with torch.no_grad():
            return self.sensor.rasterize(c2w, K, width, height, subset)

    def render_frame(self, frame: Frame) -> RenderOutput:
        """Render the current map (no gradients) from a dataset frame's view: its intrinsics, and its pose
        with the keyframe's refined correction under ``pose_refine`` (:meth:`pose_of`), the pose every score
        of the map is taken at (SLAM systems score at their estimated poses), under ``motion_blur`` blurred by
        the frame's motion (:meth:`SensorRenderer.render_view`), and under ``exposure_comp`` the frame's exposure
        response (its keyframe's, or the nearest keyframe's; colour clamped to [0, 1])."""
        return self._render_through(self.sensor, frame)

    def _render_through(self, sensor: SensorRenderer, frame: Frame) -> RenderOutput:
        """``sensor``'s map from ``frame``'s view at :meth:`pose_of`, exposed (colour clamped to [0, 1])."""
        intr = frame.intrinsics
        with torch.no_grad():
            out = sensor.render_view(self.pose_of(frame.frame_id, frame.c2w), intr.K, intr.width, intr.height,
                                     frame.frame_id, None)
        out, theta = sensor.exposed(out, frame.frame_id)
        return out if theta is None else dataclasses.replace(out, color=out.color.clamp(0.0, 1.0))

    def seen_by_this_camera(self, gmap: GaussianMap):
        """A renderer of another map as this robot's camera sees it, for scoring a team map on the robot's own frames
        by the rule its own map is scored by (:meth:`render_frame`, the ``sensor`` protocol): each frame at the
        sensor's pose with this robot's refined correction, through its sensor model (motion blur, rolling shutter)
        and its exposure response. A robot that uses the team map knows these; the map does not carry them.

        Args:
            gmap: the other map (world frame, metres), e.g. a fused team map; copied, never changed.

        Returns:
            ``render(frame) -> RenderOutput``, no gradients, charging nothing to the mapper's clock. It reads the
            robot's pose corrections when called and its sensor state (exposure responses, motion) as it is now.
        """
        model = GaussianModel(self.cfg.lr, self.device)
        model.set_map(gmap)
        sensor = SensorRenderer(self.cfg, model, WallClock())
        sensor.load_state_dict(self.sensor.state_dict())
        return lambda frame: self._render_through(sensor, frame)

    def pose_of(self, frame_id: int, c2w: np.ndarray) -> np.ndarray:
        """The pose to render frame ``frame_id`` at: ``c2w`` (4, 4) with the keyframe's refined correction
        (or the nearest keyframe's for a frame that is not one) under ``pose_refine``; ``c2w`` otherwise."""
        return self.poses.corrected(frame_id, c2w) if self.poses is not None else np.asarray(c2w, np.float64)

    # ------------------------------------------------------------------ keyframe anchors
    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Frame id → (4, 4) float64 camera-to-world pose (metres, OpenCV camera axes) of every mapped frame, the
        keyframes Gaussians are anchored to, as the map holds it now: the pose it came with and its current
        correction (:meth:`pose_of`: refinement, placement, pose-graph corrections). The poses a pose graph starts
        from and hands back to :meth:`apply_pose_corrections`."""
        return {fid: self.pose_of(fid, c2w) for fid, c2w in self.input_poses.items()}

    def apply_pose_corrections(self, new_c2w: Mapping[int, np.ndarray]) -> int:
        """Make the map follow corrected keyframe poses (e.g. a pose graph's, after a loop closure): for every
        keyframe whose pose changed, the world-frame rigid transform ``T = new_c2w · old_c2w⁻¹`` moves the Gaussians
        anchored to it (their means and rotations, :meth:`GaussianModel.move_rows
        <gausslite.mapping.model.GaussianModel.move_rows>`), so they look from the new pose as they looked from the
        old one. The keyframe's stored pose (the keyframe store, its detail crop with it) and its correction record
        (:meth:`pose_of`) take the new pose; the ROI views stored between keyframes move with their nearest mapped
        frame. Gaussians of other keyframes, and unanchored ones (a map loaded from outside), stay. Without ``pose.refine`` and tracking, the
        mapper starts keeping a correction record here, so that frames are rendered at their corrected poses.

        Args:
            new_c2w: frame id → (4, 4) camera-to-world pose (float, metres; a rigid transform, rounding off SE(3)
                projected away: :func:`~gausslite.mapping.poses.correction_moves`) of mapped frames
                (:meth:`keyframe_poses` gives their poses now). Frames whose pose is unchanged (to 1e-12) are left
                alone.
        Returns:
            the number of Gaussians moved.
        Raises:
            KeyError: a frame id that was never mapped. ValueError: a pose that is not a finite rigid transform.
        """
        moves = correction_moves(new_c2w, self.keyframe_poses())
        if not moves:
            return 0
        if self.poses is None:
            self.poses = self._new_pose_record()
            for fid in self.input_poses:
                self.poses.register(fid, np.eye(4))
        self.roi_views.follow(moves, self.input_poses, self.poses)
        n_moved = 0
        for fid, (T, new) in moves.items():
            rows = torch.nonzero(self.model.anchors == fid).squeeze(1)
            self.model.move_rows(rows, T)
            n_moved += int(rows.numel())
            self.poses.register(fid, np.linalg.inv(self.input_poses[fid]) @ new)  # projected onto SE(3) there
            self.keyframes.set_pose(fid, torch.from_numpy(new))
        return n_moved

    def load_map(self, gmap: GaussianMap, contribution: Optional[torch.Tensor] = None) -> None:
        """Replace the whole map from outside the mapping loop (refinement of a fused map, a checkpoint):
        no Adam state is carried; ``contribution`` (N,) float32, default zeros (no history). Keeps
        ``contribution`` aligned with the map, which eviction relies on.

        Raises:
            ValueError: ``contribution`` of another length than the map.
        """
        if contribution is not None and int(contribution.shape[0]) != len(gmap):
            raise ValueError(f"contribution has {contribution.shape[0]} rows, map has {len(gmap)}")
        self.model.set_map(gmap)
        self.strategy.reset(contribution)

    # ------------------------------------------------------------------ seeding
    def seed_frame(self, frame: Frame, relevance: Optional[np.ndarray],
                   detail: Optional[DetailCrop] = None) -> SeedStats:
        """Seed new Gaussians where ``frame`` (posed RGB-D, world ``c2w``, metres) is not explained by the map
        (paper Sec. III-C; :meth:`FrameSeeder.seed <gausslite.mapping.seeder.FrameSeeder.seed>`: the count, the
        draws, the budget), with the (H, W) bool ``relevance`` map w or None, and the keyframe's ``detail`` crop
        (:func:`~gausslite.mapping.detail.cut_detail`) or None. Returns :class:`SeedStats`."""
        return self.seeder.seed(frame, relevance, detail, first=self.n_mapped == 0)

    def retarget(self) -> None:
        """Forget the current task (a new one follows, :meth:`AgentRuntime.update_task
        <gausslite.mission.runtime.AgentRuntime.update_task>`): every task flag and κ restart at zero and the
        stored keyframes lose their ROI and their detail crops (cut around the old task's region); the map, its
        keyframes, poses and exposure stay. The new task's relevance maps then re-target the map through seeding and
        adoption (``seeding.adopt``)."""
        self.model.active = torch.zeros_like(self.model.active)
        self.model.kappa = torch.zeros_like(self.model.kappa)
        self.keyframes.clear_roi()
        self.roi_views.clear()

    def accumulate_contribution(self, kf: Keyframe) -> None:
        """Add each Gaussian's alpha-blending weight Σ_pixels T_i α_i in keyframe ``kf`` (sharp view) to the
        strategy's contribution, the eviction score (:meth:`DensityStrategy.eviction_score`)."""
        if len(self.model):
            self.strategy.add_contribution(self.sensor.blend_weights(kf.K, kf.width, kf.height, kf.c2w))
            self.strategy.prune_idle()  # budget.prune_contribution

    def add_roi_views(self, frames, current: Optional[Keyframe] = None, scale: Optional[float] = None) -> int:
        """Store the ROI crop of frames between keyframes (``roi_views``; gausslite mode with a task in view).

        Each frame's region is the ROI of the newest stored keyframe that sees it and of ``current`` (the keyframe
        being mapped), carried over by their depth (:func:`~gausslite.mapping.roi_views.project_roi`); a frame whose
        region has fewer than ``roi_views.min_roi_px`` pixels is skipped, and so is all but every
        ``roi_views.every``-th of the others. A stored view gets a pose-correction slot (interpolated between its
        keyframes, or the nearest one's, ``pose.between_keyframes``) and an exposure slot (likewise), refined by the
        ROI-phase iterations that draw it (``pose.roi_phase``). Charged to a deterministic clock at
        ``roi_views.view_cost_s`` per frame examined.

        Args:
            frames: decoded frames (``Frame``: uint8 rgb (H, W, 3), float32 depth (H, W) metres, ``c2w`` (4, 4),
                pinhole intrinsics) between the previous keyframe and ``current``, oldest first.
            current: the keyframe being mapped (float tensors), or None.
            scale: the frames' resolution over the mapping resolution when they are a detail view's
                (:class:`~gausslite.mapping.detail.DetailView`'s ``between``): the region's dilation is
                ``roi_views.dilate_px`` × it, its minimum size ``roi_views.min_roi_px`` × its square and the crop's
                pad :func:`~gausslite.mapping.detail.detail_pad`'s. None: frames at the mapping resolution.
        Returns:
            the number of views stored.
        """
        rc = self.cfg.roi_views
        if not (rc.enabled and self.cfg.effective().roi) or not frames:
            return 0
        sources = [k for k in reversed(list(self.keyframes)) if k.sees_roi][:1]
        if current is not None and current.roi_box is not None:
            sources.append(current.compact())
        pts = window_points(sources)
        if len(pts) == 0:
            return 0
        dilate, min_px, pad = rc.dilate_px, rc.min_roi_px, self.cfg.roi_crop_pad
        if scale is not None:
            dilate, min_px = int(round(rc.dilate_px * scale)), rc.min_roi_px * scale * scale
            pad = detail_pad(self.cfg.detail.pad_px, self.cfg.roi_crop_pad, scale)
        stored, seen = 0, 0
        for fr in frames:
            if self.clock.charges:
                self.clock.charge_fixed(rc.view_cost_s)
            c2w = self.pose_of(fr.frame_id, fr.c2w)
            roi = project_roi(pts, fr.depth, fr.intrinsics.K, c2w, rc.depth_tol_m, dilate)
            if int(roi.sum()) < min_px:
                continue
            seen += 1
            if (seen - 1) % rc.every:
                continue
            view = roi_view_of(dataclasses.replace(fr, c2w=c2w), roi, pad, self.device)
            if self.poses is not None:
                self.poses.register(fr.frame_id, np.linalg.inv(np.asarray(fr.c2w, np.float64)) @ c2w,
                                    fixed=not rc.align)
            exposure = self.sensor.exposure
            if exposure is not None:
                exposure.register(fr.frame_id, exposure.of(fr.frame_id), fixed=not rc.align)
            self.roi_views.add(view)
            stored += 1
        return stored

    def map_frame(self, frame: Frame, relevance: Optional[np.ndarray] = None,
                  time_budget_s: Optional[float] = None, between=(),
                  detail: Optional[DetailView] = None) -> FrameStats:
        """Seed and optimise for one posed RGB-D frame.

        Args:
            frame: the frame (its pose is where it starts; under ``pose.track_iters`` it is placed against the map
                before it seeds, :meth:`_place_keyframe`).
            relevance: (H, W) bool relevance map w for this frame, or None (no ROI).
            time_budget_s: wall-clock budget of this call in seconds (seeding included); None →
                ``cfg.keyframe_budget_s``; both None → ``cfg.iters_per_frame`` iterations (offline
                ``map``/``ablate``). With a budget, iterations run until it is spent (at least one; the
                last one may overrun by one iteration's time). Phases (paper III-D.1): without a budget
                the first ``warmup_iters`` iterations are full-image, the rest ROI-phase; with a budget
                the first ``warmup_iters / iters_per_frame`` of the time left after seeding is full-image
                (at least one iteration when ``warmup_iters`` > 0), the rest ROI-phase, and density
                control runs every ``densify.every`` budgeted iterations counted across calls. Under
                ``pose.track_iters`` the keyframe's placement (:meth:`_place_keyframe`) comes out of the budget too,
                at most ``pose.track_budget_frac`` of it.
            between: the frames the robot saw since the previous keyframe (oldest first; decoded ``Frame`` objects,
                or objects with ``frame_id``, ``timestamp``, ``c2w`` and ``intrinsics`` when only their motion is
                used): under ``sensor.motion_every_frame`` every mode records the camera's motion through them
                (motion blur, rolling shutter), and under ``roi_views`` GaussLite stores their ROI crops
                (:meth:`add_roi_views`), inside this call's budget.
            detail: the same keyframe at the task region's (finer) resolution, with its relevance there and the
                frames between keyframes at that size (:class:`~gausslite.mapping.detail.DetailView`). Used under
                ``detail.enabled`` in GaussLite mode with the ROI phase and a relevance map: the keyframe stores the
                region's detail crop (when both relevance maps have pixels; :attr:`FrameStats.detail_px`), its
                ROI-phase iterations fit that crop, the region's seeds come from it (``detail.seeds``) and the ROI
                views from ``detail.between`` (``detail.roi_views``). None, or ``detail.enabled`` off: mapping at
                one resolution, bit for bit.
        Returns:
            FrameStats (seconds includes seeding, optimisation and density control).
        Raises:
            ValueError: relevance map of the wrong shape; a detail view of another frame or of inconsistent shapes.
        """
        if relevance is not None and relevance.shape != frame.depth.shape:
            raise ValueError(f"relevance map shape {relevance.shape} != frame shape {frame.depth.shape}")
        cfg = self.cfg
        use_detail = (detail is not None and cfg.detail.enabled and cfg.effective().roi and relevance is not None)
        if use_detail:
            check_detail(detail, frame)
        t_wall = time.perf_counter()
        t0 = self.clock.now()
        budget = cfg.keyframe_budget_s if time_budget_s is None else time_budget_s
        if cfg.sensor.motion_every_frame:
            for fr in between:
                self.sensor.observe(fr)
        self.sensor.observe(frame)  # the camera's motion over this frame's exposure (motion blur, rolling shutter)
        frame, placed, aligned = self._place_keyframe(
            frame, relevance, None if budget is None else t0 + cfg.pose.track_budget_frac * budget)
        exposure = self.sensor.exposure
        if exposure is not None:
            # start from the latest keyframe's response; the first keyframe fixes the map's exposure
            exposure.register(frame.frame_id, exposure.initial(frame.frame_id), fixed=self.n_mapped == 0)
        crop = None
        if use_detail and roi_box(relevance) is not None:  # at the placed pose: the keyframe's
            crop = cut_detail(detail, frame.c2w, frame.intrinsics, cfg.detail.pad_px, cfg.roi_crop_pad)
        seeded = self.seed_frame(frame, relevance, crop if cfg.detail.seeds else None)
        kf = keyframe_from_frame(frame, self.device, relevance)
        if crop is not None:  # the crop shares the keyframe's pose tensor: corrections move both
            kf.detail = dataclasses.replace(keyframe_from_frame(crop.frame, self.device, crop.relevance), c2w=kf.c2w)
        if use_detail and cfg.detail.roi_views and detail.between:
            self.add_roi_views(detail.between, kf, detail_scale(detail.frame.intrinsics, frame.intrinsics))
        elif between:
            self.add_roi_views(between, kf)
        stored = None
        if self.n_mapped % cfg.store_keyframe_every == 0 or len(self.keyframes) == 0:
            stored = self.keyframes.add(kf)
        loss, active_iters, n_iters, dstats = keyframe_iterations(self, kf, t0, budget)
        if cfg.budget.evict == "contribution":
            self.accumulate_contribution(kf)
        self.n_mapped += 1
        st = FrameStats(frame.frame_id, time.perf_counter() - t_wall, seeded.n_seeds, seeded.n_roi, len(self.model),
                        loss, active_iters, dstats, n_iters, unexplained=seeded.unexplained,
                        budget=int(self.strategy.budget or 0), n_evicted=seeded.n_evicted,
                        n_adopted=seeded.n_adopted, n_gap_seeds=seeded.n_gap_seeds)
        if aligned is not None:
            st.align_accepted, st.align_fitness, st.align_s = aligned.accepted, aligned.fitness, aligned.seconds
            st.align_rot_deg, st.align_trans_m = aligned.rot_deg, aligned.trans_m
        if placed is not None:
            st.track_iters, st.track_accepted = placed.iters, placed.accepted
            st.track_rot_deg, st.track_trans_m = placed.rot_deg, placed.trans_m
        if stored is not None and stored.detail is not None:
            st.detail_px = int(stored.detail.width * stored.detail.height)
        st.n_active, st.active_scale_m = self.model.active_size()
        self.stats.append(st)
        return st

    def _place_keyframe(self, frame: Frame, relevance: Optional[np.ndarray], deadline: Optional[float]
                        ) -> tuple[Frame, Optional[TrackResult], Optional[AlignResult]]:
        """The pose a new keyframe seeds and trains at: its input pose with the correction it starts from (the latest
        keyframe's under ``pose.init: inherit``; the first keyframe fixes the gauge); under ``pose.align``, aligned
        to the depth of the keyframes before it from the input pose times the latest keyframe's correction
        (:class:`~gausslite.mapping.alignment.KeyframeAligner`; kept when it passes the gates); then, under
        ``pose.track_iters``, placed against the frozen map (:class:`~gausslite.mapping.tracking.FrameTracker`). Both
        stop at ``deadline`` clock seconds when given. Records the input pose (:attr:`input_poses`) and the
        correction (:attr:`poses`), and stores the keyframe's depth cloud for the next alignments. Returns the frame
        at that pose, the tracker's result and the alignment's (each None when it did not run)."""
        cfg = self.cfg
        fid = int(frame.frame_id)
        self.input_poses[fid] = np.asarray(frame.c2w, np.float64).copy()
        if self.poses is None:
            return frame, None, None
        latest = self.poses.initial_correction(fid)
        E0 = latest if cfg.pose.init == "inherit" else np.eye(4)
        aligned = None
        if self.aligner is not None and self.n_mapped > 0:
            start = self.input_poses[fid] @ latest
            aligned = self.aligner.align(frame, start, lambda k: self.pose_of(k, self.input_poses[k]), deadline,
                                         self.clock.now)
            if aligned.accepted:
                E0 = np.linalg.inv(self.input_poses[fid]) @ aligned.c2w
        frame = dataclasses.replace(frame, c2w=self.input_poses[fid] @ E0)
        self.poses.register(fid, E0, fixed=self.n_mapped == 0)
        if self.aligner is not None:
            self.aligner.add(frame)
        if not (cfg.pose.track_iters and self.n_mapped > 0 and len(self.model)):
            return frame, None, aligned
        res = self.tracker.track(frame, relevance, deadline)
        if res.accepted:
            self.poses.register(fid, np.linalg.inv(self.input_poses[fid]) @ res.c2w)
            frame = dataclasses.replace(frame, c2w=res.c2w.copy())
        return frame, res, aligned

    def optimize(self, max_seconds: Optional[float] = None, n_iters: Optional[int] = None) -> int:
        """Keep optimising between keyframes (MVO over the stored keyframes; paper III-D.2).

        Views are drawn like ``map_frame``'s (recent window or the whole mission, ROI-weighted with MVO:
        :meth:`KeyframeStore.sample_index`). The phase schedule continues across calls like
        ``map_frame``'s: in every run of ``iters_per_frame`` idle iterations the first ``warmup_iters`` are
        full-image, the rest ROI-phase (GaussLite with ROI and an active subset); density control runs
        every ``densify.every`` idle iterations.

        Args:
            max_seconds: stop once this much wall time passed (at least one iteration runs).
            n_iters: stop after this many iterations. At least one of the two must be given.
        Returns:
            number of iterations done (0 when there is no keyframe yet).
        Raises:
            ValueError: neither bound given, or a bound that is not > 0.
        """
        return between_keyframes(self, max_seconds, n_iters)

    def finalize(self, max_seconds: Optional[float] = None) -> int:
        """Optional extra iterations over all keyframes (``final_iters`` + ``final_iters_per_keyframe`` ×
        keyframes), drawn uniformly; full image, all Gaussians (``final_schedule: full``), or in gausslite mode
        the mapping schedule (``final_schedule: mapping``: of every ``iters_per_frame`` iterations, the first
        ``warmup_iters`` full-image, the rest ROI-phase where the drawn keyframe sees the ROI).

        Args:
            max_seconds: stop early once this much wall time (seconds) has passed (the online agent's
                Finish bound); None = all of them (offline ``map``/``ablate``, deterministic).
        Returns:
            iterations done.
        Raises:
            ValueError: ``max_seconds`` not > 0.
        """
        return final_pass(self, max_seconds)

    # ------------------------------------------------------------------ checkpoint / resume
    def state_dict(self, saved_keyframes_max: Optional[int] = 32) -> dict:
        """CPU copy of what a restarted online mapper needs, gathered from its parts' ``state_dict``: the
        Gaussians with κ, task flags and stable ids (:class:`GaussianModel`), accumulated contribution, budget
        and observed voxels (:class:`DensityStrategy`), the newest ``saved_keyframes_max`` stored keyframes in their
        compact form with their detail crops (None: all; they bound the file size of a long mission; the MVO window
        is the newest of them), the sensor state (:class:`SensorRenderer`), the pose corrections and the mapped frames' input poses (the
        keyframe anchors' frames), the schedule counters and the
        RNG state; not the Adam moments (a resumed mapper restarts them at zero, as for newly seeded
        Gaussians). One flat ``torch.save``-able dict.
        """
        n = None if saved_keyframes_max is None else max(saved_keyframes_max, self.cfg.window)
        return {
            **self.model.state_dict(), **self.strategy.state_dict(), **self.keyframes.state_dict(n),
            **self.roi_views.state_dict(),
            **self.sensor.state_dict(), **self.step.state_dict(),
            "n_mapped": self.n_mapped, "n_idle_iters": self.n_idle_iters, "n_budget_iters": self.n_budget_iters,
            "rng": self.rng.bit_generator.state,
            "pose_corrections": None if self.poses is None else self.poses.state_dict(),
            "input_poses": {k: v.copy() for k, v in self.input_poses.items()},
            "alignment": None if self.aligner is None else self.aligner.state_dict(),
        }

    def load_state_dict(self, state: dict) -> None:
        """Load a :meth:`state_dict` (replaces the map, keyframes, sensor state and counters).

        Raises:
            KeyError / ValueError: a state dict that lacks fields or holds inconsistent shapes.
        """
        self.model.load_state_dict(state)
        self.strategy.load_state_dict(state)
        self.keyframes.load_state_dict(state)
        self.roi_views.load_state_dict(state)
        self.sensor.load_state_dict(state)
        self.step.load_state_dict(state)
        self.n_mapped = int(state["n_mapped"])
        self.n_idle_iters = int(state["n_idle_iters"])
        self.n_budget_iters = int(state.get("n_budget_iters", 0))  # absent in older checkpoints
        self.rng.bit_generator.state = state["rng"]
        if state.get("pose_corrections"):
            if self.poses is None:  # corrections a pose graph applied to a mapper that neither refines nor tracks
                self.poses = self._new_pose_record()
            self.poses.load_state_dict(state["pose_corrections"])
        self.input_poses = {int(k): np.asarray(v, np.float64).copy()
                            for k, v in (state.get("input_poses") or {}).items()}  # absent in older checkpoints
        if self.aligner is not None and state.get("alignment"):  # absent in older checkpoints and without pose.align
            self.aligner.load_state_dict(state["alignment"])
