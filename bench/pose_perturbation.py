"""Robustness to pose error: how much of GaussLite's ROI gain over uniform mapping survives SLAM-like poses?

    python -m bench.pose_perturbation [--scenes synthetic_circle,synthetic_walk] [--levels exact,1cm_0.5deg,3cm_1.5deg]
                                      [--seeds 3] [--modes uniform,gausslite] [--refine off,on] [--frames 40]
                                      [--withhold-every 5] [--track-iters 20] [--jobs 2] [--set KEY=VALUE ...]
                                      [--out bench/results/pose_perturbation.json] [--resume|--fresh]

The scenes are rendered, so their poses are exact and the error is known exactly:

- ``synthetic_circle``: ``bench.realtime``'s scene (the synthetic room along ``make-scene --trajectory circle``,
  300 frames, agent_a, task ``synth-pick-object``) loaded at 160×120; the sequence is ``--frames`` frames spread
  evenly over it (every 7th frame for 40: 280 of its 300 frames, about 10 m of path).
- ``synthetic_walk``: the room along ``make-scene --trajectory walk`` (525 frames at 160×120, exact renders:
  a 7 m hand-held walk, two loops in front of the desk), agent_a, same task; every 13th frame for 40.

Every run maps one sequence OFFLINE (:func:`gausslite.pipeline.run_mapping`: fixed iteration counts, the sensor
profile's defaults, one rasterizer thread) with the frames' given poses replaced by a SLAM-like estimate
(:func:`gausslite.datasets.trajectory.perturb_trajectory` at the level, seeded by the run's seed; ``exact`` keeps the
true poses). Every ``--withhold-every``-th frame (from the middle of the first block on,
:func:`gausslite.datasets.subset.withheld_indices`) is withheld from the mapper. GaussLite's relevance is the task's
ground-truth ROI from the frames' TRUE poses (as an image-based detector sees it: no pose in it).

Scoring: the final map is rendered at the withheld frames' TRUE poses (no pose correction: where the robot really
was) and scored there on the task's ground-truth ROI (ROI PSNR) and the whole image (PSNR); the same on the mapped
frames at their true poses. A map built at drifting poses is misplaced against the world, so this is the error a
robot sees when it uses the map from where it is.

Variants: ``--refine off`` maps at the given poses as they are; ``on`` sets ``pose.refine=true`` and
``pose.track_iters=N`` (the map's keyframe pose refinement and per-frame tracking, docs/mapper.md "Pose refinement").
Per (scene, level, refine): each mode's ROI PSNR (mean ± std over seeds), the paired gain GaussLite − uniform per seed
(mean ± std, significant when the mean exceeds twice its std), and the fraction of the exact-pose gain kept (the level's
mean gain over the exact level's mean gain under the same refine setting). The seed drives both the perturbation and
the mapper.

Writes ``bench/results/pose_perturbation.json`` (through ``bench/_results.py``), ``.md`` and ``.png`` (gain and ROI
PSNR against the level). After each run the runs so far go to ``<out>.partial.json``; ``--resume`` runs only the
missing ones (runs are deterministic per seed).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from bench import realtime
from bench._results import write_results
from bench.long_mission import load_partial
from gausslite.config import load_mapper_config
from gausslite.datasets import task_roi
from gausslite.datasets.subset import EstimatedPoses, FrameSubset, withheld_indices
from gausslite.datasets.trajectory import POSE_ERROR_LEVELS, perturb_trajectory, pose_error_stats
from gausslite.evaluation import render_map, score_view
from gausslite.pipeline import run_mapping
from gausslite.stats import fmt, gain, mean_std
from gausslite.synthetic import make_scene

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"

#: the scenes: where they come from, their load resolution and task, and the step between sequence frames
SCENES = {
    "synthetic_circle": {"source": "realtime", "downscale": 2.0, "task": realtime.SCENES["synthetic_circle"]["task"]},
    "synthetic_walk": {"source": "walk", "frames": 525, "width": 160, "height": 120, "downscale": 1.0,
                       "task": "synth-pick-object"},
}
LEVELS = tuple(POSE_ERROR_LEVELS)
MODES = ("uniform", "gausslite")
#: tracking steps per frame of the refine variant (docs/results.md measured tracking with 20)
TRACK_ITERS = 20


def scene_path(name: str, work: Path) -> Path:
    """The sequence folder (agent_a) of a bench scene, rendered into ``work`` once."""
    spec = SCENES[name]
    if spec["source"] == "realtime":
        return realtime.scene_path(name, work)
    out = work / f"synthetic_walk_{spec['frames']}_{spec['width']}x{spec['height']}"
    if not (out / "agent_a" / "results" / f"depth{spec['frames'] - 1:06d}.png").exists():
        make_scene(out, frames=spec["frames"], width=spec["width"], height=spec["height"], trajectory="walk")
    return out / "agent_a"


def sequence(n_total: int, frames: int, withhold_every: int) -> tuple[list[int], list[int]]:
    """``(mapped, withheld)`` dataset indices: ``frames`` indices spread evenly over ``n_total`` (step
    ``n_total // frames``), every ``withhold_every``-th of them withheld (:func:`withheld_indices`).

    Raises:
        ValueError: fewer than ``frames`` frames, or ``frames < 2``.
    """
    if frames < 2 or n_total < frames:
        raise ValueError(f"need 2 <= frames <= {n_total}, got {frames}")
    idx = list(range(0, (n_total // frames) * frames, n_total // frames))
    held = {idx[j] for j in withheld_indices(len(idx), withhold_every)}
    return [i for i in idx if i not in held], sorted(held)


def _score(render, frames: list, roi_fn) -> dict:
    """Mean ROI PSNR and PSNR of ``render`` (frame -> RenderOutput) over ``frames``; ROI over non-empty ROIs."""
    scores = [score_view(render(fr), fr, roi_fn(fr)) for fr in frames]
    roi = [s.roi_psnr for s in scores if np.isfinite(s.roi_psnr)]
    return {"roi_psnr": float(np.mean(roi)) if roi else None, "psnr": float(np.mean([s.psnr for s in scores])),
            "roi_psnr_per_frame": {int(s.frame_id): s.roi_psnr for s in scores if np.isfinite(s.roi_psnr)}}


def _map(job: dict, ds, profile, mapped: list[int], est_by_id: dict):
    """Map the ``mapped`` frames of ``ds`` at the poses ``est_by_id`` (frame id -> c2w) with the job's settings."""
    view = EstimatedPoses(FrameSubset(ds, [i for i in range(len(ds)) if i not in set(mapped)]), est_by_id)
    overrides = list(job["overrides"])
    if job["refine"]:
        overrides += ["pose.refine=true", f"pose.track_iters={job['track_iters']}"]
    cfg = load_mapper_config(None, overrides, defaults=dict(profile.mapper), mode=job["mode"], seed=job["seed"],
                             performance={"render_threads": 1})
    task = SCENES[job["scene"]]["task"]
    mapper, _ = run_mapping(view, cfg, task_id=task, relevance_fn=view.roi_fn(ds.annotations, task), progress=False)
    return mapper


def run_one(job: dict) -> dict:
    """Map one (scene, level, refine, mode, seed) at perturbed poses and score it at the true poses (a worker);
    also at the poses the robot believes (the estimate with the map's correction), for comparison."""
    torch.set_num_threads(1)
    spec = SCENES[job["scene"]]
    ds, profile = realtime.load_scene({"downscale": spec["downscale"]}, Path(job["path"]))
    mapped, held = sequence(len(ds), job["frames"], job["withhold_every"])
    order = sorted(mapped + held)
    frames = {i: ds[i] for i in order}
    true = np.stack([frames[i].c2w for i in order])
    est = perturb_trajectory(true, job["level"], seed=job["seed"])
    est_of = {i: est[k] for k, i in enumerate(order)}
    t0 = time.perf_counter()
    mapper = _map(job, ds, profile, mapped, {int(frames[i].frame_id): est_of[i] for i in mapped})
    wall = time.perf_counter() - t0
    gmap, roi = mapper.gmap, task_roi(ds.annotations, SCENES[job["scene"]]["task"])
    believed = {i: mapper.pose_of(int(frames[i].frame_id), est_of[i]) for i in order}
    by_id = {int(frames[i].frame_id): believed[i] for i in order}

    def at_true(fr):
        return render_map(gmap, fr)

    def at_estimate(fr):  # the estimate with the map's correction; the ROI stays the true one
        return render_map(gmap, dataclasses.replace(fr, c2w=by_id[int(fr.frame_id)]))

    withheld = _score(at_true, [frames[i] for i in held], roi)
    withheld_est = _score(at_estimate, [frames[i] for i in held], roi)
    on_mapped = _score(at_true, [frames[i] for i in mapped], roi)
    mk = [k for k, i in enumerate(order) if i in set(mapped)]
    believed_mapped = np.stack([believed[i] for i in mapped])
    return {**{k: job[k] for k in ("scene", "level", "refine", "mode", "seed")},
            "roi_psnr": withheld["roi_psnr"], "psnr": withheld["psnr"],
            "roi_psnr_per_frame": withheld["roi_psnr_per_frame"],
            "roi_psnr_at_estimate": withheld_est["roi_psnr"], "psnr_at_estimate": withheld_est["psnr"],
            "roi_psnr_mapped": on_mapped["roi_psnr"], "psnr_mapped": on_mapped["psnr"],
            "pose_error": pose_error_stats(est, true), "pose_error_mapped": pose_error_stats(est[mk], true[mk]),
            "pose_error_after_map": pose_error_stats(believed_mapped, true[mk]),
            "n_mapped": len(mapped), "n_withheld": len(held), "n_gaussians": len(mapper.model),
            "s_per_frame": float(np.mean([s.seconds for s in mapper.stats])), "wall_s": wall}


def summarise(runs: list[dict], scenes: list[str], levels: list[str], refines: list[bool], seeds: list[int]) -> dict:
    """Per scene, refine setting and level: each mode's figures (mean ± std over seeds), the paired ROI gain and the
    fraction of the exact level's gain kept."""
    out: dict = {}
    for scene in scenes:
        for refine in refines:
            block: dict = {}
            for level in levels:
                rs = [r for r in runs if r["scene"] == scene and r["refine"] == refine and r["level"] == level]
                by = {m: {r["seed"]: r for r in rs if r["mode"] == m} for m in MODES}
                row: dict = {"seeds": [s for s in seeds if all(s in by[m] for m in MODES)]}
                for m in MODES:
                    for k in ("roi_psnr", "psnr", "roi_psnr_at_estimate", "roi_psnr_mapped", "psnr_mapped",
                              "n_gaussians", "s_per_frame"):
                        row[f"{m}_{k}"], row[f"{m}_{k}_std"] = mean_std([by[m][s][k] for s in by[m]])
                pe = [r["pose_error"] for r in rs if r["mode"] == "uniform"]
                for k in ("ate_m", "rot_rmse_deg", "trans_rmse_m", "trans_max_m"):
                    row[k], row[k + "_std"] = mean_std([p[k] for p in pe])
                for m in MODES:  # the mapped frames' poses after mapping (refined, or as given) against the truth
                    for k in ("ate_m", "rot_rmse_deg", "trans_rmse_m"):
                        row[f"{m}_after_map_{k}"], row[f"{m}_after_map_{k}_std"] = mean_std(
                            [by[m][s]["pose_error_after_map"][k] for s in by[m]])
                for key, field in (("gain", "roi_psnr"), ("gain_mapped", "roi_psnr_mapped"),
                                   ("gain_at_estimate", "roi_psnr_at_estimate")):
                    g = gain([by["gausslite"][s][field] for s in row["seeds"]],
                             [by["uniform"][s][field] for s in row["seeds"]])
                    row[key], row[key + "_std"], row[key + "_significant"] = g["gain"], g["gain_std"], g["significant"]
                block[level] = row
            ref = block.get("exact", {}).get("gain")
            for level, row in block.items():
                row["gain_kept"] = (row["gain"] / ref) if ref and row["gain"] is not None and ref > 0 else None
            out.setdefault(scene, {})["refine_on" if refine else "refine_off"] = block
    return out


def table(summary: dict) -> str:
    """The Markdown table of :func:`summarise`'s result."""
    lines = ["| scene | pose refine | level | given poses: ATE / rot / unaligned RMSE | mapped poses after mapping, "
             "uniform / GaussLite: unaligned RMSE, rot | uniform ROI PSNR | GaussLite ROI PSNR "
             "| gain (GaussLite − uniform) | exact gain kept | gain on mapped views | gain at the believed pose |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for scene, by_refine in summary.items():
        for rkey, block in by_refine.items():
            for level, r in block.items():
                err = (f"{100 * r['ate_m']:.2f} cm / {r['rot_rmse_deg']:.2f}° / {100 * r['trans_rmse_m']:.2f} cm"
                       if r["ate_m"] is not None else "–")
                g = "–" if r["gain"] is None else (f"{fmt(r['gain'], r['gain_std'])} dB"
                                                  + (" (sig.)" if r["gain_significant"] else ""))
                kept = "–" if r["gain_kept"] is None else f"{100 * r['gain_kept']:.0f} %"
                after = " / ".join("–" if r[f"{m}_after_map_trans_rmse_m"] is None else
                                   f"{100 * r[f'{m}_after_map_trans_rmse_m']:.2f} cm, "
                                   f"{r[f'{m}_after_map_rot_rmse_deg']:.2f}°" for m in MODES)
                lines.append(f"| {scene} | {rkey.split('_')[1]} | {level} | {err} | {after} | "
                             f"{fmt(r['uniform_roi_psnr'], r['uniform_roi_psnr_std'])} | "
                             f"{fmt(r['gausslite_roi_psnr'], r['gausslite_roi_psnr_std'])} | {g} | {kept} | "
                             f"{fmt(r['gain_mapped'], r['gain_mapped_std'])} | "
                             f"{fmt(r['gain_at_estimate'], r['gain_at_estimate_std'])} |")
    return "\n".join(lines)


def plot(summary: dict, path: Path) -> None:
    """ROI gain (left) and each mode's ROI PSNR (right) against the pose error level, per scene and refine setting."""
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    styles = {"refine_off": "-", "refine_on": "--"}
    for k, (scene, by_refine) in enumerate(summary.items()):
        for rkey, block in by_refine.items():
            levels = list(block)
            x = np.arange(len(levels)) + 0.04 * k
            lab = f"{scene}, refine {rkey.split('_')[1]}"
            g = [np.nan if block[lv]["gain"] is None else block[lv]["gain"] for lv in levels]
            e = [0.0 if block[lv]["gain_std"] is None else block[lv]["gain_std"] for lv in levels]
            axes[0].errorbar(x, g, yerr=e, ls=styles[rkey], marker="o", capsize=3, color=f"C{k}", label=lab)
            for m, mk in (("uniform", "s"), ("gausslite", "o")):
                v = [np.nan if block[lv][f"{m}_roi_psnr"] is None else block[lv][f"{m}_roi_psnr"] for lv in levels]
                axes[1].plot(x, v, ls=styles[rkey], marker=mk, color=f"C{k}", label=f"{lab}, {m}")
    for ax, ylab in zip(axes, ("ROI gain GaussLite − uniform [dB]", "ROI PSNR at true poses [dB]")):
        ax.set_xticks(np.arange(len(levels)), levels)
        ax.set_xlabel("pose error level (ATE_rotation)")
        ax.set_ylabel(ylab)
        ax.grid(alpha=0.3)
    axes[0].axhline(0.0, color="grey", lw=0.8)
    axes[0].legend(fontsize=7)
    axes[1].legend(fontsize=6, ncol=2)
    fig.suptitle("Withheld views scored at their true poses (mean ± std over seeds)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _parser() -> argparse.ArgumentParser:
    """The command line of ``python -m bench.pose_perturbation``."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma list of " + ", ".join(SCENES))
    ap.add_argument("--levels", default=",".join(LEVELS), help="comma list of pose error levels ('exact', '<x>cm_<y>deg')")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per cell (default 3)")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--refine", default="off,on", help="pose refinement variants: off, on or off,on (default)")
    ap.add_argument("--frames", type=int, default=40, help="frames per sequence, spread over the scene (default 40)")
    ap.add_argument("--withhold-every", type=int, default=5, help="withhold every k-th sequence frame (default 5)")
    ap.add_argument("--track-iters", type=int, default=TRACK_ITERS, help="pose.track_iters of the refine variant")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2, one rasterizer thread each)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="mapper config override for every run")
    ap.add_argument("--work", type=Path, default=REPO / "runs" / "bench_pose_perturbation", help="rendered scenes")
    ap.add_argument("--out", type=Path, default=RESULTS / "pose_perturbation.json")
    ap.add_argument("--resume", action="store_true", help="keep the runs of <out>.partial.json, run the missing ones")
    ap.add_argument("--fresh", action="store_true", help="discard an existing <out>.partial.json")
    return ap


def _jobs(args: argparse.Namespace, scenes: list[str], levels: list[str], refines: list[bool], modes: list[str],
          seeds: list[int]) -> list[dict]:
    """One job per (scene, level, refine, mode, seed), the scenes rendered first."""
    paths = {s: str(scene_path(s, args.work)) for s in scenes}
    return [{"scene": s, "path": paths[s], "level": lv, "refine": rf, "mode": m, "seed": sd, "frames": args.frames,
             "withhold_every": args.withhold_every, "track_iters": args.track_iters, "overrides": args.overrides}
            for s in scenes for lv in levels for rf in refines for sd in seeds for m in modes]


def _key(r: dict) -> tuple:
    return (r["scene"], r["level"], r["refine"], r["mode"], r["seed"])


def main(argv: Optional[list[str]] = None) -> int:
    """Run the bench; returns the exit code."""
    ap = _parser()
    args = ap.parse_args(argv)
    scenes = [s for s in args.scenes.split(",") if s]
    levels = [lv for lv in args.levels.split(",") if lv]
    modes = [m for m in args.modes.split(",") if m]
    refines = [{"off": False, "on": True}[r] for r in args.refine.split(",") if r]
    seeds = list(range(args.seeds))
    if any(s not in SCENES for s in scenes):
        ap.error(f"unknown scene in {scenes}; known: {list(SCENES)}")
    settings = {k: getattr(args, k) for k in ("frames", "withhold_every", "track_iters", "overrides")}
    partial = args.out.with_suffix(".partial.json")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if partial.exists() and not (args.resume or args.fresh):
        ap.error(f"{partial} exists: --resume to continue it or --fresh to discard it")
    runs, wall0 = load_partial(partial, settings) if args.resume else ([], 0.0)
    done = {_key(r) for r in runs}
    jobs = [j for j in _jobs(args, scenes, levels, refines, modes, seeds) if _key(j) not in done]
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futs = [pool.submit(run_one, j) for j in jobs]
        for f in tqdm(as_completed(futs), total=len(futs), desc="pose_perturbation", unit="run"):
            runs.append(f.result())
            partial.write_text(json.dumps({"settings": settings, "runs": runs,
                                           "wall_s": wall0 + time.perf_counter() - t0}, indent=1))
    summary = summarise(runs, scenes, levels, refines, seeds)
    wall = wall0 + time.perf_counter() - t0
    result = {"settings": {**settings, "scenes": scenes, "levels": levels, "modes": modes, "seeds": seeds,
                           "refine": args.refine, "scoring": "withheld frames at their true poses"},
              "summary": summary, "runs": runs, "wall_s": wall}
    plot(summary, args.out.with_suffix(".png"))
    write_results(args.out, "pose_perturbation", argv, f": {len(seeds)} seeds, {len(runs)} runs, {wall / 60:.0f} min "
                  "(2-core machine shared with other work)", table(summary), result)
    partial.unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
