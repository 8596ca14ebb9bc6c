"""The map follows the odometry's loop closures (gausslite.mission.pose_follow): a mapped frame moves with the
correction of its anchor keyframe, in the map's frame, once the mapping worker applies it."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from gausslite.odometry.rgbd import TrackResult
from gausslite.mission.pose_follow import MapFollower


def _shift(x: float, y: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, 0.0]
    return T


class _Mapper:
    """The two calls MapFollower makes of a mapper, recording the corrections."""

    def __init__(self, poses):
        self.poses, self.applied = dict(poses), []

    def keyframe_poses(self):
        return dict(self.poses)

    def apply_pose_corrections(self, new):
        self.applied.append(dict(new))
        self.poses.update(new)
        return 7 * len(new)


def test_a_mapped_frame_moves_with_its_anchor_in_the_maps_frame():
    graph = SimpleNamespace(nodes={10: SimpleNamespace(c2w=_shift(1.0)), 20: SimpleNamespace(c2w=_shift(2.0))})
    odo = SimpleNamespace(graph=graph, on_correction=None)
    follower = MapFollower(odo)
    assert odo.on_correction == follower.on_correction
    W = _shift(0.0, 5.0)  # the odometry's frame sits 5 m along y in the map's
    # frame 11 tracked 0.1 m past keyframe 10; frame 21 past keyframe 20; both mapped (the map refined 11's pose)
    follower.record(11, TrackResult(_shift(1.1), True, anchor=10, T_anchor=_shift(0.1)), W)
    follower.record(21, TrackResult(_shift(2.1), True, anchor=20, T_anchor=_shift(0.1)), W)
    follower.record(12, TrackResult(_shift(1.2), True, anchor=10, T_anchor=_shift(0.2)), W)  # tracked, never mapped
    follower.mapped(11)
    follower.mapped(21)
    refined = W @ _shift(1.1) @ _shift(0.0, 0.01)
    mapper = _Mapper({11: refined, 21: W @ _shift(2.1)})
    assert follower.apply(mapper) == 0 and mapper.applied == []  # nothing pending
    graph.nodes[10].c2w = _shift(1.0, 0.3)  # the pose graph moved keyframe 10 by 0.3 m along y
    follower.on_correction({10: graph.nodes[10].c2w, 20: graph.nodes[20].c2w})
    assert follower.apply(mapper) == 7
    (new,) = mapper.applied
    assert set(new) == {11}  # keyframe 20 did not move: frame 21 stays
    np.testing.assert_allclose(new[11], _shift(0.0, 0.3) @ refined)  # the refinement rides along
    assert follower.n_corrections == 1 and follower.n_moved == 7
    assert follower.apply(mapper) == 0  # applied once
    follower.on_correction({})
    assert follower.apply(mapper) == 0  # the same anchors again: nothing moves twice


def test_frames_that_are_never_mapped_are_not_kept_for_ever():
    from gausslite.mission import pose_follow

    follower = MapFollower(SimpleNamespace(graph=SimpleNamespace(nodes={}), on_correction=None))
    for fid in range(pose_follow.MAX_UNMAPPED + 10):
        follower.record(fid, TrackResult(np.eye(4), True, anchor=0, T_anchor=np.eye(4)))
    follower.mapped(3)  # dropped already: the oldest go first
    follower.mapped(pose_follow.MAX_UNMAPPED + 9)
    assert len(follower._unmapped) == pose_follow.MAX_UNMAPPED - 1 and list(follower._frames) == [
        pose_follow.MAX_UNMAPPED + 9]
