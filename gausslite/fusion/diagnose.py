"""What covers each robot's ROI in a fused map: which foreign Gaussians lie over it, which of its own are missing.

A fused team map should render every robot's task region as well as that robot's own map does (paper Sec. III-E:
"our voxel vote alone yields near-specialist quality"). When it does not, the loss has two possible sources, and
this module measures both on the robot's own ROI views (``docs/sharing.md``, "What spoils a robot's ROI"):

* **foreign cover**: Gaussians of other agents that draw the robot's ROI pixels. For each one: its blending weight
  on those pixels, its extent (3σ of its largest axis, metres), its opacity, the depth of its mean against the ROI
  surface in the views it draws (metres; negative = in front), and whether its mean lies in its own agent's task
  region or only in that agent's context;
* **own rows missing**: rows of the robot's subset that the vote dropped, with the share of the subset's own ROI
  blending weight they carried (rendering the subset alone).

The ROI pixel mass splits into ``own`` + ``foreign_task`` + ``foreign_context`` + ``uncovered`` = 1 (the fraction of
the ROI pixels' total blending weight from each source; ``uncovered`` = transmittance left to the background).

Pure NumPy/PyTorch on top of :func:`gausslite.render.blend_weights`.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import torch

from gausslite.core.arrays import GaussianArrays
from gausslite.fusion.guard import RoiView  # also importable from here (torch-free in guard)

__all__ = ["RoiView", "roi_cover", "cover_image"]


def _torch(g: GaussianArrays):
    return (torch.from_numpy(g.means), torch.from_numpy(g.quats), torch.from_numpy(g.log_scales),
            torch.from_numpy(g.opacity_logits), torch.from_numpy(g.colors))


def _depth_offset(means: np.ndarray, v: RoiView) -> np.ndarray:
    """(N,) camera-z of each mean minus the median sensor depth of the ROI (NaN without depth)."""
    if v.depth is None:
        return np.full(len(means), np.nan)
    d = v.depth[v.roi & (v.depth > 0)]
    if d.size == 0:
        return np.full(len(means), np.nan)
    w2c = np.linalg.inv(v.c2w)
    z = means.astype(np.float64) @ w2c[2, :3] + w2c[2, 3]
    return z - float(np.median(d))


def _check_provenance(subsets: Mapping[str, GaussianArrays], agents: Sequence[str], n_fused: int, src_a: np.ndarray,
                      src_r: np.ndarray) -> None:
    """Raise ValueError unless ``src_a`` / ``src_r`` have ``n_fused`` entries pointing into the subsets."""
    if len(src_a) != n_fused or len(src_r) != n_fused:
        raise ValueError(f"provenance of {len(src_a)} / {len(src_r)} rows for a fused map of {n_fused}")
    if len(src_a) and (src_a.min() < 0 or src_a.max() >= len(agents)):
        raise ValueError("source_agent points outside the subsets")
    for i, a in enumerate(agents):
        rows = src_r[src_a == i]
        if len(rows) and (rows.min() < 0 or rows.max() >= len(subsets[a])):
            raise ValueError(f"source_row points outside agent {a!r}'s subset")


def _roi_weights(fused: GaussianArrays, fused_map, own_map, n_own: int, vs: Sequence[RoiView], backend: str):
    """Summed over the views ``vs``: each fused row's ROI blending weight, its weight-averaged depth offset from the
    view's median ROI depth (m; NaN where it draws nothing or the offset is unknown), and each own-subset row's ROI
    weight (``own_map``: the subset's ``GaussianMap``, ``n_own`` rows). Also returns the views' ROI pixel count.

    Returns:
        ``(w (M,), dz (M,), own_w (n_own,), pixels)``.
    """
    # lazy: keeps gausslite.fusion.diagnose importable without OpenCV
    from gausslite.sharing import roi_contribution

    w = np.zeros(len(fused))
    wdz = np.zeros(len(fused))
    wdz_w = np.zeros(len(fused))
    own_w = np.zeros(n_own)
    pixels = 0
    for v in vs:
        pixels += int(v.roi.sum())
        wv = roi_contribution(fused_map, [v], backend)
        w += wv
        dz = _depth_offset(fused.means, v)
        ok = np.isfinite(dz) & (wv > 0)
        wdz[ok] += wv[ok] * dz[ok]
        wdz_w[ok] += wv[ok]
        own_w += roi_contribution(own_map, [v], backend)
    dz = np.where(wdz_w > 0, wdz / np.maximum(wdz_w, 1e-12), np.nan)
    return w, dz, own_w, pixels


def _foreign_stats(w: np.ndarray, dz: np.ndarray, fmask: np.ndarray, extent: np.ndarray, opacity: np.ndarray,
                   surface_margin_m: float) -> dict:
    """The ``foreign`` entry of :func:`roi_cover` for the foreign rows ``fmask`` that draw into the ROI (``w``: ROI
    weights, ``dz``: depth offsets (m), ``extent`` (m), ``opacity`` per fused row)."""
    fw = w[fmask]
    ftot = float(fw.sum())
    fdz = dz[fmask]
    known = np.isfinite(fdz)
    return {"rows": int(fmask.sum()),
            "extent_m_median": float(np.median(extent[fmask])) if fmask.any() else None,
            "extent_m_p90": float(np.percentile(extent[fmask], 90)) if fmask.any() else None,
            "weighted_extent_m": float((extent[fmask] * fw).sum() / ftot) if ftot > 0 else None,
            "opacity_median": float(np.median(opacity[fmask])) if fmask.any() else None,
            "weight_in_front": float(fw[known & (fdz < -surface_margin_m)].sum() / ftot) if ftot > 0 else None,
            "weight_at_surface": float(fw[known & (np.abs(fdz) <= surface_margin_m)].sum() / ftot)
            if ftot > 0 else None,
            "weight_behind": float(fw[known & (fdz > surface_margin_m)].sum() / ftot) if ftot > 0 else None}


def roi_cover(subsets: Mapping[str, GaussianArrays], fused: GaussianArrays, source_agent: np.ndarray,
              source_row: np.ndarray, views: Mapping[str, Sequence[RoiView]], *, region_voxel_m: float = 0.05,
              region_dilate: int = 1, surface_margin_m: float = 0.05, top: int = 8,
              backend: str = "auto") -> dict:
    """Foreign cover and missing own rows of every robot's ROI in a fused map (module docstring).

    Args:
        subsets: agent id → the subset it shared (``GaussianArrays``, world frame, metres), in the order the fused
            rows' provenance refers to.
        fused: the fused map (M rows).
        source_agent: (M,) int, index into ``sorted(subsets)`` of each fused row's agent
            (:attr:`gausslite.fusion.vote.VoteReport.source_agent`).
        source_row: (M,) int, each fused row's row in its agent's subset (``VoteReport.source_row``).
        views: agent id → that robot's ROI views (:class:`RoiView`); agents without views are not scored, but their
            task regions come from their views too (an agent without views has an empty task region).
        region_voxel_m, region_dilate: task regions as :func:`gausslite.sharing.task_region`.
        surface_margin_m: a foreign Gaussian is ``in_front`` / ``behind`` when its mean is more than this in front of
            / behind the median ROI depth of the views it draws (weight-averaged), else ``at_surface``.
        top: foreign Gaussians listed per robot, largest ROI weight first.
        backend: rasterizer backend.

    Returns:
        ``{agent: {"views", "roi_pixels", "mass": {"own", "foreign_task", "foreign_context", "uncovered"},
        "foreign": {"rows", "extent_m_median", "extent_m_p90", "opacity_median", "weight_in_front",
        "weight_at_surface", "weight_behind"} (weights as fractions of the foreign mass), "top_foreign": [...],
        "own_missing": {"rows", "of", "weight_share"}}}``.

    Raises:
        ValueError: provenance arrays of the wrong length or pointing outside the subsets.
    """
    # lazy: keeps gausslite.fusion.diagnose importable without OpenCV
    from gausslite.sharing import in_region, task_region

    agents = sorted(subsets)
    src_a = np.asarray(source_agent, np.int64).reshape(-1)
    src_r = np.asarray(source_row, np.int64).reshape(-1)
    _check_provenance(subsets, agents, len(fused), src_a, src_r)
    # each fused row: is its mean inside its own agent's task region?
    in_task = np.zeros(len(fused), bool)
    for i, a in enumerate(agents):
        sel = src_a == i
        region = task_region(views.get(a, ()), region_voxel_m, region_dilate)
        in_task[sel] = in_region(fused.means[sel], region, region_voxel_m)
    extent = 3.0 * np.exp(fused.log_scales.astype(np.float64)).max(axis=1) if len(fused) else np.zeros(0)
    opacity = 1.0 / (1.0 + np.exp(-fused.opacity_logits.astype(np.float64)))
    fused_map = fused.to_gaussian_map()
    out = {}
    for i, a in enumerate(agents):
        vs = [v for v in views.get(a, ()) if np.asarray(v.roi).any()]
        if not vs:
            continue
        w, dz, own_w, pixels = _roi_weights(fused, fused_map, subsets[a].to_gaussian_map(), len(subsets[a]), vs,
                                            backend)
        own = src_a == i
        foreign = ~own
        mass = {"own": float(w[own].sum() / pixels), "foreign_task": float(w[foreign & in_task].sum() / pixels),
                "foreign_context": float(w[foreign & ~in_task].sum() / pixels)}
        mass["uncovered"] = max(0.0, 1.0 - sum(mass.values()))
        fmask = foreign & (w > 1e-6)
        fstats = _foreign_stats(w, dz, fmask, extent, opacity, surface_margin_m)
        idx = np.nonzero(fmask)[0]
        order = idx[np.argsort(-w[idx], kind="stable")[:top]]
        top_rows = [{"agent": agents[int(src_a[j])], "row": int(src_r[j]), "roi_weight": float(w[j] / pixels),
                     "extent_m": float(extent[j]), "opacity": float(opacity[j]),
                     "depth_vs_roi_m": None if not np.isfinite(dz[j]) else float(dz[j]),
                     "in_own_task_region": bool(in_task[j])} for j in order]
        kept = np.zeros(len(subsets[a]), bool)
        kept[src_r[own]] = True
        tot = float(own_w.sum())
        out[a] = {"views": len(vs), "roi_pixels": pixels, "mass": mass, "foreign": fstats, "top_foreign": top_rows,
                  "own_missing": {"rows": int((~kept).sum()), "of": int(len(kept)),
                                  "weight_share": float(own_w[~kept].sum() / tot) if tot > 0 else None}}
    return out


def cover_image(fused: GaussianArrays, foreign: np.ndarray, view: RoiView, backend: str = "auto") -> np.ndarray:
    """(H, W, 3) uint8 BGR picture of one ROI view: the fused render, with the per-pixel blending weight of the
    ``foreign`` rows ((M,) bool) shown in red and the ROI outlined in green (for reports).
    """
    # lazy: keeps gausslite.fusion.diagnose importable without OpenCV
    import cv2

    # lazy: keeps gausslite.fusion.diagnose importable without Warp
    from gausslite.render import rasterize

    with torch.no_grad():
        args = _torch(fused)
        rgb = rasterize(*args, K=view.K, width=view.width, height=view.height, c2w=view.c2w,
                        background=torch.zeros(3), backend=backend).color.clamp(0, 1).numpy()
        ind = torch.from_numpy(np.repeat(np.asarray(foreign, np.float32)[:, None], 3, 1))
        fw = rasterize(args[0], args[1], args[2], args[3], ind, K=view.K, width=view.width, height=view.height,
                       c2w=view.c2w, background=torch.zeros(3), backend=backend).color[..., 0].clamp(0, 1).numpy()
    img = (0.6 * rgb.mean(-1, keepdims=True) * np.ones(3) + 0.4 * rgb)
    img = img * (1 - fw[..., None]) + fw[..., None] * np.array([1.0, 0.1, 0.1])
    out = cv2.cvtColor((img * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
    contours, _ = cv2.findContours(view.roi.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(out, contours, -1, (0, 255, 0), 1)
    return out
