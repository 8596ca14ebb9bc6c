"""A camera-only robot at room scale, live: the agent with ``agent.pose_source: odometry`` replays a 7 m hand-held
walk at 7.5 Hz (132 frames, 5 cm apart, two loops in front of the desk, the realistic sensor model) whose tracking
drifts, and maps every frame to the end while loop closures move its keyframes by centimetres and the map follows them.

The drift is made, not hoped for: every registration the odometry makes is biased by 0.2° about the vertical axis and
2 mm sideways (a systematic error such as a miscalibrated sensor leaves), so the poses tracked online drift by about
7 cm over the walk, about 1 % of the path, and the pose graph's loop closures pull the keyframes back (one loop
candidate a keyframe: the loop registrations are most of the run's time, and one a keyframe closes some thirty loops;
the keyframes, and so the loops, are the walk's whatever its frame rate). Every frame's pose is then a product of a
hundred and more registrations and corrections, the case that once left SO(3) and stopped every mission at its 600th
frame."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gausslite.config import load_config
from gausslite.datasets import load_dataset
from gausslite.odometry.rgbd import RGBDOdometry
from gausslite.mission import AgentRuntime
from gausslite.mission.state import MissionState
from gausslite.parser import TaskParser
from gausslite.synthetic import make_scene
from tests._waits import WORK_S

FRAMES, FPS = 132, 7.5  # the walk at 7.5 Hz: 0.40 m/s
#: the registration bias: 0.2 degrees about the camera's y axis and 2 mm along x, per registration
BIAS = np.eye(4)
BIAS[:3, :3] = Rotation.from_euler("y", 0.2, degrees=True).as_matrix()
BIAS[0, 3] = 0.002

SETTINGS = ["agent.pose_source=odometry", "agent.odometry.loop.max_candidates=1", "agent.ingest=every_frame",
            "agent.push.every=1000", "agent.idle_optimize=false", "mapper.iters_per_frame=2", "mapper.warmup_iters=1",
            "mapper.seeding.seeds_per_frame=100", "agent.scoring.protocols=[sensor]", "agent.resolution.downscale=1"]


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    out = tmp_path_factory.mktemp("walk")
    make_scene(out, width=96, height=72, frames=FRAMES, fps=FPS, trajectory="walk", sensor_noise="realistic",
               progress=False, agents=("agent_a",))
    return load_dataset(out / "agent_a")


def _rigidity(T: np.ndarray) -> float:
    R = np.asarray(T, np.float64)[:3, :3]
    return max(float(np.abs(R @ R.T - np.eye(3)).max()), abs(float(np.linalg.det(R)) - 1.0))


def test_a_drifting_camera_only_walk_is_mapped_to_the_end_through_its_loop_closures(walk, monkeypatch):
    real = RGBDOdometry.register

    def biased(self, frame, image, ref, init):
        ok, T, info, fitness = real(self, frame, image, ref, init)
        return ok, T @ BIAS, info, fitness

    monkeypatch.setattr(RGBDOdometry, "register", biased)
    text = walk.annotations.task_by_id("synth-pick-object").text
    cfg = load_config(None, SETTINGS).agent
    rt = AgentRuntime("a", text, TaskParser().parse(text), cfg, annotations=walk.annotations,
                      task_id="synth-pick-object")
    added = {}  # keyframe id -> its pose when it was taken
    graph_add = type(rt.odometry.graph).add

    def record(graph, frame_id, c2w, *a, **kw):
        added.setdefault(int(frame_id), np.asarray(c2w, np.float64).copy())
        return graph_add(graph, frame_id, c2w, *a, **kw)

    monkeypatch.setattr(type(rt.odometry.graph), "add", record)
    try:
        rt.replay(walk)
        assert rt.wait_mapped(timeout_s=WORK_S), f"the walk was not mapped within {WORK_S:.0f} s"
        assert rt.odometry.flush(WORK_S)
        rt.poses.follow(rt.mapper)  # the last loop closures, as Finish's final pass follows them
        st = rt.status()
        # to the end: every frame mapped or counted as lost, nothing failed, no correction rejected
        assert st["state"] == MissionState.REPLAY_DONE, st["last_error"]
        assert st["frames_failed"] == 0 and st["corrections_rejected"] == 0, st["last_error"]
        assert st["frames_mapped"] + st["frames_lost"] == FRAMES and st["frames_mapped"] >= 0.95 * FRAMES
        # the walk drifted and several loops closed: keyframes moved by 5 cm or more, and the map followed
        nodes = rt.odometry.graph.nodes
        moved = max(float(np.linalg.norm(nodes[fid].c2w[:3, 3] - c2w[:3, 3])) for fid, c2w in added.items())
        assert st["loop_closures"] >= 2 and moved >= 0.05, (st["loop_closures"], moved)
        follower = rt.poses.follower
        assert follower.n_corrections >= 1 and follower.n_moved > 0 and follower.n_rejected == 0
        # every pose composed on the way stays rigid to rounding
        poses = [n.c2w for n in nodes.values()] + list(rt.mapper.keyframe_poses().values())
        assert len(poses) > FRAMES and max(_rigidity(T) for T in poses) < 1e-9
        # the map sits where the corrected poses put it: the mapped frames' poses follow their keyframes'
        truth = {int(f.frame_id): f.c2w for f in walk}
        err = [np.linalg.norm(c2w[:3, 3] - truth[fid][:3, 3]) for fid, c2w in rt.mapper.keyframe_poses().items()]
        assert float(np.median(err)) < 0.10
    finally:
        rt.close()
