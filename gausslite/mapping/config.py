"""Typed mapper configuration with defaults from the paper (Sec. III-C/III-D).

The loaders live in :mod:`gausslite.config`: :func:`gausslite.config.load_config` reads the whole GaussLite YAML
(its ``mapper`` section is ``cfg.mapper``), :func:`gausslite.config.load_mapper_config` a mapper-only file
(``gausslite map --config``). Both override single fields with ``key=value`` strings (dotted keys reach nested
groups, e.g. ``lr.means=2e-4``, ``seeding.seeds_per_frame=800``). Settings named by their old flat names
(:data:`FLAT_NAMES`) or by the old names of renamed settings (:data:`RENAMED_MAPPER_KEYS`) are moved to their keys by
:func:`migrate_flat_names`, with a ``DeprecationWarning``.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from typing import Any, Iterable, Literal, Optional

import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

log = logging.getLogger(__name__)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class LearningRates(_Strict):
    """Adam learning rates per parameter group (3DGS / Gaussian-SLAM style groups)."""

    means: float = Field(2.5e-4, gt=0, description="metres per step (scaled by scene_scale)")
    quats: float = Field(2e-3, gt=0)
    log_scales: float = Field(5e-3, gt=0)
    opacity_logits: float = Field(1e-1, gt=0)
    colors: float = Field(1e-2, gt=0)


class DensifyConfig(_Strict):
    """Standard 3DGS adaptive density control (Kerbl et al. 2023), run per mapped frame."""

    enabled: bool = True
    every: int = Field(20, ge=1, description="iterations between density-control steps")
    grad_threshold: float = Field(1e-3, gt=0, description="mean ‖∂L/∂means2d‖ (pixels × half image size)")
    clone: bool = Field(
        False, description="clone high-gradient Gaussians smaller than split_scale_m (3DGS). Off: the mapper "
        "seeds new Gaussians where the map does not explain a keyframe, and cloning on top of that cost ROI "
        "and full PSNR (measured: docs/results.md). Clones start from zero Adam moments (GaussianModel.set_map)"
    )
    roi_grad_factor: float = Field(
        1.0, gt=0, le=1, description="gausslite mode: active (ROI) Gaussians densify at grad_threshold × this "
        "(densification allocated by relevance, paper Sec. III); 1 = the same threshold as the background "
        "(measured: docs/results.md)"
    )
    split_scale_m: float = Field(
        0.02, gt=0, description="high-gradient Gaussians larger than this (metres) split, smaller clone"
    )
    prune_opacity: float = Field(0.005, ge=0, description="prune Gaussians with opacity below this")
    max_scale_m: float = Field(0.5, gt=0, description="prune Gaussians with a larger max scale")
    active_phase_stats: bool = Field(
        False, description="also accumulate the view-space gradient statistics in ROI-phase iterations. Off: "
        "those iterations restrict the loss to the ROI (and, with roi_render='active', render only the "
        "active subset), so their gradients are not comparable with grad_threshold (measured: docs/results.md)"
    )


class WorkCostConfig(_Strict):
    """Cost model of the deterministic budget clock (:class:`gausslite.mapping.budget.WorkCost`; seconds)."""

    render_s: float = Field(1.9e-3, ge=0, description="per differentiable render (forward + backward)")
    pixel_s: float = Field(2.2e-7, ge=0, description="per rendered pixel")
    gaussian_s: float = Field(9.3e-7, ge=0, description="per Gaussian a render projects")
    step_s: float = Field(2.0e-3, ge=0, description="per Adam step")
    step_gaussian_s: float = Field(1.4e-6, ge=0, description="per Gaussian an Adam step updates")
    no_grad_factor: float = Field(0.4, ge=0, description="a render without gradients costs this share")


class ComponentSwitches(_Strict):
    """The paper's ablation switches (Table 3): SB, MVO, ROI, SIS, GFD."""

    sb: bool = Field(True, description="ROI seed budgeting (III-C.1)")
    mvo: bool = Field(True, description="multi-view optimisation (III-D.2)")
    roi: bool = Field(True, description="two-phase ROI optimisation (III-D.1)")
    sis: bool = Field(True, description="stratified sampling + tiered initial scale (III-C.2)")
    gfd: bool = Field(True, description="gradient-focused densification (III-C.3)")


class SeedingConfig(_Strict):
    """Relevance-driven seeding (paper Sec. III-C): how many Gaussians a frame seeds, where (SB, SIS, GFD), and
    their initial scale and opacity."""

    seeds_per_frame: int = Field(1500, ge=1, description="N new Gaussians per mapped frame")
    first_frame_seeds: Optional[int] = Field(
        None, ge=1, description="seeds on the first mapped frame (default 2×seeds_per_frame)"
    )
    coverage: bool = Field(
        True, description="seed only where the map does not explain the new frame (SplaTAM Eq. 9 silhouette "
        "and depth rule); the seed count is seeds_per_frame × the unexplained share of valid pixels"
    )
    coverage_alpha: float = Field(0.5, gt=0, le=1, description="unexplained: rendered silhouette below this")
    coverage_depth_factor: float = Field(
        50.0, gt=0, description="unexplained: rendered depth behind the observed one by more than this × the "
        "median depth error (SplaTAM: 50)"
    )
    rho: float = Field(0.4, ge=0, le=1, description="SB ROI seed share ρ (paper: 40 % on Replica)")
    m_roi: float = Field(0.5, gt=0, description="SIS scale multiplier for ROI seeds")
    m_bg: float = Field(0.7, gt=0, description="SIS scale multiplier for background seeds")
    m_uniform: float = Field(1.0, gt=0, description="scale multiplier without SIS")
    gfd_eps: float = Field(0.05, gt=0, description="GFD smoothing ε added to the Sobel magnitude")
    knn: int = Field(3, ge=1, description="neighbours for the local median NN distance s0")
    init_opacity: float = Field(0.5, gt=0, lt=1)
    adopt: bool = Field(
        True, description="a task that reaches a region the map already covers (an object first seen late, a task "
        "given mid-mission, a map at its cap): when the task's own Gaussians leave more than roi_gap of a frame's "
        "relevant pixels uncovered, the Gaussians that already draw those pixels join the task (a = 1; κ counts "
        "from then on) and the uncovered pixels get ρ × seeds_per_frame × their share of the ROI in new ROI seeds, "
        "which at the budget replace background (docs/mapper.md#tasks-that-arrive-late). GaussLite mode only"
    )
    adopt_fraction: float = Field(
        0.5, gt=0, le=1, description="adopt: a Gaussian joins when at least this share of its blending weight in "
        "the frame falls on relevant pixels (a large background splat that only grazes the ROI stays out)"
    )
    roi_gap: float = Field(
        0.1, ge=0, le=1, description="adopt: share of the frame's valid relevant pixels left uncovered (silhouette "
        "below coverage_alpha) by the task's Gaussians that triggers adoption and ROI seeds (at least 32 pixels)"
    )


class BudgetConfig(_Strict):
    """The Gaussian budget and eviction at the budget (:class:`gausslite.mapping.strategy.DensityStrategy`)."""

    max_gaussians: Optional[int] = Field(
        None, ge=1, description="global Gaussian budget; None = gaussians_per_pixel × image pixels"
    )
    gaussians_per_pixel: float = Field(
        1.0, gt=0, description="budget per image pixel when max_gaussians is None (paper: 1M at 1200×680 ≈ 1.2)"
    )
    mode: Literal["scene", "image"] = Field(
        "scene", description="default budget when max_gaussians is None. 'scene': gaussians_per_voxel × "
        "coarse voxels observed so far (grows with the mission, capped by max_gaussians_cap); 'image': "
        "gaussians_per_pixel × the first frame's pixels (fixed)"
    )
    gaussians_per_voxel: float = Field(
        4.5, gt=0, description="scene budget per observed coarse voxel (budget_voxel_m edge). Room0's first 20 "
        "frames observe 11.6k voxels of 5 cm: 4.5 gives them 52k Gaussians, the old 1-per-pixel budget at 300x170"
    )
    voxel_m: float = Field(0.05, gt=0, description="edge of the coarse voxels the scene budget counts (metres)")
    cap: int = Field(400_000, ge=1, description="hard cap on the scene budget")
    evict: Literal["contribution", "opacity"] = Field(
        "contribution", description="at the budget, new seeds replace the existing Gaussians with the lowest "
        "'contribution' (alpha-blending weight accumulated over the keyframes that see them) or 'opacity'"
    )
    roi_protect: float = Field(
        4.0, ge=1, description="eviction: active (ROI) Gaussians' contribution counts this many times "
        "(gausslite mode only; uniform mode has no active Gaussians)"
    )


class PoseConfig(_Strict):
    """Keyframe pose refinement and tracking (MonoGS Sec. 3.3; SplaTAM Sec. 3.3; :mod:`gausslite.mapping.poses`)."""

    refine: bool = Field(
        False, description="refine every keyframe's pose jointly with the map (MonoGS Sec. 3.3; "
        "gausslite.mapping.poses) in full-image iterations and, with roi_phase, ROI-phase ones: for sensors whose "
        "poses are not exact (the hand-held profile); "
        "scores are then taken at the refined poses, as SLAM systems score at their estimated poses"
    )
    track_iters: int = Field(
        0, ge=0, description="keyframe placement: at most this many Adam steps on a new keyframe's pose alone against "
        "the frozen map before it is seeded or trains (frame-to-map tracking from the sensor's pose, "
        "gausslite.mapping.tracking; SplaTAM Sec. 3.3); 0 = none. Works with or without pose.refine"
    )
    track_alpha: float = Field(0.9, gt=0, lt=1, description="tracking: pixels with rendered silhouette above this")
    track_width: Optional[int] = Field(
        None, ge=8, description="tracking: render at about this many pixels wide (the frame downscaled by the "
        "integer factor width // track_width: colour block means, valid-depth means); None = the frame's resolution"
    )
    track_lr_rot: float = Field(5e-3, gt=0, description="tracking: Adam step of the rotation (radians)")
    track_lr_trans: float = Field(5e-3, gt=0, description="tracking: Adam step of the translation (metres)")
    track_lambda_depth: Optional[float] = Field(
        None, ge=0, description="tracking: weight of the depth L1 (metres) beside the colour L1; None = lambda_depth"
    )
    track_robust_k: float = Field(
        3.0, ge=0, description="tracking: robust (Cauchy) pixel weights 1 / (1 + (r / (k σ))²) on the colour and "
        "depth residuals r, σ = 1.4826 × their median (MAD scale), so pixels the map does not explain (moving "
        "objects, new surfaces) pull less; 0 = plain L1"
    )
    track_roi_weight: float = Field(
        1.0, ge=0, description="tracking, gausslite mode: pixels of the relevance map weigh 1 + this (the task "
        "region, where the map is sharpest); uniform mode weighs every pixel alike"
    )
    track_budget_frac: float = Field(
        0.25, gt=0, le=1, description="tracking under a keyframe time budget (keyframe_budget_s or map_frame's "
        "time_budget_s): it stops once this share of the budget is spent (at least one step); offline it runs "
        "up to track_iters"
    )
    track_converge: float = Field(
        1e-3, ge=0, description="tracking: stop early once the loss has not dropped by this share of its best for "
        "10 steps; the best pose seen is kept"
    )
    track_max_trans_m: float = Field(
        0.1, gt=0, description="tracking sanity gate: a correction that moves the camera more than this (metres) "
        "is rejected (logged); the keyframe keeps the pose it came with"
    )
    track_max_rot_deg: float = Field(
        10.0, gt=0, description="tracking sanity gate: a correction that turns the camera more than this "
        "(degrees) is rejected likewise"
    )
    lr_rot: float = Field(1e-3, gt=0, description="pose refinement: Adam step of the rotation (radians)")
    lr_trans: float = Field(5e-4, gt=0, description="pose refinement: Adam step of the translation (metres)")
    roi_phase: bool = Field(
        True, description="ROI-phase iterations also step their view's pose (and, with sensor.exposure_comp, its "
        "exposure response) from the ROI loss, so the task region is fitted against aligned views (a GaussLite map "
        "spends most of its iterations there); False: full-image iterations only. The first keyframe stays fixed "
        "either way (measured: docs/realtime.md)"
    )
    roi_phase_exposure: bool = Field(
        True, description="with roi_phase and sensor.exposure_comp: ROI-phase iterations also step their view's "
        "exposure response (False: pose only; the response is then fitted on full images alone)"
    )
    roi_lr_scale: float = Field(
        1.0, gt=0, le=1, description="pose refinement: step size of ROI-phase pose steps relative to lr_rot / "
        "lr_trans (< 1 regularises the alignment the ROI alone can see)"
    )
    between_keyframes: Literal["nearest", "interpolate"] = Field(
        "interpolate", description="a frame between keyframes (a held-out view, the sensor protocol's score) is "
        "rendered with the pose correction and exposure response interpolated in frame id between the keyframes on "
        "both sides, or those of the nearest keyframe (measured on TUM: interpolation lifts every run of both modes "
        "by 0.3-0.8 dB ROI PSNR at the sensor's pose, docs/realtime.md#the-frames-between-keyframes)"
    )
    init: Literal["inherit", "identity"] = Field(
        "identity", description="pose refinement: a new keyframe starts from the latest keyframe's correction "
        "('inherit', for pose errors correlated over consecutive frames) or from the sensor's pose ('identity'; "
        "'inherit' drifts on TUM fr1/rpy, measured: docs/results.md)"
    )


class SensorConfig(_Strict):
    """The sensor model a view is rendered with (:class:`gausslite.mapping.sensor.SensorRenderer`): exposure
    compensation, motion blur, rolling shutter."""

    exposure_comp: bool = Field(
        False, description="per-keyframe exposure compensation (gausslite.mapping.exposure; MonoGS): every "
        "keyframe gets an affine colour response exp(a)·I + b per channel, optimised with the map where its pose is "
        "(full-image iterations, and ROI-phase ones under pose.roi_phase); the first keyframe fixes the map's exposure; scores are taken with each frame's response "
        "(the nearest keyframe's for a held-out view), as they are at its refined pose"
    )
    exposure_lr: float = Field(0.01, gt=0, description="exposure compensation: Adam step of a and b (MonoGS: 0.01)")
    motion_blur: bool = Field(
        False, description="model camera motion blur (gausslite.mapping.blur; BAD-Gaussians, MBA-SLAM): a view is "
        "the mean of renders at virtual poses along the camera's motion during the exposure, known from the sensor's "
        "poses of consecutive mapped frames; its scores are taken the same way. On in the hand-held profile"
    )
    blur_exposure_s: float = Field(
        0.01, gt=0, le=0.2, description="motion blur: exposure time τ, seconds (measured: docs/results.md)"
    )
    blur_px_per_sample: float = Field(4.0, gt=0, description="motion blur: one virtual pose per this many pixels of streak")
    blur_max_samples: int = Field(5, ge=1, description="motion blur: at most this many virtual poses per view")
    rolling_shutter_s: float = Field(
        0.0, ge=0, le=0.1, description="rolling shutter (gausslite.mapping.shutter; Kerl et al. ICCV 2015, Seiskari et al. "
        "ECCV 2024): readout time of the colour image, first row to last, seconds (0: global shutter). Rows are "
        "rendered in bands, each from the pose at its readout time along the camera's motion (the sensor's poses of "
        "consecutive mapped frames, as for motion_blur); scores are taken the same way"
    )
    motion_estimate: Literal["backward", "central"] = Field(
        "backward", description="the camera's motion for motion_blur and the rolling shutter: 'backward' from the "
        "previous mapped frame to this one (the velocity 1/2 frame earlier); 'central' also replaces the previous "
        "frame's estimate by the mean of its backward and forward ones once this frame arrives (the first frame "
        "gets the forward one), so stored keyframes carry the velocity at their own time"
    )
    rs_px_per_band: float = Field(2.0, gt=0, description="rolling shutter: one row band per this many pixels of motion "
                                  "between a view's first and last row")
    rs_max_bands: int = Field(6, ge=1, description="rolling shutter: at most this many row bands per view")
    motion_every_frame: bool = Field(
        False, description="motion blur and rolling shutter: estimate the camera's motion from every frame the robot "
        "saw (the frames between keyframes included, Mapper.map_frame's between), not only from consecutive keyframes"
    )
    blur_max_dt: float = Field(
        0.5, gt=0, description="motion blur: consecutive mapped frames further apart than this (seconds) give no "
        "motion estimate (the view is rendered sharp)"
    )


class RoiViewConfig(_Strict):
    """ROI views: the task region's crops of the frames between keyframes, drawn by ROI-phase iterations beside the
    keyframes (:mod:`gausslite.mapping.roi_views`; docs/realtime.md, "Every view of the region")."""

    enabled: bool = Field(
        False, description="store the ROI crop of frames between keyframes (gausslite mode, a task in view) and let "
        "ROI-phase iterations draw them as well as the keyframes (uniform maps ignore it); the frames' region comes "
        "from the keyframes' relevance maps carried over by depth"
    )
    every: int = Field(1, ge=1, description="keep every n-th frame between keyframes that sees the region")
    max_views: int = Field(96, ge=1, description="at most this many stored views (the most redundant pose is evicted)")
    max_bytes: int = Field(16 << 20, ge=1, description="at most this many bytes of stored crops")
    min_roi_px: int = Field(64, ge=1, description="a frame whose carried-over region has fewer pixels is not stored")
    depth_tol_m: float = Field(0.1, gt=0, description="carried-over region: occlusion tolerance against the "
                               "frame's depth (metres; at least 5 % of the depth)")
    dilate_px: int = Field(3, ge=0, description="carried-over region: dilation of the projected points (pixels)")
    draw: float = Field(
        1.0, ge=0, description="an ROI-phase iteration whose drawn keyframe sees the region takes a stored view "
        "instead with probability draw × views / (views + ROI keyframes): 1 = a uniform draw over every view of the "
        "region, keyframes and stored crops alike; 0 = keyframes only"
    )
    align: bool = Field(
        True, description="ROI-phase iterations on a stored view refine its pose correction and exposure response "
        "(pose.roi_phase); False: both stay as interpolated from its keyframes when it was stored"
    )
    view_cost_s: float = Field(
        1.5e-3, ge=0, description="deterministic twin (budget_clock work): modelled seconds of storing one view")


class DetailConfig(_Strict):
    """The task region at its own resolution (:mod:`gausslite.mapping.detail`; docs/mapper.md, "The task region at
    its own resolution"): beside the keyframe at the mapping resolution, ``Mapper.map_frame`` may get the same view at
    a finer one (a :class:`~gausslite.mapping.detail.DetailView`); the keyframe then keeps a crop of the task region
    at that resolution, which ROI-phase iterations fit instead of the coarse crop, and which the region's seeds and
    ROI views come from. GaussLite mode with the ROI phase only; one map either way."""

    enabled: bool = Field(
        False, description="use the detail view map_frame is given (without one, or with this off, the mapper maps "
        "as it does at one resolution, bit for bit)"
    )
    pad_px: Optional[int] = Field(
        None, ge=0, description="pixels around the region's box in the detail crop, at the detail resolution; None = "
        "roi_crop_pad × the detail scale (the detail view's focal over the mapping focal), the coarse crop's area"
    )
    max_bytes: int = Field(
        64 << 20, ge=1, description="bound on the bytes of the keyframes' detail crops (uint8 colour, float16 depth, "
        "bool region: 6 B/pixel; counted in KeyframeStore.nbytes); past it the detail crop of the most redundant "
        "keyframe is dropped (the older of the closest pair of poses), the coarse keyframe stays"
    )
    seeds: bool = Field(
        True, description="with SB: the region's seeds are drawn from the detail crop's relevant pixels (their initial "
        "scale follows the finer spacing); the background's from the coarse frame outside the region. False: every "
        "seed from the coarse frame"
    )
    roi_views: bool = Field(
        True, description="with roi_views.enabled: the ROI views of the frames between keyframes are cut from the "
        "detail view's frames (DetailView.between) when it has them, their dilation and minimum region size scaled "
        "to the detail resolution; the view store's max_bytes then counts the larger crops"
    )


class PerformanceConfig(_Strict):
    """Speed settings: threads, kernels, culling, caches and the cheaper iteration variants. Except for
    ``coarse_iters`` and ``full_crop_fraction`` they do not change the map beyond float rounding."""

    torch_threads: int = Field(
        1, ge=0, description="torch intra-op threads (0 = leave torch's setting); 1 avoids OpenMP "
        "threads competing with the rasterizer's band threads (measured 4× faster under load)"
    )
    render_threads: Optional[int] = Field(
        1, ge=1, description="rasterizer CPU band threads (None = min(2, cores)); default 1, the measured "
        "setting: two agents share two cores in the simulation, and a live agent leaves a core to its pusher, "
        "relevance and ingest threads"
    )
    cpu_kernel: Literal["simd", "tile"] = Field(
        "simd", description="CPU compositing kernels (gausslite.render.simd_kernels): 'simd' = vectorised "
        "native tile loops (default; room0 300x170: forward 20 -> 11 ms, backward 25 -> 16 ms), 'tile' = the "
        "Warp tile kernels they replace (bench.mapper baseline); the same renders to float32 rounding"
    )
    frustum_cull: bool = Field(
        True, description="render only the Gaussians whose 3σ sphere reaches the (padded) view frustum "
        "(gausslite.render.culling; the same image): a long mission's map is mostly out of view"
    )
    frustum_cull_min: int = Field(20_000, ge=0, description="cull only maps of at least this many Gaussians")
    reference_paths: bool = Field(
        False, description="use the slow reference implementations of the ROI-phase Adam step (full step, "
        "then frozen rows restored) and of SSIM (15 filtered channels, no cached ground-truth statistics): "
        "the same results to float rounding, for parity checks and as bench.mapper's baseline"
    )
    ssim_cache_views: int = Field(
        32, ge=0, description="keep the ground-truth SSIM statistics of this many recently used views (full "
        "images and ROI crops; 1.2 MB each at 300x170); 0 = recompute at every iteration. The same losses: "
        "room0 spent 0.1 s per keyframe recomputing them"
    )
    coarse_iters: int = Field(
        0, ge=0, description="coarse-to-fine: the first coarse_iters iterations of each mapped frame render "
        "full-image views at 1/coarse_downscale resolution (k×k colour mean, valid-depth mean, intrinsics "
        "scaled); later iterations, ROI-phase crops and footprint refinement stay at full resolution. 0 = "
        "off (matched-budget comparisons). All-coarse full-image iterations leave sub-pixel speckle: keep "
        "full-resolution iterations after them"
    )
    coarse_downscale: int = Field(2, ge=2, le=8, description="resolution divisor of coarse iterations")
    full_crop_fraction: float = Field(
        1.0, gt=0, le=1, description="full-image iterations render a random window of this share of the image "
        "area (same aspect, uniform position; stochastic pixel subsampling at full resolution). 1 = the whole "
        "image (matched-budget comparisons)"
    )
    roi_cull: bool = Field(
        True, description="ROI phase: render only the Gaussians whose 3σ sphere reaches the crop's frustum, whatever "
        "the map size (frustum_cull_min applies to full-image renders): a crop sees a small part of the map"
    )


#: old flat setting name → (group, name in the group), from before the settings were grouped. Input that still uses
#: one (YAML, ``--set``, keyword arguments) goes through :func:`migrate_flat_names`, which warns
#: (docs/mapper.md#old-flat-names)
FLAT_NAMES: dict[str, tuple[str, str]] = {
    "seeds_per_frame": ("seeding", "seeds_per_frame"),
    "first_frame_seeds": ("seeding", "first_frame_seeds"),
    "coverage_seeding": ("seeding", "coverage"),
    "coverage_alpha": ("seeding", "coverage_alpha"),
    "coverage_depth_factor": ("seeding", "coverage_depth_factor"),
    "rho": ("seeding", "rho"),
    "m_roi": ("seeding", "m_roi"),
    "m_bg": ("seeding", "m_bg"),
    "m_uniform": ("seeding", "m_uniform"),
    "gfd_eps": ("seeding", "gfd_eps"),
    "knn": ("seeding", "knn"),
    "init_opacity": ("seeding", "init_opacity"),
    "max_gaussians": ("budget", "max_gaussians"),
    "gaussians_per_pixel": ("budget", "gaussians_per_pixel"),
    "budget_mode": ("budget", "mode"),
    "gaussians_per_voxel": ("budget", "gaussians_per_voxel"),
    "budget_voxel_m": ("budget", "voxel_m"),
    "max_gaussians_cap": ("budget", "cap"),
    "evict": ("budget", "evict"),
    "roi_protect": ("budget", "roi_protect"),
    "pose_refine": ("pose", "refine"),
    "pose_track_iters": ("pose", "track_iters"),
    "pose_track_alpha": ("pose", "track_alpha"),
    "pose_lr_rot": ("pose", "lr_rot"),
    "pose_lr_trans": ("pose", "lr_trans"),
    "pose_init": ("pose", "init"),
    "exposure_comp": ("sensor", "exposure_comp"),
    "exposure_lr": ("sensor", "exposure_lr"),
    "motion_blur": ("sensor", "motion_blur"),
    "blur_exposure_s": ("sensor", "blur_exposure_s"),
    "blur_px_per_sample": ("sensor", "blur_px_per_sample"),
    "blur_max_samples": ("sensor", "blur_max_samples"),
    "rolling_shutter_s": ("sensor", "rolling_shutter_s"),
    "motion_estimate": ("sensor", "motion_estimate"),
    "rs_px_per_band": ("sensor", "rs_px_per_band"),
    "rs_max_bands": ("sensor", "rs_max_bands"),
    "blur_max_dt": ("sensor", "blur_max_dt"),
    "torch_threads": ("performance", "torch_threads"),
    "render_threads": ("performance", "render_threads"),
    "cpu_kernel": ("performance", "cpu_kernel"),
    "frustum_cull": ("performance", "frustum_cull"),
    "frustum_cull_min": ("performance", "frustum_cull_min"),
    "reference_paths": ("performance", "reference_paths"),
    "ssim_cache_views": ("performance", "ssim_cache_views"),
    "coarse_iters": ("performance", "coarse_iters"),
    "coarse_downscale": ("performance", "coarse_downscale"),
    "full_crop_fraction": ("performance", "full_crop_fraction"),
    "roi_cull": ("performance", "roi_cull"),
}


#: mapper settings renamed so that each name says what it bounds and means one thing across the configuration tree:
#: old name → new key (docs/reference.md#old-setting-names)
RENAMED_MAPPER_KEYS: dict[str, str] = {
    "max_keyframes": "stored_keyframes_max",
    "keyframe_every": "store_keyframe_every",
}

#: every old mapper setting name → its key now (dotted within the mapper section): the flat names
#: (:data:`FLAT_NAMES`) and the renamed settings (:data:`RENAMED_MAPPER_KEYS`); :class:`MapperConfig` migrates them
OLD_MAPPER_NAMES: dict[str, str] = {**{k: ".".join(v) for k, v in FLAT_NAMES.items()}, **RENAMED_MAPPER_KEYS}


def migrate_flat_names(data: Any, names: Optional[dict[str, str]] = None, where: str = "mapper") -> Any:
    """The one migration of old setting names to their keys now: the mapper's old flat names to their groups
    (:data:`FLAT_NAMES`) and renamed settings of every section to their new names.

    Each old key of the mapping ``data`` (a key path, dotted for a setting of a nested section: ``max_gaussians``,
    ``odometry.loop.max_keyframes``) is moved to its new key (``budget.max_gaussians``,
    ``odometry.loop.keyframe_images_max``). An old name wins over the same setting given by its new key: it comes from
    a later layer (a ``--set`` override or a keyword argument over a YAML file). Every use is reported: one
    ``DeprecationWarning`` and one warning log line naming the section and listing each old key with its new key
    (``docs/reference.md#old-setting-names``). :class:`MapperConfig` applies it to its input with
    :data:`OLD_MAPPER_NAMES`, :class:`gausslite.mission.config.AgentConfig` with its own table, so a YAML file, a
    ``--set`` override or a keyword argument written with the old names still loads, to the same values.

    Args:
        data: the settings of one section as a mapping (the ``mapper`` section of a GaussLite YAML, a mapper-only
            file, keyword arguments, the ``agent`` section); anything else is returned unchanged.
        names: old key → new key, both dotted within the section (None: :data:`OLD_MAPPER_NAMES`).
        where: the section's name in the messages.
    Returns:
        ``data`` itself when it holds no old name, else a new dict (sections along a moved key are copied, and
        sections given as models dumped to dicts of their explicitly set fields); the input is not modified.
    Raises:
        ValueError: a section along a new key is given as something other than a mapping.
    """
    if not isinstance(data, dict):
        return data
    names = OLD_MAPPER_NAMES if names is None else names
    found = [k for k in data if k in names] + [k for k in names if "." in k and _holds(data, k.split("."))]
    if not found:
        return data
    moves = ", ".join(f"{k} -> {names[k]}" for k in found)
    msg = f"old {where} setting names, use the new keys instead: {moves} (docs/reference.md#old-setting-names)"
    warnings.warn(msg, DeprecationWarning, stacklevel=2)
    log.warning("%s", msg)
    data = dict(data)
    for k in found:
        *old_path, old_leaf = k.split(".")
        value = _section(data, old_path, where).pop(old_leaf)
        *new_path, new_leaf = names[k].split(".")
        _section(data, new_path, where)[new_leaf] = value
    return data


def _holds(data: dict, path: list[str]) -> bool:
    """Whether the nested mapping ``data`` has a value at the key path ``path``."""
    node: Any = data
    for key in path[:-1]:
        node = node.get(key)
        if not isinstance(node, dict):
            return False
    return path[-1] in node


def _section(data: dict, path: list[str], where: str) -> dict:
    """The mapping at the key path ``path`` of ``data``, each level along it replaced in its parent by a copy (a
    model by a dict of its explicitly set fields, an absent or null section by an empty dict), so that changing it
    changes no input. Raises ValueError when a level is neither a mapping nor a model."""
    node = data
    for i, key in enumerate(path):
        sub = node.get(key) or {}
        if isinstance(sub, BaseModel):
            sub = sub.model_dump(exclude_unset=True)
        elif not isinstance(sub, dict):
            raise ValueError(f"{where}.{'.'.join(path[:i + 1])} must be a section (a mapping), got {sub!r}")
        node[key] = sub = dict(sub)
        node = sub
    return node


class MapperConfig(_Strict):
    """Mapper configuration. Defaults: paper values where it gives them, tuned otherwise.

    ``mode='uniform'`` is the baseline: relevance is ignored for seeding and optimisation (every
    component switch is treated as off). ``mode='gausslite'`` applies the switches in
    ``components``. Both modes share the Gaussian budget (``budget.max_gaussians``), seeds per frame
    (``seeding.seeds_per_frame``) and iterations per frame (``iters_per_frame``): the matched-budget
    comparison of paper Sec. IV.

    The settings of one concern are grouped: ``seeding``, ``budget``, ``pose``, ``sensor``, ``performance``,
    ``densify``, ``lr``, ``components``, ``roi_views``, ``detail``. Input that names a grouped setting by its old flat
    name (``max_gaussians``, ``pose_refine``, …: :data:`FLAT_NAMES`) or a renamed setting by its old name
    (``max_keyframes``, ``keyframe_every``: :data:`RENAMED_MAPPER_KEYS`) is migrated by :func:`migrate_flat_names`,
    with a warning.
    """

    mode: Literal["uniform", "gausslite"] = "uniform"
    seed: int = 0
    device: str = "cpu"
    backend: Literal["auto", "warp", "torch", "gsplat"] = "auto"
    iters_per_frame: int = Field(30, ge=1, description="Adam iterations per mapped frame")
    keyframe_budget_s: Optional[float] = Field(
        None, gt=0, description="online agent: wall-clock seconds per mapped keyframe (seeding included); "
        "iterations run until it is spent instead of iters_per_frame. None = iters_per_frame (offline map/ablate "
        "keep this for matched-budget comparisons)"
    )
    budget_clock: Literal["wall", "work"] = Field(
        "wall", description="clock of keyframe_budget_s and of optimize/finalize time bounds: 'wall' = wall time "
        "(a live robot); 'work' = the deterministic twin, modelled seconds of the work done (work_cost; "
        "gausslite.mapping.budget), for tests and reproducible budget studies"
    )
    work_cost: WorkCostConfig = WorkCostConfig()
    warmup_iters: int = Field(
        10, ge=0, description="ROI phase: full-image iterations before the active-only phase"
    )
    window: int = Field(8, ge=1, description="recent-keyframe window of view sampling")
    recent_prob: float = Field(
        0.5, ge=0, le=1, description="view sampling: probability of a draw from the recent window; otherwise "
        "the draw is over the whole mission's keyframes (MonoGS-style window + random past keyframes)"
    )
    roi_covis_weight: float = Field(
        2.0, ge=0, description="MVO mission-wide draws: keyframes that see the ROI weigh 1 + this (gausslite "
        "mode with MVO), the others 1"
    )
    stored_keyframes_max: int = Field(
        600, ge=1, description="keyframes the mapper's keyframe store keeps for the view draws and the final pass "
        "(compact: uint8 colour, float16 depth); beyond, the old keyframe closest in pose to its predecessor is dropped"
    )
    store_keyframe_every: int = Field(
        1, ge=1, description="every k-th mapped frame is stored in the keyframe store (the others are fitted "
        "while they are mapped only)"
    )
    current_frame_prob: float = Field(
        0.5, ge=0, le=1, description="without MVO: probability that an iteration uses the current frame"
    )
    final_iters: int = Field(
        0, ge=0, description="extra iterations over all keyframes after the last frame (0 = none)"
    )
    final_iters_per_keyframe: float = Field(
        0.0, ge=0, description="more final iterations: this many per keyframe, added to final_iters (the "
        "hand-held profile sets 20, the rendered one 5)"
    )
    final_schedule: Literal["full", "mapping"] = Field(
        "full", description="final pass iterations: 'full' = full-image, all Gaussians (both modes); 'mapping' = "
        "the mapping schedule in gausslite mode (per iters_per_frame final iterations, warmup_iters full-image, the "
        "rest ROI-phase on keyframes that see the ROI; uniform mode stays full-image)"
    )
    footprint_alpha: float = Field(
        0.5, ge=0, le=1, description="ROI phase: pixels with rendered alpha above this are the footprint"
    )
    roi_render: Literal["context", "active", "alternate"] = Field(
        "context", description="ROI phase render. 'active': the active Gaussians alone (the paper's wording); "
        "'context': every Gaussian, inactive ones frozen (no update, no κ), so the active ones are fitted to "
        "the pixels the full map shows; 'alternate': the two on successive ROI-phase iterations (measured: "
        "docs/results.md)"
    )
    roi_update: Literal["active", "visible", "all"] = Field(
        "visible", description="ROI phase: which Gaussians the Adam step updates: 'visible' (default: every "
        "Gaussian the ROI render draws, so inactive ones covering ROI pixels are fitted too; the others keep their "
        "values and moments; live under a keyframe budget 'active' loses to uniform: docs/realtime.md); 'active' "
        "(a = 1, the paper's rule); 'all' (a full Adam step). κ counts active Gaussians only"
    )
    roi_min_iters: int = Field(
        2, ge=0, description="ROI schedule: iterations of each keyframe the task region is owed, however few the "
        "budget buys: the warm-up ends early to leave this many, and the ROI phase's first this-many draws are among "
        "the keyframes that see the ROI (docs/mapper.md \"The ROI schedule\"); 0: the plain split"
    )
    roi_phase_views: Literal["any", "roi"] = Field(
        "any", description="ROI phase: the view is drawn as in the warm-up ('any'; a drawn view without ROI pixels "
        "gets a full-image iteration) or among the keyframes that see the ROI ('roi'; same recent-window / mission "
        "split, MVO)"
    )
    roi_loss: Literal["roi", "crop"] = Field(
        "roi", description="ROI phase loss: on ROI pixels inside the rendered footprint ('roi', the paper's Eq. 1 "
        "restriction) or on every pixel of the ROI crop ('crop': the ROI's box and roi_crop_pad around it, so "
        "Gaussians fitted to ROI pixels cannot spread over their neighbours unpenalised)"
    )
    roi_crop_pad: int = Field(
        8, ge=0, description="ROI phase: render only the ROI bounding box grown by this many pixels"
    )
    roi_outside_alpha: float = Field(
        0.0, ge=0, description="ROI phase: weight of a penalty on the rendered alpha of the crop's pixels outside the "
        "ROI (grown by roi_outside_margin_px), added to Eq. 1, so that what the step fits draws its ROI and nothing "
        "beside it. 0 = off (the mapper's own map: the background there is the map's). The share fine-tune "
        "(gausslite.sharing.finetune_subset) sets it: a subset rendered alone must not spread over its neighbours in a "
        "fused map (docs/sharing.md)"
    )
    roi_outside_margin_px: int = Field(
        2, ge=0, description="roi_outside_alpha: pixels around the ROI left out of the penalty (its anti-aliased edge)"
    )
    lambda_depth: float = Field(1.0, ge=0, description="λ_d in L = L1_c + λ_d L1_d + λ_s (1-SSIM)")
    roi_lambda_depth: Optional[float] = Field(
        None, ge=0, description="ROI phase: λ_d of ROI-phase iterations (depth supervision weighted up where the task "
        "is, against fitting few views' colour alone); None = lambda_depth"
    )
    roi_iso_weight: float = Field(
        0.0, ge=0, description="ROI phase: weight of an isotropy regulariser on the Gaussians the step updates, the "
        "mean |s - mean(s)| of their scales in metres (Gaussian-SLAM's isotropic term, Yugay et al. 2023), against "
        "needle-like Gaussians that fit their training views only; 0 = off"
    )
    lambda_ssim: float = Field(0.2, ge=0, description="λ_s")
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)

    lr: LearningRates = LearningRates()
    densify: DensifyConfig = DensifyConfig()
    components: ComponentSwitches = ComponentSwitches()
    seeding: SeedingConfig = SeedingConfig()
    budget: BudgetConfig = BudgetConfig()
    pose: PoseConfig = PoseConfig()
    sensor: SensorConfig = SensorConfig()
    performance: PerformanceConfig = PerformanceConfig()
    roi_views: RoiViewConfig = RoiViewConfig()
    detail: DetailConfig = DetailConfig()

    @model_validator(mode="before")
    @classmethod
    def _group_flat_names(cls, data: Any) -> Any:
        """Old names to their keys now (:func:`migrate_flat_names`, which warns)."""
        return migrate_flat_names(data)

    @model_validator(mode="after")
    def _check(self) -> "MapperConfig":
        if self.warmup_iters > self.iters_per_frame:
            raise ValueError(
                f"warmup_iters ({self.warmup_iters}) must not exceed iters_per_frame ({self.iters_per_frame})"
            )
        return self

    def effective(self) -> ComponentSwitches:
        """Switches actually in force: all off in uniform mode."""
        if self.mode == "uniform":
            return ComponentSwitches(sb=False, mvo=False, roi=False, sis=False, gfd=False)
        return self.components


def _coerce(text: str) -> Any:
    return yaml.safe_load(text)


def apply_overrides(data: dict, overrides: Iterable[str]) -> dict:
    """Apply ``key=value`` overrides (dotted keys, YAML-typed values) to a config dict.

    Raises:
        ValueError: an override without ``=``.
    """
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override must look like key=value, got {item!r}")
        key, value = item.split("=", 1)
        node = data
        parts = key.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ValueError(f"override {item!r}: {p} is not a section")
        node[parts[-1]] = _coerce(value)
    return data


def read_yaml(path: str | Path) -> dict:
    """The mapping at the top of a YAML file (the one reader of GaussLite configuration files).

    Raises:
        FileNotFoundError: missing file. ValueError: the top level is not a mapping.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"config file not found: {p}")
    data = yaml.safe_load(p.read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{p}: top level must be a mapping, got {type(data).__name__}")
    return data


def deep_merge(base: dict, top: dict) -> dict:
    """``base`` updated by ``top`` section by section (nested dicts merged, other values replaced); a new dict.
    Neither input is modified."""
    out = dict(base)
    for k, v in top.items():
        out[k] = deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def ablation_rows() -> list[tuple[str, ComponentSwitches]]:
    """The paper's Table 3 rows, enabling SB, MVO, ROI, SIS, GFD cumulatively."""
    names = ["sb", "mvo", "roi", "sis", "gfd"]
    rows = [("none", ComponentSwitches(sb=False, mvo=False, roi=False, sis=False, gfd=False))]
    on: dict[str, bool] = {n: False for n in names}
    for n in names:
        on[n] = True
        rows.append(("+" + n.upper(), ComponentSwitches(**on)))
    return rows
