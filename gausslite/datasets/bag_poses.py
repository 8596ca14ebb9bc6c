"""Where a bag's camera poses come from, and their sampling at the colour stamps (module docstring of
:mod:`gausslite.datasets.bag`, "Poses"): a pose topic (``PoseStamped``, ``PoseWithCovarianceStamped``,
``TransformStamped``, ``Odometry``) interpolated and carried by TF into the world and camera frames, or TF itself
(:func:`pose_sampler`).
"""

from __future__ import annotations

from typing import Callable, Dict, Optional, Tuple

import numpy as np

from gausslite.ros.transforms import TFBuffer, TFError, interpolate_transform, make_transform, normalize_frame

__all__ = ["POSE_TYPES", "PoseSample", "header_stamp", "pose_matrix", "pose_sampler", "topic_pose_sampler",
           "world_frame_of"]

#: message types that carry a pose
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
)


def header_stamp(header) -> float:
    """A ROS message header's stamp in seconds (float)."""
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def pose_matrix(pose) -> np.ndarray:
    """A ``geometry_msgs/Pose`` as a (4, 4) float64 rigid transform."""
    p, q = pose.position, pose.orientation
    return make_transform((p.x, p.y, p.z), (q.x, q.y, q.z, q.w))


#: ``sample(t) -> (T_world_camera (4, 4) float64 or None, problem)``: a camera pose at ``t`` seconds
PoseSample = Callable[[float], Tuple[Optional[np.ndarray], str]]


def pose_sampler(reader, topics: Dict[str, Tuple[str, int]], tf: TFBuffer, camera_frame: str, opt,
                 fail: Callable[[str], Exception]) -> Tuple[str, str, PoseSample]:
    """Where a bag's camera poses come from, and a sampler of them (module docstring of :mod:`gausslite.datasets.bag`):
    the pose topic ``opt.pose_topic``; else TF when the camera frame moves in it; else the bag's only pose topic.

    Args:
        reader: the open ``rosbags`` reader. topics: topic → (message type, count). tf: the bag's TF tree.
        camera_frame: the colour camera's optical frame. opt: the :class:`~gausslite.datasets.bag.BagOptions`.
        fail: message → the exception to raise (a :class:`~gausslite.datasets.bag.BagError` listing the bag).
    Returns:
        ``(pose_topic, world_frame, sample)``: ``"tf"`` or the pose topic read, the world frame, and
        ``sample(t) -> (T_world_camera (4, 4) float64 or None, problem)`` at ``t`` seconds.
    Raises:
        what ``fail`` makes: no pose source, a pose topic of another type or without messages, a disconnected TF chain.
    """
    pose_topics = [t for t, (ty, _n) in topics.items() if ty in POSE_TYPES]
    topic = opt.pose_topic
    in_tf = camera_frame in tf.frames
    moving = in_tf and not all(tf.is_static(f) for f in tf.ancestors(camera_frame))
    if not topic and not moving and len(pose_topics) == 1:
        topic = pose_topics[0]  # TF holds at most the static mounting: the pose topic moves the camera
    if not topic and not in_tf:
        raise fail(
            f"no poses: the camera frame {camera_frame!r} is not in the TF tree and "
            + ("there is no PoseStamped/Odometry topic" if not pose_topics else
               f"there are several pose topics ({', '.join(pose_topics)}); choose one with --pose-topic")
            + " (see --camera-frame, --pose-topic)")
    if topic:
        return (topic, *topic_pose_sampler(reader, topics, tf, camera_frame, opt, topic, fail))
    world = world_frame_of(tf, camera_frame, opt)
    if not tf.can_transform(world, camera_frame):
        raise fail(f"TF chain {world!r} <- {camera_frame!r} does not connect: the camera frame is in "
                   f"the tree rooted at {tf.root(camera_frame)!r}, {world!r} in the tree rooted "
                   f"at {tf.root(world) if world in tf.frames else '(not in TF)'!r}")

    def at(t: float):
        try:
            return tf.lookup(world, camera_frame, t, opt.max_pose_dt), ""
        except TFError as e:
            return None, str(e)

    return "tf", world, at


def world_frame_of(tf: TFBuffer, camera_frame: str, opt) -> str:
    """The world frame of TF poses: ``opt.world_frame``, else REP 105's ``map``, else ``odom``, else the root of the
    camera's TF tree."""
    if opt.world_frame:
        return normalize_frame(opt.world_frame)
    for f in ("map", "odom"):
        if f in tf.frames:
            return f
    return tf.root(camera_frame)


def topic_pose_sampler(reader, topics: Dict[str, Tuple[str, int]], tf: TFBuffer, camera_frame: str, opt, topic: str,
                       fail: Callable[[str], Exception]) -> Tuple[str, PoseSample]:
    """Poses from the pose topic ``topic`` (arguments as :func:`pose_sampler`): every message read, then interpolated
    at the asked stamps (within ``opt.max_pose_dt``), carried into the world frame and onto the camera frame by TF
    when the message's frames differ from them. Returns ``(world_frame, sample)`` as :func:`pose_sampler`."""
    ty = topics.get(topic, ("", 0))[0]
    if topic not in topics:
        raise fail(f"pose topic {topic!r} is not in the bag")
    if ty not in POSE_TYPES:
        raise fail(f"pose topic {topic!r} has type {ty}, expected one of {list(POSE_TYPES)}")
    times, mats, frames, childs = [], [], set(), set()
    conns = [c for c in reader.connections if c.topic == topic]
    for c, _ts, raw in reader.messages(connections=conns):
        m = reader.deserialize(raw, c.msgtype)
        if ty.endswith("Odometry"):
            T, child = pose_matrix(m.pose.pose), m.child_frame_id
        elif ty.endswith("PoseWithCovarianceStamped"):
            T, child = pose_matrix(m.pose.pose), None
        elif ty.endswith("TransformStamped"):
            tr = m.transform
            T = make_transform((tr.translation.x, tr.translation.y, tr.translation.z),
                               (tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w))
            child = m.child_frame_id
        else:
            T, child = pose_matrix(m.pose), None
        times.append(header_stamp(m.header))
        mats.append(T)
        frames.add(normalize_frame(m.header.frame_id))
        childs.add(normalize_frame(child) if child else None)
    if not times:
        raise fail(f"pose topic {topic!r} has no messages")
    if len(frames) > 1 or len(childs) > 1:
        raise fail(f"pose topic {topic!r} changes frames during the recording ({sorted(map(str, frames | childs))})")
    msg_frame = frames.pop()
    child = childs.pop() or (normalize_frame(opt.pose_child_frame) if opt.pose_child_frame else camera_frame)
    world = normalize_frame(opt.world_frame) if opt.world_frame else msg_frame
    for a, b, what in ((world, msg_frame, "world frame"), (child, camera_frame, "camera frame")):
        if a != b and not tf.can_transform(a, b):
            raise fail(f"pose topic {topic!r}: no TF chain between {a!r} and {b!r} ({what}); "
                       f"the pose topic gives {child!r} in {msg_frame!r}")
    order = np.argsort(times, kind="stable")
    ts = np.asarray(times)[order]
    mats = [mats[i] for i in order]
    tol = opt.max_pose_dt

    def at(t: float):
        j = int(np.searchsorted(ts, t))
        near = [k for k in (j - 1, j) if 0 <= k < len(ts)]
        gap = min(abs(ts[k] - t) for k in near)
        if gap > tol:
            return None, (f"no {topic} pose within {tol:g} s of t={t:.6f} (nearest {gap:.3f} s away; poses from "
                          f"{ts[0]:.6f} to {ts[-1]:.6f})")
        if 0 < j < len(ts) and ts[j] > ts[j - 1]:
            T = interpolate_transform(mats[j - 1], mats[j], (t - ts[j - 1]) / (ts[j] - ts[j - 1]))
        else:
            T = mats[min(near, key=lambda k: abs(ts[k] - t))]
        try:
            if world != msg_frame:
                T = tf.lookup(world, msg_frame, t, tol) @ T
            if child != camera_frame:
                T = T @ tf.lookup(child, camera_frame, t, tol)
        except TFError as e:
            return None, str(e)
        return T, ""

    return world, at
