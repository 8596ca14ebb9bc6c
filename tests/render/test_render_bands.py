"""Row bands from their own poses in one pass (gausslite.render.rasterize_bands): each band's rows equal a full
render from its pose, the gradients equal the sum of those renders', and bad bands are refused."""

import pytest
import torch
from scipy.spatial.transform import Rotation

from gausslite.mapping.poses import pose_delta
from gausslite.render import rasterize, rasterize_bands
from gausslite.render.culling import frustum_cull_mask

W, H = 80, 64
K = torch.tensor([[70.0, 0, 39.5], [0, 70.0, 31.5], [0, 0, 1]])


def _scene(seed: int, n: int = 3000):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([4.0, 3.0, 2.0]) + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    log_scales = torch.log(torch.rand(n, 3, generator=g) * 0.08 + 0.01)
    opac = torch.randn(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return [t.requires_grad_(True) for t in (means, quats, log_scales, opac, colors)]


def _views(seed: int, rows):
    """World-to-camera poses of the bands: a camera turning and moving a little from band to band."""
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0.05 * seed, -0.1, 0.02]).as_matrix())
    xi = torch.tensor([0.02, -0.03, 0.01, 0.02, 0.01, -0.01], dtype=torch.float64)
    n = len(rows)
    return [torch.linalg.inv(c2w @ pose_delta((b - (n - 1) / 2) * xi)) for b in range(n)]


@pytest.mark.parametrize("seed,rows", [(0, [(0, 16), (16, 48), (48, 64)]), (1, [(0, 32), (32, 64)]),
                                       (2, [(0, 16), (16, 32), (32, 48), (48, 64)])])
@pytest.mark.parametrize("cull", [False, True])
def test_each_band_equals_a_full_render_from_its_pose(seed, rows, cull):
    params = _scene(seed)
    vms = _views(seed, rows)
    subsets = None
    if cull:  # each band's own frustum (rows y0..y1: the principal point moved up by y0)
        subsets = []
        for vm, (y0, y1) in zip(vms, rows):
            Kb = K.clone()
            Kb[1, 2] -= y0
            subsets.append(frustum_cull_mask(params[0], params[2], vm, Kb, W, y1 - y0))
    got = rasterize_bands(*params, K=K, width=W, height=H, viewmats=vms, rows=rows, subsets=subsets,
                          backend="warp", num_threads=2, background=torch.tensor([0.1, 0.2, 0.3]))
    full = [rasterize(*params, K=K, width=W, height=H, viewmat=vm, subset=None if subsets is None else subsets[b],
                      backend="warp", num_threads=1, background=torch.tensor([0.1, 0.2, 0.3]))
            for b, vm in enumerate(vms)]
    assert float(got.alpha.mean()) > 0.3  # the test sees something
    for field in ("color", "depth", "alpha"):
        ref = torch.cat([getattr(o, field)[y0:y1] for o, (y0, y1) in zip(full, rows)])
        torch.testing.assert_close(getattr(got, field), ref, atol=2e-6, rtol=1e-5)
    # gradients: the bands' pixels only, through every band's pose
    g = torch.Generator().manual_seed(seed)
    wc, wd = torch.randn(H, W, 3, generator=g), torch.randn(H, W, generator=g)
    band_of = torch.zeros(H, dtype=torch.long)
    for b, (y0, y1) in enumerate(rows):
        band_of[y0:y1] = b
    g_got = torch.autograd.grad((got.color * wc).sum() + (got.depth * wd).sum(), params)
    loss = sum((o.color * wc * (band_of == b)[:, None, None]).sum() + (o.depth * wd * (band_of == b)[:, None]).sum()
               for b, o in enumerate(full))
    g_ref = torch.autograd.grad(loss, params)
    for a, b in zip(g_got, g_ref):
        torch.testing.assert_close(a, b, atol=2e-4, rtol=2e-3)
    # one projected row per band and Gaussian drawn
    assert len(got.ids) == len(got.means2d) == len(got.radii) == sum(len(o.ids) for o in full)


def test_one_band_is_rasterize():
    params = _scene(5)
    vm = _views(5, [(0, H)])[0]
    a = rasterize_bands(*params, K=K, width=W, height=H, viewmats=[vm], rows=[(0, H)], backend="warp")
    b = rasterize(*params, K=K, width=W, height=H, viewmat=vm, backend="warp")
    torch.testing.assert_close(a.color, b.color, atol=0, rtol=0)


@pytest.mark.parametrize("rows", [[(0, 16), (20, 64)], [(0, 20), (20, 64)], [(0, 32), (32, 60)], [(16, 64)], []])
def test_bands_that_do_not_tile_the_image_on_tile_rows_are_refused(rows):
    params = _scene(6, n=50)
    vms = [torch.eye(4, dtype=torch.float64)] * max(1, len(rows))
    with pytest.raises(ValueError):
        rasterize_bands(*params, K=K, width=W, height=H, viewmats=vms[:len(rows)] if rows else [], rows=rows,
                        backend="warp")


def test_banded_binning_is_the_same_on_both_backends():
    """``tile_rows`` clips each Gaussian's tiles to its band's rows, identically in the Warp and torch binning."""
    from gausslite.render.binning import _bin_torch, bin_gaussians

    g = torch.Generator().manual_seed(7)
    n = 2000
    means2d = torch.rand(n, 2, generator=g) * torch.tensor([W * 1.2, H * 1.2]) - 5.0
    radii = torch.randint(0, 12, (n,), generator=g, dtype=torch.int32)
    depths = torch.rand(n, generator=g) + 0.5
    lo = torch.randint(0, 4, (n,), generator=g, dtype=torch.int32)
    tile_rows = torch.stack([lo, torch.clamp(lo + torch.randint(0, 2, (n,), generator=g, dtype=torch.int32), max=3)], 1)
    a = bin_gaussians(means2d, radii, depths, W, H, 16, num_threads=2, tile_rows=tile_rows)
    b = _bin_torch(means2d, radii, depths, 16, a.tiles_x, a.tiles_y, tile_rows)
    for x, y in zip(a[:3], b[:3]):
        assert torch.equal(x, y)
    plain = bin_gaussians(means2d, radii, depths, W, H, 16)
    assert 0 < len(a.gids) < len(plain.gids)  # clipped, not emptied
    for t in range(a.tiles_x * a.tiles_y):  # every entry of a tile is a Gaussian whose band holds the tile's row
        rows_ok = tile_rows[a.gids[a.tile_start[t]:a.tile_end[t]].long()]
        ty = t // a.tiles_x
        assert bool(((rows_ok[:, 0] <= ty) & (ty <= rows_ok[:, 1])).all())
