"""The agent's Prometheus metrics report both mapping resolutions and the iterations keyframes got
(services/agent/metrics.py; docs/fusion-and-deploy.md, "Metrics"), read from the mission's status at scrape time."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from gausslite.mapping.resolution import ResolutionGovernor
from gausslite_services.agent.metrics import agent_registry


class _Mission:
    """A mission as the collector reads it: ``status()`` and the pusher's push records."""

    def __init__(self, status: dict) -> None:
        self._status = status
        self.pusher = SimpleNamespace(pushes=[])

    def status(self) -> dict:
        return self._status


def test_the_metrics_report_both_levels_and_the_recent_iterations():
    g = ResolutionGovernor(target_iters=10, adapt_after=2, min_width=64, roi_target_iters=6)
    g.start(640, 480, 0.5, 6000, region=True)
    for iters, roi in ((10, 6), (12, 7), (11, None), (13, 5)):
        g.record(iters, roi)
    st = {"agent_id": "a", "state": "MAPPING", "frames_received": 4, "frames_mapped": 4, "push_failures": 0,
          "keyframes_uploaded": 0, "frames_queued": 0, "n_gaussians": 10, "n_active": 2, "push_backlog": 0,
          "link_down_s": 0.0, **g.status()}
    reg = agent_registry(SimpleNamespace(missions={"m": _Mission(st)}, current="m"))

    def value(name: str) -> float:
        return reg.get_sample_value(name, {"agent": "a"})

    assert (value("gausslite_agent_mapping_width_pixels"), value("gausslite_agent_mapping_height_pixels"),
            value("gausslite_agent_mapping_downscale")) == (320, 240, 2.0)
    assert (value("gausslite_agent_region_width_pixels"), value("gausslite_agent_region_height_pixels"),
            value("gausslite_agent_region_downscale")) == (640, 480, 1.0)
    assert value("gausslite_agent_keyframe_iterations_recent") == pytest.approx(12.0)  # the first is not counted
    assert value("gausslite_agent_roi_iterations_recent") == pytest.approx(6.0)  # keyframes that showed the region
    assert value("gausslite_agent_keyframe_iterations_measured") == pytest.approx(12.0)
