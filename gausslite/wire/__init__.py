"""Wire format for Gaussian subsets exchanged between agents and the fusion server.

Paper Sec. III-E.  The codec is split by concern: :mod:`gausslite.wire.format` (constants, layouts,
configuration, limits, errors), :mod:`gausslite.wire.encode` and :mod:`gausslite.wire.decode`;
:mod:`gausslite.wire.codec` re-exports their public API.  Byte layout, precision and error hierarchy:
``docs/wire-format.md``.  Pure library code (numpy + zstandard); the gRPC services call these functions.
"""

from gausslite.wire.codec import (  # the package exports the codec facade
    DEFAULT_LIMITS,
    FORMAT_VERSION,
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
    GAUSSIAN_FIELDS,
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
    SubsetAssembler,
    apply_delta,
    assemble,
    decode_chunk,
    encode_delta,
    encode_subset,
    pack_sections,
    peek_header,
    raw_bytes_per_gaussian,
    raw_payload,
    section_lengths,
    spatial_order,
)

__all__ = [
    "DEFAULT_LIMITS", "FORMAT_VERSION", "HEADER_SIZE", "LOSSLESS", "MAGIC", "MAX_KAPPA_SHIFT",
    "SUPPORTED_VERSIONS", "BadMagic",
    "ChecksumMismatch", "ChunkHeader", "ConflictingDuplicate", "DecodedChunk", "DeltaMismatch",
    "GAUSSIAN_FIELDS", "GaussianArrays", "IncompleteSubset", "InconsistentChunks", "LimitExceeded", "MalformedChunk",
    "NonFiniteValues", "QuantConfig", "SubsetAssembler", "SubsetMeta", "TruncatedChunk",
    "UnsupportedVersion", "WireError", "WireLimits", "apply_delta", "assemble", "decode_chunk",
    "encode_delta", "encode_subset", "pack_sections", "peek_header", "raw_bytes_per_gaussian",
    "raw_payload", "section_lengths", "spatial_order",
]
