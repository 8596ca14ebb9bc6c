"""``python -m bench.report``: the generated regions of README.md and docs/*.md hold what their JSON gives, and the
generator reads the realtime protocols by name (an older result's ``novel`` is today's ``novel-tracked``)."""

from __future__ import annotations

import copy
import json
import re

import pytest

import bench.report as report

#: regions that must exist, with the page that holds them (a check over no region could not fail)
EXPECTED = {("README.md", "headline"), ("README.md", "sim-seconds"), ("README.md", "test-minutes"),
            ("docs/results.md", "glance-realtime"), ("docs/results.md", "glance-sim-synthetic"),
            ("docs/results.md", "glance-sim-room0"), ("docs/results.md", "sim-defaults"),
            ("docs/results.md", "sim-seconds"), ("docs/results.md", "first-run"), ("docs/results.md", "slowest-tests"),
            ("docs/history.md", "sim-seeds"), ("docs/history.md", "sim-seeds-minutes"),
            ("docs/realtime.md", "realtime-protocols"), ("docs/mapper.md", "odometry"),
            ("docs/design.md", "pose-graph-solvers"), ("docs/mapper.md", "odometry-gains"),
            ("docs/mapper.md", "odometry-live"), ("docs/mapper.md", "odometry-residuals"),
            ("docs/mapper.md", "map-budget"),
            ("docs/mapper.md", "detail-live"), ("docs/realtime.md", "pose-perturbation"),
            ("docs/realtime.md", "compute-sweep"), ("docs/sharing.md", "team-long"),
            ("docs/sharing.md", "team-long-onboard"), ("docs/sharing.md", "team-long-curve"),
            ("docs/sharing.md", "team-long-reserve"),
            ("docs/sharing.md", "team-long-reserve-between"),
            ("docs/realtime.md", "compute-sweep-synthetic"), ("docs/realtime.md", "throughput"),
            ("docs/realtime.md", "quality-per-iteration"), ("docs/realtime.md", "sim-time"),
            ("docs/realtime.md", "realtime-throughput"), ("docs/realtime.md", "realtime-governor-t20"),
            ("docs/realtime.md", "realtime-governor-t30"),
            *(("docs/results.md", name) for name in (
                "ablation-room0", "ablation-synth", "ablation-room0-seeds", "ablation-room0-recheck",
                "ablation-room0-noadopt", "long-mission-tum320", "long-mission-synthetic-fp5", "long-mission-tum160",
                "long-mission-synthetic160", "long-mission-roi-phase", "long-mission-no-roi-phase", "roi-ceiling",
                "mapper-speed", "map-tracking", "map-tracking-budget", "rolling-shutter", "team-live", "team-tum-halves",
                "team-map-offline", "team-map-live", "team-map-acks", "share-finetune", "share-refresh",
                "keyframe-format", "frontend", "perception-annotation", "perception-onnx", "perception-onnx-worker",
                "ingest", "soak-60min", "soak", "live-sim-tum", "fleet", "fleet-site", "fleet-db-outage",
                "bag-round-trip", "bag-registration", "quant-psnr", "wire-fuzz", "vote", "rasterizer"))}
#: the summary page of the current figures, and its length bound (the long logs live in docs/history.md)
SUMMARY, SUMMARY_MAX_LINES = "docs/results.md", 300


def page(name: str) -> str:
    return (report.REPO / name).read_text(encoding="utf-8")


def test_the_expected_regions_are_there_and_name_their_json():
    found = {(p, name) for p in report.PAGES for name, _ in report.regions_in(page(p))}
    assert EXPECTED <= found, f"generated regions missing: {sorted(EXPECTED - found)}"
    for p in report.PAGES:
        for name, src in report.regions_in(page(p)):
            assert name in report.REGIONS, f"{p}: unknown region {name!r}"
            assert src == report.REGIONS[name].source, f"{p}: region {name!r} names {src}"
            assert (report.REPO / src).is_file(), f"{p}: region {name!r}: {src} does not exist"


def test_every_generated_figure_is_what_its_json_gives():
    """Fails when a figure inside a generated region of README.md or docs/*.md differs from the JSON (run
    ``python -m bench.report`` after a benchmark, and never edit inside the markers)."""
    stale = report.stale()
    msg = "\n".join(f"{p} ({c['name']}, from {c['source']}):\n  written:  {c['old']!r}\n  the JSON: {c['new']!r}"
                    for p, cs in stale.items() for c in cs)
    assert not stale, "generated regions differ from their JSON; run python -m bench.report:\n" + msg


def test_a_figure_changed_by_hand_is_caught_and_the_prose_is_kept():
    text = page("README.md")
    m = re.search(r"\(headline\).*?<!-- end generated -->", text, re.S)
    figure = re.search(r"\*\*(\+\d+\.\d\d) \[", m.group(0)).group(1)  # the first gain of the table
    edited = text.replace(figure, "+9" + figure[2:], 1)
    assert edited != text
    new, changed = report.regenerate(edited)
    assert [c["name"] for c in changed] == ["headline"] and "+9" + figure[2:] in changed[0]["old"]
    assert new == text  # the region is written back from the JSON; everything outside it is untouched


def test_a_region_that_names_another_json_or_an_unknown_table_is_refused():
    bad_src = ("<!-- generated by bench.report (headline) from bench/results/realtime_late.json: do not edit -->x"
               "<!-- end generated -->")
    with pytest.raises(report.ReportError, match="written from bench/results/realtime.json"):
        report.regenerate(bad_src)
    with pytest.raises(report.ReportError, match="unknown generated region"):
        report.regenerate("<!-- generated by bench.report (nope) from bench/results/realtime.json: do not edit -->"
                          "x<!-- end generated -->")


def _block(roi_u: float, roi_g: float, gain: float, sig: bool = False) -> dict:
    return {"uniform": {"roi_psnr": roi_u, "roi_psnr_std": 0.1, "psnr": 20.0},
            "gausslite": {"roi_psnr": roi_g, "roi_psnr_std": 0.2, "psnr": 19.0},
            "gain": gain, "gain_std": 0.3, "gain_significant": sig}


def _realtime(protocols: dict) -> dict:
    scenes = {s: {"budgets": {"0.5": {"protocols": copy.deepcopy(protocols)}}} for s, _ in report.HEADLINE_SCENES}
    return {"settings": {"protocols": sorted(protocols)}, "scenes": scenes}


def test_the_headline_reads_protocols_by_name_in_old_and_new_results():
    base = {"sensor": _block(1, 2, 1.0, True), "tracked": _block(3, 4, 1.0), "keyframes": _block(5, 6, 1.0)}
    old = _realtime({**base, "novel": _block(10.0, 12.5, 2.5, True)})  # before the split: novel was tracked
    new = _realtime({**base, "novel": _block(30.0, 31.0, 1.0), "novel-tracked": _block(10.0, 12.5, 2.5, True)})
    new_us = _realtime({**base, "novel": _block(30.0, 31.0, 1.0), "novel_tracked": _block(10.0, 12.5, 2.5, True)})
    tables = [report.headline_table(r) for r in (new, new_us)]
    assert tables[0] == tables[1]
    row = tables[0].splitlines()[2].split(" | ")
    # the headline's ROI PSNR is novel's (the predicted pose); novel-tracked's gain stands beside it
    assert row[1:5] == ["30.00 ± 0.10", "31.00 ± 0.20", "+1.00 ± 0.30 (no per-frame pairs)",
                        "**+2.50 ± 0.30** (no per-frame pairs)"]
    assert "`novel`" in tables[0].splitlines()[0] and "`novel-tracked`" in tables[0].splitlines()[0]
    # an old result's novel was scored at a tracked pose: it is novel-tracked, and gives no headline
    assert report.protocol(old, "room0", "novel-tracked")["gain"] == 2.5
    with pytest.raises(report.ReportError, match="no protocol 'novel'"):
        report.headline_table(old)


def test_a_gain_shows_its_run_clustered_interval_bold_when_it_excludes_zero_and_no_other():
    rc = {"gain_interval": "run-clustered", "gain_runs": 6}
    assert report.gain_text({"gain": 1.2, "gain_ci": [0.4, 2.0], "gain_std": 0.9, **rc}) == "**+1.20 [+0.40, +2.00]**"
    assert report.gain_text({"gain": 0.3, "gain_ci": [-0.4, 1.0], **rc}) == "+0.30 [−0.40, +1.00]"
    # without per-frame figures: the spread over runs, and the page says so
    assert report.gain_text({"gain": 0.3, "gain_ci": None, "gain_std": 0.1, "gain_significant": True}) == \
        "**+0.30 ± 0.10** (no per-frame pairs)"
    # one run: its per-frame interval is not shown as if it were over runs
    assert report.gain_text({"gain": 0.3, "gain_ci": [0.1, 0.5], "gain_interval": "per-frame", "gain_runs": 1}) == \
        "+0.30 (one run)"
    # an interval pooled over runs × frames (a summary written before the run-clustered one) is refused
    with pytest.raises(report.ReportError, match="run-clustered"):
        report.gain_text({"gain": 1.2, "gain_ci": [0.9, 1.5], "gain_pairs": "frames"})


def test_the_pages_show_the_run_clustered_interval_of_the_committed_runs():
    """The README's find-mouse gain under ``novel`` is the t-interval over its six per-run gains, recomputed here
    from the runs the result file holds (not read from its summary)."""
    from scipy import stats

    result = json.loads((report.RESULTS / "realtime.json").read_text())
    runs = [r for r in result["runs"] if r["scene"] == "tum_fr1_rpy" and r["budget"] == 0.5]
    by = {m: {r["run"]: r["protocols"]["novel"]["roi_psnr_per_frame"] for r in runs if r["mode"] == m}
          for m in ("uniform", "gausslite")}
    per_run = [sum(g[k] - u[k] for k in g if k in u) / len([k for k in g if k in u])
               for g, u in ((by["gausslite"][i], by["uniform"][i]) for i in sorted(by["uniform"]))]
    assert len(per_run) == 6
    lo, hi = stats.t.interval(0.95, 5, loc=sum(per_run) / 6, scale=stats.sem(per_run))
    cell = report.gain_text(report.protocol(result, "tum_fr1_rpy", "novel"))
    assert f"[{report.signed(lo)}, {report.signed(hi)}]" in cell
    assert cell in report.headline_table(result) and cell in report.protocols_table(result)


def test_the_sim_figures_are_the_mean_of_both_agents():
    result = json.loads((report.RESULTS / "history" / "sim_seeds.json").read_text())
    agents = list(result["summary"]["synthetic"].values())
    text = report.sim_glance(result, "synthetic")
    for key, label in (("vote", "vote"), ("refine", "vote+refine")):
        assert f"{label} {sum(a[key] for a in agents) / 2:.2f}" in text


def test_the_summary_page_is_short_and_links_the_json_of_every_generated_figure():
    text = page(SUMMARY)
    assert len(text.splitlines()) <= SUMMARY_MAX_LINES, f"{SUMMARY}: {len(text.splitlines())} lines"
    for name, src in report.regions_in(text):
        assert f"](../{src})" in text, f"{SUMMARY}: region {name!r} is written from {src}, which the page does not link"


def test_the_run_clustered_interval_is_the_one_paired_gain_computes():
    """:func:`bench.report.run_clustered` reads per-run gains from a summary; it gives the interval
    ``gausslite.stats.paired_gain`` gives over the same runs."""
    from gausslite.stats import paired_gain

    treated = [{0: 21.0, 1: 22.5}, {0: 20.0, 1: 20.4}, {0: 23.1, 1: 22.0}]
    baseline = [{0: 20.0, 1: 20.0}, {0: 20.5, 1: 19.0}, {0: 21.0, 1: 21.5}]
    g = paired_gain(treated, baseline)
    r = report.run_clustered(g["run_gains"])
    assert r["gain"] == pytest.approx(g["gain"]) and r["gain_ci"] == pytest.approx([g["ci_low"], g["ci_high"]])
    with pytest.raises(report.ReportError, match="two runs"):
        report.run_clustered([1.0])


def test_the_ablation_cells_pair_seeds_and_name_missing_rows():
    rows = [{"row": "none", "roi_psnr": 36.0, "roi_psnr_std": 0.5, "psnr": 38.0, "seeds": [0, 1],
             "by_seed": {"0": {"roi_psnr": 35.5}, "1": {"roi_psnr": 36.5}}},
            {"row": "+GFD", "roi_psnr": 40.0, "roi_psnr_std": 0.1, "psnr": 34.0, "seeds": [0, 1],
             "by_seed": {"0": {"roi_psnr": 39.9}, "1": {"roi_psnr": 40.1}}}]
    cells = report.ablation_seeds_cells(rows).split(" | ")
    assert cells == ["36.00 ± 0.50 (38.00)", "40.00 ± 0.10 (34.00)", "**+4.00 ± 0.57**", "2"]
    # a run without the uniform row shows no gain
    assert report.ablation_seeds_cells(rows[1:]).split(" | ")[::2] == ["–", "–"]
    with pytest.raises(report.ReportError, match="no rows"):
        report.ablation_cells(rows)


def test_the_team_map_table_has_a_row_per_map_it_holds_and_needs_novel():
    """bench.team_map's table: one row per fused map the summary holds (in TEAM_MAP_ROWS' order), both tasks per cell
    in reversed task order, the other protocols as signed means and `novel` with its run-clustered interval."""
    def blk(mean, per_run):
        return {"mean": mean, "per_run": per_run}

    fused = {key: {"synth-pick-object": {"sensor": blk(d, [d]), "novel": blk(d, [d - 0.1, d + 0.1])},
                   "synth-find-chair": {"sensor": blk(-d, [-d]), "novel": blk(-d, [-d - 0.1, -d + 0.1])}}
             for key, d in (("vote", -5.0), ("team_map", 1.0))}
    md = report.team_map_table({"summary": {"fused": fused}})
    lines = md.strip().splitlines()
    assert len(lines) == 4 and lines[2].startswith("| vote |") and lines[3].startswith("| **served team map** |")
    assert "| −5.00 / +5.00 |" in lines[2] and "| +1.00 / −1.00 |" in lines[3]  # pick-object first
    assert "[" in lines[3].split("|")[3] and "| – / – |" in lines[3]  # novel's interval; no novel-tracked figures
    for b in fused.values():
        for t in b.values():
            t.pop("novel")
    with pytest.raises(report.ReportError):
        report.team_map_table({"summary": {"fused": fused}})
    with pytest.raises(report.ReportError):
        report.team_map_table({"summary": {"fused": {"team_map": fused["team_map"]}}})  # no vote
