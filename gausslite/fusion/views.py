"""The views a robot sends for the joint refinement of the team map, within a byte budget (paper Sec. III-E).

The refinement (:func:`gausslite.fusion.refine.refine_map`) fits the fused map to the robots' views of their task
regions, on the ROI pixels only. Whole keyframes are mostly pixels it never looks at, so a robot that sends whole
keyframes can afford few of them, and a refinement over a few views memorises them (live, four keyframes: +14 to
+17 dB on them, -2.7 dB on every other frame). A robot therefore sends **ROI crops**: the part of a frame around its
task region (colour, depth and the ROI mask, with the principal point moved along, so the crop is an ordinary
pinhole view), of every frame it maps and, live, of the frames it sees between keyframes, their region carried
over from the keyframe by depth (:func:`region_points`, :func:`gausslite.mapping.roi_views.project_roi`).

The bytes a robot sends for these views are bounded by a multiple of its shared subset's bytes
(:class:`ViewBudget`); when the budget is short, the views farthest from those already sent go first
(:func:`next_view`), so the server gets the widest spread of viewpoints the budget buys.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import numpy as np

from gausslite.camera import Intrinsics, backproject, rotation_angle
from gausslite.wire.images import encode_color_jpeg, encode_color_png, encode_depth_png, encode_roi_png

__all__ = ["roi_crop", "region_points", "view_bytes", "ViewBudget", "next_view", "pose_distance"]

#: bytes a ``KeyframeRequest`` adds to its images at most (an agent id of up to 64 bytes, frame id, 16 pose doubles,
#: intrinsics, time, depth scale, field tags and lengths: about 290), so a budget counted with it is never exceeded
VIEW_ENVELOPE_BYTES = 320


def roi_crop(frame, roi: np.ndarray, margin_px: int) -> Optional[Tuple[object, np.ndarray]]:
    """The crop of ``frame`` around its task region, as a frame of its own.

    Args:
        frame: a posed RGB-D frame (:class:`gausslite.datasets.base.Frame`: ``rgb`` (H, W, 3) uint8, ``depth`` (H, W)
            float32 metres, ``c2w`` (4, 4) camera-to-world, OpenCV axes, ``intrinsics`` in pixels).
        roi: (H, W) bool task ROI of the frame.
        margin_px: pixels added around the ROI's bounding box on every side (clipped to the image).
    Returns:
        ``(crop, roi_crop)``: the cropped frame (same id, time and pose; intrinsics with the principal point moved by
        the crop's corner and the crop's size) and its (h, w) bool ROI; None when the ROI is empty.
    Raises:
        ValueError: ``roi`` does not match the frame's size, or ``margin_px`` < 0.
    """
    roi = np.asarray(roi, bool)
    h, w = np.shape(frame.depth)
    if roi.shape != (h, w):
        raise ValueError(f"frame {frame.frame_id}: roi {roi.shape} does not match depth {(h, w)}")
    if margin_px < 0:
        raise ValueError(f"margin_px must be >= 0, got {margin_px}")
    ys, xs = np.nonzero(roi)
    if not ys.size:
        return None
    x0, y0 = max(0, int(xs.min()) - margin_px), max(0, int(ys.min()) - margin_px)
    x1, y1 = min(w, int(xs.max()) + 1 + margin_px), min(h, int(ys.max()) + 1 + margin_px)
    k = frame.intrinsics
    intr = Intrinsics(k.fx, k.fy, k.cx - x0, k.cy - y0, x1 - x0, y1 - y0)
    crop = dataclasses.replace(frame, rgb=np.ascontiguousarray(frame.rgb[y0:y1, x0:x1]),
                               depth=np.ascontiguousarray(frame.depth[y0:y1, x0:x1]), intrinsics=intr)
    return crop, np.ascontiguousarray(roi[y0:y1, x0:x1])


def region_points(frame, roi: np.ndarray, stride: int = 2) -> np.ndarray:
    """The task region of ``frame`` as world points: its ROI pixels with valid depth, back-projected.

    Args:
        frame: a posed RGB-D frame (depth (H, W) float32 metres; ``c2w`` (4, 4); pinhole intrinsics).
        roi: (H, W) bool task ROI.
        stride: every ``stride``-th pixel in both directions (the points are dilated when projected).
    Returns:
        (M, 3) float64 world points, metres ((0, 3) for an empty ROI).
    """
    s = max(1, int(stride))
    depth = np.asarray(frame.depth, np.float32)[::s, ::s]
    mask = np.asarray(roi, bool)[::s, ::s] & (depth > 0)
    if not mask.any():
        return np.zeros((0, 3))
    k = frame.intrinsics
    sub = Intrinsics(k.fx / s, k.fy / s, k.cx / s, k.cy / s, depth.shape[1], depth.shape[0])
    return backproject(depth, sub, np.asarray(frame.c2w, np.float64))[mask].astype(np.float64)


def view_bytes(frame, roi: Optional[np.ndarray], color_format: str = "png", jpeg_quality: int = 95) -> int:
    """Bytes ``frame`` takes on the wire as a keyframe (colour as PNG or JPEG, 16-bit PNG depth, 8-bit PNG ROI, and
    :data:`VIEW_ENVELOPE_BYTES` for the rest): what the fusion client's ``upload_keyframes`` sends for it.

    Raises:
        ValueError: unknown ``color_format``.
    """
    if color_format not in ("png", "jpeg"):
        raise ValueError(f"color_format must be 'png' or 'jpeg', got {color_format!r}")
    color = encode_color_png(frame.rgb) if color_format == "png" else encode_color_jpeg(frame.rgb, jpeg_quality)
    n = len(color) + len(encode_depth_png(frame.depth)[0]) + VIEW_ENVELOPE_BYTES
    return n + (len(encode_roi_png(roi)) if roi is not None else 0)


def pose_distance(a: np.ndarray, b: np.ndarray, rot_weight_m: float = 0.5) -> float:
    """Distance between two (4, 4) camera-to-world poses: translation (m) + ``rot_weight_m`` × rotation angle (rad)."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    r = a[:3, :3].T @ b[:3, :3]
    angle = float(rotation_angle(r))
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])) + rot_weight_m * angle


def next_view(candidates: Sequence[np.ndarray], sent: Sequence[np.ndarray]) -> int:
    """Index of the candidate pose farthest from every pose already sent (:func:`pose_distance`; the first
    candidate when nothing was sent): greedy farthest-point order, the widest spread of viewpoints first.

    Args:
        candidates: (4, 4) camera-to-world poses of the views waiting (at least one). sent: poses already sent.
    Raises:
        ValueError: no candidates.
    """
    if not len(candidates):
        raise ValueError("no candidate views")
    if not len(sent):
        return 0
    gaps = [min(pose_distance(c, s) for s in sent) for c in candidates]
    return int(np.argmax(gaps))


@dataclass
class ViewBudget:
    """The bytes one robot may send for refinement views: at most ``ratio`` × its shared subset's bytes (the latest
    subset encoded whole), counted over the whole mission; None = no bound. A share ``reserve`` of it is held back
    until the mission's final push, where it goes to the views still waiting that lie farthest from those sent: the
    views of places the robot reached late in the mission still find budget, chosen over the whole mission.

    Attributes:
        ratio: budget as a multiple of the subset's bytes (None: unbounded).
        reserve: share of the budget (0 ≤ reserve < 1) held for the final push (0: spend as views arrive).
        sent_bytes, sent: bytes and views sent so far.
        skipped: views left unsent because the budget was short when they were offered last.
        poses: (4, 4) poses of the views sent (for :func:`next_view`).
    """

    ratio: Optional[float] = 2.0
    reserve: float = 0.0
    sent_bytes: int = 0
    sent: int = 0
    skipped: int = 0
    poses: List[np.ndarray] = dataclasses.field(default_factory=list)

    def __post_init__(self) -> None:
        if not 0.0 <= float(self.reserve) < 1.0:
            raise ValueError(f"reserve must be in [0, 1), got {self.reserve}")

    def allowance(self, subset_bytes: int, final: bool = True) -> Optional[int]:
        """Bytes still allowed with a subset of ``subset_bytes`` (never negative); None when unbounded. Before the
        final push (``final`` False) the :attr:`reserve` is not yet allowed."""
        if self.ratio is None:
            return None
        share = 1.0 if final else 1.0 - float(self.reserve)
        return max(0, int(self.ratio * share * max(0, int(subset_bytes))) - self.sent_bytes)

    def record(self, nbytes: int, c2w: np.ndarray) -> None:
        """Count one view of ``nbytes`` bytes at pose ``c2w`` as sent."""
        self.sent_bytes += int(nbytes)
        self.sent += 1
        self.poses.append(np.asarray(c2w, np.float64))

    def choose(self, sizes: Sequence[int], poses: Sequence[np.ndarray], subset_bytes: int,
               final: bool = True) -> List[int]:
        """Which of the waiting views to send now, in sending order: farthest-first (:func:`next_view`) while they
        fit the allowance (a view too large is passed over for smaller ones). Records the chosen ones as sent and
        sets :attr:`skipped` to the number left.

        Args:
            sizes: bytes of each waiting view (:func:`view_bytes`). poses: their (4, 4) camera-to-world poses.
            subset_bytes: the robot's latest shared subset's bytes.
            final: the mission's final push, which may spend the :attr:`reserve` (:meth:`allowance`).
        Returns:
            indices into ``sizes``.
        Raises:
            ValueError: ``sizes`` and ``poses`` differ in length.
        """
        if len(sizes) != len(poses):
            raise ValueError(f"{len(sizes)} sizes for {len(poses)} poses")
        left = list(range(len(sizes)))
        out: List[int] = []
        while left:
            room = self.allowance(subset_bytes, final)
            fits = [i for i in left if room is None or sizes[i] <= room]
            if not fits:
                break
            i = fits[next_view([poses[j] for j in fits], self.poses)]
            self.record(sizes[i], poses[i])
            out.append(i)
            left.remove(i)
        self.skipped = len(left)
        return out
