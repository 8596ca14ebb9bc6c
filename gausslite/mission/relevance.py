"""The relevance source of a mission: the map w(u, v) of task-relevant pixels of a keyframe (paper Sec. III-B).

``agent.relevance: gt`` reads it from the scene's annotations (the paper's ground-truth protocol, Sec. IV);
``attention`` runs the task-conditioned attention front-end (:class:`gausslite.attention.AttentionFrontEnd`) with
the configured detector and segmenter: the offline annotation backend, the ONNX exports (``relevance_backend:
onnx``, ``docs/perception.md``), or the ONNX models run for their cost while the annotations answer
(``onnx_cost``, for timing studies).
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from gausslite.attention import (
    AnnotationBackend,
    AnnotationDetector,
    AnnotationSegmenter,
    AttentionConfig,
    AttentionFrontEnd,
    OnnxFastSAMSegmenter,
    OnnxGroundingDetector,
)
from gausslite.attention.timing import CostOnlyDetector, CostOnlySegmenter
from gausslite.datasets.annotations import task_roi
from gausslite.datasets.base import Frame
from gausslite.errors import RelevanceUnavailable
from gausslite.mission.config import AgentConfig

RelevanceFn = Callable[[Frame], np.ndarray]


def build_relevance(config: AgentConfig, graph, annotations=None, task_id: Optional[str] = None,
                    mapper_of: Optional[Callable] = None) -> tuple[RelevanceFn, object]:
    """The mission's relevance function ``frame -> (H, W) bool`` and its attention front-end (None for ``gt``).

    Args:
        config: the mission's ``AgentConfig`` (``relevance``, ``relevance_backend``, ``onnx``,
            ``attention_rendered_depth``, ``relevance_max_wait_s``).
        graph: the parsed task graph (``targets``, ``anchors``, ``relations``).
        annotations: the scene's ``SceneAnnotations`` (``objects.json`` / ``tasks.json``), or None.
        task_id: the task's id in ``tasks.json`` (``gt``).
        mapper_of: returns the mission's mapper at call time; with ``attention_rendered_depth`` (and relevance in
            the mapping thread) the front-end filters in 3D with the map's rendered depth instead of the sensor's.
    Raises:
        RelevanceUnavailable (a ValueError): ``gt`` without annotations or task id; ``attention`` with the
            annotation backends and no annotations; ``onnx`` with model paths missing or models that do not load.
    """
    if config.relevance == "gt":
        if annotations is None or task_id is None:
            raise RelevanceUnavailable("relevance 'gt' needs scene annotations and a task id from tasks.json")
        return task_roi(annotations, task_id), None

    if config.relevance_backend == "onnx":
        fe = onnx_frontend(config, graph, annotations)
    elif annotations is None:
        raise RelevanceUnavailable(f"relevance 'attention' with backend '{config.relevance_backend}' needs scene "
                                   "annotations (objects.json) for the offline annotation detector/segmenter; give a "
                                   "dataset or annotations path, or set agent.relevance_backend=onnx with "
                                   "agent.onnx.detector_path/vocab_path/segmenter_path")
    elif config.relevance_backend == "onnx_cost":
        fe = onnx_frontend(config, graph, annotations, answer_from=annotations)
    else:
        fe = AttentionFrontEnd.from_annotations(graph, annotations)
    # in the relevance thread (relevance_max_wait_s) the map is being optimised meanwhile: sensor depth
    rendered = config.attention_rendered_depth and config.relevance_max_wait_s is None and mapper_of is not None

    def fn(fr: Frame) -> np.ndarray:
        rd = None
        mapper = mapper_of() if rendered else None
        if mapper is not None and len(mapper.model) > 0:
            out = mapper.render(fr.c2w, fr.intrinsics.K, fr.intrinsics.width, fr.intrinsics.height)
            d = out.depth.detach().cpu().numpy().astype(np.float32)
            rd = np.where(out.alpha.detach().cpu().numpy() > 0.5, d, 0.0).astype(np.float32)
        rel, _ = fe.process(fr, rd)
        return rel

    return fn, fe


def onnx_frontend(config: AgentConfig, graph, annotations=None, answer_from=None):
    """Attention front-end over the configured ONNX detector and segmenter (paper Sec. III-B). With ``answer_from``
    (scene annotations) the models run for their cost only and the annotation backend answers
    (``relevance_backend: onnx_cost``).

    Raises:
        RelevanceUnavailable (a ValueError): model paths missing, or models that do not load (the message names
            the backend and the cause).
    """
    o = config.onnx
    name = config.relevance_backend
    missing = o.missing()
    if missing:
        raise RelevanceUnavailable(f"relevance 'attention' with backend '{name}': " + "; ".join(missing))
    try:
        det = OnnxGroundingDetector(o.detector_path, o.vocab_path, box_threshold=o.box_threshold,
                                    text_threshold=o.text_threshold, threads=o.threads)
        seg = OnnxFastSAMSegmenter(o.segmenter_path, conf=o.seg_conf, iou=o.seg_iou, threads=o.threads)
    except Exception as e:  # onnxruntime load errors, export-contract violations
        raise RelevanceUnavailable(f"relevance 'attention' with backend '{name}': cannot load the models: "
                                   f"{type(e).__name__}: {e}") from None
    if answer_from is not None:
        backend = AnnotationBackend(answer_from)
        det = CostOnlyDetector(det, AnnotationDetector(backend))
        seg = CostOnlySegmenter(seg, AnnotationSegmenter(backend))
    up = getattr(annotations, "up_axis", (0.0, 0.0, 1.0)) if annotations is not None else (0.0, 0.0, 1.0)
    return AttentionFrontEnd(graph, AttentionConfig(detector=det, segmenter=seg), up_axis=up)


__all__ = ["RelevanceFn", "build_relevance", "onnx_frontend"]
