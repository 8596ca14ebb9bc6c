"""Forward Warp kernels of the rasterizer: per-pixel compositing (the CUDA path), the CPU tile compositing, the
16-float ``gdata`` packing and the EWA projection (layout and launch geometry:
:mod:`gausslite.render.warp_kernels`, which re-exports every kernel)."""

from __future__ import annotations

from typing import Any

import warp as wp

from .warp_kernels_common import (ALPHA_MAX, ALPHA_MIN, DEPTH_ALPHA_MIN, T_MIN, load_cam, pixel_of, row_span,
                                  screen_cov, tile_box, tile_rows)

# Only the hand-written forward and backward kernels are used: skip generating Warp adjoints.
wp.set_module_options({"enable_backward": False})


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
    q = pixel_of(tid, width, height, tile_size, tiles_x, stripe, nstripes)
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


# ------------------------------------------------------------------------------------ CPU tile kernels
# (the tile kernels' scheme: :mod:`gausslite.render.warp_kernels_common`)


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
    rows = tile_rows(vv, k1, k0, y0, y1)
    for py in range(rows[0], rows[1] + 1):
        fy = float(py)
        dyr = vv - fy
        span = row_span(uu + ks * dyr, k0 - k1 * dyr * dyr, x0, x1)
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


# ------------------------------------------------------------------------------------ EWA projection
# (the conventions: :mod:`gausslite.render.warp_kernels_common`)


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
    p, q, ls = load_cam(means, quats, log_scales, i, rot, trans)
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
    qlen, qden, qn, rq, s, mm, lim, rz, txc, tyc, j0, j1, w0, w1, abc = screen_cov(
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


for _T in (wp.float32, wp.float64):
    _a2 = wp.array2d(dtype=_T)
    _common = [_a2, _a2, _a2, wp.mat33d, wp.vec3d, wp.vec4d, int, int, wp.float64, wp.float64, wp.float64,
               int]
    wp.overload(project_fwd_kernel, _common + [_a2, _a2, wp.array(dtype=_T), wp.array(dtype=wp.int32)])
