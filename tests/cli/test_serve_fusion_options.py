"""``gausslite serve fusion`` and ``python -m gausslite_services.fusion_server`` take the same options, with the same
environment fallbacks and defaults (one builder, :mod:`gausslite_services.fusion_server.options`); every fusion-server
command the README, the docs and the deployment files show parses with both; ``--max-message-bytes`` given to
``gausslite serve fusion`` is the bound a running server reports."""

from __future__ import annotations

import os
import re
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from gausslite.cli import build_parser, main
from gausslite_services.cli.cmd_serve import SERVICES, resolve_options
from gausslite_services.common.cli_options import server_options_from_args
from gausslite_services.fusion_server import options as fusion_options
from tests._waits import wait_for_start

REPO = Path(__file__).resolve().parents[2]
#: the two ways to start the fusion server, as the docs write them
FUSION_COMMANDS = ("gausslite serve fusion", "python -m gausslite_services.fusion_server")


def _serve_parser():
    """The ``gausslite serve`` sub-parser."""
    return build_parser()._subparsers._group_actions[0].choices["serve"]


def _options(parser) -> dict:
    """option string → argparse dest, of every option of ``parser`` but ``--help``."""
    return {s: a.dest for a in parser._actions for s in a.option_strings if s not in ("-h", "--help")}


def _module_options(argv, env):
    args = fusion_options.build_parser().parse_args(argv)
    opts, config = server_options_from_args(args, "fusion", env, default_port=fusion_options.DEFAULT_PORT,
                                            max_workers=fusion_options.DEFAULT_MAX_WORKERS,
                                            grace_s=fusion_options.DEFAULT_GRACE_S)
    return opts, config, fusion_options.fusion_run_arguments(args, env)


def _serve_options(argv, env):
    args = build_parser().parse_args(["serve", "fusion", *argv])
    opts, config = resolve_options(args, env=env)
    return opts, config, fusion_options.fusion_run_arguments(args, env)


def test_serve_fusion_has_every_option_of_the_fusion_module():
    module, serve = _options(fusion_options.build_parser()), _options(_serve_parser())
    assert {"--store", "--max-message-bytes", "--port-file", "--log-level", "--data-dir"} <= set(module)
    missing = sorted(set(module) - set(serve))
    assert not missing, f"python -m gausslite_services.fusion_server options missing on gausslite serve fusion: {missing}"
    assert {s: serve[s] for s in module} == module  # the same destinations: one resolution for both


FULL = ["--host", "0.0.0.0", "--port", "50099", "--token", "fleet", "--tls-cert", "s.pem", "--tls-key", "s.key",
        "--tls-client-ca", "ca.pem", "--config", "f.yaml", "--data-dir", "d", "--max-workers", "4",
        "--max-message-bytes", "262144", "--grace", "2.5", "--metrics-port", "9100", "--log-level", "debug",
        "--agent-tokens", "tokens.json", "--fleet-token-writes", "--store", "postgresql://u:pw@db:5432/g",
        "--port-file", "port.txt", "--set", "fusion.max_keyframes_per_agent=8"]
ENV = {"GAUSSLITE_FUSION_PORT": "50123", "GAUSSLITE_FUSION_HOST": "10.0.0.2", "GAUSSLITE_TOKEN": "env-token",
       "GAUSSLITE_FUSION_STORE": "postgresql://env@db/g", "GAUSSLITE_FUSION_PORT_FILE": "env-port",
       "GAUSSLITE_DATA_DIR": "env-dir", "GAUSSLITE_AGENT_TOKENS_FILE": "env-tokens.json",
       "GAUSSLITE_FUSION_METRICS_PORT": "9200", "GAUSSLITE_FUSION_CONFIG": "env.yaml",
       "GAUSSLITE_FUSION_SET": "fusion.team_map.refine_iters=50;fusion.max_keyframes_per_agent=9"}


@pytest.mark.parametrize("argv, env", [(FULL, {}), (FULL, ENV), ([], ENV), ([], {})],
                         ids=["flags", "flags-over-env", "env", "defaults"])
def test_both_entry_points_resolve_alike(argv, env):
    module, serve = _module_options(argv, env), _serve_options(argv, env)
    assert module == serve
    opts, config, run_kw = serve
    if argv:
        assert (opts.host, opts.port, opts.max_message_bytes, opts.max_workers, opts.grace_s) == \
            ("0.0.0.0", 50099, 262144, 4, 2.5)
        assert (opts.agent_tokens_file, opts.fleet_token_writes, opts.metrics_port, config) == \
            ("tokens.json", True, 9100, "f.yaml")
        assert run_kw == {"data_dir": "d", "store": "postgresql://u:pw@db:5432/g", "port_file": "port.txt",
                          "overrides": ["fusion.max_keyframes_per_agent=8"]}
    elif env:
        assert (opts.host, opts.port, opts.token, opts.metrics_port, config) == \
            ("10.0.0.2", 50123, "env-token", 9200, "env.yaml")
        assert run_kw == {"data_dir": "env-dir", "store": "postgresql://env@db/g", "port_file": "env-port",
                          "overrides": ["fusion.team_map.refine_iters=50", "fusion.max_keyframes_per_agent=9"]}
    else:  # the fusion server's defaults, whichever entry point starts it
        assert (opts.port, opts.max_workers, opts.grace_s, opts.max_message_bytes) == (50052, 16, 10.0, 4 * 1024 * 1024)
        assert SERVICES["fusion"].default_port == fusion_options.DEFAULT_PORT == 50052


def test_fusion_only_options_are_refused_for_the_other_services(capsys):
    for flag, value in (("--store", "postgresql://u@db/g"), ("--port-file", "p.txt")):
        with pytest.raises(ValueError, match="fusion server only"):
            resolve_options(build_parser().parse_args(["serve", "parser", flag, value]), env={})
    assert main(["serve", "agent", "--port", "0", "--store", "postgresql://u@db/g"]) == 2
    assert "gausslite serve agent: error: --store apply to the fusion server only" in capsys.readouterr().err


def _documented_commands() -> list:
    """(file, argument list after the command) of every fusion-server command in README.md, docs/ and deploy/."""
    found = []
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = path.read_text(encoding="utf-8")
        snippets = re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S)
        snippets += [s.replace("\n", " ") for s in re.findall(r"(?<!`)`([^`]+)`(?!`)", text)]
        for snippet in snippets:
            for line in snippet.replace("\\\n", " ").splitlines():
                for cmd in FUSION_COMMANDS:
                    if cmd in line:
                        rest = re.split(r"\s(?:#|&|\||;)", line.split(cmd, 1)[1] + " ")[0]
                        found.append((path.name, _expand(shlex.split(rest))))
    for path in sorted((REPO / "deploy").rglob("*.y*ml")):
        for doc in yaml.safe_load_all(path.read_text(encoding="utf-8")):
            for cmd in _yaml_commands(doc):
                line = " ".join(str(c) for c in cmd)
                for prefix in FUSION_COMMANDS:
                    if line.startswith(prefix):
                        found.append((path.name, [str(c) for c in cmd][len(prefix.split()):]))
    return found


def _expand(words: list) -> list:
    """A shell line's words with its variables stood in for: ``$S/ca.pem`` → ``S/ca.pem``; a variable that stands
    for several options (``$TLS``, not after an option) and ``...`` are dropped."""
    out = []
    for w in words:
        if w == "..." or (re.fullmatch(r"\$\{?\w+\}?", w) and not (out and out[-1].startswith("--"))):
            continue
        out.append(re.sub(r"\$\{?(\w+)\}?", r"\1", w))
    return out


def _yaml_commands(node) -> list:
    if isinstance(node, dict):
        out = [node["command"]] if isinstance(node.get("command"), list) else []
        return out + [c for v in node.values() for c in _yaml_commands(v)]
    if isinstance(node, list):
        return [c for v in node for c in _yaml_commands(v)]
    return []


def test_every_documented_fusion_command_parses_with_both_entry_points():
    found = _documented_commands()
    files = {f for f, _ in found}
    assert {"README.md", "fusion-and-deploy.md", "docker-compose.yml", "fusion.yaml"} <= files, files
    assert any("--store" in words for f, words in found if f == "fusion-and-deploy.md")
    for f, words in found:
        args = build_parser().parse_args(["serve", "fusion", *words])
        assert args.service == "fusion", (f, words)
        fusion_options.build_parser().parse_args(words)


def test_the_documented_options_parse_on_serve_fusion():
    """The options docs/fusion-and-deploy.md and docs/robot-integration.md give the fusion server."""
    args = build_parser().parse_args(["serve", "fusion", "--port", "50052", "--store",
                                      "postgresql://gausslite:PW@db:5432/gausslite", "--max-message-bytes", "262144"])
    opts, _ = resolve_options(args, env={})
    assert opts.max_message_bytes == 262144 and opts.port == 50052
    assert fusion_options.fusion_run_arguments(args, {})["store"] == "postgresql://gausslite:PW@db:5432/gausslite"
    robot_doc = (REPO / "docs" / "robot-integration.md").read_text(encoding="utf-8")
    assert "`--max-message-bytes` of `gausslite serve fusion`" in robot_doc


@pytest.mark.integration  # starts the server process
def test_serve_fusion_max_message_bytes_reaches_the_running_server(tmp_path):
    from gausslite.camera import Intrinsics
    from gausslite_services.fusion_server.client import FusionClient

    port_file = tmp_path / "port"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "gausslite.cli", "serve", "fusion", "--port", "0", "--data-dir",
                             str(tmp_path / "data"), "--port-file", str(port_file), "--max-message-bytes", "262144",
                             "--log-level", "warning"], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        wait_for_start(proc, lambda: port_file.exists() and port_file.read_text().strip(),
                       "the port file of gausslite serve fusion")
        port = int(port_file.read_text())
        with FusionClient(f"127.0.0.1:{port}", timeout_s=10) as c:
            c.wait_ready(20)
            info = c.open_session("robot-1", "find the red cup", Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24))
        assert info.max_chunk_bytes == 262144 - 16
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        proc.stdout.close()
