"""Two resolutions, one map: the task region mapped at a finer resolution than the rest (``mapper.detail``).

    python -m bench.detail_resolution [--seeds 0,1,2] [--factor 4] [--roi-factor 1] [--iters 30] [--frames 48]
                                      [--stride 4] [--width 640] [--height 480] [--trajectory arcs]
                                      [--task synth-pick-object] [--cap 6000] [--work DIR] [--out PATH]

On the synthetic scene (generated once into ``--work``), GaussLite maps every ``--stride``-th frame at
1/``--factor`` of the native resolution with a fixed iteration count (no time budget: the figure is accuracy, not
speed), twice per seed and with the same Gaussian cap:

- **one resolution**: everything at 1/factor (``mapper.detail.enabled`` off);
- **two resolutions**: the same, and each keyframe's task region also given at 1/``--roi-factor``
  (a :class:`gausslite.mapping.detail.DetailView`, ``mapper.detail.enabled`` on).

The frames between the keyframes (held out) are rendered at the NATIVE resolution and scored against the
ground-truth task region: ROI PSNR and full-image PSNR per run, their mean ± standard deviation over seeds and the
gain of two resolutions over one, paired by seed. Writes ``bench/results/detail_resolution.{json,md}``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

import numpy as np
from tqdm import tqdm

from bench._results import write_results
from gausslite.datasets import load_dataset
from gausslite.datasets.common import downscale_frame
from gausslite.evaluation import score_view
from gausslite.mapping.config import MapperConfig, deep_merge
from gausslite.mapping.detail import DetailView
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.profiles import RENDERED
from gausslite.pipeline import gt_roi_fn
from gausslite.synthetic import make_scene

REPO = Path(__file__).resolve().parents[1]
VARIANTS = ("one resolution", "two resolutions")


def scene_path(work: Path, width: int, height: int, frames: int, trajectory: str) -> Path:
    """The synthetic scene's first robot's folder, generated into ``work`` unless it is there already."""
    out = work / f"synthetic_{trajectory}_{frames}_{width}x{height}"
    if not (out / "agent_a" / "results" / f"depth{frames - 1:06d}.png").exists():
        make_scene(out, frames=frames, width=width, height=height, trajectory=trajectory)
    return out / "agent_a"


def mapper_config(seed: int, iters: int, cap: int, detail: bool) -> MapperConfig:
    """GaussLite with the rendered-sequence profile, ``iters`` iterations per keyframe (a third of them warm-up),
    a Gaussian cap, and the task region at its own resolution or not."""
    return MapperConfig(**deep_merge(RENDERED.mapper, {
        "mode": "gausslite", "seed": seed, "iters_per_frame": iters, "warmup_iters": max(1, iters // 3),
        "budget": {"max_gaussians": cap}, "detail": {"enabled": detail}}))


def map_run(frames: list, roi_fn, factor: int, roi_factor: Optional[int], cfg: MapperConfig) -> tuple[Mapper, float]:
    """Map the native ``frames`` (keyframes, in order) at 1/``factor``, the region at 1/``roi_factor`` when given.
    Returns the mapper and the wall seconds it took."""
    mapper = Mapper(cfg)
    t0 = time.perf_counter()
    for fr in frames:
        coarse = downscale_frame(fr, factor)
        detail = None
        if roi_factor is not None:
            fine = downscale_frame(fr, roi_factor)
            detail = DetailView(fine, roi_fn(fine))
        mapper.map_frame(coarse, roi_fn(coarse), detail=detail)
    mapper.finalize()
    return mapper, time.perf_counter() - t0


def score(mapper: Mapper, frames: list, roi_fn) -> dict:
    """Mean ROI PSNR (frames whose task region is in view) and full-image PSNR of the held-out native frames."""
    roi, full = [], []
    for fr in frames:
        mask = roi_fn(fr)
        s = score_view(mapper.render_frame(fr), fr, mask if mask.any() else None)
        full.append(s.psnr)
        if mask.any() and np.isfinite(s.roi_psnr):
            roi.append(s.roi_psnr)
    return {"roi_psnr": float(np.mean(roi)) if roi else None, "psnr": float(np.mean(full)), "n_roi_frames": len(roi),
            "n_frames": len(full)}


def run(args) -> dict:
    """Every seed × variant; returns the JSON-ready results (runs, and per variant mean ± std and the paired gain)."""
    path = scene_path(Path(args.work), args.width, args.height, args.frames, args.trajectory)
    ds = load_dataset(path)
    roi_fn = gt_roi_fn(ds, args.task)
    keyframes = [ds[i] for i in range(0, len(ds), args.stride)]
    held_out = [ds[i] for i in range(args.stride // 2, len(ds), args.stride) if i % args.stride]
    runs = []
    jobs = [(s, v) for s in args.seeds for v in VARIANTS]
    for seed, variant in tqdm(jobs, desc="detail runs"):
        two = variant == VARIANTS[1]
        mapper, wall = map_run(keyframes, roi_fn, args.factor, args.roi_factor if two else None,
                               mapper_config(seed, args.iters, args.cap, two))
        sc = score(mapper, held_out, roi_fn)
        runs.append({"seed": seed, "variant": variant, **sc, "n_gaussians": len(mapper.model),
                     "n_roi_gaussians": int(mapper.model.active.sum()), "map_wall_s": wall,
                     "detail_px_mean": float(np.mean([s.detail_px for s in mapper.stats]))})
        tqdm.write(f"seed {seed} {variant}: ROI PSNR {sc['roi_psnr']:.2f} dB, PSNR {sc['psnr']:.2f} dB, "
                   f"{len(mapper.model)} G, {wall:.0f} s")
    summary = {}
    for v in VARIANTS:
        rs = [r for r in runs if r["variant"] == v]
        summary[v] = {k: [float(np.mean([r[k] for r in rs])), float(np.std([r[k] for r in rs]))]
                      for k in ("roi_psnr", "psnr", "n_roi_gaussians")}
    gain = {k: [r2[k] - r1[k] for r1, r2 in zip([r for r in runs if r["variant"] == VARIANTS[0]],
                                              [r for r in runs if r["variant"] == VARIANTS[1]])]
            for k in ("roi_psnr", "psnr")}
    summary["gain"] = {k: [float(np.mean(g)), float(np.std(g))] for k, g in gain.items()}
    return {"scene": {"path": str(path), "width": args.width, "height": args.height, "frames": args.frames,
                      "trajectory": args.trajectory, "task": args.task, "keyframes": len(keyframes),
                      "held_out": len(held_out)},
            "factor": args.factor, "roi_factor": args.roi_factor, "iters_per_frame": args.iters, "cap": args.cap,
            "seeds": list(args.seeds), "runs": runs, "summary": summary}


def table(res: dict) -> str:
    """Markdown: per variant ROI PSNR, PSNR (held-out frames at the native resolution) and ROI Gaussians."""
    s = res["summary"]
    w, h, f, rf = res["scene"]["width"], res["scene"]["height"], res["factor"], res["roi_factor"]
    rows = ["| variant | map | task region | ROI PSNR (dB) | PSNR (dB) | ROI Gaussians |", "|---|---|---|---|---|---|"]
    for v in VARIANTS:
        reg = f"{w // rf}×{h // rf}" if v == VARIANTS[1] else f"{w // f}×{h // f}"
        rows.append(f"| {v} | {w // f}×{h // f} | {reg} | {s[v]['roi_psnr'][0]:.2f} ± {s[v]['roi_psnr'][1]:.2f} | "
                    f"{s[v]['psnr'][0]:.2f} ± {s[v]['psnr'][1]:.2f} | {s[v]['n_roi_gaussians'][0]:.0f} |")
    g = s["gain"]
    rows.append(f"| gain (paired by seed) | | | {g['roi_psnr'][0]:+.2f} ± {g['roi_psnr'][1]:.2f} | "
                f"{g['psnr'][0]:+.2f} ± {g['psnr'][1]:.2f} | |")
    return "\n".join(rows)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="0,1,2", type=lambda t: [int(x) for x in t.split(",") if x])
    ap.add_argument("--factor", type=int, default=4, help="mapping downscale of the native frames")
    ap.add_argument("--roi-factor", type=int, default=1, help="downscale of the task region's detail view")
    ap.add_argument("--iters", type=int, default=30, help="iterations per keyframe")
    ap.add_argument("--frames", type=int, default=48, help="frames of the synthetic sequence")
    ap.add_argument("--stride", type=int, default=4, help="every n-th frame is a keyframe; the rest are held out")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--trajectory", default="arcs", choices=("arcs", "circle", "walk"))
    ap.add_argument("--task", default="synth-pick-object")
    ap.add_argument("--cap", type=int, default=6000, help="Gaussian cap of both variants")
    ap.add_argument("--work", default=str(Path(tempfile.gettempdir()) / "gausslite_bench_detail"))
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "detail_resolution.json"))
    args = ap.parse_args(argv)
    if args.roi_factor > args.factor:
        ap.error("--roi-factor must not exceed --factor")
    t0 = time.perf_counter()
    res = run(args)
    write_results(Path(args.out), "detail_resolution", argv, f": {len(args.seeds)} seeds, "
                  f"{(time.perf_counter() - t0) / 60:.1f} min", table(res), res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
