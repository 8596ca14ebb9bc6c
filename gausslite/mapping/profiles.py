"""Sensor profiles: loader options and mapper defaults chosen from the dataset's layout.

Real hand-held RGB-D (TUM RGB-D, 7-Scenes, robot bags) differs from rendered sequences (Replica, the
synthetic scene): lens distortion, motion capture poses sampled at other instants than the images,
motion blur and exposure changes. A profile bundles what such data needs by default, so that
``gausslite map --dataset PATH`` is right without flags. Every setting can still be overridden
(``--config``/``--set`` for mapper fields; ``--no-undistort``/``--no-interpolate-poses`` for TUM).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from .config import MapperConfig


@dataclass(frozen=True)
class SensorProfile:
    """Defaults for one kind of data.

    Attributes:
        name: profile name (printed by ``gausslite map``).
        description: one line saying what it is for.
        loader: keyword options for the dataset loader (e.g. TUM ``undistort``, ``interpolate_poses``).
        mapper: MapperConfig field defaults (below ``--config`` and ``--set``).
    """

    name: str
    description: str
    loader: dict = field(default_factory=dict)
    mapper: dict = field(default_factory=dict)


#: Mapper defaults of hand-held RGB-D (measured on TUM fr1/rpy, 150 frames, 320x240, uniform, seed 0; README
#: "Sensor profiles"): pose refinement from the sensor's pose (21.86 dB with it, final pass 5), a depth loss
#: weight of 0.3 instead of 1 (Kinect depth is noisy and not exactly registered: 23.03), and 20 final iterations
#: per keyframe instead of 5 (23.60, first fifth 20.84 -> 22.24: the final pass draws every keyframe alike), and
#: per-keyframe exposure compensation (the Kinect's auto-exposure and white balance; seed 0: 23.49 -> 24.76 dB), and
#: the camera's motion blur (seeds 0-2, paired: uniform +0.13 +- 0.10 dB, GaussLite +0.13 +- 0.05; first - last
#: fifth -2.69 -> -2.11 and -2.36 -> -2.21), and the colour camera's rolling shutter, 20 ms readout (warp PSNR of
#: 60 overlapping frame pairs +1.02 dB, bench.rolling_shutter; first 40 frames, uniform, seed 0: 24.42 -> 27.43 dB;
#: README "Rolling shutter")
_HANDHELD_MAPPER = {"final_iters_per_keyframe": 20.0, "pose_refine": True, "lambda_depth": 0.3, "exposure_comp": True,
                    "motion_blur": True, "rolling_shutter_s": 0.02}

#: Mapper defaults of rendered sequences: a final pass of 5 iterations per keyframe, drawn uniformly over the
#: mission (MonoGS ends with a colour refinement over all keyframes, Matsuki et al., CVPR 2024). Synthetic circle,
#: 150 mapped frames, 3 seeds: uniform 26.13 -> 28.29 dB, GaussLite 26.51 -> 28.27, first - last fifth -1.54 / -0.78
#: -> +0.01 / +0.35; room0 (20 frames, 5 tasks, 3 seeds): GaussLite ROI 40.65 -> 40.61 dB with its PSNR 34.41 ->
#: 40.12, uniform ROI 36.80 -> 39.19 (README "How far ROI effort goes")
_RENDERED_MAPPER = {"final_iters_per_keyframe": 5.0}

RENDERED = SensorProfile("rendered", "rendered sequences (Replica, synthetic): pinhole, exact poses, a short final "
                         "pass over every keyframe", mapper=_RENDERED_MAPPER)
HANDHELD = SensorProfile(
    "handheld",
    "hand-held RGB-D (TUM RGB-D): undistortion with the published calibration, poses interpolated at "
    "the colour timestamps, depth re-projected from its own timestamp, keyframe poses refined from the "
    "sensor's, per-keyframe exposure compensation, the camera's motion blur and rolling shutter, a lighter depth "
    "loss, a final pass "
    "over every keyframe",
    loader={"undistort": True, "interpolate_poses": True, "align_depth_time": True},
    mapper=_HANDHELD_MAPPER,
)
HANDHELD_PINHOLE = SensorProfile(
    "handheld",
    "hand-held RGB-D without published distortion (7-Scenes) or undistorted by its loader from CameraInfo "
    "(ROS bags): keyframe poses refined from the sensor's, per-keyframe exposure compensation, the camera's "
    "motion blur and rolling shutter, a lighter depth loss, a final pass over every keyframe",
    mapper=_HANDHELD_MAPPER,
)

_BY_LAYOUT = {"replica": RENDERED, "tum": HANDHELD, "7scenes": HANDHELD_PINHOLE, "bag": HANDHELD_PINHOLE}


def profile_for_layout(layout: str) -> SensorProfile:
    """The profile of a dataset layout (``detect_layout``'s kind); rendered data for unknown kinds."""
    return _BY_LAYOUT.get(layout, RENDERED)


def with_profile(cfg: "MapperConfig", profile: SensorProfile) -> "MapperConfig":
    """``cfg`` with the profile's mapper defaults for every field ``cfg`` did not set explicitly
    (pydantic ``model_fields_set``: the keys given in YAML, ``--set`` or keyword arguments), as
    ``gausslite map`` layers them (profile below ``--config``/``--set``). Used by the agent for replayed
    datasets, whose mapper settings come from the agent's YAML rather than from ``map``'s flags.

    Args:
        cfg: the configured mapper settings.
        profile: the dataset's sensor profile (:func:`profile_for_layout`).
    Returns:
        A new MapperConfig (``cfg`` itself when the profile sets nothing or ``cfg`` sets all of it).
    Raises:
        pydantic.ValidationError: the combination is invalid (e.g. a profile value out of range).
    """
    from .config import MapperConfig

    todo = {k: v for k, v in profile.mapper.items() if k not in cfg.model_fields_set}
    if not todo:
        return cfg
    return MapperConfig.model_validate({**todo, **cfg.model_dump(include=cfg.model_fields_set)})


#: Mapper speed presets (issue 11, ``python -m bench.mapper``): MapperConfig overrides applied on top of
#: the sensor profile. ``baseline`` is the mapper before the issue-11 speed work: the reference paths
#: of the ROI-phase Adam step and of SSIM, and the Warp tile compositing kernels. ``fast`` is today's
#: default (the same results to float rounding; SIMD compositing kernels). ``coarse`` and ``window`` cut
#: full-image work (half-resolution first iterations; random half-area windows) and are measured, not
#: recommended: both cost far more than 0.5 dB on room0.
SPEED_PRESETS: dict[str, dict] = {
    "baseline": {"reference_paths": True, "cpu_kernel": "tile"},
    "fast": {},
    "coarse": {"coarse_iters": 10},
    "window": {"full_crop_fraction": 0.5},
}
