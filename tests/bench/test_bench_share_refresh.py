"""bench.share_refresh and bench.sim_seeds: the refresh arms' bytes and scores; the
multi-seed sim summary."""

import json

import pytest


def test_share_refresh_smoke_room0(tmp_path, room0_dir):
    import bench.share_refresh as bs

    out = tmp_path / "sr.json"
    assert bs.main(["--dataset", str(room0_dir), "--downscale", "8", "--max-frames", "4", "--push-every", "2",
                    "--seeds", "1", "--refresh", "1,0", "--finetune-iters", "6", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["scene"] == "room0" and res["refresh"] == [1.0, 0.0]
    for task in bs.SCENES["room0"]:
        blk = res["summary"][task]
        assert set(blk) == {"free", "r=1", "r=0"}
        for arm, b in blk.items():
            for k in ("alone", "vote", "vote_fresh_kappa", "own"):
                assert 5 < b[k] < 80, (task, arm, k, b[k])
            assert b["upload_ratio"] == pytest.approx(b["total_upload_bytes"] / b["final_subset_bytes"])
        run = res["runs"][0]["tasks"][task]
        # two pushes (frames 2 and 4): the first is full; with refresh 0 the delta carries only new rows, so it
        # is smaller than with every row free
        assert [p["frames"] for p in run["r=0"]["pushes"]] == [2, 4] and not run["r=0"]["pushes"][0]["delta"]
        assert run["r=0"]["pushes"][1]["records"] < run["r=1"]["pushes"][1]["records"]
        assert blk["r=0"]["total_upload_bytes"] < blk["free"]["total_upload_bytes"]
    assert "| room0-pick-plant | r=0 |" in out.with_suffix(".md").read_text()


def test_sim_seeds_summary_and_table():
    import bench.sim_seeds as ss

    def report(seed_shift):
        agents = [{"id": "agent_a", "task": "t1", "share_pct": 5.0 + seed_shift, "bytes_per_gaussian": 12.0,
                   "upload_ratio": 1.4, "own_roi_psnr_context": 30.0},
                  {"id": "agent_b", "task": "t2", "share_pct": 6.0, "bytes_per_gaussian": 13.0, "upload_ratio": 1.5,
                   "own_roi_psnr_context": None}]
        fused = {k: {"roi_psnr_per_task": {"t1": v + seed_shift, "t2": v}} for k, v in
                 (("concat", 20.0), ("vote", 31.0), ("refine", 32.0))}
        return {"agents": agents, "fused": fused}

    summary = ss.summarise([ss.agent_rows(report(0.0)), ss.agent_rows(report(2.0))])
    a = summary["agent_a t1"]
    assert a["share_pct"] == pytest.approx(6.0) and a["vote_minus_own_per_seed"] == pytest.approx([1.0, 3.0])
    assert a["refine_minus_own"] == pytest.approx(3.0)
    b = summary["agent_b t2"]
    assert b["own_context"] is None and b["vote_minus_own_per_seed"] == []
    with pytest.raises(ValueError):
        ss.scene_args("mars")
    md = ss.table({"room0": {"agent_a t1": a}})
    assert "| room0 | agent_a t1 |" in md and "(+1.00, +3.00)" in md
