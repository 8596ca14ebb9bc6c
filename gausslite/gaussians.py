"""GaussianMap: the structure-of-arrays Gaussian map (paper Sec. III-A, SPEC §2)."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class GaussianMap:
    """N anisotropic 3D Gaussians, structure of arrays, all tensors on one device.

    Fields (N = number of Gaussians):
        means: (N, 3) float32, world frame, metres.
        quats: (N, 4) float32, rotation quaternion (w, x, y, z), not necessarily normalised
            (normalised by the renderer).
        log_scales: (N, 3) float32, natural log of the per-axis standard deviation (metres).
        opacity_logits: (N,) float32, opacity = sigmoid(opacity_logits).
        colors: (N, 3) float32, RGB in [0, 1] (SH degree 0 stored as plain RGB; no activation).
        active: (N,) bool, task flag a_i set at seed time from the relevance map (paper III-A).
        kappa: (N,) int64, active-optimisation count κ_i (paper III-A, III-E).
    """

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    colors: torch.Tensor
    active: torch.Tensor
    kappa: torch.Tensor
