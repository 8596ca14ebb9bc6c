"""bench.map_time: a quick run makes a tiny scene and times both of its ``gausslite map`` jobs (the fixed schedule and
a time budget) with this tree's code, and writes what each got to JSON. No timing is asserted: speed is a benchmark
figure."""

from __future__ import annotations

import json

import pytest

from bench.map_time import main, map_command, summarise

pytestmark = pytest.mark.integration


def test_quick_run_times_both_jobs_and_reads_their_metrics(tmp_path):
    out = tmp_path / "map_time.json"
    res = main(["--quick", "--work", str(tmp_path / "work"), "--out", str(out)])
    data = json.loads(out.read_text())
    assert data["provenance"]["command"].startswith("python -m bench.map_time --quick")
    fixed, budget = data["runs"]
    assert (fixed["tree"], fixed["job"], budget["job"]) == ("this", "fixed", "budget")
    for run in (fixed, budget):
        assert run["returncode"] == 0 and run["wall_s"] > 0
        assert run["psnr"] > 5 and run["n_gaussians"] > 0 and run["heldout_psnr"] is not None
    assert fixed["keyframes"] == 5 and fixed["iters"] is None  # 6 frames, the 5th withheld; no budget report
    assert budget["keyframes"] >= 1 and budget["iters"] >= 1  # what the budget bought
    assert res["summary"]["this"]["fixed"]["runs"] == 1 and "ratio" not in res
    md = out.with_suffix(".md").read_text()
    assert "| this |" in md and "0.25 min budget: wall s" in md


def test_the_jobs_differ_only_in_their_schedule_and_a_failed_run_is_left_out(tmp_path):
    fixed = map_command(tmp_path / "d", tmp_path / "o", "fixed", 2.0, 1.0, 10, quick=False)
    budget = map_command(tmp_path / "d", tmp_path / "o", "budget", 2.0, 1.0, 10, quick=False)
    assert fixed[fixed.index("--time-budget") + 1] == "none" and budget[budget.index("--time-budget") + 1] == "1"
    assert [a for a in fixed if a != "none"] == [a for a in budget if a != "1"]
    runs = [{"tree": "this", "job": "fixed", "returncode": 0, "wall_s": 10.0, "psnr": 20.0},
            {"tree": "this", "job": "fixed", "returncode": 1, "wall_s": 1.0},
            {"tree": "this", "job": "fixed", "returncode": 0, "wall_s": 14.0, "psnr": 22.0}]
    s = summarise(runs, ["this"], ["fixed", "budget"])["this"]
    assert s["fixed"] == {"runs": 2, "wall_s": 12.0, "psnr": 21.0, "roi_psnr": None, "heldout_psnr": None,
                          "heldout_roi_psnr": None, "n_gaussians": None, "keyframes": None, "iters": None}
    assert s["budget"]["runs"] == 0 and s["budget"]["wall_s"] is None
