"""``gausslite attention``: ground a scene's tasks with the attention front-end and score the relevance
maps against the ground-truth ROI masks (paper Sec. III-B).

Each task text is parsed by the task parser (rules backend by default; the graph stored in tasks.json is
NOT used) and grounded with the offline annotation backend (objects.json). Output: ``DIR/attention.json``
with per-task ``mean_iou`` and per-frame IoU against ``annotations.roi_mask``, and overlay PNGs
``DIR/<task_id>/frame_XXXXXX.png`` (predicted mask tinted red, ground-truth outline in green).
IoU rule: a frame where both the prediction and the ground truth are empty counts as IoU 1.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def register(subparsers) -> None:
    """Add the ``attention`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("attention", help="task-conditioned relevance maps on a dataset, scored vs GT ROIs",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", required=True, help="dataset folder with objects.json/tasks.json")
    p.add_argument("--task-id", required=True, help="task id from tasks.json, or 'all'")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--downscale", type=float, default=1, help="image downscale factor (default 1)")
    p.add_argument("--max-frames", type=int, default=None, help="use at most N frames")
    p.add_argument("--stride", type=int, default=1, help="use every N-th frame (default 1)")
    p.add_argument("--overlays", type=int, default=3, help="overlay PNGs per task (default 3)")
    p.set_defaults(func=_handle)


def frame_iou(pred, gt) -> float:
    """IoU of two (H, W) bool masks; 1.0 when both are empty."""
    u = int((pred | gt).sum())
    return 1.0 if u == 0 else float((pred & gt).sum()) / u


def _overlay(rgb, pred, gt):
    # lazy: the command line starts without loading the library
    import cv2
    import numpy as np

    img = rgb.astype(np.float32).copy()
    img[pred] = 0.5 * img[pred] + 0.5 * np.array([255.0, 0.0, 0.0])
    out = np.ascontiguousarray(img.clip(0, 255).astype(np.uint8)[..., ::-1])
    contours, _ = cv2.findContours(gt.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, (0, 255, 0), 1)
    return out


def _handle(args: argparse.Namespace) -> int:
    # lazy: the command line starts without loading the library
    import cv2
    import numpy as np
    from tqdm import tqdm

    from gausslite.attention import AttentionFrontEnd
    from gausslite.datasets import load_dataset
    from gausslite.parser import TaskParser

    try:
        ds = load_dataset(args.dataset, downscale=args.downscale, max_frames=args.max_frames, stride=args.stride)
    except (FileNotFoundError, ValueError) as e:
        print(f"gausslite attention: error: {e}", file=sys.stderr)
        return 2
    ann = ds.annotations
    if ann is None or not ann.tasks:
        print(f"gausslite attention: error: {args.dataset} has no objects.json/tasks.json", file=sys.stderr)
        return 2
    try:
        tasks = ann.tasks if args.task_id == "all" else [ann.task_by_id(args.task_id)]
    except KeyError as e:
        print(f"gausslite attention: error: {e.args[0]}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    n = len(ds)
    shots = set(np.linspace(0, n - 1, min(max(args.overlays, 0), n)).round().astype(int).tolist()) if n else set()
    parser = TaskParser()
    report = {"dataset": str(args.dataset), "downscale": args.downscale, "frames": n,
              "iou_rule": "per-frame IoU of predicted relevance vs GT ROI mask; empty GT and empty prediction = 1.0",
              "tasks": {}}
    with tqdm(total=n * len(tasks), desc="attention", unit="frame") as bar:
        for task in tasks:
            graph = parser.parse(task.text)
            fe = AttentionFrontEnd.from_annotations(graph, ann)
            per_frame = []
            (out / task.id).mkdir(exist_ok=True)
            for i in range(n):
                f = ds[i]
                rel, _dbg = fe.process(f)
                gt = ann.roi_mask(task.id, f.depth, f.c2w, f.intrinsics)
                per_frame.append({"frame_id": int(f.frame_id), "iou": round(frame_iou(rel, gt), 5),
                                  "pred_fraction": round(float(rel.mean()), 5), "gt_fraction": round(float(gt.mean()), 5)})
                if i in shots:
                    cv2.imwrite(str(out / task.id / f"frame_{f.frame_id:06d}.png"), _overlay(f.rgb, rel, gt))
                bar.update(1)
            report["tasks"][task.id] = {
                "text": task.text, "graph": graph.graph_dict() if hasattr(graph, "graph_dict") else None,
                "mean_iou": round(float(np.mean([p["iou"] for p in per_frame])) if per_frame else 1.0, 5),
                "detector_calls": fe.detector_calls, "frames": per_frame}
    (out / "attention.json").write_text(json.dumps(report, indent=2))
    for tid, r in report["tasks"].items():
        print(f"{tid:28s} mean IoU {r['mean_iou']:.4f}")
    print(f"wrote {out / 'attention.json'}")
    return 0
