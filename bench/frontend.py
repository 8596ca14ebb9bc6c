"""Benchmark: per-keyframe cost on this CPU of the open-vocabulary front-end with full-size real
architectures (random weights: latency does not depend on the weights), and its amortised cost under the
detection schedule on the TUM fr1/rpy trajectory.

Usage::

    python -m bench.frontend            # full-size models, 320x240 and 640x480, 1 and 2 threads; writes
                                        # bench/results/frontend.json and .md (run it alone on the machine)
    python -m bench.frontend --quick    # reduced models, 320x240, 1 thread, 20 frames: checks the pipeline, prints only

Models (exported once with :mod:`gausslite.attention.export` into ``--cache``, default
``~/.cache/gausslite/frontend``; never into the repository):

* detector: Grounding DINO-T (transformers ``GroundingDinoConfig()`` defaults: Swin-T backbone, BERT-base text
  encoder, 900 queries), exported with its input at the camera resolution;
* segmenter: YOLOv8-s-seg (FastSAM-s's network; ultralytics ``yolov8s-seg.yaml``), input the camera resolution
  letterboxed to multiples of 32 (320x240 -> 320x256).

Per size and ONNX Runtime intra-op thread count:

1. **Per call**: median wall time of ``detect`` (tokenise, resize, network, post-processing) and ``segment``
   (letterbox, network, masks) on a TUM frame, after one warm-up call; network-only time alongside.
2. **Schedule**: the attention front-end (:class:`gausslite.attention.AttentionFrontEnd`, paper thresholds) runs
   on the mapping keyframes of TUM fr1/rpy (:class:`gausslite.mapping.keyframes.KeyframeSelector` defaults over
   the sequence's frames): the detector runs on motion-triggered detection keyframes (1.0 m / 15 deg, or every
   10th frame), and between them the previous boxes are re-projected and re-segmented. Each backend runs its
   ONNX model on the frame (the time) and returns the annotation backend's result (objects.json), so the
   schedule, the boxes and the masks are those of a working detector although the weights are random.
   Amortised cost = front-end time (networks, re-projection, lifting, spatial filter; the annotation
   backend's own time is subtracted) / mapping keyframes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from tqdm import tqdm

from bench._results import write_results
from gausslite.attention import (
    AttentionConfig,
    AttentionFrontEnd,
    KeyframeConfig,
    OnnxFastSAMSegmenter,
    OnnxGroundingDetector,
)
from gausslite.attention.annotation_backend import AnnotationBackend, AnnotationDetector, AnnotationSegmenter
from gausslite.attention.export import export_grounding_dino, export_yolo_seg
from gausslite.attention.frontend import graph_parts
from gausslite.attention.timing import CostOnlyDetector, CostOnlySegmenter
from gausslite.datasets import load_dataset
from gausslite.mapping.keyframes import KeyframeRule, KeyframeSelector

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results" / "frontend.json"
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
TUM = SHARED / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy"
CACHE = Path(os.environ.get("GAUSSLITE_CACHE", Path.home() / ".cache" / "gausslite")) / "frontend"
FULL_SIZES = [(320, 240), (640, 480)]
QUICK_SIZES = [(320, 240)]


# ------------------------------------------------------------------------------------------ models
def _bert_vocab(path: Path, words: Sequence[str]) -> Path:
    """A vocab.txt with BERT's special-token ids (the detector computes its text mask from them) and ``words``."""
    toks = [f"[unused{i}]" for i in range(30522)]
    toks[0], toks[100], toks[101], toks[102], toks[103] = "[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]"
    toks[1012], toks[1029] = ".", "?"
    for i, w in enumerate(sorted(set(words))):
        toks[2000 + i] = w
    path.write_text("\n".join(toks) + "\n", encoding="utf-8")
    return path


def _gdino(quick: bool):
    # lazy: heavy optional dependency, loaded only on this path
    from transformers import BertConfig, GroundingDinoConfig, GroundingDinoForObjectDetection, SwinConfig

    torch.manual_seed(0)
    if not quick:
        return GroundingDinoForObjectDetection(GroundingDinoConfig(attn_implementation="eager")).eval(), "grounding-dino-t"
    sw = SwinConfig(embed_dim=24, depths=[1, 1, 1, 1], num_heads=[1, 1, 2, 2], window_size=7,
                    out_features=["stage2", "stage3", "stage4"])
    bt = BertConfig(hidden_size=32, num_hidden_layers=1, num_attention_heads=2, intermediate_size=64)
    cfg = GroundingDinoConfig(backbone_config=sw, text_config=bt, d_model=32, encoder_layers=1, decoder_layers=2,
                              num_queries=20, encoder_ffn_dim=64, decoder_ffn_dim=64, encoder_attention_heads=2,
                              decoder_attention_heads=2, attn_implementation="eager")
    return GroundingDinoForObjectDetection(cfg).eval(), "grounding-dino-reduced"


def ensure_models(cache: Path, size: Tuple[int, int], quick: bool, words: Sequence[str]) -> Dict[str, object]:
    """Export (once) the detector and segmenter for camera ``size`` = (W, H) into ``cache``.

    Returns:
        dict with ``detector``, ``vocab``, ``segmenter`` paths, model names and ``seg_imgsz`` (h, w).
    """
    W, H = size
    cache.mkdir(parents=True, exist_ok=True)
    det_name = "grounding-dino-reduced" if quick else "grounding-dino-t"
    seg_name = "yolov8n-seg" if quick else "yolov8s-seg"
    det = cache / f"{det_name}_{W}x{H}.onnx"
    seg_hw = (-(-H // 32) * 32, -(-W // 32) * 32)
    seg = cache / f"{seg_name}_{seg_hw[1]}x{seg_hw[0]}.onnx"
    if not det.is_file():
        model, _ = _gdino(quick)
        export_grounding_dino(model, det, image_size=(H, W))
        del model
    if not seg.is_file():
        export_yolo_seg(f"{seg_name}.yaml", seg, imgsz=seg_hw)
    vocab = _bert_vocab(cache / "vocab.txt", words)
    return {"detector": det, "vocab": vocab, "segmenter": seg, "detector_model": det_name,
            "segmenter_model": seg_name, "seg_imgsz": list(seg_hw)}


# ------------------------------------------------------------------------------------------ timing
def per_call(det, seg, frame, phrases: Sequence[str], repeats: int) -> Dict[str, float]:
    """Median seconds of detect/segment (and of their networks alone) on one frame, after a warm-up."""
    img = frame.rgb
    H, W = img.shape[:2]
    boxes = np.array([[W * 0.3, H * 0.3, W * 0.6, H * 0.7]], np.float32)
    dfeeds, _, _ = det.session_feeds(img, phrases)
    sx, _, _ = seg.preprocess(img)
    res: Dict[str, List[float]] = {"detect_s": [], "detector_net_s": [], "segment_s": [], "segmenter_net_s": []}
    det.detect(img, phrases)
    seg.segment(img, boxes)
    for _ in range(repeats):
        t = time.perf_counter()
        det.detect(img, phrases)
        res["detect_s"].append(time.perf_counter() - t)
        t = time.perf_counter()
        det.session.run(None, dfeeds)
        res["detector_net_s"].append(time.perf_counter() - t)
        t = time.perf_counter()
        seg.segment(img, boxes)
        res["segment_s"].append(time.perf_counter() - t)
        t = time.perf_counter()
        seg.session.run(None, {seg.input_name: sx})
        res["segmenter_net_s"].append(time.perf_counter() - t)
    return {k: statistics.median(v) for k, v in res.items()}


def mapping_keyframes(ds) -> List[int]:
    """Indices of the frames the mapper would take (keyframe selector defaults, mapper always free)."""
    sel = KeyframeSelector()
    out = []
    for i in range(len(ds)):
        fr = ds[i]
        pending, _ = sel.offer(i, fr.c2w, fr.timestamp)
        if pending:
            out.append(sel.take())
    return out


def schedule(ds, kf: Sequence[int], graph, det, seg, progress=None) -> Dict[str, float]:
    """Run the front-end over the mapping keyframes ``kf`` with timed backends; totals in seconds."""
    backend = AnnotationBackend(ds.annotations)
    tdet = CostOnlyDetector(det, AnnotationDetector(backend))
    tseg = CostOnlySegmenter(seg, AnnotationSegmenter(backend))
    fe = AttentionFrontEnd(graph, AttentionConfig(detector=tdet, segmenter=tseg), up_axis=ds.annotations.up_axis)
    total, relevant = 0.0, 0
    for i in kf:
        fr = ds[i]
        t = time.perf_counter()
        rel, _ = fe.process(fr)
        total += time.perf_counter() - t
        relevant += int(rel.any())
        if progress is not None:
            progress.update(1)
    n = len(kf)
    ann = tdet.answer_seconds + tseg.answer_seconds
    return {"mapping_keyframes": n, "detector_calls": len(tdet.seconds), "segmenter_calls": len(tseg.seconds),
            "frames_with_relevance": relevant, "total_s": total - ann, "annotation_backend_s": ann,
            "detector_s": float(sum(tdet.seconds)), "segmenter_s": float(sum(tseg.seconds)),
            "amortised_s": (total - ann) / max(n, 1)}


# ------------------------------------------------------------------------------------------ main
def _task(ds, task_id: Optional[str]):
    tasks = json.loads((Path(ds.path) / "tasks.json").read_text())["tasks"]
    t = next((t for t in tasks if t["id"] == task_id), None) if task_id else tasks[0]
    if t is None:
        raise SystemExit(f"no task {task_id!r} in {ds.path}/tasks.json")
    return t["id"], t["graph"]


def main(argv=None) -> dict:
    """Run the benchmark, print a table, write JSON + Markdown (full mode or when --out is given)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="reduced models, 320x240, 1 thread, 20 frames; print only")
    ap.add_argument("--threads", type=int, nargs="+", default=None, help="intra-op thread counts (default 1 2)")
    ap.add_argument("--sizes", nargs="+", default=None, help="camera sizes WxH (default 320x240 640x480)")
    ap.add_argument("--repeats", type=int, default=None, help="timed calls per model (default 5; quick 2)")
    ap.add_argument("--max-frames", type=int, default=None, help="use the first N frames of the sequence")
    ap.add_argument("--task-id", default=None, help="task of tasks.json whose phrases are queried (default: first)")
    ap.add_argument("--dataset", type=Path, default=TUM, help=f"TUM sequence (default {TUM})")
    ap.add_argument("--cache", type=Path, default=CACHE, help=f"exported models (default {CACHE})")
    ap.add_argument("--out", type=Path, default=None, help=f"JSON output (default {RESULTS} in full mode)")
    args = ap.parse_args(argv)

    if not (args.dataset / "rgb.txt").is_file():
        raise SystemExit(f"TUM sequence not found at {args.dataset} (set GAUSSLITE_SHARED or --dataset)")
    sizes = [tuple(int(v) for v in s.lower().split("x")) for s in args.sizes] if args.sizes else (
        QUICK_SIZES if args.quick else FULL_SIZES)
    threads = args.threads or ([1] if args.quick else [1, 2])
    repeats = args.repeats or (2 if args.quick else 5)
    max_frames = args.max_frames or (20 if args.quick else None)
    t_start = time.time()
    out: dict = {"machine": {"cpu_count": os.cpu_count(), "processor": platform.processor() or platform.machine(),
                             "loadavg_before": list(os.getloadavg())},
                 "quick": bool(args.quick), "runs": [],
                 "schedule": {"mapping_keyframes": dataclasses.asdict(KeyframeRule()),
                              "detection_keyframes": dataclasses.asdict(KeyframeConfig())}}
    # lazy: heavy optional dependency, loaded only on this path
    import onnxruntime

    out["machine"]["onnxruntime"] = onnxruntime.__version__
    rows = []
    for W, H in sizes:
        ds = load_dataset(args.dataset, downscale=640 / W, max_frames=max_frames)
        if ds.annotations is None:
            raise SystemExit(f"{args.dataset} has no objects.json: the schedule needs the annotation backend")
        task_id, graph = _task(ds, args.task_id)
        targets, anchors, _ = graph_parts(graph)
        phrases = list(dict.fromkeys(targets + anchors))
        all_tasks = json.loads((Path(ds.path) / "tasks.json").read_text())["tasks"]
        words = [w for t in all_tasks for key in ("targets", "anchors") for p in t["graph"].get(key, [])
                 for w in str(p).lower().split()]  # every task's words: the vocab also serves bench.realtime
        print(f"[{W}x{H}] exporting/loading models in {args.cache} ...", flush=True)
        models = ensure_models(args.cache, (W, H), args.quick, words)
        kf = mapping_keyframes(ds)
        for th in threads:
            det = OnnxGroundingDetector(models["detector"], models["vocab"], threads=th)
            seg = OnnxFastSAMSegmenter(models["segmenter"], threads=th)
            calls = per_call(det, seg, ds[0], phrases, repeats)
            with tqdm(total=len(kf), desc=f"{W}x{H} {th} thread{'s' * (th > 1)}", leave=False) as bar:
                sch = schedule(ds, kf, graph, det, seg, bar)
            run = {"size": f"{W}x{H}", "threads": th, "task_id": task_id, "phrases": phrases, "frames": len(ds),
                   "detector_model": models["detector_model"], "segmenter_model": models["segmenter_model"],
                   "detector_input_hw": list(det.input_size), "segmenter_input_hw": list(seg.input_hw),
                   "repeats": repeats, **calls, "every_keyframe_s": calls["detect_s"] + calls["segment_s"], **sch}
            out["runs"].append(run)
            rows.append(run)
            print(f"  {W}x{H} {th}t: detect {calls['detect_s']:.3f} s, segment {calls['segment_s']:.3f} s, "
                  f"amortised {sch['amortised_s']:.3f} s/keyframe", flush=True)
            del det, seg
    out["machine"]["loadavg_after"] = list(os.getloadavg())
    out["wall_s"] = time.time() - t_start

    md = ["| size | threads | detector | detect s | (network s) | segmenter | segment s | (network s) | "
          "detect+segment s | mapping keyframes | detector calls | amortised s/keyframe |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['size']} | {r['threads']} | {r['detector_model']} {r['detector_input_hw'][1]}x"
                  f"{r['detector_input_hw'][0]} | {r['detect_s']:.3f} | {r['detector_net_s']:.3f} | "
                  f"{r['segmenter_model']} {r['segmenter_input_hw'][1]}x{r['segmenter_input_hw'][0]} | "
                  f"{r['segment_s']:.3f} | {r['segmenter_net_s']:.3f} | {r['every_keyframe_s']:.3f} | "
                  f"{r['mapping_keyframes']} | {r['detector_calls']} | {r['amortised_s']:.3f} |")
    la = out["machine"]
    details = (f": {'reduced models (pipeline check)' if args.quick else 'full-size models, random weights'}; "
               f"TUM fr1/rpy, {rows[0]['frames'] if rows else 0} frames; {os.cpu_count()} CPUs; onnxruntime "
               f"{la['onnxruntime']}; load average before/after {la['loadavg_before'][0]:.2f}/"
               f"{la['loadavg_after'][0]:.2f}; {out['wall_s'] / 60:.1f} min. Per-call times are medians of "
               f"{repeats} calls after a warm-up; amortised = front-end time (without the annotation backend that "
               f"supplies boxes and masks) over the mapping keyframes (detector on detection keyframes only, "
               f"segmenter on every mapping keyframe with boxes).")
    table = "\n".join(md)
    dest = args.out if args.out is not None else (None if args.quick else RESULTS)
    if dest is not None:
        write_results(dest, "frontend", argv, details, table, out)
        print(f"wrote {dest} and {dest.with_suffix('.md')}")
    else:
        print(table)
    return out


if __name__ == "__main__":
    main()
