"""Encoder of the wire format: Gaussian subsets and deltas to self-describing ``GLWC`` chunks.

Source: paper Sec. III-E (agents exchange only their ROI subset with the per-Gaussian active-optimisation
count κ).  The byte layout, the quantisers' precision and the limits are specified in
:mod:`gausslite.wire.format` and ``docs/wire-format.md``; :mod:`gausslite.wire.decode` reads what this module
writes.  Pure numpy + zstandard.
"""

from __future__ import annotations

import math
import zlib
from typing import Any, Optional, Sequence

import numpy as np
import zstandard

from gausslite.core.arrays import GaussianArrays, as_numpy
from gausslite.wire.format import (
    CRC_TRAILER,
    DEFAULT_LIMITS,
    FLAG_DELTA,
    FLAG_LOSSLESS,
    FLAG_SHUFFLE,
    FORMAT_VERSION,
    HEADER,
    HEADER_SIZE,
    MAGIC,
    MAX_KAPPA_SHIFT,
    PREDICTABLE_FIELDS,
    QUAT_COMPONENT_BOUND,
    QUAT_REST,
    SECTION_LENGTH,
    QuantConfig,
    WireLimits,
    field_widths,
    raw_length,
    raw_section_lengths,
)

__all__ = ["encode_subset", "encode_delta", "pack_sections", "spatial_order"]


# --------------------------------------------------------------------------------------------
# byte planes and quantisers


def _write_field(values: np.ndarray, width: int, shuffle: bool) -> bytes:
    """(n, C) or (n,) unsigned ints (< 2^(8 width)) → C·n·width bytes (the layout of
    :mod:`gausslite.wire.format`)."""
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


def _gaps_encode(sorted_vals: np.ndarray) -> np.ndarray:
    """Strictly increasing non-negative ints → gaps g0 = v0, gi = vi − v(i−1) − 1."""
    v = np.asarray(sorted_vals, np.int64)
    if v.size == 0:
        return v.astype(np.uint64)
    return np.diff(v, prepend=np.int64(-1)).astype(np.uint64) - np.uint64(1)


def _zigzag(k: np.ndarray) -> np.ndarray:
    k = k.astype(np.int64)
    return ((k << 1) ^ (k >> 63)).view(np.uint64)


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


def _quat_encode(q: np.ndarray, bits: int) -> np.ndarray:
    q = q.astype(np.float64)
    norm = np.sqrt((q * q).sum(axis=1))
    bad = norm == 0
    q = np.where(bad[:, None], np.array([1.0, 0.0, 0.0, 0.0]), q / np.where(bad, 1.0, norm)[:, None])
    idx = np.argmax(np.abs(q), axis=1)
    sign = np.where(np.take_along_axis(q, idx[:, None], 1)[:, 0] < 0, -1.0, 1.0)
    rest = np.take_along_axis(q, QUAT_REST[idx], 1) * sign[:, None]
    m = (1 << bits) - 1
    u = np.clip(np.rint((rest + QUAT_COMPONENT_BOUND) / (2 * QUAT_COMPONENT_BOUND) * m), 0, m).astype(np.uint64)
    b = np.uint64(bits)
    return ((idx.astype(np.uint64) << (b * np.uint64(3))) | (u[:, 0] << (b * np.uint64(2)))
            | (u[:, 1] << b) | u[:, 2])


def _opacity_encode(logit: np.ndarray, bits: int) -> np.ndarray:
    m = (1 << bits) - 1
    p = 1.0 / (1.0 + np.exp(-logit.astype(np.float64)))
    return np.clip(np.rint(p * m), 0, m).astype(np.uint64)


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
    widths = field_widths(quant.lossless, mb, qb, sb, ob, cb, kb, is_delta)
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
    for i, (c, w) in enumerate(widths[:PREDICTABLE_FIELDS]):
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
    payload = b"".join(SECTION_LENGTH.pack(len(z)) + z for z in map(cctx.compress, sections))
    r = 0 if removed is None else len(removed)
    assert len(raw) == raw_length(n, widths, r)
    flags = ((FLAG_LOSSLESS if quant.lossless else 0) | (FLAG_SHUFFLE if sh else 0)
             | (FLAG_DELTA if is_delta else 0))
    head = HEADER.pack(
        MAGIC, FORMAT_VERSION, flags, map_version, index, count, total, n, len(agent),
        mb, qb, sb, ob, cb, kb, int(kappa_shift), *map(float, origin), *map(float, step), *srange, *crange,
        len(raw), len(payload), int(base_version), int(base_count), r, predict,
    )
    body = head + agent + payload
    return body + CRC_TRAILER.pack(zlib.crc32(body))


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
        chunk with zero Gaussians).  Row order is preserved through :func:`gausslite.wire.decode.assemble`.

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

    The receiver rebuilds the new subset with :func:`gausslite.wire.decode.apply_delta`: the base subset (``base_count``
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
    overhead = HEADER_SIZE + len(agent) + CRC_TRAILER.size
    if max_chunk_bytes is not None:
        max_chunk_bytes = int(max_chunk_bytes)
        if max_chunk_bytes > limits.max_chunk_bytes:
            raise ValueError("max_chunk_bytes exceeds limits.max_chunk_bytes")
        kb = _width_for(int(_zigzag(arr.kappa).max())) if n else 0
        mb = 4 if quant.lossless else _mean_params(arr.means, quant)[2]
        widths = field_widths(quant.lossless, mb, quant.quat_bits, quant.scale_bits,
                               quant.opacity_bits, quant.color_bits, kb, delta is not None)
        n_rm = 0 if delta is None else len(delta[3])
        # worst case: every removed index lands in one chunk
        fits = lambda k: overhead + sum(  # noqa: E731
            SECTION_LENGTH.size + _zstd_bound(x) for x in raw_section_lengths(k, widths, n_rm)) <= max_chunk_bytes
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
        out.append(SECTION_LENGTH.pack(len(z)) + z)
        off += k
    return b"".join(out)


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
