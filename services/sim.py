"""Local multi-process two-agent simulation (paper Sec. III-E, IV).

:func:`run_sim` starts the parser, the fusion server and two agents as separate processes on loopback
(``gausslite serve ...`` with free 127.0.0.1 ports), configured exactly like ``deploy/docker-compose.yml``
(same YAML file, same environment variables), gives the agents two different tasks on one scene,
waits for their missions (each replays its frames, pushes its ROI subset every k frames and at the
end), runs ``concat``, ``vote`` and ``vote + refine`` on the fusion server, downloads each fused map,
evaluates it and writes ``DIR/report.json``, ``DIR/report.md`` and ``DIR/renders/*.png``.

:func:`run_sim` with ``attach=...`` skips the process launch and drives already running services (the
compose ``report`` service does this). Processes are always terminated (SIGTERM, then SIGKILL) on
success, failure, SIGTERM or Ctrl-C; their logs are in ``DIR/logs``.

Fused-map ROI PSNR of a task = mean over that task's agent's frames of the PSNR restricted to the task's
ground-truth ROI mask (frames whose ROI is empty are skipped), rendering the fused map at those views.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import grpc
import numpy as np
import yaml

from gausslite.config import GaussLiteConfig, load_config
from gausslite.datasets import detect_layout, load_dataset
from gausslite.datasets.annotations import load_annotations
from gausslite.evaluation import PROTOCOLS, evaluate_fused, render_map, score_map, side_by_side
from gausslite.fusion.diagnose import RoiView, cover_image, roi_cover
from gausslite.fusion.vote import voxel_vote
from gausslite.mission.config import AgentConfig
from gausslite.synthetic import make_scene
from gausslite.wire.decode import assemble
from gausslite.wire.format import WireLimits
from gausslite_rpc import agent_pb2
from services.agent.client import AgentClient
from services.cli.cmd_health import check_health
from services.fusion_server.client import FusionClient
from services.fusion_server.store import SqliteFusionStore

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
AGENT_NAMES = ("agent_a", "agent_b")
FUSED_KEYS = ("concat", "vote", "for_robot", "refine")
#: what each fused key is, for the report
FUSED_HELP = {
    "concat": "plain concatenation of the agents' ROI subsets",
    "vote": "the team map: per-voxel κ vote (paper Sec. III-E)",
    "for_robot": "the team map as each robot uses it (`Fuse(for_agent=…)`): its own subset whole, and the others' "
                 "voted rows except those over its ROI; each task scored on the map made for its robot",
    "refine": "vote + joint refinement over the uploaded keyframes",
}


@dataclass
class AgentPlan:
    """One simulated agent: ``name`` (also its agent id), replayed ``dataset`` folder, ``task_id``, ``task``."""

    name: str
    dataset: str
    task_id: str
    task: str
    address: str = ""


@dataclass
class SimResult:
    """``report`` (the report.json dict), ``out`` folder, wall ``seconds``."""

    report: dict
    out: Path
    seconds: float
    pids: Dict[str, int] = field(default_factory=dict)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` right now (bind to port 0, read it, close)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def plan_agents(dataset: str, cfg: GaussLiteConfig, task_ids: Optional[List[str]] = None) -> List[AgentPlan]:
    """The two agents' datasets and tasks.

    Synthetic default scene (``dataset`` holds ``agent_a``/``agent_b``): each agent its own trajectory.
    Other datasets: both agents traverse the same frames. Tasks: ``task_ids`` or the config's
    ``sim.tasks`` pair for the scene (``synthetic`` / ``room0``), else the first two tasks of tasks.json.

    Raises:
        ValueError: the scene has no annotations or fewer than two tasks. KeyError: unknown task id.
    """
    root = Path(dataset)
    split = all((root / n).is_dir() for n in AGENT_NAMES)
    paths = [str(root / n) for n in AGENT_NAMES] if split else [str(root)] * 2
    ann = load_annotations(paths[0])
    if ann is None or len(ann.tasks) < 1:
        raise ValueError(f"{dataset}: the simulation needs objects.json/tasks.json with tasks")
    known = [t.id for t in ann.tasks]

    tasks_cfg = cfg.sim.tasks
    if not task_ids:
        for key in ("synthetic", "room0"):
            pair = tasks_cfg.get(key) or []
            if len(pair) == 2 and all(t in known for t in pair):
                task_ids = list(pair)
                break
    if not task_ids:
        if len(known) < 2:
            raise ValueError(f"{dataset}: need two tasks, tasks.json has {known}")
        task_ids = known[:2]
    if len(task_ids) != 2:
        raise ValueError(f"need exactly two task ids, got {task_ids}")
    return [AgentPlan(name, path, tid, ann.task_by_id(tid).text)
            for name, path, tid in zip(AGENT_NAMES, paths, task_ids)]


def _check_bags(plans: List[AgentPlan], agent_cfg: AgentConfig) -> None:
    """Open every ROS bag the agents will replay, so a bad bag fails with its one clear error before any
    process starts (``BagError`` lists the bag's topics and TF frames). ``agent_cfg``: the typed
    :class:`gausslite.mission.config.AgentConfig` (max_frames, bag options)."""
    for path in sorted({p.dataset for p in plans}):
        if detect_layout(path)[0] == "bag":
            ds = load_dataset(path, max_frames=agent_cfg.max_frames, bag=agent_cfg.bag)
            ds.close()


class ProcessGroup:
    """Child processes started by the simulation; :meth:`stop_all` terminates every one of them
    (SIGTERM, wait ``grace_s``, then SIGKILL). Only processes started here are touched."""

    def __init__(self, log_dir: Path):
        self.log_dir = log_dir
        self.procs: Dict[str, subprocess.Popen] = {}
        self._files = []

    def start(self, name: str, argv: List[str], env: Dict[str, str]) -> subprocess.Popen:
        """Start ``argv`` with ``env`` added to the environment; output goes to ``logs/<name>.log``."""
        self.log_dir.mkdir(parents=True, exist_ok=True)
        f = open(self.log_dir / f"{name}.log", "w")
        self._files.append(f)
        full_env = {**os.environ, **env, "PYTHONUNBUFFERED": "1"}
        full_env["PYTHONPATH"] = os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
        p = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, env=full_env, cwd=str(REPO),
                             start_new_session=True)
        self.procs[name] = p
        log.info("started %s (pid %d): %s", name, p.pid, " ".join(argv[2:]))
        return p

    def check_alive(self) -> None:
        """Raise RuntimeError naming a child that exited early (with the tail of its log)."""
        for name, p in self.procs.items():
            rc = p.poll()
            if rc is not None:
                tail = (self.log_dir / f"{name}.log").read_text(errors="replace")[-1500:]
                raise RuntimeError(f"{name} exited with code {rc}; log tail:\n{tail}")

    def stop_all(self, grace_s: float = 10.0) -> None:
        """Terminate all children (idempotent)."""
        for name, p in self.procs.items():
            if p.poll() is None:
                try:
                    p.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        deadline = time.monotonic() + grace_s
        for name, p in self.procs.items():
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s (pid %d) did not stop in %.0f s: killing", name, p.pid, grace_s)
                p.kill()
                p.wait(5)
        for f in self._files:
            f.close()
        self._files.clear()


def _cli(*args: str) -> List[str]:
    return [sys.executable, "-m", "gausslite.cli", *args]


def service_commands(config_path: Path, plans: List[AgentPlan], ports: Dict[str, int], data_dir: Path,
                     host: str = "127.0.0.1") -> Dict[str, tuple]:
    """``name → (argv, env)`` of the four services, mirroring the compose file's commands/environment."""
    parser_addr, fusion_addr = f"{host}:{ports['parser']}", f"{host}:{ports['fusion_server']}"
    cmds = {
        "parser": (_cli("serve", "parser", "--host", host, "--port", str(ports["parser"])), {}),
        "fusion_server": ([sys.executable, "-m", "services.fusion_server", "--host", host,
                           "--port", str(ports["fusion_server"])],
                          {"GAUSSLITE_DATA_DIR": str(data_dir / "fusion")}),
    }
    for p in plans:
        env = {"GAUSSLITE_AGENT_ID": p.name, "GAUSSLITE_PARSER_ADDR": parser_addr,
               "GAUSSLITE_FUSION_ADDR": fusion_addr, "GAUSSLITE_AGENT_DATASET": p.dataset,
               "GAUSSLITE_AGENT_TASK": p.task, "GAUSSLITE_AGENT_TASK_ID": p.task_id,
               "GAUSSLITE_DATA_DIR": str(data_dir / "agents")}
        cmds[p.name] = (_cli("serve", "agent", "--host", host, "--port", str(ports[p.name]),
                             "--config", str(config_path)), env)
    return cmds


def wait_healthy(target: str, service: str, timeout_s: float, group: Optional[ProcessGroup] = None) -> None:
    """Poll the health service of ``target`` until ``service`` is SERVING.

    Raises:
        TimeoutError: not SERVING in time. RuntimeError: a child process died meanwhile.
    """
    deadline = time.monotonic() + timeout_s
    status = "?"
    while time.monotonic() < deadline:
        if group is not None:
            group.check_alive()
        status = check_health(target, service, timeout_s=1.0)
        if status == "SERVING":
            return
        time.sleep(0.2)
    raise TimeoutError(f"{service} at {target} not healthy after {timeout_s:.0f} s (last: {status})")


def attach_context_baseline(report: dict, context_report: dict) -> dict:
    """Copy each agent's own-map ROI PSNR of a run mapped with ``mapper.roi_render: context`` (same
    scene and tasks, e.g. ``gausslite sim ... --set mapper.roi_render=context``) into ``report`` as
    ``own_roi_psnr_context``, and per task ``vote_minus_own_context`` (fused vote ROI PSNR minus it).

    Raises:
        ValueError: the context run used another roi_render mode, or its agents/tasks differ.
    """
    mode = ((context_report.get("settings") or {}).get("mapper") or {}).get("roi_render", "context")
    if mode != "context":
        raise ValueError(f"the context report was mapped with roi_render={mode!r}, not 'context'")
    ctx = {(a["id"], a["task"]): a.get("roi_psnr") for a in context_report.get("agents", [])}
    vote = (report.get("fused") or {}).get("vote", {}).get("roi_psnr_per_task", {})
    for a in report["agents"]:
        if (a["id"], a["task"]) not in ctx:
            raise ValueError(f"the context report has no agent {a['id']} on task {a['task']}")
        a["own_roi_psnr_context"] = ctx[(a["id"], a["task"])]
        v = vote.get(a["task"])
        a["vote_minus_own_context"] = (v - a["own_roi_psnr_context"]) if v is not None and a[
            "own_roi_psnr_context"] is not None else None
    return report


def attach_uniform_baseline(report: dict, baseline: dict) -> dict:
    """Put the own-map figures of a matched uniform run (the same sim with ``mapper.mode=uniform``: same scene,
    tasks, keyframe budget and Gaussian budget) beside each agent of ``report``: ``uniform_roi_psnr``,
    ``uniform_roi_psnr_all_frames`` (realtime runs), ``uniform_psnr``, ``uniform_n_gaussians`` and
    ``task_gain_db`` (this agent's ROI PSNR minus uniform's, over every frame for realtime runs).

    Raises:
        ValueError: the baseline was not mapped in uniform mode, or its agents/tasks differ.
    """
    mode = ((baseline.get("settings") or {}).get("mapper") or {}).get("mode")
    if mode != "uniform":
        raise ValueError(f"the baseline report was mapped with mapper.mode={mode!r}, not 'uniform'")
    base = {(a["id"], a["task"]): a for a in baseline.get("agents", [])}
    for a in report["agents"]:
        b = base.get((a["id"], a["task"]))
        if b is None:
            raise ValueError(f"the baseline report has no agent {a['id']} on task {a['task']}")
        a["uniform_roi_psnr"] = b.get("roi_psnr")
        a["uniform_roi_psnr_all_frames"] = b.get("roi_psnr_all_frames")
        a["uniform_psnr"] = b.get("psnr")
        a["uniform_n_gaussians"] = b.get("n_gaussians")
        own, uni = ((a.get("roi_psnr_all_frames"), b.get("roi_psnr_all_frames")) if report.get("realtime")
                    else (a.get("roi_psnr"), b.get("roi_psnr")))
        a["task_gain_db"] = (own - uni) if own is not None and uni is not None else None
    report["uniform_baseline"] = True
    return report


def _baseline_lines(report: dict) -> List[str]:
    """Markdown of the matched uniform baseline (``gausslite sim --baseline uniform``)."""
    if not report.get("uniform_baseline"):
        return []
    col = "ROI PSNR, all frames" if report.get("realtime") else "ROI PSNR, mapped frames"
    lines = ["", "## What the task buys: GaussLite against matched uniform agents", "",
             f"| agent | task | GaussLite {col} | uniform {col} | gain (dB) | GaussLite PSNR | uniform PSNR | "
             "Gaussians (GaussLite / uniform) |", "|---|---|---|---|---|---|---|---|"]
    for a in report["agents"]:
        own = a.get("roi_psnr_all_frames") if report.get("realtime") else a.get("roi_psnr")
        uni = a.get("uniform_roi_psnr_all_frames") if report.get("realtime") else a.get("uniform_roi_psnr")
        lines.append(f"| {a['id']} | {a['task']} | {_fmt(own)} | {_fmt(uni)} | {_fmt(a.get('task_gain_db'))} | "
                     f"{_fmt(a.get('psnr'))} | {_fmt(a.get('uniform_psnr'))} | {a['n_gaussians']} / "
                     f"{a.get('uniform_n_gaussians', '–')} |")
    lines += ["", "The uniform agents ran the same sim with `mapper.mode=uniform` (same scene, keyframe rule, keyframe "
              "budget and Gaussian budget; they share nothing). `docs/realtime.md` has the budget sweep."]
    return lines


def plot_pushes(report: dict, path: Path) -> bool:
    """Plot bytes per push and share of the map over time (frames mapped) for every agent into
    ``path`` (PNG). Returns False when no agent logged a push."""
    agents = [a for a in report["agents"] if a.get("push_log")]
    if not agents:
        return False
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    for a in agents:
        log_ = a["push_log"]
        x = [q["frames_mapped"] for q in log_]
        ax1.plot(x, [q["bytes_sent"] / 1024 for q in log_], "o-", label=a["id"])
        for q, xi in zip(log_, x):
            ax1.annotate("Δ" if q["delta"] else "full", (xi, q["bytes_sent"] / 1024), fontsize=7,
                         textcoords="offset points", xytext=(0, 4), ha="center")
        ax2.plot(x, [q["share_pct"] for q in log_], "o-", label=a["id"])
    ax1.set(xlabel="frames mapped", ylabel="KiB sent", title="bytes per push")
    ax2.set(xlabel="frames mapped", ylabel="% of the agent's map", title="shared subset")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


def fuse_settings(cfg: GaussLiteConfig, realtime: bool = False) -> dict:
    """The simulation's fusion settings (:meth:`gausslite.config.SimFuse.settings` of ``cfg.sim.fuse``): live
    runs (``realtime``) contest with ``live_contest_radius`` (default 0, the paper's per-voxel rule): measured
    live, the neighbourhood contest empties an owner's voxels next to another robot's denser task region
    (``docs/sharing.md``)."""
    return cfg.sim.fuse.settings(realtime)


class FusedTimeline:
    """The fused map while the robots map: whenever an agent's latest complete subset changes on the fusion server,
    a vote fuse (no refinement) is run and the fused map downloaded; :meth:`scores` scores them afterwards, so the
    scoring takes nothing from the missions.

    Args:
        fusion: a ``FusionClient``. voxel_size: δ (m). contest_radius: vote neighbourhood (voxels).
    """

    def __init__(self, fusion, voxel_size: float, contest_radius: int) -> None:
        self.fusion, self.voxel_size, self.contest_radius = fusion, voxel_size, contest_radius
        self.versions: Dict[str, int] = {}
        self.maps: list = []  # (seconds since the start, {agent: version}, GaussianArrays)

    def poll(self, t: float) -> bool:
        """Fuse and download when a subset changed since the last call (``t``: seconds since the sim started).
        Returns True when it fused. A fusion error is logged and skipped (the timeline is a diagnostic)."""
        try:
            agents = self.fusion.stats().get("agents", {})
            latest = {a: int(v["latest_map_version"]) for a, v in agents.items() if v.get("has_complete_subset")}
            if not latest or latest == self.versions:
                return False
            res = self.fusion.fuse("vote", voxel_size=self.voxel_size, contest_radius=self.contest_radius)
            maps = {"": self.fusion.download_fused(res.fused_version)}
            for a in sorted(latest):  # the team map as each robot uses it
                r = self.fusion.fuse("vote", voxel_size=self.voxel_size, contest_radius=self.contest_radius, for_agent=a)
                maps[a] = self.fusion.download_fused(r.fused_version)
            self.maps.append((t, dict(latest), maps))
            self.versions = latest
            return True
        except Exception as e:  # noqa: BLE001 - a diagnostic must not fail the simulation
            log.warning("fused timeline: fuse at %.0f s failed: %s", t, e)
            return False

    def scores(self, frames_by_task: Dict[str, tuple], backend: str = "auto", stride: int = 5,
               task_of: Optional[Dict[str, str]] = None) -> List[dict]:
        """``[{"t": s, "versions": {...}, "n_gaussians": N, "roi_psnr": {task: dB}, "roi_psnr_for_robot": {task:
        dB}}]``: every fused team map scored on each task's ROI (every ``stride``-th frame of ``frames_by_task[task] =
        (dataset, frames)``), and each task on the map made for its robot (``task_of``: agent id → task id)."""
        out = []
        for t, versions, maps in self.maps:
            g = maps[""].to_gaussian_map()
            row = {"t": t, "versions": versions, "n_gaussians": len(maps[""]),
                   "roi_psnr": {k: evaluate_fused(g, fr[::stride], ds.annotations, k, backend)
                                for k, (ds, fr) in frames_by_task.items()}, "roi_psnr_for_robot": {}}
            for a, task in (task_of or {}).items():
                if a in maps and task in frames_by_task:
                    ds, fr = frames_by_task[task]
                    row["roi_psnr_for_robot"][task] = evaluate_fused(maps[a].to_gaussian_map(), fr[::stride],
                                                                     ds.annotations, task, backend)
            out.append(row)
        return out


def fused_protocols(gmap, frames: list, annotations, task_id: str, sensor_roi_psnr: Optional[float], scoring,
                    keyframe_poses: Dict[int, np.ndarray], backend: str = "auto") -> dict:
    """One fused map's figures on one task under the scoring protocols of ``scoring`` (a
    :class:`gausslite.mission.config.ScoringConfig`), as its robot's own map is scored
    (docs/realtime.md#scoring-protocols): ``sensor`` is ``sensor_roi_psnr`` (:func:`evaluate_fused` over every frame
    at the sensor's pose); ``keyframes`` the frames of ``keyframe_poses`` (frame id → (4, 4) camera-to-world: the
    keyframes the task's robot uploaded, at the refined poses they carry), ``tracked`` every ``track_stride``-th
    frame at a pose and exposure fitted against the fused map from the sensor's pose
    (:func:`gausslite.evaluation.score_map`).

    Returns:
        ``{protocol: {"roi_psnr": dB or None, "frames_scored": n}}``.
    """
    rest = [q for q in scoring.chosen() if q != "sensor"]
    out = {"sensor": {"roi_psnr": sensor_roi_psnr, "frames_scored": len(frames)}}
    if rest:
        res = score_map(gmap, frames, lambda fr: annotations.roi_mask(task_id, fr.depth, fr.c2w, fr.intrinsics),
                        rest, track_iters=scoring.track_iters, track_stride=scoring.track_stride,
                        keyframe_poses=keyframe_poses, backend=backend)
        out.update({q: {"roi_psnr": v["roi_psnr"], "frames_scored": v["frames_scored"]} for q, v in res.items()})
    return out


def _protocol_minus_own(report: dict) -> None:
    """Each fused map's ``protocols[q][task]["minus_own"]``: its ROI PSNR minus the task's robot's own map under the
    same protocol (the agent's ``protocols[q]``)."""
    own = {a["task"]: a.get("protocols") or {} for a in report["agents"]}
    for f in (report.get("fused") or {}).values():
        for q, per_task in (f.get("protocols") or {}).items():
            for t, v in per_task.items():
                o = (own.get(t, {}).get(q) or {}).get("roi_psnr")
                v["minus_own"] = (v["roi_psnr"] - o) if v.get("roi_psnr") is not None and o is not None else None


def roi_cover_report(out: Path, plans: List[AgentPlan], eval_frames: Dict[str, tuple], fz: dict,
                     backend: str = "auto", stride: int = 2) -> dict:
    """What covers each robot's ROI in the team (vote) map (:func:`gausslite.fusion.diagnose.roi_cover`): the final
    subsets are read from the fusion server's store in ``out/data/fusion`` and voted again with the sim's settings
    (the same vote as the server's), and scored on every ``stride``-th frame of each robot's sequence with its task's
    ground-truth ROI. Writes ``renders/cover_<task>.png`` (the others' blending weight in red, the ROI in green).

    Returns:
        agent id → the diagnosis (``mass``, ``foreign``, ``top_foreign`` (5), ``own_missing``) plus ``image``.
    """
    store = SqliteFusionStore(out / "data" / "fusion")
    try:
        subsets = {a: assemble(store.chunk_data(a, v), WireLimits())[0] for a, v in store.latest_complete().items()}
    finally:
        store.close()
    fused, rep = voxel_vote(subsets, fz["voxel_size"], contest_radius=fz["contest_radius"])
    views = {}
    for p in plans:
        ds, frames = eval_frames[p.name]
        vs = []
        for fr in frames[::stride]:
            roi = ds.annotations.roi_mask(p.task_id, fr.depth, fr.c2w, fr.intrinsics)
            if roi.any():
                vs.append(RoiView.from_frame(fr, roi))
        views[p.name] = vs
    cov = roi_cover(subsets, fused, rep.source_agent, rep.source_row, views, top=5, backend=backend)
    agents = list(rep.agents)
    for p in plans:
        if p.name in cov and views[p.name]:
            rel = f"renders/cover_{p.task_id}.png"
            view = views[p.name][len(views[p.name]) // 2]
            cv2.imwrite(str(out / rel), cover_image(fused, rep.source_agent != agents.index(p.name), view, backend))
            cov[p.name]["image"] = rel
    return cov


def plot_fused_timeline(report: dict, path: Path) -> bool:
    """PNG of the vote-fused team map's ROI PSNR per task over the simulation's time (dotted: on the team map as the
    task's robot uses it), with each agent's own final ROI PSNR as a dashed line. Returns False when there is nothing to plot."""
    tl = report.get("fused_timeline") or []
    if not tl:
        return False
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    for a in report["agents"]:
        pts = [(e["t"], e["roi_psnr"].get(a["task"])) for e in tl if e["roi_psnr"].get(a["task"]) is not None]
        if not pts:
            continue
        line, = ax.plot(*zip(*pts), "o-", ms=3, label=f"team map, {a['task']}")
        rp = [(e["t"], (e.get("roi_psnr_for_robot") or {}).get(a["task"])) for e in tl]
        rp = [q for q in rp if q[1] is not None]
        if rp:
            ax.plot(*zip(*rp), "s:", ms=3, color=line.get_color(), label=f"team map for {a['id']}")
        own = a.get("roi_psnr_all_frames") if report.get("realtime") else a.get("roi_psnr")
        if own is not None:
            ax.axhline(own, ls="--", lw=1, color=line.get_color(), label=f"{a['id']} own map (end)")
    ax.set_xlabel("simulation time (s)")
    ax.set_ylabel("ROI PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def _timeline_lines(report: dict) -> List[str]:
    """Markdown of the fused map over time (one vote after each new subset)."""
    tl = report.get("fused_timeline") or []
    if not tl:
        return []
    tasks = [a["task"] for a in report["agents"]]
    robot = any(e.get("roi_psnr_for_robot") for e in tl)
    lines = ["", "## The fused map while mapping", "",
             "A vote fuse after each new subset on the server (no refinement), scored on every fifth frame: the team "
             "map" + (", and (→ robot) each task on the team map as its robot uses it (`Fuse(for_agent=…)`)" if robot
                      else "") + ":", "",
             "| time (s) | subset versions | Gaussians | " + " | ".join(tasks)
             + ("".join(f" | {t} → robot" for t in tasks) if robot else "") + " |",
             "|---|---|---|" + "---|" * (len(tasks) * (2 if robot else 1))]
    for e in tl:
        vs = ", ".join(f"{a} v{v}" for a, v in sorted(e["versions"].items()))
        cells = [_fmt(e["roi_psnr"].get(t)) for t in tasks]
        if robot:
            cells += [_fmt((e.get("roi_psnr_for_robot") or {}).get(t)) for t in tasks]
        lines.append(f"| {e['t']:.0f} | {vs} | {e['n_gaussians']} | " + " | ".join(cells) + " |")
    if report.get("fused_timeline_plot"):
        lines += ["", f"![fused ROI PSNR over time]({report['fused_timeline_plot']})"]
    return lines


def _protocol_lines(report: dict) -> List[str]:
    """Markdown of the own and fused maps under each scoring protocol (docs/realtime.md#scoring-protocols)."""
    agents = report["agents"]
    names = sorted(dict.fromkeys(q for a in agents for q in (a.get("protocols") or {})), key=_protocol_order)
    if not names:
        return []
    tasks = [a["task"] for a in agents]
    stride = int(((report.get("settings") or {}).get("scoring") or {}).get("track_stride", 5))
    lines = ["", "## Own and fused maps under each scoring protocol", "",
             "ROI PSNR (dB) on each task's ROI; each fused cell in brackets: its difference to the robot's own map under "
             "the same protocol. `sensor`: every frame at the sensor's pose (the figures above); `keyframes`: the own "
             "map on its keyframes at their refined pose and exposure, a fused map on the keyframes the robot uploaded "
             f"at the refined poses they carry; `tracked`: {_every(stride)} at a pose and exposure fitted against the "
             "map (docs/realtime.md#scoring-protocols).", "",
             "| protocol | map | " + " | ".join(tasks) + " |", "|---|---|" + "---|" * len(tasks)]
    for q in names:
        own = {a["task"]: (a.get("protocols") or {}).get(q, {}) for a in agents}
        lines.append(f"| {q} | own | " + " | ".join(
            f"{_fmt(own[t].get('roi_psnr'))} ({own[t].get('frames_scored', 0)} frames)" for t in tasks) + " |")
        for key in FUSED_KEYS:
            per = ((report["fused"].get(key) or {}).get("protocols") or {}).get(q)
            if not per:
                continue
            cells = []
            for t in tasks:
                v = per.get(t) or {}
                mo = v.get("minus_own")
                cells.append(_fmt(v.get("roi_psnr")) + (f" ({mo:+.2f})" if mo is not None else ""))
            lines.append(f"| {q} | {key} | " + " | ".join(cells) + " |")
    return lines


def _protocol_order(name: str) -> int:
    """Report order of the scoring protocols (``sensor``, ``keyframes``, ``tracked``)."""
    return PROTOCOLS.index(name) if name in PROTOCOLS else len(PROTOCOLS)


def _every(n: int) -> str:
    """"every frame", "every 2nd frame", …, "every 5th frame"."""
    if n <= 1:
        return "every frame"
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"every {n}{suffix} frame"


def _cover_lines(report: dict) -> List[str]:
    """Markdown of what covers each robot's ROI in the team map (:func:`roi_cover_report`)."""
    cov = (report.get("fused") or {}).get("vote", {}).get("cover") or {}
    if not cov:
        return []
    lines = ["", "## What covers each robot's ROI in the team map", "",
             "Share of the ROI pixels' blending weight in the vote map drawn by the robot's own Gaussians, by the "
             "other robots' Gaussians whose centre lies in their own task region or only in their context, and left "
             "uncovered; the other robots' Gaussians over the ROI (weighted mean extent, share of their weight in front "
             "of the ROI surface); and the robot's own rows the vote dropped, with the share of its subset's ROI "
             "weight they carried (docs/sharing.md).", "",
             "| robot | own | others, in their task region | others, context | uncovered | others' extent (m) | "
             "others in front | own rows dropped | their ROI weight |", "|---|---|---|---|---|---|---|---|---|"]
    for a, c in cov.items():
        m, f, om = c["mass"], c["foreign"], c["own_missing"]
        lines.append(f"| {a} | {m['own']:.2f} | {m['foreign_task']:.2f} | {m['foreign_context']:.2f} | "
                     f"{m['uncovered']:.2f} | {_fmt(f.get('weighted_extent_m'))} | {_fmt(f.get('weight_in_front'))} | "
                     f"{om['rows']} of {om['of']} | {_fmt(om.get('weight_share'))} |")
    for a, c in cov.items():
        if c.get("image"):
            lines += ["", f"**{a}: the other robots' Gaussians over its ROI (red), ROI outline (green)**  ",
                      f"![cover {a}]({c['image']})"]
    return lines


def _fmt(v, nd=2) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f}"


def write_markdown(report: dict, path: Path) -> None:
    """Write the human-readable report (tables + render links)."""
    tasks = [a["task"] for a in report["agents"]]
    lines = ["# GaussLite two-agent simulation", "",
             f"Scene: `{report['scene']}` — {report['seconds']:.0f} s wall time.", "",
             "## Agents (own map, own task)", "",
             "| agent | task | ROI PSNR (dB) | Gaussians | shared | shared % | bytes / Gaussian | pushes | "
             "total upload bytes | final subset bytes | upload / final |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for a in report["agents"]:
        lines.append(f"| {a['id']} | {a['task']} | {_fmt(a['roi_psnr'])} | {a['n_gaussians']} | {a['n_shared']} | "
                     f"{_fmt(a['share_pct'])} | {_fmt(a['bytes_per_gaussian'])} | {a.get('pushes', 0)} | "
                     f"{a.get('total_upload_bytes', '–')} | {a.get('final_subset_bytes', '–')} | "
                     f"{_fmt(a.get('upload_ratio'))} |")
    if any("own_roi_psnr_context" in a for a in report["agents"]):
        lines += ["", "Own map with `roi_render: context` (this run's agents, or a run of the same sim mapped that "
                  "way) against the fused vote map:", "",
                  "| agent | task | own ROI PSNR, deployed | own ROI PSNR, context | fused vote | vote − own context |",
                  "|---|---|---|---|---|---|"]
        vote = report["fused"]["vote"]["roi_psnr_per_task"]
        for a in report["agents"]:
            lines.append(f"| {a['id']} | {a['task']} | {_fmt(a['roi_psnr'])} | {_fmt(a.get('own_roi_psnr_context'))} | "
                         f"{_fmt(vote.get(a['task']))} | {_fmt(a.get('vote_minus_own_context'))} |")
    lines += ["", "Pushes (bytes sent per push, `Δ` = delta push; share of the map when pushed):", ""]
    for a in report["agents"]:
        cells = ", ".join(f"{q['bytes_sent']} B{' Δ' if q['delta'] else ''} @ {q['share_pct']:.1f} %"
                          for q in a.get("push_log", []))
        lines.append(f"- {a['id']}: {cells or '–'}")
    if report.get("pushes_plot"):
        lines += ["", f"![bytes per push and share over time]({report['pushes_plot']})"]
    lines += _timeline_lines(report)
    lines += _live_lines(report)
    lines += _baseline_lines(report)
    lines += ["", "## Fused maps: ROI PSNR (dB) on each task's ROI", "",
              "Each cell: the fused map's ROI PSNR, and in brackets its difference to the robot's own map.", "",
              "| fused map | " + " | ".join(tasks) + " | mean | Gaussians | seconds |",
              "|---|" + "---|" * (len(tasks) + 3)]
    for key in FUSED_KEYS:
        f = report["fused"].get(key)
        if f is None:
            continue
        mo = f.get("minus_own") or {}
        per = " | ".join(_fmt(f["roi_psnr_per_task"].get(t)) + (f" ({mo[t]:+.2f})" if mo.get(t) is not None else "")
                         for t in tasks)
        lines.append(f"| {key} | {per} | {_fmt(f['roi_psnr_mean'])} | {f['n_gaussians']} | {_fmt(f['seconds'])} |")
    lines += [""] + [f"- `{k}`: {FUSED_HELP[k]}" for k in FUSED_KEYS if k in report["fused"]]
    lines += [f"- vote settings: δ = {report['settings']['voxel_size']} m, each voxel contested over its neighbourhood "
              f"of radius {report['settings'].get('contest_radius', 0)} voxels; refinement: "
              f"{report['settings']['refine_iters']} iterations."]
    lines += _protocol_lines(report)
    lines += _cover_lines(report)
    lines += ["", "## Renders (render | ground truth | task ROI)", ""]
    for r in report.get("renders", []):
        lines.append(f"**{r['fused']} — {r['task']} (frame {r['frame_id']})**  ")
        lines.append(f"![{r['fused']} {r['task']}]({r['path']})")
        lines.append("")
    path.write_text("\n".join(lines) + "\n")


def _generate_scene(out: Path, scene, progress: bool) -> str:
    """Generate the synthetic default scene (``scene``: :class:`gausslite.config.SimScene`) into ``out/scene`` and
    return that folder's path."""
    log.info("generating the synthetic default scene into %s", out / "scene")
    make_scene(out / "scene", seed=scene.seed, width=scene.width, height=scene.height, frames=scene.frames,
               progress=progress)
    return str(out / "scene")


def _start_services(out: Path, config_path: Path, plans: List[AgentPlan], group: ProcessGroup,
                    token: Optional[str]) -> Dict[str, str]:
    """Start the parser, the fusion server and the agents in ``group`` on free loopback ports, each waited for
    until its health service reports SERVING (120 s, agents 180 s).

    Returns:
        service name → ``host:port``.
    Raises:
        TimeoutError: a service not healthy in time. RuntimeError: a process died.
    """
    ports = {n: free_port() for n in ("parser", "fusion_server", *AGENT_NAMES)}
    addrs = {n: f"127.0.0.1:{p}" for n, p in ports.items()}
    cmds = service_commands(config_path, plans, ports, out / "data")
    tok = {"GAUSSLITE_TOKEN": token} if token else {}
    for name in ("parser", "fusion_server"):
        group.start(name, cmds[name][0], {**cmds[name][1], **tok})
    wait_healthy(addrs["parser"], "gausslite.v1.Parser", 120, group)
    wait_healthy(addrs["fusion_server"], "gausslite.v1.Fusion", 120, group)
    for p in plans:
        group.start(p.name, cmds[p.name][0], {**cmds[p.name][1], **tok})
    for p in plans:
        wait_healthy(addrs[p.name], "gausslite.v1.Agent", 180, group)
    return addrs


def _connect(addrs: Dict[str, str], plans: List[AgentPlan], token: Optional[str], fusion_token: Optional[str],
             clients: list):
    """Clients of the fusion server (waited for until ready, 60 s) and of each agent (``addrs``: service name →
    ``host:port``; each plan's ``address`` is set). Every client is appended to ``clients`` as soon as it exists,
    so the caller closes it whatever fails next.

    Returns:
        ``(fusion, agents)``: the ``FusionClient`` and agent id → ``AgentClient``.
    """
    for p in plans:
        p.address = addrs[p.name]
    fusion = FusionClient(addrs["fusion_server"], token=fusion_token or token, timeout_s=120.0)
    clients.append(fusion)
    fusion.wait_ready(60)
    agents = {p.name: AgentClient(p.address, token=token) for p in plans}
    clients.extend(agents.values())
    return fusion, agents


def _wait_for_missions(agents: dict, group: ProcessGroup, tracker: FusedTimeline, t0: float, deadline: float,
                       timeout_s: float) -> None:
    """Poll the agents' status every second until every mission is replayed or finished, vote-fusing whenever a new
    subset arrived (``tracker``: the fused map over time; ``t0``: the sim's ``perf_counter`` start) and logging
    progress every 5 s.

    Raises:
        RuntimeError: a mission failed or a process died. TimeoutError: past ``deadline`` (monotonic s).
        grpc.RpcError: an agent's status call failed (NOT_FOUND is waited out until the deadline).
    """
    done = {agent_pb2.MISSION_STATE_REPLAY_DONE, agent_pb2.MISSION_STATE_FINISHED}
    last_print = 0.0
    while True:
        group.check_alive()
        tracker.poll(time.perf_counter() - t0)
        try:
            sts = {n: c.status() for n, c in agents.items()}
        except grpc.RpcError as e:  # an attached agent that has not started its mission yet
            if e.code() != grpc.StatusCode.NOT_FOUND or time.monotonic() > deadline:
                raise
            time.sleep(1.0)
            continue
        for n, st in sts.items():
            if st.state == agent_pb2.MISSION_STATE_FAILED:
                raise RuntimeError(f"{n} mission failed: {st.last_error}")
        if time.monotonic() - last_print > 5.0 or all(st.state in done for st in sts.values()):
            last_print = time.monotonic()
            log.info("mapping: " + ", ".join(
                f"{n} {st.frames_mapped}/{st.frames_received or '?'} frames, {st.n_gaussians} G, "
                f"{st.pushes} pushes" for n, st in sts.items()))
        if all(st.state in done for st in sts.values()):
            return
        if time.monotonic() > deadline:
            raise TimeoutError(f"agents not done after {timeout_s:.0f} s")
        time.sleep(1.0)


def _finish_agents(agents: dict, deadline: float) -> dict:
    """Each agent's Finish summary (agent id → summary), within what is left until ``deadline`` (at least 10 s).

    Raises:
        RuntimeError: an agent's final push failed.
    """
    summaries = {}
    for n, c in agents.items():
        summaries[n] = c.finish(timeout_s=max(10.0, deadline - time.monotonic()))
        if not summaries[n].final_push_ok:
            raise RuntimeError(f"{n}: final push failed: {summaries[n].status.last_error}")
    return summaries


def _load_eval_frames(plans: List[AgentPlan], agent_cfg: AgentConfig) -> Dict[str, tuple]:
    """Agent id → ``(dataset, frames)``: each agent's sequence loaded as its agent replays it (``agent_cfg``: the
    typed :class:`gausslite.mission.config.AgentConfig`; downscale, max_frames, stride, bag options)."""
    eval_frames = {}
    for p in plans:
        ds = load_dataset(p.dataset, downscale=agent_cfg.downscale, max_frames=agent_cfg.max_frames,
                          stride=agent_cfg.stride, bag=agent_cfg.bag)
        eval_frames[p.name] = (ds, [ds[i] for i in range(len(ds))])
    return eval_frames


def _uploaded_keyframe_poses(fusion, plans: List[AgentPlan]) -> Dict[str, dict]:
    """Agent id → {frame id → (4, 4) camera-to-world}: the keyframes each robot uploaded, at the refined poses they
    carry (the ``keyframes`` protocol). An agent whose poses cannot be read is logged and left out."""
    import grpc

    kf_poses = {}
    for p in plans:
        try:
            kf_poses[p.name] = {int(k["frame_id"]): k["c2w"] for k in fusion.keyframe_poses(p.name)}
        except grpc.RpcError as e:
            log.warning("no keyframe poses of %s: %s", p.name, e.details())
    return kf_poses


def _fuse_maps(fusion, key: str, plans: List[AgentPlan], fz: dict):
    """Run the fusion of report key ``key`` (one of :data:`FUSED_KEYS`) on the server and download the result;
    ``for_robot`` fuses once per agent (``for_agent``). ``fz``: :func:`fuse_settings`.

    Returns:
        ``(gmaps, res)``: agent id → the fused ``GaussianMap`` its task is scored on, and the last fuse result.
    """
    method = "concat" if key == "concat" else "vote"
    gmaps, res = {}, None
    for p in (plans if key == "for_robot" else [None]):
        res = fusion.fuse(method, refine=(key == "refine"), refine_iters=fz["refine_iters"],
                          voxel_size=fz["voxel_size"], contest_radius=fz["contest_radius"] if method == "vote" else None,
                          for_agent=p.name if p is not None else None,
                          progress=(lambda f, m, k=key: log.info("  %s %3.0f%% %s", k, 100 * f, m)))
        g = fusion.download_fused(res.fused_version).to_gaussian_map()
        for q in ([p] if p is not None else plans):
            gmaps[q.name] = g
    return gmaps, res


def _write_fused_render(out: Path, key: str, gmap, frames: list, annotations, task_id: str,
                        backend: str) -> Optional[dict]:
    """Write ``out/renders/<key>_<task>.png`` (the fused map beside the frame, ROI outlined) at the frame with the
    task's largest ROI. Returns the report's render entry, or None when no frame shows the ROI."""
    import cv2

    mid = _roi_frame(frames, annotations, task_id)
    if mid is None:
        return None
    fr = frames[mid]
    roi = annotations.roi_mask(task_id, fr.depth, fr.c2w, fr.intrinsics)
    img = side_by_side(render_map(gmap, fr, backend), fr, roi)
    rel = f"renders/{key}_{task_id}.png"
    cv2.imwrite(str(out / rel), img)
    return {"fused": key, "task": task_id, "frame_id": int(fr.frame_id), "path": rel}


def _fuse_and_score(fusion, out: Path, plans: List[AgentPlan], eval_frames: Dict[str, tuple], fz: dict, scoring,
                    kf_poses: Dict[str, dict], backend: str):
    """Every fused map of :data:`FUSED_KEYS` made on the server, scored on each agent's task (ROI PSNR over its
    frames and under ``scoring``'s protocols, :func:`fused_protocols`) with a render per task in ``out/renders``.

    Returns:
        ``(fused, renders)``: key → the report's figures of that fused map, and the render entries.
    """
    from gausslite.evaluation import evaluate_fused

    fused: Dict[str, dict] = {}
    renders = []
    (out / "renders").mkdir(exist_ok=True)
    for key in FUSED_KEYS:
        log.info("fusing: %s", key)
        gmaps, res = _fuse_maps(fusion, key, plans, fz)
        per_task, protos = {}, {}
        for p in plans:
            gmap = gmaps[p.name]
            ds, frames = eval_frames[p.name]
            per_task[p.task_id] = evaluate_fused(gmap, frames, ds.annotations, p.task_id, backend)
            protos[p.task_id] = fused_protocols(gmap, frames, ds.annotations, p.task_id, per_task[p.task_id],
                                                scoring, kf_poses.get(p.name, {}), backend)
            render = _write_fused_render(out, key, gmap, frames, ds.annotations, p.task_id, backend)
            if render is not None:
                renders.append(render)
        vals = [v for v in per_task.values() if v is not None]
        fused[key] = {"roi_psnr_mean": float(np.mean(vals)) if vals else None, "roi_psnr_per_task": per_task,
                      "n_gaussians": int(res.n_gaussians), "seconds": float(res.seconds),
                      "fused_version": int(res.fused_version), "kept": dict(res.kept),
                      "protocols": {q: {t: protos[t][q] for t in protos} for q in scoring.chosen()}}
        log.info("  %s: %d Gaussians, ROI PSNR %s", key, res.n_gaussians, {k: _fmt(v) for k, v in per_task.items()})
    return fused, renders


def _agent_report(p: AgentPlan, s, st: dict, offline: Optional[Dict[str, Optional[float]]]) -> dict:
    """One agent's entry of ``report["agents"]`` from its Finish summary ``s``, the fusion server's stats of it
    ``st`` and the every-frame ROI PSNR of an offline run (``offline``: agent id → dB, or None)."""
    return {
        "id": p.name, "task": p.task_id, "task_text": p.task, "dataset": p.dataset,
        "roi_psnr": s.roi_psnr if s.has_roi_psnr else None, "psnr": s.psnr,
        "n_gaussians": int(s.status.n_gaussians), "n_shared": int(s.n_shared),
        "share_pct": float(st.get("share_pct", s.share_pct)),
        # agent-side figures: the server stores delta-rebuilt subsets losslessly
        "bytes_on_wire": int(s.bytes_on_wire),
        "bytes_per_gaussian": float(s.bytes_per_gaussian),
        "total_upload_bytes": int(s.total_upload_bytes),
        "final_subset_bytes": int(s.final_subset_bytes),
        "upload_ratio": (s.total_upload_bytes / s.final_subset_bytes) if s.final_subset_bytes else None,
        "push_log": [{"version": int(q.version), "n_shared": int(q.n_shared), "n_total": int(q.n_total),
                      "bytes_sent": int(q.bytes_sent), "delta": bool(q.delta), "records": int(q.records),
                      "removed": int(q.removed), "frames_mapped": int(q.frames_mapped),
                      "unchanged": bool(getattr(q, "unchanged", False)),
                      "share_pct": 100.0 * q.n_shared / q.n_total if q.n_total else 0.0}
                     for q in s.pushes],
        "pushes": int(s.status.pushes), "frames_mapped": int(s.status.frames_mapped),
        "seconds_per_frame": float(s.seconds_per_frame), "keyframes": int(st.get("keyframes", 0)),
        "frames_received": int(s.status.frames_received), "frames_keyframed": int(s.status.frames_keyframed),
        "frames_skipped": int(s.status.frames_skipped),
        "accept_latency_ms_p99": float(s.status.accept_latency_ms_p99),
        "keyframe_latency_s_p95": float(s.status.keyframe_latency_s_p95),
        "idle_iterations": int(s.status.idle_iterations),
        "keyframe_iterations": int(s.status.keyframe_iterations),
        "roi_psnr_all_frames": s.roi_psnr_all_frames if s.has_roi_psnr_all_frames else None,
        "frames_all": int(s.frames_all),
        "offline_roi_psnr_all_frames": (offline or {}).get(p.name),
        "protocols": {q: {"roi_psnr": v.roi_psnr if v.has_roi_psnr else None, "psnr": v.psnr,
                          "ssim": v.ssim, "frames_scored": int(v.frames_scored),
                          "roi_frames": int(v.roi_frames)}
                      for q, v in sorted(s.protocols.items(), key=lambda kv: _protocol_order(kv[0]))},
    }


def _fused_minus_own(report: dict) -> None:
    """Each fused map's ``minus_own[task]``: its ROI PSNR minus the task's robot's own map (every-frame figure in
    realtime runs, else the mapped frames')."""
    own = {a["task"]: a.get("roi_psnr_all_frames") if report["realtime"] else a.get("roi_psnr")
           for a in report["agents"]}
    for f in report["fused"].values():
        f["minus_own"] = {t: (v - own[t]) if v is not None and own.get(t) is not None else None
                          for t, v in f["roi_psnr_per_task"].items()}


def _write_report(report: dict, out: Path) -> None:
    """Write the plots (``pushes.png``, ``fused_over_time.png``, named in ``report`` when drawn), ``report.json``
    and ``report.md`` into ``out``."""
    if plot_pushes(report, out / "pushes.png"):
        report["pushes_plot"] = "pushes.png"
    if plot_fused_timeline(report, out / "fused_over_time.png"):
        report["fused_timeline_plot"] = "fused_over_time.png"
    (out / "report.json").write_text(json.dumps(report, indent=2))
    write_markdown(report, out / "report.md")
    log.info("wrote %s and %s (%.0f s)", out / "report.json", out / "report.md", report["seconds"])


def _close_all(clients: list, group: ProcessGroup, previous_sigterm) -> None:
    """Close the gRPC clients (errors ignored), stop the started processes and restore the SIGTERM handler."""
    for c in clients:
        try:
            c.close()
        except Exception:
            pass
    group.stop_all()
    if previous_sigterm is not None:
        signal.signal(signal.SIGTERM, previous_sigterm)


def run_sim(out: str | Path, dataset: Optional[str] = None, *, config: Optional[str | Path] = None,
            overrides: List[str] = (), task_ids: Optional[List[str]] = None, attach: Optional[Dict[str, str]] = None,
            timeout_s: Optional[float] = None, token: Optional[str] = None, fusion_token: Optional[str] = None,
            progress: bool = True,
            offline_report: Optional[str | Path] = None,
            context_report: Optional[str | Path] = None) -> SimResult:
    """Run the two-agent simulation and write the report.

    Stages: start the services (:func:`_start_services`, skipped with ``attach``), run the agents' missions
    (:func:`_wait_for_missions`, :func:`_finish_agents`), fuse and score (:func:`_fuse_and_score`), then write the
    report (:func:`_write_report`).

    Args:
        out: output folder (``report.json``, ``report.md``, ``renders/``, ``logs/``, ``config.yaml``, ``scene/``).
        dataset: scene folder; None → generate the synthetic default scene into ``out/scene``.
        config: GaussLite YAML (default ``deploy/gausslite.yaml``); ``overrides``: dotted ``key=value``.
        task_ids: the two agents' task ids (default from ``sim.tasks``).
        attach: ``{"parser", "fusion_server", "agent_a", "agent_b"} → host:port`` of running services
            (no processes started; the agents must already run their missions).
        timeout_s: overall bound (default ``sim.timeout_s``).
        token: bearer token for the services (also passed to started processes).
        fusion_token: this client's own token for the fusion server when it checks per-agent tokens
            (default ``token``; ``docs/security.md``).
        offline_report: folder or ``report.json`` of an earlier every-frame run on the same dataset; its
            agents' ROI PSNR is reported next to ``roi_psnr_all_frames`` (``agent.realtime`` runs).
        context_report: ``report.json`` of the same sim mapped with ``mapper.roi_render=context``:
            adds ``own_roi_psnr_context`` per agent (:func:`attach_context_baseline`). Without it, a run
            whose agents map with ``roi_render: context`` (the deployed setting) reports its own figures
            there.
    Returns:
        SimResult.
    Raises:
        TimeoutError, RuntimeError (a service died or failed), ValueError/FileNotFoundError (bad input).
    """
    t0 = time.perf_counter()
    offline = _load_offline(offline_report) if offline_report else None
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    typed = load_config(config, overrides)  # a typo fails here, before any process starts
    cfg = typed.to_yaml_dict()  # the effective tree: what the agents read (--config) and the report records
    timeout_s = float(timeout_s or typed.sim.timeout_s)
    deadline = time.monotonic() + timeout_s
    config_path = out / "config.yaml"
    config_path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    if dataset is None:
        dataset = _generate_scene(out, typed.sim.scene, progress)
    plans = plan_agents(dataset, typed, task_ids)
    _check_bags(plans, typed.agent)
    group = ProcessGroup(out / "logs")
    previous = None
    if attach is None and hasattr(signal, "SIGTERM") and _main_thread():
        previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    clients: list = []
    try:
        addrs = _start_services(out, config_path, plans, group, token) if attach is None else dict(attach)
        fusion, agents = _connect(addrs, plans, token, fusion_token, clients)
        # ---- run the missions; vote-fuse whenever a new subset arrived (the fused map over time)
        fz = typed.sim.fuse.settings(typed.agent.realtime)
        tracker = FusedTimeline(fusion, fz["voxel_size"], fz["contest_radius"])
        _wait_for_missions(agents, group, tracker, t0, deadline, timeout_s)
        summaries = _finish_agents(agents, deadline)
        tracker.poll(time.perf_counter() - t0)
        stats = fusion.stats().get("agents", {})
        # ---- fuse and score
        backend, scoring = typed.mapper.backend, typed.agent.scoring
        eval_frames = _load_eval_frames(plans, typed.agent)
        fused, renders = _fuse_and_score(fusion, out, plans, eval_frames, fz, scoring,
                                         _uploaded_keyframe_poses(fusion, plans), backend)
        timeline = tracker.scores({p.task_id: eval_frames[p.name] for p in plans}, backend,
                                  task_of={p.name: p.task_id for p in plans})
        # ---- the report
        report = {"scene": dataset, "seconds": time.perf_counter() - t0,
                  "agents": [_agent_report(p, summaries[p.name], stats.get(p.name, {}), offline) for p in plans],
                  "fused": fused, "renders": renders, "fused_timeline": timeline, "realtime": typed.agent.realtime,
                  "offline_report": str(offline_report) if offline_report else None,
                  "settings": {"voxel_size": fz["voxel_size"], "contest_radius": fz["contest_radius"],
                               "refine_iters": fz["refine_iters"], "scoring": scoring.model_dump(),
                               "config": str(config_path), "agent": cfg["agent"], "mapper": cfg["mapper"]}}
        _fused_minus_own(report)
        _protocol_minus_own(report)
        if attach is None:
            try:
                fused["vote"]["cover"] = roi_cover_report(out, plans, eval_frames, fz, backend)
            except Exception as e:  # noqa: BLE001 - a diagnostic must not fail the simulation
                log.warning("ROI cover diagnosis failed: %s", e)
        if context_report is not None:
            attach_context_baseline(report, json.loads(Path(context_report).read_text()))
        elif typed.mapper.roi_render == "context":
            attach_context_baseline(report, report)  # the agents themselves mapped with roi_render: context
        _write_report(report, out)
        return SimResult(report, out, report["seconds"], {n: p.pid for n, p in group.procs.items()})
    finally:
        _close_all(clients, group, previous)


def attach_offline_report(out: str | Path, offline_report: str | Path) -> dict:
    """Put the every-frame ROI PSNR of ``offline_report`` next to the realtime figures of the finished
    realtime simulation in ``out`` (rewrites ``out/report.json`` and ``out/report.md``; nothing is re-run).

    Raises:
        FileNotFoundError: missing reports. ValueError: ``out`` is not a realtime run, or ``offline_report``
            is one.
    """
    out = Path(out)
    p = out / "report.json"
    if not p.is_file():
        raise FileNotFoundError(f"no report.json in {out}")
    report = json.loads(p.read_text())
    if not report.get("realtime"):
        raise ValueError(f"{p} is not a realtime run (gausslite sim --realtime)")
    offline = _load_offline(offline_report)
    for a in report["agents"]:
        a["offline_roi_psnr_all_frames"] = offline.get(a["id"])
    report["offline_report"] = str(offline_report)
    p.write_text(json.dumps(report, indent=2))
    write_markdown(report, out / "report.md")
    return report


def _load_offline(path: str | Path) -> Dict[str, Optional[float]]:
    """Agent id → every-frame ROI PSNR of an earlier non-realtime ``report.json`` (or its folder): its
    ``roi_psnr_all_frames`` when present, else its ``roi_psnr`` (mean over the mapped frames, which are all
    frames in an every-frame run).

    Raises:
        FileNotFoundError: no report. ValueError: not a simulation report, or a realtime one.
    """
    p = Path(path)
    p = p / "report.json" if p.is_dir() else p
    if not p.is_file():
        raise FileNotFoundError(f"offline report not found: {p}")
    try:
        rep = json.loads(p.read_text())
        agents = rep["agents"]
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{p} is not a simulation report.json: {e}") from None
    if rep.get("realtime"):
        raise ValueError(f"{p} is a realtime run; give an every-frame run (gausslite sim without --realtime)")
    return {a["id"]: a.get("roi_psnr_all_frames", a.get("roi_psnr")) for a in agents}


def _live_lines(report: dict) -> List[str]:
    """Markdown of the live-ingest figures (realtime runs only)."""
    if not report.get("realtime"):
        return []
    src = report.get("offline_report")
    lines = ["", "## Live operation (realtime replay at the dataset clock)", "",
             "| agent | received | keyframed | skipped | accept p99 (ms) | keyframe latency p95 (s) | iters / keyframe | "
             "idle iters | ROI PSNR all frames, realtime (dB) | same, offline every-frame (dB) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for a in report["agents"]:
        lines.append(f"| {a['id']} | {a['frames_received']} | {a['frames_keyframed']} | {a['frames_skipped']} | "
                     f"{_fmt(a['accept_latency_ms_p99'])} | {_fmt(a['keyframe_latency_s_p95'])} | "
                     f"{_fmt(a.get('keyframe_iterations', 0) / max(a['frames_keyframed'], 1), 1)} | "
                     f"{a['idle_iterations']} | {_fmt(a['roi_psnr_all_frames'])} | "
                     f"{_fmt(a['offline_roi_psnr_all_frames'])} |")
    lines += ["", f"ROI PSNR over all {report['agents'][0]['frames_all']} frames of the sequence (skipped ones "
              "included) of each agent's final map on its own task. Offline column: "
              + (f"`{src}`." if src else "not given (pass `--offline-report DIR` of an every-frame `gausslite sim` "
                 "on the same dataset).")]
    return lines


def _roi_frame(frames: list, annotations, task_id: str) -> Optional[int]:
    """Index of the frame with the largest ROI of ``task_id`` (None when no frame shows it)."""
    best, idx = 0, None
    for i, fr in enumerate(frames):
        n = int(annotations.roi_mask(task_id, fr.depth, fr.c2w, fr.intrinsics).sum())
        if n > best:
            best, idx = n, i
    return idx


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _raise_interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")
