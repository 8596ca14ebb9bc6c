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
