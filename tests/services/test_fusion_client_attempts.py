"""One layer retries a push. The fusion client makes one attempt per call (each gRPC call sent once, its failure
raised, no retry policy on the channel); the agent's pusher decides every attempt of a push, each attempt resuming the
upload (``resume_upload``). An in-process fake of ``gausslite.v1.Fusion`` counts the calls it receives and fails the
ones it is told to, with ``UNAVAILABLE`` from its handler: exactly what a gRPC retry policy would have re-sent."""

from __future__ import annotations

import threading
import time
from collections import Counter
from concurrent import futures

import grpc
import numpy as np
import pytest

from gausslite.mission import AgentConfig
from gausslite.mission.pusher import Pusher, Snapshot
from gausslite.mission.share import ShareSession
from gausslite.wire.codec import LOSSLESS, encode_subset
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.errors import DeadlineExceeded, Unavailable
from gausslite_services.fusion_server.client import FusionClient, missing_chunks, resume_upload
from tests.services.test_fusion_server import INTR, frame, rand_subset, start, upload_raw

METHODS = ("OpenSession", "UploadSubset", "GetUploadStatus", "UploadKeyframes", "Fuse", "DownloadFused", "GetStats",
           "GetKeyframePoses")


class CountingFusion(fusion_pb2_grpc.FusionServicer):
    """A fusion server that holds nothing: it counts every call it receives; a call of a method in ``down``, or one of
    the next ``fail[method]`` calls, fails with UNAVAILABLE; the others answer as a server with an empty store (an
    upload's single call completes it). ``stall_s[method]``: seconds a call waits before answering."""

    def __init__(self):
        self.calls: Counter = Counter()
        self.fail: Counter = Counter()
        self.down: set = set()
        self.stall_s: dict = {}
        self._lock = threading.Lock()

    def _enter(self, method: str, context) -> None:
        with self._lock:
            self.calls[method] += 1
            failing = method in self.down or self.fail[method] > 0
            self.fail[method] = max(0, self.fail[method] - 1)
        time.sleep(self.stall_s.get(method, 0.0))
        if failing:
            context.abort(grpc.StatusCode.UNAVAILABLE, f"{method}: the fake server is down")

    def OpenSession(self, request, context):
        self._enter("OpenSession", context)
        return fusion_pb2.SessionInfo(agent_id=request.agent_id, created=True)

    def GetUploadStatus(self, request, context):
        self._enter("GetUploadStatus", context)
        return fusion_pb2.UploadAck(agent_id=request.agent_id, map_version=request.map_version)

    def UploadSubset(self, request_iterator, context):
        messages = list(request_iterator)  # the whole stream arrives, then the call fails or completes
        self._enter("UploadSubset", context)
        h = messages[0].header
        return fusion_pb2.UploadAck(agent_id=h.agent_id, map_version=h.map_version, n_chunks=h.n_chunks,
                                    stored=list(range(h.n_chunks)), complete=True, is_latest=True)

    def UploadKeyframes(self, request_iterator, context):
        n = len(list(request_iterator))
        self._enter("UploadKeyframes", context)
        return fusion_pb2.KeyframeAck(stored=n)

    def Fuse(self, request, context):
        self._enter("Fuse", context)
        yield from ()

    def DownloadFused(self, request, context):
        self._enter("DownloadFused", context)
        yield from ()

    def GetStats(self, request, context):
        self._enter("GetStats", context)
        return fusion_pb2.StatsResponse()

    def GetKeyframePoses(self, request, context):
        self._enter("GetKeyframePoses", context)
        return fusion_pb2.KeyframePosesResponse()


@pytest.fixture()
def fake():
    """(the fake servicer, its loopback address)."""
    servicer = CountingFusion()
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    fusion_pb2_grpc.add_FusionServicer_to_server(servicer, server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    yield servicer, f"127.0.0.1:{port}"
    server.stop(0.5)


def _calls_of(fusion: CountingFusion, call) -> Counter:
    """The server calls that ``call()`` made (it must raise UNAVAILABLE)."""
    before = Counter(fusion.calls)
    with pytest.raises(Unavailable):
        call()
    return fusion.calls - before


def test_every_client_method_makes_one_call_and_raises_its_status(fake):
    fusion, address = fake
    fusion.down = set(METHODS)
    with FusionClient(address, timeout_s=10) as c:
        cases = {
            "OpenSession": lambda: c.open_session("r1", "find the cup", INTR),
            "GetUploadStatus": lambda: c.upload_status("r1", 1),
            "UploadKeyframes": lambda: c.upload_keyframes("r1", [frame(0), frame(1)]),
            "Fuse": lambda: c.fuse("vote"),
            "DownloadFused": lambda: c.download_fused(0),
            "GetStats": c.stats,
            "GetKeyframePoses": c.keyframe_poses,
        }
        for method, call in cases.items():
            assert _calls_of(fusion, call) == Counter({method: 1}), method
        # an upload is one GetUploadStatus, and with it answered, one UploadSubset
        subset = rand_subset(50, 0.0, 1)
        upload = lambda: c.upload_subset("r1", 1, subset, full_map_gaussians=100)  # noqa: E731
        assert _calls_of(fusion, upload) == Counter({"GetUploadStatus": 1})
        fusion.down = {"UploadSubset"}
        assert _calls_of(fusion, upload) == Counter({"GetUploadStatus": 1, "UploadSubset": 1})
        fusion.down = set()
        assert c.upload_subset("r1", 1, subset, full_map_gaussians=100).complete  # the caller's next attempt


def test_a_deadline_ends_the_one_attempt(fake):
    fusion, address = fake
    fusion.stall_s["GetStats"] = 1.0
    with FusionClient(address, timeout_s=0.3) as c:
        with pytest.raises(DeadlineExceeded):
            c.stats()
    time.sleep(1.2)  # a re-sent call would have reached the server by now
    assert fusion.calls == Counter({"GetStats": 1})


def test_max_retries_is_deprecated_and_ignored(fake):
    fusion, address = fake
    fusion.down = {"GetStats"}
    with pytest.warns(DeprecationWarning, match="max_retries"):
        c = FusionClient(address, timeout_s=10, max_retries=5, backoff_s=0.01)
    with c:
        assert _calls_of(fusion, c.stats) == Counter({"GetStats": 1})


def test_resume_upload_sends_only_the_missing_chunks_in_bounded_calls(tmp_path):
    srv = start(tmp_path)
    chunks = encode_subset(rand_subset(3000, 0.0, 1), "r1", 1, chunk_gaussians=300, quant=LOSSLESS)
    assert len(chunks) == 10
    try:
        with FusionClient(srv.address, timeout_s=10) as c:
            c.open_session("r1", "find the cup", INTR)
            stub = c._stub
            assert not upload_raw(stub, "r1", 1, chunks, order=[0, 1, 2, 5]).complete
            status = c.upload_status("r1", 1)
            assert missing_chunks(status, 10) == [3, 4, 6, 7, 8, 9]
            assert missing_chunks(status, 11) == list(range(11))  # the server holds the version under another count
            header = fusion_pb2.UploadHeader(agent_id="r1", map_version=1, n_chunks=10, full_map_gaussians=9000)
            sent, acks = [], []
            r = resume_upload(stub, header, chunks, timeout_s=10, n_gaussians=3000, chunks_per_call=4,
                              on_send=sent.append, on_ack=lambda batch, ack: acks.append(ack.complete))
            assert sent == [[3, 4, 6, 7], [8, 9]] and acks == [False, True]
            assert r.complete and r.chunks_sent == 6 and r.attempts == 2 and r.n_gaussians == 3000
            assert r.bytes_sent == sum(len(chunks[i]) for i in (3, 4, 6, 7, 8, 9))
            again = resume_upload(stub, header, chunks, timeout_s=10)  # complete: nothing is sent
            assert again.complete and again.chunks_sent == again.attempts == 0
            assert missing_chunks(c.upload_status("r1", 1), 10) == []
            with pytest.raises(ValueError, match="10 chunks, 9 given"):
                resume_upload(stub, header, chunks[:9], timeout_s=10)
    finally:
        srv.stop(0.5)


def _pusher(fusion, **push):
    config = AgentConfig(push={"nice": 0, **push}, refine_views={"crop": False, "budget_ratio": None})
    errors = []
    p = Pusher("p1", "find the object", config, fusion, ShareSession("p1", config), mapper=None,
               intrinsics=lambda: INTR, report=errors.append)
    return p, errors


def _final_snapshot() -> Snapshot:
    return Snapshot(1, rand_subset(500, 0.0, 2), 5000, final=True, ids=np.arange(500, dtype=np.int64))


def test_a_final_push_to_a_failing_server_makes_exactly_the_pushers_attempts(fake):
    """Every pusher attempt is one session, one status and one upload call on the server, nothing more; the attempts
    follow the pusher's backoff (0.05 s doubling to 0.2 s) within the final push's budget (1 s): at most 7."""
    fusion, address = fake
    fusion.down = {"UploadSubset"}
    with FusionClient(address, timeout_s=10) as c:
        p, errors = _pusher(c, backoff_s=0.05, max_backoff_s=0.2, final_timeout_s=1.0)
        try:
            p.push_snapshot(_final_snapshot())
        finally:
            p.close()
    attempts = p.push_failures
    assert p.final_done.is_set() and not p.final_push_ok
    assert 2 <= attempts <= 7, attempts  # attempts start at 0, .05, .15, .35, .55, .75, .95 s at the most
    assert fusion.calls == Counter({"OpenSession": attempts, "GetUploadStatus": attempts, "UploadSubset": attempts})
    failed = [e for e in errors if e]
    assert [e.split(" failed")[0] for e in failed] == [f"push v1 attempt {k}" for k in range(1, attempts + 1)]
    assert all("UNAVAILABLE" in e for e in failed)


def test_the_pusher_retries_until_the_server_answers_and_each_attempt_is_one_call_each(fake):
    fusion, address = fake
    fusion.fail["UploadSubset"] = 2  # the first two uploads fail, the third completes
    with FusionClient(address, timeout_s=10) as c:
        p, _ = _pusher(c, backoff_s=0.05, max_backoff_s=0.2, final_timeout_s=30)
        try:
            p.push_snapshot(_final_snapshot())
        finally:
            p.close()
    assert p.final_push_ok and p.push_failures == 2 and [r.version for r in p.pushes] == [1]
    assert fusion.calls == Counter({"OpenSession": 3, "GetUploadStatus": 3, "UploadSubset": 3})
