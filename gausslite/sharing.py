"""Which Gaussians an agent shares for its task (issue 12 part 1; paper Sec. III-E, SPEC §7).

The shared subset is the intersection of three rules, applied to a map and the agent's ROI
keyframes (views with their relevance mask):

1. **Task region.** Every ROI pixel with valid depth of every ROI keyframe is back-projected into
   the world frame and voxelised (``region_voxel_m``), and the voxel set is dilated by
   ``region_dilate`` voxels (26-neighbourhood per step).  Only Gaussians whose mean lies in the
   region can be shared.  This drops active Gaussians that were seeded from mislabelled relevance
   pixels away from the object, and anything the ROI views do not see.
2. **Task flag and κ.**  ``a = 1`` and ``κ >= kappa_threshold`` (the paper's share rule).
3. **Compaction by contribution.**  The contribution of Gaussian i is its accumulated
   alpha-blending weight over the ROI pixels of the ROI keyframes,
   ``C_i = Σ_views Σ_{p ∈ ROI} T_ip α_ip``.  This is the LightGaussian global significance without
   the volume factor.  It is computed exactly, in one backward pass per view, as the gradient of
   the ROI-summed rendered red channel with respect to the colours.  Gaussians that are
   near-transparent (``opacity < min_opacity``) or redundant are pruned.  Redundant means outside
   the smallest set, in decreasing ``C``, that carries ``coverage`` of the total ROI weight; these
   are occluded or overlapping Gaussians whose removal changes the ROI render by at most
   ``1 − coverage`` of its blending weight.

Why this compaction rule: LightGaussian (Fan et al. 2023) and CoKo-SLAM prune by accumulated
blending weight because it measures what each Gaussian adds to the pixels that matter. Opacity
alone keeps opaque Gaussians that are occluded. Scale-based rules keep large background splats
that cross the ROI. A coverage fraction (rather than a count) adapts to how many Gaussians the ROI
really needs.

Pure torch/numpy; the renderer is :func:`gausslite.render.rasterize`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch

from gausslite.mapping.memory import VOXEL_KEY_OFFSET, pack_voxel_keys

__all__ = ["ShareConfig", "ShareView", "task_region", "in_region", "roi_contribution", "select_task_subset"]

_OFF = VOXEL_KEY_OFFSET  # voxel keys as in the scene budget (gausslite.mapping.memory)
_pack = pack_voxel_keys


@dataclass(frozen=True)
class ShareConfig:
    """Parameters of :func:`select_task_subset`.

    Attributes:
        region_voxel_m: voxel size of the task region (metres, > 0).
        region_dilate: dilation of the region in voxels (>= 0).
        kappa_threshold: minimum κ of a shared Gaussian (with ``a = 1``).
        min_opacity: prune Gaussians below this opacity (near-transparent).
        coverage: keep the fewest Gaussians (by decreasing contribution) carrying this fraction of
            the total ROI blending weight; 1.0 keeps every Gaussian with a positive contribution.
    """

    region_voxel_m: float = 0.05
    region_dilate: int = 1
    kappa_threshold: int = 1
    min_opacity: float = 0.02
    coverage: float = 0.99


@dataclass
class ShareView:
    """One ROI keyframe: ``roi`` (H, W) bool relevance mask, ``depth`` (H, W) metres (0 = invalid),
    ``c2w`` (4, 4) camera-to-world (OpenCV camera: x right, y down, z forward), ``K`` (3, 3) pixels."""

    roi: np.ndarray
    depth: np.ndarray
    c2w: np.ndarray
    K: np.ndarray

    @property
    def width(self) -> int:
        return int(self.roi.shape[1])

    @property
    def height(self) -> int:
        return int(self.roi.shape[0])




def task_region(views: Sequence[ShareView], voxel_m: float = 0.05, dilate: int = 1) -> np.ndarray:
    """Sorted unique packed voxel keys of the dilated task region (see the module docstring).

    Raises:
        ValueError: ``voxel_m <= 0`` or ``dilate < 0``.
    """
    if not voxel_m > 0 or dilate < 0:
        raise ValueError("voxel_m must be > 0 and dilate >= 0")
    keys = []
    for v in views:
        m = np.asarray(v.roi, bool) & (np.asarray(v.depth) > 0)
        if not m.any():
            continue
        vs, us = np.nonzero(m)
        z = np.asarray(v.depth, np.float64)[vs, us]
        K = np.asarray(v.K, np.float64)
        x = (us + 0.5 - K[0, 2]) / K[0, 0] * z
        y = (vs + 0.5 - K[1, 2]) / K[1, 1] * z
        c2w = np.asarray(v.c2w, np.float64)
        pw = np.stack([x, y, z], 1) @ c2w[:3, :3].T + c2w[:3, 3]
        keys.append(np.unique(_pack(np.floor(pw / voxel_m).astype(np.int64))))
    if not keys:
        return np.zeros(0, np.int64)
    base = np.unique(np.concatenate(keys))
    if dilate:
        ijk = np.stack([(base >> 42) - _OFF, ((base >> 21) & (2 * _OFF - 1)) - _OFF, (base & (2 * _OFF - 1)) - _OFF], 1)
        r = np.arange(-dilate, dilate + 1)
        offs = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
        base = np.unique(np.concatenate([_pack(ijk + o) for o in offs]))
    return base


def in_region(means, region: np.ndarray, voxel_m: float = 0.05) -> np.ndarray:
    """(N,) bool: means (N, 3) metres whose voxel is in ``region`` (keys from :func:`task_region`)."""
    m = means.detach().cpu().numpy() if hasattr(means, "detach") else np.asarray(means)
    if len(region) == 0 or len(m) == 0:
        return np.zeros(len(m), bool)
    return np.isin(_pack(np.floor(m.astype(np.float64) / voxel_m).astype(np.int64)), region)


def roi_contribution(gmap, views: Sequence[ShareView], backend: str = "auto",
                     subset: Optional[torch.Tensor] = None) -> np.ndarray:
    """(N,) float64 accumulated alpha-blending weight of each Gaussian over the ROI pixels of
    ``views`` (``Σ_views Σ_{p∈ROI} T_ip α_ip``), rendering ``gmap`` (or its ``subset`` rows).

    Exact: the rendered colour is ``Σ_i T_ip α_ip c_i + T_p · background``, so the gradient of the
    ROI-summed red channel with respect to ``c_i`` is the weight.
    """
    from gausslite.render import blend_weights

    n = len(gmap)
    out = np.zeros(n, np.float64)
    if n == 0:
        return out
    for v in views:
        roi = torch.as_tensor(np.asarray(v.roi, bool))
        if not bool(roi.any()):
            continue
        w = blend_weights(gmap.means, gmap.quats, gmap.log_scales, gmap.opacity_logits, gmap.colors,
                          K=np.asarray(v.K), width=v.width, height=v.height, c2w=np.asarray(v.c2w),
                          pixel_mask=roi, subset=subset, background=torch.zeros(3), backend=backend)
        out += w.cpu().double().numpy()
    return out
    cols = gmap.colors.detach().clone().requires_grad_(True)
    for v in views:
        roi = torch.as_tensor(np.asarray(v.roi, bool))
        if not bool(roi.any()):
            continue
        r = rasterize(gmap.means.detach(), gmap.quats.detach(), gmap.log_scales.detach(),
                      gmap.opacity_logits.detach(), cols, K=np.asarray(v.K), width=v.width, height=v.height,
                      c2w=np.asarray(v.c2w), background=torch.zeros(3), backend=backend, subset=subset)
        r.color[..., 0][roi.to(r.color.device)].sum().backward()
        out += cols.grad[:, 0].detach().cpu().double().numpy()
        cols.grad = None
    return out


def select_task_subset(gmap, views: Sequence[ShareView], cfg: ShareConfig = ShareConfig(),
                       backend: str = "auto") -> tuple[np.ndarray, dict]:
    """Boolean mask (N,) of the Gaussians to share, and counts per rule (module docstring).

    Args:
        gmap: the agent's map (GaussianMap: means, opacity_logits, active, kappa, ...).
        views: ROI keyframes.  With no ROI pixel at all, the task flag and κ rule alone decide.
        cfg: rule parameters.  backend: renderer backend.

    Returns:
        (mask, stats) with stats = {"active_kappa", "in_region", "opaque", "shared"} counts.
    """
    active = gmap.active.detach().cpu().numpy().astype(bool)
    kappa = gmap.kappa.detach().cpu().numpy()
    cand = active & (kappa >= cfg.kappa_threshold)
    stats = {"active_kappa": int(cand.sum())}
    views = [v for v in views if np.asarray(v.roi).any()]
    if not views or not cand.any():
        stats.update(in_region=stats["active_kappa"], opaque=stats["active_kappa"], shared=stats["active_kappa"])
        return cand, stats
    region = task_region(views, cfg.region_voxel_m, cfg.region_dilate)
    cand &= in_region(gmap.means, region, cfg.region_voxel_m)
    stats["in_region"] = int(cand.sum())
    opac = torch.sigmoid(gmap.opacity_logits.detach()).cpu().numpy()
    cand &= opac >= cfg.min_opacity
    stats["opaque"] = int(cand.sum())
    if cfg.coverage < 1.0 and cand.any():
        # contribution of the candidates rendered with the rest of the map (occlusion by context)
        c = roi_contribution(gmap, views, backend)
        idx = np.nonzero(cand)[0]
        ci = np.maximum(c[idx], 0.0)
        order = np.argsort(-ci, kind="stable")
        total = ci.sum()
        keep = np.zeros(len(idx), bool)
        if total > 0:
            k = int(np.searchsorted(np.cumsum(ci[order]) / total, cfg.coverage) + 1)
            keep[order[:k]] = True
        cand = np.zeros_like(cand)
        cand[idx[keep]] = True
    stats["shared"] = int(cand.sum())
    return cand, stats
