"""bench.pose_perturbation: the sequence split, the summary (run-clustered paired gains, the exact gain kept), the
table, where the withheld frames are scored (the predicted pose: the given pose with the map's interpolated
correction, never the truth), and one tiny run end to end."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.pose_perturbation import map_sequence, run_one, score_sequence, sequence, summarise, table
from gausslite.datasets.trajectory import perturb_trajectory
from gausslite.mapping.poses import interpolate_pose, neighbour_keys
from gausslite.synthetic import make_scene

TINY = ["iters_per_frame=3", "warmup_iters=1", "final_iters_per_keyframe=0"]


def test_sequence_spreads_frames_and_withholds_every_kth():
    mapped, held = sequence(300, 40, 5)
    assert len(mapped) == 32 and len(held) == 8
    every = sorted(mapped + held)
    assert every == list(range(0, 280, 7))
    assert held == [every[j] for j in range(2, 40, 5)]
    with pytest.raises(ValueError):
        sequence(10, 20, 5)


def _run(scene, level, refine, mode, seed, roi):
    """A run's figures: two withheld frames (ROI ``roi`` and ``roi + 1`` at the predicted pose, 3 dB less at the
    true pose) and one keyframe."""
    err = {"ate_m": 0.01, "rot_rmse_deg": 0.5, "trans_rmse_m": 0.02, "trans_max_m": 0.04}
    return {"scene": scene, "level": level, "refine": refine, "mode": mode, "seed": seed, "roi_psnr": roi + 0.5,
            "psnr": roi + 1, "roi_psnr_per_frame": {"3": roi, "8": roi + 1.0},
            "roi_psnr_true_pose": roi - 2.5, "psnr_true_pose": roi - 2,
            "roi_psnr_true_pose_per_frame": {"3": roi - 3.0, "8": roi - 2.0},
            "roi_psnr_keyframes": roi + 2, "psnr_keyframes": roi + 3, "roi_psnr_keyframes_per_frame": {"0": roi + 2},
            "n_gaussians": 100, "s_per_frame": 1.0, "pose_error": err, "pose_error_after_map": err,
            "pose_error_predicted": err, "correction_withheld": {"rot_deg": 0.1, "trans_m": 0.01}}


def test_summary_gains_are_paired_per_frame_and_run_clustered():
    runs = []
    for seed, off in ((0, 0.0), (1, 0.5), (2, -0.5)):
        for level, g in (("exact", 2.0), ("3cm_1.5deg", 1.0)):
            runs.append(_run("s", level, False, "uniform", seed, 20.0 + off))
            runs.append(_run("s", level, False, "gausslite", seed, 20.0 + off + g + 0.1 * seed))
    out = summarise(runs, ["s"], ["exact", "3cm_1.5deg"], [False], [0, 1, 2])
    ex, lv = out["s"]["refine_off"]["exact"], out["s"]["refine_off"]["3cm_1.5deg"]
    assert ex["gain"]["gain"] == pytest.approx(2.1) and ex["gain"]["std"] == pytest.approx(0.1)
    assert ex["gain"]["interval"] == "run-clustered" and ex["gain"]["runs"] == 3 and ex["gain"]["n"] == 6
    # t(0.975, 2 df) = 4.303: half width 4.303 * 0.1 / sqrt(3)
    assert ex["gain"]["half_width"] == pytest.approx(4.3027 * 0.1 / math.sqrt(3), rel=1e-4)
    assert ex["gain"]["significant"] and ex["gain_kept"] == pytest.approx(1.0)
    assert lv["gain"]["gain"] == pytest.approx(1.1) and lv["gain_kept"] == pytest.approx(1.1 / 2.1)
    assert lv["gain_true_pose"]["gain"] == pytest.approx(1.1) and lv["gain_keyframes"]["gain"] == pytest.approx(1.1)
    assert lv["uniform_roi_psnr"] == pytest.approx(20.5) and lv["uniform_roi_psnr_std"] == pytest.approx(0.5)
    assert lv["uniform_roi_psnr_true_pose"] == pytest.approx(17.5)
    assert lv["ate_m"] == pytest.approx(0.01) and lv["seeds"] == [0, 1, 2]
    assert lv["gausslite_predicted_trans_rmse_m"] == pytest.approx(0.02)
    md = table(out)
    assert "| s | off | 3cm_1.5deg | 1.00 cm / 0.50° / 2.00 cm | 2.00 cm, 0.50° / 2.00 cm, 0.50° | 20.50 ± 0.50 |" in md
    assert "+1.10 [+0.85, +1.35] (sig.) | 52 % | 17.50 ± 0.50 / 18.60 ± 0.46 |" in md


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    out = tmp_path_factory.mktemp("pose_perturbation") / "walk"
    make_scene(out, width=48, height=36, frames=24, progress=False, trajectory="walk", agents=("agent_a",))
    return str(out / "agent_a")


def _job(path, level, refine):
    return {"scene": "synthetic_walk", "path": path, "level": level, "refine": refine, "mode": "gausslite", "seed": 1,
            "frames": 12, "withhold_every": 5, "track_iters": 2, "overrides": TINY}


def _capture_renders(monkeypatch, mapper) -> list:
    """Record (frame id, (4, 4) pose) of every render of ``mapper``'s sensor."""
    seen = []
    render_view = mapper.sensor.render_view

    def spy(c2w, K, width, height, frame_id, *args, **kwargs):
        seen.append((int(frame_id), np.asarray(c2w, np.float64).copy()))
        return render_view(c2w, K, width, height, frame_id, *args, **kwargs)

    monkeypatch.setattr(mapper.sensor, "render_view", spy)
    return seen


def test_withheld_frames_are_scored_at_the_predicted_pose_not_the_truth(walk, monkeypatch):
    run = map_sequence(_job(walk, "3cm_1.5deg", True))
    corrections = run.mapper.poses.corrections
    assert sorted(corrections) == sorted(run.mapped_ids) and run.withheld_ids == [4, 14]
    true = {int(fr.frame_id): fr.c2w for fr in run.frames}
    seen = _capture_renders(monkeypatch, run.mapper)
    sc = score_sequence(run, "synth-pick-object")
    held = set(run.withheld_ids)
    novel_renders = [(fid, c2w) for fid, c2w in seen if fid in held][:len(held)]
    truth_renders = [(fid, c2w) for fid, c2w in seen if fid in held][len(held):]
    assert [fid for fid, _ in novel_renders] == run.withheld_ids == [fid for fid, _ in truth_renders]
    for fid, c2w in novel_renders:
        k0, k1, t = neighbour_keys(corrections, fid)  # the keyframes on both sides of the withheld frame
        expected = run.given[fid] @ interpolate_pose(corrections[k0], corrections[k1], t)
        assert np.allclose(c2w, expected, atol=1e-12) and np.allclose(sc["views"][fid].c2w, expected, atol=1e-12)
        assert not np.allclose(c2w, run.given[fid], atol=1e-9)  # the learned correction is applied
        assert np.linalg.norm(c2w[:3, 3] - true[fid][:3, 3]) > 1e-3  # not the truth
    for fid, c2w in truth_renders:  # the second figure: the same views with the camera at the truth
        assert np.allclose(c2w, true[fid], atol=1e-12)
    assert set(sc["novel"]["psnr_per_frame"]) == held and sc["novel"]["pose"] == "predicted"
    assert sc["novel"]["psnr"] != sc["true_pose"]["psnr"]
    assert sc["keyframes"]["frames_scored"] == len(run.mapped_ids)


def test_without_refinement_the_predicted_pose_is_the_given_one(walk, monkeypatch):
    run = map_sequence(_job(walk, "3cm_1.5deg", False))
    seen = _capture_renders(monkeypatch, run.mapper)
    sc = score_sequence(run, "synth-pick-object")
    for fid in run.withheld_ids:  # identity corrections: the perturbed pose as given
        assert np.array_equal(sc["views"][fid].c2w, run.given[fid])
        assert sc["views"][fid].trans_m == pytest.approx(0.0, abs=1e-9)
        assert sc["views"][fid].rot_deg == pytest.approx(0.0, abs=1e-5)
    novel = [c2w for fid, c2w in seen if fid in set(run.withheld_ids)][:len(run.withheld_ids)]
    assert all(np.array_equal(c2w, run.given[fid]) for c2w, fid in zip(novel, run.withheld_ids))


def test_one_tiny_run_end_to_end(walk):
    r = run_one(_job(walk, "exact", False))
    assert r["n_mapped"] == 10 and r["n_withheld"] == 2
    assert r["pose_error"]["ate_m"] == pytest.approx(0.0, abs=1e-9)
    assert r["pose_error_predicted"]["trans_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    # exact poses, no refinement: the predicted pose is the truth, so both figures agree
    assert r["psnr"] == pytest.approx(r["psnr_true_pose"]) and math.isfinite(r["psnr"]) and r["psnr"] > 5.0
    assert r["roi_psnr"] is None or r["roi_psnr"] == pytest.approx(r["roi_psnr_true_pose"])
    assert r["n_gaussians"] > 0 and r["psnr_keyframes"] > 5.0


# ------------------------------------------------------------------------------------ the live mode
def test_live_mode_runs_missions_at_perturbed_poses_and_records_a_failed_one(tmp_path, monkeypatch, capsys):
    """``--mode live`` (the default) on a tiny circle (12 frames at 64×48): one live agent mission per level and mode
    as bench.realtime runs it, its frames streamed at the perturbed poses, every 4th withheld and scored under
    ``novel``; a mission whose mapping fails is recorded with its end state and error, left out of the summary,
    marked †, and the command exits 1; a resumed invocation runs it again and exits 0. No timing is asserted."""
    import json

    import bench.pose_perturbation as pp
    from gausslite.mapping.mapper import Mapper

    monkeypatch.setitem(pp.LIVE_SCENES, "synthetic_circle",
                        {**pp.LIVE_SCENES["synthetic_circle"], "frames": 12, "width": 64, "height": 48, "cap": 300})
    real, real_live = Mapper.map_frame, pp.live_one
    fail = {"armed": True, "now": False}
    seen = {}  # (level, mode, frame id) → the pose the mapper was given

    def out_of_memory(self, frame, *args, **kwargs):
        seen[(fail["job"]["level"], self.cfg.mode, int(frame.frame_id))] = np.asarray(frame.c2w).copy()
        if fail["now"]:
            raise MemoryError("injected")
        return real(self, frame, *args, **kwargs)

    def live_one(job):  # the GaussLite mission at 3 cm / 1.5° runs out of memory, while armed
        fail["job"] = job
        fail["now"] = fail["armed"] and (job["level"], job["mode"]) == ("3cm_1.5deg", "gausslite")
        return real_live(job)

    monkeypatch.setattr(Mapper, "map_frame", out_of_memory)
    monkeypatch.setattr(pp, "live_one", live_one)
    out = tmp_path / "live.json"
    argv = ["--scenes", "synthetic_circle", "--levels", "exact,3cm_1.5deg", "--seeds", "1", "--refine", "off",
            "--budget", "0.1", "--withhold-every", "4", "--set", "mapper.seeding.seeds_per_frame=300",
            "--work", str(tmp_path / "work"), "--out", str(out)]
    assert pp.main(argv) == 1
    assert "level=3cm_1.5deg refine=False mode=gausslite seed=0: FAILED" in capsys.readouterr().err
    res = json.loads(out.read_text())
    assert res["settings"]["mode"] == "live" and res["settings"]["budget"] == 0.1
    assert len(res["runs"]) == 4
    for r in res["runs"]:
        assert r["run_mode"] == "live" and r["mission"]["keyframe_budget_s"] == 0.1
        assert r["mission"]["max_gaussians"] == 300 and r["mission"]["mode"] == r["mode"]
        bad = (r["level"], r["mode"]) == ("3cm_1.5deg", "gausslite")
        assert r["end_state"] == ("FAILED" if bad else "FINISHED"), (r["level"], r["mode"])
        assert bad == bool(r["error"]) and (not bad or "MemoryError: injected" in r["error"])
        if bad:  # its first keyframe failed: no map to score, the record says so
            assert r["keyframes"] == 0 and "score_error" in r and "roi_psnr" not in r
        else:
            assert r["frames_sent"] == 9 and r["keyframes"] >= 1  # 12 frames, 3 withheld: the rest streamed
            assert r["n_withheld"] == 3 and r["n_mapped"] == r["keyframes"]
            assert set(r["roi_psnr_per_frame"]) <= {"2", "6", "10"} and r["psnr"] > 5.0
            exact = r["level"] == "exact"
            assert (r["pose_error"]["ate_m"] < 1e-9) == exact  # the frames were given the perturbed poses
            assert exact or r["pose_error"]["ate_m"] > 0.01
    assert [(f["level"], f["mode"]) for f in res["failed_runs"]] == [("3cm_1.5deg", "gausslite")]
    # the missions mapped at the perturbed poses: the level's draw for the run's seed, exact ones untouched
    from bench.realtime.scenes import load_scene

    ds = load_scene({"kind": "synthetic"}, pp.live_scene_path("synthetic_circle", tmp_path / "work"))[0]
    true = {int(ds[i].frame_id): ds[i].c2w for i in range(len(ds))}
    est = perturb_trajectory(np.stack(list(true.values())), "3cm_1.5deg", seed=0)
    drawn = dict(zip(true, est))
    keys = [k for k in seen if k[1] == "uniform"]
    assert {k[0] for k in keys} == {"exact", "3cm_1.5deg"}
    for level, _, fid in keys:
        assert np.allclose(seen[(level, "uniform", fid)], true[fid] if level == "exact" else drawn[fid], atol=1e-9)
    block = res["summary"]["synthetic_circle"]["refine_off"]
    assert block["exact"]["seeds"] == [0] and block["exact"]["gain"]["gain"] is not None
    assert block["exact"]["gain_kept"] is None or block["exact"]["gain_kept"] == pytest.approx(1.0)
    lv = block["3cm_1.5deg"]
    assert lv["seeds"] == [] and lv["gain"]["gain"] is None and lv["gain_kept"] is None
    assert lv["failed_runs"][0]["end_state"] == "FAILED" and lv["gausslite_roi_psnr"] is None
    assert lv["uniform_roi_psnr"] is not None and lv["ate_m"] > 0.01
    md = out.with_suffix(".md").read_text()
    assert "| synthetic_circle | off | 3cm_1.5deg † |" in md and "† a level with a run whose mission failed" in md
    # resumed: only the failed mission runs again, and the result is complete
    fail["armed"] = False
    calls = []
    monkeypatch.setattr(pp, "live_one", lambda job: calls.append(job) or live_one(job))
    assert pp.main([*argv, "--resume"]) == 0
    assert [(j["level"], j["mode"]) for j in calls] == [("3cm_1.5deg", "gausslite")]
    res = json.loads(out.read_text())
    assert res["failed_runs"] == [] and res["summary"]["synthetic_circle"]["refine_off"]["3cm_1.5deg"]["seeds"] == [0]


def test_the_odometry_level_maps_and_scores_at_the_robots_own_estimates(tmp_path, monkeypatch):
    """``--levels odometry``: the mission tracks itself (``agent.pose_source: odometry``), the runtime withholds every
    k-th frame (tracked, not mapped), and the map is scored at the odometry's estimates: its pose error is the
    odometry's against the truth, and the withheld frames are rendered where the robot believes it is."""
    import json

    import bench.pose_perturbation as pp
    from gausslite.mapping.mapper import Mapper

    from gausslite.datasets.subset import withheld_indices

    # the robots' arcs at a hand-held pace (every frame tracks), 14 frames at 96x72
    monkeypatch.setitem(pp.LIVE_SCENES, "synthetic_circle", {**pp.LIVE_SCENES["synthetic_circle"], "trajectory": "arcs",
                                                             "frames": 14, "width": 96, "height": 72, "cap": 300})
    real = Mapper.map_frame
    mapped = {}

    def spy(self, frame, *args, **kwargs):
        mapped[int(frame.frame_id)] = np.asarray(frame.c2w).copy()
        return real(self, frame, *args, **kwargs)

    monkeypatch.setattr(Mapper, "map_frame", spy)
    out = tmp_path / "odo.json"
    assert pp.main(["--scenes", "synthetic_circle", "--levels", "odometry", "--seeds", "1", "--refine", "off",
                    "--modes", "gausslite", "--budget", "0.1", "--withhold-every", "4",
                    "--set", "mapper.seeding.seeds_per_frame=300", "--work", str(tmp_path / "work"),
                    "--out", str(out)]) == 0
    (r,) = json.loads(out.read_text())["runs"]
    assert r["level"] == "odometry" and r["mission"]["pose_source"] == "odometry" and r["end_state"] == "FINISHED"
    held = {int(i) for i in withheld_indices(14, 4)}  # frame ids are the indices here
    assert r["frames_estimated"] == 14 and r["frames_sent"] == 14 - len(held)  # all tracked, the withheld not mapped
    assert r["n_withheld"] == len(held) > 0 and not set(mapped) & held and r["n_mapped"] == len(mapped)
    assert 0.0 < r["pose_error"]["ate_m"] < 0.05  # the odometry's own error, not the truth's zero
    assert set(r["roi_psnr_per_frame"]) <= {str(i) for i in held} and r["psnr"] > 5.0
    with pytest.raises(SystemExit):  # offline maps at given poses only
        pp.main(["--mode", "offline", "--levels", "odometry"])


def test_live_mode_refuses_parallel_missions_and_unknown_scenes():
    import bench.pose_perturbation as pp

    with pytest.raises(SystemExit):
        pp.main(["--jobs", "2"])
    with pytest.raises(SystemExit):
        pp.main(["--scenes", "room0"])
