"""The views a live map is scored at (docs/realtime.md#scoring-protocols; :mod:`gausslite.evaluation`, which
re-exports every name): a :class:`TrackedView` is a frame's pose and exposure, either predicted by the map from its
training alone (:func:`predicted_view`) or fitted to the frame against the frozen map (:func:`track_view`); a map
without exposure records of a view gets its exposure fitted on the pixels outside the scored ROI
(:func:`fit_exposure_outside_roi`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from gausslite.camera import rotation_angle_deg
from gausslite.datasets.base import Frame
from gausslite.mapping.exposure import apply_exposure
from gausslite.mapping.poses import VectorAdam, pose_delta
from gausslite.mapping.views import keyframe_from_frame
from gausslite.render import RenderOutput

__all__ = ["TrackedView", "pose_offset", "has_exposure_records", "predicted_view", "fit_exposure_outside_roi",
           "track_view"]


@dataclass
class TrackedView:
    """A frame's view for scoring: a pose and exposure fitted to a frozen map by :func:`track_view`, or the pose and
    exposure a map predicts for it (:func:`predicted_view`; ``iters`` 0).

    Attributes:
        c2w: (4, 4) float64 camera-to-world pose (OpenCV camera axes, metres).
        theta: (6,) float64 affine exposure (log gains, offsets; :func:`gausslite.mapping.exposure.apply_exposure`).
        loss: the full-image tracking loss at the last step (NaN for a predicted view).
        rot_deg / trans_m: the pose's rotation (degrees) and translation (metres) away from the sensor's pose.
        iters: Adam steps of the pose fit (0: nothing fitted).
    """

    c2w: np.ndarray
    theta: np.ndarray
    loss: float
    rot_deg: float
    trans_m: float
    iters: int


def pose_offset(c2w0: np.ndarray, c2w: np.ndarray) -> tuple[float, float]:
    """Rotation (degrees) and translation (metres) of ``c2w`` away from ``c2w0`` (both (4, 4))."""
    E = np.linalg.inv(np.asarray(c2w0, np.float64)) @ np.asarray(c2w, np.float64)
    ang = rotation_angle_deg(E)
    return ang, float(np.linalg.norm(E[:3, 3]))


def has_exposure_records(mapper) -> bool:
    """Whether ``mapper`` keeps per-keyframe exposure responses (``sensor.exposure_comp`` and at least one keyframe);
    a fused map (:func:`frozen_mapper`) keeps none."""
    exposure = mapper.sensor.exposure
    return exposure is not None and bool(exposure.params)


def predicted_view(mapper, frame: Frame) -> TrackedView:
    """The pose and exposure ``mapper`` predicts for ``frame`` from its training alone, the ones the ``sensor`` protocol
    renders every frame at (:meth:`~gausslite.mapping.mapper.Mapper.render_frame`): the sensor's pose with the map's
    learned correction (:meth:`~gausslite.mapping.mapper.Mapper.pose_of`: the keyframe's own, or interpolated between
    the keyframes on either side / the nearest one's, ``mapper.pose.between_keyframes``) and the exposure response
    likewise (:meth:`~gausslite.mapping.exposure.ExposureModel.of`; zeros without exposure records). Nothing is fitted
    on ``frame``: its images are never read.

    Args:
        mapper: a :class:`~gausslite.mapping.mapper.Mapper` (not modified). frame: the view (its id and (4, 4)
            ``c2w`` camera-to-world, metres).
    Returns:
        :class:`TrackedView` with ``iters`` 0 and NaN loss.
    """
    c2w = np.asarray(mapper.pose_of(frame.frame_id, frame.c2w), np.float64)
    theta = (np.asarray(mapper.sensor.exposure.of(frame.frame_id), np.float64).copy() if has_exposure_records(mapper)
             else np.zeros(6))
    return TrackedView(c2w, theta, math.nan, *pose_offset(frame.c2w, c2w), 0)


def fit_exposure_outside_roi(out: RenderOutput, frame: Frame, roi: Optional[np.ndarray], iters: int = 100,
                             lr: float = 0.01, alpha_min: float = 0.5, min_fraction: float = 0.05) -> np.ndarray:
    """The affine exposure of a render fitted on the pixels OUTSIDE the scored ROI, for a map that keeps no exposure
    response of the view (a fused map): the appearance of a held-out image is fitted on pixels that are not scored,
    as NeRF-W fits a test image's appearance embedding on its left half and scores the right one (Martin-Brualla et
    al., CVPR 2021) and 3DGS's ``train_test_exp`` fits a test view's exposure on the half it does not score. The
    pose is never fitted and the ROI's pixels never enter the fit.

    ``iters`` Adam steps minimise L1 colour of ``exp(a)·I + b`` against the frame over the pixels outside ``roi`` that
    the map covers (rendered alpha > ``alpha_min``), from θ = 0.

    Args:
        out: the render ((H, W, 3) float colour in [0, 1], (H, W) alpha) at the pose the frame is scored at.
        frame: ground truth (uint8 rgb (H, W, 3)). roi: (H, W) bool scored ROI, or None (no ROI: every covered pixel).
        iters: Adam steps. lr: step size of θ. alpha_min: silhouette threshold. min_fraction: fewer fitting pixels
            than this share of the image: nothing is fitted (θ = 0).
    Returns:
        (6,) float64 θ (log gains, offsets; :func:`gausslite.mapping.exposure.apply_exposure`).
    Raises:
        ValueError: ``iters`` < 0, or a ROI / frame whose size differs from the render's.
    """
    if iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    color = out.color.detach()
    dev = color.device
    gt = torch.from_numpy(np.ascontiguousarray(frame.rgb)).to(dev, torch.float32) / 255.0
    if gt.shape != color.shape or (roi is not None and tuple(np.shape(roi)) != tuple(color.shape[:2])):
        raise ValueError(f"render {tuple(color.shape)}, frame {tuple(gt.shape)} and ROI "
                         f"{None if roi is None else np.shape(roi)} differ in size")
    mask = out.alpha.detach().reshape(color.shape[:2]) > alpha_min
    if roi is not None:
        mask = mask & ~torch.from_numpy(np.asarray(roi, bool)).to(dev)
    theta = np.zeros(6)
    if int(mask.sum()) < min_fraction * mask.numel():
        return theta
    adam = VectorAdam(np.full(6, float(lr)))
    m = mask.float()
    for _ in range(iters):
        th = torch.tensor(theta, dtype=torch.float32, device=dev, requires_grad=True)
        loss = ((apply_exposure(color, th) - gt).abs().sum(-1) * m).sum() / (3.0 * m.sum())
        loss.backward()
        d = adam.delta(0, th.grad.detach().cpu().double().numpy())
        if d is None:
            break
        theta = theta + d
    return theta


def track_view(sensor, frame: Frame, c2w0: np.ndarray, theta0: Optional[np.ndarray] = None, iters: int = 30,
               lr_rot: float = 2e-3, lr_trans: float = 2e-3, lr_exposure: float = 0.01, lambda_depth: float = 0.5,
               alpha_min: float = 0.5) -> TrackedView:
    """Fit a frame's pose and affine exposure to a frozen map, for scoring (the ``tracked`` and ``novel-tracked``
    protocols; MonoGS's evaluation renders every frame at the pose its tracker fitted, Matsuki et al. CVPR 2024).

    The map is never changed. Starting from ``c2w0`` (the sensor's pose) and ``theta0``, ``iters`` Adam steps
    minimise L1 colour (after the exposure ``exp(a)·I + b``) + ``lambda_depth`` · L1 depth over the pixels the
    map covers (rendered alpha > ``alpha_min``; depth where the frame's depth is valid) — the whole image, never
    a task's region, so every map is tracked the same way whatever it was trained for. The pose is corrected on
    the right, ``c2w0 · E(ξ)`` (:mod:`gausslite.mapping.poses`), folded in after every step.

    Args:
        sensor: the map's :class:`~gausslite.mapping.sensor.SensorRenderer` (the sensor model the map was trained
            with: motion blur and rolling shutter render the same way).
        frame: the view (uint8 rgb (H, W, 3), float32 depth (H, W) metres, pinhole intrinsics in pixels).
        c2w0: (4, 4) starting pose. theta0: (6,) starting exposure (None: the identity response).
        iters: Adam steps (fixed, the same for every map). lr_rot (radians), lr_trans (metres), lr_exposure: steps.
        lambda_depth: weight of the depth term. alpha_min: silhouette threshold of the pixels that count.
    Returns:
        :class:`TrackedView`. A map that covers under 5 % of the view is not tracked (the start is returned).
    Raises:
        ValueError: ``iters`` < 0 or a frame whose images do not match its intrinsics.
    """
    if iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    dev = sensor.device
    kf = keyframe_from_frame(frame, dev, None)
    c2w = torch.as_tensor(np.asarray(c2w0, np.float64), device=dev).clone()
    theta = np.zeros(6) if theta0 is None else np.asarray(theta0, np.float64).reshape(6).copy()
    pose_adam = VectorAdam(np.array([lr_rot] * 3 + [lr_trans] * 3))
    expo_adam = VectorAdam(np.full(6, float(lr_exposure)))
    valid_d = kf.depth > 0
    loss_v, done = math.nan, 0
    for _ in range(iters):
        xi = torch.zeros(6, dtype=torch.float64, device=dev, requires_grad=True)
        th = torch.tensor(theta, dtype=torch.float32, device=dev, requires_grad=True)
        out = sensor.render_view(c2w, kf.K, kf.width, kf.height, frame.frame_id, None, pose_xi=xi, detach_map=True)
        mask = out.alpha.detach() > alpha_min
        if int(mask.sum()) < 0.05 * mask.numel():
            break
        color = apply_exposure(out.color, th)
        l1c = ((color - kf.rgb).abs().sum(-1) * mask).sum() / (3.0 * mask.sum())
        dm = mask & valid_d
        l1d = ((out.depth - kf.depth).abs() * dm).sum() / dm.sum().clamp_min(1)
        loss = l1c + lambda_depth * l1d
        loss.backward()
        dxi = pose_adam.delta(0, xi.grad.detach().cpu().double().numpy())
        dth = expo_adam.delta(0, th.grad.detach().cpu().double().numpy())
        if dxi is None or dth is None:
            break
        c2w = c2w @ pose_delta(torch.from_numpy(dxi)).to(dev)
        theta = theta + dth
        loss_v, done = float(loss.detach()), done + 1
    return TrackedView(c2w.cpu().numpy(), theta, loss_v, *pose_offset(c2w0, c2w.cpu().numpy()), done)
