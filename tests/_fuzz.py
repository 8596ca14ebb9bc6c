"""Hypothesis properties of the wire codec (docs/wire-format.md) and the tools of a hostile sender (not a test
module): hostile bytes raise only WireError subclasses, valid subsets and deltas round-trip within the documented
precision. ``tests/wire/test_wire_fuzz.py`` runs every property briefly; at length they ran
100,000 examples without a failure (docs/history.md, "wire_fuzz")."""

from __future__ import annotations

import struct
import zlib
from typing import Callable, Dict

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gausslite.wire import (LOSSLESS, MAX_KAPPA_SHIFT, GaussianArrays, QuantConfig, SubsetAssembler, WireError,
                            apply_delta, assemble, decode_chunk, encode_delta, encode_subset, pack_sections,
                            peek_header, section_lengths, spatial_order)

# fixed header fields (offset, struct format), docs/wire-format.md §3
FIELDS = {
    "version": (4, "<H"), "flags": (6, "<H"), "map_version": (8, "<Q"), "index": (16, "<I"),
    "chunk_count": (20, "<I"), "total": (24, "<Q"), "count": (32, "<I"), "agent_len": (36, "<H"),
    "mean_bytes": (38, "<B"), "quat_bits": (39, "<B"), "scale_bits": (40, "<B"), "opacity_bits": (41, "<B"),
    "color_bits": (42, "<B"), "kappa_bytes": (43, "<B"), "kappa_shift": (44, "<H"), "origin_x": (46, "<d"),
    "step_x": (70, "<d"), "scale_lo": (94, "<f"), "color_hi": (106, "<f"), "raw_len": (110, "<I"),
    "payload_len": (114, "<I"), "base_version": (118, "<Q"), "base_count": (126, "<Q"), "removed": (134, "<I"),
    "predict_mask": (138, "<I"),
}


def random_arrays(n: int, seed: int, extent: float = 3.0) -> GaussianArrays:
    """n random Gaussians (finite values, κ up to 2^40)."""
    rng = np.random.default_rng(seed)
    return GaussianArrays(
        means=rng.uniform(-extent, extent, (n, 3)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.uniform(-8, 0, (n, 3)).astype(np.float32),
        opacity_logits=rng.normal(0, 3, n).astype(np.float32),
        colors=rng.uniform(-0.2, 1.2, (n, 3)).astype(np.float32),
        kappa=rng.integers(-5, 1 << int(rng.integers(1, 41)), n), active=rng.random(n) < 0.5)


VALID = [
    encode_subset(random_arrays(40, 0), "agent-a", 3, chunk_gaussians=25)[0],
    encode_subset(random_arrays(40, 1), "agent-b", 4, chunk_gaussians=25, quant=LOSSLESS)[0],
    encode_delta(random_arrays(6, 2), [1, 4, 9, 10, 11, 12], [0, 2, 7], "agent-c", 9, 5, 9)[0],
    encode_subset(random_arrays(64, 3).take(np.argsort(random_arrays(64, 3).means[:, 0])), "agent-d", 5,
                  quant=QuantConfig(shuffle=False))[0],
]


def only_wire_errors(data: bytes) -> None:
    """Decode ``data``; anything but success or a WireError is a failure (re-raised)."""
    try:
        dc = decode_chunk(data)
    except WireError:
        return
    assert len(dc.arrays) == dc.header.count
    for k in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        assert np.isfinite(getattr(dc.arrays, k)).all()


def forge(chunk: bytes, **values) -> bytes:
    """Overwrite header fields and recompute the CRC, as a hostile sender could."""
    b = bytearray(chunk)
    for name, v in values.items():
        off, fmt = FIELDS[name]
        struct.pack_into(fmt, b, off, v)
    struct.pack_into("<I", b, len(b) - 4, zlib.crc32(bytes(b[:-4])))
    return bytes(b)


def with_payload(chunk: bytes, payload: bytes, **values) -> bytes:
    """Replace the payload (fixing payload_len and the CRC), optionally forging header fields."""
    alen = struct.unpack_from("<H", chunk, 36)[0]
    body = bytearray(chunk[:142 + alen] + payload + b"\0\0\0\0")
    struct.pack_into("<I", body, 114, len(payload))
    return forge(bytes(body), **values)


# ------------------------------------------------------------------------------ properties
def prop_random_bytes(data: bytes) -> None:
    only_wire_errors(data)
    only_wire_errors(b"GLWC\x02\x00" + data)


def prop_mutations(which: int, data) -> None:
    c = bytearray(VALID[which])
    kind = data.draw(st.sampled_from(["flip", "truncate", "insert", "splice"]))
    if kind == "flip":
        for _ in range(data.draw(st.integers(1, 8))):
            i = data.draw(st.integers(0, len(c) - 1))
            c[i] ^= data.draw(st.integers(1, 255))
    elif kind == "truncate":
        c = c[: data.draw(st.integers(0, len(c)))]
    elif kind == "insert":
        i = data.draw(st.integers(0, len(c)))
        c[i:i] = data.draw(st.binary(min_size=1, max_size=16))
    else:
        i = data.draw(st.integers(0, len(c) - 1))
        j = data.draw(st.integers(i, len(c)))
        c[i:j] = data.draw(st.binary(max_size=32))
    only_wire_errors(bytes(c))
    if len(c) >= 4:  # with a valid CRC the mutation reaches the semantic checks and the decoder
        c[-4:] = struct.pack("<I", zlib.crc32(bytes(c[:-4])))
        only_wire_errors(bytes(c))


def prop_forged_fields(which: int, field: str, value: int) -> None:
    off, fmt = FIELDS[field]
    if fmt in ("<d", "<f"):
        v = struct.unpack(fmt, struct.pack("<Q", value)[: struct.calcsize(fmt)])[0]
    else:
        v = value % (1 << (8 * struct.calcsize(fmt)))
    only_wire_errors(forge(VALID[which], **{field: v}))


def prop_forged_raw(which: int, raw_seed: bytes) -> None:
    """Well-formed sections of the right lengths, arbitrary raw content (codes out of range,
    broken quaternion indices, non-finite floats, bad delta gaps)."""
    h = peek_header(VALID[which])
    raw = (raw_seed * (h.raw_len // max(1, len(raw_seed)) + 1))[: h.raw_len] if raw_seed else b"\0" * h.raw_len
    only_wire_errors(with_payload(VALID[which], pack_sections(raw, section_lengths(h))))
    only_wire_errors(with_payload(VALID[which], raw_seed))


def prop_assembler(chunks) -> None:
    asm = SubsetAssembler()
    for c in chunks:
        try:
            asm.add(c)
        except WireError:
            pass
    try:
        out, meta = asm.result()
    except WireError:
        assert not asm.complete
    else:
        assert len(out) == meta.total_count


def prop_round_trip(n: int, seed: int, per: int, extent: float, shuffle: bool, sort: bool) -> None:
    g = random_arrays(n, seed, extent)
    if sort:
        g = g.take(spatial_order(g.means))
    q = QuantConfig(shuffle=shuffle)
    out, meta = assemble(encode_subset(g, "fuzz", seed, chunk_gaussians=per, quant=q))
    assert len(out) == n and meta.total_count == n
    assert np.array_equal(out.kappa, g.kappa) and np.array_equal(out.active, g.active)
    if n:
        f32 = np.abs(g.means).max() * 2 ** -23
        assert np.abs(out.means.astype(np.float64) - g.means).max() <= q.mean_step / 2 + 2 * f32 + 1e-9
    lo, = assemble(encode_subset(g, "fuzz", seed, chunk_gaussians=per, quant=LOSSLESS))[:1]
    assert lo.equals(g)


def prop_delta_round_trip(m: int, seed: int, per: int) -> None:
    rng = np.random.default_rng(seed)
    base = random_arrays(m, seed)
    n_rm = int(rng.integers(0, m + 1))
    perm = rng.permutation(m)
    removed = np.sort(perm[:n_rm])
    upd = np.sort(perm[n_rm:][: int(rng.integers(0, m - n_rm + 1))])
    n_new = int(rng.integers(0, 20))
    targets = np.concatenate([upd, m + np.arange(n_new)])
    recs = random_arrays(len(targets), seed + 1)
    shift = int(rng.integers(0, MAX_KAPPA_SHIFT + 1)) if rng.integers(0, 3) else 0  # 0 in a third of the cases
    chunks = encode_delta(recs, targets, removed, "fuzz", 2, 1, m, chunk_gaussians=per, quant=LOSSLESS,
                          kappa_shift=shift)
    asm = SubsetAssembler()
    for c in reversed(chunks):
        asm.add(c)
    dec, meta = asm.result()
    t, rm = asm.delta_parts()
    assert meta.delta and np.array_equal(t, targets) and np.array_equal(rm, removed) and meta.kappa_shift == shift
    out = apply_delta(base, dec, t, rm, m, meta.kappa_shift)
    assert len(out) == m - n_rm + n_new
    keep = np.setdiff1d(np.arange(m), removed)
    expect = {k: np.array(getattr(base, k), copy=True) for k in GaussianArrays.FIELDS}
    expect["kappa"][expect["active"]] += shift  # active rows only
    for k in expect:
        expect[k][upd] = getattr(recs, k)[: len(upd)]
    want = GaussianArrays.concat([GaussianArrays(**{k: v[keep] for k, v in expect.items()}),
                                  recs.take(slice(len(upd), None))])
    assert out.equals(want)


def properties() -> Dict[str, Callable[[int], Callable[[], None]]]:
    """name → (max_examples → runnable hypothesis test) for every fuzz property."""
    hc = [HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much]
    which = st.integers(0, len(VALID) - 1)

    def wrap(strategies, fn):
        def make(k: int):
            return settings(max_examples=k, deadline=None, suppress_health_check=hc, database=None)(
                given(*strategies)(fn))
        return make

    return {
        "random_bytes": wrap([st.binary(max_size=600)], prop_random_bytes),
        "mutations": wrap([which, st.data()], prop_mutations),
        "forged_fields": wrap([which, st.sampled_from(sorted(FIELDS)), st.integers(0, 2 ** 64 - 1)],
                              prop_forged_fields),
        "forged_raw": wrap([which, st.binary(max_size=300)], prop_forged_raw),
        "assembler": wrap([st.lists(st.binary(max_size=200) | st.sampled_from(VALID), max_size=6)], prop_assembler),
        "round_trip": wrap([st.integers(0, 300), st.integers(0, 2 ** 31), st.integers(1, 128),
                            st.floats(1e-3, 1e4), st.booleans(), st.booleans()], prop_round_trip),
        "delta_round_trip": wrap([st.integers(0, 200), st.integers(0, 2 ** 31), st.integers(1, 64)],
                                 prop_delta_round_trip),
    }
