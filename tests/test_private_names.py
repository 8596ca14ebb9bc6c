"""No module of the product (``gausslite/``, ``services/``) or of its benchmarks (``bench/``) imports another module's
private name (``from m import _name``): what one module offers another is its public interface, named without the
leading underscore and documented (docs/architecture.md). Relative imports count; ``__future__`` and dunder names do
not."""

from __future__ import annotations

import ast
from pathlib import Path
from typing import List, Tuple

REPO = Path(__file__).resolve().parents[1]
DIRS = ("gausslite", "services", "bench")


def private_imports(source: str) -> List[Tuple[str, str, int]]:
    """``[(module, name, line)]`` of every ``from module import _name`` in ``source`` (module "." + level for a
    relative import)."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module != "__future__":
            module = "." * node.level + (node.module or "")
            out += [(module, a.name, node.lineno) for a in node.names
                    if a.name.startswith("_") and not (a.name.startswith("__") and a.name.endswith("__"))]
    return out


def test_the_checker_finds_private_imports_and_only_them():
    src = ("from __future__ import annotations\nfrom a.b import _x, y\nfrom .c import (_Z,\n    w)\n"
           "from d import __version__\nimport _thread\n")
    assert private_imports(src) == [("a.b", "_x", 2), (".c", "_Z", 3)]


def test_no_module_imports_another_modules_private_names():
    files = [p for d in DIRS for p in sorted((REPO / d).rglob("*.py")) if "gausslite_rpc" not in p.parts]
    assert len(files) > 100, "sources not found"
    found = [f"{p.relative_to(REPO)}:{line}: from {m} import {n}"
             for p in files for m, n, line in private_imports(p.read_text(encoding="utf-8"))]
    assert not found, "private names imported across modules:\n" + "\n".join(found)
