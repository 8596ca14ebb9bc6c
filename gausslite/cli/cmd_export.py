"""``gausslite export MAP --out FILE [--format splat|spz|ply]``: convert a Gaussian map to the standard
formats other splat viewers read (``.splat``: antimatter15's 32-byte records; ``.spz``: Niantic's
compressed format, via gsply). The input may be a 3DGS ``.ply`` (ours or another tool's), ``.splat`` or
``.spz``; the format defaults to the output's suffix. Both target formats are lossy and carry no κ / a.
"""

from __future__ import annotations

import argparse
import sys


def register(subparsers) -> None:
    """Add the ``export`` subcommand to ``subparsers``."""
    # lazy: the command line starts without loading the library
    from gausslite.viewer.export import FORMATS

    p = subparsers.add_parser("export", help="convert a map to .splat / .spz (standard splat viewers)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", help="input map (.ply, .splat, .spz)")
    p.add_argument("--out", required=True, help="output file")
    p.add_argument("--format", choices=FORMATS, default="", help="output format (default: from --out's suffix)")
    p.set_defaults(func=_handle)


def _handle(args: argparse.Namespace) -> int:
    # lazy: the command line starts without loading the library
    from gausslite.viewer.export import format_of, load_map, write_map

    try:
        format_of(args.out, args.format)
        g = load_map(args.map)
        n = len(g)
        size = write_map(g, args.out, args.format)
    except (FileNotFoundError, ValueError, OSError) as e:
        print(f"gausslite export: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: {n:,} Gaussians, {size:,} bytes ({size / max(n, 1):.1f} B/Gaussian)")
    return 0
