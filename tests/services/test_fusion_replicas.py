"""Fusion replicas on one PostgreSQL store: any replica accepts any agent's chunks, an
upload interrupted by a SIGKILLed replica resumes on another through the round-robin client, fused
versions are allocated in the database with concurrent ``Fuse`` calls serialised, and
``DownloadFused`` / ``GetStats`` answer the same on every replica; a ``dns:///`` target reaches a replica."""

from __future__ import annotations

import sys
import threading

import grpc
import pytest

from gausslite.fusion.vote import voxel_vote
from gausslite.wire.codec import LOSSLESS, assemble, encode_subset
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.server import ServerOptions
from gausslite_services.fusion_server.client import FusionClient
from gausslite_services.fusion_server.server import serve
from tests.services.test_fusion_server import INTR, frame, rand_subset
from tests.services.test_fusion_server_restart import _kill, _start


def _replica(tmp_path, dsn, name):
    return serve(ServerOptions(port=0, max_workers=16), data_dir=str(tmp_path / name), store=dsn)


def test_upload_interrupted_by_a_killed_replica_resumes_on_another(tmp_path, pg_schema_dsn):
    g = rand_subset(6000, 0.0, 1)
    chunks = encode_subset(g, "survivor", 3, chunk_gaussians=500, quant=LOSSLESS)  # 12 chunks
    proc, port_a = _start([sys.executable, "-m", "gausslite_services.fusion_server", "--port", "0", "--store",
                           pg_schema_dsn, "--data-dir", str(tmp_path / "unused"), "--port-file",
                           str(tmp_path / "port")],
                          tmp_path, tmp_path / "port")
    b = _replica(tmp_path, pg_schema_dsn, "b")
    try:
        with FusionClient(f"127.0.0.1:{port_a}", timeout_s=10) as ca:
            ca.wait_ready(20)
            ca.open_session("survivor", "inspect the valve", INTR)
            ca.upload_keyframes("survivor", [frame(0), frame(1)])
        ch = grpc.insecure_channel(f"127.0.0.1:{port_a}")
        hdr = fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(
            agent_id="survivor", map_version=3, n_chunks=12, full_map_gaussians=60000))
        ack = fusion_pb2_grpc.FusionStub(ch).UploadSubset(
            iter([hdr] + [fusion_pb2.UploadSubsetRequest(chunk=chunks[i]) for i in (0, 1, 2, 5, 7)]), timeout=10)
        ch.close()
        assert list(ack.stored) == [0, 1, 2, 5, 7] and not ack.complete
        _kill(proc)  # SIGKILL replica A mid-upload
        # the agent's round-robin channel names both replicas; A is gone, B has everything A acknowledged
        with FusionClient(f"ipv4:127.0.0.1:{port_a},127.0.0.1:{b.port}", timeout_s=10) as c:
            st = c.upload_status("survivor", 3)
            assert list(st.stored) == [0, 1, 2, 5, 7] and sorted(st.missing) == [3, 4, 6, 8, 9, 10, 11]
            res = c.upload_subset("survivor", 3, g, full_map_gaussians=60000, quant=LOSSLESS, chunk_gaussians=500)
            assert res.complete and res.chunks_sent == 7
            assert c.stats()["agents"]["survivor"]["keyframes"] == 2
            fused = c.fuse("concat")
            assert c.download_fused(fused.fused_version).equals(g)
        assert assemble(b.store.chunk_data("survivor", 3))[0].equals(assemble(chunks)[0])
    finally:
        _kill(proc)
        b.stop(0.5)


def test_replicas_agree_and_serialise_concurrent_fusions(tmp_path, pg_schema_dsn):
    reps = [_replica(tmp_path, pg_schema_dsn, n) for n in ("a", "b")]
    subsets = {f"r{i}": rand_subset(3000, 0.6 * i, 10 + i) for i in range(4)}  # neighbouring cubes overlap
    try:
        target = "ipv4:" + ",".join(f"127.0.0.1:{r.port}" for r in reps)
        with FusionClient(target, timeout_s=20) as c:
            for a, g in subsets.items():  # round robin: chunks of one agent land on both replicas
                c.open_session(a, f"task {a}", INTR)
                assert c.upload_subset(a, 1, g, full_map_gaussians=30000, chunk_gaussians=400,
                                       quant=LOSSLESS).complete
        clients = [FusionClient(f"127.0.0.1:{r.port}", timeout_s=30) for r in reps]
        results, errors = [], []

        def fuse(cl):
            try:
                results.append(cl.fuse("vote"))
            except Exception as e:  # noqa: BLE001
                errors.append(e)

        threads = [threading.Thread(target=fuse, args=(clients[i % 2],)) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(120)
        assert not errors
        assert sorted(r.fused_version for r in results) == [1, 2, 3, 4]  # allocated once each, in the DB
        full, report = voxel_vote(subsets, 0.10)
        assert all(r.n_gaussians == len(full) and r.kept == report.kept for r in results)
        # identical answers on every replica
        s0, s1 = (cl._stub.GetStats(fusion_pb2.StatsRequest(), timeout=10) for cl in clients)
        assert s0 == s1 and s0.latest_fused_version == 4 and len(s0.agents) == 4
        d0, d1 = (cl.download_fused(0) for cl in clients)
        assert d0.equals(d1) and d0.equals(full)
        # incremental: one agent's update re-votes only that agent, the result equals a full vote
        moved = rand_subset(2000, 0.9, 99)
        with FusionClient(target, timeout_s=20) as c:
            assert c.upload_subset("r2", 2, moved, full_map_gaussians=30000, quant=LOSSLESS).complete
        subsets["r2"] = moved
        r = clients[0]._stub.Fuse(fusion_pb2.FuseRequest(method=fusion_pb2.FUSE_METHOD_VOTE), timeout=60)
        last = [m for m in r][-1].result
        assert last.incremental and last.agents_revoted == 1 and last.fused_version == 5
        assert 0 < last.vote_seconds <= last.seconds
        full2, _ = voxel_vote(subsets, 0.10)
        assert clients[1].download_fused(5).equals(full2)
        assert not full2.equals(full)
        for cl in clients:
            cl.close()
    finally:
        for r in reps:
            r.stop(0.5)


def test_bad_store_dsn_is_a_clear_startup_error(tmp_path, capsys, monkeypatch):
    from gausslite_services.fusion_server import store_postgres
    from gausslite_services.fusion_server.server import main

    # nothing listens on port 1, so every connection attempt is refused at once: the store gives up after its
    # first-connection wait (10 s by default), which this test shortens; the error is the same
    real_init = store_postgres.PostgresFusionStore.__init__

    def quick_init(self, dsn, **kw):
        real_init(self, dsn, **{"connect_timeout_s": 1.0, **kw})

    monkeypatch.setattr(store_postgres.PostgresFusionStore, "__init__", quick_init)
    rc = main(["--port", "0", "--store", "postgresql://x:secret@127.0.0.1:1/none", "--data-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and "cannot connect to the PostgreSQL fusion store" in err
    assert "secret" not in err  # the password is never logged


def test_client_balances_round_robin_over_every_listed_replica(tmp_path):
    """The channel spreads calls over all replicas of an ``ipv4:`` list (gRPC round_robin): with
    separate SQLite stores each replica records the sessions it served."""
    from gausslite_services.fusion_server.client import service_config

    # round robin, and no retry policy: the client makes one attempt per call, its caller retries
    assert service_config() == {"loadBalancingConfig": [{"round_robin": {}}]}
    reps = [serve(ServerOptions(port=0), data_dir=str(tmp_path / n)) for n in ("a", "b")]
    try:
        with FusionClient("ipv4:" + ",".join(f"127.0.0.1:{r.port}" for r in reps), timeout_s=10) as c:
            c.wait_ready(10)
            for i in range(12):
                c.open_session(f"r{i}", "t", INTR)
        served = [len(r.store.sessions()) for r in reps]
        assert sum(served) == 12 and min(served) >= 3, served
    finally:
        for r in reps:
            r.stop(0.5)


def test_dns_target_reaches_a_replica(tmp_path, pg_schema_dsn):
    """``dns:///name:port`` (the agent's target for the headless Service in deploy/k8s) goes through
    gRPC's DNS resolver and reaches a replica: health SERVING, a session and a subset through it,
    visible on another replica of the store; a name that does not resolve never becomes ready."""
    reps = [_replica(tmp_path, pg_schema_dsn, n) for n in ("a", "b")]
    g = rand_subset(800, 0.0, 5)
    try:
        with FusionClient(f"dns:///localhost:{reps[0].port}", timeout_s=10) as c:
            c.wait_ready(20)
            assert c.open_session("dns-agent", "inspect the valve", INTR).latest_map_version == 0
            assert c.upload_subset("dns-agent", 1, g, full_map_gaussians=8000, quant=LOSSLESS).complete
            mine = c.stats()["agents"]["dns-agent"]
            assert mine["latest_map_version"] == 1 and mine["gaussians_received"] == 800
        assert reps[0].store.latest_version("dns-agent") == 1
        with FusionClient(f"127.0.0.1:{reps[1].port}", timeout_s=10) as c:
            assert c.stats()["agents"]["dns-agent"]["latest_map_version"] == 1
        with FusionClient(f"dns:///no-such-fusion-host.invalid:{reps[0].port}", timeout_s=2) as c:
            with pytest.raises(TimeoutError, match="no-such-fusion-host"):
                c.wait_ready(2)
    finally:
        for r in reps:
            r.stop(0.5)
