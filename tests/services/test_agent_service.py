"""Agent service: full in-process path parser + fusion + two agents with streamed frames,
bad-input status codes, and a fusion-server restart during a mission."""

from __future__ import annotations

import math
import threading
import time

import cv2
import grpc
import numpy as np
import pytest

from gausslite.datasets import load_dataset
from gausslite.synthetic import make_scene
from gausslite_rpc import agent_pb2, agent_pb2_grpc
from gausslite_services.agent.client import AgentClient
from gausslite_services.agent.frames import encode_frame
from gausslite.config import load_config
from gausslite.mission import AgentRuntime
from gausslite_services.agent.server import AgentSettings, serve as serve_agent
from gausslite_services.common.server import ServerOptions
from tests._waits import WORK_S

# every_frame ingest: these tests count mapped frames and pushes exactly (keyframe ingest: test_agent_live.py)
TINY = ["agent.ingest=every_frame", "agent.push.every=2", "agent.upload_keyframe_every=1", "agent.push.backoff_s=0.1", "agent.push.max_backoff_s=0.5",
        "mapper.iters_per_frame=3", "mapper.warmup_iters=1", "mapper.seeding.seeds_per_frame=200",
        # the plumbing of pushes and uploads, counted: the a = 1 subset at every snapshot and whole keyframes (task
        # sharing and ROI crops, the defaults: tests/services/test_agent_live.py, tests/docs/)
        "agent.share.rule=active", "agent.refine_views.crop=false", "agent.refine_views.budget_ratio=null"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    make_scene(out, seed=0, width=64, height=48, frames=4, progress=False)
    return out


@pytest.fixture(scope="module")
def parser_server():
    from gausslite_services.parser.server import serve

    srv = serve(ServerOptions(port=0))
    yield srv
    srv.stop(0)


def _fusion(data_dir, port=0):
    """A fusion server without the team map (tests/services/test_team_map.py): no refinement process beside the
    agents' pushes."""
    from gausslite.config import FusionSettings
    from gausslite_services.fusion_server.server import serve

    return serve(ServerOptions(port=port), FusionSettings(team_map={"enabled": False}), data_dir=str(data_dir))


def _code(excinfo) -> grpc.StatusCode:
    return excinfo.value.code()


def test_two_agents_stream_push_fuse_download(scene, parser_server, tmp_path):
    from gausslite_services.fusion_server.client import FusionClient

    fusion = _fusion(tmp_path / "fusion")
    cfg = load_config(None, TINY).agent
    agents = [serve_agent(ServerOptions(port=0), AgentSettings(
        agent_id=name, parser_address=parser_server.address, fusion_address=fusion.address,
        annotations_path=str(scene), data_dir=str(tmp_path / "agents"), config=cfg)) for name in ("agent_a", "agent_b")]
    plans = [("agent_a", "synth-pick-object"), ("agent_b", "synth-find-chair")]
    try:
        summaries = {}
        clients = []
        for (name, tid), ag in zip(plans, agents):
            c = AgentClient(ag.address)
            clients.append(c)
            c.wait_ready(10)
            ds = load_dataset(scene / name)
            text = ds.annotations.task_by_id(tid).text
            m = c.start_mission(text)  # task id found from the text in tasks.json
            assert m.agent_id == name and m.mission_id and list(m.graph.targets)
            r = c.stream_frames(m.mission_id, list(ds), timeout_s=60)
            assert r.frames_received == len(ds) == 4
        for (name, tid), c in zip(plans, clients):
            s = c.finish(timeout_s=WORK_S)
            summaries[name] = s
            assert s.status.state == agent_pb2.MISSION_STATE_FINISHED
            assert s.status.task_id == tid
            assert s.final_push_ok, s.status.last_error
            assert s.status.frames_mapped == 4
            # snapshots after frame 2, frame 4 and the final one (versions 1..3); a snapshot not yet
            # sent when a newer one arrives is superseded, so at least the first and the final push; a final
            # snapshot equal to the last push uploads nothing and reports the version the server holds (2)
            assert s.status.last_pushed_version in (2, 3)
            assert 2 <= s.status.pushes <= 3
            assert 0 < s.n_shared < s.status.n_gaussians
            assert math.isclose(s.share_pct, 100.0 * s.n_shared / s.status.n_gaussians, rel_tol=1e-6)
            assert s.has_roi_psnr and 5.0 < s.roi_psnr < 80.0
            assert s.bytes_per_gaussian > 0
            # Finish is idempotent
            assert c.finish(timeout_s=30).n_shared == s.n_shared
            assert list((tmp_path / "agents" / name).glob("*/map.ply"))
        fc = FusionClient(fusion.address, timeout_s=30)
        st = fc.stats()["agents"]
        for name, s in summaries.items():
            assert st[name]["gaussians_received"] == s.n_shared
            assert st[name]["latest_map_version"] == s.status.last_pushed_version
            assert st[name]["keyframes"] >= 4
        concat = fc.fuse("concat")
        assert concat.n_gaussians == sum(s.n_shared for s in summaries.values())
        vote = fc.fuse("vote", voxel_size=0.10)
        assert 0 < vote.n_gaussians <= concat.n_gaussians
        g = fc.download_fused(vote.fused_version)
        assert len(g) == vote.n_gaussians
        assert np.isfinite(g.means).all()
        fc.close()
        for c in clients:
            c.close()
    finally:
        for ag in agents:
            ag.stop(0)
        fusion.stop(0)


@pytest.fixture()
def local_agent(scene):
    cfg = load_config(None, TINY).agent
    ag = serve_agent(ServerOptions(port=0, token="s3cret"),
                     AgentSettings(agent_id="solo", annotations_path=str(scene), config=cfg))
    c = AgentClient(ag.address, token="s3cret")
    yield ag, c
    c.close()
    ag.stop(0)


def test_bad_inputs_give_precise_codes(local_agent, scene):
    ag, c = local_agent
    ds = load_dataset(scene / "agent_a")
    fr = ds[0]
    # token enforced
    with pytest.raises(grpc.RpcError) as e:
        AgentClient(ag.address).status("x")
    assert _code(e) == grpc.StatusCode.UNAUTHENTICATED
    # unknown mission
    with pytest.raises(grpc.RpcError) as e:
        c.status("nope")
    assert _code(e) == grpc.StatusCode.NOT_FOUND
    with pytest.raises(grpc.RpcError) as e:
        c.finish("nope", timeout_s=5)
    assert _code(e) == grpc.StatusCode.NOT_FOUND
    with pytest.raises(grpc.RpcError) as e:
        c.stream_frames("nope", [fr], timeout_s=10)
    assert _code(e) == grpc.StatusCode.NOT_FOUND
    # bad mission requests
    with pytest.raises(grpc.RpcError) as e:
        c.start_mission("   ")
    assert _code(e) == grpc.StatusCode.INVALID_ARGUMENT
    with pytest.raises(grpc.RpcError) as e:
        c.start_mission("Find the chair", dataset_path=str(scene / "definitely-not-here"))  # inside a data root
    assert _code(e) == grpc.StatusCode.INVALID_ARGUMENT
    with pytest.raises(grpc.RpcError) as e:
        c.start_mission("Find the chair", dataset_path="/definitely/not/here")  # outside: refused before the lookup
    assert _code(e) == grpc.StatusCode.PERMISSION_DENIED
    m = c.start_mission("Identify the chair closest to the table")
    good = encode_frame(fr, m.mission_id)

    def send(msg):
        with pytest.raises(grpc.RpcError) as e:
            c.stream_messages([msg], timeout_s=10)
        assert _code(e) == grpc.StatusCode.INVALID_ARGUMENT, e.value.details()
        return e.value.details()

    bad = agent_pb2.FrameMsg(); bad.CopyFrom(good); bad.color = b"not an image"
    assert "colour" in send(bad)
    bad = agent_pb2.FrameMsg(); bad.CopyFrom(good); bad.c2w[5] = float("nan")
    assert "NaN" in send(bad)
    bad = agent_pb2.FrameMsg(); bad.CopyFrom(good); del bad.c2w[:]; bad.c2w.extend([1.0] * 12)
    assert "16" in send(bad)
    bad = agent_pb2.FrameMsg(); bad.CopyFrom(good)
    bad.depth = cv2.imencode(".png", np.ones((10, 10), np.uint16))[1].tobytes()
    assert "depth is 10x10" in send(bad)
    bad = agent_pb2.FrameMsg(); bad.CopyFrom(good); bad.depth_scale = 0.0
    assert "depth_scale" in send(bad)
    bad = agent_pb2.FrameMsg(); bad.CopyFrom(good); bad.intrinsics.fx = -1
    assert "fx" in send(bad)
    # nothing malformed got in; a good frame still works
    assert c.stream_messages([good], timeout_s=30).frames_received == 1
    st = c.status(m.mission_id)
    assert st.frames_received == 1
    # a second mission while the first one runs → FAILED_PRECONDITION
    with pytest.raises(grpc.RpcError) as e:
        c.start_mission("Map the chairs")
    assert _code(e) == grpc.StatusCode.FAILED_PRECONDITION
    s = c.finish(m.mission_id, timeout_s=WORK_S)
    assert s.status.frames_mapped == 1 and not s.final_push_ok  # no fusion server configured
    with pytest.raises(grpc.RpcError) as e:
        c.stream_messages([good], timeout_s=10)
    assert _code(e) == grpc.StatusCode.FAILED_PRECONDITION
    # server is still healthy after all that
    from gausslite_services.cli.cmd_health import check_health

    assert check_health(ag.address, "gausslite.v1.Agent") == "SERVING"


def test_fusion_restart_during_mission(scene, tmp_path):
    """The fusion server goes down mid-mission and comes back on the same port and data dir: the agent
    keeps mapping, retries with backoff and completes its final push."""
    from gausslite.parser import TaskParser
    from gausslite_services.fusion_server.client import FusionClient

    data = tmp_path / "fusion"
    f1 = _fusion(data)
    port = f1.port
    cfg = load_config(None, TINY + ["agent.push.final_timeout_s=60"]).agent
    ds = load_dataset(scene / "agent_a")
    text = ds.annotations.task_by_id("synth-pick-object").text
    client = FusionClient(f1.address, timeout_s=5)
    rt = AgentRuntime("robot1", text, TaskParser().parse(text), cfg, annotations=ds.annotations, fusion=client)
    f2 = None
    try:
        rt.submit(ds[0]); rt.submit(ds[1])
        t0 = time.monotonic()
        while len(rt.pusher.pushes) < 1 and time.monotonic() - t0 < 60:
            time.sleep(0.05)
        assert len(rt.pusher.pushes) == 1
        f1.stop(0)
        rt.submit(ds[2]); rt.submit(ds[3])
        assert rt.wait_mapped(WORK_S)
        t0 = time.monotonic()
        while rt.pusher.push_failures == 0 and time.monotonic() - t0 < 30:
            time.sleep(0.05)
        assert rt.pusher.push_failures > 0 and rt.last_error
        holder = {}

        def restart():
            time.sleep(1.0)
            holder["srv"] = _fusion(data, port=port)

        th = threading.Thread(target=restart)
        th.start()
        s = rt.finish(timeout_s=WORK_S)
        th.join()
        f2 = holder["srv"]
        assert s.final_push_ok, rt.last_error
        assert s.status["frames_mapped"] == 4
        st = FusionClient(f2.address, timeout_s=10).stats()["agents"]["robot1"]
        assert st["latest_map_version"] == rt.pusher.pushes[-1].version
        assert st["gaussians_received"] == s.n_shared > 0
        assert st["has_complete_subset"]
    finally:
        rt.close()
        client.close()
        if f2 is not None:
            f2.stop(0)


def test_replayed_dataset_maps_with_its_sensor_profile_under_the_agent_yaml(scene, tmp_path):
    """A replayed TUM sequence gets the hand-held profile's mapper defaults (pose refinement, final pass),
    as `gausslite map` gives them; a field the agent's YAML/overrides set keeps its value."""
    from tests.datasets.test_datasets_fixtures import make_tum

    seq = make_tum(tmp_path / "tum", n=3)
    for overrides, want_refine in ((TINY, True), (TINY + ["mapper.pose.refine=false"], False)):
        ag = serve_agent(ServerOptions(port=0), AgentSettings(
            agent_id="tum", annotations_path=str(scene), data_roots=(str(tmp_path / "tum"),),
            config=load_config(None, overrides).agent))
        try:
            rt = ag.servicer.start_mission("Find the chair", dataset_path=str(seq), annotations_path=str(scene))
            assert rt.config.mapper.pose.refine is want_refine
            assert rt.config.mapper.final_iters_per_keyframe == 20.0 and rt.config.mapper.lambda_depth == 0.3
            assert rt.config.mapper.sensor.exposure_comp is True and rt.config.mapper.sensor.motion_blur is True
            assert rt.config.mapper.sensor.rolling_shutter_s == 0.02
            assert rt.config.mapper.iters_per_frame == 3  # from TINY
            assert ag.servicer.settings.config.mapper.pose.refine is False  # the agent's own config untouched
            rt.close()
        finally:
            ag.stop(0)


class _Recorder(grpc.GenericRpcHandler):
    """A stand-in fusion server that records the metadata of every call it gets (and answers UNIMPLEMENTED)."""

    def __init__(self):
        self.calls = []

    def service(self, handler_call_details):
        self.calls.append((handler_call_details.method, dict(handler_call_details.invocation_metadata)))
        return None


def test_a_caller_cannot_send_the_agents_fusion_credentials_elsewhere(scene, parser_server, tmp_path):
    """StartMission names neither the fusion server the agent's token and certificate go to, nor whose they are:
    anything but the configured server (or one in ``fusion_allow``) and the configured id is PERMISSION_DENIED, and
    the address a caller named never hears from the agent."""
    from concurrent import futures

    rec = _Recorder()
    rec_srv = grpc.server(futures.ThreadPoolExecutor(max_workers=2), handlers=[rec])
    rec_port = rec_srv.add_insecure_port("127.0.0.1:0")
    rec_srv.start()
    recorder = f"127.0.0.1:{rec_port}"
    fusion = _fusion(tmp_path / "fusion")
    settings = dict(agent_id="robot1", parser_address=parser_server.address, fusion_address=fusion.address,
                    fusion_token="robot1-secret", annotations_path=str(scene), config=load_config(None, TINY).agent)
    agent = serve_agent(ServerOptions(port=0), AgentSettings(**settings))
    try:
        c = AgentClient(agent.address)
        c.wait_ready(10)
        for kw in ({"fusion_address": recorder}, {"agent_id": "robot2"}, {"fusion_address": recorder, "agent_id": "x"}):
            with pytest.raises(grpc.RpcError) as e:
                c.start_mission("Prepare to pick up the object on the desk", **kw)
            assert _code(e) == grpc.StatusCode.PERMISSION_DENIED, kw
        time.sleep(0.5)
        assert rec.calls == []  # not a single call, so no token and no certificate
        # the configured server (named or not) and the configured id are accepted
        m = c.start_mission("Prepare to pick up the object on the desk", fusion_address=fusion.address,
                            agent_id="robot1")
        assert m.agent_id == "robot1"
        c.close()
    finally:
        agent.stop(0)
    # an address in the allow-list is accepted (and gets the agent's credentials, as configured)
    agent = serve_agent(ServerOptions(port=0), AgentSettings(**settings, fusion_allow=(recorder,)))
    try:
        c = AgentClient(agent.address)
        c.wait_ready(10)
        m = c.start_mission("Prepare to pick up the object on the desk", fusion_address=recorder)
        assert m.mission_id
        c.close()
    finally:
        agent.stop(0)
        fusion.stop(0)
        rec_srv.stop(0)


def test_fusion_allow_list_from_the_environment():
    from gausslite_services.agent.server import settings_from_env

    s = settings_from_env(None, env={"GAUSSLITE_FUSION_ADDR": "h:1", "GAUSSLITE_FUSION_ALLOW": "h:2, h:3,"})
    assert s.fusion_address == "h:1" and s.fusion_allow == ("h:2", "h:3")
    assert settings_from_env(None, env={}).fusion_allow == ()


def test_caller_paths_are_confined_to_the_data_roots(scene, tmp_path, caplog):
    """``dataset_path`` / ``annotations_path`` of a StartMission must resolve (symlinks followed, ``..`` removed)
    inside a data root or the configured annotations folder: outside, through a symlink leaving a root, by ``..``,
    or in a sibling folder sharing a root's prefix, the call is PERMISSION_DENIED with a log line; inside it runs."""
    import logging
    import os
    import shutil

    def scene_copy(dst):  # the annotations of the scene (objects.json, tasks.json)
        dst.mkdir(parents=True)
        for f in ("objects.json", "tasks.json"):
            shutil.copy(scene / f, dst / f)

    root = tmp_path / "missions"
    scene_copy(root / "site" / "agent_a")
    secret = tmp_path / "secret"
    scene_copy(secret)
    scene_copy(tmp_path / "missions-evil")  # shares the root's prefix
    os.symlink(secret, root / "escape")  # a link inside the root to a folder outside it
    cfg = load_config(None, TINY).agent
    ag = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="solo", annotations_path=str(scene), config=cfg,
                                                          data_roots=(str(root),)))
    c = AgentClient(ag.address)
    task = "Pick up the object on the desk"
    try:
        c.wait_ready(10)
        denied = [{"annotations_path": str(secret)}, {"annotations_path": str(root / "escape")},
                  {"annotations_path": f"{root}/site/../../secret"}, {"annotations_path": str(tmp_path / "missions-evil")},
                  {"dataset_path": str(secret)}, {"dataset_path": "/etc"}, {"annotations_path": "/"}]
        with caplog.at_level(logging.WARNING, logger="gausslite_services.agent.server"):
            for kw in denied:
                with pytest.raises(grpc.RpcError) as e:
                    c.start_mission(task, **kw)
                assert _code(e) == grpc.StatusCode.PERMISSION_DENIED, kw
                assert "outside the agent's data roots" in e.value.details()
        assert sum("rejected StartMission" in r.getMessage() and "PERMISSION_DENIED" in r.getMessage()
                   for r in caplog.records) == len(denied)
        assert ag.servicer.missions == {}
        # inside a root (also through `..` that stays inside), and the configured annotations folder itself
        m = c.start_mission(task, annotations_path=f"{root}/site/../site/agent_a")
        assert ag.servicer.missions[m.mission_id].annotations is not None
        c.finish(m.mission_id, timeout_s=WORK_S)
        m = c.start_mission(task, annotations_path=str(scene))
        c.finish(m.mission_id, timeout_s=WORK_S)
    finally:
        c.close()
        ag.stop(0)


def test_data_roots_from_the_environment_and_the_command_line():
    from gausslite.cli import build_parser
    from gausslite_services.agent.server import settings_from_env
    from gausslite_services.cli.cmd_sim import export_agent_env

    s = settings_from_env(None, env={"GAUSSLITE_AGENT_DATA_ROOTS": "/data/scene, /mnt/bags,"})
    assert s.data_roots == ("/data/scene", "/mnt/bags")
    assert settings_from_env(None, env={}).data_roots == ()
    env: dict = {}
    export_agent_env(build_parser().parse_args(["serve", "agent", "--data-roots", "/a,/b"]), env)
    assert settings_from_env(None, env=env).data_roots == ("/a", "/b")


def test_a_parser_that_never_answers_is_unavailable_and_the_error_says_how_long_the_agent_waited(tmp_path):
    """StartMission waits for the parser to become ready (``parser_timeout_s``); when it never does, the caller gets
    UNAVAILABLE with the parser's address and the wait in the message, not a bare deadline."""
    from gausslite_services.sim import free_port

    nowhere = f"127.0.0.1:{free_port()}"  # nothing listens there
    agent = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="robot1", parser_address=nowhere,
                                                             parser_timeout_s=0.5, config=load_config(None, TINY).agent))
    try:
        c = AgentClient(agent.address)
        c.wait_ready(30)
        with pytest.raises(grpc.RpcError) as ei:
            c.start_mission("pick up the red cup")
        assert _code(ei) == grpc.StatusCode.UNAVAILABLE
        assert f"waited 0.5 s for the parser at {nowhere}" in ei.value.details()
    finally:
        agent.stop(0)
