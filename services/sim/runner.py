"""The simulation run (:func:`run_sim`): services started (or attached), the agents' missions waited for while the
fused map is followed over time, every fused map made and scored, and the report written."""

from __future__ import annotations

import json
import logging
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import yaml

from gausslite.config import load_config
from gausslite.synthetic import make_scene
from gausslite.team import (agent_report, attach_context_baseline, fused_minus_own, load_eval_frames, load_offline,
                            own_map_files, protocol_minus_own, score_fused_maps, write_report)
from gausslite.team.harness import run_team
from gausslite_services.sim.launch import ProcessGroup, check_bags, main_thread, plan_agents, raise_interrupt
from gausslite_services.sim.scoring import fuse_on_server, roi_cover_report, uploaded_keyframe_poses
from gausslite_services.sim.team import ServiceTeam
from gausslite_services.sim.timeline import FusedTimeline

log = logging.getLogger("gausslite_services.sim")  # one logger for the whole simulation


@dataclass
class SimResult:
    """``report`` (the report.json dict), ``out`` folder, wall ``seconds``."""

    report: dict
    out: Path
    seconds: float
    pids: Dict[str, int] = field(default_factory=dict)


def run_sim(out: str | Path, dataset: Optional[str] = None, *, config: Optional[str | Path] = None,
            overrides: List[str] = (), task_ids: Optional[List[str]] = None, attach: Optional[Dict[str, str]] = None,
            timeout_s: Optional[float] = None, token: Optional[str] = None, fusion_token: Optional[str] = None,
            progress: bool = True,
            offline_report: Optional[str | Path] = None,
            context_report: Optional[str | Path] = None) -> SimResult:
    """Run the two-agent simulation and write the report.

    Stages: start the services (:class:`~gausslite_services.sim.team.ServiceTeam`; attached with ``attach``), drive
    the agents' missions (:func:`gausslite.team.harness.run_team`), fuse on the server and score
    (:func:`gausslite.team.scoring.score_fused_maps`), then write the report
    (:func:`gausslite.team.report.write_report`).

    Args:
        out: output folder (``report.json``, ``report.md``, ``renders/``, ``logs/``, ``config.yaml``, ``scene/``).
        dataset: scene folder; None → generate the synthetic default scene into ``out/scene``.
        config: GaussLite YAML of site settings (default: none, the models' measured defaults); ``overrides``: dotted ``key=value``.
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
    offline = load_offline(offline_report) if offline_report else None
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    typed, cfg, config_path = _sim_config(out, dataset, config, overrides)
    timeout_s = float(timeout_s or typed.sim.timeout_s)
    deadline = time.monotonic() + timeout_s
    stages = _Stages(t0)
    if dataset is None:
        dataset = _generate_scene(out, typed.sim.scene, progress)
    stages.mark("scene")
    plans = plan_agents(dataset, typed, task_ids)
    check_bags(plans, typed.agent)
    group = ProcessGroup(out / "logs")
    previous = None
    if attach is None and hasattr(signal, "SIGTERM") and main_thread():
        previous = signal.signal(signal.SIGTERM, raise_interrupt)
    team = ServiceTeam(out, config_path, plans, group, token, fusion_token, attach)
    try:
        team.start()
        stages.mark("services")
        fusion = team.fusion
        # ---- run the missions; vote-fuse whenever a new subset arrived (the fused map over time)
        fz = typed.sim.fuse.settings(typed.agent.realtime)
        tracker = FusedTimeline(fusion, fz["voxel_size"], fz["contest_radius"])
        # polled 4 times a second: the missions' end is seen within a quarter of a second, not a whole one
        summaries = run_team(team, timeout_s=max(1.0, deadline - time.monotonic()),
                             on_poll=lambda: tracker.poll(time.perf_counter() - t0), poll_s=0.25)
        tracker.poll(time.perf_counter() - t0)
        stages.mark("missions")
        stats = fusion.stats().get("agents", {})
        # ---- fuse and score
        backend, scoring = typed.mapper.backend, typed.agent.scoring
        eval_frames = load_eval_frames(plans, typed.agent)
        fused, renders = score_fused_maps(out, plans, eval_frames, scoring, uploaded_keyframe_poses(fusion, plans),
                                          backend, lambda key: fuse_on_server(fusion, key, plans, fz),
                                          {n: s.tracked_views for n, s in summaries.items()},
                                          {n: s.predicted_views for n, s in summaries.items()})
        tracker.poll(time.perf_counter() - t0)  # the team map made from the final subsets, when the server keeps one
        timeline = tracker.scores({p.task_id: eval_frames[p.name] for p in plans}, backend,
                                  task_of={p.name: p.task_id for p in plans})
        stages.mark("scoring")
        # ---- the report
        report = {"scene": dataset, "seconds": time.perf_counter() - t0,
                  "agents": [agent_report(p, summaries[p.name], stats.get(p.name, {}), offline) for p in plans],
                  "fused": fused, "renders": renders, "fused_timeline": timeline, "realtime": typed.agent.realtime,
                  "own_maps": own_map_files(out, [p.name for p in plans]),
                  "offline_report": str(offline_report) if offline_report else None,
                  "settings": {"voxel_size": fz["voxel_size"], "contest_radius": fz["contest_radius"],
                               "refine_iters": fz["refine_iters"], "scoring": scoring.model_dump(),
                               "config": str(config_path), "agent": cfg["agent"], "mapper": cfg["mapper"]}}
        fused_minus_own(report)
        protocol_minus_own(report)
        if attach is None:
            _diagnose_cover(fused, out, plans, eval_frames, fz, backend)
        stages.mark("cover")
        report["stages_s"] = stages.seconds
        if context_report is not None:
            attach_context_baseline(report, json.loads(Path(context_report).read_text()))
        elif typed.mapper.roi_render == "context":
            attach_context_baseline(report, report)  # the agents themselves mapped with roi_render: context
        write_report(report, out)
        return SimResult(report, out, report["seconds"], {n: p.pid for n, p in group.procs.items()})
    finally:
        team.close(previous)


def _sim_config(out: Path, dataset: Optional[str], config, overrides) -> tuple:
    """``(typed tree, its effective YAML dict, the services' configuration file)`` of a simulation that writes to
    ``out``: the settings given (a typo fails here, before any process starts), and, for the generated default scene,
    its withheld views (``sim.scene.novel_every``) unless ``agent.scoring.novel_every`` is given."""
    typed = load_config(config, overrides)
    if dataset is None and "novel_every" not in typed.agent.scoring.model_fields_set:  # the default scene's views
        typed = load_config(config, [*overrides, f"agent.scoring.novel_every={typed.sim.scene.novel_every}"])
    return typed, typed.to_yaml_dict(), write_service_config(typed, out / "config.yaml")


def _diagnose_cover(fused: dict, out: Path, plans, eval_frames, fz: dict, backend: str) -> None:
    """Add the ROI cover diagnosis to the vote map's figures (``fused["vote"]["cover"]``,
    :func:`~gausslite_services.sim.scoring.roi_cover_report`); a failure is logged, never raised: a diagnostic must
    not fail the simulation."""
    try:
        fused["vote"]["cover"] = roi_cover_report(out, plans, eval_frames, fz, backend)
    except Exception as e:  # noqa: BLE001 - a diagnostic must not fail the simulation
        log.warning("ROI cover diagnosis failed: %s", e)


class _Stages:
    """Wall-clock seconds of the simulation's stages, each from the previous mark (the report's ``stages_s``:
    ``scene`` generation, ``services`` start until healthy, ``missions`` replayed and finished, ``scoring`` (fusion,
    renders and the fused map over time), ``cover`` (the ROI cover diagnosis))."""

    def __init__(self, t0: float) -> None:
        self.last = t0
        self.seconds: Dict[str, float] = {}

    def mark(self, name: str) -> None:
        now = time.perf_counter()
        self.seconds[name] = round(now - self.last, 3)
        self.last = now
        log.info("sim stage %s: %.1f s", name, self.seconds[name])


def write_service_config(typed, path: Path) -> Path:
    """Write the configuration file the simulation's services read (``--config``): the settings given (file and
    overrides), so that each dataset's sensor profile fills in the rest (:meth:`GaussLiteConfig.to_yaml_dict`).

    Args:
        typed (gausslite.config.GaussLiteConfig): the simulation's tree.
        path: the file to write.
    Returns:
        ``path``.
    """
    path.write_text(yaml.safe_dump(typed.to_yaml_dict(given_only=True), sort_keys=False))
    return path


def _generate_scene(out: Path, scene, progress: bool) -> str:
    """Generate the synthetic default scene (``scene``: :class:`gausslite.config.SimScene`) into ``out/scene`` and
    return that folder's path."""
    log.info("generating the synthetic default scene into %s", out / "scene")
    make_scene(out / "scene", seed=scene.seed, width=scene.width, height=scene.height, frames=scene.frames,
               progress=progress)
    return str(out / "scene")
