"""Prometheus metrics of the three services: each ``/metrics`` endpoint is scraped over HTTP before and
after real RPCs (parser, fusion server and an agent streaming frames and pushing to that fusion server,
all in one process, each with its own registry), and the values must move by what the RPCs did."""

from __future__ import annotations

import urllib.error
import urllib.request

import grpc
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from gausslite.camera import Intrinsics
from gausslite.datasets import load_dataset
from gausslite.datasets.base import Frame
from gausslite.synthetic import make_scene
from gausslite.wire.codec import GaussianArrays, encode_subset
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.metrics import metrics_port_from
from gausslite_services.common.server import ServerOptions
from tests._waits import WORK_S

# every_frame ingest: the test counts mapped frames exactly (keyframe ingest maps a selection; test_agent_live.py)
TINY = ["agent.ingest=every_frame", "agent.push.every=2", "agent.upload_keyframe_every=1", "agent.push.backoff_s=0.1", "agent.push.max_backoff_s=0.5",
        "mapper.iters_per_frame=3", "mapper.warmup_iters=1", "mapper.seeding.seeds_per_frame=200",
        "agent.refine_views.crop=false", "agent.refine_views.budget_ratio=null",  # whole keyframes, all counted
        "agent.share.worker=thread"]  # the share worker process has tests of its own (test_agent_live.py)


def scrape(url: str) -> dict:
    """``{(sample name, frozenset(labels)): value}`` of a /metrics page fetched over HTTP."""
    with urllib.request.urlopen(url, timeout=10) as r:
        assert r.status == 200
        assert r.headers.get("Content-Type", "").startswith("text/plain")
        text = r.read().decode("utf-8")
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, frozenset(s.labels.items()))] = s.value
    return out


def val(samples: dict, name: str, **labels) -> float:
    return samples.get((name, frozenset(labels.items())), 0.0)


def subset(n: int, seed: int) -> GaussianArrays:
    r = np.random.default_rng(seed)
    return GaussianArrays(means=r.uniform(0, 1, (n, 3)), quats=r.normal(size=(n, 4)),
                          log_scales=r.uniform(-5, -3, (n, 3)), opacity_logits=r.normal(size=n),
                          colors=r.uniform(0, 1, (n, 3)), kappa=r.integers(0, 50, n), active=np.ones(n, bool))


def test_metrics_port_parsing():
    assert metrics_port_from(None, None) is None
    assert metrics_port_from(0) is None          # 0 = off on the command line
    assert metrics_port_from(None, "0") is None
    assert metrics_port_from(None, "9100") == 9100
    assert metrics_port_from(9200, "9100") == 9200  # flag wins over the environment
    with pytest.raises(ValueError, match="integer"):
        metrics_port_from(None, "abc")
    with pytest.raises(ValueError, match="0..65535"):
        metrics_port_from(70000)


def test_serve_cli_metrics_flag_and_env():
    from gausslite.cli import build_parser
    from gausslite_services.cli.cmd_serve import resolve_options

    args = build_parser().parse_args(["serve", "fusion", "--metrics-port", "9123"])
    assert resolve_options(args, env={})[0].metrics_port == 9123
    args = build_parser().parse_args(["serve", "parser"])
    assert resolve_options(args, env={})[0].metrics_port is None
    assert resolve_options(args, env={"GAUSSLITE_METRICS_PORT": "9100"})[0].metrics_port == 9100
    assert resolve_options(args, env={"GAUSSLITE_PARSER_METRICS_PORT": "9101",
                                      "GAUSSLITE_METRICS_PORT": "9100"})[0].metrics_port == 9101
    args = build_parser().parse_args(["serve", "agent", "--metrics-port", "0"])
    assert resolve_options(args, env={"GAUSSLITE_METRICS_PORT": "9100"})[0].metrics_port is None


def test_metrics_off_by_default(tmp_path):
    from gausslite_services.parser.server import serve

    srv = serve(ServerOptions(port=0))
    try:
        assert srv.metrics is None
    finally:
        srv.stop(0)


def test_parser_metrics_move(tmp_path):
    from gausslite_rpc import parser_pb2, parser_pb2_grpc
    from gausslite_services.parser.server import serve

    srv = serve(ServerOptions(port=0, metrics_port=0))
    url = srv.metrics.url
    try:
        before = scrape(url)
        assert val(before, "gausslite_parser_request_seconds_count") == 0
        with grpc.insecure_channel(srv.address) as ch:
            stub = parser_pb2_grpc.ParserStub(ch)
            g = stub.Parse(parser_pb2.ParseRequest(task_text="Prepare to pick up the cup on the desk"), timeout=10)
            with pytest.raises(grpc.RpcError) as e:
                stub.Parse(parser_pb2.ParseRequest(task_text="   "), timeout=10)
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        after = scrape(url)
        assert val(after, "gausslite_parser_requests_total", outcome="ok", backend=g.backend) == 1
        assert val(after, "gausslite_parser_requests_total", outcome="invalid_argument", backend="") == 1
        assert val(after, "gausslite_parser_request_seconds_count") == 2
        assert val(after, "gausslite_parser_request_seconds_sum") > 0
    finally:
        srv.stop(0)
    with pytest.raises((urllib.error.URLError, ConnectionError, OSError)):
        scrape(url)  # the endpoint stops with the server


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    make_scene(out, seed=0, width=64, height=48, frames=4, progress=False)
    return out


def test_fusion_and_agent_metrics_move(tmp_path, scene):
    from gausslite_services.agent.client import AgentClient
    from gausslite.config import load_config
    from gausslite_services.agent.server import AgentSettings, serve as serve_agent
    from gausslite_services.fusion_server.client import FusionClient
    from gausslite_services.fusion_server.server import serve as serve_fusion

    from gausslite.config import FusionSettings

    fusion = serve_fusion(ServerOptions(port=0, metrics_port=0, max_message_bytes=1 << 20),
                          FusionSettings(team_map={"enabled": False}),  # no refinement process (test_team_map.py)
                          data_dir=str(tmp_path / "fusion"))
    agent = serve_agent(ServerOptions(port=0, metrics_port=0), AgentSettings(
        agent_id="robot_m", fusion_address=fusion.address, annotations_path=str(scene),
        config=load_config(None, TINY).agent))
    fusion_url, agent_url = fusion.rpc.metrics.url, agent.running.metrics.url
    assert fusion_url != agent_url
    try:
        f0 = scrape(fusion_url)
        a0 = scrape(agent_url)
        assert val(f0, "gausslite_fusion_uploads_total", agent="robot_x") == 0
        assert not any(k[0] == "gausslite_agent_frames_received_total" for k in a0)  # no mission yet

        # ---- direct fusion RPCs: a 3-chunk subset, 2 keyframes, a rejected upload, one vote
        intr = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)
        g = subset(2500, 1)
        wire_bytes = sum(len(c) for c in encode_subset(g, "robot_x", 1, chunk_gaussians=1000))
        with FusionClient(fusion.address, timeout_s=20) as fc:
            fc.wait_ready(10)
            fc.open_session("robot_x", "find the cup", intr)
            up = fc.upload_subset("robot_x", 1, g, full_map_gaussians=5000, chunk_gaussians=1000)
            assert up.complete and up.n_chunks == 3 and up.bytes_on_wire == wire_bytes
            frames = [Frame(i, i / 30, np.full((24, 32, 3), 40 * i, np.uint8), np.full((24, 32), 1.5, np.float32),
                            np.eye(4), intr) for i in range(2)]
            assert fc.upload_keyframes("robot_x", frames) == 2
            with grpc.insecure_channel(fusion.address) as ch, pytest.raises(grpc.RpcError) as e:
                hdr = fusion_pb2.UploadHeader(agent_id="nobody", map_version=1, n_chunks=1)
                fusion_pb2_grpc.FusionStub(ch).UploadSubset(iter([fusion_pb2.UploadSubsetRequest(header=hdr)]),
                                                            timeout=10)
            assert e.value.code() == grpc.StatusCode.NOT_FOUND  # no session: rejected, counted unlabelled
            res = fc.fuse("vote")
            with pytest.raises(grpc.RpcError) as e:
                fc.fuse("vote", voxel_size=-1.0)
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        f1 = scrape(fusion_url)
        assert val(f1, "gausslite_fusion_uploads_total", agent="robot_x") == 1
        assert val(f1, "gausslite_fusion_chunks_received_total", agent="robot_x") == 3
        assert val(f1, "gausslite_fusion_chunks_stored_total", agent="robot_x") == 3
        assert val(f1, "gausslite_fusion_bytes_received_total", agent="robot_x") == wire_bytes
        assert val(f1, "gausslite_fusion_subsets_completed_total", agent="robot_x") == 1
        assert val(f1, "gausslite_fusion_gaussians", agent="robot_x") == 2500
        assert val(f1, "gausslite_fusion_keyframes_stored_total", agent="robot_x") == 2
        assert val(f1, "gausslite_fusion_upload_errors_total") == 1
        assert val(f1, "gausslite_fusion_upload_ack_seconds_count", agent="robot_x") == 1
        assert val(f1, "gausslite_fusion_upload_ack_seconds_bucket", agent="robot_x", le="+Inf") == 1
        assert val(f1, "gausslite_fusion_fuse_runs_total", method="vote", outcome="ok") == 1
        assert val(f1, "gausslite_fusion_fuse_runs_total", method="vote", outcome="error") == 1
        assert val(f1, "gausslite_fusion_fuse_duration_seconds_count", method="vote") == 1
        assert val(f1, "gausslite_fusion_fuse_duration_seconds_sum", method="vote") == pytest.approx(res.seconds)
        assert val(f1, "gausslite_fusion_fused_gaussians") == res.n_gaussians

        # ---- the agent streams 4 frames and pushes to the same fusion server
        ds = load_dataset(scene / "agent_a")
        with AgentClient(agent.address) as c:
            c.wait_ready(10)
            m = c.start_mission(ds.annotations.task_by_id("synth-pick-object").text)
            assert c.stream_frames(m.mission_id, list(ds), timeout_s=120).frames_received == 4
            # Finish maps what is queued, makes the final pass and push: on a busy machine that can take minutes; the
            # bound only keeps a hung agent from holding the suite
            s = c.finish(timeout_s=WORK_S)
            assert s.final_push_ok, s.status.last_error
        a1 = scrape(agent_url)
        assert val(a1, "gausslite_agent_frames_received_total", agent="robot_m") == 4
        assert val(a1, "gausslite_agent_frames_mapped_total", agent="robot_m") == 4
        assert val(a1, "gausslite_agent_queue_depth", agent="robot_m") == 0
        assert val(a1, "gausslite_agent_pushes_total", agent="robot_m") == s.status.pushes >= 1
        assert val(a1, "gausslite_agent_push_seconds_count", agent="robot_m") == s.status.pushes
        assert val(a1, "gausslite_agent_push_seconds_sum", agent="robot_m") > 0
        assert val(a1, "gausslite_agent_bytes_pushed_total", agent="robot_m") >= s.bytes_on_wire > 0
        assert val(a1, "gausslite_agent_keyframes_uploaded_total", agent="robot_m") >= 4
        assert val(a1, "gausslite_agent_gaussians", agent="robot_m") == s.status.n_gaussians
        assert val(a1, "gausslite_agent_push_backlog", agent="robot_m") == 0  # final push acknowledged
        assert val(a1, "gausslite_agent_link_down_seconds", agent="robot_m") == 0
        assert val(a1, "gausslite_agent_missions", state="finished") == 1
        f2 = scrape(fusion_url)
        assert val(f2, "gausslite_fusion_uploads_total", agent="robot_m") >= 1
        assert val(f2, "gausslite_fusion_gaussians", agent="robot_m") == s.n_shared
        assert val(f2, "gausslite_fusion_bytes_received_total", agent="robot_m") >= s.bytes_on_wire
        # the first server's counters are untouched by the second agent
        assert val(f2, "gausslite_fusion_uploads_total", agent="robot_x") == 1
    finally:
        agent.stop(0)
        fusion.stop(0)


def test_fusion_module_cli_metrics_port(tmp_path, monkeypatch):
    """``python -m gausslite_services.fusion_server`` reads --metrics-port / GAUSSLITE_METRICS_PORT (bad value → exit
    2)."""
    from gausslite_services.fusion_server.server import main

    monkeypatch.setenv("GAUSSLITE_METRICS_PORT", "not-a-port")
    assert main(["--port", "0", "--data-dir", str(tmp_path / "f")]) == 2


def _wait_scrape(url: str, proc, timeout_s: float = 60.0) -> dict:
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return scrape(url)
        except (urllib.error.URLError, ConnectionError, OSError):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"no metrics at {url}: {proc.stdout.read() if proc.poll() is not None else ''}")
            time.sleep(0.2)


@pytest.mark.parametrize("service", ["parser", "fusion_server"])
def test_compose_metrics_setting_serves_metrics(service, tmp_path):
    """deploy/docker-compose.yml passes GAUSSLITE_METRICS_PORT to every server; the service's own compose
    command, started locally with that variable set, serves /metrics over HTTP."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    import yaml

    from gausslite_services.sim import free_port

    repo = Path(__file__).resolve().parents[2]
    compose = yaml.safe_load((repo / "deploy" / "docker-compose.yml").read_text())["services"]
    for name in ("parser", "fusion_server", "agent_a", "agent_b"):
        assert compose[name]["environment"]["GAUSSLITE_METRICS_PORT"] == "${GAUSSLITE_METRICS_PORT:-0}"
    # the image's /app/deploy is this checkout's deploy/
    cmd = [c.replace("/app/deploy/", f"{repo / 'deploy'}/") for c in compose[service]["command"]]
    cmd[cmd.index("--port") + 1] = str(free_port())
    cmd = [sys.executable, "-m", "gausslite.cli", *cmd[1:]] if cmd[0] == "gausslite" else [sys.executable, *cmd[1:]]
    mport = free_port()
    env = {**os.environ, "PYTHONPATH": str(repo), "GAUSSLITE_METRICS_PORT": str(mport), "OMP_NUM_THREADS": "1",
           "GAUSSLITE_DATA_DIR": str(tmp_path / "data"), "GAUSSLITE_TOKEN": ""}
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        samples = _wait_scrape(f"http://127.0.0.1:{mport}/metrics", proc)
        family = {"parser": "gausslite_parser_request_seconds_count",
                  "fusion_server": "gausslite_fusion_upload_errors_total"}[service]
        assert val(samples, family) == 0 and (family, frozenset()) in samples
    finally:
        proc.terminate()
        proc.wait(30)
