"""Exception types of the library that callers tell apart by type, never by message text.

The services map each type to a gRPC status in one place (``services/common/errors.py``, ``status_for``).
"""

from __future__ import annotations

__all__ = ["ImageSizeError", "RelevanceUnavailable"]


class ImageSizeError(ValueError):
    """An image's size (width x height, pixels) is out of range or differs from the size expected (e.g. the
    first frame of a mission). A bad argument: the agent answers INVALID_ARGUMENT."""


class RelevanceUnavailable(ValueError):
    """The configured relevance source cannot be built: scene annotations, a task id or the ONNX models it needs
    are missing (``gausslite.mission.relevance.build_relevance``). A matter of the agent's configuration rather
    than of the request: the agent answers FAILED_PRECONDITION."""
