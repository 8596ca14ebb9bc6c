"""Keyframe placement: a new keyframe's pose tracked against the frozen Gaussian map before it seeds or trains.

A keyframe arrives with a pose from the robot (motion capture, its own SLAM, or :mod:`gausslite.odometry.rgbd`).
Seeding back-projects its depth at that pose, so a pose a few centimetres off puts its new Gaussians a few
centimetres beside the surfaces the map already holds, and every later iteration on the keyframe pulls the map
towards the wrong place. :class:`FrameTracker` first aligns the keyframe with what the map already explains, as
SplaTAM tracks every frame against its Gaussians before mapping it (Keetha et al., CVPR 2024, Sec. 3.3) and MonoGS
tracks before it inserts a keyframe (Matsuki et al., CVPR 2024, Sec. 3.2):

- only the pose moves: the map is detached (:meth:`SensorRenderer.render_view` with ``detach_map``), the pose is
  corrected on the right, ``c2w · E(ξ)`` (:mod:`gausslite.mapping.poses`), with Adam steps whose size decays along a
  cosine. The Adam keeps one second moment for the rotation and one for the translation (:class:`BlockAdam`), so a
  component with a near-zero gradient (a direction the view hardly constrains) moves little instead of a full step;
- the view is rendered at a reduced resolution (``pose.track_width``;
  :func:`~gausslite.mapping.views.downscale_keyframe`),
  through the sensor model and the exposure response the mapper keeps;
- the loss is colour L1 + λ depth L1 over the pixels the map explains (silhouette > ``pose.track_alpha``), each pixel
  weighted by a robust Cauchy weight of its residual (MAD scale; ``pose.track_robust_k``) and, in GaussLite mode, by
  1 + ``pose.track_roi_weight`` on the task's relevant pixels, where the map is sharpest;
- it stops after ``pose.track_iters`` steps, when the loss stops dropping (``pose.track_converge``), or, under a
  keyframe time budget, at a deadline the mapper gives (``pose.track_budget_frac`` of the budget); the pose of the
  lowest loss seen is kept;
- a sanity gate rejects a correction larger than ``pose.track_max_trans_m`` / ``pose.track_max_rot_deg``: the
  keyframe then keeps the pose it came with, and the rejection is logged.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from gausslite.camera import rotation_angle_deg
from gausslite.datasets.base import Frame
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.model import cosine_lr_factor
from gausslite.mapping.poses import pose_delta
from gausslite.mapping.sensor import SensorRenderer
from gausslite.mapping.views import Keyframe, downscale_keyframe, keyframe_from_frame

log = logging.getLogger(__name__)

#: steps without a relative loss drop of ``pose.track_converge`` after which tracking stops
PATIENCE = 10
#: a view the map covers on fewer than this share of its pixels is not tracked (nothing to track against)
MIN_COVERAGE = 0.05
#: the last Adam step's size relative to the first (cosine decay)
FINAL_LR = 0.1


class BlockAdam:
    """Adam (Kingma & Ba, ICLR 2015) whose second moment is shared within blocks of the parameter vector (block-wise
    adaptivity, Zheng & Kwok 2019): the step keeps the gradient's direction within a block, its size ``lr`` × the
    block's normalised first moment. For a pose ξ = (ω, v) the blocks are the rotation and the translation.

    Args:
        lr: (D,) step size per component. blocks: (D,) int block index of each component.
        b1, b2, eps: Adam's constants.
    """

    def __init__(self, lr: np.ndarray, blocks: np.ndarray, b1: float = 0.9, b2: float = 0.999,
                 eps: float = 1e-12) -> None:
        self.lr, self.blocks = np.asarray(lr, np.float64), np.asarray(blocks, np.int64)
        self.b1, self.b2, self.eps = b1, b2, eps
        self.m = np.zeros(self.lr.shape[0])
        self.v = np.zeros(int(self.blocks.max()) + 1)
        self.t = 0

    def delta(self, grad: np.ndarray) -> Optional[np.ndarray]:
        """The (D,) update for gradient ``grad`` (D,) (to be added to the parameters), or None for a gradient that
        is not finite (no state changes then)."""
        g = np.asarray(grad, np.float64)
        if not np.all(np.isfinite(g)):
            return None
        self.t += 1
        self.m = self.b1 * self.m + (1 - self.b1) * g
        self.v = self.b2 * self.v + (1 - self.b2) * np.bincount(self.blocks, g * g) / np.bincount(self.blocks)
        mhat = self.m / (1 - self.b1 ** self.t)
        vhat = self.v / (1 - self.b2 ** self.t)
        return -self.lr * mhat / (np.sqrt(vhat[self.blocks]) + self.eps)


@dataclass
class TrackResult:
    """What placing one keyframe did.

    Attributes:
        c2w: (4, 4) float64 camera-to-world pose the keyframe is placed at (metres, OpenCV camera axes): the tracked
            pose, or the input pose when the tracker found nothing to track against or the gate rejected it.
        iters: Adam steps taken.
        accepted: the tracked pose was kept (False: no coverage, or rejected by the gate).
        stop: why tracking stopped: ``"iters"``, ``"converged"``, ``"deadline"``, ``"coverage"`` or ``"gradient"``.
        rot_deg / trans_m: the tracked correction's rotation (degrees) and translation (metres), rejected or not.
        loss0 / loss: the monitored loss (colour L1 + λ depth L1 over the explained pixels) at the input pose and at
            the kept pose (NaN when nothing was rendered).
    """

    c2w: np.ndarray
    iters: int
    accepted: bool
    stop: str
    rot_deg: float = 0.0
    trans_m: float = 0.0
    loss0: float = math.nan
    loss: float = math.nan


def robust_weights(residual: torch.Tensor, mask: torch.Tensor, k: float) -> torch.Tensor:
    """Cauchy (Lorentzian) IRLS weights ``1 / (1 + (r / (k σ))²)`` of per-pixel residuals, ``σ = 1.4826 · median``
    of the residuals inside ``mask`` (the MAD scale of a zero-median residual); the weights of a robust M-estimator
    (Black & Anandan 1996), as dense RGB-D tracking weights its residuals (Kerl, Sturm, Cremers, ICRA 2013).

    Args:
        residual: (H, W) float absolute residuals (no gradient is taken through the weights).
        mask: (H, W) bool pixels that count. k: scale in σ units; 0 gives weight 1 everywhere.
    Returns:
        (H, W) float weights in (0, 1], 1 outside ``mask`` (callers mask them anyway).
    """
    r = residual.detach()
    if k <= 0 or not bool(mask.any()):
        return torch.ones_like(r)
    sigma = (1.4826 * r[mask].median()).clamp_min(1e-6)
    return 1.0 / (1.0 + (r / (k * sigma)) ** 2)


def tracking_factor(width: int, track_width: Optional[int]) -> int:
    """The integer downscale factor of a ``width``-pixel view tracked at about ``track_width`` pixels (None: 1)."""
    return 1 if track_width is None else max(1, int(width) // int(track_width))


class FrameTracker:
    """Frame-to-map tracking of a new keyframe (module docstring).

    Args:
        cfg: mapper configuration (``pose.track_*``, ``lambda_depth``, the mode).
        sensor: the mapper's sensor renderer (its model is read, never changed; its clock is charged for every
            render under a deterministic budget clock).
        clock: the mapper's budget clock (deadlines are in its seconds).
    """

    def __init__(self, cfg: MapperConfig, sensor: SensorRenderer, clock) -> None:
        self.cfg, self.sensor, self.clock = cfg, sensor, clock

    def view(self, frame: Frame, relevance: Optional[np.ndarray]) -> Keyframe:
        """``frame`` as the tracker renders it: float tensors on the sensor's device at the tracking resolution,
        with its relevance map as the ROI in GaussLite mode (pixels of the task weigh more)."""
        use_roi = self.cfg.effective().roi and relevance is not None and self.cfg.pose.track_roi_weight > 0
        kf = keyframe_from_frame(frame, self.sensor.device, relevance if use_roi else None)
        kf.c2w = kf.c2w.clone()
        return downscale_keyframe(kf, tracking_factor(kf.width, self.cfg.pose.track_width))

    def loss(self, out, kf: Keyframe) -> tuple[Optional[torch.Tensor], float]:
        """The tracking loss of render ``out`` against view ``kf``: the robust, ROI-weighted colour + λ depth L1
        (differentiable), and the monitored plain L1 (float) over the same pixels; ``(None, nan)`` when the map
        covers under :data:`MIN_COVERAGE` of the view."""
        pc = self.cfg.pose
        mask = out.alpha.detach() > pc.track_alpha
        if int(mask.sum()) < MIN_COVERAGE * mask.numel():
            return None, math.nan
        lam = self.cfg.lambda_depth if pc.track_lambda_depth is None else pc.track_lambda_depth
        w = mask.float()
        if kf.roi is not None:
            w = w * (1.0 + pc.track_roi_weight * kf.roi.float())
        dmask = mask & (kf.depth > 0)
        rc = (out.color - kf.rgb).abs().mean(-1)
        rd = (out.depth - kf.depth).abs() * dmask
        wc = w * robust_weights(rc, mask, pc.track_robust_k)
        wd = w * dmask * robust_weights(rd, dmask, pc.track_robust_k)
        loss = (wc * rc).sum() / wc.sum() + lam * (wd * rd).sum() / wd.sum().clamp_min(1e-12)
        rc0, rd0 = rc.detach(), rd.detach()
        plain = float(rc0[mask].mean()) + lam * (float(rd0[dmask].mean()) if bool(dmask.any()) else 0.0)
        return loss, plain

    def track(self, frame: Frame, relevance: Optional[np.ndarray] = None,
              deadline: Optional[float] = None) -> TrackResult:
        """Place ``frame`` against the frozen map, starting from its ``c2w``.

        Args:
            frame: the new keyframe (uint8 rgb (H, W, 3), float32 depth (H, W) metres, ``c2w`` (4, 4) float64
                camera-to-world, pinhole intrinsics in pixels).
            relevance: (H, W) bool relevance map w of the frame, or None.
            deadline: the clock time (``clock.now()`` seconds) after which no further step starts; None = none.
        Returns:
            :class:`TrackResult` (``c2w`` the pose to seed and train the keyframe at).
        Raises:
            ValueError: rgb/depth/relevance of another size than the frame's intrinsics.
        """
        pc = self.cfg.pose
        c2w0 = np.asarray(frame.c2w, np.float64)
        kf = self.view(frame, relevance)
        adam = BlockAdam(np.array([pc.track_lr_rot] * 3 + [pc.track_lr_trans] * 3), np.array([0, 0, 0, 1, 1, 1]))
        c2w = kf.c2w.clone()
        best_c2w, best, loss0, stall, done, stop = c2w.clone(), math.inf, math.nan, 0, 0, "iters"
        for it in range(pc.track_iters):
            if deadline is not None and it > 0 and self.clock.now() >= deadline:
                stop = "deadline"
                break
            xi = torch.zeros(6, dtype=torch.float64, device=c2w.device, requires_grad=True)
            out = self.sensor.render_view(c2w, kf.K, kf.width, kf.height, kf.frame_id, None, pose_xi=xi,
                                          detach_map=True)
            out, _ = self.sensor.exposed(out, kf.frame_id)
            loss, plain = self.loss(out, kf)
            if loss is None:
                stop = "coverage"
                break
            loss0 = plain if it == 0 else loss0
            if plain < best * (1.0 - pc.track_converge):
                best_c2w, best, stall = c2w.clone(), plain, 0
            else:
                stall += 1
                if stall >= PATIENCE:
                    stop = "converged"
                    break
            loss.backward()
            dxi = adam.delta(xi.grad.detach().cpu().double().numpy())
            if dxi is None:
                stop = "gradient"
                break
            dxi = dxi * cosine_lr_factor(it, pc.track_iters, FINAL_LR)
            c2w = c2w @ pose_delta(torch.from_numpy(dxi)).to(c2w.device)
            done += 1
        return self._gate(frame.frame_id, c2w0, best_c2w.cpu().numpy(), done, stop, loss0, best)

    def _gate(self, frame_id: int, c2w0: np.ndarray, c2w: np.ndarray, iters: int, stop: str, loss0: float,
              loss: float) -> TrackResult:
        """The sanity gate: ``c2w`` unless its correction from ``c2w0`` exceeds the configured bounds (then ``c2w0``,
        logged); ``c2w0`` when nothing was tracked."""
        pc = self.cfg.pose
        E = np.linalg.inv(c2w0) @ c2w
        rot = rotation_angle_deg(E)
        trans = float(np.linalg.norm(E[:3, 3]))
        if not math.isfinite(loss):  # no render covered enough of the view
            return TrackResult(c2w0.copy(), iters, False, stop, 0.0, 0.0, loss0, loss0)
        if trans > pc.track_max_trans_m or rot > pc.track_max_rot_deg:
            log.info("keyframe %d: tracked correction of %.1f cm / %.2f deg exceeds the gate (%.1f cm / %.1f deg); "
                     "keeping its input pose", frame_id, 100 * trans, rot, 100 * pc.track_max_trans_m,
                     pc.track_max_rot_deg)
            return TrackResult(c2w0.copy(), iters, False, stop, rot, trans, loss0, loss0)
        return TrackResult(c2w, iters, True, stop, rot, trans, loss0, loss)


__all__ = ["BlockAdam", "FrameTracker", "TrackResult", "robust_weights", "tracking_factor"]
