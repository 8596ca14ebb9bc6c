"""``gausslite bench NAME [ARGS...]``: run a benchmark module ``bench.NAME`` (prints a table, writes
``bench/results/NAME.json``)."""

from __future__ import annotations

import argparse
import importlib

BENCHMARKS = ("rasterizer", "codec", "vote", "parser")


def _handler(args: argparse.Namespace) -> int:
    mod = importlib.import_module(f"bench.{args.name}")
    return int(mod.main(args.args) or 0)


def register(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark (rasterizer, codec, vote, parser)")
    p.add_argument("name", choices=BENCHMARKS)
    p.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the benchmark (e.g. --quick)")
    p.set_defaults(func=_handler)
