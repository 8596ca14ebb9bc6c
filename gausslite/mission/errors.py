"""Errors of a mission: what its fusion client raises for the mission loop to act on, and what the mission raises
to its caller. :class:`PreconditionFailed` (a refused delta base) is defined in :mod:`gausslite.errors`, beside the
other library error types, and re-exported here."""

from __future__ import annotations

from gausslite.errors import ImageSizeError, PreconditionFailed

__all__ = ["PreconditionFailed", "MissionError", "FrameSizeMismatch"]


class MissionError(RuntimeError):
    """The mission cannot accept the request (finished, failed, or replaying)."""


class FrameSizeMismatch(MissionError, ImageSizeError):
    """A frame's image size differs from the mission's first frame (a :class:`MissionError` and an
    :class:`gausslite.errors.ImageSizeError`: a bad argument, not a mission state)."""
