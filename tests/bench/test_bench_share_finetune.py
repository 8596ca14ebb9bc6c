"""bench.share_finetune: two agents, fine-tuned subsets, both vote rules, both refine schedules."""

import json


def test_share_finetune_smoke(tmp_path, room0_dir):
    import bench.share_finetune as bs

    out = tmp_path / "sf.json"
    assert bs.main(["--dataset", str(room0_dir), "--downscale", "8", "--max-frames", "4", "--seeds", "1",
                    "--finetune-iters", "30", "--refine-iters", "3", "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert set(res["tasks"]) == set(bs.TASKS) and res["seeds"] == [0]
    for task, b in res["tasks"].items():
        for k in bs.FIELDS:
            assert 5 < b[k] < 80, (task, k, b[k])
        assert b["n_shared"] > 0 and b["finetune_s"] > 0
        # fine-tuning the subset alone on its ROI keyframes improves how it renders alone
        assert b["alone_ft"] > b["alone_raw"], (task, b["alone_raw"], b["alone_ft"])
        assert abs(b["vote_r1_minus_own"] - (b["vote_r1"] - b["own"])) < 1e-9
    md = out.with_suffix(".md").read_text()
    assert "| room0-pick-plant |" in md and "vote r=1" in md
