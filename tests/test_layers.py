"""The import graph of ``gausslite/``, ``services/`` (the package ``gausslite_services``) and ``bench/`` has no
circles and no import from a lower layer up to a higher one (the layers of ``docs/architecture.md``).

The graph is read with :mod:`ast` from the sources, so it holds every import: module-level, inside functions and
under ``if TYPE_CHECKING``. ``from package import name`` counts as an import of the submodule ``package.name``
when that submodule exists, else of ``package``. Imports of third-party packages are not part of the graph.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path
from typing import Dict, List, Set, Tuple

ROOT = Path(__file__).resolve().parents[1]
#: import name -> the folder of the repository that holds its sources (``pyproject.toml``'s ``package-dir``)
PACKAGES = {"gausslite": "gausslite", "gausslite_services": "services", "bench": "bench"}

#: lowest first; a module may import modules of its own layer and of the layers below it. A module belongs to the
#: entry with the longest matching dotted prefix; the roots "gausslite" and "gausslite_services" match only themselves.
LAYERS: List[Tuple[str, Tuple[str, ...]]] = [
    ("core", ("gausslite", "gausslite.core", "gausslite.errors", "gausslite.camera", "gausslite.stats",
              "gausslite.metrics", "gausslite.gaussians")),
    ("formats", ("gausslite.wire", "gausslite.ros")),
    ("odometry", ("gausslite.odometry",)),
    ("datasets", ("gausslite.datasets", "gausslite.synthetic")),
    ("perception", ("gausslite.parser", "gausslite.attention")),
    ("render", ("gausslite.render", "gausslite.fused_ssim")),
    ("mapping", ("gausslite.mapping", "gausslite.evaluation", "gausslite.tracked_views", "gausslite.pipeline")),
    ("sharing", ("gausslite.sharing", "gausslite.fusion")),
    ("mission", ("gausslite.mission",)),
    ("team", ("gausslite.team",)),
    ("app", ("gausslite.config", "gausslite.viewer", "gausslite.cli")),
    ("gausslite_services.common", ("gausslite_services", "gausslite_services.common")),
    ("gausslite_services.servers", ("gausslite_services.parser", "gausslite_services.fusion_server")),
    ("gausslite_services.agent", ("gausslite_services.agent",)),
    ("gausslite_services.entry", ("gausslite_services.viewer", "gausslite_services.sim", "gausslite_services.cli")),
    ("bench", ("bench",)),
]
_ROOTS = {"gausslite", "gausslite_services"}  # "bench" holds only benchmarks: one layer


def _modules() -> Dict[str, Path]:
    mods = {}
    for pkg, folder in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = [pkg, *path.relative_to(ROOT / folder).with_suffix("").parts]
            if parts[-1] == "__init__":
                parts.pop()
            mods[".".join(parts)] = path
    return mods


def _resolve(name: str, mods: Dict[str, Path]) -> str | None:
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


def import_graph() -> Tuple[Dict[str, Path], Dict[str, Dict[str, int]]]:
    """``(modules, edges)``: ``edges[a][b]`` is the first line of module ``a`` that imports module ``b``."""
    mods = _modules()
    edges: Dict[str, Dict[str, int]] = defaultdict(dict)
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[:len(base) - node.level + 1]
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                targets = [f"{src}.{a.name}" if f"{src}.{a.name}" in mods else src for a in node.names]
            else:
                continue
            for t in targets:
                r = _resolve(t, mods)
                if r is not None and r != mod:
                    edges[mod].setdefault(r, node.lineno)
    return mods, edges


def layer_of(mod: str) -> int | None:
    """Index in :data:`LAYERS` of ``mod``, or None when no entry matches."""
    best, best_len = None, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            hit = mod == p if p in _ROOTS else (mod == p or mod.startswith(p + "."))
            if hit and len(p) > best_len:
                best, best_len = i, len(p)
    return best


def _cycles(nodes, succ) -> List[List[str]]:
    """Strongly connected components with more than one node (Tarjan), each as a list of nodes."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(succ.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(nodes):
        if v not in index:
            visit(v)
    return out


def _where(mods, edges, a, b) -> str:
    return f"{mods[a].relative_to(ROOT)}:{edges[a][b]} {a} -> {b}"


def test_every_module_has_a_layer():
    mods, _ = import_graph()
    missing = sorted(m for m in mods if layer_of(m) is None)
    assert not missing, ("modules without a layer; add them to LAYERS in tests/test_layers.py and to the layer "
                         "table of docs/architecture.md:\n  " + "\n  ".join(missing))


def test_no_import_circles():
    mods, edges = import_graph()
    bad = []
    for comp in _cycles(mods, edges):
        inside = set(comp)
        bad.append("circle of " + ", ".join(comp) + ":\n    "
                   + "\n    ".join(_where(mods, edges, a, b) for a in comp for b in sorted(edges[a]) if b in inside))
    assert not bad, "import circles (module level or inside functions):\n  " + "\n  ".join(bad)


def test_no_circles_between_library_packages():
    """Two packages of the library (e.g. ``datasets`` and ``ros``) never import each other, whichever modules do."""
    mods, edges = import_graph()
    pkg = lambda m: ".".join(m.split(".")[:2])  # noqa: E731
    succ: Dict[str, Set[str]] = defaultdict(set)
    for a in mods:
        for b in edges[a]:
            if a.startswith("gausslite.") and b.startswith("gausslite.") and pkg(a) != pkg(b):
                succ[pkg(a)].add(pkg(b))
    bad = []
    for comp in _cycles({pkg(m) for m in mods if m.startswith("gausslite.")}, succ):
        inside = set(comp)
        bad.append(", ".join(comp) + ":\n    " + "\n    ".join(
            _where(mods, edges, a, b) for a in sorted(mods) for b in sorted(edges[a])
            if pkg(a) in inside and pkg(b) in inside and pkg(a) != pkg(b)))
    assert not bad, "circles between packages of gausslite:\n  " + "\n  ".join(bad)


def test_no_upward_imports():
    mods, edges = import_graph()
    bad = []
    for a in sorted(mods):
        la = layer_of(a)
        for b, line in sorted(edges[a].items()):
            lb = layer_of(b)
            if la is not None and lb is not None and lb > la:
                bad.append(f"{_where(mods, edges, a, b)}: layer {LAYERS[la][0]!r} imports the higher layer "
                           f"{LAYERS[lb][0]!r}")
    assert not bad, ("imports from a lower layer up (layers in tests/test_layers.py and docs/architecture.md):\n  "
                     + "\n  ".join(bad))


def test_the_checks_see_circles_and_upward_imports():
    """The graph reader finds function-level imports, and the checks report what they should."""
    mods, edges = import_graph()
    # an import of a sibling package's module is an edge: gausslite_services.sim.launch imports cmd_health for
    # wait_healthy
    assert "gausslite_services.cli.cmd_health" in edges["gausslite_services.sim.launch"]
    assert _cycles(["a", "b", "c"], {"a": {"b"}, "b": {"c"}, "c": {"a"}}) == [["a", "b", "c"]]
    assert _cycles(["a", "b"], {"a": {"b"}}) == []
    assert layer_of("gausslite.mission.runtime") > layer_of("gausslite.mapping.mapper")
    assert layer_of("gausslite.mapping.mapper") > layer_of("gausslite.wire.codec")
    assert layer_of("gausslite") == 0 and layer_of("gausslite.nope") is None
