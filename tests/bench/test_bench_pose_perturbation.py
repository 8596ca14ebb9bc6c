"""bench.pose_perturbation: the sequence split, the summary (paired gains, the exact gain kept), the table, and one
tiny run end to end (map at perturbed poses, score at the true ones)."""

from __future__ import annotations

import math

import pytest

from bench.pose_perturbation import run_one, sequence, summarise, table
from gausslite.synthetic import make_scene


def test_sequence_spreads_frames_and_withholds_every_kth():
    mapped, held = sequence(300, 40, 5)
    assert len(mapped) == 32 and len(held) == 8
    every = sorted(mapped + held)
    assert every == list(range(0, 280, 7))
    assert held == [every[j] for j in range(2, 40, 5)]
    with pytest.raises(ValueError):
        sequence(10, 20, 5)


def _run(scene, level, refine, mode, seed, roi):
    err = {"ate_m": 0.01, "rot_rmse_deg": 0.5, "trans_rmse_m": 0.02, "trans_max_m": 0.04}
    return {"scene": scene, "level": level, "refine": refine, "mode": mode, "seed": seed, "roi_psnr": roi,
            "psnr": roi + 1, "roi_psnr_mapped": roi + 2, "psnr_mapped": roi + 3, "roi_psnr_at_estimate": roi + 4,
            "n_gaussians": 100, "s_per_frame": 1.0, "pose_error": err, "pose_error_after_map": err}


def test_summary_gains_and_fraction_kept():
    runs = []
    for seed, off in ((0, 0.0), (1, 0.5), (2, -0.5)):
        for level, g in (("exact", 2.0), ("3cm_1.5deg", 1.0)):
            runs.append(_run("s", level, False, "uniform", seed, 20.0 + off))
            runs.append(_run("s", level, False, "gausslite", seed, 20.0 + off + g + 0.1 * seed))
    out = summarise(runs, ["s"], ["exact", "3cm_1.5deg"], [False], [0, 1, 2])
    ex, lv = out["s"]["refine_off"]["exact"], out["s"]["refine_off"]["3cm_1.5deg"]
    assert ex["gain"] == pytest.approx(2.1) and ex["gain_std"] == pytest.approx(0.1)
    assert ex["gain_significant"] and ex["gain_kept"] == pytest.approx(1.0)
    assert lv["gain"] == pytest.approx(1.1) and lv["gain_kept"] == pytest.approx(1.1 / 2.1)
    assert lv["uniform_roi_psnr"] == pytest.approx(20.0) and lv["uniform_roi_psnr_std"] == pytest.approx(0.5)
    assert lv["ate_m"] == pytest.approx(0.01) and lv["seeds"] == [0, 1, 2]
    md = table(out)
    assert lv["gain_at_estimate"] == pytest.approx(1.1) and lv["uniform_after_map_trans_rmse_m"] == pytest.approx(0.02)
    assert "| s | off | 3cm_1.5deg | 1.00 cm / 0.50° / 2.00 cm | 2.00 cm, 0.50° / 2.00 cm, 0.50° |" in md
    assert "52 %" in md


def test_one_tiny_run_scores_at_true_poses(tmp_path):
    make_scene(tmp_path / "walk", width=48, height=36, frames=24, progress=False, trajectory="walk")
    job = {"scene": "synthetic_walk", "path": str(tmp_path / "walk" / "agent_a"), "level": "3cm_1.5deg",
           "refine": True, "mode": "gausslite", "seed": 1, "frames": 12, "withhold_every": 5, "track_iters": 2,
           "overrides": ["iters_per_frame=3", "warmup_iters=1", "final_iters_per_keyframe=0"]}
    r = run_one(job)
    assert r["n_mapped"] == 10 and r["n_withheld"] == 2
    assert r["pose_error"]["ate_m"] == pytest.approx(0.03, rel=1e-6)
    assert r["pose_error_mapped"]["trans_rmse_m"] > 0
    assert r["pose_error_after_map"]["trans_rmse_m"] > 0 and r["psnr_at_estimate"] > 5.0
    assert math.isfinite(r["psnr"]) and r["psnr"] > 5.0 and r["n_gaussians"] > 0
    assert r["roi_psnr"] is None or math.isfinite(r["roi_psnr"])
