"""The plots of a team mission's report: each robot's bytes per push and share of its map over the mission
(:func:`plot_pushes`), and the team map's ROI PSNR per task over time (:func:`plot_fused_timeline`)."""

from __future__ import annotations

from pathlib import Path


def plot_pushes(report: dict, path: Path) -> bool:
    """Plot bytes per push and share of the map over time (frames mapped) for every agent into
    ``path`` (PNG). Returns False when no agent logged a push."""
    agents = [a for a in report["agents"] if a.get("push_log")]
    if not agents:
        return False
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    for a in agents:
        log_ = a["push_log"]
        x = [q["frames_mapped"] for q in log_]
        ax1.plot(x, [q["bytes_sent"] / 1024 for q in log_], "o-", label=a["id"])
        for q, xi in zip(log_, x):
            ax1.annotate("Δ" if q["delta"] else "full", (xi, q["bytes_sent"] / 1024), fontsize=7,
                         textcoords="offset points", xytext=(0, 4), ha="center")
        ax2.plot(x, [q["share_pct"] for q in log_], "o-", label=a["id"])
    ax1.set(xlabel="frames mapped", ylabel="KiB sent", title="bytes per push")
    ax2.set(xlabel="frames mapped", ylabel="% of the agent's map", title="shared subset")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


def plot_fused_timeline(report: dict, path: Path) -> bool:
    """PNG of the vote-fused team map's ROI PSNR per task over the simulation's time (dotted: on the team map as the
    task's robot uses it), with each agent's own final ROI PSNR as a dashed line. Returns False when there is nothing to plot."""
    tl = report.get("fused_timeline") or []
    if not tl:
        return False
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    for a in report["agents"]:
        pts = [(e["t"], e["roi_psnr"].get(a["task"])) for e in tl if e["roi_psnr"].get(a["task"]) is not None]
        if not pts:
            continue
        line, = ax.plot(*zip(*pts), "o-", ms=3, label=f"team map, {a['task']}")
        rp = [(e["t"], (e.get("roi_psnr_for_robot") or {}).get(a["task"])) for e in tl]
        rp = [q for q in rp if q[1] is not None]
        if rp:
            ax.plot(*zip(*rp), "s:", ms=3, color=line.get_color(), label=f"team map for {a['id']}")
        sp = [(e["t"], ((e.get("served") or {}).get("roi_psnr") or {}).get(a["task"])) for e in tl]
        sp = [q for q in sp if q[1] is not None]
        if sp:
            ax.plot(*zip(*sp), "^-", ms=4, lw=2, alpha=0.6, color=line.get_color(), label=f"served team map, {a['task']}")
        own = a.get("roi_psnr_all_frames") if report.get("realtime") else a.get("roi_psnr")
        if own is not None:
            ax.axhline(own, ls="--", lw=1, color=line.get_color(), label=f"{a['id']} own map (end)")
    ax.set_xlabel("simulation time (s)")
    ax.set_ylabel("ROI PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True
