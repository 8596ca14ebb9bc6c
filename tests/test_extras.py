"""The package's extras: ``pyproject.toml``'s split into a light core and the ``fusion`` / ``mapper`` / ``all`` extras,
what :mod:`gausslite.core.extras` knows of them, and the installs that must take the full set (``scripts/setup.sh``,
``deploy/Dockerfile``)."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import grpc
import pytest

from gausslite.cli import main
from gausslite.core import extras
from gausslite.errors import ExtraUnavailable
from gausslite_services.common.errors import status_for

ROOT = Path(__file__).resolve().parents[1]


def _project() -> dict:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        tomllib = pytest.importorskip("tomli")
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def _name(requirement: str) -> str:
    """``psycopg[binary]>=3.2`` → ``psycopg[binary]``; ``torch==2.13.0`` → ``torch``."""
    return re.match(r"[A-Za-z0-9_.\-]+(\[[^\]]*\])?", requirement).group(0)


def test_the_extras_tables_are_the_pyproject_extras():
    project = _project()
    opt = project["optional-dependencies"]
    for extra, modules in extras.EXTRA_MODULES.items():
        assert sorted(modules.values()) == sorted(_name(r) for r in opt[extra]), extra
    assert opt["all"] == ["gausslite[fusion,mapper]"]
    assert set(opt) == {"fusion", "mapper", "all", "dev"}
    core = {_name(r) for r in project["dependencies"]}
    for heavy in ("torch", "warp-lang", "onnxruntime", "scipy", "viser", "matplotlib", "rosbags", "plyfile"):
        assert heavy not in core and heavy in extras.EXTRA_MODULES["mapper"].values(), heavy
    for feature in extras.FEATURES.values():
        assert set(feature.modules) <= set(extras.EXTRA_MODULES[feature.extra]), feature


def test_the_full_installs_take_every_extra():
    setup = (ROOT / "scripts" / "setup.sh").read_text(encoding="utf-8")
    assert re.search(r'pip install [^\n]*-e "\.\[all,dev\]"', setup)
    dockerfile = (ROOT / "deploy" / "Dockerfile").read_text(encoding="utf-8")
    assert 'RUN pip install ".[all]"' in dockerfile and "RUN pip install . " not in dockerfile


def test_a_feature_is_unavailable_when_a_module_of_its_extra_is_missing(monkeypatch):
    assert extras.unavailable("refine") is None  # the full install (scripts/setup.sh)
    extras.require("refine")
    real = importlib.util.find_spec

    def find_spec(name, *a, **k):
        if name == "warp":
            return None
        if name == "scipy":
            raise ImportError("refused by a finder")
        return real(name, *a, **k)

    monkeypatch.setattr(importlib.util, "find_spec", find_spec)
    assert extras.missing_modules(["torch", "warp", "scipy"]) == ["warp", "scipy"]
    why = extras.unavailable("refine")
    assert why.startswith("the joint refinement of a fused map (Fuse refine=true) needs the 'mapper' extra")
    assert "pip install 'gausslite[mapper]'" in why and why.endswith("not installed here: warp-lang, scipy")
    with pytest.raises(ExtraUnavailable) as ei:
        extras.require("refine")
    assert ei.value.extra == "mapper" and ei.value.missing == ("warp", "scipy") and str(ei.value) == why
    with pytest.raises(KeyError):
        extras.unavailable("no such feature")


def test_an_import_error_names_its_extra_only_for_a_module_of_an_extra():
    err = extras.unavailable_from(ModuleNotFoundError("No module named 'torch'", name="torch.nn"), "this command")
    assert isinstance(err, ExtraUnavailable) and err.extra == "mapper" and err.missing == ("torch",)
    assert str(err) == "this command needs the 'mapper' extra (pip install 'gausslite[mapper]'); not installed here: torch"
    pg = extras.unavailable_from(ModuleNotFoundError("x", name="psycopg_pool"), "the store")
    assert pg.extra == "fusion" and "psycopg-pool" in str(pg)
    assert extras.unavailable_from(ModuleNotFoundError("x", name="numpy"), "x") is None  # core: a broken install
    assert extras.unavailable_from(ImportError("no name"), "x") is None
    assert extras.extra_of("warp.context") == "mapper" and extras.extra_of("gausslite.sharing") is None
    # the services answer FAILED_PRECONDITION: a matter of the installation, not of the request
    assert status_for(err) == grpc.StatusCode.FAILED_PRECONDITION


def test_the_command_line_names_the_missing_extra(monkeypatch, capsys):
    import gausslite.cli.cmd_config as cmd_config

    def needs_torch(args):
        raise ModuleNotFoundError("No module named 'torch'", name="torch")

    real_register = cmd_config.register

    def register(sub):
        real_register(sub)
        sub.choices["config"].set_defaults(func=needs_torch)

    monkeypatch.setattr(cmd_config, "register", register)
    assert main(["config", "--show"]) == 2
    err = capsys.readouterr().err
    assert "gausslite config: error: this command needs the 'mapper' extra (pip install 'gausslite[mapper]')" in err

    def broken(args):
        raise ModuleNotFoundError("No module named 'numpy'", name="numpy")

    register_broken = lambda sub: (real_register(sub), sub.choices["config"].set_defaults(func=broken))  # noqa: E731
    monkeypatch.setattr(cmd_config, "register", register_broken)
    with pytest.raises(ModuleNotFoundError):  # a core module: a broken install, not a missing extra
        main(["config", "--show"])
