"""How much of the image each task's ground-truth region takes: the room there is for task-conditioned mapping to gain.

    python -m bench.roi_share [--datasets DATA/TUM_rgbd_dataset_freiburg1_rpy,DATA/Replica_room0/room0]
                              [--annotations shipped] [--downscale 4] [--stride 1] [--out bench/results/roi_share.json]

For every task of each dataset's ``tasks.json``, the ROI mask of every ``--stride``-th frame
(:func:`gausslite.datasets.task_roi`: the depth pixels inside the task's boxes of ``objects.json``, enlarged by the
mask margin) over the frame's pixels with valid depth and without: the mean, median and 90th percentile share of the
image, and the share of frames that see the region at all. The default sequences are scored with the annotations
GaussLite ships for them (docs/annotations.md), as the headline is. A task whose region takes most of the image leaves little
to concentrate on; a small one (a mouse, a cup) is where GaussLite's ROI effort has room (paper Sec. III-B,
docs/realtime.md "Live under every protocol").

Writes ``bench/results/roi_share.json`` and ``.md`` (through ``bench/_results.py``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional

import numpy as np
from tqdm import tqdm

from bench._results import DATASETS, REPO, portable_path, write_results
from gausslite.datasets import task_roi
from gausslite.datasets.loader import load_dataset

#: the annotated sequences the headline reports on
DEFAULT_DATASETS = (DATASETS / "TUM_rgbd_dataset_freiburg1_rpy", DATASETS / "Replica_room0" / "room0")


def roi_share(path: Path, downscale: float = 4, stride: int = 1, annotations: str = "auto") -> dict:
    """The share of the image each task's ROI takes over the frames of the sequence at ``path``.

    Args:
        path: a sequence folder with ``objects.json`` and ``tasks.json`` (any layout ``load_dataset`` reads).
        downscale: image downscale factor (the share hardly depends on it).
        stride: every ``stride``-th frame.
        annotations: which annotations (a choice of :func:`gausslite.datasets.load_dataset`: ``auto``, ``beside``,
            ``shipped`` or a folder).
    Returns:
        ``{"frames": n, "tasks": {task id: {"text", "mean", "median", "p90", "seen"}}}``: shares in [0, 1] of the
        image's pixels (``seen``: of the frames with at least one ROI pixel).
    Raises:
        FileNotFoundError: no sequence or no annotations at ``path``.
        ValueError: ``stride`` < 1.
    """
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    try:
        ds = load_dataset(path, downscale=downscale, annotations=annotations)
    except ValueError as e:
        raise FileNotFoundError(f"{path}: not a sequence ({e})") from None
    ann = ds.annotations
    if ann is None or not ann.tasks:
        raise FileNotFoundError(f"{path}: no objects.json / tasks.json")
    idx = range(0, len(ds), stride)
    shares = {t.id: [] for t in ann.tasks}
    for i in tqdm(idx, desc=Path(path).name, unit="frame", leave=False):
        fr = ds[i]
        for t in ann.tasks:
            shares[t.id].append(float(np.mean(task_roi(ann, t.id)(fr))))
    out = {}
    for t in ann.tasks:
        s = np.asarray(shares[t.id])
        out[t.id] = {"text": t.text, "mean": float(s.mean()), "median": float(np.median(s)),
                     "p90": float(np.percentile(s, 90)), "seen": float(np.mean(s > 0))}
    return {"frames": len(idx), "tasks": out}


def table(result: dict) -> str:
    """Markdown table of :func:`main`'s result: one row per dataset and task."""
    lines = ["| sequence | task | frames | ROI share of the image: mean / median / 90th percentile | frames that see it |",
             "|---|---|---|---|---|"]
    for name, r in result["datasets"].items():
        for tid, t in r["tasks"].items():
            lines.append(f"| {name} | {tid} | {r['frames']} | {100 * t['mean']:.1f} / {100 * t['median']:.1f} / "
                         f"{100 * t['p90']:.1f} % | {100 * t['seen']:.0f} % |")
    return "\n".join(lines)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--datasets", default=",".join(map(str, DEFAULT_DATASETS)),
                    help="comma list of annotated sequence folders")
    ap.add_argument("--annotations", default=None, metavar="auto|beside|shipped|FOLDER",
                    help="the sequences' annotations (default: shipped for the default sequences, else auto; "
                         "docs/annotations.md)")
    ap.add_argument("--downscale", type=float, default=4)
    ap.add_argument("--stride", type=int, default=1, help="every this many frames")
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "roi_share.json")
    args = ap.parse_args(argv)
    if args.stride < 1:
        ap.error("--stride must be >= 1")
    paths = [Path(p) for p in args.datasets.split(",") if p]
    missing = [str(p) for p in paths if not p.is_dir()]
    if missing:
        ap.error(f"no such sequence: {', '.join(missing)} (set GAUSSLITE_SHARED)")
    default = args.datasets == ap.get_default("datasets")
    ann = args.annotations or ("shipped" if default else "auto")
    result = {"downscale": args.downscale, "stride": args.stride, "annotations": ann,
              "datasets": {portable_path(p): roi_share(p, args.downscale, args.stride, ann) for p in paths}}
    write_results(args.out, "roi_share", argv, f": {len(paths)} sequences", table(result), result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
