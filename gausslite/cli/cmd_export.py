"""``gausslite export WHAT``: write GaussLite data in the formats other tools read, one verb per kind of data.

    gausslite export map MAP.ply --out MAP.splat [--format splat|spz|ply]   # a map for standard splat viewers
    gausslite export bag --dataset PATH --out BAG [--storage mcap|sqlite3|ros1]   # a dataset as a ROS bag
    gausslite export models --detector DIR --segmenter FILE.pt --out DIR   # the agent's ONNX detector/segmenter

``export map`` converts a Gaussian map to the standard formats other splat viewers read (``.splat``:
antimatter15's 32-byte records; ``.spz``: Niantic's compressed format). The input may be a 3DGS
``.ply`` (ours or another tool's), ``.splat`` or ``.spz``; the format defaults to the output's suffix. Both
target formats are lossy and carry no κ / a.

The earlier spellings ``gausslite export MAP --out FILE``, ``gausslite export-bag`` and ``gausslite export-models``
still run, after a one-line deprecation warning on stderr (:func:`upgrade_legacy_argv`).
"""

from __future__ import annotations

import argparse
import sys
from typing import List, Optional, Tuple

#: the kinds of data ``gausslite export`` writes
EXPORT_VERBS = ("map", "bag", "models")
#: deprecated command → its new spelling
LEGACY_COMMANDS = {"export-bag": ("export", "bag"), "export-models": ("export", "models")}
#: options the top-level parser takes before the command (``gausslite -v export ...``)
GLOBAL_FLAGS = ("-v", "--verbose")


def register(subparsers) -> None:
    """Add the ``export`` subcommand with its verbs ``map``, ``bag`` and ``models`` to ``subparsers``."""
    # lazy: the command line starts without loading the library
    from gausslite.cli import export_bag, export_models

    p = subparsers.add_parser("export", help="write a map (.splat/.spz), a dataset (ROS bag) or the agent's "
                              "ONNX models", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="export_what", metavar="WHAT", title="what to export")
    sub.required = True
    add_map_arguments(sub.add_parser("map", help="a map as .splat / .spz / .ply (standard splat viewers)"))
    export_bag.add_arguments(sub.add_parser("bag", help=export_bag.HELP))
    export_models.add_arguments(sub.add_parser("models", help=export_models.HELP,
                                               formatter_class=argparse.RawDescriptionHelpFormatter))


def add_map_arguments(p: argparse.ArgumentParser) -> None:
    """Add the options of ``gausslite export map`` to ``p`` and make :func:`handle_map` its handler."""
    # lazy: the command line starts without loading the library
    from gausslite.viewer.export import FORMATS

    p.description = ("Convert a Gaussian map (.ply, .splat, .spz) to .splat / .spz (lossy, no κ / a) or .ply; the "
                     "format defaults to the suffix of --out.")
    p.add_argument("map", help="input map (.ply, .splat, .spz)")
    p.add_argument("--out", required=True, help="output file")
    p.add_argument("--format", choices=FORMATS, default="", help="output format (default: from --out's suffix)")
    p.set_defaults(func=handle_map)


def handle_map(args: argparse.Namespace) -> int:
    """Run ``gausslite export map``. Returns the exit code: 0, or 2 when the input is missing or unreadable, the
    format unknown or the output cannot be written."""
    # lazy: the command line starts without loading the library
    from gausslite.viewer.export import format_of, load_map, write_map

    try:
        format_of(args.out, args.format)
        g = load_map(args.map)
        n = len(g)
        size = write_map(g, args.out, args.format)
    except (FileNotFoundError, ValueError, OSError) as e:
        print(f"gausslite export map: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: {n:,} Gaussians, {size:,} bytes ({size / max(n, 1):.1f} B/Gaussian)")
    return 0


def upgrade_legacy_argv(argv: List[str]) -> Tuple[List[str], Optional[str]]:
    """Rewrite a deprecated spelling of an export command into its new form.

    ``export-bag ...`` → ``export bag ...``, ``export-models ...`` → ``export models ...``, and ``export MAP ...``
    (a map file, or an option, where the verb belongs) → ``export map MAP ...``. Options given before the command
    (``-v``) stay in front.

    Args:
        argv (list[str]): the command line without the program name.
    Returns:
        (argv, warning): the arguments to parse, and the one-line deprecation warning to print (None when
        ``argv`` uses no deprecated spelling; ``argv`` is then returned unchanged).
    """
    i = 0
    while i < len(argv) and argv[i] in GLOBAL_FLAGS:
        i += 1
    if i >= len(argv):
        return argv, None
    head, cmd, rest = argv[:i], argv[i], argv[i + 1:]
    if cmd in LEGACY_COMMANDS:
        new = LEGACY_COMMANDS[cmd]
        return [*head, *new, *rest], (f"'gausslite {cmd}' is deprecated; use 'gausslite {' '.join(new)}'")
    if cmd == "export" and rest and rest[0] not in (*EXPORT_VERBS, "-h", "--help"):
        return [*head, "export", "map", *rest], ("'gausslite export MAP' is deprecated; use 'gausslite export map "
                                                 "MAP'")
    return argv, None
