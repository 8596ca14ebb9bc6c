"""bench.roi_ceiling end to end on a tiny synthetic circle: the ROI-only fine-tune and the full-image pass run
from copies of the final map and are scored on the mapped views; bad --iters lists are refused."""

import json

import pytest

from bench import long_mission as lm


@pytest.fixture
def small_scenes(monkeypatch):
    monkeypatch.setitem(lm.SCENES, "synthetic_long", dict(lm.SCENES["synthetic_long"]))


def test_roi_ceiling_runs_end_to_end_on_a_tiny_synthetic_circle(tmp_path, small_scenes):
    from bench.roi_ceiling import main

    out = tmp_path / "ceiling.json"
    rc = main(["--scene", "synthetic_long", "--synthetic-frames", "24", "--max-frames", "12", "--tasks", "1",
               "--iters", "3,6", "--fresh-moments", "--set", "iters_per_frame=3", "--set", "warmup_iters=1",
               "--work", str(tmp_path / "work"), "--out", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    (task,) = res["roi_only"]
    curve = res["roi_only"][task]
    assert [c["iters"] for c in curve] == [3, 6]
    assert all(c["roi_psnr"] > 5 for c in curve) and res["n_roi_views"][task] >= 1
    assert res["before"]["roi_psnr"][task] > 5 and res["full_pass"]["iters"] == 3
    assert res["full_pass"]["psnr"] > 5 and res["settings"]["fresh_moments"] is True
    md = out.with_suffix(".md").read_text()
    assert "ceiling − map" in md and f"| {task} |" in md


def test_roi_ceiling_rejects_bad_iteration_lists(tmp_path, small_scenes):
    from bench.roi_ceiling import main

    for bad in ("0,5", "10,5", "a"):
        with pytest.raises(SystemExit):
            main(["--scene", "synthetic_long", "--iters", bad, "--work", str(tmp_path)])
