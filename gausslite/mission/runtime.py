"""The agent's mission loop: frames → attention → mapper → periodic ROI-subset pushes (paper
Sec. III-B to III-E; ``docs/live.md``, ``docs/sharing.md``).

:class:`AgentRuntime` is usable without gRPC: it needs a task graph (any object with ``targets``,
``anchors``, ``relations``), scene annotations for the offline relevance sources, and optionally a
*fusion client*: a :class:`gausslite.mission.ports.FusionPort` (``open_session``, ``upload_chunks``,
``upload_keyframes``; the gRPC ``gausslite_services.fusion_server.client.FusionClient`` is one), or None to map locally
only. The fusion client signals a rejected delta base with :class:`gausslite.mission.errors.PreconditionFailed`.

Threads per mission:

* mapping worker — takes keyframes and computes the relevance map (attention front-end over the
  annotation or ONNX backend, or GT ROI), maps them (``mapper.keyframe_budget_s`` per keyframe or fixed
  iterations), optimises over its keyframes while none is pending (live ingest), every ``push_every``
  mapped frames hands a snapshot of the ROI subset to the pusher and every ``checkpoint_every`` writes a
  checkpoint. Live ingest (``ingest: keyframes``, realtime replays): ``submit`` never blocks; the keyframe
  selector (:mod:`gausslite.mapping.keyframes`) keeps only the newest pending candidate. Every-frame ingest
  (offline replays, ``ingest: every_frame``): a bounded queue, ``submit`` blocks when it is full (gRPC flow
  control back-pressure);
* pusher (:class:`gausslite.mission.pusher.Pusher`) — sends the newest snapshot with retries and exponential
  backoff, so a fusion-server outage or a lost link never stalls mapping; at most two subsets are held however
  long the link is down. ``status()`` reports its backlog and the last acknowledged version.

What is shared, the share worker, the fine-tune cache and the delta planning live in
:class:`gausslite.mission.share.ShareSession`; the settings in :mod:`gausslite.mission.config`.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import os
import queue
import threading
import time
import uuid
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional

import numpy as np

from gausslite.attention.worker import RelevanceWorker
from gausslite.camera import Intrinsics
from gausslite.datasets.annotations import task_roi
from gausslite.datasets.base import Frame
from gausslite.mapping.keyframes import KeyframeRule, KeyframeSelector
from gausslite.mission.config import AgentConfig
from gausslite.mission.errors import FrameSizeMismatch, MissionError
from gausslite.mission.heap import trim_heap
from gausslite.mission.ports import FusionPort
from gausslite.mission.pose_follow import MapFollower
from gausslite.mission.pusher import Pusher
from gausslite.mission.relevance import build_relevance
from gausslite.mission.share import ShareSession, select_shared
from gausslite.mission.state import ACCEPTS_TASK, MissionState
from gausslite.mission.team_frame import WorldFrames, annotations_to_world, frame_to_world

log = logging.getLogger(__name__)


@dataclass
class MissionSummaryData:
    """What :meth:`AgentRuntime.finish` returns (mirrors the ``MissionSummary`` message)."""

    status: dict
    final_push_ok: bool
    n_shared: int
    share_pct: float
    bytes_on_wire: int
    bytes_per_gaussian: float
    roi_psnr: Optional[float]
    psnr: Optional[float]
    seconds_per_frame: float
    roi_psnr_all_frames: Optional[float] = None
    frames_all: int = 0
    #: replays: the final map over the sequence under each scoring protocol (``agent.scoring``; docs/realtime.md):
    #: ``{protocol: {"roi_psnr", "psnr", "ssim", "frames_scored", "roi_frames"}}``
    protocols: dict = field(default_factory=dict)
    total_upload_bytes: int = 0
    final_subset_bytes: int = 0
    pushes: List[dict] = field(default_factory=list)
    #: the views sent for the fusion refinement (``agent.refine_views``): bytes on the wire, views sent, views unsent
    view_bytes: int = 0
    views_sent: int = 0
    views_unsent: int = 0
    #: replays: frame id → :class:`gausslite.evaluation.TrackedView` of each ``tracked`` / ``novel-tracked`` frame
    #: scored (its pose and exposure fitted against this map)
    tracked_views: dict = field(default_factory=dict)
    #: replays: frame id → :class:`gausslite.evaluation.TrackedView` of each ``novel`` frame scored: the pose and
    #: exposure this map predicts for it (a team map is scored at them)
    predicted_views: dict = field(default_factory=dict)

    def as_dict(self) -> dict:
        """JSON-ready dict (``tracked_views``, ``predicted_views``: frame id → ``{"c2w": 4 × 4 list, "exposure": 6
        floats}``)."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        for key in ("tracked_views", "predicted_views"):
            out[key] = {int(i): {"c2w": np.asarray(v.c2w).tolist(), "exposure": np.asarray(v.theta).tolist()}
                        for i, v in getattr(self, key).items()}
        return out


_FINISH = object()
_DRAIN = object()  # Finish without a push: everything before it is mapped
_SLOT = object()  # "the keyframe selector holds a pending candidate"
_CKPT_COUNTERS = ("frames_received", "frames_mapped", "frames_keyframed", "frames_skipped", "seconds_mapping",
                  "idle_iterations", "keyframe_iterations")
CHECKPOINT_FILE = "checkpoint.pt"
RECENT_FRAMES = 1800  #: frames of ``accept_latency_ms_p99_recent`` (a minute at 30 Hz)
VERSION_FILE = "pushed_version.json"
#: frames between keyframes held for the next keyframe (``AgentRuntime._between``): a second at 60 Hz
BETWEEN_MAX = 64


def _percentile(vals, q: float) -> float:
    return float(np.percentile(np.asarray(vals, dtype=np.float64), q)) if len(vals) else 0.0


def _atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Write ``path`` through a temporary file in the same folder and ``os.replace`` (atomic on POSIX)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    write(tmp)
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


class AgentRuntime:
    """One mission of one agent: task-conditioned mapping of a frame stream plus fusion pushes.

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
            every ``checkpoint_every`` keyframes); when it already holds one, the mission resumes from it
            (map, keyframes, counters, pushed version) and keeps pushing newer versions.

    Raises:
        ValueError: empty agent id; ``relevance: gt`` without annotations/task id; ``relevance: attention`` without
            annotations (or ``relevance_fn``); a graph with no phrases; a checkpoint of another ``T_world_map``.
    """

    def __init__(self, agent_id: str, task_text: str, graph, config: AgentConfig, *, annotations=None,
                 task_id: Optional[str] = None, fusion: Optional[FusionPort] = None, relevance_fn: Optional[Callable] = None,
                 mission_id: Optional[str] = None,
                 on_finished: Optional[Callable[["AgentRuntime"], None]] = None,
                 checkpoint_dir: Optional[str | Path] = None) -> None:
        if not agent_id:
            raise ValueError("agent_id must be non-empty")
        self.agent_id = agent_id
        self.task_text = task_text
        self.graph = graph
        self.config = config
        self.annotations = annotations = annotations_to_world(annotations, self.T_world_map)
        self.fusion = fusion
        self.mission_id = mission_id or uuid.uuid4().hex[:12]
        self.on_finished = on_finished
        self.task_id = task_id = _task_id_of(annotations, task_id, task_text)
        self.frontend = None  # the attention front-end (relevance: attention), gausslite.mission.relevance
        if relevance_fn is None:
            relevance_fn, self.frontend = build_relevance(config, graph, annotations, task_id, lambda: self.mapper)
        self._relevance_fn = relevance_fn
        self._pending_task = None  # (text, graph, task id, relevance fn, front-end) left by update_task
        self._relevance_worker = None
        if config.relevance_max_wait_s is not None:
            self._relevance_worker = RelevanceWorker(self._relevance_fn, config.relevance_max_wait_s)

        # lazy: keeps gausslite.mission.runtime importable without torch
        import torch

        # lazy: keeps gausslite.mission.runtime importable without SciPy, Warp, torch
        from gausslite.mapping.mapper import Mapper

        # lazy: keeps gausslite.mission.runtime importable without OpenCV
        from gausslite.mapping.resolution import uses_detail

        torch.manual_seed(config.mapper.seed)
        self.mapper = Mapper(config.mapper)
        #: the mapping resolutions (agent.resolution): the background's chosen at the first frame, and with the detail
        #: layer the task region's own; each corrected both ways from the iterations keyframes get
        #: (docs/live.md#mapping-resolution)
        self.resolution = config.resolution.governor(config.mapper)
        #: the mapper maps the task region at its own level (mapper.detail, a mode with a task region)
        self.maps_detail = uses_detail(config.mapper)
        self._upload_factor: Optional[float] = None  # the downscale of the keyframes sent to the fusion server
        self._novel_ids: Optional[frozenset] = None  # frames a replay withheld from the mapper (novel, novel-tracked)
        #: frame id → TrackedView of the tracked / novel-tracked frames, and of the novel ones (predicted), last scored
        self.tracked_views, self.predicted_views = {}, {}
        self._queue: "queue.Queue" = queue.Queue(maxsize=config.queue_size)
        self._lock = threading.Lock()
        self._finish_lock = threading.Lock()
        self._stop = threading.Event()
        self._eval_frames: List[Frame] = []
        self.intrinsics = None
        self.state = MissionState.MAPPING
        self.frames_received = 0
        self.frames_mapped = 0
        self.n_gaussians = 0
        self.n_active = 0
        self.last_error = ""
        self.seconds_mapping = 0.0
        self.summary: Optional[MissionSummaryData] = None
        self.share = ShareSession(agent_id, config)  # selection, fine-tune cache, delta planning
        #: the pushes: versions, backlog, retries, keyframe uploads (gausslite.mission.pusher)
        self.pusher = Pusher(agent_id, task_text, config, fusion, self.share, self.mapper, lambda: self.upload_intrinsics,
                             self._set_error)
        self._replay_thread: Optional[threading.Thread] = None
        self.replay_frames = 0
        self._closed_for_input = False
        # ---- live ingest (keyframe selection), latencies, checkpoints

        self.selector = KeyframeSelector(KeyframeRule(config.keyframe_translation_m, config.keyframe_rotation_deg,
                                                      config.keyframe_max_interval_s))
        self._online = config.ingest == "keyframes"  # replay() sets it from config.realtime
        self.frames_keyframed = 0
        #: frames that did not become keyframes since the last one (oldest first, bounded): the mapper records the
        #: camera's motion through them and, under ``mapper.roi_views``, keeps their ROI crops
        self._between: "deque" = deque(maxlen=BETWEEN_MAX)
        self._sends_between, self._keeps_views, self._uses_between = self._between_use(config)
        self.frames_skipped = 0
        self.frames_rejected = 0
        self.odometry = _odometry(config)  # agent.pose_source odometry: every frame is tracked in submit
        #: the map follows the odometry's loop closures (agent.pose_source odometry)
        self.follower = None if self.odometry is None else MapFollower(self.odometry)
        #: replays under ``agent.pose_source: odometry``: frame id → (4, 4) float64 c2w the odometry estimated (in the
        #: world frame), every frame tracked, the withheld ones too: the poses the mission is scored at
        self.estimated_poses: Dict[int, np.ndarray] = {}
        self.keyframe_iterations = 0
        self.idle_iterations = 0
        self.checkpoints = 0
        self.resumed_keyframes = 0
        self._accept_ms: "deque[float]" = deque(maxlen=100_000)
        self._kf_latency_s: "deque[float]" = deque(maxlen=100_000)  # bounded over a long mission
        self._dataset = None
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir else None
        if self.checkpoint_dir is not None and (self.checkpoint_dir / CHECKPOINT_FILE).is_file():
            self._resume()
        self._worker = threading.Thread(target=self._work, name=f"agent-{agent_id}-map", daemon=True)
        self._worker.start()
        self.pusher.start()
        self._share_started = False

    @functools.cached_property
    def T_world_map(self) -> Optional[np.ndarray]:
        """(4, 4) float64 rigid transform from the robot's map frame into the team's world frame
        (``config.frame.T_world_map``; docs/team.md), or None when they are the same frame: every frame's pose and the
        annotations' boxes enter the mission through it (:mod:`gausslite.mission.team_frame`)."""
        return self.config.frame.matrix()

    # ------------------------------------------------------------------ input
    def submit(self, frame: Frame, timeout: Optional[float] = None, _replay: bool = False,
               arrival: Optional[float] = None) -> bool:
        """Hand one frame to the mission.

        Keyframe ingest (``ingest: keyframes``, and realtime replays) never blocks: the frame is offered to
        the keyframe selector (:mod:`gausslite.mapping.keyframes`), which keeps only the newest pending
        candidate; frames that are not candidates, or are replaced before the mapper takes them, count as
        skipped. Every-frame ingest queues the frame and blocks while the queue is full. The frame's pose is given in
        the robot's map frame and enters the mission as ``T_world_map @ c2w`` (``agent.frame``; docs/team.md).

        Args:
            frame: the decoded frame, or a validated not yet decoded one (an object with ``frame_id``,
                ``c2w``, ``intrinsics`` and ``materialize() -> Frame``, e.g.
                :class:`gausslite_services.agent.frames.PendingFrame`; decoded by the worker if it becomes a keyframe).
                timeout: every-frame ingest only: how long to wait for queue space.
            arrival: ``time.perf_counter()`` when the frame arrived (before decoding); the accept latency
                (arrival → accepted, ``accept_latency_ms_p99``) and keyframe latency (arrival → mapped)
                are measured from it (default: now).
        Returns:
            True when the frame was queued or became the pending keyframe candidate, False when skipped.
        Raises:
            MissionError: the mission no longer accepts frames (finishing, finished, failed).
            FrameSizeMismatch (a MissionError): the frame's image size differs from the mission's first frame.
            queue.Full: ``timeout`` expired (every-frame ingest).
        """
        t_arr = time.perf_counter() if arrival is None else arrival
        if self.odometry is not None:
            frame = self._track(frame, None if _replay else self.T_world_map)
            if frame is None:
                return False
        if not _replay:  # a replay's frames are in the world frame already (replay())
            frame = frame_to_world(frame, self.T_world_map)
        if not self._share_started and not _replay:
            self._start_share(self._online)  # a streamed mission starts with its first frame
        with self._lock:
            closed = (self.state in (MissionState.FINISHED, MissionState.FAILED) or self._stop.is_set()
                      or (not _replay and (self._closed_for_input or self.state == MissionState.FINISHING)))
            if closed:
                raise MissionError(f"mission {self.mission_id} is {self.state.lower()}: no more frames accepted"
                                   + (f" ({self.last_error})" if self.state == MissionState.FAILED else ""))
            intr = frame.intrinsics
            if self.intrinsics is not None and (intr.width, intr.height) != (self.intrinsics.width,
                                                                               self.intrinsics.height):
                raise FrameSizeMismatch(f"frame {frame.frame_id}: image size {intr.width}x{intr.height} differs "
                                   f"from the mission's {self.intrinsics.width}x{self.intrinsics.height}")
            if self.intrinsics is None:
                self.intrinsics = intr
            if self._online:
                pending, replaced = self.selector.offer((frame, t_arr), frame.c2w, t_arr)
                if self._uses_between:
                    if replaced is not None:
                        self._between.append(replaced[0])
                    if not pending:
                        self._between.append(frame)
                self.frames_received += 1
                self.frames_skipped += int(not pending) + int(replaced is not None)
                if pending and replaced is None:
                    self._queue.put_nowait(_SLOT)  # at most one _SLOT is queued at a time
                self._accept_ms.append(1e3 * (time.perf_counter() - t_arr))
                return pending
        self._queue.put((frame, t_arr), timeout=timeout)
        with self._lock:
            self.frames_received += 1
            self._accept_ms.append(1e3 * (time.perf_counter() - t_arr))
        return True

    def _track(self, frame, W: Optional[np.ndarray] = None) -> Optional[Frame]:
        """``frame`` (decoded) with the odometry's pose (agent.pose_source odometry), or None when its tracking failed:
        the frame is then logged, counted as rejected and not mapped. ``W`` (4, 4): the transform from the odometry's
        frame into the map's that the frame's pose takes next (None: the identity)."""
        if hasattr(frame, "materialize"):
            frame = frame.materialize()  # the odometry needs the images of every frame
        if self.odometry.last_pose is None:  # the first frame's pose (identity without one) fixes the frame
            self.odometry.initial_pose = np.asarray(frame.c2w, dtype=np.float64).copy()
        r = self.odometry.track(frame)  # its own lock: a frame's tracking does not hold the mission's
        if r.ok:
            self.follower.record(frame.frame_id, r, W)
            if self._dataset is not None:  # a replay: scored at these poses (evaluate_protocols)
                self.estimated_poses[int(frame.frame_id)] = np.asarray(r.c2w, dtype=np.float64).copy()
            return dataclasses.replace(frame, c2w=r.c2w)
        with self._lock:
            self.frames_received += 1
            self.frames_rejected += 1
            self.last_error = f"odometry lost frame {frame.frame_id}: {r.reason}"
        return None

    def replay(self, dataset, progress: Optional[Callable[[int, int], None]] = None) -> threading.Thread:
        """Feed every frame of ``dataset`` from a background thread; the state becomes ``REPLAY_DONE``
        once all its frames are mapped. Streaming (``submit`` from outside) is refused meanwhile.

        With ``config.realtime`` the frames are sent at the dataset's clock (``frame.timestamp`` relative
        to the first frame, divided by ``config.rate``) through keyframe ingest, as a robot would stream
        them; otherwise every frame is mapped (offline behaviour). The final map is evaluated over every
        frame of the dataset at Finish (``roi_psnr_all_frames``). With ``agent.frame.T_world_map`` the dataset's poses
        are moved into the team's world frame (:class:`~gausslite.mission.team_frame.WorldFrames`)."""

        self.replay_frames = len(dataset)
        if self.T_world_map is not None:
            dataset = WorldFrames(dataset, self.T_world_map)
        self._dataset = dataset
        sc = self.config.scoring
        held: frozenset = frozenset()
        if sc.withholds():
            # lazy: keeps gausslite.mission.runtime importable without the dataset loaders
            from gausslite.datasets.subset import withheld_indices

            held = frozenset(withheld_indices(len(dataset), sc.novel_every))
            self._novel_ids = frozenset(int(dataset[i].frame_id) for i in held)
        realtime = self.config.realtime
        with self._lock:
            self._online = bool(realtime)
        self._start_share(bool(realtime))

        def run():
            # the withheld frames never reach the mapper; with odometry they are still tracked in order, at their
            # own time, as a robot's odometry tracks every frame (their estimated poses are where they are scored)
            n, sent = len(dataset) - len(held), 0
            t_start, ts0 = time.perf_counter(), None
            try:
                for i in range(len(dataset)):
                    if self._stop.is_set():
                        return
                    if i in held and self.odometry is None:
                        continue
                    fr = dataset[i]
                    if realtime:
                        ts0 = fr.timestamp if ts0 is None else ts0
                        wait = t_start + (fr.timestamp - ts0) / self.config.rate - time.perf_counter()
                        if wait > 0 and self._stop.wait(wait):
                            return
                    if i in held:
                        self._track(fr)
                        continue
                    self.submit(fr, _replay=True)
                    sent += 1
                    if progress:
                        progress(sent, n)
                self._queue.join()
                with self._lock:
                    if self.state == MissionState.MAPPING:
                        self.state = MissionState.REPLAY_DONE
            except MissionError:
                return
            except Exception as e:  # unreadable frame etc.
                self._fail(f"replay failed: {type(e).__name__}: {e}")

        self._replay_thread = threading.Thread(target=run, name=f"agent-{self.agent_id}-replay", daemon=True)
        self._replay_thread.start()
        return self._replay_thread

    def _start_share(self, live: bool) -> None:
        """Under ``share_worker_start: mission``, start the share worker as the mission starts
        (:meth:`ShareSession.start`): a live mission's at ``pusher_nice``, an every-frame mission's at the mapper's
        priority (it has no keyframe budget to protect; below a mapper that maps as fast as it can, the worker would
        get no processor until mapping ends). By default (``first_push``) the worker starts at the first push: an
        early start makes the team map worse (:class:`~gausslite.mission.config.AgentConfig`)."""
        with self._lock:
            if self._share_started:
                return
            self._share_started = True
        if self.fusion is not None and self.config.share_worker_start == "mission":
            self.share.start(self.config.pusher_nice if live else 0)

    @property
    def replaying(self) -> bool:
        """True while a replay thread is feeding frames."""
        return self._replay_thread is not None and self._replay_thread.is_alive()

    # ------------------------------------------------------------------ mapping worker
    def _fail(self, msg: str) -> None:
        log.error("agent %s mission %s: %s", self.agent_id, self.mission_id, msg)
        with self._lock:
            self.state = MissionState.FAILED
            self.last_error = msg
        self.pusher.final_done.set()

    def relevance(self, frame: Frame) -> np.ndarray:
        """The mission's relevance map w of ``frame`` for its current task: (H, W) bool (paper Sec. III-B), from the
        relevance worker when there is one (``relevance_max_wait_s``), otherwise computed here."""
        if self._relevance_worker is not None:
            return self._relevance_worker.relevance(frame)
        return self._relevance_fn(frame)

    def update_task(self, task_text: str, graph, task_id: Optional[str] = None) -> None:
        """Give the running mission a new task; the map re-targets to it and keeps what it has mapped.

        The new task's relevance source is built here (so a task the scene cannot answer fails now, with nothing
        changed); the mapping thread applies it before its next keyframe or idle iteration: every task flag and κ
        restart at zero (:meth:`Mapper.retarget <gausslite.mapping.mapper.Mapper.retarget>`), the stored
        keyframes get the new task's relevance maps, and from then on the new task's relevance re-targets the map
        through seeding and adoption (``mapper.seeding.adopt``; docs/live.md#changing-the-task). The next push
        opens the fusion session under the new task.

        Args:
            task_text: the new task. graph: its parsed graph (``targets``, ``anchors``, ``relations``).
            task_id: its id in the scene's ``tasks.json`` (``relevance: gt``), or None (looked up by text).
        Raises:
            MissionError: the mission is finishing, finished or failed.
            ValueError: a relevance source that cannot be built for the task (as at :class:`AgentRuntime`), or an
                unknown task id.
        """
        with self._lock:
            if self.state not in ACCEPTS_TASK:
                raise MissionError(f"mission {self.mission_id} is {self.state}: it cannot take a new task")
        ann = self.annotations
        if task_id is None and ann is not None:
            task_id = next((t.id for t in getattr(ann, "tasks", []) or []
                            if t.text.strip().lower() == task_text.strip().lower()), None)
        if task_id is not None and ann is not None:
            ann.task_by_id(task_id)  # KeyError with the known ids
        fn, frontend = build_relevance(self.config, graph, ann, task_id, lambda: self.mapper)
        with self._lock:
            self._pending_task = (task_text, graph, task_id, fn, frontend)
        log.info("agent %s mission %s: new task %r (applied before the next keyframe)", self.agent_id,
                 self.mission_id, task_text)

    def apply_pending_task(self) -> bool:
        """Switch to the task :meth:`update_task` left, if any: the mapping thread calls it before every keyframe
        and idle iteration; a caller that drives ``self.mapper`` itself (a deterministic replay) calls it between
        keyframes. The stored keyframes get the new task's relevance maps, so the ROI phase draws every view the
        mission already has of the task's region.

        Returns:
            True when a new task was applied.
        """
        with self._lock:
            pending, self._pending_task = self._pending_task, None
        if pending is None:
            return False
        task_text, graph, task_id, fn, frontend = pending
        if self._relevance_worker is not None:
            self._relevance_worker.close()

            self._relevance_worker = RelevanceWorker(fn, self.config.relevance_max_wait_s)
        self._relevance_fn, self.frontend = fn, frontend
        self.mapper.retarget()
        store = self.mapper.keyframes
        for i in range(len(store)):
            st = store[i]
            frame = Frame(st.frame_id, 0.0, st.rgb.numpy(), st.depth.float().numpy(), st.c2w.numpy(),
                          Intrinsics.from_K(st.K.numpy(), st.width, st.height))
            store.set_roi(i, fn(frame))
        with self._lock:
            self.task_text, self.graph, self.task_id = task_text, graph, task_id
            self.n_active = 0
        self.pusher.set_task(task_text)
        log.info("agent %s mission %s: now mapping for task %r (%d stored keyframes re-targeted)", self.agent_id,
                 self.mission_id, task_text, len(store))
        return True

    def _idle_work(self) -> bool:
        """Whether the worker should optimise between keyframes instead of blocking on the queue."""
        return (self._online and self.config.idle_optimize and self.frames_mapped > 0
                and self.state == MissionState.MAPPING and not self._closed_for_input and not self._stop.is_set())

    def _work(self) -> None:
        cfg = self.config
        while True:
            try:
                self.apply_pending_task()
            except Exception as e:
                self._fail(f"switching to the new task failed: {type(e).__name__}: {e}")
            if self.pusher.trim_due.is_set():  # a push's copies back to the OS, at the mapper's priority
                self.pusher.trim_due.clear()
                trim_heap()
            idle = self._idle_work()
            try:
                # a blocking wait wakes up now and then to apply a new task (update_task)
                item = self._queue.get(block=False) if idle else self._queue.get(timeout=0.5)
            except queue.Empty:
                if not idle:
                    continue
                try:
                    if self.follower is not None:  # a loop closed while the mapper waits for a keyframe
                        self.follower.apply(self.mapper)
                    n = self.mapper.optimize(max_seconds=cfg.idle_chunk_s)
                except Exception as e:
                    self._fail(f"optimising between keyframes failed: {type(e).__name__}: {e}")
                    continue
                with self._lock:
                    self.idle_iterations += n
                if n == 0:
                    time.sleep(0.01)
                continue
            try:
                if item is None:
                    return
                if item is _FINISH:
                    if self.state != MissionState.FAILED:
                        if self.frames_mapped:
                            if self.follower is not None:  # every loop checked, then the map follows them
                                self.odometry.flush(self.config.final_pass_s)
                                self.follower.apply(self.mapper)
                            n = self.mapper.finalize(max_seconds=self.config.final_pass_s)
                            log.info("agent %s: final pass, %d iterations", self.agent_id, n)
                        self._offer_snapshot(final=True)
                        self._record_version()
                    else:
                        self.pusher.final_done.set()
                    continue
                if item is _DRAIN:
                    self.pusher.final_done.set()
                    continue
                if item is _SLOT:
                    with self._lock:
                        item = self.selector.take()
                    if item is None:
                        continue
                if self.state == MissionState.FAILED:
                    continue
                self._map_one(*item)
            finally:
                self._queue.task_done()

    def _map_one(self, item: Frame, t_arrival: float) -> None:
        """Map one keyframe (worker thread): decode (a ``PendingFrame`` of a live stream), relevance, mapper,
        counters, pushes, checkpoint. Corrupt image data found only now is logged and counted as rejected."""
        cfg = self.config
        t0 = time.perf_counter()
        if hasattr(item, "materialize"):
            try:
                item = item.materialize()
            except ValueError as e:
                log.warning("agent %s mission %s: frame rejected at decoding: %s", self.agent_id, self.mission_id, e)
                with self._lock:
                    self.frames_rejected += 1
                    self.last_error = f"rejected frame: {e}"
                return
        native = item
        try:
            if self.resolution.choice is None:
                intr = item.intrinsics
                self.resolution.start(intr.width, intr.height, cfg.mapper.keyframe_budget_s,
                                      cfg.mapper.budget.max_gaussians, region=self.maps_detail)
                self._upload_factor = self.resolution.factor
            item = self.resolution.apply(item)
            native_between = self._take_between(item.frame_id)
            between = [self.resolution.apply(f) if isinstance(f, Frame) else f for f in native_between]
            w = self.relevance(item)
            # the task region at its own level (mapper.detail): the keyframe and its frames at the region's size
            detail = self.resolution.detail_view(native, w, native_between) if self.maps_detail else None
            if self.follower is not None:  # a loop closure since the last keyframe: the map follows it first
                self.follower.apply(self.mapper)
            # the per-keyframe budget covers decoding and relevance too: the mapper gets what is left
            b = cfg.mapper.keyframe_budget_s
            left = None if b is None else max(1e-6, b - (time.perf_counter() - t0))
            st = self.mapper.map_frame(item, w, time_budget_s=left, between=between,
                                       **({} if detail is None else {"detail": detail}))
            self._record_iterations(st, w)
            if self.follower is not None:
                self.follower.mapped(item.frame_id)
        except Exception as e:
            self._fail(f"mapping frame {item.frame_id} failed: {type(e).__name__}: {e}")
            return
        with self._lock:
            self.frames_mapped += 1
            self.frames_keyframed += 1
            self.keyframe_iterations += st.iters
            self.seconds_mapping += time.perf_counter() - t0
            self._kf_latency_s.append(time.perf_counter() - t_arrival)
            self.n_gaussians = st.n_gaussians
            self.n_active = int(self.mapper.model.active.sum())
            upload = (self.frames_mapped - 1) % cfg.keyframe_every == 0
            if len(self._eval_frames) < cfg.eval_max_frames:
                self._eval_frames.append(item)
        if upload:
            self.pusher.add_keyframe(*self._upload_view(native, item, w))
        if self._sends_between and between and w is not None:  # no relevance, no task region to carry over
            self._offer_between_views(item, w, between)
        log.debug("agent %s mapped frame %d: %d Gaussians (%d active), %.2f s", self.agent_id,
                  item.frame_id, st.n_gaussians, self.n_active, st.seconds)
        if self.frames_mapped % cfg.push_every == 0:
            self._offer_snapshot(final=False)
            self._record_version()
        if self.checkpoint_dir is not None and cfg.checkpoint_every and self.frames_mapped % cfg.checkpoint_every == 0:
            try:
                self.save_checkpoint()
            except Exception as e:  # a full disk must not stop mapping
                log.warning("agent %s: checkpoint failed: %s: %s", self.agent_id, type(e).__name__, e)

    def _record_iterations(self, st, w: Optional[np.ndarray]) -> None:
        """Hand the resolution governor what keyframe ``st`` (``FrameStats``) got: its iterations, and its ROI-phase
        iterations when it showed the task region (relevance ``w``) and the map had task Gaussians to fit."""
        shows_region = w is not None and bool(np.any(w)) and bool(self.mapper.model.active.any())
        self.resolution.record(st.iters, st.active_iters if shows_region else None, st.n_gaussians, st.detail_px)

    @property
    def upload_intrinsics(self):
        """Intrinsics of the keyframes this mission sends to the fusion server: the first frame's, at the mapping
        resolution chosen then (None before the first frame)."""
        if self.intrinsics is None:
            return None
        f = self._upload_factor or self.resolution.factor
        intr = self.intrinsics
        return intr if f == 1 else intr.scaled(f)

    def _upload_view(self, native: Frame, mapped: Frame, w: np.ndarray) -> tuple:
        """The keyframe and relevance map to upload: as mapped, or at the first choice's resolution when the mapping
        resolution has changed since (the fusion session keeps one image size)."""
        if self._upload_factor is None or self._upload_factor == self.resolution.factor:
            return mapped, w
        # lazy: keeps gausslite.mission.runtime importable without OpenCV
        import cv2

        from gausslite.datasets.common import downscale_frame

        up = downscale_frame(native, self._upload_factor)
        wu = cv2.resize(np.asarray(w, np.uint8), (up.intrinsics.width, up.intrinsics.height),
                        interpolation=cv2.INTER_NEAREST) > 0
        return up, wu

    @staticmethod
    def _between_use(config: AgentConfig) -> tuple:
        """How the frames between keyframes are used: (their ROI crops are sent for the fusion refinement, they are
        decoded for ROI crops (the mapper's ROI views or those views), they are kept at all (also for their motion
        alone))."""
        m = config.mapper
        sends = config.refine_views.crop and config.refine_views.between
        keeps = (m.roi_views.enabled and m.effective().roi) or sends
        return sends, keeps, keeps or m.sensor.motion_every_frame

    def _offer_between_views(self, keyframe: Frame, w: np.ndarray, frames: list) -> int:
        """Offer the pusher the ROI crops of every ``refine_views.between_every``-th of ``frames`` (decoded frames
        between the previous keyframe and ``keyframe``, at the mapping resolution) that see the task region: the
        keyframe's ROI ``w`` carried over by depth (:func:`gausslite.fusion.views.region_points`,
        :func:`gausslite.mapping.roi_views.project_roi`). Nothing while the mapping resolution differs from the
        uploads' (the fusion session keeps one image size). Returns the views queued."""
        if self._upload_factor is not None and self._upload_factor != self.resolution.factor:
            return 0
        # lazy: keeps gausslite.mission.runtime importable without OpenCV
        from gausslite.fusion.views import region_points
        from gausslite.mapping.roi_views import project_roi

        pts = region_points(keyframe, np.asarray(w) > 0)
        if len(pts) == 0:
            return 0
        queued = 0
        for fr in frames[::self.config.refine_views.between_every]:
            if not isinstance(fr, Frame):
                continue
            roi = project_roi(pts, np.asarray(fr.depth, np.float32), fr.intrinsics.K, fr.c2w)
            queued += int(self.pusher.add_keyframe(fr, roi))
        return queued

    def _take_between(self, frame_id: int) -> list:
        """The frames seen before keyframe ``frame_id`` since the last keyframe (oldest first), for
        :meth:`Mapper.map_frame`'s ``between``: decoded when the mapper keeps their ROI crops (``mapper.roi_views``
        in gausslite mode), otherwise as they came (their pose and time are what the motion models need). A frame
        whose images do not decode is left out and logged."""
        with self._lock:
            taken = [f for f in self._between if f.frame_id < frame_id]
            rest = [f for f in self._between if f.frame_id > frame_id]
            self._between.clear()
            self._between.extend(rest)
        if not self._keeps_views:
            return taken
        out = []
        for f in taken:
            if hasattr(f, "materialize"):
                try:
                    f = f.materialize()
                except ValueError as e:
                    log.warning("agent %s mission %s: frame %d between keyframes not decoded: %s", self.agent_id,
                                self.mission_id, f.frame_id, e)
                    continue
            out.append(f)
        return out

    # ------------------------------------------------------------------ checkpoint / resume
    def save_checkpoint(self) -> Path:
        """Write ``checkpoint.pt`` (map with κ and active flags, keyframe window, counters, pushed version,
        keyframe-selector reference) atomically into ``checkpoint_dir``. Call from the worker thread (or
        while it is idle). Returns the path. Raises OSError on write failure, ValueError without a folder."""
        # lazy: keeps gausslite.mission.runtime importable without torch
        import torch

        if self.checkpoint_dir is None:
            raise ValueError("no checkpoint_dir configured")
        with self._lock:
            counters = {k: getattr(self, k) for k in _CKPT_COUNTERS}
            sel = self.selector.state_dict()
        version = self.pusher.version
        state = {"format": 1, "agent_id": self.agent_id, "mission_id": self.mission_id, "task_text": self.task_text,
                 "task_id": self.task_id, "version": version, "counters": counters, "selector": sel,
                 "mapper": self.mapper.state_dict(), "saved_unix": time.time(),
                 "T_world_map": None if self.T_world_map is None else self.T_world_map.tolist(),
                 "odometry": None if self.odometry is None else self.odometry.state_dict()}
        path = self.checkpoint_dir / CHECKPOINT_FILE
        _atomic_write(path, lambda p: torch.save(state, p))
        with self._lock:
            self.checkpoints += 1
        log.info("agent %s: checkpoint of mission %s after %d keyframes (v%d) in %s", self.agent_id,
                 self.mission_id, counters["frames_keyframed"], version, path)
        return path

    def _record_version(self) -> None:
        """Persist the newest map version handed to the pusher (a resumed mission continues above it)."""
        if self.checkpoint_dir is None:
            return

        v = self.pusher.version
        try:
            _atomic_write(self.checkpoint_dir / VERSION_FILE, lambda p: p.write_text(json.dumps({"version": v})))
        except OSError as e:
            log.warning("agent %s: cannot record the pushed version: %s", self.agent_id, e)

    def _resume(self) -> None:
        # lazy: keeps gausslite.mission.runtime importable without torch
        import torch

        path = self.checkpoint_dir / CHECKPOINT_FILE
        try:
            state = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as e:
            raise ValueError(f"cannot read the checkpoint {path}: {type(e).__name__}: {e}") from None
        if state.get("agent_id") != self.agent_id or state.get("mission_id") != self.mission_id:
            raise ValueError(f"checkpoint {path} belongs to agent {state.get('agent_id')!r} mission "
                             f"{state.get('mission_id')!r}, not {self.agent_id!r} {self.mission_id!r}")
        if state.get("task_text") != self.task_text:
            raise ValueError(f"checkpoint {path}: mission {self.mission_id} was started with the task "
                             f"{state.get('task_text')!r}, not {self.task_text!r}")
        saved = state.get("T_world_map")
        if not np.allclose(np.eye(4) if saved is None else np.asarray(saved),
                           np.eye(4) if self.T_world_map is None else self.T_world_map, atol=1e-9):
            raise ValueError(f"checkpoint {path}: mission {self.mission_id} was mapped with T_world_map {saved}, not "
                             f"{None if self.T_world_map is None else self.T_world_map.tolist()}: its map lies in "
                             "another world frame")
        self.mapper.load_state_dict(state["mapper"])
        for k, v in state["counters"].items():
            setattr(self, k, v)
        self.selector.load_state_dict(state["selector"])
        if self.odometry is not None and state.get("odometry"):  # agent.pose_source odometry: tracking resumes
            self.odometry.load_state_dict(state["odometry"])
        version = int(state["version"])
        vpath = self.checkpoint_dir / VERSION_FILE
        if vpath.is_file():  # pushes after the checkpoint: never reuse a version the fusion server holds
            version = max(version, int(json.loads(vpath.read_text()).get("version", 0)))
        self.pusher.resume(version)
        self.resumed_keyframes = self.frames_keyframed
        self.n_gaussians = len(self.mapper.model)
        self.n_active = int(self.mapper.model.active.sum())
        log.info("agent %s: mission %s resumed from %s: %d keyframes, %d Gaussians, next version v%d",
                 self.agent_id, self.mission_id, path, self.frames_keyframed, self.n_gaussians, version + 1)

    def _offer_snapshot(self, final: bool) -> None:
        """Hand the pusher what the next push needs (mapping thread; :meth:`ShareSession.capture`)."""
        self.pusher.offer(self.share.capture(self.mapper), self.frames_mapped, final)

    def _set_error(self, msg: str) -> None:
        """The mission's ``last_error`` (the pusher reports "" after each acknowledged push)."""
        with self._lock:
            self.last_error = msg

    # ------------------------------------------------------------------ status / finish
    def status(self) -> dict:
        """Snapshot of the mission's progress (keys of the ``MissionStatus`` message)."""
        pushes = self.pusher.status()
        with self._lock:
            return {
                "mission_id": self.mission_id, "agent_id": self.agent_id, "state": self.state,
                "task_text": self.task_text, "task_id": self.task_id or "",
                "frames_received": self.frames_received, "frames_mapped": self.frames_mapped,
                "frames_queued": self._queue.qsize(), "n_gaussians": self.n_gaussians, "n_active": self.n_active,
                **pushes, "last_error": self.last_error, "seconds_mapping": self.seconds_mapping,
                "frames_keyframed": self.frames_keyframed, "frames_skipped": self.frames_skipped,
                "accept_latency_ms_p99": _percentile(self._accept_ms, 99),
                "accept_latency_ms_p99_recent": _percentile(list(self._accept_ms)[-RECENT_FRAMES:], 99),
                "keyframe_latency_s_p95": _percentile(self._kf_latency_s, 95),
                "idle_iterations": self.idle_iterations, "checkpoints": self.checkpoints,
                "resumed_keyframes": self.resumed_keyframes, "frames_rejected": self.frames_rejected,
                "keyframe_iterations": self.keyframe_iterations, **self.resolution.status(), **self._tracking_status(),
            }

    def _tracking_status(self) -> dict:
        """``frames_lost``, ``frames_relocalised`` and ``loop_closures`` of the odometry (zeros without one)."""
        if self.odometry is None:
            return {"frames_lost": 0, "frames_relocalised": 0, "loop_closures": 0}
        s = self.odometry.summary()
        return {"frames_lost": s["failed"], "frames_relocalised": s["relocalised"], "loop_closures": s["loops"]}

    def acknowledged_subset(self):
        """The subset the fusion server acknowledged last, as the server holds it (decoded wire values):
        ``(version, GaussianArrays, ids)``, or None before the first acknowledged push."""
        return self.share.acknowledged()

    def wait_mapped(self, timeout_s: Optional[float] = None) -> bool:
        """Wait until every queued frame is mapped (True) or ``timeout_s`` passes (False)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            with self._lock:
                idle = self._queue.unfinished_tasks == 0 and not self.replaying
            if idle or self.state == MissionState.FAILED:
                return True
            if deadline is not None and time.monotonic() > deadline:
                return False
            time.sleep(0.05)

    def finish(self, push: bool = True, evaluate: bool = True, timeout_s: Optional[float] = None) -> MissionSummaryData:
        """Stop accepting frames, map what is queued, do the final push, evaluate; idempotent.

        Args:
            push: do the final push (retried up to ``final_push_timeout_s``).
            evaluate: compute full-image and ROI PSNR over the kept mapped frames (ROI needs annotations
                and a task id).
            timeout_s: overall bound on waiting for mapping and the final push (None: unbounded).
        Returns:
            MissionSummaryData.
        Raises:
            TimeoutError: mapping or the final push did not complete within ``timeout_s``.
        """
        if not self._finish_lock.acquire(timeout=-1 if timeout_s is None else max(0.0, timeout_s)):
            raise TimeoutError(f"mission {self.mission_id}: another Finish still running after {timeout_s} s")
        try:
            return self._finish(push, evaluate, timeout_s)
        finally:
            self._finish_lock.release()

    def _finish(self, push: bool, evaluate: bool, timeout_s: Optional[float]) -> MissionSummaryData:
        with self._lock:
            if self.summary is not None:
                return self.summary
            first = not self._closed_for_input
            self._closed_for_input = True
            if self.state in (MissionState.MAPPING, MissionState.REPLAY_DONE):
                self.state = MissionState.FINISHING
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        if first:
            if self._replay_thread is not None:
                self._stop_replay_wait(deadline)
            # both markers queue behind the pending keyframe; the worker stops optimising between keyframes
            self._queue.put(_FINISH if push else _DRAIN)
        remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
        if not self.pusher.final_done.wait(remaining):
            raise TimeoutError(f"mission {self.mission_id}: mapping/final push not done within {timeout_s} s")
        self.wait_mapped(None if deadline is None else max(0.0, deadline - time.monotonic()))
        psnr, roi_psnr = (self.evaluate() if evaluate and self.frames_mapped else (None, None))
        protocols = (self.evaluate_protocols() if evaluate and self.frames_mapped and self._dataset is not None
                     else {})
        roi_all = protocols["sensor"]["roi_psnr"] if protocols else None
        pusher = self.pusher
        last = pusher.pushes[-1] if pusher.pushes else None
        with self._lock:
            if self.state != MissionState.FAILED:
                self.state = MissionState.FINISHED
        n_total = max(self.n_gaussians, 1)
        n_shared = last.n_shared if last else int(select_shared(self.mapper.gmap, self.config.share,
                                                                self.config.kappa_threshold).sum())
        self.summary = MissionSummaryData(
            status=self.status(), final_push_ok=bool(pusher.final_push_ok and push),
            n_shared=int(n_shared), share_pct=100.0 * n_shared / n_total if self.n_gaussians else 0.0,
            bytes_on_wire=pusher.final_subset_bytes,
            bytes_per_gaussian=(pusher.final_subset_bytes / last.n_shared) if last and last.n_shared else 0.0,
            roi_psnr=roi_psnr, psnr=psnr,
            seconds_per_frame=self.seconds_mapping / max(self.frames_mapped, 1),
            roi_psnr_all_frames=roi_all, frames_all=len(self._dataset) if self._dataset is not None else 0,
            protocols=protocols,
            total_upload_bytes=pusher.total_upload_bytes, final_subset_bytes=pusher.final_subset_bytes,
            pushes=[dict(p.__dict__) for p in pusher.pushes], view_bytes=pusher.views.sent_bytes,
            views_sent=pusher.views.sent, views_unsent=pusher.views_unsent(), tracked_views=dict(self.tracked_views),
            predicted_views=dict(self.predicted_views))
        if protocols:
            # lazy: keeps gausslite.mission.runtime importable without torch (scoring imported it already)
            from gausslite.evaluation import protocol_line

            log.info("agent %s final map, ROI PSNR (dB): %s", self.agent_id, protocol_line(protocols))
        if self.on_finished is not None:
            try:
                self.on_finished(self)
            except Exception as e:  # saving results must not lose the summary
                log.warning("agent %s: on_finished hook failed: %s", self.agent_id, e)
        return self.summary

    def _stop_replay_wait(self, deadline: Optional[float]) -> None:
        # A replay that is still running is allowed to complete (Finish = "map the rest, then push").
        t = self._replay_thread
        while t is not None and t.is_alive():
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError("replay still running at the Finish deadline")
            t.join(0.1)

    def evaluate(self) -> tuple[Optional[float], Optional[float]]:
        """(full-image PSNR, ROI PSNR) in dB of the current map, mean over the kept mapped frames; ROI PSNR is
        None without annotations/task id or when no frame shows the ROI. Call only while the worker is idle."""
        # lazy: keeps gausslite.mission.runtime importable without Warp, torch
        from gausslite.evaluation import score_view

        ps, rps = [], []
        for fr in self._eval_frames:
            out = self.mapper.render_frame(fr)  # at the refined pose under pose_refine, as `map` scores
            roi = None
            if self.annotations is not None and self.task_id is not None:
                roi = self.annotations.roi_mask(self.task_id, fr.depth, fr.c2w, fr.intrinsics)
            s = score_view(out, fr, roi)
            ps.append(s.psnr)
            if not math.isnan(s.roi_psnr):
                rps.append(s.roi_psnr)
        return (float(np.mean(ps)) if ps else None, float(np.mean(rps)) if rps else None)

    def evaluate_all_frames(self) -> Optional[float]:
        """ROI PSNR (dB) of the current map over **every** frame of the replayed dataset, skipped ones included
        (mean over frames that show the ROI): the honest score of an online map. None without a replayed
        dataset, annotations or task id, or when no frame shows the ROI. Call only while the worker is idle."""
        res = self.evaluate_protocols(("sensor",))
        return res["sensor"]["roi_psnr"] if res else None

    def evaluate_protocols(self, protocols: Optional[tuple] = None) -> dict:
        """The current map over every frame of the replayed dataset under the scoring protocols of
        ``config.scoring`` (:func:`gausslite.evaluation.score_live_map`; ``sensor`` always, whose ROI PSNR is
        :meth:`evaluate_all_frames`'s figure; ``keyframes``: the mapped keyframes at their refined pose and exposure;
        ``novel``: the withheld frames at the pose and exposure the map predicts for them, nothing fitted; ``tracked``
        / ``novel-tracked``: every ``track_stride``-th / every withheld frame at a pose and exposure fitted against the
        frozen map), or of ``protocols``. Under ``agent.pose_source: odometry`` every protocol starts from the poses
        the odometry estimated (:attr:`estimated_poses`, the withheld frames' included), as the robot uses its map,
        with the ground-truth ROI from the given poses; frames it lost are not scored. Fills :attr:`tracked_views`
        and :attr:`predicted_views`.

        Returns:
            ``{protocol: {"roi_psnr", "psnr", "ssim", "frames_scored", "roi_frames", "roi_psnr_per_frame",
            "psnr_per_frame"}}`` (dB; ROI PSNR over the frames that show the ROI, None when none does; per frame:
            frame id → dB); ``{}`` without a replayed dataset, annotations or task id. Call only while the worker is
            idle."""
        # lazy: keeps gausslite.mission.runtime importable without Warp, torch
        from gausslite.datasets.subset import EstimatedPoses, ScaledFrames
        from gausslite.evaluation import score_live_map

        if self._dataset is None or self.annotations is None or self.task_id is None:
            return {}
        sc = self.config.scoring
        chosen = sc.chosen() if protocols is None else tuple(protocols)
        if self._novel_ids is None:
            chosen = tuple(p for p in chosen if p not in ("novel", "novel-tracked"))
        # scored at the mapping resolution: the map's own detail, and minutes instead of tens of minutes at 640x480
        frames = ScaledFrames(self._dataset, self.resolution.factor)
        roi = task_roi(self.annotations, self.task_id)
        if self.odometry is not None:
            # at the poses the odometry estimated, as the robot uses its map; the ROI from the given poses (the
            # image's ground truth); a frame whose tracking failed has no pose to be scored at
            frames = EstimatedPoses(frames, self.estimated_poses)
            roi = frames.roi_fn(self.annotations, self.task_id)
        self.tracked_views, self.predicted_views = {}, {}
        return score_live_map(self.mapper, frames, roi, chosen,
                              track_iters=sc.track_iters, track_stride=sc.track_stride, novel_ids=self._novel_ids,
                              record=self.tracked_views, predicted=self.predicted_views)

    def close(self) -> None:
        """Stop the threads (pending frames are dropped). Safe to call more than once."""
        with self._lock:
            self._closed_for_input = True
        self._stop.set()
        self.pusher.stop()  # a push waiting to retry ends now
        try:
            while True:
                self._queue.get_nowait()
                self._queue.task_done()
        except queue.Empty:
            pass
        self._queue.put(None)
        self._worker.join(5.0)
        self.pusher.close(5.0)
        if self._relevance_worker is not None:
            self._relevance_worker.close()
        if self.odometry is not None:
            self.odometry.close()
        self.share.close()


def _task_id_of(annotations, task_id: Optional[str], task_text: str) -> Optional[str]:
    """The annotations' id of the mission's task: ``task_id`` checked against them (KeyError with the known ids), or,
    without one, the id of the annotated task whose text is ``task_text`` (case and surrounding space ignored); None
    without annotations or a match."""
    if annotations is None:
        return task_id
    if task_id is None:
        return next((t.id for t in getattr(annotations, "tasks", []) or []
                     if t.text.strip().lower() == task_text.strip().lower()), None)
    annotations.task_by_id(task_id)  # KeyError with the known ids
    return task_id


def _odometry(config: AgentConfig):
    """The RGB-D odometry of a mission with ``agent.pose_source: odometry`` (None otherwise); its world frame is the
    first frame's pose (the identity for a stream without poses)."""
    if config.pose_source != "odometry":
        return None
    # lazy: Open3D loads only for missions that track
    from gausslite.datasets.odometry import RGBDOdometry

    # a live stream: loop closure on its own thread, so that a keyframe's loop registrations never delay tracking
    return RGBDOdometry(config.odometry, background_loops=True)
