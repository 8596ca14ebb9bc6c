"""The repository's folders are the ones of the product's design (``proto/``, ``services/agent/``,
``services/fusion_server/``, ``services/parser/``, ``deploy/``, ``tests/``, ``pyproject.toml``), and the services'
folder ``services/`` installs as the package ``gausslite_services`` (``docs/architecture.md``, "Packages"):
``pyproject.toml`` maps the import name onto the folder (``package-dir``) and lists every package; the installed
``gausslite_services`` is the one of this checkout; a wheel holds ``gausslite_services/...`` and no top-level
``services``.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from importlib import metadata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: the design's top level: folders, and the one file
DESIGN_FOLDERS = ("proto", "services/agent", "services/fusion_server", "services/parser", "deploy", "tests")
DESIGN_FILES = ("pyproject.toml",)
#: the services the design names, each a package with its gRPC server
SERVICES = ("agent", "fusion_server", "parser")


def _pyproject() -> dict:
    try:
        import tomllib
    except ImportError:  # Python 3.10
        tomllib = pytest.importorskip("tomli")
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def _setuptools() -> dict:
    return _pyproject()["tool"]["setuptools"]


def packages_in_tree() -> list:
    """Import names of the packages (folders with an ``__init__.py``) under each top-level package's folder, the
    folders mapped by ``package-dir`` (a top-level package without an entry lives in the folder of its name)."""
    package_dir = _setuptools().get("package-dir", {})
    tops = sorted({p.split(".")[0] for p in _setuptools()["packages"]})
    out = []
    for top in tops:
        folder = ROOT / package_dir.get(top, top)
        for init in sorted(folder.rglob("__init__.py")):
            out.append(".".join([top, *init.parent.relative_to(folder).parts]))
    return sorted(out)


def test_the_design_folders_exist():
    missing = [f"{d}/" for d in DESIGN_FOLDERS if not (ROOT / d).is_dir()]
    missing += [f for f in DESIGN_FILES if not (ROOT / f).is_file()]
    assert not missing, "folders of the design missing at the top of the repository: " + ", ".join(missing)
    for name in SERVICES:
        assert (ROOT / "services" / name / "__init__.py").is_file(), f"services/{name}/ is not a package"
        assert (ROOT / "services" / name / "server.py").is_file(), f"services/{name}/ holds no server"
    # the services' code lives in the design's folder only
    assert not (ROOT / "gausslite_services").exists(), "a gausslite_services/ folder: the sources are in services/"


def test_pyproject_maps_the_import_name_onto_the_folder():
    st = _setuptools()
    assert st["package-dir"] == {"gausslite_services": "services"}
    packages = st["packages"]
    assert {p.split(".")[0] for p in packages} == {"gausslite", "gausslite_rpc", "gausslite_services"}
    # every package of the tree is listed (a package left out would be missing from the wheel), and only those
    assert sorted(packages) == packages_in_tree(), (
        "pyproject.toml's [tool.setuptools] packages and the folders disagree:\n  listed, no folder: "
        f"{sorted(set(packages) - set(packages_in_tree()))}\n  folder, not listed: "
        f"{sorted(set(packages_in_tree()) - set(packages))}")
    for name in SERVICES:
        assert f"gausslite_services.{name}" in packages


def test_the_installed_services_are_this_checkouts():
    """The editable install (scripts/setup.sh) resolves ``gausslite_services`` to ``services/``."""
    import gausslite_services
    import gausslite_services.agent
    import gausslite_services.fusion_server
    import gausslite_services.parser

    for mod, folder in ((gausslite_services, "services"), (gausslite_services.agent, "services/agent"),
                        (gausslite_services.fusion_server, "services/fusion_server"),
                        (gausslite_services.parser, "services/parser")):
        where = Path(mod.__file__).resolve().parent
        assert where == ROOT / folder, (f"{mod.__name__} comes from {where}, not {ROOT / folder}: re-run "
                                        "scripts/setup.sh (pip install -e) after a change of the layout")


def test_the_entry_points_name_the_installed_package():
    dist = metadata.distribution("gausslite")
    eps = {(ep.group, ep.name): ep for ep in dist.entry_points}
    assert eps[("console_scripts", "gausslite")].value == "gausslite.cli:run_as_program"
    commands = eps[("gausslite.commands", "services")]
    assert commands.value == "gausslite_services.cli"
    assert Path(commands.load().__file__).resolve().parent == ROOT / "services" / "cli"
    # no top-level package named after the folder
    tops = (dist.read_text("top_level.txt") or "").split()
    assert "services" not in tops and "gausslite_services" in tops


def _wheel_names(whl: Path) -> list:
    with zipfile.ZipFile(whl) as z:
        return z.namelist()


@pytest.mark.integration
def test_the_wheel_holds_gausslite_services(tmp_path):
    """A regular (non-editable) build: the services install as ``gausslite_services/...``, every module of
    ``services/`` with them, and nothing as a top-level ``services``."""
    src = tmp_path / "src"  # a copy: the build leaves build/ and *.egg-info beside the sources
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    for folder in ("gausslite", "gausslite_rpc", "services"):
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation",
                           "-q", "-w", str(tmp_path / "whl")], capture_output=True, text=True, timeout=600,
                          cwd=str(tmp_path))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    (whl,) = sorted((tmp_path / "whl").glob("gausslite-*.whl"))
    names = _wheel_names(whl)
    assert not [n for n in names if n.startswith("services/")], "the wheel installs a top-level services/"
    sources = sorted("gausslite_services/" + p.relative_to(ROOT / "services").as_posix()
                     for p in (ROOT / "services").rglob("*.py"))
    assert sorted(n for n in names if n.startswith("gausslite_services/")) == sources
    for name in SERVICES:
        assert f"gausslite_services/{name}/server.py" in names
    assert "gausslite/cli/__init__.py" in names and "gausslite_rpc/fusion_pb2.py" in names
    entry_points = next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
    with zipfile.ZipFile(whl) as z:
        text = z.read(entry_points).decode()
    assert "services = gausslite_services.cli" in text and "gausslite = gausslite.cli:run_as_program" in text
