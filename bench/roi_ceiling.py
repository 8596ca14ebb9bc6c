"""How much can ROI effort give? The ROI ceiling of a long mission.

    python -m bench.roi_ceiling [--scene tum_fr1_rpy|synthetic_long] [--mode uniform] [--seed 0]
                                [--tasks 2|all|ID,ID] [--iters 750,1500,3000] [--fresh-moments]
                                [--tum-downscale 2] [--synthetic-frames 300] [--set KEY=VALUE ...] [--out PATH]

Maps the scene once (``bench.long_mission``'s job: same profile, defaults and scoring), then, from copies of
the final map:

- **ROI-only fine-tune** (per task): every Gaussian updated, loss on ROI ∩ rendered footprint
  (``footprint_only`` + ``footprint_roi`` iterations, the path of ``gausslite.fusion.refine.refine_map``), each
  view cropped to its ROI box (pad 8 px), views drawn uniformly over the keyframes that see the ROI. ROI PSNR is
  scored on the mapped views themselves after each count in ``--iters``. All of the effort goes to the pixels
  that are scored, so this is about as high as any allocation of optimisation takes the ROI with these views,
  poses and Gaussians.
- **Full-image pass** of the first count in ``--iters``: full-image iterations drawn uniformly over all keyframes,
  no ROI (what ``final_iters_per_keyframe`` does), scored the same way: how much of the headroom is forgetting
  rather than focus.

``--fresh-moments`` drops the map's Adam moments before each fine-tune (a ROI-only loss has larger gradients than
the full-image loss, so carried moments make the first steps overshoot). One seed per invocation; single runs
move by about ±0.2 dB. Writes ``bench/results/roi_ceiling_<scene>.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from bench import long_mission as lm
from bench._results import write_results
from gausslite.datasets import load_dataset
from gausslite.evaluation import evaluate
from gausslite.mapping.views import crop_keyframe, roi_box
from gausslite.pipeline import gt_roi_fn


def roi_views(mapper, ds, stride: int, roi_fn, pad: int = 8) -> list:
    """The mapper's stored keyframes that see the ROI of ``roi_fn``, each cropped to its ROI box grown by ``pad``."""
    # one load per mapped frame: its ROI by frame id
    rois = {fr.frame_id: np.asarray(roi_fn(fr), bool) for fr in (ds[i] for i in range(0, len(ds), stride))}
    views = []
    for j in range(len(mapper.keyframes)):
        kf = mapper.keyframes.load(j, mapper.device)
        roi = rois[kf.frame_id]
        kf.roi_box = roi_box(roi)
        if kf.roi_box is None:
            continue
        kf.roi = torch.from_numpy(roi).to(mapper.device)
        views.append(crop_keyframe(kf, pad))
    return views


def score(mapper, ds, stride: int, rois: dict) -> dict:
    """PSNR over the mapped views and each ROI's PSNR (``rois``: task id → ROI function)."""
    ev = evaluate(mapper.render_frame, (ds[i] for i in range(0, len(ds), stride)), None, extra_rois=rois)
    return {"psnr": float(np.mean([s.psnr for s in ev.scores])),
            "roi_psnr": {t: ev.per_roi[t].as_dict()["roi_psnr"] for t in rois}}


def _fresh(base, fresh_moments: bool):
    """A copy of the Gaussian model ``base`` (and its Adam state unless ``fresh_moments``) to fine-tune."""
    model = copy.deepcopy(base)
    if fresh_moments:
        model.set_map(model.to_map(), None)  # drops all optimiser state
    return model


def run(job: dict, iters: list[int], fresh_moments: bool = False, seed: int = 0) -> dict:
    """Map ``job`` (see ``bench.long_mission.map_job``), then the full-image pass and the ROI-only fine-tunes.

    Returns:
        ``{"before": {psnr, roi_psnr}, "full_pass": {iters, psnr, roi_psnr, seconds},
        "roi_only": {task: [{iters, roi_psnr, psnr, seconds}, ...]}, "n_roi_views": {task: n}, "map_wall_s"}``.
    """
    ds, mapper, m, wall = lm.map_job(job)
    stride = lm.SCENES[job["scene"]]["stride"]
    rois = {t: gt_roi_fn(ds, t) for t in job["eval_tasks"]}
    base = mapper.model
    out: dict = {"map_wall_s": wall, "before": score(mapper, ds, stride, rois), "roi_only": {}, "n_roi_views": {}}
    rng = np.random.default_rng(seed)
    # full-image pass: what revisiting every keyframe alike gives, with no ROI at all
    mapper.model = _fresh(base, fresh_moments)
    t0 = time.perf_counter()
    n = len(mapper.keyframes)
    for _ in range(iters[0]):
        mapper.step(mapper.keyframes.load(int(rng.integers(n)), mapper.device), active_phase=False)
    out["full_pass"] = {"iters": iters[0], "seconds": time.perf_counter() - t0, **score(mapper, ds, stride, rois)}
    for t, fn in rois.items():
        mapper.model = _fresh(base, fresh_moments)
        views = roi_views(mapper, ds, stride, fn)
        out["n_roi_views"][t] = len(views)
        curve, done, t0 = [], 0, time.perf_counter()
        for stop in iters:
            while done < stop and views:
                mapper.step(views[int(rng.integers(len(views)))], active_phase=False, footprint_only=True,
                            footprint_roi=True)
                done += 1
            sc = score(mapper, ds, stride, {t: fn})
            curve.append({"iters": stop, "roi_psnr": sc["roi_psnr"][t], "psnr": sc["psnr"],
                          "seconds": time.perf_counter() - t0})
            print(f"{t}: ROI-only +{stop}: ROI PSNR {sc['roi_psnr'][t]:.2f} dB (before "
                  f"{out['before']['roi_psnr'][t]:.2f})", flush=True)
        out["roi_only"][t] = curve
    mapper.model = base
    return out


def table(res: dict) -> str:
    """Markdown: per task, ROI PSNR before, after the full-image pass and along the ROI-only fine-tune."""
    iters = [c["iters"] for c in next(iter(res["roi_only"].values()), [])]
    head = ("| task | ROI PSNR | + full-image pass ({}) | ".format(res["full_pass"]["iters"])
            + " | ".join(f"+ {i} ROI-only" for i in iters) + " | ceiling − map | ceiling − full pass |")
    lines = [head, "|" + "---|" * (5 + len(iters))]
    for t, curve in res["roi_only"].items():
        b, fp = res["before"]["roi_psnr"][t], res["full_pass"]["roi_psnr"][t]
        best = max(c["roi_psnr"] for c in curve)
        lines.append(f"| {t} | {b:.2f} | {fp:.2f} | " + " | ".join(f"{c['roi_psnr']:.2f}" for c in curve)
                     + f" | {best - b:+.2f} | {best - fp:+.2f} |")
    lines.append(f"\nPSNR over the mapped views: {res['before']['psnr']:.2f} dB, after the full-image pass "
                 f"{res['full_pass']['psnr']:.2f} dB.")
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="tum_fr1_rpy", choices=list(lm.SCENES))
    ap.add_argument("--mode", default="uniform", choices=["uniform", "gausslite"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--tasks", default="2", help="a number (first N), 'all', or a comma list of task ids")
    ap.add_argument("--iters", default="750,1500,3000", help="comma list of fine-tune iteration counts (increasing)")
    ap.add_argument("--fresh-moments", action="store_true", help="drop the map's Adam moments before fine-tuning")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--tum-downscale", type=float, default=None)
    ap.add_argument("--synthetic-frames", type=int, default=300)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--work", type=Path, default=lm.REPO / "runs" / "bench_long_mission")
    ap.add_argument("--out", type=Path, default=None, help="default bench/results/roi_ceiling_<scene>.json")
    args = ap.parse_args(argv)
    try:
        iters = [int(v) for v in args.iters.split(",") if v.strip()]
    except ValueError:
        ap.error(f"--iters must be a comma list of integers, got {args.iters!r}")
    if not iters or any(i < 1 for i in iters) or iters != sorted(iters):
        ap.error(f"--iters must be increasing counts >= 1, got {args.iters!r}")
    if args.tum_downscale is not None:
        lm.SCENES["tum_fr1_rpy"]["downscale"] = float(args.tum_downscale)
    lm.SCENES["synthetic_long"]["frames"] = int(args.synthetic_frames)

    path = lm.scene_path(args.scene, args.work)
    try:
        tasks = lm.select_tasks(args.tasks, [t.id for t in load_dataset(path, max_frames=1).annotations.tasks])
    except ValueError as e:
        ap.error(str(e))
    job = {"scene": args.scene, "path": str(path), "max_frames": args.max_frames, "overrides": args.overrides,
           "downscale": lm.SCENES[args.scene].get("downscale", 1.0), "mode": args.mode,
           "task": None if args.mode == "uniform" else tasks[0], "seed": args.seed,
           "eval_tasks": tasks if args.mode == "uniform" else tasks[:1]}
    t0 = time.time()
    res = run(job, iters, args.fresh_moments, args.seed)
    res.update({"settings": {k: v for k, v in job.items() if k != "path"} | {"iters": iters,
                "fresh_moments": args.fresh_moments, "scene_spec": lm.SCENES[args.scene]},
                "wall_s": time.time() - t0})
    out = args.out or lm.RESULTS / f"roi_ceiling_{args.scene}.json"
    write_results(out, "roi_ceiling", argv, f": {args.scene}, {args.mode}, seed {args.seed}, "
                  f"{res['wall_s'] / 60:.1f} min", table(res), res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
