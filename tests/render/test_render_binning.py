"""Native CPU binning (gausslite.render.native_binning) against the Warp kernels it replaces and the torch binning:
the same visible rows and keys, tile counts, and tile lists, float32 and float64, banded or not, one or more
stripes."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from gausslite.render import native_binning as nb
from gausslite.render import warp_kernels as wk
from gausslite.render.binning import _bin_torch, bin_gaussians, tile_grid
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


def _warp_lists(uv, radii, depths, tiles_x, tiles_y, tile_rows, nstripes):
    """The Warp count and scatter kernels' outputs: (n, keys[:n], rows[:n] before the sort, tile_start, tile_end,
    gids after the sort and scatter)."""
    wk.ensure_loaded("cpu")
    m = len(uv)
    f32 = int(uv.dtype == torch.float32)
    banded = int(tile_rows is not None)
    t_rows = tile_rows if banded else torch.zeros(1, 2, dtype=torch.int32)
    keys, rows = torch.empty(2 * m, dtype=torch.float32), torch.empty(2 * m, dtype=torch.int32)
    n_rows = torch.empty(1, dtype=torch.int32)
    start, end = torch.empty(tiles_x * tiles_y, dtype=torch.int32), torch.zeros(tiles_x * tiles_y, dtype=torch.int32)
    launch_cpu(wk.bin_count_kernel, 1, [uv, radii, depths, 16, tiles_x, tiles_y, f32, t_rows, banded, keys, rows,
                                        n_rows, start, end])
    n = int(n_rows[0])
    before = (keys[:n].clone(), rows[:n].clone())
    wp.utils.radix_sort_pairs(wp.from_torch(keys), wp.from_torch(rows), n)
    gids, cursor = torch.empty(int(end[-1]), dtype=torch.int32), start.clone()
    for s in range(nstripes):
        launch_cpu(wk.bin_scatter_kernel, 1, [uv, radii, rows, n, 16, tiles_x, tiles_y, f32, t_rows, banded, s,
                                              nstripes, cursor, gids])
    return n, before, start, end, gids


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("banded", [False, True])
@pytest.mark.parametrize("nstripes", [1, 3])
def test_native_binning_equals_the_warp_kernels_and_the_torch_binning(dtype, banded, nstripes):
    width, height = 150, 100
    tiles_x, tiles_y = tile_grid(width, height, 16)
    uv, radii, depths, tile_rows = _rows(3000, width, height, dtype, seed=int(banded) + 2 * nstripes)
    tile_rows = tile_rows if banded else None
    n, (keys, rows), start, end, gids = _warp_lists(uv, radii, depths, tiles_x, tiles_y, tile_rows, nstripes)
    assert 0 < n < len(uv) and len(gids) > n  # some rows culled, most rows on several tiles
    # the native count pass alone: the same visible rows, keys and counts
    wk.ensure_module_loaded(nb.__name__, "cpu")
    m = len(uv)
    k2, r2 = torch.empty(2 * m, dtype=torch.float32), torch.empty(2 * m, dtype=torch.int32)
    n2 = torch.empty(1, dtype=torch.int32)
    s2, e2 = torch.empty(tiles_x * tiles_y, dtype=torch.int32), torch.zeros(tiles_x * tiles_y, dtype=torch.int32)
    t_rows = tile_rows if banded else torch.zeros(1, 2, dtype=torch.int32)
    launch_cpu(nb.bin_count_native_kernel, 1, [uv.data_ptr(), radii.data_ptr(), depths.data_ptr(),
                                               int(dtype == torch.float64), m, 16, tiles_x, tiles_y, t_rows.data_ptr(),
                                               int(banded), k2.data_ptr(), r2.data_ptr(), n2.data_ptr(), s2.data_ptr(),
                                               e2.data_ptr()])
    assert int(n2[0]) == n and torch.equal(k2[:n], keys) and torch.equal(r2[:n], rows)
    assert torch.equal(s2, start) and torch.equal(e2, end)
    # the whole binning (native count and scatter): the Warp kernels' lists, and the torch binning's
    bins = bin_gaussians(uv, radii, depths, width, height, 16, num_threads=nstripes, tile_rows=tile_rows)
    assert torch.equal(bins.gids, gids) and torch.equal(bins.tile_start, start) and torch.equal(bins.tile_end, end)
    ref = _bin_torch(uv, radii, depths, 16, tiles_x, tiles_y, tile_rows)
    assert torch.equal(bins.gids, ref.gids) and torch.equal(bins.tile_end, ref.tile_end)
