"""Decoding and encoding of ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` payloads.

Pure functions on raw fields (no ROS install, no message classes):

- Colour encodings: ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``, ``mono8`` → (H, W, 3) uint8 RGB
  (alpha dropped, grey replicated to three channels).
- Depth encodings (REP 118): ``16UC1`` (and its alias ``mono16``) in millimetres, ``32FC1`` in metres
  → (H, W) float32 metres, 0 = no measurement (0, NaN, ±inf and negative values all become 0).
- ``CompressedImage.format``: ``jpeg`` / ``png`` (optionally ``"<enc>; jpeg compressed <enc>"`` as
  ``compressed_image_transport`` writes it; OpenCV decodes to BGR which is converted to RGB), and
  image_transport's ``compressedDepth`` (``"16UC1; compressedDepth png"`` or ``"32FC1; compressedDepth"``):
  a 12-byte ``ConfigHeader`` (int32 format: 0 INV_DEPTH, 1 PNG, 2 RVL; two float32 depth
  quantisation parameters A, B; little endian) followed by a PNG. 16UC1: the PNG holds millimetres.
  32FC1: the PNG holds quantised inverse depth ``v`` with ``depth_m = A / (v - B)`` and ``v = 0``
  invalid (``compressed_depth_image_transport/codec.cpp``). RVL payloads are rejected with a clear error.

Errors are :class:`ImageDecodeError` (a ``ValueError``) naming the encoding and what is wrong.
"""

from __future__ import annotations

import struct
from typing import Tuple

import cv2
import numpy as np

__all__ = [
    "ImageDecodeError",
    "COLOR_ENCODINGS",
    "DEPTH_ENCODINGS",
    "decode_image",
    "decode_compressed",
    "encode_image",
    "encode_compressed",
    "encode_compressed_depth",
]

COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16UC1", "mono16", "32FC1")
_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "16UC1": 1, "mono16": 1, "32FC1": 1}
_DTYPES = {"16UC1": np.uint16, "mono16": np.uint16, "32FC1": np.float32}
_CONFIG_HEADER = struct.Struct("<iff")  # compressed_depth_image_transport ConfigHeader (12 bytes)
_FMT_INV_DEPTH, _FMT_PNG, _FMT_RVL = 0, 1, 2


class ImageDecodeError(ValueError):
    """An image message that cannot be decoded (unknown encoding, wrong size, corrupt payload)."""


def _to_rgb(arr: np.ndarray, order: str) -> np.ndarray:
    """(H, W[, C]) uint8 in ``order`` ("rgb", "bgr", "rgba", "bgra", "mono") → (H, W, 3) RGB."""
    if arr.ndim == 2 or order == "mono":
        g = arr if arr.ndim == 2 else arr[..., 0]
        return np.repeat(g[..., None], 3, axis=2)
    if order in ("bgr", "bgra"):
        return np.array(arr[..., 2::-1], order="C")  # a writable copy, never a view of the message buffer
    return np.array(arr[..., :3], order="C")


def _clean_depth(d: np.ndarray) -> np.ndarray:
    d = d.astype(np.float32, copy=True)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return d


def decode_image(encoding: str, height: int, width: int, step: int, data, is_bigendian: bool = False
                 ) -> Tuple[str, np.ndarray]:
    """Decode a ``sensor_msgs/Image``.

    Args:
        encoding: REP 118 encoding string (see the module docstring for the supported ones).
        height, width: pixels. step: bytes per row (>= width * bytes per pixel; padding is dropped).
        data: the ``data`` field (bytes or uint8 array). is_bigendian: byte order of 16/32-bit data.

    Returns:
        ``("color", (H, W, 3) uint8 RGB)`` or ``("depth", (H, W) float32 metres, 0 = invalid)``.

    Raises:
        ImageDecodeError: unknown encoding, zero size, or ``data`` shorter than ``height * step``.
    """
    enc = str(encoding)
    if enc not in _CHANNELS:
        raise ImageDecodeError(
            f"unsupported image encoding {enc!r}; supported: {', '.join(COLOR_ENCODINGS + DEPTH_ENCODINGS)}"
        )
    h, w, step = int(height), int(width), int(step)
    if h <= 0 or w <= 0:
        raise ImageDecodeError(f"{enc} image has size {w}x{h}")
    ch = _CHANNELS[enc]
    dt = np.dtype(_DTYPES.get(enc, np.uint8))
    row = w * ch * dt.itemsize
    if step < row:
        raise ImageDecodeError(f"{enc} {w}x{h} image: step {step} < {row} bytes per row")
    buf = np.frombuffer(memoryview(data), dtype=np.uint8) if not isinstance(data, np.ndarray) else data.view(np.uint8)
    if buf.size < h * step:
        raise ImageDecodeError(f"{enc} {w}x{h} image: {buf.size} bytes of data, expected {h * step}")
    rows = buf[: h * step].reshape(h, step)[:, :row]
    if dt.itemsize > 1:
        arr = np.ascontiguousarray(rows).view(dt.newbyteorder(">" if is_bigendian else "<")).reshape(h, w)
        arr = arr.astype(dt.newbyteorder("="))
        if enc == "32FC1":
            return "depth", _clean_depth(arr)
        return "depth", arr.astype(np.float32) / np.float32(1000.0)
    arr = rows.reshape(h, w, ch) if ch > 1 else rows.reshape(h, w)
    return "color", _to_rgb(arr, enc[:-1] if enc != "mono8" else "mono")


def decode_compressed(fmt: str, data) -> Tuple[str, np.ndarray]:
    """Decode a ``sensor_msgs/CompressedImage`` (``format`` + ``data``).

    Returns:
        ``("color", (H, W, 3) uint8 RGB)`` or ``("depth", (H, W) float32 metres, 0 = invalid)``.
        A plain 16-bit single-channel PNG is taken as depth in millimetres.

    Raises:
        ImageDecodeError: unknown format, RVL compressedDepth, undecodable payload.
    """
    f = str(fmt).strip()
    raw = bytes(data) if not isinstance(data, np.ndarray) else data.tobytes()
    low = f.lower()
    if "compresseddepth" in low:
        enc = f.split(";")[0].strip() or "16UC1"
        if enc not in ("16UC1", "32FC1"):
            raise ImageDecodeError(f"compressedDepth image with unsupported encoding {enc!r} (format {f!r})")
        if len(raw) <= _CONFIG_HEADER.size:
            raise ImageDecodeError(f"compressedDepth image of {len(raw)} bytes has no payload after its 12-byte header")
        kind, qa, qb = _CONFIG_HEADER.unpack_from(raw)
        if kind == _FMT_RVL or "rvl" in low:
            raise ImageDecodeError(f"compressedDepth RVL payloads are not supported (format {f!r}); record with png")
        img = cv2.imdecode(np.frombuffer(raw, np.uint8, offset=_CONFIG_HEADER.size), cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2 or img.dtype != np.uint16:
            raise ImageDecodeError(f"compressedDepth payload is not a 16-bit single-channel PNG (format {f!r})")
        if enc == "16UC1":
            return "depth", img.astype(np.float32) / np.float32(1000.0)
        v = img.astype(np.float32)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = np.where(img > 0, np.float32(qa) / (v - np.float32(qb)), np.float32(0.0))
        return "depth", _clean_depth(d)
    if not any(k in low for k in ("jpeg", "jpg", "png")):
        raise ImageDecodeError(f"unsupported CompressedImage format {f!r}; supported: jpeg, png, compressedDepth")
    img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageDecodeError(f"CompressedImage ({f!r}): OpenCV could not decode {len(raw)} bytes")
    if img.dtype == np.uint16 and img.ndim == 2:
        return "depth", img.astype(np.float32) / np.float32(1000.0)
    if img.dtype != np.uint8:
        raise ImageDecodeError(f"CompressedImage ({f!r}): unsupported pixel type {img.dtype}")
    order = "mono" if img.ndim == 2 else ("bgra" if img.shape[2] == 4 else "bgr")
    return "color", _to_rgb(img, order)


def encode_image(arr: np.ndarray, encoding: str) -> Tuple[int, int, int, bytes]:
    """Encode an image as ``sensor_msgs/Image`` fields (little endian).

    Args:
        arr: colour (H, W, 3) uint8 RGB for ``rgb8``/``bgr8``/``rgba8``/``bgra8``/``mono8`` (mono: the
            mean of the channels, or a (H, W) array), or depth (H, W) float metres for ``16UC1``
            (rounded to millimetres, clipped to 65.535 m, 0 = invalid) / ``32FC1``.
        encoding: target encoding.

    Returns:
        ``(height, width, step, data)``.

    Raises:
        ImageDecodeError: unsupported encoding or wrong array shape.
    """
    enc = str(encoding)
    a = np.asarray(arr)
    if enc in ("16UC1", "mono16", "32FC1"):
        if a.ndim != 2:
            raise ImageDecodeError(f"{enc} needs an (H, W) depth array, got shape {a.shape}")
        d = np.nan_to_num(a.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
        out = (np.clip(np.round(d * 1000.0), 0, 65535).astype("<u2") if enc != "32FC1" else d.astype("<f4"))
    elif enc in COLOR_ENCODINGS:
        if a.ndim == 2:
            a = np.repeat(a[..., None], 3, axis=2)
        if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
            raise ImageDecodeError(f"{enc} needs an (H, W, 3) uint8 RGB array, got {a.dtype} {a.shape}")
        if enc == "mono8":
            out = np.round(a.astype(np.float32).mean(axis=2)).astype(np.uint8)
        else:
            out = a[..., ::-1] if enc.startswith("bgr") else a
            if enc.endswith("a8"):
                out = np.concatenate([out, np.full(a.shape[:2] + (1,), 255, np.uint8)], axis=2)
    else:
        raise ImageDecodeError(f"cannot encode {enc!r}")
    out = np.ascontiguousarray(out)
    h, w = out.shape[:2]
    return h, w, out.nbytes // h, out.tobytes()


def encode_compressed(rgb: np.ndarray, fmt: str = "jpeg", quality: int = 95) -> Tuple[str, bytes]:
    """Encode (H, W, 3) uint8 RGB as a ``CompressedImage`` (``fmt`` ``jpeg`` or ``png``).

    Returns:
        ``(format string as compressed_image_transport writes it, data)``.
    """
    if fmt not in ("jpeg", "png"):
        raise ImageDecodeError(f"cannot compress to {fmt!r}; use jpeg or png")
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if fmt == "jpeg" else []
    ok, buf = cv2.imencode("." + ("jpg" if fmt == "jpeg" else "png"), np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise ImageDecodeError(f"OpenCV could not encode {fmt}")
    return f"rgb8; {fmt} compressed bgr8", buf.tobytes()


def encode_compressed_depth(depth: np.ndarray, encoding: str = "16UC1",
                            depth_max: float = 10.0, depth_quantization: float = 100.0) -> Tuple[str, bytes]:
    """Encode (H, W) depth in metres as image_transport ``compressedDepth`` (ConfigHeader + PNG).

    ``16UC1``: millimetres in the PNG. ``32FC1``: quantised inverse depth as
    ``compressed_depth_image_transport`` writes it: ``A = q (q + 1)``, ``B = 1 - A / depth_max`` with
    ``q = depth_quantization``, ``v = A / d + B`` for ``0 < d < depth_max`` metres, else 0.

    Returns:
        ``(format string, data)``.
    """
    d = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if encoding == "16UC1":
        img = np.clip(np.round(d * 1000.0), 0, 65535).astype(np.uint16)
        header = _CONFIG_HEADER.pack(_FMT_PNG, 0.0, 0.0)
    elif encoding == "32FC1":
        qa = depth_quantization * (depth_quantization + 1.0)
        qb = 1.0 - qa / depth_max
        with np.errstate(divide="ignore"):
            v = np.where((d > 0) & (d < depth_max), qa / np.maximum(d, 1e-9) + qb, 0.0)
        img = np.clip(np.round(v), 0, 65535).astype(np.uint16)
        header = _CONFIG_HEADER.pack(_FMT_INV_DEPTH, qa, qb)
    else:
        raise ImageDecodeError(f"compressedDepth supports 16UC1 and 32FC1, not {encoding!r}")
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise ImageDecodeError("OpenCV could not encode the depth PNG")
    return f"{encoding}; compressedDepth png", header + buf.tobytes()
