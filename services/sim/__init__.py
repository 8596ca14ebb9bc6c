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

Modules: :mod:`~gausslite_services.sim.launch` (agents' plans, service commands, child processes, health),
:mod:`~gausslite_services.sim.runner` (:func:`run_sim`), :mod:`~gausslite_services.sim.timeline` (the fused map over
time), :mod:`~gausslite_services.sim.scoring` (fusing and scoring the final maps) and
:mod:`~gausslite_services.sim.report` (report.json, report.md, plots, figures merged in from other runs). The names
below are this package's interface.
"""

from gausslite_services.sim.launch import (AGENT_NAMES, REPO, AgentPlan, ProcessGroup, free_port, plan_agents,
                                           service_commands, wait_healthy)
from gausslite_services.sim.report import (FUSED_HELP, FUSED_KEYS, attach_context_baseline, attach_offline_report,
                                           attach_uniform_baseline, plot_fused_timeline, plot_pushes, write_markdown)
from gausslite_services.sim.runner import SimResult, run_sim
from gausslite_services.sim.scoring import fuse_settings, fused_protocols, roi_cover_report
from gausslite_services.sim.timeline import FusedTimeline

__all__ = ["AGENT_NAMES", "FUSED_HELP", "FUSED_KEYS", "REPO", "AgentPlan", "FusedTimeline", "ProcessGroup", "SimResult",
           "attach_context_baseline", "attach_offline_report", "attach_uniform_baseline", "free_port", "fuse_settings",
           "fused_protocols", "plan_agents", "plot_fused_timeline", "plot_pushes", "roi_cover_report", "run_sim",
           "service_commands", "wait_healthy", "write_markdown"]
