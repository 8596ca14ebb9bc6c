"""The agent's Finish scoring of a replay: ``novel`` scores each withheld frame at the pose and exposure the final map
predicts (nothing fitted), ``novel-tracked`` at a pose tracked against it, and both views travel with the summary
(``predicted_views``, ``tracked_views``) so that the simulation scores a team map at the same views."""

from __future__ import annotations

import numpy as np

from gausslite.config import load_config
from gausslite.datasets import load_dataset
from gausslite.evaluation import predicted_view
from gausslite.mission import AgentRuntime
from gausslite.parser import TaskParser
from gausslite.synthetic import make_scene
from gausslite_rpc import agent_pb2, common_pb2
from gausslite_services.sim.summary import summary_from_proto
from tests._waits import WORK_S

TINY = ["agent.push.every=2", "agent.upload_keyframe_every=1", "agent.idle_chunk_s=0.05", "mapper.iters_per_frame=3",
        "mapper.warmup_iters=1", "mapper.seeding.seeds_per_frame=200", "agent.scoring.novel_every=3",
        "agent.scoring.track_iters=2", "mapper.pose.refine=true", "mapper.sensor.exposure_comp=true"]


def test_finish_scores_withheld_frames_at_the_predicted_view_and_sends_both_views(tmp_path):
    make_scene(tmp_path, seed=0, width=64, height=48, frames=6, progress=False)
    ds = load_dataset(tmp_path / "agent_a")
    text = ds.annotations.task_by_id("synth-pick-object").text
    cfg = load_config(None, TINY).agent
    rt = AgentRuntime("a", text, TaskParser().parse(text), cfg, annotations=ds.annotations,
                      task_id="synth-pick-object")
    try:
        rt.replay(ds)
        s = rt.finish(push=False, timeout_s=WORK_S)
        withheld = {int(ds[i].frame_id) for i in (1, 4)}  # every 3rd frame from the 2nd
        assert {int(st.frame_id) for st in rt.mapper.stats}.isdisjoint(withheld)
        p = s.protocols
        assert set(p["novel"]["roi_psnr_per_frame"]) <= withheld and p["novel"]["frames_scored"] == 2
        assert p["novel-tracked"]["frames_scored"] == 2 and p["novel"]["pose"] == "predicted"
        # novel: the final map's own prediction of each withheld frame, exactly; nothing fitted on the frame
        assert set(s.predicted_views) == withheld
        for i in (1, 4):
            want = predicted_view(rt.mapper, ds[i])
            got = s.predicted_views[int(ds[i].frame_id)]
            assert np.array_equal(got.c2w, want.c2w) and np.array_equal(got.theta, want.theta) and got.iters == 0
        # novel-tracked and tracked: fitted against the map
        assert withheld <= set(s.tracked_views) and all(s.tracked_views[i].iters > 0 for i in withheld)
        d = s.as_dict()
        assert set(d["predicted_views"]) == withheld and len(d["predicted_views"][1]["c2w"]) == 4
    finally:
        rt.close()
    # over the wire: the sim reads both kinds of view back from the Finish summary
    msg = agent_pb2.MissionSummary(
        predicted_views=[agent_pb2.TrackedPose(frame_id=i, pose=common_pb2.Pose(c2w=v.c2w.reshape(-1).tolist()),
                                               exposure=v.theta.tolist()) for i, v in s.predicted_views.items()],
        protocols={"novel": agent_pb2.ProtocolScore(roi_psnr_per_frame={1: 20.5})})
    back = summary_from_proto(msg).predicted_views
    assert set(back) == withheld and not summary_from_proto(msg).tracked_views
    assert all(np.array_equal(back[i].c2w, s.predicted_views[i].c2w) for i in withheld)
    assert dict(msg.protocols["novel"].roi_psnr_per_frame) == {1: 20.5}
