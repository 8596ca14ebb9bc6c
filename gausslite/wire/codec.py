"""Wire codec for Gaussian subsets: versioned, chunked, quantised, zstd-compressed, checksummed.

Source: paper Sec. III-E ("Multi-Agent Refinement": agents exchange only their ROI subset with the
per-Gaussian active-optimisation count κ). Subsets travel as chunked, zstd-compressed, versioned binary blocks
with per-chunk checksums; upload is resumable and idempotent by (agent id, map version, chunk index).
Byte layout: ``docs/wire-format.md``.

Everything here is numpy; torch is only touched when converting from/to
:class:`gausslite.gaussians.GaussianMap`.

Chunk layout (format version 3, all integers little-endian)
-----------------------------------------------------------
The normative, language-neutral specification is ``docs/wire-format.md`` (with golden vectors in
``tests/data/wire``); summary::

    off  size  field
      0     4  magic b"GLWC"
      4     2  u16 format version (= 3; format 2 chunks are still decoded, κ shift 0)
      6     2  u16 flags: bit0 lossless, bit1 byte-plane shuffle, bit2 delta; other bits must be 0
      8     8  u64 map version
     16     4  u32 chunk index (0-based)
     20     4  u32 chunk count (>= 1)
     24     8  u64 total Gaussian (record) count of the subset / delta
     32     4  u32 Gaussian count n of this chunk
     36     2  u16 agent id length L (1..limits.max_agent_id_bytes)
     38     1  u8  mean bytes per axis (quantised: 1..4; lossless: 0)
     39     1  u8  quaternion bits per smallest-three component (quantised: 4..20; lossless: 0)
     40     1  u8  log-scale bits (quantised: 1..16; lossless: 0)
     41     1  u8  opacity bits (quantised: 1..16; lossless: 0)
     42     1  u8  colour bits (quantised: 1..16; lossless: 0)
     43     1  u8  κ bytes (zigzag, 0..8; 0 means all κ are 0)
     44     2  u16 κ shift s (delta only, else 0; format 2: reserved, 0): every kept, unreplaced
               base row with the task flag set gets κ + s when the delta is applied
     46    24  3 x f64 mean origin (metres; quantised only, else 0)
     70    24  3 x f64 mean step (metres per code; quantised only, else 0)
     94     8  2 x f32 log-scale range lo, hi (quantised only)
    102     8  2 x f32 colour range lo, hi (quantised only)
    110     4  u32 raw (decompressed) payload length; must equal the sum of the section lengths
    114     4  u32 compressed payload length P
    118     8  u64 delta base version (delta only, < map version; else 0)
    126     8  u64 delta base row count (delta only; else 0)
    134     4  u32 removed rows in this chunk r (delta only; else 0)
    138     4  u32 predict mask: bit i = field i (means, quats, log_scales, opacity, colors, kappa)
               is coded as zigzagged wrapped row-to-row differences (quantised only, bits 0..5)
    142     L  agent id, UTF-8
    142+L   P  payload: per section, u32 compressed length then one zstd frame (with content size)
    142+L+P 4  u32 CRC-32 (zlib.crc32) of every preceding byte of the chunk

Raw payload = the following sections in order; each field is a (C, n) array of unsigned integers
(C components) written with ``w`` bytes per value; with the shuffle flag the bytes are written as
byte planes (component-major, then byte significance, then Gaussian), otherwise component-major with
each value's ``w`` bytes contiguous:

=============  ==  =========================================  ======================================
field           C  quantised encoding                          lossless encoding
=============  ==  =========================================  ======================================
means           3  fixed point ``round((x-origin)/step)``,     float32 bits (w = 4)
                   w = mean bytes
quats           1  smallest-three: 2-bit index of the largest  4 components, float32 bits (C = 4)
                   |component| + 3 x b-bit components,
                   w = ceil((2 + 3b) / 8)
log_scales      3  affine over [lo, hi], w = ceil(bits / 8)    float32 bits
opacity         1  ``round(sigmoid(logit) * (2^bits - 1))``    float32 bits of the logit
colors          3  affine over [lo, hi]                        float32 bits
kappa           1  zigzag(κ), w = κ bytes                      same
targets         1  delta only: 4-byte gaps of the ascending record targets (g0 = t0, gi = ti-t(i-1)-1)
removed         1  delta only: r values, 4-byte gaps of the ascending removed base rows
active          -  ``np.packbits`` (big bit order), ceil(n/8) bytes, in both modes
=============  ==  =========================================  ======================================

A field whose predict-mask bit is set stores, per component, ``zigzag(wrap(c[i] - c[i-1]))`` with
``c[-1] = 0`` and ``wrap`` to a signed 8w-bit integer; the decoder takes the running sum modulo
2^(8w).  Rows sorted along a Morton curve (:func:`spatial_order`) make the differences small.

Precision of the quantised mode (defaults of :class:`QuantConfig`)
------------------------------------------------------------------
* means: fixed point on a grid of step ``mean_step`` (0.25 mm; 0.5 mm cost 0.10 dB ROI PSNR on Replica room0, bench.quant_psnr) anchored at the chunk's bounding-box
  minimum, so the error is at most 0.125 mm (plus float32 rounding of the world coordinate) whatever
  the box size; the code width grows with the box: 1 byte per axis up to 6.4 cm, 2 bytes (16 bit)
  up to 16.4 m (a room), 3 bytes up to 4.2 km, else 4.  A fixed step rather than extent / 65535
  keeps precision bounded for large boxes and avoids spending incompressible low bits on small
  boxes (a 0.8 m ROI needs 11 bits per axis, not 16).  The decoder only reads origin and step
  from the header, so other step rules stay wire-compatible.
* quats: normalised (the renderer normalises anyway; zero quaternions become identity), sign fixed
  so that the largest component is positive (q and -q are the same rotation).  Error per stored
  component e <= (1/sqrt(2)) / (2^b - 1), hence |Δq| <= sqrt(12)·e and rotation error
  <= 4·asin(sqrt(3)·e) (about 7e rad): 0.55 degree bound / 0.42 degree measured on random rotations
  at b = 9; the default b = 8 (26 bits in a 4-byte code) doubles that and costs no measurable
  ROI PSNR on room0 (+0.004 dB with 7-bit opacity, bench.quant_psnr); 0.27 degree bound at b = 10.
* log_scales / colours: affine over the chunk's [min, max], clamped to ``scale_clamp`` /
  ``color_clamp``; error <= (hi - lo) / (2 (2^bits - 1)) for values inside the clamp.
* opacity: quantised in opacity space, error in sigmoid(logit) <= 0.5 / (2^bits - 1) (0.0039 at the
  default 7 bits, 0.00196 at 8
  bit); decoded logits are finite (|logit| <= log(2 (2^bits - 1) - 1), 6.23 at 8 bit).
* κ and the active flag are lossless in both modes.

Hostile input
-------------
:func:`decode_chunk` and :class:`SubsetAssembler` raise only :class:`WireError` subclasses on bad
bytes (after a ``TypeError`` for a non-bytes argument).  Sizes are checked against
:class:`WireLimits` before any allocation proportional to a header field, and the zstd frame's
declared content size must equal the (bounded) expected raw length before decompression.
"""

from __future__ import annotations

import hashlib
import math
import struct
import zlib
from dataclasses import dataclass
from typing import Any, Iterable, Optional, Sequence

import numpy as np
import zstandard

from gausslite.core.arrays import GAUSSIAN_FIELDS, GaussianArrays, as_numpy

__all__ = [
    "FORMAT_VERSION",
    "SUPPORTED_VERSIONS",
    "MAX_KAPPA_SHIFT",
    "MAGIC",
    "GaussianArrays",
    "GAUSSIAN_FIELDS",
    "QuantConfig",
    "WireLimits",
    "ChunkHeader",
    "DecodedChunk",
    "SubsetMeta",
    "SubsetAssembler",
    "encode_subset",
    "decode_chunk",
    "peek_header",
    "assemble",
    "section_lengths",
    "pack_sections",
    "raw_payload",
    "apply_delta",
    "encode_delta",
    "spatial_order",
    "DeltaMismatch",
    "raw_bytes_per_gaussian",
    "WireError",
    "TruncatedChunk",
    "BadMagic",
    "UnsupportedVersion",
    "ChecksumMismatch",
    "LimitExceeded",
    "MalformedChunk",
    "NonFiniteValues",
    "InconsistentChunks",
    "ConflictingDuplicate",
    "IncompleteSubset",
]

MAGIC = b"GLWC"
FORMAT_VERSION = 3
#: format versions this decoder reads (2: the same layout with the κ shift reserved as 0)
SUPPORTED_VERSIONS = (2, 3)
#: largest κ shift a delta can carry (u16 header field)
MAX_KAPPA_SHIFT = 0xFFFF

FLAG_LOSSLESS = 1
FLAG_SHUFFLE = 2
FLAG_DELTA = 4
_KNOWN_FLAGS = FLAG_LOSSLESS | FLAG_SHUFFLE | FLAG_DELTA

_HEADER = struct.Struct("<4sHHQIIQIHBBBBBBH3d3d2f2fIIQQII")
HEADER_SIZE = _HEADER.size  # 142
_CRC = struct.Struct("<I")
_SECTION = struct.Struct("<I")
_PREFIX = struct.Struct("<4sH")

_SQRT1_2 = 1.0 / math.sqrt(2.0)
_QUAT_REST = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], dtype=np.int64)


# --------------------------------------------------------------------------------------------
# errors


class WireError(ValueError):
    """Base class of every error raised for bad wire bytes (maps to gRPC INVALID_ARGUMENT)."""


class TruncatedChunk(WireError):
    """The chunk is shorter than its fixed header or than the lengths its header declares."""


class BadMagic(WireError):
    """The chunk does not start with :data:`MAGIC`."""


class UnsupportedVersion(WireError):
    """The chunk's format version is not one of :data:`SUPPORTED_VERSIONS`."""


class ChecksumMismatch(WireError):
    """The CRC-32 trailer does not match the chunk's bytes."""


class LimitExceeded(WireError):
    """A size or count exceeds :class:`WireLimits` (checked before allocating)."""


class MalformedChunk(WireError):
    """A structurally invalid chunk: bad header field, payload length, or zstd frame."""


class NonFiniteValues(MalformedChunk):
    """Decoded floating-point values contain NaN or infinity."""


class InconsistentChunks(WireError):
    """Chunks of one subset disagree (agent, map version, counts, mode) or overfill it."""


class ConflictingDuplicate(InconsistentChunks):
    """The same (agent, map version, chunk index) arrived twice with different content."""


class IncompleteSubset(WireError):
    """Assembly was requested while chunks are missing."""


@dataclass(frozen=True)
class QuantConfig:
    """Encoding parameters (see the module docstring for the resulting precision).

    Attributes:
        lossless: float32 for every field (κ zigzag-packed, active bit-packed); no quantisation.
        mean_step: fixed-point grid step of the means (metres); the max error is half of it
            (default 0.25 mm → <= 0.125 mm).  The code width (1..4 bytes per axis) follows from the
            chunk's bounding box: 2 bytes up to a 32.8 m extent, 3 bytes up to 8.4 km.
        quat_bits: bits per smallest-three component (4..20).
        scale_bits, opacity_bits, color_bits: code bits (1..16).
        scale_clamp: (lo, hi) clamp of log-scales before per-chunk range fitting.
        color_clamp: (lo, hi) clamp of colours before per-chunk range fitting.
        zstd_level: zstd compression level (1..22).
        shuffle: byte-plane shuffle before zstd.
        predict: allow previous-row prediction of quantised fields (header predict mask); the
            encoder uses it per chunk and field only when that field compresses smaller.
    """

    lossless: bool = False
    mean_step: float = 2.5e-4  # 0.25 mm; 0.35 mm cost a further 0.013 dB ROI PSNR on room0 (bench.quant_psnr)
    # bench.quant_psnr on a room0 map, B per active Gaussian / ROI PSNR vs lossless: quat 9, scale 9,
    # opacity 8 bits 12.51 B / +0.001 dB; quat 8, opacity 7: 11.55 B / +0.004 dB; and scale 8:
    # 11.10 B / -0.020 dB (the sim's room0 subsets compress about 0.5 B worse than this map's)
    quat_bits: int = 8
    scale_bits: int = 8
    opacity_bits: int = 7
    color_bits: int = 8
    scale_clamp: tuple[float, float] = (-16.0, 4.0)
    color_clamp: tuple[float, float] = (-1.0, 2.0)
    zstd_level: int = 3
    shuffle: bool = True
    predict: bool = True

    def __post_init__(self) -> None:
        if not (self.mean_step > 0 and math.isfinite(self.mean_step)):
            raise ValueError("mean_step must be a positive finite number")
        if not 4 <= self.quat_bits <= 20:
            raise ValueError("quat_bits must be in 4..20")
        for name in ("scale_bits", "opacity_bits", "color_bits"):
            if not 1 <= getattr(self, name) <= 16:
                raise ValueError(f"{name} must be in 1..16")
        for name in ("scale_clamp", "color_clamp"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise ValueError(f"{name} must be finite with lo < hi")
        if not 1 <= self.zstd_level <= 22:
            raise ValueError("zstd_level must be in 1..22")


LOSSLESS = QuantConfig(lossless=True)


@dataclass(frozen=True)
class WireLimits:
    """Decoder limits, enforced before allocation (bounded message sizes; ``docs/wire-format.md`` §8).

    Attributes:
        max_chunk_bytes: largest accepted chunk (bytes on the wire).
        max_chunk_gaussians: largest Gaussian count of one chunk.
        max_total_gaussians: largest subset (total Gaussian count in a header).
        max_chunks: largest chunk count of a subset.
        max_agent_id_bytes: longest UTF-8 agent id.
    """

    max_chunk_bytes: int = 64 << 20
    max_chunk_gaussians: int = 1 << 20
    max_total_gaussians: int = 1 << 27
    max_chunks: int = 1 << 16
    max_agent_id_bytes: int = 255


DEFAULT_LIMITS = WireLimits()


@dataclass(frozen=True)
class ChunkHeader:
    """Parsed and validated chunk header (see the layout in the module docstring)."""

    version: int
    lossless: bool
    shuffle: bool
    agent_id: str
    map_version: int
    chunk_index: int
    chunk_count: int
    total_count: int
    count: int
    mean_bytes: int
    quat_bits: int
    scale_bits: int
    opacity_bits: int
    color_bits: int
    kappa_bytes: int
    mean_origin: tuple[float, float, float]
    mean_step: tuple[float, float, float]
    scale_range: tuple[float, float]
    color_range: tuple[float, float]
    raw_len: int
    payload_len: int
    wire_len: int
    delta: bool = False
    predict_mask: int = 0
    base_version: int = 0
    base_count: int = 0
    removed_count: int = 0
    kappa_shift: int = 0


@dataclass(frozen=True)
class DecodedChunk:
    """One decoded chunk.

    Attributes:
        header: the validated header.
        arrays: the chunk's ``header.count`` Gaussians.
        digest: 32-byte BLAKE2b of the semantic header fields and the raw payload: equal digests
            mean identical content regardless of zstd level (used for idempotent re-delivery).
        targets: delta chunks only, (count,) int64 strictly increasing record targets (a target
            below ``header.base_count`` replaces that base row, one at or above it is a new row).
        removed: delta chunks only, (removed_count,) int64 strictly increasing base rows removed.
    """

    header: ChunkHeader
    arrays: GaussianArrays
    digest: bytes
    targets: Optional[np.ndarray] = None
    removed: Optional[np.ndarray] = None


@dataclass(frozen=True)
class SubsetMeta:
    """Metadata of an assembled subset.

    Attributes:
        agent_id, map_version, total_count, chunk_count, lossless: from the (consistent) headers.
        wire_bytes: sum of the chunks' lengths on the wire.
        delta, base_version, base_count: a delta subset (``total_count`` counts its records) and
            the base it applies to.
        kappa_shift: a delta's κ shift (added to the κ of every kept, unreplaced active base row).
    """

    agent_id: str
    map_version: int
    total_count: int
    chunk_count: int
    lossless: bool
    wire_bytes: int
    delta: bool = False
    base_version: int = 0
    base_count: int = 0
    kappa_shift: int = 0


# --------------------------------------------------------------------------------------------
# byte planes


def _nbytes(bits: int) -> int:
    return (bits + 7) // 8


def _write_field(values: np.ndarray, width: int, shuffle: bool) -> bytes:
    """(n, C) or (n,) unsigned ints (< 2^(8 width)) → C·n·width bytes (see module docstring)."""
    v = np.asarray(values)
    n = v.shape[0]
    if width == 0 or n == 0:
        return b""
    v = v.reshape(n, -1)
    c = v.shape[1]
    u = np.ascontiguousarray(v.T.astype("<u8"))  # (C, n)
    b = u.view(np.uint8).reshape(c, n, 8)[:, :, :width]
    if shuffle:
        b = b.transpose(0, 2, 1)
    return np.ascontiguousarray(b).tobytes()


def _read_field(buf: memoryview, n: int, c: int, width: int, shuffle: bool) -> np.ndarray:
    """Inverse of :func:`_write_field`: returns (n, C) uint64."""
    out = np.zeros((c, n, 8), dtype=np.uint8)
    if width and n:
        a = np.frombuffer(buf, dtype=np.uint8, count=c * n * width)
        if shuffle:
            out[:, :, :width] = a.reshape(c, width, n).transpose(0, 2, 1)
        else:
            out[:, :, :width] = a.reshape(c, n, width)
    return out.view("<u8").reshape(c, n).T


def _field_widths(h_lossless: bool, mean_bytes: int, quat_bits: int, scale_bits: int,
                  opacity_bits: int, color_bits: int, kappa_bytes: int,
                  delta: bool = False) -> list[tuple[int, int]]:
    """[(components, bytes per value)] of means, quats, log_scales, opacity, colors, kappa, targets
    (targets: 4-byte gap codes in delta chunks, absent otherwise)."""
    t = (1, 4 if delta else 0)
    if h_lossless:
        return [(3, 4), (4, 4), (3, 4), (1, 4), (3, 4), (1, kappa_bytes), t]
    return [
        (3, mean_bytes),
        (1, _nbytes(2 + 3 * quat_bits)),
        (3, _nbytes(scale_bits)),
        (1, _nbytes(opacity_bits)),
        (3, _nbytes(color_bits)),
        (1, kappa_bytes),
        t,
    ]


def _raw_len(n: int, widths: list[tuple[int, int]], removed: int = 0) -> int:
    return sum(_section_lengths(n, widths, removed))


def _section_lengths(n: int, widths: list[tuple[int, int]], removed: int = 0) -> list[int]:
    """Raw byte length of each payload section: the six attribute fields, in delta chunks the
    targets and removed fields, then the packed active bits."""
    out = [n * c * w for c, w in widths[:6]]
    if widths[6][1]:
        out += [n * 4, removed * 4]
    return out + [(n + 7) // 8]


#: header predict-mask bits: bit i set = field i of :func:`_field_widths` (means, quats,
#: log_scales, opacity, colors, kappa) is coded as zigzagged wrapped differences from the previous row
_PREDICTABLE = 6


def _predict_encode(codes: np.ndarray, width: int) -> np.ndarray:
    """(n, C) codes < 2^(8 width) → zigzag of the row-to-row difference wrapped to a signed
    8·width-bit integer (first row: difference from 0); same shape, same width."""
    if codes.size == 0:
        return codes
    bits = 8 * width
    mod = 1 << bits
    c = codes.astype(np.int64)
    d = np.diff(c, axis=0, prepend=np.zeros((1,) + c.shape[1:], np.int64)) % mod
    sgn = np.where(d >= mod >> 1, d - mod, d)
    return ((sgn << 1) ^ (sgn >> 63)).astype(np.uint64) & np.uint64(mod - 1)


def _predict_decode(z: np.ndarray, width: int) -> np.ndarray:
    """Inverse of :func:`_predict_encode` (uint64 in, uint64 out, values < 2^(8 width))."""
    if z.size == 0:
        return z
    mod = 1 << (8 * width)
    zz = z.astype(np.int64)
    sgn = (zz >> 1) ^ -(zz & 1)
    return (np.cumsum(sgn, axis=0) % mod).astype(np.uint64)


def _gaps_encode(sorted_vals: np.ndarray) -> np.ndarray:
    """Strictly increasing non-negative ints → gaps g0 = v0, gi = vi − v(i−1) − 1."""
    v = np.asarray(sorted_vals, np.int64)
    if v.size == 0:
        return v.astype(np.uint64)
    return np.diff(v, prepend=np.int64(-1)).astype(np.uint64) - np.uint64(1)


def _gaps_decode(g: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_gaps_encode` (int64; every value < 2^32 · (n + 1))."""
    return np.cumsum(g.astype(np.int64) + 1) - 1


def raw_bytes_per_gaussian(quant: QuantConfig = QuantConfig(), kappa_bytes: int = 2,
                           mean_bytes: int = 2) -> float:
    """Uncompressed payload bytes per Gaussian for a configuration (before zstd).

    Args:
        quant: the configuration; kappa_bytes: zigzag κ width; mean_bytes: mean code width.
    """
    w = _field_widths(quant.lossless, mean_bytes, quant.quat_bits, quant.scale_bits, quant.opacity_bits,
                      quant.color_bits, kappa_bytes)
    return sum(c * x for c, x in w) + 0.125


# --------------------------------------------------------------------------------------------
# quantisers


def _zigzag(k: np.ndarray) -> np.ndarray:
    k = k.astype(np.int64)
    return ((k << 1) ^ (k >> 63)).view(np.uint64)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    z = z.astype(np.uint64)
    return ((z >> np.uint64(1)) ^ (np.uint64(0) - (z & np.uint64(1)))).view(np.int64)


def _width_for(max_value: int) -> int:
    return (int(max_value).bit_length() + 7) // 8


def _mean_params(means: np.ndarray, quant: QuantConfig) -> tuple[np.ndarray, np.ndarray, int]:
    """Origin (3,) f64, step (3,) f64 and code width in bytes (1..4) for a block of means.

    The grid step is ``quant.mean_step`` on every axis, anchored at the block's minimum corner; the
    width is the fewest bytes that hold extent / step.  Only when the extent exceeds
    (2^32 - 1) · step (> 2147 km at 0.5 mm) does the step grow to extent / (2^32 - 1), which is
    still finer than float32 resolution at that magnitude.
    """
    if len(means) == 0:
        return np.zeros(3), np.full(3, quant.mean_step), 1
    m = means.astype(np.float64)
    lo = m.min(axis=0)
    ext = float((m.max(axis=0) - lo).max())
    step = quant.mean_step
    top = math.ceil(ext / step) if ext > 0 else 0
    if top > 0xFFFFFFFF:
        step = ext / 0xFFFFFFFF
        top = 0xFFFFFFFF
    return lo, np.full(3, step), max(1, _width_for(top))


def _affine_range(x: np.ndarray, clamp: tuple[float, float]) -> tuple[float, float]:
    if x.size == 0:
        return 0.0, 0.0
    lo = float(np.float32(np.clip(x.min(), clamp[0], clamp[1])))
    hi = float(np.float32(np.clip(x.max(), clamp[0], clamp[1])))
    return lo, hi


def _affine_encode(x: np.ndarray, lo: float, hi: float, bits: int) -> np.ndarray:
    m = (1 << bits) - 1
    if hi <= lo:
        return np.zeros(x.shape, np.uint64)
    step = (hi - lo) / m
    q = np.rint((np.clip(x.astype(np.float64), lo, hi) - lo) / step)
    return np.clip(q, 0, m).astype(np.uint64)


def _affine_decode(q: np.ndarray, lo: float, hi: float, bits: int) -> np.ndarray:
    m = (1 << bits) - 1
    step = (hi - lo) / m if hi > lo else 0.0
    return (lo + q.astype(np.float64) * step).astype(np.float32)


def _quat_encode(q: np.ndarray, bits: int) -> np.ndarray:
    q = q.astype(np.float64)
    norm = np.sqrt((q * q).sum(axis=1))
    bad = norm == 0
    q = np.where(bad[:, None], np.array([1.0, 0.0, 0.0, 0.0]), q / np.where(bad, 1.0, norm)[:, None])
    idx = np.argmax(np.abs(q), axis=1)
    sign = np.where(np.take_along_axis(q, idx[:, None], 1)[:, 0] < 0, -1.0, 1.0)
    rest = np.take_along_axis(q, _QUAT_REST[idx], 1) * sign[:, None]
    m = (1 << bits) - 1
    u = np.clip(np.rint((rest + _SQRT1_2) / (2 * _SQRT1_2) * m), 0, m).astype(np.uint64)
    b = np.uint64(bits)
    return ((idx.astype(np.uint64) << (b * np.uint64(3))) | (u[:, 0] << (b * np.uint64(2)))
            | (u[:, 1] << b) | u[:, 2])


def _quat_decode(p: np.ndarray, bits: int) -> np.ndarray:
    b = np.uint64(bits)
    m = np.uint64((1 << bits) - 1)
    hi = p >> (b * np.uint64(3))
    if hi.size and int(hi.max()) > 3:
        raise MalformedChunk("quaternion largest-component index out of range")
    idx = hi.astype(np.int64)
    u = np.stack([(p >> (b * np.uint64(2))) & m, (p >> b) & m, p & m], axis=1).astype(np.float64)
    rest = u / float(m) * (2 * _SQRT1_2) - _SQRT1_2
    big = np.sqrt(np.maximum(0.0, 1.0 - (rest * rest).sum(axis=1)))
    out = np.empty((len(p), 4), np.float64)
    np.put_along_axis(out, _QUAT_REST[idx], rest, 1)
    np.put_along_axis(out, idx[:, None], big[:, None], 1)
    return out.astype(np.float32)


def _opacity_encode(logit: np.ndarray, bits: int) -> np.ndarray:
    m = (1 << bits) - 1
    p = 1.0 / (1.0 + np.exp(-logit.astype(np.float64)))
    return np.clip(np.rint(p * m), 0, m).astype(np.uint64)


def _opacity_decode(q: np.ndarray, bits: int) -> np.ndarray:
    m = (1 << bits) - 1
    p = np.clip(q.astype(np.float64) / m, 0.5 / m, 1.0 - 0.5 / m)
    return np.log(p / (1.0 - p)).astype(np.float32)


# --------------------------------------------------------------------------------------------
# encoding


def _zstd_bound(n: int) -> int:
    # ZSTD_COMPRESSBOUND plus slack for the frame header (content size) and block headers.
    return n + (n >> 8) + (((128 << 10) - n) >> 11 if n < (128 << 10) else 0) + 64


def _encode_chunk(arr: GaussianArrays, agent: bytes, map_version: int, index: int, count: int,
                  total: int, quant: QuantConfig, cctx: zstandard.ZstdCompressor,
                  delta: Optional[tuple[int, int, np.ndarray, np.ndarray, int]] = None) -> bytes:
    """One chunk. ``delta`` = (base_version, base_count, targets (n,), removed (r,), κ shift), both sorted."""
    n = len(arr)
    sh = quant.shuffle
    kz = _zigzag(arr.kappa)
    kb = _width_for(int(kz.max())) if n else 0
    origin = step = np.zeros(3)
    srange = crange = (0.0, 0.0)
    if quant.lossless:
        mb = qb = sb = ob = cb = 0
        codes = [arr.means.view(np.uint32), arr.quats.view(np.uint32), arr.log_scales.view(np.uint32),
                 arr.opacity_logits.view(np.uint32), arr.colors.view(np.uint32)]
    else:
        qb, sb, ob, cb = quant.quat_bits, quant.scale_bits, quant.opacity_bits, quant.color_bits
        origin, step, mb = _mean_params(arr.means, quant)
        mmax = (1 << (8 * mb)) - 1
        safe = np.where(step > 0, step, 1.0)
        mq = np.where(step > 0, np.rint((arr.means.astype(np.float64) - origin) / safe), 0.0)
        mq = np.clip(mq, 0, mmax).astype(np.uint64)
        srange = _affine_range(arr.log_scales, quant.scale_clamp)
        crange = _affine_range(arr.colors, quant.color_clamp)
        codes = [mq, _quat_encode(arr.quats, qb), _affine_encode(arr.log_scales, *srange, sb),
                 _opacity_encode(arr.opacity_logits, ob), _affine_encode(arr.colors, *crange, cb)]
    is_delta = delta is not None
    base_version, base_count, targets, removed, kappa_shift = delta if is_delta else (0, 0, None, None, 0)
    widths = _field_widths(quant.lossless, mb, qb, sb, ob, cb, kb, is_delta)
    tail = []
    if is_delta:
        tail.append(_write_field(_gaps_encode(targets), 4, sh))
        tail.append(_write_field(_gaps_encode(removed), 4, sh))
    tail.append(np.packbits(arr.active).tobytes())
    codes.append(kz)
    # previous-row prediction pays off when rows are spatially ordered (see spatial_order); the
    # encoder keeps, field by field, whichever coding zstd compresses smaller on its own
    fields = []
    predict = 0
    for i, (c, w) in enumerate(widths[:_PREDICTABLE]):
        plain = _write_field(codes[i], w, sh)
        if quant.predict and not quant.lossless and n > 1 and 0 < w <= 4:
            pred = _write_field(_predict_encode(np.asarray(codes[i]).reshape(n, c), w), w, sh)
            if len(cctx.compress(pred)) < len(cctx.compress(plain)):
                plain = pred
                predict |= 1 << i
        fields.append(plain)
    sections = fields + tail
    raw = b"".join(sections)
    # one zstd frame per section (u32 compressed length first): each field gets its own entropy
    # tables, 0.8 B per Gaussian smaller than one frame over the whole payload (room0 subset)
    payload = b"".join(_SECTION.pack(len(z)) + z for z in map(cctx.compress, sections))
    r = 0 if removed is None else len(removed)
    assert len(raw) == _raw_len(n, widths, r)
    flags = ((FLAG_LOSSLESS if quant.lossless else 0) | (FLAG_SHUFFLE if sh else 0)
             | (FLAG_DELTA if is_delta else 0))
    head = _HEADER.pack(
        MAGIC, FORMAT_VERSION, flags, map_version, index, count, total, n, len(agent),
        mb, qb, sb, ob, cb, kb, int(kappa_shift), *map(float, origin), *map(float, step), *srange, *crange,
        len(raw), len(payload), int(base_version), int(base_count), r, predict,
    )
    body = head + agent + payload
    return body + _CRC.pack(zlib.crc32(body))


def encode_subset(
    gaussians: Any,
    agent_id: str,
    map_version: int,
    *,
    chunk_gaussians: Optional[int] = None,
    max_chunk_bytes: Optional[int] = None,
    quant: QuantConfig = QuantConfig(),
    limits: WireLimits = DEFAULT_LIMITS,
) -> list[bytes]:
    """Encode a Gaussian subset into self-describing wire chunks (``docs/wire-format.md``).

    Args:
        gaussians: a GaussianMap, GaussianArrays or mapping of arrays (see
            :meth:`GaussianArrays.from_any`); N rows, all values finite.
        agent_id: non-empty; UTF-8 length <= ``limits.max_agent_id_bytes``.
        map_version: 0 <= map_version < 2^64.
        chunk_gaussians: Gaussians per chunk (the last chunk may be smaller).  Default 65536 when
            neither this nor ``max_chunk_bytes`` is given.
        max_chunk_bytes: bound on each chunk's total wire size; the Gaussians per chunk are chosen
            from the worst case (incompressible payload), so every chunk is guaranteed to fit.
        quant: quantisation/compression parameters.
        limits: the receiving side's limits; encoding refuses to produce chunks that violate them.

    Returns:
        list of chunks (bytes), chunk i has index i; at least one chunk (an empty subset is one
        chunk with zero Gaussians).  Row order is preserved through :func:`assemble`.

    Raises:
        ValueError: empty/oversized agent id, map_version out of range, non-finite float fields,
            bad chunking arguments, or output that would violate ``limits`` (κ may be any int64;
            it is zigzag-coded).
        TypeError: unsupported input container.
    """
    return _encode(GaussianArrays.from_any(gaussians), agent_id, map_version, None,
                   chunk_gaussians=chunk_gaussians, max_chunk_bytes=max_chunk_bytes, quant=quant,
                   limits=limits)


def encode_delta(
    records: Any,
    targets: Any,
    removed: Any,
    agent_id: str,
    map_version: int,
    base_version: int,
    base_count: int,
    *,
    chunk_gaussians: Optional[int] = None,
    max_chunk_bytes: Optional[int] = None,
    quant: QuantConfig = QuantConfig(),
    limits: WireLimits = DEFAULT_LIMITS,
    kappa_shift: int = 0,
) -> list[bytes]:
    """Encode a delta against an earlier subset version of the same agent (FLAG_DELTA chunks).

    The receiver rebuilds the new subset with :func:`apply_delta`: the base subset (``base_count``
    rows, version ``base_version``) without the ``removed`` rows, with rows replaced by the records
    whose target is below ``base_count``, followed by the records whose target is at or above
    ``base_count`` (new rows) in ascending target order.

    Args:
        records: the changed and new Gaussians (GaussianArrays-like, R rows).
        targets: (R,) ints, distinct: a base row index (< base_count) to replace, or
            ``base_count + k`` for the k-th new row.  Records are sorted by target before encoding.
        removed: (D,) distinct base row indices (< base_count) that the new version drops; not in
            ``targets``.
        agent_id, map_version, chunk_gaussians, max_chunk_bytes, quant, limits: as
            :func:`encode_subset`.
        base_version: the version the delta applies to (< map_version).
        base_count: row count of the base subset.
        kappa_shift: κ added to every base row the delta keeps without replacing it whose task flag
            (``active``) is set, in ``[0, MAX_KAPPA_SHIFT]`` (an agent's κ grows by one per ROI-phase
            iteration for all its active Gaussians, so one shift brings the unchanged rows' κ up to
            date; written in every chunk's header).

    Returns:
        list of chunks (at least one; removed indices are spread over the chunks).

    Raises:
        ValueError: bad targets/removed (duplicates, out of range, overlap, sizes), base_version not
            below map_version, a κ shift outside ``[0, MAX_KAPPA_SHIFT]``, and everything
            :func:`encode_subset` raises.
    """
    if not isinstance(kappa_shift, (int, np.integer)) or not 0 <= int(kappa_shift) <= MAX_KAPPA_SHIFT:
        raise ValueError(f"kappa_shift must be an int in [0, {MAX_KAPPA_SHIFT}], got {kappa_shift!r}")
    arr = GaussianArrays.from_any(records)
    t = np.asarray(targets, dtype=np.int64).reshape(-1)
    rm = np.unique(np.asarray(removed, dtype=np.int64).reshape(-1))
    if len(rm) != np.asarray(removed).size:
        raise ValueError("removed holds duplicates")
    if t.shape[0] != len(arr):
        raise ValueError(f"{t.shape[0]} targets for {len(arr)} records")
    if not 0 <= int(base_count) <= limits.max_total_gaussians:
        raise ValueError("base_count out of range")
    if not isinstance(base_version, (int, np.integer)) or not 0 <= int(base_version) < int(map_version):
        raise ValueError("base_version must be an int in [0, map_version)")
    order = np.argsort(t, kind="stable")
    t = t[order]
    if t.size and (t[0] < 0 or np.any(np.diff(t) <= 0) or t[-1] > 0xFFFFFFFF):
        raise ValueError("targets must be distinct, non-negative and < 2^32")
    if rm.size and (rm[0] < 0 or rm[-1] >= base_count):
        raise ValueError("removed rows must lie in [0, base_count)")
    if np.intersect1d(rm, t).size:
        raise ValueError("a removed row is also a target")
    return _encode(arr.take(order), agent_id, map_version,
                   (int(base_version), int(base_count), t, rm, int(kappa_shift)), chunk_gaussians=chunk_gaussians,
                   max_chunk_bytes=max_chunk_bytes, quant=quant, limits=limits)


def _encode(arr: GaussianArrays, agent_id: str, map_version: int,
            delta: Optional[tuple[int, int, np.ndarray, np.ndarray, int]], *,
            chunk_gaussians: Optional[int], max_chunk_bytes: Optional[int], quant: QuantConfig,
            limits: WireLimits) -> list[bytes]:
    if not isinstance(agent_id, str) or not agent_id:
        raise ValueError("agent_id must be a non-empty str")
    agent = agent_id.encode("utf-8")
    if len(agent) > limits.max_agent_id_bytes:
        raise ValueError(f"agent_id longer than {limits.max_agent_id_bytes} bytes")
    if not isinstance(map_version, (int, np.integer)) or not 0 <= int(map_version) < 1 << 64:
        raise ValueError("map_version must be an int in [0, 2^64)")
    map_version = int(map_version)
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        if not np.isfinite(getattr(arr, name)).all():
            raise ValueError(f"{name} contains non-finite values")
    n = len(arr)
    if n > limits.max_total_gaussians:
        raise ValueError(f"{n} Gaussians exceed limits.max_total_gaussians")
    if chunk_gaussians is not None and max_chunk_bytes is not None:
        raise ValueError("give chunk_gaussians or max_chunk_bytes, not both")
    overhead = HEADER_SIZE + len(agent) + _CRC.size
    if max_chunk_bytes is not None:
        max_chunk_bytes = int(max_chunk_bytes)
        if max_chunk_bytes > limits.max_chunk_bytes:
            raise ValueError("max_chunk_bytes exceeds limits.max_chunk_bytes")
        kb = _width_for(int(_zigzag(arr.kappa).max())) if n else 0
        mb = 4 if quant.lossless else _mean_params(arr.means, quant)[2]
        widths = _field_widths(quant.lossless, mb, quant.quat_bits, quant.scale_bits,
                               quant.opacity_bits, quant.color_bits, kb, delta is not None)
        n_rm = 0 if delta is None else len(delta[3])
        # worst case: every removed index lands in one chunk
        fits = lambda k: overhead + sum(  # noqa: E731
            _SECTION.size + _zstd_bound(x) for x in _section_lengths(k, widths, n_rm)) <= max_chunk_bytes
        if not fits(1):
            raise ValueError(f"max_chunk_bytes={max_chunk_bytes} cannot hold one Gaussian")
        lo, hi = 1, max(1, min(n, limits.max_chunk_gaussians))
        while lo < hi:  # largest k with fits(k)
            mid = (lo + hi + 1) // 2
            lo, hi = (mid, hi) if fits(mid) else (lo, mid - 1)
        per = lo
    else:
        per = 65536 if chunk_gaussians is None else int(chunk_gaussians)
        if per < 1:
            raise ValueError("chunk_gaussians must be >= 1")
        if per > limits.max_chunk_gaussians:
            raise ValueError("chunk_gaussians exceeds limits.max_chunk_gaussians")
    count = max(1, -(-n // per))
    if count > limits.max_chunks:
        raise ValueError(f"{count} chunks exceed limits.max_chunks; use larger chunks")
    cctx = zstandard.ZstdCompressor(level=quant.zstd_level, write_content_size=True,
                                    write_checksum=False)
    out = []
    if delta is not None:
        rm = delta[3]
        r_per = -(-len(rm) // count)
    for i in range(count):
        sl = slice(i * per, min(n, (i + 1) * per))
        part = arr.take(sl)
        d = None
        if delta is not None:
            d = (delta[0], delta[1], delta[2][sl], rm[i * r_per:(i + 1) * r_per], delta[4])
        chunk = _encode_chunk(part, agent, map_version, i, count, n, quant, cctx, d)
        if len(chunk) > limits.max_chunk_bytes or (
                max_chunk_bytes is not None and len(chunk) > max_chunk_bytes):
            raise ValueError("a chunk exceeds the byte limit; use smaller chunks")
        out.append(chunk)
    return out


# --------------------------------------------------------------------------------------------
# decoding


def _as_view(data: Any) -> memoryview:
    if isinstance(data, (bytes, bytearray, memoryview)):
        return memoryview(data).cast("B") if isinstance(data, memoryview) else memoryview(data)
    raise TypeError(f"chunk must be bytes-like, got {type(data).__name__}")


def _check_prefix(buf, size: int, limits: WireLimits) -> int:
    """Size limit, magic and format version of a chunk of ``size`` bytes; returns the version.

    Raises:
        LimitExceeded, TruncatedChunk, BadMagic, UnsupportedVersion (checked in this order).
    """
    if size > limits.max_chunk_bytes:
        raise LimitExceeded(f"chunk of {size} bytes, above the limit of {limits.max_chunk_bytes} bytes")
    if size < len(MAGIC):
        raise TruncatedChunk(f"{size} bytes, shorter than the magic")
    if bytes(buf[:4]) != MAGIC:
        raise BadMagic(f"bad magic {bytes(buf[:4])!r}")
    if size < _PREFIX.size:
        raise TruncatedChunk("no version field")
    version = _PREFIX.unpack_from(buf)[1]
    if version not in SUPPORTED_VERSIONS:
        raise UnsupportedVersion(f"format version {version}, supported: "
                                 f"{', '.join(map(str, SUPPORTED_VERSIONS))}")
    if size < HEADER_SIZE:
        raise TruncatedChunk(f"{size} bytes, shorter than the {HEADER_SIZE}-byte header")
    return version


def _check_length_and_crc(buf, size: int, alen: int, plen: int, limits: WireLimits) -> None:
    """The declared agent-id and payload lengths against the limits and the chunk's ``size``, then its CRC-32.

    Raises:
        LimitExceeded, TruncatedChunk, MalformedChunk (trailing bytes), ChecksumMismatch.
    """
    if alen > limits.max_agent_id_bytes:
        raise LimitExceeded(f"agent id of {alen} bytes")
    if plen > limits.max_chunk_bytes:
        raise LimitExceeded(f"payload of {plen} bytes")
    expected = HEADER_SIZE + alen + plen + _CRC.size
    if size < expected:
        raise TruncatedChunk(f"{size} bytes, header declares {expected}")
    if size > expected:
        raise MalformedChunk(f"{size - expected} trailing bytes")
    (crc,) = _CRC.unpack_from(buf, size - _CRC.size)
    if zlib.crc32(buf[: size - _CRC.size]) != crc:
        raise ChecksumMismatch("CRC-32 mismatch")


def _check_flags(version: int, flags: int, kappa_shift: int, predict_mask: int, map_version: int,
                 base_version: int, base_count: int, n_removed: int, limits: WireLimits) -> tuple[bool, bool]:
    """Flags, κ shift, predict mask and delta fields of a header; returns ``(lossless, delta)``.

    Raises:
        MalformedChunk, LimitExceeded (a delta base above ``limits.max_total_gaussians``).
    """
    if flags & ~_KNOWN_FLAGS:
        raise MalformedChunk(f"unknown flags {flags:#x}")
    if kappa_shift and (version < 3 or not flags & FLAG_DELTA):
        raise MalformedChunk(f"κ shift {kappa_shift} in a {'format 2' if version < 3 else 'full'} chunk "
                             "(reserved, must be 0)")
    lossless = bool(flags & FLAG_LOSSLESS)
    delta = bool(flags & FLAG_DELTA)
    if predict_mask >> _PREDICTABLE or (predict_mask and lossless):
        raise MalformedChunk(f"predict mask {predict_mask:#x} (lossless: {lossless})")
    if delta:
        if base_version >= map_version:
            raise MalformedChunk(f"delta base version {base_version} >= map version {map_version}")
        if base_count > limits.max_total_gaussians or n_removed > limits.max_total_gaussians:
            raise LimitExceeded(f"delta base of {base_count} rows / {n_removed} removed rows")
        if n_removed > base_count:
            raise MalformedChunk(f"{n_removed} removed rows of a {base_count}-row base")
    elif base_version or base_count or n_removed:
        raise MalformedChunk("delta fields set on a full chunk")
    return lossless, delta


def _check_counts(n: int, total: int, count_chunks: int, index: int, limits: WireLimits) -> None:
    """Row and chunk counts of a header against the limits and each other.

    Raises:
        LimitExceeded, MalformedChunk.
    """
    if n > limits.max_chunk_gaussians:
        raise LimitExceeded(f"chunk claims {n} Gaussians, above the limit of {limits.max_chunk_gaussians} per chunk")
    if total > limits.max_total_gaussians:
        raise LimitExceeded(f"subset claims {total} Gaussians, above the limit of {limits.max_total_gaussians}")
    if count_chunks > limits.max_chunks:
        raise LimitExceeded(f"subset claims {count_chunks} chunks, above the limit of {limits.max_chunks}")
    if count_chunks == 0 or index >= count_chunks:
        raise MalformedChunk(f"chunk index {index} is not below the chunk count {count_chunks} (indices are 0-based)")
    if n > total or (n == 0 and total != 0):
        raise MalformedChunk(f"chunk holds {n} rows, its subset {total} (a chunk holds 1..total rows, 0 only when total is 0)")
    if count_chunks > max(1, total):
        raise MalformedChunk(f"{count_chunks} chunks for {total} Gaussians")


def _check_quantisation(lossless: bool, mb: int, qb: int, sb: int, ob: int, cb: int, kb: int, floats: tuple) -> None:
    """Field widths and quantisation parameters (``floats``: mean origin and step, scale and colour ranges): none
    in a lossless chunk, valid ones in a quantised chunk.

    Raises:
        MalformedChunk.
    """
    if kb > 8:
        raise MalformedChunk(f"kappa bytes {kb}")
    if lossless:
        if mb or qb or sb or ob or cb or any(floats):
            raise MalformedChunk("lossless chunk with quantisation parameters")
    else:
        if mb not in (1, 2, 3, 4) or not 4 <= qb <= 20 or not all(1 <= b <= 16 for b in (sb, ob, cb)):
            raise MalformedChunk(f"bad quantisation widths {(mb, qb, sb, ob, cb)}")
        if not all(math.isfinite(f) for f in floats):
            raise MalformedChunk("non-finite quantisation parameters")
        _ox, _oy, _oz, sx, sy, sz, slo, shi, clo, chi = floats
        if min(sx, sy, sz) < 0 or slo > shi or clo > chi:
            raise MalformedChunk("negative mean step or inverted range")


def peek_header(data: Any, limits: WireLimits = DEFAULT_LIMITS) -> ChunkHeader:
    """Parse and fully validate a chunk's header and checksum, without decompressing.

    Cheap (one CRC pass): servers can route, dedupe (agent, map version, chunk index) and reject
    chunks before decoding.

    Raises:
        TypeError: ``data`` is not bytes-like.
        TruncatedChunk, BadMagic, UnsupportedVersion, ChecksumMismatch, LimitExceeded,
        MalformedChunk: see their docstrings (checked in this order).
    """
    buf = _as_view(data)
    size = len(buf)
    version = _check_prefix(buf, size, limits)
    (_, _, flags, map_version, index, count_chunks, total, n, alen, mb, qb, sb, ob, cb, kb,
     kappa_shift, ox, oy, oz, sx, sy, sz, slo, shi, clo, chi, raw_len, plen, base_version, base_count,
     n_removed, predict_mask) = _HEADER.unpack_from(buf)
    _check_length_and_crc(buf, size, alen, plen, limits)
    # ---- semantic validation (a valid CRC says nothing about intent)
    lossless, delta = _check_flags(version, flags, kappa_shift, predict_mask, map_version, base_version, base_count,
                                   n_removed, limits)
    if alen == 0:
        raise MalformedChunk("empty agent id")
    try:
        agent_id = bytes(buf[HEADER_SIZE:HEADER_SIZE + alen]).decode("utf-8")
    except UnicodeDecodeError as e:
        raise MalformedChunk(f"agent id is not UTF-8: {e}") from None
    _check_counts(n, total, count_chunks, index, limits)
    _check_quantisation(lossless, mb, qb, sb, ob, cb, kb, (ox, oy, oz, sx, sy, sz, slo, shi, clo, chi))
    want = _raw_len(n, _field_widths(lossless, mb, qb, sb, ob, cb, kb, delta), n_removed)
    if raw_len != want:
        raise MalformedChunk(f"raw length {raw_len}, expected {want} for {n} Gaussians")
    return ChunkHeader(
        version=version, lossless=lossless, shuffle=bool(flags & FLAG_SHUFFLE), agent_id=agent_id,
        map_version=map_version, chunk_index=index, chunk_count=count_chunks, total_count=total,
        count=n, mean_bytes=mb, quat_bits=qb, scale_bits=sb, opacity_bits=ob, color_bits=cb,
        kappa_bytes=kb, mean_origin=(ox, oy, oz), mean_step=(sx, sy, sz), scale_range=(slo, shi),
        color_range=(clo, chi), raw_len=raw_len, payload_len=plen, wire_len=size, delta=delta,
        predict_mask=predict_mask, base_version=base_version, base_count=base_count, removed_count=n_removed,
        kappa_shift=kappa_shift,
    )


def section_lengths(h: ChunkHeader) -> list[int]:
    """Raw byte length of each payload section of a chunk with header ``h`` (see the layout)."""
    return _section_lengths(h.count, _field_widths(
        h.lossless, h.mean_bytes, h.quat_bits, h.scale_bits, h.opacity_bits, h.color_bits,
        h.kappa_bytes, h.delta), h.removed_count)


def pack_sections(raw: bytes, lengths: Sequence[int], level: int = 3) -> bytes:
    """Split ``raw`` at ``lengths`` and build a payload: per section u32 length + zstd frame.

    Raises:
        ValueError: ``lengths`` do not add up to ``len(raw)``.
    """
    if sum(lengths) != len(raw):
        raise ValueError(f"sections of {sum(lengths)} bytes for a {len(raw)}-byte raw payload")
    cctx = zstandard.ZstdCompressor(level=level, write_content_size=True, write_checksum=False)
    out, off = [], 0
    for k in lengths:
        z = cctx.compress(raw[off:off + k])
        out.append(_SECTION.pack(len(z)) + z)
        off += k
    return b"".join(out)


def raw_payload(data: Any, limits: WireLimits = DEFAULT_LIMITS) -> bytes:
    """The validated chunk's decompressed raw payload (sections concatenated), for debugging and
    conformance tests.  Raises what :func:`peek_header` raises and MalformedChunk."""
    h = peek_header(data, limits)
    start = HEADER_SIZE + len(h.agent_id.encode("utf-8"))
    return _decompress_sections(_as_view(data)[start:start + h.payload_len], section_lengths(h))


#: payload section names in order (docs/wire-format.md §4): a full chunk's, and a delta chunk's
_SECTION_NAMES = ("means", "quats", "log_scales", "opacity", "colors", "kappa", "active")
_DELTA_SECTION_NAMES = _SECTION_NAMES[:6] + ("targets", "removed", "active")


def _decompress_sections(payload: memoryview, lengths: list[int]) -> bytes:
    """Payload = for each section: u32 compressed length L, then a zstd frame of L bytes whose
    declared content size equals the section's raw length."""
    names = _DELTA_SECTION_NAMES if len(lengths) == len(_DELTA_SECTION_NAMES) else _SECTION_NAMES
    out = []
    off = 0
    for i, want in enumerate(lengths):
        what = f"section {i} ({names[i]})"
        if off + _SECTION.size > len(payload):
            raise MalformedChunk(f"payload ends before the length of {what}")
        (clen,) = _SECTION.unpack_from(payload, off)
        off += _SECTION.size
        if clen > len(payload) - off:
            raise MalformedChunk(f"{what}: {clen} compressed bytes overrun the payload")
        out.append(_decompress(payload[off:off + clen], want, what))
        off += clen
    if off != len(payload):
        raise MalformedChunk(f"{len(payload) - off} bytes after the last payload section")
    return b"".join(out)


def _decompress(payload: memoryview, raw_len: int, what: str = "section") -> bytes:
    try:
        declared = zstandard.frame_content_size(payload)
    except zstandard.ZstdError as e:
        raise MalformedChunk(f"{what}: bad zstd frame header: {e}") from None
    if declared < 0:  # zstandard reports an absent content size as -1
        raise MalformedChunk(f"{what}: the zstd frame does not declare its content size, which the format requires "
                             f"({raw_len} bytes here)")
    if declared != raw_len:
        raise MalformedChunk(f"{what}: the zstd frame declares {declared} bytes of content, the chunk header "
                             f"implies {raw_len}")
    dobj = zstandard.ZstdDecompressor().decompressobj()
    try:
        raw = dobj.decompress(payload)
    except zstandard.ZstdError as e:
        raise MalformedChunk(f"{what}: zstd: {e}") from None
    if not dobj.eof or dobj.unused_data or len(raw) != raw_len:
        raise MalformedChunk(f"{what}: zstd payload incomplete, oversized or with trailing data")
    return raw


def _digest(h: ChunkHeader, raw: bytes) -> bytes:
    ident = (h.version, h.lossless, h.shuffle, h.agent_id, h.map_version, h.chunk_index,
             h.chunk_count, h.total_count, h.count, h.mean_bytes, h.quat_bits, h.scale_bits,
             h.opacity_bits, h.color_bits, h.kappa_bytes, h.mean_origin, h.mean_step,
             h.scale_range, h.color_range, h.delta, h.predict_mask, h.base_version, h.base_count,
             h.removed_count) + ((h.kappa_shift,) if h.kappa_shift else ())  # digests of shift-0 chunks unchanged
    d = hashlib.blake2b(repr(ident).encode(), digest_size=32)
    d.update(raw)
    return d.digest()


def decode_chunk(data: Any, limits: WireLimits = DEFAULT_LIMITS) -> DecodedChunk:
    """Decode one chunk produced by :func:`encode_subset`.

    Args:
        data: bytes-like chunk.
        limits: decoder limits.

    Returns:
        :class:`DecodedChunk` with float32/int64/bool arrays (see :class:`GaussianArrays`).

    Raises:
        TypeError: ``data`` not bytes-like.  Otherwise only :class:`WireError` subclasses:
        everything :func:`peek_header` raises, MalformedChunk (zstd errors, bad quaternion code),
        NonFiniteValues (NaN/inf after decoding).
    """
    h = peek_header(data, limits)
    buf = _as_view(data)
    start = HEADER_SIZE + len(h.agent_id.encode("utf-8"))
    raw = _decompress_sections(buf[start:start + h.payload_len], section_lengths(h))
    mv = memoryview(raw)
    n, sh = h.count, h.shuffle
    widths = _field_widths(h.lossless, h.mean_bytes, h.quat_bits, h.scale_bits, h.opacity_bits,
                           h.color_bits, h.kappa_bytes, h.delta)
    cols = []
    off = 0
    for i, (c, w) in enumerate(widths):
        v = _read_field(mv[off:], n, c, w, sh)
        if h.predict_mask >> i & 1:
            v = _predict_decode(v, w)
        cols.append(v)
        off += c * w * n
    targets = removed = None
    if h.delta:
        targets = _gaps_decode(cols[6][:, 0])
        removed = _gaps_decode(_read_field(mv[off:], h.removed_count, 1, 4, sh)[:, 0])
        off += 4 * h.removed_count
        if targets.size and int(targets[-1]) > 0xFFFFFFFF:
            raise MalformedChunk("delta target beyond 2^32 - 1")
        if removed.size and int(removed[-1]) >= h.base_count:
            raise MalformedChunk("removed row beyond the base subset")
        if np.intersect1d(targets, removed).size:
            raise MalformedChunk("a removed row is also a delta target")
    active = np.unpackbits(np.frombuffer(raw, np.uint8, offset=off), count=n).astype(bool)
    kappa = _unzigzag(cols[5][:, 0])
    if h.lossless:
        f = [c.astype(np.uint32).view(np.float32) for c in cols[:5]]
        means, quats, scales, opac, colors = f[0], f[1], f[2], f[3][:, 0], f[4]
    else:
        step = np.asarray(h.mean_step)
        mmax = (1 << (8 * h.mean_bytes)) - 1
        if cols[0].size and int(cols[0].max()) > mmax:  # unreachable by construction; defensive
            raise MalformedChunk("mean code out of range")
        with np.errstate(over="ignore", invalid="ignore"):
            means = (np.asarray(h.mean_origin) + cols[0].astype(np.float64) * step).astype(
                np.float32)
            quats = _quat_decode(cols[1][:, 0], h.quat_bits)
            scales = _affine_decode(cols[2], *h.scale_range, h.scale_bits)
            opac = _opacity_decode(cols[3][:, 0], h.opacity_bits)
            colors = _affine_decode(cols[4], *h.color_range, h.color_bits)
        for name, v, bits in (("log_scales", cols[2], h.scale_bits),
                              ("opacity", cols[3], h.opacity_bits),
                              ("colors", cols[4], h.color_bits)):
            if v.size and int(v.max()) >= 1 << bits:
                raise MalformedChunk(f"{name} code exceeds {bits} bits")
    for name, v in (("means", means), ("quats", quats), ("log_scales", scales),
                    ("opacity_logits", opac), ("colors", colors)):
        if not np.isfinite(v).all():
            raise NonFiniteValues(f"non-finite {name}")
    arrays = GaussianArrays(means=means, quats=quats, log_scales=scales, opacity_logits=opac,
                            colors=colors, kappa=kappa, active=active)
    return DecodedChunk(header=h, arrays=arrays, digest=_digest(h, raw), targets=targets,
                        removed=removed)


# --------------------------------------------------------------------------------------------
# assembly


class SubsetAssembler:
    """Streaming, order-independent, idempotent assembly of one subset's chunks (``docs/wire-format.md``).

    Chunks may arrive in any order; re-delivering a chunk with identical content (same digest,
    see :class:`DecodedChunk`) is a no-op, a different chunk under the same index raises
    :class:`ConflictingDuplicate`.  The first accepted chunk fixes (agent id, map version, chunk
    count, total count, lossless flag); later chunks must agree.

    Args:
        limits: decoder limits for raw byte chunks.
        agent_id, map_version: optional expected values (e.g. from an authenticated RPC); chunks
            that disagree raise :class:`InconsistentChunks`.

    Memory is bounded by ``limits.max_total_gaussians`` decoded Gaussians (the accepted counts can
    never exceed the header's total).
    """

    def __init__(self, limits: WireLimits = DEFAULT_LIMITS, *, agent_id: Optional[str] = None,
                 map_version: Optional[int] = None) -> None:
        self.limits = limits
        self._expect_agent = agent_id
        self._expect_version = map_version
        self._key: Optional[tuple] = None
        self._chunks: dict[int, DecodedChunk] = {}
        self._received = 0
        self._wire_bytes = 0

    # -- properties
    @property
    def agent_id(self) -> Optional[str]:
        return self._key[0] if self._key else self._expect_agent

    @property
    def map_version(self) -> Optional[int]:
        return self._key[1] if self._key else self._expect_version

    @property
    def chunk_count(self) -> Optional[int]:
        """Chunk count from the first accepted chunk (None before any)."""
        return self._key[2] if self._key else None

    @property
    def total_count(self) -> Optional[int]:
        return self._key[3] if self._key else None

    @property
    def complete(self) -> bool:
        return self._key is not None and len(self._chunks) == self._key[2]

    def received(self) -> list[int]:
        """Sorted indices of accepted chunks."""
        return sorted(self._chunks)

    def missing(self) -> list[int]:
        """Sorted indices still missing (empty before the first chunk: the count is unknown)."""
        if self._key is None:
            return []
        return [i for i in range(self._key[2]) if i not in self._chunks]

    def add(self, chunk: Any) -> bool:
        """Accept one chunk (bytes-like or :class:`DecodedChunk`).

        Returns:
            True when the chunk was new, False for an identical re-delivery.

        Raises:
            WireError subclasses from :func:`decode_chunk`; InconsistentChunks; ConflictingDuplicate.
        """
        dc = chunk if isinstance(chunk, DecodedChunk) else decode_chunk(chunk, self.limits)
        h = dc.header
        key = (h.agent_id, h.map_version, h.chunk_count, h.total_count, h.lossless, h.delta,
               h.base_version, h.base_count, h.kappa_shift)
        if self._expect_agent is not None and h.agent_id != self._expect_agent:
            raise InconsistentChunks(f"agent {h.agent_id!r}, expected {self._expect_agent!r}")
        if self._expect_version is not None and h.map_version != self._expect_version:
            raise InconsistentChunks(f"map version {h.map_version}, expected "
                                     f"{self._expect_version}")
        if self._key is not None and key != self._key:
            raise InconsistentChunks(f"chunk header {key} disagrees with {self._key}")
        old = self._chunks.get(h.chunk_index)
        if old is not None:
            if old.digest != dc.digest:
                raise ConflictingDuplicate(f"chunk index {h.chunk_index} re-sent with different content")
            return False
        if self._received + h.count > h.total_count:
            raise InconsistentChunks("chunks hold more Gaussians than the subset total")
        if len(self._chunks) + 1 == h.chunk_count and self._received + h.count != h.total_count:
            raise InconsistentChunks("all chunks received but Gaussian counts do not add up")
        self._key = key
        self._chunks[h.chunk_index] = dc
        self._received += h.count
        self._wire_bytes += h.wire_len
        return True

    def result(self) -> tuple[GaussianArrays, SubsetMeta]:
        """The assembled subset (rows in chunk-index order) and its metadata.

        Raises:
            IncompleteSubset: chunks are missing (or none was added).
        """
        if not self.complete:
            raise IncompleteSubset(f"missing chunks {self.missing()[:16]}"
                                   if self._key else "no chunk received")
        agent, version, count, total, lossless, delta, base_version, base_count, shift = self._key
        arrays = GaussianArrays.concat([self._chunks[i].arrays for i in range(count)])
        return arrays, SubsetMeta(agent_id=agent, map_version=version, total_count=total,
                                  chunk_count=count, lossless=lossless,
                                  wire_bytes=self._wire_bytes, delta=delta,
                                  base_version=base_version, base_count=base_count, kappa_shift=shift)

    def delta_parts(self) -> tuple[np.ndarray, np.ndarray]:
        """(targets, removed) of a complete delta subset, int64, in record order / sorted.

        Raises:
            IncompleteSubset: chunks are missing.  MalformedChunk: not a delta subset.
        """
        if not self.complete:
            raise IncompleteSubset(f"missing chunks {self.missing()[:16]}"
                                   if self._key else "no chunk received")
        if not self._key[5]:
            raise MalformedChunk("not a delta subset")
        ch = [self._chunks[i] for i in range(self._key[2])]
        return (np.concatenate([c.targets for c in ch]),
                np.sort(np.concatenate([c.removed for c in ch])))


class DeltaMismatch(WireError):
    """A delta does not fit its base: wrong base row count, repeated or overlapping targets and
    removals across chunks, or new-row targets that are not base_count, base_count + 1, ..."""


def apply_delta(base: GaussianArrays, records: GaussianArrays, targets: np.ndarray,
                removed: np.ndarray, base_count: int, kappa_shift: int = 0) -> GaussianArrays:
    """Rebuild a subset from its base and a delta (see :func:`encode_delta`).

    Args:
        base: the base subset (must have ``base_count`` rows).
        records: (R,) changed/new Gaussians; targets: (R,) int64 ascending; removed: (D,) int64.
        base_count: the base row count the delta declares.
        kappa_shift: the delta's κ shift (``SubsetMeta.kappa_shift``), >= 0.

    Returns:
        [base rows not removed (replaced by their record when targeted; otherwise κ + ``kappa_shift``
        when active), in base order] followed by the new rows in target order.

    Raises:
        DeltaMismatch: see its docstring.
    """
    if len(base) != base_count:
        raise DeltaMismatch(f"delta declares a {base_count}-row base, the stored base has {len(base)}")
    t = np.asarray(targets, np.int64)
    rm = np.asarray(removed, np.int64)
    if len(t) != len(records):
        raise DeltaMismatch(f"{len(t)} targets for {len(records)} records")
    if (t.size and np.any(np.diff(t) <= 0)) or (rm.size and np.any(np.diff(np.sort(rm)) <= 0)):
        raise DeltaMismatch("repeated delta targets or removed rows across chunks")
    upd = t < base_count
    new = ~upd
    if np.intersect1d(t[upd], rm).size:
        raise DeltaMismatch("a removed row is also replaced")
    if not np.array_equal(t[new], base_count + np.arange(int(new.sum()))):
        raise DeltaMismatch("new-row targets are not consecutive from base_count")
    out = {k: np.array(getattr(base, k), copy=True) for k in GAUSSIAN_FIELDS}
    if kappa_shift:
        if int(kappa_shift) < 0:
            raise DeltaMismatch(f"negative κ shift {kappa_shift}")
        if out["kappa"].size and int(out["kappa"].max()) > np.iinfo(np.int64).max - int(kappa_shift):
            raise DeltaMismatch("κ shift overflows int64")
        out["kappa"][out["active"]] += int(kappa_shift)
    for k in out:
        out[k][t[upd]] = getattr(records, k)[upd]
    keep = np.ones(base_count, bool)
    keep[rm] = False
    kept = GaussianArrays(**{k: v[keep] for k, v in out.items()})
    return GaussianArrays.concat([kept, records.take(new)])


def spatial_order(means: Any, cell: float = 2.5e-4) -> np.ndarray:
    """Row permutation sorting points along a 3D Morton (Z-order) curve.

    Rows in this order make previous-row prediction (the predict mask) effective; encoders may send
    rows in any order, this is only a compression aid.

    Args:
        means: (N, 3) positions (metres); cell: quantisation cell of the curve (metres, > 0).

    Returns:
        (N,) int64 permutation (stable for ties).
    """
    m = np.asarray(as_numpy(means), np.float64).reshape(-1, 3)
    if len(m) == 0:
        return np.zeros(0, np.int64)
    q = np.floor((m - m.min(axis=0)) / cell).astype(np.int64)
    q = np.clip(q, 0, (1 << 21) - 1).astype(np.uint64)
    code = np.zeros(len(m), np.uint64)
    for b in range(21):
        for a in range(3):
            code |= ((q[:, a] >> np.uint64(b)) & np.uint64(1)) << np.uint64(3 * b + a)
    return np.argsort(code, kind="stable")


def assemble(chunks: Iterable[Any], limits: WireLimits = DEFAULT_LIMITS
             ) -> tuple[GaussianArrays, SubsetMeta]:
    """Decode and assemble a complete subset from its chunks (any order, duplicates allowed).

    Raises:
        WireError subclasses (see :class:`SubsetAssembler`), IncompleteSubset when chunks are
        missing or ``chunks`` is empty.
    """
    asm = SubsetAssembler(limits)
    for c in chunks:
        asm.add(c)
    return asm.result()
