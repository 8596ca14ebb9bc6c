"""gRPC server plumbing shared by the parser, agent and fusion services.

* :func:`build_server` — a ``grpc.server`` with bounded message sizes, the standard health service
  (``grpc.health.v1.Health``) and server reflection, caller authentication, bound to ``host:port``
  (port 0 → an ephemeral port) with or without TLS (optionally mutual TLS).
* :class:`AuthInterceptor` — authenticates every call (except health/reflection) with a
  :class:`gausslite_services.common.auth.Authenticator`: the fleet bearer token, per-agent tokens from a
  hashed token file, client certificates. Missing or wrong credentials → ``UNAUTHENTICATED``; every
  rejected call is logged. Which calls a caller may make is the service's decision
  (:meth:`gausslite_services.common.auth.Principal.check_write`). See ``docs/security.md``.
* :class:`DecodeInterceptor` — parses request messages inside the call, so bytes that are not a valid
  message end the call with ``INVALID_ARGUMENT`` and a log line (gRPC's own deserializer says ``INTERNAL``).
  The interceptors are :mod:`gausslite_services.common.interceptors`' (re-exported here).
* :class:`TlsFiles` — server certificate, key and (mTLS) client CA from PEM files, re-read at the next
  TLS handshake after any of them changes, so certificates rotate without a restart.
* :func:`run_until_signalled` — blocks until SIGTERM/SIGINT, then marks health NOT_SERVING and stops
  the server with a grace period so in-flight calls finish; SIGHUP re-reads the token file now and
  the TLS files at the next handshake (:meth:`RunningServer.reload`).
* Prometheus: with ``ServerOptions.metrics_port`` set, :func:`build_server` also serves the service's
  own registry at ``http://host:metrics_port/metrics`` (:mod:`gausslite_services.common.metrics`); it stops
  with the server.
"""

from __future__ import annotations

import logging
import os
import signal
import ssl
import threading
from concurrent import futures
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, List, Optional, Tuple

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from gausslite_services.common.auth import AgentTokens, Authenticator
# the interceptors live in a module of their own; their names import from here as before
from gausslite_services.common.interceptors import (AuthInterceptor, BearerTokenInterceptor,  # noqa: F401
                                                    DecodeInterceptor, FailureLimiter, MalformedMessage, peer_host)
from gausslite_services.common.metrics import CollectorRegistry, MetricsEndpoint, start_metrics_endpoint

log = logging.getLogger(__name__)

HEALTH_SERVICE = "grpc.health.v1.Health"
REFLECTION_SERVICES = ("grpc.reflection.v1alpha.ServerReflection", "grpc.reflection.v1.ServerReflection")


@dataclass
class ServerOptions:
    """Options common to every GaussLite gRPC server.

    Attributes:
        host (str): bind address (``127.0.0.1`` loopback; ``0.0.0.0`` for all interfaces).
        port (int): TCP port; 0 binds an ephemeral port (see :attr:`RunningServer.port`).
        token (str | None): the fleet bearer token; every call (except health/reflection) must then
            carry ``authorization: Bearer <token>`` metadata (or another valid credential below).
            Alone it is the team-wide mode: any holder may write any agent's data.
        agent_tokens_file (str | None): JSON/YAML file of per-agent token hashes
            (:class:`gausslite_services.common.auth.AgentTokens`); a caller with such a token is that agent.
        tls_cert (str | None), tls_key (str | None): PEM paths; both set → TLS, neither → plaintext.
        tls_client_ca (str | None): PEM CA bundle; set → mutual TLS: every client must present a
            certificate it signed, whose subject CN is the caller's agent id. Needs TLS.
        fleet_token_writes (bool | None): whether the fleet token may write every agent's data; None =
            only when no per-agent credential (token file, client CA) is configured.
        max_message_bytes (int): bound on received and sent messages.
        max_workers (int): handler threads.
        grace_s (float): shutdown grace period for in-flight calls.
        auth_exempt (tuple[str, ...]): method-name prefixes that need no token.
        metrics_port (int | None): Prometheus ``/metrics`` HTTP port on ``host``; None = off, 0 = an
            ephemeral port (see :attr:`RunningServer.metrics`). The CLI maps ``--metrics-port 0`` to None.
        max_concurrent_rpcs (int | None): calls in progress or queued at once; beyond it a new call gets
            RESOURCE_EXHAUSTED at once instead of queueing without bound behind a client that holds the handler
            threads (None = 4 × ``max_workers``).
        keepalive_s (float): the server pings an idle connection after this many seconds, and closes it when the
            ping is not answered within ``keepalive_timeout_s``: a vanished peer's stream frees its handler thread.
    """

    host: str = "127.0.0.1"
    port: int = 0
    token: Optional[str] = None
    tls_cert: Optional[str] = None
    tls_key: Optional[str] = None
    agent_tokens_file: Optional[str] = None
    tls_client_ca: Optional[str] = None
    fleet_token_writes: Optional[bool] = None
    max_message_bytes: int = 4 * 1024 * 1024
    max_workers: int = 8
    grace_s: float = 5.0
    auth_exempt: Tuple[str, ...] = (f"/{HEALTH_SERVICE}/",) + tuple(f"/{s}/" for s in REFLECTION_SERVICES)
    metrics_port: Optional[int] = None
    max_concurrent_rpcs: Optional[int] = None
    keepalive_s: float = 60.0
    keepalive_timeout_s: float = 20.0


def _no_password(*_):
    raise ValueError("encrypted private keys are not supported; give an unencrypted PEM key (mode 0600)")


class TlsFiles:
    """The server's TLS material from PEM files, re-read after any file changes.

    gRPC calls :meth:`fetch` before every new TLS handshake; when the stat signature of the
    certificate, key or client CA file changed, the files are read again and validated with Python's
    :mod:`ssl` (the key must match the certificate, the CA bundle must parse). Valid new material
    serves every later handshake; established connections keep theirs. Invalid material (for example
    a new certificate whose key has not been written yet) is logged and the previous material stays
    in use, so a rotation never takes the server down.

    Args:
        cert (str), key (str): PEM certificate chain and unencrypted private key.
        client_ca (str | None): PEM CA bundle for client certificates (mutual TLS, required).
    Raises:
        FileNotFoundError: a file is missing. ValueError: unusable material.
    """

    def __init__(self, cert: str, key: str, client_ca: Optional[str] = None):
        self.cert, self.key, self.client_ca = str(cert), str(key), (str(client_ca) if client_ca else None)
        for p in (self.cert, self.key, self.client_ca):
            if p and not os.path.isfile(p):
                raise FileNotFoundError(f"TLS file not found: {p}")
        self._lock = threading.Lock()
        self._sig, self._config = self._load()
        self._error: Optional[str] = None

    def _signature(self) -> tuple:
        out = []
        for p in (self.cert, self.key, self.client_ca):
            if p:
                st = os.stat(p)
                out.append((st.st_mtime_ns, st.st_size, st.st_ino))
        return tuple(out)

    def _load(self):
        """(signature, ServerCertificateConfiguration) of the files as they are now. Raises ValueError/OSError."""
        for _ in range(3):
            sig = self._signature()
            ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            try:
                ctx.load_cert_chain(self.cert, self.key, password=_no_password)
            except ssl.SSLError as e:
                raise ValueError(f"TLS certificate {self.cert} / key {self.key} unusable "
                                 f"(not PEM, or the key does not match the certificate): {e}") from None
            if self.client_ca:
                try:
                    ctx.load_verify_locations(cafile=self.client_ca)
                except ssl.SSLError as e:
                    raise ValueError(f"TLS client CA {self.client_ca} unusable: {e}") from None
            cert = Path(self.cert).read_bytes()
            key = Path(self.key).read_bytes()
            ca = Path(self.client_ca).read_bytes() if self.client_ca else None
            if self._signature() == sig:  # nothing changed while reading: what was validated is what was read
                return sig, grpc.ssl_server_certificate_configuration([(key, cert)], root_certificates=ca)
        raise ValueError("TLS files keep changing while being read")

    def fetch(self):
        """gRPC's certificate-configuration fetcher: new material after a change, else None. Never raises."""
        try:
            with self._lock:
                if self._signature() == self._sig:
                    return None
                sig, config = self._load()
                self._sig, self._config, self._error = sig, config, None
            log.info("TLS material reloaded (%s%s)", self.cert, f", client CA {self.client_ca}" if self.client_ca else "")
            return config
        except Exception as e:  # noqa: BLE001 - a bad rotation step must not break handshakes
            msg = f"{type(e).__name__}: {e}"
            if msg != self._error:
                log.error("TLS files changed but are unusable, still serving the previous certificate: %s", msg)
            self._error = msg
            return None

    def reload(self) -> None:
        """Re-read the files at the next handshake even when their stat signature is unchanged."""
        with self._lock:
            self._sig = None

    def credentials(self) -> grpc.ServerCredentials:
        """Dynamic server credentials bound to :meth:`fetch` (client certificates required with a client CA)."""
        return grpc.dynamic_ssl_server_credentials(self._config, self.fetch,
                                                   require_client_authentication=self.client_ca is not None)


def tls_files(tls_cert: Optional[str], tls_key: Optional[str], tls_client_ca: Optional[str] = None) -> Optional[TlsFiles]:
    """:class:`TlsFiles` for the options, or ``None`` for plaintext.

    Raises:
        ValueError: only one of cert/key given, a client CA without TLS, unusable material.
        FileNotFoundError: a file is missing.
    """
    if not tls_cert and not tls_key:
        if tls_client_ca:
            raise ValueError("a TLS client CA (mutual TLS) needs TLS: give --tls-cert and --tls-key too")
        return None
    if not (tls_cert and tls_key):
        raise ValueError("TLS needs both a certificate and a key (--tls-cert and --tls-key)")
    return TlsFiles(tls_cert, tls_key, tls_client_ca)


def server_credentials(tls_cert: Optional[str], tls_key: Optional[str],
                       tls_client_ca: Optional[str] = None) -> Optional[grpc.ServerCredentials]:
    """TLS server credentials from PEM files (re-read when they change, :class:`TlsFiles`), or ``None``
    for plaintext.

    Raises:
        ValueError: only one of cert/key given, a client CA without TLS, unusable material.
        FileNotFoundError: a file is missing.
    """
    files = tls_files(tls_cert, tls_key, tls_client_ca)
    return files.credentials() if files is not None else None


def authenticator_from_options(options: "ServerOptions") -> Authenticator:
    """The :class:`~gausslite_services.common.auth.Authenticator` for ``options`` (token, token file, client CA).

    Raises:
        ValueError: a malformed fleet token or an invalid token file. OSError: unreadable token file.
    """
    tokens = AgentTokens(options.agent_tokens_file) if options.agent_tokens_file else None
    return Authenticator(options.token or None, tokens, mtls=bool(options.tls_client_ca),
                         fleet_writes=options.fleet_token_writes)


@dataclass
class RunningServer:
    """A started server: ``server`` (grpc.Server), bound ``port``, ``health`` servicer, ``address``;
    ``metrics``: the Prometheus endpoint (``.port``, ``.url``) or None; ``authenticator``: the
    credential rules; ``tls``: the TLS files (None for plaintext)."""

    server: grpc.Server
    port: int
    health: health.HealthServicer
    address: str
    service_names: List[str] = field(default_factory=list)
    grace_s: float = 5.0
    metrics: Optional[MetricsEndpoint] = None
    authenticator: Optional[Authenticator] = None
    tls: Optional[TlsFiles] = None

    def reload(self) -> None:
        """Re-read the per-agent token file now and the TLS files at the next handshake (SIGHUP)."""
        log.info("reloading credentials")
        if self.authenticator is not None:
            self.authenticator.reload()
        if self.tls is not None:
            self.tls.reload()

    def stop(self, grace_s: Optional[float] = None) -> None:
        """Mark NOT_SERVING, stop accepting calls and wait up to ``grace_s`` for in-flight ones."""
        self.health.enter_graceful_shutdown()
        self.server.stop(self.grace_s if grace_s is None else grace_s).wait()
        if self.metrics is not None:
            self.metrics.stop()


def build_server(
    options: ServerOptions,
    register: Callable[[grpc.Server], None],
    service_names: Iterable[str],
    registry: Optional[CollectorRegistry] = None,
    authenticator: Optional[Authenticator] = None,
) -> RunningServer:
    """Create, configure, bind and start a gRPC server.

    Args:
        options (ServerOptions): bind address, limits, credentials, TLS.
        register (Callable[[grpc.Server], None]): adds the service servicers to the server.
        service_names (Iterable[str]): full names (``gausslite.v1.Parser``) reported SERVING by the
            health service and listed by reflection.
        registry (CollectorRegistry | None): the service's Prometheus registry, served at
            ``options.metrics_port`` (an empty registry when None).
        authenticator (Authenticator | None): the credential rules (default:
            :func:`authenticator_from_options`); pass the one the service authorises with.
    Returns:
        RunningServer: started; ``port`` is the bound port.
    Raises:
        RuntimeError: the address (or the metrics port) could not be bound. ValueError /
            FileNotFoundError / OSError: bad TLS options, token or token file.
    """
    names = list(service_names)
    auth = authenticator if authenticator is not None else authenticator_from_options(options)
    tls = tls_files(options.tls_cert, options.tls_key, options.tls_client_ca)
    metrics = start_metrics_endpoint(registry or CollectorRegistry(), options.host, options.metrics_port)
    # authentication first, then request parsing (malformed messages: INVALID_ARGUMENT, not INTERNAL)
    interceptors = ([AuthInterceptor(auth, options.auth_exempt)] if auth.enabled else []) + [DecodeInterceptor()]
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=options.max_workers, thread_name_prefix="gausslite-rpc"),
        interceptors=interceptors,
        options=[
            ("grpc.max_receive_message_length", options.max_message_bytes),
            ("grpc.max_send_message_length", options.max_message_bytes),
            ("grpc.so_reuseport", 0),
            ("grpc.keepalive_time_ms", int(options.keepalive_s * 1000)),
            ("grpc.keepalive_timeout_ms", int(options.keepalive_timeout_s * 1000)),
            ("grpc.http2.min_ping_interval_without_data_ms", 10_000),
        ],
        maximum_concurrent_rpcs=options.max_concurrent_rpcs or 4 * options.max_workers,
    )
    register(server)
    health_servicer = health.HealthServicer(experimental_non_blocking=True)
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection(names + [HEALTH_SERVICE, reflection.SERVICE_NAME], server)
    address = f"{options.host}:{options.port}"
    creds = tls.credentials() if tls is not None else None
    try:
        port = server.add_secure_port(address, creds) if creds else server.add_insecure_port(address)
    except RuntimeError as e:
        if metrics is not None:
            metrics.stop()
        raise RuntimeError(f"cannot bind {address}: {e}") from e
    if port == 0:
        if metrics is not None:
            metrics.stop()
        raise RuntimeError(f"cannot bind {address}")
    server.start()
    for name in names + [""]:
        health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    log.info("serving %s on %s:%d (%s; %s)", ", ".join(names), options.host, port,
             ("mutual TLS" if tls.client_ca else "TLS") if tls is not None else "plaintext", auth.describe())
    return RunningServer(server, port, health_servicer, f"{options.host}:{port}", names, options.grace_s, metrics,
                         auth, tls)


def run_until_signalled(running: RunningServer, stop_event: Optional[threading.Event] = None) -> int:
    """Block until SIGTERM/SIGINT (or ``stop_event``), then shut down gracefully. Returns 0.

    SIGHUP calls ``running.reload()`` (when it has one; :meth:`RunningServer.reload`) within half a
    second. Signal handlers are only installed when called from the main thread.
    """
    stop = stop_event or threading.Event()
    hup = threading.Event()
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            previous[sig] = signal.signal(sig, lambda signum, frame: stop.set())
        if hasattr(signal, "SIGHUP") and callable(getattr(running, "reload", None)):
            previous[signal.SIGHUP] = signal.signal(signal.SIGHUP, lambda signum, frame: hup.set())
    try:
        while not stop.wait(0.5):
            if hup.is_set():
                hup.clear()
                try:
                    running.reload()
                except Exception:  # noqa: BLE001 - a failed reload must not stop the server
                    log.exception("reload failed")
        log.info("shutting down (grace %.1f s)", running.grace_s)
        running.stop()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
