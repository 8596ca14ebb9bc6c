"""The agent's mission: frames → attention → mapper → periodic ROI-subset pushes (paper Sec. III-B to III-E;
``docs/live.md``, ``docs/sharing.md``).

:class:`AgentRuntime` is usable without gRPC: it needs a task graph (any object with ``targets``,
``anchors``, ``relations``), scene annotations for the offline relevance sources, and optionally a
*fusion client*: a :class:`gausslite.mission.ports.FusionPort` (``open_session``, ``upload_chunks``,
``upload_keyframes``; the gRPC ``gausslite_services.fusion_server.client.FusionClient`` is one), or None to map locally
only. The fusion client signals a rejected delta base with :class:`gausslite.mission.errors.PreconditionFailed`.

The runtime coordinates its parts, one job each:

* frames in — :class:`~gausslite.mission.ingest.Ingest` (pose into the world frame, image size, keyframe selection
  or the every-frame queue), :class:`~gausslite.mission.tracking.MissionPoses` (given poses or the RGB-D odometry),
  :class:`~gausslite.mission.replay.Replay` (a dataset fed from a thread, at its clock under ``realtime``);
* mapping worker — :class:`~gausslite.mission.worker.MappingWorker`, the thread that maps keyframes, optimises
  between them (live ingest), hands snapshots to the pusher and writes checkpoints;
* the task — :class:`~gausslite.mission.task.MissionTask` (relevance source, task swaps);
* pushes — :class:`~gausslite.mission.pusher.Pusher` (the thread that sends the newest snapshot with retries and
  backoff, so a fusion-server outage never stalls mapping), :class:`~gausslite.mission.share.ShareSession` (what is
  shared), :class:`~gausslite.mission.uploads.KeyframeUploads` (keyframes and views at one image size);
* :class:`~gausslite.mission.checkpoint.MissionCheckpoint` (checkpoint and resume),
  :class:`~gausslite.mission.finish.MissionFinish` (Finish: the last mapping and push, the scores of
  :mod:`gausslite.mission.scoring` and the summary), :class:`~gausslite.mission.lifecycle.MissionLifecycle` (its
  threads started and stopped once each), :class:`~gausslite.mission.progress.MissionProgress` (state and counters
  under the mission's lock). The settings are in :mod:`gausslite.mission.config`.
"""

from __future__ import annotations

import threading
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from gausslite.datasets.base import Frame
from gausslite.mission.checkpoint import MissionCheckpoint
from gausslite.mission.config import AgentConfig
from gausslite.mission.errors import MissionError
from gausslite.mission.finish import MissionFinish
from gausslite.mission.ingest import Ingest
from gausslite.mission.lifecycle import MissionLifecycle
from gausslite.mission.ports import FusionPort
from gausslite.mission.progress import MissionProgress
from gausslite.mission.pusher import Pusher
from gausslite.mission.scoring import MissionSummaryData
from gausslite.mission.share import ShareSession
from gausslite.mission.state import ACCEPTS_TASK
from gausslite.mission.task import MissionTask
from gausslite.mission.team_frame import annotations_to_world
from gausslite.mission.tracking import MissionPoses
from gausslite.mission.uploads import KeyframeUploads
from gausslite.mission.worker import MappingWorker

__all__ = ["AgentRuntime", "MissionSummaryData"]


class _PartField:
    """A runtime attribute kept by one of its parts: ``frames_mapped = _PartField("progress", "frames_mapped")``."""

    def __init__(self, part: str, name: str) -> None:
        self.part, self.name = part, name
        self.__doc__ = f"``{part}.{name}``"

    def __get__(self, owner: Any, cls: Any = None) -> Any:
        return self if owner is None else getattr(getattr(owner, self.part), self.name)

    def __set__(self, owner: Any, value: Any) -> None:
        setattr(getattr(owner, self.part), self.name, value)


def mapping_parts(config: AgentConfig) -> tuple:
    """A mission's ``(mapper, resolution governor, maps_detail)``: the :class:`~gausslite.mapping.mapper.Mapper`
    (torch seeded by ``mapper.seed``); the governor of the mapping resolutions (``agent.resolution``: the background's
    chosen at the first frame, and with the detail layer the task region's own, each corrected both ways from the
    iterations keyframes get; docs/live.md#mapping-resolution); whether the mapper maps the task region at its own
    level (``mapper.detail`` in a mode with a task region)."""
    # lazy: keeps gausslite.mission.runtime importable without torch
    import torch

    # lazy: keeps gausslite.mission.runtime importable without SciPy, Warp, torch
    from gausslite.mapping.mapper import Mapper

    # lazy: keeps gausslite.mission.runtime importable without OpenCV
    from gausslite.mapping.resolution import uses_detail

    torch.manual_seed(config.mapper.seed)
    return Mapper(config.mapper), config.resolution.governor(config.mapper), uses_detail(config.mapper)


class AgentRuntime:
    """One mission of one agent: task-conditioned mapping of a frame stream plus fusion pushes.

    Building one checks the arguments and assembles the parts; it reads no checkpoint and starts no thread.
    :meth:`start` does (or :meth:`launch`, which builds and starts); :meth:`submit`, :meth:`replay`, :meth:`finish`
    and :meth:`save_checkpoint` start a mission not started yet.

    Args:
        agent_id (str): the agent's id on the fusion server (non-empty).
        task_text (str): the task.
        graph: parsed task graph (``targets``, ``anchors``, ``relations``).
        config (AgentConfig): settings (``frame``: the robot's map frame in the team's world frame, docs/team.md).
        annotations: ``SceneAnnotations`` (``objects.json``/``tasks.json``) in the frame of the poses, for both
            relevance sources and the summary's ROI PSNR; None only works with a custom ``relevance_fn``.
        task_id (str | None): the task's id in ``tasks.json`` (GT relevance, evaluation).
        fusion: a FusionClient-like object, or None (no pushes).
        relevance_fn: optional override ``frame -> (H, W) bool``.
        mission_id (str | None): id (default: random).
        on_finished: optional callback ``(runtime) -> None`` after the final push (e.g. save files).
        checkpoint_dir (str | Path | None): folder of this mission's checkpoint (``checkpoint.pt``, written
            every ``checkpoint_every`` keyframes); when it already holds one, :meth:`start` resumes the mission
            from it (map, keyframes, counters, pushed version), which keeps pushing newer versions.

    Raises:
        ValueError: empty agent id; ``relevance: gt`` without annotations/task id; ``relevance: attention`` without
            annotations (or ``relevance_fn``); a graph with no phrases.
    """

    # the parts' fields under the runtime's names
    state = _PartField("progress", "state")
    last_error = _PartField("progress", "last_error")
    frames_received = _PartField("progress", "frames_received")
    frames_mapped = _PartField("progress", "frames_mapped")
    frames_keyframed = _PartField("progress", "frames_keyframed")
    frames_skipped = _PartField("progress", "frames_skipped")
    frames_rejected = _PartField("progress", "frames_rejected")
    seconds_mapping = _PartField("progress", "seconds_mapping")
    idle_iterations = _PartField("progress", "idle_iterations")
    keyframe_iterations = _PartField("progress", "keyframe_iterations")
    checkpoints = _PartField("progress", "checkpoints")
    resumed_keyframes = _PartField("progress", "resumed_keyframes")
    n_gaussians = _PartField("progress", "n_gaussians")
    n_active = _PartField("progress", "n_active")
    task_text = _PartField("task", "text")
    graph = _PartField("task", "graph")
    task_id = _PartField("task", "task_id")
    frontend = _PartField("task", "frontend")  # the attention front-end (relevance: attention), or None
    _relevance_fn = _PartField("task", "relevance_fn")
    intrinsics = _PartField("ingest", "intrinsics")
    selector = _PartField("ingest", "selector")
    odometry = _PartField("poses", "odometry")  # agent.pose_source odometry: every frame is tracked in submit
    follower = _PartField("poses", "follower")  # the map follows the odometry's loop closures
    #: replays under ``agent.pose_source: odometry``: frame id → (4, 4) float64 world c2w the odometry estimated for
    #: every frame, the withheld ones too: the poses the mission is scored at
    estimated_poses = _PartField("poses", "estimated_poses")
    summary = _PartField("finishing", "summary")  # Finish's MissionSummaryData (None before)
    #: frame id → TrackedView of the tracked / novel-tracked frames, and of the novel ones (predicted), last scored
    tracked_views = _PartField("finishing", "tracked_views")
    predicted_views = _PartField("finishing", "predicted_views")
    replaying = _PartField("lifecycle", "replaying")  # a replay thread is feeding frames
    replay_frames = _PartField("lifecycle", "replay_frames")  # frames of the replayed dataset (0: no replay)
    _replay_thread = _PartField("lifecycle", "replay_thread")
    upload_intrinsics = _PartField("uploads", "intrinsics")  # of the keyframes sent to the fusion server

    def __init__(self, agent_id: str, task_text: str, graph, config: AgentConfig, *, annotations=None,
                 task_id: Optional[str] = None, fusion: Optional[FusionPort] = None, relevance_fn: Optional[Callable] = None,
                 mission_id: Optional[str] = None,
                 on_finished: Optional[Callable[["AgentRuntime"], None]] = None,
                 checkpoint_dir: Optional[str | Path] = None) -> None:
        if not agent_id:
            raise ValueError("agent_id must be non-empty")
        self.agent_id, self.config, self.fusion, self.on_finished = agent_id, config, fusion, on_finished
        self.mission_id = mid = mission_id or uuid.uuid4().hex[:12]
        #: (4, 4) float64 rigid transform from the robot's map frame into the team's world frame (``config.frame``;
        #: docs/team.md), or None when they are the same: every pose and annotation box enters the mission through it
        self.T_world_map: Optional[np.ndarray] = config.frame.matrix()
        self.annotations = annotations_to_world(annotations, self.T_world_map)
        self.progress = MissionProgress()
        self.task = MissionTask(agent_id, mid, config, task_text, graph, task_id, self.annotations, relevance_fn,
                                lambda: self.mapper, self.progress)
        self.mapper, self.resolution, self.maps_detail = mapping_parts(config)
        self.lifecycle, self.finishing = MissionLifecycle(self), MissionFinish(self)  # threads; Finish
        self.poses = MissionPoses(config, self.progress)
        self.ingest = Ingest(agent_id, mid, config, self.progress, self.poses, self.T_world_map)
        self.uploads = KeyframeUploads(config, self.resolution, lambda: self.ingest.intrinsics)
        self.share = ShareSession(agent_id, config)  # selection, fine-tune cache, delta planning
        #: the pushes: versions, backlog, retries, keyframe uploads (gausslite.mission.pusher)
        self.pusher = Pusher(agent_id, task_text, config, fusion, self.share, self.mapper,
                             lambda: self.uploads.intrinsics, self.progress.set_error)
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir else None
        self.checkpoint = None if self.checkpoint_dir is None else MissionCheckpoint(
            self.checkpoint_dir, agent_id, mid, self.T_world_map, progress=self.progress, task=self.task,
            mapper=self.mapper, selector=self.ingest.selector, odometry=self.poses.odometry, pusher=self.pusher)
        self.worker = MappingWorker(
            agent_id, mid, config, progress=self.progress, ingest=self.ingest, poses=self.poses, task=self.task,
            mapper=self.mapper, resolution=self.resolution, maps_detail=self.maps_detail, uploads=self.uploads,
            pusher=self.pusher, share=self.share, checkpoint=self.checkpoint, fail=self.lifecycle.fail)

    @classmethod
    def launch(cls, *args, **kwargs) -> "AgentRuntime":
        """Build a runtime (the arguments of :class:`AgentRuntime`) and :meth:`start` it; one whose start fails is
        closed. Raises what either raises."""
        rt = cls(*args, **kwargs)
        try:
            return rt.start()
        except BaseException:
            rt.close()
            raise

    def start(self) -> "AgentRuntime":
        """Start the mission once: resume ``checkpoint_dir``'s checkpoint when it holds one, then start the mapping
        thread, the pusher and the relevance thread (:meth:`MissionLifecycle.start
        <gausslite.mission.lifecycle.MissionLifecycle.start>`, which raises ValueError for a checkpoint it cannot
        resume and MissionError for a closed mission). Returns self."""
        self.lifecycle.start()
        return self

    # ------------------------------------------------------------------ input
    def submit(self, frame: Frame, timeout: Optional[float] = None, _replay: bool = False,
               arrival: Optional[float] = None) -> bool:
        """Hand one frame to the mission: keyframe ingest (``ingest: keyframes``, realtime replays) never blocks,
        every-frame ingest blocks while the queue is full (:mod:`gausslite.mission.ingest`). The frame's pose is
        given in the robot's map frame and enters the mission as ``T_world_map @ c2w`` (docs/team.md).

        Args:
            frame, timeout: as :meth:`Ingest.accept <gausslite.mission.ingest.Ingest.accept>` (e.g. a
                :class:`gausslite_services.agent.frames.PendingFrame`, decoded when mapped).
            arrival: ``time.perf_counter()`` when the frame arrived (before decoding; default: now): the accept and
                keyframe latencies are measured from it.
        Returns:
            True when the frame was queued or became the pending keyframe candidate, False when skipped (or lost
            by the odometry).
        Raises:
            what :meth:`Ingest.accept <gausslite.mission.ingest.Ingest.accept>` raises (MissionError,
            FrameSizeMismatch, queue.Full); ValueError: a mission started by this frame could not resume its checkpoint.
        """
        t_arr = time.perf_counter() if arrival is None else arrival
        self.lifecycle.ensure_started()
        frame = self.ingest.posed(frame, replayed=_replay)
        if frame is None:
            return False
        if not self.lifecycle.share_started and not _replay:
            self.lifecycle.start_share(self.ingest.online)  # a streamed mission starts with its first frame
        return self.ingest.accept(frame, t_arr, streamed=not _replay, timeout=timeout)

    def replay(self, dataset, progress: Optional[Callable[[int, int], None]] = None) -> threading.Thread:
        """Feed every frame of ``dataset`` from a background thread (:class:`~gausslite.mission.replay.Replay`);
        the state becomes ``REPLAY_DONE`` once all its frames are mapped. Streaming (``submit`` from outside) is
        refused meanwhile. With ``config.realtime`` the frames are sent at the dataset's clock through keyframe
        ingest, otherwise every frame is mapped. The final map is scored over every frame of the dataset at Finish
        (``roi_psnr_all_frames``). ``progress(sent, total)`` is called after each frame sent. Returns the thread."""
        self.lifecycle.ensure_started()
        return self.lifecycle.replay(dataset, progress)

    # ------------------------------------------------------------------ task
    def relevance(self, frame: Frame) -> np.ndarray:
        """The mission's relevance map w of ``frame`` for its current task: (H, W) bool (paper Sec. III-B), from the
        relevance worker when there is one (``relevance_max_wait_s``), otherwise computed here."""
        return self.task.relevance(frame)

    def update_task(self, task_text: str, graph, task_id: Optional[str] = None) -> None:
        """Give the running mission a new task; the map re-targets to it and keeps what it has mapped. Its relevance
        source is built now (a task the scene cannot answer fails here, nothing changed); the mapping thread applies
        it before its next keyframe or idle iteration (:meth:`apply_pending_task`; docs/live.md#changing-the-task).

        Args: as :meth:`MissionTask.request <gausslite.mission.task.MissionTask.request>` (``task_id``: its id in the
        scene's ``tasks.json``, or None: looked up by text).
        Raises:
            MissionError: the mission is finishing, finished or failed. ValueError: a relevance source that cannot be
                built for the task (as at :class:`AgentRuntime`), or an unknown task id.
        """
        with self.progress.lock:
            if self.progress.state not in ACCEPTS_TASK:
                raise MissionError(f"mission {self.mission_id} is {self.progress.state}: it cannot take a new task")
        self.task.request(task_text, graph, task_id)

    def apply_pending_task(self) -> bool:
        """Switch to the task :meth:`update_task` left, if any (:meth:`MissionTask.apply_pending
        <gausslite.mission.task.MissionTask.apply_pending>`); the mapping thread calls it between keyframes, and so
        does a caller that drives ``self.mapper`` itself. Returns True when a new task was applied."""
        return self.task.apply_pending(self.mapper, self.pusher)

    # ------------------------------------------------------------------ pushes, checkpoint
    def save_checkpoint(self) -> Path:
        """Write ``checkpoint.pt`` atomically into ``checkpoint_dir`` (:meth:`MissionCheckpoint.save
        <gausslite.mission.checkpoint.MissionCheckpoint.save>`). Call from the worker thread or while it is idle.
        Returns the path. Raises OSError on write failure, ValueError without a folder."""
        if self.checkpoint is None:
            raise ValueError("no checkpoint_dir configured")
        self.lifecycle.ensure_started()  # a checkpoint to resume is resumed before it is overwritten
        return self.checkpoint.save()

    def acknowledged_subset(self):
        """The subset the fusion server acknowledged last, as the server holds it (decoded wire values):
        ``(version, GaussianArrays, ids)``, or None before the first acknowledged push."""
        return self.share.acknowledged()

    # ------------------------------------------------------------------ status / finish
    def status(self) -> dict:
        """Snapshot of the mission's progress (keys of the ``MissionStatus`` message)."""
        pushes = self.pusher.status()
        p = self.progress
        with p.lock:
            return {
                "mission_id": self.mission_id, "agent_id": self.agent_id, "state": p.state,
                "task_text": self.task.text, "task_id": self.task.task_id or "",
                "frames_received": p.frames_received, "frames_mapped": p.frames_mapped,
                "frames_queued": self.ingest.queue.qsize(), "n_gaussians": p.n_gaussians, "n_active": p.n_active,
                **pushes, "last_error": p.last_error, **p.counter_status(), **self.resolution.status(),
                **self.poses.status(),
            }

    def wait_mapped(self, timeout_s: Optional[float] = None) -> bool:
        """Wait until every queued frame is mapped and no replay feeds frames, or the mission failed (True), or
        ``timeout_s`` passes (False)."""
        return self.ingest.wait_mapped(timeout_s, busy=lambda: self.replaying)

    def finish(self, push: bool = True, evaluate: bool = True, timeout_s: Optional[float] = None) -> MissionSummaryData:
        """Stop accepting frames, map what is queued, do the final push (``push``), evaluate (``evaluate``); idempotent
        (:meth:`MissionFinish.finish <gausslite.mission.finish.MissionFinish.finish>`). Returns the summary; raises
        TimeoutError when Finish, mapping or the final push did not complete within ``timeout_s`` seconds."""
        self.lifecycle.ensure_started()
        return self.finishing.finish(push, evaluate, timeout_s)

    def evaluate(self) -> tuple[Optional[float], Optional[float]]:
        """(full-image PSNR, ROI PSNR) in dB of the current map over the kept mapped frames
        (:meth:`MissionFinish.evaluate <gausslite.mission.finish.MissionFinish.evaluate>`)."""
        return self.finishing.evaluate()

    def evaluate_all_frames(self) -> Optional[float]:
        """ROI PSNR (dB) of the current map over **every** frame of the replayed dataset (``sensor`` protocol), None
        without a replayed dataset, annotations or task id, or when no frame shows the ROI."""
        res = self.evaluate_protocols(("sensor",))
        return res["sensor"]["roi_psnr"] if res else None

    def evaluate_protocols(self, protocols: Optional[tuple] = None) -> dict:
        """The current map over every frame of the replayed dataset under the scoring protocols (``config.scoring``,
        or ``protocols``; :meth:`MissionFinish.evaluate_protocols
        <gausslite.mission.finish.MissionFinish.evaluate_protocols>`). Call while the worker is idle."""
        return self.finishing.evaluate_protocols(protocols)

    def close(self) -> None:
        """Stop the threads (pending frames are dropped); a closed mission does not start. Safe to call more than
        once."""
        self.lifecycle.close()
