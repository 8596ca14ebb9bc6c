"""Building a mission: :func:`build_mission` is the one way every caller (the agent service's ``StartMission``, the
benchmarks) turns its settings into an :class:`~gausslite.mission.runtime.AgentRuntime`, and :func:`replay_dataset`
opens a sequence for a replayed mission with its sensor profile (``docs/architecture.md#how-a-mission-is-built``).

What stays with each caller is its own: the service parses the gRPC request, checks what a caller may choose and
parses the task with the parser service; a benchmark builds its configuration and keeps its clocks. Nothing here
reads a YAML file (the typed :class:`~gausslite.mission.config.AgentConfig` comes from
:func:`gausslite.config.load_config`'s tree) or speaks gRPC.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable, Optional, Tuple

import numpy as np

from gausslite.mapping.config import MapperConfig
from gausslite.mission.config import AgentConfig, FrameConfig
from gausslite.mission.ports import FusionPort
from gausslite.mission.runtime import AgentRuntime

log = logging.getLogger(__name__)

__all__ = ["build_mission", "replay_dataset"]


def build_mission(config: AgentConfig, task_text: str, graph=None, *, agent_id: str = "agent", annotations=None,
                  task_id: Optional[str] = None, fusion: Optional[FusionPort] = None,
                  relevance_fn: Optional[Callable] = None, mission_id: Optional[str] = None,
                  on_finished: Optional[Callable[[AgentRuntime], None]] = None,
                  checkpoint_dir: Optional[str | Path] = None, T_world_map=None,
                  mapper: Optional[MapperConfig] = None, start: bool = True) -> AgentRuntime:
    """Build one agent's mission and, with ``start``, start it.

    The mission then takes its frames from a replay (``rt.replay(dataset)``, e.g. a dataset of
    :func:`replay_dataset`) or from a stream (``rt.submit(frame)``); poses come with the frames or from the RGB-D
    odometry (``config.pose_source``, a :data:`~gausslite.odometry.rgbd.PoseSource`).

    Args:
        config: the agent's settings (``load_config(...).agent``); not modified.
        task_text: the task, e.g. ``"pick up the cup"``.
        graph: its parsed task graph (``targets``, ``anchors``, ``relations``), or None to parse ``task_text`` with
            the in-process rule parser (:class:`gausslite.parser.TaskParser`).
        agent_id: the agent's id on the fusion server (non-empty).
        annotations: ``SceneAnnotations`` (``objects.json`` / ``tasks.json``) in the frame of the poses, or None.
        task_id: the task's id in ``tasks.json`` (ground-truth relevance, ROI scores), or None.
        fusion: the fusion side the mission pushes to (a :class:`~gausslite.mission.ports.FusionPort`), or None to
            map locally only.
        relevance_fn: an override ``frame -> (H, W) bool`` of the task's relevance, or None.
        mission_id: the mission's id (default: random); with ``checkpoint_dir`` holding a checkpoint of this id the
            mission resumes from it when it starts.
        on_finished: called with the runtime after the final push (e.g. to write its files).
        checkpoint_dir: folder of the mission's checkpoint, or None (no checkpoints).
        T_world_map: (4, 4) rigid transform (metres) of the robot's map frame in the team's world frame: overrides
            ``config.frame.T_world_map`` for this mission; None keeps the setting (docs/team.md).
        mapper: mapper settings replacing ``config.mapper`` for this mission (e.g. a sensor profile layered in),
            or None.
        start: start the mission (:meth:`AgentRuntime.start`: resume a checkpoint, start its threads); False
            returns it built, not started (it starts at its first ``submit`` / ``replay`` or an explicit ``start``).
    Returns:
        the :class:`~gausslite.mission.runtime.AgentRuntime`, started when ``start``.
    Raises:
        ValueError: an empty agent id, a relevance source the inputs cannot give (``relevance: gt`` without
            annotations or task id, ``relevance: attention`` without annotations or ``relevance_fn``), a task graph
            with no phrases, a ``T_world_map`` that is not a (4, 4) rigid transform, an unreadable checkpoint or one
            of another mission (at start).
        MissionError: the mission was closed before it started.
    """
    if graph is None:
        # lazy: the parser loads only for callers that do not parse the task themselves
        from gausslite.parser import TaskParser

        graph = TaskParser().parse(task_text)
    update = {}
    if T_world_map is not None:
        update["frame"] = FrameConfig(T_world_map=np.asarray(T_world_map, dtype=np.float64).tolist())
    if mapper is not None:
        update["mapper"] = mapper
    cfg = config.model_copy(update=update) if update else config
    make = AgentRuntime.launch if start else AgentRuntime
    return make(agent_id, task_text, graph, cfg, annotations=annotations, task_id=task_id, fusion=fusion,
                relevance_fn=relevance_fn, mission_id=mission_id, on_finished=on_finished,
                checkpoint_dir=checkpoint_dir)


def replay_dataset(path: str | Path, config: AgentConfig) -> Tuple[object, AgentConfig, object]:
    """Open the sequence at ``path`` for a replayed mission, as the agent replays it.

    Its layout picks a sensor profile (:func:`gausslite.mapping.profiles.profile_for_layout`): the profile's loader
    options (e.g. TUM: undistorted, interpolated poses) and its mapper defaults under whatever ``config.mapper`` sets
    explicitly (:func:`gausslite.mapping.profiles.with_profile`, as ``gausslite map`` layers them). ``config.downscale``,
    ``max_frames``, ``stride`` and ``bag`` apply; ``config.fps`` is the replay clock of Replica and 7-Scenes
    sequences (TUM and bags keep their timestamps).

    Args:
        path: a sequence folder or ROS bag (:func:`gausslite.datasets.load_dataset`).
        config: the agent's settings; not modified.
    Returns:
        ``(dataset, config, profile)``: the dataset (frames with their given poses, camera-to-world, metres;
        ``.annotations`` or None), ``config`` with the profile's mapper defaults, the
        :class:`~gausslite.mapping.profiles.SensorProfile`.
    Raises:
        FileNotFoundError: ``path`` or a file of the sequence is missing.
        ValueError: an unknown layout or invalid content (each loader's errors; a bag's ``BagError``), a profile
            value the mapper settings refuse.
    """
    # lazy: the loaders (OpenCV, the bag readers) load only for replayed missions
    from gausslite.datasets import load_dataset
    from gausslite.datasets.loader import detect_layout
    from gausslite.mapping.profiles import profile_for_layout, with_profile

    if not Path(path).exists():
        raise FileNotFoundError(f"dataset not found: {path}")
    layout = detect_layout(path)[0]
    profile = profile_for_layout(layout)
    kw = dict(profile.loader)
    cfg = config.model_copy(update={"mapper": with_profile(config.mapper, profile)})
    if cfg.fps is not None and layout in ("replica", "7scenes"):
        kw["fps"] = cfg.fps  # replay clock of datasets without timestamps (TUM keeps its own)
    dataset = load_dataset(path, downscale=cfg.downscale, max_frames=cfg.max_frames, stride=cfg.stride, bag=cfg.bag,
                           **kw)
    return dataset, cfg, profile
