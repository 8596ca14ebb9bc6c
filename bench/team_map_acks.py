"""Push acknowledgements while the fusion server refines the team map in the background.

    python -m bench.team_map_acks                    # 40 s with the team map refining, then 40 s without
    python -m bench.team_map_acks --refine-iters 300 # short refinements: vote, refine, store again and again

Starts a real fusion server process (SQLite store in ``--work``, per-robot tokens, ``fusion.team_map`` on or off).
Two robots open sessions and upload a subset (``--gaussians`` each, on a plane 1.5 m ahead) and ``--views`` ROI views
(64 × 64), so the server starts a refinement of the team map (by default a long one: ``refine_iters`` 20,000, no early
stop; ``--refine-iters``). While it runs, robot A pushes a new full subset version every ``--every`` seconds and a view
every other push, for ``--seconds``, and the benchmark times each call from the first byte sent to the
acknowledgement. The same load then runs against a server without a team map. Goal: p99 of a push acknowledgement
while the team map refines ≤ :data:`GOAL_RATIO` × its p99 without a team map.

A wall-clock benchmark: run it alone on the machine. Writes ``bench/results/team_map_acks.json`` and ``.md``
(``--out``); exit code 1 when the goal is missed or no refinement ran during the pushes (a long one: throughout; short
ones: at least two team maps made).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path
from typing import Dict, List

import numpy as np
from tqdm import tqdm

from bench._results import write_results
from bench.trust_load import RESULTS, percentiles, start_server, stop_server
from gausslite.camera import Intrinsics
from gausslite.datasets.base import Frame
from gausslite_services.common import auth
from gausslite_services.fusion_server.client import FusionClient

#: the goal: p99 of a push acknowledgement while the team map refines <= GOAL_RATIO x its p99 without a team map
GOAL_RATIO = 2.0
INTR = Intrinsics(60.0, 60.0, 31.5, 31.5, 64, 64)


def plane_subset(n: int, seed: int, x0: float):
    """``n`` random Gaussians on the plane z = 1.5 m, x in [x0, x0 + 0.8] (the views' field of view)."""
    # lazy: the wire codec loads only once the benchmark runs, not at --help
    from gausslite.wire.codec import GaussianArrays

    r = np.random.default_rng(seed)
    means = np.stack([r.uniform(x0, x0 + 0.8, n), r.uniform(-0.6, 0.6, n), np.full(n, 1.5)], 1)
    return GaussianArrays(means=means, quats=r.normal(size=(n, 4)), log_scales=r.uniform(-4.5, -3.5, (n, 3)),
                          opacity_logits=r.normal(1.0, 0.5, n), colors=r.uniform(0, 1, (n, 3)),
                          kappa=r.integers(1, 50, n), active=np.ones(n, bool))


def view(i: int, x: float):
    """A 64 × 64 ROI view (frame ``i``) looking at the plane from x = ``x`` m, with its whole-image ROI."""
    r = np.random.default_rng(i)
    c2w = np.eye(4)
    c2w[0, 3] = x
    rgb = r.integers(0, 255, (64, 64, 3), dtype=np.uint8)
    return Frame(i, i / 30.0, rgb, np.full((64, 64), 1.5, np.float32), c2w, INTR), np.ones((64, 64), bool)


def _setup(c: Dict[str, FusionClient], gaussians: int, views: int) -> None:
    for k, (a, cl) in enumerate(c.items()):
        cl.open_session(a, "find the cup", INTR)
        assert cl.upload_subset(a, 1, plane_subset(gaussians, k, -0.8 + 0.8 * k), full_map_gaussians=10 * gaussians)
        frames = [view(1000 * k + i, -0.4 + 0.8 * k + 0.02 * i) for i in range(views)]
        cl.upload_keyframes(a, [f for f, _ in frames], color_format="png", rois=[r for _, r in frames])


def run_phase(work: Path, team_map: bool, args) -> dict:
    """One phase: a server (team map on or off), the set-up, then ``args.seconds`` of pushes by robot A. Returns the
    acknowledgement times (ms) and, with the team map, whether a refinement ran throughout and how many team maps
    were stored (the first included)."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    tokens_file = work / "tokens.json"
    tokens = {a: auth.issue_token(tokens_file, a) for a in ("robot-a", "robot-b")}
    settings = {"team_map": {"enabled": team_map, "refine_iters": args.refine_iters, "settle_s": 0.2,
                             "min_interval_s": 0.0},
                "refine_validation": {"per_view_iters": 0, "patience": 1000000}}
    proc, addr = start_server(work, tokens_file, 16, None, settings)
    c = {a: FusionClient(addr, token=t, timeout_s=30) for a, t in tokens.items()}
    try:
        for cl in c.values():
            cl.wait_ready(30)
        _setup(c, args.gaussians, args.views)
        refining, made = None, None
        if team_map:  # the first refinement starts once uploads settle; it runs for minutes
            time.sleep(args.settle)
        acks, views_ms = [], []
        t_end = time.monotonic() + args.seconds
        v = 2
        with tqdm(total=int(args.seconds / args.every), desc=f"pushes, team map {'on' if team_map else 'off'}") as bar:
            while time.monotonic() < t_end:
                t0 = time.perf_counter()
                ack = c["robot-a"].upload_subset("robot-a", v, plane_subset(args.gaussians, 100 + v, -0.8),
                                                 full_map_gaussians=10 * args.gaussians)
                acks.append(1e3 * (time.perf_counter() - t0))
                if not ack.complete:
                    raise RuntimeError(f"push v{v} incomplete")
                if v % 2 == 0:
                    f, r = view(5000 + v, -0.4 + 0.01 * v)
                    t0 = time.perf_counter()
                    c["robot-a"].upload_keyframes("robot-a", [f], color_format="png", rois=[r])
                    views_ms.append(1e3 * (time.perf_counter() - t0))
                v += 1
                bar.update(1)
                time.sleep(max(0.0, args.every - acks[-1] / 1e3))
        if team_map:
            try:
                served = c["robot-b"].fuse(team_map=True)
                refining = not served.team_map_current  # never caught up: a refinement ran the whole time
                made = int(served.fused_version)  # a fresh store where only team maps are made
            except Exception:  # noqa: BLE001 - NOT_FOUND: the first refinement was still running
                refining, made = True, 0
        return {"team_map": team_map, "pushes": len(acks), "push_ack_ms": percentiles(acks),
                "view_ack_ms": percentiles(views_ms), "refining_throughout": refining, "team_maps_made": made}
    finally:
        for cl in c.values():
            cl.close()
        stop_server(proc)


def table(phases: List[dict]) -> str:
    """Markdown: push and view acknowledgement percentiles per phase."""
    f = lambda v: "–" if v is None else f"{v:.0f}"  # noqa: E731
    lines = ["| team map refining | pushes | push ack p50 / p99 / max (ms) | view ack p50 / p99 (ms) "
             "| team maps made |", "|---|---|---|---|---|"]
    for p in phases:
        a, w = p["push_ack_ms"], p["view_ack_ms"]
        made = p.get("team_maps_made")
        lines.append(f"| {'yes' if p['team_map'] else 'no (no team map)'} | {p['pushes']} | {f(a['p50'])} / "
                     f"{f(a['p99'])} / {f(a['max'])} | {f(w['p50'])} / {f(w['p99'])} | {f(made)} |")
    return "\n".join(lines)


def goal(on: dict, off: dict) -> tuple:
    """(goal met, p99 ratio or None) of the phases with (``on``) and without (``off``) a team map: met when the p99
    of a push acknowledgement with it is <= :data:`GOAL_RATIO` x without, and a refinement ran during the pushes
    (throughout, or at least two team maps were made)."""
    a, b = on["push_ack_ms"]["p99"], off["push_ack_ms"]["p99"]
    if a is None or not b:
        return False, None
    ran = bool(on["refining_throughout"]) or (on.get("team_maps_made") or 0) >= 2
    return bool(a <= GOAL_RATIO * b and ran), a / b


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.team_map_acks", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=40.0)
    ap.add_argument("--every", type=float, default=0.5, help="seconds between pushes")
    ap.add_argument("--gaussians", type=int, default=3000, help="Gaussians per subset")
    ap.add_argument("--views", type=int, default=16, help="ROI views each robot uploads at the start")
    ap.add_argument("--refine-iters", type=int, default=20000,
                    help="the team map's refine_iters (no early stop): 20,000 refines throughout the pushes, 300 (the "
                         "shipped setting) votes, refines and stores a team map every few seconds")
    ap.add_argument("--settle", type=float, default=3.0,
                    help="seconds from the uploads to the first push, for the refinement to start (the server's "
                         "settle_s is 0.2 s)")
    ap.add_argument("--work", type=Path, default=Path("runs") / "team_map_acks")
    ap.add_argument("--out", type=Path, default=RESULTS / "team_map_acks.json")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    phases = [run_phase(args.work / name, on, args) for name, on in (("on", True), ("off", False))]
    on, off = phases
    ok, ratio = goal(on, off)
    result = {"phases": phases, "goal_ratio": GOAL_RATIO, "p99_ratio": ratio, "goal_met": ok,
              "wall_s": time.perf_counter() - t0,
              "settings": vars(args) | {"work": str(args.work), "out": str(args.out)}}
    write_results(args.out, "team_map_acks", argv, f": {args.seconds:.0f} s a phase, push every {args.every} s, "
                  f"refine_iters {args.refine_iters}", table(phases), result)
    print(f"wrote {args.out}; goal (p99 while refining <= {GOAL_RATIO:g} x p99 without) {'met' if ok else 'MISSED'}"
          + ("" if ratio is None else f": {ratio:.2f} x"))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
