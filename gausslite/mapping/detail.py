"""The task region at its own resolution: two resolutions, one map (docs/mapper.md, "The task region at its own
resolution").

A live agent maps at one image resolution chosen for its compute (:mod:`gausslite.mapping.resolution`). When the
compute is scarce that resolution drops, and a small task region loses the detail GaussLite exists for. With
``mapper.detail.enabled`` the mapper may get, beside the keyframe at the mapping resolution, the same view at a
finer one (:class:`DetailView`). The map stays one set of Gaussians; what changes is where the region's pixels come
from:

- the keyframe keeps a compact *detail crop* beside its coarse stored form: the region's bounding box at the detail
  resolution grown by a pad (:func:`cut_detail`), with the principal point moved and the focal of that resolution,
  the same frame id and the keyframe's pose tensor (pose refinement, placement and loop-closure corrections move
  both; the exposure response is keyed by the frame id, so both share it);
- ROI-phase iterations that draw that keyframe render and fit the detail crop instead of the coarse crop (same
  loss, :class:`~gausslite.mapping.step.TrainStep`);
- the region's seeds come from the detail crop's relevant pixels (:func:`detail_pool`), the background's from
  the coarse frame; the count is the coarse rule's, so the Gaussian budget and eviction are unchanged;
- the ROI views of the frames between keyframes are cut from the detail view's frames.

The full-image (warm-up) iterations, tracking, coverage and adoption tests stay at the mapping resolution.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite.mapping.seeding import sobel_magnitude, weighted_choice
from gausslite.mapping.views import roi_box

__all__ = ["DetailView", "DetailCrop", "detail_scale", "detail_pad", "check_detail", "cut_detail", "coarse_index",
           "detail_pool", "detail_seed_pixels"]


@dataclass
class DetailView:
    """The keyframe at the task region's resolution (finer than the mapping resolution).

    Attributes:
        frame: the same keyframe at the ROI resolution: same ``frame_id``, ``c2w`` and ``timestamp``; rgb
            (H_d, W_d, 3) uint8, depth (H_d, W_d) float32 metres, intrinsics of that size (e.g.
            :func:`gausslite.datasets.common.downscale_frame` of the native frame).
        relevance: (H_d, W_d) bool: the task region at that size.
        between: the frames between keyframes at that size (oldest first; their ROI crops feed the ROI views,
            :meth:`Mapper.add_roi_views <gausslite.mapping.mapper.Mapper.add_roi_views>`).
    """

    frame: Frame
    relevance: np.ndarray
    between: Sequence[Frame] = ()


@dataclass
class DetailCrop:
    """A keyframe's task region cut from its :class:`DetailView` (numpy, before it becomes a tensor keyframe).

    Attributes:
        frame: the crop as a frame: rgb (h, w, 3) uint8, depth (h, w) float32 metres, intrinsics of the crop (the
            detail focal, principal point moved by the crop's corner), the keyframe's id, time and pose.
        relevance: (h, w) bool, the region inside the crop.
        scale: the detail focal over the mapping focal (4.0: a quarter-resolution map, a native-resolution region).
        box: (x0, y0, x1, y1) half-open pixels of the crop in the detail frame.
    """

    frame: Frame
    relevance: np.ndarray
    scale: float
    box: tuple[int, int, int, int]

    @property
    def pixels(self) -> int:
        """Pixels of the crop (w × h)."""
        return int(self.relevance.size)


def detail_scale(detail: Intrinsics, coarse: Intrinsics) -> float:
    """The detail resolution over the mapping resolution: ``detail.fx / coarse.fx`` (pixels per pixel)."""
    return float(detail.fx) / float(coarse.fx)


def detail_pad(pad_px: Optional[int], roi_crop_pad: int, scale: float) -> int:
    """Pad of a detail crop in detail pixels: ``pad_px`` when set, else ``roi_crop_pad`` (coarse pixels) × ``scale``
    rounded (the coarse crop's margin in the image)."""
    return int(pad_px) if pad_px is not None else int(round(roi_crop_pad * scale))


def check_detail(detail: DetailView, frame: Frame) -> None:
    """Check that ``detail`` shows ``frame``.

    Raises:
        ValueError: another frame id, a relevance map of another shape than its frame's depth, or colour/depth of
            another size than its intrinsics.
    """
    fr = detail.frame
    if int(fr.frame_id) != int(frame.frame_id):
        raise ValueError(f"detail view of frame {fr.frame_id} given for frame {frame.frame_id}")
    h, w = fr.intrinsics.height, fr.intrinsics.width
    if np.shape(fr.rgb) != (h, w, 3) or np.shape(fr.depth) != (h, w):
        raise ValueError(f"detail frame {fr.frame_id}: rgb {np.shape(fr.rgb)} / depth {np.shape(fr.depth)} do not "
                         f"match {w}x{h}")
    if np.shape(detail.relevance) != (h, w):
        raise ValueError(f"detail relevance shape {np.shape(detail.relevance)} != detail frame shape {(h, w)}")


def cut_detail(detail: DetailView, c2w: np.ndarray, coarse: Intrinsics, pad_px: Optional[int],
               roi_crop_pad: int) -> Optional[DetailCrop]:
    """The detail crop of a keyframe: the bounding box of ``detail.relevance`` grown by :func:`detail_pad` pixels,
    clipped to the image, with the principal point moved by the box's corner (cx − x0, cy − y0; the focal is the
    detail view's), as :func:`~gausslite.mapping.views.window_keyframe` cuts a window.

    Args:
        detail: the keyframe's detail view (checked with :func:`check_detail` by the caller).
        c2w: (4, 4) float64 camera-to-world pose the keyframe is mapped at (after placement and corrections).
        coarse: the keyframe's intrinsics at the mapping resolution (for the scale).
        pad_px, roi_crop_pad: ``mapper.detail.pad_px`` and ``mapper.roi_crop_pad``.
    Returns:
        the crop, or None when the relevance map is empty.
    """
    box = roi_box(np.asarray(detail.relevance, bool))
    if box is None:
        return None
    fr = detail.frame
    intr = fr.intrinsics
    scale = detail_scale(intr, coarse)
    pad = detail_pad(pad_px, roi_crop_pad, scale)
    x0, y0 = max(0, box[0] - pad), max(0, box[1] - pad)
    x1, y1 = min(intr.width, box[2] + pad), min(intr.height, box[3] + pad)
    k = Intrinsics(intr.fx, intr.fy, intr.cx - x0, intr.cy - y0, x1 - x0, y1 - y0)
    crop = dataclasses.replace(fr, rgb=np.ascontiguousarray(fr.rgb[y0:y1, x0:x1]),
                               depth=np.ascontiguousarray(fr.depth[y0:y1, x0:x1]),
                               c2w=np.asarray(c2w, np.float64).copy(), intrinsics=k)
    rel = np.ascontiguousarray(np.asarray(detail.relevance, bool)[y0:y1, x0:x1])
    return DetailCrop(crop, rel, scale, (x0, y0, x1, y1))


def coarse_index(crop: DetailCrop, pixels: np.ndarray, coarse: Intrinsics) -> np.ndarray:
    """The coarse pixel that sees each detail pixel's centre (the same ray; nearest pixel).

    Args:
        crop: the detail crop. pixels: (S,) int64 flat indices into the crop (v · w + u).
        coarse: the keyframe's intrinsics at the mapping resolution.
    Returns:
        (S,) int64 flat indices into the coarse image (v · W + u), −1 where the ray leaves it.
    """
    ci = crop.frame.intrinsics
    v, u = np.divmod(np.asarray(pixels, np.int64), ci.width)
    uc = np.rint((u - ci.cx) / ci.fx * coarse.fx + coarse.cx).astype(np.int64)
    vc = np.rint((v - ci.cy) / ci.fy * coarse.fy + coarse.cy).astype(np.int64)
    inside = (uc >= 0) & (uc < coarse.width) & (vc >= 0) & (vc < coarse.height)
    return np.where(inside, vc * coarse.width + uc, -1)


def detail_pool(crop: DetailCrop, allowed: np.ndarray, coarse: Intrinsics) -> np.ndarray:
    """The region's seed pool at the detail resolution: the crop's relevant pixels with valid depth whose coarse
    pixel (:func:`coarse_index`) is in ``allowed`` (the coverage test's candidates, or the adoption gap, both made at
    the mapping resolution).

    Args:
        crop: the detail crop. allowed: (H, W) bool mask at the mapping resolution. coarse: its intrinsics.
    Returns:
        (P,) int64 flat indices into the crop, ascending.
    """
    pool = np.flatnonzero((crop.relevance & (crop.frame.depth > 0)).ravel())
    if not pool.size:
        return pool.astype(np.int64)
    ci = coarse_index(crop, pool, coarse)
    return pool[(ci >= 0) & np.asarray(allowed, bool).ravel()[np.maximum(ci, 0)]].astype(np.int64)


def detail_seed_pixels(crop: DetailCrop, pool: np.ndarray, k: int, rng: np.random.Generator, gfd: bool = False,
                       gfd_eps: float = 0.05) -> np.ndarray:
    """``min(k, len(pool))`` seed pixels of the region drawn from ``pool`` (:func:`detail_pool`) without replacement
    (paper Sec. III-C's ROI pool, at the finer sampling): uniformly or, with GFD, ∝ the Sobel magnitude of the crop's
    luminance + ``gfd_eps``.

    Returns:
        (≤ k,) int64 flat indices into the crop.
    """
    weights = None
    if gfd and pool.size and k > 0:
        weights = (sobel_magnitude(crop.frame.rgb).astype(np.float64) + gfd_eps).ravel()[pool]
    return weighted_choice(pool, k, rng, weights).astype(np.int64)
