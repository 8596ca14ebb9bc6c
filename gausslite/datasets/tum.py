"""TUM RGB-D benchmark sequences (Sturm et al., IROS 2012) in their original layout.

Layout (the TUM RGB-D file-format page)::

    rgb.txt          "timestamp filename" per line, '#' header lines
    depth.txt        "timestamp filename" per line, 16-bit PNG, depth_m = value / 5000, 0 = no measurement
    groundtruth.txt  "timestamp tx ty tz qx qy qz qw": camera-to-world (T_wc) of the optical centre,
                     Hamilton quaternion, scalar last; 100 Hz motion capture

Association: every colour frame takes the depth frame and the groundtruth sample with the nearest
timestamp, provided the gap is at most ``max_depth_dt`` / ``max_pose_dt`` seconds (default 0.02 s each,
as TUM's ``associate.py`` default); frames without a match are dropped with a logged warning. Matching
is nearest-neighbour per colour frame (a depth frame may serve two colour frames). With
``interpolate_poses=True`` the pose is linearly/slerp-interpolated between the groundtruth samples that
bracket the colour timestamp (the frame is still dropped when the nearest sample is further than
``max_pose_dt``).

Depth/colour time offset: TUM's Kinect streams are not synchronised; the associated depth frame was
taken up to ``max_depth_dt`` before or after the colour frame (fr1/rpy: median 7.7 ms, 90th percentile
13 ms, at a median 67 deg/s of rotation, i.e. 0.5-0.9 deg, 2-4 pixels at 320x240 between depth and
colour edges). With ``align_depth_time=True`` (the hand-held profile's default) each depth image is
re-projected (z-buffered, :func:`~gausslite.datasets.registration.register_depth`) from the camera pose
at its own timestamp into the colour camera at the colour timestamp, both poses interpolated from the
groundtruth, as a depth→colour extrinsic ``T_color_depth = T_wc(t_colour)^-1 T_wc(t_depth)``.

Without ``groundtruth.txt`` the sequence has no poses (``has_poses`` False; odometry estimates them,
:mod:`gausslite.odometry.rgbd`). A camera file beside ``rgb.txt`` (``camera.yaml`` / ``camera.json``,
:mod:`gausslite.datasets.camera_file`) overrides the camera below: its size, intrinsics, ``depth_scale`` and
distortion.

Intrinsics: TUM's published pinhole values chosen from the sequence name (folder name, else the
``# file: '...bag'`` header of ``rgb.txt``): freiburg1/fr1 517.3 516.5 318.6 255.3, freiburg2/fr2 520.9
521.0 325.1 249.7, freiburg3/fr3 535.4 539.2 320.1 247.6, otherwise the ROS default 525 525 319.5 239.5;
all at 640x480. **Images are not undistorted by default** (as most GS-SLAM loaders do); pass
``undistort=True`` to undistort colour (bilinear) and depth (nearest) with the published Freiburg
distortion coefficients (fr3 and the default are distortion-free). Undistortion maps to a new
pinhole camera chosen with OpenCV's ``getOptimalNewCameraMatrix(alpha=0)`` so that every output pixel
is valid (fr1: fx 546.75, fy 543.09, cx 320.08, cy 251.85 at 640x480); ``intrinsics`` and
``native_intrinsics`` then describe the undistorted images, ``raw_intrinsics`` the files on disk.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path
from typing import List, Optional, Sequence, Tuple, Union

import cv2
import numpy as np

from gausslite.camera import Intrinsics, check_rigid
from gausslite.datasets.annotations import load_annotations
from gausslite.datasets.camera_file import find_camera_file, read_camera_file
from gausslite.datasets.registration import DepthCamera
from gausslite.datasets.common import PosedImageDataset, select_indices
from gausslite.ros.transforms import quat_to_rot, slerp

log = logging.getLogger(__name__)

__all__ = [
    "TUMDataset",
    "TUM_INTRINSICS",
    "TUM_DISTORTION",
    "freiburg_id",
    "read_file_list",
    "read_groundtruth",
    "quat_to_rot",
    "associate_nearest",
]

#: Published TUM RGB-D colour intrinsics (fx, fy, cx, cy) at 640x480; key None = ROS default.
TUM_INTRINSICS = {
    1: (517.3, 516.5, 318.6, 255.3),
    2: (520.9, 521.0, 325.1, 249.7),
    3: (535.4, 539.2, 320.1, 247.6),
    None: (525.0, 525.0, 319.5, 239.5),
}
#: Published OpenCV distortion (k1, k2, p1, p2, k3) of the colour cameras.
TUM_DISTORTION = {
    1: (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    2: (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    3: (0.0, 0.0, 0.0, 0.0, 0.0),
    None: (0.0, 0.0, 0.0, 0.0, 0.0),
}
TUM_SIZE = (640, 480)

_FR_RE = re.compile(r"(?:freiburg|(?<![a-z])fr)_?([123])(?!\d)")


def freiburg_id(name: str) -> Optional[int]:
    """Freiburg camera number (1, 2, 3) named in ``name`` ("freiburg1", "fr2", ...), else None."""
    m = _FR_RE.search(name.lower())
    return int(m.group(1)) if m else None


def _data_lines(path: Path):
    if not path.is_file():
        raise FileNotFoundError(f"TUM file not found: {path}")
    with open(path, "r", encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, start=1):
            s = line.strip()
            if s and not s.startswith("#"):
                yield lineno, s


def read_file_list(path: Path) -> Tuple[np.ndarray, List[str]]:
    """Parse ``rgb.txt`` / ``depth.txt`` ("timestamp filename" lines, '#' comments).

    Returns:
        ``(timestamps (N,) float64 seconds, relative filenames)`` in file order.

    Raises:
        FileNotFoundError: missing file. ValueError: malformed line (message names file and line).
    """
    path = Path(path)
    ts: List[float] = []
    names: List[str] = []
    for lineno, s in _data_lines(path):
        parts = s.split()
        if len(parts) != 2:
            raise ValueError(f"{path}:{lineno}: expected 'timestamp filename', got {s!r}")
        try:
            t = float(parts[0])
        except ValueError:
            raise ValueError(f"{path}:{lineno}: bad timestamp {parts[0]!r}") from None
        if not math.isfinite(t):
            raise ValueError(f"{path}:{lineno}: bad timestamp {parts[0]!r}")
        ts.append(t)
        names.append(parts[1])
    return np.asarray(ts, dtype=np.float64), names


def read_groundtruth(path: Path) -> Tuple[np.ndarray, np.ndarray, np.ndarray, List[int]]:
    """Parse ``groundtruth.txt`` ("timestamp tx ty tz qx qy qz qw", '#' comments).

    Returns:
        ``(timestamps (N,), translations (N, 3), unit quaternions (N, 4) xyzw, line numbers)``, sorted
        by timestamp.

    Raises:
        FileNotFoundError: missing file. ValueError: malformed line, NaN values or a zero quaternion
        (message names file and line), or no poses.
    """
    path = Path(path)
    rows, lines = [], []
    for lineno, s in _data_lines(path):
        parts = s.split()
        if len(parts) != 8:
            raise ValueError(f"{path}:{lineno}: expected 'timestamp tx ty tz qx qy qz qw', got {len(parts)} fields")
        try:
            r = [float(p) for p in parts]
        except ValueError:
            raise ValueError(f"{path}:{lineno}: non-numeric value") from None
        if not all(math.isfinite(v) for v in r):
            raise ValueError(f"{path}:{lineno}: NaN or infinite value in pose")
        qn = math.sqrt(sum(v * v for v in r[4:]))
        if qn < 1e-6:
            raise ValueError(f"{path}:{lineno}: zero quaternion")
        rows.append(r[:4] + [v / qn for v in r[4:]])
        lines.append(lineno)
    if not rows:
        raise ValueError(f"{path}: no poses")
    a = np.asarray(rows, dtype=np.float64)
    order = np.argsort(a[:, 0], kind="stable")
    a = a[order]
    return a[:, 0], a[:, 1:4], a[:, 4:8], [lines[i] for i in order]


def associate_nearest(query: np.ndarray, ref_sorted: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """For each query time, the index of the nearest reference time and the absolute gap.

    Args:
        query: (N,) seconds. ref_sorted: (M,) seconds, ascending, M >= 1.

    Returns:
        ``(indices (N,) int64, gaps (N,) float64 seconds)``.
    """
    query = np.asarray(query, dtype=np.float64)
    m = len(ref_sorted)
    if m == 0:
        raise ValueError("no reference timestamps to associate with")
    if m == 1:
        return np.zeros(len(query), dtype=np.int64), np.abs(query - ref_sorted[0])
    j = np.clip(np.searchsorted(ref_sorted, query), 1, m - 1)
    left = ref_sorted[j - 1]
    right = ref_sorted[j]
    use_left = np.abs(query - left) <= np.abs(right - query)
    idx = np.where(use_left, j - 1, j).astype(np.int64)
    return idx, np.abs(ref_sorted[idx] - query)


class TUMDataset(PosedImageDataset):
    """TUM RGB-D sequence (see the module docstring for association, intrinsics and distortion).

    Args:
        path: sequence folder holding ``rgb.txt``, ``depth.txt``, ``groundtruth.txt``.
        downscale: factor >= 1 (int or float) for images and intrinsics.
        max_frames: keep at most this many associated frames (after ``stride``).
        stride: keep every ``stride``-th associated frame.
        intrinsics: override: an ``Intrinsics`` (its size must match the images) or ``(fx, fy, cx, cy)``
            at 640x480. Default: chosen from the sequence name.
        depth_scale: raw depth units per metre (5000 for TUM).
        max_depth_dt, max_pose_dt: maximum |colour - depth| and |colour - groundtruth| gaps (seconds).
        interpolate_poses: interpolate between the bracketing groundtruth samples.
        align_depth_time: re-project each depth image from the pose at its own timestamp to the colour
            frame's (see the module docstring); composes with ``depth_camera``.
        undistort: undistort images with ``distortion`` (default: the published Freiburg coefficients)
            onto the alpha=0 optimal new pinhole camera (see the module docstring).
        distortion: override ``(k1, k2, p1, p2, k3)``.
        depth_camera: ``DepthCamera`` when the depth files are not registered to colour (registered into
            the raw colour camera, with its distortion, before undistortion).

    Attributes: see :class:`~gausslite.datasets.common.PosedImageDataset`; ``freiburg`` (1/2/3/None),
    ``distortion`` (5-tuple), ``n_dropped`` (colour frames without depth or pose match);
    ``frame_ids`` are indices into ``rgb.txt``; timestamps are the colour timestamps.

    Raises:
        FileNotFoundError: missing folder, list files or listed image files.
        ValueError: malformed list files (file:line), no associated frames, non-rigid poses, bad
            annotations or arguments. Frame access raises for unreadable images or sizes that
            disagree with the intrinsics.
    """

    def __init__(
        self,
        path: Union[str, Path],
        downscale: Union[int, float] = 1,
        max_frames: Optional[int] = None,
        stride: int = 1,
        intrinsics: Optional[Union[Intrinsics, Sequence[float]]] = None,
        depth_scale: float = 5000.0,
        max_depth_dt: float = 0.02,
        max_pose_dt: float = 0.02,
        interpolate_poses: bool = False,
        align_depth_time: bool = False,
        undistort: bool = False,
        distortion: Optional[Sequence[float]] = None,
        depth_camera: Optional[DepthCamera] = None,
    ) -> None:
        seq = Path(path)
        if not seq.is_dir():
            raise FileNotFoundError(f"TUM sequence folder not found: {seq}")
        for v, nm in ((max_depth_dt, "max_depth_dt"), (max_pose_dt, "max_pose_dt")):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{nm} must be a finite number >= 0, got {v!r}")
        rgb_file = seq / "rgb.txt"
        rgb_ts, rgb_names = read_file_list(rgb_file)
        depth_ts, depth_names = read_file_list(seq / "depth.txt")
        # no groundtruth.txt: a sequence without poses (odometry estimates them, gausslite.odometry.rgbd); the
        # pose interpolation and the depth time alignment need the ground truth and are off
        gt = read_groundtruth(seq / "groundtruth.txt") if (seq / "groundtruth.txt").exists() else None
        #: the pose file a sequence without poses lacks (for the error of pose_source "given")
        self.missing_poses = str(seq / "groundtruth.txt")
        if gt is None and (interpolate_poses or align_depth_time):
            log.info("%s: no groundtruth.txt: poses from odometry, without pose interpolation or depth time "
                     "alignment", seq)
            interpolate_poses = align_depth_time = False
        cam = find_camera_file(seq)
        #: the camera file beside the sequence (None: the Freiburg camera), which overrides the camera and depth / 5000
        self.camera = read_camera_file(cam) if cam is not None else None
        if self.camera is not None:
            depth_scale = self.camera.depth_scale
            distortion = self.camera.distortion if distortion is None else distortion
        if len(rgb_ts) == 0:
            raise ValueError(f"{rgb_file}: no frames listed")
        if len(depth_ts) == 0:
            raise ValueError(f"{seq / 'depth.txt'}: no frames listed")
        intr = self._setup_camera(seq, intrinsics, distortion, undistort)
        keep, d_idx, g_idx = self._associate(seq, rgb_ts, depth_ts, None if gt is None else gt[0], max_depth_dt,
                                             max_pose_dt)
        sel = [int(keep[k]) for k in select_indices(len(keep), stride, max_frames)]
        poses = None if gt is None else [self._gt_pose(seq, gt, rgb_ts[i], int(g_idx[i]), interpolate_poses)
                                         for i in sel]
        #: per selected frame, T_color_depth of the depth/colour time offset (identity when not aligned)
        self._time_extrinsics: Optional[List[np.ndarray]] = None
        self.align_depth_time = bool(align_depth_time)
        if self.align_depth_time:
            self._time_extrinsics = self._depth_time_extrinsics(seq, gt, sel, rgb_ts, depth_ts[d_idx[sel]], g_idx,
                                                                poses, interpolate_poses)
        rgb_paths = [seq / rgb_names[i] for i in sel]
        depth_paths = [seq / depth_names[int(d_idx[i])] for i in sel]
        for lst, listing in ((rgb_paths, "rgb.txt"), (depth_paths, "depth.txt")):
            for p in lst:
                if not p.is_file():
                    raise FileNotFoundError(f"image listed in {seq / listing} not found: {p}")
        super().__init__(
            path=seq,
            name=seq.name,
            rgb_paths=rgb_paths,
            depth_paths=depth_paths,
            poses=None if poses is None else np.stack(poses),
            timestamps=rgb_ts[sel],
            frame_ids=sel,
            frame_names=[Path(rgb_names[i]).stem for i in sel],
            native_intrinsics=intr,
            depth_scale=depth_scale,
            downscale=downscale,
            annotations=load_annotations(seq),
            depth_camera=depth_camera,
        )
        self._maps = None

    def _setup_camera(self, seq: Path, intrinsics, distortion, undistort: bool) -> Intrinsics:
        """Set ``freiburg`` (from the sequence name, else the comment lines of ``rgb.txt``), ``distortion``,
        ``undistort`` and ``raw_intrinsics``; returns the native intrinsics (the alpha=0 optimal new pinhole
        camera when undistorting). Arguments as the constructor's.

        Raises:
            ValueError: a bad ``intrinsics`` or ``distortion`` override.
        """
        fr = freiburg_id(seq.name)
        if fr is None:
            with open(seq / "rgb.txt", "r", encoding="utf-8") as fh:
                head = "".join(line for line in fh.readlines()[:5] if line.startswith("#"))
            fr = freiburg_id(head)
        self.freiburg = fr
        cam = self.camera
        size = (cam.intrinsics.width, cam.intrinsics.height) if cam is not None else TUM_SIZE
        if intrinsics is None and cam is not None:
            intr = cam.intrinsics
        elif intrinsics is None:
            intr = Intrinsics(*TUM_INTRINSICS[fr], *TUM_SIZE)
        elif isinstance(intrinsics, Intrinsics):
            intr = intrinsics
        else:
            vals = [float(v) for v in intrinsics]
            if len(vals) != 4:
                raise ValueError(f"intrinsics override must be Intrinsics or (fx, fy, cx, cy), got {intrinsics!r}")
            intr = Intrinsics(*vals, *size)
        dist = TUM_DISTORTION[fr] if distortion is None else tuple(float(v) for v in distortion)
        if len(dist) != 5 or not all(math.isfinite(v) for v in dist):
            raise ValueError(f"distortion must be 5 finite numbers (k1 k2 p1 p2 k3), got {distortion!r}")
        self.distortion = dist
        self.undistort = bool(undistort) and any(dist)
        #: pinhole intrinsics of the raw (distorted) image files; ``native_intrinsics`` differ from
        #: these only when ``undistort=True``
        self.raw_intrinsics = intr
        if self.undistort:
            # new camera matrix chosen so that every output pixel has a source pixel (OpenCV's
            # getOptimalNewCameraMatrix with alpha=0): no black border enters the map or the metrics
            new_k, _ = cv2.getOptimalNewCameraMatrix(intr.K, np.asarray(dist), (intr.width, intr.height), 0.0)
            intr = Intrinsics(float(new_k[0, 0]), float(new_k[1, 1]), float(new_k[0, 2]), float(new_k[1, 2]),
                              intr.width, intr.height)
        return intr

    def _associate(self, seq: Path, rgb_ts: np.ndarray, depth_ts: np.ndarray, gt_ts: np.ndarray,
                   max_depth_dt: float, max_pose_dt: float):
        """Match each colour timestamp (s) to the nearest depth and groundtruth sample; sets ``n_dropped`` (colour
        frames without a match within ``max_depth_dt`` / ``max_pose_dt`` s, logged).

        Returns:
            ``(keep, d_idx, g_idx)``: indices of the matched colour frames, and per colour frame the index of its
            depth file and of its groundtruth sample.
        Raises:
            ValueError: no colour frame matched.
        """
        d_order = np.argsort(depth_ts, kind="stable")
        d_idx, d_gap = associate_nearest(rgb_ts, depth_ts[d_order])
        d_idx = d_order[d_idx]
        if gt_ts is None:  # no ground truth: every colour frame with depth is kept
            g_idx, g_gap = np.zeros(len(rgb_ts), dtype=np.int64), np.zeros(len(rgb_ts))
        else:
            g_idx, g_gap = associate_nearest(rgb_ts, gt_ts)
        ok = (d_gap <= max_depth_dt) & (g_gap <= max_pose_dt)
        keep = np.flatnonzero(ok)
        self.n_dropped = int(len(rgb_ts) - len(keep))
        if self.n_dropped:
            bad = np.flatnonzero(~ok)
            log.warning(
                "%s: dropped %d of %d colour frames without depth within %.3f s or groundtruth within %.3f s "
                "(first: %s)",
                seq, self.n_dropped, len(rgb_ts), max_depth_dt, max_pose_dt,
                ", ".join(f"{rgb_ts[i]:.6f}" for i in bad[:5]),
            )
        if len(keep) == 0:
            raise ValueError(
                f"{seq}: no colour frame has depth within {max_depth_dt} s and groundtruth within {max_pose_dt} s"
            )
        return keep, d_idx, g_idx

    def _gt_pose(self, seq: Path, gt: tuple, ts: float, g: int, interp: bool) -> np.ndarray:
        """(4, 4) camera-to-world at time ``ts`` (s): groundtruth sample ``g`` of ``gt`` (the
        :func:`read_groundtruth` tuple), or with ``interp`` interpolated between the bracketing samples.

        Raises:
            ValueError: not a rigid transform (names the groundtruth line).
        """
        gt_ts, gt_t, gt_q, gt_lines = gt
        t, q = gt_t[g], gt_q[g]
        if interp:
            t, q = self._interp(ts, gt_ts, gt_t, gt_q, g)
        T = np.eye(4)
        T[:3, :3] = quat_to_rot(q)
        T[:3, 3] = t
        return check_rigid(T, what=f"{seq / 'groundtruth.txt'}:{gt_lines[g]}")

    def _depth_time_extrinsics(self, seq: Path, gt: tuple, sel: List[int], rgb_ts: np.ndarray, td: np.ndarray,
                               g_idx: np.ndarray, poses: List[np.ndarray], interpolate_poses: bool) -> List[np.ndarray]:
        """Per selected colour frame ``sel[k]``, the (4, 4) T_color_depth that re-projects its depth image (taken at
        ``td[k]`` s) from the interpolated pose at that time to the colour frame's (``poses``: the colour frames'
        poses, interpolated when ``interpolate_poses``)."""
        gd, _ = associate_nearest(td, gt[0])
        ext = []
        for k, i in enumerate(sel):
            T_wd = self._gt_pose(seq, gt, float(td[k]), int(gd[k]), True)
            T_wc = poses[k] if interpolate_poses else self._gt_pose(seq, gt, rgb_ts[i], int(g_idx[i]), True)
            T = np.linalg.inv(T_wc) @ T_wd
            T[3] = (0.0, 0.0, 0.0, 1.0)
            ext.append(T)
        return ext

    @staticmethod
    def _interp(t_q: float, gt_ts: np.ndarray, gt_t: np.ndarray, gt_q: np.ndarray, g: int):
        """Translation lerp + quaternion slerp between the samples bracketing ``t_q`` (nearest at the ends)."""
        j = int(np.searchsorted(gt_ts, t_q))
        if j <= 0 or j >= len(gt_ts) or gt_ts[j] == gt_ts[j - 1]:
            return gt_t[g], gt_q[g]
        a = (t_q - gt_ts[j - 1]) / (gt_ts[j] - gt_ts[j - 1])
        return (1 - a) * gt_t[j - 1] + a * gt_t[j], slerp(gt_q[j - 1], gt_q[j], a)

    def _depth_camera_for(self, i: int) -> Optional[DepthCamera]:
        """``depth_camera`` composed with frame ``i``'s depth/colour time-offset extrinsic (if aligned)."""
        if self._time_extrinsics is None:
            return self.depth_camera
        T_time = self._time_extrinsics[i]
        if self.depth_camera is None:
            ri = self.raw_intrinsics  # TUM depth files are registered to the raw (distorted) colour camera
            return DepthCamera(ri, T_time, self.distortion if any(self.distortion) else (0.0,) * 5)
        dc = self.depth_camera
        return DepthCamera(dc.intrinsics, T_time @ dc.T_color_depth, dc.distortion, dc.splat)

    def _color_camera(self):
        """The colour files are distorted: register unregistered depth into the raw camera with its distortion."""
        return self.raw_intrinsics, (self.distortion if any(self.distortion) else None)

    def _preprocess(self, rgb: np.ndarray, depth: np.ndarray, i: int):
        """Undistort colour (bilinear) and depth (nearest, keeps values) when ``undistort=True``."""
        if not self.undistort:
            return rgb, depth
        if self._maps is None:
            ri, ni = self.raw_intrinsics, self.native_intrinsics
            self._maps = cv2.initUndistortRectifyMap(
                ri.K, np.asarray(self.distortion), None, ni.K, (ni.width, ni.height), cv2.CV_32FC1
            )
        mx, my = self._maps
        rgb = cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        depth = cv2.remap(depth, mx, my, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return rgb, depth
