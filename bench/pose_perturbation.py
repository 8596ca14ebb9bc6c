"""Robustness to pose error: how much of GaussLite's ROI gain over uniform mapping survives SLAM-like poses?

    python -m bench.pose_perturbation [--mode live|offline] [--scenes synthetic_circle,synthetic_walk]
                                      [--levels exact,1cm_0.5deg,3cm_1.5deg[,odometry]] [--seeds 3]
                                      [--modes uniform,gausslite]
                                      [--refine off,on] [--withhold-every K] [--track-iters 20] [--set KEY=VALUE ...]
                                      [--out FILE] [--resume|--fresh] [--max-runs N] [--allow-failed]
                                      live: [--budget 0.5]; offline: [--frames 40] [--jobs 2]

The scenes are rendered, so their poses are exact and the error is known exactly. Every run replaces the frames'
given poses by a SLAM-like estimate (:func:`gausslite.datasets.trajectory.perturb_trajectory` at the level, seeded by
the run's seed; ``exact`` keeps the true poses) and withholds every ``--withhold-every``-th frame (from the middle of
the first block on, :func:`gausslite.datasets.subset.withheld_indices`) from the mapper. GaussLite's relevance is the
task's ground-truth ROI from the frames' TRUE poses (as an image-based detector sees it: no pose in it). Two modes:

**Live** (``--mode live``, the default): what a robot meets. Each run is one live in-process agent mission as
``bench.realtime`` runs it (:func:`bench.realtime.start_mission`: the agent's deployed settings, the scene's sensor
profile, keyframe ingest at the scene's clock, ``--budget`` seconds of wall time per keyframe (0.5 s: the dataset
clock itself), the Gaussian cap, no sharing, **no final pass**) over the scene's whole sequence, its frames streamed at
the perturbed poses. The scenes (:data:`LIVE_SCENES`) are ``bench.realtime``'s at its resolution:

- ``synthetic_circle``: ``bench.realtime``'s scene, the synthetic room along ``make-scene --trajectory circle``, 300
  frames at 320×240 and 30 Hz (10 s), agent_a, task ``synth-pick-object``, cap 6,000;
- ``synthetic_walk``: the room along ``make-scene --trajectory walk`` (525 frames at 320×240 and 30 Hz: a 7 m
  hand-held walk, two loops in front of the desk, 17.5 s), agent_a, same task and cap.

The live level ``odometry`` leaves the given poses aside: the robot tracks itself with its own RGB-D odometry
(``agent.pose_source: odometry``, from the first frame's pose, exact at every level), the runtime withholds the frames
(tracked, not mapped), and the map is scored at the odometry's estimates (its pose error is the odometry's).

Every 10th frame is withheld by default (``bench.realtime``'s ``novel`` protocol). The missions are wall-clock
measurements: they run one at a time in this process, each map scored right after its mission ended, and nothing else
should run on the machine. Each run records its mission (``mission``: :func:`bench.realtime.mission_settings`), its
keyframes and iterations per keyframe, the resolution it mapped at (the map is scored there; only seeds whose two
modes mapped at the same resolution are paired) and how it ended (below). ``--set`` takes agent config keys
(``mapper.seeding.rho=0.5``).

**Offline** (``--mode offline``): every run maps a sparse sequence OFFLINE (:func:`gausslite.pipeline.run_mapping`:
fixed iteration counts, the sensor profile's defaults and final pass, one rasterizer thread, no time budget), on
``--jobs`` worker processes. The scenes (:data:`SCENES`) at 160×120:

- ``synthetic_circle``: ``bench.realtime``'s scene loaded at 160×120; the sequence is ``--frames`` frames spread
  evenly over it (every 7th frame for 40: 280 of its 300 frames, about 10 m of path).
- ``synthetic_walk``: the walk rendered at 160×120 (525 frames), agent_a, same task; every 13th frame for 40.

Every 5th sequence frame is withheld by default. ``--set`` takes mapper config keys (``seeding.rho=0.5``).

Scoring (docs/realtime.md "Scoring protocols", :func:`gausslite.evaluation.score_live_map`), the same in both modes. A
robot uses the map at the pose its SLAM gives it, so the withheld frames are scored under the ``novel`` protocol: at
each frame's GIVEN (perturbed) pose with the map's learned pose correction interpolated in frame id between the
keyframes on either side (:func:`gausslite.evaluation.predicted_view`; the identity without pose refinement). Nothing
is fitted on a withheld frame, and the true pose is never used to place the camera. The ROI scored is the ground
truth's, from the true pose (a property of the image, :class:`gausslite.datasets.subset.EstimatedPoses`). The gains
and the fraction kept are taken from this figure: how good the map is where the robot uses it. Two more figures answer
other questions:

- ``true_pose``: the same render and exposure with the camera at the frame's TRUE pose: the map's absolute accuracy,
  whether its content sits where it is in the world, as a user localised independently of this robot's SLAM (another
  robot, a motion-capture system) sees it. A map built at drifting poses, or whose refinement moved its gauge, is
  misplaced against the world and loses here even where its own robot sees it right.
- ``keyframes``: the mapped frames (live: the keyframes) at their own refined pose: what the map memorised.

Variants: ``--refine off`` maps at the given poses as they are (the profile's setting; the rendered profile does not
refine); ``on`` sets ``pose.refine=true`` and ``pose.track_iters=N`` (the map's keyframe pose refinement and
per-frame tracking, docs/mapper.md "Pose refinement"; live: ``mapper.pose.*``). Per (scene, level, refine): each
mode's ROI PSNR (mean ± std over seeds); the gain GaussLite − uniform, paired frame by frame within a seed and
run-clustered over the seeds (the mean of the per-seed gains with its 95 % Student-t interval,
:func:`gausslite.stats.paired_gain`; significant when the interval excludes zero); and the fraction of the exact-pose
gain kept (the level's gain at the predicted pose over the exact level's, same refine setting). The seed drives both
the perturbation and the mapper.

Failed missions (live; :mod:`bench._missions`): every live run records ``end_state``, ``error``, ``frames_failed`` and
``corrections_rejected``. A run whose mission failed (not ``FINISHED``, or frames that failed to
map) keeps whatever it scored (or ``score_error``), is left out of every mean and gain (its row lists it under
``failed_runs`` and is marked †), and the command exits 1 once the result is written unless ``--allow-failed``;
``--resume`` runs it again.

Writes ``bench/results/pose_perturbation_live.json`` (live) or ``pose_perturbation.json`` (offline) (``--out``;
through ``bench/_results.py``), ``.md`` and ``.png`` (gain and ROI PSNR against the level). After each run the runs so
far go to ``<out>.partial.json``; ``--resume`` runs only the missing ones (offline runs are deterministic per seed);
``--max-runs N`` stops after N runs and leaves the partial file for the next ``--resume`` (a long run in short
chunks). The results are written once no run is missing; the partial file is then removed, unless a mission failed
(``--resume`` runs those again).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from bench._missions import (FAILED_MARK, add_allow_failed, exit_code, failed, failed_note, failure_rows,
                             mission_outcome, succeeded)
from bench.realtime import scenes as realtime
from bench.realtime.missions import mission_settings, start_mission
from bench.realtime.protocol import check_withheld, novel_ids, training_frames
from bench._results import write_results
from bench.long_mission import load_partial
from gausslite.config import load_mapper_config
from gausslite.datasets.subset import EstimatedPoses, FrameSubset, ScaledFrames, withheld_indices
from gausslite.datasets.trajectory import POSE_ERROR_LEVELS, perturb_trajectory, pose_error_stats
from gausslite.evaluation import NOVEL_EVERY, score_live_map
from gausslite.pipeline import run_mapping
from gausslite.stats import fmt, fmt_gain, mean_std, paired_gain, significant
from gausslite.synthetic import make_scene

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"

#: the scenes: where they come from, their load resolution and task, and the step between sequence frames
SCENES = {
    "synthetic_circle": {"source": "realtime", "downscale": 2.0, "task": realtime.SCENES["synthetic_circle"]["task"]},
    "synthetic_walk": {"source": "walk", "frames": 525, "width": 160, "height": 120, "downscale": 1.0,
                       "task": "synth-pick-object"},
}
#: the live mode's scenes (``bench.realtime``'s resolution, clock and cap): the trajectory rendered, its frames, size
#: (pixels) and Gaussian cap, the task; the whole sequence streams at its 30 Hz clock
LIVE_SCENES = {
    "synthetic_circle": {"trajectory": "circle", "frames": realtime.SCENES["synthetic_circle"]["frames"],
                         "width": realtime.SCENES["synthetic_circle"]["width"],
                         "height": realtime.SCENES["synthetic_circle"]["height"],
                         "cap": realtime.SCENES["synthetic_circle"]["cap"],
                         "task": realtime.SCENES["synthetic_circle"]["task"]},
    "synthetic_walk": {"trajectory": "walk", "frames": 525, "width": 320, "height": 240, "cap": 6000,
                       "task": "synth-pick-object"},
}
#: how the benchmark maps: live agent missions under a keyframe budget, or offline at fixed iterations
RUN_MODES = ("live", "offline")
LEVELS = tuple(POSE_ERROR_LEVELS)
#: the live level whose robot tracks itself (``agent.pose_source: odometry``, from the first frame's pose, which every
#: level keeps exact): its map's given poses are the odometry's estimates, its withheld frames tracked but not mapped
ODOMETRY = "odometry"
MODES = ("uniform", "gausslite")
#: the fields that name a run (a job or its result)
RUN_KEYS = ("scene", "level", "refine", "mode", "seed")
#: tracking steps per frame of the refine variant (docs/results.md measured tracking with 20)
TRACK_ITERS = 20
#: how the withheld frames are scored (kept with the runs: a partial file scored otherwise is not resumed)
SCORING = ("withheld frames under the novel protocol: the given pose with the map's correction interpolated from its "
           "keyframes (also at the true pose, for the map's absolute accuracy)")


def scene_path(name: str, work: Path) -> Path:
    """The sequence folder (agent_a) of a bench scene, rendered into ``work`` once."""
    spec = SCENES[name]
    if spec["source"] == "realtime":
        return realtime.scene_path(name, work)
    out = work / f"synthetic_walk_{spec['frames']}_{spec['width']}x{spec['height']}"
    if not (out / "agent_a" / "results" / f"depth{spec['frames'] - 1:06d}.png").exists():
        make_scene(out, frames=spec["frames"], width=spec["width"], height=spec["height"], trajectory="walk",
                   agents=("agent_a",))
    return out / "agent_a"


def live_scene_path(name: str, work: Path) -> Path:
    """The sequence folder (agent_a) of a live scene (:data:`LIVE_SCENES`), rendered into ``work`` once (the circle
    into the folder ``bench.realtime`` renders it to, ``synthetic_circle_<frames>_<w>x<h>``)."""
    spec = LIVE_SCENES[name]
    out = Path(work) / f"synthetic_{spec['trajectory']}_{spec['frames']}_{spec['width']}x{spec['height']}"
    if not (out / "agent_a" / "results" / f"depth{spec['frames'] - 1:06d}.png").exists():
        agents = {} if spec["trajectory"] == "circle" else {"agents": ("agent_a",)}  # the circle as bench.realtime's
        make_scene(out, frames=spec["frames"], width=spec["width"], height=spec["height"],
                   trajectory=spec["trajectory"], **agents)
    return out / "agent_a"


def sequence(n_total: int, frames: int, withhold_every: int) -> tuple[list[int], list[int]]:
    """``(mapped, withheld)`` dataset indices: ``frames`` indices spread evenly over ``n_total`` (step
    ``n_total // frames``), every ``withhold_every``-th of them withheld (:func:`withheld_indices`).

    Raises:
        ValueError: fewer than ``frames`` frames, or ``frames < 2``.
    """
    if frames < 2 or n_total < frames:
        raise ValueError(f"need 2 <= frames <= {n_total}, got {frames}")
    idx = list(range(0, (n_total // frames) * frames, n_total // frames))
    held = {idx[j] for j in withheld_indices(len(idx), withhold_every)}
    return [i for i in idx if i not in held], sorted(held)


@dataclasses.dataclass
class MappedSequence:
    """One run's map and what scoring it needs.

    Attributes:
        mapper: the :class:`~gausslite.mapping.mapper.Mapper` after mapping (its pose corrections, if any).
        frames: the sequence's frames in order (mapped and withheld), at their TRUE poses.
        given: frame id → (4, 4) float64 camera-to-world pose the robot gives (the perturbed estimate; metres,
            OpenCV camera axes): the mapper's input for the mapped frames, the robot's pose at the withheld ones.
        mapped_ids / withheld_ids: frame ids mapped / withheld from the mapper.
        annotations: the scene's annotations (the task's ground-truth ROI).
        wall_s: seconds the mapping took.
    """

    mapper: object
    frames: list
    given: dict
    mapped_ids: list
    withheld_ids: list
    annotations: object
    wall_s: float


def _map(job: dict, ds, profile, mapped: list[int], est_by_id: dict):
    """Map the ``mapped`` frames of ``ds`` at the poses ``est_by_id`` (frame id -> c2w) with the job's settings."""
    view = EstimatedPoses(FrameSubset(ds, [i for i in range(len(ds)) if i not in set(mapped)]), est_by_id)
    overrides = list(job["overrides"])
    if job["refine"]:
        overrides += ["pose.refine=true", f"pose.track_iters={job['track_iters']}"]
    cfg = load_mapper_config(None, overrides, defaults=dict(profile.mapper), mode=job["mode"], seed=job["seed"],
                             performance={"render_threads": 1})
    task = SCENES[job["scene"]]["task"]
    mapper, _ = run_mapping(view, cfg, task_id=task, relevance_fn=view.roi_fn(ds.annotations, task), progress=False)
    return mapper


def map_sequence(job: dict) -> MappedSequence:
    """Map one job's sequence (``scene``, ``path``, ``level``, ``refine``, ``mode``, ``seed``, ``frames``,
    ``withhold_every``, ``track_iters``, ``overrides``) at poses perturbed to the job's level (seeded by its seed),
    its withheld frames left out of the mapper."""
    spec = SCENES[job["scene"]]
    ds, profile = realtime.load_scene({"downscale": spec["downscale"]}, Path(job["path"]))
    mapped, held = sequence(len(ds), job["frames"], job["withhold_every"])
    frames = [ds[i] for i in sorted(mapped + held)]
    est = perturb_trajectory(np.stack([fr.c2w for fr in frames]), job["level"], seed=job["seed"])
    given = {int(fr.frame_id): est[k] for k, fr in enumerate(frames)}
    mapped_ids, held_ids = [int(ds[i].frame_id) for i in mapped], [int(ds[i].frame_id) for i in held]
    t0 = time.perf_counter()
    mapper = _map(job, ds, profile, mapped, {fid: given[fid] for fid in mapped_ids})
    return MappedSequence(mapper, frames, given, mapped_ids, held_ids, ds.annotations, time.perf_counter() - t0)


def score_sequence(run: MappedSequence, task: str) -> dict:
    """Score a mapped sequence (docs/realtime.md "Scoring protocols"): the withheld frames under ``novel``, at the
    pose the robot would use (the given pose with the map's correction interpolated from its keyframes,
    :func:`gausslite.evaluation.predicted_view`; nothing fitted on the frame), the same renders with the camera at
    the TRUE pose instead (the map's absolute accuracy), and the mapped frames under ``keyframes`` (their own refined
    pose). The ROI of every score is the task's ground truth from the true pose.

    Returns:
        ``{"novel", "true_pose", "keyframes"}``: :func:`gausslite.evaluation.score_live_map`'s figures of each
        (``roi_psnr`` dB or None, ``psnr``, ``roi_psnr_per_frame`` frame id → dB, …), and ``"views"``: withheld frame
        id → the :class:`~gausslite.evaluation.TrackedView` it was rendered at under ``novel`` (its ``c2w`` the
        predicted pose, ``rot_deg`` / ``trans_m`` the correction away from the given pose).
    """
    at_given = EstimatedPoses(run.frames, run.given)  # the frames at the robot's poses; the ROI from the true ones
    frames = [at_given[k] for k in range(len(at_given))]
    roi_fn = at_given.roi_fn(run.annotations, task)
    views: dict = {}
    res = score_live_map(run.mapper, frames, roi_fn, protocols=("novel", "keyframes"), novel_ids=run.withheld_ids,
                         predicted=views)
    # the same exposure, the camera at the truth (the offsets from the given pose are not read for rendering)
    true = {int(fr.frame_id): np.asarray(fr.c2w, np.float64) for fr in run.frames}
    at_truth = {fid: dataclasses.replace(v, c2w=true[fid].copy(), rot_deg=math.nan, trans_m=math.nan)
                for fid, v in views.items()}
    truth = score_live_map(run.mapper, frames, roi_fn, protocols=("novel",), novel_ids=run.withheld_ids,
                           novel_views=at_truth)["novel"]
    return {"novel": res["novel"], "true_pose": truth, "keyframes": res["keyframes"], "views": views}


def run_one(job: dict) -> dict:
    """Map one (scene, level, refine, mode, seed) OFFLINE at perturbed poses and score it (:func:`figures`; a
    worker)."""
    torch.set_num_threads(1)
    run = map_sequence(job)
    return figures(job, run, SCENES[job["scene"]]["task"])


def figures(job: dict, run: MappedSequence, task: str) -> dict:
    """The figures of one mapped sequence: its scores (:func:`score_sequence`: ``roi_psnr`` / ``psnr`` and their
    ``_per_frame`` under ``novel``, the same with ``_true_pose`` and ``_keyframes``, dB) and the pose errors
    (:func:`gausslite.datasets.trajectory.pose_error_stats`: the given poses, the mapped frames' given poses and their
    poses after mapping, the withheld frames' predicted poses, each against the truth), the correction the map applied
    to the withheld frames (mean ``rot_deg`` degrees, ``trans_m`` metres), counts and timing (``s_per_frame``: mean
    seconds per mapped frame, None without one).

    Raises:
        ValueError: no withheld or no mapped frame (nothing to score or to compare).
    """
    mapper, true = run.mapper, {int(fr.frame_id): fr.c2w for fr in run.frames}
    if not run.withheld_ids or not run.mapped_ids:
        raise ValueError(f"{len(run.mapped_ids)} mapped and {len(run.withheld_ids)} withheld frames: nothing to score")
    sc = score_sequence(run, task)
    views, order = sc["views"], sorted(true)

    def err(ids, poses):
        return pose_error_stats(np.stack([poses[i] for i in ids]), np.stack([true[i] for i in ids]))

    after_map = {i: mapper.pose_of(i, run.given[i]) for i in run.mapped_ids}
    held = sorted(views)
    out = {k: job[k] for k in RUN_KEYS}
    for name, key in (("", "novel"), ("_true_pose", "true_pose"), ("_keyframes", "keyframes")):
        out.update({f"roi_psnr{name}": sc[key]["roi_psnr"], f"psnr{name}": sc[key]["psnr"],
                    f"roi_psnr{name}_per_frame": sc[key]["roi_psnr_per_frame"]})
    secs = [s.seconds for s in mapper.stats]
    return {**out, "scored_at": "predicted pose (novel protocol)",
            "correction_withheld": {"rot_deg": float(np.mean([views[i].rot_deg for i in held])),
                                    "trans_m": float(np.mean([views[i].trans_m for i in held]))},
            "pose_error": err(order, run.given), "pose_error_mapped": err(run.mapped_ids, run.given),
            "pose_error_after_map": err(run.mapped_ids, after_map),
            "pose_error_predicted": err(held, {i: views[i].c2w for i in held}),
            "n_mapped": len(run.mapped_ids), "n_withheld": len(held), "n_roi_withheld": sc["novel"]["roi_frames"],
            "n_gaussians": len(mapper.model), "s_per_frame": float(np.mean(secs)) if secs else None,
            "wall_s": run.wall_s}


def live_job(job: dict) -> dict:
    """The ``bench.realtime`` job (:func:`bench.realtime.start_mission`) of one live run of this bench: its scene
    (``job["path"]``, the scene's ``cap`` and ``task``), ``mode``, keyframe ``budget`` (s), the seed as its ``run``,
    the withheld frames (``novel_every``) and its overrides: with ``refine``, ``mapper.pose.refine=true`` and
    ``mapper.pose.track_iters``, then ``job["overrides"]``."""
    refine = ["mapper.pose.refine=true", f"mapper.pose.track_iters={job['track_iters']}"] if job["refine"] else []
    spec = LIVE_SCENES[job["scene"]]
    if job["level"] == ODOMETRY:
        # the runtime withholds the frames itself, so that its odometry still tracks them in order, unmapped
        source = ["agent.pose_source=odometry", f"agent.scoring.novel_every={job['withhold_every']}",
                  "agent.scoring.protocols=[sensor,novel]"]
    else:  # the bench withholds the frames itself (training_frames): the agent's replay streams every other one
        source = ["agent.scoring.protocols=[sensor]"]
    return {"scene": job["scene"], "spec": {"kind": "synthetic"}, "path": job["path"], "task": spec["task"],
            "mode": job["mode"], "budget": job["budget"], "run": job["seed"], "cap": spec["cap"], "clock": "scaled",
            "novel_every": job["withhold_every"], "pose_source": "odometry" if job["level"] == ODOMETRY else "given",
            "overrides": [*source, *refine, *job["overrides"]]}


def live_one(job: dict) -> dict:
    """One live run: the scene's whole sequence streamed at perturbed poses to a live in-process agent mission as
    ``bench.realtime`` runs it (:func:`live_job`; the agent's deployed settings, keyframe ingest at the scene's clock,
    ``job["budget"]`` s per keyframe, the cap, no final pass, no push), every ``job["withhold_every"]``-th frame
    withheld, then the map scored at the resolution it mapped at (:func:`figures`).

    Args:
        job: ``scene`` (a :data:`LIVE_SCENES` name), ``path`` (its rendered sequence), ``level``, ``refine``, ``mode``,
            ``seed``, ``budget``, ``withhold_every``, ``track_iters``, ``overrides`` (agent config keys).
    Returns:
        :func:`figures`'s record with ``run_mode: "live"``, the mission's ``end_state``, ``error``,
        ``frames_failed``, ``corrections_rejected`` (:func:`bench._missions.mission_outcome`), ``keyframes``,
        ``keyframe_iters``, ``idle_iters``, ``iters_per_keyframe``, ``frames_sent``, ``mapping_downscale``,
        ``mission`` (:func:`bench.realtime.mission_settings`) and ``wall_s`` (the mission's seconds). A failed mission
        is recorded, not raised; when its map cannot be scored, ``score_error`` replaces the figures.
    """
    mjob = live_job(job)
    rate = realtime.REFERENCE_BUDGET_S / job["budget"]
    poses: dict = {}
    odometry = job["level"] == ODOMETRY

    def relevance(ds, ann, task):
        """The task's ground-truth ROI from the true poses; the frames' poses perturbed (kept in ``poses``; the true
        ones for the odometry, which reads only the first)."""
        true = np.stack([ds[i].c2w for i in range(len(ds))])
        est = true if odometry else perturb_trajectory(true, job["level"], seed=job["seed"])
        poses["given"] = {int(ds[i].frame_id): est[i] for i in range(len(ds))}
        poses["view"] = EstimatedPoses(ds, poses["given"])
        return poses["view"].roi_fn(ann, task.id)

    ds, ann, task, rt, _ = start_mission(mjob, rate, relevance=relevance)
    train = poses["view"] if odometry else training_frames(mjob, poses["view"])
    t0 = time.perf_counter()
    try:
        rt.replay(train).join()
        rt.finish(push=False, evaluate=False)
        wall = time.perf_counter() - t0
        outcome = mission_outcome(rt.status())
        factor = float(rt.resolution.factor)
        rs = rt.resolution.status()
        mjob["resolution"] = {"downscale": factor, "size": [rs["mapping_width"], rs["mapping_height"]],
                              "native_size": list(rt.resolution.native) if rt.resolution.native else None,
                              "changes": int(rt.resolution.changes)}
        mjob["rate"] = rate
        live = {"run_mode": "live", **outcome, "keyframes": int(rt.frames_keyframed),
                "keyframe_iters": int(rt.keyframe_iterations), "idle_iters": int(rt.idle_iterations),
                "iters_per_keyframe": rt.keyframe_iterations / max(1, rt.frames_keyframed),
                "frames_sent": int(rt.frames_received), "mapping_downscale": factor,
                "mission": mission_settings(mjob, rt.mapper.cfg, rt.keyframe_iterations / max(1, rt.frames_keyframed))}
    finally:
        rt.close()
    mapper = rt.mapper
    frames = ScaledFrames(ds, factor) if factor != 1 else ds  # scored at the resolution the mission mapped at
    frames, given, held = [frames[i] for i in range(len(frames))], poses["given"], novel_ids(mjob, ds) or []
    if odometry:  # the map's poses are the odometry's; a frame it lost has none and is not scored
        given = {int(k): np.asarray(v, np.float64) for k, v in rt.estimated_poses.items()}
        frames, held = [f for f in frames if int(f.frame_id) in given], [i for i in held if i in given]
        live["frames_estimated"] = len(given)
    mapped = sorted(int(s.frame_id) for s in mapper.stats)
    check_withheld(held, mapped, mapper.roi_views.frame_ids)
    run = MappedSequence(mapper, frames, given, mapped, held, ann, wall)
    if not failed(live):
        return {**figures(job, run, task.id), **live}
    try:  # what is left of a failed mission's map, for the record: it is never averaged
        return {**figures(job, run, task.id), **live}
    except Exception as e:
        return {**{k: job[k] for k in RUN_KEYS}, **live, "wall_s": wall, "score_error": f"{type(e).__name__}: {e}"}


#: the per-run figures a summary row gives per mode (mean and std over seeds)
MODE_FIGURES = ("roi_psnr", "psnr", "roi_psnr_true_pose", "psnr_true_pose", "roi_psnr_keyframes", "n_gaussians",
                "s_per_frame")
#: the live runs' further figures per mode (rows of offline runs leave them out)
LIVE_FIGURES = ("keyframes", "iters_per_keyframe", "mapping_downscale")
#: the gains of a summary row: key → the per-frame figure paired (GaussLite − uniform)
GAINS = {"gain": "roi_psnr_per_frame", "gain_true_pose": "roi_psnr_true_pose_per_frame",
         "gain_keyframes": "roi_psnr_keyframes_per_frame"}


def _pose_rows(row: dict, rs: list[dict], by: dict) -> None:
    """The pose errors of a summary row (mean and std over seeds), in place: the given poses' (of the uniform runs:
    both modes draw the same), and per mode the mapped frames' poses after mapping, the withheld frames' predicted
    poses against the truth and the correction the map applied to the withheld frames' given poses."""
    pe = [r["pose_error"] for r in rs if r["mode"] == "uniform"] or [r["pose_error"] for r in rs]
    for k in ("ate_m", "rot_rmse_deg", "trans_rmse_m", "trans_max_m"):
        row[k], row[k + "_std"] = mean_std([p[k] for p in pe])
    for m in MODES:
        runs = list(by[m].values())
        for what in ("after_map", "predicted"):
            for k in ("ate_m", "rot_rmse_deg", "trans_rmse_m"):
                row[f"{m}_{what}_{k}"], row[f"{m}_{what}_{k}_std"] = mean_std(
                    [r[f"pose_error_{what}"][k] for r in runs])
        for k in ("rot_deg", "trans_m"):
            row[f"{m}_correction_{k}"], row[f"{m}_correction_{k}_std"] = mean_std(
                [r["correction_withheld"][k] for r in runs])


def summary_row(rs: list[dict], seeds: list[int]) -> dict:
    """One cell's summary (the runs ``rs`` of one scene, refine setting and level): each mode's figures (mean ±
    std over seeds), the pose errors, and the gains GaussLite − uniform of :data:`GAINS` (paired frame by frame within
    a seed, run-clustered over the seeds that ran both modes: :func:`gausslite.stats.paired_gain`). Runs whose
    mission failed (:func:`bench._missions.failed`) are left out and listed under ``failed_runs``; a seed whose two
    modes mapped at different resolutions (live) is not paired (``unpaired_seeds``)."""
    bad = failure_rows(rs, ("mode", "seed"))
    rs = succeeded(rs)
    by = {m: {r["seed"]: r for r in rs if r["mode"] == m} for m in MODES}
    both = [s for s in seeds if all(s in by[m] for m in MODES)]
    res = {s: {by[m][s].get("mapping_downscale", 1.0) for m in MODES} for s in both}
    row: dict = {"seeds": [s for s in both if len(res[s]) == 1]}
    if len(row["seeds"]) < len(both):
        row["unpaired_seeds"] = [s for s in both if len(res[s]) > 1]
    if bad:
        row["failed_runs"] = bad
    live = [k for k in LIVE_FIGURES if any(k in r for r in rs)]
    for m in MODES:
        for k in (*MODE_FIGURES, *live):
            row[f"{m}_{k}"], row[f"{m}_{k}_std"] = mean_std([by[m][s].get(k) for s in by[m]])
    _pose_rows(row, rs, by)
    for key, field in GAINS.items():
        g = paired_gain([by["gausslite"][s][field] for s in row["seeds"]],
                        [by["uniform"][s][field] for s in row["seeds"]])
        row[key] = {**g, "significant": significant(g)}
    return row


def summarise(runs: list[dict], scenes: list[str], levels: list[str], refines: list[bool], seeds: list[int]) -> dict:
    """Per scene, refine setting and level: :func:`summary_row`, and the fraction of the exact level's gain each level
    keeps (``gain_kept`` at the predicted pose, ``gain_true_pose_kept`` at the true one; same refine setting; None
    when the exact gain is not positive)."""
    out: dict = {}
    for scene in scenes:
        for refine in refines:
            block = {level: summary_row([r for r in runs if r["scene"] == scene and r["refine"] == refine
                                         and r["level"] == level], seeds) for level in levels}
            for key in ("gain", "gain_true_pose"):
                ref = block.get("exact", {}).get(key, {}).get("gain")
                for row in block.values():
                    g = row[key]["gain"]
                    row[key + "_kept"] = g / ref if ref is not None and ref > 0 and g is not None else None
            out.setdefault(scene, {})["refine_on" if refine else "refine_off"] = block
    return out


def _cm_deg(r: dict, prefix: str) -> str:
    """``"2.07 cm, 0.50°"``: a summary row's unaligned position RMSE and rotation RMSE under ``prefix``."""
    if r.get(prefix + "trans_rmse_m") is None:
        return "–"
    return f"{100 * r[prefix + 'trans_rmse_m']:.2f} cm, {r[prefix + 'rot_rmse_deg']:.2f}°"


def table(summary: dict) -> str:
    """The Markdown table of :func:`summarise`'s result: ROI PSNR of the withheld frames at the predicted pose (the
    ``novel`` protocol) and the gain with its 95 % run-clustered interval, then the same at the true pose, then the
    gain on the keyframes."""
    lines = ["| scene | pose refine | level | given poses: ATE / rot / unaligned RMSE | withheld frames' predicted "
             "pose vs truth, uniform / GaussLite | uniform ROI PSNR | GaussLite ROI PSNR | gain (GaussLite − uniform) "
             "[95 % CI] | exact gain kept | at the true pose: uniform / GaussLite | gain at the true pose [95 % CI] "
             "| gain on keyframes |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for scene, by_refine in summary.items():
        for rkey, block in by_refine.items():
            for level, r in block.items():
                err = (f"{100 * r['ate_m']:.2f} cm / {r['rot_rmse_deg']:.2f}° / {100 * r['trans_rmse_m']:.2f} cm"
                       if r["ate_m"] is not None else "–")
                g = fmt_gain(r["gain"]) + (" (sig.)" if r["gain"]["significant"] else "")
                gt = fmt_gain(r["gain_true_pose"]) + (" (sig.)" if r["gain_true_pose"]["significant"] else "")
                kept = "–" if r["gain_kept"] is None else f"{100 * r['gain_kept']:.0f} %"
                pred = " / ".join(_cm_deg(r, f"{m}_predicted_") for m in MODES)
                at_true = " / ".join(fmt(r[f"{m}_roi_psnr_true_pose"], r[f"{m}_roi_psnr_true_pose_std"])
                                     for m in MODES)
                mark = f" {FAILED_MARK}" if r.get("failed_runs") else ""
                lines.append(f"| {scene} | {rkey.split('_')[1]} | {level}{mark} | {err} | {pred} | "
                             f"{fmt(r['uniform_roi_psnr'], r['uniform_roi_psnr_std'])} | "
                             f"{fmt(r['gausslite_roi_psnr'], r['gausslite_roi_psnr_std'])} | {g} | {kept} | "
                             f"{at_true} | {gt} | {fmt_gain(r['gain_keyframes'])} |")
    if any(r.get("failed_runs") for by_refine in summary.values() for block in by_refine.values()
           for r in block.values()):
        lines += ["", failed_note("level with a run")]
    return "\n".join(lines)


def plot(summary: dict, path: Path) -> None:
    """ROI gain (left, with its 95 % interval) and each mode's ROI PSNR (right) of the withheld frames at the
    predicted pose against the pose error level, per scene and refine setting."""
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    styles = {"refine_off": "-", "refine_on": "--"}
    for k, (scene, by_refine) in enumerate(summary.items()):
        for rkey, block in by_refine.items():
            levels = list(block)
            x = np.arange(len(levels)) + 0.04 * k
            lab = f"{scene}, refine {rkey.split('_')[1]}"
            g = [np.nan if block[lv]["gain"]["gain"] is None else block[lv]["gain"]["gain"] for lv in levels]
            e = [0.0 if block[lv]["gain"]["half_width"] is None else block[lv]["gain"]["half_width"]
                 for lv in levels]
            axes[0].errorbar(x, g, yerr=e, ls=styles[rkey], marker="o", capsize=3, color=f"C{k}", label=lab)
            for m, mk in (("uniform", "s"), ("gausslite", "o")):
                v = [np.nan if block[lv][f"{m}_roi_psnr"] is None else block[lv][f"{m}_roi_psnr"] for lv in levels]
                axes[1].plot(x, v, ls=styles[rkey], marker=mk, color=f"C{k}", label=f"{lab}, {m}")
    for ax, ylab in zip(axes, ("ROI gain GaussLite − uniform [dB]", "ROI PSNR at the predicted pose [dB]")):
        ax.set_xticks(np.arange(len(levels)), levels)
        ax.set_xlabel("pose error level (ATE_rotation)")
        ax.set_ylabel(ylab)
        ax.grid(alpha=0.3)
    axes[0].axhline(0.0, color="grey", lw=0.8)
    axes[0].legend(fontsize=7)
    axes[1].legend(fontsize=6, ncol=2)
    fig.suptitle("Withheld views at the predicted pose (given pose + the map's interpolated correction); "
                 "gain: mean and 95 % interval over seeds", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _parser() -> argparse.ArgumentParser:
    """The command line of ``python -m bench.pose_perturbation``."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=RUN_MODES, default="live",
                    help="live: live agent missions under a keyframe budget, as bench.realtime runs them (default); "
                         "offline: a sparse sequence mapped at fixed iterations per frame, no time budget")
    ap.add_argument("--scenes", default=",".join(SCENES), help="comma list of " + ", ".join(SCENES))
    ap.add_argument("--levels", default=",".join(LEVELS),
                    help=f"comma list of pose error levels ('exact', '<x>cm_<y>deg'; live also '{ODOMETRY}': the "
                         "robot tracks itself with its RGB-D odometry instead of using the given poses)")
    ap.add_argument("--seeds", type=int, default=3, help="seeds per cell (default 3)")
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--refine", default="off,on", help="pose refinement variants: off, on or off,on (default)")
    ap.add_argument("--budget", type=float, default=realtime.REFERENCE_BUDGET_S,
                    help="live: seconds of wall time per keyframe (default 0.5, the scene's own clock)")
    ap.add_argument("--frames", type=int, default=40,
                    help="offline: frames per sequence, spread over the scene (default 40)")
    ap.add_argument("--withhold-every", type=int, default=None, metavar="K",
                    help=f"withhold every k-th frame (default: live {NOVEL_EVERY}, every frame of the sequence as "
                         "bench.realtime; offline 5, every sequence frame)")
    ap.add_argument("--track-iters", type=int, default=TRACK_ITERS, help="pose.track_iters of the refine variant")
    ap.add_argument("--jobs", type=int, default=None,
                    help="offline: worker processes (default 2, one rasterizer thread each); live missions run one at "
                         "a time")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override for every run: live, an agent key (mapper.seeding.rho=0.5); offline, a "
                         "mapper key (seeding.rho=0.5)")
    ap.add_argument("--work", type=Path, default=REPO / "runs" / "bench_pose_perturbation", help="rendered scenes")
    ap.add_argument("--out", type=Path, default=None,
                    help="result file (default bench/results/pose_perturbation_live.json live, "
                         "pose_perturbation.json offline)")
    ap.add_argument("--resume", action="store_true", help="keep the runs of <out>.partial.json, run the missing ones "
                    "(and the failed ones again)")
    ap.add_argument("--fresh", action="store_true", help="discard an existing <out>.partial.json")
    ap.add_argument("--max-runs", type=int, default=None, metavar="N",
                    help="run at most N of the missing runs, then stop (continue with --resume); the results are "
                    "written once none is missing")
    add_allow_failed(ap)
    return ap


def _jobs(args: argparse.Namespace, scenes: list[str], levels: list[str], refines: list[bool], modes: list[str],
          seeds: list[int]) -> list[dict]:
    """One job per (scene, level, refine, mode, seed), the scenes rendered first (``args.mode``'s scenes)."""
    live = args.mode == "live"
    paths = {s: str(live_scene_path(s, args.work) if live else scene_path(s, args.work)) for s in scenes}
    common = {"withhold_every": args.withhold_every, "track_iters": args.track_iters, "overrides": args.overrides,
              **({"budget": args.budget} if live else {"frames": args.frames})}
    return [{"scene": s, "path": paths[s], "level": lv, "refine": rf, "mode": m, "seed": sd, **common}
            for s in scenes for lv in levels for rf in refines for sd in seeds for m in modes]


def _key(r: dict) -> tuple:
    return tuple(r[k] for k in RUN_KEYS)


def _settings(args: argparse.Namespace) -> dict:
    """The settings a partial file is resumed with: the offline ones as before the live mode, the live ones with
    ``mode``, ``budget`` and the live scenes' specs."""
    base = {k: getattr(args, k) for k in ("withhold_every", "track_iters", "overrides")}
    if args.mode == "offline":
        return {"frames": args.frames, **base, "scoring": SCORING}
    return {"mode": "live", "budget": args.budget, **base, "scoring": SCORING,
            "scenes_spec": {s: LIVE_SCENES[s] for s in args.scenes.split(",") if s in LIVE_SCENES}}


def _run(args: argparse.Namespace, jobs: list[dict], runs: list[dict], partial: Path, settings: dict,
         wall0: float) -> float:
    """Run ``jobs`` (live: one mission after another in this process; offline: on ``--jobs`` processes), appending
    to ``runs`` and rewriting ``partial`` after each; returns the seconds spent."""
    t0 = time.perf_counter()

    def keep(r: dict) -> None:
        runs.append(r)
        if failed(r):
            tqdm.write(f"{FAILED_MARK} {' '.join(str(r[k]) for k in RUN_KEYS)}: mission {r['end_state']}"
                       + (f": {r['error']}" if r.get("error") else "") + " (recorded, left out of the figures)")
        partial.write_text(json.dumps({"settings": settings, "runs": runs,
                                       "wall_s": wall0 + time.perf_counter() - t0}, indent=1))

    if args.mode == "live":
        for job in tqdm(jobs, desc="pose_perturbation (live)", unit="mission"):
            keep(live_one(job))
        return time.perf_counter() - t0
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futs = [pool.submit(run_one, j) for j in jobs]
        for f in tqdm(as_completed(futs), total=len(futs), desc="pose_perturbation", unit="run"):
            keep(f.result())
    return time.perf_counter() - t0


def main(argv: Optional[list[str]] = None) -> int:
    """Run the bench (or ``--max-runs`` of its missing runs). Returns 0, or 1 when a live mission failed (recorded,
    left out of the figures, printed to stderr) and ``--allow-failed`` was not given."""
    ap = _parser()
    args = ap.parse_args(argv)
    live = args.mode == "live"
    scenes = [s for s in args.scenes.split(",") if s]
    levels = [lv for lv in args.levels.split(",") if lv]
    modes = [m for m in args.modes.split(",") if m]
    refines = [{"off": False, "on": True}[r] for r in args.refine.split(",") if r]
    seeds = list(range(args.seeds))
    known = LIVE_SCENES if live else SCENES
    if any(s not in known for s in scenes):
        ap.error(f"unknown scene in {scenes}; known: {list(known)}")
    if args.max_runs is not None and args.max_runs < 1:
        ap.error("--max-runs must be >= 1")
    if live and args.jobs not in (None, 1):
        ap.error("--jobs: live missions are wall-clock measurements and run one at a time")
    if not live and ODOMETRY in levels:
        ap.error(f"--levels {ODOMETRY}: the robot's own odometry runs in live missions only")
    args.jobs = args.jobs or 2
    if args.withhold_every is None:
        args.withhold_every = NOVEL_EVERY if live else 5
    if args.withhold_every < 2:
        ap.error("--withhold-every must be >= 2")
    out = args.out or RESULTS / ("pose_perturbation_live.json" if live else "pose_perturbation.json")
    settings = _settings(args)
    partial = out.with_suffix(".partial.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    if partial.exists() and not (args.resume or args.fresh):
        ap.error(f"{partial} exists: --resume to continue it or --fresh to discard it")
    runs, wall0 = load_partial(partial, settings) if args.resume else ([], 0.0)
    runs = succeeded(runs)  # a failed mission of an earlier invocation runs again
    done = {_key(r) for r in runs}
    missing = [j for j in _jobs(args, scenes, levels, refines, modes, seeds) if _key(j) not in done]
    jobs = missing[:args.max_runs] if args.max_runs is not None else missing
    wall = wall0 + _run(args, jobs, runs, partial, settings, wall0)
    if len(jobs) < len(missing):
        print(f"{len(missing) - len(jobs)} runs left ({len(runs)} done, {wall / 60:.1f} min so far): "
              f"continue with --resume")
        return exit_code(runs, args.allow_failed, "bench.pose_perturbation", RUN_KEYS)
    summary = summarise(runs, scenes, levels, refines, seeds)
    result = {"settings": {**settings, "mode": args.mode, "scenes": scenes, "levels": levels, "modes": modes,
                           "seeds": seeds, "refine": args.refine},
              "summary": summary, "failed_runs": failure_rows(runs, RUN_KEYS), "runs": runs, "wall_s": wall}
    plot(summary, out.with_suffix(".png"))
    how = (f"live missions, {args.budget:g} s per keyframe, one at a time" if live
           else f"offline mapping and scoring ({args.jobs} workers)")
    write_results(out, "pose_perturbation", argv, f": {len(seeds)} seeds, {len(runs)} runs, {wall / 60:.0f} min "
                  f"of {how} (2-core machine shared with other work)", table(summary), result)
    if result["failed_runs"]:  # kept for --resume, which runs the failed missions again
        print(f"{len(result['failed_runs'])} failed missions: --resume (same options) runs them again")
    else:
        partial.unlink(missing_ok=True)
    return exit_code(runs, args.allow_failed, "bench.pose_perturbation", RUN_KEYS)


if __name__ == "__main__":
    sys.exit(main())
