"""Thin orchestrator: Dataset → Mapper → Evaluator (Gaussian-SLAM's separation of concerns).

``run_mapping`` maps a sequence with a config and optional task, evaluates on the mapped (training)
views and, when frames were skipped, on held-out views, and writes ``map.ply``, ``metrics.json`` and
render/ground-truth PNGs.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
from tqdm import tqdm

from gausslite.datasets.base import Frame, RGBDDataset
from gausslite.evaluation import evaluate
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.mapper import Mapper

log = logging.getLogger(__name__)

RelevanceFn = Callable[[Frame], np.ndarray]


def gt_roi_fn(dataset: RGBDDataset, task_id: str) -> RelevanceFn:
    """Ground-truth relevance: pixels whose depth point lies in one of the task's boxes (paper Sec. IV).

    Raises:
        ValueError: the dataset has no annotations. KeyError: unknown task id (lists the known ones).
    """
    ann = dataset.annotations
    if ann is None:
        raise ValueError(f"{dataset.path}: no objects.json/tasks.json found; a task id needs annotations")
    ann.task_by_id(task_id)  # raises KeyError with the available ids

    def fn(frame: Frame) -> np.ndarray:
        return ann.roi_mask(task_id, frame.depth, frame.c2w, frame.intrinsics)

    return fn


def run_mapping(
    dataset: RGBDDataset,
    cfg: MapperConfig,
    *,
    task_id: Optional[str] = None,
    relevance_fn: Optional[RelevanceFn] = None,
    stride: int = 1,
    out_dir: Optional[Path] = None,
    n_images: int = 3,
    progress: bool = True,
    desc: str = "mapping",
    eval_task_ids: Optional[list[str]] = None,
) -> tuple[Mapper, dict]:
    """Map ``dataset`` (every ``stride``-th frame) and evaluate.

    Args:
        dataset: posed RGB-D sequence; with a ``pose_ok`` array (odometry), the frames whose tracking failed are
            neither mapped nor scored (``metrics["n_frames_lost"]``).
        cfg: mapper config. In ``gausslite`` mode a relevance source is required.
        task_id: task in the dataset's ``tasks.json``: gives the ground-truth ROI for the ROI
            metrics, and the relevance map when ``relevance_fn`` is None.
        relevance_fn: frame → (H, W) bool relevance map w (e.g. from the attention front-end).
        stride: map every ``stride``-th frame; the others are held-out views.
        out_dir: where ``map.ply``, ``metrics.json`` and PNGs go (None: write nothing).
        eval_task_ids: also score the mapped views on each of these tasks' ground-truth ROIs:
            ``metrics["per_task"][task]`` holds psnr, ssim, depth_l1, roi_psnr, roi_ssim, roi_fraction
            (for a map that does not depend on the task, such as uniform mapping).
    Returns:
        (mapper, metrics dict).
    Raises:
        ValueError: ``gausslite`` mode without task or relevance source; empty dataset.
        KeyError: an unknown task id in ``eval_task_ids``.
    """
    if len(dataset) == 0:
        raise ValueError(f"{dataset.path}: no frames")
    roi_fn = gt_roi_fn(dataset, task_id) if task_id is not None else None
    if relevance_fn is None:
        relevance_fn = roi_fn
    if cfg.mode == "gausslite" and relevance_fn is None:
        raise ValueError("mode 'gausslite' needs a task (--task-id) or a relevance source")

    torch.manual_seed(cfg.seed)
    mapper = Mapper(cfg)
    # frames whose odometry failed (pose_ok False) carry the last good pose, not theirs: neither mapped nor scored
    lost = set(np.flatnonzero(~np.asarray(dataset.pose_ok)).tolist()) if hasattr(dataset, "pose_ok") else set()
    if lost:
        log.warning("%s: %d frames lost by the odometry are neither mapped nor scored", dataset.path, len(lost))
    train_idx = [i for i in range(0, len(dataset), stride) if i not in lost]
    test_idx = [i for i in range(len(dataset)) if i % stride != 0 and i not in lost]
    if not train_idx:
        raise ValueError(f"{dataset.path}: every frame to map was lost by the odometry")
    t0 = time.perf_counter()
    bar = tqdm(train_idx, desc=desc, disable=not progress, unit="frame")
    for i in bar:
        fr = dataset[i]
        w = relevance_fn(fr) if relevance_fn is not None else None
        st = mapper.map_frame(fr, w)
        bar.set_postfix(gaussians=st.n_gaussians, loss=f"{st.loss:.3f}", s=f"{st.seconds:.2f}")
    mapper.finalize()
    map_seconds = time.perf_counter() - t0

    img_dir = out_dir / "renders" if out_dir is not None else None
    pick = [train_idx[j] for j in np.linspace(0, len(train_idx) - 1, min(n_images, len(train_idx))).round().astype(int)]
    pick_ids = [dataset[i].frame_id for i in pick] if img_dir is not None else []
    task_rois = {t: gt_roi_fn(dataset, t) for t in (eval_task_ids or [])}
    # every view at the mapper's refined pose under pose_refine (held-out views: the nearest keyframe's correction)
    train = evaluate(mapper.render_frame, (dataset[i] for i in train_idx), roi_fn, img_dir, pick_ids,
                     tag="train_", extra_rois=task_rois)
    metrics: dict = {
        "mode": cfg.mode,
        "task_id": task_id,
        **train.as_dict(),
        "n_gaussians": len(mapper.model),
        "n_active": int(mapper.model.active.sum()),
        "seconds_per_frame": float(np.mean([s.seconds for s in mapper.stats])),
        "map_seconds": map_seconds,
        "n_frames": len(train_idx),
        "n_frames_lost": len(lost),
        "stride": stride,
    }
    if test_idx:
        test_pick = [dataset[test_idx[len(test_idx) // 2]].frame_id] if img_dir is not None else []
        test = evaluate(mapper.render_frame, (dataset[i] for i in test_idx), roi_fn, img_dir, test_pick, tag="heldout_")
        metrics.update(test.as_dict(prefix="heldout_"))
    if eval_task_ids:
        # one map scored on several tasks' ROIs (a map that does not depend on the task: uniform)
        metrics["per_task"] = {t: {k: (None if isinstance(v, float) and math.isnan(v) else v)
                                   for k, v in sm.as_dict().items()} for t, sm in train.per_roi.items()}
    metrics["per_frame"] = [asdict(s) for s in train.scores]
    metrics = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in metrics.items()}
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        mapper.gmap.save_ply(out_dir / "map.ply")
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
        (out_dir / "config.json").write_text(cfg.model_dump_json(indent=2))
    return mapper, metrics
