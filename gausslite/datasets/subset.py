"""Frames withheld from a mapper: the split of a sequence of the ``novel`` and ``novel-tracked`` scoring protocols
(docs/realtime.md#scoring-protocols).

A map is scored on frames that no mapper trained on (MonoGS evaluates non-keyframes; novel-view benchmarks hold
frames out): every k-th frame of the sequence is withheld from the mapper, in every mode, and scored at the pose and
exposure the finished map predicts for it (``novel``) and at a pose and exposure tracked against the finished map
(``novel-tracked``; :func:`gausslite.evaluation.score_live_map`).
"""

from __future__ import annotations

import dataclasses
from typing import Iterable, Mapping

import numpy as np

from gausslite.datasets.common import downscale_frame

#: the ``novel`` protocol's default: every this many frames of a sequence is withheld from the mapper
NOVEL_EVERY = 10

__all__ = ["NOVEL_EVERY", "withheld_indices", "FrameSubset", "ScaledFrames", "EstimatedPoses"]


def withheld_indices(n: int, every: int = NOVEL_EVERY) -> list[int]:
    """Indices of the frames a sequence of ``n`` frames withholds from the mapper for the ``novel`` protocol: every
    ``every``-th frame, starting at ``every // 2`` (the first frame, which fixes the map's gauge, is never withheld).

    Raises:
        ValueError: ``every`` < 2 (every frame withheld leaves nothing to map).
    """
    if every < 2:
        raise ValueError(f"the novel protocol withholds every k-th frame with k >= 2, got {every}")
    return list(range(every // 2, int(n), every))


class FrameSubset:
    """The frames of a sequence a mapper may see when some are withheld (``novel`` protocol): a read-only view of
    ``frames`` without the indices ``withheld``, with the sequence's ``annotations`` (if any). Frames keep their ids
    and timestamps, so a realtime replay of the subset sends each at its own time and the withheld ones never.

    Args:
        frames: a dataset or list (``len`` and indexing). withheld: indices into ``frames``.
    Attributes:
        withheld_ids: frame ids (``Frame.frame_id``) of the withheld frames.
    """

    def __init__(self, frames, withheld: Iterable[int]) -> None:
        held = {int(i) for i in withheld}
        self._frames = frames
        self._keep = [i for i in range(len(frames)) if i not in held]
        self.withheld_ids = frozenset(int(frames[i].frame_id) for i in sorted(held) if 0 <= i < len(frames))
        self.annotations = getattr(frames, "annotations", None)

    def __len__(self) -> int:
        return len(self._keep)

    def __getitem__(self, i: int):
        return self._frames[self._keep[i]]


class ScaledFrames:
    """A read-only view of ``frames`` with every frame downscaled by ``factor`` on access
    (:func:`~gausslite.datasets.common.downscale_frame`): scoring a map at the resolution it was mapped at."""

    def __init__(self, frames, factor: float) -> None:
        self._frames, self.factor = frames, float(factor)
        self.annotations = getattr(frames, "annotations", None)

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, i: int):
        return downscale_frame(self._frames[i], self.factor)


class EstimatedPoses:
    """A read-only view of ``frames`` at the poses a robot estimated for them (``agent.pose_source: odometry``): each
    frame's ``c2w`` is replaced by its estimate, and a frame without one (its tracking failed) is left out, as a robot
    has no pose to use the map at there. The frames' own poses stay in :attr:`given`, for what is a property of the
    image rather than of the robot's belief: the ground-truth ROI (:meth:`roi_fn`).

    Args:
        frames: a dataset or list (``len`` and indexing) of frames with their given (reference) poses.
        poses: frame id → (4, 4) float64 camera-to-world estimate (metres; the world frame of ``frames``).
    Attributes:
        given: frame id → (4, 4) float64 given camera-to-world pose of every frame kept.
        n_without_estimate: frames of ``frames`` left out for want of an estimate.
    """

    def __init__(self, frames, poses: Mapping[int, np.ndarray]) -> None:
        self._frames = frames
        self._poses = {int(k): np.asarray(v, dtype=np.float64) for k, v in poses.items()}
        ids = [int(frames[i].frame_id) for i in range(len(frames))]
        self._keep = [i for i, fid in enumerate(ids) if fid in self._poses]
        self.given = {ids[i]: np.asarray(frames[i].c2w, dtype=np.float64) for i in self._keep}
        self.n_without_estimate = len(ids) - len(self._keep)
        self.annotations = getattr(frames, "annotations", None)

    def __len__(self) -> int:
        return len(self._keep)

    def __getitem__(self, i: int):
        fr = self._frames[self._keep[i]]
        return dataclasses.replace(fr, c2w=self._poses[int(fr.frame_id)].copy())

    def roi_fn(self, annotations, task_id: str):
        """The ground-truth ROI of ``task_id`` (:func:`gausslite.datasets.annotations.task_roi`) of each frame of this
        view, from its given pose, not its estimate: frame → (H, W) bool.

        Raises:
            KeyError (when called): unknown task id, or a frame not in this view.
        """
        return lambda fr: annotations.roi_mask(task_id, fr.depth, self.given[int(fr.frame_id)], fr.intrinsics)
