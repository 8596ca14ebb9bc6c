"""Detection keyframe trigger (paper Sec. III-B).

A frame is a detection keyframe when the camera moved more than ``translation_m`` or rotated more than
``rotation_deg`` since the last keyframe, or when ``every_k`` frames have passed since it. The first
frame is always a keyframe. Paper values: θ_t = 1.0 m, θ_r = 15°.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = ["KeyframeConfig", "KeyframeTrigger", "relative_motion"]


@dataclass
class KeyframeConfig:
    """Thresholds of :class:`KeyframeTrigger`.

    Attributes:
        translation_m: θ_t, metres (> 0).
        rotation_deg: θ_r, degrees (> 0).
        every_k: also trigger when this many frames passed since the last keyframe (None: never;
            1: every frame is a keyframe).
    """

    translation_m: float = 1.0
    rotation_deg: float = 15.0
    every_k: Optional[int] = 10

    def __post_init__(self) -> None:
        if not self.translation_m > 0 or not self.rotation_deg > 0:
            raise ValueError(f"keyframe thresholds must be > 0, got {self.translation_m} m, {self.rotation_deg} deg")
        if self.every_k is not None and int(self.every_k) < 1:
            raise ValueError(f"every_k must be >= 1 or None, got {self.every_k}")


def relative_motion(c2w_a: np.ndarray, c2w_b: np.ndarray) -> tuple:
    """Translation (metres) and rotation angle (degrees) between two camera-to-world poses (4x4)."""
    a = np.asarray(c2w_a, dtype=np.float64)
    b = np.asarray(c2w_b, dtype=np.float64)
    t = float(np.linalg.norm(b[:3, 3] - a[:3, 3]))
    R = a[:3, :3].T @ b[:3, :3]
    c = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
    return t, float(np.degrees(np.arccos(c)))


class KeyframeTrigger:
    """Stateful trigger. Call :meth:`update` once per frame with its pose.

    Raises (from ``update``):
        ValueError: the pose is not a 4x4 matrix with finite entries.
    """

    def __init__(self, config: Optional[KeyframeConfig] = None) -> None:
        self.config = config or KeyframeConfig()
        self.reset()

    def reset(self) -> None:
        """Forget the last keyframe: the next frame triggers."""
        self.last_pose: Optional[np.ndarray] = None
        self.frames_since = 0

    def update(self, c2w: np.ndarray) -> bool:
        """Whether the frame with camera-to-world pose ``c2w`` is a keyframe; records it if so."""
        c2w = np.asarray(c2w, dtype=np.float64)
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise ValueError(f"c2w must be a finite 4x4 matrix, got shape {c2w.shape}")
        self.frames_since += 1
        fire = self.last_pose is None
        if not fire:
            t, r = relative_motion(self.last_pose, c2w)
            fire = t > self.config.translation_m or r > self.config.rotation_deg
            if self.config.every_k is not None and self.frames_since >= int(self.config.every_k):
                fire = True
        if fire:
            self.last_pose = c2w.copy()
            self.frames_since = 0
        return fire
