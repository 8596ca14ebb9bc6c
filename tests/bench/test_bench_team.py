"""The live team benchmark (bench.team): its team definitions (the overlapping-view team among them) and its goal
checks."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from bench.team import FUSED_KEYS, PER_ROBOT, TEAMS, summarise
from gausslite.wire.codec import GaussianArrays

SHARED = Path(os.environ.get("GAUSSLITE_SHARED", Path(__file__).resolve().parents[3] / "shared"))


def test_teams_and_the_overlapping_view_team():
    for name, team in TEAMS.items():
        n = 3 if name == "tum_three" else 2
        assert len(team["agents"]) == n and len({a["id"] for a in team["agents"]}) == n, name
        assert len({a["task"] for a in team["agents"]}) == n, name
    halves = TEAMS["tum_halves"]
    assert halves["overlap"] and not TEAMS["tum"]["overlap"] and not TEAMS["synthetic"]["overlap"]
    (a0, a1), (b0, b1) = (a["frames"] for a in halves["agents"])
    assert (a0, a1, b0, b1) == (0, 75, 75, 150)  # two robots, one half of the sequence each
    tasks = SHARED / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy" / "tasks.json"
    if not tasks.is_file():
        if os.environ.get("CI") == "true":
            pytest.fail(f"{tasks} is missing (set GAUSSLITE_SHARED)")
        pytest.skip("TUM dataset absent")
    import json

    by_id = {t["id"]: set(t["roi_object_ids"]) for t in json.loads(tasks.read_text())["tasks"]}
    # the two tasks' ROIs share an object (the keyboard): the robots map a common region
    shared = by_id[halves["agents"][0]["task"]] & by_id[halves["agents"][1]["task"]]
    assert shared


def _run(team, run, own, concat, vote, refine, share=8.0, upload=1.2, robot=(-0.2, -0.2), with_own=(0.0, -0.05),
         views=6.5):
    agents = [{"id": f"agent_{c}", "task": f"t{c}", "share_pct": share, "upload_ratio": upload, "view_ratio": views,
               "bytes_per_gaussian": 12.0, "own_roi_psnr": own[i], "concat_roi_psnr": concat[i],
               "vote_roi_psnr": vote[i], "vote_r1_roi_psnr": vote[i] - 1, "refine_roi_psnr": refine[i],
               "refine_long_roi_psnr": refine[i] + 0.5, "for_robot_roi_psnr": own[i] + robot[i],
               "with_own_roi_psnr": own[i] + with_own[i], "keyframes": 20, "iters_per_keyframe": 20.0,
               "pushes": 2, "n_gaussians": 6000} for i, c in enumerate("ab")]
    return {"team": team, "run": run, "agents": agents}


def test_summary_checks_the_goals_per_team():
    runs = [_run("tum_halves", r, own=(20, 22), concat=(19, 21), vote=(20.5, 22.5), refine=(21, 23)) for r in range(3)]
    runs += [_run("tum", r, own=(20, 22), concat=(19, 21), vote=(18, 21.5), refine=(21, 21.9), share=30.0,
                  robot=(0.3, -1.0), with_own=(0.0, -0.3), views=9.0) for r in range(3)]
    s = summarise(runs)
    h, t = s["tum_halves"], s["tum"]
    assert t["goals"]["views_le_8x"] is False and t["agents"]["agent_a"]["view_ratio"] == pytest.approx(9.0)
    assert h["goals"] == {"share_le_25pct": True, "upload_le_1.5x": True, "views_le_8x": True, "refine_ge_own": True,
                          "refine_long_ge_own": True, "vote_ge_concat": True, "vote_ge_own": True,
                          "for_robot_ge_own_minus_0.5": True, "with_own_ge_own_minus_0.1": True}
    assert h["agents"]["agent_b"]["for_robot_minus_own"] == pytest.approx(-0.2)
    assert t["goals"]["for_robot_ge_own_minus_0.5"] is False  # agent_b: 1 dB below its own map
    assert t["goals"]["with_own_ge_own_minus_0.1"] is False  # agent_b: 0.3 dB below
    assert h["agents"]["agent_b"]["with_own_minus_own"] == pytest.approx(-0.05)
    assert h["agents"]["agent_a"]["vote_minus_own"] == pytest.approx(0.5)
    assert t["goals"]["share_le_25pct"] is False and t["goals"]["vote_ge_concat"] is False
    assert t["goals"]["refine_ge_own"] is False and "vote_ge_own" not in t["goals"]
    assert t["goals"]["refine_long_ge_own"] is True  # 21.5 / 22.4 against 20 / 22
    assert t["agents"]["agent_b"]["refine_minus_own"] == pytest.approx(-0.1)
    assert h["goals_protocol"] == t["goals_protocol"] == "sensor"  # no protocol rows: the sensor figures
    # under novel the fused − own goals read the novel rows: here agent_b's map from the server holds its region
    for r in runs[3:]:
        for i, a in enumerate(r["agents"]):
            a["protocols"] = {"novel": {"own_roi_psnr": 20.0, **{f"{k}_roi_psnr": 20.0 - 0.05 * i
                                                                  for k in (*FUSED_KEYS, *PER_ROBOT)}}}
    t = summarise(runs)["tum"]
    assert t["goals_protocol"] == "novel"
    assert t["goals"]["for_robot_ge_own_minus_0.5"] is True and t["goals"]["with_own_ge_own_minus_0.1"] is True
    assert t["goals"]["refine_ge_own"] is False  # agent_b: 0.05 dB below under novel too


def test_fused_maps_are_scored_under_every_protocol_beside_the_owners_own_map(monkeypatch, tmp_path):
    """``fused_scores``: every final fused map (and the map made for each robot) on each task under ``sensor`` (the
    top-level figure), ``keyframes`` (the owner's uploaded keyframes at the poses they carry), ``novel`` (the withheld
    frame through the owner's camera model: its predicted pose, nothing fitted), ``tracked`` (every stride-th frame)
    and ``novel-tracked``, each with its per-frame figures; ``run_team``'s per-agent ``protocols`` rows and
    ``summarise`` carry them, with vote − own per protocol paired frame by frame, and the markdown has a protocol
    table."""
    import bench.team as team
    from gausslite.mapping.config import MapperConfig
    from gausslite.mapping.mapper import Mapper
    from gausslite.mapping.views import keyframe_from_frame
    from tests._scenes import plane_frame

    monkeypatch.setattr(team, "LONG_REFINE_ITERS", 2)
    H, W = 40, 56
    roi = np.zeros((H, W), bool)
    roi[10:30, 14:42] = True

    class _Ann:
        def roi_mask(self, task, depth, c2w, intr):
            return roi

    frames = [plane_frame(i, 0.015 * i, H, W) for i in range(7)]  # frame 6: withheld from both robots
    agents = []
    for n, (aid, lo) in enumerate((("agent_a", 0), ("agent_b", 3))):
        cfg = MapperConfig(mode="gausslite", seeding={"seeds_per_frame": 300}, iters_per_frame=5, warmup_iters=2,
                           backend="warp")
        m = Mapper(cfg)
        for fr in frames[lo:lo + 3]:
            m.map_frame(fr, roi)
        g = GaussianArrays.from_any(m.gmap)
        kfs = [keyframe_from_frame(fr, "cpu", roi) for fr in frames[lo:lo + 3:2]]  # 2 uploaded keyframes
        agents.append({"id": aid, "task": f"t{n}", "_history": [(1.0 + n, g)], "_keyframes": kfs, "_frames": frames,
                       "_annotations": _Ann(), "_seen": m.seen_by_this_camera, "_novel": [6], "_own_map": g,
                       "_own_views": [kf for kf in m.keyframes if kf.roi is not None]})
    fuse = {"voxel_size": 0.1, "contest_radius": 0, "refine_iters": 2}
    out = team.fused_scores(agents, fuse, 0, 3, track_iters=3, track_stride=4, renders=tmp_path / "renders")
    # one picture per robot at its middle withheld frame: own | vote | on board | frame, each H x W
    import cv2

    for a in agents:
        img = cv2.imread(out["renders"][a["id"]])
        assert img is not None and img.shape == (H, 4 * W, 3), a["id"]
    for key in (*team.FUSED_KEYS, *team.PER_ROBOT):
        p = out[key]["protocols"]
        assert set(p) == {"sensor", "keyframes", "novel", "tracked", "novel-tracked", team.ROBOT_CAMERA}, key
        for a in agents:
            assert p["sensor"][a["task"]] == out[key]["roi_psnr"][a["task"]]
            per = out[key]["protocols_per_frame"]
            assert set(per["novel"][a["task"]]) == set(per["novel-tracked"][a["task"]]) == {6}
            assert len(per["sensor"][a["task"]]) == 7
            # novel: the robot's camera on the withheld frame, exactly its figure under the robot's camera model
            assert per["novel"][a["task"]][6] == per[team.ROBOT_CAMERA][a["task"]][6]
            # these robots model no exposure, blur or pose correction: their camera renders the bare sensor pose
            assert p[team.ROBOT_CAMERA][a["task"]] == pytest.approx(p["sensor"][a["task"]], abs=1e-3)
            assert p["keyframes"][a["task"]] is not None and p["tracked"][a["task"]] is not None
    # the map made on board holds the robot's whole own map, the server's its shared subset
    for a in agents:
        assert out["with_own"]["n"][a["id"]] >= len(a["_own_map"])
        assert out["for_robot"]["n"][a["id"]] >= len(a["_history"][-1][1])
    # what draws each robot's ROI in the vote map: every robot diagnosed, the weights add up to the ROI
    for a in agents:
        c = out["cover"][a["id"]]
        assert sum(c["mass"].values()) == pytest.approx(1.0, abs=1e-6)
        assert 0.0 < c["mass"]["own"] <= 1.0
        assert c["own_missing"]["of"] == len(a["_history"][-1][1])
    run = {"team": "synthetic", "agents": [{"id": a["id"], "task": a["task"], "cover": out["cover"][a["id"]]}
                                           for a in agents]}
    md = team.cover_table([run, run])
    assert md.count("\n") == 1 + 2 and "| synthetic | agent_a, t0 |" in md and "| 2 |" in md
    # without the robot's camera, novel renders the owner's predicted views as given
    from gausslite.evaluation import TrackedView

    bare = [{**a, "_predicted": {6: TrackedView(frames[6].c2w, np.zeros(6), 0.0, 0.0, 0.0, 0)}} for a in agents]
    for a in bare:
        a.pop("_seen")
    alone = team.fused_scores(bare, fuse, 0, 3, protocols=("sensor", "novel"))
    for a in agents:
        assert alone["vote"]["protocols"]["novel"][a["task"]] == pytest.approx(
            out["vote"]["protocols"]["novel"][a["task"]], abs=1e-3)  # no correction, exposure or blur to model
    # sensor alone: no other protocol is scored but the robots' camera model (it costs renders only)
    only = team.fused_scores(agents, fuse, 0, 3, protocols=("sensor",))
    assert set(only["vote"]["protocols"]) == {"sensor", team.ROBOT_CAMERA}  # the robot's camera goes with sensor
    # the per-agent rows of a run and their summary over runs
    runs = []
    for r in range(2):
        run = _run("synthetic", r, own=(20, 22), concat=(19, 21), vote=(20.5, 22.5), refine=(21, 23))
        for i, a in enumerate(run["agents"]):
            a["protocols"] = {q: {"own_roi_psnr": 20.0 + i + d, "own_frames": 6,
                                  **{f"{k}_roi_psnr": 19.0 + i + d + 0.5 * r for k in (*team.FUSED_KEYS, "for_robot")}}
                              for q, d in (("sensor", 0.0), ("keyframes", 2.0), ("tracked", 1.0))}
        runs.append(run)
    s = summarise(runs)
    pa = s["synthetic"]["agents"]["agent_b"]["protocols"]
    assert set(pa) == {"sensor", "keyframes", "tracked"} and pa["keyframes"]["runs"] == 2
    assert pa["keyframes"]["own_roi_psnr"] == pytest.approx(23.0)
    assert pa["keyframes"]["vote_minus_own"] == pytest.approx(-0.75) and pa["keyframes"]["vote_minus_own_gain"] is None
    assert pa["tracked"]["for_robot_minus_own_std"] == pytest.approx(np.std([-1.0, -0.5], ddof=1))
    md = team.protocol_table({"teams": s})
    assert "| synthetic | agent_b, tb | keyframes | 23.00 ± 0.00 |" in md and md.count("\n") == 1 + 6
    # with per-frame figures, every gain pairs frame by frame over runs × frames
    for r, run in enumerate(runs):
        for a in run["agents"]:
            row = a["protocols"]["novel"] = dict(a["protocols"]["sensor"], pose="predicted")
            row["own_per_frame"] = {str(i): 20.0 + i for i in range(8)}
            for k in (*team.FUSED_KEYS, "for_robot"):
                row[f"{k}_per_frame"] = {str(i): 20.0 + i - 1.0 + (0.1 if (i + r) % 2 else -0.1) for i in range(8)}
    g = summarise(runs)["synthetic"]["agents"]["agent_a"]["protocols"]["novel"]["vote_minus_own_gain"]
    assert g["n"] == 16 and g["gain"] == pytest.approx(-1.0) and g["ci_low"] <= -1.0 <= g["ci_high"]
    assert g["interval"] == "run-clustered" and g["runs"] == 2  # both runs' gains are −1.0: a zero-width interval
    assert "[" in team.protocol_table({"teams": summarise(runs)})
    # what the refinement's views add to the vote, paired frame by frame: +0.4 in run 0, +0.6 in run 1
    for r, run in enumerate(runs):
        for a in run["agents"]:
            row = a["protocols"]["novel"]
            row["refine_per_frame"] = {i: v + 0.4 + 0.2 * r for i, v in row["vote_per_frame"].items()}
    s = summarise(runs)
    views = s["synthetic"]["agents"]["agent_a"]["protocols"]["novel"]["refine_minus_vote_gain"]
    assert views["gain"] == pytest.approx(0.5) and views["runs"] == 2 and views["ci_low"] < 0.4 < 0.6 < views["ci_high"]
    lines = team.long_table({"teams": s}).splitlines()
    assert lines[0].endswith("| team map made on board − own | served team map − vote |") and len(lines) == 4
    assert lines[2].startswith("| synthetic | agent_a, ta | 20.00 | -1.00 [") and lines[2].endswith("|")
    assert lines[2].split(" | ")[-1].startswith("+0.50 [")
    # a summary from before the column: a dash
    del s["synthetic"]["agents"]["agent_a"]["protocols"]["novel"]["refine_minus_vote_gain"]
    del s["synthetic"]["agents"]["agent_a"]["protocols"]["novel"]["refine_minus_vote"]
    assert team.long_table({"teams": s}).splitlines()[2].endswith(" | – |")


def _team_result(bound, vote_minus_own):
    agent = {"task": "synth-pick-object", "share_pct": 100 * (bound or 0.08), "upload_ratio": 1.2,
             "bytes_per_gaussian": 13.0, "own_roi_psnr": 22.0, "vote_minus_own": vote_minus_own,
             "for_robot_minus_own": vote_minus_own + 0.1, "refine_minus_own": 1.0}
    agent.update({f"{k}_std": 0.1 for k in list(agent) if k != "task"})
    return {"settings": {"overrides": [] if bound is None else [f"agent.share.max_fraction={bound}"]},
            "teams": {"synthetic": {"runs": 3, "agents": {"agent_a": agent}}}}


def test_share_curve_orders_the_bounds_and_keeps_the_figures(tmp_path):
    import json

    from bench.team import main, share_bound, share_curve

    res = [_team_result(0.25, -1.0), _team_result(None, -4.6), _team_result(0.15, -3.5)]
    assert [share_bound(r) for r in res] == [0.25, None, 0.15]
    pts = share_curve(res, default_bound=0.08)["synthetic"]["agent_a"]["points"]
    assert [p["bound"] for p in pts] == [0.08, 0.15, 0.25]
    assert [p["vote_minus_own"] for p in pts] == [-4.6, -3.5, -1.0] and pts[0]["runs"] == 3
    with pytest.raises(ValueError):
        share_curve(res)  # a result without a bound and no default
    with pytest.raises(ValueError):
        share_curve([_team_result(0.15, -3.5), _team_result(0.15, -3.0)])
    files = []
    for i, r in enumerate(res):
        files.append(tmp_path / f"r{i}.json")
        files[-1].write_text(json.dumps(r))
    out = tmp_path / "team.json"
    out.write_text(json.dumps({"teams": {"kept": True}}))
    assert main(["--curve", ",".join(map(str, files)), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["teams"] == {"kept": True} and len(doc["share_curve"]["teams"]["synthetic"]["agent_a"]["points"]) == 3
    md = (tmp_path / "team_curve.md").read_text()
    assert "| synthetic | agent_a, synth-pick-object | 15 % |" in md and "-3.50 ± 0.10" in md


def test_share_curve_under_a_protocol_reads_its_figures_and_keeps_the_bytes(tmp_path):
    import json

    from bench.team import main, share_curve

    res = [_team_result(0.25, -1.0), _team_result(0.5, -0.4)]
    for r, novel in zip(res, (-2.0, -0.6)):
        a = r["teams"]["synthetic"]["agents"]["agent_a"]
        a["view_ratio"] = 6.0
        gain = {"gain": novel, "ci_low": novel - 0.3, "ci_high": novel + 0.3, "runs": 3, "n": 30,
                "interval": "run-clustered"}
        a["protocols"] = {"novel": {"own_roi_psnr": 21.0, "own_roi_psnr_std": 0.2, "refine_minus_own": novel,
                                    "refine_minus_own_std": 0.4, "refine_minus_own_gain": gain}}
    pts = share_curve(res, protocol="novel")["synthetic"]["agent_a"]["points"]
    assert [p["refine_minus_own"] for p in pts] == [-2.0, -0.6] and pts[1]["refine_minus_own_gain"]["ci_low"] == pytest.approx(-0.9)
    assert [p["own_roi_psnr"] for p in pts] == [21.0, 21.0]  # the protocol's own map, not the sensor figure (22.0)
    assert [p["share_pct"] for p in pts] == [25.0, 50.0] and pts[0]["view_ratio"] == 6.0  # bytes from the summary
    assert [p["refine_minus_own"] for p in share_curve(res)["synthetic"]["agent_a"]["points"]] == [1.0, 1.0]
    with pytest.raises(ValueError, match="tracked"):
        share_curve(res, protocol="tracked")  # not scored under it
    files = []
    for i, r in enumerate(res):
        files.append(tmp_path / f"r{i}.json")
        files[-1].write_text(json.dumps(r))
    out = tmp_path / "long.json"
    assert main(["--curve", ",".join(map(str, files)), "--curve-protocol", "novel", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["share_curve"]["protocol"] == "novel"
    md = (tmp_path / "long_curve.md").read_text()
    assert "under `novel`" in md and "| synthetic | agent_a, synth-pick-object | 50 % | 50.0 | 1.20 | 6.00 |" in md
    assert "-0.60 [-0.90, -0.30] (σ runs 0.40)" in md
    with pytest.raises(SystemExit):
        main(["--curve", str(files[0]), "--curve-protocol", "nonsense", "--out", str(out)])


def test_a_team_runs_end_to_end_through_the_harness(tmp_path, monkeypatch):
    """``python -m bench.team`` on a tiny synthetic circle (12 frames at 64×48): both robots driven by the team
    harness in process, one after the other, each sharing to its own store; their own and fused maps scored and the
    results written. Figures on a tiny scene are not measurements: only what the bench computes from them is checked."""
    import json

    import bench.team as team
    from bench.realtime import scenes

    monkeypatch.setitem(scenes.SCENES, "synthetic_circle",
                        {**scenes.SCENES["synthetic_circle"], "frames": 12, "width": 64, "height": 48, "cap": 1000})
    monkeypatch.setattr(team, "LONG_REFINE_ITERS", 2)
    settings = {**team.fuse_settings(), "refine_iters": 5}
    monkeypatch.setattr(team, "fuse_settings", lambda: settings)
    out = tmp_path / "team.json"
    rc = team.main(["--teams", "synthetic", "--runs", "1", "--protocols", "sensor", "--out", str(out),
                    "--work", str(tmp_path / "work"), "--budget", "0.2", "--set", "mapper.iters_per_frame=3",
                    "--set", "mapper.warmup_iters=1", "--set", "agent.share.worker=thread"])
    assert rc == 0
    res = json.loads(out.read_text())
    (run,) = res["runs"]
    assert run["end_state"] == "FINISHED" and run["error"] == "" and res["failed_runs"] == []
    assert [a["id"] for a in run["agents"]] == ["agent_a", "agent_b"]
    for a in run["agents"]:
        assert a["wall_s"] > 0 and a["keyframes"] >= 1 and a["pushes"] >= 1 and not a["last_error"]
        assert a["end_state"] == "FINISHED" and not a["error"] and a["frames_failed"] == 0  # how its mission ended
        assert a["own_roi_psnr"] is not None and a["vote_roi_psnr"] is not None
        times = [p["t"] for p in a["push_log"]]
        assert times == sorted(times) and times[-1] <= a["wall_s"]  # on the robot's own mission clock
    # the fused map over time merges both robots' pushes by mission time
    assert {e["agent"] for e in run["fused"]["timeline"]} == {"agent_a", "agent_b"}
    assert res["teams"]["synthetic"]["runs"] == 1
    assert out.with_suffix(".md").is_file() and (tmp_path / "team_synthetic.png").is_file()
