"""Native CPU loops for the compositing pass's per-Gaussian rows: packing the projected Gaussians into the
16-column ``gdata`` rows the tile kernels read, and unpacking the backward pass's per-stripe gradient buffers.

Same arithmetic and output, bit for bit, as the Warp kernels :func:`~gausslite.render.warp_kernels.pack_gdata_kernel`
and :func:`~gausslite.render.warp_kernels.unpack_grads_kernel`, which stay their references
(tests/render/test_render_simd.py): every value in float64 (or the input dtype where the Warp kernel uses it) with
the same libm ``exp`` and ``log``, products and sums as separate roundings (no FMA contraction). The Warp kernels run
one launch thread per row with generic 2-D array indexing; here one thread loops over :data:`CHUNK` rows (on the
mapper's keyframe case the two took 0.64 and 0.47 ms per iteration).
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

#: rows per launch thread
CHUNK = 4096

_PACK = r"""
#pragma clang fp contract(off)
float* G = (float*)gdata;
auto body = [&](auto zero) {
    using T = decltype(zero);
    const T* M2 = (const T*)means2d;
    const T* CO = (const T*)conics;
    const T* OP = (const T*)opacities;
    const T* CL = (const T*)colors;
    const T* DP = (const T*)depths;
    for (long i = start; i < end; ++i) {
        const double u = (double)M2[2 * i], v = (double)M2[2 * i + 1];
        const float uh = (float)u, vh = (float)v;
        const double a = (double)CO[3 * i], b = (double)CO[3 * i + 1], c = (double)CO[3 * i + 2];
        double o = (double)OP[i];
        if (logit != 0) o = 1.0 / (1.0 + exp(-o));
        const double p_min = -log(255.0 * (o > 1e-30 ? o : 1e-30)) - 1e-3;
        float* g = G + 16 * i;
        g[0] = uh; g[1] = vh;
        g[2] = (float)a; g[3] = (float)b; g[4] = (float)c; g[5] = (float)o;
        g[6] = (float)CL[3 * i]; g[7] = (float)CL[3 * i + 1]; g[8] = (float)CL[3 * i + 2];
        g[9] = (float)DP[i];
        g[10] = (float)(u - (double)uh); g[11] = (float)(v - (double)vh);
        g[12] = (float)p_min;
        const double det = a * c - b * b;
        double ks = 0.0, k1 = 0.0, k0 = 1e38;
        if (a > 0.0 && det > 0.0 && __builtin_isfinite(det)) {
            ks = b / a;
            k1 = det / (a * a);
            k0 = -2.0 * (p_min - 0.01) / a;
        }
        g[13] = (float)ks; g[14] = (float)k1; g[15] = (float)k0;
    }
};
if (is64) body(0.0); else body(0.0f);
"""

_UNPACK = r"""
#pragma clang fp contract(off)
const float* B = (const float*)bufs;
auto body = [&](auto zero) {
    using T = decltype(zero);
    const T* OP = (const T*)opacities;
    T* GM = (T*)g_means2d;
    T* GC = (T*)g_conics;
    T* GO = (T*)g_opacities;
    T* GL = (T*)g_colors;
    T* GD = (T*)g_depths;
    for (long i = start; i < end; ++i) {
        float acc[10];
        for (int k = 0; k < 10; ++k) acc[k] = 0.0f;
        for (int s = 0; s < nbufs; ++s) {
            const float* r = B + ((long)s * count + i) * 10;
            for (int k = 0; k < 10; ++k) acc[k] += r[k];
        }
        GM[2 * i] = (T)acc[0]; GM[2 * i + 1] = (T)acc[1];
        GC[3 * i] = (T)acc[2]; GC[3 * i + 1] = (T)acc[3]; GC[3 * i + 2] = (T)acc[4];
        double go = (double)acc[5];
        if (logit != 0) {
            const double o = 1.0 / (1.0 + exp(-(double)OP[i]));
            go = go * o * (1.0 - o);
        }
        GO[i] = (T)go;
        GL[3 * i] = (T)acc[6]; GL[3 * i + 1] = (T)acc[7]; GL[3 * i + 2] = (T)acc[8];
        GD[i] = (T)acc[9];
    }
};
if (is64) body(0.0); else body(0.0f);
"""


@wp.func_native(_PACK)
def _pack_native(means2d: wp.uint64, conics: wp.uint64, opacities: wp.uint64, colors: wp.uint64, depths: wp.uint64,
                 is64: int, logit: int, start: int, end: int, gdata: wp.uint64): ...


@wp.func_native(_UNPACK)
def _unpack_native(bufs: wp.uint64, nbufs: int, count: int, opacities: wp.uint64, is64: int, logit: int, start: int,
                   end: int, g_means2d: wp.uint64, g_conics: wp.uint64, g_opacities: wp.uint64, g_colors: wp.uint64,
                   g_depths: wp.uint64): ...


@wp.kernel
def pack_gdata_native_kernel(means2d: wp.uint64, conics: wp.uint64, opacities: wp.uint64, colors: wp.uint64,
                             depths: wp.uint64, is64: int, logit: int, count: int, gdata: wp.uint64):
    """:func:`~gausslite.render.warp_kernels.pack_gdata_kernel` on pointers to C-contiguous arrays of ``count`` rows,
    :data:`CHUNK` rows per thread: ``means2d`` (count, 2), ``conics`` (count, 3), ``opacities`` (count,) (logits when
    ``logit`` != 0), ``colors`` (count, 3), ``depths`` (count,), all float64 if ``is64`` else float32; ``gdata``
    (count, 16) float32."""
    s = wp.tid() * CHUNK
    _pack_native(means2d, conics, opacities, colors, depths, is64, logit, s, wp.min(s + CHUNK, count), gdata)


@wp.kernel
def unpack_grads_native_kernel(bufs: wp.uint64, nbufs: int, count: int, opacities: wp.uint64, is64: int, logit: int,
                               g_means2d: wp.uint64, g_conics: wp.uint64, g_opacities: wp.uint64,
                               g_colors: wp.uint64, g_depths: wp.uint64):
    """:func:`~gausslite.render.warp_kernels.unpack_grads_kernel` on pointers to C-contiguous arrays, :data:`CHUNK` rows
    per thread: ``bufs`` (nbufs, count, 10) float32, ``opacities`` (count,) and the gradients of means2d (count, 2),
    conics (count, 3), opacities (count,), colors (count, 3) and depths (count,), float64 if ``is64`` else
    float32."""
    s = wp.tid() * CHUNK
    _unpack_native(bufs, nbufs, count, opacities, is64, logit, s, wp.min(s + CHUNK, count), g_means2d, g_conics,
                   g_opacities, g_colors, g_depths)


__all__ = ["CHUNK", "pack_gdata_native_kernel", "unpack_grads_native_kernel"]
