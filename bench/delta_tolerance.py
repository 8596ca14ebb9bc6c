"""Delta pushes: bytes on the link against the fidelity of the server's copy, per change tolerance
(goal ``total_upload_bytes ≤ 1.5 × final_subset_bytes`` on room0 with ``agent.push.every: 5``).

    python -m bench.delta_tolerance [--tolerances 1,4,16] [--kappa-rel 0.25,1e9] [--seeds 3] [--task-id room0-pick-plant]

One agent maps Replica room0 (20 frames, 300×170) with the default mapper settings (full GaussLite, 30 iterations
and 1,500 seeds per frame) and the differences the
committed figures were measured with (:data:`MAPPER_OVERRIDES`: ``roi_render: active``, ``roi_update:
active``, every 2nd frame a keyframe), with the ground-truth ROI. Every ``--push-every`` frames and after the
last one it selects the task subset (``gausslite.sharing.select_task_subset``, coverage 0.99) and plans
a push with one :class:`gausslite.wire.delta.PushPlanner` per (tolerance, κ re-send threshold) pair, all
fed the same snapshots, so the pairs differ in nothing else. A planner's acknowledged subset is the server's
copy. ``--kappa-rel``: relative κ change that forces a re-send (the agent's default 0.25; κ of an active
Gaussian grows by one per ROI-phase iteration, so 0.25 re-sends every active Gaussian at every push; 1e9
never re-sends for κ alone, leaving the server's κ stale until the Gaussian moves).

Per pair: ``total_upload_bytes`` (all pushes), ``final_subset_bytes`` (the final subset encoded
whole), their ratio, rows re-sent, and the ROI PSNR of the server's copy rendered alone (as fusion sees an
agent's subset) over the ROI of every mapped frame, next to the exact final subset's (``roi_psnr_exact``;
the difference is what the tolerance costs). Mean ± std over seeds.

Writes ``bench/results/delta_tolerance.json`` and ``.md``.
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
from gausslite.config import load_config
from gausslite.datasets import load_dataset
from gausslite.evaluation import score_view
from gausslite.mapping.mapper import Mapper
from gausslite.pipeline import gt_roi_fn
from gausslite.render import rasterize
from gausslite.mission.config import ShareConfig
from gausslite.sharing import select_task_subset
from gausslite.stats import fmt, mean_std
from gausslite.wire.codec import GaussianArrays
from gausslite.wire.delta import PushPlanner

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
RESULTS = REPO / "bench" / "results"

#: the committed figures' mapper: the defaults with these overrides
MAPPER_OVERRIDES = ["mapper.roi_render=active", "mapper.roi_update=active", "mapper.store_keyframe_every=2",
                    "mapper.performance.render_threads=null"]
#: the committed figures' share rule (here and in ``bench.share_finetune``, ``bench.share_refresh``): the agent's
#: defaults (``agent.share``) but for the paper's candidates (a = 1 and κ in the task region, for a map fitted with
#: ``mapper.roi_update: active``) and no bound on the shared fraction
SHARE_RULE = ShareConfig(candidates="active", max_fraction=None)


def agent_mapper(seed: int, extra=()):
    """The deployed mapper settings with :data:`MAPPER_OVERRIDES`, then ``extra`` overrides (``mapper.<key>=<value>``)
    and ``seed`` (``bench.share_finetune`` and ``bench.share_refresh`` use it with ``roi_render: context``)."""
    return load_config(None, MAPPER_OVERRIDES + list(extra) + [f"mapper.seed={seed}"]).agent.mapper


def _roi_psnr(arrays, frames, rois) -> float:
    """Mean over frames of the ROI PSNR of ``arrays`` rendered alone (black background)."""
    g = arrays.to_gaussian_map()
    vals = []
    with torch.no_grad():
        for fr, roi in zip(frames, rois):
            if not roi.any():
                continue
            out = rasterize(g.means, g.quats, g.log_scales, g.opacity_logits, g.colors, K=fr.intrinsics.K,
                            width=fr.intrinsics.width, height=fr.intrinsics.height, c2w=fr.c2w)
            vals.append(score_view(out, fr, roi).roi_psnr)
    return float(np.mean(vals))


def run_seed(args, seed: int, tolerances: list[tuple[float, float]]) -> dict:
    """Map once, plan every push with every tolerance; per tolerance bytes, rows and server-copy PSNR."""
    torch.set_num_threads(1)
    ds = load_dataset(args.dataset, downscale=args.downscale, max_frames=args.max_frames)
    roi_fn = gt_roi_fn(ds, args.task_id)
    cfg = agent_mapper(seed)
    mapper = Mapper(cfg)
    planners = {t: PushPlanner("agent_a", tolerance=t[0], kappa_rel=t[1]) for t in tolerances}
    log = {t: [] for t in tolerances}
    frames, rois = [], []
    version = 0
    arrays = None
    for i in range(len(ds)):
        fr = ds[i]
        roi = roi_fn(fr)
        mapper.map_frame(fr, roi)
        frames.append(fr)
        rois.append(roi)
        last = i == len(ds) - 1
        if (i + 1) % args.push_every and not last:
            continue
        gmap = mapper.gmap
        mask, _ = select_task_subset(gmap, list(mapper.keyframes), SHARE_RULE)
        arrays = GaussianArrays.from_any(gmap).take(mask)
        ids = mapper.model.ids.numpy()[mask]
        version += 1
        for t, pl in planners.items():
            p = pl.plan(ids, arrays, version)
            pl.acknowledge(p)
            log[t].append({"version": version, "frames": i + 1, "n_shared": len(arrays), "bytes": p.nbytes,
                           "delta": p.is_delta, "records": p.n_records, "removed": p.n_removed,
                           "full_bytes": p.full_bytes})
    final_bytes = log[tolerances[0]][-1]["full_bytes"]
    exact = _roi_psnr(arrays, frames, rois)
    out = {"seed": seed, "n_gaussians": len(mapper.model), "n_shared": len(arrays), "final_subset_bytes": final_bytes,
           "roi_psnr_exact": exact, "by_tolerance": {}}
    for t in tolerances:
        total = sum(p["bytes"] for p in log[t])
        server = _roi_psnr(planners[t].base, frames, rois)
        out["by_tolerance"][_key(t)] = {"total_upload_bytes": total, "upload_ratio": total / final_bytes,
                                       "records": sum(p["records"] for p in log[t]), "roi_psnr_server": server,
                                       "roi_psnr_cost": exact - server, "pushes": log[t]}
    return out


def _key(t: tuple[float, float]) -> str:
    return f"{t[0]:g}/{t[1]:g}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.delta_tolerance", description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", default=str(SHARED / "datasets" / "Replica_room0"))
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--max-frames", type=int, default=20)
    ap.add_argument("--task-id", default="room0-pick-plant")
    ap.add_argument("--push-every", type=int, default=5)
    ap.add_argument("--tolerances", default="1,4,16", help="multiples of one code step")
    ap.add_argument("--kappa-rel", default="0.25,1e9", help="relative κ changes that force a re-send")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS / "delta_tolerance.json")
    args = ap.parse_args(argv)

    tolerances = [(float(x), float(k)) for k in args.kappa_rel.split(",") if k
                  for x in args.tolerances.split(",") if x]
    t0 = time.perf_counter()
    runs = [run_seed(args, s, tolerances) for s in tqdm(range(args.seeds), desc="bench.delta_tolerance", unit="seed")]
    summary = {}
    for t in tolerances:
        rows = [r["by_tolerance"][_key(t)] for r in runs]
        blk = {}
        for k in ("total_upload_bytes", "upload_ratio", "records", "roi_psnr_server", "roi_psnr_cost"):
            blk[k], blk[k + "_std"] = mean_std([x[k] for x in rows])
        summary[_key(t)] = blk
    fb = mean_std([r["final_subset_bytes"] for r in runs])
    ex = mean_std([r["roi_psnr_exact"] for r in runs])
    result = {"dataset": args.dataset, "downscale": args.downscale, "max_frames": args.max_frames,
              "task_id": args.task_id, "push_every": args.push_every, "mapper_overrides": MAPPER_OVERRIDES,
              "seeds": list(range(args.seeds)), "final_subset_bytes": fb[0], "final_subset_bytes_std": fb[1],
              "roi_psnr_exact": ex[0], "roi_psnr_exact_std": ex[1], "tolerances": summary, "runs": runs,
              "wall_s": time.perf_counter() - t0}
    lines = ["| tolerance (code steps) / κ re-send | total upload [B] | total / final subset | Gaussians sent | server copy ROI PSNR [dB] | cost vs exact [dB] |",
             "|---|---|---|---|---|---|"]
    for t in tolerances:
        b = summary[_key(t)]
        f = lambda k, d=2: fmt(b[k], b[k + "_std"], d)  # noqa: E731
        lines.append(f"| {_key(t)} | {f('total_upload_bytes', 0)} | {f('upload_ratio')} | {f('records', 0)} | "
                     f"{f('roi_psnr_server')} | {f('roi_psnr_cost')} |")
    write_results(args.out, "delta_tolerance", argv,
                  f": {args.task_id}, final subset {fmt(fb[0], fb[1], 0)} B, exact subset ROI PSNR {fmt(*ex)} dB, "
                  f"{len(runs)} seeds, {result['wall_s'] / 60:.1f} min", "\n".join(lines), result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
