"""Frames withheld from a mapper: the split of a sequence of the ``novel`` and ``novel-tracked`` scoring protocols
(docs/realtime.md#scoring-protocols).

A map is scored on frames that no mapper trained on (MonoGS evaluates non-keyframes; novel-view benchmarks hold
frames out): every k-th frame of the sequence is withheld from the mapper, in every mode, and scored at the pose and
exposure the finished map predicts for it (``novel``) and at a pose and exposure tracked against the finished map
(``novel-tracked``; :func:`gausslite.evaluation.score_live_map`).
"""

from __future__ import annotations

from typing import Iterable

from gausslite.datasets.common import downscale_frame

#: the ``novel`` protocol's default: every this many frames of a sequence is withheld from the mapper
NOVEL_EVERY = 10

__all__ = ["NOVEL_EVERY", "withheld_indices", "FrameSubset"]


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
