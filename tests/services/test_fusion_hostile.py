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
from services.common import auth
from services.common.convert import intrinsics_to_proto
from services.common.server import ServerOptions
from services.fusion_server.client import FusionClient
from services.fusion_server.server import serve

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
        with FusionClient(srv.address, timeout_s=10, max_retries=0) as c:
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
    cfg = FusionSettings(stream_idle_s=30.0, max_upload_streams=16, max_upload_streams_per_caller=2)
    # 6 handler threads: upload streams are capped at 3, leaving 3 for everything else
    srv = serve(ServerOptions(port=0, max_workers=6, grace_s=0.5, agent_tokens_file=str(path)), cfg,
                data_dir=str(tmp_path / "data"))
    assert srv.servicer.uploads.max_streams == 3
    ch = grpc.insecure_channel(srv.address)
    st = fusion_pb2_grpc.FusionStub(ch)
    md = {a: (("authorization", f"Bearer {t}"),) for a, t in tok.items()}
    held = []
    try:
        for _ in range(2):
            held.append(Stalled(st.UploadKeyframes, [], md["robot-a"]))
        deadline = time.monotonic() + 5
        while srv.servicer.uploads.active < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        # robot-a's third stream: per caller
        with pytest.raises(grpc.RpcError) as e:
            st.UploadKeyframes(iter([]), timeout=5, metadata=md["robot-a"])
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "from this caller" in e.value.details()
        # robot-b takes the last server-wide slot
        held.append(Stalled(st.UploadKeyframes, [], md["robot-b"]))
        while srv.servicer.uploads.active < 3 and time.monotonic() < deadline:
            time.sleep(0.02)
        with pytest.raises(grpc.RpcError) as e:
            st.UploadKeyframes(iter([]), timeout=5, metadata=md["robot-c"])
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "3 on this server" in e.value.details()
        # unary calls are still answered at once: the stalled streams hold only half the threads
        t0 = time.monotonic()
        for _ in range(20):
            st.GetStats(fusion_pb2.StatsRequest(), timeout=5, metadata=md["robot-c"])
        assert time.monotonic() - t0 < 5.0
        # a slot freed (the client gave up) is free again for another robot
        for s in held[:1]:
            s.release()
        held[0].wait(10)
        while srv.servicer.uploads.active > 2 and time.monotonic() < deadline + 5:
            time.sleep(0.02)
        with FusionClient(srv.address, token=tok["robot-c"], timeout_s=10, max_retries=0) as c:
            c.open_session("robot-c", "find the chair", INTR)
            assert c.upload_subset("robot-c", 1, rand_subset(200, 3), full_map_gaussians=500).complete
    finally:
        for s in held:
            s.release()
        ch.close()
        srv.stop(0)
