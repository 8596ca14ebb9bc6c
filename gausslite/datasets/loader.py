"""Dataset factory: ``load_dataset`` detects the on-disk layout (Replica / NICE-SLAM, TUM RGB-D, 7-Scenes, ROS
bags) and builds the matching :class:`~gausslite.datasets.base.RGBDDataset`.

The image I/O, validation and downscaling the per-format loaders share live in :mod:`gausslite.datasets.common`.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal, Optional, Tuple, Union

from gausslite.datasets.bag import BagDataset
from gausslite.datasets.base import RGBDDataset
from gausslite.datasets.camera_folder import CameraFolderDataset, is_camera_folder
from gausslite.datasets.common import PathLike
from gausslite.datasets.labelling import resolve_annotations
from gausslite.odometry.config import OdometryConfig, PoseSource
from gausslite.odometry.rgbd import with_pose_source
from gausslite.datasets.realsense import RealSenseBagDataset, is_realsense_bag
from gausslite.datasets.replica import ReplicaDataset
from gausslite.datasets.sevenscenes import SevenScenesDataset
from gausslite.datasets.tum import TUMDataset
from gausslite.ros.bagio import is_bag_path

__all__ = ["load_dataset", "detect_layout"]

# ----------------------------------------------------------------------------------------------
# layout detection and factory
# ----------------------------------------------------------------------------------------------
_SEVEN_RE = re.compile(r"^frame-\d+\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
_REPLICA_RE = re.compile(r"^frame\d+\.(jpg|jpeg|png)$", re.IGNORECASE)


def _is_replica(p: Path) -> bool:
    res = p / "results"
    return res.is_dir() and any(_REPLICA_RE.match(f.name) for f in res.iterdir())


def _is_tum(p: Path) -> bool:
    return all((p / f).is_file() for f in ("rgb.txt", "depth.txt"))


def _is_seven(p: Path) -> bool:
    return any(_SEVEN_RE.match(f.name) for f in p.iterdir())


def detect_layout(path: PathLike) -> Tuple[str, Path]:
    """Detect the dataset layout of a folder.

    Rules, in order: a RealSense recording (a ROS 1 ``.bag`` with ``/device_0/sensor_*/.../image/data``
    topics) -> ``"realsense"``; a ROS bag (rosbag2 folder with ``metadata.yaml``, ``.mcap``, ``.db3`` or ``.bag``
    file) -> ``"bag"``; ``results/frameNNNNNN.*`` (+ ``traj.txt`` when posed) -> ``"replica"``; ``rgb.txt`` +
    ``depth.txt`` (+ ``groundtruth.txt`` when posed) -> ``"tum"``; ``frame-NNNNNN.color.*`` -> ``"7scenes"``; a
    camera file (``camera.yaml`` / ``camera.json``) with ``rgb/`` (or ``color/``) and ``depth/`` -> ``"camera"``. A
    folder
    holding ``cam_params.json`` and exactly one Replica sequence sub-folder (e.g. ``Replica_room0``)
    resolves to that sub-folder.

    Returns:
        ``(kind, sequence_folder)``.

    Raises:
        FileNotFoundError: ``path`` is not a folder.
        ValueError: no known layout (the message lists what was looked for).
    """
    p = Path(path)
    if is_bag_path(p):
        return ("realsense" if is_realsense_bag(p) else "bag"), p
    if not p.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {p}")
    if _is_replica(p):
        return "replica", p
    if _is_tum(p):
        return "tum", p
    if _is_seven(p):
        return "7scenes", p
    if is_camera_folder(p):
        return "camera", p
    subs = [s for s in sorted(p.iterdir()) if s.is_dir() and _is_replica(s)]
    if len(subs) == 1:
        return "replica", subs[0]
    raise ValueError(
        f"{p}: unknown dataset layout; expected Replica (results/frameNNNNNN.jpg [+ traj.txt]), "
        f"TUM RGB-D (rgb.txt, depth.txt [, groundtruth.txt]), 7-Scenes (frame-NNNNNN.color.png), a camera folder "
        f"(camera.yaml or camera.json, rgb/ and depth/ [, trajectory.txt]) or a ROS bag "
        f"(rosbag2 folder with metadata.yaml, .mcap, .db3, .bag; a RealSense .bag)"
    )


_KINDS = {
    "replica": "replica",
    "nice-slam": "replica",
    "tum": "tum",
    "tum-rgbd": "tum",
    "7scenes": "7scenes",
    "7-scenes": "7scenes",
    "sevenscenes": "7scenes",
    "bag": "bag",
    "camera": "camera",
    "realsense": "realsense",
    "rosbag": "bag",
    "rosbag2": "bag",
}


def load_dataset(
    path: PathLike,
    kind: str = "auto",
    downscale: Union[int, float] = 1,
    max_frames: Optional[int] = None,
    stride: int = 1,
    bag: Optional[object] = None,
    pose_source: Union[PoseSource, Literal["auto"]] = "auto",
    odometry: Optional[OdometryConfig] = None,
    progress: bool = True,
    annotations: Union[str, Path] = "auto",
    **kw,
) -> RGBDDataset:
    """Open an RGB-D sequence, detecting its layout when ``kind == "auto"``.

    Args:
        path: sequence folder (for Replica, the parent holding ``cam_params.json`` and a single
            sequence folder is accepted too).
        kind: ``"auto"``, ``"replica"``, ``"tum"``, ``"7scenes"``, ``"camera"``, ``"realsense"`` or ``"bag"`` (aliases ``"rosbag"``, ``"rosbag2"``, ``"sevenscenes"``,
            ``"7-scenes"``, ``"tum-rgbd"``, ``"nice-slam"``).
        downscale: factor >= 1 applied to images and intrinsics.
        max_frames: keep at most this many frames (after ``stride``).
        stride: keep every ``stride``-th frame.
        bag: ``BagOptions`` or dict (topics, frames, tolerances) used when the path is a ROS bag; a
            non-empty value for another layout is an error.
        pose_source: a :data:`~gausslite.odometry.rgbd.PoseSource`, ``given`` (its poses; an error when it
            has none) or ``odometry``, or ``auto`` (the sequence's poses, else odometry;
            :func:`gausslite.odometry.rgbd.with_pose_source`).
        odometry: the odometry's settings (``OdometryConfig``; None: the defaults).
        progress: the odometry shows a progress bar.
        annotations: which scene annotations the dataset carries (:func:`gausslite.datasets.labelling.resolve_annotations`):
            ``"auto"`` (``objects.json`` / ``tasks.json`` beside the data, else the set GaussLite ships for a
            recognised public sequence), ``"beside"``, ``"shipped"``, or a folder holding the two files.
        **kw: passed to the loader (``ReplicaDataset``, ``TUMDataset``, ``SevenScenesDataset``,
            ``BagDataset``); ``depth_camera`` (a ``DepthCamera``) registers unregistered depth files.

    Returns:
        The dataset, with ``.annotations`` set (None when there are none).

    Raises:
        FileNotFoundError: missing folder or files. ValueError: unknown ``kind``, unknown layout, or
        invalid content (see each loader), or ``annotations="shipped"`` for a sequence GaussLite ships none for.
    """
    p = Path(path)
    if kind == "auto":
        k, p = detect_layout(p)
    else:
        k = _KINDS.get(str(kind).lower())
        if k is None:
            raise ValueError(f"unknown dataset kind {kind!r}; use 'auto' or one of {sorted(set(_KINDS))}")
    if k == "bag":
        ds = BagDataset(p, downscale=downscale, max_frames=max_frames, stride=stride, options=bag, **kw)
        ds.annotations = resolve_annotations(ds.path, k, annotations, ds.annotations)
        return with_pose_source(ds, pose_source, odometry, progress)
    bag_opts = bag.model_dump(exclude_defaults=True) if hasattr(bag, "model_dump") else dict(bag or {})
    if bag_opts:
        raise ValueError(f"{p}: bag options ({', '.join(sorted(bag_opts))}) apply to ROS bags only, not a {k} dataset")
    cls = {"replica": ReplicaDataset, "tum": TUMDataset, "7scenes": SevenScenesDataset,
           "camera": CameraFolderDataset, "realsense": RealSenseBagDataset}[k]
    ds = cls(p, downscale=downscale, max_frames=max_frames, stride=stride, **kw)
    ds.annotations = resolve_annotations(ds.path, k, annotations, ds.annotations)
    return with_pose_source(ds, pose_source, odometry, progress)
