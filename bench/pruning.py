"""The pruning curve: how much of the map does ``mapper.budget.prune_contribution`` prune, and what becomes of the task
region? Read from the live ``bench.realtime`` results of each setting (off, 1, 5, 20 pixels), TUM's two tasks and the
rendered walk with TUM's sensor (docs/realtime.md#pruning).

    python -m bench.pruning [--results bench/results] [--out bench/results/realtime_prune_curve.json]

Per scene, mode and setting: the pruned share of the map, pruned ÷ (pruned + final Gaussians) with both means over the
runs (0 with pruning off, which prunes nothing), against the region's PSNR under ``novel`` (mean ± std over runs) and
the gain with its run-clustered 95 % interval. Prints the table and writes the JSON, a Markdown table and a PNG (one
panel per scene: region PSNR against pruned share, both modes, the runs' spread as error bars).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Optional

from bench._results import write_results
from bench.report import HEADLINE_PRIMARY, gain_text, pm, protocol, pruning_scenes, run_mean

RESULTS = Path(__file__).resolve().parent / "results"
#: the settings of ``mapper.budget.prune_contribution`` (pixels) and the result files' suffix of each
SETTINGS = (("off", 0.0), ("1", 1.0), ("5", 5.0), ("20", 20.0))
#: the result files: ``realtime_prune_<setting>.json`` (TUM's tasks) and ``realtime_prune_walk_<setting>.json``
FAMILIES = ("realtime_prune_{}.json", "realtime_prune_walk_{}.json")
MODES = ("gausslite", "uniform")


def curve_points(results: Path) -> list[dict]:
    """One point per scene of :data:`~bench.report.PRUNING_SCENES` (:func:`~bench.report.pruning_scenes`), mode and setting found under ``results``: the
    setting (pixels), the pruned share (0 … 1), the final Gaussians, the region's PSNR under ``novel`` (dB, mean and
    std over runs), the gain (GaussLite − uniform, dB) with its interval and the runs.

    Raises:
        FileNotFoundError: no result of any setting under ``results``.
    """
    points = []
    for family in FAMILIES:
        for name, pixels in SETTINGS:
            path = Path(results) / family.format(name)
            if not path.is_file():
                continue
            res = json.loads(path.read_text())
            for scene, label in pruning_scenes(res):
                p = protocol(res, scene, HEADLINE_PRIMARY)
                for mode in MODES:
                    final = run_mean(res, scene, mode, "n_gaussians")
                    pruned = (run_mean(res, scene, mode, "pruned") or 0.0) if pixels else 0.0
                    points.append({"scene": scene, "label": label, "mode": mode, "setting": name, "pixels": pixels,
                                   "pruned": pruned, "final_gaussians": final,
                                   "pruned_share": pruned / (pruned + final) if final else None,
                                   "roi_psnr": p[mode]["roi_psnr"], "roi_psnr_std": p[mode]["roi_psnr_std"],
                                   "gain": p.get("gain"), "gain_ci": p.get("gain_ci"), "gain_text": gain_text(p),
                                   "runs": p[mode].get("runs"), "source": path.name})
    if not points:
        raise FileNotFoundError(f"no realtime_prune*.json under {results}")
    return points


def curve_table(points: list[dict]) -> str:
    """The points as a Markdown table, one row per scene and setting (both modes side by side)."""
    head = ["scene, task", "prune_contribution", "pruned share, GaussLite / uniform",
            f"ROI PSNR `{HEADLINE_PRIMARY}`, GaussLite", "uniform", "gain [95 %, run-clustered]"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rows = {}
    for q in points:
        rows.setdefault((q["label"], q["setting"]), {})[q["mode"]] = q
    for (label, setting), by in rows.items():
        g, u = by["gausslite"], by["uniform"]
        lines.append("| " + " | ".join([
            label, "off" if setting == "off" else f"{setting} px",
            f"{100 * g['pruned_share']:.1f} / {100 * u['pruned_share']:.1f} %",
            pm(g["roi_psnr"], g["roi_psnr_std"]), pm(u["roi_psnr"], u["roi_psnr_std"]), g["gain_text"]]) + " |")
    return "\n".join(lines)


def plot_curve(points: list[dict], path: Path) -> Path:
    """The PNG: a panel per scene, region PSNR (dB) against pruned share (%), a line per mode through the settings
    (each labelled with its threshold), error bars of the runs' std."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(q["scene"] for q in points))
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.6 * len(scenes), 3.8), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for mode, colour in (("gausslite", "tab:red"), ("uniform", "tab:blue")):
            pts = sorted((q for q in points if q["scene"] == scene and q["mode"] == mode), key=lambda q: q["pixels"])
            xs = [100 * q["pruned_share"] for q in pts]
            ax.errorbar(xs, [q["roi_psnr"] for q in pts], yerr=[q["roi_psnr_std"] or 0.0 for q in pts], marker="o",
                        capsize=3, color=colour, label="GaussLite" if mode == "gausslite" else "uniform")
            for x, q in zip(xs, pts):
                ax.annotate(q["setting"] if q["setting"] == "off" else f"{q['setting']} px", (x, q["roi_psnr"]),
                            textcoords="offset points", xytext=(4, 4), fontsize=7, color=colour)
        ax.set_title(next(q["label"] for q in points if q["scene"] == scene), fontsize=9)
        ax.set_xlabel("pruned share of the map (%)")
        ax.set_ylabel(f"ROI PSNR, {HEADLINE_PRIMARY} (dB)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv: Optional[list[str]] = None) -> dict:
    ap = argparse.ArgumentParser(prog="python -m bench.pruning", description=__doc__.split("\n")[0])
    ap.add_argument("--results", type=Path, default=RESULTS, help="folder of the realtime_prune*.json results")
    ap.add_argument("--out", type=Path, default=RESULTS / "realtime_prune_curve.json")
    args = ap.parse_args(argv)
    points = curve_points(args.results)
    png = plot_curve(points, args.out.with_suffix(".png"))
    result = {"points": points, "png": png.name}
    write_results(args.out, "pruning", argv, f": {len(points)} points; ![curve]({png.name})", curve_table(points),
                  result)
    print(f"wrote {args.out}, {args.out.with_suffix('.md')} and {png}")
    return result


if __name__ == "__main__":
    main()
