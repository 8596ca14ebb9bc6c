"""Rolling-shutter calibration: warp PSNR of overlapping frame pairs against an assumed readout time.

    python -m bench.rolling_shutter [--dataset PATH] [--downscale 2] [--pairs 60] [--out bench/results/rolling_shutter.json]

A rolling-shutter camera reads row ``v`` at ``t(v)`` (:func:`gausslite.mapping.shutter.row_time`), so a
moving camera sees each row from its own pose. This bench needs no map: it warps frame ``j`` into frame
``i`` with frame ``i``'s depth and the sensor's poses, each row of both frames placed at the pose of its
readout time ``c2w · E(t(v) · ξ̇)`` (ξ̇ the camera's velocity, a central difference of the sensor's poses
around the frame; the row of frame ``j`` a point lands in is found by fixed-point iteration), and scores the
warped colour against frame ``i`` (PSNR over the pixels that land inside frame ``j``). A readout time that
models the camera raises the warp PSNR of pairs taken at different velocities; the wrong row order lowers
it. Pairs: random ``(i, j)`` at least ``--min-gap`` frames apart whose optical axes are within 15° and where
one of the two turns faster than ``--min-speed`` °/s. Each readout is also scored with the poses read
``--offsets`` seconds later (a clock offset between camera and motion capture; per-keyframe pose refinement
absorbs it in the mapper). Prints a table, writes JSON and ``<out>.png`` (frame ``i`` of the fastest pair, the
warp error at readout 0 and at the best readout).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from tqdm import tqdm

from bench._results import write_json
from gausslite.datasets import detect_layout, load_dataset
from gausslite.mapping.blur import exposure_twist
from gausslite.mapping.profiles import profile_for_layout
from gausslite.mapping.shutter import readout_norm, row_time

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))


def velocities(frames) -> list[np.ndarray]:
    """(6,) twist per second (ω rad/s, v m/s, in the frame's own camera frame) of every frame: the central
    difference of the sensor's poses of its neighbours (one-sided at the ends; :func:`exposure_twist` over
    one second)."""
    n = len(frames)
    return [exposure_twist(frames[a].c2w, frames[a].timestamp, frames[b].c2w, frames[b].timestamp, 1.0, math.inf)
            for a, b in ((max(i - 1, 0), min(i + 1, n - 1)) for i in range(n))]


def _row_pose_apply(X: np.ndarray, t: np.ndarray, vel: np.ndarray, inverse: bool) -> np.ndarray:
    """Points (N, 3) moved by ``E(t_n · vel)`` (camera at its row time → camera at the frame time), or by its
    inverse."""
    R = Rotation.from_rotvec(t[:, None] * vel[None, :3]).as_matrix()
    if not inverse:
        return np.einsum("nij,nj->ni", R, X) + t[:, None] * vel[None, 3:]
    return np.einsum("nji,nj->ni", R, X - t[:, None] * vel[None, 3:])


def warp_psnr(fi, fj, vel_i: np.ndarray, vel_j: np.ndarray, readout_s: float, offset_s: float = 0.0,
              rows_top_first: bool = True, return_error: bool = False):
    """PSNR (dB) of frame ``fj``'s colour warped into frame ``fi`` (see module doc) for a readout of
    ``readout_s`` seconds (top row first unless ``rows_top_first`` is False) with poses read ``offset_s``
    later. Returns (psnr, covered fraction of fi's pixels[, (H, W) squared error with NaN outside])."""
    H, W = fi.depth.shape
    K = fi.intrinsics.K.astype(np.float64)
    rn = readout_norm(readout_s, K[1, 1], H) * (1.0 if rows_top_first else -1.0)
    vv, uu = np.nonzero(fi.depth > 0)
    z = fi.depth[vv, uu].astype(np.float64)
    X = np.stack([(uu - K[0, 2]) / K[0, 0] * z, (vv - K[1, 2]) / K[1, 1] * z, z], 1)
    ti = row_time(vv.astype(np.float64), K[1, 2], K[1, 1], rn) + offset_s
    Pw = _row_pose_apply(X, ti, vel_i, False) @ fi.c2w[:3, :3].T + fi.c2w[:3, 3]
    w2c = np.linalg.inv(fj.c2w)
    Pj = Pw @ w2c[:3, :3].T + w2c[:3, 3]
    Q, vj = Pj, K[1, 1] * Pj[:, 1] / Pj[:, 2] + K[1, 2]
    for _ in range(3):  # the row a point lands in sets the pose it is seen from
        tj = row_time(vj, K[1, 2], K[1, 1], rn) + offset_s
        Q = _row_pose_apply(Pj, tj, vel_j, True)
        vj = K[1, 1] * Q[:, 1] / Q[:, 2] + K[1, 2]
    uj = K[0, 0] * Q[:, 0] / Q[:, 2] + K[0, 2]
    ok = (Q[:, 2] > 0.1) & (uj >= 0) & (uj <= W - 1) & (vj >= 0) & (vj <= H - 1)
    mapx = np.full((H, W), -1.0, np.float32)
    mapy = np.full((H, W), -1.0, np.float32)
    mapx[vv[ok], uu[ok]] = uj[ok]
    mapy[vv[ok], uu[ok]] = vj[ok]
    warped = cv2.remap(fj.rgb.astype(np.float32) / 255.0, mapx, mapy, cv2.INTER_LINEAR)
    err = np.full((H, W), np.nan)
    err[vv[ok], uu[ok]] = ((warped - fi.rgb.astype(np.float32) / 255.0) ** 2)[vv[ok], uu[ok]].mean(1)
    mse = float(np.nanmean(err)) if ok.any() else float("nan")
    psnr = -10.0 * np.log10(max(mse, 1e-12))
    return (psnr, float(ok.mean()), err) if return_error else (psnr, float(ok.mean()))


def pick_pairs(frames, vels, n_pairs: int, min_gap: int, min_speed_deg: float, max_angle_deg: float, seed: int):
    """``n_pairs`` random (i, j) pairs (see module doc); fewer if the sequence has fewer after 200 000 draws."""
    rng = np.random.default_rng(seed)
    speed = np.array([np.degrees(np.linalg.norm(v[:3])) for v in vels])
    pairs, n = [], len(frames)
    for _ in range(200_000):
        if len(pairs) >= n_pairs:
            break
        i, j = (int(x) for x in rng.integers(0, n, 2))
        if abs(i - j) < min_gap or max(speed[i], speed[j]) < min_speed_deg:
            continue
        cos = float(frames[i].c2w[:3, 2] @ frames[j].c2w[:3, 2])
        if np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) > max_angle_deg:
            continue
        pairs.append((i, j))
    return pairs, speed


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", type=Path, default=SHARED / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy")
    ap.add_argument("--downscale", type=float, default=2.0)
    ap.add_argument("--pairs", type=int, default=60)
    ap.add_argument("--min-gap", type=int, default=8, help="frames between the two of a pair, at least")
    ap.add_argument("--min-speed", type=float, default=40.0, help="one frame of a pair turns faster (°/s)")
    ap.add_argument("--readouts", default="0,0.01,0.015,0.02,0.025,0.03,0.04", help="readout times, seconds")
    ap.add_argument("--offsets", default="0,-0.005", help="pose time offsets, seconds")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "results" / "rolling_shutter.json")
    args = ap.parse_args(argv)

    if not args.dataset.exists():
        print(f"dataset not found: {args.dataset}", file=sys.stderr)
        return 2
    profile = profile_for_layout(detect_layout(args.dataset)[0])
    ds = load_dataset(args.dataset, downscale=args.downscale, **profile.loader)
    frames = [ds[i] for i in range(len(ds))]
    vels = velocities(frames)
    pairs, speed = pick_pairs(frames, vels, args.pairs, args.min_gap, args.min_speed, 15.0, args.seed)
    readouts = [float(x) for x in args.readouts.split(",")]
    offsets = [float(x) for x in args.offsets.split(",")]
    t0 = time.perf_counter()
    base = np.array([warp_psnr(frames[i], frames[j], vels[i], vels[j], 0.0)[0] for i, j in pairs])
    rows = []
    settings = [(ro, off, True) for off in offsets for ro in readouts] + [(0.02, 0.0, False)]
    for ro, off, top in tqdm(settings, desc="rolling_shutter", unit="setting"):
        p = np.array([warp_psnr(frames[i], frames[j], vels[i], vels[j], ro, off, top)[0] for i, j in pairs])
        gain = p - base
        rows.append({"readout_s": ro, "offset_s": off, "rows": "top first" if top else "bottom first",
                     "warp_psnr": float(p.mean()), "gain": float(gain.mean()), "gain_std": float(gain.std()),
                     "improved": float((gain > 0).mean())})
    best = max((r for r in rows if r["offset_s"] == 0.0 and r["rows"] == "top first"), key=lambda r: r["gain"])
    print(f"{len(pairs)} pairs of {args.dataset.name} at 1/{args.downscale:g} ({time.perf_counter() - t0:.0f} s); "
          f"warp PSNR at readout 0: {base.mean():.2f} dB")
    print("| readout ms | pose offset ms | rows | warp PSNR dB | gain dB (mean ± std over pairs) | pairs improved |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['readout_s'] * 1e3:g} | {r['offset_s'] * 1e3:g} | {r['rows']} | {r['warp_psnr']:.2f} | "
              f"{r['gain']:+.2f} ± {r['gain_std']:.2f} | {100 * r['improved']:.0f} % |")
    write_json(args.out, {"dataset": str(args.dataset.name), "downscale": args.downscale, "pairs": pairs,
                          "base_warp_psnr": float(base.mean()), "rows": rows, "best_readout_s": best["readout_s"]},
               "rolling_shutter", argv, indent=1)
    # picture: frame i of the fastest pair, its warp error without and with the best readout
    i, j = max(pairs, key=lambda p: max(speed[p[0]], speed[p[1]]))
    errs = [warp_psnr(frames[i], frames[j], vels[i], vels[j], ro, return_error=True)[2] for ro in (0.0, best["readout_s"])]
    tiles = [cv2.cvtColor(frames[i].rgb, cv2.COLOR_RGB2BGR)]
    for e in errs:
        e8 = np.nan_to_num(np.sqrt(e) * 4 * 255, nan=0).clip(0, 255).astype(np.uint8)
        tiles.append(cv2.applyColorMap(e8, cv2.COLORMAP_INFERNO))
    img = np.concatenate(tiles, 1)
    for k, label in enumerate([f"frame {i} ({speed[i]:.0f} deg/s), warped from {j}", "error, global shutter",
                               f"error, readout {best['readout_s'] * 1e3:g} ms"]):
        cv2.putText(img, label, (k * frames[i].rgb.shape[1] + 4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
    cv2.imwrite(str(args.out.with_suffix(".png")), img)
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
