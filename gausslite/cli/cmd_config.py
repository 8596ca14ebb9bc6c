"""``gausslite config --show | --schema``: the effective configuration tree, or its JSON schema
(:mod:`gausslite.config`)."""

from __future__ import annotations

import argparse
import json
import sys


def register(subparsers) -> None:
    """Add the ``config`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("config", help="print the effective configuration (YAML) or its JSON schema",
                              description="Print the effective GaussLite configuration {agent, mapper, sim, fusion} "
                                          "after the file and the overrides, or the JSON schema of the file.")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--show", action="store_true", help="the effective configuration as YAML")
    what.add_argument("--schema", action="store_true", help="the JSON schema of a configuration file")
    p.add_argument("--config", default=None, help="GaussLite YAML of site settings (default: none, the measured defaults)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="dotted override, e.g. --set mapper.iters_per_frame=10 (repeatable)")
    p.add_argument("--role", choices=["all", "agent", "fusion", "sim"], default="all",
                   help="only the sections this process runs with: what `gausslite serve ROLE` given the same "
                        "--config and --set runs (and logs at start-up as 'effective configuration')")
    p.set_defaults(func=_handle)


def _handle(args: argparse.Namespace) -> int:
    # lazy: the command line starts without loading the library
    import yaml
    from pydantic import ValidationError

    from gausslite.config import GaussLiteConfig, load_config

    if args.schema:
        print(json.dumps(GaussLiteConfig.json_schema(), indent=2))
        return 0
    try:
        cfg = load_config(args.config, args.overrides)
    except (ValidationError, ValueError, OSError) as e:
        print(f"gausslite config: error: {e}", file=sys.stderr)
        return 2
    print(yaml.safe_dump(cfg.sections(args.role), sort_keys=False), end="")
    return 0
