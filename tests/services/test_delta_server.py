"""Delta pushes through a real (in-process) fusion server: the server rebuilds every version from
its base plus the delta and holds exactly the agent's mirror; a server restart between pushes keeps
deltas working; a lost base gives FAILED_PRECONDITION and a full upload recovers; an interrupted
delta (all chunks stored, rebuild not committed) is completed by the resumed upload."""

from __future__ import annotations

import contextlib

import grpc
import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.wire.codec import GaussianArrays, assemble, decode_chunk, peek_header
from gausslite.wire.delta import PushPlanner
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.server import ServerOptions
from gausslite_services.fusion_server.client import FusionClient
from gausslite_services.fusion_server.server import serve

INTR = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)


def _arrays(n: int, seed: int) -> GaussianArrays:
    r = np.random.default_rng(seed)
    return GaussianArrays(means=r.uniform(0, 1, (n, 3)), quats=r.normal(size=(n, 4)),
                          log_scales=r.uniform(-5, -3, (n, 3)), opacity_logits=r.normal(size=n),
                          colors=r.uniform(0, 1, (n, 3)), kappa=r.integers(1, 100, n), active=np.ones(n, bool))


class Agent:
    """A simulated agent map: ids + arrays, evolving between pushes."""

    def __init__(self, n: int):
        self.ids = np.arange(n)
        self.arr = _arrays(n, 0)
        self.next_id = n

    def evolve(self, seed: int, n_move=30, n_remove=20, n_new=50, kappa_growth=0):
        r = np.random.default_rng(seed)
        a = {k: np.array(getattr(self.arr, k), copy=True) for k in GaussianArrays.FIELDS}
        a["kappa"] += kappa_growth  # ROI-phase iterations since the last push: every active row grows
        mv = r.choice(len(self.ids), n_move, replace=False)
        a["means"][mv] += 0.01
        keep = np.ones(len(self.ids), bool)
        keep[r.choice(len(self.ids), n_remove, replace=False)] = False
        self.arr = GaussianArrays.concat([GaussianArrays(**{k: v[keep] for k, v in a.items()}), _arrays(n_new, seed)])
        self.ids = np.concatenate([self.ids[keep], self.next_id + np.arange(n_new)])
        self.next_id += n_new


@contextlib.contextmanager
def _server(path):
    """An in-process fusion server on ``path`` and a client with the agent's session open."""
    srv = serve(ServerOptions(port=0, max_workers=8), None, data_dir=str(path))
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            c.wait_ready(10)
            c.open_session("robot", "find the mug", INTR)
            yield srv, c
    finally:
        srv.stop(0.5)


def _held(srv, agent: str) -> GaussianArrays:
    v = srv.store.latest_version(agent)
    return assemble(srv.store.chunk_data(agent, v))[0]


def _push(client, planner, agent, version):
    plan = planner.plan(agent.ids, agent.arr, version, measure_full=False)
    r = client.upload_chunks("robot", plan.version, plan.chunks, n_gaussians=plan.n_records,
                             full_map_gaussians=10 * len(agent.arr))
    assert r.complete
    planner.acknowledge(plan)
    return plan, r


def test_delta_round_trips_restart_and_lost_base(tmp_path):
    agent = Agent(400)
    planner = PushPlanner("robot", chunk_gaussians=128)
    with _server(tmp_path / "data") as (srv, c):
        p1, r1 = _push(c, planner, agent, 1)
        assert not p1.is_delta and r1.bytes_sent == p1.nbytes
        assert _held(srv, "robot").equals(p1.subset)
        agent.evolve(1, kappa_growth=25)
        p2, r2 = _push(c, planner, agent, 2)
        assert p2.is_delta and p2.n_records == 30 + 50 and p2.n_removed == 20
        assert planner.last_stats["kappa_shift"] == 25
        assert r2.bytes_sent == p2.nbytes < p1.nbytes / 2
        held = _held(srv, "robot")
        assert held.equals(p2.subset)  # rebuilt from base + delta (κ shift applied), stored whole
        row = {int(i): k for i, k in zip(p2.ids, held.kappa)}
        assert [row[int(i)] for i in agent.ids] == agent.arr.kappa.tolist()  # the server's κ is the agent's
        assert srv.store.latest_version("robot") == 2 and srv.store.upload("robot", 1) is None
        for v in range(3, 8):  # a long mission: the server keeps one decoded subset per agent, not one per version
            agent.evolve(10 + v)
            assert _push(c, planner, agent, v)[0].is_delta
        assert list(srv.servicer._cache) == [("robot", 7)] and _held(srv, "robot").equals(planner.base)
    # restart on the same data dir between pushes: the base survives, deltas keep working
    with _server(tmp_path / "data") as (srv, c):
        agent.evolve(2, kappa_growth=7)
        p3, _ = _push(c, planner, agent, 8)
        assert p3.is_delta and p3.base_version == 7
        assert _held(srv, "robot").equals(p3.subset)
    # a server that lost its data: the delta is refused precisely, a full upload recovers
    with _server(tmp_path / "fresh") as (srv, c):
        agent.evolve(3)
        p4 = planner.plan(agent.ids, agent.arr, 9, measure_full=False)
        assert p4.is_delta
        with pytest.raises(grpc.RpcError) as ei:
            c.upload_chunks("robot", 9, p4.chunks, n_gaussians=p4.n_records, full_map_gaussians=9000)
        assert ei.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert "base version 8" in ei.value.details()
        assert srv.store.upload("robot", 9) is None  # the refused delta left nothing behind
        planner.forget()
        p5, _ = _push(c, planner, agent, 10)
        assert not p5.is_delta and _held(srv, "robot").equals(p5.subset)


def test_interrupted_delta_rebuild_is_completed_by_the_resumed_upload(tmp_path):
    agent = Agent(300)
    planner = PushPlanner("robot", chunk_gaussians=64)
    with _server(tmp_path / "data") as (srv, c):
        _push(c, planner, agent, 1)
        agent.evolve(5, n_move=100, n_new=120)
        p2 = planner.plan(agent.ids, agent.arr, 2, measure_full=False)
        assert p2.is_delta and len(p2.chunks) > 1
        # a crash after every delta chunk was persisted but before the rebuild committed
        srv.store.begin_upload("robot", 2, len(p2.chunks), 0, 0)
        for data in p2.chunks:
            h, dc = peek_header(data), decode_chunk(data)
            srv.store.put_chunk("robot", 2, h.chunk_index, data, dc.digest, h.count, h.total_count,
                                h.lossless, defer_complete=True)
        st = c.upload_status("robot", 2)
        assert not st.complete and not st.missing
        r = c.upload_chunks("robot", 2, p2.chunks, n_gaussians=p2.n_records, full_map_gaussians=5000)
        assert r.complete and r.chunks_sent == 0  # nothing re-sent: the header alone resumed it
        assert _held(srv, "robot").equals(p2.subset)
        # re-sending the completed version is an idempotent no-op
        assert c.upload_chunks("robot", 2, p2.chunks, n_gaussians=p2.n_records,
                               full_map_gaussians=5000).complete


def test_ack_and_stats_report_the_bytes_received_for_a_delta(tmp_path):
    """``bytes_on_wire`` of a delta version is what crossed the link (its delta chunks), not the lossless rebuilt
    subset the server stores (``stored_bytes``), in the ack, in GetUploadStatus, in GetStats and after a restart."""
    agent = Agent(600)
    planner = PushPlanner("robot", chunk_gaussians=128)
    with _server(tmp_path / "data") as (srv, c):
        p1, _ = _push(c, planner, agent, 1)
        st1 = c.upload_status("robot", 1)
        assert st1.bytes_on_wire == st1.stored_bytes == p1.nbytes  # a full upload is stored as sent
        agent.evolve(1, n_move=10, n_remove=5, n_new=10)
        p2 = planner.plan(agent.ids, agent.arr, 2, measure_full=False)
        assert p2.is_delta
        msgs = [fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(
            agent_id="robot", map_version=2, n_chunks=len(p2.chunks), full_map_gaussians=6000))]
        msgs += [fusion_pb2.UploadSubsetRequest(chunk=x) for x in p2.chunks]
        with grpc.insecure_channel(f"127.0.0.1:{srv.port}") as ch:  # the raw ack of the call that completes it
            ack = fusion_pb2_grpc.FusionStub(ch).UploadSubset(iter(msgs), timeout=20)
        planner.acknowledge(p2)
        delta_bytes = sum(len(x) for x in p2.chunks)
        stored = sum(len(x) for x in srv.store.chunk_data("robot", 2))
        assert ack.complete and ack.bytes_on_wire == delta_bytes
        assert ack.stored_bytes == stored > 5 * delta_bytes  # the lossless rebuild, kept apart
        assert ack.n_gaussians == len(agent.arr) == len(_held(srv, "robot"))
        st2 = c.upload_status("robot", 2)
        assert (st2.bytes_on_wire, st2.stored_bytes) == (delta_bytes, stored)
        a = c.stats()["agents"]["robot"]
        assert (a["bytes_on_wire"], a["stored_bytes"]) == (delta_bytes, stored)
        assert a["bytes_per_gaussian"] == pytest.approx(stored / len(agent.arr))
    with _server(tmp_path / "data") as (srv, c):  # persisted with the upload
        st2 = c.upload_status("robot", 2)
        assert (st2.bytes_on_wire, st2.stored_bytes) == (delta_bytes, stored)
