"""Returning a push's freed memory to the OS (gausslite.mission.heap) happens on the mapping thread, never on the
pusher thread: at ``push.nice`` a thread holding the interpreter lock or the allocator's locks
(``malloc_trim``) is descheduled whenever another process wants the cores, and every thread of the agent waits for it
(docs/live.md, "Beside other processes")."""

from __future__ import annotations

import threading

from gausslite.config import load_config
from gausslite.mapping.mapper import FrameStats
from gausslite.mission import AgentRuntime
from gausslite.mission import worker as worker_mod
from tests._scenes import plane_frame
from tests._waits import WORK_S, wait_until

GRAPH = {"targets": ["object"], "anchors": [], "relations": []}


def test_a_push_is_trimmed_by_the_mapping_thread_not_the_niced_pusher(monkeypatch):
    trims = []
    monkeypatch.setattr(worker_mod, "trim_heap", lambda: trims.append(threading.current_thread().name) or True)
    cfg = load_config(None, ["agent.ingest=every_frame", "agent.push.every=1", "mapper.mode=uniform",
                             "agent.resolution.min_width=16"]).agent
    rt = AgentRuntime("t", "Pick up the object", GRAPH, cfg, relevance_fn=lambda fr: None)
    rt.mapper.map_frame = lambda frame, *a, **k: FrameStats(frame.frame_id, 0.01, 0, 0, 0, 0.0, 0, iters=1)
    try:
        for i in range(3):
            rt.submit(plane_frame(i, 0.1 * i, 24, 32))
        assert rt.wait_mapped(WORK_S)
        # each push sets the flag when it is done; the worker, awake at least every 0.5 s, takes it
        assert wait_until(lambda: trims, 60), "the mapping thread never trimmed after a push (waited 60 s)"
    finally:
        rt.close()
    assert set(trims) == {"agent-t-map"}, trims


def test_the_mapping_threads_trim_does_not_walk_the_heap(monkeypatch):
    """A full collection walks every object (tens of milliseconds with PyTorch loaded), taken from a keyframe's
    budget after every push: the mapping thread only returns free pages; a caller that asks collects first."""
    import gc

    from gausslite.mission import heap

    calls = []
    monkeypatch.setattr(gc, "collect", lambda *a: calls.append(a) or 0)
    heap.trim_heap()
    assert calls == []
    heap.trim_heap(collect=True)
    assert len(calls) == 1
