"""Replayed CPU launches (gausslite.render.launch.launch_cpu) against ``wp.launch``."""

from __future__ import annotations

import threading

import pytest
import torch
import warp as wp

from gausslite.render import warp_kernels as wk
from gausslite.render.launch import Vec, launch_cpu


def _projection_args(n: int, dtype, seed: int):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) + torch.tensor([0.0, 0.0, 2.5], dtype=dtype)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=dtype), dim=1)
    log_scales = torch.rand(n, 3, generator=g, dtype=dtype) - 4.0
    consts = [wp.mat33d(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), wp.vec3d(0.1, -0.2, 0.0),
              wp.vec4d(300.0, 310.0, 160.0, 120.0), 320, 240, wp.float64(0.01), wp.float64(1e4), wp.float64(0.3)]
    outs = [torch.zeros(n, 2, dtype=dtype), torch.zeros(n, 3, dtype=dtype), torch.zeros(n, dtype=dtype),
            torch.zeros(n, dtype=torch.int32)]
    return [means, quats, log_scales], consts, outs


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_replayed_launches_equal_wp_launch(dtype):
    """The same outputs as wp.launch, call after call with new tensors, other sizes and another offset (the
    recorded launch's slots are all rewritten), for both overloads of a generic kernel."""
    wk.ensure_loaded("cpu")
    for n, seed in ((50, 0), (50, 1), (7, 2), (300, 3)):
        ins, consts, ref = _projection_args(n, dtype, seed)
        wp.launch(wk.project_fwd_kernel, dim=n, inputs=[wp.from_torch(t) for t in ins] + consts + [0],
                  outputs=[wp.from_torch(t) for t in ref], device="cpu")
        _, _, got = _projection_args(n, dtype, seed)
        half = n // 2
        launch_cpu(wk.project_fwd_kernel, half, ins + consts + [0] + got)
        launch_cpu(wk.project_fwd_kernel, n - half, ins + consts + [half] + got)
        for a, b in zip(got, ref):
            assert torch.equal(a, b)
        assert int((got[3] > 0).sum()) > 0  # the scene is in view: the outputs are not all zero


def test_vector_views_and_threads():
    """A Vec argument (a (N, 4) tensor as an array of vec4) and launches from two threads (each replays its own
    recording) give the packed rows wp.launch gives."""
    wk.ensure_loaded("cpu")
    n = 64
    g = torch.Generator().manual_seed(4)
    ins = [torch.rand(n, 2, generator=g) * 100, torch.rand(n, 3, generator=g) * 0.1 + torch.tensor([0.5, 0.0, 0.5]),
           torch.randn(n, generator=g), torch.rand(n, 3, generator=g), torch.rand(n, generator=g) + 1.0]
    ref = torch.zeros(n, 16)
    wp.launch(wk.pack_gdata_kernel, dim=n, inputs=[wp.from_torch(t) for t in ins] + [1],
              outputs=[wp.from_torch(ref)], device="cpu")
    results = {}

    def run(k):
        out = torch.zeros(n, 16)
        for _ in range(3):
            launch_cpu(wk.pack_gdata_kernel, n, ins + [1, out])
        results[k] = out

    threads = [threading.Thread(target=run, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k in range(2):
        assert torch.equal(results[k], ref)
    # a vec4 view: the background colour written through a (N, 4) tensor seen as N vec4
    c4 = torch.zeros(n, 4)
    launch_cpu(_fill_vec4, n, [Vec(c4, wp.vec4), 2.5])
    assert torch.equal(c4, torch.full((n, 4), 2.5) * torch.tensor([1.0, 2.0, 3.0, 4.0]))


@wp.kernel
def _fill_vec4(out: wp.array(dtype=wp.vec4), x: float):
    i = wp.tid()
    out[i] = wp.vec4(x, 2.0 * x, 3.0 * x, 4.0 * x)


def test_bad_arguments_are_refused():
    wk.ensure_loaded("cpu")
    c8 = torch.zeros(16, 8)
    with pytest.raises(ValueError, match="contiguous"):
        launch_cpu(_fill_vec4, 16, [Vec(c8[:, ::2], wp.vec4), 1.0])
    launch_cpu(_fill_vec4, 0, [Vec(torch.zeros(0, 4), wp.vec4), 1.0])  # nothing to launch: no error, no work
