"""``gausslite`` command line. Each subcommand lives in a module ``cmd_<name>.py`` that defines
``register(subparsers)``: the library's own in ``gausslite/cli/``, and those of every package named by a
``gausslite.commands`` entry point (the services' in ``services/cli/``, which run or call the gRPC
services), so the core library never imports the services or gRPC.

``gausslite --help`` lists the product's commands first (:data:`PRODUCT_COMMANDS`, in that order; a command of
another package that is not named there follows them) and the research and benchmark commands
(:data:`RESEARCH_COMMANDS`) in a group of their own."""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import pkgutil
import sys
from typing import Callable, List, NoReturn, Optional, Sequence

from gausslite.core.extras import unavailable_from

#: the product's commands, in the order ``gausslite --help`` lists them
PRODUCT_COMMANDS = ("sim", "map", "serve", "health", "view", "config", "certs", "tokens", "parse", "annotate", "export",
                    "make-scene")
#: commands that reproduce the paper's measurements and run benchmarks, listed apart
RESEARCH_COMMANDS = ("ablate", "attention", "bench")


def package_version() -> str:
    """The installed ``gausslite`` distribution's version (:mod:`importlib.metadata`), or ``"unknown"`` when the
    package runs from a checkout that is not installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("gausslite")
    except PackageNotFoundError:
        return "unknown"


def build_parser() -> argparse.ArgumentParser:
    """The top-level argument parser with every discovered subcommand registered."""
    parser = argparse.ArgumentParser(prog="gausslite", description="Task-conditioned 3DGS mapping for robot teams",
                                     usage="%(prog)s [-h] [--version] [-v] COMMAND ...",
                                     epilog="`gausslite COMMAND --help` describes a command.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}",
                        help="print the installed version and exit")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    # the command list is the help's own groups (list_commands); prog: the usage above names more than the program
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", help=argparse.SUPPRESS, prog="gausslite")
    sub.required = True
    modules = {}
    for pkg_name in [__name__, *command_packages()]:
        pkg = importlib.import_module(pkg_name)
        for mod in pkgutil.iter_modules(pkg.__path__):
            if mod.name.startswith("cmd_"):
                modules.setdefault(mod.name, f"{pkg_name}.{mod.name}")
    for name in sorted(modules):
        importlib.import_module(modules[name]).register(sub)
    list_commands(parser, sub)
    return parser


def list_commands(parser: argparse.ArgumentParser, sub) -> None:
    """Put the registered commands into the help of ``parser`` as two groups: the product's commands
    (:data:`PRODUCT_COMMANDS` first, in that order, then any other) and the research and benchmark commands.

    Args:
        parser (argparse.ArgumentParser): the top-level parser.
        sub: its sub-parsers action (``add_subparsers``) with every command registered; a command registered
            without ``help`` (a hidden one) is not listed.
    """
    listed = {a.dest: a for a in sub._get_subactions()}
    order = {name: i for i, name in enumerate(PRODUCT_COMMANDS)}
    product = sorted((n for n in listed if n not in RESEARCH_COMMANDS), key=lambda n: (order.get(n, len(order)), n))
    research = [n for n in RESEARCH_COMMANDS if n in listed]
    groups = (("commands", None, product),
              ("research and benchmark commands", "the paper's measurements and the benchmarks; run from a checkout",
               research))
    for i, (title, description, names) in enumerate(groups):
        group = parser.add_argument_group(title, description)
        # help-only entries: the group lists them, parsing still goes through the sub-parsers action alone
        group._group_actions.extend(listed[n] for n in names)
        parser._action_groups.insert(i, parser._action_groups.pop())  # the commands before the options


def command_packages() -> list:
    """Packages of further subcommands: the values of the ``gausslite.commands`` entry points (``pyproject.toml``)."""
    # lazy: the command line starts without loading the library
    from importlib.metadata import entry_points

    return sorted({ep.value for ep in entry_points(group="gausslite.commands")})


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of the ``gausslite`` console script. Returns the process exit code (2 when the command needs an
    extra of the package that is not installed: ``gausslite.core.extras``). A deprecated spelling of a command
    (``export-bag``, ``export-models``, ``export MAP``) runs its new form after a one-line warning on stderr
    (:func:`gausslite.cli.cmd_export.upgrade_legacy_argv`)."""
    # lazy: the command line starts without loading the library
    from gausslite.cli.cmd_export import upgrade_legacy_argv

    args_in: List[str] = list(sys.argv[1:] if argv is None else argv)
    args_in, warning = upgrade_legacy_argv(args_in)
    if warning:
        print(f"gausslite: warning: {warning}", file=sys.stderr)
    parser = build_parser()
    args = parser.parse_args(args_in)
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


def run_as_program(argv: Optional[Sequence[str]] = None,
                   program: Callable[[Optional[Sequence[str]]], int] = main) -> NoReturn:
    """``program(argv)`` (default :func:`main`) as a process's whole program (the ``gausslite`` console script,
    ``python -m gausslite.cli``, the services' ``__main__``): exits with its code. Before the exit, what the program
    left in reference cycles is collected (with its native resources: Open3D reports tensors still allocated at exit
    as leaks and exits with 1), and every object still alive is frozen out of the garbage collector (``gc.freeze``):
    the process's memory goes back with it, and the interpreter's last collection would otherwise walk every object
    torch, Warp and Open3D made at import (1.7 s at exit after the agent's imports on a 2-core machine, 0.4 s with the
    collection and the freeze), which ``gausslite sim`` pays for each of its four services and itself."""
    try:
        rc = program(argv)
    finally:
        gc.collect()  # what the program left in reference cycles goes now, with its native resources
        gc.freeze()
    sys.exit(rc)


if __name__ == "__main__":  # pragma: no cover
    run_as_program()
