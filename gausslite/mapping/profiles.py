"""Sensor profiles: loader options and mapper defaults chosen from the dataset's layout.

Real hand-held RGB-D (TUM RGB-D, 7-Scenes, robot bags) differs from rendered sequences (Replica, the
synthetic scene): lens distortion, motion capture poses sampled at other instants than the images,
motion blur and exposure changes. A profile bundles what such data needs by default, so that
``gausslite map --dataset PATH`` is right without flags. Every setting can still be overridden
(``--config``/``--set`` for mapper fields; ``--no-undistort``/``--no-interpolate-poses`` for TUM).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from pydantic import BaseModel

from .config import MapperConfig, deep_merge


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


#: Mapper defaults of hand-held RGB-D (docs/mapper.md "Sensor profiles"; measured on TUM fr1/rpy: docs/results.md):
#: pose refinement from the sensor's pose, a depth loss weight of 0.3 instead of 1 (Kinect depth is noisy and not
#: exactly registered), 20 final iterations per keyframe instead of 5 (the final pass draws every keyframe alike),
#: per-keyframe exposure compensation (the Kinect's auto-exposure and white balance), the camera's motion blur, and
#: the colour camera's rolling shutter with a 20 ms readout (calibrated by bench.rolling_shutter, retired:
#: docs/history.md#rolling_shutter)
_HANDHELD_MAPPER = {"final_iters_per_keyframe": 20.0, "pose": {"refine": True}, "lambda_depth": 0.3,
                    "sensor": {"exposure_comp": True, "motion_blur": True, "rolling_shutter_s": 0.02}}

#: Mapper defaults of rendered sequences: a final pass of 5 iterations per keyframe, drawn uniformly over the
#: mission (MonoGS ends with a colour refinement over all keyframes, Matsuki et al., CVPR 2024); measured on the
#: synthetic circle and room0: docs/results.md "How far ROI effort goes"
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
    "hand-held RGB-D without published distortion (7-Scenes), undistorted by its loader from CameraInfo "
    "(ROS bags) or from its camera file (camera folders), or RealSense recordings: keyframe poses refined from the "
    "sensor's, per-keyframe exposure compensation, the camera's motion blur and rolling shutter, a lighter depth loss, a final pass over every keyframe",
    mapper=_HANDHELD_MAPPER,
)

_BY_LAYOUT = {"replica": RENDERED, "tum": HANDHELD, "7scenes": HANDHELD_PINHOLE, "bag": HANDHELD_PINHOLE,
              "camera": HANDHELD_PINHOLE, "realsense": HANDHELD_PINHOLE}


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
    explicit = _explicit(cfg)
    merged = deep_merge(profile.mapper, explicit)  # what cfg set explicitly wins
    if merged == explicit:  # the profile adds nothing cfg left unset
        return cfg
    return MapperConfig.model_validate(merged)


def _explicit(model) -> dict:
    """The settings of a pydantic model given explicitly (``model_fields_set``), groups recursed into."""
    out = {}
    for k in model.model_fields_set:
        v = getattr(model, k)
        out[k] = _explicit(v) if isinstance(v, BaseModel) else v
    return out


#: Mapper speed presets (``python -m bench.mapper``, retired: docs/history.md#mapper): MapperConfig overrides applied
#: on top of
#: the sensor profile. ``baseline`` is the mapper before the CPU speed work: the reference paths
#: of the ROI-phase Adam step and of SSIM, and the Warp tile compositing kernels. ``fast`` is today's
#: default (the same results to float rounding; SIMD compositing kernels). ``coarse`` and ``window`` cut
#: full-image work (half-resolution first iterations; random half-area windows) and are measured, not
#: recommended: both cost far more than 0.5 dB on room0.
SPEED_PRESETS: dict[str, dict] = {
    "baseline": {"performance": {"reference_paths": True, "cpu_kernel": "tile"}},
    "fast": {},
    "coarse": {"performance": {"coarse_iters": 10}},
    "window": {"performance": {"full_crop_fraction": 0.5}},
}
