"""SIMD CPU compositing kernels (gausslite.render.simd_kernels) against the Warp tile kernels they
replace and the pure-PyTorch reference: images to float32 rounding, gradients to 1e-5 relative, on
partial tiles, tile sizes below and above the 16-lane limit, early-terminating opaque scenes, a
background, and several launch threads."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gausslite.render import rasterize

from tests.render.test_render_rasterizer import C2W, K, NAMES, H, W, assert_parity, make_scene


def _render(params, cpu_kernel, **kw):
    ps = [p.detach().clone().requires_grad_(True) for p in params]
    out = rasterize(*ps, backend="warp", cpu_kernel=cpu_kernel, **kw)
    gen = torch.Generator().manual_seed(7)
    wc = torch.rand(out.color.shape, generator=gen, dtype=out.color.dtype)
    wd = torch.rand(out.depth.shape, generator=gen, dtype=out.depth.dtype)
    wa = torch.rand(out.alpha.shape, generator=gen, dtype=out.alpha.dtype)
    ((out.color * wc).sum() + (out.depth * wd).sum() + (out.alpha * wa).sum()).backward()
    return out, [p.grad for p in ps]


def _assert_close(params, **kw):
    o_t, g_t = _render(params, "tile", **kw)
    o_s, g_s = _render(params, "simd", **kw)
    for k in ("color", "alpha"):
        err = (getattr(o_s, k) - getattr(o_t, k)).abs().max().item()
        assert err <= 2e-6, f"{k}: simd vs tile max abs error {err:.3g}"
    derr = (o_s.depth - o_t.depth).abs().max().item()
    assert derr <= 2e-6 * max(1.0, o_t.depth.abs().max().item()), derr
    for name, a, b in zip(NAMES, g_s, g_t):
        nb = b.norm().item()
        assert nb > 0, f"tile-kernel gradient of {name} is zero: vacuous scene"
        rel = (a - b).norm().item() / nb
        assert rel <= 1e-5, f"grad {name}: simd vs tile relative error {rel:.3g}"
    return o_s


@pytest.mark.parametrize("tile_size", [8, 16])
@pytest.mark.parametrize("size", [(64, 48), (83, 61)])
def test_simd_matches_tile_kernels(tile_size, size):
    params, _ = make_scene(seed=31, n=500, smax=0.15, dtype=torch.float32, border=15, degenerate=8)
    w, h = size
    out = _assert_close(params, K=K, width=w, height=h, c2w=C2W, tile_size=tile_size)
    assert (out.alpha > 0.5).float().mean() > 0.3  # the scene covers the image


def test_simd_dense_opaque_scene_terminates_like_tile_kernels():
    params, _ = make_scene(seed=32, n=900, smax=0.25, dtype=torch.float32)
    with torch.no_grad():
        params[3].add_(4.0)
        params[2][::3, 0] += 1.5
    out = _assert_close(params, K=K, width=W, height=H, c2w=C2W)
    assert (out.alpha > 0.9998).float().mean() > 0.5  # most pixels stop early (T < 1e-4)


def test_simd_background_and_threads():
    params, _ = make_scene(seed=33, n=300, dtype=torch.float32)
    bg = torch.tensor([0.2, 0.5, 0.9])
    a = _assert_close(params, K=K, width=W, height=H, c2w=C2W, background=bg, num_threads=1)
    b, _ = _render(params, "simd", K=K, width=W, height=H, c2w=C2W, background=bg, num_threads=3)
    assert torch.equal(a.color, b.color) and torch.equal(a.alpha, b.alpha)


def test_wide_tiles_fall_back_to_tile_kernels():
    """Tiles wider than 16 px are not SIMD-eligible: the same image as the tile kernels, bit for bit."""
    params, _ = make_scene(seed=34, n=200, dtype=torch.float32)
    o_s, _ = _render(params, "simd", K=K, width=W, height=H, c2w=C2W, tile_size=32)
    o_t, _ = _render(params, "tile", K=K, width=W, height=H, c2w=C2W, tile_size=32)
    assert torch.equal(o_s.color, o_t.color) and torch.equal(o_s.alpha, o_t.alpha)


def test_simd_parity_with_reference():
    """The default path (SIMD) against the float64 PyTorch reference (the rasterizer's parity bar)."""
    params, _ = make_scene(seed=35, n=400, smax=0.2)
    ow, _, _, _ = assert_parity(params, K=K, width=W, height=H, c2w=C2W)
    assert (ow.alpha > 0.5).float().mean() > 0.3


def test_bad_cpu_kernel():
    params, _ = make_scene(seed=36, n=10)
    with pytest.raises(ValueError, match="cpu_kernel"):
        rasterize(*params, K=K, width=W, height=H, c2w=C2W, cpu_kernel="avx512")


def test_render_in_forked_child_after_parent_used_the_thread_pool():
    """A forked worker (ProcessPoolExecutor's default on Linux, as in bench.long_mission) inherits the
    parent's launch thread pool without its threads; rendering there must not wait on it forever."""
    import multiprocessing as mp

    params, _ = make_scene(seed=37, n=100, dtype=torch.float32)
    kw = dict(K=K, width=W, height=H, c2w=C2W, num_threads=2)
    with torch.no_grad():
        ref = rasterize(*params, **kw).color  # the parent's pool now exists
    ctx = mp.get_context("fork")
    with ctx.Pool(1) as pool:
        res = pool.apply_async(_child_render, (37,))
        color = res.get(timeout=120)
    assert torch.equal(torch.as_tensor(color), ref)


def _child_render(seed):
    params, _ = make_scene(seed=seed, n=100, dtype=torch.float32)
    with torch.no_grad():
        return rasterize(*params, K=K, width=W, height=H, c2w=C2W, num_threads=2).color.numpy()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("logit", [False, True])
def test_native_pack_and_unpack_equal_the_warp_kernels(dtype, logit):
    """The native gdata packing and gradient unpacking (gausslite.render.native_pack) give the Warp kernels' rows and
    gradients bit for bit: several chunks of rows, degenerate conics (not positive definite), opacities near 0."""
    from gausslite.render import native_pack as pk
    from gausslite.render import warp_kernels as wk
    from gausslite.render.autograd import _pack_gdata, _unpack_grads
    from gausslite.render.launch import launch_cpu

    m = 2 * pk.CHUNK + 77
    g = torch.Generator().manual_seed(int(logit) + 2 * (dtype == torch.float64))
    means2d = (torch.rand(m, 2, generator=g, dtype=torch.float64) * 300 - 10).to(dtype)
    conics = (torch.rand(m, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 1.0, 2.0])
              - torch.tensor([0.1, 0.5, 0.1])).to(dtype)  # some not positive definite
    ops = (torch.randn(m, generator=g, dtype=torch.float64) * 4 if logit
           else torch.rand(m, generator=g, dtype=torch.float64)).to(dtype)
    ops[:5] = 0.0 if not logit else -80.0
    colors = torch.rand(m, 3, generator=g, dtype=torch.float64).to(dtype)
    depths = (torch.rand(m, generator=g, dtype=torch.float64) * 5 + 0.1).to(dtype)
    wk.ensure_loaded("cpu")
    ref = torch.empty(m, 16, dtype=torch.float32)
    launch_cpu(wk.pack_gdata_kernel, m, [means2d, conics, ops, colors, depths, int(logit), ref])
    got = _pack_gdata(means2d, conics, ops, colors, depths, opacity_is_logit=logit)
    assert torch.equal(got.view(torch.int32), ref.view(torch.int32))
    assert (ref[:, 15] == 1e38).any() and (ref[:, 15] < 1e38).any()
    bufs = torch.randn(3, m, 10, generator=g, dtype=torch.float64).to(torch.float32)
    outs = [torch.empty(s, dtype=dtype) for s in ((m, 2), (m, 3), (m,), (m, 3), (m,))]
    launch_cpu(wk.unpack_grads_kernel, m, [bufs, ops, int(logit)] + outs)
    got = _unpack_grads(bufs, ops, logit, (dtype,) * 5)
    for a, b in zip(got, outs):
        assert a.dtype == dtype and torch.equal(a, b)
