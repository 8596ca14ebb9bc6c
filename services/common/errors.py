"""Typed errors of the GaussLite gRPC clients.

Every failed call of :class:`gausslite_services.fusion_server.client.FusionClient` and
:class:`gausslite_services.agent.client.AgentClient` raises a subclass of :class:`RpcStatusError` chosen by the server's
status code, so callers catch what they handle (``except FailedPrecondition:``) instead of comparing status names. They
are ``grpc.RpcError`` subclasses with the same ``code()`` and ``details()``, so code written against plain gRPC errors
keeps working.
"""

from __future__ import annotations

import functools
import inspect
from typing import Dict, Tuple, Type

import grpc

from gausslite.errors import (CapacityExceeded, ExtraUnavailable, ImageSizeError, PreconditionFailed,
                              RelevanceUnavailable)
from gausslite.mission.errors import MissionError

__all__ = ["status_for", "LIBRARY_STATUSES",
           "RpcStatusError", "InvalidArgument", "NotFound", "AlreadyExists", "FailedPrecondition",
           "PermissionDenied", "Unauthenticated", "ResourceExhausted", "Unavailable", "DeadlineExceeded",
           "Cancelled", "Internal", "typed_error", "raises_typed_errors"]


class RpcStatusError(grpc.RpcError):
    """A failed call: the server's (or the channel's) status ``code()`` and ``details()``.

    Args:
        code: the ``grpc.StatusCode``. details: the status message. method: the client method that failed.
    """

    status = grpc.StatusCode.UNKNOWN

    def __init__(self, code: grpc.StatusCode, details: str, method: str = "") -> None:
        super().__init__(f"{method + ': ' if method else ''}{code.name}: {details}")
        self._code, self._details, self.method = code, details, method

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return self._details


def _status(code: grpc.StatusCode, *bases: type) -> Type[RpcStatusError]:
    return type(code.name.title().replace("_", ""), (RpcStatusError, *bases), {"status": code, "__module__": __name__})


InvalidArgument = _status(grpc.StatusCode.INVALID_ARGUMENT)
NotFound = _status(grpc.StatusCode.NOT_FOUND)
AlreadyExists = _status(grpc.StatusCode.ALREADY_EXISTS)
#: also the mission loop's :class:`gausslite.errors.PreconditionFailed` (a delta push without its base)
FailedPrecondition = _status(grpc.StatusCode.FAILED_PRECONDITION, PreconditionFailed)
PermissionDenied = _status(grpc.StatusCode.PERMISSION_DENIED)
Unauthenticated = _status(grpc.StatusCode.UNAUTHENTICATED)
ResourceExhausted = _status(grpc.StatusCode.RESOURCE_EXHAUSTED)
Unavailable = _status(grpc.StatusCode.UNAVAILABLE)
DeadlineExceeded = _status(grpc.StatusCode.DEADLINE_EXCEEDED)
Cancelled = _status(grpc.StatusCode.CANCELLED)
Internal = _status(grpc.StatusCode.INTERNAL)

_BY_CODE: Dict[grpc.StatusCode, Type[RpcStatusError]] = {
    c.status: c for c in (InvalidArgument, NotFound, AlreadyExists, FailedPrecondition, PermissionDenied,
                          Unauthenticated, ResourceExhausted, Unavailable, DeadlineExceeded, Cancelled, Internal)}


def typed_error(e: grpc.RpcError, method: str = "") -> RpcStatusError:
    """The typed error of a raw ``grpc.RpcError`` (itself when it is one already)."""
    if isinstance(e, RpcStatusError):
        return e
    code = e.code() if callable(getattr(e, "code", None)) else grpc.StatusCode.UNKNOWN
    details = e.details() if callable(getattr(e, "details", None)) else str(e)
    return _BY_CODE.get(code, RpcStatusError)(code, details or "", method)


def raises_typed_errors(cls):
    """Class decorator: every public method (and generator method) of ``cls`` re-raises ``grpc.RpcError`` as its
    :func:`typed_error`."""
    for name, fn in list(vars(cls).items()):
        if name.startswith("_") or not inspect.isfunction(fn):
            continue
        if inspect.isgeneratorfunction(fn):
            @functools.wraps(fn)
            def gen(*a, _fn=fn, **k):
                try:
                    yield from _fn(*a, **k)
                except RpcStatusError:
                    raise
                except grpc.RpcError as e:
                    raise typed_error(e, _fn.__name__) from e
            setattr(cls, name, gen)
        else:
            @functools.wraps(fn)
            def call(*a, _fn=fn, **k):
                try:
                    return _fn(*a, **k)
                except RpcStatusError:
                    raise
                except grpc.RpcError as e:
                    raise typed_error(e, _fn.__name__) from e
            setattr(cls, name, call)
    return cls


#: the gRPC status of each library exception type, most specific first (:func:`status_for` takes the first match)
LIBRARY_STATUSES: Tuple[Tuple[Type[BaseException], grpc.StatusCode], ...] = (
    (ImageSizeError, grpc.StatusCode.INVALID_ARGUMENT),  # also a mission's FrameSizeMismatch
    (RelevanceUnavailable, grpc.StatusCode.FAILED_PRECONDITION),
    (ExtraUnavailable, grpc.StatusCode.FAILED_PRECONDITION),  # a feature of an extra this install lacks
    (MissionError, grpc.StatusCode.FAILED_PRECONDITION),
    (PreconditionFailed, grpc.StatusCode.FAILED_PRECONDITION),  # also gausslite.fusion.uploads' version checks
    (CapacityExceeded, grpc.StatusCode.RESOURCE_EXHAUSTED),
    (ValueError, grpc.StatusCode.INVALID_ARGUMENT),
)


def status_for(e: BaseException, default: grpc.StatusCode = grpc.StatusCode.INTERNAL) -> grpc.StatusCode:
    """The gRPC status a server answers for the library exception ``e``, chosen by its type
    (:data:`LIBRARY_STATUSES`), never by its message; ``default`` when no entry matches."""
    for cls, code in LIBRARY_STATUSES:
        if isinstance(e, cls):
            return code
    return default

