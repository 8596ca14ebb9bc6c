"""The SIMD kernels built for AVX2 (x86-64-v3: 16-lane vectors as two 8-lane halves) and for AVX-512 (x86-64-v4),
each in a process of its own whose Warp modules are compiled with that target (``bench.throughput.ISA_FLAGS``, the
flags ``python -m bench.throughput --isa`` measures): the parity tests of tests/render/test_render_simd.py (against
the Warp tile kernels and the float64 reference) and the tight tile lists' (tests/render/test_render_binning.py) pass
in each build. A build the host CPU cannot run is skipped with the missing features named."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bench.throughput import ISA_FLAGS

REPO = Path(__file__).resolve().parents[2]
#: the CPU features (``/proc/cpuinfo`` flags) each build's code needs
NEEDS = {"avx2": {"avx2", "fma", "bmi2"}, "avx512": {"avx512f", "avx512bw", "avx512cd", "avx512dq", "avx512vl"}}

_RUN = """
import sys
import warp as wp
wp.config.cpu_compiler_flags = sys.argv[1]
wp.config.quiet = True
import torch
from tests.render import test_render_binning as b, test_render_simd as s
s.test_simd_matches_tile_kernels(16, (83, 61))
s.test_simd_matches_tile_kernels(8, (64, 48))
s.test_simd_dense_opaque_scene_terminates_like_tile_kernels()
s.test_simd_parity_with_reference()
b.test_tight_lists_render_the_squares_images_and_gradients_bit_for_bit()
from warp._src import context
import gausslite.render.simd_kernels as sk
ex = next(iter(context.get_module(sk.__name__).execs.values()))
print("BUILT", ex.binary_path, wp.config.cpu_compiler_flags)
"""


def _cpu_flags() -> set:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


@pytest.mark.parametrize("isa", ["avx2", "avx512"])
def test_simd_parity_holds_in_the_avx2_and_the_avx512_build(isa):
    missing = NEEDS[isa] - _cpu_flags()
    if missing:
        pytest.skip(f"this CPU cannot run the {isa} build (no {', '.join(sorted(missing))})")
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, "-c", _RUN, ISA_FLAGS[isa]], cwd=REPO, env=env, capture_output=True,
                          text=True, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    built = [ln.split(" ", 2) for ln in proc.stdout.splitlines() if ln.startswith("BUILT ")]
    assert built and built[-1][2] == ISA_FLAGS[isa]  # the kernels that passed were built with the target's flags
    objdump = shutil.which("objdump")
    if objdump:  # and the build is that target's: AVX-512 registers only in the AVX-512 build
        asm = subprocess.run([objdump, "-d", built[-1][1]], capture_output=True, text=True, check=True).stdout
        assert ("zmm" in asm) == (isa == "avx512") and "ymm" in asm
