"""How much GaussLite gains with the compute its mapper gets: the live real-time protocol (``bench.realtime``) over a
grid of compute cells, every map scored at the scene's own resolution. See ``docs/realtime.md#compute-sweep``.

    python -m bench.compute_sweep [--cells t1-b0.25,t1-b0.5,t1-b1,t2-b0.25,t2-b0.5,t2-b1,single,multi]
                                  [--scenes tum_fr1_rpy,tum_fr1_rpy_cup] [--runs 3] [--jobs 2]
                                  [--work /tmp/gausslite_bench_compute_sweep] [--out bench/results/compute_sweep.json]
                                  [any option of bench.realtime: --set KEY=VALUE, --protocols, --dataset PATH ...]

A cell is the compute one mission gets: the rasterizer's band threads (``mapper.performance.render_threads``, the
product's knob), the keyframe budget (seconds of wall time per keyframe, ``--clock scaled`` as bench.realtime: every
budget covers 0.5 s of the sequence per keyframe) and, optionally, a CPU-bound process running beside the agent:

- ``t<threads>-b<budget>``: the agent alone, e.g. ``t1-b0.25``;
- ``t<threads>-b<budget>-single``: beside a single-threaded busy loop (one core taken);
- ``t<threads>-b<budget>-multi``: beside a matrix-product loop whose BLAS threads cover every core;
- ``single`` / ``multi``: ``t2-b0.5-single`` / ``t2-b0.5-multi``.

The missions of every cell run first, one at a time (they are wall-clock measurements; nothing else should run on
the machine), each cell through ``bench.realtime --missions-only`` into ``<work>/cells/<cell>.json``; a cell's load
process is started before its missions and killed after them, also when a mission fails (and it ends itself when
this process dies). Then every saved map is scored (``bench.realtime --score-only``, ``--jobs`` processes) at the
scene's own resolution (``--score-at scene``: the dataset as the scene spec loads it, e.g. TUM at 320×240), whatever
mapping resolution the agent's governor chose, so that GaussLite and uniform pair within every cell and cells compare
on the same pixels. Scoring protocols ``sensor,novel`` unless ``--protocols`` is given.

Writes ``bench/results/compute_sweep.{json,md}`` (per scene and cell: iterations per keyframe of both modes, the mapping
sizes, both modes' ROI PSNR and the ``novel`` ROI gain GaussLite − uniform with its run-clustered interval,
:func:`gausslite.stats.paired_gain`; every mission's figures and each run's paired gain) and
``compute_sweep.png`` (the gain against GaussLite's iterations per keyframe).

Failed missions (:mod:`bench._missions`): every cell's missions run to the end whatever fails (``bench.realtime
--allow-failed``); each mission's ``end_state`` and ``error`` go to its run record, a failed one is left out of the
figures and pairs (as ``bench.realtime`` leaves it out), its cell is marked † in the table, and the sweep exits 1 once
the result is written unless ``--allow-failed``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator, Optional

from tqdm import tqdm

from gausslite.evaluation import current_protocols
from gausslite.stats import aggregate, fmt, paired_gain

from bench._missions import FAILED_MARK, OUTCOME_KEYS, add_allow_failed, exit_code, failed_note, succeeded
from bench._results import write_results
from bench.realtime import cli as realtime_cli
from bench.realtime.missions import load_average
from bench.realtime.scenes import MODES
from bench.realtime.summary import pairable_runs
from bench.realtime.tables import gain_cell

RESULTS = Path(__file__).resolve().parents[1] / "bench" / "results"
THREADS = (1, 2)
BUDGETS = (0.25, 0.5, 1.0)
#: the cells beside a load process: (render threads, keyframe budget in seconds)
LOAD_CELL = (2, 0.5)
LOADS = ("single", "multi")
DEFAULT_CELLS = [f"t{t}-b{b:g}" for t in THREADS for b in BUDGETS] + list(LOADS)
DEFAULT_SCENES = "tum_fr1_rpy,tum_fr1_rpy_cup"
DEFAULT_PROTOCOLS = "sensor,novel"
#: seconds between starting a load process and the cell's first mission (interpreter and NumPy start-up)
LOAD_WARMUP_S = 1.0
#: side of the square float64 matrices the ``multi`` load multiplies (about 0.27 GFLOP a product)
MATMUL_SIZE = 512
#: bench.realtime options the sweep sets itself (per cell, or as its own options)
RESERVED = ("--budgets", "--runs", "--out", "--work", "--scenes", "--missions-only", "--score-only", "--resume",
            "--jobs", "--score-at", "--twin", "--score-inline", "--reaggregate", "--calibrate", "--modes",
            "--final-pass-budgets")
#: the load processes' programs (argument: the pid of the process that starts them): each loops until killed, or
#: until that process is gone (also when it died before the program read its parent)
LOAD_CODE = {
    "single": ("import os, sys\n"
               "parent = int(sys.argv[1])\n"
               "while os.getppid() == parent:\n"
               "    for _ in range(100000):\n"
               "        pass\n"),
    "multi": ("import os, sys\n"
              "import numpy as np\n"
              "parent = int(sys.argv[1])\n"
              f"a = np.random.default_rng(0).random(({MATMUL_SIZE}, {MATMUL_SIZE}))\n"
              "b = np.empty_like(a)\n"
              "while os.getppid() == parent:\n"
              "    np.matmul(a, a, out=b)\n"),
}


@dataclass(frozen=True)
class Cell:
    """One compute setting of the sweep.

    Attributes:
        name: its name on the command line and in the results (``t1-b0.25``, ``single``).
        threads: rasterizer band threads (``mapper.performance.render_threads``).
        budget: keyframe budget, seconds of wall time per keyframe.
        load: the process beside the agent: None, ``"single"`` or ``"multi"``.
    """

    name: str
    threads: int
    budget: float
    load: Optional[str] = None


def parse_cell(name: str) -> Cell:
    """The cell a name stands for: ``t<threads>-b<budget>[-single|-multi]``, or ``single`` / ``multi`` (the load
    beside :data:`LOAD_CELL`'s threads and budget).

    Raises:
        ValueError: a name of neither form, zero threads or a budget that is not positive.
    """
    if name in LOADS:
        return Cell(name, LOAD_CELL[0], LOAD_CELL[1], name)
    m = re.fullmatch(r"t(\d+)-b(\d+(?:\.\d*)?|\.\d+)(?:-(single|multi))?", name)
    if not m or int(m.group(1)) < 1 or float(m.group(2)) <= 0:
        raise ValueError(f"unknown cell {name!r}: t<threads>-b<budget>[-single|-multi], single or multi "
                         f"(threads >= 1, budget > 0 s)")
    return Cell(name, int(m.group(1)), float(m.group(2)), m.group(3))


def process_cpu_seconds(pid: int) -> Optional[float]:
    """CPU seconds (user + system, every thread) process ``pid`` has used so far, from ``/proc/<pid>/stat`` (Linux);
    None where it cannot be read."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def start_load(kind: str) -> subprocess.Popen:
    """Start the CPU-bound process ``kind`` (:data:`LOAD_CODE`): ``single`` a busy loop on one core, ``multi`` a
    NumPy matrix-product loop with as many BLAS threads as the machine has cores. It runs until killed, or until
    this process is gone.

    Raises:
        ValueError: an unknown kind.
    """
    if kind not in LOAD_CODE:
        raise ValueError(f"unknown load {kind!r} (known: {', '.join(LOAD_CODE)})")
    cores = str(os.cpu_count() or 1)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": cores, "OMP_NUM_THREADS": cores, "MKL_NUM_THREADS": cores}
    return subprocess.Popen([sys.executable, "-c", LOAD_CODE[kind], str(os.getpid())], env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def stop_load(proc: subprocess.Popen) -> None:
    """Kill a load process (SIGKILL: it has nothing to clean up) and reap it."""
    if proc.poll() is None:
        proc.kill()
    proc.wait(timeout=30)


@contextmanager
def load_process(kind: Optional[str]) -> Iterator[Optional[dict]]:
    """A load process (:func:`start_load`) running for the body of the ``with``: started, given
    :data:`LOAD_WARMUP_S` to get going, and killed when the body ends, whether it returns or raises.

    Yields:
        None without a load (``kind`` None), else its record, filled in when it stops: ``{"kind", "pid", "cpu_s",
        "wall_s", "cores_busy"}`` (CPU seconds it used, seconds it ran, their ratio: the cores it kept busy).
    Raises:
        RuntimeError: the process exited on its own before the body or during it (the missions ran without it).
    """
    if kind is None:
        yield None
        return
    proc = start_load(kind)
    rec = {"kind": kind, "pid": proc.pid, "cpu_s": None, "wall_s": None, "cores_busy": None}
    t0 = time.perf_counter()
    try:
        time.sleep(LOAD_WARMUP_S)
        if proc.poll() is not None:
            raise RuntimeError(f"the {kind} load process exited (code {proc.returncode}) before the missions")
        yield rec
        if proc.poll() is not None:
            raise RuntimeError(f"the {kind} load process exited (code {proc.returncode}) during the missions: "
                               f"they ran without their load")
    finally:
        rec["cpu_s"] = process_cpu_seconds(proc.pid)
        rec["wall_s"] = time.perf_counter() - t0
        stop_load(proc)
        if rec["cpu_s"] is not None:
            rec["cores_busy"] = rec["cpu_s"] / rec["wall_s"]


def cell_out(cell: Cell, work: Path) -> Path:
    """The bench.realtime result file of ``cell`` (its partial file, maps and renders beside it)."""
    return Path(work) / "cells" / f"{cell.name}.json"


def cell_args(cell: Cell, work: Path) -> list[str]:
    """The bench.realtime options of ``cell``: its budget, its render threads (the last ``--set``: it wins) and its
    result file."""
    return ["--budgets", f"{cell.budget:g}", "--set", f"mapper.performance.render_threads={cell.threads}",
            "--out", str(cell_out(cell, work))]


def _saved_runs(partial: Path) -> int:
    return len(json.loads(partial.read_text())["runs"]) if partial.is_file() else 0


def run_missions(cells: list[Cell], common: list[str], work: Path, resume: bool) -> None:
    """The live missions of every cell, one cell after another, each beside its load process
    (:func:`load_process`), saved unscored (``bench.realtime --missions-only``). Each cell's invocations, with the
    load's record and the load average before and after, go to ``<work>/cells/<cell>.missions.json``.

    Raises:
        RuntimeError: a load process that exited on its own. Whatever a mission raises (its cell's load is killed
            first).
    """
    for cell in tqdm(cells, desc="cells (missions)", unit="cell"):
        out = cell_out(cell, work)
        log_path = out.with_suffix(".missions.json")
        before = _saved_runs(out.with_suffix(".partial.json")) if resume else 0
        log = json.loads(log_path.read_text()) if resume and log_path.is_file() else []
        tqdm.write(f"cell {cell.name}: {cell.threads} render thread(s), {cell.budget:g} s per keyframe, "
                   f"load {cell.load or 'none'}")
        t0 = time.perf_counter()
        with load_process(cell.load) as load:
            load0 = load_average()
            # every mission runs, whatever fails: the sweep records failed ones and decides the exit code at the end
            realtime_cli.main([*common, *cell_args(cell, work), "--missions-only", "--allow-failed",
                               *(["--resume"] if resume else [])])
            load1 = load_average()
        log.append({"missions": _saved_runs(out.with_suffix(".partial.json")) - before, "load": load,
                    "load_avg_1m": [load0, load1], "wall_s": time.perf_counter() - t0})
        log_path.parent.mkdir(parents=True, exist_ok=True)
        log_path.write_text(json.dumps(log, indent=1))


def score_cells(cells: list[Cell], common: list[str], work: Path, jobs: int) -> None:
    """Score every cell's saved maps (``bench.realtime --score-only``, ``jobs`` processes).

    Raises:
        FileNotFoundError: a cell whose missions never ran.
    """
    for cell in tqdm(cells, desc="cells (scoring)", unit="cell"):
        if not cell_out(cell, work).with_suffix(".partial.json").is_file():
            raise FileNotFoundError(f"cell {cell.name} has no missions in {work}: run the sweep without --score-only")
        realtime_cli.main([*common, *cell_args(cell, work), "--score-only", "--allow-failed", "--jobs",
                           str(max(1, jobs))])


def sizes(run: dict) -> dict:
    """The image sizes a run's mission mapped at: ``{name: [width, height]}`` for every ``<name>_width`` /
    ``<name>_height`` pair of the governor's status (``mapping``, and any further resolution it reports), else the
    mapping size its settings record; pixels."""
    st = run.get("resolution_status") or {}
    out = {k[:-6]: [st[k], st[k[:-6] + "_height"]] for k in st if k.endswith("_width") and k[:-6] + "_height" in st}
    if not out and (run.get("mission") or {}).get("mapping_size"):
        out["mapping"] = run["mission"]["mapping_size"]
    return out


def _novel(run: dict) -> dict:
    return current_protocols(run.get("protocols")).get("novel") or {}


def run_row(cell: Cell, run: dict) -> dict:
    """The sweep's record of one mission: its cell (threads, budget, load), the render threads its mapper ran with,
    iterations per keyframe, ROI-phase iterations (in total and per keyframe), mapping size(s), the size it was
    scored at, the load average (1 min) at its start and end, and its ROI PSNR / PSNR under ``sensor`` and ``novel``
    (with the per-frame ROI PSNR ``novel`` pairs on, frame id → dB), and how its mission ended (``end_state``,
    ``error``, ``frames_failed``, ``corrections_rejected``, when the run records them)."""
    mission = run.get("mission") or {}
    novel = _novel(run)
    return {"cell": cell.name, "threads": cell.threads, "budget": cell.budget, "load": cell.load,
            "scene": run["scene"], "mode": run["mode"], "run": run["run"],
            "render_threads": mission.get("render_threads"), "iters_per_keyframe": run.get("iters_per_keyframe"),
            "keyframes": run.get("keyframes"), "roi_iters": run.get("roi_iters"),
            "roi_iters_per_keyframe": (run["roi_iters"] / max(1, run["keyframes"])
                                       if run.get("roi_iters") is not None and run.get("keyframes") else None),
            "idle_iters": run.get("idle_iters"), "n_gaussians": run.get("n_gaussians"),
            "mapping_size": mission.get("mapping_size"), "sizes": sizes(run), "score_at": run.get("score_at"),
            "scored_size": run.get("scored_size"), "load_avg_1m": run.get("load_avg_1m"), "wall_s": run.get("wall_s"),
            "roi_psnr": run.get("roi_psnr"), "psnr": run.get("psnr"),
            "novel": {"roi_psnr": novel.get("roi_psnr"), "psnr": novel.get("psnr"),
                      "roi_psnr_per_frame": novel.get("roi_psnr_per_frame")},
            **{k: run[k] for k in OUTCOME_KEYS if k in run}}


def pair_row(g: dict, u: dict, ok: bool) -> dict:
    """One run's pair (``g`` GaussLite, ``u`` uniform: :func:`run_row` records of the same cell, scene and run; ``ok``:
    whether they pair, :func:`bench.realtime.summary.pairable_runs`): both modes' iterations per keyframe, ROI
    iterations per keyframe, mapping sizes and load averages, and the run's ``novel`` ROI gain (the mean of its paired
    per-frame differences, dB; None when they do not pair)."""
    both = {"gausslite": g, "uniform": u}
    pg = paired_gain(g["novel"]["roi_psnr_per_frame"] or {}, u["novel"]["roi_psnr_per_frame"] or {}) if ok else {}
    return {"cell": g["cell"], "threads": g["threads"], "budget": g["budget"], "load": g["load"], "scene": g["scene"],
            "run": g["run"], "paired": bool(ok), "novel_gain": pg.get("gain"), "novel_frames": pg.get("n"),
            **{k: {m: r[k] for m, r in both.items()}
               for k in ("iters_per_keyframe", "roi_iters_per_keyframe", "sizes", "load_avg_1m")}}


def cell_summary(cell: Cell, block: dict, rows: list[dict]) -> dict:
    """One scene's figures in one cell: ``block`` is bench.realtime's summary of the cell's budget (means over runs,
    paired gains); ``rows`` the cell's :func:`run_row` records of the scene. Means and stds over runs of iterations
    per keyframe and ROI iterations per keyframe per mode, the mapping sizes seen, the size scored at, each protocol's
    ROI PSNR per mode and ROI gain (``gain``, ``gain_ci`` run-clustered over several runs, ``gain_std``,
    ``gain_interval``, ``gain_significant``, ``runs``, ``unpaired_runs``), the mean load average at the runs'
    ends and, when missions failed, ``failed_runs`` (mode → count). Failed missions' rows are left out."""
    rows = succeeded(rows)
    per_mode = {m: [r for r in rows if r["mode"] == m] for m in MODES}
    its = {m: aggregate(rs, ["iters_per_keyframe", "roi_iters_per_keyframe"]) for m, rs in per_mode.items() if rs}
    protocols = {}
    for p, pv in block.get("protocols", {}).items():
        protocols[p] = {"roi_psnr": {m: pv.get(m, {}).get("roi_psnr") for m in MODES},
                        "roi_psnr_std": {m: pv.get(m, {}).get("roi_psnr_std") for m in MODES},
                        **{k: pv.get(k) for k in ("gain", "gain_ci", "gain_std", "gain_interval", "gain_significant",
                                                  "gain_per_run", "runs", "unpaired_runs")}}
    ends = [r["load_avg_1m"][1] for r in rows if r.get("load_avg_1m") and r["load_avg_1m"][1] is not None]
    n_failed = {m: len(v) for m, v in (block.get("failed_runs") or {}).items() if v}
    return {"cell": cell.name, "threads": cell.threads, "budget": cell.budget, "load": cell.load,
            "runs": {m: len(rs) for m, rs in per_mode.items()}, **({"failed_runs": n_failed} if n_failed else {}),
            "iters_per_keyframe": {m: v["iters_per_keyframe"] for m, v in its.items()},
            "iters_per_keyframe_std": {m: v["iters_per_keyframe_std"] for m, v in its.items()},
            "roi_iters_per_keyframe": {m: v["roi_iters_per_keyframe"] for m, v in its.items()},
            "sizes": {m: sorted({f"{n} {w}x{h}" for r in rs for n, (w, h) in r["sizes"].items()})
                      for m, rs in per_mode.items()},
            "scored_size": sorted({tuple(r["scored_size"]) for r in rows if r.get("scored_size")}),
            "protocols": protocols, "load_avg_1m": sum(ends) / len(ends) if ends else None}


def collect(cells: list[Cell], work: Path) -> dict:
    """The sweep's result from the cells' scored bench.realtime results: ``{"cells": {cell: {"threads", "budget",
    "load", "missions"}}, "scenes": {scene: {cell: cell_summary}}, "runs": [run_row], "pairs": [pair_row]}``.

    Raises:
        FileNotFoundError: a cell not scored yet. KeyError: a cell result without its budget.
    """
    out: dict = {"cells": {}, "scenes": {}, "runs": [], "pairs": []}
    for cell in cells:
        path = cell_out(cell, work)
        res = json.loads(path.read_text())
        log = path.with_suffix(".missions.json")
        out["cells"][cell.name] = {**asdict(cell), "missions": json.loads(log.read_text()) if log.is_file() else []}
        rows = [run_row(cell, r) for r in res["runs"]]
        out["runs"] += rows
        for scene, blk in res["scenes"].items():
            mine = [r for r in rows if r["scene"] == scene]
            out["scenes"].setdefault(scene, {})[cell.name] = cell_summary(cell, blk["budgets"][f"{cell.budget:g}"],
                                                                           mine)
            raw = {m: {r["run"]: r for r in succeeded(res["runs"]) if r["scene"] == scene and r["mode"] == m}
                   for m in MODES}
            ok, _ = pairable_runs(raw["gausslite"], raw["uniform"], set(raw["gausslite"]) & set(raw["uniform"]))
            g = {r["run"]: r for r in succeeded(mine) if r["mode"] == "gausslite"}
            u = {r["run"]: r for r in succeeded(mine) if r["mode"] == "uniform"}
            out["pairs"] += [pair_row(g[i], u[i], i in ok) for i in sorted(set(g) & set(u))]
    return out


def table(result: dict, protocol: str = "novel") -> str:
    """Markdown table of a sweep: per scene and cell, both modes' iterations per keyframe, GaussLite's ROI-phase
    iterations per keyframe, the mapping sizes, both modes' ROI PSNR and the ROI gain under ``protocol``
    (:func:`bench.realtime.tables.gain_cell`), and the load average."""
    lines = [f"| scene | cell | threads | budget (s) | load | iters/kf GaussLite / uniform | ROI iters/kf GaussLite | "
             f"mapping size GaussLite / uniform | {protocol} ROI PSNR uniform | {protocol} ROI PSNR GaussLite | "
             f"{protocol} ROI gain | load avg (1 min) |", "|" + "---|" * 12]
    for scene, by_cell in result["scenes"].items():
        for name, s in by_cell.items():
            it, sd = s["iters_per_keyframe"], s["iters_per_keyframe_std"]
            pv = s["protocols"].get(protocol, {})
            psnr, psd = pv.get("roi_psnr", {}), pv.get("roi_psnr_std", {})
            size = " / ".join(", ".join(x.removeprefix("mapping ") for x in s["sizes"].get(m, [])) or "–"
                              for m in ("gausslite", "uniform"))
            mark = f" {FAILED_MARK}" if s.get("failed_runs") else ""
            lines.append(f"| {scene} | {name}{mark} | {s['threads']} | {s['budget']:g} | {s['load'] or 'none'} | "
                         f"{fmt(it.get('gausslite'), sd.get('gausslite'), 1)} / "
                         f"{fmt(it.get('uniform'), sd.get('uniform'), 1)} | "
                         f"{fmt(s['roi_iters_per_keyframe'].get('gausslite'), None, 1)} | {size} | "
                         f"{fmt(psnr.get('uniform'), psd.get('uniform'))} | "
                         f"{fmt(psnr.get('gausslite'), psd.get('gausslite'))} | {gain_cell(pv)} | "
                         f"{fmt(s['load_avg_1m'], None)} |")
    lines += ["", f"Every map scored at the scene's resolution ({_scored(result)}). ROI gain: GaussLite − uniform, "
              "paired frame by frame within each run: the mean of the per-run gains [95 % run-clustered interval], "
              "σ runs their spread; * the interval excludes zero. iters/kf: mean ± std over runs of the iterations "
              "each keyframe got. Mapping size: what the agent's governor chose (several: it changed between runs "
              "or the governor reports more than one resolution)."]
    if any(s.get("failed_runs") for by_cell in result["scenes"].values() for s in by_cell.values()):
        lines += ["", failed_note("cell with a run")]
    return "\n".join(lines)


def _scored(result: dict) -> str:
    sizes_ = sorted({f"{w}x{h}" for by_cell in result["scenes"].values() for s in by_cell.values()
                     for w, h in s["scored_size"]})
    return ", ".join(sizes_) or "–"


def plot(result: dict, path: Path, protocol: str = "novel") -> None:
    """The ROI gain under ``protocol`` against GaussLite's iterations per keyframe: one hollow marker per run (its
    paired gain), the cells' run-clustered gains joined by a line per scene (task), each labelled with its cell;
    marker shape by load (none ○, single □, multi △)."""
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    shape = {None: "o", "single": "s", "multi": "^"}
    fig, ax = plt.subplots(figsize=(7.0, 4.6))
    for (scene, by_cell), colour in zip(result["scenes"].items(), plt.rcParams["axes.prop_cycle"].by_key()["color"]):
        for p in result["pairs"]:
            if p["scene"] == scene and p["novel_gain"] is not None and p["iters_per_keyframe"]["gausslite"]:
                ax.scatter(p["iters_per_keyframe"]["gausslite"], p["novel_gain"], marker=shape[p["load"]],
                           facecolors="none", edgecolors=colour, s=22, lw=0.8)
        pts = sorted((s["iters_per_keyframe"].get("gausslite"), s["protocols"].get(protocol, {}).get("gain"), name,
                      s["load"]) for name, s in by_cell.items())
        pts = [q for q in pts if q[0] is not None and q[1] is not None]
        if pts:
            ax.plot([q[0] for q in pts], [q[1] for q in pts], color=colour, lw=1.2, label=scene)
            for x, y, name, load in pts:
                ax.scatter(x, y, marker=shape[load], color=colour, s=36, zorder=3)
                ax.annotate(name, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7, color=colour)
    for load in sorted({p["load"] for p in result["pairs"]}, key=lambda x: x or ""):
        ax.scatter([], [], marker=shape[load], color="0.4", label=f"load: {load or 'none'}")
    ax.axhline(0.0, color="k", lw=0.8, ls=":")
    ax.set_xlabel("GaussLite iterations per keyframe")
    ax.set_ylabel(f"{protocol} ROI gain, GaussLite − uniform (dB)")
    ax.set_title("ROI gain against compute (hollow: runs; filled: cells)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _parser() -> argparse.ArgumentParser:
    """The command line of ``python -m bench.compute_sweep`` (other options go to bench.realtime)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False,
                                 epilog="Any other option is passed to every bench.realtime invocation.")
    ap.add_argument("--cells", default=",".join(DEFAULT_CELLS),
                    help="t<threads>-b<budget>[-single|-multi], single, multi; comma-separated")
    ap.add_argument("--scenes", default=DEFAULT_SCENES, help="bench.realtime scenes (e.g. also synthetic_circle,room0)")
    ap.add_argument("--runs", type=int, default=3, help="runs (seeds) per cell, scene and mode")
    ap.add_argument("--jobs", type=int, default=2, help="worker processes of the scoring")
    ap.add_argument("--work", default="/tmp/gausslite_bench_compute_sweep",
                    help="the cells' bench.realtime results, saved maps and load records")
    ap.add_argument("--out", default=str(RESULTS / "compute_sweep.json"))
    ap.add_argument("--resume", action="store_true", help="continue the cells' missions where they stopped")
    ap.add_argument("--missions-only", action="store_true", help="run the missions, score nothing")
    ap.add_argument("--score-only", action="store_true", help="start no mission: score the saved maps and write")
    add_allow_failed(ap)
    return ap


def _checked(ap: argparse.ArgumentParser, args: argparse.Namespace, extra: list[str]) -> list[Cell]:
    """The cells of the command line; options the sweep sets itself among ``extra`` end the program."""
    taken = [t for t in extra if t.startswith("--") and any(r.startswith(t.split("=")[0]) for r in RESERVED)]
    if taken:
        ap.error(f"{', '.join(taken)}: set by the sweep itself (its own options: --cells, --scenes, --runs, --jobs, "
                 f"--work, --out, --resume, --missions-only, --score-only)")
    try:
        cells = [parse_cell(c) for c in args.cells.split(",") if c]
    except ValueError as e:
        ap.error(str(e))
    names = [c.name for c in cells]
    if not cells or len(set(names)) != len(names):
        ap.error(f"--cells needs distinct cells, got {args.cells!r}")
    if args.runs < 1:
        ap.error("--runs must be >= 1")
    return cells


def main(argv: Optional[list[str]] = None) -> int:
    """Run the sweep of the command line ``argv`` (``--help``); 0 on success."""
    ap = _parser()
    args, extra = ap.parse_known_args(argv)
    cells = _checked(ap, args, extra)
    work = Path(args.work)
    protocols = [] if any(t.split("=")[0] == "--protocols" for t in extra) else ["--protocols", DEFAULT_PROTOCOLS]
    common = ["--scenes", args.scenes, "--runs", str(args.runs), "--work", str(work), "--final-pass-budgets=",
              "--score-at", "scene", *protocols, *extra]
    if not args.score_only:
        run_missions(cells, common, work, args.resume)
        if args.missions_only:
            print(f"missions of {len(cells)} cells saved in {work}: score them with --score-only (same --work)")
            saved = []
            for c in cells:
                f = cell_out(c, work).with_suffix(".partial.json")
                saved += json.loads(f.read_text())["runs"] if f.is_file() else []
            return exit_code(saved, args.allow_failed, "bench.compute_sweep", ("scene", "mode", "budget", "run"))
    score_cells(cells, common, work, args.jobs)
    result = {"settings": {"cells": [asdict(c) for c in cells], "runs": args.runs, "jobs": args.jobs,
                           "score_at": "scene", "realtime_args": common, "cores": os.cpu_count(),
                           "load_warmup_s": LOAD_WARMUP_S, "matmul_size": MATMUL_SIZE},
              **collect(cells, work)}
    out = Path(args.out)
    md = table(result)
    write_results(out, "compute_sweep", argv, f": {len(cells)} cells, {args.runs} runs per cell, scene and mode, "
                  f"every map scored at the scene's resolution", md, result)
    plot(result, out.with_suffix(".png"))
    return exit_code(result["runs"], args.allow_failed, "bench.compute_sweep", ("cell", "scene", "mode", "run"))


if __name__ == "__main__":
    sys.exit(main())
