"""The figures of a team mission's report (``report.json``): each robot's entry from its Finish summary
(:func:`agent_report`), each fused map's gain over the task's robot's own map (:func:`fused_minus_own`,
:func:`protocol_minus_own`), and the figures of other runs merged in (matched uniform agents, a ``roi_render: context``
run, an every-frame offline run). Gains are the mean of the paired per-frame differences of ROI PSNR (dB) with their
95 % interval (:func:`gausslite.stats.paired_gain`).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Dict, Optional

from gausslite.evaluation import PROTOCOLS, current_protocols
from gausslite.stats import paired_gain

if TYPE_CHECKING:
    from gausslite.mission.scoring import MissionSummaryData
    from gausslite.team.plan import AgentPlan


FUSED_KEYS = ("concat", "vote", "for_robot", "with_own", "refine", "team_map")
#: the fused keys made once per robot (each task is scored on its robot's map)
PER_ROBOT = ("for_robot", "with_own")
#: what each fused key is, for the report
FUSED_HELP = {
    "concat": "plain concatenation of the agents' ROI subsets",
    "vote": "the team map: per-voxel κ vote (paper Sec. III-E)",
    "for_robot": "the team map as each robot uses it (`Fuse(for_agent=…)`): its own subset whole, and the others' "
                 "voted rows except those over its ROI; each task scored on the map made for its robot",
    "with_own": "the team map as each robot loads it on board (`gausslite.fusion.guard.with_own_map`): its own whole "
                "map, and the others' voted rows except those that draw its ROI in its keyframes",
    "refine": "vote + joint refinement over the uploaded views (`Fuse(refine=true)` once the missions ended)",
    "team_map": "the team map the fusion server keeps refined in the background (`Fuse(team_map=true)`), once it holds "
                "the final subsets and views",
}


def attach_context_baseline(report: dict, context_report: dict) -> dict:
    """Copy each agent's own-map ROI PSNR of a run mapped with ``mapper.roi_render: context`` (same
    scene and tasks, e.g. ``gausslite sim ... --set mapper.roi_render=context``) into ``report`` as
    ``own_roi_psnr_context``, and per task ``vote_minus_own_context`` (fused vote minus it: the mean of the paired
    per-frame differences of the ``sensor`` protocol, ``vote_minus_own_context_gain`` with its 95 % interval,
    :func:`gausslite.stats.paired_gain`; None when either side has no per-frame figures).

    Raises:
        ValueError: the context run used another roi_render mode, or its agents/tasks differ.
    """
    mode = ((context_report.get("settings") or {}).get("mapper") or {}).get("roi_render", "context")
    if mode != "context":
        raise ValueError(f"the context report was mapped with roi_render={mode!r}, not 'context'")
    ctx = {(a["id"], a["task"]): a for a in context_report.get("agents", [])}
    vote = _fused_frames(report, "vote", "sensor")
    for a in report["agents"]:
        if (a["id"], a["task"]) not in ctx:
            raise ValueError(f"the context report has no agent {a['id']} on task {a['task']}")
        c = ctx[(a["id"], a["task"])]
        a["own_roi_psnr_context"] = c.get("roi_psnr")
        g = _pair(vote.get(a["task"]), own_frames(c, "sensor"))
        a["vote_minus_own_context_gain"] = g
        a["vote_minus_own_context"] = None if g is None else g["gain"]
    return report


def own_frames(agent: dict, protocol: str) -> Optional[dict]:
    """Frame id → ROI PSNR (dB) of an agent's own map under ``protocol`` (its report entry's
    ``protocols[protocol]["roi_psnr_per_frame"]``, the name read as :func:`gausslite.evaluation.current_protocols`
    reads an older report's); None when the report has none."""
    v = current_protocols(agent.get("protocols")).get(protocol) or {}
    return v.get("roi_psnr_per_frame")


def _fused_frames(report: dict, key: str, protocol: str) -> Dict[str, dict]:
    """task → frame id → ROI PSNR (dB) of fused map ``key`` under ``protocol`` (empty when not scored)."""
    per = current_protocols(((report.get("fused") or {}).get(key) or {}).get("protocols")).get(protocol) or {}
    return {t: v.get("roi_psnr_per_frame") for t, v in per.items() if v.get("roi_psnr_per_frame") is not None}


def _pair(treated: Optional[dict], baseline: Optional[dict]) -> Optional[dict]:
    """The paired per-frame gain ``treated − baseline`` (:func:`gausslite.stats.paired_gain`), None without figures
    on either side or without a common frame."""
    if treated is None or baseline is None:
        return None
    g = paired_gain(treated, baseline)
    return g if g["n"] else None


def attach_uniform_baseline(report: dict, baseline: dict) -> dict:
    """Put the own-map figures of a matched uniform run (the same sim with ``mapper.mode=uniform``: same scene,
    tasks, keyframe budget and Gaussian budget) beside each agent of ``report``: ``uniform_roi_psnr``,
    ``uniform_roi_psnr_all_frames`` (realtime runs), ``uniform_psnr``, ``uniform_n_gaussians``, ``uniform_protocols``
    (uniform's ROI PSNR per protocol) and the gains GaussLite − uniform as means of paired per-frame differences with
    their 95 % interval (:func:`gausslite.stats.paired_gain`): ``gain_by_protocol`` (protocol → gain), and
    ``task_gain_db`` / ``task_gain``, the ``sensor`` protocol's (every frame). A gain is None where either report has
    no per-frame figures.

    Raises:
        ValueError: the baseline was not mapped in uniform mode, or its agents/tasks differ.
    """
    mode = ((baseline.get("settings") or {}).get("mapper") or {}).get("mode")
    if mode != "uniform":
        raise ValueError(f"the baseline report was mapped with mapper.mode={mode!r}, not 'uniform'")
    base = {(a["id"], a["task"]): a for a in baseline.get("agents", [])}
    for a in report["agents"]:
        b = base.get((a["id"], a["task"]))
        if b is None:
            raise ValueError(f"the baseline report has no agent {a['id']} on task {a['task']}")
        a["uniform_roi_psnr"] = b.get("roi_psnr")
        a["uniform_roi_psnr_all_frames"] = b.get("roi_psnr_all_frames")
        a["uniform_psnr"] = b.get("psnr")
        a["uniform_n_gaussians"] = b.get("n_gaussians")
        uni = current_protocols(b.get("protocols"))
        a["uniform_protocols"] = {q: (v or {}).get("roi_psnr") for q, v in uni.items()}
        a["gain_by_protocol"] = {q: _pair(own_frames(a, q), own_frames(b, q))
                                 for q in current_protocols(a.get("protocols")) if q in uni}
        a["task_gain"] = a["gain_by_protocol"].get("sensor")
        a["task_gain_db"] = None if a["task_gain"] is None else a["task_gain"]["gain"]
    report["uniform_baseline"] = True
    return report


def load_offline(path: str | Path) -> Dict[str, Optional[float]]:
    """Agent id → every-frame ROI PSNR of an earlier non-realtime ``report.json`` (or its folder): its
    ``roi_psnr_all_frames`` when present, else its ``roi_psnr`` (mean over the mapped frames, which are all
    frames in an every-frame run).

    Raises:
        FileNotFoundError: no report. ValueError: not a simulation report, or a realtime one.
    """
    p = Path(path)
    p = p / "report.json" if p.is_dir() else p
    if not p.is_file():
        raise FileNotFoundError(f"offline report not found: {p}")
    try:
        rep = json.loads(p.read_text())
        agents = rep["agents"]
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{p} is not a simulation report.json: {e}") from None
    if rep.get("realtime"):
        raise ValueError(f"{p} is a realtime run; give an every-frame run (gausslite sim without --realtime)")
    return {a["id"]: a.get("roi_psnr_all_frames", a.get("roi_psnr")) for a in agents}


def agent_report(p: AgentPlan, s: MissionSummaryData, st: dict, offline: Optional[Dict[str, Optional[float]]]) -> dict:
    """One agent's entry of ``report["agents"]``.

    Args:
        p: the agent's plan (id, task, dataset).
        s: its Finish summary (:class:`gausslite.mission.scoring.MissionSummaryData`: ``status`` its mission status,
            ``pushes`` one record per push with ``bytes_on_wire``, ``protocols`` its own map's figures per scoring
            protocol; ROI PSNR in dB, None where no frame showed the ROI).
        st: the fusion server's stats of the agent (``share_pct``, ``keyframes``; empty when unknown).
        offline: agent id → the every-frame ROI PSNR (dB) of an offline run, or None.
    Returns:
        the entry: the agent's figures, its ``push_log`` and its ``protocols`` in report order.
    """
    status = s.status
    return {
        "id": p.name, "task": p.task_id, "task_text": p.task, "dataset": p.dataset,
        "roi_psnr": s.roi_psnr, "psnr": s.psnr,
        "n_gaussians": int(status["n_gaussians"]), "n_shared": int(s.n_shared),
        "share_pct": float(st.get("share_pct", s.share_pct)),
        # agent-side figures: the server stores delta-rebuilt subsets losslessly
        "bytes_on_wire": int(s.bytes_on_wire),
        "bytes_per_gaussian": float(s.bytes_per_gaussian),
        "total_upload_bytes": int(s.total_upload_bytes),
        "final_subset_bytes": int(s.final_subset_bytes),
        "upload_ratio": (s.total_upload_bytes / s.final_subset_bytes) if s.final_subset_bytes else None,
        # the views sent for the fusion refinement (agent.refine_views), beside the subset's bytes
        "view_bytes": int(s.view_bytes), "views_sent": int(s.views_sent), "views_unsent": int(s.views_unsent),
        "view_ratio": (s.view_bytes / s.final_subset_bytes) if s.final_subset_bytes else None,
        "push_log": [{"version": int(q["version"]), "n_shared": int(q["n_shared"]), "n_total": int(q["n_total"]),
                      "bytes_sent": int(q["bytes_on_wire"]), "delta": bool(q["delta"]), "records": int(q["records"]),
                      "removed": int(q["removed"]), "frames_mapped": int(q["frames_mapped"]),
                      "unchanged": bool(q.get("unchanged", False)),
                      "share_pct": 100.0 * q["n_shared"] / q["n_total"] if q["n_total"] else 0.0}
                     for q in s.pushes],
        "pushes": int(status["pushes"]), "frames_mapped": int(status["frames_mapped"]),
        "seconds_per_frame": float(s.seconds_per_frame), "keyframes": int(st.get("keyframes", 0)),
        "frames_received": int(status["frames_received"]), "frames_keyframed": int(status["frames_keyframed"]),
        "frames_skipped": int(status["frames_skipped"]),
        "accept_latency_ms_p99": float(status["accept_latency_ms_p99"]),
        "keyframe_latency_s_p95": float(status["keyframe_latency_s_p95"]),
        "idle_iterations": int(status["idle_iterations"]),
        "keyframe_iterations": int(status["keyframe_iterations"]),
        "roi_psnr_all_frames": s.roi_psnr_all_frames,
        "frames_all": int(s.frames_all),
        "offline_roi_psnr_all_frames": (offline or {}).get(p.name),
        "protocols": {q: {"roi_psnr": v.get("roi_psnr"), "psnr": v.get("psnr"), "ssim": v.get("ssim"),
                          "frames_scored": int(v.get("frames_scored", 0)), "roi_frames": int(v.get("roi_frames", 0)),
                          "roi_psnr_per_frame": {int(k): float(x) for k, x in
                                                 sorted((v.get("roi_psnr_per_frame") or {}).items())},
                          **({"pose": "predicted"} if q == "novel" else {})}
                      for q, v in sorted(s.protocols.items(), key=lambda kv: protocol_order(kv[0]))},
    }


def fused_minus_own(report: dict) -> None:
    """Each fused map's ``minus_own[task]``: its ROI PSNR minus the task's robot's own map, the mean of the paired
    per-frame differences under the ``sensor`` protocol (every frame at the sensor's pose; the own map's figures are
    its Finish summary's), and ``minus_own_gain[task]`` with its 95 % interval (:func:`gausslite.stats.paired_gain`);
    None where either map has no per-frame figures."""
    own = {a["task"]: own_frames(a, "sensor") for a in report["agents"]}
    for key, f in report["fused"].items():
        fused = _fused_frames(report, key, "sensor")
        f["minus_own_gain"] = {t: _pair(fused.get(t), own.get(t)) for t in f["roi_psnr_per_task"]}
        f["minus_own"] = {t: None if g is None else g["gain"] for t, g in f["minus_own_gain"].items()}


def protocol_minus_own(report: dict) -> None:
    """Each fused map's ``protocols[q][task]["minus_own"]``: its ROI PSNR minus the task's robot's own map under the
    same protocol (the agent's ``protocols[q]``; ``q@own``: the own map's ``q``), the mean of the paired per-frame
    differences, and ``["minus_own_gain"]`` with its 95 % interval (:func:`gausslite.stats.paired_gain`)."""
    for f in (report.get("fused") or {}).values():
        for q, per_task in (f.get("protocols") or {}).items():
            for t, v in per_task.items():
                a = next((a for a in report["agents"] if a["task"] == t), {})
                g = _pair(v.get("roi_psnr_per_frame"), own_frames(a, q.split("@")[0]))
                v["minus_own_gain"] = g
                v["minus_own"] = None if g is None else g["gain"]


def fmt(v, nd=2) -> str:
    """``v`` with ``nd`` decimals for a report table; "–" for None or NaN."""
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{nd}f}"


def lead_protocol(report: dict) -> str:
    """The protocol the report leads with: ``novel`` (the map at the pose a robot would use, on views no map trained
    on) when the agents scored withheld frames, else ``sensor``."""
    for a in report["agents"]:
        v = current_protocols(a.get("protocols")).get("novel") or {}
        if v.get("frames_scored"):
            return "novel"
    return "sensor"


def protocol_order(name: str) -> int:
    """Report order of the scoring protocols (:data:`gausslite.evaluation.PROTOCOLS`: ``sensor``, ``keyframes``,
    ``novel``, ``tracked``, ``novel-tracked``)."""
    return PROTOCOLS.index(name) if name in PROTOCOLS else len(PROTOCOLS)
