"""Frustum culling before rasterization (gausslite.render.culling): the image never changes."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from gausslite.render import rasterize
from gausslite.render.culling import frustum_cull_mask


def _scene(seed: int, n: int = 6000):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([12.0, 12.0, 12.0])  # all around the camera
    quats = torch.randn(n, 4, generator=g)
    log_scales = torch.log(torch.rand(n, 3, generator=g) * 0.3 + 0.005)  # 5 mm .. 30 cm, some huge below
    log_scales[:50] = np.log(2.0)
    opac = torch.randn(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return [t.requires_grad_(True) for t in (means, quats, log_scales, opac, colors)]


@pytest.mark.parametrize("seed", range(8))
def test_culled_render_is_identical_and_culls_most_of_a_surrounding_map(seed):
    W, H = 64, 48
    K = torch.tensor([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0.2 * seed, -0.4, 0.1]).as_matrix())
    params = _scene(seed)
    vm = torch.linalg.inv(c2w)
    keep = frustum_cull_mask(params[0], params[2], vm, K, W, H)
    full = rasterize(*params, K=K, width=W, height=H, c2w=c2w, backend="warp", num_threads=1)
    assert int((full.radii > 0).sum()) > 200  # something is in view
    visible = full.ids[full.radii > 0]
    assert bool(keep[visible].all())  # nothing the rasterizer draws is culled
    assert float(keep.float().mean()) < 0.5  # most of a map around the camera is culled
    culled = rasterize(*params, K=K, width=W, height=H, c2w=c2w, subset=keep, backend="warp", num_threads=1)
    for a, b in ((full.color, culled.color), (full.depth, culled.depth), (full.alpha, culled.alpha)):
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    # gradients of the kept rows are the same; culled rows get none
    g_full = torch.autograd.grad(full.color.sum() + full.depth.sum(), params)
    g_cull = torch.autograd.grad(culled.color.sum() + culled.depth.sum(), params)
    for a, b in zip(g_full, g_cull):
        torch.testing.assert_close(a[keep], b[keep], atol=1e-6, rtol=1e-5)
        assert float(b[~keep].abs().sum()) == 0.0


def test_sphere_radius_and_near_plane():
    K = torch.tensor([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    vm = torch.eye(4, dtype=torch.float64)
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, -1.0], [0.0, 0.0, -0.5], [20.0, 0.0, 2.0], [20.0, 0.0, 2.0]])
    log_scales = torch.log(torch.tensor([[0.01] * 3, [0.01] * 3, [1.0] * 3, [0.01] * 3, [8.0] * 3]))
    keep = frustum_cull_mask(means, log_scales, vm, K, 64, 48)
    # in view; behind; behind but its 3σ sphere crosses the near plane; far aside; far aside but huge
    assert keep.tolist() == [True, False, True, False, True]


@pytest.mark.parametrize("seed", range(4))
def test_the_warp_cull_equals_the_torch_reference(seed):
    """The CPU kernel keeps exactly the Gaussians the pure-PyTorch reference keeps (posed cameras, padded and
    unpadded frustums, huge and tiny Gaussians, some behind the camera)."""
    from gausslite.render.culling import frustum_cull_mask_torch

    params = _scene(seed, n=20000)
    K = torch.tensor([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0.3 * seed, -0.2, 0.5]).as_matrix())
    c2w[:3, 3] = torch.tensor([0.5, -0.3, 0.2 * seed], dtype=torch.float64)
    vm = torch.linalg.inv(c2w)
    for pad in (0.0, 0.5):
        got = frustum_cull_mask(params[0], params[2], vm, K, 64, 48, pad=pad)
        ref = frustum_cull_mask_torch(params[0], params[2], vm, K, 64, 48, pad=pad)
        assert got.dtype == torch.bool and 0 < int(ref.sum()) < len(ref)
        assert torch.equal(got, ref)


def test_several_views_in_one_pass_equal_one_pass_per_view():
    """frustum_cull_masks (the bands of a rolling-shutter image, each with its own pose, principal point and height)
    keeps, view by view, exactly what the pure-PyTorch reference keeps for that view alone."""
    from gausslite.render.culling import frustum_cull_mask_torch, frustum_cull_masks

    params = _scene(3, n=20000)
    vms, Ks, heights = [], [], []
    for b in range(6):
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0.05 * b, -0.2, 0.5]).as_matrix())
        c2w[:3, 3] = torch.tensor([0.02 * b, -0.3, 0.1], dtype=torch.float64)
        vms.append(torch.linalg.inv(c2w))
        Ks.append(torch.tensor([[50.0, 0, 31.5], [0, 50.0, 23.5 - 8 * b], [0, 0, 1]]))
        heights.append(8 if b < 5 else 9)
    masks = frustum_cull_masks(params[0], params[2], vms, Ks, 64, heights)
    assert masks.shape == (6, 20000) and masks.dtype == torch.bool
    for b in range(6):
        assert torch.equal(masks[b], frustum_cull_mask_torch(params[0], params[2], vms[b], Ks[b], 64, heights[b]))
    assert not torch.equal(masks[0], masks[5])
    with pytest.raises(ValueError, match="heights"):
        frustum_cull_masks(params[0], params[2], vms, Ks, 64, heights[:2])


def test_the_native_cull_handles_counts_off_its_block_and_chunk_sizes():
    """frustum_cull_masks keeps, view by view, what the pure-PyTorch reference keeps, for several views and a count
    that is neither a multiple of the native loop's eight-Gaussian blocks nor of a thread's chunk."""
    from gausslite.render.culling import CULL_CHUNK, frustum_cull_mask_torch, frustum_cull_masks

    n = 2 * CULL_CHUNK + 13
    params = _scene(5, n=n)
    vms, Ks = [], []
    for b in range(3):
        c2w = torch.eye(4, dtype=torch.float64)
        c2w[:3, :3] = torch.from_numpy(Rotation.from_rotvec([0.1 * b, 0.3, -0.2]).as_matrix())
        c2w[:3, 3] = torch.tensor([0.1, 0.05 * b, -0.2], dtype=torch.float64)
        vms.append(torch.linalg.inv(c2w))
        Ks.append(torch.tensor([[50.0, 0, 31.5], [0, 50.0, 23.5 - 16 * b], [0, 0, 1]]))
    got = frustum_cull_masks(params[0], params[2], vms, Ks, 64, [16, 16, 16], pad=0.2)
    for b in range(3):
        ref = frustum_cull_mask_torch(params[0], params[2], vms[b], Ks[b], 64, 16, pad=0.2)
        assert 0 < int(ref.sum()) < n
        assert torch.equal(got[b], ref)
