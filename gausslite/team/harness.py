"""The one harness that drives a team mission (paper Sec. III-E, IV): :func:`run_team` starts every robot's mission
through a :class:`TeamRunner`, follows them until each has replayed its frames, then finishes them (mapping what is
queued and the final push) and returns each robot's Finish summary.

Where the robots run is the runner's business; how a team mission is driven is this module's:

* :class:`gausslite.team.inprocess.InProcessTeam` runs the missions in this process, one robot after the other so
  that each has the machine to itself as a robot has its own computer, each sharing to an in-memory stand-in of the
  fusion server's store (``bench.team``);
* the simulation's runner (``gausslite sim``, ``gausslite_services.sim.ServiceTeam``) starts the parser, the fusion
  server and the agents as processes, side by side, and drives them over gRPC.

What happens after the missions (the fused maps and their scores) belongs to the caller: the simulation asks the
fusion server for its maps, the team benchmark makes them in process; both score them with
:mod:`gausslite.team.scoring`. No gRPC here.
"""

from __future__ import annotations

import logging
import time
from typing import Callable, Dict, List, Optional, Protocol, runtime_checkable

from gausslite.mission.scoring import MissionSummaryData
from gausslite.mission.state import MissionState
from gausslite.team.plan import AgentPlan

log = logging.getLogger(__name__)

__all__ = ["DONE", "TeamRunner", "run_team", "progress_line"]

#: the states in which a robot's mission has replayed every frame it was given (its Finish can start)
DONE = frozenset({MissionState.REPLAY_DONE, MissionState.FINISHED})


@runtime_checkable
class TeamRunner(Protocol):
    """Where a team's robots run: what :func:`run_team` needs of it.

    Attributes:
        plans: the robots (:class:`~gausslite.team.plan.AgentPlan`), in order.
    """

    plans: List[AgentPlan]

    def start(self) -> None:
        """Start the team (idempotent: a second call does nothing). Raises what starting a robot raises
        (``TimeoutError`` for a service that is not healthy in time, ``RuntimeError`` for one that died)."""

    def progress(self) -> Dict[str, Optional[dict]]:
        """Agent id → its mission's status (the keys of the ``MissionStatus`` message: ``state`` a
        :class:`~gausslite.mission.state.MissionState`, ``frames_received``, ``frames_mapped``, ``n_gaussians``,
        ``pushes``, ``last_error``), or None while the robot has no mission to report yet. A runner that runs its
        robots in turn starts the next one here. Raises ``RuntimeError`` when a robot's process died."""

    def finish(self, timeout_s: Optional[float]) -> Dict[str, MissionSummaryData]:
        """Finish every robot's mission (map what is queued, the final push) within ``timeout_s`` seconds (None:
        unbounded); agent id → its Finish summary. Raises ``TimeoutError``."""

    def close(self) -> None:
        """Stop everything the runner started (idempotent)."""


def progress_line(progress: Dict[str, Optional[dict]]) -> str:
    """One log line of the team's progress: per robot the frames mapped of the frames received, its Gaussians and its
    pushes (``waiting`` for a robot not reporting yet)."""
    return ", ".join(f"{n} waiting" if st is None else
                     f"{n} {st['frames_mapped']}/{st['frames_received'] or '?'} frames, {st['n_gaussians']} G, "
                     f"{st['pushes']} pushes" for n, st in progress.items())


def run_team(runner: TeamRunner, *, timeout_s: float, on_poll: Optional[Callable[[], None]] = None,
             poll_s: float = 1.0, log_every_s: float = 5.0) -> Dict[str, MissionSummaryData]:
    """Drive one team mission: start the runner, follow every robot's mission until each has replayed its frames
    (:data:`DONE`), then finish them.

    Args:
        runner: where the robots run (:class:`TeamRunner`).
        timeout_s: bound on the whole drive, start and Finish included (s, > 0).
        on_poll: called at every poll, before the robots' progress is read (the simulation follows the fused map
            over time there); its exceptions propagate.
        poll_s: seconds between polls. log_every_s: seconds between progress log lines (and one when all are done).
    Returns:
        agent id → the robot's Finish summary (:class:`~gausslite.mission.scoring.MissionSummaryData`), in the
        runner's plan order.
    Raises:
        ValueError: ``timeout_s`` or ``poll_s`` not positive.
        RuntimeError: a robot's mission failed (``FAILED``, with its last error), its process died, or its final push
            failed.
        TimeoutError: the missions were not replayed and finished within ``timeout_s``.
    """
    if not timeout_s > 0 or not poll_s > 0:
        raise ValueError(f"timeout_s and poll_s must be positive, got {timeout_s} and {poll_s}")
    deadline = time.monotonic() + timeout_s
    runner.start()
    last_log = -float("inf")
    while True:
        if on_poll is not None:
            on_poll()
        progress = runner.progress()
        for name, st in progress.items():
            if st is not None and st["state"] == MissionState.FAILED:
                raise RuntimeError(f"{name} mission failed: {st['last_error']}")
        done = all(st is not None and st["state"] in DONE for st in progress.values())
        if done or time.monotonic() - last_log > log_every_s:
            last_log = time.monotonic()
            log.info("mapping: %s", progress_line(progress))
        if done:
            break
        if time.monotonic() > deadline:
            raise TimeoutError(f"the team's missions were not replayed after {timeout_s:.0f} s: "
                               f"{progress_line(progress)}")
        time.sleep(poll_s)
    summaries = runner.finish(max(10.0, deadline - time.monotonic()))
    for name, s in summaries.items():
        if not s.final_push_ok:
            raise RuntimeError(f"{name}: final push failed: {s.status.get('last_error')}")
    return summaries
