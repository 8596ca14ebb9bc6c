"""Golden wire-format vectors (tests/data/wire, docs/wire-format.md §10): the checked-in chunks must
decode to the checked-in arrays, and an independent reading of the documented byte layout (header
offsets, CRC, section framing) must agree with the codec. ``tests/data/wire`` holds format 3 (the
current one); ``tests/data/wire/v2`` the format-2 vectors, which decoders still read."""

from __future__ import annotations

import hashlib
import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
import zstandard

from gausslite.wire import (FORMAT_VERSION, SUPPORTED_VERSIONS, GaussianArrays, MalformedChunk, apply_delta,
                            decode_chunk, peek_header, raw_payload)

DATA = Path(__file__).resolve().parents[1] / "data" / "wire"
DIRS = {3: DATA, 2: DATA / "v2"}
VECTORS = [dict(v, dir=str(d), format=f) for f, d in DIRS.items()
           for v in json.loads((d / "vectors.json").read_text())["vectors"]]
IDS = [f"v{v['format']}/{v['file']}" for v in VECTORS]

# docs/wire-format.md §3: (offset, struct format) of every fixed header field
LAYOUT = {
    "magic": (0, "4s"), "version": (4, "H"), "flags": (6, "H"), "map_version": (8, "Q"),
    "chunk_index": (16, "I"), "chunk_count": (20, "I"), "total_count": (24, "Q"), "count": (32, "I"),
    "agent_len": (36, "H"), "mean_bytes": (38, "B"), "quat_bits": (39, "B"), "scale_bits": (40, "B"),
    "opacity_bits": (41, "B"), "color_bits": (42, "B"), "kappa_bytes": (43, "B"), "kappa_shift": (44, "H"),
    "mean_origin": (46, "3d"), "mean_step": (70, "3d"), "scale_range": (94, "2f"), "color_range": (102, "2f"),
    "raw_len": (110, "I"), "payload_len": (114, "I"), "base_version": (118, "Q"), "base_count": (126, "Q"),
    "removed_count": (134, "I"), "predict_mask": (138, "I"),
}


def _field(buf: bytes, name: str):
    off, fmt = LAYOUT[name]
    v = struct.unpack_from("<" + fmt, buf, off)
    return v[0] if len(v) == 1 else tuple(v)


def test_vectors_exist_and_pin_the_format_version():
    assert FORMAT_VERSION == 3 and SUPPORTED_VERSIONS == (2, 3)
    for f, d in DIRS.items():
        assert json.loads((d / "vectors.json").read_text())["format_version"] == f
        vecs = [v for v in VECTORS if v["format"] == f]
        assert {v["file"].rsplit("_", 1)[0] for v in vecs} == {
            "quantised_predicted", "quantised_unshuffled", "lossless", "two_chunks", "delta"}
        assert all(v["header"]["version"] == f for v in vecs)
        assert any(v["header"]["predict_mask"] for v in vecs)
        assert any(v["header"]["delta"] for v in vecs)
    assert [v["header"]["kappa_shift"] for v in VECTORS if v["format"] == 3 and v["header"]["delta"]] == [12]


@pytest.mark.parametrize("vec", VECTORS, ids=IDS)
def test_golden_chunk_decodes_to_the_golden_arrays(vec):
    data = (Path(vec["dir"]) / vec["file"]).read_bytes()
    h = peek_header(data)
    for k, v in vec["header"].items():
        got = getattr(h, k)
        assert (list(got) if isinstance(got, tuple) else got) == v, k
    assert hashlib.sha256(raw_payload(data)).hexdigest() == vec["raw_payload_sha256"]
    dc = decode_chunk(data)
    want = GaussianArrays(**{k: np.asarray(v) for k, v in vec["decoded"].items()})
    assert dc.arrays.equals(want)
    if "targets" in vec:
        assert dc.targets.tolist() == vec["targets"] and dc.removed.tolist() == vec["removed"]


@pytest.mark.parametrize("vec", VECTORS, ids=IDS)
def test_documented_layout_read_independently(vec):
    """A reader written from docs/wire-format.md alone: fixed offsets, CRC-32 trailer, then
    per-section (u32 length, zstd frame) framing of the payload."""
    data = (Path(vec["dir"]) / vec["file"]).read_bytes()
    h = vec["header"]
    assert _field(data, "magic") == b"GLWC" and _field(data, "version") == vec["format"]
    assert _field(data, "kappa_shift") == h.get("kappa_shift", 0)  # format 2: reserved, 0
    for name in ("map_version", "chunk_index", "chunk_count", "total_count", "count", "mean_bytes",
                 "quat_bits", "scale_bits", "opacity_bits", "color_bits", "kappa_bytes", "raw_len",
                 "payload_len", "base_version", "base_count", "removed_count", "predict_mask"):
        assert _field(data, name) == h[name], name
    flags = _field(data, "flags")
    assert (bool(flags & 1), bool(flags & 2), bool(flags & 4)) == (h["lossless"], h["shuffle"], h["delta"])
    alen = _field(data, "agent_len")
    assert data[142:142 + alen].decode() == h["agent_id"]
    assert struct.unpack_from("<I", data, len(data) - 4)[0] == zlib.crc32(data[:-4])
    payload = data[142 + alen:len(data) - 4]
    assert len(payload) == h["payload_len"]
    raw, off, sections = b"", 0, 0
    while off < len(payload):
        (clen,) = struct.unpack_from("<I", payload, off)
        frame = payload[off + 4:off + 4 + clen]
        raw += zstandard.ZstdDecompressor().decompress(frame)
        off += 4 + clen
        sections += 1
    assert sections == (9 if h["delta"] else 7)
    assert len(raw) == h["raw_len"]
    assert hashlib.sha256(raw).hexdigest() == vec["raw_payload_sha256"]


def test_golden_delta_kappa_shift_applies_to_kept_unreplaced_base_rows():
    """§6: the rebuilt subset's kept, unreplaced active base rows carry base κ + the header's κ shift;
    inactive ones keep their κ."""
    vec = next(v for v in VECTORS if v["format"] == 3 and v["header"]["delta"])
    dc = decode_chunk((Path(vec["dir"]) / vec["file"]).read_bytes())
    n = dc.header.base_count
    base = GaussianArrays(means=np.zeros((n, 3), np.float32), quats=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                          log_scales=np.zeros((n, 3), np.float32), opacity_logits=np.zeros(n, np.float32),
                          colors=np.zeros((n, 3), np.float32), kappa=np.arange(n) * 10,
                          active=np.array([True, True, False, True, True]))
    out = apply_delta(base, dc.arrays, dc.targets, dc.removed, n, dc.header.kappa_shift)
    # base rows 0 and 3 removed, row 1 replaced, rows 2 (inactive) and 4 kept: κ 20, 40 + 12; then the new rows
    assert out.kappa.tolist() == [int(dc.arrays.kappa[0]), 20, 52] + dc.arrays.kappa[1:].tolist()


@pytest.mark.parametrize("fmt,delta", [(2, True), (3, False)])
def test_kappa_shift_outside_a_format3_delta_is_rejected(fmt, delta):
    """A non-zero κ shift is malformed in format 2 (reserved) and in full chunks."""
    vec = next(v for v in VECTORS if v["format"] == fmt and v["header"]["delta"] == delta)
    data = bytearray((Path(vec["dir"]) / vec["file"]).read_bytes())
    struct.pack_into("<H", data, 44, 5)
    struct.pack_into("<I", data, len(data) - 4, zlib.crc32(bytes(data[:-4])))
    with pytest.raises(MalformedChunk, match="κ shift 5"):
        peek_header(bytes(data))
