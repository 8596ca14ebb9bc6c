"""Per-pixel Warp kernels for tile-based Gaussian rasterization (forward and backward).

Port of the per-pixel loops of Kerbl et al. 2023 (diff-gaussian-rasterization ``renderCUDA`` /
``renderCUDA`` backward) in the gsplat data layout, written without Warp tile primitives so the
same source runs correctly on CPU (one thread per pixel, serial per launch) and CUDA.

Per-Gaussian data is packed into one float32 row
``gdata[g] = (u_hi, v_hi, a, b, c, o, r, g, b, z, u_lo, v_lo, p_min, 0, 0, 0)`` (64 bytes): pixel centre (u, v) stored as a
float32 pair ``u = u_hi + u_lo`` (``u_hi - px`` is exact, so the pixel offset keeps ~float64
precision at no cost; plain float32 u would carry ~1e-5 px rounding at u ~ 300), conic (a, b, c) with Mahalanobis form ``a dx^2 + 2 b dx dy + c dy^2``,
post-sigmoid opacity o, colour rgb, camera depth z (metres) and
``p_min = ln(1 / (255 o)) - 1e-3``: a conservative pre-test (power < p_min implies
alpha < 1/255) that skips the exp for the many pixel/Gaussian pairs far outside the footprint;
the exact ``alpha < 1/255`` test still decides the remaining pairs, so semantics are unchanged. Gradients are written to a
(M, 10) buffer with the first ten columns of that layout (d/du, d/dv, ...).

The footprint test of each (pixel, Gaussian) pair reads a per-intersection copy
``idata[j] = (u_hi, v_hi, a, b, c, u_lo, v_lo, p_min)`` stored in the sorted tile order, so the
inner loop streams through contiguous memory; ``gdata[gids[j]]`` is only read for pairs that
pass the test.

The image is processed in horizontal stripes: launch ``stripe`` of ``nstripes`` covers tile rows
``stripe, stripe + nstripes, ...`` so several CPU launches (one per Python thread) can run in
parallel with balanced work. Thread ``tid`` of a launch maps to pixel
``py = ((tid // W) // ts * nstripes + stripe) * ts + (tid // W) % ts``, ``px = tid % W``.
"""

from __future__ import annotations

import threading

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
