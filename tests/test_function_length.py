"""No function of the product (``gausslite/``, ``services/``) or of its benchmarks (``bench/``) is longer than
:data:`MAX_LINES` lines.

Length of a function = ``end_lineno - lineno + 1`` of its ``def`` (decorators not counted, docstring and nested
functions counted), for every ``def`` / ``async def`` at any depth, methods and nested functions included.
Generated gRPC stubs (``gausslite_rpc/``, ``*_pb2*.py``) are not product code written by hand and are skipped.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, List, Tuple

REPO = Path(__file__).resolve().parents[1]
PRODUCT_DIRS = ("gausslite", "services")  # the folders (services/ installs as gausslite_services)
BENCH_DIRS = ("bench",)  # the benchmarks' entry points are held to the product's length
MAX_LINES = 100

#: ``(path relative to the repo, function name) -> the longest length allowed``, each with the reason it cannot be
#: split. Only compute kernels belong here, and only when splitting them costs speed (docs/architecture.md,
#: "Kernel sources"). Empty: every kernel is split into ``@wp.func`` helpers at no measured cost.
ALLOWED: Dict[Tuple[str, str], int] = {}


def _generated(path: Path) -> bool:
    return "gausslite_rpc" in path.parts or path.name.endswith(("_pb2.py", "_pb2_grpc.py", "_pb2.pyi"))


def long_functions(source: str, limit: int = MAX_LINES) -> List[Tuple[str, int, int]]:
    """``[(name, first line, length)]`` of the functions in ``source`` longer than ``limit`` lines."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            n = node.end_lineno - node.lineno + 1
            if n > limit:
                out.append((node.name, node.lineno, n))
    return out


def _product_files() -> List[Path]:
    return [p for d in PRODUCT_DIRS for p in sorted((REPO / d).rglob("*.py")) if not _generated(p)]


def _bench_files() -> List[Path]:
    return [p for d in BENCH_DIRS for p in sorted((REPO / d).rglob("*.py")) if not _generated(p)]


def test_measure_flags_long_functions_at_any_depth():
    body = "\n".join(f"    x{i} = {i}" for i in range(100))
    src = (f"def ok():\n{body[: body.rfind(chr(10))]}\n\n"  # 100 lines: allowed
           f"class C:\n    async def too_long(self):\n    {body.replace(chr(10), chr(10) + '    ')}\n"
           f"        def nested_fine():\n            pass\n")
    found = long_functions(src)
    assert [(name, n) for name, _, n in found] == [("too_long", 103)]


def _over_limit(files: List[Path]) -> List[str]:
    """``path:line name: n lines`` of every function in ``files`` longer than :data:`ALLOWED` or :data:`MAX_LINES`."""
    over = []
    for path in files:
        rel = path.relative_to(REPO).as_posix()
        for name, line, n in long_functions(path.read_text(encoding="utf-8")):
            if n > ALLOWED.get((rel, name), MAX_LINES):
                over.append(f"{rel}:{line} {name}: {n} lines")
    return over


def test_product_functions_are_short():
    files = _product_files()
    assert len(files) > 50, "product sources not found"
    over = _over_limit(files)
    assert not over, f"functions over {MAX_LINES} lines (split them into named helpers):\n" + "\n".join(over)


def test_bench_functions_are_short():
    files = _bench_files()
    assert len(files) > 20, "benchmark sources not found"
    over = _over_limit(files)
    assert not over, f"functions over {MAX_LINES} lines (split them into named helpers):\n" + "\n".join(over)


def test_allow_list_holds_no_benchmark():
    assert not [rel for rel, _ in ALLOWED if rel.startswith(tuple(d + "/" for d in BENCH_DIRS))], \
        "benchmark functions are split, never allow-listed"


def test_allow_list_entries_still_exist_and_are_needed():
    for (rel, name), limit in ALLOWED.items():
        path = REPO / rel
        assert path.is_file(), f"allow-listed file {rel} is gone"
        lengths = [n for fn, _, n in long_functions(path.read_text(encoding="utf-8"), limit=0) if fn == name]
        assert lengths, f"allow-listed function {rel}:{name} is gone"
        assert max(lengths) > MAX_LINES, f"{rel}:{name} is {max(lengths)} lines now: drop it from ALLOWED"
