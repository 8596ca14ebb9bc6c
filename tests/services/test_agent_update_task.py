"""A running mission takes a new task (``UpdateTask``): the map re-targets to it and keeps what it has mapped; bad
requests get precise status codes."""

from __future__ import annotations

import time

import grpc
import numpy as np
import pytest

from gausslite.datasets import load_dataset
from gausslite.config import load_config
from gausslite.synthetic import make_scene
from gausslite_services.agent.client import AgentClient
from gausslite_services.agent.server import AgentSettings, serve as serve_agent
from gausslite_services.common.server import ServerOptions
from tests._waits import WORK_S

TINY = ["agent.ingest=every_frame", "agent.push.every=100", "agent.upload_keyframe_every=1", "mapper.iters_per_frame=4",
        "mapper.warmup_iters=1", "mapper.seeding.seeds_per_frame=300",
        "agent.share.worker=thread"]  # the share worker process has tests of its own (test_agent_live.py)
OBJECT = "Prepare to pick up the object on the desk"
CHAIR = "Identify the chair closest to the table"


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene")
    make_scene(out, seed=0, width=64, height=48, frames=6, progress=False)
    return out


@pytest.fixture()
def agent(scene):
    ag = serve_agent(ServerOptions(port=0), AgentSettings(agent_id="robot", annotations_path=str(scene),
                                                          config=load_config(None, TINY).agent))
    c = AgentClient(ag.address)
    yield ag, c
    c.close()
    ag.stop(0)


def _wait(pred, timeout_s=60.0):
    deadline = time.monotonic() + timeout_s
    while not pred():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_update_task_retargets_a_running_mission(agent, scene):
    ag, c = agent
    ds = load_dataset(scene / "agent_a")
    m = c.start_mission(OBJECT)
    c.stream_frames(m.mission_id, [ds[i] for i in range(3)])
    _wait(lambda: c.status(m.mission_id).frames_mapped == 3)
    rt = ag.servicer.missions[m.mission_id]
    assert c.status(m.mission_id).n_active > 0
    object_active = rt.mapper.model.active.clone()

    r = c.update_task(m.mission_id, CHAIR)
    assert list(r.graph.targets) == ["chair"]
    _wait(lambda: c.status(m.mission_id).task_text == CHAIR)
    st = c.status(m.mission_id)
    assert st.task_id == "synth-find-chair" and st.frames_mapped == 3
    # the map is kept; the stored keyframes now carry the chair's relevance, not the object's
    ann = rt.annotations
    for k in rt.mapper.keyframes:
        fr = next(f for f in (ds[i] for i in range(3)) if f.frame_id == k.frame_id)
        want = rt.relevance(fr)
        got = np.zeros(want.shape, bool) if k.roi is None else k.roi.numpy()
        assert np.array_equal(got, want)
        assert not np.array_equal(got, ann.roi_mask("synth-pick-object", fr.depth, fr.c2w, fr.intrinsics)) or \
            not got.any()
    # new frames map for the chair: its Gaussians join the task, the object's left it
    c.stream_frames(m.mission_id, [ds[i] for i in range(3, 6)])
    _wait(lambda: c.status(m.mission_id).frames_mapped == 6)
    active = rt.mapper.model.active
    assert bool(active.any()) and int(rt.mapper.model.kappa.max()) > 0
    n_old = min(len(object_active), len(active))
    assert int((active[:n_old] & object_active[:n_old]).sum()) < int(object_active.sum())
    s = c.finish(m.mission_id, skip_push=True, timeout_s=WORK_S)
    assert s.status.task_text == CHAIR
    with pytest.raises(grpc.RpcError) as e:
        c.update_task(m.mission_id, OBJECT)
    assert e.value.code() == grpc.StatusCode.FAILED_PRECONDITION


def test_update_task_bad_requests(agent, scene):
    ag, c = agent
    with pytest.raises(grpc.RpcError) as e:
        c.update_task("no-such-mission", CHAIR)
    assert e.value.code() == grpc.StatusCode.NOT_FOUND
    m = c.start_mission(OBJECT)
    for text, task_id in (("   ", ""), ("x" * 3000, ""), ("find\x00chair", ""), (CHAIR, "no-such-task")):
        with pytest.raises(grpc.RpcError) as e:
            c.update_task(m.mission_id, text, task_id)
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, (text[:10], e.value.details())
    assert c.status(m.mission_id).task_text == OBJECT  # nothing changed
