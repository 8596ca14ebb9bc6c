"""Writing a benchmark's results: the JSON with its provenance, and a Markdown table headed by the command that made
it. Every path written is made portable first: relative to the repository, a dataset as ``DATA/<name>``, the home
folder as ``~`` (:func:`portable_path`), so that no result file names a folder of the machine that measured it."""

from __future__ import annotations

import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Optional, Sequence

REPO = Path(__file__).resolve().parents[1]
#: where the benchmarks read the real sequences (``$GAUSSLITE_SHARED/datasets``, docs/results.md "Datasets")
DATASETS = Path(os.environ.get("GAUSSLITE_SHARED", REPO.parent / "shared")) / "datasets"
#: an absolute POSIX path inside a longer string: a ``/`` that does not follow a word, a dot, ``~``, ``:`` or ``/``
#: (so ``http://host/x``, ``a/b`` and ``~/x`` are left alone), then at least two components
_ABS = re.compile(r"(?<![\w.~:/\-])/(?:[\w.@+\-]+/)+[\w.@+\-]*")
#: the top-level folders under which a string is taken for a path of the machine (not a ROS topic such as /tf)
_MACHINE_ROOTS = ("home", "root", "tmp", "var", "mnt", "media", "opt", "srv", "data", "scratch", "work", "private",
                  "Users", "nfs", "usr", "etc")
UNKNOWN = "unknown"


def _is_under(path: Path, root: Path) -> bool:
    try:
        path.relative_to(root)
        return True
    except ValueError:
        return False


def portable_path(path: Any) -> str:
    """``path`` as a result file stores it: relative to the repository when inside it; ``DATA/<rest>`` when under the
    datasets folder (or any folder named ``datasets``); ``~/<rest>`` under the home folder; ``TMP/<rest>`` under the
    system's temporary folder; else ``…/<last two components>``. A relative path is returned unchanged."""
    p = Path(str(path))
    if not p.is_absolute():
        return str(path)
    p = Path(os.path.normpath(p))
    for root, prefix in ((REPO, ""), (DATASETS, "DATA/")):
        if _is_under(p, root):
            return prefix + (p.relative_to(root).as_posix() or ".")
    if "datasets" in p.parts:
        i = len(p.parts) - 1 - p.parts[::-1].index("datasets")
        return "DATA/" + "/".join(p.parts[i + 1:])
    for root, prefix in ((Path.home(), "~/"), (Path(tempfile.gettempdir()), "TMP/")):
        if root != Path("/") and _is_under(p, root):
            return prefix + p.relative_to(root).as_posix()
    return "…/" + "/".join(p.parts[-2:])


def portable_text(text: str) -> str:
    """``text`` with every absolute path of the machine in it (``/home/...``, ``/tmp/...``, a checkout's folder)
    replaced by :func:`portable_path`; other slashes (``/tf``, URLs, ``a/b``) are left alone."""
    roots = set(_MACHINE_ROOTS) | {REPO.parts[1] if len(REPO.parts) > 1 else ""}

    def sub(m: re.Match) -> str:
        s = m.group(0)
        first = s.split("/")[1]
        return portable_path(s) if first in roots else s

    return _ABS.sub(sub, text)


def portable(obj: Any) -> Any:
    """A copy of the JSON-ready ``obj`` with :func:`portable_text` applied to every string (keys included)."""
    if isinstance(obj, str):
        return portable_text(obj)
    if isinstance(obj, dict):
        return {portable(k) if isinstance(k, str) else k: portable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [portable(v) for v in obj]
    return obj


def _git(*args: str) -> Optional[str]:
    try:
        out = subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or UNKNOWN


def _ram_gb() -> Any:
    try:
        return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (AttributeError, ValueError, OSError):
        return UNKNOWN


def machine() -> dict:
    """The machine a benchmark runs on: ``cores`` (logical CPUs), ``cpu`` (model), ``ram_gb``, ``os``."""
    return {"cores": os.cpu_count() or UNKNOWN, "cpu": _cpu_model(), "ram_gb": _ram_gb(),
            "os": platform.platform()}


def command_line(module: str, argv: Optional[Sequence[str]]) -> str:
    """``python -m bench.<module> ARGS`` (``argv`` None: ``sys.argv[1:]``), its paths made portable."""
    args = list(argv if argv is not None else sys.argv[1:])
    return portable_text(" ".join([f"python -m bench.{module}", *args]))


def provenance(module: str, argv: Optional[Sequence[str]]) -> dict:
    """What a result file records about its run: ``command`` (:func:`command_line`), ``date`` (UTC, ISO 8601),
    ``commit`` (``git rev-parse HEAD``) and ``dirty`` (tracked files differ from it), ``machine`` (:func:`machine`).
    A field that cannot be established (no git, say) is ``"unknown"``."""
    commit = _git("rev-parse", "HEAD")
    status = _git("status", "--porcelain", "--untracked-files=no")
    return {"command": command_line(module, argv),
            "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "commit": commit or UNKNOWN, "dirty": UNKNOWN if status is None else bool(status),
            "machine": machine()}


def write_json(out: Path, result: Any, module: str, argv: Optional[Sequence[str]], indent: int = 2) -> Path:
    """Write the JSON-ready ``result`` to ``out`` (its folder is created) with its paths made portable and, when it is
    a dict, a ``provenance`` object first (:func:`provenance`; one already there is kept). Returns ``out``."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = portable(result)
    if isinstance(doc, dict):
        doc = {"provenance": doc.get("provenance") or provenance(module, argv),
               **{k: v for k, v in doc.items() if k != "provenance"}}
    out.write_text(json.dumps(doc, indent=indent) + "\n")
    return out


def write_results(out: Path, module: str, argv: Optional[Sequence[str]], details: str, md: str,
                  result: Optional[dict] = None) -> Path:
    """Write ``result`` as JSON to ``out`` (:func:`write_json`: portable paths and the run's provenance) and ``md`` to
    ``out`` with suffix ``.md``, under ``# bench.<module>`` and the command line ``python -m bench.<module> ARGS``
    followed by ``details`` (e.g. ``": 3 seeds, 5.4 min"``); print the table.

    Args:
        out: the JSON path (its folder is created).
        module: the bench module's name (``team_map``).
        argv: the arguments the bench ran with (None: ``sys.argv[1:]``).
        details: text right after the command's closing backtick.
        md: the Markdown table.
        result: the JSON-ready results; None when the bench wrote its JSON itself (it is then read back and
            rewritten with its provenance and portable paths).
    Returns:
        the Markdown file's path.
    """
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if result is None and out.is_file():
        result = json.loads(out.read_text())
    if result is not None:
        write_json(out, result, module, argv)
    md_path = out.with_suffix(".md")
    md_path.write_text(portable_text(f"# bench.{module}\n\n`{command_line(module, argv)}`{details}\n\n{md}\n"))
    print(md)
    return md_path


def publish(dest: Optional[Path], module: str, argv: Optional[Sequence[str]], md: str, result: dict) -> None:
    """A bench's output: print ``md`` when ``dest`` is None (a quick run), else :func:`write_results` to ``dest``
    with the run's minutes (``result["wall_s"]``) after the command line, and say what was written."""
    if dest is None:
        print(md)
        return
    write_results(dest, module, argv, f" ({result['wall_s'] / 60:.1f} min)", md, result)
    print(f"wrote {dest} and {Path(dest).with_suffix('.md')}")
