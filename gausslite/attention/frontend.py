"""Task-conditioned attention front-end: task graph + RGB-D frame -> per-pixel relevance map
(paper Sec. III-B "Task-Conditioned Attention Front-End").

Per frame (:meth:`AttentionFrontEnd.process`):

1. Keyframe trigger (:class:`KeyframeTrigger`): on a detection keyframe the detector runs with the
   query set (targets ∪ anchors); between keyframes the previous boxes are re-projected through their 3D
   frustum corners (:func:`reproject_box`) and the detector is not called.
2. Boxes larger than the box-area limit are dropped (:func:`max_box_fraction_for`).
3. The segmenter turns the surviving boxes into masks; masks are matched to boxes one-to-one by IoU.
4. Each mask is lifted to a world centroid with the map-rendered depth (sensor depth where the rendered
   depth is 0/absent); target detections with relations are kept only if a relation holds against an
   anchor detection of this frame or, when the anchor is not seen in this frame, against the anchor's
   last observation (kept in world coordinates). Targets without relations and anchors are kept.
5. The union of kept masks is the relevance map w(u, v), (H, W) bool.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np

from gausslite.attention.annotation_backend import AnnotationBackend, AnnotationDetector, AnnotationSegmenter
from gausslite.attention.interfaces import (
    Detections,
    Detector,
    FrameContext,
    Segmenter,
    filter_boxes_by_area,
    match_masks_to_boxes,
)
from gausslite.attention.keyframes import KeyframeConfig, KeyframeTrigger
from gausslite.attention.phrases import normalize_phrase
from gausslite.attention.spatial import LiftedMask, SpatialConfig, lift_mask, merge_depth, relation_holds, reproject_box

__all__ = ["AttentionConfig", "AttentionFrontEnd", "graph_parts", "max_box_fraction_for", "LARGE_OBJECT_WORDS",
           "BOX_FRACTION_SMALL", "BOX_FRACTION_LARGE", "BOX_FRACTION_MULTI"]

BOX_FRACTION_SMALL = 0.20
BOX_FRACTION_LARGE = 0.40
BOX_FRACTION_MULTI = 0.70

#: head nouns treated as furniture / large objects for the box-area limit (paper: 0.40 for furniture)
LARGE_OBJECT_WORDS = frozenset({
    "table", "desk", "sofa", "couch", "settee", "bed", "chair", "armchair", "bench", "stool", "ottoman", "pouf",
    "cabinet", "sideboard", "dresser", "cupboard", "wardrobe", "shelf", "bookshelf", "bookcase", "counter",
    "door", "doorway", "window", "wall", "floor", "rug", "carpet", "curtain", "fridge", "refrigerator", "oven",
    "monitor", "screen", "display", "tv", "television", "whiteboard", "obstacle", "furniture", "car", "vehicle",
    "person", "robot", "machine", "printer", "sink", "bathtub", "toilet", "stair", "staircase", "column", "pillar",
})


def max_box_fraction_for(phrase: str, n_targets: int) -> float:
    """Box-area limit (fraction of the image) for detections of a target ``phrase`` (paper Sec. III-B).

    0.70 for multi-object tasks (two or more target phrases), else 0.40 when the phrase's head noun is
    a furniture / large-object word (:data:`LARGE_OBJECT_WORDS`), else 0.20 (small objects).
    """
    if n_targets >= 2:
        return BOX_FRACTION_MULTI
    words = normalize_phrase(phrase).split()
    return BOX_FRACTION_LARGE if words and words[-1] in LARGE_OBJECT_WORDS else BOX_FRACTION_SMALL


@dataclass
class AttentionConfig:
    """Configuration of :class:`AttentionFrontEnd`.

    Attributes:
        detector: open-vocabulary detector backend (required by the front-end).
        segmenter: promptable segmenter backend (required by the front-end).
        keyframe: detection keyframe trigger thresholds (paper: 1.0 m / 15°; every ``every_k`` frames).
        max_box_fraction: box-area limit for target detections, fraction of the image in (0, 1]; None:
            per phrase by :func:`max_box_fraction_for` (0.20 small / 0.40 furniture / 0.70 multi-object).
        anchor_max_box_fraction: limit for anchor detections. Default 1.0 (no limit): anchors are often
            supporting surfaces (a desk, a table) that fill most of the view when the robot is close
            (the TUM desk covers up to the whole image).
        mask_match_min_iou: a segmenter mask is assigned to a box only above this mask-vs-box IoU.
        spatial: thresholds of the 3D spatial filter.
        remember_anchors: use an anchor's last observation (world frame) when it is not seen in the frame.
    """

    detector: Optional[Detector] = None
    segmenter: Optional[Segmenter] = None
    keyframe: KeyframeConfig = field(default_factory=KeyframeConfig)
    max_box_fraction: Optional[float] = None
    anchor_max_box_fraction: float = 1.0
    mask_match_min_iou: float = 0.0
    spatial: SpatialConfig = field(default_factory=SpatialConfig)
    remember_anchors: bool = True


@dataclass
class _Track:
    box: np.ndarray
    phrase_id: int
    score: float
    extra: Any
    depth_lo: float
    depth_hi: float
    c2w: np.ndarray
    intr: Any


class AttentionFrontEnd:
    """Stateful per-sequence front-end.

    Args:
        graph: a ``TaskGraph`` (``gausslite.parser``) or a mapping with ``targets``, ``anchors``,
            ``relations`` (relations as objects with ``predicate/target/anchor`` or dicts).
        config: :class:`AttentionConfig` holding the backends.
        up_axis: (3,) world up direction (``annotations.up_axis``), default +z.

    Raises:
        ValueError: missing backends, an empty query set, or a relation naming an unknown phrase.
    """

    def __init__(self, graph, config: AttentionConfig, up_axis: Sequence[float] = (0.0, 0.0, 1.0)) -> None:
        if config.detector is None or config.segmenter is None:
            raise ValueError("AttentionConfig needs both a detector and a segmenter")
        if config.max_box_fraction is not None and not 0 < config.max_box_fraction <= 1:
            raise ValueError(f"max_box_fraction must be in (0, 1], got {config.max_box_fraction}")
        self.config = config
        targets, anchors, relations = graph_parts(graph)
        self.targets = list(dict.fromkeys(targets))
        self.anchors = [a for a in dict.fromkeys(anchors)]
        self.phrases: List[str] = list(dict.fromkeys(self.targets + self.anchors))
        if not self.phrases:
            raise ValueError("the task graph has no targets or anchors: nothing to attend to")
        for pred, t, a in relations:
            if t not in self.phrases or a not in self.phrases:
                raise ValueError(f"relation {pred}({t!r}, {a!r}) names a phrase outside the query set {self.phrases}")
        self.relations = relations
        up = np.asarray(up_axis, dtype=np.float64)
        self.up_axis = up / np.linalg.norm(up)
        n_t = len(self.targets)
        self.box_limits = np.array([
            (config.max_box_fraction if config.max_box_fraction is not None else max_box_fraction_for(p, n_t))
            if p in self.targets else config.anchor_max_box_fraction
            for p in self.phrases
        ], dtype=np.float64)
        self.trigger = KeyframeTrigger(config.keyframe)
        self.detector_calls = 0
        self.reset()

    def reset(self) -> None:
        """Forget tracks, anchor memory and the keyframe state (start of a new sequence)."""
        self.trigger.reset()
        self._tracks: List[_Track] = []
        self._anchor_memory: Dict[str, List[LiftedMask]] = {}

    # ------------------------------------------------------------------------------------------
    def process(self, frame, rendered_depth: Optional[np.ndarray] = None) -> Tuple[np.ndarray, Dict[str, Any]]:
        """Relevance map of one frame.

        Args:
            frame: a ``gausslite.datasets.Frame`` (rgb (H,W,3) uint8, depth (H,W) float32 m, c2w (4,4),
                intrinsics, frame_id).
            rendered_depth: optional (H, W) depth rendered from the current map, metres, 0 = no coverage.

        Returns:
            (relevance (H, W) bool, debug dict with ``keyframe`` (bool), ``detector_calls`` (int, total),
            ``phrases``, ``detections`` (list of per-detection dicts: phrase, role, box, score, extra,
            mask_pixels, centroid, kept, reason)).

        Raises:
            ValueError: image/depth shapes that disagree with the intrinsics or ``rendered_depth``.
        """
        rgb = np.asarray(frame.rgb)
        intr = frame.intrinsics
        H, W = intr.height, intr.width
        if rgb.shape[:2] != (H, W) or np.asarray(frame.depth).shape != (H, W):
            raise ValueError(f"frame image {rgb.shape[:2]} / depth {np.asarray(frame.depth).shape} do not match "
                             f"intrinsics {W}x{H}")
        depth = merge_depth(frame.depth, rendered_depth)
        ctx = FrameContext(depth=np.asarray(frame.depth), c2w=np.asarray(frame.c2w, dtype=np.float64),
                           intrinsics=intr, frame_id=int(getattr(frame, "frame_id", -1)))
        is_kf = self.trigger.update(frame.c2w)
        dets, extras = self._detect_or_track(rgb, ctx, is_kf)
        debug: Dict[str, Any] = {"keyframe": bool(is_kf), "frame_id": ctx.frame_id, "phrases": list(self.phrases),
                                 "detections": []}
        relevance = np.zeros((H, W), dtype=bool)
        if len(dets) == 0:
            if is_kf:
                self._tracks = []
            debug["detector_calls"] = self.detector_calls
            return relevance, debug

        keep_area = filter_boxes_by_area(dets.boxes, (H, W), self.box_limits[dets.phrase_ids])
        idx = np.flatnonzero(keep_area)
        for i in np.flatnonzero(~keep_area):
            debug["detections"].append(self._dbg(dets, extras, i, None, None, False, "box too large"))
        masks = np.zeros((0, H, W), dtype=bool)
        if len(idx):
            cand = np.asarray(self.config.segmenter.segment(rgb, dets.boxes[idx], ctx), dtype=bool).reshape(-1, H, W)
            assign = match_masks_to_boxes(cand, dets.boxes[idx], self.config.mask_match_min_iou)
            masks = np.stack([cand[a] if a >= 0 else np.zeros((H, W), dtype=bool) for a in assign])
        lifted = self._lift_and_track(dets, extras, idx, masks, depth, ctx)
        keep, reasons = self._judge(dets, idx, masks, lifted, self._anchor_pool(dets, idx, lifted))
        for k, i in enumerate(idx):
            if keep[k]:
                relevance |= masks[k]
            debug["detections"].append(self._dbg(dets, extras, i, masks[k], lifted[k], bool(keep[k]), reasons[k]))
        debug["detector_calls"] = self.detector_calls
        return relevance, debug

    def _detect_or_track(self, rgb: np.ndarray, ctx: FrameContext, is_kf: bool) -> Tuple[Detections, list]:
        """This frame's detections and their per-detection extras: the detector's on a keyframe, else the tracks'
        boxes reprojected into this view (tracks that leave the view are dropped for this frame)."""
        if is_kf:
            self.detector_calls += 1
            dets = self.config.detector.detect(rgb, self.phrases, ctx)
            return dets, (dets.extra if dets.extra else [None] * len(dets))
        boxes, scores, pids, extras = [], [], [], []
        for tr in self._tracks:
            b = reproject_box(tr.box, tr.depth_lo, tr.depth_hi, tr.c2w, tr.intr, ctx.c2w, ctx.intrinsics)
            if b is not None:
                boxes.append(b)
                scores.append(tr.score)
                pids.append(tr.phrase_id)
                extras.append(tr.extra)
        if not boxes:
            return Detections.empty(), []
        return Detections(np.reshape(boxes, (-1, 4)), scores, pids, extras), extras

    def _lift_and_track(self, dets: Detections, extras: list, idx: np.ndarray, masks: np.ndarray, depth: np.ndarray,
                        ctx: FrameContext) -> List[Optional[LiftedMask]]:
        """Lift each kept detection's mask (``masks[k]`` of ``dets[idx[k]]``) into the world frame with ``depth``
        (metres) and make the detections with a lifted mask the new tracks (a detection whose mask is empty, an
        object that left the view, ends its track). Returns the lifted masks (None: no valid depth)."""
        intr = ctx.intrinsics
        lifted: List[Optional[LiftedMask]] = []
        new_tracks: List[_Track] = []
        for k, i in enumerate(idx):
            lm = lift_mask(masks[k], depth, ctx.c2w, intr, self.config.spatial.max_footprint_points)
            lifted.append(lm)
            if lm is not None:
                new_tracks.append(_Track(dets.boxes[i].copy(), int(dets.phrase_ids[i]), float(dets.scores[i]),
                                         extras[i], lm.depth_lo, lm.depth_hi, ctx.c2w.copy(), intr))
        self._tracks = new_tracks
        return lifted

    def _anchor_pool(self, dets: Detections, idx: np.ndarray,
                     lifted: List[Optional[LiftedMask]]) -> Dict[str, List[LiftedMask]]:
        """Anchor phrase → its lifted masks (world frame) this frame, merged into the anchor memory when
        ``config.remember_anchors`` (then the memory is the pool)."""
        anchors_now: Dict[str, List[LiftedMask]] = {}
        for k, i in enumerate(idx):
            p = self.phrases[int(dets.phrase_ids[i])]
            if p in self.anchors and lifted[k] is not None:
                anchors_now.setdefault(p, []).append(lifted[k])
        if self.config.remember_anchors:
            self._anchor_memory.update(anchors_now)
            return dict(self._anchor_memory)
        return anchors_now

    def _judge(self, dets: Detections, idx: np.ndarray, masks: np.ndarray, lifted: List[Optional[LiftedMask]],
               anchor_pool: Dict[str, List[LiftedMask]]) -> Tuple[np.ndarray, List[str]]:
        """Which kept detections are relevant: anchors and targets without relations are; a target with relations
        is when one of them holds against an anchor in ``anchor_pool`` (then, with ``spatial.nearest_only``, only
        the nearest for each ``near`` relation). Returns ``(keep (K,) bool, reasons)``."""
        keep = np.zeros(len(idx), dtype=bool)
        reasons: List[str] = [""] * len(idx)
        dists: Dict[Tuple[int, str, str], float] = {}
        sp = self.config.spatial
        for k, i in enumerate(idx):
            p = self.phrases[int(dets.phrase_ids[i])]
            if not masks[k].any():
                reasons[k] = "empty mask"
                continue
            if p in self.anchors:
                keep[k], reasons[k] = True, "anchor"
                continue
            rels = [r for r in self.relations if r[1] == p]
            if not rels:
                keep[k], reasons[k] = True, "target without relations"
                continue
            if lifted[k] is None:
                reasons[k] = "no valid depth to test relations"
                continue
            why = []
            for pred, _t, a in rels:
                cands = anchor_pool.get(a, [])
                if not cands:
                    why.append(f"{pred}({a}): anchor not observed")
                    continue
                res = [relation_holds(pred, lifted[k], c, self.up_axis, sp) for c in cands]
                best = min(d for _, d in res)
                dists[(k, pred, a)] = best
                if any(h for h, _ in res):
                    keep[k] = True
                    why.append(f"{pred}({a}) holds, d={best:.2f} m")
                else:
                    why.append(f"{pred}({a}) fails, d={best:.2f} m")
            reasons[k] = "; ".join(why)
        if sp.nearest_only:
            self._keep_nearest(dets, idx, keep, reasons, dists)
        return keep, reasons

    def _keep_nearest(self, dets: Detections, idx: np.ndarray, keep: np.ndarray, reasons: List[str],
                      dists: Dict[Tuple[int, str, str], float]) -> None:
        """For each ``near`` relation, unkeep (in place) the kept targets farther from the anchor than the
        nearest one plus ``spatial.nearest_tie_m`` (``dists``: (k, predicate, anchor) → metres)."""
        for pred, t, a in self.relations:
            if pred != "near":
                continue
            ks = [k for k in range(len(idx)) if keep[k] and (k, pred, a) in dists
                  and self.phrases[int(dets.phrase_ids[idx[k]])] == t]
            if ks:
                dmin = min(dists[(k, pred, a)] for k in ks)
                for k in ks:
                    if dists[(k, pred, a)] > dmin + self.config.spatial.nearest_tie_m:
                        keep[k] = False
                        reasons[k] += "; not the nearest to " + a

    def _dbg(self, dets: Detections, extras, i, mask, lm, kept: bool, reason: str) -> Dict[str, Any]:
        p = self.phrases[int(dets.phrase_ids[i])]
        return {
            "phrase": p,
            "role": "anchor" if p in self.anchors else "target",
            "box": [round(float(v), 2) for v in dets.boxes[i]],
            "score": round(float(dets.scores[i]), 4),
            "extra": extras[i] if i < len(extras) else None,
            "mask_pixels": int(mask.sum()) if mask is not None else 0,
            "centroid": None if lm is None else [round(float(v), 4) for v in lm.centroid],
            "kept": kept,
            "reason": reason,
        }

    # ------------------------------------------------------------------------------------------
    @classmethod
    def from_annotations(cls, graph, annotations, config: Optional[AttentionConfig] = None,
                         matcher=None) -> "AttentionFrontEnd":
        """Front-end grounded with the offline annotation backend of a scene (``dataset.annotations``).

        ``config`` supplies thresholds; its detector/segmenter are replaced by the annotation backend.
        The up axis is ``annotations.up_axis``.
        """
        cfg = config or AttentionConfig()
        backend = AnnotationBackend(annotations, matcher=matcher)
        cfg = AttentionConfig(**{**cfg.__dict__, "detector": AnnotationDetector(backend),
                                 "segmenter": AnnotationSegmenter(backend)})
        return cls(graph, cfg, up_axis=annotations.up_axis)


def graph_parts(graph) -> Tuple[List[str], List[str], List[Tuple[str, str, str]]]:
    """``(targets, anchors, relations)`` of a task graph: a ``TaskGraph``-like object or a dict with those keys;
    each relation as ``(predicate, target, anchor)`` strings."""

    def get(name):
        return graph.get(name, []) if isinstance(graph, dict) else getattr(graph, name, [])

    rels = []
    for r in get("relations") or []:
        if isinstance(r, dict):
            rels.append((str(r["predicate"]), str(r["target"]), str(r["anchor"])))
        else:
            rels.append((str(r.predicate), str(r.target), str(r.anchor)))
    for pred, _, _ in rels:
        if pred not in ("near", "on"):
            raise ValueError(f"unsupported predicate {pred!r} (supported: 'near', 'on')")
    return [str(t) for t in get("targets") or []], [str(a) for a in get("anchors") or []], rels
