"""Fusion server: ``gausslite.v1.Fusion`` over gRPC (paper Sec. III-E).

Robots open a session, upload their ROI-Gaussian subsets (wire-codec chunks with κ, resumable and
idempotent by (agent id, map version, chunk index)) and keyframes; ``Fuse`` voxel-votes (or
concatenates) the latest complete subset of every agent, optionally refines the result jointly over
the union of the keyframe buffers (:func:`gausslite.fusion.refine.refine_map`), persists it as a new
fused version and streams progress; ``DownloadFused`` serves it as wire-codec chunks.

Status codes (see also ``proto/gausslite_rpc/fusion.proto``): INVALID_ARGUMENT for bad input
(never a crash), NOT_FOUND for an agent without a session (the session is the addressed entity) and
unknown fused versions, FAILED_PRECONDITION for a Fuse without complete subsets / refine without
keyframes / an upload older than the agent's latest complete version, and for a refine or a ``for_agent`` ROI guard
on an install without the ``mapper`` extra (torch, the rasterizer: ``gausslite.core.extras``; the startup log and the
``gausslite_fusion_fuse_mode_available`` metric say which fuse modes this server runs), RESOURCE_EXHAUSTED for
oversized messages and subsets beyond the server's limits and for upload streams beyond its caps,
DEADLINE_EXCEEDED for an upload stream that sent nothing for ``fusion.stream_idle_s``, ABORTED for a stalled upload
stream whose slot went to another upload (:class:`gausslite_services.fusion_server.guards.UploadStreams`),
UNAUTHENTICATED for missing, wrong or revoked credentials, PERMISSION_DENIED for a write to another agent's data. Every
rejected call is logged (``rejected <method> from <peer>: <code>: <reason>``).

Who may do what (``docs/security.md``): every call except health/reflection needs a credential when
the server has any (:mod:`gausslite_services.common.auth`: the fleet token, per-agent tokens from a hashed
token file, client certificates whose CN is the agent id). The writes — ``OpenSession`` (open or
resume a session), ``UploadSubset`` and ``UploadKeyframes`` — are allowed only for the caller's own
agent id (any id in the team-wide fleet-token mode); reads (``GetStats``, ``GetUploadStatus``,
``GetKeyframePoses``, ``DownloadFused``) and ``Fuse`` are open to every authenticated caller.

Persistence: a :class:`gausslite_services.fusion_server.store.SqlFusionStore` — SQLite (WAL,
synchronous=FULL) under the data directory by default, or PostgreSQL selected by a
``postgresql://`` DSN (``--store`` / ``$GAUSSLITE_FUSION_STORE``), which several replicas of this
server share; everything is committed before it is acknowledged. ``Fuse`` runs under the store's
fuse lock (a PostgreSQL advisory lock across replicas); fused versions are allocated by the database.

Incremental fusion: the servicer's :class:`gausslite.fusion.engine.FuseEngine` keeps an
:class:`gausslite.fusion.vote.IncrementalVote` of the
subsets it last voted; a vote re-loads only agents whose latest complete version changed and
re-votes only the voxels they touch (the result equals a full :func:`voxel_vote`).

Keyframe buffer: at most ``FusionConfig.max_keyframes_per_agent`` per agent; beyond that the oldest
(by arrival) are dropped (the ack reports how many). Keyframes are idempotent by (agent id,
frame_id): the first write wins, re-sends are no-ops.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
from dataclasses import dataclass
from typing import Optional

from grpc_health.v1 import health_pb2

from gausslite.config import FusionSettings
from gausslite_rpc import fusion_pb2_grpc
from gausslite_services.common.metrics import metrics_port_from
from gausslite_services.common.server import (RunningServer, ServerOptions, authenticator_from_options, build_server,
                                              run_until_signalled)
from gausslite_services.fusion_server.metrics import FusionMetrics, MeteredFusion
from gausslite_services.fusion_server.guards import check_agent_id  # noqa: F401 - re-exported
from gausslite_services.fusion_server.servicer import FUSED_AGENT_ID, SERVICE_NAME, FusionServicer  # noqa: F401 - re-exported
from gausslite_services.fusion_server.store import SqlFusionStore, StoreUnavailable, open_store

log = logging.getLogger(__name__)

DEFAULT_PORT = 50053

#: the fusion server's settings: the ``fusion`` section of the configuration tree (:mod:`gausslite.config`)
FusionConfig = FusionSettings


class StoreHealth:
    """Health that tells the truth about the store: every ``interval_s`` a cheap read of the store; while the
    database cannot be reached (:class:`StoreUnavailable`, e.g. PostgreSQL down) the fusion service and the server
    as a whole report NOT_SERVING, so an orchestrator or load balancer takes the replica out of rotation, and
    SERVING again once the read succeeds.

    Args:
        store: the fusion store. running: the RunningServer whose health servicer is set. interval_s: probe period.
    """

    def __init__(self, store: SqlFusionStore, running: RunningServer, interval_s: float) -> None:
        self.store, self.running, self.interval_s = store, running, float(interval_s)
        self.serving = True
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gausslite-store-health", daemon=True)
        self._thread.start()

    def probe(self) -> bool:
        """One probe; updates health on a change. Returns whether the store answered."""
        try:
            self.store.latest_complete()
            ok = True
        except StoreUnavailable as e:
            ok = False
            why = str(e)
        except Exception as e:  # noqa: BLE001 - a closed or broken store is not serving either
            ok = False
            why = f"{type(e).__name__}: {e}"
        if ok != self.serving and not self._stop.is_set():
            self.serving = ok
            status = health_pb2.HealthCheckResponse.SERVING if ok else health_pb2.HealthCheckResponse.NOT_SERVING
            for name in list(self.running.service_names) + [""]:
                self.running.health.set(name, status)
            if ok:
                log.info("fusion store reachable again: SERVING")
            else:
                log.error("fusion store unreachable, health NOT_SERVING: %s", why)
        return ok

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.probe()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=self.interval_s + 5)


@dataclass
class FusionServer:
    """A running fusion server: ``rpc`` (RunningServer), ``servicer``, ``store``; ``port``/``address``;
    ``store_health`` (:class:`StoreHealth`)."""

    rpc: RunningServer
    servicer: FusionServicer
    store: SqlFusionStore
    store_health: Optional[StoreHealth] = None

    @property
    def port(self) -> int:
        return self.rpc.port

    @property
    def address(self) -> str:
        return self.rpc.address

    @property
    def grace_s(self) -> float:
        return self.rpc.grace_s

    def reload(self) -> None:
        """Re-read the per-agent token file now and the TLS files at the next handshake (SIGHUP)."""
        self.rpc.reload()

    def stop(self, grace_s: Optional[float] = None) -> None:
        """Graceful shutdown: NOT_SERVING, let in-flight calls finish for ``grace_s``, close the store."""
        if self.store_health is not None:
            self.store_health.stop()
        self.rpc.stop(grace_s)
        self.servicer.shutdown()
        self.store.close()


def serve(options: ServerOptions, config: Optional[FusionConfig] = None, *,
          data_dir: Optional[str] = None, store: Optional[str] = None) -> FusionServer:
    """Start the fusion server (non-blocking).

    Args:
        options (ServerOptions): bind address, message bound, workers, credentials (fleet token,
            per-agent token file, client CA), TLS.
        config (FusionConfig | None): limits/defaults (default ``FusionConfig()``).
        data_dir (str | None): overrides ``config.data_dir``.
        store (str | None): overrides ``config.store`` (a ``postgresql://`` DSN, or "" for SQLite).
    Returns:
        FusionServer: ``.port`` is the bound port; ``.stop()`` shuts down gracefully.
    Raises:
        RuntimeError: the address cannot be bound. OSError / sqlite3.Error: unusable data dir.
        StoreError: unreachable PostgreSQL; SchemaTooNew: a store written by a newer GaussLite.
        ValueError / FileNotFoundError: bad credentials options (token, token file, TLS files), or a message bound
            below :data:`gausslite_services.fusion_server.servicer.MIN_MESSAGE_BYTES`.
    """
    auth = authenticator_from_options(options)
    config = config or FusionConfig()
    if data_dir is not None:
        config = config.model_copy(update={"data_dir": str(data_dir)})
    if store is not None:
        config = config.model_copy(update={"store": str(store)})
    store = (open_store(config.store, pool_size=config.store_pool_size,
                        acquire_timeout_s=config.store_acquire_timeout_s) if config.store
             else open_store(config.data_dir))
    try:
        servicer = FusionServicer(store, config, options.max_message_bytes, auth=auth,
                                  handler_threads=options.max_workers)
    except BaseException:
        store.close()
        raise
    metered = MeteredFusion(servicer, FusionMetrics())
    try:
        running = build_server(options, lambda srv: fusion_pb2_grpc.add_FusionServicer_to_server(metered, srv),
                               [SERVICE_NAME], metered.metrics.registry, authenticator=auth)
    except BaseException:
        store.close()
        raise
    log.info("fusion store: %s (%s, schema %d)", store.location, store.dialect, store.schema_version())
    for mode, why in servicer.fuse_modes().items():
        metered.metrics.fuse_mode_available.labels(mode=mode).set(0 if why else 1)
    log.info("%s", servicer.describe_fuse_modes())
    return FusionServer(running, servicer, store, StoreHealth(store, running, config.health_probe_s))


def _write_port_file(path: str, port: int) -> None:
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(f"{port}\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def run(options: ServerOptions, config_path: Optional[str] = None, *, data_dir: Optional[str] = None,
        port_file: Optional[str] = None, store: Optional[str] = None) -> int:
    """Serve until SIGTERM/SIGINT (``gausslite serve fusion`` / ``python -m gausslite_services.fusion_server``).

    The data directory comes from ``data_dir``, else ``$GAUSSLITE_DATA_DIR``, else the config file's
    ``data_dir``, else ``./gausslite_fusion_data``; the store from ``store`` (a ``postgresql://``
    DSN), else ``$GAUSSLITE_FUSION_STORE``, else the config file's ``store``, else SQLite in the
    data directory; the port file from ``port_file`` or ``$GAUSSLITE_FUSION_PORT_FILE``. Prints
    ``fusion listening on HOST:PORT`` once serving.
    """
    if not logging.getLogger().handlers:  # `gausslite serve` does not configure logging itself
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    config = FusionConfig.from_file(config_path) if config_path else FusionConfig()
    data_dir = data_dir or os.environ.get("GAUSSLITE_DATA_DIR") or None
    store = store or os.environ.get("GAUSSLITE_FUSION_STORE") or None
    server = serve(options, config, data_dir=data_dir, store=store)
    port_file = port_file or os.environ.get("GAUSSLITE_FUSION_PORT_FILE") or None
    if port_file:
        _write_port_file(port_file, server.port)
    print(f"fusion listening on {options.host}:{server.port}", flush=True)
    return run_until_signalled(server)  # duck-typed: .stop() and .grace_s


def main(argv=None) -> int:
    """``python -m gausslite_services.fusion_server``: CLI with environment fallbacks (see ``--help``)."""
    env = os.environ
    p = argparse.ArgumentParser(prog="python -m gausslite_services.fusion_server",
                                description="GaussLite fusion server (gausslite.v1.Fusion).")
    p.add_argument("--host", default=env.get("GAUSSLITE_FUSION_HOST", "127.0.0.1"),
                   help="bind address (env GAUSSLITE_FUSION_HOST)")
    p.add_argument("--port", type=int, default=int(env.get("GAUSSLITE_FUSION_PORT", DEFAULT_PORT)),
                   help=f"port, 0 = ephemeral (env GAUSSLITE_FUSION_PORT, default {DEFAULT_PORT})")
    p.add_argument("--data-dir", default=env.get("GAUSSLITE_DATA_DIR"),
                   help="folder of the fusion store, the SQLite database fusion.sqlite3 with every subset, keyframe "
                        "and fused map the server acknowledged (env GAUSSLITE_DATA_DIR; default ./gausslite_fusion_data; "
                        "not used with --store)")
    p.add_argument("--store", default=env.get("GAUSSLITE_FUSION_STORE"),
                   help="postgresql://user:pw@host:port/db to share a PostgreSQL store between replicas "
                        "(env GAUSSLITE_FUSION_STORE; default: SQLite in --data-dir)")
    p.add_argument("--port-file", default=env.get("GAUSSLITE_FUSION_PORT_FILE"),
                   help="write the bound port to this file (env GAUSSLITE_FUSION_PORT_FILE)")
    p.add_argument("--token", default=env.get("GAUSSLITE_TOKEN"),
                   help="fleet bearer token, team-wide mode (env GAUSSLITE_TOKEN)")
    p.add_argument("--agent-tokens", default=env.get("GAUSSLITE_AGENT_TOKENS_FILE"),
                   help="JSON/YAML file of per-agent token hashes, re-read when it changes or on SIGHUP "
                        "(env GAUSSLITE_AGENT_TOKENS_FILE; `gausslite tokens` makes it)")
    p.add_argument("--fleet-token-writes", action="store_true",
                   default=env.get("GAUSSLITE_FLEET_TOKEN_WRITES", "").lower() in ("1", "true", "yes"),
                   help="the fleet token keeps write access to every agent next to per-agent credentials "
                        "(migration; env GAUSSLITE_FLEET_TOKEN_WRITES=1)")
    p.add_argument("--tls-cert", default=env.get("GAUSSLITE_TLS_CERT"), help="PEM cert (env GAUSSLITE_TLS_CERT)")
    p.add_argument("--tls-key", default=env.get("GAUSSLITE_TLS_KEY"), help="PEM key (env GAUSSLITE_TLS_KEY)")
    p.add_argument("--tls-client-ca", default=env.get("GAUSSLITE_TLS_CLIENT_CA"),
                   help="PEM CA of client certificates: mutual TLS, the certificate CN is the agent id "
                        "(env GAUSSLITE_TLS_CLIENT_CA)")
    p.add_argument("--config", default=env.get("GAUSSLITE_FUSION_CONFIG"),
                   help="JSON/TOML FusionConfig file (env GAUSSLITE_FUSION_CONFIG)")
    p.add_argument("--max-workers", type=int, default=16, help="handler threads")
    p.add_argument("--max-message-bytes", type=int, default=4 * 1024 * 1024, help="gRPC message bound in bytes (default 4 MiB, at least 128 KiB); a wire chunk may take it minus 16 "
                        "bytes (SessionInfo.max_chunk_bytes)")
    p.add_argument("--grace", type=float, default=10.0, help="shutdown grace period, seconds")
    p.add_argument("--metrics-port", type=int, default=None,
                   help="Prometheus /metrics port, 0 = off (env GAUSSLITE_FUSION_METRICS_PORT, GAUSSLITE_METRICS_PORT)")
    p.add_argument("--log-level", default=env.get("GAUSSLITE_LOG_LEVEL", "INFO"))
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    opts = ServerOptions(host=args.host, port=args.port, token=args.token or None, tls_cert=args.tls_cert or None,
                         tls_key=args.tls_key or None, agent_tokens_file=args.agent_tokens or None,
                         tls_client_ca=args.tls_client_ca or None,
                         fleet_token_writes=True if args.fleet_token_writes else None,
                         max_message_bytes=args.max_message_bytes,
                         max_workers=args.max_workers, grace_s=args.grace)
    try:
        opts.metrics_port = metrics_port_from(args.metrics_port, env.get("GAUSSLITE_FUSION_METRICS_PORT")
                                              or env.get("GAUSSLITE_METRICS_PORT"))
        return run(opts, args.config, data_dir=args.data_dir, port_file=args.port_file, store=args.store)
    except (ValueError, OSError, RuntimeError) as e:
        print(f"fusion server: error: {e}", file=sys.stderr)
        return 2


__all__ = ["FusionConfig", "FusionServicer", "FusionServer", "serve", "run", "main", "SERVICE_NAME",
           "DEFAULT_PORT", "check_agent_id"]
