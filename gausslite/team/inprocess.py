"""A team mission in this process (:class:`InProcessTeam`): the :class:`gausslite.team.harness.TeamRunner` of the team
benchmark. Each robot's mission is built when its turn comes (by the caller's :data:`MissionFactory`, which builds it
with :func:`gausslite.mission.build_mission`), replays its frames, and is finished (the final push) before the next
robot starts: each has the machine to itself, as a robot has its own computer. Each shares to its own
:class:`gausslite.mission.fakes.RecordingFusion`, what the fusion server's store holds of that robot (every map
version rebuilt, the uploaded keyframes), with each push's time on the robot's mission clock. No gRPC here.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

from gausslite.mission.fakes import RecordingFusion
from gausslite.mission.ports import FusionPort
from gausslite.mission.runtime import AgentRuntime
from gausslite.mission.scoring import MissionSummaryData
from gausslite.mission.state import MissionState
from gausslite.team.plan import AgentPlan

log = logging.getLogger(__name__)

__all__ = ["InProcessMission", "InProcessTeam", "MissionFactory"]

#: builds one robot's mission, not started, sharing to ``fusion``: ``(plan, fusion) → (runtime, frames to replay)``
#: (what :meth:`AgentRuntime.replay <gausslite.mission.runtime.AgentRuntime.replay>` reads: a dataset, or a
#: :class:`gausslite.evaluation.FrameSubset` with frames withheld)
MissionFactory = Callable[[AgentPlan, FusionPort], Tuple[AgentRuntime, object]]


@dataclass
class InProcessMission:
    """One robot's mission as :class:`InProcessTeam` ran it.

    Attributes:
        plan: the robot. runtime: its mission (finished and closed: its threads stopped, its map, keyframes and pusher
            still readable).
        fusion: what the fusion server's store holds of it (its ``history`` clock starts when the replay starts).
        wall_s: seconds from the replay's start to the end of its Finish (the final push included).
        summary: its Finish summary.
    """

    plan: AgentPlan
    runtime: AgentRuntime
    fusion: RecordingFusion
    wall_s: float = 0.0
    summary: Optional[MissionSummaryData] = None


class InProcessTeam:
    """The robots of ``plans`` as missions of this process, one after the other.

    :meth:`progress` runs the turns: when the running robot has replayed its frames, it is finished (the final push,
    ``evaluate`` scoring its map at Finish or not) and closed, and the next robot's mission is built and started.
    Read :attr:`missions` after :func:`gausslite.team.harness.run_team`; :meth:`close` closes every mission (after a
    failure, the one still running).

    Args:
        plans: the robots, in the order they run (unique names).
        make_mission: :data:`MissionFactory`.
        evaluate: score each map at its Finish (:meth:`AgentRuntime.finish`'s ``evaluate``).
        max_keyframes: keyframes each robot's store keeps (the fusion server's per-agent bound).
    Raises:
        ValueError: no robot, or two with the same name.
    """

    def __init__(self, plans: List[AgentPlan], make_mission: MissionFactory, *, evaluate: bool = False,
                 max_keyframes: int = 64) -> None:
        names = [p.name for p in plans]
        if not names or len(set(names)) != len(names):
            raise ValueError(f"a team needs robots with unique names, got {names}")
        self.plans, self.make_mission, self.evaluate = list(plans), make_mission, evaluate
        self.max_keyframes = max_keyframes
        #: agent id → its mission, in the order they ran (a robot not started yet has none)
        self.missions: Dict[str, InProcessMission] = {}
        self._replay = None  # the running robot's replay thread

    def start(self) -> None:
        """Start the first robot's mission (idempotent)."""
        if not self.missions:
            self._begin(self.plans[0])

    def _begin(self, plan: AgentPlan) -> None:
        fusion = RecordingFusion(self.max_keyframes)
        rt, frames = self.make_mission(plan, fusion)
        self.missions[plan.name] = InProcessMission(plan, rt, fusion)
        log.info("%s: mission started (task %s)", plan.name, plan.task_id)
        fusion.start()
        self._replay = rt.replay(frames)

    def _last(self) -> Optional[InProcessMission]:
        """The robot started last (the running one until it is finished), None before the first."""
        return next(reversed(self.missions.values()), None)

    def _finish_running(self, timeout_s: Optional[float] = None) -> None:
        """Finish the running robot (its final push), then close it: none of its threads or worker processes runs
        beside the next robot; its map, keyframes, pusher and store stay readable."""
        m = self._last()
        try:
            m.summary = m.runtime.finish(push=True, evaluate=self.evaluate, timeout_s=timeout_s)
            m.wall_s = time.perf_counter() - m.fusion.t0
        finally:
            m.runtime.close()

    def progress(self) -> Dict[str, Optional[dict]]:
        """Agent id → its mission's status (None for a robot whose turn has not come). When the running robot has
        replayed its frames it is finished here and the next robot started; a robot whose mission failed stays as it
        is (``FAILED``, for :func:`~gausslite.team.harness.run_team` to report)."""
        running = self._last()
        if (running is not None and running.summary is None and not self._replay.is_alive()
                and running.runtime.status()["state"] != MissionState.FAILED):  # a failed one is reported, not finished
            self._finish_running()
            if len(self.missions) < len(self.plans):
                self._begin(self.plans[len(self.missions)])
        return self.statuses()

    def statuses(self) -> Dict[str, Optional[dict]]:
        """Agent id → its mission's status as it is (None for a robot whose turn has not come), without running the
        turns as :meth:`progress` does: how each robot's mission ended after :func:`~gausslite.team.harness.run_team`
        stopped the team."""
        return {p.name: self.missions[p.name].runtime.status() if p.name in self.missions else None
                for p in self.plans}

    def finish(self, timeout_s: Optional[float] = None) -> Dict[str, MissionSummaryData]:
        """Each robot's Finish summary (the running robot's Finish done here, within ``timeout_s``).

        Raises:
            RuntimeError: a robot never started (its turn did not come). TimeoutError: the running robot's Finish.
        """
        missing = [p.name for p in self.plans if p.name not in self.missions]
        if missing:
            raise RuntimeError(f"robots that never started: {missing}")
        if self._last().summary is None:
            self._finish_running(timeout_s)
        return {p.name: self.missions[p.name].summary for p in self.plans}

    def close(self) -> None:
        """Close every mission (idempotent)."""
        for m in self.missions.values():
            m.runtime.close()
