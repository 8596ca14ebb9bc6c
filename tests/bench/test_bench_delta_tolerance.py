"""bench.delta_tolerance: one mapping, every tolerance planned on the same snapshots."""

import json


def test_delta_tolerance_smoke(tmp_path, room0_dir):
    import bench.delta_tolerance as bd

    out = tmp_path / "dt.json"
    assert bd.main(["--dataset", str(room0_dir), "--downscale", "8", "--max-frames", "4", "--push-every", "2",
                    "--tolerances", "1,16", "--kappa-rel", "1e9", "--seeds", "1", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    t1, t16 = res["tolerances"]["1/1e+09"], res["tolerances"]["16/1e+09"]
    run = res["runs"][0]
    assert [p["version"] for p in run["by_tolerance"]["1/1e+09"]["pushes"]] == [1, 2]
    assert not run["by_tolerance"]["1/1e+09"]["pushes"][0]["delta"]  # the first push is always whole
    # a looser tolerance never sends more rows or bytes, and the ratio is against the same final subset
    assert t16["records"] <= t1["records"] and t16["total_upload_bytes"] <= t1["total_upload_bytes"]
    # every Gaussian of the final subset reached the server at least once, whatever the tolerance
    assert t16["records"] >= run["n_shared"] and t1["records"] >= run["n_shared"]
    assert res["final_subset_bytes"] > 0 and 0 < res["roi_psnr_exact"] < 100
    for t in (t1, t16):
        assert 0 < t["roi_psnr_server"] < 100
    assert "| 16/1e+09 |" in out.with_suffix(".md").read_text()
