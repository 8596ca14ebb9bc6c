"""Any camera's files: a folder of colour and depth images and a small camera file.

Layout::

    my_folder/
        camera.yaml | camera.json   the camera (below)
        rgb/ | color/               colour images (PNG or JPEG), any resolution
        depth/                      single-channel 16-bit PNG depth, ``depth_scale`` units per metre, 0 = none
        trajectory.txt | groundtruth.txt | trajectory.tum   optional: TUM-format poses (``timestamp tx ty tz qx
                                    qy qz qw``, camera-to-world); without one the poses come from odometry

The camera file (YAML or JSON) holds ``width``, ``height``, ``fx``, ``fy``, ``cx``, ``cy`` (pixels),
``depth_scale`` (depth units per metre: 1000 for millimetres, 5000 for TUM), and optionally ``distortion`` (OpenCV
``[k1, k2, p1, p2, k3]``; the images are then undistorted onto the alpha=0 optimal pinhole camera, colour bilinear
and depth nearest, as :mod:`gausslite.datasets.tum` does) and ``fps`` (frame rate, 30 by default, for timestamps
when the file names are not times).

Colour and depth files are paired by file name stem when the stems agree, else in sorted order when both folders
hold as many files. A stem that is a decimal number with a point (``1305031102.175304``) is the frame's time in
seconds; otherwise frame ``k`` is at ``k / fps`` s. With a trajectory file each frame takes the pose of the nearest
timestamp within ``max_pose_dt`` (frames without one are dropped, logged).

The same camera file beside a TUM RGB-D sequence (``rgb.txt``, ``depth.txt``) overrides its 640×480 Freiburg
camera and its ``depth ÷ 5000``.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import List, Optional, Tuple, Union

import cv2
import numpy as np

from gausslite.camera import Intrinsics
from gausslite.datasets.annotations import load_annotations
from gausslite.datasets.camera_file import CAMERA_FILES, find_camera_file, read_camera_file
from gausslite.datasets.common import PosedImageDataset, select_indices
from gausslite.datasets.trajectory import read_tum_trajectory
from gausslite.datasets.tum import associate_nearest

log = logging.getLogger(__name__)

__all__ = ["TRAJECTORY_FILES", "is_camera_folder", "CameraFolderDataset"]

#: the optional trajectory file's names, in the order they are looked for
TRAJECTORY_FILES = ("trajectory.txt", "trajectory.tum", "groundtruth.txt")
_COLOR_DIRS = ("rgb", "color", "colour")
_IMAGE_EXT = {".png", ".jpg", ".jpeg"}
_TIME_RE = re.compile(r"^\d+\.\d+$")


def _color_dir(folder: Path) -> Optional[Path]:
    for name in _COLOR_DIRS:
        if (folder / name).is_dir():
            return folder / name
    return None


def is_camera_folder(folder: Union[str, Path]) -> bool:
    """True for a folder with a camera file, a colour image folder and a ``depth/`` folder."""
    p = Path(folder)
    return find_camera_file(p) is not None and _color_dir(p) is not None and (p / "depth").is_dir()


def _images(folder: Path) -> List[Path]:
    return sorted(f for f in folder.iterdir() if f.is_file() and f.suffix.lower() in _IMAGE_EXT)


def _pair(color_dir: Path, depth_dir: Path) -> Tuple[List[Path], List[Path]]:
    """Colour and depth files paired by stem, else in sorted order. Raises ValueError when neither works."""
    colour, depth = _images(color_dir), _images(depth_dir)
    if not colour:
        raise FileNotFoundError(f"no colour images (.png, .jpg) in {color_dir}")
    by_stem = {f.stem: f for f in depth}
    if all(f.stem in by_stem for f in colour):
        return colour, [by_stem[f.stem] for f in colour]
    if len(colour) == len(depth):
        return colour, depth
    missing = next(f for f in colour if f.stem not in by_stem)
    raise ValueError(f"{depth_dir}: no depth image named like {missing.name} and {len(depth)} depth images for "
                     f"{len(colour)} colour images: colour and depth cannot be paired")


class CameraFolderDataset(PosedImageDataset):
    """A sequence in the camera-file folder layout (the module docstring).

    Args:
        path: the folder.
        downscale, max_frames, stride: as every loader.
        max_pose_dt: largest gap (s) between a frame's time and its trajectory pose.
        undistort: undistort when the camera file gives a distortion (default True).

    Attributes: those of :class:`~gausslite.datasets.common.PosedImageDataset`; ``camera`` (the
    :class:`CameraFile`), ``raw_intrinsics`` (of the files), ``distortion``, ``has_poses`` (a trajectory file was
    found), ``n_dropped`` (frames without a pose within ``max_pose_dt``).

    Raises:
        FileNotFoundError: missing folder, camera file or image folders. ValueError: a malformed camera file,
            images that cannot be paired, a malformed trajectory (each names the file and the field or line).
    """

    def __init__(self, path: Union[str, Path], downscale: Union[int, float] = 1, max_frames: Optional[int] = None,
                 stride: int = 1, max_pose_dt: float = 0.02, undistort: bool = True) -> None:
        seq = Path(path)
        if not seq.is_dir():
            raise FileNotFoundError(f"dataset folder not found: {seq}")
        cam_path = find_camera_file(seq)
        if cam_path is None:
            raise FileNotFoundError(f"{seq}: no camera file ({', '.join(CAMERA_FILES)})")
        self.camera = cam = read_camera_file(cam_path)
        color_dir = _color_dir(seq)
        if color_dir is None or not (seq / "depth").is_dir():
            raise FileNotFoundError(f"{seq}: expected a colour image folder ({', '.join(_COLOR_DIRS)}) and depth/")
        colour, depth = _pair(color_dir, seq / "depth")
        stems = [f.stem for f in colour]
        times = (np.array([float(s) for s in stems]) if all(_TIME_RE.match(s) for s in stems)
                 else np.arange(len(colour)) / cam.fps)
        keep = np.arange(len(colour))
        poses = self._poses(seq, times, max_pose_dt)
        if poses is not None:
            keep, poses = poses
        sel = [int(keep[k]) for k in select_indices(len(keep), stride, max_frames)]
        self.raw_intrinsics, self.distortion = cam.intrinsics, cam.distortion
        self.undistort = bool(undistort) and any(cam.distortion)
        native = self._undistorted_camera() if self.undistort else cam.intrinsics
        self._maps = None
        super().__init__(path=seq, name=seq.name, rgb_paths=[colour[i] for i in sel],
                         depth_paths=[depth[i] for i in sel],
                         poses=None if poses is None else poses[[list(keep).index(i) for i in sel]],
                         timestamps=times[sel], frame_ids=sel, frame_names=[stems[i] for i in sel],
                         native_intrinsics=native, depth_scale=cam.depth_scale, downscale=downscale,
                         annotations=load_annotations(seq))

    def _poses(self, seq: Path, times: np.ndarray, max_pose_dt: float):
        """``(kept frame indices, their (K, 4, 4) poses)`` from the trajectory file, or None without one."""
        traj = next((seq / n for n in TRAJECTORY_FILES if (seq / n).is_file()), None)
        self.n_dropped = 0
        #: the pose file a sequence without poses lacks (for the error of pose_source "given")
        self.missing_poses = str(seq / TRAJECTORY_FILES[0])
        if traj is None:
            return None
        t_ref, poses = read_tum_trajectory(traj)
        order = np.argsort(t_ref, kind="stable")
        idx, gap = associate_nearest(times, t_ref[order])
        ok = gap <= max_pose_dt
        self.n_dropped = int((~ok).sum())
        if not ok.any():
            raise ValueError(f"{traj}: no pose within {max_pose_dt} s of any frame's time (first frame at "
                             f"{times[0]:.6f} s, first pose at {t_ref[order][0]:.6f} s)")
        if self.n_dropped:
            log.warning("%s: dropped %d of %d frames without a pose within %.3f s", traj, self.n_dropped, len(times),
                        max_pose_dt)
        keep = np.flatnonzero(ok)
        return keep, poses[order][idx[keep]]

    def _undistorted_camera(self) -> Intrinsics:
        """The alpha=0 optimal new pinhole camera of the distorted files (OpenCV getOptimalNewCameraMatrix)."""
        ri = self.raw_intrinsics
        new_k, _ = cv2.getOptimalNewCameraMatrix(ri.K, np.asarray(self.distortion), (ri.width, ri.height), 0.0)
        return Intrinsics(float(new_k[0, 0]), float(new_k[1, 1]), float(new_k[0, 2]), float(new_k[1, 2]),
                          ri.width, ri.height)

    def _color_camera(self):
        """The files' own camera (with its distortion): the registration target."""
        return self.raw_intrinsics, (self.distortion if any(self.distortion) else None)

    def _load(self, i: int):
        """Frame ``i``; files of another size than the camera file's give one error naming both."""
        try:
            return super()._load(i)
        except ValueError as e:
            if "intrinsics are for" not in str(e):
                raise
            ri = self.raw_intrinsics
            raise ValueError(f"{e}: the camera file {self.camera.path} says width {ri.width}, height "
                             f"{ri.height}") from None

    def _preprocess(self, rgb: np.ndarray, depth: np.ndarray, i: int):
        """Undistort colour (bilinear) and depth (nearest) when the camera file gives a distortion."""
        if not self.undistort:
            return rgb, depth
        if self._maps is None:
            ri, ni = self.raw_intrinsics, self.native_intrinsics
            self._maps = cv2.initUndistortRectifyMap(ri.K, np.asarray(self.distortion), None, ni.K,
                                                     (ni.width, ni.height), cv2.CV_32FC1)
        mx, my = self._maps
        rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        depth = cv2.remap(depth, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return rgb, depth
