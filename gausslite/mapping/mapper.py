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

The mapper does not care where w came from (ground truth or the attention front-end).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch

from gausslite.datasets.base import Frame
from gausslite.fused_ssim import ssim_mean
from gausslite.gaussians import GaussianMap
from gausslite.mapping.budget import WallClock, WorkClock, WorkCost
from gausslite.mapping.blur import blur_samples, exposure_twist, motion_deltas
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.exposure import ExposureModel, apply_exposure, invert_exposure
from gausslite.mapping.memory import KeyframeStore, SurfaceVoxels, unexplained_mask
from gausslite.mapping.model import GaussianModel
from gausslite.mapping.shutter import readout_norm, shutter_bands
from gausslite.mapping.poses import PoseRefiner, move_gaussians_for_pose_delta, nearest_key
from gausslite.mapping.seeding import local_median_nn_distance, seed_points, select_seeds
from gausslite.metrics import ssim_gt_stats, ssim_map
from gausslite.render import RenderOutput, blend_weights, rasterize
from gausslite.render.culling import frustum_cull_mask

log = logging.getLogger(__name__)


@dataclass
class Keyframe:
    """A training view kept in the mapper's window (tensors on the mapper's device).

    rgb (H,W,3) float32 [0,1]; depth (H,W) float32 metres (0 invalid); c2w (4,4) float64;
    K (3,3) float32; roi (H,W) bool or None; roi_box (x0, y0, x1, y1) pixels, the half-open
    bounding box of the ROI pixels, or None when the ROI is absent or empty.
    """

    frame_id: int
    rgb: torch.Tensor
    depth: torch.Tensor
    c2w: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    roi: Optional[torch.Tensor]
    roi_box: Optional[tuple[int, int, int, int]] = None
    #: cached :func:`gausslite.metrics.ssim_gt_stats` of ``rgb`` (filled by the first loss on this view;
    #: the mapper also keeps recent views' statistics, see ``MapperConfig.ssim_cache_views``)
    ssim_stats: Optional[tuple] = field(default=None, repr=False, compare=False)


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


def roi_box(roi: Optional[np.ndarray]) -> Optional[tuple[int, int, int, int]]:
    """Bounding box ``(x0, y0, x1, y1)`` in pixels (x1, y1 exclusive) of an (H, W) bool ROI; None when the ROI is
    None or empty (``Keyframe.roi_box``)."""
    if roi is None:
        return None
    ys, xs = np.nonzero(roi)
    if not ys.size:
        return None
    return (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)


def keyframe_from_frame(frame: Frame, device: torch.device, roi: Optional[np.ndarray] = None) -> Keyframe:
    """Convert a dataset ``Frame`` (uint8 rgb, metres depth) into a tensor ``Keyframe``."""
    box = roi_box(roi)
    return Keyframe(
        frame_id=frame.frame_id,
        rgb=torch.from_numpy(frame.rgb).to(device, torch.float32) / 255.0,
        depth=torch.from_numpy(np.ascontiguousarray(frame.depth)).to(device, torch.float32),
        c2w=torch.from_numpy(np.asarray(frame.c2w, dtype=np.float64)).to(device),
        K=torch.from_numpy(frame.intrinsics.K).to(device, torch.float32),
        width=frame.intrinsics.width,
        height=frame.intrinsics.height,
        roi=None if roi is None else torch.from_numpy(np.asarray(roi, dtype=bool)).to(device),
        roi_box=box,
    )


def downscale_keyframe(kf: Keyframe, factor: int) -> Keyframe:
    """The keyframe at 1/``factor`` resolution, for coarse full-image iterations (a two-level image
    pyramid, as Photo-SLAM's Gaussian-pyramid training; cost of an iteration ∝ pixels).

    Colour is the ``factor`` × ``factor`` area mean; depth the mean of the valid (> 0) depths of a block
    (0 where none is valid); the ROI a block's any. Intrinsics follow the pixel-centre convention of
    :mod:`gausslite.camera`: fx' = fx / f, cx' = (cx + 0.5) / f − 0.5 (same for y). Trailing rows and
    columns that do not fill a block are dropped. ``factor`` 1 returns ``kf`` itself.
    Raises ValueError for a factor < 1 or one that leaves no pixel.
    """
    f = int(factor)
    if f < 1 or kf.width < f or kf.height < f:
        raise ValueError(f"cannot downscale a {kf.width}x{kf.height} keyframe by {factor}")
    if f == 1:
        return kf
    h, w = kf.height // f, kf.width // f
    rgb = kf.rgb[: h * f, : w * f].reshape(h, f, w, f, 3).mean(dim=(1, 3))
    d = kf.depth[: h * f, : w * f].reshape(h, f, w, f)
    valid = (d > 0).sum(dim=(1, 3))
    depth = torch.where(valid > 0, d.sum(dim=(1, 3)) / valid.clamp_min(1), torch.zeros((), dtype=d.dtype))
    K = kf.K.clone()
    K[0, 0] /= f
    K[1, 1] /= f
    K[0, 2] = (K[0, 2] + 0.5) / f - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / f - 0.5
    roi, box = None, None
    if kf.roi is not None:
        roi = kf.roi[: h * f, : w * f].reshape(h, f, w, f).any(dim=3).any(dim=1)
        ys, xs = torch.nonzero(roi, as_tuple=True)
        if len(ys):
            box = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1)
    return Keyframe(frame_id=kf.frame_id, rgb=rgb.contiguous(), depth=depth.contiguous(), c2w=kf.c2w, K=K,
                    width=w, height=h, roi=roi, roi_box=box)


def window_keyframe(kf: Keyframe, x0: int, y0: int, x1: int, y1: int) -> Keyframe:
    """The keyframe restricted to pixels [x0, x1) × [y0, y1) (clipped to the image): the principal
    point moves with the window (cx -= x0, cy -= y0), so the window's render shows the same pixels as the
    full render (see :func:`crop_keyframe`). The ROI, if any, is cropped along."""
    x0, y0 = max(0, int(x0)), max(0, int(y0))
    x1, y1 = min(kf.width, int(x1)), min(kf.height, int(y1))
    if x1 <= x0 or y1 <= y0:
        raise ValueError(f"empty window [{x0}, {x1}) x [{y0}, {y1}) of keyframe {kf.frame_id}")
    K = kf.K.clone()
    K[0, 2] -= x0
    K[1, 2] -= y0
    roi, box = None, None
    if kf.roi is not None:
        roi = kf.roi[y0:y1, x0:x1]
        if kf.roi_box is not None:
            bx0, by0, bx1, by1 = kf.roi_box
            cx0, cy0, cx1, cy1 = max(bx0, x0), max(by0, y0), min(bx1, x1), min(by1, y1)
            box = (cx0 - x0, cy0 - y0, cx1 - x0, cy1 - y0) if cx1 > cx0 and cy1 > cy0 else None
    return Keyframe(frame_id=kf.frame_id, rgb=kf.rgb[y0:y1, x0:x1], depth=kf.depth[y0:y1, x0:x1], c2w=kf.c2w,
                    K=K, width=x1 - x0, height=y1 - y0, roi=roi, roi_box=box)


def random_window(kf: Keyframe, fraction: float, rng: np.random.Generator) -> Keyframe:
    """A window of up to ``fraction`` of the keyframe's area (the image's aspect ratio) for a full-image
    iteration: stochastic pixel subsampling at full resolution (no aliasing, unlike a downscaled view).

    The window's corner is drawn uniformly from positions that let it hang over the image border by up to
    its size less 8 pixels, and it is clipped to the image: every pixel is then covered about equally
    often (a window kept inside the image would cover a corner pixel 1/((W−w+1)(H−h+1)) as often as the
    centre). Windows at the border are smaller, hence cheaper.
    """
    s = float(np.sqrt(fraction))
    w = min(kf.width, max(16, int(round(kf.width * s))))
    h = min(kf.height, max(16, int(round(kf.height * s))))
    mx, my = min(8, w), min(8, h)
    x0 = int(rng.integers(-(w - mx), kf.width - mx + 1))
    y0 = int(rng.integers(-(h - my), kf.height - my + 1))
    return window_keyframe(kf, x0, y0, x0 + w, y0 + h)


def crop_keyframe(kf: Keyframe, pad: int) -> Keyframe:
    """The keyframe restricted to its ROI bounding box grown by ``pad`` pixels (clipped to the image).

    The principal point moves with the crop (cx -= x0, cy -= y0), so a render with the cropped K at
    the cropped size shows the same pixels as the full render, up to the EWA Jacobian clamp that
    follows the image bounds (Gaussians centred far outside the crop; ≤ 3e-3 colour in the tests).
    Raises ValueError without an ROI.
    """
    if kf.roi_box is None or kf.roi is None:
        raise ValueError(f"keyframe {kf.frame_id} has no ROI to crop to")
    bx0, by0, bx1, by1 = kf.roi_box
    return window_keyframe(kf, bx0 - pad, by0 - pad, bx1 + pad, by1 + pad)


def _gt_ssim_stats(kf: Keyframe, dtype: torch.dtype) -> tuple:
    """``kf.ssim_stats`` in ``dtype``, computed (:func:`gausslite.metrics.ssim_gt_stats`) and kept on ``kf``
    when missing or of another dtype."""
    if kf.ssim_stats is None or kf.ssim_stats[0].dtype != dtype:
        kf.ssim_stats = ssim_gt_stats(kf.rgb, dtype=dtype)
    return kf.ssim_stats


def photometric_loss(
    out: RenderOutput,
    kf: Keyframe,
    lambda_depth: float,
    lambda_ssim: float,
    mask: Optional[torch.Tensor] = None,
    reference: bool = False,
) -> torch.Tensor:
    """L = L1_colour + λ_d · L1_depth + λ_s · (1 − SSIM) (paper Eq. 1).

    Args:
        out: render of the keyframe's view.
        kf: the keyframe (ground truth).
        mask: (H, W) bool pixels the terms are restricted to (ROI ∩ footprint in the active phase),
            None = full image. The depth term also requires valid ground-truth depth.
        reference: SSIM by the slow reference path (:func:`gausslite.metrics.ssim_map`), no cached
            ground-truth statistics (``MapperConfig.reference_paths``); otherwise
            :func:`gausslite.fused_ssim.ssim_mean` (fused native SSIM on CPU, 20 -> 4 ms forward and
            backward at 300x170).
    Returns:
        scalar tensor (0 with a zero-gradient graph when the mask is empty). With a mask and λ_s = 0
        SSIM is not computed.
    """
    valid_d = kf.depth > 0
    if mask is None:
        l1c = (out.color - kf.rgb).abs().mean()
        dmask = valid_d
        if reference:
            s = ssim_map(out.color, kf.rgb, reference=True).mean()
        else:
            s = ssim_mean(out.color, kf.rgb, _gt_ssim_stats(kf, out.color.dtype))
    else:
        if not bool(mask.any()):
            return out.color.sum() * 0.0
        l1c = (out.color - kf.rgb).abs()[mask].mean()
        dmask = valid_d & mask
        if not lambda_ssim:
            s = 1.0
        elif reference:
            s = ssim_map(out.color, kf.rgb, reference=True)[mask].mean()
        else:
            s = ssim_mean(out.color, kf.rgb, _gt_ssim_stats(kf, out.color.dtype), mask=mask)
    l1d = (out.depth - kf.depth).abs()[dmask].mean() if bool(dmask.any()) else out.depth.sum() * 0.0
    return l1c + lambda_depth * l1d + lambda_ssim * (1.0 - s)


class Mapper:
    """The online mapper (one global map, known poses).

    Args:
        cfg: mapper configuration (mode, budgets, switches, learning rates).
    """

    def __init__(self, cfg: MapperConfig) -> None:
        self.cfg = cfg
        self.device = torch.device(cfg.device)
        if cfg.torch_threads:
            torch.set_num_threads(cfg.torch_threads)  # process-wide (see MapperConfig.torch_threads)
        self.model = GaussianModel(cfg.lr, self.device)
        self._background = torch.tensor(cfg.background, dtype=torch.float32, device=self.device)
        self.rng = np.random.default_rng(cfg.seed)
        #: clock of the keyframe budget and the idle/final time bounds (wall time, or its deterministic twin)
        self.clock = (WorkClock(WorkCost(**cfg.work_cost.model_dump())) if cfg.budget_clock == "work"
                      else WallClock())
        self.torch_gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
        #: every keyframe of the mission, compact and bounded (MVO draws from it)
        self.keyframes = KeyframeStore(cfg.max_keyframes, protect_recent=cfg.window)
        #: coarse voxels observed so far (scene-following budget)
        self.voxels = SurfaceVoxels(cfg.budget_voxel_m)
        #: (N,) float32 alpha-blending weight each Gaussian accumulated over the keyframes that saw it
        self.contribution = torch.zeros(0, device=self.device)
        self._last_unexplained = 1.0
        self._last_evicted = 0
        self.n_mapped = 0
        self._roi_iters = 0  # ROI-phase iterations so far (roi_render="alternate")
        self.stats: list[FrameStats] = []
        #: Gaussian budget in force (``max_gaussians``, or the scene/image rule; see MapperConfig)
        self.budget: Optional[int] = cfg.max_gaussians
        self.n_idle_iters = 0  # iterations of optimize() between keyframes
        #: iterations of time-budgeted map_frame calls (their density-control schedule spans calls)
        self.n_budget_iters = 0
        #: keyframe pose refinement (``cfg.pose_refine``), None when off
        self.poses: Optional[PoseRefiner] = (PoseRefiner(cfg.pose_lr_rot, cfg.pose_lr_trans)
                                             if cfg.pose_refine else None)
        #: per-keyframe exposure compensation (``cfg.exposure_comp``), None when off
        self.exposure: Optional[ExposureModel] = ExposureModel(cfg.exposure_lr) if cfg.exposure_comp else None
        #: motion over the exposure of every mapped frame, frame id → (6,) ξ_b = τ · (ω, v) with τ =
        #: ``cfg.blur_exposure_s`` (``cfg.motion_blur``; the camera's velocity ξ_b / τ also gives the rolling
        #: shutter's row poses, ``cfg.rolling_shutter_s``)
        self.blur: dict[int, np.ndarray] = {}
        #: rolling shutter: readout time per unit of normalised image y of the full image (seconds;
        #: :func:`gausslite.mapping.shutter.readout_norm`), set from the first mapped frame
        self._rs_norm = 0.0
        self._last_sensor: Optional[tuple] = None  # (timestamp, c2w, frame id) of the last mapped frame
        #: ground-truth SSIM statistics of recently used views (LRU, ``cfg.ssim_cache_views`` entries),
        #: keyed by (frame id, view size, principal point): keyframes loaded from the compact store and
        #: ROI crops are new objects at every draw, so their own ``ssim_stats`` would not survive
        self._ssim_cache: "OrderedDict[tuple, tuple]" = OrderedDict()
        self._reset_densify_stats()

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

    def render(self, c2w: torch.Tensor | np.ndarray, K: torch.Tensor | np.ndarray, width: int, height: int,
               subset: Optional[torch.Tensor] = None) -> RenderOutput:
        """Render the current map (no gradients) from a camera-to-world pose ``c2w`` (4,4)."""
        with torch.no_grad():
            return self._rasterize(c2w, K, width, height, subset)

    def render_frame(self, frame: Frame) -> RenderOutput:
        """Render the current map (no gradients) from a dataset frame's view: its intrinsics, and its pose
        with the keyframe's refined correction under ``pose_refine`` (:meth:`pose_of`), the pose every score
        of the map is taken at (SLAM systems score at their estimated poses), under ``motion_blur`` blurred by
        the frame's motion (:meth:`_render_view`), and under ``exposure_comp`` the frame's exposure response
        (its keyframe's, or the nearest keyframe's; colour clamped to [0, 1])."""
        intr = frame.intrinsics
        with torch.no_grad():
            out = self._render_view(self.pose_of(frame.frame_id, frame.c2w), intr.K, intr.width, intr.height,
                                    frame.frame_id, None)
        out, theta = self._exposed(out, frame.frame_id)
        return out if theta is None else dataclasses.replace(out, color=out.color.clamp(0.0, 1.0))

    def _exposed(self, out: RenderOutput, frame_id: int,
                 requires_grad: bool = False) -> tuple[RenderOutput, Optional[torch.Tensor]]:
        """``out`` with frame ``frame_id``'s exposure response applied to its colour (its keyframe's θ, or
        the nearest keyframe's), and that θ (6,) as a leaf tensor, with gradients if ``requires_grad``;
        ``(out, None)`` without exposure compensation or before the first keyframe."""
        if self.exposure is None or not self.exposure.params:
            return out, None
        theta = self.exposure.tensor(frame_id, self.device, requires_grad=requires_grad)
        return dataclasses.replace(out, color=apply_exposure(out.color, theta)), theta

    def pose_of(self, frame_id: int, c2w: np.ndarray) -> np.ndarray:
        """The pose to render frame ``frame_id`` at: ``c2w`` (4, 4) with the keyframe's refined correction
        (or the nearest keyframe's for a frame that is not one) under ``pose_refine``; ``c2w`` otherwise."""
        return self.poses.corrected(frame_id, c2w) if self.poses is not None else np.asarray(c2w, np.float64)

    def _render_view(self, c2w, K, width: int, height: int, frame_id: int, subset: Optional[torch.Tensor],
                     pose_xi: Optional[torch.Tensor] = None, detach_map: bool = False,
                     parts: Optional[list] = None, cull: bool = False) -> RenderOutput:
        """:meth:`_rasterize` of frame ``frame_id``'s view as the camera took it while moving (the nearest
        mapped frame's motion for a frame that was not mapped):

        - ``cfg.motion_blur`` (:mod:`gausslite.mapping.blur`): the mean colour, depth and alpha of K renders at
          ``c2w · E(s_k ξ_b)``;
        - ``cfg.rolling_shutter_s`` (:mod:`gausslite.mapping.shutter`): row bands, band b rendered alone (its
          rows only) from ``c2w · E(t_b ξ_b / τ)`` (and blurred around that pose), stacked top to bottom.

        The screen-space data (means2d, radii, ids) are the middle render's. ``parts``: a list that receives
        the renders as groups, one group per blur sample holding its bands (nothing when the view is rendered
        as one sharp image), for density statistics (:meth:`_accumulate`).
        """
        cfg = self.cfg
        rs = cfg.rolling_shutter_s > 0 and self._rs_norm > 0
        if not ((cfg.motion_blur or rs) and self.blur):
            return self._rasterize(c2w, K, width, height, subset, pose_xi=pose_xi, detach_map=detach_map, cull=cull)
        xi_b = self.blur[nearest_key(self.blur, frame_id)]
        n_blur = (blur_samples(xi_b, float(K[0, 0]), width, height, cfg.blur_px_per_sample, cfg.blur_max_samples)
                  if cfg.motion_blur else 1)
        bands = (shutter_bands(K, width, height, xi_b / cfg.blur_exposure_s, self._rs_norm, cfg.rs_px_per_band,
                               cfg.rs_max_bands) if rs else [(0, height, 0.0)])
        if n_blur <= 1 and len(bands) == 1 and bands[0][2] == 0.0:
            return self._rasterize(c2w, K, width, height, subset, pose_xi=pose_xi, detach_map=detach_map, cull=cull)
        groups: list[list[RenderOutput]] = [[] for _ in range(n_blur)]
        for y0, y1, t in bands:
            Kb = torch.as_tensor(K).clone()  # the band's rows alone: principal point moved up by its first row
            Kb[1, 2] -= y0
            # the blur's virtual poses around the band's readout time t (t / τ exposures from the frame's pose)
            for g, delta in zip(groups, motion_deltas(xi_b, n_blur, t / cfg.blur_exposure_s, self.device)):
                g.append(self._rasterize(c2w, Kb, width, y1 - y0, subset, pose_xi=pose_xi, detach_map=detach_map,
                                         view_delta=delta, cull=cull))
        if parts is not None:
            parts.extend(groups)

        def stacked(field: str) -> torch.Tensor:
            per_sample = [torch.cat([getattr(o, field) for o in g], 0) if len(g) > 1 else getattr(g[0], field)
                          for g in groups]
            return per_sample[0] if len(per_sample) == 1 else torch.stack(per_sample).mean(0)

        mid = groups[len(groups) // 2][len(bands) // 2]
        return dataclasses.replace(mid, color=stacked("color"), depth=stacked("depth"), alpha=stacked("alpha"))

    def _rasterize(self, c2w, K, width: int, height: int, subset: Optional[torch.Tensor],
                   pose_xi: Optional[torch.Tensor] = None, detach_map: bool = False,
                   view_delta: Optional[torch.Tensor] = None, cull: bool = False) -> RenderOutput:
        """Render the current parameters (differentiable) with the configured backend and threads.
        ``pose_xi`` (6,) float64: render from ``c2w · E(ξ)`` with gradients reaching ξ
        (:func:`~gausslite.mapping.poses.move_gaussians_for_pose_delta`); ``detach_map``: no gradient
        reaches the Gaussians (pose tracking); ``view_delta`` (4, 4) float64: render from
        ``c2w · E(ξ) · view_delta`` (a virtual pose within the exposure, :meth:`_render_view`); ``cull``: frustum
        culling whatever the map size (``frustum_cull_min``; ROI crops, ``roi_cull``)."""
        p = self.model.params
        if detach_map:
            p = {k: v.detach() for k, v in p.items()}
        means, quats = p["means"], p["quats"]
        if pose_xi is not None:
            c2w_t = torch.as_tensor(c2w, dtype=torch.float64, device=means.device)
            means, quats = move_gaussians_for_pose_delta(means, quats, c2w_t, pose_xi)
        cam = torch.as_tensor(c2w, dtype=torch.float64, device=means.device)
        if view_delta is not None:
            cam = cam @ view_delta.to(cam.device)
        vm = torch.linalg.inv(cam)
        if self.cfg.frustum_cull and (len(means) >= self.cfg.frustum_cull_min or cull):
            vis = frustum_cull_mask(means, p["log_scales"], vm, K, width, height)
            if subset is not None:
                vis &= subset if subset.dtype == torch.bool else torch.zeros_like(vis).index_fill_(0, subset, True)
            subset = vis
        if self.clock.charges:
            n_render = len(means) if subset is None else (
                int(subset.sum()) if subset.dtype == torch.bool else int(subset.numel()))
            self.clock.charge_render(int(width) * int(height), n_render, torch.is_grad_enabled())
        return rasterize(
            means, quats, p["log_scales"], p["opacity_logits"], p["colors"],
            K=K, width=width, height=height, viewmat=vm, subset=subset, background=self._background,
            backend=self.cfg.backend, num_threads=self.cfg.render_threads, cpu_kernel=self.cfg.cpu_kernel,
        )

    # ------------------------------------------------------------------ seeding
    def _update_budget(self, frame: Frame) -> int:
        """Resolve the Gaussian budget after observing ``frame`` (see ``MapperConfig.budget_mode``)."""
        cfg = self.cfg
        if cfg.max_gaussians is not None:
            self.budget = cfg.max_gaussians
        elif cfg.budget_mode == "image":
            if self.budget is None:
                self.budget = max(1, round(cfg.gaussians_per_pixel * frame.depth.size))
        else:
            self.voxels.add_frame(frame.depth, frame.intrinsics, frame.c2w)
            first = cfg.first_frame_seeds or 2 * cfg.seeds_per_frame
            self.budget = int(min(cfg.max_gaussians_cap, max(first, round(cfg.gaussians_per_voxel * len(self.voxels)))))
        return self.budget

    def _candidates(self, frame: Frame) -> tuple[np.ndarray, float]:
        """Seed candidate pixels of ``frame`` and their share of the valid pixels.

        With ``coverage_seeding`` and a non-empty map: the pixels the map does not explain
        (:func:`~gausslite.mapping.memory.unexplained_mask`, SplaTAM Eq. 9); otherwise every valid pixel.
        """
        cfg = self.cfg
        valid = frame.depth > 0
        if not cfg.coverage_seeding or len(self.model) == 0:
            return valid, 1.0
        intr = frame.intrinsics
        out = self.render(frame.c2w, intr.K, intr.width, intr.height)
        cand = unexplained_mask(frame.depth, out.alpha.cpu().numpy(), out.depth.cpu().numpy(),
                                cfg.coverage_alpha, cfg.coverage_depth_factor)
        return cand, float(cand.sum()) / max(1, int(valid.sum()))

    def _eviction_score(self, cur: GaussianMap) -> torch.Tensor:
        """(N,) score of the existing Gaussians at the budget: the lowest are replaced first."""
        cfg = self.cfg
        if cfg.evict == "opacity":
            return torch.sigmoid(cur.opacity_logits)
        score = self.contribution.clone()
        if cfg.mode == "gausslite":
            score[cur.active] *= cfg.roi_protect
        return score

    def _seed(self, frame: Frame, relevance: Optional[np.ndarray]) -> tuple[int, int]:
        cfg, sw = self.cfg, self.cfg.effective()
        budget = self._update_budget(frame)
        cand, share = self._candidates(frame)
        self._last_unexplained = share
        self._last_evicted = 0
        n = cfg.seeds_per_frame
        if self.n_mapped == 0 or len(self.model) == 0:
            n = cfg.first_frame_seeds or 2 * cfg.seeds_per_frame
        else:
            n = int(math.ceil(n * share))
        n = min(n, budget)
        if n == 0:
            return 0, 0
        sel = select_seeds(
            cand, n, self.rng, relevance=relevance if sw.sb else None, rgb=frame.rgb,
            sb=sw.sb, sis=sw.sis, gfd=sw.gfd, rho=cfg.rho, gfd_eps=cfg.gfd_eps,
        )
        if sel.pixels.size == 0:
            return 0, 0
        if sel.n_roi_shortfall:
            log.debug("frame %d: ROI has %d fewer candidate pixels than its seed share; moved to background",
                      frame.frame_id, sel.n_roi_shortfall)
        # a_i comes from w at the seed pixel, whatever the seeding strategy
        is_roi = relevance.ravel()[sel.pixels] if relevance is not None else np.zeros(sel.pixels.size, bool)
        pts, cols = seed_points(sel.pixels, frame.depth, frame.rgb, frame.intrinsics, frame.c2w)
        if self.exposure is not None:
            cols = invert_exposure(cols, self.exposure.of(frame.frame_id))  # into the map's exposure
        s0 = local_median_nn_distance(pts, k=cfg.knn)
        if sw.sis:
            mult = np.where(is_roi, cfg.m_roi, cfg.m_bg)
        else:
            mult = np.full(pts.shape[0], cfg.m_uniform)
        new = GaussianMap.from_points(
            torch.from_numpy(pts).float(), torch.from_numpy(cols).float(),
            torch.from_numpy(s0 * mult).float(), opacity=cfg.init_opacity,
            active=torch.from_numpy(is_roi),
        ).to(self.device)
        cur = self.model.to_map()
        n_old = len(self.model)
        merged = cur.append(new)
        parent = torch.cat([torch.arange(n_old, device=self.device),
                            torch.full((len(new),), -1, dtype=torch.int64, device=self.device)])
        if len(merged) > budget:
            # at the budget, the new seeds (what this frame sees and the map does not explain) always
            # enter and replace the existing Gaussians of lowest score (same rule in every mode)
            score = torch.cat([self._eviction_score(cur), torch.full((len(new),), float("inf"), device=self.device)])
            merged, keep = merged.cap(budget, score=score)
            parent = parent[keep]
            self._last_evicted = len(cur) + len(new) - len(merged)
        self._set_map(merged, parent)
        return int(sel.pixels.size), int(is_roi.sum())

    def _set_map(self, gmap: GaussianMap, parent: torch.Tensor) -> None:
        """``model.set_map`` that also carries each Gaussian's accumulated contribution along
        ``parent`` (new rows start at 0) and resets the densification statistics."""
        new = torch.zeros(parent.shape[0], device=self.device)
        has = parent >= 0  # rows of the current map: len(contribution) == len(model) always holds
        new[has] = self.contribution[parent[has]]
        self.contribution = new
        self.model.set_map(gmap, parent)
        self._reset_densify_stats()

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
        self.contribution = (contribution.to(self.device, torch.float32).clone() if contribution is not None
                             else torch.zeros(len(gmap), device=self.device))
        self._reset_densify_stats()

    def _accumulate_contribution(self, kf: Keyframe) -> None:
        """Add each Gaussian's alpha-blending weight Σ_pixels T_i α_i in keyframe ``kf`` to
        ``contribution`` (:func:`gausslite.render.blend_weights`)."""
        if len(self.model) == 0:
            return
        p = self.model.params
        if self.clock.charges:
            self.clock.charge_render(kf.width * kf.height, len(self.model), grad=False)
        self.contribution += blend_weights(
            p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"], K=kf.K, width=kf.width,
            height=kf.height, c2w=kf.c2w, background=self._background, backend=self.cfg.backend,
            num_threads=self.cfg.render_threads)

    # ------------------------------------------------------------------ density control
    def _reset_densify_stats(self) -> None:
        n = len(self.model)
        self._grad_accum = torch.zeros(n, device=self.device)
        self._grad_count = torch.zeros(n, device=self.device)

    def _accumulate(self, outs: list[RenderOutput], width: int, height: int, weight: float = 1.0) -> None:
        """Add each visible Gaussian's view-space gradient norm (pixels × half the image size, times
        ``weight``) to the density-control statistics. ``outs``: the renders of one image (one, or the row
        bands of a rolling-shutter view, whose gradients of a Gaussian are summed before the norm, so a
        Gaussian cut by a band edge counts as in one render)."""
        if len(outs) == 1:
            g, vis = outs[0].means2d.grad, outs[0].radii > 0
            if g is None:
                return
            ids, g = outs[0].ids[vis], g[vis]
        else:
            total = torch.zeros(len(self._grad_accum), 2, device=self._grad_accum.device)
            seen = torch.zeros(len(self._grad_accum), dtype=torch.bool, device=self._grad_accum.device)
            for o in outs:
                if o.means2d.grad is None:
                    continue
                v = o.radii > 0
                total.index_add_(0, o.ids[v], o.means2d.grad[v].to(total.dtype))
                seen[o.ids[v]] = True
            ids = torch.nonzero(seen).squeeze(1)
            if len(ids) == 0:
                return
            g = total[ids]
        scale = torch.tensor([weight * width / 2.0, weight * height / 2.0], device=g.device)
        norm = (g * scale).norm(dim=1)
        self._grad_accum.index_add_(0, ids, norm)
        self._grad_count.index_add_(0, ids, torch.ones_like(norm))

    def _densify_and_prune(self) -> dict:
        dc = self.cfg.densify
        gmap = self.model.to_map()
        n = len(gmap)
        if n == 0:
            return {}
        avg = self._grad_accum / self._grad_count.clamp_min(1)
        thr = torch.full_like(avg, dc.grad_threshold)
        if self.cfg.mode == "gausslite" and dc.roi_grad_factor < 1.0:
            thr[gmap.active] *= dc.roi_grad_factor  # densification allocated by relevance
        high = avg >= thr
        max_scale = gmap.log_scales.exp().max(dim=1).values
        split = high & (max_scale > dc.split_scale_m)
        clone = high & ~split & dc.clone
        room = (self.budget or n) - n
        n_new = int(clone.sum()) + int(split.sum())  # n_split=2: one extra row per split
        if n_new > room:
            # keep the highest-gradient candidates within the budget
            cand = torch.nonzero(clone | split).squeeze(1)
            order = torch.argsort(avg[cand] / thr[cand], descending=True)
            keep = cand[order[: max(room, 0)]]
            sel = torch.zeros(n, dtype=torch.bool, device=self.device)
            sel[keep] = True
            clone &= sel
            split &= sel
        stats = {"clone": int(clone.sum()), "split": int(split.sum())}
        if stats["clone"] or stats["split"]:
            gmap, parent = gmap.densify(clone, split, n_split=2, generator=self.torch_gen)
        else:
            parent = torch.arange(n, device=self.device)
        opacity = torch.sigmoid(gmap.opacity_logits)
        big = gmap.log_scales.exp().max(dim=1).values > dc.max_scale_m
        keep = ~((opacity < dc.prune_opacity) | big)
        stats["prune"] = int((~keep).sum())
        if stats["prune"]:
            gmap = gmap.prune(keep)
            parent = parent[keep]
        self._set_map(gmap, parent)
        return stats

    # ------------------------------------------------------------------ optimisation
    def _pick_view(self, current: Keyframe, roi_phase: bool = False) -> Keyframe:
        """The view of one iteration: from the recent window or the whole mission (see
        ``KeyframeStore.sample_index``); without MVO the current frame with ``current_frame_prob``. ``roi_phase``
        with ``roi_phase_views='roi'`` and MVO: among the keyframes that see the ROI."""
        cfg, sw = self.cfg, self.cfg.effective()
        n = len(self.keyframes)
        if not sw.mvo and (n <= 1 or self.rng.random() < cfg.current_frame_prob):
            return current
        roi_w = cfg.roi_covis_weight if sw.mvo else 0.0
        i = self.keyframes.sample_index(self.rng, cfg.window, cfg.recent_prob, roi_w,
                                        roi_only=roi_phase and cfg.roi_phase_views == "roi")
        if i == n - 1 and self.keyframes[i].frame_id == current.frame_id:
            return current
        return self.keyframes.load(i, self.device)

    def _iterate(self, kf: Keyframe, active_phase: bool, footprint_only: bool = False,
                 coarse: bool = False, footprint_roi: bool = False) -> float:
        """One Adam iteration on keyframe ``kf``.

        ``active_phase`` (paper III-D.1): update only active Gaussians (``roi_update='active'``; ``'visible'``:
        every Gaussian the ROI render draws, ``'all'``: a full step), with colour, depth and SSIM on
        ROI ∩ rendered footprint (``roi_loss='roi'``; ``'crop'``: every pixel of the crop), κ += 1 for each
        active Gaussian. The render covers only the ROI's
        bounding box (``roi_crop_pad``). It holds the active Gaussians alone (``roi_render='active'``,
        the paper's wording), or every Gaussian with the inactive ones frozen (``'context'``), so the
        active subset is fitted to the pixels the full map will show, or the two in turn. A view
        whose ROI is empty gets a full-image iteration instead (no κ): no ROI pixel, nothing to fit.
        ``footprint_only``: all Gaussians, loss on the rendered footprint (alpha > footprint_alpha);
        used to refine partial maps such as fused ROI subsets, which do not cover the background;
        with ``footprint_roi`` the loss is further restricted to the keyframe's ROI when it has a non-empty one.
        ``coarse``: a full-image iteration renders the view at 1/``coarse_downscale`` resolution
        (:func:`downscale_keyframe`).
        """
        cfg = self.cfg
        if active_phase and kf.roi_box is None:
            active_phase = False
        # density statistics: view-space gradients normalised by the full image size (crops and windows
        # keep its pixel scale; a downscaled view has its own), times a weight (below)
        stat_w, stat_h, stat_weight = kf.width, kf.height, 1.0
        if active_phase:
            view = crop_keyframe(kf, cfg.roi_crop_pad)
        elif coarse and not footprint_only:
            view = downscale_keyframe(kf, cfg.coarse_downscale)
            stat_w, stat_h = view.width, view.height
        elif cfg.full_crop_fraction < 1.0 and not footprint_only:
            view = random_window(kf, cfg.full_crop_fraction, self.rng)
            # the window's loss is a mean over fewer pixels: each pixel weighs full/window more, so its
            # Gaussians' gradients are larger by that factor; weigh them back to full-image scale
            stat_weight = view.width * view.height / float(kf.width * kf.height)
        else:
            view = kf
        alone = cfg.roi_render == "active" or (cfg.roi_render == "alternate" and self._roi_iters % 2 == 1)
        subset = self.model.active if active_phase and alone else None
        self._roi_iters += int(active_phase)
        # pose refinement: full-image iterations only (ROI-phase and footprint losses see part of the view)
        refine = (self.poses is not None and not active_phase and not footprint_only
                  and kf.frame_id in self.poses.corrections and kf.frame_id not in self.poses.fixed)
        xi = torch.zeros(6, dtype=torch.float64, device=self.device, requires_grad=True) if refine else None
        parts: list = []
        out = self._render_view(view.c2w, view.K, view.width, view.height, view.frame_id, subset, pose_xi=xi,
                                parts=parts, cull=active_phase and cfg.roi_cull)
        theta = None
        if self.exposure is not None and kf.frame_id in self.exposure.params:
            # the keyframe's exposure response; optimised where its pose is (full-image iterations)
            train_exposure = not active_phase and not footprint_only and self.exposure.trainable(kf.frame_id)
            out, theta = self._exposed(out, kf.frame_id, requires_grad=train_exposure)
        mask = None
        if active_phase and cfg.roi_loss == "roi":
            mask = view.roi & (out.alpha.detach() > cfg.footprint_alpha)
        elif footprint_only:
            mask = out.alpha.detach() > cfg.footprint_alpha
            if footprint_roi and view.roi is not None and view.roi_box is not None:  # empty ROI: the footprint
                mask = mask & view.roi
        cache_key = None
        if cfg.ssim_cache_views and not cfg.reference_paths:
            cache_key = (view.frame_id, view.width, view.height, float(view.K[0, 2]), float(view.K[1, 2]))
            if view.ssim_stats is None:
                view.ssim_stats = self._ssim_cache.get(cache_key)
        loss = photometric_loss(out, view, cfg.lambda_depth, cfg.lambda_ssim, mask, cfg.reference_paths)
        if cache_key is not None and view.ssim_stats is not None:
            self._ssim_cache[cache_key] = view.ssim_stats
            self._ssim_cache.move_to_end(cache_key)
            while len(self._ssim_cache) > cfg.ssim_cache_views:
                self._ssim_cache.popitem(last=False)
        loss.backward()
        if cfg.densify.enabled and (not active_phase or cfg.densify.active_phase_stats):
            # a blurred view: each of its K renders carries 1/K of the loss, so its gradients count K times
            for group in parts or [[out]]:
                self._accumulate(group, stat_w, stat_h, stat_weight * max(1, len(parts)))
        upd = None
        if active_phase and cfg.roi_update == "active":
            upd = self.model.active
        elif active_phase and cfg.roi_update == "visible":
            upd = torch.zeros(len(self.model), dtype=torch.bool, device=self.device)
            for o in [o for g in (parts or [[out]]) for o in g]:
                upd[o.ids[o.radii > 0]] = True
        self.model.step(update=upd, reference=cfg.reference_paths)
        if self.clock.charges:
            self.clock.charge_step(int(upd.sum()) if upd is not None else len(self.model))
        if active_phase:
            self.model.kappa[self.model.active] += 1
        if theta is not None and theta.requires_grad:
            self.exposure.step(kf.frame_id, theta.grad)
        if refine:
            new = self.poses.step(kf.frame_id, xi.grad, kf.c2w)
            if new is not None:
                kf.c2w.copy_(new)  # crops/windows of kf share this tensor
                self.keyframes.set_pose(kf.frame_id, new)
        return float(loss.detach())

    def map_frame(self, frame: Frame, relevance: Optional[np.ndarray] = None,
                  time_budget_s: Optional[float] = None) -> FrameStats:
        """Seed and optimise for one posed RGB-D frame.

        Args:
            frame: the frame (its pose is trusted).
            relevance: (H, W) bool relevance map w for this frame, or None (no ROI).
            time_budget_s: wall-clock budget of this call in seconds (seeding included); None →
                ``cfg.keyframe_budget_s``; both None → ``cfg.iters_per_frame`` iterations (offline
                ``map``/``ablate``). With a budget, iterations run until it is spent (at least one; the
                last one may overrun by one iteration's time). Phases (paper III-D.1): without a budget
                the first ``warmup_iters`` iterations are full-image, the rest ROI-phase; with a budget
                the first ``warmup_iters / iters_per_frame`` of the time left after seeding is full-image
                (at least one iteration when ``warmup_iters`` > 0), the rest ROI-phase, and density
                control runs every ``densify.every`` budgeted iterations counted across calls.
        Returns:
            FrameStats (seconds includes seeding, optimisation and density control).
        Raises:
            ValueError: relevance map of the wrong shape.
        """
        if relevance is not None and relevance.shape != frame.depth.shape:
            raise ValueError(f"relevance map shape {relevance.shape} != frame shape {frame.depth.shape}")
        cfg, sw = self.cfg, self.cfg.effective()
        t_wall = time.perf_counter()
        t0 = self.clock.now()
        if cfg.motion_blur or cfg.rolling_shutter_s > 0:
            # the camera's motion over this frame's exposure, from the sensor's poses (before refinement)
            prev = self._last_sensor
            xi_b = (np.zeros(6) if prev is None else
                    exposure_twist(prev[1], prev[0], frame.c2w, frame.timestamp, cfg.blur_exposure_s, cfg.blur_max_dt))
            self.blur[frame.frame_id] = xi_b
            if cfg.motion_estimate == "central" and prev is not None and len(prev) > 2 and prev[2] in self.blur \
                    and xi_b.any():
                # the previous frame's motion is now known on both sides: the mean of its backward and forward
                # estimates (the forward one alone for the first frame, which had none)
                back = self.blur[prev[2]]
                self.blur[prev[2]] = 0.5 * (back + xi_b) if back.any() else xi_b.copy()
            self._last_sensor = (float(frame.timestamp), np.asarray(frame.c2w, np.float64).copy(), int(frame.frame_id))
            self._rs_norm = readout_norm(cfg.rolling_shutter_s, frame.intrinsics.fy, frame.intrinsics.height)
        if self.poses is not None:
            # start from the latest keyframe's correction (or the sensor's pose); the first keyframe fixes the gauge
            E0 = self.poses.initial_correction(frame.frame_id) if cfg.pose_init == "inherit" else np.eye(4)
            frame = dataclasses.replace(frame, c2w=np.asarray(frame.c2w, np.float64) @ E0)
            self.poses.register(frame.frame_id, E0, fixed=self.n_mapped == 0)
            if cfg.pose_track_iters and self.n_mapped > 0 and len(self.model):
                frame = self._track(frame)
        if self.exposure is not None:
            # start from the latest keyframe's response; the first keyframe fixes the map's exposure
            self.exposure.register(frame.frame_id, self.exposure.initial(frame.frame_id), fixed=self.n_mapped == 0)
        n_seeds, n_roi = self._seed(frame, relevance)
        kf = keyframe_from_frame(frame, self.device, relevance)
        if self.n_mapped % cfg.keyframe_every == 0 or len(self.keyframes) == 0:
            self.keyframes.add(kf)
        loss = 0.0
        active_iters = 0
        n_iters = 0
        dstats: dict = {}
        has_active = bool(self.model.active.any())
        budget = self.cfg.keyframe_budget_s if time_budget_s is None else time_budget_s
        warm_until = None
        if budget is not None:
            # the paper's warm-up → ROI-phase schedule in time: the first warmup_iters / iters_per_frame of
            # the time left after seeding is full-image, the rest ROI-phase (a fixed warm-up count would
            # outlast a short budget and leave the ROI phase, κ and the shared subset empty)
            t_it = self.clock.now()
            warm_until = t_it + max(0.0, budget - (t_it - t0)) * cfg.warmup_iters / cfg.iters_per_frame
        for it in self._iterations(t0, budget):
            if warm_until is None:
                warm = it < cfg.warmup_iters
            else:  # at least one full-image iteration for the new seeds (unless warm-up is off)
                warm = cfg.warmup_iters > 0 and (it == 0 or self.clock.now() < warm_until)
            view = self._pick_view(kf, roi_phase=sw.roi and not warm and has_active)
            active_phase = sw.roi and not warm and has_active and view.roi is not None
            loss = self._iterate(view, active_phase, coarse=it < cfg.coarse_iters)
            active_iters += int(active_phase)
            n_iters += 1
            if warm_until is not None:  # a budget may give fewer than densify.every iterations per call
                self.n_budget_iters += 1
                dc_due = self.n_budget_iters % cfg.densify.every == 0
            else:
                dc_due = (it + 1) % cfg.densify.every == 0
            if cfg.densify.enabled and dc_due:
                for k, v in self._densify_and_prune().items():
                    dstats[k] = dstats.get(k, 0) + v
                has_active = bool(self.model.active.any())
        if cfg.evict == "contribution":
            self._accumulate_contribution(kf)
        self.n_mapped += 1
        st = FrameStats(frame.frame_id, time.perf_counter() - t_wall, n_seeds, n_roi, len(self.model), loss,
                        active_iters, dstats, n_iters, unexplained=self._last_unexplained,
                        budget=int(self.budget or 0), n_evicted=self._last_evicted)
        self.stats.append(st)
        return st

    def _track(self, frame: Frame) -> Frame:
        """Refine a new frame's pose against the current map before seeding (``pose_track_iters`` Adam
        steps on ξ alone, Gaussians fixed): colour and depth L1 on the pixels the map explains (rendered
        silhouette > ``pose_track_alpha``), SplaTAM's tracking loss (Keetha et al., CVPR 2024, Sec. 3.3)
        started from the sensor's pose instead of a motion model. Returns the frame at the tracked pose."""
        cfg = self.cfg
        kf = keyframe_from_frame(frame, self.device, None)
        kf.c2w = kf.c2w.clone()
        for _ in range(cfg.pose_track_iters):
            xi = torch.zeros(6, dtype=torch.float64, device=self.device, requires_grad=True)
            out = self._render_view(kf.c2w, kf.K, kf.width, kf.height, kf.frame_id, None, pose_xi=xi,
                                    detach_map=True)
            mask = out.alpha.detach() > cfg.pose_track_alpha
            if int(mask.sum()) < 0.05 * mask.numel():
                break  # the map hardly covers the frame: nothing to track against
            out, _ = self._exposed(out, kf.frame_id)
            loss = photometric_loss(out, kf, cfg.lambda_depth, 0.0, mask)
            loss.backward()
            new = self.poses.step(kf.frame_id, xi.grad, kf.c2w)
            if new is None:
                break
            kf.c2w = new
        return dataclasses.replace(frame, c2w=kf.c2w.cpu().numpy().copy())

    def _iterations(self, t0: float, budget: Optional[float]):
        """Iteration indices of one ``map_frame`` call: ``iters_per_frame`` (``budget`` None), or as many as
        fit ``budget`` seconds after ``t0``."""
        if budget is None:
            yield from range(self.cfg.iters_per_frame)
            return
        it = 0
        while it == 0 or self.clock.now() - t0 < budget:
            yield it
            it += 1

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
        if max_seconds is None and n_iters is None:
            raise ValueError("optimize needs max_seconds or n_iters")
        if (max_seconds is not None and not max_seconds > 0) or (n_iters is not None and n_iters < 1):
            raise ValueError(f"optimize bounds must be > 0, got max_seconds={max_seconds}, n_iters={n_iters}")
        if len(self.keyframes) == 0 or len(self.model) == 0:
            return 0
        cfg, sw = self.cfg, self.cfg.effective()
        roi_w = cfg.roi_covis_weight if sw.mvo else 0.0
        t0 = self.clock.now()
        done = 0
        while (n_iters is None or done < n_iters) and (done == 0 or max_seconds is None
                                                         or self.clock.now() - t0 < max_seconds):
            i = self.keyframes.sample_index(self.rng, cfg.window, cfg.recent_prob, roi_w)
            view = self.keyframes.load(i, self.device)
            phase = self.n_idle_iters % cfg.iters_per_frame
            active_phase = (sw.roi and phase >= cfg.warmup_iters and view.roi is not None
                            and bool(self.model.active.any()))
            self._iterate(view, active_phase)
            self.n_idle_iters += 1
            done += 1
            if cfg.densify.enabled and self.n_idle_iters % cfg.densify.every == 0:
                self._densify_and_prune()
        return done

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
        if max_seconds is not None and not max_seconds > 0:
            raise ValueError(f"max_seconds must be > 0, got {max_seconds}")
        cfg = self.cfg
        n = len(self.keyframes)
        total = cfg.final_iters + round(cfg.final_iters_per_keyframe * n)
        roi_schedule = cfg.final_schedule == "mapping" and cfg.effective().roi and bool(self.model.active.any())
        t0 = self.clock.now()
        done = 0
        for it in range(total if n else 0):
            if max_seconds is not None and self.clock.now() - t0 >= max_seconds:
                break
            view = self.keyframes.load(int(self.rng.integers(n)), self.device)
            # a keyframe without ROI pixels gets a full-image iteration (_iterate)
            self._iterate(view, active_phase=roi_schedule and it % cfg.iters_per_frame >= cfg.warmup_iters)
            done += 1
        return done

    # ------------------------------------------------------------------ checkpoint / resume
    def checkpoint_state(self, max_keyframes: Optional[int] = 32) -> dict:
        """CPU copy of what a restarted online mapper needs: the Gaussians (with κ, active flags and
        accumulated contribution), the newest ``max_keyframes`` stored keyframes in their compact form
        (None: all; they bound the file size of a long mission; the MVO window is the newest of them),
        the observed voxels, counters, budget and RNG state (not the Adam moments: a resumed mapper
        restarts them at zero, as for newly seeded Gaussians). ``torch.save``-able.
        """
        import dataclasses

        g = self.model.to_map().to("cpu")
        n = len(self.keyframes)
        first = 0 if max_keyframes is None else max(0, n - max(max_keyframes, self.cfg.window))
        kfs = [{f.name: getattr(self.keyframes[i], f.name) for f in dataclasses.fields(self.keyframes[i])}
               for i in range(first, n)]
        return {
            "gaussians": {f: getattr(g, f).clone() for f in ("means", "quats", "log_scales", "opacity_logits",
                                                             "colors", "active", "kappa")},
            "contribution": self.contribution.detach().cpu().clone(),
            "ids": self.model.ids.clone(), "next_id": int(self.model._next_id),
            "keyframes": kfs, "voxel_keys": self.voxels._keys.copy(),
            "n_mapped": self.n_mapped, "n_idle_iters": self.n_idle_iters, "n_budget_iters": self.n_budget_iters,
            "budget": self.budget,
            "roi_iters": self._roi_iters, "rng": self.rng.bit_generator.state,
            "pose_corrections": (None if self.poses is None else
                                 {"corrections": {k: v.copy() for k, v in self.poses.corrections.items()},
                                  "fixed": sorted(self.poses.fixed)}),
            "exposure": None if self.exposure is None else self.exposure.state(),
            "blur": {k: v.copy() for k, v in self.blur.items()}, "last_sensor": self._last_sensor,
            "rs_norm": self._rs_norm,
        }

    def restore_state(self, state: dict) -> None:
        """Load a :meth:`checkpoint_state` dict (replaces the map, keyframes and counters).

        Raises:
            KeyError / ValueError: a state dict that lacks fields or holds inconsistent shapes.
        """
        from gausslite.mapping.memory import StoredKeyframe

        g = GaussianMap(**{k: v.to(self.device) for k, v in state["gaussians"].items()})
        self.load_map(g, state.get("contribution"))
        if "ids" in state and int(state["ids"].shape[0]) == len(g):  # stable ids survive a restart (delta pushes)
            self.model.ids = state["ids"].clone()
            self.model._next_id = int(state["next_id"])
        self.keyframes = KeyframeStore(self.cfg.max_keyframes, protect_recent=self.cfg.window)
        self.keyframes._items = [StoredKeyframe(**d) for d in state["keyframes"]]
        self.voxels = SurfaceVoxels(self.cfg.budget_voxel_m)
        self.voxels._keys = np.asarray(state.get("voxel_keys", np.zeros(0, np.int64)), np.int64)
        self.n_mapped = int(state["n_mapped"])
        self.n_idle_iters = int(state["n_idle_iters"])
        self.n_budget_iters = int(state.get("n_budget_iters", 0))  # absent in older checkpoints
        self.budget = state["budget"]
        self._roi_iters = int(state["roi_iters"])
        self.rng.bit_generator.state = state["rng"]
        pc = state.get("pose_corrections")
        if self.poses is not None and pc:
            self.poses = PoseRefiner(self.cfg.pose_lr_rot, self.cfg.pose_lr_trans)
            for fid, E in pc["corrections"].items():
                self.poses.register(int(fid), E, fixed=int(fid) in set(pc["fixed"]))
        if self.exposure is not None and state.get("exposure"):
            self.exposure.load_state(state["exposure"])
        self.blur = {int(k): np.asarray(v, np.float64) for k, v in (state.get("blur") or {}).items()}
        self._last_sensor = state.get("last_sensor")
        self._rs_norm = float(state.get("rs_norm", 0.0))  # absent in older checkpoints
