"""Robot-side client of the GaussLite fusion server (``gausslite.v1.Fusion``).

Source: paper Sec. III-E ("Multi-Agent Refinement": agents share their ROI subset with κ and their
keyframes); wire format (``docs/wire-format.md``): chunked, resumable, idempotent upload by
(agent id, map version, chunk index); deadlines on every client call; TLS, mutual TLS and bearer token.

Usage::

    from gausslite_services.fusion_server.client import FusionClient

    with FusionClient("127.0.0.1:50052", token="secret") as fc:
        fc.wait_ready()
        fc.open_session("robot-1", "find the red cup on the desk", intrinsics)
        res = fc.upload_subset("robot-1", map_version=3, gaussians=roi_subset,
                               full_map_gaussians=len(full_map))
        fc.upload_keyframes("robot-1", keyframes)
        fused = fc.fuse("vote", refine=True, refine_iters=100, progress=lambda f, m: print(f, m))
        arrays = fc.download_fused(fused.fused_version)

Replicas: ``target`` may name several fusion replicas sharing one PostgreSQL store —
``dns:///fusion.example:50052`` (every address the name resolves to, e.g. a Kubernetes headless
service) or ``ipv4:10.0.0.5:50052,10.0.0.6:50052``. The channel uses gRPC's own client-side load
balancing (``round_robin`` over the resolved addresses, re-resolved when connections drop; calls go to
the replicas that are connected, :func:`channel_options`); any replica accepts any agent's chunks, and an
upload interrupted on one replica resumes on another.

Credentials (``docs/security.md``): a robot sends its own per-agent token (``token=``) and/or presents
a client certificate whose CN is its agent id (``client_cert=``, ``client_key=``); the server lets it
write only its own agent id (``PERMISSION_DENIED`` otherwise). :func:`client_credentials_from_env`
reads them the way the agent service and the CLI do.

Errors and retries: the client makes one attempt. Every method sends each of its calls once, with a
deadline (``timeout_s`` unless stated otherwise), and raises the :class:`grpc.RpcError` of the call that
failed (a :mod:`gausslite_services.common.errors` subclass) with its status code: ``UNAVAILABLE`` (no
server at the address, a server restarting, its database unreachable), ``DEADLINE_EXCEEDED``, or the
server's own status (see ``proto/gausslite_rpc/fusion.proto``). The channel sets no gRPC retry policy.
What gRPC still does by itself is its transparent retry: it re-sends a call that never reached the
server's handler (its connection dropped before the call left this process, or the server refused the
stream unread), so no call is handled twice and no attempt count stacks under the caller's.

Retrying is the caller's choice: every call except :meth:`FusionClient.fuse` is idempotent, and
:data:`RETRYABLE` lists the transient codes. The agent's pusher (:class:`gausslite.mission.pusher.Pusher`)
retries pushes with exponential backoff, knowing about newer snapshots and the final push's deadline; a
robot without an agent retries in a loop of its own (``docs/robot-integration.md``). An upload resumes:
each :meth:`FusionClient.upload_subset` / :meth:`FusionClient.upload_chunks` call asks ``GetUploadStatus``
first and sends only the chunks the server misses (:func:`resume_upload` does the same over a stub of
the caller's own). :meth:`FusionClient.wait_ready` and :meth:`FusionClient.team_map` poll until their own
deadline: they wait for a state, they do not retry failures.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import grpc
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

from gausslite.core.arrays import GaussianArrays
from gausslite.core.environment import EnvironmentSettings
from gausslite.wire.decode import assemble
from gausslite.wire.encode import encode_subset
from gausslite.wire.format import QuantConfig
from gausslite.wire.images import encode_color_jpeg, encode_depth_png  # noqa: F401 - re-exported
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common.auth import read_secret
from gausslite_services.common.client_tls import default_client_tls
from gausslite_services.common.convert import intrinsics_to_proto
from gausslite_services.common.errors import raises_typed_errors
# the upload helpers live in a module of their own; imported from here as before
from gausslite_services.fusion_server.client_uploads import (UPLOAD_BATCH_BYTES, UploadResult,  # noqa: F401
                                                             keyframe_to_proto, missing_chunks, resume_upload)

SERVICE_NAME = "gausslite.v1.Fusion"
#: Transient status codes: worth retrying with backoff (the client itself does not; module docstring).
RETRYABLE = (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED)
#: Client-side message bound (the server enforces its own, smaller one).
CLIENT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024
#: Keyframes sent per ``UploadKeyframes`` call.
KEYFRAME_BATCH = 8


def client_credentials_from_env(env=None) -> dict:
    """Fusion-client credentials from the environment, as keyword arguments of :class:`FusionClient`.

    * ``token``: ``GAUSSLITE_FUSION_TOKEN``, else the file ``GAUSSLITE_FUSION_TOKEN_FILE`` (a docker
      secret / mounted Kubernetes Secret), else the fleet token ``GAUSSLITE_TOKEN``, else None.
    * ``root_cert``: the PEM file ``GAUSSLITE_TLS_CA`` (set → TLS).
    * ``client_cert``, ``client_key``: the PEM files ``GAUSSLITE_TLS_CLIENT_CERT`` and
      ``GAUSSLITE_TLS_CLIENT_KEY`` (mutual TLS).

    Args:
        env (Mapping | None): environment (default ``os.environ``).
    Returns:
        dict with keys ``token``, ``root_cert``, ``client_cert``, ``client_key`` (None when unset).
    Raises:
        OSError: a named file is unreadable. ValueError: an empty/invalid token file, only one of
            client certificate and key, or a ``GAUSSLITE_*`` variable that does not parse.
    """
    variables = EnvironmentSettings.read(env)
    token = variables.fusion_token
    if token is None and variables.fusion_token_file:
        token = read_secret(variables.fusion_token_file)
    token = token or variables.token
    read = lambda path: Path(path).read_bytes() if path else None  # noqa: E731
    cert, key = read(variables.tls_client_cert), read(variables.tls_client_key)
    if (cert is None) != (key is None):
        raise ValueError("mutual TLS needs both GAUSSLITE_TLS_CLIENT_CERT and GAUSSLITE_TLS_CLIENT_KEY")
    return {"token": token, "root_cert": read(variables.tls_ca), "client_cert": cert, "client_key": key}


def channel_credentials(root_cert: Optional[bytes] = None, client_cert: Optional[bytes] = None,
                        client_key: Optional[bytes] = None) -> Optional[grpc.ChannelCredentials]:
    """TLS channel credentials, or None for plaintext (no CA and no client certificate).

    Args:
        root_cert (bytes | None): PEM CA certificate(s) the server's certificate must chain to (None
            with a client certificate: the system's roots).
        client_cert (bytes | None), client_key (bytes | None): PEM client certificate chain and key
            (mutual TLS; the certificate's CN is the agent id).
    Raises:
        ValueError: only one of client certificate and key.
    """
    if (client_cert is None) != (client_key is None):
        raise ValueError("mutual TLS needs both a client certificate and its key")
    if root_cert is None and client_cert is None:
        return None
    return grpc.ssl_channel_credentials(root_certificates=root_cert, private_key=client_key,
                                        certificate_chain=client_cert)


def service_config() -> dict:
    """gRPC service config of the fusion channel: ``round_robin`` load balancing over every resolved address and no
    retry policy (the client makes one attempt per call; module docstring).

    Returns:
        dict: the JSON service config (see gRPC's service_config.proto).
    """
    return {"loadBalancingConfig": [{"round_robin": {}}]}


def channel_options(max_message_bytes: int = 64 * 1024 * 1024, max_reconnect_backoff_ms: int = 5000) -> list:
    """Channel arguments of :class:`FusionClient`: message bounds (bytes), the service config (:func:`service_config`:
    no retry policy), and a bound on gRPC's reconnection backoff (ms; gRPC's default grows to 120 s, so after a long
    outage the channel would keep failing calls for up to two minutes after the server is back).
    ``grpc.enable_retries`` stays on for gRPC's transparent retry of calls that never reached a server's handler
    (module docstring)."""
    return [("grpc.max_receive_message_length", max_message_bytes),
            ("grpc.max_send_message_length", max_message_bytes),
            ("grpc.enable_retries", 1),
            ("grpc.initial_reconnect_backoff_ms", min(1000, int(max_reconnect_backoff_ms))),
            ("grpc.max_reconnect_backoff_ms", int(max_reconnect_backoff_ms)),
            ("grpc.service_config", json.dumps(service_config()))]


_METHODS = {"vote": fusion_pb2.FUSE_METHOD_VOTE, "concat": fusion_pb2.FUSE_METHOD_CONCAT}
_METHOD_NAMES = {v: k for k, v in _METHODS.items()}
_METHOD_NAMES[fusion_pb2.FUSE_METHOD_UNSPECIFIED] = "vote"


@dataclass(frozen=True)
class FuseResult:
    """Outcome of :meth:`FusionClient.fuse` (the last ``FuseProgress`` message).

    Attributes:
        fused_version (int): the new fused map's version (download it with this number).
        n_gaussians (int): Gaussians in the fused map.
        seconds (float): server wall time of the fusion work.
        kept (dict[str, int]): agent id → Gaussians kept by the vote/concat (before refinement).
        received (dict[str, int]): agent id → Gaussians in the subset that was fused.
        map_versions (dict[str, int]): agent id → map version that was fused.
        method (str): "vote" or "concat". refined (bool), refine_iters (int), voxel_size (float, m),
        keyframes_used (int), bytes (int): size of the stored fused map.
        contest_radius (int): the vote's neighbourhood radius in voxels (0 for concat).
        for_agent (str): the agent the map was made for (``fuse(for_agent=...)``; "" = the team map).
        first_row (dict[str, int]): provenance, agent id → its first row in the fused map: rows
            ``[first_row[a], first_row[a] + kept[a])`` of :meth:`FusionClient.download_fused` came from agent ``a``;
            empty for a refined map (the refinement splits, clones and prunes rows).
        vote_seconds (float): wall time of the vote stage alone (s; 0 for concat). agents_revoted (int): agents whose
        subset changed since the server's last vote. incremental (bool): the vote re-used the server's voted map.
        refine_record (dict): refined maps: what the refinement did (``RefineRecord``: iterations requested, planned
            and run, training and held-out views, held-out losses of the vote and of the best state, best iteration,
            early stop, rollback to the vote); empty otherwise.
        team_map (bool): made by the server's background refinement (``fuse(team_map=True)``).
        age_s (float): served maps: seconds since it was made. team_map_current (bool): a team map made from the
            server's latest subsets and keyframes. keyframes_seen (int): team map: keyframes held when it was made.
    """

    fused_version: int
    n_gaussians: int
    seconds: float
    kept: Dict[str, int]
    received: Dict[str, int] = field(default_factory=dict)
    map_versions: Dict[str, int] = field(default_factory=dict)
    method: str = "vote"
    refined: bool = False
    refine_iters: int = 0
    voxel_size: float = 0.10
    keyframes_used: int = 0
    bytes: int = 0
    contest_radius: int = 0
    for_agent: str = ""
    first_row: Dict[str, int] = field(default_factory=dict)
    vote_seconds: float = 0.0
    agents_revoted: int = 0
    incremental: bool = False
    refine_record: Dict[str, object] = field(default_factory=dict)
    team_map: bool = False
    age_s: float = 0.0
    team_map_current: bool = False
    keyframes_seen: int = 0


def fuse_result_from_proto(r: "fusion_pb2.FuseResult") -> FuseResult:
    """Convert the wire ``FuseResult`` to :class:`FuseResult`."""
    return FuseResult(
        fused_version=int(r.fused_version), n_gaussians=int(r.n_gaussians), seconds=float(r.seconds),
        kept={a.agent_id: int(a.kept) for a in r.agents},
        received={a.agent_id: int(a.received) for a in r.agents},
        map_versions={a.agent_id: int(a.map_version) for a in r.agents},
        method=_METHOD_NAMES.get(r.method, "vote"), refined=bool(r.refined),
        refine_iters=int(r.refine_iters), voxel_size=float(r.voxel_size),
        keyframes_used=int(r.keyframes_used), bytes=int(r.bytes), contest_radius=int(r.contest_radius),
        for_agent=str(r.for_agent), vote_seconds=float(r.vote_seconds), agents_revoted=int(r.agents_revoted),
        incremental=bool(r.incremental),
        first_row={a.agent_id: int(a.first_row) for a in r.agents if a.HasField("first_row")},
        refine_record=({f.name: getattr(r.refine_record, f.name) for f in r.refine_record.DESCRIPTOR.fields}
                       if r.HasField("refine_record") else {}),
        team_map=bool(r.team_map), age_s=float(r.age_s), team_map_current=bool(r.team_map_current),
        keyframes_seen=int(r.keyframes_seen),
    )


@raises_typed_errors
class FusionClient:
    """Synchronous client of ``gausslite.v1.Fusion`` (thread-safe: one channel, stateless calls). Each method makes
    its calls once and raises the failed call's ``grpc.RpcError``; retrying is the caller's (module docstring).

    Args:
        target (str): ``host:port`` of the fusion server, or several replicas as
            ``dns:///name:port`` / ``ipv4:addr1:port,addr2:port`` (round-robin load balancing).
        token (str | None): bearer token sent as ``authorization: Bearer <token>`` on every call: the
            robot's own per-agent token, or the fleet token (team-wide mode).
        root_cert (bytes | None): PEM root certificate(s); set → TLS channel, else plaintext.
        client_cert (bytes | None), client_key (bytes | None): PEM client certificate and key for
            mutual TLS (TLS even without ``root_cert``: the system's roots then); the CN is the agent id.
            With none of the three: the process defaults (:mod:`gausslite_services.common.client_tls`), else plaintext.
        timeout_s (float): deadline of each call (seconds); :meth:`fuse` uses its own, longer one.
        max_retries, backoff_s: deprecated and ignored (a ``DeprecationWarning``): every call is made once and its
            failure raised (module docstring); retry in the caller.
    Raises:
        ValueError: non-positive timeout; only one of client cert/key.
    """

    def __init__(self, target: str, *, token: Optional[str] = None, root_cert: Optional[bytes] = None,
                 timeout_s: float = 30.0, max_retries: Optional[int] = None, backoff_s: Optional[float] = None,
                 client_cert: Optional[bytes] = None, client_key: Optional[bytes] = None):
        if not timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {timeout_s!r}")
        if max_retries is not None or backoff_s is not None:
            warnings.warn("FusionClient(max_retries=, backoff_s=) is deprecated and ignored: the client makes one "
                          "attempt per call and raises its failure; retry in the caller (docs/robot-integration.md)",
                          DeprecationWarning, stacklevel=2)
        self.target = target
        self.timeout_s = float(timeout_s)
        self._metadata = (("authorization", f"Bearer {token}"),) if token else None
        if root_cert is None and client_cert is None and client_key is None:
            root_cert, client_cert, client_key = default_client_tls()
        opts = channel_options(CLIENT_MAX_MESSAGE_BYTES)
        creds = channel_credentials(root_cert, client_cert, client_key)
        if creds is not None:
            self._channel = grpc.secure_channel(target, creds, opts)
        else:
            self._channel = grpc.insecure_channel(target, opts)
        self._stub = fusion_pb2_grpc.FusionStub(self._channel)
        self._health = health_pb2_grpc.HealthStub(self._channel)

    # ------------------------------------------------------------------ plumbing
    def _unary(self, method, request):
        """One call of the unary ``method`` with the client's deadline and credentials."""
        return method(request, timeout=self.timeout_s, metadata=self._metadata)

    # ------------------------------------------------------------------ API
    def wait_ready(self, timeout_s: float = 30.0) -> None:
        """Poll the standard health service until ``gausslite.v1.Fusion`` is SERVING.

        Raises:
            TimeoutError: not SERVING within ``timeout_s`` seconds (last error in the message).
        """
        deadline = time.monotonic() + timeout_s
        last = "no answer"
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(f"fusion server {self.target} not ready after {timeout_s:.1f}s: {last}")
            try:
                r = self._health.Check(health_pb2.HealthCheckRequest(service=SERVICE_NAME),
                                       timeout=max(0.05, min(2.0, remaining)), metadata=self._metadata)
                if r.status == health_pb2.HealthCheckResponse.SERVING:
                    return
                last = health_pb2.HealthCheckResponse.ServingStatus.Name(r.status)
            except grpc.RpcError as e:
                last = f"{e.code()}: {e.details()}"
            time.sleep(min(0.1, max(0.0, deadline - time.monotonic())))

    def open_session(self, agent_id: str, task_text: str, intrinsics) -> fusion_pb2.SessionInfo:
        """Open (or re-open, keeping earlier uploads) the session of ``agent_id``; returns the server's
        ``SessionInfo`` (``latest_map_version``: the agent's latest complete subset there, 0 = none).

        Args:
            agent_id (str): 1..64 chars of ``[A-Za-z0-9_.-]``.
            task_text (str): the agent's task.
            intrinsics (gausslite.camera.Intrinsics): the agent's camera (pixels).
        Raises:
            grpc.RpcError: INVALID_ARGUMENT (bad id / intrinsics), UNAUTHENTICATED, PERMISSION_DENIED
            (``agent_id`` is not the caller's own), ...
        """
        req = fusion_pb2.OpenSessionRequest(agent_id=agent_id, task_text=task_text,
                                            intrinsics=intrinsics_to_proto(intrinsics))
        return self._unary(self._stub.OpenSession, req)

    def upload_status(self, agent_id: str, map_version: int) -> fusion_pb2.UploadAck:
        """The server's ``UploadAck`` for (agent, map version) (``n_chunks == 0``: never seen)."""
        return self._unary(self._stub.GetUploadStatus,
                           fusion_pb2.UploadStatusRequest(agent_id=agent_id, map_version=int(map_version)))

    def upload_subset(self, agent_id: str, map_version: int, gaussians, *, full_map_gaussians: int,
                      quant: Optional[QuantConfig] = None, chunk_gaussians: int = 20000,
                      full_map_bytes: int = 0) -> UploadResult:
        """Encode and upload an ROI subset, resuming whatever the server already holds.

        The subset is encoded with :func:`gausslite.wire.encode.encode_subset`; the client asks
        ``GetUploadStatus`` and sends only missing chunks, in calls of at most :data:`UPLOAD_BATCH_BYTES`
        (each call is acknowledged after its chunks are persisted): one attempt (:func:`resume_upload`).
        Call it again after a failure to resume.

        Args:
            agent_id (str): the agent (its session must be open).
            map_version (int): version of the agent's map (newer complete versions supersede older).
            gaussians: GaussianMap / GaussianArrays / mapping of arrays (the ROI subset, with κ).
            full_map_gaussians (int): size of the agent's whole map (for the share %).
            quant (QuantConfig | None): codec quantisation (default ``QuantConfig()``).
            chunk_gaussians (int): Gaussians per chunk.
            full_map_bytes (int): optional wire size of the whole map (for statistics).
        Returns:
            UploadResult (``complete`` False: the server still misses chunks after this pass; call again).
        Raises:
            ValueError: the subset cannot be encoded (non-finite values, bad id).
            grpc.RpcError: the failed call's status: INVALID_ARGUMENT, NOT_FOUND (no session), FAILED_PRECONDITION
            (older than the latest complete version), RESOURCE_EXHAUSTED, PERMISSION_DENIED (``agent_id`` is not
            the caller's own), or a transient UNAVAILABLE / DEADLINE_EXCEEDED (chunks acknowledged before it stay).
        """
        chunks = encode_subset(gaussians, agent_id, int(map_version), chunk_gaussians=int(chunk_gaussians),
                               quant=quant or QuantConfig())
        return self.upload_chunks(agent_id, map_version, chunks, n_gaussians=len(GaussianArrays.from_any(gaussians)),
                                  full_map_gaussians=full_map_gaussians, full_map_bytes=full_map_bytes)

    def upload_chunks(self, agent_id: str, map_version: int, chunks: Sequence[bytes], *, n_gaussians: int,
                      full_map_gaussians: int, full_map_bytes: int = 0) -> UploadResult:
        """Upload already encoded chunks of (agent, map version) — a full subset or a delta
        (:func:`gausslite.wire.encode.encode_delta`) — resuming whatever the server already holds: one attempt
        (:func:`resume_upload`); call it again after a failure to resume.

        Args:
            chunks: the version's wire chunks (chunk i has index i).
            n_gaussians: Gaussians (records) the chunks carry (reported back only).
            full_map_gaussians, full_map_bytes: as :meth:`upload_subset`.
        Returns:
            UploadResult (``bytes_on_wire``: the sizes of ``chunks``, what the server's ack reports as received;
            ``bytes_sent`` counts the bytes transmitted by this call; ``complete`` False: the server still misses
            chunks after this pass).
        Raises:
            grpc.RpcError: as :meth:`upload_subset`; FAILED_PRECONDITION also when a delta's base
            version is not on the server (upload the full subset then).
        """
        header = fusion_pb2.UploadHeader(agent_id=agent_id, map_version=int(map_version), n_chunks=len(chunks),
                                         full_map_gaussians=int(full_map_gaussians), full_map_bytes=int(full_map_bytes))
        return resume_upload(self._stub, header, chunks, timeout_s=self.timeout_s, metadata=self._metadata,
                             n_gaussians=int(n_gaussians))

    def upload_keyframes(self, agent_id: str, keyframes: Sequence, *, jpeg_quality: int = 95,
                         color_format: str = "jpeg", rois: Optional[Sequence] = None) -> int:
        """Upload keyframes (colour as JPEG, depth as 16-bit PNG, pose, intrinsics).

        Args:
            agent_id (str): the agent (session must be open).
            keyframes (list[gausslite.datasets.base.Frame]): posed RGB-D frames; ``frame_id`` is the
                idempotency key (re-sending a stored frame is a no-op).
            jpeg_quality (int): 1..100.
            rois (list[np.ndarray | None] | None): per keyframe, the (H, W) bool task ROI (None: none);
                the fusion refinement restricts its loss to it.
        Returns:
            int: keyframes the server accepted (newly stored plus ones it already held); equals
            ``len(keyframes)`` on success. The server keeps at most ``max_keyframes`` per agent
            (oldest dropped).
        Raises:
            ValueError: a frame cannot be encoded.
            grpc.RpcError: INVALID_ARGUMENT (bad pose / image), NOT_FOUND (no session),
            PERMISSION_DENIED (``agent_id`` is not the caller's own), ...
        """
        if rois is not None and len(rois) != len(keyframes):
            raise ValueError(f"{len(rois)} ROIs for {len(keyframes)} keyframes")
        rois = list(rois) if rois is not None else [None] * len(keyframes)
        msgs = [keyframe_to_proto(agent_id, f, jpeg_quality, color_format, r) for f, r in zip(keyframes, rois)]
        accepted = 0
        for s in range(0, len(msgs), KEYFRAME_BATCH):
            batch = msgs[s:s + KEYFRAME_BATCH]
            ack = self._stub.UploadKeyframes(iter(batch), timeout=self.timeout_s, metadata=self._metadata)
            accepted += int(ack.stored) + int(ack.duplicates)
        return accepted

    def fuse(self, method: str = "vote", *, refine: bool = False, refine_iters: int = 200,
             voxel_size: float = 0.10, progress: Optional[Callable[[float, str], None]] = None,
             seed: int = 0, timeout_s: Optional[float] = None, contest_radius: Optional[int] = None,
             for_agent: Optional[str] = None, team_map: bool = False) -> FuseResult:
        """Run a fusion on the server and wait for its result (not retried: each call makes a version).

        Args:
            method (str): "vote" (κ-weighted voxel vote) or "concat" (baseline).
            refine (bool): joint refinement over the union of the agents' keyframes.
            refine_iters (int): refinement iterations.
            voxel_size (float): vote voxel edge δ in metres.
            progress (callable(fraction: float, message: str) | None): called for every progress
                message; ``message`` starts with the stage in brackets, e.g. ``"[refine] ..."``.
            seed (int): refinement RNG seed.
            timeout_s (float | None): deadline of the whole call (default ``max(600, 20·timeout_s)``).
            contest_radius (int | None): vote neighbourhood radius in voxels (0 = the paper's per-voxel
                rule, :func:`gausslite.fusion.vote.voxel_vote`); None = the server's default.
            for_agent (str | None): vote only: the team map as this agent uses it, its whole subset and the others'
                voted rows except those that draw its ROI in its uploaded ROI keyframes
                (:func:`gausslite.fusion.guard.for_robot`, ``docs/sharing.md``); None = the team map.
            team_map (bool): no fusion: the team map the server keeps refined in the background (``fusion.team_map``),
                its newest complete version at once, with ``age_s`` and ``team_map_current``; the other arguments
                are ignored. FAILED_PRECONDITION when the server keeps none, NOT_FOUND before its first version.
        Returns:
            FuseResult.
        Raises:
            ValueError: unknown method.
            grpc.RpcError: FAILED_PRECONDITION (nothing uploaded / refine without keyframes / ``for_agent`` without a
            complete subset), NOT_FOUND (``for_agent`` unknown),
            INVALID_ARGUMENT, DEADLINE_EXCEEDED, ...; RuntimeError: the stream ended without a result.
        """
        if method not in _METHODS:
            raise ValueError(f"method must be one of {sorted(_METHODS)}, got {method!r}")
        req = fusion_pb2.FuseRequest(method=_METHODS[method], voxel_size=float(voxel_size), refine=bool(refine),
                                     refine_iters=int(refine_iters), seed=int(seed))
        if contest_radius is not None:
            req.contest_radius = int(contest_radius)
        if for_agent:
            req.for_agent = str(for_agent)
        req.team_map = bool(team_map)
        t = timeout_s if timeout_s is not None else max(600.0, 20 * self.timeout_s)
        stream = self._stub.Fuse(req, timeout=t, metadata=self._metadata)
        try:
            for msg in stream:
                if progress is not None:
                    progress(float(msg.fraction), f"[{msg.stage}] {msg.message}")
                if msg.done:
                    return fuse_result_from_proto(msg.result)
        finally:
            stream.cancel()  # no-op when finished; stops server work if the caller bailed out
        raise RuntimeError("Fuse stream ended without a result")

    def team_map(self, wait_s: float = 0.0, *, current: bool = False, poll_s: float = 1.0) -> FuseResult:
        """The team map the server keeps refined in the background (``fuse(team_map=True)``), waiting up to
        ``wait_s`` seconds for its first version (NOT_FOUND until the first refinement over the robots' subsets and
        keyframes is done) or, with ``current``, for a version made from every robot's latest subset.

        Args:
            wait_s (float): seconds to wait; 0 = ask once.
            current (bool): also wait until ``team_map_current`` (the robots' final pushes are in it).
            poll_s (float): seconds between two asks.
        Returns:
            FuseResult of the newest version (``age_s``, ``team_map_current``); after ``wait_s`` the newest there is,
            current or not.
        Raises:
            gausslite_services.common.errors.NotFound: no version within ``wait_s``.
            gausslite_services.common.errors.FailedPrecondition: the server keeps no team map
            (``fusion.team_map.enabled: false``, or an install without the refinement's extra).
        """
        deadline = time.monotonic() + max(0.0, float(wait_s))
        while True:
            try:
                r = self.fuse(team_map=True)
                if r.team_map_current or not current or time.monotonic() >= deadline:
                    return r
            except grpc.RpcError as e:
                if e.code() != grpc.StatusCode.NOT_FOUND or time.monotonic() >= deadline:
                    raise
            time.sleep(max(0.05, min(poll_s, deadline - time.monotonic())))

    def download_fused(self, fused_version: int = 0, method: Optional[str] = None) -> GaussianArrays:
        """Download a fused map (``fused_version`` 0 = latest, optionally of ``method``).

        Returns:
            GaussianArrays (lossless copy of the server's fused map).
        Raises:
            grpc.RpcError: NOT_FOUND (unknown version / no fused map yet), ...
            gausslite.wire.format.WireError: corrupt download.
        """
        m = fusion_pb2.FUSE_METHOD_UNSPECIFIED if method is None else _METHODS[method]
        req = fusion_pb2.DownloadFusedRequest(fused_version=int(fused_version), method=m)
        chunks = [c.chunk for c in self._stub.DownloadFused(req, timeout=self.timeout_s, metadata=self._metadata)]
        arrays, _ = assemble(chunks)
        return arrays

    def stats(self) -> dict:
        """Server statistics (every page of ``GetStats``).

        Returns:
            dict: ``{"agents": {agent_id: {task_text, latest_map_version, has_complete_subset,
            gaussians_received, bytes_on_wire (received for that version: a delta as sent), stored_bytes, chunks,
            full_map_gaussians, full_map_bytes, share_pct, keyframes, bytes_per_gaussian (stored)}}, "fused": [{fused_version, n_gaussians,
            seconds, method, refined, kept: {...}, ...}], "latest_fused_version": int}``.
        """
        pages = [self._unary(self._stub.GetStats, fusion_pb2.StatsRequest())]
        while pages[-1].next_page_token:  # every page of agents; the fused maps come with the first
            pages.append(self._unary(self._stub.GetStats, fusion_pb2.StatsRequest(page_token=pages[-1].next_page_token)))
        r = pages[0]
        agents = {}
        for a in (a for p in pages for a in p.agents):
            agents[a.agent_id] = {
                "task_text": a.task_text, "latest_map_version": int(a.latest_map_version),
                "has_complete_subset": bool(a.has_complete_subset), "gaussians_received": int(a.gaussians_received),
                "bytes_on_wire": int(a.bytes_on_wire), "stored_bytes": int(a.stored_bytes), "chunks": int(a.chunks),
                "full_map_gaussians": int(a.full_map_gaussians), "full_map_bytes": int(a.full_map_bytes),
                "share_pct": float(a.share_pct), "keyframes": int(a.keyframes),
                "bytes_per_gaussian": float(a.bytes_per_gaussian),
            }
        fused = [fuse_result_from_proto(f).__dict__ for f in r.fused]
        return {"agents": agents, "fused": fused, "latest_fused_version": int(r.latest_fused_version)}

    def keyframe_poses(self, agent_id: str = "") -> List[dict]:
        """Poses of the keyframes the server buffers (no images), for viewers.

        Args:
            agent_id (str): one agent, or "" for every agent.
        Returns:
            list of dict ``{agent_id, frame_id, c2w: (4, 4) float64 camera-to-world (OpenCV axes, m),
            fx, fy, cx, cy (pixels), width, height, timestamp (s)}``, ordered by agent then arrival.
        Raises:
            grpc.RpcError: NOT_FOUND (agent without a session), INVALID_ARGUMENT (bad agent id), ...
        """
        r = self._unary(self._stub.GetKeyframePoses, fusion_pb2.KeyframePosesRequest(agent_id=agent_id))
        return [{"agent_id": k.agent_id, "frame_id": int(k.frame_id),
                 "c2w": np.asarray(k.pose.c2w, np.float64).reshape(4, 4), "fx": k.intrinsics.fx,
                 "fy": k.intrinsics.fy, "cx": k.intrinsics.cx, "cy": k.intrinsics.cy,
                 "width": int(k.intrinsics.width), "height": int(k.intrinsics.height), "timestamp": k.timestamp}
                for k in r.keyframes]

    def close(self) -> None:
        """Close the channel (idempotent)."""
        self._channel.close()

    def __enter__(self) -> "FusionClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["FusionClient", "client_credentials_from_env", "channel_credentials", "service_config", "channel_options",
           "resume_upload", "missing_chunks", "UploadResult", "FuseResult", "RETRYABLE", "encode_depth_png",
           "encode_color_jpeg", "keyframe_to_proto", "intrinsics_to_proto", "fuse_result_from_proto"]
