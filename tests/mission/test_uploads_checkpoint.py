"""Two parts of a mission on their own: what it uploads for the fusion refinement (gausslite.mission.uploads: one
image size per fusion session, the views between keyframes carried over by depth) and its checkpoint
(gausslite.mission.checkpoint: written atomically, resumed only by the same agent, mission, task and world frame,
and never below a version already handed to the pusher)."""

from __future__ import annotations

import json
import types

import numpy as np
import pytest

from gausslite.config import load_config
from gausslite.mapping.keyframes import KeyframeSelector
from gausslite.mission.checkpoint import CHECKPOINT_FILE, VERSION_FILE, MissionCheckpoint, atomic_write
from gausslite.mission.progress import MissionProgress
from gausslite.mission.uploads import KeyframeUploads
from tests._scenes import plane_frame, plane_roi


# ---------------------------------------------------------------------------------------------- uploads
def _uploads(factor: float, every: int = 1):
    cfg = load_config(None, [f"agent.refine_views.between_every={every}"]).agent
    resolution = types.SimpleNamespace(factor=factor)
    native = plane_frame(0).intrinsics
    return KeyframeUploads(cfg, resolution, lambda: native), resolution


def test_uploads_keep_the_size_fixed_at_the_first_keyframe():
    up, resolution = _uploads(2.0)
    assert up.factor is None and up.intrinsics.width == 28  # before fix: the current mapping size
    up.fix()
    fr, roi = plane_frame(0), plane_roi()
    mapped, w_mapped = plane_frame(0, H=20, W=28), roi[::2, ::2]
    sent, w = up.keyframe(fr, mapped, w_mapped)
    assert sent is mapped and w is w_mapped  # at the session's size: as mapped
    resolution.factor = 1.0  # the governor moved to a finer level: uploads keep the session's size
    assert (up.intrinsics.width, up.intrinsics.height) == (28, 20) and not up.at_mapping_size
    sent, w = up.keyframe(fr, fr, roi)
    assert (sent.intrinsics.width, sent.intrinsics.height) == (28, 20) and w.shape == (20, 28)
    assert w.dtype == bool and w[8, 10] and not w[0, 0]  # the ROI resized with the frame
    assert list(up.between_views(fr, roi, [plane_frame(1)])) == []  # no views at another size


def test_views_between_keyframes_carry_the_keyframes_region_over():
    up, _ = _uploads(1.0, every=2)
    key, roi = plane_frame(0), plane_roi()
    frames = [plane_frame(i, 0.05 * i) for i in range(1, 5)]
    views = list(up.between_views(key, roi, frames + [object()]))  # a frame not decoded is skipped
    assert [f.frame_id for f, _ in views] == [1, 3]
    for fr, w in views:
        assert w.shape == fr.depth.shape and w.dtype == bool and 0 < w.sum() < w.size
    assert list(up.between_views(key, np.zeros_like(roi), frames)) == []  # no region, no views


# ---------------------------------------------------------------------------------------------- checkpoint
class _Model:
    def __init__(self, n: int):
        self.active = np.arange(n) % 2 == 0  # every other Gaussian serves the task

    def __len__(self):
        return len(self.active)


class _Mapper:
    """The mapper's checkpoint interface: ``state_dict`` / ``load_state_dict`` and its model's size."""

    def __init__(self, n: int = 0):
        self.state, self.model = {"weights": list(range(n))}, _Model(n)

    def state_dict(self):
        return dict(self.state)

    def load_state_dict(self, state):
        self.state, self.model = dict(state), _Model(len(state["weights"]))


class _Pusher:
    def __init__(self, version: int = 0):
        self.version = version

    def resume(self, version: int):
        self.version = max(self.version, version)


def _checkpoint(folder, *, agent="a", mission="m1", text="Find the chair", T=None, n=0, version=0):
    progress = MissionProgress()
    parts = types.SimpleNamespace(progress=progress, task=types.SimpleNamespace(text=text, task_id="chair"),
                                  mapper=_Mapper(n), selector=KeyframeSelector(), pusher=_Pusher(version))
    ck = MissionCheckpoint(folder, agent, mission, T, progress=progress, task=parts.task, mapper=parts.mapper,
                           selector=parts.selector, odometry=None, pusher=parts.pusher)
    return ck, parts


def test_a_checkpoint_resumes_the_map_counters_and_the_newest_version(tmp_path):
    ck, parts = _checkpoint(tmp_path / "m1", n=6, version=3)
    assert not ck.exists()
    p = parts.progress
    p.frames_keyframed = p.frames_mapped = 4
    p.seconds_mapping, p.frames_rejected = 1.5, 2
    parts.selector.offer("kf", np.eye(4), 0.0)
    parts.selector.take()
    assert ck.save() == tmp_path / "m1" / CHECKPOINT_FILE and ck.exists() and p.checkpoints == 1
    parts.pusher.version = 5  # two more offers after the checkpoint
    ck.record_version()
    assert json.loads((tmp_path / "m1" / VERSION_FILE).read_text()) == {"version": 5}
    fresh, new = _checkpoint(tmp_path / "m1")
    assert fresh.resume() == 4
    q = new.progress
    assert (q.frames_keyframed, q.frames_mapped, q.seconds_mapping, q.resumed_keyframes) == (4, 4, 1.5, 4)
    assert q.frames_rejected == 0  # not a checkpoint counter
    assert (q.n_gaussians, q.n_active) == (6, 3) and new.mapper.state == {"weights": list(range(6))}
    assert new.pusher.version == 5  # never below a version the fusion server may hold
    np.testing.assert_array_equal(new.selector.ref_pose, np.eye(4))
    assert not list((tmp_path / "m1").glob(".*.tmp"))  # written through temporary files, renamed


def test_a_checkpoint_resumes_only_its_own_mission(tmp_path):
    ck, _ = _checkpoint(tmp_path / "m1", n=2)
    ck.save()
    T = np.eye(4)
    T[0, 3] = 1.0
    for kw, match in (({"agent": "b"}, "belongs to agent 'a' mission 'm1'"),
                      ({"mission": "m2"}, "belongs to agent"),
                      ({"text": "Open the box"}, "was started with the task 'Find the chair'"),
                      ({"T": T}, "another world frame")):
        other, parts = _checkpoint(tmp_path / "m1", **kw)
        with pytest.raises(ValueError, match=match):
            other.resume()
        assert parts.progress.resumed_keyframes == 0 and parts.mapper.state == {"weights": []}
    (tmp_path / "m1" / CHECKPOINT_FILE).write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot read the checkpoint"):
        _checkpoint(tmp_path / "m1")[0].resume()


def test_atomic_write_replaces_the_file_whole(tmp_path):
    path = tmp_path / "sub" / "f.json"
    atomic_write(path, lambda p: p.write_text("one"))
    atomic_write(path, lambda p: p.write_text("two"))
    assert path.read_text() == "two" and [q.name for q in path.parent.iterdir()] == ["f.json"]

    def broken(p):
        p.write_text("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        atomic_write(path, broken)
    assert path.read_text() == "two"  # the old file stays whole
