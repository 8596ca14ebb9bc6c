"""bench.long_mission's aggregation: the JSON schema (mean, ``_std`` and seeds per field,
uniform scored on every task's ROI, paired gains) and gausslite.stats."""

import math

import pytest

from bench.long_mission import summarise, table
from gausslite.stats import aggregate, gain, mean_std


def _run(mode, seed, task, roi, psnr, fifths):
    return {"scene": "s", "mode": mode, "task": task, "seed": seed, "psnr": psnr, "roi_psnr_per_task": roi,
            "psnr_by_fifth": fifths, "heldout_psnr": psnr - 1, "s_per_frame": 2.0,
            "s_per_frame_by_fifth": [2.0] * 5, "n_gaussians": 1000, "keyframe_mb": 3.0}


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """``--work``: where the bench generates its synthetic scene (the same 24-frame circle for every run here, made
    once and only read by the runs)."""
    return tmp_path_factory.mktemp("work")


def test_summarise_follows_the_issue_schema():
    runs = []
    for s, off in ((0, 0.0), (1, 1.0)):
        runs.append(_run("uniform", s, None, {"a": 20 + off, "b": 22 + off}, 21 + off, [18, 19, 20, 21, 22]))
        runs.append(_run("gausslite", s, "a", {"a": 25 + off}, 20 + off, [20, 20, 20, 20, 20]))
        runs.append(_run("gausslite", s, "b", {"b": 26 + off}, 22 + off, [20, 20, 20, 20, 20]))
    out = summarise(runs, "s", ["a", "b"], [0, 1])
    u, g = out["uniform"], out["gausslite"]
    assert out["tasks"] == ["a", "b"]
    for b in (u, g):
        for k in ("psnr", "roi_psnr", "psnr_by_fifth", "heldout_psnr", "s_per_frame", "n_gaussians"):
            assert k in b and k + "_std" in b
        assert b["seeds"] == [0, 1]
        assert len(b["psnr_by_fifth"]) == 5
    assert u["roi_psnr"] == pytest.approx(21.5)  # mean over tasks a, b on the uniform map, then seeds
    assert u["roi_psnr_std"] == pytest.approx(math.sqrt(0.5))
    assert g["roi_psnr"] == pytest.approx(26.0)
    assert u["retention_db"] == pytest.approx(18 - 22)
    assert out["roi_gain"]["gain"] == pytest.approx(4.5) and out["roi_gain"]["gain_std"] == pytest.approx(0.0)
    assert out["roi_gain"]["significant"]
    md = table({"scenes": {"s": out}})
    assert "| s | uniform |" in md and "ROI gain" in md and "significant" in md


def test_stats_helpers():
    assert mean_std([1.0, 3.0]) == (2.0, pytest.approx(math.sqrt(2)))
    assert mean_std([5.0]) == (5.0, 0.0)
    assert mean_std([None, float("nan")]) == (None, None)
    agg = aggregate([{"x": 1.0, "l": [1, 2]}, {"x": 3.0, "l": [3, 4]}], ["x", "l"])
    assert agg["x"] == 2.0 and agg["l"] == [2.0, 3.0] and agg["l_std"][0] == pytest.approx(math.sqrt(2))
    g = gain([3.0, 3.2, 2.8], [1.0, 1.0, 1.0])
    assert g["significant"] and g["n"] == 3
    noisy = gain([3.0, -1.0], [1.0, 1.0])  # mean 0 ± 2.8: not a gain
    assert not noisy["significant"]
    assert not gain([2.0], [1.0])["significant"]  # one seed can never show significance
    with pytest.raises(ValueError):
        gain([1.0], [1.0, 2.0])


def test_bench_runs_end_to_end_on_a_tiny_synthetic_circle(tmp_path, work):
    """``python -m bench.long_mission`` on a 24-frame synthetic circle (first 20 frames, 10 mapped, 3 iterations each):
    JSON in the issue's schema, the table, the plot, and no partial file left behind."""
    import json

    from bench.long_mission import main

    out = tmp_path / "lm.json"
    rc = main(["--scenes", "synthetic_long", "--seeds", "1", "--tasks", "1", "--jobs", "1", "--synthetic-frames", "24",
               "--max-frames", "20", "--set", "iters_per_frame=3", "--set", "warmup_iters=1",
               "--work", str(work), "--out", str(out)])
    assert rc == 0
    res = json.loads(out.read_text())
    sc = res["scenes"]["synthetic_long"]
    for mode in ("uniform", "gausslite"):
        assert sc[mode]["psnr"] > 5 and len(sc[mode]["psnr_by_fifth"]) == 5 and sc[mode]["heldout_psnr"] is not None
    assert res["settings"]["scenes"]["synthetic_long"]["frames"] == 24
    assert all(r["pose_correction_deg"] is None for r in res["runs"])  # rendered profile: poses are exact
    assert (tmp_path / "lm_synthetic_long.png").stat().st_size > 1000
    assert out.with_suffix(".md").read_text().count("| synthetic_long |") >= 2
    assert not out.with_suffix(".partial.json").exists()


def test_one_mode_compares_settings_within_it(tmp_path, work):
    """``--modes gausslite``: only GaussLite runs (a comparison of two settings of one mode), the table has no uniform
    row and no ROI gain; an unknown mode is refused."""
    import json

    from bench.long_mission import main

    out = tmp_path / "lm.json"
    argv = ["--scenes", "synthetic_long", "--seeds", "1", "--tasks", "1", "--jobs", "1", "--synthetic-frames", "24",
            "--max-frames", "12", "--set", "iters_per_frame=2", "--set", "warmup_iters=1",
            "--work", str(work), "--out", str(out)]
    assert main([*argv, "--modes", "gausslite"]) == 0
    res = json.loads(out.read_text())
    assert {r["mode"] for r in res["runs"]} == {"gausslite"} and res["settings"]["modes"] == ["gausslite"]
    assert "roi_gain" not in res["scenes"]["synthetic_long"]
    md = out.with_suffix(".md").read_text()
    assert "| synthetic_long | gausslite |" in md and "| uniform |" not in md and "ROI gain" not in md
    with pytest.raises(SystemExit):
        main([*argv, "--modes", "splat"])


def test_select_tasks():
    from bench.long_mission import select_tasks

    ts = ["a", "b", "c"]
    assert select_tasks("2", ts) == ["a", "b"] and select_tasks("all", ts) == ts and select_tasks("c,a", ts) == ["c", "a"]
    with pytest.raises(ValueError, match="this scene has"):
        select_tasks("a,zz", ts)
    with pytest.raises(ValueError):
        select_tasks("0", ts)


def test_resume_keeps_the_partial_runs_and_runs_only_the_missing_ones(tmp_path, capsys, work):
    """An interrupted bench (its ``.partial.json``) resumed with one more seed: the kept runs are not redone
    (their figures are carried over as written), the missing seed runs, and other settings are refused."""
    import json

    from bench.long_mission import main

    common = ["--scenes", "synthetic_long", "--tasks", "synth-pick-object", "--jobs", "1", "--synthetic-frames", "24",
              "--max-frames", "8", "--set", "iters_per_frame=2", "--set", "warmup_iters=1",
              "--work", str(work)]
    first = tmp_path / "a.json"
    assert main(common + ["--seeds", "1", "--out", str(first)]) == 0
    res1 = json.loads(first.read_text())
    kept = res1["runs"][:1]  # as if the bench stopped after its first run
    kept[0]["psnr"] = 99.0  # a marker: a kept run is carried over, not recomputed
    out = tmp_path / "b.json"
    out.with_suffix(".partial.json").write_text(json.dumps(
        {"partial": True, "settings": res1["settings"]["run_settings"], "runs": kept, "wall_s": 1.0}))
    assert main(common + ["--seeds", "2", "--resume", "--out", str(out)]) == 0
    assert "kept 1 run(s)" in capsys.readouterr().out
    res2 = json.loads(out.read_text())
    keys = sorted((r["mode"], r["seed"]) for r in res2["runs"])
    assert keys == [("gausslite", 0), ("gausslite", 1), ("uniform", 0), ("uniform", 1)]
    assert sum(r["psnr"] == 99.0 for r in res2["runs"]) == 1 and res2["settings"]["resumed"]
    assert not out.with_suffix(".partial.json").exists()
    # a partial made with other settings is refused with the reason
    out.with_suffix(".partial.json").write_text(json.dumps(
        {"partial": True, "settings": {**res1["settings"]["run_settings"], "overrides": []}, "runs": kept}))
    with pytest.raises(SystemExit):
        main(common + ["--seeds", "2", "--resume", "--out", str(out)])
    assert "other settings" in capsys.readouterr().err
    # without --resume an existing partial file stops the bench instead of being overwritten
    before = out.with_suffix(".partial.json").read_text()
    with pytest.raises(SystemExit):
        main(common + ["--seeds", "2", "--out", str(out)])
    assert "--resume" in capsys.readouterr().err and out.with_suffix(".partial.json").read_text() == before
    with pytest.raises(SystemExit):
        main(common + ["--seeds", "2", "--resume", "--fresh", "--out", str(out)])
    assert main(common + ["--seeds", "1", "--fresh", "--out", str(out)]) == 0  # --fresh starts over
    assert len(json.loads(out.read_text())["runs"]) == 2 and not out.with_suffix(".partial.json").exists()
