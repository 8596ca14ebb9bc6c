"""Detector / segmenter plug-in interfaces and box/mask utilities (paper Sec. III-B, grounding and segmentation).

Conventions: images are (H, W, 3) uint8 RGB; boxes are (K, 4) float32 ``x0, y0, x1, y1`` in pixels of
that image (continuous coordinates, pixel (u, v) covers [u-0.5, u+0.5), so a box covering pixels
u0..u1 is ``[u0-0.5, ..., u1+0.5, ...]``); masks are (K, H, W) bool.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Protocol, Sequence, runtime_checkable

import numpy as np

from gausslite.camera import Intrinsics

__all__ = [
    "Detections",
    "FrameContext",
    "Detector",
    "Segmenter",
    "box_iou",
    "mask_iou",
    "mask_box_iou",
    "nms",
    "filter_boxes_by_area",
    "match_masks_to_boxes",
]


@dataclass
class FrameContext:
    """Geometry of the current frame, for backends that need more than the image (annotation backend).

    Attributes:
        depth: (H, W) float32 metres along camera z, 0 = invalid.
        c2w: (4, 4) float64 camera-to-world pose, OpenCV camera axes.
        intrinsics: pinhole intrinsics of the image.
        frame_id: index of the frame (used as a cache key together with the arrays' identity).
    """

    depth: np.ndarray
    c2w: np.ndarray
    intrinsics: Intrinsics
    frame_id: int = -1


@dataclass
class Detections:
    """Open-vocabulary detections of one image.

    Attributes:
        boxes: (K, 4) float32 xyxy pixels.
        scores: (K,) float32 confidence in [0, 1].
        phrase_ids: (K,) int64 index into the query phrase list.
        extra: backend-specific per-detection info (e.g. annotation object ids), length K or empty.
    """

    boxes: np.ndarray
    scores: np.ndarray
    phrase_ids: np.ndarray
    extra: list = field(default_factory=list)

    def __post_init__(self) -> None:
        self.boxes = np.asarray(self.boxes, dtype=np.float32).reshape(-1, 4)
        self.scores = np.asarray(self.scores, dtype=np.float32).reshape(-1)
        self.phrase_ids = np.asarray(self.phrase_ids, dtype=np.int64).reshape(-1)
        k = len(self.boxes)
        if len(self.scores) != k or len(self.phrase_ids) != k or (self.extra and len(self.extra) != k):
            raise ValueError(f"inconsistent detection lengths: boxes {k}, scores {len(self.scores)}, "
                             f"phrase_ids {len(self.phrase_ids)}, extra {len(self.extra)}")

    def __len__(self) -> int:
        return len(self.boxes)

    @staticmethod
    def empty() -> "Detections":
        """No detections."""
        return Detections(np.zeros((0, 4)), np.zeros(0), np.zeros(0, dtype=np.int64))

    def select(self, idx) -> "Detections":
        """Subset by an index array or boolean mask."""
        idx = np.asarray(idx)
        if idx.dtype == bool:
            idx = np.flatnonzero(idx)
        return Detections(self.boxes[idx], self.scores[idx], self.phrase_ids[idx],
                          [self.extra[i] for i in idx] if self.extra else [])


@runtime_checkable
class Detector(Protocol):
    """Open-vocabulary detector: ``detect(image (H,W,3) uint8, phrases, context) -> Detections``."""

    def detect(self, image: np.ndarray, phrases: Sequence[str], context: Optional[FrameContext] = None) -> Detections:
        ...


@runtime_checkable
class Segmenter(Protocol):
    """Promptable segmenter: ``segment(image (H,W,3) uint8, boxes (K,4) xyxy, context) -> (K,H,W) bool``."""

    def segment(self, image: np.ndarray, boxes: np.ndarray, context: Optional[FrameContext] = None) -> np.ndarray:
        ...


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of xyxy boxes: (N, 4), (M, 4) -> (N, M) float64 (0 where the union is empty)."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    ix0 = np.maximum(a[:, None, 0], b[None, :, 0])
    iy0 = np.maximum(a[:, None, 1], b[None, :, 1])
    ix1 = np.minimum(a[:, None, 2], b[None, :, 2])
    iy1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(ix1 - ix0, 0, None) * np.clip(iy1 - iy0, 0, None)
    area_a = np.clip(a[:, 2] - a[:, 0], 0, None) * np.clip(a[:, 3] - a[:, 1], 0, None)
    area_b = np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def mask_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of bool masks: (N, H, W), (M, H, W) -> (N, M) float64 (0 where the union is empty)."""
    a = np.asarray(a, dtype=bool).reshape(len(a), -1).astype(np.float32)
    b = np.asarray(b, dtype=bool).reshape(len(b), -1).astype(np.float32)
    inter = a @ b.T
    union = a.sum(1)[:, None] + b.sum(1)[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0).astype(np.float64)


def mask_box_iou(masks: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU between masks (N, H, W) and the filled pixel regions of boxes (M, 4) -> (N, M) float64."""
    masks = np.asarray(masks, dtype=bool)
    N, H, W = masks.shape
    fills = np.zeros((len(boxes), H, W), dtype=bool)
    for j, (x0, y0, x1, y1) in enumerate(np.asarray(boxes, dtype=np.float64).reshape(-1, 4)):
        u0, v0 = max(0, int(np.ceil(x0 - 0.5))), max(0, int(np.ceil(y0 - 0.5)))
        u1, v1 = min(W - 1, int(np.floor(x1 - 0.5))), min(H - 1, int(np.floor(y1 - 0.5)))
        if u1 >= u0 and v1 >= v0:
            fills[j, v0 : v1 + 1, u0 : u1 + 1] = True
    return mask_iou(masks, fills)


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy non-maximum suppression. Returns kept indices (int64), sorted by decreasing score."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    order = np.argsort(-np.asarray(scores, dtype=np.float64), kind="stable")
    keep = []
    while order.size:
        i = order[0]
        keep.append(i)
        if order.size == 1:
            break
        ious = box_iou(boxes[i : i + 1], boxes[order[1:]])[0]
        order = order[1:][ious <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


def filter_boxes_by_area(boxes: np.ndarray, image_hw: Sequence[int], max_fraction) -> np.ndarray:
    """Boolean keep-mask (K,) of boxes whose area is <= ``max_fraction`` of the image area.

    Args:
        boxes: (K, 4) xyxy pixels (clipped to the image before measuring).
        image_hw: (H, W).
        max_fraction: scalar or (K,) per-box limit in (0, 1]; 1 keeps everything.

    Raises:
        ValueError: a limit outside (0, 1].
    """
    H, W = int(image_hw[0]), int(image_hw[1])
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    lim = np.broadcast_to(np.asarray(max_fraction, dtype=np.float64), (len(b),))
    if np.any(lim <= 0) or np.any(lim > 1):
        raise ValueError(f"max_box_fraction must be in (0, 1], got {max_fraction}")
    x0 = np.clip(b[:, 0], -0.5, W - 0.5)
    x1 = np.clip(b[:, 2], -0.5, W - 0.5)
    y0 = np.clip(b[:, 1], -0.5, H - 0.5)
    y1 = np.clip(b[:, 3], -0.5, H - 0.5)
    area = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    return area <= lim * (H * W) + 1e-9


def match_masks_to_boxes(masks: np.ndarray, boxes: np.ndarray, min_iou: float = 0.0) -> np.ndarray:
    """Assign candidate masks to boxes one-to-one by mask-vs-box IoU (greedy, highest IoU first).

    Args:
        masks: (N, H, W) bool candidate masks (e.g. everything a FastSAM pass produced).
        boxes: (M, 4) xyxy pixels.
        min_iou: pairs at or below this IoU are never matched.

    Returns:
        (M,) int64: index of the mask matched to each box, -1 when none.
    """
    M = len(np.asarray(boxes).reshape(-1, 4))
    out = -np.ones(M, dtype=np.int64)
    if M == 0 or len(masks) == 0:
        return out
    iou = mask_box_iou(masks, boxes)  # (N, M)
    used_m, used_b = set(), set()
    for flat in np.argsort(-iou, axis=None, kind="stable"):
        n, m = np.unravel_index(flat, iou.shape)
        if iou[n, m] <= min_iou:
            break
        if n in used_m or m in used_b:
            continue
        out[m] = n
        used_m.add(n)
        used_b.add(m)
    return out
