"""The in-memory fusion sides (gausslite.mission.fakes): the recording store holds what the fusion server holds
after full and delta pushes, and keeps the newest keyframes within the server's bound."""

from __future__ import annotations

import numpy as np

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.mission.fakes import RecordingFusion
from gausslite.wire.codec import GaussianArrays
from gausslite.wire.delta import PushPlanner
from tests._fuzz import random_arrays


def test_recording_fusion_holds_what_the_server_holds_after_full_and_delta_pushes():
    planner = PushPlanner("a", chunk_gaussians=64)
    sink = RecordingFusion()
    ids = np.arange(200)
    cur = random_arrays(200, 0, extent=1.0)
    p1 = planner.plan(ids, cur, 1)
    sink.upload_chunks("a", 1, p1.chunks)
    planner.acknowledge(p1)
    nxt = GaussianArrays(**{k: np.array(getattr(cur, k), copy=True) for k in GaussianArrays.FIELDS})
    nxt.means[:10] += 0.02
    keep = np.ones(200, bool)
    keep[50:60] = False
    nxt = GaussianArrays.concat([nxt.take(keep), random_arrays(30, 7, extent=1.0)])
    p2 = planner.plan(np.concatenate([ids[keep], 1000 + np.arange(30)]), nxt, 2, measure_full=False)
    assert p2.is_delta
    sink.upload_chunks("a", 2, p2.chunks)
    assert sink.subsets[1].equals(p1.subset) and sink.subsets[2].equals(p2.subset)
    assert [v for _, v, _ in sink.history] == [1, 2] and sink.history[0][0] <= sink.history[1][0]
    assert sink.uploads == 2 and sink.bytes == sum(len(c) for c in p1.chunks + p2.chunks)


def test_recording_fusion_keeps_the_newest_keyframes_within_the_servers_bound():
    K = np.array([[50.0, 0, 16], [0, 50.0, 12], [0, 0, 1]])
    frames = [Frame(i, float(i), np.zeros((24, 32, 3), np.uint8), np.ones((24, 32), np.float32), np.eye(4),
                    Intrinsics.from_K(K, 32, 24)) for i in range(5)]
    sink = RecordingFusion(max_keyframes=3)
    roi = np.zeros((24, 32), bool)
    assert sink.upload_keyframes("a", frames[:2], rois=[roi, None]) == 2
    assert sink.upload_keyframes("a", frames[2:]) == 3
    assert sorted(sink.keyframes) == [2, 3, 4]
    assert sink.keyframes[2].roi is None and sink.keyframes[4].width == 32
