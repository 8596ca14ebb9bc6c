"""Where a mission's poses come from (``agent.pose_source``, a :data:`gausslite.odometry.rgbd.PoseSource`): the
poses each frame carries (``given``), or the RGB-D odometry tracking every frame as it arrives (``odometry``,
:class:`gausslite.odometry.rgbd.RGBDOdometry`), whose loop closures the map then follows
(:class:`gausslite.mission.pose_follow.MapFollower`). :class:`MissionPoses` is the mission's part that holds them.

Poses are camera-to-world, (4, 4) float64, metres, OpenCV camera axes.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Dict, Optional

import numpy as np

from gausslite.datasets.base import Frame
from gausslite.odometry.config import TrackResult
from gausslite.mission.config import AgentConfig
from gausslite.mission.errors import stops_the_mission
from gausslite.mission.pose_follow import MapFollower
from gausslite.mission.progress import MissionProgress

__all__ = ["MissionPoses", "odometry_for"]

log = logging.getLogger("gausslite.mission.runtime")  # one logger for the whole mission loop


def odometry_for(config: AgentConfig):
    """The RGB-D odometry of a mission with ``agent.pose_source: odometry`` (None otherwise); its world frame is the
    first frame's pose (the identity for a stream without poses)."""
    if config.pose_source != "odometry":
        return None
    # lazy: Open3D loads only for missions that track
    from gausslite.odometry.rgbd import RGBDOdometry

    # a live stream: loop closure on its own thread, so that a keyframe's loop registrations never delay tracking
    return RGBDOdometry(config.odometry, background_loops=True)


class MissionPoses:
    """The mission's poses: given with the frames, or tracked by the odometry (``agent.pose_source``).

    Args:
        config: the mission's ``AgentConfig`` (``pose_source``, ``odometry``).
        progress: the mission's :class:`~gausslite.mission.progress.MissionProgress` (a frame the odometry loses is
            counted as received and rejected there, with ``last_error``).

    Attributes:
        odometry: the :class:`~gausslite.odometry.rgbd.RGBDOdometry`, or None for given poses.
        follower: the :class:`~gausslite.mission.pose_follow.MapFollower` moving the map after the odometry's loop
            closures, or None.
        estimated_poses: frame id → (4, 4) float64 c2w the odometry estimated, in the world frame, for every frame
            tracked while :attr:`records` is set (a replay: the poses its map is scored at).
        records: keep :attr:`estimated_poses` (set by a replay before its first frame).
    """

    def __init__(self, config: AgentConfig, progress: MissionProgress) -> None:
        self.progress = progress
        self.odometry = odometry_for(config)
        self.follower = None if self.odometry is None else MapFollower(self.odometry)
        self.estimated_poses: Dict[int, np.ndarray] = {}
        self.records = False

    @property
    def tracks(self) -> bool:
        """The odometry gives the poses (``agent.pose_source: odometry``)."""
        return self.odometry is not None

    def track(self, frame, W: Optional[np.ndarray] = None) -> Optional[Frame]:
        """``frame`` decoded, with the odometry's pose, or None when its tracking failed: the frame is then logged in
        ``last_error``, counted as received and rejected, and not mapped. Call only when :attr:`tracks`.

        Args:
            frame: a :class:`~gausslite.datasets.base.Frame` or a not yet decoded one (``materialize() -> Frame``):
                the odometry needs every frame's images.
            W: (4, 4) the transform from the odometry's frame into the map's that the frame's pose takes next
                (None: the identity).
        Returns:
            the decoded frame with ``c2w`` the odometry's (4, 4) float64 estimate, or None.
        """
        if hasattr(frame, "materialize"):
            frame = frame.materialize()
        odometry = self.odometry
        if odometry.last_pose is None:  # the first frame's pose (identity without one) fixes the frame
            odometry.initial_pose = np.asarray(frame.c2w, dtype=np.float64).copy()
        try:
            r = odometry.track(frame)  # its own lock: a frame's tracking does not hold the mission's
        except Exception as e:
            if stops_the_mission(e):
                raise
            # one frame's failure, not the mission's: counted as lost (frames_failed too) and the next frame tracks
            log.warning("odometry: tracking frame %d raised %s: %s; the frame is lost, the mission goes on",
                        frame.frame_id, type(e).__name__, e, exc_info=e)
            self.progress.frame_failed(f"tracking frame {frame.frame_id} failed: {type(e).__name__}: {e}")
            r = TrackResult(np.eye(4), False, f"{type(e).__name__}: {e}")
        if r.ok:
            self.follower.record(frame.frame_id, r, W)
            if self.records:
                self.estimated_poses[int(frame.frame_id)] = np.asarray(r.c2w, dtype=np.float64).copy()
            return dataclasses.replace(frame, c2w=r.c2w)
        p = self.progress
        with p.lock:
            p.frames_received += 1
            p.frames_rejected += 1
            p.last_error = f"odometry lost frame {frame.frame_id}: {r.reason}"
        return None

    def follow(self, mapper) -> None:
        """Move ``mapper``'s frames by the loop closures found since the last call (no-op for given poses)."""
        if self.follower is not None:
            self.follower.apply(mapper)

    def status(self) -> dict:
        """``frames_lost``, ``frames_relocalised`` and ``loop_closures`` of the odometry, and
        ``corrections_rejected``: mapped frames whose loop-closure correction could not be applied (logged and
        skipped, :attr:`MapFollower.n_rejected <gausslite.mission.pose_follow.MapFollower.n_rejected>`); zeros
        without an odometry."""
        if self.odometry is None:
            return {"frames_lost": 0, "frames_relocalised": 0, "loop_closures": 0, "corrections_rejected": 0}
        s = self.odometry.summary()
        return {"frames_lost": s["failed"], "frames_relocalised": s["relocalised"], "loop_closures": s["loops"],
                "corrections_rejected": self.follower.n_rejected}

    def close(self) -> None:
        """Stop the odometry's loop-closing thread. Safe to call more than once."""
        if self.odometry is not None:
            self.odometry.close()
