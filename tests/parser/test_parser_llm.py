"""LLM backends and fallback against a real local OpenAI-compatible HTTP server."""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from gausslite.parser import (
    BackendUnavailableError,
    LLMOutputError,
    OnnxGenAIBackend,
    OnnxGenAIConfig,
    OpenAIConfig,
    ParserConfig,
    TaskParser,
    graph_from_llm_text,
)
from gausslite.parser.graph import Relation

GOOD = {"targets": ["mugs"], "anchors": ["the kitchen counter"],
        "relations": [{"predicate": "on", "target": "mugs", "anchor": "kitchen counter"}], "unsupported": []}


class _Handler(BaseHTTPRequestHandler):
    mode = "good"  # set per server via subclass attribute

    def log_message(self, *args):  # keep test output quiet
        pass

    def do_POST(self):  # noqa: N802
        length = int(self.headers.get("Content-Length", 0))
        body = json.loads(self.rfile.read(length))
        srv = self.server
        srv.requests.append({"path": self.path, "body": body, "auth": self.headers.get("Authorization")})
        mode = srv.mode
        if mode == "http500":
            self.send_response(500)
            self.end_headers()
            self.wfile.write(b"boom")
            return
        if mode == "slow":
            time.sleep(1.5)
        if mode == "no_schema" and "response_format" in body:
            self.send_response(400)
            self.end_headers()
            self.wfile.write(b'{"error": "response_format not supported"}')
            return
        content = {
            "good": json.dumps(GOOD), "slow": json.dumps(GOOD), "no_schema": "```json\n" + json.dumps(GOOD) + "\n```",
            "malformed": '{"targets": ["mug", ',
            "hallucinated": json.dumps({"targets": ["banana"], "anchors": [], "relations": [], "unsupported": []}),
            "badpred": json.dumps({"targets": ["mug"], "anchors": ["kitchen counter"],
                                   "relations": [{"predicate": "under", "target": "mug", "anchor": "kitchen counter"}],
                                   "unsupported": []}),
        }[mode]
        payload = json.dumps({"choices": [{"message": {"role": "assistant", "content": content}}]}).encode()
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(payload)))
        self.end_headers()
        try:
            self.wfile.write(payload)
        except (BrokenPipeError, ConnectionResetError):  # the client timed out and left
            pass


@pytest.fixture()
def llm_server():
    srv = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    srv.daemon_threads = True
    srv.mode = "good"
    srv.requests = []
    th = threading.Thread(target=srv.serve_forever, daemon=True)
    th.start()
    yield srv
    srv.shutdown()
    srv.server_close()


def _parser(srv, timeout=2.0, **kw):
    cfg = ParserConfig(backend="openai", openai=OpenAIConfig(
        base_url=f"http://127.0.0.1:{srv.server_address[1]}/v1", model="test-model", timeout_s=timeout, **kw))
    return TaskParser(cfg)


TEXT = "Grab the mug on the kitchen counter"


def test_good_answer_and_request_shape(llm_server):
    p = _parser(llm_server, api_key="sekret")
    g = p.parse(TEXT)
    assert g.backend == "openai"
    assert g.targets == ["mug"] and g.anchors == ["kitchen counter"]  # normalised (singular, no det)
    assert g.relations == [Relation("on", "mug", "kitchen counter")]
    req = llm_server.requests[0]
    assert req["path"] == "/v1/chat/completions"
    assert req["auth"] == "Bearer sekret"
    assert req["body"]["model"] == "test-model"
    assert req["body"]["response_format"]["type"] == "json_schema"
    msgs = req["body"]["messages"]
    assert msgs[0]["role"] == "system" and msgs[-1]["content"] == TEXT.lower()
    assert sum(m["role"] == "assistant" for m in msgs) >= 3  # few-shot examples


def test_cache_hits_per_normalised_text(llm_server):
    p = _parser(llm_server)
    p.parse(TEXT)
    p.parse("  grab THE mug on the kitchen counter!! ")
    g = p.parse(TEXT + ".")
    assert len(llm_server.requests) == 1
    assert p.cache_info()["hits"] == 2 and p.cache_info()["misses"] == 1
    assert g.backend == "openai"
    g.targets.append("mutated")  # returned copies do not alter the cache
    assert p.parse(TEXT).targets == ["mug"]


def test_retry_without_response_format(llm_server):
    llm_server.mode = "no_schema"
    g = _parser(llm_server).parse(TEXT)
    assert g.backend == "openai" and g.targets == ["mug"]
    assert len(llm_server.requests) == 2 and "response_format" not in llm_server.requests[1]["body"]


@pytest.mark.parametrize("mode,needle", [
    ("malformed", "malformed JSON"),
    ("hallucinated", "not grounded"),
    ("http500", "HTTP 500"),
    ("badpred", "predicate"),
])
def test_fallback_to_rules(llm_server, mode, needle):
    llm_server.mode = mode
    p = _parser(llm_server)
    g = p.parse(TEXT)
    assert g.backend == "rules(fallback from openai)"
    assert any(needle in w for w in g.warnings), g.warnings
    assert g.targets == ["mug"] and g.anchors == ["kitchen counter"]  # the rule parser's answer
    # fallbacks are not cached: the next call asks the LLM again
    p.parse(TEXT)
    assert len(llm_server.requests) == 2


def test_slow_answer_times_out(llm_server):
    llm_server.mode = "slow"
    p = _parser(llm_server, timeout=0.3)
    t0 = time.monotonic()
    g = p.parse(TEXT)
    assert time.monotonic() - t0 < 1.2
    assert g.backend == "rules(fallback from openai)"
    assert any("timed out" in w for w in g.warnings), g.warnings


def test_call_timeout_bounds_config_timeout(llm_server):
    llm_server.mode = "slow"
    p = _parser(llm_server, timeout=5.0)
    t0 = time.monotonic()
    g = p.parse(TEXT, timeout_s=0.2)
    assert time.monotonic() - t0 < 1.2 and g.backend.startswith("rules(fallback")


def test_unreachable_endpoint_falls_back():
    p = TaskParser(ParserConfig(backend="openai", openai=OpenAIConfig(base_url="http://127.0.0.1:9/v1",
                                                                      model="m", timeout_s=0.5)))
    g = p.parse("Pick up the box")
    assert g.backend == "rules(fallback from openai)" and g.targets == ["box"]


@pytest.mark.parametrize("raw,needle", [
    ("no json here", "no JSON"),
    ('["a"]', "no JSON object"),
    ('{"targets": ["mug"], "anchors": []}', "lacks 'relations'"),
    ('{"targets": "mug", "anchors": [], "relations": []}', "list of strings"),
    ('{"targets": ["mug"], "anchors": [], "relations": [], "extra": 1}', "unexpected key"),
    ('{"targets": [], "anchors": [], "relations": []}', "no target"),
    ('{"targets": ["mug"], "anchors": ["counter"], "relations": [{"predicate": "on", "target": "cup", '
     '"anchor": "counter"}]}', "not a target"),
    ('{"targets": ["mug"], "anchors": ["mug"], "relations": []}', "both target and anchor"),
    ('{"targets": ["mug"], "anchors": [], "relations": [], "unsupported": ["beneath"]}', "not grounded"),
])
def test_validation_errors(raw, needle):
    with pytest.raises(LLMOutputError, match=needle):
        graph_from_llm_text(raw, "Grab the mug on the kitchen counter", "x")


def test_validation_accepts_fenced_and_plural():
    raw = "Sure!\n```json\n" + json.dumps({"targets": ["Trash Cans", "dirt"], "anchors": [], "relations": []}) + "\n```"
    g = graph_from_llm_text(raw, "Avoid the trash cans/dirt", "openai")
    assert g.targets == ["trash can", "dirt"] and g.unsupported == []


def test_onnx_backend_clear_errors(tmp_path):
    try:
        import onnxruntime_genai  # noqa: F401
        have = True
    except ImportError:
        have = False
    with pytest.raises(BackendUnavailableError) as ei:
        OnnxGenAIBackend(OnnxGenAIConfig(model_dir=str(tmp_path / "missing")))
    assert ("onnxruntime-genai" in str(ei.value)) if not have else ("not found" in str(ei.value))
    with pytest.raises(BackendUnavailableError):
        TaskParser(ParserConfig(backend="onnx", onnx=OnnxGenAIConfig(model_dir=str(tmp_path))))


def test_config_from_file(tmp_path):
    f = tmp_path / "parser.yaml"
    f.write_text("parser:\n  backend: openai\n  cache_size: 3\n  openai:\n    base_url: http://x/v1\n    model: m\n")
    cfg = ParserConfig.from_file(f)
    assert cfg.backend == "openai" and cfg.cache_size == 3 and cfg.openai.model == "m"
    f.write_text('{"backend": "gpt"}')
    f2 = tmp_path / "p.json"
    f2.write_text('{"backend": "gpt"}')
    with pytest.raises(ValueError, match="unknown parser backend"):
        ParserConfig.from_file(f2)
    f2.write_text('{"bogus": 1}')
    with pytest.raises(ValueError, match="unknown parser config"):
        ParserConfig.from_file(f2)
