"""Warp kernels of the Gaussian rasterizer: tile-based compositing (forward and backward), plus
the CPU-side EWA projection (forward and backward), tile binning and gradient (un)packing.

Port of the per-pixel loops of Kerbl et al. 2023 (diff-gaussian-rasterization ``renderCUDA`` /
``renderCUDA`` backward) in the gsplat data layout, written without Warp tile primitives so the
same source runs correctly on CPU (one thread per pixel, serial per launch) and CUDA.

Per-Gaussian data is packed into one float32 row (64 bytes)
``gdata[g] = (u_hi, v_hi, a, b, c, o, r, g, b, z, u_lo, v_lo, p_min, ks, k1, k0)``
(filled by :func:`pack_gdata_kernel`):
- pixel centre (u, v) stored as a float32 pair ``u = u_hi + u_lo`` (``u_hi - px`` is exact, so
  the pixel offset keeps ~float64 precision at no cost; plain float32 u would carry ~1e-5 px
  rounding at u ~ 300);
- conic (a, b, c) with Mahalanobis form ``a dx^2 + 2 b dx dy + c dy^2`` (px^-2);
- post-sigmoid opacity o, colour rgb, camera depth z (metres);
- ``p_min = ln(1 / (255 o)) - 1e-3``: a conservative pre-test (power < p_min implies
  alpha < 1/255) that skips the exp for pairs far outside the footprint; the exact
  ``alpha < 1/255`` test still decides the remaining pairs, so semantics are unchanged.
- ``(ks, k1, k0)``: row-span coefficients of the CPU tile kernels (see ``pack_gdata_kernel``).
Gradients are written to (M, 10) buffers holding the first ten columns of that layout.

The footprint test of each (pixel, Gaussian) pair reads a per-intersection copy
``idata[j] = (u_hi, v_hi, a, b, c, u_lo, v_lo, p_min)`` stored in the sorted tile order, so the
inner loop streams through contiguous memory; ``gdata[gids[j]]`` is only read for pairs that
pass the test.

On CPU, :func:`rasterize_fwd_tile_kernel` / :func:`rasterize_bwd_tile_kernel` (one tile per
thread, Gaussian-outer) replace the per-pixel kernels below; those remain the CUDA path. The CPU
tile kernels keep colour + depth sum as one ``vec4`` per pixel (and can finish the image: background
compositing and depth normalisation), and their backward keeps two floats of running state per
pixel (see :func:`rasterize_bwd_tile_kernel`). :func:`pack_gdata_kernel` can apply the opacity
sigmoid and :func:`unpack_grads_kernel` sums the per-thread gradient buffers (and applies the
sigmoid derivative), so that no per-element torch op remains around the CPU launches.

:func:`project_fwd_kernel` / :func:`project_bwd_kernel` (CPU path of
:class:`gausslite.render.autograd.ProjectWarp`) and :func:`bin_count_kernel` /
:func:`bin_scatter_kernel` (CPU path of :func:`gausslite.render.binning.bin_gaussians`) replace
the vectorised torch code of those stages; see their section comments.

The image is processed in horizontal stripes: launch ``stripe`` of ``nstripes`` covers tile rows
``stripe, stripe + nstripes, ...`` so several CPU launches (one per Python thread) can run in
parallel with balanced work. Thread ``tid`` of a launch maps to pixel
``py = ((tid // W) // ts * nstripes + stripe) * ts + (tid // W) % ts``, ``px = tid % W``.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import warp as wp

ALPHA_MIN = wp.constant(1.0 / 255.0)
ALPHA_MAX = wp.constant(0.99)
T_MIN = wp.constant(1.0e-4)
DEPTH_ALPHA_MIN = wp.constant(1.0e-6)

# Only the hand-written forward and backward kernels are used: skip generating Warp adjoints.
wp.set_module_options({"enable_backward": False})

_init_lock = threading.Lock()
_loaded: set[str] = set()
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()


@wp.func
def _pixel_of(tid: int, width: int, height: int, tile_size: int, tiles_x: int, stripe: int, nstripes: int):
    local_row = tid // width
    px = tid - local_row * width
    tr_local = local_row // tile_size
    py = (tr_local * nstripes + stripe) * tile_size + (local_row - tr_local * tile_size)
    return wp.vec3i(px, py, (py // tile_size) * tiles_x + px // tile_size)


@wp.kernel
def rasterize_fwd_kernel(
    gdata: wp.array2d(dtype=wp.float32),
    idata: wp.array2d(dtype=wp.float32),
    gids: wp.array(dtype=wp.int32),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
    width: int,
    height: int,
    tile_size: int,
    tiles_x: int,
    stripe: int,
    nstripes: int,
    out_feat: wp.array2d(dtype=wp.float32),
    out_T: wp.array(dtype=wp.float32),
    out_last: wp.array(dtype=wp.int32),
):
    """Front-to-back compositing of one pixel.

    Writes ``out_feat[pix] = (R, G, B, sum w z, sum w)`` (``sum w = 1 - T`` mathematically; the sum
    keeps depth = sum w z / sum w accurate in float32 where alpha is small), final transmittance ``out_T[pix]`` and
    ``out_last[pix]`` = one past the index (into ``gids``) of the last contributing Gaussian.
    """
    tid = wp.tid()
    q = _pixel_of(tid, width, height, tile_size, tiles_x, stripe, nstripes)
    px = q[0]
    py = q[1]
    if py >= height:
        return
    tile = q[2]
    start = tile_start[tile]
    end = tile_end[tile]
    fx = float(px)
    fy = float(py)
    T = float(1.0)
    cr = float(0.0)
    cg = float(0.0)
    cb = float(0.0)
    cd = float(0.0)
    ca = float(0.0)
    last = start
    for j in range(start, end):
        dx = (idata[j, 0] - fx) + idata[j, 5]
        dy = (idata[j, 1] - fy) + idata[j, 6]
        power = -0.5 * (idata[j, 2] * dx * dx + idata[j, 4] * dy * dy) - idata[j, 3] * dx * dy
        if power > 0.0 or power < idata[j, 7]:
            continue
        g = gids[j]
        alpha = wp.min(ALPHA_MAX, gdata[g, 5] * wp.exp(power))
        if alpha < ALPHA_MIN:
            continue
        test_T = T * (1.0 - alpha)
        if test_T < T_MIN:
            break
        w = alpha * T
        cr += w * gdata[g, 6]
        cg += w * gdata[g, 7]
        cb += w * gdata[g, 8]
        cd += w * gdata[g, 9]
        ca += w
        T = test_T
        last = j + 1
    pix = py * width + px
    out_feat[pix, 0] = cr
    out_feat[pix, 1] = cg
    out_feat[pix, 2] = cb
    out_feat[pix, 3] = cd
    out_feat[pix, 4] = ca
    out_T[pix] = T
    out_last[pix] = last


@wp.kernel
def rasterize_bwd_kernel(
    gdata: wp.array2d(dtype=wp.float32),
    idata: wp.array2d(dtype=wp.float32),
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
    grad_feat: wp.array2d(dtype=wp.float32),
    grad_gdata: wp.array2d(dtype=wp.float32),
):
    """Back-to-front gradient of one pixel's (R, G, B, depth sum, alpha) w.r.t. ``gdata`` rows.

    With ``w_i = alpha_i T_i`` and ``R_i = sum_{k>i} f_k w_k`` for every feature f:
    ``dF/dalpha_i = f_i T_i - R_i / (1 - alpha_i)`` and for the alpha output
    ``d(sum w)/dalpha_i = d(1 - T_final)/dalpha_i = T_final / (1 - alpha_i)``. ``T_i`` is recovered from ``T_final``
    by division. No gradient flows through a clamped alpha (``o G > 0.99``).
    """
    tid = wp.tid()
    q = _pixel_of(tid, width, height, tile_size, tiles_x, stripe, nstripes)
    px = q[0]
    py = q[1]
    if py >= height:
        return
    tile = q[2]
    pix = py * width + px
    start = tile_start[tile]
    last = last_idx[pix]
    if last <= start:
        return
    fx = float(px)
    fy = float(py)
    T_fin = final_T[pix]
    T = T_fin
    gr = grad_feat[pix, 0]
    gg = grad_feat[pix, 1]
    gb = grad_feat[pix, 2]
    gd = grad_feat[pix, 3]
    ga = grad_feat[pix, 4]
    rr = float(0.0)
    rg = float(0.0)
    rb = float(0.0)
    rd = float(0.0)
    for k in range(last - start):
        j = last - 1 - k
        dx = (idata[j, 0] - fx) + idata[j, 5]
        dy = (idata[j, 1] - fy) + idata[j, 6]
        ca = idata[j, 2]
        cbb = idata[j, 3]
        cc = idata[j, 4]
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cbb * dx * dy
        if power > 0.0 or power < idata[j, 7]:
            continue
        g = gids[j]
        G = wp.exp(power)
        op = gdata[g, 5]
        raw = op * G
        alpha = wp.min(ALPHA_MAX, raw)
        if alpha < ALPHA_MIN:
            continue
        inv = 1.0 / (1.0 - alpha)
        T = T * inv
        w = alpha * T
        fr = gdata[g, 6]
        fg = gdata[g, 7]
        fb = gdata[g, 8]
        fd = gdata[g, 9]
        wp.atomic_add(grad_gdata, g, 6, w * gr)
        wp.atomic_add(grad_gdata, g, 7, w * gg)
        wp.atomic_add(grad_gdata, g, 8, w * gb)
        wp.atomic_add(grad_gdata, g, 9, w * gd)
        dl_dalpha = (
            (fr * T - rr * inv) * gr
            + (fg * T - rg * inv) * gg
            + (fb * T - rb * inv) * gb
            + (fd * T - rd * inv) * gd
            + ga * T_fin * inv
        )
        rr += fr * w
        rg += fg * w
        rb += fb * w
        rd += fd * w
        if raw <= ALPHA_MAX:
            wp.atomic_add(grad_gdata, g, 5, G * dl_dalpha)
            dl_dp = alpha * dl_dalpha
            wp.atomic_add(grad_gdata, g, 0, -dl_dp * (ca * dx + cbb * dy))
            wp.atomic_add(grad_gdata, g, 1, -dl_dp * (cc * dy + cbb * dx))
            wp.atomic_add(grad_gdata, g, 2, -0.5 * dl_dp * dx * dx)
            wp.atomic_add(grad_gdata, g, 3, -dl_dp * dx * dy)
            wp.atomic_add(grad_gdata, g, 4, -0.5 * dl_dp * dy * dy)


# ------------------------------------------------------------------------------------ CPU tile kernels
#
# On CPU a Warp launch is a serial loop over thread ids, so the per-pixel kernels above evaluate
# every (pixel, Gaussian) pair of a tile even though a Gaussian typically covers a small part of
# each tile it is binned to. The tile kernels below run one *tile* per thread, Gaussian-outer and
# pixel-inner: for each Gaussian of the tile list only the pixels inside a conservative row-wise
# bound of its ``power >= p_min - 0.01`` ellipse (computed in float64, widened by 0.5 px) are
# visited, and each visited pair is evaluated with exactly the float32 arithmetic and tests of the
# per-pixel kernels. Every pixel still composites its Gaussians in list order with the same early
# termination, so the outputs are identical (bit for bit in the forward pass); the backward pass
# sums one tile's pixel contributions to a Gaussian locally before writing them once.
# Per-pixel running state lives in global per-pixel arrays, so the kernels are race free on any
# device, but they are only launched on CPU.


@wp.func
def _tile_rows(vv: float, ky1: float, ky0: float, y0: int, y1: int):
    """Rows [ya, yb] of ``[y0, y1]`` whose row offset ``dy = v - py`` satisfies
    ``ky0 - ky1 dy^2 >= 0`` (widened by 0.5 px); empty if ya > yb."""
    e = wp.sqrt(ky0 / ky1) + 0.5
    lo = wp.ceil(vv - e)
    hi = wp.floor(vv + e)
    ya = y0
    yb = y1
    if lo > float(y0):
        ya = y1 + 1
        if lo <= float(y1):
            ya = int(lo)
    if hi < float(y1):
        yb = y0 - 1
        if hi >= float(y0):
            yb = int(hi)
    return wp.vec2i(ya, yb)


@wp.func
def _row_span(cx: float, half2: float, x0: int, x1: int):
    """Columns [xa, xb] of ``[x0, x1]`` within ``sqrt(half2) + 0.5`` px of ``cx``; empty if
    ``half2 < 0`` or xa > xb."""
    xa = x1 + 1
    xb = x1
    if half2 >= 0.0:
        hw = wp.sqrt(half2) + 0.5
        lo = wp.ceil(cx - hw)
        hi = wp.floor(cx + hw)
        xa = x0
        if lo > float(x0):
            xa = x1 + 1
            if lo <= float(x1):
                xa = int(lo)
        if hi < float(x1):
            xb = x0 - 1
            if hi >= float(x0):
                xb = int(hi)
    return wp.vec2i(xa, xb)


vec5i = wp.types.vector(length=5, dtype=wp.int32)


@wp.func
def tile_box(tid: int, tiles_x: int, stripe: int, nstripes: int, tile_size: int, width: int, height: int):
    """Tile of launch thread ``tid`` in stripe ``stripe`` of ``nstripes`` (tile rows ``stripe``,
    ``stripe + nstripes``, ...): ``(tile index, x0, y0, x1, y1)`` with the inclusive pixel bounds."""
    tr = tid // tiles_x
    tx = tid - tr * tiles_x
    ty = tr * nstripes + stripe
    x0 = tx * tile_size
    y0 = ty * tile_size
    return vec5i(ty * tiles_x + tx, x0, y0, wp.min(x0 + tile_size, width) - 1, wp.min(y0 + tile_size, height) - 1)


@wp.func
def _fwd_tile_reset(x0: int, y0: int, x1: int, y1: int, width: int, start: int,
                    out_c: wp.array(dtype=wp.vec4), out_a: wp.array(dtype=wp.float32),
                    out_T: wp.array(dtype=wp.float32), out_last: wp.array(dtype=wp.int32)):
    """Start values of the tile's pixels [x0, x1] x [y0, y1]: no colour or alpha, T = 1, last = ``start``."""
    for py in range(y0, y1 + 1):
        for px in range(x0, x1 + 1):
            pix = py * width + px
            out_c[pix] = wp.vec4(0.0)
            out_a[pix] = 0.0
            out_T[pix] = 1.0
            out_last[pix] = start


@wp.func
def _fwd_tile_gaussian(gdata: wp.array2d(dtype=wp.float32), g: int, jn: int, x0: int, y0: int, x1: int, y1: int,
                       width: int, out_c: wp.array(dtype=wp.vec4), out_a: wp.array(dtype=wp.float32),
                       out_T: wp.array(dtype=wp.float32), out_last: wp.array(dtype=wp.int32)):
    """Composite Gaussian ``g`` (``gdata`` row; ``jn``: one past its index into ``gids``) front to back into the
    tile's pixels its footprint reaches. Returns how many pixels it terminated (marked by a negated ``out_T``)."""
    uh = gdata[g, 0]
    vh = gdata[g, 1]
    ca = gdata[g, 2]
    cb = gdata[g, 3]
    cc = gdata[g, 4]
    op = gdata[g, 5]
    feat = wp.vec4(gdata[g, 6], gdata[g, 7], gdata[g, 8], gdata[g, 9])
    ul = gdata[g, 10]
    vl = gdata[g, 11]
    pm = gdata[g, 12]
    uu = uh + ul
    vv = vh + vl
    ks = gdata[g, 13]
    k1 = gdata[g, 14]
    k0 = gdata[g, 15]
    n_done = int(0)
    rows = _tile_rows(vv, k1, k0, y0, y1)
    for py in range(rows[0], rows[1] + 1):
        fy = float(py)
        dyr = vv - fy
        span = _row_span(uu + ks * dyr, k0 - k1 * dyr * dyr, x0, x1)
        if span[0] > span[1]:
            continue
        dy = (vh - fy) + vl
        for px in range(span[0], span[1] + 1):
            pix = py * width + px
            T = out_T[pix]
            if T < 0.0:
                continue
            dx = (uh - float(px)) + ul
            power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
            if power > 0.0 or power < pm:
                continue
            alpha = wp.min(ALPHA_MAX, op * wp.exp(power))
            if alpha < ALPHA_MIN:
                continue
            test_T = T * (1.0 - alpha)
            if test_T < T_MIN:
                out_T[pix] = -T
                n_done += 1
                continue
            w = alpha * T
            out_c[pix] = out_c[pix] + w * feat
            out_a[pix] = out_a[pix] + w
            out_T[pix] = test_T
            out_last[pix] = jn
    return n_done


@wp.func
def _fwd_tile_finish(x0: int, y0: int, x1: int, y1: int, width: int, composite: int, bg: wp.vec3,
                     out_c: wp.array(dtype=wp.vec4), out_a: wp.array(dtype=wp.float32),
                     out_T: wp.array(dtype=wp.float32)):
    """Unmark terminated pixels (``|out_T|``) and, with ``composite`` != 0, finish ``out_c`` as
    ``(RGB + (1 - A) bg, depth)`` (see :func:`rasterize_fwd_tile_kernel`)."""
    for py in range(y0, y1 + 1):
        for px in range(x0, x1 + 1):
            pix = py * width + px
            out_T[pix] = wp.abs(out_T[pix])
            if composite != 0:
                c = out_c[pix]
                A = out_a[pix]
                t = 1.0 - A
                depth = float(0.0)
                if A >= DEPTH_ALPHA_MIN:
                    depth = c[3] / A
                out_c[pix] = wp.vec4(c[0] + t * bg[0], c[1] + t * bg[1], c[2] + t * bg[2], depth)


@wp.func
def _fwd_tile_warp(gdata: wp.array2d(dtype=wp.float32), gids: wp.array(dtype=wp.int32), start: int, end: int,
                   x0: int, y0: int, x1: int, y1: int, width: int, composite: int, bgr: float, bgg: float,
                   bgb: float, out_c: wp.array(dtype=wp.vec4), out_a: wp.array(dtype=wp.float32),
                   out_T: wp.array(dtype=wp.float32), out_last: wp.array(dtype=wp.int32)):
    """Forward pass of the tile [x0, x1] x [y0, y1] over its entries ``gids[start:end]`` (the signature of the SIMD
    kernels' native tile function); stops once every pixel has terminated."""
    _fwd_tile_reset(x0, y0, x1, y1, width, start, out_c, out_a, out_T, out_last)
    n_active = (x1 - x0 + 1) * (y1 - y0 + 1)
    for j in range(start, end):
        n_active -= _fwd_tile_gaussian(gdata, gids[j], j + 1, x0, y0, x1, y1, width, out_c, out_a, out_T, out_last)
        if n_active == 0:
            break
    _fwd_tile_finish(x0, y0, x1, y1, width, composite, wp.vec3(bgr, bgg, bgb), out_c, out_a, out_T)


@wp.kernel
def rasterize_fwd_tile_kernel(
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
    """Forward pass of one tile (same values as :func:`rasterize_fwd_kernel`, bit for bit).

    Outputs per pixel: ``out_c[pix] = (R, G, B, sum w z)``, ``out_a[pix] = A = sum w``, final
    transmittance ``out_T[pix]`` and ``out_last[pix]`` (one past the index into ``gids`` of the
    last contributing Gaussian). With ``composite`` != 0, ``out_c[pix]`` is finished as in
    :func:`gausslite.render.api.rasterize`: ``(RGB + (1 - A) bg, depth)`` with
    ``depth = sum w z / A`` if ``A >= 1e-6`` else 0 (same float32 operations as the torch code).
    While the tile is processed, a pixel that has terminated is marked by a negated ``out_T``.
    The work is :func:`_fwd_tile_warp`, the Warp twin of the SIMD kernel's native tile function.
    """
    box = tile_box(wp.tid(), tiles_x, stripe, nstripes, tile_size, width, height)
    tile = box[0]
    _fwd_tile_warp(gdata, gids, tile_start[tile], tile_end[tile], box[1], box[2], box[3], box[4], width, composite,
                   bg[0], bg[1], bg[2], out_c, out_a, out_T, out_last)


@wp.func
def bwd_tile_init(
    x0: int, y0: int, x1: int, y1: int, width: int, start: int,
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
):
    """Initialisation pass of a backward tile (pixels [x0, x1] x [y0, y1]), shared by
    :func:`rasterize_bwd_tile_kernel` and the SIMD kernel: writes ``grad_c[pix]`` and ``state[pix]``
    (see :func:`rasterize_bwd_tile_kernel`) and returns the largest ``last_idx`` of the tile (at least
    ``start``)."""
    maxlast = start
    for py in range(y0, y1 + 1):
        for px in range(x0, x1 + 1):
            pix = py * width + px
            tf = final_T[pix]
            gr = g_color[pix, 0]
            gg = g_color[pix, 1]
            gb = g_color[pix, 2]
            gd = g_depth[pix]
            ga = g_alpha[pix]
            if composite != 0:
                # color = RGB + (1 - A) bg, depth = D / A (A >= 1e-6, else 0)
                A = out_a[pix]
                ga = ga - (gr * bg[0] + gg * bg[1] + gb * bg[2])
                if A >= DEPTH_ALPHA_MIN:
                    ga = ga - gd * out_c[pix][3] / A
                    gd = gd / A
                else:
                    gd = 0.0
            grad_c[pix] = wp.vec4(gr, gg, gb, gd)
            state[pix] = wp.vec2(tf, ga * tf)
            maxlast = wp.max(maxlast, last_idx[pix])
    return maxlast


@wp.func
def _bwd_tile_row(gdata: wp.array2d(dtype=wp.float32), g: int, j: int, py: int, xa: int, xb: int, dy: float,
                  width: int, last_idx: wp.array(dtype=wp.int32), grad_c: wp.array(dtype=wp.vec4),
                  state: wp.array(dtype=wp.vec2), s_f: wp.vec4):
    """Back-to-front step of Gaussian ``g`` (entry ``j`` of ``gids``) over pixels [xa, xb] of row ``py`` (``dy``:
    the row's offset v - py): updates each pixel's ``state`` and adds ``w * grad_c`` to ``s_f``.

    Returns:
        ``(hit, m0, mx, mxx, s_f)``: whether any pixel took part, the row's sums of dl/dpower, dl/dpower dx and
        dl/dpower dx^2 (unclamped pairs only), and the updated ``s_f``.
    """
    uh = gdata[g, 0]
    ca = gdata[g, 2]
    cbb = gdata[g, 3]
    cc = gdata[g, 4]
    op = gdata[g, 5]
    feat = wp.vec4(gdata[g, 6], gdata[g, 7], gdata[g, 8], gdata[g, 9])
    ul = gdata[g, 10]
    pm = gdata[g, 12]
    hit = int(0)
    m0 = float(0.0)
    mx = float(0.0)
    mxx = float(0.0)
    for px in range(xa, xb + 1):
        pix = py * width + px
        if j >= last_idx[pix]:
            continue
        dx = (uh - float(px)) + ul
        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cbb * dx * dy
        if power > 0.0 or power < pm:
            continue
        G = wp.exp(power)
        raw = op * G
        alpha = wp.min(ALPHA_MAX, raw)
        if alpha < ALPHA_MIN:
            continue
        hit = 1
        inv = 1.0 / (1.0 - alpha)
        st = state[pix]
        T = st[0] * inv
        w = alpha * T
        gf = grad_c[pix]
        s_f += w * gf
        fg = wp.dot(feat, gf)
        dl_dalpha = fg * T + st[1] * inv
        state[pix] = wp.vec2(T, st[1] - fg * w)
        if raw <= ALPHA_MAX:
            # dl/dpower = alpha dl/dalpha (no gradient through a clamped alpha)
            dl_dp = alpha * dl_dalpha
            m0 += dl_dp
            t = dl_dp * dx
            mx += t
            mxx += t * dx
    return hit, m0, mx, mxx, s_f


@wp.func
def _bwd_tile_gaussian(gdata: wp.array2d(dtype=wp.float32), g: int, j: int, x0: int, y0: int, x1: int, y1: int,
                       width: int, last_idx: wp.array(dtype=wp.int32), grad_c: wp.array(dtype=wp.vec4),
                       state: wp.array(dtype=wp.vec2), grad_gdata: wp.array2d(dtype=wp.float32)):
    """Gradients of Gaussian ``g`` (entry ``j`` of ``gids``) over the tile [x0, x1] x [y0, y1], row by row
    (:func:`_bwd_tile_row`), expanded from the per-row moments and added to ``grad_gdata[g]``."""
    uh = gdata[g, 0]
    vh = gdata[g, 1]
    ca = gdata[g, 2]
    cbb = gdata[g, 3]
    cc = gdata[g, 4]
    op = gdata[g, 5]
    ul = gdata[g, 10]
    vl = gdata[g, 11]
    uu = uh + ul
    vv = vh + vl
    ks = gdata[g, 13]
    k1 = gdata[g, 14]
    k0 = gdata[g, 15]
    rows = _tile_rows(vv, k1, k0, y0, y1)
    hit = int(0)
    # sums over the tile's pixels of dl_dp, dl_dp dx, dl_dp dy, dl_dp dx^2, dl_dp dx dy, dl_dp dy^2
    s_0 = float(0.0)
    s_x = float(0.0)
    s_y = float(0.0)
    s_xx = float(0.0)
    s_xy = float(0.0)
    s_yy = float(0.0)
    s_f = wp.vec4(0.0)
    for py in range(rows[0], rows[1] + 1):
        fy = float(py)
        dyr = vv - fy
        span = _row_span(uu + ks * dyr, k0 - k1 * dyr * dyr, x0, x1)
        if span[0] > span[1]:
            continue
        dy = (vh - fy) + vl
        row_hit, m0, mx, mxx, s_f = _bwd_tile_row(gdata, g, j, py, span[0], span[1], dy, width, last_idx, grad_c,
                                                  state, s_f)
        hit = wp.max(hit, row_hit)
        s_0 += m0
        s_x += mx
        s_y += m0 * dy
        s_xx += mxx
        s_xy += mx * dy
        s_yy += m0 * dy * dy
    if hit != 0:
        # power = -0.5 (a dx^2 + c dy^2) - b dx dy with dx = u - px, dy = v - py;
        # dl/do = sum G dl/dalpha = sum dl_dp / o (unclamped pairs: alpha = o G)
        wp.atomic_add(grad_gdata, g, 0, -(ca * s_x + cbb * s_y))
        wp.atomic_add(grad_gdata, g, 1, -(cc * s_y + cbb * s_x))
        wp.atomic_add(grad_gdata, g, 2, -0.5 * s_xx)
        wp.atomic_add(grad_gdata, g, 3, -s_xy)
        wp.atomic_add(grad_gdata, g, 4, -0.5 * s_yy)
        wp.atomic_add(grad_gdata, g, 5, s_0 / op)
        wp.atomic_add(grad_gdata, g, 6, s_f[0])
        wp.atomic_add(grad_gdata, g, 7, s_f[1])
        wp.atomic_add(grad_gdata, g, 8, s_f[2])
        wp.atomic_add(grad_gdata, g, 9, s_f[3])


@wp.func
def _bwd_tile_warp(gdata: wp.array2d(dtype=wp.float32), gids: wp.array(dtype=wp.int32), start: int,
                   maxlast: int, x0: int, y0: int, x1: int, y1: int, width: int,
                   last_idx: wp.array(dtype=wp.int32), grad_c: wp.array(dtype=wp.vec4),
                   state: wp.array(dtype=wp.vec2), grad_gdata: wp.array2d(dtype=wp.float32)):
    """Back-to-front loop of the tile [x0, x1] x [y0, y1] over ``gids[start:maxlast]`` (the signature of the SIMD
    kernels' native tile function)."""
    for k in range(maxlast - start):
        j = maxlast - 1 - k
        _bwd_tile_gaussian(gdata, gids[j], j, x0, y0, x1, y1, width, last_idx, grad_c, state, grad_gdata)


@wp.kernel
def rasterize_bwd_tile_kernel(
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
    """Backward pass of one tile (the gradients of :func:`rasterize_bwd_kernel`, summed per
    Gaussian over the tile before being added to ``grad_gdata``).

    Inputs per pixel: the forward outputs ``out_c`` / ``out_a`` of
    :func:`rasterize_fwd_tile_kernel` (same ``composite`` flag and ``bg``) and the gradients of
    the loss w.r.t. them, ``g_color`` (HW, 3), ``g_depth`` (HW,) and ``g_alpha`` (HW,) (any
    strides). The initialisation pass converts them into ``grad_c[pix]`` = dL/d(R, G, B, sum w z)
    of the raw sums and dL/dA (A = sum w; through the background term and the depth division when
    ``composite`` != 0). With ``g = grad_c[pix]`` and ``f_i`` = (r, g, b, z) of Gaussian i, the
    colour terms of dL/dalpha_i only need the scalar ``S_i = sum_{k>i} (f_k . g) w_k``:
    ``dL/dalpha_i = (f_i . g) T_i + (dL/dA T_final - S_i) / (1 - alpha_i)``.
    ``state[pix] = (T_i, dL/dA T_final - S_i)`` is the back-to-front running state of each
    pixel. ``grad_c`` and ``state`` are per-pixel scratch arrays written here. The geometric
    gradients are accumulated as per-row moments of dL/dpower (sums of dl_dp, dl_dp dx,
    dl_dp dx^2 per row, combined with the row offset dy) and expanded once per Gaussian. The loop is
    :func:`_bwd_tile_warp`, the Warp twin of the SIMD kernel's native tile function.
    """
    box = tile_box(wp.tid(), tiles_x, stripe, nstripes, tile_size, width, height)
    tile = box[0]
    x0 = box[1]
    y0 = box[2]
    x1 = box[3]
    y1 = box[4]
    start = tile_start[tile]
    maxlast = bwd_tile_init(x0, y0, x1, y1, width, start, final_T, last_idx, composite, bg, out_c, out_a,
                            g_color, g_depth, g_alpha, grad_c, state)
    _bwd_tile_warp(gdata, gids, start, maxlast, x0, y0, x1, y1, width, last_idx, grad_c, state, grad_gdata)


@wp.kernel
def pack_gdata_kernel(
    means2d: wp.array2d(dtype=Any),
    conics: wp.array2d(dtype=Any),
    opacities: wp.array(dtype=Any),
    colors: wp.array2d(dtype=Any),
    depths: wp.array(dtype=Any),
    logit: int,
    gdata: wp.array2d(dtype=wp.float32),
):
    """Fill one row of the 16-column ``gdata`` layout (see the module docstring) from the
    projected parameters (float32 or float64); with ``logit`` != 0, ``opacities`` holds logits
    and the opacity is their sigmoid (in float64). Columns 13-15 hold the row-span coefficients
    ``(b / a, det / a^2, -2 (p_min - 0.01) / a)`` used by the tile kernels: on the row at offset
    ``dy = v - py`` the pixels with ``power >= p_min - 0.01`` lie within ``sqrt(k0 - k1 dy^2)`` px
    of ``u + (b / a) dy`` (unbounded span if the conic is not positive definite)."""
    i = wp.tid()
    u = wp.float64(means2d[i, 0])
    v = wp.float64(means2d[i, 1])
    uh = wp.float32(u)
    vh = wp.float32(v)
    a = wp.float64(conics[i, 0])
    b = wp.float64(conics[i, 1])
    c = wp.float64(conics[i, 2])
    o = wp.float64(opacities[i])
    if logit != 0:
        o = wp.float64(1.0) / (wp.float64(1.0) + wp.exp(-o))
    p_min = -wp.log(wp.float64(255.0) * wp.max(o, wp.float64(1e-30))) - wp.float64(1e-3)
    gdata[i, 0] = uh
    gdata[i, 1] = vh
    gdata[i, 2] = wp.float32(a)
    gdata[i, 3] = wp.float32(b)
    gdata[i, 4] = wp.float32(c)
    gdata[i, 5] = wp.float32(o)
    gdata[i, 6] = wp.float32(colors[i, 0])
    gdata[i, 7] = wp.float32(colors[i, 1])
    gdata[i, 8] = wp.float32(colors[i, 2])
    gdata[i, 9] = wp.float32(depths[i])
    gdata[i, 10] = wp.float32(u - wp.float64(uh))
    gdata[i, 11] = wp.float32(v - wp.float64(vh))
    gdata[i, 12] = wp.float32(p_min)
    det = a * c - b * b
    ks = wp.float64(0.0)
    k1 = wp.float64(0.0)
    k0 = wp.float64(1e38)
    if a > wp.float64(0.0) and det > wp.float64(0.0) and wp.isfinite(det):
        ks = b / a
        k1 = det / (a * a)
        k0 = wp.float64(-2.0) * (p_min - wp.float64(0.01)) / a
    gdata[i, 13] = wp.float32(ks)
    gdata[i, 14] = wp.float32(k1)
    gdata[i, 15] = wp.float32(k0)


for _T in (wp.float32, wp.float64):
    wp.overload(pack_gdata_kernel, [wp.array2d(dtype=_T), wp.array2d(dtype=_T), wp.array(dtype=_T),
                                    wp.array2d(dtype=_T), wp.array(dtype=_T), int,
                                    wp.array2d(dtype=wp.float32)])


@wp.kernel
def unpack_grads_kernel(
    bufs: wp.array3d(dtype=wp.float32),
    opacities: wp.array(dtype=Any),
    logit: int,
    g_means2d: wp.array2d(dtype=Any),
    g_conics: wp.array2d(dtype=Any),
    g_opacities: wp.array(dtype=Any),
    g_colors: wp.array2d(dtype=Any),
    g_depths: wp.array(dtype=Any),
):
    """Sum the per-thread (S, M, 10) float32 gradient buffers of one row (the first ten ``gdata``
    columns) and split them into the gradients of the projected inputs, in their dtype; with
    ``logit`` != 0 the opacity gradient is taken w.r.t. the logits ``opacities`` (times
    ``sigmoid'(x) = o (1 - o)``, in float64)."""
    i = wp.tid()
    acc = wp.vector(dtype=wp.float32, length=10)
    for s in range(bufs.shape[0]):
        for k in range(10):
            acc[k] += bufs[s, i, k]
    g_means2d[i, 0] = g_means2d.dtype(acc[0])
    g_means2d[i, 1] = g_means2d.dtype(acc[1])
    g_conics[i, 0] = g_conics.dtype(acc[2])
    g_conics[i, 1] = g_conics.dtype(acc[3])
    g_conics[i, 2] = g_conics.dtype(acc[4])
    go = wp.float64(acc[5])
    if logit != 0:
        o = wp.float64(1.0) / (wp.float64(1.0) + wp.exp(-wp.float64(opacities[i])))
        go = go * o * (wp.float64(1.0) - o)
    g_opacities[i] = g_opacities.dtype(go)
    g_colors[i, 0] = g_colors.dtype(acc[6])
    g_colors[i, 1] = g_colors.dtype(acc[7])
    g_colors[i, 2] = g_colors.dtype(acc[8])
    g_depths[i] = g_depths.dtype(acc[9])


for _T in (wp.float32, wp.float64):
    wp.overload(unpack_grads_kernel, [wp.array3d(dtype=wp.float32), wp.array(dtype=_T), int,
                                      wp.array2d(dtype=_T), wp.array2d(dtype=_T), wp.array(dtype=_T),
                                      wp.array2d(dtype=_T), wp.array(dtype=_T)])


# ------------------------------------------------------------------------------------ tile binning (CPU)
#
# Counting-sort replacement of the torch binning (see :mod:`gausslite.render.binning`): the visible
# rows are listed and counted per tile, sorted by float32 depth with Warp's stable radix sort, and
# appended in that (depth, row) order to the lists of the tiles they cover, which leaves every tile
# list sorted by depth with ties in row order -- exactly the order of the torch sort by
# ``tile << 32 | float32_bits(depth)``. Serial kernels (launched with dim=1 on CPU).


@wp.func
def _bin_tile(c: wp.float64, ts: wp.float64, f32: int, n: int):
    """``clamp(floor(c / ts), 0, n - 1)`` with the division rounded to float32 if ``f32``."""
    q = c / ts
    if f32 != 0:
        q = wp.float64(wp.float32(q))
    t = wp.floor(q)
    if t < wp.float64(0.0):
        t = wp.float64(0.0)
    if t > wp.float64(n - 1):
        t = wp.float64(n - 1)
    return int(t)


@wp.func
def _bin_rect(u: wp.float64, v: wp.float64, r: wp.float64, ts: wp.float64, f32: int, tiles_x: int,
              tiles_y: int):
    """Tile rectangle (tx0, tx1, ty0, ty1) of the bounding square ``[u - r, u + r] x [v - r, v + r]``,
    evaluated like the torch expression ``floor((u -+ r) / ts).clamp(0, n - 1)`` in the input dtype:
    for float32 inputs (``f32`` != 0) each float64 operation on float32 operands is rounded back to
    float32, which reproduces float32 arithmetic exactly (a single +, - or / in float64 followed by
    rounding to float32 is correctly rounded)."""
    a = u - r
    b = u + r
    c = v - r
    d = v + r
    if f32 != 0:
        a = wp.float64(wp.float32(a))
        b = wp.float64(wp.float32(b))
        c = wp.float64(wp.float32(c))
        d = wp.float64(wp.float32(d))
    return wp.vec4i(_bin_tile(a, ts, f32, tiles_x), _bin_tile(b, ts, f32, tiles_x),
                    _bin_tile(c, ts, f32, tiles_y), _bin_tile(d, ts, f32, tiles_y))


@wp.kernel
def bin_count_kernel(
    means2d: wp.array2d(dtype=Any),
    radii: wp.array(dtype=wp.int32),
    depths: wp.array(dtype=Any),
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    f32: int,
    keys: wp.array(dtype=wp.float32),
    rows: wp.array(dtype=wp.int32),
    n_rows: wp.array(dtype=wp.int32),
    tile_start: wp.array(dtype=wp.int32),
    tile_end: wp.array(dtype=wp.int32),
):
    """Serial (dim=1). Lists the rows with radius > 0 in increasing order in ``rows[:n]`` with
    their float32 depth in ``keys[:n]`` (``n_rows[0] = n``), and turns their per-tile intersection
    counts into ``tile_start`` / ``tile_end`` (exclusive / inclusive prefix sums, so the number of
    intersections is ``tile_end[-1]``). ``tile_end`` must be zero on entry."""
    ts = wp.float64(tile_size)
    n = int(0)
    for i in range(radii.shape[0]):
        r = radii[i]
        if r <= 0:
            continue
        keys[n] = wp.float32(depths[i])
        rows[n] = i
        n += 1
        q = _bin_rect(wp.float64(means2d[i, 0]), wp.float64(means2d[i, 1]), wp.float64(r), ts, f32,
                      tiles_x, tiles_y)
        for ty in range(q[2], q[3] + 1):
            for tx in range(q[0], q[1] + 1):
                tile_end[ty * tiles_x + tx] += 1
    n_rows[0] = n
    acc = int(0)
    for t in range(tiles_x * tiles_y):
        tile_start[t] = acc
        acc += tile_end[t]
        tile_end[t] = acc


@wp.kernel
def bin_scatter_kernel(
    means2d: wp.array2d(dtype=Any),
    radii: wp.array(dtype=wp.int32),
    rows: wp.array(dtype=wp.int32),
    n: int,
    tile_size: int,
    tiles_x: int,
    tiles_y: int,
    f32: int,
    stripe: int,
    nstripes: int,
    cursor: wp.array(dtype=wp.int32),
    gids: wp.array(dtype=wp.int32),
):
    """Serial (dim=1): append the rows ``rows[:n]`` (visited in that order) to the list of each tile
    they cover, for the tile rows ``ty`` with ``ty % nstripes == stripe`` (one launch per stripe;
    stripes write disjoint tiles). ``cursor`` starts as a copy of ``tile_start`` and ends equal to
    ``tile_end``."""
    ts = wp.float64(tile_size)
    for k in range(n):
        i = rows[k]
        q = _bin_rect(wp.float64(means2d[i, 0]), wp.float64(means2d[i, 1]), wp.float64(radii[i]), ts,
                      f32, tiles_x, tiles_y)
        ty0 = q[2] + (stripe - q[2] % nstripes + nstripes) % nstripes
        for ty in range(ty0, q[3] + 1, nstripes):
            for tx in range(q[0], q[1] + 1):
                t = ty * tiles_x + tx
                c = cursor[t]
                gids[c] = i
                cursor[t] = c + 1


for _T in (wp.float32, wp.float64):
    _i32 = wp.array(dtype=wp.int32)
    wp.overload(bin_count_kernel, [wp.array2d(dtype=_T), _i32, wp.array(dtype=_T), int, int, int, int,
                                   wp.array(dtype=wp.float32), _i32, _i32, _i32, _i32])
    wp.overload(bin_scatter_kernel, [wp.array2d(dtype=_T), _i32, _i32, int, int, int, int, int, int, int,
                                     _i32, _i32])


# ------------------------------------------------------------------------------------ EWA projection
#
# Per-Gaussian forward and hand-written backward of :func:`gausslite.render.projection.project_gaussians`
# (same formulas, culling and radius rule), evaluated in float64 whatever the input dtype.
# Gradients follow torch's conventions for the non-smooth pieces: nothing flows through the
# sanitised (culled) rows, the Jacobian clamp of x/z, y/z passes half the gradient on exact ties
# (torch.maximum / torch.minimum), and the conic of a row with a non positive-definite 2D
# covariance is (c, -b, a) (division by a constant 1).


@wp.func
def _quat_rotmat(w: wp.float64, x: wp.float64, y: wp.float64, z: wp.float64):
    """Rotation matrix of the unit quaternion (w, x, y, z) (formula of ``quat_to_rotmat``)."""
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    return wp.mat33d(
        one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y),
        two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x),
        two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y),
    )


@wp.func
def _clamp_grad_factor(x: wp.float64, lo: wp.float64, hi: wp.float64):
    """d/dx of ``min(max(x, lo), hi)`` with torch's tie rule (1/2 on each equality)."""
    f = wp.float64(1.0)
    if x < lo:
        f = wp.float64(0.0)
    elif x == lo:
        f = wp.float64(0.5)
    m = wp.max(x, lo)
    if m > hi:
        f = wp.float64(0.0)
    elif m == hi:
        f = f * wp.float64(0.5)
    return f


@wp.func
def _load_cam(
    means: wp.array2d(dtype=Any),
    quats: wp.array2d(dtype=Any),
    log_scales: wp.array2d(dtype=Any),
    i: int,
    rot: wp.mat33d,
    trans: wp.vec3d,
):
    """Row ``i`` in float64: camera-frame centre ``rot @ mean + trans`` (metres), raw quaternion
    (w, x, y, z) and log-scales."""
    m = wp.vec3d(wp.float64(means[i, 0]), wp.float64(means[i, 1]), wp.float64(means[i, 2]))
    q = wp.vec4d(wp.float64(quats[i, 0]), wp.float64(quats[i, 1]), wp.float64(quats[i, 2]),
                 wp.float64(quats[i, 3]))
    ls = wp.vec3d(wp.float64(log_scales[i, 0]), wp.float64(log_scales[i, 1]),
                  wp.float64(log_scales[i, 2]))
    return rot @ m + trans, q, ls


@wp.func
def _cam_cov(rot: wp.mat33d, qn: wp.vec4d, ls: wp.vec3d):
    """Camera-frame 3D covariance ``cov = M M^T`` with ``M = rot Rq diag(exp(ls))`` for the unit
    quaternion ``qn``; returns (Rq, exp(ls), M, cov), metres^2."""
    rq = _quat_rotmat(qn[0], qn[1], qn[2], qn[3])
    s = wp.vec3d(wp.exp(ls[0]), wp.exp(ls[1]), wp.exp(ls[2]))
    mm = rot @ (rq @ wp.diag(s))
    return rq, s, mm, mm @ wp.transpose(mm)


@wp.func
def _tan_limits(width: int, height: int, intr: wp.vec4d):
    """Clamp limits (x+, x-, y+, y-) of x/z and y/z for the EWA Jacobian: the image bounds widened by
    30 % of the half field of view (reference implementation's ``limx``/``limy``)."""
    fx = intr[0]
    fy = intr[1]
    cx = intr[2]
    cy = intr[3]
    w = wp.float64(width)
    h = wp.float64(height)
    tfx = wp.float64(0.5) * w / fx
    tfy = wp.float64(0.5) * h / fy
    return wp.vec4d((w - cx) / fx + wp.float64(0.3) * tfx, cx / fx + wp.float64(0.3) * tfx,
                    (h - cy) / fy + wp.float64(0.3) * tfy, cy / fy + wp.float64(0.3) * tfy)


@wp.func
def _ewa_cov2d(cov: wp.mat33d, fx: wp.float64, fy: wp.float64, rz: wp.float64, tx: wp.float64,
               ty: wp.float64, eps2d: wp.float64):
    """Rows j0, j1 of the projection Jacobian J at the clamped point (tx, ty, 1/rz) and the
    low-passed screen covariance J cov J^T + eps2d I as (a, b, c) = ([0,0], [0,1], [1,1]) in px^2;
    also returns w0 = cov j0 and w1 = cov j1 (needed by the backward)."""
    zero = wp.float64(0.0)
    j0 = wp.vec3d(fx * rz, zero, -fx * tx * rz * rz)
    j1 = wp.vec3d(zero, fy * rz, -fy * ty * rz * rz)
    w0 = cov @ j0
    w1 = cov @ j1
    abc = wp.vec3d(wp.dot(j0, w0) + eps2d, wp.dot(j1, w0), wp.dot(j1, w1) + eps2d)
    return j0, j1, w0, w1, abc


@wp.func
def _screen_cov(rot: wp.mat33d, q: wp.vec4d, ls: wp.vec3d, xs: wp.float64, ys: wp.float64, zs: wp.float64,
                width: int, height: int, intr: wp.vec4d, eps2d: wp.float64):
    """The projection's shared intermediates of one Gaussian at camera point (xs, ys, zs) (metres): the quaternion
    norm ``qlen`` and divisor ``qden``, unit quaternion ``qn``, (Rq, exp(ls), M) of :func:`_cam_cov`, the clamp
    limits ``lim`` (:func:`_tan_limits`), ``rz = 1 / zs``, the clamped ``txc = x/z``, ``tyc = y/z`` and the
    outputs of :func:`_ewa_cov2d` at them (the screen covariance ``abc`` in px^2 and its factors)."""
    qlen = wp.length(q)
    qden = wp.max(qlen, wp.float64(1e-12))
    qn = q / qden
    rq, s, mm, cov = _cam_cov(rot, qn, ls)
    lim = _tan_limits(width, height, intr)
    rz = wp.float64(1.0) / zs
    txc = wp.min(wp.max(xs * rz, -lim[1]), lim[0])
    tyc = wp.min(wp.max(ys * rz, -lim[3]), lim[2])
    j0, j1, w0, w1, abc = _ewa_cov2d(cov, intr[0], intr[1], rz, zs * txc, zs * tyc, eps2d)
    return qlen, qden, qn, rq, s, mm, lim, rz, txc, tyc, j0, j1, w0, w1, abc


@wp.func
def _conic_grad(gA: wp.float64, gB: wp.float64, gC: wp.float64, abc: wp.vec3d):
    """Gradient w.r.t. the screen covariance (a, b, c) of the conic ``(c, -b, a) / det`` given its gradient
    (gA, gB, gC); a covariance that is not positive definite had the conic ``(c, -b, a)`` (det taken as 1)."""
    a = abc[0]
    b = abc[1]
    c = abc[2]
    one = wp.float64(1.0)
    det = a * c - b * b
    ga = gC
    gb = -gB
    gc = gA
    if det > wp.float64(0.0) and wp.isfinite(det):
        idet = one / det
        gdet = -(gA * c - gB * b + gC * a) * idet * idet
        ga = gC * idet + gdet * c
        gc = gA * idet + gdet * a
        gb = -gB * idet - wp.float64(2.0) * gdet * b
    return wp.vec3d(ga, gb, gc)


@wp.func
def _quat_grad(qn: wp.vec4d, qlen: wp.float64, qden: wp.float64, grq: wp.mat33d):
    """Gradient w.r.t. the raw quaternion of ``Rq = R(q / max(|q|, 1e-12))`` given ``grq = dL/dRq``."""
    two = wp.float64(2.0)
    qw = qn[0]
    qx = qn[1]
    qy = qn[2]
    qz = qn[3]
    gw = two * (-qz * grq[0, 1] + qy * grq[0, 2] + qz * grq[1, 0] - qx * grq[1, 2] - qy * grq[2, 0]
                + qx * grq[2, 1])
    gx = two * (qy * grq[0, 1] + qz * grq[0, 2] + qy * grq[1, 0] - two * qx * grq[1, 1] - qw * grq[1, 2]
                + qz * grq[2, 0] + qw * grq[2, 1] - two * qx * grq[2, 2])
    gy = two * (-two * qy * grq[0, 0] + qx * grq[0, 1] + qw * grq[0, 2] + qx * grq[1, 0] + qz * grq[1, 2]
                - qw * grq[2, 0] + qz * grq[2, 1] - two * qy * grq[2, 2])
    gz = two * (-two * qz * grq[0, 0] - qw * grq[0, 1] + qx * grq[0, 2] + qw * grq[1, 0]
                - two * qz * grq[1, 1] + qy * grq[1, 2] + qx * grq[2, 0] + qy * grq[2, 1])
    gqn = wp.vec4d(gw, gx, gy, gz)
    gq = gqn / qden
    if qlen >= wp.float64(1e-12):
        gq = (gqn - qn * wp.dot(qn, gqn)) / qden
    return gq


@wp.func
def _mean_grad(rot: wp.mat33d, intr: wp.vec4d, lim: wp.vec4d, xs: wp.float64, ys: wp.float64, zs: wp.float64,
               rz: wp.float64, txc: wp.float64, tyc: wp.float64, gj0: wp.vec3d, gj1: wp.vec3d, gu: wp.float64,
               gv: wp.float64, gzs: wp.float64):
    """Gradient w.r.t. the world-frame mean through the Jacobian rows (``gj0``, ``gj1``: their gradients), the
    pixel centre (gu, gv) and the depth (``gzs``), with the clamp of x/z, y/z (:func:`_clamp_grad_factor`)."""
    two = wp.float64(2.0)
    fx = intr[0]
    fy = intr[1]
    tx = zs * txc
    ty = zs * tyc
    # Jacobian entries J00 = fx rz, J02 = -fx tx rz^2, J11 = fy rz, J12 = -fy ty rz^2
    grz = fx * gj0[0] + fy * gj1[1] - two * fx * tx * rz * gj0[2] - two * fy * ty * rz * gj1[2]
    gtx = -fx * rz * rz * gj0[2]
    gty = -fy * rz * rz * gj1[2]
    # u = fx xs rz + cx, v = fy ys rz + cy
    gxs = gu * fx * rz
    gys = gv * fy * rz
    grz += gu * fx * xs + gv * fy * ys
    # tx = zs clamp(xs rz), ty = zs clamp(ys rz)
    gzs += gtx * txc + gty * tyc
    gxr = gtx * zs * _clamp_grad_factor(xs * rz, -lim[1], lim[0])
    gyr = gty * zs * _clamp_grad_factor(ys * rz, -lim[3], lim[2])
    gxs += gxr * rz
    gys += gyr * rz
    grz += gxr * xs + gyr * ys
    gzs += -grz * rz * rz
    return wp.transpose(rot) @ wp.vec3d(gxs, gys, gzs)


@wp.kernel
def project_fwd_kernel(
    means: wp.array2d(dtype=Any),
    quats: wp.array2d(dtype=Any),
    log_scales: wp.array2d(dtype=Any),
    rot: wp.mat33d,
    trans: wp.vec3d,
    intr: wp.vec4d,
    width: int,
    height: int,
    near: wp.float64,
    far: wp.float64,
    eps2d: wp.float64,
    offset: int,
    means2d: wp.array2d(dtype=Any),
    conics: wp.array2d(dtype=Any),
    depths: wp.array(dtype=Any),
    radii: wp.array(dtype=wp.int32),
):
    """EWA projection of Gaussian ``offset + tid``; outputs as
    :class:`~gausslite.render.projection.Projection`.

    ``rot``/``trans``: world-to-camera rotation and translation; ``intr = (fx, fy, cx, cy)`` in
    pixels; ``near``/``far`` in metres; ``eps2d`` in px^2.
    """
    i = wp.tid() + offset
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    half = wp.float64(0.5)
    fx = intr[0]
    fy = intr[1]
    cx = intr[2]
    cy = intr[3]
    p, q, ls = _load_cam(means, quats, log_scales, i, rot, trans)
    finite = wp.isfinite(p) and wp.isfinite(q) and wp.isfinite(ls)
    valid = finite and p[2] > near and p[2] < far
    xs = zero
    ys = zero
    zs = one
    if valid:
        xs = p[0]
        ys = p[1]
        zs = p[2]
    else:
        q = wp.vec4d(one, one, one, one)
        ls = wp.vec3d(zero, zero, zero)
    qlen, qden, qn, rq, s, mm, lim, rz, txc, tyc, j0, j1, w0, w1, abc = _screen_cov(
        rot, q, ls, xs, ys, zs, width, height, intr, eps2d)
    w = wp.float64(width)
    h = wp.float64(height)
    a = abc[0]
    b = abc[1]
    c = abc[2]
    det = a * c - b * b
    valid = valid and det > zero and wp.isfinite(det)
    det_s = one
    if valid:
        det_s = det
    u = fx * xs * rz + cx
    v = fy * ys * rz + cy
    mid = half * (a + c)
    lam = one
    if valid:
        lam = mid + wp.sqrt(wp.max(mid * mid - det, wp.float64(0.1)))
    r = wp.ceil(wp.float64(3.0) * wp.sqrt(lam))
    inside = u + r >= zero and u - r <= w - one and v + r >= zero and v - r <= h - one
    keep = valid and inside and wp.isfinite(r) and wp.isfinite(u) and wp.isfinite(v)
    ri = int(0)
    if keep:
        ri = int(wp.min(r, wp.float64(1073741824.0)))
    means2d[i, 0] = means2d.dtype(u)
    means2d[i, 1] = means2d.dtype(v)
    conics[i, 0] = conics.dtype(c / det_s)
    conics[i, 1] = conics.dtype(-b / det_s)
    conics[i, 2] = conics.dtype(a / det_s)
    depths[i] = depths.dtype(zs)
    radii[i] = ri


@wp.kernel
def project_bwd_kernel(
    means: wp.array2d(dtype=Any),
    quats: wp.array2d(dtype=Any),
    log_scales: wp.array2d(dtype=Any),
    rot: wp.mat33d,
    trans: wp.vec3d,
    intr: wp.vec4d,
    width: int,
    height: int,
    near: wp.float64,
    far: wp.float64,
    eps2d: wp.float64,
    offset: int,
    g_means2d: wp.array2d(dtype=Any),
    g_conics: wp.array2d(dtype=Any),
    g_depths: wp.array(dtype=Any),
    g_means: wp.array2d(dtype=Any),
    g_quats: wp.array2d(dtype=Any),
    g_log_scales: wp.array2d(dtype=Any),
):
    """Gradients of the outputs of :func:`project_fwd_kernel` (means2d, conics, depths) w.r.t.
    means, quats and log_scales of Gaussian ``offset + tid`` (recomputes the forward
    intermediates)."""
    i = wp.tid() + offset
    half = wp.float64(0.5)
    two = wp.float64(2.0)
    p, q, ls = _load_cam(means, quats, log_scales, i, rot, trans)
    finite = wp.isfinite(p) and wp.isfinite(q) and wp.isfinite(ls)
    valid = finite and p[2] > near and p[2] < far
    if not valid:
        for k in range(3):
            g_means[i, k] = g_means.dtype(0.0)
            g_log_scales[i, k] = g_log_scales.dtype(0.0)
        for k in range(4):
            g_quats[i, k] = g_quats.dtype(0.0)
        return
    xs = p[0]
    ys = p[1]
    zs = p[2]
    qlen, qden, qn, rq, s, mm, lim, rz, txc, tyc, j0, j1, w0, w1, abc = _screen_cov(
        rot, q, ls, xs, ys, zs, width, height, intr, eps2d)
    gabc = _conic_grad(wp.float64(g_conics[i, 0]), wp.float64(g_conics[i, 1]), wp.float64(g_conics[i, 2]), abc)
    ga = gabc[0]
    gb = gabc[1]
    gc = gabc[2]
    # cov2 = J cov J^T with the symmetric upstream gradient [[ga, gb/2], [gb/2, gc]]
    gj0 = two * ga * w0 + gb * w1
    gj1 = gb * w0 + two * gc * w1
    gcov = ga * wp.outer(j0, j0) + half * gb * (wp.outer(j0, j1) + wp.outer(j1, j0)) + gc * wp.outer(j1, j1)
    gmm = two * (gcov @ mm)
    gn = wp.transpose(rot) @ gmm  # gradient of N = Rq diag(s)
    grq = gn @ wp.diag(s)
    gls = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for k in range(3):
        gls[k] = (gn[0, k] * rq[0, k] + gn[1, k] * rq[1, k] + gn[2, k] * rq[2, k]) * s[k]
    gq = _quat_grad(qn, qlen, qden, grq)
    gm = _mean_grad(rot, intr, lim, xs, ys, zs, rz, txc, tyc, gj0, gj1, wp.float64(g_means2d[i, 0]),
                    wp.float64(g_means2d[i, 1]), wp.float64(g_depths[i]))
    for k in range(3):
        g_means[i, k] = g_means.dtype(gm[k])
        g_log_scales[i, k] = g_log_scales.dtype(gls[k])
    for k in range(4):
        g_quats[i, k] = g_quats.dtype(gq[k])


for _T in (wp.float32, wp.float64):
    _a2 = wp.array2d(dtype=_T)
    _common = [_a2, _a2, _a2, wp.mat33d, wp.vec3d, wp.vec4d, int, int, wp.float64, wp.float64, wp.float64,
               int]
    wp.overload(project_fwd_kernel, _common + [_a2, _a2, wp.array(dtype=_T), wp.array(dtype=wp.int32)])
    wp.overload(project_bwd_kernel, _common + [_a2, _a2, wp.array(dtype=_T), _a2, _a2, _a2])



def ensure_loaded(device: str) -> None:
    """Initialise Warp and compile/load this module (and, on CPU, :mod:`gausslite.render.simd_kernels`)
    for ``device`` once per process.

    Must run before concurrent launches so that two threads never compile the module at the same
    time. Compiled binaries are cached on disk by Warp (``~/.cache/warp``) across processes.
    """
    ensure_module_loaded(__name__, device)
    if device == "cpu":
        ensure_module_loaded("gausslite.render.simd_kernels", device)


def ensure_module_loaded(module: str, device: str) -> None:
    """Initialise Warp and compile/load the Warp module named ``module`` (imported) for ``device`` once
    per process, under one lock for every module (see :func:`ensure_loaded`)."""
    key = f"{module}@{device}"
    if key in _loaded:
        return
    with _init_lock:
        if key in _loaded:
            return
        wp.init()
        wp.load_module(module=module, device=device)
        _loaded.add(key)


def _forget_pool_in_child() -> None:
    # a forked child (multiprocessing's default start method on Linux) inherits the pool object but not
    # its threads: work submitted to it would never run. Start a fresh pool on first use instead.
    global _pool, _pool_size, _pool_lock
    _pool, _pool_size, _pool_lock = None, 0, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool_in_child)


def run_parallel(fns) -> None:
    """Run the callables in ``fns`` concurrently and re-raise any error: the first one in the
    calling thread, the others in a persistent thread pool (CPU Warp launches release the GIL,
    so each callable can keep one core busy). Fork-safe: a forked child starts its own pool."""
    global _pool, _pool_size
    if len(fns) == 1:
        fns[0]()
        return
    with _pool_lock:
        if _pool is None or _pool_size < len(fns) - 1:
            if _pool is not None:
                _pool.shutdown(wait=True)
            _pool = ThreadPoolExecutor(max_workers=len(fns) - 1, thread_name_prefix="gausslite-raster")
            _pool_size = len(fns) - 1
        pool = _pool
    futs = [pool.submit(f) for f in fns[1:]]
    try:
        fns[0]()
    finally:
        for f in futs:
            f.result()
