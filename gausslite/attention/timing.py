"""Backends that spend one backend's compute time and give another backend's answer: the cost of real
networks (e.g. random-weight ONNX exports, whose detections mean nothing) with the relevance of a working
source (the scene's annotations). Used by ``bench.frontend`` and the agent's ``relevance_backend: onnx_cost``
to measure how the front-end's compute changes mapping, separately from how its accuracy does."""

from __future__ import annotations

import time
from typing import List, Optional, Sequence

import numpy as np

from gausslite.attention.interfaces import Detections, Detector, FrameContext, Segmenter

__all__ = ["CostOnlyDetector", "CostOnlySegmenter"]


class CostOnlyDetector:
    """Runs ``cost.detect`` (its result is dropped), then returns ``answer.detect``.

    Attributes:
        seconds: wall time of each ``cost`` call, seconds. answer_seconds: total time of ``answer``, seconds.
    """

    def __init__(self, cost: Detector, answer: Detector) -> None:
        self.cost, self.answer = cost, answer
        self.seconds: List[float] = []
        self.answer_seconds = 0.0

    def detect(self, image: np.ndarray, phrases: Sequence[str], context: Optional[FrameContext] = None) -> Detections:
        """``answer``'s detections of ``phrases`` in the (H, W, 3) uint8 image, after running ``cost`` on it."""
        t = time.perf_counter()
        self.cost.detect(image, phrases, context)
        t1 = time.perf_counter()
        self.seconds.append(t1 - t)
        out = self.answer.detect(image, phrases, context)
        self.answer_seconds += time.perf_counter() - t1
        return out


class CostOnlySegmenter:
    """Runs ``cost.segment`` (its result is dropped), then returns ``answer.segment``.

    Attributes:
        seconds: wall time of each ``cost`` call, seconds. answer_seconds: total time of ``answer``, seconds.
    """

    def __init__(self, cost: Segmenter, answer: Segmenter) -> None:
        self.cost, self.answer = cost, answer
        self.seconds: List[float] = []
        self.answer_seconds = 0.0

    def segment(self, image: np.ndarray, boxes: np.ndarray, context: Optional[FrameContext] = None) -> np.ndarray:
        """``answer``'s (K, H, W) bool masks for the (K, 4) xyxy boxes, after running ``cost`` on them."""
        t = time.perf_counter()
        self.cost.segment(image, boxes, context)
        t1 = time.perf_counter()
        self.seconds.append(t1 - t)
        out = self.answer.segment(image, boxes, context)
        self.answer_seconds += time.perf_counter() - t1
        return out
