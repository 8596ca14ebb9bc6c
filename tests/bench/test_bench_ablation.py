"""bench.ablation: the paper's ablation rows run live through bench.realtime, each row's figures paired by seed with
the row before it, with ``none`` and (leave-one-out rows) with the full pipeline."""

from __future__ import annotations

import json

import pytest

from bench import ablation


def test_the_rows_are_the_papers_progressive_ones_then_each_component_left_out():
    names = [n for n, _ in ablation.rows()]
    assert names[:6] == ["none", "+SB", "+MVO", "+ROI", "+SIS", "+GFD"]
    assert names[6:] == ["full-SB", "full-MVO", "full-ROI", "full-SIS", "full-GFD"]
    sw = dict(ablation.rows())
    assert not any(sw["none"].values()) and all(sw["+GFD"].values())
    assert sw["full-SIS"] == {**sw["+GFD"], "sis": False}
    assert ablation.row_overrides(sw["+MVO"]) == ["mapper.components.sb=true", "mapper.components.mvo=true",
                                                   "mapper.components.roi=false", "mapper.components.sis=false",
                                                   "mapper.components.gfd=false"]
    assert set(ablation.PAPER_CAMPUS) == set(names[:6])


def _run(run: int, frames: dict) -> dict:
    return {"run": run, "protocols": {"novel": {"roi_psnr": sum(frames.values()) / len(frames), "psnr": 20.0,
                                                "roi_psnr_per_frame": frames, "pose": "predicted"}}}


def test_the_summary_pairs_each_row_by_seed_with_the_row_before_with_none_and_with_the_full_pipeline():
    by_row = {"none": [_run(0, {1: 20.0, 2: 21.0}), _run(1, {1: 20.5, 2: 21.5})],
              "+SB": [_run(0, {1: 21.0, 2: 22.0}), _run(1, {1: 21.0, 2: 22.5})],
              "+GFD": [_run(0, {1: 23.0, 2: 24.0}), _run(1, {1: 23.0, 2: 24.0})],
              "full-SB": [_run(1, {1: 22.0, 2: 23.0}), _run(0, {1: 22.5, 2: 23.5})]}
    got = ablation.summarise(by_row)
    assert list(got) == ["none", "+SB", "+GFD", "full-SB"]
    assert got["none"]["roi_psnr"] == pytest.approx(20.75) and "vs_none" not in got["none"]
    # per seed, the mean of its frames' differences, then the mean over seeds
    assert got["+SB"]["step"]["gain"] == pytest.approx(0.875) and got["+SB"]["vs_none"]["runs"] == 2
    assert got["+GFD"]["step"]["gain"] == pytest.approx(1.875)  # over +SB, the row before it that ran
    assert got["full-SB"]["vs_full"]["gain"] == pytest.approx(-0.75)  # paired by seed, not by position
    assert got["+GFD"]["paper_campus"] == 25.25 and got["full-SB"]["paper_campus"] is None
    md = ablation.table({"settings": {"budget": 0.5, "runs": 2}, "scenes": {"s": got}})
    assert "| s | +SB | 21.62 ± 0.18 |" in md and "| 25.25 |" in md


@pytest.mark.integration
def test_a_live_ablation_of_two_rows_runs_scores_and_writes_its_table(tmp_path):
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=6, width=64, height=48, trajectory="circle")
    out = tmp_path / "ablation.json"
    assert ablation.main(["--dataset", str(tmp_path / "scene" / "agent_a"), "--tasks", "synth-pick-object",
                          "--rows", "none,+SB", "--runs", "1", "--budget", "0.2", "--work", str(tmp_path / "work"),
                          "--set", "mapper.seeding.seeds_per_frame=300", "--set", "mapper.budget.max_gaussians=300",
                          "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    blk = res["scenes"]["synth-pick-object"]
    assert set(blk) == {"none", "+SB"} and blk["+SB"]["runs"] == 1 and blk["none"]["roi_psnr"] is not None
    assert blk["+SB"]["vs_none"] is not None and res["provenance"]["command"].startswith("python -m bench.ablation")
    assert "| synth-pick-object | +SB |" in out.with_suffix(".md").read_text()
