"""One set of defaults: a service started by hand, without ``--config``, runs exactly the settings that
``gausslite sim`` and the compose deployment run (the models' defaults, the measured settings), and
``gausslite config --show --role ROLE`` prints what ``gausslite serve ROLE`` runs."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from gausslite.config import DEFAULT_CONFIG_PATH, load_config
from gausslite_services.sim.runner import write_service_config

REPO = Path(__file__).resolve().parents[2]
GAUSSLITE = [sys.executable, "-m", "gausslite.cli"]


def _effective(argv: list, cwd: Path, timeout_s: float = 60.0) -> dict:
    """Start a service, read the ``effective configuration: {...}`` line it logs at start-up, stop it."""
    log = cwd / "service.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(argv, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            m = re.search(r"effective configuration: (\{.*\})$", log.read_text(errors="replace"), flags=re.M)
            if m:
                return json.loads(m.group(1))
            assert proc.poll() is None, log.read_text(errors="replace")
            time.sleep(0.2)
        raise AssertionError(f"no effective configuration logged: {log.read_text(errors='replace')}")
    finally:
        proc.terminate()
        proc.wait(20)


def _compose_config() -> Path:
    """The file the compose deployment's agents and fusion replicas pass with --config: the image's (and, for the
    agents, the mounted) copy of deploy/gausslite.yaml."""
    compose = yaml.safe_load((REPO / "deploy" / "docker-compose.yml").read_text(encoding="utf-8"))
    for name in ("fusion_server", "fusion_server_2", "agent_a", "agent_b"):
        cmd = compose["services"][name]["command"]
        assert cmd[cmd.index("--config") + 1] == "/app/deploy/gausslite.yaml", cmd
    assert "./gausslite.yaml:/app/deploy/gausslite.yaml:ro" in compose["services"]["agent_a"]["volumes"]
    return DEFAULT_CONFIG_PATH


def _json(tree: dict) -> dict:
    return json.loads(json.dumps(tree, sort_keys=True))


@pytest.mark.parametrize("role, argv", [
    ("agent", ["serve", "agent", "--port", "0", "--agent-id", "robot1", "--data-dir", "agents"]),
    ("fusion", ["serve", "fusion", "--port", "0", "--data-dir", "fusion"]),
])
def test_a_service_without_config_runs_what_sim_and_compose_run(role, argv, tmp_path):
    served = _effective(GAUSSLITE + argv, tmp_path)
    sim_file = write_service_config(load_config(), tmp_path / "sim_config.yaml")  # `gausslite sim`'s own writer
    sim = _json(load_config(sim_file).sections(role))
    compose = _json(load_config(_compose_config()).sections(role))
    assert served == sim == compose
    # the measured settings, not a model's bare defaults
    if role == "agent":
        assert (served["agent"]["share"]["rule"], served["mapper"]["roi_update"]) == ("task", "visible")
    else:
        assert served["fusion"]["team_map"]["enabled"] is True
    # `gausslite config --show --role` prints the same
    shown = subprocess.run(GAUSSLITE + ["config", "--show", "--role", role], capture_output=True, text=True,
                           check=True, timeout=60).stdout
    assert _json(yaml.safe_load(shown)) == served


def test_a_site_file_changes_only_what_it_names(tmp_path):
    site = tmp_path / "site.yaml"
    site.write_text("agent:\n  upload_backlog_max: 128\nfusion:\n  max_keyframes_per_agent: 96\n")
    base, mine = load_config().to_yaml_dict(), load_config(site).to_yaml_dict()
    assert mine["agent"]["upload_backlog_max"] == 128 and mine["fusion"]["max_keyframes_per_agent"] == 96
    for section, key in (("agent", "upload_backlog_max"), ("fusion", "max_keyframes_per_agent")):
        mine[section][key] = base[section][key]
    assert mine == base


@pytest.mark.parametrize("role, argv, override", [
    ("agent", ["serve", "agent", "--port", "0", "--agent-id", "robot1", "--data-dir", "agents"], "agent.upload_backlog_max=9"),
    ("fusion", ["serve", "fusion", "--port", "0", "--data-dir", "fusion"], "fusion.team_map.refine_iters=77"),
])
def test_config_show_prints_what_serve_runs_given_the_same_flags(role, argv, override, tmp_path):
    site = tmp_path / "site.yaml"
    site.write_text("agent:\n  push:\n    every: 4\nfusion:\n  max_keyframes_per_agent: 96\n")
    flags = ["--config", str(site), "--set", override]
    served = _effective(GAUSSLITE + argv + flags, tmp_path)
    shown = subprocess.run(GAUSSLITE + ["config", "--show", "--role", role, *flags], capture_output=True, text=True,
                           check=True, timeout=60).stdout
    assert _json(yaml.safe_load(shown)) == served != _json(load_config().sections(role))
    key, _, value = override.partition("=")
    node = served
    for part in key.split("."):
        node = node[part]
    assert str(node) == value


def test_a_service_refuses_settings_of_another_role(tmp_path):
    r = subprocess.run(GAUSSLITE + ["serve", "fusion", "--port", "0", "--data-dir", str(tmp_path),
                                    "--set", "agent.push.every=3"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "fusion.* overrides only" in r.stderr
