"""Finish's scoring and summary (gausslite.mission.scoring) and a replay's feeding thread (gausslite.mission.replay),
each on its own: the protocols a replay can be scored under, the summary's share and byte figures, the frames a
replay withholds from the mapper (still tracked by an odometry), and how a replay ends."""

from __future__ import annotations

import types

import numpy as np
import pytest

from gausslite.config import load_config
from gausslite.mission import scoring
from gausslite.mission.errors import MissionError
from gausslite.mission.progress import MissionProgress
from gausslite.mission.pusher import PushRecord
from gausslite.mission.replay import Replay
from gausslite.mission.state import MissionState
from gausslite.mission.tracking import MissionPoses
from tests._scenes import plane_frame


# ---------------------------------------------------------------------------------------------- scoring
class _Pusher:
    def __init__(self, pushes=()):
        self.pushes, self.final_push_ok = list(pushes), True
        self.final_subset_bytes, self.total_upload_bytes = 4000, 9000
        self.views = types.SimpleNamespace(sent_bytes=300, sent=3)

    def views_unsent(self):
        return 2


STATUS = {"n_gaussians": 200, "frames_mapped": 4, "seconds_mapping": 2.0}


def test_the_summary_reads_the_last_push_and_the_final_status():
    push = PushRecord(version=3, n_shared=50, n_total=200, bytes_on_wire=4000, n_chunks=1, keyframes=2, seconds=0.1)
    protocols = {"sensor": {"roi_psnr": 21.5}, "novel": {"roi_psnr": 18.0}}
    view = types.SimpleNamespace(c2w=np.eye(4), theta=np.zeros(6))
    s = scoring.summarise(dict(STATUS), _Pusher([push]), mapper=None, config=None, pushed=True, psnr=25.0,
                          roi_psnr=22.0, protocols=protocols, frames_all=12, tracked_views={7: view},
                          predicted_views={})
    assert (s.n_shared, s.share_pct, s.bytes_per_gaussian) == (50, 25.0, 80.0)
    assert s.final_push_ok and s.roi_psnr_all_frames == 21.5 and s.seconds_per_frame == 0.5 and s.frames_all == 12
    assert (s.view_bytes, s.views_sent, s.views_unsent, s.total_upload_bytes) == (300, 3, 2, 9000)
    assert s.pushes == [dict(push.__dict__)] and s.tracked_views == {7: view}
    d = s.as_dict()
    assert d["tracked_views"] == {7: {"c2w": np.eye(4).tolist(), "exposure": [0.0] * 6}} and d["protocols"] == protocols


def test_without_a_push_the_summary_counts_what_the_share_rule_would_send():
    gmap = types.SimpleNamespace(active=np.array([True, True, False, True]), kappa=np.array([0, 2, 3, 1]))
    cfg = load_config(None, ["agent.share.rule=active"]).agent
    s = scoring.summarise(dict(STATUS, n_gaussians=4), _Pusher(), types.SimpleNamespace(gmap=gmap), cfg,
                          pushed=False, psnr=None, roi_psnr=None, protocols={}, frames_all=0, tracked_views={},
                          predicted_views={})
    assert (s.n_shared, s.share_pct, s.bytes_per_gaussian) == (3, 75.0, 0.0)
    assert not s.final_push_ok and s.roi_psnr_all_frames is None
    empty = scoring.summarise(dict(STATUS, n_gaussians=0), _Pusher(), types.SimpleNamespace(gmap=gmap), cfg,
                              pushed=True, psnr=None, roi_psnr=None, protocols={}, frames_all=0, tracked_views={},
                              predicted_views={})
    assert empty.share_pct == 0.0


def test_protocols_of_withheld_frames_are_scored_only_when_frames_were_withheld(monkeypatch):
    import gausslite.evaluation as evaluation

    seen = {}

    def fake(mapper, frames, roi_fn, protocols, **kw):
        seen.update(protocols=protocols, frames=frames, kw=kw)
        return {p: {} for p in protocols}

    monkeypatch.setattr(evaluation, "score_live_map", fake)
    sc = load_config(None, ["agent.scoring.protocols=[sensor,novel,tracked]"]).agent.scoring
    ds = [plane_frame(i) for i in range(4)]
    out = scoring.score_protocols("mapper", ds, object(), "task", sc, 1.0)
    assert set(out) == {"sensor", "tracked"} and seen["kw"]["novel_ids"] is None
    scoring.score_protocols("mapper", ds, object(), "task", sc, 1.0, protocols=("sensor", "novel"),
                            novel_ids=frozenset({1}))
    assert seen["protocols"] == ("sensor", "novel") and seen["kw"]["novel_ids"] == frozenset({1})
    # at the odometry's poses: a frame without an estimate is not scored
    est = {0: np.eye(4), 2: np.eye(4)}
    scoring.score_protocols("mapper", ds, object(), "task", sc, 1.0, estimated_poses=est)
    frames = seen["frames"]
    assert [int(frames[i].frame_id) for i in range(len(frames))] == [0, 2]


# ---------------------------------------------------------------------------------------------- replay
def _replay(n=6, *overrides, T=None):
    cfg = load_config(None, list(overrides)).agent
    return Replay([plane_frame(i, 0.1 * i) for i in range(n)], cfg, T), cfg


def _feed(rp, cfg, *, submit=None, tracks=False, report=None):
    progress = MissionProgress()
    poses = MissionPoses(cfg, progress)
    tracked, sent, failures = [], [], []
    if tracks:
        poses.odometry, poses.track = object(), lambda fr, W=None: tracked.append(fr.frame_id)
    rp.start(submit=submit or (lambda fr: sent.append(fr.frame_id) or True), progress=progress, poses=poses,
             join=lambda: None, fail=failures.append, report=report)
    rp.wait()
    return types.SimpleNamespace(progress=progress, tracked=tracked, sent=sent, failures=failures)


def test_a_replay_withholds_every_kth_frame_from_the_mapper_and_reports_each_frame_sent():
    rp, cfg = _replay(6, "agent.scoring.novel_every=3", "agent.scoring.protocols=[sensor,novel]")
    assert rp.frames == 6 and rp.held == frozenset({1, 4}) and rp.novel_ids == frozenset({1, 4})
    reports = []
    r = _feed(rp, cfg, report=lambda i, n: reports.append((i, n)))
    assert r.sent == [0, 2, 3, 5] and reports == [(1, 4), (2, 4), (3, 4), (4, 4)]
    assert r.progress.state == MissionState.REPLAY_DONE and not rp.running
    # with an odometry the withheld frames are still tracked, in order
    rp, cfg = _replay(6, "agent.scoring.novel_every=3", "agent.scoring.protocols=[sensor,novel]")
    r = _feed(rp, cfg, tracks=True)
    assert r.sent == [0, 2, 3, 5] and r.tracked == [1, 4]


def test_a_replay_moves_its_frames_into_the_world_frame():
    T = np.eye(4)
    T[2, 3] = 5.0
    rp, _ = _replay(2, "agent.scoring.protocols=[sensor]", T=T)
    assert rp.novel_ids is None and rp.held == frozenset()  # nothing withheld by rule
    np.testing.assert_allclose(rp.dataset[1].c2w, T @ plane_frame(1, 0.1).c2w)


@pytest.mark.parametrize("error", [MissionError("mission m1 is failed"), OSError("unreadable frame 2")])
def test_a_replay_ends_quietly_when_the_mission_refuses_and_fails_it_on_a_bad_frame(error):
    rp, cfg = _replay(4)

    def submit(fr):
        if fr.frame_id == 2:
            raise error
        return True

    r = _feed(rp, cfg, submit=submit)
    assert r.progress.state == MissionState.MAPPING  # not done
    if isinstance(error, MissionError):
        assert r.failures == []
    else:
        assert r.failures == ["replay failed: OSError: unreadable frame 2"]


def test_a_stopped_mission_stops_its_replay_and_a_replay_not_started_waits_for_nothing():
    rp, cfg = _replay(4)
    rp.wait()
    progress = MissionProgress()
    progress.stop.set()
    sent = []
    rp.start(submit=sent.append, progress=progress, poses=MissionPoses(cfg, progress), join=lambda: None,
             fail=lambda msg: None)
    rp.wait()
    assert sent == [] and progress.state == MissionState.MAPPING
