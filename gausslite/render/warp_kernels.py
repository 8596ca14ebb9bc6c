"""Per-pixel Warp kernels for tile-based Gaussian rasterization (forward and backward).

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
thread, Gaussian-outer) replace the per-pixel kernels below; those remain the CUDA path.

The image is processed in horizontal stripes: launch ``stripe`` of ``nstripes`` covers tile rows
``stripe, stripe + nstripes, ...`` so several CPU launches (one per Python thread) can run in
parallel with balanced work. Thread ``tid`` of a launch maps to pixel
``py = ((tid // W) // ts * nstripes + stripe) * ts + (tid // W) % ts``, ``px = tid % W``.
"""

from __future__ import annotations

import threading
from typing import Any

import warp as wp

ALPHA_MIN = wp.constant(1.0 / 255.0)
ALPHA_MAX = wp.constant(0.99)
T_MIN = wp.constant(1.0e-4)

# Only the hand-written forward and backward kernels are used: skip generating Warp adjoints.
wp.set_module_options({"enable_backward": False})

_init_lock = threading.Lock()
_loaded: set[str] = set()


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
    out_feat: wp.array2d(dtype=wp.float32),
    out_T: wp.array(dtype=wp.float32),
    out_last: wp.array(dtype=wp.int32),
):
    """Forward pass of one tile (same outputs as :func:`rasterize_fwd_kernel`).

    While the tile is processed, a pixel that has terminated is marked by a negated ``out_T``.
    """
    tid = wp.tid()
    tr = tid // tiles_x
    tx = tid - tr * tiles_x
    ty = tr * nstripes + stripe
    tile = ty * tiles_x + tx
    x0 = tx * tile_size
    y0 = ty * tile_size
    x1 = wp.min(x0 + tile_size, width) - 1
    y1 = wp.min(y0 + tile_size, height) - 1
    start = tile_start[tile]
    end = tile_end[tile]
    for py in range(y0, y1 + 1):
        for px in range(x0, x1 + 1):
            pix = py * width + px
            for k in range(5):
                out_feat[pix, k] = 0.0
            out_T[pix] = 1.0
            out_last[pix] = start
    n_active = (x1 - x0 + 1) * (y1 - y0 + 1)
    for j in range(start, end):
        g = gids[j]
        uh = gdata[g, 0]
        vh = gdata[g, 1]
        ca = gdata[g, 2]
        cb = gdata[g, 3]
        cc = gdata[g, 4]
        op = gdata[g, 5]
        ul = gdata[g, 10]
        vl = gdata[g, 11]
        pm = gdata[g, 12]
        uu = uh + ul
        vv = vh + vl
        ks = gdata[g, 13]
        k1 = gdata[g, 14]
        k0 = gdata[g, 15]
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
                    n_active -= 1
                    continue
                w = alpha * T
                out_feat[pix, 0] += w * gdata[g, 6]
                out_feat[pix, 1] += w * gdata[g, 7]
                out_feat[pix, 2] += w * gdata[g, 8]
                out_feat[pix, 3] += w * gdata[g, 9]
                out_feat[pix, 4] += w
                out_T[pix] = test_T
                out_last[pix] = j + 1
        if n_active == 0:
            break
    for py in range(y0, y1 + 1):
        for px in range(x0, x1 + 1):
            pix = py * width + px
            out_T[pix] = wp.abs(out_T[pix])


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
    grad_feat: wp.array2d(dtype=wp.float32),
    state: wp.array2d(dtype=wp.float32),
    grad_gdata: wp.array2d(dtype=wp.float32),
):
    """Backward pass of one tile (same gradients as :func:`rasterize_bwd_kernel`, summed per
    Gaussian over the tile before being added to ``grad_gdata``).

    ``state[pix] = (T, R_r, R_g, R_b, R_d, dL/dR, dL/dG, dL/dB, dL/dD, dL/dA * T_final, ...)``
    (12 columns, initialised here) is the back-to-front running state of each pixel, packed so
    that one pixel's data shares a cache line.
    """
    tid = wp.tid()
    tr = tid // tiles_x
    tx = tid - tr * tiles_x
    ty = tr * nstripes + stripe
    tile = ty * tiles_x + tx
    x0 = tx * tile_size
    y0 = ty * tile_size
    x1 = wp.min(x0 + tile_size, width) - 1
    y1 = wp.min(y0 + tile_size, height) - 1
    start = tile_start[tile]
    maxlast = start
    for py in range(y0, y1 + 1):
        for px in range(x0, x1 + 1):
            pix = py * width + px
            state[pix, 0] = final_T[pix]
            state[pix, 1] = 0.0
            state[pix, 2] = 0.0
            state[pix, 3] = 0.0
            state[pix, 4] = 0.0
            state[pix, 5] = grad_feat[pix, 0]
            state[pix, 6] = grad_feat[pix, 1]
            state[pix, 7] = grad_feat[pix, 2]
            state[pix, 8] = grad_feat[pix, 3]
            state[pix, 9] = grad_feat[pix, 4] * final_T[pix]
            maxlast = wp.max(maxlast, last_idx[pix])
    for k in range(maxlast - start):
        j = maxlast - 1 - k
        g = gids[j]
        uh = gdata[g, 0]
        vh = gdata[g, 1]
        ca = gdata[g, 2]
        cbb = gdata[g, 3]
        cc = gdata[g, 4]
        op = gdata[g, 5]
        fr = gdata[g, 6]
        fg = gdata[g, 7]
        fb = gdata[g, 8]
        fd = gdata[g, 9]
        ul = gdata[g, 10]
        vl = gdata[g, 11]
        pm = gdata[g, 12]
        uu = uh + ul
        vv = vh + vl
        ks = gdata[g, 13]
        k1 = gdata[g, 14]
        k0 = gdata[g, 15]
        rows = _tile_rows(vv, k1, k0, y0, y1)
        hit = int(0)
        s_u = float(0.0)
        s_v = float(0.0)
        s_a = float(0.0)
        s_b = float(0.0)
        s_c = float(0.0)
        s_o = float(0.0)
        s_r = float(0.0)
        s_g = float(0.0)
        s_bl = float(0.0)
        s_d = float(0.0)
        for py in range(rows[0], rows[1] + 1):
            fy = float(py)
            dyr = vv - fy
            span = _row_span(uu + ks * dyr, k0 - k1 * dyr * dyr, x0, x1)
            if span[0] > span[1]:
                continue
            dy = (vh - fy) + vl
            for px in range(span[0], span[1] + 1):
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
                T = state[pix, 0] * inv
                w = alpha * T
                gr = state[pix, 5]
                gg = state[pix, 6]
                gb = state[pix, 7]
                gd = state[pix, 8]
                gaT = state[pix, 9]
                rr = state[pix, 1]
                rg = state[pix, 2]
                rb = state[pix, 3]
                rd = state[pix, 4]
                s_r += w * gr
                s_g += w * gg
                s_bl += w * gb
                s_d += w * gd
                dl_dalpha = (
                    (fr * T - rr * inv) * gr
                    + (fg * T - rg * inv) * gg
                    + (fb * T - rb * inv) * gb
                    + (fd * T - rd * inv) * gd
                    + gaT * inv
                )
                state[pix, 0] = T
                state[pix, 1] = rr + fr * w
                state[pix, 2] = rg + fg * w
                state[pix, 3] = rb + fb * w
                state[pix, 4] = rd + fd * w
                if raw <= ALPHA_MAX:
                    s_o += G * dl_dalpha
                    dl_dp = alpha * dl_dalpha
                    s_u += -dl_dp * (ca * dx + cbb * dy)
                    s_v += -dl_dp * (cc * dy + cbb * dx)
                    s_a += -0.5 * dl_dp * dx * dx
                    s_b += -dl_dp * dx * dy
                    s_c += -0.5 * dl_dp * dy * dy
        if hit != 0:
            wp.atomic_add(grad_gdata, g, 0, s_u)
            wp.atomic_add(grad_gdata, g, 1, s_v)
            wp.atomic_add(grad_gdata, g, 2, s_a)
            wp.atomic_add(grad_gdata, g, 3, s_b)
            wp.atomic_add(grad_gdata, g, 4, s_c)
            wp.atomic_add(grad_gdata, g, 5, s_o)
            wp.atomic_add(grad_gdata, g, 6, s_r)
            wp.atomic_add(grad_gdata, g, 7, s_g)
            wp.atomic_add(grad_gdata, g, 8, s_bl)
            wp.atomic_add(grad_gdata, g, 9, s_d)



@wp.kernel
def pack_gdata_kernel(
    means2d: wp.array2d(dtype=Any),
    conics: wp.array2d(dtype=Any),
    opacities: wp.array(dtype=Any),
    colors: wp.array2d(dtype=Any),
    depths: wp.array(dtype=Any),
    gdata: wp.array2d(dtype=wp.float32),
):
    """Fill one row of the 16-column ``gdata`` layout (see the module docstring) from the
    projected parameters (float32 or float64). Columns 13-15 hold the row-span coefficients
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
                                    wp.array2d(dtype=_T), wp.array(dtype=_T),
                                    wp.array2d(dtype=wp.float32)])


def ensure_loaded(device: str) -> None:
    """Initialise Warp and compile/load this module for ``device`` once per process.

    Must run before concurrent launches so that two threads never compile the module at the same
    time. Compiled binaries are cached on disk by Warp (``~/.cache/warp``) across processes.
    """
    if device in _loaded:
        return
    with _init_lock:
        if device in _loaded:
            return
        wp.init()
        wp.load_module(module=__name__, device=device)
        _loaded.add(device)
