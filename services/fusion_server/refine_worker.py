"""The team map's refinement in a worker process of its own (:class:`RefineWorker`), off the fusion server's
interpreter.

A refinement is PyTorch driven by Python: run in a thread of the server, it shares the interpreter lock with the gRPC
handler threads, and every handler that gives the lock up (a store read, a socket write, a commit) waits for it to
come back, so acknowledgements stretch out while it runs, whatever its niceness. In a child process it shares only
the cores, at niceness ``nice`` and on one thread, and the server's thread that asked for it waits on a pipe.

The child is started with the ``spawn`` method (no fork of a threaded server) on the first refinement and kept for the
next ones; it holds the decoded views of the keyframes it was sent (:func:`keyframe_key`), so each refinement sends
and decodes only the keyframes stored since the last one. Stopping kills it at once (a refinement in it ends there);
the next refinement starts a new one. A child whose server is gone exits at its next progress report (or at once,
when idle).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import traceback
import zlib
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

from gausslite.core.arrays import GaussianArrays
from gausslite_services.fusion_server.store_records import StoredKeyframe

log = logging.getLogger("gausslite_services.fusion_server.server")  # one logger for the whole service

__all__ = ["RefineWorker", "RefineOutcome", "keyframe_key", "decode_keyframe", "POLL_S"]

#: seconds between two looks at the stop callback while a refinement runs in the child (a stop ends it within this)
POLL_S = 0.1


def keyframe_key(k: StoredKeyframe) -> tuple:
    """What a decoded keyframe depends on: (agent, frame id, CRC-32 of the stored images, pose, intrinsics, depth
    scale). Two stored keyframes with one key decode to the same view."""
    return (k.agent_id, k.frame_id, zlib.crc32(k.roi, zlib.crc32(k.depth, zlib.crc32(k.color))),
            np.asarray(k.c2w, np.float64).tobytes(), k.fx, k.fy, k.cx, k.cy, k.width, k.height, k.depth_scale)


def decode_keyframe(k: StoredKeyframe):
    """A stored keyframe decoded for the refinement: a :class:`gausslite.mapping.views.Keyframe` on the CPU (colour
    in [0, 1], depth in metres, its ROI when it carries one).

    Raises:
        ValueError: an image that does not decode or does not match the keyframe's width × height.
        ImportError: no torch (the ``mapper`` extra).
    """
    # lazy: torch (the 'mapper' extra); the light install (vote, concat) has none
    from gausslite.camera import Intrinsics
    from gausslite.datasets.base import Frame
    from gausslite.mapping.views import keyframe_from_frame
    from gausslite.wire import images

    what = f"stored keyframe {k.frame_id}"
    size = (int(k.height), int(k.width))
    frame = Frame(k.frame_id, k.timestamp, images.decode_color(k.color, what, size),
                  images.decode_depth(k.depth, k.depth_scale, what, size), np.asarray(k.c2w, np.float64),
                  Intrinsics(k.fx, k.fy, k.cx, k.cy, k.width, k.height))
    roi = images.decode_roi(k.roi, size, what) if k.roi else None
    return keyframe_from_frame(frame, "cpu", roi)


class RefineOutcome:
    """What the child sends back: the refined map (``GaussianArrays``), its
    :class:`~gausslite.fusion.holdout.RefineReport`, the keyframes it was refined over and how many of them it
    decoded for it (the others it held decoded from earlier refinements)."""

    __slots__ = ("fused", "report", "keyframes_used", "decoded")

    def __init__(self, fused: GaussianArrays, report, keyframes_used: int, decoded: int) -> None:
        self.fused, self.report, self.keyframes_used, self.decoded = fused, report, keyframes_used, decoded


class RefineWorker:
    """One child process that runs refinements (:meth:`gausslite.fusion.engine.FuseEngine.refine`) one at a time.

    Args:
        nice: the child's niceness (0-19; it never runs below its parent's thread that starts it).
        torch_threads: the child's PyTorch threads.

    Thread-safety: :meth:`refine` is called by one thread at a time; :meth:`kill` may be called from any thread.
    """

    def __init__(self, nice: int = 10, torch_threads: int = 1) -> None:
        self.nice, self.torch_threads = int(nice), int(torch_threads)
        self._ctx = multiprocessing.get_context("spawn")
        self._proc = None
        self._conn = None
        self._held: set = set()  # keys of the decoded keyframes the child holds
        self._lock = threading.Lock()  # guards _proc / _conn against kill() from another thread
        self.starts = 0

    @property
    def pid(self) -> Optional[int]:
        """The running child's process id, or None."""
        p = self._proc
        return p.pid if p is not None and p.is_alive() else None

    def _ensure(self) -> None:
        with self._lock:
            if self._proc is not None and self._proc.is_alive():
                return
            self._drop()
            parent, child = self._ctx.Pipe(duplex=True)
            proc = self._ctx.Process(target=serve, args=(child, self.nice, self.torch_threads, os.getpid()),
                                     name="gausslite-team-map-refine", daemon=True)
            proc.start()
            child.close()
            self._proc, self._conn, self._held = proc, parent, set()
            self.starts += 1
            if self.nice > 0 and hasattr(os, "setpriority"):  # at once: the child's start-up imports are work too
                try:
                    os.setpriority(os.PRIO_PROCESS, proc.pid, max(self.nice, os.getpriority(os.PRIO_PROCESS, proc.pid)))
                except OSError as e:
                    log.warning("team map: niceness %d of the refinement process not set: %s", self.nice, e)

    def _drop(self) -> None:
        """Forget a dead child (lock held)."""
        if self._conn is not None:
            self._conn.close()
        if self._proc is not None:
            self._proc.join(1.0)
        self._proc, self._conn, self._held = None, None, set()

    def kill(self, wait_s: float = 2.0) -> None:
        """Kill the child now (a running refinement ends; :meth:`refine` raises InterruptedError or RuntimeError) and
        wait up to ``wait_s`` seconds for it to exit. Idempotent; safe from any thread."""
        proc = self._proc
        if proc is not None and proc.is_alive():
            proc.kill()
            proc.join(wait_s)

    def refine(self, fused: GaussianArrays, keyframes: Sequence[StoredKeyframe], iters: int, seed: int,
               engine_options: dict, options: dict, stopped: Callable[[], bool]) -> RefineOutcome:
        """Refine ``fused`` over ``keyframes`` (the store's, ordered by agent: the held-out views are spread over the
        agents) in the child, as :meth:`gausslite.fusion.engine.FuseEngine.refine` with ``engine_options`` then
        ``options``, at most ``iters`` iterations, seed ``seed``. Sends only the keyframes the child does not hold
        decoded; the child keeps those of this call and drops the others. Looks at ``stopped()`` every
        :data:`POLL_S` seconds while it waits.

        Raises:
            InterruptedError: ``stopped()`` turned true (the child was killed). ValueError: the refinement refused its
            input (no keyframe). RuntimeError: it failed in the child (the child's error and traceback in the message
            and the log), or the child died.
        """
        self._ensure()
        views = [(keyframe_key(k), k.agent_id) for k in keyframes]
        job = {"fused": fused, "iters": int(iters), "seed": int(seed), "engine_options": dict(engine_options),
               "options": dict(options),
               "views": [(key, agent, None if key in self._held else k) for (key, agent), k in zip(views, keyframes)]}
        conn, proc = self._conn, self._proc
        try:
            conn.send(job)
            while not conn.poll(POLL_S):
                if stopped():
                    raise InterruptedError("stopped during the refinement")
            reply = conn.recv()
        except InterruptedError:
            self.kill()
            with self._lock:
                self._drop()
            raise
        except (EOFError, OSError) as e:
            self.kill()
            with self._lock:
                self._drop()
            if stopped():
                raise InterruptedError("stopped during the refinement") from None
            raise RuntimeError(f"the refinement process died (exit code {proc.exitcode}): {e!r}") from None
        kind, payload, held = reply
        self._held = set(held)
        if kind == "done":
            return RefineOutcome(*payload)
        name, message, tb = payload
        log.error("team map: the refinement failed in its process:\n%s", tb)
        if name == "ValueError":
            raise ValueError(message)
        raise RuntimeError(f"{name}: {message}")


# ---------------------------------------------------------------------- the child
def _views(job_views: List[tuple], cache: Dict[tuple, object]) -> Tuple[Dict[str, list], Dict[tuple, object], int]:
    """(agent id → its decoded keyframes in the job's order, the new cache: exactly the job's keys, keyframes
    decoded). Raises LookupError when a keyframe sent without its images is not in ``cache``."""
    kfs: Dict[str, list] = {}
    keep: Dict[tuple, object] = {}
    decoded = 0
    for key, agent, stored in job_views:
        kf = cache.get(key)
        if kf is None:
            if stored is None:
                raise LookupError(f"keyframe {key[1]} of {key[0]!r} was sent without its images and is not held")
            kf = decode_keyframe(stored)
            decoded += 1
        keep[key] = kf
        kfs.setdefault(agent, []).append(kf)
    return kfs, keep, decoded


def _run(job: dict, cache: Dict[tuple, object], parent_pid: int) -> Tuple[RefineOutcome, Dict[tuple, object]]:
    """One job in the child: decode what it lacks, refine; returns (outcome, the new cache)."""
    from gausslite.fusion.engine import FuseEngine, FuseOutcome

    kfs, cache, decoded = _views(job["views"], cache)

    def emit(stage: str, fraction: float, message: str) -> None:
        if os.getppid() != parent_pid:  # the server is gone: nobody waits for this refinement
            os._exit(0)

    out = FuseOutcome(job["fused"], {})
    FuseEngine(job["engine_options"]).refine(out, lambda: kfs, job["iters"], job["seed"], emit,
                                             options=job["options"])
    return RefineOutcome(out.fused, out.refine_report, out.keyframes_used, decoded), cache


def serve(conn, nice: int, torch_threads: int, parent_pid: int) -> None:
    """The child's main loop (the target of the ``spawn`` process; public for it): lower its priority, load PyTorch
    and the refinement, then answer jobs on ``conn`` with ``(kind, payload, keys held)`` until the pipe closes or
    its parent ``parent_pid`` is gone. ``kind`` "done": payload (fused, report, keyframes used, decoded); "error":
    payload (exception type name, message, traceback)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C in the server's terminal: the server stops the child
    if nice > 0 and hasattr(os, "setpriority"):
        try:
            os.setpriority(os.PRIO_PROCESS, 0, max(nice, os.getpriority(os.PRIO_PROCESS, 0)))
        except OSError:
            pass
    os.environ.setdefault("OMP_NUM_THREADS", str(torch_threads))
    import torch

    torch.set_num_threads(max(1, torch_threads))
    import gausslite.fusion.refine  # noqa: F401 - loaded while the parent votes, not in the first job

    cache: Dict[tuple, object] = {}
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        try:
            outcome, cache = _run(job, cache, parent_pid)
            reply = ("done", (outcome.fused, outcome.report, outcome.keyframes_used, outcome.decoded), list(cache))
        except Exception as e:  # noqa: BLE001 - reported to the parent, the child serves the next job
            reply = ("error", (type(e).__name__, str(e), traceback.format_exc()), list(cache))
        try:
            conn.send(reply)
        except (EOFError, OSError):
            return
