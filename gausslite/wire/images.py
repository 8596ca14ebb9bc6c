"""Image codecs of keyframes on the wire: colour (JPEG or lossless PNG), metric depth (16-bit PNG with a scale)
and task ROI masks (8-bit PNG), encoded by the agents' clients and decoded by the fusion server
(``proto/gausslite_rpc/fusion.proto``, ``KeyframeRequest``). OpenCV does the compression; colour arrays are RGB.
"""

from __future__ import annotations

import struct
from typing import Optional

import cv2
import numpy as np

__all__ = ["DEFAULT_DEPTH_SCALE", "encode_depth_png", "encode_color_jpeg", "encode_color_png", "encode_roi_png",
           "decode_color", "decode_roi", "decode_depth", "png_header", "jpeg_header", "image_size"]

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


def png_header(data: bytes) -> Optional[tuple[int, int, int, int]]:
    """(width, height, bit depth, colour type) of a PNG from its IHDR chunk, or None if not a PNG."""
    if len(data) < 26 or data[:8] != _PNG_MAGIC or data[12:16] != b"IHDR":
        return None
    w, h = struct.unpack(">II", data[16:24])
    return w, h, data[24], data[25]


_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def jpeg_header(data: bytes) -> Optional[tuple[int, int, int, int]]:
    """(width, height, precision, components) from a JPEG's start-of-frame segment, or None."""
    if len(data) < 4 or data[:2] != b"\xff\xd8":
        return None
    i, n = 2, len(data)
    while i + 4 <= n:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        seg = struct.unpack(">H", data[i + 2:i + 4])[0]
        if marker in _SOF:
            if i + 10 > n:
                return None
            prec, h, w, nc = struct.unpack(">BHHB", data[i + 4:i + 10])
            return w, h, prec, nc
        if marker == 0xDA or seg < 2:  # scan data before any frame header
            return None
        i += 2 + seg
    return None


def image_size(data: bytes) -> Optional[tuple[int, int]]:
    """(height, width) a PNG or JPEG declares in its header, read without decoding; None without a readable one."""
    h = png_header(data) or jpeg_header(data)
    return None if h is None else (int(h[1]), int(h[0]))


def _check_size(data: bytes, size: Optional[tuple], what: str, name: str) -> None:
    """Compare the header's size with ``size`` (H, W) *before* decoding: a small file can declare a huge image
    (a decompression bomb: a 1 MB PNG of 20000x20000 pixels decodes to 1.2 GB)."""
    if size is None:
        return
    got = image_size(data)
    if got is None:
        raise ValueError(f"{what}: {name} has no readable image header")
    if got != tuple(int(x) for x in size):
        raise ValueError(f"{what}: {name} is {got[1]}x{got[0]}, expected {size[1]}x{size[0]}")


def decode_color(data: bytes, what: str, size: Optional[tuple] = None) -> np.ndarray:
    """Decode a JPEG/PNG colour image to (H, W, 3) uint8 RGB; with ``size`` (H, W) the header's size is checked
    first, before anything is decoded. Raises ValueError naming ``what``."""
    if not (data.startswith(_JPEG_MAGIC) or data.startswith(_PNG_MAGIC)):
        raise ValueError(f"{what}: colour is neither JPEG nor PNG")
    _check_size(data, size, what, "colour")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"{what}: undecodable colour image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def decode_roi(data: bytes, size: tuple, what: str) -> np.ndarray:
    """Decode an 8-bit single-channel PNG ROI mask to (H, W) bool (nonzero = ROI) and check its size
    ``(H, W)``. Raises ValueError naming ``what``."""
    if not data.startswith(_PNG_MAGIC):
        raise ValueError(f"{what}: roi_png is not a PNG")
    _check_size(data, size, what, "roi_png")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"{what}: roi_png must be a single-channel 8-bit PNG")
    if img.shape != tuple(size):
        raise ValueError(f"{what}: roi_png is {img.shape[1]}x{img.shape[0]}, the keyframe {size[1]}x{size[0]}")
    return img > 0


def decode_depth(data: bytes, scale: float, what: str, size: Optional[tuple] = None) -> np.ndarray:
    """Decode a 16-bit PNG depth image to (H, W) float32 metres; with ``size`` (H, W) the header's size is checked
    first, before anything is decoded. Raises ValueError naming ``what``."""
    if not data.startswith(_PNG_MAGIC):
        raise ValueError(f"{what}: depth is not a PNG")
    _check_size(data, size, what, "depth")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.dtype != np.uint16:
        raise ValueError(f"{what}: depth must be a single-channel 16-bit PNG")
    return (img.astype(np.float32) / np.float32(scale)).astype(np.float32)
