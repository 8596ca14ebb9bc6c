"""Parser gRPC service integration: real server in-process on an ephemeral loopback port."""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

from gausslite.parser import LLMBackend, OpenAIConfig, ParserConfig, TaskGraph, TaskParser
from gausslite_rpc import parser_pb2, parser_pb2_grpc
from gausslite_services.common.server import ServerOptions
from gausslite_services.parser.server import SERVICE_NAME, serve

TOKEN = "s3cret-token"


def _graph(msg) -> TaskGraph:
    return TaskGraph.from_dict({
        "targets": list(msg.targets), "anchors": list(msg.anchors), "unsupported": list(msg.unsupported),
        "relations": [{"predicate": r.predicate, "target": r.target, "anchor": r.anchor} for r in msg.relations],
    })


@pytest.fixture(scope="module")
def server():
    running = serve(ServerOptions(host="127.0.0.1", port=0, grace_s=1.0))
    yield running
    running.stop(1.0)


@pytest.fixture(scope="module")
def channel(server):
    ch = grpc.insecure_channel(server.address)
    grpc.channel_ready_future(ch).result(timeout=5)
    yield ch
    ch.close()


def test_parse_all_shared_phrasings(channel, tasks_dir):
    stub = parser_pb2_grpc.ParserStub(channel)
    items = [json.loads(x) for x in (tasks_dir / "phrasings.jsonl").read_text().splitlines() if x.strip()]
    for item in items:
        resp = stub.Parse(parser_pb2.ParseRequest(task_text=item["text"]), timeout=5)
        assert _graph(resp).same_graph(TaskGraph.from_dict(item["graph"])), item["text"]
        assert resp.backend == "rules"


def test_health_serving(channel):
    stub = health_pb2_grpc.HealthStub(channel)
    for name in ("", SERVICE_NAME):
        resp = stub.Check(health_pb2.HealthCheckRequest(service=name), timeout=5)
        assert resp.status == health_pb2.HealthCheckResponse.SERVING


def test_reflection_lists_service(channel):
    db = ProtoReflectionDescriptorDatabase(channel)
    services = db.get_services()
    assert SERVICE_NAME in services and "grpc.health.v1.Health" in services
    desc = db.FindFileContainingSymbol(SERVICE_NAME)
    assert desc.package == "gausslite.v1"


@pytest.mark.parametrize("text,needle", [("", "empty"), ("   \n ", "empty"), ("x" * 2049, "2048"),
                                         ("é" * 1025, "2048")])
def test_invalid_argument(channel, text, needle):
    stub = parser_pb2_grpc.ParserStub(channel)
    with pytest.raises(grpc.RpcError) as ei:
        stub.Parse(parser_pb2.ParseRequest(task_text=text), timeout=5)
    assert ei.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert needle in ei.value.details()


def test_limit_is_inclusive(channel):
    stub = parser_pb2_grpc.ParserStub(channel)
    text = "Pick up the box " + "x" * (2048 - 16)
    assert len(text.encode()) == 2048
    assert stub.Parse(parser_pb2.ParseRequest(task_text=text), timeout=5).targets


def test_message_size_bounded(channel):
    stub = parser_pb2_grpc.ParserStub(channel)
    with pytest.raises(grpc.RpcError) as ei:
        stub.Parse(parser_pb2.ParseRequest(task_text="x" * (256 * 1024)), timeout=5)
    assert ei.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED


def test_token_auth():
    running = serve(ServerOptions(host="127.0.0.1", port=0, token=TOKEN, grace_s=0.5))
    try:
        with grpc.insecure_channel(running.address) as ch:
            stub = parser_pb2_grpc.ParserStub(ch)
            req = parser_pb2.ParseRequest(task_text="Pick up the box")
            for md in (None, (("authorization", "Bearer wrong"),), (("authorization", TOKEN),)):
                with pytest.raises(grpc.RpcError) as ei:
                    stub.Parse(req, timeout=5, metadata=md)
                assert ei.value.code() == grpc.StatusCode.UNAUTHENTICATED
            ok = stub.Parse(req, timeout=5, metadata=(("authorization", f"Bearer {TOKEN}"),))
            assert list(ok.targets) == ["box"]
            # health stays reachable without a token (for orchestrators)
            h = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(service=""), timeout=5)
            assert h.status == health_pb2.HealthCheckResponse.SERVING
    finally:
        running.stop(0.5)


class _SlowLLM(BaseHTTPRequestHandler):
    def log_message(self, *args):
        pass

    def do_POST(self):  # noqa: N802
        self.rfile.read(int(self.headers.get("Content-Length", 0)))
        time.sleep(1.0)
        try:
            self.send_response(500)
            self.end_headers()
        except (BrokenPipeError, ConnectionResetError):
            pass


class _StuckLLM(LLMBackend):
    """A misbehaving backend that ignores its time budget."""

    name = "stuck"

    def complete(self, messages, timeout_s=None):
        time.sleep(0.8)
        return "{}"


def test_deadline_exceeded_no_crash():
    running = serve(ServerOptions(host="127.0.0.1", port=0, grace_s=0.5), parser=TaskParser(llm=_StuckLLM()))
    try:
        with grpc.insecure_channel(running.address) as ch:
            stub = parser_pb2_grpc.ParserStub(ch)
            with pytest.raises(grpc.RpcError) as ei:
                stub.Parse(parser_pb2.ParseRequest(task_text="Pick up the box"), timeout=0.3)
            assert ei.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
            resp = stub.Parse(parser_pb2.ParseRequest(task_text="Map the lawn chairs"), timeout=5)
            assert list(resp.targets) == ["lawn chair"] and resp.backend == "rules(fallback from stuck)"
            h = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(service=""), timeout=5)
            assert h.status == health_pb2.HealthCheckResponse.SERVING
    finally:
        running.stop(0.5)


def test_remaining_deadline_bounds_llm_call():
    http = ThreadingHTTPServer(("127.0.0.1", 0), _SlowLLM)
    http.daemon_threads = True
    threading.Thread(target=http.serve_forever, daemon=True).start()
    cfg = ParserConfig(backend="openai", openai=OpenAIConfig(
        base_url=f"http://127.0.0.1:{http.server_address[1]}/v1", model="m", timeout_s=3.0))
    running = serve(ServerOptions(host="127.0.0.1", port=0, grace_s=0.5), cfg)
    try:
        with grpc.insecure_channel(running.address) as ch:
            stub = parser_pb2_grpc.ParserStub(ch)
            # the LLM (configured timeout 3 s, answers after 1 s) is cut short by the client deadline
            # with a margin, so the rule-parser fallback still arrives in time
            t0 = time.monotonic()
            resp = stub.Parse(parser_pb2.ParseRequest(task_text="Map the lawn chairs"), timeout=1.0)
            assert list(resp.targets) == ["lawn chair"] and resp.backend == "rules(fallback from openai)"
            assert time.monotonic() - t0 < 1.0
    finally:
        running.stop(0.5)
        http.shutdown()
        http.server_close()


def test_graceful_shutdown_finishes_inflight():
    http = ThreadingHTTPServer(("127.0.0.1", 0), _SlowLLM)
    http.daemon_threads = True
    threading.Thread(target=http.serve_forever, daemon=True).start()
    cfg = ParserConfig(backend="openai", openai=OpenAIConfig(
        base_url=f"http://127.0.0.1:{http.server_address[1]}/v1", model="m", timeout_s=0.5))
    running = serve(ServerOptions(host="127.0.0.1", port=0, grace_s=3.0), cfg)
    result = {}
    with grpc.insecure_channel(running.address) as ch:
        stub = parser_pb2_grpc.ParserStub(ch)
        grpc.channel_ready_future(ch).result(timeout=5)
        fut = stub.Parse.future(parser_pb2.ParseRequest(task_text="Pick up the box"), timeout=5)
        time.sleep(0.15)  # the call is in flight (waiting for the slow LLM)
        t = threading.Thread(target=lambda: result.setdefault("stopped", running.stop(3.0)))
        t.start()
        resp = fut.result(timeout=5)
        t.join(5)
        assert list(resp.targets) == ["box"]
        with pytest.raises(grpc.RpcError):
            stub.Parse(parser_pb2.ParseRequest(task_text="Pick up the box"), timeout=1)
    http.shutdown()
    http.server_close()
