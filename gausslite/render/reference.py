"""Slow pure-PyTorch reference rasterizer (autograd only, no custom backward).

Same semantics as the Warp kernels in :mod:`gausslite.render.warp_kernels` (Kerbl et al. 2023,
``renderCUDA``): per pixel, Gaussians of the pixel's tile are composited front to back with
``alpha = min(0.99, o * exp(-0.5 d^T conic d))``; terms with ``alpha < 1/255`` are skipped; the
first Gaussian that would drive the transmittance below 1e-4 stops compositing and is itself
excluded. The exclusive transmittance is a cumulative product, so the whole thing is ordinary
differentiable tensor algebra. Works in float32 or float64 (the dtype of its inputs).

Memory is bounded by processing tiles in chunks of at most ``chunk_elems`` (pixel, Gaussian)
pairs, each wrapped in :func:`torch.utils.checkpoint.checkpoint` so that only the chunk
inputs/outputs are kept between forward and backward.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from .binning import TileBins

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


def _composite_chunk(pix, idx, valid, means2d, conics, opacities, colors, depths):
    """Composite one chunk of tiles.

    Args:
        pix: (B, P, 2) pixel-centre coordinates of the chunk's tiles.
        idx: (B, L) int64 projected-row indices, depth-sorted per tile, padded.
        valid: (B, L) bool, False on padding.
        means2d, conics, opacities, colors, depths: per-row projected parameters.

    Returns:
        (B, P, 5) tensor: RGB, depth sum (sum w z), alpha (sum w).
    """
    mu = means2d[idx]  # (B, L, 2)
    con = conics[idx]
    dx = mu[:, None, :, 0] - pix[:, :, None, 0]  # (B, P, L)
    dy = mu[:, None, :, 1] - pix[:, :, None, 1]
    a = con[:, None, :, 0]
    b = con[:, None, :, 1]
    c = con[:, None, :, 2]
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = torch.clamp(opacities[idx][:, None, :] * torch.exp(power), max=ALPHA_MAX)
    keep = valid[:, None, :] & (power <= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    t_after = torch.cumprod(1.0 - alpha, dim=-1)
    t_before = torch.cat([torch.ones_like(t_after[..., :1]), t_after[..., :-1]], dim=-1)
    included = (t_after >= T_MIN).detach()
    w = torch.where(included, alpha * t_before, torch.zeros_like(alpha))  # (B, P, L)
    feat = torch.cat([colors[idx], depths[idx][..., None], torch.ones_like(depths[idx][..., None])], -1)
    return torch.bmm(w, feat)


def rasterize_reference(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    bins: TileBins,
    width: int,
    height: int,
    tile_size: int = 16,
    chunk_elems: int = 1 << 22,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Reference alpha compositing of projected Gaussians.

    Args:
        means2d: (M, 2) pixel centres of the projected Gaussians (pixels).
        conics: (M, 3) inverse 2D covariance (a, b, c) in px^-2.
        opacities: (M,) post-sigmoid opacities in [0, 1].
        colors: (M, 3) RGB.
        depths: (M,) camera z in metres.
        bins: tile lists from :func:`gausslite.render.binning.bin_gaussians`.
        width, height: image size in pixels.
        tile_size: tile edge in pixels (must match ``bins``).
        chunk_elems: max (pixel x Gaussian) pairs evaluated at once (memory bound).

    Returns:
        color (H, W, 3) without background, depth_sum (H, W) = sum w_i z_i (metres, not
        normalised), alpha (H, W) = sum w_i; dtype of ``means2d``.
    """
    dev, dt = means2d.device, means2d.dtype
    tx, ty = bins.tiles_x, bins.tiles_y
    n_tiles = tx * ty
    P = tile_size * tile_size
    start = bins.tile_start.to(torch.int64)
    count = bins.tile_end.to(torch.int64) - start
    ly, lx = torch.meshgrid(
        torch.arange(tile_size, device=dev), torch.arange(tile_size, device=dev), indexing="ij"
    )
    local = torch.stack([lx.reshape(-1), ly.reshape(-1)], -1).to(dt)  # (P, 2) (x, y)
    tile_ids = torch.arange(n_tiles, device=dev)
    origin = torch.stack([(tile_ids % tx) * tile_size, (tile_ids // tx) * tile_size], -1).to(dt)
    gids = bins.gids.to(torch.int64)

    outs = []
    t0 = 0
    counts_list = count.tolist()
    while t0 < n_tiles:
        # Grow the chunk while the padded (B * P * L) stays under budget.
        t1 = t0 + 1
        lmax = max(counts_list[t0], 1)
        while t1 < n_tiles:
            l_new = max(lmax, counts_list[t1])
            if (t1 + 1 - t0) * P * l_new > chunk_elems:
                break
            lmax = l_new
            t1 += 1
        ar = torch.arange(lmax, device=dev)
        pos = start[t0:t1, None] + ar[None, :]
        valid = ar[None, :] < count[t0:t1, None]
        idx = gids[torch.where(valid, pos, torch.zeros_like(pos)).clamp_max(max(gids.numel() - 1, 0))] \
            if gids.numel() > 0 else torch.zeros_like(pos)
        pix = origin[t0:t1, None, :] + local[None]
        if not bool(valid.any()):
            outs.append(torch.zeros(t1 - t0, P, 5, dtype=dt, device=dev))
        elif torch.is_grad_enabled() and any(
            t.requires_grad for t in (means2d, conics, opacities, colors, depths)
        ):
            outs.append(
                checkpoint(
                    _composite_chunk, pix, idx, valid, means2d, conics, opacities, colors, depths,
                    use_reentrant=False,
                )
            )
        else:
            outs.append(_composite_chunk(pix, idx, valid, means2d, conics, opacities, colors, depths))
        t0 = t1
    img = torch.cat(outs, 0).reshape(ty, tx, tile_size, tile_size, 5)
    img = img.permute(0, 2, 1, 3, 4).reshape(ty * tile_size, tx * tile_size, 5)[:height, :width]
    return img[..., :3], img[..., 3], img[..., 4]
