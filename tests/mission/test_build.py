"""How a mission is built (docs/architecture.md, "How a mission is built"): ``gausslite.mission.build_mission`` builds
the runtime from the typed settings, the task and the fusion side, started or not; ``replay_dataset`` opens a sequence
with its sensor profile; the agent service and the benchmarks build their missions through it and no other code
constructs an ``AgentRuntime``; one ``PoseSource`` type names where poses come from."""

from __future__ import annotations

import ast
from pathlib import Path
from types import SimpleNamespace
from typing import get_args

import numpy as np
import pytest

from gausslite.config import load_config
from gausslite.odometry.rgbd import POSE_SOURCES, PoseSource
from gausslite.mapping.profiles import profile_for_layout, with_profile
from gausslite.mission import AgentRuntime, build_mission, replay_dataset
from gausslite.mission.fakes import SinkFusion
from tests._scenes import plane_frame, plane_roi
from tests._source import calls_in
from tests._waits import WORK_S

ROOT = Path(__file__).resolve().parents[2]
GRAPH = {"targets": ["object"], "anchors": [], "relations": []}
#: the callers that build a mission, and the function of each that does
CALLERS = {"services/agent/server.py": "start_mission", "bench/realtime/missions.py": "start_mission",
           "bench/odometry.py": "live"}


def _config(*overrides):
    return load_config(None, ["agent.ingest=every_frame", "agent.push.every=1000", "mapper.mode=gausslite",
                              "mapper.iters_per_frame=3", "mapper.warmup_iters=1", *overrides]).agent


def _shift(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_build_mission_maps_a_tiny_scene_and_pushes_to_its_fusion_side():
    cfg, sink = _config("agent.share.worker=thread", "agent.share.finetune_iters=2"), SinkFusion()
    rt = build_mission(cfg, "Pick up the object", GRAPH, agent_id="b", fusion=sink, relevance_fn=lambda fr: plane_roi(),
                       T_world_map=_shift(1.0))
    try:
        assert isinstance(rt, AgentRuntime) and rt.agent_id == "b" and rt.fusion is sink
        assert np.allclose(rt.T_world_map, _shift(1.0))  # the mission's own frame; the settings stay as they were
        assert cfg.frame.matrix() is None and rt.config.mapper == cfg.mapper
        for i in range(3):
            assert rt.submit(plane_frame(i, 0.05 * i))
        assert rt.wait_mapped(WORK_S)
        summary = rt.finish(push=True, evaluate=False, timeout_s=WORK_S)
        assert rt.frames_mapped == 3 and summary.final_push_ok and sink.uploads >= 1
    finally:
        rt.close()


def test_build_mission_unstarted_parses_the_task_and_takes_a_mapper_of_its_own():
    cfg = _config()
    mapper = cfg.mapper.model_copy(update={"final_iters": 0})
    rt = build_mission(cfg, "pick up the cup", relevance_fn=lambda fr: plane_roi(), mapper=mapper, start=False)
    try:
        assert not rt.lifecycle.started and rt.agent_id == "agent"
        assert "cup" in list(rt.graph.targets)  # the in-process rule parser's graph
        assert rt.config.mapper == mapper and rt.config.mapper.final_iters == 0
        assert cfg.mapper is not mapper and rt.config is not cfg  # the settings given stay as they were
    finally:
        rt.close()


def test_build_mission_refuses_what_the_runtime_refuses():
    with pytest.raises(ValueError, match="agent_id"):
        build_mission(_config(), "Pick up the object", GRAPH, agent_id="", relevance_fn=lambda fr: plane_roi())
    with pytest.raises(ValueError):
        build_mission(_config(), "Pick up the object", GRAPH, T_world_map=np.full((4, 4), 2.0),
                      relevance_fn=lambda fr: plane_roi(), start=False)


def test_replay_dataset_opens_a_sequence_with_its_sensor_profile(tmp_path):
    from gausslite.synthetic import make_scene

    make_scene(tmp_path, seed=0, width=64, height=48, frames=4, progress=False)
    cfg = load_config(None, ["agent.max_frames=3"]).agent
    ds, out, profile = replay_dataset(tmp_path / "agent_a", cfg)
    assert len(ds) == 3 and ds.annotations is not None
    assert profile == profile_for_layout("replica")
    assert out.mapper == with_profile(cfg.mapper, profile) and out.max_frames == 3
    with pytest.raises(FileNotFoundError):
        replay_dataset(tmp_path / "missing", cfg)


@pytest.mark.parametrize("path", sorted(CALLERS))
def test_every_caller_builds_its_mission_with_build_mission(path):
    assert "build_mission" in calls_in(path, CALLERS[path])


def test_no_code_but_build_mission_constructs_a_runtime():
    allowed = {ROOT / "gausslite/mission/runtime.py", ROOT / "gausslite/mission/build.py"}
    found = []
    for folder in ("gausslite", "services", "bench"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path in allowed:
                continue
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if not isinstance(node, ast.Call):
                    continue
                f = node.func
                if (isinstance(f, ast.Name) and f.id == "AgentRuntime") or (
                        isinstance(f, ast.Attribute) and f.attr == "launch" and isinstance(f.value, ast.Name)
                        and f.value.id == "AgentRuntime"):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not found, f"AgentRuntime built outside build_mission: {found}"


def test_gausslite_map_runs_no_mission_and_takes_the_loaders_pose_sources():
    import argparse

    from gausslite.cli import cmd_map

    assert "build_mission" not in calls_in("gausslite/cli/cmd_map.py", "_handler")
    p = argparse.ArgumentParser()
    cmd_map.add_mapping_args(p)
    choices = next(a.choices for a in p._actions if a.dest == "pose_source")
    assert tuple(choices) == POSE_SOURCES == ("auto", *get_args(PoseSource))


def test_one_pose_source_type_for_the_agent_and_the_loader():
    from gausslite.mission.config import AgentConfig

    assert get_args(PoseSource) == ("given", "odometry")
    assert AgentConfig.model_fields["pose_source"].annotation == PoseSource
    for value in get_args(PoseSource):
        assert AgentConfig(pose_source=value).pose_source == value
    with pytest.raises(ValueError):
        AgentConfig(pose_source="auto")  # a mission's frames come with poses or are tracked: no "auto"


def test_the_agent_service_builds_its_mission_with_build_mission(monkeypatch):
    from gausslite_services.agent import server

    calls = []

    def spy(config, task_text, graph=None, **kw):
        calls.append((config, task_text, graph, kw))
        return SimpleNamespace(mission_id="m1", agent_id=kw["agent_id"], close=lambda: None)

    monkeypatch.setattr(server, "build_mission", spy)
    servicer = server.AgentServicer(server.AgentSettings(agent_id="a1"))
    T = _shift(0.5)
    rt = servicer.start_mission("pick up the cup", T_world_map=T.reshape(-1).tolist())
    assert rt.mission_id == "m1" and servicer.current == "m1" and len(calls) == 1
    config, text, graph, kw = calls[0]
    assert text == "pick up the cup" and "cup" in list(graph.targets)
    assert config is servicer.settings.config and kw["agent_id"] == "a1" and kw["start"] is True
    assert np.allclose(kw["T_world_map"], T) and kw["fusion"] is None and kw["on_finished"] == servicer._save
    servicer.close()
