"""bench.mapper: the JSON schema (baseline/fast per scene, mean ± std over seeds, paired
speed-up and ROI PSNR loss) and an end-to-end smoke run on the synthetic scene."""

import json

import pytest

from bench.mapper import summarise, table


def _run(setting, seed, task, s, roi):
    return {"setting": setting, "seed": seed, "task": task, "s_per_keyframe": s, "roi_psnr": roi, "psnr": roi - 5,
            "n_gaussians": 1000, "iters_per_keyframe": 40}


def test_summarise_pairs_seeds():
    runs = []
    for seed, off in ((0, 0.0), (1, 1.0)):
        for task, t_off in (("a", 0.0), ("b", 2.0)):
            runs.append(_run("baseline", seed, task, 4.0, 30 + off + t_off))
            runs.append(_run("fast", seed, task, 1.0 + 0.5 * seed, 29.5 + off + t_off))
    out = summarise(runs, ["baseline", "fast"], [0, 1])
    for st in ("baseline", "fast"):
        for k in ("s_per_keyframe", "roi_psnr", "psnr"):
            assert k in out[st] and k + "_std" in out[st]
        assert out[st]["seeds"] == [0, 1]
    assert out["baseline"]["roi_psnr"] == pytest.approx(31.5)  # tasks averaged within a seed, then seeds
    assert out["speedup"] == pytest.approx((4.0 + 4.0 / 1.5) / 2)
    assert out["roi_psnr_loss"] == pytest.approx(0.5) and out["roi_psnr_loss_std"] == pytest.approx(0.0)
    md = table({"settings": ["baseline", "fast"], "scenes": {"s": out}})
    assert "| s | baseline |" in md and "fast vs baseline" in md


def test_bench_mapper_smoke(tmp_path, monkeypatch):
    """Two frames, one task, one seed, both settings: the JSON has the issue's fields and the fast
    baseline ran the reference paths (no timing assertion: speed is a benchmark figure)."""
    import bench.mapper as bm

    monkeypatch.setattr(bm, "WORK", tmp_path / "work")
    out = tmp_path / "mapper.json"
    assert bm.main(["--scenes", "synthetic", "--seeds", "1", "--tasks", "1", "--max-frames", "2",
                    "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    blk = res["scenes"]["synthetic"]
    for st in ("baseline", "fast"):
        for k in ("s_per_keyframe", "roi_psnr", "psnr"):
            assert isinstance(blk[st][k], float)
    assert blk["frames"] == 2 and (blk["width"], blk["height"]) == (160, 120)
    assert {r["setting"] for r in blk["runs"]} == {"baseline", "fast"}
    assert res["presets"]["baseline"] == {"performance": {"reference_paths": True, "cpu_kernel": "tile"}} and res["presets"]["fast"] == {}
    assert "speedup" in blk and "roi_psnr_loss" in blk
    assert out.with_suffix(".md").read_text().count("| synthetic |") >= 2
