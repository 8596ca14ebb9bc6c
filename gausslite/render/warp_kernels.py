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
thread, Gaussian-outer) replace the per-pixel kernels; those remain the CUDA path. The CPU
tile kernels keep colour + depth sum as one ``vec4`` per pixel (and can finish the image: background
compositing and depth normalisation), and their backward keeps two floats of running state per
pixel (see :func:`rasterize_bwd_tile_kernel`). :func:`pack_gdata_kernel` can apply the opacity
sigmoid and :func:`unpack_grads_kernel` sums the per-thread gradient buffers (and applies the
sigmoid derivative), so that no per-element torch op remains around the CPU launches.

:func:`project_fwd_kernel` / :func:`project_bwd_kernel` (the scalar CPU path of
:class:`gausslite.render.autograd.ProjectWarp`) replace the vectorised torch code of that stage; see its section
comment. CPU binning and frustum culling are native loops (:mod:`gausslite.render.native_binning`,
:func:`gausslite.render.culling.frustum_cull_native_kernel`), tested against their torch references.

The image is processed in horizontal stripes: launch ``stripe`` of ``nstripes`` covers tile rows
``stripe, stripe + nstripes, ...`` so several CPU launches (one per Python thread) can run in
parallel with balanced work. Thread ``tid`` of a launch maps to pixel
``py = ((tid // W) // ts * nstripes + stripe) * ts + (tid // W) % ts``, ``px = tid % W``.

The kernels live in three modules, re-exported here: :mod:`~gausslite.render.warp_kernels_fwd` (the forward
kernels: compositing, ``gdata`` packing, projection), :mod:`~gausslite.render.warp_kernels_bwd` (their
hand-written backward kernels and the gradient unpacking) and :mod:`~gausslite.render.warp_kernels_common` (the
thresholds and the ``@wp.func`` helpers both call). Warp compiles each Python module that defines kernels as one
module, with the helpers it calls from other modules compiled into it; :func:`ensure_loaded` loads every one. This
module also runs the launches in parallel (:func:`run_parallel`).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import warp as wp

from .warp_kernels_bwd import (bwd_tile_init, project_bwd_kernel, rasterize_bwd_kernel, rasterize_bwd_tile_kernel,
                               unpack_grads_kernel)
from .warp_kernels_common import ALPHA_MAX, ALPHA_MIN, DEPTH_ALPHA_MIN, T_MIN, tile_box, vec5i
from .warp_kernels_fwd import pack_gdata_kernel, project_fwd_kernel, rasterize_fwd_kernel, rasterize_fwd_tile_kernel

#: the modules that define the rasterizer's Warp kernels (each one Warp module), loaded by :func:`ensure_loaded`
KERNEL_MODULES = ("gausslite.render.warp_kernels_fwd", "gausslite.render.warp_kernels_bwd")

_init_lock = threading.Lock()
_loaded: set[str] = set()
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_lock = threading.Lock()


def ensure_loaded(device: str) -> None:
    """Initialise Warp and compile/load the kernel modules (:data:`KERNEL_MODULES` and, on CPU,
    :mod:`gausslite.render.simd_kernels` and :mod:`gausslite.render.simd_projection`) for ``device`` once per
    process.

    Must run before concurrent launches so that two threads never compile the module at the same
    time. Compiled binaries are cached on disk by Warp (``~/.cache/warp``) across processes.
    """
    for module in KERNEL_MODULES:
        ensure_module_loaded(module, device)
    if device == "cpu":
        ensure_module_loaded("gausslite.render.simd_kernels", device)
        ensure_module_loaded("gausslite.render.simd_projection", device)


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


__all__ = ["ALPHA_MAX", "ALPHA_MIN", "DEPTH_ALPHA_MIN", "KERNEL_MODULES", "T_MIN", "bwd_tile_init", "ensure_loaded",
           "ensure_module_loaded", "pack_gdata_kernel", "project_bwd_kernel", "project_fwd_kernel",
           "rasterize_bwd_kernel", "rasterize_bwd_tile_kernel", "rasterize_fwd_kernel", "rasterize_fwd_tile_kernel",
           "run_parallel", "tile_box", "unpack_grads_kernel", "vec5i"]
