"""Optional CUDA fast path through gsplat's ``rasterization`` (Ye et al. 2024, gsplat).

Import-guarded: nothing here imports gsplat until it is used, and it is never needed on CPU.
Semantics differ from the Warp/torch backends in gsplat's own culling and radius rule, so it
is a fast path for CUDA training, not a bit-exact twin of the reference.
"""

from __future__ import annotations

import torch


def gsplat_available() -> bool:
    """True when CUDA is available and ``import gsplat`` succeeds."""
    if not torch.cuda.is_available():
        return False
    try:
        # lazy: heavy optional dependency, loaded only on this path
        import gsplat  # noqa: F401
    except Exception:  # noqa: BLE001 - any import failure means "not available"
        return False
    return True


def rasterize_gsplat(means, quats, log_scales, opacity_logits, colors, *, viewmat, K, width,
                     height, near, far, eps2d, tile_size):
    """Render with ``gsplat.rasterization`` (classic mode, unpacked, render_mode "RGB+D").

    Args:
        means (M,3), quats (M,4) wxyz, log_scales (M,3), opacity_logits (M,), colors (M,3):
            CUDA tensors, world frame, metres.
        viewmat: (4,4) world-to-camera (OpenCV axes); K: (3,3) intrinsics in pixels.
        width, height: pixels; near, far: metres; eps2d: px^2; tile_size: pixels.

    Returns:
        color_raw (H,W,3) without background, depth_sum (H,W) = sum w z (gsplat's accumulated
        depth), alpha (H,W), means2d (M,2) pixels (a view of gsplat's projected centres whose
        ``.grad`` is filled by a hook during backward), radii (M,)
        int32 (max over x/y radii for gsplat >= 1.5, which returns (C,N,2)).
    """
    # lazy: heavy optional dependency, loaded only on this path
    from gsplat import rasterization

    render, alphas, meta = rasterization(
        means=means, quats=quats, scales=torch.exp(log_scales),
        opacities=torch.sigmoid(opacity_logits), colors=colors,
        viewmats=viewmat[None].to(means.dtype), Ks=K[None].to(means.dtype),
        width=width, height=height, near_plane=near, far_plane=far, eps2d=eps2d,
        packed=False, tile_size=tile_size, render_mode="RGB+D", rasterize_mode="classic",
    )
    full = meta["means2d"]  # (1, M, 2): the tensor that actually feeds gsplat's rasterizer
    means2d = full[0]
    if full.requires_grad:
        # The (M, 2) view is not on the path to the image, so copy the gradient of the (1, M, 2)
        # tensor into ``means2d.grad`` when backward reaches it.
        def _copy_grad(g, view=means2d):
            view.grad = g[0].detach().clone()

        full.register_hook(_copy_grad)
    radii = meta["radii"][0]
    if radii.dim() == 2:
        radii = radii.max(dim=-1).values
    return render[0, ..., :3], render[0, ..., 3], alphas[0, ..., 0], means2d, radii.to(torch.int32)
