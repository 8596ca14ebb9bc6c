"""Tests of the differentiable Gaussian rasterizer (gausslite.render).

Parity: the Warp kernels (float32) against the pure-PyTorch reference run in float64.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gausslite.render import RenderOutput, project_gaussians, rasterize

W, H = 64, 48
K = np.array([[55.0, 0.0, 31.7], [0.0, 52.0, 23.2], [0.0, 0.0, 1.0]])


def _rot(ax, ay, az):
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


C2W = np.eye(4)
C2W[:3, :3] = _rot(0.1, -0.2, 0.05)
C2W[:3, 3] = [0.3, -0.2, 0.5]


def _cam_points(gen, n, zmin, zmax, spread=1.3, dtype=torch.float64):
    """n camera-frame points inside (spread x) the frustum, depth in [zmin, zmax]."""
    z = torch.rand(n, generator=gen, dtype=dtype) * (zmax - zmin) + zmin
    u = (torch.rand(n, generator=gen, dtype=dtype) - 0.5) * spread * W + K[0, 2]
    v = (torch.rand(n, generator=gen, dtype=dtype) - 0.5) * spread * H + K[1, 2]
    return torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)


def _to_world(pc, c2w=C2W):
    c = torch.as_tensor(c2w, dtype=pc.dtype)
    return pc @ c[:3, :3].T + c[:3, 3]


def make_scene(seed=0, n=150, dtype=torch.float64, behind=0, border=0, degenerate=0, c2w=C2W, smax=0.06):
    """Random scene in world coordinates plus index groups of the special cases."""
    g = torch.Generator().manual_seed(seed)
    pts = [_cam_points(g, n, 1.0, 5.0, dtype=dtype)]
    groups = {}
    k = n
    if behind:
        pb = _cam_points(g, behind, 0.5, 3.0, dtype=dtype)
        pb[:, 2] = -pb[:, 2]
        pts.append(pb)
        groups["behind"] = torch.arange(k, k + behind)
        k += behind
    if border:
        # centres right on / just outside the image edges (u ~ -1 or W, v ~ -1 or H)
        z = torch.rand(border, generator=g, dtype=dtype) * 2 + 1.5
        side = torch.arange(border) % 4
        u = torch.rand(border, generator=g, dtype=dtype) * W
        v = torch.rand(border, generator=g, dtype=dtype) * H
        u = torch.where(side == 0, torch.full_like(u, -1.5), torch.where(side == 1, torch.full_like(u, W + 0.5), u))
        v = torch.where(side == 2, torch.full_like(v, -1.5), torch.where(side == 3, torch.full_like(v, H + 0.5), v))
        pts.append(torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1))
        groups["border"] = torch.arange(k, k + border)
        k += border
    if degenerate:
        pts.append(_cam_points(g, degenerate, 1.0, 3.0, spread=0.8, dtype=dtype))
        groups["degenerate"] = torch.arange(k, k + degenerate)
        k += degenerate
    means = _to_world(torch.cat(pts), c2w)
    N = means.shape[0]
    quats = torch.randn(N, 4, generator=g, dtype=dtype)
    log_scales = torch.log(torch.rand(N, 3, generator=g, dtype=dtype) * smax + 0.01)
    if degenerate:
        log_scales[groups["degenerate"], 1] = math.log(1e-6)
    if border:
        log_scales[groups["border"]] = math.log(0.1)
    opacity_logits = torch.randn(N, generator=g, dtype=dtype) * 1.5
    colors = torch.rand(N, 3, generator=g, dtype=dtype)
    params = [t.clone().requires_grad_(True) for t in (means, quats, log_scales, opacity_logits, colors)]
    return params, groups


def render_and_grad(params, seed=123, **kw):
    """Render, backprop a random linear loss on colour+depth+alpha, return (out, grads)."""
    for p in params:
        p.grad = None
    out = rasterize(*params, **kw)
    g = torch.Generator().manual_seed(seed)
    h, w = out.alpha.shape
    wc = torch.randn(h, w, 3, generator=g, dtype=torch.float64)
    wd = torch.randn(h, w, generator=g, dtype=torch.float64)
    wa = torch.randn(h, w, generator=g, dtype=torch.float64)
    loss = (out.color.double() * wc).sum() + (out.depth.double() * wd).sum() + (out.alpha.double() * wa).sum()
    loss.backward()
    return out, [p.grad.detach().clone() for p in params]


NAMES = ("means", "quats", "log_scales", "opacity_logits", "colors")


def assert_parity(params, **kw):
    ow, gw = render_and_grad(params, backend="warp", **kw)
    orf, gr = render_and_grad(params, backend="torch", **kw)
    assert orf.color.dtype == torch.float64 and ow.color.dtype == torch.float32
    for k in ("color", "depth", "alpha"):
        err = (getattr(ow, k).double() - getattr(orf, k)).abs().max().item()
        assert err <= 1e-5, f"{k} forward max abs error {err:.3g}"
    for name, a, b in zip(NAMES, gw, gr):
        assert torch.isfinite(a).all(), name
        nb = b.norm().item()
        assert nb > 0, f"reference gradient of {name} is zero: test scene is vacuous"
        rel = (a - b).norm().item() / nb
        assert rel <= 1e-4, f"grad {name} relative error {rel:.3g}"
    assert torch.equal(ow.radii, orf.radii)
    assert torch.allclose(ow.means2d.double(), orf.means2d.double(), atol=1e-9)
    return ow, orf, gw, gr


# ------------------------------------------------------------------------------------------ parity


def test_parity_random_scene():
    params, _ = make_scene(seed=1, n=600, smax=0.2)
    ow, _, _, _ = assert_parity(params, K=K, width=W, height=H, c2w=C2W)
    assert (ow.alpha > 0.5).float().mean() > 0.3  # the scene actually covers the image
    assert ow.alpha.max() > 0.999  # transmittance gets near the 1e-4 early-termination level


def test_parity_behind_border_degenerate():
    params, groups = make_scene(seed=2, n=120, behind=20, border=24, degenerate=15)
    ow, _, gw, _ = assert_parity(params, K=K, width=W, height=H, c2w=C2W)
    assert (ow.radii[groups["behind"]] == 0).all()
    # behind-camera Gaussians get exactly zero gradient
    for g in gw:
        assert (g[groups["behind"]] == 0).all()
    # border Gaussians straddle the edge: centre outside the image, yet rendered
    b = groups["border"]
    uv = ow.means2d[b].detach()
    outside = (uv[:, 0] < 0) | (uv[:, 0] > W - 1) | (uv[:, 1] < 0) | (uv[:, 1] > H - 1)
    assert outside.all()
    assert (ow.radii[b] > 0).sum() >= len(b) // 2
    assert gw[4][b].abs().sum(1).gt(0).sum() >= len(b) // 2  # colour grads reach them
    # near-degenerate (one axis 1e-6 m) Gaussians are rendered with finite gradients
    d = groups["degenerate"]
    assert (ow.radii[d] > 0).all()
    assert gw[2][d].abs().sum() > 0


def test_parity_other_pose_and_background():
    c2w = np.eye(4)
    c2w[:3, :3] = _rot(-0.3, 0.4, 0.2)
    c2w[:3, 3] = [-1.0, 0.5, 2.0]
    params, _ = make_scene(seed=3, n=150, behind=10, c2w=c2w)
    assert_parity(params, K=K, width=W, height=H, viewmat=np.linalg.inv(c2w),
                  background=np.array([0.2, 0.5, 0.9]))


def test_parity_float32_inputs():
    params, _ = make_scene(seed=4, n=150, dtype=torch.float32)
    ow, gw = render_and_grad(params, backend="warp", K=K, width=W, height=H, c2w=C2W)
    p64 = [p.detach().double().requires_grad_() for p in params]
    orf, gr = render_and_grad(p64, backend="torch", K=K, width=W, height=H, c2w=C2W)
    assert gw[0].dtype == torch.float32
    assert (ow.color.double() - orf.color).abs().max() < 1e-4
    for name, a, b in zip(NAMES, gw, gr):
        assert (a.double() - b).norm() / b.norm() < 1e-3, name


def test_single_and_multi_thread_agree():
    params, _ = make_scene(seed=5, n=200)
    o1, g1 = render_and_grad(params, backend="warp", K=K, width=W, height=H, c2w=C2W, num_threads=1)
    o3, g3 = render_and_grad(params, backend="warp", K=K, width=W, height=H, c2w=C2W, num_threads=3)
    assert torch.equal(o1.color, o3.color) and torch.equal(o1.depth, o3.depth)
    for a, b in zip(g1, g3):  # per-thread buffers are summed in another order: float32 rounding only
        assert (a - b).norm() <= 1e-5 * b.norm()
        assert b.norm() > 0


def test_parity_dense_opaque_scene_with_early_tile_exit():
    """Opaque, overlapping, partly elongated Gaussians: every pixel of most tiles terminates early
    (T < 1e-4), exercising the CPU tile kernels' per-tile exit and their row-span bounds."""
    params, _ = make_scene(seed=21, n=900, smax=0.25)
    with torch.no_grad():
        params[3].add_(4.0)  # opacities ~ sigmoid(4 + 1.5 N(0, 1))
        params[2][::3, 0] += 1.5  # elongated footprints
    ow, _, _, _ = assert_parity(params, K=K, width=W, height=H, c2w=C2W)
    assert (ow.alpha > 0.9998).float().mean() > 0.5


def _per_pixel_kernel_render(gdata, bins, width, height, ts):
    """Forward of the generic per-pixel kernel (the CUDA path), launched on CPU."""
    import warp as wp

    from gausslite.render import warp_kernels as wk

    idata = gdata[:, [0, 1, 2, 3, 4, 10, 11, 12]].index_select(0, bins.gids.long()).contiguous()
    HW = width * height
    feat, T, last = torch.zeros(HW, 5), torch.ones(HW), torch.zeros(HW, dtype=torch.int32)
    wk.ensure_loaded("cpu")
    wp.launch(wk.rasterize_fwd_kernel, dim=bins.tiles_y * ts * width,
              inputs=[wp.from_torch(gdata), wp.from_torch(idata), wp.from_torch(bins.gids),
                      wp.from_torch(bins.tile_start), wp.from_torch(bins.tile_end), width, height, ts,
                      bins.tiles_x, 0, 1],
              outputs=[wp.from_torch(feat), wp.from_torch(T), wp.from_torch(last)], device="cpu")
    return feat, T, last


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpu_tile_kernels_bitwise_match_per_pixel_kernel(dtype):
    """The CPU tile kernels visit only the pixels inside each Gaussian's row spans; the result must
    be bit-identical to the per-pixel kernel that tests every (pixel, Gaussian) pair (Warp tile kernels),
    and equal to float32 rounding for the SIMD kernels (same spans as lane masks, polynomial exp)."""
    from gausslite.render.autograd import RasterizeWarp, _pack_gdata
    from gausslite.render.binning import bin_gaussians

    params, _ = make_scene(seed=22, n=700, smax=0.2, dtype=dtype, border=12, degenerate=10)
    m, q, ls, ol, col = (p.detach() for p in params)
    vm = torch.tensor(np.linalg.inv(C2W), dtype=dtype)
    w, h = 83, 61  # partial tiles on both edges
    pr = project_gaussians(m, q, ls, vm, torch.tensor(K, dtype=dtype), w, h)
    bins = bin_gaussians(pr.means2d, pr.radii, pr.depths, w, h, 16)
    op = torch.sigmoid(ol)
    gdata = _pack_gdata(pr.means2d, pr.conics, op, col, pr.depths)
    feat, T, last = _per_pixel_kernel_render(gdata, bins, w, h, 16)
    for nt in (1, 2):
        c, d, a = RasterizeWarp.apply(pr.means2d, pr.conics, op, col, pr.depths, bins.gids,
                                      bins.tile_start, bins.tile_end, w, h, 16, bins.tiles_x,
                                      bins.tiles_y, nt, False, None, "tile")
        assert torch.equal(c.reshape(-1, 3), feat[:, :3])
        assert torch.equal(d.reshape(-1), feat[:, 3]) and torch.equal(a.reshape(-1), feat[:, 4])
        # the SIMD kernels visit the same pixels; only their polynomial exp rounds differently
        c, d, a = RasterizeWarp.apply(pr.means2d, pr.conics, op, col, pr.depths, bins.gids,
                                      bins.tile_start, bins.tile_end, w, h, 16, bins.tiles_x,
                                      bins.tiles_y, nt, False, None, "simd")
        assert (c.reshape(-1, 3) - feat[:, :3]).abs().max() <= 2e-6
        assert (a.reshape(-1) - feat[:, 4]).abs().max() <= 2e-6
        assert (d.reshape(-1) - feat[:, 3]).abs().max() <= 2e-6 * max(1.0, float(feat[:, 3].abs().max()))
    assert (feat[:, 4] > 0).float().mean() > 0.5


# ------------------------------------------------------------------------------------------ subset


@pytest.mark.parametrize("backend", ["warp", "torch"])
@pytest.mark.parametrize("kind", ["bool", "index"])
def test_subset_matches_gathered_map(backend, kind):
    params, _ = make_scene(seed=6, n=160)
    N = params[0].shape[0]
    g = torch.Generator().manual_seed(7)
    mask = torch.rand(N, generator=g) < 0.4
    idx = torch.nonzero(mask).squeeze(1)
    if kind == "index":
        idx = idx[torch.randperm(idx.numel(), generator=g)]  # order must not matter
        subset = idx
    else:
        subset = mask
    kw = dict(K=K, width=W, height=H, c2w=C2W, backend=backend)
    out, grads = render_and_grad(params, subset=subset, **kw)
    gathered = [p.detach()[idx].clone().requires_grad_() for p in params]
    ref, grads_g = render_and_grad(gathered, **kw)
    assert torch.equal(out.ids, idx)
    assert out.means2d.shape == (idx.numel(), 2) and out.radii.shape == (idx.numel(),)
    for k in ("color", "depth", "alpha"):
        assert torch.allclose(getattr(out, k), getattr(ref, k), atol=1e-6), k
    outside = ~mask
    for name, gfull, gsub in zip(NAMES, grads, grads_g):
        assert (gfull[outside] == 0).all(), name
        assert torch.allclose(gfull[idx], gsub, rtol=1e-5, atol=1e-8), name
        assert gsub.abs().sum() > 0, name


def test_subset_errors():
    params, _ = make_scene(seed=6, n=10)
    kw = dict(K=K, width=W, height=H, c2w=C2W)
    with pytest.raises(ValueError, match="bool subset"):
        rasterize(*params, subset=torch.ones(3, dtype=torch.bool), **kw)
    with pytest.raises(ValueError, match="subset indices"):
        rasterize(*params, subset=torch.tensor([0, 10]), **kw)
    with pytest.raises(ValueError, match="subset must be"):
        rasterize(*params, subset=torch.tensor([0.5]), **kw)


# ------------------------------------------------------------------------------------------ empty


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_empty_scene(backend):
    bg = torch.tensor([0.1, 0.2, 0.3])
    params = [torch.zeros(0, d, dtype=torch.float64, requires_grad=True) for d in (3, 4, 3)]
    params += [torch.zeros(0, dtype=torch.float64, requires_grad=True),
               torch.zeros(0, 3, dtype=torch.float64, requires_grad=True)]
    out = rasterize(*params, K=K, width=W, height=H, c2w=C2W, background=bg, backend=backend)
    assert torch.allclose(out.color.float(), bg.expand(H, W, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    assert out.means2d.shape == (0, 2) and out.radii.shape == (0,) and out.ids.shape == (0,)
    (out.color.sum() + out.depth.sum() + out.alpha.sum()).backward()
    assert all(p.grad is not None and p.grad.shape == p.shape for p in params)


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_everything_culled(backend):
    params, _ = make_scene(seed=8, n=0, behind=12)
    out, grads = render_and_grad(params, K=K, width=W, height=H, c2w=C2W, backend=backend,
                                 background=[1.0, 0.0, 0.5])
    assert (out.radii == 0).all()
    assert torch.allclose(out.color.float(), torch.tensor([1.0, 0.0, 0.5]).expand(H, W, 3))
    assert (out.alpha == 0).all() and (out.depth == 0).all()
    for g in grads:
        assert (g == 0).all()


# ------------------------------------------------------------------------------------------ API


def test_c2w_vs_viewmat_and_numpy_vs_torch():
    params, _ = make_scene(seed=9, n=100)
    a = rasterize(*params, K=K, width=W, height=H, c2w=C2W)
    b = rasterize(*params, K=torch.tensor(K, dtype=torch.float32), width=W, height=H,
                  viewmat=torch.tensor(np.linalg.inv(C2W)))
    assert isinstance(a, RenderOutput)
    for k in ("color", "depth", "alpha"):
        assert torch.allclose(getattr(a, k), getattr(b, k), atol=1e-6), k
    assert torch.equal(a.radii, b.radii) and torch.equal(a.ids, torch.arange(params[0].shape[0]))
    assert a.color.shape == (H, W, 3) and a.depth.shape == (H, W) and a.alpha.shape == (H, W)
    assert a.radii.dtype == torch.int32 and a.ids.dtype == torch.int64


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_background(backend):
    params, _ = make_scene(seed=10, n=60)
    kw = dict(K=K, width=W, height=H, c2w=C2W, backend=backend)
    a = rasterize(*params, **kw)
    bg = torch.tensor([0.3, 0.6, 0.9])
    b = rasterize(*params, background=bg, **kw)
    assert torch.allclose(a.color, torch.zeros(3, dtype=a.color.dtype) + a.color)
    expect = a.color + (1 - a.alpha)[..., None] * bg.to(a.color.dtype)
    assert torch.allclose(b.color, expect, atol=1e-6)
    assert ((a.alpha < 0.999) & (a.alpha > 0)).any() and (a.alpha == 0).any()
    assert torch.equal(a.depth, b.depth) and torch.equal(a.alpha, b.alpha)


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_means2d_grad_populated(backend):
    params, _ = make_scene(seed=11, n=80, behind=5)
    out, _ = render_and_grad(params, K=K, width=W, height=H, c2w=C2W, backend=backend)
    g = out.means2d.grad
    assert g is not None and g.shape == (params[0].shape[0], 2)
    vis = out.radii > 0
    assert (g[vis].abs().sum(1) > 0).float().mean() > 0.8
    assert (g[~vis] == 0).all()


def test_no_grad_mode():
    params, _ = make_scene(seed=12, n=50)
    with torch.no_grad():
        out = rasterize(*params, K=K, width=W, height=H, c2w=C2W)
    assert not out.color.requires_grad and out.means2d.grad is None


@pytest.mark.parametrize("backend", ["warp", "torch"])
def test_single_gaussian_lands_at_K_pixel(backend):
    fx, fy, cx, cy = 80.0, 70.0, 40.3, 29.6
    Kp = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    c2w = np.eye(4)
    c2w[:3, :3] = _rot(0.2, 0.3, -0.1)
    c2w[:3, 3] = [1.0, 2.0, -0.5]
    pc = np.array([0.37, -0.21, 2.5])  # camera frame
    u, v = fx * pc[0] / pc[2] + cx, fy * pc[1] / pc[2] + cy
    pw = c2w[:3, :3] @ pc + c2w[:3, 3]
    means = torch.tensor(pw[None], dtype=torch.float32)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]])
    log_scales = torch.full((1, 3), math.log(0.004))
    out = rasterize(means, quats, log_scales, torch.tensor([8.0]), torch.tensor([[1.0, 0.5, 0.25]]),
                    K=Kp, width=80, height=60, c2w=c2w, backend=backend)
    assert torch.allclose(out.means2d[0].double(), torch.tensor([u, v], dtype=torch.float64), atol=1e-4)
    flat = int(torch.argmax(out.alpha))
    assert (flat % 80, flat // 80) == (round(u), round(v))
    # sigma = 0.004 m * 80 px / 2.5 m = 0.128 px, plus the 0.3 px^2 filter; offset (0.14, 0.28) px
    s2x, s2y = (fx * 0.004 / 2.5) ** 2 + 0.3, (fy * 0.004 / 2.5) ** 2 + 0.3
    du, dv = round(u) - u, round(v) - v
    expect_alpha = torch.sigmoid(torch.tensor(8.0)).item() * math.exp(-0.5 * (du * du / s2x + dv * dv / s2y))
    assert abs(out.alpha.max().item() - expect_alpha) < 1e-3  # small J x/z cross-terms neglected
    assert abs(out.depth[round(v), round(u)].item() - 2.5) < 1e-4
    assert torch.allclose(out.color[round(v), round(u)].float(),
                          torch.tensor([1.0, 0.5, 0.25]) * out.alpha.max().float(), atol=1e-5)


def test_project_gaussians_matches_pinhole_and_culls():
    means = torch.tensor([[0.1, 0.2, 2.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.005], [100.0, 0.0, 1.0]],
                         dtype=torch.float64)
    quats = torch.tensor([[2.0, 0.0, 0.0, 0.0]] * 4, dtype=torch.float64)  # unnormalised identity
    ls = torch.full((4, 3), math.log(0.01), dtype=torch.float64)
    Kt = torch.tensor(K)
    pr = project_gaussians(means, quats, ls, torch.eye(4, dtype=torch.float64), Kt, W, H)
    assert torch.allclose(pr.means2d[0], torch.tensor([55 * 0.05 + 31.7, 52 * 0.1 + 23.2], dtype=torch.float64))
    assert pr.radii.tolist()[1:] == [0, 0, 0] and pr.radii[0] > 0
    # isotropic sigma = 0.01 m: cov2d = sigma^2 J J^T + 0.3 I with the EWA Jacobian at (0.1, 0.2, 2)
    x, y, z = 0.1, 0.2, 2.0
    J = np.array([[55 / z, 0, -55 * x / z**2], [0, 52 / z, -52 * y / z**2]])
    cov = 1e-4 * J @ J.T + 0.3 * np.eye(2)
    inv = np.linalg.inv(cov)
    assert np.allclose(pr.conics[0].numpy(), [inv[0, 0], inv[0, 1], inv[1, 1]], rtol=1e-10)
    # radius rule of Kerbl et al.: lambda = mid + sqrt(max(0.1, mid^2 - det)), r = ceil(3 sqrt(lambda))
    mid = 0.5 * (cov[0, 0] + cov[1, 1])
    lam = mid + math.sqrt(max(0.1, mid * mid - np.linalg.det(cov)))
    assert lam >= np.linalg.eigvalsh(cov).max()
    assert pr.radii[0] == math.ceil(3 * math.sqrt(lam))
    assert abs(pr.depths[0].item() - 2.0) < 1e-12
    assert torch.isfinite(pr.means2d).all() and torch.isfinite(pr.conics).all()


def test_reference_gradcheck():
    """torch.autograd.gradcheck of the reference on a tiny smooth scene (all alphas in (1/255, 0.99))."""
    Kt = np.array([[20.0, 0, 5.5], [0, 20.0, 4.5], [0, 0, 1]])
    means = torch.tensor([[0.02, 0.01, 2.0], [-0.05, 0.03, 2.5], [0.04, -0.04, 3.0]], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0.1, -0.2, 0.3], [0.9, 0.3, 0.1, 0.0], [1.0, 0.0, 0.4, -0.1]], dtype=torch.float64)
    log_scales = torch.log(torch.tensor([[0.4, 0.6, 0.5], [0.7, 0.4, 0.6], [0.5, 0.5, 0.9]], dtype=torch.float64))
    opl = torch.tensor([-0.5, 0.2, 0.0], dtype=torch.float64)
    colors = torch.tensor([[0.9, 0.1, 0.2], [0.2, 0.8, 0.3], [0.1, 0.3, 0.7]], dtype=torch.float64)
    inputs = tuple(t.clone().requires_grad_() for t in (means, quats, log_scales, opl, colors))

    def f(*p):
        o = rasterize(*p, K=Kt, width=11, height=9, viewmat=np.eye(4), backend="torch",
                      background=[0.1, 0.1, 0.1])
        return o.color, o.depth, o.alpha

    o = f(*inputs)
    assert o[2].min() > 0.2  # every pixel sees the Gaussians: no threshold is near
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)
    # a tampered function must fail the same check (the check is not vacuous)
    def g(*p):
        c, d, a = f(*p)
        return c + 1e-3 * torch.sin(1e3 * p[0][0, 0].detach()) * p[0][0, 0], d, a

    assert not torch.autograd.gradcheck(g, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True,
                                        raise_exception=False)


def test_reference_chunking_is_invisible():
    from gausslite.render.binning import bin_gaussians
    from gausslite.render.reference import rasterize_reference

    params, _ = make_scene(seed=17, n=300, smax=0.1)
    m, q, ls, ol, col = params
    vm = torch.tensor(np.linalg.inv(C2W))
    pr = project_gaussians(m, q, ls, vm, torch.tensor(K), W, H)
    bins = bin_gaussians(pr.means2d, pr.radii, pr.depths, W, H, 16)
    op = torch.sigmoid(ol)
    a = rasterize_reference(pr.means2d, pr.conics, op, col, pr.depths, bins, W, H, 16)
    b = rasterize_reference(pr.means2d, pr.conics, op, col, pr.depths, bins, W, H, 16, chunk_elems=2000)
    for x, y in zip(a, b):
        assert torch.allclose(x, y, atol=1e-12)
    (a[0].sum() + a[1].sum()).backward(retain_graph=True)
    g1 = m.grad.clone()
    m.grad = None
    (b[0].sum() + b[1].sum()).backward()
    assert torch.allclose(g1, m.grad, atol=1e-10) and g1.abs().sum() > 0


@pytest.mark.parametrize(
    "kw, msg",
    [
        (dict(c2w=C2W, viewmat=np.eye(4)), "exactly one"),
        (dict(), "exactly one"),
        (dict(c2w=C2W, width=0), "width and height"),
        (dict(c2w=C2W, height=-3), "width and height"),
        (dict(c2w=C2W, K=np.full((3, 3), np.nan)), "K contains NaN"),
        (dict(c2w=np.full((4, 4), np.nan)), "c2w contains NaN"),
        (dict(viewmat=np.eye(3)), "viewmat must have shape"),
        (dict(c2w=C2W, K=np.eye(2)), "K must have shape"),
        (dict(c2w=C2W, backend="cuda-magic"), "unknown backend"),
        (dict(c2w=C2W, background=[1.0, 0.0]), "background must have shape"),
    ],
)
def test_errors(kw, msg):
    params, _ = make_scene(seed=13, n=5)
    args = dict(K=K, width=W, height=H)
    args.update(kw)
    with pytest.raises(ValueError, match=msg):
        rasterize(*params, **args)


def test_shape_errors():
    params, _ = make_scene(seed=14, n=5)
    kw = dict(K=K, width=W, height=H, c2w=C2W)
    with pytest.raises(ValueError, match="means must have shape"):
        rasterize(params[0][:, :2], *params[1:], **kw)
    with pytest.raises(ValueError, match="quats must have shape"):
        rasterize(params[0], params[1][:3], *params[2:], **kw)
    with pytest.raises(ValueError, match="colors must have shape"):
        rasterize(*params[:4], params[4][:, :2], **kw)
    with pytest.raises(ValueError, match="gsplat"):
        rasterize(*params, backend="gsplat", **kw)


# ------------------------------------------------------------------------------------------ CUDA


def _gsplat_skip_reason():
    if not torch.cuda.is_available():
        return "CUDA not available (torch.cuda.is_available() is False): gsplat backend is CUDA-only"
    try:
        import gsplat  # noqa: F401
    except Exception as e:  # noqa: BLE001
        return f"gsplat not importable ({type(e).__name__}: {e})"
    return None


@pytest.mark.skipif(_gsplat_skip_reason() is not None, reason=str(_gsplat_skip_reason()))
def test_gsplat_backend_close_to_warp_on_cuda():
    params, _ = make_scene(seed=15, n=200, dtype=torch.float32)
    params = [p.detach().cuda().requires_grad_() for p in params]
    a, _ = render_and_grad(params, backend="gsplat", K=K, width=W, height=H, c2w=C2W)
    b, _ = render_and_grad(params, backend="warp", K=K, width=W, height=H, c2w=C2W)
    assert a.means2d.grad is not None
    assert (a.color - b.color).abs().mean() < 1e-2
    assert (a.alpha - b.alpha).abs().mean() < 1e-2


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available (torch.cuda.is_available() is False)")
def test_warp_cuda_matches_cpu():
    params, _ = make_scene(seed=16, n=200, dtype=torch.float32)
    a, ga = render_and_grad(params, backend="warp", K=K, width=W, height=H, c2w=C2W)
    pc = [p.detach().cuda().requires_grad_() for p in params]
    b, gb = render_and_grad(pc, backend="warp", K=K, width=W, height=H, c2w=C2W)
    assert torch.allclose(a.color, b.color.cpu(), atol=1e-5)
    for x, y in zip(ga, gb):
        assert torch.allclose(x, y.cpu(), rtol=1e-3, atol=1e-5)
