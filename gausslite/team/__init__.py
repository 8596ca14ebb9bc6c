"""A team mission as a library: the robots of a team (:class:`AgentPlan`) and their frames, their fused maps scored
against each robot's own map under the scoring protocols (:mod:`gausslite.team.scoring`), the report's figures
(:mod:`gausslite.team.figures`: each robot's entry, the paired gains of a fused map over the own map, other runs'
figures merged in) and the written report (:mod:`gausslite.team.report`, :mod:`gausslite.team.plots`). No gRPC here:
``gausslite sim`` (``gausslite_services.sim``) runs the services and drives the robots over the wire, and the team
benchmark (``bench.team``) runs them in process; both score and report through this package."""

from gausslite.team.figures import (FUSED_HELP, FUSED_KEYS, PER_ROBOT, agent_report, attach_context_baseline,
                                    attach_uniform_baseline, fused_minus_own, lead_protocol, load_offline, own_frames,
                                    protocol_minus_own)
from gausslite.team.plan import AgentPlan, load_eval_frames
from gausslite.team.plots import plot_fused_timeline, plot_pushes
from gausslite.team.report import answer_markdown, attach_offline_report, write_markdown, write_report
from gausslite.team.scoring import (AT_OWN, cover_report, fused_protocols, own_map_files, save_fused_maps,
                                    score_fused_maps, score_team_map, score_timeline, team_cover)

__all__ = ["AT_OWN", "FUSED_HELP", "FUSED_KEYS", "PER_ROBOT", "AgentPlan", "agent_report", "answer_markdown",
           "attach_context_baseline", "attach_offline_report", "attach_uniform_baseline", "cover_report",
           "fused_minus_own", "fused_protocols", "lead_protocol", "load_eval_frames", "load_offline", "own_frames",
           "own_map_files", "plot_fused_timeline", "plot_pushes", "protocol_minus_own", "save_fused_maps",
           "score_fused_maps", "score_team_map", "score_timeline", "team_cover", "write_markdown", "write_report"]
