"""Native CPU binning (gausslite.render.native_binning) against the torch binning, its reference: the same visible
rows and keys, tile counts and tile lists, float32 and float64, banded or not, one or more stripes."""

from __future__ import annotations

import pytest
import torch

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
                                               int(banded), keys.data_ptr(), rows.data_ptr(), n_rows.data_ptr(),
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
