"""Benchmark: the user's wait for ``gausslite map``, this tree against another commit on the same machine.

Usage::

    python -m bench.map_time --against 43a6a8d --rounds 2     # bench/results/map_time.*
    python -m bench.map_time --quick                          # a tiny scene once per tree, prints only

The sequence is ``--dataset PATH`` (anything ``gausslite map --dataset`` reads), by default a rendered scene made once
under ``--work`` by this tree's ``gausslite make-scene`` (:data:`SCENE`: robot ``agent_a``, 640×480, 40 frames round
the room, the realistic sensor), mapped at ``--downscale`` (2, as the README maps a robot's bag). Each run is
``python -m gausslite.cli map`` in a fresh process whose ``gausslite`` is the tree's (``PYTHONPATH``, as
:mod:`bench.sim_time`), in the task's mode (``--mode gausslite``, the sequence's first task), every
``--withhold``-th frame withheld and scored (``heldout_*``). Two jobs per tree and round, the trees alternating
(this, that, this, that ...) so that drift of the machine falls on both:

- ``fixed`` (``--time-budget none``): every frame mapped with ``iters_per_frame`` iterations. Its wall seconds are
  the user's wait for a fixed amount of mapping, loading and scoring included;
- ``budget`` (``--time-budget MIN``, default 1 minute): the run fits its keyframes' iterations to the budget (at most
  ``iters_per_frame`` each, so a short sequence may finish early), so the speed shows in what the budget bought:
  keyframes, iterations (``metrics.json``'s ``time_budget``) and the map's quality.

Output: a table (printed) and, in full mode or with ``--out``, JSON through :mod:`bench._results`: ``settings``,
``trees``, ``runs`` (tree, job, ``wall_s``, ``returncode``, and from ``metrics.json`` ``psnr``, ``roi_psnr``,
``heldout_psnr``, ``heldout_roi_psnr``, ``n_gaussians``, ``keyframes``, ``iters``), ``summary`` (per tree and job
the medians) and ``ratio`` (the fixed job's wall seconds, that / this: > 1 means this tree is faster). Exits 1 when a
run failed, after writing.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results" / "map_time.json"
#: ``gausslite make-scene`` arguments of the default sequence (``--out`` added), and of ``--quick``'s
SCENE = ["--frames", "40", "--width", "640", "--height", "480", "--trajectory", "circle", "--sensor-noise",
         "realistic", "--agents", "agent_a"]
QUICK_SCENE = ["--frames", "6", "--width", "64", "--height", "48", "--trajectory", "circle", "--agents", "agent_a"]
#: what ``--quick`` adds to every map run (fewer seeds on tiny frames), and to the fixed schedule's (a few iterations)
QUICK_SET = ["--seeds-per-frame", "150"]
QUICK_FIXED = ["--iters", "3", "--set", "warmup_iters=1"]
#: the metrics.json figures a run keeps (None where the tree's map did not write one)
METRICS = ("psnr", "roi_psnr", "heldout_psnr", "heldout_roi_psnr", "n_gaussians")


def make_sequence(work: Path, quick: bool) -> Path:
    """The default sequence (:data:`SCENE`, or :data:`QUICK_SCENE`), made under ``work`` with this tree's
    ``gausslite make-scene`` unless it is there; returns the robot's folder. Raises CalledProcessError when the
    scene cannot be made."""
    args = QUICK_SCENE if quick else SCENE
    root = work / ("scene_" + "_".join(a.lstrip("-").replace("_", "") for a in args))
    robot = root / "agent_a"
    if not (robot / "tasks.json").is_file():
        subprocess.run([sys.executable, "-m", "gausslite.cli", "make-scene", "--out", str(root), *args], check=True,
                       capture_output=True, text=True, timeout=1800, cwd=REPO)
    return robot


def map_command(dataset: Path, out: Path, job: str, downscale: float, budget_min: float, withhold: int,
                quick: bool) -> list[str]:
    """The ``gausslite map`` command line of ``job`` (``fixed`` or ``budget``)."""
    cmd = [sys.executable, "-m", "gausslite.cli", "map", "--dataset", str(dataset), "--downscale", f"{downscale:g}",
           "--mode", "gausslite", "--withhold", str(withhold), "--no-progress", "--out", str(out),
           "--time-budget", "none" if job == "fixed" else f"{budget_min:g}"]
    if quick:
        cmd += QUICK_SET + (QUICK_FIXED if job == "fixed" else [])
    return cmd


def run_map(tree: Path, shim: Path, cmd: list[str], out: Path, timeout_s: float) -> dict:
    """One timed ``gausslite map`` run with ``tree``'s code: wall seconds, return code, the :data:`METRICS` of its
    ``metrics.json`` and, under a time budget, its keyframes and total iterations (the end of stderr when it
    failed)."""
    from bench.sim_time import tree_env

    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=out.parent, env=tree_env(tree, shim), capture_output=True, text=True,
                          timeout=timeout_s, check=False)
    res: dict = {"wall_s": time.perf_counter() - t0, "returncode": proc.returncode}
    if proc.returncode != 0:
        res["stderr_tail"] = proc.stderr[-2000:]
    path = out / "metrics.json"
    if path.is_file():
        m = json.loads(path.read_text())
        res.update({k: m.get(k) for k in METRICS})
        tb = m.get("time_budget") or {}
        res["keyframes"] = tb.get("n_keyframes", m.get("n_frames"))
        res["iters"] = (tb.get("keyframe_iters") or {}).get("total")
    return res


def _median(xs: list) -> Optional[float]:
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def summarise(runs: list[dict], trees: list[str], jobs: list[str]) -> dict:
    """Per tree and job the medians of the successful runs' figures (``wall_s``, :data:`METRICS`, ``keyframes``,
    ``iters``) and their count."""
    out: dict = {}
    for t in trees:
        for j in jobs:
            ok = [r for r in runs if r["tree"] == t and r["job"] == j and r["returncode"] == 0]
            out.setdefault(t, {})[j] = {"runs": len(ok), **{k: _median([r.get(k) for r in ok])
                                                            for k in ("wall_s", *METRICS, "keyframes", "iters")}}
    return out


def _f(x: Optional[float], nd: int = 2) -> str:
    return "–" if x is None else f"{x:.{nd}f}"


def table(result: dict) -> str:
    """Markdown: per tree the fixed schedule's wall seconds (median and each run), its quality, and what the time
    budget bought (keyframes, iterations, quality); the fixed job's ratio that / this."""
    budget = result["settings"]["budget_min"]
    lines = [f"| tree | commit | fixed: wall s (median) | each run s | fixed: PSNR / ROI PSNR | fixed: held-out "
             f"PSNR / ROI PSNR | {budget:g} min budget: wall s | keyframes | iterations | held-out PSNR / ROI PSNR | "
             f"that / this (fixed) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for t, s in result["summary"].items():
        f, b = s["fixed"], s["budget"]
        each = ", ".join(f"{r['wall_s']:.0f}" + ("" if r["returncode"] == 0 else " (failed)")
                         for r in result["runs"] if r["tree"] == t and r["job"] == "fixed")
        ratio = result.get("ratio") if t == "this" else None
        lines.append(f"| {t} | {result['trees'][t]['commit'][:7]} | {_f(f['wall_s'], 1)} | {each} | "
                     f"{_f(f['psnr'])} / {_f(f['roi_psnr'])} | {_f(f['heldout_psnr'])} / {_f(f['heldout_roi_psnr'])} | "
                     f"{_f(b['wall_s'], 1)} | {_f(b['keyframes'], 0)} | {_f(b['iters'], 0)} | "
                     f"{_f(b['heldout_psnr'])} / {_f(b['heldout_roi_psnr'])} | {_f(ratio)} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    """Run the benchmark (module docstring); returns the result dict."""
    ap = argparse.ArgumentParser(prog="python -m bench.map_time", description=__doc__.splitlines()[0])
    ap.add_argument("--against", metavar="COMMIT", help="also time COMMIT's map (a git worktree), A B per round")
    ap.add_argument("--rounds", type=int, default=1, help="runs of each job per tree")
    ap.add_argument("--dataset", type=Path, default=None, help="the sequence (default: the rendered scene above)")
    ap.add_argument("--downscale", type=float, default=2.0, help="gausslite map --downscale (default 2)")
    ap.add_argument("--budget", type=float, default=None, help="the budget job's minutes (default 1; quick 0.25)")
    ap.add_argument("--withhold", type=int, default=10, help="withhold every K-th frame and score it (default 10)")
    ap.add_argument("--quick", action="store_true", help="a tiny scene; prints only unless --out is given")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "gausslite-map-time-work",
                    help="where the default sequence is made once")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds one run may take")
    ap.add_argument("--out", type=Path, default=None, help=f"JSON output (default {RESULTS} unless --quick)")
    args = ap.parse_args(argv)
    from tqdm import tqdm

    from bench._results import publish
    from bench.sim_time import raise_if_failed, trees_and_shims

    budget = args.budget if args.budget is not None else (0.25 if args.quick else 1.0)
    downscale = 1.0 if args.quick and args.dataset is None else args.downscale
    dataset = args.dataset or make_sequence(args.work, args.quick)
    t_start = time.perf_counter()
    runs: list[dict] = []
    jobs = ["fixed", "budget"]
    with trees_and_shims(args.against, "gausslite-map-time-") as (trees, shims, tmp, info):
        plan = [(t, j) for _ in range(args.rounds) for j in jobs for t in trees]
        for k, (t, j) in enumerate(tqdm(plan, desc="bench.map_time", unit="run")):
            out = tmp / f"map_{k}_{t}_{j}"
            cmd = map_command(dataset, out, j, downscale, budget, args.withhold, args.quick)
            res = {"tree": t, "job": j, **run_map(trees[t], shims[t], cmd, out, args.timeout)}
            runs.append(res)
            tqdm.write(f"{t:<5} {j:<6} run {k}: {res['wall_s']:.1f} s (exit {res['returncode']}), "
                       f"PSNR {_f(res.get('psnr'))}, iterations {res.get('iters')}")
    summary = summarise(runs, list(trees), jobs)
    result = {"settings": {"quick": args.quick, "rounds": args.rounds, "dataset": str(dataset),
                           "scene": None if args.dataset else (QUICK_SCENE if args.quick else SCENE),
                           "downscale": downscale, "budget_min": budget, "withhold": args.withhold,
                           "command": map_command(Path("DATASET"), Path("OUT"), "fixed", downscale, budget,
                                                  args.withhold, args.quick)[1:]},
              "trees": info, "runs": runs, "summary": summary, "wall_s": time.perf_counter() - t_start}
    fixed = {t: summary[t]["fixed"]["wall_s"] for t in trees}
    if "that" in trees and fixed["this"] and fixed["that"]:
        result["ratio"] = fixed["that"] / fixed["this"]
    publish(args.out if args.out is not None else (None if args.quick else RESULTS), "map_time", argv, table(result),
            result)
    raise_if_failed(runs, "map run(s)")
    return result


if __name__ == "__main__":
    main()
