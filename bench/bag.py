"""ROS bag input: TUM round trip through every storage, and depth registration on an unregistered recording.

1. **Round trip.** TUM fr1_rpy (first ``--frames`` frames, ``--downscale``, undistorted, interpolated
   poses) → ``export_bag`` (MCAP, SQLite3, ROS 1) → ``BagDataset``: largest colour / depth / pose /
   timestamp differences, intrinsics equality, bag size and export / load times; then the same
   mapping run on the folder and on the MCAP bag (PSNR, depth L1, Gaussians).
2. **Registration.** The synthetic room recorded like a Kinect / RealSense without ``align_depth``:
   colour at fx = fy = 525, a separate depth camera at fx = fy = 585 (both at 640x480 / ``--reg-downscale``),
   depth 2.5 cm to the side and turned 1°, depth as 16UC1 millimetres on its own topic with its own
   CameraInfo, REP 105 TF tree (``map → odom → base_link → camera_link → camera_color_optical_frame →
   camera_depth_optical_frame``). The bag loader registers the depth into the colour camera; it is
   compared with the depth the colour camera itself would measure (ray-cast), and with using the
   unregistered depth as if it were registered ("naive"). Mapping PSNR with the three depths
   (ideal = ray-cast colour-camera depth, registered, naive).

Usage::

    python -m bench.bag [--quick] [--out bench/results/bag.json]
"""

from __future__ import annotations

import argparse
import platform
import shutil
import tempfile
import time
from pathlib import Path
from typing import Optional

import numpy as np

from gausslite.camera import Intrinsics
from gausslite.datasets import load_dataset
from gausslite.config import load_mapper_config
from gausslite.pipeline import run_mapping
from gausslite.ros.bagio import BagWriter
from gausslite.ros.export import T_BASE_OPTICAL, export_bag
from gausslite.ros.transforms import make_transform
from gausslite.synthetic.raycast import render
from gausslite.synthetic.scene import build_default_scene
from gausslite.synthetic.trajectories import make_trajectories

from bench._results import write_json

RESULTS = Path(__file__).resolve().parent / "results"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy"


def _dir_size(p: Path) -> int:
    return p.stat().st_size if p.is_file() else sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def _map(ds, iters: int, seeds: int) -> dict:
    overrides = [f"iters_per_frame={iters}", f"seeding.seeds_per_frame={seeds}", "final_iters=0",
                 f"warmup_iters={max(1, iters // 3)}"]
    cfg = load_mapper_config(None, overrides, backend="warp")
    _, m = run_mapping(ds, cfg, progress=False)
    return {k: m[k] for k in ("psnr", "ssim", "depth_l1", "n_gaussians", "n_frames")}


def round_trip(tum: Path, frames: int, downscale: float, iters: int, seeds: int, work: Path) -> dict:
    src = load_dataset(tum, downscale=downscale, max_frames=frames, undistort=True, interpolate_poses=True)
    ref = [src[i] for i in range(len(src))]
    out = {"frames": len(src), "size": [src.intrinsics.width, src.intrinsics.height], "storages": {}}
    for storage in ("mcap", "sqlite3", "ros1"):
        path = work / ("tum.bag" if storage == "ros1" else f"tum_{storage}")
        t0 = time.perf_counter()
        export_bag(src, path, storage=storage)
        t_exp = time.perf_counter() - t0
        t0 = time.perf_counter()
        bag = load_dataset(path)
        got = [bag[i] for i in range(len(bag))]
        t_load = time.perf_counter() - t0
        out["storages"][storage] = {
            "frames": len(bag),
            "intrinsics_equal": bag.intrinsics == src.intrinsics,
            "max_rgb_diff": int(max(np.abs(a.rgb.astype(int) - b.rgb).max() for a, b in zip(ref, got))),
            "max_depth_diff_m": float(max(np.abs(a.depth - b.depth).max() for a, b in zip(ref, got))),
            "max_pose_diff": float(max(np.abs(a.c2w - b.c2w).max() for a, b in zip(ref, got))),
            "max_stamp_diff_s": float(max(abs(a.timestamp - b.timestamp) for a, b in zip(ref, got))),
            "bytes": _dir_size(path), "export_s": t_exp, "load_all_s": t_load,
        }
    bag = load_dataset(work / "tum_mcap")
    out["mapping"] = {"folder": _map(src, iters, seeds), "bag_mcap": _map(bag, iters, seeds)}
    # The mapper is chaotic in the poses: show that the bag maps exactly like the folder once the folder
    # carries the bag's poses (they differ by ~1e-16), and how far 1e-15 of pose noise moves the folder.
    folder_poses = src.poses.copy()
    src.poses = np.stack([bag[i].c2w for i in range(len(bag))])
    out["mapping"]["folder_with_bag_poses"] = _map(src, iters, seeds)
    for seed in (1, 2):
        src.poses = folder_poses + np.random.default_rng(seed).normal(scale=1e-15, size=folder_poses.shape) * \
            np.array([1, 1, 1, 0])[None, :, None]
        out["mapping"][f"folder_pose_noise_1e-15_seed{seed}"] = _map(src, iters, seeds)
    src.poses = folder_poses
    return out


def registration(frames: int, s: float, iters: int, seeds: int, work: Path, do_map: bool) -> dict:
    ci = Intrinsics(525 / s, 525 / s, (319.5 + 0.5) / s - 0.5, (239.5 + 0.5) / s - 0.5, int(640 // s), int(480 // s))
    di = Intrinsics(585 / s, 585 / s, ci.cx, ci.cy, ci.width, ci.height)
    T_cd = make_transform([-0.025, 0.0, 0.0], [0.0, np.sin(np.radians(0.5)), 0.0, np.cos(np.radians(0.5))])
    scene = build_default_scene(0)
    traj = make_trajectories(frames, 0)["agent_a"]
    renders = []
    for c2w in traj:
        col = render(scene, ci, c2w)
        renders.append((col.rgb, col.depth.astype(np.float32), render(scene, di, c2w @ T_cd).depth.astype(np.float32)))

    def write(path: Path, kind: str) -> Path:
        """kind: 'unregistered' (the recording), 'ideal' (colour-camera depth), 'naive' (raw depth labelled registered)."""
        opt, dopt = "camera_color_optical_frame", "camera_depth_optical_frame"
        with BagWriter(path, "mcap") as w:
            t0 = 1700000000.0
            w.write_tf(t0, [("map", "odom", np.eye(4)), ("base_link", "camera_link", np.eye(4)),
                            ("camera_link", opt, T_BASE_OPTICAL), (opt, dopt, T_cd)], static=True)
            for k, (c2w, (rgb, d_col, d_raw)) in enumerate(zip(traj, renders)):
                t = t0 + k / 30.0
                w.write_tf(t, [("odom", "base_link", c2w @ np.linalg.inv(T_BASE_OPTICAL))])
                w.write_camera_info("/camera/color/camera_info", t, opt, ci)
                w.write_image("/camera/color/image_raw", t, opt, rgb, "rgb8")
                if kind == "unregistered":
                    w.write_camera_info("/camera/depth/camera_info", t, dopt, di)
                    w.write_image("/camera/depth/image_rect_raw", t + 0.004, dopt, d_raw, "16UC1")
                else:
                    w.write_image("/camera/depth/image_rect_raw", t + 0.004, opt, d_col if kind == "ideal" else d_raw, "16UC1")
        return path

    bag = load_dataset(write(work / "unregistered", "unregistered"))
    assert not bag.registered
    errs, naive, cover = [], [], []
    t0 = time.perf_counter()
    frames_reg = [bag[i] for i in range(len(bag))]
    t_load = time.perf_counter() - t0
    for fr, (_rgb, d_col, d_raw) in zip(frames_reg, renders):
        d_mm = np.round(d_col * 1000) / 1000  # the recording is in millimetres
        ok = fr.depth > 0
        cover.append(ok.mean())
        errs.append(np.abs(fr.depth - d_mm)[ok])
        naive.append(np.abs(np.round(d_raw * 1000) / 1000 - d_mm)[d_raw > 0])
    e, n = np.concatenate(errs), np.concatenate(naive)
    res = {
        "frames": len(bag), "size": [ci.width, ci.height], "colour_f": ci.fx, "depth_f": di.fx,
        "baseline_m": 0.025, "rotation_deg": 1.0, "load_s_per_frame": t_load / len(bag),
        "registered": {"coverage": float(np.mean(cover)), "median_abs_err_m": float(np.median(e)),
                       "p95_abs_err_m": float(np.percentile(e, 95)), "p99_abs_err_m": float(np.percentile(e, 99)),
                       "frac_err_gt_5cm": float((e > 0.05).mean())},
        "naive": {"median_abs_err_m": float(np.median(n)), "p95_abs_err_m": float(np.percentile(n, 95)),
                  "frac_err_gt_5cm": float((n > 0.05).mean())},
    }
    if do_map:
        res["mapping"] = {
            "ideal": _map(load_dataset(write(work / "ideal", "ideal")), iters, seeds),
            "registered": _map(bag, iters, seeds),
            "naive": _map(load_dataset(write(work / "naive", "naive")), iters, seeds),
        }
    return res


def main(argv: Optional[list[str]] = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames, no mapping")
    ap.add_argument("--tum", type=Path, default=SHARED)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--downscale", type=float, default=4.0)
    ap.add_argument("--reg-frames", type=int, default=8)
    ap.add_argument("--reg-downscale", type=float, default=2.0)
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--seeds-per-frame", dest="seeds", type=int, default=1000, help="new Gaussians per frame")
    ap.add_argument("--out", type=Path, default=RESULTS / "bag.json")
    a = ap.parse_args(argv)
    if a.quick:
        a.frames, a.reg_frames = 4, 3
    work = Path(tempfile.mkdtemp(prefix="gausslite_bag_bench_"))
    try:
        result = {"machine": platform.platform(), "args": {k: str(v) for k, v in vars(a).items()}}
        if a.tum.exists():
            result["round_trip"] = round_trip(a.tum, a.frames, a.downscale, a.iters, a.seeds, work)
        else:
            print(f"TUM sequence not found at {a.tum}: round trip skipped")
        result["registration"] = registration(a.reg_frames, a.reg_downscale, a.iters, a.seeds, work, not a.quick)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    rt = result.get("round_trip")
    if rt:
        print(f"\nTUM round trip ({rt['frames']} frames, {rt['size'][0]}x{rt['size'][1]})")
        print("| storage | frames | K equal | max |Δrgb| | max |Δdepth| m | max |Δpose| | bytes | export s | load s |")
        print("|---|---|---|---|---|---|---|---|---|")
        for st, r in rt["storages"].items():
            print(f"| {st} | {r['frames']} | {r['intrinsics_equal']} | {r['max_rgb_diff']} | {r['max_depth_diff_m']:.2e} | "
                  f"{r['max_pose_diff']:.2e} | {r['bytes']} | {r['export_s']:.2f} | {r['load_all_s']:.2f} |")
        for k, m in rt["mapping"].items():
            print(f"mapping {k}: PSNR {m['psnr']:.4f} dB, depth L1 {m['depth_l1']:.5f} m, {m['n_gaussians']} G")
    rg = result["registration"]
    r, n = rg["registered"], rg["naive"]
    print(f"\nRegistration ({rg['frames']} frames, {rg['size'][0]}x{rg['size'][1]}, colour f={rg['colour_f']:.1f}, "
          f"depth f={rg['depth_f']:.1f}, 2.5 cm + 1 deg)")
    print("| depth | coverage | median |err| m | p95 m | >5 cm |")
    print("|---|---|---|---|---|")
    print(f"| registered | {r['coverage']:.3f} | {r['median_abs_err_m']:.4f} | {r['p95_abs_err_m']:.4f} | {r['frac_err_gt_5cm']:.4f} |")
    print(f"| naive (unregistered) | - | {n['median_abs_err_m']:.4f} | {n['p95_abs_err_m']:.4f} | {n['frac_err_gt_5cm']:.4f} |")
    if "mapping" in rg:
        for k, m in rg["mapping"].items():
            print(f"mapping with {k} depth: PSNR {m['psnr']:.2f} dB, depth L1 {m['depth_l1']:.4f} m, {m['n_gaussians']} G")
    write_json(a.out, result, "bag", argv)
    print(f"wrote {a.out}")
    return result


if __name__ == "__main__":
    main()
