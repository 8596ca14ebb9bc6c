"""Drift correction for the RGB-D odometry (gausslite.odometry.pose_graph): the keyframe pose graph removes the drift
a loop measures, its gates turn false loops away, the map's frames follow the corrected keyframes, and a lost frame
is re-localised against the keyframes when the camera comes back."""

from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest

from gausslite.datasets import load_dataset
from gausslite.odometry.rgbd import OdometryConfig, RGBDOdometry
from gausslite.odometry.config import REPEAT_BOUND_M
from gausslite.odometry.pose_graph import KeyframeGraph, LoopConfig, LoopEdge, thumbnail
from gausslite.datasets.trajectory import ate_rmse, rotation_angle_deg
from gausslite.synthetic import make_scene


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """The synthetic scene's robot A, 16 frames at 160x120, read with their exact poses."""
    out = tmp_path_factory.mktemp("scene")
    make_scene(out, frames=16, width=160, height=120, progress=False, agents=("agent_a",))
    return list(load_dataset(out / "agent_a", pose_source="given"))


def _pose(x: float, y: float, yaw_deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = [x, y, 0]
    return T


def test_a_loop_edge_removes_the_drift_of_a_square():
    # a 1 m square walked in 8 keyframes: each odometry edge turns 1 degree too far, so the chain drifts
    true = [_pose(*p) for p in [(0, 0, 0), (.5, 0, 0), (1, 0, 90), (1, .5, 90), (1, 1, 180), (.5, 1, 180),
                               (0, 1, 270), (0, .5, 270)]]
    bias = _pose(0.0, 0.0, 1.0)
    est = [true[0]]
    for i in range(1, len(true)):
        est.append(est[-1] @ np.linalg.inv(true[i - 1]) @ true[i] @ bias)
    graph = KeyframeGraph()
    graph.add(0, est[0])
    for i in range(1, len(true)):
        graph.add(i, est[i], i - 1, np.linalg.inv(est[i - 1]) @ est[i], np.eye(6) * 100)
    drifted = ate_rmse(np.stack(est), np.stack(true))
    # the last keyframe sees the first again: the loop measures their true relative pose
    graph.loops.append(LoopEdge(7, 0, np.linalg.inv(true[0]) @ true[7], 0.9, 0.005))
    cfg = LoopConfig(drift_floor_m=0.5, drift_floor_deg=20.0)
    new = graph.optimise(cfg)
    fixed = ate_rmse(np.stack([new[i] for i in range(8)]), np.stack(true))
    assert drifted > 0.02 and fixed < 0.5 * drifted
    assert np.allclose(new[0], est[0])  # the first keyframe fixes the gauge
    assert graph.summary()["loops"] == 1 and graph.summary()["optimisations"] == 1


def _chain(information: float) -> KeyframeGraph:
    """Three keyframes 10 cm apart, and a "loop" that puts the last one 2 m from the first."""
    graph = KeyframeGraph()
    graph.add(0, np.eye(4))
    graph.add(1, _pose(0.1, 0, 0), 0, _pose(0.1, 0, 0), np.eye(6) * information)
    graph.add(2, _pose(0.2, 0, 0), 1, _pose(0.1, 0, 0), np.eye(6) * information)
    graph.loops.append(LoopEdge(2, 0, _pose(2.0, 0, 0), 0.9, 0.005))
    return graph


def test_a_loop_that_disagrees_with_the_odometry_is_pruned_or_undone():
    graph = _chain(100.0)  # firm odometry: the line process prunes the loop, and nothing moves
    before = {k: n.c2w.copy() for k, n in graph.nodes.items()}
    new = graph.optimise(LoopConfig())
    assert graph.loops == [] and all(np.allclose(new[k], before[k], atol=1e-6) for k in before)
    graph = _chain(1e-6)  # weak odometry: the loop wins, moves a keyframe 1.8 m, and the optimisation is undone
    before = {k: n.c2w.copy() for k, n in graph.nodes.items()}
    assert graph.optimise(LoopConfig(prune_threshold=1e-3)) == {}
    assert all(np.array_equal(graph.nodes[k].c2w, before[k]) for k in before)


@pytest.mark.parametrize("registration", ["icp", "hybrid", "point_to_plane"])
def test_false_loops_between_different_places_are_turned_away(frames, registration):
    cfg = OdometryConfig(track_width=None)
    cfg.loop.registration = registration
    odo = RGBDOdometry(cfg, initial_pose=frames[0].c2w)
    for f in frames:
        odo.track(f)
    kfs = list(odo.loop_keyframes.values())
    assert len(kfs) >= 8
    kfs = kfs[::2][:5]  # views 0.4 m or more apart
    # every pair of keyframes, each registered as if the camera stood where the other one does: a "loop" between
    # views that do not show the same place (or do, at the wrong pose) must not pass the gates
    from gausslite.odometry.pose_graph import verify_registration

    cfg = odo.config.loop
    accepted_wrong = 0
    for a in kfs:
        for b in kfs:
            if a is b:
                continue
            got = verify_registration(odo, a.frame, a.image, b, np.eye(4), cfg.min_fitness, cfg)
            if got is None:
                continue
            true = np.linalg.inv(b.c2w) @ a.c2w
            d = np.linalg.inv(true) @ got[0]
            # wrong: off by more than a registration's error over that baseline (2 cm + 6 % of it, or 3 degrees)
            baseline = float(np.linalg.norm(true[:3, 3]))
            accepted_wrong += float(np.linalg.norm(d[:3, 3])) > 0.02 + 0.06 * baseline or rotation_angle_deg(d) > 3.0
    assert accepted_wrong == 0


def test_a_loop_is_registered_from_an_estimate_centimetres_off(frames):
    # a loop's estimated relative pose carries the odometry's drift: from 5 cm and 3 degrees off, the registration
    # lands on the true relative pose of two keyframes and passes the gates
    from gausslite.odometry.pose_graph import verify_registration

    odo = RGBDOdometry(OdometryConfig(track_width=None), initial_pose=frames[0].c2w)
    for f in frames:
        odo.track(f)
    kfs = list(odo.loop_keyframes.values())
    truth = {int(f.frame_id): f.c2w for f in frames}
    a, b = kfs[3], kfs[2]
    true = np.linalg.inv(truth[int(b.frame_id)]) @ truth[int(a.frame_id)]
    cfg = odo.config.loop
    got = verify_registration(odo, a.frame, a.image, b, true @ _pose(0.05, -0.03, 3.0), cfg.min_fitness, cfg)
    assert got is not None
    d = np.linalg.inv(true) @ got[0]
    assert float(np.linalg.norm(d[:3, 3])) < 0.01 and rotation_angle_deg(d) < 0.5
    assert got[1].shape == (6, 6) and got[2] >= cfg.min_fitness and 0.0 <= got[3] <= cfg.icp_max_rmse_m


def test_a_loops_information_is_open3ds_from_the_inliers_already_found(frames):
    """icp_information gives what Open3D's get_information_matrix_from_point_clouds does, from the correspondences of
    an evaluation at the same distance and pose (no second nearest-neighbour search)."""
    from gausslite.odometry.pose_graph import DepthClouds, icp_information, open3d_module

    reg = open3d_module().pipelines.registration
    clouds = DepthClouds(4.0)
    src, tgt = clouds.of(frames[5], 0.02), clouds.of(frames[3], 0.02)
    T = np.linalg.inv(frames[3].c2w) @ frames[5].c2w
    fit = reg.evaluate_registration(src, tgt, 0.05, T)
    assert len(fit.correspondence_set) > 100
    want = np.asarray(reg.get_information_matrix_from_point_clouds(src, tgt, 0.05, T))
    got = icp_information(tgt, fit.correspondence_set)
    assert got.shape == (6, 6) and np.allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())


def test_the_loop_search_makes_each_keyframes_cloud_once_and_keeps_only_the_keyframes_thinned_clouds(frames,
                                                                                                 monkeypatch):
    """A keyframe's depth cloud is made once for every later loop search that registers to it; the cache holds the
    loop keyframes' thinned clouds alone, and the poses are those of a search without it."""
    from gausslite.odometry import pose_graph

    made = []
    real = pose_graph.DepthClouds.of

    def counting(self, frame, voxel_m=None):
        key = (id(frame), voxel_m)
        if key not in self._made:
            made.append((int(frame.frame_id), voxel_m))
        return real(self, frame, voxel_m)

    cfg = OdometryConfig(loop=LoopConfig(min_gap=1, radius_m=2.0, max_angle_deg=180.0, max_candidates=2))
    stream = frames[:7]
    plain = RGBDOdometry(cfg, initial_pose=frames[0].c2w)
    plain_poses = [plain.track(f).c2w for f in stream]
    monkeypatch.setattr(pose_graph.DepthClouds, "of", counting)
    odo = RGBDOdometry(cfg, initial_pose=frames[0].c2w)
    poses = [odo.track(f).c2w for f in stream]
    thinned = [m for m in made if m[1] == cfg.loop.icp_voxel_m]
    assert odo.graph.n_loop_tried > len(odo.loop_keyframes) and len(thinned) == len(set(thinned))
    kept = {k for k, _ in odo.loops.clouds._made}
    assert kept <= {id(k.frame) for k in odo.loop_keyframes.values()}
    assert {v for _, v in odo.loops.clouds._made} == {cfg.loop.icp_voxel_m}
    # the poses of a search without the cache, to the bound two runs of the tracker repeat to
    assert float(np.abs(np.stack(poses) - np.stack(plain_poses)).max()) <= REPEAT_BOUND_M


def test_the_cloud_cache_keeps_the_thinned_clouds_used_last(frames):
    """keep(frames, voxel, limit) holds the thinned clouds of those frames alone, at most ``limit``, the most
    recently used; a kept cloud is the same object on the next use."""
    from gausslite.odometry.pose_graph import DepthClouds

    clouds = DepthClouds(4.0)
    made = [clouds.of(f, 0.04) for f in frames[:3]]
    assert clouds.of(frames[0], 0.04) is made[0]  # used again: now the most recent
    clouds.keep(frames[:3], 0.04, limit=2)
    assert {k for k, _ in clouds._made} == {id(frames[0]), id(frames[2])}
    assert {v for _, v in clouds._made} == {0.04}  # the full clouds are gone
    assert clouds.of(frames[2], 0.04) is made[2] and clouds.of(frames[1], 0.04) is not made[1]
    clouds.keep(frames[1:2], 0.04)
    assert [k for k, _ in clouds._made] == [id(frames[1])]


def test_a_lost_frame_is_relocalised_when_the_camera_comes_back(frames):
    blank = dataclasses.replace(frames[8], depth=np.zeros_like(frames[8].depth))  # the camera covered
    stream = frames[:14] + [dataclasses.replace(blank, frame_id=100 + i) for i in range(3)]
    back = dataclasses.replace(frames[1], frame_id=200)  # then it comes back, 2.6 m away, to a view it saw before
    stream.append(back)
    for enabled in (False, True):
        cfg = OdometryConfig(track_width=None)
        cfg.relocalise.enabled = enabled
        odo = RGBDOdometry(cfg, initial_pose=frames[0].c2w)
        results = [odo.track(f) for f in stream]
        assert [r.ok for r in results[14:17]] == [False] * 3
        last = results[-1]
        if not enabled:
            assert not last.ok and odo.n_relocalised == 0
            continue
        assert last.ok and last.relocalised and odo.n_relocalised == 1 and odo.n_failed == 3
        assert float(np.linalg.norm(last.c2w[:3, 3] - frames[1].c2w[:3, 3])) < 0.02
        assert odo.summary()["relocalised"] == 1


def test_frames_follow_their_anchor_keyframe_when_the_graph_moves_it(frames):
    odo = RGBDOdometry(OdometryConfig(track_width=None), initial_pose=frames[0].c2w)
    results = [odo.track(f) for f in frames[:6]]
    moved = {}
    odo.on_correction = moved.update
    r = results[3]
    shift = _pose(0.0, 0.1, 0.0)
    new = {fid: (shift @ n.c2w if fid == r.anchor else n.c2w) for fid, n in odo.graph.nodes.items()}
    for fid, c2w in new.items():
        odo.graph.nodes[fid].c2w = c2w
    odo.apply_correction(new)
    assert np.allclose(odo.corrected(r), shift @ r.c2w)
    assert moved.keys() == new.keys()


def test_stopping_the_loop_thread_drops_its_backlog_and_ends_it():
    """stop() ends the loop-closing thread after the keyframe it is checking: a backlog of queued keyframes is
    dropped unchecked (a thread still inside Open3D when the interpreter exits aborts the process)."""
    import time
    from types import SimpleNamespace

    from gausslite.odometry.loop_closing import LoopClosing

    loops = LoopClosing(SimpleNamespace(config=OdometryConfig(), lock=threading.Lock()))
    checked = []
    loops.candidates = lambda kf: []
    loops.verify = lambda kf, cands: (time.sleep(0.2), checked.append(kf))[1] or []
    loops.commit = lambda kf, added, tried: 0
    for k in range(50):
        loops.later(k)
    while not checked:
        time.sleep(0.01)
    t0 = time.perf_counter()
    loops.stop(timeout_s=5.0)
    assert not loops.thread.is_alive() and time.perf_counter() - t0 < 2.0
    assert 1 <= len(checked) <= 3 and loops.queue.unfinished_tasks == 0
    loops.stop()  # again: a no-op


def test_thumbnails_match_the_same_view_best(frames):
    th = [thumbnail(f.rgb) for f in frames]
    sims = np.array([[a @ b for b in th] for a in th])
    assert np.allclose(np.diag(sims), 1.0, atol=1e-5)
    assert all(int(np.argmax(row)) == i for i, row in enumerate(sims))


def _there_and_back(frames):
    """The camera walks the frames and comes back along them (new frame ids): with a tracking window of two
    keyframes, the way back takes new keyframes where old ones stand, and those close loops."""
    back = [dataclasses.replace(f, frame_id=100 + i) for i, f in enumerate(reversed(frames[:-1]))]
    return list(frames) + back


def test_loops_closed_on_their_own_thread_never_hold_up_tracking(frames, monkeypatch):
    stream = _there_and_back(frames[:10])
    # one loop candidate a keyframe (a quarter of the registrations): the way back still closes eight loops
    cfg = OdometryConfig(track_width=None, reference_keyframes_max=2, loop=LoopConfig(max_candidates=1))
    inline = RGBDOdometry(cfg, initial_pose=frames[0].c2w)
    for f in stream:
        inline.track(f)
    assert inline.summary()["loops"] >= 1  # the way back closes loops

    odo = RGBDOdometry(cfg, initial_pose=frames[0].c2w, background_loops=True)
    gate = threading.Event()
    verify = odo.loops.verify

    def held_verify(kf, cands):  # the loop thread's registrations wait until the whole stream is tracked
        gate.wait(60.0)
        return verify(kf, cands)

    monkeypatch.setattr(odo.loops, "verify", held_verify)
    corrections = []
    odo.on_correction = corrections.append
    try:
        results = [odo.track(f) for f in stream]  # returns although no keyframe's loops were checked yet
        assert all(r.ok for r in results) and not corrections and odo.summary()["loops"] == 0
        gate.set()
        assert odo.flush(60.0)
        assert odo.summary()["loops"] >= 1 and corrections
        # the loops a thread closes later correct the keyframes as those closed at once do
        for fid, node in inline.graph.nodes.items():
            assert float(np.linalg.norm(odo.graph.nodes[fid].c2w[:3, 3] - node.c2w[:3, 3])) < 0.01
    finally:
        gate.set()
        odo.close()
    assert not odo.loops.thread.is_alive()


def _cloud(points: np.ndarray):
    """An Open3D cloud of ``points`` (N, 3) metres with normals estimated as the loop check's clouds are."""
    from gausslite.odometry.pose_graph import open3d_module

    o3d = open3d_module()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.1, max_nn=30))
    return pcd


def _grid(u: np.ndarray, v: np.ndarray, axes: tuple, offset: float, normal_axis: int) -> np.ndarray:
    uu, vv = np.meshgrid(u, v)
    p = np.zeros((uu.size, 3))
    p[:, axes[0]], p[:, axes[1]], p[:, normal_axis] = uu.ravel(), vv.ravel(), offset
    return p


def _corridor() -> np.ndarray:
    """Two walls (x = ±0.6 m) and a floor (y = 0.5 m) along z from 1 to 4 m, 3 cm apart: nothing faces along z."""
    z, s = np.arange(1.0, 4.0, 0.03), np.arange(-0.6, 0.6, 0.03)
    walls = [_grid(s[s < 0.5], z, (1, 2), x, 0) for x in (-0.6, 0.6)]
    return np.concatenate(walls + [_grid(s, z, (0, 2), 0.5, 1)])


def _corner() -> np.ndarray:
    """The corridor closed by an end wall (z = 4 m): every direction is pinned."""
    s = np.arange(-0.6, 0.6, 0.03)
    return np.concatenate([_corridor(), _grid(s, s[s < 0.5], (0, 1), 4.0, 2)])


def test_the_least_pinned_direction_is_along_a_corridor_and_none_in_a_closed_room():
    from gausslite.odometry.pose_graph import least_pinned_direction

    for points, pinned in ((_corridor(), False), (_corner(), True)):
        tgt = _cloud(points)
        value, direction = least_pinned_direction(tgt, np.stack([np.arange(len(points))] * 2, 1))
        assert abs(np.linalg.norm(direction) - 1.0) < 1e-9
        if pinned:
            assert value > 0.1  # the end wall faces along z
        else:
            assert value < 1e-3 and abs(direction[2]) > 0.99  # sliding down the corridor costs nothing
    with pytest.raises(ValueError, match="no inlier"):
        least_pinned_direction(_cloud(_corner()), np.zeros((0, 2), np.int64))


@pytest.mark.parametrize("closed", [False, True])
def test_a_registration_that_can_slide_is_turned_away_by_the_restarts(closed):
    # the same view of a corridor, "registered" 8 cm down it: a plane-to-plane fit everywhere along it, so gates 2-3
    # pass from either side; the restarts along the corridor do not come back, and the loop is turned away. With an
    # end wall the restarts return to the true pose, and the check passes.
    from gausslite.odometry.pose_graph import _icp, _in_basin, open3d_module

    points = _corner() if closed else _corridor()
    src, tgt = _cloud(points), _cloud(points)
    cfg = LoopConfig()
    start = np.eye(4)
    start[2, 3] = 0.08
    T = _icp(src, tgt, start if not closed else np.eye(4), cfg.icp_levels_m, cfg)
    fit = open3d_module().pipelines.registration.evaluate_registration(src, tgt, cfg.icp_distance_m, T)
    assert fit.fitness > 0.9  # a perfect fit by the inlier gates in both cases
    assert _in_basin(src, tgt, T, fit.correspondence_set, cfg) is closed
    assert _in_basin(src, tgt, T, fit.correspondence_set, LoopConfig(basin_m=None))  # the check turned off
