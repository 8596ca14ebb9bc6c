"""Offline ``gausslite map`` under its default time budget against the fixed schedule it replaced (docs/mapper.md,
"Running it").

    python -m bench.map_budget [--frames 250] [--size 640x480] [--trajectory circle] [--seeds 0,1,2]
                               [--fixed-frames 40] [--time-budget MIN] [--withhold 10] [--task-id ID]
                               [--set KEY=VALUE ...] [--work DIR] [--out bench/results/map_budget.json]

The input is the synthetic scene's first robot (``gausslite make-scene --trajectory circle``, ``--frames`` frames at
``--size``), copied without its poses (``traj.txt`` left out), so that every run tracks it with the RGB-D odometry
first, as ``gausslite map --dataset DIR`` does with a folder without poses. Three runs per seed, each one
``gausslite map`` process timed from its start to its exit:

- ``budget``: the default schedule (a total time budget, ``--time-budget`` when given) on every frame;
- ``fixed``: the fixed schedule (``--time-budget none``: every frame mapped with ``iters_per_frame`` iterations at
  its size, the full final pass) on the first ``--fixed-frames`` frames only: on every frame it takes tens of
  minutes. Its wall time for every frame is **extrapolated** linearly in frames (``wall × frames / fixed_frames``:
  odometry, mapping, the final pass and scoring all grow with the frames);
- ``budget_subset``: the default schedule on the same first frames with the budget scaled to them: the budget run's
  start-up ``S`` (what it spent before mapping less its odometry: imports, loading, the renderer's first load) plus
  ``(budget − S) × fixed_frames / frames``; the quality against ``fixed`` at the same input.

Every run withholds every ``--withhold``-th frame from the mapper and scores it (``heldout_*``), and scores the ROI of
``--task-id`` (default: the scene's first task; the mapping stays uniform). Reported per run: wall seconds, ATE RMSE of
the odometry's trajectory (``trajectory.tum`` against the rendered poses after rigid alignment; the same odometry in
every run), PSNR and ROI PSNR on the mapped frames and on the withheld ones, keyframes, iterations per keyframe and
the mapping resolution; per configuration the mean ± std over seeds, and the paired gain of ``budget_subset`` over
``fixed``.

Wall-clock figures are only meaningful on an otherwise idle machine: run it alone. Writes ``--out`` (JSON) and the
Markdown table beside it.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

import numpy as np

from bench._results import write_results
from gausslite.cli.cmd_map import DEFAULT_TIME_BUDGET_MIN
from gausslite.datasets.trajectory import ate_rmse, read_tum_trajectory
from gausslite.stats import fmt, gain, mean_std

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
WORK = Path(tempfile.gettempdir()) / "gausslite_map_budget"
#: the configurations of a seed, in the order they run
CONFIGS = ("budget", "budget_subset", "fixed")
#: the scores read from each run's metrics.json
SCORES = ("psnr", "roi_psnr", "heldout_psnr", "heldout_roi_psnr")


def make_input(work: Path, frames: int, size: tuple, trajectory: str) -> tuple[Path, Path]:
    """Render the synthetic scene once (``gausslite make-scene``; kept in ``work`` and reused when its frames, size
    and trajectory match) and lay out its first robot without poses. Returns ``(folder without poses, traj.txt)``.

    Raises:
        RuntimeError: ``make-scene`` failed.
    """
    tag = f"{trajectory}_{frames}_{size[0]}x{size[1]}"
    scene = work / f"scene_{tag}"
    if not (scene / "agent_a" / "traj.txt").is_file():
        cmd = [sys.executable, "-m", "gausslite.cli", "make-scene", "--out", str(scene), "--frames", str(frames),
               "--width", str(size[0]), "--height", str(size[1]), "--trajectory", trajectory, "--agents", "agent_a",
               "--quiet"]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"make-scene failed ({r.returncode}): {r.stderr[-2000:]}")
    bare = work / f"bare_{tag}" / "agent_a"
    if not (bare / "results").exists():
        bare.mkdir(parents=True, exist_ok=True)
        (bare / "results").symlink_to((scene / "agent_a" / "results").resolve(), target_is_directory=True)
        for name in ("cam_params.json", "objects.json", "tasks.json"):
            shutil.copy(scene / name, bare.parent / name)
    return bare, scene / "agent_a" / "traj.txt"


def first_task(folder: Path) -> str:
    """The first task id of the ``tasks.json`` beside ``folder``."""
    return json.loads((folder.parent / "tasks.json").read_text())["tasks"][0]["id"]


def odometry_ate(out: Path, traj_txt: Path, fps: float = 30.0) -> Optional[float]:
    """ATE RMSE (metres) of ``out/trajectory.tum`` against the rendered poses (``traj.txt``: one 4×4 c2w per line,
    frame ``i`` at ``i / fps`` s), frames matched by time; None when no frame matches."""
    ts, est = read_tum_trajectory(out / "trajectory.tum")
    ref = np.loadtxt(traj_txt).reshape(-1, 4, 4)
    idx = np.rint(ts * fps).astype(int)
    ok = (idx >= 0) & (idx < len(ref)) & (np.abs(idx / fps - ts) < 0.5 / fps)
    return ate_rmse(est[ok], ref[idx[ok]]) if ok.any() else None


def run_map(folder: Path, out: Path, args: List[str]) -> tuple[float, dict]:
    """Run ``gausslite map --dataset folder ARGS --out out`` in its own process; returns (wall seconds from start to
    exit, its metrics.json with ``iters_per_frame`` from its config.json). Its output goes to ``out/map.log``.

    Raises:
        RuntimeError: the command failed (the log's tail in the message).
    """
    out.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "gausslite.cli", "map", "--dataset", str(folder), *args, "--out", str(out)]
    t0 = time.perf_counter()
    with open(out / "map.log", "w") as log:
        rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - t0
    if rc != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {rc}: {(out / 'map.log').read_text()[-2000:]}")
    metrics = json.loads((out / "metrics.json").read_text())
    metrics["iters_per_frame"] = json.loads((out / "config.json").read_text())["iters_per_frame"]
    return wall, metrics


def summarise(config: str, wall: float, metrics: dict, ate: Optional[float], frames: int, n_frames: int) -> dict:
    """One run's row: wall seconds (and, for ``fixed``, extrapolated linearly to ``frames``), ATE, scores, what the
    schedule decided."""
    tb = metrics.get("time_budget") or {}
    res = tb.get("resolution", {})
    # the fixed schedule: iters_per_frame on every mapped frame (config.json beside metrics.json)
    iters = tb.get("keyframe_iters", {}).get("mean") if tb else metrics.get("iters_per_frame")
    row = {"config": config, "frames": n_frames, "wall_s": wall,
           "wall_s_all_frames": wall * frames / n_frames if config == "fixed" else (wall if n_frames == frames else None),
           "ate_m": ate, **{k: metrics.get(k) for k in SCORES},
           "n_keyframes": metrics.get("n_keyframes"), "iters_per_keyframe": iters,
           "final_iters": tb.get("final_iters"), "mapping_size": [res.get("mapping_width"), res.get("mapping_height")]
           if res else None, "map_seconds": metrics.get("map_seconds"), "score_seconds": metrics.get("score_seconds"),
           "score_reserve_s": tb.get("score_reserve_s"), "budget_elapsed_s": tb.get("elapsed_s"),
           "spent_before_s": tb.get("spent_before_s"), "odometry_s": metrics.get("odometry_s"),
           "n_gaussians": metrics.get("n_gaussians")}
    return row


def subset_budget(budget_row: dict, minutes: float, sub: int, frames: int) -> float:
    """Seconds of budget for the first ``sub`` of ``frames`` frames: the budget run's start-up ``S`` (what it spent
    before mapping less its odometry) plus ``(minutes × 60 − S) × sub / frames``."""
    start = max(0.0, (budget_row.get("spent_before_s") or 0.0) - (budget_row.get("odometry_s") or 0.0))
    return start + max(0.0, 60.0 * minutes - start) * sub / frames


def run_seed(seed: int, folder: Path, traj: Path, opts: argparse.Namespace) -> List[dict]:
    """The three configurations (:data:`CONFIGS`) of one seed; returns their rows."""
    minutes = opts.time_budget if opts.time_budget is not None else DEFAULT_TIME_BUDGET_MIN
    common = ["--seed", str(seed), "--withhold", str(opts.withhold), "--task-id", opts.task_id, "--no-progress"]
    for kv in opts.overrides:
        common += ["--set", kv]
    sub = min(opts.fixed_frames, opts.frames)
    runs = {"budget": ["--time-budget", f"{minutes:g}"], "budget_subset": ["--max-frames", str(sub)],
            "fixed": ["--max-frames", str(sub), "--time-budget", "none"]}
    rows = []
    for config in CONFIGS:
        out = opts.work / "runs" / f"{config}_seed{seed}"
        print(f"seed {seed}: {config} …", flush=True)
        if config == "budget_subset":
            runs[config] += ["--time-budget", f"{subset_budget(rows[0], minutes, sub, opts.frames) / 60:.4g}"]
        wall, metrics = run_map(folder, out, common + runs[config])
        n = opts.frames if config == "budget" else sub
        rows.append({"seed": seed, **summarise(config, wall, metrics, odometry_ate(out, traj), opts.frames, n)})
        print(f"seed {seed}: {config}: {wall:.1f} s, PSNR {rows[-1]['psnr']}, held-out {rows[-1]['heldout_psnr']}",
              flush=True)
    return rows


def aggregate_rows(rows: List[dict]) -> dict:
    """Per configuration: mean ± std over seeds of the numeric columns; and the paired gain (per seed) of
    ``budget_subset`` over ``fixed`` on every score."""
    keys = ("wall_s", "wall_s_all_frames", "ate_m", *SCORES, "n_keyframes", "iters_per_keyframe", "final_iters")
    out: dict = {}
    for config in CONFIGS:
        sel = [r for r in rows if r["config"] == config]
        out[config] = {k: dict(zip(("mean", "std"), mean_std([r.get(k) for r in sel]))) for k in keys}
    by = {c: {r["seed"]: r for r in rows if r["config"] == c} for c in ("budget_subset", "fixed")}
    seeds = sorted(set(by["budget_subset"]) & set(by["fixed"]))
    out["budget_subset_minus_fixed"] = {k: gain([by["budget_subset"][s].get(k) for s in seeds],
                                                [by["fixed"][s].get(k) for s in seeds]) for k in SCORES}
    return out


def table(agg: dict, opts: argparse.Namespace) -> str:
    """The Markdown table of :func:`aggregate_rows`."""
    sub = min(opts.fixed_frames, opts.frames)
    head = ("| run | frames | wall (s) | wall for all frames (s) | keyframes | iters / keyframe | ATE (cm) | PSNR | "
            "ROI PSNR | held-out PSNR | held-out ROI PSNR |\n|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for config, n in (("budget", opts.frames), ("budget_subset", sub), ("fixed", sub)):
        a = agg[config]

        def cell(k, d=2, scale=1.0):
            m, s = a[k]["mean"], a[k]["std"]
            return fmt(None if m is None else m * scale, None if s is None else s * scale, d)

        extra = " (extrapolated)" if config == "fixed" else ""
        lines.append(f"| {config} | {n} | {cell('wall_s', 0)} | {cell('wall_s_all_frames', 0)}{extra} | "
                     f"{cell('n_keyframes', 0)} | {cell('iters_per_keyframe', 1)} | {cell('ate_m', 2, 100.0)} | "
                     f"{cell('psnr')} | {cell('roi_psnr')} | {cell('heldout_psnr')} | {cell('heldout_roi_psnr')} |")
    g = agg["budget_subset_minus_fixed"]
    lines.append("\nbudget_subset − fixed (paired by seed, dB): " + ", ".join(
        f"{k} {fmt(g[k].get('gain'), g[k].get('gain_std'))}" for k in SCORES))
    return "\n".join(lines)


def parse_args(argv: Optional[List[str]]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m bench.map_budget", description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=250, help="frames of the rendered sequence")
    p.add_argument("--size", default="640x480", help="image size WxH")
    p.add_argument("--trajectory", choices=["circle", "arcs"], default="circle")
    p.add_argument("--seeds", default="0,1,2", help="mapper seeds, comma-separated")
    p.add_argument("--fixed-frames", type=int, default=40,
                   help="frames the fixed schedule (and budget_subset) map; its wall time is extrapolated")
    p.add_argument("--time-budget", type=float, default=None, metavar="MIN",
                   help=f"the budget run's minutes (default: map's default, {DEFAULT_TIME_BUDGET_MIN:g})")
    p.add_argument("--withhold", type=int, default=10, help="withhold every k-th frame from the mapper")
    p.add_argument("--task-id", default=None, help="task whose ROI is scored (default: the scene's first)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="mapper override for every run (map's --set)")
    p.add_argument("--work", type=Path, default=WORK, help="scene and runs (reused)")
    p.add_argument("--out", type=Path, default=RESULTS / "map_budget.json")
    opts = p.parse_args(argv)
    opts.size_wh = tuple(int(v) for v in opts.size.lower().split("x"))
    opts.seed_list = [int(s) for s in opts.seeds.split(",") if s.strip()]
    return opts


def main(argv: Optional[List[str]] = None) -> int:
    opts = parse_args(argv)
    t0 = time.perf_counter()
    folder, traj = make_input(opts.work, opts.frames, opts.size_wh, opts.trajectory)
    opts.task_id = opts.task_id or first_task(folder)
    rows = [r for seed in opts.seed_list for r in run_seed(seed, folder, traj, opts)]
    agg = aggregate_rows(rows)
    result = {"frames": opts.frames, "size": list(opts.size_wh), "trajectory": opts.trajectory,
              "fixed_frames": min(opts.fixed_frames, opts.frames), "withhold": opts.withhold, "task_id": opts.task_id,
              "time_budget_min": opts.time_budget or DEFAULT_TIME_BUDGET_MIN, "seeds": opts.seed_list,
              "overrides": opts.overrides, "extrapolation": "fixed: wall_s × frames / fixed_frames (linear in frames)",
              "summary": agg, "runs": rows}
    minutes = (time.perf_counter() - t0) / 60
    write_results(opts.out, "map_budget", argv, f": {len(opts.seed_list)} seeds, {minutes:.1f} min",
                  table(agg, opts), result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
