"""ROS bags as RGB-D datasets: rosbag2 (MCAP or SQLite3 storage) and ROS 1 ``.bag``, read with ``rosbags``.

A bag is a dataset wherever a dataset path is accepted (``gausslite map``, ``ablate``, ``sim``, the
agent's replay): ``load_dataset`` recognises a rosbag2 folder (``metadata.yaml``), a bare ``.mcap`` /
``.db3`` file or a ``.bag`` file.

Topics (:class:`BagOptions`; each can be given, else it is chosen as below; when a choice is ambiguous
or missing the loader raises :class:`BagError` listing every topic and TF frame of the bag):

- colour: ``sensor_msgs/Image`` (rgb8, bgr8, rgba8, bgra8, mono8) or ``sensor_msgs/CompressedImage``
  (jpeg/png) — the only colour image topic of the bag;
- depth: ``Image`` (16UC1 / mono16 in millimetres, 32FC1 in metres) or ``CompressedImage`` (image_transport
  ``compressedDepth``, or a 16-bit PNG in millimetres) — the only depth topic, or, among several, the only
  one in the colour camera's frame (already registered);
- colour ``sensor_msgs/CameraInfo``: the one whose ``frame_id`` is the colour image's, else
  ``<colour topic namespace>/camera_info``, else the only CameraInfo topic;
- depth ``CameraInfo`` (only when the depth image is in another frame than the colour image: unregistered
  depth): the one in the depth image's frame, else ``<depth topic namespace>/camera_info``.

Intrinsics: ``K`` and the ``plumb_bob`` (or ``rational_polynomial``) ``D`` of the colour CameraInfo.
Topics whose name contains ``rect`` are taken as rectified: ``P[:, :3]`` is used and ``D`` ignored. With
``undistort=True`` (default) images with non-zero ``D`` are undistorted as :mod:`gausslite.datasets.tum`
does (OpenCV alpha=0 optimal new camera; colour bilinear, depth nearest).

Poses (the camera pose is the pose of the colour image's optical frame, ``header.frame_id`` or
``camera_frame``, in the world frame; optical axes x right, y down, z forward = GaussLite's camera axes,
REP 103):

- ``pose_topic`` (``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``TransformStamped`` or
  ``nav_msgs/Odometry``): the pose of a body ``B`` in the message's ``header.frame_id``; ``B`` is the
  Odometry's ``child_frame_id``, else ``pose_child_frame``, else the camera frame itself. When ``B`` is not
  the camera frame, ``T_B_camera`` comes from TF; when ``world_frame`` differs from the message frame,
  ``T_world_msgframe`` comes from TF.
- otherwise TF (``/tf`` composed with ``/tf_static`` along the tree): ``world_frame``, by default ``map``
  if it is connected to the camera frame, else ``odom`` (REP 105), else the root of the camera's tree.
  When the camera frame is not in TF, or TF holds only static transforms above it (the mounting),
  the bag's only pose-type topic is used.

Poses are interpolated at the colour stamps (translation lerp, rotation slerp); a frame whose stamp is
further than ``max_pose_dt`` from the nearest sample of any dynamic transform it needs is dropped with a
warning, and when no frame is left the loader raises. Colour↔depth association: the nearest depth stamp
within ``max_depth_dt``, as TUM's ``associate.py``.

Unregistered depth is registered to the colour camera with
:func:`gausslite.datasets.registration.register_depth` (both intrinsics, ``T_colour_depth`` from TF at the
frame's stamp).
"""

from __future__ import annotations

import logging
import threading
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gausslite.camera import Intrinsics, check_rigid
from gausslite.datasets.annotations import load_annotations
from gausslite.datasets.bag_poses import POSE_TYPES, header_stamp, pose_sampler  # noqa: F401 - POSE_TYPES re-exported
from gausslite.datasets.base import Frame, RGBDDataset
from gausslite.datasets.common import check_downscale, downscale_depth, downscale_rgb, select_indices
from gausslite.datasets.registration import DepthCamera, register_depth
from gausslite.datasets.tum import associate_nearest
from gausslite.ros.bagio import is_bag_path
from gausslite.ros.images import ImageDecodeError, decode_compressed, decode_image
from gausslite.ros.transforms import TFBuffer, TFError, make_transform, normalize_frame

log = logging.getLogger(__name__)

__all__ = ["BagOptions", "BagDataset", "BagError"]

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"


class BagError(ValueError):
    """A bag that cannot be used as a dataset; the message lists the bag's topics and TF frames."""


class BagOptions(BaseModel):
    """How to read a bag (all optional; see the module docstring for the defaults).

    Attributes:
        rgb_topic, depth_topic, camera_info_topic, depth_camera_info_topic: topic names.
        pose_topic: PoseStamped / PoseWithCovarianceStamped / TransformStamped / Odometry topic; None = TF.
        pose_child_frame: frame whose pose a PoseStamped topic gives (default: the camera frame).
        world_frame: world frame id (default ``map``, else ``odom``, else the tree root / the pose topic's frame).
        camera_frame: camera optical frame id (default: the colour image's ``header.frame_id``).
        max_depth_dt: colour↔depth association tolerance (seconds).
        max_pose_dt: pose tolerance (seconds) between a colour stamp and the nearest pose sample.
        undistort: undistort images whose CameraInfo has non-zero distortion.
        depth_splat: footprint (pixels) of each registered depth sample (1 = nearest pixel).
    """

    model_config = ConfigDict(extra="forbid")

    rgb_topic: Optional[str] = None
    depth_topic: Optional[str] = None
    camera_info_topic: Optional[str] = None
    depth_camera_info_topic: Optional[str] = None
    pose_topic: Optional[str] = None
    pose_child_frame: Optional[str] = None
    world_frame: Optional[str] = None
    camera_frame: Optional[str] = None
    max_depth_dt: float = Field(0.02, ge=0)
    max_pose_dt: float = Field(0.05, ge=0)
    undistort: bool = True
    depth_splat: int = Field(1, ge=1, le=5)


@dataclass
class _Img:
    stamp: float
    log_ns: int
    frame: str
    index: int


def _field(msg, name: str):
    """CameraInfo fields are ``k`` in ROS 2 and ``K`` in ROS 1."""
    v = getattr(msg, name, None)
    return v if v is not None else getattr(msg, name.upper())


def _namespace(topic: str) -> str:
    t = topic.rstrip("/")
    for suffix in ("/compressedDepth", "/compressed"):
        if t.endswith(suffix):
            t = t[: -len(suffix)]
    return t.rsplit("/", 1)[0]


class BagDataset(RGBDDataset):
    """A posed RGB-D sequence read from a ROS bag (see the module docstring).

    Args:
        path: rosbag2 folder, ``.mcap`` / ``.db3`` file or ROS 1 ``.bag`` file.
        downscale, max_frames, stride: as every loader (applied after association).
        options: :class:`BagOptions` or a dict of its fields; keyword arguments override single fields.

    Attributes:
        path, name, intrinsics (after undistortion and downscaling), native_intrinsics (full size, after
        undistortion), raw_intrinsics (CameraInfo), distortion, poses ((N, 4, 4) float64 camera-to-world,
        optical axes), timestamps ((N,) colour stamps, s), frame_ids (index of the colour message),
        topics (``{name: (type, count)}``), tf (:class:`TFBuffer`), world_frame, camera_frame,
        rgb_topic, depth_topic, pose_topic (where the poses were read: ``"tf"`` for the TF tree, else the pose
        topic; ``pose_source`` is its old name, deprecated), registered (False: the depth
        topic has its own camera and is registered on load, see :meth:`depth_camera_at`), n_dropped, annotations.

    Raises:
        FileNotFoundError: missing path. BagError (a ValueError): unreadable bag, missing/ambiguous topic,
            unsupported encoding, disconnected TF chain, no pose/depth within tolerance; the message lists
            the topics and TF frames found.
    """

    def __init__(
        self,
        path: Union[str, Path],
        downscale: Union[int, float] = 1,
        max_frames: Optional[int] = None,
        stride: int = 1,
        options: Optional[Union[BagOptions, dict]] = None,
        **kw,
    ) -> None:
        p = Path(path)
        if not p.exists():
            raise FileNotFoundError(f"bag not found: {p}")
        if not is_bag_path(p):
            raise ValueError(f"{p}: not a bag (a rosbag2 folder with metadata.yaml, or a .mcap/.db3/.bag file)")
        base = options.model_dump() if isinstance(options, BagOptions) else dict(options or {})
        base.update({k: v for k, v in kw.items() if v is not None})
        self.options = opt = BagOptions(**base)
        self.path = p
        self.name = p.stem if p.is_file() else p.name
        self.downscale = check_downscale(downscale)
        self._lock = threading.Lock()
        self._reader = None
        self.topics: Dict[str, Tuple[str, int]] = {}
        self.tf = TFBuffer()

        reader = self._open()
        try:
            self._scan(reader, opt)
        finally:
            self._close_reader()

        self.annotations = load_annotations(p)
        sel = select_indices(len(self._pairs), stride, max_frames)
        self._pairs = [self._pairs[k] for k in sel]
        self.poses = np.stack([pr[2] for pr in self._pairs]) if self._pairs else np.zeros((0, 4, 4))
        self.timestamps = np.array([pr[0].stamp for pr in self._pairs], dtype=np.float64)
        self.frame_ids = [pr[0].index for pr in self._pairs]
        self.frame_names = [f"frame{i:06d}" for i in self.frame_ids]
        ni = self.native_intrinsics
        self.intrinsics = ni if self.downscale == 1.0 else ni.scaled(self.downscale)

    # ------------------------------------------------------------------ reading
    def _open(self):
        # lazy: heavy optional dependency, loaded only on this path
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        store = Stores.ROS1_NOETIC if self.path.suffix == ".bag" else Stores.ROS2_HUMBLE
        try:
            r = AnyReader([self.path], default_typestore=get_typestore(store))
            r.open()
        except FileNotFoundError:
            raise
        except Exception as e:  # rosbags raises several reader error types
            raise BagError(f"{self.path}: cannot read bag ({type(e).__name__}: {e})") from None
        self._reader = r
        return r

    def _close_reader(self) -> None:
        r, self._reader = self._reader, None
        if r is not None:
            try:
                r.close()
            except Exception:  # noqa: BLE001 - closing a half-open reader must not mask the real error
                pass

    def close(self) -> None:
        """Close the bag reader held open for lazy frame access (reopened on the next access)."""
        with self._lock:
            self._close_reader()

    def __del__(self) -> None:
        try:
            self._close_reader()
        except Exception:  # noqa: BLE001
            pass

    def _inventory(self) -> str:
        tops = "\n".join(f"    {t}  [{ty}, {n} messages]" for t, (ty, n) in sorted(self.topics.items())) or "    (none)"
        frames = ", ".join(self.tf.frames) or "(none)"
        return f"  topics found:\n{tops}\n  TF frames found: {frames}\n  TF edges: {self.tf.describe()}"

    def _fail(self, msg: str) -> BagError:
        return BagError(f"{self.path}: {msg}\n{self._inventory()}")

    def _first(self, reader, topic: str):
        conns = [c for c in reader.connections if c.topic == topic]
        for c, _ts, raw in reader.messages(connections=conns):
            return reader.deserialize(raw, c.msgtype)
        return None

    # ------------------------------------------------------------------ topic selection
    def _classify(self, reader, topic: str) -> Tuple[Optional[str], str, str]:
        """(``"color"``/``"depth"``/None, frame_id, problem) of an image topic from its first message."""
        msg = self._first(reader, topic)
        if msg is None:
            return None, "", "no messages"
        try:
            kind, _ = self._decode(self.topics[topic][0], msg)
        except ImageDecodeError as e:
            return None, normalize_frame(msg.header.frame_id), str(e)
        return kind, normalize_frame(msg.header.frame_id), ""

    @staticmethod
    def _decode(msgtype: str, msg) -> Tuple[str, np.ndarray]:
        if msgtype == COMPRESSED:
            return decode_compressed(msg.format, msg.data)
        return decode_image(msg.encoding, msg.height, msg.width, msg.step, msg.data, bool(msg.is_bigendian))

    def _pick_topic(self, given: Optional[str], what: str, candidates: List[str], types: Sequence[str],
                    hint: str = "") -> str:
        """``given`` (checked to exist with one of ``types``), else the only candidate; ``hint`` is added when
        there is none."""
        if given:
            if given not in self.topics:
                raise self._fail(f"{what} topic {given!r} is not in the bag")
            if self.topics[given][0] not in types:
                raise self._fail(f"{what} topic {given!r} has type {self.topics[given][0]}, expected one of {list(types)}")
            return given
        if len(candidates) == 1:
            return candidates[0]
        if not candidates:
            raise self._fail(f"no {what} topic found{hint}")
        flag = "--" + what.replace(" ", "-") + "-topic"
        raise self._fail(f"several {what} topics ({', '.join(candidates)}); choose one with {flag}")

    def _scan(self, reader, opt: BagOptions) -> None:
        for c in reader.connections:
            ty, n = self.topics.get(c.topic, (c.msgtype, 0))
            self.topics[c.topic] = (ty, n + int(c.msgcount or 0))
        # TF first: error messages list the frames
        tf_conns = [c for c in reader.connections if c.msgtype == TF_TYPE and c.topic in ("/tf", "/tf_static")]
        for c, _ts, raw in (reader.messages(connections=tf_conns) if tf_conns else ()):  # [] would mean "all"
            msg = reader.deserialize(raw, c.msgtype)
            for tr in msg.transforms:
                T = make_transform((tr.transform.translation.x, tr.transform.translation.y, tr.transform.translation.z),
                                   (tr.transform.rotation.x, tr.transform.rotation.y, tr.transform.rotation.z,
                                    tr.transform.rotation.w))
                try:
                    self.tf.add(tr.header.frame_id, tr.child_frame_id, header_stamp(tr.header), T, static=c.topic == "/tf_static")
                except TFError as e:
                    raise self._fail(str(e)) from None

        # image topics: colour / depth by their first message
        kinds: Dict[str, Tuple[Optional[str], str, str]] = {}
        for t, (ty, _n) in self.topics.items():
            if ty in (IMAGE, COMPRESSED):
                kinds[t] = self._classify(reader, t)
        for given, want in ((opt.rgb_topic, "color"), (opt.depth_topic, "depth")):
            if given and given in kinds and kinds[given][0] != want:
                k, _f, prob = kinds[given]
                raise self._fail(f"{'colour' if want == 'color' else 'depth'} topic {given!r}: "
                                 + (prob if k is None else f"holds {k} images, not {want}"))
        colors = [t for t, k in kinds.items() if k[0] == "color"]
        depths = [t for t, k in kinds.items() if k[0] == "depth"]
        bad = [f"{t} ({k[2]})" for t, k in kinds.items() if k[0] is None]
        hint = f" (unusable image topics: {'; '.join(bad)})" if bad else ""
        self.rgb_topic = self._pick_topic(opt.rgb_topic, "rgb", colors, (IMAGE, COMPRESSED), hint)
        color_frame = kinds[self.rgb_topic][1]
        if not opt.depth_topic and len(depths) > 1:
            same = [t for t in depths if kinds[t][1] == color_frame]
            if len(same) == 1:
                log.info("%s: several depth topics; using %s (in the colour frame %s)", self.path, same[0], color_frame)
                depths = same
        self.depth_topic = self._pick_topic(opt.depth_topic, "depth", depths, (IMAGE, COMPRESSED), hint)
        depth_frame = kinds[self.depth_topic][1]
        self.camera_frame = normalize_frame(opt.camera_frame) if opt.camera_frame else color_frame

        # camera infos
        infos = {t: self._first(reader, t) for t, (ty, _n) in self.topics.items() if ty == CAMERA_INFO}
        info_frames = {t: normalize_frame(m.header.frame_id) for t, m in infos.items() if m is not None}

        def pick_info(given, what, frame, img_topic, flag):
            if given:
                return self._pick_topic(given, what, [], (CAMERA_INFO,))
            same = [t for t, f in info_frames.items() if f == frame and frame]
            if len(same) == 1:
                return same[0]
            ns = _namespace(img_topic) + "/camera_info"
            if ns in info_frames:
                return ns
            if len(info_frames) == 1:
                return next(iter(info_frames))
            raise self._fail(f"no {what} topic found for {img_topic!r}; choose one with {flag}")

        self.camera_info_topic = pick_info(opt.camera_info_topic, "camera info", color_frame, self.rgb_topic,
                                           "--camera-info-topic")
        color_info = infos[self.camera_info_topic]
        if color_info is None:
            raise self._fail(f"camera info topic {self.camera_info_topic!r} has no messages")
        self.registered = depth_frame == color_frame and not opt.depth_camera_info_topic
        self.depth_camera_info_topic = None
        if not self.registered:
            self.depth_camera_info_topic = pick_info(opt.depth_camera_info_topic, "depth camera info", depth_frame,
                                                     self.depth_topic, "--depth-camera-info-topic")
            if self.depth_camera_info_topic == self.camera_info_topic and depth_frame != color_frame:
                raise self._fail(f"depth topic {self.depth_topic!r} is in frame {depth_frame!r}, colour in "
                                 f"{color_frame!r}, but no CameraInfo of the depth camera was found; give "
                                 f"--depth-camera-info-topic")
        self.raw_intrinsics, self.distortion = self._intrinsics(color_info, self.rgb_topic)

        # image stamps
        imgs: Dict[str, List[_Img]] = {self.rgb_topic: [], self.depth_topic: []}
        conns = [c for c in reader.connections if c.topic in imgs]
        for c, ts, raw in reader.messages(connections=conns):
            h = reader.deserialize(raw, c.msgtype).header
            lst = imgs[c.topic]
            lst.append(_Img(header_stamp(h), int(ts), normalize_frame(h.frame_id), len(lst)))
        colour_msgs, depth_msgs = imgs[self.rgb_topic], imgs[self.depth_topic]

        # depth camera (unregistered)
        if not self.registered:
            dinfo = infos[self.depth_camera_info_topic]
            if dinfo is None:
                raise self._fail(f"depth camera info topic {self.depth_camera_info_topic!r} has no messages")
            d_intr, d_dist = self._intrinsics(dinfo, self.depth_topic)
            self._depth_intr, self._depth_dist = d_intr, d_dist
            if depth_frame != color_frame and not self.tf.can_transform(color_frame, depth_frame):
                raise self._fail(f"unregistered depth: no TF chain between the depth frame {depth_frame!r} and "
                                 f"the colour frame {color_frame!r}")
            self._depth_frame, self._color_frame = depth_frame, color_frame

        self.native_intrinsics, self._maps = self._undistortion(opt)
        self._pairs = self._associate(reader, opt, colour_msgs, depth_msgs)

    def _intrinsics(self, info, topic: str) -> Tuple[Intrinsics, Tuple[float, ...]]:
        K = np.asarray(_field(info, "k"), dtype=np.float64).reshape(3, 3)
        P = np.asarray(_field(info, "p"), dtype=np.float64).reshape(3, 4)
        D = tuple(float(v) for v in _field(info, "d"))
        model = str(info.distortion_model or "plumb_bob")
        if "rect" in topic:
            if P[0, 0] > 0:
                K = P[:, :3]
            D = ()
        if any(D) and model not in ("plumb_bob", "rational_polynomial"):
            raise self._fail(f"camera info of {topic!r}: distortion model {model!r} is not supported "
                             f"(plumb_bob, rational_polynomial)")
        try:
            intr = Intrinsics.from_K(K, int(info.width), int(info.height))
        except ValueError as e:
            raise self._fail(f"camera info of {topic!r}: {e}") from None
        return intr, (D if any(D) else ())

    def _undistortion(self, opt: BagOptions):
        ri = self.raw_intrinsics
        if not (opt.undistort and self.distortion):
            return ri, None
        dist = np.asarray(self.distortion)
        new_k, _ = cv2.getOptimalNewCameraMatrix(ri.K, dist, (ri.width, ri.height), 0.0)
        ni = Intrinsics(float(new_k[0, 0]), float(new_k[1, 1]), float(new_k[0, 2]), float(new_k[1, 2]), ri.width, ri.height)
        maps = cv2.initUndistortRectifyMap(ri.K, dist, None, ni.K, (ni.width, ni.height), cv2.CV_32FC1)
        return ni, maps

    # ------------------------------------------------------------------ association
    def _associate(self, reader, opt: BagOptions, colour: List[_Img], depth: List[_Img]):
        if not colour:
            raise self._fail(f"colour topic {self.rgb_topic!r} has no messages")
        if not depth:
            raise self._fail(f"depth topic {self.depth_topic!r} has no messages")
        self.pose_topic, self.world_frame, pose_at = pose_sampler(reader, self.topics, self.tf, self.camera_frame,
                                                                  opt, self._fail)
        d_ts = np.array([d.stamp for d in depth])
        d_order = np.argsort(d_ts, kind="stable")
        idx, gap = associate_nearest(np.array([c.stamp for c in colour]), d_ts[d_order])
        pairs, problems = [], []
        for c, j, g in zip(colour, idx, gap):
            if g > opt.max_depth_dt:
                problems.append(f"t={c.stamp:.6f}: no depth within {opt.max_depth_dt:g} s (nearest {g:.3f} s)")
                continue
            T, prob = pose_at(c.stamp)
            if T is None:
                problems.append(f"t={c.stamp:.6f}: {prob}")
                continue
            try:
                T = check_rigid(T, what=f"pose at t={c.stamp:.6f}")
            except ValueError as e:
                problems.append(str(e))
                continue
            pairs.append((c, depth[int(d_order[j])], T))
        self.n_dropped = len(colour) - len(pairs)
        if not pairs:
            raise self._fail(f"no colour frame of {self.rgb_topic!r} has depth and a pose within tolerance "
                             f"(poses from {self.pose_topic!r}, world {self.world_frame!r}, camera "
                             f"{self.camera_frame!r}); first problems:\n    " + "\n    ".join(problems[:3]))
        if self.n_dropped:
            log.warning("%s: dropped %d of %d colour frames without depth/pose within tolerance (first: %s)",
                        self.path, self.n_dropped, len(colour), problems[0])
        return pairs

    # ------------------------------------------------------------------ frames
    @property
    def pose_source(self) -> str:
        """The old name of :attr:`pose_topic` (``"tf"`` or the pose topic the poses were read from); reading it warns
        (DeprecationWarning). ``pose_source`` names where poses come from across GaussLite
        (:data:`gausslite.odometry.rgbd.PoseSource`: ``given`` / ``odometry``); a bag's are ``given``."""
        warnings.warn("BagDataset.pose_source is renamed pose_topic (\"tf\" or the pose topic read)",
                      DeprecationWarning, stacklevel=2)
        return self.pose_topic

    def __len__(self) -> int:
        """Number of (selected) frames."""
        return len(self._pairs)

    def __repr__(self) -> str:
        i = self.intrinsics
        return f"BagDataset({str(self.path)!r}, frames={len(self)}, size={i.width}x{i.height})"

    def _message(self, topic: str, log_ns: int, index: int):
        with self._lock:
            r = self._reader or self._open()
            conns = [c for c in r.connections if c.topic == topic]
            for c, ts, raw in r.messages(connections=conns, start=log_ns, stop=log_ns + 1):
                return c.msgtype, r.deserialize(raw, c.msgtype)
        raise self._fail(f"message {index} of {topic!r} at log time {log_ns} ns vanished")

    def _image(self, topic: str, img: _Img, want: str) -> np.ndarray:
        ty, msg = self._message(topic, img.log_ns, img.index)
        try:
            kind, arr = self._decode(ty, msg)
        except ImageDecodeError as e:
            raise self._fail(f"{topic} message {img.index} (t={img.stamp:.6f}): {e}") from None
        if kind != want:
            raise self._fail(f"{topic} message {img.index}: {kind} image on the {want} topic")
        return arr

    def depth_camera_at(self, t: float) -> DepthCamera:
        """The unregistered depth camera with ``T_colour_depth`` from TF at ``t`` seconds.

        Raises:
            BagError: the bag's depth is registered, or TF has no transform within tolerance.
        """
        if self.registered:
            raise self._fail("the depth topic is registered to the colour camera")
        try:
            T = self.tf.lookup(self._color_frame, self._depth_frame, t, self.options.max_pose_dt)
        except TFError as e:
            raise self._fail(f"depth registration: {e}") from None
        return DepthCamera(self._depth_intr, T, self._depth_dist or (0.0,) * 5, splat=self.options.depth_splat)

    def _load(self, i: int) -> Frame:
        """Decode, register, undistort and downscale frame ``i``.

        Raises:
            BagError: undecodable image, or sizes that disagree with the CameraInfo.
        """
        c, d, T = self._pairs[i]
        rgb = self._image(self.rgb_topic, c, "color")
        depth = self._image(self.depth_topic, d, "depth")
        ri = self.raw_intrinsics
        if (rgb.shape[1], rgb.shape[0]) != (ri.width, ri.height):
            raise self._fail(f"{self.rgb_topic} message {c.index} is {rgb.shape[1]}x{rgb.shape[0]} but its CameraInfo "
                             f"says {ri.width}x{ri.height}")
        if self.registered:
            if depth.shape != rgb.shape[:2]:
                raise self._fail(f"{self.depth_topic} message {d.index} is {depth.shape[1]}x{depth.shape[0]}, colour "
                                 f"{rgb.shape[1]}x{rgb.shape[0]}; for unregistered depth give --depth-camera-info-topic")
        else:
            dc = self.depth_camera_at(c.stamp)
            if depth.shape != (dc.intrinsics.height, dc.intrinsics.width):
                raise self._fail(f"{self.depth_topic} message {d.index} is {depth.shape[1]}x{depth.shape[0]} but its "
                                 f"CameraInfo says {dc.intrinsics.width}x{dc.intrinsics.height}")
            depth = register_depth(depth, dc, ri, self.distortion or None)
        if self._maps is not None:
            mx, my = self._maps
            rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            depth = cv2.remap(depth, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if self.downscale != 1.0:
            rgb = downscale_rgb(rgb, self.downscale)
            depth = downscale_depth(depth, self.downscale)
        return Frame(frame_id=c.index, timestamp=c.stamp, rgb=rgb, depth=depth.astype(np.float32, copy=False),
                     c2w=T.copy(), intrinsics=self.intrinsics, name=f"frame{c.index:06d}")

    @property
    def depth_intrinsics(self) -> Optional[Intrinsics]:
        """Intrinsics of an unregistered depth topic (None when registered)."""
        return None if self.registered else self._depth_intr

