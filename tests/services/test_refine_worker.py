"""The team map's refinement process (RefineWorker): it refines as the engine does in the server's own process, keeps
the decoded views between refinements (and only those the store still holds), reports a refusal and serves on, and
a stop kills it at once; the next refinement starts a new process."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest

from gausslite.fusion.engine import FuseEngine, FuseOutcome
from gausslite.wire import images
from tests.services.test_fusion_server import HAVE_REFINE, INTR, frame, rand_subset

from gausslite_services.fusion_server.refine_worker import POLL_S, RefineWorker, decode_keyframe, keyframe_key
from gausslite_services.fusion_server.store import StoredKeyframe

pytestmark = [pytest.mark.integration, pytest.mark.skipif(not HAVE_REFINE, reason="needs the 'mapper' extra")]

OPTIONS = {"holdout_fraction": 0.25, "check_every": 5, "patience": 3, "per_view_iters": 0}
PERF = {"performance": {"render_threads": 1, "torch_threads": 1}}


def _stored(agent: str, i: int, shift: float) -> StoredKeyframe:
    f = frame(i, shift)
    depth, scale = images.encode_depth_png(f.depth)
    k = INTR
    return StoredKeyframe(agent, i, images.encode_color_png(f.rgb), depth, scale, f.c2w, k.fx, k.fy, k.cx, k.cy,
                          k.width, k.height, f.timestamp, images.encode_roi_png(np.ones((k.height, k.width), bool)))


def _plane(seed: int, off: float):
    g = rand_subset(300, 0.0, seed)
    g.means[:, 0] = g.means[:, 0] * 0.8 + off
    g.means[:, 1] = g.means[:, 1] * 0.6 - 0.3
    g.means[:, 2] = 1.5
    return g


@pytest.fixture(scope="module")
def worker():
    w = RefineWorker(nice=5)
    yield w
    w.kill()


def test_the_process_refines_as_the_engine_does_in_process_and_keeps_the_decoded_views(worker):
    vote = FuseEngine().fuse({"a": 1, "b": 1}, {"a": _plane(1, -0.3), "b": _plane(2, 0.0)}, "vote").fused
    stored = [_stored("a", i, 0.05 * i) for i in range(3)] + [_stored("b", 10 + i, 0.05 * i) for i in range(3)]
    got = worker.refine(vote, stored, 20, 0, OPTIONS, PERF, lambda: False)
    assert worker.pid is not None and worker.pid != os.getpid() and worker.starts == 1
    assert os.getpriority(os.PRIO_PROCESS, worker.pid) >= 5
    here = FuseOutcome(vote, {})
    views = {}
    for k in stored:
        views.setdefault(k.agent_id, []).append(decode_keyframe(k))
    FuseEngine(OPTIONS).refine(here, lambda: views, 20, 0, options=PERF)
    assert got.keyframes_used == here.keyframes_used == 6 and got.decoded == 6
    rep, ref = got.report, here.refine_report
    assert (rep.train_views, rep.heldout_views, rep.iters_planned) == (ref.train_views, ref.heldout_views, 20)
    assert rep.vote_loss == pytest.approx(ref.vote_loss, rel=1e-5) and len(got.fused) == len(here.fused)
    assert rep.best_loss <= rep.vote_loss
    # the next refinement decodes only the keyframes stored since; an evicted one leaves the process's views
    again = worker.refine(vote, stored[1:] + [_stored("b", 20, 0.2)], 10, 0, OPTIONS, PERF, lambda: False)
    assert again.keyframes_used == 6 and again.decoded == 1 and worker.starts == 1
    assert worker.refine(vote, stored[1:2] + [stored[0]], 5, 0, OPTIONS, PERF, lambda: False).decoded == 1
    assert keyframe_key(stored[0]) != keyframe_key(_stored("a", 0, 0.5))  # another pose: another view


def test_a_refusal_is_raised_and_the_process_serves_on(worker):
    vote = _plane(3, 0.0)
    with pytest.raises(ValueError, match="at least one keyframe"):
        worker.refine(vote, [], 5, 0, OPTIONS, PERF, lambda: False)
    pid = worker.pid
    assert pid is not None
    assert worker.refine(vote, [_stored("a", 1, 0.0)], 5, 0, OPTIONS, PERF, lambda: False).keyframes_used == 1
    assert worker.pid == pid


def test_a_stop_kills_a_long_refinement_at_once_and_the_next_starts_a_new_process(worker):
    vote = _plane(4, 0.0)
    stored = [_stored("a", i, 0.05 * i) for i in range(3)]
    worker.refine(vote, stored, 5, 0, OPTIONS, PERF, lambda: False)  # the process is up and holds the views
    pid, starts = worker.pid, worker.starts
    endless = {**OPTIONS, "patience": 10 ** 6}
    stop, set_at = threading.Event(), []
    threading.Timer(1.0, lambda: (set_at.append(time.monotonic()), stop.set())).start()
    with pytest.raises(InterruptedError):
        worker.refine(vote, stored, 10 ** 6, 0, endless, PERF, stop.is_set)
    # seen at the next look (every POLL_S), not after the refinement's hours (a loose bound: a shared machine)
    assert time.monotonic() - set_at[0] < 10 * POLL_S + 2.0 and worker.pid is None
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    # killed from another thread (the server's stop) while it refines: the caller sees the stop too
    stop.clear()
    threading.Timer(1.0, lambda: (stop.set(), worker.kill())).start()
    with pytest.raises(InterruptedError):
        worker.refine(vote, stored, 10 ** 6, 0, endless, PERF, stop.is_set)
    assert worker.starts == starts + 1 and worker.pid is None
    got = worker.refine(vote, stored, 5, 0, OPTIONS, PERF, lambda: False)
    assert worker.starts == starts + 2 and got.decoded == 3  # a new process decodes every view again
