"""``gausslite sim --baseline uniform``: matched uniform agents beside GaussLite's in the report."""

import pytest

from services.sim import attach_uniform_baseline, write_markdown


LIVE = {"frames_received": 150, "frames_keyframed": 20, "frames_skipped": 130, "accept_latency_ms_p99": 0.1,
        "keyframe_latency_s_p95": 0.6, "idle_iterations": 5, "keyframe_iterations": 200, "frames_all": 150,
        "offline_roi_psnr_all_frames": None}


def _report(mode: str, realtime: bool, own: float, all_frames: float) -> dict:
    agents = [{"id": "agent_a", "task": "t-a", "roi_psnr": own, "roi_psnr_all_frames": all_frames, "psnr": 20.0,
               "n_gaussians": 6000, "n_shared": 10, "share_pct": 1.0, "bytes_per_gaussian": 12.0, **LIVE},
              {"id": "agent_b", "task": "t-b", "roi_psnr": own + 1, "roi_psnr_all_frames": all_frames + 1,
               "psnr": 21.0, "n_gaussians": 6000, "n_shared": 10, "share_pct": 1.0, "bytes_per_gaussian": 12.0, **LIVE}]
    return {"scene": "s", "seconds": 1.0, "agents": agents, "realtime": realtime,
            "fused": {k: {"roi_psnr_per_task": {}, "roi_psnr_mean": None, "n_gaussians": 0, "seconds": 0.0}
                      for k in ("concat", "vote", "refine")},
            "settings": {"mapper": {"mode": mode}, "voxel_size": 0.1, "refine_iters": 0}}


@pytest.mark.parametrize("realtime", [True, False])
def test_uniform_baseline_gives_each_agent_its_task_gain(tmp_path, realtime):
    rep = _report("gausslite", realtime, own=25.0, all_frames=23.0)
    base = _report("uniform", realtime, own=24.0, all_frames=21.5)
    attach_uniform_baseline(rep, base)
    a = rep["agents"][0]
    assert a["uniform_roi_psnr_all_frames"] == 21.5 and a["uniform_roi_psnr"] == 24.0
    assert a["task_gain_db"] == pytest.approx(1.5 if realtime else 1.0)
    write_markdown(rep, tmp_path / "report.md")
    md = (tmp_path / "report.md").read_text()
    assert "What the task buys" in md and ("| 1.50 |" if realtime else "| 1.00 |") in md


def test_uniform_baseline_refuses_a_mismatched_report():
    rep = _report("gausslite", True, 25.0, 23.0)
    with pytest.raises(ValueError, match="not 'uniform'"):
        attach_uniform_baseline(rep, _report("gausslite", True, 24.0, 21.0))
    other = _report("uniform", True, 24.0, 21.0)
    other["agents"][1]["task"] = "t-c"
    with pytest.raises(ValueError, match="no agent agent_b"):
        attach_uniform_baseline(rep, other)
