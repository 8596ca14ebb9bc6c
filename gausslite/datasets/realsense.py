"""RealSense recordings: the ROS 1 ``.bag`` that the RealSense Viewer and ``rs-record`` write (librealsense's
rosbag format), read with ``rosbags``.

Topics used (``N``, ``S`` and ``D``: the device's, colour sensor's and depth sensor's numbers, found in the bag)::

    /device_N/sensor_S/Color_0/image/data              sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8)
    /device_N/sensor_S/Color_0/info/camera_info        sensor_msgs/CameraInfo: K, width, height
    /device_N/sensor_S/Color_0/tf/0                    geometry_msgs/Transform: the colour stream's extrinsics
    /device_N/sensor_D/Depth_0/image/data              sensor_msgs/Image (mono16 / 16UC1, in depth units)
    /device_N/sensor_D/Depth_0/info/camera_info        the depth camera's K
    /device_N/sensor_D/Depth_0/tf/0                    the depth stream's extrinsics
    /device_N/sensor_D/option/Depth Units/value        std_msgs/Float32: metres per depth unit (0.001 if absent)

Extrinsics (librealsense's ``ros_writer``): each stream's ``tf/0`` is the rigid transform from that stream's
optical frame to the device's reference stream (``p_ref = R p_stream + t``, metres; RealSense's optical axes are
x right, y down, z forward, as OpenCV's). The depth image is registered (aligned) to the colour camera with
``T_color_depth = T_ref_color^-1 T_ref_depth`` and both intrinsics by
:func:`gausslite.datasets.registration.register_depth` (z-buffered re-projection); when the depth image already
has the colour image's size and intrinsics and the extrinsics are the identity (an aligned recording), it is used
as it is. The streams' distortion is not applied (the D400 depth stream is rectified and its colour stream's
coefficients are usually zero; a non-zero one is logged).

Frames: each colour message is paired with the depth message nearest in bag time within ``max_depth_dt``; the
frame's timestamp is its bag time (seconds). A recording has no poses: ``has_poses`` is False and odometry
estimates them (:mod:`gausslite.odometry.rgbd`).
"""

from __future__ import annotations

import logging
import re
import threading
from pathlib import Path
from typing import List, Optional, Tuple, Union

import numpy as np

from gausslite.camera import Intrinsics
from gausslite.datasets.annotations import load_annotations
from gausslite.datasets.base import Frame, RGBDDataset
from gausslite.datasets.common import check_downscale, downscale_depth, downscale_rgb, select_indices
from gausslite.datasets.registration import DepthCamera, register_depth
from gausslite.datasets.tum import associate_nearest
from gausslite.ros.images import ImageDecodeError, decode_image
from gausslite.ros.transforms import make_transform

log = logging.getLogger(__name__)

__all__ = ["is_realsense_bag", "RealSenseBagDataset"]

_STREAM_RE = re.compile(r"^(/device_\d+/sensor_\d+)/(Color|Depth)_0/image/data$")


def _ros1_reader(path: Path):
    """An open ``rosbags`` reader of a ROS 1 bag (ROS 1 Noetic types, plus those the bag defines)."""
    # lazy: heavy optional dependency, loaded only on this path
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    r = AnyReader([path], default_typestore=get_typestore(Stores.ROS1_NOETIC))
    r.open()
    return r


def is_realsense_bag(path: Union[str, Path]) -> bool:
    """True for a ROS 1 ``.bag`` holding a RealSense colour stream topic (``/device_N/sensor_S/Color_0/image/
    data``); False for any other path, and for a file that cannot be read as a bag."""
    p = Path(path)
    if not (p.is_file() and p.suffix.lower() == ".bag"):
        return False
    try:
        r = _ros1_reader(p)
    except Exception:  # noqa: BLE001 - not a readable bag: the generic bag reader reports why
        return False
    try:
        return any((m := _STREAM_RE.match(c.topic)) and m.group(2) == "Color" for c in r.connections)
    finally:
        r.close()


def _K(info) -> np.ndarray:
    """(3, 3) K of a CameraInfo (``K`` in ROS 1, ``k`` in ROS 2)."""
    k = getattr(info, "K", None)
    return np.asarray(k if k is not None else info.k, dtype=np.float64).reshape(3, 3)


class RealSenseBagDataset(RGBDDataset):
    """A RealSense recording as an RGB-D sequence without poses (see the module docstring).

    Args:
        path: the ``.bag`` file.
        downscale, max_frames, stride: as every loader.
        max_depth_dt: colour↔depth pairing tolerance (seconds).
        depth_splat: footprint (pixels) of each registered depth sample.

    Attributes:
        path, name, intrinsics (after downscaling), native_intrinsics (the colour CameraInfo's), depth_camera
        (:class:`DepthCamera`, or None when the depth is already aligned), depth_units (metres per unit),
        timestamps ((N,) s), frame_ids (index of the colour message), poses ((N, 4, 4) identity), has_poses (False),
        n_dropped (colour frames without depth within ``max_depth_dt``).

    Raises:
        FileNotFoundError: no such file. ValueError: not a RealSense recording, a missing topic (named), or no
            colour frame with depth.
    """

    has_poses = False

    def __init__(self, path: Union[str, Path], downscale: Union[int, float] = 1, max_frames: Optional[int] = None,
                 stride: int = 1, max_depth_dt: float = 0.02, depth_splat: int = 1) -> None:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"bag not found: {p}")
        self.path, self.name = p, p.stem
        self.downscale = check_downscale(downscale)
        self._lock = threading.Lock()
        self._reader = _ros1_reader(p)
        try:
            self._scan(max_depth_dt, depth_splat)
        finally:
            self.close()
        sel = select_indices(len(self._pairs), stride, max_frames)
        self._pairs = [self._pairs[k] for k in sel]
        self.timestamps = np.array([c[0] * 1e-9 for c, _ in self._pairs], dtype=np.float64)
        self.frame_ids = [c[1] for c, _ in self._pairs]
        self.frame_names = [f"frame{i:06d}" for i in self.frame_ids]
        self.poses = np.broadcast_to(np.eye(4), (len(self._pairs), 4, 4))
        ni = self.native_intrinsics
        self.intrinsics = ni if self.downscale == 1.0 else ni.scaled(self.downscale)
        self.annotations = load_annotations(p.parent)

    def _topics(self) -> Tuple[str, str]:
        """The colour and depth streams' topic prefixes (``/device_N/sensor_S/Color_0``)."""
        found = {}
        for c in self._reader.connections:
            m = _STREAM_RE.match(c.topic)
            if m:
                found.setdefault(m.group(2), f"{m.group(1)}/{m.group(2)}_0")
        for kind in ("Color", "Depth"):
            if kind not in found:
                raise ValueError(f"{self.path}: topic /device_0/sensor_*/{kind}_0/image/data is missing: not a "
                                 f"RealSense recording with colour and depth")
        return found["Color"], found["Depth"]

    def _first(self, topic: str, required: bool = True):
        conns = [c for c in self._reader.connections if c.topic == topic]
        for c, _t, raw in self._reader.messages(connections=conns) if conns else ():  # no connection: all of them
            return self._reader.deserialize(raw, c.msgtype)
        if required:
            raise ValueError(f"{self.path}: topic {topic} is missing or empty")
        return None

    def _stamps(self, topic: str) -> List[Tuple[int, int]]:
        """``[(bag time ns, message index)]`` of an image topic, in bag order."""
        conns = [c for c in self._reader.connections if c.topic == topic]
        msgs = self._reader.messages(connections=conns) if conns else ()  # no connection would read every topic
        return [(int(t), i) for i, (_c, t, _raw) in enumerate(msgs)]

    def _scan(self, max_depth_dt: float, depth_splat: int) -> None:
        """Read the cameras, the depth units and the extrinsics, and pair colour with depth messages."""
        color, depth = self._topics()
        self.rgb_topic, self.depth_topic = f"{color}/image/data", f"{depth}/image/data"
        ci, di = self._first(f"{color}/info/camera_info"), self._first(f"{depth}/info/camera_info")
        for info, topic in ((ci, color), (di, depth)):
            d = getattr(info, "D", None) if getattr(info, "D", None) is not None else getattr(info, "d", ())
            if any(float(v) for v in d):
                log.warning("%s: %s/info/camera_info has distortion %s, which is not applied", self.path, topic,
                            list(d))
        self.native_intrinsics = Intrinsics.from_K(_K(ci), int(ci.width), int(ci.height))
        depth_intr = Intrinsics.from_K(_K(di), int(di.width), int(di.height))
        sensor = depth.rsplit("/", 1)[0]
        units = self._first(f"{sensor}/option/Depth Units/value", required=False)
        self.depth_units = float(units.data) if units is not None else 0.001
        if units is None:
            log.warning("%s: no %s/option/Depth Units/value: depth units taken as 0.001 m", self.path, sensor)
        T_ref = {}
        for kind, topic in (("color", color), ("depth", depth)):
            tf = self._first(f"{topic}/tf/0")
            tr, q = tf.translation, tf.rotation
            T_ref[kind] = make_transform((tr.x, tr.y, tr.z), (q.x, q.y, q.z, q.w))
        T_cd = np.linalg.inv(T_ref["color"]) @ T_ref["depth"]
        aligned = depth_intr == self.native_intrinsics and np.allclose(T_cd, np.eye(4), atol=1e-6)
        self.depth_camera = None if aligned else DepthCamera(depth_intr, T_cd, splat=depth_splat)
        cs, ds = self._stamps(self.rgb_topic), self._stamps(self.depth_topic)
        if not cs or not ds:
            raise ValueError(f"{self.path}: no {'colour' if not cs else 'depth'} image messages")
        d_t = np.array([t for t, _ in ds], dtype=np.float64) * 1e-9
        idx, gap = associate_nearest(np.array([t for t, _ in cs], dtype=np.float64) * 1e-9, d_t)
        self._pairs = [(c, ds[int(j)]) for c, j, g in zip(cs, idx, gap) if g <= max_depth_dt]
        self.n_dropped = len(cs) - len(self._pairs)
        if not self._pairs:
            raise ValueError(f"{self.path}: no colour frame has a depth frame within {max_depth_dt} s")
        if self.n_dropped:
            log.warning("%s: dropped %d of %d colour frames without depth within %.3f s", self.path, self.n_dropped,
                        len(cs), max_depth_dt)

    def close(self) -> None:
        """Close the bag (reopened on the next frame read)."""
        r, self._reader = self._reader, None
        if r is not None:
            r.close()

    def __len__(self) -> int:
        """Number of (selected) frames."""
        return len(self._pairs)

    def __repr__(self) -> str:
        i = self.intrinsics
        return f"RealSenseBagDataset({str(self.path)!r}, frames={len(self)}, size={i.width}x{i.height})"

    def _image(self, topic: str, log_ns: int, index: int, want: str) -> np.ndarray:
        with self._lock:
            if self._reader is None:
                self._reader = _ros1_reader(self.path)
            conns = [c for c in self._reader.connections if c.topic == topic]
            msg = next((self._reader.deserialize(raw, c.msgtype)
                        for c, _t, raw in self._reader.messages(connections=conns, start=log_ns, stop=log_ns + 1)),
                       None)
        if msg is None:
            raise ValueError(f"{self.path}: message {index} of {topic} vanished")
        try:
            kind, arr = decode_image(msg.encoding, msg.height, msg.width, msg.step, msg.data, bool(msg.is_bigendian))
        except ImageDecodeError as e:
            raise ValueError(f"{self.path}: {topic} message {index}: {e}") from None
        if kind != want:
            raise ValueError(f"{self.path}: {topic} message {index}: a {kind} image on the {want} stream")
        return arr

    def _load(self, i: int) -> Frame:
        """Decode frame ``i``, register its depth to the colour camera and downscale it."""
        (c_ns, c_idx), (d_ns, d_idx) = self._pairs[i]
        rgb = self._image(self.rgb_topic, c_ns, c_idx, "color")
        depth = self._image(self.depth_topic, d_ns, d_idx, "depth") * np.float32(self.depth_units / 0.001)
        ni = self.native_intrinsics
        if (rgb.shape[1], rgb.shape[0]) != (ni.width, ni.height):
            raise ValueError(f"{self.path}: {self.rgb_topic} message {c_idx} is {rgb.shape[1]}x{rgb.shape[0]}, its "
                             f"camera_info says {ni.width}x{ni.height}")
        if self.depth_camera is not None:
            depth = register_depth(depth, self.depth_camera, ni)
        if self.downscale != 1.0:
            rgb, depth = downscale_rgb(rgb, self.downscale), downscale_depth(depth, self.downscale)
        return Frame(frame_id=c_idx, timestamp=c_ns * 1e-9, rgb=rgb, depth=depth.astype(np.float32, copy=False),
                     c2w=np.eye(4), intrinsics=self.intrinsics, name=f"frame{c_idx:06d}")
