"""Why refinement ended below the vote on room0: refine one fused vote map over the keyframes as the
agents uploaded them (JPEG) and over the original frames (lossless), and compare ROI PSNR.

    gausslite sim --dataset DATA/Replica_room0/room0 --downscale 4 --out runs/sim_room0 \\
        --set agent.keyframe_format=jpeg
    python -m bench.refine_keyframes --fusion-dir runs/sim_room0/data/fusion \\
        --dataset DATA/Replica_room0/room0 --downscale 4

Prints a table and writes ``bench/results/share_sim_seeds/refine_jpeg_vs_png_room0.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from bench._results import write_json
from gausslite.camera import Intrinsics
from gausslite.datasets import load_dataset
from gausslite.datasets.base import Frame
from gausslite.evaluation import evaluate_fused
from gausslite.fusion.refine import refine_map
from gausslite.mapping.views import keyframe_from_frame
from gausslite.wire.codec import assemble
from gausslite.wire.images import decode_color, decode_depth
from gausslite_rpc import fusion_pb2
from gausslite_services.fusion_server.store import FusionStore

RESULTS = Path(__file__).resolve().parent / "results" / "share_sim_seeds"


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run the comparison (exit 0)."""
    ap = argparse.ArgumentParser(prog="python -m bench.refine_keyframes", description=__doc__.splitlines()[0])
    ap.add_argument("--fusion-dir", required=True, type=Path, help="DIR/data/fusion of a sim run")
    ap.add_argument("--dataset", required=True, type=Path)
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--iters", type=int, default=100)
    ap.add_argument("--tasks", default="room0-pick-plant,room0-find-ottoman", help="task ids, comma-separated")
    ap.add_argument("--out", type=Path, default=RESULTS / "refine_jpeg_vs_png_room0.json")
    args = ap.parse_args(argv)

    st = FusionStore(args.fusion_dir)
    infos = [fusion_pb2.FuseResult.FromString(b) for b in st.fused_infos()]
    vote = [i for i in infos if i.method == fusion_pb2.FUSE_METHOD_VOTE and not i.refined][-1]
    _, _, n_chunks = st.fused_info(vote.fused_version)
    fused, _ = assemble([st.fused_chunk(vote.fused_version, i) for i in range(n_chunks)])
    ds = load_dataset(args.dataset, downscale=args.downscale)
    frames = [ds[i] for i in range(len(ds))]
    by_id = {int(f.frame_id): f for f in frames}
    uploaded, original = [], []
    for k in st.keyframes():
        f = by_id[int(k.frame_id)]
        intr = Intrinsics(k.fx, k.fy, k.cx, k.cy, k.width, k.height)
        up = Frame(k.frame_id, k.timestamp, decode_color(k.color, "keyframe"),
                   decode_depth(k.depth, k.depth_scale, "keyframe"), np.asarray(k.c2w, np.float64), intr)
        uploaded.append(keyframe_from_frame(up, "cpu"))
        original.append(keyframe_from_frame(dataclasses.replace(f, intrinsics=intr), "cpu"))
    tasks = [t.id for t in ds.annotations.tasks][:2] if args.tasks is None else args.tasks.split(",")
    rows = {}
    for name, arr in (("vote", fused), ("refine, uploaded keyframes", refine_map(fused, uploaded, args.iters)),
                      ("refine, original frames", refine_map(fused, original, args.iters))):
        g = arr.to_gaussian_map()
        rows[name] = {t: evaluate_fused(g, frames, ds.annotations, t) for t in tasks}
        print(f"{name:<28} " + "  ".join(f"{t} {v:.2f}" for t, v in rows[name].items()), flush=True)
    write_json(args.out, {"fusion_dir": str(args.fusion_dir), "keyframes": len(uploaded), "roi_psnr": rows},
               "refine_keyframes", argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
