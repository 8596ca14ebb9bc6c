"""The odometry's image pyramid (gausslite.odometry.pyramid): the reductions Open3D's multi-scale odometry makes, in
arithmetic that repeats on any CPU."""

from __future__ import annotations

import numpy as np
import pytest

from gausslite.odometry.pyramid import GAUSS5, pyrdown_depth, pyrdown_rgb, rgbd_pyramid


def _reference_rgb(img: np.ndarray) -> np.ndarray:
    """The same reduction written as a 2-D weighted sum per output pixel, in float64 (the reference)."""
    h, w = img.shape[:2]
    k = GAUSS5.astype(np.float64)
    out = np.zeros(((h + 1) // 2, (w + 1) // 2) + img.shape[2:])
    for y in range(out.shape[0]):
        for x in range(out.shape[1]):
            for dy in range(-2, 3):
                for dx in range(-2, 3):
                    yy, xx = min(max(2 * y + dy, 0), h - 1), min(max(2 * x + dx, 0), w - 1)
                    out[y, x] += k[dy + 2] * k[dx + 2] * img[yy, xx]
    return out


@pytest.mark.parametrize("shape", [(12, 16, 3), (9, 7, 3), (5, 5)])
def test_the_colour_level_is_the_gaussian_blur_at_every_other_pixel(shape):
    rng = np.random.default_rng(0)
    img = rng.random(shape, dtype=np.float32)
    got = pyrdown_rgb(img)
    assert got.dtype == np.float32 and got.shape[:2] == ((shape[0] + 1) // 2, (shape[1] + 1) // 2)
    np.testing.assert_allclose(got, _reference_rgb(img), rtol=0, atol=2e-6)
    assert abs(float(GAUSS5.sum()) - 1.0) < 1e-6 and np.allclose(GAUSS5, GAUSS5[::-1])
    flat = np.full(shape, 0.25, np.float32)
    np.testing.assert_allclose(pyrdown_rgb(flat), 0.25, atol=1e-7)  # a flat image stays flat


def test_the_depth_level_keeps_edges_and_holes_apart():
    d = np.full((8, 8), 1.0, np.float32)
    d[:, 4:] = 3.0  # a step of 2 m: foreground and background never mix
    d[4, 0] = 0.0  # a hole at a centre sample
    d[1, 2] = np.nan  # a non-finite sample next to a centre
    got = pyrdown_depth(d, 0.14)
    assert got.shape == (4, 4) and got.dtype == np.float32
    assert got[2, 0] == 0.0  # the centre is invalid: the output is
    np.testing.assert_allclose(np.delete(got[:, :2].ravel(), 4), 1.0, atol=1e-6)
    np.testing.assert_allclose(got[:, 2:], 3.0, atol=1e-6)
    # within the bound the samples average with the Gaussian's weights
    ramp = np.tile(np.arange(10, dtype=np.float32) * 0.01 + 1.0, (10, 1))
    got = pyrdown_depth(ramp, 1.0)
    np.testing.assert_allclose(got[2, 2], ramp[4, 4], atol=1e-6)  # a linear ramp's weighted mean is its centre
    with pytest.raises(ValueError, match="float32"):
        pyrdown_depth(ramp.astype(np.float64), 1.0)


def test_the_pyramid_has_a_level_per_iteration_entry_finest_first():
    rng = np.random.default_rng(1)
    rgb, depth = rng.random((120, 160, 3), dtype=np.float32), rng.uniform(0.5, 3, (120, 160)).astype(np.float32)
    levels = rgbd_pyramid(rgb, depth, 3, 0.14)
    assert [c.shape for c, _ in levels] == [(120, 160, 3), (60, 80, 3), (30, 40, 3)]
    assert [d.shape for _, d in levels] == [(120, 160), (60, 80), (30, 40)]
    assert np.array_equal(levels[0][0], rgb)
    # the same input gives the same levels, bit for bit (elementwise float32 arithmetic, one process)
    again = rgbd_pyramid(rgb.copy(), depth.copy(), 3, 0.14)
    assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(levels, again))
    with pytest.raises(ValueError, match="at least 1"):
        rgbd_pyramid(rgb, depth, 0, 0.14)
