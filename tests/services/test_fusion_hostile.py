"""Clients that try to hold or exhaust the fusion server (docs/security.md, "Hostile bytes"): upload streams that
stall get DEADLINE_EXCEEDED after ``fusion.stream_idle_s`` and free their handler thread, upload streams are
bounded server-wide and per caller (RESOURCE_EXHAUSTED beyond), a valid robot keeps being answered meanwhile, and a
decompression bomb sent to a real server process neither grows its memory nor takes it down."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import grpc
import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.config import FusionSettings
from gausslite.wire.codec import GaussianArrays, encode_subset
from gausslite_rpc import common_pb2, fusion_pb2, fusion_pb2_grpc
from gausslite_services.common import auth
from gausslite_services.common.convert import intrinsics_to_proto
from gausslite_services.common.server import ServerOptions
from gausslite_services.fusion_server.client import FusionClient
from gausslite_services.fusion_server.server import serve
from tests._waits import wait_for_start

REPO = Path(__file__).resolve().parents[2]
H, W = 24, 32
INTR = Intrinsics(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, W, H)


def rand_subset(n: int, seed: int) -> GaussianArrays:
    r = np.random.default_rng(seed)
    return GaussianArrays(means=r.uniform(0, 1, (n, 3)), quats=r.normal(size=(n, 4)),
                          log_scales=r.uniform(-5, -3, (n, 3)), opacity_logits=r.normal(size=n),
                          colors=r.uniform(0, 1, (n, 3)), kappa=r.integers(0, 100, n), active=r.random(n) < 0.5)


class Stalled:
    """A client stream that sends ``messages`` and then nothing until :meth:`release` (the call runs in a thread);
    ``.error`` is the call's RpcError, ``.ended_s`` the seconds from the start to its end."""

    def __init__(self, method, messages, metadata=None, timeout=120.0):
        self._go = threading.Event()
        self.error, self.result, self.ended_s = None, None, None
        self._t0 = time.monotonic()

        def requests():
            yield from messages
            self._go.wait()

        def call():
            try:
                self.result = method(requests(), timeout=timeout, metadata=metadata)
            except grpc.RpcError as e:
                self.error = e
            self.ended_s = time.monotonic() - self._t0

        self.thread = threading.Thread(target=call, daemon=True)
        self.thread.start()

    def release(self) -> None:
        self._go.set()

    def wait(self, timeout: float) -> bool:
        self.thread.join(timeout)
        return not self.thread.is_alive()


def _readers() -> list:
    return [t for t in threading.enumerate() if t.name.startswith("gausslite-Upload") and t.is_alive()]


def _header(agent, version, n_chunks):
    return fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(agent_id=agent, map_version=version,
                                                                        n_chunks=n_chunks, full_map_gaussians=400))


def test_a_stalled_upload_ends_after_the_idle_deadline_and_keeps_nothing_visible(tmp_path):
    cfg = FusionSettings(stream_idle_s=1.0)
    srv = serve(ServerOptions(port=0, max_workers=8, grace_s=0.5), cfg, data_dir=str(tmp_path / "data"))
    ch = grpc.insecure_channel(srv.address)
    st = fusion_pb2_grpc.FusionStub(ch)
    stalled = []
    try:
        with FusionClient(srv.address, timeout_s=10) as c:
            for a in ("slow", "good"):
                c.open_session(a, "find the chair", INTR)
            chunks = encode_subset(rand_subset(400, 1), "slow", 1, max_chunk_bytes=8 * 1024)
            assert len(chunks) >= 2
            # header and one chunk, then nothing: a subset upload; and a keyframe stream that sends nothing at all
            stalled.append(Stalled(st.UploadSubset, [_header("slow", 1, len(chunks)),
                                                     fusion_pb2.UploadSubsetRequest(chunk=chunks[0])]))
            stalled.append(Stalled(st.UploadKeyframes, []))
            time.sleep(0.3)
            # meanwhile a valid robot uploads and is answered, and reads work (2 of the 8 threads are held)
            t0 = time.monotonic()
            res = c.upload_subset("good", 1, rand_subset(300, 2), full_map_gaussians=1000)
            assert res.complete and c.stats()["agents"]["good"]["has_complete_subset"]
            assert time.monotonic() - t0 < 0.9  # answered while both stalled streams were still open
            for s in stalled:
                assert s.wait(10), "the stalled stream was not ended"
                assert s.error.code() == grpc.StatusCode.DEADLINE_EXCEEDED, s.error
                assert "fusion.stream_idle_s" in s.error.details()
                assert 0.9 < s.ended_s < 4.0
            assert srv.servicer.uploads.deadline_exceeded == 2 and srv.servicer.uploads.active == 0
            # the chunk that arrived stays a resumable, incomplete upload: not a subset Fuse would see
            status = c.upload_status("slow", 1)
            assert not status.complete and len(status.missing) == len(chunks) - 1
            assert not c.stats()["agents"]["slow"]["has_complete_subset"]
            deadline = time.monotonic() + 5
            while _readers() and time.monotonic() < deadline:
                time.sleep(0.05)
            assert _readers() == []  # the reader threads ended with their calls
            # the robot resumes: only the missing chunks are sent, and the subset completes
            res = c.upload_chunks("slow", 1, chunks, n_gaussians=400, full_map_gaussians=400)
            assert res.complete and res.chunks_sent == len(chunks) - 1
    finally:
        for s in stalled:
            s.release()
        ch.close()
        srv.stop(0)


def test_upload_streams_are_bounded_server_wide_and_per_caller(tmp_path):
    path = tmp_path / "tokens.yaml"
    tok = {a: auth.issue_token(path, a) for a in ("robot-a", "robot-b", "robot-c", "viewer")}
    cfg = FusionSettings(stream_idle_s=30.0, max_upload_streams=16, max_upload_streams_per_caller=2,
                         stream_evict_idle_s=60.0)  # no eviction for waiting long (test below)
    # 6 handler threads: upload streams are capped at 3, leaving 3 for everything else
    srv = serve(ServerOptions(port=0, max_workers=6, grace_s=0.5, agent_tokens_file=str(path)), cfg,
                data_dir=str(tmp_path / "data"))
    assert srv.servicer.uploads.max_streams == 3
    ch = grpc.insecure_channel(srv.address)
    st = fusion_pb2_grpc.FusionStub(ch)
    md = {a: (("authorization", f"Bearer {t}"),) for a, t in tok.items()}
    held = []

    def wait_active(n):
        deadline = time.monotonic() + 5
        while srv.servicer.uploads.active != n and time.monotonic() < deadline:
            time.sleep(0.02)
        assert srv.servicer.uploads.active == n

    try:
        for _ in range(2):
            held.append(Stalled(st.UploadKeyframes, [], md["robot-a"]))
        wait_active(2)
        # robot-a's third stream: per caller
        with pytest.raises(grpc.RpcError) as e:
            st.UploadKeyframes(iter([]), timeout=5, metadata=md["robot-a"])
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "from this caller" in e.value.details()
        held.append(Stalled(st.UploadKeyframes, [], md["robot-b"]))  # the last server-wide slot
        wait_active(3)
        # robot-c holds none and robot-a two: one of robot-a's slots goes to robot-c (its fair share)
        held.append(Stalled(st.UploadKeyframes, [], md["robot-c"]))
        deadline = time.monotonic() + 5
        while not (held[0].wait(0.05) or held[1].wait(0.05)) and time.monotonic() < deadline:
            pass
        gone = [s for s in held[:2] if not s.thread.is_alive()]
        assert len(gone) == 1 and gone[0].error.code() == grpc.StatusCode.ABORTED
        wait_active(3)
        # robot-a, robot-b and robot-c hold one each: the viewer (may write nothing) gets none
        with pytest.raises(grpc.RpcError) as e:
            st.UploadKeyframes(iter([]), timeout=5, metadata=md["viewer"])
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "3 on this server" in e.value.details()
        # unary calls are still answered at once: the stalled streams hold only half the threads
        t0 = time.monotonic()
        for _ in range(20):
            st.GetStats(fusion_pb2.StatsRequest(), timeout=5, metadata=md["viewer"])
        assert time.monotonic() - t0 < 5.0
        # a slot freed (robot-b's client gave up) is free again
        held[2].release()
        held[2].wait(10)
        wait_active(2)
        with FusionClient(srv.address, token=tok["robot-b"], timeout_s=10) as c:
            c.open_session("robot-b", "find the chair", INTR)
            assert c.upload_subset("robot-b", 1, rand_subset(200, 3), full_map_gaussians=500).complete
    finally:
        for s in held:
            s.release()
        ch.close()
        srv.stop(0)


def test_a_new_upload_takes_the_slot_of_a_stalled_stream_when_all_are_taken(tmp_path):
    """Streams stalled by several identities fill every upload slot: a valid robot's upload evicts the one that has
    waited longest for its next message (longer than fusion.stream_evict_idle_s), which ends ABORTED; a stream that
    is still sending is never evicted, so with no stalled stream the new upload is RESOURCE_EXHAUSTED."""
    path = tmp_path / "tokens.yaml"
    tok = {a: auth.issue_token(path, a) for a in ("bad-1", "bad-2", "good")}
    cfg = FusionSettings(stream_idle_s=30.0, max_upload_streams_per_caller=1, stream_evict_idle_s=0.5)
    srv = serve(ServerOptions(port=0, max_workers=4, grace_s=0.5, agent_tokens_file=str(path)), cfg,
                data_dir=str(tmp_path / "data"))
    assert srv.servicer.uploads.max_streams == 2
    ch = grpc.insecure_channel(srv.address)
    st = fusion_pb2_grpc.FusionStub(ch)
    md = {a: (("authorization", f"Bearer {t}"),) for a, t in tok.items()}
    held = []
    try:
        held.append(Stalled(st.UploadKeyframes, [], md["bad-1"]))
        time.sleep(0.1)
        held.append(Stalled(st.UploadKeyframes, [], md["bad-2"]))
        deadline = time.monotonic() + 5
        while srv.servicer.uploads.active < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        # both slots taken by streams that waited less than 0.5 s: refused
        with pytest.raises(grpc.RpcError) as e:
            st.UploadKeyframes(iter([]), timeout=5, metadata=md["good"])
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "2 on this server" in e.value.details()
        time.sleep(0.6)
        with FusionClient(srv.address, token=tok["good"], timeout_s=10) as c:
            c.open_session("good", "find the chair", INTR)
            assert c.upload_subset("good", 1, rand_subset(300, 5), full_map_gaussians=500).complete
        assert held[0].wait(5) and not held[1].wait(0.5)  # the longest-waiting stream (bad-1) gave its slot
        assert held[0].error.code() == grpc.StatusCode.ABORTED and "slot" in held[0].error.details()
        assert srv.servicer.uploads.evicted >= 1
    finally:
        for s in held:
            s.release()
        ch.close()
        srv.stop(0)


def test_upload_slots_go_to_a_caller_below_its_fair_share():
    """With every slot taken, a caller holding none takes a waiting stream's slot from a caller holding two (even
    one that waited only briefly); between callers holding one slot each, only a stream waiting longer than
    evict_idle_s gives way."""
    from gausslite_services.fusion_server.guards import Reject, UploadStreams

    class Ctx:
        def is_active(self):
            return True

    ups = UploadStreams(max_streams=2, per_caller=2, idle_s=30.0, evict_idle_s=60.0)
    opened = [ups.open(iter(()), Ctx(), "UploadKeyframes", "agent a") for _ in range(2)]
    for cm in opened:
        cm.__enter__()
    opened.append(ups.open(iter(()), Ctx(), "UploadKeyframes", "agent b"))
    opened[-1].__enter__()  # a holds two: one of its slots goes to b
    assert ups.evicted == 1 and ups.active == 2
    with pytest.raises(Reject) as e:  # a and b hold one each: c waits its turn
        ups.open(iter(()), Ctx(), "UploadKeyframes", "agent c").__enter__()
    assert e.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    for cm in opened:
        cm.__exit__(None, None, None)
    assert ups.active == 0


def test_get_stats_pages_its_agents(tmp_path):
    """GetStats returns at most page_size agents (100 by default, 1000 at most) in agent-id order with a token for the
    next page; the fused maps come with the first page; the client's stats() joins every page."""
    srv = serve(ServerOptions(port=0, max_workers=8, grace_s=0.5), data_dir=str(tmp_path / "data"))
    ch = grpc.insecure_channel(srv.address)
    st = fusion_pb2_grpc.FusionStub(ch)
    try:
        with FusionClient(srv.address, timeout_s=10) as c:
            ids = [f"robot-{i:03d}" for i in range(103)]
            for a in ids:
                c.open_session(a, "find the chair", INTR)
            c.upload_subset("robot-000", 1, rand_subset(100, 4), full_map_gaussians=100)
            c.fuse("concat")
            first = st.GetStats(fusion_pb2.StatsRequest(), timeout=10)
            assert [a.agent_id for a in first.agents] == ids[:100] and first.next_page_token == "robot-099"
            assert len(first.fused) == 1 and first.latest_fused_version == first.fused[0].fused_version
            rest = st.GetStats(fusion_pb2.StatsRequest(page_token=first.next_page_token), timeout=10)
            assert [a.agent_id for a in rest.agents] == ids[100:] and rest.next_page_token == ""
            assert len(rest.fused) == 0 and rest.latest_fused_version == first.latest_fused_version
            seen, token = [], ""
            while True:
                page = st.GetStats(fusion_pb2.StatsRequest(page_size=40, page_token=token), timeout=10)
                assert len(page.agents) <= 40
                seen += [a.agent_id for a in page.agents]
                token = page.next_page_token
                if not token:
                    break
            assert seen == ids
            stats = c.stats()
            assert sorted(stats["agents"]) == ids and len(stats["fused"]) == 1
            assert stats["agents"]["robot-000"]["has_complete_subset"]
            for req in (fusion_pb2.StatsRequest(page_size=1001), fusion_pb2.StatsRequest(page_token="../x")):
                with pytest.raises(grpc.RpcError) as e:
                    st.GetStats(req, timeout=10)
                assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    finally:
        ch.close()
        srv.stop(0)


# ------------------------------------------------------------------------------------------ decompression bomb
BOMB_SIDE = 20000


def black_png(side: int, level: int = 9) -> bytes:
    """A valid all-black RGB PNG of ``side`` × ``side`` pixels, written row block by row block (the pixels are never
    held): 20000 × 20000 is 1.2 GB decoded, about 1.17 MB encoded."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    co, rows, parts = zlib.compressobj(level), 100, []
    block = (b"\0" * (1 + 3 * side)) * rows  # filter byte 0 + RGB zeros, per row
    for start in range(0, side, rows):
        parts.append(co.compress(block if start + rows <= side else block[:(side - start) * (1 + 3 * side)]))
    parts.append(co.flush())
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", side, side, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", b"".join(parts)) + chunk(b"IEND", b""))


@pytest.fixture(scope="session")
def bomb_png() -> bytes:
    """The 20000 × 20000 black PNG, built once and cached in the temp dir (about 4 s to compress)."""
    import tempfile

    path = Path(tempfile.gettempdir()) / f"gausslite_black_{BOMB_SIDE}.png"
    if not path.exists() or path.stat().st_size < 1_000_000:
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_bytes(black_png(BOMB_SIDE))
        os.replace(tmp, path)
    return path.read_bytes()


def test_black_png_builder_makes_valid_pngs():
    import cv2

    img = cv2.imdecode(np.frombuffer(black_png(123, level=1), np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (123, 123, 3) and not img.any()


def _vm_kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def test_a_decompression_bomb_leaves_a_server_process_small_and_serving(tmp_path, bomb_png):
    """A valid all-black 20000 × 20000 PNG (1.2 GB of pixels in 1.2 MB) as a keyframe of a 32 × 24 session, sent to a
    real fusion server process: INVALID_ARGUMENT, its peak RSS (VmHWM) grows by less than 100 MB, health SERVING, and
    a valid keyframe is stored afterwards."""
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    from gausslite.datasets.base import Frame
    from gausslite_services.fusion_server.client import keyframe_to_proto

    assert 1_000_000 < len(bomb_png) < 1_400_000
    port_file = tmp_path / "port"
    env = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"}
    log = open(tmp_path / "fusion.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "gausslite_services.fusion_server", "--port", "0", "--port-file",
                             str(port_file), "--data-dir", str(tmp_path / "data")], cwd=str(REPO), env=env,
                            stdout=log, stderr=subprocess.STDOUT)
    try:
        wait_for_start(proc, lambda: port_file.exists() and port_file.read_text().strip(),
                       "the fusion server's port file", tmp_path / "fusion.log")
        address = f"127.0.0.1:{int(port_file.read_text())}"
        r = np.random.default_rng(0)
        good = Frame(1, 0.0, r.integers(0, 255, (H, W, 3), dtype=np.uint8), np.full((H, W), 1.5, np.float32),
                     np.eye(4), INTR)
        with FusionClient(address, timeout_s=30) as c:
            c.wait_ready(30)
            c.open_session("robot-1", "find the chair", INTR)
            c.upload_keyframes("robot-1", [good])  # warm: the decoding path has run once
            before = _vm_kb(proc.pid, "VmHWM")
            bomb = keyframe_to_proto("robot-1", Frame(2, 0.1, good.rgb, good.depth, np.eye(4), INTR))
            bomb.color = bomb_png
            st = fusion_pb2_grpc.FusionStub(c._channel)
            for _ in range(3):
                with pytest.raises(grpc.RpcError) as e:
                    st.UploadKeyframes(iter([bomb]), timeout=30)
                assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, e.value.details()
                assert "20000" in e.value.details()
            grown_mb = (_vm_kb(proc.pid, "VmHWM") - before) / 1024.0
            assert grown_mb < 100.0, f"peak RSS grew by {grown_mb:.0f} MB"
            h = health_pb2_grpc.HealthStub(c._channel).Check(health_pb2.HealthCheckRequest(service=""), timeout=5)
            assert h.status == health_pb2.HealthCheckResponse.SERVING
            assert c.upload_keyframes("robot-1", [Frame(3, 0.2, good.rgb, good.depth, np.eye(4), INTR)]) == 1
            assert proc.poll() is None
    finally:
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
