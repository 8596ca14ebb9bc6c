"""Drift correction for the RGB-D odometry: a keyframe pose graph with verified loop closures, and re-localisation.

The odometry (:mod:`gausslite.datasets.odometry`) registers each frame to a nearby keyframe, so its error grows with
the path: a room-sized walk drifts by centimetres. As keyframe SLAM systems do (DVO-SLAM, Kerl, Sturm, Cremers, IROS
2013; ORB-SLAM, Mur-Artal et al., T-RO 2015), this module keeps every keyframe as a node of a pose graph and, when
the camera comes back to a place it saw before, adds a **loop edge** between the new keyframe and the old one and
optimises the graph (Open3D's ``global_optimization``, Levenberg-Marquardt with its line process that prunes edges
that disagree with the rest; Choi, Zhou, Koltun, CVPR 2015).

Loop edges are gated hard, since one false loop bends the whole map:

1. **candidates**: keyframes at least ``min_gap`` keyframes older than the new one, within ``radius_m`` of its
   estimated position and ``max_angle_deg`` of its viewing direction (the drift is small against these), nearest
   first, at most ``max_candidates``;
2. **dense registration**: Open3D's RGB-D odometry (hybrid term) from the estimated relative pose converges and at
   least ``min_fitness`` of the new keyframe's valid depth pixels find a correspondence;
3. **verification**: the registration the other way round (the old keyframe to the new one, from the inverse of the
   result) passes gate 2 and lands on the same pose within ``agree_m`` and ``agree_deg`` (a wrong local minimum is
   rarely one from both sides); and point-to-plane ICP on the two depth clouds, started from the dense result, keeps
   ``min_fitness`` of the points as inliers within ``icp_distance_m`` at an inlier RMSE of at most
   ``icp_max_rmse_m`` and agrees with it as well: registrations of different residuals (photometric + depth,
   point-to-plane) land on the same pose;
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
from typing import Dict, List, Optional, Tuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gausslite.camera import nearest_rigid
from gausslite.datasets.trajectory import rotation_angle_deg

log = logging.getLogger(__name__)

__all__ = ["LoopConfig", "RelocConfig", "LoopEdge", "KeyframeGraph", "verify_registration", "relocalise",
           "thumbnail", "open3d_module", "loop_information", "DepthClouds"]


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
        agree_m, agree_deg: the dense and the ICP registration must agree within these.
        drift_floor_m, drift_per_m, drift_floor_deg, drift_deg_per_m: the largest correction a loop may imply, over
            the path travelled between its keyframes.
        prune_threshold: Open3D's ``edge_prune_threshold`` (the line process's confidence below which an uncertain
            edge is dropped).
        keyframe_images_max: keyframes kept with their images for loops and re-localisation (the oldest dropped
            first; their poses stay in the graph).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    enabled: bool = True
    min_gap: int = Field(5, ge=1)
    radius_m: float = Field(0.4, gt=0)
    max_angle_deg: float = Field(25.0, gt=0)
    max_candidates: int = Field(2, ge=1)
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
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    enabled: bool = True
    candidates: int = Field(6, ge=1)
    every: int = Field(1, ge=1)
    min_fitness: float = Field(0.45, gt=0, le=1)
    min_support: int = Field(2, ge=1)


@dataclass
class LoopEdge:
    """A loop closure that passed every gate.

    Attributes:
        source, target: frame ids of the new keyframe and the older one.
        T: (4, 4) float64 ``c2w_target⁻¹ c2w_source`` the registration measured.
        fitness: the dense registration's fitness; icp_rmse_m: ICP's inlier RMSE (metres).
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
    several keyframes. Keyed by the frame object, so it lives only as long as that search."""

    def __init__(self, depth_max: float) -> None:
        self.depth_max = depth_max
        self._made: Dict[int, Tuple[object, object]] = {}

    def of(self, frame):
        """The cloud of ``frame`` (``depth`` (H, W) float32 metres, ``intrinsics``)."""
        hit = self._made.get(id(frame))
        if hit is not None and hit[0] is frame:
            return hit[1]
        o3d = open3d_module()
        i = frame.intrinsics
        pin = o3d.camera.PinholeCameraIntrinsic(i.width, i.height, i.fx, i.fy, i.cx, i.cy)
        pcd = o3d.geometry.PointCloud.create_from_depth_image(
            o3d.geometry.Image(np.ascontiguousarray(frame.depth, dtype=np.float32)), pin, depth_scale=1.0,
            depth_trunc=self.depth_max)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.1, max_nn=30))
        self._made[id(frame)] = (frame, pcd)
        return pcd


def verify_registration(odo, frame, image, target, init: np.ndarray, min_fitness: float, cfg: LoopConfig,
                        clouds: Optional[DepthClouds] = None) -> Optional[Tuple[np.ndarray, np.ndarray, float, float]]:
    """Register ``frame`` to the keyframe ``target`` from ``init`` and apply gates 2-3 of the module docstring.

    Args:
        odo: the :class:`~gausslite.datasets.odometry.RGBDOdometry` (its ``register`` and settings).
        frame, image: the frame at the tracking size and its Open3D RGB-D image.
        target: the keyframe (``frame``, ``image``, ``c2w``).
        init: (4, 4) initial ``c2w_target⁻¹ c2w_frame``.
        min_fitness: the dense and ICP fitness gate; cfg: the ICP gates.
        clouds: the depth clouds of the search this check belongs to (None: made for this check alone).
    Returns:
        ``(T (4, 4) c2w_target⁻¹ c2w_frame, information (6, 6), fitness, icp_rmse_m)``, or None when a gate failed.
    """
    ok, T, info, fitness = odo.register(frame, image, target, init)
    if not ok or fitness < min_fitness:
        return None
    # the other way round, from the inverse of the result: a pose that is a true fit is found from both sides
    back_ok, back, _, back_fit = odo.register(target.frame, target.image, _FrameView(frame, image), np.linalg.inv(T))
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
        frame, image: the frame at the tracking size and its Open3D RGB-D image.
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
    for k in by_look[:n_look] + by_pose:
        if len(tried) >= cfg.candidates:
            break
        if k.frame_id in tried:
            continue
        tried.add(k.frame_id)
        init = np.eye(4) if k.frame_id in look_ids else np.linalg.inv(k.c2w) @ pred
        got = verify_registration(odo, frame, image, k, init, cfg.min_fitness, odo.config.loop, clouds)
        if got is not None:
            passed.append((k.c2w @ got[0], k.frame_id, got[2]))
    # a pose two keyframes give alike (a slide along a wall or the desk fits one keyframe, rarely two)
    support = [[q for q in passed if _agree(p[0], q[0], odo.config.loop)] for p in passed]
    agreed = [p for p, s in zip(passed, support) if len(s) >= min(cfg.min_support, len(kfs))]
    return max(agreed, key=lambda p: p[2], default=None)
