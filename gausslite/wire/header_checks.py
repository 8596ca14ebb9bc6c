"""The checks a wire chunk's header passes before anything in it is decoded (:func:`gausslite.wire.decode.peek_header`
runs them in this order): size, magic and version (:func:`check_prefix`), the declared lengths and the CRC-32
(:func:`check_length_and_crc`), flags and delta fields (:func:`check_flags`), row and chunk counts
(:func:`check_counts`), field widths and quantisation parameters (:func:`check_quantisation`). Each raises a
:class:`~gausslite.wire.format.WireError` subclass; every size is checked against
:class:`~gausslite.wire.format.WireLimits` before anything proportional to it is allocated.
"""

from __future__ import annotations

import math
import struct
import zlib
from typing import Any

from gausslite.wire.format import (
    CRC_TRAILER,
    FLAG_DELTA,
    FLAG_LOSSLESS,
    HEADER_SIZE,
    KNOWN_FLAGS,
    MAGIC,
    PREDICTABLE_FIELDS,
    SUPPORTED_VERSIONS,
    BadMagic,
    ChecksumMismatch,
    LimitExceeded,
    MalformedChunk,
    TruncatedChunk,
    UnsupportedVersion,
    WireLimits,
)

__all__ = ["as_view", "check_prefix", "check_length_and_crc", "check_flags", "check_counts", "check_quantisation",
           "PREFIX"]

#: the magic and format version, read before the rest of the header
PREFIX = struct.Struct("<4sH")


def as_view(data: Any) -> memoryview:
    """``data`` as a memoryview of bytes. Raises TypeError for anything not bytes-like."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return memoryview(data).cast("B") if isinstance(data, memoryview) else memoryview(data)
    raise TypeError(f"chunk must be bytes-like, got {type(data).__name__}")


def check_prefix(buf, size: int, limits: WireLimits) -> int:
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
    if size < PREFIX.size:
        raise TruncatedChunk("no version field")
    version = PREFIX.unpack_from(buf)[1]
    if version not in SUPPORTED_VERSIONS:
        raise UnsupportedVersion(f"format version {version}, supported: "
                                 f"{', '.join(map(str, SUPPORTED_VERSIONS))}")
    if size < HEADER_SIZE:
        raise TruncatedChunk(f"{size} bytes, shorter than the {HEADER_SIZE}-byte header")
    return version


def check_length_and_crc(buf, size: int, alen: int, plen: int, limits: WireLimits) -> None:
    """The declared agent-id and payload lengths against the limits and the chunk's ``size``, then its CRC-32.

    Raises:
        LimitExceeded, TruncatedChunk, MalformedChunk (trailing bytes), ChecksumMismatch.
    """
    if alen > limits.max_agent_id_bytes:
        raise LimitExceeded(f"agent id of {alen} bytes")
    if plen > limits.max_chunk_bytes:
        raise LimitExceeded(f"payload of {plen} bytes")
    expected = HEADER_SIZE + alen + plen + CRC_TRAILER.size
    if size < expected:
        raise TruncatedChunk(f"{size} bytes, header declares {expected}")
    if size > expected:
        raise MalformedChunk(f"{size - expected} trailing bytes")
    (crc,) = CRC_TRAILER.unpack_from(buf, size - CRC_TRAILER.size)
    if zlib.crc32(buf[: size - CRC_TRAILER.size]) != crc:
        raise ChecksumMismatch("CRC-32 mismatch")


def check_flags(version: int, flags: int, kappa_shift: int, predict_mask: int, map_version: int,
                 base_version: int, base_count: int, n_removed: int, limits: WireLimits) -> tuple[bool, bool]:
    """Flags, κ shift, predict mask and delta fields of a header; returns ``(lossless, delta)``.

    Raises:
        MalformedChunk, LimitExceeded (a delta base above ``limits.max_total_gaussians``).
    """
    if flags & ~KNOWN_FLAGS:
        raise MalformedChunk(f"unknown flags {flags:#x}")
    if kappa_shift and (version < 3 or not flags & FLAG_DELTA):
        raise MalformedChunk(f"κ shift {kappa_shift} in a {'format 2' if version < 3 else 'full'} chunk "
                             "(reserved, must be 0)")
    lossless = bool(flags & FLAG_LOSSLESS)
    delta = bool(flags & FLAG_DELTA)
    if predict_mask >> PREDICTABLE_FIELDS or (predict_mask and lossless):
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


def check_counts(n: int, total: int, count_chunks: int, index: int, limits: WireLimits) -> None:
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


def check_quantisation(lossless: bool, mb: int, qb: int, sb: int, ob: int, cb: int, kb: int, floats: tuple) -> None:
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
