"""The team harness (docs/architecture.md, "One harness for team missions"): ``run_team`` starts a team's runner,
follows every robot until it has replayed its frames, finishes them and returns their summaries, with a clear error
for a failed mission, a failed final push or a team that does not finish in time; ``InProcessTeam`` runs the robots
in this process one after the other, each sharing to its own recording store; the simulation and the team benchmark
both drive their teams through it."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from gausslite.config import load_config
from gausslite.mission import MissionState, build_mission
from gausslite.mission.scoring import MissionSummaryData
from gausslite.team import AgentPlan
from gausslite.team.harness import TeamRunner, progress_line, run_team
from gausslite.team.inprocess import InProcessTeam
from tests._scenes import plane_frame, plane_roi
from tests._source import calls_in

ROOT = Path(__file__).resolve().parents[2]
GRAPH = {"targets": ["object"], "anchors": [], "relations": []}


def _status(state, mapped=3):
    return {"state": state, "frames_received": 3, "frames_mapped": mapped, "n_gaussians": 100, "pushes": 1,
            "last_error": "worker died" if state == MissionState.FAILED else ""}


def _summary(ok=True):
    return MissionSummaryData(status={"last_error": "" if ok else "fusion unreachable"}, final_push_ok=ok, n_shared=10,
                              share_pct=5.0, bytes_on_wire=100, bytes_per_gaussian=10.0, roi_psnr=None, psnr=None,
                              seconds_per_frame=0.1)


class _Runner:
    """A runner whose robots report the scripted states, one list entry per poll (the last one repeats)."""

    def __init__(self, script, push_ok=True):
        self.plans = [AgentPlan("a", "", "t1", ""), AgentPlan("b", "", "t2", "")]
        self.script, self.push_ok = script, push_ok
        self.starts = self.polls = 0
        self.finished_with = None

    def start(self):
        self.starts += 1

    def progress(self):
        states = self.script[min(self.polls, len(self.script) - 1)]
        self.polls += 1
        return {p.name: None if s is None else _status(s) for p, s in zip(self.plans, states)}

    def finish(self, timeout_s):
        self.finished_with = timeout_s
        return {p.name: _summary(self.push_ok) for p in self.plans}

    def close(self):
        pass


def test_run_team_follows_the_robots_until_replayed_then_finishes_them(caplog):
    M, R, F = MissionState.MAPPING, MissionState.REPLAY_DONE, MissionState.FINISHED
    runner, polled = _Runner([(None, M), (M, M), (R, M), (R, F)]), []
    assert isinstance(runner, TeamRunner)
    with caplog.at_level(logging.INFO, logger="gausslite.team.harness"):
        out = run_team(runner, timeout_s=60, poll_s=0.01, on_poll=lambda: polled.append(runner.polls))
    assert runner.starts == 1 and runner.polls == 4 and polled == [0, 1, 2, 3]  # on_poll runs before each read
    assert list(out) == ["a", "b"] and all(s.final_push_ok for s in out.values())
    assert 10.0 <= runner.finished_with <= 60  # Finish gets what is left of the bound, at least 10 s
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0] == "mapping: a waiting, b 3/3 frames, 100 G, 1 pushes"  # a robot not reporting yet is waited for
    assert lines[-1].startswith("mapping: a 3/3") and len(lines) == 2  # the first poll, then when all are done


def test_run_team_says_which_robot_failed_and_why():
    M = MissionState.MAPPING
    with pytest.raises(RuntimeError, match="b mission failed: worker died"):
        run_team(_Runner([(M, M), (M, MissionState.FAILED)]), timeout_s=60, poll_s=0.01)
    with pytest.raises(RuntimeError, match="a: final push failed: fusion unreachable"):
        run_team(_Runner([(MissionState.REPLAY_DONE,) * 2], push_ok=False), timeout_s=60, poll_s=0.01)


def test_run_team_bounds_the_wait_and_refuses_a_bound_that_is_not_positive():
    stuck = _Runner([(MissionState.REPLAY_DONE, None)])  # b never starts its mission
    with pytest.raises(TimeoutError, match="not replayed after 0 s: a 3/3 frames, 100 G, 1 pushes, b waiting"):
        run_team(stuck, timeout_s=0.05, poll_s=0.01)
    assert stuck.finished_with is None
    for kw in ({"timeout_s": 0}, {"timeout_s": 10, "poll_s": 0}):
        with pytest.raises(ValueError, match="must be positive"):
            run_team(_Runner([(MissionState.REPLAY_DONE,) * 2]), **{"poll_s": 0.01, **kw})
    assert progress_line({"a": None}) == "a waiting"


def _config():
    return load_config(None, ["agent.ingest=every_frame", "agent.push.every=2", "mapper.mode=gausslite",
                              "mapper.iters_per_frame=3", "mapper.warmup_iters=1",
                              "mapper.seeding.seeds_per_frame=200", "agent.share.worker=thread"]).agent


def test_in_process_team_runs_the_robots_in_turn_each_sharing_to_its_own_store():
    cfg, seen = _config(), []
    plans = [AgentPlan("a", "", "t1", ""), AgentPlan("b", "", "t2", "")]

    def mission(plan, fusion):
        # what has run when this robot's turn comes: every robot before it finished, none after it built
        seen.append((plan.name, {n: m.summary is not None for n, m in runner.missions.items()}))
        rt = build_mission(cfg, "Pick up the object", GRAPH, agent_id=plan.name, fusion=fusion,
                           relevance_fn=lambda fr: plane_roi(), start=False)
        x0 = 0.0 if plan.name == "a" else 0.2
        return rt, [plane_frame(i, x0 + 0.03 * i) for i in range(4)]

    runner = InProcessTeam(plans, mission)
    try:
        out = run_team(runner, timeout_s=300, poll_s=0.01)
        assert seen == [("a", {}), ("b", {"a": True})]
        assert list(out) == ["a", "b"]
        for name, m in runner.missions.items():
            assert m.summary is out[name] and m.summary.final_push_ok and m.wall_s > 0
            assert m.runtime.frames_mapped == 4 and m.runtime.status()["state"] == MissionState.FINISHED
            assert not m.runtime.worker.thread.is_alive()  # closed after its turn, before the next robot's
            # the store holds what the robot pushed, on its own mission clock, and the robot's subset only
            assert m.fusion.history and m.fusion.history[0][0] <= m.wall_s
            assert len(m.fusion.history[-1][2]) == m.summary.n_shared
        a, b = (runner.missions[n].fusion.history[-1][2] for n in "ab")
        assert np.median(a.means[:, 0]) < np.median(b.means[:, 0])  # each its own part of the plane
    finally:
        runner.close()
    with pytest.raises(ValueError, match="unique names"):
        InProcessTeam([plans[0], plans[0]], mission)

    def broken(plan, fusion):  # the first robot's mission fails (out of memory): reported by name, the second never
        def relevance(fr):       # starts (an ordinary error would cost its frame alone)
            raise MemoryError("no relevance")

        rt = build_mission(cfg, "Pick up the object", GRAPH, agent_id=plan.name, fusion=fusion,
                           relevance_fn=relevance, start=False)
        return rt, [plane_frame(i, 0.03 * i) for i in range(4)]

    failing = InProcessTeam(plans, broken)
    try:
        with pytest.raises(RuntimeError, match="a mission failed: .*no relevance"):
            run_team(failing, timeout_s=120, poll_s=0.01)
        assert list(failing.missions) == ["a"]
    finally:
        failing.close()
    idle = InProcessTeam(plans, mission)
    with pytest.raises(RuntimeError, match=r"never started: \['a', 'b'\]"):
        idle.finish()


@pytest.mark.parametrize("path, function, runner", [("services/sim/runner.py", "run_sim", "ServiceTeam"),
                                                     ("bench/team.py", "run_missions", "InProcessTeam")])
def test_the_simulation_and_the_team_benchmark_drive_their_teams_with_the_harness(path, function, runner):
    called = calls_in(path, function)
    assert {"run_team", runner} <= called
    # nothing else in them follows or finishes a robot's mission itself
    src = (ROOT / path).read_text(encoding="utf-8")
    assert ".replay(" not in src and ".status()" not in src and "MISSION_STATE_" not in src
