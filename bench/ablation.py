"""The paper's ablation (Table 3) live, on real sensors: which of GaussLite's components pay under a real-time
per-keyframe budget on real RGB-D.

    python -m bench.ablation [--scenes tum_fr1_rpy,tum_fr1_rpy_cup] [--rows ROWS] [--runs 6] [--budget 0.5]
                             [--dataset DIR --tasks T1,T2] [--out bench/results/ablation_live.json]

Rows (GaussLite mode, ``mapper.components``): the paper's progressive rows (``none``, ``+SB``, ``+MVO``, ``+ROI``,
``+SIS``, ``+GFD``: each component enabled on top of the previous ones, ``gausslite.mapping.config.ablation_rows``),
then each component left out of the full pipeline (``full-SB`` ... ``full-GFD``). Each row's missions are
``bench.realtime``'s live protocol: 0.5 s per keyframe, the scene's matched Gaussian cap, no final pass, the
withheld frames scored (``novel``), both resolution levels pinned at the one resolution ``bench.realtime`` shares
between runs (``--resolution shared``). All missions of every row run first, one at a time, alone on the machine
(``--missions-only``), then the saved maps are scored.

Per scene and row: the ROI PSNR and the full-image PSNR under ``novel`` (mean ± std over runs), the row's step over the
row before it and its gain over ``none`` (paired frame by frame within each seed, a run-clustered 95 % interval,
:func:`gausslite.stats.paired_gain`), and the paper's Campus column (its real rover data) beside it. A leave-one-out
row's figure is its difference from the full pipeline (what the component adds to the others). ``--dataset DIR
--tasks ...`` runs a folder of one's own (the rendered walk of ``gausslite make-scene --trajectory walk``, say) as
``bench.realtime --dataset`` does.

Writes ``--out`` (JSON: the settings, per scene the rows' figures, and every run of ``bench.realtime`` it read) and
the markdown table beside it (``.md``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

from gausslite.cli.cmd_ablate import SWITCHES
from gausslite.evaluation import current_protocols
from gausslite.mapping.config import ablation_rows
from gausslite.stats import aggregate, paired_gain

from bench import realtime
from bench._results import write_json

#: the paper's Table 3 on its real rover data (Campus), ROI PSNR in dB, rows enabled cumulatively
PAPER_CAMPUS = {"none": 21.50, "+SB": 21.61, "+MVO": 22.55, "+ROI": 22.15, "+SIS": 25.14, "+GFD": 25.25}
PROTOCOL = "novel"
#: the full pipeline's row (the last progressive one), which the leave-one-out rows are compared with
FULL = ablation_rows()[-1][0]
#: what the result keeps of each run (besides its ``novel`` figures)
RUN_FIELDS = ("scene", "run", "budget", "n_gaussians", "iters_per_keyframe", "roi_iters", "keyframes",
              "mapping_downscale", "resolution_mode", "end_state")


def rows() -> list[tuple[str, dict]]:
    """The rows: ``[(name, {switch: bool})]``, the progressive ones then the leave-one-out ones."""
    out = [(name, sw.model_dump()) for name, sw in ablation_rows()]
    full = out[-1][1]
    out += [(f"full-{s.upper()}", {**full, s: False}) for s in SWITCHES]
    return out


def row_overrides(switches: dict) -> list[str]:
    """``bench.realtime --set`` arguments that set the mapper's component switches to ``switches``."""
    return [f"mapper.components.{s}={'true' if switches[s] else 'false'}" for s in SWITCHES]


def _entry(run: dict) -> dict:
    """A scored ``bench.realtime`` run's :data:`PROTOCOL` entry ({} when it has none)."""
    return current_protocols(run.get("protocols")).get(PROTOCOL) or {}


def figures(run: dict) -> tuple:
    """(ROI PSNR, PSNR, per-frame ROI PSNR) of one scored ``bench.realtime`` run under :data:`PROTOCOL`."""
    p = _entry(run)
    return p.get("roi_psnr"), p.get("psnr"), p.get("roi_psnr_per_frame")


def kept_protocol(run: dict) -> dict:
    """What a result keeps of a scored run's scores: ``{PROTOCOL: {roi_psnr, psnr, roi_psnr_per_frame, pose}}``."""
    p = _entry(run)
    return {PROTOCOL: {k: p.get(k) for k in ("roi_psnr", "psnr", "roi_psnr_per_frame", "pose")}}


def paired(a: list, b: list) -> Optional[dict]:
    """Runs ``a`` − runs ``b`` (paired by run id): :func:`paired_gain` over the per-frame ROI PSNR, as ``{gain, ci,
    runs, interval}``; None without a pair or with a run lacking its per-frame figures."""
    by_b = {r["run"]: r for r in b}
    pairs = [(r, by_b[r["run"]]) for r in a if r["run"] in by_b]
    fa, fb = [figures(x)[2] for x, _ in pairs], [figures(y)[2] for _, y in pairs]
    if not pairs or any(f is None for f in fa + fb):
        return None
    g = paired_gain(fa, fb)
    return {"gain": g["gain"], "ci": [g["ci_low"], g["ci_high"]], "runs": g["runs"], "interval": g["interval"]}


def summarise(by_row: dict) -> dict:
    """Per row of one scene (``by_row``: row → its scored runs): the means over runs and the paired differences."""
    out = {}
    names = [n for n, _ in rows() if n in by_row]
    progressive = [n for n in names if not n.startswith("full-")]
    for name in names:
        rs = [r for r in by_row[name] if figures(r)[0] is not None]
        blk = aggregate([{"roi_psnr": figures(r)[0], "psnr": figures(r)[1]} for r in rs], ["roi_psnr", "psnr"])
        blk["runs"] = len(rs)
        if name.startswith("full-") and FULL in by_row:
            blk["vs_full"] = paired(rs, by_row[FULL])  # negative: the component pays
        elif name in progressive and progressive.index(name) > 0:
            blk["step"] = paired(rs, by_row[progressive[progressive.index(name) - 1]])
        if name != "none" and "none" in by_row:
            blk["vs_none"] = paired(rs, by_row["none"])
        blk["paper_campus"] = PAPER_CAMPUS.get(name)
        out[name] = blk
    return out


def gain_cell(d: Optional[dict]) -> str:
    """A :func:`paired` difference as a table cell: ``+0.58 [+0.48, +0.69]*`` (* the interval excludes zero)."""
    if not d or d.get("gain") is None:
        return ""
    lo, hi = d["ci"]
    star = "*" if lo is not None and (lo > 0 or hi < 0) else ""
    return (f"{d['gain']:+.2f} [{lo:+.2f}, {hi:+.2f}]{star}" if lo is not None else f"{d['gain']:+.2f}")


def table(result: dict) -> str:
    """The markdown table: per scene and row, ROI PSNR and PSNR (mean ± std), the step, the gain over ``none``
    (leave-one-out rows: the difference from the full pipeline), and the paper's Campus ROI PSNR."""
    lines = [f"Live, {result['settings']['budget']:g} s per keyframe, `{PROTOCOL}`, {result['settings']['runs']} runs "
             "per row; differences paired frame by frame within each seed [95 % run-clustered interval], * the "
             "interval excludes zero.", "",
             "| scene | row | ROI PSNR | PSNR | step | vs none | leave-one-out vs full | paper Campus ROI PSNR |",
             "|---|---|---|---|---|---|---|---|"]
    for scene, blk in result["scenes"].items():
        for name, r in blk.items():
            roi = "" if r.get("roi_psnr") is None else f"{r['roi_psnr']:.2f} ± {r['roi_psnr_std'] or 0:.2f}"
            psnr = "" if r.get("psnr") is None else f"{r['psnr']:.2f} ± {r['psnr_std'] or 0:.2f}"
            paper = "" if r["paper_campus"] is None else f"{r['paper_campus']:.2f}"
            lines.append(f"| {scene} | {name} | {roi} | {psnr} | {gain_cell(r.get('step'))} "
                         f"| {gain_cell(r.get('vs_none'))} | {gain_cell(r.get('vs_full'))} | {paper} |")
    return "\n".join(lines)


def _realtime_args(args: argparse.Namespace, name: str, switches: dict, work: Path) -> list[str]:
    """``bench.realtime``'s arguments for one row (its own result file in ``work``)."""
    where = (["--dataset", args.dataset, "--tasks", args.tasks, "--downscale", str(args.downscale)]
             if args.dataset else ["--scenes", args.scenes])
    out = ["--modes", "gausslite", "--budgets", f"{args.budget:g}", "--runs", str(args.runs),
           "--final-pass-budgets=", "--protocols", PROTOCOL, "--work", str(work), "--out", str(work / f"{name}.json")]
    sets = [x for o in [*row_overrides(switches), *args.overrides] for x in ("--set", o)]
    return where + out + sets


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.ablation", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="tum_fr1_rpy,tum_fr1_rpy_cup", help="bench.realtime scenes, comma-separated")
    ap.add_argument("--dataset", default=None, help="a folder of one's own instead (bench.realtime --dataset)")
    ap.add_argument("--tasks", default="", help="--dataset: its task ids, comma-separated")
    ap.add_argument("--downscale", type=float, default=1.0, help="--dataset: image downscale factor")
    ap.add_argument("--rows", default=",".join(n for n, _ in rows()), help="rows to run, comma-separated")
    ap.add_argument("--runs", type=int, default=6)
    ap.add_argument("--budget", type=float, default=realtime.REFERENCE_BUDGET_S, help="seconds per keyframe")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="agent setting for every row (as bench.realtime --set)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/gausslite_bench_ablation"))
    ap.add_argument("--jobs", type=int, default=1, help="processes that score the saved maps")
    ap.add_argument("--out", type=Path, default=realtime.RESULTS / "ablation_live.json")
    args = ap.parse_args(argv)
    known = dict(rows())
    chosen = [r for r in args.rows.split(",") if r]
    if unknown := [r for r in chosen if r not in known]:
        ap.error(f"unknown rows {unknown} (known: {', '.join(known)})")
    args.work.mkdir(parents=True, exist_ok=True)
    # every row's missions first, one at a time (each alone on the machine), then the scoring
    for name in chosen:
        if realtime.main(_realtime_args(args, name, known[name], args.work) + ["--missions-only", "--resume"]):
            return 1
    runs: dict = {}
    for name in chosen:
        if realtime.main(_realtime_args(args, name, known[name], args.work) + ["--score-only", "--jobs",
                                                                               str(args.jobs)]):
            return 1
        for r in json.loads((args.work / f"{name}.json").read_text())["runs"]:
            kept = {k: r.get(k) for k in RUN_FIELDS}
            kept["protocols"] = kept_protocol(r)
            runs.setdefault(r["scene"], {}).setdefault(name, []).append(kept)
    result = {"settings": {"budget": args.budget, "runs": args.runs, "rows": chosen, "protocol": PROTOCOL,
                           "overrides": args.overrides, "scenes": args.scenes if not args.dataset else None,
                           "dataset": args.dataset, "tasks": args.tasks or None},
              "scenes": {scene: summarise(by_row) for scene, by_row in runs.items()},
              "runs": {scene: by_row for scene, by_row in runs.items()}}
    write_json(args.out, result, "ablation", argv)
    md = table(result)
    args.out.with_suffix(".md").write_text(md + "\n")
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
