"""Which optional parts of GaussLite are installed: the package's extras (``pyproject.toml``) and the features that
need them.

The light install (``pip install gausslite``, or ``gausslite[fusion]`` for the fusion server with its PostgreSQL
store) runs the fusion server's vote and concat, the command line and the clients; mapping, the agent, perception,
the viewer and the fusion server's refinement need the ``mapper`` extra (torch, Warp, ...).
``docs/fusion-and-deploy.md`` ("A light fusion-server install") lists what each install holds.

A feature is available when every module it imports is found (:func:`importlib.util.find_spec`, which loads none
of them): asking costs no torch import.
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

from gausslite.errors import ExtraUnavailable

__all__ = ["EXTRA_MODULES", "FEATURES", "Feature", "missing_modules", "unavailable", "require", "extra_of",
           "unavailable_from", "install_hint"]

#: extra name → {top-level module: the distribution (as ``pyproject.toml`` lists it) that brings it}; only the
#: modules that extra alone brings
EXTRA_MODULES: Dict[str, Dict[str, str]] = {
    "fusion": {"psycopg": "psycopg[binary]", "psycopg_pool": "psycopg-pool"},
    "mapper": {"torch": "torch", "warp": "warp-lang", "scipy": "scipy", "onnxruntime": "onnxruntime",
               "plyfile": "plyfile", "matplotlib": "matplotlib", "viser": "viser",
               "rosbags": "rosbags", "open3d": "open3d-cpu"},
}


@dataclass(frozen=True)
class Feature:
    """An optional capability: what it is (for messages), the extra that brings it and the modules it imports."""

    what: str
    extra: str
    modules: Tuple[str, ...]


#: feature name → :class:`Feature`. The module lists are what importing the feature's code loads (measured by
#: ``tests/services/test_fusion_light_install.py``).
FEATURES: Dict[str, Feature] = {
    # gausslite.fusion.refine: the mapper (torch, the Warp rasterizer, SciPy seeding, plyfile maps)
    "refine": Feature("the joint refinement of a fused map (Fuse refine=true)", "mapper",
                      ("torch", "warp", "scipy", "plyfile")),
    # gausslite.sharing.roi_contribution: renders the ROI views
    "roi_guard": Feature("the ROI guard of a robot's team map (Fuse for_agent) over its ROI keyframes", "mapper",
                         ("torch", "warp", "plyfile")),
}


def _found(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # a finder that refuses the name, or a broken half-imported module
        return False


def missing_modules(modules) -> List[str]:
    """The top-level module names among ``modules`` that cannot be imported here (none is imported)."""
    return [m for m in modules if not _found(m)]


def install_hint(extra: str) -> str:
    """``pip install 'gausslite[EXTRA]'``."""
    return f"pip install 'gausslite[{extra}]'"


def _distributions(extra: str, modules) -> str:
    dists = EXTRA_MODULES.get(extra, {})
    return ", ".join(dists.get(m, m) for m in modules)


def unavailable(feature: str) -> Optional[str]:
    """None when ``feature`` (a key of :data:`FEATURES`) can run here, else why not: the extra it needs, the
    distributions missing and how to install them.

    Raises:
        KeyError: unknown feature.
    """
    f = FEATURES[feature]
    missing = missing_modules(f.modules)
    if not missing:
        return None
    return (f"{f.what} needs the '{f.extra}' extra ({install_hint(f.extra)}); not installed here: "
            f"{_distributions(f.extra, missing)}")


def require(feature: str) -> None:
    """Raise :class:`~gausslite.errors.ExtraUnavailable` when ``feature`` cannot run here (:func:`unavailable`)."""
    why = unavailable(feature)
    if why is not None:
        f = FEATURES[feature]
        raise ExtraUnavailable(why, extra=f.extra, missing=tuple(missing_modules(f.modules)))


def extra_of(module: str) -> Optional[str]:
    """The extra that brings the top-level module of the dotted name ``module``, or None (core or unknown)."""
    top = module.split(".")[0]
    for extra, mods in EXTRA_MODULES.items():
        if top in mods:
            return extra
    return None


def unavailable_from(err: ImportError, what: str) -> Optional[ExtraUnavailable]:
    """An :class:`~gausslite.errors.ExtraUnavailable` for ``err`` when it is a module of an extra that is missing
    (``err.name``), else None (a core module's import failed: a broken install, not a missing extra).

    Args:
        err: the ImportError (``ModuleNotFoundError``, or one raised by an import hook) of the failed import.
        what: what could not run, for the message (e.g. "Fuse for_agent").
    """
    name = getattr(err, "name", None) or ""
    extra = extra_of(name) if name else None
    if extra is None:
        return None
    top = name.split(".")[0]
    return ExtraUnavailable(f"{what} needs the '{extra}' extra ({install_hint(extra)}); not installed here: "
                            f"{_distributions(extra, [top])}", extra=extra, missing=(top,))
