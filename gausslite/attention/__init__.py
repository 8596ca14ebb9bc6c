"""Task-conditioned attention front-end (paper Sec. III-B): task graph + posed RGB-D frames ->
per-pixel boolean relevance maps for the mapper.

Main entry points: :class:`AttentionFrontEnd` / :class:`AttentionConfig`; backends
:class:`AnnotationDetector` + :class:`AnnotationSegmenter` (offline default, from ``objects.json``),
:class:`OnnxGroundingDetector`, :class:`OnnxFastSAMSegmenter`, :class:`GrabCutSegmenter`; phrase
matching :class:`PhraseMatcher`; :class:`KeyframeTrigger`.
"""

from gausslite.attention.annotation_backend import (
    AnnotationBackend,
    AnnotationDetector,
    AnnotationSegmenter,
    project_box_2d,
)
from gausslite.attention.frontend import AttentionConfig, AttentionFrontEnd, max_box_fraction_for
from gausslite.attention.grabcut import GrabCutSegmenter
from gausslite.attention.interfaces import (
    Detections,
    Detector,
    FrameContext,
    Segmenter,
    box_iou,
    filter_boxes_by_area,
    mask_box_iou,
    mask_iou,
    match_masks_to_boxes,
    nms,
)
from gausslite.attention.keyframes import KeyframeConfig, KeyframeTrigger
from gausslite.attention.onnx_backends import OnnxFastSAMSegmenter, OnnxGroundingDetector
from gausslite.attention.phrases import PhraseMatcher, PhraseMatcherConfig, normalize_phrase, singularize
from gausslite.attention.spatial import SpatialConfig, lift_mask, relation_holds, reproject_box
from gausslite.attention.tokenizer import WordPieceTokenizer

__all__ = [
    "AttentionConfig", "AttentionFrontEnd", "max_box_fraction_for",
    "AnnotationBackend", "AnnotationDetector", "AnnotationSegmenter", "project_box_2d",
    "GrabCutSegmenter", "OnnxGroundingDetector", "OnnxFastSAMSegmenter",
    "Detections", "Detector", "Segmenter", "FrameContext",
    "box_iou", "mask_iou", "mask_box_iou", "nms", "filter_boxes_by_area", "match_masks_to_boxes",
    "KeyframeConfig", "KeyframeTrigger",
    "PhraseMatcher", "PhraseMatcherConfig", "normalize_phrase", "singularize",
    "SpatialConfig", "lift_mask", "relation_holds", "reproject_box",
    "WordPieceTokenizer",
]
