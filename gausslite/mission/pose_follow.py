"""The map follows the odometry's pose graph: when a loop closure corrects keyframe poses, the mapped frames anchored
to them move, and with them the Gaussians those frames seeded (:meth:`gausslite.mapping.mapper.Mapper.apply_pose_corrections`).

Each frame the odometry tracks holds its pose relative to an anchor keyframe of the odometry
(:attr:`gausslite.odometry.rgbd.TrackResult.anchor`, ``T_anchor``). When the pose graph moves the anchor
(:attr:`gausslite.odometry.rgbd.RGBDOdometry.on_correction`, called from its loop-closing thread), this module only
notes it; the mapping worker then, between two keyframes (:meth:`MapFollower.apply`), moves every mapped frame by the
correction of its anchor, applied on the left in the world frame: a frame mapped at ``P`` (its sensor pose, before the
map's own pose refinement) whose new sensor pose is ``P'`` moves by ``W P' P⁻¹ W⁻¹``, with ``W`` the transform from
the odometry's frame into the map's (``agent.frame.T_world_map`` for a streamed mission; the identity for a replay,
whose poses are moved first). The map's own refinement of the frame's pose rides along.

Poses are camera-to-world, (4, 4) float64, metres, OpenCV camera axes.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from typing import Dict, Optional, Tuple

import numpy as np

from gausslite.camera import nearest_rigid

log = logging.getLogger(__name__)

__all__ = ["MapFollower"]

#: tracked frames held until the mapper maps or skips them (most are never mapped): a minute at 30 Hz
MAX_UNMAPPED = 1800


class MapFollower:
    """Keeps each tracked frame's anchor and moves the map's frames when the odometry corrects their anchors.

    Args:
        odometry: the mission's :class:`~gausslite.odometry.rgbd.RGBDOdometry` (its ``graph`` holds the anchors'
            current poses); its ``on_correction`` is set to :meth:`on_correction`.

    Attributes:
        n_corrections: corrections applied to the map; n_moved: Gaussians moved in all; n_rejected: mapped frames'
            corrections that could not be applied (not a rigid transform: logged and skipped, the frame stays where it
            was mapped).
    """

    def __init__(self, odometry) -> None:
        self.odometry = odometry
        odometry.on_correction = self.on_correction
        self._lock = threading.Lock()
        #: mapped frames: frame id → (anchor keyframe id, T_anchor (4, 4), sensor pose it is mapped at (4, 4), W (4, 4))
        self._frames: Dict[int, Tuple[int, np.ndarray, np.ndarray, np.ndarray]] = {}
        #: the same for tracked frames not mapped yet (bounded: the oldest go first)
        self._unmapped: "OrderedDict[int, Tuple[int, np.ndarray, np.ndarray, np.ndarray]]" = OrderedDict()
        self._pending = False
        self.n_corrections = 0
        self.n_moved = 0
        self.n_rejected = 0

    def record(self, frame_id: int, result, W: Optional[np.ndarray] = None) -> None:
        """Note a tracked frame (tracking thread): ``result`` its :class:`~gausslite.odometry.rgbd.TrackResult`,
        ``W`` (4, 4) the transform from the odometry's frame into the map's (None: the identity)."""
        if result.anchor < 0 or result.T_anchor is None:
            return
        with self._lock:
            self._unmapped[int(frame_id)] = (int(result.anchor), np.asarray(result.T_anchor, np.float64).copy(),
                                             np.asarray(result.c2w, np.float64).copy(),
                                             np.eye(4) if W is None else np.asarray(W, np.float64).copy())
            while len(self._unmapped) > MAX_UNMAPPED:
                self._unmapped.popitem(last=False)

    def mapped(self, frame_id: int) -> None:
        """Note that the mapper mapped ``frame_id`` (mapping worker): only mapped frames follow corrections."""
        with self._lock:
            rec = self._unmapped.pop(int(frame_id), None)
            if rec is not None:
                self._frames[int(frame_id)] = rec

    def on_correction(self, new_poses: Dict[int, np.ndarray]) -> None:
        """The odometry's callback after its pose graph moved keyframes (its tracking or loop-closing thread): the map
        is moved at the next :meth:`apply`."""
        with self._lock:
            self._pending = True

    def apply(self, mapper) -> int:
        """Move the mapper's frames whose anchors the pose graph corrected since the last call (mapping worker,
        between keyframes). Returns the Gaussians moved (0 when nothing was pending)."""
        with self._lock:
            if not self._pending:
                return 0
            self._pending = False
            frames = dict(self._frames)
        nodes = self.odometry.graph.nodes
        current = mapper.keyframe_poses()
        new: Dict[int, np.ndarray] = {}
        updated = {}
        rejected = 0
        for fid, (anchor, T, sensor, W) in frames.items():
            if fid not in current or anchor not in nodes:
                continue
            try:  # every product projected back onto SE(3): a correction applied a thousand times stays rigid
                moved = nearest_rigid(nodes[anchor].c2w @ T, f"frame {fid}'s corrected sensor pose")
                delta = nearest_rigid(W @ moved @ np.linalg.inv(sensor) @ np.linalg.inv(W), f"frame {fid}'s correction")
                if np.allclose(delta, np.eye(4), rtol=0.0, atol=1e-12):
                    continue
                new[fid] = nearest_rigid(delta @ current[fid], f"frame {fid}'s corrected pose")
            except (ValueError, np.linalg.LinAlgError) as e:  # a bug, not rounding: this frame stays, the map maps on
                rejected += 1
                log.warning("a loop closure's correction of mapped frame %d was rejected and skipped: %s", fid, e)
                continue
            updated[fid] = (anchor, T, moved, W)
        n = mapper.apply_pose_corrections(new) if new else 0
        with self._lock:
            self.n_rejected += rejected
            if not new:
                return 0
            self._frames.update(updated)
            self.n_corrections += 1
            self.n_moved += n
        log.info("the map followed a loop closure: %d mapped frames and %d Gaussians moved", len(new), n)
        return n
