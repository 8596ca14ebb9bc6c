"""The SIMD EWA projection (gausslite.render.simd_projection) against the scalar Warp kernels it replaces and the
pure-PyTorch reference: outputs and gradients, culled and degenerate rows, several cameras in one launch."""

from __future__ import annotations

import pytest
import torch
from scipy.spatial.transform import Rotation

from gausslite.render import project_gaussians
from gausslite.render.autograd import project_gaussians_warp

W, H = 96, 72


def _camera(seed: int):
    """A (4, 4) float64 world-to-camera matrix and (3, 3) intrinsics."""
    g = torch.Generator().manual_seed(seed)
    vm = torch.eye(4, dtype=torch.float64)
    vm[:3, :3] = torch.from_numpy(Rotation.from_rotvec((torch.rand(3, generator=g) - 0.5).numpy() * 0.4).as_matrix())
    vm[:3, 3] = (torch.rand(3, generator=g) - 0.5) * 0.3
    K = torch.tensor([[80.0, 0, 47.5], [0, 82.0, 35.5], [0, 0, 1]], dtype=torch.float64)
    return vm, K


def _gaussians(n: int, dtype: torch.dtype, seed: int = 0):
    """``n`` Gaussians in front of the camera, with the rows a projection must cull or sanitise: behind the near
    plane, a NaN mean, a zero quaternion (projected as the identity rotation), an infinite and a huge log-scale, one
    far outside the image."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.6
    means[:, 2] += 2.5
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    ls = torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.4 - 3.0
    means[1, 2] = -0.5
    means[2, 0] = float("nan")
    quats[3] = 0.0
    ls[4, 1] = float("inf")
    ls[5] = 800.0
    means[6] = torch.tensor([40.0, 0.0, 1.0], dtype=torch.float64)
    return [t.to(dtype) for t in (means, quats, ls)]


def _weights(n: int, dtype: torch.dtype) -> list:
    """A fixed random linear loss's weights on (means2d, conics, depths) of ``n`` rows."""
    g = torch.Generator().manual_seed(7)
    return [torch.randn(n, 2, generator=g, dtype=dtype), torch.randn(n, 3, generator=g, dtype=dtype),
            torch.randn(n, generator=g, dtype=dtype)]


def _project(params, vm, K, simd: bool, cam_of_row=None, weights=None):
    """Outputs (means2d, conics, depths, radii) and the gradients of a fixed random linear loss on them
    (``weights``, default :func:`_weights`) w.r.t. the means, quats and log-scales."""
    ps = [t.clone().requires_grad_(True) for t in params]
    p = project_gaussians_warp(*ps, vm, K, W, H, num_threads=2, simd=simd, cam_of_row=cam_of_row)
    wm, wc, wd = weights if weights is not None else _weights(len(ps[0]), ps[0].dtype)
    loss = (p.means2d * wm).sum() + (p.conics * wc).sum() + (p.depths * wd).sum()
    loss.backward()
    return [p.means2d.detach(), p.conics.detach(), p.depths.detach(), p.radii] + [t.grad for t in ps]


def _close(a: torch.Tensor, b: torch.Tensor, rtol: float, atol: float) -> None:
    assert torch.equal(torch.isfinite(a), torch.isfinite(b))
    ok = torch.isfinite(a)
    torch.testing.assert_close(a[ok], b[ok], rtol=rtol, atol=atol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n", [1, 7, 8, 1003])
def test_simd_projection_matches_the_warp_kernels(dtype, n):
    params = _gaussians(max(n, 8), dtype)
    params = [t[:n] for t in params]
    vm, K = _camera(1)
    simd, ref = _project(params, vm, K, True), _project(params, vm, K, False)
    # float64 throughout: the two differ by the order of float64 operations (FMA contraction) only
    tol = dict(rtol=1e-6, atol=1e-6) if dtype == torch.float32 else dict(rtol=1e-9, atol=1e-9)
    for a, b in zip(simd, ref):
        if a.dtype == torch.int32:
            assert torch.equal(a, b)
        else:
            _close(a, b, **tol)
    radii = simd[3]
    if n >= 8:
        assert (radii[[1, 2, 4, 5, 6]] == 0).all(), "culled and degenerate rows have radius 0"
        assert radii[3] > 0, "a zero quaternion is the identity rotation"
        assert (radii[7:] > 0).any()
        assert torch.equal(simd[4][1], torch.zeros(3, dtype=dtype)), "no gradient through a row behind the camera"


def test_simd_projection_matches_the_reference():
    params = _gaussians(500, torch.float64, seed=3)
    params = [t[8:] for t in params]  # finite rows in front of the camera
    vm, K = _camera(2)
    ps = [t.clone().requires_grad_(True) for t in params]
    ref = project_gaussians(*ps, vm, K, W, H)
    out = project_gaussians_warp(*[t.detach() for t in params], vm, K, W, H)
    torch.testing.assert_close(out.means2d, ref.means2d.detach(), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(out.conics, ref.conics.detach(), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(out.depths, ref.depths.detach(), rtol=1e-12, atol=1e-12)
    assert torch.equal(out.radii, ref.radii.to(torch.int32))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_several_cameras_in_one_launch_match_one_launch_per_camera(dtype):
    params = _gaussians(600, dtype, seed=5)
    cams = [_camera(s) for s in (1, 2, 3)]
    counts = [250, 3, 347]
    cam_of_row = torch.repeat_interleave(torch.arange(3, dtype=torch.int32), torch.tensor(counts))
    weights = _weights(600, dtype)
    both = _project(params, [c[0] for c in cams], [c[1] for c in cams], True, cam_of_row, weights)
    a = 0
    for (vm, K), n in zip(cams, counts):
        one = _project([t[a:a + n] for t in params], vm, K, True, weights=[w[a:a + n] for w in weights])
        for x, y in zip(both, one):
            torch.testing.assert_close(x[a:a + n], y, rtol=0, atol=0, equal_nan=True)  # bit for bit
        a += n


def test_several_cameras_need_the_simd_kernels_and_one_camera_per_row():
    params = _gaussians(16, torch.float32)
    vm, K = _camera(1)
    with pytest.raises(ValueError, match="SIMD"):
        project_gaussians_warp(*params, [vm], [K], W, H, simd=False, cam_of_row=torch.zeros(16, dtype=torch.int32))
    with pytest.raises(ValueError, match="int32"):
        project_gaussians_warp(*params, [vm], [K], W, H, cam_of_row=torch.zeros(16, dtype=torch.int64))
    with pytest.raises(ValueError, match="int32"):
        project_gaussians_warp(*params, [vm, vm], [K], W, H, cam_of_row=torch.zeros(16, dtype=torch.int32))
