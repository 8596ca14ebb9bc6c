"""A mission's task and its swaps on their own (gausslite.mission.task): the task id found by text or checked, the
relevance source built for a new task at once (so a task the scene cannot answer fails with nothing changed), and
applied later between keyframes: the mapper re-targets, its stored keyframes get the new task's ROI, the pusher
opens its next session under the new task."""

from __future__ import annotations

import types

import numpy as np
import pytest
import torch

from gausslite.attention.worker import RelevanceWorker
from gausslite.config import load_config
from gausslite.mission.progress import MissionProgress
from gausslite.mission.task import MissionTask, task_id_of
from tests._scenes import plane_frame

GRAPH = {"targets": ["object"], "anchors": [], "relations": []}


class _Annotations:
    """Two annotated tasks; the ROI of ``mug`` is the left half of the image, of ``box`` the right half."""

    tasks = [types.SimpleNamespace(id="mug", text="Pick up the mug"), types.SimpleNamespace(id="box", text="Open the box")]

    def task_by_id(self, task_id):
        for t in self.tasks:
            if t.id == task_id:
                return t
        raise KeyError(f"unknown task {task_id!r}; known: {[t.id for t in self.tasks]}")

    def roi_mask(self, task_id, depth, c2w, intrinsics):
        m = np.zeros(depth.shape, bool)
        half = depth.shape[1] // 2
        m[:, :half] = task_id == "mug"
        m[:, half:] = task_id == "box"
        return m


class _Store:
    """Stored keyframes (the mapper's ``keyframes``): images as tensors, and the ROI each was given."""

    def __init__(self, frames):
        self.items = [types.SimpleNamespace(frame_id=f.frame_id, rgb=torch.from_numpy(f.rgb),
                                            depth=torch.from_numpy(f.depth), c2w=torch.from_numpy(f.c2w),
                                            K=torch.from_numpy(f.intrinsics.K), width=f.intrinsics.width,
                                            height=f.intrinsics.height) for f in frames]
        self.rois = {}

    def __len__(self):
        return len(self.items)

    def __getitem__(self, i):
        return self.items[i]

    def set_roi(self, i, roi):
        self.rois[i] = roi


class _Mapper:
    def __init__(self, frames):
        self.keyframes, self.retargets = _Store(frames), 0

    def retarget(self):
        self.retargets += 1


class _Pusher:
    def __init__(self):
        self.tasks = []

    def set_task(self, text):
        self.tasks.append(text)


def _task(*overrides, text="Pick up the mug", task_id=None, relevance_fn=None):
    cfg = load_config(None, ["agent.relevance=gt", *overrides]).agent
    progress = MissionProgress()
    return MissionTask("a", "m1", cfg, text, GRAPH, task_id, _Annotations(), relevance_fn, lambda: None,
                       progress), progress


def test_the_task_id_is_checked_or_found_by_its_text():
    ann = _Annotations()
    assert task_id_of(ann, None, "  pick UP the mug ") == "mug"
    assert task_id_of(ann, None, "fly to the moon") is None
    assert task_id_of(ann, "box", "whatever the text") == "box"
    assert task_id_of(None, "anything", "t") == "anything"
    with pytest.raises(KeyError, match="known"):
        task_id_of(ann, "cup", "t")


def test_the_relevance_of_the_current_task_and_its_thread_only_after_start():
    task, _ = _task()
    fr = plane_frame(0)
    assert task.task_id == "mug" and task.frontend is None
    w = task.relevance(fr)
    assert w.shape == fr.depth.shape and w[:, 0].all() and not w[:, -1].any()
    task.start()
    assert task._worker is None  # relevance_max_wait_s unset: computed in the caller's thread
    threaded, _ = _task("agent.relevance_max_wait_s=5")
    assert threaded._worker is None  # nothing runs before start
    threaded.start()
    try:
        assert isinstance(threaded._worker, RelevanceWorker)
        np.testing.assert_array_equal(threaded.relevance(fr), w)
    finally:
        threaded.close()
    used, _ = _task("agent.relevance_max_wait_s=5")
    try:
        np.testing.assert_array_equal(used.relevance(fr), w)  # a caller that never starts it: started on first use
        assert isinstance(used._worker, RelevanceWorker)
    finally:
        used.close()


def test_a_new_task_is_built_at_once_and_applied_between_keyframes():
    task, progress = _task()
    progress.n_active = 12
    frames = [plane_frame(i, 0.1 * i) for i in range(3)]
    mapper, pusher = _Mapper(frames), _Pusher()
    assert task.apply_pending(mapper, pusher) is False  # nothing pending
    task.request("Open the box", {"targets": ["box"], "anchors": [], "relations": []})
    assert task.text == "Pick up the mug" and mapper.retargets == 0  # not applied yet
    assert task.apply_pending(mapper, pusher) is True
    assert (task.text, task.task_id, task.graph["targets"]) == ("Open the box", "box", ["box"])
    assert mapper.retargets == 1 and pusher.tasks == ["Open the box"] and progress.n_active == 0
    # every stored keyframe has the new task's ROI (the right half)
    assert set(mapper.keyframes.rois) == {0, 1, 2}
    assert all(r[:, -1].all() and not r[:, 0].any() for r in mapper.keyframes.rois.values())
    assert task.apply_pending(mapper, pusher) is False  # applied once


def test_a_task_the_scene_cannot_answer_fails_at_request_with_nothing_changed():
    task, _ = _task()
    with pytest.raises(KeyError, match="known"):
        task.request("Open the box", GRAPH, task_id="cupboard")
    with pytest.raises(ValueError, match="needs scene annotations and a task id"):
        task.request("Fly to the moon", GRAPH)  # gt relevance: no annotated task of that text
    assert task.apply_pending(_Mapper([]), _Pusher()) is False and task.text == "Pick up the mug"


def test_a_given_relevance_function_is_used_as_is():
    ones = lambda fr: np.ones(fr.depth.shape, bool)  # noqa: E731
    task, _ = _task(relevance_fn=ones)
    assert task.relevance_fn is ones and task.relevance(plane_frame(0)).all()
