"""Bag files through ``rosbags`` (pure Python, no ROS install): path detection and a message writer.

Storage formats: rosbag2 with MCAP storage (a folder with ``metadata.yaml`` and ``*.mcap``, or a
bare ``.mcap`` file), rosbag2 with SQLite3 storage (folder with ``*.db3``, or a bare ``.db3``), and
ROS 1 bags (``.bag``, format 2.0). Reading is :class:`gausslite.datasets.bag.BagDataset`.

:class:`BagWriter` writes the message types GaussLite uses (``sensor_msgs/Image``,
``CompressedImage``, ``CameraInfo``, ``tf2_msgs/TFMessage``, ``geometry_msgs/PoseStamped``,
``nav_msgs/Odometry``) into any of the three formats, with the field spellings each ROS version uses
(ROS 1 ``CameraInfo.K`` / ``Header.seq``, ROS 2 ``CameraInfo.k``). It is used by
``gausslite export bag`` and by the tests that build bags.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, Iterable, Sequence, Tuple, Union

import numpy as np

from gausslite.camera import Intrinsics
from gausslite.ros.images import encode_image
from gausslite.ros.transforms import transform_to_tq

__all__ = ["BAG_SUFFIXES", "is_bag_path", "BagWriter", "ros_typestore"]

#: File suffixes of bags (a rosbag2 folder is recognised by its ``metadata.yaml``).
BAG_SUFFIXES = (".bag", ".mcap", ".db3")
STORAGES = ("mcap", "sqlite3", "ros1")


def is_bag_path(path: Union[str, Path]) -> bool:
    """True for a ``.bag`` / ``.mcap`` / ``.db3`` file or a rosbag2 folder (``metadata.yaml`` inside)."""
    p = Path(path)
    if p.is_file():
        return p.suffix.lower() in BAG_SUFFIXES
    return p.is_dir() and (p / "metadata.yaml").is_file()


def ros_typestore(ros1: bool):
    """The rosbags typestore for writing: ROS 1 Noetic (+ ``tf2_msgs/TFMessage``) or ROS 2 Humble."""
    # lazy: heavy optional dependency, loaded only on this path
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if not ros1:
        return get_typestore(Stores.ROS2_HUMBLE)
    ts = get_typestore(Stores.ROS1_NOETIC)
    if "tf2_msgs/msg/TFMessage" not in ts.fielddefs:
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


def _ns(t: float) -> int:
    return int(round(float(t) * 1e9))


class BagWriter:
    """Write GaussLite's message types to a new bag.

    Args:
        path: output: a folder for rosbag2 (``storage`` ``"mcap"`` or ``"sqlite3"``; must not exist), a
            ``.bag`` file for ``"ros1"``.
        storage: ``"mcap"`` (default), ``"sqlite3"`` or ``"ros1"``.

    Every ``write_*`` method takes the message stamp ``t`` in seconds; the bag's log time is the same.
    Use as a context manager (closing writes the index / ``metadata.yaml``).

    Raises:
        ValueError: unknown storage. FileExistsError: the output exists.
    """

    def __init__(self, path: Union[str, Path], storage: str = "mcap") -> None:
        if storage not in STORAGES:
            raise ValueError(f"unknown bag storage {storage!r}; use one of {STORAGES}")
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f"bag output already exists: {self.path}")
        self.storage = storage
        self.ros1 = storage == "ros1"
        self.ts = ros_typestore(self.ros1)
        if self.ros1:
            # lazy: heavy optional dependency, loaded only on this path
            from rosbags.rosbag1 import Writer as W1

            self._w = W1(self.path)
        else:
            # lazy: heavy optional dependency, loaded only on this path
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as W2

            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self._w = W2(self.path, version=9, storage_plugin=plugin)
        self._conns: Dict[str, object] = {}
        self._seq: Dict[str, int] = {}

    # ------------------------------------------------------------------ plumbing
    def __enter__(self) -> "BagWriter":
        self._w.open()
        return self

    def __exit__(self, *exc) -> None:
        self._w.close()

    def _t(self, name: str):
        return self.ts.types[name]

    def _stamp(self, t: float):
        ns = _ns(t)
        return self._t("builtin_interfaces/msg/Time")(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    def header(self, t: float, frame: str, topic: str = ""):
        """A ``std_msgs/Header`` (ROS 1: with a per-topic ``seq``)."""
        H = self._t("std_msgs/msg/Header")
        if self.ros1:
            seq = self._seq.get(topic, 0)
            self._seq[topic] = seq + 1
            return H(seq=seq, stamp=self._stamp(t), frame_id=frame)
        return H(stamp=self._stamp(t), frame_id=frame)

    def write(self, topic: str, msgtype: str, msg, t: float) -> None:
        """Serialise ``msg`` of ``msgtype`` (e.g. ``sensor_msgs/msg/Image``) to ``topic`` at log time ``t`` s."""
        conn = self._conns.get(topic)
        if conn is None:
            kw = {"latching": 1} if (self.ros1 and topic == "/tf_static") else {}
            conn = self._conns[topic] = self._w.add_connection(topic, msgtype, typestore=self.ts, **kw)
        data = self.ts.serialize_ros1(msg, msgtype) if self.ros1 else self.ts.serialize_cdr(msg, msgtype)
        self._w.write(conn, _ns(t), data)

    # ------------------------------------------------------------------ messages
    def write_image(self, topic: str, t: float, frame: str, arr: np.ndarray, encoding: str) -> None:
        """``sensor_msgs/Image`` of a colour (H, W, 3) uint8 RGB or depth (H, W) metres array."""
        h, w, step, data = encode_image(arr, encoding)
        msg = self._t("sensor_msgs/msg/Image")(
            header=self.header(t, frame, topic), height=h, width=w, encoding=encoding, is_bigendian=0,
            step=step, data=np.frombuffer(data, np.uint8))
        self.write(topic, "sensor_msgs/msg/Image", msg, t)

    def write_compressed(self, topic: str, t: float, frame: str, fmt: str, data: bytes) -> None:
        """``sensor_msgs/CompressedImage`` with ``format`` and payload (see :mod:`gausslite.ros.images`)."""
        msg = self._t("sensor_msgs/msg/CompressedImage")(
            header=self.header(t, frame, topic), format=fmt, data=np.frombuffer(data, np.uint8))
        self.write(topic, "sensor_msgs/msg/CompressedImage", msg, t)

    def write_camera_info(self, topic: str, t: float, frame: str, intr: Intrinsics,
                          distortion: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0)) -> None:
        """``sensor_msgs/CameraInfo``: ``K``, plumb_bob ``D``, identity ``R``, ``P = [K | 0]``."""
        K = intr.K
        P = np.zeros((3, 4))
        P[:, :3] = K
        fields = dict(d=np.asarray(distortion, np.float64), k=K.ravel(), r=np.eye(3).ravel(), p=P.ravel())
        if self.ros1:
            fields = {k.upper(): v for k, v in fields.items()}
        roi = self._t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        msg = self._t("sensor_msgs/msg/CameraInfo")(
            header=self.header(t, frame, topic), height=intr.height, width=intr.width,
            distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi, **fields)
        self.write(topic, "sensor_msgs/msg/CameraInfo", msg, t)

    def _tq(self, T: np.ndarray):
        tr, q = transform_to_tq(T)
        V = self._t("geometry_msgs/msg/Vector3")
        Q = self._t("geometry_msgs/msg/Quaternion")
        return V(x=tr[0], y=tr[1], z=tr[2]), Q(x=q[0], y=q[1], z=q[2], w=q[3])

    def _pose(self, T: np.ndarray):
        v, q = self._tq(T)
        Pt = self._t("geometry_msgs/msg/Point")
        return self._t("geometry_msgs/msg/Pose")(position=Pt(x=v.x, y=v.y, z=v.z), orientation=q)

    def write_tf(self, t: float, transforms: Iterable[Tuple[str, str, np.ndarray]], static: bool = False) -> None:
        """One ``tf2_msgs/TFMessage`` on ``/tf`` (or ``/tf_static``) of ``(parent, child, T_parent_child)``."""
        topic = "/tf_static" if static else "/tf"
        items = []
        for parent, child, T in transforms:
            v, q = self._tq(T)
            items.append(self._t("geometry_msgs/msg/TransformStamped")(
                header=self.header(t, parent, topic), child_frame_id=child,
                transform=self._t("geometry_msgs/msg/Transform")(translation=v, rotation=q)))
        self.write(topic, "tf2_msgs/msg/TFMessage", self._t("tf2_msgs/msg/TFMessage")(transforms=items), t)

    def write_pose(self, topic: str, t: float, frame: str, T: np.ndarray) -> None:
        """``geometry_msgs/PoseStamped``: the pose ``T`` (4x4) in ``frame``."""
        msg = self._t("geometry_msgs/msg/PoseStamped")(header=self.header(t, frame, topic), pose=self._pose(T))
        self.write(topic, "geometry_msgs/msg/PoseStamped", msg, t)

    def write_odometry(self, topic: str, t: float, frame: str, child: str, T: np.ndarray) -> None:
        """``nav_msgs/Odometry``: pose ``T`` of ``child`` in ``frame`` (zero twist and covariances)."""
        cov = np.zeros(36)
        V = self._t("geometry_msgs/msg/Vector3")
        twist = self._t("geometry_msgs/msg/Twist")(linear=V(x=0.0, y=0.0, z=0.0), angular=V(x=0.0, y=0.0, z=0.0))
        msg = self._t("nav_msgs/msg/Odometry")(
            header=self.header(t, frame, topic), child_frame_id=child,
            pose=self._t("geometry_msgs/msg/PoseWithCovariance")(pose=self._pose(T), covariance=cov),
            twist=self._t("geometry_msgs/msg/TwistWithCovariance")(twist=twist, covariance=cov))
        self.write(topic, "nav_msgs/msg/Odometry", msg, t)

