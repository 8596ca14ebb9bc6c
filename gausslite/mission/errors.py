"""Errors of a mission: what its fusion client raises for the mission loop to act on, and what the mission raises
to its caller."""

from __future__ import annotations

from gausslite.errors import ImageSizeError

__all__ = ["PreconditionFailed", "MissionError", "FrameSizeMismatch"]


class MissionError(RuntimeError):
    """The mission cannot accept the request (finished, failed, or replaying)."""


class FrameSizeMismatch(MissionError, ImageSizeError):
    """A frame's image size differs from the mission's first frame (a :class:`MissionError` and an
    :class:`gausslite.errors.ImageSizeError`: a bad argument, not a mission state)."""


class PreconditionFailed(Exception):
    """The fusion side refused a call because of its state (for a delta push: it does not hold the delta's base).
    The mission then uploads the full subset. The gRPC client's ``FailedPrecondition`` is one."""
