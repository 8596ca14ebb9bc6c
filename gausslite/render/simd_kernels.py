"""SIMD CPU compositing kernels: the tile kernels of :mod:`gausslite.render.warp_kernels` with their
inner loops in native C++ (``wp.func_native``) that the compiler vectorises.

Same algorithm and data layout as :func:`~gausslite.render.warp_kernels.rasterize_fwd_tile_kernel` /
:func:`~gausslite.render.warp_kernels.rasterize_bwd_tile_kernel` (Kerbl et al. 2023 front-to-back
compositing; alpha clamped to 0.99, alpha < 1/255 skipped, a pixel stops before T < 1e-4), with three
changes that let clang emit 8-wide AVX2 code:

- **Tile-local SoA state.** Each tile (edge ``tile_size`` <= 16) keeps its pixels' colour sums, alpha,
  transmittance and last index (forward) or gradient and back-to-front state (backward) in 16 x 16
  stack arrays, one array per quantity, written back once per tile.
- **Fixed 8-lane row blocks.** For each (Gaussian, row) the row span of
  :func:`~gausslite.render.warp_kernels_common.row_span` becomes a lane mask over the 8-column halves of the tile
  row it touches, and the per-pixel branches (terminated pixel, footprint pre-test, alpha threshold, termination)
  become selects; every lane of a block runs the same instructions.
- **Polynomial exp.** ``exp(power)`` for ``power`` in ``[p_min, 0]`` is the Cephes ``expf`` polynomial
  (range reduction by ln 2, degree-6 polynomial, exponent bits); within 2 ulp of libm ``expf``, whose
  scalar call would keep the loop from vectorising. The backward pass's per-row sums are vectorised
  with ``#pragma clang fp reassociate(on)``, so they add in another order than the Warp kernel.

Results match the Warp tile kernels to float32 rounding (tests/render/test_render_simd.py: colours and alpha
within 2e-6, gradients within 1e-5 relative) and the pure-PyTorch reference as the Warp kernels do
(tests/render/test_render_rasterizer.py parity tests run through this path). Measured on a room0 map at 300x170,
18k Gaussians, 2 threads: forward 20.1 -> 11.1 ms, backward 25.1 -> 16.0 ms; ``python -m bench.rasterizer``
times both kernel sets on random scenes (forward + backward 1.8-2.2x).
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

# Pieces shared by both snippets (substituted below): the Gaussian's gdata row, its tile rows
# (:func:`~gausslite.render.warp_kernels_common.tile_rows`), the row span as lanes [la, lb] with the row
# offsets (:func:`~gausslite.render.warp_kernels_common.row_span`), and the polynomial exp of ``x``
# (Cephes expf: x = n ln2 + r, e^r by a degree-6 polynomial, 2^n through the exponent bits) as
# ``p * sc.f``.
_LOAD = r"""
    const float uh = r[0], vh = r[1], ca = r[2], cb = r[3], cc = r[4], op = r[5];
    const float f0 = r[6], f1 = r[7], f2 = r[8], f3 = r[9];
    const float ul = r[10], vl = r[11], pm = r[12], ks = r[13], k1 = r[14], k0 = r[15];
    const float uu = uh + ul, vv = vh + vl;
"""
_ROWS = r"""
    float e = sqrtf(k0 / k1) + 0.5f;
    float lo = ceilf(vv - e), hi = floorf(vv + e);
    int ya = y0, yb = y1;
    if (lo > (float)y0) { ya = y1 + 1; if (lo <= (float)y1) ya = (int)lo; }
    if (hi < (float)y1) { yb = y0 - 1; if (hi >= (float)y0) yb = (int)hi; }
"""
_SPAN = r"""
        const float fy = (float)py;
        const float dyr = vv - fy;
        const float cx = uu + ks * dyr;
        const float half2 = k0 - k1 * dyr * dyr;
        int xa = x1 + 1, xb = x1;
        if (half2 >= 0.0f) {
            float hw = sqrtf(half2) + 0.5f;
            float l2 = ceilf(cx - hw), h2 = floorf(cx + hw);
            xa = x0;
            if (l2 > (float)x0) { xa = x1 + 1; if (l2 <= (float)x1) xa = (int)l2; }
            if (h2 < (float)x1) { xb = x0 - 1; if (h2 >= (float)x0) xb = (int)h2; }
        }
        if (xa > xb) continue;
        const int la = xa - x0, lb = xb - x0;
        const float dy = (vh - fy) + vl;
        const int o = (py - y0) * 16;
"""
_EXP = r"""
            const float n = floorf(x * 1.44269504088896341f + 0.5f);
            float rr = x - n * 0.693359375f;
            rr = rr - n * -2.12194440e-4f;
            float p = 1.9875691500E-4f;
            p = p * rr + 1.3981999507E-3f;
            p = p * rr + 8.3334519073E-3f;
            p = p * rr + 4.1665795894E-2f;
            p = p * rr + 1.6666665459E-1f;
            p = p * rr + 5.0000001201E-1f;
            p = p * rr * rr + rr + 1.0f;
            union { int i; float f; } sc;
            sc.i = ((int)n + 127) << 23;
"""


def _fill(snippet: str) -> str:
    for key, code in (("@LOAD@", _LOAD), ("@ROWS@", _ROWS), ("@SPAN@", _SPAN), ("@EXP@", _EXP)):
        snippet = snippet.replace(key + "\n", code.lstrip("\n"))
    return snippet


# forward: one tile, Gaussian-outer, 16-lane rows
_FWD = r"""
const float* gd = (const float*)gdata.data;
const int* ids = (const int*)gids.data;
float* C = (float*)out_c.data;
float* Ag = (float*)out_a.data;
float* Tg = (float*)out_T.data;
int* Lg = (int*)out_last.data;
const int nw = x1 - x0 + 1, nh = y1 - y0 + 1;
float c0[256], c1[256], c2[256], c3[256], A[256], T[256];
int L[256];
for (int k = 0; k < 256; ++k) { c0[k] = 0.0f; c1[k] = 0.0f; c2[k] = 0.0f; c3[k] = 0.0f; A[k] = 0.0f; T[k] = 1.0f; L[k] = start; }
// lanes outside the tile never contribute: mark them terminated
for (int ly = 0; ly < 16; ++ly) for (int lx = 0; lx < 16; ++lx) if (lx >= nw || ly >= nh) T[ly * 16 + lx] = -1.0f;
int n_active = nw * nh;
for (int j = start; j < end; ++j) {
    const float* r = gd + 16 * (long)ids[j];
@LOAD@
    const int jn = j + 1;
@ROWS@
    for (int py = ya; py <= yb; ++py) {
@SPAN@
        float* Tr = T + o; float* Ar = A + o; float* C0 = c0 + o; float* C1 = c1 + o; float* C2 = c2 + o; float* C3 = c3 + o;
        int* Lr = L + o;
        int nterm = 0;
        for (int kb = la & ~7; kb <= lb; kb += 8) {  // the 8-lane halves the span touches
        #pragma clang loop vectorize(enable)
        for (int kk = 0; kk < 8; ++kk) {
            const int k = kb + kk;
            const float Tk = Tr[k];
            const float dx = (uh - (float)(x0 + k)) + ul;
            const float power = -0.5f * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
            const bool in = (k >= la) & (k <= lb) & (Tk >= 0.0f) & (power <= 0.0f) & (power >= pm);
            float x = in ? power : -1.0f;
@EXP@
            float alpha = op * (p * sc.f);
            alpha = 0.99f < alpha ? 0.99f : alpha;
            const bool ok = in & (alpha >= (1.0f / 255.0f));
            const float test_T = Tk * (1.0f - alpha);
            const bool term = ok & (test_T < 1.0e-4f);
            const bool upd = ok & !term;
            const float w = upd ? alpha * Tk : 0.0f;
            C0[k] += w * f0; C1[k] += w * f1; C2[k] += w * f2; C3[k] += w * f3;
            Ar[k] += w;
            Tr[k] = term ? -Tk : (upd ? test_T : Tk);
            Lr[k] = upd ? jn : Lr[k];
            nterm += term ? 1 : 0;
        }
        }
        n_active -= nterm;
    }
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



# backward: one tile, back to front, 16-lane rows
_BWD = r"""
const float* gd = (const float*)gdata.data;
const int* ids = (const int*)gids.data;
const float* GC = (const float*)grad_c.data;
const float* ST = (const float*)state.data;
const int* LI = (const int*)last_idx.data;
float* out = (float*)grad_gdata.data;
const int nw = x1 - x0 + 1, nh = y1 - y0 + 1;
float g0[256], g1[256], g2[256], g3[256], s0[256], s1[256];
int L[256];
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
for (int j = maxlast - 1; j >= start; --j) {
    const int g = ids[j];
    const float* r = gd + 16 * (long)g;
@LOAD@
@ROWS@
    int hit = 0;
    float S0 = 0.0f, SX = 0.0f, SY = 0.0f, SXX = 0.0f, SXY = 0.0f, SYY = 0.0f;
    float F0 = 0.0f, F1 = 0.0f, F2 = 0.0f, F3 = 0.0f;
    for (int py = ya; py <= yb; ++py) {
@SPAN@
        float* S0r = s0 + o; float* S1r = s1 + o;
        const float* G0 = g0 + o; const float* G1 = g1 + o; const float* G2 = g2 + o; const float* G3 = g3 + o;
        const int* Lr = L + o;
        float m0 = 0.0f, mx = 0.0f, mxx = 0.0f, a0 = 0.0f, a1 = 0.0f, a2 = 0.0f, a3 = 0.0f;
        int h = 0;
        for (int kb = la & ~7; kb <= lb; kb += 8) {  // the 8-lane halves the span touches
        #pragma clang fp reassociate(on)
        #pragma clang loop vectorize(enable)
        for (int kk = 0; kk < 8; ++kk) {
            const int k = kb + kk;
            const float dx = (uh - (float)(x0 + k)) + ul;
            const float power = -0.5f * (ca * dx * dx + cc * dy * dy) - cb * dx * dy;
            const bool in = (k >= la) & (k <= lb) & (j < Lr[k]) & (power <= 0.0f) & (power >= pm);
            const float x = in ? power : -1.0f;
@EXP@
            const float raw = op * (p * sc.f);
            const float alpha = 0.99f < raw ? 0.99f : raw;
            const bool ok = in & (alpha >= (1.0f / 255.0f));
            const float inv = 1.0f / (1.0f - alpha);
            const float st0 = S0r[k], st1 = S1r[k];
            const float T = st0 * inv;
            const float w = ok ? alpha * T : 0.0f;
            const float gg0 = G0[k], gg1 = G1[k], gg2 = G2[k], gg3 = G3[k];
            a0 += w * gg0; a1 += w * gg1; a2 += w * gg2; a3 += w * gg3;
            const float fg = f0 * gg0 + f1 * gg1 + f2 * gg2 + f3 * gg3;
            const float dl_dalpha = fg * T + st1 * inv;
            S0r[k] = ok ? T : st0;
            S1r[k] = ok ? st1 - fg * w : st1;
            const float dl_dp = (ok & (raw <= 0.99f)) ? alpha * dl_dalpha : 0.0f;
            m0 += dl_dp;
            const float t = dl_dp * dx;
            mx += t;
            mxx += t * dx;
            h |= ok ? 1 : 0;
        }
        }
        hit |= h;
        S0 += m0; SX += mx; SY += m0 * dy; SXX += mxx; SXY += mx * dy; SYY += m0 * dy * dy;
        F0 += a0; F1 += a1; F2 += a2; F3 += a3;
    }
    if (hit) {
        float* o = out + 10 * (long)g;
        o[0] += -(ca * SX + cb * SY);
        o[1] += -(cc * SY + cb * SX);
        o[2] += -0.5f * SXX;
        o[3] += -SXY;
        o[4] += -0.5f * SYY;
        o[5] += S0 / op;
        o[6] += F0; o[7] += F1; o[8] += F2; o[9] += F3;
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
