"""SIMD CPU compositing kernels: the tile kernels of :mod:`gausslite.render.warp_kernels` with their
inner loops in native C++ (``wp.func_native``) written with clang vector types.

Same algorithm and data layout as :func:`~gausslite.render.warp_kernels.rasterize_fwd_tile_kernel` /
:func:`~gausslite.render.warp_kernels.rasterize_bwd_tile_kernel` (Kerbl et al. 2023 front-to-back
compositing; alpha clamped to 0.99, alpha < 1/255 skipped, a pixel stops before T < 1e-4), organised for SIMD:

- **Tile-local SoA state.** Each tile (edge ``tile_size`` <= 16) keeps its pixels' colour sums, alpha,
  transmittance and last index (forward) or gradient and back-to-front state (backward) in 16 x 16
  stack arrays, one array per quantity, written back once per tile.
- **Column box instead of per-row spans.** Per Gaussian the columns it can reach in the tile are bounded once
  (the box around all the row spans of :func:`~gausslite.render.warp_kernels_common.row_span`, see ``_BOX``); if
  they lie in one 8-column half of the tile its rows are processed as 8-lane vectors, else as whole 16-lane rows
  (one AVX-512 register, two AVX2 ones). Each row costs only its offset ``dy``: no per-row square root, rounding
  or span branches, and the row-independent column terms of ``power`` (``dx``, ``ca dx^2``, ``cb dx``) are
  computed once per Gaussian. The per-pixel branches (terminated pixel, footprint test ``power`` in
  ``[p_min, 0]``, alpha threshold, termination) are lane masks and selects. The lane test alone decides which
  pixels composite (the box holds every pixel with ``power >= p_min``), so the result is the per-row spans'.
- **Column sums in the backward pass.** The sums over a Gaussian's pixels (dL/dpower times 1, dx, dx^2, dy,
  dx dy, dy^2 and the colour gradients) are kept per lane across the rows -- as sums of dL/dpower times 1, dy,
  dy^2 per column, since ``dx`` is the column's -- and reduced horizontally once per Gaussian instead of once
  per row. Per-row termination counts of the forward pass likewise.
- **Polynomial exp, FMA.** ``exp(power)`` for ``power`` in ``[p_min, 0]`` is the Cephes ``expf`` polynomial
  (range reduction by ln 2, degree-6 polynomial, exponent bits); within 2 ulp of libm ``expf``. The snippets
  are compiled with ``#pragma clang fp contract(fast)`` (without it the loops had no FMA at all), so
  products and sums fuse into FMAs; together with the summation order this moves results at float32 rounding.

The vector types (``ext_vector_type``) compile for whatever the host has (Warp builds with ``-march=native``):
AVX-512 here, two halves per 16-lane vector on AVX2, SSE on a bare x86-64 (the parity tests pass with the module
built for each of these).

Results match the Warp tile kernels to float32 rounding (tests/render/test_render_simd.py: colours and alpha
within 2e-6, gradients within 1e-5 relative) and the pure-PyTorch reference as the Warp kernels do
(tests/render/test_render_rasterizer.py parity tests run through this path).

Measured (kernels alone, one thread, one stripe; a 20k-Gaussian map of the synthetic circle scene built by
``bench.throughput``'s case builder, 320x240, 3 keyframe views; AMD EPYC (Zen 4, AVX-512) VM with 2 shared
cores), previous kernels (8-lane blocks per row span, per-row reductions, no FMA) -> these:
forward 161 -> 80 ms per view (median of 21 interleaved runs; minimum 145 -> 72), backward 311 -> 123 ms
(minimum 282 -> 105): 2.0x and 2.5x. The absolute times are inflated about 3x by other jobs on the shared cores
(unloaded, the previous kernels took 46 and 94 ms); the ratios come from old and new runs alternating in one
process. Instructions executed (callgrind, one view; under valgrind Warp builds for the CPU valgrind reports,
without AVX-512): forward 361.7 -> 209.8 million, backward 495.4 -> 267.6 million. Against the Warp tile
kernels on the parity-test scenes: colours and alpha within 2e-7, depth 8e-7, gradients within 4e-7 relative.
CPU only; the CUDA path keeps the per-pixel kernels of :mod:`~gausslite.render.warp_kernels`.
"""

from __future__ import annotations

import warp as wp

from .warp_kernels_bwd import bwd_tile_init
from .warp_kernels_common import tile_box

wp.set_module_options({"enable_backward": False})

#: widest tile the SIMD kernels handle (lanes per row); wider tiles use the Warp tile kernels
MAX_TILE = 16
#: CPU compositing kernel choices: these SIMD kernels, or the Warp tile kernels
CPU_KERNELS = ("simd", "tile")


def check_cpu_kernel(cpu_kernel: str) -> None:
    """Raise ValueError unless ``cpu_kernel`` is one of :data:`CPU_KERNELS`."""
    if cpu_kernel not in CPU_KERNELS:
        raise ValueError(f"cpu_kernel must be one of {CPU_KERNELS}, got {cpu_kernel!r}")

# Pieces shared by both snippets (substituted below). ``@HEAD@``: FMA contraction, the vector types (clang
# ``ext_vector_type``: 8 or 16 float / int lanes, compiled to whatever the host has -- AVX-512, AVX2 or SSE) and
# the horizontal sums. ``@LOAD@``: the Gaussian's gdata row. ``@ROWS@``: its tile rows ``[ya, yb]``
# (:func:`~gausslite.render.warp_kernels_common.tile_rows`), or ``continue`` if none. ``@BOX@``: the 8-lane
# halves ``[ba, bb]`` of the tile row that its column box (below) touches, or ``continue`` if no pixel of the
# tile can be reached, and the row-independent column terms of ``power`` (``dx``, ``ca dx^2``, ``cb dx``) for
# the half ``ba`` (8 lanes) and the whole row (16 lanes). ``@ROW@``: the row offset ``dy``, the row's term
# ``cc dy^2`` and the row's offset in the tile arrays. ``@EXP@``: ``e = exp(x)`` by the polynomial (Cephes expf:
# x = n ln2 + r, e^r by a degree-6 polynomial, 2^n through the exponent bits) for the lanes' ``x`` (vector type
# ``VF``, its mask type ``VI``).
#
# The column box: on the row at offset dy the reachable columns are within sqrt(k0 - k1 dy^2) + 0.5 px of
# u + ks dy (:func:`~gausslite.render.warp_kernels_common.row_span`); over all dy (Cauchy-Schwarz) that is within
# sqrt(k0 (1 + ks^2 / k1)) + 0.5 px of u, widened here by 1e-5 relative + 0.01 px for float rounding. Every pixel
# with power >= p_min lies inside it, and the lane tests (power in [p_min, 0]) decide which pixels of the box
# composite, so the box stands in for the per-row spans with the same result. k1 <= 0 (no positive-definite
# conic in float32) leaves the whole tile width; k0 < 0 (opacity below 1/255) reaches no pixel.
_HEAD = r"""
#pragma clang fp contract(fast)
typedef float v8f __attribute__((ext_vector_type(8)));
typedef float v4f __attribute__((ext_vector_type(4)));
typedef float v2f __attribute__((ext_vector_type(2)));
typedef int v8i __attribute__((ext_vector_type(8)));
typedef float v16f __attribute__((ext_vector_type(16)));
typedef int v16i __attribute__((ext_vector_type(16)));
auto hsum = [](const v8f v) -> float { const v4f a = v.lo + v.hi; const v2f b = a.lo + a.hi; return b.x + b.y; };
auto hsum16 = [&](const v16f v) -> float { return hsum(v.lo + v.hi); };
const v16f lane = {0.0f, 1.0f, 2.0f, 3.0f, 4.0f, 5.0f, 6.0f, 7.0f, 8.0f, 9.0f, 10.0f, 11.0f, 12.0f, 13.0f, 14.0f, 15.0f};
"""
_LOAD = r"""
    const float uh = r[0], vh = r[1], ca = r[2], cb = r[3], cc = r[4], op = r[5];
    const float f0 = r[6], f1 = r[7], f2 = r[8], f3 = r[9];
    const float ul = r[10], vl = r[11], pm = r[12], ks = r[13], k1 = r[14], k0 = r[15];
    const float uu = uh + ul, vv = vh + vl;
"""
_ROWS = r"""
    const float ey = sqrtf(k0 / k1) + 0.5f;
    const float lo = ceilf(vv - ey), hi = floorf(vv + ey);
    int ya = y0, yb = y1;
    if (lo > (float)y0) { ya = y1 + 1; if (lo <= (float)y1) ya = (int)lo; }
    if (hi < (float)y1) { yb = y0 - 1; if (hi >= (float)y0) yb = (int)hi; }
    if (ya > yb) continue;
"""
_BOX = r"""
    int xa = x0, xb = x1;
    if (k1 > 0.0f) {
        const float E = sqrtf(k0 + k0 * ks * ks / k1) * 1.00001f + 0.51f;
        if (!(E >= 0.0f)) continue;
        const float l2 = ceilf(uu - E), h2 = floorf(uu + E);
        if (l2 > (float)x0) { xa = x1 + 1; if (l2 <= (float)x1) xa = (int)l2; }
        if (h2 < (float)x1) { xb = x0 - 1; if (h2 >= (float)x0) xb = (int)h2; }
        if (xa > xb) continue;
    }
    const int ba = (xa - x0) >> 3, bb = (xb - x0) >> 3;
    // per-block column terms of power (row independent): dx, ca dx^2, cb dx
    const v8f dxa = (uh - (colf.lo + (float)(8 * ba))) + ul;
    const v16f dx2 = (uh - colf) + ul;
    const v8f Pa = ca * dxa * dxa, Qa = cb * dxa;
    const v16f P2 = ca * dx2 * dx2, Q2 = cb * dx2;
"""
_ROW = r"""
        const float fy = (float)py;
        const float dy = (vh - fy) + vl;
        const float cdy = cc * dy * dy;
        const int o = (py - y0) * 16;
"""
_EXP = r"""
        const VF n = __builtin_elementwise_floor(x * 1.44269504088896341f + 0.5f);
        VF rr = x - n * 0.693359375f;
        rr = rr - n * -2.12194440e-4f;
        VF p = 1.9875691500E-4f;
        p = p * rr + 1.3981999507E-3f;
        p = p * rr + 8.3334519073E-3f;
        p = p * rr + 4.1665795894E-2f;
        p = p * rr + 1.6666665459E-1f;
        p = p * rr + 5.0000001201E-1f;
        p = p * rr * rr + rr + 1.0f;
        const VF e = p * __builtin_bit_cast(VF, (__builtin_convertvector(n, VI) + 127) << 23);
"""


def _fill(snippet: str) -> str:
    for key, code in (("@HEAD@", _HEAD), ("@LOAD@", _LOAD), ("@ROWS@", _ROWS), ("@BOX@", _BOX),
                      ("@ROW@", _ROW), ("@EXP@", _EXP)):
        snippet = snippet.replace(key + "\n", code.lstrip("\n"))
    return snippet


# forward: one tile, Gaussian-outer, the rows of each Gaussian's column box as 8- or 16-lane vectors
_FWD = r"""
@HEAD@
const float* gd = (const float*)gdata.data;
const int* ids = (const int*)gids.data;
float* C = (float*)out_c.data;
float* Ag = (float*)out_a.data;
float* Tg = (float*)out_T.data;
int* Lg = (int*)out_last.data;
const int nw = x1 - x0 + 1, nh = y1 - y0 + 1;
alignas(64) float c0[256], c1[256], c2[256], c3[256], A[256], T[256];
alignas(64) int L[256];
for (int k = 0; k < 256; ++k) { c0[k] = 0.0f; c1[k] = 0.0f; c2[k] = 0.0f; c3[k] = 0.0f; A[k] = 0.0f; T[k] = 1.0f; L[k] = start; }
// lanes outside the tile never contribute: mark them terminated
for (int ly = 0; ly < 16; ++ly) for (int lx = 0; lx < 16; ++lx) if (lx >= nw || ly >= nh) T[ly * 16 + lx] = -1.0f;
const v16f colf = (float)x0 + lane;
int n_active = nw * nh;
for (int j = start; j < end; ++j) {
    const float* r = gd + 16 * (long)ids[j];
@LOAD@
    const int jn = j + 1;
@ROWS@
@BOX@
    int nterm = 0;
    // the lanes at k (VF: 8 or 16 of them): the pixel tests become lane masks, the updates selects
    auto block = [&](const int k, const auto P, const auto Q, const float dy, const float cdy, auto& nt) {
        using VF = decltype(P + 0.0f);
        using VI = decltype(P < 0.0f);
        const VF Tk = *(const VF*)(T + k);
        const VF power = -0.5f * (P + cdy) - Q * dy;
        const VI in = (Tk >= 0.0f) & (power <= 0.0f) & (power >= pm);
        const VF x = in ? power : (VF)(-1.0f);
@EXP@
        VF alpha = op * e;
        alpha = 0.99f < alpha ? (VF)(0.99f) : alpha;
        const VI ok = in & (alpha >= (1.0f / 255.0f));
        const VF test_T = Tk * (1.0f - alpha);
        const VI term = ok & (test_T < 1.0e-4f);
        const VI upd = ok & ~term;
        const VF w = upd ? alpha * Tk : (VF)(0.0f);
        *(VF*)(c0 + k) += w * f0; *(VF*)(c1 + k) += w * f1; *(VF*)(c2 + k) += w * f2; *(VF*)(c3 + k) += w * f3;
        *(VF*)(A + k) += w;
        *(VF*)(T + k) = term ? -Tk : (upd ? test_T : Tk);
        VI* Lk = (VI*)(L + k);
        *Lk = upd ? (VI)jn : *Lk;
        nt += term;  // -1 per terminated lane
    };
    if (ba == bb) {  // one 8-lane half of the tile row
        v8i nt = 0;
        for (int py = ya; py <= yb; ++py) {
@ROW@
            block(o + 8 * ba, Pa, Qa, dy, cdy, nt);
        }
        nterm = __builtin_reduce_add(nt);
    } else {  // the whole 16-lane row
        v16i nt = 0;
        for (int py = ya; py <= yb; ++py) {
@ROW@
            block(o, P2, Q2, dy, cdy, nt);
        }
        nterm = __builtin_reduce_add(nt);
    }
    n_active += nterm;
    if (n_active == 0) break;
}
for (int ly = 0; ly < nh; ++ly) {
    for (int lx = 0; lx < nw; ++lx) {
        const int k = ly * 16 + lx;
        const int pix = (y0 + ly) * width + x0 + lx;
        float Tk = T[k]; Tg[pix] = Tk < 0.0f ? -Tk : Tk;
        Lg[pix] = L[k];
        const float Ak = A[k];
        Ag[pix] = Ak;
        float* c = C + 4 * pix;
        if (composite != 0) {
            const float t = 1.0f - Ak;
            float depth = 0.0f;
            if (Ak >= 1.0e-6f) depth = c3[k] / Ak;
            c[0] = c0[k] + t * bgr; c[1] = c1[k] + t * bgg; c[2] = c2[k] + t * bgb; c[3] = depth;
        } else {
            c[0] = c0[k]; c[1] = c1[k]; c[2] = c2[k]; c[3] = c3[k];
        }
    }
}
"""



# backward: one tile, back to front, the rows of each Gaussian's column box as 8- or 16-lane vectors; the sums
# over the pixels are kept per lane (per column) across the rows and reduced once per Gaussian
_BWD = r"""
@HEAD@
const float* gd = (const float*)gdata.data;
const int* ids = (const int*)gids.data;
const float* GC = (const float*)grad_c.data;
const float* ST = (const float*)state.data;
const int* LI = (const int*)last_idx.data;
float* out = (float*)grad_gdata.data;
const int nw = x1 - x0 + 1, nh = y1 - y0 + 1;
alignas(64) float g0[256], g1[256], g2[256], g3[256], s0[256], s1[256];
alignas(64) int L[256];
for (int k = 0; k < 256; ++k) { g0[k] = 0.0f; g1[k] = 0.0f; g2[k] = 0.0f; g3[k] = 0.0f; s0[k] = 1.0f; s1[k] = 0.0f; L[k] = -1; }
for (int ly = 0; ly < nh; ++ly) {
    for (int lx = 0; lx < nw; ++lx) {
        const int k = ly * 16 + lx;
        const int pix = (y0 + ly) * width + x0 + lx;
        g0[k] = GC[4 * pix]; g1[k] = GC[4 * pix + 1]; g2[k] = GC[4 * pix + 2]; g3[k] = GC[4 * pix + 3];
        s0[k] = ST[2 * pix]; s1[k] = ST[2 * pix + 1];
        L[k] = LI[pix];
    }
}
const v16f colf = (float)x0 + lane;
for (int j = maxlast - 1; j >= start; --j) {
    const int g = ids[j];
    const float* r = gd + 16 * (long)g;
@LOAD@
@ROWS@
@BOX@
    // the lanes at k (VF: 8 or 16 of them); per lane (column) across the rows: M0, MY, MYY the sums of dL/dpower
    // times 1, dy, dy^2, F0..F3 of w * grad
    auto block = [&](const int k, const auto P, const auto Q, const float dy, const float cdy, auto& M0, auto& MY,
                     auto& MYY, auto& F0, auto& F1, auto& F2, auto& F3, auto& hit) {
        using VF = decltype(P + 0.0f);
        using VI = decltype(P < 0.0f);
        const VF power = -0.5f * (P + cdy) - Q * dy;
        const VI in = (j < *(const VI*)(L + k)) & (power <= 0.0f) & (power >= pm);
        const VF x = in ? power : (VF)(-1.0f);
@EXP@
        const VF raw = op * e;
        const VF alpha = 0.99f < raw ? (VF)(0.99f) : raw;
        const VI ok = in & (alpha >= (1.0f / 255.0f));
        const VF inv = 1.0f / (1.0f - alpha);
        VF* S0k = (VF*)(s0 + k); VF* S1k = (VF*)(s1 + k);
        const VF st0 = *S0k, st1 = *S1k;
        const VF Tt = st0 * inv;
        const VF w = ok ? alpha * Tt : (VF)(0.0f);
        const VF gg0 = *(const VF*)(g0 + k), gg1 = *(const VF*)(g1 + k);
        const VF gg2 = *(const VF*)(g2 + k), gg3 = *(const VF*)(g3 + k);
        F0 += w * gg0; F1 += w * gg1; F2 += w * gg2; F3 += w * gg3;
        const VF fg = f0 * gg0 + f1 * gg1 + f2 * gg2 + f3 * gg3;
        const VF dl_dalpha = fg * Tt + st1 * inv;
        *S0k = ok ? Tt : st0;
        *S1k = ok ? st1 - fg * w : st1;
        const VF dl_dp = (ok & (raw <= 0.99f)) ? alpha * dl_dalpha : (VF)(0.0f);
        M0 += dl_dp;
        const VF t = dl_dp * dy;
        MY += t;
        MYY += t * dy;
        hit |= ok;
    };
    // sums over the pixels: dx is the column's, so sum dL/dpower dx^m dy^n = sum over columns of dx^m (column sum)
    float S0, SX, SXX, SY, SXY, SYY, G0, G1, G2, G3;
    if (ba == bb) {  // one 8-lane half of the tile row
        v8f M0 = 0.0f, MY = 0.0f, MYY = 0.0f, F0 = 0.0f, F1 = 0.0f, F2 = 0.0f, F3 = 0.0f;
        v8i hit = 0;
        for (int py = ya; py <= yb; ++py) {
@ROW@
            block(o + 8 * ba, Pa, Qa, dy, cdy, M0, MY, MYY, F0, F1, F2, F3, hit);
        }
        if (!__builtin_reduce_or(hit)) continue;
        S0 = hsum(M0); SX = hsum(M0 * dxa); SXX = hsum(M0 * dxa * dxa);
        SY = hsum(MY); SXY = hsum(MY * dxa); SYY = hsum(MYY);
        G0 = hsum(F0); G1 = hsum(F1); G2 = hsum(F2); G3 = hsum(F3);
    } else {  // the whole 16-lane row
        v16f M0 = 0.0f, MY = 0.0f, MYY = 0.0f, F0 = 0.0f, F1 = 0.0f, F2 = 0.0f, F3 = 0.0f;
        v16i hit = 0;
        for (int py = ya; py <= yb; ++py) {
@ROW@
            block(o, P2, Q2, dy, cdy, M0, MY, MYY, F0, F1, F2, F3, hit);
        }
        if (!__builtin_reduce_or(hit)) continue;
        S0 = hsum16(M0); SX = hsum16(M0 * dx2); SXX = hsum16(M0 * dx2 * dx2);
        SY = hsum16(MY); SXY = hsum16(MY * dx2); SYY = hsum16(MYY);
        G0 = hsum16(F0); G1 = hsum16(F1); G2 = hsum16(F2); G3 = hsum16(F3);
    }
    {
        float* o = out + 10 * (long)g;
        o[0] += -(ca * SX + cb * SY);
        o[1] += -(cc * SY + cb * SX);
        o[2] += -0.5f * SXX;
        o[3] += -SXY;
        o[4] += -0.5f * SYY;
        o[5] += S0 / op;
        o[6] += G0; o[7] += G1; o[8] += G2; o[9] += G3;
    }
}
"""



@wp.func_native(_fill(_FWD))
def _fwd_tile_native(gdata: wp.array2d(dtype=wp.float32), gids: wp.array(dtype=wp.int32), start: int, end: int,
                     x0: int, y0: int, x1: int, y1: int, width: int, composite: int, bgr: float, bgg: float,
                     bgb: float, out_c: wp.array(dtype=wp.vec4), out_a: wp.array(dtype=wp.float32),
                     out_T: wp.array(dtype=wp.float32), out_last: wp.array(dtype=wp.int32)): ...


@wp.func_native(_fill(_BWD))
def _bwd_tile_native(gdata: wp.array2d(dtype=wp.float32), gids: wp.array(dtype=wp.int32), start: int,
                     maxlast: int, x0: int, y0: int, x1: int, y1: int, width: int,
                     last_idx: wp.array(dtype=wp.int32), grad_c: wp.array(dtype=wp.vec4),
                     state: wp.array(dtype=wp.vec2), grad_gdata: wp.array2d(dtype=wp.float32)): ...


# The kernels below are the Warp tile kernels' wrappers with the native tile function in place of
# ``_fwd_tile_warp`` / ``_bwd_tile_warp`` (same arguments); why the parameter lists and inner loops are
# not one source: docs/architecture.md, "Kernel sources".
@wp.kernel
def rasterize_fwd_tile_simd_kernel(
    gdata: wp.array2d(dtype=wp.float32),
    gids: wp.array(dtype=wp.int32),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    stripe: int,
    nstripes: int,
    composite: int,
    bg: wp.vec3,
    out_c: wp.array(dtype=wp.vec4),
    out_a: wp.array(dtype=wp.float32),
    out_T: wp.array(dtype=wp.float32),
    out_last: wp.array(dtype=wp.int32),
):
    """Forward pass of one tile: the arguments and outputs of
    :func:`gausslite.render.warp_kernels.rasterize_fwd_tile_kernel` (``tile_size`` <= :data:`MAX_TILE`;
    all arrays contiguous). ``gdata`` (M, 16) float32 rows, ``out_c`` (H*W,) vec4 (R, G, B, Σ w z) or the
    finished (colour over ``bg``, depth) with ``composite`` != 0, ``out_a`` / ``out_T`` (H*W,) float32
    alpha and final transmittance, ``out_last`` (H*W,) int32 one past the last contributing entry."""
    box = tile_box(wp.tid(), tiles_x, stripe, nstripes, tile_size, width, height)
    tile = box[0]
    x0 = box[1]
    y0 = box[2]
    x1 = box[3]
    y1 = box[4]
    _fwd_tile_native(gdata, gids, tile_start[tile], tile_end[tile], x0, y0, x1, y1, width, composite,
                     bg[0], bg[1], bg[2], out_c, out_a, out_T, out_last)


@wp.kernel
def rasterize_bwd_tile_simd_kernel(
    gdata: wp.array2d(dtype=wp.float32),
    gids: wp.array(dtype=wp.int32),
    tile_start: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    stripe: int,
    nstripes: int,
    final_T: wp.array(dtype=wp.float32),
    last_idx: wp.array(dtype=wp.int32),
    composite: int,
    bg: wp.vec3,
    out_c: wp.array(dtype=wp.vec4),
    out_a: wp.array(dtype=wp.float32),
    g_color: wp.array2d(dtype=wp.float32),
    g_depth: wp.array(dtype=wp.float32),
    g_alpha: wp.array(dtype=wp.float32),
    grad_c: wp.array(dtype=wp.vec4),
    state: wp.array(dtype=wp.vec2),
    grad_gdata: wp.array2d(dtype=wp.float32),
):
    """Backward pass of one tile: the arguments of
    :func:`gausslite.render.warp_kernels.rasterize_bwd_tile_kernel` (``tile_size`` <= :data:`MAX_TILE`;
    ``grad_c``, ``state``, ``last_idx``, ``gdata`` and ``grad_gdata`` contiguous). The per-pixel
    initialisation is the Warp kernel's; the back-to-front loop is native. ``grad_gdata`` (M, 10) float32
    is this launch's own buffer (no other launch writes it concurrently), so it is updated with plain adds."""
    box = tile_box(wp.tid(), tiles_x, stripe, nstripes, tile_size, width, height)
    tile = box[0]
    x0 = box[1]
    y0 = box[2]
    x1 = box[3]
    y1 = box[4]
    start = tile_start[tile]
    maxlast = bwd_tile_init(x0, y0, x1, y1, width, start, final_T, last_idx, composite, bg, out_c, out_a,
                            g_color, g_depth, g_alpha, grad_c, state)
    _bwd_tile_native(gdata, gids, start, maxlast, x0, y0, x1, y1, width, last_idx, grad_c, state, grad_gdata)
