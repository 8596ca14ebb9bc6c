"""``gausslite ablate``: the paper's Table 3 at matched budget (SB, MVO, ROI, SIS, GFD cumulatively).

Writes ``DIR/ablation.json`` (a list of rows: the five switches, ``roi_psnr``, ``psnr``,
``seconds_per_frame``, ``n_gaussians``, per task and averaged), ``DIR/ablation.md`` and
``DIR/ablation.png`` (ROI PSNR and full-image PSNR per row, the paper's Fig. 5 trade-off).

``--rows`` runs a subset of the rows; ``--merge PREV/ablation.json`` fills the rows not run from an
earlier report (each such row keeps ``"source": PREV`` so the table says where it came from), e.g. to
re-run only the rows a mapper change can affect.
"""

from __future__ import annotations

import argparse
import json
import logging
import textwrap
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from gausslite.cli.cmd_map import add_mapping_args, config_from_args, resolve_dataset

if TYPE_CHECKING:  # the command line starts without loading the library
    from gausslite.mapping.config import MapperConfig

log = logging.getLogger("gausslite.ablate")

SWITCHES = ("sb", "mvo", "roi", "sis", "gfd")


def select_rows(names: str | None) -> list[tuple[str, object]]:
    """The ablation rows named in a comma list (``none,+SB,...``; None = all), in table order.

    Raises:
        ValueError: an unknown row name.
    """
    # lazy: the command line starts without loading the library
    from gausslite.mapping.config import ablation_rows

    rows = ablation_rows()
    if not names:
        return rows
    want = [n.strip() for n in names.split(",") if n.strip()]
    known = [n for n, _ in rows]
    bad = [n for n in want if n not in known]
    if bad:
        raise ValueError(f"unknown ablation rows {bad}; rows are {known}")
    return [(n, sw) for n, sw in rows if n in want]


def rows_from_previous(previous: Path, run: list[str], task_ids: list[str]) -> dict[str, dict]:
    """The rows of an earlier ablation.json (``previous``) that fill the table rows not in ``run``,
    each marked with ``source``.

    Raises:
        OSError: ``previous`` cannot be read.
        ValueError: it is not a list of rows, lacks a row that is not run, or covers other tasks.
    """
    # lazy: the command line starts without loading the library
    from gausslite.mapping.config import ablation_rows

    try:
        old = {r["row"]: r for r in json.loads(Path(previous).read_text())}
    except (TypeError, KeyError, json.JSONDecodeError) as e:
        raise ValueError(f"{previous} is not an ablation.json: {e}") from e
    filled = {}
    for name, _ in ablation_rows():
        if name in run:
            continue
        if name not in old:
            raise ValueError(f"{previous} has no row {name!r} to merge")
        if sorted(old[name].get("per_task", {})) != sorted(task_ids):
            raise ValueError(f"{previous} row {name!r} covers tasks {sorted(old[name].get('per_task', {}))}, "
                             f"not {sorted(task_ids)}")
        filled[name] = {**old[name], "source": str(previous)}
    return filled


def merge_rows(rows: list[dict], filled: dict[str, dict]) -> list[dict]:
    """All table rows in order: ``rows`` (just run) and ``filled`` (from :func:`rows_from_previous`)."""
    # lazy: the command line starts without loading the library
    from gausslite.mapping.config import ablation_rows

    done = {r["row"]: r for r in rows}
    return [done[name] if name in done else filled[name] for name, _ in ablation_rows()]


ROW_KEYS = ("roi_psnr", "psnr", "seconds_per_frame", "n_gaussians")
TASK_KEYS = ("roi_psnr", "psnr", "ssim", "roi_ssim", "seconds_per_frame", "n_gaussians", "n_active")


def run_ablation(dataset, base_cfg: MapperConfig, task_ids: list[str], out: Path, stride: int = 1, progress: bool = True,
                 rows_to_run: list[tuple[str, object]] | None = None, seeds: list[int] | None = None) -> list[dict]:
    """Run ablation rows (default: all) for every task and seed at the same budget; return the rows.

    Each row holds, for ``roi_psnr``/``psnr``/``seconds_per_frame``/``n_gaussians``, the mean over
    seeds of the per-seed mean over tasks, with ``<key>_std`` (standard deviation over seeds) beside
    it; ``by_seed`` (seed → task-mean figures), ``per_task`` (task → mean and std over seeds) and
    ``seeds``. Seeds change seeding and view sampling (``MapperConfig.seed``).
    """
    # lazy: the command line starts without loading the library
    from tqdm import tqdm

    from gausslite.pipeline import run_mapping
    from gausslite.stats import aggregate

    seeds = list(seeds) if seeds else [base_cfg.seed]
    selected = rows_to_run if rows_to_run is not None else select_rows(None)
    rows = []
    # the "none" row is the uniform baseline: its map does not depend on the task, so it is mapped once
    # per seed (uniform mode, no relevance) and scored on every task's ROI
    jobs = [(name, sw, (None if name == "none" else t), sd) for name, sw in selected for sd in seeds
            for t in (task_ids[:1] if name == "none" else task_ids)]
    bar = tqdm(total=len(jobs), desc="ablation", disable=not progress, unit="run")
    results: dict[str, dict[int, dict[str, dict]]] = {}
    for name, sw, task, sd in jobs:
        bar.set_postfix(row=name, task=task or "all", seed=sd)
        if task is None:
            cfg = base_cfg.model_copy(update={"mode": "uniform", "components": sw, "seed": sd})
            _, m = run_mapping(dataset, cfg, task_id=None, stride=stride, out_dir=None, progress=False,
                               eval_task_ids=task_ids)
            scored = {t: {**{k: m.get(k) for k in TASK_KEYS}, **{k: m["per_task"][t][k] for k in ("roi_psnr", "roi_ssim")},
                          "n_active": 0} for t in task_ids}
        else:
            cfg = base_cfg.model_copy(update={"mode": "gausslite", "components": sw, "seed": sd})
            _, m = run_mapping(dataset, cfg, task_id=task, stride=stride, out_dir=None, progress=False)
            scored = {task: {k: m[k] for k in TASK_KEYS}}
        for t, v in scored.items():
            results.setdefault(name, {}).setdefault(sd, {})[t] = v
            log.info("row %s, task %s, seed %d: ROI PSNR %.2f dB, PSNR %.2f dB, %.2f s/frame, %d Gaussians",
                     name, t, sd, v["roi_psnr"] if v["roi_psnr"] is not None else float("nan"), v["psnr"],
                     v["seconds_per_frame"], v["n_gaussians"])
        bar.update(1)
    bar.close()
    for name, sw in selected:
        res = results[name]
        row = {s: bool(getattr(sw, s)) for s in SWITCHES}
        row["row"] = name
        by_seed = {}
        for sd in seeds:
            per = res[sd]
            by_seed[sd] = {}
            for k in ROW_KEYS:
                vals = [v[k] for v in per.values() if v[k] is not None]
                by_seed[sd][k] = float(np.mean(vals)) if vals else None
        row.update(aggregate(list(by_seed.values()), ROW_KEYS))
        row["per_task"] = {t: aggregate([res[sd][t] for sd in seeds], TASK_KEYS) for t in task_ids}
        row["by_seed"] = {str(sd): v for sd, v in by_seed.items()}
        row["seeds"] = seeds
        rows.append(row)
    return rows


def gains_vs_baseline(rows: list[dict]) -> dict[str, dict]:
    """Paired ROI PSNR gain of every row over the ``none`` row, per seed (mean, std, significant =
    mean > 2 std); empty when there is no ``none`` row or the rows' seeds differ."""
    # lazy: the command line starts without loading the library
    from gausslite.stats import gain

    base = next((r for r in rows if r["row"] == "none"), None)
    if base is None or "by_seed" not in base:
        return {}
    out = {}
    for r in rows:
        if r["row"] == "none" or r.get("by_seed", {}).keys() != base["by_seed"].keys():
            continue
        ks = sorted(base["by_seed"])
        out[r["row"]] = gain([r["by_seed"][k]["roi_psnr"] for k in ks], [base["by_seed"][k]["roi_psnr"] for k in ks])
    return out


def write_report(rows: list[dict], out: Path, title: str) -> None:
    """Write ablation.json, ablation.md and ablation.png."""
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib

    matplotlib.use("Agg")
    # lazy: heavy optional dependency, loaded only on this path
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    (out / "ablation.json").write_text(json.dumps(rows, indent=2))
    mark = lambda b: "✓" if b else "✗"  # noqa: E731
    # lazy: the command line starts without loading the library
    from gausslite.stats import fmt

    gains = gains_vs_baseline(rows)
    n_seeds = len(rows[0].get("seeds", [0]))
    lines = [f"# Ablation: {title}", "",
             f"Mean ± standard deviation over {n_seeds} seed(s); the gain over the `none` row is paired per "
             "seed and counts (✓) only when it exceeds twice its standard deviation.", "",
             "| SB | MVO | ROI | SIS | GFD | ROI PSNR [dB] | gain [dB] | PSNR [dB] | s/frame | Gaussians |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        g = gains.get(r["row"])
        gtxt = "–" if g is None or g["gain"] is None else f"{fmt(g['gain'], g['gain_std'])} {mark(g['significant'])}"
        lines.append("| " + " | ".join(mark(r[s]) for s in SWITCHES)
                     + f" | {fmt(r['roi_psnr'], r.get('roi_psnr_std'))} | {gtxt} | {fmt(r['psnr'], r.get('psnr_std'))}"
                     f" | {r['seconds_per_frame']:.2f} | {r['n_gaussians']:.0f} |")
    merged = [r for r in rows if r.get("source")]
    if merged:
        lines += ["", "Rows taken from earlier runs: "
                  + "; ".join(f"{r['row']} from {r['source']}" for r in merged) + "."]
    tasks = sorted(rows[0]["per_task"])
    if len(tasks) > 1:
        lines += ["", "ROI PSNR per task [dB]:", "", "| row | " + " | ".join(tasks) + " |",
                  "|---|" + "---|" * len(tasks)]
        for r in rows:
            lines.append(f"| {r['row']} | " + " | ".join(
                fmt(r['per_task'][t]['roi_psnr'], r['per_task'][t].get('roi_psnr_std')) for t in tasks) + " |")
    (out / "ablation.md").write_text("\n".join(lines) + "\n")

    fig, ax1 = plt.subplots(figsize=(7, 4))
    x = np.arange(len(rows))
    ax1.errorbar(x, [r["roi_psnr"] for r in rows], yerr=[r.get("roi_psnr_std") or 0 for r in rows], fmt="o-",
                 color="tab:red", capsize=3, label="ROI PSNR")
    ax1.set_ylabel("ROI PSNR [dB]", color="tab:red")
    ax2 = ax1.twinx()
    ax2.plot(x, [r["psnr"] for r in rows], "s--", color="tab:blue", label="full-image PSNR")
    ax2.set_ylabel("full-image PSNR [dB]", color="tab:blue")
    ax1.set_xticks(x, [r["row"] for r in rows])
    ax1.set_title("Ablation trade-off: " + textwrap.fill(title, 60), fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "ablation.png", dpi=120)
    plt.close(fig)


def _handler(args: argparse.Namespace) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    args.mode = "gausslite"
    try:
        ds = resolve_dataset(args, out)
    except (ValueError, FileNotFoundError) as e:  # bad dataset / bag: one clear error, no traceback
        log.error("cannot load the dataset: %s", e)
        return 2
    if ds.annotations is None:
        log.error("%s has no tasks.json: ablation needs ground-truth ROI", ds.path)
        return 2
    task_ids = [t.id for t in ds.annotations.tasks] if args.task_id in (None, "all") else [args.task_id]
    try:
        base = config_from_args(args, mode="gausslite")
        selected = select_rows(args.rows)
    except (ValueError, FileNotFoundError) as e:  # pydantic's ValidationError is a ValueError
        log.error("%s", e)
        return 2
    filled: dict[str, dict] = {}
    if args.merge is not None:
        try:  # read and check the earlier report before hours of mapping, not after
            filled = rows_from_previous(args.merge, [n for n, _ in selected], task_ids)
        except (OSError, ValueError) as e:
            log.error("--merge %s: %s", args.merge, e)
            return 2
    elif len(selected) < len(select_rows(None)):
        log.info("running rows %s only (no --merge): the table holds just these", [n for n, _ in selected])
    seeds = [base.seed + i for i in range(args.seeds)]
    rows = run_ablation(ds, base, task_ids, out, stride=args.stride, progress=not args.no_progress,
                        rows_to_run=selected, seeds=seeds)
    if args.merge is not None:
        rows = merge_rows(rows, filled)
    write_report(rows, out, f"{ds.path.name} ({', '.join(task_ids)})")
    print((out / "ablation.md").read_text())
    return 0


def register(sub) -> None:
    p = sub.add_parser("ablate", help="component ablation at matched budget (paper Table 3)")
    add_mapping_args(p)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--rows", default=None,
                   help="comma list of rows to run (none,+SB,+MVO,+ROI,+SIS,+GFD; default all)")
    p.add_argument("--merge", type=Path, default=None,
                   help="earlier ablation.json whose rows fill the ones not run (marked in the table)")
    p.add_argument("--seeds", type=int, default=3,
                   help="random seeds per row and task (default 3; seeds --seed, --seed+1, ...): every figure is "
                        "the mean ± std over seeds")
    p.set_defaults(func=_handler)
