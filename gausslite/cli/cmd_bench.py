"""``gausslite bench NAME [ARGS...]``: run a benchmark module ``bench.NAME`` (prints a table, writes
``bench/results/NAME.json``).

The benchmarks are repository tooling, not installed with the package (``docs/architecture.md``, "Packages"): the
command runs them from a checkout's root, as ``python -m bench.NAME`` does."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

BENCHMARKS = ("rasterizer", "codec", "vote", "parser")


def _benchmark(name: str):
    """The module ``bench.<name>``: from the import path, else from the working directory when it is a checkout's
    root (it holds ``bench/__init__.py``), as ``python -m bench.<name>`` run there finds it. None when neither has
    the ``bench`` package.

    Raises:
        ImportError: the benchmark module itself fails to import (e.g. an extra it needs is missing).
    """
    try:
        return importlib.import_module(f"bench.{name}")
    except ModuleNotFoundError as e:
        if e.name != "bench":
            raise
    root = Path.cwd()
    if not (root / "bench" / "__init__.py").is_file():
        return None
    sys.path.insert(0, str(root))
    return importlib.import_module(f"bench.{name}")


def _handler(args: argparse.Namespace) -> int:
    mod = _benchmark(args.name)
    if mod is None:
        print("gausslite bench: error: the benchmarks (bench/) are not installed with the package; run this command "
              "from the root of a GaussLite checkout", file=sys.stderr)
        return 2
    return int(mod.main(args.args) or 0)


def register(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark (rasterizer, codec, vote, parser) from a checkout's root")
    p.add_argument("name", choices=BENCHMARKS)
    p.add_argument("args", nargs=argparse.REMAINDER, help="arguments passed to the benchmark (e.g. --quick)")
    p.set_defaults(func=_handler)
