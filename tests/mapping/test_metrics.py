"""PSNR / SSIM / depth L1."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from gausslite.metrics import depth_l1, gaussian_window, psnr, ssim, ssim_map


def rand_img(h=24, w=32, seed=0, dtype=torch.float32):
    return torch.rand(h, w, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)


def reference_ssim_map(x: np.ndarray, y: np.ndarray, win=11, sigma=1.5) -> np.ndarray:
    """Straight Wang et al. 2004 SSIM with scipy, zero padding ('same'), per channel then mean."""
    r = np.arange(win) - win // 2
    g = np.exp(-(r**2) / (2 * sigma**2))
    g /= g.sum()
    k = np.outer(g, g)
    c1, c2 = 0.01**2, 0.03**2
    maps = []
    for c in range(x.shape[2]):
        a, b = x[..., c], y[..., c]
        f = lambda z: ndimage.correlate(z, k, mode="constant", cval=0.0)  # noqa: E731
        mu_a, mu_b = f(a), f(b)
        va, vb, cov = f(a * a) - mu_a**2, f(b * b) - mu_b**2, f(a * b) - mu_a * mu_b
        maps.append(((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (va + vb + c2)))
    return np.mean(maps, axis=0)


# -------------------------------------------------------------------- PSNR
def test_psnr_identical_is_inf_and_known_values():
    a = rand_img()
    assert math.isinf(float(psnr(a, a))) and float(psnr(a, a)) > 0
    b = (a + 0.1).clamp(max=10)  # constant error 0.1 → MSE 0.01 → 20 dB
    assert float(psnr(b, a)) == pytest.approx(20.0, abs=1e-4)
    z = torch.zeros(4, 4, 3)
    assert float(psnr(z, z + 0.5)) == pytest.approx(10 * math.log10(4), abs=1e-9)
    assert psnr(a, b).dtype == torch.float64 and psnr(a, b).ndim == 0


def test_psnr_mask_only_uses_masked_pixels_and_empty_is_nan():
    a = rand_img(seed=1)
    b = a.clone()
    mask = torch.zeros(24, 32, dtype=torch.bool)
    mask[5:10, 3:20] = True
    b[mask] += 0.01                   # error 0.01 inside → 40 dB
    b[~mask] = 1.0 - b[~mask]         # garbage outside
    assert float(psnr(b, a, mask)) == pytest.approx(40.0, abs=1e-3)
    assert float(psnr(b, a)) < 20
    assert math.isnan(float(psnr(b, a, torch.zeros(24, 32, dtype=torch.bool))))


def test_input_validation():
    a = rand_img()
    with pytest.raises(ValueError, match="differ in shape"):
        psnr(a, a[:-1])
    with pytest.raises(ValueError, match=r"\(H, W, C\)"):
        ssim(a[..., 0], a[..., 0])
    with pytest.raises(ValueError, match="mask must be"):
        psnr(a, a, torch.ones(24, 32))
    with pytest.raises(ValueError, match="odd"):
        ssim(a, a, window=4)
    with pytest.raises(ValueError, match="float"):
        psnr((a * 255).to(torch.uint8), (a * 255).to(torch.uint8))
    with pytest.raises(ValueError, match="depths"):
        depth_l1(torch.zeros(3, 4), torch.zeros(4, 3))


# -------------------------------------------------------------------- SSIM
def test_ssim_identical_is_one_and_window_sums_to_one():
    a = rand_img(seed=2)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-6)
    assert torch.allclose(ssim_map(a, a), torch.ones(24, 32), atol=1e-5)
    g = gaussian_window(11, 1.5, dtype=torch.float64)
    assert float(g.sum()) == pytest.approx(1.0) and int(g.argmax()) == 5


@pytest.mark.parametrize("win,sigma", [(11, 1.5), (7, 1.0)])
def test_ssim_matches_scipy_reference(win, sigma):
    a = rand_img(20, 27, seed=3, dtype=torch.float64)
    b = (a + 0.15 * torch.randn(20, 27, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)).clamp(0, 1)
    ref = reference_ssim_map(a.numpy(), b.numpy(), win, sigma)
    got = ssim_map(a, b, window=win, sigma=sigma).numpy()
    np.testing.assert_allclose(got, ref, atol=1e-10)
    assert float(ssim(a, b, window=win, sigma=sigma)) == pytest.approx(ref.mean(), abs=1e-10)
    # float32 path agrees to float32 accuracy
    got32 = ssim(a.float(), b.float(), window=win, sigma=sigma)
    assert got32.dtype == torch.float32 and float(got32) == pytest.approx(ref.mean(), abs=2e-5)
    assert 0 < ref.mean() < 1


def test_ssim_tiny_image_smaller_than_window():
    a = rand_img(4, 5, seed=5)
    assert float(ssim(a, a)) == pytest.approx(1.0, abs=1e-6)
    assert float(ssim(a, 1 - a)) < 0.5


def test_masked_ssim_averages_the_map_over_the_mask():
    a = rand_img(40, 40, seed=6)
    b = (a + 0.05).clamp(0, 1)
    mask = torch.zeros(40, 40, dtype=torch.bool)
    mask[15:25, 12:28] = True
    full_map = ssim_map(a, b)
    assert float(ssim(a, b, mask)) == pytest.approx(float(full_map[mask].mean()), abs=1e-7)
    # pixels farther than window//2 = 5 from the mask do not matter
    far = torch.ones(40, 40, dtype=torch.bool)
    far[10:30, 7:33] = False
    b2 = b.clone()
    b2[far] = torch.rand(int(far.sum()), 3, generator=torch.Generator().manual_seed(9))
    assert float(ssim(a, b2, mask)) == pytest.approx(float(ssim(a, b, mask)), abs=1e-6)
    assert float(ssim(a, b2)) < float(ssim(a, b)) - 0.05
    assert math.isnan(float(ssim(a, b, torch.zeros(40, 40, dtype=torch.bool))))


def test_ssim_is_differentiable_plain_and_masked():
    gt = rand_img(16, 16, seed=7)
    pred = (gt + 0.1 * torch.randn(16, 16, 3, generator=torch.Generator().manual_seed(8))).clamp(0, 1)
    pred.requires_grad_(True)
    loss = 1.0 - ssim(pred, gt)
    loss.backward()
    assert pred.grad is not None and torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0
    # gradient step decreases 1 - SSIM
    with torch.no_grad():
        better = pred - 0.5 * pred.grad / pred.grad.abs().max() * 0.05
    assert float(1.0 - ssim(better, gt)) < float(loss.detach())
    # float64 gradcheck on a small patch
    x = rand_img(6, 7, seed=10, dtype=torch.float64).requires_grad_(True)
    y = rand_img(6, 7, seed=11, dtype=torch.float64)
    m = torch.zeros(6, 7, dtype=torch.bool)
    m[1:4, 2:6] = True
    assert torch.autograd.gradcheck(lambda t: ssim(t, y, m, window=5), (x,))
    # masked: gradient only reaches pixels within the window of the mask
    p2 = pred.detach().clone().requires_grad_(True)
    m2 = torch.zeros(16, 16, dtype=torch.bool)
    m2[0:2, 0:2] = True
    (1.0 - ssim(p2, gt, m2, window=3)).backward()
    assert p2.grad[5:, :].abs().sum() == 0 and p2.grad[:3, :3].abs().sum() > 0


# ---------------------------------------------------------------- depth L1
def test_depth_l1_valid_pixels_and_mask():
    gt = torch.full((5, 6), 2.0)
    gt[0, :] = 0.0                    # invalid row
    gt[1, 0] = float("nan")           # invalid
    pred = gt.nan_to_num(0.0) + 0.25
    pred[0, :] = 100.0                # must be ignored
    pred[1, 0] = 100.0
    assert float(depth_l1(pred, gt)) == pytest.approx(0.25)
    mask = torch.zeros(5, 6, dtype=torch.bool)
    mask[4, 2:4] = True
    pred[4, 2] += 1.0
    assert float(depth_l1(pred, gt, mask)) == pytest.approx((1.25 + 0.25) / 2)
    mask0 = torch.zeros(5, 6, dtype=torch.bool)
    mask0[0, :] = True                # only invalid gt pixels
    assert math.isnan(float(depth_l1(pred, gt, mask0)))
    p = pred.clone().requires_grad_(True)
    depth_l1(p, gt).backward()
    assert p.grad[0].abs().sum() == 0 and p.grad[2, 2] > 0


def test_ssim_map_fast_path_matches_full_filtering():
    """Ground truth without gradients (the mapper's case): its statistics are filtered without a graph
    (or passed cached) and only x, x², x·y with one; values and gradients equal the 15-channel path."""
    from gausslite.metrics import ssim_gt_stats

    g = torch.Generator().manual_seed(0)
    pred0, gt = torch.rand(23, 31, 3, generator=g), torch.rand(23, 31, 3, generator=g)
    a = pred0.clone().requires_grad_(True)
    fast = ssim_map(a, gt)
    fast.sum().backward()
    b = pred0.clone().requires_grad_(True)
    full = ssim_map(b, gt.clone().requires_grad_(True))  # gt with a graph: the 15-channel path
    full.sum().backward()
    torch.testing.assert_close(fast, full.detach(), rtol=0, atol=1e-6)
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-5, atol=1e-7)
    c = pred0.clone().requires_grad_(True)
    cached = ssim_map(c, gt, gt_stats=ssim_gt_stats(gt))
    torch.testing.assert_close(cached, fast.detach(), rtol=0, atol=0)


def test_ssim_with_mask_gives_both_ssim_values_from_one_map_and_cached_statistics():
    from gausslite.metrics import GtStatsCache, ssim_with_mask

    g = torch.Generator().manual_seed(3)
    rgb = (torch.rand(40, 56, 3, generator=g) * 255).to(torch.uint8).numpy()
    gt = torch.from_numpy(rgb).float() / 255.0
    pred = (gt + 0.05 * torch.randn(40, 56, 3, generator=g)).clamp(0, 1)
    mask = torch.zeros(40, 56, dtype=torch.bool)
    mask[10:25, 5:30] = True
    cache = GtStatsCache(size=2)
    stats = cache.get(rgb, gt, pred.dtype)
    assert cache.get(rgb.copy(), gt, pred.dtype) is stats  # the same pixels, another array: a hit
    full, roi = ssim_with_mask(pred, gt, mask, stats)
    assert float(full) == float(ssim(pred, gt)) and float(roi) == float(ssim(pred, gt, mask=mask))
    full2, none = ssim_with_mask(pred, gt, torch.zeros_like(mask))
    assert float(full2) == float(full) and math.isnan(float(none))
    changed = rgb.copy()
    changed[0, 0, 0] ^= 1
    assert cache.get(changed, torch.from_numpy(changed).float() / 255.0, pred.dtype) is not stats
    with pytest.raises(ValueError):
        ssim_with_mask(pred, gt, mask[:-1])
