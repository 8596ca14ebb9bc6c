"""Keyframe alignment (``pose.align: depth``): a new keyframe's depth registered to the depth of the keyframes before it (frame-to-model).

A keyframe's pose from the robot carries errors of a centimetre and half a degree (a robot's odometry, a SLAM
estimate, motion capture with a sync offset), and they grow along the path. Views that disagree by that much cannot
all be fitted by the same Gaussians: the task region, which GaussLite maps with small Gaussians, loses most (docs/
mapper.md "What real sensors do to the region"). KinectFusion (Newcombe et al., ISMAR 2011, Sec. 3.5) and
ElasticFusion align every frame to the model before fusing it; :class:`KeyframeAligner` does the same for keyframes,
against the sensor's own measurements rather than the Gaussians' render, whose expected depth sits up to a Gaussian's
scale in front of the surface while the map is young:

- the model is the raw depth of every keyframe mapped so far, each kept as a small cloud in its own camera frame
  (points sampled every ``stride`` pixels, with normals from the depth image's neighbours, one point per
  ``pose.align_voxel_m`` voxel) and placed at the pose the map holds for that keyframe **now**
  (:meth:`gausslite.mapping.mapper.Mapper.pose_of`): corrections by pose refinement or by a pose graph
  (:meth:`~gausslite.mapping.mapper.Mapper.apply_pose_corrections`) move the model with them;
- the new keyframe's sampled points are registered to the model clouds that reach its view (those whose world boxes
  meet its own, grown by ``pose.align_margin_m``), point to plane (Chen & Medioni 1992; Open3D's
  ``registration_icp``), coarse to fine at voxels ``2 δ`` then ``δ``, from the pose it came with times the latest
  keyframe's correction;
- a result is kept when the share of points with a correspondence (fitness) reaches ``pose.align_min_fitness`` and
  the correction is within ``pose.track_max_trans_m`` / ``pose.track_max_rot_deg`` of the start; otherwise the
  keyframe keeps its start pose (logged).

Open3D runs on one thread here (its reductions are summed in a timing-dependent order on more), so an alignment
repeats bit for bit.

Poses are camera-to-world (4, 4) float64, metres, OpenCV camera axes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable, Dict, Mapping, Optional

import numpy as np

from gausslite.camera import rotation_angle_deg
from gausslite.datasets.base import Frame

log = logging.getLogger(__name__)

#: coarse-to-fine levels of the registration: (voxel as a multiple of ``align_voxel_m``, ICP iterations)
LEVELS = ((2.0, 15), (1.0, 8))
#: correspondences farther than this multiple of a level's voxel are not used at that level
MAX_CORRESPONDENCE = 1.5
#: sampled pixels whose depth differs from a neighbour's by more than this share of their depth get no normal
#: (a depth edge: the neighbours lie on another surface)
EDGE_REL = 0.05


@dataclass
class AlignResult:
    """What aligning one keyframe gave.

    Attributes:
        c2w: (4, 4) float64 the aligned pose (the start pose when not ``accepted``).
        accepted: the alignment passed the gates (False: too little overlap, or a correction beyond them).
        fitness: share of the keyframe's sampled points with a model point within the finest level's distance.
        rmse_m: RMS point-to-plane residual of those correspondences, metres.
        rot_deg: the correction's rotation from the start pose, degrees (kept or not).
        trans_m: the correction's translation, metres.
        seconds: wall time of the alignment.
    """

    c2w: np.ndarray
    accepted: bool
    fitness: float = 0.0
    rmse_m: float = 0.0
    rot_deg: float = 0.0
    trans_m: float = 0.0
    seconds: float = 0.0


def depth_cloud(frame: Frame, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Points and normals of a depth image in its camera frame, one every ``stride`` pixels.

    Args:
        frame: a frame with (H, W) float32 ``depth`` in metres (0: invalid) and its ``intrinsics`` (pixel centres at
            integer coordinates, OpenCV).
        stride: sampling step in pixels (>= 1).
    Returns:
        ``(points, normals)``, each (N, 3) float64 in the camera frame (metres; unit normals facing the camera):
        the sampled pixels with valid depth whose right and lower neighbours (one step away) are valid and on the
        same surface (depth within :data:`EDGE_REL`), the normal the cross product of the two differences.
    Raises:
        ValueError: ``stride`` < 1.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    K = frame.intrinsics
    d = np.asarray(frame.depth, np.float64)[::stride, ::stride]
    h, w = d.shape
    v, u = np.mgrid[0:h, 0:w]
    pts = np.stack([(u * stride - K.cx) / K.fx * d, (v * stride - K.cy) / K.fy * d, d], axis=-1)
    if h < 2 or w < 2:
        return np.zeros((0, 3)), np.zeros((0, 3))
    p, pr, pd = pts[:-1, :-1], pts[:-1, 1:], pts[1:, :-1]
    z, zr, zd = d[:-1, :-1], d[:-1, 1:], d[1:, :-1]
    ok = (z > 0) & (zr > 0) & (zd > 0) & (np.abs(zr - z) < EDGE_REL * z) & (np.abs(zd - z) < EDGE_REL * z)
    n = np.cross(pr - p, pd - p)
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0
    n = n[ok] / norm[ok][:, None]
    p = p[ok]
    n *= -np.sign(np.einsum("ij,ij->i", n, p))[:, None]  # facing the camera
    return p, n


class KeyframeAligner:
    """Frame-to-model alignment of keyframes against the raw depth of the keyframes mapped before them.

    Args:
        voxel_m: the model's voxel size δ (metres; ``pose.align_voxel_m``), the finest level's.
        width: keyframes are sampled every ``max(1, W // width)`` pixels (``pose.align_width``).
        min_fitness: the least share of sampled points with a correspondence for a result to be kept.
        max_trans_m, max_rot_deg: the largest correction kept (metres, degrees).
        margin_m: a stored keyframe's cloud joins the model of a new keyframe when their world boxes, grown by this,
            meet (metres).
        max_keyframes: clouds kept at most; beyond it the oldest are dropped (the first keyframe's stays: the gauge).
    Attributes:
        clouds: frame id → ``(points, normals)`` (N, 3) float64 in that keyframe's camera frame, one per voxel.
    """

    def __init__(self, voxel_m: float = 0.02, width: int = 80, min_fitness: float = 0.3, max_trans_m: float = 0.1,
                 max_rot_deg: float = 10.0, margin_m: float = 0.2, max_keyframes: int = 1000) -> None:
        self.voxel_m, self.width, self.min_fitness = float(voxel_m), int(width), float(min_fitness)
        self.max_trans_m, self.max_rot_deg, self.margin_m = float(max_trans_m), float(max_rot_deg), float(margin_m)
        self.max_keyframes = int(max_keyframes)
        self.clouds: Dict[int, tuple[np.ndarray, np.ndarray]] = {}
        #: frame id → (8, 3) corners of its cloud's box in its camera frame (a cloud whose box, placed at its pose,
        #: misses a keyframe's view is passed over without moving its points)
        self._corners: Dict[int, np.ndarray] = {}
        from gausslite.odometry.pose_graph import open3d_module  # lazy: Open3D loads only for mappers that align

        self._o3d = open3d_module()  # here, so that its import (about a second) is not taken from a keyframe's budget

    def __len__(self) -> int:
        return len(self.clouds)

    def _stride(self, frame: Frame) -> int:
        return max(1, int(frame.intrinsics.width) // self.width)

    def _voxelised(self, pts: np.ndarray, nrm: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
        """One point per ``voxel`` cell: the mean of its points and the normalised mean of their normals."""
        if len(pts) == 0:
            return pts, nrm
        cell = np.floor(pts / voxel).astype(np.int64)
        cell -= cell.min(0)
        span = cell.max(0) + 1
        key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]  # one integer per cell
        _, inv, count = np.unique(key, return_inverse=True, return_counts=True)
        p = np.zeros((len(count), 3))
        n = np.zeros((len(count), 3))
        np.add.at(p, inv, pts)
        np.add.at(n, inv, nrm)
        p /= count[:, None]
        norm = np.linalg.norm(n, axis=1)
        keep = norm > 1e-6
        return p[keep], n[keep] / norm[keep][:, None]

    def _store(self, fid: int, pts: np.ndarray, nrm: np.ndarray) -> None:
        """Keep a cloud and its box's corners."""
        self.clouds[fid] = (pts, nrm)
        if len(pts):
            lo, hi = pts.min(0), pts.max(0)
            self._corners[fid] = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                           for z in (lo[2], hi[2])])

    def add(self, frame: Frame) -> None:
        """Store a mapped keyframe's cloud (its camera frame; placed at its pose when a later keyframe aligns)."""
        pts, nrm = depth_cloud(frame, self._stride(frame))
        self._store(int(frame.frame_id), *self._voxelised(pts, nrm, self.voxel_m))
        if len(self.clouds) > self.max_keyframes:
            ids = sorted(self.clouds)
            for fid in ids[1:len(ids) - self.max_keyframes + 1]:
                del self.clouds[fid]
                self._corners.pop(fid, None)

    def _model(self, box_min: np.ndarray, box_max: np.ndarray, pose_of: Callable[[int], np.ndarray]):
        """The stored clouds' points inside the box, in the world at their keyframes' poses now: an Open3D point cloud
        with unit normals (None when no point is inside)."""
        P, N = [], []
        for fid, (pts, nrm) in self.clouds.items():
            if len(pts) == 0:
                continue
            T = pose_of(fid)
            box = self._corners[fid] @ T[:3, :3].T + T[:3, 3]
            if np.any(box.max(0) < box_min) or np.any(box.min(0) > box_max):
                continue  # no point of it can be inside
            wp = pts @ T[:3, :3].T + T[:3, 3]
            inside = np.all((wp >= box_min) & (wp <= box_max), axis=1)
            if inside.any():
                P.append(wp[inside])
                N.append(nrm[inside] @ T[:3, :3].T)
        if not P:
            return None
        o3d = self._o3d
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(P)))
        cloud.normals = o3d.utility.Vector3dVector(np.concatenate(N))
        return cloud  # one point per voxel per keyframe: where keyframes overlap, a point of each

    def align(self, frame: Frame, c2w: np.ndarray, pose_of: Callable[[int], np.ndarray],
              deadline: Optional[float] = None, clock: Callable[[], float] = time.perf_counter) -> AlignResult:
        """Register ``frame``'s depth to the model, from ``c2w``.

        Args:
            frame: the new keyframe (depth in metres, intrinsics).
            c2w: (4, 4) float the pose it starts from (world, metres).
            pose_of: frame id → (4, 4) float64 the pose the map holds now for a stored keyframe.
            deadline: ``clock()`` time after which no further level starts (the first always runs); None: all levels.
            clock: the clock of ``deadline``.
        Returns:
            :class:`AlignResult` (not accepted, at ``c2w``, when there is no model yet or too little overlap).
        """
        t0 = time.perf_counter()
        start = np.asarray(c2w, np.float64)
        pts, _ = depth_cloud(frame, self._stride(frame))
        if len(pts) < 6 or not self.clouds:
            return AlignResult(start.copy(), False, seconds=time.perf_counter() - t0)
        wp = pts @ start[:3, :3].T + start[:3, 3]
        grow = self.margin_m + self.max_trans_m
        tgt_all = self._model(wp.min(0) - grow, wp.max(0) + grow, pose_of)
        if tgt_all is None or len(tgt_all.points) < 6:
            return AlignResult(start.copy(), False, seconds=time.perf_counter() - t0)
        o3d = self._o3d
        if o3d.utility.get_max_threads() != 1:
            o3d.utility.set_max_threads(1)  # a repeatable sum (module doc)
        reg = o3d.pipelines.registration
        src_all = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        T, result = start, None
        for i, (scale, iters) in enumerate(LEVELS):
            if i and deadline is not None and clock() >= deadline:
                break
            vox = scale * self.voxel_m
            src = src_all.voxel_down_sample(vox) if scale > 1 else src_all
            tgt = tgt_all
            if scale > 1:
                tgt = tgt_all.voxel_down_sample(vox)
                tgt.normalize_normals()
            result = reg.registration_icp(src, tgt, MAX_CORRESPONDENCE * vox, T,
                                          reg.TransformationEstimationPointToPlane(),
                                          reg.ICPConvergenceCriteria(1e-6, 1e-6, iters))
            T = np.asarray(result.transformation, np.float64)
        D = np.linalg.inv(start) @ T
        rot, trans = rotation_angle_deg(D), float(np.linalg.norm(D[:3, 3]))
        fitness, rmse = float(result.fitness), float(result.inlier_rmse)
        ok = (np.all(np.isfinite(T)) and fitness >= self.min_fitness and trans <= self.max_trans_m
              and rot <= self.max_rot_deg)
        if not ok:
            log.info("keyframe %s: alignment kept its pose (fitness %.2f, correction %.1f mm / %.2f deg)",
                     frame.frame_id, fitness, trans * 1e3, rot)
        return AlignResult(T.copy() if ok else start.copy(), bool(ok), fitness, rmse, rot, trans,
                           time.perf_counter() - t0)

    def state_dict(self) -> dict:
        """Plain-data copy for checkpoints: ``{"clouds": {frame id: (points, normals) float32}}``."""
        return {"clouds": {k: (p.astype(np.float32), n.astype(np.float32)) for k, (p, n) in self.clouds.items()}}

    def load_state_dict(self, state: Mapping) -> None:
        """Replace the stored clouds by a :meth:`state_dict`'s.

        Raises:
            ValueError: a cloud whose points and normals are not (N, 3) of one length.
        """
        clouds = {}
        for fid, (p, n) in state["clouds"].items():
            p, n = np.asarray(p, np.float64), np.asarray(n, np.float64)
            if p.ndim != 2 or p.shape[1:] != (3,) or p.shape != n.shape:
                raise ValueError(f"keyframe {fid}'s alignment cloud has shapes {p.shape} and {n.shape}")
            clouds[int(fid)] = (p, n)
        self.clouds, self._corners = {}, {}
        for fid, (p, n) in clouds.items():
            self._store(fid, p, n)


__all__ = ["KeyframeAligner", "AlignResult", "depth_cloud", "LEVELS"]
