"""Library types ⇄ the shared messages of ``proto/gausslite_rpc/common.proto``, for clients and servers alike."""

from __future__ import annotations

from gausslite.camera import Intrinsics
from gausslite.errors import ImageSizeError
from gausslite_rpc import common_pb2

#: Largest image side (pixels) a message may declare: a larger one is refused before any buffer is sized by it.
MAX_SIDE = 8192


def intrinsics_to_proto(intr) -> common_pb2.Intrinsics:
    """:class:`gausslite.camera.Intrinsics` (or any object with fx, fy, cx, cy in pixels and width, height) →
    ``common.Intrinsics``."""
    return common_pb2.Intrinsics(fx=float(intr.fx), fy=float(intr.fy), cx=float(intr.cx), cy=float(intr.cy),
                                 width=int(intr.width), height=int(intr.height))


def intrinsics_from_proto(m: common_pb2.Intrinsics) -> Intrinsics:
    """``common.Intrinsics`` (pixels) → :class:`gausslite.camera.Intrinsics`, validated.

    Raises:
        ValueError: non-finite or non-positive focal lengths, a non-finite principal point, or (an
            :class:`gausslite.errors.ImageSizeError`) an image side of 0 or above :data:`MAX_SIDE`. The agent
            answers it as a rejected frame, the fusion server as INVALID_ARGUMENT.
    """
    if not (0 < m.width <= MAX_SIDE and 0 < m.height <= MAX_SIDE):
        raise ImageSizeError(f"image size {m.width}x{m.height} outside 1..{MAX_SIDE}")
    return Intrinsics(float(m.fx), float(m.fy), float(m.cx), float(m.cy), int(m.width), int(m.height))


__all__ = ["MAX_SIDE", "intrinsics_from_proto", "intrinsics_to_proto"]
