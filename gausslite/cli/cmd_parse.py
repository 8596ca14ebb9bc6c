"""``gausslite parse "task text"``: print the task graph as JSON (local library, no server; paper Sec. III-B)."""

from __future__ import annotations

import argparse
import json
import sys


def register(subparsers) -> None:
    """Add the ``parse`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("parse", help="parse a task text into an object-relation graph (JSON)",
                              description="Parse a task text into {targets, anchors, relations} (paper Sec. III-B).")
    p.add_argument("text", help="task text, e.g. \"Pick up the cup on the desk\"")
    p.add_argument("--backend", choices=["rules", "openai", "onnx"], default=None,
                   help="parser backend (default: from --config, else rules)")
    p.add_argument("--config", default=None, help="parser config file (YAML or JSON)")
    p.add_argument("--compact", action="store_true", help="one-line JSON")
    p.set_defaults(func=_handle)


def _handle(args: argparse.Namespace) -> int:
    # lazy: the command line starts without loading the library
    from gausslite.parser import BackendUnavailableError, InvalidTaskTextError, ParserConfig, TaskParser

    try:
        cfg = ParserConfig.from_file(args.config) if args.config else ParserConfig()
        if args.backend:
            cfg.backend = args.backend
        graph = TaskParser(cfg).parse(args.text)
    except (BackendUnavailableError, InvalidTaskTextError, ValueError, OSError) as e:
        print(f"gausslite parse: error: {e}", file=sys.stderr)
        return 2
    print(json.dumps(graph.to_dict(), indent=None if args.compact else 2))
    return 0
