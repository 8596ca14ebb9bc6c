"""Wire codec for Gaussian subsets: versioned, chunked, quantised, zstd-compressed, checksummed.

Source: paper Sec. III-E ("Multi-Agent Refinement": agents exchange only their ROI subset with the
per-Gaussian active-optimisation count κ).  Byte layout: ``docs/wire-format.md``.

This module is the codec's public face; the code is split by concern:

* :mod:`gausslite.wire.format`: constants, header and chunk layouts, :class:`QuantConfig` (and the
  precision of the quantised mode), :class:`WireLimits`, the parsed-header and metadata types, and the
  :class:`WireError` hierarchy;
* :mod:`gausslite.wire.encode`: :func:`encode_subset`, :func:`encode_delta`, :func:`pack_sections`,
  :func:`spatial_order`;
* :mod:`gausslite.wire.decode`: :func:`peek_header`, :func:`decode_chunk`, :func:`raw_payload`,
  :class:`SubsetAssembler`, :func:`assemble`, :func:`apply_delta` (hostile input raises only
  :class:`WireError` subclasses).

Every name below is re-exported unchanged, so ``from gausslite.wire.codec import ...`` keeps working.
"""

from __future__ import annotations

from gausslite.wire.decode import SubsetAssembler, apply_delta, assemble, decode_chunk, peek_header, raw_payload
from gausslite.wire.encode import encode_delta, encode_subset, pack_sections, spatial_order
from gausslite.wire.format import (  # noqa: F401 - the constants outside __all__ stay importable here
    DEFAULT_LIMITS,
    FLAG_DELTA,
    FLAG_LOSSLESS,
    FLAG_SHUFFLE,
    FORMAT_VERSION,
    GAUSSIAN_FIELDS,
    HEADER_SIZE,
    LOSSLESS,
    MAGIC,
    MAX_KAPPA_SHIFT,
    SUPPORTED_VERSIONS,
    BadMagic,
    ChecksumMismatch,
    ChunkHeader,
    ConflictingDuplicate,
    DecodedChunk,
    DeltaMismatch,
    GaussianArrays,
    IncompleteSubset,
    InconsistentChunks,
    LimitExceeded,
    MalformedChunk,
    NonFiniteValues,
    QuantConfig,
    SubsetMeta,
    TruncatedChunk,
    UnsupportedVersion,
    WireError,
    WireLimits,
    raw_bytes_per_gaussian,
    section_lengths,
)

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
