"""The two-agent sim over several seeds: the sharing table (share, bytes, own vs fused per task), mean ± std.

    python -m bench.sim_seeds [--scenes room0,synthetic] [--seeds 3] [--set agent.share.refresh=0.1 ...]

Runs ``gausslite sim`` once per scene and seed (``--set mapper.seed=S``; the default settings
otherwise, plus any ``--set``), one after the other, each into
``runs/sim_seeds/<scene>_seed<S>``, and summarises the reports per agent: ``share_pct``,
``bytes_per_gaussian``, ``upload_ratio`` (total upload / final subset), the agent's own map
(``own_context``: ROI PSNR with ``roi_render: context``), the fused ROI PSNR of its task for ``concat``,
``vote`` and ``refine``, and ``vote − own``, ``refine − own``. Every field is the mean over seeds with its
standard deviation and the per-seed values.

Scenes: ``room0`` = ``--dataset $GAUSSLITE_SHARED/datasets/Replica_room0/room0 --downscale 4``; ``synthetic`` = the
embedded default scene. Writes ``bench/results/sim_seeds.json`` and ``.md`` (``--out``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from tqdm import tqdm

from bench._results import write_results
from gausslite.stats import fmt, mean_std

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
RESULTS = REPO / "bench" / "results"
FIELDS = ("share_pct", "bytes_per_gaussian", "upload_ratio", "own_context", "concat", "vote", "refine",
          "vote_minus_own", "refine_minus_own")


def scene_args(scene: str) -> list[str]:
    """``gausslite sim`` arguments of a bench scene."""
    if scene == "room0":
        path = SHARED / "datasets" / "Replica_room0" / "room0"
        if not path.is_dir():
            raise FileNotFoundError(f"{path} not found (set GAUSSLITE_SHARED)")
        return ["--dataset", str(path), "--downscale", "4"]
    if scene == "synthetic":
        return []
    raise ValueError(f"unknown scene {scene!r} (room0, synthetic)")


def agent_rows(report: dict) -> dict:
    """Per agent (``"<id> <task>"``) the summary fields of one sim report."""
    out = {}
    for a in report["agents"]:
        task = a["task"]
        fused = {k: report["fused"][k]["roi_psnr_per_task"].get(task) for k in ("concat", "vote", "refine")}
        own = a.get("own_roi_psnr_context")
        row = {"share_pct": a["share_pct"], "bytes_per_gaussian": a["bytes_per_gaussian"],
               "upload_ratio": a["upload_ratio"], "own_context": own, **fused,
               "vote_minus_own": None if own is None or fused["vote"] is None else fused["vote"] - own,
               "refine_minus_own": None if own is None or fused["refine"] is None else fused["refine"] - own}
        out[f"{a['id']} {task}"] = row
    return out


def summarise(per_seed: list[dict]) -> dict:
    """Mean, std and per-seed values of every field, per agent."""
    out = {}
    for key in per_seed[0]:
        blk = {}
        for f in FIELDS:
            vals = [s[key][f] for s in per_seed if key in s and s[key].get(f) is not None]
            blk[f], blk[f + "_std"] = mean_std(vals) if vals else (None, None)
            blk[f + "_per_seed"] = vals
        out[key] = blk
    return out


def table(summary: dict) -> str:
    """Markdown table of a summary ({scene: {agent: block}})."""
    lines = ["| scene | agent, task | share of map [%] | B / shared Gaussian | total upload / final subset | own map "
             "(context) | fused concat → vote → refine | vote − own | refine − own |",
             "|---|---|---|---|---|---|---|---|---|"]
    for scene, agents in summary.items():
        for key, b in agents.items():
            f = lambda k, d=2: fmt(b[k], b[k + "_std"], d)  # noqa: E731
            per = ", ".join(f"{v:+.2f}" for v in b["vote_minus_own_per_seed"])
            lines.append(f"| {scene} | {key} | {f('share_pct')} | {f('bytes_per_gaussian')} | {f('upload_ratio')} | "
                         f"{f('own_context')} | {b['concat']:.2f} → {f('vote')} → {f('refine')} | "
                         f"{f('vote_minus_own')} ({per}) | {f('refine_minus_own')} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.sim_seeds", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="room0,synthetic")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="passed to gausslite sim")
    ap.add_argument("--work", type=Path, default=REPO / "runs" / "sim_seeds")
    ap.add_argument("--out", type=Path, default=RESULTS / "sim_seeds.json")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    scenes = [s for s in args.scenes.split(",") if s]
    jobs = [(sc, s) for sc in scenes for s in range(args.seeds)]
    reports: dict = {sc: [] for sc in scenes}
    for sc, s in tqdm(jobs, desc="bench.sim_seeds", unit="sim"):
        out = args.work / f"{sc}_seed{s}"
        shutil.rmtree(out, ignore_errors=True)  # a fresh fusion store and agent data per run
        cmd = [sys.executable, "-m", "gausslite.cli", "sim", *scene_args(sc), "--set", f"mapper.seed={s}",
               *[x for kv in args.set for x in ("--set", kv)], "--out", str(out)]
        r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-3000:]}")
        reports[sc].append(json.loads((out / "report.json").read_text()))
    summary = {sc: summarise([agent_rows(rep) for rep in reps]) for sc, reps in reports.items()}
    result = {"scenes": scenes, "seeds": list(range(args.seeds)), "set": args.set, "summary": summary,
              "reports": {sc: [str(args.work / f"{sc}_seed{s}" / "report.json") for s in range(args.seeds)]
                          for sc in scenes},
              "wall_s": time.perf_counter() - t0}
    write_results(args.out, "sim_seeds", argv, f": {args.seeds} seeds, {result['wall_s'] / 60:.1f} min",
                  table(summary), result)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
