"""Backward Warp kernels of the rasterizer (hand-written gradients; no Warp adjoints): per-pixel compositing (the
CUDA path), the CPU tile compositing, the gradient unpacking and the EWA projection (layout and launch geometry:
:mod:`gausslite.render.warp_kernels`, which re-exports every kernel)."""

from __future__ import annotations

from typing import Any

import warp as wp

from .warp_kernels_common import (ALPHA_MAX, ALPHA_MIN, DEPTH_ALPHA_MIN, load_cam, pixel_of, row_span,
                                  screen_cov, tile_box, tile_rows)

# Only the hand-written forward and backward kernels are used: skip generating Warp adjoints.
wp.set_module_options({"enable_backward": False})


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
    q = pixel_of(tid, width, height, tile_size, tiles_x, stripe, nstripes)
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
# (the tile kernels' scheme: :mod:`gausslite.render.warp_kernels_common`)


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
    rows = tile_rows(vv, k1, k0, y0, y1)
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
        span = row_span(uu + ks * dyr, k0 - k1 * dyr * dyr, x0, x1)
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


# ------------------------------------------------------------------------------------ EWA projection
# (the conventions: :mod:`gausslite.render.warp_kernels_common`)


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
    p, q, ls = load_cam(means, quats, log_scales, i, rot, trans)
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
    qlen, qden, qn, rq, s, mm, lim, rz, txc, tyc, j0, j1, w0, w1, abc = screen_cov(
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
    wp.overload(project_bwd_kernel, _common + [_a2, _a2, wp.array(dtype=_T), _a2, _a2, _a2])
