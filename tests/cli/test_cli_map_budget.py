"""``gausslite map``'s total time budget (docs/mapper.md, "Running it"): keyframes by the live agent's rule, the mapping
resolution by its governor, each keyframe's share of the time left, a final pass and the scoring inside the budget;
``--time-budget none`` (or an iteration count) keeps the fixed schedule. Every decision is checked on the mapper's
deterministic clock (``budget_clock: work``), never against elapsed wall time."""

from __future__ import annotations

import argparse
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from gausslite.cli import main
from gausslite.cli.cmd_map import (DEFAULT_TIME_BUDGET_MIN, add_mapping_args, config_from_args, parse_time_budget,
                                   parse_withhold, time_budget_from_args)
from gausslite.datasets import load_dataset
from gausslite.datasets.trajectory import read_tum_trajectory
from gausslite.mapping.budget import WorkCost
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.keyframes import KeyframeRule
from gausslite.mapping.resolution import ResolutionGovernor
from gausslite.mission.config import AgentConfig
from gausslite.pipeline import (TimeBudget, final_share, keyframe_share, poses_and_times, run_mapping,
                                select_keyframes)
from gausslite.synthetic import make_scene

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """The synthetic scene's first robot, 60 frames at 160x120 on the arcs (3.6 cm apart: dense for the keyframe
    rule), with its poses and without them (the annotations beside both)."""
    root = tmp_path_factory.mktemp("budget")
    make_scene(root / "scene", frames=60, width=160, height=120, progress=False, agents=("agent_a",))
    bare = root / "bare" / "agent_a"
    shutil.copytree(root / "scene" / "agent_a", bare)
    for name in ("cam_params.json", "objects.json", "tasks.json"):
        shutil.copy(root / "scene" / name, bare.parent)
    (bare / "traj.txt").unlink()
    return root / "scene" / "agent_a", bare


def _line(n: int, step_m: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = step_m * np.arange(n)
    return poses


def test_keyframes_thin_out_dense_frames_as_the_live_agent_picks_them():
    rule = KeyframeRule(0.05, 5.0, 1.0)
    times = np.arange(60) / 30.0
    assert select_keyframes(_line(60, 0.012), times, rule) == list(range(0, 60, 5))  # 6 cm > 5 cm > 4.8 cm
    assert select_keyframes(_line(60, 0.0), times, rule) == [0, 30]  # a still camera: every second
    assert select_keyframes(_line(10, 0.2), times[:10], rule) == list(range(10))  # far apart: every frame
    with pytest.raises(ValueError, match="poses but"):
        select_keyframes(_line(3, 0.1), times[:2], rule)


def test_a_keyframe_gets_an_equal_share_capped_at_the_fixed_schedules_iterations():
    assert keyframe_share(10.0, 4, None, 30) == 2.5
    assert keyframe_share(10.0, 4, 0.05, 30) == pytest.approx(1.5)  # 30 iterations of 50 ms
    assert keyframe_share(-3.0, 4, 0.05, 30) == 1e-3  # over budget: seeding and one iteration
    rendered = MapperConfig(final_iters_per_keyframe=5.0)
    assert final_share(rendered, 100) == pytest.approx(5 / 35)
    assert final_share(MapperConfig(), 100) == 0.0
    assert final_share(MapperConfig(final_iters=300), 10) == pytest.approx(300 / 600)
    with pytest.raises(ValueError, match="total_s > 0"):
        TimeBudget(0.0)


def _args(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_mapping_args(p)
    p.add_argument("--time-budget", dest="time_budget", type=parse_time_budget, default=None)
    return p.parse_args(list(argv))


def test_the_budget_flags_choose_the_schedule():
    assert parse_time_budget("none") == "none" and parse_time_budget("OFF") == "none"
    assert parse_time_budget("2.5") == 2.5 and parse_withhold("10") == 10
    for bad in ("0", "-1", "inf", "soon"):
        with pytest.raises(argparse.ArgumentTypeError):
            parse_time_budget(bad)
    with pytest.raises(argparse.ArgumentTypeError):
        parse_withhold("1")

    def decide(*argv):
        args = _args(*argv)
        return time_budget_from_args(args, config_from_args(args), 3.0)

    b = decide()  # the default: a total budget with the live agent's rule and governor
    agent = AgentConfig()
    assert b.total_s == 60 * DEFAULT_TIME_BUDGET_MIN and b.spent_s == 3.0
    assert (b.rule.translation_m, b.rule.rotation_deg, b.rule.max_interval_s) == (
        agent.keyframe_translation_m, agent.keyframe_rotation_deg, agent.keyframe_max_interval_s)
    g, rc = b.governor, agent.resolution
    assert (g.target_iters, g.max_downscale, g.min_width, g.adapt_after, g.tolerance) == (
        rc.target_iters, rc.max_downscale, rc.min_width, rc.adapt_after, rc.tolerance)
    assert g.cost == WorkCost(**MapperConfig().work_cost.model_dump()) and g.pinned is None
    assert decide("--time-budget", "none") is None  # the fixed schedule, explicitly
    assert decide("--iters", "10") is None  # an iteration count alone keeps the fixed schedule
    assert decide("--set", "iters_per_frame=12") is None
    assert decide("--set", "keyframe_budget_s=0.5") is None
    assert decide("--time-budget", "2", "--iters", "10").total_s == 120.0  # both: the budget, 10 iterations at most
    with pytest.raises(ValueError, match="both set a budget"):
        decide("--time-budget", "2", "--set", "keyframe_budget_s=0.5")


def _work_cfg(**kw) -> MapperConfig:
    return MapperConfig(budget_clock="work", final_iters_per_keyframe=5.0, **kw)


def _budget(total_s: float) -> TimeBudget:
    return TimeBudget(total_s, 0.0, KeyframeRule(0.05, 5.0, 1.0), ResolutionGovernor(min_width=64), score_reserve_s=0.0)


def test_run_mapping_spends_a_tight_budget_on_the_keyframes_at_a_coarser_resolution(scene):
    posed, _ = scene
    ds = load_dataset(posed, max_frames=30)
    cfg = _work_cfg()
    mapper, m = run_mapping(ds, cfg, progress=False, time_budget=_budget(3.0), withhold_every=10)
    tb = m["time_budget"]
    poses, times = poses_and_times(ds, [i for i in range(30) if i % 10 != 5])
    expected = select_keyframes(poses, times, KeyframeRule(0.05, 5.0, 1.0))
    assert tb["n_keyframes"] == len(expected) == m["n_keyframes"] == len(mapper.stats) < m["n_frames"] == 27
    assert tb["keyframe_ids"] == [int(ds[[i for i in range(30) if i % 10 != 5][k]].frame_id) for k in expected]
    assert m["heldout_n_views"] == 3 and m["n_views"] == 27  # every frame to map is scored, keyframe or not
    # the work model predicts too few iterations at 160x120 for the share: the governor maps at 80x60, its coarsest
    res = tb["resolution"]
    assert (res["mapping_width"], res["mapping_height"], res["mapping_downscale"]) == (80, 60, 2.0)
    assert res["resolution_predicted_iters"] < 10 and "coarsest level 2" in res["reason"]
    # the keyframes' budgets fill the keyframes' share of the budget, the final pass the rest
    share = 3.0 * (1 - final_share(cfg, tb["n_keyframes"]))
    assert tb["keyframe_budget_s"]["mean"] * tb["n_keyframes"] == pytest.approx(share, rel=0.15)
    assert sum(s.iters for s in mapper.stats) == tb["keyframe_iters"]["total"]
    assert tb["keyframe_iters"]["max"] < cfg.iters_per_frame
    assert 0 < tb["final_iters"] < tb["final_iters_planned"] == 5 * len(mapper.keyframes)
    assert tb["elapsed_s"] == pytest.approx(3.0, abs=0.2)  # modelled seconds: it ends when the budget does


def test_run_mapping_under_an_ample_budget_keeps_the_fixed_schedules_iterations_and_ends_early(scene):
    posed, _ = scene
    ds = load_dataset(posed, max_frames=8)
    cfg = _work_cfg()
    mapper, m = run_mapping(ds, cfg, progress=False, time_budget=_budget(600.0))
    tb = m["time_budget"]
    assert tb["resolution"]["mapping_downscale"] == 1.0 and tb["resolution"]["resolution_reaches_target"]
    # each keyframe after the first gets about iters_per_frame iterations' worth, not its 600 s share
    later = [s.iters for s in mapper.stats[2:]]
    assert later and 0.6 * cfg.iters_per_frame <= np.mean(later) <= 1.4 * cfg.iters_per_frame
    assert tb["final_iters"] == tb["final_iters_planned"] == 5 * len(mapper.keyframes)
    assert tb["elapsed_s"] < 60.0


def test_map_fits_the_budget_and_the_progress_bar_counts_it_down(scene, tmp_path, capsys):
    _, bare = scene
    out = tmp_path / "run"
    rc = main(["map", "--dataset", str(bare), "--max-frames", "18", "--time-budget", "0.2", "--set",
               "budget_clock=work", "--out", str(out)])
    text = capsys.readouterr()
    assert rc == 0, text.out
    assert "schedule: time budget 0.2 min" in text.out
    assert re.search(r"mapping \(0:12 budget\).*keyframe.*left=\d+:\d\d", text.err)  # the bar and its countdown
    m = json.loads((out / "metrics.json").read_text())
    tb = m["time_budget"]
    ts, poses = read_tum_trajectory(out / "trajectory.tum")  # the odometry's poses: keyframes are picked on them
    kf = select_keyframes(poses, ts, KeyframeRule(0.05, 5.0, 1.0))
    assert tb["keyframe_ids"] == [int(round(ts[k] * 30)) for k in kf] and len(kf) < m["n_frames"] == 18
    assert tb["total_s"] == 12.0 and tb["spent_before_s"] > 0 and m["odometry_s"] > 0
    assert tb["keyframe_iters"]["total"] >= tb["n_keyframes"] and tb["final_iters"] <= tb["final_iters_planned"]


def test_time_budget_none_keeps_the_fixed_schedule(scene, tmp_path, capsys):
    _, bare = scene
    out = tmp_path / "fixed"
    rc = main(["map", "--dataset", str(bare), "--max-frames", "6", "--time-budget", "none", "--iters", "2",
               "--set", "warmup_iters=1", "--set", "final_iters_per_keyframe=0", "--no-progress", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "schedule: fixed, 2 iterations on every frame" in text
    m = json.loads((out / "metrics.json").read_text())
    assert "time_budget" not in m and m["n_keyframes"] == m["n_frames"] == 6  # every frame mapped


def test_the_docs_show_the_budget_and_how_to_turn_it_off():
    mapper = (REPO / "docs" / "mapper.md").read_text()
    running = mapper.split("## Running it", 1)[1].split("\n## ", 1)[0]
    assert "--time-budget MIN" in running and "--time-budget none" in running and "history.md#map_budget" in running
    row = next(line for line in (REPO / "docs" / "reference.md").read_text().splitlines()
               if line.startswith("| `gausslite map "))
    assert "--time-budget" in row and "none" in row
