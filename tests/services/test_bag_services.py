"""Bags wherever a dataset path is accepted by the services: the agent's replay mission and ``gausslite sim``
(planning and the up-front bag check), plus ``gausslite ablate`` on a bag."""

from __future__ import annotations

import logging
import time

import grpc
import pytest

from gausslite.cli import main
from gausslite.config import load_config
from gausslite.datasets import load_dataset
from gausslite.datasets.bag import BagError
from gausslite.ros.export import export_bag
from gausslite.synthetic import make_scene
from gausslite_rpc import agent_pb2
from gausslite_services.agent.client import AgentClient
from gausslite_services.agent.server import AgentSettings, serve as serve_agent
from gausslite_services.common.server import ServerOptions
from gausslite_services.sim import plan_agents
from gausslite_services.sim.launch import check_bags
from tests._waits import WORK_S

TINY = ["agent.push.every=2", "agent.upload_keyframe_every=1", "mapper.iters_per_frame=3", "mapper.warmup_iters=1",
        "mapper.seeding.seeds_per_frame=150",
        "agent.share.worker=thread"]  # the share worker process has tests of its own (test_agent_live.py)


@pytest.fixture(scope="module")
def bag_scene(tmp_path_factory):
    """The synthetic two-agent scene with each agent's sequence as a rosbag2 MCAP (annotations copied)."""
    src = tmp_path_factory.mktemp("scene")
    make_scene(src, seed=0, width=64, height=48, frames=4, progress=False)
    out = tmp_path_factory.mktemp("bags")
    for name in ("agent_a", "agent_b"):
        export_bag(load_dataset(src / name), out / name)
    return src, out


def test_exported_scene_bags_match_the_folders(bag_scene):
    src, out = bag_scene
    for name in ("agent_a", "agent_b"):
        a, b = load_dataset(src / name), load_dataset(out / name)
        assert len(a) == len(b) == 4 and a.intrinsics == b.intrinsics
        assert [t.id for t in b.annotations.tasks] == [t.id for t in a.annotations.tasks]


def test_agent_replays_a_bag(bag_scene, tmp_path):
    _src, out = bag_scene
    cfg = load_config(None, TINY + ["agent.bag.max_pose_dt=0.01"]).agent
    assert cfg.bag.max_pose_dt == 0.01
    ag = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="solo", data_dir=str(tmp_path / "a"),
                                                          data_roots=(str(out),), config=cfg))
    c = AgentClient(ag.address)
    try:
        c.wait_ready(10)
        text = load_dataset(out / "agent_a").annotations.tasks[0].text
        m = c.start_mission(text, dataset_path=str(out / "agent_a"))
        deadline = time.monotonic() + WORK_S
        while c.status(m.mission_id).state != agent_pb2.MISSION_STATE_REPLAY_DONE:
            assert time.monotonic() < deadline, "replay did not finish"
            time.sleep(0.5)
        s = c.finish(m.mission_id, timeout_s=WORK_S)
        assert s.status.frames_received == 4 and s.status.frames_mapped == 4
        # a bad bag is refused with the bag's one clear error
        bad_cfg = load_config(None, TINY + ["agent.bag.rgb_topic=/nope"]).agent
        ag2 = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="bad", data_roots=(str(out),), config=bad_cfg))
        c2 = AgentClient(ag2.address)
        try:
            with pytest.raises(grpc.RpcError) as e:
                c2.start_mission(text, dataset_path=str(out / "agent_a"))
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert "rgb topic '/nope' is not in the bag" in e.value.details()
        finally:
            c2.close()
            ag2.stop(0)
    finally:
        c.close()
        ag.stop(0)


def test_sim_plans_bag_agents_and_checks_bags_before_starting(bag_scene):
    _src, out = bag_scene
    cfg = load_config()
    plans = plan_agents(str(out), cfg)
    assert [p.dataset for p in plans] == [str(out / "agent_a"), str(out / "agent_b")]
    assert [p.task_id for p in plans] == ["synth-pick-object", "synth-find-chair"]
    check_bags(plans, cfg.agent)  # good bags pass
    bad = load_config(None, ["agent.bag.depth_topic=/nope"])
    with pytest.raises(BagError, match="depth topic '/nope' is not in the bag"):
        check_bags(plans, bad.agent)


def test_sim_cli_bag_flags_become_agent_overrides(bag_scene, capsys):
    _src, out = bag_scene
    rc = main(["sim", "--dataset", str(out), "--out", str(out.parent / "simout"), "--rgb-topic", "/nope",
               "--timeout", "30"])
    assert rc == 1
    err = capsys.readouterr().err
    assert "rgb topic '/nope' is not in the bag" in err and "topics found:" in err


def test_ablate_rejects_a_bad_bag_with_one_error(bag_scene, tmp_path, caplog):
    _src, out = bag_scene
    with caplog.at_level(logging.ERROR):
        rc = main(["ablate", "--dataset", str(out / "agent_a"), "--world-frame", "nowhere", "--out", str(tmp_path)])
    assert rc == 2
    errors = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "TF chain 'nowhere' <- 'camera_color_optical_frame' does not connect" in errors[0]


def _serve_agent_as_documented(argv, data_dir):
    """``gausslite serve agent ARGV`` in-process: the real CLI parser and flag → environment → settings
    path of ``gausslite serve agent``, then the agent server (not its blocking ``run``)."""
    from gausslite.cli import build_parser
    from gausslite_services.cli.cmd_serve import resolve_options
    from gausslite_services.cli.cmd_sim import export_agent_env
    from gausslite_services.agent.server import settings_from_env

    args = build_parser().parse_args(["serve", "agent", *argv, "--data-dir", str(data_dir)])
    env: dict = {}
    export_agent_env(args, env)
    opts, config_path = resolve_options(args, env={})
    return serve_agent(opts, settings_from_env(config_path, env, token=opts.token))


def test_bag_to_fused_map_as_documented(bag_scene, tmp_path):
    """docs/ros.md "From bags to a fused map": two robots' rosbag2 recordings (no objects.json in them, as a
    robot records them), the parser, fusion server and two agents, the robot-side calls
    ``start_mission(task, dataset_path=BAG, annotations_path=SCENE)`` → ``wait_state`` → ``finish``,
    then ``fuse`` → ``download_fused`` → a PLY: the fused map has both agents' subsets."""
    import shutil

    from gausslite.viewer.export import load_map
    from gausslite_services.fusion_server.client import FusionClient
    from gausslite_services.fusion_server.server import serve as serve_fusion
    from gausslite_services.parser.server import serve as serve_parser

    src, out = bag_scene
    tasks = {t.id: t.text for t in load_dataset(src / "agent_a").annotations.tasks}
    # the robots' recordings: bags without annotations; the operator writes objects.json (here the scene's)
    bags = tmp_path / "bags"
    for name in ("agent_a", "agent_b"):
        shutil.copytree(out / name, bags / name)
        for f in ("objects.json", "tasks.json"):
            (bags / name / f).unlink()
    scene = tmp_path / "scene"
    scene.mkdir()
    shutil.copy(src / "objects.json", scene / "objects.json")  # given with annotations_path (robot1) ...
    shutil.copy(src / "objects.json", bags / "agent_b" / "objects.json")  # ... or beside the bag (robot2)

    parser = serve_parser(ServerOptions(port=0))
    fusion_srv = serve_fusion(ServerOptions(port=0), data_dir=str(tmp_path / "fusion"))
    fast = [a for kv in TINY for a in ("--set", kv)]
    agents = {rid: _serve_agent_as_documented(["--port", "0", "--agent-id", rid, "--parser", parser.address,
                                               "--fusion", fusion_srv.address, "--data-roots", f"{bags},{scene}",
                                               *fast], tmp_path / "agents")
              for rid in ("robot1", "robot2")}
    clients = {rid: AgentClient(ag.address) for rid, ag in agents.items()}
    try:
        for c in clients.values():
            c.wait_ready(10)
        assert agents["robot1"].servicer.settings.parser_address == parser.address
        assert agents["robot1"].servicer.settings.config.mapper.iters_per_frame == 3
        # the bag alone gives the agent no relevance source: FAILED_PRECONDITION says what to provide
        with pytest.raises(grpc.RpcError) as e:
            clients["robot1"].start_mission(tasks["synth-pick-object"], dataset_path=str(bags / "agent_a"))
        assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert "objects.json" in e.value.details() and "agent.relevance_backend=onnx" in e.value.details()
        # robot side, as documented
        plan = {"robot1": (bags / "agent_a", tasks["synth-pick-object"], str(scene)),
                "robot2": (bags / "agent_b", tasks["synth-find-chair"], "")}
        missions = {rid: clients[rid].start_mission(text, dataset_path=str(bag), annotations_path=ann)
                    for rid, (bag, text, ann) in plan.items()}
        summaries = {}
        for rid, m in missions.items():
            assert m.replay_frames == 4 and m.agent_id == rid
            clients[rid].wait_state([agent_pb2.MISSION_STATE_REPLAY_DONE], m.mission_id, timeout_s=WORK_S)
            summaries[rid] = s = clients[rid].finish(m.mission_id, timeout_s=WORK_S)  # the final pass and push, busy or not
            assert s.final_push_ok and s.status.frames_mapped == 4 and s.n_shared > 0
        with FusionClient(fusion_srv.address) as fusion:
            stats = fusion.stats()["agents"]
            for rid, s in summaries.items():  # each agent's final subset arrived whole
                assert stats[rid]["has_complete_subset"] and stats[rid]["gaussians_received"] == s.n_shared
                assert stats[rid]["latest_map_version"] == s.pushes[-1].version
            r = fusion.fuse("vote")
            fused = fusion.download_fused(r.fused_version)
            fused.to_gaussian_map().save_ply(tmp_path / "fused.ply")
        assert r.n_gaussians == len(fused) > 0
        assert set(r.kept) == {"robot1", "robot2"} and all(r.kept[k] > 0 for k in r.kept)
        assert sum(r.kept.values()) == len(fused)
        assert r.received == {rid: s.n_shared for rid, s in summaries.items()}
        back = load_map(tmp_path / "fused.ply")  # what `gausslite view fused.ply` shows
        assert back.equals(fused)
    finally:
        for c in clients.values():
            c.close()
        for ag in agents.values():
            ag.stop(0)
        fusion_srv.stop(0)
        parser.stop(0)
