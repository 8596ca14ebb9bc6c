"""Rigid transforms, quaternions and a TF buffer (the ``/tf`` + ``/tf_static`` tree of ROS).

Conventions:

- Quaternions are Hamilton, scalar last ``(x, y, z, w)`` as in ``geometry_msgs/Quaternion``.
- ``T_a_b`` is a 4x4 float64 matrix mapping points in frame ``b`` to frame ``a`` (``p_a = T_a_b p_b``);
  it is the pose of ``b`` in ``a``. A ``geometry_msgs/TransformStamped`` with ``header.frame_id = a``
  and ``child_frame_id = b`` is ``T_a_b`` (tf2 convention, REP 105).
- Frame ids are compared without a leading ``/`` (ROS 1 recordings often have ``/map``).
- Times are float seconds.

Interpolation (as tf2 does): translation linearly, rotation by slerp, between the two samples of an
edge bracketing the query time. Unlike tf2, a query slightly outside the samples of an edge takes the
nearest sample when it is within ``tolerance`` seconds (tf2 raises ``ExtrapolationException``); a query
whose nearest sample of some edge is further than ``tolerance`` raises :class:`TFError`.
"""

from __future__ import annotations

import math
from typing import Dict, Iterable, List, Optional, Sequence, Tuple

import numpy as np

__all__ = [
    "TFError",
    "TFBuffer",
    "quat_to_rot",
    "rot_to_quat",
    "slerp",
    "make_transform",
    "transform_to_tq",
    "interpolate_transform",
    "invert",
    "normalize_frame",
    "R_BODY_OPTICAL",
]

#: Rotation ``R_body_optical`` of a camera optical frame (x right, y down, z forward) in a REP 103 body/link
#: frame (x forward, y left, z up): ``T_link_optical`` with this rotation and zero translation is what
#: ``static_transform_publisher 0 0 0 -1.5708 0 -1.5708 camera_link camera_optical_frame`` publishes.
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


class TFError(ValueError):
    """A transform cannot be looked up: unknown frame, disconnected tree, or no sample in tolerance."""


def normalize_frame(frame: str) -> str:
    """Frame id without leading/trailing whitespace and leading ``/`` (``"/map"`` → ``"map"``)."""
    return str(frame).strip().lstrip("/")


def quat_to_rot(q: Sequence[float]) -> np.ndarray:
    """(3, 3) float64 rotation of a Hamilton quaternion ``(x, y, z, w)`` (normalised first).

    Raises:
        ValueError: zero-length or non-finite quaternion.
    """
    q = np.asarray(q, dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not math.isfinite(n) or n < 1e-12:
        raise ValueError(f"invalid quaternion {q.tolist()}")
    x, y, z, w = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(x, y, z, w)`` with ``w >= 0`` of a (3, 3) rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, 0.25 * s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s, (R[2, 1] - R[1, 2]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s, (R[0, 2] - R[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s, (R[1, 0] - R[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (shortest arc), ``a`` in [0, 1]."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
    else:
        th = math.acos(min(1.0, d))
        q = (math.sin((1 - a) * th) * q0 + math.sin(a * th) * q1) / math.sin(th)
    return q / np.linalg.norm(q)


def make_transform(t: Sequence[float], q: Sequence[float]) -> np.ndarray:
    """(4, 4) float64 ``T`` from a translation (metres) and a quaternion ``(x, y, z, w)``."""
    T = np.eye(4)
    T[:3, :3] = quat_to_rot(q)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def transform_to_tq(T: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """``(translation (3,), quaternion (4,) xyzw)`` of a (4, 4) rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, 3].copy(), rot_to_quat(T[:3, :3])


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a (4, 4) rigid transform."""
    T = np.asarray(T, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def interpolate_transform(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    """Lerp translation + slerp rotation between two rigid transforms, ``a`` in [0, 1]."""
    t0, q0 = transform_to_tq(T0)
    t1, q1 = transform_to_tq(T1)
    return make_transform((1 - a) * t0 + a * t1, slerp(q0, q1, a))


class _Edge:
    """Transforms of one child frame relative to its parent: static, or time-stamped samples."""

    def __init__(self, parent: str, static: bool):
        self.parent = parent
        self.static = static
        self.times: List[float] = []
        self.mats: List[np.ndarray] = []
        self._sorted = True

    def add(self, t: float, T: np.ndarray) -> None:
        if self.static:  # latest static transform wins (as tf2's static buffer)
            self.times, self.mats = [t], [T]
            return
        if self.times and t < self.times[-1]:
            self._sorted = False
        self.times.append(t)
        self.mats.append(T)

    def at(self, t: float, tolerance: float) -> Tuple[Optional[np.ndarray], float]:
        """(transform at ``t`` or None, gap to the nearest sample in seconds)."""
        if self.static:
            return self.mats[0], 0.0
        if not self._sorted:
            order = np.argsort(self.times, kind="stable")
            self.times = [self.times[i] for i in order]
            self.mats = [self.mats[i] for i in order]
            self._sorted = True
        ts = self.times
        j = int(np.searchsorted(ts, t))
        gaps = [abs(ts[k] - t) for k in (j - 1, j) if 0 <= k < len(ts)]
        gap = min(gaps)
        if gap > tolerance:
            return None, gap
        if 0 < j < len(ts) and ts[j] > ts[j - 1]:
            a = (t - ts[j - 1]) / (ts[j] - ts[j - 1])
            return interpolate_transform(self.mats[j - 1], self.mats[j], a), gap
        k = j if j < len(ts) and abs(ts[j] - t) <= gap else j - 1
        return self.mats[k], gap


class TFBuffer:
    """A TF tree built from ``/tf`` and ``/tf_static`` messages, queried at arbitrary times.

    Each child frame has one parent (a tree, as tf2 requires). :meth:`lookup` composes the transforms
    along the path ``target → common ancestor ← source``; each dynamic edge is interpolated at the query
    time (see the module docstring), static edges are time-independent.
    """

    def __init__(self) -> None:
        self._edges: Dict[str, _Edge] = {}

    def add(self, parent: str, child: str, stamp: float, T: np.ndarray, static: bool = False) -> None:
        """Add ``T_parent_child`` at ``stamp`` seconds (``static``: from ``/tf_static``).

        Raises:
            TFError: the child already has a different parent, or is both static and dynamic.
        """
        p, c = normalize_frame(parent), normalize_frame(child)
        if not p or not c or p == c:
            raise TFError(f"invalid transform {parent!r} -> {child!r}")
        e = self._edges.get(c)
        if e is None:
            e = self._edges[c] = _Edge(p, static)
        elif e.parent != p:
            raise TFError(f"frame {c!r} has two parents: {e.parent!r} and {p!r} (TF must be a tree)")
        elif e.static != static:
            raise TFError(f"transform {p!r} -> {c!r} is published on both /tf and /tf_static")
        e.add(float(stamp), np.asarray(T, dtype=np.float64))

    @property
    def frames(self) -> List[str]:
        """Every frame id seen (parents and children), sorted."""
        s = set(self._edges)
        s.update(e.parent for e in self._edges.values())
        return sorted(s)

    def parent(self, frame: str) -> Optional[str]:
        """Parent of ``frame`` or None (a root or an unknown frame)."""
        e = self._edges.get(normalize_frame(frame))
        return e.parent if e else None

    def is_static(self, frame: str) -> bool:
        """True when the edge from ``frame`` to its parent is static (roots count as static)."""
        e = self._edges.get(normalize_frame(frame))
        return e is None or e.static

    def ancestors(self, frame: str) -> List[str]:
        """``[frame, parent, grandparent, ..., root]``.

        Raises:
            TFError: a cycle.
        """
        out = [normalize_frame(frame)]
        while out[-1] in self._edges:
            out.append(self._edges[out[-1]].parent)
            if len(out) > len(self._edges) + 1:
                raise TFError(f"TF cycle through {out[-1]!r}")
        return out

    def root(self, frame: str) -> str:
        """The root of the tree holding ``frame``."""
        return self.ancestors(frame)[-1]

    def describe(self) -> str:
        """One line per edge, ``parent -> child (static|N samples)``, for error messages."""
        if not self._edges:
            return "(no TF transforms)"
        return ", ".join(
            f"{e.parent} -> {c} ({'static' if e.static else f'{len(e.times)} samples'})"
            for c, e in sorted(self._edges.items())
        )

    def can_transform(self, target: str, source: str) -> bool:
        """True when both frames are in one tree (ignores time)."""
        known = set(self.frames)
        t, s = normalize_frame(target), normalize_frame(source)
        if t == s:
            return True
        return t in known and s in known and self.root(t) == self.root(s)

    def lookup(self, target: str, source: str, t: float, tolerance: float = 0.05) -> np.ndarray:
        """``T_target_source`` at time ``t`` (the pose of ``source`` in ``target``).

        Args:
            target, source: frame ids.
            t: seconds.
            tolerance: maximum gap (s) between ``t`` and the nearest sample of every dynamic edge on the path.

        Returns:
            (4, 4) float64.

        Raises:
            TFError: unknown frame, frames in different trees (names both roots), or an edge with no
                sample within ``tolerance`` (names the edge and the gap).
        """
        tgt, src = normalize_frame(target), normalize_frame(source)
        if tgt == src:
            return np.eye(4)
        known = set(self.frames)
        for f, what in ((tgt, "target"), (src, "source")):
            if f not in known:
                raise TFError(f"{what} frame {f!r} is not in the TF tree (frames: {', '.join(sorted(known)) or 'none'})")
        up_s, up_t = self.ancestors(src), self.ancestors(tgt)
        if up_s[-1] != up_t[-1]:
            raise TFError(
                f"TF chain {tgt!r} <- {src!r} does not connect: {src!r} is in the tree rooted at {up_s[-1]!r}, "
                f"{tgt!r} in the tree rooted at {up_t[-1]!r}"
            )
        common = next(f for f in up_s if f in set(up_t))
        T_common_src = self._chain(up_s[: up_s.index(common)], t, tolerance)
        T_common_tgt = self._chain(up_t[: up_t.index(common)], t, tolerance)
        return invert(T_common_tgt) @ T_common_src

    def _chain(self, frames: Iterable[str], t: float, tolerance: float) -> np.ndarray:
        """``T_ancestor_frames[0]`` composed upwards over ``frames`` (each with its parent edge)."""
        T = np.eye(4)
        for f in frames:
            e = self._edges[f]
            M, gap = e.at(t, tolerance)
            if M is None:
                raise TFError(
                    f"no transform {e.parent!r} -> {f!r} within {tolerance:g} s of t={t:.6f} "
                    f"(nearest sample {gap:.3f} s away; samples from {e.times[0]:.6f} to {e.times[-1]:.6f})"
                )
            T = M @ T
        return T

