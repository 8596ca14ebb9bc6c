"""The paper's real-time protocol as a benchmark: live single agents, a per-keyframe time budget, a matched
Gaussian cap, no final pass (paper Sec. IV-A, Baselines). See ``docs/realtime.md``.

    python -m bench.realtime [--scenes tum_fr1_rpy,synthetic_circle,room0] [--budgets 0.25,0.5,1,2]
                             [--runs 3] [--modes uniform,gausslite] [--clock scaled|dataset]
                             [--final-pass-budgets 0.5] [--score-at mapping|scene] [--set KEY=VALUE ...]
                             [--out bench/results/realtime.json]

Each run is one agent mission (:class:`gausslite.mission.AgentRuntime`, in process, no fusion server)
that replays the scene through the agent's keyframe ingest as a robot streams it: frames arrive at the
scene's clock, the keyframe selector keeps the newest candidate while the mapper is busy, and every mapped
keyframe gets ``budget`` seconds of wall time (decoding, relevance and seeding included). Both modes map with
the agent's default settings (the measured ones) and the scene's sensor profile, at the same
**binding** Gaussian cap (``mapper.budget.max_gaussians``; each run's final count is reported), the same keyframe
rule, no sharing and **no final pass**. At the end of the mission the map is scored over **every** frame of
the sequence (skipped ones included): ROI PSNR, PSNR, SSIM. With ``--final-pass-budgets`` the same map then
gets the profile's final pass and is scored again (a separate column).

Clock. ``--clock scaled`` (default) replays at ``rate = 0.5 / budget``: every budget covers the same 0.5 s of
the sequence per keyframe, so 2 s per keyframe is 4× the compute of 0.5 s, as a robot whose computer is 4×
faster (the paper adjusts the frame step to the budget). The 0.5 s budget is the dataset clock itself.
``--clock dataset`` replays every budget at the dataset clock (the same total compute; the budget only trades
keyframes against iterations).

Runs are wall-clock measurements: they run one at a time in this process, and nothing else should run
beside the bench. Writes ``bench/results/realtime.json`` (``{"scenes": {scene: {"cap", "budgets": {b:
{"uniform": {...}, "gausslite": {...}, "gain", "gain_ci", "gain_interval", "gain_std", "protocols"}}}}, "runs":
[...]}``), ``realtime.md`` and ``realtime_<scene>.png`` (ROI PSNR against budget, both modes). After each run the
runs so far go to ``<out>.partial.json``; ``--resume`` continues from it.

Scoring resolution. ``--score-at mapping`` (default) scores each map at the resolution its mission mapped at;
``--score-at scene`` at the scene's own (the dataset as the scene spec loads it, e.g. TUM at 320×240), whatever
resolution the agent chose, so that runs mapped at different resolutions compare on the same pixels and a map's
finer detail counts (``bench.compute_sweep``). Each run records the basis and the size it was scored at.

Gains pair GaussLite and uniform frame by frame within each run (the same seed), and only runs scored at the same
resolution (:func:`pairable_runs`); over several runs the interval is run-clustered, a t-interval over the
per-run gains (:func:`gausslite.stats.paired_gain`). Each run records the settings its mission ran with
(``"mission"``, :func:`mission_settings`). ``--reaggregate`` rewrites a written result's summary from its runs.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Optional, get_args

import cv2
import numpy as np
import torch
from tqdm import tqdm

from gausslite.datasets import detect_layout, load_dataset, task_roi
from gausslite.evaluation import (NOVEL_EVERY, PROTOCOLS, WITHHELD_PROTOCOLS, FrameSubset, current_protocols,
                                  score_live_map, side_by_side, withheld_indices)
from gausslite.datasets.odometry import PoseSource
from gausslite.datasets.subset import EstimatedPoses, ScaledFrames
from gausslite.mapping.budget import WallClock, WorkCost, fit_work_cost
from gausslite.mapping.resolution import choose_downscale
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.profiles import profile_for_layout, with_profile
from gausslite.config import load_config
from gausslite.mission import FusionPort, build_mission
from gausslite.mission.fakes import SinkFusion
from gausslite.parser import parse_task
from gausslite.stats import aggregate, fmt, fmt_gain, gain, paired_gain, significant
from gausslite.synthetic import make_scene

from bench._results import provenance, write_json
from bench.realtime_late import LATE_VIA, give_late_task, late_relevance

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared"))
RESULTS = REPO / "bench" / "results"
log = logging.getLogger(__name__)

#: bench scenes: dataset, task, resolution, clock and the matched Gaussian cap (a cap uniform reaches at every
#: budget: measured counts below it, docs/realtime.md)
SCENES = {
    "tum_fr1_rpy": {"kind": "tum", "downscale": 2.0, "task": "tum-find-mouse", "cap": 6000},
    "synthetic_circle": {"kind": "synthetic", "frames": 300, "width": 320, "height": 240,
                         "task": "synth-pick-object", "cap": 6000},
    "room0": {"kind": "replica", "downscale": 4.0, "fps": 2.0, "task": "room0-pick-plant", "cap": 6000},
    "tum_fr1_rpy_cup": {"kind": "tum", "downscale": 2.0, "task": "tum-pick-cup", "cap": 6000},
}
MODES = ("uniform", "gausslite")
#: the tracked protocol: Adam steps per frame, and every how many frames of the sequence it scores
TRACK_ITERS = 30
TRACK_STRIDE = 5
#: data seconds per keyframe that every budget covers under ``--clock scaled`` (the paper's 0.5 s/frame)
REFERENCE_BUDGET_S = 0.5


def scene_path(name: str, work: Path) -> Path:
    """The dataset folder of a bench scene (the synthetic circle is generated into ``work`` once).

    Raises:
        FileNotFoundError: a shared dataset that is absent (set ``GAUSSLITE_SHARED``).
    """
    spec = SCENES[name]
    if spec["kind"] == "tum":
        p = SHARED / "datasets" / "TUM_rgbd_dataset_freiburg1_rpy"
    elif spec["kind"] == "replica":
        p = SHARED / "datasets" / "Replica_room0"
    else:
        out = work / f"synthetic_circle_{spec['frames']}_{spec['width']}x{spec['height']}"
        if not (out / "agent_a" / "results" / f"depth{spec['frames'] - 1:06d}.png").exists():
            make_scene(out, frames=spec["frames"], width=spec["width"], height=spec["height"], trajectory="circle")
        p = out / "agent_a"
    if not p.exists():
        raise FileNotFoundError(f"{p} not found (set GAUSSLITE_SHARED)")
    return p


def dataset_scenes(path: Path, task_ids: list[str], cap: int, downscale: float = 1.0,
                   fps: Optional[float] = None) -> dict:
    """Bench scenes of a user's own sequence (``--dataset``): one per task id, named after it.

    Args:
        path: a folder the loaders read (:func:`gausslite.datasets.load_dataset`) whose annotations
            (``objects.json`` / ``tasks.json``) name the tasks.
        task_ids: ids in its ``tasks.json``. cap: the matched Gaussian cap. downscale: image downscale factor.
        fps: replay clock of sequences without timestamps (Replica, 7-Scenes).
    Returns:
        ``{task id: scene spec}`` (the layout of :data:`SCENES`, with ``"path"``).
    Raises:
        FileNotFoundError: no such folder. ValueError: no task ids, a sequence without annotations, or a task id
            its ``tasks.json`` lacks.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} not found")
    if not task_ids:
        raise ValueError("--dataset needs --tasks ID[,ID...]")
    ann = load_dataset(path, max_frames=1).annotations
    if ann is None:
        raise ValueError(f"{path} has no objects.json / tasks.json (docs/mapper.md#scene-annotations)")
    known = [t.id for t in ann.tasks]
    missing = [t for t in task_ids if t not in known]
    if missing:
        raise ValueError(f"tasks {missing} are not in {path}'s tasks.json (known: {known})")
    return {t: {"kind": "dataset", "path": str(path), "task": t, "cap": cap, "downscale": downscale,
                **({"fps": fps} if fps else {})} for t in task_ids}


def load_scene(spec: dict, path: Path):
    """(dataset, sensor profile) of a scene spec with the profile's loader options and the scene's clock."""
    layout = detect_layout(path)[0]
    profile = profile_for_layout(layout)
    kw = dict(profile.loader)
    if spec.get("fps") and layout in ("replica", "7scenes"):
        kw["fps"] = spec["fps"]
    return load_dataset(path, downscale=spec.get("downscale", 1.0), **kw), profile


class Preloaded:
    """A dataset's frames decoded into memory: a replay then sends frames as a sensor driver delivers them,
    without the loader's decoding, undistortion and depth registration competing with the mapper."""

    def __init__(self, ds) -> None:
        self.frames = [ds[i] for i in range(len(ds))]
        self.annotations = ds.annotations

    def slice(self, start: int, stop: int) -> "Preloaded":
        """Frames ``[start, stop)`` as a preloaded dataset of their own (no copy of the frames)."""
        out = Preloaded.__new__(Preloaded)
        out.frames, out.annotations = self.frames[start:stop], self.annotations
        return out

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int):
        return self.frames[i]


def agent_config(mode: str, budget: float, cap: int, seed: int, rate: float, profile, overrides=()):
    """The agent's default configuration (the measured settings) for one bench run: ``mode``, the keyframe
    budget, the cap, no final pass, realtime replay at ``rate``, one agent with the machine to itself."""
    cfg = load_config(None, [
        f"mapper.mode={mode}", f"mapper.seed={seed}", f"mapper.keyframe_budget_s={budget}",
        f"mapper.budget.max_gaussians={cap}", "mapper.performance.render_threads=2", "agent.realtime=true",
        f"agent.rate={rate}", "agent.downscale=1", *overrides]).agent
    m = with_profile(cfg.mapper, profile)
    final_per_kf = float(m.final_iters_per_keyframe)
    # no offline refinement: the final pass is scored in its own column
    m = m.model_copy(update={"final_iters": 0, "final_iters_per_keyframe": 0.0})
    return cfg.model_copy(update={"mapper": m}), final_per_kf


def training_frames(job: dict, ds):
    """The frames the mission of ``job`` may see: ``ds`` without every ``job["novel_every"]``-th frame (the
    ``novel`` protocol's withheld frames, :func:`gausslite.evaluation.withheld_indices`), or ``ds`` itself when
    nothing is withheld (``novel_every`` 0)."""
    k = int(job.get("novel_every") or 0)
    return FrameSubset(ds, withheld_indices(len(ds), k)) if k else ds


def novel_ids(job: dict, ds) -> Optional[list[int]]:
    """Frame ids of the frames ``job``'s mission never saw (None when nothing is withheld)."""
    k = int(job.get("novel_every") or 0)
    return [int(ds[i].frame_id) for i in withheld_indices(len(ds), k)] if k else None


def score(mapper, ds, ann, task: str, protocols=("sensor",), track_iters: int = TRACK_ITERS,
          track_stride: int = TRACK_STRIDE, keyframe_ids=None, novel=None, record: Optional[dict] = None,
          predicted: Optional[dict] = None, poses: Optional[dict] = None) -> dict:
    """ROI PSNR, PSNR and SSIM (means; ROI over frames that show the ROI) of the map under each scoring protocol
    (:func:`gausslite.evaluation.score_live_map`: ``sensor``, ``keyframes``, ``tracked``, and ``novel`` (at the pose
    the map predicts) and ``novel-tracked`` over the frame ids ``novel`` withheld from the mission), the same for
    every mode. The top-level figures are the ``sensor`` protocol's (every frame at the sensor's pose);
    ``protocols`` holds each protocol's, with each frame's figures. ``record`` / ``predicted``: filled with the
    views the tracked / ``novel`` frames were scored at (frame id → ``TrackedView``). ``poses``: frame id → (4, 4)
    c2w the mission's odometry estimated (``--pose-source odometry``): every protocol starts from those instead of
    the given poses, the ROI stays the given poses', frames without an estimate are not scored
    (:class:`gausslite.datasets.subset.EstimatedPoses`)."""
    protocols = tuple(dict.fromkeys(("sensor", *protocols)))
    if novel is None:
        protocols = tuple(p for p in protocols if p not in WITHHELD_PROTOCOLS)
    roi = task_roi(ann, task)
    if poses is not None:
        ds = EstimatedPoses(ds, poses)
        roi = ds.roi_fn(ann, task)
    frames = [ds[i] for i in range(len(ds))]
    res = score_live_map(mapper, frames, roi, protocols,
                         track_iters=track_iters, track_stride=track_stride, keyframe_ids=keyframe_ids,
                         novel_ids=novel, record=record, predicted=predicted)
    sensor = res["sensor"]
    return {"roi_psnr": sensor["roi_psnr"], "psnr": sensor["psnr"], "ssim": sensor["ssim"],
            "frames_scored": sensor["frames_scored"], "protocols": res}


def save_render(mapper, ds, ann, task: str, path: Path) -> None:
    """A side-by-side PNG (render | ground truth | ROI overlay) of the frame whose ROI is largest."""
    best, best_n = 0, -1
    for i in range(0, len(ds), max(1, len(ds) // 30)):
        fr = ds[i]
        n = int(ann.roi_mask(task, fr.depth, fr.c2w, fr.intrinsics).sum())
        if n > best_n:
            best, best_n = i, n
    fr = ds[best]
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), side_by_side(mapper.render_frame(fr), fr, ann.roi_mask(task, fr.depth, fr.c2w,
                                                                                  fr.intrinsics)))


def start_mission(job: dict, rate: float, extra_overrides=(), fusion: Optional[FusionPort] = None):
    """The bench agent of ``job`` (in process): (frames in memory, annotations, task, AgentRuntime, the profile's
    final-pass iterations per keyframe)."""
    ds, profile = load_scene(job.get("spec") or SCENES[job["scene"]], Path(job["path"]))
    ds = Preloaded(ds)
    ann = ds.annotations
    task = ann.task_by_id(job["task"])
    cfg, fp_per_kf = agent_config(job["mode"], job["budget"], job["cap"], job["run"], rate, profile,
                                  [*extra_overrides, *job.get("overrides", ())])
    graph = parse_task(task.text)
    relevance_fn, bind = late_relevance(job, ds, cfg, graph, ann, task)
    rt = build_mission(cfg, task.text, graph, agent_id="bench", annotations=ann, task_id=task.id, fusion=fusion,
                       relevance_fn=relevance_fn, start=False)
    bind(rt)
    return ds, ann, task, rt, fp_per_kf


def _result(job: dict, mapper, ds, ann, task, fp_per_kf: float, **fields) -> dict:
    """The figures of one finished mission: ``fields``, the map's counts, the settings it ran with (``"mission"``,
    :func:`mission_settings`), the scores over every frame, the render (``job["render_dir"]``) and, with
    ``job["final_pass"]``, the scores after the profile's final pass."""
    res = {"scene": job["scene"], "mode": job["mode"], "budget": job["budget"], "run": job["run"], "cap": job["cap"],
           **fields, "n_gaussians": len(mapper.model), "n_active": int(mapper.model.active.sum()), "frames": len(ds),
           "roi_iters": int(sum(s.active_iters for s in mapper.stats)),
           "cap_reached": max((s.n_gaussians for s in mapper.stats), default=0) >= job["cap"],
           "evicted": int(sum(s.n_evicted for s in mapper.stats)), "roi_views": len(mapper.roi_views),
           "roi_views_added": int(mapper.roi_views.n_added), "withheld": len(novel_ids(job, ds) or []),
           "mapping_downscale": float(job.get("mapping_downscale") or 1.0),
           "pose_source": job.get("pose_source") or "given",
           "mission": mission_settings(job, mapper.cfg, fields.get("iters_per_keyframe"))}
    kf_ids = sorted(int(s.frame_id) for s in mapper.stats)
    if job.get("defer_dir"):
        # scored after every mission ran (score_deferred): scoring never shares the machine with a live mission

        path = Path(job["defer_dir"]) / f"{_key_name(job)}.pt"
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"state": mapper.state_dict(saved_keyframes_max=None), "cfg": mapper.cfg.model_dump(),
                    "keyframe_ids": kf_ids, "estimated_poses": job.get("estimated_poses")}, path)
        res.update(state_path=str(path), fp_per_kf=fp_per_kf,
                   score_job={k: job.get(k) for k in ("scene", "mode", "spec", "path", "task", "protocols",
                                                       "track_iters", "track_stride", "render_dir", "final_pass",
                                                       "novel_every", "mapping_downscale", "score_at")})
        return res
    res.update(_scores(job, mapper, ds, ann, task.id, fp_per_kf, kf_ids))
    return res


def mission_settings(job: dict, cfg: MapperConfig, iters_per_keyframe: Optional[float]) -> dict:
    """What a run's mission ran with, as its result records it (``"mission"``): the effective mapper settings that
    decide its figures and the resolution it mapped at.

    Args:
        job: the run's job (``mode``, ``budget``, ``clock``, ``pose_source``, ``novel_every``, ``overrides``, and
            ``resolution``: ``{"downscale", "size": [w, h], "native_size": [w, h], "changes"}`` of the mapping
            resolution, pixels; absent: ``mapping_downscale`` alone).
        cfg: the mission's effective :class:`~gausslite.mapping.config.MapperConfig` (after the sensor profile and
            every override).
        iters_per_keyframe: iterations per keyframe the mission achieved (None: not measured).
    Returns:
        ``{"mode", "keyframe_budget_s", "budget_clock", "max_gaussians", "render_threads", "seed", "pose_source",
        "clock", "rate", "novel_every", "overrides", "mapping_downscale", "mapping_size", "native_size",
        "resolution_changes", "iters_per_keyframe"}`` (sizes [width, height] in pixels, None when not known).
    """
    res = job.get("resolution") or {}
    return {"mode": cfg.mode, "keyframe_budget_s": cfg.keyframe_budget_s, "budget_clock": cfg.budget_clock,
            "max_gaussians": cfg.budget.max_gaussians, "render_threads": cfg.performance.render_threads,
            "seed": cfg.seed, "pose_source": job.get("pose_source") or "given", "clock": job.get("clock"),
            "rate": job.get("rate"), "novel_every": int(job.get("novel_every") or 0),
            "overrides": list(job.get("overrides") or ()),
            "mapping_downscale": float(res.get("downscale") or job.get("mapping_downscale") or 1.0),
            "mapping_size": res.get("size"), "native_size": res.get("native_size"),
            "resolution_changes": res.get("changes"),
            "iters_per_keyframe": None if iters_per_keyframe is None else float(iters_per_keyframe)}


def check_withheld(novel, keyframe_ids, roi_view_ids=()) -> None:
    """The leak guard of the withheld protocols: no frame scored as novel was a training view of the map.

    Args:
        novel: frame ids withheld from the mission (None: nothing withheld).
        keyframe_ids: frame ids of the map's keyframes (a saved map's own record: a map rebuilt from its state has
            no per-keyframe statistics of its own to check).
        roi_view_ids: frame ids of its stored ROI views.
    Raises:
        ValueError: a withheld frame among them (the mission saw it: the novel figures would not be novel).
    """
    if not novel:
        return
    trained = {int(i) for i in keyframe_ids or ()} | {int(i) for i in roi_view_ids or ()}
    leaked = sorted({int(i) for i in novel} & trained)
    if leaked:
        raise ValueError(f"withheld frames {leaked[:5]} were training views of the map (keyframes or ROI views): "
                         f"not novel")


def _key_name(job: dict) -> str:
    return "_".join(str(x) for x in _key(job)).replace("/", "-")


def _scores(job: dict, mapper, ds, ann, task_id: str, fp_per_kf: float, keyframe_ids) -> dict:
    """The scores of a finished map under ``job["protocols"]``, its render (``job["render_dir"]``) and, with
    ``job["final_pass"]``, the scores after the profile's final pass (which changes ``mapper``). Scored at the
    resolution the mission mapped at (``job["mapping_downscale"]``, agent.resolution) or, with ``job["score_at"]``
    ``"scene"``, at the resolution of ``ds`` itself (the scene's); the result records which (``"score_at"``) and the
    size, ``"scored_size"`` [width, height] in pixels.

    Raises:
        ValueError: a withheld frame among ``keyframe_ids`` or the map's ROI views (:func:`check_withheld`)."""
    basis = job.get("score_at") or "mapping"
    f = float(job.get("mapping_downscale") or 1.0) if basis == "mapping" else 1.0
    if f != 1:
        ds = ScaledFrames(ds, f)
    novel = novel_ids(job, ds)
    check_withheld(novel, keyframe_ids, mapper.roi_views.frame_ids)
    size = ds[0].intrinsics
    res = {"score_at": basis, "scored_size": [int(size.width), int(size.height)]}
    res |= score(mapper, ds, ann, task_id, job.get("protocols", ("sensor",)), job.get("track_iters", TRACK_ITERS),
                 job.get("track_stride", TRACK_STRIDE), keyframe_ids, novel, poses=job.get("estimated_poses"))
    if job.get("render_dir"):
        save_render(mapper, ds, ann, task_id, Path(job["render_dir"]) / f"{job['scene']}_{job['mode']}.png")
    if job.get("final_pass") and fp_per_kf:
        mapper.cfg = mapper.cfg.model_copy(update={"final_iters_per_keyframe": fp_per_kf})
        res["final_iters"] = mapper.finalize()
        res.update({f"final_{k}": v for k, v in score(mapper, ds, ann, task_id).items()
                    if k not in ("frames_scored", "protocols")})
    return res


def score_deferred(res: dict) -> dict:
    """Score a mission whose map :func:`run_one` saved (its run result, with ``state_path`` and ``score_job``):
    rebuild the mapper from its state and configuration and add the scores to the result (the state file is
    removed)."""
    job = res["score_job"]
    t0 = time.perf_counter()
    saved = torch.load(res["state_path"], weights_only=False)
    mapper = Mapper(MapperConfig.model_validate(saved["cfg"]))
    mapper.load_state_dict(saved["state"])
    ds, _ = load_scene(job.get("spec") or SCENES[job["scene"]], Path(job["path"]))
    ds = Preloaded(ds)
    out = {k: v for k, v in res.items() if k not in ("state_path", "fp_per_kf", "score_job")}
    job = {**job, "estimated_poses": saved.get("estimated_poses")}
    out.update(_scores(job, mapper, ds, ds.annotations, job["task"], res["fp_per_kf"], saved["keyframe_ids"]))
    out["score_s"] = time.perf_counter() - t0  # loading, every protocol, the render (and a final pass, if asked)
    Path(res["state_path"]).unlink(missing_ok=True)
    return out


def run_one(job: dict) -> dict:
    """One live mission of one (scene, mode, budget, run): replay, finish (with ``job["share"]`` after a final push
    to the in-process sink, otherwise without a push), score."""
    rate = REFERENCE_BUDGET_S / job["budget"] if job["clock"] == "scaled" else 1.0
    sink = SinkFusion() if job.get("share") else None
    odometry = job.get("pose_source") == "odometry"
    extra = ()
    if odometry:
        # the runtime withholds the frames itself, so that its odometry still tracks them in order, unmapped
        k = int(job.get("novel_every") or 0)
        extra = ("agent.pose_source=odometry",
                 *((f"agent.scoring.novel_every={k}", "agent.scoring.protocols=[sensor,novel]") if k
                   else ("agent.scoring.protocols=[sensor]",)))
    ds, ann, task, rt, fp_per_kf = start_mission(job, rate, extra, fusion=sink)
    train = ds if odometry else training_frames(job, ds)
    give = give_late_task(job, train, rt, task)
    load0 = load_average()
    t0 = time.perf_counter()
    try:
        # the replay reports each frame after it is sent: the task is given before the late start's frame
        rt.replay(train, progress=(lambda i, n: give(i)) if give else None).join()
        rt.finish(push=sink is not None, evaluate=False)
        wall = time.perf_counter() - t0
        rs = rt.resolution.status()
        job = {**job, "mapping_downscale": rt.resolution.factor, "rate": rate,
               "resolution": {"downscale": rt.resolution.factor, "size": [rs["mapping_width"], rs["mapping_height"]],
                              "native_size": list(rt.resolution.native) if rt.resolution.native else None,
                              "changes": int(rt.resolution.changes)},
               "estimated_poses": {int(k): v.copy() for k, v in rt.estimated_poses.items()} if odometry else None}
        st = rt.status()
        mapper = rt.mapper
        last = rt.pusher.pushes[-1] if rt.pusher.pushes else None
        return _result(
            job, mapper, ds, ann, task, fp_per_kf, rate=rate, wall_s=wall, keyframes=int(rt.frames_keyframed),
            keyframe_iters=int(rt.keyframe_iterations), idle_iters=int(rt.idle_iterations),
            iters_per_keyframe=rt.keyframe_iterations / max(1, rt.frames_keyframed),
            kappa_mean_active=(float(mapper.model.kappa[mapper.model.active].float().mean())
                               if bool(mapper.model.active.any()) else 0.0),
            status={k: st[k] for k in ("frames_received", "frames_skipped", "frames_rejected") if k in st},
            frames_estimated=len(rt.estimated_poses) if odometry else None,
            share=bool(sink), pushes=len(rt.pusher.pushes),
            share_pct=100.0 * last.n_shared / max(1, last.n_total) if last else None,
            resolution_status=dict(rs), load_avg_1m=[load0, load_average()])
    finally:
        rt.close()


def load_average() -> Optional[float]:
    """The machine's 1-minute load average (runnable processes, ``os.getloadavg``); None where the platform has none."""
    try:
        return float(os.getloadavg()[0])
    except (AttributeError, OSError):
        return None


def keyframe_schedule(ds, spacing_s: float) -> list[int]:
    """Frame indices of the twin's keyframes: the first frame, then the first frame at or after every further
    ``spacing_s`` seconds of the sequence clock (what the live selector takes when the mapper is always busy)."""
    out, next_t = [], None
    t0 = ds[0].timestamp
    for i in range(len(ds)):
        t = ds[i].timestamp - t0
        if next_t is None or t >= next_t - 1e-9:
            out.append(i)
            next_t = (0.0 if next_t is None else next_t) + spacing_s
            while t >= next_t - 1e-9:
                next_t += spacing_s
    return out


def twin_one(job: dict) -> dict:
    """The deterministic twin of :func:`run_one`: the same agent (relevance front-end, mapper settings), keyframes
    at a fixed spacing of the sequence clock (``keyframe_schedule``), each mapped with ``budget`` modelled seconds
    of the work clock (``mapper.budget_clock=work``), no idle iterations. Same result on any machine and load."""
    spacing = REFERENCE_BUDGET_S if job["clock"] == "scaled" else job["budget"]
    ds, ann, task, rt, fp_per_kf = start_mission(job, 1.0, ["mapper.budget_clock=work"])
    try:
        mapper = rt.mapper
        # the mapping resolution the agent would pick (agent.resolution) from the work model of the twin's clock
        rc, fr0 = rt.config.resolution, ds[0]
        choice = choose_downscale(fr0.intrinsics.width, fr0.intrinsics.height, job["budget"], job["cap"],
                                  WorkCost(**mapper.cfg.work_cost.model_dump()), rc.target_iters, rc.max_downscale,
                                  rc.pinned, min_width=rc.min_width)
        job = {**job, "mapping_downscale": choice.factor, "rate": 1.0,
               "resolution": {"downscale": choice.factor, "size": [choice.width, choice.height],
                              "native_size": [fr0.intrinsics.width, fr0.intrinsics.height], "changes": 0}}
        train = training_frames(job, ScaledFrames(ds, choice.factor) if choice.factor != 1 else ds)
        kfs = keyframe_schedule(train, spacing)
        iters = 0
        give = give_late_task(job, train, rt, task)
        prev = -1
        for i in kfs:
            if give and give(i):
                rt.apply_pending_task()
            fr = train[i]
            # the frames the robot saw since the previous keyframe (their motion; ROI crops under roi_views)
            between = [train[j] for j in range(prev + 1, i)]
            prev = i
            iters += mapper.map_frame(fr, rt.relevance(fr), time_budget_s=job["budget"], between=between).iters
        return _result(job, mapper, ds, ann, task, fp_per_kf, twin=True, keyframes=len(kfs), keyframe_iters=iters,
                       idle_iters=0, iters_per_keyframe=iters / max(1, len(kfs)), wall_s=0.0)
    finally:
        rt.close()


def summarise(runs: list[dict], scene: str, budgets: list[float], cap: int) -> dict:
    """The JSON block of one scene: per budget and mode the means and stds over runs, and the paired gain."""
    keys = ["roi_psnr", "psnr", "ssim", "n_gaussians", "iters_per_keyframe", "keyframes", "idle_iters",
            "roi_iters", "final_roi_psnr", "final_psnr", "final_ssim"]
    out = {"cap": cap, "budgets": {}}
    for b in budgets:
        blk: dict = {}
        by_mode = {}
        for mode in MODES:
            rs = sorted([r for r in runs if r["scene"] == scene and r["mode"] == mode and r["budget"] == b],
                        key=lambda r: r["run"])
            if not rs:
                continue
            by_mode[mode] = rs
            agg = aggregate(rs, [k for k in keys if any(r.get(k) is not None for r in rs)])
            agg["runs"] = len(rs)
            agg["n_gaussians_runs"] = [r["n_gaussians"] for r in rs]
            agg["cap_reached_runs"] = sum(bool(r.get("cap_reached")) for r in rs)
            blk[mode] = agg
        if len(by_mode) == 2:
            u = {r["run"]: r for r in by_mode["uniform"]}
            g = {r["run"]: r for r in by_mode["gausslite"]}
            common, refused = pairable_runs(g, u, set(u) & set(g))
            if refused:
                blk["unpaired_runs"] = refused
            blk.update(_paired(g, u, common, "roi_psnr", "sensor"))
            pg = _paired(g, u, common, "psnr", "sensor")
            blk["psnr_gain"], blk["psnr_gain_std"] = pg["gain"], pg["gain_std"]
        protos = _summarise_protocols(by_mode)
        if protos:
            blk["protocols"] = protos
        if blk:
            out["budgets"][_bkey(b)] = blk
    out["uniform_budget_matching_gausslite_0.5"] = _matching_budget(out)
    protos = sorted({p for v in out["budgets"].values() for p in v.get("protocols", {})})
    if protos:
        out["uniform_budget_matching_gausslite_0.5_by_protocol"] = {p: _matching_budget(out, p) for p in protos}
    return out


def mapping_resolution(r: dict) -> tuple:
    """The resolution run ``r`` mapped at, as its result records it: ``(downscale factor, width, height, resolution
    changes during the mission)``; width, height and changes None when not recorded (a result written before the
    ``mission`` record), a factor not recorded read as 1 (the runner writes an absent factor as 1)."""
    m = r.get("mission") or {}
    w, h = m.get("mapping_size") or (None, None)
    return float(r.get("mapping_downscale") or 1.0), w, h, m.get("resolution_changes")


def pairable_runs(g: dict, u: dict, runs) -> tuple[list, list[dict]]:
    """The runs of ``runs`` (ids of both modes' results, ``g`` / ``u``: run → result) whose GaussLite and uniform maps
    were scored at the same image size, and the others, refused: a map's PSNR depends on the image size it is scored
    at, so a pair across sizes would measure the size, not the mode. Maps scored at their own mapping resolution
    (``--score-at mapping``) pair when their missions mapped at the same resolution; maps both scored at the scene's
    resolution (``--score-at scene``) pair when that size is the same, whatever resolutions they mapped at (that
    choice is then part of what the gain compares). Each refusal is logged.

    Returns:
        (sorted run ids to pair, ``[{"run", "reason"}]`` of the refused ones). Two maps scored at the scene's
        resolution differ when their recorded ``scored_size`` differ; two others when their mapping factors differ,
        or both record the mapped size (or the count of resolution changes) and those differ.
    """
    keep, refused = [], []
    for i in sorted(runs):
        a, b = mapping_resolution(g[i]), mapping_resolution(u[i])
        if g[i].get("score_at") == u[i].get("score_at") == "scene":
            sa, sb = g[i].get("scored_size"), u[i].get("scored_size")
            differs = sa != sb
            reason = f"scored at different sizes: GaussLite {sa}, uniform {sb}"
        else:
            differs = [k for k, x, y in zip(("downscale", "width", "height", "changes"), a, b)
                       if x is not None and y is not None and x != y]
            reason = (f"mapped at different resolutions: GaussLite downscale {a[0]:g} ({a[1]}x{a[2]}, {a[3]} "
                      f"changes), uniform {b[0]:g} ({b[1]}x{b[2]}, {b[3]} changes)")
        if differs:
            log.warning("%s, budget %s s, run %s not paired: %s", g[i].get("scene"), g[i].get("budget"), i, reason)
            refused.append({"run": i, "reason": reason})
        else:
            keep.append(i)
    return keep, refused


def _paired(g: dict, u: dict, runs: list, field: str, protocol: str) -> dict:
    """GaussLite − uniform of ``field`` (``roi_psnr`` or ``psnr``) over the runs ``runs`` of both modes (run → result,
    already checked to pair: :func:`pairable_runs`), paired frame by frame within each run under ``protocol``
    (:func:`gausslite.stats.paired_gain`): ``gain`` the mean of the per-run gains (each the mean of that run's paired
    per-frame differences), ``gain_ci`` its 95 % interval, run-clustered over several runs (``gain_interval``:
    ``"run-clustered"``, a t-interval over the per-run gains; ``"per-frame"`` for a single run), ``gain_runs`` the
    runs, ``gain_per_run`` their gains, ``gain_frames`` the frame pairs, ``gain_std`` the spread of the per-run gains,
    ``gain_significant`` whether the interval excludes zero. Runs scored before per-frame figures were kept (an older
    partial file): the per-run differences of the means alone (``gain_pairs: "runs"``, no interval, significant
    above twice their spread)."""
    def frames(r):
        return ((current_protocols(r.get("protocols")).get(protocol) or {}).get(f"{field}_per_frame"))

    def top(r):
        return r.get(field) if protocol == "sensor" else (current_protocols(r.get("protocols")).get(protocol)
                                                          or {}).get(field)

    per_run = gain([top(g[i]) for i in runs], [top(u[i]) for i in runs])
    fg, fu = [frames(g[i]) for i in runs], [frames(u[i]) for i in runs]
    if runs and all(x is not None for x in fg + fu):
        pg = paired_gain(fg, fu)
        return {"gain": pg["gain"], "gain_ci": [pg["ci_low"], pg["ci_high"]], "gain_interval": pg["interval"],
                "gain_runs": pg["runs"], "gain_per_run": pg["run_gains"], "gain_frames": pg["n"],
                "gain_std": pg["std"] if pg["interval"] == "run-clustered" else per_run["gain_std"],
                "gain_significant": significant(pg), "gain_pairs": "frames"}
    return {"gain": per_run["gain"], "gain_ci": None, "gain_interval": None, "gain_runs": per_run["n"],
            "gain_frames": None, "gain_std": per_run["gain_std"], "gain_significant": per_run["significant"],
            "gain_pairs": "runs"}


def _summarise_protocols(by_mode: dict) -> dict:
    """``{protocol: {"uniform": {...}, "gausslite": {...}, "gain", "gain_ci", "gain_interval", "gain_std",
    "gain_significant", "psnr_gain", "runs", "unpaired_runs"}}`` of one budget: per mode the means and stds over runs
    of each protocol's figures, and the paired gain (:func:`_paired`: per frame within each run, run-clustered over
    the runs of both modes with the same seed that mapped at the same resolution, :func:`pairable_runs`). Older runs'
    ``novel`` (then tracked) is read as ``novel-tracked``."""
    names = sorted({p for rs in by_mode.values() for r in rs for p in current_protocols(r.get("protocols"))},
                   key=lambda p: PROTOCOLS.index(p) if p in PROTOCOLS else len(PROTOCOLS))
    out = {}
    for p in names:
        blk: dict = {}
        per_mode = {}
        for mode, rs in by_mode.items():
            rows = [{"run": r["run"], **current_protocols(r.get("protocols"))[p]} for r in rs
                    if p in current_protocols(r.get("protocols"))]
            if not rows:
                continue
            per_mode[mode] = {r["run"]: r for r in rows}
            agg = aggregate(rows, [k for k in ("roi_psnr", "psnr", "ssim", "frames_scored")
                                   if any(r.get(k) is not None for r in rows)])
            agg["runs"] = len(rows)
            blk[mode] = agg
        if len(per_mode) == 2:
            u = {r["run"]: r for r in by_mode["uniform"]}
            g = {r["run"]: r for r in by_mode["gausslite"]}
            pu, pgl = per_mode["uniform"], per_mode["gausslite"]
            common, refused = pairable_runs(g, u, {i for i in set(pu) & set(pgl)
                                                   if pu[i]["roi_psnr"] is not None and pgl[i]["roi_psnr"] is not None})
            if refused:
                blk["unpaired_runs"] = refused
            if common:
                blk.update(_paired(g, u, common, "roi_psnr", p))
                pg = _paired(g, u, common, "psnr", p)
                blk.update(psnr_gain=pg["gain"], psnr_gain_std=pg["gain_std"], runs=len(common))
        out[p] = blk
    return out


def _bkey(b: float) -> str:
    return f"{b:g}"


def _matching_budget(block: dict, protocol: Optional[str] = None) -> Optional[float]:
    """The smallest budget at which uniform's ROI PSNR reaches GaussLite's at 0.5 s (linear interpolation
    between measured budgets on a log axis), under ``protocol`` (None: the top-level ``sensor`` figures); None
    when uniform never reaches it or 0.5 s was not run."""
    def fig(v: dict, mode: str):
        v = v.get("protocols", {}).get(protocol, {}) if protocol else v
        return v.get(mode, {}).get("roi_psnr")

    g = fig(block["budgets"].get("0.5", {}), "gausslite")
    if g is None:
        return None
    pts = sorted((float(b), fig(v, "uniform")) for b, v in block["budgets"].items() if fig(v, "uniform") is not None)
    for (b0, r0), (b1, r1) in zip([(None, None)] + pts[:-1], pts):
        if r1 >= g:
            if b0 is None or r1 == r0:
                return b1
            t = (g - r0) / (r1 - r0)
            return float(math.exp(math.log(b0) + t * (math.log(b1) - math.log(b0))))
    return None


def table(result: dict) -> str:
    """Markdown table of a result."""
    lines = ["| scene | cap | budget (s) | mode | ROI PSNR | PSNR | SSIM | Gaussians | iters/kf | keyframes | "
             "ROI gain | final pass: ROI PSNR / PSNR |", "|" + "---|" * 12]
    for scene, blk in result["scenes"].items():
        for b, v in blk["budgets"].items():
            for mode in MODES:
                m = v.get(mode)
                if not m:
                    continue
                g = gain_cell(v) if mode == "gausslite" and "gain" in v else ""
                fp = (f"{fmt(m.get('final_roi_psnr'), m.get('final_roi_psnr_std'))} / "
                      f"{fmt(m.get('final_psnr'), m.get('final_psnr_std'))}" if m.get("final_roi_psnr") is not None
                      else "")
                lines.append(f"| {scene} | {blk['cap']} | {b} | {mode} | {fmt(m['roi_psnr'], m['roi_psnr_std'])} | "
                             f"{fmt(m['psnr'], m['psnr_std'])} | {fmt(m['ssim'], m['ssim_std'], 3)} | "
                             f"{m['n_gaussians']:.0f} | {m['iters_per_keyframe']:.1f} | {m['keyframes']:.1f} | {g} | {fp} |")
    return "\n".join(lines)


def gain_cell(v: dict) -> str:
    """A gain of :func:`_paired` for a table: ``"+1.23 [+0.80, +1.66] (σ runs 0.30)"`` (the mean of the per-run
    paired gains, its run-clustered 95 % interval, their spread), ``"+1.23 [+0.80, +1.66] (per frame, 1 run)"`` for
    a single run's per-frame interval, or ``"+1.23 ± 0.30 (runs)"`` for runs without per-frame figures; ``*``: the
    interval (without one: twice the spread) excludes zero."""
    if v.get("gain") is None:
        return "–"
    star = "*" if v.get("gain_significant") else ""
    if v.get("gain_ci") and v["gain_ci"][0] is not None:
        ci = {"gain": v["gain"], "ci_low": v["gain_ci"][0], "ci_high": v["gain_ci"][1]}
        if v.get("gain_interval") == "per-frame":
            return f"{fmt_gain(ci)}{star} (per frame, 1 run)"
        return f"{fmt_gain(ci)}{star} (σ runs {fmt(v.get('gain_std'), None)})"
    return f"{fmt(v['gain'], v.get('gain_std'))} (runs){star}"


def protocol_table(result: dict) -> str:
    """Markdown table of every scoring protocol: per scene, budget and protocol (docs/realtime.md#scoring-protocols:
    ``sensor``, ``keyframes``, ``novel`` at the pose the robot gives; ``tracked``, ``novel-tracked`` at a pose fitted
    to the map), both modes' ROI PSNR and PSNR (mean ± std over runs) and the paired ROI gain (:func:`gain_cell`:
    the mean of the per-run paired gains with its run-clustered 95 % interval and their spread)."""
    lines = ["| scene | budget (s) | protocol | uniform ROI PSNR | GaussLite ROI PSNR | ROI gain | uniform PSNR | "
             "GaussLite PSNR | runs |", "|" + "---|" * 9]
    for scene, blk in result["scenes"].items():
        for b, v in blk["budgets"].items():
            for p, pv in v.get("protocols", {}).items():
                u, g = pv.get("uniform", {}), pv.get("gausslite", {})
                lines.append(
                    f"| {scene} | {b} | {p} | {fmt(u.get('roi_psnr'), u.get('roi_psnr_std'))} | "
                    f"{fmt(g.get('roi_psnr'), g.get('roi_psnr_std'))} | {gain_cell(pv)} | "
                    f"{fmt(u.get('psnr'), u.get('psnr_std'))} | "
                    f"{fmt(g.get('psnr'), g.get('psnr_std'))} | {pv.get('runs', max(u.get('runs', 0), g.get('runs', 0)))} |")
    lines += ["", "ROI gain: GaussLite − uniform, paired frame by frame within each run: the mean of the per-run "
              "gains [95 % run-clustered interval: the t-interval over the per-run gains], σ runs: their spread; "
              "* the interval excludes zero. "
              "`novel` answers how the map serves a robot at the pose it would use on views it never trained on; "
              "`tracked` / `novel-tracked` how well a robot could localise against the map, and the map from there."]
    return "\n".join(lines)


def plot_scene(block: dict, scene: str, path: Path) -> None:
    """ROI PSNR against the per-keyframe budget, both modes (mean ± std), with the budget at which uniform
    reaches GaussLite's 0.5 s ROI PSNR marked."""
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for mode, colour in (("uniform", "tab:gray"), ("gausslite", "tab:red")):
        pts = sorted((float(b), v[mode]["roi_psnr"], v[mode]["roi_psnr_std"] or 0.0)
                     for b, v in block["budgets"].items() if v.get(mode, {}).get("roi_psnr") is not None)
        if pts:
            x, y, e = zip(*pts)
            ax.errorbar(x, y, yerr=e, marker="o", capsize=3, label=mode, color=colour)
    mb = block.get("uniform_budget_matching_gausslite_0.5")
    g05 = block["budgets"].get("0.5", {}).get("gausslite", {}).get("roi_psnr")
    if g05 is not None:
        ax.axhline(g05, ls=":", color="tab:red", lw=1)
        if mb is not None:
            ax.axvline(mb, ls="--", color="tab:gray", lw=1, label=f"uniform reaches it at {mb:.2g} s")
        else:
            ax.plot([], [], ls=":", color="tab:red", label="GaussLite at 0.5 s (uniform never reaches it)")
    ax.set_xscale("log")
    ticks = sorted(float(b) for b in block["budgets"])
    ax.set_xticks(ticks)
    ax.set_xticklabels([f"{b:g}" for b in ticks])
    ax.minorticks_off()
    ax.set_xlabel("keyframe budget (s)")
    ax.set_ylabel("ROI PSNR over every frame (dB)")
    ax.set_title(f"{scene}: cap {block['cap']} Gaussians, no final pass")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


class _CountingClock(WallClock):
    """A wall clock that also counts the work charged to it (the features of :func:`fit_work_cost`)."""

    charges = True

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.renders = self.pixels = self.gaussian_renders = self.stepped = 0

    def charge_render(self, pixels: int, gaussians: int, grad: bool = True) -> None:
        if grad:
            self.renders += 1
            self.pixels += pixels
            self.gaussian_renders += gaussians

    def charge_step(self, gaussians: int) -> None:
        self.stepped += gaussians

    def charge_fixed(self, seconds: float) -> None:
        pass


def calibrate(scene: str, work: Path, mode: str = "gausslite", frames: int = 24, iters: int = 12,
              overrides=()) -> dict:
    """Fit the deterministic clock's :class:`~gausslite.mapping.budget.WorkCost` on this machine: map the first
    ``frames`` frames of ``scene`` with ``iters`` iterations each, then time ``8 × frames`` single idle
    iterations (full-image and ROI-phase, the scene's sensor profile) and fit the linear model."""
    ds, profile = load_scene(SCENES[scene], scene_path(scene, work))
    ann = ds.annotations
    cfg, _ = agent_config(mode, 1.0, SCENES[scene]["cap"], 0, 1.0, profile, overrides)
    m = cfg.mapper.model_copy(update={"keyframe_budget_s": None, "iters_per_frame": iters,
                                      "warmup_iters": min(cfg.mapper.warmup_iters, iters)})

    mapper = Mapper(m)
    clock = _CountingClock()
    mapper.clock = clock
    task = SCENES[scene]["task"]
    step = max(1, len(ds) // frames)
    samples, roi_phase = [], []
    for i in range(0, min(len(ds), step * frames), step):
        fr = ds[i]
        mapper.map_frame(fr, ann.roi_mask(task, fr.depth, fr.c2w, fr.intrinsics))
        for _ in range(8):
            clock.reset()
            k0 = int(mapper.model.kappa.sum())
            t = time.perf_counter()
            mapper.optimize(n_iters=1)
            samples.append((clock.renders, clock.pixels, clock.gaussian_renders, clock.stepped,
                            time.perf_counter() - t))
            roi_phase.append(int(mapper.model.kappa.sum()) > k0)  # κ grows in ROI-phase iterations only
    roi = [s[-1] for s, r in zip(samples, roi_phase) if r]
    full = [s[-1] for s, r in zip(samples, roi_phase) if not r]
    cost = fit_work_cost(samples)
    pred = [cost.render_s * r + cost.pixel_s * p + cost.gaussian_s * g + cost.step(s) for r, p, g, s, _ in samples]
    meas = [s[-1] for s in samples]
    return {"scene": scene, "samples": len(samples), "work_cost": cost.__dict__, "roi_cull": m.performance.roi_cull,
            "full_iter_s": float(np.mean(full)) if full else None, "roi_iter_s": float(np.mean(roi)) if roi else None,
            "mean_measured_s": float(np.mean(meas)), "mean_abs_error_s": float(np.mean(np.abs(np.subtract(pred, meas))))}


def _key(r: dict) -> tuple:
    return (r["scene"], r["mode"], _bkey(r["budget"]), r["run"], bool(r.get("share")))


def main(argv: Optional[list[str]] = None) -> int:
    """Run the benchmark of the command line ``argv`` (``--help``); 0 on success."""
    ap = _parser()
    args = ap.parse_args(argv)

    if args.calibrate:
        work = Path(args.work)
        work.mkdir(parents=True, exist_ok=True)
        res = calibrate(args.scenes.split(",")[0], work, overrides=args.overrides)
        print(json.dumps(res, indent=1))
        return 0

    if args.reaggregate:
        reaggregate(Path(args.out), argv)
        return 0
    protocols, scenes, specs = _checked_scenes(ap, args)
    budgets = [float(b) for b in args.budgets.split(",") if b]
    fp_budgets = {float(b) for b in args.final_pass_budgets.split(",") if b}
    modes = [m for m in args.modes.split(",") if m]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_suffix(".partial.json")
    runs: list[dict] = []
    if (args.resume or args.score_only) and partial.is_file():
        runs = json.loads(partial.read_text())["runs"]
    done = {_key(r) for r in runs}
    jobs, names = _build_jobs(args, scenes, specs, protocols, budgets, fp_budgets, modes, out, done)
    if args.score_only:
        # score what earlier --missions-only invocations saved (every budget they ran), start no mission
        jobs = []
        budgets = sorted({float(r["budget"]) for r in runs if r["scene"] in names} | set(budgets))
    # one folder per result file: two invocations that share --work (given and odometry poses, say) keep their maps
    defer = None if args.twin or args.score_inline else Path(args.work) / "maps" / out.stem
    for job in jobs:
        job["defer_dir"] = str(defer) if defer else None
    t0 = time.time()
    _run_jobs(args, jobs, runs, partial)
    pending = [i for i, r in enumerate(runs) if "state_path" in r and Path(r["state_path"]).is_file()]
    if args.missions_only:
        print(f"{len(pending)} maps saved for scoring: score them with --score-only (same --out)")
        return 0
    _score_pending(args, runs, pending, partial)
    _write_result(args, runs, names, budgets, protocols, out, t0, argv)
    return 0


def _parser() -> argparse.ArgumentParser:
    """The command line of ``python -m bench.realtime``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="tum_fr1_rpy,synthetic_circle,tum_fr1_rpy_cup,room0")
    ap.add_argument("--dataset", default=None, metavar="PATH",
                    help="a sequence of your own (any folder the loaders read, with objects.json / tasks.json) "
                         "instead of the built-in scenes: one scene per --tasks id, named after it")
    ap.add_argument("--tasks", default="", help="--dataset: task ids of its tasks.json, comma-separated")
    ap.add_argument("--fps", type=float, default=None, help="--dataset: replay clock of sequences without timestamps")
    ap.add_argument("--downscale", type=float, default=1.0, help="--dataset: image downscale factor")
    ap.add_argument("--protocols", default=",".join(PROTOCOLS),
                    help="scoring protocols (docs/realtime.md#scoring-protocols), comma-separated")
    ap.add_argument("--novel-every", type=int, default=NOVEL_EVERY,
                    help="novel / novel-tracked protocols: every k-th frame of the sequence is withheld from the "
                         "mapper in both modes, scored at the pose the map predicts (novel) and at a pose tracked "
                         "against the map (novel-tracked) (0: nothing withheld, neither protocol)")
    ap.add_argument("--pose-source", choices=get_args(PoseSource), default="given",
                    help="the poses the agents map and are scored at: the sequence's own (given), or the RGB-D "
                         "odometry's estimates of every frame, the withheld ones included (agent.pose_source "
                         "odometry: a camera without SLAM); the ROI is the given poses' either way")
    ap.add_argument("--score-at", choices=("mapping", "scene"), default="mapping",
                    help="score each map at the resolution its mission mapped at (mapping), or at the scene's own "
                         "resolution whatever the agent mapped at (scene: runs mapped at different resolutions pair, "
                         "and a map's detail counts); decided with the missions, recorded with each saved map")
    ap.add_argument("--track-iters", type=int, default=TRACK_ITERS,
                    help="tracked / novel-tracked protocols: Adam steps per frame")
    ap.add_argument("--track-stride", type=int, default=TRACK_STRIDE,
                    help="tracked protocol: score every k-th frame of the sequence (MonoGS: every 5th)")
    ap.add_argument("--late", type=float, default=None, metavar="F",
                    help="the 'late' scenario: the task starts after this share of the sequence (scenes named "
                         "<scene>_late, or <scene>_late_detection with --late-via detection)")
    ap.add_argument("--late-via", choices=LATE_VIA, default="task",
                    help="late scenario: 'task', the task is given mid-mission (UpdateTask: the stored keyframes "
                         "get its relevance); 'detection', the task's object is first detected then (earlier frames "
                         "never get its relevance)")
    ap.add_argument("--budgets", default="0.25,0.5,1,2", help="seconds per keyframe, comma-separated")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--clock", choices=("scaled", "dataset"), default="scaled")
    ap.add_argument("--task", default=None, help="task id of every scene (default: the scene's)")
    ap.add_argument("--cap", type=int, default=None, help="Gaussian cap of every scene (default: the scene's)")
    ap.add_argument("--final-pass-budgets", default="0.5",
                    help="budgets whose maps also get the profile's final pass, scored in a separate column ('' = none)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="agent config override for both modes, e.g. mapper.seeding.rho=0.5")
    ap.add_argument("--out", default=str(RESULTS / "realtime.json"))
    ap.add_argument("--work", default="/tmp/gausslite_bench_realtime")
    ap.add_argument("--resume", action="store_true")
    ap.add_argument("--share", action="store_true",
                    help="agents also share (select, fine-tune, encode and push their subset to an in-process sink), "
                         "as on a robot: measures what sharing costs the agent's own map")
    ap.add_argument("--twin", action="store_true",
                    help="the deterministic twin: fixed keyframe spacing, budgets on the work clock (mapper.work_cost), "
                         "not wall time; runs may go to --jobs processes")
    ap.add_argument("--jobs", type=int, default=1,
                    help="worker processes of --twin runs, and of the scoring that follows the live missions")
    ap.add_argument("--missions-only", action="store_true",
                    help="run the live missions and save their maps, without scoring (score later with --score-only): "
                         "several invocations' missions can then run back to back, alone, before any scoring")
    ap.add_argument("--score-only", action="store_true",
                    help="start no mission: score the maps earlier --missions-only runs saved to the same --out "
                         "(its partial file) and write the result over every budget they ran")
    ap.add_argument("--reaggregate", action="store_true",
                    help="start no mission, score nothing: rewrite the summary (means, paired gains) of the result "
                         "--out from the runs it holds, with today's aggregation; its runs and settings stay")
    ap.add_argument("--score-inline", action="store_true",
                    help="score each live map right after its mission (default: every mission first, alone on the "
                         "machine, then the saved maps are scored, --jobs at a time)")
    ap.add_argument("--calibrate", action="store_true",
                    help="fit the deterministic budget clock's cost model (mapper.work_cost) on this machine and "
                         "print it (first scene)")
    return ap


def _checked_scenes(ap: argparse.ArgumentParser, args: argparse.Namespace) -> tuple:
    """The protocols, the scene names and each scene's spec (``--dataset``'s tasks or built-in scenes); unusable
    options end the program through ``ap.error``."""
    protocols = tuple(p for p in args.protocols.split(",") if p)

    if any(p not in PROTOCOLS for p in protocols):
        ap.error(f"unknown protocol in {args.protocols!r} (known: {', '.join(PROTOCOLS)})")
    if args.novel_every == 1 or args.novel_every < 0:
        ap.error("--novel-every must be 0 (off) or >= 2")
    if args.late is not None and not 0 < args.late < 1:
        ap.error("--late must be in (0, 1)")
    if args.twin and args.pose_source != "given":
        ap.error("--pose-source odometry runs live missions only (the twin replays the given poses)")
    if args.dataset:
        try:
            specs = dataset_scenes(Path(args.dataset), [t for t in args.tasks.split(",") if t],
                                   args.cap or 6000, args.downscale, args.fps)
        except (FileNotFoundError, ValueError) as e:
            ap.error(str(e))
        scenes = list(specs)
    else:
        scenes = [s for s in args.scenes.split(",") if s]
        for s in scenes:
            if s not in SCENES:
                ap.error(f"unknown scene {s!r} (known: {', '.join(SCENES)})")
        specs = {s: SCENES[s] for s in scenes}
    return protocols, scenes, specs


def _build_jobs(args: argparse.Namespace, scenes: list[str], specs: dict, protocols: tuple, budgets: list[float],
                fp_budgets: set, modes: list[str], out: Path, done: set) -> tuple[list[dict], dict]:
    """The (scene, run, budget, mode) jobs not ``done`` yet, and each scene's name (``_late`` ...) with its cap."""
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    jobs = []
    names = {}
    for scene in scenes:
        spec = specs[scene]
        path = Path(spec["path"]) if "path" in spec else scene_path(scene, work)
        cap = args.cap or spec["cap"]
        name = (scene + ("_late" if args.late_via == "task" else "_late_detection")) if args.late else scene
        names[name] = cap
        for run in range(args.runs):
            for b in budgets:
                for mode in modes:
                    job = {"scene": name, "spec": spec, "path": str(path), "task": args.task or spec["task"],
                           "mode": mode, "budget": b, "run": run, "cap": cap, "clock": args.clock,
                           "final_pass": b in fp_budgets, "overrides": list(args.overrides), "share": args.share,
                           "late": args.late, "late_via": args.late_via, "protocols": protocols,
                           "novel_every": args.novel_every, "pose_source": args.pose_source,
                           "track_iters": args.track_iters,
                           "track_stride": args.track_stride, "score_at": args.score_at,
                           "render_dir": (str(out.with_name(out.stem + "_renders"))
                                          if run == 0 and b == REFERENCE_BUDGET_S and not args.twin else None)}
                    if _key(job) not in done:
                        jobs.append(job)
    return jobs, names


def _run_jobs(args: argparse.Namespace, jobs: list[dict], runs: list[dict], partial: Path) -> None:
    """Run ``jobs`` (twin runs on ``--jobs`` processes, live missions one after another), appending to ``runs`` and
    rewriting ``partial`` after each."""
    if args.twin:
        with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            results = pool.map(twin_one, jobs)
            results = list(tqdm(results, total=len(jobs), desc="twin runs", unit="run"))
    else:
        results = (run_one(job) for job in jobs)
    for r in tqdm(results, total=len(jobs), desc="realtime runs", unit="run", disable=args.twin):
        runs.append(r)
        if "state_path" in r:  # scored below, once every mission ran
            tqdm.write(f"{r['scene']} {r['mode']:9s} b={r['budget']:<5g} run {r['run']}: {r['n_gaussians']} G, "
                       f"{r['keyframes']} kf x {r['iters_per_keyframe']:.1f} it (+{r['idle_iters']} idle), "
                       f"{r['wall_s']:.0f} s")
            partial.write_text(json.dumps({"runs": runs}, indent=1))
            continue
        per = " ".join(f"{p} {v['roi_psnr']:.2f}" for p, v in r.get("protocols", {}).items()
                       if v.get("roi_psnr") is not None)
        tqdm.write(f"{r['scene']} {r['mode']:9s} b={r['budget']:<5g} run {r['run']}: ROI {r['roi_psnr']:.2f} dB "
                   f"({per}), PSNR {r['psnr']:.2f}, {r['n_gaussians']} G, {r['keyframes']} kf x "
                   f"{r['iters_per_keyframe']:.1f} it (+{r['idle_iters']} idle), {r['wall_s']:.0f} s")
        partial.write_text(json.dumps({"runs": runs}, indent=1))


def _score_pending(args: argparse.Namespace, runs: list[dict], pending: list[int], partial: Path) -> None:
    """Score the saved maps of ``runs[i]`` for ``i`` in ``pending`` on ``--jobs`` processes, in place."""
    if pending:
        items = [runs[i] for i in pending]
        with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            for i, r in zip(pending, tqdm(pool.map(score_deferred, items), total=len(items), desc="scoring",
                                          unit="map")):
                runs[i] = r
                per = " ".join(f"{p} {v['roi_psnr']:.2f}" for p, v in r["protocols"].items()
                               if v.get("roi_psnr") is not None)
                tqdm.write(f"{r['scene']} {r['mode']:9s} b={r['budget']:<5g} run {r['run']}: ROI ({per}), "
                           f"PSNR {r['psnr']:.2f}")
                partial.write_text(json.dumps({"runs": runs}, indent=1))


def reaggregate(out: Path, argv: Optional[list[str]] = None) -> dict:
    """Rewrite the summary of the written result ``out`` from the runs it holds (``--reaggregate``): every scene's
    block (:func:`summarise`: the means over runs and the paired gains, run-clustered) and ``<out>.md``; the runs, the
    settings and the provenance of the missions stay as they were, the aggregation's own provenance goes to
    ``"aggregation"``. Nothing is run or scored again.

    Returns:
        the rewritten result.
    Raises:
        FileNotFoundError: no such file. KeyError: a file without ``runs`` and ``scenes`` (not a realtime result).
    """
    result = json.loads(Path(out).read_text())
    budgets = [float(b) for b in result["settings"]["budgets"]]
    for scene, blk in result["scenes"].items():
        result["scenes"][scene] = summarise(result["runs"], scene, budgets, blk["cap"])
    result["aggregation"] = provenance("realtime", argv)
    write_json(out, result, "realtime", argv, indent=1)
    md = table(result) + "\n\n" + protocol_table(result)
    Path(out).with_suffix(".md").write_text(md + "\n")
    print(md)
    return result


def _write_result(args: argparse.Namespace, runs: list[dict], names: dict, budgets: list[float], protocols: tuple,
                  out: Path, t0: float, argv: Optional[list[str]] = None) -> None:
    """Write the JSON (with the run's provenance, :func:`bench._results.write_json`), the markdown tables and one
    plot per scene with several budgets; print the tables."""
    result = {"settings": {"budgets": budgets, "runs": args.runs, "clock": args.clock, "overrides": args.overrides,
                           "reference_budget_s": REFERENCE_BUDGET_S, "machine": platform.machine(),
                           "cpus": os.cpu_count(), "wall_s": time.time() - t0, "protocols": list(protocols),
                           "track_iters": args.track_iters, "track_stride": args.track_stride, "late": args.late,
                           "novel_every": args.novel_every, "pose_source": args.pose_source,
                           "score_at": args.score_at,
                           "late_via": args.late_via if args.late else None, "dataset": args.dataset},
              "scenes": {}, "runs": runs}
    for scene, cap in names.items():
        blk = summarise(runs, scene, budgets, cap)
        result["scenes"][scene] = blk
        if len(blk["budgets"]) > 1:
            plot_scene(blk, scene, out.with_name(f"{out.stem}_{scene}.png"))
    write_json(out, result, "realtime", argv, indent=1)
    md = table(result) + "\n\n" + protocol_table(result)
    out.with_suffix(".md").write_text(md + "\n")
    print(md)


if __name__ == "__main__":
    sys.exit(main())
