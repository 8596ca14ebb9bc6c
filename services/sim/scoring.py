"""Fusing and scoring at the end of a simulation: every fused map of :data:`~gausslite_services.sim.report.FUSED_KEYS`
made on the fusion server, scored on each agent's task ROI over its frames and under the scoring protocols
(:func:`fused_protocols`), a render per task, and what covers each robot's ROI in the team map
(:func:`roi_cover_report`).

Fused-map ROI PSNR of a task = mean over that task's agent's frames of the PSNR restricted to the task's
ground-truth ROI mask (frames whose ROI is empty are skipped), rendering the fused map at those views.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional

import cv2
import grpc
import numpy as np

from gausslite.config import GaussLiteConfig
from gausslite.core.arrays import GaussianArrays
from gausslite.datasets import load_dataset, task_roi
from gausslite.evaluation import TrackedView, render_map, score_map, side_by_side, withheld_indices
from gausslite.fusion.diagnose import RoiView, cover_image, roi_cover
from gausslite.fusion.guard import with_own_map
from gausslite.gaussians import GaussianMap
from gausslite.fusion.vote import voxel_vote
from gausslite.mission.config import AgentConfig
from gausslite.wire.decode import assemble
from gausslite.wire.format import WireLimits
from gausslite_services.fusion_server.store import SqliteFusionStore
from gausslite_services.sim.launch import AgentPlan
from gausslite_services.sim.report import FUSED_KEYS, PER_ROBOT, fmt

log = logging.getLogger("gausslite_services.sim")  # one logger for the whole simulation


def fuse_settings(cfg: GaussLiteConfig, realtime: bool = False) -> dict:
    """The simulation's fusion settings (:meth:`gausslite.config.SimFuse.settings` of ``cfg.sim.fuse``): live
    runs (``realtime``) contest with ``live_contest_radius`` (default 0, the paper's per-voxel rule): measured
    live, the neighbourhood contest empties an owner's voxels next to another robot's denser task region
    (``docs/sharing.md``)."""
    return cfg.sim.fuse.settings(realtime)


#: the protocols a team map is also scored under at its robot's own tracked views: ``tracked@own`` and
#: ``novel-tracked@own`` (``novel`` scores a team map at its robot's predicted views already)
AT_OWN = ("tracked", "novel-tracked")


def _views(summary, field: str) -> Dict[int, TrackedView]:
    return {int(t.frame_id): TrackedView(np.asarray(t.pose.c2w, np.float64).reshape(4, 4),
                                         np.asarray(t.exposure, np.float64), 0.0, 0.0, 0.0, 0)
            for t in getattr(summary, field, ())}


def own_views(summary) -> Dict[int, TrackedView]:
    """frame id → the :class:`gausslite.evaluation.TrackedView` (pose and exposure) each ``tracked`` /
    ``novel-tracked`` frame was scored at on the robot's own map, tracked against it, from its Finish summary
    (``MissionSummary.tracked_views``)."""
    return _views(summary, "tracked_views")


def predicted_views(summary) -> Dict[int, TrackedView]:
    """frame id → the :class:`gausslite.evaluation.TrackedView` each ``novel`` frame was scored at on the robot's own
    map: the pose and exposure its map predicts from its training alone (the given pose with the robot's learned
    correction, the exposure between its keyframes), from its Finish summary (``MissionSummary.predicted_views``);
    empty for an agent that sends none (a fused map is then scored at the sensor's pose, its exposure fitted outside
    the ROI)."""
    return _views(summary, "predicted_views")


def _entry(q: str, v: dict) -> dict:
    """A protocol's figures as the report keeps them (ROI PSNR, frames, each frame's ROI PSNR; ``novel``'s pose)."""
    out = {"roi_psnr": v["roi_psnr"], "frames_scored": v["frames_scored"],
           "roi_psnr_per_frame": dict(v.get("roi_psnr_per_frame") or {})}
    if q.split("@")[0] == "novel":
        out["pose"] = "predicted"
    return out


def fused_protocols(gmap, frames: list, annotations, task_id: str, scoring, keyframe_poses: Dict[int, np.ndarray],
                    backend: str = "auto", views: Optional[Dict[int, TrackedView]] = None,
                    novel_views: Optional[Dict[int, TrackedView]] = None) -> dict:
    """One fused map's figures on one task under the scoring protocols of ``scoring`` (a
    :class:`gausslite.mission.config.ScoringConfig`), as its robot's own map is scored
    (docs/realtime.md#scoring-protocols; :func:`gausslite.evaluation.score_map`): ``sensor`` every frame at the
    sensor's pose (:func:`gausslite.evaluation.evaluate_fused`'s figure); ``keyframes`` the frames of
    ``keyframe_poses`` (frame id → (4, 4) camera-to-world: the keyframes the task's robot uploaded, at the refined
    poses they carry); ``novel`` the frames
    every agent's replay withheld (every ``novel_every``-th of the sequence,
    :func:`gausslite.evaluation.withheld_indices`) at the pose and exposure the task's robot predicts for them
    (``novel_views``, :func:`predicted_views`: a robot loads the team map and uses it at its own SLAM pose with its
    learned correction), nothing fitted; ``tracked`` / ``novel-tracked`` every ``track_stride``-th / every withheld
    frame at a pose and exposure fitted against the fused map from the sensor's pose, only with
    ``scoring.track_fused``. With ``views``
    (:func:`own_views`), ``tracked@own`` and ``novel-tracked@own`` score the same frames at the pose and exposure they
    were tracked at on the robot's own map: both maps at the same views, so their difference is what they render, not
    how well each tracks (a team map holds ROI subsets only, and a partial map tracks worse).

    Returns:
        ``{protocol: {"roi_psnr": dB or None, "frames_scored": n, "roi_psnr_per_frame": {frame id: dB}}}``
        (``novel`` with ``"pose": "predicted"``).
    """
    chosen = list(scoring.chosen())
    withheld = any(q in ("novel", "novel-tracked") for q in chosen)
    novel = [int(frames[i].frame_id) for i in withheld_indices(len(frames), scoring.novel_every)] if withheld else None
    roi_fn = task_roi(annotations, task_id)
    fitted = [q for q in chosen if q not in AT_OWN or scoring.track_fused]
    res = score_map(gmap, frames, roi_fn, fitted, track_iters=scoring.track_iters, track_stride=scoring.track_stride,
                    keyframe_poses=keyframe_poses, backend=backend, novel_ids=novel, novel_views=novel_views)
    out = {q: _entry(q, v) for q, v in res.items()}
    at_own = [q for q in chosen if q in AT_OWN]
    if views and at_own:
        res = score_map(gmap, frames, roi_fn, at_own, track_iters=scoring.track_iters,
                        track_stride=scoring.track_stride, backend=backend, novel_ids=novel, views=views)
        out.update({f"{q}@own": _entry(q, v) for q, v in res.items()})
    return out


def roi_cover_report(out: Path, plans: List[AgentPlan], eval_frames: Dict[str, tuple], fz: dict,
                     backend: str = "auto", stride: int = 2) -> dict:
    """What covers each robot's ROI in the team (vote) map (:func:`gausslite.fusion.diagnose.roi_cover`): the final
    subsets are read from the fusion server's store in ``out/data/fusion`` and voted again with the sim's settings
    (the same vote as the server's), and scored on every ``stride``-th frame of each robot's sequence with its task's
    ground-truth ROI. Writes ``renders/cover_<task>.png`` (the others' blending weight in red, the ROI in green).

    Returns:
        agent id → the diagnosis (``mass``, ``foreign``, ``top_foreign`` (5), ``own_missing``) plus ``image``.
    """
    store = SqliteFusionStore(out / "data" / "fusion")
    try:
        subsets = {a: assemble(store.chunk_data(a, v), WireLimits())[0] for a, v in store.latest_complete().items()}
    finally:
        store.close()
    fused, rep = voxel_vote(subsets, fz["voxel_size"], contest_radius=fz["contest_radius"])
    views = {}
    for p in plans:
        ds, frames = eval_frames[p.name]
        views[p.name] = RoiView.of_frames(frames, task_roi(ds.annotations, p.task_id), stride)
    cov = roi_cover(subsets, fused, rep.source_agent, rep.source_row, views, top=5, backend=backend)
    agents = list(rep.agents)
    for p in plans:
        if p.name in cov and views[p.name]:
            rel = f"renders/cover_{p.task_id}.png"
            view = views[p.name][len(views[p.name]) // 2]
            cv2.imwrite(str(out / rel), cover_image(fused, rep.source_agent != agents.index(p.name), view, backend))
            cov[p.name]["image"] = rel
    return cov


def load_eval_frames(plans: List[AgentPlan], agent_cfg: AgentConfig) -> Dict[str, tuple]:
    """Agent id → ``(dataset, frames)``: each agent's sequence loaded as its agent replays it (``agent_cfg``: the
    typed :class:`gausslite.mission.config.AgentConfig`; downscale, max_frames, stride, bag options)."""
    eval_frames = {}
    for p in plans:
        ds = load_dataset(p.dataset, downscale=agent_cfg.downscale, max_frames=agent_cfg.max_frames,
                          stride=agent_cfg.stride, bag=agent_cfg.bag)
        eval_frames[p.name] = (ds, [ds[i] for i in range(len(ds))])
    return eval_frames


def uploaded_keyframe_poses(fusion, plans: List[AgentPlan]) -> Dict[str, dict]:
    """Agent id → {frame id → (4, 4) camera-to-world}: the keyframes each robot uploaded, at the refined poses they
    carry (the ``keyframes`` protocol). An agent whose poses cannot be read is logged and left out."""
    kf_poses = {}
    for p in plans:
        try:
            kf_poses[p.name] = {int(k["frame_id"]): k["c2w"] for k in fusion.keyframe_poses(p.name)}
        except grpc.RpcError as e:
            log.warning("no keyframe poses of %s: %s", p.name, e.details())
    return kf_poses


def _fuse_maps(fusion, key: str, plans: List[AgentPlan], fz: dict):
    """Run the fusion of report key ``key`` (one of :data:`FUSED_KEYS`) on the server and download the result;
    ``for_robot`` fuses once per agent (``for_agent``). ``fz``: :func:`fuse_settings`.

    Returns:
        ``(gmaps, res)``: agent id → the fused ``GaussianMap`` its task is scored on, and the last fuse result.
    """
    if key == "team_map":
        res = _current_team_map(fusion)
        if res is None:
            return None, None
        g = fusion.download_fused(res.fused_version).to_gaussian_map()
        return {p.name: g for p in plans}, res
    method = "concat" if key == "concat" else "vote"
    gmaps, res = {}, None
    held = fusion.stats().get("agents", {}) if key == "refine" else {}
    if key == "refine" and not any(v.get("keyframes") for v in held.values()):
        log.warning("no refinement: no robot sent a view for it (agent.refine_views)")
        return None, None
    for p in (plans if key == "for_robot" else [None]):
        res = fusion.fuse(method, refine=(key == "refine"), refine_iters=fz["refine_iters"],
                          voxel_size=fz["voxel_size"], contest_radius=fz["contest_radius"] if method == "vote" else None,
                          for_agent=p.name if p is not None else None,
                          progress=(lambda f, m, k=key: log.info("  %s %3.0f%% %s", k, 100 * f, m)))
        g = fusion.download_fused(res.fused_version).to_gaussian_map()
        for q in ([p] if p is not None else plans):
            gmaps[q.name] = g
    return gmaps, res


@dataclass
class _LocalFuse:
    """What :func:`fuse_and_score` reads of a fuse made on the robots' side (the fields of a ``FuseResult``)."""

    n_gaussians: int
    seconds: float
    kept: dict
    fused_version: int = 0
    refine_record: dict = field(default_factory=dict)


def _with_own_maps(out: Path, plans: List[AgentPlan], vote, eval_frames: Dict[str, tuple], kf_poses: Dict[str, dict],
                   backend: str):
    """Each robot's team map made on board (:func:`gausslite.fusion.guard.with_own_map`): its own map as its agent
    wrote it and the vote's rows of the others, culled in its keyframes (the frames it mapped, at its keyframe poses,
    with its task's ROI). ``vote``: (the vote's map, its fuse result with provenance), or None.

    Returns:
        ``(gmaps, res)`` as :func:`_fuse_maps`; (None, None) without a vote or an own map of every robot.
    """
    own = own_map_files(out, [p.name for p in plans])
    if vote is None or len(own) < len(plans):
        log.warning("no on-board team maps: %s", "no vote" if vote is None else "a robot's own map is missing")
        return None, None
    t0 = time.perf_counter()
    vote_map, res = vote
    fused = GaussianArrays.from_any(vote_map)
    gmaps, own_rows = {}, {}
    for p in plans:
        ds, frames = eval_frames[p.name]
        poses = kf_poses.get(p.name, {})
        keyframes = [dataclasses.replace(fr, c2w=np.asarray(poses[int(fr.frame_id)]))
                     for fr in frames if int(fr.frame_id) in poses]
        views = RoiView.of_frames(keyframes, task_roi(ds.annotations, p.task_id))
        own_map = GaussianArrays.from_any(GaussianMap.load_ply(out / own[p.name]))
        g, st = with_own_map(fused, res.first_row, res.kept, p.name, own_map, views, backend=backend)
        gmaps[p.name] = g.to_gaussian_map()
        own_rows[p.name] = st["own"]
    n = max(len(g) for g in gmaps.values())
    return gmaps, _LocalFuse(n, time.perf_counter() - t0, own_rows)  # kept: robot → its own rows


def _current_team_map(fusion, timeout_s: float = 600.0):
    """The team map the fusion server serves once it is current (made from the final subsets and views), waited for
    up to ``timeout_s``; None when the server keeps none (logged). Raises TimeoutError when it is not current in
    time."""
    t0 = time.monotonic()
    while True:
        try:
            res = fusion.fuse(team_map=True)
            if res.team_map_current:
                return res
        except grpc.RpcError as e:
            if e.code() == grpc.StatusCode.FAILED_PRECONDITION:
                log.info("no team map: %s", e.details())
                return None
            if e.code() != grpc.StatusCode.NOT_FOUND:
                raise
        if time.monotonic() - t0 > timeout_s:
            raise TimeoutError(f"the team map was not current after {timeout_s:.0f} s")
        time.sleep(1.0)


def _write_fused_render(out: Path, key: str, gmap, frames: list, annotations, task_id: str,
                        backend: str) -> Optional[dict]:
    """Write ``out/renders/<key>_<task>.png`` (the fused map beside the frame, ROI outlined) at the frame with the
    task's largest ROI. Returns the report's render entry, or None when no frame shows the ROI."""
    mid = _roi_frame(frames, annotations, task_id)
    if mid is None:
        return None
    fr = frames[mid]
    roi = annotations.roi_mask(task_id, fr.depth, fr.c2w, fr.intrinsics)
    img = side_by_side(render_map(gmap, fr, backend), fr, roi)
    rel = f"renders/{key}_{task_id}.png"
    cv2.imwrite(str(out / rel), img)
    return {"fused": key, "task": task_id, "frame_id": int(fr.frame_id), "path": rel}


def fuse_and_score(fusion, out: Path, plans: List[AgentPlan], eval_frames: Dict[str, tuple], fz: dict, scoring,
                   kf_poses: Dict[str, dict], backend: str, views: Optional[Dict[str, dict]] = None,
                   novel_views: Optional[Dict[str, dict]] = None):
    """Every fused map of :data:`FUSED_KEYS` made on the server, scored on each agent's task (ROI PSNR over its
    frames, the ``sensor`` protocol's, and under ``scoring``'s protocols, :func:`fused_protocols`: ``novel`` at the
    agent's predicted views, ``novel_views``: agent id → :func:`predicted_views`, and at the agent's own tracked
    ``views`` too: agent id → :func:`own_views`) with a render per task in ``out/renders``.

    Returns:
        ``(fused, renders)``: key → the report's figures of that fused map, and the render entries.
    """
    fused: Dict[str, dict] = {}
    renders = []
    (out / "renders").mkdir(exist_ok=True)
    vote = None
    for key in FUSED_KEYS:
        log.info("fusing: %s", key)
        if key == "with_own":
            gmaps, res = _with_own_maps(out, plans, vote, eval_frames, kf_poses, backend)
        else:
            gmaps, res = _fuse_maps(fusion, key, plans, fz)
        if key == "vote" and gmaps is not None:
            vote = (next(iter(gmaps.values())), res)
        if gmaps is None:
            continue
        files = save_fused_maps(out, key, gmaps)
        per_task, protos = {}, {}
        for p in plans:
            gmap = gmaps[p.name]
            ds, frames = eval_frames[p.name]
            protos[p.task_id] = fused_protocols(gmap, frames, ds.annotations, p.task_id, scoring,
                                                kf_poses.get(p.name, {}), backend, (views or {}).get(p.name),
                                                (novel_views or {}).get(p.name))
            per_task[p.task_id] = protos[p.task_id]["sensor"]["roi_psnr"]  # evaluate_fused's figure
            render = _write_fused_render(out, key, gmap, frames, ds.annotations, p.task_id, backend)
            if render is not None:
                renders.append(render)
        vals = [v for v in per_task.values() if v is not None]
        fused[key] = {"roi_psnr_mean": float(np.mean(vals)) if vals else None, "roi_psnr_per_task": per_task,
                      "n_gaussians": int(res.n_gaussians), "seconds": float(res.seconds),
                      "fused_version": int(res.fused_version), "kept": dict(res.kept), "ply": files,
                      "protocols": {q: {t: protos[t][q] for t in protos if q in protos[t]}
                                    for q in [*scoring.chosen(), *[f"{a}@own" for a in AT_OWN]]
                                    if any(q in v for v in protos.values())},
                      "refine_record": dict(res.refine_record) or None}
        log.info("  %s: %d Gaussians, ROI PSNR %s", key, res.n_gaussians, {k: fmt(v) for k, v in per_task.items()})
    return fused, renders


def save_fused_maps(out: Path, key: str, gmaps: Dict[str, object]) -> Dict[str, str]:
    """Write fused map ``key`` as PLY under ``out/maps`` for ``gausslite view``: ``<key>.ply``, or for a map made per
    robot (``for_robot``, ``with_own``) ``<key>_<agent>.ply``. ``gmaps``: agent id → ``GaussianMap``. Returns agent
    id → the file's path relative to ``out``."""
    (out / "maps").mkdir(exist_ok=True)
    if key not in PER_ROBOT:  # one map every task is scored on
        next(iter(gmaps.values())).save_ply(out / f"maps/{key}.ply")
        return {agent: f"maps/{key}.ply" for agent in gmaps}
    for agent, gmap in gmaps.items():
        gmap.save_ply(out / f"maps/{key}_{agent}.ply")
    return {agent: f"maps/{key}_{agent}.ply" for agent in gmaps}


def own_map_files(out: Path, agent_ids: List[str]) -> Dict[str, str]:
    """Each robot's own final map as its agent wrote it (``data/agents/<agent>/<mission>/map.ply``, the newest
    mission's), relative to ``out``; robots without one are left out."""
    files = {}
    for a in agent_ids:
        found = sorted((out / "data" / "agents" / a).glob("*/map.ply"), key=lambda f: f.stat().st_mtime)
        if found:
            files[a] = str(found[-1].relative_to(out))
    return files


def _roi_frame(frames: list, annotations, task_id: str) -> Optional[int]:
    """Index of the frame with the largest ROI of ``task_id`` (None when no frame shows it)."""
    best, idx = 0, None
    for i, fr in enumerate(frames):
        n = int(annotations.roi_mask(task_id, fr.depth, fr.c2w, fr.intrinsics).sum())
        if n > best:
            best, idx = n, i
    return idx
