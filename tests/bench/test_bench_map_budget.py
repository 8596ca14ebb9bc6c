"""``python -m bench.map_budget`` end to end on a tiny input (24 frames at 160x120, one seed): the three runs, the
extrapolation of the fixed schedule's wall time, the ATE and the scores in the JSON, and the table. Its figures are
not measurements (a shared machine, a tiny scene): only what the bench computes from them is checked."""

from __future__ import annotations

import json

import pytest

from bench import map_budget


def test_subset_budget_keeps_the_start_up_and_scales_the_rest():
    row = {"spent_before_s": 20.0, "odometry_s": 5.0}
    assert map_budget.subset_budget(row, 4.0, 40, 250) == pytest.approx(15.0 + (240.0 - 15.0) * 40 / 250)
    assert map_budget.subset_budget({}, 1.0, 10, 20) == pytest.approx(30.0)


def test_the_bench_runs_both_schedules_and_writes_its_table(tmp_path):
    out = tmp_path / "map_budget.json"
    rc = map_budget.main(["--frames", "24", "--size", "160x120", "--trajectory", "arcs", "--seeds", "0",
                          "--fixed-frames", "6", "--time-budget", "0.2", "--set", "iters_per_frame=4",
                          "--set", "warmup_iters=2", "--work", str(tmp_path / "work"), "--out", str(out)])
    assert rc == 0
    doc = json.loads(out.read_text())
    assert doc["provenance"]["command"].startswith("python -m bench.map_budget --frames 24")
    rows = {r["config"]: r for r in doc["runs"]}
    assert set(rows) == {"budget", "budget_subset", "fixed"} and doc["seeds"] == [0]
    budget, subset, fixed = rows["budget"], rows["budget_subset"], rows["fixed"]
    assert budget["frames"] == 24 and subset["frames"] == fixed["frames"] == 6
    assert fixed["wall_s_all_frames"] == pytest.approx(fixed["wall_s"] * 24 / 6)  # extrapolated, linear in frames
    assert budget["wall_s_all_frames"] == budget["wall_s"] and subset["wall_s_all_frames"] is None
    # every 10th frame from the 5th withheld: the fixed schedule maps the other 5 of 6, 4 iterations each
    assert fixed["n_keyframes"] == 5 and fixed["iters_per_keyframe"] == 4 and fixed["mapping_size"] is None
    assert 1 <= budget["n_keyframes"] <= 22 and budget["iters_per_keyframe"] >= 1
    assert budget["mapping_size"] == [160, 120] and budget["odometry_s"] > 0
    for r in rows.values():
        assert 0 <= r["ate_m"] < 0.1 and r["psnr"] > 10 and r["heldout_psnr"] > 10
    g = doc["summary"]["budget_subset_minus_fixed"]["psnr"]
    assert g["n"] == 1 and g["gain"] == pytest.approx(subset["psnr"] - fixed["psnr"])
    md = out.with_suffix(".md").read_text()
    assert "| budget | 24 |" in md and "(extrapolated)" in md and "budget_subset − fixed" in md
