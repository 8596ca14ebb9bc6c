"""The ``GAUSSLITE_*`` environment variables: every one the product reads (``gausslite/``, ``services/``) is a field of
:class:`gausslite.core.environment.EnvironmentSettings` and a row of ``docs/reference.md#environment-variables``; the
model parses them as the readers did (empty = unset, lists, yes/no), and a value that does not parse is an error
naming the variable, from every reader."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from gausslite.core.environment import SERVICES, EnvironmentSettings, EnvironmentVariableError

ROOT = Path(__file__).resolve().parents[1]
#: a variable's name as the sources spell it (``GAUSSLITE_<SERVICE>_PORT`` is built from :data:`SERVICES`)
NAME = re.compile(r"\bGAUSSLITE_[A-Z][A-Z0-9_]*[A-Z0-9]\b")
PER_SERVICE = ("HOST", "PORT", "CONFIG", "METRICS_PORT")


def _named_in_sources() -> dict:
    """Variable name → the first source file of ``gausslite/`` or ``services/`` that names it."""
    out = {}
    for folder in ("gausslite", "services"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for name in NAME.findall(path.read_text(encoding="utf-8")):
                out.setdefault(name, path.relative_to(ROOT))
    return out


def _documented() -> set:
    text = (ROOT / "docs" / "reference.md").read_text(encoding="utf-8")
    section = text.split("### Environment variables", 1)[1].split("\n#", 1)[0]
    return set(re.findall(r"^\| `(GAUSSLITE_\w+)` \|", section, flags=re.M))


def test_every_variable_the_product_reads_is_a_field_and_documented():
    fields = set(EnvironmentSettings.variables())
    named = _named_in_sources()
    assert {"GAUSSLITE_FUSION_TOKEN_FILE", "GAUSSLITE_AGENT_SET", "GAUSSLITE_HEALTH_TARGET"} <= set(named)  # the scan
    missing = {n: str(p) for n, p in named.items() if n not in fields}
    assert not missing, f"GAUSSLITE_* names read without a field of EnvironmentSettings: {missing}"
    per_service = {f"GAUSSLITE_{s.upper()}_{v}" for s in SERVICES for v in PER_SERVICE}
    assert per_service <= fields
    assert _documented() == fields, (sorted(fields - _documented()), sorted(_documented() - fields))
    # one typed field per variable, each with its meaning
    assert len(fields) == len(EnvironmentSettings.model_fields)
    assert all(f.description for f in EnvironmentSettings.model_fields.values())


def test_the_variables_parse_as_the_readers_did():
    env = {"GAUSSLITE_PARSER_PORT": "6000", "GAUSSLITE_TOKEN": "", "GAUSSLITE_FUSION_ALLOW": "a:1, b:2,",
           "GAUSSLITE_AGENT_DATA_ROOTS": "/d1,/d2", "GAUSSLITE_AGENT_SET": "agent.push.every=3;;mapper.seed=2",
           "GAUSSLITE_LOG_LEVEL": "debug", "GAUSSLITE_AGENT_AUTO_FINISH": "no", "GAUSSLITE_METRICS_PORT": "9100",
           "GAUSSLITE_FUSION_METRICS_PORT": "0", "gausslite_view_port": "1", "GAUSSLITE_TEST_PG_DSN": "ignored"}
    v = EnvironmentSettings.read(env)
    assert v.parser_port == 6000 and v.token is None  # an empty variable is unset
    assert v.fusion_allow == ("a:1", "b:2") and v.agent_data_roots == ("/d1", "/d2")
    assert v.agent_set == ("agent.push.every=3", "mapper.seed=2") and v.fusion_set == ()
    assert v.log_level == "DEBUG" and v.agent_auto_finish is False and v.fleet_token_writes is False
    assert v.view_port is None  # names are case-sensitive
    # a server's own metrics port wins, 0 included (off); else GAUSSLITE_METRICS_PORT
    assert v.service("parser") == (None, 6000, None, 9100) and v.service("fusion")[3] == 0
    defaults = EnvironmentSettings.read({})
    assert defaults.agent_auto_finish is True and defaults.service("agent") == (None, None, None, None)
    with pytest.raises(ValueError, match="viewer"):
        defaults.service("viewer")


@pytest.mark.parametrize("name, value", [("GAUSSLITE_PARSER_PORT", "abc"), ("GAUSSLITE_METRICS_PORT", "70000"),
                                         ("GAUSSLITE_LOG_LEVEL", "loud"), ("GAUSSLITE_FLEET_TOKEN_WRITES", "maybe"),
                                         ("GAUSSLITE_AGENT_AUTO_FINISH", "perhaps"), ("GAUSSLITE_VIEW_PORT", "x")])
def test_a_value_that_does_not_parse_is_an_error_naming_the_variable(name, value):
    with pytest.raises(EnvironmentVariableError, match=rf"{name}={value!r}"):
        EnvironmentSettings.read({name: value})
    assert issubclass(EnvironmentVariableError, ValueError)  # the commands report it as bad input


def test_the_readers_take_the_model_and_name_a_bad_variable(monkeypatch):
    from gausslite_services.agent.server import settings_from_env
    from gausslite_services.common.cli_options import (client_credentials_from_args, client_tls_paths,
                                                       log_level_from, server_options_from_args)
    from gausslite_services.fusion_server.client import client_credentials_from_env
    from gausslite_services.fusion_server.options import fusion_run_arguments

    none = argparse.Namespace()
    env = {"GAUSSLITE_FUSION_PORT": "50123", "GAUSSLITE_FUSION_HOST": "10.0.0.2", "GAUSSLITE_METRICS_PORT": "9100",
           "GAUSSLITE_FLEET_TOKEN_WRITES": "yes", "GAUSSLITE_AGENT_TOKENS_FILE": "t.json", "GAUSSLITE_TOKEN": "fleet",
           "GAUSSLITE_FUSION_SET": "fusion.store_pool_size=3", "GAUSSLITE_FUSION_STORE": "postgresql://x@db/g",
           "GAUSSLITE_LOG_LEVEL": "warning"}
    opts, config = server_options_from_args(none, "fusion", env, default_port=1)
    assert (opts.host, opts.port, opts.metrics_port, opts.fleet_token_writes, opts.agent_tokens_file, opts.token,
            config) == ("10.0.0.2", 50123, 9100, True, "t.json", "fleet", None)
    assert server_options_from_args(none, "parser", {}, default_port=7)[0].port == 7
    assert fusion_run_arguments(none, env) == {"data_dir": None, "store": "postgresql://x@db/g", "port_file": None,
                                               "overrides": ["fusion.store_pool_size=3"]}
    assert log_level_from(none, env) == "WARNING"
    assert client_credentials_from_args(none, env)["token"] == "fleet" == client_credentials_from_env(env)["token"]
    assert client_tls_paths(none, {}) == (None, None, None)
    s = settings_from_env(None, {"GAUSSLITE_AGENT_ID": "r1", "GAUSSLITE_AGENT_SET": "agent.push.every=4",
                                 "GAUSSLITE_FUSION_ALLOW": "h:1,h:2", "GAUSSLITE_AGENT_AUTO_FINISH": "0"})
    assert (s.agent_id, s.config.push.every, s.fusion_allow, s.auto_finish) == ("r1", 4, ("h:1", "h:2"), False)
    bad = {"GAUSSLITE_FUSION_PORT": "fifty"}
    for read in (lambda: server_options_from_args(none, "fusion", bad, default_port=1),
                 lambda: fusion_run_arguments(none, bad), lambda: client_credentials_from_env(bad),
                 lambda: client_tls_paths(none, bad), lambda: settings_from_env(None, bad)):
        with pytest.raises(ValueError, match="GAUSSLITE_FUSION_PORT='fifty'"):
            read()
    # the command line reports it and exits 2
    from gausslite.cli import main

    monkeypatch.setenv("GAUSSLITE_HEALTH_TARGET", "127.0.0.1:1")
    monkeypatch.setenv("GAUSSLITE_VIEW_PORT", "eighty")
    assert main(["health"]) == 2
