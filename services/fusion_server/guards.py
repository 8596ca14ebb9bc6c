"""Request checks and status guards of the fusion service: every rejected call ends with a precise gRPC status
and a log line (``rejected <method> from <peer>: <code>: <reason>``), never a crash."""

from __future__ import annotations

import functools
import logging
from typing import Optional

import grpc
import numpy as np

from gausslite.camera import Intrinsics
from gausslite.wire import images
from services.common import convert
from services.common.auth import AGENT_ID_RE
from services.common.server import MalformedMessage
from services.fusion_server.store import StoreUnavailable

log = logging.getLogger("services.fusion_server.server")  # one logger for the whole service

__all__ = ["Reject", "Cancelled", "abort_call", "unary_guard", "stream_guard", "check_int64", "check_agent_id",
           "intrinsics_from_proto", "decode_color", "decode_roi", "decode_depth", "MAX_VERSION"]


class Reject(Exception):
    """Abort the call with ``code`` (``grpc.StatusCode``) and ``message`` (raised inside a guarded method)."""

    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


class Cancelled(Exception):
    """The Fuse call was cancelled (client cancel, deadline, shutdown)."""


def abort_call(context, method: str, code: grpc.StatusCode, message: str):
    """Log the rejection (method, peer, status, reason) and end the call with ``code``."""
    log.warning("rejected %s from %s: %s: %s", method, context.peer(), code.name, message)
    context.abort(code, message)


def _as_reject(e: Exception, method: str) -> Reject:
    """The status a handler's exception ends its call with: its own (:class:`Reject`), UNAVAILABLE for a database
    that is down or restarting (transient: the client retries), otherwise INTERNAL with the cause logged."""
    if isinstance(e, Reject):
        return e
    if isinstance(e, StoreUnavailable):
        return Reject(grpc.StatusCode.UNAVAILABLE, str(e))
    log.exception("%s failed", method)
    return Reject(grpc.StatusCode.INTERNAL, f"internal error: {type(e).__name__}: {e}")


def unary_guard(fn):
    """Translate :class:`Reject` and unexpected errors of a unary-response handler into statuses."""

    @functools.wraps(fn)
    def wrapper(self, request, context):
        try:
            return fn(self, request, context)
        except MalformedMessage:  # already logged; DecodeInterceptor ends the call with INVALID_ARGUMENT
            raise
        except Exception as e:  # noqa: BLE001 - never crash: a precise status, or INTERNAL with the cause logged
            err = _as_reject(e, fn.__name__)
        abort_call(context, fn.__name__, err.code, err.message)

    return wrapper


def stream_guard(fn):
    """Like :func:`unary_guard` for server-streaming handlers (generators)."""

    @functools.wraps(fn)
    def wrapper(self, request, context):
        try:
            yield from fn(self, request, context)
            return
        except MalformedMessage:  # already logged; DecodeInterceptor ends the call with INVALID_ARGUMENT
            raise
        except Exception as e:  # noqa: BLE001 - never crash: a precise status, or INTERNAL with the cause logged
            err = _as_reject(e, fn.__name__)
        abort_call(context, fn.__name__, err.code, err.message)

    return wrapper


MAX_VERSION = 2**63 - 1  #: versions are stored as signed 64-bit integers (SQLite, PostgreSQL BIGINT)


def check_int64(value: int, what: str) -> int:
    """A uint64 field of a request (versions, counts) as an int. Raises Reject(INVALID_ARGUMENT) above
    :data:`MAX_VERSION` (the database stores signed 64-bit integers)."""
    v = int(value)
    if v > MAX_VERSION:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"{what} {v} exceeds {MAX_VERSION}")
    return v


def check_agent_id(agent_id: str) -> str:
    """Validate an agent id (1..64 chars of ``[A-Za-z0-9_.-]``). Raises Reject(INVALID_ARGUMENT)."""
    if not isinstance(agent_id, str) or not AGENT_ID_RE.match(agent_id):
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT,
                     f"invalid agent_id {agent_id[:80]!r}: need 1..64 characters of [A-Za-z0-9_.-]")
    return agent_id


def intrinsics_from_proto(msg, what: str) -> Intrinsics:
    """``common.Intrinsics`` (pixels) as :class:`gausslite.camera.Intrinsics`
    (:func:`services.common.convert.intrinsics_from_proto`). Raises Reject(INVALID_ARGUMENT)."""
    try:
        return convert.intrinsics_from_proto(msg)
    except ValueError as e:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, f"{what}: {e}") from None


def decode_color(data: bytes, what: str, size: Optional[tuple] = None) -> np.ndarray:
    """:func:`gausslite.wire.images.decode_color` (``size`` (H, W): checked from the header before decoding); raises
    Reject(INVALID_ARGUMENT)."""
    return _image(images.decode_color, data, what, size)


def decode_roi(data: bytes, size: tuple, what: str) -> np.ndarray:
    """:func:`gausslite.wire.images.decode_roi`; raises Reject(INVALID_ARGUMENT)."""
    return _image(images.decode_roi, data, size, what)


def decode_depth(data: bytes, scale: float, what: str, size: Optional[tuple] = None) -> np.ndarray:
    """:func:`gausslite.wire.images.decode_depth` (``size`` (H, W): checked from the header before decoding); raises
    Reject(INVALID_ARGUMENT)."""
    return _image(images.decode_depth, data, scale, what, size)


def _image(fn, *args):
    try:
        return fn(*args)
    except ValueError as e:
        raise Reject(grpc.StatusCode.INVALID_ARGUMENT, str(e)) from None
