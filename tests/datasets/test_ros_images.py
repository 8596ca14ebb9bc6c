"""sensor_msgs/Image and CompressedImage decoding/encoding (gausslite.ros.images)."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from gausslite.ros.images import (
    ImageDecodeError,
    decode_compressed,
    decode_image,
    encode_compressed,
    encode_compressed_depth,
    encode_image,
)

RNG = np.random.default_rng(3)
RGB = RNG.integers(0, 256, size=(5, 7, 3), dtype=np.uint8)


@pytest.mark.parametrize("enc", ["rgb8", "bgr8", "rgba8", "bgra8"])
def test_colour_encodings_round_trip(enc):
    h, w, step, data = encode_image(RGB, enc)
    assert (h, w, step) == (5, 7, 7 * len(enc[:-1]))
    kind, out = decode_image(enc, h, w, step, data)
    assert kind == "color" and out.dtype == np.uint8 and np.array_equal(out, RGB)


def test_channel_order_is_interpreted():
    px = np.array([[[10, 20, 30]]], np.uint8)
    assert decode_image("bgr8", 1, 1, 3, px.tobytes())[1].tolist() == [[[30, 20, 10]]]
    assert decode_image("bgra8", 1, 1, 4, bytes([10, 20, 30, 40]))[1].tolist() == [[[30, 20, 10]]]
    assert decode_image("rgba8", 1, 1, 4, bytes([10, 20, 30, 40]))[1].tolist() == [[[10, 20, 30]]]


def test_mono8_and_row_padding():
    g = RNG.integers(0, 256, size=(4, 3), dtype=np.uint8)
    padded = np.zeros((4, 8), np.uint8)
    padded[:, :3] = g
    kind, out = decode_image("mono8", 4, 3, 8, padded.tobytes())
    assert kind == "color" and out.shape == (4, 3, 3) and all(np.array_equal(out[..., c], g) for c in range(3))


def test_depth_16uc1_mm_and_32fc1_m_with_invalids():
    mm = np.array([[0, 1000, 2500], [65535, 1, 300]], np.uint16)
    kind, d = decode_image("16UC1", 2, 3, 6, mm.astype("<u2").tobytes())
    assert kind == "depth" and d.dtype == np.float32
    assert np.allclose(d, mm / 1000.0)
    # big endian
    _, d_be = decode_image("16UC1", 2, 3, 6, mm.astype(">u2").tobytes(), is_bigendian=True)
    assert np.array_equal(d_be, d)
    _, d_m16 = decode_image("mono16", 2, 3, 6, mm.astype("<u2").tobytes())
    assert np.array_equal(d_m16, d)
    m = np.array([[1.25, np.nan, -1.0], [np.inf, 0.0, 3.5]], np.float32)
    _, f = decode_image("32FC1", 2, 3, 12, m.astype("<f4").tobytes())
    assert f.tolist() == [[1.25, 0.0, 0.0], [0.0, 0.0, 3.5]]
    _, f_be = decode_image("32FC1", 2, 3, 12, m.astype(">f4").tobytes(), is_bigendian=True)
    assert np.array_equal(f_be, f)


def test_depth_encode_round_trip():
    d = np.array([[0.0, 1.2346], [2.0, np.nan]], np.float32)
    h, w, step, data = encode_image(d, "32FC1")
    assert np.array_equal(decode_image("32FC1", h, w, step, data)[1], np.nan_to_num(d))
    h, w, step, data = encode_image(d, "16UC1")
    assert np.allclose(decode_image("16UC1", h, w, step, data)[1], [[0.0, 1.235], [2.0, 0.0]], atol=1e-6)


def test_decode_errors():
    with pytest.raises(ImageDecodeError, match=r"unsupported image encoding 'yuv422'.*rgb8.*32FC1"):
        decode_image("yuv422", 2, 2, 4, bytes(8))
    with pytest.raises(ImageDecodeError, match="8 bytes of data, expected 12"):
        decode_image("rgb8", 2, 2, 6, bytes(8))
    with pytest.raises(ImageDecodeError, match="step 4 < 6"):
        decode_image("rgb8", 2, 2, 4, bytes(8))
    with pytest.raises(ImageDecodeError, match="size 0x2"):
        decode_image("rgb8", 2, 0, 0, b"")


@pytest.mark.parametrize("fmt", ["jpeg", "png"])
def test_compressed_colour(fmt):
    img = np.zeros((16, 16, 3), np.uint8)
    img[:, :8] = (200, 30, 10)  # red left half (RGB)
    f, data = encode_compressed(img, fmt)
    kind, out = decode_compressed(f, data)
    assert kind == "color" and out.shape == img.shape
    if fmt == "png":
        assert np.array_equal(out, img)
    else:  # lossy: the interior of each half keeps its colour, in RGB order
        assert np.abs(out[2:-2, 1:5].astype(int) - [200, 30, 10]).max() <= 6
        assert np.abs(out[2:-2, 11:15].astype(int)).max() <= 6
    # a plain "jpeg"/"png" format string (cameras publishing directly) decodes the same
    assert np.array_equal(decode_compressed(fmt, data)[1], out)


def test_compressed_png_16bit_is_depth_mm_and_mono_is_grey():
    mm = np.array([[0, 1500], [3000, 42]], np.uint16)
    ok, buf = cv2.imencode(".png", mm)
    kind, d = decode_compressed("png", buf.tobytes())
    assert kind == "depth" and np.allclose(d, mm / 1000.0)
    g = np.array([[0, 255], [7, 9]], np.uint8)
    ok, buf = cv2.imencode(".png", g)
    kind, c = decode_compressed("mono8; png compressed mono8", buf.tobytes())
    assert kind == "color" and np.array_equal(c[..., 1], g)


def test_compressed_depth_16uc1_exact_and_32fc1_quantised():
    d = np.array([[0.0, 0.5, 1.0], [2.0, 4.0, 9.0]], np.float32)
    fmt, data = encode_compressed_depth(d, "16UC1")
    assert fmt == "16UC1; compressedDepth png" and struct.unpack_from("<iff", data)[0] == 1
    kind, out = decode_compressed(fmt, data)
    assert kind == "depth" and np.array_equal(out, d)
    fmt, data = encode_compressed_depth(d, "32FC1", depth_max=10.0, depth_quantization=100.0)
    kind, out = decode_compressed(fmt, data)
    assert out[0, 0] == 0.0
    # inverse-depth quantisation error: |dd| <= d^2 / (2 A) with A = q (q + 1)
    bound = d ** 2 / (2 * 100 * 101) + 1e-6
    assert np.all(np.abs(out - d) <= bound) and np.abs(out - d)[1, 2] > 0  # it is lossy, within the bound
    # the older format string without "png"
    assert np.array_equal(decode_compressed("32FC1; compressedDepth", data)[1], out)


def test_compressed_errors():
    with pytest.raises(ImageDecodeError, match="unsupported CompressedImage format 'webp'"):
        decode_compressed("webp", b"abc")
    with pytest.raises(ImageDecodeError, match="could not decode"):
        decode_compressed("jpeg", b"not a jpeg")
    rvl = struct.pack("<iff", 2, 0.0, 0.0) + b"\x00" * 8
    with pytest.raises(ImageDecodeError, match="RVL"):
        decode_compressed("16UC1; compressedDepth rvl", rvl)
    with pytest.raises(ImageDecodeError, match="no payload"):
        decode_compressed("16UC1; compressedDepth png", b"\x00" * 12)
    with pytest.raises(ImageDecodeError, match="unsupported encoding '8UC1'"):
        decode_compressed("8UC1; compressedDepth png", b"\x00" * 20)
    ok, buf = cv2.imencode(".png", np.zeros((2, 2), np.uint8))
    with pytest.raises(ImageDecodeError, match="not a 16-bit single-channel PNG"):
        decode_compressed("16UC1; compressedDepth png", struct.pack("<iff", 1, 0, 0) + buf.tobytes())
