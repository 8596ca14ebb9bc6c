"""Evaluator: renders a map at dataset views and scores it (paper Sec. IV, metrics).

Full-image PSNR/SSIM/depth L1, and PSNR/SSIM restricted to the ground-truth ROI mask of a task
(pixels whose depth point lies inside a task-relevant box, from ``objects.json``/``tasks.json``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping, Optional, Sequence

import cv2
import numpy as np
import torch

from gausslite.datasets.base import Frame
from gausslite.metrics import depth_l1, psnr, ssim
from gausslite.render import RenderOutput

RenderFn = Callable[[Frame], RenderOutput]


@dataclass
class FrameScore:
    """Scores of one view. ROI fields are NaN when no ROI mask was given or it is empty."""

    frame_id: int
    psnr: float
    ssim: float
    depth_l1: float
    roi_psnr: float = math.nan
    roi_ssim: float = math.nan
    roi_fraction: float = math.nan


@dataclass
class EvalSummary:
    """Means over views (ROI means over views whose ROI is non-empty)."""

    scores: list[FrameScore] = field(default_factory=list)
    #: name → summary of the same renders scored on another ROI (``evaluate(extra_rois=...)``)
    per_roi: dict = field(default_factory=dict)

    def mean(self, key: str) -> float:
        vals = [getattr(s, key) for s in self.scores]
        vals = [v for v in vals if not math.isnan(v)]
        return float(np.mean(vals)) if vals else math.nan

    def as_dict(self, prefix: str = "") -> dict:
        keys = ["psnr", "ssim", "depth_l1", "roi_psnr", "roi_ssim", "roi_fraction"]
        d = {prefix + k: self.mean(k) for k in keys}
        d[prefix + "n_views"] = len(self.scores)
        return d


def score_view(out: RenderOutput, frame: Frame, roi: Optional[np.ndarray] = None) -> FrameScore:
    """Score one render against its frame.

    Args:
        out: render at the frame's pose and intrinsics (colour clamped to [0,1] here).
        frame: ground truth.
        roi: (H, W) bool ground-truth ROI mask or None.
    """
    dev = out.color.device
    gt = torch.from_numpy(frame.rgb).to(dev, torch.float32) / 255.0
    gtd = torch.from_numpy(np.ascontiguousarray(frame.depth)).to(dev, torch.float32)
    pred = out.color.detach().clamp(0, 1)
    s = FrameScore(
        frame_id=frame.frame_id,
        psnr=float(psnr(pred, gt)),
        ssim=float(ssim(pred, gt)),
        depth_l1=float(depth_l1(out.depth.detach(), gtd)),
    )
    if roi is not None:
        m = torch.from_numpy(np.asarray(roi, bool)).to(dev)
        s.roi_fraction = float(m.float().mean())
        if bool(m.any()):
            s.roi_psnr = float(psnr(pred, gt, mask=m))
            s.roi_ssim = float(ssim(pred, gt, mask=m))
    return s


def side_by_side(out: RenderOutput, frame: Frame, roi: Optional[np.ndarray] = None) -> np.ndarray:
    """(H, 2W or 3W, 3) uint8 BGR image: render | ground truth [| ROI overlay] for PNG output."""
    pred = (out.color.detach().clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
    panels = [pred, frame.rgb]
    if roi is not None:
        ov = frame.rgb.copy()
        ov[roi] = (0.5 * ov[roi] + 0.5 * np.array([255, 0, 0])).astype(np.uint8)
        panels.append(ov)
    return cv2.cvtColor(np.concatenate(panels, axis=1), cv2.COLOR_RGB2BGR)


def render_map(gmap, frame: Frame, backend: str = "auto") -> RenderOutput:
    """Render a map at a frame's view, without gradients.

    Args:
        gmap: ``GaussianMap`` (means (N, 3) metres world frame, quats, log_scales, opacity_logits, colors; torch).
        frame: the view (its ``c2w`` (4, 4) camera-to-world, OpenCV camera, and pixel intrinsics).
        backend: rasterizer backend (``gausslite.render.rasterize``).

    Returns:
        ``RenderOutput`` at the frame's resolution, on a black background.
    """
    from gausslite.render import rasterize

    with torch.no_grad():
        return rasterize(gmap.means, gmap.quats, gmap.log_scales, gmap.opacity_logits, gmap.colors,
                         K=frame.intrinsics.K, width=frame.intrinsics.width, height=frame.intrinsics.height,
                         c2w=frame.c2w, background=torch.zeros(3), backend=backend)


def evaluate_fused(gmap, frames: Sequence[Frame], annotations, task_id: str, backend: str = "auto") -> Optional[float]:
    """Mean ROI PSNR (dB) of a (fused) map over ``frames``, each restricted to ``task_id``'s ground-truth ROI
    (``annotations.roi_mask``); frames with an empty ROI are skipped (paper Sec. IV, ROI PSNR).

    Args:
        gmap: ``GaussianMap`` (see :func:`render_map`). frames: dataset frames. annotations: the scene's
            ``SceneAnnotations``. task_id: task whose ROI is scored. backend: rasterizer backend.

    Returns:
        The mean ROI PSNR in dB, or None when no frame shows the ROI or the map is empty.
    """
    if len(gmap) == 0:
        return None
    vals = []
    for fr in frames:
        roi = annotations.roi_mask(task_id, fr.depth, fr.c2w, fr.intrinsics)
        if not roi.any():
            continue
        s = score_view(render_map(gmap, fr, backend), fr, roi)
        if not math.isnan(s.roi_psnr):
            vals.append(s.roi_psnr)
    return float(np.mean(vals)) if vals else None


def evaluate(
    render: RenderFn,
    frames: Iterable[Frame],
    roi_fn: Optional[Callable[[Frame], np.ndarray]] = None,
    image_dir: Optional[Path] = None,
    image_ids: Sequence[int] = (),
    tag: str = "",
    extra_rois: Optional[Mapping[str, Callable[[Frame], np.ndarray]]] = None,
) -> EvalSummary:
    """Render and score each frame; write side-by-side PNGs for ``image_ids``.

    Args:
        render: function rendering the map at a frame's view.
        frames: views to score.
        roi_fn: frame → (H, W) bool ground-truth ROI mask, or None.
        image_dir: where PNGs go (``{tag}frame_{id:06d}.png``).
        extra_rois: name → ROI function; each render is also scored on these ROIs, into
            ``summary.per_roi[name]`` (one map, several tasks, one render per view).
    """
    summary = EvalSummary()
    extra = dict(extra_rois or {})
    summary.per_roi = {name: EvalSummary() for name in extra}
    wanted = set(int(i) for i in image_ids)
    for fr in frames:
        out = render(fr)
        roi = roi_fn(fr) if roi_fn is not None else None
        summary.scores.append(score_view(out, fr, roi))
        for name, fn in extra.items():
            summary.per_roi[name].scores.append(score_view(out, fr, fn(fr)))
        if image_dir is not None and fr.frame_id in wanted:
            image_dir.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(image_dir / f"{tag}frame_{fr.frame_id:06d}.png"), side_by_side(out, fr, roi))
    return summary
