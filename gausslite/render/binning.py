"""Tile binning of projected Gaussians (PyTorch, no gradients).

Each non-culled Gaussian is duplicated once per ``tile_size`` x ``tile_size`` screen tile that its
bounding square ``[u - r, u + r] x [v - r, v + r]`` touches; the duplicates are sorted by the
64-bit key ``tile_id << 32 | float32_bits(depth)`` so that each tile's list is contiguous and
front-to-back (Kerbl et al. 2023, ``duplicateWithKeys`` + radix sort; gsplat ``isect_tiles``).
Both backends use this exact function, so their per-pixel Gaussian lists are identical.

Given each row's conic and opacity, a row is listed only in the tiles that its footprint reaches (after
Speedy-Splat's SnugBox and AccuTile, Hanson et al. 2025): in each tile row of its square, the columns between the
leftmost and the rightmost point of the ellipse ``a dx^2 + 2 b dx dy + c dy^2 <= t`` within the tile row's pixel
rows, one pixel wider on each side, with ``t = 2 (ln(255 o) + FOOTPRINT_MARGIN)`` the Mahalanobis level below which
``o exp(-m / 2)`` reaches 1/255. The compositing kernels composite a pair only where alpha >= 1/255 within that same
footprint (the SIMD kernels' lane test, :mod:`gausslite.render.simd_kernels`), so a tile left out held no pixel that
the row could reach: the images and gradients are those of the square's lists, with fewer pairs to visit. The
rasterizer bins squares: at the mapper's sizes the narrowed lists cost more to build than the kernels save on them
(docs/realtime.md, "Fewer pairs").

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


#: the margin added to ``ln(255 o)`` in a footprint's level: the compositing kernels' ``p_min`` margin (1e-3, the
#: alpha test's) and the row-span margin (0.01) of :mod:`gausslite.render.native_pack`, so that the level bounds every
#: pixel the kernels may composite
FOOTPRINT_MARGIN = 0.011


def footprint_levels(opacities: torch.Tensor, logit: bool = False) -> torch.Tensor:
    """(M,) Mahalanobis level ``t = 2 (ln(255 o) + FOOTPRINT_MARGIN)`` of each row's footprint: ``o exp(-m / 2) >=
    1/255`` only where ``m <= t - 2 FOOTPRINT_MARGIN`` (Kerbl et al. 2023's alpha threshold; Speedy-Splat's SnugBox
    level ``2 ln(255 o)``, Hanson et al. 2025). ``opacities``: (M,) in [0, 1], or logits when ``logit``; the result
    has their dtype and is <= 0 where the row can reach no pixel (o below 1/255)."""
    o = torch.sigmoid(opacities) if logit else opacities
    return 2.0 * (torch.log(255.0 * o) + FOOTPRINT_MARGIN)


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
    conics: torch.Tensor | None = None,
    levels: torch.Tensor | None = None,
) -> TileBins:
    """Assign projected Gaussians to screen tiles and sort each tile's list by depth.

    Tile rule: pixel (px, py) belongs to tile (px // tile_size, py // tile_size). A Gaussian with
    centre (u, v) and integer radius r > 0 covers tiles ``floor((u - r) / ts) .. floor((u + r) / ts)``
    in x (clamped to the grid), likewise in y. With ``conics`` and ``levels``, each tile row of that rectangle keeps
    only the columns its footprint ellipse reaches (module docstring): ``floor((u + x_l - 1) / ts) .. floor((u + x_r +
    1) / ts)``, ``x_l`` / ``x_r`` the ellipse's extreme offsets over the tile row's pixel rows ``ty ts .. ty ts + ts -
    1`` (a rectangle one tile wide keeps its column); none where ``t <= 0`` or the ellipse ends a pixel before the
    tile row; a row whose conic is not positive definite keeps its rectangle.

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
        conics: optional (M, 3) conics (a, b, c) in px^-2 (:class:`gausslite.render.projection.Projection`), with
        levels: (M,) footprint levels (:func:`footprint_levels`): list each row only in the tiles its footprint
            reaches. Both or neither; evaluated in the dtype of ``means2d``.

    Raises:
        ValueError: ``tile_rows`` not (M, 2), or only one of ``conics`` / ``levels``.

    Returns:
        :class:`TileBins` on the same device as ``means2d``.
    """
    dev = means2d.device
    tiles_x, tiles_y = tile_grid(width, height, tile_size)
    if tile_rows is not None and tuple(tile_rows.shape) != (means2d.shape[0], 2):
        raise ValueError(f"tile_rows must have shape ({means2d.shape[0]}, 2), got {tuple(tile_rows.shape)}")
    if (conics is None) != (levels is None):
        raise ValueError("conics and levels are given together or not at all")
    foot = None
    if conics is not None:
        foot = (conics.detach().to(means2d.dtype).contiguous(), levels.detach().to(means2d.dtype).contiguous())
    if dev.type == "cpu" and means2d.dtype in (torch.float32, torch.float64):
        return _bin_cpu_warp(means2d, radii, depths, tile_size, tiles_x, tiles_y, num_threads, tile_rows, foot)
    return _bin_torch(means2d, radii, depths, tile_size, tiles_x, tiles_y, tile_rows, foot)


def _bin_cpu_warp(means2d, radii, depths, tile_size, tiles_x, tiles_y, num_threads=1, tile_rows=None,
                  foot=None) -> TileBins:
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
    tight = int(foot is not None)
    con, lev = foot if tight else (uv, uv)  # not read when not tight
    wk.ensure_module_loaded(nb.__name__, "cpu")
    is64 = int(uv.dtype == torch.float64)
    ptr = torch.Tensor.data_ptr
    launch_cpu(nb.bin_count_native_kernel, 1, [ptr(uv), ptr(rad), ptr(dep), is64, M, tile_size, tiles_x, tiles_y,
                                               ptr(t_rows), banded, ptr(con), ptr(lev), tight, ptr(keys),
                                               ptr(rows), ptr(n_rows),
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
                   [ptr(uv), ptr(rad), ptr(rows), n, is64, tile_size, tiles_x, tiles_y, ptr(t_rows), banded,
                    ptr(con), ptr(lev), tight, s, nstripes, ptr(cursor), ptr(gids)])

    wk.run_parallel([lambda s=s: scatter(s) for s in range(nstripes)])
    return TileBins(gids, tile_start, tile_end, tiles_x, tiles_y)


def _bin_torch(means2d, radii, depths, tile_size, tiles_x, tiles_y, tile_rows=None, foot=None) -> TileBins:
    """Vectorised torch binning: one sort of all (tile, depth) keys; ``foot`` (conics, levels): the footprint's tile
    rows, in the native loops' arithmetic (:func:`_row_spans`)."""
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
    # one span (tile row ty, columns c0 .. c1) per visible row and tile row of its rectangle
    nr = (y1 - y0 + 1).clamp_min(0)
    ri = torch.repeat_interleave(torch.arange(vid.numel(), device=dev), nr)
    ty = y0[ri] + torch.arange(ri.numel(), device=dev) - (torch.cumsum(nr, 0) - nr)[ri]
    c0, c1 = x0[ri], x1[ri]
    if foot is not None:
        c0, c1 = _row_spans(uv[ri], foot[0][vid][ri], foot[1][vid][ri], ty, c0, c1, tile_size, tiles_x)
    wr = (c1 - c0 + 1).clamp_min(0)
    n = int(wr.sum())
    si = torch.repeat_interleave(torch.arange(ri.numel(), device=dev), wr, output_size=n)
    tile = ty[si] * tiles_x + c0[si] + torch.arange(n, device=dev) - (torch.cumsum(wr, 0) - wr)[si]
    li = ri[si]
    # Positive float32 bit patterns sort like the floats themselves.
    dbits = depths.detach()[vid].to(torch.float32).view(torch.int32).to(torch.int64)
    key = (tile << 32) | dbits[li]
    order = torch.sort(key, stable=True).indices
    gids = vid[li[order]].to(torch.int32)
    counts = torch.bincount(tile, minlength=n_tiles)
    tile_end = torch.cumsum(counts, 0)
    tile_start = (tile_end - counts).to(torch.int32)
    return TileBins(gids, tile_start, tile_end.to(torch.int32), tiles_x, tiles_y)


def _row_spans(uv, conics, levels, ty, c0, c1, tile_size: int, tiles_x: int):
    """The columns ``c0 .. c1`` (int64, empty where c0 > c1) of tile row ``ty`` that a footprint ellipse reaches
    (:func:`bin_gaussians`), for K (row, tile row) pairs: ``uv`` (K, 2), ``conics`` (K, 3), ``levels`` (K,) in one
    dtype; ``c0``, ``c1``: the rectangle's columns, returned where the conic is not positive definite. Each value
    is rounded where the native count and scatter loops round it, so the two give the same lists."""
    T = uv.dtype
    a, b, c = conics.unbind(-1)
    t = levels
    u, v = uv.unbind(-1)
    det = a * c - b * b
    ok = (a > 0) & (c > 0) & (det > 0) & torch.isfinite(det) & torch.isfinite(t)
    with torch.no_grad():
        ts, one = torch.tensor(float(tile_size), dtype=T), torch.tensor(1.0, dtype=T)
        ymax = torch.sqrt(t * a / det)
        dyr = -(b / c) * torch.sqrt(t * c / det)
        dy0 = ty.to(T) * ts - v
        dy1 = dy0 + (ts - one)
        none = ~(t > 0) | (dy0 > ymax + one) | (dy1 < -ymax - one)
        lo = torch.where(dy0 > -ymax, dy0, -ymax)
        hi = torch.where(dy1 < ymax, dy1, ymax)
        flip = lo > hi
        edge = torch.where(dy0 > 0, ymax, -ymax)
        lo, hi = torch.where(flip, edge, lo), torch.where(flip, edge, hi)
        dR = torch.where(dyr < lo, lo, torch.where(dyr > hi, hi, dyr))
        dL = torch.where(-dyr < lo, lo, torch.where(-dyr > hi, hi, -dyr))
        wR, wL = a * t - det * dR * dR, a * t - det * dL * dL
        wR, wL = torch.where(wR > 0, wR, torch.zeros_like(wR)), torch.where(wL > 0, wL, torch.zeros_like(wL))
        xr, xl = (torch.sqrt(wR) - b * dR) / a, (-torch.sqrt(wL) - b * dL) / a
        s0 = torch.floor((u + xl - one) / ts).clamp(0, tiles_x - 1)
        s1 = torch.floor((u + xr + one) / ts).clamp(0, tiles_x - 1)
    narrow = ok & (c1 > c0)  # a rectangle one tile wide keeps its column
    s0 = torch.where(narrow, torch.maximum(torch.nan_to_num(s0).to(torch.int64), c0), c0)
    s1 = torch.where(narrow, torch.minimum(torch.nan_to_num(s1).to(torch.int64), c1), c1)
    s0 = torch.where(ok & none, torch.ones_like(s0), s0)
    s1 = torch.where(ok & none, torch.zeros_like(s1), s1)
    return s0, s1
