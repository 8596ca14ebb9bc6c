"""Smoke test of ``python -m bench.codec --quick``: runs, writes JSON, quantised beats lossless."""

from __future__ import annotations

import json

from bench import codec


def test_codec_bench_quick(tmp_path):
    out = tmp_path / "codec.json"
    res = codec.main(["--quick", "--out", str(out)])
    saved = json.loads(out.read_text())
    assert saved["n"] == res["n"] == 20_000
    by = {c["case"]: c for c in saved["cases"]}
    q, ll = by["quantised (default)"], by["lossless"]
    assert q["bytes_per_gaussian"] < 16.0 < ll["bytes_per_gaussian"] < codec.PLY_BYTES_PER_GAUSSIAN
    assert q["errors"]["means_mm"]["max"] <= 0.26 and q["errors"]["kappa_exact"]
    assert ll["errors"]["means_mm"]["max"] == 0.0 and ll["errors"]["quat_deg"]["max"] == 0.0
