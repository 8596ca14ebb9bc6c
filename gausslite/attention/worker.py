"""Relevance off the mapping thread: a keyframe maps with the newest relevance there is, and never waits for
the detector longer than a bound (paper Sec. III-B, re-projection between detection frames; ``docs/perception.md``).

:class:`RelevanceWorker` runs a relevance function (frame → (H, W) bool) in a thread of its own. The mapping thread
hands it each keyframe (:meth:`RelevanceWorker.relevance`) and waits at most ``max_wait_s`` for that frame's mask.
When the mask is not ready by then, the newest finished mask (of an earlier keyframe) is re-projected into this
keyframe through that frame's depth and both poses (:func:`reproject_mask`), and the frame's own mask, when it
arrives, becomes the newest for the next keyframe. A detector slower than the keyframe rate then costs mapping at
most ``max_wait_s`` per keyframe instead of its whole latency.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable, Optional

import cv2
import numpy as np

log = logging.getLogger(__name__)

__all__ = ["RelevanceWorker", "reproject_mask"]


def reproject_mask(mask: np.ndarray, depth: np.ndarray, c2w_src: np.ndarray, K_src: np.ndarray,
                   c2w_dst: np.ndarray, K_dst: np.ndarray, width: int, height: int, dilate_px: int = 2) -> np.ndarray:
    """Carry a relevance mask from one view into another through the source view's depth.

    Every mask pixel with valid depth is back-projected (OpenCV camera: x right, y down, z forward; metres) into
    the world frame with ``c2w_src`` and projected into the destination view; the hit pixels are dilated by
    ``dilate_px`` (the splats of neighbouring pixels spread apart as the view changes). Pixels hidden in the
    destination view are not tested (no depth there yet): the mapper's ROI tolerates a mask a little too large.

    Args:
        mask: (H, W) bool source mask. depth: (H, W) float metres (0 = invalid) of the source view.
        c2w_src, c2w_dst: (4, 4) camera-to-world. K_src, K_dst: (3, 3) pixel intrinsics.
        width, height: destination image size (pixels). dilate_px: dilation radius (>= 0).

    Returns:
        (height, width) bool mask of the destination view.

    Raises:
        ValueError: mask and depth of different shapes.
    """
    m = np.asarray(mask, bool)
    d = np.asarray(depth, np.float64)
    if m.shape != d.shape:
        raise ValueError(f"mask {m.shape} and depth {d.shape} differ")
    out = np.zeros((int(height), int(width)), np.uint8)
    vs, us = np.nonzero(m & (d > 0) & np.isfinite(d))
    if len(vs):
        z = d[vs, us]
        K = np.asarray(K_src, np.float64)
        pc = np.stack([(us + 0.5 - K[0, 2]) / K[0, 0] * z, (vs + 0.5 - K[1, 2]) / K[1, 1] * z, z], 1)
        src = np.asarray(c2w_src, np.float64)
        pw = pc @ src[:3, :3].T + src[:3, 3]
        dst = np.linalg.inv(np.asarray(c2w_dst, np.float64))
        q = pw @ dst[:3, :3].T + dst[:3, 3]
        front = q[:, 2] > 1e-6
        q = q[front]
        Kd = np.asarray(K_dst, np.float64)
        u = np.floor(Kd[0, 0] * q[:, 0] / q[:, 2] + Kd[0, 2]).astype(np.int64)
        v = np.floor(Kd[1, 1] * q[:, 1] / q[:, 2] + Kd[1, 2]).astype(np.int64)
        ok = (u >= 0) & (u < width) & (v >= 0) & (v < height)
        out[v[ok], u[ok]] = 1
    if dilate_px > 0 and out.any():
        k = 2 * int(dilate_px) + 1
        out = cv2.dilate(out, np.ones((k, k), np.uint8))
    return out.astype(bool)


class RelevanceWorker:
    """Relevance in a thread of its own with a bounded wait (module docstring).

    Args:
        fn: frame (``gausslite.datasets.base.Frame``) → (H, W) bool relevance (or None).
        max_wait_s: longest wait of :meth:`relevance` for the frame's own mask (seconds, >= 0).

    Raises:
        ValueError: negative ``max_wait_s``.
    """

    def __init__(self, fn: Callable, max_wait_s: float) -> None:
        if max_wait_s < 0:
            raise ValueError(f"max_wait_s must be >= 0, got {max_wait_s}")
        self.fn, self.max_wait_s = fn, float(max_wait_s)
        self._cv = threading.Condition()
        self._todo = None  # the next frame to process (only the newest waits)
        self._done: dict = {}  # frame_id -> mask of recent frames
        self._newest = None  # (frame, mask) of the newest finished frame
        self._stop = False
        self.computed = self.reprojected = self.waited_out = 0
        self.seconds = 0.0
        self._thread = threading.Thread(target=self._run, name="gausslite-relevance", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            with self._cv:
                while self._todo is None and not self._stop:
                    self._cv.wait()
                if self._stop:
                    return
                fr, self._todo = self._todo, None
            t0 = time.perf_counter()
            try:
                mask = self.fn(fr)
            except Exception as e:  # noqa: BLE001 - a failed frame leaves the newest mask in place
                log.warning("relevance of frame %s failed: %s: %s", getattr(fr, "frame_id", "?"), type(e).__name__, e)
                mask = None
            with self._cv:
                self.seconds += time.perf_counter() - t0
                self.computed += 1
                self._done[fr.frame_id] = mask
                while len(self._done) > 8:
                    self._done.pop(next(iter(self._done)))
                if mask is not None:
                    self._newest = (fr, np.asarray(mask, bool))
                self._cv.notify_all()

    def relevance(self, frame) -> Optional[np.ndarray]:
        """This frame's relevance, or (after ``max_wait_s``) the newest earlier one re-projected into it; None when
        there is none yet. The frame's own mask keeps being computed after a time-out."""
        fid = frame.frame_id
        with self._cv:
            if fid not in self._done:
                self._todo = frame
                self._cv.notify_all()
                deadline = time.monotonic() + self.max_wait_s
                while fid not in self._done and not self._stop:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        break
                    self._cv.wait(left)
            if fid in self._done:
                return self._done[fid]
            self.waited_out += 1
            newest = self._newest
        if newest is None:
            return None
        src, mask = newest
        self.reprojected += 1
        return reproject_mask(mask, src.depth, src.c2w, src.intrinsics.K, frame.c2w, frame.intrinsics.K,
                              frame.intrinsics.width, frame.intrinsics.height)

    def close(self) -> None:
        """Stop the thread (a running relevance call finishes first)."""
        with self._cv:
            self._stop = True
            self._cv.notify_all()
        self._thread.join(timeout=30)
