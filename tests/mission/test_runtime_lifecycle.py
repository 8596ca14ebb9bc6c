"""The runtime's life cycle (gausslite.mission.runtime): building one assembles its parts and neither reads a
checkpoint nor starts a thread; ``start`` (or ``launch``, which builds and starts) resumes the checkpoint and starts
the threads, once; a runtime used without ``start`` starts at its first frame, replay or Finish; a closed one never
starts. The mapper is a stand-in: these tests are about the order of things, not the map."""

from __future__ import annotations

import threading

import pytest

from gausslite.config import load_config
from gausslite.mapping.mapper import FrameStats
from gausslite.mission import AgentRuntime, MissionError, MissionState
from tests._scenes import plane_frame
from tests._waits import WORK_S

GRAPH = {"targets": ["object"], "anchors": [], "relations": []}
CFG = ["agent.ingest=every_frame", "agent.push.every=1000", "agent.checkpoint_every=1", "mapper.mode=uniform",
       "agent.resolution.min_width=16"]


def _runtime(task="Pick up the object", build=AgentRuntime, **kw) -> AgentRuntime:
    rt = build("L", task, GRAPH, load_config(None, CFG).agent, relevance_fn=lambda fr: None, mission_id="m1", **kw)
    rt.mapper.map_frame = lambda frame, *a, **k: FrameStats(frame.frame_id, 0.01, 0, 0, 0, 0.0, 0, iters=1)
    return rt


def _threads() -> set:
    return {t.name for t in threading.enumerate() if t.name.startswith("agent-L-")}


def test_building_starts_nothing_and_a_closed_runtime_never_starts():
    rt = _runtime()
    try:
        assert not rt.worker.thread.is_alive() and not rt.pusher.thread.is_alive() and not _threads()
        st = rt.status()
        assert st["state"] == MissionState.MAPPING and st["frames_received"] == 0 and rt.wait_mapped(0)
    finally:
        rt.close()
    assert not _threads()
    with pytest.raises(MissionError, match="closed"):
        rt.start()
    with pytest.raises(MissionError):
        rt.submit(plane_frame(0))


def test_start_starts_the_threads_once_and_the_first_frame_starts_a_runtime_not_started():
    rt = _runtime()
    try:
        assert rt.start() is rt
        worker = rt.worker.thread
        assert rt.start() is rt and rt.worker.thread is worker and worker.is_alive() and rt.pusher.thread.is_alive()
    finally:
        rt.close()
    assert not worker.is_alive()
    rt = _runtime()
    try:
        assert rt.submit(plane_frame(0)) and rt.wait_mapped(WORK_S)  # as callers that never call start do
        assert rt.frames_mapped == 1 and rt.worker.thread.is_alive()
        s = rt.finish(push=False, evaluate=False, timeout_s=WORK_S)
        assert s.status["frames_mapped"] == 1 and rt.state == MissionState.FINISHED
    finally:
        rt.close()


def test_the_checkpoint_is_resumed_at_start_not_when_the_runtime_is_built(tmp_path):
    rt = _runtime(checkpoint_dir=tmp_path / "m1")
    try:
        for i in range(2):
            rt.submit(plane_frame(i, 0.1 * i))
        assert rt.wait_mapped(WORK_S) and rt.checkpoints == 2 and rt.checkpoint.exists()
    finally:
        rt.close()
    again = _runtime(checkpoint_dir=tmp_path / "m1")
    try:
        assert again.resumed_keyframes == 0 and again.frames_keyframed == 0  # built: nothing read yet
        again.start()
        assert again.resumed_keyframes == 2 == again.status()["frames_keyframed"]
    finally:
        again.close()
    launched = _runtime(checkpoint_dir=tmp_path / "m1", build=AgentRuntime.launch)
    try:
        assert launched.resumed_keyframes == 2 and launched.worker.thread.is_alive()
    finally:
        launched.close()
    with pytest.raises(ValueError, match="was started with the task"):
        _runtime("Open the box", checkpoint_dir=tmp_path / "m1", build=AgentRuntime.launch)
    assert not _threads()  # the runtime whose start failed was closed
