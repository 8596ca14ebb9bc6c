"""The image pyramid of the RGB-D odometry, made in NumPy so that a registration repeats exactly on any CPU.

Open3D's multi-scale odometry (``open3d.t.pipelines.odometry.rgbd_odometry_multi_scale``) builds its own pyramid, and
its colour reduction (``Image.pyrdown``: a Gaussian blur and a 2:1 subsample, through the Intel IPP routines bundled
with the wheel) does not repeat on every CPU: on an x86-64 CPU with AVX2 and no AVX-512 the same call on the same
40 × 30 image returns pixels that differ in the last bit from one call to the next, with one thread (docs/mapper.md,
"Poses from odometry": repeatable tracking). A registration started from such a level ends 1e-5 to 1e-4 m away,
and a tracked sequence then parts by up to 4e-4 m over a dozen frames. :class:`~gausslite.odometry.rgbd.
RGBDOdometry` registers one level at a time on the levels made here instead: the same reductions as Open3D's
(colour: a 5-tap Gaussian of σ = 1 pixel, then every other pixel; depth: Open3D's ``PyrDownDepth``), in elementwise
float32 arithmetic whose result does not depend on the vector width.
"""

from __future__ import annotations

from typing import List, Tuple

import numpy as np

__all__ = ["GAUSS5", "BINOMIAL5", "pyrdown_rgb", "pyrdown_depth", "rgbd_pyramid"]

#: the 5-tap Gaussian of σ = 1 pixel, normalised (float32), the kernel of Open3D's ``Image.pyrdown``
GAUSS5 = (lambda g: (g / g.sum()).astype(np.float32))(np.exp(-0.5 * np.arange(-2.0, 3.0) ** 2))
#: the 5-tap binomial kernel (1 4 6 4 1) / 16, the weights of Open3D's ``PyrDownDepth`` (after KinectFusion's
#: depth pyramid, Newcombe et al., ISMAR 2011)
BINOMIAL5 = np.array([0.0625, 0.25, 0.375, 0.25, 0.0625], np.float32)


def pyrdown_rgb(rgb: np.ndarray) -> np.ndarray:
    """One pyramid level down of a colour (or grey) image: the 5-tap Gaussian (:data:`GAUSS5`) along rows and
    columns with the border replicated, then the pixels at even rows and columns.

    Args:
        rgb: (H, W, C) or (H, W) float32.
    Returns:
        (ceil(H/2), ceil(W/2)[, C]) float32; pixel (y, x) is centred on input pixel (2y, 2x), so intrinsics halve
        (``fx/2, fy/2, cx/2, cy/2``).
    Raises:
        ValueError: not a 2-D or 3-D float32 array.
    """
    if rgb.dtype != np.float32 or rgb.ndim not in (2, 3):
        raise ValueError(f"expected an (H, W[, C]) float32 image, got {rgb.dtype} {rgb.shape}")
    h, w = rgb.shape[:2]
    pad = [(2, 2), (2, 2)] + [(0, 0)] * (rgb.ndim - 2)
    p = np.pad(rgb, pad, mode="edge")
    # rows first (only the even output rows are kept), then columns: each sum in a fixed order, tap by tap
    rows = GAUSS5[0] * p[0:h:2]
    for k in range(1, 5):
        rows = rows + GAUSS5[k] * p[k:k + h:2]
    out = GAUSS5[0] * rows[:, 0:w:2]
    for k in range(1, 5):
        out = out + GAUSS5[k] * rows[:, k:k + w:2]
    return np.ascontiguousarray(out, dtype=np.float32)


def pyrdown_depth(depth: np.ndarray, depth_diff_m: float) -> np.ndarray:
    """One pyramid level down of a depth map, as Open3D's ``Image::PyrDownDepth``: output pixel (y, x) is the
    weighted mean (:data:`BINOMIAL5` in both directions) of the valid samples of the 5 × 5 block around input
    pixel (2y, 2x) that lie within ``depth_diff_m`` of that centre sample; 0 (invalid) where the centre is invalid.

    Args:
        depth: (H, W) float32 metres; 0, negative or non-finite is invalid.
        depth_diff_m: samples further than this from the centre's depth are left out (metres; foreground and
            background do not mix).
    Returns:
        (ceil(H/2), ceil(W/2)) float32 metres, 0 where invalid.
    Raises:
        ValueError: not a 2-D float32 array.
    """
    if depth.dtype != np.float32 or depth.ndim != 2:
        raise ValueError(f"expected an (H, W) float32 depth map, got {depth.dtype} {depth.shape}")
    h, w = depth.shape
    d = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0)).astype(np.float32)
    p = np.pad(d, 2, mode="constant")  # outside the image: invalid, left out
    centre = d[0:h:2, 0:w:2]
    num = np.zeros_like(centre)
    den = np.zeros_like(centre)
    diff = np.float32(depth_diff_m)
    for dy in range(5):
        for dx in range(5):
            s = p[dy:dy + h:2, dx:dx + w:2]
            keep = (s > 0) & (np.abs(s - centre) < diff)
            wgt = np.where(keep, BINOMIAL5[dy] * BINOMIAL5[dx], np.float32(0))
            num = num + wgt * s
            den = den + wgt
    out = np.where((centre > 0) & (den > 0), num / np.where(den > 0, den, np.float32(1)), np.float32(0))
    return np.ascontiguousarray(out, dtype=np.float32)


def rgbd_pyramid(rgb: np.ndarray, depth: np.ndarray, levels: int, depth_diff_m: float
                 ) -> List[Tuple[np.ndarray, np.ndarray]]:
    """The ``levels`` levels of an RGB-D frame, finest first (level 0 is the input, as float32).

    Args:
        rgb: (H, W, 3) float32 colour (any range) or uint8.
        depth: (H, W) float32 metres.
        levels: number of levels (≥ 1).
        depth_diff_m: :func:`pyrdown_depth`'s bound (Open3D's multi-scale odometry uses twice its
            ``depth_outlier_trunc``).
    Returns:
        ``[(rgb_l (H_l, W_l, 3) float32, depth_l (H_l, W_l) float32)]``, ``H_{l+1} = ceil(H_l / 2)``.
    Raises:
        ValueError: ``levels`` below 1.
    """
    if levels < 1:
        raise ValueError(f"levels must be at least 1, got {levels}")
    out = [(np.ascontiguousarray(rgb, dtype=np.float32), np.ascontiguousarray(depth, dtype=np.float32))]
    for _ in range(levels - 1):
        c, d = out[-1]
        out.append((pyrdown_rgb(c), pyrdown_depth(d, depth_diff_m)))
    return out
