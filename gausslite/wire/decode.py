"""Decoder of the wire format: validation, decoding and assembly of ``GLWC`` chunks, and delta application.

Source: paper Sec. III-E.  The byte layout is specified in :mod:`gausslite.wire.format` and
``docs/wire-format.md``; :mod:`gausslite.wire.encode` writes what this module reads.  Uploads are resumable
and idempotent by (agent id, map version, chunk index): :class:`SubsetAssembler` accepts chunks in any order
and ignores identical re-deliveries.  The checks of a header before anything is decoded are
:mod:`gausslite.wire.header_checks`'.  Pure numpy + zstandard.

Hostile input
-------------
:func:`decode_chunk` and :class:`SubsetAssembler` raise only :class:`~gausslite.wire.format.WireError`
subclasses on bad bytes (after a ``TypeError`` for a non-bytes argument).  Sizes are checked against
:class:`~gausslite.wire.format.WireLimits` before any allocation proportional to a header field, and the zstd
frame's declared content size must equal the (bounded) expected raw length before decompression.
"""

from __future__ import annotations

import hashlib
from typing import Any, Iterable, Optional

import numpy as np
import zstandard

from gausslite.core.arrays import GAUSSIAN_FIELDS, GaussianArrays
from gausslite.wire.format import (
    DEFAULT_LIMITS,
    FLAG_SHUFFLE,
    HEADER,
    HEADER_SIZE,
    QUAT_COMPONENT_BOUND,
    QUAT_REST,
    SECTION_LENGTH,
    ChunkHeader,
    ConflictingDuplicate,
    DecodedChunk,
    DeltaMismatch,
    IncompleteSubset,
    InconsistentChunks,
    MalformedChunk,
    NonFiniteValues,
    SubsetMeta,
    WireLimits,
    field_widths,
    raw_length,
    section_lengths,
)
from gausslite.wire.header_checks import (as_view, check_counts, check_flags, check_length_and_crc, check_prefix,
                                          check_quantisation)

__all__ = ["peek_header", "decode_chunk", "raw_payload", "SubsetAssembler", "assemble", "apply_delta"]

# --------------------------------------------------------------------------------------------
# byte planes and dequantisers


def _read_field(buf: memoryview, n: int, c: int, width: int, shuffle: bool) -> np.ndarray:
    """Read C·n·width bytes written as in :mod:`gausslite.wire.format` (byte planes when
    ``shuffle``): returns (n, C) uint64."""
    out = np.zeros((c, n, 8), dtype=np.uint8)
    if width and n:
        a = np.frombuffer(buf, dtype=np.uint8, count=c * n * width)
        if shuffle:
            out[:, :, :width] = a.reshape(c, width, n).transpose(0, 2, 1)
        else:
            out[:, :, :width] = a.reshape(c, n, width)
    return out.view("<u8").reshape(c, n).T


def _predict_decode(z: np.ndarray, width: int) -> np.ndarray:
    """Undo previous-row prediction: running sum of the unzigzagged differences modulo 2^(8 width)
    (uint64 in, uint64 out, values < 2^(8 width))."""
    if z.size == 0:
        return z
    mod = 1 << (8 * width)
    zz = z.astype(np.int64)
    sgn = (zz >> 1) ^ -(zz & 1)
    return (np.cumsum(sgn, axis=0) % mod).astype(np.uint64)


def _gaps_decode(g: np.ndarray) -> np.ndarray:
    """Gap codes g0 = v0, gi = vi − v(i−1) − 1 back to the strictly increasing values (int64; every
    value < 2^32 · (n + 1))."""
    return np.cumsum(g.astype(np.int64) + 1) - 1


def _unzigzag(z: np.ndarray) -> np.ndarray:
    z = z.astype(np.uint64)
    return ((z >> np.uint64(1)) ^ (np.uint64(0) - (z & np.uint64(1)))).view(np.int64)


def _affine_decode(q: np.ndarray, lo: float, hi: float, bits: int) -> np.ndarray:
    m = (1 << bits) - 1
    step = (hi - lo) / m if hi > lo else 0.0
    return (lo + q.astype(np.float64) * step).astype(np.float32)


def _quat_decode(p: np.ndarray, bits: int) -> np.ndarray:
    b = np.uint64(bits)
    m = np.uint64((1 << bits) - 1)
    hi = p >> (b * np.uint64(3))
    if hi.size and int(hi.max()) > 3:
        raise MalformedChunk("quaternion largest-component index out of range")
    idx = hi.astype(np.int64)
    u = np.stack([(p >> (b * np.uint64(2))) & m, (p >> b) & m, p & m], axis=1).astype(np.float64)
    rest = u / float(m) * (2 * QUAT_COMPONENT_BOUND) - QUAT_COMPONENT_BOUND
    big = np.sqrt(np.maximum(0.0, 1.0 - (rest * rest).sum(axis=1)))
    out = np.empty((len(p), 4), np.float64)
    np.put_along_axis(out, QUAT_REST[idx], rest, 1)
    np.put_along_axis(out, idx[:, None], big[:, None], 1)
    return out.astype(np.float32)


def _opacity_decode(q: np.ndarray, bits: int) -> np.ndarray:
    m = (1 << bits) - 1
    p = np.clip(q.astype(np.float64) / m, 0.5 / m, 1.0 - 0.5 / m)
    return np.log(p / (1.0 - p)).astype(np.float32)


def peek_header(data: Any, limits: WireLimits = DEFAULT_LIMITS) -> ChunkHeader:
    """Parse and fully validate a chunk's header and checksum, without decompressing.

    Cheap (one CRC pass): servers can route, dedupe (agent, map version, chunk index) and reject
    chunks before decoding.

    Raises:
        TypeError: ``data`` is not bytes-like.
        TruncatedChunk, BadMagic, UnsupportedVersion, ChecksumMismatch, LimitExceeded,
        MalformedChunk: see their docstrings (checked in this order).
    """
    buf = as_view(data)
    size = len(buf)
    version = check_prefix(buf, size, limits)
    (_, _, flags, map_version, index, count_chunks, total, n, alen, mb, qb, sb, ob, cb, kb,
     kappa_shift, ox, oy, oz, sx, sy, sz, slo, shi, clo, chi, raw_len, plen, base_version, base_count,
     n_removed, predict_mask) = HEADER.unpack_from(buf)
    check_length_and_crc(buf, size, alen, plen, limits)
    # ---- semantic validation (a valid CRC says nothing about intent)
    lossless, delta = check_flags(version, flags, kappa_shift, predict_mask, map_version, base_version, base_count,
                                   n_removed, limits)
    if alen == 0:
        raise MalformedChunk("empty agent id")
    try:
        agent_id = bytes(buf[HEADER_SIZE:HEADER_SIZE + alen]).decode("utf-8")
    except UnicodeDecodeError as e:
        raise MalformedChunk(f"agent id is not UTF-8: {e}") from None
    check_counts(n, total, count_chunks, index, limits)
    check_quantisation(lossless, mb, qb, sb, ob, cb, kb, (ox, oy, oz, sx, sy, sz, slo, shi, clo, chi))
    want = raw_length(n, field_widths(lossless, mb, qb, sb, ob, cb, kb, delta), n_removed)
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


# --------------------------------------------------------------------------------------------
# decoding


def raw_payload(data: Any, limits: WireLimits = DEFAULT_LIMITS) -> bytes:
    """The validated chunk's decompressed raw payload (sections concatenated), for debugging and
    conformance tests.  Raises what :func:`peek_header` raises and MalformedChunk."""
    h = peek_header(data, limits)
    start = HEADER_SIZE + len(h.agent_id.encode("utf-8"))
    return _decompress_sections(as_view(data)[start:start + h.payload_len], section_lengths(h))


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
        if off + SECTION_LENGTH.size > len(payload):
            raise MalformedChunk(f"payload ends before the length of {what}")
        (clen,) = SECTION_LENGTH.unpack_from(payload, off)
        off += SECTION_LENGTH.size
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
    """Decode one chunk produced by :func:`gausslite.wire.encode.encode_subset` (or ``encode_delta``).

    Args:
        data: bytes-like chunk.
        limits: decoder limits.

    Returns:
        :class:`DecodedChunk` with float32/int64/bool arrays (see :class:`GaussianArrays`).

    Raises:
        TypeError: ``data`` not bytes-like.  Otherwise only :class:`~gausslite.wire.format.WireError` subclasses:
        everything :func:`peek_header` raises, MalformedChunk (zstd errors, bad quaternion code),
        NonFiniteValues (NaN/inf after decoding).
    """
    h = peek_header(data, limits)
    buf = as_view(data)
    start = HEADER_SIZE + len(h.agent_id.encode("utf-8"))
    raw = _decompress_sections(buf[start:start + h.payload_len], section_lengths(h))
    mv = memoryview(raw)
    n, sh = h.count, h.shuffle
    widths = field_widths(h.lossless, h.mean_bytes, h.quat_bits, h.scale_bits, h.opacity_bits,
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
# assembly and delta application


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


def apply_delta(base: GaussianArrays, records: GaussianArrays, targets: np.ndarray,
                removed: np.ndarray, base_count: int, kappa_shift: int = 0) -> GaussianArrays:
    """Rebuild a subset from its base and a delta (see :func:`gausslite.wire.encode.encode_delta`).

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
