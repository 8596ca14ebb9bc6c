"""Backends that spend one backend's compute time and give another backend's answer: the cost of real
networks (e.g. random-weight ONNX exports, whose detections mean nothing) with the relevance of a working
source (the scene's annotations). Used by the retired ``bench.frontend`` (docs/history.md#frontend) and the agent's
``relevance_backend: onnx_cost``
to measure how the front-end's compute changes mapping, separately from how its accuracy does."""

from __future__ import annotations

import time
from typing import List, Optional, Sequence

import numpy as np

from gausslite.attention.interfaces import Detections, Detector, FrameContext, Segmenter

__all__ = ["CostOnlyDetector", "CostOnlySegmenter"]


class _CostOnly:
    """Runs the ``cost`` backend's method (its result is dropped), then returns the ``answer`` backend's.

    Attributes:
        seconds: wall time of each ``cost`` call, seconds. answer_seconds: total time of ``answer``, seconds.
    """

    def __init__(self, cost, answer) -> None:
        self.cost, self.answer = cost, answer
        self.seconds: List[float] = []
        self.answer_seconds = 0.0

    def _call(self, method: str, *args):
        t = time.perf_counter()
        getattr(self.cost, method)(*args)
        t1 = time.perf_counter()
        self.seconds.append(t1 - t)
        out = getattr(self.answer, method)(*args)
        self.answer_seconds += time.perf_counter() - t1
        return out


class CostOnlyDetector(_CostOnly):
    """Runs ``cost.detect`` (its result is dropped), then returns ``answer.detect`` (:class:`_CostOnly`)."""

    def __init__(self, cost: Detector, answer: Detector) -> None:
        super().__init__(cost, answer)

    def detect(self, image: np.ndarray, phrases: Sequence[str], context: Optional[FrameContext] = None) -> Detections:
        """``answer``'s detections of ``phrases`` in the (H, W, 3) uint8 image, after running ``cost`` on it."""
        return self._call("detect", image, phrases, context)


class CostOnlySegmenter(_CostOnly):
    """Runs ``cost.segment`` (its result is dropped), then returns ``answer.segment`` (:class:`_CostOnly`)."""

    def __init__(self, cost: Segmenter, answer: Segmenter) -> None:
        super().__init__(cost, answer)

    def segment(self, image: np.ndarray, boxes: np.ndarray, context: Optional[FrameContext] = None) -> np.ndarray:
        """``answer``'s (K, H, W) bool masks for the (K, 4) xyxy boxes, after running ``cost`` on them."""
        return self._call("segment", image, boxes, context)
