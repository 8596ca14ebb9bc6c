"""The frame and dataset interfaces every loader and the odometry share, and the resolution change of a frame.

:class:`Frame` is one posed RGB-D frame; :class:`RGBDDataset` the sequence interface every loader implements
(Replica, TUM RGB-D, 7-Scenes, ROS bags, RealSense, camera folders: :mod:`gausslite.datasets`) and the odometry wraps
(:mod:`gausslite.odometry`).

Downscaling (``downscale_rgb`` / ``downscale_depth``) by a factor ``f >= 1`` (int or float):

- The output size is ``floor(W / f) x floor(H / f)``, exactly the size given by
  :meth:`gausslite.camera.Intrinsics.scaled`, so the scaled intrinsics match the images.
- Output pixel ``(i, j)`` covers the source block of pixels whose centres lie in
  ``[j f, (j+1) f) x [i f, (i+1) f)`` (the same pixel-centre mapping ``c' = (c + 0.5) / f - 0.5`` that
  ``Intrinsics.scaled`` uses). Source rows/columns beyond the last full block are dropped.
- Colour: area interpolation (``cv2.INTER_AREA``) of the cropped source.
- Depth: **nearest valid sample to the block centre**. The sample nearest to the block centre
  (Euclidean distance in source pixels; ties broken by the first sample in row-major order, i.e. the
  top-left of the central samples for even integer factors) is taken; when it is invalid (0 or not
  finite), the nearest *valid* sample of the same block is taken instead; a block with no valid sample
  gives 0. Every output depth is therefore a value that exists in its source block: an invalid 0 is never
  averaged into a valid depth and no value is blended across a depth edge.
"""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from gausslite.camera import Intrinsics

__all__ = ["Frame", "RGBDDataset", "check_downscale", "downscale_rgb", "downscale_depth", "downscale_frame"]


@dataclass
class Frame:
    """One posed RGB-D frame.

    Attributes:
        frame_id: index of the frame in its sequence (0-based, before any frame skipping).
        timestamp: seconds (dataset clock; frame index / fps when the dataset has none).
        rgb: (H, W, 3) uint8 colour image, RGB order.
        depth: (H, W) float32 depth in metres along camera z; 0 = invalid.
        c2w: (4, 4) float64 camera-to-world pose, OpenCV camera axes (x right, y down, z forward).
        intrinsics: pinhole intrinsics matching ``rgb``/``depth`` size.
        name: the frame's name in its sequence (e.g. the colour file's stem).
        pose_ok: False when ``c2w`` is not an estimate of this frame: its odometry failed and it carries the last
            good pose (:mod:`gausslite.odometry.rgbd`); the mapper skips such a frame.
    """

    frame_id: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    c2w: np.ndarray
    intrinsics: Intrinsics
    name: str = ""
    pose_ok: bool = True


class RGBDDataset(Sequence[Frame], ABC):
    """Base class: a posed RGB-D sequence, indexable and iterable, loading frames lazily.

    Subclasses set ``self.path``, ``self.intrinsics`` (after downscaling), ``self.annotations``
    (``SceneAnnotations`` or None) and implement ``__len__`` and ``_load(i)``. ``has_poses`` is False for a
    sequence read without poses (its frames carry the identity until :class:`~gausslite.odometry.rgbd.
    OdometryDataset` estimates them).
    """

    path: Path
    intrinsics: Intrinsics
    annotations: "Optional[object]" = None
    name: str = ""
    has_poses: bool = True

    @abstractmethod
    def __len__(self) -> int:
        """Number of frames."""

    @abstractmethod
    def _load(self, i: int) -> Frame:
        """Load frame ``i`` (0 <= i < len(self))."""

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        return self._load(i)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self._load(i)


def check_downscale(factor: Union[int, float]) -> float:
    """Validate a downscale factor and return it as a float.

    Args:
        factor: int or float, must be finite and ``>= 1`` (1 = full resolution).

    Raises:
        ValueError: not an int/float (strings and bools are rejected), not finite or smaller than 1.
    """
    if isinstance(factor, bool) or not isinstance(factor, (int, float, np.integer, np.floating)):
        raise ValueError(f"downscale factor must be a number >= 1, got {factor!r}")
    f = float(factor)
    if not math.isfinite(f) or f < 1.0:
        raise ValueError(f"downscale factor must be a finite number >= 1, got {factor!r}")
    return f


def _block_edges(n_out: int, f: float, n_src: int) -> Tuple[np.ndarray, np.ndarray]:
    """[start, stop) source indices of each of ``n_out`` blocks: pixels with centre in [j f, (j+1) f)."""
    j = np.arange(n_out + 1, dtype=np.float64)
    edges = np.clip(np.ceil(j * f - 0.5).astype(np.int64), 0, n_src)
    return edges[:-1], edges[1:]


def _out_size(h: int, w: int, f: float) -> Tuple[int, int]:
    oh, ow = int(h // f), int(w // f)
    if oh < 1 or ow < 1:
        raise ValueError(f"downscale factor {f} too large for a {w}x{h} image")
    return oh, ow


def downscale_rgb(rgb: np.ndarray, factor: Union[int, float]) -> np.ndarray:
    """Downscale a colour image by ``factor`` with area interpolation.

    Args:
        rgb: (H, W, 3) uint8 image.
        factor: >= 1 (see the module docstring for the block geometry).

    Returns:
        (floor(H/f), floor(W/f), 3) uint8 image; a copy of ``rgb`` when ``factor == 1``.

    Raises:
        ValueError: invalid factor or a factor larger than the image.
    """
    f = check_downscale(factor)
    if f == 1.0:
        return rgb.copy()
    h, w = rgb.shape[:2]
    oh, ow = _out_size(h, w, f)
    y_stop = int(_block_edges(oh, f, h)[1][-1])
    x_stop = int(_block_edges(ow, f, w)[1][-1])
    src = np.ascontiguousarray(rgb[:y_stop, :x_stop])
    return cv2.resize(src, (ow, oh), interpolation=cv2.INTER_AREA)


def downscale_depth(depth: np.ndarray, factor: Union[int, float]) -> np.ndarray:
    """Downscale a depth map by ``factor`` without mixing invalid or foreground/background samples.

    Each output pixel takes the source sample nearest to its block centre, falling back to the
    nearest *valid* (> 0, finite) sample of the block, and 0 if the block has none (see the module
    docstring). Vectorised: one gather of all blocks, one argmin.

    Args:
        depth: (H, W) float depth in metres, 0 = invalid.
        factor: >= 1, int or float.

    Returns:
        (floor(H/f), floor(W/f)) array of the input dtype; every value is a valid sample of its source
        block, or 0 (non-finite inputs become 0, also for ``factor == 1``, which otherwise copies).

    Raises:
        ValueError: invalid factor, a factor larger than the image, or ``depth`` not 2-D.
    """
    f = check_downscale(factor)
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be 2-D, got shape {depth.shape}")
    if f == 1.0:
        out = depth.copy()
        if np.issubdtype(out.dtype, np.floating):
            out[~np.isfinite(out)] = 0
        return out
    H, W = depth.shape
    oh, ow = _out_size(H, W, f)
    y0, y1 = _block_edges(oh, f, H)
    x0, x1 = _block_edges(ow, f, W)
    ky, kx = int((y1 - y0).max()), int((x1 - x0).max())
    ys = y0[:, None] + np.arange(ky)[None, :]  # (oh, ky)
    xs = x0[:, None] + np.arange(kx)[None, :]  # (ow, kx)
    y_in = ys < y1[:, None]
    x_in = xs < x1[:, None]
    ys_c = np.minimum(ys, H - 1)
    xs_c = np.minimum(xs, W - 1)
    # distance of every block sample to its block centre (source pixel units)
    cy = (np.arange(oh) + 0.5) * f - 0.5
    cx = (np.arange(ow) + 0.5) * f - 0.5
    dy2 = np.where(y_in, (ys - cy[:, None]) ** 2, np.inf)  # (oh, ky)
    dx2 = np.where(x_in, (xs - cx[:, None]) ** 2, np.inf)  # (ow, kx)
    block = depth[ys_c[:, :, None, None], xs_c[None, None, :, :]]  # (oh, ky, ow, kx)
    d2 = dy2[:, :, None, None] + dx2[None, None, :, :]
    valid = np.isfinite(block) & (block > 0)
    d2 = np.where(valid, d2, np.inf)
    block = block.transpose(0, 2, 1, 3).reshape(oh, ow, ky * kx)
    d2 = d2.transpose(0, 2, 1, 3).reshape(oh, ow, ky * kx)
    best = np.argmin(d2, axis=-1)
    out = np.take_along_axis(block, best[..., None], axis=-1)[..., 0]
    has_valid = np.isfinite(np.take_along_axis(d2, best[..., None], axis=-1)[..., 0])
    out = np.where(has_valid, out, 0).astype(depth.dtype, copy=False)
    return out


def downscale_frame(frame: Frame, factor: Union[int, float]) -> Frame:
    """``frame`` at 1/``factor`` resolution: colour by area, depth by the valid sample nearest each block's centre
    (:func:`downscale_depth`), intrinsics scaled (:meth:`Intrinsics.scaled`); pose,
    time and id unchanged. ``factor`` 1 returns ``frame``.

    Raises:
        ValueError: a factor below 1 or one larger than the image.
    """
    if factor == 1:
        return frame
    rgb = downscale_rgb(frame.rgb, factor)
    depth = downscale_depth(frame.depth, factor)
    intr = frame.intrinsics.scaled(factor)
    if (intr.width, intr.height) != (depth.shape[1], depth.shape[0]):
        intr = dataclasses.replace(intr, width=depth.shape[1], height=depth.shape[0])
    return dataclasses.replace(frame, rgb=rgb, depth=np.ascontiguousarray(depth), intrinsics=intr)
