"""Pinhole camera intrinsics and pose helpers.

Conventions (used everywhere in GaussLite):
- Camera axes follow OpenCV: x right, y down, z forward.
- Poses are camera-to-world ``c2w`` 4x4 float64 matrices (metres); ``viewmat`` is world-to-camera.
- Pixel centres sit at integer coordinates: pixel (u, v) covers [u-0.5, u+0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height`` pixels.

    Attributes:
        fx, fy: focal lengths (pixels).
        cx, cy: principal point (pixels).
        width, height: image size (pixels).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        vals = np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float64)
        if not np.all(np.isfinite(vals)) or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"invalid intrinsics: fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"invalid image size {self.width}x{self.height}")

    @property
    def K(self) -> np.ndarray:
        """3x3 float64 intrinsic matrix."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics for an image downscaled by ``factor`` (e.g. 2 halves width and height).

        The new size is ``floor(width / factor)`` x ``floor(height / factor)``; focal lengths divide
        by ``factor`` and the principal point moves so that pixel centres stay consistent:
        ``c' = (c + 0.5) / factor - 0.5``.
        """
        if factor <= 0:
            raise ValueError(f"downscale factor must be > 0, got {factor}")
        return Intrinsics(
            fx=self.fx / factor,
            fy=self.fy / factor,
            cx=(self.cx + 0.5) / factor - 0.5,
            cy=(self.cy + 0.5) / factor - 0.5,
            width=int(self.width // factor),
            height=int(self.height // factor),
        )

    @staticmethod
    def from_K(K: np.ndarray, width: int, height: int) -> "Intrinsics":
        """Build from a 3x3 matrix ``K`` (pixels)."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise ValueError(f"K must be 3x3, got {K.shape}")
        return Intrinsics(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), int(width), int(height))


def rotation_angle(R) -> np.ndarray:
    """Angle (radians, in [0, π]) of rotation matrices: ``arccos((trace(R) − 1) / 2)``, its argument clipped to
    [−1, 1] against rounding.

    Args:
        R: (..., 3, 3) rotation matrices or (..., 4, 4) poses (their rotation block), any float dtype.
    Returns:
        (...) float64 array (0-dimensional for one matrix).
    """
    R = np.asarray(R, np.float64)[..., :3, :3]
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0))


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle (degrees) of a (3, 3) rotation matrix."""
    return float(np.degrees(rotation_angle(np.asarray(R)[:3, :3])))


def check_rigid(c2w: np.ndarray, atol: float = 1e-3, what: str = "pose") -> np.ndarray:
    """Validate a 4x4 rigid transform and return it as float64.

    Raises:
        ValueError: wrong shape, non-finite entries, last row not [0,0,0,1], or a rotation block
            that is not orthonormal with determinant +1 (tolerance ``atol``). The message names ``what``.
    """
    T = np.asarray(c2w, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"{what}: expected a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise ValueError(f"{what}: pose has NaN or infinite entries")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=atol):
        raise ValueError(f"{what}: last row must be [0 0 0 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=atol) or abs(np.linalg.det(R) - 1.0) > atol:
        raise ValueError(f"{what}: rotation block is not a proper rotation (non-rigid pose)")
    return T


#: how far from SE(3) a composed pose may have drifted before :func:`nearest_rigid` calls it a bug, not rounding
#: (:func:`check_rigid`'s ``atol``; rounding stays near 1e-7 per float32 factor; a thousand factors, about 1e-4)
RIGID_DRIFT_MAX = 1e-2


def nearest_rigid(T: np.ndarray, what: str = "pose", max_drift: float = RIGID_DRIFT_MAX) -> np.ndarray:
    """The rigid transform nearest ``T``: its rotation block projected onto SO(3), its last row ``[0, 0, 0, 1]``.

    Poses composed as products (a tracker's ``c2w_ref · T`` along a chain of keyframes, a pose graph's corrections, a
    map's correction record) gather rounding with every factor: after a few hundred products of registrations
    computed in float32, ``R Rᵀ`` is off the identity by about 1e-4. Projecting each product back keeps every pose
    rigid by construction, as Sophus re-normalises its quaternion after a product. The projection is the orthogonal
    Procrustes solution ``R' = U Vᵀ`` of ``R = U Σ Vᵀ`` (the rotation nearest ``R`` in the Frobenius norm; Horn,
    Hilden and Negahdaripour, JOSA A 1988; a proper rotation, since :func:`check_rigid` refuses reflections); the
    translation is kept.

    Args:
        T: (4, 4) transform (any float dtype; metres).
        what: what ``T`` is, for the error message.
        max_drift: how far off rigid (:func:`check_rigid`'s ``atol``) is still rounding; beyond it ``T`` is no pose.
    Returns:
        (4, 4) float64 rigid transform (``R Rᵀ = I`` and ``det R = 1`` to about 1e-15).
    Raises:
        ValueError: :func:`check_rigid`'s, at ``atol = max_drift``: wrong shape, a non-finite entry, a last row other
            than ``[0, 0, 0, 1]``, or a rotation block that is no proper rotation: a bug, not drift.
    """
    out = check_rigid(T, atol=max_drift, what=what).copy()
    U, _, Vt = np.linalg.svd(out[:3, :3])
    out[:3, :3] = U @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def backproject(depth: np.ndarray, intr: Intrinsics, c2w: np.ndarray) -> np.ndarray:
    """Back-project a depth image to world points.

    Args:
        depth: (H, W) float depth in metres along the camera z axis; 0 = invalid.
        intr: intrinsics matching the image size.
        c2w: (4, 4) camera-to-world pose.

    Returns:
        (H, W, 3) float64 world points (metres); invalid pixels give the camera centre scaled by 0
        depth, i.e. callers must mask with ``depth > 0``.
    """
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    z = depth.astype(np.float64)
    x = (u - intr.cx) / intr.fx * z
    y = (v - intr.cy) / intr.fy * z
    pc = np.stack([x, y, z], axis=-1)
    return pc @ c2w[:3, :3].T + c2w[:3, 3] * (z[..., None] > 0)
