"""A mission's checkpoint and its resumption (``agent.checkpoint_every``; docs/live.md).

The mission's folder holds ``checkpoint.pt`` (the map with κ and active flags, the keyframe window, the counters,
the newest pushed version, the keyframe selector's reference, the odometry's state), written every
``checkpoint_every`` keyframes, and ``pushed_version.json``, the newest map version handed to the pusher, written
after each offer: a resumed mission never reuses a version the fusion server may hold. Both are written atomically
(a temporary file in the folder, then ``os.replace``).
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from gausslite.mission.progress import CHECKPOINT_COUNTERS, MissionProgress

log = logging.getLogger("gausslite.mission.runtime")  # one logger for the whole mission loop

__all__ = ["MissionCheckpoint", "CHECKPOINT_FILE", "VERSION_FILE", "atomic_write"]

CHECKPOINT_FILE = "checkpoint.pt"
VERSION_FILE = "pushed_version.json"
FORMAT = 1  #: ``format`` of the checkpoints written


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Write ``path`` through ``write(temporary path)`` in the same folder (created if missing), fsync, then
    ``os.replace`` (atomic on POSIX). Raises what ``write`` raises, or OSError."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    write(tmp)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


def _same_frame(saved, T_world_map: Optional[np.ndarray]) -> bool:
    """Whether a checkpoint's ``T_world_map`` (nested lists or None) is ``T_world_map`` (None: the identity)."""
    return bool(np.allclose(np.eye(4) if saved is None else np.asarray(saved),
                            np.eye(4) if T_world_map is None else T_world_map, atol=1e-9))


class MissionCheckpoint:
    """Saves and resumes one mission's parts in its folder (module docstring).

    Args:
        folder: the mission's checkpoint folder (created at the first write).
        agent_id, mission_id: the mission's identity (a checkpoint of another is refused).
        T_world_map: (4, 4) float64 map-to-world transform of the mission, or None (a checkpoint mapped in another
            world frame is refused).
        progress: the mission's :class:`~gausslite.mission.progress.MissionProgress` (counters).
        task: the mission's :class:`~gausslite.mission.task.MissionTask` (``text``, ``task_id``).
        mapper: the mission's mapper (``state_dict``, ``load_state_dict``, ``model``).
        selector: the keyframe selector (``state_dict``, ``load_state_dict``).
        odometry: the mission's RGB-D odometry, or None.
        pusher: the mission's :class:`~gausslite.mission.pusher.Pusher` (``version``, ``resume``).
    """

    def __init__(self, folder: Path, agent_id: str, mission_id: str, T_world_map: Optional[np.ndarray], *,
                 progress: MissionProgress, task, mapper, selector, odometry, pusher) -> None:
        self.folder = Path(folder)
        self.agent_id, self.mission_id, self.T_world_map = agent_id, mission_id, T_world_map
        self.progress, self.task, self.mapper = progress, task, mapper
        self.selector, self.odometry, self.pusher = selector, odometry, pusher

    @property
    def path(self) -> Path:
        """The checkpoint file."""
        return self.folder / CHECKPOINT_FILE

    def exists(self) -> bool:
        """Whether the folder holds a checkpoint."""
        return self.path.is_file()

    def save(self) -> Path:
        """Write the checkpoint atomically (call from the mapping thread, or while it is idle) and count it in
        ``progress.checkpoints``. Returns its path. Raises OSError on write failure."""
        # lazy: keeps gausslite.mission importable without torch
        import torch

        p = self.progress
        with p.lock:
            counters = {k: getattr(p, k) for k in CHECKPOINT_COUNTERS}
            sel = self.selector.state_dict()
            task_text, task_id = self.task.text, self.task.task_id
        version = self.pusher.version
        T = self.T_world_map
        state = {"format": FORMAT, "agent_id": self.agent_id, "mission_id": self.mission_id, "task_text": task_text,
                 "task_id": task_id, "version": version, "counters": counters, "selector": sel,
                 "mapper": self.mapper.state_dict(), "saved_unix": time.time(),
                 "T_world_map": None if T is None else T.tolist(),
                 "odometry": None if self.odometry is None else self.odometry.state_dict()}
        atomic_write(self.path, lambda tmp: torch.save(state, tmp))
        with p.lock:
            p.checkpoints += 1
        log.info("agent %s: checkpoint of mission %s after %d keyframes (v%d) in %s", self.agent_id,
                 self.mission_id, counters["frames_keyframed"], version, self.path)
        return self.path

    def record_version(self) -> None:
        """Persist the newest map version handed to the pusher (a resumed mission continues above it); a write
        failure is logged, not raised."""
        v = self.pusher.version
        try:
            atomic_write(self.folder / VERSION_FILE, lambda tmp: tmp.write_text(json.dumps({"version": v})))
        except OSError as e:
            log.warning("agent %s: cannot record the pushed version: %s", self.agent_id, e)

    def load(self) -> dict:
        """The checkpoint's state, checked to be this mission's.

        Raises:
            ValueError: unreadable; another agent or mission; started with another task; mapped in another world
                frame.
        """
        # lazy: keeps gausslite.mission importable without torch
        import torch

        path = self.path
        try:
            state = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e:
            raise ValueError(f"cannot read the checkpoint {path}: {type(e).__name__}: {e}") from None
        if state.get("agent_id") != self.agent_id or state.get("mission_id") != self.mission_id:
            raise ValueError(f"checkpoint {path} belongs to agent {state.get('agent_id')!r} mission "
                             f"{state.get('mission_id')!r}, not {self.agent_id!r} {self.mission_id!r}")
        if state.get("task_text") != self.task.text:
            raise ValueError(f"checkpoint {path}: mission {self.mission_id} was started with the task "
                             f"{state.get('task_text')!r}, not {self.task.text!r}")
        saved, T = state.get("T_world_map"), self.T_world_map
        if not _same_frame(saved, T):
            raise ValueError(f"checkpoint {path}: mission {self.mission_id} was mapped with T_world_map {saved}, not "
                             f"{None if T is None else T.tolist()}: its map lies in another world frame")
        return state

    def resume(self) -> int:
        """Load the checkpoint into the mission's parts: map, counters, keyframe selector, odometry; the pusher
        continues above the newest version recorded (the checkpoint's, or ``pushed_version.json``'s when higher).

        Returns:
            the keyframes resumed (also ``progress.resumed_keyframes``).
        Raises:
            ValueError: as :meth:`load`.
        """
        state = self.load()
        self.mapper.load_state_dict(state["mapper"])
        self.progress.restore(state["counters"])
        self.selector.load_state_dict(state["selector"])
        if self.odometry is not None and state.get("odometry"):  # agent.pose_source odometry: tracking resumes
            self.odometry.load_state_dict(state["odometry"])
        version = int(state["version"])
        vpath = self.folder / VERSION_FILE
        if vpath.is_file():  # pushes after the checkpoint: never reuse a version the fusion server holds
            version = max(version, int(json.loads(vpath.read_text()).get("version", 0)))
        self.pusher.resume(version)
        p, model = self.progress, self.mapper.model
        with p.lock:
            p.resumed_keyframes = p.frames_keyframed
            p.n_gaussians = len(model)
            p.n_active = int(model.active.sum())
            keyframes = p.frames_keyframed
        log.info("agent %s: mission %s resumed from %s: %d keyframes, %d Gaussians, next version v%d",
                 self.agent_id, self.mission_id, self.path, keyframes, p.n_gaussians, version + 1)
        return keyframes
