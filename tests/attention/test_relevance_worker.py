"""Relevance in its own thread with a bounded wait (gausslite.attention.worker)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from gausslite.attention.worker import RelevanceWorker, reproject_mask
from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame

K = np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])


def _frame(i: int, x: float = 0.0) -> Frame:
    c2w = np.eye(4)
    c2w[0, 3] = x
    return Frame(i, float(i), np.zeros((24, 32, 3), np.uint8), np.full((24, 32), 2.0, np.float32), c2w,
                 Intrinsics.from_K(K, 32, 24))


def _box(x0, y0, x1, y1):
    m = np.zeros((24, 32), bool)
    m[y0:y1, x0:x1] = True
    return m


def test_reproject_mask_is_the_identity_in_place_and_shifts_with_the_camera():
    m = _box(10, 8, 20, 16)
    same = reproject_mask(m, np.full((24, 32), 2.0), np.eye(4), K, np.eye(4), K, 32, 24, dilate_px=0)
    assert np.array_equal(same, m)
    # the camera moves 0.1 m to the right: a plane 2 m away shifts 40 * 0.1 / 2 = 2 px to the left
    c2w = np.eye(4)
    c2w[0, 3] = 0.1
    moved = reproject_mask(m, np.full((24, 32), 2.0), np.eye(4), K, c2w, K, 32, 24, dilate_px=0)
    assert np.array_equal(moved, _box(8, 8, 18, 16))
    # no valid depth, nothing to carry; a dilation grows the mask
    assert not reproject_mask(m, np.zeros((24, 32)), np.eye(4), K, np.eye(4), K, 32, 24).any()
    assert reproject_mask(m, np.full((24, 32), 2.0), np.eye(4), K, np.eye(4), K, 32, 24, dilate_px=1).sum() > m.sum()
    with pytest.raises(ValueError):
        reproject_mask(m, np.zeros((2, 2)), np.eye(4), K, np.eye(4), K, 32, 24)


def test_worker_answers_with_the_frames_own_mask_when_it_is_in_time():
    w = RelevanceWorker(lambda fr: _box(fr.frame_id, 0, fr.frame_id + 4, 4), max_wait_s=10.0)
    try:
        for i in range(3):
            assert np.array_equal(w.relevance(_frame(i)), _box(i, 0, i + 4, 4))
        assert w.computed == 3 and w.reprojected == 0 and w.waited_out == 0
    finally:
        w.close()


def test_a_slow_detector_costs_the_keyframe_at_most_the_bound_and_the_newest_mask_is_reprojected():
    gate = threading.Event()

    def slow(fr):
        if fr.frame_id > 0:
            gate.wait(10)
        return _box(10, 8, 20, 16)

    w = RelevanceWorker(slow, max_wait_s=0.05)
    try:
        assert w.relevance(_frame(0)) is not None  # the first frame is fast
        out = w.relevance(_frame(1, x=0.1))  # its own mask is blocked: the newest (frame 0) is carried over
        assert w.waited_out == 1 and w.reprojected == 1
        assert out[10, 9] and not out[10, 20]  # shifted left with the camera (and dilated)
        gate.set()
        for _ in range(200):  # frame 1's own mask arrives later and becomes the newest
            if w.computed == 2:
                break
            threading.Event().wait(0.01)
        assert w.computed == 2
    finally:
        gate.set()
        w.close()
    with pytest.raises(ValueError):
        RelevanceWorker(lambda fr: None, -1.0)


def test_no_mask_yet_is_none():
    gate = threading.Event()
    w = RelevanceWorker(lambda fr: gate.wait(10) and None, max_wait_s=0.0)
    try:
        assert w.relevance(_frame(0)) is None and w.waited_out == 1
    finally:
        gate.set()
        w.close()
