"""``gausslite sim``: a tiny two-agent simulation with real processes (parser, fusion server, two agents)
on loopback, fusion (concat / vote / vote+refine), evaluation and the report."""

from __future__ import annotations

import json
import math
import os

import pytest
from pydantic import ValidationError

from gausslite.config import load_config
from gausslite_services.sim import plan_agents, run_sim

TINY = ["sim.scene.width=64", "sim.scene.height=48", "sim.scene.frames=3", "agent.downscale=1",
        "agent.push.every=2", "mapper.iters_per_frame=3", "mapper.warmup_iters=1", "mapper.seeding.seeds_per_frame=150",
        "sim.fuse.refine_iters=3", "agent.share.finetune_iters=20", "agent.refine_views.min_roi_px=1",
        "agent.refine_views.budget_ratio=8", "fusion.team_map.refine_iters=3",
        # the team map made from the final subsets starts at once, not min_interval_s after the one before it
        "fusion.team_map.min_interval_s=0"]


def test_tiny_sim_writes_report_and_cleans_up(tmp_path):
    # every 2nd frame withheld from the 2nd: of 3 frames the agents map 0 and 2, and frame 1 is scored under novel
    res = run_sim(tmp_path / "sim", None, overrides=TINY + ["agent.scoring.novel_every=2"], timeout_s=240,
                  progress=False)
    rep = json.loads((tmp_path / "sim" / "report.json").read_text())
    assert rep == json.loads(json.dumps(res.report))
    assert [a["id"] for a in rep["agents"]] == ["agent_a", "agent_b"]
    # where the wall time went: every stage timed, together within the run's own seconds
    assert list(rep["stages_s"]) == ["scene", "services", "missions", "scoring", "cover"]
    assert all(v >= 0 for v in rep["stages_s"].values()) and rep["stages_s"]["services"] > 0
    assert sum(rep["stages_s"].values()) >= rep["seconds"] - 1.0
    assert [a["task"] for a in rep["agents"]] == ["synth-pick-object", "synth-find-chair"]
    for a in rep["agents"]:
        assert set(a) >= {"id", "task", "roi_psnr", "n_gaussians", "n_shared", "share_pct", "bytes_per_gaussian"}
        assert a["roi_psnr"] is not None and 5 < a["roi_psnr"] < 80
        assert 0 < a["n_shared"] < a["n_gaussians"]
        assert math.isclose(a["share_pct"], 100 * a["n_shared"] / a["n_gaussians"], rel_tol=1e-3)
        assert 0 < a["bytes_per_gaussian"] < 100
    assert set(rep["fused"]) == {"concat", "vote", "for_robot", "with_own", "refine", "team_map"}
    tm = rep["fused"]["team_map"]  # the served team map, once made from the final subsets and views
    assert tm["refine_record"]["train_views"] + tm["refine_record"]["heldout_views"] >= 1
    for a in rep["agents"]:
        assert 0 < a["view_bytes"] <= 8 * a["final_subset_bytes"] and a["views_sent"] >= 1
    shared = sum(a["n_shared"] for a in rep["agents"])
    assert rep["fused"]["concat"]["n_gaussians"] == shared
    assert rep["fused"]["vote"]["n_gaussians"] <= shared
    for k, f in rep["fused"].items():
        assert set(f) >= {"roi_psnr_mean", "roi_psnr_per_task", "n_gaussians", "seconds"}
        assert set(f["roi_psnr_per_task"]) == {"synth-pick-object", "synth-find-chair"}
        assert f["roi_psnr_mean"] is not None and 5 < f["roi_psnr_mean"] < 80
    md = (tmp_path / "sim" / "report.md").read_text()
    assert "| agent_a | synth-pick-object |" in md and "| refine |" in md
    assert rep["renders"] and all((tmp_path / "sim" / r["path"]).is_file() for r in rep["renders"])
    # bandwidth fields: every push logged, the total is their sum, the plot exists
    for a in rep["agents"]:
        assert a["push_log"] and a["final_subset_bytes"] > 0
        assert a["total_upload_bytes"] == sum(q["bytes_sent"] for q in a["push_log"]) >= a["final_subset_bytes"]
        assert not a["push_log"][0]["delta"]  # the first push has no base
    assert rep["pushes_plot"] == "pushes.png" and (tmp_path / "sim" / "pushes.png").is_file()
    assert "total upload bytes" in md and "![bytes per push" in md
    # the agents' config holds the settings given, not every default: the scene's sensor profile fills in the rest
    import yaml

    given = yaml.safe_load((tmp_path / "sim" / "config.yaml").read_text())
    assert given["mapper"]["iters_per_frame"] == 3 and "roi_render" not in given["mapper"]  # a default: not given
    assert "final_iters_per_keyframe" not in given["mapper"] and "lambda_depth" not in given["mapper"]
    # the deployed agents map with roi_render: context, so their own maps are the context figure
    assert rep["settings"]["mapper"]["roi_render"] == "context"
    assert rep["settings"]["contest_radius"] == 1 and "neighbourhood of radius 1" in md
    for a in rep["agents"]:
        assert a["own_roi_psnr_context"] == a["roi_psnr"]
        assert math.isclose(a["vote_minus_own_context"], rep["fused"]["vote"]["minus_own"][a["task"]])
    assert "vote − own context" in md
    # each fused map's gain over the robot's own map: the mean of the paired per-frame differences (sensor, every
    # frame), with its interval; the team map made for each robot holds its whole subset
    for k, f in rep["fused"].items():
        for a in rep["agents"]:
            t = a["task"]
            own, fused = a["protocols"]["sensor"]["roi_psnr_per_frame"], f["protocols"]["sensor"][t]["roi_psnr_per_frame"]
            assert set(own) == set(fused) and len(own) == 3
            assert math.isclose(f["minus_own"][t], sum(fused[i] - own[i] for i in own) / 3, abs_tol=1e-9)
            g = f["minus_own_gain"][t]
            assert g["n"] == 3 and g["ci_low"] <= g["gain"] <= g["ci_high"]
    assert set(rep["fused"]["for_robot"]["kept"]) == {"agent_a", "agent_b"}
    # what covers each ROI in the team map: shares of the ROI weight that add up, and a picture per robot
    cov = rep["fused"]["vote"]["cover"]
    assert set(cov) == {"agent_a", "agent_b"}
    for a, c in cov.items():
        assert math.isclose(sum(c["mass"].values()), 1.0, abs_tol=1e-6)
        assert 0 <= c["own_missing"]["rows"] <= c["own_missing"]["of"]
        assert (tmp_path / "sim" / c["image"]).is_file()
    assert "What covers each robot's ROI" in md
    # the timeline scores each task on the team map made for its robot as well
    assert rep["fused_timeline"] and all(set(e["roi_psnr_for_robot"]) <= {"synth-pick-object", "synth-find-chair"}
                                         for e in rep["fused_timeline"])
    assert any(e["roi_psnr_for_robot"] for e in rep["fused_timeline"])
    # own-map figure of a roi_render=context run of the same sim
    from gausslite.team import attach_context_baseline

    ctx = json.loads(json.dumps(rep))
    ctx["settings"]["mapper"]["roi_render"] = "context"
    for a in ctx["agents"]:
        a["roi_psnr"] = 20.0
        a["protocols"]["sensor"]["roi_psnr_per_frame"] = {k: 20.0 for k in a["protocols"]["sensor"]["roi_psnr_per_frame"]}
    merged = attach_context_baseline(json.loads(json.dumps(rep)), ctx)
    for a in merged["agents"]:
        vote = rep["fused"]["vote"]["protocols"]["sensor"][a["task"]]["roi_psnr_per_frame"]
        assert a["own_roi_psnr_context"] == 20.0
        assert math.isclose(a["vote_minus_own_context"], sum(v - 20.0 for v in vote.values()) / len(vote))
    ctx["settings"]["mapper"]["roi_render"] = "active"
    with pytest.raises(ValueError):
        attach_context_baseline(rep, ctx)
    # every map under each scoring protocol (agent.scoring): the own maps scored by their agents, the fused maps
    # by the sim, each fused figure beside the own one under the same protocol; sensor is the top-level figure
    protos = {"sensor", "keyframes", "novel", "tracked", "novel-tracked"}
    assert rep["settings"]["scoring"]["protocols"] == ["sensor", "keyframes", "novel", "tracked", "novel-tracked"]
    for a in rep["agents"]:
        p = a["protocols"]
        assert set(p) == protos
        assert p["sensor"]["roi_psnr"] == pytest.approx(a["roi_psnr_all_frames"]) and p["sensor"]["frames_scored"] == 3
        assert p["keyframes"]["frames_scored"] == a["frames_mapped"] == 2  # an every-frame replay, frame 1 withheld
        assert p["tracked"]["frames_scored"] == 1  # every 5th of 3 frames
        assert p["novel"]["frames_scored"] == p["novel-tracked"]["frames_scored"] == 1  # the withheld frame
        assert p["novel"]["pose"] == "predicted" and set(p["novel"]["roi_psnr_per_frame"]) == {"1"}
        assert all(v["roi_psnr"] is not None for v in p.values())
    # the fused maps: tracked / novel-tracked at the views the robot tracked against its own map (@own), not fitted
    # against each fused map (agent.scoring.track_fused is off)
    fused_protos = {"sensor", "keyframes", "novel", "tracked@own", "novel-tracked@own"}
    for k, f in rep["fused"].items():
        # @own: the same frames at the pose and exposure the robot's own map was tracked at
        assert set(f["protocols"]) == fused_protos, k
        for a in rep["agents"]:
            t = a["task"]
            assert f["protocols"]["sensor"][t]["roi_psnr"] == f["roi_psnr_per_task"][t]
            # the views the robot uploaded (a crop of each mapped frame that shows its ROI, within the budget)
            assert f["protocols"]["keyframes"][t]["frames_scored"] == a["views_sent"], (k, t)
            assert f["protocols"]["tracked@own"][t]["frames_scored"] == 1
            # the fused map at the robot's predicted view of the withheld frame: one frame, paired with its own map's
            assert f["protocols"]["novel"][t]["frames_scored"] == 1 and f["protocols"]["novel"][t]["pose"] == "predicted"
            for q in fused_protos:
                v = f["protocols"][q][t]
                own = a["protocols"][q.split("@")[0]]
                both = set(v["roi_psnr_per_frame"]) & set(own["roi_psnr_per_frame"])
                want = sum(v["roi_psnr_per_frame"][i] - own["roi_psnr_per_frame"][i] for i in both) / len(both)
                assert v["roi_psnr"] is not None and math.isclose(v["minus_own"], want, abs_tol=1e-9), (k, t, q)
    # the answer first: each robot's own map and the team map it can load now, with the bytes it sent and a picture;
    # then the protocols × the maps
    assert md.index("## The answer") < md.index("## The protocols × the maps") < md.index("## Agents (own map")
    lead = md[md.index("## The answer"):md.index("## The protocols × the maps")]
    assert "under `novel`" in lead and "team_map (`Fuse(team_map=true)`)" in lead and "bytes sent" in lead
    assert "| agent_a | synth-pick-object |" in lead and "![team_map " in lead
    for a in rep["agents"]:
        assert f"{a['total_upload_bytes'] + a['view_bytes']:,}" in lead
    # the maps a user can open: each robot's own, every fused one, the team map for each robot, with the command
    sim = tmp_path / "sim"
    assert set(rep["own_maps"]) == {"agent_a", "agent_b"}
    for key in ("for_robot", "with_own"):
        assert rep["fused"][key]["ply"] == {a: f"maps/{key}_{a}.ply" for a in ("agent_a", "agent_b")}
    assert rep["fused"]["team_map"]["ply"] == {"agent_a": "maps/team_map.ply", "agent_b": "maps/team_map.ply"}
    files = [*rep["own_maps"].values(), *(f for v in rep["fused"].values() for f in v["ply"].values())]
    for f in files:
        assert (sim / f).stat().st_size > 1000 and f"`gausslite view {f}`" in lead, f
    # the team map made on board holds the robot's whole map: its own region is its own map's, whatever others sent
    for a in rep["agents"]:
        g = rep["fused"]["with_own"]["protocols"]["sensor"][a["task"]]
        assert g["minus_own"] > -0.1, (a["task"], g["minus_own"])
        assert rep["fused"]["with_own"]["kept"][a["id"]] > a["n_shared"]  # its own rows: more than it shared
    assert "| tracked | own |" in md and "| keyframes | vote |" in md and "| sensor | for_robot |" in md
    assert "| novel-tracked@own | team_map |" in md and "how well a robot could localise" in md
    assert md.index("| sensor | own |") < md.index("| keyframes | own |") < md.index("| novel | own |") \
        < md.index("| tracked | own |")
    # every child process is gone
    assert set(res.pids) == {"parser", "fusion_server", "agent_a", "agent_b"}
    for pid in res.pids.values():
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)


def test_sim_plans_room0_tasks(room0_dir):
    plans = plan_agents(str(room0_dir), load_config())
    assert [p.task_id for p in plans] == ["room0-pick-plant", "room0-find-ottoman"]
    assert plans[0].dataset == plans[1].dataset == str(room0_dir)


def test_sim_rejects_bad_settings_before_starting(tmp_path):
    with pytest.raises(ValidationError, match="iters_per_frame"):
        run_sim(tmp_path / "out", overrides=["mapper.iters_per_frame=0"])
    assert not (tmp_path / "out" / "config.yaml").exists()  # failed before writing the agents' config
