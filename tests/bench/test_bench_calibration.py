"""bench.calibration on the first frames of the shared TUM fr1/rpy and Replica room0: the JSON per camera variant
(the camera read, the odometry's ATE per run, the consistency with the ground truth and its paired comparison with
the default), the depth-scale sweeps, Replica's camera against its cam_params.json, and the printed tables; and the
warp itself on a synthetic pair whose answer is known."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame


def _plane_pair(depth_factor: float = 1.0):
    """Two 64×48 views of a textured plane at 2 m, the second 10 cm to the right; the second view's depth is
    multiplied by ``depth_factor`` (1: the views agree)."""
    intr = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    vv, uu = np.mgrid[0:48, 0:64]

    def view(tx: float, factor: float) -> Frame:
        x_world = (uu - intr.cx) / intr.fx * 2.0 + tx  # the plane's x under each pixel
        shade = (127 + 100 * np.sin(6.0 * x_world)).astype(np.uint8)
        c2w = np.eye(4)
        c2w[0, 3] = tx
        return Frame(0 if tx == 0 else 1, 0.0, np.repeat(shade[..., None], 3, 2), np.full((48, 64), 2.0 * factor,
                     np.float32), c2w, intr)

    return view(0.0, 1.0), view(0.1, depth_factor)


def test_the_warp_of_agreeing_views_has_no_error_and_a_scaled_depth_shows():
    from bench.calibration import warp_pair

    fi, fj = _plane_pair()
    r = warp_pair(fi, fj)
    assert r["depth_rel_pct"] < 1e-4 and abs(r["depth_bias_pct"]) < 1e-4
    assert r["colour_l1"] < 1.0 and abs(r["covered"] - 61 / 64) < 1e-9  # 10 cm at 2 m: 3 of 64 columns leave
    fi, fj = _plane_pair(1.035)
    r = warp_pair(fi, fj)
    assert abs(r["depth_bias_pct"] - 100 * (1 / 1.035 - 1)) < 1e-3 and abs(r["depth_rel_pct"] - 3.38) < 0.01


def test_calibration_bench_on_the_first_frames(tmp_path, capsys, tum_rpy_dir, room0_dir):
    import bench.calibration as bc

    out = tmp_path / "calibration.json"
    assert bc.main(["--tum", str(tum_rpy_dir), "--replica", str(room0_dir.parent), "--max-frames", "8",
                    "--runs", "2", "--gaps", "1", "--variants", "fr1_undistorted,ros_default",
                    "--depth-multipliers", "1,1.035", "--replica-multipliers", "0.97,1,1.03", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["provenance"]["command"].startswith("python -m bench.calibration --tum")
    tum = res["tum"]
    assert set(tum["variants"]) == {"fr1_undistorted", "ros_default"}
    default, ros = tum["variants"]["fr1_undistorted"], tum["variants"]["ros_default"]
    assert default["camera"]["file_intrinsics"] == [517.3, 516.5, 318.6, 255.3]
    assert default["camera"]["undistorted_with"] == [0.2624, -0.9531, -0.0054, 0.0026, 1.1633]
    assert ros["camera"]["intrinsics"] == [525.0, 525.0, 319.5, 239.5] and ros["camera"]["undistorted_with"] is None
    for v in (default, ros):
        assert len(v["ate"]["runs"]) == 2 and 0 <= v["ate"]["mean_m"] < 0.1 and v["ate"]["std_m"] >= 0
        adj = v["consistency"]["adjacent"]
        assert adj["n_pairs"] == 7 and 0 < adj["colour_l1"][0] < 40 and 0 < adj["depth_rel_pct"][0] < 10
    cmp = tum["compare"]["ros_default"]
    assert cmp["colour_l1_minus_default"]["n"] == 7 and cmp["beyond_spread"] in (True, False)
    assert tum["compare"]["fr1_undistorted"]["ate_minus_default_m"] == 0.0
    assert [r["multiplier"] for r in tum["depth_sweep"]] == [1.0, 1.035]
    assert tum["verdict"]["default"] == "fr1_undistorted"
    rep = res["replica"]
    assert rep["agree"] and rep["loader"]["native"] == [600.0, 600.0, 599.5, 339.5, 1200, 680]
    assert rep["loader"]["scaled"] == [150.0, 150.0, 149.5, 84.5, 300, 170] and rep["loader"]["depth_scale"] == 6553.5
    # rendered depth at exact poses: the file's scale agrees best, and better than 3 % off either way
    errs = {r["multiplier"]: r["adjacent"]["depth_rel_pct"][0] for r in rep["depth_sweep"]}
    assert errs[1.0] < 0.2 and errs[1.0] < min(errs[0.97], errs[1.03])
    printed = capsys.readouterr().out
    assert "| fr1_undistorted (default) | 546.75, 543.09, 320.08, 251.85 (undistorted) | 5000.0 |" in printed
    assert "| depth units per metre | 6553.5 | 6553.5 | True |" in printed and out.with_suffix(".md").is_file()


def test_a_variant_list_without_the_default_is_refused():
    import bench.calibration as bc

    with pytest.raises(SystemExit):
        bc.main(["--variants", "ros_default"])
    with pytest.raises(SystemExit):
        bc.main(["--variants", "fr1_undistorted,no_such_camera"])
