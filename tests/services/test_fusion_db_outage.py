"""PostgreSQL going away under two fusion replicas: the replicas reach the test database through a TCP relay
(:class:`tests._relay.TcpRelay`) that the test cuts — their connections drop and new ones are refused, as
when the database is stopped — without stopping the shared cluster. Calls then fail with UNAVAILABLE (not
INTERNAL), a retrying client gets through once the link is back, nothing acknowledged before is lost and
the replicas serve again without a restart."""

from __future__ import annotations

import threading
import time
from urllib.parse import urlsplit, urlunsplit

import grpc
import pytest

from tests._relay import TcpRelay
from gausslite.wire.codec import LOSSLESS, encode_subset
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.server import ServerOptions
from gausslite_services.fusion_server.client import RETRYABLE, FusionClient, intrinsics_to_proto
from gausslite_services.fusion_server.server import FusionConfig, serve
from gausslite_services.fusion_server.store import PostgresFusionStore, StoreUnavailable
from tests.services.test_fusion_server import INTR, rand_subset


@pytest.fixture()
def relayed(pg_schema_dsn):
    """(relay, DSN of the test schema through the relay)."""
    u = urlsplit(pg_schema_dsn)
    relay = TcpRelay((u.hostname or "127.0.0.1", u.port or 5432))
    auth = u.netloc.rpartition("@")[0]
    dsn = urlunsplit(u._replace(netloc=(auth + "@" if auth else "") + f"127.0.0.1:{relay.port}"))
    yield relay, dsn
    relay.cut()


def _until(fn, timeout_s: float):
    """``fn()``'s result once it stops raising grpc.RpcError / StoreUnavailable (the last error after ``timeout_s``)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return fn()
        except (grpc.RpcError, StoreUnavailable):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def test_store_raises_store_unavailable_while_the_database_is_unreachable(relayed):
    relay, dsn = relayed
    store = PostgresFusionStore(dsn, pool_size=2, acquire_timeout_s=1.0)
    try:
        assert store.latest_complete() == {}
        relay.cut()
        with pytest.raises(StoreUnavailable):
            store.latest_complete()
        with pytest.raises(StoreUnavailable):
            store.begin_upload("robot1", 1, 2, 10, 0)
        relay.restore()
        assert _until(store.latest_complete, 60) == {}  # the same store object recovers
        assert store.begin_upload("robot1", 1, 2, 10, 0).n_chunks == 2
    finally:
        store.close()


def test_two_replicas_answer_unavailable_and_recover_without_restart(tmp_path, relayed):
    relay, dsn = relayed
    cfg = FusionConfig(store_acquire_timeout_s=1.0, store_pool_size=4)
    reps = [serve(ServerOptions(port=0, max_workers=8), cfg, data_dir=str(tmp_path / n), store=dsn) for n in "ab"]
    channels = [grpc.insecure_channel(r.address) for r in reps]  # no retry policy: every status is seen
    stubs = [fusion_pb2_grpc.FusionStub(ch) for ch in channels]
    g1, g2 = rand_subset(900, 0.0, 1), rand_subset(700, 0.5, 2)
    try:
        with FusionClient(reps[0].address, timeout_s=10) as c:
            c.open_session("robot1", "inspect the valve", INTR)
            assert c.upload_subset("robot1", 1, g1, full_map_gaussians=5000, quant=LOSSLESS).complete

        relay.cut()  # the database goes away
        chunks = encode_subset(g2, "robot1", 2, chunk_gaussians=300, quant=LOSSLESS)
        hdr = fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(agent_id="robot1", map_version=2,
                                                                            n_chunks=len(chunks)))
        calls = {
            "GetStats": lambda s: s.GetStats(fusion_pb2.StatsRequest(), timeout=10),
            "GetUploadStatus": lambda s: s.GetUploadStatus(
                fusion_pb2.UploadStatusRequest(agent_id="robot1", map_version=1), timeout=10),
            "OpenSession": lambda s: s.OpenSession(fusion_pb2.OpenSessionRequest(
                agent_id="robot2", task_text="find the chair", intrinsics=intrinsics_to_proto(INTR)), timeout=10),
            "UploadSubset": lambda s: s.UploadSubset(iter([hdr] + [fusion_pb2.UploadSubsetRequest(chunk=x)
                                                                  for x in chunks]), timeout=10),
            "Fuse": lambda s: list(s.Fuse(fusion_pb2.FuseRequest(method=fusion_pb2.FUSE_METHOD_CONCAT), timeout=10)),
        }
        codes = {}
        for name, call in calls.items():
            for r, stub in zip("ab", stubs):
                with pytest.raises(grpc.RpcError) as ei:
                    call(stub)
                codes[f"{name}@{r}"] = ei.value.code()
        assert set(codes.values()) == {grpc.StatusCode.UNAVAILABLE}, codes

        # a caller retrying with backoff gets through once the database is back (the client makes one attempt)
        threading.Timer(1.5, relay.restore).start()
        with FusionClient(f"ipv4:127.0.0.1:{reps[0].port},127.0.0.1:{reps[1].port}", timeout_s=10) as c:
            for attempt in range(9):
                try:
                    res = c.upload_subset("robot1", 2, g2, full_map_gaussians=5000, quant=LOSSLESS,
                                          chunk_gaussians=300)
                    break
                except grpc.RpcError as e:
                    assert e.code() in RETRYABLE and attempt < 8, e
                    time.sleep(0.2 * 2 ** attempt)
            assert res.complete
        # both replicas serve again (same processes) and agree; nothing acknowledged was lost
        for r in reps:
            with FusionClient(r.address, timeout_s=10) as c:
                st = _until(lambda: c.stats()["agents"]["robot1"], 60)
                assert st["latest_map_version"] == 2 and st["has_complete_subset"]
        with FusionClient(reps[1].address, timeout_s=30) as c:
            fused = c.fuse("concat")
            assert c.download_fused(fused.fused_version).equals(g2)
    finally:
        for ch in channels:
            ch.close()
        for r in reps:
            r.stop(0.5)


def test_health_is_not_serving_while_the_database_is_unreachable(tmp_path, relayed):
    """Health tells the truth about the store: NOT_SERVING while PostgreSQL cannot be reached (an orchestrator takes
    the replica out of rotation), SERVING again once it can, without a restart."""
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    from gausslite_services.fusion_server.servicer import SERVICE_NAME

    relay, dsn = relayed
    rep = serve(ServerOptions(port=0), FusionConfig(store_acquire_timeout_s=1.0, health_probe_s=0.3),
                data_dir=str(tmp_path / "h"), store=dsn)
    ch = grpc.insecure_channel(rep.address)
    hs = health_pb2_grpc.HealthStub(ch)

    def status(name: str):
        return hs.Check(health_pb2.HealthCheckRequest(service=name), timeout=5).status

    def until(want, timeout_s=20.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if status(SERVICE_NAME) == want and status("") == want:
                return True
            time.sleep(0.1)
        return False

    try:
        assert until(health_pb2.HealthCheckResponse.SERVING)
        relay.cut()
        assert until(health_pb2.HealthCheckResponse.NOT_SERVING)
        relay.restore()
        assert until(health_pb2.HealthCheckResponse.SERVING, 60)
    finally:
        ch.close()
        rep.stop(0.5)
