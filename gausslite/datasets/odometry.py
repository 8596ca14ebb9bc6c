"""Poses from RGB-D odometry, for input without poses: a hand-held camera and no SLAM.

Each frame is registered to a keyframe with Open3D's dense RGB-D odometry (``open3d.pipelines.odometry.
compute_rgbd_odometry`` with the hybrid Jacobian: photometric and geometric terms, Park, Zhou, Koltun, ICCV 2017;
Open3D's "RGBD Odometry" tutorial), and the estimate is checked before it is kept:

- **reference**: the keyframe nearest to the frame's predicted pose (rotation angle in degrees plus translation
  scaled by ``keyframe_rot_deg / keyframe_trans_m``), among the latest ``max_keyframes``; a frame becomes a
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

Open3D (the ``open3d-cpu`` wheel of the ``mapper`` extra) is imported on first use.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from dataclasses import dataclass
from typing import List, Literal, Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from tqdm import tqdm

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame, RGBDDataset
from gausslite.datasets.common import downscale_frame
from gausslite.datasets.trajectory import rotation_angle_deg

log = logging.getLogger(__name__)

__all__ = ["OdometryConfig", "TrackResult", "RGBDOdometry", "OdometryDataset", "POSE_SOURCES", "with_pose_source"]

#: the values of ``pose_source`` (``agent.pose_source``, ``gausslite map --pose-source``, ``load_dataset``)
POSE_SOURCES = ("auto", "given", "odometry")


class OdometryConfig(BaseModel):
    """Settings of the RGB-D odometry (defaults: the measured choice on TUM fr1/rpy, ``docs/mapper.md``).

    Attributes:
        method: Open3D's Jacobian: ``hybrid`` (photometric + geometric) or ``color`` (photometric only).
        reference: what a frame registers to: ``nearest_keyframe`` (of the latest ``max_keyframes``),
            ``last_keyframe``, or ``previous_frame`` (plain frame-to-frame).
        keyframe_trans_m, keyframe_rot_deg: a frame that moved more than either from its reference becomes a keyframe.
        max_keyframes: keyframes kept for the nearest-keyframe search (the oldest is dropped first).
        motion_prior: start from the previous frame's motion (constant velocity); False: from the last good pose.
        depth_max_m: depth beyond this is ignored (metres).
        depth_diff_max_m: largest depth difference of a correspondence (Open3D's ``depth_diff_max``, metres).
        iterations: Gauss-Newton iterations per pyramid level, coarse levels last (Open3D's order).
        min_fitness: a frame whose share of valid depth pixels with a correspondence is below this fails.
        track_width: frames are tracked downscaled by the integer factor that brings their width nearest this
            (pixels; None: at the frames' own resolution). 160 tracks TUM as well as 320 does, at a third of the cost.
        max_step_m, max_step_deg: an estimate further than these from the last good pose fails (a jump).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    method: Literal["hybrid", "color"] = "hybrid"
    reference: Literal["nearest_keyframe", "last_keyframe", "previous_frame"] = "nearest_keyframe"
    keyframe_trans_m: float = Field(0.10, gt=0)
    keyframe_rot_deg: float = Field(10.0, gt=0)
    max_keyframes: int = Field(64, ge=1)
    motion_prior: bool = True
    depth_max_m: float = Field(10.0, gt=0)
    depth_diff_max_m: float = Field(0.15, gt=0)
    iterations: List[int] = Field(default_factory=lambda: [20, 10, 5], min_length=1)
    min_fitness: float = Field(0.2, ge=0, le=1)
    track_width: Optional[int] = Field(160, ge=16)
    max_step_m: float = Field(0.3, gt=0)
    max_step_deg: float = Field(30.0, gt=0)


@dataclass
class TrackResult:
    """What tracking one frame gave.

    Attributes:
        c2w: (4, 4) float64 camera-to-world pose: the estimate, or the last good pose when ``ok`` is False.
        ok: the estimate passed every check.
        reason: why it failed ("" when ``ok``).
        fitness: share of the frame's valid depth pixels with a correspondence (0..1).
        keyframe: the frame became a keyframe.
        reference: frame id of the keyframe (or frame) it was registered to; -1 for the first frame.
    """

    c2w: np.ndarray
    ok: bool
    reason: str = ""
    fitness: float = 1.0
    keyframe: bool = False
    reference: int = -1


@dataclass
class _Keyframe:
    frame_id: int
    c2w: np.ndarray
    image: object  # open3d.geometry.RGBDImage of ``frame``
    frame: Frame  # at the tracking size (for the state)


def _open3d():
    """The ``open3d`` module (imported on first use: about a second).

    Raises:
        ModuleNotFoundError: Open3D is not installed (the ``mapper`` extra brings it).
        RuntimeError: it is installed but its native library does not load (a system library missing).
    """
    try:
        import open3d  # noqa: PLC0415 - heavy, and only the odometry needs it
    except ModuleNotFoundError:
        raise
    except (ImportError, OSError) as e:
        raise RuntimeError(f"Open3D's library does not load ({e}); on Debian/Ubuntu: apt-get install libusb-1.0-0 "
                           "libgl1 libegl1 libx11-6 (scripts/setup.sh installs them)") from None
    return open3d


class RGBDOdometry:
    """Frame-by-frame RGB-D odometry against keyframes (see the module docstring).

    Args:
        config: the settings (None: the defaults).
        initial_pose: (4, 4) c2w of the first frame (None: the identity).

    Attributes:
        n_tracked, n_failed: frames tracked and frames that failed so far (the first frame counts as tracked).
        n_keyframes: keyframes taken so far.
        failed_ids: frame ids of the failed frames.
    """

    def __init__(self, config: Optional[OdometryConfig] = None, initial_pose: Optional[np.ndarray] = None) -> None:
        self.config = config or OdometryConfig()
        self.initial_pose = np.eye(4) if initial_pose is None else np.asarray(initial_pose, np.float64).copy()
        self.keyframes: List[_Keyframe] = []
        self.last_pose: Optional[np.ndarray] = None
        self.velocity = np.eye(4)
        self.n_tracked = 0
        self.n_failed = 0
        self.failed_ids: List[int] = []
        #: keyframes taken so far (including those dropped from the search)
        self.n_keyframes = 0
        self._since_good = 0  # frames lost since the last good pose
        self._lock = threading.Lock()
        self._prev: Optional[_Keyframe] = None
        o3d = _open3d()
        c = self.config
        self._option = o3d.pipelines.odometry.OdometryOption(
            iteration_number_per_pyramid_level=o3d.utility.IntVector(list(c.iterations)),
            depth_diff_max=c.depth_diff_max_m, depth_min=0.0, depth_max=c.depth_max_m)
        self._jacobian = (o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm() if c.method == "hybrid"
                          else o3d.pipelines.odometry.RGBDOdometryJacobianFromColorTerm())

    def _image(self, frame: Frame):
        """Open3D's RGB-D image of ``frame`` (intensity from the colour, depth in metres truncated at depth_max_m)."""
        o3d = _open3d()
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(frame.rgb)),
            o3d.geometry.Image(np.ascontiguousarray(frame.depth, dtype=np.float32)),
            depth_scale=1.0, depth_trunc=self.config.depth_max_m, convert_rgb_to_intensity=True)

    def _at_tracking_size(self, frame: Frame) -> Frame:
        """``frame`` downscaled by the integer factor that brings its width nearest ``track_width`` (colour by area,
        depth by the valid sample nearest each block's centre, :func:`~gausslite.datasets.common.downscale_frame`)."""
        tw = self.config.track_width
        factor = 1 if tw is None else max(1, round(frame.intrinsics.width / tw))
        return frame if factor == 1 else downscale_frame(frame, factor)

    def _add_keyframe(self, frame: Frame, c2w: np.ndarray, image) -> None:
        self.keyframes.append(_Keyframe(frame.frame_id, c2w.copy(), image, frame))
        self.n_keyframes += 1
        if len(self.keyframes) > self.config.max_keyframes:
            self.keyframes.pop(0)

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
        with self._lock:
            return self._track(frame)

    def _track(self, frame: Frame) -> TrackResult:
        frame = self._at_tracking_size(frame)
        image = self._image(frame)
        if self.last_pose is None:  # the first frame fixes the world frame
            self.last_pose = self.initial_pose.copy()
            self._add_keyframe(frame, self.last_pose, image)
            self._prev = self.keyframes[-1]
            self.n_tracked += 1
            return TrackResult(self.last_pose.copy(), True, keyframe=True)
        # the previous good frame's motion, once per frame since the last good pose (lost frames in between)
        steps = self._since_good + 1
        vel = np.linalg.matrix_power(self.velocity, steps) if self.config.motion_prior else np.eye(4)
        pred = self.last_pose @ vel
        ref = self._reference(pred)
        ok, T, info, fitness = self._register(frame, image, ref, np.linalg.inv(ref.c2w) @ pred)
        c2w = ref.c2w @ T
        reason = "" if ok else "Open3D's odometry did not converge"
        if ok and fitness < self.config.min_fitness:
            reason = f"fitness {fitness:.2f} < {self.config.min_fitness}"
        reason = reason or self._implausible(c2w, steps)
        if reason:
            return self._fail(frame, reason, fitness, ref)
        self.velocity = self._root(np.linalg.inv(self.last_pose) @ c2w, steps)
        self.last_pose, self._since_good = c2w, 0
        self.n_tracked += 1
        rel = np.linalg.inv(ref.c2w) @ c2w
        is_kf = (float(np.linalg.norm(rel[:3, 3])) > self.config.keyframe_trans_m
                 or rotation_angle_deg(rel) > self.config.keyframe_rot_deg)
        if is_kf:
            self._add_keyframe(frame, c2w, image)
        self._prev = _Keyframe(frame.frame_id, c2w.copy(), image, frame)
        return TrackResult(c2w.copy(), True, fitness=fitness, keyframe=is_kf, reference=ref.frame_id)

    def _register(self, frame: Frame, image, ref: _Keyframe, init: np.ndarray):
        """Open3D's odometry of ``image`` (source) to ``ref`` (target) from ``init`` (4, 4) T_ref_frame. Returns
        ``(success, T_ref_frame (4, 4), information (6, 6), fitness)``."""
        o3d = _open3d()
        intr = frame.intrinsics
        pin = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
        ok, T, info = o3d.pipelines.odometry.compute_rgbd_odometry(image, ref.image, pin, init, self._jacobian,
                                                                  self._option)
        valid = int(np.count_nonzero((frame.depth > 0) & (frame.depth < self.config.depth_max_m)))
        # the information matrix is the sum over correspondences of J^T J with J = [-[p]x | I]: its translation
        # block holds the number of correspondences on the diagonal
        n_corr = float(info[3, 3]) if np.size(info) == 36 else 0.0
        return bool(ok), np.asarray(T, np.float64), info, (n_corr / valid if valid else 0.0)

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
        """The tracker's state (for a mission's checkpoint): poses, motion, counters and the keyframes' images at the
        tracking size (``rgb`` (h, w, 3) uint8, ``depth`` (h, w) float32 metres, ``c2w`` (4, 4) float64)."""
        def kf(k: _Keyframe) -> dict:
            i = k.frame.intrinsics
            return {"frame_id": k.frame_id, "c2w": k.c2w.copy(), "rgb": k.frame.rgb.copy(),
                    "depth": k.frame.depth.copy(), "timestamp": k.frame.timestamp,
                    "intrinsics": [i.fx, i.fy, i.cx, i.cy, i.width, i.height]}

        with self._lock:
            return {"format": 1, "config": self.config.model_dump(), "initial_pose": self.initial_pose.copy(),
                    "last_pose": None if self.last_pose is None else self.last_pose.copy(),
                    "velocity": self.velocity.copy(), "since_good": self._since_good, "n_tracked": self.n_tracked,
                    "n_failed": self.n_failed, "failed_ids": list(self.failed_ids), "n_keyframes": self.n_keyframes,
                    "keyframes": [kf(k) for k in self.keyframes],
                    "previous": None if self._prev is None else kf(self._prev)}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s state (the settings stay this tracker's).

        Raises:
            ValueError: not a state of this format.
        """
        if not isinstance(state, dict) or state.get("format") != 1:
            raise ValueError("not an odometry state (format 1)")

        def kf(d: dict) -> _Keyframe:
            fx, fy, cx, cy, w, h = d["intrinsics"]
            f = Frame(int(d["frame_id"]), float(d["timestamp"]), d["rgb"], d["depth"], d["c2w"],
                      Intrinsics(fx, fy, cx, cy, int(w), int(h)))
            return _Keyframe(f.frame_id, np.asarray(d["c2w"], np.float64), self._image(f), f)

        with self._lock:
            self.initial_pose = np.asarray(state["initial_pose"], np.float64)
            self.last_pose = None if state["last_pose"] is None else np.asarray(state["last_pose"], np.float64)
            self.velocity = np.asarray(state["velocity"], np.float64)
            self._since_good, self.n_tracked, self.n_failed = state["since_good"], state["n_tracked"], state["n_failed"]
            self.failed_ids, self.n_keyframes = list(state["failed_ids"]), state["n_keyframes"]
            self.keyframes = [kf(d) for d in state["keyframes"]]
            self._prev = None if state["previous"] is None else kf(state["previous"])

    def summary(self) -> dict:
        """``{"tracked", "failed", "keyframes", "failed_frame_ids"}``: the counts so far."""
        return {"tracked": self.n_tracked, "failed": self.n_failed, "keyframes": self.n_keyframes,
                "failed_frame_ids": list(self.failed_ids)}


class OdometryDataset(RGBDDataset):
    """A dataset whose poses come from :class:`RGBDOdometry` run over its frames in order.

    The odometry runs once, over every frame, at the first frame read (with a progress bar); each frame then
    carries its estimate as ``c2w`` and ``pose_ok`` False when its tracking failed. Other attributes are the
    wrapped dataset's.

    Args:
        base: the dataset (its frames' colour, depth, intrinsics and timestamps are used; its poses are not).
        config: the odometry's settings.
        progress: show a progress bar while tracking.

    Attributes:
        reference_poses: (N, 4, 4) the wrapped dataset's own poses when it has them (for tracking error), else None.
        poses: (N, 4, 4) the estimates (after tracking), results: the N :class:`TrackResult`.
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
            bar.set_postfix(lost=odo.n_failed, keyframes=odo.n_keyframes)
        self.odometry, self.results = odo, results
        log.info("odometry: %d of %d frames tracked, %d lost, %d keyframes (%s)", odo.n_tracked, len(results),
                 odo.n_failed, odo.n_keyframes, self.path)
        return results

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) float64 estimated c2w poses (tracks on first use)."""
        return np.stack([r.c2w for r in self.track()])

    @property
    def pose_ok(self) -> np.ndarray:
        """(N,) bool: the frame's tracking passed its checks (tracks on first use)."""
        return np.array([r.ok for r in self.track()], dtype=bool)

    def _load(self, i: int) -> Frame:
        r = self.track()[i]
        return dataclasses.replace(self.base[i], c2w=r.c2w.copy(), pose_ok=bool(r.ok))

    def __repr__(self) -> str:
        return f"OdometryDataset({self.base!r})"



def with_pose_source(dataset: RGBDDataset, pose_source: str = "auto", config: Optional[OdometryConfig] = None,
                     progress: bool = True) -> RGBDDataset:
    """``dataset`` with the poses ``pose_source`` names: ``given`` (its own), ``odometry`` (an
    :class:`OdometryDataset` over it), or ``auto`` (its own when it has them, else odometry).

    Args:
        dataset: the dataset (``has_poses`` False when it was read without poses).
        pose_source: one of :data:`POSE_SOURCES`.
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
