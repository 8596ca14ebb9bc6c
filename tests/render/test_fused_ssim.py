"""Fused CPU SSIM (gausslite.fused_ssim) against the torch reference gausslite.metrics.ssim_map:
value and gradient, on odd sizes, near-identical images and images smaller than the window."""

from __future__ import annotations

import pytest
import torch

from gausslite.fused_ssim import FusedSSIM, fused_ssim_available, ssim_mean
from gausslite.metrics import ssim_gt_stats, ssim_map


def _pair(h, w, seed, noise=None):
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(h, w, 3, generator=g)
    pred = torch.rand(h, w, 3, generator=g) if noise is None else (gt + noise * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    return pred, gt


@pytest.mark.parametrize("h,w,seed,noise", [(48, 64, 0, None), (61, 83, 1, 0.05), (170, 300, 2, 0.02), (7, 9, 3, 0.1)])
def test_fused_ssim_matches_reference(h, w, seed, noise):
    pred, gt = _pair(h, w, seed, noise)
    stats = ssim_gt_stats(gt)
    p_ref = pred.clone().requires_grad_(True)
    ref = ssim_map(p_ref, gt, gt_stats=stats).mean()
    ref.backward()
    p = pred.clone().requires_grad_(True)
    val = FusedSSIM.apply(p, gt, *stats)
    val.backward()
    assert abs(val.item() - ref.item()) <= 1e-6
    assert p_ref.grad.norm() > 0
    rel = float((p.grad - p_ref.grad).norm() / p_ref.grad.norm())
    assert rel <= 1e-5, rel


def test_fused_ssim_upstream_gradient_scales():
    pred, gt = _pair(20, 30, 4, 0.1)
    stats = ssim_gt_stats(gt)
    p1 = pred.clone().requires_grad_(True)
    (3.0 * (1.0 - FusedSSIM.apply(p1, gt, *stats))).backward()
    p2 = pred.clone().requires_grad_(True)
    (1.0 - ssim_map(p2, gt, gt_stats=stats).mean()).backward()
    ref = 3.0 * p2.grad
    assert ref.norm() > 0 and float((p1.grad - ref).norm() / ref.norm()) <= 1e-5


def test_ssim_mean_dispatch():
    pred, gt = _pair(16, 16, 5, 0.1)
    assert fused_ssim_available(pred)
    p64 = pred.double()
    assert not fused_ssim_available(p64)  # float64 takes the torch path
    v64 = ssim_mean(p64, gt.double(), ssim_gt_stats(gt, dtype=torch.float64))
    v32 = ssim_mean(pred, gt, ssim_gt_stats(gt))
    assert v64.dtype == torch.float64 and abs(float(v64) - float(v32)) < 1e-5
    assert float(ssim_mean(gt, gt, ssim_gt_stats(gt))) == pytest.approx(1.0, abs=1e-5)


def test_fused_ssim_masked_mean_matches_reference():
    pred, gt = _pair(56, 74, 6, 0.05)
    g = torch.Generator().manual_seed(9)
    mask = torch.rand(56, 74, generator=g) > 0.6
    stats = ssim_gt_stats(gt)
    p_ref = pred.clone().requires_grad_(True)
    ref = ssim_map(p_ref, gt, gt_stats=stats)[mask].mean()
    ref.backward()
    p = pred.clone().requires_grad_(True)
    val = ssim_mean(p, gt, stats, mask=mask)
    val.backward()
    assert abs(val.item() - ref.item()) <= 1e-6
    rel = float((p.grad - p_ref.grad).norm() / p_ref.grad.norm())
    assert rel <= 1e-5, rel
    assert (p.grad[~mask].abs().sum() > 0)  # pixels next to the mask still move: their window overlaps it
    assert torch.isnan(ssim_mean(pred, gt, stats, mask=torch.zeros(56, 74, dtype=torch.bool)))


def _render_and_truth(h, w, seed):
    """A render (colour, depth with gradients) and a keyframe whose depth has holes (0) and NaN in invalid pixels."""
    from types import SimpleNamespace

    g = torch.Generator().manual_seed(seed)
    pred, gt = _pair(h, w, seed, 0.1)
    depth = (torch.rand(h, w, generator=g) * 3 + 0.5)
    gt_depth = (depth + 0.2 * torch.randn(h, w, generator=g)).clamp(min=0.1)
    gt_depth[torch.rand(h, w, generator=g) < 0.2] = 0.0
    gt_depth[: h // 4, : w // 4] = float("nan")
    out = SimpleNamespace(color=pred.clone().requires_grad_(True), depth=depth.clone().requires_grad_(True))
    return out, SimpleNamespace(rgb=gt, depth=gt_depth, ssim_stats=None)


@pytest.mark.parametrize("lam_ssim,masked", [(0.2, False), (0.2, True), (0.0, True), (0.0, False)])
def test_fused_photometric_loss_matches_the_torch_terms(lam_ssim, masked):
    """The fused path of photometric_loss (FusedPhotometric) against its torch expressions (reference=True): the
    loss, and the gradients of colour and depth, with and without a pixel mask, SSIM weighted or off, ground-truth
    depth with holes and NaN."""
    from gausslite.mapping import loss as loss_mod

    h, w = 61, 83
    out, kf = _render_and_truth(h, w, 7)
    mask = None
    if masked:
        mask = torch.rand(h, w, generator=torch.Generator().manual_seed(8)) > 0.5
    assert loss_mod._fused(out, kf)
    fused = loss_mod.photometric_loss(out, kf, 0.3, lam_ssim, mask)
    fused.backward()
    ref_out, _ = _render_and_truth(h, w, 7)
    ref = loss_mod.photometric_loss(ref_out, kf, 0.3, lam_ssim, mask, reference=True)
    ref.backward()
    assert abs(float(fused.detach()) - float(ref.detach())) <= 1e-6 * max(1.0, abs(float(ref.detach())))
    for a, b in ((out.color.grad, ref_out.color.grad), (out.depth.grad, ref_out.depth.grad)):
        assert b.norm() > 0
        assert float((a - b).norm() / b.norm()) <= 1e-5
    assert torch.isfinite(out.depth.grad).all() and not out.depth.grad[: h // 4, : w // 4].any()


def test_fused_photometric_loss_edge_cases():
    """An empty mask gives 0 with a zero gradient; no valid ground-truth depth leaves the depth term 0 (the colour
    terms stay); only the inputs that need a gradient get one."""
    from gausslite.mapping import loss as loss_mod

    out, kf = _render_and_truth(20, 30, 9)
    empty = loss_mod.photometric_loss(out, kf, 0.3, 0.2, torch.zeros(20, 30, dtype=torch.bool))
    empty.backward()
    assert float(empty) == 0.0 and not out.color.grad.any()
    out, kf = _render_and_truth(20, 30, 9)
    kf.depth[:] = 0.0
    loss = loss_mod.photometric_loss(out, kf, 0.3, 0.2)
    ref_out, _ = _render_and_truth(20, 30, 9)
    ref = loss_mod.photometric_loss(ref_out, kf, 0.3, 0.2, reference=True)
    loss.backward()
    assert float(loss) > 0 and abs(float(loss) - float(ref)) <= 1e-6
    assert not out.depth.grad.any() and out.color.grad.norm() > 0
    out, kf = _render_and_truth(20, 30, 9)
    out.depth = out.depth.detach()
    loss_mod.photometric_loss(out, kf, 0.3, 0.2).backward()
    assert out.color.grad.norm() > 0
