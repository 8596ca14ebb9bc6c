"""Drift correction for the RGB-D odometry: a keyframe pose graph with verified loop closures, and re-localisation.

The odometry (:mod:`gausslite.odometry.rgbd`) registers each frame to a nearby keyframe, so its error grows with
the path: a room-sized walk drifts by centimetres. As keyframe SLAM systems do (DVO-SLAM, Kerl, Sturm, Cremers, IROS
2013; ORB-SLAM, Mur-Artal et al., T-RO 2015), this module keeps every keyframe as a node of a pose graph and, when
the camera comes back to a place it saw before, adds a **loop edge** between the new keyframe and the old one and
optimises the graph (Open3D's ``global_optimization``, Levenberg-Marquardt with its line process that prunes edges
that disagree with the rest; Choi, Zhou, Koltun, CVPR 2015).

Loop edges are gated hard, since one false loop bends the whole map:

1. **candidates**: keyframes at least ``min_gap`` keyframes older than the new one, within ``radius_m`` of its
   estimated position and ``max_angle_deg`` of its viewing direction (the drift is small against these), nearest
   first, at most ``max_candidates``;
2. **registration**: point-to-plane ICP of the two keyframes' depth clouds from the estimated relative pose, coarse
   to fine over ``icp_levels_m`` (``registration: icp``, the default), keeps at least ``min_fitness`` of the new
   keyframe's points as inliers within ``icp_distance_m`` at an inlier RMSE of at most ``icp_max_rmse_m``;
3. **verification**: the same ICP the other way round (the old keyframe's cloud onto the new one's, from the inverse
   of the result) lands on the same pose within ``agree_m`` and ``agree_deg`` (a wrong local minimum is rarely one
   from both sides); and the result is a minimum along the direction the surfaces pin down least (the eigenvector
   of the smallest eigenvalue of the inliers' mean ``n nᵀ``, ``n`` the target's normals; Zhang, Kaess, Singh, ICRA
   2016), when that direction holds under ``basin_below`` of the normals' weight: ICP restarted from the result
   shifted by ``basin_m`` either way along it comes back within ``agree_m`` and ``agree_deg``. Two clouds that can
   slide along a wall or down a corridor fit anywhere along it, from either side, and this is the check that finds
   them out (``basin_m: null`` turns it off).

   With ``registration: hybrid`` or ``point_to_plane``, gate 2 is Open3D's RGB-D odometry with those residuals
   (the tracker's own registration) from the estimated relative pose, with at least ``min_fitness`` of the new
   keyframe's valid depth pixels finding a correspondence, and gate 3 that registration the other way round plus ICP
   started from its result, each agreeing with it. On the synthetic scan walk with a TUM-like sensor (its first
   rendering), from the same estimated relative poses (median 2.6 cm off), the hybrid registration placed 23 of 88
   candidates within 2 cm of the true relative pose (median 3.8 cm) and the coarse-to-fine ICP 73 (median 1.3 cm)
   (docs/mapper.md, "Loop registration");
4. **plausible drift**: the correction the loop implies is at most ``drift_floor_m + drift_per_m × path`` metres and
   ``drift_floor_deg + drift_deg_per_m × path`` degrees, ``path`` the distance travelled between the two keyframes;
5. **consistency**: after optimisation, a loop edge the line process pruned (confidence below
   ``prune_threshold``) does not count, and the optimisation is undone when it moved a keyframe further than the
   drift bound allows.

A frame whose tracking failed is **re-localised** (:func:`relocalise`): the keyframes whose thumbnails look most
like it (zero-mean normalised cross-correlation of 40 × 30 grey images), each from its own pose, and those nearest
the pose the last motion predicts, from that prediction, are tried with the same gates as a loop (2-3), and the pose
is kept only when ``min_support`` keyframes give it alike (a registration that slid along a wall or the desk fits
one keyframe, rarely two). Once a frame
is lost, the next ones are only re-localised: the ordinary tracking's looser check does not apply until one is found
again. The best one passing them gives the frame's pose.

Poses are camera-to-world (c2w, (4, 4) float64, metres, OpenCV camera axes). An edge ``(source i, target j, T)``
holds ``T = c2w_j⁻¹ c2w_i``, Open3D's convention.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Dict, List, Literal, Optional, Tuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gausslite.camera import nearest_rigid, rotation_angle_deg

log = logging.getLogger(__name__)

__all__ = ["LoopConfig", "RelocConfig", "LoopEdge", "KeyframeGraph", "verify_registration", "relocalise",
           "thumbnail", "open3d_module", "loop_information", "DepthClouds", "least_pinned_direction",
           "icp_information"]


def open3d_module():
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


class LoopConfig(BaseModel):
    """Loop closure over the odometry's keyframes (see the module docstring for each gate).

    Attributes:
        enabled: detect loops and optimise the pose graph.
        min_gap: a candidate is at least this many keyframes older than the new one.
        radius_m, max_angle_deg: a candidate's position and viewing direction lie within these of the new keyframe's.
        max_candidates: candidates tried per new keyframe (nearest first).
        min_fitness: share of the new keyframe's valid depth pixels with a correspondence (dense) and of its points
            that are ICP inliers.
        icp_distance_m: ICP's correspondence distance; icp_max_rmse_m: the largest inlier RMSE accepted (point to
            point: it grows with the spacing of the depth points, about 3 cm at 96 pixels wide).
        agree_m, agree_deg: the registrations of gate 3 must agree within these.
        drift_floor_m, drift_per_m, drift_floor_deg, drift_deg_per_m: the largest correction a loop may imply, over
            the path travelled between its keyframes.
        prune_threshold: Open3D's ``edge_prune_threshold`` (the line process's confidence below which an uncertain
            edge is dropped).
        keyframe_images_max: keyframes kept with their images for loops and re-localisation (the oldest dropped
            first; their poses stay in the graph).
        registration: how gates 2-3 register a pair: ``icp`` (point-to-plane ICP coarse to fine over
            ``icp_levels_m``, then from the other side) or ``hybrid`` / ``point_to_plane`` (Open3D's RGB-D odometry
            with those residuals both ways, then ICP).
        basin_m: gate 3's restarts along the least-pinned direction start this far either side of the result
            (metres; None: no restarts); basin_below: they run when that direction's eigenvalue of the inliers' mean
            ``n nᵀ`` (trace 1: 0 for one plane, 1/3 for normals facing every way alike) is below this.
        icp_levels_m: the correspondence distances of the ``icp`` registration's levels, coarsest first (metres).
        icp_voxel_m: the ``icp`` registration's clouds are thinned to one point per voxel of this size (metres; None:
            every depth pixel's point); icp_iterations: ICP iterations per level at most; icp_relative_change: a level
            stops once an iteration changes the fitness and the inlier RMSE by less than this fraction (Open3D's
            ``relative_fitness`` and ``relative_rmse``).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    enabled: bool = True
    min_gap: int = Field(5, ge=1)
    radius_m: float = Field(0.4, gt=0)
    max_angle_deg: float = Field(25.0, gt=0)
    max_candidates: int = Field(4, ge=1)
    min_fitness: float = Field(0.45, gt=0, le=1)
    icp_distance_m: float = Field(0.05, gt=0)
    icp_max_rmse_m: float = Field(0.035, gt=0)
    agree_m: float = Field(0.03, gt=0)
    agree_deg: float = Field(2.0, gt=0)
    drift_floor_m: float = Field(0.05, ge=0)
    drift_per_m: float = Field(0.05, ge=0)
    drift_floor_deg: float = Field(2.0, ge=0)
    drift_deg_per_m: float = Field(3.0, ge=0)
    prune_threshold: float = Field(0.25, gt=0, lt=1)
    keyframe_images_max: int = Field(2000, ge=1)
    registration: Literal["icp", "hybrid", "point_to_plane"] = "icp"
    icp_levels_m: List[float] = Field(default_factory=lambda: [0.15, 0.08, 0.04, 0.02], min_length=1)
    basin_m: Optional[float] = Field(0.05, gt=0)
    basin_below: float = Field(0.05, gt=0, le=1.0 / 3.0)
    icp_voxel_m: Optional[float] = Field(0.04, gt=0)
    icp_iterations: int = Field(15, ge=1)
    icp_relative_change: float = Field(1e-6, gt=0)


class RelocConfig(BaseModel):
    """Re-localisation of lost frames against the keyframes.

    Attributes:
        enabled: try to re-localise a frame whose tracking failed.
        candidates: keyframes tried per lost frame: half by appearance (thumbnail correlation), the rest nearest
            to the pose the last motion predicts.
        every: try on every ``every``-th consecutive lost frame (1: each one), to bound the cost of a long loss.
        min_fitness: the gates' fitness (as :class:`LoopConfig`'s; the ICP gates are :class:`LoopConfig`'s).
        min_support: keyframes whose registrations must give the same pose (within :class:`LoopConfig`'s
            ``agree_m`` / ``agree_deg``; fewer only while the odometry has fewer keyframes).
        registration: how a candidate is registered (:class:`LoopConfig`'s ``registration``): ``hybrid`` by default,
            since a lost frame is tried against up to ``candidates`` keyframes on every frame it stays lost, and ICP
            costs about five times as much per candidate (docs/mapper.md, "Loop registration").
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    enabled: bool = True
    candidates: int = Field(6, ge=1)
    every: int = Field(1, ge=1)
    min_fitness: float = Field(0.45, gt=0, le=1)
    min_support: int = Field(2, ge=1)
    registration: Literal["icp", "hybrid", "point_to_plane"] = "hybrid"


@dataclass
class LoopEdge:
    """A loop closure that passed every gate.

    Attributes:
        source, target: frame ids of the new keyframe and the older one.
        T: (4, 4) float64 ``c2w_target⁻¹ c2w_source`` the registration measured.
        fitness: the registration's fitness (gate 2); icp_rmse_m: ICP's inlier RMSE (metres).
    """

    source: int
    target: int
    T: np.ndarray
    fitness: float
    icp_rmse_m: float


@dataclass
class _Node:
    frame_id: int
    c2w: np.ndarray
    path_m: float  # distance travelled from the first keyframe to this one (metres, along the estimates)


@dataclass
class KeyframeGraph:
    """The odometry's keyframes as a pose graph: one node per keyframe, an odometry edge to the keyframe it was
    tracked against, and loop edges (:class:`LoopEdge`).

    Attributes:
        nodes: frame id → node (current pose ``c2w`` and path length), in insertion order.
        odometry_edges: ``(source, target, T (4, 4), information (6, 6))``.
        loops: accepted loop edges (pruned ones removed); n_loop_tried / n_loop_rejected: candidates registered and
            rejected by a gate.
        n_optimisations: graph optimisations run.
    """

    nodes: Dict[int, _Node] = field(default_factory=dict)
    odometry_edges: List[Tuple[int, int, np.ndarray, np.ndarray]] = field(default_factory=list)
    loops: List[LoopEdge] = field(default_factory=list)
    n_loop_tried: int = 0
    n_loop_rejected: int = 0
    n_optimisations: int = 0

    def add(self, frame_id: int, c2w: np.ndarray, reference: Optional[int] = None,
            T: Optional[np.ndarray] = None, information: Optional[np.ndarray] = None) -> None:
        """Add a keyframe at ``c2w`` (4, 4); with ``reference``, the odometry edge ``T = c2w_ref⁻¹ c2w`` measured
        with ``information`` (6, 6; Open3D's information matrix of the registration)."""
        prev = next(reversed(self.nodes.values()), None)
        path = 0.0 if prev is None else prev.path_m + float(np.linalg.norm(c2w[:3, 3] - prev.c2w[:3, 3]))
        self.nodes[int(frame_id)] = _Node(int(frame_id), np.asarray(c2w, np.float64).copy(), path)
        if reference is not None and int(reference) in self.nodes:
            info = np.eye(6) if information is None or np.size(information) != 36 else np.asarray(information)
            self.odometry_edges.append((int(frame_id), int(reference), np.asarray(T, np.float64).copy(), info))

    def drift_bound(self, a: int, b: int, cfg: LoopConfig) -> Tuple[float, float]:
        """The largest correction (metres, degrees) a loop between keyframes ``a`` and ``b`` may imply."""
        return _drift_over(abs(self.nodes[a].path_m - self.nodes[b].path_m), cfg)

    def optimise(self, cfg: LoopConfig) -> Dict[int, np.ndarray]:
        """Optimise the graph (Open3D's Levenberg-Marquardt with the line process; the first keyframe is fixed).

        Returns:
            frame id → new (4, 4) c2w of every keyframe, or ``{}`` when the optimisation was undone (a keyframe moved
            further than the drift bound of the loops allows). Loop edges the line process pruned are removed from
            :attr:`loops`.
        """
        o3d = open3d_module()
        reg = o3d.pipelines.registration
        ids = list(self.nodes)
        index = {fid: i for i, fid in enumerate(ids)}
        pg = reg.PoseGraph()
        for fid in ids:
            pg.nodes.append(reg.PoseGraphNode(self.nodes[fid].c2w))
        for s, t, T, info in self.odometry_edges:
            pg.edges.append(reg.PoseGraphEdge(index[s], index[t], T, info, uncertain=False))
        for e in self.loops:
            info = loop_information(e)
            pg.edges.append(reg.PoseGraphEdge(index[e.source], index[e.target], e.T, info, uncertain=True))
        option = reg.GlobalOptimizationOption(max_correspondence_distance=cfg.icp_distance_m,
                                              edge_prune_threshold=cfg.prune_threshold, preference_loop_closure=1.0,
                                              reference_node=0)
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            reg.global_optimization(pg, reg.GlobalOptimizationLevenbergMarquardt(),
                                    reg.GlobalOptimizationConvergenceCriteria(), option)
        self.n_optimisations += 1
        kept = {(index[e.source], index[e.target]) for e in self.loops}
        kept &= {(int(e.source_node_id), int(e.target_node_id)) for e in pg.edges if e.uncertain}
        pruned = [e for e in self.loops if (index[e.source], index[e.target]) not in kept]
        for e in pruned:
            log.info("pose graph: the loop %d -> %d disagreed with the rest and was pruned", e.source, e.target)
        self.loops = [e for e in self.loops if (index[e.source], index[e.target]) in kept]
        new = {fid: nearest_rigid(pg.nodes[index[fid]].pose, f"keyframe {fid}'s optimised pose") for fid in ids}
        worst = self._largest_move(new, cfg)
        if worst is not None:
            log.warning("pose graph: the optimisation moved keyframe %d by %.3f m / %.1f deg, beyond what the loops' "
                        "drift allows; undone", *worst)
            return {}
        for fid, c2w in new.items():
            self.nodes[fid].c2w = c2w
        return new

    def _largest_move(self, new: Dict[int, np.ndarray], cfg: LoopConfig) -> Optional[Tuple[int, float, float]]:
        """The first keyframe the optimisation moved further than the loops allow, as ``(frame id, metres,
        degrees)``, or None. The bound is the drift bound of the longest path from the fixed first keyframe to a
        loop's later end (no keyframe can have drifted more than that), doubled for slack."""
        if not self.loops:
            return None
        path = max(max(self.nodes[e.source].path_m, self.nodes[e.target].path_m) for e in self.loops)
        lim_m, lim_deg = (2.0 * v for v in _drift_over(path, cfg))
        for fid, c2w in new.items():
            old = self.nodes[fid].c2w
            moved = float(np.linalg.norm(c2w[:3, 3] - old[:3, 3]))
            turned = rotation_angle_deg(np.linalg.inv(old) @ c2w)
            if moved > lim_m or turned > lim_deg:
                return fid, moved, turned
        return None

    def summary(self) -> dict:
        """``{"keyframes", "loops", "loop_candidates", "loop_rejected", "optimisations"}``."""
        return {"keyframes": len(self.nodes), "loops": len(self.loops), "loop_candidates": self.n_loop_tried,
                "loop_rejected": self.n_loop_rejected, "optimisations": self.n_optimisations}


def _drift_over(path_m: float, cfg: LoopConfig) -> Tuple[float, float]:
    """The drift (metres, degrees) the odometry may accumulate over ``path_m`` metres of path (gate 4)."""
    return cfg.drift_floor_m + cfg.drift_per_m * path_m, cfg.drift_floor_deg + cfg.drift_deg_per_m * path_m


def loop_information(e: LoopEdge) -> np.ndarray:
    """A loop edge's information: identity scaled by 1 / RMSE² (a tighter registration weighs more)."""
    return np.eye(6) / max(e.icp_rmse_m, 1e-3) ** 2


def thumbnail(rgb: np.ndarray) -> np.ndarray:
    """(30 × 40,) float32 zero-mean, unit-norm grey thumbnail of ``rgb`` (H, W, 3) uint8: the appearance a lost frame
    is matched by (:func:`relocalise`)."""
    import cv2  # noqa: PLC0415 - OpenCV only where a thumbnail is made

    g = cv2.resize(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), (40, 30),
                   interpolation=cv2.INTER_AREA).astype(np.float32).ravel()
    g -= g.mean()
    return g / max(float(np.linalg.norm(g)), 1e-6)


class DepthClouds:
    """Open3D point clouds (camera frame, metres, with normals) of frames' depth up to ``depth_max`` metres, each made
    once: one search (a keyframe's loop candidates, a lost frame's re-localisation) registers the same frame to
    several keyframes, and later searches register to the same keyframes again. Keyed by the frame object (a cloud
    depends on the depth alone, not the pose), in the order of last use; :meth:`keep` drops what later searches do not
    need."""

    def __init__(self, depth_max: float) -> None:
        self.depth_max = depth_max
        self._made: Dict[tuple, Tuple[object, object]] = {}

    def of(self, frame, voxel_m: Optional[float] = None):
        """The cloud of ``frame`` (``depth`` (H, W) float32 metres, ``intrinsics``), thinned to one point per voxel of
        ``voxel_m`` metres (None: every point), with normals (of the full cloud, averaged over each voxel)."""
        key = (id(frame), voxel_m)
        hit = self._made.get(key)
        if hit is not None and hit[0] is frame:
            self._made[key] = self._made.pop(key)  # the most recently used last
            return hit[1]
        if voxel_m is not None:
            pcd = self.of(frame).voxel_down_sample(voxel_m)
            pcd.normalize_normals()
            self._made[key] = (frame, pcd)
            return pcd
        o3d = open3d_module()
        i = frame.intrinsics
        pin = o3d.camera.PinholeCameraIntrinsic(i.width, i.height, i.fx, i.fy, i.cx, i.cy)
        pcd = o3d.geometry.PointCloud.create_from_depth_image(
            o3d.geometry.Image(np.ascontiguousarray(frame.depth, dtype=np.float32)), pin, depth_scale=1.0,
            depth_trunc=self.depth_max)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.1, max_nn=30))
        self._made[key] = (frame, pcd)
        return pcd

    def keep(self, frames, voxel_m: Optional[float], limit: Optional[int] = None) -> None:
        """Keep only the clouds of ``frames`` thinned to ``voxel_m``, at most the ``limit`` used last (None: all): a
        cache that outlives one search holds what later searches register to, the keyframes' thinned clouds, not the
        full ones (a thinned cloud at 160×120 holds about 10,000 points with normals, 0.5 MB)."""
        ids = {id(f) for f in frames}
        kept = [(k, v) for k, v in self._made.items() if k[0] in ids and k[1] == voxel_m]
        self._made = dict(kept[-limit:] if limit is not None else kept)


def verify_registration(odo, frame, image, target, init: np.ndarray, min_fitness: float, cfg: LoopConfig,
                        clouds: Optional[DepthClouds] = None) -> Optional[Tuple[np.ndarray, np.ndarray, float, float]]:
    """Register ``frame`` to the keyframe ``target`` from ``init`` and apply gates 2-3 of the module docstring.

    Args:
        odo: the :class:`~gausslite.odometry.rgbd.RGBDOdometry` (its ``register`` and settings).
        frame, image: the frame at the tracking size and its Open3D RGB-D pyramid (``RGBDOdometry._image``).
        target: the keyframe (``frame``, ``image``, ``c2w``).
        init: (4, 4) initial ``c2w_target⁻¹ c2w_frame``.
        min_fitness: the fitness gate of gates 2-3; cfg: the other gates and the registration.
        clouds: the depth clouds of the search this check belongs to (None: made for this check alone).
    Returns:
        ``(T (4, 4) c2w_target⁻¹ c2w_frame, information (6, 6), fitness, icp_rmse_m)``, or None when a gate failed.
    """
    if cfg.registration == "icp":
        return _verify_icp(odo, frame, target, init, min_fitness, cfg, clouds)
    ok, T, info, fitness = odo.register(frame, image, target, init, cfg.registration)
    if not ok or fitness < min_fitness:
        return None
    # the other way round, from the inverse of the result: a pose that is a true fit is found from both sides
    back_ok, back, _, back_fit = odo.register(target.frame, target.image, _FrameView(frame, image), np.linalg.inv(T),
                                              cfg.registration)
    if not back_ok or back_fit < min_fitness or not _agree(T @ back, np.eye(4), cfg):
        return None
    reg = open3d_module().pipelines.registration
    clouds = clouds or DepthClouds(odo.config.depth_max_m)
    src, tgt = clouds.of(frame), clouds.of(target.frame)
    icp = reg.registration_icp(src, tgt, cfg.icp_distance_m, T, reg.TransformationEstimationPointToPlane())
    if icp.fitness < min_fitness or icp.inlier_rmse > cfg.icp_max_rmse_m:
        return None
    if not _agree(T, np.asarray(icp.transformation), cfg):
        return None
    return T, info, fitness, float(icp.inlier_rmse)


def _icp(src, tgt, init: np.ndarray, levels: List[float], cfg: LoopConfig) -> np.ndarray:
    """Point-to-plane ICP of the cloud ``src`` onto ``tgt`` from ``init`` (4, 4), coarse to fine over the
    correspondence distances ``levels`` (metres), each level stopped as ``cfg`` says (``icp_iterations``,
    ``icp_relative_change``): the (4, 4) float64 result."""
    reg = open3d_module().pipelines.registration
    stop = reg.ICPConvergenceCriteria(cfg.icp_relative_change, cfg.icp_relative_change, cfg.icp_iterations)
    T = np.asarray(init, np.float64)
    for dist in levels:
        T = np.asarray(reg.registration_icp(src, tgt, dist, T, reg.TransformationEstimationPointToPlane(),
                                            stop).transformation)
    return nearest_rigid(T, "a loop's ICP registration")


def _verify_icp(odo, frame, target, init: np.ndarray, min_fitness: float, cfg: LoopConfig,
                clouds: Optional[DepthClouds]) -> Optional[Tuple[np.ndarray, np.ndarray, float, float]]:
    """Gates 2-3 with ``registration: icp``: point-to-plane ICP of the two depth clouds from ``init``, coarse to fine
    (``icp_levels_m``), keeps ``min_fitness`` of the frame's points as inliers within ``icp_distance_m`` at an inlier
    RMSE of at most ``icp_max_rmse_m``, and the same ICP from the other side (the keyframe's cloud onto the frame's,
    from the inverse of the result, at the finer half of the levels) lands on the same pose within ``agree_m`` and
    ``agree_deg``. Returns what :func:`verify_registration` does; the information is :func:`icp_information`'s."""
    reg = open3d_module().pipelines.registration
    clouds = clouds or DepthClouds(odo.config.depth_max_m)
    src, tgt = clouds.of(frame, cfg.icp_voxel_m), clouds.of(target.frame, cfg.icp_voxel_m)
    if not len(src.points) or not len(tgt.points):
        return None
    T = _icp(src, tgt, init, cfg.icp_levels_m, cfg)
    fit = reg.evaluate_registration(src, tgt, cfg.icp_distance_m, T)
    if fit.fitness < min_fitness or fit.inlier_rmse > cfg.icp_max_rmse_m:
        return None
    back = _icp(tgt, src, np.linalg.inv(T), cfg.icp_levels_m[len(cfg.icp_levels_m) // 2:], cfg)
    if not _agree(T @ back, np.eye(4), cfg) or not _in_basin(src, tgt, T, fit.correspondence_set, cfg):
        return None
    return T, icp_information(tgt, fit.correspondence_set), float(fit.fitness), float(fit.inlier_rmse)


def icp_information(tgt, correspondences) -> np.ndarray:
    """The (6, 6) float64 information of a registration from its inlier pairs, as Open3D's
    ``get_information_matrix_from_point_clouds`` gives it (Choi, Zhou, Koltun, CVPR 2015): ``Σ GᵢᵀGᵢ`` over the
    inliers' target points ``t``, ``G = [[t]ₓᵀ | I₃]`` (rotation first), from the correspondences an evaluation at the
    same distance and pose already found instead of a second nearest-neighbour search.

    Args:
        tgt: the target Open3D cloud. correspondences: (M, 2) int (source, target) inlier indices.
    """
    t = np.asarray(tgt.points)[np.asarray(correspondences, np.int64).reshape(-1, 2)[:, 1]]
    G = np.zeros((len(t), 3, 6))
    x, y, z = t[:, 0], t[:, 1], t[:, 2]
    G[:, 0, 1], G[:, 0, 2], G[:, 1, 0], G[:, 1, 2], G[:, 2, 0], G[:, 2, 1] = z, -y, -z, x, y, -x
    G[:, 0, 3] = G[:, 1, 4] = G[:, 2, 5] = 1.0
    return np.einsum("nki,nkj->ij", G, G)


def least_pinned_direction(tgt, correspondences) -> Tuple[float, np.ndarray]:
    """The translation an ICP result's inliers constrain least: ``(eigenvalue, (3,) unit direction)`` of the smallest
    eigenvalue of the mean ``n nᵀ`` over the inlier pairs' target normals ``n`` (the target's frame). The eigenvalue
    is 0 for one plane (sliding along it costs nothing) and 1/3 for normals spread evenly over every direction.

    Args:
        tgt: the target Open3D cloud, with normals. correspondences: (M, 2) int (source, target) inlier indices.
    Raises:
        ValueError: no correspondences.
    """
    idx = np.asarray(correspondences, np.int64).reshape(-1, 2)[:, 1]
    if not len(idx):
        raise ValueError("no inlier correspondences")
    n = np.asarray(tgt.normals)[idx]
    values, vectors = np.linalg.eigh(n.T @ n / len(n))
    return float(values[0]), vectors[:, 0]


def _in_basin(src, tgt, T: np.ndarray, correspondences, cfg: LoopConfig) -> bool:
    """Gate 3's restarts: ICP from ``T`` shifted by ``cfg.basin_m`` either way along the least-pinned direction comes
    back within ``cfg.agree_m`` and ``cfg.agree_deg`` of ``T``, from the finest level wider than the shift (True when
    ``basin_m`` is None or that direction is pinned by at least ``cfg.basin_below``)."""
    if cfg.basin_m is None:
        return True
    value, direction = least_pinned_direction(tgt, correspondences)
    if value >= cfg.basin_below:
        return True
    wider = [d for d in cfg.icp_levels_m if d > cfg.basin_m]
    levels = wider[-1:] + [d for d in cfg.icp_levels_m if d <= cfg.basin_m]
    for sign in (1.0, -1.0):
        shift = np.eye(4)
        shift[:3, 3] = sign * cfg.basin_m * direction
        if not _agree(T, _icp(src, tgt, shift @ T, levels, cfg), cfg):
            return False
    return True


@dataclass
class _FrameView:
    """A frame as a registration target (the fields :meth:`RGBDOdometry.register` reads of a keyframe)."""

    frame: object
    image: object


def _agree(a: np.ndarray, b: np.ndarray, cfg: LoopConfig) -> bool:
    """Poses ``a`` and ``b`` (4, 4) lie within ``cfg.agree_m`` and ``cfg.agree_deg`` of each other."""
    d = np.linalg.inv(a) @ b
    return float(np.linalg.norm(d[:3, 3])) <= cfg.agree_m and rotation_angle_deg(d) <= cfg.agree_deg


def relocalise(odo, frame, image, pred: np.ndarray,
               cfg: RelocConfig) -> Optional[Tuple[np.ndarray, int, float]]:
    """Re-localise a lost ``frame`` against the odometry's stored keyframes (module docstring).

    Args:
        odo: the odometry (its keyframe store ``loop_keyframes`` and gates).
        frame, image: the frame at the tracking size and its Open3D RGB-D pyramid (``RGBDOdometry._image``).
        pred: (4, 4) c2w the motion predicts for the frame (the last good pose moved by the last motion).
        cfg: the settings.
    Returns:
        ``(c2w (4, 4), keyframe id, fitness)`` of the best candidate passing the gates, or None.
    """
    kfs = list(odo.loop_keyframes.values())
    if not kfs:
        return None
    th = thumbnail(frame.rgb)
    by_look = sorted(kfs, key=lambda k: -float(th @ k.thumb))
    by_pose = sorted(kfs, key=lambda k: float(np.linalg.norm(k.c2w[:3, 3] - pred[:3, 3])))
    n_look = max(1, cfg.candidates // 2)
    look_ids = {k.frame_id for k in by_look[:n_look]}
    tried, passed = set(), []
    clouds = DepthClouds(odo.config.depth_max_m)
    gates = odo.config.loop.model_copy(update={"registration": cfg.registration})
    for k in by_look[:n_look] + by_pose:
        if len(tried) >= cfg.candidates:
            break
        if k.frame_id in tried:
            continue
        tried.add(k.frame_id)
        init = np.eye(4) if k.frame_id in look_ids else np.linalg.inv(k.c2w) @ pred
        got = verify_registration(odo, frame, image, k, init, cfg.min_fitness, gates, clouds)
        if got is not None:
            passed.append((k.c2w @ got[0], k.frame_id, got[2]))
    # a pose two keyframes give alike (a slide along a wall or the desk fits one keyframe, rarely two)
    support = [[q for q in passed if _agree(p[0], q[0], gates)] for p in passed]
    agreed = [p for p, s in zip(passed, support) if len(s) >= min(cfg.min_support, len(kfs))]
    return max(agreed, key=lambda p: p[2], default=None)
