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
    # The synthetic room has uniformly random rotations and attributes (close to incompressible); with
    # the precision that keeps the ROI PSNR cost within 0.05 dB (0.25 mm means, 9-bit log-scales) it
    # takes 16.25 B/G, while a real mapped map (Replica room0) takes 15.22 B/G (bench.quant_psnr, retired:
    # docs/history.md#quant_psnr).
    assert q["bytes_per_gaussian"] < 16.5 < ll["bytes_per_gaussian"] < codec.PLY_BYTES_PER_GAUSSIAN
    assert q["errors"]["means_mm"]["max"] <= 0.26 and q["errors"]["kappa_exact"]
    assert ll["errors"]["means_mm"]["max"] == 0.0 and ll["errors"]["quat_deg"]["max"] == 0.0
