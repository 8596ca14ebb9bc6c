"""bench.soak's bookkeeping (the timed run itself is not part of the suite): growth over the last half, the
process-tree RSS and folder size readers, the table and the plot."""

from __future__ import annotations

import os

import pytest

from bench.soak import dir_mb, growth_last_half, parse_args, plot, table, tree_memory_mb, trend_last_half


def _samples(values):
    return [{"t_s": 10.0 * (i + 1), "v": v} for i, v in enumerate(values)]


def test_growth_over_the_last_half():
    # 6 samples to t = 60 s: the last half starts at the sample at t = 30 s (value 100)
    assert growth_last_half(_samples([50, 80, 100, 101, 103, 102]), "v") == pytest.approx(0.03)
    assert growth_last_half(_samples([50, 80, 100, 90, 95, 99]), "v") == pytest.approx(0.0)
    assert growth_last_half(_samples([10]), "v") is None
    assert growth_last_half([], "v") is None


def test_trend_over_the_last_half_sees_a_leak_and_not_a_transient():
    def minutes(values):  # one sample every 10 minutes
        return [{"t_s": 600.0 * (i + 1), "v": v} for i, v in enumerate(values)]

    flat_with_peak = minutes([50, 80, 100, 100, 130, 100, 100])  # a one-sample peak: growth counts it, trend hardly
    assert growth_last_half(flat_with_peak, "v") == pytest.approx(0.3)
    assert abs(trend_last_half(flat_with_peak, "v")) < 0.1
    leak = minutes([100, 101, 102, 103, 104, 105, 106])  # +1 per 10 min: +3 per 30 min, median 104.5 there
    assert trend_last_half(leak, "v") == pytest.approx(3 / 104.5)
    assert trend_last_half(minutes([1, 2]), "v") is None


def test_readers(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "x.bin").write_bytes(b"\0" * 2**20)
    (tmp_path / "y.bin").write_bytes(b"\0" * 2**19)
    assert dir_mb(tmp_path) == pytest.approx((1.5, 0.0))
    (tmp_path / "a" / ".checkpoint.pt.123.tmp").write_bytes(b"\0" * 2**20)  # an atomic write in flight: apart
    assert dir_mb(tmp_path) == pytest.approx((1.5, 1.0))
    assert tree_memory_mb(os.getpid())["rss"] > 10.0


def test_tree_memory_counts_children_apart():
    """A child holding 64 MB of written heap shows in the tree's anonymous memory and in its own entry; PSS (shared
    pages split) is at most the summed RSS."""
    import subprocess
    import sys
    import time

    child = subprocess.Popen([sys.executable, "-c", "import sys, time; b = bytearray(64 * 2**20); b[::4096] = "
                              "b'x' * len(b[::4096]); print('ok', flush=True); time.sleep(60)"],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ok"
        me = tree_memory_mb(os.getpid())
        kid = [p for p in me["procs"] if p["pid"] == child.pid]
        assert len(kid) == 1 and kid[0]["anon"] >= 60.0, me["procs"]
        assert me["anon"] >= kid[0]["anon"] + 1.0
        assert 0.0 < me["pss"] <= me["rss"] + 1e-6
        assert me["rss"] == pytest.approx(sum(p["rss"] for p in me["procs"]), abs=0.1 * len(me["procs"]))
    finally:
        child.kill()
        child.wait()
    time.sleep(0.05)
    assert tree_memory_mb(2**22 + 12345)["procs"] == []  # no such process


def test_table_and_plot(tmp_path):
    keys = ["rss_mb_agent", "rss_mb_fusion", "disk_mb_agent", "disk_mb_fusion", "accept_p99_ms",
            "keyframe_latency_s_p95", "n_gaussians", "fusion_subset_gaussians", "frames_keyframed", "pushes"]
    samples = [dict({k: 1.0 + i for k in keys}, t_s=10.0 * (i + 1)) for i in range(4)]
    res = {"samples": samples, "minutes": 0.7, "fps": 30.0, "scene": "test", "errors": [],
           "accept_p99_ms_max": 4.0, "growth_last_half": {"rss_mb_agent": 0.5, "disk_mb_agent": None},
           "goals": {"rss_mb_agent growth<=5%": False, "no errors": True}}
    md = table(res)
    assert md.count("\n| ") == 4 and "rss_mb_agent +50.0 %" in md and "disk_mb_agent n/a" in md
    assert "rss_mb_agent growth<=5% MISSED" in md
    plot(res, tmp_path / "soak.png")
    assert (tmp_path / "soak.png").stat().st_size > 10_000
    a = parse_args(["--minutes", "1", "--sample-s", "10"])
    assert (a.minutes, a.sample_s, a.fps) == (1.0, 10.0, 30.0)
