"""RGB-D dataset loaders (Replica / NICE-SLAM layout, TUM RGB-D, 7-Scenes, ROS bags, RealSense recordings, camera-file
folders) and scene annotations; poses for input without them come from :mod:`gausslite.odometry`.

Every loader is an :class:`RGBDDataset` yielding :class:`Frame` objects lazily; ``load_dataset`` picks
the loader from the folder layout. ``dataset.annotations`` is a :class:`SceneAnnotations` or None.
"""

from gausslite.datasets.annotations import (
    SceneAnnotations,
    SceneObject,
    Task,
    find_annotation_files,
    load_annotations,
    parse_up_axis,
    task_roi,
)
from gausslite.datasets.base import Frame, RGBDDataset
from gausslite.datasets.common import PosedImageDataset, downscale_depth, downscale_rgb, read_depth, read_rgb
from gausslite.datasets.bag import BagDataset, BagError, BagOptions
from gausslite.datasets.camera_folder import CameraFolderDataset
from gausslite.datasets.loader import detect_layout, load_dataset
from gausslite.datasets.realsense import RealSenseBagDataset
from gausslite.datasets.registration import DepthCamera, register_depth
from gausslite.datasets.replica import ReplicaDataset
from gausslite.datasets.sevenscenes import SevenScenesDataset
from gausslite.datasets.tum import TUMDataset

__all__ = [
    "Frame",
    "RGBDDataset",
    "PosedImageDataset",
    "ReplicaDataset",
    "TUMDataset",
    "SevenScenesDataset",
    "BagDataset",
    "CameraFolderDataset",
    "RealSenseBagDataset",
    "BagOptions",
    "BagError",
    "DepthCamera",
    "register_depth",
    "load_dataset",
    "detect_layout",
    "downscale_rgb",
    "downscale_depth",
    "read_rgb",
    "read_depth",
    "SceneAnnotations",
    "SceneObject",
    "Task",
    "load_annotations",
    "find_annotation_files",
    "parse_up_axis",
    "task_roi",
]
