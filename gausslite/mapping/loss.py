"""The mapping loss (paper Eq. 1): L1 colour + λ_d L1 depth + λ_s (1 − SSIM), on the whole view or a mask."""

from __future__ import annotations

from typing import Optional

import torch

from gausslite.fused_ssim import FusedPhotometric, fused_ssim_available, ssim_mean
from gausslite.mapping.views import Keyframe
from gausslite.metrics import ssim_gt_stats, ssim_map
from gausslite.render import RenderOutput


def _gt_ssim_stats(kf: Keyframe, dtype: torch.dtype) -> tuple:
    """``kf.ssim_stats`` in ``dtype``, computed (:func:`gausslite.metrics.ssim_gt_stats`) and kept on ``kf``
    when missing or of another dtype."""
    if kf.ssim_stats is None or kf.ssim_stats[0].dtype != dtype:
        kf.ssim_stats = ssim_gt_stats(kf.rgb, dtype=dtype)
    return kf.ssim_stats


def photometric_loss(
    out: RenderOutput,
    kf: Keyframe,
    lambda_depth: float,
    lambda_ssim: float,
    mask: Optional[torch.Tensor] = None,
    reference: bool = False,
) -> torch.Tensor:
    """L = L1_colour + λ_d · L1_depth + λ_s · (1 − SSIM) (paper Eq. 1).

    Args:
        out: render of the keyframe's view.
        kf: the keyframe (ground truth).
        mask: (H, W) bool pixels the terms are restricted to (ROI ∩ footprint in the active phase),
            None = full image. The depth term also requires valid ground-truth depth.
        reference: the terms as torch expressions, SSIM by the slow reference path
            (:func:`gausslite.metrics.ssim_map`), no cached ground-truth statistics
            (``MapperConfig.performance.reference_paths``). Otherwise, for a CPU float32 render, the three terms
            in one native pass without an autograd graph (:class:`gausslite.fused_ssim.FusedPhotometric`; the
            same values to float32 rounding); elsewhere the torch terms with :func:`gausslite.fused_ssim.ssim_mean`.
    Returns:
        scalar tensor (0 with a zero-gradient graph when the mask is empty). With a mask and λ_s = 0
        SSIM is not computed.
    """
    if not reference and _fused(out, kf):
        return _fused_loss(out, kf, lambda_depth, lambda_ssim, mask)
    valid_d = kf.depth > 0
    if mask is None:
        l1c = (out.color - kf.rgb).abs().mean()
        dmask = valid_d
        if reference:
            s = ssim_map(out.color, kf.rgb, reference=True).mean()
        else:
            s = ssim_mean(out.color, kf.rgb, _gt_ssim_stats(kf, out.color.dtype))
    else:
        if not bool(mask.any()):
            return out.color.sum() * 0.0
        # means over the mask as masked sums (no gather of the masked pixels, and no scatter back in the backward)
        l1c = ((out.color - kf.rgb).abs() * mask[..., None]).sum() / (3.0 * mask.sum())
        dmask = valid_d & mask
        if not lambda_ssim:
            s = 1.0
        elif reference:
            s = ssim_map(out.color, kf.rgb, reference=True)[mask].mean()
        else:
            s = ssim_mean(out.color, kf.rgb, _gt_ssim_stats(kf, out.color.dtype), mask=mask)
    n_d = dmask.sum()
    # torch.where, not a product: a NaN of an invalid pixel stays out of the sum
    l1d = (torch.where(dmask, (out.depth - kf.depth).abs(), 0.0).sum() / n_d if bool(n_d > 0)
           else out.depth.sum() * 0.0)
    return l1c + lambda_depth * l1d + lambda_ssim * (1.0 - s)


def _fused(out: RenderOutput, kf: Keyframe) -> bool:
    """Whether :func:`photometric_loss` takes the fused path: CPU float32 render and ground truth of one size."""
    return (fused_ssim_available(out.color) and out.depth.dtype == torch.float32 and out.depth.device.type == "cpu"
            and tuple(kf.rgb.shape) == tuple(out.color.shape) and tuple(kf.depth.shape) == tuple(out.depth.shape))


def _fused_loss(out: RenderOutput, kf: Keyframe, lambda_depth: float, lambda_ssim: float,
                mask: Optional[torch.Tensor]) -> torch.Tensor:
    """:func:`photometric_loss` by :class:`~gausslite.fused_ssim.FusedPhotometric` (same terms and masks)."""
    weight = None
    if mask is not None:
        n = int(mask.sum())
        if n == 0:
            return out.color.sum() * 0.0
        weight = mask.to(torch.float32) / n
    with_ssim = bool(lambda_ssim)  # λ_s = 0: the term is 0 whatever SSIM is
    mu, var = _gt_ssim_stats(kf, out.color.dtype) if with_ssim else (kf.rgb, kf.rgb)
    l1c, l1d, s = FusedPhotometric.apply(out.color, out.depth, kf.rgb, kf.depth, mu, var, weight, with_ssim)
    return l1c + lambda_depth * l1d + lambda_ssim * (1.0 - s)


def outside_alpha(alpha: torch.Tensor, roi: torch.Tensor, margin_px: int = 2) -> torch.Tensor:
    """Mean rendered alpha over the pixels outside the ROI grown by ``margin_px`` (a transparency penalty).

    A Gaussian fitted on ROI pixels alone (paper Eq. 1 restricted to the ROI) is free to spread over the pixels
    beside it; in a fused team map those belong to other robots' regions. This term makes what is fitted draw its
    ROI and nothing around it (``MapperConfig.roi_outside_alpha``; ``docs/sharing.md``).

    Args:
        alpha: (H, W) float rendered alpha (``RenderOutput.alpha``), in [0, 1].
        roi: (H, W) bool ROI pixels of the same view.
        margin_px: pixels around the ROI that are not penalised (>= 0; its anti-aliased edge).

    Returns:
        scalar tensor; 0 (with a graph) when no pixel lies outside.

    Raises:
        ValueError: shapes differ or ``margin_px`` < 0.
    """
    if alpha.shape != roi.shape:
        raise ValueError(f"alpha {tuple(alpha.shape)} and roi {tuple(roi.shape)} differ")
    if margin_px < 0:
        raise ValueError(f"margin_px must be >= 0, got {margin_px}")
    grown = roi.to(alpha.device, torch.float32)[None, None]
    if margin_px:
        grown = torch.nn.functional.max_pool2d(grown, 2 * margin_px + 1, stride=1, padding=margin_px)
    outside = grown[0, 0] < 0.5
    if not bool(outside.any()):
        return alpha.sum() * 0.0
    return alpha[outside].mean()
