"""What wire quantisation costs in rendering quality (quantise where it costs no measurable ROI PSNR;
target ≤ 0.05 dB against lossless).

Maps a sequence (or loads a mapped ``map.ply``), encodes it with the quantised and lossless wire
codecs, decodes both, renders every frame and compares ROI PSNR and full-image PSNR.

    python -m bench.quant_psnr --dataset DATA/Replica_room0/room0 --downscale 4 \
        --map runs/room0/map.ply --task-id room0-pick-plant

Prints a table and writes ``bench/results/quant_psnr.json``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

from bench._results import write_json
from gausslite.datasets import load_dataset
from gausslite.gaussians import GaussianMap
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.mapper import Mapper
from gausslite.metrics import psnr
from gausslite.pipeline import gt_roi_fn
from gausslite.wire.codec import GaussianArrays, LOSSLESS, QuantConfig, assemble, encode_subset, spatial_order

RESULTS = Path(__file__).resolve().parent / "results"


def _render_scores(gmap, dataset, roi_fn) -> tuple[float, float]:
    m = Mapper(MapperConfig())
    m.load_map(gmap)
    full, roi = [], []
    for fr in dataset:
        out = m.render(fr.c2w, fr.intrinsics.K, fr.intrinsics.width, fr.intrinsics.height)
        pred = out.color.clamp(0, 1)
        gt = torch.from_numpy(fr.rgb).float() / 255
        full.append(float(psnr(pred, gt)))
        if roi_fn is not None:
            mask = torch.from_numpy(roi_fn(fr))
            if bool(mask.any()):
                roi.append(float(psnr(pred, gt, mask=mask)))
    return float(np.mean(full)), (float(np.mean(roi)) if roi else math.nan)


def _parse_variant(text: str):
    """``name:key=value,key=value`` → (name, QuantConfig) (values: int, float or bool)."""
    name, _, body = text.partition(":")
    kw = {}
    for item in filter(None, body.split(",")):
        k, _, v = item.partition("=")
        kw[k] = (v.lower() == "true") if v.lower() in ("true", "false") else (
            int(v) if v.lstrip("-").isdigit() else float(v))
    return name, QuantConfig(**kw)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the comparison; returns 0, or 1 when the default quantised codec's ROI PSNR loss exceeds
    ``--budget-db``."""
    ap = argparse.ArgumentParser(prog="python -m bench.quant_psnr", description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", required=True, type=Path)
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--map", required=True, type=Path, help="map.ply written by `gausslite map`")
    ap.add_argument("--task-id", default=None)
    ap.add_argument("--budget-db", type=float, default=0.05)
    ap.add_argument("--variant", action="append", default=[], metavar="NAME:KEY=VALUE,...",
                    help="extra QuantConfig variants to compare (e.g. q8:quat_bits=8)")
    ap.add_argument("--out", type=Path, default=RESULTS / "quant_psnr.json")
    args = ap.parse_args(argv)

    ds = load_dataset(args.dataset, downscale=args.downscale, max_frames=args.max_frames)
    roi_fn = gt_roi_fn(ds, args.task_id) if args.task_id else None
    gmap = GaussianMap.load_ply(args.map)
    arrays = GaussianArrays.from_any(gmap)
    # the agents send rows in Morton order (previous-row prediction); so does the bench
    arrays = arrays.take(spatial_order(arrays.means))
    active = arrays.take(arrays.active)
    rows = []
    variants = [("lossless", LOSSLESS), ("quantised", QuantConfig())] + [_parse_variant(v) for v in args.variant]
    for name, quant in variants:
        chunks = encode_subset(arrays, "bench", 1, quant=quant)
        decoded, _ = assemble(chunks)
        full, roi = _render_scores(decoded.to_gaussian_map(), ds, roi_fn)
        sub = sum(map(len, encode_subset(active, "bench", 1, quant=quant))) / max(1, len(active))
        rows.append({"codec": name, "quant": {k: getattr(quant, k) for k in quant.__dataclass_fields__},
                     "bytes_per_gaussian": sum(map(len, chunks)) / len(arrays),
                     "active_subset_bytes_per_gaussian": sub, "psnr": full, "roi_psnr": roi})
    for r in rows:
        r["delta_psnr_db"] = r["psnr"] - rows[0]["psnr"]
        r["delta_roi_psnr_db"] = r["roi_psnr"] - rows[0]["roi_psnr"]
    print(f"map: {args.map} ({len(arrays)} Gaussians, {len(active)} active), {len(ds)} views, task {args.task_id}")
    print(f"{'codec':<12} {'B/Gaussian':>10} {'B/G active':>10} {'PSNR':>8} {'ROI PSNR':>9} {'ΔROI dB':>8}")
    for r in rows:
        print(f"{r['codec']:<12} {r['bytes_per_gaussian']:>10.2f} {r['active_subset_bytes_per_gaussian']:>10.2f} "
              f"{r['psnr']:>8.3f} {r['roi_psnr']:>9.3f} {r['delta_roi_psnr_db']:>+8.4f}")
    d_full, d_roi = rows[1]["delta_psnr_db"], rows[1]["delta_roi_psnr_db"]
    print(f"quantised − lossless: PSNR {d_full:+.4f} dB, ROI PSNR {d_roi:+.4f} dB (budget −{args.budget_db} dB)")
    write_json(args.out, {"map": str(args.map), "task_id": args.task_id, "n_gaussians": len(arrays),
                          "n_active": len(active), "rows": rows, "delta_psnr_db": d_full,
                          "delta_roi_psnr_db": d_roi}, "quant_psnr", argv)
    return 0 if (math.isnan(d_roi) or d_roi >= -args.budget_db) else 1


if __name__ == "__main__":
    raise SystemExit(main())
