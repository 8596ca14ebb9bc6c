"""Optional sensor error model for the synthetic renders: a Kinect-like RGB-D camera carried by hand.

:func:`gausslite.synthetic.make_scene` applies it with ``sensor_noise="realistic"`` (off by default, so the default
scenes stay byte-identical). The pose written to ``traj.txt`` stays the exact pose of the frame's timestamp (the
centre of the colour exposure and of the colour readout, and the depth image's pose); what the model changes is the
images:

- Depth (:func:`depth_with_errors`), rendered at the frame's pose:

  - axial noise, Gaussian with the standard deviation of Nguyen, Izadi and Lovell (3DIMPVT 2012, Sec. 4, the axial
    noise model fitted to a Kinect): ``sigma_z = 0.0012 + 0.0019 (z - 0.4)^2 + 0.0001 / sqrt(z) * theta^2 /
    (pi/2 - theta)^2`` metres (``z`` depth in metres, ``theta`` the angle between the ray and the surface normal);
  - holes (depth 0): outside the working range ``[0.4, 5.0]`` m; at grazing angles (dropped with a probability
    rising linearly from 0 at 70 degrees to 1 at 85 degrees incidence); on the far side of depth edges (a jump
    to a 4-neighbour of more than ``max(0.05 m, 4 % of z)``, widened by one pixel per 320 image columns, dropped with
    probability 0.7: the projector's shadow and the mixed pixels a structured-light sensor discards); random
    dropouts as blobs (a smooth random field at 1/8 of the resolution, thresholded to 1 % of the pixels) plus
    single pixels (0.3 %).

- Colour (:func:`colour_with_errors`):

  - rolling shutter and motion blur: row ``v`` is exposed over ``[t(v) - exposure_s / 2, t(v) + exposure_s / 2]``
    around ``t(v) = (v / (H - 1) - 1/2) * readout_s`` (both 0.02 s) from the frame's time. The colour is the mean of
    ``K`` images at instants evenly spread over the exposure (one per pixel of streak, at most 8; BAD-Gaussians,
    Zhao et al., ECCV 2024, model a blurred image the same way), each image with every row at its own pose. Each is
    warped from one render at the frame's pose with that render's depth (a pixel's point at its row's pose projected
    into the render, bilinear), the cheap approximation that is exact except where the warp uncovers surfaces;
  - exposure changes: a slowly varying gain ``exp(g(t) + w_c(t))`` per channel and offset ``o(t)``
    (:func:`exposure_track`): ``g`` log-gain of standard deviation 0.12, ``w_c`` white-balance drift 0.03 per
    channel, ``o`` 0.015, each white noise low-passed by a Gaussian of 1.5 s;
  - photon and read noise: Gaussian of variance ``0.004^2 + 0.0001 * I`` on colour in [0, 1].

The numbers above are the ``"realistic"`` level's (the :class:`SensorErrorModel` defaults). The ``"tum"`` level
(:data:`TUM_FR1`) is a sensor as hard as TUM RGB-D fr1's Kinect v1, each value calibrated against a statistic
measured on fr1/rpy (``python -m bench.sensor_calibration``, retired: docs/history.md#sensor_calibration;
docs/mapper.md, "The synthetic sensor calibrated on TUM
fr1"). Besides other values for the parameters above it turns on (:mod:`gausslite.synthetic.kinect`):

- the Kinect's field of view (``fx_per_width``, ``fy_per_height``: :func:`sensor_intrinsics`) instead of the
  scene's 90 degrees;
- depth on the disparity lattice (step ``depth_quant_per_m * z^2``), with axial noise correlated over
  ``depth_noise_corr_px`` pixels before the quantisation;
- holes in the bands the registered depth does not cover (``border_*``), on dark surfaces by grey level of the
  recorded colour (``dark_dropout``), as runs on the far side of depth edges (``shadow_p``, ``shadow_mean_px``), and
  flying pixels between the two sides of an edge (``flying_p``);
- the depth camera offset from the colour camera: rendered at the pose of ``t + dt`` (``depth_time_offset_s`` plus
  Gaussian jitter ``depth_time_jitter_s`` per frame), rotated against the colour camera (``misregistration_*_mrad``:
  :func:`misregistration`), its rows read out over ``depth_readout_s`` (:func:`depth_render`).

``"tum-<fault>"`` (:func:`tum_fault`) turns on one group of the ``"tum"`` level's faults alone
(:data:`TUM_FAULTS`: ``exposure``, ``blur``, ``misregistration``, ``depth-noise``, ``depth-holes``) on its camera;
``"tum-clean"`` is that camera with none (``python -m bench.faults`` maps each).

Poses between frames (blur instants, shutter rows, the depth's delay) come from the trajectory by :func:`pose_at`
(rotation slerp, translation linear interpolation, in fractional frame index at the writer's frame rate). All
randomness is drawn from one seeded generator per agent, so equal arguments give byte-identical files; a part that
is off draws nothing, so the ``"realistic"`` level's files are those it wrote before the ``"tum"`` level existed.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Optional, Tuple

import cv2
import numpy as np

from gausslite.camera import Intrinsics
from gausslite.synthetic import kinect
from gausslite.synthetic.raycast import RenderResult, camera_rays, render
from gausslite.synthetic.scene import Scene

@dataclass(frozen=True)
class SensorErrorModel:
    """Parameters of the sensor error model (module docstring; lengths in metres, times in seconds, angles in
    degrees, colour in [0, 1]; ``misregistration_*_mrad`` in milliradians, ``*_px`` in pixels of the rendered image,
    ``border_*`` fractions of its height or width, ``dark_dropout`` ``(grey level 0..255, probability)`` knots,
    ``depth_quant_per_m`` the lattice step of ``1 / z`` in 1/m). The defaults are the ``"realistic"`` level."""

    depth_sigma_a: float = 0.0012
    depth_sigma_b: float = 0.0019
    depth_sigma_z0: float = 0.4
    depth_sigma_angle: float = 0.0001
    depth_min_m: float = 0.4
    depth_max_m: float = 5.0
    grazing_start_deg: float = 70.0
    grazing_full_deg: float = 85.0
    edge_jump_m: float = 0.05
    edge_jump_rel: float = 0.04
    edge_drop_p: float = 0.7
    blob_fraction: float = 0.01
    speckle_fraction: float = 0.003
    exposure_s: float = 0.02
    readout_s: float = 0.02
    max_blur_samples: int = 8
    gain_log_std: float = 0.12
    white_balance_std: float = 0.03
    offset_std: float = 0.015
    exposure_smooth_s: float = 1.5
    read_noise: float = 0.004
    shot_noise: float = 0.0001
    # the structured-light depth camera (gausslite.synthetic.kinect); all off at the defaults ("realistic")
    depth_quant_per_m: float = 0.0
    depth_noise_corr_px: float = 0.0
    depth_time_offset_s: float = 0.0
    depth_time_jitter_s: float = 0.0
    depth_readout_s: float = 0.0
    misregistration_x_mrad: float = 0.0
    misregistration_y_mrad: float = 0.0
    border_top: float = 0.0
    border_bottom: float = 0.0
    border_left: float = 0.0
    border_right: float = 0.0
    dark_dropout: Tuple[Tuple[float, float], ...] = ()
    shadow_p: float = 0.0
    shadow_mean_px: float = 1.0
    flying_p: float = 0.0
    # the camera's focal lengths over the image width and height (0: the scene's own 90-degree camera)
    fx_per_width: float = 0.0
    fy_per_height: float = 0.0

    def to_json(self) -> dict:
        """The parameters as a JSON-ready dict (written to ``scene.json``)."""
        return asdict(self)

    @property
    def moves_depth(self) -> bool:
        """Whether the depth image is taken at another pose than the colour image's (time offset, depth rolling
        shutter, misregistration), so that :func:`render_with_errors` renders it on its own."""
        return bool(self.depth_time_offset_s or self.depth_time_jitter_s or self.depth_readout_s
                    or self.misregistration_x_mrad or self.misregistration_y_mrad)


def sensor_intrinsics(model: SensorErrorModel, width: int, height: int) -> Intrinsics:
    """The camera of a sensor model at ``width`` x ``height`` pixels: focal lengths ``model.fx_per_width * width``
    and ``model.fy_per_height * height`` (pixels), principal point at the image centre; the scene's own camera
    (:func:`gausslite.synthetic.writer.default_intrinsics`, 90 degrees across) where they are 0.

    Raises:
        ValueError: ``width < 16`` or ``height < 12``.
    """
    if int(width) < 16 or int(height) < 12:
        raise ValueError(f"image too small: {width}x{height} (minimum 16x12)")
    fx = model.fx_per_width * width if model.fx_per_width > 0 else width / 2.0
    fy = model.fy_per_height * height if model.fy_per_height > 0 else width / 2.0
    return Intrinsics(fx=float(fx), fy=float(fy), cx=(width - 1) / 2.0, cy=(height - 1) / 2.0, width=int(width),
                      height=int(height))


#: The ``"tum"`` level: the Kinect v1 of TUM RGB-D fr1, each value measured on fr1/rpy as ``bench.odometry`` reads it
#: (320x240, undistorted) by ``python -m bench.sensor_calibration``, retired: docs/history.md#sensor_calibration
#: (docs/mapper.md, "The synthetic sensor calibrated
#: on TUM fr1"). Read from a TUM statistic directly: the camera (the undistorted fr1 camera, 546.75 / 640 and
#: 543.09 / 480), the disparity lattice (depth step 2.8e-3 z^2), the border bands without depth, the holes by grey
#: level, the misregistration (depth edges 1.04 px below colour edges at fy 271.5: 3.8 mrad), the depth's delay (the
#: depth minus colour timestamps, 7.6 +- 4.7 ms), the exposure track (log gain 0.16, smoothed over 0.325 s, white
#: balance 0.035) and the colour readout (25 ms, ``python -m bench.rolling_shutter``, retired:
#: docs/history.md#rolling_shutter). Chosen so that the walk's
#: statistic matches TUM's: the axial noise (a, b, correlation: the plane-fit residuals), blobs, shadows, grazing
#: angles and flying pixels (the holes and the pixels at depth edges), the exposure time (the blur estimate on a walk
#: moving as fast as TUM's images) and no added colour noise (TUM's images are smoother than the renders). The
#: depth camera's rows are taken to be read like the colour camera's (``depth_readout_s``; not measured).
TUM_FR1 = SensorErrorModel(
    depth_sigma_a=0.0004, depth_sigma_b=0.0016, depth_noise_corr_px=1.0, depth_quant_per_m=0.0028,
    grazing_start_deg=85.0, grazing_full_deg=89.5, edge_drop_p=0.0, blob_fraction=0.03, speckle_fraction=0.0,
    shadow_p=0.035, shadow_mean_px=4.5, flying_p=0.01,
    border_top=0.0667, border_bottom=0.0, border_left=0.0063, border_right=0.0625,
    dark_dropout=((10.0, 0.236), (30.0, 0.19), (50.0, 0.07), (75.0, 0.025), (110.0, 0.017), (192.5, 0.0)),
    depth_time_offset_s=0.0076, depth_time_jitter_s=0.0047, depth_readout_s=0.025,
    misregistration_x_mrad=0.0, misregistration_y_mrad=3.8,
    exposure_s=0.031, readout_s=0.025, gain_log_std=0.16, white_balance_std=0.035, offset_std=0.0,
    exposure_smooth_s=0.325, read_noise=0.0, shot_noise=0.0,
    fx_per_width=546.75 / 640, fy_per_height=543.09 / 480,
)

#: :data:`TUM_FR1`'s faults, each group of its fields alone: the walk rendered with one of them (``tum-<fault>``)
#: against the same camera without any (``tum-clean``) tells what that fault of a real sensor costs the map
TUM_FAULTS = {
    "exposure": ("gain_log_std", "white_balance_std", "offset_std", "exposure_smooth_s"),
    "blur": ("exposure_s", "readout_s", "max_blur_samples"),  # the colour camera's motion blur and rolling shutter
    # the depth camera registered off the colour camera, in angle and in time
    "misregistration": ("misregistration_x_mrad", "misregistration_y_mrad", "depth_time_offset_s",
                        "depth_time_jitter_s", "depth_readout_s"),
    "depth-noise": ("depth_sigma_a", "depth_sigma_b", "depth_sigma_z0", "depth_sigma_angle", "depth_noise_corr_px",
                    "depth_quant_per_m"),
    # holes (grazing angles, blobs, dark surfaces, border bands, shadows) and flying pixels at depth edges
    "depth-holes": ("grazing_start_deg", "grazing_full_deg", "edge_jump_m", "edge_jump_rel", "edge_drop_p",
                    "blob_fraction", "speckle_fraction", "dark_dropout", "shadow_p", "shadow_mean_px", "flying_p",
                    "border_top", "border_bottom", "border_left", "border_right"),
}
#: TUM fr1's camera without any of its faults: exact colour and depth (within its 0.4-5 m range) through its lens
TUM_CLEAN = SensorErrorModel(
    depth_sigma_a=0.0, depth_sigma_b=0.0, depth_sigma_angle=0.0, grazing_start_deg=90.0, grazing_full_deg=91.0,
    edge_drop_p=0.0, blob_fraction=0.0, speckle_fraction=0.0, exposure_s=0.0, readout_s=0.0, gain_log_std=0.0,
    white_balance_std=0.0, offset_std=0.0, read_noise=0.0, shot_noise=0.0,
    fx_per_width=TUM_FR1.fx_per_width, fy_per_height=TUM_FR1.fy_per_height,
)


def tum_fault(name: str) -> SensorErrorModel:
    """:data:`TUM_CLEAN` with one fault of :data:`TUM_FR1` (a :data:`TUM_FAULTS` name; ``"clean"``: none).

    Raises:
        ValueError: an unknown fault.
    """
    if name == "clean":
        return TUM_CLEAN
    if name not in TUM_FAULTS:
        raise ValueError(f"unknown fault {name!r}; expected clean or one of {tuple(TUM_FAULTS)}")
    return replace(TUM_CLEAN, **{f: getattr(TUM_FR1, f) for f in TUM_FAULTS[name]})


#: the levels of ``make_scene(sensor_noise=...)``: None = exact renders
SENSOR_LEVELS = {"none": None, "realistic": SensorErrorModel(), "tum": TUM_FR1,
                 **{f"tum-{f}": tum_fault(f) for f in ("clean", *TUM_FAULTS)}}
#: names accepted by ``make_scene(sensor_noise=...)`` / ``make-scene --sensor-noise``
SENSOR_NOISE = tuple(SENSOR_LEVELS)


def sensor_model(name: str) -> Optional[SensorErrorModel]:
    """The model named ``name``: None for ``"none"``, the default :class:`SensorErrorModel` for ``"realistic"``,
    :data:`TUM_FR1` for ``"tum"``, one of its faults alone for ``"tum-<fault>"`` (:func:`tum_fault`; ``"tum-clean"``:
    its camera without any).

    Raises:
        ValueError: an unknown name.
    """
    if name not in SENSOR_NOISE:
        raise ValueError(f"unknown sensor noise {name!r}; expected one of {SENSOR_NOISE}")
    return SENSOR_LEVELS[name]


def pose_at(poses: np.ndarray, t: float) -> np.ndarray:
    """The pose at fractional frame index ``t`` of a trajectory (clamped to ``[0, N - 1]``): rotation slerped and
    translation interpolated linearly between the two neighbouring frames.

    Args:
        poses: (N, 4, 4) float64 camera-to-world poses (metres, OpenCV camera axes), N >= 1.
        t: fractional frame index.
    Returns:
        (4, 4) float64 camera-to-world pose.
    """
    return poses_at(poses, np.array([float(t)]))[0]


def exposure_track(rng: np.random.Generator, n_frames: int, fps: float,
                   model: SensorErrorModel) -> Tuple[np.ndarray, np.ndarray]:
    """Per-frame colour response of the camera's auto-exposure and white balance.

    Args:
        rng: the agent's generator. n_frames: frames. fps: frame rate (frames per second). model: the parameters.
    Returns:
        ``(gain (n, 3) float64, offset (n,) float64)``: frame ``i``'s colour is ``gain[i] * I + offset[i]``.
    """
    from scipy.ndimage import gaussian_filter1d  # noqa: PLC0415 - SciPy is not in the light install

    sigma = max(model.exposure_smooth_s * fps, 0.5)

    def smooth(k: int) -> np.ndarray:
        x = gaussian_filter1d(rng.standard_normal((int(n_frames) + 1, k)), sigma=sigma, axis=0, mode="nearest")
        return (x / np.maximum(x.std(axis=0), 1e-12))[: int(n_frames)]

    log_gain = model.gain_log_std * smooth(1) + model.white_balance_std * smooth(3)
    return np.exp(log_gain), model.offset_std * smooth(1)[:, 0]


def _image_motion_px(poses: np.ndarray, i: int, fps: float, f_px: float) -> float:
    """Image motion (pixels per second) of frame ``i``: ``f * (|omega| + |v| / 1 m)`` from its neighbours' poses."""
    a, b = poses[max(i - 1, 0)], poses[min(i + 1, len(poses) - 1)]
    dt = (min(i + 1, len(poses) - 1) - max(i - 1, 0)) / fps
    if dt <= 0:
        return 0.0
    rel = np.linalg.inv(a) @ b
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 - SciPy is not in the light install

    ang = Rotation.from_matrix(rel[:3, :3]).magnitude()
    return f_px * (ang + float(np.linalg.norm(rel[:3, 3])) / 1.0) / dt


def poses_at(poses: np.ndarray, ts: np.ndarray) -> np.ndarray:
    """:func:`pose_at` for many instants at once.

    Args:
        poses: (N, 4, 4) float64 camera-to-world poses (metres), N >= 1. ts: (M,) fractional frame indices.
    Returns:
        (M, 4, 4) float64 camera-to-world poses.
    """
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 - SciPy is not in the light install

    n = len(poses)
    ts = np.clip(np.asarray(ts, np.float64), 0.0, n - 1)
    out = np.repeat(np.eye(4)[None], len(ts), axis=0)
    if n == 1:
        out[:] = poses[0]
        return out
    seg = np.minimum(np.floor(ts).astype(int), n - 2)
    for j in np.unique(seg):
        m = seg == j
        a = ts[m] - j
        R0, R1 = poses[j][:3, :3], poses[j + 1][:3, :3]
        step = Rotation.from_matrix(R0.T @ R1).as_rotvec()
        out[m, :3, :3] = R0 @ Rotation.from_rotvec(a[:, None] * step[None]).as_matrix()
        out[m, :3, 3] = (1.0 - a)[:, None] * poses[j][:3, 3] + a[:, None] * poses[j + 1][:3, 3]
    return out


def _warp_rows(rgb: np.ndarray, depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray,
               row_poses: np.ndarray) -> np.ndarray:
    """The image a camera whose row ``v`` sits at ``row_poses[v]`` (H, 4, 4) would see, warped from ``rgb`` (H, W, 3)
    rendered at ``c2w`` with its ``depth`` (H, W): each pixel's point (at its own depth) projected into the render."""
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    cam = np.stack([(u - intr.cx) / intr.fx * depth, (v - intr.cy) / intr.fy * depth, depth], axis=-1)
    rel = np.linalg.inv(c2w)[None] @ row_poses  # (H, 4, 4): row camera -> render camera
    p = np.einsum("hij,hwj->hwi", rel[:, :3, :3], cam) + rel[:, None, :3, 3]
    z = np.maximum(p[..., 2], 1e-6)
    mx = (intr.fx * p[..., 0] / z + intr.cx).astype(np.float32)
    my = (intr.fy * p[..., 1] / z + intr.cy).astype(np.float32)
    return cv2.remap(rgb.astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def colour_with_errors(render_at_pose: RenderResult, intr: Intrinsics, poses: np.ndarray, i: int, fps: float,
                       model: SensorErrorModel, rng: np.random.Generator, gain: np.ndarray,
                       offset: float) -> np.ndarray:
    """Frame ``i``'s colour image with rolling shutter, motion blur, exposure and noise (module docstring).

    Args:
        render_at_pose: the exact render at ``poses[i]`` (its rgb and depth). intr: intrinsics (pixels).
        poses: (N, 4, 4) float64 c2w trajectory (metres). i: frame index. fps: frame rate (frames per second).
        model: parameters. rng: the agent's generator. gain: (3,) this frame's colour gain. offset: this frame's
        colour offset.
    Returns:
        (H, W, 3) uint8 RGB.
    """
    H = intr.height
    speed = _image_motion_px(poses, i, fps, 0.5 * (intr.fx + intr.fy))
    n_blur = int(np.clip(math.ceil(speed * model.exposure_s), 1, model.max_blur_samples))
    t_row = (np.arange(H) / max(H - 1, 1) - 0.5) * model.readout_s
    acc = np.zeros(render_at_pose.rgb.shape)
    for k in range(n_blur):
        t_blur = ((k + 0.5) / n_blur - 0.5) * model.exposure_s
        rows = poses_at(poses, i + (t_blur + t_row) * fps)
        acc += _warp_rows(render_at_pose.rgb, render_at_pose.depth, intr, poses[i], rows)
    img = acc / (255.0 * n_blur)
    img = img * np.asarray(gain)[None, None, :] + offset
    img = img + rng.standard_normal(img.shape) * np.sqrt(model.read_noise ** 2 + model.shot_noise * np.clip(img, 0, 1))
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)


def _edge_holes(z: np.ndarray, model: SensorErrorModel) -> np.ndarray:
    """(H, W) bool: pixels on the far side of a depth edge (a jump to a 4-neighbour above the threshold), widened."""
    far = np.zeros(z.shape, bool)
    for axis in (0, 1):
        d = np.diff(z, axis=axis)
        zmax = np.maximum(np.delete(z, 0, axis), np.delete(z, -1, axis))
        jump = np.abs(d) > np.maximum(model.edge_jump_m, model.edge_jump_rel * zmax)
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        far[tuple(hi)] |= jump & (d > 0)  # the later pixel is farther
        far[tuple(lo)] |= jump & (d < 0)
    width = max(1, round(z.shape[1] / 320))
    if width > 1:
        far = cv2.dilate(far.astype(np.uint8), np.ones((2 * width - 1, 2 * width - 1), np.uint8)) > 0
    return far


def depth_with_errors(r: RenderResult, intr: Intrinsics, c2w: np.ndarray, model: SensorErrorModel,
                      rng: np.random.Generator, grey: Optional[np.ndarray] = None) -> np.ndarray:
    """The depth image of a render with the model's holes and axial noise (module docstring), and the
    structured-light effects the model turns on (:mod:`gausslite.synthetic.kinect`: border bands, dark surfaces,
    edge shadows, flying pixels, correlated noise, disparity quantisation).

    Args:
        r: the render at the depth camera's pose (its ``depth``, 0 = nothing seen, and ``normal``). intr: intrinsics
        (pixels). c2w: (4, 4) float64 camera-to-world pose of the render (metres). model: parameters. rng: the
        agent's generator. grey: (H, W) grey level 0..255 of the surfaces for ``model.dark_dropout`` (default: the
        render's own colour).
    Returns:
        (H, W) float64 depth in metres, 0 where the sensor has none.
    Raises:
        ValueError: the render has no normals.
    """
    if r.normal is None:
        raise ValueError("depth_with_errors needs a render with surface normals")
    z = r.depth
    H, W = z.shape
    _, d = camera_rays(intr, c2w)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    cos = np.abs(np.einsum("ij,ij->i", d, r.normal.reshape(-1, 3))).reshape(H, W)
    theta = np.arccos(np.clip(cos, 0.0, 1.0))
    p_graze = np.clip((np.degrees(theta) - model.grazing_start_deg)
                      / (model.grazing_full_deg - model.grazing_start_deg), 0.0, 1.0)
    holes = rng.random((H, W)) < p_graze
    holes |= _edge_holes(z, model) & (rng.random((H, W)) < model.edge_drop_p)
    field = cv2.resize(rng.random((max(H // 8, 2), max(W // 8, 2))), (W, H), interpolation=cv2.INTER_LINEAR)
    holes |= field < np.quantile(field, model.blob_fraction)
    holes |= rng.random((H, W)) < model.speckle_fraction
    holes |= (z < model.depth_min_m) | (z > model.depth_max_m)
    holes, z = _structured_light(z, holes, model, rng, r.rgb if grey is None else grey)
    th = np.minimum(theta, np.deg2rad(85.0))
    sigma = (model.depth_sigma_a + model.depth_sigma_b * (z - model.depth_sigma_z0) ** 2
             + model.depth_sigma_angle / np.sqrt(np.maximum(z, 1e-3)) * th ** 2 / (np.pi / 2 - th) ** 2)
    noise = (kinect.correlated_field(rng, (H, W), model.depth_noise_corr_px) if model.depth_noise_corr_px > 0
             else rng.standard_normal((H, W)))
    noisy = kinect.quantise_disparity(z + sigma * noise, model.depth_quant_per_m)
    return np.where(holes | (noisy <= 0), 0.0, noisy)


def _structured_light(z: np.ndarray, holes: np.ndarray, model: SensorErrorModel, rng: np.random.Generator,
                      grey: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """``(holes, depth)`` with the structured-light holes and flying pixels the model turns on (each draws from
    ``rng`` only when it is on, so the ``"realistic"`` level's images stay as they were)."""
    if model.border_top or model.border_bottom or model.border_left or model.border_right:
        holes = holes | kinect.border_holes(z.shape, model.border_top, model.border_bottom, model.border_left,
                                            model.border_right)
    if model.dark_dropout:
        g = np.asarray(grey, np.float64)
        g = g @ np.array([0.299, 0.587, 0.114]) if g.ndim == 3 else g
        holes = holes | kinect.dark_dropout(g, rng, model.dark_dropout)
    if model.shadow_p > 0:
        holes = holes | kinect.edge_shadows(z, rng, model.shadow_p, model.shadow_mean_px, model.edge_jump_m,
                                            model.edge_jump_rel)
    if model.flying_p > 0:
        z = kinect.flying_pixels(z, rng, model.flying_p, model.edge_jump_m, model.edge_jump_rel)
    return holes, z


def misregistration(model: SensorErrorModel) -> np.ndarray:
    """(4, 4) float64 pose of the depth camera in the colour camera's frame: the rotation that moves the depth
    image's content ``model.misregistration_x_mrad * fx / 1000`` pixels right and ``misregistration_y_mrad * fy /
    1000`` pixels down against the colour image (for small angles; no translation)."""
    from scipy.spatial.transform import Rotation  # noqa: PLC0415 - SciPy is not in the light install

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([1e-3 * model.misregistration_y_mrad, -1e-3 * model.misregistration_x_mrad,
                                      0.0]).as_matrix()
    return T


def depth_render(scene: Scene, intr: Intrinsics, poses: np.ndarray, i: int, fps: float, model: SensorErrorModel,
                 rng: np.random.Generator) -> Tuple[RenderResult, np.ndarray]:
    """The exact depth the depth camera sees for frame ``i``: rendered at the pose of ``t + dt`` (``dt`` =
    ``model.depth_time_offset_s`` plus Gaussian jitter of ``depth_time_jitter_s``, one draw from ``rng`` when it is
    on) times :func:`misregistration`, each row moved to its readout time over ``model.depth_readout_s``
    (:func:`gausslite.synthetic.kinect.warp_depth_rows`).

    Returns:
        ``(render, c2w)``: the render (its depth 0 where a row's view falls outside it) and its (4, 4) pose.
    Raises:
        ValueError: a pose outside the room or not rigid.
    """
    dt = model.depth_time_offset_s
    if model.depth_time_jitter_s > 0:
        dt += model.depth_time_jitter_s * float(rng.standard_normal())
    T = misregistration(model)
    c2w = pose_at(poses, i + dt * fps) @ T
    r = render(scene, intr, c2w)
    if model.depth_readout_s > 0:
        H = intr.height
        t_row = (np.arange(H) / max(H - 1, 1) - 0.5) * model.depth_readout_s
        rows = poses_at(poses, i + (dt + t_row) * fps) @ T[None]
        r = RenderResult(rgb=r.rgb, depth=kinect.warp_depth_rows(r.depth, intr, c2w, rows), ids=r.ids,
                         normal=r.normal)
    return r, c2w


def render_with_errors(scene: Scene, intr: Intrinsics, poses: np.ndarray, i: int, fps: float,
                       model: SensorErrorModel, rng: np.random.Generator, gain: np.ndarray,
                       offset: float) -> RenderResult:
    """Frame ``i`` of a trajectory as the modelled sensor records it: one exact render at the frame's pose, colour
    from :func:`colour_with_errors`, depth from :func:`depth_with_errors` (of a render of its own from
    :func:`depth_render` when the depth camera is offset in time or pose; dark surfaces judged by the recorded
    colour, as the calibration measures them); ``ids`` and ``normal`` are the exact render's.

    Args:
        scene: the scene. intr: intrinsics (pixels). poses: (N, 4, 4) float64 c2w trajectory (metres). i: frame
        index. fps, model, rng, gain, offset: as :func:`colour_with_errors`.
    Returns:
        :class:`RenderResult` (rgb (H, W, 3) uint8, depth (H, W) float64 metres with 0 = no depth).
    Raises:
        ValueError: a pose outside the room or not rigid.
    """
    exact = render(scene, intr, poses[i])
    rgb = colour_with_errors(exact, intr, poses, i, fps, model, rng, gain, offset)
    if model.moves_depth:
        rd, c2w_d = depth_render(scene, intr, poses, i, fps, model, rng)
        depth = depth_with_errors(rd, intr, c2w_d, model, rng, grey=rgb)
    else:
        depth = depth_with_errors(exact, intr, poses[i], model, rng)
    return RenderResult(rgb=rgb, depth=depth, ids=exact.ids, normal=exact.normal)
