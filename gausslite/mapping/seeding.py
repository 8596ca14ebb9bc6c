"""Relevance-driven seeding: which pixels become new Gaussians, and their initial scale.

Paper Sec. III-C:
- SB (ROI seed budgeting): N_roi = ⌊ρN⌋ seeds from ROI pixels, N_bg = N − N_roi from the rest.
- SIS (stratified initial scaling): background seeds on a √N_bg × √N_bg jittered grid, one per
  cell; initial scale log(s0·m) with m = 0.5 (ROI) / 0.7 (background).
- GFD (gradient-focused densification): within each cell and in the ROI pool the seed pixel is drawn
  with probability ∝ E + ε, E the Sobel magnitude of the luminance.

All pixel sampling here is without replacement and deterministic for a given ``numpy`` Generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np
from scipy.spatial import cKDTree

from gausslite.camera import Intrinsics


@dataclass
class SeedSelection:
    """Chosen seed pixels of one frame.

    Attributes:
        pixels: (S,) int64 flat pixel indices (v * W + u) into the H×W image.
        is_roi: (S,) bool, True for seeds drawn from the ROI pool.
        n_roi_requested: ⌊ρN⌋ (0 without SB).
        n_roi_shortfall: ROI seeds requested but unavailable (too few valid ROI pixels); these go to
            the background pool.
    """

    pixels: np.ndarray
    is_roi: np.ndarray
    n_roi_requested: int = 0
    n_roi_shortfall: int = 0


def sobel_magnitude(rgb: np.ndarray) -> np.ndarray:
    """Edge magnitude E(u,v) = ‖∇I‖ of the luminance, Sobel 3×3 (paper III-C.3).

    Args:
        rgb: (H, W, 3) uint8 RGB image.
    Returns:
        (H, W) float32, luminance in [0, 1] units per pixel.
    """
    lum = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    gx = cv2.Sobel(lum, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(lum, cv2.CV_32F, 0, 1, ksize=3)
    return np.sqrt(gx * gx + gy * gy)


def _gumbel_keys(weights: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Keys log(w) + Gumbel noise: the top-k keys are a weighted sample without replacement
    (Efraimidis & Spirakis 2006); the per-group argmax is a draw ∝ w."""
    u = rng.random(weights.shape[0])
    return np.log(np.maximum(weights, 1e-30)) - np.log(-np.log(np.clip(u, 1e-12, 1.0 - 1e-12)))


def weighted_choice(pool: np.ndarray, k: int, rng: np.random.Generator, weights: Optional[np.ndarray] = None) -> np.ndarray:
    """Draw ``min(k, len(pool))`` distinct elements of ``pool``, with probability ∝ ``weights``
    (uniform when None).

    Args:
        pool: (P,) int64 candidates. weights: (P,) positive float or None.
    Returns:
        (min(k, P),) int64 chosen elements.
    """
    k = int(min(max(k, 0), pool.shape[0]))
    if k == 0:
        return pool[:0]
    if weights is None:
        return rng.choice(pool, size=k, replace=False)
    keys = _gumbel_keys(weights.astype(np.float64), rng)
    idx = np.argpartition(-keys, k - 1)[:k]
    return pool[idx]


def stratified_choice(
    candidate: np.ndarray,
    n: int,
    rng: np.random.Generator,
    weights: Optional[np.ndarray] = None,
) -> np.ndarray:
    """One jittered sample per cell of a g × g grid over the image, g = ⌈√n⌉ (paper III-C.2).

    Cells without a candidate pixel give nothing. When more than ``n`` cells have candidates, a
    uniformly random subset of ``n`` cells is kept, so at most ``n`` pixels are returned. Within a
    cell the pixel is drawn ∝ ``weights`` (GFD) or uniformly.

    Args:
        candidate: (H, W) bool, pixels that may be drawn.
        n: number of samples wanted.
        weights: (H, W) positive float or None.
    Returns:
        (≤ n,) int64 flat pixel indices.
    """
    H, W = candidate.shape
    flat = np.flatnonzero(candidate.ravel())
    if n <= 0 or flat.size == 0:
        return flat[:0].astype(np.int64)
    g = int(math.ceil(math.sqrt(n)))
    v, u = np.divmod(flat, W)
    cell = (v * g // H) * g + (u * g // W)
    w = np.ones(flat.size) if weights is None else weights.ravel()[flat].astype(np.float64)
    keys = _gumbel_keys(w, rng)
    order = np.lexsort((-keys, cell))
    cells_sorted = cell[order]
    first = np.flatnonzero(np.r_[True, cells_sorted[1:] != cells_sorted[:-1]])
    chosen = flat[order[first]]
    if chosen.size > n:
        chosen = rng.choice(chosen, size=n, replace=False)
    return chosen.astype(np.int64)


def select_seeds(
    valid: np.ndarray,
    n: int,
    rng: np.random.Generator,
    *,
    relevance: Optional[np.ndarray] = None,
    rgb: Optional[np.ndarray] = None,
    sb: bool = False,
    sis: bool = False,
    gfd: bool = False,
    rho: float = 0.4,
    gfd_eps: float = 0.05,
) -> SeedSelection:
    """Choose up to ``n`` seed pixels of one frame (paper Sec. III-C).

    - Without SB: ``n`` pixels uniformly at random from all valid pixels (the uniform baseline;
      ρ is then effectively the ROI's pixel share).
    - With SB: N_roi = ⌊ρn⌋ pixels from valid ROI pixels, N_bg = n − N_roi from valid non-ROI
      pixels. When the ROI holds fewer valid pixels than N_roi, every valid ROI pixel is taken and
      the shortfall is added to the background budget (reported in ``n_roi_shortfall``).
    - With SIS the background pool is sampled on the stratified grid, else uniformly.
    - With GFD every draw (grid cells and the ROI pool) is ∝ Sobel magnitude + ε.

    Args:
        valid: (H, W) bool, depth-valid pixels.
        n: seed budget N for this frame.
        relevance: (H, W) bool ROI map w, or None (treated as all-background).
        rgb: (H, W, 3) uint8, required when ``gfd``.
    Returns:
        SeedSelection with ``is_roi`` set from ``relevance`` at each chosen pixel.
    Raises:
        ValueError: shape mismatch, or ``gfd`` without ``rgb``.
    """
    H, W = valid.shape
    if relevance is None:
        relevance = np.zeros((H, W), dtype=bool)
    if relevance.shape != (H, W):
        raise ValueError(f"relevance map shape {relevance.shape} != depth shape {(H, W)}")
    weights = None
    if gfd:
        if rgb is None or rgb.shape[:2] != (H, W):
            raise ValueError("GFD needs the frame's rgb image of the same size")
        weights = sobel_magnitude(rgb).astype(np.float64) + gfd_eps

    roi_valid = valid & relevance
    bg_valid = valid & ~relevance
    flat_w = None if weights is None else weights.ravel()

    if not sb:
        pool = np.flatnonzero(valid.ravel())
        pix = weighted_choice(pool, n, rng, None if flat_w is None else flat_w[pool])
        return SeedSelection(pix.astype(np.int64), relevance.ravel()[pix])

    n_roi_req = int(math.floor(rho * n))
    roi_pool = np.flatnonzero(roi_valid.ravel())
    roi_pix = weighted_choice(roi_pool, n_roi_req, rng, None if flat_w is None else flat_w[roi_pool])
    shortfall = n_roi_req - roi_pix.size
    n_bg = n - roi_pix.size
    if sis:
        bg_pix = stratified_choice(bg_valid, n_bg, rng, weights)
    else:
        bg_pool = np.flatnonzero(bg_valid.ravel())
        bg_pix = weighted_choice(bg_pool, n_bg, rng, None if flat_w is None else flat_w[bg_pool])
    pix = np.concatenate([roi_pix, bg_pix]).astype(np.int64)
    is_roi = np.concatenate([np.ones(roi_pix.size, bool), np.zeros(bg_pix.size, bool)])
    return SeedSelection(pix, is_roi, n_roi_requested=n_roi_req, n_roi_shortfall=int(shortfall))


def local_median_nn_distance(points: np.ndarray, k: int = 3, reference: Optional[np.ndarray] = None) -> np.ndarray:
    """s0: per point, the median distance to its ``k`` nearest neighbours (metres).

    Args:
        points: (S, 3) float world points.
        k: neighbours considered.
        reference: (R, 3) points to search (default ``points`` itself, excluding the point).
    Returns:
        (S,) float64 distances, clamped to [1e-4, 1.0] m; a lone point gets 1e-2 m.
    """
    S = points.shape[0]
    if S == 0:
        return np.zeros(0)
    ref = points if reference is None else reference
    self_ref = reference is None
    kk = min(k + (1 if self_ref else 0), ref.shape[0])
    if kk <= (1 if self_ref else 0):
        return np.full(S, 1e-2)
    d, _ = cKDTree(ref).query(points, k=kk)
    d = np.atleast_2d(d.reshape(S, -1))
    if self_ref:
        d = d[:, 1:]
    return np.clip(np.median(d, axis=1), 1e-4, 1.0)


def seed_points(
    pixels: np.ndarray,
    depth: np.ndarray,
    rgb: np.ndarray,
    intr: Intrinsics,
    c2w: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Back-project chosen pixels to world points with their colours.

    Args:
        pixels: (S,) flat indices. depth: (H, W) metres. rgb: (H, W, 3) uint8. c2w: (4, 4).
    Returns:
        (points (S, 3) float64 world metres, colors (S, 3) float32 in [0, 1]).
    """
    H, W = depth.shape
    v, u = np.divmod(pixels, W)
    z = depth.ravel()[pixels].astype(np.float64)
    x = (u - intr.cx) / intr.fx * z
    y = (v - intr.cy) / intr.fy * z
    pc = np.stack([x, y, z], axis=1)
    pw = pc @ c2w[:3, :3].T + c2w[:3, 3]
    col = rgb.reshape(-1, 3)[pixels].astype(np.float32) / 255.0
    return pw, col
