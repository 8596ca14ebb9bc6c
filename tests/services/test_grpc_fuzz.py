"""Hostile bytes on every gRPC method of the three services: random byte strings and mutated serialized
messages (seeded, bounded) go through a generic channel with raw-bytes (de)serializers to each method
enumerated from the proto descriptors. Every call must end with a gRPC status within its deadline —
never UNKNOWN (an unhandled exception in a handler) nor INTERNAL (a crash reported as such) — and every
server must still answer its health check afterwards. The fusion server runs once on SQLite and once on
PostgreSQL (``$GAUSSLITE_TEST_PG_DSN``; skipped without it, except under CI).

``GAUSSLITE_FUZZ_SEED`` (default 0) and ``GAUSSLITE_FUZZ_CASES`` (cases per method, default 60) vary the run.
"""

from __future__ import annotations

import os
import random
import time

import grpc
import pytest
from google.protobuf.descriptor import FieldDescriptor

from gausslite.datasets import load_dataset
from gausslite.synthetic import make_scene
from gausslite.wire.codec import GaussianArrays, encode_subset
from gausslite_rpc import agent_pb2, fusion_pb2, parser_pb2
from gausslite.config import FusionSettings, load_config
from gausslite_services.agent.server import AgentSettings, serve as serve_agent
from gausslite_services.common.server import ServerOptions

SEED = int(os.environ.get("GAUSSLITE_FUZZ_SEED", "0"))
CASES = int(os.environ.get("GAUSSLITE_FUZZ_CASES", "60"))
#: each call's deadline, which a hung handler misses; generous, as CI runs beside other work on two cores
CALL_TIMEOUT_S = 60.0
#: the fusion server's refinements here: some cases are valid Fuse calls with a joint refinement, which run at most
#: this many iterations (a case asking for more gets INVALID_ARGUMENT), and the team map kept refined in the
#: background refines as briefly. At the defaults (200 and up to 20000 iterations for a Fuse) one valid case took
#: more than a minute beside a CPU-bound process, which the call's deadline would take for a hang.
REFINE_LIMITS = {"default_refine_iters": 5, "max_refine_iters": 10, "team_map": {"refine_iters": 5}}
FORBIDDEN = {grpc.StatusCode.UNKNOWN, grpc.StatusCode.INTERNAL}


@pytest.fixture(params=["sqlite", "postgresql"])
def services(request, tmp_path):
    """Parser, fusion server (SQLite store, or PostgreSQL: a fresh schema of the test database) and agent."""
    from gausslite_services.fusion_server.server import serve as serve_fusion
    from gausslite_services.parser.server import serve as serve_parser

    store = request.getfixturevalue("pg_schema_dsn") if request.param == "postgresql" else None
    make_scene(tmp_path / "scene", seed=0, width=32, height=24, frames=2, progress=False)
    parser = serve_parser(ServerOptions(port=0))
    fusion = serve_fusion(ServerOptions(port=0, max_message_bytes=1 << 20), FusionSettings(**REFINE_LIMITS),
                          data_dir=str(tmp_path / "fusion"), store=store)
    # a final push that fails (the fuzzer may have opened the agent's session) ends Finish well within its deadline
    cfg = load_config(None, ["mapper.iters_per_frame=1", "mapper.warmup_iters=1", "mapper.seeding.seeds_per_frame=50",
                                   "agent.share.rule=active", "agent.push.final_timeout_s=2", "agent.final_pass_s=1"]).agent
    agent = serve_agent(ServerOptions(port=0, max_message_bytes=1 << 20), AgentSettings(
        agent_id="fuzzbot", parser_address=parser.address, fusion_address=fusion.address, parser_timeout_s=5,
        annotations_path=str(tmp_path / "scene"), config=cfg))
    servers = {"gausslite.v1.Parser": parser, "gausslite.v1.Fusion": fusion, "gausslite.v1.Agent": agent}
    ds = load_dataset(tmp_path / "scene" / "agent_a")
    yield servers, (ds, ds.annotations.tasks[0].text)
    for srv in servers.values():
        srv.stop(0)


def _methods():
    out = []
    for mod in (parser_pb2, agent_pb2, fusion_pb2):
        for svc in mod.DESCRIPTOR.services_by_name.values():
            for m in svc.methods:
                out.append((svc.full_name, m))
    return out


def _value(f: FieldDescriptor, rng: random.Random):
    t = f.type
    if t == FieldDescriptor.TYPE_STRING:
        return rng.choice(["", "robot1", "fuzzbot", "pick up the red mug", "../../etc", "x" * rng.randint(0, 300),
                           "\u00e9\u4e2d", "a/b", "-1", "nul\x00inside", ".."])
    if t == FieldDescriptor.TYPE_BYTES:
        return bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 64)))
    if t == FieldDescriptor.TYPE_BOOL:
        return rng.random() < 0.5
    if t in (FieldDescriptor.TYPE_DOUBLE, FieldDescriptor.TYPE_FLOAT):
        return rng.choice([0.0, 1.0, -1.0, 1e9, -1e-9, float("nan"), float("inf"), 0.5])
    if t == FieldDescriptor.TYPE_ENUM:
        return rng.choice([v.number for v in f.enum_type.values] + [99])
    if t in (FieldDescriptor.TYPE_UINT32, FieldDescriptor.TYPE_FIXED32):
        return rng.choice([0, 1, 2, 7, 1000, 2**32 - 1])
    if t in (FieldDescriptor.TYPE_UINT64, FieldDescriptor.TYPE_FIXED64):
        return rng.choice([0, 1, 2, 3, 1000, 2**63, 2**64 - 1])
    if t in (FieldDescriptor.TYPE_INT32, FieldDescriptor.TYPE_SINT32, FieldDescriptor.TYPE_SFIXED32):
        return rng.choice([0, 1, -1, 2**31 - 1, -2**31])
    return rng.choice([0, 1, -1, 2**63 - 1, -2**63])


def _fill(msg, rng: random.Random, depth: int = 0):
    """Set a random selection of ``msg``'s fields to plausible or extreme values (nested up to 3 deep)."""
    for f in msg.DESCRIPTOR.fields:
        if rng.random() < 0.35:
            continue
        repeated = f.is_repeated
        if f.type == FieldDescriptor.TYPE_MESSAGE:
            if depth >= 3 or f.message_type.GetOptions().map_entry:
                continue
            if repeated:
                for _ in range(rng.randint(0, 3)):
                    _fill(getattr(msg, f.name).add(), rng, depth + 1)
            else:
                _fill(getattr(msg, f.name), rng, depth + 1)
        elif repeated:
            n = rng.choice([0, 1, 16, 17, rng.randint(0, 40)])
            getattr(msg, f.name).extend(_value(f, rng) for _ in range(n))
        else:
            setattr(msg, f.name, _value(f, rng))
    return msg


def _mutate(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(5)
        if op == 0 and b:  # flip bits
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        elif op == 1 and b:  # truncate
            del b[rng.randrange(len(b)):]
        elif op == 2:  # insert random bytes
            i = rng.randint(0, len(b))
            b[i:i] = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 16)))
        elif op == 3 and b:  # duplicate a slice
            i = rng.randrange(len(b))
            b[i:i] = b[i:i + rng.randint(1, 32)]
        else:  # a huge varint length prefix
            b[rng.randint(0, len(b)):0] = b"\x0a\xff\xff\xff\xff\x0f"
    return bytes(b)


def _chunks(rng: random.Random, version: int = 1) -> list:
    import numpy as np

    r = np.random.default_rng(rng.getrandbits(32))
    n = 40
    g = GaussianArrays(means=r.uniform(-1, 1, (n, 3)), quats=r.normal(size=(n, 4)),
                       log_scales=r.uniform(-5, -3, (n, 3)), opacity_logits=r.normal(size=n),
                       colors=r.uniform(0, 1, (n, 3)), kappa=r.integers(0, 50, n), active=r.random(n) < 0.5)
    return encode_subset(g, "fuzzbot", version, chunk_gaussians=20)


def _templates(m, rng: random.Random, scene) -> list | None:
    """Valid requests of the method (a mission, a session, a subset upload, keyframes), which mutations then
    damage; None for methods without one (their messages are filled at random)."""
    from gausslite_services.agent.frames import encode_frame
    from gausslite_services.fusion_server.client import intrinsics_to_proto, keyframe_to_proto

    ds, text = scene
    if m.name == "Parse":
        return [parser_pb2.ParseRequest(task_text=text)]
    if m.name == "StartMission":
        return [agent_pb2.StartMissionRequest(task_text=text)]
    if m.name == "StreamFrames":
        return [encode_frame(ds[i % len(ds)]) for i in range(rng.randint(1, 3))]
    if m.name == "OpenSession":
        return [fusion_pb2.OpenSessionRequest(agent_id="fuzzbot", task_text=rng.choice([text, text + "\x00"]),
                                              intrinsics=intrinsics_to_proto(ds[0].intrinsics))]
    if m.name == "UploadSubset":
        version = rng.randint(1, 4)
        chunks = _chunks(rng, version)
        hdr = fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(
            agent_id="fuzzbot", map_version=version, n_chunks=len(chunks), full_map_gaussians=100))
        return [hdr] + [fusion_pb2.UploadSubsetRequest(chunk=c) for c in chunks]
    if m.name == "UploadKeyframes":
        return [keyframe_to_proto("fuzzbot", ds[i % len(ds)], color_format="png") for i in range(rng.randint(1, 2))]
    return None


def _seed_messages(m, rng: random.Random, scene) -> list:
    """Request messages of the method's input type: a valid template or random field values."""
    t = _templates(m, rng, scene) if rng.random() < 0.7 else None
    if t is not None:
        return t
    mod = next(x for x in (parser_pb2, agent_pb2, fusion_pb2) if x.DESCRIPTOR.package and
               m.input_type.name in x.DESCRIPTOR.message_types_by_name)
    Msg = getattr(mod, m.input_type.name)
    return [_fill(Msg(), rng) for _ in range(rng.randint(1, 3) if m.client_streaming else 1)]


def _case(m, rng: random.Random, scene) -> list:
    """One call's request messages as raw bytes."""
    kind = rng.randrange(3)
    if kind == 0:  # random bytes
        msgs = [bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 200)))
                for _ in range(rng.randint(1, 3) if m.client_streaming else 1)]
    else:
        msgs = [x.SerializeToString() for x in _seed_messages(m, rng, scene)]
        if kind == 2:  # mutated
            k = rng.randrange(len(msgs))
            msgs[k] = _mutate(msgs[k], rng)
    return msgs if m.client_streaming else msgs[:1]


def _call(channel: grpc.Channel, path: str, m, msgs: list):
    """Make the call; return the status code (OK when it succeeded)."""
    try:
        if m.client_streaming and m.server_streaming:
            list(channel.stream_stream(path)(iter(msgs), timeout=CALL_TIMEOUT_S))
        elif m.client_streaming:
            channel.stream_unary(path)(iter(msgs), timeout=CALL_TIMEOUT_S)
        elif m.server_streaming:
            list(channel.unary_stream(path)(msgs[0], timeout=CALL_TIMEOUT_S))
        else:
            channel.unary_unary(path)(msgs[0], timeout=CALL_TIMEOUT_S)
    except grpc.RpcError as e:
        return e.code(), e.details()
    return grpc.StatusCode.OK, ""


def test_every_method_survives_hostile_bytes(services):
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    services, scene = services
    rng = random.Random(SEED)
    methods = _methods()
    assert {s for s, _ in methods} == set(services) and len(methods) >= 13
    bad, seen = [], {}
    t0 = time.monotonic()
    channels = {s: grpc.insecure_channel(srv.address) for s, srv in services.items()}
    try:
        for svc, m in methods:
            path = f"/{svc}/{m.name}"
            for i in range(CASES):
                msgs = _case(m, rng, scene)
                code, details = _call(channels[svc], path, m, msgs)
                seen.setdefault(path, set()).add(code.name)
                if code in FORBIDDEN or code == grpc.StatusCode.DEADLINE_EXCEEDED:
                    bad.append((path, i, code.name, details[:200], [x[:40].hex() for x in msgs]))
        for svc, srv in services.items():
            stub = health_pb2_grpc.HealthStub(channels[svc])
            r = stub.Check(health_pb2.HealthCheckRequest(service=svc), timeout=5)
            assert r.status == health_pb2.HealthCheckResponse.SERVING, svc
    finally:
        for ch in channels.values():
            ch.close()
    print(f"{sum(map(len, seen.values()))} (method, status) pairs over {len(methods)} methods in "
          f"{time.monotonic() - t0:.1f} s: {dict(sorted((k, sorted(v)) for k, v in seen.items()))}")
    assert not bad, "\n".join(map(str, bad[:20]))
