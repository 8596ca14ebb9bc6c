"""bench.trust_load end to end on a tiny run (a real fusion server process, stalled streams, wrong tokens, a valid
robot pushing), and its table."""

from __future__ import annotations

import json

from bench.trust_load import main, percentiles, table


def test_percentiles():
    p = percentiles([float(v) for v in range(1, 101)])
    assert p["p50"] == 50.5 and p["max"] == 100.0 and 98.0 < p["p99"] < 100.0
    assert percentiles([]) == {"p50": None, "p95": None, "p99": None, "max": None}


def test_trust_load_tiny_run(tmp_path):
    out = tmp_path / "trust_load.json"
    main(["--seconds", "3", "--idle-s", "1", "--stalled", "4", "--bad-rate", "10", "--gaussians", "200",
          "--token-scheme", "sha256", "--work", str(tmp_path / "work"), "--out", str(out), "--no-progress"])
    res = json.loads(out.read_text())
    assert res["acks"] > 5 and res["ack_ms"]["p50"] > 0 and res["ack_ms"]["max"] >= res["ack_ms"]["p99"]
    # one robot identity: 2 streams held (per-caller bound), ended by the 1 s deadline and re-opened; the rest refused
    assert res["stalled_ended_by_deadline"] >= 2 and res["stalled_refused"] >= 2
    assert 0.9 < res["stalled_s_median"] < 3.0
    assert res["bad_calls"] >= 10 and set(res["bad_codes"]) <= {"UNAUTHENTICATED", "RESOURCE_EXHAUSTED"}
    assert res["health_after"] == "SERVING" and res["rss_mb_peak"] > 10
    md = out.with_suffix(".md").read_text()
    assert "python -m bench.trust_load" in md and "ack latency p50 / p95 / p99 / max" in md
    assert table(res) in md and "goal: ack p99 <= 250 ms" in md
