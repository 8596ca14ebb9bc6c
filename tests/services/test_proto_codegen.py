"""Generated gRPC code is current (scripts/gen_proto.py --check) and importable."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _load_gen_proto():
    spec = importlib.util.spec_from_file_location("gen_proto_under_test", REPO / "scripts" / "gen_proto.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_generated_code_is_current():
    res = subprocess.run([sys.executable, str(REPO / "scripts" / "gen_proto.py"), "--check"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr


def test_check_detects_stale_code(tmp_path, monkeypatch):
    shutil.copytree(REPO / "proto", tmp_path / "proto")
    shutil.copytree(REPO / "gausslite_rpc", tmp_path / "gausslite_rpc", ignore=shutil.ignore_patterns("__pycache__"))
    gp = _load_gen_proto()
    monkeypatch.setattr(gp, "REPO", tmp_path)
    monkeypatch.setattr(gp, "PROTO_DIR", tmp_path / "proto")
    assert gp.check() == 0
    proto = tmp_path / "proto" / "gausslite_rpc" / "parser.proto"
    proto.write_text(proto.read_text().replace("string task_text = 1;", "string task_text = 1;\n  string lang = 2;"))
    assert gp.check() == 1
    assert gp.main([]) == 0  # regenerate
    assert gp.check() == 0
    (tmp_path / "gausslite_rpc" / "common_pb2.py").unlink()
    assert gp.check() == 1


def test_messages_roundtrip():
    from gausslite_rpc import common_pb2, parser_pb2, parser_pb2_grpc

    g = common_pb2.TaskGraph(targets=["cup"], anchors=["desk"],
                             relations=[common_pb2.Relation(predicate="on", target="cup", anchor="desk")],
                             backend="rules")
    assert common_pb2.TaskGraph.FromString(g.SerializeToString()) == g
    assert parser_pb2.DESCRIPTOR.services_by_name["Parser"].full_name == "gausslite.v1.Parser"
    assert hasattr(parser_pb2_grpc, "ParserStub")
