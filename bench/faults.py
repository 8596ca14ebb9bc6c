"""Which fault of a real sensor erases GaussLite's gain: the rendered walk through TUM fr1's camera with one of its
faults at a time, mapped live.

    python -m bench.faults [--faults clean,exposure,blur,misregistration,depth-noise,depth-holes,all] [--runs 3]
                           [--budget 0.5] [--cap 6000] [--frames 525] [--size 320x240]
                           [--profile rendered|handheld] [--set KEY=VALUE ...]
                           [--work DIR] [--jobs 1] [--out bench/results/faults_live.json]

Each row renders the hand-held walk (``gausslite make-scene --trajectory walk``: robot A, 525 frames at 320×240 and
30 Hz, a 7 m walk with two loops in front of the desk, seed 0) through TUM fr1's camera at the sensor level
``tum-<fault>`` (:func:`gausslite.synthetic.sensor.tum_fault`: one group of the measured Kinect's faults alone,
:data:`~gausslite.synthetic.sensor.TUM_FAULTS`; ``clean``: none of them; ``all``: the ``tum`` level, every one),
then maps it as ``bench.realtime --dataset`` does: live in-process missions of both modes, ``--budget`` seconds per
keyframe, the 6,000-Gaussian cap, task ``synth-pick-object``, the given (exact) poses, the mapper settings of the
walk's sensor profile (``rendered``) or, with ``--profile handheld``, of TUM's (exposure compensation, motion blur and
rolling shutter, pose refinement: :data:`gausslite.mapping.profiles.HANDHELD`), both resolution levels pinned
at the one resolution the runs share, every 10th frame withheld and scored (``novel``). Every row's missions run
first, one at a time (alone on the machine: they are wall-clock measurements), then the saved maps are scored. Faults
of the poses are ``bench.pose_perturbation``'s (the same walk, its given poses perturbed).

Per row: each mode's ROI PSNR and full-image PSNR (mean ± std over runs), the gain GaussLite − uniform (paired frame
by frame within a run, :func:`gausslite.stats.paired_gain`: the mean of the runs' gains with its 95 % run-clustered
interval) and the share of the clean row's gain it keeps.

Writes ``--out`` (JSON: the settings, per row the figures and the runs) and the markdown table beside it (``.md``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

from gausslite.mapping.profiles import HANDHELD
from gausslite.stats import aggregate
from gausslite.synthetic import make_scene
from gausslite.synthetic.sensor import TUM_FAULTS

from bench import realtime
from bench._results import write_results
from bench.ablation import PROTOCOL, figures, gain_cell, kept_protocol, paired

#: the rows: no fault, each fault alone, all of them (the ``tum`` level)
FAULTS = ("clean", *TUM_FAULTS, "all")
TASK = "synth-pick-object"
#: the walk every row renders (``make_scene`` arguments)
WALK = {"frames": 525, "width": 320, "height": 240, "trajectory": "walk", "seed": 0}
CAP = 6000


def sensor_level(fault: str) -> str:
    """The ``make_scene(sensor_noise=...)`` level of a row."""
    return "tum" if fault == "all" else f"tum-{fault}"


def walk_path(fault: str, work: Path, walk: Optional[dict] = None) -> Path:
    """Robot A's folder of the walk (``make_scene`` arguments, default :data:`WALK`) rendered with ``fault`` into
    ``work`` (rendered once)."""
    walk = {**WALK, **(walk or {})}
    out = Path(work) / f"walk_{walk['frames']}_{walk['width']}x{walk['height']}_{sensor_level(fault)}"
    if not (out / "agent_a" / "results" / f"depth{walk['frames'] - 1:06d}.png").exists():
        make_scene(out, sensor_noise=sensor_level(fault), agents=("agent_a",), **walk)
    return out / "agent_a"


def summarise(runs: list[dict]) -> dict:
    """One row's figures from its scored ``bench.realtime`` runs (both modes)."""
    out: dict = {}
    by_mode: dict = {}
    for r in runs:
        if figures(r)[0] is not None and r.get("end_state", "FINISHED") == "FINISHED":
            by_mode.setdefault(r["mode"], []).append(r)
    for mode, rs in by_mode.items():
        blk = aggregate([{"roi_psnr": figures(r)[0], "psnr": figures(r)[1]} for r in rs], ["roi_psnr", "psnr"])
        out[mode] = {**blk, "runs": len(rs),
                     "iters_per_keyframe": sum(r.get("iters_per_keyframe") or 0 for r in rs) / len(rs)}
    gain = paired(by_mode.get("gausslite", []), by_mode.get("uniform", []))
    if gain is not None:
        out["gain"] = gain
    return out


def table(result: dict) -> str:
    """The markdown table: per row, both modes' ROI PSNR and PSNR, the gain [interval] and the clean gain kept."""
    s = result["settings"]
    lines = [f"The walk through TUM fr1's camera, one fault at a time, mapped with the {s.get('profile', 'rendered')} "
             f"profile's settings; live, {s['budget']:g} s per keyframe, "
             f"`{PROTOCOL}`, {s['runs']} runs per mode; the gain paired frame by frame within a run [95 % "
             "run-clustered interval], * the interval excludes zero.", "",
             "| fault | uniform ROI PSNR | GaussLite ROI PSNR | gain | clean gain kept | uniform PSNR | GaussLite PSNR "
             "| iters/kf, uniform / GaussLite |",
             "|---|---|---|---|---|---|---|---|"]
    clean = (result["rows"].get("clean") or {}).get("gain", {}).get("gain")

    def cell(b: Optional[dict], key: str) -> str:
        return "" if not b or b.get(key) is None else f"{b[key]:.2f} ± {b.get(key + '_std') or 0:.2f}"

    for fault, row in result["rows"].items():
        u, g, d = row.get("uniform"), row.get("gausslite"), row.get("gain")
        gain = gain_cell(d)
        kept = f"{100 * d['gain'] / clean:.0f} %" if gain and clean else ""
        iters = (f"{u['iters_per_keyframe']:.1f} / {g['iters_per_keyframe']:.1f}" if u and g else "")
        lines.append(f"| {fault} | {cell(u, 'roi_psnr')} | {cell(g, 'roi_psnr')} | {gain} | {kept} "
                     f"| {cell(u, 'psnr')} | {cell(g, 'psnr')} | {iters} |")
    return "\n".join(lines)


def profile_overrides(name: str) -> list[str]:
    """``bench.realtime --set`` arguments that map the walk with sensor profile ``name``'s mapper settings
    (:mod:`gausslite.mapping.profiles`; ``rendered``: the walk's own, none), e.g. ``handheld``: TUM's."""
    if name == "rendered":
        return []
    if name != HANDHELD.name:
        raise ValueError(f"unknown profile {name!r} (rendered or {HANDHELD.name})")

    def flat(d: dict, prefix: str) -> list[str]:
        out = []
        for k, v in d.items():
            if isinstance(v, dict):
                out += flat(v, f"{prefix}{k}.")
            else:
                out.append(f"{prefix}{k}={str(v).lower() if isinstance(v, bool) else v}")
        return out

    return flat(HANDHELD.mapper, "mapper.")


def _realtime_args(args: argparse.Namespace, fault: str, path: Path) -> list[str]:
    """``bench.realtime``'s arguments for one row (its own result file in ``work``)."""
    sets = [x for o in [*profile_overrides(args.profile), *args.overrides] for x in ("--set", o)]
    return ["--dataset", str(path), "--tasks", TASK, "--cap", str(args.cap), "--modes", "uniform,gausslite",
            "--budgets", f"{args.budget:g}", "--runs", str(args.runs), "--final-pass-budgets=", "--protocols",
            PROTOCOL, "--work", str(args.work), "--out", str(args.work / f"{fault}.json"), *sets]


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.faults", description=__doc__.split("\n\n")[0])
    ap.add_argument("--faults", default=",".join(FAULTS), help="rows to run, comma-separated")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=WALK["frames"], help="frames of the walk (30 Hz)")
    ap.add_argument("--size", default=f"{WALK['width']}x{WALK['height']}", help="the walk's image size, WxH")
    ap.add_argument("--cap", type=int, default=CAP, help="the matched Gaussian cap")
    ap.add_argument("--profile", choices=("rendered", "handheld"), default="rendered",
                    help="the mapper settings of a sensor profile: rendered (the walk's own) or handheld (TUM's: "
                         "exposure compensation, motion blur and rolling shutter, pose refinement, a lighter depth "
                         "loss)")
    ap.add_argument("--budget", type=float, default=realtime.REFERENCE_BUDGET_S, help="seconds per keyframe")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="agent setting for every run (as bench.realtime --set)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/gausslite_bench_faults"))
    ap.add_argument("--jobs", type=int, default=1, help="processes that score the saved maps")
    ap.add_argument("--out", type=Path, default=realtime.RESULTS / "faults_live.json")
    args = ap.parse_args(argv)
    chosen = [f for f in args.faults.split(",") if f]
    if unknown := [f for f in chosen if f not in FAULTS]:
        ap.error(f"unknown faults {unknown} (known: {', '.join(FAULTS)})")
    try:
        w, h = (int(x) for x in args.size.lower().split("x"))
    except ValueError:
        ap.error(f"--size takes WxH, got {args.size!r}")
    walk = {**WALK, "frames": args.frames, "width": w, "height": h}
    args.work.mkdir(parents=True, exist_ok=True)
    paths = {f: walk_path(f, args.work, walk) for f in chosen}  # every render before the first mission
    for f in chosen:  # every row's missions, one at a time, then the scoring
        if realtime.main(_realtime_args(args, f, paths[f]) + ["--missions-only", "--resume"]):
            return 1
    rows, kept_runs = {}, {}
    for f in chosen:
        if realtime.main(_realtime_args(args, f, paths[f]) + ["--score-only", "--jobs", str(args.jobs)]):
            return 1
        runs = json.loads((args.work / f"{f}.json").read_text())["runs"]
        rows[f] = summarise(runs)
        kept_runs[f] = [{"mode": r["mode"], "run": r["run"], "end_state": r.get("end_state"),
                         "iters_per_keyframe": r.get("iters_per_keyframe"), "keyframes": r.get("keyframes"),
                         "mapping_downscale": r.get("mapping_downscale"), "protocols": kept_protocol(r)}
                        for r in runs]
    result = {"settings": {"budget": args.budget, "runs": args.runs, "faults": chosen, "protocol": PROTOCOL,
                           "task": TASK, "cap": args.cap, "walk": walk, "profile": args.profile,
                           "overrides": [*profile_overrides(args.profile), *args.overrides],
                           "levels": {f: sensor_level(f) for f in chosen}},
              "rows": rows, "runs": kept_runs}
    write_results(args.out, "faults", argv, f": {len(chosen)} rows, {args.runs} runs a mode", table(result), result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
