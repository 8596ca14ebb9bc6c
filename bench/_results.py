"""Writing a benchmark's results: the JSON, and a Markdown table headed by the command that made it."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Optional, Sequence


def write_results(out: Path, module: str, argv: Optional[Sequence[str]], details: str, md: str,
                  result: Optional[dict] = None) -> Path:
    """Write ``result`` as JSON to ``out`` (when given) and ``md`` to ``out`` with suffix ``.md``, under
    ``# bench.<module>`` and the command line ``python -m bench.<module> ARGS`` followed by ``details``
    (e.g. ``": 3 seeds, 5.4 min"``); print the table.

    Args:
        out: the JSON path (its folder is created).
        module: the bench module's name (``sim_seeds``).
        argv: the arguments the bench ran with (None: ``sys.argv[1:]``).
        details: text right after the command's closing backtick.
        md: the Markdown table.
        result: the JSON-ready results; None when the bench wrote its JSON itself.
    Returns:
        the Markdown file's path.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if result is not None:
        out.write_text(json.dumps(result, indent=2))
    args = " ".join(argv if argv is not None else sys.argv[1:])
    md_path = out.with_suffix(".md")
    md_path.write_text(f"# bench.{module}\n\n`python -m bench.{module} {args}`{details}\n\n{md}\n")
    print(md)
    return md_path
