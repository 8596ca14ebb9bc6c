"""The one team map over several runs of the two-agent simulation: every fused map against each robot's own map under
every scoring protocol, the team map served while the team maps, and the bytes of the views sent for the refinement.

    python -m bench.team_map [--realtime] [--runs 3] [--scene synthetic] [--set KEY=VALUE ...] [--out PATH]
    python -m bench.team_map --summarise runs/a/report.json runs/b/report.json ...   # reports already made

Runs ``gausslite sim`` ``--runs`` times one after the other (seed ``s`` → ``--set mapper.seed=s``; ``--realtime`` adds
``--realtime``: live, under the keyframe time budget, so nothing else may run beside it), each into
``<work>/<scene>[_rt]_seed<s>``, and summarises the reports (docs/sharing.md#which-map-to-use-when):

- ``fused``: for ``vote``, ``for_robot``, ``refine`` and ``team_map`` (the served team map once current), per task and
  protocol (``sensor``, ``keyframes``, ``novel``: at the pose the robot's own map predicts, ``tracked``,
  ``novel-tracked``, and ``tracked@own``, ``novel-tracked@own``: at the views the robot's own map was tracked at), the
  fused map's ROI PSNR minus the robot's own map's under the same protocol: the mean of the paired per-frame
  differences over runs × frames with its 95 % interval, and the per-run values' mean ± std (older reports, whose
  ``novel`` was tracked, are read as ``novel-tracked``);
- ``refine_record``: the refinement's held-out record per run (views trained / held out, iterations run, early stop,
  rollback), for ``refine`` and ``team_map``;
- ``served``: per run, the served team map against each robot's own map at every step of the timeline once the
  served map holds both robots' subsets (the worst step's paired per-frame gain, and how many steps);
- ``views``: per agent, the bytes of the views sent for the refinement over its final subset's bytes, views sent and
  left unsent.

Writes ``bench/results/team_map_sim.json`` (``--realtime``: ``team_map_sim_rt.json``) and ``.md`` (``--out``), and per
task an image of the first run's team vote above its served team map (``team_map_sim_<task>.png``).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

from tqdm import tqdm

from bench._results import DATASETS, write_results
from gausslite.evaluation import PROTOCOL_QUESTIONS, current_protocols
from gausslite.stats import fmt, fmt_gain, mean_std, paired_gain

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
KEYS = ("vote", "for_robot", "with_own", "refine", "team_map")
PROTOCOLS = ("sensor", "keyframes", "novel", "tracked", "novel-tracked", "tracked@own", "novel-tracked@own")


def scene_args(scene: str) -> list[str]:
    """``gausslite sim`` arguments of a bench scene: ``room0`` (Replica room0 from :data:`bench._results.DATASETS` at
    ``--downscale 4``) or ``synthetic`` (the embedded scene)."""
    if scene == "room0":
        path = DATASETS / "Replica_room0" / "room0"
        if not path.is_dir():
            raise FileNotFoundError(f"{path} not found (set GAUSSLITE_SHARED)")
        return ["--dataset", str(path), "--downscale", "4"]
    if scene == "synthetic":
        return []
    raise ValueError(f"unknown scene {scene!r} (room0, synthetic)")


def _own_frames(report: dict) -> Dict[str, Dict[str, dict]]:
    """task → protocol → frame id → the robot's own map's ROI PSNR (dB), where the report has per-frame figures."""
    out: dict = {}
    for a in report.get("agents") or []:
        for q, v in current_protocols(a.get("protocols")).items():
            if (v or {}).get("roi_psnr_per_frame") is not None:
                out.setdefault(a["task"], {})[q] = v["roi_psnr_per_frame"]
    return out


def fused_rows(report: dict) -> Dict[str, Dict[str, Dict[str, dict]]]:
    """key → task → protocol → ``{"minus_own": fused − own (dB, the report's figure), "fused": frame id → dB,
    "own": frame id → dB}`` of one report (per-frame figures None where the report has none: an older report, whose
    ``novel`` / ``novel@own`` — then tracked against the map — are read as ``novel-tracked`` /
    ``novel-tracked@own``)."""
    own = _own_frames(report)
    out: dict = {}
    for k in KEYS:
        f = (report.get("fused") or {}).get(k)
        if not f:
            continue
        for q, per in current_protocols(f.get("protocols")).items():
            for task, v in per.items():
                out.setdefault(k, {}).setdefault(task, {})[q] = {
                    "minus_own": v.get("minus_own"), "fused": v.get("roi_psnr_per_frame"),
                    "own": own.get(task, {}).get(q.split("@")[0])}
    return out


def served_steps(report: dict) -> Dict[str, dict]:
    """task → {"worst": the timeline step whose served team map, holding every robot's subset, is furthest below the
    robot's own map: its paired per-frame gain served − own (:func:`gausslite.stats.paired_gain`, the own map's
    ``sensor`` figures, every frame as the timeline scores the fused maps; an older report without per-frame figures:
    the difference of the means, ``{"gain": dB}``), "steps": their number}."""
    agents = report["agents"]
    own_all = {a["task"]: a.get("roi_psnr_all_frames") or a.get("roi_psnr") for a in agents}
    own_frames = {t: q.get("sensor") for t, q in _own_frames(report).items()}
    ids = {a["id"] for a in agents}
    out = {}
    for task, o in own_all.items():
        gains = []
        for e in report.get("fused_timeline") or []:
            s = e.get("served")
            if not s or not set(s["versions"]) >= ids:
                continue
            frames = (s.get("roi_psnr_per_frame") or {}).get(task)
            if frames is not None and own_frames.get(task) is not None:
                g = paired_gain(frames, own_frames[task])
            elif s["roi_psnr"].get(task) is not None and o is not None:
                g = {"gain": s["roi_psnr"][task] - o}
            else:
                continue
            if g.get("gain") is not None:
                gains.append(g)
        out[task] = {"worst": min(gains, key=lambda g: g["gain"]) if gains else None, "steps": len(gains)}
    return out


def view_rows(report: dict) -> Dict[str, dict]:
    """agent id → its refinement views: ``ratio`` (view bytes / final subset bytes), ``view_bytes``, ``views_sent``,
    ``views_unsent``, ``final_subset_bytes``."""
    return {a["id"]: {"ratio": a.get("view_ratio"), "view_bytes": a.get("view_bytes"),
                      "views_sent": a.get("views_sent"), "views_unsent": a.get("views_unsent"),
                      "final_subset_bytes": a.get("final_subset_bytes")} for a in report["agents"]}


def _stat(vals: List[Optional[float]]) -> dict:
    got = [v for v in vals if v is not None]
    m, s = mean_std(got) if got else (None, None)
    return {"mean": m, "std": s, "per_run": vals}


def _gain(cells: List[Optional[dict]]) -> dict:
    """One map, task and protocol over runs: the paired per-frame gain over runs × frames (``gain``, with its 95 %
    interval; None when a run lacks per-frame figures) beside the per-run figures' mean ± std (``mean``, ``std``,
    ``per_run``)."""
    out = _stat([(c or {}).get("minus_own") for c in cells])
    pairs = [(c["fused"], c["own"]) for c in cells if c and c.get("fused") is not None and c.get("own") is not None]
    out["gain"] = (paired_gain([f for f, _ in pairs], [o for _, o in pairs])
                   if pairs and len(pairs) == sum(1 for c in cells if c) else None)
    return out


def summarise(reports: List[dict]) -> dict:
    """The summary of several reports of the same configuration (module docstring)."""
    rows = [fused_rows(r) for r in reports]
    fused: dict = {}
    for k in KEYS:
        tasks = sorted({t for r in rows for t in r.get(k, {})})
        for t in tasks:
            for q in PROTOCOLS:
                fused.setdefault(k, {}).setdefault(t, {})[q] = _gain([r.get(k, {}).get(t, {}).get(q) for r in rows])
    served = [served_steps(r) for r in reports]
    tasks = sorted({t for s in served for t in s})
    views = [view_rows(r) for r in reports]
    agents = sorted({a for v in views for a in v})
    return {"runs": len(reports), "fused": fused,
            "refine_record": {k: [((r.get("fused") or {}).get(k) or {}).get("refine_record") for r in reports]
                              for k in ("refine", "team_map")},
            "served": {t: {"worst": _stat([((s.get(t) or {}).get("worst") or {}).get("gain") for s in served]),
                           "worst_gain": [(s.get(t) or {}).get("worst") for s in served],
                           "steps": [s.get(t, {}).get("steps") for s in served]} for t in tasks},
            "views": {a: {f: _stat([v.get(a, {}).get(f) for v in views])
                          for f in ("ratio", "view_bytes", "views_sent", "views_unsent")} for a in agents},
            "seconds": _stat([r.get("seconds") for r in reports])}


def table(summary: dict) -> str:
    """Markdown tables of a summary: fused − own per map, task and protocol (the paired per-frame gain over runs ×
    frames [95 % interval], and the per-run mean ± std); the served timeline; the views."""
    f = lambda b: fmt(b["mean"], b["std"], 2) if b["mean"] is not None else "–"  # noqa: E731

    def cell(b):
        return (fmt_gain(b.get("gain")) + f" (runs {f(b)})") if b.get("gain") else f(b)

    lines = ["Fused map − the robot's own map under each protocol (dB): the mean of the paired per-frame differences "
             "over runs × frames [95 % interval], and in brackets the per-run differences' mean ± std. What each "
             "protocol answers: " + "; ".join(f"`{q}`: {PROTOCOL_QUESTIONS[q]}" for q in PROTOCOLS
                                              if q in PROTOCOL_QUESTIONS)
             + "; `@own`: at the pose the robot tracked against its own map.", "",
             "| map | task | " + " | ".join(PROTOCOLS) + " |", "|---|---|" + "---|" * len(PROTOCOLS)]
    for k, per in summary["fused"].items():
        for t, qs in per.items():
            lines.append(f"| {k} | {t} | " + " | ".join(cell(qs[q]) for q in PROTOCOLS) + " |")
    lines += ["", "| task | served team map − own, worst step once it holds both subsets (paired gain per run) | "
              "over runs | steps |", "|---|---|---|---|"]
    for t, b in summary["served"].items():
        per_run = ", ".join("–" if not g else fmt_gain(g) if "n" in g else f"{g['gain']:+.2f}" for g in b["worst_gain"])
        lines.append(f"| {t} | {per_run} | {f(b['worst'])} | {b['steps']} |")
    lines += ["", "| agent | view bytes / subset bytes | view bytes | views sent | views unsent |", "|---|---|---|---|---|"]
    for a, b in summary["views"].items():
        lines.append(f"| {a} | {f(b['ratio'])} | {f(b['view_bytes'])} | {f(b['views_sent'])} | "
                     f"{f(b['views_unsent'])} |")
    return "\n".join(lines)


def before_after(report_path: Path, out: Path) -> List[str]:
    """Write, per task, ``<out stem>_<task>.png``: the first run's render of the team vote (top) above the served team
    map (bottom), each beside the frame and its ROI (the sim's ``renders/vote_*`` and ``renders/team_map_*``).
    Returns the images written (none when the report has no such renders)."""
    # lazy: OpenCV, only for the images
    import cv2
    import numpy as np

    rep = json.loads(report_path.read_text())
    paths = {(r["fused"], r["task"]): report_path.parent / r["path"] for r in rep.get("renders") or []}
    written = []
    for a in rep["agents"]:
        pair = [paths.get((k, a["task"])) for k in ("vote", "team_map")]
        if not all(p is not None and p.is_file() for p in pair):
            continue
        rows = []
        for p, label in zip(pair, ("team vote", "served team map (refined in the background)")):
            img = cv2.imread(str(p))
            bar = np.full((22, img.shape[1], 3), 255, np.uint8)
            cv2.putText(bar, label, (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
            rows += [bar, img]
        dest = out.with_name(f"{out.stem}_{a['task']}.png")
        dest.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(dest), np.vstack(rows)):
            raise OSError(f"could not write {dest}")
        written.append(str(dest))
    return written


def run_sims(scene: str, runs: int, realtime: bool, sets: List[str], work: Path) -> List[Path]:
    """Run ``gausslite sim`` ``runs`` times, one after the other; returns the report paths."""
    paths = []
    for s in tqdm(range(runs), desc="bench.team_map", unit="sim"):
        out = work / f"{scene}{'_rt' if realtime else ''}_seed{s}"
        shutil.rmtree(out, ignore_errors=True)  # a fresh fusion store and agent data per run
        cmd = [sys.executable, "-m", "gausslite.cli", "sim", *scene_args(scene), *(["--realtime"] if realtime else []),
               "--set", f"mapper.seed={s}",
               "--set", "agent.scoring.track_fused=true",  # the table's tracked columns: fitted to each fused map
               *[x for kv in sets for x in ("--set", kv)], "--out", str(out)]
        r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-3000:]}")
        paths.append(out / "report.json")
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.team_map", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="synthetic", help="synthetic (the embedded default) or room0")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--realtime", action="store_true", help="gausslite sim --realtime (live; run it alone)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="passed to gausslite sim")
    ap.add_argument("--summarise", nargs="+", type=Path, metavar="REPORT", help="summarise these reports only")
    ap.add_argument("--work", type=Path, default=REPO / "runs" / "team_map")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    out = args.out or RESULTS / f"team_map_sim{'_rt' if args.realtime else ''}.json"
    t0 = time.perf_counter()
    paths = args.summarise or run_sims(args.scene, args.runs, args.realtime, args.set, args.work)
    summary = summarise([json.loads(Path(p).read_text()) for p in paths])
    result = {"scene": args.scene, "realtime": args.realtime, "set": args.set, "reports": [str(p) for p in paths],
              "summary": summary, "images": before_after(Path(paths[0]), out), "wall_s": time.perf_counter() - t0}
    write_results(out, "team_map", argv, f": {summary['runs']} runs, {result['wall_s'] / 60:.1f} min",
                  table(summary), result)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
