"""Integration tests of the fusion server (paper Sec. III-E) with real in-process gRPC
servers on ephemeral loopback ports (127.0.0.1:0) and the robot-side :class:`FusionClient`."""

from __future__ import annotations

import importlib.util
import logging
import random
import threading
import time

import grpc
import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.fusion.vote import concat, voxel_vote
from gausslite.wire.codec import LOSSLESS, GaussianArrays, QuantConfig, assemble, encode_subset
from gausslite_rpc import common_pb2, fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.server import ServerOptions
from gausslite_services.fusion_server.client import (FusionClient, encode_color_jpeg, encode_depth_png,
                                                     intrinsics_to_proto, keyframe_to_proto)
from gausslite_services.fusion_server.server import FusionConfig, serve

H, W = 24, 32
INTR = Intrinsics(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, W, H)
HAVE_REFINE = importlib.util.find_spec("gausslite.fusion.refine") is not None


def rand_subset(n: int, offset: float, seed: int) -> GaussianArrays:
    """n random Gaussians in the cube [offset, offset + 1]^3 metres with κ in [0, 100)."""
    r = np.random.default_rng(seed)
    return GaussianArrays(means=r.uniform(0, 1, (n, 3)) + offset, quats=r.normal(size=(n, 4)),
                          log_scales=r.uniform(-5, -3, (n, 3)), opacity_logits=r.normal(size=n),
                          colors=r.uniform(0, 1, (n, 3)), kappa=r.integers(0, 100, n), active=r.random(n) < 0.5)


def frame(i: int, shift: float = 0.0) -> Frame:
    """A posed RGB-D frame looking at a textured plane 1.5 m ahead."""
    r = np.random.default_rng(i)
    c2w = np.eye(4)
    c2w[0, 3] = shift
    rgb = (r.uniform(0, 255, (H, W, 3))).astype(np.uint8)
    return Frame(i, i / 30.0, rgb, np.full((H, W), 1.5, np.float32), c2w, INTR)


def start(tmp_path, name="data", **kw):
    opts = dict(port=0, max_workers=16)
    cfg = kw.pop("config", None)
    opts.update(kw)
    return serve(ServerOptions(**opts), cfg, data_dir=str(tmp_path / name))


@pytest.fixture()
def server(tmp_path):
    srv = start(tmp_path, max_message_bytes=1 << 20)
    yield srv
    srv.stop(0.5)


@pytest.fixture()
def client(server):
    with FusionClient(f"127.0.0.1:{server.port}", timeout_s=20) as c:
        c.wait_ready(10)
        yield c


def stub_of(srv, token=None):
    ch = grpc.insecure_channel(f"127.0.0.1:{srv.port}")
    return ch, fusion_pb2_grpc.FusionStub(ch), ((("authorization", f"Bearer {token}"),) if token else None)


def header(agent, version, n_chunks, full=0):
    return fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(
        agent_id=agent, map_version=version, n_chunks=n_chunks, full_map_gaussians=full))


def upload_raw(stub, agent, version, chunks, order=None, full=0, n_chunks=None):
    order = range(len(chunks)) if order is None else order
    msgs = [header(agent, version, n_chunks or len(chunks), full)] + \
        [fusion_pb2.UploadSubsetRequest(chunk=chunks[i]) for i in order]
    return stub.UploadSubset(iter(msgs), timeout=20)


def code_of(fn):
    with pytest.raises(grpc.RpcError) as ei:
        fn()
    return ei.value.code(), ei.value.details()


# --------------------------------------------------------------------------------------------


def test_two_agents_full_path(server, client):
    a, b = rand_subset(3000, 0.0, 1), rand_subset(2000, 0.5, 2)  # overlapping cubes → contested voxels
    client.open_session("robot-a", "find the cup", INTR)
    client.open_session("robot_b.2", "find the desk", INTR)
    ra = client.upload_subset("robot-a", 1, a, full_map_gaussians=30000, chunk_gaussians=700)
    rb = client.upload_subset("robot_b.2", 4, b, full_map_gaussians=8000, quant=LOSSLESS, chunk_gaussians=500)
    assert ra.complete and rb.complete and ra.n_chunks == 5 and rb.n_chunks == 4
    assert ra.n_gaussians == 3000 and rb.n_gaussians == 2000
    chunks_a = encode_subset(a, "robot-a", 1, chunk_gaussians=700)
    assert ra.bytes_on_wire == sum(len(c) for c in chunks_a)
    assert client.upload_keyframes("robot-a", [frame(i, 0.1 * i) for i in range(3)]) == 3
    assert client.upload_keyframes("robot_b.2", [frame(10 + i) for i in range(2)]) == 2

    # expected results computed locally from what the server decodes (lossless storage of fused maps)
    maps = {"robot-a": assemble(chunks_a)[0],
            "robot_b.2": assemble(encode_subset(b, "robot_b.2", 4, chunk_gaussians=500, quant=LOSSLESS))[0]}
    seen = []
    rc = client.fuse("concat", progress=lambda f, m: seen.append((f, m)))
    assert rc.n_gaussians == 5000 and rc.kept == {"robot-a": 3000, "robot_b.2": 2000} and rc.method == "concat"
    assert seen[-1][0] == 1.0 and all(0.0 <= f <= 1.0 for f, _ in seen)
    assert [f for f, _ in seen] == sorted(f for f, _ in seen)
    # the 3x3x3 neighbourhood contest (contest_radius 1, what the sim requests), then the server default:
    # the paper's per-voxel rule
    r1 = client.fuse("vote", voxel_size=0.1, contest_radius=1)
    expected1, report1 = voxel_vote(maps, 0.1, contest_radius=1)
    assert r1.contest_radius == 1 and r1.kept == dict(report1.kept)
    assert client.download_fused(r1.fused_version).equals(expected1)
    rv = client.fuse("vote", voxel_size=0.1, progress=None)
    expected, report = voxel_vote(maps, 0.1)
    assert rv.contest_radius == 0 and rc.contest_radius == 0
    assert report1.contested_voxels > report.contested_voxels > 0 and rv.n_gaussians == len(expected) < 5000
    assert rv.kept == dict(report.kept) and rv.fused_version == r1.fused_version + 1 == rc.fused_version + 2
    assert client.download_fused(rv.fused_version).equals(expected)
    # provenance: each agent's rows are one block of the downloaded map, where FuseResult.agents says
    assert rv.first_row == {"robot-a": 0, "robot_b.2": rv.kept["robot-a"]}
    assert rc.first_row == {"robot-a": 0, "robot_b.2": 3000}
    for name, first in rv.first_row.items():
        rows = np.flatnonzero(np.array(report.agents)[report.source_agent] == name)
        assert rows.tolist() == list(range(first, first + rv.kept[name]))
    assert client.download_fused(0).equals(expected)  # latest
    assert client.download_fused(0, method="concat").equals(concat(maps))
    assert client.download_fused(rc.fused_version).equals(concat(maps))

    st = client.stats()
    sa, sb = st["agents"]["robot-a"], st["agents"]["robot_b.2"]
    assert sa["share_pct"] == pytest.approx(10.0) and sb["share_pct"] == pytest.approx(25.0)
    assert sa["bytes_on_wire"] == ra.bytes_on_wire and sb["bytes_on_wire"] == rb.bytes_on_wire
    assert sa["gaussians_received"] == 3000 and sa["chunks"] == 5 and sa["latest_map_version"] == 1
    assert sb["latest_map_version"] == 4 and sa["keyframes"] == 3 and sb["keyframes"] == 2
    assert sa["task_text"] == "find the cup"
    assert [f["fused_version"] for f in st["fused"]] == [rc.fused_version, r1.fused_version, rv.fused_version]
    assert st["latest_fused_version"] == rv.fused_version


@pytest.mark.skipif(not HAVE_REFINE, reason="gausslite.fusion.refine (lead's core library work) is not available")
def test_fuse_with_refinement(server, client):
    client.open_session("r1", "cup", INTR)
    client.open_session("r2", "desk", INTR)
    # Gaussians on the plane z = 1.5 m seen by the keyframes
    for agent, off, seed in (("r1", -0.3, 3), ("r2", 0.0, 4)):
        g = rand_subset(300, 0.0, seed)
        g.means[:, 0] = g.means[:, 0] * 0.8 + off
        g.means[:, 1] = g.means[:, 1] * 0.6 - 0.3
        g.means[:, 2] = 1.5
        assert client.upload_subset(agent, 1, g, full_map_gaussians=3000).complete
    client.upload_keyframes("r1", [frame(0), frame(1, 0.05)])
    client.upload_keyframes("r2", [frame(2, -0.05)])
    msgs = []
    r = client.fuse("vote", refine=True, refine_iters=4, progress=lambda f, m: msgs.append(m))
    assert r.refined and r.refine_iters == 4 and r.keyframes_used == 3
    assert r.first_row == {}  # the refinement re-made the rows: no per-agent row ranges
    assert any(m.startswith("[refine]") for m in msgs)
    fused = client.download_fused(r.fused_version)
    assert len(fused) == r.n_gaussians > 0 and np.isfinite(fused.means).all()


def test_upload_idempotent_shuffled_and_resumable(server, client):
    g = rand_subset(4000, 0.0, 5)
    client.open_session("agent-1", "t", INTR)
    chunks = encode_subset(g, "agent-1", 7, chunk_gaussians=400)  # 10 chunks
    ch, stub, _ = stub_of(server)
    try:
        order = list(range(10))
        random.Random(0).shuffle(order)
        ack = upload_raw(stub, "agent-1", 7, chunks, order=order[:6] + order[:3], full=40000)  # duplicates
        assert ack.newly_stored == 6 and sorted(ack.stored) == sorted(order[:6]) and not ack.complete
        assert sorted(ack.missing) == sorted(order[6:])
        # interrupted stream: the server persists each chunk on receipt, the call is then cancelled
        gate = threading.Event()

        def gen():
            yield header("agent-1", 7, 10, 40000)
            yield fusion_pb2.UploadSubsetRequest(chunk=chunks[order[6]])
            gate.wait(10)

        fut = stub.UploadSubset.future(gen(), timeout=20)
        for _ in range(200):
            st = stub.GetUploadStatus(fusion_pb2.UploadStatusRequest(agent_id="agent-1", map_version=7), timeout=5)
            if len(st.stored) == 7:
                break
            time.sleep(0.02)
        fut.cancel()
        gate.set()
        assert len(st.stored) == 7 and order[6] in st.stored
        # resume with the client: only the 3 missing chunks travel
        res = client.upload_subset("agent-1", 7, g, full_map_gaussians=40000, chunk_gaussians=400)
        assert res.complete and res.chunks_sent == 3 and res.bytes_on_wire == sum(len(c) for c in chunks)
        # everything again, shuffled: no-op, still complete
        again = upload_raw(stub, "agent-1", 7, chunks, order=order[::-1])
        assert again.complete and again.newly_stored == 0 and list(again.stored) == list(range(10))
        stored, meta = assemble(server.store.chunk_data("agent-1", 7))
        assert stored.equals(assemble(chunks)[0]) and meta.wire_bytes == res.bytes_on_wire
        # the same index with different content is refused
        other = encode_subset(rand_subset(4000, 0.0, 6), "agent-1", 7, chunk_gaussians=400)
        code, msg = code_of(lambda: upload_raw(stub, "agent-1", 7, other, order=[2]))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "chunk index 2 " in msg
        # a newer complete version supersedes; older ones are refused afterwards
        assert client.upload_subset("agent-1", 8, g.take(slice(0, 100)), full_map_gaussians=40000).complete
        st7 = stub.GetUploadStatus(fusion_pb2.UploadStatusRequest(agent_id="agent-1", map_version=7), timeout=5)
        assert st7.superseded_by == 8 and st7.n_chunks == 0 and not st7.is_latest
        code, _ = code_of(lambda: upload_raw(stub, "agent-1", 7, chunks))
        assert code == grpc.StatusCode.FAILED_PRECONDITION
        assert client.stats()["agents"]["agent-1"]["gaussians_received"] == 100
    finally:
        ch.close()


def test_bad_input_precise_codes(server, client, caplog):
    caplog.set_level(logging.WARNING, logger="gausslite_services.fusion_server.server")
    ch, stub, _ = stub_of(server)
    try:
        g = rand_subset(500, 0.0, 7)
        # nothing fused / uploaded yet
        code, _ = code_of(lambda: list(stub.Fuse(fusion_pb2.FuseRequest(), timeout=10)))
        assert code == grpc.StatusCode.FAILED_PRECONDITION
        code, _ = code_of(lambda: list(stub.DownloadFused(fusion_pb2.DownloadFusedRequest(fused_version=42), timeout=10)))
        assert code == grpc.StatusCode.NOT_FOUND
        code, _ = code_of(lambda: client.download_fused(0))
        assert code == grpc.StatusCode.NOT_FOUND
        # agent ids
        for bad in ("", "bad id", "x" * 65, "ünïcode", "a/b"):
            code, _ = code_of(lambda: client.open_session(bad, "t", INTR))
            assert code == grpc.StatusCode.INVALID_ARGUMENT, bad
        code, _ = code_of(lambda: stub.OpenSession(fusion_pb2.OpenSessionRequest(agent_id="ok"), timeout=5))
        assert code == grpc.StatusCode.INVALID_ARGUMENT  # intrinsics missing
        # unknown agent (no session)
        chunks = encode_subset(g, "ghost", 1)
        code, msg = code_of(lambda: upload_raw(stub, "ghost", 1, chunks))
        assert code == grpc.StatusCode.NOT_FOUND and "OpenSession" in msg
        code, _ = code_of(lambda: client.upload_status("ghost", 1))
        assert code == grpc.StatusCode.NOT_FOUND
        code, _ = code_of(lambda: client.upload_keyframes("ghost", [frame(0)]))
        assert code == grpc.StatusCode.NOT_FOUND

        client.open_session("a1", "t", INTR)
        client.open_session("a2", "t", INTR)
        chunks = encode_subset(g, "a1", 1, chunk_gaussians=200)  # 3 chunks
        # stream without header / malformed bytes / corrupt CRC / wrong agent / wrong version / wrong count
        code, _ = code_of(lambda: stub.UploadSubset(iter([fusion_pb2.UploadSubsetRequest(chunk=chunks[0])]), timeout=5))
        assert code == grpc.StatusCode.INVALID_ARGUMENT
        code, msg = code_of(lambda: upload_raw(stub, "a1", 1, [b"definitely not a chunk"], n_chunks=3))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "BadMagic" in msg and "the 1st chunk of this call" in msg
        corrupt = bytearray(chunks[1])
        corrupt[200] ^= 0xFF
        code, msg = code_of(lambda: upload_raw(stub, "a1", 1, [chunks[0], bytes(corrupt)], n_chunks=3))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "ChecksumMismatch" in msg
        code, msg = code_of(lambda: upload_raw(stub, "a1", 1, [chunks[0][:50]], n_chunks=3))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "TruncatedChunk" in msg
        code, msg = code_of(lambda: upload_raw(stub, "a2", 1, chunks))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "'a1'" in msg and "chunk index 0 " in msg
        code, _ = code_of(lambda: upload_raw(stub, "a1", 2, chunks))
        assert code == grpc.StatusCode.INVALID_ARGUMENT
        code, msg = code_of(lambda: upload_raw(stub, "a1", 3, encode_subset(g, "a1", 3, chunk_gaussians=200),
                                               n_chunks=4))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "has 3 chunks, the upload header 4" in msg
        code, _ = code_of(lambda: upload_raw(stub, "a1", 1, chunks, full=100))  # subset > full map
        assert code == grpc.StatusCode.INVALID_ARGUMENT
        # the chunk stored before the corrupt one is kept (persisted on receipt), the rest completes
        st = client.upload_status("a1", 1)
        assert list(st.stored) == [0] and not st.complete
        assert client.upload_subset("a1", 1, g, full_map_gaussians=5000, chunk_gaussians=200).chunks_sent == 2
        # oversized message (server bound 1 MiB) → RESOURCE_EXHAUSTED
        big = encode_subset(rand_subset(30000, 0, 8), "a2", 1, chunk_gaussians=30000, quant=LOSSLESS)
        assert len(big[0]) > 1 << 20
        code, _ = code_of(lambda: upload_raw(stub, "a2", 1, big))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED

        # keyframes: NaN pose, non-rigid pose, undecodable JPEG, wrong size, bad depth scale
        def kf(**over):
            m = keyframe_to_proto("a1", frame(5))
            for k, v in over.items():
                if k == "c2w":
                    m.pose.CopyFrom(common_pb2.Pose(c2w=v))
                else:
                    setattr(m, k, v)
            return m

        nan_pose = list(np.eye(4).ravel())
        nan_pose[3] = float("nan")
        bad = {"NaN pose": kf(c2w=nan_pose), "scaled pose": kf(c2w=list((np.eye(4) * 2).ravel())),
               "short pose": kf(c2w=[1.0] * 12), "bad jpeg": kf(color=b"\xff\xd8\xff\xe0" + b"\x00" * 64),
               "gif": kf(color=b"GIF89a" + b"\x00" * 32),
               "wrong size": kf(color=encode_color_jpeg(np.zeros((H + 2, W, 3), np.uint8))),
               "rgb depth": kf(depth_png=encode_color_jpeg(np.zeros((H, W, 3), np.uint8))),
               "depth scale": kf(depth_scale=0.0)}
        for what, m in bad.items():
            code, _ = code_of(lambda: stub.UploadKeyframes(iter([m]), timeout=5))
            assert code == grpc.StatusCode.INVALID_ARGUMENT, what
        assert client.stats()["agents"]["a1"]["keyframes"] == 0
        # fuse option checks and refine without keyframes
        code, _ = code_of(lambda: list(stub.Fuse(fusion_pb2.FuseRequest(voxel_size=-1.0), timeout=10)))
        assert code == grpc.StatusCode.INVALID_ARGUMENT
        code, msg = code_of(lambda: list(stub.Fuse(fusion_pb2.FuseRequest(contest_radius=9), timeout=10)))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "contest_radius" in msg
        code, msg = code_of(lambda: client.fuse("vote", refine=True, refine_iters=5))
        assert code == grpc.StatusCode.FAILED_PRECONDITION and "keyframes" in msg
        with pytest.raises(ValueError):
            client.fuse("median")
        r = client.fuse("vote")
        code, _ = code_of(lambda: client.download_fused(r.fused_version + 1))
        assert code == grpc.StatusCode.NOT_FOUND
        code, _ = code_of(lambda: client.download_fused(0, method="concat"))  # only a vote exists
        assert code == grpc.StatusCode.NOT_FOUND
        assert len(client.download_fused(0, method="vote")) == r.n_gaussians
    finally:
        ch.close()
    rejected = [r.getMessage() for r in caplog.records if r.getMessage().startswith("rejected ")]
    assert any("ChecksumMismatch" in m for m in rejected) and any("NOT_FOUND" in m for m in rejected)


def test_keyframes_idempotent_and_bounded(tmp_path):
    srv = start(tmp_path, config=FusionConfig(max_keyframes_per_agent=3))
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=10) as c:
            c.open_session("kf", "t", INTR)
            assert c.upload_keyframes("kf", [frame(0), frame(1)]) == 2
            assert c.upload_keyframes("kf", [frame(1), frame(0)]) == 2  # duplicates: accepted, not re-stored
            assert c.stats()["agents"]["kf"]["keyframes"] == 2
            ch, stub, _ = stub_of(srv)
            ack = stub.UploadKeyframes(iter([keyframe_to_proto("kf", frame(i)) for i in (1, 2, 3, 4)]), timeout=10)
            ch.close()
            assert (ack.stored, ack.duplicates, ack.evicted, ack.buffered) == (3, 1, 2, 3)
            kept = [k.frame_id for k in srv.store.keyframes(["kf"])]
            assert kept == [2, 3, 4]  # oldest (0, 1) dropped
            stored = srv.store.keyframes(["kf"])[0]
            assert np.array_equal(stored.c2w, frame(2).c2w)
            png, scale = encode_depth_png(frame(2).depth)
            assert stored.depth == png and stored.depth_scale == scale
    finally:
        srv.stop(0.5)


def test_auth_token(tmp_path):
    srv = start(tmp_path, token="s3cret")
    try:
        target = f"127.0.0.1:{srv.port}"
        with FusionClient(target, timeout_s=5) as anon:
            anon.wait_ready(5)  # health is exempt from the token
            code, _ = code_of(lambda: anon.open_session("a", "t", INTR))
            assert code == grpc.StatusCode.UNAUTHENTICATED
        with FusionClient(target, token="wrong", timeout_s=5) as wrong:
            code, _ = code_of(lambda: wrong.stats())
            assert code == grpc.StatusCode.UNAUTHENTICATED
            code, _ = code_of(lambda: wrong.upload_subset("a", 1, rand_subset(10, 0, 1), full_map_gaussians=10))
            assert code == grpc.StatusCode.UNAUTHENTICATED
        with FusionClient(target, token="s3cret", timeout_s=5) as ok:
            ok.open_session("a", "t", INTR)
            assert ok.upload_subset("a", 1, rand_subset(10, 0, 1), full_map_gaussians=10).complete
            assert ok.stats()["agents"]["a"]["share_pct"] == pytest.approx(100.0)
    finally:
        srv.stop(0.5)


def test_eight_concurrent_agents(server):
    target = f"127.0.0.1:{server.port}"
    subsets = {f"bot{i}": rand_subset(1500, 0.25 * i, 100 + i) for i in range(8)}
    results, errors = {}, []
    barrier = threading.Barrier(8)

    def robot(agent):
        try:
            with FusionClient(target, timeout_s=30) as c:
                c.open_session(agent, f"task of {agent}", INTR)
                barrier.wait(10)
                results[agent] = c.upload_subset(agent, 1, subsets[agent], full_map_gaussians=15000,
                                                 chunk_gaussians=300, quant=QuantConfig(quat_bits=10))
                c.upload_keyframes(agent, [frame(int(agent[3:]))])
        except Exception as e:  # noqa: BLE001 - reported by the assertion below
            errors.append((agent, e))

    threads = [threading.Thread(target=robot, args=(a,)) for a in subsets]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors
    assert all(results[a].complete and results[a].n_chunks == 5 for a in subsets)
    with FusionClient(target, timeout_s=30) as c:
        r = c.fuse("vote")
        st = c.stats()
    assert set(r.kept) == set(subsets) and sum(r.received.values()) == 12000
    assert r.n_gaussians == sum(r.kept.values()) < 12000  # neighbouring cubes overlap
    assert all(st["agents"][a]["share_pct"] == pytest.approx(10.0) and st["agents"][a]["keyframes"] == 1
               for a in subsets)


@pytest.mark.skipif(not HAVE_REFINE, reason="gausslite.fusion.refine (lead's core library work) is not available")
def test_fuse_cancellation_stops_work(server, client):
    client.open_session("c1", "t", INTR)
    g = rand_subset(400, 0.0, 9)
    g.means[:, 2] = 1.5
    g.means[:, :2] -= 0.5
    client.upload_subset("c1", 1, g, full_map_gaussians=400)
    client.upload_keyframes("c1", [frame(0)])
    ch, stub, _ = stub_of(server)
    try:
        # refine_map reports progress every iters/20 iterations: cancellation is noticed after 20
        call = stub.Fuse(fusion_pb2.FuseRequest(refine=True, refine_iters=400), timeout=60)
        for msg in call:
            if msg.stage == "refine":
                break
        call.cancel()
        # the worker notices at its next progress report and releases the fuse lock
        assert server.servicer._fuse_lock.acquire(timeout=30)
        server.servicer._fuse_lock.release()
        assert client.stats()["fused"] == []  # nothing was stored
        assert client.fuse("concat").n_gaussians == 400  # the server is still usable
    finally:
        ch.close()


def test_intrinsics_and_session_reopen(server, client):
    client.open_session("re", "first", INTR)
    client.upload_subset("re", 2, rand_subset(50, 0, 1), full_map_gaussians=100)
    ch, stub, _ = stub_of(server)
    try:
        info = stub.OpenSession(fusion_pb2.OpenSessionRequest(agent_id="re", task_text="second",
                                                              intrinsics=intrinsics_to_proto(INTR)), timeout=5)
        assert not info.created and info.has_complete_subset and info.latest_map_version == 2
        assert info.max_message_bytes == 1 << 20
        huge = common_pb2.Intrinsics(fx=30, fy=30, cx=1, cy=1, width=10**6, height=H)  # above the side cap
        for bad in (common_pb2.Intrinsics(fx=-1, fy=30, cx=1, cy=1, width=W, height=H), huge):
            code, detail = code_of(lambda: stub.OpenSession(
                fusion_pb2.OpenSessionRequest(agent_id="re", intrinsics=bad), timeout=5))
            assert code == grpc.StatusCode.INVALID_ARGUMENT and "intrinsics" in detail, detail
    finally:
        ch.close()
    assert client.stats()["agents"]["re"]["task_text"] == "second"


def test_client_fails_fast_and_a_retry_loop_of_the_caller_gets_through(tmp_path):
    """No server: a call fails with UNAVAILABLE (one attempt, no waiting for a deadline); the server comes up while the
    caller's own loop backs off, and the next attempt succeeds on the same client."""
    import socket

    with socket.socket() as s:  # a free loopback port with nothing listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    box = {}
    starter = threading.Timer(0.4, lambda: box.setdefault("srv", start(tmp_path, port=port)))
    with FusionClient(f"127.0.0.1:{port}", timeout_s=10) as c:
        t0 = time.monotonic()
        code, _ = code_of(c.stats)
        assert code == grpc.StatusCode.UNAVAILABLE and time.monotonic() - t0 < 10  # not the deadline: refused
        with pytest.raises(TimeoutError):
            c.wait_ready(0.3)
        starter.start()
        try:
            deadline = time.monotonic() + 30
            while True:
                try:
                    c.open_session("late", "t", INTR)
                    break
                except grpc.RpcError as e:
                    assert e.code() == grpc.StatusCode.UNAVAILABLE and time.monotonic() < deadline
                    time.sleep(0.1)
            assert c.upload_subset("late", 1, rand_subset(100, 0, 1), full_map_gaussians=100).complete
        finally:
            starter.join()
            box["srv"].stop(0.5)


def test_keyframe_roi_is_validated_and_stored(server, client):
    """Keyframes may carry the agent's task ROI (8-bit PNG); a wrong size or format is INVALID_ARGUMENT."""
    import cv2

    from gausslite_services.fusion_server.client import keyframe_to_proto

    _, stub, _ = stub_of(server)
    client.open_session("roi-agent", "find the cup", INTR)
    f = frame(0)
    roi = np.zeros(np.shape(f.depth), bool)
    roi[2:10, 3:12] = True
    assert client.upload_keyframes("roi-agent", [f], rois=[roi]) == 1
    stored = [k for k in server.store.keyframes(["roi-agent"])]
    dec = cv2.imdecode(np.frombuffer(stored[0].roi, np.uint8), cv2.IMREAD_UNCHANGED) > 0
    assert np.array_equal(dec, roi)
    with pytest.raises(ValueError, match="roi"):
        keyframe_to_proto("roi-agent", f, roi=roi[:-1])
    bad_size = keyframe_to_proto("roi-agent", frame(1))
    bad_size.roi_png = cv2.imencode(".png", np.zeros((3, 3), np.uint8))[1].tobytes()
    not_png = keyframe_to_proto("roi-agent", frame(2))
    not_png.roi_png = b"\xff\xd8\xff\xe0nope"
    rgb_roi = keyframe_to_proto("roi-agent", frame(3))
    rgb_roi.roi_png = cv2.imencode(".png", np.zeros((*np.shape(f.depth), 3), np.uint8))[1].tobytes()
    for what, m in {"size": bad_size, "format": not_png, "channels": rgb_roi}.items():
        code, msg = code_of(lambda m=m: stub.UploadKeyframes(iter([m]), timeout=5))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "roi_png" in msg, what
    assert server.store.keyframe_count("roi-agent") == 1


def _png_bomb(width: int, height: int, color_type: int = 2, bits: int = 8) -> bytes:
    """A PNG whose header declares ``width`` x ``height`` (its data is a stub): what a decompression bomb shows
    before it is decoded."""
    import struct
    import zlib

    ihdr = struct.pack(">IIBBBBB", width, height, bits, color_type, 0, 0, 0)
    chunk = lambda t, d: struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d))  # noqa: E731
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


def test_a_refinement_decodes_only_the_keyframes_stored_since_the_last_one(tmp_path, monkeypatch):
    """Fuse's refinements run again and again over the same stored views: each keyframe is decoded once, the decoded
    views are the same objects the next time, and evicted keyframes leave the cache (the team map's refinement
    process keeps its own: tests/services/test_refine_worker.py)."""
    from gausslite.wire import images

    srv = start(tmp_path, config=FusionConfig(max_keyframes_per_agent=3, team_map={"enabled": False}))
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            c.open_session("a", "find the cup", INTR)
            decoded = []
            real = images.decode_color
            monkeypatch.setattr(images, "decode_color",  # the refinement's decoding (uploads check theirs too)
                                lambda *a: (a[1].startswith("stored") and decoded.append(a[1])) or real(*a))
            assert c.upload_keyframes("a", [frame(i) for i in range(2)]) == 2
            first = srv.servicer._refine_keyframes()
            assert [k.frame_id for k in first["a"]] == [0, 1] and len(decoded) == 2
            again = srv.servicer._refine_keyframes()
            assert len(decoded) == 2 and all(x is y for x, y in zip(first["a"], again["a"]))
            assert c.upload_keyframes("a", [frame(i) for i in range(2, 4)], color_format="png") == 2  # 0 is evicted
            later = srv.servicer._refine_keyframes()
            assert [k.frame_id for k in later["a"]] == [1, 2, 3] and len(decoded) == 4
            assert later["a"][0] is first["a"][1]
            assert sorted(k[1] for k in srv.servicer._decoded) == [1, 2, 3]
            np.testing.assert_allclose(later["a"][2].rgb.numpy(), frame(3).rgb / 255.0, atol=1e-6)  # lossless PNG
    finally:
        srv.stop(0.5)


def test_keyframe_images_are_checked_against_the_intrinsics_before_they_are_decoded(server, client, monkeypatch):
    """A small file can declare a huge image: a 1.17 MB PNG of 20000x20000 pixels decodes to 1.2 GB. The server reads
    the sizes from the headers and rejects a mismatch without decoding anything (INVALID_ARGUMENT)."""
    import cv2

    from gausslite.wire import images

    _, stub, _ = stub_of(server)
    client.open_session("bomb-agent", "find the cup", INTR)
    decoded = []
    real = cv2.imdecode
    monkeypatch.setattr(images.cv2, "imdecode", lambda *a: decoded.append(1) or real(*a))
    colour = keyframe_to_proto("bomb-agent", frame(0))
    colour.color = _png_bomb(20000, 20000)
    depth = keyframe_to_proto("bomb-agent", frame(1))
    depth.depth_png = _png_bomb(20000, 20000, color_type=0, bits=16)
    roi = keyframe_to_proto("bomb-agent", frame(2))
    roi.roi_png = _png_bomb(20000, 20000, color_type=0)
    headless = keyframe_to_proto("bomb-agent", frame(3))
    headless.color = b"\xff\xd8\xff\xd9"  # a JPEG without a frame header
    for what, m in {"colour": colour, "depth": depth, "roi_png": roi, "headless": headless}.items():
        n = len(decoded)
        code, msg = code_of(lambda m=m: stub.UploadKeyframes(iter([m]), timeout=5))
        assert code == grpc.StatusCode.INVALID_ARGUMENT, what
        assert ("20000x20000" in msg) or ("header" in msg), (what, msg)
        # the oversized image is never decoded: only the valid images before it (colour, then depth, then roi)
        assert len(decoded) - n == {"colour": 0, "depth": 1, "roi_png": 2, "headless": 0}[what], what
    assert server.store.keyframe_count("bomb-agent") == 0
    assert client.upload_keyframes("bomb-agent", [frame(4)]) == 1  # a valid one still goes in
    # decoded pixels have a cap: a keyframe whose intrinsics declare more is refused before decoding
    n = len(decoded)
    big = keyframe_to_proto("bomb-agent", frame(5))
    big.intrinsics.CopyFrom(intrinsics_to_proto(Intrinsics(3000.0, 3000.0, 2000.0, 2000.0, 4000, 4000)))
    code, msg = code_of(lambda: stub.UploadKeyframes(iter([big]), timeout=5))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "pixels" in msg and len(decoded) == n


def _splats(means, scale, kappa=5):
    n = len(means)
    return GaussianArrays(means=np.asarray(means, np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          log_scales=np.full((n, 3), np.log(scale), np.float32),
                          opacity_logits=np.full(n, 3.0, np.float32), colors=np.full((n, 3), 0.5, np.float32),
                          kappa=np.full(n, kappa, np.int64), active=np.ones(n, bool))


def test_fuse_for_agent_keeps_its_whole_subset_and_drops_what_lies_over_its_roi(server, client):
    """The team map as one robot uses it (docs/sharing.md): its subset whole, the others' voted rows except those
    that draw its ROI in its uploaded ROI keyframes; and the errors of a bad ``for_agent``."""
    xs = np.linspace(-0.5, -0.05, 6)
    a = _splats([[x, y, 1.5] for x in xs for y in (-0.2, 0.0, 0.2)], 0.04)
    # robot_b: its own region on the right, and one large splat in front of robot_a's region
    b = GaussianArrays.concat([_splats([[x, 0.0, 1.5] for x in (0.3, 0.4, 0.5)], 0.04),
                               _splats([[-0.3, 0.0, 1.2]], 0.3, kappa=50)])
    client.open_session("robot_a", "find the cup", INTR)
    client.open_session("robot_b", "find the desk", INTR)
    client.open_session("robot_c", "idle", INTR)
    client.upload_subset("robot_a", 1, a, full_map_gaussians=1000, quant=LOSSLESS)
    client.upload_subset("robot_b", 1, b, full_map_gaussians=1000, quant=LOSSLESS)
    roi_a = np.zeros((H, W), bool)
    roi_a[:, : W // 2] = True
    roi_b = ~roi_a
    assert client.upload_keyframes("robot_a", [frame(i) for i in range(2)], rois=[roi_a, roi_a]) == 2
    assert client.upload_keyframes("robot_b", [frame(5)], rois=[roi_b]) == 1
    team = client.fuse("vote", voxel_size=0.1)
    assert team.for_agent == "" and team.kept == {"robot_a": len(a), "robot_b": len(b)}  # nothing contested
    ra = client.fuse("vote", voxel_size=0.1, for_agent="robot_a")
    assert ra.for_agent == "robot_a" and ra.kept == {"robot_a": len(a), "robot_b": 3}
    got = client.download_fused(ra.fused_version)
    assert len(got) == len(a) + 3 and got.take(np.arange(len(a))).equals(a)
    assert not np.isclose(got.means[:, 2], 1.2).any()  # the large splat over robot_a's ROI is gone
    assert ra.first_row == {"robot_a": 0, "robot_b": len(a)}  # the robot's own rows first
    rb = client.fuse("vote", voxel_size=0.1, for_agent="robot_b")
    assert rb.kept["robot_b"] == len(b)
    assert rb.first_row == {"robot_b": 0, "robot_a": len(b)}
    assert client.download_fused(rb.fused_version).take(np.arange(len(b))).equals(b)
    # errors: unknown agent, an agent without a subset, concat, a malformed id
    code, _ = code_of(lambda: client.fuse("vote", for_agent="robot_z"))
    assert code == grpc.StatusCode.NOT_FOUND
    code, msg = code_of(lambda: client.fuse("vote", for_agent="robot_c"))
    assert code == grpc.StatusCode.FAILED_PRECONDITION and "robot_c" in msg
    code, msg = code_of(lambda: client.fuse("concat", for_agent="robot_a"))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "VOTE" in msg
    code, _ = code_of(lambda: client.fuse("vote", for_agent="bad id!"))
    assert code == grpc.StatusCode.INVALID_ARGUMENT


def test_absurd_gaussians_are_refused_and_the_bounds_are_configurable(tmp_path):
    """Finite but absurd values (a 1 km splat, a mean 100 km away, an opacity logit of 1e6) would spoil every fused
    map: the server refuses them with INVALID_ARGUMENT and keeps nothing of the upload."""
    from gausslite.config import FusionSettings

    srv = start(tmp_path)
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            c.wait_ready(10)
            c.open_session("robot_p", "find the cup", INTR)
            good = _splats([[0.0, 0.0, 1.5], [0.1, 0.0, 1.5]], 0.05)
            for what, bad in {"scale": _splats([[0.0, 0.0, 1.5]], 1000.0),
                              "mean": _splats([[1.0e5, 0.0, 1.5]], 0.05)}.items():
                code, msg = code_of(lambda bad=bad: c.upload_subset("robot_p", 1, GaussianArrays.concat([good, bad]),
                                                                   full_map_gaussians=10, quant=LOSSLESS))
                assert code == grpc.StatusCode.INVALID_ARGUMENT and what in msg and "bound" in msg, (what, msg)
            logit = _splats([[0.0, 0.0, 1.5]], 0.05)
            logit.opacity_logits[:] = 1e6
            code, msg = code_of(lambda: c.upload_subset("robot_p", 1, logit, full_map_gaussians=10, quant=LOSSLESS))
            assert code == grpc.StatusCode.INVALID_ARGUMENT and "opacity" in msg
            negative = _splats([[0.0, 0.0, 1.5]], 0.05)  # κ < 0 would fail every later Fuse of the team
            negative.kappa[:] = -3
            code, msg = code_of(lambda: c.upload_subset("robot_p", 1, GaussianArrays.concat([good, negative]),
                                                        full_map_gaussians=10, quant=LOSSLESS))
            assert code == grpc.StatusCode.INVALID_ARGUMENT and "kappa -3 is negative" in msg, msg
            assert c.stats()["agents"]["robot_p"]["latest_map_version"] in (0, None)
            assert c.upload_subset("robot_p", 1, good, full_map_gaussians=10, quant=LOSSLESS).complete
    finally:
        srv.stop(0.5)
    srv = start(tmp_path, name="wide", config=FusionSettings(max_scale_m=2000.0))
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            c.wait_ready(10)
            c.open_session("robot_p", "find the cup", INTR)
            assert c.upload_subset("robot_p", 1, _splats([[0.0, 0.0, 1.5]], 1000.0), full_map_gaussians=10,
                                   quant=LOSSLESS).complete
    finally:
        srv.stop(0.5)


def test_fused_maps_are_kept_up_to_the_retention_bound(tmp_path):
    """Every Fuse stores a map; a read-only caller fusing in a loop must not fill the disk or grow GetStats without
    bound: only the newest ``fused_keep_per_method`` maps of each method are kept."""
    from gausslite.config import FusionSettings

    srv = start(tmp_path, config=FusionSettings(fused_keep_per_method=3))
    try:
        with FusionClient(f"127.0.0.1:{srv.port}", timeout_s=20) as c:
            c.wait_ready(10)
            c.open_session("robot_r", "find the cup", INTR)
            c.upload_subset("robot_r", 1, rand_subset(200, 0.0, 3), full_map_gaussians=1000)
            versions = [c.fuse("concat").fused_version for _ in range(8)]
            vote = c.fuse("vote").fused_version
            st = c.stats()
            held = sorted(f["fused_version"] for f in st["fused"])
            assert held == versions[-3:] + [vote]
            code, _ = code_of(lambda: c.download_fused(versions[0]))
            assert code == grpc.StatusCode.NOT_FOUND
            assert len(c.download_fused(versions[-1])) == 200
            assert len(c.download_fused(0, method="concat")) == 200
        rows = srv.store._conn().execute("SELECT COUNT(DISTINCT version) FROM fused_chunks").fetchone()[0]
        assert rows == 4
    finally:
        srv.stop(0.5)


def test_stalled_streams_cannot_queue_calls_without_bound(tmp_path):
    """Two clients that open uploads and stall hold the server's two call slots (4 handler threads: 2 upload slots):
    a third call is RESOURCE_EXHAUSTED at once (not queued behind them), and the server answers again when they go."""
    srv = start(tmp_path, max_workers=4, max_concurrent_rpcs=2)
    release = threading.Event()
    try:
        _, stub, _ = stub_of(srv)
        stub.OpenSession(fusion_pb2.OpenSessionRequest(agent_id="robot_s", task_text="find the cup",
                                                       intrinsics=intrinsics_to_proto(INTR)), timeout=5)

        def stalled():
            yield header("robot_s", 1, 1)
            release.wait(30)

        calls = [stub.UploadSubset.future(stalled(), timeout=30) for _ in range(2)]
        time.sleep(1.0)
        code, _ = code_of(lambda: stub.GetStats(fusion_pb2.StatsRequest(), timeout=5))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED
        release.set()
        for f in calls:
            f.exception(timeout=30)  # both end once their clients go on
            assert f.done()
        stub.GetStats(fusion_pb2.StatsRequest(), timeout=5)
    finally:
        release.set()
        srv.stop(0.5)
