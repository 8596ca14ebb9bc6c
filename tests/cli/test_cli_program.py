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


def test_a_program_that_used_open3ds_tensors_exits_with_its_own_code(tmp_path):
    """Open3D exits with 1 when its tensors are still allocated at exit; what the program left in reference cycles
    is collected before the heap is frozen, so a program whose odometry sat in a cycle still exits 0."""
    script = tmp_path / "prog.py"
    script.write_text(
        "import numpy as np, open3d as o3d\n"
        "from gausslite.cli import run_as_program\n"
        "def prog(argv):\n"
        "    img = o3d.t.geometry.Image(o3d.core.Tensor(np.zeros((48, 64), np.float32)))\n"
        "    cycle = [img]\n"
        "    cycle.append(cycle)\n"
        "    return 0\n"
        "run_as_program([], program=prog)\n")
    p = subprocess.run([sys.executable, str(script)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr[-2000:]


def test_python_m_gausslite_cli_runs_a_command_and_exits_with_its_code():
    ok = subprocess.run([sys.executable, "-m", "gausslite.cli", "config", "--help"], capture_output=True, text=True)
    assert ok.returncode == 0 and "usage: gausslite config" in ok.stdout
    bad = subprocess.run([sys.executable, "-m", "gausslite.cli", "no-such-command"], capture_output=True, text=True)
    assert bad.returncode == 2 and "invalid choice" in bad.stderr
