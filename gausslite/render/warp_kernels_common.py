"""Constants and ``@wp.func`` helpers shared by the forward (:mod:`gausslite.render.warp_kernels_fwd`) and backward
(:mod:`gausslite.render.warp_kernels_bwd`) Warp kernels of the rasterizer and by the SIMD kernels
(:mod:`gausslite.render.simd_kernels`): the compositing thresholds of Kerbl et al. 2023, the pixel or tile of a launch
thread, the row bounds of a Gaussian's footprint in a tile, and the EWA projection's forward intermediates. The data
layout and launch geometry are described in :mod:`gausslite.render.warp_kernels`.

The interface (what the kernel modules import; every other name here is this module's own):

- :data:`ALPHA_MIN`, :data:`ALPHA_MAX`, :data:`T_MIN`, :data:`DEPTH_ALPHA_MIN`: the compositing thresholds
  (``wp.constant``);
- :func:`pixel_of`: pixel and tile of a per-pixel launch thread;
- :func:`tile_box` (with its return type :data:`vec5i`): tile and pixel bounds of a tile launch thread;
- :func:`tile_rows`, :func:`row_span`: the rows of a tile, and the columns of one row, that a Gaussian's
  footprint reaches (the tile kernels' pixel bounds);
- :func:`load_cam`: one Gaussian's centre in the camera frame and its raw rotation and scale, in float64;
- :func:`screen_cov`: the EWA projection's intermediates of one Gaussian, shared by the forward and the
  hand-written backward projection.

A ``@wp.func`` is compiled into every Warp module whose kernels call it, so these helpers have no module of their
own to load. They are called from Warp kernels and functions only, not from Python.
"""

from __future__ import annotations

from typing import Any

import warp as wp

# compositing thresholds (Kerbl et al. 2023): alpha below 1/255 skipped, alpha clamped to 0.99, a pixel stops before
# T < 1e-4; depth = sum w z / sum w only where sum w >= 1e-6
ALPHA_MIN = wp.constant(1.0 / 255.0)
ALPHA_MAX = wp.constant(0.99)
T_MIN = wp.constant(1.0e-4)
DEPTH_ALPHA_MIN = wp.constant(1.0e-6)

# Only the hand-written forward and backward kernels are used: skip generating Warp adjoints.
wp.set_module_options({"enable_backward": False})


@wp.func
def pixel_of(tid: int, width: int, height: int, tile_size: int, tiles_x: int, stripe: int, nstripes: int):
    """Pixel of thread ``tid`` of a per-pixel launch over stripe ``stripe`` of ``nstripes`` (tile rows ``stripe``,
    ``stripe + nstripes``, ...; the mapping of :mod:`gausslite.render.warp_kernels`) of a ``width`` x ``height``
    image (px) cut into ``tile_size`` px tiles, ``tiles_x`` per row. Returns ``wp.vec3i(px, py, tile)``: the column
    and row (int32, px; ``py`` may be ``>= height`` in the last tile row, which the caller skips) and the row-major
    tile index."""
    local_row = tid // width
    px = tid - local_row * width
    tr_local = local_row // tile_size
    py = (tr_local * nstripes + stripe) * tile_size + (local_row - tr_local * tile_size)
    return wp.vec3i(px, py, (py // tile_size) * tiles_x + px // tile_size)


# ------------------------------------------------------------------------------------ CPU tile kernels
#
# On CPU a Warp launch is a serial loop over thread ids, so the per-pixel kernels (``rasterize_fwd_kernel`` /
# ``rasterize_bwd_kernel``) evaluate every (pixel, Gaussian) pair of a tile even though a Gaussian typically covers
# a small part of each tile it is binned to. The tile kernels (``rasterize_fwd_tile_kernel`` /
# ``rasterize_bwd_tile_kernel``) run one *tile* per thread, Gaussian-outer and
# pixel-inner: for each Gaussian of the tile list only the pixels inside a conservative row-wise
# bound of its ``power >= p_min - 0.01`` ellipse (computed in float64, widened by 0.5 px) are
# visited, and each visited pair is evaluated with exactly the float32 arithmetic and tests of the
# per-pixel kernels. Every pixel still composites its Gaussians in list order with the same early
# termination, so the outputs are identical (bit for bit in the forward pass); the backward pass
# sums one tile's pixel contributions to a Gaussian locally before writing them once.
# Per-pixel running state lives in global per-pixel arrays, so the kernels are race free on any
# device, but they are only launched on CPU.


@wp.func
def tile_rows(vv: float, ky1: float, ky0: float, y0: int, y1: int):
    """Rows ``[ya, yb]`` of the tile rows ``[y0, y1]`` (inclusive, px) that a Gaussian's footprint reaches: those
    whose row offset ``dy = vv - py`` satisfies ``ky0 - ky1 dy^2 >= 0``, widened by 0.5 px. ``vv`` is the
    Gaussian's row centre (float32, px); ``ky1`` (1) and ``ky0`` (px^2) are its ``gdata`` row-span coefficients
    ``k1``, ``k0`` (columns 14, 15; :func:`~gausslite.render.warp_kernels_fwd.pack_gdata_kernel`). Returns
    ``wp.vec2i(ya, yb)`` (int32); empty if ``ya > yb``."""
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
def row_span(cx: float, half2: float, x0: int, x1: int):
    """Columns ``[xa, xb]`` of the tile columns ``[x0, x1]`` (inclusive, px) within ``sqrt(half2) + 0.5`` px of
    ``cx``: on a row at offset ``dy`` from a Gaussian's centre, ``cx = u + ks dy`` (float32, px) is the footprint's
    centre and ``half2 = k0 - k1 dy^2`` (float32, px^2) its squared half-width. Returns ``wp.vec2i(xa, xb)``
    (int32); empty if ``half2 < 0`` or ``xa > xb``."""
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
def load_cam(
    means: wp.array2d(dtype=Any),
    quats: wp.array2d(dtype=Any),
    log_scales: wp.array2d(dtype=Any),
    i: int,
    rot: wp.mat33d,
    trans: wp.vec3d,
):
    """Row ``i`` of the ``(N, 3)`` ``means`` (world frame, metres), ``(N, 4)`` ``quats`` (w, x, y, z; not
    necessarily unit) and ``(N, 3)`` ``log_scales`` (log metres), float32 or float64, read in float64. ``rot``
    (``wp.mat33d``) and ``trans`` (``wp.vec3d``, metres) map world to camera. Returns ``(p, q, ls)``: the
    camera-frame centre ``rot @ mean + trans`` (``wp.vec3d``, metres, OpenCV axes), the raw quaternion
    (``wp.vec4d``) and the log-scales (``wp.vec3d``)."""
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
def screen_cov(rot: wp.mat33d, q: wp.vec4d, ls: wp.vec3d, xs: wp.float64, ys: wp.float64, zs: wp.float64,
               width: int, height: int, intr: wp.vec4d, eps2d: wp.float64):
    """The projection's shared intermediates of one Gaussian at camera point (xs, ys, zs) (float64, metres; ``zs >
    0``), with ``rot`` the world-to-camera rotation, ``q`` its raw quaternion (w, x, y, z) and ``ls`` its log-scales
    (as :func:`load_cam` returns them), a ``width`` x ``height`` px image, ``intr = (fx, fy, cx, cy)`` (px) and the
    low-pass ``eps2d`` (px^2). All in float64; returns, in order: the quaternion norm ``qlen`` and divisor ``qden``
    (scalars), the unit quaternion ``qn`` (``wp.vec4d``), ``(Rq, exp(ls), M)`` of :func:`_cam_cov` (``wp.mat33d``,
    ``wp.vec3d`` metres, ``wp.mat33d``), the clamp limits ``lim`` (``wp.vec4d``, :func:`_tan_limits`),
    ``rz = 1 / zs`` (1/metres), the clamped ``txc = x/z``, ``tyc = y/z`` (scalars) and the outputs of
    :func:`_ewa_cov2d` at them: the Jacobian rows ``j0``, ``j1`` and ``w0 = cov j0``, ``w1 = cov j1``
    (``wp.vec3d``) and the screen covariance ``abc = (a, b, c)`` (``wp.vec3d``, px^2)."""
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
