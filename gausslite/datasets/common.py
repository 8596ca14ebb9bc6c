"""Image I/O, validation, downscaling and the posed image-file sequence shared by every dataset loader.

The per-format modules (Replica, TUM RGB-D, 7-Scenes, ROS bags) build on these helpers (``read_rgb``,
``read_depth``, ``downscale_rgb``, ``downscale_depth``, ``select_indices``, ``PosedImageDataset``); the factory
:func:`gausslite.datasets.loader.load_dataset` picks the format.

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
from pathlib import Path
from typing import List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame, RGBDDataset
from gausslite.datasets.registration import DepthCamera, register_depth


PathLike = Union[str, Path]

__all__ = [
    "check_downscale",
    "downscale_rgb",
    "downscale_depth",
    "read_rgb",
    "read_depth",
    "select_indices",
    "PosedImageDataset",
]


# ----------------------------------------------------------------------------------------------
# argument validation
# ----------------------------------------------------------------------------------------------
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


def select_indices(n: int, stride: int = 1, max_frames: Optional[int] = None) -> List[int]:
    """Indices ``0, stride, 2*stride, ...`` into ``n`` frames, truncated to ``max_frames``.

    Raises:
        ValueError: ``stride`` not an int >= 1, or ``max_frames`` not None / an int >= 1.
    """
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"stride must be an integer >= 1, got {stride!r}")
    if max_frames is not None and (
        isinstance(max_frames, bool) or not isinstance(max_frames, (int, np.integer)) or max_frames < 1
    ):
        raise ValueError(f"max_frames must be None or an integer >= 1, got {max_frames!r}")
    idx = list(range(0, n, int(stride)))
    if max_frames is not None:
        idx = idx[: int(max_frames)]
    return idx


# ----------------------------------------------------------------------------------------------
# image I/O
# ----------------------------------------------------------------------------------------------
def read_rgb(path: PathLike) -> np.ndarray:
    """Read a colour image file (PNG/JPEG) as RGB.

    Returns:
        (H, W, 3) uint8 array in RGB order (grey images are expanded to 3 channels, alpha is dropped).

    Raises:
        FileNotFoundError: the file does not exist (message names it).
        ValueError: OpenCV cannot decode the file (message names it).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"colour image not found: {p}")
    img = cv2.imread(str(p), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{p}: unreadable colour image (OpenCV could not decode it)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: PathLike, scale: float, invalid_values: Sequence[int] = ()) -> np.ndarray:
    """Read a single-channel 16-bit depth PNG and convert it to metres.

    Args:
        path: depth image file.
        scale: raw units per metre (``depth_m = raw / scale``; 5000 for TUM, 6553.5 for Replica,
            1000 for 7-Scenes).
        invalid_values: raw values besides 0 that mean "no measurement" (e.g. 65535 in 7-Scenes).

    Returns:
        (H, W) float32 depth in metres, 0 where invalid.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: unreadable file, or not a single-channel uint16 image (message names the file).
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"depth image not found: {p}")
    raw = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"{p}: unreadable depth image (OpenCV could not decode it)")
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise ValueError(
            f"{p}: depth must be a single-channel 16-bit image, got dtype {raw.dtype} shape {raw.shape}"
        )
    depth = raw.astype(np.float32) / np.float32(scale)
    for v in invalid_values:
        depth[raw == v] = 0.0
    return depth


# ----------------------------------------------------------------------------------------------
# downscaling
# ----------------------------------------------------------------------------------------------
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
    (:func:`~gausslite.datasets.common.downscale_depth`), intrinsics scaled (:meth:`Intrinsics.scaled`); pose,
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

# ----------------------------------------------------------------------------------------------
# generic posed image-file sequence
# ----------------------------------------------------------------------------------------------
class PosedImageDataset(RGBDDataset):
    """An RGB-D sequence stored as one colour file and one 16-bit depth file per frame.

    Subclasses (Replica, TUM, 7-Scenes) parse their layout and pass per-frame lists here. Images are
    read lazily in ``_load``; poses are parsed and validated when the dataset is built.

    Attributes:
        path: sequence folder.
        name: sequence name (folder name).
        intrinsics: intrinsics of the frames returned (after downscaling).
        native_intrinsics: intrinsics of the image files on disk.
        downscale: the downscale factor (float >= 1).
        depth_scale: raw depth units per metre.
        poses: (N, 4, 4) float64 camera-to-world poses of the selected frames (OpenCV camera axes); the identity
            when the constructor got ``poses=None`` (no pose file: ``has_poses`` False).
        timestamps: (N,) float64 seconds.
        frame_ids: list of N ints, index of each frame in the full sequence.
        rgb_paths, depth_paths: lists of N file paths.
        annotations: ``SceneAnnotations`` or None.
    """

    def __init__(
        self,
        path: Path,
        name: str,
        rgb_paths: Sequence[Path],
        depth_paths: Sequence[Path],
        poses: Optional[np.ndarray],
        timestamps: Sequence[float],
        frame_ids: Sequence[int],
        frame_names: Sequence[str],
        native_intrinsics: Intrinsics,
        depth_scale: float,
        downscale: Union[int, float] = 1,
        invalid_depth_values: Sequence[int] = (),
        annotations: Optional[object] = None,
        depth_camera: Optional["DepthCamera"] = None,
    ) -> None:
        n = len(rgb_paths)
        #: False when the sequence has no pose file: every frame carries the identity until odometry estimates
        #: its pose (:func:`gausslite.datasets.odometry.with_pose_source`)
        self.has_poses = poses is not None
        if poses is None:
            poses = np.broadcast_to(np.eye(4), (n, 4, 4))
        if not (len(depth_paths) == len(poses) == len(timestamps) == len(frame_ids) == len(frame_names) == n):
            raise ValueError(f"{path}: internal error, per-frame lists have different lengths")
        if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and depth_scale > 0):
            raise ValueError(f"{path}: depth scale must be a positive finite number, got {depth_scale!r}")
        self.path = Path(path)
        self.name = name
        self.rgb_paths = [Path(p) for p in rgb_paths]
        self.depth_paths = [Path(p) for p in depth_paths]
        self.poses = np.asarray(poses, dtype=np.float64).reshape(n, 4, 4)
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.frame_ids = [int(i) for i in frame_ids]
        self.frame_names = list(frame_names)
        self.native_intrinsics = native_intrinsics
        self.downscale = check_downscale(downscale)
        self.intrinsics = native_intrinsics if self.downscale == 1.0 else native_intrinsics.scaled(self.downscale)
        self.depth_scale = float(depth_scale)
        self.invalid_depth_values = tuple(invalid_depth_values)
        self.annotations = annotations
        if depth_camera is not None and not isinstance(depth_camera, DepthCamera):
            raise ValueError(f"depth_camera must be a DepthCamera, got {type(depth_camera).__name__}")
        #: unregistered depth camera (intrinsics + extrinsic); depth is registered to colour on load
        self.depth_camera = depth_camera

    def _color_camera(self) -> Tuple[Intrinsics, Optional[Sequence[float]]]:
        """Intrinsics and distortion of the colour files on disk (the registration target)."""
        return self.native_intrinsics, None

    def __len__(self) -> int:
        """Number of (selected) frames."""
        return len(self.rgb_paths)

    def __repr__(self) -> str:
        i = self.intrinsics
        return f"{type(self).__name__}({str(self.path)!r}, frames={len(self)}, size={i.width}x{i.height})"

    def _depth_camera_for(self, i: int) -> Optional["DepthCamera"]:
        """The depth camera frame ``i``'s depth is registered from (None: already registered). Hook for
        per-frame extrinsics, e.g. TUM's depth/colour time offset; ``depth_camera`` here."""
        return self.depth_camera

    def _preprocess(self, rgb: np.ndarray, depth: np.ndarray, i: int) -> Tuple[np.ndarray, np.ndarray]:
        """Hook for full-resolution per-frame processing (e.g. undistortion); identity here."""
        return rgb, depth

    def _load(self, i: int) -> Frame:
        """Read, validate and downscale frame ``i``.

        Raises:
            FileNotFoundError / ValueError: missing or unreadable image; colour and depth sizes differ;
                image size differs from the intrinsics (messages name the files).
        """
        rp, dp = self.rgb_paths[i], self.depth_paths[i]
        rgb = read_rgb(rp)
        depth = read_depth(dp, self.depth_scale, self.invalid_depth_values)
        depth_camera = self._depth_camera_for(i)
        if depth_camera is not None:
            ci, cdist = self._color_camera()
            try:
                depth = register_depth(depth, depth_camera, ci, cdist)
            except ValueError as e:
                raise ValueError(f"{dp}: {e}") from None
        if rgb.shape[:2] != depth.shape:
            raise ValueError(
                f"colour/depth size mismatch: {rp} is {rgb.shape[1]}x{rgb.shape[0]}, "
                f"{dp} is {depth.shape[1]}x{depth.shape[0]}"
            )
        ni = self.native_intrinsics
        if (depth.shape[1], depth.shape[0]) != (ni.width, ni.height):
            raise ValueError(
                f"{rp}: image is {depth.shape[1]}x{depth.shape[0]} but the intrinsics are for "
                f"{ni.width}x{ni.height}"
            )
        rgb, depth = self._preprocess(rgb, depth, i)
        if self.downscale != 1.0:
            rgb = downscale_rgb(rgb, self.downscale)
            depth = downscale_depth(depth, self.downscale)
        return Frame(
            frame_id=self.frame_ids[i],
            timestamp=float(self.timestamps[i]),
            rgb=rgb,
            depth=depth,
            c2w=self.poses[i].copy(),
            intrinsics=self.intrinsics,
            name=self.frame_names[i],
        )
