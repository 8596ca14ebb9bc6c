"""Per-keyframe exposure compensation: the map keeps one radiance, each keyframe its own camera response.

Hand-held RGB-D cameras adjust exposure and white balance as they move (the Kinect of TUM RGB-D does
both automatically). Fitting one set of Gaussian colours to views whose brightness differs makes every
view pull the colours towards its own exposure, so a long mission's later views overwrite the earlier
ones. MonoGS (Matsuki et al., CVPR 2024, Sec. 3.3 and its code's ``exposure_a``/``exposure_b``) gives
each keyframe an affine brightness ``I' = exp(a) · I + b`` optimised with the map; this module does the
same with one gain and one offset per colour channel (white balance as well as exposure):

    I'_c = exp(a_c) · I_c + b_c,   c ∈ {R, G, B},   θ = (a_R, a_G, a_B, b_R, b_G, b_B)

``I`` is the rendered colour (RGB in [0, 1], background included), ``I'`` what the keyframe's camera
saw. Each keyframe's θ has its own Adam moments (:class:`~gausslite.mapping.poses.VectorAdam`). The
first keyframe is fixed at θ = 0 (the gauge: otherwise the map's colours and every θ could drift
together), so the map's colours are in the first keyframe's exposure. A new keyframe starts from the
latest keyframe's θ (exposure changes slowly between frames). Views that are not keyframes (held-out
frames) use the nearest keyframe's θ, as :class:`~gausslite.mapping.poses.PoseRefiner` does for poses.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from .poses import VectorAdam, nearest_key, neighbour_keys


def apply_exposure(color: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """``exp(a) ⊙ color + b`` (module docstring), differentiable in both inputs.

    Args:
        color: (H, W, 3) rendered RGB in [0, 1] (any float dtype).
        theta: (6,) (a_R, a_G, a_B, b_R, b_G, b_B): log gains and offsets.
    Returns:
        (H, W, 3) tensor in the dtype of ``color`` (not clamped: the loss sees the affine image).
    """
    th = theta.to(color.dtype)
    return color * torch.exp(th[:3]) + th[3:]


def invert_exposure(rgb: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Colours seen under ``theta`` (6,) brought back to the map's exposure, ``(rgb − b) / exp(a)``,
    clipped to [0, 1]. ``rgb``: (..., 3) float in [0, 1]. Used for the colours of new seeds."""
    th = np.asarray(theta, np.float64)
    return np.clip((np.asarray(rgb, np.float64) - th[3:]) / np.exp(th[:3]), 0.0, 1.0).astype(np.float32)


class ExposureModel:
    """Per-keyframe affine exposure θ (``MapperConfig.sensor.exposure_comp``; module docstring).

    Args:
        lr: Adam step size of θ (log gain and offset alike; MonoGS uses 0.01).
    Attributes:
        params: frame id → (6,) float64 θ.
        fixed: frame ids whose θ is not optimised (the mission's first keyframe).
    """

    def __init__(self, lr: float = 0.01, interpolate: bool = False) -> None:
        self._adam = VectorAdam(np.full(6, float(lr)))
        self.params: dict[int, np.ndarray] = {}
        self.fixed: set[int] = set()
        self.interpolate = interpolate

    def initial(self, frame_id: int) -> np.ndarray:
        """θ a new keyframe starts from: the latest earlier keyframe's, zeros for the first."""
        earlier = [k for k in self.params if k < int(frame_id)]
        return self.params[max(earlier)].copy() if earlier else np.zeros(6)

    def register(self, frame_id: int, theta: np.ndarray, fixed: bool = False) -> None:
        """Start tracking keyframe ``frame_id`` at ``theta`` (6,)."""
        self.params[int(frame_id)] = np.asarray(theta, np.float64).reshape(6).copy()
        if fixed:
            self.fixed.add(int(frame_id))

    def of(self, frame_id: int) -> np.ndarray:
        """θ (6,) of ``frame_id``; for a frame between keyframes θ interpolated linearly in frame id between the
        keyframes on both sides (``interpolate``) or the nearest keyframe's; zeros without any keyframe."""
        if not self.params:
            return np.zeros(6)
        nb = neighbour_keys(self.params, frame_id) if self.interpolate else None
        if nb is not None:
            k0, k1, t = nb
            return (1.0 - t) * self.params[k0] + t * self.params[k1]
        return self.params[nearest_key(self.params, frame_id)]

    def trainable(self, frame_id: int) -> bool:
        """Whether ``frame_id`` is a registered keyframe whose θ is optimised."""
        return int(frame_id) in self.params and int(frame_id) not in self.fixed

    def tensor(self, frame_id: int, device: torch.device, requires_grad: bool = False) -> torch.Tensor:
        """(6,) float32 θ of ``frame_id`` (:meth:`of`) on ``device``, a leaf with gradients if asked."""
        return torch.tensor(self.of(frame_id), dtype=torch.float32, device=device, requires_grad=requires_grad)

    def step(self, frame_id: int, grad: Optional[torch.Tensor]) -> None:
        """One Adam step of keyframe ``frame_id``'s θ from ``grad`` (6,) = ∂L/∂θ; nothing for a fixed or
        unknown keyframe or a missing / non-finite gradient."""
        if grad is None or not self.trainable(frame_id):
            return
        d = self._adam.delta(int(frame_id), grad.detach().cpu().double().numpy())
        if d is not None:
            self.params[int(frame_id)] = self.params[int(frame_id)] + d

    def state_dict(self) -> dict:
        """Plain-data copy for checkpoints (θ per keyframe and the fixed ids; not the Adam moments)."""
        return {"params": {k: v.copy() for k, v in self.params.items()}, "fixed": sorted(self.fixed)}

    def load_state_dict(self, state: dict) -> None:
        """Replace θ and the fixed ids by a :meth:`state_dict` (Adam moments restart at zero)."""
        self._adam = VectorAdam(self._adam.lr)
        self.params, self.fixed = {}, set()
        for fid, th in state["params"].items():
            self.register(int(fid), th, fixed=int(fid) in set(state["fixed"]))


__all__ = ["apply_exposure", "invert_exposure", "ExposureModel"]
