"""Seeding one frame (paper Sec. III-C): :class:`FrameSeeder`, the mapper's part that turns the pixels a frame shows
and the map does not explain into new Gaussians.

Per frame: the seed candidates (every valid pixel, or under ``seeding.coverage`` the pixels the map does not explain,
SplaTAM Eq. 9); under ``seeding.adopt`` the Gaussians that already draw the task region join the task, and relevant
pixels the task's Gaussians leave uncovered get ROI seeds; the seed pixels (uniform, or SB/SIS/GFD with the relevance
map, :func:`~gausslite.mapping.seeding.select_seeds`; with a detail crop the region's from its finer pixels); their
initial scale from the local nearest-neighbour spacing; at the Gaussian budget, the new seeds replace the Gaussians of
lowest eviction score (:class:`~gausslite.mapping.strategy.DensityStrategy`).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from gausslite.datasets.base import Frame
from gausslite.gaussians import GaussianMap
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.detail import DetailCrop, detail_pool, detail_seed_pixels
from gausslite.mapping.exposure import invert_exposure
from gausslite.mapping.memory import unexplained_mask
from gausslite.mapping.model import GaussianModel
from gausslite.mapping.seeding import (SeedSelection, local_median_nn_distance, seed_points, select_seeds,
                                       weighted_choice)
from gausslite.mapping.sensor import SensorRenderer
from gausslite.mapping.strategy import DensityStrategy
from gausslite.render import RenderOutput

log = logging.getLogger(__name__)

__all__ = ["FrameSeeder", "SeedStats"]


@dataclass
class SeedStats:
    """What seeding one frame did (:meth:`FrameSeeder.seed`, :meth:`Mapper.seed_frame
    <gausslite.mapping.mapper.Mapper.seed_frame>`)."""

    n_seeds: int = 0  #: new Gaussians
    n_roi: int = 0  #: of them active (a = 1: their seed pixel is in the relevance map)
    unexplained: float = 1.0  #: share of valid pixels the map did not explain before seeding
    n_evicted: int = 0  #: existing Gaussians the new seeds replaced at the budget
    n_adopted: int = 0  #: existing Gaussians that joined the task (``seeding.adopt``)
    n_gap_seeds: int = 0  #: of the new seeds, those on relevant pixels the task's Gaussians left uncovered


class FrameSeeder:
    """Seeds new Gaussians into the map where a frame is not explained by it (:meth:`seed`).

    Args:
        cfg: the mapper's configuration (``seeding``, ``components``, ``mode``).
        model: the Gaussians the seeds join.
        strategy: the budget and the eviction score (its ``set_map`` takes the merged map).
        sensor: renders the map for the coverage and adoption tests; its exposure model maps seed colours into the
            map's exposure.
        rng: the mapper's generator (seed pixels, adoption gap draws).
    """

    def __init__(self, cfg: MapperConfig, model: GaussianModel, strategy: DensityStrategy, sensor: SensorRenderer,
                 rng: np.random.Generator) -> None:
        self.cfg, self.model, self.strategy, self.sensor, self.rng = cfg, model, strategy, sensor, rng
        self.device = model.device

    def _render(self, c2w, K, width: int, height: int, subset: Optional[torch.Tensor] = None) -> RenderOutput:
        """The current map (no gradients) from ``c2w`` (4, 4), intrinsics ``K`` (3, 3), at ``width`` × ``height``."""
        with torch.no_grad():
            return self.sensor.rasterize(c2w, K, width, height, subset)

    def seed(self, frame: Frame, relevance: Optional[np.ndarray], detail: Optional[DetailCrop] = None, *,
             first: bool = False) -> SeedStats:
        """Seed new Gaussians where ``frame`` is not explained by the map (paper Sec. III-C).

        The count is ``seeds_per_frame`` × the unexplained share of valid pixels (twice as many, or
        ``first_frame_seeds``, on the first frame), within the budget; pixels are drawn uniformly or by SB/SIS/GFD
        with the relevance map; a new Gaussian is active when its seed pixel is relevant. At the budget the new
        seeds replace the existing Gaussians of lowest eviction score (:class:`DensityStrategy`). With a ``detail``
        crop and SB the region's seeds come from the crop's pixels (:meth:`_two_resolution_seeds`).

        Args:
            frame: posed RGB-D frame (world frame ``c2w``, metres).
            relevance: (H, W) bool relevance map w, or None.
            detail: the keyframe's detail crop (:func:`~gausslite.mapping.detail.cut_detail`), or None.
            first: the mapper's first frame (it seeds ``first_frame_seeds``; so does a frame over an empty map).
        Returns:
            :class:`SeedStats`.
        """
        cfg, sw = self.cfg, self.cfg.effective()
        budget = self.strategy.update_budget(frame)
        cand, share = self._candidates(frame)
        stats = SeedStats(unexplained=share)
        gap = self._adopt_task_region(frame, relevance, cand, stats)
        n = cfg.seeding.seeds_per_frame
        if first or len(self.model) == 0:
            n = cfg.seeding.first_frame_seeds or 2 * cfg.seeding.seeds_per_frame
        else:
            n = int(math.ceil(n * share))
        n = min(n, budget)
        if detail is not None and sw.sb and relevance is not None:
            seeds = self._two_resolution_seeds(frame, relevance, cand, gap, n, budget, detail, stats)
        else:
            seeds = self._frame_seeds(frame, relevance, cand, gap, n, budget, stats)
        if seeds is None:
            return stats
        pts, cols, is_roi = seeds
        if self.sensor.exposure is not None:
            cols = invert_exposure(cols, self.sensor.exposure.of(frame.frame_id))  # into the map's exposure
        s0 = local_median_nn_distance(pts, k=cfg.seeding.knn)
        if sw.sis:
            mult = np.where(is_roi, cfg.seeding.m_roi, cfg.seeding.m_bg)
        else:
            mult = np.full(pts.shape[0], cfg.seeding.m_uniform)
        new = GaussianMap.from_points(
            torch.from_numpy(pts).float(), torch.from_numpy(cols).float(),
            torch.from_numpy(s0 * mult).float(), opacity=cfg.seeding.init_opacity,
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
            score = torch.cat([self.strategy.eviction_score(cur),
                               torch.full((len(new),), float("inf"), device=self.device)])
            merged, keep = merged.cap(budget, score=score)
            parent = parent[keep]
            stats.n_evicted = len(cur) + len(new) - len(merged)
        self.strategy.set_map(merged, parent, new_anchor=int(frame.frame_id))
        stats.n_seeds, stats.n_roi = int(pts.shape[0]), int(is_roi.sum())
        return stats

    def _candidates(self, frame: Frame) -> tuple[np.ndarray, float]:
        """Seed candidate pixels of ``frame`` and their share of the valid pixels.

        With ``coverage_seeding`` and a non-empty map: the pixels the map does not explain
        (:func:`~gausslite.mapping.memory.unexplained_mask`, SplaTAM Eq. 9); otherwise every valid pixel.
        """
        cfg = self.cfg
        valid = frame.depth > 0
        if not cfg.seeding.coverage or len(self.model) == 0:
            return valid, 1.0
        intr = frame.intrinsics
        out = self._render(frame.c2w, intr.K, intr.width, intr.height)
        cand = unexplained_mask(frame.depth, out.alpha.cpu().numpy(), out.depth.cpu().numpy(),
                                cfg.seeding.coverage_alpha, cfg.seeding.coverage_depth_factor)
        return cand, float(cand.sum()) / max(1, int(valid.sum()))

    def _adopt_task_region(self, frame: Frame, relevance: Optional[np.ndarray], cand: np.ndarray,
                           stats: SeedStats) -> Optional[np.ndarray]:
        """Task adoption (``seeding.adopt``; docs/mapper.md#tasks-that-arrive-late): when the task's Gaussians
        (a = 1) leave more than ``roi_gap`` of ``frame``'s valid relevant pixels uncovered, the Gaussians that draw
        those pixels with at least ``adopt_fraction`` of their blending weight in the frame join the task (a = 1;
        their κ counts from the next ROI-phase iteration on).

        Args:
            frame: the new frame (world ``c2w``, metres). relevance: (H, W) bool relevance map w, or None.
            cand: (H, W) bool seed candidates (pixels the whole map does not explain). stats: receives
                ``n_adopted``.
        Returns:
            (H, W) bool relevant pixels that the map explains but the task's Gaussians did not (they get ROI
            seeds), or None when adoption is off, not GaussLite, or the gap is below the trigger.
        """
        cfg, sw = self.cfg, self.cfg.effective()
        if not (cfg.seeding.adopt and sw.roi and sw.sb) or relevance is None or len(self.model) == 0:
            return None
        roi_valid = relevance & (frame.depth > 0)
        n_roi = int(roi_valid.sum())
        if n_roi == 0:
            return None
        intr = frame.intrinsics
        active = self.model.active
        if bool(active.any()):
            alpha = self._render(frame.c2w, intr.K, intr.width, intr.height, subset=active).alpha.cpu().numpy()
        else:
            alpha = np.zeros(roi_valid.shape, np.float32)
        gap = roi_valid & (alpha < cfg.seeding.coverage_alpha) & ~cand
        if int(gap.sum()) < max(32, cfg.seeding.roi_gap * n_roi):
            return None
        c2w = torch.as_tensor(np.asarray(frame.c2w, np.float64))
        inside, total = self.sensor.blend_weights_inside(torch.as_tensor(intr.K), intr.width, intr.height, c2w,
                                                         torch.from_numpy(roi_valid))
        join = (~active) & (inside >= 1.0) & (inside >= cfg.seeding.adopt_fraction * total)
        stats.n_adopted = int(join.sum())
        if stats.n_adopted:
            self.model.active = active | join
        return gap

    def _gap_count(self, n_pool: int, n_roi_valid: int, budget: int) -> int:
        """Adoption's ROI seeds: ρ × ``seeds_per_frame`` × the uncovered share of the valid relevant pixels (at most
        the pool and the budget)."""
        sc = self.cfg.seeding
        return min(n_pool, budget, int(math.ceil(sc.rho * sc.seeds_per_frame * n_pool / max(1, n_roi_valid))))

    def _frame_seeds(self, frame: Frame, relevance: Optional[np.ndarray], cand: np.ndarray,
                     gap: Optional[np.ndarray], n: int, budget: int,
                     stats: SeedStats) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Seeds of one frame at its own resolution: ``n`` pixels of ``cand`` (uniform, or SB/SIS/GFD with
        ``relevance``), plus ROI seeds on the adoption ``gap``. Returns (points (S, 3) float64 world metres, colours
        (S, 3) float32 in [0, 1], is_roi (S,) bool), or None without a seed."""
        cfg, sw = self.cfg, self.cfg.effective()
        sel = select_seeds(
            cand, n, self.rng, relevance=relevance if sw.sb else None, rgb=frame.rgb,
            sb=sw.sb, sis=sw.sis, gfd=sw.gfd, rho=cfg.seeding.rho, gfd_eps=cfg.seeding.gfd_eps,
        ) if n > 0 else None
        if gap is not None:
            # ROI seeds where the task's Gaussians leave relevant pixels uncovered (gap ∩ cand = ∅: no duplicates)
            pool = np.flatnonzero(gap.ravel())
            n_gap = self._gap_count(pool.size, int((relevance & (frame.depth > 0)).sum()), budget)
            extra = self.rng.choice(pool, size=n_gap, replace=False).astype(np.int64)
            stats.n_gap_seeds = int(extra.size)
            sel = SeedSelection(extra, np.ones(extra.size, bool)) if sel is None else dataclasses.replace(
                sel, pixels=np.concatenate([sel.pixels, extra]), is_roi=np.concatenate([sel.is_roi, np.ones(extra.size, bool)]))
        if sel is None or sel.pixels.size == 0:
            return None
        if sel.n_roi_shortfall:
            log.debug("frame %d: ROI has %d fewer candidate pixels than its seed share; moved to background",
                      frame.frame_id, sel.n_roi_shortfall)
        # a_i comes from w at the seed pixel, whatever the seeding strategy
        is_roi = relevance.ravel()[sel.pixels] if relevance is not None else np.zeros(sel.pixels.size, bool)
        pts, cols = seed_points(sel.pixels, frame.depth, frame.rgb, frame.intrinsics, frame.c2w)
        return pts, cols, is_roi

    def _two_resolution_seeds(self, frame: Frame, relevance: np.ndarray, cand: np.ndarray,
                              gap: Optional[np.ndarray], n: int, budget: int, detail: DetailCrop,
                              stats: SeedStats) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Seeds of a keyframe with a detail crop (SB; docs/mapper.md, "The task region at its own resolution"): the
        region's ⌊ρn⌋ seeds from the crop's relevant pixels whose coarse pixel is a candidate
        (:func:`~gausslite.mapping.detail.detail_pool`, GFD at the detail resolution), the background's n − those
        from the coarse frame outside the region (SIS/GFD as :func:`select_seeds`), the adoption gap's ROI seeds from
        the crop's pixels on the gap. A region seed's initial scale (s0, the nearest-neighbour spacing of the new
        seeds) then follows the finer sampling. Returns (points, colours, is_roi) as :meth:`_frame_seeds`, or None."""
        cfg, sw = self.cfg, self.cfg.effective()
        cf = detail.frame
        roi_pix = np.zeros(0, np.int64)
        if n > 0:
            roi_pix = detail_seed_pixels(detail, detail_pool(detail, cand, frame.intrinsics),
                                         int(math.floor(cfg.seeding.rho * n)), self.rng, sw.gfd, cfg.seeding.gfd_eps)
        n_bg = n - int(roi_pix.size)  # a short pool leaves its share to the background, as SB does
        bg_pix = select_seeds(cand, n_bg, self.rng, relevance=relevance, rgb=frame.rgb, sb=True, sis=sw.sis,
                              gfd=sw.gfd, rho=0.0, gfd_eps=cfg.seeding.gfd_eps).pixels if n_bg > 0 else roi_pix[:0]
        if gap is not None:
            pool = detail_pool(detail, gap, frame.intrinsics)
            n_gap = self._gap_count(pool.size, int((detail.relevance & (cf.depth > 0)).sum()), budget)
            extra = weighted_choice(pool, n_gap, self.rng)
            stats.n_gap_seeds = int(extra.size)
            roi_pix = np.concatenate([roi_pix, extra])
        if roi_pix.size + bg_pix.size == 0:
            return None
        p_roi, c_roi = seed_points(roi_pix, cf.depth, cf.rgb, cf.intrinsics, cf.c2w)
        p_bg, c_bg = seed_points(bg_pix, frame.depth, frame.rgb, frame.intrinsics, frame.c2w)
        is_roi = np.concatenate([np.ones(roi_pix.size, bool), relevance.ravel()[bg_pix]])
        return np.concatenate([p_roi, p_bg]), np.concatenate([c_roi, c_bg]), is_roi
