"""bench.sim_time: a quick run times one tiny ``gausslite sim`` with this tree's code (imported through the
PYTHONPATH shim the bench builds) and a service's start-up, and writes both to JSON. No timing is asserted: speed
is a benchmark figure.

The sim the bench starts is a stand-in here (:data:`STAND_IN`): a process in the bench's environment that imports
``gausslite_services`` through the bench's shim, parses the bench's command with the command line's own parser, loads
the settings it sets and writes a report with the sim's stages. The tiny sim itself, those settings, runs in
tests/services/test_sim.py; the bench's own runs time it."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from types import SimpleNamespace

import pytest

import bench.sim_time as sim_time
from tests.services.test_sim import TINY

pytestmark = pytest.mark.integration

#: ``python -m gausslite.cli sim ARGS`` as ``python -c STAND_IN ARGS``: fails unless ``gausslite_services`` comes
#: from the shim on the PYTHONPATH (``TREE:SHIM``), the command line parses and its settings load
STAND_IN = """
import json, os, sys
from pathlib import Path

import gausslite_services
from gausslite.cli import build_parser
from gausslite.config import load_config

shim = Path(os.environ["PYTHONPATH"].split(os.pathsep)[1])
assert Path(gausslite_services.__file__).parent == shim / "gausslite_services", gausslite_services.__file__
args = build_parser().parse_args(sys.argv[1:])
assert args.command == "sim"
load_config(None, args.overrides)
out = Path(args.out)
out.mkdir(parents=True)
stages = dict.fromkeys(["scene", "services", "missions", "scoring", "cover"], 0.001)
(out / "report.json").write_text(json.dumps({"agents": [], "fused": {}, "stages_s": stages}))
"""


def test_quick_run_times_a_tiny_sim(tmp_path, monkeypatch):
    sims = []

    def run(cmd, **kw):
        if cmd[1:4] == ["-m", "gausslite.cli", "sim"]:
            sims.append(cmd)
            cmd = [cmd[0], "-c", STAND_IN, *cmd[3:]]
        return subprocess.run(cmd, **kw)

    monkeypatch.setattr(sim_time, "subprocess", SimpleNamespace(run=run))
    out = tmp_path / "sim_time.json"
    res = sim_time.main(["--quick", "--out", str(out)])
    data = json.loads(out.read_text())
    assert data["provenance"]["command"].startswith("python -m bench.sim_time --quick")
    # the tiny sim of tests/services/test_sim.py, once, through the command line
    assert sim_time.QUICK_SET == TINY
    (cmd,) = sims
    assert cmd[:5] == [sys.executable, "-m", "gausslite.cli", "sim", "--out"]
    assert cmd[6:] == [arg for o in TINY for arg in ("--set", o)]
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

