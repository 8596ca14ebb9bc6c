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

import collections
import hmac
import logging
import os
import signal
import ssl
import threading
import time
from concurrent import futures
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, List, Optional, Sequence, Tuple

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from gausslite_services.common.auth import AgentTokens, Authenticator, AuthError
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
    """Requires ``authorization: Bearer <token>`` call metadata (constant-time comparison).

    A single shared token only; :func:`build_server` uses :class:`AuthInterceptor`, which also knows
    per-agent tokens and client certificates.
    """

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


def peer_host(peer: str) -> str:
    """The host part of a gRPC peer string (``ipv4:10.0.0.7:51234`` → ``ipv4:10.0.0.7``; ``ipv6:[::1]:5`` →
    ``ipv6:[::1]``; anything else unchanged)."""
    head, sep, tail = (peer or "").rpartition(":")
    return head if sep and tail.isdigit() and head not in ("ipv4", "ipv6", "unix") else (peer or "")


class FailureLimiter:
    """Failed authentications per peer host in a sliding window. A wrong token costs a PBKDF2 derivation per token
    record (about 65 ms each): a client sending wrong tokens could keep the handler threads busy and starve the robots
    with valid ones. A host with ``max_failures`` failures in the last ``window_s`` seconds therefore gets only the
    cheap checks until the window has passed: tokens already verified, sha256 records and certificates still work (a
    robot behind the same address keeps working), an unknown token is refused without a key derivation.
    Failures count only once a check has ended, so a burst of wrong tokens sent at once would all be derived before
    the first failure counts: a host also gets at most ``max_in_flight`` costly checks at a time (:meth:`begin_costly`),
    and only the cheap checks beyond them.
    Thread-safe; memory bounded by ``max_hosts`` (oldest hosts forgotten first).
    """

    def __init__(self, max_failures: int = 20, window_s: float = 10.0, max_hosts: int = 4096,
                 max_in_flight: int = 4) -> None:
        self.max_failures, self.window_s, self.max_hosts = int(max_failures), float(window_s), int(max_hosts)
        self.max_in_flight = int(max_in_flight)
        self._lock = threading.Lock()
        self._hosts: "collections.OrderedDict[str, collections.deque]" = collections.OrderedDict()
        self._in_flight: dict = {}

    def begin_costly(self, host: str) -> bool:
        """Take one of ``host``'s slots for a check that may derive keys; False when all are taken (then only the
        cheap checks). Pair a True with :meth:`end_costly`."""
        with self._lock:
            n = self._in_flight.get(host, 0)
            if n >= self.max_in_flight:
                return False
            self._in_flight[host] = n + 1
            return True

    def end_costly(self, host: str) -> None:
        """Give back a slot taken by :meth:`begin_costly`."""
        with self._lock:
            n = self._in_flight.get(host, 1) - 1
            if n > 0:
                self._in_flight[host] = n
            else:
                self._in_flight.pop(host, None)

    def _recent(self, host: str, now: float):
        q = self._hosts.get(host)
        if q is None:
            return None
        while q and now - q[0] > self.window_s:
            q.popleft()
        return q

    def blocked(self, host: str) -> bool:
        """Whether ``host`` has used up its failures in the current window."""
        with self._lock:
            q = self._recent(host, time.monotonic())
            return q is not None and len(q) >= self.max_failures

    def failed(self, host: str) -> None:
        """Record one failed authentication of ``host``."""
        now = time.monotonic()
        with self._lock:
            q = self._recent(host, now)
            if q is None:
                q = self._hosts[host] = collections.deque(maxlen=self.max_failures)
            self._hosts.move_to_end(host)
            q.append(now)
            while len(self._hosts) > self.max_hosts:
                self._hosts.popitem(last=False)


class AuthInterceptor(grpc.ServerInterceptor):
    """Authenticates every call with an :class:`~gausslite_services.common.auth.Authenticator`.

    Each handler is wrapped so the check sees the call's context (metadata and the TLS auth context
    with the client certificate); a refused call is logged and aborted with the authenticator's
    status (``UNAUTHENTICATED``) before the service's handler runs.

    Args:
        authenticator (Authenticator): the credential rules.
        exempt_prefixes (Sequence[str]): method prefixes let through unauthenticated (health, reflection).
    """

    def __init__(self, authenticator: Authenticator, exempt_prefixes: Sequence[str] = (),
                 failures: Optional["FailureLimiter"] = None):
        self._auth = authenticator
        self._exempt = tuple(exempt_prefixes)
        self._failures = failures or FailureLimiter()

    def intercept_service(self, continuation, handler_call_details):
        method = handler_call_details.method or ""
        handler = continuation(handler_call_details)
        if handler is None or not self._auth.enabled or method.startswith(self._exempt):
            return handler
        if handler.request_streaming and handler.response_streaming:
            inner, make = handler.stream_stream, grpc.stream_stream_rpc_method_handler
        elif handler.request_streaming:
            inner, make = handler.stream_unary, grpc.stream_unary_rpc_method_handler
        elif handler.response_streaming:
            inner, make = handler.unary_stream, grpc.unary_stream_rpc_method_handler
        else:
            inner, make = handler.unary_unary, grpc.unary_unary_rpc_method_handler
        auth = self._auth
        failures = self._failures

        def guarded(request_or_iterator, context):
            host = peer_host(context.peer())
            # a host over its failure budget gets only the cheap checks (no key derivation for an unknown token)
            limited = failures.blocked(host)
            # ... and at most max_in_flight checks of one host may derive keys at a time
            costly = not limited and failures.begin_costly(host)
            try:
                auth.identify_context(context, cheap_only=not costly)
            except AuthError as e:
                failures.failed(host)
                msg = e.message
                if limited:
                    msg += (f" (too many failed authentications from this peer: only known credentials are "
                            f"checked for {failures.window_s:.0f} s)")
                elif not costly:
                    msg += (f" (more than {failures.max_in_flight} authentications from this peer in progress: "
                            "only known credentials are checked)")
                log.warning("rejected call %s from %s: %s: %s", method, context.peer(), e.code.name, msg)
                context.abort(e.code, msg)
            finally:
                if costly:
                    failures.end_costly(host)
            return inner(request_or_iterator, context)

        return make(guarded, request_deserializer=handler.request_deserializer,
                    response_serializer=handler.response_serializer)


class MalformedMessage(Exception):
    """Raised into a client-streaming handler by its request iterator when a message is not valid protobuf of
    the method's request type (:class:`DecodeInterceptor`; the call then ends with INVALID_ARGUMENT and the
    rejection is already logged): handlers re-raise it without logging a failure of their own."""


class DecodeInterceptor(grpc.ServerInterceptor):
    """Parses request messages in the handler instead of gRPC's own deserializer, so bytes that are not a
    valid message of the method's request type end the call with ``INVALID_ARGUMENT`` and a log line
    (gRPC reports a failed deserialization as ``INTERNAL``). Client streams are parsed lazily, message by
    message: a malformed message stops the handler's iteration, and the call ends with INVALID_ARGUMENT
    whatever the handler made of it. Place it after the authentication interceptor, so an unauthenticated
    caller learns nothing about its bytes."""

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        if handler is None or handler.request_deserializer is None:
            return handler
        return _decoding_handler(handler, handler_call_details.method or "")


def _decoding_handler(handler: grpc.RpcMethodHandler, method: str) -> grpc.RpcMethodHandler:
    """``handler`` with raw-bytes requests parsed by its own deserializer inside the call (DecodeInterceptor)."""
    parse = handler.request_deserializer
    kw = dict(request_deserializer=None, response_serializer=handler.response_serializer)

    def reject(context, err: BaseException) -> str:
        msg = f"malformed request message: {type(err).__name__}: {str(err)[:200]}"
        log.warning("rejected call %s from %s: INVALID_ARGUMENT: %s", method, context.peer(), msg)
        return msg

    def decode(raw, context):
        try:
            return parse(raw)
        except Exception as e:  # noqa: BLE001 - DecodeError and whatever a deserializer raises
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, reject(context, e))

    if not handler.request_streaming:
        if handler.response_streaming:
            def unary_stream(raw, context):
                yield from handler.unary_stream(decode(raw, context), context)

            return grpc.unary_stream_rpc_method_handler(unary_stream, **kw)

        def unary_unary(raw, context):
            return handler.unary_unary(decode(raw, context), context)

        return grpc.unary_unary_rpc_method_handler(unary_unary, **kw)

    def parsed(raw_iterator, context, bad: list):
        for raw in raw_iterator:
            try:
                msg = parse(raw)
            except Exception as e:  # noqa: BLE001
                bad.append(reject(context, e))
                raise MalformedMessage(bad[0]) from None
            yield msg

    if handler.response_streaming:
        def stream_stream(raw_iterator, context):
            bad: list = []
            try:
                yield from handler.stream_stream(parsed(raw_iterator, context, bad), context)
            except Exception:
                if bad:
                    context.abort(grpc.StatusCode.INVALID_ARGUMENT, bad[0])
                raise
            if bad:
                context.abort(grpc.StatusCode.INVALID_ARGUMENT, bad[0])

        return grpc.stream_stream_rpc_method_handler(stream_stream, **kw)

    def stream_unary(raw_iterator, context):
        bad: list = []
        try:
            out = handler.stream_unary(parsed(raw_iterator, context, bad), context)
        except Exception:
            if bad:  # the handler's own status (often INTERNAL for an unexpected exception) is replaced
                context.abort(grpc.StatusCode.INVALID_ARGUMENT, bad[0])
            raise
        if bad:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, bad[0])
        return out

    return grpc.stream_unary_rpc_method_handler(stream_unary, **kw)


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
