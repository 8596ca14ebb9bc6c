"""Fused SSIM loss on CPU: mean SSIM of a rendered image against a fixed ground truth, forward and
backward in native loops that the compiler vectorises.

The value is :func:`gausslite.metrics.ssim_map` ``(pred, gt, gt_stats=...).mean()`` (Wang et al. 2004;
11 x 11 Gaussian window, σ = 1.5, zero padding, C1 = 0.01², C2 = 0.03², mean over pixels and channels),
the structural term of the mapping loss (paper Eq. 1). The torch path filters 9 channels with grouped
``conv2d`` forward and again backward (about 19 ms per 300 x 170 image on this CPU); here each channel is
processed in one pass: the three statistics of the prediction (μ_x, E[x²], E[xy]) are blurred with a
separable window (row pass on a zero-padded copy, then column pass), SSIM and its derivatives with
respect to the three statistics are formed per pixel, and the backward pass blurs those derivatives
with the same (symmetric, zero-padded, hence self-adjoint) window:
``∂L/∂x = g · (G * ∂s/∂μ_x + 2 x · G * ∂s/∂E[x²] + y · G * ∂s/∂E[xy])`` with ``g = 1 / (3 H W)``.

Used by :func:`gausslite.mapping.loss.photometric_loss` for full-image views on CPU (float32);
:func:`gausslite.metrics.ssim_map` stays the reference (tests/render/test_fused_ssim.py: value within 1e-6,
gradient within 1e-5 relative).
"""

from __future__ import annotations

from typing import Optional

import torch
import warp as wp

from .metrics import SSIM_C1, SSIM_C2, gaussian_window, ssim_gt_stats, ssim_map
from .render.launch import launch_cpu
from .render.warp_kernels import ensure_module_loaded, run_parallel

wp.set_module_options({"enable_backward": False})

WINDOW = 11
SIGMA = 1.5
_PAD = WINDOW // 2

_BLUR = r"""
// separable zero-padded blur of a planar (H, W) map `src` into `dst`, via `tmp` (H*W) and `pad` (W + 16)
#define GL_BLUR(src, dst) do { \
    for (int yy = 0; yy < H; ++yy) { \
        for (int k = 0; k < W + 16; ++k) pad[k] = 0.0f; \
        const float* sr = (src) + (long)yy * W; \
        for (int xx = 0; xx < W; ++xx) pad[xx + 5] = sr[xx]; \
        float* tr = tmp + (long)yy * W; \
        for (int xx = 0; xx < W; ++xx) tr[xx] = 0.0f; \
        for (int k = 0; k < 11; ++k) { \
            const float gk = g[k]; \
            const float* pk = pad + k; \
            _Pragma("clang loop vectorize(enable)") \
            for (int xx = 0; xx < W; ++xx) tr[xx] += gk * pk[xx]; \
        } \
    } \
    for (int yy = 0; yy < H; ++yy) { \
        float* dr = (dst) + (long)yy * W; \
        for (int xx = 0; xx < W; ++xx) dr[xx] = 0.0f; \
        for (int k = 0; k < 11; ++k) { \
            const int ys = yy + k - 5; \
            if (ys < 0 || ys >= H) continue; \
            const float gk = g[k]; \
            const float* tr = tmp + (long)ys * W; \
            _Pragma("clang loop vectorize(enable)") \
            for (int xx = 0; xx < W; ++xx) dr[xx] += gk * tr[xx]; \
        } \
    } \
} while (0)
"""

# per channel c: the images, the window and this channel's scratch (three planar maps q0..q2, the
# row-pass buffer and the padded row)
_COMMON = _BLUR + r"""
const float* X = (const float*)pred.data;
const float* Y = (const float*)gt.data;
const float* g = (const float*)win.data;
const long HW = (long)H * W;
float* base = (float*)scratch.data + (long)c * 8 * (HW + W + 16);
float* q0 = base; float* q1 = base + HW; float* q2 = base + 2 * HW; float* tmp = base + 3 * HW;
float* pad = base + 4 * HW;
"""

_FWD = _COMMON + r"""
const float* MY = (const float*)mu_y.data + (long)c * H * W;
const float* VY = (const float*)sig_y.data + (long)c * H * W;
const float* WT = (const float*)weight.data;
float* D = (float*)deriv.data + (long)c * 3 * HW;   // ds/dmu_x, ds/de_xx, ds/de_xy
for (long i = 0; i < HW; ++i) {
    const float x = X[3 * i + c], y = Y[3 * i + c];
    q0[i] = x; q1[i] = x * x; q2[i] = x * y;
}
float* mux = D; float* exx = D + HW; float* exy = D + 2 * HW;
GL_BLUR(q0, mux);
GL_BLUR(q1, exx);
GL_BLUR(q2, exy);
double total = 0.0;
const float C1 = c1, C2 = c2;
for (int yy = 0; yy < H; ++yy) {
    float acc = 0.0f;
    const long o = (long)yy * W;
    #pragma clang loop vectorize(enable)
    for (int xx = 0; xx < W; ++xx) {
        const long i = o + xx;
        const float mx = mux[i], my = MY[i];
        const float vx = exx[i] - mx * mx;
        const float cv = exy[i] - mx * my;
        const float A1 = 2.0f * mx * my + C1, A2 = 2.0f * cv + C2;
        const float B1 = mx * mx + my * my + C1, B2 = vx + VY[i] + C2;
        const float Dn = B1 * B2;
        const float s = (A1 * A2) / Dn;
        const float wt = use_w ? WT[i] : 1.0f;
        acc += wt * s;
        mux[i] = wt * ((2.0f * my * (A2 - A1) - s * 2.0f * mx * (B2 - B1)) / Dn);
        exx[i] = wt * (-s / B2);
        exy[i] = wt * (2.0f * A1 / Dn);
    }
    total += (double)acc;
}
((double*)ssum.data)[c] = total;
"""

_BWD = _COMMON + r"""
const float* D = (const float*)deriv.data + (long)c * 3 * HW;
GL_BLUR(D, q0);
GL_BLUR(D + HW, q1);
GL_BLUR(D + 2 * HW, q2);
float* G = (float*)grad.data;
const float sc = scale;
for (long i = 0; i < HW; ++i) {
    const float x = X[3 * i + c], y = Y[3 * i + c];
    G[3 * i + c] = sc * (q0[i] + 2.0f * x * q1[i] + y * q2[i]);
}
"""


@wp.func_native(_FWD)
def _ssim_fwd_native(pred: wp.array(dtype=wp.float32), gt: wp.array(dtype=wp.float32),
                     mu_y: wp.array(dtype=wp.float32), sig_y: wp.array(dtype=wp.float32),
                     win: wp.array(dtype=wp.float32), weight: wp.array(dtype=wp.float32), use_w: int,
                     H: int, W: int, c: int, c1: float, c2: float,
                     scratch: wp.array(dtype=wp.float32), deriv: wp.array(dtype=wp.float32),
                     ssum: wp.array(dtype=wp.float64)): ...


@wp.func_native(_BWD)
def _ssim_bwd_native(pred: wp.array(dtype=wp.float32), gt: wp.array(dtype=wp.float32),
                     win: wp.array(dtype=wp.float32), H: int, W: int, c: int, scale: float,
                     scratch: wp.array(dtype=wp.float32), deriv: wp.array(dtype=wp.float32),
                     grad: wp.array(dtype=wp.float32)): ...


@wp.kernel
def ssim_fwd_kernel(pred: wp.array(dtype=wp.float32), gt: wp.array(dtype=wp.float32),
                    mu_y: wp.array(dtype=wp.float32), sig_y: wp.array(dtype=wp.float32),
                    win: wp.array(dtype=wp.float32), weight: wp.array(dtype=wp.float32), use_w: int,
                    H: int, W: int, c: int, c1: float, c2: float,
                    scratch: wp.array(dtype=wp.float32), deriv: wp.array(dtype=wp.float32),
                    ssum: wp.array(dtype=wp.float64)):
    """Channel ``c`` of the fused SSIM forward: ``ssum[c]`` = Σ over pixels of SSIM (times ``weight``
    (H*W) when ``use_w`` != 0), ``deriv[c]`` the three (H, W) derivative maps (weighted alike). ``pred``/``gt`` flat (H*W*3) float32 HWC; ``mu_y``/``sig_y`` (the variance of y) flat
    (3*H*W) planar; ``win`` (11,) window; ``scratch`` per channel 8 * (H*W + W + 16) floats."""
    _ssim_fwd_native(pred, gt, mu_y, sig_y, win, weight, use_w, H, W, c, c1, c2, scratch, deriv, ssum)


@wp.kernel
def ssim_bwd_kernel(pred: wp.array(dtype=wp.float32), gt: wp.array(dtype=wp.float32),
                    win: wp.array(dtype=wp.float32), H: int, W: int, c: int, scale: float,
                    scratch: wp.array(dtype=wp.float32), deriv: wp.array(dtype=wp.float32),
                    grad: wp.array(dtype=wp.float32)):
    """Channel ``c`` of the fused SSIM backward: ``grad`` (H*W*3) HWC gets ``scale`` × ∂(Σ SSIM)/∂pred."""
    _ssim_bwd_native(pred, gt, win, H, W, c, scale, scratch, deriv, grad)


class FusedSSIM(torch.autograd.Function):
    """Mean SSIM of ``pred`` against a fixed ``gt`` (no gradient to gt), CPU float32.

    forward(pred (H, W, 3) float32, gt (H, W, 3), mu_y (1, 3, H, W), var_y (1, 3, H, W)[, weight (H, W)])
    -> 0-dim float32 tensor: ``mean_{p, c} s_pc`` without ``weight``, ``Σ_p weight_p · mean_c s_pc`` with it
    (``weight = mask / |mask|`` is the mean over a pixel mask). ``mu_y``/``var_y`` are
    :func:`gausslite.metrics.ssim_gt_stats` of ``gt``.
    """

    @staticmethod
    def forward(ctx, pred, gt, mu_y, var_y, weight=None):
        H, W, C = pred.shape
        p = pred.detach().contiguous().reshape(-1)
        y = gt.detach().to(torch.float32).contiguous().reshape(-1)
        my = mu_y.detach().to(torch.float32).contiguous().reshape(-1)
        vy = var_y.detach().to(torch.float32).contiguous().reshape(-1)
        use_w = weight is not None
        wt = weight.detach().to(torch.float32).contiguous().reshape(-1) if use_w else torch.zeros(1)
        win = gaussian_window(WINDOW, SIGMA, dtype=torch.float32)
        scratch = torch.empty(C * 8 * (H * W + W + 16), dtype=torch.float32)
        deriv = torch.empty(C * 3 * H * W, dtype=torch.float32)
        ssum = torch.zeros(C, dtype=torch.float64)
        ensure_module_loaded(__name__, "cpu")

        def run(c):
            launch_cpu(ssim_fwd_kernel, 1, [p, y, my, vy, win, wt, int(use_w), H, W, c, SSIM_C1, SSIM_C2, scratch, deriv,
                                            ssum])

        run_parallel([lambda c=c: run(c) for c in range(C)])
        ctx.save_for_backward(p, y, win, scratch, deriv)
        ctx.shape = (H, W, C)
        ctx.norm = C if use_w else C * H * W
        return (ssum.sum() / ctx.norm).to(torch.float32)

    @staticmethod
    def backward(ctx, g_out):
        p, y, win, scratch, deriv = ctx.saved_tensors
        H, W, C = ctx.shape
        grad = torch.empty(H * W * C, dtype=torch.float32)
        scale = float(g_out) / ctx.norm

        def run(c):
            launch_cpu(ssim_bwd_kernel, 1, [p, y, win, H, W, c, scale, scratch, deriv, grad])

        run_parallel([lambda c=c: run(c) for c in range(C)])
        return grad.reshape(H, W, C), None, None, None, None


def fused_ssim_available(pred: torch.Tensor) -> bool:
    """True when :func:`ssim_mean` takes the fused path: a CPU float32 (H, W, 3) image."""
    return pred.device.type == "cpu" and pred.dtype == torch.float32 and pred.ndim == 3 and pred.shape[2] == 3


def ssim_mean(pred: torch.Tensor, gt: torch.Tensor, gt_stats: Optional[tuple[torch.Tensor, torch.Tensor]] = None,
              mask: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Mean SSIM of ``pred`` against the fixed ``gt``, differentiable in ``pred`` (the mapping loss's
    structural term, paper Eq. 1).

    Args:
        pred: (H, W, 3) float image in [0, 1] (the render).
        gt: (H, W, 3) ground truth (no gradient).
        gt_stats: :func:`gausslite.metrics.ssim_gt_stats` of ``gt`` in pred's dtype, each (1, 3, H, W);
            computed here when None.
        mask: optional (H, W) bool: the SSIM map is averaged over these pixels only (each still sees its
            full window, as :func:`gausslite.metrics.ssim`).
    Returns:
        0-dim tensor (NaN for an empty mask): the fused CPU path when :func:`fused_ssim_available`, else
        ``ssim_map(pred, gt, gt_stats=gt_stats)`` averaged (over ``mask``).
    """
    if gt_stats is None:
        gt_stats = ssim_gt_stats(gt, dtype=pred.dtype)
    if fused_ssim_available(pred) and tuple(gt.shape) == tuple(pred.shape):
        if mask is None:
            return FusedSSIM.apply(pred, gt, gt_stats[0], gt_stats[1])
        n = int(mask.sum())
        if n == 0:
            return torch.tensor(float("nan"), dtype=pred.dtype)
        return FusedSSIM.apply(pred, gt, gt_stats[0], gt_stats[1], mask.to(torch.float32) / n)
    m = ssim_map(pred, gt, gt_stats=gt_stats)
    return m.mean() if mask is None else m[mask].mean()
