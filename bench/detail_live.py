"""Live missions with the task region at its own resolution (``mapper.detail``, docs/mapper.md "The task region at
its own resolution") against the same missions at one resolution, where compute is scarce.

Each comparison is two ``bench.realtime`` results of the same scenes, budget, runs and scoring resolution: one at the
defaults (``off``) and one with ``--set mapper.detail.enabled=true`` (``on``), each with both modes, scored under
``novel`` at the scene's own resolution (``--score-at scene``, so that the region's finer detail counts whatever size
the governor mapped at). For example, a 0.25 s keyframe budget::

    python -m bench.realtime --scenes tum_fr1_rpy,tum_fr1_rpy_cup --runs 3 --final-pass-budgets= --protocols novel \\
        --score-at scene --budgets 0.25 --missions-only --out OFF.json
    python -m bench.realtime ... --set mapper.detail.enabled=true --out ON.json

then each with ``--score-only --jobs 2``, and::

    python -m bench.detail_live --pair b0.25=OFF.json,ON.json [--pair ...] [--out bench/results/detail_live.json]

Per cell (a label for one pair) and scene: both modes' ROI PSNR, GaussLite's iterations per keyframe and mapping
sizes, the ROI gain (GaussLite − uniform, paired per frame within each run, run-clustered over runs) without and with
the detail layer, and their difference (``on − off``, the interval of a difference of independent means: the two
half-widths in quadrature). Nothing is run here: wall-clock missions are run alone on the machine by
``bench.realtime``.

Failed missions (:mod:`bench._missions`): the two results' figures already leave out the runs whose mission failed
(``bench.realtime`` records them with their end state and error). A scene with such runs in either result lists them
under ``failed_runs`` (``{"off": [...], "on": [...]}``), its row is marked †, and the command exits 1 unless
``--allow-failed``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import List, Optional

import numpy as np

from bench._missions import FAILED_MARK, add_allow_failed, exit_code, failed_note, failure_rows, succeeded
from bench._results import write_results
from gausslite.stats import fmt, mean_std

RESULTS = Path(__file__).resolve().parent / "results"


def _block(result: dict, scene: str, protocol: str) -> Optional[dict]:
    """The one budget block of ``scene`` in a ``bench.realtime`` result, under ``protocol`` (None: not scored)."""
    budgets = result["scenes"].get(scene, {}).get("budgets", {})
    if len(budgets) != 1:
        return None
    blk = next(iter(budgets.values()))
    return blk["protocols"].get(protocol)


def _runs(result: dict, scene: str, mode: str) -> list:
    """The runs of ``scene`` and ``mode`` whose mission did not fail (:func:`bench._missions.succeeded`)."""
    return succeeded(r for r in result["runs"] if r["scene"] == scene and r["mode"] == mode)


def _mapped(runs: list) -> dict:
    """GaussLite's iterations per keyframe and mapping sizes over its runs."""
    it = mean_std([r.get("iters_per_keyframe") for r in runs])
    sizes = sorted({f"{r['mission']['mapping_size'][0]}×{r['mission']['mapping_size'][1]}"
                    for r in runs if (r.get("mission") or {}).get("mapping_size")})
    return {"iters_per_keyframe": it[0], "iters_per_keyframe_std": it[1], "mapping_sizes": sizes,
            "roi_iters_per_keyframe": mean_std([r.get("roi_iters", 0) / max(1, r.get("keyframes") or 1)
                                                for r in runs])[0]}


#: the fields that name a run of a ``bench.realtime`` result
RUN_KEYS = ("scene", "mode", "budget", "run")


def compare(off: dict, on: dict, protocol: str = "novel") -> dict:
    """Per scene: the ROI gain without (``off``) and with (``on``) the detail layer, and ``on − off``; a scene with
    failed missions in either result also ``failed_runs`` (``{"off": [...], "on": [...]}``,
    :func:`bench._missions.failure_rows`).

    Raises:
        ValueError: ``on`` was not run with the detail layer, or the two share no scene scored under ``protocol``.
    """
    if "mapper.detail.enabled=true" not in on["settings"].get("overrides", []):
        raise ValueError("the second result must be run with --set mapper.detail.enabled=true")
    out = {}
    for scene in on["scenes"]:
        b_off, b_on = _block(off, scene, protocol), _block(on, scene, protocol)
        if not b_off or not b_on or b_off.get("gain") is None or b_on.get("gain") is None:
            continue
        hw = [None if b.get("gain_ci") is None else (b["gain_ci"][1] - b["gain_ci"][0]) / 2 for b in (b_off, b_on)]
        d = b_on["gain"] - b_off["gain"]
        half = None if None in hw else float(np.hypot(*hw))
        out[scene] = {
            "protocol": protocol,
            **{v: {"gain": b["gain"], "gain_ci": b.get("gain_ci"), "runs": b["gausslite"].get("runs"),
                   "roi_psnr": {m: b[m]["roi_psnr"] for m in ("uniform", "gausslite")},
                   "gausslite": _mapped(_runs(res, scene, "gausslite")),
                   "uniform": _mapped(_runs(res, scene, "uniform"))}
               for v, b, res in (("off", b_off, off), ("on", b_on, on))},
            "on_minus_off": {"mean": d, "ci": None if half is None else [d - half, d + half]}}
        bad = {v: failure_rows([r for r in res.get("runs", []) if r.get("scene") == scene], RUN_KEYS)
               for v, res in (("off", off), ("on", on))}
        if any(bad.values()):
            out[scene]["failed_runs"] = bad
    if not out:
        raise ValueError(f"the two results share no scene scored under {protocol}")
    return out


def table(cells: dict) -> str:
    """The Markdown table of :func:`compare` per cell."""
    def gain(g: dict) -> str:
        ci = g.get("gain_ci") or g.get("ci")
        m = g.get("gain", g.get("mean"))
        return f"{m:+.2f}" + ("" if ci is None else f" [{ci[0]:+.2f}, {ci[1]:+.2f}]")

    rows = ["| cell | scene | uniform ROI PSNR | GaussLite ROI PSNR, one resolution / detail | GaussLite iters per "
            "keyframe, one / detail | GaussLite mapped at, one / detail | gain, one resolution | gain, detail | "
            "detail − one |", "|---|---|---|---|---|---|---|---|---|"]
    for cell, scenes in cells.items():
        for scene, v in scenes.items():
            o, n = v["off"], v["on"]
            mark = f" {FAILED_MARK}" if v.get("failed_runs") else ""
            rows.append(
                f"| {cell} | {scene}{mark} | {o['roi_psnr']['uniform']:.2f} / {n['roi_psnr']['uniform']:.2f} | "
                f"{o['roi_psnr']['gausslite']:.2f} / {n['roi_psnr']['gausslite']:.2f} | "
                f"{fmt(o['gausslite']['iters_per_keyframe'], o['gausslite']['iters_per_keyframe_std'], 1)} / "
                f"{fmt(n['gausslite']['iters_per_keyframe'], n['gausslite']['iters_per_keyframe_std'], 1)} | "
                f"{', '.join(o['gausslite']['mapping_sizes']) or '–'} / {', '.join(n['gausslite']['mapping_sizes']) or '–'} | "
                f"{gain(o)} | {gain(n)} | {gain(v['on_minus_off'])} |")
    if any(v.get("failed_runs") for scenes in cells.values() for v in scenes.values()):
        rows += ["", failed_note("scene with a run")]
    return "\n".join(rows)


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point: compare each ``--pair``, write the JSON and the Markdown table, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pair", action="append", required=True, metavar="CELL=OFF.json,ON.json",
                    help="a label and two bench.realtime results: without and with --set mapper.detail.enabled=true")
    ap.add_argument("--protocol", default="novel")
    ap.add_argument("--out", type=Path, default=RESULTS / "detail_live.json")
    add_allow_failed(ap)
    args = ap.parse_args(argv)
    cells, sources = {}, {}
    for spec in args.pair:
        label, _, paths = spec.partition("=")
        files = [Path(p) for p in paths.split(",") if p]
        if not label or len(files) != 2:
            ap.error(f"--pair takes CELL=OFF.json,ON.json, got {spec!r}")
        try:
            off, on = (json.loads(f.read_text()) for f in files)
            cells[label] = compare(off, on, args.protocol)
        except (FileNotFoundError, ValueError, KeyError) as e:
            ap.error(f"--pair {label}: {e}")
        sources[label] = {"off": off["settings"], "on": on["settings"], "files": [str(f) for f in files]}
    write_results(args.out, "detail_live", argv, "", table(cells), {"cells": cells, "sources": sources})
    bad = [{**r, "cell": label, "detail": v} for label, scenes in cells.items() for sc in scenes.values()
           for v, rs in (sc.get("failed_runs") or {}).items() for r in rs]
    return exit_code(bad, args.allow_failed, "bench.detail_live", ("cell", "detail", *RUN_KEYS))


if __name__ == "__main__":
    raise SystemExit(main())
