"""Wire codec on hostile bytes: only typed WireError subclasses, limits before allocation.
The randomised (hypothesis) hostile-input properties live in ``tests/_fuzz.py``
(``tests/wire/test_wire_fuzz.py`` runs them briefly)."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
import zstandard

from tests._fuzz import forge, with_payload
from gausslite.wire import (
    HEADER_SIZE,
    LOSSLESS,
    BadMagic,
    ChecksumMismatch,
    GaussianArrays,
    LimitExceeded,
    MalformedChunk,
    NonFiniteValues,
    QuantConfig,
    TruncatedChunk,
    UnsupportedVersion,
    WireError,
    WireLimits,
    decode_chunk,
    encode_delta,
    pack_sections,
    raw_payload,
    section_lengths,
    encode_subset,
    peek_header,
)


def _arrays(n: int, seed: int = 0) -> GaussianArrays:
    rng = np.random.default_rng(seed)
    return GaussianArrays(
        means=rng.uniform(-3, 3, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.uniform(-6, -2, (n, 3)).astype(np.float32),
        opacity_logits=rng.normal(0, 3, n).astype(np.float32),
        colors=rng.uniform(0, 1, (n, 3)).astype(np.float32),
        kappa=rng.integers(0, 300, n), active=rng.random(n) < 0.5,
    )


QUANT_CHUNK = encode_subset(_arrays(40), "agent-a", 3, chunk_gaussians=25)[0]
LOSSLESS_CHUNK = encode_subset(_arrays(40, 1), "agent-b", 4, chunk_gaussians=25, quant=LOSSLESS)[0]
DELTA_CHUNK = encode_delta(_arrays(6, 2), [1, 4, 9, 10, 11, 12], [0, 2, 7], "agent-c", 9, 5, 9,
                           chunk_gaussians=25)[0]



def test_specific_failures_raise_the_right_type():
    c = QUANT_CHUNK
    with pytest.raises(TruncatedChunk):
        decode_chunk(c[:2])
    with pytest.raises(TruncatedChunk):
        decode_chunk(c[:HEADER_SIZE - 1])
    with pytest.raises(TruncatedChunk):
        decode_chunk(c[:-1])
    with pytest.raises(BadMagic):
        decode_chunk(b"PLY\n" + c[4:])
    for v in (1, 4):  # format 1 (before delta records) and unknown formats are rejected
        with pytest.raises(UnsupportedVersion):
            decode_chunk(forge(c, version=v))
    bad = bytearray(c)
    bad[HEADER_SIZE + 10] ^= 0x40
    with pytest.raises(ChecksumMismatch):
        decode_chunk(bytes(bad))
    with pytest.raises(MalformedChunk):
        decode_chunk(c + b"\0")
    with pytest.raises(TypeError):
        decode_chunk("not bytes")  # type: ignore[arg-type]
    assert decode_chunk(memoryview(c)).header.agent_id == "agent-a"
    assert decode_chunk(bytearray(c)).header.map_version == 3


def test_absurd_counts_are_rejected_before_allocation():
    c = QUANT_CHUNK
    with pytest.raises(LimitExceeded):
        decode_chunk(forge(c, total=2**40))
    with pytest.raises(LimitExceeded):
        decode_chunk(forge(c, count=2**31, total=2**31))
    with pytest.raises(LimitExceeded):
        decode_chunk(forge(c, chunk_count=2**32 - 1))
    with pytest.raises(LimitExceeded):
        peek_header(forge(c, payload_len=2**32 - 1))
    with pytest.raises(LimitExceeded):
        decode_chunk(c, limits=WireLimits(max_chunk_bytes=len(c) - 1))
    with pytest.raises(LimitExceeded):
        decode_chunk(c, limits=WireLimits(max_chunk_gaussians=10))
    with pytest.raises(LimitExceeded):
        decode_chunk(c, limits=WireLimits(max_agent_id_bytes=3))
    # header count larger than what the raw length implies
    with pytest.raises(MalformedChunk):
        decode_chunk(forge(c, count=26))
    with pytest.raises(MalformedChunk):
        decode_chunk(forge(c, raw_len=2**32 - 1))
    with pytest.raises(MalformedChunk):
        decode_chunk(forge(c, index=7))
    # delta fields: base not older than the version, delta fields on a full chunk, too many removals
    with pytest.raises(MalformedChunk):
        decode_chunk(forge(DELTA_CHUNK, base_version=9))
    with pytest.raises(MalformedChunk):
        decode_chunk(forge(c, base_count=3))
    with pytest.raises(MalformedChunk):
        decode_chunk(forge(DELTA_CHUNK, removed=10))
    with pytest.raises(MalformedChunk):
        decode_chunk(forge(QUANT_CHUNK, predict_mask=1 << 6))


def test_zstd_bomb_and_garbage_payloads_are_rejected():
    h = peek_header(QUANT_CHUNK)
    lengths = section_lengths(h)
    ok = pack_sections(b"\0" * h.raw_len, lengths)
    assert len(decode_chunk(with_payload(QUANT_CHUNK, ok)).arrays) == h.count
    first = struct.unpack_from("<I", ok)[0]
    rest = ok[4 + first:]

    def section(frame: bytes) -> bytes:
        return struct.pack("<I", len(frame)) + frame

    # a first-section frame that declares a much larger content size than the section
    bomb = zstandard.ZstdCompressor(write_content_size=True).compress(b"\0" * (64 << 20))
    with pytest.raises(MalformedChunk, match=rf"section 0 \(means\): the zstd frame declares {64 << 20} bytes of "
                                             rf"content, the chunk header implies {lengths[0]}$"):
        decode_chunk(with_payload(QUANT_CHUNK, section(bomb) + rest))
    # a frame without content size: named as such (zstandard's -1 for "unknown" never reaches the message)
    nosize = zstandard.ZstdCompressor(write_content_size=False).compress(b"\0" * lengths[0])
    with pytest.raises(MalformedChunk, match=r"section 0 \(means\): the zstd frame does not declare its content "
                                             r"size") as err:
        decode_chunk(with_payload(QUANT_CHUNK, section(nosize) + rest))
    assert "-1" not in str(err.value)
    # a section whose frame is followed by a second frame inside its declared length
    fr = zstandard.ZstdCompressor(write_content_size=True).compress(b"\0" * lengths[0])
    with pytest.raises(MalformedChunk):
        decode_chunk(with_payload(QUANT_CHUNK, section(fr + fr) + rest))
    # one single frame of the whole raw payload (format 1 style), trailing bytes, overrun length
    with pytest.raises(MalformedChunk):
        decode_chunk(with_payload(QUANT_CHUNK, zstandard.ZstdCompressor().compress(b"\0" * h.raw_len)))
    with pytest.raises(MalformedChunk):
        decode_chunk(with_payload(QUANT_CHUNK, ok + b"\0"))
    with pytest.raises(MalformedChunk):
        decode_chunk(with_payload(QUANT_CHUNK, struct.pack("<I", 1 << 30) + ok[4:]))
    with pytest.raises(MalformedChunk):
        decode_chunk(with_payload(QUANT_CHUNK, b"\x28\xb5\x2f\xfd garbage garbage"))
    with pytest.raises(MalformedChunk):
        decode_chunk(with_payload(QUANT_CHUNK, b""))


def test_non_finite_values_and_bad_parameters():
    h = peek_header(LOSSLESS_CHUNK)
    raw = bytearray(b"\0" * h.raw_len)
    raw[0:4] = np.float32(np.nan).tobytes()  # shuffled planes: breaks means[0].x
    nan_chunk = with_payload(LOSSLESS_CHUNK, pack_sections(bytes(raw), section_lengths(h)),
                             flags=1)  # lossless, unshuffled
    with pytest.raises(NonFiniteValues):
        decode_chunk(nan_chunk)
    c = QUANT_CHUNK
    for kw in ({"step_x": float("inf")}, {"step_x": -1.0}, {"origin_x": float("nan")},
               {"step_x": 1e308}, {"scale_lo": 5.0}, {"mean_bytes": 9}, {"quat_bits": 2},
               {"scale_bits": 0}, {"kappa_bytes": 9}, {"flags": 0x80}, {"kappa_shift": 1},
               {"agent_len": 0}, {"color_hi": float("inf")}):
        with pytest.raises(WireError):
            decode_chunk(forge(c, **kw))
    with pytest.raises(MalformedChunk):  # lossless chunk carrying quantisation parameters
        decode_chunk(forge(LOSSLESS_CHUNK, quat_bits=9))
    bad_agent = bytearray(c)
    bad_agent[HEADER_SIZE] = 0xFF
    with pytest.raises(MalformedChunk):
        decode_chunk(forge(bytes(bad_agent)))


def test_out_of_range_codes_are_rejected():
    # quat_bits 4 → 14-bit codes in 2 bytes: the top 2 bits (index > 3) are invalid
    g = _arrays(16)
    (c,) = encode_subset(g, "a", 0, quant=QuantConfig(quat_bits=4, scale_bits=4, shuffle=False,
                                                      predict=False))
    h = peek_header(c)
    raw = bytearray(raw_payload(c))
    q_off = 3 * h.mean_bytes * h.count
    raw[q_off + 1] = 0xFF
    with pytest.raises(MalformedChunk):
        decode_chunk(with_payload(c, pack_sections(bytes(raw), section_lengths(h))))
    raw2 = bytearray(raw_payload(c))
    raw2[q_off + 2 * h.count] = 0xFF  # log-scale code 255 with 4 bits
    with pytest.raises(MalformedChunk):
        decode_chunk(with_payload(c, pack_sections(bytes(raw2), section_lengths(h))))
