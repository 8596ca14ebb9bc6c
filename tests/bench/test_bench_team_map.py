"""bench.team_map (the team map over several sim runs): the summary's arithmetic on hand-made reports, a report file
summarised from the command line, and the sim arguments of each bench scene."""

from __future__ import annotations

import json

import pytest

from bench import team_map


OLD = ("sensor", "keyframes", "tracked", "novel", "tracked@own", "novel@own")  # an older report's protocol names


def _report(minus: float, served: list, ratio: float, names=OLD) -> dict:
    agents = [{"id": "a", "task": "t1", "roi_psnr": 30.0, "view_ratio": ratio, "view_bytes": 100, "views_sent": 3,
               "views_unsent": 1, "final_subset_bytes": 50},
              {"id": "b", "task": "t2", "roi_psnr": 20.0, "view_ratio": ratio, "view_bytes": 80, "views_sent": 2,
               "views_unsent": 0, "final_subset_bytes": 40}]
    proto = {q: {"t1": {"minus_own": minus}, "t2": {"minus_own": None}} for q in names}
    fused = {k: {"protocols": proto, "refine_record": {"iters_run": 5} if k in ("refine", "team_map") else None}
             for k in team_map.KEYS}
    timeline = [{"t": 1.0, "served": None},
                {"t": 2.0, "served": {"versions": {"a": 1}, "roi_psnr": {"t1": 10.0, "t2": 5.0}}}]  # one robot only
    timeline += [{"t": 3.0 + i, "served": {"versions": {"a": 2, "b": 1}, "roi_psnr": {"t1": v, "t2": 19.0}}}
                 for i, v in enumerate(served)]
    return {"agents": agents, "fused": fused, "fused_timeline": timeline, "realtime": False, "seconds": 60.0}


def test_an_older_report_is_summarised_with_its_tracked_novel_read_as_novel_tracked():
    """Reports written before ``novel`` scored the predicted pose: their ``novel`` (tracked against the map) is
    ``novel-tracked``; without per-frame figures the per-run differences are all there is (no interval invented)."""
    s = team_map.summarise([_report(-1.0, [29.5, 28.0], 1.5), _report(-3.0, [29.9], 2.5)])
    b = s["fused"]["team_map"]["t1"]["novel-tracked"]
    assert b["mean"] == pytest.approx(-2.0) and b["per_run"] == [-1.0, -3.0] and b["std"] > 0 and b["gain"] is None
    assert s["fused"]["team_map"]["t1"]["novel-tracked@own"]["per_run"] == [-1.0, -3.0]
    assert s["fused"]["team_map"]["t1"]["novel"]["mean"] is None  # the predicted-pose figure did not exist then
    assert s["fused"]["vote"]["t2"]["sensor"]["mean"] is None  # no figure: none invented
    # only steps whose served map holds both robots' subsets count
    assert s["served"]["t1"]["worst"]["per_run"] == [pytest.approx(-2.0), pytest.approx(-0.1)]
    assert s["served"]["t1"]["steps"] == [2, 1] and s["served"]["t2"]["worst"]["mean"] == pytest.approx(-1.0)
    assert s["views"]["a"]["ratio"]["mean"] == pytest.approx(2.0)
    assert s["refine_record"]["team_map"] == [{"iters_run": 5}] * 2
    md = team_map.table(s)
    assert "| team_map | t1 |" in md and "-2.00 ±" in md and "| a | 2.00 ±" in md


def test_the_gain_is_the_mean_of_paired_per_frame_differences_over_runs_and_frames():
    """A report with per-frame figures: each map's gain over the robot's own map pairs frame by frame, pooled over
    runs × frames with its t-interval; the served timeline's worst step is a paired gain too."""
    reps = []
    for r, shift in enumerate((-1.0, -2.0, -1.5)):
        rep = _report(0.0, [], 1.0, names=team_map.PROTOCOLS)
        own = {i: 30.0 + i for i in range(10)}
        rep["agents"][0]["protocols"] = {q: {"roi_psnr": 34.5, "roi_psnr_per_frame": own,
                                             **({"pose": "predicted"} if q == "novel" else {})}
                                         for q in ("sensor", "novel", "tracked", "novel-tracked")}
        fused = {q: {"t1": {"minus_own": shift, "pose": "predicted",
                            "roi_psnr_per_frame": {str(i): v + shift + (0.2 if i % 2 else -0.2)
                                                   for i, v in own.items()}}}
                 for q in team_map.PROTOCOLS}
        for k in team_map.KEYS:
            rep["fused"][k]["protocols"] = fused
        rep["fused_timeline"] = [{"t": 1.0, "served": {"versions": {"a": 1, "b": 1}, "roi_psnr": {"t1": 0.0},
                                                       "roi_psnr_per_frame": {"t1": {str(i): v - 1.0 - 0.1 * r
                                                                                     for i, v in own.items()}}}}]
        reps.append(rep)
    s = team_map.summarise(reps)
    for q in ("novel", "novel-tracked@own"):
        g = s["fused"]["team_map"]["t1"][q]["gain"]
        assert g["n"] == 30 and g["gain"] == pytest.approx(-1.5) and g["ci_low"] < -1.5 < g["ci_high"]
    worst = s["served"]["t1"]["worst_gain"]
    assert [w["gain"] for w in worst] == [pytest.approx(-1.0), pytest.approx(-1.1), pytest.approx(-1.2)]
    assert "[" in team_map.table(s)


def test_a_report_file_is_summarised_from_the_command_line(tmp_path):
    p = tmp_path / "report.json"
    p.write_text(json.dumps(_report(-0.5, [29.0], 1.0)))
    out = tmp_path / "tm.json"
    assert team_map.main(["--summarise", str(p), "--out", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["summary"]["fused"]["refine"]["t1"]["tracked"]["mean"] == pytest.approx(-0.5)
    assert (tmp_path / "tm.md").read_text().count("| refine | t1 |") == 1



def test_each_bench_scene_gives_its_sim_arguments():
    assert team_map.scene_args("synthetic") == []
    with pytest.raises(ValueError, match="unknown scene"):
        team_map.scene_args("kitchen")
