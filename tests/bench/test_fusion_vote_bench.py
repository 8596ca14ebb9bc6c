"""Smoke test of ``python -m bench.vote --quick``: runs, writes JSON, vote is consistent."""

from __future__ import annotations

import json

from bench import vote


def test_vote_bench_quick(tmp_path):
    out = tmp_path / "vote.json"
    res = vote.main(["--quick", "--out", str(out)])
    saved = json.loads(out.read_text())
    assert saved["n"] == res["n"] == 100_000
    rep = saved["report"]
    assert sum(rep["kept"].values()) == saved["fused_n"]
    assert sum(rep["kept"].values()) + sum(rep["dropped"].values()) == saved["n"]
    assert 0 < rep["contested_voxels"] <= rep["voxels"]
    assert saved["vote_s_min"] < 1.0  # 100k Gaussians on one core: far below the 1M target
