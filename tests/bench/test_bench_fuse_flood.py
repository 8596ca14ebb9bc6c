"""bench.fuse_flood end to end on a tiny run (a real fusion server process, a read-only member calling Fuse)."""

from __future__ import annotations

import json

from bench.fuse_flood import main


def test_fuse_flood_tiny_run_keeps_the_store_bounded(tmp_path):
    out = tmp_path / "fuse_flood.json"
    rc = main(["--calls", "30", "--every", "5", "--keep", "4", "--gaussians", "300", "--work", str(tmp_path / "w"),
               "--out", str(out), "--no-progress"])
    res = json.loads(out.read_text())
    held = [s["fused_held"] for s in res["samples"]]
    assert held[0] == 1 and max(held) == 4 == res["fused_held_max"]  # retention: never more than --keep
    assert [s["calls"] for s in res["samples"]] == [1, 5, 10, 15, 20, 25, 30]
    assert res["samples"][-1]["store_bytes"] > 0 and res["stats_bytes_max"] < 1 << 20
    assert rc == 0 and all(res["goals"].values())
    md = out.with_suffix(".md").read_text()
    assert "python -m bench.fuse_flood" in md and "| store_bounded | met |" in md
