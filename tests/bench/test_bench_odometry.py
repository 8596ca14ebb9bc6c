"""bench.odometry on a tiny synthetic circle: the JSON per sequence and variant (ATE, RPE per frame and per second,
ms per frame, tracked fraction, the run's provenance and load average) and the printed table."""

import json

import pytest


@pytest.fixture(scope="module")
def circle(tmp_path_factory):
    """The ``--work`` folder of the synthetic circle's 90 frames at 160×120, rendered by the first test that reads it
    and read by the next (the bench renders a sequence once into ``--work``)."""
    return tmp_path_factory.mktemp("circle")


def test_odometry_bench_smoke(tmp_path, capsys, circle):
    import bench.odometry as bo

    out = tmp_path / "odometry.json"
    # at 160×120 the mapping resolution is the default's tracking size: the two variants would be the same run
    assert bo.main(["--sequences", "synthetic_circle", "--synthetic-frames", "90", "--synthetic-size", "160x120",
                    "--variants", "default,frame_to_frame", "--work", str(circle), "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["provenance"]["command"].startswith("python -m bench.odometry --sequences synthetic_circle")
    assert len(res["load_average_before"]) == 3 and res["odometry_defaults"]["reference"] == "nearest_keyframe"
    assert set(res["sequences"]["synthetic_circle"]) == {"default", "frame_to_frame"}
    for variant in ("default", "frame_to_frame"):
        r = res["sequences"]["synthetic_circle"][variant]
        assert r["frames"] == 90 and r["size"] == [160, 120] and r["ms_per_frame"] > 0
        assert r["tracked_fraction"] > 0.9 and r["ate_rmse_m"] < 0.1
        assert r["rpe"]["per_frame"]["pairs"] == 89 and r["rpe"]["per_second"]["trans_rmse_m"] is not None
        assert r["ate_online_m"] < 0.1 and r["loops"]["false"] == 0 and r["lost"] == 0
    printed = capsys.readouterr().out
    assert "| synthetic_circle | default | 90 | 160×120 | 160×120 |" in printed
    assert printed.count("| synthetic_circle |") == 2 and out.with_suffix(".md").is_file()


def test_the_covered_walk_loses_the_covered_frames_and_counts_what_it_found_again(tmp_path):
    import bench.odometry as bo

    # the walk in 50 frames of 96×72: its lens covered for 3 of them, re-localised after, loops closed on the way back
    out = tmp_path / "odometry.json"
    assert bo.main(["--sequences", "synthetic_walk_covered", "--walk-frames", "50", "--synthetic-size", "96x72",
                    "--variants", "default,no_relocalisation", "--work", str(tmp_path), "--out", str(out)]) == 0
    res = json.loads(out.read_text())["sequences"]["synthetic_walk_covered"]
    covered = list(bo.covered(50))
    assert len(covered) == 3
    for variant in ("default", "no_relocalisation"):
        r = res[variant]
        assert r["frames"] == 50 and r["lost"] >= len(covered) and set(covered) <= set(r["lost_frame_ids"])
        assert r["loops"]["false"] == 0
    assert res["default"]["relocalised"] >= 1 and res["default"]["loops"]["accepted"] >= 1
    assert res["no_relocalisation"]["relocalised"] == 0


def test_loop_accuracy_registers_each_candidate_with_each_registration(tmp_path, capsys, circle):
    import bench.odometry as bo

    out = tmp_path / "odometry.json"
    assert bo.main(["--sequences", "synthetic_circle", "--synthetic-frames", "90", "--synthetic-size", "160x120",
                    "--loop-accuracy", "--work", str(circle), "--out", str(out)]) == 0
    acc = json.loads(out.read_text())["loop_accuracy"]["synthetic_circle"]
    assert acc["candidates"] > 0
    for name in bo.LOOP_REGISTRATIONS:
        v = acc[name]
        assert 0 <= v["within_2cm"] <= v["within_3cm"] <= acc["candidates"] and v["ms_median"] > 0
        assert v["median_cm"] >= 0 and v["median_deg"] >= 0
    # the candidates are the shipped odometry's: its loop closure is what wraps the registrations, and it is restored
    from gausslite.odometry import loop_closing, pose_graph
    assert loop_closing.verify_registration is pose_graph.verify_registration
    printed = capsys.readouterr().out
    assert printed.count("| synthetic_circle |") == 1 + len(bo.LOOP_REGISTRATIONS)


def test_the_live_table_gives_each_variant_its_mean_and_spread_over_runs():
    import bench.odometry as bo

    def run(variant, on_time, loops, iters=None):
        return {"variant": variant, "keyframe_budget_s": 0.5, "tracked_fraction": 1.0, "lost": 0, "track_ms_mean": 27.2,
                "track_ms_p95": 37.4, "on_time_fraction": on_time, "late_s_max": 0.1, "loops": loops,
                "frames_keyframed": 20, **({} if iters is None else {"iters_per_keyframe": iters})}

    rows = bo.live_table([run("default", 0.98, 6, 24.0), run("default", 0.96, 4, 26.0), run("loops_inline", 0.84, 6)])
    rows = rows.splitlines()
    assert len(rows) == 4
    assert rows[2] == ("| 0.5 s | default | 2 | 100 ± 0 % | 0 ± 0 | 27 ± 0 / 37 ± 0 | 97 ± 1 % | 0.10 ± 0.00 | "
                       "5.0 ± 1.4 | 20 ± 0 | 25.0 ± 1.4 |")
    # a run recorded without the mapper's iterations (an older result) shows none
    assert rows[3].startswith("| 0.5 s | loops_inline | 1 | 100 % |") and "| 84 % |" in rows[3]
    assert rows[3].endswith("| 20 | – |")


def _realtime_result(pose_source, gain, ci, uniform, gausslite):
    novel = {"gain": gain, "gain_ci": ci, "gain_frames": 30,
             "uniform": {"roi_psnr": uniform, "runs": 3}, "gausslite": {"roi_psnr": gausslite, "runs": 3}}
    return {"settings": {"pose_source": pose_source},
            "scenes": {"tum_fr1_rpy": {"budgets": {"0.5": {"protocols": {"novel": novel, "sensor": novel}}}}}}


def test_the_gain_at_the_odometrys_poses_is_compared_with_the_gain_at_the_given_ones(tmp_path):
    import bench.odometry as bo

    given, odo = tmp_path / "given.json", tmp_path / "odo.json"
    given.write_text(json.dumps(_realtime_result("given", 1.5, [0.5, 2.5], 21.0, 22.5)))
    odo.write_text(json.dumps(_realtime_result("odometry", 0.9, [0.6, 1.2], 20.0, 20.9)))
    g = bo.pose_gains(given, odo)["tum_fr1_rpy"]
    d = g["gain_estimated_minus_given"]
    assert abs(d["mean"] + 0.6) < 1e-9
    half = (1.0 ** 2 + 0.3 ** 2) ** 0.5  # the half-widths in quadrature
    assert abs(d["ci"][0] - (-0.6 - half)) < 1e-9 and abs(d["ci"][1] - (-0.6 + half)) < 1e-9
    assert g["roi_psnr"]["estimated"] == {"uniform": 20.0, "gausslite": 20.9} and g["runs"]["estimated"] == 3
    row = bo.gains_table({"tum_fr1_rpy": g}).splitlines()[-1]
    assert row.startswith("| tum_fr1_rpy | 21.00 / 22.50 | 20.00 / 20.90 | +1.50 [+0.50, +2.50] | +0.90 [+0.60, +1.20]")
    with pytest.raises(ValueError, match="pose-source odometry"):
        bo.pose_gains(odo, given)  # the files swapped


def test_the_walk_with_the_tum_sensor_is_rendered_beside_the_realistic_one(tmp_path):
    import bench.odometry as bo

    frames = bo.load_sequence("synthetic_walk_tum", tmp_path, 0, (48, 36), walk_frames=4)
    assert len(frames) == 4 and frames[0].depth.shape == (36, 48)
    meta = json.loads((tmp_path / "walk_tum" / "scene.json").read_text())
    assert meta["sensor_noise"] == "tum" and not (tmp_path / "walk").exists()
    assert abs(frames[0].intrinsics.fx - 48 * 546.75 / 640) < 1e-6  # the Kinect's field of view


def test_the_scan_walk_is_the_tum_walk_looking_around(tmp_path):
    import numpy as np

    import bench.odometry as bo

    walk = bo.load_sequence("synthetic_walk_tum", tmp_path, 0, (48, 36), walk_frames=12)
    scan = bo.load_sequence("synthetic_scan_walk_tum", tmp_path, 0, (48, 36), walk_frames=12)
    meta = json.loads((tmp_path / "scan_walk_tum" / "scene.json").read_text())
    assert meta["trajectory"] == "scan_walk" and meta["sensor_noise"] == "tum"
    # the same path, looking elsewhere (how fast it turns: tests/datasets/test_synthetic_walk.py)
    assert np.allclose([f.c2w[:3, 3] for f in scan], [f.c2w[:3, 3] for f in walk])
    assert not np.allclose([f.c2w[:3, :3] for f in scan[1:-1]], [f.c2w[:3, :3] for f in walk[1:-1]])


def test_walk_seeds_are_their_own_sequences(tmp_path):
    """``--walk-seeds 0,1``: the walk once per rendering, seed 1 as ``<name>_seed1`` from its own folder (the folder
    bench.sensor_calibration, retired: docs/history.md#sensor_calibration renders it into), with another trajectory;
    sequences that are not walks run once."""
    import numpy as np

    import bench.odometry as bo

    out = bo.run(["synthetic_scan_walk_tum"], ["default"], 0, (48, 36), tmp_path, walk_frames=6, walk_seeds=(0, 1))
    assert list(out) == ["synthetic_scan_walk_tum", "synthetic_scan_walk_tum_seed1"]
    assert all(out[k]["default"]["frames"] == 6 for k in out)
    assert (bo.walk_dir(tmp_path, "tum", 1, "scan_walk") / "agent_a" / "traj.txt").is_file()
    a = bo.load_sequence("synthetic_scan_walk_tum", tmp_path, 0, (48, 36), walk_frames=6)
    b = bo.load_sequence("synthetic_scan_walk_tum", tmp_path, 0, (48, 36), walk_frames=6, seed=1)
    assert not np.allclose([f.c2w for f in a], [f.c2w for f in b])
