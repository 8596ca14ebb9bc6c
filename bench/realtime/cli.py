"""The paper's real-time protocol as a benchmark: live single agents, a per-keyframe time budget, a matched
Gaussian cap, no final pass (paper Sec. IV-A, Baselines). See ``docs/realtime.md``.

The command line of ``python -m bench.realtime`` (:func:`main`): its options, the jobs they ask for, the runs (live
missions one after another, twin runs on worker processes), the scoring of the saved maps, and the result written
(``<out>``, its tables and plots; the package's docstring describes the protocol and the result's layout).

A failed mission (:mod:`bench._missions`) is recorded with its end state and error, left out of the figures, marked †
in the tables, and makes the command exit 1 once its result (or, with ``--missions-only``, its partial file) is
written, unless ``--allow-failed``; ``--resume`` runs a failed mission again."""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Optional, get_args

from tqdm import tqdm

from gausslite.odometry.rgbd import PoseSource
from gausslite.evaluation import NOVEL_EVERY, PROTOCOLS

from bench._missions import add_allow_failed, exit_code, failed, failure_rows
from bench._results import provenance, write_json
from bench.realtime.missions import RESOLUTION_KEYS, calibrate, run_key, run_one, shared_resolution, twin_one
from bench.realtime.protocol import TRACK_ITERS, TRACK_STRIDE, score_deferred
from bench.realtime.scenes import MODES, REFERENCE_BUDGET_S, RESULTS, SCENES, dataset_scenes, scene_path
from bench.realtime.summary import budget_key, summarise
from bench.realtime.tables import plot_scene, plot_trace, protocol_table, table, trace_tables
from bench.realtime.late import LATE_VIA


#: the fields that name a run in a failed mission's message
RUN_KEYS = ("scene", "mode", "budget", "run")


def main(argv: Optional[list[str]] = None, prog: Optional[str] = None) -> int:
    """Run the benchmark of the command line ``argv`` (``--help``; ``prog``: the program name its usage shows, default
    argparse's). Returns 0 on success, 1 when a run's mission failed (recorded, left out of the figures, each printed
    to stderr) and ``--allow-failed`` was not given."""
    ap = _parser(prog)
    args = ap.parse_args(argv)

    if args.calibrate:
        work = Path(args.work)
        work.mkdir(parents=True, exist_ok=True)
        res = calibrate(args.scenes.split(",")[0], work, overrides=args.overrides)
        print(json.dumps(res, indent=1))
        return 0

    if args.reaggregate:
        res = reaggregate(Path(args.out), argv)
        return exit_code(res["runs"], args.allow_failed, "bench.realtime", RUN_KEYS)
    protocols, scenes, specs = _checked_scenes(ap, args)
    budgets = [float(b) for b in args.budgets.split(",") if b]
    fp_budgets = {float(b) for b in args.final_pass_budgets.split(",") if b}
    modes = [m for m in args.modes.split(",") if m]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_suffix(".partial.json")
    runs: list[dict] = []
    if (args.resume or args.score_only) and partial.is_file():
        runs = json.loads(partial.read_text())["runs"]
    if args.resume and not args.score_only:
        runs = _drop_failed(runs)  # a failed mission runs again
    done = {run_key(r) for r in runs}
    jobs, names = _build_jobs(args, scenes, specs, protocols, budgets, fp_budgets, modes, out, done)
    if args.score_only:
        # score what earlier --missions-only invocations saved (every budget they ran), start no mission
        jobs = []
        budgets = sorted({float(r["budget"]) for r in runs if r["scene"] in names} | set(budgets))
    # one folder per result file: two invocations that share --work (given and odometry poses, say) keep their maps
    defer = None if args.twin or args.score_inline else Path(args.work) / "maps" / out.stem
    for job in jobs:
        job["defer_dir"] = str(defer) if defer else None
    t0 = time.time()
    _run_jobs(args, jobs, runs, partial)
    pending = [i for i, r in enumerate(runs) if "state_path" in r and Path(r["state_path"]).is_file()]
    if args.missions_only:
        print(f"{len(pending)} maps saved for scoring: score them with --score-only (same --out)")
        return exit_code(runs, args.allow_failed, "bench.realtime", RUN_KEYS)
    _score_pending(args, runs, pending, partial)
    _write_result(args, runs, names, budgets, protocols, out, t0, argv)
    return exit_code(runs, args.allow_failed, "bench.realtime", RUN_KEYS)


def _shared_resolutions(runs: list[dict]) -> dict:
    """scene → budget key → the downscale both modes mapped at, for the runs under ``--resolution shared``."""
    out: dict = {}
    for r in runs:
        if r.get("resolution_mode") == "shared":
            out.setdefault(r["scene"], {})[budget_key(r["budget"])] = r["mapping_downscale"]
    return out


def _drop_failed(runs: list[dict]) -> list[dict]:
    """``runs`` without its failed missions (their saved maps removed), so that a resumed invocation runs them
    again."""
    for r in runs:
        if failed(r) and r.get("state_path"):
            Path(r["state_path"]).unlink(missing_ok=True)
    return [r for r in runs if not failed(r)]


def _parser(prog: Optional[str] = None) -> argparse.ArgumentParser:
    """The command line of ``python -m bench.realtime``."""
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="tum_fr1_rpy,synthetic_circle,tum_fr1_rpy_cup,room0")
    ap.add_argument("--dataset", default=None, metavar="PATH",
                    help="a sequence of your own (any folder the loaders read, with objects.json / tasks.json) "
                         "instead of the built-in scenes: one scene per --tasks id, named after it")
    ap.add_argument("--tasks", default="", help="--dataset: task ids of its tasks.json, comma-separated")
    ap.add_argument("--fps", type=float, default=None, help="--dataset: replay clock of sequences without timestamps")
    ap.add_argument("--downscale", type=float, default=1.0, help="--dataset: image downscale factor")
    ap.add_argument("--protocols", default=",".join(PROTOCOLS),
                    help="scoring protocols (docs/realtime.md#scoring-protocols), comma-separated")
    ap.add_argument("--novel-every", type=int, default=NOVEL_EVERY,
                    help="novel / novel-tracked protocols: every k-th frame of the sequence is withheld from the "
                         "mapper in both modes, scored at the pose the map predicts (novel) and at a pose tracked "
                         "against the map (novel-tracked) (0: nothing withheld, neither protocol)")
    ap.add_argument("--pose-source", choices=get_args(PoseSource), default="given",
                    help="the poses the agents map and are scored at: the sequence's own (given), or the RGB-D "
                         "odometry's estimates of every frame, the withheld ones included (agent.pose_source "
                         "odometry: a camera without SLAM); the ROI is the given poses' either way")
    ap.add_argument("--resolution", choices=("shared", "agent"), default="shared",
                    help="shared (default): both modes map at one resolution per scene and budget, the agent "
                         "governor's first choice under the uniform settings, background and task region alike, so "
                         "that every run pairs; agent: each mission's own governor (a finer region level, changes "
                         "mid-mission), as a robot runs it. A --set of agent.resolution.downscale or roi_downscale "
                         "pins it instead")
    ap.add_argument("--score-at", choices=("mapping", "scene"), default="mapping",
                    help="score each map at the resolution its mission mapped at (mapping), or at the scene's own "
                         "resolution whatever the agent mapped at (scene: runs mapped at different resolutions pair, "
                         "and a map's detail counts); decided with the missions, recorded with each saved map")
    ap.add_argument("--track-iters", type=int, default=TRACK_ITERS,
                    help="tracked / novel-tracked protocols: Adam steps per frame")
    ap.add_argument("--track-stride", type=int, default=TRACK_STRIDE,
                    help="tracked protocol: score every k-th frame of the sequence (MonoGS: every 5th)")
    ap.add_argument("--late", type=float, default=None, metavar="F",
                    help="the 'late' scenario: the task starts after this share of the sequence (scenes named "
                         "<scene>_late, or <scene>_late_detection with --late-via detection)")
    ap.add_argument("--late-via", choices=LATE_VIA, default="task",
                    help="late scenario: 'task', the task is given mid-mission (UpdateTask: the stored keyframes "
                         "get its relevance); 'detection', the task's object is first detected then (earlier frames "
                         "never get its relevance)")
    ap.add_argument("--budgets", default="0.25,0.5,1,2", help="seconds per keyframe, comma-separated")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--clock", choices=("scaled", "dataset"), default="scaled")
    ap.add_argument("--task", default=None, help="task id of every scene (default: the scene's)")
    ap.add_argument("--cap", type=int, default=None, help="Gaussian cap of every scene (default: the scene's)")
    ap.add_argument("--final-pass-budgets", default="0.5",
                    help="budgets whose maps also get the profile's final pass, scored in a separate column ('' = none)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="agent config override for both modes, e.g. mapper.seeding.rho=0.5")
    ap.add_argument("--out", default=str(RESULTS / "realtime.json"))
    ap.add_argument("--work", default="/tmp/gausslite_bench_realtime")
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--share", action="store_true",
                    help="agents also share (select, fine-tune, encode and push their subset to an in-process sink), "
                         "as on a robot: measures what sharing costs the agent's own map")
    ap.add_argument("--twin", action="store_true",
                    help="the deterministic twin: fixed keyframe spacing, budgets on the work clock (mapper.work_cost), "
                         "not wall time; runs may go to --jobs processes")
    ap.add_argument("--jobs", type=int, default=1,
                    help="worker processes of --twin runs, and of the scoring that follows the live missions")
    ap.add_argument("--missions-only", action="store_true",
                    help="run the live missions and save their maps, without scoring (score later with --score-only): "
                         "several invocations' missions can then run back to back, alone, before any scoring")
    ap.add_argument("--score-only", action="store_true",
                    help="start no mission: score the maps earlier --missions-only runs saved to the same --out "
                         "(its partial file) and write the result over every budget they ran")
    ap.add_argument("--reaggregate", action="store_true",
                    help="start no mission, score nothing: rewrite the summary (means, paired gains) of the result "
                         "--out from the runs it holds, with today's aggregation; its runs and settings stay")
    ap.add_argument("--score-inline", action="store_true",
                    help="score each live map right after its mission (default: every mission first, alone on the "
                         "machine, then the saved maps are scored, --jobs at a time)")
    ap.add_argument("--calibrate", action="store_true",
                    help="fit the deterministic budget clock's cost model (mapper.work_cost) on this machine and "
                         "print it (first scene)")
    add_allow_failed(ap)
    return ap


def _checked_scenes(ap: argparse.ArgumentParser, args: argparse.Namespace) -> tuple:
    """The protocols, the scene names and each scene's spec (``--dataset``'s tasks or built-in scenes); unusable
    options end the program through ``ap.error``."""
    protocols = tuple(p for p in args.protocols.split(",") if p)

    if any(p not in PROTOCOLS for p in protocols):
        ap.error(f"unknown protocol in {args.protocols!r} (known: {', '.join(PROTOCOLS)})")
    if args.novel_every == 1 or args.novel_every < 0:
        ap.error("--novel-every must be 0 (off) or >= 2")
    if args.late is not None and not 0 < args.late < 1:
        ap.error("--late must be in (0, 1)")
    if args.twin and args.pose_source != "given":
        ap.error("--pose-source odometry runs live missions only (the twin replays the given poses)")
    if args.dataset:
        try:
            specs = dataset_scenes(Path(args.dataset), [t for t in args.tasks.split(",") if t],
                                   args.cap or 6000, args.downscale, args.fps)
        except (FileNotFoundError, ValueError) as e:
            ap.error(str(e))
        scenes = list(specs)
    else:
        scenes = [s for s in args.scenes.split(",") if s]
        for s in scenes:
            if s not in SCENES:
                ap.error(f"unknown scene {s!r} (known: {', '.join(SCENES)})")
        specs = {s: SCENES[s] for s in scenes}
    return protocols, scenes, specs


def _build_jobs(args: argparse.Namespace, scenes: list[str], specs: dict, protocols: tuple, budgets: list[float],
                fp_budgets: set, modes: list[str], out: Path, done: set) -> tuple[list[dict], dict]:
    """The (scene, run, budget, mode) jobs not ``done`` yet, and each scene's name (``_late`` ...) with its cap."""
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    jobs = []
    names = {}
    pinned_by_user = any(o.split("=", 1)[0].strip() in RESOLUTION_KEYS for o in args.overrides)
    for scene in scenes:
        spec = specs[scene]
        path = Path(spec["path"]) if "path" in spec else scene_path(scene, work)
        cap = args.cap or spec["cap"]
        name = (scene + ("_late" if args.late_via == "task" else "_late_detection")) if args.late else scene
        names[name] = cap
        shared = {}
        if args.resolution == "shared" and not (pinned_by_user or args.twin or args.score_only):
            # one resolution per scene and budget for both modes, chosen before any mission (the same for every run)
            shared = shared_resolution(spec, path, budgets, cap, args.overrides)
        for run in range(args.runs):
            for b in budgets:
                for mode in modes:
                    job = {"scene": name, "spec": spec, "path": str(path), "task": args.task or spec["task"],
                           "mode": mode, "budget": b, "run": run, "cap": cap, "clock": args.clock,
                           "final_pass": b in fp_budgets,
                           "overrides": list(args.overrides) + (shared[b]["overrides"] if shared else []),
                           "resolution_mode": "shared" if shared else "pinned" if pinned_by_user else "agent",
                           "share": args.share,
                           "late": args.late, "late_via": args.late_via, "protocols": protocols,
                           "novel_every": args.novel_every, "pose_source": args.pose_source,
                           "track_iters": args.track_iters,
                           "track_stride": args.track_stride, "score_at": args.score_at,
                           "render_dir": (str(out.with_name(out.stem + "_renders"))
                                          if run == 0 and b == REFERENCE_BUDGET_S and not args.twin else None)}
                    if run_key(job) not in done:
                        jobs.append(job)
    return jobs, names


def _run_jobs(args: argparse.Namespace, jobs: list[dict], runs: list[dict], partial: Path) -> None:
    """Run ``jobs`` (twin runs on ``--jobs`` processes, live missions one after another), appending to ``runs`` and
    rewriting ``partial`` after each."""
    if args.twin:
        with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            results = pool.map(twin_one, jobs)
            results = list(tqdm(results, total=len(jobs), desc="twin runs", unit="run"))
    else:
        results = (run_one(job) for job in jobs)
    for r in tqdm(results, total=len(jobs), desc="realtime runs", unit="run", disable=args.twin):
        runs.append(r)
        if failed(r):
            tqdm.write(f"{r['scene']} {r['mode']:9s} b={r['budget']:<5g} run {r['run']}: mission {r['end_state']}"
                       + (f": {r['error']}" if r.get("error") else "")
                       + (f", {r['frames_failed']} frames failed" if r.get("frames_failed") else "")
                       + " (recorded, left out of the figures)")
            partial.write_text(json.dumps({"runs": runs}, indent=1))
            continue
        if "state_path" in r:  # scored below, once every mission ran
            tqdm.write(f"{r['scene']} {r['mode']:9s} b={r['budget']:<5g} run {r['run']}: {r['n_gaussians']} G, "
                       f"{r['keyframes']} kf x {r['iters_per_keyframe']:.1f} it (+{r['idle_iters']} idle), "
                       f"{r['wall_s']:.0f} s")
            partial.write_text(json.dumps({"runs": runs}, indent=1))
            continue
        per = " ".join(f"{p} {v['roi_psnr']:.2f}" for p, v in r.get("protocols", {}).items()
                       if v.get("roi_psnr") is not None)
        tqdm.write(f"{r['scene']} {r['mode']:9s} b={r['budget']:<5g} run {r['run']}: ROI {r['roi_psnr']:.2f} dB "
                   f"({per}), PSNR {r['psnr']:.2f}, {r['n_gaussians']} G, {r['keyframes']} kf x "
                   f"{r['iters_per_keyframe']:.1f} it (+{r['idle_iters']} idle), {r['wall_s']:.0f} s")
        partial.write_text(json.dumps({"runs": runs}, indent=1))


def _score_pending(args: argparse.Namespace, runs: list[dict], pending: list[int], partial: Path) -> None:
    """Score the saved maps of ``runs[i]`` for ``i`` in ``pending`` on ``--jobs`` processes, in place."""
    if pending:
        items = [runs[i] for i in pending]
        with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            for i, r in zip(pending, tqdm(pool.map(score_saved, items), total=len(items), desc="scoring",
                                          unit="map")):
                runs[i] = r
                if "protocols" not in r:  # a failed mission's map that could not be scored
                    partial.write_text(json.dumps({"runs": runs}, indent=1))
                    continue
                per = " ".join(f"{p} {v['roi_psnr']:.2f}" for p, v in r["protocols"].items()
                               if v.get("roi_psnr") is not None)
                tqdm.write(f"{r['scene']} {r['mode']:9s} b={r['budget']:<5g} run {r['run']}: ROI ({per}), "
                           f"PSNR {r['psnr']:.2f}")
                partial.write_text(json.dumps({"runs": runs}, indent=1))


def score_saved(res: dict) -> dict:
    """:func:`~bench.realtime.protocol.score_deferred` of one saved map (a worker). A failed mission's map that cannot
    be scored keeps its run without scores and records ``score_error`` (its state file removed); a finished mission's
    scoring errors propagate."""
    if not failed(res):
        return score_deferred(res)
    try:
        return score_deferred(res)
    except Exception as e:
        Path(res["state_path"]).unlink(missing_ok=True)
        return {**{k: v for k, v in res.items() if k not in ("state_path", "fp_per_kf", "score_job")},
                "score_error": f"{type(e).__name__}: {e}"}


def reaggregate(out: Path, argv: Optional[list[str]] = None) -> dict:
    """Rewrite the summary of the written result ``out`` from the runs it holds (``--reaggregate``): every scene's
    block (:func:`summarise`: the means over runs and the paired gains, run-clustered) and ``<out>.md``; the runs, the
    settings and the provenance of the missions stay as they were, the aggregation's own provenance goes to
    ``"aggregation"``. Nothing is run or scored again.

    Returns:
        the rewritten result.
    Raises:
        FileNotFoundError: no such file. KeyError: a file without ``runs`` and ``scenes`` (not a realtime result).
    """
    result = json.loads(Path(out).read_text())
    budgets = [float(b) for b in result["settings"]["budgets"]]
    for scene, blk in result["scenes"].items():
        result["scenes"][scene] = summarise(result["runs"], scene, budgets, blk["cap"])
    result["failed_runs"] = failure_rows(result["runs"], RUN_KEYS)
    result["aggregation"] = provenance("realtime", argv)
    write_json(out, result, "realtime", argv, indent=1)
    md = _tables(result, Path(out))
    Path(out).with_suffix(".md").write_text(md + "\n")
    print(md)
    return result


def _write_result(args: argparse.Namespace, runs: list[dict], names: dict, budgets: list[float], protocols: tuple,
                  out: Path, t0: float, argv: Optional[list[str]] = None) -> None:
    """Write the JSON (with the run's provenance, :func:`bench._results.write_json`), the markdown tables and one
    plot per scene with several budgets; print the tables."""
    result = {"settings": {"budgets": budgets, "runs": args.runs, "clock": args.clock, "overrides": args.overrides,
                           "reference_budget_s": REFERENCE_BUDGET_S, "machine": platform.machine(),
                           "cpus": os.cpu_count(), "wall_s": time.time() - t0, "protocols": list(protocols),
                           "track_iters": args.track_iters, "track_stride": args.track_stride, "late": args.late,
                           "novel_every": args.novel_every, "pose_source": args.pose_source,
                           "score_at": args.score_at, "resolution": args.resolution,
                           "shared_resolution": _shared_resolutions(runs),
                           "late_via": args.late_via if args.late else None, "dataset": args.dataset},
              "scenes": {}, "failed_runs": failure_rows(runs, RUN_KEYS), "runs": runs}
    for scene, cap in names.items():
        blk = summarise(runs, scene, budgets, cap)
        result["scenes"][scene] = blk
        if len(blk["budgets"]) > 1:
            plot_scene(blk, scene, out.with_name(f"{out.stem}_{scene}.png"))
    write_json(out, result, "realtime", argv, indent=1)
    md = _tables(result, out)
    out.with_suffix(".md").write_text(md + "\n")
    print(md)


def _tables(result: dict, out: Path) -> str:
    """A result's markdown: the table, the protocols' table and, when its runs were scored under the sensor protocol,
    each scene's per-keyframe trace (also plotted beside ``out``: ``<stem>_trace_<scene>_<budget>.png``)."""
    md = table(result) + "\n\n" + protocol_table(result)
    traces = trace_tables(result)
    if traces:
        md += "\n\n## Per-keyframe trace\n\n" + traces
        for scene in result["scenes"]:
            for b in result["settings"]["budgets"]:
                plot_trace(result["runs"], scene, float(b), out.with_name(f"{out.stem}_trace_{scene}_{float(b):g}.png"))
    return md
