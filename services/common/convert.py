"""Library types ⇄ the shared messages of ``proto/gausslite_rpc/common.proto``, for clients and servers alike."""

from __future__ import annotations

from gausslite_rpc import common_pb2


def intrinsics_to_proto(intr) -> common_pb2.Intrinsics:
    """:class:`gausslite.camera.Intrinsics` (or any object with fx, fy, cx, cy in pixels and width, height) →
    ``common.Intrinsics``."""
    return common_pb2.Intrinsics(fx=float(intr.fx), fy=float(intr.fy), cx=float(intr.cx), cy=float(intr.cy),
                                 width=int(intr.width), height=int(intr.height))


__all__ = ["intrinsics_to_proto"]
