"""Evaluator: renders a map at dataset views and scores it (paper Sec. IV, metrics).

Full-image PSNR/SSIM/depth L1, and PSNR/SSIM restricted to the ground-truth ROI mask of a task
(pixels whose depth point lies inside a task-relevant box, from ``objects.json``/``tasks.json``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Mapping, Optional, Sequence

import cv2
import numpy as np
import torch

from gausslite.datasets.annotations import task_roi
from gausslite.datasets.base import Frame
from gausslite.datasets.subset import NOVEL_EVERY, FrameSubset, withheld_indices  # noqa: F401  (re-exported)
from gausslite.mapping.exposure import apply_exposure
from gausslite.mapping.poses import VectorAdam, pose_delta
from gausslite.mapping.views import keyframe_from_frame
from gausslite.metrics import depth_l1, psnr, ssim
from gausslite.render import RenderOutput, rasterize

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
    return roi_psnr_over(lambda fr: render_map(gmap, fr, backend), frames,
                         task_roi(annotations, task_id))


def roi_psnr_over(render: RenderFn, frames: Sequence[Frame], roi_fn: Callable[[Frame], np.ndarray]) -> Optional[float]:
    """Mean ROI PSNR (dB) of ``render`` (frame → ``RenderOutput``) over ``frames``, each restricted to
    ``roi_fn(frame)`` ((H, W) bool); frames with an empty ROI, or whose ROI PSNR is undefined, are skipped (paper
    Sec. IV, ROI PSNR). E.g. a team map through a robot's camera model
    (:meth:`gausslite.mapping.mapper.Mapper.seen_by_this_camera`).

    Returns:
        The mean ROI PSNR in dB, or None when no frame shows the ROI.
    """
    vals = []
    for fr in frames:
        roi = roi_fn(fr)
        if not roi.any():
            continue
        s = score_view(render(fr), fr, roi)
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


# ---------------------------------------------------------------------------------------------------- live-map scoring
#: the scoring protocols of a live map (docs/realtime.md#scoring-protocols)
PROTOCOLS = ("sensor", "keyframes", "tracked", "novel")


@dataclass
class TrackedView:
    """A frame's view fitted to a frozen map by :func:`track_view`.

    Attributes:
        c2w: (4, 4) float64 fitted camera-to-world pose (OpenCV camera axes, metres).
        theta: (6,) float64 fitted affine exposure (log gains, offsets; :func:`gausslite.mapping.exposure.apply_exposure`).
        loss: the full-image tracking loss at the last step.
        rot_deg / trans_m: the fitted pose's rotation (degrees) and translation (metres) away from the start.
        iters: Adam steps taken.
    """

    c2w: np.ndarray
    theta: np.ndarray
    loss: float
    rot_deg: float
    trans_m: float
    iters: int


def track_view(sensor, frame: Frame, c2w0: np.ndarray, theta0: Optional[np.ndarray] = None, iters: int = 30,
               lr_rot: float = 2e-3, lr_trans: float = 2e-3, lr_exposure: float = 0.01, lambda_depth: float = 0.5,
               alpha_min: float = 0.5) -> TrackedView:
    """Fit a frame's pose and affine exposure to a frozen map, for scoring (the ``tracked`` protocol; MonoGS's
    evaluation renders every frame at the pose its tracker fitted, Matsuki et al. CVPR 2024).

    The map is never changed. Starting from ``c2w0`` (the sensor's pose) and ``theta0``, ``iters`` Adam steps
    minimise L1 colour (after the exposure ``exp(a)·I + b``) + ``lambda_depth`` · L1 depth over the pixels the
    map covers (rendered alpha > ``alpha_min``; depth where the frame's depth is valid) — the whole image, never
    a task's region, so every map is tracked the same way whatever it was trained for. The pose is corrected on
    the right, ``c2w0 · E(ξ)`` (:mod:`gausslite.mapping.poses`), folded in after every step.

    Args:
        sensor: the map's :class:`~gausslite.mapping.sensor.SensorRenderer` (the sensor model the map was trained
            with: motion blur and rolling shutter render the same way).
        frame: the view (uint8 rgb (H, W, 3), float32 depth (H, W) metres, pinhole intrinsics in pixels).
        c2w0: (4, 4) starting pose. theta0: (6,) starting exposure (None: the identity response).
        iters: Adam steps (fixed, the same for every map). lr_rot (radians), lr_trans (metres), lr_exposure: steps.
        lambda_depth: weight of the depth term. alpha_min: silhouette threshold of the pixels that count.
    Returns:
        :class:`TrackedView`. A map that covers under 5 % of the view is not tracked (the start is returned).
    Raises:
        ValueError: ``iters`` < 0 or a frame whose images do not match its intrinsics.
    """
    if iters < 0:
        raise ValueError(f"iters must be >= 0, got {iters}")
    dev = sensor.device
    kf = keyframe_from_frame(frame, dev, None)
    c2w = torch.as_tensor(np.asarray(c2w0, np.float64), device=dev).clone()
    theta = np.zeros(6) if theta0 is None else np.asarray(theta0, np.float64).reshape(6).copy()
    pose_adam = VectorAdam(np.array([lr_rot] * 3 + [lr_trans] * 3))
    expo_adam = VectorAdam(np.full(6, float(lr_exposure)))
    valid_d = kf.depth > 0
    loss_v, done = math.nan, 0
    for _ in range(iters):
        xi = torch.zeros(6, dtype=torch.float64, device=dev, requires_grad=True)
        th = torch.tensor(theta, dtype=torch.float32, device=dev, requires_grad=True)
        out = sensor.render_view(c2w, kf.K, kf.width, kf.height, frame.frame_id, None, pose_xi=xi, detach_map=True)
        mask = out.alpha.detach() > alpha_min
        if int(mask.sum()) < 0.05 * mask.numel():
            break
        color = apply_exposure(out.color, th)
        l1c = ((color - kf.rgb).abs().sum(-1) * mask).sum() / (3.0 * mask.sum())
        dm = mask & valid_d
        l1d = ((out.depth - kf.depth).abs() * dm).sum() / dm.sum().clamp_min(1)
        loss = l1c + lambda_depth * l1d
        loss.backward()
        dxi = pose_adam.delta(0, xi.grad.detach().cpu().double().numpy())
        dth = expo_adam.delta(0, th.grad.detach().cpu().double().numpy())
        if dxi is None or dth is None:
            break
        c2w = c2w @ pose_delta(torch.from_numpy(dxi)).to(dev)
        theta = theta + dth
        loss_v, done = float(loss.detach()), done + 1
    E = np.linalg.inv(np.asarray(c2w0, np.float64)) @ c2w.cpu().numpy()
    ang = float(np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1))))
    return TrackedView(c2w.cpu().numpy(), theta, loss_v, ang, float(np.linalg.norm(E[:3, 3])), done)


def _protocol_render(mapper, frame: Frame, protocol: str, track_iters: int,
                     pose: Optional[np.ndarray] = None, given: Optional[TrackedView] = None,
                     record: Optional[dict] = None) -> RenderOutput:
    """The render a protocol scores a frame by (:func:`score_live_map`); ``pose``: a ``keyframes`` view's own pose
    (rendered as is, identity exposure) instead of the mapper's refined one; ``given``: a ``tracked`` or ``novel``
    view's pose and exposure fitted against another map (rendered as is, not tracked); ``record``: frame id → the
    :class:`TrackedView` of each ``tracked`` / ``novel`` frame, filled."""
    intr = frame.intrinsics
    if protocol == "keyframes" and pose is not None:
        with torch.no_grad():
            return mapper.sensor.render_view(np.asarray(pose, np.float64), intr.K, intr.width, intr.height,
                                             frame.frame_id, None)
    if protocol in ("sensor", "keyframes"):
        return mapper.render_frame(frame)
    # tracked and novel: a pose and exposure fitted to the frame against the frozen map
    tv = given
    if tv is None:
        exposure = mapper.sensor.exposure
        theta0 = exposure.of(frame.frame_id) if exposure is not None else None
        tv = track_view(mapper.sensor, frame, frame.c2w, theta0, iters=track_iters)
    if record is not None:
        record[int(frame.frame_id)] = tv
    with torch.no_grad():
        out = mapper.sensor.render_view(tv.c2w, intr.K, intr.width, intr.height, frame.frame_id, None)
        th = torch.tensor(tv.theta, dtype=torch.float32, device=out.color.device)
        return dataclasses.replace(out, color=apply_exposure(out.color, th).clamp(0.0, 1.0))


def score_live_map(mapper, frames: Sequence[Frame], roi_fn: Callable[[Frame], np.ndarray],
                   protocols: Sequence[str] = PROTOCOLS[:3], track_iters: int = 30, track_stride: int = 1,
                   keyframe_ids: Optional[Iterable[int]] = None,
                   keyframe_poses: Optional[Mapping[int, np.ndarray]] = None,
                   novel_ids: Optional[Iterable[int]] = None, views: Optional[Mapping[int, TrackedView]] = None,
                   record: Optional[dict] = None) -> dict:
    """Score a live map (:class:`~gausslite.mapping.mapper.Mapper`) under the scoring protocols, the same way for
    every mode (docs/realtime.md#scoring-protocols):

    - ``sensor``: every frame at the sensor's pose with its keyframe's refined correction and exposure response
      (between keyframes: interpolated, or the nearest one's, ``pose.between_keyframes``; :meth:`Mapper.render_frame`);
    - ``keyframes``: the trained views only (``keyframe_ids``; default the mapped frames), each at its own refined
      pose and exposure response; with ``keyframe_poses`` (frame id → (4, 4) camera-to-world, e.g. the keyframes a
      robot uploaded at their refined poses) those frames at those poses, identity exposure;
    - ``tracked``: every ``track_stride``-th frame at a pose and affine exposure fitted to that frame against the
      frozen map (:func:`track_view`, ``track_iters`` full-image steps from the sensor's pose), MonoGS's protocol;
    - ``novel``: the frames withheld from the mapper (``novel_ids``: never a keyframe, never a training view of any
      kind), each at a pose and exposure tracked like ``tracked``'s: what the map renders from views it was not
      trained on.

    Args:
        mapper: the map to score (not modified). frames: the sequence's frames (ground truth): a list, or a dataset
            (``len`` and indexing; read one frame at a time).
        roi_fn: frame → (H, W) bool ground-truth ROI mask (the scores' ROI; tracking never sees it).
        protocols: which of :data:`PROTOCOLS` to score. track_iters: the tracker's Adam steps per frame.
        track_stride: ``tracked`` scores every this many frames. keyframe_ids / keyframe_poses: see ``keyframes``.
        novel_ids: frame ids withheld from the mapper (:func:`withheld_indices`, :class:`FrameSubset`); needed by
            ``novel``.
        views: frame id → a :class:`TrackedView` fitted against another map (e.g. the robot's own map, when scoring a
            team map at the views its robot localises): ``tracked`` and ``novel`` frames with an entry are rendered
            at its pose and exposure instead of being tracked against this map. Both maps are then scored at the
            same views: their difference is what they render, not how well each one tracks.
        record: filled with frame id → the :class:`TrackedView` of every ``tracked`` and ``novel`` frame scored (the
            ``views`` of another map's scoring).
    Returns:
        ``{protocol: {"roi_psnr", "psnr", "ssim", "frames_scored", "roi_frames"}}``: means over the scored frames
        (ROI PSNR over those that show the ROI; None when none does).
    Raises:
        ValueError: an unknown protocol, ``track_stride`` < 1, ``novel`` without ``novel_ids``, or a withheld frame
            that the mapper trained on (a keyframe or a stored ROI view: the bookkeeping is broken).
    """
    bad = [p for p in protocols if p not in PROTOCOLS]
    if bad or track_stride < 1:
        raise ValueError(f"unknown protocols {bad} (known: {PROTOCOLS})" if bad else
                         f"track_stride must be >= 1, got {track_stride}")
    novel = {int(i) for i in novel_ids} if novel_ids is not None else None
    if "novel" in protocols and novel is None:
        raise ValueError("the novel protocol needs the withheld frames' ids (novel_ids)")
    if novel:
        trained = {int(s.frame_id) for s in mapper.stats} | set(mapper.roi_views.frame_ids)
        leaked = sorted(novel & trained)
        if leaked:
            raise ValueError(f"withheld frames {leaked[:5]} were training views of the map: not novel")
    poses = {int(k): v for k, v in keyframe_poses.items()} if keyframe_poses is not None else {}
    kf_ids = (set(poses) if keyframe_poses is not None else {int(s.frame_id) for s in mapper.stats}
              if keyframe_ids is None else {int(i) for i in keyframe_ids})
    res = {}
    n = len(frames)
    for protocol in protocols:
        # one frame in memory at a time (``frames`` may be a dataset that loads each on access)
        if protocol == "keyframes":
            chosen = (fr for fr in (frames[i] for i in range(n)) if int(fr.frame_id) in kf_ids)
        elif protocol == "novel":
            chosen = (fr for fr in (frames[i] for i in range(n)) if int(fr.frame_id) in novel)
        else:
            chosen = (frames[i] for i in range(0, n, track_stride if protocol == "tracked" else 1))
        ps, ss, rps = [], [], []
        for fr in chosen:
            given = None if views is None or protocol not in ("tracked", "novel") else views.get(int(fr.frame_id))
            s = score_view(_protocol_render(mapper, fr, protocol, track_iters, poses.get(int(fr.frame_id)), given,
                                            record), fr, roi_fn(fr))
            ps.append(s.psnr)
            ss.append(s.ssim)
            if not math.isnan(s.roi_psnr):
                rps.append(s.roi_psnr)
        res[protocol] = {"roi_psnr": float(np.mean(rps)) if rps else None,
                         "psnr": float(np.mean(ps)) if ps else None, "ssim": float(np.mean(ss)) if ss else None,
                         "frames_scored": len(ps), "roi_frames": len(rps)}
    return res


def frozen_mapper(gmap, backend: str = "auto"):
    """A :class:`~gausslite.mapping.mapper.Mapper` that holds ``gmap`` and nothing else, to score a map that has no
    mission of its own (a fused team map) with :func:`score_live_map`: no pose corrections, no exposure responses,
    no sensor effects (a fused map has no per-view record of them), black background.

    Args:
        gmap: ``GaussianMap`` (means (N, 3) metres world frame, …; torch, CPU). backend: rasterizer backend.
    """
    from gausslite.mapping.config import MapperConfig
    from gausslite.mapping.mapper import Mapper

    m = Mapper(MapperConfig(backend=backend))
    m.load_map(gmap)
    return m


def score_map(gmap, frames: Sequence[Frame], roi_fn: Callable[[Frame], np.ndarray],
              protocols: Sequence[str] = PROTOCOLS[:3], track_iters: int = 30, track_stride: int = 1,
              keyframe_poses: Optional[Mapping[int, np.ndarray]] = None, backend: str = "auto",
              novel_ids: Optional[Iterable[int]] = None, views: Optional[Mapping[int, TrackedView]] = None) -> dict:
    """Score a frozen map that has no mission of its own (a fused team map) under the scoring protocols, as
    :func:`score_live_map` scores a robot's own map (docs/realtime.md#scoring-protocols):

    - ``sensor``: every frame at the sensor's pose (:func:`evaluate_fused`'s figure);
    - ``keyframes``: the frames of ``keyframe_poses`` (frame id → (4, 4) camera-to-world: the keyframes the owner
      robot uploaded, at the refined poses they carry), identity exposure; none scored without it;
    - ``tracked``: every ``track_stride``-th frame at the pose and affine exposure :func:`track_view` fits against
      ``gmap`` from the sensor's pose;
    - ``novel``: the frames of ``novel_ids`` (withheld from every robot's mapper), tracked the same way.

    Args:
        gmap: ``GaussianMap`` (torch, CPU). frames: ground-truth frames. roi_fn: frame → (H, W) bool ROI mask.
        protocols, track_iters, track_stride, novel_ids, views: as :func:`score_live_map` (``views``: the poses and
            exposures the robot's own map was tracked at, to score a team map at the robot's views).
        backend: rasterizer backend.
    Returns:
        ``{protocol: {"roi_psnr", "psnr", "ssim", "frames_scored", "roi_frames"}}`` (None figures for an empty map).
    Raises:
        ValueError: an unknown protocol or ``track_stride`` < 1.
    """
    if len(gmap) == 0:
        bad = [p for p in protocols if p not in PROTOCOLS]
        if bad or track_stride < 1:
            raise ValueError(f"unknown protocols {bad} (known: {PROTOCOLS})" if bad else
                             f"track_stride must be >= 1, got {track_stride}")
        return {p: {"roi_psnr": None, "psnr": None, "ssim": None, "frames_scored": 0, "roi_frames": 0}
                for p in protocols}
    return score_live_map(frozen_mapper(gmap, backend), frames, roi_fn, protocols, track_iters=track_iters,
                          track_stride=track_stride, keyframe_poses=keyframe_poses or {}, novel_ids=novel_ids,
                          views=views)
