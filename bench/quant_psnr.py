"""What wire quantisation costs in rendering quality (SPEC §8: quantise where it costs no measurable
ROI PSNR; target ≤ 0.05 dB against lossless).

Maps a sequence (or loads a mapped ``map.ply``), encodes it with the quantised and lossless wire
codecs, decodes both, renders every frame and compares ROI PSNR and full-image PSNR.

    python -m bench.quant_psnr --dataset ../shared/datasets/Replica_room0/room0 --downscale 4 \
        --map runs/room0/map.ply --task-id room0-pick-plant

Prints a table and writes ``bench/results/quant_psnr.json``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch

RESULTS = Path(__file__).resolve().parent / "results"


def _render_scores(gmap, dataset, roi_fn) -> tuple[float, float]:
    from gausslite.mapping.config import MapperConfig
    from gausslite.mapping.mapper import Mapper
    from gausslite.metrics import psnr

    m = Mapper(MapperConfig())
    m.model.set_map(gmap)
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


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the comparison; returns 0, or 1 when the quantised ROI PSNR loss exceeds ``--budget-db``."""
    from gausslite.datasets import load_dataset
    from gausslite.gaussians import GaussianMap
    from gausslite.pipeline import gt_roi_fn
    from gausslite.wire.codec import LOSSLESS, GaussianArrays, QuantConfig, assemble, encode_subset

    ap = argparse.ArgumentParser(prog="python -m bench.quant_psnr", description=__doc__.splitlines()[0])
    ap.add_argument("--dataset", required=True, type=Path)
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--map", required=True, type=Path, help="map.ply written by `gausslite map`")
    ap.add_argument("--task-id", default=None)
    ap.add_argument("--budget-db", type=float, default=0.05)
    ap.add_argument("--out", type=Path, default=RESULTS / "quant_psnr.json")
    args = ap.parse_args(argv)

    ds = load_dataset(args.dataset, downscale=args.downscale, max_frames=args.max_frames)
    roi_fn = gt_roi_fn(ds, args.task_id) if args.task_id else None
    gmap = GaussianMap.load_ply(args.map)
    arrays = GaussianArrays.from_any(gmap)
    rows = []
    for name, quant in (("lossless", LOSSLESS), ("quantised", QuantConfig())):
        chunks = encode_subset(arrays, "bench", 1, quant=quant)
        decoded, _ = assemble(chunks)
        full, roi = _render_scores(decoded.to_gaussian_map(), ds, roi_fn)
        rows.append({"codec": name, "bytes_per_gaussian": sum(map(len, chunks)) / len(arrays),
                     "psnr": full, "roi_psnr": roi})
    d_full = rows[1]["psnr"] - rows[0]["psnr"]
    d_roi = rows[1]["roi_psnr"] - rows[0]["roi_psnr"]
    print(f"map: {args.map} ({len(arrays)} Gaussians), {len(ds)} views, task {args.task_id}")
    print(f"{'codec':<10} {'B/Gaussian':>10} {'PSNR':>8} {'ROI PSNR':>9}")
    for r in rows:
        print(f"{r['codec']:<10} {r['bytes_per_gaussian']:>10.2f} {r['psnr']:>8.3f} {r['roi_psnr']:>9.3f}")
    print(f"quantised − lossless: PSNR {d_full:+.4f} dB, ROI PSNR {d_roi:+.4f} dB (budget −{args.budget_db} dB)")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"map": str(args.map), "task_id": args.task_id, "n_gaussians": len(arrays),
                                    "rows": rows, "delta_psnr_db": d_full, "delta_roi_psnr_db": d_roi},
                                   indent=2))
    return 0 if (math.isnan(d_roi) or d_roi >= -args.budget_db) else 1


if __name__ == "__main__":
    raise SystemExit(main())
