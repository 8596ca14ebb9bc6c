"""Image codecs of keyframes on the wire: colour (JPEG or lossless PNG), metric depth (16-bit PNG with a scale)
and task ROI masks (8-bit PNG), encoded by the agents' clients and decoded by the fusion server
(``proto/gausslite_rpc/fusion.proto``, ``KeyframeRequest``). OpenCV does the compression; colour arrays are RGB.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["DEFAULT_DEPTH_SCALE", "encode_depth_png", "encode_color_jpeg", "encode_color_png", "encode_roi_png",
           "decode_color", "decode_roi", "decode_depth"]

#: depth PNG units per metre (0.2 mm steps, up to 13.1 m); deeper frames get a coarser scale
DEFAULT_DEPTH_SCALE = 5000.0


def encode_depth_png(depth: np.ndarray) -> tuple[bytes, float]:
    """Encode metric depth as a 16-bit PNG.

    Args:
        depth: (H, W) float depth in metres, 0 / non-finite = invalid.
    Returns:
        (png bytes, depth_scale) with metres = value / depth_scale. The scale is
        :data:`DEFAULT_DEPTH_SCALE` unless the largest depth needs a coarser one (then
        65535 / max depth).
    Raises:
        ValueError: not a 2-D array, or PNG encoding failed.
    """
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {d.shape}")
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
    dmax = float(d.max()) if d.size else 0.0
    scale = DEFAULT_DEPTH_SCALE if dmax * DEFAULT_DEPTH_SCALE <= 65535 else 65535.0 / dmax
    q = np.clip(np.round(d * scale), 0, 65535).astype(np.uint16)
    ok, buf = cv2.imencode(".png", q)
    if not ok:
        raise ValueError("PNG encoding of depth failed")
    return buf.tobytes(), float(scale)


def encode_color_jpeg(rgb: np.ndarray, quality: int = 95) -> bytes:
    """Encode an (H, W, 3) uint8 RGB image as JPEG. Raises ValueError on bad input."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"rgb must be (H, W, 3), got {a.shape}")
    if a.dtype != np.uint8:
        a = np.clip(a * (255.0 if a.dtype.kind == "f" else 1.0), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(a, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def encode_color_png(rgb: np.ndarray) -> bytes:
    """Encode an (H, W, 3) uint8 RGB image as lossless PNG. Raises ValueError on bad input."""
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise ValueError(f"rgb must be (H, W, 3) uint8, got {a.shape} {a.dtype}")
    ok, buf = cv2.imencode(".png", cv2.cvtColor(a, cv2.COLOR_RGB2BGR))
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def encode_roi_png(roi: np.ndarray) -> bytes:
    """Encode an (H, W) bool ROI mask as an 8-bit single-channel PNG (0 / 255). Raises ValueError on bad input."""
    a = np.asarray(roi)
    if a.ndim != 2:
        raise ValueError(f"roi must be (H, W), got {a.shape}")
    ok, buf = cv2.imencode(".png", a.astype(bool).astype(np.uint8) * 255)
    if not ok:
        raise ValueError("PNG encoding of the ROI failed")
    return buf.tobytes()


_JPEG_MAGIC = b"\xff\xd8\xff"
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def decode_color(data: bytes, what: str) -> np.ndarray:
    """Decode a JPEG/PNG colour image to (H, W, 3) uint8 RGB. Raises ValueError naming ``what``."""
    if not (data.startswith(_JPEG_MAGIC) or data.startswith(_PNG_MAGIC)):
        raise ValueError(f"{what}: colour is neither JPEG nor PNG")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"{what}: undecodable colour image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def decode_roi(data: bytes, size: tuple, what: str) -> np.ndarray:
    """Decode an 8-bit single-channel PNG ROI mask to (H, W) bool (nonzero = ROI) and check its size
    ``(H, W)``. Raises ValueError naming ``what``."""
    if not data.startswith(_PNG_MAGIC):
        raise ValueError(f"{what}: roi_png is not a PNG")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"{what}: roi_png must be a single-channel 8-bit PNG")
    if img.shape != tuple(size):
        raise ValueError(f"{what}: roi_png is {img.shape[1]}x{img.shape[0]}, the keyframe {size[1]}x{size[0]}")
    return img > 0


def decode_depth(data: bytes, scale: float, what: str) -> np.ndarray:
    """Decode a 16-bit PNG depth image to (H, W) float32 metres. Raises ValueError naming ``what``."""
    if not data.startswith(_PNG_MAGIC):
        raise ValueError(f"{what}: depth is not a PNG")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.dtype != np.uint16:
        raise ValueError(f"{what}: depth must be a single-channel 16-bit PNG")
    return (img.astype(np.float32) / np.float32(scale)).astype(np.float32)
