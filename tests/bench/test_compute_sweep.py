"""bench.compute_sweep: its cells, the load process beside a cell's missions (gone afterwards, whatever happened), the
pairing of maps scored at the scene's resolution, and a two-cell sweep on a tiny live scene."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from bench import compute_sweep as cs
from bench import realtime as rt


def _gone(pid: int) -> bool:
    """Whether process ``pid`` has ended (an orphan that ended and waits to be reaped counts as ended)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] in ("Z", "X")
    except (OSError, IndexError):
        return False


def test_cells_name_their_threads_budget_and_load():
    assert cs.parse_cell("t1-b0.25") == cs.Cell("t1-b0.25", 1, 0.25, None)
    assert cs.parse_cell("t2-b1-multi") == cs.Cell("t2-b1-multi", 2, 1.0, "multi")
    assert cs.parse_cell("single") == cs.Cell("single", 2, 0.5, "single")
    for bad in ("t0-b0.5", "t1-b0", "t1", "b0.5", "t1-b0.5-heavy", "t1-b-1"):
        with pytest.raises(ValueError, match="unknown cell"):
            cs.parse_cell(bad)
    cells = [cs.parse_cell(c) for c in cs.DEFAULT_CELLS]
    assert {(c.threads, c.budget) for c in cells if c.load is None} == {(t, b) for t in (1, 2) for b in (0.25, 0.5, 1.0)}
    assert {(c.threads, c.budget, c.load) for c in cells if c.load} == {(2, 0.5, "single"), (2, 0.5, "multi")}
    # the options the sweep sets per cell are refused, also abbreviated
    for taken in (["--budgets", "0.5"], ["--run", "2"], ["--score-at=mapping"], ["--twin"]):
        with pytest.raises(SystemExit):
            cs.main(["--cells", "t1-b0.5", *taken])


@pytest.mark.parametrize("kind", ["single", "multi"])
def test_a_load_process_runs_through_the_body_and_is_killed_when_it_raises(kind):
    with pytest.raises(RuntimeError, match="a mission failed"):
        with cs.load_process(kind) as rec:
            pid = rec["pid"]
            assert not _gone(pid)
            raise RuntimeError("a mission failed")
    assert _gone(pid)
    assert rec["cpu_s"] > 0.1 and rec["wall_s"] >= cs.LOAD_WARMUP_S and rec["cores_busy"] > 0  # it did burn CPU
    with cs.load_process(None) as none:
        assert none is None


def test_a_load_process_ends_itself_when_the_process_that_started_it_dies():
    """The starter exits at once, before or after the load reads its parent: the load ends either way."""
    starter = ("import subprocess, sys, os\n"
               f"p = subprocess.Popen([sys.executable, '-c', {cs.LOAD_CODE['single']!r}, str(os.getpid())], "
               "stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)\n"
               "print(p.pid, flush=True)\n"
               "os._exit(0)\n")
    out = subprocess.run([sys.executable, "-c", starter], capture_output=True, text=True, timeout=30, check=True)
    pid = int(out.stdout.split()[0])
    try:
        deadline = time.monotonic() + 10
        while not _gone(pid) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _gone(pid)
    finally:
        if not _gone(pid):
            os.kill(pid, signal.SIGKILL)


def _run(mode, factor, size, basis, scored):
    return {"scene": "s", "mode": mode, "budget": 0.5, "run": 0, "mapping_downscale": factor,
            "mission": {"mapping_size": size, "resolution_changes": 0}, "score_at": basis, "scored_size": scored}


def test_maps_scored_at_the_scene_resolution_pair_whatever_resolution_they_mapped_at():
    g = {0: _run("gausslite", 2.0, [160, 120], "scene", [320, 240])}
    assert rt.pairable_runs(g, {0: _run("uniform", 1.0, [320, 240], "scene", [320, 240])}, [0]) == ([0], [])
    keep, refused = rt.pairable_runs(g, {0: _run("uniform", 1.0, [320, 240], "scene", [160, 120])}, [0])
    assert keep == [] and "scored at different sizes" in refused[0]["reason"]
    # scored at their own mapping resolutions (the default), or one of each: different resolutions never pair
    gm = {0: _run("gausslite", 2.0, [160, 120], "mapping", [160, 120])}
    for u in (_run("uniform", 1.0, [320, 240], "mapping", [320, 240]), _run("uniform", 1.0, [320, 240], "scene",
                                                                            [320, 240])):
        keep, refused = rt.pairable_runs(gm, {0: u}, [0])
        assert keep == [] and "mapped at different resolutions" in refused[0]["reason"]


def test_a_two_cell_sweep_beside_a_load_scores_every_map_at_the_scene_size(tmp_path):
    """Two cells (one render thread, 0.2 s per keyframe; alone and beside the single-threaded load), one run each, on
    a 64x48 scene mapped at a pinned 32x24: every map is scored at 64x48, both modes pair, each run records its cell,
    and the load process is gone afterwards."""
    from gausslite.synthetic import make_scene

    make_scene(tmp_path / "scene", frames=8, width=64, height=48, trajectory="circle")
    out = tmp_path / "sweep.json"
    argv = ["--cells", "t1-b0.2,t1-b0.2-single", "--runs", "1", "--jobs", "1", "--work", str(tmp_path / "work"),
            "--out", str(out), "--dataset", str(tmp_path / "scene" / "agent_a"), "--tasks", "synth-pick-object",
            "--cap", "300", "--fps", "4", "--set", "mapper.seeding.seeds_per_frame=300",
            "--set", "agent.resolution.downscale=2"]
    assert cs.main(argv) == 0
    res = json.loads(out.read_text())
    assert res["provenance"]["command"].startswith("python -m bench.compute_sweep --cells")
    assert res["settings"]["score_at"] == "scene" and "--score-at" in res["settings"]["realtime_args"]
    loaded = res["cells"]["t1-b0.2-single"]["missions"]
    assert len(loaded) == 1 and loaded[0]["missions"] == 2 and loaded[0]["load"]["kind"] == "single"
    assert _gone(loaded[0]["load"]["pid"]) and loaded[0]["load"]["cpu_s"] > 0
    assert res["cells"]["t1-b0.2"]["missions"][0]["load"] is None
    assert len(res["runs"]) == 4
    for r in res["runs"]:
        assert r["threads"] == r["render_threads"] == 1 and r["budget"] == 0.2
        assert r["load"] == ("single" if r["cell"] == "t1-b0.2-single" else None)
        assert r["iters_per_keyframe"] > 0 and r["keyframes"] > 0 and len(r["load_avg_1m"]) == 2
        assert r["mapping_size"] == [32, 24] and r["sizes"]["mapping"] == [32, 24]
        assert r["score_at"] == "scene" and r["scored_size"] == [64, 48]
        assert r["novel"]["roi_psnr"] is not None
        assert r["end_state"] == "FINISHED" and not r["error"] and r["frames_failed"] == 0  # every mission's end
    assert all(r["roi_iters"] > 0 for r in res["runs"] if r["mode"] == "gausslite")
    assert len(res["pairs"]) == 2 and all(p["paired"] and p["novel_gain"] is not None for p in res["pairs"])
    by_cell = res["scenes"]["synth-pick-object"]
    assert set(by_cell) == {"t1-b0.2", "t1-b0.2-single"}
    for s in by_cell.values():
        assert s["scored_size"] == [[64, 48]] and "mapping 32x24" in s["sizes"]["gausslite"]
        assert s["protocols"]["novel"]["gain"] is not None and s["protocols"]["novel"]["runs"] == 1
        assert s["iters_per_keyframe"]["gausslite"] > 0 and s["iters_per_keyframe"]["uniform"] > 0
    assert "t1-b0.2-single" in out.with_suffix(".md").read_text() and out.with_suffix(".png").stat().st_size > 0
