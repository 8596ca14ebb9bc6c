"""``torch.autograd.Function`` wrappers of the Warp kernels (projection and rasterization).

Forward/backward launch :mod:`gausslite.render.warp_kernels` on the device of the input tensors, zero-copy: on
CPU through :func:`gausslite.render.launch.launch_cpu` (replayed launches), on CUDA through ``wp.from_torch``.

:class:`RasterizeWarp`: one launch packs the per-Gaussian ``gdata`` rows, then the compositing
kernels run (per-tile kernels on CPU, per-pixel kernels on CUDA). On CPU the image is split into
``num_threads`` interleaved stripes of tile rows, each launched from its own Python thread (Warp
releases the GIL during CPU launches); in the backward pass every thread accumulates into its own
gradient buffer and one launch sums the buffers into the input gradients, because CPU atomics are
not safe across concurrent launches.

:class:`ProjectWarp` (CPU): the EWA projection of
:func:`gausslite.render.projection.project_gaussians` as one forward and one backward launch.
"""

from __future__ import annotations

import os

import torch
import warp as wp

from . import native_pack as pk
from . import simd_kernels as sk
from . import simd_projection as sp
from . import warp_kernels as wk
from .launch import Vec, launch_cpu
from .projection import Projection

_IDATA_COLS = [0, 1, 2, 3, 4, 10, 11, 12]


def default_num_threads() -> int:
    """Default CPU launch parallelism: ``min(2, os.cpu_count())``."""
    return max(1, min(2, os.cpu_count() or 1))


def _stripe_dim(stripe: int, nstripes: int, tiles_y: int, tile_size: int, width: int) -> int:
    n_rows = (tiles_y - stripe + nstripes - 1) // nstripes
    return max(n_rows, 0) * tile_size * width


def _wp_device(dev: torch.device) -> str:
    if dev.type == "cuda":
        return f"cuda:{dev.index if dev.index is not None else torch.cuda.current_device()}"
    return "cpu"


def _launch_rows(kernel, n: int, num_threads: int, inputs, outputs) -> None:
    """Launch a per-row CPU kernel with a trailing-``offset`` argument (between ``inputs`` and
    ``outputs``) over rows [0, n), split into ``num_threads`` contiguous chunks run concurrently (tensors and
    scalars as :func:`~gausslite.render.launch.launch_cpu` takes them)."""
    k = max(1, min(int(num_threads), n // 4096 + 1))
    bounds = [n * s // k for s in range(k + 1)]

    def run(s):
        launch_cpu(kernel, bounds[s + 1] - bounds[s], list(inputs) + [bounds[s]] + list(outputs))

    wk.run_parallel([lambda s=s: run(s) for s in range(k)])


def _launch_lanes(kernel, n: int, num_threads: int, inputs, outputs) -> None:
    """Launch a :mod:`~gausslite.render.simd_projection` kernel over rows [0, n) as :func:`_launch_rows` does
    (contiguous chunks run concurrently), one kernel thread per :data:`~gausslite.render.simd_projection.LANES`
    rows: each chunk's ``offset`` and ``end`` go between ``inputs`` and ``outputs``, tensors as their data
    pointers (C-contiguous rows, checked)."""
    k = max(1, min(int(num_threads), n // 4096 + 1))
    bounds = [n * s // k for s in range(k + 1)]

    def ptr(a):
        if isinstance(a, torch.Tensor):
            if a.device.type != "cpu" or not a.is_contiguous():
                raise ValueError("the SIMD projection takes C-contiguous CPU tensors")
            return a.data_ptr()
        return a

    ins, outs = [ptr(a) for a in inputs], [ptr(a) for a in outputs]

    def run(s):
        rows = bounds[s + 1] - bounds[s]
        launch_cpu(kernel, -(-rows // sp.LANES), ins + [bounds[s], bounds[s + 1]] + outs)

    wk.run_parallel([lambda s=s: run(s) for s in range(k)])


def _pixel_grad(g, HW: int, cols: int, dev) -> torch.Tensor:
    """Incoming gradient of a (H, W[, 3]) output as a float32 (HW, cols) or (HW,) tensor that
    Warp can index (zeros if None; expanded / zero-stride tensors are materialised)."""
    shape = (HW, cols) if cols > 1 else (HW,)
    if g is None:
        return torch.zeros(shape, dtype=torch.float32, device=dev)
    g = g.to(torch.float32).reshape(shape)
    if 0 in g.stride() or g.stride()[-1] != 1:
        g = g.contiguous()
    return g


def _pack_gdata(means2d, conics, opacities, colors, depths, opacity_is_logit: bool = False) -> torch.Tensor:
    """(M, 16) float32 ``gdata`` rows (layout in :mod:`warp_kernels`), built by one launch (on CPU the native loop of
    :mod:`~gausslite.render.native_pack`, elsewhere the Warp kernel).

    ``opacities`` are post-sigmoid opacities, or logits (sigmoid applied in the kernel) if
    ``opacity_is_logit``."""
    ins = [t.detach() for t in (means2d, conics, opacities, colors, depths)]
    dt = ins[0].dtype
    if dt not in (torch.float32, torch.float64) or any(t.dtype != dt for t in ins):
        ins = [t.to(torch.float64) for t in ins]
    ins = [t.contiguous() for t in ins]
    M = ins[0].shape[0]
    dev = ins[0].device
    gdata = torch.empty(M, 16, dtype=torch.float32, device=dev)
    if M > 0:
        wdev = _wp_device(dev)
        wk.ensure_loaded(wdev)
        if dev.type == "cpu":
            wk.ensure_module_loaded(pk.__name__, "cpu")
            launch_cpu(pk.pack_gdata_native_kernel, -(-M // pk.CHUNK),
                       [t.data_ptr() for t in ins] + [int(ins[0].dtype == torch.float64), int(bool(opacity_is_logit)),
                                                      M, gdata.data_ptr()])
        else:
            wp.launch(wk.pack_gdata_kernel, dim=M,
                      inputs=[wp.from_torch(t) for t in ins] + [int(bool(opacity_is_logit))],
                      outputs=[wp.from_torch(gdata)], device=wdev, stream=wp.stream_from_torch(dev))
    return gdata


def _unpack_grads(bufs: torch.Tensor, opacities: torch.Tensor, opacity_is_logit: bool, dtypes):
    """Sum the (S, M, 10) float32 per-thread gradient buffers into the gradients of (means2d,
    conics, opacities, colors, depths), each in its input dtype (opacity gradient w.r.t. the logits
    if ``opacity_is_logit``): one launch (on CPU the native loop of :mod:`~gausslite.render.native_pack`)."""
    M = bufs.shape[1]
    dev = bufs.device
    shapes = ((M, 2), (M, 3), (M,), (M, 3), (M,))
    dt = dtypes[0]
    if M > 0 and dt in (torch.float32, torch.float64) and all(d == dt for d in dtypes) \
            and opacities.dtype == dt:
        outs = [torch.empty(shp, dtype=dt, device=dev) for shp in shapes]
        wdev = _wp_device(dev)
        wk.ensure_loaded(wdev)
        ops = opacities.detach().contiguous()
        if dev.type == "cpu":
            wk.ensure_module_loaded(pk.__name__, "cpu")
            bufs = bufs.contiguous()
            launch_cpu(pk.unpack_grads_native_kernel, -(-M // pk.CHUNK),
                       [bufs.data_ptr(), bufs.shape[0], M, ops.data_ptr(), int(dt == torch.float64),
                        int(bool(opacity_is_logit))] + [t.data_ptr() for t in outs])
        else:
            wp.launch(wk.unpack_grads_kernel, dim=M, inputs=[wp.from_torch(bufs), wp.from_torch(ops),
                                                             int(bool(opacity_is_logit))],
                      outputs=[wp.from_torch(t) for t in outs], device=wdev, stream=wp.stream_from_torch(dev))
        return tuple(outs)
    grad = bufs.sum(0)
    g_op = grad[:, 5]
    if opacity_is_logit:
        o = torch.sigmoid(opacities.detach().to(torch.float64))
        g_op = g_op.to(torch.float64) * o * (1.0 - o)
    return (grad[:, 0:2].to(dtypes[0]), grad[:, 2:5].to(dtypes[1]), g_op.to(dtypes[2]),
            grad[:, 6:9].to(dtypes[3]), grad[:, 9].to(dtypes[4]))


class RasterizeWarp(torch.autograd.Function):
    """Differentiable compositing of projected Gaussians with the Warp kernels.

    forward(means2d (M,2), conics (M,3), opacities (M,), colors (M,3), depths (M,), gids
    (n_isect,) int32, tile_start/tile_end (n_tiles,) int32, width, height, tile_size, tiles_x,
    tiles_y, num_threads[, opacity_is_logit=False, background=None]) -> (color (H,W,3),
    depth_sum (H,W), alpha (H,W)), all float32 with the semantics of
    :func:`gausslite.render.reference.rasterize_reference`. Gradients are returned in the dtype of
    each input.

    Optional (CPU only): ``opacity_is_logit=True`` takes opacity logits (sigmoid applied inside);
    ``background`` ((3,) float32 tensor) makes the outputs the finished images of
    :func:`gausslite.render.api.rasterize`: colour composited over the background and the
    normalised depth (``depth_sum / alpha`` where alpha >= 1e-6, else 0) instead of depth_sum.
    ``cpu_kernel`` (CPU only): ``"simd"`` (default) runs the vectorised tile kernels of
    :mod:`gausslite.render.simd_kernels` when ``tile_size`` <= 16, ``"tile"`` the Warp tile kernels
    (the slower path they replace, kept for comparison and for wider tiles).
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, gids, tile_start, tile_end,
                width, height, tile_size, tiles_x, tiles_y, num_threads, opacity_is_logit=False,
                background=None, cpu_kernel="simd"):
        sk.check_cpu_kernel(cpu_kernel)
        dev = means2d.device
        M = means2d.shape[0]
        cpu = dev.type != "cuda"
        composite = background is not None
        if not cpu and composite:
            raise ValueError("RasterizeWarp: background compositing is only implemented on CPU")
        gdata = _pack_gdata(means2d, conics, opacities, colors, depths, opacity_is_logit)
        HW = height * width
        n_isect = gids.numel()
        nstripes = 1 if not cpu else max(1, min(int(num_threads), tiles_y))
        wdev = _wp_device(dev)
        wk.ensure_loaded(wdev)
        ctx.dims = (width, height, tile_size, tiles_x, tiles_y, nstripes)
        ctx.in_dtypes = (means2d.dtype, conics.dtype, opacities.dtype, colors.dtype, depths.dtype)
        ctx.opacity_is_logit = bool(opacity_is_logit)
        if cpu:
            # tile kernels: read gdata through gids and initialise every pixel themselves
            simd = cpu_kernel == "simd" and tile_size <= sk.MAX_TILE
            ctx.simd = simd
            fwd_kernel = sk.rasterize_fwd_tile_simd_kernel if simd else wk.rasterize_fwd_tile_kernel
            c4 = torch.empty(HW, 4, dtype=torch.float32, device=dev)
            A = torch.empty(HW, dtype=torch.float32, device=dev)
            T = torch.empty(HW, dtype=torch.float32, device=dev)
            last = torch.empty(HW, dtype=torch.int32, device=dev)
            bg = wp.vec3(*(background.detach().to(torch.float32).cpu().tolist() if composite else (0.0,) * 3))
            outs = [Vec(c4, wp.vec4), A, T, last]

            def launch_stripe(s):
                launch_cpu(fwd_kernel, _stripe_dim(s, nstripes, tiles_y, 1, tiles_x),
                           [gdata, gids, tile_start, tile_end, width, height, tile_size, tiles_x, s, nstripes,
                            int(composite), bg] + outs)

            wk.run_parallel([lambda s=s: launch_stripe(s) for s in range(nstripes)])
            ctx.composite = composite
            ctx.bg = bg
            ctx.save_for_backward(gdata, gids, tile_start, T, last, c4, A, opacities)
            c4 = c4.reshape(height, width, 4)
            return c4[..., :3], c4[..., 3], A.reshape(height, width)

        # CUDA: per-pixel kernels on a per-intersection copy of the footprint columns
        idata = gdata[:, _IDATA_COLS].index_select(0, gids.to(torch.int64)).contiguous()
        feat = torch.zeros(HW, 5, dtype=torch.float32, device=dev)
        T = torch.ones(HW, dtype=torch.float32, device=dev)
        last = torch.zeros(HW, dtype=torch.int32, device=dev)
        if n_isect > 0 and M > 0:
            wp.launch(
                wk.rasterize_fwd_kernel, dim=_stripe_dim(0, 1, tiles_y, tile_size, width),
                inputs=[wp.from_torch(gdata), wp.from_torch(idata), wp.from_torch(gids),
                        wp.from_torch(tile_start), wp.from_torch(tile_end), width, height,
                        tile_size, tiles_x, 0, 1],
                outputs=[wp.from_torch(feat), wp.from_torch(T), wp.from_torch(last)], device=wdev,
                stream=wp.stream_from_torch(dev),
            )
        ctx.composite = False
        ctx.save_for_backward(gdata, gids, tile_start, T, last, idata, opacities)
        feat = feat.reshape(height, width, 5)
        return feat[..., :3], feat[..., 3], feat[..., 4]

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha):
        width, height, tile_size, tiles_x, tiles_y, nstripes = ctx.dims
        dev = ctx.saved_tensors[0].device
        HW = height * width
        cpu = dev.type != "cuda"
        wdev = _wp_device(dev)
        wk.ensure_loaded(wdev)
        tail = (None,) * 12
        if cpu:
            gdata, gids, tile_start, T, last, c4, A, opacities = ctx.saved_tensors
            M = gdata.shape[0]
            gc = _pixel_grad(g_color, HW, 3, dev)
            gd = _pixel_grad(g_depth, HW, 1, dev)
            ga = _pixel_grad(g_alpha, HW, 1, dev)
            bufs = torch.zeros(nstripes, M, 10, dtype=torch.float32, device=dev)
            ins = [T, last, int(ctx.composite), ctx.bg, Vec(c4, wp.vec4), A, gc, gd, ga,
                   Vec(torch.empty(HW, 4, dtype=torch.float32, device=dev), wp.vec4),
                   Vec(torch.empty(HW, 2, dtype=torch.float32, device=dev), wp.vec2)]
            bwd_kernel = sk.rasterize_bwd_tile_simd_kernel if ctx.simd else wk.rasterize_bwd_tile_kernel

            def launch_stripe(s):
                launch_cpu(bwd_kernel, _stripe_dim(s, nstripes, tiles_y, 1, tiles_x),
                           [gdata, gids, tile_start, width, height, tile_size, tiles_x, s, nstripes] + ins
                           + [bufs[s]])

            wk.run_parallel([lambda s=s: launch_stripe(s) for s in range(nstripes)])
            return _unpack_grads(bufs, opacities, ctx.opacity_is_logit, ctx.in_dtypes) + tail

        gdata, gids, tile_start, T, last, idata, opacities = ctx.saved_tensors
        M = gdata.shape[0]
        zeros = lambda *s: torch.zeros(*s, dtype=torch.float32, device=dev)  # noqa: E731
        gc = g_color if g_color is not None else zeros(height, width, 3)
        gd = g_depth if g_depth is not None else zeros(height, width)
        ga = g_alpha if g_alpha is not None else zeros(height, width)
        gfeat = torch.cat(
            [gc.reshape(HW, 3), gd.reshape(HW, 1), ga.reshape(HW, 1)], dim=1
        ).to(torch.float32).contiguous()
        bufs = zeros(1, M, 10)
        if gids.numel() > 0 and M > 0:
            wp.launch(
                wk.rasterize_bwd_kernel, dim=_stripe_dim(0, 1, tiles_y, tile_size, width),
                inputs=[wp.from_torch(gdata), wp.from_torch(idata), wp.from_torch(gids),
                        wp.from_torch(tile_start), width, height, tile_size, tiles_x, 0, 1,
                        wp.from_torch(T), wp.from_torch(last), wp.from_torch(gfeat)],
                outputs=[wp.from_torch(bufs[0])], device=wdev, stream=wp.stream_from_torch(dev),
            )
        return _unpack_grads(bufs, opacities, ctx.opacity_is_logit, ctx.in_dtypes) + tail


class ProjectWarp(torch.autograd.Function):
    """EWA projection with the Warp kernels (CPU): same outputs and gradients as
    :func:`gausslite.render.projection.project_gaussians` (see ``project_fwd_kernel`` /
    ``project_bwd_kernel`` in :mod:`warp_kernels`), evaluated in float64.

    forward(means (N,3), quats (N,4), log_scales (N,3) -- one dtype, float32 or float64 --,
    viewmat (4,4) world-to-camera, K (3,3) intrinsics in pixels, width, height, near, far, eps2d
    [, num_threads=1, simd=True, cam_of_row=None]) -> (means2d (N,2), conics (N,3), depths (N,), radii (N,)
    int32), float outputs in the input dtype. viewmat and K get no gradient. The rows are split into
    ``num_threads`` contiguous chunks launched concurrently. ``simd`` (default True): the SIMD kernels of
    :mod:`gausslite.render.simd_projection` (eight Gaussians per call); False: the scalar Warp kernels they
    replace (the parity tests' reference). With ``cam_of_row`` ((N,) int32, SIMD only), ``viewmat`` (B,4,4) and
    ``K`` (B,3,3) are B cameras and row i is projected by camera ``cam_of_row[i]`` (the bands of a rolling
    shutter in one launch).
    """

    @staticmethod
    def forward(ctx, means, quats, log_scales, viewmat, K, width, height, near, far, eps2d,
                num_threads=1, simd=True, cam_of_row=None):
        dt = means.dtype
        N = means.shape[0]
        ins = [t.detach().contiguous() for t in (means, quats, log_scales)]
        tail = [int(width), int(height), wp.float64(near), wp.float64(far), wp.float64(eps2d)]
        if simd:
            many = cam_of_row is not None
            cams = sp.camera_table(viewmat if many else [viewmat], K if many else [K], width, height)
            if many and (cam_of_row.dtype != torch.int32 or tuple(cam_of_row.shape) != (N,)
                         or len(cams) != len(K)):
                raise ValueError("cam_of_row must be (N,) int32 with (B, 4, 4) viewmats and (B, 3, 3) Ks")
            rows = cam_of_row.contiguous() if many else None
            consts = [int(dt == torch.float64), cams, rows.data_ptr() if many else 0] + tail
            ctx.keep = (cams, rows)  # the pointers the backward reads
        else:
            if cam_of_row is not None:
                raise ValueError("several cameras (cam_of_row) need the SIMD kernels (simd=True)")
            vm = viewmat.detach().to(torch.float64).cpu().tolist()
            k = K.detach().to(torch.float64).cpu().tolist()
            consts = [wp.mat33d(*(vm[r][c] for r in range(3) for c in range(3))),
                      wp.vec3d(vm[0][3], vm[1][3], vm[2][3]), wp.vec4d(k[0][0], k[1][1], k[0][2], k[1][2])] + tail
        means2d = torch.empty(N, 2, dtype=dt)
        conics = torch.empty(N, 3, dtype=dt)
        depths = torch.empty(N, dtype=dt)
        radii = torch.empty(N, dtype=torch.int32)
        if N > 0:
            wk.ensure_loaded("cpu")
            if simd:
                _launch_lanes(sp.project_fwd_simd_kernel, N, num_threads, ins + consts,
                              [means2d, conics, depths, radii])
            else:
                _launch_rows(wk.project_fwd_kernel, N, num_threads, ins + consts, [means2d, conics, depths, radii])
        ctx.consts = consts
        ctx.num_threads = num_threads
        ctx.simd = bool(simd)
        ctx.save_for_backward(*ins)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, g_radii):
        means, quats, log_scales = ctx.saved_tensors
        dt = means.dtype
        N = means.shape[0]
        tail = (None,) * 10
        if N == 0 or not any(ctx.needs_input_grad[:3]):
            return (torch.zeros_like(means), torch.zeros_like(quats), torch.zeros_like(log_scales)) + tail

        def prep(g, shape):
            if g is None:
                return torch.zeros(shape, dtype=dt)
            return g.to(dt).contiguous()

        outs = [torch.empty_like(means), torch.empty_like(quats), torch.empty_like(log_scales)]
        wk.ensure_loaded("cpu")
        grads = [prep(g_means2d, (N, 2)), prep(g_conics, (N, 3)), prep(g_depths, (N,))]
        if ctx.simd:
            _launch_lanes(sp.project_bwd_simd_kernel, N, ctx.num_threads, [means, quats, log_scales] + ctx.consts,
                          grads + outs)
        else:
            _launch_rows(wk.project_bwd_kernel, N, ctx.num_threads, [means, quats, log_scales] + ctx.consts,
                         grads + outs)
        return tuple(outs) + tail


def project_gaussians_warp(means, quats, log_scales, viewmat, K, width, height, near=0.01, far=1e4,
                           eps2d=0.3, num_threads=1, simd=True, cam_of_row=None) -> Projection:
    """:func:`gausslite.render.projection.project_gaussians` computed by :class:`ProjectWarp`
    (CPU, float32/float64 inputs of one dtype; same argument conventions; ``num_threads``
    concurrent launches; ``simd``: the SIMD kernels, else the scalar Warp kernels; ``cam_of_row``: each row's
    camera among B given as ``viewmat`` (B, 4, 4) and ``K`` (B, 3, 3), see :class:`ProjectWarp`).

    Raises:
        ValueError: ``cam_of_row`` without ``simd``, or not (N,) int32 with one camera per viewmat and K.
    """
    means2d, conics, depths, radii = ProjectWarp.apply(means, quats, log_scales, viewmat, K, width,
                                                       height, near, far, eps2d, int(num_threads), bool(simd),
                                                       cam_of_row)
    return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii)
