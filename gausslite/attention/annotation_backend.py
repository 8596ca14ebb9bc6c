"""Offline annotation backend: detector + segmenter from a scene's ``objects.json`` (format: ``docs/mapper.md``).

Detector: every annotated object whose names (label + synonyms) match a query phrase
(:class:`~gausslite.attention.phrases.PhraseMatcher`, open-vocabulary: synonyms, singular/plural,
MiniLM similarity) and whose mask has at least ``min_mask_pixels`` pixels in this frame is a detection.
Its 2D box is the bounding box of the 8 projected corners of the box enlarged by its mask margin
(so that the whole mask lies inside it), clipped to the image; corners behind
the camera are handled by clipping the box edges at the near plane first. The score is the phrase
match score; ``Detections.extra`` holds the object ids.

Segmenter: a prompt box selects the annotated object whose projected 2D box has the highest IoU with it
(at least ``min_box_iou``), and returns that object's mask in this frame: pixels whose back-projected
depth lies inside the box enlarged by ``mask_margin_m`` (``SceneAnnotations.object_mask``).

Both need the frame geometry, passed as :class:`~gausslite.attention.interfaces.FrameContext`.
"""

from __future__ import annotations

from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from gausslite.attention.interfaces import Detections, FrameContext, box_iou
from gausslite.attention.phrases import PhraseMatcher
from gausslite.camera import Intrinsics

__all__ = ["AnnotationDetector", "AnnotationSegmenter", "AnnotationBackend", "project_box_2d"]

_EDGES = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]  # 12 box edges


def project_box_2d(corners_w: np.ndarray, c2w: np.ndarray, intr: Intrinsics, near: float = 1e-3) -> Optional[np.ndarray]:
    """2D xyxy box (4,) float32 of a 3D box's projection, clipped to the image, or None when not visible.

    Args:
        corners_w: (8, 3) world corners (``SceneAnnotations.box_corners`` order: corner k and corner
            k ^ (1 << b) differ along one box axis).
        c2w: (4, 4) camera-to-world pose (OpenCV axes).
        intr: intrinsics (image size W x H).
        near: near-plane depth in metres; the box is clipped to z >= near before projecting.
    """
    c2w = np.asarray(c2w, dtype=np.float64)
    pc = (np.asarray(corners_w, dtype=np.float64) - c2w[:3, 3]) @ c2w[:3, :3]  # camera frame
    pts = [p for p in pc if p[2] >= near]
    for i, j in _EDGES:
        zi, zj = pc[i, 2], pc[j, 2]
        if (zi - near) * (zj - near) < 0:
            t = (near - zi) / (zj - zi)
            pts.append(pc[i] + t * (pc[j] - pc[i]))
    if not pts:
        return None
    P = np.asarray(pts)
    u = intr.fx * P[:, 0] / P[:, 2] + intr.cx
    v = intr.fy * P[:, 1] / P[:, 2] + intr.cy
    W, H = intr.width, intr.height
    x0, x1 = max(u.min(), -0.5), min(u.max(), W - 0.5)
    y0, y1 = max(v.min(), -0.5), min(v.max(), H - 0.5)
    if x1 <= x0 or y1 <= y0:
        return None
    return np.array([x0, y0, x1, y1], dtype=np.float32)


class AnnotationBackend:
    """Per-frame projected boxes and masks of all annotated objects (shared cache of detector and segmenter).

    Args:
        annotations: ``SceneAnnotations`` of the scene (``dataset.annotations``).
        matcher: phrase matcher (default: :class:`PhraseMatcher` with its default config).
        min_mask_pixels: an object is visible in a frame when its mask has at least this many pixels.
    """

    def __init__(self, annotations, matcher: Optional[PhraseMatcher] = None, min_mask_pixels: int = 1) -> None:
        if annotations is None or not getattr(annotations, "objects", None):
            raise ValueError("the annotation backend needs SceneAnnotations with at least one object")
        self.annotations = annotations
        self.matcher = matcher or PhraseMatcher()
        self.min_mask_pixels = int(min_mask_pixels)
        self._key: Optional[Tuple] = None
        self._frame: Dict[int, Tuple[Optional[np.ndarray], np.ndarray]] = {}
        self._match_cache: Dict[Tuple[str, ...], List[List[Tuple[int, float]]]] = {}

    def _ensure_frame(self, ctx: FrameContext) -> None:
        if ctx is None:
            raise ValueError("the annotation backend needs a FrameContext (depth, c2w, intrinsics)")
        depth = np.asarray(ctx.depth)
        key = (ctx.frame_id, id(ctx.depth), depth.shape, np.asarray(ctx.c2w, dtype=np.float64).tobytes())
        if key == self._key:
            return
        self._frame = {}
        for o in self.annotations.objects:
            box = project_box_2d(self.annotations.box_corners(o, enlarged=True), ctx.c2w, ctx.intrinsics)
            if box is None:
                mask = np.zeros(depth.shape, dtype=bool)
            else:
                mask = self.annotations.object_mask(o.id, depth, ctx.c2w, ctx.intrinsics)
            self._frame[o.id] = (box, mask)
        self._key = key

    def object_box_mask(self, object_id: int, ctx: FrameContext) -> Tuple[Optional[np.ndarray], np.ndarray]:
        """(projected box (4,) or None, mask (H, W) bool) of one object in the frame ``ctx``."""
        self._ensure_frame(ctx)
        return self._frame[int(object_id)]

    def matches(self, phrases: Sequence[str]) -> List[List[Tuple[int, float]]]:
        """Per phrase, matched ``(object_id, score)`` pairs (cached per phrase tuple)."""
        key = tuple(phrases)
        if key not in self._match_cache:
            ents = [[o.label, *o.synonyms] for o in self.annotations.objects]
            res = self.matcher.match(list(phrases), ents)
            self._match_cache[key] = [[(self.annotations.objects[j].id, s) for j, s in row] for row in res]
        return self._match_cache[key]


class AnnotationDetector:
    """Detector interface over :class:`AnnotationBackend` (see module docstring)."""

    def __init__(self, backend: AnnotationBackend) -> None:
        self.backend = backend

    def detect(self, image: np.ndarray, phrases: Sequence[str], context: Optional[FrameContext] = None) -> Detections:
        """Detections of the objects matching ``phrases`` that are visible in this frame.

        Each object is reported once, with the phrase it matches best.

        Raises:
            ValueError: ``context`` is None.
        """
        matches = self.backend.matches(phrases)
        best: Dict[int, Tuple[float, int]] = {}
        for pi, row in enumerate(matches):
            for oid, s in row:
                if oid not in best or s > best[oid][0]:
                    best[oid] = (s, pi)
        boxes, scores, pids, extra = [], [], [], []
        for oid, (s, pi) in sorted(best.items()):
            box, mask = self.backend.object_box_mask(oid, context)
            if box is None or int(mask.sum()) < self.backend.min_mask_pixels:
                continue
            boxes.append(box)
            scores.append(s)
            pids.append(pi)
            extra.append(oid)
        if not boxes:
            return Detections.empty()
        return Detections(np.stack(boxes), scores, pids, extra)


class AnnotationSegmenter:
    """Segmenter interface over :class:`AnnotationBackend` (see module docstring).

    Args:
        backend: the shared backend.
        min_box_iou: prompt boxes whose best IoU with a projected object box is below this get an empty mask.
    """

    def __init__(self, backend: AnnotationBackend, min_box_iou: float = 0.1) -> None:
        self.backend = backend
        self.min_box_iou = float(min_box_iou)

    def segment(self, image: np.ndarray, boxes: np.ndarray, context: Optional[FrameContext] = None) -> np.ndarray:
        """(K, H, W) bool masks for the prompt boxes (K, 4) xyxy.

        Raises:
            ValueError: ``context`` is None.
        """
        boxes = np.asarray(boxes, dtype=np.float32).reshape(-1, 4)
        if context is None:
            raise ValueError("the annotation backend needs a FrameContext (depth, c2w, intrinsics)")
        H, W = np.asarray(context.depth).shape
        out = np.zeros((len(boxes), H, W), dtype=bool)
        ids, obj_boxes = [], []
        for o in self.backend.annotations.objects:
            b, m = self.backend.object_box_mask(o.id, context)
            if b is not None and m.any():
                ids.append(o.id)
                obj_boxes.append(b)
        if not ids or len(boxes) == 0:
            return out
        iou = box_iou(boxes, np.stack(obj_boxes))
        for k in range(len(boxes)):
            j = int(np.argmax(iou[k]))
            if iou[k, j] >= self.min_box_iou:
                out[k] = self.backend.object_box_mask(ids[j], context)[1]
        return out
