"""bench.quality_per_iteration: a quick run (the tiny scene, against HEAD in a git worktree when git is there)
writes every run's PSNR curve at increasing iteration counts for both trees, and the summary pairs the trees by
seed. No figure is asserted beyond being a finite PSNR: quality is a benchmark result."""

from __future__ import annotations

import json
import math

import pytest

from bench.quality_per_iteration import main, summarise

from tests._git import has_git

pytestmark = pytest.mark.integration


def test_quick_run_writes_curves_for_both_trees(tmp_path):
    out = tmp_path / "q.json"
    against = ["--against", "HEAD"] if has_git() else []
    main(["--quick", "--work", str(tmp_path / "work"), "--out", str(out), *against])
    res = json.loads(out.read_text())
    assert res["provenance"]["command"].startswith("python -m bench.quality_per_iteration --quick")
    assert out.with_suffix(".png").stat().st_size > 1000
    trees = {r["tree"] for r in res["runs"]}
    assert trees == ({"this", "that"} if against else {"this"})
    for r in res["runs"]:
        its = [c["iters"] for c in r["curve"]]
        assert len(its) == 2 and its[1] == its[0] + 10 and its[0] > 0  # mapped, then 10 more iterations
        assert all(math.isfinite(c["keyframes"]) and math.isfinite(c["novel"]) for c in r["curve"])
    row = res["summary"]["rendered"][-1]
    if against:  # the same code on both sides, the same seed: the same map
        assert row["diff_keyframes"] == pytest.approx(0.0, abs=1e-6)
    assert "| rendered |" in out.with_suffix(".md").read_text()


def test_the_summary_pairs_runs_by_seed():
    def run(tree, seed, k):
        return {"tree": tree, "scene": "s", "seed": seed,
                "curve": [{"iters": 10, "keyframes": k, "novel": k - 1, "roi_keyframes": None, "roi_novel": k - 2}]}

    runs = [run("this", 0, 20.0), run("this", 1, 22.0), run("that", 0, 19.0), run("that", 1, 22.5),
            run("that", 2, 30.0)]  # seed 2 has no partner: in the mean of its tree, not in the differences
    row = summarise(runs)["s"][0]
    assert row["this_keyframes"] == pytest.approx(21.0) and row["that_keyframes"] == pytest.approx(23.8333333)
    assert row["diff_keyframes"] == pytest.approx(0.25)  # (+1.0 − 0.5) / 2
    assert row["diff_keyframes_std"] == pytest.approx(math.sqrt(((1.0 - 0.25) ** 2 + (-0.5 - 0.25) ** 2) / 1))
    assert row["this_roi_keyframes"] is None and row["diff_roi_keyframes"] is None


def test_an_infinite_or_missing_psnr_is_left_out_of_the_means():
    """A region rendered exactly scores an infinite PSNR: it is left out of the means and differences, which stay
    finite."""
    def run(tree, seed, r):
        return {"tree": tree, "scene": "s", "seed": seed,
                "curve": [{"iters": 10, "keyframes": 20.0, "novel": 19.0, "roi_keyframes": r, "roi_novel": None}]}

    row = summarise([run("this", 0, float("inf")), run("this", 1, 21.0), run("that", 0, 20.0),
                     run("that", 1, 20.5)])["s"][0]
    assert row["this_roi_keyframes"] == pytest.approx(21.0) and row["diff_roi_keyframes"] == pytest.approx(0.5)
    assert row["diff_roi_keyframes_std"] is None and row["diff_roi_novel"] is None


def test_a_setting_applies_to_this_trees_runs(tmp_path):
    out = tmp_path / "q.json"
    main(["--quick", "--work", str(tmp_path / "work"), "--out", str(out), "--set", "seeding.seeds_per_frame=40"])
    res = json.loads(out.read_text())
    assert res["settings"]["overrides_this"] == ["seeding.seeds_per_frame=40"]
    # 8 mapped frames of at most 2 × 40 seeds each, at most doubled by one density step: far below the default's
    assert all(0 < r["n_gaussians"] <= 2 * 8 * 80 for r in res["runs"])
