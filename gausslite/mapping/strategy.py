"""Budget and density strategy of the mapper: the Gaussian budget, eviction at the budget, and 3DGS
adaptive density control (paper Sec. III-C; Kerbl et al. 2023), in the manner of gsplat's strategies:
settings in the typed config, state in :class:`DensityStrategy`, hooks the mapper calls around its steps.

- **Budget** (:meth:`DensityStrategy.update_budget`): ``max_gaussians``, or the scene rule
  (``gaussians_per_voxel`` × coarse voxels observed so far, capped by ``max_gaussians_cap``), or the image rule.
- **Eviction** (:meth:`DensityStrategy.eviction_score`): at the budget, new seeds replace the Gaussians with
  the lowest alpha-blending weight accumulated over the keyframes that saw them (``evict: contribution``),
  ROI Gaussians weighted by ``roi_protect``; or the lowest opacity.
- **Pruning** (:meth:`DensityStrategy.prune_idle`, after each keyframe's contribution): the Gaussians that a few
  keyframes have mapped and that still contribute under ``budget.prune_contribution`` pixels are removed, whether
  the budget is reached or not (Speedy-Splat's pruning of low-contribution Gaussians during training, Hanson et
  al. CVPR 2025).
- **Density control** (:meth:`DensityStrategy.accumulate` after each backward pass,
  :meth:`DensityStrategy.densify_and_prune` every ``densify.every`` iterations): clone/split on the mean
  view-space gradient norm, prune transparent or oversized Gaussians, within the budget.

The gradient statistic is resolution-free: a Gaussian's gradient in pixels times half the size of the full image at
the rendered view's resolution is its gradient in normalised image coordinates, which does not change with the pixel
size (a view k times finer gives 1/k the pixel gradient and k times the image size). ``densify.grad_threshold`` thus
holds for a coarse view, a downscaled one and the task region's detail crop (:mod:`gausslite.mapping.detail`) alike,
and none of them over- or under-densifies the region; ROI-phase iterations, detail crops included, feed the statistic
only under ``densify.active_phase_stats``.
"""

from __future__ import annotations

from typing import Optional

import torch

from gausslite.datasets.base import Frame
from gausslite.gaussians import GaussianMap
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.memory import SurfaceVoxels
from gausslite.mapping.model import GaussianModel
from gausslite.render import RenderOutput


class DensityStrategy:
    """Budget, eviction and density-control state of one map.

    Args:
        cfg: mapper configuration (budget fields, ``evict``, ``roi_protect``, ``densify``, ``mode``).
        model: the Gaussians being optimised; :meth:`set_map` and :meth:`densify_and_prune` replace its rows.
        generator: torch CPU generator of the split daughters' positions.
    Attributes:
        budget: Gaussian budget in force (None until the first frame under the scene/image rules).
        voxels: coarse voxels observed so far (scene budget).
        contribution: (N,) float32 alpha-blending weight each Gaussian accumulated over the keyframes that saw it,
            aligned with the model's rows.
        age: (N,) int32 keyframes whose contribution each Gaussian's row (or the row it derives from) took part in.
        pruned: Gaussians :meth:`prune_idle` removed so far.
        grad_accum, grad_count: (N,) float32 view-space gradient norm sums and counts since the last density step.
    """

    def __init__(self, cfg: MapperConfig, model: GaussianModel, generator: torch.Generator) -> None:
        self.cfg = cfg
        self.model = model
        self.generator = generator
        self.device = model.device
        self.budget: Optional[int] = cfg.budget.max_gaussians
        self.voxels = SurfaceVoxels(cfg.budget.voxel_m)
        self.contribution = torch.zeros(0, device=self.device)
        self.age = torch.zeros(0, dtype=torch.int32, device=self.device)
        self.pruned = 0
        self.reset_stats()

    # ------------------------------------------------------------------ budget and eviction
    def update_budget(self, frame: Frame) -> int:
        """Resolve the Gaussian budget after observing ``frame`` (``MapperConfig.budget.mode``) and return it."""
        cfg = self.cfg
        if cfg.budget.max_gaussians is not None:
            self.budget = cfg.budget.max_gaussians
        elif cfg.budget.mode == "image":
            if self.budget is None:
                self.budget = max(1, round(cfg.budget.gaussians_per_pixel * frame.depth.size))
        else:
            self.voxels.add_frame(frame.depth, frame.intrinsics, frame.c2w)
            first = cfg.seeding.first_frame_seeds or 2 * cfg.seeding.seeds_per_frame
            self.budget = int(min(cfg.budget.cap, max(first, round(cfg.budget.gaussians_per_voxel * len(self.voxels)))))
        return self.budget

    def eviction_score(self, cur: GaussianMap) -> torch.Tensor:
        """(N,) score of the existing Gaussians ``cur`` at the budget: the lowest are replaced first."""
        cfg = self.cfg
        if cfg.budget.evict == "opacity":
            return torch.sigmoid(cur.opacity_logits)
        score = self.contribution.clone()
        if cfg.mode == "gausslite":
            score[cur.active] *= cfg.budget.roi_protect
        return score

    def add_contribution(self, weights: torch.Tensor) -> None:
        """Add one keyframe's (N,) alpha-blending weights (:meth:`SensorRenderer.blend_weights
        <gausslite.mapping.sensor.SensorRenderer.blend_weights>`) to :attr:`contribution`; every row ages by one
        keyframe."""
        self.contribution += weights
        self.age += 1

    def prune_idle(self) -> int:
        """Remove the Gaussians of at least ``budget.prune_after`` keyframes whose :meth:`eviction_score` (pixels)
        is below ``budget.prune_contribution``: those that the views mapping them have hardly drawn, hidden or
        transparent. Call after :meth:`add_contribution` (which ``budget.evict: contribution`` runs, as the config
        requires with pruning on); no-op when ``prune_contribution`` is 0. Returns the number removed."""
        bc = self.cfg.budget
        if bc.prune_contribution <= 0 or len(self.model) == 0:
            return 0
        gmap = self.model.to_map()
        idle = (self.age >= bc.prune_after) & (self.eviction_score(gmap) < bc.prune_contribution)
        n = int(idle.sum())
        if n:
            keep = ~idle
            self.set_map(gmap.prune(keep), torch.nonzero(keep).squeeze(1))
            self.pruned += n
        return n

    # ------------------------------------------------------------------ map changes
    def set_map(self, gmap: GaussianMap, parent: torch.Tensor, new_anchor: int = -1) -> None:
        """Replace the model's rows by ``gmap`` (``parent`` (M,) int64: the current row each derives from, −1 for
        a new one, whose keyframe anchor is ``new_anchor``; :meth:`GaussianModel.set_map`), carry
        :attr:`contribution` along ``parent`` (new rows start at 0) and reset the density statistics."""
        new = torch.zeros(parent.shape[0], device=self.device)
        age = torch.zeros(parent.shape[0], dtype=torch.int32, device=self.device)
        has = parent >= 0  # rows of the current map: len(contribution) == len(model) always holds
        new[has] = self.contribution[parent[has]]
        age[has] = self.age[parent[has]]
        self.contribution, self.age = new, age
        self.model.set_map(gmap, parent, new_anchor)
        self.reset_stats()

    def reset(self, contribution: Optional[torch.Tensor] = None, age: Optional[torch.Tensor] = None) -> None:
        """After the whole map was replaced from outside (a loaded map): ``contribution`` (N,) float32 and ``age``
        (N,) int32, default zeros, and fresh density statistics.

        Raises:
            ValueError: ``contribution`` or ``age`` of another length than the model.
        """
        for name, t in (("contribution", contribution), ("age", age)):
            if t is not None and int(t.shape[0]) != len(self.model):
                raise ValueError(f"{name} has {t.shape[0]} rows, map has {len(self.model)}")
        self.contribution = (contribution.to(self.device, torch.float32).clone() if contribution is not None
                             else torch.zeros(len(self.model), device=self.device))
        self.age = (age.to(self.device, torch.int32).clone() if age is not None
                    else torch.zeros(len(self.model), dtype=torch.int32, device=self.device))
        self.reset_stats()

    # ------------------------------------------------------------------ density control
    def reset_stats(self) -> None:
        """Zero the view-space gradient statistics (one entry per model row)."""
        n = len(self.model)
        self.grad_accum = torch.zeros(n, device=self.device)
        self.grad_count = torch.zeros(n, device=self.device)

    def accumulate(self, outs: list[RenderOutput], width: float, height: float, weight: float = 1.0) -> None:
        """Post-backward hook: add each visible Gaussian's view-space gradient norm (pixels × half the image
        size, times ``weight``; ``width`` × ``height`` the full image at the view's resolution, fractional for a
        detail crop) to the density-control statistics. ``outs``: the renders of one image (one, or the
        row bands of a rolling-shutter view, whose gradients of a Gaussian are summed before the norm, so a
        Gaussian cut by a band edge counts as in one render; likewise the bands of one render in one pass,
        ``n_bands`` > 1)."""
        if len(outs) == 1 and outs[0].n_bands == 1:
            g, vis = outs[0].means2d.grad, outs[0].radii > 0
            if g is None:
                return
            ids, g = outs[0].ids[vis], g[vis]
        else:
            total = torch.zeros(len(self.grad_accum), 2, device=self.grad_accum.device)
            seen = torch.zeros(len(self.grad_accum), dtype=torch.bool, device=self.grad_accum.device)
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
        self.grad_accum.index_add_(0, ids, norm)
        self.grad_count.index_add_(0, ids, torch.ones_like(norm))

    def densify_and_prune(self) -> dict:
        """One density-control step on the model: clone (``densify.clone``) and split the Gaussians whose mean
        view-space gradient norm reaches ``densify.grad_threshold`` (× ``roi_grad_factor`` for active ones in
        gausslite mode), the highest first within the budget, then prune those below ``prune_opacity`` or larger
        than ``max_scale_m``. Returns ``{"clone": n, "split": n, "prune": n}`` (empty for an empty map)."""
        dc = self.cfg.densify
        gmap = self.model.to_map()
        n = len(gmap)
        if n == 0:
            return {}
        avg = self.grad_accum / self.grad_count.clamp_min(1)
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
            gmap, parent = gmap.densify(clone, split, n_split=2, generator=self.generator, split_mode=dc.split)
        else:
            parent = torch.arange(n, device=self.device)
        opacity = torch.sigmoid(gmap.opacity_logits)
        big = gmap.log_scales.exp().max(dim=1).values > dc.max_scale_m
        keep = ~((opacity < dc.prune_opacity) | big)
        stats["prune"] = int((~keep).sum())
        if stats["prune"]:
            gmap = gmap.prune(keep)
            parent = parent[keep]
        self.set_map(gmap, parent)
        return stats

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """Plain-data copy for checkpoints: ``contribution`` (N,) float32 CPU, ``age`` (N,) int32 CPU,
        ``pruned``, ``budget``, ``voxel_keys`` (not the gradient statistics, which restart at every density step
        anyway)."""
        return {"contribution": self.contribution.detach().cpu().clone(), "age": self.age.cpu().clone(),
                "pruned": self.pruned, "budget": self.budget, **self.voxels.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Restore a :meth:`state_dict` after the model's rows were loaded.

        Raises:
            KeyError: no ``budget``. ValueError: a contribution of another length than the model.
        """
        self.reset(state.get("contribution"), state.get("age"))
        self.pruned = int(state.get("pruned", 0))
        self.budget = state["budget"]
        self.voxels.load_state_dict(state)


__all__ = ["DensityStrategy"]
