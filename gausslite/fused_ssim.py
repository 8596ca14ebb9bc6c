"""Fused photometric loss terms on CPU: the mean SSIM and the L1 colour and depth terms of the mapping loss
(paper Eq. 1) of a rendered image against a fixed ground truth, forward and backward in native loops that the
compiler vectorises, with no autograd graph between them.

The SSIM value is :func:`gausslite.metrics.ssim_map` ``(pred, gt, gt_stats=...).mean()`` (Wang et al. 2004;
11 x 11 Gaussian window, σ = 1.5, zero padding, C1 = 0.01², C2 = 0.03², mean over pixels and channels).
The torch path filters 9 channels with grouped ``conv2d`` forward and again backward (about 19 ms per
300 x 170 image on this CPU); here each channel is processed in one pass: the three statistics of the
prediction (μ_x, E[x²], E[xy]) are blurred with a separable window (a row pass, then a column pass, each
output vector of 16 pixels summed over the 11 taps in registers), SSIM and its derivatives with respect to
the three statistics are formed per pixel, and the backward pass blurs those derivatives with the same
(symmetric, zero-padded, hence self-adjoint) window:
``∂L/∂x = g · (G * ∂s/∂μ_x + 2 x · G * ∂s/∂E[x²] + y · G * ∂s/∂E[xy])`` with ``g = 1 / (3 H W)``.
The same passes sum the L1 colour term ``mean |x − y|`` (gradient ``sign(x − y) / (3 H W)``), and one more
the L1 depth term over the pixels with valid ground-truth depth (:class:`FusedPhotometric`).

Used by :func:`gausslite.mapping.loss.photometric_loss` on CPU (float32); the torch expressions stay the
reference (:func:`gausslite.metrics.ssim_map`, and the loss's own torch terms under
``performance.reference_paths``; tests/render/test_fused_ssim.py: values within 1e-6, gradients within 1e-5
relative).
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
_WIN = gaussian_window(WINDOW, SIGMA, dtype=torch.float32)

# separable zero-padded blur of a planar (H, W) map `src` into `dst`, via `tmp` (H*W) and `pad` (W + 16): the
# row pass on a zero-padded copy of each row, then the column pass; each 16-pixel output vector is summed over the
# 11 taps in a register (11 loads and one store), a scalar loop finishes a row
_BLUR = r"""
typedef float v16f __attribute__((ext_vector_type(16)));
auto ld16 = [](const float* p) -> v16f { v16f v; __builtin_memcpy(&v, p, sizeof(v)); return v; };
auto st16 = [](float* p, const v16f v) { __builtin_memcpy(p, &v, sizeof(v)); };
auto blur = [&](const float* src, float* dst) {
    for (int k = 0; k < 5; ++k) pad[k] = 0.0f;
    for (int k = W + 5; k < W + 16; ++k) pad[k] = 0.0f;
    for (int yy = 0; yy < H; ++yy) {
        const float* sr = src + (long)yy * W;
        for (int xx = 0; xx < W; ++xx) pad[xx + 5] = sr[xx];
        float* tr = tmp + (long)yy * W;
        int xx = 0;
        for (; xx + 16 <= W; xx += 16) {
            v16f acc = g[0] * ld16(pad + xx);
            for (int k = 1; k < 11; ++k) acc += g[k] * ld16(pad + xx + k);
            st16(tr + xx, acc);
        }
        for (; xx < W; ++xx) {
            float acc = 0.0f;
            for (int k = 0; k < 11; ++k) acc += g[k] * pad[xx + k];
            tr[xx] = acc;
        }
    }
    for (int yy = 0; yy < H; ++yy) {
        const int ka = yy >= 5 ? 0 : 5 - yy, kb = yy + 5 < H ? 10 : H - 1 - yy + 5;
        const float* t0 = tmp + (long)(yy + ka - 5) * W;  // the row of tap ka
        const float* gk = g + ka;
        const int nk = kb - ka;
        float* dr = dst + (long)yy * W;
        int xx = 0;
        for (; xx + 16 <= W; xx += 16) {
            v16f acc = gk[0] * ld16(t0 + xx);
            for (int k = 1; k <= nk; ++k) acc += gk[k] * ld16(t0 + (long)k * W + xx);
            st16(dr + xx, acc);
        }
        for (; xx < W; ++xx) {
            float acc = 0.0f;
            for (int k = 0; k <= nk; ++k) acc += gk[k] * t0[(long)k * W + xx];
            dr[xx] = acc;
        }
    }
};
"""

# per channel c: the images, the window and this channel's scratch (three planar maps q0..q2, the
# row-pass buffer and the padded row)
_COMMON = r"""
#pragma clang fp contract(fast)
const float* X = (const float*)pred.data;
const float* Y = (const float*)gt.data;
const float* WT = (const float*)weight.data;
const long HW = (long)H * W;
float* base = (float*)scratch.data + (long)c * (4 * HW + W + 16);
float* q0 = base; float* q1 = base + HW; float* q2 = base + 2 * HW; float* tmp = base + 3 * HW;
float* pad = base + 4 * HW;
const float* g = (const float*)win.data;
""" + _BLUR

_FWD = _COMMON + r"""
float* D = (float*)deriv.data + (long)c * 3 * HW;   // ds/dmu_x, ds/de_xx, ds/de_xy
double l1 = 0.0;
for (int yy = 0; yy < H; ++yy) {
    float acc = 0.0f;
    for (int xx = 0; xx < W; ++xx) {
        const long i = (long)yy * W + xx;
        const float x = X[3 * i + c], y = Y[3 * i + c];
        if (do_ssim) { q0[i] = x; q1[i] = x * x; q2[i] = x * y; }
        acc += (use_w ? WT[i] : 1.0f) * fabsf(x - y);
    }
    l1 += (double)acc;
}
((double*)lsum.data)[c] = l1;
((double*)ssum.data)[c] = 0.0;
if (do_ssim) {
    const float* MY = (const float*)mu_y.data + (long)c * H * W;
    const float* VY = (const float*)sig_y.data + (long)c * H * W;
    float* mux = D; float* exx = D + HW; float* exy = D + 2 * HW;
    blur(q0, mux);
    blur(q1, exx);
    blur(q2, exy);
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
}
"""

_BWD = _COMMON + r"""
const float* D = (const float*)deriv.data + (long)c * 3 * HW;
float* G = (float*)grad.data;
const float sc = scale, lsc = l1_scale;
if (do_ssim) {
    blur(D, q0);
    blur(D + HW, q1);
    blur(D + 2 * HW, q2);
}
for (long i = 0; i < HW; ++i) {
    const float x = X[3 * i + c], y = Y[3 * i + c];
    const float sgn = (float)(x > y) - (float)(x < y);
    const float gl = lsc * (use_w ? WT[i] : 1.0f) * sgn;
    G[3 * i + c] = do_ssim ? sc * (q0[i] + 2.0f * x * q1[i] + y * q2[i]) + gl : gl;
}
"""

# the L1 depth term over the pixels with valid ground truth (depth > 0; NaN is invalid) and a positive weight:
# the sum and the count (forward), and the gradient ``scale * sign(d - d_gt)`` there, 0 elsewhere (backward)
_DEPTH_FWD = r"""
const long HW = nhw;
const float* Dp = (const float*)depth.data;
const float* Dg = (const float*)gt_depth.data;
const float* WT = (const float*)weight.data;
double s = 0.0;
long n = 0;
for (long i = 0; i < HW; ++i) {
    if (Dg[i] > 0.0f && (!use_w || WT[i] > 0.0f)) { s += (double)fabsf(Dp[i] - Dg[i]); ++n; }
}
((double*)out.data)[0] = s;
((double*)out.data)[1] = (double)n;
"""

_DEPTH_BWD = r"""
const long HW = nhw;
const float* Dp = (const float*)depth.data;
const float* Dg = (const float*)gt_depth.data;
const float* WT = (const float*)weight.data;
float* G = (float*)grad.data;
const float sc = scale;
for (long i = 0; i < HW; ++i) {
    const bool v = Dg[i] > 0.0f && (!use_w || WT[i] > 0.0f);
    const float d = Dp[i] - Dg[i];
    G[i] = v ? sc * ((float)(d > 0.0f) - (float)(d < 0.0f)) : 0.0f;
}
"""


@wp.func_native(_FWD)
def _ssim_fwd_native(pred: wp.array(dtype=wp.float32), gt: wp.array(dtype=wp.float32),
                     mu_y: wp.array(dtype=wp.float32), sig_y: wp.array(dtype=wp.float32),
                     win: wp.array(dtype=wp.float32), weight: wp.array(dtype=wp.float32), use_w: int,
                     do_ssim: int, H: int, W: int, c: int, c1: float, c2: float,
                     scratch: wp.array(dtype=wp.float32), deriv: wp.array(dtype=wp.float32),
                     ssum: wp.array(dtype=wp.float64), lsum: wp.array(dtype=wp.float64)): ...


@wp.func_native(_BWD)
def _ssim_bwd_native(pred: wp.array(dtype=wp.float32), gt: wp.array(dtype=wp.float32),
                     win: wp.array(dtype=wp.float32), weight: wp.array(dtype=wp.float32), use_w: int,
                     do_ssim: int, H: int, W: int, c: int, scale: float, l1_scale: float,
                     scratch: wp.array(dtype=wp.float32), deriv: wp.array(dtype=wp.float32),
                     grad: wp.array(dtype=wp.float32)): ...


@wp.func_native(_DEPTH_FWD)
def _depth_fwd_native(depth: wp.array(dtype=wp.float32), gt_depth: wp.array(dtype=wp.float32),
                      weight: wp.array(dtype=wp.float32), use_w: int, nhw: int,
                      out: wp.array(dtype=wp.float64)): ...


@wp.func_native(_DEPTH_BWD)
def _depth_bwd_native(depth: wp.array(dtype=wp.float32), gt_depth: wp.array(dtype=wp.float32),
                      weight: wp.array(dtype=wp.float32), use_w: int, nhw: int, scale: float,
                      grad: wp.array(dtype=wp.float32)): ...


@wp.kernel
def ssim_fwd_kernel(pred: wp.array(dtype=wp.float32), gt: wp.array(dtype=wp.float32),
                    mu_y: wp.array(dtype=wp.float32), sig_y: wp.array(dtype=wp.float32),
                    win: wp.array(dtype=wp.float32), weight: wp.array(dtype=wp.float32), use_w: int,
                    do_ssim: int, H: int, W: int, c: int, c1: float, c2: float,
                    scratch: wp.array(dtype=wp.float32), deriv: wp.array(dtype=wp.float32),
                    ssum: wp.array(dtype=wp.float64), lsum: wp.array(dtype=wp.float64)):
    """Channel ``c`` of the fused forward: ``lsum[c]`` = Σ over pixels of |pred − gt| and, when ``do_ssim`` != 0,
    ``ssum[c]`` = Σ of SSIM and ``deriv[c]`` its three (H, W) derivative maps (``ssum[c]`` = 0 otherwise), each
    term times ``weight`` (H*W) when ``use_w`` != 0. ``pred``/``gt`` flat (H*W*3) float32 HWC; ``mu_y``/``sig_y``
    (the variance of y) flat (3*H*W) planar; ``win`` (11,) window; ``scratch`` per channel 4 * H*W + W + 16
    floats."""
    _ssim_fwd_native(pred, gt, mu_y, sig_y, win, weight, use_w, do_ssim, H, W, c, c1, c2, scratch, deriv, ssum,
                     lsum)


@wp.kernel
def ssim_bwd_kernel(pred: wp.array(dtype=wp.float32), gt: wp.array(dtype=wp.float32),
                    win: wp.array(dtype=wp.float32), weight: wp.array(dtype=wp.float32), use_w: int,
                    do_ssim: int, H: int, W: int, c: int, scale: float, l1_scale: float,
                    scratch: wp.array(dtype=wp.float32), deriv: wp.array(dtype=wp.float32),
                    grad: wp.array(dtype=wp.float32)):
    """Channel ``c`` of the fused backward: ``grad`` (H*W*3) HWC gets ``scale`` × ∂(Σ SSIM)/∂pred (when
    ``do_ssim`` != 0) + ``l1_scale`` × ∂(Σ |pred − gt|)/∂pred, weighted as the forward."""
    _ssim_bwd_native(pred, gt, win, weight, use_w, do_ssim, H, W, c, scale, l1_scale, scratch, deriv, grad)


@wp.kernel
def depth_l1_fwd_kernel(depth: wp.array(dtype=wp.float32), gt_depth: wp.array(dtype=wp.float32),
                        weight: wp.array(dtype=wp.float32), use_w: int, nhw: int, out: wp.array(dtype=wp.float64)):
    """``out`` (2,) float64 = (Σ |depth − gt_depth|, count) over the HW pixels with gt_depth > 0 (and weight > 0
    when ``use_w`` != 0); flat float32 maps."""
    _depth_fwd_native(depth, gt_depth, weight, use_w, nhw, out)


@wp.kernel
def depth_l1_bwd_kernel(depth: wp.array(dtype=wp.float32), gt_depth: wp.array(dtype=wp.float32),
                        weight: wp.array(dtype=wp.float32), use_w: int, nhw: int, scale: float,
                        grad: wp.array(dtype=wp.float32)):
    """``grad`` (HW,) = ``scale`` × sign(depth − gt_depth) on the pixels :func:`depth_l1_fwd_kernel` sums, 0
    elsewhere."""
    _depth_bwd_native(depth, gt_depth, weight, use_w, nhw, scale, grad)


def _flat(t: torch.Tensor) -> torch.Tensor:
    """``t`` as a flat contiguous float32 tensor without a graph."""
    return t.detach().to(torch.float32).contiguous().reshape(-1)


class _ColourPass:
    """The colour channels' fused forward (SSIM when ``do_ssim``, and L1) and, from what it kept, their gradient."""

    def __init__(self, pred, gt, mu_y, var_y, weight, do_ssim: bool):
        self.H, self.W, self.C = H, W, C = pred.shape
        self.p, self.y = _flat(pred), _flat(gt)
        my, vy = (_flat(mu_y), _flat(var_y)) if do_ssim else (self.y, self.y)
        self.use_w = weight is not None
        self.wt = _flat(weight) if self.use_w else torch.zeros(1)
        self.do_ssim = bool(do_ssim)
        self.scratch = torch.empty(C * (4 * H * W + W + 16), dtype=torch.float32)
        self.deriv = torch.empty(C * 3 * H * W, dtype=torch.float32) if do_ssim else torch.zeros(1)
        self.ssum = torch.zeros(C, dtype=torch.float64)
        self.lsum = torch.zeros(C, dtype=torch.float64)
        #: the sums' divisor: the mean over pixels and channels, or over channels of weighted sums
        self.norm = C if self.use_w else C * H * W
        ensure_module_loaded(__name__, "cpu")
        self.fns = [lambda c=c: launch_cpu(ssim_fwd_kernel, 1, [
            self.p, self.y, my, vy, _WIN, self.wt, int(self.use_w), int(self.do_ssim), H, W, c, SSIM_C1, SSIM_C2,
            self.scratch, self.deriv, self.ssum, self.lsum]) for c in range(C)]

    def grad_fns(self, g_ssim: float, g_l1: float, grad: torch.Tensor) -> list:
        """Callables that write ``g_ssim`` × ∂mean SSIM/∂pred + ``g_l1`` × ∂mean L1/∂pred into ``grad`` (H*W*3)."""
        H, W = self.H, self.W
        return [lambda c=c: launch_cpu(ssim_bwd_kernel, 1, [
            self.p, self.y, _WIN, self.wt, int(self.use_w), int(self.do_ssim), H, W, c, g_ssim / self.norm,
            g_l1 / self.norm, self.scratch, self.deriv, grad]) for c in range(self.C)]


class FusedSSIM(torch.autograd.Function):
    """Mean SSIM of ``pred`` against a fixed ``gt`` (no gradient to gt), CPU float32.

    forward(pred (H, W, 3) float32, gt (H, W, 3), mu_y (1, 3, H, W), var_y (1, 3, H, W)[, weight (H, W)])
    -> 0-dim float32 tensor: ``mean_{p, c} s_pc`` without ``weight``, ``Σ_p weight_p · mean_c s_pc`` with it
    (``weight = mask / |mask|`` is the mean over a pixel mask). ``mu_y``/``var_y`` are
    :func:`gausslite.metrics.ssim_gt_stats` of ``gt``.
    """

    @staticmethod
    def forward(ctx, pred, gt, mu_y, var_y, weight=None):
        ctx.colour = cp = _ColourPass(pred, gt, mu_y, var_y, weight, True)
        run_parallel(cp.fns)
        return (cp.ssum.sum() / cp.norm).to(torch.float32)

    @staticmethod
    def backward(ctx, g_out):
        cp = ctx.colour
        grad = torch.empty(cp.H * cp.W * cp.C, dtype=torch.float32)
        run_parallel(cp.grad_fns(float(g_out), 0.0, grad))
        return grad.reshape(cp.H, cp.W, cp.C), None, None, None, None


class FusedPhotometric(torch.autograd.Function):
    """The three terms of the mapping loss (paper Eq. 1) in one native pass, CPU float32, no gradient to the
    ground truth.

    forward(pred (H, W, 3), depth (H, W), gt (H, W, 3), gt_depth (H, W), mu_y (1, 3, H, W), var_y (1, 3, H, W),
    weight (H, W) or None, with_ssim: bool) -> (l1_colour, l1_depth, ssim), 0-dim float32 tensors:

    - ``l1_colour`` = ``mean |pred − gt|`` over pixels and channels (``Σ_p weight_p · mean_c |…|`` with a weight);
    - ``l1_depth`` = the mean of ``|depth − gt_depth|`` over the pixels with ``gt_depth > 0`` (and ``weight > 0``),
      0 with a zero gradient when there is none; NaN in an invalid pixel stays out;
    - ``ssim`` as :class:`FusedSSIM` when ``with_ssim``, else 1 (not computed; its gradient 0).

    ``weight = mask / |mask|`` restricts every term to a pixel mask. ``mu_y``/``var_y``:
    :func:`gausslite.metrics.ssim_gt_stats` of ``gt`` (unused without SSIM).
    """

    @staticmethod
    def forward(ctx, pred, depth, gt, gt_depth, mu_y, var_y, weight=None, with_ssim=True):
        cp = _ColourPass(pred, gt, mu_y, var_y, weight, with_ssim)
        d, dg = _flat(depth), _flat(gt_depth)
        dsum = torch.zeros(2, dtype=torch.float64)
        HW = cp.H * cp.W

        def colour0_and_depth():
            cp.fns[0]()
            launch_cpu(depth_l1_fwd_kernel, 1, [d, dg, cp.wt, int(cp.use_w), HW, dsum])

        run_parallel([colour0_and_depth] + cp.fns[1:])
        ctx.colour, ctx.depth = cp, (d, dg, float(dsum[1]))
        ctx.depth_shape = tuple(depth.shape)
        l1d = dsum[0] / dsum[1] if float(dsum[1]) > 0 else dsum[0] * 0.0
        s = cp.ssum.sum() / cp.norm if with_ssim else torch.ones((), dtype=torch.float64)
        return tuple(v.to(torch.float32) for v in (cp.lsum.sum() / cp.norm, l1d, s))

    @staticmethod
    def backward(ctx, g_l1, g_l1d, g_ssim):
        cp, (d, dg, n_d) = ctx.colour, ctx.depth
        g_pred = g_depth = None
        fns = []
        if ctx.needs_input_grad[0]:
            g_pred = torch.empty(cp.H * cp.W * cp.C, dtype=torch.float32)
            fns += cp.grad_fns(float(g_ssim) if g_ssim is not None and cp.do_ssim else 0.0,
                               float(g_l1) if g_l1 is not None else 0.0, g_pred)
            g_pred = g_pred.reshape(cp.H, cp.W, cp.C)
        if ctx.needs_input_grad[1]:
            g_depth = torch.empty(cp.H * cp.W, dtype=torch.float32)
            scale = float(g_l1d) / n_d if g_l1d is not None and n_d > 0 else 0.0
            fns.append(lambda: launch_cpu(depth_l1_bwd_kernel, 1, [d, dg, cp.wt, int(cp.use_w), cp.H * cp.W, scale,
                                                                   g_depth]))
        if fns:
            run_parallel(fns)
        if g_depth is not None:
            g_depth = g_depth.reshape(ctx.depth_shape)
        return g_pred, g_depth, None, None, None, None, None, None


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
