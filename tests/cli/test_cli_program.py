"""``gausslite.cli.run_as_program``: the console script's entry exits with the command's code and freezes the heap
out of the garbage collector's last walk first, also when the command raises."""

import subprocess
import sys

import pytest

import gausslite.cli as cli


def test_the_program_exits_with_its_code_after_freezing_the_heap(monkeypatch):
    frozen = []
    monkeypatch.setattr(cli.gc, "freeze", lambda: frozen.append(True))
    with pytest.raises(SystemExit) as e:
        cli.run_as_program(["x"], program=lambda argv: 3 if argv == ["x"] else 0)
    assert e.value.code == 3 and frozen == [True]

    def boom(argv):
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        cli.run_as_program([], program=boom)
    assert frozen == [True, True]


def test_python_m_gausslite_cli_runs_a_command_and_exits_with_its_code():
    ok = subprocess.run([sys.executable, "-m", "gausslite.cli", "config", "--help"], capture_output=True, text=True)
    assert ok.returncode == 0 and "usage: gausslite config" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "gausslite.cli", "no-such-command"], capture_output=True, text=True)
    assert bad.returncode == 2 and "invalid choice" in bad.stderr
