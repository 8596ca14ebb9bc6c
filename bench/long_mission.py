"""Retention benchmark: does the map keep what it has seen over a long mission?

    python -m bench.long_mission [--seeds 3] [--tasks 2|all|ID,ID] [--jobs 2] [--scenes tum_fr1_rpy,synthetic_long]
                                 [--modes uniform,gausslite]
                                 [--tum-downscale 2] [--synthetic-frames 600] [--set KEY=VALUE ...] [--resume|--fresh]

On this 2-core machine the full default bench takes longer than a session; the run reported in
``docs/results.md`` used ``--tasks 1 --tum-downscale 4 --synthetic-frames 300`` (TUM at 160×120, the synthetic
circle with 300 frames, 150 of them mapped), and says so. After every run the
runs so far are written to ``<out>.partial.json`` with the settings; ``--resume`` reads it back and runs
only the missing (scene, mode, task, seed) runs, so a bench longer than a session finishes over several
(runs are deterministic per seed: a resumed bench gives the figures of an uninterrupted one). An existing
partial file stops a bench started without ``--resume`` (its runs would be lost); ``--fresh`` discards it.

Scenes, each mapped at matched budget (same seeding rule, budget rule and iterations in both modes):

- ``tum_fr1_rpy``: TUM RGB-D fr1/rpy, all 150 frames (``$GAUSSLITE_SHARED/datasets``) at 320×240, default (hand-held)
  profile: undistorted, interpolated poses. It maps every frame, so held-out PSNR is null.
- ``synthetic_long``: the synthetic room rendered along ``make-scene --trajectory circle`` (600
  frames at 160×120, agent_a); every 2nd frame is mapped (300 frames), the frames between them are the
  held-out views.

Uniform mapping runs once per scene and seed (its map does not depend on the task), and every task's
ROI is scored on it; full GaussLite runs once per task and seed. For every run: PSNR and ROI PSNR
over all mapped frames, PSNR per fifth of the sequence, held-out PSNR, s/frame, Gaussian count. Every
figure is the mean over seeds with its standard deviation beside it (``<field>_std``); the ROI gain
is paired per seed and counts only when it exceeds twice its standard deviation.

Writes ``bench/results/long_mission.json``, ``long_mission.md`` and ``long_mission_<scene>.png`` (PSNR
along the sequence, both modes). Runs go to ``--jobs`` worker processes (one rasterizer thread each).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from bench._results import command_line, portable_text, write_json
from gausslite.datasets import detect_layout, load_dataset
from gausslite.config import load_mapper_config
from gausslite.mapping.profiles import profile_for_layout
from gausslite.pipeline import run_mapping
from gausslite.stats import aggregate, fmt, gain, mean_std
from gausslite.synthetic import make_scene

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
RESULTS = REPO / "bench" / "results"

SCENES = {
    "tum_fr1_rpy": {"kind": "tum", "downscale": 2.0, "stride": 1},
    "synthetic_long": {"kind": "synthetic", "frames": 600, "width": 160, "height": 120, "stride": 2},
}


def scene_path(name: str, work: Path) -> Path:
    """The dataset folder of a bench scene (the synthetic one is generated into ``work`` once)."""
    spec = SCENES[name]
    if spec["kind"] == "tum":
        p = SHARED / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy"
        if not p.is_dir():
            raise FileNotFoundError(f"{p} not found (set GAUSSLITE_SHARED)")
        return p

    out = work / f"synthetic_circle_{spec['frames']}_{spec['width']}x{spec['height']}"
    if not (out / "agent_a" / "results" / f"depth{spec['frames'] - 1:06d}.png").exists():
        make_scene(out, frames=spec["frames"], width=spec["width"], height=spec["height"], trajectory="circle")
    return out / "agent_a"


def load_scene(name: str, path: Path, max_frames: Optional[int] = None, downscale: Optional[float] = None):
    """The dataset with the loader options of its sensor profile."""
    spec = SCENES[name]
    profile = profile_for_layout(detect_layout(path)[0])
    ds = load_dataset(path, downscale=downscale or spec.get("downscale", 1.0), max_frames=max_frames, **profile.loader)
    return ds, profile


def map_job(job: dict):
    """Map one (scene, mode, task, seed) job with the scene's profile, one rasterizer thread.

    Returns:
        (dataset, mapper, metrics of ``run_mapping``, wall seconds).
    """
    torch.set_num_threads(1)
    ds, profile = load_scene(job["scene"], Path(job["path"]), job.get("max_frames"), job.get("downscale"))
    stride = SCENES[job["scene"]]["stride"]
    cfg = load_mapper_config(None, job.get("overrides", []), defaults=dict(profile.mapper), mode=job["mode"],
                             seed=job["seed"], performance={"render_threads": 1})
    t0 = time.perf_counter()
    # run_mapping scores every mapped frame (at the mapper's refined pose under pose_refine, as SLAM
    # systems score at their own poses) and, in the same render pass, each task's ROI
    mapper, m = run_mapping(ds, cfg, task_id=job["task"], stride=stride, out_dir=None, progress=False,
                            eval_task_ids=job["eval_tasks"])
    return ds, mapper, m, time.perf_counter() - t0


def run_one(job: dict) -> dict:
    """Map one (scene, mode, task, seed) and score it; runs in a worker process."""
    _, mapper, m, wall = map_job(job)
    task = job["task"]
    frame_psnr = [f["psnr"] for f in m["per_frame"]]
    fifths = [float(np.mean(c)) for c in np.array_split(np.array(frame_psnr), 5)]
    secs = [s.seconds for s in mapper.stats]
    return {
        "scene": job["scene"], "mode": job["mode"], "task": task, "seed": job["seed"],
        "psnr": float(np.mean(frame_psnr)),
        "roi_psnr_per_task": {t: v["roi_psnr"] for t, v in m["per_task"].items()},
        "psnr_by_fifth": fifths,
        "heldout_psnr": m.get("heldout_psnr"),
        "s_per_frame": float(np.mean(secs)),
        "s_per_frame_by_fifth": [float(np.mean(c)) for c in np.array_split(np.array(secs), 5)],
        "n_gaussians": len(mapper.model),
        "n_keyframes": len(mapper.keyframes),
        "keyframe_mb": mapper.keyframes.nbytes / 1e6,
        "frame_psnr": frame_psnr,
        # pose refinement (hand-held profile): mean correction of the sensor poses, degrees / metres
        "pose_correction_deg": float(np.mean(mapper.poses.magnitudes()[0])) if mapper.poses else None,
        "pose_correction_m": float(np.mean(mapper.poses.magnitudes()[1])) if mapper.poses else None,
        "wall_s": wall,
    }


def summarise(runs: list[dict], scene: str, tasks: list[str], seeds: list[int]) -> dict:
    """The JSON block of one scene: per mode, every figure as mean and std over seeds."""
    def roi(rseed: list[dict], task: str) -> Optional[float]:
        """ROI PSNR of ``task`` in one seed's runs: the uniform map serves every task, GaussLite maps per task."""
        return next((r["roi_psnr_per_task"][task] for r in rseed if r["task"] in (None, task)), None)

    out: dict = {"tasks": tasks, "seeds": seeds}
    per_seed_roi: dict[str, list] = {}
    for mode in ("uniform", "gausslite"):
        rs = [r for r in runs if r["scene"] == scene and r["mode"] == mode]
        by_seed = []
        roi_by_seed = []
        per_task: dict[str, list] = {t: [] for t in tasks}
        for s in seeds:
            rseed = [r for r in rs if r["seed"] == s]
            if not rseed:
                continue
            for t in tasks:
                per_task[t].append(roi(rseed, t))
            vals = [per_task[t][-1] for t in tasks if per_task[t][-1] is not None]
            roi_by_seed.append(float(np.mean(vals)) if vals else None)
            by_seed.append({
                "psnr": float(np.mean([r["psnr"] for r in rseed])),
                "roi_psnr": roi_by_seed[-1],
                "psnr_by_fifth": list(np.mean([r["psnr_by_fifth"] for r in rseed], axis=0)),
                "heldout_psnr": (float(np.mean([r["heldout_psnr"] for r in rseed]))
                                 if all(r["heldout_psnr"] is not None for r in rseed) else None),
                "s_per_frame": float(np.mean([r["s_per_frame"] for r in rseed])),
                "s_per_frame_by_fifth": list(np.mean([r["s_per_frame_by_fifth"] for r in rseed], axis=0)),
                "n_gaussians": float(np.mean([r["n_gaussians"] for r in rseed])),
                "keyframe_mb": float(np.mean([r["keyframe_mb"] for r in rseed])),
            })
        block = aggregate(by_seed, ["psnr", "roi_psnr", "psnr_by_fifth", "heldout_psnr", "s_per_frame",
                                    "s_per_frame_by_fifth", "n_gaussians", "keyframe_mb"])
        fifth = block["psnr_by_fifth"]
        block["retention_db"] = (fifth[0] - fifth[-1]) if by_seed and None not in (fifth[0], fifth[-1]) else None
        block["roi_psnr_per_task"] = {t: dict(zip(("roi_psnr", "roi_psnr_std"), mean_std(v)))
                                      for t, v in per_task.items()}
        block["seeds"] = [s for s in seeds if any(r["seed"] == s for r in rs)]
        out[mode] = block
        per_seed_roi[mode] = roi_by_seed
    if len(per_seed_roi["uniform"]) == len(per_seed_roi["gausslite"]):
        out["roi_gain"] = gain(per_seed_roi["gausslite"], per_seed_roi["uniform"])
    return out


def plot_scene(runs: list[dict], scene: str, path: Path) -> None:
    """PSNR along the sequence (mapped frames), both modes, mean over seeds (and tasks)."""
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 3.6))
    for mode, color in (("uniform", "tab:blue"), ("gausslite", "tab:red")):
        rs = [r for r in runs if r["scene"] == scene and r["mode"] == mode]
        if not rs:
            continue
        curve = np.mean([r["frame_psnr"] for r in rs], axis=0)
        ax.plot(curve, color=color, alpha=0.35, lw=0.8)
        k = max(1, len(curve) // 30)
        padded = np.pad(curve, (k // 2, k - 1 - k // 2), mode="edge")  # no zero-padding dips at the ends
        smooth = np.convolve(padded, np.ones(k) / k, mode="valid")
        ax.plot(smooth, color=color, lw=2, label=f"{mode} (mean {curve.mean():.2f} dB, {len(rs)} runs)")
    for q in range(1, 5):
        ax.axvline(q * len(curve) / 5, color="grey", lw=0.5, ls=":")
    ax.set_xlabel("mapped frame (mission order)")
    ax.set_ylabel("PSNR of the final map [dB]")
    ax.set_title(f"{scene}: final map scored on every mapped frame")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def table(result: dict) -> str:
    """Markdown table of the JSON result."""
    lines = ["| scene | mode | PSNR | ROI PSNR | PSNR by fifth (first → last) | first − last | held-out PSNR | s/frame | Gaussians |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, sc in result["scenes"].items():
        for mode in ("uniform", "gausslite"):
            b = sc.get(mode)
            if not b or b.get("psnr") is None:
                continue
            fifths = " / ".join("–" if v is None else f"{v:.2f}" for v in b["psnr_by_fifth"])
            lines.append(f"| {name} | {mode} | {fmt(b['psnr'], b['psnr_std'])} | {fmt(b['roi_psnr'], b['roi_psnr_std'])} "
                         f"| {fifths} | {'–' if b['retention_db'] is None else format(b['retention_db'], '+.2f')} | {fmt(b['heldout_psnr'], b.get('heldout_psnr_std'))} "
                         f"| {fmt(b['s_per_frame'], b['s_per_frame_std'])} | {b['n_gaussians']:.0f} |")
        g = sc.get("roi_gain")
        if g and g["gain"] is not None:
            lines.append(f"| {name} | ROI gain | | {fmt(g['gain'], g['gain_std'])} dB "
                         f"({'significant' if g['significant'] else 'not significant'}: > 2σ needed) | | | | | |")
    return "\n".join(lines)


def select_tasks(spec: str, all_tasks: list[str]) -> list[str]:
    """The tasks of ``--tasks``: a number (the first N), ``all``, or a comma list of task ids.

    Raises:
        ValueError: a count < 1 or an unknown task id (the message lists the scene's tasks).
    """
    spec = spec.strip()
    if spec == "all":
        return list(all_tasks)
    if spec.isdigit():
        if int(spec) < 1:
            raise ValueError("--tasks must be >= 1")
        return list(all_tasks[: int(spec)])
    ids = [t.strip() for t in spec.split(",") if t.strip()]
    unknown = [t for t in ids if t not in all_tasks]
    if unknown or not ids:
        raise ValueError(f"unknown tasks {unknown or spec!r}; this scene has {all_tasks}")
    return ids


def _run_key(r: dict) -> tuple:
    return (r["scene"], r["mode"], r["task"], r["seed"])


def load_partial(path: Path, settings: dict) -> tuple[list[dict], float]:
    """Runs and wall seconds of an interrupted bench (``<out>.partial.json``) made with ``settings``.

    Returns:
        ([], 0.0) when there is no partial file.
    Raises:
        ValueError: the partial file was made with other settings (scenes, tasks, frames, resolution,
            overrides): its runs would not be comparable.
    """
    if not path.exists():
        return [], 0.0
    part = json.loads(path.read_text())
    settings = json.loads(json.dumps(settings))  # as written to the file (tuples become lists, ...)
    if part.get("settings") != settings:
        raise ValueError(f"{path} was made with other settings ({part.get('settings')}, now {settings}): "
                         "rerun with the same options or delete it")
    return list(part["runs"]), float(part.get("wall_s", 0.0))


def _parser() -> argparse.ArgumentParser:
    """The command line of ``python -m bench.long_mission``."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma list of " + ", ".join(SCENES))
    ap.add_argument("--seeds", type=int, default=3, help="random seeds per run (default 3)")
    ap.add_argument("--tasks", default="2",
                    help="tasks per scene for GaussLite: a number (first N), 'all', or a comma list of task ids")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    ap.add_argument("--modes", default="uniform,gausslite",
                    help="modes to run (default both; one mode: a comparison of settings within it, no ROI gain)")
    ap.add_argument("--max-frames", type=int, default=None, help="quick runs: first N frames only")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="mapper config override for both modes")
    ap.add_argument("--tum-downscale", type=float, default=None,
                    help="TUM image downscale (default 2: 320×240); 4 gives 160×120 for quick runs")
    ap.add_argument("--synthetic-frames", type=int, default=None,
                    help="frames of the synthetic circle (default 600; every 2nd is mapped)")
    ap.add_argument("--work", type=Path, default=REPO / "runs" / "bench_long_mission", help="generated scenes")
    ap.add_argument("--out", type=Path, default=RESULTS / "long_mission.json")
    ap.add_argument("--resume", action="store_true",
                    help="keep the runs of <out>.partial.json (same settings) and run only the missing ones")
    ap.add_argument("--fresh", action="store_true",
                    help="discard the runs of an existing <out>.partial.json and start over (without --resume or "
                    "--fresh, an existing partial file stops the bench, so that its runs are not lost)")
    return ap


def _scenes_seeds_modes(ap: argparse.ArgumentParser, args: argparse.Namespace
                        ) -> tuple[list[str], list[int], list[str]]:
    """The scenes (with ``--tum-downscale`` / ``--synthetic-frames`` applied to :data:`SCENES`), seeds and modes."""
    if args.tum_downscale is not None:
        SCENES["tum_fr1_rpy"]["downscale"] = float(args.tum_downscale)
    if args.synthetic_frames is not None:
        if args.synthetic_frames < 10:
            ap.error("--synthetic-frames must be >= 10")
        SCENES["synthetic_long"]["frames"] = int(args.synthetic_frames)
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = [s for s in scenes if s not in SCENES]
    if unknown:
        ap.error(f"unknown scenes {unknown}; known: {list(SCENES)}")
    seeds = list(range(args.seeds))
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or set(modes) - {"uniform", "gausslite"}:
        ap.error(f"--modes takes uniform and/or gausslite, got {args.modes!r}")
    return scenes, seeds, modes


def _build_jobs(ap: argparse.ArgumentParser, args: argparse.Namespace, scenes: list[str], seeds: list[int],
                modes: list[str]) -> tuple[list[dict], dict[str, list[str]]]:
    """The (scene, mode, task, seed) jobs to run and each scene's tasks (generates the synthetic scene once)."""
    jobs, scene_tasks = [], {}
    for sc in scenes:
        path = scene_path(sc, args.work)
        ann = load_dataset(path, max_frames=1).annotations
        all_tasks = [t.id for t in ann.tasks]
        try:
            tasks = select_tasks(args.tasks, all_tasks)
        except ValueError as e:
            ap.error(f"{sc}: {e}")
        scene_tasks[sc] = tasks
        base = {"scene": sc, "path": str(path), "max_frames": args.max_frames, "overrides": args.overrides,
                "downscale": SCENES[sc].get("downscale", 1.0)}
        for s in seeds:
            if "uniform" in modes:
                jobs.append({**base, "mode": "uniform", "task": None, "seed": s, "eval_tasks": tasks})
            if "gausslite" in modes:
                jobs.extend({**base, "mode": "gausslite", "task": t, "seed": s, "eval_tasks": [t]} for t in tasks)
    return jobs, scene_tasks


def _resume_or_fresh(ap: argparse.ArgumentParser, args: argparse.Namespace, jobs: list[dict], settings: dict,
                     partial_path: Path) -> tuple[list[dict], list[dict], float]:
    """``--resume`` / ``--fresh`` against ``partial_path``: (jobs still to run, runs kept, wall seconds before)."""
    runs, wall_before = [], 0.0
    if args.resume and args.fresh:
        ap.error("--resume and --fresh exclude each other")
    if not args.resume and not args.fresh and partial_path.exists():
        ap.error(f"{partial_path} holds the runs of an unfinished bench: pass --resume to keep them (same settings) "
                 "or --fresh to discard them")
    if args.resume:
        try:
            runs, wall_before = load_partial(partial_path, settings)
        except ValueError as e:
            ap.error(str(e))
        done = {_run_key(r) for r in runs}
        jobs = [j for j in jobs if _run_key(j) not in done]
        print(f"resuming: kept {len(runs)} run(s) from {partial_path}, {len(jobs)} to run")
    return jobs, runs, wall_before


def _run_jobs(jobs: list[dict], runs: list[dict], n_workers: int, settings: dict, out: Path, partial_path: Path,
              t0: float) -> None:
    """Run ``jobs`` on ``n_workers`` processes, appending to ``runs`` and rewriting ``partial_path`` after each."""
    with ProcessPoolExecutor(max_workers=n_workers) as ex:
        futs = {ex.submit(run_one, j): j for j in jobs}
        with tqdm(total=len(futs), desc="long_mission", unit="run") as bar:
            for f in as_completed(futs):
                j = futs[f]
                r = f.result()
                runs.append(r)
                bar.set_postfix(scene=j["scene"], mode=j["mode"], seed=j["seed"])
                bar.write(f"{j['scene']} {j['mode']} task={j['task']} seed={j['seed']}: PSNR {r['psnr']:.2f}, "
                          f"fifths {' '.join(f'{v:.1f}' for v in r['psnr_by_fifth'])}, "
                          f"{r['s_per_frame']:.2f} s/frame, {r['n_gaussians']} Gaussians")
                bar.update(1)
                partial = {"partial": True, "settings": settings, "runs": runs, "wall_s": time.time() - t0}
                out.parent.mkdir(parents=True, exist_ok=True)
                partial_path.write_text(json.dumps(partial))  # survives an interrupted bench (--resume)


def _write_results(args: argparse.Namespace, runs: list[dict], scenes: list[str], scene_tasks: dict, seeds: list[int],
                   modes: list[str], settings: dict, t0: float, argv: Optional[list[str]] = None) -> None:
    """Write the JSON, the markdown table and one plot per scene to ``--out``; print the table."""
    result = {
        "scenes": {sc: summarise(runs, sc, scene_tasks[sc], seeds) for sc in scenes},
        "settings": {"seeds": seeds, "tasks": args.tasks, "modes": modes, "max_frames": args.max_frames,
                     "overrides": args.overrides,
                     "scenes": {sc: SCENES[sc] for sc in scenes}, "jobs": args.jobs, "resumed": bool(args.resume),
                     "run_settings": settings},  # what --resume requires of a partial file
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "load_avg_end": os.getloadavg()},
        "wall_s": time.time() - t0,
        "runs": runs,  # with frame_psnr: the plot can be redrawn from the JSON
    }
    write_json(args.out, result, "long_mission", argv)
    md = table(result)
    head = f"# Long-mission retention\n\n`{command_line('long_mission', argv)}`\n\n"
    args.out.with_suffix(".md").write_text(portable_text(head + md + "\n"))
    for sc in scenes:
        plot_scene(runs, sc, args.out.parent / f"{args.out.stem}_{sc}.png")
    print(md)
    print(f"wrote {args.out} ({result['wall_s'] / 60:.1f} min)")


def main(argv: Optional[list[str]] = None) -> int:
    """Run the bench of the command line ``argv``; 0 on success."""
    ap = _parser()
    args = ap.parse_args(argv)
    scenes, seeds, modes = _scenes_seeds_modes(ap, args)
    jobs, scene_tasks = _build_jobs(ap, args, scenes, seeds, modes)
    settings = {"tasks": scene_tasks, "max_frames": args.max_frames, "overrides": args.overrides,
                "scenes": {sc: SCENES[sc] for sc in scenes}}
    partial_path = args.out.with_suffix(".partial.json")
    jobs, runs, wall_before = _resume_or_fresh(ap, args, jobs, settings, partial_path)
    t0 = time.time() - wall_before
    _run_jobs(jobs, runs, args.jobs, settings, args.out, partial_path, t0)
    partial_path.unlink(missing_ok=True)
    _write_results(args, runs, scenes, scene_tasks, seeds, modes, settings, t0, argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
