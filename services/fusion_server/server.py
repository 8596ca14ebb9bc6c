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

import json
import logging
import os
import sys
import threading
from dataclasses import dataclass
from typing import Optional, Sequence

from grpc_health.v1 import health_pb2
from pydantic import ValidationError

from gausslite.config import FusionSettings, GaussLiteConfig, load_config
from gausslite.core.environment import EnvironmentSettings
from gausslite.mapping.config import apply_overrides
from gausslite_rpc import fusion_pb2_grpc
from gausslite_services.common.cli_options import log_level_from, server_options_from_args
from gausslite_services.common.server import (RunningServer, ServerOptions, authenticator_from_options, build_server,
                                              run_until_signalled)
from gausslite_services.fusion_server.metrics import FusionMetrics, MeteredFusion
from gausslite_services.fusion_server.options import (DEFAULT_GRACE_S, DEFAULT_MAX_WORKERS, DEFAULT_PORT, build_parser,
                                                      fusion_run_arguments)
from gausslite_services.fusion_server.guards import check_agent_id  # noqa: F401 - re-exported
from gausslite_services.fusion_server.servicer import FUSED_AGENT_ID, SERVICE_NAME, FusionServicer  # noqa: F401 - re-exported
from gausslite_services.fusion_server.store import SqlFusionStore, StoreUnavailable, open_store

log = logging.getLogger(__name__)


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


def fusion_settings(config_path: Optional[str] = None, overrides: Sequence[str] = ()) -> FusionConfig:
    """The settings a fusion server runs with: the models' defaults (the measured settings), the file's, then the
    dotted ``fusion.KEY=VALUE`` overrides (``gausslite serve fusion --set``); what ``gausslite config --show --role
    fusion`` prints given the same file and overrides.

    Args:
        config_path: a GaussLite YAML (its ``fusion`` section), or a JSON or TOML file of the section's fields; None.
        overrides: ``fusion.``-prefixed dotted overrides, values parsed as YAML.
    Raises:
        ValueError: an override outside ``fusion.``, a bad value or file. FileNotFoundError: a missing file.
    """
    outside = [o for o in overrides if not o.strip().startswith("fusion.")]
    if outside:
        raise ValueError(f"the fusion server takes fusion.* overrides only, got {', '.join(outside)}")
    if not overrides:
        return FusionConfig.from_file(config_path) if config_path else FusionConfig()
    try:
        if config_path and not str(config_path).endswith((".yaml", ".yml")):  # a JSON/TOML file of the section
            base = {"fusion": FusionConfig.from_file(config_path).model_dump(mode="json", exclude_unset=True)}
            return GaussLiteConfig.model_validate(apply_overrides(base, list(overrides))).fusion
        return load_config(config_path, overrides).fusion  # the one loader of a GaussLite YAML
    except ValidationError as e:
        raise ValueError(f"bad fusion setting: {e}") from None


def run(options: ServerOptions, config_path: Optional[str] = None, *, data_dir: Optional[str] = None,
        port_file: Optional[str] = None, store: Optional[str] = None, overrides: Sequence[str] = ()) -> int:
    """Serve until SIGTERM/SIGINT (``gausslite serve fusion`` / ``python -m gausslite_services.fusion_server``).

    The data directory comes from ``data_dir``, else ``$GAUSSLITE_DATA_DIR``, else the config file's
    ``data_dir``, else ``./gausslite_fusion_data``; the store from ``store`` (a ``postgresql://``
    DSN), else ``$GAUSSLITE_FUSION_STORE``, else the config file's ``store``, else SQLite in the
    data directory; the port file from ``port_file`` or ``$GAUSSLITE_FUSION_PORT_FILE``. Prints
    ``fusion listening on HOST:PORT`` once serving. The settings: :func:`fusion_settings` (``overrides``: ``--set``).

    Raises:
        ValueError: a bad configuration, or a ``GAUSSLITE_*`` variable that does not parse
            (:class:`gausslite.core.environment.EnvironmentSettings`).
    """
    if not logging.getLogger().handlers:  # `gausslite serve` does not configure logging itself
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    config = fusion_settings(config_path, overrides)
    log.info("effective configuration: %s", json.dumps({"fusion": config.model_dump(mode="json")}, sort_keys=True))
    variables = EnvironmentSettings.read()
    data_dir = data_dir or variables.data_dir
    store = store or variables.fusion_store
    server = serve(options, config, data_dir=data_dir, store=store)
    port_file = port_file or variables.fusion_port_file
    if port_file:
        _write_port_file(port_file, server.port)
    print(f"fusion listening on {options.host}:{server.port}", flush=True)
    return run_until_signalled(server)  # duck-typed: .stop() and .grace_s


def main(argv=None) -> int:
    """``python -m gausslite_services.fusion_server``: the options of ``gausslite serve fusion``
    (:func:`gausslite_services.fusion_server.options.build_parser`, see ``--help``) with their environment fallbacks.
    Returns the exit code: 2 on bad options or a failed start (the reason on stderr)."""
    args = build_parser().parse_args(argv)
    env = os.environ
    try:
        level = log_level_from(args, env) or "INFO"
        logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        opts, config_path = server_options_from_args(args, "fusion", env, default_port=DEFAULT_PORT,
                                                     max_workers=DEFAULT_MAX_WORKERS, grace_s=DEFAULT_GRACE_S)
        return run(opts, config_path, **fusion_run_arguments(args, env))
    except (ValueError, OSError, RuntimeError) as e:
        print(f"fusion server: error: {e}", file=sys.stderr)
        return 2


__all__ = ["FusionConfig", "FusionServicer", "FusionServer", "fusion_settings", "serve", "run", "main", "SERVICE_NAME",
           "DEFAULT_PORT", "check_agent_id"]
