"""The pusher on its own (gausslite.mission.pusher): superseded offers, retries with backoff while the link is down,
the keyframe bound, the final push's outcome, and what a status shows at an acknowledgement. Fake fusion clients stand in
for the server."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np

from gausslite.mission import AgentConfig
from gausslite.mission.pusher import Pusher, Snapshot
from gausslite.mission.share import Captured, ShareSession
from tests._fuzz import random_arrays
from tests._waits import wait_until


class _DownLink:
    """A fusion client whose link is down: every call raises ConnectionError."""

    def __init__(self):
        self.calls = 0

    def open_session(self, *a, **k):
        self.calls += 1
        raise ConnectionError("link down")


def _pusher(fusion, agent=None, **push):
    # the pusher at the test's own priority: these tests time its logic, not how a niced thread fares on a busy
    # machine (push.nice 19 starves it while other jobs run)
    # whole keyframes: these tests are about the backlog (ROI crops: tests/services/test_agent_live.py)
    config = AgentConfig(push={"nice": 0, **push}, refine_views={"crop": False, "budget_ratio": None}, **(agent or {}))
    errors = []
    p = Pusher("p1", "find the object", config, fusion, ShareSession("p1", config), mapper=None,
               intrinsics=lambda: None, report=errors.append)
    return p, errors


def test_retries_with_backoff_while_the_link_is_down_and_a_newer_offer_replaces_the_retried_one():
    link = _DownLink()
    p, errors = _pusher(link, backoff_s=0.05, max_backoff_s=0.2)
    p.start()
    try:
        v1 = p.offer(Captured(None, np.zeros(0, np.int64), 10), frames_mapped=5, final=False)
        assert wait_until(lambda: p.status()["push_failures"] >= 3, 10.0, poll_s=0.01)
        st = p.status()
        assert st["link_down_s"] > 0 and st["push_backlog"] == 1 and st["newest_map_version"] == v1 == 1
        assert st["pushes"] == 0 and st["last_pushed_version"] == 0
        assert errors and errors[-1].startswith("push v1 attempt") and "ConnectionError" in errors[-1]
        # the backoff doubles up to max_backoff_s: attempts slow down instead of spinning
        n, t0 = link.calls, time.monotonic()
        time.sleep(0.5)
        assert link.calls - n <= int(0.5 / 0.2) + 2, (link.calls - n, time.monotonic() - t0)
        v2 = p.offer(Captured(None, np.zeros(0, np.int64), 10), frames_mapped=9, final=False)
        assert v2 == 2
        assert wait_until(lambda: any(e.startswith("push v2") for e in errors), 10.0, poll_s=0.01)  # the newer one is tried, v1 dropped
        assert p.status()["push_backlog"] <= 2
    finally:
        p.close()
    assert not p.thread.is_alive()


def test_the_final_push_gives_up_after_its_budget_and_reports_it():
    p, _ = _pusher(_DownLink(), backoff_s=0.05, max_backoff_s=0.1, final_timeout_s=0.3)
    p.start()
    try:
        t0 = time.monotonic()
        p.offer(Captured(None, np.zeros(0, np.int64), 10), frames_mapped=5, final=True)
        assert p.final_done.wait(5.0)
        assert not p.final_push_ok and time.monotonic() - t0 < 2.0
    finally:
        p.close()


def test_without_a_fusion_client_offers_are_dropped_and_the_final_one_ends_unacknowledged():
    p, errors = _pusher(None)
    p.start()
    try:
        p.offer(Captured(None, np.zeros(0, np.int64), 1), frames_mapped=1, final=False)
        p.offer(Captured(None, np.zeros(0, np.int64), 1), frames_mapped=2, final=True)
        assert p.final_done.wait(5.0) and not p.final_push_ok
        assert p.status()["pushes"] == 0 and errors == []
    finally:
        p.close()


def test_only_the_newest_upload_backlog_max_views_wait_for_upload_and_a_resumed_mission_continues_above_its_version():
    p, _ = _pusher(None, agent={"upload_backlog_max": 3})  # never started: nothing is sent
    frames = [object() for _ in range(5)]
    for i, f in enumerate(frames):
        p.add_keyframe(f, np.full((2, 2), i % 2 == 0))
    assert p.status()["keyframes_backlog"] == 3
    assert [w.frame for w in p._kf_pending] == frames[2:] and all(w.roi is not None for w in p._kf_pending)
    p.resume(41)
    p.resume(7)  # never goes back
    assert p.version == 41
    assert p.offer(Captured(None, np.zeros(0, np.int64), 1), frames_mapped=1, final=False) == 42
    p.close()


def test_a_periodic_snapshot_without_a_fusion_client_leaves_the_final_open_and_close_is_idempotent():
    p, _ = _pusher(None)
    p.push_snapshot(Snapshot(1, None, 0, final=False))
    assert not p.final_done.is_set()  # only the final snapshot (or the mission) ends it
    p.close()  # never started
    p.start()
    p.close()
    p.close()
    assert not p.thread.is_alive()


def test_uploaded_keyframes_carry_their_refined_pose_and_leave_the_backlog():
    """The fusion refinement sees each keyframe at the pose mapping refined (full-image and ROI-phase alignment),
    not the sensor's; a keyframe without a correction goes as it is."""
    from gausslite.datasets.base import Frame
    from gausslite.camera import Intrinsics

    E = np.eye(4)
    E[0, 3] = 0.02
    sent = []
    fusion = SimpleNamespace(upload_keyframes=lambda agent_id, frames, **kw: sent.extend(frames) or len(frames))
    config = AgentConfig(refine_views={"crop": False, "budget_ratio": None})
    mapper = SimpleNamespace(poses=SimpleNamespace(corrections={3: E}))
    p = Pusher("p1", "find the object", config, fusion, ShareSession("p1", config), mapper=mapper,
               intrinsics=lambda: None, report=lambda m: None)
    intr = Intrinsics(50.0, 50.0, 3.5, 2.5, 8, 6)
    frames = [Frame(i, 0.0, np.zeros((6, 8, 3), np.uint8), np.ones((6, 8), np.float32), np.eye(4), intr)
              for i in (3, 4)]
    for f in frames:
        p.add_keyframe(f, None)
    kfs, n = p._upload_pending_keyframes(fusion)
    assert n == 2 and p.status()["keyframes_backlog"] == 0 and kfs == frames
    np.testing.assert_allclose(sent[0].c2w, E)  # frame 3 at its refined pose
    np.testing.assert_array_equal(sent[1].c2w, np.eye(4))  # frame 4 has no correction
    np.testing.assert_array_equal(frames[0].c2w, np.eye(4))  # the mission's own frame is unchanged
    p.close()


class _FlakyLink:
    """A fusion client whose link is down for its first ``down`` sessions, then acknowledges every upload."""

    def __init__(self, down: int):
        self.down = down

    def open_session(self, *a, **k):
        if self.down > 0:
            self.down -= 1
            raise ConnectionError("link down")
        return SimpleNamespace(latest_map_version=0)

    def upload_chunks(self, agent_id, version, chunks, **kw):
        return SimpleNamespace(complete=True, bytes_sent=sum(len(c) for c in chunks), n_chunks=len(chunks))


def test_an_acknowledgement_clears_the_backlog_and_the_outage_in_the_same_status():
    """A status that shows a version acknowledged shows no snapshot in flight and the link up: a GetStatus between
    the two never says "v1 acknowledged, backlog 1, link down"."""
    seen = []
    p, _ = _pusher(_FlakyLink(down=2), backoff_s=0.01, max_backoff_s=0.02)
    p._report = lambda m: seen.append(p.status()) if m == "" else None  # what a reader sees at the acknowledgement
    p.start()
    try:
        p.offer(Captured(random_arrays(20, 0), np.arange(20), 40), frames_mapped=5, final=False)
        assert wait_until(lambda: p.status()["last_pushed_version"] == 1, 10.0, poll_s=0.01)
        assert p.status()["push_failures"] == 2
        assert seen and seen[0]["last_pushed_version"] == 1
        assert seen[0]["push_backlog"] == 0 and seen[0]["link_down_s"] == 0.0
    finally:
        p.close()
