"""Delta pushes of fine-tuned subsets: bytes on the link against the fused map, per refresh share
(goal ``total_upload_bytes ≤ 1.5 × final_subset_bytes`` on room0 with ``agent.push.every: 5``).

    python -m bench.share_refresh [--scene room0|synthetic] [--seeds 3] [--refresh 1,0.25,0.07]
                                  [--finetune-iters 200]

Two agents map with the deployed agent settings and ``roi_render: context`` (as ``bench.share_finetune``),
one per task, with the ground-truth ROI as relevance: on ``room0`` both map the same 20 frames (300×170)
for room0-pick-plant and room0-find-ottoman; on ``synthetic`` each its own trajectory of the sim's default
scene (16 frames, 160×120) for synth-pick-object (agent_a) and synth-find-chair (agent_b). Every
``--push-every`` frames and after the last one each agent selects its task subset (coverage 0.99) and,
per arm, prepares the push and plans it with its own :class:`gausslite.wire.delta.PushPlanner`, which
acknowledges it (a loss-free link):

- ``free``: today's rule before this bench: the subset fine-tuned from the agent's values at every push
  (:func:`gausslite.sharing.finetune_subset`), so every row moves and every delta re-sends about all of it;
- ``r=<x>``: :func:`gausslite.sharing.update_shared_subset` against the arm's acknowledged copy, with
  ``refresh`` x (the rows the server holds start from its values; only the new rows and x of the held
  ones may change).

Per arm and task: ``total_upload_bytes`` (all pushes), ``final_subset_bytes`` (the final copy encoded whole)
and their ratio; the ROI PSNR over the agent's frames of the server's copy rendered alone (``alone``), and of
the voxel vote (δ = 0.10 m, neighbourhood radius 1, as the sim) of the two agents' server copies
(``vote``), and the same vote with every row's κ replaced by the agent's current κ of that Gaussian
(``vote_fresh_kappa``: what the vote would pick if κ were never stale on the server; since wire format 3's κ
shift keeps the server's κ current, it equals ``vote`` up to the planner's 25 % κ tolerance, where stale κ cost
the vote 0.2–0.9 dB before); ``own``: the agent's
whole map. Each task is scored over the frames its agent mapped. Mean ± std over seeds.

Writes ``bench/results/share_refresh.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
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
from gausslite.fusion.vote import voxel_vote
from gausslite.mapping.mapper import Mapper
from gausslite.pipeline import gt_roi_fn
from gausslite.sharing import finetune_subset, select_task_subset, update_shared_subset
from gausslite.stats import fmt, mean_std
from gausslite.synthetic import make_scene
from gausslite.wire.codec import GaussianArrays
from gausslite.wire.delta import PushPlanner

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
RESULTS = REPO / "bench" / "results"
SCENES = {"room0": ("room0-pick-plant", "room0-find-ottoman"), "synthetic": ("synth-pick-object", "synth-find-chair")}
FIELDS = ("upload_ratio", "total_upload_bytes", "final_subset_bytes", "alone", "vote", "vote_fresh_kappa")


def scene_datasets(args) -> list:
    """The two agents' datasets of ``args.scene`` (room0: the same frames twice)."""
    if args.scene == "room0":
        ds = load_dataset(args.dataset, downscale=args.downscale, max_frames=args.max_frames)
        return [ds, ds]

    out = REPO / "runs" / "bench_share_refresh" / "scene"
    if not (out / "agent_b").is_dir():
        make_scene(out, seed=0, width=320, height=240, frames=16, progress=False)
    return [load_dataset(out / n, downscale=2.0) for n in ("agent_a", "agent_b")]


def arm_names(refresh: list[float]) -> list[str]:
    """Arm labels: ``free`` for the pre-existing rule, ``r=<x>`` per refresh share."""
    return ["free"] + [f"r={r:g}" for r in refresh]


def run_seed(args, seed: int, refresh: list[float]) -> dict:
    """One seed: map both agents with periodic pushes per arm; bytes and ROI PSNR per arm and task."""
    torch.set_num_threads(1)
    tasks = SCENES[args.scene]
    datasets = scene_datasets(args)
    arms = arm_names(refresh)

    def score(g, task, ds, frames):
        return evaluate_fused(GaussianArrays.from_any(g).to_gaussian_map(), frames, ds.annotations, task)

    out = {t: {a: {} for a in arms} for t in tasks}
    server = {a: {} for a in arms}
    kappa_now = {}
    for task, ds in zip(tasks, datasets):
        frames = [ds[i] for i in range(len(ds))]
        roi_fn = gt_roi_fn(ds, task)
        mapper = Mapper(agent_mapper(seed, ["mapper.roi_render=context"]))
        planners = {a: PushPlanner(task) for a in arms}
        sent = {a: [] for a in arms}
        version = 0
        for i, fr in enumerate(frames):
            mapper.map_frame(fr, roi_fn(fr))
            if (i + 1) % args.push_every and i != len(frames) - 1:
                continue
            version += 1
            kfs = [mapper.keyframes.load(k, mapper.device) for k in range(len(mapper.keyframes))]
            mask, _ = select_task_subset(mapper.gmap, kfs, SHARE_RULE)
            raw = GaussianArrays.from_any(mapper.gmap).take(mask)
            ids = mapper.model.ids.numpy()[mask]
            for a, r in zip(arms, [None] + refresh):
                pl = planners[a]
                if r is None:
                    sub = GaussianArrays.from_any(finetune_subset(raw, kfs, args.finetune_iters, mapper.cfg, seed=seed))
                else:
                    sub, _ = update_shared_subset(raw, ids, pl.base, pl.base_ids, kfs, args.finetune_iters, r,
                                                  mapper.cfg, seed=seed)
                p = pl.plan(ids, sub, version)
                pl.acknowledge(p)
                sent[a].append({"frames": i + 1, "bytes": p.nbytes, "records": p.n_records, "delta": p.is_delta,
                                "full_bytes": p.full_bytes})
        own = score(mapper.gmap, task, ds, frames)
        kappa_now[task] = dict(zip(mapper.model.ids.numpy().tolist(), mapper.gmap.kappa.cpu().numpy().tolist()))
        for a in arms:
            o = out[task][a]
            o["total_upload_bytes"] = sum(s["bytes"] for s in sent[a])
            o["final_subset_bytes"] = sent[a][-1]["full_bytes"]
            o["upload_ratio"] = o["total_upload_bytes"] / o["final_subset_bytes"]
            o["pushes"] = sent[a]
            o["alone"] = score(planners[a].base, task, ds, frames)
            o["own"] = own
            server[a][task] = (planners[a].base, planners[a].base_ids)
    for a in arms:
        subs = {n: server[a][t][0] for n, t in zip(("agent_a", "agent_b"), tasks)}
        fresh = {}
        for n, t in zip(("agent_a", "agent_b"), tasks):
            g, gids = server[a][t]
            k = np.array([kappa_now[t].get(int(i), int(kk)) for i, kk in zip(gids, g.kappa)], np.int64)
            fresh[n] = GaussianArrays(**{**{f: getattr(g, f) for f in GaussianArrays.FIELDS}, "kappa": k})
        fused, _ = voxel_vote(subs, 0.10, contest_radius=1)
        fused_fresh, _ = voxel_vote(fresh, 0.10, contest_radius=1)
        for task, ds in zip(tasks, datasets):
            frames = [ds[i] for i in range(len(ds))]
            out[task][a]["vote"] = score(fused, task, ds, frames)
            out[task][a]["vote_fresh_kappa"] = score(fused_fresh, task, ds, frames)
    return {"seed": seed, "tasks": out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.share_refresh", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", choices=sorted(SCENES), default="room0")
    ap.add_argument("--dataset", default=str(SHARED / "datasets" / "Replica_room0"), help="room0 scene: the dataset")
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--max-frames", type=int, default=20)
    ap.add_argument("--push-every", type=int, default=5)
    ap.add_argument("--refresh", default="1,0.25,0.07", help="comma list of refresh shares in [0, 1]")
    ap.add_argument("--finetune-iters", type=int, default=200)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="default bench/results/share_refresh_<scene>.json")
    args = ap.parse_args(argv)

    refresh = [float(x) for x in args.refresh.split(",") if x]
    arms = arm_names(refresh)
    tasks = SCENES[args.scene]
    args.out = args.out or RESULTS / f"share_refresh_{args.scene}.json"
    t0 = time.perf_counter()
    runs = [run_seed(args, s, refresh) for s in tqdm(range(args.seeds), desc="bench.share_refresh", unit="seed")]
    summary = {t: {a: {} for a in arms} for t in tasks}
    for t in tasks:
        for a in arms:
            for k in FIELDS + ("own",):
                m, s = mean_std([r["tasks"][t][a][k] for r in runs])
                summary[t][a][k], summary[t][a][k + "_std"] = m, s
            m, s = mean_std([r["tasks"][t][a]["vote"] - r["tasks"][t][a]["own"] for r in runs])
            summary[t][a]["vote_minus_own"], summary[t][a]["vote_minus_own_std"] = m, s
    result = {"scene": args.scene, "dataset": args.dataset if args.scene == "room0" else "synthetic default",
              "downscale": args.downscale, "max_frames": args.max_frames,
              "push_every": args.push_every, "finetune_iters": args.finetune_iters, "refresh": refresh,
              "seeds": list(range(args.seeds)), "summary": summary, "runs": runs,
              "wall_s": time.perf_counter() - t0}
    lines = ["| task | arm | total / final subset | total upload [B] | server copy alone [dB] | vote [dB] | "
             "vote, fresh κ [dB] | own [dB] | vote − own [dB] |", "|---|---|---|---|---|---|---|---|---|"]
    for t in tasks:
        for a in arms:
            b = summary[t][a]
            f = lambda k, d=2: fmt(b[k], b[k + "_std"], d)  # noqa: E731
            lines.append(f"| {t} | {a} | {f('upload_ratio')} | {f('total_upload_bytes', 0)} | {f('alone')} | "
                         f"{f('vote')} | {f('vote_fresh_kappa')} | {f('own')} | {f('vote_minus_own')} |")
    write_results(args.out, "share_refresh", argv, f": {len(runs)} seeds, {result['wall_s'] / 60:.1f} min",
                  "\n".join(lines), result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
