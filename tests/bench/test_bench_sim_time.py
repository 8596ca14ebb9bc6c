"""bench.sim_time: a quick run times one tiny ``gausslite sim`` with this tree's code (imported through the
PYTHONPATH shim the bench builds) and a service's start-up, and writes both to JSON. No timing is asserted: speed
is a benchmark figure."""

from __future__ import annotations

import json
import math

import pytest

from bench.sim_time import main

pytestmark = pytest.mark.integration


def test_quick_run_times_a_tiny_sim(tmp_path):
    out = tmp_path / "sim_time.json"
    res = main(["--quick", "--out", str(out)])
    data = json.loads(out.read_text())
    assert data["provenance"]["command"].startswith("python -m bench.sim_time --quick")
    (run,) = data["runs"]
    assert run["tree"] == "this" and run["returncode"] == 0 and run["wall_s"] > 0
    assert "agents" in run["report_keys"]  # the sim wrote its report
    # where the time went: the sim's stages and the rest of the command, which add up to its wall time
    assert list(run["stages_s"]) == ["scene", "services", "missions", "scoring", "cover"]
    assert run["outside_s"] > 0 and sum(run["stages_s"].values()) + run["outside_s"] == pytest.approx(run["wall_s"])
    s = res["summary"]["this"]
    assert math.isfinite(s["wall_s"]) and s["import_s"] > 0
    md = out.with_suffix(".md").read_text()
    assert "| this |" in md and "| missions s |" in md
