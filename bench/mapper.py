"""Mapper speed benchmark: seconds per keyframe and map quality, today's settings vs fast.

    python -m bench.mapper [--seeds 3] [--scenes room0,synthetic] [--tasks all|N] [--settings baseline,fast]

Scenes, each mapped with full GaussLite once per task and seed (offline, fixed iterations per frame):

- ``room0``: Replica room0 (``$GAUSSLITE_SHARED/datasets``), first 20 frames at 300×170 (downscale 4), every task.
- ``synthetic``: the default synthetic scene (``make-scene`` arcs, agent_a, 30 frames) at 160×120,
  generated once into ``runs/bench_mapper``; every task of agent_a.

Settings are :data:`gausslite.mapping.profiles.SPEED_PRESETS` on top of the scene's sensor profile:
``baseline`` (the mapper as configured) and ``fast``. Runs go one at a time in this process with the
default rasterizer threads (min(2, cores)), so that seconds are comparable; do not run other work
beside it. ``s_per_keyframe`` is the mean ``map_frame`` time (seeding, iterations, density control,
contribution update); ``roi_psnr`` the task's ROI PSNR over the mapped frames, ``psnr`` the full-image
PSNR; each is the mean over tasks of a seed, then mean ± std over seeds.

Writes ``bench/results/mapper.json`` as ``{"scenes": {"<scene>": {"baseline": {"s_per_keyframe", "roi_psnr",
"psnr", ...}, "fast": {...}, "speedup": .., "roi_psnr_loss": ..}}}`` and ``mapper.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from bench._results import write_results
from gausslite.datasets import detect_layout, load_dataset
from gausslite.config import load_mapper_config
from gausslite.mapping.profiles import SPEED_PRESETS, profile_for_layout
from gausslite.pipeline import run_mapping
from gausslite.stats import aggregate, fmt, mean_std
from gausslite.synthetic import make_scene

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
RESULTS = REPO / "bench" / "results"
WORK = REPO / "runs" / "bench_mapper"

SCENES = {
    "room0": {"downscale": 4.0, "max_frames": 20},
    "synthetic": {"downscale": 1.0, "max_frames": None, "width": 160, "height": 120},
}


def scene_dataset(name: str, max_frames: Optional[int] = None):
    """(dataset, sensor profile, task ids) of a bench scene (``max_frames`` overrides the scene's count)."""
    spec = SCENES[name]
    if name == "room0":
        path = SHARED / "datasets" / "Replica_room0"
        if not path.is_dir():
            raise FileNotFoundError(f"{path} not found (set GAUSSLITE_SHARED)")
    else:
        out = WORK / f"synthetic_{spec['width']}x{spec['height']}"
        if not (out / "agent_a").is_dir():
            make_scene(out, width=spec["width"], height=spec["height"], progress=False, agents=("agent_a",))
        path = out / "agent_a"
    profile = profile_for_layout(detect_layout(path)[0])
    ds = load_dataset(path, downscale=spec["downscale"], max_frames=max_frames or spec["max_frames"],
                      **profile.loader)
    return ds, profile, task_ids(path)


def task_ids(path: Path) -> list[str]:
    """Task ids of the ``tasks.json`` next to (or above) a dataset folder."""
    for p in (path, path.parent):
        f = p / "tasks.json"
        if f.exists():
            d = json.loads(f.read_text())
            return [t["id"] for t in (d["tasks"] if isinstance(d, dict) else d)]
    raise FileNotFoundError(f"no tasks.json at {path} or its parent")


def run_one(ds, profile, setting: str, task: str, seed: int) -> dict:
    """Map ``ds`` with full GaussLite for one task, seed and speed setting; times and scores."""
    defaults = {**profile.mapper, **SPEED_PRESETS[setting]}
    cfg = load_mapper_config(None, [], defaults=defaults, mode="gausslite", seed=seed)
    t0 = time.perf_counter()
    mapper, m = run_mapping(ds, cfg, task_id=task, out_dir=None, progress=False)
    secs = [s.seconds for s in mapper.stats]
    return {"setting": setting, "task": task, "seed": seed, "s_per_keyframe": float(np.mean(secs)),
            "iters_per_keyframe": float(np.mean([s.iters for s in mapper.stats])),
            "roi_psnr": float(m["roi_psnr"]), "psnr": float(m["psnr"]), "n_gaussians": len(mapper.model),
            "wall_s": time.perf_counter() - t0}


def summarise(runs: list[dict], settings: list[str], seeds: list[int]) -> dict:
    """Per setting: each field averaged over tasks within a seed, then mean ± std over seeds; and the
    speed-up and ROI PSNR loss of every non-baseline setting against ``baseline`` (paired per seed)."""
    fields = ["s_per_keyframe", "roi_psnr", "psnr", "n_gaussians", "iters_per_keyframe"]
    out: dict = {}
    per_seed: dict[str, list[dict]] = {}
    for st in settings:
        by_seed = []
        for s in seeds:
            rs = [r for r in runs if r["setting"] == st and r["seed"] == s]
            if rs:
                by_seed.append({f: float(np.mean([r[f] for r in rs])) for f in fields})
        per_seed[st] = by_seed
        block = aggregate(by_seed, fields)
        block["roi_psnr_per_task"] = {
            t: dict(zip(("roi_psnr", "roi_psnr_std"),
                        mean_std([r["roi_psnr"] for r in runs if r["setting"] == st and r["task"] == t])))
            for t in sorted({r["task"] for r in runs})}
        block["seeds"] = [s for s in seeds if any(r["setting"] == st and r["seed"] == s for r in runs)]
        out[st] = block
    base = per_seed.get("baseline", [])
    for st in settings:
        if st == "baseline" or len(per_seed[st]) != len(base) or not base:
            continue
        sp = [b["s_per_keyframe"] / f["s_per_keyframe"] for b, f in zip(base, per_seed[st])]
        loss = [b["roi_psnr"] - f["roi_psnr"] for b, f in zip(base, per_seed[st])]
        key = "" if st == "fast" else f"_{st}"
        out[f"speedup{key}"], out[f"speedup{key}_std"] = mean_std(sp)
        out[f"roi_psnr_loss{key}"], out[f"roi_psnr_loss{key}_std"] = mean_std(loss)
    return out


def table(result: dict) -> str:
    """Markdown table of a result."""
    lines = ["| scene | setting | s / keyframe | iters / keyframe | ROI PSNR [dB] | PSNR [dB] | Gaussians |",
             "|---|---|---|---|---|---|---|"]
    for scene, blk in result["scenes"].items():
        for st in result["settings"]:
            b = blk.get(st)
            if not b:
                continue
            f = lambda d, k, n=2: fmt(d.get(k), d.get(f"{k}_std"), n)  # noqa: E731
            lines.append(f"| {scene} | {st} | {f(b, 's_per_keyframe', 3)} | {b['iters_per_keyframe']:.0f} | "
                         f"{f(b, 'roi_psnr')} | {f(b, 'psnr')} | {b['n_gaussians']:,.0f} |")
        if "speedup" in blk:
            g = lambda k: fmt(blk.get(k), blk.get(f"{k}_std"))  # noqa: E731
            lines.append(f"| {scene} | **fast vs baseline** | **{g('speedup')}× faster** | | "
                         f"**loss {g('roi_psnr_loss')}** | | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.mapper", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="room0,synthetic")
    ap.add_argument("--settings", default="baseline,fast", help="comma list of SPEED_PRESETS names")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--tasks", default="all", help="'all' or the first N tasks of each scene")
    ap.add_argument("--max-frames", type=int, default=None, help="override the scenes' frame counts (smoke runs)")
    ap.add_argument("--out", type=Path, default=RESULTS / "mapper.json")
    args = ap.parse_args(argv)

    torch.set_num_threads(1)
    settings = [s for s in args.settings.split(",") if s]
    for st in settings:
        if st not in SPEED_PRESETS:
            ap.error(f"unknown setting {st!r}; known: {', '.join(SPEED_PRESETS)}")
    seeds = list(range(args.seeds))
    result: dict = {"settings": settings, "presets": {s: SPEED_PRESETS[s] for s in settings}, "seeds": seeds,
                    "machine": {"cpus": os.cpu_count(), "platform": platform.platform()}, "scenes": {}}
    t_start = time.perf_counter()
    for scene in [s for s in args.scenes.split(",") if s]:
        if scene not in SCENES:
            ap.error(f"unknown scene {scene!r}; known: {', '.join(SCENES)}")
        ds, profile, tasks = scene_dataset(scene, args.max_frames)
        if args.tasks != "all":
            tasks = tasks[: int(args.tasks)]
        jobs = [(st, t, s) for s in seeds for t in tasks for st in settings]
        runs = []
        for st, t, s in tqdm(jobs, desc=f"bench.mapper {scene}", unit="run"):
            r = run_one(ds, profile, st, t, s)
            r["scene"] = scene
            runs.append(r)
            tqdm.write(f"{scene} {st:9s} {t:22s} seed {s}: {r['s_per_keyframe']:.2f} s/kf, ROI {r['roi_psnr']:.2f} dB, "
                       f"PSNR {r['psnr']:.2f} dB, {r['n_gaussians']} G")
        blk = summarise(runs, settings, seeds)
        blk.update({"tasks": tasks, "frames": len(ds), "width": ds[0].intrinsics.width,
                    "height": ds[0].intrinsics.height, "runs": runs})
        result["scenes"][scene] = blk
        result["wall_s"] = time.perf_counter() - t_start
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))  # after every scene: a long run keeps what it measured
    md_path = write_results(args.out, "mapper", argv, f" ({len(seeds)} seeds, {result['wall_s'] / 60:.0f} min)",
                            table(result))  # the JSON was written after every scene
    print(f"wrote {args.out} and {md_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
