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

This package is the adapter between the services and the library: it runs the processes and drives them over the
wire; how a team mission is driven (:func:`gausslite.team.harness.run_team`, the harness the team benchmark drives
too), the scoring of the team's maps against each robot's own and the report are the library's
(:mod:`gausslite.team`). Modules: :mod:`~gausslite_services.sim.launch` (agents' plans, service commands, child
processes, health), :mod:`~gausslite_services.sim.team` (:class:`ServiceTeam`, the harness's runner of the services),
:mod:`~gausslite_services.sim.runner` (:func:`run_sim`), :mod:`~gausslite_services.sim.timeline`
(the fused map over time, polled from the server), :mod:`~gausslite_services.sim.scoring` (the fused maps the server
makes, the keyframe poses and subsets it holds) and :mod:`~gausslite_services.sim.summary` (an agent's Finish summary
as the library reads it). The names below are this package's interface.
"""

from gausslite_services.sim.launch import (AGENT_NAMES, REPO, AgentPlan, ProcessGroup, free_port, plan_agents,
                                           service_commands, wait_healthy)
from gausslite_services.sim.runner import SimResult, run_sim
from gausslite_services.sim.scoring import fuse_settings, roi_cover_report
from gausslite_services.sim.summary import status_from_proto, summary_from_proto
from gausslite_services.sim.team import ServiceTeam
from gausslite_services.sim.timeline import FusedTimeline

__all__ = ["AGENT_NAMES", "REPO", "AgentPlan", "FusedTimeline", "ProcessGroup", "ServiceTeam", "SimResult",
           "free_port", "fuse_settings", "plan_agents", "roi_cover_report", "run_sim", "service_commands",
           "status_from_proto", "summary_from_proto", "wait_healthy"]
