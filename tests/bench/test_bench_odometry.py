"""bench.odometry on a tiny synthetic circle: the JSON per sequence and variant (ATE, RPE per frame and per second,
ms per frame, tracked fraction, the run's provenance and load average) and the printed table."""

import json


def test_odometry_bench_smoke(tmp_path, capsys):
    import bench.odometry as bo

    out = tmp_path / "odometry.json"
    assert bo.main(["--sequences", "synthetic_circle", "--synthetic-frames", "90", "--synthetic-size", "160x120",
                    "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["provenance"]["command"].startswith("python -m bench.odometry --sequences synthetic_circle")
    assert len(res["load_average_before"]) == 3 and res["odometry_defaults"]["reference"] == "nearest_keyframe"
    for variant in ("default", "mapping_resolution", "frame_to_frame"):
        r = res["sequences"]["synthetic_circle"][variant]
        assert r["frames"] == 90 and r["size"] == [160, 120] and r["ms_per_frame"] > 0
        assert r["tracked_fraction"] > 0.9 and r["ate_rmse_m"] < 0.1
        assert r["rpe"]["per_frame"]["pairs"] == 89 and r["rpe"]["per_second"]["trans_rmse_m"] is not None
    printed = capsys.readouterr().out
    assert "| synthetic_circle | default | 90 | 160×120 | 160×120 |" in printed
    assert printed.count("| synthetic_circle |") == 3 and out.with_suffix(".md").is_file()


def test_the_live_table_reads_the_live_figures():
    import bench.odometry as bo

    r = {"keyframe_budget_s": 0.5, "tracked_fraction": 0.96, "lost": 6, "track_ms_mean": 27.2, "track_ms_p95": 37.4,
         "on_time_fraction": 1.0, "late_s_max": 0.0, "frames_keyframed": 20}
    assert bo.live_table(r).splitlines()[-1] == "| keyframe budget 0.5 s | 96 % | 6 | 27 / 37 | 100 % | 0.00 | 20 |"
