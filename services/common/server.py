"""gRPC server plumbing shared by the parser, agent and fusion services.

* :func:`build_server` — a ``grpc.server`` with bounded message sizes, the standard health service
  (``grpc.health.v1.Health``) and server reflection, an optional bearer-token interceptor, bound to
  ``host:port`` (port 0 → an ephemeral port) with or without TLS.
* :class:`BearerTokenInterceptor` — per-call ``authorization: Bearer <token>`` metadata; missing or
  wrong token → ``UNAUTHENTICATED``; every rejected call is logged.
* :func:`run_until_signalled` — blocks until SIGTERM/SIGINT, then marks health NOT_SERVING and stops
  the server with a grace period so in-flight calls finish.
* Prometheus: with ``ServerOptions.metrics_port`` set, :func:`build_server` also serves the service's
  own registry at ``http://host:metrics_port/metrics`` (:mod:`services.common.metrics`); it stops
  with the server.
"""

from __future__ import annotations

import hmac
import logging
import signal
import threading
from concurrent import futures
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, List, Optional, Sequence, Tuple

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from services.common.metrics import CollectorRegistry, MetricsEndpoint, start_metrics_endpoint

log = logging.getLogger(__name__)

HEALTH_SERVICE = "grpc.health.v1.Health"
REFLECTION_SERVICES = ("grpc.reflection.v1alpha.ServerReflection", "grpc.reflection.v1.ServerReflection")


@dataclass
class ServerOptions:
    """Options common to every GaussLite gRPC server.

    Attributes:
        host (str): bind address (``127.0.0.1`` loopback; ``0.0.0.0`` for all interfaces).
        port (int): TCP port; 0 binds an ephemeral port (see :attr:`RunningServer.port`).
        token (str | None): when set, every call (except health/reflection) must carry
            ``authorization: Bearer <token>`` metadata.
        tls_cert (str | None), tls_key (str | None): PEM paths; both set → TLS, neither → plaintext.
        max_message_bytes (int): bound on received and sent messages.
        max_workers (int): handler threads.
        grace_s (float): shutdown grace period for in-flight calls.
        auth_exempt (tuple[str, ...]): method-name prefixes that need no token.
        metrics_port (int | None): Prometheus ``/metrics`` HTTP port on ``host``; None = off, 0 = an
            ephemeral port (see :attr:`RunningServer.metrics`). The CLI maps ``--metrics-port 0`` to None.
    """

    host: str = "127.0.0.1"
    port: int = 0
    token: Optional[str] = None
    tls_cert: Optional[str] = None
    tls_key: Optional[str] = None
    max_message_bytes: int = 4 * 1024 * 1024
    max_workers: int = 8
    grace_s: float = 5.0
    auth_exempt: Tuple[str, ...] = (f"/{HEALTH_SERVICE}/",) + tuple(f"/{s}/" for s in REFLECTION_SERVICES)
    metrics_port: Optional[int] = None


def _deny_handler(handler: grpc.RpcMethodHandler, method: str, reason: str) -> grpc.RpcMethodHandler:
    """A handler of the same streaming kind as ``handler`` that aborts with UNAUTHENTICATED."""

    def abort(request_or_iterator, context):
        log.warning("rejected call %s from %s: %s", method, context.peer(), reason)
        context.abort(grpc.StatusCode.UNAUTHENTICATED, reason)

    kw = dict(request_deserializer=handler.request_deserializer, response_serializer=handler.response_serializer)
    if handler.request_streaming and handler.response_streaming:
        return grpc.stream_stream_rpc_method_handler(abort, **kw)
    if handler.request_streaming:
        return grpc.stream_unary_rpc_method_handler(abort, **kw)
    if handler.response_streaming:
        return grpc.unary_stream_rpc_method_handler(abort, **kw)
    return grpc.unary_unary_rpc_method_handler(abort, **kw)


class BearerTokenInterceptor(grpc.ServerInterceptor):
    """Requires ``authorization: Bearer <token>`` call metadata (constant-time comparison)."""

    def __init__(self, token: str, exempt_prefixes: Sequence[str] = ()):
        """Args:
            token (str): the shared secret (non-empty).
            exempt_prefixes (Sequence[str]): method prefixes let through without a token.
        Raises:
            ValueError: empty token.
        """
        if not token:
            raise ValueError("bearer token must be non-empty")
        self._expected = f"Bearer {token}".encode("utf-8")
        self._exempt = tuple(exempt_prefixes)

    def intercept_service(self, continuation, handler_call_details):
        method = handler_call_details.method or ""
        if method.startswith(self._exempt):
            return continuation(handler_call_details)
        value = None
        for key, val in handler_call_details.invocation_metadata or ():
            if key.lower() == "authorization":
                value = val if isinstance(val, str) else val.decode("utf-8", "replace")
                break
        handler = continuation(handler_call_details)
        if handler is None:
            return None
        if value is None:
            return _deny_handler(handler, method, "missing 'authorization: Bearer <token>' metadata")
        if not hmac.compare_digest(value.encode("utf-8"), self._expected):
            return _deny_handler(handler, method, "invalid bearer token")
        return handler


def server_credentials(tls_cert: Optional[str], tls_key: Optional[str]) -> Optional[grpc.ServerCredentials]:
    """TLS server credentials from PEM files, or ``None`` for plaintext.

    Raises:
        ValueError: only one of cert/key given. FileNotFoundError: a file is missing.
    """
    if not tls_cert and not tls_key:
        return None
    if not (tls_cert and tls_key):
        raise ValueError("TLS needs both a certificate and a key (--tls-cert and --tls-key)")
    cert = Path(tls_cert).read_bytes()
    key = Path(tls_key).read_bytes()
    return grpc.ssl_server_credentials([(key, cert)])


@dataclass
class RunningServer:
    """A started server: ``server`` (grpc.Server), bound ``port``, ``health`` servicer, ``address``;
    ``metrics``: the Prometheus endpoint (``.port``, ``.url``) or None."""

    server: grpc.Server
    port: int
    health: health.HealthServicer
    address: str
    service_names: List[str] = field(default_factory=list)
    grace_s: float = 5.0
    metrics: Optional[MetricsEndpoint] = None

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
) -> RunningServer:
    """Create, configure, bind and start a gRPC server.

    Args:
        options (ServerOptions): bind address, limits, token, TLS.
        register (Callable[[grpc.Server], None]): adds the service servicers to the server.
        service_names (Iterable[str]): full names (``gausslite.v1.Parser``) reported SERVING by the
            health service and listed by reflection.
        registry (CollectorRegistry | None): the service's Prometheus registry, served at
            ``options.metrics_port`` (an empty registry when None).
    Returns:
        RunningServer: started; ``port`` is the bound port.
    Raises:
        RuntimeError: the address (or the metrics port) could not be bound. ValueError /
            FileNotFoundError: bad TLS options.
    """
    names = list(service_names)
    metrics = start_metrics_endpoint(registry or CollectorRegistry(), options.host, options.metrics_port)
    interceptors = []
    if options.token:
        interceptors.append(BearerTokenInterceptor(options.token, options.auth_exempt))
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=options.max_workers, thread_name_prefix="gausslite-rpc"),
        interceptors=interceptors,
        options=[
            ("grpc.max_receive_message_length", options.max_message_bytes),
            ("grpc.max_send_message_length", options.max_message_bytes),
            ("grpc.so_reuseport", 0),
        ],
    )
    register(server)
    health_servicer = health.HealthServicer(experimental_non_blocking=True)
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    reflection.enable_server_reflection(names + [HEALTH_SERVICE, reflection.SERVICE_NAME], server)
    address = f"{options.host}:{options.port}"
    creds = server_credentials(options.tls_cert, options.tls_key)
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
    log.info("serving %s on %s:%d (%s%s)", ", ".join(names), options.host, port, "TLS" if creds else "plaintext",
             ", token required" if options.token else "")
    return RunningServer(server, port, health_servicer, f"{options.host}:{port}", names, options.grace_s, metrics)


def run_until_signalled(running: RunningServer, stop_event: Optional[threading.Event] = None) -> int:
    """Block until SIGTERM/SIGINT (or ``stop_event``), then shut down gracefully. Returns 0.

    Signal handlers are only installed when called from the main thread.
    """
    stop = stop_event or threading.Event()
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            previous[sig] = signal.signal(sig, lambda signum, frame: stop.set())
    try:
        while not stop.wait(0.5):
            pass
        log.info("shutting down (grace %.1f s)", running.grace_s)
        running.stop()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0
