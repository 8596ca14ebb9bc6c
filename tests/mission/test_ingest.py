"""Frames into a mission, part by part: the shared progress (gausslite.mission.progress), the pose source
(gausslite.mission.tracking) and the ingest (gausslite.mission.ingest): keyframe selection with its one pending slot,
the every-frame queue and its back-pressure, the image size check, the frames kept between keyframes, and the
states in which a mission refuses frames."""

from __future__ import annotations

import queue
import types

import numpy as np
import pytest

from gausslite.config import load_config
from gausslite.mission.errors import FrameSizeMismatch, MissionError
from gausslite.mission.ingest import SLOT, Ingest, between_use
from gausslite.mission.progress import CHECKPOINT_COUNTERS, MissionProgress, percentile
from gausslite.mission.state import MissionState
from gausslite.mission.tracking import MissionPoses
from tests._scenes import plane_frame


def _ingest(*overrides, T_world_map=None):
    cfg = load_config(None, list(overrides)).agent
    progress = MissionProgress()
    poses = MissionPoses(cfg, progress)
    return Ingest("a", "m1", cfg, progress, poses, T_world_map), progress


def _moved(i: int):
    """Frame ``i`` of a camera moving 0.5 m per frame: every frame is a keyframe candidate."""
    return plane_frame(i, 0.5 * i)


# ---------------------------------------------------------------------------------------------- progress
def test_progress_refuses_frames_by_state_and_keeps_a_replays_frames_while_finishing():
    p = MissionProgress()
    p.check_accepts("m1", streamed=True)  # mapping: both kinds taken
    assert p.begin_finish() is True and p.state == MissionState.FINISHING and p.closed_for_input
    assert p.begin_finish() is False  # the second close is not the first
    with pytest.raises(MissionError, match="mission m1 is finishing"):
        p.check_accepts("m1", streamed=True)
    p.check_accepts("m1", streamed=False)  # a replay still running completes
    p.fail("mapping frame 3 failed")
    p.end_finish()
    assert p.state == MissionState.FAILED  # a failed mission stays failed
    with pytest.raises(MissionError, match=r"mission m1 is failed: .*\(mapping frame 3 failed\)"):
        p.check_accepts("m1", streamed=False)
    q = MissionProgress()
    q.end_finish()
    assert q.state == MissionState.FINISHED
    q = MissionProgress()
    q.stop.set()
    with pytest.raises(MissionError):
        q.check_accepts("m1", streamed=False)


def test_progress_restores_the_checkpoints_counters_and_reports_latency_percentiles():
    p = MissionProgress()
    p.restore({"frames_mapped": 7, "frames_keyframed": 7, "seconds_mapping": 2.5, "not_a_counter": 1})
    assert (p.frames_mapped, p.frames_keyframed, p.seconds_mapping) == (7, 7, 2.5)
    assert not hasattr(p, "not_a_counter") and "frames_rejected" not in CHECKPOINT_COUNTERS
    p.accept_ms.extend([1.0] * 99 + [101.0])
    p.keyframe_latency_s.extend([0.5, 1.5])
    st = p.counter_status()
    assert st["accept_latency_ms_p99"] == pytest.approx(percentile([1.0] * 99 + [101.0], 99))
    assert st["keyframe_latency_s_p95"] == pytest.approx(1.45) and st["frames_keyframed"] == 7
    assert percentile([], 50) == 0.0


# ---------------------------------------------------------------------------------------------- keyframe ingest
def test_keyframe_ingest_keeps_one_pending_candidate_and_counts_the_replaced_as_skipped():
    ing, p = _ingest("agent.ingest=keyframes", "agent.refine_views.crop=true", "agent.refine_views.between=true")
    assert ing.online
    for i in range(3):
        assert ing.accept(_moved(i), arrival=0.0, streamed=True) is True
    # one SLOT for the first candidate; the later ones replaced it in the selector, not in the queue
    assert ing.queue.qsize() == 1 and ing.queue.get_nowait() is SLOT
    assert (p.frames_received, p.frames_skipped) == (3, 2) and len(p.accept_ms) == 3
    frame, arrival = ing.take_keyframe()
    assert frame.frame_id == 2 and arrival == 0.0
    assert ing.take_keyframe() is None
    # the replaced candidates are the frames between keyframes, oldest first, decoded for their ROI crops
    assert [f.frame_id for f in ing.take_between(2)] == [0, 1]
    assert ing.take_between(5) == []


def test_a_frame_that_is_no_candidate_is_skipped_and_kept_as_a_frame_between():
    ing, p = _ingest("agent.ingest=keyframes", "agent.refine_views.crop=true", "agent.refine_views.between=true")
    assert ing.accept(plane_frame(0), 0.0, streamed=True) is True
    assert ing.take_keyframe()[0].frame_id == 0  # the mapper took it: the selector's reference
    assert ing.accept(plane_frame(1), 0.0, streamed=True) is False  # the camera did not move
    assert (p.frames_received, p.frames_skipped) == (2, 1) and ing.queue.qsize() == 1
    assert ing.take_between(0) == []  # frame 1 came after keyframe 0: kept for the next keyframe
    assert [f.frame_id for f in ing.take_between(9)] == [1]


def test_how_the_frames_between_keyframes_are_used():
    def use(*overrides):
        return between_use(load_config(None, list(overrides)).agent)

    off = ("agent.refine_views.between=false", "mapper.roi_views.enabled=false", "mapper.sensor.motion_every_frame=false")
    assert use(*off) == (False, False, False)
    assert use(*off[:2], "mapper.sensor.motion_every_frame=true") == (False, False, True)  # their motion alone
    assert use("agent.refine_views.crop=true", "agent.refine_views.between=true", *off[1:]) == (True, True, True)
    ing, p = _ingest("agent.ingest=keyframes", *off)
    for i in range(3):
        ing.accept(_moved(i), 0.0, streamed=True)
    assert ing.take_between(9) == [] and p.frames_skipped == 2  # not kept when nothing uses them


def test_frames_between_that_do_not_decode_are_left_out():
    ing, _ = _ingest("agent.ingest=keyframes", "agent.refine_views.crop=true", "agent.refine_views.between=true")

    class Corrupt:
        def __init__(self, fr):
            self.frame_id, self.c2w, self.intrinsics = fr.frame_id, fr.c2w, fr.intrinsics

        def materialize(self):
            raise ValueError("truncated JPEG")

    class Pending(Corrupt):
        def __init__(self, fr):
            super().__init__(fr)
            self.fr = fr

        def materialize(self):
            return self.fr

    for i, wrap in enumerate((Corrupt, Pending, lambda fr: fr)):
        ing.accept(wrap(_moved(i)), 0.0, streamed=True)
    kept = ing.take_between(2)
    assert [f.frame_id for f in kept] == [1] and all(not hasattr(f, "materialize") for f in kept)


# ---------------------------------------------------------------------------------------------- every-frame ingest
def test_every_frame_ingest_queues_each_frame_and_blocks_when_the_queue_is_full():
    ing, p = _ingest("agent.ingest=every_frame", "agent.queue_size=2")
    assert not ing.online
    assert ing.accept(plane_frame(0), 1.0, streamed=True) and ing.accept(plane_frame(1), 2.0, streamed=True)
    with pytest.raises(queue.Full):
        ing.accept(plane_frame(2), 3.0, streamed=True, timeout=0.01)
    assert p.frames_received == 2
    fr, arrival = ing.queue.get_nowait()
    assert (fr.frame_id, arrival) == (0, 1.0)


def test_every_frame_has_the_first_frames_image_size():
    ing, _ = _ingest("agent.ingest=every_frame")
    ing.accept(plane_frame(0, H=40, W=56), 0.0, streamed=True)
    with pytest.raises(FrameSizeMismatch, match="frame 1: image size 64x48 differs from the mission's 56x40"):
        ing.accept(plane_frame(1, H=48, W=64), 0.0, streamed=True)
    assert (ing.intrinsics.width, ing.intrinsics.height) == (56, 40) and ing.queue.qsize() == 1


def test_a_finishing_mission_refuses_streamed_frames_but_takes_its_replays():
    ing, p = _ingest("agent.ingest=every_frame")
    p.begin_finish()
    with pytest.raises(MissionError, match="finishing"):
        ing.accept(plane_frame(0), 0.0, streamed=True)
    assert ing.accept(plane_frame(0), 0.0, streamed=False)


def test_wait_mapped_waits_for_the_queue_and_the_busy_condition():
    ing, p = _ingest("agent.ingest=every_frame")
    assert ing.wait_mapped(0.0)
    ing.accept(plane_frame(0), 0.0, streamed=True)
    assert not ing.wait_mapped(0.05)  # queued, not done
    ing.queue.get_nowait()
    ing.queue.task_done()
    assert not ing.wait_mapped(0.05, busy=lambda: True) and ing.wait_mapped(0.05)
    ing.accept(plane_frame(1), 0.0, streamed=True)
    p.fail("boom")
    assert ing.wait_mapped(0.0)  # a failed mission maps nothing more
    ing.drop_queued()
    assert ing.queue.unfinished_tasks == 0


# ---------------------------------------------------------------------------------------------- poses
def test_streamed_poses_enter_the_world_frame_and_a_replays_are_left_as_they_are():
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    ing, _ = _ingest(T_world_map=T)
    fr = plane_frame(0, 0.25)
    np.testing.assert_allclose(ing.posed(fr, replayed=False).c2w, T @ fr.c2w)
    assert ing.posed(fr, replayed=True) is fr
    assert not ing.poses.tracks
    assert ing.poses.status() == {"frames_lost": 0, "frames_relocalised": 0, "loop_closures": 0,
                                  "corrections_rejected": 0}


class _Odometry:
    """A stand-in odometry: loses the frames whose id is in ``lost``, puts the others 1 m further along x."""

    def __init__(self, lost=()):
        self.lost, self.last_pose, self.initial_pose, self.tracked = set(lost), None, None, []

    def track(self, frame):
        self.tracked.append(frame.frame_id)
        if frame.frame_id in self.lost:
            return types.SimpleNamespace(ok=False, reason="too few inliers")
        c2w = np.asarray(frame.c2w, np.float64).copy()
        c2w[0, 3] += 1.0
        self.last_pose = c2w
        return types.SimpleNamespace(ok=True, c2w=c2w)


class _Follower:
    def __init__(self):
        self.recorded, self.applied = [], 0

    def record(self, frame_id, result, W=None):
        self.recorded.append((frame_id, W))

    def apply(self, mapper):
        self.applied += 1


def test_the_odometry_tracks_each_frame_and_a_lost_one_is_counted_rejected():
    p = MissionProgress()
    poses = MissionPoses(load_config(None, []).agent, p)
    poses.odometry, poses.follower = _Odometry(lost={1}), _Follower()
    poses.records = True
    assert poses.tracks
    out = poses.track(plane_frame(0, 0.5))
    assert out.c2w[0, 3] == pytest.approx(1.5) and poses.odometry.initial_pose[0, 3] == pytest.approx(0.5)
    np.testing.assert_allclose(poses.estimated_poses[0], out.c2w)
    assert poses.track(plane_frame(1)) is None
    assert (p.frames_received, p.frames_rejected) == (1, 1)
    assert p.last_error == "odometry lost frame 1: too few inliers" and set(poses.estimated_poses) == {0}
    poses.follow(mapper=None)
    assert poses.follower.recorded == [(0, None)] and poses.follower.applied == 1


def test_ingest_tracks_streamed_frames_before_the_world_frame_and_skips_the_lost():
    T = np.eye(4)
    T[1, 3] = 2.0
    ing, p = _ingest("agent.ingest=every_frame", T_world_map=T)
    ing.poses.odometry, ing.poses.follower = _Odometry(lost={1}), _Follower()
    fr = ing.posed(plane_frame(0), replayed=False)
    assert fr.c2w[0, 3] == pytest.approx(1.0) and fr.c2w[1, 3] == pytest.approx(2.0)
    (fid, W), = ing.poses.follower.recorded
    assert fid == 0 and W is T  # the map follows the odometry in the map's frame
    assert ing.posed(plane_frame(1), replayed=False) is None and p.frames_rejected == 1
    # a replay's frame (world frame already) is tracked with no transform
    ing.posed(plane_frame(2), replayed=True)
    assert ing.poses.follower.recorded[-1] == (2, None)
