"""``gausslite`` command line. Each subcommand lives in a module ``cmd_<name>.py`` that defines
``register(subparsers)``: the library's own in ``gausslite/cli/``, and those of every package named by a
``gausslite.commands`` entry point (the services' in ``services/cli/``, which run or call the gRPC
services), so the core library never imports the services or gRPC."""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
from typing import Optional, Sequence

from gausslite.core.extras import unavailable_from


def build_parser() -> argparse.ArgumentParser:
    """The top-level argument parser with every discovered subcommand registered."""
    parser = argparse.ArgumentParser(prog="gausslite", description="Task-conditioned 3DGS mapping for robot teams")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    modules = {}
    for pkg_name in [__name__, *command_packages()]:
        pkg = importlib.import_module(pkg_name)
        for mod in pkgutil.iter_modules(pkg.__path__):
            if mod.name.startswith("cmd_"):
                modules.setdefault(mod.name, f"{pkg_name}.{mod.name}")
    for name in sorted(modules):
        importlib.import_module(modules[name]).register(sub)
    return parser


def command_packages() -> list:
    """Packages of further subcommands: the values of the ``gausslite.commands`` entry points (``pyproject.toml``)."""
    # lazy: the command line starts without loading the library
    from importlib.metadata import entry_points

    return sorted({ep.value for ep in entry_points(group="gausslite.commands")})


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the ``gausslite`` console script. Returns the process exit code (2 when the command needs an
    extra of the package that is not installed: ``gausslite.core.extras``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        rc = args.func(args)
    except ImportError as e:
        # a command needing an extra this install lacks (e.g. `map` on the light fusion-server install): name the
        # extra instead of a traceback; any other failed import is a broken install and propagates
        missing = unavailable_from(e, "this command")
        if missing is None:
            raise
        print(f"gausslite {args.command}: error: {missing}", file=sys.stderr)
        return 2
    return int(rc or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
