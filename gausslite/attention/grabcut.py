"""Weight-free promptable segmenter: OpenCV GrabCut initialised with each prompt box (a fallback).

GrabCut fits foreground/background colour GMMs, starting from "everything inside the box is probably
foreground, everything outside is background", and refines the labelling with graph cuts.
"""

from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from gausslite.attention.interfaces import FrameContext

__all__ = ["GrabCutSegmenter"]


class GrabCutSegmenter:
    """Segmenter interface: ``segment(image, boxes) -> (K, H, W) bool``.

    Args:
        iterations: GrabCut iterations per box (>= 1).
        min_box_px: boxes thinner than this (pixels) after clipping give an empty mask.
    """

    def __init__(self, iterations: int = 5, min_box_px: int = 2) -> None:
        if int(iterations) < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations}")
        self.iterations = int(iterations)
        self.min_box_px = int(min_box_px)

    def segment(self, image: np.ndarray, boxes: np.ndarray, context: Optional[FrameContext] = None) -> np.ndarray:
        """Masks for the xyxy pixel boxes (K, 4); ``image`` is (H, W, 3) uint8 RGB. Pixels outside a box
        are never in its mask.

        Raises:
            ValueError: the image is not (H, W, 3) uint8.
        """
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"image must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
        H, W = img.shape[:2]
        bgr = np.ascontiguousarray(img[..., ::-1])
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
        out = np.zeros((len(boxes), H, W), dtype=bool)
        for k, (x0, y0, x1, y1) in enumerate(boxes):
            u0, v0 = max(0, int(np.floor(x0 + 0.5))), max(0, int(np.floor(y0 + 0.5)))
            u1, v1 = min(W, int(np.ceil(x1 + 0.5))), min(H, int(np.ceil(y1 + 0.5)))
            if u1 - u0 < self.min_box_px or v1 - v0 < self.min_box_px:
                continue
            if u0 == 0 and v0 == 0 and u1 == W and v1 == H:
                u0, v0, u1, v1 = 1, 1, W - 1, H - 1  # GrabCut needs some background outside the rect
            lab = np.zeros((H, W), dtype=np.uint8)
            bgd = np.zeros((1, 65), dtype=np.float64)
            fgd = np.zeros((1, 65), dtype=np.float64)
            try:
                cv2.grabCut(bgr, lab, (u0, v0, u1 - u0, v1 - v0), bgd, fgd, self.iterations, cv2.GC_INIT_WITH_RECT)
            except cv2.error:
                continue  # degenerate colour statistics (e.g. a constant image): no mask
            m = (lab == cv2.GC_FGD) | (lab == cv2.GC_PR_FGD)
            m[:, :u0] = False
            m[:, u1:] = False
            m[:v0] = False
            m[v1:] = False
            out[k] = m
        return out
