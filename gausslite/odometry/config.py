"""The settings and results of the RGB-D odometry (:mod:`gausslite.odometry.rgbd`, which re-exports them): where
camera poses come from (:data:`PoseSource`, :data:`POSE_SOURCES`), the odometry's settings (:class:`OdometryConfig`)
and what tracking one frame gives (:class:`TrackResult`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Literal, Optional, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from gausslite.odometry.pose_graph import LoopConfig, RelocConfig

__all__ = ["PoseSource", "POSE_SOURCES", "OdometryConfig", "TrackResult", "REPEAT_BOUND_M"]

#: where the camera poses (camera-to-world) come from: the frames' own (``given``: the sequence's pose file, a bag's
#: TF or pose topic, the pose each streamed frame carries) or the RGB-D odometry's estimate (``odometry``). The type of
#: ``agent.pose_source``; ``load_dataset`` and ``gausslite map --pose-source`` take it or ``auto``
#: (:data:`POSE_SOURCES`).
PoseSource = Literal["given", "odometry"]
#: the values a loader takes (``load_dataset(pose_source=...)``, ``gausslite map --pose-source``): a
#: :data:`PoseSource`, or ``auto`` (``given`` when the sequence has poses, else ``odometry``)
POSE_SOURCES = ("auto", *get_args(PoseSource))

#: how far two runs of the tracker on the same input may part with ``threads`` 1 (metres, and the same bound on each
#: element of the rotation): its poses repeat bit for bit on every CPU measured (AVX-512, and AVX2 without it), and
#: the tests hold every repetition to this bound rather than to one machine's rounding (``docs/mapper.md``,
#: "Repeatable tracking")
REPEAT_BOUND_M = 1e-6


class OdometryConfig(BaseModel):
    """Settings of the RGB-D odometry (defaults: the measured choice on TUM fr1/rpy, ``docs/mapper.md``).

    Attributes:
        method: the residuals Open3D minimises: ``hybrid`` (photometric + geometric), ``color`` (photometric only)
            or ``point_to_plane`` (geometric only).
        reference: what a frame registers to: ``nearest_keyframe`` (of the latest ``reference_keyframes_max``),
            ``last_keyframe``, or ``previous_frame`` (plain frame-to-frame).
        keyframe_trans_m, keyframe_rot_deg: a frame that moved more than either from its reference becomes a keyframe.
        reference_keyframes_max: keyframes a frame may register to, the nearest-keyframe search's (the oldest is
            dropped first).
        motion_prior: start from the previous frame's motion (constant velocity); False: from the last good pose.
        depth_max_m: depth beyond this is ignored (metres).
        depth_diff_max_m: largest depth difference of a correspondence (Open3D's ``depth_outlier_trunc``, metres).
        depth_huber_delta_m: the geometric residual's Huber threshold (metres).
        intensity_huber_delta: the photometric residual's Huber threshold (intensity in 0..1). Open3D's default,
            0.1, down-weights most of a hand-held camera's photometric residuals (exposure, blur) and drifts; 0.5
            measures best on every sequence of ``bench.odometry`` (``docs/mapper.md``, "Poses from odometry").
        iterations: Gauss-Newton iterations per pyramid level, the coarsest level first (Open3D's order: its
            multi-scale odometry runs ``criteria[0]`` on the coarsest level).
        threads: Open3D's worker threads (a process-wide Open3D setting, applied when the odometry is built and again
            before each frame and each loop search where something else changed it; 0 leaves Open3D's setting as it
            is). With 1 (the default) the poses repeat to within 1e-6 m from run to run, at any thread count of the
            rest of the process (torch, OpenMP, BLAS), on every CPU measured: bit for bit on AVX-512 and on AVX2
            (``docs/mapper.md``, "Repeatable tracking"). With more, Open3D's reductions sum in a varying order and a
            sequence parts by millimetres over tens of frames (5e-4 m over 12 frames of the synthetic scene). One
            thread is also faster at the tracking size on 2 cores beside the mapper.
        min_fitness: a frame whose share of valid depth pixels with a correspondence is below this fails.
        track_width: frames are tracked downscaled by the integer factor that brings their width nearest this
            (pixels; None: at the frames' own resolution). 160 tracks TUM as well as 320 does, at a third of the cost.
        max_step_m, max_step_deg: an estimate further than these from the last good pose fails (a jump).
        prediction_check_m, prediction_check_deg: an estimate further than these (per frame since the last good
            pose) from the motion's prediction gets a second registration, to the previous good frame, kept when it
            passes the fitness check and lands within these bounds and nearer the prediction (a registration to a
            keyframe far back in time can converge to a wrong pose that passes the fitness check).
        loop: loop closure over the keyframes (:class:`~gausslite.odometry.pose_graph.LoopConfig`).
        relocalise: re-localisation of lost frames (:class:`~gausslite.odometry.pose_graph.RelocConfig`).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    method: Literal["hybrid", "color", "point_to_plane"] = "hybrid"
    reference: Literal["nearest_keyframe", "last_keyframe", "previous_frame"] = "nearest_keyframe"
    keyframe_trans_m: float = Field(0.10, gt=0)
    keyframe_rot_deg: float = Field(10.0, gt=0)
    reference_keyframes_max: int = Field(64, ge=1)
    motion_prior: bool = True
    depth_max_m: float = Field(10.0, gt=0)
    depth_diff_max_m: float = Field(0.07, gt=0)
    depth_huber_delta_m: float = Field(0.05, gt=0)
    intensity_huber_delta: float = Field(0.5, gt=0)
    iterations: List[int] = Field(default_factory=lambda: [20, 10, 5], min_length=1)
    threads: int = Field(1, ge=0)
    min_fitness: float = Field(0.2, ge=0, le=1)
    track_width: Optional[int] = Field(160, ge=16)
    max_step_m: float = Field(0.3, gt=0)
    max_step_deg: float = Field(30.0, gt=0)
    prediction_check_m: float = Field(0.08, gt=0)
    prediction_check_deg: float = Field(8.0, gt=0)
    loop: LoopConfig = Field(default_factory=LoopConfig)
    relocalise: RelocConfig = Field(default_factory=RelocConfig)


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
        anchor: frame id of the keyframe the pose is held relative to (itself for a keyframe; -1: none, a lost frame).
        T_anchor: (4, 4) float64 ``c2w_anchor⁻¹ c2w`` at tracking time: when the pose graph corrects the anchor, the
            frame's corrected pose is the anchor's new pose times this (:meth:`RGBDOdometry.corrected`).
        relocalised: the frame was lost to the tracking and found again against a keyframe.
    """

    c2w: np.ndarray
    ok: bool
    reason: str = ""
    fitness: float = 1.0
    keyframe: bool = False
    reference: int = -1
    anchor: int = -1
    T_anchor: Optional[np.ndarray] = None
    relocalised: bool = False
