"""The server interceptors of the GaussLite gRPC services (:func:`gausslite_services.common.server.build_server` installs
them, and :mod:`gausslite_services.common.server` re-exports them):

* :class:`AuthInterceptor` authenticates every call (except health and reflection) with an
  :class:`~gausslite_services.common.auth.Authenticator`, a :class:`FailureLimiter` bounding the key derivations a
  peer host can cause; :class:`BearerTokenInterceptor` checks a single shared token only;
* :class:`DecodeInterceptor` parses request messages inside the call, so bytes that are not a valid message end the
  call with ``INVALID_ARGUMENT`` and a log line (:class:`MalformedMessage` in a client stream).
"""

from __future__ import annotations

import collections
import hmac
import logging
import threading
import time
from typing import Optional, Sequence

import grpc

from gausslite_services.common.auth import Authenticator, AuthError

log = logging.getLogger("gausslite_services.common.server")  # one logger for the server plumbing

__all__ = ["AuthInterceptor", "BearerTokenInterceptor", "DecodeInterceptor", "FailureLimiter", "MalformedMessage",
           "deny_handler", "decoding_handler", "peer_host"]


def deny_handler(handler: grpc.RpcMethodHandler, method: str, reason: str) -> grpc.RpcMethodHandler:
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
            return deny_handler(handler, method, "missing 'authorization: Bearer <token>' metadata")
        if not hmac.compare_digest(value.encode("utf-8"), self._expected):
            return deny_handler(handler, method, "invalid bearer token")
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
        return decoding_handler(handler, handler_call_details.method or "")


def decoding_handler(handler: grpc.RpcMethodHandler, method: str) -> grpc.RpcMethodHandler:
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
