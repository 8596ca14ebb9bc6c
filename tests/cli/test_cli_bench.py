"""``gausslite bench``: the benchmarks are not installed with the package, so the command finds ``bench/`` in the
working directory (a checkout's root) and says so where there is none (``docs/architecture.md``, "Packages").

Each case runs in a child process whose import system sees ``bench`` only in the working directory's path entries,
as on an install without the benchmarks; a stand-in ``bench/codec.py`` replaces the real benchmark."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

_CHILD = textwrap.dedent('''
    import argparse, os, sys
    from importlib.machinery import PathFinder

    sys.path[:] = [p for p in sys.path if p and os.path.abspath(p) != os.getcwd()]  # no implicit working directory

    class NotInstalled:
        """Finds the top-level ``bench`` only in path entries that are the working directory."""

        def find_spec(self, name, path=None, target=None):
            if name != "bench":
                return None
            here = [p for p in sys.path if os.path.abspath(p) == os.getcwd()]
            spec = PathFinder.find_spec(name, here) if here else None
            if spec is None:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return spec

    sys.meta_path.insert(0, NotInstalled())
    from gausslite.cli.cmd_bench import _handler
    sys.exit(_handler(argparse.Namespace(name="codec", args=["--quick"])))
''')


def _run(cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", _CHILD], cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


def test_bench_runs_the_checkouts_benchmark_from_its_root(tmp_path):
    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "__init__.py").write_text("")
    (tmp_path / "bench" / "codec.py").write_text("def main(argv):\n    print('ran', argv)\n    return 3\n")
    r = _run(tmp_path)
    assert r.returncode == 3, r.stderr
    assert r.stdout.strip() == "ran ['--quick']"


def test_bench_outside_a_checkout_says_where_to_run_it(tmp_path):
    r = _run(tmp_path)
    assert r.returncode == 2, r.stderr
    assert "not installed with the package" in r.stderr and "root of a GaussLite checkout" in r.stderr
