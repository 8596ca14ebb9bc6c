"""The agent's mission loop: frames → attention → mapper → periodic ROI-subset pushes (SPEC §4–§8,
paper Sec. III-E "Multi-Agent Fusion").

:class:`AgentRuntime` is usable without gRPC: it needs a task graph (any object with ``targets``,
``anchors``, ``relations``), scene annotations for the offline relevance sources, and optionally a
*fusion client*: any object with the methods of ``services.fusion_server.client.FusionClient``
(``open_session``, ``upload_subset``, ``upload_keyframes``), or None to map locally only.

Threads per mission:

* mapping worker — takes frames from a bounded queue (``submit`` blocks when it is full, which gives
  gRPC flow control back-pressure), computes the relevance map (attention front-end or GT ROI), maps
  the frame, and every ``push_every`` mapped frames hands a snapshot of the ROI subset to the pusher;
* pusher — uploads the newest pending snapshot (older pending ones are superseded; keyframes not yet
  uploaded accumulate) with retries and exponential backoff, so a fusion-server outage never stalls
  mapping; the client resumes a half-uploaded subset of the same ``map_version``.

The shared subset (SPEC §7) is the Gaussians with ``active = 1`` (``share: active``) or with
``κ >= kappa_threshold`` (``share: kappa``), with their κ counts.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, List, Literal, Optional

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field

from gausslite.datasets.base import Frame
from gausslite.mapping.config import MapperConfig, apply_overrides

log = logging.getLogger(__name__)


class AgentConfig(BaseModel):
    """Agent mission settings (YAML section ``agent`` plus the mapper section ``mapper``).

    Attributes:
        relevance: ``attention`` (task graph grounded by the attention front-end with the scene's offline
            annotation backend, SPEC §4) or ``gt`` (ground-truth ROI of ``task_id``, for ablations).
        share: ``active`` (a = 1), ``kappa`` (κ >= ``kappa_threshold``) or ``task`` (a = 1 and
            κ >= ``kappa_threshold`` inside the task's 3D region, compacted by ROI contribution:
            :func:`gausslite.sharing.select_task_subset`): which Gaussians are pushed.
        share_coverage: ``share: task``: fraction of the ROI blending weight the shared subset keeps.
        kappa_threshold: κ threshold for ``share: kappa``.
        push_every: push a subset every this many mapped frames (and always at the end).
        downscale, max_frames, stride: applied to replayed datasets (``load_dataset``).
        queue_size: frames buffered between the stream and the mapping worker.
        keyframe_every: every k-th mapped frame is uploaded as a keyframe for the fusion refinement.
        max_keyframes: keep at most this many keyframes for upload (older ones dropped first).
        jpeg_quality: keyframe JPEG quality on the wire (``keyframe_format: jpeg``).
        keyframe_format: ``png`` (lossless colour, default: JPEG q95 keyframes cost the fusion
            refinement 2 dB ROI PSNR on room0) or ``jpeg``.
        chunk_gaussians: Gaussians per wire chunk.
        delta_push: push only the Gaussians new or changed beyond quantisation since the version the
            server acknowledged, plus the removed rows (wire delta chunks); a full upload when the
            server lacks the base (FAILED_PRECONDITION) or the delta would not be smaller.
        delta_tolerance: multiple of one code step that counts as "changed" (gausslite.wire.delta).
        push_attempt_s: give up one periodic push after this many seconds of retries (the next push
            carries the newer map anyway).
        final_push_timeout_s: retry the final push for up to this many seconds (fusion-server restart).
        backoff_s, max_backoff_s: exponential backoff between retries of a push (seconds).
        attention_rendered_depth: give the attention front-end the depth rendered from the current map.
        eval_max_frames: frames kept for the ROI PSNR of the Finish summary.
        mapper: the mapper configuration (default mode ``gausslite``).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    relevance: Literal["attention", "gt"] = "attention"
    share: Literal["active", "kappa", "task"] = "active"
    kappa_threshold: int = Field(1, ge=0)
    share_coverage: float = Field(0.99, gt=0, le=1)
    push_every: int = Field(5, ge=1)
    downscale: float = Field(1.0, ge=1.0)
    max_frames: Optional[int] = Field(None, ge=1)
    stride: int = Field(1, ge=1)
    queue_size: int = Field(4, ge=1)
    keyframe_every: int = Field(2, ge=1)
    max_keyframes: int = Field(64, ge=1)
    jpeg_quality: int = Field(95, ge=1, le=100)
    keyframe_format: Literal["png", "jpeg"] = "png"
    chunk_gaussians: int = Field(20000, ge=1)
    delta_push: bool = True
    delta_tolerance: float = Field(1.0, ge=0)
    push_attempt_s: float = Field(20.0, gt=0)
    final_push_timeout_s: float = Field(120.0, gt=0)
    backoff_s: float = Field(0.2, gt=0)
    max_backoff_s: float = Field(5.0, gt=0)
    attention_rendered_depth: bool = True
    eval_max_frames: int = Field(200, ge=1)
    mapper: MapperConfig = MapperConfig(mode="gausslite")


def load_agent_config(path: Optional[str | Path] = None, overrides: List[str] = ()) -> AgentConfig:
    """Read the ``agent`` and ``mapper`` sections of a GaussLite YAML file (other sections, e.g. ``sim``,
    are ignored) and apply dotted ``key=value`` overrides (``agent.push_every=3``,
    ``mapper.iters_per_frame=5``).

    Raises:
        FileNotFoundError: missing file. ValueError: not a mapping. pydantic.ValidationError: bad values.
    """
    data: dict = {}
    if path:
        p = Path(path)
        if not p.is_file():
            raise FileNotFoundError(f"agent config not found: {p}")
        data = yaml.safe_load(p.read_text()) or {}
        if not isinstance(data, dict):
            raise ValueError(f"{p}: top level must be a mapping")
    data = apply_overrides(data, overrides)
    agent = dict(data.get("agent") or {})
    mapper = dict(data.get("mapper") or {})
    mapper.setdefault("mode", "gausslite")
    agent["mapper"] = MapperConfig.model_validate(mapper)
    return AgentConfig.model_validate(agent)


class MissionError(RuntimeError):
    """The mission cannot accept the request (finished, failed, or replaying)."""


@dataclass
class PushRecord:
    """One successful push: ``version``, ``n_shared`` Gaussians of ``n_total``, wire bytes sent, chunk
    count; ``delta`` (a delta push carrying ``records`` Gaussians and ``removed`` row removals),
    ``frames_mapped`` when the snapshot was taken."""

    version: int
    n_shared: int
    n_total: int
    bytes_on_wire: int
    n_chunks: int
    keyframes: int
    seconds: float
    delta: bool = False
    records: int = 0
    removed: int = 0
    frames_mapped: int = 0


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
    total_upload_bytes: int = 0
    final_subset_bytes: int = 0
    pushes: List[dict] = field(default_factory=list)

    def as_dict(self) -> dict:
        """JSON-ready dict."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass
class _Snapshot:
    version: int
    gaussians: Any  # GaussianArrays
    n_total: int
    final: bool = False
    ids: Any = None  # (N,) int64 stable Gaussian ids of the rows
    frames_mapped: int = 0


_FINISH = object()


def select_shared(gmap, share: str = "active", kappa_threshold: int = 1) -> np.ndarray:
    """Boolean mask (N,) of the Gaussians an agent shares (SPEC §7).

    Args:
        gmap: ``GaussianMap`` (or anything with ``active`` and ``kappa`` arrays/tensors).
        share: ``active`` (a = 1) or ``kappa`` (κ >= ``kappa_threshold``).
    Raises:
        ValueError: unknown ``share`` rule.
    """
    active = np.asarray(gmap.active.cpu().numpy() if hasattr(gmap.active, "cpu") else gmap.active, dtype=bool)
    kappa = np.asarray(gmap.kappa.cpu().numpy() if hasattr(gmap.kappa, "cpu") else gmap.kappa)
    if share == "active":
        return active
    if share == "kappa":
        return kappa >= int(kappa_threshold)
    if share == "task":  # without views: a = 1 and κ (AgentRuntime applies region and compaction)
        return active & (kappa >= int(kappa_threshold))
    raise ValueError(f"unknown share rule {share!r} (use 'active', 'kappa' or 'task')")


class AgentRuntime:
    """One mission of one agent: task-conditioned mapping of a frame stream plus fusion pushes.

    Args:
        agent_id (str): the agent's id on the fusion server (non-empty).
        task_text (str): the task.
        graph: parsed task graph (``targets``, ``anchors``, ``relations``).
        config (AgentConfig): settings.
        annotations: ``SceneAnnotations`` of the scene (``objects.json``/``tasks.json``), needed by both
            relevance sources and by the ROI PSNR of the summary; None only works with a custom
            ``relevance_fn``.
        task_id (str | None): the task's id in ``tasks.json`` (GT relevance, evaluation).
        fusion: a FusionClient-like object, or None (no pushes).
        relevance_fn: optional override ``frame -> (H, W) bool``.
        mission_id (str | None): id (default: random).
        on_finished: optional callback ``(runtime) -> None`` after the final push (e.g. save files).

    Raises:
        ValueError: empty agent id; ``relevance: gt`` without annotations/task id; ``relevance:
            attention`` without annotations (and without ``relevance_fn``); a graph with no phrases.
    """

    def __init__(self, agent_id: str, task_text: str, graph, config: AgentConfig, *, annotations=None,
                 task_id: Optional[str] = None, fusion=None, relevance_fn: Optional[Callable] = None,
                 mission_id: Optional[str] = None,
                 on_finished: Optional[Callable[["AgentRuntime"], None]] = None) -> None:
        if not agent_id:
            raise ValueError("agent_id must be non-empty")
        self.agent_id = agent_id
        self.task_text = task_text
        self.graph = graph
        self.config = config
        self.annotations = annotations
        self.fusion = fusion
        self.mission_id = mission_id or uuid.uuid4().hex[:12]
        self.on_finished = on_finished
        if task_id is None and annotations is not None:
            task_id = next((t.id for t in getattr(annotations, "tasks", []) or []
                            if t.text.strip().lower() == task_text.strip().lower()), None)
        if task_id is not None and annotations is not None:
            annotations.task_by_id(task_id)  # KeyError with the known ids
        self.task_id = task_id
        self._relevance_fn = relevance_fn or self._build_relevance()

        import torch

        from gausslite.mapping.mapper import Mapper

        torch.manual_seed(config.mapper.seed)
        self.mapper = Mapper(config.mapper)
        self._queue: "queue.Queue" = queue.Queue(maxsize=config.queue_size)
        self._lock = threading.Lock()
        self._finish_lock = threading.Lock()
        self._push_cv = threading.Condition(self._lock)
        self._pending: Optional[_Snapshot] = None
        self._final_done = threading.Event()
        self._stop = threading.Event()
        self._eval_frames: List[Frame] = []
        self._kf_pending: List[Frame] = []
        self.intrinsics = None
        self.state = "MAPPING"
        self.frames_received = 0
        self.frames_mapped = 0
        self.n_gaussians = 0
        self.n_active = 0
        self.pushes: List[PushRecord] = []
        self.push_failures = 0
        self.keyframes_uploaded = 0
        self.last_error = ""
        self.seconds_mapping = 0.0
        self.final_push_ok = False
        self.summary: Optional[MissionSummaryData] = None
        self._version = 0
        self._planner = None  # gausslite.wire.delta.PushPlanner, created at the first push
        self.total_upload_bytes = 0  # bytes of subset chunks sent over the mission (all pushes)
        self.final_subset_bytes = 0  # the last pushed subset encoded whole
        self._session_open = False
        self._replay_thread: Optional[threading.Thread] = None
        self.replay_frames = 0
        self._closed_for_input = False
        self._worker = threading.Thread(target=self._work, name=f"agent-{agent_id}-map", daemon=True)
        self._pusher = threading.Thread(target=self._push_loop, name=f"agent-{agent_id}-push", daemon=True)
        self._worker.start()
        self._pusher.start()

    # ------------------------------------------------------------------ relevance
    def _build_relevance(self) -> Callable:
        cfg = self.config
        ann = self.annotations
        if cfg.relevance == "gt":
            if ann is None or self.task_id is None:
                raise ValueError("relevance 'gt' needs scene annotations and a task id from tasks.json")
            tid = self.task_id
            return lambda fr: ann.roi_mask(tid, fr.depth, fr.c2w, fr.intrinsics)
        if ann is None:
            raise ValueError("relevance 'attention' needs scene annotations (objects.json) for the offline "
                             "annotation detector/segmenter; give a dataset or annotations path")
        from gausslite.attention import AttentionFrontEnd

        fe = AttentionFrontEnd.from_annotations(self.graph, ann)
        self.frontend = fe

        def fn(fr: Frame) -> np.ndarray:
            rd = None
            if cfg.attention_rendered_depth and len(self.mapper.model) > 0:
                out = self.mapper.render(fr.c2w, fr.intrinsics.K, fr.intrinsics.width, fr.intrinsics.height)
                d = out.depth.detach().cpu().numpy().astype(np.float32)
                rd = np.where(out.alpha.detach().cpu().numpy() > 0.5, d, 0.0).astype(np.float32)
            rel, _ = fe.process(fr, rd)
            return rel

        return fn

    # ------------------------------------------------------------------ input
    def submit(self, frame: Frame, timeout: Optional[float] = None, _replay: bool = False) -> None:
        """Queue one frame for mapping (blocks while the queue is full).

        Raises:
            MissionError: the mission no longer accepts frames (finishing, finished, failed) or the
                frame's image size differs from the mission's first frame.
            queue.Full: ``timeout`` expired.
        """
        with self._lock:
            closed = (self.state in ("FINISHED", "FAILED") or self._stop.is_set()
                      or (not _replay and (self._closed_for_input or self.state == "FINISHING")))
            if closed:
                raise MissionError(f"mission {self.mission_id} is {self.state.lower()}: no more frames accepted"
                                   + (f" ({self.last_error})" if self.state == "FAILED" else ""))
            intr = frame.intrinsics
            if self.intrinsics is not None and (intr.width, intr.height) != (self.intrinsics.width,
                                                                               self.intrinsics.height):
                raise MissionError(f"frame {frame.frame_id}: image size {intr.width}x{intr.height} differs "
                                   f"from the mission's {self.intrinsics.width}x{self.intrinsics.height}")
            if self.intrinsics is None:
                self.intrinsics = intr
        self._queue.put(frame, timeout=timeout)
        with self._lock:
            self.frames_received += 1

    def replay(self, dataset, progress: Optional[Callable[[int, int], None]] = None) -> threading.Thread:
        """Feed every frame of ``dataset`` from a background thread; the state becomes ``REPLAY_DONE``
        once all its frames are mapped. Streaming (``submit`` from outside) is refused meanwhile."""

        self.replay_frames = len(dataset)

        def run():
            n = len(dataset)
            try:
                for i in range(n):
                    if self._stop.is_set():
                        return
                    self.submit(dataset[i], _replay=True)
                    if progress:
                        progress(i + 1, n)
                self._queue.join()
                with self._lock:
                    if self.state == "MAPPING":
                        self.state = "REPLAY_DONE"
            except MissionError:
                return
            except Exception as e:  # unreadable frame etc.
                self._fail(f"replay failed: {type(e).__name__}: {e}")

        self._replay_thread = threading.Thread(target=run, name=f"agent-{self.agent_id}-replay", daemon=True)
        self._replay_thread.start()
        return self._replay_thread

    @property
    def replaying(self) -> bool:
        """True while a replay thread is feeding frames."""
        return self._replay_thread is not None and self._replay_thread.is_alive()

    # ------------------------------------------------------------------ mapping worker
    def _fail(self, msg: str) -> None:
        log.error("agent %s mission %s: %s", self.agent_id, self.mission_id, msg)
        with self._lock:
            self.state = "FAILED"
            self.last_error = msg
            self._push_cv.notify_all()
        self._final_done.set()

    def _work(self) -> None:
        cfg = self.config
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                if item is _FINISH:
                    if self.state != "FAILED":
                        if self.frames_mapped:
                            self.mapper.finalize()
                        self._offer_snapshot(final=True)
                    else:
                        self._final_done.set()
                    continue
                if self.state == "FAILED":
                    continue
                t0 = time.perf_counter()
                try:
                    w = self._relevance_fn(item)
                    st = self.mapper.map_frame(item, w)
                except Exception as e:
                    self._fail(f"mapping frame {item.frame_id} failed: {type(e).__name__}: {e}")
                    continue
                with self._lock:
                    self.frames_mapped += 1
                    self.seconds_mapping += time.perf_counter() - t0
                    self.n_gaussians = st.n_gaussians
                    self.n_active = int(self.mapper.model.active.sum())
                    if (self.frames_mapped - 1) % cfg.keyframe_every == 0:
                        self._kf_pending.append(item)
                        del self._kf_pending[:-cfg.max_keyframes]
                    if len(self._eval_frames) < cfg.eval_max_frames:
                        self._eval_frames.append(item)
                log.debug("agent %s mapped frame %d: %d Gaussians (%d active), %.2f s", self.agent_id,
                          item.frame_id, st.n_gaussians, self.n_active, st.seconds)
                if self.frames_mapped % cfg.push_every == 0:
                    self._offer_snapshot(final=False)
            finally:
                self._queue.task_done()

    def _offer_snapshot(self, final: bool) -> None:
        from gausslite.wire.codec import GaussianArrays

        gmap = self.mapper.gmap
        if self.config.share == "task":
            from gausslite.sharing import ShareConfig, ShareView, select_task_subset

            views = [ShareView(kf.roi.cpu().numpy(), kf.depth.cpu().numpy(), kf.c2w.cpu().numpy(), kf.K.cpu().numpy())
                     for kf in self.mapper.keyframes if kf.roi is not None]
            mask, st = select_task_subset(gmap, views, ShareConfig(kappa_threshold=self.config.kappa_threshold,
                                                                   coverage=self.config.share_coverage),
                                          backend=self.config.mapper.backend)
            log.info("agent %s share: %s of %d (%d ROI keyframes)", self.agent_id, st, len(gmap), len(views))
        else:
            mask = select_shared(gmap, self.config.share, self.config.kappa_threshold)
        arrays = GaussianArrays.from_any(gmap).take(mask)
        ids = self.mapper.model.ids.numpy()[mask]
        with self._lock:
            self._version += 1
            self._pending = _Snapshot(self._version, arrays, len(gmap), final, ids, self.frames_mapped)
            self._push_cv.notify_all()

    # ------------------------------------------------------------------ pusher
    def _push_loop(self) -> None:
        while True:
            with self._lock:
                while self._pending is None and not self._stop.is_set():
                    self._push_cv.wait(0.5)
                if self._stop.is_set() and self._pending is None:
                    return
                snap, self._pending = self._pending, None
            if self.fusion is None:
                if snap.final:
                    self.final_push_ok = False
                    self._final_done.set()
                continue
            budget = self.config.final_push_timeout_s if snap.final else self.config.push_attempt_s
            ok = self._push_with_retries(snap, budget)
            if snap.final:
                self.final_push_ok = ok
                self._final_done.set()

    def _superseded(self, snap: _Snapshot) -> bool:
        with self._lock:
            return (not snap.final) and self._pending is not None

    def _push_with_retries(self, snap: _Snapshot, budget_s: float) -> bool:
        deadline = time.monotonic() + budget_s
        delay = self.config.backoff_s
        attempt = 0
        while True:
            attempt += 1
            try:
                self._push_once(snap)
                return True
            except Exception as e:  # grpc.RpcError, ConnectionError, client-side errors
                msg = f"push v{snap.version} attempt {attempt} failed: {type(e).__name__}: {_short(e)}"
                with self._lock:
                    self.push_failures += 1
                    self.last_error = msg
                    self._session_open = False  # re-open after a server restart
                log.warning("agent %s: %s", self.agent_id, msg)
            if self._stop.is_set() or self._superseded(snap) or time.monotonic() + delay > deadline:
                return False
            time.sleep(delay)
            delay = min(delay * 2.0, self.config.max_backoff_s)

    def _push_once(self, snap: _Snapshot) -> None:
        t0 = time.perf_counter()
        c = self.fusion
        if not self._session_open:
            c.open_session(self.agent_id, self.task_text, self.intrinsics)
            self._session_open = True
        if self._planner is None:
            from gausslite.wire.delta import PushPlanner

            self._planner = PushPlanner(self.agent_id, chunk_gaussians=self.config.chunk_gaussians,
                                        tolerance=self.config.delta_tolerance, delta=self.config.delta_push)
        plan = self._planner.plan(snap.ids, snap.gaussians, snap.version)
        try:
            r = c.upload_chunks(self.agent_id, plan.version, plan.chunks, n_gaussians=plan.n_records,
                                full_map_gaussians=snap.n_total)
        except Exception as e:
            code = getattr(e, "code", None)
            if not (plan.is_delta and callable(code) and getattr(code(), "name", "") == "FAILED_PRECONDITION"):
                raise
            # the server lacks the delta's base (restarted without its data, or superseded): full upload
            log.warning("agent %s: delta v%d rejected (%s); uploading the full subset", self.agent_id,
                        plan.version, _short(e))
            self._planner.forget()
            with self._lock:
                self._version += 1
                version = self._version
            plan = self._planner.plan(snap.ids, snap.gaussians, version)
            r = c.upload_chunks(self.agent_id, plan.version, plan.chunks, n_gaussians=plan.n_records,
                                full_map_gaussians=snap.n_total)
        if not getattr(r, "complete", True):
            raise RuntimeError(f"subset v{plan.version} upload incomplete ({getattr(r, 'n_chunks', '?')} chunks)")
        self._planner.acknowledge(plan)
        if self._planner.last_stats:
            log.info("agent %s delta plan v%d: %s (sent %s)", self.agent_id, plan.version, self._planner.last_stats,
                     "delta" if plan.is_delta else "full")
        self.final_subset_bytes = plan.full_bytes if plan.full_bytes is not None else plan.nbytes
        with self._lock:
            kfs = list(self._kf_pending)
        n_kf = 0
        if kfs:
            n_kf = int(c.upload_keyframes(self.agent_id, kfs, jpeg_quality=self.config.jpeg_quality,
                                          color_format=self.config.keyframe_format) or 0)
            with self._lock:
                sent = {id(f) for f in kfs}
                self._kf_pending = [f for f in self._kf_pending if id(f) not in sent]
        rec = PushRecord(plan.version, len(snap.gaussians), snap.n_total, int(getattr(r, "bytes_sent", 0)),
                         int(getattr(r, "n_chunks", 0)), len(kfs), time.perf_counter() - t0, plan.is_delta,
                         plan.n_records, plan.n_removed, snap.frames_mapped)
        with self._lock:
            self.total_upload_bytes += rec.bytes_on_wire
            self.pushes.append(rec)
            self.keyframes_uploaded += len(kfs)
            self.last_error = ""
        log.info("agent %s pushed v%d: %d/%d Gaussians, %d B, %d keyframes (%d acknowledged)", self.agent_id,
                 rec.version, rec.n_shared, rec.n_total, rec.bytes_on_wire, len(kfs), n_kf)

    # ------------------------------------------------------------------ status / finish
    def status(self) -> dict:
        """Snapshot of the mission's progress (keys of the ``MissionStatus`` message)."""
        with self._lock:
            return {
                "mission_id": self.mission_id, "agent_id": self.agent_id, "state": self.state,
                "task_text": self.task_text, "task_id": self.task_id or "",
                "frames_received": self.frames_received, "frames_mapped": self.frames_mapped,
                "frames_queued": self._queue.qsize(), "n_gaussians": self.n_gaussians, "n_active": self.n_active,
                "pushes": len(self.pushes), "push_failures": self.push_failures,
                "last_pushed_version": self.pushes[-1].version if self.pushes else 0,
                "last_error": self.last_error, "seconds_mapping": self.seconds_mapping,
                "keyframes_uploaded": self.keyframes_uploaded,
            }

    def wait_mapped(self, timeout_s: Optional[float] = None) -> bool:
        """Wait until every queued frame is mapped (True) or ``timeout_s`` passes (False)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            with self._lock:
                idle = self._queue.unfinished_tasks == 0 and not self.replaying
            if idle or self.state == "FAILED":
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
            if self.state in ("MAPPING", "REPLAY_DONE"):
                self.state = "FINISHING"
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        if first:
            if self._replay_thread is not None:
                self._stop_replay_wait(deadline)
            if push:
                self._queue.put(_FINISH)
            else:
                self._final_done.set()
        remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
        if not self._final_done.wait(remaining):
            raise TimeoutError(f"mission {self.mission_id}: mapping/final push not done within {timeout_s} s")
        self.wait_mapped(None if deadline is None else max(0.0, deadline - time.monotonic()))
        psnr, roi_psnr = (self.evaluate() if evaluate and self.frames_mapped else (None, None))
        last = self.pushes[-1] if self.pushes else None
        with self._lock:
            if self.state != "FAILED":
                self.state = "FINISHED"
        n_total = max(self.n_gaussians, 1)
        n_shared = last.n_shared if last else int(select_shared(self.mapper.gmap, self.config.share,
                                                                self.config.kappa_threshold).sum())
        self.summary = MissionSummaryData(
            status=self.status(), final_push_ok=bool(self.final_push_ok and push),
            n_shared=int(n_shared), share_pct=100.0 * n_shared / n_total if self.n_gaussians else 0.0,
            bytes_on_wire=self.final_subset_bytes,
            bytes_per_gaussian=(self.final_subset_bytes / last.n_shared) if last and last.n_shared else 0.0,
            roi_psnr=roi_psnr, psnr=psnr,
            seconds_per_frame=self.seconds_mapping / max(self.frames_mapped, 1),
            total_upload_bytes=self.total_upload_bytes, final_subset_bytes=self.final_subset_bytes,
            pushes=[dict(p.__dict__) for p in self.pushes])
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
        from gausslite.evaluation import score_view

        ps, rps = [], []
        for fr in self._eval_frames:
            out = self.mapper.render(fr.c2w, fr.intrinsics.K, fr.intrinsics.width, fr.intrinsics.height)
            roi = None
            if self.annotations is not None and self.task_id is not None:
                roi = self.annotations.roi_mask(self.task_id, fr.depth, fr.c2w, fr.intrinsics)
            s = score_view(out, fr, roi)
            ps.append(s.psnr)
            if not math.isnan(s.roi_psnr):
                rps.append(s.roi_psnr)
        return (float(np.mean(ps)) if ps else None, float(np.mean(rps)) if rps else None)

    def close(self) -> None:
        """Stop the threads (pending frames are dropped). Safe to call more than once."""
        with self._lock:
            self._closed_for_input = True
        self._stop.set()
        with self._lock:
            self._push_cv.notify_all()
        try:
            while True:
                self._queue.get_nowait()
                self._queue.task_done()
        except queue.Empty:
            pass
        self._queue.put(None)
        self._worker.join(5.0)
        self._pusher.join(5.0)


def _short(e: BaseException) -> str:
    details = getattr(e, "details", None)
    if callable(details):
        try:
            code = e.code()  # type: ignore[attr-defined]
            return f"{getattr(code, 'name', code)}: {details()}"
        except Exception:
            pass
    return str(e)[:300]
