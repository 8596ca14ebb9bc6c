"""Benchmark: PSNR against optimisation iterations, this tree against another commit, on a rendered and a real scene.

Usage::

    python -m bench.quality_per_iteration --against 43a6a8d          # 2 scenes × 3 seeds × 2 trees: bench/results/...
    python -m bench.quality_per_iteration --quick                    # one tiny run per tree, prints only
    python -m bench.quality_per_iteration --against HEAD --set densify.split=axis --out F.json  # a setting's effect

A faster mapper must not buy its speed with a worse iteration: each iteration of this tree should leave the map as
good as one of the other. **Protocol.** Each run maps a scene offline with the live agent's mapper settings under the
scene's sensor profile (as :mod:`bench.throughput` configures them, mode ``gausslite``, one render thread, seeded),
``--iters-per-frame`` iterations per frame on the training frames (``--set KEY=VALUE``: mapper settings of this
tree's runs only) (the agent's 10 full-image warm-up iterations at
most all of them: at the default 10, each mapped frame gets full-image iterations only, and the task region its
ROI-phase iterations in the optimisation that follows) (every 5th frame withheld), then keeps optimising
over its keyframes (``Mapper.optimize(n_iters=...)``) and scores the map at each checkpoint of ``--checkpoints``
further iterations: PSNR over the training frames (``keyframes``) and over the withheld ones (``novel``), each
rendered by ``Mapper.render_frame`` at the frame's pose, and the task region's PSNR on both. The x axis is the
total number of Adam iterations so far. Scenes:

- ``rendered``: the embedded synthetic room (:func:`gausslite.synthetic.make_scene`, ``circle``, 72 frames at
  640 × 480, generated into ``--work``), loaded at 160 × 120, the ``rendered`` profile, task ``synth-pick-object``;
- ``tum``: TUM RGB-D fr1/rpy (``$GAUSSLITE_SHARED/datasets``), its first 40 frames at 160 × 120, the ``handheld``
  profile, task ``tum-find-mouse``.

Both trees run the same worker (this file, its ``gausslite`` imported from the tree by ``PYTHONPATH``, as
:func:`bench.throughput.run_worker` runs it), seed by seed in turn. The comparison is paired by seed: the mean
difference this − that at each checkpoint and its standard deviation over the seeds.

Output: a table (printed), and in full mode or with ``--out`` JSON through :mod:`bench._results` (``settings``,
``trees``, ``runs``: each run's ``curve`` of ``{"iters", "keyframes", "novel", "roi_keyframes", "roi_novel"}`` in dB,
and ``summary``: per scene and checkpoint the trees' means and the paired differences) and a PNG of the curves.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Optional

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results" / "quality_per_iteration.json"
WORK = REPO / "runs" / "bench_quality_per_iteration"
THIS_FILE = Path(__file__).resolve()
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
RESULT_TAG = "QUALITY_RESULT "
#: scene name → (kind, frames, downscale of the stored images, task)
SCENES = {"rendered": ("synthetic", 40, 4.0, "synth-pick-object"),
          "tum": ("tum", 40, 4.0, "tum-find-mouse")}
#: the quick run: the tiny synthetic scene (128 × 96) at 64 × 48
QUICK_SCENES = {"rendered": ("synthetic", 10, 2.0, "synth-pick-object")}
WITHHOLD_EVERY = 5


def _scene_path(kind: str, work: Path, quick: bool = False) -> Path:
    """The dataset folder of a scene kind (the synthetic one generated into ``work`` once; ``quick``: the tiny one)."""
    if kind == "tum":
        p = SHARED / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy"
        if not p.is_dir():
            raise FileNotFoundError(f"{p} not found (set GAUSSLITE_SHARED)")
        return p
    from bench.throughput import FULL_SCENE, QUICK_SCENE, ensure_scene

    return ensure_scene(work, QUICK_SCENE if quick else FULL_SCENE)


def _throughput():
    """:mod:`bench.throughput` of this file's tree, loaded by path: a worker's ``PYTHONPATH`` is the tree under test,
    whose ``bench`` may not have it (its ``mapper_config`` uses only library entry points both trees have)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("_gausslite_bench_throughput", THIS_FILE.parent / "throughput.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _finite(xs: list) -> list:
    """``xs`` without None, NaN and infinities (a region that renders exactly scores an infinite PSNR), as floats."""
    return [float(x) for x in xs if x is not None and math.isfinite(float(x))]


def _mean(xs: list) -> Optional[float]:
    xs = _finite(xs)
    return float(sum(xs) / len(xs)) if xs else None


def _std(xs: list) -> Optional[float]:
    xs = _finite(xs)
    return statistics.stdev(xs) if len(xs) > 1 else None


def worker(spec: dict) -> dict:
    """One run in this process (module docstring, "Protocol"): ``spec`` holds ``scene``, ``kind``, ``path``,
    ``frames``, ``downscale``, ``task``, ``seed``, ``iters_per_frame``, ``checkpoints``. Uses only entry points both
    trees have (``load_config``, ``with_profile``, ``Mapper``, ``map_frame``, ``optimize(n_iters=)``,
    ``render_frame``, :func:`gausslite.evaluation.score_view`)."""
    import torch

    import gausslite
    from gausslite.datasets import load_dataset
    from gausslite.evaluation import score_view
    from gausslite.mapping.mapper import Mapper
    from gausslite.mapping.profiles import HANDHELD, RENDERED
    from gausslite.pipeline import gt_roi_fn

    torch.set_num_threads(1)
    name, profile = ("handheld", HANDHELD) if spec["kind"] == "tum" else ("rendered", RENDERED)
    ds = load_dataset(spec["path"], downscale=spec["downscale"], max_frames=spec["frames"], **profile.loader)
    roi = gt_roi_fn(ds, spec["task"])
    ipf = int(spec["iters_per_frame"])
    tp = _throughput()
    # the mapped frames' iterations: ipf, the full-image warm-up at most all of them
    sets = list(spec.get("overrides", []))
    cfg = tp.mapper_config(name, sets, {"mode": "gausslite", "seed": int(spec["seed"]), "iters_per_frame": ipf,
                                        "warmup_iters": min(int(tp.mapper_config(name, sets).warmup_iters), ipf)})
    n = min(len(ds), int(spec["frames"]))
    train = [i for i in range(n) if i % WITHHOLD_EVERY != WITHHOLD_EVERY - 1]
    test = [i for i in range(n) if i % WITHHOLD_EVERY == WITHHOLD_EVERY - 1]
    mapper = Mapper(cfg)
    t0 = time.perf_counter()
    for i in train:
        fr = ds[i]
        mapper.map_frame(fr, roi(fr))

    def score(ids: list) -> tuple[float, Optional[float]]:
        with torch.no_grad():
            s = [score_view(mapper.render_frame(ds[i]), ds[i], roi(ds[i])) for i in ids]
        return _mean([x.psnr for x in s]), _mean([x.roi_psnr for x in s])

    done = len(train) * cfg.iters_per_frame
    curve = []
    extra = 0
    for cp in [0] + list(spec["checkpoints"]):
        if cp > extra:
            mapper.optimize(n_iters=cp - extra)
            extra = cp
        k, rk = score(train)
        v, rv = score(test)
        curve.append({"iters": done + extra, "keyframes": k, "novel": v, "roi_keyframes": rk, "roi_novel": rv})
    return {"scene": spec["scene"], "seed": spec["seed"], "curve": curve, "n_gaussians": len(mapper.model),
            "seconds": time.perf_counter() - t0, "gausslite_file": str(Path(gausslite.__file__).resolve())}


def summarise(runs: list[dict]) -> dict:
    """Per scene and checkpoint: each tree's mean over seeds and the paired difference this − that (mean, std)."""
    out: dict = {}
    for scene in sorted({r["scene"] for r in runs}):
        rows = []
        this = {r["seed"]: r for r in runs if r["scene"] == scene and r["tree"] == "this"}
        that = {r["seed"]: r for r in runs if r["scene"] == scene and r["tree"] == "that"}
        n_cp = len(next(iter(this.values()))["curve"])
        for j in range(n_cp):
            row = {"iters": next(iter(this.values()))["curve"][j]["iters"]}
            for key in ("keyframes", "novel", "roi_keyframes", "roi_novel"):
                row[f"this_{key}"] = _mean([r["curve"][j][key] for r in this.values()])
                row[f"that_{key}"] = _mean([r["curve"][j][key] for r in that.values()]) if that else None
                diffs = _finite([this[s]["curve"][j][key] - that[s]["curve"][j][key] for s in this
                                 if s in that and _finite([this[s]["curve"][j][key], that[s]["curve"][j][key]])
                                 and len(_finite([this[s]["curve"][j][key], that[s]["curve"][j][key]])) == 2])
                row[f"diff_{key}"] = _mean(diffs)
                row[f"diff_{key}_std"] = _std(diffs)
            rows.append(row)
        out[scene] = rows
    return out


def _f(x: Optional[float], sign: bool = False) -> str:
    return "–" if x is None else (f"{x:+.2f}" if sign else f"{x:.2f}")


def table(summary: dict) -> str:
    """Markdown: per scene and checkpoint, the trees' PSNR (training frames, withheld frames) and the paired
    difference ± its std over seeds."""
    lines = ["| scene | iterations | keyframes this / that | Δ keyframes | novel this / that | Δ novel | "
             "ROI novel this / that | Δ ROI novel |", "|---|---|---|---|---|---|---|---|"]
    for scene, rows in summary.items():
        for r in rows:
            cells = [scene, f"{r['iters']:,}"]
            for key in ("keyframes", "novel", "roi_novel"):
                cells.append(f"{_f(r[f'this_{key}'])} / {_f(r[f'that_{key}'])}")
                sd = r[f"diff_{key}_std"]
                cells.append(_f(r[f"diff_{key}"], True) + ("" if sd is None else f" ± {sd:.2f}"))
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(summary: dict, runs: list[dict], dest: Path) -> None:
    """PNG: per scene, PSNR on training and withheld frames against iterations, each run thin, the means thick."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(summary), figsize=(5.5 * len(summary), 4), squeeze=False)
    for ax, (scene, rows) in zip(axes[0], summary.items()):
        for tree, colour in (("this", "tab:blue"), ("that", "tab:orange")):
            for r in runs:
                if r["scene"] == scene and r["tree"] == tree:
                    xs = [c["iters"] for c in r["curve"]]
                    ax.plot(xs, [c["keyframes"] for c in r["curve"]], color=colour, alpha=0.25, lw=0.8)
                    ax.plot(xs, [c["novel"] for c in r["curve"]], color=colour, alpha=0.25, lw=0.8, ls="--")
            xs = [r["iters"] for r in rows]
            if rows[0][f"{tree}_keyframes"] is None:
                continue
            ax.plot(xs, [r[f"{tree}_keyframes"] for r in rows], color=colour, lw=2, label=f"{tree}: keyframes")
            ax.plot(xs, [r[f"{tree}_novel"] for r in rows], color=colour, lw=2, ls="--", label=f"{tree}: novel")
        ax.set_title(scene)
        ax.set_xlabel("Adam iterations")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(dest, dpi=110)
    plt.close(fig)


def _parse(argv) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m bench.quality_per_iteration", description=__doc__.splitlines()[0])
    ap.add_argument("--against", metavar="COMMIT", help="also run every seed for COMMIT (a git worktree)")
    ap.add_argument("--quick", action="store_true", help="one tiny run per tree; prints only unless --out is given")
    ap.add_argument("--scenes", default=None, help=f"comma list of {', '.join(SCENES)} (default: all)")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per scene and tree (quick: 1)")
    ap.add_argument("--iters-per-frame", type=int, default=10, help="iterations per mapped frame (quick: 3)")
    ap.add_argument("--checkpoints", default="100,300,600",
                    help="further iterations after mapping at which the map is scored (quick: 10)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="a mapper setting for this tree's runs only (e.g. densify.split=axis; repeatable): with "
                         "--against HEAD, the setting against the committed default")
    ap.add_argument("--work", type=Path, default=WORK, help="where the synthetic scene is generated once")
    ap.add_argument("--out", type=Path, default=None, help=f"JSON output (default {RESULTS} unless --quick)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    """Run the benchmark (module docstring); returns the result dict."""
    args = _parse(argv)
    if args.worker:
        res = worker(json.loads(args.worker))
        print(RESULT_TAG + json.dumps(res), flush=True)
        return res
    from tqdm import tqdm

    from bench._results import portable_path, publish
    from bench.throughput import git, run_worker, worktree

    t_start = time.perf_counter()
    scenes = QUICK_SCENES if args.quick else SCENES
    if args.scenes:
        unknown = sorted(set(args.scenes.split(",")) - set(SCENES))
        if unknown:
            raise SystemExit(f"unknown scene(s) {', '.join(unknown)}; known: {', '.join(SCENES)}")
        scenes = {k: SCENES[k] for k in args.scenes.split(",")}
    seeds = 1 if args.quick else args.seeds
    checkpoints = [10] if args.quick else [int(c) for c in args.checkpoints.split(",") if c]
    ipf = 3 if args.quick else args.iters_per_frame
    specs = []
    for name, (kind, frames, downscale, task) in scenes.items():
        path = _scene_path(kind, args.work, args.quick)
        for seed in range(seeds):
            specs.append({"name": f"{name}/{seed}", "scene": name, "kind": kind, "path": str(path), "frames": frames,
                          "downscale": downscale, "task": task, "seed": seed, "iters_per_frame": ipf,
                          "checkpoints": checkpoints})
    from contextlib import nullcontext

    runs: list[dict] = []
    with (worktree(args.against) if args.against else nullcontext()) as other:
        trees = {"this": REPO} if other is None else {"this": REPO, "that": other[0]}
        jobs = [(s, t) for s in specs for t in trees]
        for spec, t in tqdm(jobs, desc="bench.quality_per_iteration", unit="run"):
            res = run_worker(trees[t], spec | ({"overrides": args.overrides} if t == "this" else {}),
                             script=THIS_FILE, tag=RESULT_TAG)
            res["tree"] = t
            runs.append(res)
            last = res["curve"][-1]
            tqdm.write(f"{spec['name']:<12} {t:<5} {last['iters']:>6,} it: keyframes {last['keyframes']:.2f} dB, "
                       f"novel {last['novel']:.2f} dB ({res['seconds']:.0f} s)")
    summary = summarise(runs)
    result = {"settings": {"quick": args.quick, "seeds": seeds, "iters_per_frame": ipf, "checkpoints": checkpoints,
                           "overrides_this": args.overrides,
                           "withhold_every": WITHHOLD_EVERY,
                           "scenes": {k: {"kind": v[0], "frames": v[1], "downscale": v[2], "task": v[3]}
                                      for k, v in scenes.items()}},
              "trees": {"this": {"commit": git("rev-parse", "HEAD")},
                        "that": None if other is None else {"ref": args.against, "commit": other[1]}},
              "runs": [{k: v for k, v in r.items() if k != "gausslite_file"} | {"gausslite_file": portable_path(
                  Path(r["gausslite_file"]))} for r in runs],
              "summary": summary, "wall_s": time.perf_counter() - t_start}
    md = table(summary)
    dest = args.out if args.out is not None else (None if args.quick else RESULTS)
    publish(dest, "quality_per_iteration", argv, md, result)
    if dest is not None:
        plot(summary, runs, dest.with_suffix(".png"))
    return result


if __name__ == "__main__":
    main()
