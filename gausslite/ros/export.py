"""Write any GaussLite dataset as a ROS bag (``gausslite export bag``), readable back by the bag loader.

Topics and frames (the layout a RealSense-style driver with ``align_depth`` publishes; REP 105 frames):

=====================================  ================================  =================================
topic                                  type                              content
=====================================  ================================  =================================
``/camera/color/image_raw``            ``sensor_msgs/Image`` rgb8        colour, frame ``camera_color_optical_frame``
``/camera/color/camera_info``          ``sensor_msgs/CameraInfo``        K, plumb_bob D = 0 (images as loaded)
``/camera/aligned_depth_to_color/      ``sensor_msgs/Image`` 32FC1 (m)   depth registered to colour (same frame)
image_raw``                            or 16UC1 (mm)
``/tf_static``                         ``tf2_msgs/TFMessage``            ``map → odom`` (identity), ``base_link →
                                                                         camera_link`` (identity mount),
                                                                         ``camera_link → camera_color_optical_frame``
                                                                         (REP 103 optical rotation)
``/tf``                                ``tf2_msgs/TFMessage``            ``odom → base_link`` per frame
``/camera/pose``                       ``geometry_msgs/PoseStamped``     optical frame pose in ``map`` per frame
=====================================  ================================  =================================

Every message is stamped (header and log time) with the frame's timestamp, so the loader's pose
interpolation returns the exported pose exactly. ``objects.json`` / ``tasks.json`` of the dataset are
copied into a rosbag2 output folder (so ``gausslite sim`` / ``--task-id`` work on the bag).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any, Optional, Protocol, Union

import numpy as np

from gausslite.ros.bagio import BagWriter
from gausslite.ros.transforms import R_BODY_OPTICAL, invert

log = logging.getLogger(__name__)

__all__ = ["export_bag", "PosedFrames", "TOPICS", "FRAMES", "T_BASE_OPTICAL"]


class PosedFrames(Protocol):
    """What :func:`export_bag` reads: a sized, indexable sequence of posed RGB-D frames with a ``path``.

    Any :class:`gausslite.datasets.base.RGBDDataset` conforms. ``self[i]`` has the fields of
    :class:`gausslite.datasets.base.Frame`: ``timestamp`` (s), ``rgb`` (H, W, 3) uint8, ``depth`` (H, W) float32
    metres, ``c2w`` (4, 4) OpenCV camera-to-world, ``intrinsics``. An optional ``annotations`` attribute with
    ``objects_path`` / ``tasks_path`` is copied beside a rosbag2 output.
    """

    path: Path

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> Any: ...

TOPICS = {
    "rgb": "/camera/color/image_raw",
    "camera_info": "/camera/color/camera_info",
    "depth": "/camera/aligned_depth_to_color/image_raw",
    "pose": "/camera/pose",
}
FRAMES = {"world": "map", "odom": "odom", "base": "base_link", "link": "camera_link",
          "optical": "camera_color_optical_frame"}
_T_LINK_OPTICAL = np.eye(4)
_T_LINK_OPTICAL[:3, :3] = R_BODY_OPTICAL
#: pose of the colour optical frame in ``base_link`` (identity mount, optical rotation)
T_BASE_OPTICAL = _T_LINK_OPTICAL


def export_bag(dataset: PosedFrames, out: Union[str, Path], storage: str = "mcap", depth_encoding: str = "32FC1",
               progress: Optional[callable] = None) -> dict:
    """Write ``dataset`` as a bag (see the module docstring for topics and frames).

    Args:
        dataset: any loaded dataset (its downscale / frame selection / undistortion are what is written).
        out: output path: a new folder for rosbag2 (``mcap``, ``sqlite3``), a ``.bag`` file for ``ros1``.
        storage: ``"mcap"`` (default), ``"sqlite3"`` or ``"ros1"``.
        depth_encoding: ``"32FC1"`` (metres, exact float32) or ``"16UC1"`` (millimetres, rounded).
        progress: optional callback ``(i, n)`` after each frame.

    Returns:
        Summary dict: ``out``, ``frames``, ``topics``, ``storage``, ``depth_encoding``, ``annotations`` (copied files).

    Raises:
        FileExistsError: ``out`` exists. ValueError: bad storage / encoding, empty dataset, equal timestamps.
    """
    if depth_encoding not in ("32FC1", "16UC1"):
        raise ValueError(f"depth encoding must be 32FC1 or 16UC1, got {depth_encoding!r}")
    n = len(dataset)
    if n == 0:
        raise ValueError(f"{dataset.path}: no frames to export")
    out = Path(out)
    if storage == "ros1" and out.suffix != ".bag":
        raise ValueError(f"a ROS 1 bag must be a .bag file, got {out}")
    F = FRAMES
    T_odom_base_of = lambda c2w: c2w @ invert(T_BASE_OPTICAL)  # noqa: E731 - map == odom (identity)
    stamps = []
    with BagWriter(out, storage) as w:
        for i in range(n):
            fr = dataset[i]
            t = float(fr.timestamp)
            if stamps and t <= stamps[-1]:
                raise ValueError(f"{dataset.path}: timestamps must increase (frame {i}: {t} after {stamps[-1]})")
            stamps.append(t)
            if i == 0:
                w.write_tf(t, [(F["world"], F["odom"], np.eye(4)), (F["base"], F["link"], np.eye(4)),
                               (F["link"], F["optical"], _T_LINK_OPTICAL)], static=True)
            w.write_tf(t, [(F["odom"], F["base"], T_odom_base_of(fr.c2w))])
            w.write_pose(TOPICS["pose"], t, F["world"], fr.c2w)
            w.write_camera_info(TOPICS["camera_info"], t, F["optical"], fr.intrinsics)
            w.write_image(TOPICS["rgb"], t, F["optical"], fr.rgb, "rgb8")
            w.write_image(TOPICS["depth"], t, F["optical"], fr.depth, depth_encoding)
            if progress is not None:
                progress(i + 1, n)
    copied = []
    ann = getattr(dataset, "annotations", None)
    if ann is not None and out.is_dir():
        for src in (getattr(ann, "objects_path", None), getattr(ann, "tasks_path", None)):
            if src is not None:
                shutil.copyfile(src, out / Path(src).name)
                copied.append(Path(src).name)
    elif ann is not None:
        log.warning("%s: annotations not copied (a .bag file has no folder); put objects.json/tasks.json beside it", out)
    return {"out": str(out), "frames": n, "topics": dict(TOPICS), "storage": storage,
            "depth_encoding": depth_encoding, "annotations": copied}
