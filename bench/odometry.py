"""Tracking error and cost of the RGB-D odometry (``gausslite.odometry.rgbd``), the pose source of input without
poses (docs/mapper.md, "Poses from odometry").

Per sequence, at the mapping resolution of ``bench.realtime``'s scenes:

- ``tum_fr1_rpy``: TUM RGB-D fr1/rpy, the loader's 150 frames at 320×240 (``--downscale 2``), undistorted; the depth
  is not re-aligned in time (that uses the ground truth);
- ``synthetic_circle``: the synthetic scene (``gausslite make-scene --trajectory circle``), robot A, 300 frames at
  320×240 (rendered: exact depth, no noise);
- ``room0``: Replica room0, 20 frames at 300×170 (``--downscale 4``), far apart;
- ``synthetic_walk``: a room-sized hand-held walk of the synthetic scene (``gausslite make-scene --trajectory walk
  --sensor-noise realistic``: 7 m in two loops that come back to the desk, Kinect-like depth noise and holes, motion
  blur, rolling shutter, exposure changes), robot A, 525 frames at 320×240;
- ``synthetic_walk_tum``: the same walk seen by the Kinect v1 of TUM fr1 as measured (``--sensor-noise tum``: its
  field of view, disparity-quantised correlated depth noise and holes, colour-depth misregistration and delay, its
  exposure changes, blur and rolling shutter; ``bench.sensor_calibration``), robot A, 525 frames at 320×240;
- ``synthetic_walk_covered``: the same walk with the lens covered for 30 frames (2 s, black and without depth) halfway
  round its first loop, while the camera keeps walking (:func:`covered`): the tracker loses those frames and must
  re-localise;
- ``synthetic_scan_walk_tum``: the ``tum`` walk looking around as it goes (``--trajectory scan_walk``: roll, pitch
  and yaw sweeps that turn the camera at TUM fr1/rpy's median rate, about 52°/s against the walk's 17°/s), robot A,
  525 frames at 320×240.

Measured: ATE RMSE after rigid (SE(3), no scale) alignment to the reference poses, as the TUM benchmark's
``evaluate_ate.py``, of the poses as each frame was tracked (``ate_online_m``: what a live robot has at that moment)
and after the pose graph's later loop closures (``ate_rmse_m``: what an offline map uses), over the frames tracked;
the loop closures accepted and their error against the reference (a **false loop**: one whose measured relative pose
is more than 5 cm or 3° from the truth); the frames lost and re-localised; RPE (translational and rotational RMSE) per frame and per second; the fraction of frames
tracked (not lost); the odometry's wall-clock time per frame (``track`` alone: the frames are read first). Each
variant (``--variants``) is an ``OdometryConfig``: ``default`` (the shipped settings: tracked at about 160 pixels
wide), ``mapping_resolution`` (tracked at the sequence's own resolution), ``frame_to_frame`` (the shipped settings
registering against the previous frame only), ``no_loops`` (the shipped settings without loop closure),
``no_relocalisation`` (without re-localisation), and the registration's residuals: ``open3d_huber`` (Open3D's own
photometric Huber threshold, 0.1, instead of 0.5), ``photometric`` (the colour term alone) and ``geometric``
(point-to-plane alone); and how a loop candidate is registered (``loop.registration``, gates 2-3 of
``gausslite.odometry.pose_graph``): ``hybrid_loops`` (the tracker's own RGB-D registration), ``point_to_plane_loops``
(the same with its depth term alone) and ``fine_icp_loops`` (the default ICP on every depth point, up to 30 iterations
per level, instead of one point per 4 cm voxel and 15); and which loops get through: ``no_basin`` (without gate 3's
restarts along the least-pinned direction, ``loop.basin_m``) and ``two_candidates_no_basin`` (that, with 2 loop
candidates tried per keyframe instead of 4).

``--walk-seeds 0,1,2`` runs each synthetic walk once per rendering (its trajectory's and sensor's random draws; the
rows of seed s ≠ 0 are the sequence ``<name>_seed<s>``), as ``bench.sensor_calibration`` renders them.

``--loop-accuracy`` measures the loop registrations themselves (:func:`loop_accuracy`): every loop candidate the
shipped odometry tries is registered, from the same estimated relative pose, by each ``LoopConfig.registration``
alone, and the errors against the reference poses are reported (synthetic walks and TUM).

``--gains GIVEN.json,ODOMETRY.json`` compares the ROI gain (GaussLite − uniform, ``novel``) of live missions at the
odometry's poses with the gain at the given poses, from two ``bench.realtime`` runs (:func:`pose_gains`).

``--live`` also streams TUM fr1/rpy at 15 Hz to an agent with ``agent.pose_source: odometry`` that maps as it tracks
(:func:`live`): the share of frames tracked, the tracking time while mapping, and whether the frames kept to the
stream's clock.

Wall-clock figures are only comparable on an idle machine: the JSON records the load average before and after.

Usage::

    python -m bench.odometry [--sequences tum_fr1_rpy,synthetic_circle,room0]
                             [--variants default,mapping_resolution,frame_to_frame]
                             [--synthetic-frames 300] [--walk-seeds 0,1,2] [--loop-accuracy] [--live]
                             [--gains GIVEN.json,ODOMETRY.json]
                             [--out bench/results/odometry.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

import numpy as np
from tqdm import tqdm

from bench._results import write_results
from gausslite.stats import fmt, mean_std
from gausslite.datasets import load_dataset
from gausslite.odometry.rgbd import OdometryConfig, RGBDOdometry
from gausslite.datasets.trajectory import ate_rmse, rotation_angle_deg, rpe
from gausslite.synthetic import make_scene

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared")) / "datasets"
RESULTS = REPO / "bench" / "results"

#: the odometry settings compared (``OdometryConfig`` fields over the defaults)
VARIANTS = {"default": {}, "mapping_resolution": {"track_width": None},
            "frame_to_frame": {"reference": "previous_frame"}, "no_loops": {"loop": {"enabled": False}},
            "no_relocalisation": {"relocalise": {"enabled": False}},
            # the registration's residuals: Open3D's own Huber threshold on the photometric term, and each term alone
            "open3d_huber": {"intensity_huber_delta": 0.1}, "photometric": {"method": "color"},
            "geometric": {"method": "point_to_plane"},
            # how a loop candidate is registered and verified (gates 2-3 of gausslite.odometry.pose_graph)
            "hybrid_loops": {"loop": {"registration": "hybrid"}},
            "point_to_plane_loops": {"loop": {"registration": "point_to_plane"}},
            "fine_icp_loops": {"loop": {"icp_voxel_m": None, "icp_iterations": 30, "icp_relative_change": 1e-6}},
            # which loops get through: gate 3 without its restarts along the least-pinned direction; and the
            # candidates tried per keyframe, 2 instead of 4, without the restarts
            "no_basin": {"loop": {"basin_m": None}},
            "two_candidates_no_basin": {"loop": {"max_candidates": 2, "basin_m": None}}}
SEQUENCES = ("tum_fr1_rpy", "synthetic_circle", "room0", "synthetic_walk", "synthetic_walk_covered",
             "synthetic_walk_tum", "synthetic_scan_walk_tum")
#: the name prefixes of the synthetic walks (rendered per ``--walk-seeds``; :func:`walk_dir`)
WALKS = ("synthetic_walk", "synthetic_scan_walk")
#: a loop closure whose relative pose is further than this from the reference's is a false loop (metres, degrees)
FALSE_LOOP = (0.05, 3.0)


def covered(n: int) -> range:
    """``synthetic_walk_covered``'s frames with the lens covered (black, no depth) in a walk of ``n`` frames: from 23 %
    of the walk (halfway round its first loop), 30 of 525 (2 s at 30 fps), scaled with ``n``."""
    start = int(0.23 * n)
    return range(start, start + max(1, round(30 * n / 525)))


def walk_dir(work: Path, level: str, seed: int = 0, trajectory: str = "walk") -> Path:
    """The folder of the synthetic walk (``trajectory``: ``walk`` or ``scan_walk``) with sensor level ``level`` and
    seed ``seed`` under ``work``, as this bench and ``bench.sensor_calibration`` render it: seed 0 ``walk`` for
    ``realistic``, else ``walk_<level>``, ``walk`` replaced by the trajectory's name; ``_seed<seed>`` added for
    another seed."""
    name = "walk" if level == "realistic" else f"walk_{level}"
    return work / (name.replace("walk", trajectory, 1) + (f"_seed{seed}" if seed else ""))


def load_sequence(name: str, work: Path, synthetic_frames: int, size: tuple, walk_frames: int = 525,
                  seed: int = 0) -> list:
    """The frames (with their reference poses as ``c2w``) of a bench sequence, read into memory; ``seed``: which
    rendering of a synthetic walk (its trajectory's and sensor's random draws; 0 for every other sequence).

    Raises:
        FileNotFoundError: a shared dataset that is absent (set ``GAUSSLITE_SHARED``).
    """
    if name == "tum_fr1_rpy":
        ds = load_dataset(SHARED / "TUM_rgbd_dataset_freiburg1_rpy", downscale=2, undistort=True,
                          interpolate_poses=True, align_depth_time=False, pose_source="given")
    elif name == "room0":
        ds = load_dataset(SHARED / "Replica_room0", downscale=4, pose_source="given")
    elif name.startswith(WALKS):
        level = "tum" if name.endswith("_tum") else "realistic"
        kind = "scan_walk" if name.startswith("synthetic_scan_walk") else "walk"
        scene = walk_dir(work, level, seed, trajectory=kind)
        if not (scene / "agent_a" / "traj.txt").is_file():
            make_scene(scene, seed=seed, frames=walk_frames, width=size[0], height=size[1], trajectory=kind,
                       sensor_noise=level, agents=("agent_a",))
        ds = load_dataset(scene / "agent_a", pose_source="given")
        frames = [ds[i] for i in range(len(ds))]
        if name.endswith("_covered"):
            frames = [dataclasses.replace(f, rgb=np.zeros_like(f.rgb), depth=np.zeros_like(f.depth))
                      if i in covered(len(frames)) else f for i, f in enumerate(frames)]
        return frames
    else:
        scene = work / "synthetic"
        if not (scene / "agent_a" / "traj.txt").is_file():
            make_scene(scene, frames=synthetic_frames, width=size[0], height=size[1], trajectory="circle",
                       agents=("agent_a",))
        ds = load_dataset(scene / "agent_a", pose_source="given")
    return [ds[i] for i in range(len(ds))]


def track(frames: list, overrides: dict) -> dict:
    """Run the odometry over ``frames`` (the first one's reference pose fixes the world frame) and score it: ATE of
    the online and the corrected poses over the tracked frames, RPE of the corrected ones, the loop closures and
    their error against the reference poses, the frames lost and re-localised, and the time per frame."""
    odo = RGBDOdometry(OdometryConfig(**overrides), initial_pose=frames[0].c2w)
    seconds, results = [], []
    for f in tqdm(frames, desc="odometry", unit="frame", leave=False):
        t0 = time.perf_counter()
        results.append(odo.track(f))
        seconds.append(time.perf_counter() - t0)
    ok = np.array([r.ok for r in results])
    online = np.stack([r.c2w for r in results])
    est = np.stack([odo.corrected(r) for r in results])
    ref = np.stack([f.c2w for f in frames])
    ts = np.array([f.timestamp for f in frames])
    i = frames[0].intrinsics
    tw = odo.config.track_width
    f = 1 if tw is None else max(1, round(i.width / tw))
    loops = loop_errors(odo, frames)
    summary = odo.summary()
    return {"frames": len(frames), "size": [i.width, i.height], "tracked_size": [i.width // f, i.height // f],
            "ate_rmse_m": ate_rmse(est[ok], ref[ok]), "ate_online_m": ate_rmse(online[ok], ref[ok]),
            "rpe": {"per_frame": rpe(est[ok], ref[ok]), "per_second": rpe(est[ok], ref[ok], ts[ok], 1.0,
                                                                          per_second=True)},
            "ms_per_frame": 1000.0 * float(np.mean(seconds[1:])) if len(seconds) > 1 else None,
            "tracked_fraction": float(np.mean(ok)), "lost": summary["failed"], "relocalised": summary["relocalised"],
            "lost_frame_ids": list(odo.failed_ids), "keyframes": odo.n_keyframes,
            "loops": {"accepted": len(loops), "false": sum(e["false"] for e in loops),
                      "candidates": summary["loop_candidates"], "rejected": summary["loop_rejected"],
                      "max_error_m": max((e["error_m"] for e in loops), default=None),
                      "max_error_deg": max((e["error_deg"] for e in loops), default=None), "edges": loops}}


def relative_error(true: np.ndarray, T: np.ndarray) -> tuple:
    """``(metres, degrees)`` of the relative pose ``T`` (4, 4) away from the reference ``true`` (4, 4)."""
    d = np.linalg.inv(true) @ T
    return float(np.linalg.norm(d[:3, 3])), rotation_angle_deg(d)


def loop_errors(odo: RGBDOdometry, frames: list) -> list:
    """Each accepted loop closure of ``odo`` with its error against the reference poses of ``frames``:
    ``[{"source", "target", "error_m", "error_deg", "false"}]`` (false: beyond :data:`FALSE_LOOP`)."""
    index = {int(f.frame_id): i for i, f in enumerate(frames)}
    out = []
    for e in odo.graph.loops:
        true = np.linalg.inv(frames[index[e.target]].c2w) @ frames[index[e.source]].c2w
        err_m, err_deg = relative_error(true, e.T)
        out.append({"source": e.source, "target": e.target, "error_m": err_m, "error_deg": err_deg,
                    "false": bool(err_m > FALSE_LOOP[0] or err_deg > FALSE_LOOP[1])})
    return out


#: the live measurement's variants: agent settings, and whether loops are closed on the tracking thread instead of
#: the agent's own loop-closing thread (``RGBDOdometry(background_loops=...)``)
LIVE_VARIANTS = {"default": ([], True), "loops_inline": ([], False),
                 "no_loops": (["agent.odometry.loop.enabled=false"], True),
                 "hybrid_loops": (["agent.odometry.loop.registration=hybrid"], True),
                 "two_candidates_no_basin": (["agent.odometry.loop.max_candidates=2",
                                              "agent.odometry.loop.basin_m=null"], True)}


def live(rate: float, budget: float, variant: str = "default") -> dict:
    """TUM fr1/rpy streamed to an agent at its 15 Hz (``agent.realtime``, ``agent.rate`` ``rate``) with
    ``agent.pose_source: odometry``: every frame is tracked as it arrives while the mapper maps keyframes under a
    ``budget`` s keyframe budget (the hand-held profile, no final pass), with the settings of ``variant``
    (:data:`LIVE_VARIANTS`). Returns the share of frames tracked, the tracking time per frame while mapping, how late
    the frames reached the agent against the stream's clock (on time: within one frame period), the loops closed and
    the keyframes mapped."""
    # lazy: the agent (torch, the mapper) loads only for the live measurement
    from gausslite.config import load_config
    from gausslite.mapping.profiles import profile_for_layout, with_profile
    from gausslite.mission import build_mission

    ds = load_dataset(SHARED / "TUM_rgbd_dataset_freiburg1_rpy", downscale=2, undistort=True, interpolate_poses=True,
                      align_depth_time=False, pose_source="given")
    frames = [ds[i] for i in range(len(ds))]  # read first: the stream's clock measures the agent, not the disk
    overrides, background = LIVE_VARIANTS[variant]
    cfg = load_config(None, ["agent.pose_source=odometry", "agent.realtime=true", f"agent.rate={rate}",
                             "agent.downscale=1", "agent.scoring.protocols=[sensor]", "agent.push.every=100000",
                             f"mapper.keyframe_budget_s={budget}", "mapper.performance.render_threads=2",
                             *overrides]).agent
    m = with_profile(cfg.mapper, profile_for_layout("tum")).model_copy(update={"final_iters": 0,
                                                                                "final_iters_per_keyframe": 0.0})
    task = ds.annotations.tasks[0]
    rt = build_mission(cfg, task.text, agent_id="bench", annotations=ds.annotations, task_id=task.id, mapper=m,
                       start=False)
    rt.odometry.background_loops = background
    track_ms, arrivals = [], []
    track, submit = rt.odometry.track, rt.submit

    def timed_track(frame):
        t0 = time.perf_counter()
        out = track(frame)
        track_ms.append(1e3 * (time.perf_counter() - t0))
        return out

    def recorded_submit(frame, *a, **kw):
        arrivals.append((frame.timestamp, time.perf_counter()))
        return submit(frame, *a, **kw)

    rt.odometry.track, rt.submit = timed_track, recorded_submit
    try:
        rt.replay(frames)
        rt.wait_mapped(timeout_s=600)
        st = rt.status()
        iters = [fs.iters for fs in rt.mapper.stats]
    finally:
        rt.close()
    t_data0, t_wall0 = arrivals[0]
    late = [max(0.0, (w - t_wall0) - (t - t_data0) / rate) for t, w in arrivals]
    period = 1.0 / (15.0 * rate)
    return {"variant": variant, "frames": len(frames), "rate": rate, "keyframe_budget_s": budget,
            "loops": st["loop_closures"],
            "tracked_fraction": rt.odometry.n_tracked / len(frames), "lost": rt.odometry.n_failed,
            "track_ms_mean": float(np.mean(track_ms)), "track_ms_p95": float(np.percentile(track_ms, 95)),
            "on_time_fraction": float(np.mean([x <= period for x in late])), "late_s_max": float(max(late)),
            "frames_keyframed": st["frames_keyframed"], "frames_skipped": st["frames_skipped"],
            "iters_per_keyframe": float(np.mean(iters)) if iters else None}


def pose_gains(given_path: Path, odometry_path: Path, protocol: str = "novel", budget: str = "0.5") -> dict:
    """The ROI gain (GaussLite − uniform) of live missions mapped and scored at the odometry's poses against the
    same missions at the given poses: two ``bench.realtime`` results, ``--pose-source given`` and ``--pose-source
    odometry``, of the same scenes, budget and runs. Per scene (a sequence and its task): both gains (the paired
    per-frame means with their 95 % interval, :func:`gausslite.stats.paired_gain`) and ``gain_estimated_minus_given``,
    their difference with the interval of a difference of independent means (half-widths added in quadrature).

    Raises:
        FileNotFoundError: a result file is missing. ValueError: the files share no scene at ``budget``, or the
            second was not run with ``--pose-source odometry``.
    """
    import json

    given, est = (json.loads(Path(p).read_text()) for p in (given_path, odometry_path))
    if est["settings"].get("pose_source") != "odometry" or given["settings"].get("pose_source", "given") != "given":
        raise ValueError(f"{odometry_path} must be a --pose-source odometry run and {given_path} a given-pose run")
    out = {}
    for scene, blk in est["scenes"].items():
        g_blk = given["scenes"].get(scene, {}).get("budgets", {}).get(budget)
        e_blk = blk.get("budgets", {}).get(budget)
        if not g_blk or not e_blk or protocol not in g_blk["protocols"] or protocol not in e_blk["protocols"]:
            continue
        g, e = g_blk["protocols"][protocol], e_blk["protocols"][protocol]
        if g["gain"] is None or e["gain"] is None:
            continue
        hw = [None if v.get("gain_ci") is None else (v["gain_ci"][1] - v["gain_ci"][0]) / 2 for v in (g, e)]
        d = e["gain"] - g["gain"]
        half = None if None in hw else float(np.hypot(*hw))
        out[scene] = {"protocol": protocol, "budget_s": float(budget),
                      "given": {k: g[k] for k in ("gain", "gain_ci", "gain_frames")},
                      "estimated": {k: e[k] for k in ("gain", "gain_ci", "gain_frames")},
                      "roi_psnr": {src: {m: v[m]["roi_psnr"] for m in ("uniform", "gausslite")}
                                   for src, v in (("given", g), ("estimated", e))},
                      "runs": {"given": g["gausslite"].get("runs"), "estimated": e["gausslite"].get("runs")},
                      "gain_estimated_minus_given": {"mean": d, "ci": None if half is None else [d - half, d + half]}}
    if not out:
        raise ValueError(f"{given_path} and {odometry_path} share no scene scored under {protocol} at {budget} s")
    return out


def gains_table(gains: dict) -> str:
    """The Markdown table of :func:`pose_gains`."""
    def cell(v):
        ci = v.get("gain_ci") or v.get("ci")
        m = v.get("gain", v.get("mean"))
        return f"{m:+.2f}" + ("" if not ci else f" [{ci[0]:+.2f}, {ci[1]:+.2f}]")

    rows = ["| scene | ROI PSNR uniform / GaussLite, given poses (dB) | the same, odometry's poses (dB) | gain, given | "
            "gain, odometry's poses | estimated − given |", "|---|---|---|---|---|---|"]
    for scene, r in gains.items():
        p = r["roi_psnr"]
        rows.append(f"| {scene} | {p['given']['uniform']:.2f} / {p['given']['gausslite']:.2f} | "
                    f"{p['estimated']['uniform']:.2f} / {p['estimated']['gausslite']:.2f} | {cell(r['given'])} | "
                    f"{cell(r['estimated'])} | {cell(r['gain_estimated_minus_given'])} |")
    return "\n".join(rows)


def _cm(v) -> str:
    return "—" if v is None else f"{100 * v:.2f}"


def table(results: dict) -> str:
    """The Markdown table of ``results[sequence][variant]``."""
    rows = ["| sequence | variant | frames | size | tracked at | ATE (cm) | ATE online (cm) | RPE (cm / frame) | "
            "RPE (° / frame) | RPE (cm / s) | tracked | lost / re-localised | loops (false) | largest loop error | "
            "ms / frame |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for seq, by_variant in results.items():
        for var, r in by_variant.items():
            pf, ps = r["rpe"]["per_frame"], r["rpe"]["per_second"]
            rot = "—" if pf["rot_rmse_deg"] is None else f"{pf['rot_rmse_deg']:.2f}"
            ms = "—" if r["ms_per_frame"] is None else f"{r['ms_per_frame']:.0f}"
            ts = r["tracked_size"]
            lp = r["loops"]
            worst = ("—" if lp["max_error_m"] is None
                     else f"{100 * lp['max_error_m']:.1f} cm / {lp['max_error_deg']:.1f}°")
            rows.append(f"| {seq} | {var} | {r['frames']} | {r['size'][0]}×{r['size'][1]} | {ts[0]}×{ts[1]} | "
                        f"{_cm(r['ate_rmse_m'])} | {_cm(r['ate_online_m'])} "
                        f"| {_cm(pf['trans_rmse_m'])} | {rot} | {_cm(ps['trans_rmse_m'])} | "
                        f"{100 * r['tracked_fraction']:.0f} % | {r['lost']} / {r['relocalised']} | "
                        f"{lp['accepted']} ({lp['false']}) | {worst} | {ms} |")
    return "\n".join(rows)


def live_table(runs: List[dict]) -> str:
    """The Markdown table of the live measurement: per variant, the mean ± std over its runs (:func:`live`)."""
    rows = ["| live: TUM fr1/rpy at 15 Hz, keyframe budget | variant | runs | tracked | lost | track ms (mean / p95) "
            "| frames on time | latest (s) | loops | keyframes | mapping iterations per keyframe |",
            "|---|---|---|---|---|---|---|---|---|---|---|"]
    for var in dict.fromkeys(r["variant"] for r in runs):
        rs = [r for r in runs if r["variant"] == var]

        def ms(key: str, scale: float = 1.0, digits: int = 0) -> str:  # one run: no spread
            m, sd = mean_std([scale * r[key] for r in rs])
            return fmt(m, sd if len(rs) > 1 else None, digits)

        rows.append(f"| {rs[0]['keyframe_budget_s']} s | {var} | {len(rs)} | {ms('tracked_fraction', 100)} % | "
                    f"{ms('lost')} | {ms('track_ms_mean')} / {ms('track_ms_p95')} | {ms('on_time_fraction', 100)} % | "
                    f"{ms('late_s_max', 1.0, 2)} | {ms('loops', 1.0, 1)} | {ms('frames_keyframed')} | "
                    f"{ms('iters_per_keyframe', 1.0, 1) if all(r.get('iters_per_keyframe') for r in rs) else '–'} |")
    return "\n".join(rows)


#: the loop registrations :func:`loop_accuracy` compares (``LoopConfig.registration`` values)
LOOP_REGISTRATIONS = ("hybrid", "point_to_plane", "icp")


def loop_accuracy(frames: list, registrations=LOOP_REGISTRATIONS) -> dict:
    """How accurately each loop registration (``LoopConfig.registration``) measures the relative pose of the same
    loop candidates: the shipped odometry tracks ``frames`` (the loops it closes move its poses as usual), and every
    candidate pair it tries is also registered, from the same estimated relative pose, by each of
    ``registrations`` alone (gate 2's registration, without the gates). Each error is against the reference poses.

    Returns:
        ``{"candidates": n, "init": stats, <registration>: stats}``, ``stats`` = ``{"median_cm", "median_deg",
        "within_2cm", "within_3cm", "ms_median"}`` (``within_*``: candidates within 2 / 3 cm of the truth).
    """
    from gausslite.odometry import loop_closing, pose_graph  # noqa: PLC0415 - only this measurement wraps them

    truth = {int(f.frame_id): f.c2w for f in frames}
    errs: dict = {k: [] for k in ("init", *registrations)}
    ms: dict = {k: [] for k in registrations}
    shipped = pose_graph.verify_registration

    def err(true: np.ndarray, T: np.ndarray) -> tuple:
        m, deg = relative_error(true, T)
        return 100.0 * m, deg

    def measured(odo, frame, image, target, init, min_fitness, cfg, clouds=None):
        true = np.linalg.inv(truth[int(target.frame_id)]) @ truth[int(frame.frame_id)]
        errs["init"].append(err(true, init))
        for name in registrations:
            t0 = time.perf_counter()
            if name == "icp":
                cl = pose_graph.DepthClouds(odo.config.depth_max_m)
                T = pose_graph._icp(cl.of(frame, cfg.icp_voxel_m), cl.of(target.frame, cfg.icp_voxel_m), init,
                                    cfg.icp_levels_m, cfg)
            else:
                T = odo.register(frame, image, target, init, name)[1]
            ms[name].append(1e3 * (time.perf_counter() - t0))
            errs[name].append(err(true, T))
        return shipped(odo, frame, image, target, init, min_fitness, cfg, clouds)

    loop_closing.verify_registration = measured
    try:
        track(frames, {})
    finally:
        loop_closing.verify_registration = shipped

    def stats(name: str) -> dict:
        e = np.array(errs[name]).reshape(-1, 2)
        out = {"median_cm": float(np.median(e[:, 0])) if len(e) else None,
               "median_deg": float(np.median(e[:, 1])) if len(e) else None,
               "within_2cm": int((e[:, 0] < 2.0).sum()), "within_3cm": int((e[:, 0] < 3.0).sum())}
        if name in ms:
            out["ms_median"] = float(np.median(ms[name])) if ms[name] else None
        return out

    return {"candidates": len(errs["init"]), **{k: stats(k) for k in errs}}


def loop_accuracy_table(acc: dict) -> str:
    """Markdown of :func:`loop_accuracy` per sequence: ``{sequence: result}``."""
    rows = ["| sequence | candidates | registration | median error (cm / °) | within 2 cm | within 3 cm | ms, median |",
            "|---|---|---|---|---|---|---|"]
    for seq, a in acc.items():
        for name in ("init", *[k for k in a if k not in ("candidates", "init")]):
            v = a[name]
            ms = "–" if v.get("ms_median") is None else f"{v['ms_median']:.0f}"
            med = "–" if v["median_cm"] is None else f"{v['median_cm']:.2f} / {v['median_deg']:.2f}"
            label = "estimated poses (start)" if name == "init" else f"`{name}`"
            rows.append(f"| {seq} | {a['candidates']} | {label} | {med} | {v['within_2cm']} | {v['within_3cm']} | {ms} |")
    return "\n".join(rows) + "\n"


def renderings(sequences: List[str], walk_seeds: tuple) -> List[tuple]:
    """``[(name, seed, key)]``: each synthetic walk once per seed of ``walk_seeds``, every other sequence once (seed
    0); ``key`` is the name of its rows, ``<name>_seed<seed>`` for a seed other than 0."""
    return [(name, seed, name + (f"_seed{seed}" if seed else "")) for name in sequences
            for seed in (walk_seeds if name.startswith(WALKS) else (0,))]


def run(sequences: List[str], variants: List[str], synthetic_frames: int, size: tuple, work: Path,
        walk_frames: int = 525, walk_seeds: tuple = (0,)) -> dict:
    """``{sequence: {variant: metrics}}`` (:func:`track`), printing each row as it is measured. A synthetic walk is
    run once per seed of ``walk_seeds``; a seed other than 0 is its own sequence, ``<name>_seed<seed>``."""
    out: dict = {}
    for name, seed, key in renderings(sequences, walk_seeds):
        frames = load_sequence(name, work, synthetic_frames, size, walk_frames, seed)
        out[key] = {}
        for var in variants:
            out[key][var] = track(frames, VARIANTS[var])
            r = out[key][var]
            print(f"{key} {var}: ATE {100 * r['ate_rmse_m']:.2f} cm (online {100 * r['ate_online_m']:.2f}), "
                  f"tracked {100 * r['tracked_fraction']:.0f} %, lost {r['lost']}, re-localised {r['relocalised']}, "
                  f"loops {r['loops']['accepted']} ({r['loops']['false']} false), {r['ms_per_frame']:.0f} ms/frame",
                  flush=True)
    return out


def main(argv: Optional[List[str]] = None) -> int:
    """Entry point: measure, write the JSON and the Markdown table, print the table."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequences", default=",".join(SEQUENCES), help=f"comma-separated, of {', '.join(SEQUENCES)}")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    ap.add_argument("--synthetic-frames", type=int, default=300, help="frames of the synthetic circle")
    ap.add_argument("--synthetic-size", default="320x240", help="WxH of the synthetic circle and walk")
    ap.add_argument("--walk-frames", type=int, default=525, help="frames of the synthetic walk (525: 7 m at 30 fps)")
    ap.add_argument("--walk-seeds", default="0",
                    help="comma-separated renderings of the synthetic walks (seed 0 is the sequence itself)")
    ap.add_argument("--work", type=Path, default=None,
                    help="folder for the rendered synthetic scenes, kept for the next run (default: a temporary one)")
    ap.add_argument("--loop-accuracy", action="store_true",
                    help="instead of the variants: register every loop candidate the shipped odometry tries on each "
                         "sequence with each loop registration, from the same estimate, and report the errors")
    ap.add_argument("--live", action="store_true",
                    help="also stream TUM fr1/rpy at 15 Hz to an agent that tracks every frame while it maps")
    ap.add_argument("--live-budget", type=float, default=0.5, help="the live agent's keyframe budget, seconds")
    ap.add_argument("--live-runs", type=int, default=3, help="runs of each live variant")
    ap.add_argument("--live-variants", default="default", help=f"comma-separated, of {', '.join(LIVE_VARIANTS)}")
    ap.add_argument("--gains", default=None, metavar="GIVEN.json,ODOMETRY.json",
                    help="also compare the ROI gain of live missions at the odometry's poses with the gain at the "
                         "given poses: two bench.realtime results of the same scenes (--pose-source given, then "
                         "odometry), scored under novel")
    ap.add_argument("--out", type=Path, default=RESULTS / "odometry.json")
    args = ap.parse_args(argv)
    gains = None
    if args.gains:
        paths = [Path(p) for p in args.gains.split(",") if p]
        if len(paths) != 2:
            ap.error("--gains takes two files: GIVEN.json,ODOMETRY.json")
        try:
            gains = pose_gains(*paths)
        except (FileNotFoundError, ValueError, KeyError) as e:
            ap.error(f"--gains: {e}")
    seqs = [s for s in args.sequences.split(",") if s]
    variants = [v for v in args.variants.split(",") if v]
    live_variants = [v for v in args.live_variants.split(",") if v]
    bad = ([s for s in seqs if s not in SEQUENCES] + [v for v in variants if v not in VARIANTS]
           + [v for v in live_variants if v not in LIVE_VARIANTS])
    if bad:
        ap.error(f"unknown sequence or variant: {', '.join(bad)}")
    size = tuple(int(v) for v in args.synthetic_size.lower().split("x"))
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    accuracy = None
    with tempfile.TemporaryDirectory(prefix="bench_odometry_") as tmp:
        seeds = tuple(int(v) for v in args.walk_seeds.split(",") if v)
        if args.loop_accuracy:
            results, accuracy = {}, {}
            for name, seed, key in renderings(seqs, seeds):
                frames = load_sequence(name, args.work or Path(tmp), args.synthetic_frames, size, args.walk_frames,
                                       seed)
                accuracy[key] = loop_accuracy(frames)
        else:
            results = run(seqs, variants, args.synthetic_frames, size, args.work or Path(tmp), args.walk_frames,
                          seeds)
    live_result = ([live(1.0, args.live_budget, v) for v in tqdm(live_variants, desc="live variants")
                    for _ in range(args.live_runs)] if args.live else None)
    doc = {"load_average_before": list(load_before), "load_average_after": list(os.getloadavg()),
           "note": "ms_per_frame is wall-clock time on this machine; compare it only with runs at a similar load",
           "variants": {v: VARIANTS[v] for v in variants}, "odometry_defaults": OdometryConfig().model_dump(),
           "sequences": results, **({"live": live_result} if live_result else {}),
           **({"loop_accuracy": accuracy} if accuracy is not None else {}),
           **({"gain_estimated_minus_given": gains, "gains_from": args.gains} if gains else {})}
    details = (f": {time.perf_counter() - t0:.0f} s; load average {load_before[0]:.1f} before, "
               f"{os.getloadavg()[0]:.1f} after (2 cores)")
    md = table(results) if results else ""
    if accuracy:
        md += ("\n\n" if md else "") + loop_accuracy_table(accuracy)
    if live_result:
        md += ("\n\n" if md else "") + live_table(live_result)
    if gains:
        md += "\n\n" + gains_table(gains)
    write_results(args.out, "odometry", argv, details, md, doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
