"""bench.cross_scoring: both modes' maps of a real-time run scored on the withheld frames at each map's predicted
pose, at its own tracked pose, and at the poses tracked against the other map."""

from __future__ import annotations

import json

import pytest

from bench import cross_scoring as cs


def test_cross_scoring_holds_the_view_or_the_map_fixed(tmp_path):
    """On the deterministic twin of a tiny synthetic scene: the rows that share a view with ``own tracked`` give the
    very same per-frame figures for the map that view was tracked on (same view, same map), and every gain is the
    paired per-frame mean with its interval."""
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=8, width=64, height=48, trajectory="circle", progress=False)
    out = tmp_path / "cs.json"
    argv = ["--dataset", str(tmp_path / "scene" / "agent_a"), "--tasks", "synth-pick-object", "--budget", "0.08",
            "--runs", "1", "--twin", "--cap", "300", "--novel-every", "3", "--track-iters", "3",
            "--set", "mapper.seeding.seeds_per_frame=300", "--work", str(tmp_path / "work"), "--out", str(out)]
    assert cs.main(argv) == 0
    res = json.loads(out.read_text())
    (pair,) = res["pairs"]
    rows = pair["rows"]
    assert set(rows) == {name for name, _, _ in cs.ROWS} | {"offset"}
    assert set(rows["predicted"]["uniform"]) == {"1", "4", "7"}  # every 3rd frame from the 2nd, withheld
    assert rows["tracked on uniform"]["uniform"] == rows["own tracked"]["uniform"]
    assert rows["tracked on GaussLite"]["gausslite"] == rows["own tracked"]["gausslite"]
    blk = res["summary"]["synth-pick-object"]["0.08"]
    for name, _, _ in cs.ROWS:
        g = blk[name]["gain"]
        want = sum(rows[name]["gausslite"][k] - rows[name]["uniform"][k] for k in rows[name]["uniform"]) / 3
        assert g["n"] == 3 and g["gain"] == pytest.approx(want) and g["ci_low"] <= g["gain"] <= g["ci_high"]
    md = out.with_suffix(".md").read_text()
    assert md.startswith("# bench.cross_scoring") and "| synth-pick-object | 0.08 | tracked on GaussLite |" in md
