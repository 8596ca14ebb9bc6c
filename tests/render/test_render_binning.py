"""Native CPU binning (gausslite.render.native_binning) against the torch binning, its reference: the same visible
rows and keys, tile counts and tile lists, float32 and float64, banded or not, one or more stripes."""

from __future__ import annotations

import pytest
import torch

from gausslite.render import native_binning as nb
from gausslite.render import warp_kernels as wk
from gausslite.render.binning import _bin_torch, bin_gaussians, footprint_levels, tile_grid
from gausslite.render.launch import launch_cpu


def _rows(m: int, width: int, height: int, dtype, seed: int):
    """Projected rows: centres on and off the image (some on tile edges), radii 0 (culled) to wider than the image,
    depths with ties, and the tile-row band of each row."""
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(m, 2, generator=g, dtype=torch.float64) * torch.tensor([width * 1.4, height * 1.4]) - 0.2 * torch.tensor(
        [width, height])
    uv[: m // 10] = torch.round(uv[: m // 10] / 16) * 16  # exactly on tile edges
    radii = torch.randint(0, 12, (m,), generator=g, dtype=torch.int32)
    radii[torch.rand(m, generator=g) < 0.02] = max(width, height)
    depths = torch.round(torch.rand(m, generator=g, dtype=torch.float64) * 50) / 10 + 0.1  # ties
    tiles_y = tile_grid(width, height, 16)[1]
    band = torch.randint(0, 3, (m,), generator=g)
    edges = [0, tiles_y // 3, 2 * tiles_y // 3, tiles_y]
    tile_rows = torch.stack([torch.tensor(edges)[band], torch.tensor(edges)[band + 1] - 1], 1).to(torch.int32)
    return uv.to(dtype), radii, depths.to(dtype), tile_rows


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("banded", [False, True])
@pytest.mark.parametrize("nstripes", [1, 3])
def test_native_binning_equals_the_torch_binning(dtype, banded, nstripes):
    width, height = 150, 100
    tiles_x, tiles_y = tile_grid(width, height, 16)
    uv, radii, depths, tile_rows = _rows(3000, width, height, dtype, seed=int(banded) + 2 * nstripes)
    tile_rows = tile_rows if banded else None
    ref = _bin_torch(uv, radii, depths, 16, tiles_x, tiles_y, tile_rows)
    visible = radii > 0
    assert 0 < int(visible.sum()) < len(uv) and len(ref.gids) > int(visible.sum())  # rows culled, most on several tiles
    # the native count pass alone: the visible rows in order, their float32 depths, the tile counts
    wk.ensure_module_loaded(nb.__name__, "cpu")
    m = len(uv)
    keys, rows = torch.empty(2 * m, dtype=torch.float32), torch.empty(2 * m, dtype=torch.int32)
    n_rows = torch.empty(1, dtype=torch.int32)
    start, end = torch.empty(tiles_x * tiles_y, dtype=torch.int32), torch.zeros(tiles_x * tiles_y, dtype=torch.int32)
    t_rows = tile_rows if banded else torch.zeros(1, 2, dtype=torch.int32)
    launch_cpu(nb.bin_count_native_kernel, 1, [uv.data_ptr(), radii.data_ptr(), depths.data_ptr(),
                                               int(dtype == torch.float64), m, 16, tiles_x, tiles_y, t_rows.data_ptr(),
                                               int(banded), uv.data_ptr(), uv.data_ptr(), 0, keys.data_ptr(),
                                               rows.data_ptr(), n_rows.data_ptr(),
                                               start.data_ptr(), end.data_ptr()])
    n = int(n_rows[0])
    assert n == int(visible.sum())
    assert torch.equal(rows[:n], torch.nonzero(visible).squeeze(1).to(torch.int32))
    assert torch.equal(keys[:n], depths[visible].to(torch.float32))
    assert torch.equal(start, ref.tile_start) and torch.equal(end, ref.tile_end)
    # the whole binning (native count and scatter): the torch binning's lists
    bins = bin_gaussians(uv, radii, depths, width, height, 16, num_threads=nstripes, tile_rows=tile_rows)
    assert torch.equal(bins.gids, ref.gids) and torch.equal(bins.tile_start, ref.tile_start)
    assert torch.equal(bins.tile_end, ref.tile_end)


def _footprints(m: int, dtype, seed: int):
    """Conics and levels for :func:`_rows`' rows: round to needle-thin ellipses at any angle, opacities from below
    1/255 (level <= 0: no tile) to 1, a few conics not positive definite and a few non-finite levels (the square
    is kept)."""
    g = torch.Generator().manual_seed(100 + seed)
    ang = torch.rand(m, generator=g, dtype=torch.float64) * torch.pi
    sd = torch.exp(torch.rand(m, 2, generator=g, dtype=torch.float64) * 4 - 1)  # 0.37 .. 20 px
    cs, sn = torch.cos(ang), torch.sin(ang)
    iv = 1 / sd ** 2
    conics = torch.stack([cs * cs * iv[:, 0] + sn * sn * iv[:, 1], cs * sn * (iv[:, 0] - iv[:, 1]),
                          sn * sn * iv[:, 0] + cs * cs * iv[:, 1]], 1)
    conics[:20, 1] = conics[:20, 0] * 2  # det < 0
    o = torch.rand(m, generator=g, dtype=torch.float64) ** 3
    o[20:40] = 0.001  # below 1/255
    levels = footprint_levels(o)
    levels[40:45] = float("nan")
    return conics.to(dtype), levels.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("banded", [False, True])
@pytest.mark.parametrize("nstripes", [1, 3])
def test_tight_native_binning_equals_the_torch_binning(dtype, banded, nstripes):
    width, height = 150, 100
    tiles_x, tiles_y = tile_grid(width, height, 16)
    uv, radii, depths, tile_rows = _rows(3000, width, height, dtype, seed=7 + int(banded) + 2 * nstripes)
    radii = radii * 3  # squares around the ellipses of up to 60 px
    conics, levels = _footprints(len(uv), dtype, seed=nstripes)
    tile_rows = tile_rows if banded else None
    ref = _bin_torch(uv, radii, depths, 16, tiles_x, tiles_y, tile_rows, (conics, levels))
    square = _bin_torch(uv, radii, depths, 16, tiles_x, tiles_y, tile_rows)
    assert 0 < len(ref.gids) < 0.9 * len(square.gids)  # the footprints drop tiles
    bins = bin_gaussians(uv, radii, depths, width, height, 16, num_threads=nstripes, tile_rows=tile_rows,
                         conics=conics, levels=levels)
    assert torch.equal(bins.gids, ref.gids) and torch.equal(bins.tile_start, ref.tile_start)
    assert torch.equal(bins.tile_end, ref.tile_end)


def test_tight_lists_keep_every_tile_a_footprint_reaches_in_the_squares_order():
    """Each tile's tight list is its square list with rows left out, in the same order; a row left out of a tile
    reaches none of the tile's pixel centres (its Mahalanobis distance there is above the level, evaluated in
    float64); rows without a positive-definite conic or with a non-finite level keep their squares' tiles, rows below
    1/255 opacity get none."""
    width, height, ts = 150, 100, 16
    tiles_x, tiles_y = tile_grid(width, height, ts)
    uv, radii, depths, _ = _rows(2000, width, height, torch.float64, seed=11)
    radii = radii * 3
    conics, levels = _footprints(len(uv), torch.float64, seed=5)
    sq = _bin_torch(uv, radii, depths, ts, tiles_x, tiles_y)
    ti = _bin_torch(uv, radii, depths, ts, tiles_x, tiles_y, None, (conics, levels))
    det = conics[:, 0] * conics[:, 2] - conics[:, 1] ** 2
    kept_whole = (det <= 0) | ~torch.isfinite(levels)
    dropped = 0
    for t in range(tiles_x * tiles_y):
        a = sq.gids[sq.tile_start[t]:sq.tile_end[t]].tolist()
        b = ti.gids[ti.tile_start[t]:ti.tile_end[t]].tolist()
        it = iter(a)
        assert all(x in it for x in b)  # a subsequence: same order
        x0, y0 = (t % tiles_x) * ts, (t // tiles_x) * ts
        py, px = torch.meshgrid(torch.arange(y0, min(y0 + ts, height), dtype=torch.float64),
                                torch.arange(x0, min(x0 + ts, width), dtype=torch.float64), indexing="ij")
        for i in set(a) - set(b):
            dropped += 1
            assert not kept_whole[i]
            dx, dy = px - uv[i, 0], py - uv[i, 1]
            md = conics[i, 0] * dx * dx + 2 * conics[i, 1] * dx * dy + conics[i, 2] * dy * dy
            assert float(md.min()) > float(levels[i])
    assert dropped > 0
    low = (levels <= 0) & (radii > 0) & ~kept_whole
    assert int(low.sum()) > 0 and not torch.isin(ti.gids, torch.nonzero(low).squeeze(1).to(torch.int32)).any()


def test_tight_lists_render_the_squares_images_and_gradients_bit_for_bit():
    """The rasterizer's lists (tight) against the squares' through the same compositing kernels, SIMD and tile: the
    same colours, depths, alpha and gradients, bit for bit, with fewer entries."""
    from gausslite.render.autograd import RasterizeWarp, project_gaussians_warp

    from tests.render.test_render_rasterizer import C2W, K, make_scene

    params, _ = make_scene(seed=41, n=600, smax=0.2, dtype=torch.float32, border=12, degenerate=6)
    w, h = 83, 61
    vm = torch.linalg.inv(torch.as_tensor(C2W, dtype=torch.float64))
    k64 = torch.as_tensor(K, dtype=torch.float64)
    for kernel in ("simd", "tile"):
        res = []
        for tight in (False, True):
            ps = [p.detach().clone().requires_grad_(True) for p in params]
            proj = project_gaussians_warp(ps[0], ps[1], ps[2], vm, k64, w, h, near=0.01, far=1e4, eps2d=0.3,
                                          num_threads=1, simd=True)
            kw = {"conics": proj.conics, "levels": footprint_levels(ps[3].detach(), logit=True)} if tight else {}
            bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, w, h, 16, **kw)
            out = RasterizeWarp.apply(proj.means2d, proj.conics, ps[3], ps[4], proj.depths, bins.gids,
                                      bins.tile_start, bins.tile_end, w, h, 16, bins.tiles_x, bins.tiles_y, 1, True,
                                      torch.zeros(3), kernel)
            gen = torch.Generator().manual_seed(3)
            sum((o * torch.rand(o.shape, generator=gen)).sum() for o in out).backward()
            res.append(([o.detach() for o in out], [p.grad for p in ps], len(bins.gids)))
        (img_sq, g_sq, n_sq), (img_ti, g_ti, n_ti) = res
        assert n_ti < n_sq
        assert all(torch.equal(a, b) for a, b in zip(img_sq, img_ti))
        assert all(torch.equal(a, b) for a, b in zip(g_sq, g_ti)) and all(g.abs().sum() > 0 for g in g_sq)
