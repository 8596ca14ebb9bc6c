"""Poses from RGB-D odometry, for input without poses: a hand-held camera and no SLAM.

Each frame is registered to a keyframe with Open3D's dense RGB-D odometry (``open3d.t.pipelines.odometry.
rgbd_odometry_multi_scale``, the hybrid method: photometric and geometric terms, Park, Zhou, Koltun, ICCV 2017, each
under a Huber loss), and the estimate is checked before it is kept:

- **reference**: the keyframe nearest to the frame's predicted pose (rotation angle in degrees plus translation
  scaled by ``keyframe_rot_deg / keyframe_trans_m``), among the latest ``reference_keyframes_max``; a frame becomes a
  keyframe when it moved more than ``keyframe_trans_m`` or ``keyframe_rot_deg`` from its reference. A hand-held
  camera that sweeps back over a view registers against the keyframe it took there, not against a chain of
  frames, so its error does not grow with every frame (``docs/mapper.md``, "Poses from odometry", measures each
  choice).
- **size**: frames are tracked downscaled to about ``track_width`` (160) pixels wide, whatever the mapping resolution.
- **initial guess**: the previous good frame's motion (constant velocity), applied to the last good pose once per
  frame since it.
- **check**: Open3D's success flag; the fitness, the share of the frame's valid depth pixels that found a
  correspondence (the information matrix's translation block counts them); and the motion from the last good
  pose against ``max_step_m`` / ``max_step_deg`` per frame since it (an implausible jump; per frame, since many
  layouts' timestamps are frame numbers over an assumed rate). A frame that fails keeps the last
  good pose, is flagged (``TrackResult.ok``, ``Frame.pose_ok``) and counted, is logged, and is never chained: the
  next frame starts again from the last good pose.

Poses are camera-to-world (c2w, 4 × 4 float64, metres, OpenCV camera axes: x right, y down, z forward). The world
frame is the first frame's camera frame, or the pose given to it (``initial_pose``).

Open3D (the ``open3d-cpu`` wheel of the ``mapper`` extra) is imported on first use. The settings and results are
:mod:`gausslite.odometry.config`'s (re-exported here); loop closure over the keyframes is
:class:`~gausslite.odometry.loop_closing.LoopClosing`'s (``RGBDOdometry.loops``).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from dataclasses import dataclass
from typing import Callable, Dict, List, Literal, Optional, Union

import numpy as np
from tqdm import tqdm

from gausslite.camera import Intrinsics, nearest_rigid, rotation_angle_deg
from gausslite.core.frames import Frame, RGBDDataset, downscale_frame
# the settings and results live in a module of their own; their names import from here as well
from gausslite.odometry.config import POSE_SOURCES, OdometryConfig, PoseSource, TrackResult  # noqa: F401
from gausslite.odometry.loop_closing import LoopClosing
from gausslite.odometry.pose_graph import KeyframeGraph, open3d_module, relocalise, thumbnail
from gausslite.odometry.pyramid import rgbd_pyramid

log = logging.getLogger(__name__)

__all__ = ["OdometryConfig", "TrackResult", "RGBDOdometry", "OdometryDataset", "PoseSource", "POSE_SOURCES",
           "with_pose_source"]

@dataclass
class _Keyframe:
    frame_id: int
    c2w: np.ndarray
    image: object  # list of open3d.t.geometry.RGBDImage: ``frame``'s pyramid, finest first (RGBDOdometry._image)
    frame: Frame  # at the tracking size (for the state)
    thumb: Optional[np.ndarray] = None  # appearance for re-localisation (pose_graph.thumbnail)


class RGBDOdometry:
    """Frame-by-frame RGB-D odometry against keyframes (see the module docstring).

    Args:
        config: the settings (None: the defaults).
        initial_pose: (4, 4) c2w of the first frame (None: the identity).
        background_loops: loop closure runs on its own thread (a live stream: a new keyframe's loop registrations,
            tens of milliseconds each, never hold up the next frame's tracking), as ORB-SLAM's LoopClosing thread
            (Mur-Artal and Tardós, IEEE T-RO 2017, Sec. III). The corrections then come later, through ``on_correction``;
            :meth:`flush` waits for them and :meth:`close` stops the thread. False (offline, the default): each
            keyframe's loops are closed before its frame returns, so the result does not depend on timing.

    Attributes:
        n_tracked, n_failed: frames tracked and frames that failed so far (the first frame counts as tracked;
            a re-localised frame counts as tracked).
        n_keyframes: keyframes taken so far.
        n_relocalised: lost frames found again against a keyframe (:func:`~gausslite.odometry.pose_graph.relocalise`).
        failed_ids: frame ids of the failed frames.
        graph: the keyframe pose graph with its loop closures (:class:`~gausslite.odometry.pose_graph.KeyframeGraph`).
        loop_keyframes: frame id → keyframe kept with its images for loops and re-localisation.
        loops: loop closure over the keyframes (:class:`~gausslite.odometry.loop_closing.LoopClosing`).
        lock: held while a frame is tracked and while the loop-closing thread changes the pose graph.
        on_correction: called with ``{frame id: new (4, 4) c2w}`` of every keyframe after the pose graph moved them
            (from the tracking thread, or the loop-closing thread under ``background_loops``), e.g. to move the map
            with its keyframes.
    """

    def __init__(self, config: Optional[OdometryConfig] = None, initial_pose: Optional[np.ndarray] = None,
                 background_loops: bool = False) -> None:
        self.config = config or OdometryConfig()
        self.background_loops = bool(background_loops)
        self.initial_pose = np.eye(4) if initial_pose is None else np.asarray(initial_pose, np.float64).copy()
        self.keyframes: List[_Keyframe] = []
        self.last_pose: Optional[np.ndarray] = None
        self.velocity = np.eye(4)
        self.n_tracked = 0
        self.n_failed = 0
        self.failed_ids: List[int] = []
        #: keyframes taken so far (including those dropped from the search)
        self.n_keyframes = 0
        self.n_relocalised = 0
        self.graph = KeyframeGraph()
        self.loop_keyframes: Dict[int, _Keyframe] = {}
        self.on_correction: Optional[Callable[[Dict[int, np.ndarray]], None]] = None
        self._since_good = 0  # frames lost since the last good pose
        self.lock = threading.Lock()  # one frame at a time; the loop-closing thread's pose graph updates
        self.loops = LoopClosing(self)  # loop closure over the keyframes, inline or on its own thread
        self._prev: Optional[_Keyframe] = None
        o3d = open3d_module()
        c, odometry = self.config, o3d.t.pipelines.odometry
        self.pin_threads()
        self._criteria = [odometry.OdometryConvergenceCriteria(n) for n in c.iterations]
        self._methods = {"hybrid": odometry.Method.Hybrid, "color": odometry.Method.Intensity,
                         "point_to_plane": odometry.Method.PointToPlane}
        self._loss = odometry.OdometryLossParams(c.depth_diff_max_m, c.depth_huber_delta_m, c.intensity_huber_delta)

    def _image(self, frame: Frame) -> list:
        """Open3D's RGB-D images of ``frame``'s pyramid, finest first, one level per entry of ``iterations``
        (tensor geometry: colour as float32 in 0..1, depth in metres, 0 where invalid; made by
        :func:`~gausslite.odometry.pyramid.rgbd_pyramid`, which repeats exactly on any CPU, unlike Open3D's own)."""
        o3d = open3d_module()
        c = self.config
        levels = rgbd_pyramid(np.ascontiguousarray(frame.rgb, dtype=np.float32) / np.float32(255.0),
                              np.ascontiguousarray(frame.depth, dtype=np.float32), len(c.iterations),
                              2.0 * c.depth_diff_max_m)
        return [o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(o3d.core.Tensor(rgb)),
                                         o3d.t.geometry.Image(o3d.core.Tensor(depth))) for rgb, depth in levels]

    def _at_tracking_size(self, frame: Frame) -> Frame:
        """``frame`` downscaled by the integer factor that brings its width nearest ``track_width`` (colour by area,
        depth by the valid sample nearest each block's centre, :func:`~gausslite.datasets.common.downscale_frame`)."""
        tw = self.config.track_width
        factor = 1 if tw is None else max(1, round(frame.intrinsics.width / tw))
        return frame if factor == 1 else downscale_frame(frame, factor)

    def _add_keyframe(self, frame: Frame, c2w: np.ndarray, image, reference: Optional[int] = None,
                      T: Optional[np.ndarray] = None, information: Optional[np.ndarray] = None) -> _Keyframe:
        """A new keyframe: into the tracking window, the loop store and the pose graph (with its odometry edge to
        ``reference``, ``T = c2w_ref⁻¹ c2w`` measured with ``information``)."""
        kf = _Keyframe(frame.frame_id, c2w.copy(), image, frame, thumbnail(frame.rgb))
        self.keyframes.append(kf)
        self.n_keyframes += 1
        if len(self.keyframes) > self.config.reference_keyframes_max:
            self.keyframes.pop(0)
        self.loop_keyframes[int(frame.frame_id)] = kf
        if len(self.loop_keyframes) > self.config.loop.keyframe_images_max:
            self.loop_keyframes.pop(next(iter(self.loop_keyframes)))
        self.graph.add(frame.frame_id, c2w, reference, T, information)
        return kf

    def corrected(self, result: TrackResult) -> np.ndarray:
        """(4, 4) float64 c2w of a tracked frame after the pose graph's corrections so far: its anchor keyframe's
        current pose times ``result.T_anchor`` (a lost frame, with no anchor: its own ``c2w``)."""
        node = self.graph.nodes.get(int(result.anchor))
        if node is None or result.T_anchor is None:
            return result.c2w.copy()
        return nearest_rigid(node.c2w @ result.T_anchor, f"frame {result.anchor}'s corrected pose")

    def _reference(self, pred: np.ndarray) -> _Keyframe:
        """The keyframe (or previous frame) the frame predicted at ``pred`` registers to."""
        c = self.config
        if c.reference == "previous_frame":
            return self._prev
        if c.reference == "last_keyframe":
            return self.keyframes[-1]
        scale = c.keyframe_rot_deg / c.keyframe_trans_m

        def distance(k: _Keyframe) -> float:
            rel = np.linalg.inv(k.c2w) @ pred
            return rotation_angle_deg(rel) + scale * float(np.linalg.norm(rel[:3, 3]))

        return min(self.keyframes, key=distance)

    def track(self, frame: Frame) -> TrackResult:
        """Estimate the pose of the next frame of the stream (thread-safe: one frame at a time).

        Args:
            frame: the frame (``rgb`` (H, W, 3) uint8, ``depth`` (H, W) float32 metres, ``intrinsics``,
                ``timestamp`` seconds); its ``c2w`` is not read.
        Returns:
            the :class:`TrackResult` (a failed frame: ``ok`` False, ``c2w`` the last good pose).
        """
        with self.lock:
            return self._track(frame)

    def pin_threads(self) -> None:
        """Apply ``config.threads`` to Open3D's process-wide thread limit where something else in the process changed
        it since (``threads`` 0: leave it). Called before each frame's and each loop search's Open3D calls, so that
        the poses do not depend on what else the process set (:class:`OdometryConfig`'s ``threads``)."""
        n = self.config.threads
        if n:
            o3d = open3d_module()
            if o3d.utility.get_max_threads() != n:
                o3d.utility.set_max_threads(n)

    def _track(self, frame: Frame) -> TrackResult:
        self.pin_threads()
        frame = self._at_tracking_size(frame)
        image = self._image(frame)
        if self.last_pose is None:  # the first frame fixes the world frame
            self.last_pose = self.initial_pose.copy()
            self._prev = self._add_keyframe(frame, self.last_pose, image)
            self.n_tracked += 1
            return TrackResult(self.last_pose.copy(), True, keyframe=True, anchor=int(frame.frame_id),
                               T_anchor=np.eye(4))
        # the previous good frame's motion, once per frame since the last good pose (lost frames in between)
        steps = self._since_good + 1
        vel = np.linalg.matrix_power(self.velocity, steps) if self.config.motion_prior else np.eye(4)
        pred = self.last_pose @ vel
        ref = self._reference(pred)
        if self._since_good and self.config.relocalise.enabled:
            # after a loss the camera may be anywhere: only a re-localisation, with its stricter gates, finds it again
            return self._relocalise(frame, image, pred) or self._fail(frame, "not re-localised", 0.0, ref)
        ok, T, info, fitness = self.register(frame, image, ref, np.linalg.inv(ref.c2w) @ pred)
        if ok and ref.frame_id != self._prev.frame_id and (off := self._from_prediction(ref.c2w @ T, pred, steps)) > 1.0:
            ok, T, info, fitness = self._second_opinion(frame, image, pred, steps, ref, (ok, T, info, fitness), off)
        c2w = nearest_rigid(ref.c2w @ T, f"frame {frame.frame_id}'s pose")  # rigid by construction, every product
        reason = "" if ok else "Open3D's odometry did not converge"
        # after a loss the motion prior means little: the estimate must pass the re-localisation's fitness
        min_fit = self.config.min_fitness
        if self._since_good:
            min_fit = max(min_fit, self.config.relocalise.min_fitness)
        if ok and fitness < min_fit:
            reason = f"fitness {fitness:.2f} < {min_fit}"
        reason = reason or self._implausible(c2w, steps)
        if reason:
            return self._relocalise(frame, image, pred) or self._fail(frame, reason, fitness, ref)
        self.velocity = nearest_rigid(self._root(np.linalg.inv(self.last_pose) @ c2w, steps), "the motion")
        self.last_pose, self._since_good = c2w, 0
        self.n_tracked += 1
        rel = np.linalg.inv(ref.c2w) @ c2w
        is_kf = (float(np.linalg.norm(rel[:3, 3])) > self.config.keyframe_trans_m
                 or rotation_angle_deg(rel) > self.config.keyframe_rot_deg)
        out = TrackResult(c2w.copy(), True, fitness=fitness, keyframe=is_kf, reference=ref.frame_id,
                          anchor=ref.frame_id, T_anchor=T.copy())
        if is_kf:
            self._prev = self._add_keyframe(frame, c2w, image, ref.frame_id, T, info)
            out.anchor, out.T_anchor = int(frame.frame_id), np.eye(4)
            if self.background_loops:
                self.loops.later(self._prev)
            else:
                self.loops.close_loops(self._prev)
                out.c2w = self.last_pose.copy()  # the pose graph may have moved it
        else:
            self._prev = _Keyframe(frame.frame_id, c2w.copy(), image, frame)
        return out

    def flush(self, timeout_s: Optional[float] = None) -> bool:
        """Wait until the loop-closing thread has checked every keyframe queued so far (``background_loops``; returns
        at once otherwise). Returns False when ``timeout_s`` seconds passed first."""
        return self.loops.flush(timeout_s)

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the loop-closing thread (keyframes still queued are not checked). Safe to call more than once."""
        self.loops.stop(timeout_s)

    def apply_correction(self, new: Dict[int, np.ndarray]) -> None:
        """Move the stored keyframes to the pose graph's ``new`` poses, and the last pose and previous frame with
        the newest keyframe (they are the newest keyframe, or tracked against it)."""
        newest = next(reversed(self.graph.nodes))
        old_newest = self.loop_keyframes[newest].c2w.copy()
        for fid, c2w in new.items():
            if fid in self.loop_keyframes:
                self.loop_keyframes[fid].c2w = c2w.copy()
        delta = new[newest] @ np.linalg.inv(old_newest)
        self.last_pose = nearest_rigid(delta @ self.last_pose, "the last pose")
        if self._prev is not None and self._prev.frame_id not in self.loop_keyframes:
            self._prev.c2w = nearest_rigid(delta @ self._prev.c2w, "the previous frame's pose")
        if self.on_correction is not None:
            self.on_correction({fid: c2w.copy() for fid, c2w in new.items()})

    def _relocalise(self, frame: Frame, image, pred: np.ndarray) -> Optional[TrackResult]:
        """A lost frame found again against the keyframes (:func:`~gausslite.odometry.pose_graph.relocalise`, from
        ``pred`` (4, 4), the pose the motion predicts), as a tracked frame, or None."""
        cfg = self.config.relocalise
        if not cfg.enabled or self._since_good % cfg.every != 0:
            return None
        got = relocalise(self, frame, image, pred, cfg)
        if got is None:
            return None
        c2w, fid, fitness = got
        c2w = nearest_rigid(c2w, f"frame {frame.frame_id}'s re-localised pose")
        lost = self._since_good
        self.velocity, self.last_pose, self._since_good = np.eye(4), c2w, 0
        self.n_tracked += 1
        self.n_relocalised += 1
        self._prev = _Keyframe(frame.frame_id, c2w.copy(), image, frame)
        log.info("odometry: frame %d re-localised against keyframe %d (fitness %.2f) after %d lost frame(s)",
                 frame.frame_id, fid, fitness, lost)
        kf = self.loop_keyframes[fid]
        return TrackResult(c2w.copy(), True, fitness=fitness, reference=fid, anchor=fid,
                           T_anchor=np.linalg.inv(kf.c2w) @ c2w, relocalised=True)

    def register(self, frame: Frame, image, ref, init: np.ndarray, method: Optional[str] = None):
        """Open3D's odometry of ``frame`` (at the tracking size; ``image`` its Open3D RGB-D pyramid, :meth:`_image`) to ``ref`` (a
        keyframe: ``frame``, ``image``) from ``init`` (4, 4) T_ref_frame, with the residuals ``method``
        (:class:`OdometryConfig`'s ``method`` values; None: the configured one).

        Returns:
            ``(success, T_ref_frame (4, 4) float64, information (6, 6), fitness)``: fitness is the share of the
            frame's valid depth pixels with a correspondence.
        """
        o3d = open3d_module()
        odometry, c, intr = o3d.t.pipelines.odometry, self.config, frame.intrinsics
        K = np.array([[intr.fx, 0.0, intr.cx], [0.0, intr.fy, intr.cy], [0.0, 0.0, 1.0]])
        T_l = np.asarray(init, np.float64)
        try:
            # coarse to fine, one level per call on the pyramid of _image (Open3D's multi-scale loop, level by level:
            # its own pyramid does not repeat on every CPU, gausslite.odometry.pyramid)
            n = len(self._criteria)
            for level in reversed(range(n)):  # level 0 is the finest; the criteria are the coarsest first
                K_l = K / 2.0 ** level
                K_l[2, 2] = 1.0
                result = odometry.rgbd_odometry_multi_scale(
                    image[level], ref.image[level], o3d.core.Tensor(K_l), o3d.core.Tensor(T_l), 1.0, c.depth_max_m,
                    [self._criteria[n - 1 - level]], self._methods[method or c.method], self._loss)
                T_l = result.transformation.numpy().astype(np.float64)
        except RuntimeError as e:  # Open3D raises when a level has too few correspondences to solve
            log.debug("frame %s: Open3D's odometry failed: %s", frame.frame_id, e)
            return False, np.asarray(init, np.float64), np.zeros((6, 6)), 0.0
        K = o3d.core.Tensor(K)
        ok, T = result.fitness > 0, result.transformation.numpy().astype(np.float64)
        if not np.all(np.isfinite(T)):
            return False, np.asarray(init, np.float64), np.zeros((6, 6)), 0.0
        # Open3D solves each level in float32: its rotation is orthonormal to about 1e-7, and chained products of such
        # registrations drift off SO(3) unless projected back
        T = nearest_rigid(T, f"frame {frame.frame_id}'s registration")
        info = odometry.compute_odometry_information_matrix(image[0].depth, ref.image[0].depth, K, result.transformation,
                                                            c.depth_diff_max_m, 1.0, c.depth_max_m).numpy()
        valid = int(np.count_nonzero((frame.depth > 0) & (frame.depth < c.depth_max_m)))
        # the information matrix is the sum over correspondences of J^T J with J = [-[p]x | I]: its translation
        # block holds the number of correspondences on the diagonal
        return bool(ok), T, info, (float(info[3, 3]) / valid if valid else 0.0)

    def _from_prediction(self, c2w: np.ndarray, pred: np.ndarray, steps: int = 1) -> float:
        """How far ``c2w`` lies from the motion's prediction ``pred``, in units of the prediction check's bounds
        (``prediction_check_m`` / ``prediction_check_deg`` per frame since the last good pose): above 1 is off it."""
        c = self.config
        d = np.linalg.inv(pred) @ c2w
        return max(float(np.linalg.norm(d[:3, 3])) / c.prediction_check_m,
                   rotation_angle_deg(d) / c.prediction_check_deg) / steps

    def _second_opinion(self, frame: Frame, image, pred: np.ndarray, steps: int, ref: _Keyframe, got: tuple,
                        off: float) -> tuple:
        """The frame registered again, to the previous good frame, after its registration to the keyframe ``ref``
        (``got``: :meth:`register`'s result) landed ``off`` (:meth:`_from_prediction`) from the motion's prediction
        ``pred``: a registration to a keyframe far back in time can converge to a wrong pose that passes the fitness
        check, and the previous frame is the nearest in time. The second is kept when it passes the fitness check,
        lands within the check's bounds of the prediction (``steps`` frames since the last good pose) and nearer it
        than the first. Returns :meth:`register`'s result, relative to ``ref``, of the registration kept."""
        prev = self._prev
        alt = self.register(frame, image, prev, np.linalg.inv(prev.c2w) @ pred)
        if not alt[0] or alt[3] < self.config.min_fitness:
            return got
        c2w = prev.c2w @ alt[1]
        alt_off = self._from_prediction(c2w, pred, steps)
        if alt_off > 1.0 or alt_off >= off:  # the second must agree with the motion
            return got
        log.debug("odometry: frame %d kept its registration to the previous frame %d: keyframe %d's lands further "
                  "from the motion's prediction", frame.frame_id, prev.frame_id, ref.frame_id)
        return True, nearest_rigid(np.linalg.inv(ref.c2w) @ c2w, "a registration"), alt[2], alt[3]

    @staticmethod
    def _root(T: np.ndarray, steps: int) -> np.ndarray:
        """The per-frame motion of ``T`` (4, 4) made over ``steps`` frames (its ``steps``-th root on SE(3))."""
        if steps == 1:
            return T
        # lazy: SciPy's rotation is only needed after a lost frame
        from scipy.spatial.transform import Rotation

        out = np.eye(4)
        out[:3, :3] = Rotation.from_rotvec(Rotation.from_matrix(T[:3, :3]).as_rotvec() / steps).as_matrix()
        out[:3, 3] = T[:3, 3] / steps
        return out

    def _implausible(self, c2w: np.ndarray, steps: int = 1) -> str:
        """Why the motion from the last good pose to ``c2w``, ``steps`` frames later, is implausible, or ""."""
        c = self.config
        if not np.all(np.isfinite(c2w)):
            return "a non-finite pose"
        rel = np.linalg.inv(self.last_pose) @ c2w
        step, turn = float(np.linalg.norm(rel[:3, 3])), rotation_angle_deg(rel)
        if step > c.max_step_m * steps:
            return f"a jump of {step:.2f} m > {c.max_step_m * steps:g} m"
        if turn > c.max_step_deg * steps:
            return f"a turn of {turn:.0f} deg > {c.max_step_deg * steps:g} deg"
        return ""

    def _fail(self, frame: Frame, reason: str, fitness: float, ref: _Keyframe) -> TrackResult:
        self.n_failed += 1
        self._since_good += 1
        self.failed_ids.append(int(frame.frame_id))
        log.warning("odometry: frame %d lost (%s); it keeps the last good pose and is not mapped (%d lost so far)",
                    frame.frame_id, reason, self.n_failed)
        return TrackResult(self.last_pose.copy(), False, reason, fitness, False, ref.frame_id)

    def state_dict(self) -> dict:
        """The tracker's state (for a mission's checkpoint): poses, motion, counters, the pose graph, and the stored
        keyframes' images at the tracking size (``rgb`` (h, w, 3) uint8, ``depth`` (h, w) float32 metres, ``c2w``
        (4, 4) float64)."""
        with self.lock:
            g = self.graph
            return {"format": 2, "config": self.config.model_dump(), "initial_pose": self.initial_pose.copy(),
                    "last_pose": None if self.last_pose is None else self.last_pose.copy(),
                    "velocity": self.velocity.copy(), "since_good": self._since_good, "n_tracked": self.n_tracked,
                    "n_failed": self.n_failed, "failed_ids": list(self.failed_ids), "n_keyframes": self.n_keyframes,
                    "n_relocalised": self.n_relocalised,
                    "stored": [_keyframe_state(k) for k in self.loop_keyframes.values()],
                    "window": [k.frame_id for k in self.keyframes],
                    "previous": None if self._prev is None else _keyframe_state(self._prev),
                    # the previous frame is a keyframe itself (one object, moved with it by a loop closure)
                    "previous_is_keyframe": self._prev is not None and self.loop_keyframes.get(
                        self._prev.frame_id) is self._prev,
                    "graph": {"nodes": [(n.frame_id, n.c2w.copy(), n.path_m) for n in g.nodes.values()],
                              "odometry_edges": list(g.odometry_edges), "loops": list(g.loops),
                              "counts": [g.n_loop_tried, g.n_loop_rejected, g.n_optimisations]}}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s state (the settings stay this tracker's); a state of the format before the
        pose graph (1) restores its keyframes with an empty graph.

        Raises:
            ValueError: not a state of either format.
        """
        if not isinstance(state, dict) or state.get("format") not in (1, 2):
            raise ValueError("not an odometry state (format 1 or 2)")
        with self.lock:
            self.initial_pose = np.asarray(state["initial_pose"], np.float64)
            self.last_pose = None if state["last_pose"] is None else np.asarray(state["last_pose"], np.float64)
            self.velocity = np.asarray(state["velocity"], np.float64)
            self._since_good, self.n_tracked, self.n_failed = state["since_good"], state["n_tracked"], state["n_failed"]
            self.failed_ids, self.n_keyframes = list(state["failed_ids"]), state["n_keyframes"]
            self.n_relocalised = int(state.get("n_relocalised", 0))
            stored = [self._keyframe_of(d) for d in state.get("stored", state.get("keyframes", []))]
            self.loop_keyframes = {k.frame_id: k for k in stored}
            window = state.get("window", [k.frame_id for k in stored])
            self.keyframes = [self.loop_keyframes[i] for i in window if i in self.loop_keyframes]
            prev = state["previous"]
            shared = prev is not None and state.get("previous_is_keyframe") and prev["frame_id"] in self.loop_keyframes
            self._prev = (None if prev is None else self.loop_keyframes[prev["frame_id"]] if shared
                          else self._keyframe_of(prev))
            self.graph = KeyframeGraph()
            g = state.get("graph")
            if g is None:  # format 1: the keyframes alone, as graph nodes without edges
                for k in stored:
                    self.graph.add(k.frame_id, k.c2w)
                return
            for fid, c2w, path in g["nodes"]:
                self.graph.add(fid, c2w)
                self.graph.nodes[int(fid)].path_m = float(path)
            self.graph.odometry_edges, self.graph.loops = list(g["odometry_edges"]), list(g["loops"])
            self.graph.n_loop_tried, self.graph.n_loop_rejected, self.graph.n_optimisations = g["counts"]

    def _keyframe_of(self, d: dict) -> _Keyframe:
        """A keyframe from :func:`_keyframe_state`'s dict (its Open3D image and thumbnail made anew)."""
        fx, fy, cx, cy, w, h = d["intrinsics"]
        f = Frame(int(d["frame_id"]), float(d["timestamp"]), d["rgb"], d["depth"], d["c2w"],
                  Intrinsics(fx, fy, cx, cy, int(w), int(h)))
        return _Keyframe(f.frame_id, np.asarray(d["c2w"], np.float64), self._image(f), f, thumbnail(f.rgb))

    def summary(self) -> dict:
        """``{"tracked", "failed", "keyframes", "failed_frame_ids", "relocalised", "loops", "loop_candidates",
        "loop_rejected", "optimisations"}``: the counts so far."""
        g = self.graph.summary()
        return {"tracked": self.n_tracked, "failed": self.n_failed, "keyframes": self.n_keyframes,
                "failed_frame_ids": list(self.failed_ids), "relocalised": self.n_relocalised, "loops": g["loops"],
                "loop_candidates": g["loop_candidates"], "loop_rejected": g["loop_rejected"],
                "optimisations": g["optimisations"]}


def _keyframe_state(k: _Keyframe) -> dict:
    """A keyframe as plain arrays (for a checkpoint): its id, pose, tracking-size images, timestamp, intrinsics."""
    i = k.frame.intrinsics
    return {"frame_id": k.frame_id, "c2w": k.c2w.copy(), "rgb": k.frame.rgb.copy(), "depth": k.frame.depth.copy(),
            "timestamp": k.frame.timestamp, "intrinsics": [i.fx, i.fy, i.cx, i.cy, i.width, i.height]}


class OdometryDataset(RGBDDataset):
    """A dataset whose poses come from :class:`RGBDOdometry` run over its frames in order.

    The odometry runs once, over every frame, at the first frame read (with a progress bar); each frame then
    carries its pose after the pose graph's corrections over the whole sequence (:meth:`RGBDOdometry.corrected`: an
    offline map is made after every loop is closed) as ``c2w``, and ``pose_ok`` False when its tracking failed. Other
    attributes are the wrapped dataset's.

    Args:
        base: the dataset (its frames' colour, depth, intrinsics and timestamps are used; its poses are not).
        config: the odometry's settings.
        progress: show a progress bar while tracking.

    Attributes:
        reference_poses: (N, 4, 4) the wrapped dataset's own poses when it has them (for tracking error), else None.
        poses: (N, 4, 4) the corrected estimates (after tracking), online_poses: (N, 4, 4) the estimates as each frame
            was tracked, before later loop closures; results: the N :class:`TrackResult`.
    """

    has_poses = True

    def __init__(self, base: RGBDDataset, config: Optional[OdometryConfig] = None, progress: bool = True) -> None:
        self.base = base
        self.config = config or OdometryConfig()
        self.progress = progress
        self.path = base.path
        self.name = base.name
        self.intrinsics = base.intrinsics
        self.annotations = base.annotations
        self.reference_poses = getattr(base, "poses", None) if getattr(base, "has_poses", True) else None
        self.results: Optional[List[TrackResult]] = None
        self._corrected: List[np.ndarray] = []
        self.odometry: Optional[RGBDOdometry] = None

    def __getattr__(self, name):  # the wrapped dataset's other attributes (frame_ids, timestamps, ...)
        if name == "base":
            raise AttributeError(name)
        return getattr(self.base, name)

    def __len__(self) -> int:
        """Number of frames (the wrapped dataset's)."""
        return len(self.base)

    def track(self) -> List[TrackResult]:
        """Run the odometry over every frame (once); returns the results, one per frame."""
        if self.results is not None:
            return self.results
        init = self.reference_poses[0] if self.reference_poses is not None and len(self.reference_poses) else None
        odo = RGBDOdometry(self.config, initial_pose=init)
        results = []
        bar = tqdm(range(len(self.base)), desc="odometry", unit="frame", disable=not self.progress)
        for i in bar:
            results.append(odo.track(self.base[i]))
            bar.set_postfix(lost=odo.n_failed, keyframes=odo.n_keyframes, loops=len(odo.graph.loops))
        self._corrected = [odo.corrected(r) for r in results]
        self.odometry, self.results = odo, results
        log.info("odometry: %d of %d frames tracked, %d lost, %d re-localised, %d keyframes, %d loops closed (%s)",
                 odo.n_tracked, len(results), odo.n_failed, odo.n_relocalised, odo.n_keyframes,
                 len(odo.graph.loops), self.path)
        return results

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) float64 estimated c2w poses after the pose graph's corrections (tracks on first use)."""
        self.track()
        return np.stack(self._corrected)

    @property
    def online_poses(self) -> np.ndarray:
        """(N, 4, 4) float64 c2w poses as each frame was tracked, before later loop closures (tracks on first use)."""
        return np.stack([r.c2w for r in self.track()])

    @property
    def pose_ok(self) -> np.ndarray:
        """(N,) bool: the frame's tracking passed its checks (tracks on first use)."""
        return np.array([r.ok for r in self.track()], dtype=bool)

    def _load(self, i: int) -> Frame:
        r = self.track()[i]
        return dataclasses.replace(self.base[i], c2w=self._corrected[i].copy(), pose_ok=bool(r.ok))

    def __repr__(self) -> str:
        return f"OdometryDataset({self.base!r})"



def with_pose_source(dataset: RGBDDataset, pose_source: Union[PoseSource, Literal["auto"]] = "auto",
                     config: Optional[OdometryConfig] = None, progress: bool = True) -> RGBDDataset:
    """``dataset`` with the poses ``pose_source`` names: ``given`` (its own), ``odometry`` (an
    :class:`OdometryDataset` over it), or ``auto`` (its own when it has them, else odometry).

    Args:
        dataset: the dataset (``has_poses`` False when it was read without poses).
        pose_source: one of :data:`POSE_SOURCES` (a :data:`PoseSource` or ``auto``).
        config: the odometry's settings.
        progress: the odometry shows a progress bar.
    Returns:
        the dataset, or the odometry over it.
    Raises:
        ValueError: an unknown ``pose_source``, or ``given`` for a dataset without poses.
    """
    if pose_source not in POSE_SOURCES:
        raise ValueError(f"pose_source must be one of {', '.join(POSE_SOURCES)}, got {pose_source!r}")
    has = bool(getattr(dataset, "has_poses", True))
    if pose_source == "given" and not has:
        raise ValueError(f"{dataset.path}: pose_source 'given', but the dataset has no poses "
                         f"({getattr(dataset, 'missing_poses', 'no pose file')} not found); use pose_source 'odometry'")
    if pose_source == "odometry" or not has:
        return OdometryDataset(dataset, config, progress=progress)
    return dataset
