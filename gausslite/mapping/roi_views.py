"""ROI views: what the task region looks like in the frames between keyframes (paper Sec. III-D, extended).

A live robot sees the task region in many more frames than it keeps as keyframes (on TUM fr1/rpy about 7 for
each one it keeps). A map whose ROI is fitted to its ~20 keyframes alone fits those views, not the region: the
ROI scores several dB lower on frames it was not trained on (docs/realtime.md, "The frames between keyframes").
The ROI view store keeps, from each frame between keyframes that sees the region, only what the ROI phase
needs: the crop around the region (colour, depth, ROI mask), its pose and a slot for its pose correction and
exposure response. ROI-phase iterations draw those crops as well as the keyframes, and align them as they align
keyframes (``mapper.pose.roi_phase``). The per-keyframe time budget and the Gaussian cap are unchanged: what
changes is which views the ROI phase spends its iterations on.

- :func:`roi_points`: the task region of a keyframe as world points (its ROI pixels back-projected with depth);
- :func:`project_roi`: those points seen from another frame, as that frame's ROI mask (depth-tested, dilated);
- :class:`RoiViewStore`: the bounded store (a count and a byte cap; the most redundant view is evicted: the
  one whose pose is closest to another stored view's, as :class:`~gausslite.mapping.memory.KeyframeStore` drops
  keyframes).

The region of a frame between keyframes comes from the keyframes' relevance maps, not from the relevance
source (a detector costs too much to run on every frame): it is the ROI of the keyframes on both sides of the
frame, carried over by their depth.
"""

from __future__ import annotations

from typing import Optional, Sequence

import cv2
import numpy as np
import torch

from gausslite.camera import Intrinsics, backproject, rotation_angle
from gausslite.mapping.poses import PoseRefiner, nearest_key
from gausslite.mapping.views import (Keyframe, StoredKeyframe, StoredViews, closest_pose_pair, keyframe_from_frame,
                                     roi_box, window_keyframe)

__all__ = ["RoiViewStore", "roi_points", "project_roi", "roi_view_of"]


def roi_points(kf: StoredKeyframe, stride: int = 2) -> np.ndarray:
    """The task region of a keyframe as world points: its ROI pixels with valid depth, back-projected.

    Args:
        kf: a stored keyframe (compact; ``roi`` (H, W) bool or None, depth float16 metres, ``c2w`` (4, 4)
            camera-to-world, OpenCV camera axes, ``K`` (3, 3) pixels).
        stride: every ``stride``-th pixel in both directions (the points are dilated again when projected).
    Returns:
        (M, 3) float64 world points in metres; (0, 3) without ROI.
    """
    if kf.roi is None or kf.roi_box is None:
        return np.zeros((0, 3))
    s = max(1, int(stride))
    depth = kf.depth.float().numpy()[::s, ::s]
    roi = kf.roi.numpy()[::s, ::s]
    K = kf.K.numpy()
    sub = Intrinsics(K[0, 0] / s, K[1, 1] / s, K[0, 2] / s, K[1, 2] / s, depth.shape[1], depth.shape[0])
    pts = backproject(depth, sub, kf.c2w.numpy())
    return pts[roi & (depth > 0)].astype(np.float64)


def project_roi(points: np.ndarray, depth: np.ndarray, K: np.ndarray, c2w: np.ndarray, depth_tol_m: float = 0.1,
                dilate_px: int = 3) -> np.ndarray:
    """The ROI mask of a frame from the task region's world points (:func:`roi_points`).

    A point marks its pixel when it lies in front of the camera, inside the image and, where the frame has depth,
    within ``depth_tol_m`` (or 5 % of its depth, whichever is larger) of the observed depth there: a surface in
    front of the region hides it. The marks are dilated by ``dilate_px`` and their holes closed, then kept where
    the frame has valid depth.

    Args:
        points: (M, 3) world points, metres. depth: (H, W) float32 observed depth, metres (0 = invalid).
        K: (3, 3) intrinsics, pixels. c2w: (4, 4) camera-to-world pose (OpenCV camera axes).
        depth_tol_m: occlusion tolerance in metres. dilate_px: dilation radius in pixels.
    Returns:
        (H, W) bool mask (all False when no point is visible).
    """
    h, w = depth.shape
    mask = np.zeros((h, w), np.uint8)
    if len(points) == 0:
        return mask.astype(bool)
    w2c = np.linalg.inv(np.asarray(c2w, np.float64))
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    front = z > 1e-3
    pc, z = pc[front], z[front]
    u = np.round(K[0, 0] * pc[:, 0] / z + K[0, 2]).astype(np.int64)
    v = np.round(K[1, 1] * pc[:, 1] / z + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z = u[inside], v[inside], z[inside]
    d = depth[v, u]
    seen = (d <= 0) | (np.abs(d - z) <= np.maximum(depth_tol_m, 0.05 * z))
    mask[v[seen], u[seen]] = 1
    if dilate_px > 0 and mask.any():
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate_px + 1, 2 * dilate_px + 1))
        mask = cv2.morphologyEx(cv2.dilate(mask, k), cv2.MORPH_CLOSE, k)
    return (mask > 0) & (depth > 0)


def roi_view_of(frame, roi: np.ndarray, pad: int, device: torch.device | str = "cpu") -> Optional[Keyframe]:
    """The crop of ``frame`` around its ROI (the box grown by ``pad`` pixels, clipped to the image), with the
    principal point moved along (:func:`~gausslite.mapping.views.window_keyframe`): the view an ROI-phase iteration
    renders. None when the ROI is empty."""
    box = roi_box(roi)
    if box is None:
        return None
    kf = keyframe_from_frame(frame, device, roi)
    x0, y0, x1, y1 = box
    return window_keyframe(kf, x0 - pad, y0 - pad, x1 + pad, y1 + pad)


class RoiViewStore(StoredViews):
    """The ROI crops of frames between keyframes, compact (uint8 colour, float16 depth, bool ROI) and bounded.

    Args:
        max_views: at most this many views; max_bytes: at most this many bytes of images. Past either bound the
            most redundant view is evicted: the one whose pose lies closest to another stored view's (translation
            in metres + rotation angle in radians × ``rot_weight_m``), the older of the pair.
    Attributes:
        n_added / n_evicted: views stored and evicted so far.
    Raises:
        ValueError: a bound below 1.
    """

    def __init__(self, max_views: int = 96, max_bytes: int = 16 << 20, rot_weight_m: float = 0.5) -> None:
        if max_views < 1 or max_bytes < 1:
            raise ValueError(f"max_views and max_bytes must be >= 1, got {max_views}, {max_bytes}")
        self.max_views, self.max_bytes, self.rot_weight_m = int(max_views), int(max_bytes), float(rot_weight_m)
        super().__init__()
        self.n_added = 0
        self.n_evicted = 0

    @property
    def frame_ids(self) -> list[int]:
        """Frame ids of the stored views, oldest first."""
        return [int(k.frame_id) for k in self._items]

    def add(self, view: Keyframe) -> StoredKeyframe:
        """Store an ROI crop (:func:`roi_view_of`) compactly, then evict while over a bound; returns it.

        Raises:
            ValueError: a view without ROI pixels.
        """
        if view.roi_box is None:
            raise ValueError(f"view {view.frame_id} has no ROI pixels")
        st = view.compact()
        self._items.append(st)
        self.n_added += 1
        while len(self._items) > 1 and (len(self._items) > self.max_views or self.nbytes > self.max_bytes):
            self._evict()
        return st

    def _evict(self) -> None:
        c2w = torch.stack([k.c2w for k in self._items]).numpy()
        t = c2w[:, :3, 3]
        dt = np.linalg.norm(t[:, None] - t[None], axis=-1)
        rel = np.einsum("aji,bjk->abik", c2w[:, :3, :3], c2w[:, :3, :3])
        ang = rotation_angle(rel)
        cost = dt + self.rot_weight_m * ang
        np.fill_diagonal(cost, np.inf)
        a, b = np.unravel_index(int(np.argmin(cost)), cost.shape)
        self._items.pop(min(a, b))  # the older of the closest pair
        self.n_evicted += 1

    def load(self, i: int, device: torch.device) -> Keyframe:
        """View ``i`` as a float :class:`~gausslite.mapping.views.Keyframe` on ``device``."""
        return self._items[i].to_keyframe(device)

    def clear(self) -> None:
        """Forget every view (the task changed: their ROI was the old task's)."""
        self._items = []

    def follow(self, moves: dict, input_poses: dict, poses: PoseRefiner) -> None:
        """Move the views with corrected keyframes (:meth:`Mapper.apply_pose_corrections
        <gausslite.mapping.mapper.Mapper.apply_pose_corrections>`): each view whose nearest mapped frame (by frame id,
        among ``input_poses``' keys) has a move in ``moves`` (frame id → ((4, 4) world transform T, new pose)) takes
        ``T`` on its stored pose, and its correction in ``poses`` follows when it has one."""
        for view in self:
            k = nearest_key(input_poses, view.frame_id)
            if k not in moves:
                continue
            old = view.c2w.numpy().copy()
            new = moves[k][0] @ old
            view.c2w.copy_(torch.from_numpy(new))
            if view.frame_id in poses.corrections:
                E = poses.corrections[view.frame_id]
                poses.register(view.frame_id, E @ np.linalg.inv(old) @ new)

    def state_dict(self) -> dict:
        """``{"roi_views": [...]}``: the stored views as plain dicts of their compact fields (CPU tensor copies)."""
        return {"roi_views": self._dump(self._items)}

    def load_state_dict(self, state: dict) -> None:
        """Replace the views by copies of those of a :meth:`state_dict` (none when the key is absent: a checkpoint
        written before the store existed)."""
        self._items = self._undump(state.get("roi_views", []))


def window_points(stores: Sequence[StoredKeyframe], stride: int = 2) -> np.ndarray:
    """The task region of several keyframes as one (M, 3) array of world points (:func:`roi_points`)."""
    pts = [roi_points(k, stride) for k in stores]
    return np.concatenate(pts) if pts else np.zeros((0, 3))
