"""Image I/O, validation and the posed image-file sequence shared by every dataset loader.

The per-format modules (Replica, TUM RGB-D, 7-Scenes, ROS bags) build on these helpers (``read_rgb``,
``read_depth``, ``downscale_rgb``, ``downscale_depth``, ``select_indices``, ``PosedImageDataset``); the factory
:func:`gausslite.datasets.loader.load_dataset` picks the format.

Downscaling (``downscale_rgb``, ``downscale_depth``, ``downscale_frame``) lives in :mod:`gausslite.core.frames`.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from gausslite.camera import Intrinsics
from gausslite.core.frames import (  # noqa: F401 - the loaders' downscaling, named here as well
    Frame,
    RGBDDataset,
    check_downscale,
    downscale_depth,
    downscale_frame,
    downscale_rgb,
)
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
        #: its pose (:func:`gausslite.odometry.rgbd.with_pose_source`)
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
