"""Errors of a mission: what its fusion client raises for the mission loop to act on, and what the mission raises
to its caller. :class:`PreconditionFailed` (a refused delta base) is defined in :mod:`gausslite.errors`, beside the
other library error types, and re-exported here."""

from __future__ import annotations

import errno

from gausslite.errors import ImageSizeError, PreconditionFailed

__all__ = ["PreconditionFailed", "MissionError", "FrameSizeMismatch", "stops_the_mission"]


class MissionError(RuntimeError):
    """The mission cannot accept the request (finished, failed, or replaying)."""


class FrameSizeMismatch(MissionError, ImageSizeError):
    """A frame's image size differs from the mission's first frame (a :class:`MissionError` and an
    :class:`gausslite.errors.ImageSizeError`: a bad argument, not a mission state)."""


#: errno values of a full disk or quota: nothing the next frame does can succeed either
_FULL = {errno.ENOSPC, errno.EDQUOT}


def stops_the_mission(e: BaseException) -> bool:
    """Whether ``e``, raised by one frame's step of a live mission (tracking, decoding, relevance, mapping, a loop
    closure's correction, an upload), must stop the mission rather than cost that frame alone: out of memory
    (``MemoryError``, PyTorch's ``OutOfMemoryError``) or a full disk (``OSError`` ENOSPC / EDQUOT). Any other
    error is one frame's: it is logged, counted (``frames_failed``) and the mission maps on (``docs/live.md``,
    "When a frame fails")."""
    if isinstance(e, MemoryError) or type(e).__name__ == "OutOfMemoryError":
        return True
    return isinstance(e, OSError) and e.errno in _FULL
