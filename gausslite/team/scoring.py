"""Scoring a team's maps against each robot's own (paper Sec. IV): a fused map scored on a robot's task under the
scoring protocols (:func:`score_team_map`, :func:`fused_protocols`), every final fused map made, saved and scored
with a render per task (:func:`score_fused_maps`; the maps the fusion server makes come from the caller, the team map
each robot makes on board is made here), what covers each robot's ROI in the team map (:func:`team_cover`,
:func:`cover_report`) and the fused maps over time (:func:`score_timeline`).

Fused-map ROI PSNR of a task = mean over that task's robot's frames of the PSNR restricted to the task's
ground-truth ROI mask (frames whose ROI is empty are skipped), rendering the fused map at those views. Frames and maps
are in the team's world frame (metres); PSNR in dB.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Dict, List, Optional, Sequence

import cv2
import numpy as np

from gausslite.core.arrays import GaussianArrays
from gausslite.datasets import task_roi
from gausslite.evaluation import (TrackedView, evaluate_fused_frames, render_map, score_map, side_by_side,
                                  withheld_indices)
from gausslite.fusion.diagnose import RoiView, cover_image, roi_cover
from gausslite.fusion.guard import with_own_map
from gausslite.fusion.vote import voxel_vote
from gausslite.gaussians import GaussianMap
from gausslite.team.figures import FUSED_KEYS, PER_ROBOT, fmt
from gausslite.team.plan import AgentPlan

log = logging.getLogger(__name__)


#: the protocols a team map is also scored under at its robot's own tracked views: ``tracked@own`` and
#: ``novel-tracked@own`` (``novel`` scores a team map at its robot's predicted views already)
AT_OWN = ("tracked", "novel-tracked")


def _entry(q: str, v: dict) -> dict:
    """A protocol's figures as the report keeps them (ROI PSNR, frames, each frame's ROI PSNR; ``novel``'s pose)."""
    out = {"roi_psnr": v["roi_psnr"], "frames_scored": v["frames_scored"],
           "roi_psnr_per_frame": dict(v.get("roi_psnr_per_frame") or {})}
    if q.split("@")[0] == "novel":
        out["pose"] = "predicted"
    return out


def score_team_map(gmap, frames: Sequence, roi_fn: Callable, protocols: Sequence[str], *, track_iters: int,
                   track_stride: int, keyframe_poses: Dict[int, np.ndarray], novel_ids: Optional[Sequence[int]] = None,
                   novel_views: Optional[Dict[int, TrackedView]] = None,
                   own_views: Optional[Dict[int, TrackedView]] = None, fit_tracked: bool = True,
                   backend: str = "auto") -> dict:
    """One team map's figures on one robot's task under ``protocols``, as the robot's own map is scored
    (docs/realtime.md#scoring-protocols; :func:`gausslite.evaluation.score_map`).

    Args:
        gmap: the team map (``GaussianMap``, world frame). frames: the robot's frames (ground truth).
        roi_fn: frame → (H, W) bool ROI mask of the robot's task. protocols: of
            :data:`gausslite.evaluation.PROTOCOLS`.
        track_iters, track_stride: the fitted protocols' Adam steps per frame, and ``tracked``'s frame stride.
        keyframe_poses: frame id → (4, 4) camera-to-world: the keyframes the robot uploaded, at the refined poses they
            carry (``keyframes``).
        novel_ids: the frame ids withheld from every robot's mapper (``novel``, ``novel-tracked``).
        novel_views: frame id → the view the robot's own map predicts for a withheld frame (``novel``; a frame
            without one: the sensor's pose, its exposure fitted outside the ROI).
        own_views: frame id → the view each ``tracked`` / ``novel-tracked`` frame was tracked at on the robot's own
            map: those protocols are also scored there, as ``tracked@own`` / ``novel-tracked@own`` (both maps at the
            same views: their difference is what they render, not how well each tracks).
        fit_tracked: score ``tracked`` / ``novel-tracked`` at a pose fitted against ``gmap`` itself too.
        backend: rasterizer backend.
    Returns:
        ``{protocol: {"roi_psnr": dB or None, "frames_scored": n, "roi_psnr_per_frame": {frame id: dB}}}``
        (``novel`` with ``"pose": "predicted"``); empty without a protocol to score.
    Raises:
        ValueError: an unknown protocol, or a withheld protocol without ``novel_ids``.
    """
    fitted = [q for q in protocols if q not in AT_OWN or fit_tracked]
    out = {}
    if fitted:
        res = score_map(gmap, frames, roi_fn, fitted, track_iters=track_iters, track_stride=track_stride,
                        keyframe_poses=keyframe_poses, backend=backend, novel_ids=novel_ids, novel_views=novel_views)
        out = {q: _entry(q, v) for q, v in res.items()}
    at_own = [q for q in protocols if q in AT_OWN]
    if own_views and at_own:
        res = score_map(gmap, frames, roi_fn, at_own, track_iters=track_iters, track_stride=track_stride,
                        backend=backend, novel_ids=novel_ids, views=own_views)
        out.update({f"{q}@own": _entry(q, v) for q, v in res.items()})
    return out


def fused_protocols(gmap, frames: list, annotations, task_id: str, scoring, keyframe_poses: Dict[int, np.ndarray],
                    backend: str = "auto", views: Optional[Dict[int, TrackedView]] = None,
                    novel_views: Optional[Dict[int, TrackedView]] = None) -> dict:
    """One fused map's figures on one task under the scoring protocols of ``scoring`` (a
    :class:`gausslite.mission.config.ScoringConfig`), as its robot's own map is scored (:func:`score_team_map`):
    ``sensor`` every frame at the sensor's pose (:func:`gausslite.evaluation.evaluate_fused`'s figure); ``keyframes``
    the frames of ``keyframe_poses`` (the keyframes the task's robot uploaded, at the refined poses they carry);
    ``novel`` the frames every agent's replay withheld (every ``novel_every``-th of the sequence,
    :func:`gausslite.evaluation.withheld_indices`) at the pose and exposure the task's robot predicts for them
    (``novel_views``: a robot loads the team map and uses it at its own SLAM pose with its learned correction),
    nothing fitted; ``tracked`` / ``novel-tracked`` every ``track_stride``-th / every withheld frame at a pose and
    exposure fitted against the fused map from the sensor's pose, only with ``scoring.track_fused``. With ``views``
    (the views the robot's own map was tracked at), ``tracked@own`` and ``novel-tracked@own`` score the same frames
    at the pose and exposure they were tracked at on the robot's own map (a team map holds ROI subsets only, and a
    partial map tracks worse).

    Returns:
        as :func:`score_team_map`.
    """
    chosen = list(scoring.chosen())
    withheld = any(q in ("novel", "novel-tracked") for q in chosen)
    novel = [int(frames[i].frame_id) for i in withheld_indices(len(frames), scoring.novel_every)] if withheld else None
    return score_team_map(gmap, frames, task_roi(annotations, task_id), chosen, track_iters=scoring.track_iters,
                          track_stride=scoring.track_stride, keyframe_poses=keyframe_poses, novel_ids=novel,
                          novel_views=novel_views, own_views=views, fit_tracked=scoring.track_fused, backend=backend)


def score_fused_maps(out: Path, plans: List[AgentPlan], eval_frames: Dict[str, tuple], scoring,
                     kf_poses: Dict[str, dict], backend: str, fuse: Callable[[str], tuple],
                     views: Optional[Dict[str, dict]] = None, novel_views: Optional[Dict[str, dict]] = None):
    """Every fused map of :data:`~gausslite.team.figures.FUSED_KEYS`, made, saved under ``out/maps``
    (:func:`save_fused_maps`) and scored on each agent's task (ROI PSNR over its frames, the ``sensor`` protocol's,
    and under ``scoring``'s protocols, :func:`fused_protocols`: ``novel`` at the agent's predicted views, and at the
    agent's own tracked ``views`` too) with a render per task in ``out/renders``.

    Args:
        out: the output folder (it holds each robot's own map, :func:`own_map_files`).
        plans: the robots. eval_frames: agent id → ``(dataset, frames)``
            (:func:`~gausslite.team.plan.load_eval_frames`).
        scoring: the agents' :class:`gausslite.mission.config.ScoringConfig`.
        kf_poses: agent id → {frame id → (4, 4) camera-to-world}: the keyframes each robot uploaded.
        backend: rasterizer backend.
        fuse: fused-map key → ``(gmaps, res)``: agent id → the fused ``GaussianMap`` its task is scored on, and the
            fuse's result (``n_gaussians``, ``seconds``, ``fused_version``, ``kept``, ``refine_record``; the vote's
            also ``first_row``), or ``(None, None)`` when that map is not made. Every key but ``with_own`` (the team
            map each robot makes on board from its own map and the vote, made here) comes from it.
        views, novel_views: agent id → frame id → the :class:`~gausslite.evaluation.TrackedView` each frame was
            tracked at / predicted at on the robot's own map (its Finish summary's ``tracked_views`` /
            ``predicted_views``).
    Returns:
        ``(fused, renders)``: key → the report's figures of that fused map, and the render entries.
    """
    fused: Dict[str, dict] = {}
    renders = []
    (out / "renders").mkdir(exist_ok=True)
    vote = None
    # the robots' tasks are scored side by side, a thread each (the kernels and torch release the GIL): one robot's
    # scoring alone leaves every other core idle
    with ThreadPoolExecutor(max_workers=max(1, min(len(plans), os.cpu_count() or 1)),
                            thread_name_prefix="gausslite-score") as pool:
        for key in FUSED_KEYS:
            vote = _score_fused_key(key, out, plans, eval_frames, scoring, kf_poses, backend, fuse, views,
                                    novel_views, vote, fused, renders, pool)
    return fused, renders


def _score_fused_key(key: str, out: Path, plans: List[AgentPlan], eval_frames: Dict[str, tuple], scoring,
                     kf_poses: Dict[str, dict], backend: str, fuse: Callable[[str], tuple], views, novel_views, vote,
                     fused: Dict[str, dict], renders: list, pool: ThreadPoolExecutor):
    """:func:`score_fused_maps` of one fused-map key: made, saved, scored on every robot's task (one ``pool`` task
    per robot) into ``fused`` and ``renders``. Returns the vote (map, result) once ``vote`` is made, else ``vote``."""
    log.info("fusing: %s", key)
    if key == "with_own":
        gmaps, res = _with_own_maps(out, plans, vote, eval_frames, kf_poses, backend)
    else:
        gmaps, res = fuse(key)
    if key == "vote" and gmaps is not None:
        vote = (next(iter(gmaps.values())), res)
    if gmaps is None:
        return vote
    files = save_fused_maps(out, key, gmaps)
    per_task, protos = {}, {}

    def score(p: AgentPlan) -> tuple:
        ds, frames = eval_frames[p.name]
        proto = fused_protocols(gmaps[p.name], frames, ds.annotations, p.task_id, scoring, kf_poses.get(p.name, {}),
                                backend, (views or {}).get(p.name), (novel_views or {}).get(p.name))
        return proto, _write_fused_render(out, key, gmaps[p.name], frames, ds.annotations, p.task_id, backend)

    for p, (proto, render) in zip(plans, pool.map(score, plans)):
        protos[p.task_id] = proto
        per_task[p.task_id] = proto["sensor"]["roi_psnr"]  # evaluate_fused's figure
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
    return vote


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
    wrote it and the vote's rows of the others, culled in every keyframe the robot holds (its checkpoint's keyframes,
    :func:`own_keyframe_poses`; else the keyframes it uploaded, ``kf_poses``), at their poses, with its task's ROI.
    ``vote``: (the vote's map, its fuse result with provenance), or None.

    Returns:
        ``(gmaps, res)`` as :func:`score_fused_maps`'s ``fuse``; (None, None) without a vote or an own map of every
        robot.
    """
    own = own_map_files(out, [p.name for p in plans])
    if vote is None or len(own) < len(plans):
        log.warning("no on-board team maps: %s", "no vote" if vote is None else "a robot's own map is missing")
        return None, None
    t0 = time.perf_counter()
    vote_map, res = vote
    fused = GaussianArrays.from_any(vote_map)
    gmaps, own_rows = {}, {}
    held = own_keyframe_poses(out, [p.name for p in plans])
    for p in plans:
        ds, frames = eval_frames[p.name]
        poses = held.get(p.name) or kf_poses.get(p.name, {})
        keyframes = [dataclasses.replace(fr, c2w=np.asarray(poses[int(fr.frame_id)]))
                     for fr in frames if int(fr.frame_id) in poses]
        views = RoiView.of_frames(keyframes, task_roi(ds.annotations, p.task_id))
        own_map = GaussianArrays.from_any(GaussianMap.load_ply(out / own[p.name]))
        g, st = with_own_map(fused, res.first_row, res.kept, p.name, own_map, views, backend=backend)
        gmaps[p.name] = g.to_gaussian_map()
        own_rows[p.name] = st["own"]
    n = max(len(g) for g in gmaps.values())
    return gmaps, _LocalFuse(n, time.perf_counter() - t0, own_rows)  # kept: robot → its own rows


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
        found = _newest_mission_file(out, a, "map.ply")
        if found is not None:
            files[a] = str(found.relative_to(out))
    return files


def _newest_mission_file(out: Path, agent_id: str, name: str) -> Optional[Path]:
    """``out/data/agents/<agent_id>/<mission>/<name>`` of the newest mission that wrote one, or None."""
    found = sorted((out / "data" / "agents" / agent_id).glob(f"*/{name}"), key=lambda f: f.stat().st_mtime)
    return found[-1] if found else None


def own_keyframe_poses(out: Path, agent_ids: List[str]) -> Dict[str, dict]:
    """Every keyframe each robot holds, from the checkpoint its agent wrote beside its map
    (``data/agents/<agent>/<mission>/checkpoint.pt``, the newest mission's): agent id → {frame id → (4, 4) float64
    camera-to-world, world frame}. Robots without a readable checkpoint are left out (logged)."""
    import torch  # lazy: the checkpoint is a torch file; the report's other parts need none of it

    poses = {}
    for a in agent_ids:
        found = _newest_mission_file(out, a, "checkpoint.pt")
        if found is None:
            continue
        try:
            state = torch.load(found, map_location="cpu", weights_only=False)
            kfs = state["mapper"]["keyframes"]
            poses[a] = {int(k["frame_id"]): np.asarray(torch.as_tensor(k["c2w"]), np.float64) for k in kfs}
        except (OSError, RuntimeError, KeyError, TypeError, ValueError) as e:
            log.warning("%s: no keyframes read from %s (%s); its on-board team map is culled in its uploaded ones",
                        a, found, e)
    return poses


def _roi_frame(frames: list, annotations, task_id: str) -> Optional[int]:
    """Index of the frame with the largest ROI of ``task_id`` (None when no frame shows it)."""
    best, idx = 0, None
    for i, fr in enumerate(frames):
        n = int(annotations.roi_mask(task_id, fr.depth, fr.c2w, fr.intrinsics).sum())
        if n > best:
            best, idx = n, i
    return idx


def team_cover(subsets: Dict[str, GaussianArrays], fused: GaussianArrays, vote_report, robots: Dict[str, tuple],
               stride: int = 2, top: int = 5, backend: str = "auto") -> tuple:
    """What draws each robot's ROI in the team vote map (:func:`gausslite.fusion.diagnose.roi_cover`).

    Args:
        subsets: agent id → the final subset it shared (``GaussianArrays``, world frame).
        fused: their vote map, and ``vote_report`` the vote's ``VoteReport`` (each row's source agent and row).
        robots: agent id → ``(frames, annotations, task id)``: its sequence and task; its views are every
            ``stride``-th frame that shows the task's ground-truth ROI.
        top: how many of the other robots' rows over the ROI each diagnosis lists. backend: rasterizer backend.
    Returns:
        ``(cover, views)``: agent id → the diagnosis (``mass``, ``foreign``, ``top_foreign``, ``own_missing``), and
        agent id → its ``RoiView`` list.
    """
    views = {a: RoiView.of_frames(frames, task_roi(ann, task), stride) for a, (frames, ann, task) in robots.items()}
    cov = roi_cover(subsets, fused, vote_report.source_agent, vote_report.source_row, views, top=top, backend=backend)
    return cov, views


def cover_report(out: Path, plans: List[AgentPlan], eval_frames: Dict[str, tuple], subsets: Dict[str, GaussianArrays],
                 voxel_size: float, contest_radius: int, backend: str = "auto", stride: int = 2) -> dict:
    """What covers each robot's ROI in the team (vote) map (:func:`team_cover`): the final ``subsets`` (agent id →
    ``GaussianArrays``, e.g. as the fusion server's store holds them) voted with the team's settings (``voxel_size``
    δ in metres, ``contest_radius`` in voxels: the same vote as the server's) and scored on every ``stride``-th frame
    of each robot's sequence with its task's ground-truth ROI. Writes ``out/renders/cover_<task>.png`` (the others'
    blending weight in red, the ROI in green).

    Returns:
        agent id → the diagnosis (``mass``, ``foreign``, ``top_foreign`` (5), ``own_missing``) plus ``image``.
    """
    fused, rep = voxel_vote(subsets, voxel_size, contest_radius=contest_radius)
    robots = {p.name: (eval_frames[p.name][1], eval_frames[p.name][0].annotations, p.task_id) for p in plans}
    cov, views = team_cover(subsets, fused, rep, robots, stride, top=5, backend=backend)
    agents = list(rep.agents)
    for p in plans:
        if p.name in cov and views[p.name]:
            rel = f"renders/cover_{p.task_id}.png"
            view = views[p.name][len(views[p.name]) // 2]
            cv2.imwrite(str(out / rel), cover_image(fused, rep.source_agent != agents.index(p.name), view, backend))
            cov[p.name]["image"] = rel
    return cov


def score_timeline(rows: list, served: Dict[int, tuple], frames_by_task: Dict[str, tuple], backend: str = "auto",
                   stride: Optional[int] = None, task_of: Optional[Dict[str, str]] = None) -> List[dict]:
    """The fused maps over time, scored after the missions (so that the scoring takes nothing from them).

    Args:
        rows: ``[(t, {agent: version}, {"" | agent: GaussianArrays}, (version, current) or None)]``: per change, the
            seconds since the team started, the subset versions voted, the vote map for the team (``""``) and for each
            robot, and the team map the fusion server served then.
        served: team-map version → ``(GaussianArrays, fuse result when first served, t then)``.
        frames_by_task: task id → ``(dataset, frames)``; each map is scored on every ``stride``-th frame (None:
            every frame of a sequence of up to 50, else a stride that scores about 50). task_of: agent id → task id.
        backend: rasterizer backend.
    Returns:
        ``[{"t": s, "versions": {...}, "n_gaussians": N, "roi_psnr": {task: dB}, "roi_psnr_for_robot": {task: dB},
        "served": {...} | None}]``: every fused team map scored on each task's ROI, each task on the map made for its
        robot, and the team map served then (``served``: its ``version``, the subset ``versions`` it was made from,
        whether it was ``current``, the time it was first served ``made_t``, its ``refine_record``, ``roi_psnr`` per
        task and ``roi_psnr_per_frame``: task → frame id → dB, the pairs of its gain over a robot's own map). A map
        is scored once, however many rows hold it.
    """
    cache: Dict[tuple, dict] = {}

    def frames_of(arrays, task) -> dict:
        key = (id(arrays), task)
        if key not in cache:
            ds, fr = frames_by_task[task]
            step = stride or max(1, len(fr) // 50)
            cache[key] = evaluate_fused_frames(arrays.to_gaussian_map(), fr[::step], ds.annotations, task, backend)
        return cache[key]

    def score(arrays, task) -> Optional[float]:
        vals = list(frames_of(arrays, task).values())
        return sum(vals) / len(vals) if vals else None

    out = []
    for t, versions, maps, seen in rows:
        row = {"t": t, "versions": versions, "n_gaussians": len(maps[""]),
               "roi_psnr": {k: score(maps[""], k) for k in frames_by_task}, "roi_psnr_for_robot": {},
               "served": None}
        for a, task in (task_of or {}).items():
            if a in maps and task in frames_by_task:
                row["roi_psnr_for_robot"][task] = score(maps[a], task)
        if seen is not None:
            arrays, r, made_t = served[seen[0]]
            row["served"] = {"version": seen[0], "current": seen[1], "versions": dict(r.map_versions),
                             "made_t": made_t, "n_gaussians": len(arrays), "refine_record": dict(r.refine_record),
                             "roi_psnr": {k: score(arrays, k) for k in frames_by_task},
                             "roi_psnr_per_frame": {k: frames_of(arrays, k) for k in frames_by_task}}
        out.append(row)
    return out
