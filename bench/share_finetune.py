"""Fused map against the agents' own maps: fine-tuned subsets, the neighbourhood vote and
the refinement schedule, on two agents mapping Replica room0.

    python -m bench.share_finetune [--seeds 3] [--finetune-iters 200] [--refine-iters 100]

Two agents map the same 20 room0 frames (300×170) with the deployed agent settings (full GaussLite,
30 iterations and 1,500 seeds per frame, every 2nd frame a keyframe) and ``roi_render: context``, one per
task (room0-pick-plant, room0-find-ottoman), with the ground-truth ROI as relevance (the sim uses the
attention front-end; this bench isolates the sharing and fusion steps). Each agent selects its task subset
(``select_task_subset``, coverage 0.99) and fine-tunes a copy alone on its ROI keyframes
(:func:`gausslite.sharing.finetune_subset`). Per task, ROI PSNR over the 20 frames of:

- ``own``: the agent's whole map (what the robot has);
- ``alone_raw`` / ``alone_ft``: the shared subset rendered alone, before / after fine-tuning;
- ``vote_r0`` / ``vote_r1``: the voxel vote (δ = 0.10 m) of the two fine-tuned subsets, per-voxel (the
  paper's rule) / contested over each voxel's 3×3×3 neighbourhood;
- ``refine_foot`` / ``refine_roi``: ``vote_r1`` jointly refined (``refine_map``, 100 iterations over every
  2nd keyframe of both agents) with the loss on the rendered footprint / on the footprint within each
  keyframe's ROI (the agents send their ROI with their keyframes);
- ``refine_roi_cos``: as ``refine_roi`` with the learning rate on a cosine down to 5 %.

Mean ± std over seeds. Writes ``bench/results/share_finetune.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from bench._results import write_results
from bench.delta_tolerance import SHARE_RULE, agent_mapper
from gausslite.datasets import load_dataset
from gausslite.evaluation import evaluate_fused
from gausslite.fusion.refine import refine_map
from gausslite.fusion.vote import voxel_vote
from gausslite.mapping.mapper import Mapper
from gausslite.pipeline import gt_roi_fn
from gausslite.sharing import finetune_subset, select_task_subset
from gausslite.stats import fmt, mean_std
from gausslite.wire.codec import GaussianArrays

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
RESULTS = REPO / "bench" / "results"
TASKS = ("room0-pick-plant", "room0-find-ottoman")
FIELDS = ("own", "alone_raw", "alone_ft", "vote_r0", "vote_r1", "refine_foot", "refine_roi", "refine_roi_cos")


def run_seed(args, seed: int) -> dict:
    """One seed: map both agents, fine-tune, vote, refine; ROI PSNR per task and variant."""
    torch.set_num_threads(1)
    ds = load_dataset(args.dataset, downscale=args.downscale, max_frames=args.max_frames)
    frames = [ds[i] for i in range(len(ds))]

    def score(g, task):
        return evaluate_fused(GaussianArrays.from_any(g).to_gaussian_map(), frames, ds.annotations, task)

    out = {t: {} for t in TASKS}
    subs, refine_kfs = {}, []
    for task in TASKS:
        roi_fn = gt_roi_fn(ds, task)
        mapper = Mapper(agent_mapper(seed, ["mapper.roi_render=context"]))
        for fr in frames:
            mapper.map_frame(fr, roi_fn(fr))
        out[task]["own"] = score(mapper.gmap, task)
        kfs = [mapper.keyframes.load(i, mapper.device) for i in range(len(mapper.keyframes))]
        mask, _ = select_task_subset(mapper.gmap, kfs, SHARE_RULE)
        raw = GaussianArrays.from_any(mapper.gmap).take(mask)
        t0 = time.perf_counter()
        subs[task] = GaussianArrays.from_any(finetune_subset(raw, kfs, args.finetune_iters, mapper.cfg, seed=seed))
        out[task]["finetune_s"] = time.perf_counter() - t0
        out[task]["n_shared"] = len(raw)
        out[task]["alone_raw"] = score(raw, task)
        out[task]["alone_ft"] = score(subs[task], task)
        # the keyframes as uploaded: colour rounded to 8 bits
        refine_kfs += [dataclasses.replace(k, rgb=(k.rgb * 255 + 0.5).floor() / 255.0) for k in kfs[::2]]
    fused = {}
    for r in (0, 1):
        fused[r], _ = voxel_vote(dict(zip(("agent_a", "agent_b"), (subs[t] for t in TASKS))), 0.10, contest_radius=r)
    refined = {name: refine_map(fused[1], refine_kfs, args.refine_iters, seed=seed, final_lr=fl, roi_loss=roi)
               for name, fl, roi in (("refine_foot", 1.0, False), ("refine_roi", 1.0, True),
                                     ("refine_roi_cos", 0.05, True))}
    for task in TASKS:
        out[task]["vote_r0"] = score(fused[0], task)
        out[task]["vote_r1"] = score(fused[1], task)
        for name, g in refined.items():
            out[task][name] = score(g, task)
    return {"seed": seed, "tasks": out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.share_finetune", description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=str(SHARED / "datasets" / "Replica_room0" / "room0"))
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--max-frames", type=int, default=20)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--finetune-iters", type=int, default=200)
    ap.add_argument("--refine-iters", type=int, default=100)
    ap.add_argument("--out", type=Path, default=RESULTS / "share_finetune.json")
    args = ap.parse_args(argv)
    if not Path(args.dataset).is_dir():
        ap.error(f"{args.dataset} not found (set GAUSSLITE_SHARED)")

    t0 = time.perf_counter()
    runs = [run_seed(args, s) for s in tqdm(range(args.seeds), desc="bench.share_finetune", unit="seed")]
    summary = {}
    for task in TASKS:
        blk = {}
        for k in FIELDS + ("n_shared", "finetune_s"):
            blk[k], blk[k + "_std"] = mean_std([r["tasks"][task][k] for r in runs])
        for k in ("alone_ft", "vote_r0", "vote_r1", "refine_roi"):
            blk[f"{k}_minus_own"], blk[f"{k}_minus_own_std"] = mean_std(
                [r["tasks"][task][k] - r["tasks"][task]["own"] for r in runs])
        blk["vote_r1_ge_own_every_seed"] = all(r["tasks"][task]["vote_r1"] >= r["tasks"][task]["own"] for r in runs)
        summary[task] = blk
    result = {"dataset": args.dataset, "downscale": args.downscale, "max_frames": args.max_frames,
              "finetune_iters": args.finetune_iters, "refine_iters": args.refine_iters,
              "seeds": list(range(args.seeds)), "tasks": summary, "runs": runs, "wall_s": time.perf_counter() - t0}
    lines = ["| task | own map | subset alone | fine-tuned alone | vote r=0 | vote r=1 | refine, footprint | refine, ROI | refine, ROI, cosine lr | vote r=1 − own |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for task, b in summary.items():
        f = lambda k: fmt(b[k], b[k + "_std"], 2)  # noqa: E731
        lines.append(f"| {task} | " + " | ".join(f(k) for k in FIELDS) + f" | {f('vote_r1_minus_own')} |")
    write_results(args.out, "share_finetune", argv, f": ROI PSNR [dB] over {args.max_frames} room0 frames, mean ± std "
                  f"over {args.seeds} seeds, {result['wall_s'] / 60:.1f} min", "\n".join(lines), result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
