"""bench.faults: the walk through TUM fr1's camera with one fault at a time, both modes paired by run."""

from __future__ import annotations

import json

import pytest

from bench import faults


def _run(mode: str, run: int, frames: dict, end: str = "FINISHED") -> dict:
    return {"mode": mode, "run": run, "end_state": end, "iters_per_keyframe": 10.0,
            "protocols": {"novel": {"roi_psnr": sum(frames.values()) / len(frames), "psnr": 20.0,
                                    "roi_psnr_per_frame": frames, "pose": "predicted"}}}


def test_rows_are_clean_each_fault_alone_then_all():
    assert faults.FAULTS[0] == "clean" and faults.FAULTS[-1] == "all"
    assert [faults.sensor_level(f) for f in faults.FAULTS] == [
        "tum-clean", "tum-exposure", "tum-blur", "tum-misregistration", "tum-depth-noise", "tum-depth-holes", "tum"]


def test_the_gain_pairs_the_modes_by_run_and_leaves_failed_missions_out():
    runs = [_run("uniform", 0, {1: 20.0, 2: 22.0}), _run("gausslite", 0, {1: 23.0, 2: 25.0}),
            _run("gausslite", 1, {1: 24.0, 2: 24.0}), _run("uniform", 1, {1: 21.0, 2: 21.0}),
            _run("gausslite", 2, {1: 30.0, 2: 30.0}), _run("uniform", 2, {1: 10.0, 2: 10.0}, end="FAILED")]
    got = faults.summarise(runs)
    assert got["uniform"]["runs"] == 2 and got["gausslite"]["runs"] == 3
    assert got["gain"]["gain"] == pytest.approx(3.0) and got["gain"]["runs"] == 2  # run 2 has no uniform pair
    half = faults.summarise([_run("uniform", 0, {1: 20.0}), _run("gausslite", 0, {1: 21.5})])
    md = faults.table({"settings": {"budget": 0.5, "runs": 2}, "rows": {"clean": got, "blur": half}})
    assert "| clean | 21.00 ± 0.00 |" in md and "| 100 % |" in md and "| 50 % |" in md


@pytest.mark.integration
def test_a_live_fault_row_renders_maps_scores_and_writes_its_table(tmp_path):
    out = tmp_path / "faults.json"
    assert faults.main(["--faults", "clean,exposure", "--runs", "1", "--budget", "0.2", "--frames", "8",
                        "--size", "64x48", "--cap", "300", "--work", str(tmp_path / "work"),
                        "--set", "mapper.seeding.seeds_per_frame=300", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert set(res["rows"]) == {"clean", "exposure"} and res["settings"]["levels"]["exposure"] == "tum-exposure"
    for row in res["rows"].values():
        assert row["uniform"]["runs"] == 1 and row["gausslite"]["runs"] == 1 and "gain" in row
    meta = json.loads((tmp_path / "work" / "walk_8_64x48_tum-exposure" / "scene.json").read_text())
    assert meta["sensor_noise"] == "tum-exposure"
    assert "| exposure |" in out.with_suffix(".md").read_text()
