"""The team's world frame: a robot's poses and scene annotations moved from its own map frame into the frame the
whole team maps in (docs/team.md).

The fusion server votes per voxel in the coordinates it receives and aligns nothing, so every robot of a team must
give its Gaussians, keyframes and task regions in one world frame. A robot whose SLAM runs in a map frame of its own
gets a fixed rigid transform ``T_world_map`` (``agent.frame.T_world_map``, or ``StartMissionRequest.T_world_map``
per mission): it maps points given in the robot's ``map`` frame into ``world`` (REP 103/105 naming), so a pose
``c2w`` in the map frame becomes ``T_world_map @ c2w`` and an annotated box centred at ``c`` with axes ``R`` becomes
one centred at ``T_world_map · c`` with axes ``R_world_map @ R``. :class:`~gausslite.mission.runtime.AgentRuntime`
applies it where poses enter a mission: every replayed and every streamed frame, and the scene annotations.
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np

from gausslite.camera import check_rigid
from gausslite.datasets.annotations import SceneAnnotations
from gausslite.datasets.base import Frame
from gausslite.mission.config import RIGID_ATOL, FrameConfig

__all__ = ["rigid_transform", "parse_T_world_map", "annotations_to_world", "frame_to_world", "WorldPendingFrame",
           "WorldFrames"]


def rigid_transform(translation: Sequence[float], rotation_xyzw: Sequence[float]) -> np.ndarray:
    """The 4 × 4 rigid transform of a translation and a unit quaternion, in the order ROS tools print them
    (``tf2_echo world map``: translation, then rotation x, y, z, w): what ``agent.frame.T_world_map`` takes.

    Args:
        translation: (3,) metres. rotation_xyzw: (4,) quaternion ``[x, y, z, w]`` (normalised here).
    Returns:
        (4, 4) float64 row-major matrix ``[[R, t], [0, 0, 0, 1]]``.
    Raises:
        ValueError: wrong lengths, non-finite numbers, or a zero quaternion.
    """
    t = np.asarray(translation, np.float64).reshape(-1)
    q = np.asarray(rotation_xyzw, np.float64).reshape(-1)
    if t.shape != (3,) or q.shape != (4,):
        raise ValueError(f"translation needs 3 numbers and rotation_xyzw 4, got {t.size} and {q.size}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
        raise ValueError("translation and rotation_xyzw must be finite")
    n = float(np.linalg.norm(q))
    if n < 1e-9:
        raise ValueError("rotation_xyzw is a zero quaternion")
    x, y, z, w = q / n
    T = np.eye(4)
    T[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    T[:3, 3] = t
    return T


def parse_T_world_map(values: Sequence[float], what: str = "T_world_map") -> Optional[np.ndarray]:
    """A transform given as 16 row-major numbers (``StartMissionRequest.T_world_map``), checked rigid.

    Args:
        values: 16 numbers (row-major 4 × 4), or none at all (not given).
        what: the name errors use.
    Returns:
        (4, 4) float64, or None for an empty ``values``.
    Raises:
        ValueError: not 16 numbers, non-finite, or not rigid (orthonormal rotation with det +1 and last row
            ``0 0 0 1``, tolerance 1e-3); the message names ``what``.
    """
    vals = [float(v) for v in values]
    if not vals:
        return None
    if len(vals) != 16:
        raise ValueError(f"{what} must have 16 numbers (row-major 4x4), got {len(vals)}")
    T = check_rigid(np.asarray(vals).reshape(4, 4), atol=RIGID_ATOL, what=what)  # the setting's check
    return FrameConfig(T_world_map=T.tolist()).matrix()


def annotations_to_world(annotations: Optional[SceneAnnotations], T_world_map: Optional[np.ndarray]
                         ) -> Optional[SceneAnnotations]:
    """Scene annotations given in a robot's map frame, expressed in the world frame: every box centre
    ``c → R c + t``, its axes ``rotation → R @ rotation``, the up axis ``→ R up``; sizes, margins and tasks unchanged.

    Args:
        annotations: ``SceneAnnotations`` in the map frame, or None.
        T_world_map: (4, 4) rigid transform map → world, or None (identity: ``annotations`` is returned).
    Returns:
        A new ``SceneAnnotations`` (same files recorded), or ``annotations`` itself when nothing changes.
    """
    if annotations is None or T_world_map is None:
        return annotations
    T = check_rigid(T_world_map, what="T_world_map")
    R, t = T[:3, :3], T[:3, 3]
    objects = [dataclasses.replace(o, center=R @ np.asarray(o.center, np.float64) + t,
                                   rotation=R @ np.asarray(o.rotation, np.float64)) for o in annotations.objects]
    return SceneAnnotations(objects, list(annotations.tasks), R @ annotations.up_axis,
                            objects_path=annotations.objects_path, tasks_path=annotations.tasks_path)


@dataclasses.dataclass
class WorldPendingFrame:
    """A not yet decoded frame (e.g. :class:`gausslite_services.agent.frames.PendingFrame`) posed in the world frame:
    ``c2w`` is ``T_world_map @ frame.c2w``, and :meth:`materialize` decodes the frame with that pose. Other attributes
    (``frame_id``, ``timestamp``, ``intrinsics``, ...) are the wrapped frame's."""

    frame: object
    T_world_map: np.ndarray
    c2w: np.ndarray = dataclasses.field(init=False)

    def __post_init__(self) -> None:
        self.c2w = self.T_world_map @ np.asarray(self.frame.c2w, np.float64)

    def __getattr__(self, name: str):
        if name == "frame":  # not set yet (copy / unpickle): no recursion
            raise AttributeError(name)
        return getattr(self.frame, name)

    def materialize(self) -> Frame:
        """The decoded frame at the world pose. Raises what the wrapped frame's ``materialize`` raises."""
        return dataclasses.replace(self.frame.materialize(), c2w=self.c2w.copy())


def frame_to_world(frame, T_world_map: Optional[np.ndarray]):
    """``frame`` with its pose in the world frame: ``c2w → T_world_map @ c2w``.

    Args:
        frame: a decoded :class:`~gausslite.datasets.base.Frame` (``c2w`` (4, 4) float64, camera-to-map), or a not
            yet decoded one (``c2w`` and ``materialize() -> Frame``).
        T_world_map: (4, 4) rigid transform map → world, or None (``frame`` is returned unchanged).
    Returns:
        A new ``Frame`` (images shared, not copied), or a :class:`WorldPendingFrame`.
    """
    if T_world_map is None:
        return frame
    if isinstance(frame, Frame):
        return dataclasses.replace(frame, c2w=T_world_map @ np.asarray(frame.c2w, np.float64))
    return WorldPendingFrame(frame, T_world_map)


class WorldFrames:
    """A read-only view of a replayed dataset in the world frame: each frame's pose ``T_world_map @ c2w`` on access,
    the dataset's ``annotations`` moved likewise (:func:`annotations_to_world`).

    Args:
        frames: a dataset or list (``len``, indexing; ``annotations`` optional). T_world_map: (4, 4) map → world.
    """

    def __init__(self, frames, T_world_map: np.ndarray) -> None:
        self._frames = frames
        self.T_world_map = check_rigid(T_world_map, what="T_world_map")
        self.annotations = annotations_to_world(getattr(frames, "annotations", None), self.T_world_map)
        self.intrinsics = getattr(frames, "intrinsics", None)

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, i: int) -> Frame:
        return frame_to_world(self._frames[i], self.T_world_map)

    def __getattr__(self, name: str):
        if name == "_frames":  # not set yet (copy / unpickle): no recursion
            raise AttributeError(name)
        return getattr(self._frames, name)  # the dataset's other attributes (path, ...)
