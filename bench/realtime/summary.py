"""The real-time benchmark's summary of its runs: per scene, budget and mode the means over runs and the paired gain of
GaussLite over uniform under each scoring protocol (:func:`summarise`), over the runs whose maps were scored at the
same size (:func:`pairable_runs`)."""

from __future__ import annotations

import logging
import math
from typing import Optional

from gausslite.evaluation import PROTOCOLS, current_protocols
from gausslite.stats import aggregate, gain, paired_gain, significant, unpaired_gain

from bench._missions import failure_rows, succeeded
from bench.realtime.scenes import MODES

log = logging.getLogger("bench.realtime")  # one logger for the whole benchmark


def summarise(runs: list[dict], scene: str, budgets: list[float], cap: int) -> dict:
    """The JSON block of one scene: per budget and mode the means and stds over runs, and the paired gain. Runs of
    failed missions (:func:`bench._missions.failed`) are left out of every figure; a budget with any lists them
    under ``"failed_runs"`` (``{mode: [{"run", "end_state", "error", "frames_failed", "corrections_rejected"}]}``)."""
    keys = ["roi_psnr", "psnr", "ssim", "n_gaussians", "iters_per_keyframe", "keyframes", "idle_iters",
            "roi_iters", "final_roi_psnr", "final_psnr", "final_ssim"]
    out = {"cap": cap, "budgets": {}}
    for b in budgets:
        blk: dict = {}
        by_mode = {}
        for mode in MODES:
            every = sorted([r for r in runs if r["scene"] == scene and r["mode"] == mode and r["budget"] == b],
                           key=lambda r: r["run"])
            bad = failure_rows(every, ("run",))
            if bad:
                blk.setdefault("failed_runs", {})[mode] = bad
            rs = succeeded(every)
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
            blk.update(_unpaired(g, u, "roi_psnr", "sensor"))
            blk.update(_paired(g, u, common, "roi_psnr", "sensor"))
            pg = _paired(g, u, common, "psnr", "sensor")
            blk["psnr_gain"], blk["psnr_gain_std"] = pg["gain"], pg["gain_std"]
        protos = _summarise_protocols(by_mode)
        if protos:
            blk["protocols"] = protos
        if blk:
            out["budgets"][budget_key(b)] = blk
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


def _unpaired(g: dict, u: dict, field: str, protocol: str) -> dict:
    """GaussLite − uniform of ``field`` under ``protocol`` over every run of each mode (run → result), unpaired: the
    difference of the two modes' means over runs with its Welch interval (:func:`gausslite.stats.unpaired_gain`):
    ``{"unpaired_gain", "unpaired_gain_ci", "unpaired_gain_runs": [GaussLite runs, uniform runs]}``. It gives every
    cell a figure when runs cannot pair (:func:`pairable_runs`: mapped at different resolutions, as a resolution
    governor under load does), at the price of the run-to-run spread the pairing removes."""
    def top(r):
        return r.get(field) if protocol == "sensor" else (current_protocols(r.get("protocols")).get(protocol)
                                                          or {}).get(field)

    ug = unpaired_gain([top(r) for r in g.values()], [top(r) for r in u.values()])
    return {"unpaired_gain": ug["gain"],
            "unpaired_gain_ci": None if ug["ci_low"] is None else [ug["ci_low"], ug["ci_high"]],
            "unpaired_gain_runs": [ug["n_treated"], ug["n_baseline"]]}


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
            blk.update(_unpaired(g, u, "roi_psnr", p))
            if common:
                blk.update(_paired(g, u, common, "roi_psnr", p))
                pg = _paired(g, u, common, "psnr", p)
                blk.update(psnr_gain=pg["gain"], psnr_gain_std=pg["gain_std"], runs=len(common))
        out[p] = blk
    return out


def budget_key(b: float) -> str:
    """A budget (seconds per keyframe) as the result's key of its block: ``0.5`` -> ``"0.5"``, ``2.0`` -> ``"2"``."""
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
