"""Reading the repository's source without importing it: the names a function calls (:func:`calls_in`), for the tests
that check which code path a caller takes."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def calls_in(path: str, function: str) -> set:
    """Names called inside ``function`` (a function or method) of the file at ``path`` (relative to the repository):
    a called name, or a called attribute's name.

    Raises:
        AssertionError: the file has no such function.
    """
    tree = ast.parse((ROOT / path).read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name == function:
            return {c.func.id if isinstance(c.func, ast.Name) else c.func.attr
                    for c in ast.walk(node) if isinstance(c, ast.Call) and isinstance(c.func, (ast.Name, ast.Attribute))}
    raise AssertionError(f"{path} has no function {function}")
