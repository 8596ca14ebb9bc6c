"""The mapper's training step: one Adam iteration on one view (paper Sec. III-D, Eq. 1).

:class:`TrainStep` is what the mapping schedules (:class:`~gausslite.mapping.mapper.Mapper`), the share
fine-tune (:func:`gausslite.sharing.finetune_subset`), the fused-map refinement
(:func:`gausslite.fusion.refine.refine_map`) and the benches call: ``mapper.step(view, active_phase=...)``.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Optional

import numpy as np
import torch

from gausslite.mapping.config import MapperConfig
from gausslite.mapping.loss import outside_alpha, photometric_loss
from gausslite.mapping.memory import KeyframeStore
from gausslite.mapping.model import GaussianModel
from gausslite.mapping.poses import PoseRefiner
from gausslite.mapping.sensor import SensorRenderer
from gausslite.mapping.strategy import DensityStrategy
from gausslite.mapping.views import Keyframe, crop_keyframe, downscale_keyframe, random_window


class TrainStep:
    """One Adam iteration of the map (and of the view's pose and exposure when those are refined).

    Args:
        cfg: mapper configuration.
        model: the Gaussians; sensor: renders them as the sensor saw a view; strategy: receives the density
            statistics (post-backward hook).
        keyframes: the mission's keyframe store (a refined pose is written back to it).
        views: the ROI view store (:class:`~gausslite.mapping.roi_views.RoiViewStore`) a refined view pose is
            written back to when the view is not a keyframe, or None.
        poses: per-keyframe pose refinement, or None.
        clock: the budget clock (a deterministic clock is charged for every Adam step).
        rng: NumPy generator of random windows (``full_crop_fraction``).
    Attributes:
        roi_iters: ROI-phase iterations so far (``roi_render: alternate`` alternates on it).
    """

    def __init__(self, cfg: MapperConfig, model: GaussianModel, sensor: SensorRenderer, strategy: DensityStrategy,
                 keyframes: KeyframeStore, poses: Optional[PoseRefiner], clock, rng: np.random.Generator,
                 views=None) -> None:
        self.cfg, self.model, self.sensor, self.strategy = cfg, model, sensor, strategy
        self.views = views
        self.keyframes, self.poses, self.clock, self.rng = keyframes, poses, clock, rng
        self.device = model.device
        self.roi_iters = 0
        #: ground-truth SSIM statistics of recently used views (LRU, ``cfg.performance.ssim_cache_views`` entries),
        #: keyed by (frame id, view size, principal point): keyframes loaded from the compact store and
        #: ROI crops are new objects at every draw, so their own ``ssim_stats`` would not survive
        self.ssim_cache: "OrderedDict[tuple, tuple]" = OrderedDict()

    def state_dict(self) -> dict:
        """``{"roi_iters": n}`` (the SSIM cache is rebuilt on demand)."""
        return {"roi_iters": self.roi_iters}

    def load_state_dict(self, state: dict) -> None:
        """Restore a :meth:`state_dict`. Raises KeyError without ``roi_iters``."""
        self.roi_iters = int(state["roi_iters"])

    def __call__(self, kf: Keyframe, active_phase: bool = False, footprint_only: bool = False,
                 coarse: bool = False, footprint_roi: bool = False) -> float:
        """One Adam iteration on keyframe ``kf``; returns the loss (paper Eq. 1).

        ``active_phase`` (paper III-D.1): update only active Gaussians (``roi_update='active'``; ``'visible'``:
        every Gaussian the ROI render draws, ``'all'``: a full step), with colour, depth and SSIM on
        ROI ∩ rendered footprint (``roi_loss='roi'``; ``'crop'``: every pixel of the crop), κ += 1 for each
        active Gaussian. The render covers only the ROI's bounding box (``roi_crop_pad``). It holds the active
        Gaussians alone (``roi_render='active'``, the paper's wording), or every Gaussian with the inactive ones
        frozen (``'context'``), so the active subset is fitted to the pixels the full map will show, or the two
        in turn. A view whose ROI is empty gets a full-image iteration instead (no κ): no ROI pixel, nothing to
        fit.
        ``footprint_only``: all Gaussians, loss on the rendered footprint (alpha > footprint_alpha); used to
        refine partial maps such as fused ROI subsets, which do not cover the background; with
        ``footprint_roi`` the loss is further restricted to the keyframe's ROI when it has a non-empty one.
        ``coarse``: a full-image iteration renders the view at 1/``coarse_downscale`` resolution
        (:func:`~gausslite.mapping.views.downscale_keyframe`).
        Under ``detail.enabled`` an ROI-phase iteration on a keyframe with a detail crop (``kf.detail``,
        :mod:`gausslite.mapping.detail`) renders and fits that crop instead of the coarse one: same loss, the
        keyframe's pose correction and exposure response (keyed by its frame id; the crop shares its pose tensor).
        """
        cfg = self.cfg
        if active_phase and kf.roi_box is None:
            active_phase = False
        view, stat_w, stat_h, stat_weight = self._view_of(kf, active_phase, footprint_only, coarse)
        alone = cfg.roi_render == "active" or (cfg.roi_render == "alternate" and self.roi_iters % 2 == 1)
        subset = self.model.active if active_phase and alone else None
        self.roi_iters += int(active_phase)
        # the view's own alignment (pose and exposure): full-image iterations, and ROI-phase ones under
        # pose.roi_phase (the ROI is fitted against aligned views); never footprint losses (partial maps)
        align = not footprint_only and (not active_phase or cfg.pose.roi_phase)
        refine = (self.poses is not None and align
                  and kf.frame_id in self.poses.corrections and kf.frame_id not in self.poses.fixed)
        xi = torch.zeros(6, dtype=torch.float64, device=self.device, requires_grad=True) if refine else None
        parts: list = []
        out = self.sensor.render_view(view.c2w, view.K, view.width, view.height, view.frame_id, subset, pose_xi=xi,
                                      parts=parts, cull=active_phase and cfg.performance.roi_cull)
        theta = None
        exposure = self.sensor.exposure
        if exposure is not None and kf.frame_id in exposure.params:
            # the keyframe's exposure response; optimised where its pose is
            train_exposure = (align and exposure.trainable(kf.frame_id)
                              and (not active_phase or cfg.pose.roi_phase_exposure))
            out, theta = self.sensor.exposed(out, kf.frame_id, requires_grad=train_exposure)
        mask = None
        if active_phase and cfg.roi_loss == "roi":
            mask = view.roi & (out.alpha.detach() > cfg.footprint_alpha)
        elif footprint_only:
            mask = out.alpha.detach() > cfg.footprint_alpha
            if footprint_roi and view.roi is not None and view.roi_box is not None:  # empty ROI: the footprint
                mask = mask & view.roi
        cache_key = None
        if cfg.performance.ssim_cache_views and not cfg.performance.reference_paths:
            cache_key = (view.frame_id, view.width, view.height, float(view.K[0, 2]), float(view.K[1, 2]))
            if view.ssim_stats is None:
                view.ssim_stats = self.ssim_cache.get(cache_key)
        loss = self._loss(out, view, mask, active_phase, parts)
        if active_phase and cfg.roi_outside_alpha > 0 and view.roi is not None:
            loss = loss + cfg.roi_outside_alpha * outside_alpha(out.alpha, view.roi, cfg.roi_outside_margin_px)
        if cache_key is not None and view.ssim_stats is not None:
            self.ssim_cache[cache_key] = view.ssim_stats
            self.ssim_cache.move_to_end(cache_key)
            while len(self.ssim_cache) > cfg.performance.ssim_cache_views:
                self.ssim_cache.popitem(last=False)
        loss.backward()
        if cfg.densify.enabled and (not active_phase or cfg.densify.active_phase_stats):
            # a blurred view: each of its K renders carries 1/K of the loss, so its gradients count K times
            for group in parts or [[out]]:
                self.strategy.accumulate(group, stat_w, stat_h, stat_weight * max(1, len(parts)))
        upd = None
        if active_phase and cfg.roi_update == "active":
            upd = self.model.active
        elif active_phase and cfg.roi_update == "visible":
            upd = torch.zeros(len(self.model), dtype=torch.bool, device=self.device)
            for o in [o for g in (parts or [[out]]) for o in g]:
                upd[o.ids[o.radii > 0]] = True
        self.model.step(update=upd, reference=cfg.performance.reference_paths)
        if self.clock.charges:
            self.clock.charge_step(int(upd.sum()) if upd is not None else len(self.model))
        if active_phase:
            self.model.kappa[self.model.active] += 1
        if theta is not None and theta.requires_grad:
            exposure.step(kf.frame_id, theta.grad)
        if refine:
            new = self.poses.step(kf.frame_id, xi.grad, kf.c2w, cfg.pose.roi_lr_scale if active_phase else 1.0)
            if new is not None:
                self._write_pose(kf, new)
        return float(loss.detach())

    def _view_of(self, kf: Keyframe, active_phase: bool, footprint_only: bool,
                 coarse: bool) -> tuple[Keyframe, float, float, float]:
        """The view one iteration on ``kf`` renders (ROI crop, detail crop, downscaled view, random window or the
        keyframe itself) and its density-statistics scale: (view, width, height, weight), the gradients normalised by
        the full image size at the view's resolution (crops and windows keep the keyframe's pixel scale; a
        downscaled view and a detail crop have their own: :class:`~gausslite.mapping.strategy.DensityStrategy`)."""
        cfg = self.cfg
        detail = kf.detail if active_phase and cfg.detail.enabled else None
        if detail is not None and detail.roi_box is not None:
            scale = float(detail.K[0, 0]) / float(kf.K[0, 0])
            return detail, kf.width * scale, kf.height * scale, 1.0
        if active_phase:
            return crop_keyframe(kf, cfg.roi_crop_pad), kf.width, kf.height, 1.0
        if coarse and not footprint_only:
            view = downscale_keyframe(kf, cfg.performance.coarse_downscale)
            return view, view.width, view.height, 1.0
        if cfg.performance.full_crop_fraction < 1.0 and not footprint_only:
            view = random_window(kf, cfg.performance.full_crop_fraction, self.rng)
            # the window's loss is a mean over fewer pixels: each pixel weighs full/window more, so its
            # Gaussians' gradients are larger by that factor; weigh them back to full-image scale
            return view, kf.width, kf.height, view.width * view.height / float(kf.width * kf.height)
        return kf, kf.width, kf.height, 1.0

    def _loss(self, out, view: Keyframe, mask: Optional[torch.Tensor], active_phase: bool, parts: list) -> torch.Tensor:
        """Eq. 1 on ``view`` (ROI-phase iterations with their own depth weight ``roi_lambda_depth`` and the isotropy
        term ``roi_iso_weight`` when set)."""
        cfg = self.cfg
        lam_d = cfg.roi_lambda_depth if active_phase and cfg.roi_lambda_depth is not None else cfg.lambda_depth
        loss = photometric_loss(out, view, lam_d, cfg.lambda_ssim, mask, cfg.performance.reference_paths)
        if active_phase and cfg.roi_iso_weight > 0:
            loss = loss + cfg.roi_iso_weight * self._isotropy(parts or [[out]])
        return loss

    def _isotropy(self, groups) -> torch.Tensor:
        """Mean over the Gaussians a render drew of |s − mean(s)| (scales in metres): Gaussian-SLAM's isotropic
        regulariser (Yugay et al. 2023, Eq. 9), 0 when none is drawn."""
        ids = torch.unique(torch.cat([o.ids[o.radii > 0] for g in groups for o in g]))
        if ids.numel() == 0:
            return torch.zeros((), device=self.device)
        s = torch.exp(self.model.params["log_scales"][ids])
        return (s - s.mean(dim=1, keepdim=True)).abs().mean()

    def _write_pose(self, kf: Keyframe, new: torch.Tensor) -> None:
        """Keep view ``kf``'s refined pose ``new`` (4, 4): in the view (its crops and windows share the tensor) and
        in the store that holds it (a keyframe, or else a stored ROI view)."""
        kf.c2w.copy_(new)
        if not self.keyframes.set_pose(kf.frame_id, new) and self.views is not None:
            self.views.set_pose(kf.frame_id, new)


__all__ = ["TrainStep"]
