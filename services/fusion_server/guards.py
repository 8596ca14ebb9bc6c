"""Request checks and status guards of the fusion service: every rejected call ends with a precise gRPC status
and a log line (``rejected <method> from <peer>: <code>: <reason>``), never a crash."""

from __future__ import annotations

import contextlib
import functools
import logging
import queue
import threading
import time
from typing import Dict, Iterator, Optional

import grpc
import numpy as np

from gausslite.camera import Intrinsics
from gausslite.wire import images
from gausslite_services.common import convert
from gausslite_services.common.auth import AGENT_ID_RE
from gausslite_services.common.server import MalformedMessage
from gausslite_services.fusion_server.store import StoreUnavailable

log = logging.getLogger("gausslite_services.fusion_server.server")  # one logger for the whole service

__all__ = ["Reject", "Cancelled", "UploadStreams", "abort_call", "unary_guard", "stream_guard", "check_int64", "check_agent_id",
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
    (:func:`gausslite_services.common.convert.intrinsics_from_proto`). Raises Reject(INVALID_ARGUMENT)."""
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


class _Stream:
    """One open upload stream: its caller, since when it has waited for its next message (None while its handler
    works on one), and whether it was evicted."""

    __slots__ = ("caller", "waiting_since", "evict")

    def __init__(self, caller: Optional[str]):
        self.caller = caller
        self.waiting_since: Optional[float] = time.monotonic()
        self.evict = threading.Event()


class UploadStreams:
    """Bounds on the client streams of uploads (``UploadSubset``, ``UploadKeyframes``), so a client that opens
    streams and stops sending cannot hold the server's handler threads, nor the upload slots other robots need.

    * **Idle deadline**: the stream's messages are read by a small reader thread into a queue of two; the handler
      waits for each at most ``idle_s`` seconds. When none arrives in time the call ends with DEADLINE_EXCEEDED
      (``no message of the UploadSubset stream for 15 s``), the handler thread is free again, and gRPC, having sent
      the status, ends the reader's wait. What was stored before the stall stays as after a dropped link: complete
      keyframes, and the chunks of an incomplete upload (invisible to ``Fuse``, resumable); never part of a message.
    * **Concurrency**: at most ``max_streams`` upload streams at once on the server, and ``per_caller`` per caller
      (the authenticated agent id; the peer host of a caller that may write nothing; callers that may write every
      agent's data, on an open server or with the team-wide fleet token, only count server-wide); beyond the
      per-caller bound a new upload is RESOURCE_EXHAUSTED at once. So stalled streams leave handler threads for the
      unary calls (acks, status, reads).
    * **Eviction**: when every server-wide slot is taken, a new upload takes the slot of the stream that has waited
      longest for its next message among those that have waited longer than ``evict_idle_s`` or belong to a caller
      holding at least two slots more than the new upload's caller (its fair share); the evicted call ends with
      ABORTED (its handler notices within a quarter second). A client sending its upload waits milliseconds between
      messages, so stalled streams are the ones evicted, and streams stalled by several identities cannot keep
      other robots from uploading. With no such stream the new upload is RESOURCE_EXHAUSTED.

    Args:
        max_streams (int): server-wide bound (keep it below the handler threads).
        per_caller (int): bound per caller.
        idle_s (float): longest wait for the next message of a stream, seconds.
        evict_idle_s (float): a stream waiting longer than this for its next message gives its slot to a new upload
            when the server-wide bound is reached, seconds.
    """

    def __init__(self, max_streams: int, per_caller: int, idle_s: float, evict_idle_s: float = 1.0):
        self.max_streams, self.per_caller, self.idle_s = int(max_streams), int(per_caller), float(idle_s)
        self.evict_idle_s = float(evict_idle_s)
        self._lock = threading.Lock()
        self._streams: "set[_Stream]" = set()
        self.deadline_exceeded = 0  #: streams ended by the idle deadline (for tests and metrics)
        self.evicted = 0  #: streams evicted for a new upload

    @property
    def active(self) -> int:
        """Upload streams holding a slot now."""
        with self._lock:
            return len(self._streams)

    def _take_slot(self, caller: Optional[str]) -> _Stream:
        """A slot for ``caller`` (under the lock): Reject(RESOURCE_EXHAUSTED) when none can be had."""
        mine = sum(1 for st in self._streams if st.caller == caller) if caller is not None else 0
        if mine >= self.per_caller:
            raise Reject(grpc.StatusCode.RESOURCE_EXHAUSTED, f"too many upload streams in progress ({self.per_caller} "
                         "from this caller); retry when one has finished")
        if len(self._streams) >= self.max_streams:
            now = time.monotonic()
            held: Dict[Optional[str], int] = {}
            for st in self._streams:
                held[st.caller] = held.get(st.caller, 0) + 1
            # waiting for a message, and either long enough, or of a caller holding more slots than its fair share
            idle = [st for st in self._streams if st.waiting_since is not None and (
                now - st.waiting_since >= self.evict_idle_s
                or (st.caller is not None and held[st.caller] >= mine + 2))]
            if not idle:
                raise Reject(grpc.StatusCode.RESOURCE_EXHAUSTED, f"too many upload streams in progress "
                             f"({self.max_streams} on this server); retry when one has finished")
            victim = min(idle, key=lambda st: st.waiting_since)
            victim.evict.set()
            self._streams.discard(victim)
            self.evicted += 1
        st = _Stream(caller)
        self._streams.add(st)
        return st

    @contextlib.contextmanager
    def open(self, request_iterator, context, method: str, caller: Optional[str]) -> Iterator[Iterator]:
        """Take a slot for ``caller`` (None: only the server-wide bound applies) and yield the stream's messages,
        each waited for at most ``idle_s``.

        Raises (into the handler, as :class:`Reject`): RESOURCE_EXHAUSTED when no slot is free; DEADLINE_EXCEEDED
        when the client sent nothing for ``idle_s``; ABORTED when a new upload took the slot of this stalled one;
        CANCELLED when the client cancelled the call or its deadline passed. A malformed message re-raises
        :class:`MalformedMessage` (the decode interceptor's status).
        """
        with self._lock:
            me = self._take_slot(caller)
        stop = threading.Event()
        items: "queue.Queue[tuple]" = queue.Queue(maxsize=2)  # bounded: gRPC's flow control still applies

        def put(item) -> bool:
            while not stop.is_set():
                try:
                    items.put(item, timeout=0.5)
                    return True
                except queue.Full:
                    continue
            return False

        def read() -> None:
            try:
                for msg in request_iterator:
                    if not put(("msg", msg)):
                        return
                put(("end", None))
            except BaseException as e:  # noqa: BLE001 - handed to the handler thread
                put(("error", e))

        reader = threading.Thread(target=read, name=f"gausslite-{method}-reader", daemon=True)
        reader.start()

        def messages():
            while True:
                me.waiting_since = time.monotonic()
                deadline = me.waiting_since + self.idle_s
                while True:
                    left = deadline - time.monotonic()
                    try:
                        kind, payload = items.get(timeout=max(0.0, min(0.25, left)))
                        break
                    except queue.Empty:
                        if me.evict.is_set():
                            raise Reject(grpc.StatusCode.ABORTED,
                                         f"no message of the {method} stream for {self.evict_idle_s:g} s while every "
                                         "upload slot of the server was taken: its slot went to another upload") from None
                        if not context.is_active():
                            raise Reject(grpc.StatusCode.CANCELLED, "the client cancelled the stream") from None
                        if time.monotonic() >= deadline:
                            with self._lock:
                                self.deadline_exceeded += 1
                            raise Reject(grpc.StatusCode.DEADLINE_EXCEEDED,
                                         f"no message of the {method} stream for {self.idle_s:g} s "
                                         "(the server's fusion.stream_idle_s)") from None
                me.waiting_since = None  # the handler works on a message: not idle
                if kind == "msg":
                    yield payload
                elif kind == "end":
                    return
                elif isinstance(payload, MalformedMessage):
                    raise payload
                elif isinstance(payload, grpc.RpcError):  # the client cancelled, or its own deadline passed
                    raise Reject(grpc.StatusCode.CANCELLED, "the client cancelled the stream") from None
                else:
                    raise payload

        try:
            yield messages()
        finally:
            stop.set()
            with self._lock:
                self._streams.discard(me)
