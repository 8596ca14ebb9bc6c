"""Which pose-graph solver the odometry's loop closure uses: Open3D's global optimisation against gtsam's, on the
same keyframe graphs (``gausslite.datasets.pose_graph``; docs/design.md, "Drift correction").

Per sequence of ``bench.odometry`` (TUM fr1/rpy, the synthetic circle, the synthetic walk), the odometry runs once
with loop closure; its final graph (odometry edges and accepted loop edges) is then solved from the chained odometry
poses, without the corrections made while tracking, by

- ``open3d``: ``open3d.pipelines.registration.global_optimization`` (Levenberg-Marquardt with the line process that
  prunes disagreeing loop edges; Choi, Zhou, Koltun, CVPR 2015), as the odometry does;
- ``gtsam``: ``gtsam.LevenbergMarquardtOptimizer`` over ``BetweenFactorPose3`` factors with the same information
  matrices, loop factors under a Huber kernel (Dellaert, Kaess, "Factor Graphs for Robot Perception", 2017).

Measured: the keyframes' ATE RMSE against the reference poses (chained, and after each solver) and each solver's
time. gtsam is not a GaussLite dependency: ``pip install gtsam`` to run this bench.

Usage::

    python -m bench.pose_graph_solvers [--sequences tum_fr1_rpy,synthetic_circle,synthetic_walk] [--work DIR]
                                       [--out bench/results/pose_graph_solvers.json]
"""

from __future__ import annotations

import argparse
import copy
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
from tqdm import tqdm

from bench._results import write_results
from bench.odometry import RESULTS, load_sequence
from gausslite.datasets.odometry import OdometryConfig, RGBDOdometry
from gausslite.datasets.pose_graph import KeyframeGraph, LoopConfig, loop_information
from gausslite.datasets.trajectory import ate_rmse

SEQUENCES = ("tum_fr1_rpy", "synthetic_circle", "synthetic_walk")


def chained(graph: KeyframeGraph) -> Dict[int, np.ndarray]:
    """Frame id → (4, 4) c2w of every keyframe, integrated along the odometry edges from the first keyframe."""
    first = next(iter(graph.nodes))
    pose = {first: graph.nodes[first].c2w.copy()}
    for s, t, T, _ in graph.odometry_edges:  # T = c2w_t⁻¹ c2w_s, in the order the keyframes were taken
        pose[s] = pose[t] @ T
    return pose


def solve_open3d(graph: KeyframeGraph, init: Dict[int, np.ndarray], cfg: LoopConfig) -> tuple:
    """``(poses, seconds)`` of Open3D's global optimisation from ``init`` (a copy of the graph is solved)."""
    g = copy.deepcopy(graph)
    for fid in g.nodes:
        g.nodes[fid].c2w = init[fid].copy()
    t0 = time.perf_counter()
    new = g.optimise(cfg)
    return (new or init), time.perf_counter() - t0


def solve_gtsam(graph: KeyframeGraph, init: Dict[int, np.ndarray]) -> tuple:
    """``(poses, seconds)`` of gtsam's Levenberg-Marquardt from ``init`` (the first keyframe held by a tight prior).

    Raises:
        ModuleNotFoundError: gtsam is not installed.
    """
    import gtsam  # noqa: PLC0415 - an optional comparison, not a dependency

    ids = list(graph.nodes)
    key = {fid: i for i, fid in enumerate(ids)}
    factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for fid in ids:
        values.insert(key[fid], gtsam.Pose3(init[fid]))
    factors.add(gtsam.PriorFactorPose3(key[ids[0]], gtsam.Pose3(init[ids[0]]),
                                       gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for s, t, T, info in graph.odometry_edges:
        factors.add(gtsam.BetweenFactorPose3(key[t], key[s], gtsam.Pose3(T),
                                             gtsam.noiseModel.Gaussian.Information(info)))
    for e in graph.loops:
        noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345),
                                               gtsam.noiseModel.Gaussian.Information(loop_information(e)))
        factors.add(gtsam.BetweenFactorPose3(key[e.target], key[e.source], gtsam.Pose3(e.T), noise))
    t0 = time.perf_counter()
    res = gtsam.LevenbergMarquardtOptimizer(factors, values, gtsam.LevenbergMarquardtParams()).optimize()
    return {fid: res.atPose3(key[fid]).matrix() for fid in ids}, time.perf_counter() - t0


def compare(frames: list) -> dict:
    """The solvers on the final keyframe graph of the odometry over ``frames`` (reference poses as ``c2w``)."""
    odo = RGBDOdometry(OdometryConfig(), initial_pose=frames[0].c2w)
    for f in tqdm(frames, desc="odometry", unit="frame", leave=False):
        odo.track(f)
    g = odo.graph
    ref = {int(f.frame_id): f.c2w for f in frames}
    ids = list(g.nodes)
    truth = np.stack([ref[i] for i in ids])
    init = chained(g)

    def ate(p):
        return ate_rmse(np.stack([p[i] for i in ids]), truth)

    p_o3d, s_o3d = solve_open3d(g, init, odo.config.loop)
    p_gt, s_gt = solve_gtsam(g, init)
    return {"keyframes": len(ids), "loops": len(g.loops), "ate_chained_m": ate(init),
            "open3d": {"ate_m": ate(p_o3d), "seconds": s_o3d}, "gtsam": {"ate_m": ate(p_gt), "seconds": s_gt}}


def table(results: dict) -> str:
    """The Markdown table of ``results[sequence]``."""
    rows = ["| sequence | keyframes | loops | keyframe ATE, chained (cm) | Open3D (cm) | gtsam (cm) | Open3D (ms) | "
            "gtsam (ms) |", "|---|---|---|---|---|---|---|---|"]
    for seq, r in results.items():
        rows.append(f"| {seq} | {r['keyframes']} | {r['loops']} | {100 * r['ate_chained_m']:.2f} | "
                    f"{100 * r['open3d']['ate_m']:.2f} | {100 * r['gtsam']['ate_m']:.2f} | "
                    f"{1e3 * r['open3d']['seconds']:.0f} | {1e3 * r['gtsam']['seconds']:.0f} |")
    return "\n".join(rows)


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point: solve, write the JSON and the Markdown table, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequences", default=",".join(SEQUENCES), help=f"comma-separated, of {', '.join(SEQUENCES)}")
    ap.add_argument("--synthetic-frames", type=int, default=300, help="frames of the synthetic circle")
    ap.add_argument("--walk-frames", type=int, default=525, help="frames of the synthetic walk")
    ap.add_argument("--synthetic-size", default="320x240", help="WxH of the synthetic scenes")
    ap.add_argument("--work", type=Path, default=None, help="folder for the rendered synthetic scenes (kept)")
    ap.add_argument("--out", type=Path, default=RESULTS / "pose_graph_solvers.json")
    args = ap.parse_args(argv)
    seqs = [s for s in args.sequences.split(",") if s]
    if any(s not in SEQUENCES for s in seqs):
        ap.error(f"sequences are of {', '.join(SEQUENCES)}")
    size = tuple(int(v) for v in args.synthetic_size.lower().split("x"))
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench_solvers_") as tmp:
        for name in seqs:
            frames = load_sequence(name, args.work or Path(tmp), args.synthetic_frames, size, args.walk_frames)
            results[name] = compare(frames)
            print(f"{name}: {results[name]}", flush=True)
    write_results(args.out, "pose_graph_solvers", argv, "", table(results), {"sequences": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
