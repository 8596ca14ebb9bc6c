"""Cross-scoring: what each scoring protocol measures, from the maps of a real-time run (docs/realtime.md#cross-scoring).

    python -m bench.cross_scoring [--scenes synthetic_circle] [--budget 0.5] [--runs 3] [--twin]
    python -m bench.cross_scoring --from bench/results/realtime.partial.json   # maps a --missions-only run saved
    python -m bench.cross_scoring --dataset PATH --tasks ID [--fps F] ...       # a sequence of your own

Both modes (uniform, GaussLite) map each scene with ``bench.realtime``'s protocol (live missions, or ``--twin``: the
deterministic twin), every ``--novel-every``-th frame withheld from both; or ``--from`` reads the maps that
``python -m bench.realtime --missions-only`` saved (its ``<out>.partial.json``; the maps are kept). Each pair of maps
of one run (same scene, budget and seed) is scored on the withheld frames, ROI PSNR on the task's ground-truth ROI,
at four kinds of view:

- ``predicted``: each map at the pose and exposure its own training predicts (the given pose with its learned
  correction, the exposure between its keyframes): the ``novel`` protocol, what a robot gets from the map at the pose
  its SLAM reports;
- ``own tracked``: each map at a pose and exposure tracked against itself: ``novel-tracked``, MonoGS's way;
- ``tracked on uniform``: both maps at the poses and exposures tracked against the uniform map;
- ``tracked on GaussLite``: both maps at the poses and exposures tracked against the GaussLite map.

The last two hold the view fixed and change the map: their gain is what the maps render; the gap between
``own tracked`` and them is what tracking against each map does to the view (a map kept coarse outside the task's
region localises less precisely). Each gain is GaussLite − uniform, the mean of the paired per-frame differences
over runs × frames with its 95 % interval (:func:`gausslite.stats.paired_gain`).

Prints the table and writes ``bench/results/cross_scoring.json`` / ``.md`` (``--out``).

Failed missions (:mod:`bench._missions`: a run whose mission did not end ``FINISHED`` or failed to map
frames, as ``bench.realtime`` records it) are never cross-scored: their run and its pair are left out, listed under
``failed_runs`` in the JSON and below the table (†), and the command exits 1 unless ``--allow-failed``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from bench._missions import FAILED_MARK, add_allow_failed, describe, exit_code, failure_rows, succeeded
from bench._results import write_results
from bench.realtime.missions import run_one, twin_one
from bench.realtime.protocol import TRACK_ITERS, novel_ids
from bench.realtime.scenes import REFERENCE_BUDGET_S, RESULTS, SCENES, Preloaded, dataset_scenes, load_scene, scene_path
from gausslite.datasets import task_roi
from gausslite.datasets.subset import ScaledFrames
from gausslite.evaluation import NOVEL_EVERY, score_live_map
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.mapper import Mapper
from gausslite.stats import fmt, fmt_gain, mean_std, paired_gain

#: the rows of the table: (name, view of the uniform map, view of the GaussLite map)
ROWS = (("predicted", "predicted", "predicted"), ("own tracked", "own", "own"),
        ("tracked on uniform", "own", "on_uniform"), ("tracked on GaussLite", "on_gausslite", "own"))
#: what each row answers, for the table
ROW_HELP = {
    "predicted": "the given pose with each map's learned correction (`novel`): the map as a robot uses it",
    "own tracked": "each map at a pose tracked against itself (`novel-tracked`): localisation and rendering together",
    "tracked on uniform": "both maps at the views tracked against the uniform map: the rendering alone",
    "tracked on GaussLite": "both maps at the views tracked against the GaussLite map: the rendering alone",
}


def load_map(run: dict):
    """(mapper, frames at its mapping resolution, annotations, task id, withheld frame ids) of a run whose map
    ``bench.realtime`` saved (``state_path`` and ``score_job``; the file is kept).

    Raises:
        FileNotFoundError: the saved map is gone (scored and removed by ``--score-only``).
    """
    job = run["score_job"]
    if not Path(run["state_path"]).is_file():
        raise FileNotFoundError(f"{run['state_path']}: the map was scored and removed; rerun --missions-only")
    saved = torch.load(run["state_path"], weights_only=False)
    mapper = Mapper(MapperConfig.model_validate(saved["cfg"]))
    mapper.load_state_dict(saved["state"])
    ds, _ = load_scene(job.get("spec") or SCENES[job["scene"]], Path(job["path"]))
    ds = Preloaded(ds)
    f = float(job.get("mapping_downscale") or 1.0)
    frames = ScaledFrames(ds, f) if f != 1 else ds
    return mapper, frames, ds.annotations, job["task"], novel_ids(job, frames)


def cross_score(uniform, gausslite, frames, roi_fn, novel: list, track_iters: int = TRACK_ITERS) -> dict:
    """The four views of :data:`ROWS` for one pair of maps on the withheld frames ``novel``.

    Args:
        uniform, gausslite: the two :class:`~gausslite.mapping.mapper.Mapper` (not modified). frames: the sequence
            (ground truth). roi_fn: frame → (H, W) bool ROI. novel: frame ids withheld from both mappers.
        track_iters: the tracker's Adam steps per frame.
    Returns:
        ``{row: {"uniform": {frame id: dB}, "gausslite": {frame id: dB}}}`` and ``"offset"``: per map the mean
        rotation (degrees) and translation (metres) of its tracked views away from the sensor's pose.
    """
    maps = {"uniform": uniform, "gausslite": gausslite}
    views = {m: {} for m in maps}
    per = {}
    for m, mapper in maps.items():
        per[(m, "predicted")] = score_live_map(mapper, frames, roi_fn, ("novel",), novel_ids=novel)["novel"]
        per[(m, "own")] = score_live_map(mapper, frames, roi_fn, ("novel-tracked",), track_iters=track_iters,
                                         novel_ids=novel, record=views[m])["novel-tracked"]
    per[("gausslite", "on_uniform")] = score_live_map(gausslite, frames, roi_fn, ("novel-tracked",), novel_ids=novel,
                                                      views=views["uniform"])["novel-tracked"]
    per[("uniform", "on_gausslite")] = score_live_map(uniform, frames, roi_fn, ("novel-tracked",), novel_ids=novel,
                                                      views=views["gausslite"])["novel-tracked"]
    out = {name: {"uniform": per[("uniform", u)]["roi_psnr_per_frame"],
                  "gausslite": per[("gausslite", g)]["roi_psnr_per_frame"]} for name, u, g in ROWS}
    out["offset"] = {m: {"rot_deg": float(np.mean([v.rot_deg for v in vs.values()])) if vs else None,
                         "trans_m": float(np.mean([v.trans_m for v in vs.values()])) if vs else None}
                     for m, vs in views.items()}
    return out


def summarise(pairs: list[dict]) -> dict:
    """``{scene: {budget: {row: {"uniform", "uniform_std", "gausslite", "gausslite_std" (means over runs of the
    per-run means, and their spread), "gain" (paired per frame over runs × frames), "runs", "frames"}}}}``."""
    out: dict = {}
    for scene in sorted({p["scene"] for p in pairs}):
        for b in sorted({p["budget"] for p in pairs if p["scene"] == scene}):
            ps = [p for p in pairs if p["scene"] == scene and p["budget"] == b]
            blk = {}
            for name, _, _ in ROWS:
                rows = [p["rows"][name] for p in ps]
                cell = {"runs": len(rows)}
                for m in ("uniform", "gausslite"):
                    means = [float(np.mean(list(r[m].values()))) if r[m] else None for r in rows]
                    cell[m], cell[f"{m}_std"] = mean_std(means)
                cell["gain"] = paired_gain([r["gausslite"] for r in rows], [r["uniform"] for r in rows])
                blk[name] = cell
            blk["offset"] = {m: {k: mean_std([p["rows"]["offset"][m][k] for p in ps])[0] for k in ("rot_deg", "trans_m")}
                             for m in ("uniform", "gausslite")}
            out.setdefault(scene, {})[f"{b:g}"] = blk
    return out


#: the fields that name a run in a failed mission's line
RUN_KEYS = ("scene", "mode", "budget", "run")


def table(summary: dict, failed: Optional[list] = None) -> str:
    """Markdown table of :func:`summarise`; ``failed``: the failed runs left out (:func:`bench._missions.failure_rows`),
    listed below it, marked †."""
    lines = ["| scene | budget (s) | view | uniform ROI PSNR | GaussLite ROI PSNR | gain, paired per frame [95 %] | "
             "runs × frames |", "|---|---|---|---|---|---|---|"]
    for scene, per in summary.items():
        for b, blk in per.items():
            for name, _, _ in ROWS:
                c = blk[name]
                lines.append(f"| {scene} | {b} | {name} | {fmt(c['uniform'], c['uniform_std'])} | "
                             f"{fmt(c['gausslite'], c['gausslite_std'])} | {fmt_gain(c['gain'])} | "
                             f"{c['runs']} × {c['gain']['n'] // max(1, c['runs'])} |")
    lines += ["", "Views (docs/realtime.md#cross-scoring): " + "; ".join(f"**{k}**: {v}" for k, v in ROW_HELP.items())
              + ". ROI PSNR in dB on the frames withheld from both mappers, mean ± std over runs."]
    for scene, per in summary.items():
        for b, blk in per.items():
            o = blk["offset"]
            lines.append(f"- {scene}, {b} s: tracking moved the views away from the sensor's pose by "
                         + ", ".join(f"{m} {fmt(o[m]['rot_deg'], None)}° / {fmt(100 * o[m]['trans_m'], None)} cm"
                                     if o[m]["trans_m"] is not None else f"{m} –" for m in ("uniform", "gausslite"))
                         + " (mean over frames and runs).")
    if failed:
        lines += ["", f"{FAILED_MARK} Runs whose mission failed, left out with their pair (end state and error in the "
                  "JSON's failed_runs):"] + [f"- {describe(r, RUN_KEYS)}" for r in failed]
    return "\n".join(lines)


def mission_jobs(args: argparse.Namespace, work: Path) -> list[dict]:
    """The (scene, run, mode) jobs of ``bench.realtime``'s protocol at ``--budget``, each saving its map unscored."""
    specs = (dataset_scenes(Path(args.dataset), [t for t in args.tasks.split(",") if t], args.cap or 6000,
                            args.downscale, args.fps) if args.dataset
             else {s: SCENES[s] for s in args.scenes.split(",") if s})
    jobs = []
    for scene, spec in specs.items():
        path = Path(spec["path"]) if "path" in spec else scene_path(scene, work)
        for run in range(args.runs):
            for mode in ("uniform", "gausslite"):
                jobs.append({"scene": scene, "spec": spec, "path": str(path), "task": spec["task"], "mode": mode,
                             "budget": args.budget, "run": run, "cap": args.cap or spec["cap"], "clock": args.clock,
                             "final_pass": False, "overrides": list(args.overrides), "novel_every": args.novel_every,
                             "protocols": ("sensor",), "track_iters": args.track_iters, "render_dir": None,
                             "defer_dir": str(work / "maps")})
    return jobs


def pairs_of(runs: list[dict], track_iters: int) -> list[dict]:
    """Cross-score every (scene, budget, run) that has a saved map of both modes."""
    by = {}
    for r in runs:
        if "state_path" in r:
            by.setdefault((r["scene"], float(r["budget"]), r["run"]), {})[r["mode"]] = r
    pairs = []
    for (scene, b, run), modes in sorted(by.items()):
        if set(modes) != {"uniform", "gausslite"}:
            continue
        mu, frames, ann, task, novel = load_map(modes["uniform"])
        mg, _, _, _, novel_g = load_map(modes["gausslite"])
        if not novel or novel != novel_g:
            raise ValueError(f"{scene} run {run}: both modes must withhold the same frames (--novel-every >= 2)")
        rows = cross_score(mu, mg, frames, task_roi(ann, task), novel, track_iters)
        pairs.append({"scene": scene, "budget": b, "run": run, "rows": rows})
        print(f"{scene} b={b:g} run {run}: " + "; ".join(
            f"{name} {fmt_gain(paired_gain(rows[name]['gausslite'], rows[name]['uniform']))}" for name, _, _ in ROWS))
    return pairs


def main(argv: Optional[list[str]] = None) -> int:
    """Run the cross-scoring of the command line ``argv`` (``--help``); 0 on success."""
    ap = argparse.ArgumentParser(prog="python -m bench.cross_scoring", description=__doc__.split("\n\n")[0])
    ap.add_argument("--from", dest="source", type=Path, default=None, metavar="PARTIAL",
                    help="the <out>.partial.json of a `python -m bench.realtime --missions-only` run: its saved maps")
    ap.add_argument("--scenes", default=None,
                    help="scenes to run (default synthetic_circle) or, with --from, to score (default: every scene "
                         "of the file)")
    ap.add_argument("--dataset", default=None, metavar="PATH", help="a sequence of your own (bench.realtime --dataset)")
    ap.add_argument("--tasks", default="", help="--dataset: task ids, comma-separated")
    ap.add_argument("--fps", type=float, default=None, help="--dataset: replay clock of sequences without timestamps")
    ap.add_argument("--downscale", type=float, default=1.0, help="--dataset: image downscale factor")
    ap.add_argument("--cap", type=int, default=None, help="Gaussian cap (default: the scene's)")
    ap.add_argument("--budget", type=float, default=REFERENCE_BUDGET_S, help="seconds per keyframe")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--clock", choices=("scaled", "dataset"), default="scaled")
    ap.add_argument("--twin", action="store_true", help="the deterministic twin instead of live missions")
    ap.add_argument("--novel-every", type=int, default=NOVEL_EVERY, help="every k-th frame withheld (>= 2)")
    ap.add_argument("--track-iters", type=int, default=TRACK_ITERS, help="the tracker's Adam steps per frame")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="agent config override for both modes")
    ap.add_argument("--work", default="/tmp/gausslite_bench_cross_scoring")
    ap.add_argument("--out", type=Path, default=RESULTS / "cross_scoring.json")
    add_allow_failed(ap)
    args = ap.parse_args(argv)
    if args.novel_every < 2:
        ap.error("--novel-every must be >= 2: the cross-scoring scores the withheld frames")
    t0 = time.time()
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    if args.source is not None:
        runs = json.loads(args.source.read_text())["runs"]
        if args.scenes:
            runs = [r for r in runs if r["scene"] in args.scenes.split(",")]
    else:
        args.scenes = args.scenes or "synthetic_circle"
        try:
            jobs = mission_jobs(args, work)
        except (FileNotFoundError, ValueError, KeyError) as e:
            ap.error(str(e))
        runs = [(twin_one if args.twin else run_one)(job) for job in jobs]
    failed = failure_rows(runs, RUN_KEYS)
    pairs = pairs_of(succeeded(runs), args.track_iters)
    if not pairs and not failed:
        ap.error("no run holds a saved map of both modes")
    summary = summarise(pairs)
    result = {"settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
              "summary": summary, "pairs": pairs, "failed_runs": failed, "wall_s": time.time() - t0}
    write_results(args.out, "cross_scoring", argv, f": {len(pairs)} pairs of maps, {(time.time() - t0) / 60:.1f} min",
                  table(summary, failed), result)
    return exit_code(runs, args.allow_failed, "bench.cross_scoring", RUN_KEYS)


if __name__ == "__main__":
    sys.exit(main())
