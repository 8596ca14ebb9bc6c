"""Keyframe pose refinement during mapping: the photometric map corrects the sensor's poses.

Hand-held RGB-D poses are never exact. TUM RGB-D's motion-capture poses, interpolated at the colour
timestamps, leave 0.2–1.3° and up to 27 mm of error between frames 100 ms apart on fr1/rpy (measured:
aligning frame pairs photometrically with their depth raises the warp PSNR by 2–5 dB); at 320×240,
1° is about 5 pixels, so every view pulls the shared Gaussians towards a different place. SLAM
systems avoid this because they render at the poses their own tracking estimated. MonoGS (Matsuki et
al., CVPR 2024, Sec. 3.3) optimises the keyframe poses jointly with the Gaussians in mapping; this
module does the same with the given poses as the starting point (no tracking).

Parameterisation: each keyframe's pose is corrected on the right, in its camera frame,
``c2w' = c2w · E(ξ)`` with ``ξ = (ω, v)`` (ω rotation vector in radians, v metres, OpenCV camera
axes) and ``E(ξ) = [[exp(ω^), v], [0, 1]]``. After every step the correction is folded into the pose
and ξ restarts at 0, so the gradient is always taken at ξ = 0 (MonoGS's update). Because our
rasterizer takes a fixed view matrix, the gradient with respect to ξ is obtained by moving the
Gaussians instead of the camera (equivalent): rendering ``(means, quats)`` from ``c2w · E`` equals
rendering ``(M means, q_M ⊗ quats)`` from ``c2w``, with the world-frame rigid transform
``M = c2w · E⁻¹ · c2w⁻¹`` (:func:`move_gaussians_for_pose_delta`).

Each keyframe's ξ has its own Adam moments (:class:`PoseRefiner`, :class:`VectorAdam`). The first keyframe stays fixed
(the gauge: the whole map and every pose could otherwise drift together).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional

import numpy as np
import torch

from gausslite.camera import nearest_rigid, rotation_angle


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Rotation matrix of a rotation vector (Rodrigues), differentiable also at 0.

    Args:
        omega: (3,) rotation vector, radians (axis × angle), any float dtype.
    Returns:
        (3, 3) rotation matrix of the same dtype.
    """
    theta2 = (omega * omega).sum()
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-10
    # sin(θ)/θ and (1 − cos θ)/θ² with their Taylor series near 0 (keeps the gradient exact at 0)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    zero = torch.zeros((), dtype=omega.dtype, device=omega.device)
    wx, wy, wz = omega.unbind()
    W = torch.stack([zero, -wz, wy, wz, zero, -wx, -wy, wx, zero]).reshape(3, 3)
    return torch.eye(3, dtype=omega.dtype, device=omega.device) + a * W + b * (W @ W)


def quat_of_rotvec(r: torch.Tensor) -> torch.Tensor:
    """(4,) unit quaternion (w, x, y, z) of a rotation vector ``r`` (3,) in radians, differentiable at 0."""
    theta2 = (r * r).sum()
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-10
    s = torch.where(small, 0.5 - theta2 / 48.0, torch.sin(theta / 2) / theta)  # sin(θ/2)/θ
    c = torch.where(small, 1.0 - theta2 / 8.0, torch.cos(theta / 2))
    return torch.cat([c.reshape(1), s * r])


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``a ⊗ b`` of (4,) or (N, 4) quaternions (w, x, y, z), broadcast over rows."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)


def pose_delta(xi: torch.Tensor) -> torch.Tensor:
    """(4, 4) ``E(ξ) = [[exp(ω^), v], [0, 1]]`` of ``xi`` (6,) = (ω radians, v metres), differentiable
    (:func:`pose_delta_np` for a value without gradient)."""
    E = torch.eye(4, dtype=xi.dtype, device=xi.device)
    E[:3, :3] = so3_exp(xi[:3])
    E[:3, 3] = xi[3:]
    return E


def pose_delta_np(xi: np.ndarray) -> np.ndarray:
    """:func:`pose_delta` as a value: (4, 4) float64 ``E(ξ)`` of ``xi`` (6,) = (ω radians, v metres), the rotation by
    SciPy's ``Rotation.from_rotvec`` (a few NumPy calls instead of twenty torch ops: the mapper takes one per pose
    step and per blur sample and shutter band of a render)."""
    from scipy.spatial.transform import Rotation  # lazy: keeps this module importable without SciPy

    xi = np.asarray(xi, np.float64)
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix()
    E[:3, 3] = xi[3:]
    return E


def move_gaussians_for_pose_delta(means: torch.Tensor, quats: torch.Tensor, c2w: torch.Tensor,
                                  xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Gaussians moved so that rendering them from ``c2w`` equals rendering the originals from
    ``c2w · E(ξ)`` (module docstring): ``means' = M means``, ``quats' = q_M ⊗ quats`` with
    ``M = c2w E(ξ)⁻¹ c2w⁻¹``.

    Args:
        means: (N, 3) world-frame centres, metres (float32). quats: (N, 4) (w, x, y, z).
        c2w: (4, 4) float64 camera-to-world pose. xi: (6,) float64 pose delta (ω, v), camera frame.
    Returns:
        ``(means', quats')`` in the dtype of ``means``/``quats``, differentiable in means, quats and ξ (and in
        ``c2w`` for ξ ≠ 0). At ξ = 0, where the mapper and the trackers take every gradient, the Gaussians are
        returned unmoved and ξ's gradient is closed-form (:class:`_PoseDeltaAtZero`).
    """
    if not bool(xi.detach().any()):
        return _PoseDeltaAtZero.apply(means, quats, c2w, xi)
    return _move_gaussians(means, quats, c2w, xi)


def _move_gaussians(means: torch.Tensor, quats: torch.Tensor, c2w: torch.Tensor,
                    xi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`move_gaussians_for_pose_delta` for any ξ, by autograd through the moved Gaussians."""
    Rc, tc = c2w[:3, :3], c2w[:3, 3]
    Re = so3_exp(xi[:3])
    RM = Rc @ Re.T @ Rc.T  # = exp((−Rc ω)^)
    tM = Rc @ (-(Re.T @ xi[3:])) + tc - RM @ tc
    moved = means @ RM.T.to(means.dtype) + tM.to(means.dtype)
    qM = quat_of_rotvec(-(Rc @ xi[:3])).to(quats.dtype)
    return moved, quat_mul(qM, quats)


def _axial(A: np.ndarray) -> np.ndarray:
    """(3,) ``(A[1,2] − A[2,1], A[2,0] − A[0,2], A[0,1] − A[1,0])`` of a (3, 3) ``A``: for ``A = Σ_i a_i b_iᵀ`` it is
    ``Σ_i a_i × b_i``."""
    return np.array([A[1, 2] - A[2, 1], A[2, 0] - A[0, 2], A[0, 1] - A[1, 0]])


class _PoseDeltaAtZero(torch.autograd.Function):
    """:func:`move_gaussians_for_pose_delta` at ξ = 0: the Gaussians unchanged, and in the backward pass the
    gradients passed through to ``means`` and ``quats`` (the move's Jacobian in them is the identity at 0) and
    the gradient of ξ in closed form, the first-order move summed over the Gaussians. With ``u = Rc ω``:
    ``means' ≈ means − u × (means − tc) − Rc v`` and ``quats' ≈ (1, −u/2) ⊗ quats``, so
    ``dL/dω = Rcᵀ Σ_i [g_i × (μ_i − tc) + (g_w,i q_v,i − q_w,i g_v,i − q_v,i × g_v,i) / 2]`` and
    ``dL/dv = −Rcᵀ Σ_i g_i`` (g: the means' gradient; (g_w, g_v): the quaternion's). No (N, ·) work in the
    forward pass and one pass over the gradients in the backward, where the general path builds and
    differentiates the move of every Gaussian."""

    @staticmethod
    def forward(ctx, means, quats, c2w, xi):
        ctx.save_for_backward(means, quats, c2w)
        return means.view_as(means), quats.view_as(quats)

    @staticmethod
    def backward(ctx, g_means, g_quats):
        means, quats, c2w = ctx.saved_tensors
        # the (N, ·) products in torch, the (3,)-sized rest in NumPy float64 (a few microseconds, where each of about
        # twenty small torch operations cost several)
        pose = c2w.detach().cpu().to(torch.float64).numpy()
        Rc, tc = pose[:3, :3], pose[:3, 3]
        d_u, d_v = np.zeros(3), np.zeros(3)
        if g_means is not None:
            # Σ g × (μ − tc) = Σ g × μ − (Σ g) × tc, with Σ g × μ the axial vector of A − Aᵀ, A = Σ g μᵀ (3, 3):
            # one (3, N) @ (N, 3) product in the map's dtype instead of N cross products
            A = (g_means.T @ means).cpu().to(torch.float64).numpy()
            g_sum = g_means.sum(0, dtype=torch.float64).cpu().numpy()
            d_u = d_u + _axial(A) - np.cross(g_sum, tc)
            d_v = -(Rc.T @ g_sum)
        if g_quats is not None:
            B = (quats.T @ g_quats).cpu().to(torch.float64).numpy()  # B[i, j] = Σ q_i g_j, (w, x, y, z)
            # Σ (g_w q_v − q_w g_v − q_v × g_v) / 2, with Σ q_v × g_v the axial vector of B[1:, 1:]
            d_u = d_u + 0.5 * (B[1:, 0] - B[0, 1:] - _axial(B[1:, 1:]))
        d_xi = (torch.from_numpy(np.concatenate([Rc.T @ d_u, d_v])).to(c2w.device)
                if ctx.needs_input_grad[3] else None)
        return (g_means if ctx.needs_input_grad[0] else None, g_quats if ctx.needs_input_grad[1] else None,
                None, d_xi)


def neighbour_keys(keyed: dict, frame_id: int) -> Optional[tuple[int, int, float]]:
    """The keyframes on both sides of frame ``frame_id`` in ``keyed`` (frame id → per-keyframe value) and the
    frame's position between them: ``(k0, k1, t)`` with ``k0 < frame_id < k1`` the nearest ones and
    ``t = (frame_id − k0) / (k1 − k0)``; None when ``frame_id`` is a key itself or lies outside the keys (before
    the first or after the last keyframe)."""
    fid = int(frame_id)
    if fid in keyed:
        return None
    below = [k for k in keyed if k < fid]
    above = [k for k in keyed if k > fid]
    if not below or not above:
        return None
    k0, k1 = max(below), min(above)
    return k0, k1, (fid - k0) / float(k1 - k0)


def interpolate_pose(E0: np.ndarray, E1: np.ndarray, t: float) -> np.ndarray:
    """(4, 4) float64 rigid transform a share ``t`` ∈ [0, 1] of the way from ``E0`` to ``E1`` (4, 4): rotation by
    spherical linear interpolation, translation linearly."""
    # lazy: keeps gausslite.mapping.poses importable without SciPy
    from scipy.spatial.transform import Rotation, Slerp

    rots = Rotation.from_matrix(np.stack([E0[:3, :3], E1[:3, :3]]))
    out = np.eye(4)
    out[:3, :3] = Slerp([0.0, 1.0], rots)([float(t)]).as_matrix()[0]
    out[:3, 3] = (1.0 - t) * E0[:3, 3] + t * E1[:3, 3]
    return out


def nearest_key(keyed: dict, frame_id: int) -> int:
    """The key of ``keyed`` (frame id → per-keyframe value) for frame ``frame_id``: itself when present,
    otherwise the nearest keyframe by frame id (a held-out view between keyframes). ``keyed`` must not be
    empty. Used for pose corrections, exposure responses and motion-blur twists alike."""
    fid = int(frame_id)
    return fid if fid in keyed else min(keyed, key=lambda k: abs(k - fid))


def correction_moves(new_c2w: Mapping[int, np.ndarray],
                     current: Mapping[int, np.ndarray]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The rigid moves that take mapped frames from their ``current`` poses to corrected ones.

    Args:
        new_c2w: frame id → corrected (4, 4) camera-to-world pose (float, metres; a rigid transform: rounding off
            SO(3) up to :data:`gausslite.camera.RIGID_DRIFT_MAX` is projected away).
        current: frame id → (4, 4) float64 pose of every mapped frame now.
    Returns:
        frame id → ``(T, new)``: the world-frame (4, 4) float64 transform ``T = new · current⁻¹`` and the new pose, for
        the frames whose pose changes (``T`` off the identity by more than 1e-12).
    Raises:
        KeyError: a frame id of ``new_c2w`` not in ``current``. ValueError: a pose that is not a finite rigid
        transform (beyond rounding: :func:`gausslite.camera.nearest_rigid`).
    """
    moves: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for fid, c2w in new_c2w.items():
        fid = int(fid)
        if fid not in current:
            raise KeyError(f"frame {fid} was never mapped: no keyframe to correct (mapped: {len(current)} frames)")
        # rounding is projected away (gausslite.camera.nearest_rigid); only a pose that is no rigid transform raises
        new = nearest_rigid(c2w, f"frame {fid}: the corrected pose")
        if np.allclose(np.asarray(c2w, np.float64), current[fid], rtol=0.0, atol=1e-12):
            continue  # unchanged (the projection of a pose that was not rigid to the last bit is no move)
        T = nearest_rigid(new @ np.linalg.inv(current[fid]), f"frame {fid}: the correction")
        if not np.allclose(T, np.eye(4), rtol=0.0, atol=1e-12):
            moves[fid] = (T, new)
    return moves


@dataclass
class _AdamState:
    m: np.ndarray
    v: np.ndarray
    t: int = 0


class VectorAdam:
    """Adam on small per-key parameter vectors (a keyframe's pose delta ξ or exposure θ), in float64 on
    the host: one set of moments per key, so every keyframe's parameters keep their own step history.

    Args:
        lr: (D,) step size per component.
    """

    def __init__(self, lr: np.ndarray, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-12) -> None:
        self.lr = np.asarray(lr, np.float64)
        self.b1, self.b2, self.eps = b1, b2, eps
        self._state: dict[int, _AdamState] = {}

    def delta(self, key: int, grad: np.ndarray) -> Optional[np.ndarray]:
        """The (D,) Adam update of ``key`` for gradient ``grad`` (D,) (to be added to its parameters), or
        None when ``grad`` is not finite (no state changes then)."""
        g = np.asarray(grad, np.float64)
        if not np.all(np.isfinite(g)):
            return None
        d = self.lr.shape[0]
        st = self._state.setdefault(int(key), _AdamState(np.zeros(d), np.zeros(d)))
        st.t += 1
        st.m = self.b1 * st.m + (1 - self.b1) * g
        st.v = self.b2 * st.v + (1 - self.b2) * g * g
        mhat = st.m / (1 - self.b1 ** st.t)
        vhat = st.v / (1 - self.b2 ** st.t)
        return -self.lr * mhat / (np.sqrt(vhat) + self.eps)


class PoseRefiner:
    """Per-keyframe Adam on the pose delta ξ (``MapperConfig.pose.refine``).

    Args:
        lr_rot: step size of ω (radians). lr_trans: step size of v (metres).
    Attributes:
        corrections: frame id → (4, 4) float64 ``E = c2w_input⁻¹ · c2w_refined`` (right correction).
        fixed: frame ids whose pose is not refined (the mission's first keyframe).
    """

    def __init__(self, lr_rot: float = 1e-3, lr_trans: float = 5e-4, interpolate: bool = False) -> None:
        self._adam = VectorAdam(np.array([lr_rot] * 3 + [lr_trans] * 3))
        self.corrections: dict[int, np.ndarray] = {}
        self.fixed: set[int] = set()
        self.interpolate = interpolate

    def initial_correction(self, frame_id: int) -> np.ndarray:
        """The correction a new keyframe starts from: the latest keyframe's (pose errors of a hand-held
        sensor are correlated over consecutive frames), identity for the first."""
        if not self.corrections:
            return np.eye(4)
        last = max(self.corrections)  # frame ids grow along the mission
        return self.corrections[last].copy() if last < frame_id else np.eye(4)

    def register(self, frame_id: int, correction: np.ndarray, fixed: bool = False) -> None:
        """Start tracking keyframe ``frame_id`` with ``correction`` (4, 4; rounding off SE(3) projected away).

        Raises:
            ValueError: ``correction`` is not a rigid transform (:func:`gausslite.camera.nearest_rigid`).
        """
        self.corrections[int(frame_id)] = nearest_rigid(correction, f"keyframe {int(frame_id)}'s correction")
        if fixed:
            self.fixed.add(int(frame_id))

    def step(self, frame_id: int, grad: torch.Tensor, c2w: torch.Tensor, scale: float = 1.0) -> Optional[torch.Tensor]:
        """One Adam step of keyframe ``frame_id`` from ``grad`` (6,) = ∂L/∂ξ at ξ = 0.

        Args:
            c2w: (4, 4) float64 the keyframe's current (refined) pose.
            scale: the step's size relative to the refiner's learning rates (``pose.roi_lr_scale`` in ROI-phase
                iterations).
        Returns:
            the new (4, 4) float64 pose ``c2w · E(Δξ)``, or None (fixed or unknown keyframe, no gradient).
        """
        fid = int(frame_id)
        if fid in self.fixed or fid not in self.corrections or grad is None:
            return None
        dxi = self._adam.delta(fid, grad.detach().cpu().double().numpy())
        if dxi is None:
            return None
        dxi = dxi * float(scale)
        E = pose_delta_np(dxi)
        new = torch.from_numpy(nearest_rigid(c2w.detach().cpu().numpy() @ E, f"keyframe {fid}'s refined pose")).to(c2w)
        # thousands of steps fold into the correction: each product projected back onto SE(3)
        self.corrections[fid] = nearest_rigid(self.corrections[fid] @ E, f"keyframe {fid}'s correction")
        return new

    def state_dict(self) -> dict:
        """Plain-data copy for checkpoints: ``{"corrections": {frame id: (4, 4) float64}, "fixed": [ids]}`` (not
        the Adam moments)."""
        return {"corrections": {k: v.copy() for k, v in self.corrections.items()}, "fixed": sorted(self.fixed)}

    def load_state_dict(self, state: dict) -> None:
        """Replace the corrections and fixed ids by a :meth:`state_dict`'s, bit for bit (Adam moments restart at zero).

        Raises:
            ValueError: a correction that is not a rigid transform (:func:`gausslite.camera.nearest_rigid`).
        """
        self._adam = VectorAdam(self._adam.lr)
        self.corrections, self.fixed = {}, set(int(f) for f in state["fixed"])
        for fid, E in state["corrections"].items():
            nearest_rigid(E, f"keyframe {int(fid)}'s correction")  # a state that holds no pose raises
            self.corrections[int(fid)] = np.asarray(E, np.float64).copy()  # as saved: bit for bit

    def corrected(self, frame_id: int, c2w: np.ndarray) -> np.ndarray:
        """``c2w`` (4, 4) of a frame with its keyframe's correction; for a frame between keyframes (a held-out view)
        the correction interpolated in frame id between the keyframes on both sides (``interpolate``,
        :func:`interpolate_pose`) or the nearest keyframe's; unchanged without any keyframe."""
        if not self.corrections:
            return np.asarray(c2w, np.float64)
        nb = neighbour_keys(self.corrections, frame_id) if self.interpolate else None
        if nb is not None:
            k0, k1, t = nb
            return np.asarray(c2w, np.float64) @ interpolate_pose(self.corrections[k0], self.corrections[k1], t)
        return np.asarray(c2w, np.float64) @ self.corrections[nearest_key(self.corrections, frame_id)]

    def magnitudes(self) -> tuple[np.ndarray, np.ndarray]:
        """Per keyframe, the correction's rotation (degrees) and translation (metres) (for reports)."""
        if not self.corrections:
            return np.zeros(0), np.zeros(0)
        E = np.stack(list(self.corrections.values()))
        ang = np.degrees(rotation_angle(E))
        return ang, np.linalg.norm(E[:, :3, 3], axis=1)


__all__ = ["so3_exp", "quat_of_rotvec", "quat_mul", "pose_delta", "move_gaussians_for_pose_delta", "PoseRefiner",
           "VectorAdam", "nearest_key", "neighbour_keys", "interpolate_pose"]
