"""The ``.spz`` codec (gausslite.viewer.spz): its bytes read against the layout its docstring gives, files of the
other versions built here by hand (3-byte rotations, zstd streams, higher SH bands), and what it refuses."""

from __future__ import annotations

import gzip
import struct

import numpy as np
import pytest
import zstandard

from gausslite.viewer.spz import MAGIC, decode_spz, encode_spz


def _gaussians(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    return dict(means=rng.normal(0, 5, (n, 3)).astype(np.float32), log_scales=rng.uniform(-6, 1, (n, 3)),
                quats_wxyz=q / np.linalg.norm(q, axis=1, keepdims=True), opacity_logits=rng.normal(0, 2, n),
                sh_dc=rng.normal(0, 1, (n, 3)))


def test_one_gaussian_is_the_documented_bytes():
    data = encode_spz(np.array([[1.0, -0.5, 2.0]]), np.array([[-10.0, 0.0, 5.9375]]), np.array([[1.0, 0, 0, 0]]),
                      np.array([0.0]), np.array([[0.0, 1.0, -1.0]]))
    assert data == encode_spz(np.array([[1.0, -0.5, 2.0]]), np.array([[-10.0, 0.0, 5.9375]]),
                              np.array([[1.0, 0, 0, 0]]), np.array([0.0]), np.array([[0.0, 1.0, -1.0]]))
    raw = gzip.decompress(data)
    assert struct.unpack_from("<IIIBBBB", raw) == (MAGIC, 3, 1, 0, 12, 0, 0)
    body = raw[16:]
    assert body[:9] == (4096).to_bytes(3, "little") + (2**24 - 2048).to_bytes(3, "little") + (8192).to_bytes(3, "little")
    assert body[9] == 128  # round(sigmoid(0) · 255)
    assert list(body[10:13]) == [128, 166, 89]  # round(c · 0.15 · 255 + 127.5)
    assert list(body[13:16]) == [0, 160, 255]  # round((s + 10) · 16)
    assert struct.unpack_from("<I", body, 16)[0] == 3 << 30  # w is the largest; x = y = z = 0
    assert len(body) == 20


def test_round_trip_within_the_quantisation():
    g = _gaussians(2000)
    d = decode_spz(encode_spz(**g))
    np.testing.assert_allclose(d["means"], g["means"], atol=2.0 ** -13 + 1e-6)
    np.testing.assert_allclose(d["log_scales"], g["log_scales"], atol=1 / 32 + 1e-6)
    np.testing.assert_allclose(d["sh_dc"], np.clip(g["sh_dc"], -127.5 / 38.25, 127.5 / 38.25), atol=0.5 / 38.25 + 1e-6)
    alpha = 1 / (1 + np.exp(-g["opacity_logits"]))
    np.testing.assert_allclose(1 / (1 + np.exp(-d["opacity_logits"].astype(np.float64))), alpha, atol=0.5 / 255 + 1e-6)
    assert np.abs((d["quats_wxyz"] * g["quats_wxyz"]).sum(1)).min() > 0.999
    np.testing.assert_allclose(np.linalg.norm(d["quats_wxyz"], axis=1), 1.0, atol=1e-6)
    empty = decode_spz(encode_spz(**_gaussians(0)))
    assert all(len(v) == 0 for v in empty.values())


def _sections(n: int, rot: int, sh_rest: int) -> bytes:
    pos = (np.arange(3 * n).reshape(n, 3) * 4096).astype("<u4").view(np.uint8).reshape(n, 3, 4)[:, :, :3]
    rows = [pos.tobytes(), bytes([255] * n), bytes([128] * 3 * n), bytes([160] * 3 * n)]
    rows.append(bytes([128, 128, 128] * n) if rot == 3 else struct.pack("<I", 3 << 30) * n)
    return b"".join(rows) + bytes([7] * 3 * sh_rest * n)


@pytest.mark.parametrize("version", [2, 3, 4])
def test_other_versions_and_sh_bands_read(version):
    n, degree = 4, 1
    body = _sections(n, 3 if version == 2 else 4, 3)
    if version < 4:
        data = gzip.compress(struct.pack("<IIIBBBB", MAGIC, version, n, degree, 12, 0, 0) + body)
    else:
        cuts = np.cumsum([0, 9 * n, n, 3 * n, 3 * n, 4 * n, 9 * n])
        streams = [zstandard.ZstdCompressor().compress(body[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
        head = struct.pack("<IIIBBBBI", MAGIC, 4, n, degree, 12, 0, len(streams), 32) + bytes(12)
        table = b"".join(struct.pack("<QQ", len(s), b - a) for s, a, b in zip(streams, cuts[:-1], cuts[1:]))
        data = head + table + b"".join(streams)
    d = decode_spz(data)
    np.testing.assert_array_equal(d["means"], np.arange(3 * n).reshape(n, 3))
    np.testing.assert_allclose(d["quats_wxyz"], np.tile([1.0, 0, 0, 0], (n, 1)), atol=0.02)
    np.testing.assert_allclose(d["log_scales"], 0.0)
    assert (d["opacity_logits"] > 13).all() and np.abs(d["sh_dc"]).max() < 0.02


def test_what_it_refuses():
    with pytest.raises(ValueError, match="not an SPZ file"):
        decode_spz(b"not an spz file")
    with pytest.raises(ValueError, match="not an SPZ file"):
        decode_spz(gzip.compress(struct.pack("<IIIBBBB", 0x1234, 3, 0, 0, 12, 0, 0)))
    with pytest.raises(ValueError, match="version 1"):
        decode_spz(gzip.compress(struct.pack("<IIIBBBB", MAGIC, 1, 0, 0, 12, 0, 0)))
    with pytest.raises(ValueError, match="SH degree 4"):
        decode_spz(gzip.compress(struct.pack("<IIIBBBB", MAGIC, 3, 0, 4, 12, 0, 0)))
    with pytest.raises(ValueError, match="needed for 2 Gaussians"):
        decode_spz(gzip.compress(struct.pack("<IIIBBBB", MAGIC, 3, 2, 0, 12, 0, 0) + bytes(20)))
    with pytest.raises(ValueError, match="gzip stream"):
        decode_spz(b"\x1f\x8b" + bytes(30))
    g = _gaussians(3)
    g["means"][1, 0] = 2048.0
    with pytest.raises(ValueError, match="2048 m"):
        encode_spz(**g)
    with pytest.raises(ValueError, match=r"sh_dc must be \(3, 3\)"):
        encode_spz(**{**_gaussians(3), "sh_dc": np.zeros((3, 4))})
