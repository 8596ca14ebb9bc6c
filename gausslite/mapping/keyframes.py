"""Mapping keyframe selection for a live RGB-D stream (online agent; ``docs/live.md``).

A robot streams frames faster than a CPU mapper maps them. Each arriving frame is *offered* to a
:class:`KeyframeSelector`; the mapper *takes* the pending candidate when it is free. A frame becomes the
pending candidate when, relative to the last keyframe the mapper took,

* the camera moved more than ``translation_m`` metres, or
* it rotated more than ``rotation_deg`` degrees, or
* ``max_interval_s`` seconds of the frame clock passed (so a still robot still refreshes its map);

and the first frame is always a candidate. Only the **newest** candidate is kept: a newer candidate
replaces a pending one that the mapper has not taken yet (that one counts as skipped), so the memory
held for the mapper is bounded by one frame whatever the stream rate.

Source of the rule: translation/rotation thresholds since the last keyframe as in Gaussian-SLAM's motion
heuristic (Yugay et al., 2023) and MonoGS's relative-translation keyframe test (Matsuki et al., CVPR 2024,
Sec. 3.4); the maximum interval plays the role of SplaTAM's "every n-th frame" keyframe rule (Keetha et
al., CVPR 2024). Covisibility tests are not used (they need a render per arriving frame, which the
accept path cannot afford on a CPU). The pose arithmetic is shared with the detection keyframe trigger
(:func:`gausslite.attention.keyframes.relative_motion`, paper Sec. III-B), whose thresholds are larger.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional, Tuple

import numpy as np

from gausslite.attention.keyframes import relative_motion

__all__ = ["KeyframeRule", "KeyframeSelector"]


@dataclass(frozen=True)
class KeyframeRule:
    """Thresholds of :class:`KeyframeSelector`.

    Attributes:
        translation_m: camera-centre distance since the last keyframe, metres (> 0).
        rotation_deg: rotation angle since the last keyframe, degrees (> 0).
        max_interval_s: frame-clock seconds since the last keyframe that make any frame a candidate
            (> 0; None: never).
    Raises:
        ValueError: a threshold that is not finite and > 0.
    """

    translation_m: float = 0.05
    rotation_deg: float = 5.0
    max_interval_s: Optional[float] = 1.0

    def __post_init__(self) -> None:
        vals = [self.translation_m, self.rotation_deg] + ([] if self.max_interval_s is None else [self.max_interval_s])
        if not all(math.isfinite(v) and v > 0 for v in vals):
            raise ValueError(f"keyframe thresholds must be finite and > 0, got translation_m={self.translation_m}, "
                             f"rotation_deg={self.rotation_deg}, max_interval_s={self.max_interval_s}")


class KeyframeSelector:
    """Keyframe candidate selection with a single pending slot (not thread-safe: callers lock).

    Args:
        rule: thresholds (default :class:`KeyframeRule`).
    """

    def __init__(self, rule: Optional[KeyframeRule] = None) -> None:
        self.rule = rule or KeyframeRule()
        self.ref_pose: Optional[np.ndarray] = None  # (4, 4) c2w of the last keyframe taken
        self.ref_time: Optional[float] = None
        self._pending: Optional[Tuple[Any, np.ndarray, float]] = None

    def is_candidate(self, c2w: np.ndarray, t: float) -> bool:
        """Whether a frame with camera-to-world pose ``c2w`` (4, 4, metres) at clock ``t`` (seconds)
        qualifies as a keyframe against the last keyframe taken."""
        if self.ref_pose is None:
            return True
        dt, dr = relative_motion(self.ref_pose, c2w)
        if dt > self.rule.translation_m or dr > self.rule.rotation_deg:
            return True
        mi = self.rule.max_interval_s
        return mi is not None and self.ref_time is not None and t - self.ref_time >= mi

    def offer(self, item: Any, c2w: np.ndarray, t: float) -> Tuple[bool, Optional[Any]]:
        """Offer an arriving frame.

        Args:
            item: what to hand to the mapper (e.g. the frame).
            c2w: (4, 4) camera-to-world pose, metres; t: frame clock, seconds.
        Returns:
            (pending, replaced): whether ``item`` is now the pending candidate, and the older pending
            item it replaced (None if the slot was empty or ``item`` was not a candidate).
        Raises:
            ValueError: a pose that is not a finite (4, 4) matrix or a non-finite time.
        """
        pose = np.asarray(c2w, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)) or not math.isfinite(t):
            raise ValueError(f"keyframe selection needs a finite 4x4 pose and time, got shape {pose.shape}, t={t}")
        if not self.is_candidate(pose, t):
            return False, None
        replaced = self._pending[0] if self._pending is not None else None
        self._pending = (item, pose, float(t))
        return True, replaced

    @property
    def has_pending(self) -> bool:
        """True while a candidate waits for the mapper."""
        return self._pending is not None

    def take(self) -> Optional[Any]:
        """Hand the pending candidate to the mapper (it becomes the reference keyframe); None when empty."""
        if self._pending is None:
            return None
        item, pose, t = self._pending
        self._pending = None
        self.ref_pose, self.ref_time = pose, t
        return item

    def drop_pending(self) -> Optional[Any]:
        """Discard the pending candidate (mission closed); returns it or None."""
        item = self._pending[0] if self._pending is not None else None
        self._pending = None
        return item

    def state_dict(self) -> dict:
        """Reference keyframe (for checkpoints): ``{"ref_pose": list | None, "ref_time": float | None}``."""
        return {"ref_pose": None if self.ref_pose is None else self.ref_pose.tolist(), "ref_time": self.ref_time}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state` (the pending slot starts empty)."""
        rp = state.get("ref_pose")
        self.ref_pose = None if rp is None else np.asarray(rp, dtype=np.float64).reshape(4, 4)
        self.ref_time = state.get("ref_time")
        self._pending = None
