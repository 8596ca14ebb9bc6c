"""bench.realtime: the paper's real-time protocol (matched binding cap, no final pass, the keyframe schedule of
the budget twin, the summary's paired gain and the budget at which uniform catches up)."""

import math

import pytest

from bench import realtime as rt


class _Frames:
    def __init__(self, ts):
        self.ts = ts

    def __len__(self):
        return len(self.ts)

    def __getitem__(self, i):
        from types import SimpleNamespace

        return SimpleNamespace(timestamp=self.ts[i])


def test_keyframe_schedule_takes_the_first_frame_at_every_spacing():
    ds = _Frames([10.0 + i / 15.0 for i in range(31)])  # 2 s at 15 Hz
    kf = rt.keyframe_schedule(ds, 0.5)
    assert kf[0] == 0 and len(kf) == 5
    assert all(ds[i].timestamp - 10.0 >= 0.5 * k - 1e-9 for k, i in enumerate(kf))
    assert rt.keyframe_schedule(ds, 0.05) == list(range(31))  # spacing below the frame period: every frame


def test_agent_config_matches_the_cap_and_drops_the_final_pass():
    from gausslite.mapping.profiles import HANDHELD

    for mode in ("uniform", "gausslite"):
        cfg, fp = rt.agent_config(mode, 0.5, 6000, 1, 2.0, HANDHELD)
        m = cfg.mapper
        assert (m.mode, m.budget.max_gaussians, m.keyframe_budget_s, m.seed) == (mode, 6000, 0.5, 1)
        assert m.final_iters == 0 and m.final_iters_per_keyframe == 0.0
        assert fp == HANDHELD.mapper["final_iters_per_keyframe"]  # the final-pass column uses the profile's
        assert cfg.realtime and cfg.rate == 2.0
        assert m.pose.refine and m.sensor.rolling_shutter_s > 0  # the sensor profile applies to both modes


def test_twin_reaches_the_same_binding_cap_in_both_modes_and_is_deterministic(tmp_path):
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=8, width=64, height=48, trajectory="circle")
    path = tmp_path / "scene" / "agent_a"
    job = {"scene": "synthetic_circle", "path": str(path), "task": "synth-pick-object", "budget": 0.08, "run": 0,
           "cap": 300, "clock": "dataset", "overrides": ["mapper.seeds_per_frame=600"]}
    runs = {mode: rt.twin_one({**job, "mode": mode}) for mode in ("uniform", "gausslite")}
    for mode, r in runs.items():
        assert r["cap_reached"] and 0.9 * 300 <= r["n_gaussians"] <= 300, mode  # the cap binds (less what pruning took)
        assert r["keyframes"] == len(rt.keyframe_schedule(rt.Preloaded(rt.load_scene("synthetic_circle", path)[0]),
                                                           0.08))
        assert r["frames_scored"] == 8 and r["roi_psnr"] is not None
    assert runs["gausslite"]["roi_iters"] > 0 and runs["uniform"]["roi_iters"] == 0
    again = rt.twin_one({**job, "mode": "gausslite"})
    assert again["roi_psnr"] == runs["gausslite"]["roi_psnr"]
    assert again["keyframe_iters"] == runs["gausslite"]["keyframe_iters"]


def _run(mode, b, run, roi):
    return {"scene": "s", "mode": mode, "budget": b, "run": run, "roi_psnr": roi, "psnr": 20.0, "ssim": 0.7,
            "n_gaussians": 100, "iters_per_keyframe": 5.0, "keyframes": 20, "idle_iters": 0, "roi_iters": 0}


def test_summary_pairs_runs_and_finds_the_budget_uniform_needs():
    runs = []
    for run in range(3):
        for b, u in ((0.25, 20.0), (0.5, 21.0), (1.0, 22.0), (2.0, 23.0)):
            runs.append(_run("uniform", b, run, u + 0.1 * run))
            runs.append(_run("gausslite", b, run, u + 1.5 + 0.1 * run))
    s = rt.summarise(runs, "s", [0.25, 0.5, 1.0, 2.0], 100)
    blk = s["budgets"]["0.5"]
    assert blk["gain"] == pytest.approx(1.5) and blk["gain_std"] == pytest.approx(0.0, abs=1e-9)
    assert blk["uniform"]["roi_psnr"] == pytest.approx(21.1) and blk["uniform"]["runs"] == 3
    # GaussLite at 0.5 s: 22.6 dB; uniform reaches it between 1 s (22.1) and 2 s (23.1), halfway on a log axis
    assert s["uniform_budget_matching_gausslite_0.5"] == pytest.approx(math.sqrt(2.0), rel=1e-6)
    md = rt.table({"scenes": {"s": s}})
    assert "| s | 100 | 0.5 | gausslite |" in md
