"""Frame and dataset interfaces shared by every loader (Replica, TUM RGB-D, 7-Scenes, synthetic)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence

import numpy as np

from gausslite.camera import Intrinsics


@dataclass
class Frame:
    """One posed RGB-D frame.

    Attributes:
        frame_id: index of the frame in its sequence (0-based, before any frame skipping).
        timestamp: seconds (dataset clock; frame index / fps when the dataset has none).
        rgb: (H, W, 3) uint8 colour image, RGB order.
        depth: (H, W) float32 depth in metres along camera z; 0 = invalid.
        c2w: (4, 4) float64 camera-to-world pose, OpenCV camera axes (x right, y down, z forward).
        intrinsics: pinhole intrinsics matching ``rgb``/``depth`` size.
        name: the frame's name in its sequence (e.g. the colour file's stem).
        pose_ok: False when ``c2w`` is not an estimate of this frame: its odometry failed and it carries the last
            good pose (:mod:`gausslite.datasets.odometry`); the mapper skips such a frame.
    """

    frame_id: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    c2w: np.ndarray
    intrinsics: Intrinsics
    name: str = ""
    pose_ok: bool = True


class RGBDDataset(Sequence[Frame], ABC):
    """Base class: a posed RGB-D sequence, indexable and iterable, loading frames lazily.

    Subclasses set ``self.path``, ``self.intrinsics`` (after downscaling), ``self.annotations``
    (``SceneAnnotations`` or None) and implement ``__len__`` and ``_load(i)``. ``has_poses`` is False for a
    sequence read without poses (its frames carry the identity until :class:`~gausslite.datasets.odometry.
    OdometryDataset` estimates them).
    """

    path: Path
    intrinsics: Intrinsics
    annotations: "Optional[object]" = None
    name: str = ""
    has_poses: bool = True

    @abstractmethod
    def __len__(self) -> int:
        """Number of frames."""

    @abstractmethod
    def _load(self, i: int) -> Frame:
        """Load frame ``i`` (0 <= i < len(self))."""

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        return self._load(i)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self._load(i)
