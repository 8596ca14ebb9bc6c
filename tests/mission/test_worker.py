"""The mapping worker on its own (gausslite.mission.worker), with stand-ins for the mapper, the pusher, the share
session and the checkpoint: each keyframe is mapped at the mapping resolution with its relevance, counted, uploaded
every ``upload_keyframe_every``, offered to the pusher every ``push.every`` and checkpointed every
``checkpoint_every``; corrupt images are rejected, a failed step costs its frame alone (out of memory and a full disk
fail the mission); the thread optimises between keyframes under live ingest, applies a new task, and ends a Finish with the final pass and push (or without a push)."""

from __future__ import annotations

import threading
import types

import numpy as np
import pytest

from gausslite.config import load_config
from gausslite.mission import task as task_mod
from gausslite.mission import worker as worker_mod
from gausslite.mission.ingest import Ingest
from gausslite.mission.progress import MissionProgress
from gausslite.mission.state import MissionState
from gausslite.mission.task import MissionTask
from gausslite.mission.tracking import MissionPoses
from gausslite.mission.uploads import KeyframeUploads
from gausslite.mission.worker import DRAIN, FINISH, MappingWorker
from tests._scenes import plane_frame, plane_roi
from tests._waits import WORK_S, wait_until

GRAPH = {"targets": ["object"], "anchors": [], "relations": []}


class _Mapper:
    """Records what it is asked to map; each keyframe gets 5 iterations and adds 10 Gaussians, 4 of them active."""

    def __init__(self):
        self.mapped, self.finalized, self.optimized, self.retargets = [], 0, 0, 0
        self.model = types.SimpleNamespace(active=np.zeros(0, bool))
        self.keyframes = []
        self.fail_on, self.error = None, ValueError("frame 4: the corrected pose is not a rigid transform")

    def map_frame(self, frame, relevance=None, time_budget_s=None, between=(), **kw):
        if frame.frame_id == self.fail_on:
            raise self.error
        self.mapped.append((frame.frame_id, frame.intrinsics.width, relevance, [f.frame_id for f in between], kw))
        n = 10 * len(self.mapped)
        self.model.active = np.arange(n) % 10 < 4
        return types.SimpleNamespace(iters=5, active_iters=2, n_gaussians=n, detail_px=0, seconds=0.01)

    def optimize(self, max_seconds=None):
        self.optimized += 1
        return 3

    def finalize(self, max_seconds=None):
        self.finalized += 1
        return 7

    def retarget(self):
        self.retargets += 1


class _Pusher:
    """Records offers and keyframes; ends a final offer as a real pusher does (``final_done``)."""

    def __init__(self):
        self.offers, self.keyframes, self.tasks = [], [], []
        self.final_done, self.trim_due = threading.Event(), threading.Event()

    def offer(self, cap, frames_mapped, final):
        self.offers.append((cap, frames_mapped, final))
        if final:
            self.final_done.set()

    def add_keyframe(self, frame, roi):
        self.keyframes.append((frame.frame_id, roi))
        return True

    def set_task(self, text):
        self.tasks.append(text)


class _Checkpoint:
    def __init__(self):
        self.saved, self.versions = [], 0

    def save(self):
        self.saved.append(len(self.saved) + 1)

    def record_version(self):
        self.versions += 1


def _worker(*overrides, relevance=None):
    cfg = load_config(None, ["agent.ingest=every_frame", "agent.resolution.downscale=2", "mapper.mode=uniform",
                             "agent.resolution.min_width=16", "agent.refine_views.between=false",
                             *overrides]).agent
    progress = MissionProgress()
    poses = MissionPoses(cfg, progress)
    ingest = Ingest("w", "m1", cfg, progress, poses, None)
    mapper, pusher, checkpoint, failures = _Mapper(), _Pusher(), _Checkpoint(), []
    roi = relevance or (lambda fr: np.ones(fr.depth.shape, bool))
    task = MissionTask("w", "m1", cfg, "Pick up the object", GRAPH, None, None, roi, lambda: mapper, progress)
    resolution = cfg.resolution.governor(cfg.mapper)
    uploads = KeyframeUploads(cfg, resolution, lambda: ingest.intrinsics)
    share = types.SimpleNamespace(capture=lambda m: ("snapshot", len(m.mapped)))

    def fail(msg):
        failures.append(msg)
        progress.fail(msg)
        pusher.final_done.set()

    w = MappingWorker("w", "m1", cfg, progress=progress, ingest=ingest, poses=poses, task=task, mapper=mapper,
                      resolution=resolution, maps_detail=False, uploads=uploads, pusher=pusher, share=share,
                      checkpoint=checkpoint, fail=fail)
    return types.SimpleNamespace(worker=w, progress=progress, ingest=ingest, mapper=mapper, pusher=pusher,
                                 checkpoint=checkpoint, failures=failures, task=task, uploads=uploads)


def test_each_keyframe_is_mapped_counted_uploaded_pushed_and_checkpointed_on_its_schedule():
    m = _worker("agent.upload_keyframe_every=2", "agent.push.every=3", "agent.checkpoint_every=2",
                "agent.eval_max_frames=4")
    for i in range(6):
        m.worker.map_keyframe(plane_frame(i, 0.1 * i), t_arrival=0.0)
    # mapped at the mapping resolution (downscale 2 of 56x40), with the task's relevance at that size
    assert [(fid, width) for fid, width, *_ in m.mapper.mapped] == [(i, 28) for i in range(6)]
    assert all(w.shape == (20, 28) and w.all() for _, _, w, _, _ in m.mapper.mapped)
    p = m.progress
    assert (p.frames_mapped, p.frames_keyframed, p.keyframe_iterations) == (6, 6, 30)
    assert (p.n_gaussians, p.n_active) == (60, 24) and len(p.keyframe_latency_s) == 6 and p.seconds_mapping > 0
    assert [fid for fid, _ in m.pusher.keyframes] == [0, 2, 4]  # every upload_keyframe_every-th mapped frame
    assert m.uploads.factor == 2.0 and m.pusher.keyframes[0][1].shape == (20, 28)
    assert [(n, final) for _, n, final in m.pusher.offers] == [(3, False), (6, False)]
    assert m.pusher.offers[0][0] == ("snapshot", 3) and m.checkpoint.versions == 2
    assert m.checkpoint.saved == [1, 2, 3]  # after keyframes 2, 4 and 6
    assert [f.frame_id for f in m.worker.eval_frames] == [0, 1, 2, 3]
    assert m.failures == []


def test_a_frame_whose_images_do_not_decode_is_rejected_and_a_mapping_error_costs_that_frame_alone():
    m = _worker()

    class Corrupt:
        frame_id = 3

        def materialize(self):
            raise ValueError("truncated PNG")

    m.worker.map_keyframe(Corrupt(), 0.0)
    p = m.progress
    assert p.frames_rejected == 1 and p.last_error == "rejected frame: truncated PNG" and m.mapper.mapped == []
    assert p.state == MissionState.MAPPING
    m.mapper.fail_on = 4
    m.worker.map_keyframe(plane_frame(4), 0.0)
    # one frame's error: logged, counted, and the mission maps on
    assert m.failures == [] and p.state == MissionState.MAPPING and p.frames_failed == 1 and p.frames_mapped == 0
    assert p.last_error == "mapping frame 4 failed: ValueError: frame 4: the corrected pose is not a rigid transform"
    m.worker.map_keyframe(plane_frame(5), 0.0)
    assert p.frames_mapped == 1 and [fid for fid, *_ in m.mapper.mapped] == [5]


@pytest.mark.parametrize("error", [MemoryError("cannot allocate"), OSError(28, "No space left on device")])
def test_out_of_memory_or_a_full_disk_fails_the_mission(error):
    m = _worker()
    m.mapper.fail_on, m.mapper.error = 4, error
    m.worker.map_keyframe(plane_frame(4), 0.0)
    assert len(m.failures) == 1 and m.failures[0].startswith(f"mapping frame 4 failed: {type(error).__name__}")
    assert m.progress.state == MissionState.FAILED and m.progress.frames_failed == 0


def test_an_upload_or_a_snapshot_that_fails_costs_that_step_alone():
    m = _worker("agent.upload_keyframe_every=1", "agent.push.every=1")

    def broken(*a):
        raise RuntimeError("encoder crashed")

    m.pusher.add_keyframe = broken
    m.worker.share = types.SimpleNamespace(capture=broken)
    for i in range(2):
        m.worker.map_keyframe(plane_frame(i), 0.0)
    p = m.progress
    assert p.frames_mapped == 2 and m.failures == [] and p.state == MissionState.MAPPING
    assert p.frames_failed == 4  # per frame: its upload and its snapshot
    assert p.last_error == "taking the snapshot after frame 2 failed: RuntimeError: encoder crashed"
    assert p.counter_status()["frames_failed"] == 4


def test_a_checkpoint_that_cannot_be_written_does_not_stop_mapping():
    m = _worker("agent.checkpoint_every=1")

    def full_disk():
        raise OSError("No space left on device")

    m.checkpoint.save = full_disk
    for i in range(2):
        m.worker.map_keyframe(plane_frame(i), 0.0)
    assert m.progress.frames_mapped == 2 and m.failures == []


def test_the_frames_between_keyframes_reach_the_mapper_and_the_uploads():
    m = _worker("agent.ingest=keyframes", "agent.refine_views.crop=true", "agent.refine_views.between=true",
                "agent.refine_views.between_every=1", relevance=lambda fr: plane_roi()[::2, ::2])
    for i in range(3):
        m.ingest.accept(plane_frame(i, 0.5 * i), 0.0, streamed=True)
    m.worker.map_keyframe(*m.ingest.take_keyframe())
    assert m.mapper.mapped[0][0] == 2 and m.mapper.mapped[0][3] == [0, 1]  # the replaced candidates, oldest first
    # the keyframe, then the views of the frames between, their region carried over from the keyframe's
    assert [fid for fid, _ in m.pusher.keyframes] == [2, 0, 1]
    assert all(roi.shape == (20, 28) for _, roi in m.pusher.keyframes) and m.pusher.keyframes[2][1].any()


def test_the_thread_maps_the_queue_then_ends_finish_with_the_final_pass_and_push():
    m = _worker("agent.push.every=100")
    m.worker.start()
    try:
        q = m.ingest.queue
        for i in range(3):
            q.put((plane_frame(i, 0.1 * i), 0.0))
        q.put(FINISH)
        assert m.pusher.final_done.wait(WORK_S), f"no final push (waited {WORK_S:.0f} s)"
        assert m.ingest.wait_mapped(WORK_S)
        assert [fid for fid, *_ in m.mapper.mapped] == [0, 1, 2] and m.mapper.finalized == 1
        assert [(n, final) for _, n, final in m.pusher.offers] == [(3, True)] and m.checkpoint.versions == 1
    finally:
        m.worker.stop(10.0)
    assert not m.worker.thread.is_alive()


def test_finish_without_a_push_and_finish_of_a_failed_mission_only_end_the_finish():
    m = _worker()
    m.worker.start()
    try:
        m.ingest.queue.put(DRAIN)
        assert m.pusher.final_done.wait(WORK_S)
        m.pusher.final_done.clear()
        m.progress.fail("earlier failure")
        m.ingest.queue.put((plane_frame(0), 0.0))  # a failed mission maps nothing more
        m.ingest.queue.put(FINISH)
        assert m.pusher.final_done.wait(WORK_S)
        assert m.ingest.wait_mapped(WORK_S)
        assert m.mapper.mapped == [] and m.mapper.finalized == 0 and m.pusher.offers == []
    finally:
        m.worker.stop(10.0)


def test_live_ingest_optimises_between_keyframes_and_a_new_task_is_applied_by_the_thread(monkeypatch):
    none = lambda fr: np.zeros(fr.depth.shape, bool)  # noqa: E731
    monkeypatch.setattr(task_mod, "build_relevance", lambda *a, **k: (none, None))
    m = _worker("agent.ingest=keyframes", "agent.idle_optimize=true", "agent.idle_chunk_s=0.01")
    m.worker.start()
    try:
        assert m.ingest.accept(plane_frame(0), 0.0, streamed=True)
        assert wait_until(lambda: m.progress.idle_iterations > 0, 60), "no idle optimisation (waited 60 s)"
        assert m.progress.frames_mapped == 1 and m.progress.idle_iterations % 3 == 0
        m.task.request("Open the box", GRAPH)
        assert wait_until(lambda: m.task.text == "Open the box", 60), "the new task was not applied (waited 60 s)"
        assert m.mapper.retargets == 1 and m.pusher.tasks == ["Open the box"] and m.task.relevance_fn is none
        m.progress.begin_finish()  # Finish began: no more optimisation between keyframes
        n = m.mapper.optimized
        m.ingest.queue.put(DRAIN)
        assert m.pusher.final_done.wait(WORK_S) and m.ingest.wait_mapped(WORK_S)
        assert m.mapper.optimized - n <= 1  # at most the chunk in progress when Finish began
    finally:
        m.worker.stop(10.0)


def test_a_pushs_memory_goes_back_to_the_os_on_the_mapping_thread(monkeypatch):
    trims = []
    monkeypatch.setattr(worker_mod, "trim_heap", lambda: trims.append(threading.current_thread().name) or True)
    m = _worker()
    m.worker.start()
    try:
        m.pusher.trim_due.set()
        assert wait_until(lambda: trims, 60), "no trim (waited 60 s)"
        assert not m.pusher.trim_due.is_set()
    finally:
        m.worker.stop(10.0)
    assert trims == ["agent-w-map"]


@pytest.mark.parametrize("online", [False, True])
def test_stop_ends_the_thread(online):
    m = _worker("agent.ingest=" + ("keyframes" if online else "every_frame"))
    m.worker.start()
    m.worker.stop(10.0)
    assert not m.worker.thread.is_alive()
