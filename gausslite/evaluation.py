"""Evaluator: renders a map at dataset views and scores it (paper Sec. IV, metrics).

Full-image PSNR/SSIM/depth L1, and PSNR/SSIM restricted to the ground-truth ROI mask of a task
(pixels whose depth point lies inside a task-relevant box, from ``objects.json``/``tasks.json``); a live map under the
scoring protocols (:func:`score_live_map`), at the views of :mod:`gausslite.tracked_views`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, Iterable, Mapping, Optional, Sequence

import cv2
import numpy as np
import torch

from gausslite.datasets.annotations import task_roi
from gausslite.datasets.base import Frame
from gausslite.datasets.subset import NOVEL_EVERY, FrameSubset, withheld_indices  # noqa: F401  (re-exported)
from gausslite.mapping.exposure import apply_exposure
from gausslite.metrics import GtStatsCache, depth_l1, psnr, ssim_with_mask
from gausslite.render import RenderOutput, rasterize
# the views a live map is scored at live in a module of their own; their names import from here as before
from gausslite.tracked_views import (TrackedView, fit_exposure_outside_roi, has_exposure_records,  # noqa: F401
                                     predicted_view, track_view)

RenderFn = Callable[[Frame], RenderOutput]
#: the ground truth's SSIM statistics of the frames scored last (each frame is scored under several protocols and maps)
_GT_STATS = GtStatsCache()


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
    m = torch.from_numpy(np.asarray(roi, bool)).to(dev) if roi is not None else None
    # one SSIM map for the image and the ROI, against the frame's statistics (cached: scored again and again)
    with torch.no_grad():
        full, in_roi = ssim_with_mask(pred, gt, m, _GT_STATS.get(frame.rgb, gt, pred.dtype))
    s = FrameScore(frame_id=frame.frame_id, psnr=float(psnr(pred, gt)), ssim=float(full),
                   depth_l1=float(depth_l1(out.depth.detach(), gtd)))
    if m is not None:
        s.roi_fraction = float(m.float().mean())
        if bool(m.any()):
            s.roi_psnr = float(psnr(pred, gt, mask=m))
            s.roi_ssim = float(in_roi)
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
    vals = list(evaluate_fused_frames(gmap, frames, annotations, task_id, backend).values())
    return float(np.mean(vals)) if vals else None


def evaluate_fused_frames(gmap, frames: Sequence[Frame], annotations, task_id: str,
                          backend: str = "auto") -> dict[int, float]:
    """:func:`evaluate_fused` frame by frame: frame id → ROI PSNR (dB) of each frame that shows the ROI (the pairs of
    a paired gain, :func:`gausslite.stats.paired_gain`); empty for an empty map."""
    if len(gmap) == 0:
        return {}
    return roi_psnr_frames(lambda fr: render_map(gmap, fr, backend), frames, task_roi(annotations, task_id))


def roi_psnr_over(render: RenderFn, frames: Sequence[Frame], roi_fn: Callable[[Frame], np.ndarray]) -> Optional[float]:
    """Mean ROI PSNR (dB) of ``render`` (frame → ``RenderOutput``) over ``frames``, each restricted to
    ``roi_fn(frame)`` ((H, W) bool); frames with an empty ROI, or whose ROI PSNR is undefined, are skipped (paper
    Sec. IV, ROI PSNR). E.g. a team map through a robot's camera model
    (:meth:`gausslite.mapping.mapper.Mapper.seen_by_this_camera`).

    Returns:
        The mean ROI PSNR in dB, or None when no frame shows the ROI.
    """
    vals = list(roi_psnr_frames(render, frames, roi_fn).values())
    return float(np.mean(vals)) if vals else None


def roi_psnr_frames(render: RenderFn, frames: Sequence[Frame],
                    roi_fn: Callable[[Frame], np.ndarray]) -> dict[int, float]:
    """:func:`roi_psnr_over` frame by frame: frame id → ROI PSNR (dB) of each frame whose ROI is not empty and whose
    ROI PSNR is defined."""
    vals = {}
    for fr in frames:
        roi = roi_fn(fr)
        if not roi.any():
            continue
        s = score_view(render(fr), fr, roi)
        if not math.isnan(s.roi_psnr):
            vals[int(fr.frame_id)] = s.roi_psnr
    return vals


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
#: the scoring protocols of a live map (docs/realtime.md#scoring-protocols): three at the pose the robot gives (with
#: the map's learned correction), two at a pose fitted to the frame against the map
PROTOCOLS = ("sensor", "keyframes", "novel", "tracked", "novel-tracked")
#: the protocols that fit each frame's pose and exposure to the map under test (:func:`track_view`)
TRACKED_PROTOCOLS = ("tracked", "novel-tracked")
#: the protocols that score the frames withheld from the mapper (``novel_ids``)
WITHHELD_PROTOCOLS = ("novel", "novel-tracked")
#: the question each protocol answers, for reports
PROTOCOL_QUESTIONS = {
    "sensor": "every frame at the pose the robot gives with the map's learned correction and exposure: the map as "
              "the robot uses it, mostly on views it trained on",
    "keyframes": "the trained views at their refined pose and exposure: what the map memorised",
    "novel": "frames withheld from the mapper at the pose and exposure the map predicts from its training alone: the "
             "map at the pose a robot would use, on views it never trained on",
    "tracked": "every k-th frame at a pose and exposure fitted to it against the map: how well a robot could localise "
               "against the map, and how the map looks from there",
    "novel-tracked": "the withheld frames at a pose and exposure fitted against the map: localisation on views no map "
                     "trained on, and the map from there",
}


def protocol_line(protocols: Mapping[str, Mapping]) -> str:
    """One line of a map's ROI PSNR under each scored protocol, each with the question it answers in short: the
    figures at the pose the robot gives (``sensor``, ``keyframes``, ``novel``) first, the tracked ones beside them.

    Args:
        protocols: :func:`score_live_map`'s result (``{protocol: {"roi_psnr": dB or None, "frames_scored": n}}``).
    Returns:
        e.g. ``"novel 23.10 (given pose, unseen views; 12 frames) | novel-tracked 23.60 (…) | …"``.
    """
    short = {"sensor": "given pose, every frame", "keyframes": "trained views", "novel": "given pose, unseen views",
             "tracked": "pose fitted to the map", "novel-tracked": "unseen views, pose fitted to the map"}
    order = ["novel", "novel-tracked", "sensor", "keyframes", "tracked"]
    cells = []
    for q in sorted(protocols, key=lambda q: order.index(q) if q in order else len(order)):
        v = protocols[q] or {}
        r = v.get("roi_psnr")
        fig = "–" if r is None else f"{r:.2f}"
        cells.append(f"{q} {fig} ({short.get(q, q)}; {v.get('frames_scored', 0)} frames)")
    return " | ".join(cells)


def current_protocol_name(name: str, entry=None) -> str:
    """The current name of a protocol read from an older result. Before ``novel`` scored the withheld frames at the
    pose the map predicts, ``novel`` (and a fused map's ``novel@own``) scored them at a pose tracked against the map:
    that figure is ``novel-tracked`` now. A ``novel`` entry written since carries ``"pose": "predicted"`` (itself, or
    each of its per-task entries); one without it is the older figure.

    Args:
        name: the protocol key read (``novel``, ``tracked@own``, …). entry: its value (a protocol's figures, or
            task → figures); None: the name alone decides (an old name stays).
    Returns:
        ``name``, or ``novel-tracked`` / ``novel-tracked@own`` for an older ``novel`` / ``novel@own`` entry.
    """
    base, at, suffix = name.partition("@")
    if base != "novel" or entry is None or not isinstance(entry, Mapping):
        return name
    marks = [entry.get("pose")] + [v.get("pose") for v in entry.values() if isinstance(v, Mapping)]
    return name if "predicted" in marks else "novel-tracked" + at + suffix


def current_protocols(protocols: Optional[Mapping]) -> dict:
    """``{protocol: entry}`` read from a result of any age, with :func:`current_protocol_name`'s keys (an older
    ``novel`` entry becomes ``novel-tracked``)."""
    return {current_protocol_name(q, v): v for q, v in (protocols or {}).items()}


def _render_at(mapper, frame: Frame, view: TrackedView) -> RenderOutput:
    """``mapper``'s map from ``frame``'s intrinsics at ``view``'s pose through its sensor model, ``view``'s exposure
    applied (colour clamped to [0, 1]); no gradients."""
    intr = frame.intrinsics
    with torch.no_grad():
        out = mapper.sensor.render_view(view.c2w, intr.K, intr.width, intr.height, frame.frame_id, None)
        th = torch.tensor(view.theta, dtype=torch.float32, device=out.color.device)
        return dataclasses.replace(out, color=apply_exposure(out.color, th).clamp(0.0, 1.0))


def _novel_render(mapper, frame: Frame, roi: Optional[np.ndarray], given: Optional[TrackedView],
                  fit_exposure: bool) -> tuple[RenderOutput, TrackedView]:
    """The ``novel`` protocol's render of a withheld frame and the view it was rendered at: ``given`` (the pose and
    exposure its owner robot's map predicts, e.g. to score a fused map), else the map's own prediction through the
    ``sensor`` protocol's code (:meth:`Mapper.render_frame`, :func:`predicted_view`); a map without exposure records
    under ``fit_exposure`` gets the exposure fitted outside the ROI (:func:`fit_exposure_outside_roi`). The pose is
    never fitted."""
    if given is not None:
        return _render_at(mapper, frame, given), given
    view = predicted_view(mapper, frame)
    if not (fit_exposure and not has_exposure_records(mapper)):
        return mapper.render_frame(frame), view
    intr = frame.intrinsics
    with torch.no_grad():
        out = mapper.sensor.render_view(view.c2w, intr.K, intr.width, intr.height, frame.frame_id, None)
    view = dataclasses.replace(view, theta=fit_exposure_outside_roi(out, frame, roi))
    th = torch.tensor(view.theta, dtype=torch.float32, device=out.color.device)
    return dataclasses.replace(out, color=apply_exposure(out.color.detach(), th).clamp(0.0, 1.0)), view


def _protocol_render(mapper, frame: Frame, protocol: str, track_iters: int, roi: Optional[np.ndarray],
                     pose: Optional[np.ndarray] = None, given: Optional[TrackedView] = None,
                     record: Optional[dict] = None, fit_exposure: bool = False) -> RenderOutput:
    """The render a protocol scores a frame by (:func:`score_live_map`); ``pose``: a ``keyframes`` view's own pose
    (rendered as is, identity exposure) instead of the mapper's refined one; ``given``: the view to render a
    ``tracked`` / ``novel-tracked`` frame at (fitted against another map) or a ``novel`` frame at (predicted by
    another map), not fitted here; ``record``: frame id → the :class:`TrackedView` the frame was rendered at, filled
    for the tracked and ``novel`` protocols; ``fit_exposure``: see :func:`score_live_map`."""
    if protocol == "keyframes" and pose is not None:
        intr = frame.intrinsics
        with torch.no_grad():
            return mapper.sensor.render_view(np.asarray(pose, np.float64), intr.K, intr.width, intr.height,
                                             frame.frame_id, None)
    if protocol in ("sensor", "keyframes"):
        return mapper.render_frame(frame)
    if protocol == "novel":
        out, view = _novel_render(mapper, frame, roi, given, fit_exposure)
        if record is not None:
            record[int(frame.frame_id)] = view
        return out
    # tracked and novel-tracked: a pose and exposure fitted to the frame against the frozen map
    tv = given
    if tv is None:
        exposure = mapper.sensor.exposure
        theta0 = exposure.of(frame.frame_id) if exposure is not None else None
        tv = track_view(mapper.sensor, frame, frame.c2w, theta0, iters=track_iters)
    if record is not None:
        record[int(frame.frame_id)] = tv
    return _render_at(mapper, frame, tv)


def _check_protocols(protocols: Sequence[str], track_stride: int) -> None:
    bad = [p for p in protocols if p not in PROTOCOLS]
    if bad or track_stride < 1:
        raise ValueError(f"unknown protocols {bad} (known: {PROTOCOLS})" if bad else
                         f"track_stride must be >= 1, got {track_stride}")


def _empty_result(protocol: str) -> dict:
    out = {"roi_psnr": None, "psnr": None, "ssim": None, "frames_scored": 0, "roi_frames": 0,
           "roi_psnr_per_frame": {}, "psnr_per_frame": {}}
    if protocol == "novel":
        out["pose"] = "predicted"
    return out


def score_live_map(mapper, frames: Sequence[Frame], roi_fn: Callable[[Frame], np.ndarray],
                   protocols: Sequence[str] = ("sensor", "keyframes", "tracked"), track_iters: int = 30,
                   track_stride: int = 1, keyframe_ids: Optional[Iterable[int]] = None,
                   keyframe_poses: Optional[Mapping[int, np.ndarray]] = None,
                   novel_ids: Optional[Iterable[int]] = None, views: Optional[Mapping[int, TrackedView]] = None,
                   record: Optional[dict] = None, novel_views: Optional[Mapping[int, TrackedView]] = None,
                   predicted: Optional[dict] = None, fit_exposure: bool = False) -> dict:
    """Score a live map (:class:`~gausslite.mapping.mapper.Mapper`) under the scoring protocols, the same way for
    every mode (docs/realtime.md#scoring-protocols; :data:`PROTOCOL_QUESTIONS` says what each answers). At the pose
    the robot gives (its own SLAM's) with what the map learned:

    - ``sensor``: every frame at the sensor's pose with its keyframe's refined correction and exposure response
      (between keyframes: interpolated, or the nearest one's, ``pose.between_keyframes``; :meth:`Mapper.render_frame`);
    - ``keyframes``: the trained views only (``keyframe_ids``; default the mapped frames), each at its own refined
      pose and exposure response; with ``keyframe_poses`` (frame id → (4, 4) camera-to-world, e.g. the keyframes a
      robot uploaded at their refined poses) those frames at those poses, identity exposure;
    - ``novel``: the frames withheld from the mapper (``novel_ids``: never a keyframe, never a training view of any
      kind) at the pose and exposure the map predicts for them from its training alone, exactly as ``sensor`` renders
      every frame (:func:`predicted_view`): nothing is fitted on a withheld frame. With ``novel_views`` (frame id →
      the view the owner robot's map predicts, e.g. to score a fused map) those views; a map without exposure
      records under ``fit_exposure`` gets each frame's affine exposure fitted on the pixels outside the ROI only
      (:func:`fit_exposure_outside_roi`, as NeRF-W and 3DGS's ``train_test_exp``), never the pose.

    At a pose fitted to the frame against the map under test (how well a robot could localise against it, and how the
    map looks from there):

    - ``tracked``: every ``track_stride``-th frame at a pose and affine exposure fitted to that frame against the
      frozen map (:func:`track_view`, ``track_iters`` full-image steps from the sensor's pose), MonoGS's protocol;
    - ``novel-tracked``: the withheld frames, tracked like ``tracked``'s. A frame both protocols score is fitted
      once: the same start, map and steps give the same view.

    Args:
        mapper: the map to score (not modified). frames: the sequence's frames (ground truth): a list, or a dataset
            (``len`` and indexing; read one frame at a time).
        roi_fn: frame → (H, W) bool ground-truth ROI mask (the scores' ROI; tracking never sees it, an exposure fit
            only its complement).
        protocols: which of :data:`PROTOCOLS` to score. track_iters: the tracker's Adam steps per frame.
        track_stride: ``tracked`` scores every this many frames. keyframe_ids / keyframe_poses: see ``keyframes``.
        novel_ids: frame ids withheld from the mapper (:func:`withheld_indices`, :class:`FrameSubset`); needed by
            ``novel`` and ``novel-tracked``.
        views: frame id → a :class:`TrackedView` fitted against another map (e.g. the robot's own map, when scoring a
            team map at the views its robot localises): ``tracked`` and ``novel-tracked`` frames with an entry are
            rendered at its pose and exposure instead of being tracked against this map. Both maps are then scored at
            the same views: their difference is what they render, not how well each one tracks.
        record / predicted: filled with frame id → the :class:`TrackedView` of every ``tracked`` and ``novel-tracked``
            frame scored (the ``views`` of another map's scoring) / every ``novel`` frame.
        novel_views: frame id → the view to render a ``novel`` frame at (another map's :func:`predicted_view`).
        fit_exposure: ``novel`` frames without a ``novel_views`` entry, on a map without exposure records: fit the
            affine exposure outside the ROI (a fused map); False: the map's prediction as is (identity exposure).
    Returns:
        ``{protocol: {"roi_psnr", "psnr", "ssim", "frames_scored", "roi_frames", "roi_psnr_per_frame",
        "psnr_per_frame"}}``: means over the scored frames (ROI PSNR over those that show the ROI; None when none
        does) and each frame's figure (frame id → dB; the pairs of every paired gain,
        :func:`gausslite.stats.paired_gain`); ``novel`` also carries ``"pose": "predicted"``
        (:func:`current_protocol_name`).
    Raises:
        ValueError: an unknown protocol, ``track_stride`` < 1, ``novel`` / ``novel-tracked`` without ``novel_ids``,
            or a withheld frame that the mapper trained on (a keyframe or a stored ROI view: the bookkeeping is
            broken).
    """
    _check_protocols(protocols, track_stride)
    novel = {int(i) for i in novel_ids} if novel_ids is not None else None
    if any(p in WITHHELD_PROTOCOLS for p in protocols) and novel is None:
        raise ValueError("the novel and novel-tracked protocols need the withheld frames' ids (novel_ids)")
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
    # a frame that two protocols render the same way is rendered and scored once (:func:`_view_key`): a frame that
    # both tracked protocols score (the same start, map and iterations give the same view), and a frame that
    # ``sensor``, ``keyframes`` and ``novel`` render at the same pose and exposure through the same path
    shown: Dict[tuple, tuple] = {}
    for protocol in protocols:
        # one frame in memory at a time (``frames`` may be a dataset that loads each on access)
        if protocol == "keyframes":
            chosen = (fr for fr in (frames[i] for i in range(n)) if int(fr.frame_id) in kf_ids)
        elif protocol in WITHHELD_PROTOCOLS:
            chosen = (fr for fr in (frames[i] for i in range(n)) if int(fr.frame_id) in novel)
        else:
            chosen = (frames[i] for i in range(0, n, track_stride if protocol == "tracked" else 1))
        given_of = (novel_views if protocol == "novel" else views if protocol in TRACKED_PROTOCOLS else None) or {}
        rec = predicted if protocol == "novel" else record if protocol in TRACKED_PROTOCOLS else None
        res[protocol] = _score_frames(
            protocol, chosen, lambda fr, roi, seen: _protocol_render(
                mapper, fr, protocol, track_iters, roi, poses.get(int(fr.frame_id)), given_of.get(int(fr.frame_id)),
                seen, fit_exposure), roi_fn, rec, shown,
            lambda fr: _view_key(mapper, fr, protocol, poses.get(int(fr.frame_id)), given_of.get(int(fr.frame_id)),
                                 fit_exposure),
            lambda fr: predicted_view(mapper, fr))
    return res


def _view_key(mapper, frame: Frame, protocol: str, pose: Optional[np.ndarray], given: Optional[TrackedView],
              fit_exposure: bool) -> Optional[tuple]:
    """What :func:`_protocol_render` renders ``frame`` from under ``protocol`` (its arguments), as a key: two
    protocols whose frames get the same key render the same image (the same path, pose and exposure: the renders are
    deterministic), so :func:`score_live_map` renders and scores it once. ``("fitted", id)``: the tracked protocols'
    view, fitted once or ``given``; ``("frame", id)``: :meth:`Mapper.render_frame`'s (``sensor``, ``keyframes`` at the
    refined pose, ``novel`` at the predicted view; ``keyframes`` at a given ``pose`` too when that is the pose
    ``render_frame`` takes and the map has no exposure records, whose response it would apply); ``("pose", …)`` /
    ``("view", …)``: a ``keyframes`` pose / a given ``novel`` view of its own. None: an exposure fitted on the render
    itself (``fit_exposure``), never shared."""
    fid = int(frame.frame_id)
    if protocol in TRACKED_PROTOCOLS:
        return ("fitted", fid)
    if protocol == "keyframes" and pose is not None:
        pose = np.asarray(pose, np.float64)
        same = not has_exposure_records(mapper) and np.array_equal(pose, mapper.pose_of(fid, frame.c2w))
        return ("frame", fid) if same else ("pose", fid, pose.tobytes())
    if protocol == "novel" and given is not None:
        return ("view", fid, np.asarray(given.c2w, np.float64).tobytes(), np.asarray(given.theta, np.float64).tobytes())
    if protocol == "novel" and fit_exposure and not has_exposure_records(mapper):
        return None
    return ("frame", fid)


def _score_frames(protocol: str, chosen: Iterable[Frame], render: Callable, roi_fn: Callable, rec: Optional[dict],
                  shown: Dict[tuple, tuple], key_of: Callable, view_of: Callable) -> dict:
    """:func:`score_live_map`'s figures of one protocol over the ``chosen`` frames: ``render(frame, roi, record)``
    renders a frame (filling ``record`` with its view); a frame whose :func:`_view_key` (``key_of``) is already in
    ``shown`` (key → ``(view, score)``, filled here) is not rendered again; ``rec``: the caller's record of the views
    (``view_of(frame)``: the predicted view of a ``novel`` frame whose render ``sensor`` or ``keyframes`` made, which
    record none; a given or fitted view is stored with its score)."""
    out = _empty_result(protocol)
    ss = []
    for fr in chosen:
        fid = int(fr.frame_id)
        key = key_of(fr)
        if key is not None and key in shown:
            view, s = shown[key]
            if rec is not None:
                rec[fid] = view if view is not None else view_of(fr)
        else:
            roi = roi_fn(fr)
            seen: dict = {}
            s = score_view(render(fr, roi, seen), fr, roi)
            if rec is not None and fid in seen:
                rec[fid] = seen[fid]
            if key is not None:
                shown[key] = (seen.get(fid), s)
        out["psnr_per_frame"][fid] = s.psnr
        ss.append(s.ssim)
        if not math.isnan(s.roi_psnr):
            out["roi_psnr_per_frame"][fid] = s.roi_psnr
    rps, ps = list(out["roi_psnr_per_frame"].values()), list(out["psnr_per_frame"].values())
    out.update(roi_psnr=float(np.mean(rps)) if rps else None, psnr=float(np.mean(ps)) if ps else None,
               ssim=float(np.mean(ss)) if ss else None, frames_scored=len(ps), roi_frames=len(rps))
    return out


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
              protocols: Sequence[str] = ("sensor", "keyframes", "tracked"), track_iters: int = 30,
              track_stride: int = 1, keyframe_poses: Optional[Mapping[int, np.ndarray]] = None, backend: str = "auto",
              novel_ids: Optional[Iterable[int]] = None, views: Optional[Mapping[int, TrackedView]] = None,
              novel_views: Optional[Mapping[int, TrackedView]] = None, record: Optional[dict] = None,
              predicted: Optional[dict] = None) -> dict:
    """Score a frozen map that has no mission of its own (a fused team map) under the scoring protocols, as
    :func:`score_live_map` scores a robot's own map (docs/realtime.md#scoring-protocols):

    - ``sensor``: every frame at the sensor's pose (:func:`evaluate_fused`'s figure);
    - ``keyframes``: the frames of ``keyframe_poses`` (frame id → (4, 4) camera-to-world: the keyframes the owner
      robot uploaded, at the refined poses they carry), identity exposure; none scored without it;
    - ``novel``: the frames of ``novel_ids`` (withheld from every robot's mapper) at the pose and exposure the owner
      robot's map predicts for them (``novel_views``: its :func:`predicted_view` of each, the robot's learned
      correction and exposure response); a frame without one at the sensor's pose, its affine exposure fitted on
      the pixels outside the ROI (:func:`fit_exposure_outside_roi`: a fused map keeps no exposure records). Nothing
      is fitted to the pose;
    - ``tracked``: every ``track_stride``-th frame at the pose and affine exposure :func:`track_view` fits against
      ``gmap`` from the sensor's pose;
    - ``novel-tracked``: the frames of ``novel_ids``, tracked the same way.

    Args:
        gmap: ``GaussianMap`` (torch, CPU). frames: ground-truth frames. roi_fn: frame → (H, W) bool ROI mask.
        protocols, track_iters, track_stride, novel_ids, views, record, predicted: as :func:`score_live_map`
            (``views``: the poses and exposures the robot's own map was tracked at, to score a team map at the
            robot's views).
        novel_views: frame id → the owner robot's :func:`predicted_view` of each withheld frame.
        backend: rasterizer backend.
    Returns:
        as :func:`score_live_map` (None figures and no frames for an empty map).
    Raises:
        ValueError: an unknown protocol or ``track_stride`` < 1.
    """
    if len(gmap) == 0:
        _check_protocols(protocols, track_stride)
        return {p: _empty_result(p) for p in protocols}
    return score_live_map(frozen_mapper(gmap, backend), frames, roi_fn, protocols, track_iters=track_iters,
                          track_stride=track_stride, keyframe_poses=keyframe_poses or {}, novel_ids=novel_ids,
                          views=views, record=record, novel_views=novel_views, predicted=predicted, fit_exposure=True)
