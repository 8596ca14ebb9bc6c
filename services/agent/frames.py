"""``FrameMsg`` ⇄ :class:`gausslite.datasets.Frame` (clear INVALID_ARGUMENT for bad input).

Wire form of one posed RGB-D frame: colour as JPEG or PNG (8-bit RGB), depth as a single-channel
16-bit PNG with ``depth_scale`` metres per unit, ``c2w`` as 16 row-major doubles, pinhole intrinsics.
:func:`decode_frame` validates everything and raises :class:`FrameError` (a ``ValueError``) with a
message naming the problem; the server maps it to ``INVALID_ARGUMENT``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from gausslite.camera import Intrinsics, check_rigid
from gausslite.datasets.base import Frame
from gausslite.wire.images import jpeg_header, png_header
from gausslite_rpc import agent_pb2, common_pb2
from gausslite_services.common import convert
from gausslite_services.common.convert import intrinsics_to_proto
#: Largest depth of a valid pixel after scaling (metres); larger values are rejected as a bad scale.
MAX_DEPTH_M = 1000.0


class FrameError(ValueError):
    """A malformed ``FrameMsg`` (undecodable image, wrong shape, NaN pose, bad intrinsics...)."""


def intrinsics_from_proto(m: common_pb2.Intrinsics) -> Intrinsics:
    """Wire message → library intrinsics (:func:`gausslite_services.common.convert.intrinsics_from_proto`).

    Raises:
        FrameError: non-finite or non-positive focal lengths, an image side of 0 or above
            :data:`gausslite_services.common.convert.MAX_SIDE`.
    """
    try:
        return convert.intrinsics_from_proto(m)
    except ValueError as e:
        raise FrameError(f"intrinsics: {e}") from None


def encode_frame(frame: Frame, mission_id: str = "", color_format: str = ".png", jpeg_quality: int = 95,
                 depth_scale: float = 1.0 / 6553.5) -> agent_pb2.FrameMsg:
    """Encode a frame for ``StreamFrames``.

    Args:
        frame: the frame (rgb uint8 (H,W,3), depth float32 metres).
        mission_id: the mission it belongs to.
        color_format: ``.png`` (lossless) or ``.jpg``.
        depth_scale: metres per 16-bit unit (default 1/6553.5: 0.15 mm steps, up to 10 m).
    Raises:
        ValueError: depth beyond the 16-bit range for ``depth_scale``; encoding failure.
    """
    bgr = cv2.cvtColor(np.ascontiguousarray(frame.rgb), cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if color_format in (".jpg", ".jpeg") else []
    ok, col = cv2.imencode(color_format, bgr, params)
    d = np.asarray(frame.depth, dtype=np.float64) / depth_scale
    if np.nanmax(d, initial=0.0) > 65535.5:
        raise ValueError(f"depth up to {np.nanmax(frame.depth):.2f} m does not fit 16 bits at scale {depth_scale}")
    ok2, dep = cv2.imencode(".png", np.nan_to_num(d).round().clip(0, 65535).astype(np.uint16))
    if not (ok and ok2):
        raise ValueError("image encoding failed")
    return agent_pb2.FrameMsg(
        mission_id=mission_id, frame_id=int(frame.frame_id), timestamp=float(frame.timestamp),
        color=col.tobytes(), depth=dep.tobytes(), depth_scale=float(depth_scale),
        c2w=[float(v) for v in np.asarray(frame.c2w, dtype=np.float64).reshape(-1)],
        intrinsics=intrinsics_to_proto(frame.intrinsics))


def _check_meta(msg: agent_pb2.FrameMsg):
    """(frame id, Intrinsics, rigid c2w (4, 4) float64) of a message whose intrinsics, pose, depth scale
    and image presence are valid. Raises FrameError naming the problem."""
    fid = int(msg.frame_id)
    if not msg.HasField("intrinsics"):
        raise FrameError(f"frame {fid}: intrinsics missing")
    intr = intrinsics_from_proto(msg.intrinsics)
    W, H = intr.width, intr.height
    if len(msg.c2w) != 16:
        raise FrameError(f"frame {fid}: c2w must have 16 numbers (row-major 4x4), got {len(msg.c2w)}")
    c2w = np.asarray(msg.c2w, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(c2w)):
        raise FrameError(f"frame {fid}: c2w has NaN or infinite entries")
    try:
        c2w = check_rigid(c2w, atol=1e-3, what=f"frame {fid} c2w")
    except ValueError as e:
        raise FrameError(str(e)) from None
    if not (math.isfinite(msg.depth_scale) and msg.depth_scale > 0):
        raise FrameError(f"frame {fid}: depth_scale must be finite and > 0 (metres per unit), got {msg.depth_scale}")
    if not msg.color:
        raise FrameError(f"frame {fid}: colour image missing")
    if not msg.depth:
        raise FrameError(f"frame {fid}: depth image missing")
    return fid, intr, c2w


def decode_frame(msg: agent_pb2.FrameMsg) -> Frame:
    """Validate and decode one ``FrameMsg``.

    Returns:
        Frame with rgb (H,W,3) uint8, depth (H,W) float32 metres, c2w (4,4) float64.
    Raises:
        FrameError: missing/undecodable colour or depth, shapes that disagree with the intrinsics or each
            other, a depth PNG that is not 16-bit single-channel, a non-positive/non-finite depth scale,
            a pose that is not 16 finite numbers forming a rigid transform.
    """
    fid, intr, c2w = _check_meta(msg)
    W, H = intr.width, intr.height
    bgr = cv2.imdecode(np.frombuffer(msg.color, np.uint8), cv2.IMREAD_UNCHANGED)
    if bgr is None:
        raise FrameError(f"frame {fid}: colour bytes are not a decodable JPEG/PNG image")
    if bgr.dtype != np.uint8 or bgr.ndim != 3 or bgr.shape[2] not in (3, 4):
        raise FrameError(f"frame {fid}: colour must be 8-bit RGB, got dtype {bgr.dtype} shape {bgr.shape}")
    if bgr.shape[:2] != (H, W):
        raise FrameError(f"frame {fid}: colour is {bgr.shape[1]}x{bgr.shape[0]}, intrinsics say {W}x{H}")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGRA2RGB if bgr.shape[2] == 4 else cv2.COLOR_BGR2RGB)
    draw = cv2.imdecode(np.frombuffer(msg.depth, np.uint8), cv2.IMREAD_UNCHANGED)
    if draw is None:
        raise FrameError(f"frame {fid}: depth bytes are not a decodable PNG image")
    if draw.dtype != np.uint16 or draw.ndim != 2:
        raise FrameError(f"frame {fid}: depth must be a single-channel 16-bit PNG, got dtype {draw.dtype} "
                         f"shape {draw.shape}")
    if draw.shape != (H, W):
        raise FrameError(f"frame {fid}: depth is {draw.shape[1]}x{draw.shape[0]}, colour/intrinsics are {W}x{H}")
    depth = (draw.astype(np.float64) * msg.depth_scale).astype(np.float32)
    if float(depth.max(initial=0.0)) > MAX_DEPTH_M:
        raise FrameError(f"frame {fid}: depth up to {depth.max():.1f} m: wrong depth_scale?")
    if not np.any(depth > 0):
        raise FrameError(f"frame {fid}: depth has no valid (non-zero) pixel")
    return Frame(frame_id=fid, timestamp=float(msg.timestamp), rgb=np.ascontiguousarray(rgb), depth=depth,
                 c2w=c2w, intrinsics=intr, name=f"frame{fid:06d}")


@dataclass
class PendingFrame:
    """A validated, not yet decoded ``FrameMsg``: what keyframe selection needs (pose, intrinsics,
    timestamp, id) now, the images only if the frame becomes a keyframe (:meth:`materialize`).

    Attributes: frame_id (int), timestamp (float, s), c2w ((4, 4) float64), intrinsics (Intrinsics), msg.
    """

    frame_id: int
    timestamp: float
    c2w: np.ndarray
    intrinsics: Intrinsics
    msg: agent_pb2.FrameMsg

    def materialize(self) -> Frame:
        """Decode the images (:func:`decode_frame`). Raises FrameError for corrupt image data."""
        return decode_frame(self.msg)


def validate_frame(msg: agent_pb2.FrameMsg) -> PendingFrame:
    """Validate a ``FrameMsg`` without decoding its images: intrinsics, a finite rigid pose, the depth scale,
    and the image headers (colour: 8-bit JPEG with 3 components or 8-bit RGB/RGBA/palette PNG; depth:
    16-bit single-channel PNG; both of the intrinsics' size). Costs microseconds, so the accept path of a
    live stream stays far below a frame period; corrupt data behind a valid header is found by
    :meth:`PendingFrame.materialize`.

    Raises:
        FrameError: the same problems as :func:`decode_frame` reports from headers alone.
    """
    fid, intr, c2w = _check_meta(msg)
    W, H = intr.width, intr.height
    png = png_header(msg.color)
    if png is not None:
        cw, ch, bits, ctype = png
        if bits != 8 or ctype not in (2, 3, 6):
            raise FrameError(f"frame {fid}: colour must be 8-bit RGB, got a PNG of bit depth {bits} colour type {ctype}")
    else:
        jpg = jpeg_header(msg.color)
        if jpg is None:
            raise FrameError(f"frame {fid}: colour bytes are not a decodable JPEG/PNG image")
        cw, ch, bits, nc = jpg
        if bits != 8 or nc != 3:
            raise FrameError(f"frame {fid}: colour must be 8-bit RGB, got a JPEG of {bits} bits x {nc} components")
    if (cw, ch) != (W, H):
        raise FrameError(f"frame {fid}: colour is {cw}x{ch}, intrinsics say {W}x{H}")
    dh = png_header(msg.depth)
    if dh is None:
        raise FrameError(f"frame {fid}: depth bytes are not a decodable PNG image")
    dw, dhh, dbits, dtype = dh
    if dbits != 16 or dtype != 0:
        raise FrameError(f"frame {fid}: depth must be a single-channel 16-bit PNG, got bit depth {dbits} "
                         f"colour type {dtype}")
    if (dw, dhh) != (W, H):
        raise FrameError(f"frame {fid}: depth is {dw}x{dhh}, colour/intrinsics are {W}x{H}")
    return PendingFrame(fid, float(msg.timestamp), c2w, intr, msg)
