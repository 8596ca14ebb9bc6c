"""Exception types of the library that callers tell apart by type, never by message text.

The services map each type to a gRPC status in one place (``services/common/errors.py``, ``status_for``).
"""

from __future__ import annotations

__all__ = ["ImageSizeError", "RelevanceUnavailable", "PreconditionFailed", "CapacityExceeded", "ExtraUnavailable"]


class ImageSizeError(ValueError):
    """An image's size (width x height, pixels) is out of range or differs from the size expected (e.g. the
    first frame of a mission). A bad argument: the agent answers INVALID_ARGUMENT."""


class RelevanceUnavailable(ValueError):
    """The configured relevance source cannot be built: scene annotations, a task id or the ONNX models it needs
    are missing (``gausslite.mission.relevance.build_relevance``). A matter of the agent's configuration rather
    than of the request: the agent answers FAILED_PRECONDITION."""


class PreconditionFailed(Exception):
    """A call was refused because of the callee's state, not because of its arguments: for a delta push, the fusion
    side does not hold the delta's base (``gausslite.fusion.uploads.MissingDeltaBase``), or a newer complete version
    supersedes the upload (``gausslite.fusion.uploads.SupersededVersion``). The services answer
    FAILED_PRECONDITION; the mission then uploads the full subset. The gRPC client's ``FailedPrecondition`` is one.
    Also importable as ``gausslite.mission.errors.PreconditionFailed``."""


class CapacityExceeded(Exception):
    """A request would make the callee hold more than a configured bound allows (e.g. a delta that rebuilds a subset
    above the fusion server's ``fusion.max_subset_gaussians``). Not a malformed argument: the services answer
    RESOURCE_EXHAUSTED."""


class ExtraUnavailable(RuntimeError):
    """A feature needs an optional extra of the package that is not installed here (``gausslite.core.extras``; e.g.
    the fusion server's refinement on a light install without torch). A matter of the installation rather than of
    the request: the services answer FAILED_PRECONDITION.

    Args:
        message: what cannot run, the extra it needs and how to install it.
        extra: the extra's name (``mapper``, ``fusion``).
        missing: the top-level modules not found.
    """

    def __init__(self, message: str, extra: str = "", missing: tuple = ()) -> None:
        super().__init__(message)
        self.extra = extra
        self.missing = tuple(missing)
