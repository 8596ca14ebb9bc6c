"""Niantic's ``.spz`` splat format, encoded and decoded with numpy (SH degree 0 written; higher bands skipped on read).

Two containers hold the same packed sections:

* gzip (versions 2 and 3; written as version 3): one gzip stream of a 16-byte header — magic ``NGSP``
  (``0x5053474E``), version, point count (uint32 each), SH degree, fractional bits, flags, reserved (uint8 each) —
  then the sections one after another;
* version 4: a 32-byte header — magic, version, point count (uint32), SH degree, fractional bits, flags, stream
  count (uint8), the table's byte offset (uint32), 12 reserved bytes — a table of (compressed, uncompressed) uint64
  sizes, then each non-empty section as a zstd stream of its own.

Sections, per Gaussian, little-endian:

==========  ==============  ==========================================================================
positions   3 × 24 bits     signed fixed point, metres × 2^fractional_bits
alphas      1 byte          round(sigmoid(opacity logit) · 255)
colors      3 bytes         round(SH DC · 0.15 · 255 + 127.5)
scales      3 bytes         round((log-scale + 10) · 16)
rotations   4 bytes (v≥3)   smallest three of the unit quaternion (x, y, z, w), largest made positive: its index
                            in the top 2 bits, then per other component 1 sign bit and 9 bits of
                            |q| / √½ · 511, the first component in the highest bits
            3 bytes (v2)    round((q + 1) · 127.5) of x, y, z with w ≥ 0
sh          3 · K bytes     higher SH bands (K = 3, 8, 15 for degree 1..3): round(c · 128 + 128)
==========  ==============  ==========================================================================

Version 1 (float16 positions) is refused.
"""

from __future__ import annotations

import gzip
import struct
import zlib
from typing import Dict

import numpy as np

#: ``NGSP`` as a little-endian uint32
MAGIC = 0x5053474E
#: SH coefficients per colour channel beyond the DC term, by SH degree
SH_REST = {0: 0, 1: 3, 2: 8, 3: 15}
#: the colour section's scale of the SH DC term
COLOR_SCALE = 0.15
#: the version :func:`encode_spz` writes
WRITE_VERSION = 3
_SQRT1_2 = float(np.sqrt(0.5))
_MAG = 511  # 9 bits


def _pack_quats(q_xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) float quaternions (x, y, z, w) → (N, 4) uint8 smallest-three codes."""
    n = len(q_xyzw)
    q = np.asarray(q_xyzw, np.float32)  # normalised in float32, the magnitudes rounded in float64
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)
    sign = np.sign(q[np.arange(n), largest])
    q = q * np.where(sign == 0, np.float32(1), sign)[:, None]
    packed = np.zeros(n, np.uint32)
    for axis in range(4):
        keep = largest != axis
        mag = np.clip(np.round(_MAG * np.abs(q[:, axis]).astype(np.float64) / _SQRT1_2), 0, _MAG).astype(np.uint32)
        code = (packed << np.uint32(10)) | ((q[:, axis] < 0).astype(np.uint32) << np.uint32(9)) | mag
        packed = np.where(keep, code, packed)
    packed |= largest.astype(np.uint32) << np.uint32(30)
    return packed.astype("<u4").view(np.uint8).reshape(n, 4)


def _unpack_quats(codes: np.ndarray) -> np.ndarray:
    """(N, 4) uint8 smallest-three codes → (N, 4) float32 unit quaternions (x, y, z, w)."""
    packed = np.ascontiguousarray(codes).view("<u4").reshape(-1).astype(np.uint32)
    largest = (packed >> np.uint32(30)) & np.uint32(3)
    q = np.zeros((len(packed), 4), np.float64)
    work = packed.copy()
    for axis in range(3, -1, -1):
        other = largest != axis
        val = _SQRT1_2 * (work & np.uint32(_MAG)).astype(np.float64) / _MAG
        val = np.where((work >> np.uint32(9)) & np.uint32(1), -val, val)
        q[:, axis] = np.where(other, val, 0.0)
        work = np.where(other, work >> np.uint32(10), work)
    rest = np.maximum(0.0, 1.0 - (q * q).sum(axis=1))
    q[np.arange(len(q)), largest] = np.sqrt(rest)
    return q.astype(np.float32)


def encode_spz(means: np.ndarray, log_scales: np.ndarray, quats_wxyz: np.ndarray, opacity_logits: np.ndarray,
               sh_dc: np.ndarray, fractional_bits: int = 12) -> bytes:
    """A version-3 ``.spz`` file (gzip container, SH degree 0) of N Gaussians.

    Args:
        means: (N, 3) metres; log_scales: (N, 3) natural-log standard deviations; quats_wxyz: (N, 4), any norm > 0;
        opacity_logits: (N,); sh_dc: (N, 3) SH DC colour coefficients. Finite float arrays.
        fractional_bits: bits of the positions' fixed point (1..23); 12 = 1/4096 m.
    Returns:
        The file's bytes (the gzip header's time is 0, so equal inputs give equal bytes).
    Raises:
        ValueError: mismatched shapes, fractional_bits out of range, or positions beyond the 24-bit range.
    """
    n = len(means)
    shapes = {"means": (means, 3), "log_scales": (log_scales, 3), "quats_wxyz": (quats_wxyz, 4), "sh_dc": (sh_dc, 3)}
    for name, (a, width) in shapes.items():
        if np.shape(a) != (n, width):
            raise ValueError(f"{name} must be ({n}, {width}), got {np.shape(a)}")
    if np.shape(opacity_logits) != (n,):
        raise ValueError(f"opacity_logits must be ({n},), got {np.shape(opacity_logits)}")
    if not 1 <= fractional_bits <= 23:
        raise ValueError(f"fractional_bits must be in 1..23, got {fractional_bits}")
    fixed = np.round(np.asarray(means, np.float64) * (1 << fractional_bits)).astype(np.int64)
    if n and np.abs(fixed).max() >= 1 << 23:
        raise ValueError(f"positions beyond ±{(1 << 23) / (1 << fractional_bits):g} m do not fit {fractional_bits} "
                         "fractional bits of a 24-bit position")
    pos = (fixed & 0xFFFFFF).astype("<u4").view(np.uint8).reshape(n, 3, 4)[:, :, :3]
    alpha = 1.0 / (1.0 + np.exp(-np.asarray(opacity_logits, np.float64)))
    sections = [
        pos,
        np.clip(np.round(alpha * 255.0), 0, 255).astype(np.uint8),
        np.clip(np.round(np.asarray(sh_dc, np.float64) * (COLOR_SCALE * 255.0) + 127.5), 0, 255).astype(np.uint8),
        np.clip(np.round((np.asarray(log_scales, np.float64) + 10.0) * 16.0), 0, 255).astype(np.uint8),
        _pack_quats(np.roll(np.asarray(quats_wxyz), -1, axis=1)),
    ]
    header = struct.pack("<IIIBBBB", MAGIC, WRITE_VERSION, n, 0, fractional_bits, 0, 0)
    return gzip.compress(header + b"".join(np.ascontiguousarray(s).tobytes() for s in sections), 6, mtime=0)


def _gzip_payload(data: bytes) -> tuple:
    """(version, n, sh degree, fractional bits, the sections' bytes) of a gzip-container file."""
    try:
        raw = gzip.decompress(data)
    except (OSError, EOFError, zlib.error) as e:
        raise ValueError(f"not a readable SPZ gzip stream: {e}") from e
    if len(raw) < 16:
        raise ValueError(f"SPZ payload of {len(raw)} bytes is shorter than its 16-byte header")
    magic, version, n, degree, bits, _flags, _ = struct.unpack_from("<IIIBBBB", raw)
    if magic != MAGIC:
        raise ValueError(f"not an SPZ file (magic 0x{magic:08x})")
    return version, n, degree, bits, raw[16:]


def _zstd_payload(data: bytes) -> tuple:
    """(version, n, sh degree, fractional bits, the sections' bytes) of a version-4 (zstd streams) file."""
    import zstandard

    if len(data) < 32:
        raise ValueError(f"SPZ file of {len(data)} bytes is shorter than its 32-byte header")
    _, version, n, degree, bits, _flags, streams, toc = struct.unpack_from("<IIIBBBBI", data)
    if toc < 32 or toc + 16 * streams > len(data):
        raise ValueError("SPZ stream table lies outside the file")
    out, at = [], toc + 16 * streams
    for i in range(streams):
        packed, size = struct.unpack_from("<QQ", data, toc + 16 * i)
        if at + packed > len(data):
            raise ValueError(f"SPZ stream {i} runs past the end of the file")
        try:
            out.append(zstandard.ZstdDecompressor().decompress(data[at:at + packed], max_output_size=size))
        except zstandard.ZstdError as e:
            raise ValueError(f"SPZ stream {i} is not a readable zstd stream: {e}") from e
        at += packed
    return version, n, degree, bits, b"".join(out)


def decode_spz(data: bytes) -> Dict[str, np.ndarray]:
    """The Gaussians of a ``.spz`` file (versions 2 to 4); higher SH bands are read past and dropped.

    Returns:
        ``means`` (N, 3), ``log_scales`` (N, 3), ``quats_wxyz`` (N, 4) unit, ``opacity_logits`` (N,) (alphas of 0
        and 255 clamped to 1e-6 from 0 and 1), ``sh_dc`` (N, 3); float32.
    Raises:
        ValueError: not an SPZ file, version 1 or above 4, an SH degree above 3, fractional bits outside 1..23, or
            fewer bytes than the header's point count needs.
    """
    if data[:2] == b"\x1f\x8b":
        version, n, degree, bits, raw = _gzip_payload(data)
        if version not in (2, 3):
            raise ValueError(f"SPZ version {version} in a gzip container is not read (versions 2 and 3 are)")
    elif len(data) >= 4 and struct.unpack_from("<I", data)[0] == MAGIC:
        version, n, degree, bits, raw = _zstd_payload(data)
        if version != 4:
            raise ValueError(f"SPZ version {version} without gzip is not read (version 4 is)")
    else:
        raise ValueError("not an SPZ file (neither a gzip stream nor the NGSP magic)")
    if degree not in SH_REST or not 1 <= bits <= 23:
        raise ValueError(f"SPZ header out of range: SH degree {degree} (0..3), fractional bits {bits} (1..23)")
    rot = 4 if version >= 3 else 3
    need = n * (9 + 1 + 3 + 3 + rot + 3 * SH_REST[degree])
    if len(raw) < need:
        raise ValueError(f"SPZ sections of {len(raw)} bytes, {need} needed for {n} Gaussians")
    buf = np.frombuffer(raw, np.uint8, count=n * (16 + rot))
    p = buf[:9 * n].reshape(n, 3, 3).astype(np.int32)
    fixed = p[..., 0] | (p[..., 1] << 8) | (p[..., 2] << 16)
    fixed = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed)
    alpha = np.clip(buf[9 * n:10 * n].astype(np.float64) / 255.0, 1e-6, 1 - 1e-6)
    codes = buf[16 * n:].reshape(n, rot)
    if rot == 4:
        q_xyzw = _unpack_quats(codes)
    else:
        xyz = codes.astype(np.float64) / 127.5 - 1.0
        q_xyzw = np.concatenate([xyz, np.sqrt(np.maximum(0.0, 1.0 - (xyz * xyz).sum(1)))[:, None]], 1)
    return {"means": (fixed / float(1 << bits)).astype(np.float32),
            "log_scales": (buf[13 * n:16 * n].reshape(n, 3) / 16.0 - 10.0).astype(np.float32),
            "quats_wxyz": np.roll(q_xyzw, 1, axis=1).astype(np.float32),
            "opacity_logits": np.log(alpha / (1.0 - alpha)).astype(np.float32),
            "sh_dc": ((buf[10 * n:13 * n].reshape(n, 3) / 255.0 - 0.5) / COLOR_SCALE).astype(np.float32)}


__all__ = ["MAGIC", "SH_REST", "COLOR_SCALE", "WRITE_VERSION", "encode_spz", "decode_spz"]
