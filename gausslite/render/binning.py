"""Tile binning of projected Gaussians (PyTorch, no gradients).

Each non-culled Gaussian is duplicated once per ``tile_size`` x ``tile_size`` screen tile that its
bounding square ``[u - r, u + r] x [v - r, v + r]`` touches; the duplicates are sorted by the
64-bit key ``tile_id << 32 | float32_bits(depth)`` so that each tile's list is contiguous and
front-to-back (Kerbl et al. 2023, ``duplicateWithKeys`` + radix sort; gsplat ``isect_tiles``).
Both backends use this exact function, so their per-pixel Gaussian lists are identical.
"""

from __future__ import annotations

from typing import NamedTuple

import torch


class TileBins(NamedTuple):
    """Result of :func:`bin_gaussians`.

    Attributes:
        gids: (n_isect,) int32 row indices (into the projected rows) sorted by (tile, depth).
        tile_start: (tiles_y * tiles_x,) int32 first index into ``gids`` of each tile (row-major).
        tile_end: (tiles_y * tiles_x,) int32 one past the last index of each tile.
        tiles_x, tiles_y: tile grid size.
    """

    gids: torch.Tensor
    tile_start: torch.Tensor
    tile_end: torch.Tensor
    tiles_x: int
    tiles_y: int


def tile_grid(width: int, height: int, tile_size: int) -> tuple[int, int]:
    """Number of tiles (tiles_x, tiles_y) covering a ``width`` x ``height`` pixel image."""
    return (width + tile_size - 1) // tile_size, (height + tile_size - 1) // tile_size


@torch.no_grad()
def bin_gaussians(
    means2d: torch.Tensor,
    radii: torch.Tensor,
    depths: torch.Tensor,
    width: int,
    height: int,
    tile_size: int = 16,
) -> TileBins:
    """Assign projected Gaussians to screen tiles and sort each tile's list by depth.

    Tile rule: pixel (px, py) belongs to tile (px // tile_size, py // tile_size). A Gaussian with
    centre (u, v) and integer radius r > 0 covers tiles ``floor((u - r) / ts) .. floor((u + r) / ts)``
    in x (clamped to the grid), likewise in y.

    Args:
        means2d: (M, 2) pixel coordinates of the centres (any float dtype; detached here).
        radii: (M,) int radius in pixels, 0 = culled.
        depths: (M,) camera z in metres (positive for non-culled rows).
        width, height: image size in pixels.
        tile_size: tile edge in pixels.

    Returns:
        :class:`TileBins` on the same device as ``means2d``.
    """
    dev = means2d.device
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    n_tiles = tiles_x * tiles_y
    vid = torch.nonzero(radii > 0).squeeze(1)
    if vid.numel() == 0:
        z = torch.zeros(n_tiles, dtype=torch.int32, device=dev)
        return TileBins(torch.zeros(0, dtype=torch.int32, device=dev), z, z.clone(), tiles_x, tiles_y)
    uv = means2d.detach()[vid]
    r = radii[vid].to(uv.dtype)
    ts = float(tile_size)
    x0 = torch.floor((uv[:, 0] - r) / ts).clamp_(0, tiles_x - 1).to(torch.int64)
    x1 = torch.floor((uv[:, 0] + r) / ts).clamp_(0, tiles_x - 1).to(torch.int64)
    y0 = torch.floor((uv[:, 1] - r) / ts).clamp_(0, tiles_y - 1).to(torch.int64)
    y1 = torch.floor((uv[:, 1] + r) / ts).clamp_(0, tiles_y - 1).to(torch.int64)
    wr = x1 - x0 + 1
    cnt = wr * (y1 - y0 + 1)
    n = int(cnt.sum())
    li = torch.repeat_interleave(torch.arange(vid.numel(), device=dev), cnt, output_size=n)
    first = torch.cumsum(cnt, 0) - cnt
    off = torch.arange(n, device=dev) - first[li]
    wl = wr[li]
    oy = torch.div(off, wl, rounding_mode="floor")
    tile = (y0[li] + oy) * tiles_x + x0[li] + (off - oy * wl)
    # Positive float32 bit patterns sort like the floats themselves.
    dbits = depths.detach()[vid].to(torch.float32).view(torch.int32).to(torch.int64)
    key = (tile << 32) | dbits[li]
    order = torch.sort(key, stable=True).indices
    gids = vid[li[order]].to(torch.int32)
    counts = torch.bincount(tile, minlength=n_tiles)
    tile_end = torch.cumsum(counts, 0)
    tile_start = (tile_end - counts).to(torch.int32)
    return TileBins(gids, tile_start, tile_end.to(torch.int32), tiles_x, tiles_y)
