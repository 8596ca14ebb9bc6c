"""Keyframe placement against the frozen map (``pose.track_iters``, :mod:`gausslite.mapping.tracking`): does tracking
each keyframe against the Gaussian map before it seeds bring its pose closer to the ground truth, and the task region
of withheld frames closer to the images?

TUM fr1/rpy (150 frames, 160×120 at ``--downscale 4``, undistorted), mapped offline as ``gausslite map`` maps it (the
hand-held profile: pose refinement, exposure, motion blur, rolling shutter, a final pass of 20 iterations per keyframe),
at the RGB-D odometry's poses (``--pose-sources odometry``: the depth is not re-timed, that uses the ground truth) and
at the given motion-capture poses (``given``). Every 10th frame (from the 5th) is withheld from the mapper
(:func:`gausslite.datasets.subset.withheld_indices`); of the others every ``--stride``-th is mapped. Per run:

- ``ate_input_cm``: the mapped frames' input poses against the reference (the dataset's own poses), ATE RMSE after
  rigid alignment (:func:`gausslite.datasets.trajectory.ate_rmse`); 0 at the given poses;
- ``ate_placed_cm``: the poses the keyframes were seeded at (after placement, before any later refinement);
- ``ate_final_cm``: the keyframe poses the finished map holds (:meth:`Mapper.keyframe_poses`: placement and
  refinement);
- ``roi_psnr`` / ``psnr``: the withheld frames rendered at the pose the map predicts for them
  (:meth:`Mapper.render_frame`: the input pose with the correction interpolated between the keyframes on either side),
  scored on the task's ground-truth ROI from the reference pose (``--task``, default the mouse) and on the whole image;
- the tracker's Adam steps per keyframe, the share of placements kept, and the mean correction.

Variants (``--variants``): ``off`` (no placement), ``track{N}`` (N steps at the mapping resolution),
``track{N}_w80`` (N steps at 80 pixels wide), or ``NAME=key=value;key=value`` (``pose`` fields). Uniform maps every
region alike (the task only scores it); GaussLite maps for the task, its relevance the ground-truth ROI.

Accuracy only (iteration counts, ATE, PSNR at fixed iteration counts): no wall-clock figure is measured. Runs are
kept in ``<out>.partial.json`` as they finish; ``--resume`` skips those done.

Usage::

    python -m bench.map_tracking [--pose-sources odometry,given] [--modes uniform,gausslite]
                                 [--variants off,track20,track40_w80] [--seeds 0,1,2] [--stride 2]
                                 [--task tum-find-mouse] [--resume] [--out bench/results/map_tracking.json]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import List, Optional

import numpy as np
from tqdm import tqdm

from bench._results import DATASETS, write_results
from gausslite.datasets import load_dataset
from gausslite.datasets.subset import withheld_indices
from gausslite.datasets.trajectory import ate_rmse
from gausslite.evaluation import score_view
from gausslite.mapping.config import MapperConfig, apply_overrides, deep_merge
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.profiles import HANDHELD

RESULTS = Path(__file__).resolve().parent / "results"
TUM = DATASETS / "TUM_rgbd_dataset_freiburg1_rpy"
#: named variants: ``pose`` fields over the hand-held profile
VARIANTS = {"off": {}, "track20": {"track_iters": 20}, "track40": {"track_iters": 40},
            "track20_w80": {"track_iters": 20, "track_width": 80},
            "track40_w80": {"track_iters": 40, "track_width": 80}}


def parse_variant(text: str) -> tuple[str, dict]:
    """``name`` of :data:`VARIANTS`, or ``NAME=key=value;key=value`` (``pose`` fields, YAML-typed values).

    Raises:
        ValueError: an unknown name or a malformed field.
    """
    import yaml

    if "=" not in text:
        if text not in VARIANTS:
            raise ValueError(f"unknown variant {text!r} (known: {', '.join(VARIANTS)}, or NAME=key=value;...)")
        return text, dict(VARIANTS[text])
    name, _, rest = text.partition("=")
    fields = {}
    for item in filter(None, rest.split(";")):
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"variant {name}: {item!r} is not key=value")
        fields[key.strip()] = yaml.safe_load(value)
    return name, fields


def load(source: str, downscale: float, max_frames: Optional[int] = None):
    """TUM fr1/rpy (its first ``max_frames``) with ``source`` poses (``given`` or ``odometry``) and its reference
    poses (N, 4, 4)."""
    ds = load_dataset(TUM, downscale=downscale, max_frames=max_frames, undistort=True, interpolate_poses=True,
                      align_depth_time=source == "given", pose_source=source, progress=False)
    ref = np.asarray(ds.reference_poses if source == "odometry" else ds.poses, np.float64)
    return ds, ref


def mapper_config(mode: str, seed: int, pose: dict, overrides: Optional[dict] = None) -> MapperConfig:
    """The hand-held profile's mapper in ``mode`` with ``seed``, the variant's ``pose`` fields and ``overrides``."""
    return MapperConfig.model_validate(deep_merge(deep_merge(HANDHELD.mapper, overrides or {}),
                                                  {"mode": mode, "seed": seed, "pose": pose}))


def run_one(ds, ref: np.ndarray, mode: str, seed: int, pose: dict, stride: int, task: str,
            overrides: Optional[dict] = None) -> dict:
    """Map the non-withheld frames (every ``stride``-th), score the withheld ones; the run's figures (module doc)."""
    held = set(withheld_indices(len(ds)))
    mapped = [i for i in range(len(ds)) if i not in held][::stride]
    ok = np.asarray(getattr(ds, "pose_ok", np.ones(len(ds), bool)), bool)
    mapped = [i for i in mapped if ok[i]]
    ann = ds.annotations
    roi_of: dict = {}
    mapper = Mapper(mapper_config(mode, seed, pose, overrides))
    mapper.tracker = recorder = PlacementRecorder(mapper.tracker)
    idx_of = {}
    for i in tqdm(mapped, desc=f"{mode} seed {seed}", unit="frame", leave=False):
        fr = ds[i]
        idx_of[int(fr.frame_id)] = i
        roi_of[i] = ann.roi_mask(task, fr.depth, ref[i], fr.intrinsics)
        mapper.map_frame(fr, roi_of[i] if mode == "gausslite" else None)
    mapper.finalize()
    # the pose each keyframe seeded at: the tracker's, else its input pose (pose.init identity: no correction yet)
    placed = {f: recorder.results[f].c2w if f in recorder.results else mapper.input_poses[f] for f in idx_of}
    final = mapper.keyframe_poses()
    fids = sorted(idx_of)
    refs = np.stack([ref[idx_of[f]] for f in fids])
    scores = []
    for i in sorted(held):
        fr = ds[i]
        if ok[i]:
            scores.append(score_view(mapper.render_frame(fr), fr, ann.roi_mask(task, fr.depth, ref[i], fr.intrinsics)))
    tracked = [s for s in mapper.stats if s.track_accepted is not None]
    roi = [s.roi_psnr for s in scores if not math.isnan(s.roi_psnr)]
    return {
        "mode": mode, "seed": seed, "pose": pose, "n_mapped": len(fids), "n_scored": len(scores),
        "roi_frames": len(roi),
        "ate_input_cm": 100 * ate_rmse(np.stack([mapper.input_poses[f] for f in fids]), refs),
        "ate_placed_cm": 100 * ate_rmse(np.stack([placed[f] for f in fids]), refs),
        "ate_final_cm": 100 * ate_rmse(np.stack([final[f] for f in fids]), refs),
        "roi_psnr": float(np.mean(roi)) if roi else None, "psnr": float(np.mean([s.psnr for s in scores])),
        "track_iters_mean": float(np.mean([s.track_iters for s in tracked])) if tracked else 0.0,
        "track_kept": float(np.mean([bool(s.track_accepted) for s in tracked])) if tracked else None,
        "track_rot_deg_mean": float(np.mean([s.track_rot_deg for s in tracked])) if tracked else 0.0,
        "track_trans_cm_mean": 100 * float(np.mean([s.track_trans_m for s in tracked])) if tracked else 0.0,
        "n_gaussians": len(mapper.model), "map_iters_mean": float(np.mean([s.iters for s in mapper.stats])),
    }


class PlacementRecorder:
    """A :class:`~gausslite.mapping.tracking.FrameTracker` that keeps every result (frame id → ``TrackResult``): the
    poses the keyframes were seeded at, before later refinement moves them."""

    def __init__(self, tracker) -> None:
        self.tracker, self.results = tracker, {}

    def track(self, frame, relevance=None, deadline=None):
        """:meth:`FrameTracker.track`, recorded."""
        res = self.tracker.track(frame, relevance, deadline)
        self.results[int(frame.frame_id)] = res
        return res


def summarise(runs: List[dict]) -> List[dict]:
    """Per (pose source, mode, variant): mean and standard deviation over seeds of every figure, and the paired
    difference to ``off`` of the same source, mode and seed."""
    keys = ["ate_placed_cm", "ate_final_cm", "roi_psnr", "psnr", "track_iters_mean", "track_trans_cm_mean",
            "track_rot_deg_mean", "ate_input_cm", "map_iters_mean"]
    groups: dict = {}
    for r in runs:
        groups.setdefault((r["source"], r["mode"], r["variant"]), []).append(r)
    out = []
    for (source, mode, variant), rs in sorted(groups.items()):
        row = {"source": source, "mode": mode, "variant": variant, "seeds": sorted(r["seed"] for r in rs)}
        for k in keys:
            v = [r[k] for r in rs if r.get(k) is not None]
            row[k] = float(np.mean(v)) if v else None
            row[k + "_std"] = float(np.std(v)) if v else None
        base = {r["seed"]: r for r in groups.get((source, mode, "off"), [])}
        for k in ("roi_psnr", "psnr", "ate_final_cm"):
            d = [r[k] - base[r["seed"]][k] for r in rs if r["seed"] in base and r[k] is not None
                 and base[r["seed"]][k] is not None]
            row[k + "_minus_off"] = float(np.mean(d)) if d and variant != "off" else None
            row[k + "_minus_off_std"] = float(np.std(d)) if d and variant != "off" else None
        out.append(row)
    return out


def table(rows: List[dict]) -> str:
    """The Markdown table of :func:`summarise`'s rows."""
    def f(r, k, p=2):
        v, s = r.get(k), r.get(k + "_std")
        return "—" if v is None else (f"{v:.{p}f} ± {s:.{p}f}" if s is not None else f"{v:.{p}f}")

    lines = ["| poses | mode | variant | seeds | ATE input (cm) | ATE placed (cm) | ATE final (cm) | ROI PSNR (dB) | "
             "ROI − off (dB) | PSNR (dB) | PSNR − off (dB) | tracker steps / keyframe | correction (cm) | "
             "mapping iterations / keyframe |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['source']} | {r['mode']} | {r['variant']} | {len(r['seeds'])} | {f(r, 'ate_input_cm')} | "
                     f"{f(r, 'ate_placed_cm')} | {f(r, 'ate_final_cm')} | {f(r, 'roi_psnr')} | "
                     f"{f(r, 'roi_psnr_minus_off')} | {f(r, 'psnr')} | {f(r, 'psnr_minus_off')} | "
                     f"{f(r, 'track_iters_mean', 1)} | {f(r, 'track_trans_cm_mean')} | {f(r, 'map_iters_mean', 1)} |")
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    """Run the grid (resumable), write the JSON and the Markdown table, print the table."""
    ap = argparse.ArgumentParser(prog="python -m bench.map_tracking", description=__doc__.split("\n\n")[0])
    ap.add_argument("--pose-sources", default="odometry,given")
    ap.add_argument("--modes", default="uniform,gausslite")
    ap.add_argument("--variants", default="off,track20,track40_w80",
                    help=f"comma-separated: {', '.join(VARIANTS)}, or NAME=key=value;key=value (pose fields)")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--stride", type=int, default=2, help="map every k-th frame of those not withheld")
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--task", default="tum-find-mouse")
    ap.add_argument("--max-frames", type=int, default=None, help="the sequence's first N frames only")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="a mapper setting over the hand-held profile for every run, e.g. final_iters_per_keyframe=0")
    ap.add_argument("--resume", action="store_true", help="keep the runs of <out>.partial.json")
    ap.add_argument("--out", type=Path, default=RESULTS / "map_tracking.json")
    args = ap.parse_args(argv)
    try:
        variants = [parse_variant(v) for v in args.variants.split(",") if v]
        overrides = apply_overrides({}, args.overrides)
    except ValueError as e:
        ap.error(str(e))
    partial = args.out.with_suffix(".partial.json")
    runs = json.loads(partial.read_text())["runs"] if args.resume and partial.is_file() else []
    done = {(r["source"], r["mode"], r["variant"], r["seed"]) for r in runs}
    seeds = [int(s) for s in args.seeds.split(",") if s]
    for source in [s for s in args.pose_sources.split(",") if s]:
        ds, ref = load(source, args.downscale, args.max_frames)
        for mode in [m for m in args.modes.split(",") if m]:
            for name, pose in variants:
                for seed in seeds:
                    if (source, mode, name, seed) in done:
                        continue
                    r = run_one(ds, ref, mode, seed, pose, args.stride, args.task, overrides)
                    runs.append({"source": source, "variant": name, **r})
                    partial.parent.mkdir(parents=True, exist_ok=True)
                    partial.write_text(json.dumps({"runs": runs}, indent=1))
                    print(f"{source} {mode} {name} seed {seed}: ATE placed {r['ate_placed_cm']:.2f} final "
                          f"{r['ate_final_cm']:.2f} cm, ROI {r['roi_psnr']:.2f} dB, {r['track_iters_mean']:.1f} "
                          f"steps", flush=True)
    rows = summarise(runs)
    result = {"task": args.task, "stride": args.stride, "downscale": args.downscale, "max_frames": args.max_frames,
              "profile": HANDHELD.mapper, "overrides": overrides,
              "variants": dict(variants), "summary": rows, "runs": runs}
    write_results(args.out, "map_tracking", argv, f": TUM fr1/rpy, {len(seeds)} seeds", table(rows), result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
