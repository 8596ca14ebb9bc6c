"""Differentiable tile-based 3D Gaussian Splatting rasterizer (Kerbl et al. 2023).

Public API: :func:`rasterize`, :class:`RenderOutput`, :func:`project_gaussians`.
Backends: Warp kernels (CPU and CUDA, default), a slow pure-PyTorch reference, and an optional
gsplat fast path on CUDA.
"""

from .api import RenderOutput, blend_weights, blend_weights_inside, rasterize, rasterize_bands
from .projection import project_gaussians

__all__ = ["rasterize", "rasterize_bands", "blend_weights", "blend_weights_inside", "RenderOutput", "project_gaussians"]
