"""The agent with ``agent.pose_source: odometry``: every replayed frame is tracked as it arrives, the mapper maps at
the estimate, and a lost frame is logged, counted in the mission status and not mapped."""

from __future__ import annotations

import dataclasses

import numpy as np

from gausslite.config import load_config
from gausslite.datasets import load_dataset
from gausslite.mission import AgentRuntime
from gausslite.parser import TaskParser
from gausslite.synthetic import make_scene

TINY = ["agent.push_every=100", "agent.idle_chunk_s=0.05", "mapper.iters_per_frame=3", "mapper.warmup_iters=1",
        "mapper.seeding.seeds_per_frame=200", "agent.scoring.protocols=[sensor]", "agent.pose_source=odometry",
        "agent.ingest=every_frame"]


class _Spoiled:
    """The dataset with one frame's images replaced by noise and no depth (nothing to register)."""

    def __init__(self, ds, bad: int):
        self.ds, self.bad = ds, bad
        self.path, self.annotations, self.intrinsics = ds.path, ds.annotations, ds.intrinsics

    def __len__(self):
        return len(self.ds)

    def __getitem__(self, i):
        f = self.ds[i]
        if i != self.bad:
            return f
        rng = np.random.default_rng(0)
        return dataclasses.replace(f, rgb=rng.integers(0, 255, f.rgb.shape, dtype=np.uint8),
                                   depth=np.zeros_like(f.depth))


def test_a_replay_tracks_every_frame_and_a_lost_one_is_counted_not_mapped(tmp_path):
    make_scene(tmp_path, seed=0, width=96, height=72, frames=14, progress=False)
    ds = load_dataset(tmp_path / "agent_a")
    text = ds.annotations.task_by_id("synth-pick-object").text
    cfg = load_config(None, TINY).agent
    assert cfg.pose_source == "odometry"
    rt = AgentRuntime("a", text, TaskParser().parse(text), cfg, annotations=ds.annotations,
                      task_id="synth-pick-object")
    try:
        rt.replay(_Spoiled(ds, 5))
        assert rt.wait_mapped(timeout_s=120)
        st = rt.status()
        assert st["frames_rejected"] == 1 and "odometry lost frame 5" in st["last_error"]
        assert st["frames_received"] == 14 and st["frames_mapped"] == 13
        mapped = {int(s.frame_id) for s in rt.mapper.stats}
        assert 5 not in mapped and len(mapped) == 13
        odo = rt.odometry
        assert odo.n_failed == 1 and odo.n_tracked == 13
        # the tracked poses stay near the given ones (the first frame's pose fixes the frame)
        assert np.linalg.norm(odo.last_pose[:3, 3] - ds[13].c2w[:3, 3]) < 0.25 < np.linalg.norm(ds[13].c2w[:3, 3])
    finally:
        rt.close()
