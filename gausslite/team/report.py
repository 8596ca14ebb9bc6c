"""A team mission's written report: ``report.json``, ``report.md`` and its plots (:func:`write_report`), the
markdown that answers first and details after (:func:`write_markdown`, :func:`answer_markdown`), and an every-frame
offline run's figures merged into a written report (:func:`attach_offline_report`). The figures are
:mod:`gausslite.team.figures`'.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import List, Optional

from gausslite.evaluation import PROTOCOL_QUESTIONS, current_protocols
from gausslite.stats import fmt_gain, significant
from gausslite.team.figures import FUSED_HELP, FUSED_KEYS, PER_ROBOT, fmt, lead_protocol, load_offline, protocol_order
from gausslite.team.plots import plot_fused_timeline, plot_pushes

log = logging.getLogger(__name__)


def attach_offline_report(out: str | Path, offline_report: str | Path) -> dict:
    """Put the every-frame ROI PSNR of ``offline_report`` next to the realtime figures of the finished
    realtime simulation in ``out`` (rewrites ``out/report.json`` and ``out/report.md``; nothing is re-run).

    Raises:
        FileNotFoundError: missing reports. ValueError: ``out`` is not a realtime run, or ``offline_report``
            is one.
    """
    out = Path(out)
    p = out / "report.json"
    if not p.is_file():
        raise FileNotFoundError(f"no report.json in {out}")
    report = json.loads(p.read_text())
    if not report.get("realtime"):
        raise ValueError(f"{p} is not a realtime run (gausslite sim --realtime)")
    offline = load_offline(offline_report)
    for a in report["agents"]:
        a["offline_roi_psnr_all_frames"] = offline.get(a["id"])
    report["offline_report"] = str(offline_report)
    p.write_text(json.dumps(report, indent=2))
    write_markdown(report, out / "report.md")
    return report


def write_report(report: dict, out: Path) -> None:
    """Write the plots (``pushes.png``, ``fused_over_time.png``, named in ``report`` when drawn), ``report.json``
    and ``report.md`` into ``out``."""
    if plot_pushes(report, out / "pushes.png"):
        report["pushes_plot"] = "pushes.png"
    if plot_fused_timeline(report, out / "fused_over_time.png"):
        report["fused_timeline_plot"] = "fused_over_time.png"
    (out / "report.json").write_text(json.dumps(report, indent=2))
    write_markdown(report, out / "report.md")
    log.info("wrote %s and %s (%.0f s)", out / "report.json", out / "report.md", report["seconds"])


def write_markdown(report: dict, path: Path) -> None:
    """Write the human-readable report: the answer first (each robot's own map, the team map a robot can load now,
    the bytes shared, one picture: :func:`_answer_lines`), then the protocols × the maps, then the details (agents,
    pushes, the fused map over time, live figures, baselines, every fused map, what covers each ROI, the renders)."""
    tasks = [a["task"] for a in report["agents"]]
    lines = answer_markdown(report).splitlines()
    lines += _protocol_lines(report)
    lines += ["", "## Agents (own map, own task)", "",
              "| agent | task | ROI PSNR (dB) | Gaussians | shared | shared % | bytes / Gaussian | pushes | "
              "total upload bytes | final subset bytes | upload / final |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for a in report["agents"]:
        lines.append(f"| {a['id']} | {a['task']} | {fmt(a['roi_psnr'])} | {a['n_gaussians']} | {a['n_shared']} | "
                     f"{fmt(a['share_pct'])} | {fmt(a['bytes_per_gaussian'])} | {a.get('pushes', 0)} | "
                     f"{a.get('total_upload_bytes', '–')} | {a.get('final_subset_bytes', '–')} | "
                     f"{fmt(a.get('upload_ratio'))} |")
    if any("own_roi_psnr_context" in a for a in report["agents"]):
        lines += ["", "Own map with `roi_render: context` (this run's agents, or a run of the same sim mapped that "
                  "way) against the fused vote map (`sensor`; gain: mean of the paired per-frame differences "
                  "[95 % interval]):", "",
                  "| agent | task | own ROI PSNR, deployed | own ROI PSNR, context | fused vote | vote − own context |",
                  "|---|---|---|---|---|---|"]
        vote = report["fused"]["vote"]["roi_psnr_per_task"]
        for a in report["agents"]:
            lines.append(f"| {a['id']} | {a['task']} | {fmt(a['roi_psnr'])} | {fmt(a.get('own_roi_psnr_context'))} | "
                         f"{fmt(vote.get(a['task']))} | {fmt_gain(a.get('vote_minus_own_context_gain'))} |")
    lines += ["", "Pushes (bytes sent per push, `Δ` = delta push; share of the map when pushed):", ""]
    for a in report["agents"]:
        cells = ", ".join(f"{q['bytes_sent']} B{' Δ' if q['delta'] else ''} @ {q['share_pct']:.1f} %"
                          for q in a.get("push_log", []))
        lines.append(f"- {a['id']}: {cells or '–'}")
    if report.get("pushes_plot"):
        lines += ["", f"![bytes per push and share over time]({report['pushes_plot']})"]
    lines += _timeline_lines(report)
    lines += _live_lines(report)
    lines += _baseline_lines(report)
    lines += _fused_lines(report, tasks)
    lines += _cover_lines(report)
    lines += ["", "## Renders (render | ground truth | task ROI)", ""]
    for r in report.get("renders", []):
        lines.append(f"**{r['fused']} — {r['task']} (frame {r['frame_id']})**  ")
        lines.append(f"![{r['fused']} {r['task']}]({r['path']})")
        lines.append("")
    path.write_text("\n".join(lines) + "\n")


def answer_markdown(report: dict) -> str:
    """The report's first screen: the title, the scene, the answer table, the maps written and how to open them, and
    one picture (:func:`_answer_lines`); ``gausslite sim`` prints it, ``report.md`` goes on with the details."""
    lines = ["# GaussLite two-agent simulation", "",
             f"Scene: `{report['scene']}` — {report['seconds']:.0f} s wall time."]
    return "\n".join(lines + _answer_lines(report)) + "\n"


#: the team maps a robot can load now, in the order the answer prefers them (report key, how it is asked for)
LOADABLE = (("team_map", "`Fuse(team_map=true)`"), ("with_own", "`with_own_map` on the robot"),
            ("for_robot", "`Fuse(for_agent=…)`"))


def _loadable_cell(report: dict, key: str, q: str, task: str) -> tuple:
    """(ROI PSNR, gain over the own map) cells of loadable map ``key`` on ``task`` under protocol ``q``."""
    v = ((((report.get("fused") or {}).get(key) or {}).get("protocols") or {}).get(q) or {}).get(task) or {}
    if not v:
        return "–", "–"
    return fmt(v.get("roi_psnr")), fmt_gain(v.get("minus_own_gain"))


def _answer_lines(report: dict) -> List[str]:
    """The report's lead: per robot its own map, the team map it can load now (the served team map and the one made
    for it) with the paired gain over its own map, the tracked figure beside it, the bytes it sent; and one picture
    (:func:`_telling_render`)."""
    q = lead_protocol(report)
    tracked = "novel-tracked@own" if q == "novel" else "tracked@own"
    keys = [(k, how) for k, how in LOADABLE if k in (report.get("fused") or {})]
    question = PROTOCOL_QUESTIONS[q]
    lines = ["", "## The answer", "",
             f"ROI PSNR (dB) on each robot's task under `{q}`: {question}"
             + ("" if q == "novel" else " (no frame was withheld from the mappers: `novel` has nothing to score)")
             + ". Gains: mean of the paired per-frame differences [95 % interval]. "
             f"`{tracked}`: the same frames at the pose the robot tracked against its own map: how the team map looks "
             "where the robot localises. Bytes: every subset push and the views sent for the refinement.", "",
             "| robot | task | own map | " + "".join(f"{k} ({how}) | {k} − own | " for k, how in keys)
             + (f"{keys[0][0]} − own, `{tracked}` | " if keys else "") + "bytes sent (subsets + views) |",
             "|---|---|---|" + "---|---|" * len(keys) + ("---|" if keys else "") + "---|"]
    for a in report["agents"]:
        own = (current_protocols(a.get("protocols")).get(q) or {}).get("roi_psnr")
        own = own if own is not None or q != "sensor" else a.get("roi_psnr_all_frames")
        cells = [c for k, _ in keys for c in _loadable_cell(report, k, q, a["task"])]
        if keys:
            cells.append(_loadable_cell(report, keys[0][0], tracked, a["task"])[1])
        sent = int(a.get("total_upload_bytes") or 0) + int(a.get("view_bytes") or 0)
        lines.append(f"| {a['id']} | {a['task']} | {fmt(own)} | " + "".join(f"{c} | " for c in cells) + f"{sent:,} |")
    lines += _map_file_lines(report)
    pic = _telling_render(report, q)
    if pic is not None:
        r, why = pic
        lines += ["", f"![{r['fused']} {r['task']}]({r['path']})", "",
                  f"*{r['fused']} on `{r['task']}`, frame {r['frame_id']} (render | ground truth | ROI): {why}.*"]
    return lines


def _map_file_lines(report: dict) -> List[str]:
    """The maps the simulation wrote, each with the command that opens it (paths relative to the output folder)."""
    rows = [(f"{a}'s own map", f) for a, f in (report.get("own_maps") or {}).items()]
    for key, v in (report.get("fused") or {}).items():
        files = v.get("ply") or {}
        if key in PER_ROBOT:
            rows += [(f"`{key}` for {a}", f) for a, f in files.items()]
        elif files:
            rows.append((f"`{key}`", next(iter(files.values()))))
    if not rows:
        return []
    return ["", "Open a map in the browser with `gausslite view FILE` (from this folder):", "",
            *[f"- {what}: `gausslite view {f}`" for what, f in rows]]


def _telling_render(report: dict, q: str) -> Optional[tuple]:
    """(render entry, why) of the render the answer shows: the first loadable team map's render on the task where it
    differs most from the robot's own map under ``q`` (either way); None without such a render."""
    renders = report.get("renders") or []
    for key, _ in LOADABLE:
        per = ((((report.get("fused") or {}).get(key) or {}).get("protocols") or {}).get(q) or {})
        cands = [r for r in renders if r["fused"] == key]
        if not cands:
            continue
        gain = {t: (v.get("minus_own") if v else None) for t, v in per.items()}

        def size(r):
            g = gain.get(r["task"])
            return -1.0 if g is None else abs(g)

        r = max(cands, key=size)
        g = gain.get(r["task"])
        why = ("the task where the team map differs most from the robot's own map "
               f"({g:+.2f} dB under `{q}`)" if g is not None else "the team map a robot loads now")
        return r, why
    return None


def _fused_lines(report: dict, tasks: List[str]) -> List[str]:
    """Markdown of every fused map's ROI PSNR per task (``sensor``), with its paired gain over the own map."""
    lines = ["", "## Fused maps: ROI PSNR (dB) on each task's ROI", "",
             "Each cell: the fused map's ROI PSNR over every frame at the sensor's pose (`sensor`), and in brackets its "
             "gain over the robot's own map: the mean of the paired per-frame differences [95 % interval].", "",
             "| fused map | " + " | ".join(tasks) + " | mean | Gaussians | seconds |",
             "|---|" + "---|" * (len(tasks) + 3)]
    for key in FUSED_KEYS:
        f = report["fused"].get(key)
        if f is None:
            continue
        mo = f.get("minus_own_gain") or {}
        per = " | ".join(fmt(f["roi_psnr_per_task"].get(t)) + (f" ({fmt_gain(mo[t])})" if mo.get(t) else "")
                         for t in tasks)
        lines.append(f"| {key} | {per} | {fmt(f['roi_psnr_mean'])} | {f['n_gaussians']} | {fmt(f['seconds'])} |")
    lines += [""] + [f"- `{k}`: {FUSED_HELP[k]}" for k in FUSED_KEYS if k in report["fused"]]
    lines += [f"- vote settings: δ = {report['settings']['voxel_size']} m, each voxel contested over its neighbourhood "
              f"of radius {report['settings'].get('contest_radius', 0)} voxels; refinement: "
              f"{report['settings']['refine_iters']} iterations."]
    return lines


def _baseline_lines(report: dict) -> List[str]:
    """Markdown of the matched uniform baseline (``gausslite sim --baseline uniform``): per agent and protocol both
    maps' ROI PSNR and the paired per-frame gain."""
    if not report.get("uniform_baseline"):
        return []
    names = sorted({q for a in report["agents"] for q in (a.get("gain_by_protocol") or {})}, key=protocol_order)
    lines = ["", "## What the task buys: GaussLite against matched uniform agents", "",
             "ROI PSNR (dB) of each robot's own map under each protocol, GaussLite / uniform, and the gain: the mean of "
             "the paired per-frame differences [95 % interval].", "",
             "| agent | task | protocol | GaussLite | uniform | gain (dB) |", "|---|---|---|---|---|---|"]
    for a in report["agents"]:
        own = current_protocols(a.get("protocols"))
        for q in names or ["sensor"]:
            lines.append(f"| {a['id']} | {a['task']} | {q} | {fmt((own.get(q) or {}).get('roi_psnr'))} | "
                         f"{fmt((a.get('uniform_protocols') or {}).get(q))} | "
                         f"{fmt_gain((a.get('gain_by_protocol') or {}).get(q))} |")
    lines += ["", "Full-image PSNR, GaussLite / uniform: " + "; ".join(
        f"{a['id']} {fmt(a.get('psnr'))} / {fmt(a.get('uniform_psnr'))}" for a in report["agents"])
              + ". Gaussians: " + "; ".join(f"{a['id']} {a['n_gaussians']} / {a.get('uniform_n_gaussians', '–')}"
                                            for a in report["agents"]) + ".",
              "", "The uniform agents ran the same sim with `mapper.mode=uniform` (same scene, keyframe rule, keyframe "
              "budget and Gaussian budget; they share nothing). `docs/realtime.md` has the budget sweep."]
    return lines


def _live_lines(report: dict) -> List[str]:
    """Markdown of the live-ingest figures (realtime runs only)."""
    if not report.get("realtime"):
        return []
    src = report.get("offline_report")
    lines = ["", "## Live operation (realtime replay at the dataset clock)", "",
             "| agent | received | keyframed | skipped | accept p99 (ms) | keyframe latency p95 (s) | iters / keyframe | "
             "idle iters | ROI PSNR all frames, realtime (dB) | same, offline every-frame (dB) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for a in report["agents"]:
        lines.append(f"| {a['id']} | {a['frames_received']} | {a['frames_keyframed']} | {a['frames_skipped']} | "
                     f"{fmt(a['accept_latency_ms_p99'])} | {fmt(a['keyframe_latency_s_p95'])} | "
                     f"{fmt(a.get('keyframe_iterations', 0) / max(a['frames_keyframed'], 1), 1)} | "
                     f"{a['idle_iterations']} | {fmt(a['roi_psnr_all_frames'])} | "
                     f"{fmt(a['offline_roi_psnr_all_frames'])} |")
    lines += ["", f"ROI PSNR over all {report['agents'][0]['frames_all']} frames of the sequence (skipped ones "
              "included) of each agent's final map on its own task. Offline column: "
              + (f"`{src}`." if src else "not given (pass `--offline-report DIR` of an every-frame `gausslite sim` "
                 "on the same dataset).")]
    return lines


def _timeline_lines(report: dict) -> List[str]:
    """Markdown of the fused map over time (one vote after each new subset)."""
    tl = report.get("fused_timeline") or []
    if not tl:
        return []
    tasks = [a["task"] for a in report["agents"]]
    robot = any(e.get("roi_psnr_for_robot") for e in tl)
    served = any(e.get("served") for e in tl)
    lines = ["", "## The fused map while mapping", "",
             "A vote fuse after each new subset on the server (no refinement), scored on every frame (every k-th of a "
             "sequence longer than 50 frames, about 50 of them): the team "
             "map" + (", and (→ robot) each task on the team map as its robot uses it (`Fuse(for_agent=…)`)" if robot
                      else "")
             + ("; (served) the team map the server serves then (`Fuse(team_map=true)`, refined in the background), "
                "its version and the subset versions it was made from (* = current)" if served else "") + ":", "",
             "| time (s) | subset versions | Gaussians | " + " | ".join(tasks)
             + ("".join(f" | {t} → robot" for t in tasks) if robot else "")
             + (" | served | " + " | ".join(f"{t} (served)" for t in tasks) if served else "") + " |",
             "|---|---|---|" + "---|" * (len(tasks) * (2 if robot else 1) + ((1 + len(tasks)) if served else 0))]
    for e in tl:
        vs = ", ".join(f"{a} v{v}" for a, v in sorted(e["versions"].items()))
        cells = [fmt(e["roi_psnr"].get(t)) for t in tasks]
        if robot:
            cells += [fmt((e.get("roi_psnr_for_robot") or {}).get(t)) for t in tasks]
        if served:
            s = e.get("served") or {}
            cells += [(f"v{s['version']}{'*' if s['current'] else ''} ("
                       + ", ".join(f"{a} v{v}" for a, v in sorted(s["versions"].items())) + ")") if s else "–"]
            cells += [fmt((s.get("roi_psnr") or {}).get(t)) for t in tasks]
        lines.append(f"| {e['t']:.0f} | {vs} | {e['n_gaussians']} | " + " | ".join(cells) + " |")
    if report.get("fused_timeline_plot"):
        lines += ["", f"![fused ROI PSNR over time]({report['fused_timeline_plot']})"]
    return lines


def _protocol_lines(report: dict) -> List[str]:
    """Markdown of the own and fused maps under each scoring protocol (docs/realtime.md#scoring-protocols): the
    protocols × the maps, each fused cell with its paired per-frame gain over the robot's own map, and what each
    protocol answers."""
    agents = report["agents"]
    names = sorted(dict.fromkeys(q for a in agents for q in current_protocols(a.get("protocols"))),
                   key=protocol_order)
    if not names:
        return []
    tasks = [a["task"] for a in agents]
    scoring = (report.get("settings") or {}).get("scoring") or {}
    stride, every = int(scoring.get("track_stride", 5)), int(scoring.get("novel_every", 10))
    fused = report.get("fused") or {}
    at_own = [f"{q}@own" for q in names if any(f"{q}@own" in (f.get("protocols") or {}) for f in fused.values())]
    which = {"tracked": f"{_every(stride)}", "novel": f"{_every(every)}, withheld from every robot's mapper",
             "novel-tracked": "the withheld frames"}
    lines = ["", "## The protocols × the maps", "",
             "ROI PSNR (dB) on each task's ROI; each fused cell in brackets: its gain over the robot's own map under "
             "the same protocol, the mean of the paired per-frame differences [95 % interval]. What each protocol "
             "answers (docs/realtime.md#scoring-protocols):", ""]
    lines += [f"- `{q}`" + (f" ({which[q]})" if q in which else "") + f": {PROTOCOL_QUESTIONS.get(q, q)}."
              for q in names]
    lines += ["- a fused map under `keyframes`: the keyframes the robot uploaded, at the refined poses they carry; "
              "under `novel`: at the pose and exposure the robot's own map predicts (a robot loads the team map and "
              "uses it at its own pose); under `tracked` / `novel-tracked`: tracked against the fused map itself."]
    if at_own:
        lines += ["- " + ", ".join(f"`{q}`" for q in at_own) + ": a fused map at the pose and exposure the robot "
                  "tracked those frames at on its own map, so both maps are scored at the same views: where the robot "
                  "localises, how the team map looks."]
    lines += ["", "| protocol | map | " + " | ".join(tasks) + " |", "|---|---|" + "---|" * len(tasks)]
    for q in [*names, *at_own]:
        own = {a["task"]: current_protocols(a.get("protocols")).get(q.split("@")[0]) or {} for a in agents}
        lines.append(f"| {q} | own | " + " | ".join(
            f"{fmt(own[t].get('roi_psnr'))} ({_frames(own[t].get('frames_scored', 0))})" for t in tasks) + " |")
        for key in FUSED_KEYS:
            per = current_protocols((fused.get(key) or {}).get("protocols")).get(q)
            if not per:
                continue
            cells = []
            for t in tasks:
                v = per.get(t) or {}
                g = v.get("minus_own_gain")
                cells.append(fmt(v.get("roi_psnr")) + (f" ({fmt_gain(g)}{'*' if significant(g) else ''})" if g else ""))
            lines.append(f"| {q} | {key} | " + " | ".join(cells) + " |")
    lines += ["", "\\* the interval excludes zero."]
    return lines


def _frames(n: int) -> str:
    """"1 frame", "3 frames"."""
    return f"{n} frame" + ("" if n == 1 else "s")


def _every(n: int) -> str:
    """"every frame", "every 2nd frame", …, "every 5th frame"."""
    if n <= 1:
        return "every frame"
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"every {n}{suffix} frame"


def _cover_lines(report: dict) -> List[str]:
    """Markdown of what covers each robot's ROI in the team map (:func:`gausslite.team.scoring.cover_report`)."""
    cov = (report.get("fused") or {}).get("vote", {}).get("cover") or {}
    if not cov:
        return []
    lines = ["", "## What covers each robot's ROI in the team map", "",
             "Share of the ROI pixels' blending weight in the vote map drawn by the robot's own Gaussians, by the "
             "other robots' Gaussians whose centre lies in their own task region or only in their context, and left "
             "uncovered; the other robots' Gaussians over the ROI (weighted mean extent, share of their weight in front "
             "of the ROI surface); and the robot's own rows the vote dropped, with the share of its subset's ROI "
             "weight they carried (docs/sharing.md).", "",
             "| robot | own | others, in their task region | others, context | uncovered | others' extent (m) | "
             "others in front | own rows dropped | their ROI weight |", "|---|---|---|---|---|---|---|---|---|"]
    for a, c in cov.items():
        m, f, om = c["mass"], c["foreign"], c["own_missing"]
        lines.append(f"| {a} | {m['own']:.2f} | {m['foreign_task']:.2f} | {m['foreign_context']:.2f} | "
                     f"{m['uncovered']:.2f} | {fmt(f.get('weighted_extent_m'))} | {fmt(f.get('weight_in_front'))} | "
                     f"{om['rows']} of {om['of']} | {fmt(om.get('weight_share'))} |")
    for a, c in cov.items():
        if c.get("image"):
            lines += ["", f"**{a}: the other robots' Gaussians over its ROI (red), ROI outline (green)**  ",
                      f"![cover {a}]({c['image']})"]
    return lines
