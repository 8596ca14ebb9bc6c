"""bench.pruning: the pruning curve read from the committed live results (docs/realtime.md#pruning)."""

import json

import pytest

from bench import pruning
from bench.report import HEADLINE_PRIMARY, protocol


def test_the_curve_has_a_point_per_scene_mode_and_setting_read_from_the_results(tmp_path):
    out = tmp_path / "curve.json"
    pruning.main(["--results", str(pruning.RESULTS), "--out", str(out)])
    doc = json.loads(out.read_text())
    assert doc["provenance"]["command"].startswith("python -m bench.pruning")
    points = doc["points"]
    assert len(points) == 3 * 4 * 2  # TUM's two tasks and the walk, four settings, two modes
    assert all(q["pruned_share"] == 0.0 for q in points if q["setting"] == "off")
    for q in points:  # each point is its result file's figure
        res = json.loads((pruning.RESULTS / q["source"]).read_text())
        assert q["roi_psnr"] == protocol(res, q["scene"], HEADLINE_PRIMARY)[q["mode"]]["roi_psnr"]
        if q["setting"] != "off":
            runs = [r for r in res["runs"] if r["scene"] == q["scene"] and r["mode"] == q["mode"]]
            pruned = sum(r["pruned"] for r in runs) / len(runs)
            final = sum(r["n_gaussians"] for r in runs) / len(runs)
            assert q["pruned_share"] == pytest.approx(pruned / (pruned + final))
    # more pixels prune more: 20 px prunes a larger share than 1 px in every scene and mode
    share = {(q["scene"], q["mode"], q["setting"]): q["pruned_share"] for q in points}
    assert all(share[(s, m, "20")] > share[(s, m, "1")] for s, m, _ in share)
    png = out.with_suffix(".png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert "| TUM fr1/rpy, pick up the cup | off |" in out.with_suffix(".md").read_text()


def test_no_results_is_an_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="realtime_prune"):
        pruning.main(["--results", str(tmp_path), "--out", str(tmp_path / "c.json")])
