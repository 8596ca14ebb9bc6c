"""``gausslite ablate``: the Table 3 rows, the report files, ``--rows`` and ``--merge``."""

import json

import pytest

from gausslite.cli import main
from gausslite.cli.cmd_ablate import SWITCHES
from gausslite.synthetic import make_scene

ROWS = ["none", "+SB", "+MVO", "+ROI", "+SIS", "+GFD"]


@pytest.fixture(scope="module")
def TINY(tmp_path_factory):
    scene = tmp_path_factory.mktemp("scene")
    make_scene(scene, seed=0, width=64, height=48, frames=2, progress=False)
    return ["--dataset", str(scene / "agent_a"), "--iters", "4", "--set", "warmup_iters=2", "--seeds-per-frame", "60",
            "--seeds", "1",
            "--task-id", "synth-pick-object", "--no-progress"]


def test_ablate_writes_every_row_then_merges_a_partial_rerun(tmp_path, TINY):
    a = tmp_path / "a"
    assert main(["ablate", *TINY, "--out", str(a)]) == 0
    rows = json.loads((a / "ablation.json").read_text())
    assert [r["row"] for r in rows] == ROWS
    # cumulative switches: row k has the first k switches on
    for k, r in enumerate(rows):
        assert [r[s] for s in SWITCHES] == [i < k for i in range(5)]
        assert r["roi_psnr"] > 5 and r["psnr"] > 5 and r["seconds_per_frame"] > 0
        assert set(r["per_task"]) == {"synth-pick-object"} and "source" not in r
        assert r["seeds"] == [0] and r["roi_psnr_std"] == 0.0
    assert "| ROI PSNR [dB] |" in (a / "ablation.md").read_text()
    assert (a / "ablation.png").stat().st_size > 1000

    b = tmp_path / "b"
    assert main(["ablate", *TINY, "--rows", "+GFD", "--merge", str(a / "ablation.json"), "--out", str(b)]) == 0
    merged = json.loads((b / "ablation.json").read_text())
    assert [r["row"] for r in merged] == ROWS
    assert all(r["source"] == str(a / "ablation.json") for r in merged[:5]) and "source" not in merged[5]
    assert merged[:5] == [{**r, "source": str(a / "ablation.json")} for r in rows[:5]]
    assert "+SB from" in (b / "ablation.md").read_text()


def test_ablate_rejects_unknown_rows_and_a_bad_merge_before_mapping(tmp_path, caplog, TINY):
    assert main(["ablate", *TINY, "--rows", "+XYZ", "--out", str(tmp_path / "c")]) == 2
    assert "unknown ablation rows" in caplog.text
    prev = tmp_path / "prev.json"
    prev.write_text(json.dumps([{"row": "none", "per_task": {"synth-pick-object": {}}}]))
    assert main(["ablate", *TINY, "--rows", "+GFD", "--merge", str(prev), "--out", str(tmp_path / "d")]) == 2
    assert "has no row '+SB'" in caplog.text
    assert not (tmp_path / "d" / "ablation.json").exists()
    # an inconsistent configuration is a clear error, not a traceback
    bad = [a for a in TINY if a != "warmup_iters=2" and a != "--set"]
    assert main(["ablate", *bad, "--out", str(tmp_path / "e")]) == 2
    assert "warmup_iters (10) must not exceed iters_per_frame (4)" in caplog.text
    assert main(["map", *bad, "--mode", "gausslite", "--out", str(tmp_path / "f")]) == 2


def test_ablate_seeds_give_mean_std_and_paired_gains(tmp_path, TINY):
    args = [a for a in TINY]
    args[args.index("--seeds") + 1] = "2"
    out = tmp_path / "s"
    assert main(["ablate", *args, "--rows", "none,+ROI", "--out", str(out)]) == 0
    rows = json.loads((out / "ablation.json").read_text())
    for r in rows:
        assert r["seeds"] == [0, 1] and set(r["by_seed"]) == {"0", "1"}
        vals = [r["by_seed"][k]["roi_psnr"] for k in ("0", "1")]
        assert r["roi_psnr"] == pytest.approx(sum(vals) / 2)
        assert r["roi_psnr_std"] == pytest.approx(abs(vals[0] - vals[1]) / 2 ** 0.5)
        assert vals[0] != vals[1]  # the seed changes seeding and view sampling
        t = r["per_task"]["synth-pick-object"]
        assert t["roi_psnr"] == pytest.approx(r["roi_psnr"]) and "roi_psnr_std" in t
    md = (out / "ablation.md").read_text()
    assert "±" in md and "over 2 seed(s)" in md


def test_uniform_row_is_mapped_once_per_seed_and_scored_on_every_task(tmp_path, TINY, monkeypatch):
    """The ``none`` row (uniform mapping) does not depend on the task: one map per seed, every task's ROI
    scored on it; the task rows still map once per task."""
    import gausslite.pipeline as pipeline

    calls = []
    real = pipeline.run_mapping

    def counting(ds, cfg, **kw):
        calls.append((cfg.mode, kw.get("task_id")))
        return real(ds, cfg, **kw)

    monkeypatch.setattr(pipeline, "run_mapping", counting)
    args = [a for a in TINY]
    args[args.index("--task-id") + 1] = "all"
    out = tmp_path / "all"
    assert main(["ablate", *args, "--rows", "none,+ROI", "--out", str(out)]) == 0
    rows = {r["row"]: r for r in json.loads((out / "ablation.json").read_text())}
    tasks = sorted(rows["+ROI"]["per_task"])
    assert len(tasks) >= 3 and sorted(rows["none"]["per_task"]) == tasks
    assert calls.count(("uniform", None)) == 1 and len(calls) == 1 + len(tasks)
    none = rows["none"]["per_task"]
    assert len({none[t]["psnr"] for t in tasks}) == 1  # one map …
    assert len({none[t]["roi_psnr"] for t in tasks}) > 1  # … scored on each task's ROI
