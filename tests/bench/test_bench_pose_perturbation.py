"""bench.pose_perturbation: the sequence split, the summary (run-clustered paired gains, the exact gain kept), the
table, where the withheld frames are scored (the predicted pose: the given pose with the map's interpolated
correction, never the truth), and one tiny run end to end."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bench.pose_perturbation import map_sequence, run_one, score_sequence, sequence, summarise, table
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
