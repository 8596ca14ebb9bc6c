"""The real-time benchmark's missions: one agent's configuration for a run (:func:`agent_config`), its mission built
in process (:func:`start_mission`), a live run (:func:`run_one`) and its deterministic twin (:func:`twin_one`), the
figures of a finished mission (:func:`mission_result`, :func:`mission_settings`), and the fit of the twin's work
clock on this machine (:func:`calibrate`).

Every run records how its mission ended (``end_state``, ``error``, ``frames_failed``, ``corrections_rejected``:
:func:`bench._missions.mission_outcome`); a failed mission's run is kept with its figures and never averaged
(:mod:`bench._missions`)."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch

from gausslite.config import load_config
from gausslite.datasets.subset import ScaledFrames
from gausslite.mapping.budget import WallClock, WorkCost, fit_work_cost
from gausslite.mapping.config import MapperConfig
from gausslite.mapping.mapper import Mapper
from gausslite.mapping.profiles import with_profile
from gausslite.mapping.resolution import choose_downscale
from gausslite.mission import FusionPort, build_mission
from gausslite.mission.errors import stops_the_mission
from gausslite.mission.fakes import SinkFusion
from gausslite.parser import parse_task

from bench._missions import END_OK, failed, mission_outcome
from bench.realtime.protocol import map_scores, novel_ids, training_frames
from bench.realtime.scenes import REFERENCE_BUDGET_S, SCENES, Preloaded, load_scene, scene_path
from bench.realtime.summary import budget_key
from bench.realtime.late import give_late_task, late_relevance


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


def first_choice(config, width: int, height: int, budget: float, cap: int):
    """The mapping resolution an agent of ``config`` (an ``AgentConfig``) picks at its first frame (``width`` ×
    ``height`` native pixels, ``budget`` seconds per keyframe, ``cap`` Gaussians): its governor's choice
    (:func:`~gausslite.mapping.resolution.choose_downscale`) from the work model ``mapper.work_cost`` and
    ``agent.resolution``'s target, levels and pinned factor. Returns the
    :class:`~gausslite.mapping.resolution.ResolutionChoice`."""
    rc = config.resolution
    return choose_downscale(width, height, budget, cap, WorkCost(**config.mapper.work_cost.model_dump()),
                            rc.target_iters, rc.max_downscale, rc.pinned, min_width=rc.min_width)


#: the agent settings that pin the mapping resolution of the background and of the task region
RESOLUTION_KEYS = ("agent.resolution.downscale", "agent.resolution.roi_downscale")


def shared_resolution(spec: dict, path: Path, budgets, cap: int, overrides=()) -> dict:
    """The one mapping resolution both modes of a comparison map at (``--resolution shared``), chosen once per scene
    and budget: the first choice of the agent governor (:func:`first_choice`) under the uniform mode's settings with
    ``overrides``, at the scene's size as loaded (the scene is loaded once for every budget). Both modes get the same
    inputs (the same work model, the same target), so the choice does not depend on the mode, and every run pairs
    (:func:`~bench.realtime.summary.pairable_runs`); the region is mapped at the same level. The agents' own governor
    (a finer region level, changes mid-mission) is what ``--resolution agent`` measures.

    Returns:
        ``{budget: {"downscale": factor, "size": [w, h], "native_size": [W, H], "predicted_iters", "reason",
        "overrides": [the two RESOLUTION_KEYS settings that pin it]}}`` for each of ``budgets`` (seconds).
    """
    ds, profile = load_scene(spec, path)
    w, h = ds.intrinsics.width, ds.intrinsics.height
    out = {}
    for b in budgets:
        cfg, _ = agent_config("uniform", b, cap, 0, 1.0, profile, overrides)
        c = first_choice(cfg, w, h, b, cap)
        out[b] = {"downscale": c.factor, "size": [c.width, c.height], "native_size": [w, h],
                  "predicted_iters": c.predicted_iters, "reason": c.reason,
                  "overrides": [f"{k}={c.factor:g}" for k in RESOLUTION_KEYS]}
    return out


def start_mission(job: dict, rate: float, extra_overrides=(), fusion: Optional[FusionPort] = None,
                  relevance: Optional[Callable] = None):
    """The bench agent of ``job`` (in process), built and not started.

    Args:
        job: the run (``scene`` or ``spec``, ``path``, ``task``, ``mode``, ``budget``, ``cap``, ``run``: the seed,
            ``overrides``, and the ``late`` scenario's keys).
        rate: replay speed-up (``agent.rate``). extra_overrides: agent config overrides before ``job["overrides"]``.
        fusion: where the agent pushes (None: no pushes).
        relevance: ``(frames, annotations, task) -> relevance_fn`` (``relevance_fn``: frame → (H, W) bool), a
            relevance source that replaces the scene's own (and the ``late`` scenario's); None: the scene's.
    Returns:
        (frames in memory (:class:`~bench.realtime.scenes.Preloaded`), annotations, task, AgentRuntime, the
        profile's final-pass iterations per keyframe).
    """
    ds, profile = load_scene(job.get("spec") or SCENES[job["scene"]], Path(job["path"]))
    ds = Preloaded(ds)
    ann = ds.annotations
    task = ann.task_by_id(job["task"])
    cfg, fp_per_kf = agent_config(job["mode"], job["budget"], job["cap"], job["run"], rate, profile,
                                  [*extra_overrides, *job.get("overrides", ())])
    graph = parse_task(task.text)
    if relevance is not None:
        relevance_fn, bind = relevance(ds, ann, task), (lambda rt: None)
    else:
        relevance_fn, bind = late_relevance(job, ds, cfg, graph, ann, task)
    rt = build_mission(cfg, task.text, graph, agent_id="bench", annotations=ann, task_id=task.id, fusion=fusion,
                       relevance_fn=relevance_fn, start=False)
    bind(rt)
    return ds, ann, task, rt, fp_per_kf


def mission_result(job: dict, mapper, ds, ann, task, fp_per_kf: float, **fields) -> dict:
    """The figures of one finished mission: ``fields`` (with the mission's outcome, ``end_state``, ``error``, ...:
    :func:`bench._missions.mission_outcome`), the map's counts, the settings it ran with (``"mission"``,
    :func:`mission_settings`), the scores over every frame, the render (``job["render_dir"]``) and, with
    ``job["final_pass"]``, the scores after the profile's final pass. With ``job["defer_dir"]`` the map is saved for
    :func:`~bench.realtime.protocol.score_deferred` instead of scored. A failed mission (:func:`bench._missions.failed`)
    is scored like any other when its map can be; when scoring it raises, the run records ``score_error`` instead of
    scores (a finished mission's scoring errors propagate)."""
    res = {"scene": job["scene"], "mode": job["mode"], "budget": job["budget"], "run": job["run"], "cap": job["cap"],
           **fields, "n_gaussians": len(mapper.model), "n_active": int(mapper.model.active.sum()), "frames": len(ds),
           "roi_iters": int(sum(s.active_iters for s in mapper.stats)),
           "cap_reached": max((s.n_gaussians for s in mapper.stats), default=0) >= job["cap"],
           "evicted": int(sum(s.n_evicted for s in mapper.stats)), "pruned": int(mapper.strategy.pruned),
           "roi_views": len(mapper.roi_views),
           "roi_views_added": int(mapper.roi_views.n_added), "withheld": len(novel_ids(job, ds) or []),
           "mapping_downscale": float(job.get("mapping_downscale") or 1.0),
           "resolution_mode": job.get("resolution_mode", "agent"),
           "pose_source": job.get("pose_source") or "given",
           "mission": mission_settings(job, mapper.cfg, fields.get("iters_per_keyframe")),
           "trace": keyframe_trace(mapper.stats)}
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
    try:
        res.update(map_scores(job, mapper, ds, ann, task.id, fp_per_kf, kf_ids))
    except Exception as e:
        if not failed(res):
            raise
        res["score_error"] = f"{type(e).__name__}: {e}"  # what is left of a failed mission's map: never averaged
    return res


#: what a run's per-keyframe trace keeps of each keyframe's ``FrameStats``
TRACE_FIELDS = ("frame_id", "iters", "active_iters", "n_gaussians", "n_active", "active_scale_m", "n_roi_seeds")


def keyframe_trace(stats) -> dict:
    """A mission's per-keyframe trace: ``{field: [value per keyframe in mapping order]}`` for :data:`TRACE_FIELDS` of
    the mapper's ``FrameStats`` (``active_iters``: the ROI phase's iterations; ``n_active``: task Gaussians after the
    keyframe; ``active_scale_m``: their median largest-axis standard deviation, metres)."""
    return {f: [getattr(s, f) for s in stats] for f in TRACE_FIELDS}


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


def run_key(r: dict) -> tuple:
    """What names one run among a result's runs (a job or its result): ``(scene, mode, budget key, run, share)``; a
    resumed or re-scored result skips the runs whose key it holds."""
    return (r["scene"], r["mode"], budget_key(r["budget"]), r["run"], bool(r.get("share")))


def _key_name(job: dict) -> str:
    """:func:`run_key` as a file name (a saved map's)."""
    return "_".join(str(x) for x in run_key(job)).replace("/", "-")


def run_one(job: dict) -> dict:
    """One live mission of one (scene, mode, budget, run): replay, finish (with ``job["share"]`` after a final push
    to the in-process sink, otherwise without a push), score. The result records how the mission ended
    (``end_state``, ``error``, ``frames_failed``, ``corrections_rejected``): a mission that failed on the way (out of
    memory: ``FAILED``) or lost frames to errors (``frames_failed``) is recorded with its error, not raised
    (:func:`mission_result`)."""
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
        return mission_result(
            job, mapper, ds, ann, task, fp_per_kf, rate=rate, wall_s=wall, keyframes=int(rt.frames_keyframed),
            keyframe_iters=int(rt.keyframe_iterations), idle_iters=int(rt.idle_iterations),
            iters_per_keyframe=rt.keyframe_iterations / max(1, rt.frames_keyframed),
            kappa_mean_active=(float(mapper.model.kappa[mapper.model.active].float().mean())
                               if bool(mapper.model.active.any()) else 0.0),
            status={k: st[k] for k in ("frames_received", "frames_skipped", "frames_rejected") if k in st},
            **mission_outcome(st),
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
    of the work clock (``mapper.budget_clock=work``), no idle iterations. Same result on any machine and load.
    The twin maps in this thread as the mission's mapping worker would: a keyframe whose mapping raises is skipped and
    counted (``frames_failed``, ``error`` ``"mapping frame <id> failed: ..."``), and one that runs out of memory or
    disk ends the mapping (``end_state`` ``FAILED``; :func:`gausslite.mission.errors.stops_the_mission`)."""
    spacing = REFERENCE_BUDGET_S if job["clock"] == "scaled" else job["budget"]
    ds, ann, task, rt, fp_per_kf = start_mission(job, 1.0, ["mapper.budget_clock=work"])
    try:
        mapper = rt.mapper
        # the mapping resolution the agent would pick (agent.resolution) from the work model of the twin's clock
        fr0 = ds[0]
        choice = first_choice(rt.config, fr0.intrinsics.width, fr0.intrinsics.height, job["budget"], job["cap"])
        job = {**job, "mapping_downscale": choice.factor, "rate": 1.0,
               "resolution": {"downscale": choice.factor, "size": [choice.width, choice.height],
                              "native_size": [fr0.intrinsics.width, fr0.intrinsics.height], "changes": 0}}
        train = training_frames(job, ScaledFrames(ds, choice.factor) if choice.factor != 1 else ds)
        kfs = keyframe_schedule(train, spacing)
        iters = 0
        give = give_late_task(job, train, rt, task)
        prev = -1
        status = {"state": END_OK, "last_error": "", "frames_failed": 0}
        for i in kfs:
            if give and give(i):
                rt.apply_pending_task()
            fr = train[i]
            # the frames the robot saw since the previous keyframe (their motion; ROI crops under roi_views)
            between = [train[j] for j in range(prev + 1, i)]
            prev = i
            try:
                iters += mapper.map_frame(fr, rt.relevance(fr), time_budget_s=job["budget"], between=between).iters
            except Exception as e:  # as the mapping worker: the frame's failure, or the mission's
                status.update(last_error=f"mapping frame {fr.frame_id} failed: {type(e).__name__}: {e}")
                if stops_the_mission(e):
                    status["state"] = "FAILED"
                    break
                status["frames_failed"] += 1
        return mission_result(job, mapper, ds, ann, task, fp_per_kf, twin=True, keyframes=len(kfs), keyframe_iters=iters,
                       idle_iters=0, iters_per_keyframe=iters / max(1, len(kfs)), wall_s=0.0,
                       **mission_outcome(status))
    finally:
        rt.close()


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
