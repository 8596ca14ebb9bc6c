"""Benchmark: fwd+bwd time and peak RSS of the Warp rasterizer (SIMD compositing kernels, and the Warp
tile kernels they replace) vs the pure-PyTorch reference.

Usage::

    python -m bench.rasterizer            # (20k, 320x240) and (100k, 640x480), writes JSON
    python -m bench.rasterizer --quick    # small sizes, prints only (unless --out is given)

Each (backend, size) runs in its own subprocess so that peak RSS (``ru_maxrss``, which includes
the Python/torch/warp baseline of the process) is not polluted by the other runs. A run is one
warm-up iteration followed by ``repeats`` timed iterations of: ``rasterize`` forward, a random
linear loss on colour + depth + alpha, and ``backward``; the median is reported.

Scenes: N Gaussians uniformly inside the camera frustum 1-5 m ahead, isotropic-ish scales of
1-3 cm (per axis), random rotations, opacities sigmoid(N(0, 1)), colours U(0, 1);
intrinsics fx = fy = 0.82 W (roughly a Kinect-like 64 deg horizontal field of view).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

from bench._results import write_json
from gausslite.render import rasterize

import numpy as np
import torch

RESULTS = Path(__file__).resolve().parent / "results" / "rasterizer.json"
FULL_SIZES = [(20000, 320, 240), (100000, 640, 480)]
QUICK_SIZES = [(2000, 160, 120), (5000, 320, 240)]


def make_scene(n: int, width: int, height: int, seed: int = 0):
    """Random plausible scene: returns (params list requiring grad, K (3,3) float64 numpy)."""
    g = torch.Generator().manual_seed(seed)
    f = 0.82 * width
    z = torch.rand(n, generator=g) * 4 + 1
    x = (torch.rand(n, generator=g) - 0.5) * z * width / f
    y = (torch.rand(n, generator=g) - 0.5) * z * height / f
    params = [
        torch.stack([x, y, z], 1),
        torch.randn(n, 4, generator=g),
        torch.log(torch.rand(n, 3, generator=g) * 0.02 + 0.01),
        torch.randn(n, generator=g),
        torch.rand(n, 3, generator=g),
    ]
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    return [p.requires_grad_() for p in params], K


def worker(backend: str, n: int, width: int, height: int, repeats: int) -> dict:
    """Time fwd+bwd in this process; returns timings (s) and peak RSS (MB)."""
    params, K = make_scene(n, width, height)
    g = torch.Generator().manual_seed(1)
    wc, wd, wa = torch.randn(height, width, 3, generator=g), torch.randn(height, width, generator=g), \
        torch.randn(height, width, generator=g)
    fwd, tot = [], []
    out = None
    kw = {"cpu_kernel": "tile"} if backend == "warp-tile" else {}
    backend = "warp" if backend == "warp-tile" else backend
    for it in range(repeats + 1):
        for p in params:
            p.grad = None
        t0 = time.perf_counter()
        out = rasterize(*params, K=K, width=width, height=height, viewmat=np.eye(4), backend=backend, **kw)
        t1 = time.perf_counter()
        loss = (out.color * wc).sum() + (out.depth * wd).sum() + (out.alpha * wa).sum()
        loss.backward()
        t2 = time.perf_counter()
        if it > 0:
            fwd.append(t1 - t0)
            tot.append(t2 - t0)
    return {
        "backend": backend + ("-tile" if kw else ""), "n": n, "width": width, "height": height, "repeats": repeats,
        "fwd_bwd_median_s": statistics.median(tot), "fwd_median_s": statistics.median(fwd),
        "fwd_bwd_all_s": tot,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "visible": int((out.radii > 0).sum()),
        "mean_alpha": float(out.alpha.mean()),
        "torch_threads": torch.get_num_threads(),
    }


def _run_sub(backend: str, n: int, w: int, h: int, repeats: int) -> dict:
    cmd = [sys.executable, "-m", "bench.rasterizer", "--worker", backend, "--n", str(n),
           "--width", str(w), "--height", str(h), "--repeats", str(repeats)]
    root = Path(__file__).resolve().parents[1]
    res = subprocess.run(cmd, cwd=root, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"benchmark worker failed ({' '.join(cmd)}):\n{res.stderr[-4000:]}")
    line = [ln for ln in res.stdout.splitlines() if ln.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def _key(n: int, w: int, h: int) -> str:
    return f"{n // 1000}k_{w}x{h}" if n % 1000 == 0 else f"{n}_{w}x{h}"


def main(argv=None) -> dict:
    """Run the benchmark, print a table, write JSON (full mode or when --out is given)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (seconds), print only")
    ap.add_argument("--repeats", type=int, default=5, help="timed iterations for the warp kernel")
    ap.add_argument("--ref-repeats", type=int, default=2, help="timed iterations for the reference")
    ap.add_argument("--out", type=Path, default=None, help=f"JSON output (default {RESULTS} in full mode)")
    ap.add_argument("--worker", choices=["warp", "warp-tile", "torch"], help=argparse.SUPPRESS)
    ap.add_argument("--n", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--width", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--height", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.worker:
        r = worker(args.worker, args.n, args.width, args.height, args.repeats)
        print("RESULT " + json.dumps(r), flush=True)
        return r

    sizes = QUICK_SIZES if args.quick else FULL_SIZES
    out: dict = {"machine": {"cpu_count": os.cpu_count(), "loadavg_before": list(os.getloadavg())},
                 "runs": []}
    rows = []
    for n, w, h in sizes:
        ours = _run_sub("warp", n, w, h, args.repeats)
        tile = _run_sub("warp-tile", n, w, h, args.repeats)
        ref = _run_sub("torch", n, w, h, args.ref_repeats)
        k = _key(n, w, h)
        out[f"tile_s_{k}"] = tile["fwd_bwd_median_s"]
        out[f"simd_vs_tile_{k}"] = tile["fwd_bwd_median_s"] / ours["fwd_bwd_median_s"]
        out[f"ours_s_{k}"] = ours["fwd_bwd_median_s"]
        out[f"ref_s_{k}"] = ref["fwd_bwd_median_s"]
        out[f"speedup_{k}"] = ref["fwd_bwd_median_s"] / ours["fwd_bwd_median_s"]
        out[f"peak_rss_mb_{k}"] = ours["peak_rss_mb"]
        out[f"ref_peak_rss_mb_{k}"] = ref["peak_rss_mb"]
        out["runs"] += [ours, tile, ref]
        rows.append((k, ours, tile, ref))
    out["machine"]["loadavg_after"] = list(os.getloadavg())

    hdr = f"{'size':<16}{'backend':<10}{'fwd+bwd s':>11}{'fwd s':>9}{'peak RSS MB':>13}{'visible':>9}"
    print(hdr)
    print("-" * len(hdr))
    for k, ours, tile, ref in rows:
        for r in (ours, tile, ref):
            print(f"{k:<16}{r['backend']:<10}{r['fwd_bwd_median_s']:>11.3f}{r['fwd_median_s']:>9.3f}"
                  f"{r['peak_rss_mb']:>13.0f}{r['visible']:>9d}")
        print(f"{k:<16}{'vs torch':<10}{ref['fwd_bwd_median_s'] / ours['fwd_bwd_median_s']:>11.1f}x")
        print(f"{k:<16}{'vs tile':<10}{tile['fwd_bwd_median_s'] / ours['fwd_bwd_median_s']:>11.2f}x")
    print(f"load average before/after: {out['machine']['loadavg_before']} / {out['machine']['loadavg_after']}")

    dest = args.out if args.out is not None else (None if args.quick else RESULTS)
    if dest is not None:
        write_json(dest, out, "rasterizer", argv)
        print(f"wrote {dest}")
    return out


if __name__ == "__main__":
    main()
