"""No source file of the product (``gausslite/``, ``services/``) is longer than :data:`MAX_FILE_LINES` lines, and the
mission's coordinator, :class:`gausslite.mission.runtime.AgentRuntime`, is at most :data:`MAX_RUNTIME_LINES` lines
(docs/architecture.md, "Module size"): a module longer than that holds more than one job and is split along its
seams into modules of their own (the original re-exports what it offered), and the runtime's logic lives in its parts.

Length of a file = its number of lines; of a class = ``end_lineno - lineno + 1`` of its ``class`` statement
(decorators not counted). Generated gRPC stubs (``gausslite_rpc/``, ``*_pb2*.py``) are not product code written by hand
and are skipped.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import List, Optional, Tuple

REPO = Path(__file__).resolve().parents[1]
PRODUCT_DIRS = ("gausslite", "services")
MAX_FILE_LINES = 600
MAX_RUNTIME_LINES = 250
#: the coordinator held to :data:`MAX_RUNTIME_LINES`: (path relative to the repository, class name)
RUNTIME = ("gausslite/mission/runtime.py", "AgentRuntime")


def _generated(path: Path) -> bool:
    return "gausslite_rpc" in path.parts or path.name.endswith(("_pb2.py", "_pb2_grpc.py", "_pb2.pyi"))


def _product_files() -> List[Path]:
    return [p for d in PRODUCT_DIRS for p in sorted((REPO / d).rglob("*.py")) if not _generated(p)]


def long_files(files: List[Path], limit: int = MAX_FILE_LINES) -> List[Tuple[Path, int]]:
    """``[(path, lines)]`` of the files in ``files`` longer than ``limit`` lines."""
    out = []
    for path in files:
        n = len(path.read_text(encoding="utf-8").splitlines())
        if n > limit:
            out.append((path, n))
    return out


def class_length(source: str, name: str) -> Optional[int]:
    """Lines of the top-level class ``name`` in ``source`` (``end_lineno - lineno + 1``), or None when it has none."""
    for node in ast.parse(source).body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            return node.end_lineno - node.lineno + 1
    return None


def test_the_measures_count_lines_of_files_and_classes(tmp_path):
    short, long = tmp_path / "short.py", tmp_path / "long.py"
    short.write_text("x = 1\n" * 4)
    long.write_text("x = 1\n" * 5)
    assert long_files([short, long], limit=4) == [(long, 5)]
    src = "import os\n\n\nclass A:\n    x = 1\n\n    def f(self):\n        return 2\n\n\nclass B:\n    pass\n"
    assert class_length(src, "A") == 5 and class_length(src, "B") == 2 and class_length(src, "C") is None


def test_product_files_are_at_most_600_lines():
    files = _product_files()
    assert len(files) > 50, "product sources not found"
    over = long_files(files)
    assert not over, (f"product files over {MAX_FILE_LINES} lines (split each along its seams into modules of their "
                      "own, the original re-exporting what it offered):\n"
                      + "\n".join(f"  {p.relative_to(REPO).as_posix()}: {n} lines" for p, n in over))


def test_the_agent_runtime_is_a_thin_coordinator():
    rel, name = RUNTIME
    n = class_length((REPO / rel).read_text(encoding="utf-8"), name)
    assert n is not None, f"{rel} holds no class {name}"
    assert n <= MAX_RUNTIME_LINES, (f"{name} is {n} lines (at most {MAX_RUNTIME_LINES}): move its logic into its parts "
                                    "(gausslite/mission/*.py), keeping its public methods and their docstrings")
