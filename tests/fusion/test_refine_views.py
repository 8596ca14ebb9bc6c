"""The views a robot sends for the joint refinement (gausslite.fusion.views): ROI crops that are ordinary pinhole
views, the task region carried to another frame by depth, and the byte budget (farthest views first, never above
ratio × the subset's bytes, counted on the real wire messages)."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.fusion.views import ViewBudget, next_view, region_points, roi_crop, view_bytes
from gausslite.mapping.roi_views import project_roi
from gausslite.mission import AgentConfig
from gausslite.mission import pusher as pusher_mod
from gausslite.mission.pusher import Pusher
from gausslite.mission.share import ShareSession
from gausslite_services.fusion_server.client import keyframe_to_proto

H, W = 60, 80
INTR = Intrinsics(70.0, 70.0, 39.5, 29.5, W, H)


def _frame(i: int, x: float = 0.0, seed: int = 0) -> Frame:
    r = np.random.default_rng(seed + i)
    c2w = np.eye(4)
    c2w[0, 3] = x
    depth = np.full((H, W), 2.0, np.float32)
    return Frame(i, i / 30.0, r.integers(0, 255, (H, W, 3), dtype=np.uint8), depth, c2w, INTR)


def _roi(x0=30, y0=20, x1=50, y1=40) -> np.ndarray:
    roi = np.zeros((H, W), bool)
    roi[y0:y1, x0:x1] = True
    return roi


def _project(K, c2w, p):
    w2c = np.linalg.inv(c2w)
    q = w2c[:3, :3] @ p + w2c[:3, 3]
    return K[0, 0] * q[0] / q[2] + K[0, 2], K[1, 1] * q[1] / q[2] + K[1, 2]


def test_an_roi_crop_is_the_same_pinhole_view_cut_around_the_roi():
    f, roi = _frame(0), _roi()
    crop, rc = roi_crop(f, roi, margin_px=4)
    assert crop.rgb.shape == (28, 28, 3) and crop.depth.shape == rc.shape == (28, 28) and rc.all() == False  # noqa: E712
    assert rc.sum() == roi.sum() and crop.frame_id == f.frame_id and np.array_equal(crop.c2w, f.c2w)
    assert (crop.intrinsics.width, crop.intrinsics.height) == (28, 28)
    # a world point lands on the same image content in both views
    p = np.array([0.1, -0.05, 2.0])
    u, v = _project(f.intrinsics.K, f.c2w, p)
    uc, vc = _project(crop.intrinsics.K, crop.c2w, p)
    assert (u - uc, v - vc) == pytest.approx((26.0, 16.0))
    assert np.array_equal(crop.rgb[int(round(vc)), int(round(uc))], f.rgb[int(round(v)), int(round(u))])
    # clipped at the border; empty ROI: nothing to send; mismatched ROI: an error
    edge, _ = roi_crop(f, _roi(0, 0, 5, 5), margin_px=10)
    assert edge.rgb.shape[:2] == (15, 15) and edge.intrinsics.cx == f.intrinsics.cx
    assert roi_crop(f, np.zeros((H, W), bool), 4) is None
    with pytest.raises(ValueError):
        roi_crop(f, np.zeros((H, W + 1), bool), 4)


def test_the_region_carried_to_another_frame_by_depth_lands_where_it_is_seen():
    kf, roi = _frame(0), _roi()
    pts = region_points(kf, roi, stride=1)
    assert pts.shape == (int(roi.sum()), 3) and np.allclose(pts[:, 2], 2.0)
    moved = _frame(1, x=0.2)  # camera 0.2 m to the right: the region moves 0.2 * 70 / 2 = 7 px to the left
    mask = project_roi(pts, moved.depth, moved.intrinsics.K, moved.c2w, dilate_px=0)
    ys, xs = np.nonzero(mask)
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (23, 42, 20, 39)
    # a nearer surface in front hides it
    occluded = _frame(2, x=0.2)
    occluded.depth[:] = 1.0
    assert not project_roi(pts, occluded.depth, occluded.intrinsics.K, occluded.c2w).any()
    assert region_points(kf, np.zeros((H, W), bool)).shape == (0, 3)


def test_the_budget_sends_the_farthest_views_first_and_never_beyond_its_ratio():
    poses = [np.eye(4) for _ in range(5)]
    for i, x in enumerate([0.0, 0.01, 0.5, 1.0, 0.02]):
        poses[i][0, 3] = x
    b = ViewBudget(ratio=2.0)
    assert b.allowance(1000) == 2000
    chosen = b.choose([500] * 5, poses, subset_bytes=1000)
    assert chosen == [0, 3, 2, 4] and b.sent_bytes == 2000 and b.skipped == 1
    assert b.choose([500], [poses[1]], subset_bytes=1000) == [] and b.skipped == 1
    # a larger subset raises the allowance; a view too large is passed over for a smaller one
    assert b.choose([900, 300], [poses[1], poses[1]], subset_bytes=1200) == [1]
    assert b.sent_bytes == 2300 <= 2 * 1200
    assert ViewBudget(ratio=None).choose([10 ** 9, 5], poses[:2], 1) == [0, 1]
    assert next_view(poses, []) == 0 and next_view(poses[1:], [poses[0]]) == 2
    with pytest.raises(ValueError):
        next_view([], [])
    with pytest.raises(ValueError):
        b.choose([1, 2], poses[:1], 10)


def test_the_reserve_waits_for_the_final_push_and_buys_the_farthest_views_left():
    poses = [np.eye(4) for _ in range(6)]
    for i, x in enumerate([0.0, 0.05, 0.1, 2.0, 1.0, 0.15]):
        poses[i][0, 3] = x
    b = ViewBudget(ratio=4.0, reserve=0.5)
    assert b.allowance(1000, final=False) == 2000 and b.allowance(1000) == 4000
    # during the mission only half the budget goes: the early, close views
    assert b.choose([1000] * 3, poses[:3], subset_bytes=1000, final=False) == [0, 2]
    assert b.sent_bytes == 2000 and b.skipped == 1
    assert b.choose([1000] * 4, [poses[1], *poses[3:]], subset_bytes=1000, final=False) == []
    # the final push spends the reserve on the waiting views farthest from those sent, wherever they came from
    assert b.choose([1000] * 4, [poses[1], *poses[3:]], subset_bytes=1000, final=True) == [1, 2]
    assert b.sent_bytes == 4000 and b.skipped == 2
    # without a reserve the final flag changes nothing
    assert ViewBudget(ratio=2.0).allowance(1000, final=False) == 2000
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError):
            ViewBudget(ratio=2.0, reserve=bad)


class _Recorder:
    """A fusion client that records the keyframes it is given and their bytes on the wire."""

    def __init__(self):
        self.sent, self.wire_bytes = [], 0

    def upload_keyframes(self, agent_id, frames, *, jpeg_quality=95, color_format="png", rois=None):
        for f, r in zip(frames, rois):
            self.wire_bytes += keyframe_to_proto(agent_id, f, jpeg_quality, color_format, r).ByteSize()
            self.sent.append(f)
        return len(frames)


def test_the_pusher_sends_roi_crops_within_its_byte_budget_measured_on_the_wire(monkeypatch):
    config = AgentConfig(push={"nice": 0}, refine_views={"crop": True, "margin_px": 4, "budget_ratio": 2.0,
                                                      "min_roi_px": 16})
    p = Pusher("p1", "find the object", config, None, ShareSession("p1", config), mapper=None,
               intrinsics=lambda: None, report=lambda m: None)
    for i in range(12):
        assert p.add_keyframe(_frame(i, x=0.05 * i), _roi())
    assert not p.add_keyframe(_frame(99), _roi(0, 0, 2, 2))  # too small a region: not offered
    assert not p.add_keyframe(_frame(98), None)
    sizes = [view_bytes(*roi_crop(_frame(i, x=0.05 * i), _roi(), 4)) for i in range(12)]
    assert max(sizes) < 1.2 * min(sizes)
    p.final_subset_bytes = -(-5 * max(sizes) // 2)  # room for five views, not six
    measured = []  # each waiting view is encoded to measure its size once, not at every push
    monkeypatch.setattr(pusher_mod, "view_bytes", lambda *a: measured.append(1) or view_bytes(*a))
    rec = _Recorder()
    sent, n = p._upload_pending_keyframes(rec)
    assert n == len(sent) == 5 and p.views.sent == 5 and p.views_unsent() == 7
    # the sizes of the views still waiting are kept
    assert len(measured) == 12 and len(p._kf_pending) == 7 and all(w.size for w in p._kf_pending)
    assert all(f.rgb.shape == (28, 28, 3) for f in rec.sent)
    assert rec.wire_bytes <= p.views.sent_bytes <= 2 * p.final_subset_bytes
    # spread over the trajectory: the first and last frames and the middle, not five neighbours
    assert {rec.sent[0].frame_id, rec.sent[1].frame_id} == {0, 11}
    p.final_subset_bytes *= 2  # a larger subset: more room
    sent, _ = p._upload_pending_keyframes(rec)
    assert len(sent) == 5 and p.views_unsent() == 2 and rec.wire_bytes <= 2 * p.final_subset_bytes
    assert len(measured) == 12 and len(p._kf_pending) == 2 and all(w.size for w in p._kf_pending)



def test_the_pusher_keeps_the_reserve_for_its_final_push():
    config = AgentConfig(push={"nice": 0}, refine_views={"crop": True, "margin_px": 4, "budget_ratio": 2.0,
                                                      "min_roi_px": 16, "reserve": 0.5})
    p = Pusher("p1", "find the object", config, None, ShareSession("p1", config), mapper=None,
               intrinsics=lambda: None, report=lambda m: None)
    for i in range(8):
        assert p.add_keyframe(_frame(i, x=0.05 * i), _roi())
    size = max(view_bytes(*roi_crop(_frame(i, x=0.05 * i), _roi(), 4)) for i in range(8))
    p.final_subset_bytes = 2 * size  # room for four views in all, two before the final push
    rec = _Recorder()
    sent, _ = p._upload_pending_keyframes(rec)
    assert len(sent) == 2 and p.views_unsent() == 6
    sent, _ = p._upload_pending_keyframes(rec, final=True)
    assert len(sent) == 2 and p.views_unsent() == 4 and rec.wire_bytes <= 2 * p.final_subset_bytes
