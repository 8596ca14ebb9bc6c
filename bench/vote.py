"""Voxel-vote fusion benchmark: 1M Gaussians from two agents on one core (target <= 1 s).

Two agents map the same synthetic room (:func:`bench.codec.synthetic_room`) with different ROI
clusters (high κ) and 1 cm pose offset; :func:`gausslite.fusion.voxel_vote` (δ = 0.10 m, paper
Sec. III-E) is timed against the :func:`gausslite.fusion.concat` baseline, with numpy / torch
limited to one thread.

Usage::

    python -m bench.vote [--quick] [--n 1000000] [--out bench/results/vote.json]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from bench._results import write_json
from bench.codec import synthetic_room
from gausslite.fusion import concat, voxel_vote

RESULTS = Path(__file__).resolve().parent / "results"


def _time(fn, repeats: int) -> tuple[float, float, object]:
    ts, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return min(ts), float(np.median(ts)), out


def main(argv: Optional[list[str]] = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m bench.vote", description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="100k Gaussians, 2 repeats")
    ap.add_argument("--n", type=int, default=1_000_000, help="total Gaussians (both agents)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--voxel", type=float, default=0.10)
    ap.add_argument("--out", type=Path, default=RESULTS / "vote.json")
    args = ap.parse_args(argv)
    n = 100_000 if args.quick else args.n
    reps = 2 if args.quick else args.repeats

    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")

    half = n // 2
    maps = {
        "agent_a": synthetic_room(half, seed=1, roi_center=(5.0, 2.0, 0.9)),
        "agent_b": synthetic_room(n - half, seed=2, roi_center=(2.0, 1.5, 1.0),
                                  offset=(0.01, -0.01, 0.005)),
    }
    t_vote_min, t_vote_med, (fused, report) = _time(lambda: voxel_vote(maps, args.voxel), reps)
    t_cat_min, t_cat_med, cat = _time(lambda: concat(maps), reps)
    gm = {k: v.to_gaussian_map() for k, v in maps.items()}
    t_gm_min, t_gm_med, _ = _time(lambda: voxel_vote(gm, args.voxel), max(1, reps // 2))

    rows = [
        ("voxel_vote (numpy in)", t_vote_min, t_vote_med, len(fused)),
        ("voxel_vote (GaussianMap in)", t_gm_min, t_gm_med, len(fused)),
        ("concat baseline", t_cat_min, t_cat_med, len(cat)),
    ]
    print(f"{n} Gaussians ({half} + {n - half}), δ = {args.voxel} m, 1 thread, {reps} repeats")
    print(f"{'method':30s} {'min s':>8s} {'median s':>9s} {'output N':>10s} {'MG/s':>7s}")
    for name, tmin, tmed, m in rows:
        print(f"{name:30s} {tmin:8.3f} {tmed:9.3f} {m:10d} {n / tmin / 1e6:7.2f}")
    print(f"voxels {report.voxels}, contested {report.contested_voxels}, kept {report.kept}, "
          f"dropped {report.dropped}, won {report.won_voxels}")
    target = 1.0
    print(f"target <= {target} s for 1M: {'met' if t_vote_min <= target else 'MISSED'}"
          + ("" if n == 1_000_000 else f" (measured at N = {n})"))
    result = {
        "benchmark": "vote", "n": n, "quick": bool(args.quick), "repeats": reps,
        "voxel_size": args.voxel, "threads": 1,
        "vote_s_min": t_vote_min, "vote_s_median": t_vote_med,
        "vote_gaussianmap_s_min": t_gm_min, "concat_s_min": t_cat_min,
        "target_s": target, "target_met": bool(t_vote_min <= target),
        "fused_n": len(fused), "report": report.to_dict(),
        "machine": {"python": platform.python_version(), "numpy": np.__version__,
                    "processor": platform.processor() or platform.machine()},
    }
    write_json(args.out, result, "vote", argv)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
