"""TaskParser facade and CLI ``parse``."""

from __future__ import annotations

import json
import sys

import pytest

from gausslite.cli import main
from gausslite.parser import InvalidTaskTextError, ParserConfig, TaskParser


def test_rules_cache_hits_and_lru_eviction():
    p = TaskParser(ParserConfig(cache_size=2))
    a = p.parse("Pick up the box")
    assert p.parse("pick   up the BOX.").same_graph(a)
    assert p.cache_info() == {"hits": 1, "misses": 1, "size": 1, "maxsize": 2}
    p.parse("Map the lawn chairs")
    p.parse("Go to the window")  # evicts "pick up the box"
    p.parse("Pick up the box")
    assert p.cache_info()["misses"] == 4 and p.cache_info()["size"] == 2


def test_text_limit_message():
    p = TaskParser(ParserConfig(max_text_bytes=16))
    with pytest.raises(InvalidTaskTextError, match="16 UTF-8 bytes"):
        p.parse("é" * 9)  # 18 bytes
    assert p.parse("Pick up the box").targets == ["box"]


def test_empty_text_gives_empty_graph():
    g = TaskParser().parse("")
    assert g.targets == [] and g.warnings


def test_core_package_does_not_import_grpc():
    import subprocess

    code = ("import sys, gausslite.parser, gausslite.cli; gausslite.cli.build_parser(); "
            "gausslite.parser.TaskParser().parse('Pick up the box'); print('grpc' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


def test_cli_parse(capsys):
    rc = main(["parse", "Find the laptop next to the monitor"])
    out = json.loads(capsys.readouterr().out)
    assert rc == 0
    assert out["targets"] == ["laptop"] and out["anchors"] == ["monitor"]
    assert out["relations"] == [{"predicate": "near", "target": "laptop", "anchor": "monitor"}]
    assert out["backend"] == "rules" and "unsupported" not in out


def test_cli_parse_unsupported_and_config(capsys, tmp_path):
    cfg = tmp_path / "c.json"
    cfg.write_text('{"backend": "rules", "cache_size": 0}')
    assert main(["parse", "--config", str(cfg), "--compact", "Pick up the toy under the couch"]) == 0
    out = capsys.readouterr().out
    assert "\n" not in out.strip()
    assert json.loads(out)["unsupported"] == ["under"]


def test_cli_parse_errors(capsys, tmp_path):
    assert main(["parse", "--backend", "onnx", "Pick up the box"]) == 2
    assert "error" in capsys.readouterr().err
    assert main(["parse", "--config", str(tmp_path / "nope.yaml"), "x"]) == 2


def test_cli_serve_options_env():
    import argparse

    from gausslite_services.cli.cmd_serve import SERVICES, resolve_options

    assert "parser" in SERVICES
    args = argparse.Namespace(service="parser", host=None, port=None, token=None, tls_cert=None, tls_key=None,
                              config=None, max_workers=4, grace=1.0)
    opts, cfg = resolve_options(args, env={"GAUSSLITE_PARSER_PORT": "6000", "GAUSSLITE_TOKEN": "t",
                                           "GAUSSLITE_PARSER_CONFIG": "/x.yaml"})
    assert opts.port == 6000 and opts.token == "t" and cfg == "/x.yaml" and opts.host == "127.0.0.1"
    args.port, args.token = 0, "cli"
    opts, _ = resolve_options(args, env={"GAUSSLITE_PARSER_PORT": "6000", "GAUSSLITE_TOKEN": "t"})
    assert opts.port == 0 and opts.token == "cli"
    args.port = None
    opts, _ = resolve_options(args, env={})
    assert opts.port == SERVICES["parser"].default_port
