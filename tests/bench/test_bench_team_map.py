"""bench.team_map (the team map over several sim runs) and bench.team_map_acks (push acknowledgements while the team
map refines): the summary's arithmetic on hand-made reports, and the acknowledgement bench end to end on a tiny
load."""

from __future__ import annotations

import json

import pytest

from bench import team_map, team_map_acks


def _report(minus: float, served: list, ratio: float) -> dict:
    agents = [{"id": "a", "task": "t1", "roi_psnr": 30.0, "view_ratio": ratio, "view_bytes": 100, "views_sent": 3,
               "views_unsent": 1, "final_subset_bytes": 50},
              {"id": "b", "task": "t2", "roi_psnr": 20.0, "view_ratio": ratio, "view_bytes": 80, "views_sent": 2,
               "views_unsent": 0, "final_subset_bytes": 40}]
    proto = {q: {"t1": {"minus_own": minus}, "t2": {"minus_own": None}} for q in team_map.PROTOCOLS}
    fused = {k: {"protocols": proto, "refine_record": {"iters_run": 5} if k in ("refine", "team_map") else None}
             for k in team_map.KEYS}
    timeline = [{"t": 1.0, "served": None},
                {"t": 2.0, "served": {"versions": {"a": 1}, "roi_psnr": {"t1": 10.0, "t2": 5.0}}}]  # one robot only
    timeline += [{"t": 3.0 + i, "served": {"versions": {"a": 2, "b": 1}, "roi_psnr": {"t1": v, "t2": 19.0}}}
                 for i, v in enumerate(served)]
    return {"agents": agents, "fused": fused, "fused_timeline": timeline, "realtime": False, "seconds": 60.0}


def test_the_summary_pairs_each_map_with_the_robots_own_and_takes_the_worst_served_step():
    s = team_map.summarise([_report(-1.0, [29.5, 28.0], 1.5), _report(-3.0, [29.9], 2.5)])
    b = s["fused"]["team_map"]["t1"]["novel"]
    assert b["mean"] == pytest.approx(-2.0) and b["per_run"] == [-1.0, -3.0] and b["std"] > 0
    assert s["fused"]["vote"]["t2"]["sensor"]["mean"] is None  # no figure: none invented
    # only steps whose served map holds both robots' subsets count
    assert s["served"]["t1"]["worst"]["per_run"] == [pytest.approx(-2.0), pytest.approx(-0.1)]
    assert s["served"]["t1"]["steps"] == [2, 1] and s["served"]["t2"]["worst"]["mean"] == pytest.approx(-1.0)
    assert s["views"]["a"]["ratio"]["mean"] == pytest.approx(2.0)
    assert s["refine_record"]["team_map"] == [{"iters_run": 5}] * 2
    md = team_map.table(s)
    assert "| team_map | t1 |" in md and "-2.00 ±" in md and "| a | 2.00 ±" in md


def test_a_report_file_is_summarised_from_the_command_line(tmp_path):
    p = tmp_path / "report.json"
    p.write_text(json.dumps(_report(-0.5, [29.0], 1.0)))
    out = tmp_path / "tm.json"
    assert team_map.main(["--summarise", str(p), "--out", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["summary"]["fused"]["refine"]["t1"]["tracked"]["mean"] == pytest.approx(-0.5)
    assert (tmp_path / "tm.md").read_text().count("| refine | t1 |") == 1


@pytest.mark.integration
def test_push_acknowledgements_are_timed_while_the_team_map_refines(tmp_path):
    out = tmp_path / "acks.json"
    team_map_acks.main(["--seconds", "2", "--every", "0.3", "--gaussians", "400", "--views", "4", "--settle", "1",
                        "--work", str(tmp_path / "w"), "--out", str(out)])
    got = json.loads(out.read_text())
    on, off = got["phases"]
    assert on["team_map"] and not off["team_map"] and on["pushes"] >= 3 and off["pushes"] >= 3
    assert on["refining_throughout"] is True  # the refinement was running during the pushes
    assert on["push_ack_ms"]["p99"] > 0 and got["goal_met"] == (on["push_ack_ms"]["p99"] <= 250.0)
