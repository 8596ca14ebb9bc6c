"""Wire format of Gaussian subsets: constants, header and chunk layouts, fields, limits and errors.

Source: paper Sec. III-E ("Multi-Agent Refinement": agents exchange only their ROI subset with the
per-Gaussian active-optimisation count κ). Subsets travel as chunked, zstd-compressed, versioned binary blocks
with per-chunk checksums; upload is resumable and idempotent by (agent id, map version, chunk index).
Byte layout: ``docs/wire-format.md``.

The codec is split by concern: this module is the format (what the encoder writes and the decoder
accepts); :mod:`gausslite.wire.encode` writes chunks, :mod:`gausslite.wire.decode` validates, decodes and
assembles them; :mod:`gausslite.wire.codec` re-exports the public API of all three.  Everything here is
numpy; torch is only touched when converting from/to :class:`gausslite.gaussians.GaussianMap`.

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
2^(8w).  Rows sorted along a Morton curve (:func:`gausslite.wire.encode.spatial_order`) make the differences small.

Precision of the quantised mode (defaults of :class:`QuantConfig`)
------------------------------------------------------------------
* means: fixed point on a grid of step ``mean_step`` (0.25 mm; 0.5 mm cost 0.10 dB ROI PSNR on Replica room0,
bench.quant_psnr, retired: docs/history.md#quant_psnr) anchored at the chunk's bounding-box
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
  ROI PSNR on room0 (+0.004 dB with 7-bit opacity, bench.quant_psnr, retired: docs/history.md#quant_psnr); 0.27
  degree bound at b = 10.
* log_scales / colours: affine over the chunk's [min, max], clamped to ``scale_clamp`` /
  ``color_clamp``; error <= (hi - lo) / (2 (2^bits - 1)) for values inside the clamp.
* opacity: quantised in opacity space, error in sigmoid(logit) <= 0.5 / (2^bits - 1) (0.0039 at the
  default 7 bits, 0.00196 at 8
  bit); decoded logits are finite (|logit| <= log(2 (2^bits - 1) - 1), 6.23 at 8 bit).
* κ and the active flag are lossless in both modes.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Optional

import numpy as np

from gausslite.core.arrays import GAUSSIAN_FIELDS, GaussianArrays

__all__ = [
    "MAGIC", "FORMAT_VERSION", "SUPPORTED_VERSIONS", "MAX_KAPPA_SHIFT",
    "FLAG_LOSSLESS", "FLAG_SHUFFLE", "FLAG_DELTA", "KNOWN_FLAGS",
    "HEADER", "HEADER_SIZE", "CRC_TRAILER", "SECTION_LENGTH", "PREDICTABLE_FIELDS",
    "QUAT_COMPONENT_BOUND", "QUAT_REST",
    "GaussianArrays", "GAUSSIAN_FIELDS",
    "QuantConfig", "LOSSLESS", "WireLimits", "DEFAULT_LIMITS", "ChunkHeader", "DecodedChunk", "SubsetMeta",
    "field_widths", "raw_length", "raw_section_lengths", "section_lengths", "raw_bytes_per_gaussian",
    "WireError", "TruncatedChunk", "BadMagic", "UnsupportedVersion", "ChecksumMismatch", "LimitExceeded",
    "MalformedChunk", "NonFiniteValues", "InconsistentChunks", "ConflictingDuplicate", "IncompleteSubset",
    "DeltaMismatch",
]

MAGIC = b"GLWC"
FORMAT_VERSION = 3
#: format versions this decoder reads (2: the same layout with the κ shift reserved as 0)
SUPPORTED_VERSIONS = (2, 3)
#: largest κ shift a delta can carry (u16 header field)
MAX_KAPPA_SHIFT = 0xFFFF

#: header flag bits (offset 6): lossless float32 fields, byte-plane shuffle, delta chunk
FLAG_LOSSLESS = 1
FLAG_SHUFFLE = 2
FLAG_DELTA = 4
#: every flag bit the format defines; a chunk with any other bit set is malformed
KNOWN_FLAGS = FLAG_LOSSLESS | FLAG_SHUFFLE | FLAG_DELTA

#: the fixed header (offsets 0..141 of the layout above, little-endian), in field order
HEADER = struct.Struct("<4sHHQIIQIHBBBBBBH3d3d2f2fIIQQII")
HEADER_SIZE = HEADER.size  # 142
#: the u32 CRC-32 trailer of every chunk
CRC_TRAILER = struct.Struct("<I")
#: the u32 compressed length in front of each payload section's zstd frame
SECTION_LENGTH = struct.Struct("<I")

#: smallest-three quaternion code: each stored component lies in [-bound, bound] (bound = 1/sqrt(2))
QUAT_COMPONENT_BOUND = 1.0 / math.sqrt(2.0)
#: smallest-three quaternion code: row i = the three stored components (in order) when component i is the largest
QUAT_REST = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], dtype=np.int64)


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


class DeltaMismatch(WireError):
    """A delta does not fit its base: wrong base row count, repeated or overlapping targets and
    removals across chunks, or new-row targets that are not base_count, base_count + 1, ..."""


# --------------------------------------------------------------------------------------------
# configuration, limits and parsed headers


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
    # 0.25 mm; 0.35 mm cost a further 0.013 dB ROI PSNR on room0 (bench.quant_psnr, retired: docs/history.md#quant_psnr)
    mean_step: float = 2.5e-4
    # on a room0 map (bench.quant_psnr, retired: docs/history.md#quant_psnr), B per active Gaussian / ROI PSNR vs
    # lossless: quat 9, scale 9,
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
# payload layout


def _nbytes(bits: int) -> int:
    return (bits + 7) // 8


def field_widths(lossless: bool, mean_bytes: int, quat_bits: int, scale_bits: int,
                 opacity_bits: int, color_bits: int, kappa_bytes: int,
                 delta: bool = False) -> list[tuple[int, int]]:
    """The per-row fields of the payload table above, as the encoder writes and the decoder reads them.

    Args:
        lossless: the lossless flag (float32 fields; the bit widths are then ignored).
        mean_bytes: bytes per mean axis (1..4); quat_bits: bits per smallest-three component;
        scale_bits, opacity_bits, color_bits: code bits; kappa_bytes: zigzag κ bytes (0..8).
        delta: a delta chunk (the targets field is present).

    Returns:
        [(components C, bytes per value w)] of means, quats, log_scales, opacity, colors, kappa, targets
        (targets: (1, 4) in delta chunks, (1, 0) otherwise).
    """
    t = (1, 4 if delta else 0)
    if lossless:
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


def raw_section_lengths(n: int, widths: list[tuple[int, int]], removed: int = 0) -> list[int]:
    """Raw (decompressed) byte length of each payload section of a chunk.

    Args:
        n: rows of the chunk; widths: :func:`field_widths` of its header; removed: removed rows it lists (delta).

    Returns:
        the six attribute fields' lengths, in delta chunks then the targets' and removed rows' (4 bytes each),
        then the packed active bits (ceil(n / 8)).
    """
    out = [n * c * w for c, w in widths[:6]]
    if widths[6][1]:
        out += [n * 4, removed * 4]
    return out + [(n + 7) // 8]


def raw_length(n: int, widths: list[tuple[int, int]], removed: int = 0) -> int:
    """Raw payload length in bytes (the header field at offset 110): the sum of :func:`raw_section_lengths`."""
    return sum(raw_section_lengths(n, widths, removed))


#: header predict-mask bits: bit i set = field i of :func:`field_widths` (means, quats,
#: log_scales, opacity, colors, kappa) is coded as zigzagged wrapped differences from the previous row
PREDICTABLE_FIELDS = 6


def raw_bytes_per_gaussian(quant: QuantConfig = QuantConfig(), kappa_bytes: int = 2,
                           mean_bytes: int = 2) -> float:
    """Uncompressed payload bytes per Gaussian for a configuration (before zstd).

    Args:
        quant: the configuration; kappa_bytes: zigzag κ width; mean_bytes: mean code width.
    """
    w = field_widths(quant.lossless, mean_bytes, quant.quat_bits, quant.scale_bits, quant.opacity_bits,
                     quant.color_bits, kappa_bytes)
    return sum(c * x for c, x in w) + 0.125


def section_lengths(h: ChunkHeader) -> list[int]:
    """Raw byte length of each payload section of a chunk with header ``h`` (see the layout)."""
    return raw_section_lengths(h.count, field_widths(
        h.lossless, h.mean_bytes, h.quat_bits, h.scale_bits, h.opacity_bits, h.color_bits,
        h.kappa_bytes, h.delta), h.removed_count)
