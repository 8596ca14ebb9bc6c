"""Which Gaussians an agent shares for its task (paper Sec. III-E; ``docs/sharing.md``).

The shared subset is the intersection of three rules, applied to a map and the agent's ROI
keyframes (:class:`~gausslite.mapping.views.Keyframe`, or their compact stored form, with their relevance
mask ``roi``; keyframes without one are ignored):

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

from typing import Optional, Protocol, Sequence

import numpy as np
import torch

from gausslite.core.arrays import GaussianArrays
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.memory import VOXEL_KEY_OFFSET, pack_voxel_keys
from gausslite.mapping.model import cosine_lr_factor
from gausslite.mapping.views import StoredKeyframe
from gausslite.wire.delta import change_steps
from gausslite.wire.format import QuantConfig

__all__ = ["ShareRule", "task_region", "in_region", "roi_contribution", "select_task_subset",
           "finetune_subset", "update_shared_subset"]

_OFF = VOXEL_KEY_OFFSET  # voxel keys as in the scene budget (gausslite.mapping.memory)
_pack = pack_voxel_keys


class ShareRule(Protocol):
    """The parameters :func:`select_task_subset` reads: :class:`gausslite.mission.config.ShareConfig` (an agent's
    ``agent.share``) conforms, and holds their meaning and defaults.

    Attributes:
        kappa_threshold: minimum κ of a shared Gaussian (with ``a = 1``).
        region_voxel_m: voxel size of the task region (metres, > 0).
        region_dilate: dilation of the region in voxels (>= 0).
        min_opacity: prune Gaussians below this opacity (near-transparent).
        coverage: keep the fewest Gaussians (by decreasing contribution) carrying this fraction of
            the total ROI blending weight; 1.0 keeps every Gaussian with a positive contribution.
        candidates: ``active`` — rules 1 and 2 (the paper's ``a = 1`` and κ, inside the task region);
            ``rendered`` — every Gaussian that draws the ROI pixels of the ROI keyframes competes in rule 3,
            whatever its flag.
        max_fraction: at most this fraction of the map is shared (the Gaussians with the largest
            contribution); None = no bound.
        held_weight: the Gaussians the fusion server already holds (``held`` of :func:`select_task_subset`) rank
            with their contribution times this (>= 1).
    """

    kappa_threshold: int
    region_voxel_m: float
    region_dilate: int
    min_opacity: float
    coverage: float
    candidates: str
    max_fraction: Optional[float]
    held_weight: float


def task_region(views: Sequence, voxel_m: float = 0.05, dilate: int = 1) -> np.ndarray:
    """Sorted unique packed voxel keys of the dilated task region (see the module docstring) of the ROI keyframes
    ``views`` (each with ``roi`` (H, W) bool, ``depth`` (H, W) metres, ``c2w`` (4, 4) camera-to-world, OpenCV axes,
    and ``K`` (3, 3) pixels; arrays or CPU tensors).

    Raises:
        ValueError: ``voxel_m <= 0`` or ``dilate < 0``.
    """
    if not voxel_m > 0 or dilate < 0:
        raise ValueError("voxel_m must be > 0 and dilate >= 0")
    keys = []
    for v in views:
        if v.roi is None:
            continue
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


def roi_contribution(gmap, views: Sequence, backend: str = "auto",
                     subset: Optional[torch.Tensor] = None) -> np.ndarray:
    """(N,) float64 accumulated alpha-blending weight of each Gaussian over the ROI pixels of
    ``views`` (``Σ_views Σ_{p∈ROI} T_ip α_ip``; ROI keyframes as in :func:`task_region`), rendering ``gmap``
    (or its ``subset`` rows).

    Exact: the rendered colour is ``Σ_i T_ip α_ip c_i + T_p · background``, so the gradient of the
    ROI-summed red channel with respect to ``c_i`` is the weight.
    """
    # lazy: keeps gausslite.sharing importable without Warp
    from gausslite.render import blend_weights

    n = len(gmap)
    out = np.zeros(n, np.float64)
    if n == 0:
        return out
    for v in views:
        if v.roi is None:
            continue
        roi = torch.as_tensor(np.asarray(v.roi, bool))
        if not bool(roi.any()):
            continue
        w = blend_weights(gmap.means, gmap.quats, gmap.log_scales, gmap.opacity_logits, gmap.colors,
                          K=np.asarray(v.K), width=v.width, height=v.height, c2w=np.asarray(v.c2w),
                          pixel_mask=roi, subset=subset, background=torch.zeros(3), backend=backend)
        out += w.cpu().double().numpy()
    return out


def select_task_subset(gmap, views: Sequence, cfg: ShareRule, backend: str = "auto",
                       held: Optional[np.ndarray] = None) -> tuple[np.ndarray, dict]:
    """Boolean mask (N,) of the Gaussians to share, and counts per rule (module docstring).

    Args:
        gmap: the agent's map (GaussianMap: means, opacity_logits, active, kappa, ...).
        views: the ROI keyframes (as in :func:`task_region`).  With no ROI pixel at all, the task flag and κ rule
            alone decide.
        cfg: rule parameters (:class:`ShareRule`; an agent's ``agent.share``).  backend: renderer backend.
        held: optional (N,) bool, the Gaussians the fusion server holds from the last push (``cfg.held_weight``).

    Returns:
        (mask, stats) with stats = {"active_kappa", "in_region", "opaque", "shared"} counts
        (``candidates: rendered``: ``in_region`` counts every Gaussian; no region rule).
    """
    active = gmap.active.detach().cpu().numpy().astype(bool)
    kappa = gmap.kappa.detach().cpu().numpy()
    rendered = cfg.candidates == "rendered"
    cand = np.ones(len(active), bool) if rendered else active & (kappa >= cfg.kappa_threshold)
    stats = {"active_kappa": int((active & (kappa >= cfg.kappa_threshold)).sum())}
    views = [v for v in views if v.roi is not None and np.asarray(v.roi).any()]
    if not views or not cand.any():
        if rendered:  # no ROI seen yet: nothing draws the task region
            cand = np.zeros_like(cand)
        n = int(cand.sum())
        stats.update(in_region=n, opaque=n, shared=n)
        return cand, stats
    if not rendered:
        region = task_region(views, cfg.region_voxel_m, cfg.region_dilate)
        cand &= in_region(gmap.means, region, cfg.region_voxel_m)
    stats["in_region"] = int(cand.sum())
    opac = torch.sigmoid(gmap.opacity_logits.detach()).cpu().numpy()
    cand &= opac >= cfg.min_opacity
    stats["opaque"] = int(cand.sum())
    limit = None if cfg.max_fraction is None else int(np.floor(cfg.max_fraction * len(active)))
    if (cfg.coverage < 1.0 or rendered or limit is not None) and cand.any():
        # contribution of the candidates rendered with the rest of the map (occlusion by context)
        c = roi_contribution(gmap, views, backend)
        idx = np.nonzero(cand)[0]
        ci = np.maximum(c[idx], 0.0)
        rank = ci
        if held is not None and cfg.held_weight != 1.0:
            rank = ci * np.where(np.asarray(held, bool)[idx], cfg.held_weight, 1.0)
        order = np.argsort(-rank, kind="stable")
        total = ci.sum()
        keep = np.zeros(len(idx), bool)
        if total > 0:
            k = int(np.searchsorted(np.cumsum(ci[order]) / total, cfg.coverage) + 1)
            k = min(k, int((ci > 0).sum()), len(idx) if limit is None else limit)
            keep[order[:k]] = True
        cand = np.zeros_like(cand)
        cand[idx[keep]] = True
    stats["shared"] = int(cand.sum())
    return cand, stats


def finetune_subset(subset, keyframes: Sequence, iters: int, cfg: Optional[MapperConfig] = None, seed: int = 0,
                    footprint_alpha: float = 0.0, final_lr: float = 0.05, frozen: Optional[np.ndarray] = None):
    """Fit a copy of the shared subset, rendered alone, to the ROI of the agent's keyframes.

    An agent that maps with ``roi_render: context`` fits its active Gaussians to the pixels the *full*
    map shows: in its own map, background Gaussians fill the ROI's gaps and sit behind translucent
    ROI Gaussians. The shared subset leaves those behind, so rendered alone (as the fusion server
    renders it) it shows holes and dark fringes. Before a push the agent fine-tunes a copy of the
    subset on its ROI keyframes with the subset rendered alone (``docs/sharing.md``). The agent's
    own map is left untouched.

    Each iteration draws one ROI keyframe uniformly and takes one ROI-phase step of the mapper's loss
    (paper Eq. 1: L1 colour + depth + SSIM, on the ROI box crop) with every Gaussian of the copy
    treated as active and rendered alone. The learning rates follow a cosine from the mapper's down to
    ``final_lr`` × them, so the copy settles instead of ending on an Adam step. No density control, no
    pose refinement; rows keep their order, so the agent's stable ids stay aligned. κ and the task
    flags of the result are those of the input (the fine-tune steps are not active-optimisation
    counts of the agent's map).

    Measured (``bench.share_finetune``, retired: docs/history.md#share_finetune-and-share_refresh; room0 pick-plant /
    find-ottoman, deployed agent settings with
    ``roi_render: context``, 3 seeds): the subset alone renders its ROI at 28.17 / 27.71 dB on average
    before, and 37.40 / 38.88, 37.62 / 38.63, 37.91 / 39.16 dB after 200 iterations with ``final_lr``
    0.05, against the agent's own full map 36.70 / 35.67, 37.47 / 38.54, 32.77 / 38.75 dB. 60
    iterations at a constant rate gave 35.92 / 37.68 and 36.94 / 37.88 dB (seeds 0, 1). About 2 s per
    push on one core at 300×170.

    Args:
        subset: ``GaussianMap`` (or any container ``GaussianArrays.from_any`` takes) of N Gaussians,
            world frame, metres.
        keyframes: the agent's keyframes: float ``gausslite.mapping.views.Keyframe`` on any device, or compact
            ``StoredKeyframe`` (the store's form), decoded one at a time as they are drawn, so the fine-tune
            holds a single float keyframe however many there are (200 ROI keyframes of 320×240 in float
            are 245 MB); those without ROI pixels are skipped.
        iters: Adam iterations (>= 0; 0 or no ROI keyframe returns a copy of the input).
        cfg: ``MapperConfig`` giving the learning rates and loss weights (default ``MapperConfig()``).
        seed: RNG seed of the view draws.
        footprint_alpha: the loss covers ROI pixels whose rendered alpha exceeds this; the default 0
            covers the whole ROI, so Gaussians grow over the gaps the background used to fill.
        final_lr: learning-rate factor reached at the last iteration (cosine schedule; 1 = constant).
        frozen: optional (N,) bool rows that keep their values exactly (they are rendered, so the free
            rows fit around them, but never updated): the rows the fusion server already holds and
            the agent does not re-send (:func:`update_shared_subset`).

    Returns:
        ``GaussianMap`` with N rows in the input's order.

    Raises:
        ValueError: ``iters < 0``, ``final_lr`` outside (0, 1], or ``frozen`` of the wrong shape.
    """
    # lazy: keeps gausslite.sharing importable without SciPy, Warp
    from gausslite.mapping.mapper import Mapper

    if iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    if not 0 < final_lr <= 1:
        raise ValueError(f"final_lr must be in (0, 1], got {final_lr}")
    base = cfg or MapperConfig()
    gmap = GaussianArrays.from_any(subset).to_gaussian_map(base.device)
    free = np.ones(len(gmap), bool)
    if frozen is not None:
        frozen = np.asarray(frozen)
        if frozen.shape != (len(gmap),) or frozen.dtype != np.bool_:
            raise ValueError(f"frozen must be a ({len(gmap)},) bool array, got {frozen.dtype} {frozen.shape}")
        free = ~frozen
    kfs = [kf for kf in keyframes if kf.roi_box is not None]
    if iters == 0 or len(gmap) == 0 or not kfs or not free.any():
        return gmap
    active, kappa = gmap.active.clone(), gmap.kappa.clone()
    # 'context' render inside the copy = the whole copy (the subset alone), with only the free rows updated: the
    # step updates the active rows alone ('active'), whatever rule the mapper maps with ('visible' would move the
    # frozen rows the server holds too)
    fcfg = base.model_copy(update={
        "seed": seed, "roi_render": "context", "roi_update": "active", "footprint_alpha": float(footprint_alpha),
        "budget": base.budget.model_copy(update={"max_gaussians": max(base.budget.max_gaussians or 0, len(gmap))}),
        "densify": base.densify.model_copy(update={"enabled": False})})
    mapper = Mapper(fcfg)
    gmap.active = torch.from_numpy(free).to(gmap.active.device)
    mapper.load_map(gmap)
    # float keyframes move to the mapper's device once; compact ones are decoded when drawn
    kfs = [kf if isinstance(kf, StoredKeyframe) or kf.rgb.device == mapper.device else kf.to(mapper.device)
           for kf in kfs]
    rng = np.random.default_rng(seed)
    for it in range(int(iters)):
        mapper.model.set_lr_scale(cosine_lr_factor(it, iters, final_lr))
        kf = kfs[int(rng.integers(len(kfs)))]
        if isinstance(kf, StoredKeyframe):
            kf = kf.to_keyframe(mapper.device)
        # the mapper's ROI-phase step: renders the whole copy and updates its free (active) rows
        mapper.step(kf, active_phase=True)
    out = mapper.gmap
    out.active, out.kappa = active.to(out.means.device), kappa.to(out.means.device)
    return out


def update_shared_subset(arrays, ids, base, base_ids, keyframes: Sequence, iters: int, refresh: float = 0.05,
                         cfg: Optional[MapperConfig] = None, seed: int = 0, quant=None, final_lr: float = 0.05):
    """Fine-tune the subset to share next against the copy the fusion server already holds, so that a
    delta push carries the new Gaussians and only a bounded share of the old ones (target:
    ``total_upload_bytes ≤ 1.5 × final_subset_bytes``).

    :func:`finetune_subset` alone moves every row at every push, so every delta re-sends the whole
    subset (room0 sim: 4 pushes, upload 3.9× the final subset). Here the rows the server holds start
    from the server's decoded values, and only ``refresh`` × their count may change:

    1. rows whose id is in ``base_ids`` take the base values (what the server renders), new rows the
       agent's current values;
    2. ranking pass: all rows are fine-tuned alone (:func:`finetune_subset`, ``iters // 2``); the base
       rows that moved most, in code steps of the codec (:func:`gausslite.wire.delta.change_steps`), up to
       ``refresh`` × the number of base rows, are the refreshed rows;
    3. every other base row keeps the server's values and task flag; every held row carries the agent's
       current κ (the push planner sends the κ growth of the rows it does not re-send as the delta's κ
       shift, wire format 3, so the server's κ stays current at no per-row cost);
    4. the new and refreshed rows are fine-tuned for ``iters`` iterations, from the ranking pass's values,
       around the frozen rows (``frozen``), so they fit the copy the server will hold.

    Measured on room0 (both tasks, seeds 0 and 1, ground-truth ROI, refresh 0.1, the copy alone): ranking
    by movement beat ranking by ROI contribution × movement (−0.5 dB) and by loss gradient (−0.1 to −0.4
    dB), and a final pass of ``iters`` beat one of ``iters // 4`` by 0.3–0.6 dB. ``bench.share_refresh``, retired:
    docs/history.md#share_finetune-and-share_refresh
    (3 seeds): starting the held rows from the server's values is by itself worth +0.8 to +1.6 dB over
    fine-tuning the agent's values afresh at every push (refresh 1).

    The frozen rows are then bit-identical to the server's but for κ, and the push planner
    (:class:`gausslite.wire.delta.PushPlanner`) sends exactly the new and refreshed rows plus the removed
    ids. Without a base (first push, or after the server lost it) this is :func:`finetune_subset`.

    Args:
        arrays: the N Gaussians selected for sharing (``GaussianArrays`` or anything ``from_any`` takes),
            the agent's current values, world frame, metres.
        ids: (N,) int64 stable ids of ``arrays``' rows (``GaussianModel.ids``).
        base, base_ids: the server's copy (decoded ``GaussianArrays``, M rows) and its (M,) ids; None
            for none.
        keyframes: the agent's keyframes, float or compact (as :func:`finetune_subset`; ROI keyframes are used).
        iters: fine-tune iterations (>= 0).
        refresh: share of the base rows that may change at this push, in [0, 1] (1 = all, which is
            :func:`finetune_subset` started from the server's values).
        cfg, seed, final_lr: as :func:`finetune_subset`.
        quant: codec configuration whose code steps rank the moves (default ``QuantConfig()``).

    Returns:
        ``(GaussianArrays, stats)``: N rows in the input's order; stats ``{"base": rows held by the
        server, "new": rows not in it, "refreshed": base rows allowed to change}``.

    Raises:
        ValueError: ``refresh`` outside [0, 1], ``ids`` of the wrong length, ``base`` and ``base_ids``
            of different lengths.
    """
    if not 0.0 <= refresh <= 1.0:
        raise ValueError(f"refresh must be in [0, 1], got {refresh}")
    cur = GaussianArrays.from_any(arrays)
    ids = np.asarray(ids, np.int64).reshape(-1)
    if len(ids) != len(cur):
        raise ValueError(f"{len(ids)} ids for {len(cur)} Gaussians")
    n = len(cur)
    pos = np.full(n, -1, np.int64)
    if base is not None and len(base):
        base_ids = np.asarray(base_ids, np.int64).reshape(-1)
        if len(base_ids) != len(base):
            raise ValueError(f"{len(base_ids)} base ids for {len(base)} base rows")
        sorter = np.argsort(base_ids)
        p = sorter[np.clip(np.searchsorted(base_ids, ids, sorter=sorter), 0, len(base_ids) - 1)]
        pos = np.where(base_ids[p] == ids, p, -1)
    held = pos >= 0
    stats = {"base": int(held.sum()), "new": int(n - held.sum()), "refreshed": 0}
    if not held.any():
        return GaussianArrays.from_any(finetune_subset(cur, keyframes, iters, cfg, seed, final_lr=final_lr)), stats
    start = _rows_replaced(cur, np.nonzero(held)[0], base.take(pos[held]))
    if refresh >= 1.0:  # every row may move: one fine-tune from the server's values
        out = GaussianArrays.from_any(finetune_subset(start, keyframes, iters, cfg, seed, final_lr=final_lr))
        out.kappa[held], out.active[held] = cur.kappa[held], cur.active[held]
        stats["refreshed"] = stats["base"]
        return out, stats
    free_all = GaussianArrays.from_any(finetune_subset(start, keyframes, max(1, iters // 2), cfg, seed,
                                                      final_lr=final_lr))
    hidx = np.nonzero(held)[0]
    k = int(np.floor(refresh * len(hidx) + 1e-9))
    keep = np.zeros(n, bool)
    if k:
        moved = change_steps(free_all.take(hidx), start.take(hidx), quant or QuantConfig())
        keep[hidx[np.argsort(-moved, kind="stable")[:k]]] = True
    stats["refreshed"] = int(keep.sum())
    frozen = held & ~keep
    out = _rows_replaced(free_all, np.nonzero(frozen)[0], start.take(np.nonzero(frozen)[0]))
    out.active[keep] = cur.active[keep]
    if not frozen.all():
        out = GaussianArrays.from_any(finetune_subset(out, keyframes, iters, cfg, seed + 1, final_lr=final_lr,
                                                      frozen=frozen))
        # exact server values on the frozen rows (the map round trip may touch the last float bit)
        out = _rows_replaced(out, np.nonzero(frozen)[0], start.take(np.nonzero(frozen)[0]))
    out.kappa[held] = cur.kappa[held]  # today's κ on every held row (see step 3)
    return out, stats


def _rows_replaced(arrays, rows: np.ndarray, values):
    """A copy of ``arrays`` (GaussianArrays) with ``rows`` set to the rows of ``values``."""
    cols = {}
    for name in GaussianArrays.FIELDS:
        a = np.array(getattr(arrays, name), copy=True)
        if len(rows):
            a[rows] = getattr(values, name)
        cols[name] = a
    return GaussianArrays(**cols)
