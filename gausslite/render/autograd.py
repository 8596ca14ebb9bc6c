"""``torch.autograd.Function`` wrapping the Warp rasterization kernels.

Forward/backward launch :mod:`gausslite.render.warp_kernels` on the device of the input tensors
(zero-copy through ``wp.from_torch``): one launch packs the per-Gaussian ``gdata`` rows, then the
compositing kernels run (per-tile kernels on CPU, per-pixel kernels on CUDA). On CPU the image is
split into ``num_threads`` interleaved stripes of tile rows, each launched from its own Python thread (Warp releases the GIL during CPU
launches); in the backward pass every thread accumulates into its own gradient buffer and the
buffers are summed afterwards, because CPU atomics are not safe across concurrent launches.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import torch
import warp as wp

from . import warp_kernels as wk

_IDATA_COLS = [0, 1, 2, 3, 4, 10, 11, 12]
_pool: ThreadPoolExecutor | None = None
_pool_size = 0


def default_num_threads() -> int:
    """Default CPU launch parallelism: ``min(2, os.cpu_count())``."""
    return max(1, min(2, os.cpu_count() or 1))


def _run_parallel(fns):
    """Run the callables in ``fns`` concurrently (persistent pool) and re-raise any error."""
    global _pool, _pool_size
    if len(fns) == 1:
        fns[0]()
        return
    if _pool is None or _pool_size < len(fns):
        if _pool is not None:
            _pool.shutdown(wait=True)
        _pool = ThreadPoolExecutor(max_workers=len(fns), thread_name_prefix="gausslite-raster")
        _pool_size = len(fns)
    futs = [_pool.submit(f) for f in fns]
    for f in futs:
        f.result()


def _stripe_dim(stripe: int, nstripes: int, tiles_y: int, tile_size: int, width: int) -> int:
    n_rows = (tiles_y - stripe + nstripes - 1) // nstripes
    return max(n_rows, 0) * tile_size * width


def _wp_device(dev: torch.device) -> str:
    if dev.type == "cuda":
        return f"cuda:{dev.index if dev.index is not None else torch.cuda.current_device()}"
    return "cpu"


def _pack_gdata(means2d, conics, opacities, colors, depths) -> torch.Tensor:
    """(M, 16) float32 ``gdata`` rows (layout in :mod:`warp_kernels`), built by one Warp launch."""
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
        wp.launch(wk.pack_gdata_kernel, dim=M, inputs=[wp.from_torch(t) for t in ins],
                  outputs=[wp.from_torch(gdata)], device=wdev,
                  stream=wp.stream_from_torch(dev) if dev.type == "cuda" else None)
    return gdata


class RasterizeWarp(torch.autograd.Function):
    """Differentiable compositing of projected Gaussians with the Warp kernels.

    forward(means2d (M,2), conics (M,3), opacities (M,), colors (M,3), depths (M,), gids
    (n_isect,) int32, tile_start/tile_end (n_tiles,) int32, width, height, tile_size, tiles_x,
    tiles_y, num_threads) -> (color (H,W,3), depth_sum (H,W), alpha (H,W)), all float32 with the
    semantics of :func:`gausslite.render.reference.rasterize_reference`. Gradients are returned in
    the dtype of each input.
    """

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, gids, tile_start, tile_end,
                width, height, tile_size, tiles_x, tiles_y, num_threads):
        dev = means2d.device
        M = means2d.shape[0]
        gdata = _pack_gdata(means2d, conics, opacities, colors, depths)
        cpu = dev.type != "cuda"
        HW = height * width
        if cpu:
            # tile kernels: read gdata through gids and initialise every pixel themselves
            idata = gdata.new_empty(0, 8)
            feat = torch.empty(HW, 5, dtype=torch.float32, device=dev)
            T = torch.empty(HW, dtype=torch.float32, device=dev)
            last = torch.empty(HW, dtype=torch.int32, device=dev)
        else:
            # per-intersection copy of the footprint columns, in sorted tile order (see warp_kernels)
            idata = gdata[:, _IDATA_COLS].index_select(0, gids.to(torch.int64)).contiguous()
            feat = torch.zeros(HW, 5, dtype=torch.float32, device=dev)
            T = torch.ones(HW, dtype=torch.float32, device=dev)
            last = torch.zeros(HW, dtype=torch.int32, device=dev)
        n_isect = gids.numel()
        nstripes = 1 if dev.type == "cuda" else max(1, min(int(num_threads), tiles_y))
        if n_isect > 0 and M > 0:
            wdev = _wp_device(dev)
            wk.ensure_loaded(wdev)
            a_g = wp.from_torch(gdata)
            a_i = wp.from_torch(idata)
            a_ids = wp.from_torch(gids)
            a_ts = wp.from_torch(tile_start)
            a_te = wp.from_torch(tile_end)
            a_f = wp.from_torch(feat)
            a_T = wp.from_torch(T)
            a_l = wp.from_torch(last)
            stream = wp.stream_from_torch(dev) if dev.type == "cuda" else None

            def launch(s):
                if cpu:
                    dim = _stripe_dim(s, nstripes, tiles_y, 1, tiles_x)
                    if dim > 0:
                        wp.launch(
                            wk.rasterize_fwd_tile_kernel, dim=dim,
                            inputs=[a_g, a_ids, a_ts, a_te, width, height, tile_size, tiles_x, s,
                                    nstripes],
                            outputs=[a_f, a_T, a_l], device=wdev,
                        )
                    return
                dim = _stripe_dim(s, nstripes, tiles_y, tile_size, width)
                if dim == 0:
                    return
                wp.launch(
                    wk.rasterize_fwd_kernel, dim=dim,
                    inputs=[a_g, a_i, a_ids, a_ts, a_te, width, height, tile_size, tiles_x, s, nstripes],
                    outputs=[a_f, a_T, a_l], device=wdev, stream=stream,
                )

            _run_parallel([lambda s=s: launch(s) for s in range(nstripes)])
        elif cpu:
            feat.zero_()
            T.fill_(1.0)
            last.zero_()
        ctx.save_for_backward(gdata, idata, gids, tile_start, T, last)
        ctx.dims = (width, height, tile_size, tiles_x, tiles_y, nstripes)
        ctx.in_dtypes = (means2d.dtype, conics.dtype, opacities.dtype, colors.dtype, depths.dtype)
        feat = feat.reshape(height, width, 5)
        return feat[..., :3], feat[..., 3], feat[..., 4]

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha):
        gdata, idata, gids, tile_start, T, last = ctx.saved_tensors
        width, height, tile_size, tiles_x, tiles_y, nstripes = ctx.dims
        dev = gdata.device
        M = gdata.shape[0]
        HW = height * width
        zeros = lambda *s: torch.zeros(*s, dtype=torch.float32, device=dev)  # noqa: E731
        gc = g_color if g_color is not None else zeros(height, width, 3)
        gd = g_depth if g_depth is not None else zeros(height, width)
        ga = g_alpha if g_alpha is not None else zeros(height, width)
        gfeat = torch.cat(
            [gc.reshape(HW, 3), gd.reshape(HW, 1), ga.reshape(HW, 1)], dim=1
        ).to(torch.float32).contiguous()
        bufs = [zeros(M, 10) for _ in range(nstripes)]
        if gids.numel() > 0 and M > 0:
            wdev = _wp_device(dev)
            wk.ensure_loaded(wdev)
            a_g = wp.from_torch(gdata)
            a_i = wp.from_torch(idata)
            a_ids = wp.from_torch(gids)
            a_ts = wp.from_torch(tile_start)
            a_T = wp.from_torch(T)
            a_l = wp.from_torch(last)
            a_gf = wp.from_torch(gfeat)
            a_bufs = [wp.from_torch(b) for b in bufs]
            stream = wp.stream_from_torch(dev) if dev.type == "cuda" else None
            cpu = dev.type != "cuda"
            if cpu:
                a_st = wp.from_torch(torch.empty(HW, 12, dtype=torch.float32, device=dev))

            def launch(s):
                if cpu:
                    dim = _stripe_dim(s, nstripes, tiles_y, 1, tiles_x)
                    if dim > 0:
                        wp.launch(
                            wk.rasterize_bwd_tile_kernel, dim=dim,
                            inputs=[a_g, a_ids, a_ts, width, height, tile_size, tiles_x, s,
                                    nstripes, a_T, a_l, a_gf, a_st],
                            outputs=[a_bufs[s]], device=wdev,
                        )
                    return
                dim = _stripe_dim(s, nstripes, tiles_y, tile_size, width)
                if dim == 0:
                    return
                wp.launch(
                    wk.rasterize_bwd_kernel, dim=dim,
                    inputs=[a_g, a_i, a_ids, a_ts, width, height, tile_size, tiles_x, s, nstripes,
                            a_T, a_l, a_gf],
                    outputs=[a_bufs[s]], device=wdev, stream=stream,
                )

            _run_parallel([lambda s=s: launch(s) for s in range(nstripes)])
        grad = bufs[0]
        for b in bufs[1:]:
            grad += b
        dts = ctx.in_dtypes
        return (
            grad[:, 0:2].to(dts[0]),
            grad[:, 2:5].to(dts[1]),
            grad[:, 5].to(dts[2]),
            grad[:, 6:9].to(dts[3]),
            grad[:, 9].to(dts[4]),
            None, None, None, None, None, None, None, None, None,
        )
