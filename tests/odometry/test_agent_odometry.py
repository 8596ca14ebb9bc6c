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

TINY = ["agent.push.every=100", "agent.idle_chunk_s=0.05", "mapper.iters_per_frame=3", "mapper.warmup_iters=1",
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
    make_scene(tmp_path, seed=0, width=96, height=72, frames=14, progress=False, agents=("agent_a",))
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
        # the frame after the lost one is found again by re-localisation against the keyframes
        assert st["frames_lost"] == 1 and st["frames_relocalised"] == 1 and st["loop_closures"] == 0
        assert st["frames_received"] == 14 and st["frames_mapped"] == 13
        mapped = {int(s.frame_id) for s in rt.mapper.stats}
        assert 5 not in mapped and len(mapped) == 13
        odo = rt.odometry
        assert odo.n_failed == 1 and odo.n_tracked == 13
        # the tracked poses stay near the given ones (the first frame's pose fixes the frame)
        assert np.linalg.norm(odo.last_pose[:3, 3] - ds[13].c2w[:3, 3]) < 0.25 < np.linalg.norm(ds[13].c2w[:3, 3])
    finally:
        rt.close()


def test_withheld_frames_are_tracked_not_mapped_and_the_map_is_scored_at_the_estimated_poses(tmp_path, monkeypatch):
    """A robot's odometry tracks every frame, the ones withheld from the mapper too: ``novel`` scores those at their
    estimated pose (with the map's learned correction), and every protocol starts from the estimates, with the ROI
    of the given poses."""
    import gausslite.evaluation as evaluation

    make_scene(tmp_path, seed=0, width=96, height=72, frames=14, progress=False, agents=("agent_a",))
    ds = load_dataset(tmp_path / "agent_a")
    text = ds.annotations.task_by_id("synth-pick-object").text
    cfg = load_config(None, [*TINY, "agent.scoring.protocols=[sensor,novel]", "agent.scoring.novel_every=4"]).agent
    rt = AgentRuntime("a", text, TaskParser().parse(text), cfg, annotations=ds.annotations,
                      task_id="synth-pick-object")
    seen = {}
    real = evaluation.score_live_map

    def spy(mapper, frames, roi_fn, *a, **kw):
        seen["poses"] = {int(f.frame_id): f.c2w.copy() for f in frames}
        seen["roi"] = {int(f.frame_id): roi_fn(f) for f in frames}
        return real(mapper, frames, roi_fn, *a, **kw)

    monkeypatch.setattr(evaluation, "score_live_map", spy)
    try:
        rt.replay(ds)
        assert rt.wait_mapped(timeout_s=120)
        held = {int(ds[i].frame_id) for i in (2, 6, 10)}
        mapped = {int(s.frame_id) for s in rt.mapper.stats}
        assert mapped.isdisjoint(held) and len(mapped) == 11
        # every frame tracked, the withheld ones too, in order: the odometry's count and the recorded estimates
        assert rt.odometry.n_tracked == 14 and set(rt.estimated_poses) == {int(f.frame_id) for f in ds}
        assert rt.status()["frames_received"] == 11
        res = rt.evaluate_protocols()
        assert res["novel"]["frames_scored"] == 3 and res["sensor"]["frames_scored"] == 14
        for fid, c2w in seen["poses"].items():
            np.testing.assert_allclose(c2w, rt.estimated_poses[fid])
        moved = [fid for fid in held if np.linalg.norm(rt.estimated_poses[fid][:3, 3] - ds[fid].c2w[:3, 3]) > 1e-6]
        assert moved  # estimates, not the given poses
        # the ROI is the image's ground truth: the mask of the given pose
        f = ds[6]
        np.testing.assert_array_equal(seen["roi"][int(f.frame_id)],
                                      ds.annotations.roi_mask("synth-pick-object", f.depth, f.c2w, f.intrinsics))
    finally:
        rt.close()
