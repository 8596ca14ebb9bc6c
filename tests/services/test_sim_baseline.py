"""``gausslite sim --baseline uniform``: matched uniform agents beside GaussLite's in the report."""

import pytest

from gausslite.team import attach_uniform_baseline, plot_fused_timeline, write_markdown


LIVE = {"frames_received": 150, "frames_keyframed": 20, "frames_skipped": 130, "accept_latency_ms_p99": 0.1,
        "keyframe_latency_s_p95": 0.6, "idle_iterations": 5, "keyframe_iterations": 200, "frames_all": 150,
        "offline_roi_psnr_all_frames": None}


def _report(mode: str, realtime: bool, own: float, all_frames: float, per_frame: bool = True) -> dict:
    def protocols(base: float) -> dict:
        if not per_frame:
            return {"sensor": {"roi_psnr": base}}
        frames = {str(i): base + 0.5 * (i % 3) for i in range(12)}
        return {"sensor": {"roi_psnr": base + 0.5, "roi_psnr_per_frame": frames},
                "novel": {"roi_psnr": base, "roi_psnr_per_frame": {k: v - 0.5 for k, v in frames.items() if int(k) % 4 == 1},
                          "pose": "predicted", "frames_scored": 3}}

    agents = [{"id": "agent_a", "task": "t-a", "roi_psnr": own, "roi_psnr_all_frames": all_frames, "psnr": 20.0,
               "n_gaussians": 6000, "n_shared": 10, "share_pct": 1.0, "bytes_per_gaussian": 12.0,
               "protocols": protocols(all_frames), **LIVE},
              {"id": "agent_b", "task": "t-b", "roi_psnr": own + 1, "roi_psnr_all_frames": all_frames + 1,
               "psnr": 21.0, "n_gaussians": 6000, "n_shared": 10, "share_pct": 1.0, "bytes_per_gaussian": 12.0,
               "protocols": protocols(all_frames + 1), **LIVE}]
    return {"scene": "s", "seconds": 1.0, "agents": agents, "realtime": realtime,
            "fused": {k: {"roi_psnr_per_task": {}, "roi_psnr_mean": None, "n_gaussians": 0, "seconds": 0.0}
                      for k in ("concat", "vote", "refine")},
            "settings": {"mapper": {"mode": mode}, "voxel_size": 0.1, "refine_iters": 0}}


@pytest.mark.parametrize("realtime", [True, False])
def test_uniform_baseline_gives_each_agent_its_task_gain(tmp_path, realtime):
    """GaussLite − uniform per protocol: the mean of the paired per-frame differences with its interval, the
    ``sensor`` one as the agent's ``task_gain_db``; a baseline without per-frame figures gives no gain."""
    rep = _report("gausslite", realtime, own=25.0, all_frames=23.0)
    base = _report("uniform", realtime, own=24.0, all_frames=21.5)
    attach_uniform_baseline(rep, base)
    a = rep["agents"][0]
    assert a["uniform_roi_psnr_all_frames"] == 21.5 and a["uniform_roi_psnr"] == 24.0
    assert a["task_gain_db"] == pytest.approx(1.5) and a["task_gain"]["n"] == 12
    assert a["gain_by_protocol"]["novel"]["gain"] == pytest.approx(1.5) and a["gain_by_protocol"]["novel"]["n"] == 3
    assert a["uniform_protocols"]["novel"] == 21.5
    write_markdown(rep, tmp_path / "report.md")
    md = (tmp_path / "report.md").read_text()
    assert "What the task buys" in md and "| agent_a | t-a | novel | 23.00 | 21.50 | +1.50 [+1.50, +1.50] |" in md
    old = _report("gausslite", realtime, own=25.0, all_frames=23.0)
    attach_uniform_baseline(old, _report("uniform", realtime, own=24.0, all_frames=21.5, per_frame=False))
    assert old["agents"][0]["task_gain_db"] is None  # nothing to pair: no gain invented


def test_uniform_baseline_refuses_a_mismatched_report():
    rep = _report("gausslite", True, 25.0, 23.0)
    with pytest.raises(ValueError, match="not 'uniform'"):
        attach_uniform_baseline(rep, _report("gausslite", True, 24.0, 21.0))
    other = _report("uniform", True, 24.0, 21.0)
    other["agents"][1]["task"] = "t-c"
    with pytest.raises(ValueError, match="no agent agent_b"):
        attach_uniform_baseline(rep, other)


class _FakeFusion:
    """Fusion client double: two agents whose versions advance as the test says; every vote fuse returns a map
    of as many Gaussians as the sum of the versions."""

    def __init__(self):
        self.versions = {}
        self.fuses = []
        self.team = None  # the served team map: (version, its subset versions, current), None before the first

    def stats(self):
        return {"agents": {a: {"latest_map_version": v, "has_complete_subset": v > 0} for a, v in self.versions.items()}}

    def fuse(self, method="vote", voxel_size=0.1, contest_radius=None, for_agent=None, team_map=False):
        from types import SimpleNamespace

        import grpc

        if team_map:
            if self.team is None:
                raise type("NotFound", (grpc.RpcError,), {"code": lambda s: grpc.StatusCode.NOT_FOUND,
                                                          "details": lambda s: "no team map yet"})()
            v, versions, current = self.team
            return SimpleNamespace(fused_version=v, map_versions=versions, team_map_current=current,
                                   refine_record={"iters_run": 5})
        self.fuses.append((method, voxel_size, contest_radius, for_agent))
        return SimpleNamespace(fused_version=len(self.fuses))

    def download_fused(self, version):
        from tests._fuzz import random_arrays

        return random_arrays(sum(self.versions.values()), version, extent=1.0)


def test_fused_timeline_fuses_after_each_new_subset_and_reaches_the_report(tmp_path, monkeypatch):
    from gausslite.team import scoring
    from gausslite_services import sim

    fusion = _FakeFusion()
    tl = sim.FusedTimeline(fusion, 0.1, 1)
    assert not tl.poll(0.0)  # nothing uploaded yet
    fusion.versions = {"agent_a": 1, "agent_b": 0}
    assert tl.poll(1.0) and not tl.poll(2.0)  # fused once; nothing new since
    fusion.versions = {"agent_a": 1, "agent_b": 1}
    assert tl.poll(3.0)
    # the team map, then the map for each robot with a subset
    assert fusion.fuses == [("vote", 0.1, 1, None), ("vote", 0.1, 1, "agent_a"),
                            ("vote", 0.1, 1, None), ("vote", 0.1, 1, "agent_a"), ("vote", 0.1, 1, "agent_b")]
    assert [(t, v) for t, v, _, _ in tl.maps] == [(1.0, {"agent_a": 1}), (3.0, {"agent_a": 1, "agent_b": 1})]
    scored = []
    monkeypatch.setattr(scoring, "evaluate_fused_frames",
                        lambda g, frames, ann, task, backend="auto": scored.append((len(g), len(frames)))
                        or {int(i): 20.0 + len(g) for i in frames})

    class _DS:
        annotations = None

    out = tl.scores({"t-a": (_DS, list(range(12))), "t-b": (_DS, list(range(12)))}, stride=5,
                    task_of={"agent_a": "t-a", "agent_b": "t-b"})
    assert [e["n_gaussians"] for e in out] == [1, 2] and out[1]["roi_psnr"] == {"t-a": 22.0, "t-b": 22.0}
    assert out[0]["roi_psnr_for_robot"] == {"t-a": 21.0} and out[1]["roi_psnr_for_robot"] == {"t-a": 22.0, "t-b": 22.0}
    assert scored[0] == (1, 3)  # every fifth frame
    rep = _report("gausslite", True, own=25.0, all_frames=23.0)
    rep["fused_timeline"] = out
    assert plot_fused_timeline(rep, tmp_path / "t.png") and (tmp_path / "t.png").stat().st_size > 0
    rep["fused_timeline_plot"] = "t.png"
    write_markdown(rep, tmp_path / "report.md")
    md = (tmp_path / "report.md").read_text()
    assert "The fused map while mapping" in md and "| 3 | agent_a v1, agent_b v1 | 2 | 22.00 | 22.00 | 22.00 | 22.00 |" in md
    assert "| 1 | agent_a v1 | 1 | 21.00 | 21.00 | 21.00 | – |" in md
    assert "![fused ROI PSNR over time](t.png)" in md
    # the served team map: a row when a new version is served, then when it turns current; none before it exists
    assert all(m[3] is None for m in tl.maps)
    fusion.team = (50, {"agent_a": 1, "agent_b": 1}, True)
    assert tl.poll(3.5) and tl.maps[-1][3] == (50, True) and not tl.poll(3.6)
    fusion.team = (50, {"agent_a": 1, "agent_b": 1}, False)
    assert tl.poll(3.7) and tl.maps[-1][3] == (50, False)
    rows = tl.scores({"t-a": (_DS, list(range(12))), "t-b": (_DS, list(range(12)))}, stride=5,
                     task_of={"agent_a": "t-a", "agent_b": "t-b"})
    s = rows[-1]["served"]
    assert s["version"] == 50 and not s["current"] and s["versions"] == {"agent_a": 1, "agent_b": 1}
    assert s["made_t"] == 3.5 and s["roi_psnr"]["t-a"] == 20.0 + s["n_gaussians"] and rows[0]["served"] is None
    # each served map's frames, the pairs of its gain over a robot's own map
    assert s["roi_psnr_per_frame"]["t-a"] == {0: 20.0 + s["n_gaussians"], 5: 20.0 + s["n_gaussians"],
                                              10: 20.0 + s["n_gaussians"]}
    # a failing fuse is logged and skipped, not raised
    fusion.versions = {"agent_a": 2, "agent_b": 1}
    fusion.fuse = lambda *a, **k: (_ for _ in ()).throw(RuntimeError("server gone"))
    assert not tl.poll(4.0) and len(tl.maps) == 4


def test_live_sims_fuse_with_the_paper_per_voxel_rule_and_offline_sims_with_the_neighbourhood():
    from gausslite.config import load_config
    from gausslite_services.sim import fuse_settings

    cfg = load_config()  # deploy/gausslite.yaml
    assert fuse_settings(cfg) == {"voxel_size": 0.10, "contest_radius": 1, "refine_iters": 300}
    assert fuse_settings(cfg, realtime=True)["contest_radius"] == 0
    assert fuse_settings(load_config(None, ["sim.fuse.contest_radius=2"]), realtime=True)["contest_radius"] == 0
    # the deployed agents share with the live rule
    agent = cfg.agent
    assert agent.share.rule == "task" and agent.share.candidates == "rendered" and agent.share.max_fraction == 0.25
