"""Live operation of the agent: keyframe selection, the non-blocking ingest path, time-budgeted
mapping and optimisation between keyframes, checkpoint/resume (in-process and after SIGKILL of a real agent
process), the ONNX relevance backend and its FAILED_PRECONDITION path."""

from __future__ import annotations

import contextlib

import dataclasses
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import grpc
import numpy as np
import pytest
import torch

from gausslite.datasets import load_dataset
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.keyframes import KeyframeRule, KeyframeSelector
from gausslite.mapping.mapper import Mapper
from gausslite.synthetic import make_scene
from gausslite_rpc import agent_pb2
from gausslite_services.agent.client import AgentClient
from gausslite_services.agent.frames import encode_frame
from gausslite.config import load_config
from gausslite.mission import AgentRuntime
from gausslite_services.agent.server import AgentSettings, serve as serve_agent
from gausslite_services.common.server import ServerOptions
from tests._waits import WORK_S, wait_until

REPO = Path(__file__).resolve().parents[2]
TINY = ["agent.push.every=2", "agent.upload_keyframe_every=1", "agent.push.backoff_s=0.1",
        "agent.push.max_backoff_s=0.5", "agent.idle_chunk_s=0.05", "mapper.iters_per_frame=3", "mapper.warmup_iters=1", "mapper.seeding.seeds_per_frame=200"]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    make_scene(out, seed=0, width=64, height=48, frames=6, progress=False)
    return out


def _pose(tx=0.0, yaw_deg=0.0):
    a = np.radians(yaw_deg)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[0, 3] = tx
    return T


# ---------------------------------------------------------------------------------------------- selection
def test_keyframe_rule_translation_rotation_interval_and_newest_pending():
    sel = KeyframeSelector(KeyframeRule(translation_m=0.1, rotation_deg=10.0, max_interval_s=2.0))
    assert sel.offer("f0", _pose(), 0.0) == (True, None)  # first frame
    assert sel.take() == "f0" and not sel.has_pending
    assert sel.offer("f1", _pose(tx=0.05), 0.1) == (False, None)        # below both thresholds
    assert sel.offer("f2", _pose(yaw_deg=5.0), 0.2) == (False, None)
    assert sel.offer("f3", _pose(tx=0.15), 0.3) == (True, None)         # translation
    assert sel.offer("f4", _pose(yaw_deg=12.0), 0.4) == (True, "f3")    # rotation; replaces the older candidate
    assert sel.take() == "f4" and sel.take() is None
    # reference is now f4's pose: a frame at the same pose qualifies only by the interval
    assert sel.offer("f5", _pose(yaw_deg=12.0), 2.3) == (False, None)
    assert sel.offer("f6", _pose(yaw_deg=12.0), 2.4) == (True, None)
    assert sel.drop_pending() == "f6"
    with pytest.raises(ValueError):
        sel.offer("bad", np.full((4, 4), np.nan), 3.0)
    with pytest.raises(ValueError):
        KeyframeRule(translation_m=0.0)
    s2 = KeyframeSelector(sel.rule)
    s2.load_state_dict(sel.state_dict())
    assert s2.offer("g", _pose(yaw_deg=12.0), 1.0) == (False, None)  # reference f4 (t=0.4) restored


# ---------------------------------------------------------------------------------------------- mapper API
def _mapper(**kw):
    return Mapper(MapperConfig(mode="gausslite", iters_per_frame=4, warmup_iters=1, seeding={"seeds_per_frame": 150},
                               **kw))


def _count_iters(m):
    n = {"i": 0}
    orig = m.step

    def wrapped(*a, **k):
        n["i"] += 1
        return orig(*a, **k)

    m.step = wrapped
    return n


def test_map_frame_budget_and_optimize_between_keyframes(scene):
    ds = load_dataset(scene / "agent_a")
    m = _mapper()
    n = _count_iters(m)
    m.map_frame(ds[0])
    assert n["i"] == 4  # no budget: iters_per_frame
    n["i"] = 0
    st = m.map_frame(ds[1], time_budget_s=1e-9)
    assert n["i"] == 1  # a budget already spent by seeding still gets one iteration
    n["i"] = 0
    st = m.map_frame(ds[2], time_budget_s=0.3)
    assert n["i"] == st.iters >= 1 and st.seconds >= 0.3  # iterations continue until the budget is spent
    m2 = _mapper(keyframe_budget_s=1e-9)  # the config value applies when the call gives none
    n2 = _count_iters(m2)
    m2.map_frame(ds[0])
    assert n2["i"] == 1
    # optimisation between keyframes: MVO over the stored keyframes, bounded by n_iters or time
    n["i"] = 0
    assert m.optimize(n_iters=5) == 5 and n["i"] == 5 and m.n_idle_iters == 5
    assert m.optimize(max_seconds=1e-9) == 1
    with pytest.raises(ValueError):
        m.optimize()
    with pytest.raises(ValueError):
        m.optimize(n_iters=0)
    assert _mapper().optimize(n_iters=3) == 0  # nothing mapped yet


def test_mapper_checkpoint_round_trip(scene):
    ds = load_dataset(scene / "agent_a")
    m = _mapper()
    for i in range(3):
        m.map_frame(ds[i])
    st = m.state_dict()
    m2 = _mapper()
    m2.load_state_dict(st)
    fr = ds[3]
    a = m.render(fr.c2w, fr.intrinsics.K, fr.intrinsics.width, fr.intrinsics.height)
    b = m2.render(fr.c2w, fr.intrinsics.K, fr.intrinsics.width, fr.intrinsics.height)
    assert torch.equal(a.color, b.color)
    assert torch.equal(m.model.kappa, m2.model.kappa) and torch.equal(m.model.active, m2.model.active)
    assert [k.frame_id for k in m2.window] == [k.frame_id for k in m.window]
    assert m2.n_mapped == 3 and m2.budget == m.budget
    assert torch.equal(m2.strategy.contribution, m.strategy.contribution) and len(m2.strategy.voxels) == len(m.strategy.voxels)
    assert torch.equal(m2.model.ids, m.model.ids) and m2.model._next_id == m.model._next_id
    m2.map_frame(ds[3])  # and it keeps mapping
    assert m2.n_mapped == 4
    m3 = _mapper()  # a bounded checkpoint keeps the newest keyframes, never fewer than the window
    m3.load_state_dict(m.state_dict(saved_keyframes_max=1))
    keep = max(1, m.cfg.window)
    assert [k.frame_id for k in m3.keyframes] == [k.frame_id for k in m.keyframes][-keep:]
    assert [k.frame_id for k in m3.window] == [k.frame_id for k in m.window]
    m4 = _mapper(window=2)
    for i in range(4):
        m4.map_frame(ds[i])
    m5 = _mapper(window=2)
    m5.load_state_dict(m4.state_dict(saved_keyframes_max=1))
    assert [k.frame_id for k in m5.keyframes] == [k.frame_id for k in m4.keyframes][-2:]


# ---------------------------------------------------------------------------------------------- ingest
def test_submit_never_blocks_while_the_mapper_is_busy(scene):
    ds = load_dataset(scene / "agent_a")
    cfg = load_config(None, TINY + ["agent.keyframe_translation_m=1e-6", "agent.idle_optimize=false"]).agent
    rt = AgentRuntime("live", "Pick up the object", {"targets": ["object"], "anchors": [], "relations": []}, cfg,
                      relevance_fn=lambda fr: None)
    gate, entered = threading.Event(), threading.Event()
    mapped = []
    orig = rt.mapper.map_frame

    def slow_map(frame, w=None, **kw):
        entered.set()
        gate.wait(30)
        mapped.append(frame.frame_id)
        return orig(frame, w, **kw)

    rt.mapper.map_frame = slow_map
    frames = [ds[i % len(ds)] for i in range(40)]
    results = []

    def send():
        for k, f in enumerate(frames):
            c2w = f.c2w.copy()
            c2w[0, 3] += 0.01 * k  # every frame moved since the last keyframe
            f = dataclasses.replace(f, frame_id=k, c2w=c2w)
            results.append(rt.submit(f))
            if k == 0:
                assert entered.wait(30)  # the mapper took frame 0 and is now busy

    t = threading.Thread(target=send)
    t.start()
    t.join(20)
    try:
        assert not t.is_alive(), "submit blocked while the mapper was busy"
        st = rt.status()
        assert st["frames_received"] == 40 and all(results)  # every frame moved: each one was a candidate
        assert st["frames_mapped"] == 0 and st["frames_queued"] <= 1
        # frame 0 went to the (blocked) mapper, the newest pending candidate is frame 39, the rest were replaced
        assert st["frames_skipped"] == 38
    finally:
        gate.set()
    s = rt.finish(push=False, timeout_s=WORK_S)
    assert mapped == [0, 39]
    assert s.status["frames_keyframed"] == 2
    assert s.status["frames_received"] == s.status["frames_keyframed"] + s.status["frames_skipped"]
    assert s.status["accept_latency_ms_p99"] > 0 and s.status["keyframe_latency_s_p95"] > 0
    rt.close()


def test_idle_optimisation_and_checkpoint_resume_in_process(scene, tmp_path):
    ds = load_dataset(scene / "agent_a")
    cfg = load_config(None, TINY + ["agent.checkpoint_every=1", "agent.keyframe_translation_m=1e-6"]).agent
    graph = {"targets": ["object"], "anchors": [], "relations": []}
    rt = AgentRuntime("a1", "Pick up the object", graph, cfg, relevance_fn=lambda fr: None, mission_id="m1",
                      checkpoint_dir=tmp_path / "m1")
    for i in range(3):
        rt.submit(ds[i])
        rt.wait_mapped(WORK_S)
    deadline = time.monotonic() + 30
    while rt.status()["idle_iterations"] == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    st = rt.status()
    assert st["idle_iterations"] > 0  # the map keeps improving between keyframes
    assert st["checkpoints"] >= 1 and (tmp_path / "m1" / "checkpoint.pt").is_file()
    keyframed, n_g, version = st["frames_keyframed"], st["n_gaussians"], rt.pusher.version
    rt.close()
    # a second runtime with the same mission id resumes
    rt2 = AgentRuntime.launch("a1", "Pick up the object", graph, cfg, relevance_fn=lambda fr: None, mission_id="m1",
                              checkpoint_dir=tmp_path / "m1")
    st2 = rt2.status()
    assert st2["resumed_keyframes"] == keyframed == st2["frames_keyframed"] >= 1
    assert st2["n_gaussians"] > 0 and rt2.pusher.version >= version >= 1
    rt2.close()
    with pytest.raises(ValueError, match="task"):
        AgentRuntime.launch("a1", "Find the chair", graph, cfg, relevance_fn=lambda fr: None, mission_id="m1",
                            checkpoint_dir=tmp_path / "m1")


# ---------------------------------------------------------------------------------------------- gRPC
def test_streaming_with_keyframe_ingest_and_bad_input(scene):
    cfg = load_config(None, TINY).agent
    ag = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="solo", annotations_path=str(scene), config=cfg))
    c = AgentClient(ag.address)
    try:
        ds = load_dataset(scene / "agent_a")
        m = c.start_mission("Identify the chair closest to the table")
        r = c.stream_frames(m.mission_id, [ds[i] for i in range(len(ds))], timeout_s=60)
        assert r.frames_received == len(ds)
        st = c.status(m.mission_id)
        assert st.frames_received == len(ds)
        assert st.frames_keyframed + st.frames_skipped + st.frames_queued >= 1
        good = encode_frame(ds[0], m.mission_id)
        bad = agent_pb2.FrameMsg(); bad.CopyFrom(good); bad.color = b"\x89PNG broken"
        with pytest.raises(grpc.RpcError) as e:
            c.stream_messages([bad], timeout_s=10)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "colour" in e.value.details()
        bad = agent_pb2.FrameMsg(); bad.CopyFrom(good); bad.c2w[3] = float("inf")
        with pytest.raises(grpc.RpcError) as e:
            c.stream_messages([bad], timeout_s=10)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        small = load_dataset(scene / "agent_a", downscale=2)[0]
        with pytest.raises(grpc.RpcError) as e:
            c.stream_frames(m.mission_id, [small], timeout_s=10)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "image size" in e.value.details()
        s = c.finish(m.mission_id, timeout_s=WORK_S)
        assert s.status.frames_received == s.status.frames_keyframed + s.status.frames_skipped
        assert s.status.frames_keyframed >= 1
        with pytest.raises(grpc.RpcError) as e:
            c.stream_messages([good], timeout_s=10)
        assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        with pytest.raises(grpc.RpcError) as e:
            c.start_mission("Find the chair", mission_id="bad id!")
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    finally:
        c.close()
        ag.stop(0)


def test_no_relevance_source_is_failed_precondition(scene, tmp_path):
    cfg = load_config(None, TINY).agent
    ag = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="solo", config=cfg))  # no annotations
    cfg2 = load_config(None, TINY + ["agent.relevance_backend=onnx",
                                           f"agent.onnx.detector_path={tmp_path / 'missing.onnx'}"]).agent
    ag2 = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="solo2", config=cfg2))
    try:
        with AgentClient(ag.address) as c:
            with pytest.raises(grpc.RpcError) as e:
                c.start_mission("Find the chair")
            assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
            assert "objects.json" in e.value.details() and "onnx" in e.value.details()
        with AgentClient(ag2.address) as c:
            with pytest.raises(grpc.RpcError) as e:
                c.start_mission("Find the chair")
            assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
            d = e.value.details()
            assert "missing.onnx does not exist" in d and "vocab_path is not set" in d and "segmenter_path" in d
    finally:
        ag.stop(0)
        ag2.stop(0)


def test_onnx_relevance_backend_with_tiny_models(scene, tmp_path):
    from tests.attention.test_attention_onnx import _detector_model, _fastsam_model

    # caption for the graph {targets: [chair]} is "chair ." -> [CLS] chair . [SEP]
    (tmp_path / "vocab.txt").write_text("\n".join(["[PAD]", "[UNK]", "[CLS]", "[SEP]", ".", "chair"]) + "\n")
    L, Q = 16, 2
    lg = np.full((1, Q, L), -10.0)
    lg[0, 0, 1] = 4.0  # query 0 -> "chair", box in the image centre
    bx = np.array([[[0.5, 0.5, 0.4, 0.5], [0.1, 0.1, 0.05, 0.05]]])
    det = _detector_model(tmp_path / "gd.onnx", lg, bx)
    protos = np.full((1, 1, 16, 16), 5.0)
    pred = np.asarray([[32, 32, 30, 30, 0.9, 1]], dtype=np.float64).T[None]  # one big mask in the centre
    seg = _fastsam_model(tmp_path / "fs.onnx", pred, protos, 64)
    cfg = load_config(None, TINY + ["agent.ingest=every_frame", "agent.relevance_backend=onnx",
                                          f"agent.onnx.detector_path={det}", f"agent.onnx.segmenter_path={seg}",
                                          f"agent.onnx.vocab_path={tmp_path / 'vocab.txt'}"]).agent
    graph = {"targets": ["chair"], "anchors": [], "relations": []}
    rt = AgentRuntime("onnx", "Find the chair", graph, cfg)  # no annotations at all
    ds = load_dataset(scene / "agent_a")
    rel = rt._relevance_fn(ds[0])
    assert rel.shape == ds[0].depth.shape and rel.dtype == bool and rel.any()
    rt.submit(ds[0])
    rt.wait_mapped(WORK_S)
    assert rt.status()["frames_mapped"] == 1 and rt.status()["n_active"] > 0
    rt.close()



def test_onnx_cost_backend_runs_the_models_and_answers_from_annotations(scene, tmp_path):
    from tests.attention.test_attention_onnx import _detector_model, _fastsam_model

    (tmp_path / "vocab.txt").write_text("\n".join(["[PAD]", "[UNK]", "[CLS]", "[SEP]", ".", "chair"]) + "\n")
    det = _detector_model(tmp_path / "gd.onnx", np.full((1, 2, 16), -10.0), np.full((1, 2, 4), 0.5))  # detects nothing
    seg = _fastsam_model(tmp_path / "fs.onnx", np.zeros((1, 7, 1)), np.zeros((1, 2, 16, 16)), 64)
    ds = load_dataset(scene / "agent_a")
    graph = {"targets": ["chair"], "anchors": [], "relations": []}
    onnx = [f"agent.onnx.detector_path={det}", f"agent.onnx.segmenter_path={seg}",
            f"agent.onnx.vocab_path={tmp_path / 'vocab.txt'}"]
    ref = AgentRuntime("ann", "Find the chair", graph, load_config(None, TINY).agent, annotations=ds.annotations)
    cost = AgentRuntime("cost", "Find the chair", graph,
                        load_config(None, TINY + ["agent.relevance_backend=onnx_cost"] + onnx).agent,
                        annotations=ds.annotations)
    try:
        for i in range(3):
            want, got = ref._relevance_fn(ds[i]), cost._relevance_fn(ds[i])
            np.testing.assert_array_equal(got, want)
        assert want.any()  # the chair is in view: the masks come from the annotations, not the models
        d, s = cost.frontend.config.detector, cost.frontend.config.segmenter
        assert len(d.seconds) == cost.frontend.detector_calls >= 1 and len(s.seconds) == 3  # the models ran
    finally:
        ref.close()
        cost.close()
    with pytest.raises(ValueError, match="backend 'onnx_cost' needs scene annotations"):
        AgentRuntime("cost", "Find the chair", graph,
                     load_config(None, TINY + ["agent.relevance_backend=onnx_cost"] + onnx).agent)

def test_incompatible_onnx_models_are_failed_precondition(tmp_path):
    from tests.attention.test_attention_onnx import _fastsam_model

    (tmp_path / "vocab.txt").write_text("\n".join(["[PAD]", "[UNK]", "[CLS]", "[SEP]", ".", "chair"]) + "\n")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"\x00 not a model")
    seg = _fastsam_model(tmp_path / "fs.onnx", np.zeros((1, 7, 1)), np.zeros((1, 2, 16, 16)), 64)
    cases = [(junk, seg, "junk.onnx is not a loadable ONNX model"),
             (seg, seg, "fs.onnx: the model has no 'input_ids' input")]  # a segmenter given as the detector
    for det_path, seg_path, why in cases:
        cfg = load_config(None, TINY + ["agent.relevance_backend=onnx", f"agent.onnx.detector_path={det_path}",
                                              f"agent.onnx.segmenter_path={seg_path}",
                                              f"agent.onnx.vocab_path={tmp_path / 'vocab.txt'}"]).agent
        ag = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="solo", config=cfg))
        try:
            with AgentClient(ag.address) as c:
                with pytest.raises(grpc.RpcError) as e:
                    c.start_mission("Find the chair")
                assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION
                assert why in e.value.details(), e.value.details()
        finally:
            ag.stop(0)

# ---------------------------------------------------------------------------------------------- SIGKILL
def _start_agent(port, data_dir, cfg_path, log):
    env = {**os.environ, "GAUSSLITE_AGENT_ID": "robot1", "GAUSSLITE_DATA_DIR": str(data_dir),
           "GAUSSLITE_FUSION_ADDR": os.environ["_TEST_FUSION"], "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1",
           "PYTHONPATH": str(REPO)}
    return subprocess.Popen([sys.executable, "-m", "gausslite.cli", "serve", "agent", "--host", "127.0.0.1",
                             "--port", str(port), "--config", str(cfg_path)], stdout=log, stderr=subprocess.STDOUT,
                            env=env, cwd=str(REPO), start_new_session=True)


@contextlib.contextmanager
def _agent_processes(scene, tmp_path, monkeypatch, agent_cfg: dict):
    """An in-process fusion server and a ``start()`` that runs ``gausslite serve agent`` processes (agent id robot1,
    on one port, with ``agent_cfg`` as its ``agent`` section); yields (start, fusion client, frames, port) and stops
    everything afterwards."""
    import yaml

    from gausslite_services.fusion_server.client import FusionClient
    from gausslite_services.fusion_server.server import serve as serve_fusion
    from gausslite_services.sim import free_port

    fusion = serve_fusion(ServerOptions(port=0), data_dir=str(tmp_path / "fusion"))
    monkeypatch.setenv("_TEST_FUSION", fusion.address)
    monkeypatch.setenv("GAUSSLITE_AGENT_DATA_ROOTS", str(scene))  # the missions name scene/agent_a
    cfg_path = tmp_path / "agent.yaml"
    agent = {"keyframe_translation_m": 1e-6, "idle_chunk_s": 0.05, **agent_cfg,
             "push": {"backoff_s": 0.1, **agent_cfg.get("push", {})}}
    cfg_path.write_text(yaml.safe_dump({
        "agent": agent,
        "mapper": {"iters_per_frame": 3, "warmup_iters": 1, "seeding": {"seeds_per_frame": 200}}}))
    port = free_port()
    log = open(tmp_path / "agent.log", "w")
    procs = []

    def start():
        procs.append(_start_agent(port, tmp_path / "agents", cfg_path, log))
        return procs[-1]

    fc = FusionClient(fusion.address, timeout_s=30)
    try:
        yield start, fc, load_dataset(scene / "agent_a"), port
    finally:
        fc.close()
        for proc in procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(30)
        log.close()
        fusion.stop(0)


def _stream_keyframes(c, mission_id: str, frames) -> None:
    """Stream ``frames`` one per call, each waited for until it is a keyframe (once the mapper is free)."""
    for i, fr in enumerate(frames):
        c.stream_frames(mission_id, [fr], timeout_s=60)
        deadline = time.monotonic() + WORK_S
        while c.status(mission_id).frames_keyframed < i + 1 and time.monotonic() < deadline:
            time.sleep(0.1)


def test_agent_resumes_after_sigkill(scene, tmp_path, monkeypatch):
    cfg = {"push": {"every": 1}, "checkpoint_every": 1, "share": {"worker": "thread"}}
    with _agent_processes(scene, tmp_path, monkeypatch, cfg) as (start, fc, ds, port):
        p = start()
        with AgentClient(f"127.0.0.1:{port}") as c:
            c.wait_ready(120)
            m = c.start_mission("Pick up the object", annotations_path=str(scene / "agent_a"), mission_id="run-7")
            assert m.mission_id == "run-7" and not m.resumed
            _stream_keyframes(c, "run-7", [ds[i] for i in range(3)])
            deadline = time.monotonic() + WORK_S
            while (c.status("run-7").checkpoints < 3 or c.status("run-7").pushes < 1) and time.monotonic() < deadline:
                time.sleep(0.1)
            st = c.status("run-7")
            assert st.frames_keyframed == 3 and st.checkpoints >= 3 and st.pushes >= 1, st
        v_before = fc.stats()["agents"]["robot1"]["latest_map_version"]
        assert v_before >= 1
        os.killpg(p.pid, signal.SIGKILL)  # no graceful shutdown, no final push
        p.wait(30)
        start()
        with AgentClient(f"127.0.0.1:{port}") as c:
            c.wait_ready(120)
            m = c.start_mission("Pick up the object", annotations_path=str(scene / "agent_a"), mission_id="run-7")
            assert m.resumed and m.resumed_keyframes == 3
            st = c.status("run-7")
            assert st.frames_keyframed == 3 and st.n_gaussians > 0
            c.stream_frames("run-7", [ds[3]], timeout_s=60)
            s = c.finish("run-7", timeout_s=WORK_S)
            assert s.final_push_ok, s.status.last_error
            assert s.status.frames_keyframed == 4
            assert s.status.last_pushed_version > v_before  # same agent, newer versions
        assert fc.stats()["agents"]["robot1"]["latest_map_version"] == s.status.last_pushed_version


def test_sigterm_pushes_the_final_subset_and_checkpoints(scene, tmp_path, monkeypatch):
    """A robot being shut down (SIGTERM) mid-mission, with no periodic push or checkpoint due yet: the agent stops
    ingest, pushes its final subset, writes its checkpoint and exits; a restart resumes the mission."""
    cfg = {"push": {"every": 1000}, "checkpoint_every": 1000, "share": {"worker": "thread"}}
    with _agent_processes(scene, tmp_path, monkeypatch, cfg) as (start, fc, ds, port):
        p = start()
        with AgentClient(f"127.0.0.1:{port}") as c:
            c.wait_ready(120)
            c.start_mission("Pick up the object", annotations_path=str(scene / "agent_a"), mission_id="run-8")
            _stream_keyframes(c, "run-8", [ds[i] for i in range(3)])
            st = c.status("run-8")
            assert st.frames_keyframed == 3 and st.pushes == 0 and st.checkpoints == 0, st
        assert "robot1" not in fc.stats()["agents"]
        os.killpg(p.pid, signal.SIGTERM)
        assert p.wait(90) == 0
        held = fc.stats()["agents"]["robot1"]
        assert held["has_complete_subset"] and held["latest_map_version"] >= 1
        assert (tmp_path / "agents" / "robot1" / "run-8" / "checkpoint.pt").is_file()
        start()
        with AgentClient(f"127.0.0.1:{port}") as c:
            c.wait_ready(120)
            m = c.start_mission("Pick up the object", annotations_path=str(scene / "agent_a"), mission_id="run-8")
            assert m.resumed and m.resumed_keyframes == 3


def test_validate_frame_reads_headers_and_defers_decoding(scene):
    import cv2

    from gausslite_services.agent.frames import FrameError, validate_frame

    fr = load_dataset(scene / "agent_a")[0]
    for fmt in (".png", ".jpg"):
        msg = encode_frame(fr, "m", color_format=fmt)
        pf = validate_frame(msg)
        assert (pf.frame_id, pf.intrinsics.width, pf.intrinsics.height) == (fr.frame_id, 64, 48)
        np.testing.assert_allclose(pf.c2w, fr.c2w)
        assert pf.materialize().rgb.shape == (48, 64, 3)
    msg = encode_frame(fr, "m", color_format=".jpg")
    cases = {
        "8-bit RGB": cv2.imencode(".jpg", np.zeros((48, 64), np.uint8))[1].tobytes(),  # grey JPEG
        "colour is 32x48": cv2.imencode(".png", np.zeros((48, 32, 3), np.uint8))[1].tobytes(),
        "not a decodable": b"GIF89a....",
    }
    for want, data in cases.items():
        bad = agent_pb2.FrameMsg(); bad.CopyFrom(msg); bad.color = data
        with pytest.raises(FrameError, match=want):
            validate_frame(bad)
    bad = agent_pb2.FrameMsg(); bad.CopyFrom(msg); bad.depth = cv2.imencode(".png", np.zeros((48, 64), np.uint8))[1].tobytes()
    with pytest.raises(FrameError, match="16-bit"):
        validate_frame(bad)
    # a valid header in front of corrupt data passes the accept path and fails at decoding
    bad = agent_pb2.FrameMsg(); bad.CopyFrom(msg); bad.color = msg.color[:200]
    pf = validate_frame(bad)
    with pytest.raises(FrameError):
        pf.materialize()
    cfg = load_config(None, TINY).agent
    rt = AgentRuntime("r", "Pick up the object", {"targets": ["object"], "anchors": [], "relations": []}, cfg,
                      relevance_fn=lambda f: None)
    assert rt.submit(pf) is True
    rt.wait_mapped(WORK_S)
    st = rt.status()
    assert st["frames_rejected"] == 1 and st["frames_mapped"] == 0 and "rejected frame" in st["last_error"]
    rt.close()


def test_realtime_replay_follows_the_clock_and_scores_every_frame(scene):
    from gausslite.parser import TaskParser

    ds = load_dataset(scene / "agent_a")
    text = ds.annotations.task_by_id("synth-pick-object").text
    # no frame withheld for the novel-view protocol: every frame of the replay reaches the agent
    cfg = load_config(None, TINY + ["agent.realtime=true", "agent.rate=0.5",
                                    "agent.scoring.protocols=[sensor,keyframes,tracked]"]).agent
    rt = AgentRuntime("rt", text, TaskParser().parse(text), cfg, annotations=ds.annotations,
                      task_id="synth-pick-object")
    t0 = time.perf_counter()
    rt.replay(ds)
    rt._replay_thread.join(60)
    # 6 frames at 30 Hz, clock slowed to half speed: the last frame is sent 5/30/0.5 s after the first
    assert time.perf_counter() - t0 >= 5 / 30 / 0.5
    s = rt.finish(push=False, timeout_s=WORK_S)
    st = s.status
    assert st["frames_received"] == len(ds) == st["frames_keyframed"] + st["frames_skipped"]
    assert st["frames_keyframed"] >= 1
    assert s.frames_all == len(ds) and s.roi_psnr_all_frames is not None and 0 < s.roi_psnr_all_frames < 80
    # every scoring protocol (agent.scoring): sensor is the every-frame figure, keyframes the mapped ones,
    # tracked every 5th frame
    p = s.protocols
    assert set(p) == {"sensor", "keyframes", "tracked"}
    assert p["sensor"]["roi_psnr"] == s.roi_psnr_all_frames and p["sensor"]["frames_scored"] == len(ds)
    assert p["keyframes"]["frames_scored"] == st["frames_keyframed"]
    assert p["tracked"]["frames_scored"] == len(range(0, len(ds), 5))
    assert all(v["roi_psnr"] is not None and 0 < v["roi_psnr"] < 80 for v in p.values())
    rt.close()
    # sensor alone when told so
    cfg = load_config(None, TINY + ["agent.scoring.protocols=[tracked]", "agent.scoring.track_stride=2"]).agent
    rt = AgentRuntime("rt2", text, TaskParser().parse(text), cfg, annotations=ds.annotations,
                      task_id="synth-pick-object")
    try:
        rt.replay(ds)
        s = rt.finish(push=False, timeout_s=WORK_S)
        assert set(s.protocols) == {"sensor", "tracked"}
        assert s.protocols["tracked"]["frames_scored"] == len(range(0, len(ds), 2))
    finally:
        rt.close()


def test_sim_cli_rejects_rate_without_realtime(tmp_path, capsys):
    from gausslite.cli import main

    assert main(["sim", "--out", str(tmp_path / "x"), "--rate", "2"]) == 2
    assert "--realtime" in capsys.readouterr().err
    assert main(["sim", "--out", str(tmp_path / "x"), "--report-only"]) == 2
    assert main(["sim", "--out", str(tmp_path / "x"), "--protocols", "sensor,oracle"]) == 2
    assert "--protocols" in capsys.readouterr().err


def test_attach_offline_report_puts_the_every_frame_figure_beside_the_realtime_one(tmp_path):
    import json

    from gausslite.team import attach_offline_report

    agent = {"id": "agent_a", "task": "t", "roi_psnr": 20.0, "n_gaussians": 10, "n_shared": 5, "share_pct": 50.0,
             "bytes_per_gaussian": 14.0, "frames_received": 16, "frames_keyframed": 4, "frames_skipped": 12,
             "accept_latency_ms_p99": 0.5, "keyframe_latency_s_p95": 2.0, "keyframe_iterations": 40,
             "idle_iterations": 7, "roi_psnr_all_frames": 21.25, "frames_all": 16, "offline_roi_psnr_all_frames": None}
    rt = {"scene": "s", "seconds": 1.0, "agents": [agent], "fused": {k: {"roi_psnr_per_task": {}, "roi_psnr_mean": None,
          "n_gaussians": 0, "seconds": 0.0} for k in ("concat", "vote", "refine")}, "realtime": True,
          "offline_report": None, "settings": {"voxel_size": 0.1, "refine_iters": 100}}
    (tmp_path / "rt").mkdir()
    (tmp_path / "rt" / "report.json").write_text(json.dumps(rt))
    (tmp_path / "off").mkdir()
    (tmp_path / "off" / "report.json").write_text(json.dumps({"agents": [{"id": "agent_a", "roi_psnr": 27.5}]}))
    rep = attach_offline_report(tmp_path / "rt", tmp_path / "off")
    assert rep["agents"][0]["offline_roi_psnr_all_frames"] == 27.5
    md = (tmp_path / "rt" / "report.md").read_text()
    assert "| agent_a | 16 | 4 | 12 | 0.50 | 2.00 | 10.0 | 7 | 21.25 | 27.50 |" in md
    with pytest.raises(ValueError, match="realtime"):
        attach_offline_report(tmp_path / "rt", tmp_path / "rt")


# ---------------------------------------------------------------------------------------------- sharing
class _RecordingFusion:
    """A FusionClient stand-in that keeps the uploaded chunks."""

    def __init__(self):
        self.uploads = []
        self.keyframe_rois = []

    def open_session(self, agent_id, task_text, intrinsics):
        return None

    def upload_chunks(self, agent_id, version, chunks, n_gaussians=0, full_map_gaussians=0):
        self.uploads.append((version, list(chunks)))
        return type("R", (), {"complete": True, "bytes_sent": sum(len(c) for c in chunks), "n_chunks": len(chunks)})()

    def upload_keyframes(self, agent_id, kfs, jpeg_quality=95, color_format="png", rois=None):
        self.keyframe_rois += list(rois or [None] * len(kfs))
        return len(kfs)


def _run_task_agent(scene, overrides: list, n_frames: int, push_after: int = 0):
    """An agent with ``share: task`` and a fixed ROI box maps ``n_frames`` of the scene's agent_a and pushes
    to a recording fusion stand-in (with ``push_after``, a periodic push is acknowledged before the frames after the
    first ``push_after`` are sent); returns (runtime, fusion, roi)."""
    ds = load_dataset(scene / "agent_a")
    # the share work in the pusher thread, so spies in this process see it (the worker process: its own test)
    cfg = load_config(None, TINY + ["agent.share.rule=task", "agent.ingest=every_frame", "mapper.roi_render=context",
                                          "agent.share.worker=thread", *overrides]).agent
    roi = np.zeros((48, 64), bool)
    roi[12:36, 16:48] = True
    fusion = _RecordingFusion()
    return _mission("a1", cfg, lambda fr: roi, fusion, ds, n_frames, push_after), fusion, roi


def _mission(agent_id, cfg, relevance_fn, fusion, ds, n_frames: int, push_after: int = 0) -> AgentRuntime:
    """One mission of an in-process agent: map ``n_frames`` of ``ds``, finish with a push, close. With
    ``push_after``, the frames after the first ``push_after`` wait for a periodic push to be acknowledged (a loaded
    machine would otherwise fold it into the final one)."""
    rt = AgentRuntime(agent_id, "Pick up the object", {"targets": ["object"], "anchors": [], "relations": []}, cfg,
                      relevance_fn=relevance_fn, fusion=fusion)
    try:
        for i in range(n_frames):
            if push_after and i == push_after:
                deadline = time.monotonic() + WORK_S
                while not rt.pusher.pushes and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert rt.pusher.pushes, rt.status()
            rt.submit(ds[i])
        rt.finish(push=True, evaluate=False, timeout_s=WORK_S)
    finally:
        rt.close()
    return rt


@pytest.mark.parametrize("iters", [0, 7])
def test_task_share_pushes_the_subset_fine_tuned_alone(scene, monkeypatch, iters):
    """``share.rule: task`` with ``share.finetune_iters``: each push carries the output of
    ``finetune_subset`` on the agent's keyframes (the map itself is not modified); 0 turns it off."""
    import gausslite.sharing as sharing
    from gausslite.wire.codec import GaussianArrays, assemble

    calls = []
    real = sharing.finetune_subset

    threads = []

    def spy(subset, keyframes, n, cfg=None, seed=0, **kw):
        threads.append(threading.current_thread().name)
        out = real(subset, keyframes, n, cfg, seed=seed, **kw)
        calls.append((n, len(keyframes), GaussianArrays.from_any(subset), GaussianArrays.from_any(out)))
        return out

    monkeypatch.setattr(sharing, "finetune_subset", spy)
    whole = ["agent.refine_views.crop=false", "agent.refine_views.budget_ratio=null"]  # whole keyframes, their ROI
    rt, fusion, roi = _run_task_agent(scene, [f"agent.share.finetune_iters={iters}", "agent.push.delta=false", *whole],
                                      4)
    assert fusion.uploads
    # keyframes travel with the relevance the agent mapped them with (ROI-restricted refinement)
    assert fusion.keyframe_rois and all(r is not None and np.array_equal(r, roi) for r in fusion.keyframe_rois)
    assert [w for w in rt.pusher._kf_pending if w.roi is not None] == []  # nothing kept once sent
    if iters == 0:
        assert calls == []
        return
    assert 1 <= len(calls) <= len(fusion.uploads) and all(c[0] == iters and c[1] >= 1 for c in calls)
    # the fine-tune runs in the pusher thread: the mapping thread never waits for it (live agents)
    assert threads and all(t == "agent-a1-push" for t in threads), threads
    # an unchanged subset (and keyframes) is not fine-tuned again: the same result, so the delta is empty
    n = len(calls)
    store = rt.mapper.keyframes
    cache = rt.share.finetune_cache
    key, kfs = rt.share.finetune_inputs(calls[-1][2], cache[2], [(int(k.frame_id), k.c2w.cpu().numpy()) for k in store],
                                        [k for k in store if k.sees_roi])
    assert key == cache[0] and kfs
    again = rt.share.finetuned(calls[-1][2], cache[2], key, kfs, rt.mapper.cfg)
    assert len(calls) == n and again is cache[1]
    # the final push is the fine-tuned copy of the final subset, not the map's rows
    pushed, _ = assemble(fusion.uploads[-1][1])
    _, _, before, after = calls[-1]
    assert len(pushed) == len(after) == len(before) > 0
    from scipy.spatial import cKDTree

    dist, match = cKDTree(after.means).query(pushed.means)  # the wire reorders rows spatially
    assert dist.max() < 1e-3 and len(set(match.tolist())) == len(after)
    np.testing.assert_allclose(pushed.colors, after.colors[match], atol=0.02)
    assert np.abs(after.colors - before.colors).max() > 0.02  # fine-tuning changed the subset


def test_task_share_with_delta_pushes_fine_tunes_against_the_acknowledged_copy(scene, monkeypatch):
    """With delta pushes, every push after the first fine-tunes against the copy the server acknowledged
    (``update_shared_subset`` gets the planner's base), and the delta carries at most the new rows plus
    ``share.refresh`` of the held ones."""
    import gausslite.sharing as sharing
    from gausslite.wire.codec import peek_header

    calls = []
    real = sharing.update_shared_subset

    def spy(arrays, ids, base, base_ids, keyframes, iters, refresh=0.1, *a, **kw):
        out, st = real(arrays, ids, base, base_ids, keyframes, iters, refresh, *a, **kw)
        calls.append((None if base is None else len(base), refresh, dict(st)))
        return out, st

    monkeypatch.setattr(sharing, "update_shared_subset", spy)
    _, fusion, _ = _run_task_agent(scene, ["agent.share.finetune_iters=5", "agent.share.refresh=0.2"], 6,
                                   push_after=2)
    assert len(calls) >= 2 and calls[0][0] is None and calls[0][2]["base"] == 0
    later = [c for c in calls[1:] if c[0] is not None]
    assert later, calls
    for n_base, refresh, st in later:
        assert refresh == 0.2 and st["refreshed"] == int(0.2 * st["base"]) and st["base"] <= n_base
    deltas = [[peek_header(c) for c in ch] for _, ch in fusion.uploads[1:]]
    assert deltas and all(h.delta for d in deltas for h in d)
    # rows carried by the first delta: the new rows and the refreshed rows at most, never the frozen ones
    st = later[0][2]
    assert sum(h.count for h in deltas[0]) <= st["new"] + st["refreshed"] < st["new"] + st["base"]


def test_new_mission_never_reuses_a_version_the_fusion_server_holds(scene, tmp_path):
    """A fusion server that kept this agent's subset from an earlier mission (same agent id, a re-run into the
    same data dir): the new mission pushes above that version. Both missions push once, at the end, as v1 of
    their own count: without the rule the resumable upload would find v1 complete on the server and take the
    old mission's chunks for the new ones."""
    from gausslite.wire.codec import assemble
    from gausslite_services.fusion_server.client import FusionClient
    from gausslite_services.fusion_server.server import serve as serve_fusion

    ds = load_dataset(scene / "agent_a")
    srv = serve_fusion(ServerOptions(port=0, max_workers=8), None, data_dir=str(tmp_path / "fusion"))
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            c.wait_ready(10)
            runs = []
            for n_frames in (2, 5):
                cfg = load_config(None, TINY + ["agent.ingest=every_frame", "agent.share.rule=active",
                                                      "agent.push.every=100"]).agent
                rt = _mission("robot", cfg, lambda fr: np.ones((48, 64), bool), c, ds, n_frames)
                assert rt.pusher.final_push_ok and len(rt.pusher.pushes) == 1
                runs.append(rt.pusher.pushes[0])
            first, second = runs
            assert first.version == 1 and second.version == 2 and second.bytes_on_wire > 0
            assert srv.store.latest_version("robot") == 2
            held, _ = assemble(srv.store.chunk_data("robot", 2))
            assert len(held) == second.n_shared != first.n_shared
    finally:
        srv.stop(0.5)


def test_an_unchanged_subset_is_not_uploaded_again_but_kappa_growth_is(scene):
    """A push whose delta would change nothing (no record, no removal, κ shift 0), e.g. the final push
    right after a periodic one, uploads nothing (an empty delta is still 270 B of headers) and is logged
    as ``unchanged`` at the version the server holds; κ growth alone is a real push (the κ shift)."""
    from gausslite.wire.codec import GaussianArrays, peek_header
    from gausslite.mission.pusher import Snapshot

    rt, fusion, _ = _run_task_agent(scene, ["agent.share.finetune_iters=0"], 2)
    n_up, n_push = len(fusion.uploads), len(rt.pusher.pushes)
    base = rt.share.planner.base
    ids = rt.share.planner.base_ids
    held = rt.pusher.pushes[-1].version
    rt.pusher.push_once(Snapshot(held + 1, base, 1000, True, ids, 2))
    assert len(fusion.uploads) == n_up and len(rt.pusher.pushes) == n_push + 1
    rec = rt.pusher.pushes[-1]
    assert rec.unchanged and rec.bytes_on_wire == 0 and rec.version == held == rt.share.planner.base_version
    assert rt.pusher.total_upload_bytes == sum(p.bytes_on_wire for p in rt.pusher.pushes)
    grown = GaussianArrays(**{k: np.array(getattr(base, k), copy=True) for k in GaussianArrays.FIELDS})
    grown.kappa[grown.active] += 25
    rt.pusher.push_once(Snapshot(held + 2, grown, 1000, True, ids, 2))
    assert len(fusion.uploads) == n_up + 1 and not rt.pusher.pushes[-1].unchanged
    hdr = [peek_header(c) for c in fusion.uploads[-1][1]]
    assert all(h.delta and h.kappa_shift == 25 for h in hdr) and sum(h.count for h in hdr) == 0


def test_pusher_runs_at_lower_priority_and_fine_tunes_with_one_thread_of_its_own(monkeypatch):
    """The share fine-tune competes with mapping on a robot's few cores: the pusher thread takes
    ``agent.push.nice`` niceness, and its fine-tune renders with a single rasterizer thread (the band pool is
    shared with the mapper and runs at the mapper's priority)."""
    import os

    from gausslite.mission import AgentConfig

    graph = {"targets": ["object"], "anchors": [], "relations": []}
    cfg = AgentConfig(share={"rule": "task", "worker": "thread"},
                      mapper=MapperConfig(mode="gausslite", performance={"render_threads": 2}))
    rt = AgentRuntime.launch("p1", "Pick up the object", graph, cfg, relevance_fn=lambda fr: None)
    try:
        deadline = time.time() + 5
        nice = None
        while time.time() < deadline:
            nice = os.getpriority(os.PRIO_PROCESS, rt.pusher.thread.native_id)
            if nice >= 19:
                break
            time.sleep(0.02)
        assert nice == 19
        seen = {}

        def fake_update(arrays, ids, base, base_ids, kfs, iters, refresh, fcfg, seed=0):
            seen["threads"] = fcfg.performance.render_threads
            return arrays, {}

        monkeypatch.setattr("gausslite.sharing.update_shared_subset", fake_update)
        rt.share.finetuned(np.zeros(0), np.zeros(0, np.int64), b"key", [], rt.mapper.cfg)
        assert seen["threads"] == 1 and rt.mapper.cfg.performance.render_threads == 2
    finally:
        rt.close()
    with pytest.raises(Exception):
        AgentConfig(push={"nice": 20})
    assert AgentConfig().push.nice == 19


def test_task_share_in_the_worker_process_pushes_a_fine_tuned_subset(scene, monkeypatch):
    """``share.worker: process`` (the default): selection and fine-tune run in a worker process of their own (no
    interpreter lock shared with mapping); the pushes carry a fine-tuned task subset, and close() stops the worker."""
    import gausslite.sharing as sharing
    from gausslite.wire.codec import assemble

    here = []
    for name in ("select_task_subset", "update_shared_subset"):
        real = getattr(sharing, name)
        monkeypatch.setattr(sharing, name, lambda *a, _real=real, _n=name, **kw: here.append(_n) or _real(*a, **kw))
    rt, fusion, _ = _run_task_agent(scene, ["agent.share.worker=process", "agent.share.finetune_iters=5",
                                            "agent.push.delta=false"], 4)
    assert fusion.uploads and rt.pusher.final_push_ok
    pushed, _ = assemble(fusion.uploads[-1][1])
    assert 0 < len(pushed) <= rt.n_gaussians
    assert rt.share.finetune_cache is not None  # the last push was fine-tuned...
    assert here == []  # ...and neither the selection nor the fine-tune ran in the agent's process
    assert rt.share.pool is None  # close() stopped the worker


@pytest.mark.parametrize("realtime", [False, True])
def test_the_share_worker_starts_with_the_mission_not_at_its_first_push(scene, realtime, monkeypatch):
    """Under ``share.worker_start: mission`` a sharing mission starts (and warms up) its share worker process when
    its replay starts, before any frame is mapped, and the pushes use that same process; a live mission's worker
    runs at ``push.nice``, an every-frame replay's at the mapper's priority. By default (``first_push``) no worker
    runs until the first push."""
    from gausslite.mission import AgentConfig
    from gausslite.mission.share import _warm

    ds = load_dataset(scene / "agent_a")
    graph = {"targets": ["object"], "anchors": [], "relations": []}
    share = {"rule": "task", "worker": "process"}
    base = dict(realtime=realtime, rate=0.2,
                mapper=MapperConfig(mode="gausslite", iters_per_frame=2, warmup_iters=1, seeds_per_frame=100))
    rt = AgentRuntime("w0", "Pick up the object", graph, AgentConfig(**base, share=share),
                      relevance_fn=lambda fr: None, fusion=_RecordingFusion())
    try:
        rt.replay(ds)
        assert rt.share.pool is None and rt.share.warm is None  # the default: at the first push
    finally:
        rt.close()
    cfg = AgentConfig(**base, share={**share, "worker_start": "mission"})
    rt = AgentRuntime("w1", "Pick up the object", graph, cfg, relevance_fn=lambda fr: None, fusion=_RecordingFusion())
    try:
        assert rt.share.pool is None  # nothing runs before the mission starts
        rt.replay(ds)
        assert rt.share.pool is not None and rt.share.warm is not None and rt.frames_mapped < len(ds)
        pid = rt.share.warm.result(timeout=300)  # the warm-up job ran in the worker process...
        assert pid != os.getpid() and rt.share.call(_warm) == pid  # ...which is the one the pushes use
        expected = min(19, os.getpriority(os.PRIO_PROCESS, 0) + (19 if realtime else 0))
        assert os.getpriority(os.PRIO_PROCESS, pid) == expected
        import gausslite.mission.share as share_mod

        killed, real_kill = [], os.kill
        monkeypatch.setattr(share_mod.os, "kill", lambda p, sig: (killed.append((p, sig)), real_kill(p, sig)))
    finally:
        rt.close()
    assert rt.share.pool is None and killed == [(pid, signal.SIGTERM)]

    def gone() -> bool:  # terminated, not left to end its interpreter at low priority while the agent waits
        try:
            return os.waitpid(pid, os.WNOHANG)[0] == pid
        except ChildProcessError:
            return True

    assert wait_until(gone, WORK_S)
    # a mission that does not share (no fusion client) or shares without the worker starts no process
    for kw in ({"fusion": None}, {"fusion": _RecordingFusion(), "share": "active"}):
        c = AgentConfig(share={"rule": kw.get("share", "task"), "worker": "process", "worker_start": "mission"},
                        mapper=MapperConfig(mode="gausslite"))
        r = AgentRuntime("w2", "Pick up the object", graph, c, relevance_fn=lambda fr: None, fusion=kw["fusion"])
        try:
            r.lifecycle.start_share(True)
            assert r.share.pool is None
        finally:
            r.close()


def test_a_selected_snapshot_is_superseded_at_most_once_in_a_row(monkeypatch):
    """When the selection takes longer than the keyframes between pushes, a newer snapshot is always waiting by the
    time it ends; the pusher skips the older one once, then pushes, so a long live mission keeps pushing."""
    from gausslite.mission import AgentConfig
    from gausslite.mission.pusher import Snapshot

    graph = {"targets": ["object"], "anchors": [], "relations": []}
    cfg = AgentConfig(share={"rule": "task", "worker": "thread"}, mapper=MapperConfig(mode="gausslite"))
    rt = AgentRuntime("s1", "Pick up the object", graph, cfg, relevance_fn=lambda fr: None, fusion=object())
    pushed = []
    try:
        def select(cap, backend="auto"):
            with rt.pusher._lock:  # a newer snapshot arrives while this one is being selected
                rt.pusher._pending = Snapshot(99, None, 1, False, np.zeros(1, np.int64), 0, None, "later")
            return dataclasses.replace(cap, gaussians="subset", finetune=("key", []), select=None)

        monkeypatch.setattr(rt.share, "select", select)
        monkeypatch.setattr(rt.share, "finetuned", lambda arrays, ids, key, kfs, cfg: arrays)
        monkeypatch.setattr(rt.pusher, "_push_with_retries", lambda snap, budget: pushed.append(snap.version) or True)
        for v in (1, 2, 3):
            with rt.pusher._lock:  # the pusher loop has taken the pending snapshot
                rt.pusher._pending = None
            rt.pusher.push_snapshot(Snapshot(v, None, 1, False, np.zeros(1, np.int64), 0, None, "select"))
        assert pushed == [2]  # v1 superseded, v2 pushed although v99 waited, v3 superseded again
    finally:
        with rt.pusher._lock:
            rt.pusher._pending = None
        rt.close()


def test_the_mapping_resolution_is_reported_pinned_or_chosen_and_maps_what_it_says(scene):
    """``agent.resolution``: a pinned downscale maps every keyframe at that size and is reported in GetStatus; the
    keyframes sent to the fusion session keep the size the mission opened with; automatic, a tiny image under a
    generous budget maps at its own size and says it reaches the target."""
    ds = load_dataset(scene / "agent_a")
    graph = {"targets": ["object"], "anchors": [], "relations": []}
    for extra, factor, pinned in ((["agent.resolution.downscale=2"], 2.0, True),
                                  (["mapper.keyframe_budget_s=0.5", "mapper.budget.max_gaussians=2000",
                                   "agent.resolution.min_width=16"], 1.0, False)):
        cfg = load_config(None, TINY + ["agent.ingest=every_frame", *extra]).agent
        rt = AgentRuntime("res", "Pick up the object", graph, cfg, relevance_fn=lambda fr: np.ones(fr.depth.shape, bool))
        sizes = []
        orig = rt.mapper.map_frame

        def spy(frame, w=None, **kw):
            sizes.append((frame.intrinsics.width, frame.intrinsics.height, None if w is None else w.shape))
            return orig(frame, w, **kw)

        rt.mapper.map_frame = spy
        try:
            for i in range(3):
                rt.submit(ds[i])
            assert rt.wait_mapped(WORK_S)
            st = rt.status()
            w, h = 64 // int(factor), 48 // int(factor)
            assert set(sizes) == {(w, h, (h, w))}
            assert (st["mapping_width"], st["mapping_height"], st["mapping_downscale"]) == (w, h, factor)
            assert st["resolution_pinned"] is pinned
            if not pinned:
                assert st["resolution_predicted_iters"] > 10 and st["resolution_reaches_target"]
            assert (rt.upload_intrinsics.width, rt.upload_intrinsics.height) == (w, h)
            msg = agent_pb2.MissionStatus(**{k: v for k, v in st.items() if k != "state"})
            assert msg.mapping_downscale == factor and msg.mapping_width == w
        finally:
            rt.close()


class _ViewRecorder(_RecordingFusion):
    """A fusion stand-in that also keeps the refinement views it is sent."""

    def __init__(self):
        super().__init__()
        self.views = []

    def upload_keyframes(self, agent_id, kfs, jpeg_quality=95, color_format="png", rois=None):
        self.views += list(zip(kfs, rois or [None] * len(kfs)))
        return super().upload_keyframes(agent_id, kfs, jpeg_quality, color_format, rois)


def test_a_live_agent_sends_roi_crops_of_keyframes_and_of_the_frames_between_them_within_its_budget(scene):
    from gausslite.parser import TaskParser

    ds = load_dataset(scene / "agent_a")
    text = ds.annotations.task_by_id("synth-pick-object").text
    cfg = load_config(None, TINY + ["agent.realtime=true", "agent.rate=0.5", "agent.upload_keyframe_every=1",
                                    "agent.keyframe_max_interval_s=0.1", "agent.keyframe_translation_m=10",
                                    "agent.keyframe_rotation_deg=90", "agent.refine_views.crop=true",
                                    "agent.refine_views.between=true", "agent.refine_views.between_every=1",
                                    "agent.refine_views.min_roi_px=4", "agent.refine_views.budget_ratio=40"],
                      ).agent
    fusion = _ViewRecorder()
    rt = AgentRuntime("rv", text, TaskParser().parse(text), cfg, annotations=ds.annotations,
                      task_id="synth-pick-object", fusion=fusion)
    try:
        rt.replay(ds)
        s = rt.finish(push=True, timeout_s=WORK_S)
    finally:
        rt.close()
    st = s.status
    assert st["frames_keyframed"] >= 2 and st["frames_skipped"] >= 1
    sent = {int(f.frame_id) for f, _ in fusion.views}
    keyframes = {int(x.frame_id) for x in rt.mapper.stats}
    assert sent - keyframes, (sent, keyframes)  # frames that were never keyframes reached the server as views
    full = ds[0].rgb.shape[:2]
    for f, roi in fusion.views:
        assert roi is not None and roi.shape == f.depth.shape and roi.any()
        assert f.rgb.shape[0] <= full[0] and f.rgb.shape[1] <= full[1]
        assert (f.intrinsics.width, f.intrinsics.height) == (f.rgb.shape[1], f.rgb.shape[0])
    assert s.views_sent == len(fusion.views) and 0 < s.view_bytes <= 40 * s.final_subset_bytes
    # the own map's tracked views travel with the summary: a team map is scored at them
    assert set(s.tracked_views) == set(range(0, len(ds), 5)) and all(v.c2w.shape == (4, 4) for v in s.tracked_views.values())
