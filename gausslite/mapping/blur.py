"""Camera motion blur: a view is the mean of renders along the camera's motion during the exposure.

A hand-held camera turns while its shutter is open. TUM fr1/rpy turns at a median 67°/s; over a 10 ms
exposure that is 0.7°, about 3 pixels at 320×240, and up to twice that in the fast passages, where the
mapped frames score 3–4 dB below the slow ones (per-frame PSNR against angular speed: correlation −0.5;
the images' Laplacian variance against angular speed: −0.58). A sharp map cannot match a blurred image,
and fitting one to blurred views blurs the map for the sharp ones. BAD-Gaussians (Zhao et al., ECCV 2024)
and MBA-SLAM (Wang et al., 2024) render a blurred view as the average of sharp renders at virtual poses
sampled along the camera's trajectory within the exposure. This module does the same with the motion
known from the sensor's poses instead of estimating it:

    Ĩ = (1/K) Σ_k I(c2w · E(s_k · ξ_b)),   s_k evenly spaced in [−½, ½],   ξ_b = τ · (ω, v)

with (ω, v) the camera's twist between the previous mapped frame and this one (rad/s, m/s, this camera's
frame; :func:`exposure_twist`), τ the exposure time (``MapperConfig.sensor.blur_exposure_s``) and K chosen from
the blur length in pixels (:func:`blur_samples`). ``E`` is :func:`gausslite.mapping.poses.pose_delta`.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from .poses import pose_delta_np


def exposure_twist(c2w_prev: np.ndarray, t_prev: float, c2w: np.ndarray, t: float, exposure_s: float,
                   max_dt: float = 0.5) -> np.ndarray:
    """The camera's motion over one exposure, ``ξ_b = τ · (ω, v)``, from two consecutive sensor poses.

    Args:
        c2w_prev, c2w: (4, 4) camera-to-world poses (metres, OpenCV camera axes) at times ``t_prev`` < ``t``
            (seconds).
        exposure_s: exposure time τ, seconds.
        max_dt: poses further apart than this (seconds) give no estimate.
    Returns:
        (6,) float64 (ω radians, v metres) in the camera frame of ``c2w``; zeros when ``t − t_prev`` is not
        in (0, max_dt] or a pose is not finite.
    """
    dt = float(t) - float(t_prev)
    if not (0.0 < dt <= max_dt) or not (np.all(np.isfinite(c2w_prev)) and np.all(np.isfinite(c2w))):
        return np.zeros(6)
    rel = np.linalg.inv(np.asarray(c2w_prev, np.float64)) @ np.asarray(c2w, np.float64)
    omega = Rotation.from_matrix(rel[:3, :3]).as_rotvec() / dt
    v = rel[:3, 3] / dt
    return float(exposure_s) * np.concatenate([omega, v])


def blur_length_px(xi_b: np.ndarray, fx: float, width: int, height: int, depth_m: float = 1.5) -> float:
    """Approximate length in pixels of the blur streak of ``xi_b`` (6,): rotation about the optical
    axes x/y moves every pixel by ``fx·|ω_xy|``, roll moves the image corners by ``|ω_z|·max(w, h)/2``,
    and a sideways translation moves a point at ``depth_m`` by ``fx·|v_xy|/depth_m``."""
    w, v = np.asarray(xi_b[:3]), np.asarray(xi_b[3:])
    return float(fx * math.hypot(w[0], w[1]) + abs(w[2]) * max(width, height) / 2 + fx * math.hypot(v[0], v[1]) / depth_m)


def blur_samples(xi_b: np.ndarray, fx: float, width: int, height: int, px_per_sample: float,
                 max_samples: int) -> int:
    """Number K of virtual poses for a blur of ``xi_b``: one per ``px_per_sample`` pixels of streak
    (:func:`blur_length_px`), at most ``max_samples``; 1 means the view is rendered sharp."""
    n = math.ceil(blur_length_px(xi_b, fx, width, height) / px_per_sample)
    return int(min(max(n, 1), max_samples))


def motion_deltas(xi_b: np.ndarray, k: int, centre: float = 0.0,
                  device: Optional[torch.device] = None) -> list[torch.Tensor]:
    """The (4, 4) float64 right corrections ``E((c + s_k) · ξ_b)`` of K ≥ 1 virtual poses, ``s_k =
    linspace(−½, ½, K)`` (``s = 0`` for K = 1) around ``c`` = ``centre`` exposures from the frame's pose (a
    rolling-shutter band's readout time over τ, :mod:`gausslite.mapping.shutter`; 0 for the whole frame). One
    twist, so ``E(c ξ_b) E(s ξ_b) = E((c + s) ξ_b)``."""
    xi = np.asarray(xi_b, np.float64)
    offsets = np.linspace(-0.5, 0.5, k) if k > 1 else np.zeros(1)
    return [torch.from_numpy(pose_delta_np(float(centre + s) * xi)).to(device) for s in offsets]


__all__ = ["exposure_twist", "blur_length_px", "blur_samples", "motion_deltas"]
