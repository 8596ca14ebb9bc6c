"""The real-time benchmark's tables and plots: a result's markdown tables (:func:`table`, :func:`protocol_table`, a
gain's cell :func:`gain_cell`, a failed run's mark :func:`failed_mark`) and a scene's ROI PSNR against the budget
(:func:`plot_scene`)."""

from __future__ import annotations

from pathlib import Path

from gausslite.stats import fmt, fmt_gain

from bench._missions import FAILED_MARK, failed_note
from bench.realtime.scenes import MODES


def failed_mark(v: dict, mode: str) -> str:
    """The mark of a budget block's ``mode`` in a table: ``" † 1 failed"`` when runs of it failed (the block's
    ``failed_runs``, :func:`bench.realtime.summary.summarise`), else ``""``."""
    n = len((v.get("failed_runs") or {}).get(mode, ()))
    return f" {FAILED_MARK} {n} failed" if n else ""


def _any_failed(result: dict) -> bool:
    return any(v.get("failed_runs") for blk in result["scenes"].values() for v in blk["budgets"].values())


def table(result: dict) -> str:
    """Markdown table of a result; a mode with failed runs is marked † with their count, and a footnote says what
    that means (:func:`bench._missions.failed_note`)."""
    lines = ["| scene | cap | budget (s) | mode | ROI PSNR | PSNR | SSIM | Gaussians | iters/kf | keyframes | "
             "ROI gain | final pass: ROI PSNR / PSNR |", "|" + "---|" * 12]
    for scene, blk in result["scenes"].items():
        for b, v in blk["budgets"].items():
            for mode in MODES:
                m = v.get(mode)
                mark = failed_mark(v, mode)
                if not m:
                    if mark:  # every run of the mode failed: nothing to average, the row says so
                        lines.append(f"| {scene} | {blk['cap']} | {b} | {mode}{mark} | " + "– | " * 6 + "| |")
                    continue
                g = gain_cell(v) if mode == "gausslite" and "gain" in v else ""
                fp = (f"{fmt(m.get('final_roi_psnr'), m.get('final_roi_psnr_std'))} / "
                      f"{fmt(m.get('final_psnr'), m.get('final_psnr_std'))}" if m.get("final_roi_psnr") is not None
                      else "")
                lines.append(f"| {scene} | {blk['cap']} | {b} | {mode}{mark} | "
                             f"{fmt(m['roi_psnr'], m['roi_psnr_std'])} | "
                             f"{fmt(m['psnr'], m['psnr_std'])} | {fmt(m['ssim'], m['ssim_std'], 3)} | "
                             f"{m['n_gaussians']:.0f} | {m['iters_per_keyframe']:.1f} | {m['keyframes']:.1f} | {g} | {fp} |")
    if _any_failed(result):
        lines += ["", failed_note()]
    return "\n".join(lines)


def gain_cell(v: dict) -> str:
    """A gain of :func:`_paired` for a table: ``"+1.23 [+0.80, +1.66] (σ runs 0.30)"`` (the mean of the per-run
    paired gains, its run-clustered 95 % interval, their spread), ``"+1.23 [+0.80, +1.66] (per frame, 1 run)"`` for
    a single run's per-frame interval, or ``"+1.23 ± 0.30 (runs)"`` for runs without per-frame figures; ``*``: the
    interval (without one: twice the spread) excludes zero."""
    if v.get("gain") is None:
        return unpaired_cell(v)
    star = "*" if v.get("gain_significant") else ""
    if v.get("gain_ci") and v["gain_ci"][0] is not None:
        ci = {"gain": v["gain"], "ci_low": v["gain_ci"][0], "ci_high": v["gain_ci"][1]}
        if v.get("gain_interval") == "per-frame":
            return f"{fmt_gain(ci)}{star} (per frame, 1 run)"
        return f"{fmt_gain(ci)}{star} (σ runs {fmt(v.get('gain_std'), None)})"
    return f"{fmt(v['gain'], v.get('gain_std'))} (runs){star}"


def unpaired_cell(v: dict) -> str:
    """The unpaired difference of a block whose runs did not pair (:func:`bench.realtime.summary._unpaired`):
    ``"+1.23 [−0.40, +2.86] (unpaired, 3 + 3 runs)"`` (the difference of the modes' means over runs with its Welch
    95 % interval), ``"–"`` without one."""
    if v.get("unpaired_gain") is None:
        return "–"
    ci = v.get("unpaired_gain_ci")
    cell = fmt_gain({"gain": v["unpaired_gain"], "ci_low": ci[0] if ci else None, "ci_high": ci[1] if ci else None})
    ng, nu = v.get("unpaired_gain_runs") or (None, None)
    return f"{cell} (unpaired, {ng} + {nu} runs)"


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
                mark = "".join(failed_mark(v, m) for m in MODES)
                lines.append(
                    f"| {scene} | {b} | {p} | {fmt(u.get('roi_psnr'), u.get('roi_psnr_std'))} | "
                    f"{fmt(g.get('roi_psnr'), g.get('roi_psnr_std'))} | {gain_cell(pv)} | "
                    f"{fmt(u.get('psnr'), u.get('psnr_std'))} | "
                    f"{fmt(g.get('psnr'), g.get('psnr_std'))} | "
                    f"{pv.get('runs', max(u.get('runs', 0), g.get('runs', 0)))}{mark} |")
    lines += ["", "ROI gain: GaussLite − uniform, paired frame by frame within each run: the mean of the per-run "
              "gains [95 % run-clustered interval: the t-interval over the per-run gains], σ runs: their spread; "
              "* the interval excludes zero. "
              "`novel` answers how the map serves a robot at the pose it would use on views it never trained on; "
              "`tracked` / `novel-tracked` how well a robot could localise against the map, and the map from there."]
    if _any_failed(result):
        lines += ["", failed_note()]
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


#: the protocol whose per-frame scores a trace reads: the final map at every frame of the sequence, keyframes included
TRACE_PROTOCOL = "sensor"


def _trace_rows(runs: list[dict], scene: str, budget: float) -> dict:
    """Per mode, the runs' per-keyframe traces (``run["trace"]``, :func:`bench.realtime.missions.keyframe_trace`)
    of one scene and budget, averaged over runs keyframe by keyframe (the k-th keyframe of each run; runs keep about
    the same keyframes, the live selector takes the frame that is waiting when the mapper is free), and the per-frame
    region PSNR of the final maps under :data:`TRACE_PROTOCOL`, averaged over runs: ``{mode: {"k": [...], "frame":
    [median frame id], field: [mean], "roi_psnr": {frame id: mean dB}}}``."""
    import numpy as np

    out = {}
    for mode in MODES:
        rs = [r for r in runs if r["scene"] == scene and r["mode"] == mode and abs(r["budget"] - budget) < 1e-9
              and r.get("trace") and (r.get("protocols") or {}).get(TRACE_PROTOCOL)]
        if not rs:
            continue
        n = min(len(r["trace"]["frame_id"]) for r in rs)
        m = {"k": list(range(n)), "runs": len(rs),
             "frame": [int(np.median([r["trace"]["frame_id"][k] for r in rs])) for k in range(n)]}
        for f in ("iters", "active_iters", "n_gaussians", "n_active", "active_scale_m"):
            m[f] = [float(np.mean([r["trace"][f][k] for r in rs])) for k in range(n)]
        per = {}
        for r in rs:
            for fid, v in r["protocols"][TRACE_PROTOCOL]["roi_psnr_per_frame"].items():
                per.setdefault(int(fid), []).append(float(v))
        m["roi_psnr"] = {fid: float(np.mean(v)) for fid, v in sorted(per.items()) if len(v) == len(rs)}
        out[mode] = m
    return out


def trace_table(runs: list[dict], scene: str, budget: float) -> str:
    """Markdown per-keyframe trace of one scene and budget (GaussLite's keyframes, :func:`_trace_rows`): the region
    PSNR of both modes' final maps at the keyframe's frame, GaussLite's task Gaussians, their median scale and the ROI
    phase's iterations, and both modes' iterations. Empty when the runs hold no trace."""
    t = _trace_rows(runs, scene, budget)
    g, u = t.get("gausslite"), t.get("uniform")
    if not g:
        return ""
    lines = [f"{scene}, {budget:g} s per keyframe, GaussLite's k-th keyframe (median frame over {g['runs']} runs); "
             f"region PSNR of the final maps at that frame ({TRACE_PROTOCOL} protocol, mean over runs)",
             "", "| k | frame | region PSNR GaussLite | uniform | gain | task Gaussians | median scale (mm) | "
             "ROI iterations | iterations GaussLite / uniform |", "|" + "---|" * 9]
    for k in g["k"]:
        fid = g["frame"][k]
        pg = g["roi_psnr"].get(fid)
        pu = u["roi_psnr"].get(fid) if u else None
        gain = f"{pg - pu:+.2f}" if pg is not None and pu is not None else "–"
        iu = f"{u['iters'][k]:.1f}" if u and k < len(u["iters"]) else "–"
        lines.append(f"| {k} | {fid} | {fmt(pg, None)} | {fmt(pu, None)} | {gain} | {g['n_active'][k]:.0f} | "
                     f"{1e3 * g['active_scale_m'][k]:.1f} | {g['active_iters'][k]:.1f} | {g['iters'][k]:.1f} / {iu} |")
    return "\n".join(lines)


def trace_tables(result: dict) -> str:
    """Every scene's and budget's per-keyframe trace of a ``bench.realtime`` result (:func:`trace_table`), one after
    the other; empty when its runs hold no trace (they were not scored under :data:`TRACE_PROTOCOL`)."""
    budgets = [float(b) for b in result["settings"]["budgets"]]
    return "\n\n".join(t for t in (trace_table(result["runs"], scene, b) for scene in result["scenes"]
                                     for b in budgets) if t)


def plot_trace(runs: list[dict], scene: str, budget: float, path: Path) -> bool:
    """The per-keyframe trace as a figure (:func:`_trace_rows`): both modes' region PSNR at every frame (GaussLite's
    keyframes marked), GaussLite's task Gaussians and their median scale, and the iterations per keyframe. Returns
    False (nothing written) when the runs hold no trace."""
    t = _trace_rows(runs, scene, budget)
    if "gausslite" not in t:
        return False
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(7, 7.5), sharex=True)
    g = t["gausslite"]
    for mode, colour in (("uniform", "tab:gray"), ("gausslite", "tab:red")):
        if mode in t:
            fr = sorted(t[mode]["roi_psnr"])
            axes[0].plot(fr, [t[mode]["roi_psnr"][f] for f in fr], color=colour, lw=1, label=mode)
    kf = [f for f in g["frame"] if f in g["roi_psnr"]]
    axes[0].plot(kf, [g["roi_psnr"][f] for f in kf], "o", ms=3, color="tab:red", label="GaussLite's keyframes")
    axes[0].set_ylabel("region PSNR (dB)")
    axes[0].legend(fontsize=8)
    axes[1].plot(g["frame"], g["n_active"], marker=".", color="tab:red", label="task Gaussians")
    axes[1].set_ylabel("task Gaussians")
    ax2 = axes[1].twinx()
    ax2.plot(g["frame"], [1e3 * s for s in g["active_scale_m"]], marker=".", color="tab:blue")
    ax2.set_ylabel("median scale (mm)", color="tab:blue")
    axes[2].plot(g["frame"], g["iters"], marker=".", color="tab:red", label="GaussLite")
    axes[2].plot(g["frame"], g["active_iters"], marker=".", ls="--", color="tab:red", label="GaussLite ROI phase")
    if "uniform" in t:
        axes[2].plot(t["uniform"]["frame"], t["uniform"]["iters"], marker=".", color="tab:gray", label="uniform")
    axes[2].set_ylabel("iterations")
    axes[2].set_xlabel("frame")
    axes[2].legend(fontsize=8)
    axes[0].set_title(f"{scene}: per-keyframe trace, {budget:g} s per keyframe, mean over {g['runs']} runs")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True
