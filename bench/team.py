"""Live robot teams under the real-time protocol: what two agents share, and how good the team's fused map is.

    python -m bench.team                                # every team, keyframe budget 0.5 s, 3 runs
    python -m bench.team --teams tum_halves --runs 1    # one team, one run

Each run maps every agent of a team live (``bench.realtime``'s protocol: the agent's deployed settings, the
scene's sensor profile, keyframe ingest at the scene's clock, ``budget`` s of wall time per keyframe, the Gaussian
cap, **no final pass**), one agent after the other, so that each has the machine to itself as a robot has its own
computer: the team harness that drives ``gausslite sim`` (:func:`gausslite.team.harness.run_team`), with the robots
in this process (:class:`gausslite.team.inprocess.InProcessTeam`) instead of as services. Agents share as deployed
(task selection, fine-tune, delta pushes) to an in-process stand-in of the
fusion server's store (:class:`gausslite.mission.fakes.RecordingFusion`): it rebuilds every push (deltas on their
base) as the server holds it and keeps the uploaded keyframes (the server's per-agent bound), with the push's time
on the mission clock. After the missions:

* **fused over time** — the pushes of all agents are merged by mission time; after each one the vote map of the
  subsets held at that moment is scored on every task's ROI (every ``--eval-stride``-th frame);
* **final** — concat, vote, vote + refine and the team map as each robot uses it (``for_robot``,
  :func:`gausslite.fusion.guard.for_robot`) of the final subsets (the ``sim.fuse``
  settings), scored on every frame of the team's sequence, against each agent's own map scored
  on the same frames (``own``: ROI PSNR of the owner's task over all frames);
* **scoring protocols** — the own and final fused maps also under ``keyframes``, ``novel``, ``tracked`` and
  ``novel-tracked`` (docs/realtime.md#scoring-protocols; ``--protocols``, ``--track-stride``): the own map on its
  keyframes at their refined pose and exposure, a fused map on the owner's uploaded keyframes at the refined poses
  they carry; both on the withheld frames at the pose and exposure the owner's map predicts (``novel``: the fused map
  through the owner's camera model, nothing fitted), and on every 5th / every withheld frame at a pose fitted against
  that map (:func:`gausslite.team.scoring.score_team_map`, the scoring of ``gausslite sim``'s team maps); each agent
  row's ``protocols`` block, the top-level figures being ``sensor``'s. Every gain (fused − own) is the mean of the
  paired per-frame differences over runs × frames with its 95 % interval;
* **bandwidth** — share of the map (final subset / map), bytes per pushed Gaussian, total upload / final subset.

Teams (``TEAMS``): ``tum`` and ``synthetic`` are the live sims of ``gausslite sim --realtime`` (two tasks, both
robots over the whole sequence); ``tum_halves`` is the overlapping-view team (each robot maps half of the TUM
sequence; their tasks share the keyboard), where vote ≥ each owner's own map is the goal.

Writes ``bench/results/team.json`` / ``.md`` and ``team_<team>.png`` (fused ROI PSNR over mission time, with each
owner's final own figure). Wall-clock: run it alone on the machine (``docs/realtime.md``).

Failed missions (:mod:`bench._missions`): every agent row records how its mission ended (``end_state``, ``error``,
``frames_failed``, ``corrections_rejected``) and so does each run (the first agent's failure). A run in which a robot's
mission failed (the harness stops the team: ``FAILED``, a dead mission, a final push that failed, a timeout), or whose
agent failed to map frames, is kept in ``runs`` (a stopped run with its agents' end states and no
figures) and the top-level ``failed_runs``, left out of the summary, marked † in the tables, and the command exits 1
unless ``--allow-failed``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np
from tqdm import tqdm

from bench._missions import (END_OK, FAILED_MARK, add_allow_failed, describe, exit_code, failed, failed_note,
                             failure_rows, mission_outcome, succeeded)
from bench._results import write_json, write_results
from bench.realtime.missions import start_mission
from bench.realtime.protocol import TRACK_ITERS, TRACK_STRIDE, score
from bench.realtime.scenes import REFERENCE_BUDGET_S, RESULTS, SCENES, scene_path
from gausslite.config import load_config
from gausslite.datasets import task_roi
from gausslite.evaluation import (NOVEL_EVERY, PROTOCOLS, WITHHELD_PROTOCOLS, FrameSubset, evaluate_fused,
                                  evaluate_fused_frames, roi_psnr_frames, withheld_indices)
from gausslite.stats import fmt_gain, paired_gain
from gausslite.fusion.diagnose import RoiView
from gausslite.fusion.guard import ON_BOARD_MIN_WEIGHT, for_robot
from gausslite.fusion.refine import RefineReport, refine_map
from gausslite.fusion.vote import concat, voxel_vote
from gausslite.team import AgentPlan
from gausslite.team import scoring as team_scoring
from gausslite.team import harness
from gausslite.team.inprocess import InProcessMission, InProcessTeam
from gausslite.core.arrays import GaussianArrays

#: teams: the scene (``bench.realtime.SCENES``), and per agent its id, task, and the frames it maps ([start, stop)
#: of the sequence; None = all). ``dir``: the synthetic scene's robot folder.
TEAMS = {
    "tum": {"scene": "tum_fr1_rpy", "overlap": False,
            "agents": [{"id": "agent_a", "task": "tum-pick-cup"}, {"id": "agent_b", "task": "tum-find-mouse"}]},
    "synthetic": {"scene": "synthetic_circle", "overlap": False,
                  "agents": [{"id": "agent_a", "task": "synth-pick-object", "dir": "agent_a"},
                             {"id": "agent_b", "task": "synth-find-chair", "dir": "agent_b"}]},
    "tum_three": {"scene": "tum_fr1_rpy", "overlap": False,
                  "agents": [{"id": "agent_a", "task": "tum-pick-cup"}, {"id": "agent_b", "task": "tum-find-mouse"},
                             {"id": "agent_c", "task": "tum-reach-keyboard"}]},
    "tum_halves": {"scene": "tum_fr1_rpy", "overlap": True,
                   "agents": [{"id": "agent_a", "task": "tum-find-mouse", "frames": [0, 75]},
                              {"id": "agent_b", "task": "tum-reach-keyboard", "frames": [75, 150]}]},
}
FUSED_KEYS = ("concat", "vote", "vote_r1", "refine", "refine_long")
#: the team map as each robot loads it: ``for_robot`` made on the server from the robot's subset
#: (:func:`gausslite.fusion.guard.for_robot`), ``with_own`` made on the robot from its own whole map
#: (:func:`gausslite.fusion.guard.with_own_map`); both cull the others' rows that draw the robot's ROI in its views
PER_ROBOT = ("for_robot", "with_own")
#: the fused maps' scores through each robot's own camera model: every frame at the sensor's pose with the robot's
#: refined correction, motion blur, rolling shutter and exposure response, the rule its own map's ``sensor`` score
#: follows (:meth:`gausslite.mapping.mapper.Mapper.seen_by_this_camera`); the fused ``sensor`` figures render the
#: bare sensor pose, with none of these
ROBOT_CAMERA = "robot_camera"
#: refinement iterations of the ``refine_long`` column (a fusion server with time to spare)
LONG_REFINE_ITERS = 1000


def fuse_settings() -> dict:
    """The live sim's fusion settings (``sim.fuse``, with its ``live_contest_radius``)."""
    return load_config().sim.fuse.settings(realtime=True)


#: bound on one team run's missions (s): the longest team here runs about 10 min
TEAM_TIMEOUT_S = 3600.0


def team_plans(team: str, work: Path) -> list[AgentPlan]:
    """The robots of ``team`` (:data:`TEAMS`) as the team harness's plans: each its id, its scene folder (the synthetic
    scene's robot folder for robots with a ``dir``) and its task id; the task's text is filled in when its mission
    is built."""
    scene = TEAMS[team]["scene"]
    path = scene_path(scene, work)
    return [AgentPlan(spec["id"], str(path.parent / spec["dir"] if spec.get("dir") else path), spec["task"], "")
            for spec in TEAMS[team]["agents"]]


class TeamMissionFailed(RuntimeError):
    """The team harness stopped a team run: a robot's mission failed, its final push failed, or the missions did not
    finish in time (:func:`gausslite.team.harness.run_team`).

    Attributes:
        agents: per robot of the team, in plan order, ``{"id", "task", "end_state", "error", "frames_failed",
            "corrections_rejected"}`` (:func:`bench._missions.mission_outcome` of its mission; ``end_state``
            ``"NOT_STARTED"`` for a robot whose turn did not come).
    """

    def __init__(self, message: str, agents: list[dict]) -> None:
        super().__init__(message)
        self.agents = agents


def run_missions(team: str, budget: float, run: int, cap: int, work: Path, overrides=(),
                 novel_every: int = NOVEL_EVERY) -> tuple[InProcessTeam, dict]:
    """Every robot of ``team`` live (``bench.realtime``'s protocol: its deployed settings, the scene's sensor profile,
    keyframe ingest at the scene's clock scaled to ``budget`` s per keyframe, the Gaussian ``cap``, no final pass),
    driven by the team harness (:func:`gausslite.team.harness.run_team`) in this process, one robot after the other
    (:class:`gausslite.team.inprocess.InProcessTeam`), each sharing to its own recording store. Every
    ``novel_every``-th frame of the team's sequence is withheld from every robot (0: none); a robot with ``frames``
    maps that window of the sequence.

    Returns:
        ``(team runner, loaded)``: the runner, its missions finished and still open (close it), and per agent id
        ``{"dataset", "annotations", "task", "frames": [lo, hi], "novel": withheld frame ids or None}``.
    Raises:
        TeamMissionFailed: the harness stopped the team (a mission failed, a final push failed, a timeout); the
            runner is closed, the robots' end states are in the exception.
    """
    specs = {a["id"]: a for a in TEAMS[team]["agents"]}
    rate = REFERENCE_BUDGET_S / budget
    loaded: dict = {}

    def mission(plan: AgentPlan, fusion):
        job = {"scene": TEAMS[team]["scene"], "path": plan.dataset, "task": plan.task_id, "mode": "gausslite",
               "budget": budget, "run": run, "cap": cap, "clock": "scaled", "overrides": list(overrides)}
        ds, ann, task, rt, _ = start_mission(job, rate, fusion=fusion)
        plan.task = task.text
        lo, hi = specs[plan.name].get("frames") or (0, len(ds))
        held = withheld_indices(len(ds), novel_every) if novel_every else []
        loaded[plan.name] = {"dataset": ds, "annotations": ann, "task": task, "frames": [lo, hi],
                             "novel": [int(ds[i].frame_id) for i in held] if novel_every else None}
        return rt, FrameSubset(ds.slice(lo, hi), [i - lo for i in held if lo <= i < hi])

    runner = InProcessTeam(team_plans(team, work), mission)
    try:
        harness.run_team(runner, timeout_s=TEAM_TIMEOUT_S, poll_s=0.05)
    except (RuntimeError, TimeoutError) as e:  # the harness stopped the team: record how each robot's mission ended
        ended = runner.statuses()
        agents = [{"id": p.name, "task": p.task_id,
                   **(mission_outcome(ended[p.name]) if ended[p.name] is not None
                      else {"end_state": "NOT_STARTED", "error": ""})} for p in runner.plans]
        runner.close()
        raise TeamMissionFailed(f"{type(e).__name__}: {e}", agents) from e
    except BaseException:
        runner.close()
        raise
    return runner, loaded


def agent_row(m: InProcessMission, loaded: dict, rate: float, protocols=PROTOCOLS, track_iters: int = TRACK_ITERS,
              track_stride: int = TRACK_STRIDE) -> dict:
    """One robot's figures after its mission (``m``, :func:`run_missions`): its share and bytes, its own map's scores
    over every frame of the team's sequence under each scoring protocol (``protocols``, :func:`bench.realtime.score`:
    ``own_protocols``; the top-level ``own_*`` figures are ``sensor``'s), its push history on the sequence clock
    (``rate``: the mission clock's speed-up) and uploaded keyframes, how its mission ended (``end_state``, ``error``,
    ``frames_failed``, ``corrections_rejected``: :func:`bench._missions.mission_outcome`); the keys starting with
    ``_`` are for :func:`fused_scores` and leave the run's record."""
    rt, sink, pu = m.runtime, m.fusion, m.runtime.pusher
    ds, ann, task, novel = loaded["dataset"], loaded["annotations"], loaded["task"], loaded["novel"]
    last = pu.pushes[-1] if pu.pushes else None
    predicted: dict = {}
    own = score(rt.mapper, ds, ann, task.id, protocols, track_iters, track_stride,
                sorted(int(st.frame_id) for st in rt.mapper.stats), novel, predicted=predicted)
    return {"id": m.plan.name, "task": task.id, "frames": loaded["frames"], "wall_s": m.wall_s, "rate": rate,
            "keyframes": int(rt.frames_keyframed), "n_gaussians": len(rt.mapper.model),
            "iters_per_keyframe": rt.keyframe_iterations / max(1, rt.frames_keyframed),
            "n_shared": int(last.n_shared) if last else 0,
            "share_pct": 100.0 * last.n_shared / max(1, last.n_total) if last else None,
            "pushes": len(pu.pushes), "last_error": rt.last_error, **mission_outcome(m.summary.status),
            "total_upload_bytes": int(pu.total_upload_bytes),
            "final_subset_bytes": int(pu.final_subset_bytes),
            # the views sent for the refinement (agent.refine_views), beside the subset's bytes
            "view_bytes": int(pu.views.sent_bytes), "views_sent": int(pu.views.sent),
            "views_unsent": pu.views_unsent(),
            "view_ratio": pu.views.sent_bytes / pu.final_subset_bytes if pu.final_subset_bytes else None,
            "upload_ratio": pu.total_upload_bytes / pu.final_subset_bytes if pu.final_subset_bytes else None,
            "bytes_per_gaussian": (pu.final_subset_bytes / last.n_shared) if last and last.n_shared else None,
            "push_log": [{"t": t, "version": v, "n": len(s)} for t, v, s in sink.history],
            "own_roi_psnr": own["roi_psnr"], "own_psnr": own["psnr"], "own_protocols": own["protocols"],
            "_history": [(t * rate, s) for t, _, s in sink.history], "_keyframes": list(sink.keyframes.values()),
            "_seen": rt.mapper.seen_by_this_camera, "_novel": novel,
            "_own_map": GaussianArrays.from_any(rt.mapper.gmap), "_predicted": predicted,
            # every keyframe the robot holds with its ROI: the views its on-board team map is culled in
            "_own_views": [kf for kf in rt.mapper.keyframes if kf.roi is not None],
            "_frames": ds.frames, "_annotations": ann}


def fused_scores(agents: list[dict], fuse: dict, seed: int, eval_stride: int, protocols=PROTOCOLS,
                 track_iters: int = TRACK_ITERS, track_stride: int = TRACK_STRIDE,
                 renders: Optional[Path] = None) -> dict:
    """Fused figures of one team run: ROI PSNR per task (on its owner's whole sequence) after each push (vote,
    every ``eval_stride``-th frame, time on the mission clock in s) and of the final concat / vote / refine maps
    over every frame, each final map also under the scoring protocols (``protocols``: ``{protocol: {task: dB}}``, and
    each frame's figure in ``protocols_per_frame``: ``{protocol: {task: {frame id: dB}}}``, the pairs of every fused −
    own gain; :func:`_by_protocol`)."""
    def scores(g, stride: int = 1) -> dict:
        return {a["task"]: evaluate_fused(g, a["_frames"][::stride], a["_annotations"], a["task"]) for a in agents}

    events = sorted((t, a["id"], s) for a in agents for t, s in a["_history"])
    held, timeline = {}, []
    for t, aid, s in events:
        held[aid] = s
        fused, _ = voxel_vote(held, fuse["voxel_size"], contest_radius=fuse["contest_radius"])
        g = fused.to_gaussian_map()
        timeline.append({"t": t, "agent": aid, "n": len(fused),
                         "roi_psnr": scores(g, eval_stride)})
    final = {a["id"]: a["_history"][-1][1] for a in agents if a["_history"]}
    out = {"timeline": timeline}
    vote, report = voxel_vote(final, fuse["voxel_size"], contest_radius=fuse["contest_radius"])
    kfs = [k for a in agents for k in a["_keyframes"]]
    sources = [a["id"] for a in agents for _ in a["_keyframes"]]  # held-out views spread over the robots
    records = {"refine": RefineReport(), "refine_long": RefineReport()}
    maps = {"concat": concat(final), "vote": vote,
            "vote_r1": voxel_vote(final, fuse["voxel_size"], contest_radius=1)[0],
            "refine": refine_map(vote, kfs, fuse["refine_iters"], seed=seed, sources=sources,
                                 report=records["refine"]) if kfs else vote,
            "refine_long": refine_map(vote, kfs, LONG_REFINE_ITERS, seed=seed, per_view_iters=0, sources=sources,
                                      report=records["refine_long"]) if kfs else vote}
    for key in FUSED_KEYS:
        g = maps[key].to_gaussian_map()
        out[key] = {"n": len(maps[key])}
        if key in records:  # the refinement's held-out record: views, iterations run, early stop, rollback
            out[key]["refine_record"] = records[key].as_dict() if kfs else None
        _put_protocols(out[key], {a["task"]: _by_protocol(g, a, protocols, track_iters, track_stride)
                                  for a in agents})
    # the team map as each robot loads it: each task scored on the map made for its robot, from its shared subset
    # on the server (Fuse(for_agent=...)) and from its own whole map on board (with_own_map)
    on_board = {}
    for key in PER_ROBOT:
        out[key] = {"n": {}}
        robot = {}
        for a in agents:
            if a["id"] not in final:
                continue
            if key == "for_robot":  # on the server: the robot's subset, culled in the ROI views it uploaded
                m, _ = for_robot(vote, report.source_agent, report.agents, a["id"], final[a["id"]],
                                 [k for k in a["_keyframes"] if k.roi is not None])
            else:  # on board: its whole map, culled in every keyframe it holds (with_own_map's default)
                m, _ = for_robot(vote, report.source_agent, report.agents, a["id"], a["_own_map"], a["_own_views"],
                                 min_weight=ON_BOARD_MIN_WEIGHT, max_views=None)
            out[key]["n"][a["id"]] = len(m)
            robot[a["task"]] = _by_protocol(m.to_gaussian_map(), a, protocols, track_iters, track_stride)
            if key == "with_own":
                on_board[a["id"]] = m
        _put_protocols(out[key], robot)
    if renders is not None:
        out["renders"] = write_renders(agents, vote, report, on_board, renders)
    out["vote_report"] = report.to_dict()
    out["cover"] = team_cover(agents, final, vote, report)
    return out


def _put_protocols(block: dict, per_task: dict) -> None:
    """Fill a fused map's ``roi_psnr`` (task → the ``sensor`` figure), ``protocols`` (protocol → task → dB) and
    ``protocols_per_frame`` (protocol → task → frame id → dB) from task → :func:`_by_protocol`."""
    block["roi_psnr"] = {t: v["sensor"][0] for t, v in per_task.items()}
    block["protocols"] = _by_task({t: {q: v[0] for q, v in p.items()} for t, p in per_task.items()})
    block["protocols_per_frame"] = _by_task({t: {q: v[1] for q, v in p.items()} for t, p in per_task.items()})


def _by_protocol(g, a: dict, protocols, track_iters: int, track_stride: int) -> dict:
    """``{protocol: (ROI PSNR dB or None, {frame id: dB})}`` of map ``g`` on agent ``a``'s task: ``sensor`` every frame
    at the sensor's pose (:func:`gausslite.evaluation.evaluate_fused`'s figure); ``keyframes`` the owner's uploaded
    keyframes at the refined poses they carry; ``novel`` the withheld frames through the owner's camera model
    (:meth:`gausslite.mapping.mapper.Mapper.seen_by_this_camera`: the pose and exposure the owner's map predicts,
    exactly as its own map's ``novel``; without it at the owner's predicted views, ``a["_predicted"]``); ``tracked`` /
    ``novel-tracked`` at a pose fitted against ``g`` (:func:`gausslite.team.scoring.score_team_map`, as the sim scores
    its team maps); ``ROBOT_CAMERA`` every frame through the owner's camera model."""
    roi_fn = task_roi(a["_annotations"], a["task"])
    rest = [q for q in dict.fromkeys(protocols) if q != "sensor"
            and (q not in WITHHELD_PROTOCOLS or a.get("_novel") is not None)]
    camera = a["_seen"](g) if "_seen" in a else None
    todo = [q for q in rest if not (q == "novel" and camera is not None)]
    res = team_scoring.score_team_map(
        g, a["_frames"], roi_fn, todo, track_iters=track_iters, track_stride=track_stride,
        keyframe_poses={int(k.frame_id): k.c2w.double().numpy() for k in a["_keyframes"]},
        novel_ids=a.get("_novel"), novel_views=a.get("_predicted"))
    sensor = evaluate_fused_frames(g, a["_frames"], a["_annotations"], a["task"])
    out = {"sensor": (_mean(sensor), sensor), **{q: (v["roi_psnr"], v["roi_psnr_per_frame"]) for q, v in res.items()}}
    if camera is not None:
        if "novel" in rest:
            held = set(a["_novel"])
            per = roi_psnr_frames(camera, [fr for fr in a["_frames"] if int(fr.frame_id) in held], roi_fn)
            out["novel"] = (_mean(per), per)
        per = roi_psnr_frames(camera, a["_frames"], roi_fn)  # the robot's own camera model (ROBOT_CAMERA)
        out[ROBOT_CAMERA] = (_mean(per), per)
    return out


def _mean(per_frame: dict) -> Optional[float]:
    return float(np.mean(list(per_frame.values()))) if per_frame else None


def write_renders(agents: list[dict], vote, report, on_board: dict, folder: Path) -> dict:
    """One picture per robot (``folder/<task>.png``): at its middle withheld frame, at the sensor's pose, its own map |
    the team vote with the other robots' blending weight in red (:func:`gausslite.fusion.diagnose.cover_image`) | the
    team map made on board | the frame, each with the task's ROI outlined in green. Returns agent id → the file."""
    import cv2  # lazy: only this picture needs OpenCV here

    from gausslite.evaluation import render_map
    from gausslite.fusion.diagnose import cover_image

    folder.mkdir(parents=True, exist_ok=True)
    files = {}
    for a in agents:
        ids = a["_novel"] or [int(f.frame_id) for f in a["_frames"]]
        fid = ids[len(ids) // 2]
        frame = next(f for f in a["_frames"] if int(f.frame_id) == fid)
        roi = task_roi(a["_annotations"], a["task"])(frame)
        outline = cv2.morphologyEx(roi.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8)) > 0

        def panel(bgr: np.ndarray, title: str) -> np.ndarray:
            img = bgr.copy()
            img[outline] = (0, 255, 0)
            cv2.putText(img, title, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
            return img

        def rendered(g) -> np.ndarray:
            rgb = render_map(g.to_gaussian_map(), frame).color.clamp(0, 1).cpu().numpy()
            return cv2.cvtColor((rgb * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)

        foreign = report.source_agent != list(report.agents).index(a["id"])
        panels = [panel(rendered(a["_own_map"]), "own map"),
                  panel(cover_image(vote, foreign, RoiView.from_frame(frame, roi)), "team vote (others in red)"),
                  panel(rendered(on_board[a["id"]]), "team map made on board"),
                  panel(cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR), f"frame {fid} (withheld)")]
        path = folder / f"{a['task']}.png"
        cv2.imwrite(str(path), np.concatenate(panels, axis=1))
        files[a["id"]] = str(path)
    return files


def team_cover(agents: list[dict], final: dict, vote, report, stride: int = 2) -> dict:
    """What draws each robot's ROI in the team vote map (:func:`gausslite.team.scoring.team_cover`, the sim report's
    "what covers each robot's ROI"): the final subsets ``final`` (agent id → ``GaussianArrays``), the vote map
    ``vote`` and its ``VoteReport``, each robot's views every ``stride``-th frame of its sequence that shows its ROI
    (ground truth). Returns agent id → ``{"mass", "foreign", "own_missing", "top_foreign" (3)}``."""
    if not final:
        return {}
    robots = {a["id"]: (a["_frames"], a["_annotations"], a["task"]) for a in agents}
    cov, _ = team_scoring.team_cover(final, vote, report, robots, stride, top=3)
    return {aid: {k: c[k] for k in ("mass", "foreign", "own_missing", "top_foreign")} for aid, c in cov.items()}


def cover_table(runs: list[dict]) -> str:
    """Markdown: per team and robot, the share of its ROI pixels' blending weight in the vote map drawn by its own
    rows, by the other robots' rows in their task region or only in their context, left uncovered, the others' rows
    over it (weighted extent, share in front of the ROI surface) and the robot's own rows the vote dropped (share of
    its subset's ROI weight); mean over runs and, in brackets, the range."""
    def rng(v: list) -> str:
        v = [x for x in v if x is not None]
        if not v:
            return "–"
        return f"{np.mean(v):.2f}" + (f" ({min(v):.2f}–{max(v):.2f})" if len(v) > 1 else "")

    lines = ["| team | robot, task | own | others, task region | others, context | uncovered | others' extent (m) | "
             "others in front | own ROI weight dropped | runs |", "|---|---|---|---|---|---|---|---|---|---|"]
    for team in sorted({r["team"] for r in runs}):
        rs = [r for r in runs if r["team"] == team]
        for aid in [a["id"] for a in rs[0]["agents"]]:
            cs = [next(a for a in r["agents"] if a["id"] == aid).get("cover") for r in rs]
            cs = [c for c in cs if c]
            if not cs:
                continue
            task = next(a for a in rs[0]["agents"] if a["id"] == aid)["task"]
            lines.append(
                f"| {team} | {aid}, {task} | {rng([c['mass']['own'] for c in cs])} | "
                f"{rng([c['mass']['foreign_task'] for c in cs])} | {rng([c['mass']['foreign_context'] for c in cs])} | "
                f"{rng([c['mass']['uncovered'] for c in cs])} | "
                f"{rng([c['foreign'].get('weighted_extent_m') for c in cs])} | "
                f"{rng([c['foreign'].get('weight_in_front') for c in cs])} | "
                f"{rng([c['own_missing'].get('weight_share') for c in cs])} | {len(cs)} |")
    return "\n".join(lines)


def _by_task(per_task: dict) -> dict:
    """``{task: {protocol: v}}`` → ``{protocol: {task: v}}``."""
    return {q: {t: v[q] for t, v in per_task.items() if q in v}
            for q in dict.fromkeys(q for v in per_task.values() for q in v)}


def run_team(team: str, budget: float, run: int, work: Path, eval_stride: int = 5, overrides=(),
             protocols=PROTOCOLS, track_iters: int = TRACK_ITERS, track_stride: int = TRACK_STRIDE,
             novel_every: int = NOVEL_EVERY, renders: Optional[Path] = None) -> dict:
    """One run of a team: every agent live, one after the other (:func:`run_missions`), then the fused figures. Each agent's row gains
    ``protocols``: ``{protocol: {"own_roi_psnr", "concat_roi_psnr", "vote_roi_psnr", …, "for_robot_roi_psnr"}}``, its
    own and every fused map on its task under that protocol (the top-level figures are ``sensor``'s), each with its
    per-frame figures (``own_per_frame``, ``vote_per_frame``, …: frame id → dB, the pairs of the summary's gains).
    The run records how its missions ended (``end_state``: the first failed agent's, else ``FINISHED``; ``error``:
    each failed agent's, :func:`bench._missions.describe`; ``frames_failed``, ``corrections_rejected``: summed). A run
    the harness stopped (:class:`TeamMissionFailed`) is returned as ``{"team", "budget", "run", "end_state": "FAILED",
    "error", "agents": [each robot's end state]}``, without figures."""
    try:
        runner, loaded = run_missions(team, budget, run, SCENES[TEAMS[team]["scene"]]["cap"], work, overrides,
                                      novel_every)
    except TeamMissionFailed as e:
        return {"team": team, "budget": budget, "run": run, "end_state": "FAILED", "error": str(e),
                "frames_failed": sum(int(a.get("frames_failed") or 0) for a in e.agents),
                "corrections_rejected": sum(int(a.get("corrections_rejected") or 0) for a in e.agents),
                "agents": e.agents}
    try:
        agents = [agent_row(runner.missions[p.name], loaded[p.name], REFERENCE_BUDGET_S / budget, protocols,
                            track_iters, track_stride) for p in runner.plans]
    finally:
        runner.close()
    fused = fused_scores(agents, fuse_settings(), run, eval_stride, protocols, track_iters, track_stride,
                         renders / f"{team}_run{run}" if renders is not None else None)
    for a in agents:
        for k in [k for k in a if k.startswith("_")]:
            a.pop(k)
        for key in (*FUSED_KEYS, *PER_ROBOT):
            a[f"{key}_roi_psnr"] = fused[key]["roi_psnr"].get(a["task"])
        a["cover"] = fused["cover"].get(a["id"])
        own = a.pop("own_protocols")
        if ROBOT_CAMERA in fused["vote"]["protocols"]:
            own[ROBOT_CAMERA] = own["sensor"]  # the own map is scored through its camera model already
        keys = (*FUSED_KEYS, *PER_ROBOT)
        a["own_per_frame"] = own["sensor"]["roi_psnr_per_frame"]
        a.update({f"{key}_per_frame": fused[key]["protocols_per_frame"].get("sensor", {}).get(a["task"])
                  for key in keys})
        a["protocols"] = {q: {"own_roi_psnr": v["roi_psnr"], "own_frames": v["frames_scored"],
                              "own_per_frame": v["roi_psnr_per_frame"],
                              **({"pose": "predicted"} if q == "novel" else {}),
                              **{f"{key}_roi_psnr": fused[key]["protocols"].get(q, {}).get(a["task"]) for key in keys},
                              **{f"{key}_per_frame": fused[key]["protocols_per_frame"].get(q, {}).get(a["task"])
                                 for key in keys}}
                          for q, v in own.items()}
    for key in (*FUSED_KEYS, *PER_ROBOT):
        fused[key].pop("protocols_per_frame", None)  # in the agents' rows
    bad = [a for a in agents if failed(a)]
    return {"team": team, "budget": budget, "run": run,
            "end_state": next((a["end_state"] for a in bad if a["end_state"] != END_OK), END_OK),
            "error": "; ".join(describe(a, ("id",)) for a in bad),
            "frames_failed": sum(int(a.get("frames_failed") or 0) for a in agents),
            "corrections_rejected": sum(int(a.get("corrections_rejected") or 0) for a in agents),
            "agents": agents, "fused": fused}


def summarise(runs: list[dict]) -> dict:
    """Per team: per agent the mean ± std over runs of share %, upload ratio, the refinement views' bytes over the final
    subset's, bytes per Gaussian, own and fused ROI PSNR, the gains fused − own and vote − concat
    (:func:`gain_over_runs`: the mean of the paired per-frame differences over runs × frames with its 95 % interval,
    ``<gain>_gain``, beside the per-run spread ``<gain>_std``), and the goals' checks (share ≤ 25 %, upload ≤ 1.5×,
    views ≤ 8× the subset, refine ≥ own, vote ≥ concat, overlap: vote ≥ own). Runs whose missions failed
    (:func:`bench._missions.failed`) are left out (a team with any lists them under ``failed_runs``); a team whose
    every run failed has no block."""
    out = {}
    for team in sorted({r["team"] for r in runs}):
        every = [r for r in runs if r["team"] == team]
        rs = succeeded(every)
        if not rs:
            continue
        ids = [a["id"] for a in rs[0]["agents"]]
        blk = {"runs": len(rs), "overlap": TEAMS[team]["overlap"], "agents": {}}
        if len(rs) < len(every):
            blk["failed_runs"] = failure_rows(every, ("run",))
        for aid in ids:
            per = [next(a for a in r["agents"] if a["id"] == aid) for r in rs]
            row = {"task": per[0]["task"]}
            for k in ("share_pct", "upload_ratio", "view_ratio", "bytes_per_gaussian", "own_roi_psnr",
                      "concat_roi_psnr", "vote_roi_psnr", "vote_r1_roi_psnr", "refine_roi_psnr", "refine_long_roi_psnr",
                      "for_robot_roi_psnr", "with_own_roi_psnr", "keyframes", "iters_per_keyframe", "pushes",
                      "n_gaussians"):
                v = [a[k] for a in per if a.get(k) is not None]
                row[k] = float(np.mean(v)) if v else None
                row[k + "_std"] = float(np.std(v, ddof=1)) if len(v) > 1 else 0.0
            for k in ("vote_minus_own", "refine_minus_own", "vote_minus_concat", "refine_long_minus_own",
                      "for_robot_minus_own", "with_own_minus_own"):
                row.update(gain_over_runs(per, *k.rsplit("_minus_", 1), name=k))
            row["protocols"] = _summarise_protocols(per)
            blk["agents"][aid] = row
        ag = blk["agents"].values()
        # the fused − own goals are judged under novel where it was scored (the map at the pose the robot would
        # use, on views no map trained on; under sensor a fused map renders the bare sensor pose, the own map its
        # robot's camera model), else under sensor
        lead = [(a.get("protocols") or {}).get("novel") or a for a in ag]
        blk["goals_protocol"] = "novel" if all((a.get("protocols") or {}).get("novel") for a in ag) else "sensor"
        blk["goals"] = {
            "share_le_25pct": all(a["share_pct"] is not None and a["share_pct"] <= 25.0 for a in ag),
            "upload_le_1.5x": all(a["upload_ratio"] is not None and a["upload_ratio"] <= 1.5 for a in ag),
            "views_le_8x": all(a.get("view_ratio") is not None and a["view_ratio"] <= 8.0 for a in ag),
            "refine_ge_own": all(a["refine_minus_own"] is not None and a["refine_minus_own"] >= 0 for a in lead),
            "refine_long_ge_own": all(a.get("refine_long_minus_own") is not None and a["refine_long_minus_own"] >= 0
                                      for a in ag),
            "vote_ge_concat": all(a["vote_minus_concat"] is not None and a["vote_minus_concat"] >= 0 for a in ag),
            "for_robot_ge_own_minus_0.5": all(a.get("for_robot_minus_own") is not None and a["for_robot_minus_own"] >= -0.5
                                              for a in lead),
            "with_own_ge_own_minus_0.1": all(a.get("with_own_minus_own") is not None
                                             and a["with_own_minus_own"] >= -0.1 for a in lead),
        }
        if blk["overlap"]:
            blk["goals"]["vote_ge_own"] = all(a["vote_minus_own"] is not None and a["vote_minus_own"] >= 0 for a in lead)
        out[team] = blk
    return out


def gain_over_runs(rows: list[dict], treated: str, baseline: str, name: Optional[str] = None) -> dict:
    """``treated − baseline`` (map names: ``vote``, ``own``, …) over one agent's rows of several runs:
    ``{name: gain, name_std: spread over runs, name_gain: the paired per-frame gain}``. The gain is the mean of the
    paired per-frame differences over runs × frames (``<map>_per_frame``; :func:`gausslite.stats.paired_gain`, with
    its 95 % interval); rows without per-frame figures (older runs) give the mean of the per-run differences and no
    interval. The spread is the std of the per-run differences of the means."""
    name = name or f"{treated}_minus_{baseline}"
    d = [r[f"{treated}_roi_psnr"] - r[f"{baseline}_roi_psnr"] for r in rows
         if r.get(f"{treated}_roi_psnr") is not None and r.get(f"{baseline}_roi_psnr") is not None]
    pairs = [(r.get(f"{treated}_per_frame"), r.get(f"{baseline}_per_frame")) for r in rows]
    g = (paired_gain([t for t, _ in pairs], [b for _, b in pairs])
         if rows and all(t is not None and b is not None for t, b in pairs) else None)
    g = g if g and g["n"] else None
    return {name: g["gain"] if g else (float(np.mean(d)) if d else None),
            name + "_std": float(np.std(d, ddof=1)) if len(d) > 1 else 0.0, name + "_gain": g}


def _summarise_protocols(per: list[dict]) -> dict:
    """One agent's rows over runs → ``{protocol: {"own_roi_psnr", …, "for_robot_roi_psnr" (means), their "_std",
    "vote_minus_own", "for_robot_minus_own", "refine_minus_own", and "refine_minus_vote" (what the refinement adds to
    the vote it starts from) (:func:`gain_over_runs`: paired per frame over runs × frames, with "_gain" and the
    per-run "_std"), "runs"}}``."""
    names = list(dict.fromkeys(q for a in per for q in a.get("protocols", {})))
    out = {}
    for q in names:
        rows = [a["protocols"][q] for a in per if q in a.get("protocols", {})]
        blk = {"runs": len(rows)}
        for k in ("own_roi_psnr", *(f"{key}_roi_psnr" for key in (*FUSED_KEYS, *PER_ROBOT))):
            v = [r[k] for r in rows if r.get(k) is not None]
            blk[k] = float(np.mean(v)) if v else None
            blk[k + "_std"] = float(np.std(v, ddof=1)) if len(v) > 1 else 0.0
        for key in ("vote", "refine", *PER_ROBOT):
            blk.update(gain_over_runs(rows, key, "own"))
        blk.update(gain_over_runs(rows, "refine", "vote"))  # what the refinement's views add to the vote
        out[q] = blk
    return out


def protocol_table(result: dict) -> str:
    """Markdown table of every team agent's own and fused maps under each scoring protocol (mean ± std over runs;
    the gains fused − own paired per frame over runs × frames [95 % interval]; docs/realtime.md#scoring-protocols:
    ``novel`` the maps at the pose the robot would use on views no map trained on, ``tracked`` / ``novel-tracked``
    at a pose fitted to each map, how well a robot could localise against it)."""
    lines = ["| team | agent, task | protocol | own ROI PSNR | concat | vote | refine | for robot | with own | "
             "vote − own | refine − own | for robot − own | with own − own |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for team, blk in result["teams"].items():
        for aid, a in blk["agents"].items():
            for q, v in (a.get("protocols") or {}).items():
                lines.append(
                    f"| {team} | {aid}, {a['task']} | {q} | {_pm(v['own_roi_psnr'], v['own_roi_psnr_std'])} | "
                    f"{_pm(v['concat_roi_psnr'], v['concat_roi_psnr_std'])} | {_pm(v['vote_roi_psnr'], v['vote_roi_psnr_std'])} | "
                    f"{_pm(v['refine_roi_psnr'], v['refine_roi_psnr_std'])} | "
                    f"{_pm(v['for_robot_roi_psnr'], v['for_robot_roi_psnr_std'])} | "
                    f"{_pm(v.get('with_own_roi_psnr'), v.get('with_own_roi_psnr_std', 0.0))} | "
                    f"{_gain_pm(v, 'vote_minus_own')} | {_gain_pm(v, 'refine_minus_own')} | "
                    f"{_gain_pm(v, 'for_robot_minus_own')} | {_gain_pm(v, 'with_own_minus_own')} |")
    return "\n".join(lines)


#: the maps a long-mission table compares with each robot's own map: (summary key, column title)
LONG_COLUMNS = (("vote", "vote"), ("refine", "served team map (vote + refine)"),
                ("for_robot", "map for the robot (server)"), ("with_own", "team map made on board"))


def long_table(result: dict, q: str = "novel") -> str:
    """docs/sharing.md's long-mission table: per team and robot its own map's ROI PSNR under protocol ``q``, each
    map of :data:`LONG_COLUMNS` − the own map, and the served team map − the vote, what the refinement's views add
    (each the paired per-frame gain over runs, run-clustered 95 % interval; a summary without it: a dash)."""
    lines = ["| team | robot, task | own map (dB) | " + " | ".join(f"{t} − own" for _, t in LONG_COLUMNS)
             + " | served team map − vote |", "|---|---|---|" + "---|" * (len(LONG_COLUMNS) + 1)]
    for team, blk in result["teams"].items():
        for aid, a in blk["agents"].items():
            v = (a.get("protocols") or {}).get(q)
            if not v:
                continue
            cells = [_gain_cell(v, f"{k}_minus_own") for k, _ in LONG_COLUMNS] + [_gain_cell(v, "refine_minus_vote")]
            lines.append(f"| {team}{_failed_mark(blk)} | {aid}, {a['task']} | {_f(v['own_roi_psnr'])} | "
                         + " | ".join(cells) + " |")
    if any(blk.get("failed_runs") for blk in result["teams"].values()):
        lines += ["", failed_note("team with a run")]
    return "\n".join(lines)


def _failed_mark(blk: dict) -> str:
    """``" †"`` for a team summary block with failed runs (:func:`summarise`), else ``""``."""
    return f" {FAILED_MARK}" if blk.get("failed_runs") else ""


def _gain_cell(row: dict, key: str) -> str:
    """A gain of :func:`gain_over_runs` as a table cell: the paired per-frame gain [95 % interval], or the mean of
    the per-run gains for rows without per-frame figures (a dash without either)."""
    g = row.get(f"{key}_gain")
    return fmt_gain(g) if g else _f(row.get(key))


def _gain_pm(row: dict, key: str) -> str:
    """A gain of :func:`gain_over_runs` for a table: the paired per-frame gain [95 % interval] with the per-run
    spread, or mean ± std over runs for rows without per-frame figures."""
    g = row.get(f"{key}_gain")
    if g:
        return f"{fmt_gain(g)} (σ runs {_f(row.get(f'{key}_std'))})"
    return _pm(row.get(key), row.get(f"{key}_std", 0.0))


def _f(v, nd=2) -> str:
    return "–" if v is None else f"{v:.{nd}f}"


def _pm(v, s, nd=2) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f} ± {s:.{nd}f}"


def table(result: dict) -> str:
    """Markdown tables of :func:`summarise`'s output."""
    f = result["settings"]["fuse"]
    lines = [f"Keyframe budget {result['settings']['budget']} s, {result['settings']['runs']} run(s); mean ± std over "
             f"runs. ROI PSNR (dB) over every frame of the owner's sequence (`sensor`); gains: the mean of the paired "
             f"per-frame differences over runs × frames [95 % interval] (σ runs: the spread of the per-run gains). "
             f"vote: δ = {f['voxel_size']} m, contest "
             f"radius {f['contest_radius']}; vote r1: radius 1; refine: vote + {f['refine_iters']} iterations; "
             f"refine {LONG_REFINE_ITERS}: vote + {LONG_REFINE_ITERS} iterations.", "",
             "| team | agent, task | share % | upload / final | B / Gaussian | own ROI PSNR | concat | vote | vote r1 | "
             f"refine | refine {LONG_REFINE_ITERS} | for robot | with own | vote − concat | vote − own | "
             "refine − own | for robot − own | with own − own |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for team, blk in result["teams"].items():
        for aid, a in blk["agents"].items():
            lines.append(
                f"| {team}{_failed_mark(blk)} | {aid}, {a['task']} | {_pm(a['share_pct'], a['share_pct_std'], 1)} | "
                f"{_pm(a['upload_ratio'], a['upload_ratio_std'])} | {_pm(a['bytes_per_gaussian'], a['bytes_per_gaussian_std'], 1)} | "
                f"{_pm(a['own_roi_psnr'], a['own_roi_psnr_std'])} | {_pm(a['concat_roi_psnr'], a['concat_roi_psnr_std'])} | "
                f"{_pm(a['vote_roi_psnr'], a['vote_roi_psnr_std'])} | {_pm(a['vote_r1_roi_psnr'], a['vote_r1_roi_psnr_std'])} | "
                f"{_pm(a['refine_roi_psnr'], a['refine_roi_psnr_std'])} | "
                f"{_pm(a['refine_long_roi_psnr'], a['refine_long_roi_psnr_std'])} | "
                f"{_pm(a.get('for_robot_roi_psnr'), a.get('for_robot_roi_psnr_std', 0.0))} | "
                f"{_pm(a.get('with_own_roi_psnr'), a.get('with_own_roi_psnr_std', 0.0))} | "
                f"{_gain_pm(a, 'vote_minus_concat')} | {_gain_pm(a, 'vote_minus_own')} | "
                f"{_gain_pm(a, 'refine_minus_own')} | {_gain_pm(a, 'for_robot_minus_own')} | "
                f"{_gain_pm(a, 'with_own_minus_own')} |")
    goals = list(dict.fromkeys(k for blk in result["teams"].values() for k in blk["goals"]))
    lines += ["", "Goals on a fused map − the robot's own map are judged under `novel` where it was scored (`goals_protocol`).",
              "", "| team | " + " | ".join(goals) + " |", "|---|" + "---|" * len(goals)]
    for team, blk in result["teams"].items():
        g = blk["goals"]
        lines.append(f"| {team} | " + " | ".join("–" if k not in g else "yes" if g[k] else "**no**" for k in goals) + " |")
    return "\n".join(lines)


def plot_team(runs: list[dict], team: str, path: Path) -> None:
    """Fused (vote) ROI PSNR per task over mission time, one line per run, with each owner's final own figure."""
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    rs = [r for r in runs if r["team"] == team]
    tasks = [a["task"] for a in rs[0]["agents"]]
    fig, axes = plt.subplots(1, len(tasks), figsize=(5 * len(tasks), 3.6), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        for r in rs:
            tl = r["fused"]["timeline"]
            ax.plot([e["t"] for e in tl], [e["roi_psnr"][task] for e in tl], "o-", ms=3, alpha=0.8,
                    label=f"vote, run {r['run']}")
            own = next(a for a in r["agents"] if a["task"] == task)["own_roi_psnr"]
            ax.axhline(own, ls="--", lw=1, color=ax.lines[-1].get_color())
        ax.set_title(f"{team}: {task}")
        ax.set_xlabel("mission time (s, sequence clock)")
        ax.set_ylabel("fused ROI PSNR (dB)")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=7, title="dashed: owner's own map, end", title_fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: the figures of the share curve, per agent (``summarise``'s names; each with its ``_std``)
CURVE_KEYS = ("share_pct", "upload_ratio", "view_ratio", "bytes_per_gaussian", "own_roi_psnr", "vote_minus_own",
              "for_robot_minus_own", "with_own_minus_own", "refine_minus_own")
#: the keys of :data:`CURVE_KEYS` a scoring protocol gives (the rest are the robot's bytes, the same under every one)
CURVE_SCORES = ("own_roi_psnr", "vote_minus_own", "for_robot_minus_own", "with_own_minus_own", "refine_minus_own")


def share_bound(result: dict) -> Optional[float]:
    """The ``agent.share.max_fraction`` a team result ran with (its ``--set`` overrides, under that key or its old
    name ``agent.share_max_fraction``), None when not set."""
    for o in result.get("settings", {}).get("overrides", []):
        key, _, val = o.partition("=")
        if key.strip() in ("agent.share.max_fraction", "agent.share_max_fraction"):
            return float(val)
    return None


def share_curve(results: list[dict], default_bound: Optional[float] = None, protocol: Optional[str] = None) -> dict:
    """The share curve (docs/sharing.md#how-much-to-share) from team results run at different share bounds:
    ``{team: {agent_id: {"task", "points": [{"bound", <CURVE_KEYS>, <key>_std, "runs"}, ...]}}}``, points sorted by
    bound. A result without a bound override counts at ``default_bound``. With ``protocol`` (e.g. ``novel``) the own
    map's ROI PSNR and the fused − own gains (:data:`CURVE_SCORES`) are that protocol's (``protocols`` of each agent's
    summary, the paired per-frame gain with its run-clustered interval), else the summary's top-level (``sensor``)
    figures.

    Raises:
        ValueError: a result has no bound and ``default_bound`` is None, two results have the same bound, or an agent
            of a result was not scored under ``protocol``.
    """
    bounds = [default_bound if b is None else b for b in map(share_bound, results)]
    if any(b is None for b in bounds):
        raise ValueError("a team result without agent.share.max_fraction: pass the deployed bound")
    if len(set(bounds)) != len(bounds):
        raise ValueError(f"two results at the same share bound: {bounds}")
    curve: dict = {}
    for b, r in sorted(zip(bounds, results), key=lambda x: x[0]):
        for team, blk in r["teams"].items():
            for aid, a in blk["agents"].items():
                entry = curve.setdefault(team, {}).setdefault(aid, {"task": a["task"], "points": []})
                scores = a
                if protocol is not None:
                    scores = (a.get("protocols") or {}).get(protocol)
                    if not scores:
                        raise ValueError(f"{team} {aid} at bound {b} was not scored under {protocol!r}")
                src = {k: (scores if k in CURVE_SCORES else a) for k in CURVE_KEYS}
                entry["points"].append({"bound": b, "runs": blk.get("runs"),
                                        **{k: src[k].get(k) for k in CURVE_KEYS},
                                        **{f"{k}_std": src[k].get(f"{k}_std") for k in CURVE_KEYS},
                                        **{f"{k}_gain": src[k].get(f"{k}_gain") for k in CURVE_KEYS if "_minus_" in k}})
    return curve


def curve_table(curve: dict) -> str:
    """Markdown table of :func:`share_curve`: per team, agent and bound the share, upload ratio, the refinement views'
    bytes over the final subset's, bytes per Gaussian and the fused ROI PSNR − the robot's own map (vote, team map for
    the robot, team map made on board, vote + refine)."""
    lines = ["| team | agent, task | bound | shared % | upload / final | views / final | B / Gaussian | own ROI PSNR | "
             "vote − own | for robot − own | with own − own | refine − own |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for team, agents in curve.items():
        for aid, e in agents.items():
            for q in e["points"]:
                lines.append(f"| {team} | {aid}, {e['task']} | {100 * q['bound']:g} % | {_f(q['share_pct'], 1)} | "
                             f"{_f(q['upload_ratio'])} | {_f(q.get('view_ratio'))} | {_f(q['bytes_per_gaussian'], 1)} | "
                             f"{_f(q['own_roi_psnr'])} | "
                             f"{_gain_pm(q, 'vote_minus_own')} | {_gain_pm(q, 'for_robot_minus_own')} | "
                             f"{_gain_pm(q, 'with_own_minus_own')} | {_gain_pm(q, 'refine_minus_own')} |")
    return "\n".join(lines)


def write_curve(files: list[str], out: Path, default_bound: float, argv, protocol: Optional[str] = None) -> dict:
    """Read the team results ``files``, write their share curve (:func:`share_curve`, under ``protocol``) into
    ``out`` (its other keys kept; a new file holds the curve alone) and the table beside it
    (``<out stem>_curve.md``); returns the curve."""
    curve = share_curve([json.loads(Path(f).read_text()) for f in files], default_bound, protocol)
    doc = json.loads(out.read_text()) if out.exists() else {}
    doc["share_curve"] = {"sources": [Path(f).name for f in files], "protocol": protocol or "sensor", "teams": curve}
    write_json(out, doc, "team", argv, indent=1)
    md = out.with_name(f"{out.stem}_curve.md")
    md.write_text(f"# bench.team share curve\n\n`python -m bench.team {' '.join(argv or [])}`\n\n"
                  f"Fused ROI PSNR − the robot's own map against the share bound (agent.share.max_fraction), under "
                  f"`{protocol or 'sensor'}`: the paired per-frame gain over runs × frames [95 % interval] and the "
                  f"per-run spread.\n\n{curve_table(curve)}\n")
    print(curve_table(curve))
    return curve


def markdown(result: dict) -> str:
    """A team result's Markdown: the summary (:func:`table`), the protocol table, what draws each robot's ROI and,
    when missions failed, the failed runs (†, left out of the figures)."""
    ok = succeeded(result["runs"])
    md = (table(result) + "\n\n" + protocol_table(result)
          + "\n\nWhat draws each robot's ROI in the team vote map (docs/sharing.md):\n\n" + cover_table(ok))
    bad = failed_team_runs(result["runs"])
    if bad:
        md += ("\n\n" + failed_note("team with a run") + "\n\n"
               + "\n".join(f"- {FAILED_MARK} {describe(r, RUN_KEYS)}" for r in bad))
    return md


#: the fields that name a team run in a failed mission's line
RUN_KEYS = ("team", "budget", "run")


def failed_team_runs(runs: list[dict]) -> list[dict]:
    """The failed team runs of ``runs`` (:func:`bench._missions.failed`) as :func:`bench._missions.failure_rows`."""
    return failure_rows(runs, RUN_KEYS)


def resummarise(src: Path, out: Path, argv) -> dict:
    """Summarise the runs of the team result ``src`` again (:func:`summarise`, the tables) into ``out`` and its
    ``.md``; the JSON keeps the runs' provenance and settings. Returns the result."""
    result = json.loads(src.read_text())
    result["teams"] = summarise(result["runs"])
    result["failed_runs"] = failed_team_runs(result["runs"])
    ran = result.get("provenance", {}).get("command", str(src))
    write_results(out, "team", argv, f": the runs of `{ran}`, summarised again", markdown(result), result)
    return result


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--teams", default=",".join(TEAMS))
    ap.add_argument("--budget", type=float, default=REFERENCE_BUDGET_S, help="seconds per keyframe")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--eval-stride", type=int, default=5, help="frame stride of the fused-over-time scores")
    ap.add_argument("--protocols", default=",".join(PROTOCOLS),
                    help="scoring protocols of the own and final fused maps (sensor always; "
                         "docs/realtime.md#scoring-protocols)")
    ap.add_argument("--track-iters", type=int, default=TRACK_ITERS,
                    help="tracked / novel-tracked protocols: Adam steps per frame")
    ap.add_argument("--track-stride", type=int, default=TRACK_STRIDE, help="tracked protocol: every this many frames")
    ap.add_argument("--novel-every", type=int, default=NOVEL_EVERY,
                    help="novel / novel-tracked protocols: every k-th frame of the team's sequence is withheld from "
                         "every robot, scored at the pose the robot's map predicts (novel) and at a pose tracked "
                         "against each map (novel-tracked) (0: none withheld, neither protocol)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="agent config override, e.g. agent.share.coverage=0.9")
    ap.add_argument("--out", default=str(RESULTS / "team.json"))
    ap.add_argument("--work", default="/tmp/gausslite_bench_realtime")
    ap.add_argument("--curve", default=None, metavar="FILE[,FILE...]",
                    help="run nothing: read team results run at different agent.share.max_fraction bounds and write "
                         "their share curve into --out (key share_curve) and <out>_curve.md")
    ap.add_argument("--renders", default=None, metavar="DIR",
                    help="also write, per run and robot, its own map | the team vote (the others in red) | the team "
                         "map made on board | the frame, at its middle withheld frame (DIR/<team>_run<k>/<task>.png)")
    ap.add_argument("--summary-of", default=None, metavar="FILE",
                    help="run nothing: summarise the runs of a team result again (this version's goals and tables) "
                         "into --out, keeping the runs' provenance")
    ap.add_argument("--default-bound", type=float, default=0.08,
                    help="--curve: the bound of a result run without an agent.share.max_fraction override")
    ap.add_argument("--curve-protocol", default=None, metavar="PROTOCOL",
                    help="--curve: the scoring protocol of the figures (e.g. novel, as the long-mission goals are "
                         "judged; default: the summary's sensor figures)")
    add_allow_failed(ap)
    args = ap.parse_args(argv)
    if args.summary_of:
        res = resummarise(Path(args.summary_of), Path(args.out), argv)
        return exit_code(res["runs"], args.allow_failed, "bench.team", RUN_KEYS)
    if args.curve:
        if args.curve_protocol is not None and args.curve_protocol not in PROTOCOLS:
            ap.error(f"unknown --curve-protocol {args.curve_protocol!r} (known: {', '.join(PROTOCOLS)})")
        write_curve([f for f in args.curve.split(",") if f], Path(args.out), args.default_bound, argv,
                    args.curve_protocol)
        return 0

    teams = [t for t in args.teams.split(",") if t]
    for t in teams:
        if t not in TEAMS:
            ap.error(f"unknown team {t!r} (known: {', '.join(TEAMS)})")
    protocols = tuple(dict.fromkeys(("sensor", *(q.strip() for q in args.protocols.split(",") if q.strip()))))
    if any(q not in PROTOCOLS for q in protocols):
        ap.error(f"unknown protocol in {args.protocols!r} (known: {', '.join(PROTOCOLS)})")
    if args.track_stride < 1 or args.track_iters < 0:
        ap.error("--track-stride must be >= 1 and --track-iters >= 0")
    if args.novel_every == 1 or args.novel_every < 0:
        ap.error("--novel-every must be 0 (off) or >= 2")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    runs = []
    for team, run in tqdm([(t, r) for t in teams for r in range(args.runs)], desc="team runs", unit="run"):
        r = run_team(team, args.budget, run, work, args.eval_stride, args.overrides, protocols, args.track_iters,
                     args.track_stride, args.novel_every, Path(args.renders) if args.renders else None)
        runs.append(r)
        if "fused" not in r:  # the harness stopped the team
            tqdm.write(f"{team} run {run}: {FAILED_MARK} {r['end_state']}: {r['error']} (recorded, left out)")
            out.with_suffix(".partial.json").write_text(json.dumps({"runs": runs}, indent=1))
            continue
        tqdm.write(f"{team} run {run}: " + "; ".join(
            f"{a['id']} {a['task']} share {_f(a['share_pct'], 1)} % upload {_f(a['upload_ratio'])}x own "
            f"{_f(a['own_roi_psnr'])} concat {_f(a['concat_roi_psnr'])} vote {_f(a['vote_roi_psnr'])} "
            f"refine {_f(a['refine_roi_psnr'])}" + (f" ({a['last_error']})" if a.get("last_error") else "")
            for a in r["agents"]))
        out.with_suffix(".partial.json").write_text(json.dumps({"runs": runs}, indent=1))
    result = {"settings": {"budget": args.budget, "runs": args.runs, "eval_stride": args.eval_stride,
                           "protocols": list(protocols), "track_iters": args.track_iters,
                           "track_stride": args.track_stride,
                           "overrides": args.overrides, "fuse": fuse_settings(), "machine": platform.machine(),
                           "cpus": os.cpu_count(), "wall_s": time.time() - t0},
              "teams": summarise(runs), "failed_runs": failed_team_runs(runs), "runs": runs}
    for team in teams:
        if any(r["team"] == team for r in succeeded(runs)):
            plot_team(succeeded(runs), team, out.with_name(f"{out.stem}_{team}.png"))
    write_results(out, "team", argv, f": {len(runs)} runs, {(time.time() - t0) / 60:.1f} min", markdown(result),
                  result)
    out.with_suffix(".partial.json").unlink(missing_ok=True)  # the runs are in the result now
    return exit_code(runs, args.allow_failed, "bench.team", RUN_KEYS)


if __name__ == "__main__":
    sys.exit(main())
