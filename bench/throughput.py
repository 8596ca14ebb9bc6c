"""Benchmark: mapping iterations per second of the mapper's own optimisation step, optionally against another commit,
with a roofline of the rasterizer's forward + backward pass.

Usage::

    python -m bench.throughput                       # 4 size cases + the keyframe case: bench/results/throughput.*
    python -m bench.throughput --against 43a6a8d     # the same cases for that commit too, case by case (A B), this/that
    python -m bench.throughput --quick               # tiny sizes (seconds), prints only unless --out is given
    python -m bench.throughput --against 718445f --isa avx2   # both trees built for AVX2: throughput_avx2.*

**What is timed.** The step the mapper runs, not a re-implementation of it: ``Mapper.optimize(n_iters=...)``, whose
iterations are :class:`gausslite.mapping.step.TrainStep`'s (the view drawn from the stored keyframes, the render as
the sensor took it, Eq. 1's loss with SSIM, backward, Adam on the map, and, as the sensor profile configures them, the
keyframe's exposure response and pose correction, motion blur and rolling-shutter bands, ROI crops in the ROI phase)
and density control on its schedule. The mapper configuration is the live agent's (``load_config().agent.mapper``:
mode ``gausslite``, one render thread, one torch thread) under the sensor profile of ``--profile`` (default
``handheld``: exposure compensation, pose refinement, motion blur, a 20 ms rolling shutter, depth weight 0.3; or
``rendered``: none of these), with ``--set KEY=VALUE`` on top.

**Cases.** ``<N>k_<W>x<H>``: N Gaussians (the cap ``budget.max_gaussians`` = N) at W × H pixels. The map is made in
the worker by mapping the first ``--keyframes`` frames of the scene below with one mapper whose seeding is switched
to 1.2 N / keyframes seeds per frame without the coverage rule (so that the cap is reached; at the cap new seeds
evict) and 2 iterations per frame (1 full-image, 1 ROI-phase);
its state (``Mapper.state_dict``) is loaded into the mapper that is timed. A timed repeat restores that state and
runs one schedule cycle, ``iters_per_frame`` iterations: ``optimize(n_iters=warmup_iters)`` (full-image
iterations) then ``optimize(n_iters=iters_per_frame - warmup_iters)`` (ROI-phase iterations: crops around the task
region, every Gaussian the crop draws updated; density control falls at iteration 20). ``--warmup`` untimed
iterations run first; each figure is the median over ``--repeats`` repeats (and ``--rounds`` workers). ``it_per_s``
is the cycle's iterations over its seconds; ``full_it_per_s`` and ``roi_it_per_s`` the two phases'.
``keyframe_agent``: one keyframe's whole ``Mapper.map_frame`` at the agent's default settings (no keyframe budget:
``iters_per_frame`` iterations; the pose it starts from, seeding with the coverage rule, the iterations, density
control and the contribution update) on the next frame of the scene after ``--keyframes`` frames mapped with
``iters_per_frame`` iterations each (a count, not a time budget: the map the call starts from is the same for a
faster and a slower tree), at the agent's default downscale; ``it_per_s`` is the call's iterations over its seconds
(``FrameStats``).

**Scene.** The embedded synthetic room (:func:`gausslite.synthetic.make_scene`, the ``circle`` trajectory, robot
``agent_a``), 72 frames once around the room at 640 × 480 (quick: 24 at 128 × 96), generated once into ``--work``,
loaded at downscale 2 or 1; the replay clock is set so the camera turns as fast as on the 300-frame circle at 30 Hz
(36 ° s⁻¹), so the motion-blur and rolling-shutter models see the motion a live robot's keyframes see. The task
region is the ground-truth ROI of ``synth-pick-object`` (:func:`gausslite.pipeline.gt_roi_fn`).

**Against another commit.** ``--against COMMIT`` checks COMMIT out with ``git worktree add`` into a temporary folder
and runs the same worker (this file) with ``PYTHONPATH`` at that folder, so ``import gausslite`` is the old code
(each worker reports ``gausslite.__file__``, which is checked). Case by case the two trees alternate (this, that, this,
that ...), ``--rounds`` times per case, so that drift of the machine falls on both. The worker uses only entry points
that both trees have: ``load_config``, ``with_profile``, ``Mapper(cfg)``, ``map_frame``, ``optimize(n_iters=)``,
``state_dict`` / ``load_state_dict`` and :func:`gausslite.render.rasterize`. Ratios are this / that (> 1: this tree
is faster).

**Roofline.** The rasterizer alone: :func:`gausslite.render.rasterize` forward + a random linear loss on colour, depth
and alpha + backward, on full views of the case's map from its keyframes, at the mapper's render threads and CPU
kernel. Its rate is counted in pixel–Gaussian pairs the compositing kernels evaluate, read from what the forward
pass saved for the backward (the packed Gaussian rows, the tile lists, each pixel's last contributing entry): for
the SIMD kernels, the lanes of the 8-lane row blocks that each Gaussian's footprint rows touch in each tile it is
binned to (masked lanes included, since they execute), over the entries each pass visits: the backward every entry
before the tile's largest last index, the forward the whole list unless every pixel of the tile may have saturated
(alpha > 0.99), then the same entries as the backward (a lower bound: the forward stops at the last saturation, at
or after that index). ``tile_pairs`` is the per-pixel formulation's count, tile-list length × tile pixels.
The ceiling is an FMA loop compiled by Warp like the SIMD kernels (a ``wp.func_native`` loop of ``acc = acc * a + b``
over 128 float32 lanes, clang vectorised, 2 FLOPs per FMA) on one core and on all cores (one Warp launch per thread,
as the rasterizer runs its bands). **Assumption:** a lane costs 43 FLOPs forward and 61 backward (counted from the
SIMD kernels' inner loops, :mod:`gausslite.render.simd_kernels`: the offset and the conic's power 9, the polynomial
``exp`` 20, alpha 2, transmittance 2, weight 1, colour and depth sums 8, alpha sum 1; backward: offset and power 9,
``exp`` 20, alpha 2, ``1 / (1 − alpha)`` 2, transmittance 1, weight 1, colour gradient sums 8, ``f·g`` 7,
``dL/dalpha`` 3, the back-to-front state 2, ``dL/dpower`` 1 and its moment sums 5; compares, selects, integer and
per-row work not counted), and every FLOP could issue as half of an FMA at the loop's rate: an upper bound on the
pairs per second the cores allow, so the fraction is a lower bound of how much of the machine the kernels use.

**Pairs.** Once per tree and case (the first round's worker), the pixel–Gaussian pairs the tile lists hold are
counted by what becomes of them (:func:`pair_census`, the views of the roofline): ``listed`` (each tile's pixels ×
its list's entries), ``passing`` (alpha >= 1/255), ``contributing`` (passing, before the pixel stopped) and
``after_stop`` (listed after the entry where a pixel stopped). ``listed`` over ``contributing`` is the room the tile
lists leave; the SIMD lanes over ``contributing`` what the kernels visit per pair that counts.

**Instruction sets.** ``--isa avx2`` / ``avx512`` builds every Warp module of both trees (the SIMD kernels among
them) for x86-64-v3 (AVX2, FMA: a 16-lane vector is two 8-lane halves) or x86-64-v4 (AVX-512) instead of the host's
CPU (:data:`ISA_FLAGS`; a build needs a host that can run it), so that one machine measures both vector widths.

Output: a table (printed) and, in full mode or with ``--out``, JSON through :mod:`bench._results` with ``settings``,
``trees`` (``this`` / ``that``: commit, root, the ``gausslite.__file__`` its workers imported), ``roofline``
(``fma_gflops_1``, ``fma_gflops_all`` GFLOP/s, ``threads_all``, ``flops_per_pair``, ``pairs_per_s_1`` /
``pairs_per_s_all`` allowed) and ``cases``: ``{name: {"this": {...}, "that": {...}, "ratio": {...}}}``, each tree's
block holding ``n_gaussians``, ``width``, ``height`` (px), ``it_per_s``, ``full_it_per_s``, ``roi_it_per_s``
(iterations s⁻¹; medians), ``cycle_s`` / ``full_s`` / ``roi_s`` (seconds of every repeat) and ``raster``: ``views``,
``fwd_bwd_s`` (seconds, summed over the views' medians), ``tile_pairs``, ``lane_pairs_fwd``, ``lane_pairs_bwd``
(counts per fwd+bwd of all views), ``entries`` (tile-list entries), the census's counts in the first round's
worker, ``pairs_per_s`` (forward lanes s⁻¹), ``gflops`` and ``roofline_fraction``
(against one core's ceiling × the render threads, capped at all cores).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Optional

import numpy as np
import warp as wp

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results" / "throughput.json"
WORK = REPO / "runs" / "bench_throughput"
THIS_FILE = Path(__file__).resolve()
#: (name, Gaussians, downscale of the scene) of the full run; the scene is 640 × 480
FULL_CASES = [("6k_320x240", 6000, 2.0), ("20k_320x240", 20000, 2.0), ("6k_640x480", 6000, 1.0),
              ("20k_640x480", 20000, 1.0)]
#: the quick run's cases on a 128 × 96 scene
QUICK_CASES = [("1k_64x48", 1000, 2.0), ("2k_128x96", 2000, 1.0)]
KEYFRAME_CASE = "keyframe_agent"
FULL_SCENE = {"width": 640, "height": 480, "frames": 72}
QUICK_SCENE = {"width": 128, "height": 96, "frames": 24}
#: frames of the 30 Hz synthetic circle (bench.realtime's ``synthetic_circle``): the replay clock below turns as fast
CIRCLE_FRAMES, CIRCLE_FPS = 300, 30.0
TASK = "synth-pick-object"
#: FLOPs of one lane (pixel–Gaussian pair) of the SIMD compositing kernels (module docstring)
FWD_FLOPS, BWD_FLOPS = 43, 61
#: the worker's result line on stdout
RESULT_TAG = "THROUGHPUT_RESULT "
#: :func:`pair_census`'s counts
CENSUS_KEYS = ("listed", "passing", "contributing", "after_stop")
#: ``--isa``: the compiler flags every Warp module (the SIMD kernels among them) is built with in the workers, for
#: this tree and the other alike: Warp's default flags (``wp.config.cpu_compiler_flags``) with the host's CPU
#: (``-march=native``) replaced by a fixed target, x86-64-v3 (AVX2, FMA) or x86-64-v4 (AVX-512 F/BW/CD/DQ/VL); Warp's
#: in-process clang takes the target as the compiler front end's ``-target-cpu``. ``native``: Warp's default.
_LLVM_FLAGS = ("-mllvm=-inline-threshold=9000 -mllvm=-inline-cold-callsite-threshold=3000"
               " -mllvm=-slp-recursion-max-depth=4")
ISA_FLAGS = {"native": None, "avx2": f"-target-cpu x86-64-v3 {_LLVM_FLAGS}",
             "avx512": f"-target-cpu x86-64-v4 {_LLVM_FLAGS}"}
#: run this file as ``__main__`` without putting its folder on ``sys.path`` (``bench/`` holds modules whose names a
#: library might import), so that ``PYTHONPATH`` alone decides which ``gausslite`` the worker imports
_BOOT = "import runpy, sys; p = sys.argv[1]; sys.argv = sys.argv[1:]; runpy.run_path(p, run_name='__main__')"

wp.set_module_options({"enable_backward": False})

# the roofline's ceiling: ``acc = acc * a + b`` over 128 float32 lanes (independent chains, as many vectors as the
# target's width gives), vectorised by clang as Warp compiles the SIMD kernels and contracted to FMAs by the pragma
# (the ceiling is the cores', whether or not a kernel's own multiply-adds are fused); ``slot`` receives the lanes' sum
_FMA_LOOP = r"""
float acc[128];
for (int k = 0; k < 128; ++k) acc[k] = seed + 1.0e-3f * (float)k;
for (int i = 0; i < iters; ++i) {
    #pragma clang fp contract(fast)
    #pragma clang loop vectorize(enable)
    for (int k = 0; k < 128; ++k) acc[k] = acc[k] * a + b;
}
float s = 0.0f;
for (int k = 0; k < 128; ++k) s += acc[k];
float* o = (float*)out.data;
o[slot] = s;
"""


@wp.func_native(_FMA_LOOP)
def _fma_loop(iters: int, a: float, b: float, seed: float, slot: int, out: wp.array(dtype=wp.float32)): ...


@wp.kernel
def fma_kernel(iters: int, a: float, b: float, out: wp.array(dtype=wp.float32)):
    """``iters`` × 128 float32 FMAs per thread into ``out[tid]`` (a (dim,) float32 array)."""
    t = wp.tid()
    _fma_loop(iters, a, b, float(t), t, out)


def fma_peak(threads: int, seconds: float = 0.15, tries: int = 7) -> float:
    """The best FMA-loop rate (GFLOP/s, 2 FLOPs per FMA) of ``threads`` concurrent one-thread Warp launches, each
    sized to about ``seconds``; best of ``tries`` (a peak: on a shared machine the best try is the one that had the
    cores)."""
    outs = [wp.zeros(1, dtype=wp.float32, device="cpu") for _ in range(threads)]
    wp.launch(fma_kernel, dim=1, inputs=[1000, 0.999, 0.001, outs[0]], device="cpu")  # compile / load
    t0 = time.perf_counter()
    wp.launch(fma_kernel, dim=1, inputs=[1_000_000, 0.999, 0.001, outs[0]], device="cpu")
    iters = max(1000, int(1_000_000 * seconds / max(time.perf_counter() - t0, 1e-6)))
    best = 0.0
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for _ in range(tries):
            t0 = time.perf_counter()
            futs = [pool.submit(wp.launch, fma_kernel, dim=1, inputs=[iters, 0.999, 0.001, o], device="cpu")
                    for o in outs]
            for f in futs:
                f.result()
            best = max(best, threads * iters * 128 * 2 / (time.perf_counter() - t0) / 1e9)
    return best


# ------------------------------------------------------------------------------------------------ the worker
def mapper_config(profile: str, overrides: list, extra: Optional[dict] = None):
    """The live agent's mapper settings (``load_config().agent.mapper``) under sensor profile ``profile``
    (``handheld`` / ``rendered``, below what the agent's settings set explicitly), then ``overrides``
    (``key=value``), then ``extra`` (a nested dict), as a ``MapperConfig``."""
    from gausslite.config import load_config
    from gausslite.mapping.config import MapperConfig, apply_overrides, deep_merge
    from gausslite.mapping.profiles import HANDHELD, RENDERED, with_profile

    cfg = with_profile(load_config().agent.mapper, {"handheld": HANDHELD, "rendered": RENDERED}[profile])
    data = apply_overrides(cfg.model_dump(), list(overrides))
    return MapperConfig.model_validate(deep_merge(data, extra or {}))


def _scene(spec: dict):
    """(frames list, relevance fn) of the worker's scene at ``spec["downscale"]``."""
    from gausslite.datasets import load_dataset
    from gausslite.pipeline import gt_roi_fn

    ds = load_dataset(spec["scene"], downscale=spec["downscale"], fps=spec["fps"])
    return ds, gt_roi_fn(ds, TASK)


def _sensor_summary(cfg) -> dict:
    return {"exposure_comp": cfg.sensor.exposure_comp, "motion_blur": cfg.sensor.motion_blur,
            "rolling_shutter_s": cfg.sensor.rolling_shutter_s, "pose_refine": cfg.pose.refine,
            "lambda_ssim": cfg.lambda_ssim, "roi_update": cfg.roi_update,
            "render_threads": cfg.performance.render_threads, "cpu_kernel": cfg.performance.cpu_kernel,
            "torch_threads": cfg.performance.torch_threads}


def run_size_case(spec: dict) -> dict:
    """Time one size case in this process (module docstring, "Cases"). ``spec``: ``n`` Gaussians, ``downscale``,
    ``keyframes``, ``repeats``, ``warmup``, ``profile``, ``overrides``, ``scene`` (folder), ``fps``,
    ``raster_views``, ``raster_repeats``. Returns the case's figures (seconds per repeat, counts)."""
    from gausslite.mapping.mapper import Mapper

    n, k = int(spec["n"]), int(spec["keyframes"])
    ds, roi = _scene(spec)
    cfg = mapper_config(spec["profile"], spec["overrides"], {"budget": {"max_gaussians": n}})
    build_cfg = mapper_config(spec["profile"], spec["overrides"], {
        "budget": {"max_gaussians": n}, "iters_per_frame": 2, "warmup_iters": 1,
        "seeding": {"seeds_per_frame": math.ceil(1.2 * n / k), "first_frame_seeds": math.ceil(1.2 * n / k),
                    "coverage": False}})
    t0 = time.perf_counter()
    builder = Mapper(build_cfg)
    frames = [ds[i] for i in range(min(k, len(ds)))]
    for fr in frames:
        builder.map_frame(fr, roi(fr))
    snapshot = builder.state_dict(None)
    del builder
    mapper = Mapper(cfg)
    mapper.load_state_dict(copy.deepcopy(snapshot))
    build_s = time.perf_counter() - t0
    n0, active = len(mapper.model), int(mapper.model.active.sum())
    if spec["warmup"]:
        mapper.optimize(n_iters=int(spec["warmup"]))
    ipf, warm = cfg.iters_per_frame, cfg.warmup_iters
    full_s, roi_s = [], []
    for _ in range(int(spec["repeats"])):
        mapper.load_state_dict(copy.deepcopy(snapshot))
        t0 = time.perf_counter()
        if warm:
            mapper.optimize(n_iters=warm)
        t1 = time.perf_counter()
        if ipf > warm:
            mapper.optimize(n_iters=ipf - warm)
        t2 = time.perf_counter()
        full_s.append(t1 - t0)
        roi_s.append(t2 - t1)
    out = {"kind": "size", "n_target": n, "n_gaussians": n0, "n_gaussians_after": len(mapper.model),
           "active": active, "width": frames[0].intrinsics.width, "height": frames[0].intrinsics.height,
           "keyframes": len(mapper.keyframes), "iters_per_frame": ipf, "warmup_iters": warm, "build_s": build_s,
           "full_s": full_s, "roi_s": roi_s, "cycle_s": [a + b for a, b in zip(full_s, roi_s)],
           "config": _sensor_summary(cfg)}
    mapper.load_state_dict(copy.deepcopy(snapshot))
    out["raster"] = rasterizer_rate(mapper, frames[:int(spec["raster_views"])], int(spec["raster_repeats"]),
                                    bool(spec.get("census")))
    return out


def run_keyframe_case(spec: dict) -> dict:
    """Time one keyframe's ``map_frame`` at the agent's settings (module docstring, "Cases"): ``spec`` as
    :func:`run_size_case`'s (``n`` unused). Returns seconds, iterations and Gaussians of every repeat."""
    from gausslite.mapping.mapper import Mapper

    k = int(spec["keyframes"])
    ds, roi = _scene(spec)
    cfg = mapper_config(spec["profile"], spec["overrides"])
    mapper = Mapper(cfg)
    t0 = time.perf_counter()
    for i in range(min(k, len(ds) - 1)):
        fr = ds[i]
        mapper.map_frame(fr, roi(fr))
    build_s = time.perf_counter() - t0
    snapshot = mapper.state_dict(None)
    frame = ds[min(k, len(ds) - 1)]
    w = roi(frame)
    n0 = len(mapper.model)
    runs = []
    for rep in range(int(spec["repeats"]) + 1):  # the first call warms up
        mapper.load_state_dict(copy.deepcopy(snapshot))
        st = mapper.map_frame(frame, w)
        if rep:
            runs.append({"seconds": st.seconds, "iters": st.iters, "n_seeds": st.n_seeds,
                         "n_gaussians": st.n_gaussians, "active_iters": st.active_iters})
    return {"kind": "keyframe", "n_gaussians": n0, "width": frame.intrinsics.width,
            "height": frame.intrinsics.height, "keyframes": k, "iters_per_frame": cfg.iters_per_frame,
            "warmup_iters": cfg.warmup_iters, "build_s": build_s, "runs": runs,
            "keyframe_s": [r["seconds"] for r in runs], "config": _sensor_summary(cfg)}


def rasterizer_rate(mapper, frames: list, repeats: int, census: bool = False) -> dict:
    """The rasterizer's forward + backward on full views of ``mapper``'s map from ``frames``' poses, at the mapper's
    render threads, backend and CPU kernel: seconds (the median of ``repeats`` after one warm-up, summed over the
    views) and the pairs the kernels evaluated (:func:`count_pairs`; None where the render's saved state cannot be
    read; with ``census`` also :func:`pair_census`'s)."""
    import torch
    from gausslite.render import rasterize

    perf = mapper.cfg.performance
    names = ("means", "quats", "log_scales", "opacity_logits", "colors")
    keys = ("tile_pairs", "entries", "lane_pairs_fwd", "lane_pairs_bwd") + (CENSUS_KEYS if census else ())
    total_s, counts, ok = 0.0, dict.fromkeys(keys, 0), True
    gen = torch.Generator().manual_seed(0)
    for fr in frames:
        W, H = fr.intrinsics.width, fr.intrinsics.height
        wc, wd, wa = torch.randn(H, W, 3, generator=gen), torch.randn(H, W, generator=gen), \
            torch.randn(H, W, generator=gen)
        times = []
        for rep in range(repeats + 1):
            params = [mapper.model.params[k].detach().clone().requires_grad_(True) for k in names]
            t0 = time.perf_counter()
            out = rasterize(*params, K=fr.intrinsics.K, width=W, height=H, c2w=fr.c2w, backend=mapper.cfg.backend,
                            num_threads=perf.render_threads, cpu_kernel=perf.cpu_kernel)
            t1 = time.perf_counter()
            if rep == 0 and ok:  # untimed, and before the backward frees the saved state
                c = count_pairs(out, census)
                ok = c is not None
                for key in counts:
                    counts[key] += c[key] if ok else 0
            t2 = time.perf_counter()
            ((out.color * wc).sum() + (out.depth * wd).sum() + (out.alpha * wa).sum()).backward()
            times.append(t1 - t0 + time.perf_counter() - t2)
        total_s += statistics.median(times[1:]) if len(times) > 1 else times[0]
    res = {"views": len(frames), "fwd_bwd_s": total_s, "threads": perf.render_threads, "cpu_kernel": perf.cpu_kernel}
    res.update(counts if ok else {k: None for k in counts})
    return res


def _tile_max(img: np.ndarray, ts: int, tiles_x: int, tiles_y: int, fill) -> np.ndarray:
    """(tiles_y * tiles_x,) max of ``img`` (H, W) over each ``ts`` px tile (padding ``fill``), row-major."""
    H, W = img.shape
    pad = np.full((tiles_y * ts, tiles_x * ts), fill, dtype=img.dtype)
    pad[:H, :W] = img
    return pad.reshape(tiles_y, ts, tiles_x, ts).max(axis=(1, 3)).reshape(-1)


def count_pairs(out, census: bool = False) -> Optional[dict]:
    """The pixel–Gaussian pairs the CPU compositing kernels evaluated for render ``out`` (a ``RenderOutput`` whose
    alpha came from the Warp rasterizer), read from the state its forward pass saved for the backward: ``gdata``
    (M, 16) float32 rows, the depth-sorted tile lists ``gids`` / ``tile_start``, the final transmittance ``T`` and each
    pixel's last contributing entry ``last`` (module docstring, "Roofline"). Returns ``tile_pairs``,
    ``entries`` (tile-list entries), ``lane_pairs_fwd``, ``lane_pairs_bwd`` (ints) and with ``census``
    :func:`pair_census`'s counts, or None when the render did not save that state (another backend, or kernels whose
    saved state differs)."""
    try:
        node = out.alpha.grad_fn
        gdata, gids, tile_start, T, last = (t.detach().cpu().numpy() for t in node.saved_tensors[:5])
        width, height, ts, tiles_x, tiles_y, _ = node.dims
        simd = bool(getattr(node, "simd", False))
    except (AttributeError, ValueError, TypeError, RuntimeError):
        return None
    if gdata.ndim != 2 or gdata.shape[1] != 16 or T.size != width * height:
        return None
    n_tiles = tiles_x * tiles_y
    start = tile_start.astype(np.int64)
    end = np.append(start[1:], len(gids))
    maxlast = np.maximum(_tile_max(last.reshape(height, width), ts, tiles_x, tiles_y, np.iinfo(np.int32).min),
                         start)
    unsaturated = _tile_max(T.reshape(height, width), ts, tiles_x, tiles_y, 0.0) >= 0.01
    stop_fwd = np.where(unsaturated, end, maxlast)
    tx = np.arange(n_tiles) % tiles_x
    ty = np.arange(n_tiles) // tiles_x
    px = (np.minimum((tx + 1) * ts, width) - tx * ts) * (np.minimum((ty + 1) * ts, height) - ty * ts)
    res = {"tile_pairs": int(((end - start) * px).sum()), "entries": int(len(gids)),
           "lane_pairs_fwd": _lanes(gdata, gids, start, stop_fwd, ts, tiles_x, width, height, simd),
           "lane_pairs_bwd": _lanes(gdata, gids, start, maxlast, ts, tiles_x, width, height, simd)}
    if census:
        res.update(pair_census(gdata, gids, start, end, ts, tiles_x, width, height))
    return res


def pair_census(gdata, gids, start, end, ts: int, tiles_x: int, width: int, height: int) -> dict:
    """What becomes of the pixel–Gaussian pairs the tile lists hold (every pixel of a tile × every entry of its
    list), evaluated in float32 from the packed rows as the kernels composite them (Kerbl et al. 2023: ``alpha =
    min(0.99, o exp(power))``, a pair with ``power > 0`` or ``alpha < 1/255`` skipped, a pixel stops at the entry
    that would take its transmittance below 1e-4): ``listed`` (all pairs), ``passing`` (alpha >= 1/255),
    ``contributing`` (passing, before the pixel stopped) and ``after_stop`` (the listed pairs from the entry where
    a pixel stopped to its tile's end, which a stopped pixel skips)."""
    f32 = np.float32
    out = {"listed": 0, "passing": 0, "contributing": 0, "after_stop": 0}
    for t in range(len(start)):
        a, b = int(start[t]), int(end[t])
        if b <= a:
            continue
        x0, y0 = (t % tiles_x) * ts, (t // tiles_x) * ts
        xs, ys = np.arange(x0, min(x0 + ts, width), dtype=f32), np.arange(y0, min(y0 + ts, height), dtype=f32)
        px, py = (m.reshape(-1, 1) for m in np.meshgrid(xs, ys))
        r = gdata[gids[a:b]]
        dx, dy = r[:, 0] - px + r[:, 10], r[:, 1] - py + r[:, 11]
        power = f32(-0.5) * (r[:, 2] * dx * dx + r[:, 4] * dy * dy) - r[:, 3] * dx * dy
        with np.errstate(over="ignore"):
            alpha = np.minimum(f32(0.99), r[:, 5] * np.exp(power))
        ok = (power <= 0) & (alpha >= f32(1.0 / 255.0))
        trans = np.cumprod(np.where(ok, f32(1) - alpha, f32(1)), axis=1)
        stopped = ok & (trans < f32(1e-4))
        stop = np.where(stopped.any(axis=1), stopped.argmax(axis=1), b - a)
        before = np.arange(b - a)[None, :] < stop[:, None]
        out["listed"] += ok.size
        out["passing"] += int(ok.sum())
        out["contributing"] += int((ok & before).sum())
        out["after_stop"] += int((b - a - stop).sum())
    return out


def _lanes(gdata, gids, start, stop, ts, tiles_x, width, height, simd: bool, chunk: int = 1 << 17) -> int:
    """Lanes the tile kernels evaluate over the entries ``[start[t], stop[t])`` of every tile ``t``: per entry and
    footprint row in the tile (the kernels' ``tile_rows`` / ``row_span`` bounds, in float32), the 8-lane blocks the
    row's span touches × 8 (``simd``), or the span's pixels (the Warp tile kernels)."""
    counts = np.maximum(stop - start, 0)
    total = int(counts.sum())
    tiles = np.repeat(np.arange(len(start)), counts)
    entry = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(start, counts)
    n = 0
    f32 = np.float32
    for a in range(0, total, chunk):
        t, r = tiles[a:a + chunk], gdata[gids[entry[a:a + chunk]]]
        x0, y0 = ((t % tiles_x) * ts).astype(f32), ((t // tiles_x) * ts).astype(f32)
        x1, y1 = np.minimum(x0 + ts, width) - 1, np.minimum(y0 + ts, height) - 1
        uu, vv, ks, k1, k0 = r[:, 0] + r[:, 10], r[:, 1] + r[:, 11], r[:, 13], r[:, 14], r[:, 15]
        with np.errstate(all="ignore"):
            e = np.sqrt(k0 / k1) + f32(0.5)
            lo, hi = np.ceil(vv - e), np.floor(vv + e)
            ya = np.where(lo > y0, np.where(lo <= y1, lo, y1 + 1), y0)
            yb = np.where(hi < y1, np.where(hi >= y0, hi, y0 - 1), y1)
            for row in range(ts):
                py = y0 + f32(row)
                dyr = vv - py
                cx, half2 = uu + ks * dyr, k0 - k1 * dyr * dyr
                hw = np.sqrt(np.maximum(half2, 0)) + f32(0.5)
                lo2, hi2 = np.ceil(cx - hw), np.floor(cx + hw)
                xa = np.where(lo2 > x0, np.where(lo2 <= x1, lo2, x1 + 1), x0)
                xb = np.where(hi2 < x1, np.where(hi2 >= x0, hi2, x0 - 1), x1)
                ok = (py >= ya) & (py <= yb) & (half2 >= 0) & (xa <= xb)
                la, lb = (np.where(ok, xa - x0, 0)).astype(np.int64), (np.where(ok, xb - x0, 0)).astype(np.int64)
                width_px = ((lb >> 3) - (la >> 3) + 1) * 8 if simd else lb - la + 1
                n += int(np.where(ok, width_px, 0).sum())
    return n


def worker(spec: dict) -> dict:
    """Run one case (``spec["kind"]``: ``size`` or ``keyframe``) in this process; the result carries which
    ``gausslite`` was imported (``gausslite_file``) and the library versions."""
    if spec.get("cpu_flags") is not None:  # before any Warp module of gausslite is built
        wp.config.cpu_compiler_flags = spec["cpu_flags"]
    import torch

    import gausslite

    res = run_keyframe_case(spec) if spec["kind"] == "keyframe" else run_size_case(spec)
    res.update({"gausslite_file": str(Path(gausslite.__file__).resolve()), "torch": torch.__version__,
                "warp": wp.config.version, "python": sys.version.split()[0]})
    return res


# ------------------------------------------------------------------------------------------------ the driver
def run_worker(tree: Path, spec: dict, timeout_s: float = 3600.0, script: Path = THIS_FILE,
               tag: str = RESULT_TAG) -> dict:
    """Run ``script --worker SPEC`` (default: this file's :func:`worker`) in a fresh process whose ``import
    gausslite`` is ``tree``'s (``PYTHONPATH``), started from an empty folder; its result is the JSON of the last
    stdout line that starts with ``tag`` and carries ``gausslite_file``. Raises RuntimeError when it fails or
    imported another tree's ``gausslite``."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    with tempfile.TemporaryDirectory(prefix="gausslite-worker-") as cwd:
        proc = subprocess.run([sys.executable, "-c", _BOOT, str(script), "--worker", json.dumps(spec)],
                              cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout_s, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"{Path(script).stem} worker failed for {tree} ({spec['name']}):\n{proc.stderr[-4000:]}")
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith(tag)]
    if not lines:
        raise RuntimeError(f"{Path(script).stem} worker for {tree} printed no result:\n{proc.stdout[-2000:]}")
    res = json.loads(lines[-1][len(tag):])
    if Path(tree).resolve() not in Path(res["gausslite_file"]).resolve().parents:
        raise RuntimeError(f"the worker for {tree} imported gausslite from {res['gausslite_file']}")
    return res


def git(*args: str, cwd: Path = REPO) -> str:
    """``git ARGS`` in ``cwd``: its stdout, stripped. Raises CalledProcessError when git fails."""
    out = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True, timeout=120)
    return out.stdout.strip()


@contextmanager
def worktree(commit: str) -> Iterator[tuple[Path, str]]:
    """``(folder, full commit hash)`` of a ``git worktree`` of ``commit`` in a temporary folder, removed on exit."""
    sha = git("rev-parse", "--verify", f"{commit}^{{commit}}")
    parent = Path(tempfile.mkdtemp(prefix="gausslite-against-"))
    path = parent / "tree"
    git("worktree", "add", "--detach", str(path), sha)
    try:
        yield path, sha
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(path)], cwd=REPO, capture_output=True,
                       check=False, timeout=120)
        subprocess.run(["git", "worktree", "prune"], cwd=REPO, capture_output=True, check=False, timeout=120)
        import shutil  # lazy: only for the clean-up of --against

        shutil.rmtree(parent, ignore_errors=True)


def ensure_scene(work: Path, scene: dict) -> Path:
    """The ``agent_a`` folder of the synthetic circle of ``scene`` (width, height, frames), generated into ``work``
    once."""
    from gausslite.synthetic import make_scene

    out = Path(work) / f"synthetic_circle_{scene['frames']}_{scene['width']}x{scene['height']}"
    if not (out / "agent_a" / "results" / f"depth{scene['frames'] - 1:06d}.png").exists():
        make_scene(out, frames=scene["frames"], width=scene["width"], height=scene["height"], trajectory="circle",
                   progress=False, agents=("agent_a",))
    return out / "agent_a"


def _median(xs: list) -> Optional[float]:
    """The median of ``xs``, None when empty."""
    return statistics.median(xs) if xs else None


def summarise_tree(runs: list[dict], peak_1: float, peak_all: float, threads_all: int) -> dict:
    """One tree's figures of one case from its workers' results ``runs`` (repeats pooled over rounds): the median
    rates, and the rasterizer's pairs per second and fraction of the roofline (GFLOP/s ceilings ``peak_1`` of one
    core, ``peak_all`` of ``threads_all``)."""
    r0 = runs[0]
    keep = ("kind", "n_target", "n_gaussians", "n_gaussians_after", "active", "width", "height", "keyframes",
            "iters_per_frame", "warmup_iters", "config", "gausslite_file", "torch", "warp", "python")
    out = {k: r0[k] for k in keep if k in r0}
    out["build_s"] = [r["build_s"] for r in runs]
    if r0["kind"] == "keyframe":
        secs = [s for r in runs for s in r["keyframe_s"]]
        iters = [x["iters"] for r in runs for x in r["runs"]]
        out.update({"keyframe_s": secs, "iters": iters, "runs": [x for r in runs for x in r["runs"]],
                    "it_per_s": _median([i / s for i, s in zip(iters, secs)])})
        return out
    full = [s for r in runs for s in r["full_s"]]
    roi = [s for r in runs for s in r["roi_s"]]
    cyc = [s for r in runs for s in r["cycle_s"]]
    ipf, warm = r0["iters_per_frame"], r0["warmup_iters"]
    out.update({"full_s": full, "roi_s": roi, "cycle_s": cyc, "it_per_s": ipf / _median(cyc),
                "full_it_per_s": warm / _median(full) if warm else None,
                "roi_it_per_s": (ipf - warm) / _median(roi) if ipf > warm else None})
    ras = dict(r0["raster"])
    ras["fwd_bwd_s"] = _median([r["raster"]["fwd_bwd_s"] for r in runs])
    if ras.get("lane_pairs_fwd"):
        flops = FWD_FLOPS * ras["lane_pairs_fwd"] + BWD_FLOPS * ras["lane_pairs_bwd"]
        ceiling = min(peak_all, peak_1 * max(1, int(ras.get("threads") or 1)))
        ras.update({"pairs_per_s": ras["lane_pairs_fwd"] / ras["fwd_bwd_s"], "gflops": flops / ras["fwd_bwd_s"] / 1e9,
                    "flops_per_pair": flops / ras["lane_pairs_fwd"], "ceiling_gflops": ceiling,
                    "roofline_fraction": flops / ras["fwd_bwd_s"] / 1e9 / ceiling,
                    "roofline_fraction_all_cores": flops / ras["fwd_bwd_s"] / 1e9 / peak_all})
    ras["tile_pairs_per_s"] = ras["tile_pairs"] / ras["fwd_bwd_s"] if ras.get("tile_pairs") else None
    out["raster"] = ras
    return out


def ratios(this: dict, that: dict) -> dict:
    """this / that of every rate both trees have (> 1: this tree is faster), and of the rasterizer's seconds
    that / this."""
    out = {k: this[k] / that[k] for k in ("it_per_s", "full_it_per_s", "roi_it_per_s")
           if this.get(k) and that.get(k)}
    a, b = this.get("raster", {}).get("fwd_bwd_s"), that.get("raster", {}).get("fwd_bwd_s")
    if a and b:
        out["raster_speed"] = b / a
    return out


def _fmt(x: Optional[float], nd: int = 2) -> str:
    return "–" if x is None else f"{x:.{nd}f}"


def table(result: dict) -> str:
    """Markdown table of a result: per case and tree the iterations per second (cycle, full-image, ROI phase), the
    ratio, and the rasterizer's pairs per second and roofline fraction; the roofline's line under it."""
    trees = [t for t in ("this", "that") if result["trees"].get(t)]
    lines = ["| case | tree | Gaussians | px | it/s | full it/s | ROI it/s | this/that | raster fwd+bwd s | "
             "pairs/s (M) | roofline |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, blk in result["cases"].items():
        for t in trees:
            b = blk[t]
            ras = b.get("raster") or {}
            ratio = blk.get("ratio", {}).get("it_per_s") if t == "this" else None
            pps = ras.get("pairs_per_s")
            frac = ras.get("roofline_fraction")
            lines.append(f"| {name} | {t} | {b['n_gaussians']:,} | {b['width']}×{b['height']} | "
                         f"{_fmt(b['it_per_s'])} | "
                         f"{_fmt(b.get('full_it_per_s'))} | {_fmt(b.get('roi_it_per_s'))} | {_fmt(ratio, 3)} | "
                         f"{_fmt(ras.get('fwd_bwd_s'), 3)} | {_fmt(None if pps is None else pps / 1e6, 1)} | "
                         f"{'–' if frac is None else f'{100 * frac:.1f} %'} |")
    lines += ["", "| case | tree | tile entries | pairs listed / px | passing 1/255 / px | contributing / px | "
              "after a pixel stopped / px | listed per contributing | SIMD lanes per contributing |",
              "|---|---|---|---|---|---|---|---|---|"]
    for name, blk in result["cases"].items():
        for t in trees:
            ras, b = blk[t].get("raster") or {}, blk[t]
            if not ras.get("listed"):
                continue
            px = b["width"] * b["height"] * ras["views"]
            lines.append(f"| {name} | {t} | {ras['entries']:,} | {ras['listed'] / px:.1f} | "
                         f"{ras['passing'] / px:.1f} | {ras['contributing'] / px:.1f} | {ras['after_stop'] / px:.1f} | "
                         f"{ras['listed'] / ras['contributing']:.2f} | "
                         f"{ras['lane_pairs_fwd'] / ras['contributing']:.2f} |")
    rf = result["roofline"]
    lines.append("")
    lines.append(f"Roofline: the FMA loop reaches {rf['fma_gflops_1']:.1f} GFLOP/s on one core, "
                 f"{rf['fma_gflops_all']:.1f} on {rf['threads_all']}; at {FWD_FLOPS} + {BWD_FLOPS} FLOPs per pair "
                 f"(forward + backward) that allows {rf['pairs_per_s_1'] / 1e9:.2f} G pairs/s per core "
                 f"({rf['pairs_per_s_all'] / 1e9:.2f} G on all). The rasterizer's fraction is against one core × its "
                 "render threads; pairs are the SIMD kernels' forward lanes.")
    return "\n".join(lines)


def _parse(argv) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m bench.throughput", description=__doc__.splitlines()[0])
    ap.add_argument("--against", metavar="COMMIT", help="also run the cases for COMMIT (a git worktree), A B per case")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (seconds); prints only unless --out is given")
    ap.add_argument("--cases", default=None,
                    help=f"comma list of case names (default: all; '{KEYFRAME_CASE}' is the keyframe case)")
    ap.add_argument("--profile", choices=("handheld", "rendered"), default="handheld",
                    help="sensor profile on top of the agent's mapper settings")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="mapper setting for every case (dotted keys, e.g. performance.render_threads=2)")
    ap.add_argument("--repeats", type=int, default=None, help="timed repeats per worker (default 3; quick 1)")
    ap.add_argument("--rounds", type=int, default=1, help="workers per tree and case, alternating A B A B")
    ap.add_argument("--warmup", type=int, default=4, help="untimed iterations before the repeats")
    ap.add_argument("--keyframes", type=int, default=None, help="keyframes the map is built from (default 12; quick 4)")
    ap.add_argument("--raster-views", type=int, default=3, help="views of the roofline's rasterizer timing")
    ap.add_argument("--raster-repeats", type=int, default=3, help="timed rasterizer passes per view")
    ap.add_argument("--work", type=Path, default=WORK, help="where the synthetic scene is generated once")
    ap.add_argument("--out", type=Path, default=None, help=f"JSON output (default {RESULTS} unless --quick)")
    ap.add_argument("--isa", choices=tuple(ISA_FLAGS), default="native",
                    help="instruction set the kernels of both trees are built for (default: the host's); results "
                         "go to throughput_<isa>.json unless native")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def _specs(args, scene_dir: Path, scene: dict) -> list[dict]:
    """The workers' specs of the selected cases (the keyframe case at the agent's default downscale)."""
    from gausslite.config import load_config

    cases = [(name, n, ds, "size") for name, n, ds in (QUICK_CASES if args.quick else FULL_CASES)]
    cases.append((KEYFRAME_CASE, 0, float(load_config().agent.downscale), "keyframe"))
    if args.cases:
        wanted = [c for c in args.cases.split(",") if c]
        unknown = sorted(set(wanted) - {c[0] for c in cases})
        if unknown:
            raise SystemExit(f"unknown case(s) {', '.join(unknown)}; known: {', '.join(c[0] for c in cases)}")
        cases = [c for c in cases if c[0] in wanted]
    fps = CIRCLE_FPS * scene["frames"] / CIRCLE_FRAMES
    common = {"scene": str(scene_dir), "fps": fps, "profile": args.profile, "overrides": list(args.overrides),
              "repeats": args.repeats or (1 if args.quick else 3), "warmup": args.warmup,
              "keyframes": args.keyframes or (4 if args.quick else 12), "raster_views": args.raster_views,
              "raster_repeats": args.raster_repeats, "isa": args.isa, "cpu_flags": ISA_FLAGS[args.isa]}
    return [{**common, "name": name, "n": n, "downscale": ds, "kind": kind} for name, n, ds, kind in cases]


def run_cases(specs: list[dict], trees: dict, rounds: int) -> dict:
    """Every case's workers: per case, ``rounds`` times each tree in turn (this, that, this, that ...). Returns
    ``{case: {tree: [worker results]}}``."""
    from tqdm import tqdm

    runs: dict = {s["name"]: {t: [] for t in trees} for s in specs}
    jobs = [(s, t, k) for s in specs for k in range(rounds) for t in trees]
    for spec, t, k in tqdm(jobs, desc="bench.throughput", unit="worker"):
        res = run_worker(trees[t], {**spec, "census": k == 0})  # the pairs are counted once per tree and case
        runs[spec["name"]][t].append(res)
        rate = (res["iters_per_frame"] / statistics.median(res["cycle_s"]) if res["kind"] == "size"
                else statistics.median(r["iters"] / r["seconds"] for r in res["runs"]))
        tqdm.write(f"{spec['name']:<16} {t:<5} {res['n_gaussians']:>7,} Gaussians {res['width']}x{res['height']}: "
                   f"{rate:.2f} it/s")
    return runs


def _roofline(quick: bool) -> dict:
    threads = os.cpu_count() or 1
    secs = 0.05 if quick else 0.15
    p1, pall = fma_peak(1, secs), fma_peak(threads, secs)
    per_pair = FWD_FLOPS + BWD_FLOPS
    return {"fma_gflops_1": p1, "fma_gflops_all": pall, "threads_all": threads,
            "flops_per_pair": {"forward": FWD_FLOPS, "backward": BWD_FLOPS, "total": per_pair},
            "pairs_per_s_1": p1 * 1e9 / per_pair, "pairs_per_s_all": pall * 1e9 / per_pair,
            "assumption": "43 FLOPs per lane forward and 61 backward (the SIMD kernels' inner loops; compares, "
                          "selects, integer and per-row work not counted), each FLOP at half an FMA of the loop's "
                          "rate: an upper bound on the pairs per second, so the fraction is a lower bound"}


def main(argv=None) -> dict:
    """Run the benchmark (module docstring); returns the result dict."""
    args = _parse(argv)
    if args.worker:
        res = worker(json.loads(args.worker))
        print(RESULT_TAG + json.dumps(res), flush=True)
        return res
    from bench._results import portable_path, publish  # lazy: a worker may run against another tree's bench

    t_start = time.perf_counter()
    if ISA_FLAGS[args.isa] is not None:  # the roofline's FMA loop as the kernels are built
        wp.config.cpu_compiler_flags = ISA_FLAGS[args.isa]
    scene = QUICK_SCENE if args.quick else FULL_SCENE
    scene_dir = ensure_scene(args.work, scene)
    specs = _specs(args, scene_dir, scene)
    load_before = list(os.getloadavg())
    roofline = _roofline(args.quick)
    against = worktree(args.against) if args.against else None
    with (against if against is not None else _nothing()) as other:
        trees = {"this": REPO} if other is None else {"this": REPO, "that": other[0]}
        runs = run_cases(specs, trees, args.rounds)
    result: dict = {
        "settings": {"quick": args.quick, "profile": args.profile, "overrides": list(args.overrides),
                     "repeats": specs[0]["repeats"], "rounds": args.rounds, "warmup_iters": args.warmup,
                     "keyframes": specs[0]["keyframes"], "isa": args.isa, "cpu_flags": ISA_FLAGS[args.isa],
                     "scene": {**scene, "fps": specs[0]["fps"], "task": TASK,
                                                                     "path": portable_path(scene_dir)}},
        "trees": {"this": {"commit": git("rev-parse", "HEAD"), "dirty": bool(git("status", "--porcelain",
                                                                                  "--untracked-files=no"))},
                  "that": None if other is None else {"ref": args.against, "commit": other[1]}},
        "roofline": roofline, "cases": {}}
    for t, info in result["trees"].items():
        first = next((rs[0] for per_tree in runs.values() for tt, rs in per_tree.items() if tt == t and rs), None)
        if info is not None and first is not None:
            info.update({"root": portable_path(trees[t]), "gausslite_file": first["gausslite_file"]})
    for name, per_tree in runs.items():
        blk = {t: summarise_tree(rs, roofline["fma_gflops_1"], roofline["fma_gflops_all"], roofline["threads_all"])
               for t, rs in per_tree.items()}
        if "that" in blk:
            blk["ratio"] = ratios(blk["this"], blk["that"])
        result["cases"][name] = blk
    result["load_average"] = {"before": load_before, "after": list(os.getloadavg())}
    result["wall_s"] = time.perf_counter() - t_start
    md = table(result)
    default_out = RESULTS if args.isa == "native" else RESULTS.with_name(f"throughput_{args.isa}.json")
    publish(args.out if args.out is not None else (None if args.quick else default_out), "throughput", argv, md,
            result)
    return result


@contextmanager
def _nothing():
    yield None


if __name__ == "__main__":
    main()
