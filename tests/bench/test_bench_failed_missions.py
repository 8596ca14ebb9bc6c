"""No benchmark scores a failed mission silently (bench/_missions.py): every run records how its mission ended, a
failed run is kept in the result but left out of its figures and marked † in its tables, and the command exits 1
unless ``--allow-failed``. Fake mission runs keep these tests fast; one tiny live mission checks the record the
real runtime gives."""

from __future__ import annotations

import io
import json

import pytest

import bench._missions as missions
from gausslite.mission.state import MissionState

FAIL = "mapping frame 612 failed: RuntimeError: boom"


# ------------------------------------------------------------------------------------ the rule
def test_the_outcome_is_read_from_an_in_process_or_a_grpc_status_with_or_without_the_counters():
    from gausslite_rpc import agent_pb2

    ok = missions.mission_outcome({"state": MissionState.FINISHED, "last_error": ""})
    assert ok == {"end_state": "FINISHED", "error": "", "frames_failed": 0, "corrections_rejected": 0}
    assert not missions.failed(ok)
    bad = missions.mission_outcome({"state": MissionState.FAILED, "last_error": FAIL, "frames_failed": 0})
    assert bad["end_state"] == "FAILED" and bad["error"] == FAIL and missions.failed(bad)
    grpc = missions.mission_outcome(agent_pb2.MissionStatus(state=agent_pb2.MISSION_STATE_FAILED, last_error=FAIL))
    assert grpc["end_state"] == "FAILED" and grpc["error"] == FAIL and grpc["frames_failed"] == 0
    assert missions.state_name(agent_pb2.MISSION_STATE_FINISHED) == "FINISHED"
    # finished, but frames failed to map: failed too; an error the mission survives by design (a lost or rejected
    # frame) and rejected corrections alone are not
    assert missions.failed({**ok, "frames_failed": 2})
    assert not missions.failed({**ok, "error": "odometry lost frame 5: fitness 0.10 < 0.2"})
    assert not missions.failed({**ok, "corrections_rejected": 3})
    assert not missions.failed({"roi_psnr": 20.0})  # an offline run, or a result written before the rule


def test_the_exit_code_names_every_failed_run_and_allow_failed_waives_it():
    runs = [{"scene": "s", "run": 0, "end_state": "FINISHED", "error": ""},
            {"scene": "s", "run": 1, "end_state": "FAILED", "error": FAIL}]
    err = io.StringIO()
    assert missions.exit_code(runs, False, "bench.x", ("scene", "run"), stream=err) == 1
    assert f"scene=s run=1: FAILED ({FAIL})" in err.getvalue() and "run=0" not in err.getvalue()
    assert missions.exit_code(runs, True, "bench.x", ("scene", "run"), stream=io.StringIO()) == 0
    assert missions.exit_code(runs[:1], False, "bench.x", stream=io.StringIO()) == 0
    assert missions.failure_rows(runs, ("run",)) == [{"run": 1, "end_state": "FAILED", "error": FAIL}]


# ------------------------------------------------------------------------------------ bench.realtime
def _fake_run(fail: set):
    """A stand-in of ``bench.realtime``'s live run: scored figures of one run, its mission FAILED when its (mode, run)
    is in ``fail``; every call recorded."""
    calls = []

    def run_one(job):
        calls.append((job["mode"], job["run"]))
        bad = (job["mode"], job["run"]) in fail
        roi = 20.0 + (1.0 if job["mode"] == "gausslite" else 0.0) + 0.1 * job["run"]
        frames = {str(i): roi + 0.1 * i for i in range(4)}
        return {"scene": job["scene"], "mode": job["mode"], "budget": job["budget"], "run": job["run"],
                "cap": job["cap"], "roi_psnr": roi, "psnr": 20.0, "ssim": 0.7, "n_gaussians": 100,
                "iters_per_keyframe": 5.0, "keyframes": 10, "idle_iters": 0, "roi_iters": 0, "wall_s": 1.0,
                "protocols": {"sensor": {"roi_psnr": roi, "psnr": 20.0, "ssim": 0.7, "frames_scored": 4,
                                         "roi_psnr_per_frame": frames, "psnr_per_frame": frames}},
                "end_state": "FAILED" if bad else "FINISHED", "error": FAIL if bad else "", "frames_failed": 0,
                "corrections_rejected": 0}

    run_one.calls = calls
    return run_one


def test_realtime_records_a_failed_mission_leaves_it_out_marks_it_and_exits_1(tmp_path, monkeypatch, capsys):
    from bench.realtime import cli

    fake = _fake_run({("gausslite", 1)})
    monkeypatch.setattr(cli, "run_one", fake)
    monkeypatch.setattr(cli, "scene_path", lambda scene, work: tmp_path)  # no scene is rendered
    out = tmp_path / "rt.json"
    # each mission's own governor: no scene is loaded to choose a shared resolution before the (fake) missions
    argv = ["--scenes", "synthetic_circle", "--budgets", "0.5", "--runs", "3", "--final-pass-budgets=",
            "--protocols", "sensor", "--resolution", "agent", "--work", str(tmp_path / "w"), "--out", str(out)]
    assert cli.main(argv) == 1
    assert f"run=1: FAILED ({FAIL})" in capsys.readouterr().err
    res = json.loads(out.read_text())
    assert [r["end_state"] for r in res["runs"] if r["mode"] == "gausslite"] == ["FINISHED", "FAILED", "FINISHED"]
    assert res["failed_runs"] == [{"scene": "synthetic_circle", "mode": "gausslite", "budget": 0.5, "run": 1,
                                   "end_state": "FAILED", "error": FAIL, "frames_failed": 0,
                                   "corrections_rejected": 0}]
    blk = res["scenes"]["synthetic_circle"]["budgets"]["0.5"]
    assert [r["run"] for r in blk["failed_runs"]["gausslite"]] == [1] and "uniform" not in blk["failed_runs"]
    assert blk["gausslite"]["runs"] == 2 and blk["uniform"]["runs"] == 3
    assert blk["gausslite"]["roi_psnr"] == pytest.approx(21.1)  # runs 0 and 2: the failed one is never averaged
    assert blk["gain_runs"] == 2 and blk["gain"] == pytest.approx(1.0)
    md = out.with_suffix(".md").read_text()
    assert "| gausslite † 1 failed |" in md and "† a run whose mission failed" in md
    # allowed: the same record and figures, exit 0
    assert cli.main([*argv, "--allow-failed"]) == 0
    assert json.loads(out.read_text())["scenes"] == res["scenes"]
    # a resumed invocation runs the failed mission again, and only it
    monkeypatch.setattr(cli, "run_one", fixed := _fake_run(set()))
    assert cli.main([*argv, "--resume"]) == 0
    assert fixed.calls == [("gausslite", 1)]
    res = json.loads(out.read_text())
    assert res["failed_runs"] == [] and res["scenes"]["synthetic_circle"]["budgets"]["0.5"]["gausslite"]["runs"] == 3


def test_a_mode_whose_every_run_failed_still_has_its_row():
    from bench import realtime as rt

    runs = [_fake_run({("gausslite", 0)})({"scene": "s", "mode": m, "budget": 0.5, "run": 0, "cap": 100})
            for m in ("uniform", "gausslite")]
    s = rt.summarise(runs, "s", [0.5], 100)
    blk = s["budgets"]["0.5"]
    assert "gausslite" not in blk and blk["uniform"]["runs"] == 1 and "gain" not in blk
    md = rt.table({"scenes": {"s": s}})
    assert "| s | 100 | 0.5 | gausslite † 1 failed | – |" in md


@pytest.mark.parametrize("runner", ["run_one", "twin_one"])
@pytest.mark.parametrize("error, state", [(MemoryError, "FAILED"), (RuntimeError, "FINISHED")])
def test_a_mission_whose_mapping_fails_is_recorded_with_its_state_and_error(tmp_path, monkeypatch, error, state,
                                                                             runner):
    """The real runtime (live) and the twin, on a tiny scene: out of memory fails the mission (``FAILED``, its error);
    any other error costs the frame alone (``FINISHED``, ``frames_failed``): both are failed runs, recorded, not
    raised."""
    from bench import realtime as rt
    from gausslite.mapping.mapper import Mapper
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=8, width=64, height=48, trajectory="circle", progress=False)
    real, calls = Mapper.map_frame, []

    def fails_after_the_first(self, *args, **kwargs):
        calls.append(1)
        if len(calls) > 1:
            raise error("injected")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Mapper, "map_frame", fails_after_the_first)
    job = {"scene": "synthetic_circle", "spec": rt.SCENES["synthetic_circle"], "path": str(tmp_path / "scene" / "agent_a"),
           "task": "synth-pick-object", "mode": "gausslite", "budget": 0.08, "run": 0, "cap": 300, "clock": "dataset",
           "overrides": ["mapper.seeding.seeds_per_frame=300"], "protocols": ("sensor",), "novel_every": 0}
    r = getattr(rt, runner)(job)
    assert r["end_state"] == state and missions.failed(r)
    assert r["error"].startswith("mapping frame ") and f"{error.__name__}: injected" in r["error"]
    assert (r["frames_failed"] >= 1) == (state == "FINISHED")  # a frame's own failure is counted, the mission's not
    assert "corrections_rejected" in r


# ------------------------------------------------------------------------------------ the other benches
def test_a_team_run_the_harness_stopped_is_recorded_and_the_team_bench_exits_1(tmp_path, monkeypatch, capsys):
    import bench.team as team
    from gausslite.team import AgentPlan

    monkeypatch.setattr(team, "team_plans", lambda name, work: [AgentPlan("agent_a", str(tmp_path), "t-a", ""),
                                                                AgentPlan("agent_b", str(tmp_path), "t-b", "")])

    def harness_stops(runner, **kwargs):
        raise RuntimeError(f"agent_a mission failed: {FAIL}")

    monkeypatch.setattr(team.harness, "run_team", harness_stops)
    out = tmp_path / "team.json"
    argv = ["--teams", "synthetic", "--runs", "1", "--out", str(out), "--work", str(tmp_path / "w")]
    assert team.main(argv) == 1
    assert "FAILED" in capsys.readouterr().err
    res = json.loads(out.read_text())
    (run,) = res["runs"]
    assert run["end_state"] == "FAILED" and FAIL in run["error"] and "fused" not in run
    assert [a["end_state"] for a in run["agents"]] == ["NOT_STARTED", "NOT_STARTED"]
    assert res["failed_runs"][0]["run"] == 0 and res["teams"] == {}
    assert "- † team=synthetic budget=0.5 run=0: FAILED" in out.with_suffix(".md").read_text()
    assert team.main([*argv, "--allow-failed"]) == 0

