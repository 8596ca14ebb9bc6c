"""Fuse flood benchmark: does a read-only team member who calls ``Fuse`` over and over grow the fusion server?

    python -m bench.fuse_flood                 # 5,000 Fuse(concat) calls; --calls, --gaussians, --every

Starts a real fusion server process (``python -m gausslite_services.fusion_server``, SQLite store in ``--work``,
per-robot tokens), has one robot upload a ``--gaussians`` (2,000) Gaussian subset, then has a second robot — a team
member that uploads nothing — call ``Fuse(concat)`` ``--calls`` (5,000) times. Every ``--every`` calls it records the
store's size on disk (the SQLite file and its WAL), the serialized size of a ``GetStats`` first page, and the server's
RSS.

The server keeps only the newest ``fusion.fused_keep_per_method`` fused maps of each method
(docs/security.md#the-fusion-server), so the store must stop growing once that many maps exist, and ``GetStats``
(paged) must stay small. Goals: the store after the last call within 10 % of its size half-way (plus 5 MB for
SQLite's write-ahead log, which grows to about 4 MB before it is checkpointed and then reused), ``GetStats`` OK and
< 1 MB.
Writes ``bench/results/fuse_flood.json`` (``--out``) and the table beside it (``.md``); exit code 1 when a goal is
missed. Counts bytes, not time: it may run beside other jobs.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path
from typing import List

import grpc
from tqdm import tqdm

from bench._results import write_results
from bench.trust_load import RESULTS, proc_status_mb, random_subset, start_server, stop_server
from gausslite.camera import Intrinsics
from gausslite_rpc import fusion_pb2, fusion_pb2_grpc
from gausslite_services.common import auth
from gausslite_services.fusion_server.client import FusionClient

REPO = Path(__file__).resolve().parents[1]
STATS_GOAL_BYTES = 1 << 20
#: SQLite's write-ahead log grows to about 4 MB before its automatic checkpoint, then is reused
STORE_SLACK_BYTES = 5 << 20


def parse_args(argv=None) -> argparse.Namespace:
    """Command-line options (``--help``)."""
    p = argparse.ArgumentParser(prog="python -m bench.fuse_flood", description=__doc__.split("\n\n")[0])
    p.add_argument("--calls", type=int, default=5000, help="Fuse(concat) calls (default 5,000)")
    p.add_argument("--gaussians", type=int, default=2000, help="Gaussians in the uploaded subset (default 2,000)")
    p.add_argument("--every", type=int, default=250, help="record sizes every this many calls")
    p.add_argument("--keep", type=int, default=None,
                   help="the server's fusion.fused_keep_per_method (default: its own, 32)")
    p.add_argument("--work", default=str(REPO / "runs" / "fuse_flood"), help="scratch folder (store, tokens, log)")
    p.add_argument("--out", default=str(RESULTS / "fuse_flood.json"))
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p.parse_args(argv)


def store_bytes(data_dir: Path) -> int:
    """Bytes on disk of the server's store under ``data_dir`` (every file: database, WAL, shared memory)."""
    return sum(f.stat().st_size for f in data_dir.rglob("*") if f.is_file())


def run(args: argparse.Namespace) -> dict:
    """Run the benchmark (module docstring) and return its results (sizes in bytes, RSS in MB)."""
    if args.calls < 1 or args.every < 1 or args.gaussians < 1:
        raise ValueError("--calls, --every and --gaussians must be >= 1")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(work / "data", ignore_errors=True)
    tokens_file = work / "fusion_tokens.json"
    tokens_file.unlink(missing_ok=True)
    tok = {a: auth.issue_token(tokens_file, a, scheme="sha256") for a in ("mapper", "reader")}
    proc, address = start_server(work, tokens_file, 16, None,
                                 {} if args.keep is None else {"fused_keep_per_method": args.keep})
    samples: List[dict] = []
    try:
        with FusionClient(address, token=tok["mapper"], timeout_s=60) as up:
            up.wait_ready(60)
            up.open_session("mapper", "find the chair", Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240))
            ack = up.upload_subset("mapper", 1, random_subset(args.gaussians, 1), full_map_gaussians=20 * args.gaussians)
            if not ack.complete:
                raise RuntimeError("the subset upload did not complete")
        md = (("authorization", f"Bearer {tok['reader']}"),)
        with FusionClient(address, token=tok["reader"], timeout_s=60) as reader, \
                grpc.insecure_channel(address) as channel:
            stub = fusion_pb2_grpc.FusionStub(channel)  # raw GetStats: the first page's size on the wire
            for i in tqdm(range(1, args.calls + 1), desc="Fuse(concat)", unit="call", disable=args.no_progress):
                reader.fuse("concat")
                if i % args.every == 0 or i == args.calls or i == 1:
                    raw = stub.GetStats(fusion_pb2.StatsRequest(), timeout=60, metadata=md)
                    samples.append({"calls": i, "store_bytes": store_bytes(work / "data"),
                                    "stats_bytes": raw.ByteSize(), "fused_held": len(raw.fused),
                                    "rss_mb": proc_status_mb(proc.pid, "VmRSS")})
    finally:
        stop_server(proc)
    mid = min(samples, key=lambda q: abs(q["calls"] - args.calls / 2))
    last = samples[-1]
    goals = {"store_bounded": last["store_bytes"] <= 1.1 * mid["store_bytes"] + STORE_SLACK_BYTES,
             "get_stats_under_1_MB": max(s["stats_bytes"] for s in samples) < STATS_GOAL_BYTES}
    return {"calls": args.calls, "gaussians": args.gaussians,
            "fused_held_max": max(q["fused_held"] for q in samples), "samples": samples,
            "store_bytes_half_way": mid["store_bytes"], "half_way_calls": mid["calls"],
            "store_bytes_last": last["store_bytes"], "stats_bytes_max": max(s["stats_bytes"] for s in samples),
            "rss_mb_max": max((s["rss_mb"] or 0.0) for s in samples), "goals": goals}


def table(res: dict) -> str:
    """The results as a Markdown table."""
    rows = [(f"after {s['calls']} calls", f"{s['store_bytes'] / 1e6:.2f} MB", f"{s['stats_bytes']:,} B",
             str(s["fused_held"]), "n/a" if s["rss_mb"] is None else f"{s['rss_mb']:.0f} MB")
            for s in res["samples"]]
    out = ["| Fuse(concat) calls | store on disk | GetStats first page | fused maps held | server RSS |",
           "|---|---|---|---|---|"] + [f"| {' | '.join(r)} |" for r in rows]
    out += ["", "| goal | result |", "|---|---|"] + [f"| {k} | {'met' if v else 'MISSED'} |"
                                                     for k, v in res["goals"].items()]
    return "\n".join(out)


def main(argv=None) -> int:
    """``python -m bench.fuse_flood``: run, print the table, write the JSON and Markdown. Returns 1 when a goal is
    missed."""
    args = parse_args(argv)
    res = run(args)
    details = f": {res['calls']} Fuse(concat) calls from a read-only team member on a {res['gaussians']}-Gaussian subset"
    write_results(Path(args.out), "fuse_flood", argv, details, table(res), res)
    return 0 if all(res["goals"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
