"""Benchmark: the user's wait for the main job, ``gausslite sim``, this tree against another commit on the same machine.

Usage::

    python -m bench.sim_time --against 43a6a8d --rounds 2     # the default sim, A B A B: bench/results/sim_time.*
    python -m bench.sim_time --quick                          # a tiny sim once per tree, prints only

Each run is ``python -m gausslite.cli sim --out DIR [--set ...]`` in a fresh process whose ``gausslite`` and
``gausslite_services`` are the tree's (``PYTHONPATH``: the tree, and a folder that links ``gausslite_services`` to the
tree's ``services``), so the sim's own service processes (``python -m gausslite.cli serve ...``) import that tree too.
The trees alternate run by run (this, that, this, that ...) so that drift of the machine falls on both. Timed: the
wall seconds of the whole command, the embedded scene's generation included (each run writes a fresh folder), and
the import of the agent service's module in a fresh process (``python -c "import gausslite_services.agent.server"``,
the faster of two:
what a service process pays before its own start-up; the libraries that module imports lazily are not in it). Each
run records the top-level keys of the sim's ``report.json`` (``report_keys``: that the sim wrote its report) and,
when the report has them, the sim's stages (``stages_s``: scene generation, services started, missions replayed and
finished, fused maps scored, the ROI cover diagnosis) and ``outside_s``, the wall time outside them (the command's
imports, the report, the services' shutdown).

Output: a table (printed) and, in full mode or with ``--out``, JSON through :mod:`bench._results`: ``settings``,
``trees`` and ``runs`` (tree, ``wall_s``, ``import_s``, ``returncode``), ``summary`` (per tree the median wall and
import seconds) and ``ratio`` (that / this: > 1 means this tree is faster).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Iterator, Optional

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results" / "sim_time.json"
#: the tiny sim of ``--quick`` (as tests/services/test_sim.py runs it)
QUICK_SET = ["sim.scene.width=64", "sim.scene.height=48", "sim.scene.frames=3", "agent.downscale=1",
             "agent.push.every=2", "mapper.iters_per_frame=3", "mapper.warmup_iters=1",
             "mapper.seeding.seeds_per_frame=150", "sim.fuse.refine_iters=3", "agent.share.finetune_iters=20",
             "agent.refine_views.min_roi_px=1", "agent.refine_views.budget_ratio=8", "fusion.team_map.refine_iters=3",
             "fusion.team_map.min_interval_s=0"]


def tree_env(tree: Path, shim: Path) -> dict:
    """The environment that makes a process import ``tree``'s ``gausslite`` and ``gausslite_services`` (``shim``: a
    folder where ``gausslite_services`` links to ``tree / "services"``)."""
    link = shim / "gausslite_services"
    if not link.exists():
        link.symlink_to(Path(tree).resolve() / "services", target_is_directory=True)
    return dict(os.environ, PYTHONPATH=f"{Path(tree).resolve()}{os.pathsep}{shim}")


def raise_if_failed(runs: list, what: str) -> None:
    """Raise SystemExit when a timed run of ``runs`` (each with its process's ``returncode``) exited non-zero, after
    the result is written: ``"<n> <what> failed; the first: <its stderr tail>"``."""
    failed = [r for r in runs if r["returncode"] != 0]
    if failed:
        raise SystemExit(f"{len(failed)} {what} failed; the first: {failed[0].get('stderr_tail', '')}")


@contextmanager
def trees_and_shims(against: Optional[str], prefix: str) -> Iterator[tuple[dict, dict, Path, dict]]:
    """This tree and, with ``against``, a git worktree of that commit (:func:`bench.throughput.worktree`), each with a
    shim folder for :func:`tree_env`, under a temporary folder. Yields ``(trees, shims, tmp, info)``: ``"this"`` /
    ``"that"`` → tree root, → shim folder, the temporary folder the runs write under, and the result's ``trees``
    block (each tree's commit, and the ref asked for)."""
    from bench.throughput import git, worktree

    with (worktree(against) if against else nullcontext()) as other, \
            tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        trees = {"this": REPO} if other is None else {"this": REPO, "that": other[0]}
        shims = {t: Path(tmp) / f"shim_{t}" for t in trees}
        for s in shims.values():
            s.mkdir()
        info = {"this": {"commit": git("rev-parse", "HEAD")}} | (
            {} if other is None else {"that": {"ref": against, "commit": other[1]}})
        yield trees, shims, Path(tmp), info


def run_sim(tree: Path, out: Path, overrides: list, timeout_s: float, shim: Path) -> dict:
    """One timed ``gausslite sim --out out`` with ``tree``'s code: wall seconds, return code, the report's top-level
    keys (and the end of stderr when it failed)."""
    env = tree_env(tree, shim)
    cmd = [sys.executable, "-m", "gausslite.cli", "sim", "--out", str(out)]
    for o in overrides:
        cmd += ["--set", o]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=out.parent, env=env, capture_output=True, text=True, timeout=timeout_s, check=False)
    wall = time.perf_counter() - t0
    res = {"wall_s": wall, "returncode": proc.returncode}
    if proc.returncode != 0:
        res["stderr_tail"] = proc.stderr[-2000:]
    rep = out / "report.json"
    if rep.is_file():
        data = json.loads(rep.read_text())
        res["report_keys"] = sorted(data)[:40]
        if data.get("stages_s"):  # where the time went (a tree whose sim reports its stages)
            res["stages_s"] = data["stages_s"]
            res["outside_s"] = wall - sum(data["stages_s"].values())
    return res


def import_seconds(tree: Path, shim: Path, module: str = "gausslite_services.agent.server") -> float:
    """Seconds for a fresh process to import ``module`` with ``tree``'s code (the start-up of a service process)."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", f"import {module}"], env=tree_env(tree, shim), capture_output=True,
                   check=True, timeout=600)
    return time.perf_counter() - t0


def _median(xs: list) -> Optional[float]:
    return statistics.median(xs) if xs else None


def table(result: dict) -> str:
    """Markdown: per tree the median wall seconds of the sim and of a service's imports, and the ratio; then, for
    the runs whose report has them, the stages' seconds (``stages_s``) and the rest of the wall time (the command's
    imports before the sim starts, the report, the services' shutdown)."""
    lines = ["| tree | commit | sims | sim wall s (median) | each run s | service import s | that / this |",
             "|---|---|---|---|---|---|---|"]
    for t, s in result["summary"].items():
        runs = [r for r in result["runs"] if r["tree"] == t]
        each = ", ".join(f"{r['wall_s']:.0f}" + ("" if r["returncode"] == 0 else " (failed)") for r in runs)
        ratio = result.get("ratio") if t == "this" else None
        lines.append(f"| {t} | {result['trees'][t]['commit'][:7]} | {len(runs)} | "
                     f"{s['wall_s']:.1f} | {each} | {s['import_s']:.2f} | "
                     f"{'–' if ratio is None else f'{ratio:.2f}'} |")
    staged = [r for r in result["runs"] if r.get("stages_s")]
    if staged:
        stages = list(dict.fromkeys(n for r in staged for n in r["stages_s"]))  # in the order the sim ran them
        lines += ["", "| tree | run | " + " | ".join(f"{k} s" for k in stages) + " | imports, report, shutdown s |",
                  "|---|---|" + "---|" * (len(stages) + 1)]
        for k, r in enumerate(staged):
            cells = [f"{r['stages_s'][n]:.1f}" if n in r["stages_s"] else "–" for n in stages]
            lines.append(f"| {r['tree']} | {k} | " + " | ".join(cells) + f" | {r['outside_s']:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> dict:
    """Run the benchmark (module docstring); returns the result dict."""
    ap = argparse.ArgumentParser(prog="python -m bench.sim_time", description=__doc__.splitlines()[0])
    ap.add_argument("--against", metavar="COMMIT", help="also time COMMIT's sim (a git worktree), A B per round")
    ap.add_argument("--rounds", type=int, default=1, help="sims per tree")
    ap.add_argument("--quick", action="store_true", help="the tiny sim; prints only unless --out is given")
    ap.add_argument("--timeout", type=float, default=1800.0, help="seconds one sim may take")
    ap.add_argument("--out", type=Path, default=None, help=f"JSON output (default {RESULTS} unless --quick)")
    args = ap.parse_args(argv)
    from tqdm import tqdm

    from bench._results import publish

    overrides = QUICK_SET if args.quick else []
    t_start = time.perf_counter()
    runs: list[dict] = []
    with trees_and_shims(args.against, "gausslite-sim-time-") as (trees, shims, tmp, info):
        # twice per tree, the faster kept: the first import of a tree reads its files cold
        imports = {t: min(import_seconds(trees[t], shims[t]) for _ in range(2)) for t in trees}
        jobs = [t for _ in range(args.rounds) for t in trees]
        for k, t in enumerate(tqdm(jobs, desc="bench.sim_time", unit="sim")):
            out = tmp / f"sim_{k}_{t}"
            res = run_sim(trees[t], out, overrides, args.timeout, shims[t])
            res["tree"] = t
            runs.append(res)
            tqdm.write(f"{t:<5} sim {k}: {res['wall_s']:.1f} s (exit {res['returncode']})")
    summary = {t: {"wall_s": _median([r["wall_s"] for r in runs if r["tree"] == t and r["returncode"] == 0]) or
                   float("nan"), "import_s": imports[t]} for t in trees}
    result = {"settings": {"quick": args.quick, "rounds": args.rounds, "overrides": overrides},
              "trees": info, "runs": runs, "summary": summary, "wall_s": time.perf_counter() - t_start}
    if "that" in trees:
        result["ratio"] = summary["that"]["wall_s"] / summary["this"]["wall_s"]
    md = table(result)
    publish(args.out if args.out is not None else (None if args.quick else RESULTS), "sim_time", argv, md, result)
    raise_if_failed(runs, "sim(s)")
    return result


if __name__ == "__main__":
    main()
