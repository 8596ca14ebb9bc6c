"""The live agent's mapping resolutions (docs/live.md, "Mapping resolution"): it hands the mapper the keyframe at the
task region's resolution (a DetailView) only with the detail layer on, and reports both levels in its status, which
the MissionStatus message carries field for field."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.config import load_config
from gausslite.mapping.detail import DetailView
from gausslite.mapping.mapper import FrameStats
from gausslite.mapping.resolution import nearest_mask
from gausslite.mission import AgentRuntime
from gausslite_rpc import agent_pb2
from tests._scenes import plane_frame
from tests._waits import WORK_S

GRAPH = {"targets": ["object"], "anchors": [], "relations": []}


@pytest.mark.parametrize("enabled", [False, True])
def test_the_agent_hands_the_mapper_a_detail_view_only_with_the_detail_layer(enabled):
    cfg = load_config(None, ["agent.ingest=every_frame", "agent.push.every=1000", "mapper.mode=gausslite",
                             "mapper.keyframe_budget_s=0.5", "agent.resolution.downscale=2",
                             "agent.resolution.min_width=16", f"mapper.detail.enabled={str(enabled).lower()}"]).agent
    region = np.zeros((24, 32), bool)
    region[6:18, 8:24] = True
    rt = AgentRuntime("d", "Pick up the object", GRAPH, cfg,
                      relevance_fn=lambda fr: nearest_mask(region, fr.depth.shape))
    calls = []

    def fake_map_frame(frame, relevance=None, time_budget_s=None, between=(), **kw):  # no mapping: what it is given
        calls.append((frame.intrinsics.width, relevance.shape, kw))
        return FrameStats(frame.frame_id, 0.01, 0, 0, 0, 0.0, 4, iters=9, detail_px=0)

    rt.mapper.map_frame = fake_map_frame
    try:
        for i in range(3):
            rt.submit(plane_frame(i, 0.1 * i, 48, 64))
        assert rt.wait_mapped(WORK_S)
        st = rt.status()
    finally:
        rt.close()
    assert len(calls) == 3 and {c[:2] for c in calls} == {(32, (24, 32))}  # the background at 32x24 either way
    details = [c[2].get("detail") for c in calls]
    assert (st["mapping_width"], st["mapping_downscale"], st["keyframe_iters_recent"]) == (32, 2.0, 9.0)
    if enabled:
        assert all(isinstance(d, DetailView) for d in details)
        assert {(d.frame.intrinsics.width, d.relevance.shape) for d in details} == {(64, (48, 64))}
        assert [d.frame.frame_id for d in details] == [0, 1, 2]
        assert (st["region_width"], st["region_height"], st["region_downscale"], st["region_detail"]) == (
            64, 48, 1.0, True)
    else:
        assert all("detail" not in c[2] for c in calls)  # the mapper is called exactly as without the layer
        assert (st["region_width"], st["region_downscale"], st["region_detail"]) == (32, 2.0, False)
    msg = agent_pb2.MissionStatus(**{k: v for k, v in st.items() if k != "state"})  # every status key is a field
    assert (msg.region_width, msg.keyframe_iters_recent) == (st["region_width"], 9.0)
