"""Rolling shutter: each image row is read out at its own time, so a moving camera sees each row from its
own pose.

The Kinect of TUM RGB-D reads its colour rows out top to bottom over a readout time ``t_r`` of about 20 ms.
TUM fr1/rpy turns at a median 67°/s: 1.3° between the first and the last row, about 6 pixels at 320×240,
a shear (yaw), a stretch (pitch) or a bend (roll) that differs between a view taken turning left and one
taken turning right. A global-shutter map cannot match both. As in continuous-time RGB-D tracking with rolling
shutter (Kerl, Stückler, Cremers, ICCV 2015) and in 3DGS with rolling-shutter compensation (Seiskari et al.,
"Gaussian Splatting on the Move", ECCV 2024), row ``v`` is rendered from

    c2w(v) = c2w · E(t(v) · (ω, v_lin)),    t(v) = ((v − c_y) / f_y) · t_r · f_y⁰ / H⁰

with ``(ω, v_lin)`` the camera's twist per second (from the sensor's poses of consecutive mapped frames, as for
motion blur, :mod:`gausslite.mapping.blur`), ``f_y⁰``, ``H⁰`` the focal length and height of the full
image (so crops and downscaled views keep the row times of the rows they show) and the image centre row read
at the frame's timestamp. The image is rendered in horizontal bands, one pose per band: one band per
``rs_px_per_band`` pixels of motion between the view's first and last row, at most ``rs_max_bands``. The
rows of a band are rendered by the rasterizer alone (the principal point shifted by the band's first row),
so the pixels rendered stay those of one image; only the per-render projection is repeated.

Calibrated on TUM fr1/rpy (``bench.rolling_shutter``, retired: docs/history.md#rolling_shutter), 320×240, 60 random
pairs of overlapping frames
≥ 8 frames apart (one of them turning faster than 40°/s), warping one frame into the other with its depth and the
sensor's poses: mean warp PSNR +1.02 dB with ``t_r`` = 20 ms (top row first; 25 ms +1.10), −1.29 dB with the rows
taken bottom first, and +2.18 dB with 20 ms when the poses are also read 5 ms earlier (a clock offset that
per-keyframe pose refinement absorbs).
"""

from __future__ import annotations

import math

import numpy as np

from .blur import blur_length_px


def row_time(v, cy: float, fy: float, readout_norm: float):
    """Readout time (seconds, relative to the frame's timestamp) of image row ``v`` (pixels, may be
    fractional; a float or an array of rows, giving the same shape) of a view with principal point row ``cy``
    and focal length ``fy`` (pixels).

    ``readout_norm`` = ``t_r · f_y⁰ / H⁰`` (seconds per unit of normalised image y, from the full image:
    :func:`readout_norm`), so the time of a scene ray does not depend on how the view was cropped or scaled.
    """
    return (v - float(cy)) / float(fy) * float(readout_norm)


def readout_norm(readout_s: float, fy_full: float, height_full: int) -> float:
    """``t_r · f_y⁰ / H⁰``: the readout time ``readout_s`` (seconds, first to last row) of a full image of
    ``height_full`` rows with focal length ``fy_full`` (pixels), per unit of normalised image y."""
    return float(readout_s) * float(fy_full) / float(height_full)


def shutter_bands(K, width: int, height: int, xi_rate: np.ndarray, readout_norm_s: float,
                  px_per_band: float, max_bands: int, align: int = 1) -> list[tuple[int, int, float]]:
    """The row bands of a view and the readout time of each.

    Args:
        K: (3, 3) intrinsics of the view (pixels; a crop's principal point is shifted).
        width, height: view size in pixels.
        xi_rate: (6,) the camera's twist per second (ω rad/s, v m/s) in its own frame.
        readout_norm_s: :func:`readout_norm` of the full image (0: global shutter).
        px_per_band: one band per this many pixels of motion between the view's first and last row
            (:func:`gausslite.mapping.blur.blur_length_px`).
        max_bands: at most this many bands.
        align: band edges on multiples of this many rows (the rasterizer's tile size, so that the bands render
            in one pass: :func:`gausslite.render.rasterize_bands`); 1: anywhere. Bands that alignment would
            leave empty are merged.
    Returns:
        [(y0, y1, t)]: rows ``y0 ≤ v < y1`` rendered from ``c2w · E(t · xi_rate)``, ``t`` the readout time
        (seconds) of the band's centre; they cover ``0 … height`` in order. One band when the view's rows
        are read out within less than ``px_per_band`` pixels of motion.
    """
    fx, fy, cy = float(K[0][0]), float(K[1][1]), float(K[1][2])
    span = row_time(height, cy, fy, readout_norm_s) - row_time(0, cy, fy, readout_norm_s)
    motion_px = blur_length_px(span * np.asarray(xi_rate, np.float64), fx, width, height)
    align = max(int(align), 1)
    n = int(min(max(math.ceil(motion_px / px_per_band), 1), max_bands, math.ceil(height / align)))
    inner = np.round(np.linspace(0, height, n + 1)[1:-1] / align).astype(int) * align
    edges = [0] + sorted({int(e) for e in inner if 0 < e < height}) + [int(height)]
    return [(int(a), int(b), row_time(0.5 * (a + b), cy, fy, readout_norm_s)) for a, b in zip(edges[:-1], edges[1:])]


__all__ = ["row_time", "readout_norm", "shutter_bands"]
