"""Durability: a real fusion-server subprocess is SIGKILLed mid-upload (after some chunks
were acknowledged) and restarted on the same data dir; nothing acknowledged is lost, the client
resumes via GetUploadStatus and the assembled subset equals the original."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import grpc
import numpy as np
import pytest

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.wire.codec import LOSSLESS, GaussianArrays, assemble, encode_subset
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.fusion_server.client import FusionClient
from tests._waits import wait_for_start

REPO = Path(__file__).resolve().parents[2]
INTR = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)


def _subset(n: int, seed: int) -> GaussianArrays:
    r = np.random.default_rng(seed)
    return GaussianArrays(means=r.uniform(-1, 1, (n, 3)), quats=r.normal(size=(n, 4)),
                          log_scales=r.uniform(-5, -3, (n, 3)), opacity_logits=r.normal(size=n),
                          colors=r.uniform(0, 1, (n, 3)), kappa=r.integers(0, 50, n), active=r.random(n) < 0.5)


def _start(cmd, data_dir: Path, port_file: Path, env_extra=None):
    if port_file.exists():
        port_file.unlink()
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.update(env_extra or {})
    log = data_dir.parent / f"{port_file.name}.log"
    with open(log, "ab") as out:
        proc = subprocess.Popen(cmd, cwd=str(REPO), env=env, stdout=out, stderr=subprocess.STDOUT)
    wait_for_start(proc, lambda: port_file.exists() and port_file.read_text().strip(),
                   f"the fusion server's port file {port_file}", log)
    return proc, int(port_file.read_text().strip())


def _kill(proc):
    if proc.poll() is None:
        proc.send_signal(signal.SIGKILL)
    proc.wait(10)


def test_sigkill_mid_upload_then_resume(tmp_path):
    data_dir, port_file = tmp_path / "data", tmp_path / "port"
    g = _subset(6000, 1)
    chunks = encode_subset(g, "survivor", 3, chunk_gaussians=500, quant=LOSSLESS)  # 12 chunks
    frames = [Frame(i, 0.0, np.full((24, 32, 3), 40 * i, np.uint8), np.full((24, 32), 2.0, np.float32),
                    np.eye(4), INTR) for i in range(3)]

    # 1st run: python -m gausslite_services.fusion_server
    proc, port = _start([sys.executable, "-m", "gausslite_services.fusion_server", "--port", "0", "--data-dir",
                         str(data_dir), "--port-file", str(port_file)], data_dir, port_file)
    try:
        with FusionClient(f"127.0.0.1:{port}", timeout_s=10) as c:
            c.wait_ready(20)
            c.open_session("survivor", "inspect the valve", INTR)
            c.open_session("other", "t", INTR)
            assert c.upload_subset("other", 1, _subset(300, 2), full_map_gaussians=3000).complete
            assert c.upload_keyframes("survivor", frames) == 3
            fused_before = c.fuse("concat")
            ch = grpc.insecure_channel(f"127.0.0.1:{port}")
            stub = fusion_pb2_grpc.FusionStub(ch)
            hdr = fusion_pb2.UploadSubsetRequest(header=fusion_pb2.UploadHeader(
                agent_id="survivor", map_version=3, n_chunks=12, full_map_gaussians=60000))
            ack = stub.UploadSubset(iter([hdr] + [fusion_pb2.UploadSubsetRequest(chunk=chunks[i])
                                                  for i in (0, 1, 2, 5, 7)]), timeout=10)
            assert list(ack.stored) == [0, 1, 2, 5, 7] and not ack.complete
            ch.close()
    finally:
        _kill(proc)  # SIGKILL: no graceful shutdown, no checkpoint

    # 2nd run on the same data dir: `gausslite serve fusion` with env fallbacks
    proc, port2 = _start([sys.executable, "-m", "gausslite.cli", "serve", "fusion", "--port", "0"], data_dir,
                         port_file, {"GAUSSLITE_DATA_DIR": str(data_dir), "GAUSSLITE_FUSION_PORT_FILE": str(port_file)})
    try:
        with FusionClient(f"127.0.0.1:{port2}", timeout_s=10) as c:
            c.wait_ready(20)
            st = c.upload_status("survivor", 3)  # session survived: no OpenSession needed
            assert list(st.stored) == [0, 1, 2, 5, 7] and sorted(st.missing) == [3, 4, 6, 8, 9, 10, 11]
            res = c.upload_subset("survivor", 3, g, full_map_gaussians=60000, quant=LOSSLESS, chunk_gaussians=500)
            assert res.complete and res.chunks_sent == 7 and res.bytes_on_wire == sum(len(x) for x in chunks)
            stats = c.stats()
            assert stats["agents"]["survivor"]["keyframes"] == 3
            assert stats["agents"]["survivor"]["share_pct"] == pytest.approx(10.0)
            assert stats["agents"]["other"]["gaussians_received"] == 300
            assert stats["latest_fused_version"] == fused_before.fused_version
            assert len(c.download_fused(fused_before.fused_version)) == 300
            # the assembled subset equals the original: fuse (concat keeps rows verbatim) and download
            fused = c.fuse("concat")
            assert fused.fused_version == fused_before.fused_version + 1
            down = c.download_fused(fused.fused_version)
            mine = down.take(slice(300, 6300))  # agents in sorted id order: "other" first
            assert mine.equals(g) and mine.equals(assemble(chunks)[0])
            assert len(down) == 6300
    finally:
        proc.send_signal(signal.SIGTERM)  # graceful this time
        try:
            assert proc.wait(20) == 0
        finally:
            _kill(proc)
