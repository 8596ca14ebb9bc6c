"""bench.realtime: the paper's real-time protocol (matched binding cap, no final pass, the keyframe schedule of
the budget twin, the summary's paired gain and the budget at which uniform catches up)."""

import math
from pathlib import Path

import numpy as np
import pytest

from bench import realtime as rt
from bench.realtime.late import give_late_task, late_index


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
           "cap": 300, "clock": "dataset", "overrides": ["mapper.seeding.seeds_per_frame=600"]}
    runs = {mode: rt.twin_one({**job, "mode": mode}) for mode in ("uniform", "gausslite")}
    for mode, r in runs.items():
        assert r["cap_reached"] and 0.9 * 300 <= r["n_gaussians"] <= 300, mode  # the cap binds (less what pruning took)
        assert r["keyframes"] == len(rt.keyframe_schedule(rt.Preloaded(rt.load_scene(rt.SCENES["synthetic_circle"], path)[0]),
                                                           0.08))
        assert r["frames_scored"] == 8 and r["roi_psnr"] is not None
    assert runs["gausslite"]["roi_iters"] > 0 and runs["uniform"]["roi_iters"] == 0
    for mode, r in runs.items():  # the settings the mission ran with
        m = r["mission"]
        assert (m["mode"], m["keyframe_budget_s"], m["max_gaussians"], m["seed"]) == (mode, 0.08, 300, 0), mode
        assert m["render_threads"] == 2 and m["pose_source"] == "given" and m["budget_clock"] == "work"
        assert m["mapping_size"] == [64 / m["mapping_downscale"], 48 / m["mapping_downscale"]]
        assert m["native_size"] == [64, 48] and m["iters_per_keyframe"] == r["iters_per_keyframe"] > 0
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


def _proto_run(mode, b, run, roi, protos, frames=None):
    """A run with each protocol's ROI PSNR; with ``frames`` (frame id → offset) also its per-frame figures."""
    r = _run(mode, b, run, roi)
    r["protocols"] = {p: {"roi_psnr": v, "psnr": 20.0 + 0.1 * run, "ssim": 0.7, "frames_scored": 30}
                      for p, v in protos.items()}
    if frames is not None:
        for p, v in protos.items():
            r["protocols"][p]["roi_psnr_per_frame"] = {str(i): v + d for i, d in frames.items()}
            r["protocols"][p]["psnr_per_frame"] = {str(i): 20.0 + 0.1 * run for i in frames}
    return r


def test_summary_reports_every_protocol_with_its_paired_gain_and_matching_budget():
    """Runs without per-frame figures (an older partial file): the gain pairs run by run; their ``novel`` (then
    tracked against the map) reads as ``novel-tracked``."""
    runs = []
    for run in range(3):
        for b, u in ((0.25, 20.0), (0.5, 21.0), (1.0, 22.0), (2.0, 23.0)):
            runs.append(_proto_run("uniform", b, run, u, {"sensor": u, "tracked": u + 1.0, "keyframes": u + 2.0,
                                                          "novel": u + 0.5}))
            runs.append(_proto_run("gausslite", b, run, u + 0.5,
                                   {"sensor": u + 0.5, "tracked": u + 3.0 + 0.1 * run, "keyframes": u + 5.0,
                                    "novel": u + 1.0}))
    s = rt.summarise(runs, "s", [0.25, 0.5, 1.0, 2.0], 100)
    p = s["budgets"]["0.5"]["protocols"]
    assert set(p) == {"sensor", "tracked", "keyframes", "novel-tracked"}
    assert p["tracked"]["gain"] == pytest.approx(2.1) and p["tracked"]["runs"] == 3
    assert p["tracked"]["gain_std"] == pytest.approx(0.1) and p["tracked"]["gain_significant"]
    assert p["tracked"]["gain_pairs"] == "runs" and p["tracked"]["gain_ci"] is None
    assert p["tracked"]["uniform"]["roi_psnr"] == pytest.approx(22.0)
    assert p["keyframes"]["gain"] == pytest.approx(3.0)
    # GaussLite tracked at 0.5 s: 24.1 dB; uniform tracked reaches it between 1 s (23) and 2 s (24.0): beyond 2 s
    by = s["uniform_budget_matching_gausslite_0.5_by_protocol"]
    assert by["tracked"] is None and by["sensor"] == pytest.approx(0.5 ** 0.5, rel=1e-6)  # 21.5 dB: halfway
    md = rt.protocol_table({"scenes": {"s": s}})
    assert "| s | 0.5 | tracked | 22.00 ± 0.00 | 24.10 ± 0.10 | 2.10 ± 0.10 (runs)* |" in md


RUN_SHIFT = (0.0, 0.3, -0.3)  # each run's own gain offset: 1.0, 1.3 and 0.7 dB


def _per_frame_runs(frames: dict, resolution=lambda mode, run: 1.0) -> list:
    """Three runs of both modes with per-frame figures: GaussLite 1 dB + the run's shift above uniform on every
    frame, ±0.4 dB of frame noise that cancels within each run; ``resolution(mode, run)``: its mapping downscale."""
    runs = []
    for run in range(3):
        jitter = {i: d + (0.4 if (i + run) % 2 else -0.4) for i, d in frames.items()}
        for r in (_proto_run("uniform", 0.5, run, 21.0, {"sensor": 21.0, "novel": 21.0}, frames),
                  _proto_run("gausslite", 0.5, run, 22.0 + RUN_SHIFT[run],
                             {"sensor": 22.0 + RUN_SHIFT[run], "novel": 22.0 + RUN_SHIFT[run]}, jitter)):
            r["protocols"]["novel"]["pose"] = "predicted"  # as score_live_map writes it
            r["mapping_downscale"] = resolution(r["mode"], run)
            runs.append(r)
    return runs


def test_the_gain_pairs_frames_within_each_run_with_a_run_clustered_interval():
    """Runs with per-frame figures: GaussLite − uniform pairs frame by frame within each seed; the interval is the
    t-interval over the three per-run gains (1.0, 1.3, 0.7 dB), not over the 60 frame pairs pooled, which the
    frames' ±0.4 dB noise would make look far more precise than three runs are."""
    from scipy import stats

    frames = {i: 0.3 * (i % 5) for i in range(20)}  # the frames' own spread, shared by both maps
    s = rt.summarise(_per_frame_runs(frames), "s", [0.5], 100)
    blk = s["budgets"]["0.5"]
    p = blk["protocols"]["novel"]
    lo, hi = stats.t.interval(0.95, 2, loc=1.0, scale=stats.sem([1.0, 1.3, 0.7]))
    assert p["gain"] == pytest.approx(1.0) and p["gain_frames"] == 60 and p["gain_pairs"] == "frames"
    assert p["gain_interval"] == "run-clustered" and p["gain_runs"] == 3
    assert p["gain_per_run"] == [pytest.approx(1.0), pytest.approx(1.3), pytest.approx(0.7)]
    assert p["gain_ci"] == [pytest.approx(lo), pytest.approx(hi)] and p["gain_std"] == pytest.approx(0.3)
    assert p["gain_significant"] and blk["gain"] == pytest.approx(1.0) and blk["gain_interval"] == "run-clustered"
    assert hi - lo > 1.4  # what three runs support; pooled over 60 frame pairs it was a quarter of that
    md = rt.protocol_table({"scenes": {"s": s}})
    assert f"| s | 0.5 | novel | 21.00 ± 0.00 | 22.00 ± 0.30 | +1.00 [{lo:+.2f}, {hi:+.2f}]* (σ runs 0.30)" in md
    assert "run-clustered" in md


def test_runs_mapped_at_different_resolutions_are_never_paired(caplog):
    """Each map is scored at its own mapping resolution, so a GaussLite run at half the resolution of its uniform
    twin would measure the resolution: that run is left out of every gain, with its reason logged and recorded."""
    frames = {i: 0.3 * (i % 5) for i in range(20)}
    runs = _per_frame_runs(frames, lambda mode, run: 2.0 if (mode, run) == ("gausslite", 1) else 1.0)
    with caplog.at_level("WARNING", logger="bench.realtime"):
        blk = rt.summarise(runs, "s", [0.5], 100)["budgets"]["0.5"]
    p = blk["protocols"]["novel"]
    assert [u["run"] for u in p["unpaired_runs"]] == [1] and "different resolutions" in p["unpaired_runs"][0]["reason"]
    assert [u["run"] for u in blk["unpaired_runs"]] == [1]
    assert p["gain_runs"] == 2 and p["gain_frames"] == 40 and p["gain_per_run"] == [pytest.approx(1.0),
                                                                                    pytest.approx(0.7)]
    assert p["gausslite"]["runs"] == 3  # each mode's own means keep every run
    assert "run 1 not paired" in caplog.text
    # the same factor but a different mapped size (or a mid-mission change) is a different resolution too
    g, u = {0: {"mapping_downscale": 2.0, "mission": {"mapping_size": [320, 240], "resolution_changes": 0}}}, \
        {0: {"mapping_downscale": 2.0, "mission": {"mapping_size": [320, 240], "resolution_changes": 1}}}
    assert rt.pairable_runs(g, u, [0])[0] == []
    u[0]["mission"]["resolution_changes"] = 0
    assert rt.pairable_runs(g, u, [0]) == ([0], [])
    assert rt.pairable_runs(g, {0: {}}, [0])[0] == []  # no factor recorded: the scene's own resolution, 1


def test_when_no_run_pairs_the_cell_gives_the_unpaired_difference_with_its_welch_interval():
    """Under load both modes can end at the same size after different changes: no run pairs, and the cell still gets
    a figure, the difference of the modes' means over runs with its Welch interval, marked unpaired."""
    from scipy import stats

    frames = {i: 0.3 * (i % 5) for i in range(20)}
    runs = _per_frame_runs(frames, lambda mode, run: 2.0 if mode == "gausslite" else 1.0)
    s = rt.summarise(runs, "s", [0.5], 100)
    p = s["budgets"]["0.5"]["protocols"]["novel"]
    assert [u["run"] for u in p["unpaired_runs"]] == [0, 1, 2] and "gain" not in p
    g = [r["protocols"]["novel"]["roi_psnr"] for r in runs if r["mode"] == "gausslite"]
    u = [r["protocols"]["novel"]["roi_psnr"] for r in runs if r["mode"] == "uniform"]
    want = stats.ttest_ind(g, u, equal_var=False).confidence_interval(0.95)
    assert p["unpaired_gain"] == pytest.approx(float(np.mean(g) - np.mean(u)))
    assert p["unpaired_gain_ci"] == [pytest.approx(want.low), pytest.approx(want.high)]
    assert p["unpaired_gain_runs"] == [3, 3]
    md = rt.protocol_table({"scenes": {"s": s}})
    assert f"{p['unpaired_gain']:+.2f} [{want.low:+.2f}, {want.high:+.2f}] (unpaired, 3 + 3 runs)" in md


def test_a_users_own_sequence_runs_with_every_protocol_and_the_late_scenario(tmp_path):
    """``--dataset PATH --tasks ID`` on a folder the loaders read: one scene per task, named after it, with the
    protocols in the same layout as the built-in scenes; ``--late`` names it ``<task>_late``."""
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=8, width=64, height=48, trajectory="circle")
    path = tmp_path / "scene" / "agent_a"
    with pytest.raises(ValueError, match="not in"):
        rt.dataset_scenes(path, ["no-such-task"], 300)
    with pytest.raises(FileNotFoundError):
        rt.dataset_scenes(tmp_path / "nowhere", ["synth-pick-object"], 300)
    out = tmp_path / "own.json"
    for late, via in ((None, None), (0.4, "task"), (0.4, "detection")):
        argv = ["--dataset", str(path), "--tasks", "synth-pick-object", "--budgets", "0.08", "--runs", "1",
                "--twin", "--cap", "300", "--fps", "2", "--final-pass-budgets", "", "--track-iters", "3",
                "--track-stride", "4", "--set", "mapper.seeding.seeds_per_frame=600", "--out", str(out)]
        if late:
            argv += ["--late", str(late), "--late-via", via]
        assert rt.main(argv) == 0
        res = __import__("json").loads(out.read_text())
        name = "synth-pick-object" + ({"task": "_late", "detection": "_late_detection"}[via] if late else "")
        blk = res["scenes"][name]["budgets"]["0.08"]
        assert set(blk["protocols"]) == {"sensor", "keyframes", "novel", "tracked", "novel-tracked"}
        for q in ("novel", "novel-tracked"):  # frame 5 of 8 withheld (every 10th)
            assert blk["protocols"][q]["gausslite"]["frames_scored"] == 1
        for p, v in blk["protocols"].items():
            assert v["uniform"]["runs"] == v["gausslite"]["runs"] == 1 and v["gain"] is not None, p
        assert blk["protocols"]["tracked"]["gausslite"]["frames_scored"] == 2  # every 4th of 8 frames
        assert blk["protocols"]["sensor"]["gausslite"]["roi_psnr"] == blk["gausslite"]["roi_psnr"]
        assert res["settings"]["late"] == late and res["settings"]["late_via"] == via
        g = [r for r in res["runs"] if r["mode"] == "gausslite" and r["scene"] == name][0]
        assert g["roi_iters"] > 0  # the (late) task engaged


def test_a_late_task_given_mid_mission_reaches_the_stored_keyframes(tmp_path):
    """``--late F`` (``late_via: task``): the mission has no relevance before F, then gets its task through
    ``AgentRuntime.update_task`` (the product's path): the keyframes stored before F carry the task's ROI, so the
    ROI phase draws them. ``late_via: detection``: the keyframes before F never get it."""
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=8, width=64, height=48, trajectory="circle")
    base = {"scene": "synthetic_circle", "spec": rt.SCENES["synthetic_circle"], "path": str(tmp_path / "scene" / "agent_a"),
            "task": "synth-pick-object", "mode": "gausslite", "budget": 0.08, "run": 0, "cap": 300, "late": 0.5,
            "overrides": ["mapper.seeding.seeds_per_frame=600", "mapper.budget_clock=work"]}
    seen = {}
    for via in ("task", "detection"):
        job = {**base, "late_via": via}
        ds, ann, task, agent, fp = rt.start_mission(job, 1.0)
        try:
            give = give_late_task(job, ds, agent, task)
            assert (give is None) == (via == "detection")
            start = late_index(job, ds)
            for i in range(len(ds)):
                if give and give(i):
                    assert i == start and agent.apply_pending_task()
                    assert not agent.apply_pending_task()  # applied once
                if i < start:
                    assert not agent.relevance(ds[i]).any()
                agent.mapper.map_frame(ds[i], agent.relevance(ds[i]), time_budget_s=0.08)
            seen[via] = [k.sees_roi for k in agent.mapper.keyframes if k.frame_id < ds[start].frame_id]
        finally:
            agent.close()
    assert seen["task"] and any(seen["task"])
    assert not any(seen["detection"])


def test_a_live_map_scored_after_the_missions_scores_as_it_would_inline(tmp_path):
    """Live missions save their maps and are scored once every mission ran (no scoring beside a live mission): the
    rebuilt map scores exactly as the map itself."""
    import torch

    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=6, width=64, height=48, trajectory="circle")
    job = {"scene": "synthetic_circle", "spec": rt.SCENES["synthetic_circle"], "path": str(tmp_path / "scene" / "agent_a"),
           "task": "synth-pick-object", "mode": "gausslite", "budget": 0.08, "run": 0, "cap": 300, "clock": "dataset",
           "overrides": ["mapper.seeding.seeds_per_frame=600", "mapper.budget_clock=work"],
           "protocols": ("sensor", "keyframes", "tracked"), "track_iters": 3, "track_stride": 2,
           "defer_dir": str(tmp_path / "maps")}
    ds, ann, task, agent, fp = rt.start_mission(job, 1.0)
    try:
        for i in rt.keyframe_schedule(ds, 0.5):
            agent.mapper.map_frame(ds[i], agent.relevance(ds[i]), time_budget_s=0.08)
        saved = rt.mission_result(job, agent.mapper, ds, ann, task, fp)
        assert "protocols" not in saved and Path(saved["state_path"]).is_file()
        inline = rt.map_scores(job, agent.mapper, ds, ann, task.id, fp, sorted(s.frame_id for s in agent.mapper.stats))
    finally:
        agent.close()
    scored = rt.score_deferred(saved)
    assert not Path(saved["state_path"]).exists() and "score_job" not in scored
    for p in ("sensor", "keyframes", "tracked"):
        assert scored["protocols"][p]["roi_psnr"] == pytest.approx(inline["protocols"][p]["roi_psnr"], abs=1e-4), p


def test_a_saved_map_whose_keyframes_include_a_withheld_frame_is_not_scored_as_novel(tmp_path):
    """``--score-only`` rebuilds each saved map from its state, which holds no per-keyframe statistics: the leak
    guard checks the keyframe ids saved with the map against the withheld frames, and refuses to score a map that
    trained on one."""
    import torch

    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=7, width=64, height=48, trajectory="circle")
    job = {"scene": "synthetic_circle", "spec": rt.SCENES["synthetic_circle"], "path": str(tmp_path / "scene" / "agent_a"),
           "task": "synth-pick-object", "mode": "gausslite", "budget": 0.08, "run": 0, "cap": 300, "clock": "dataset",
           "overrides": ["mapper.seeding.seeds_per_frame=300", "mapper.budget_clock=work"],
           "protocols": ("sensor", "novel"), "novel_every": 3, "track_iters": 2, "track_stride": 4,
           "defer_dir": str(tmp_path / "maps")}
    ds, ann, task, agent, fp = rt.start_mission(job, 1.0)
    try:
        train = rt.training_frames(job, ds)
        for i in range(0, len(train), 2):
            agent.mapper.map_frame(train[i], agent.relevance(train[i]), time_budget_s=0.08)
        saved = rt.mission_result(job, agent.mapper, ds, ann, task, fp)
    finally:
        agent.close()
    withheld = rt.novel_ids(job, ds)
    state = torch.load(saved["state_path"], weights_only=False)
    assert state["keyframe_ids"] and not set(withheld) & set(state["keyframe_ids"])
    rt.check_withheld(withheld, state["keyframe_ids"])  # the true record passes
    state["keyframe_ids"] = sorted([*state["keyframe_ids"], withheld[0]])  # a map that trained on a withheld frame
    torch.save(state, saved["state_path"])
    with pytest.raises(ValueError, match=f"withheld frames \\[{withheld[0]}\\]"):
        rt.score_deferred(saved)


def test_live_missions_back_to_back_then_scored_apart(tmp_path):
    """``--missions-only`` runs the live missions and saves their maps unscored; ``--score-only`` scores them (no
    new mission) and writes the usual layout over every budget run."""
    import json

    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=6, width=64, height=48, trajectory="circle")
    out = tmp_path / "live.json"
    base = ["--dataset", str(tmp_path / "scene" / "agent_a"), "--tasks", "synth-pick-object", "--runs", "1",
            "--cap", "300", "--fps", "4", "--final-pass-budgets", "", "--track-iters", "2", "--track-stride", "3",
            "--set", "mapper.seeding.seeds_per_frame=300", "--out", str(out), "--work", str(tmp_path / "work")]
    assert rt.main(base + ["--budgets", "0.2", "--missions-only"]) == 0
    assert rt.main(base + ["--budgets", "0.4", "--modes", "uniform", "--missions-only", "--resume"]) == 0
    saved = json.loads(out.with_suffix(".partial.json").read_text())["runs"]
    assert len(saved) == 3 and all("state_path" in r and "protocols" not in r for r in saved)
    # both modes mapped at the one resolution chosen for the scene and budget (--resolution shared, the default)
    assert {r["resolution_mode"] for r in saved} == {"shared"}
    assert len({(r["budget"], r["mapping_downscale"]) for r in saved if r["budget"] == 0.2}) == 1
    assert not out.exists()
    # another result file sharing the work folder (the same scene, mode, budget and run) keeps its maps apart
    other = tmp_path / "other.json"
    assert rt.main([*base[:-4], "--out", str(other), "--work", str(tmp_path / "work"), "--budgets", "0.2",
                    "--modes", "uniform", "--missions-only"]) == 0
    theirs = json.loads(other.with_suffix(".partial.json").read_text())["runs"][0]["state_path"]
    assert theirs not in {r["state_path"] for r in saved} and all(Path(r["state_path"]).is_file() for r in saved)
    assert rt.main(base + ["--budgets", "0.2", "--score-only"]) == 0
    res = json.loads(out.read_text())
    blk = res["scenes"]["synth-pick-object"]["budgets"]
    assert set(blk) == {"0.2", "0.4"} and blk["0.2"]["protocols"]["tracked"]["runs"] == 1
    assert "gausslite" not in blk["0.4"] and blk["0.4"]["uniform"]["runs"] == 1
    # the shared resolutions come from the runs, so a scoring-only invocation records them too
    assert res["settings"]["shared_resolution"]["synth-pick-object"] == {
        b: next(r["mapping_downscale"] for r in res["runs"] if f"{r['budget']:g}" == b) for b in ("0.2", "0.4")}
    assert all("protocols" in r and "state_path" not in r for r in res["runs"])
    assert not list((tmp_path / "work" / "maps" / "live").glob("*.pt")) and Path(theirs).is_file()


def test_withheld_frames_never_reach_the_mapper_in_either_mode_twin_or_live(tmp_path, monkeypatch):
    """The novel protocols: every k-th frame is withheld from the mission in both modes, live and on the twin: never
    a keyframe, never a frame between keyframes (whose ROI crop the mapper may keep), and scored under ``novel`` and
    ``novel-tracked``."""
    from gausslite.mapping.mapper import Mapper
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=9, width=64, height=48, trajectory="circle")
    seen: list = []
    real = Mapper.map_frame

    def spy(self, frame, relevance=None, time_budget_s=None, between=()):
        seen.extend([int(frame.frame_id), *(int(f.frame_id) for f in between)])
        return real(self, frame, relevance, time_budget_s, between)

    monkeypatch.setattr(Mapper, "map_frame", spy)
    job = {"scene": "synthetic_circle", "spec": rt.SCENES["synthetic_circle"], "path": str(tmp_path / "scene" / "agent_a"),
           "task": "synth-pick-object", "budget": 0.08, "run": 0, "cap": 300, "clock": "dataset",
           "overrides": ["mapper.seeding.seeds_per_frame=300", "mapper.roi_views.enabled=true"],
           "protocols": ("sensor", "keyframes", "novel", "tracked", "novel-tracked"), "track_iters": 2,
           "track_stride": 4, "novel_every": 3}
    ds = rt.Preloaded(rt.load_scene(rt.SCENES["synthetic_circle"], Path(job["path"]))[0])
    withheld = set(rt.novel_ids(job, ds))
    assert withheld == {int(ds[i].frame_id) for i in (1, 4, 7)}
    for run in (rt.twin_one, rt.run_one):
        for mode in ("uniform", "gausslite"):
            seen.clear()
            r = run({**job, "mode": mode})
            assert seen and not withheld & set(seen), (run.__name__, mode)
            assert r["withheld"] == 3, (run.__name__, mode)
            for q in ("novel", "novel-tracked"):
                assert r["protocols"][q]["frames_scored"] == 3, (run.__name__, mode, q)


def test_live_missions_with_poses_from_odometry_are_scored_at_the_estimates(tmp_path):
    """``--pose-source odometry``: the agents track every frame (the withheld ones too) and map at the estimates; both
    modes are scored at those estimates, the ROI from the given poses; the twin refuses it."""
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=14, width=96, height=72)  # a hand-held pace: every frame tracks
    path = tmp_path / "scene" / "agent_a"
    out = tmp_path / "odo.json"
    argv = ["--dataset", str(path), "--tasks", "synth-pick-object", "--budgets", "0.1", "--runs", "1", "--cap", "300",
            "--fps", "8", "--final-pass-budgets", "", "--protocols", "sensor,novel", "--novel-every", "4",
            "--set", "mapper.seeding.seeds_per_frame=300", "--work", str(tmp_path / "w"), "--out", str(out)]
    with pytest.raises(SystemExit):
        rt.main([*argv, "--twin", "--pose-source", "odometry"])
    assert rt.main([*argv, "--pose-source", "odometry"]) == 0
    res = __import__("json").loads(out.read_text())
    assert res["settings"]["pose_source"] == "odometry"
    for r in res["runs"]:
        assert r["pose_source"] == "odometry" and r["frames_estimated"] == 14 and r["withheld"] == 3
        assert r["mission"]["pose_source"] == "odometry" and r["mission"]["mapping_size"] == [96, 72]
        assert r["mission"]["keyframe_budget_s"] == 0.1 and r["mission"]["rate"] == 5.0
        assert r["status"]["frames_received"] == 11  # the withheld frames were tracked, never sent to the mapper
    blk = res["scenes"]["synth-pick-object"]["budgets"]["0.1"]["protocols"]
    assert blk["novel"]["gausslite"]["frames_scored"] == 3 and blk["novel"]["gain"] is not None
    assert blk["sensor"]["uniform"]["frames_scored"] == 14


def test_both_modes_get_one_resolution_per_scene_and_budget_unless_a_user_pins_it(tmp_path):
    """``--resolution shared`` (the default) gives every job of a scene and budget the same two pins (background and
    task region), the agent governor's first choice under the uniform settings, which the GaussLite settings would
    choose alike; ``--resolution agent`` or a user's own pin leaves each mission's governor (or the pin) alone."""
    from bench.realtime import cli
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=4, width=64, height=48, trajectory="circle")
    base = ["--dataset", str(tmp_path / "scene" / "agent_a"), "--tasks", "synth-pick-object", "--runs", "2",
            "--cap", "300", "--budgets", "0.05,2", "--work", str(tmp_path / "work"), "--out", str(tmp_path / "r.json")]

    def jobs(extra):
        ap = cli._parser()
        args = ap.parse_args(base + extra)
        protocols, scenes, specs = cli._checked_scenes(ap, args)
        got, _ = cli._build_jobs(args, scenes, specs, protocols, [0.05, 2.0], set(), ["uniform", "gausslite"],
                                 tmp_path / "r.json", set())
        return got

    shared = jobs([])
    assert len(shared) == 8 and {j["resolution_mode"] for j in shared} == {"shared"}
    for b in (0.05, 2.0):
        pins = {tuple(o for o in j["overrides"] if o.startswith("agent.resolution.")) for j in shared
                if j["budget"] == b}
        assert len(pins) == 1
        (down, roi), = pins
        assert down.split("=")[1] == roi.split("=")[1]  # the region at the background's level
    choice = rt.shared_resolution(shared[0]["spec"], Path(shared[0]["path"]), [0.05], 300)[0.05]
    _, profile = rt.load_scene(shared[0]["spec"], Path(shared[0]["path"]))
    g, _ = rt.agent_config("gausslite", 0.05, 300, 0, 1.0, profile)
    assert rt.first_choice(g, *choice["native_size"], 0.05, 300).factor == choice["downscale"]
    assert all(j["overrides"] == [] and j["resolution_mode"] == "agent" for j in jobs(["--resolution", "agent"]))
    pinned = jobs(["--set", "agent.resolution.downscale=2"])
    assert all(j["overrides"] == ["agent.resolution.downscale=2"] and j["resolution_mode"] == "pinned"
               for j in pinned)


def _traced_run(mode, run, frames, n_active, region):
    """A scored run with a per-keyframe trace (keyframes ``frames``) and the sensor protocol's per-frame region."""
    n = len(frames)
    return {"scene": "tum_fr1_rpy", "mode": mode, "budget": 0.5, "run": run,
            "trace": {"frame_id": frames, "iters": [20] * n, "active_iters": [8] * n, "n_gaussians": [6000] * n,
                      "n_active": n_active, "active_scale_m": [0.004] * n, "n_roi_seeds": [100] * n},
            "protocols": {"sensor": {"roi_psnr_per_frame": {str(f): v for f, v in region.items()}}}}


def test_the_keyframe_trace_pairs_both_modes_region_at_gausslites_keyframes(tmp_path):
    from bench.realtime.tables import plot_trace, trace_table

    region_g = {0: 25.0, 7: 24.0, 14: 22.0}
    region_u = {0: 24.0, 7: 24.5, 14: 21.0}
    runs = [_traced_run("gausslite", r, [0, 7 + r, 14], [100, 200 + 10 * r, 300], region_g) for r in range(3)]
    runs += [_traced_run("uniform", r, [0, 7, 14], [0, 0, 0], region_u) for r in range(3)]
    rows = trace_table(runs, "tum_fr1_rpy", 0.5).splitlines()
    # the k-th keyframe's median frame over runs, both modes' region there, the gain, the task's Gaussians, scale
    assert rows[4] == "| 0 | 0 | 25.00 | 24.00 | +1.00 | 100 | 4.0 | 8.0 | 20.0 / 20.0 |"
    assert rows[5].startswith("| 1 | 8 | – | – | – | 210 |")  # frame 8 is no scored frame: no region there
    assert rows[6].startswith("| 2 | 14 | 22.00 | 21.00 | +1.00 | 300 |")
    assert plot_trace(runs, "tum_fr1_rpy", 0.5, tmp_path / "trace.png") and (tmp_path / "trace.png").stat().st_size
    untraced = [{k: v for k, v in r.items() if k != "trace"} for r in runs]
    assert trace_table(untraced, "tum_fr1_rpy", 0.5) == ""
    assert not plot_trace(untraced, "tum_fr1_rpy", 0.5, tmp_path / "none.png")


def test_a_missions_trace_keeps_each_keyframes_stats_in_mapping_order():
    from types import SimpleNamespace

    from bench.realtime.missions import TRACE_FIELDS, keyframe_trace

    stats = [SimpleNamespace(**{f: i * 10 + j for j, f in enumerate(TRACE_FIELDS)}) for i in range(3)]
    t = keyframe_trace(stats)
    assert list(t) == list(TRACE_FIELDS) and t["frame_id"] == [0, 10, 20] and t["iters"] == [1, 11, 21]
