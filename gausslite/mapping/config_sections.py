"""The sections of the mapper's configuration (:class:`gausslite.mapping.config.MapperConfig`, which re-exports them):
one typed pydantic model per concern: learning rates, density control, the deterministic clock's cost model, the
component switches, seeding, the Gaussian budget, poses, the sensor model, ROI views, the detail layer and speed.
"""

from __future__ import annotations

from typing import Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["StrictModel", "LearningRates", "DensifyConfig", "WorkCostConfig", "ComponentSwitches", "SeedingConfig",
           "BudgetConfig", "PoseConfig", "SensorConfig", "RoiViewConfig", "DetailConfig", "PerformanceConfig"]


class StrictModel(BaseModel):
    """A settings model that refuses unknown keys and checks values on assignment too."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class LearningRates(StrictModel):
    """Adam learning rates per parameter group (3DGS / Gaussian-SLAM style groups)."""

    means: float = Field(2.5e-4, gt=0, description="metres per step (scaled by scene_scale)")
    quats: float = Field(2e-3, gt=0)
    log_scales: float = Field(5e-3, gt=0)
    opacity_logits: float = Field(1e-1, gt=0)
    colors: float = Field(1e-2, gt=0)


class DensifyConfig(StrictModel):
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
    split: Literal["sample", "axis"] = Field(
        "sample", description="how a Gaussian splits (GaussianMap.densify): 'sample' = 3DGS, two daughters sampled "
        "from it and shrunk by 1.6 on every axis; 'axis' = two daughters on its longest axis, moment-matched, with "
        "the opacity correction of Rota Bulo et al. 2024 (the image barely changes at the split; measured: "
        "docs/mapper.md, 'Density control')"
    )
    prune_opacity: float = Field(0.005, ge=0, description="prune Gaussians with opacity below this")
    max_scale_m: float = Field(0.5, gt=0, description="prune Gaussians with a larger max scale")
    active_phase_stats: bool = Field(
        False, description="also accumulate the view-space gradient statistics in ROI-phase iterations. Off: "
        "those iterations restrict the loss to the ROI (and, with roi_render='active', render only the "
        "active subset), so their gradients are not comparable with grad_threshold (measured: docs/results.md)"
    )


class WorkCostConfig(StrictModel):
    """Cost model of the deterministic budget clock (:class:`gausslite.mapping.budget.WorkCost`; seconds)."""

    render_s: float = Field(1.9e-3, ge=0, description="per differentiable render (forward + backward)")
    pixel_s: float = Field(2.2e-7, ge=0, description="per rendered pixel")
    gaussian_s: float = Field(9.3e-7, ge=0, description="per Gaussian a render projects")
    step_s: float = Field(2.0e-3, ge=0, description="per Adam step")
    step_gaussian_s: float = Field(1.4e-6, ge=0, description="per Gaussian an Adam step updates")
    no_grad_factor: float = Field(0.4, ge=0, description="a render without gradients costs this share")


class ComponentSwitches(StrictModel):
    """The paper's ablation switches (Table 3): SB, MVO, ROI, SIS, GFD."""

    sb: bool = Field(True, description="ROI seed budgeting (III-C.1)")
    mvo: bool = Field(True, description="multi-view optimisation (III-D.2)")
    roi: bool = Field(True, description="two-phase ROI optimisation (III-D.1)")
    sis: bool = Field(True, description="stratified sampling + tiered initial scale (III-C.2)")
    gfd: bool = Field(True, description="gradient-focused densification (III-C.3)")


class SeedingConfig(StrictModel):
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


class BudgetConfig(StrictModel):
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
    prune_contribution: float = Field(
        0.0, ge=0, description="prune, after each keyframe, the Gaussians mapped for at least prune_after keyframes "
        "whose contribution (the eviction score: alpha-blending weight summed over the pixels of the keyframes "
        "since their birth, active ones × roi_protect) is below this many pixels; needs evict: contribution. "
        "0: off (measured live: docs/realtime.md#pruning)"
    )
    prune_after: int = Field(
        3, ge=1, description="keyframes a Gaussian is mapped for before prune_contribution may prune it"
    )

    @model_validator(mode="after")
    def _check_pruning(self) -> "BudgetConfig":
        if self.prune_contribution > 0 and self.evict != "contribution":
            raise ValueError(f"prune_contribution ({self.prune_contribution}) prunes by contribution, which is only "
                             f"accumulated with evict: contribution, not {self.evict!r}")
        return self


class PoseConfig(StrictModel):
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
    align: Literal["off", "depth"] = Field(
        "off", description="keyframe alignment: a new keyframe's depth registered, point to plane, to the raw depth "
        "of the keyframes mapped before it, at the poses the map holds for them, before it seeds or trains "
        "(frame-to-model, KinectFusion Sec. 3.5; gausslite.mapping.alignment): for poses with errors of "
        "centimetres (a robot's odometry, a SLAM estimate); it starts from the latest keyframe's correction. "
        "'off': the keyframe keeps its pose (measured per sensor: docs/mapper.md#keyframe-alignment)"
    )
    align_voxel_m: float = Field(
        0.02, gt=0, description="keyframe alignment: the depth model's voxel size δ (metres); the registration runs "
        "at 2δ, then δ"
    )
    align_width: int = Field(
        80, ge=8, description="keyframe alignment: a keyframe's depth is sampled every W // align_width pixels"
    )
    align_min_fitness: float = Field(
        0.3, ge=0, le=1, description="keyframe alignment: the least share of the keyframe's sampled points with a "
        "model point within 1.5δ for the alignment to be kept (less: too little overlap, the keyframe keeps its pose)"
    )
    align_max_keyframes: int = Field(
        1000, ge=1, description="keyframe alignment: depth clouds kept (about 40 kB each); beyond it the oldest are "
        "dropped, the first keyframe's kept"
    )


class SensorConfig(StrictModel):
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


class RoiViewConfig(StrictModel):
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


class DetailConfig(StrictModel):
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


class PerformanceConfig(StrictModel):
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
        "Warp tile kernels they replace (the baseline of the retired bench.mapper, docs/history.md#mapper); the same "
        "renders to float32 rounding"
    )
    frustum_cull: bool = Field(
        True, description="render only the Gaussians whose 3σ sphere reaches the (padded) view frustum "
        "(gausslite.render.culling; the same image): a long mission's map is mostly out of view"
    )
    frustum_cull_min: int = Field(20_000, ge=0, description="cull only maps of at least this many Gaussians")
    reference_paths: bool = Field(
        False, description="use the slow reference implementations of the ROI-phase Adam step (full step, "
        "then frozen rows restored) and of SSIM (15 filtered channels, no cached ground-truth statistics): "
        "the same results to float rounding, for parity checks and as the retired bench.mapper's baseline "
        "(docs/history.md#mapper)"
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
    bands_in_one_pass: bool = Field(
        True, description="motion blur and rolling shutter: render a view's blur samples and row bands (each from "
        "its own pose) in one compositing and backward pass (gausslite.render.rasterize_bands), the band edges on "
        "the rasterizer's 16-row tiles; False = one render per blur sample and band, bands at any row "
        "(docs/mapper.md, 'One render per view')"
    )
