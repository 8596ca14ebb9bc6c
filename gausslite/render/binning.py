"""Tile binning of projected Gaussians (PyTorch, no gradients).

Each non-culled Gaussian is duplicated once per ``tile_size`` x ``tile_size`` screen tile that its
bounding square ``[u - r, u + r] x [v - r, v + r]`` touches; the duplicates are sorted by the
64-bit key ``tile_id << 32 | float32_bits(depth)`` so that each tile's list is contiguous and
front-to-back (Kerbl et al. 2023, ``duplicateWithKeys`` + radix sort; gsplat ``isect_tiles``).
Both backends use this exact function, so their per-pixel Gaussian lists are identical.

On CPU (float32/float64 ``means2d``) the same lists are built without materialising and sorting
the keys: a serial native loop lists the visible rows and counts their tiles, Warp's stable radix
sort orders the visible rows by depth (ties stay in row order), and each row is appended to the
tiles it covers in that order (:mod:`gausslite.render.native_binning`). Elsewhere the
vectorised torch version below is used; both give identical output.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import warp as wp

from . import native_binning as nb
from . import warp_kernels as wk
from .launch import launch_cpu


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
    num_threads: int = 1,
    tile_rows: torch.Tensor | None = None,
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
        num_threads: CPU threads for the Warp scatter pass (no effect on the result).
        tile_rows: optional (M, 2) int32 inclusive range of tile rows each Gaussian may be binned to (its
            tile rectangle is clipped to them): the rows of one row band, where each band of the image is
            projected from its own pose (:func:`gausslite.render.rasterize_bands`). None: every tile row.

    Returns:
        :class:`TileBins` on the same device as ``means2d``.
    """
    dev = means2d.device
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    if tile_rows is not None and tuple(tile_rows.shape) != (means2d.shape[0], 2):
        raise ValueError(f"tile_rows must have shape ({means2d.shape[0]}, 2), got {tuple(tile_rows.shape)}")
    if dev.type == "cpu" and means2d.dtype in (torch.float32, torch.float64):
        return _bin_cpu_warp(means2d, radii, depths, tile_size, tiles_x, tiles_y, num_threads, tile_rows)
    return _bin_torch(means2d, radii, depths, tile_size, tiles_x, tiles_y, tile_rows)


def _bin_cpu_warp(means2d, radii, depths, tile_size, tiles_x, tiles_y, num_threads=1, tile_rows=None) -> TileBins:
    """CPU binning with the native count and scatter loops and Warp's stable radix sort (same output as
    :func:`_bin_torch`); no per-element torch ops. The scatter pass is split over
    ``num_threads`` stripes of tile rows run concurrently."""
    M = means2d.shape[0]
    n_tiles = tiles_x * tiles_y
    uv = means2d.detach().contiguous()
    rad = radii if radii.dtype == torch.int32 else radii.to(torch.int32)
    rad = rad.contiguous()
    dep = depths.detach().to(uv.dtype).contiguous()
    keys = torch.empty(2 * M, dtype=torch.float32)  # radix sort needs 2x storage
    rows = torch.empty(2 * M, dtype=torch.int32)
    n_rows = torch.empty(1, dtype=torch.int32)
    tile_start = torch.empty(n_tiles, dtype=torch.int32)
    tile_end = torch.zeros(n_tiles, dtype=torch.int32)
    banded = int(tile_rows is not None)
    t_rows = (tile_rows.to(torch.int32).contiguous() if banded else torch.zeros(1, 2, dtype=torch.int32))
    wk.ensure_module_loaded(nb.__name__, "cpu")
    is64 = int(uv.dtype == torch.float64)
    ptr = torch.Tensor.data_ptr
    launch_cpu(nb.bin_count_native_kernel, 1, [ptr(uv), ptr(rad), ptr(dep), is64, M, tile_size, tiles_x, tiles_y,
                                               ptr(t_rows), banded, ptr(keys), ptr(rows), ptr(n_rows),
                                               ptr(tile_start), ptr(tile_end)])
    n = int(n_rows[0])
    n_isect = int(tile_end[-1])
    gids = torch.empty(n_isect, dtype=torch.int32)
    if n == 0:
        return TileBins(gids, tile_start, tile_end, tiles_x, tiles_y)
    # Positive depths: float order = order of the float32 bit patterns used by _bin_torch.
    wp.utils.radix_sort_pairs(wp.from_torch(keys), wp.from_torch(rows), n)
    cursor = tile_start.clone()
    nstripes = max(1, min(int(num_threads), tiles_y))

    def scatter(s):
        launch_cpu(nb.bin_scatter_native_kernel, 1,
                   [ptr(uv), ptr(rad), ptr(rows), n, is64, tile_size, tiles_x, tiles_y, ptr(t_rows), banded, s,
                    nstripes, ptr(cursor), ptr(gids)])

    wk.run_parallel([lambda s=s: scatter(s) for s in range(nstripes)])
    return TileBins(gids, tile_start, tile_end, tiles_x, tiles_y)


def _bin_torch(means2d, radii, depths, tile_size, tiles_x, tiles_y, tile_rows=None) -> TileBins:
    """Vectorised torch binning: one sort of all (tile, depth) keys."""
    dev = means2d.device
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
    if tile_rows is not None:
        band = tile_rows.to(device=dev, dtype=torch.int64)[vid]
        y0, y1 = torch.maximum(y0, band[:, 0]), torch.minimum(y1, band[:, 1])
    wr = x1 - x0 + 1
    cnt = wr * (y1 - y0 + 1).clamp_min(0)
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
