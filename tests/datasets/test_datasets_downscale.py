"""Downscaling of colour and depth (gausslite.datasets.loader)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gausslite.camera import Intrinsics
from gausslite.datasets import downscale_depth, downscale_rgb


def _blocks(n_out: int, f: float):
    """Independent reference: source pixels whose centres (x + 0.5) fall in [j f, (j+1) f)."""
    return [[x for x in range(int(n_out * f) + 2) if j * f <= x + 0.5 < (j + 1) * f] for j in range(n_out)]


@settings(max_examples=60, deadline=None)
@given(
    h=st.integers(1, 23),
    w=st.integers(1, 23),
    f=st.one_of(st.integers(1, 6), st.floats(1.0, 5.0, allow_nan=False)),
    p_invalid=st.sampled_from([0.0, 0.3, 0.8, 1.0]),
    seed=st.integers(0, 2**16),
)
def test_depth_values_come_from_their_block(h, w, f, p_invalid, seed):
    rng = np.random.default_rng(seed)
    H, W = int(math.ceil(h * f)) + rng.integers(0, 3), int(math.ceil(w * f)) + rng.integers(0, 3)
    src = rng.uniform(0.3, 8.0, size=(H, W)).astype(np.float32)
    src[rng.random((H, W)) < p_invalid] = 0.0
    src[rng.random((H, W)) < 0.05] = np.nan  # non-finite counts as invalid too
    out = downscale_depth(src, f)
    oh, ow = int(H // f), int(W // f)
    assert out.shape == (oh, ow) and out.dtype == np.float32
    assert (Intrinsics(10, 10, 5, 5, W, H).scaled(f).height, Intrinsics(10, 10, 5, 5, W, H).scaled(f).width) == (oh, ow)
    rows, cols = _blocks(oh, float(f)), _blocks(ow, float(f))
    for i in range(oh):
        for j in range(ow):
            block = src[np.ix_(rows[i], cols[j])]
            valid = block[np.isfinite(block) & (block > 0)]
            if valid.size == 0:
                assert out[i, j] == 0
            else:
                assert out[i, j] in valid  # an actual valid sample of the block, never a blend


def test_depth_nearest_to_centre_then_nearest_valid():
    d = np.arange(1, 10, dtype=np.float32).reshape(3, 3)
    assert downscale_depth(d, 3)[0, 0] == 5  # block centre
    d[1, 1] = 0
    assert downscale_depth(d, 3)[0, 0] == 2  # nearest valid: first edge neighbour (row-major)
    d[0, 1] = 0
    assert downscale_depth(d, 3)[0, 0] == 4
    d2 = np.array([[0, 0], [0, 7.5]], np.float32)
    assert downscale_depth(d2, 2)[0, 0] == 7.5
    assert downscale_depth(np.zeros((4, 4), np.float32), 2).max() == 0
    # even factor: the four central samples tie, the top-left one wins
    assert downscale_depth(np.array([[1, 2], [3, 4]], np.float32), 2)[0, 0] == 1


def test_depth_edge_not_blended():
    d = np.ones((8, 8), np.float32)
    d[:, 3:] = 5.0  # depth edge crossing the 4x4 blocks
    out = downscale_depth(d, 4)
    assert set(np.unique(out)) <= {1.0, 5.0}


def test_depth_identity_and_errors():
    d = np.random.default_rng(1).random((5, 6)).astype(np.float32)
    out = downscale_depth(d, 1)
    np.testing.assert_array_equal(out, d)
    assert out is not d
    for bad in (0.5, 0, -2, float("nan"), float("inf"), "2", None, True):
        with pytest.raises(ValueError):
            downscale_depth(d, bad)
    with pytest.raises(ValueError, match="too large"):
        downscale_depth(d, 7)
    with pytest.raises(ValueError, match="2-D"):
        downscale_depth(np.zeros((4, 4, 1)), 2)


def test_rgb_area_average():
    rgb = np.zeros((6, 9, 3), np.uint8)
    rgb[:3, :3] = 30
    rgb[:3, 3:6] = [0, 60, 90]
    rgb[3:, :] = 200
    rgb[:, 6:] = 10
    out = downscale_rgb(rgb, 3)
    assert out.shape == (2, 3, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[0, 0], [30, 30, 30])
    np.testing.assert_array_equal(out[0, 1], [0, 60, 90])
    np.testing.assert_array_equal(out[1, 0], [200, 200, 200])
    checker = np.zeros((4, 4, 3), np.uint8)
    checker[::2, ::2] = 100
    checker[1::2, 1::2] = 100
    np.testing.assert_array_equal(downscale_rgb(checker, 2), np.full((2, 2, 3), 50, np.uint8))
    # float factor: size matches Intrinsics.scaled
    img = np.full((480, 640, 3), 77, np.uint8)
    o = downscale_rgb(img, 2.5)
    i = Intrinsics(500, 500, 319.5, 239.5, 640, 480).scaled(2.5)
    assert o.shape == (i.height, i.width, 3) == (192, 256, 3)
    assert np.all(o == 77)
    np.testing.assert_array_equal(downscale_rgb(img, 1), img)
