"""Loop closure over an RGB-D odometry's keyframes (:class:`LoopClosing`, the part of
:class:`~gausslite.odometry.rgbd.RGBDOdometry` at ``odometry.loops``): a new keyframe's candidates (older keyframes
near it), their registrations checked against the drift the pose graph allows (:mod:`gausslite.odometry.pose_graph`),
and the pose graph optimised over the loops that pass, which moves the keyframes. It runs on the tracking thread, or on
a thread of its own (``background_loops``) so that a keyframe's registrations never hold up the next frame.
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import List, Optional

import numpy as np

from gausslite.camera import rotation_angle_deg
from gausslite.odometry.pose_graph import DepthClouds, LoopEdge, verify_registration

log = logging.getLogger("gausslite.odometry.rgbd")  # one logger for the odometry

__all__ = ["LoopClosing", "CLOUDS_KEPT"]

#: keyframe depth clouds the loop search keeps between searches, the most recently used (about 0.5 MB each at the
#: tracking size: a mission's keyframes alone would hold hundreds of megabytes); a search's candidates are the
#: keyframes near the new one, so the next searches register to the same few again
CLOUDS_KEPT = 32


class LoopClosing:
    """The loops of one odometry (its keyframes: ``frame_id``, ``c2w`` (4, 4) float64, the Open3D ``image`` and the
    tracking-size ``frame``).

    Args:
        odometry: the :class:`~gausslite.odometry.rgbd.RGBDOdometry` whose keyframes, pose graph, settings
            (``config.loop``), lock and corrections (``apply_correction``) the loops use.

    Attributes:
        queue: keyframes waiting for the loop-closing thread (None stops it). thread: that thread, once started.
    """

    def __init__(self, odometry) -> None:
        self.odometry = odometry
        self.queue: "queue.Queue" = queue.Queue()
        self.thread: Optional[threading.Thread] = None
        #: the keyframes' depth clouds, each made once for the searches that register to it (pruned in :meth:`commit`,
        #: under the lock, to the :data:`CLOUDS_KEPT` thinned clouds of loop keyframes used last; one search at a time)
        self.clouds = DepthClouds(odometry.config.depth_max_m)

    def close_loops(self, kf) -> int:
        """Look for loops from the new keyframe ``kf`` to older ones, gate them (:mod:`~gausslite.odometry.pose_graph`)
        and, when one passes, optimise the pose graph and move the keyframes, the last pose and the previous frame
        with it (the caller holds the tracker's lock). Returns the loops accepted."""
        odo = self.odometry
        if not odo.config.loop.enabled:
            return 0
        cands = self.candidates(kf)
        return self.commit(kf, self.verify(kf, cands), len(cands))

    def candidates(self, kf) -> list:
        """The keyframes a loop from ``kf`` is tried to (under the lock): ``[(keyframe, init (4, 4) T_target_kf at the
        current poses, drift bound in metres, drift bound in degrees)]``, nearest first, at most ``max_candidates``."""
        odo = self.odometry
        cfg = odo.config.loop
        ids = list(odo.graph.nodes)
        older = set(ids[:max(0, len(ids) - 1 - cfg.min_gap)])

        def near(k) -> Optional[float]:
            dist = float(np.linalg.norm(k.c2w[:3, 3] - kf.c2w[:3, 3]))
            cos = float(np.clip(k.c2w[:3, 2] @ kf.c2w[:3, 2], -1.0, 1.0))
            return dist if dist <= cfg.radius_m and np.degrees(np.arccos(cos)) <= cfg.max_angle_deg else None

        near_ids = sorted((d, k.frame_id) for k in odo.loop_keyframes.values()
                          if k.frame_id in older and (d := near(k)) is not None)[:cfg.max_candidates]
        out = []
        for _, fid in near_ids:
            target = odo.loop_keyframes[fid]
            out.append((target, np.linalg.inv(target.c2w) @ kf.c2w, *odo.graph.drift_bound(kf.frame_id, fid, cfg)))
        return out

    def verify(self, kf, cands: list) -> List[LoopEdge]:
        """The loop edges from ``kf`` that pass every gate (registrations only: no state of the tracker changes, so a
        loop-closing thread runs this without the lock)."""
        odo = self.odometry
        cfg = odo.config.loop
        odo.pin_threads()
        added = []
        for target, init, bound_m, bound_deg in cands:
            got = verify_registration(odo, kf.frame, kf.image, target, init, cfg.min_fitness, cfg, self.clouds)
            d = None if got is None else np.linalg.inv(init) @ got[0]
            if d is None or float(np.linalg.norm(d[:3, 3])) > bound_m or rotation_angle_deg(d) > bound_deg:
                continue
            added.append(LoopEdge(int(kf.frame_id), int(target.frame_id), got[0], got[2], got[3]))
        return added

    def commit(self, kf, added: List[LoopEdge], tried: int) -> int:
        """Add the verified loop edges ``added`` of ``kf`` (``tried`` candidates) to the pose graph and optimise it;
        the keyframes move when the optimisation holds (under the lock). Returns the loops accepted."""
        odo = self.odometry
        self.clouds.keep([k.frame for k in odo.loop_keyframes.values()], odo.config.loop.icp_voxel_m, CLOUDS_KEPT)
        g = odo.graph
        g.n_loop_tried += tried
        g.n_loop_rejected += tried - len(added)
        if not added:
            return 0
        g.loops.extend(added)
        new = g.optimise(odo.config.loop)
        if not new:
            g.loops = [e for e in g.loops if e not in added]
            g.n_loop_rejected += len(added)
            return 0
        odo.apply_correction(new)
        log.info("odometry: %d loop(s) closed at keyframe %d; the pose graph moved the keyframes (%d loops so far)",
                 len(added), kf.frame_id, len(g.loops))
        return len(added)

    def later(self, kf) -> None:
        """Queue ``kf`` for the loop-closing thread (started on first use; ``background_loops``)."""
        odo = self.odometry
        if not odo.config.loop.enabled:
            return
        if self.thread is None:
            self.thread = threading.Thread(target=self._worker, name="odometry-loops", daemon=True)
            self.thread.start()
        self.queue.put(kf)

    def _worker(self) -> None:
        """The loop-closing thread: candidates under the lock, registrations without it (the tracking goes on), the
        pose graph under it again. A loop's edge is a relative pose, so keyframes tracked meanwhile join the
        optimisation through their odometry edges."""
        odo = self.odometry
        while True:
            kf = self.queue.get()
            try:
                if kf is None:
                    return
                with odo.lock:
                    cands = self.candidates(kf)
                added = self.verify(kf, cands)
                with odo.lock:
                    self.commit(kf, added, len(cands))
            except Exception:  # a failed loop check must not stop the tracking: logged, the keyframe has no loop
                log.exception("odometry: loop closure at keyframe %d failed", getattr(kf, "frame_id", -1))
            finally:
                self.queue.task_done()

    def flush(self, timeout_s: Optional[float] = None) -> bool:
        """Wait until the loop-closing thread has checked every keyframe queued so far (at once without one). Returns
        False when ``timeout_s`` seconds passed first."""
        q = self.queue
        with q.all_tasks_done:
            return q.all_tasks_done.wait_for(lambda: q.unfinished_tasks == 0, timeout_s)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the loop-closing thread: keyframes still queued are dropped unchecked (the thread ends after the one
        it is checking, instead of working through a backlog after the odometry is closed, where the interpreter's
        exit would stop it inside Open3D and abort the process). Safe to call more than once."""
        if self.thread is not None and self.thread.is_alive():
            while True:
                try:
                    self.queue.get_nowait()
                except queue.Empty:
                    break
                self.queue.task_done()
            self.queue.put(None)
            self.thread.join(timeout_s)
