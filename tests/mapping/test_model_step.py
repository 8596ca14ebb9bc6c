"""Masked Adam step of the ROI phase (``GaussianModel.step(update=...)``) against its slow reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gausslite.gaussians import GaussianMap
from gausslite.mapping.config import LearningRates
from gausslite.mapping.model import GaussianModel, masked_step_reference


def _model(n: int, seed: int) -> GaussianModel:
    g = torch.Generator().manual_seed(seed)
    gmap = GaussianMap(
        means=torch.randn(n, 3, generator=g), quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
        log_scales=torch.randn(n, 3, generator=g) - 3, opacity_logits=torch.randn(n, generator=g),
        colors=torch.rand(n, 3, generator=g), active=torch.rand(n, generator=g) < 0.3,
        kappa=torch.zeros(n, dtype=torch.int64))
    m = GaussianModel(LearningRates())
    m.set_map(gmap)
    return m


def _grads(model: GaussianModel, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    for p in model.params.values():
        p.grad = torch.randn(p.shape, generator=g) * 1e-2


@pytest.mark.parametrize("schedule", ["FMMFM", "MMMF", "MFMF"])
def test_masked_step_matches_full_step_with_restore(schedule):
    """F = full step, M = masked step: values, both Adam moments and the step count agree with the
    reference (full step, then the unselected rows restored) after every step; unselected rows never move."""
    fast, ref = _model(500, 0), _model(500, 0)
    rng = np.random.default_rng(1)
    for i, kind in enumerate(schedule):
        mask = torch.from_numpy(rng.random(500) < 0.2) if kind == "M" else None
        before = {k: v.detach().clone() for k, v in fast.params.items()}
        _grads(fast, i)
        _grads(ref, i)
        fast.step(update=mask)
        if mask is None:
            ref.step()
        else:
            masked_step_reference(ref, mask)
        for name in fast.params:
            a, b = fast.params[name].detach(), ref.params[name].detach()
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
            sa, sb = fast.optimizer.state[fast.params[name]], ref.optimizer.state[ref.params[name]]
            assert float(sa["step"]) == float(sb["step"]) == i + 1
            for k in ("exp_avg", "exp_avg_sq"):
                # the moments are about 1e-3 and 1e-6 here; 2e-10 is two float32 ulps of 1e-3 (a moment that
                # cancels towards 0 keeps its rounding in absolute terms)
                torch.testing.assert_close(sa[k], sb[k], rtol=1e-5, atol=2e-10)
            if mask is not None:
                assert torch.equal(a[~mask], before[name][~mask])
                assert not torch.equal(a[mask], before[name][mask])
        assert all(p.grad is None for p in fast.params.values())


def test_masked_step_with_empty_selection_moves_nothing():
    m = _model(50, 3)
    before = {k: v.detach().clone() for k, v in m.params.items()}
    _grads(m, 0)
    m.step(update=torch.zeros(50, dtype=torch.bool))
    for k, v in m.params.items():
        assert torch.equal(v.detach(), before[k])



@pytest.mark.parametrize("steps", [1, 7])
def test_fused_masked_adam_matches_the_torch_ops(steps):
    """The Warp masked step (one launch per parameter) against the torch ops it replaces, over several steps with
    a new selection each: values and both moments within float32 rounding, unselected rows exactly unchanged."""
    fast, ref = _model(400, 5), _model(400, 5)
    rng = np.random.default_rng(2)
    for i in range(steps):
        mask = torch.from_numpy(rng.random(400) < 0.3)
        rows = torch.nonzero(mask).squeeze(1)
        before = {k: v.detach().clone() for k, v in fast.params.items()}
        _grads(fast, 10 + i)
        _grads(ref, 10 + i)
        fast._masked_adam(rows)
        ref._masked_adam(rows, fused=False)
        for name in fast.params:
            a, b = fast.params[name].detach(), ref.params[name].detach()
            torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
            assert torch.equal(a[~mask], before[name][~mask])
            sa, sb = fast.optimizer.state[fast.params[name]], ref.optimizer.state[ref.params[name]]
            for k in ("exp_avg", "exp_avg_sq"):
                torch.testing.assert_close(sa[k], sb[k], rtol=1e-6, atol=2e-10)
        for m in (fast, ref):
            m.optimizer.zero_grad(set_to_none=True)


def test_fused_masked_adam_rejects_what_it_cannot_update():
    from gausslite.mapping.adam import masked_adam_

    p = torch.zeros(4, 3)
    with pytest.raises(ValueError, match="float32"):
        masked_adam_(p.double(), p.double(), p.double(), p.double(), torch.tensor([0]), 1e-3, 0.9, 0.999, 1e-8, 1)
    with pytest.raises(ValueError, match="one shape"):
        masked_adam_(p, torch.zeros(4, 2), p.clone(), p.clone(), torch.tensor([0]), 1e-3, 0.9, 0.999, 1e-8, 1)

# ---------------------------------------------------------------- coarse (downscaled) views
def test_downscale_keyframe_pixel_centres_and_depth():
    """fx' = fx/f, cx' = (cx + 0.5)/f − 0.5: a 3-D point lands on the same place of the image in both
    pixel grids; colour is the block mean, depth the mean of the valid depths of a block."""
    from gausslite.mapping.views import Keyframe, downscale_keyframe

    H, W, f = 6, 8, 2
    rgb = torch.arange(H * W * 3, dtype=torch.float32).reshape(H, W, 3) / (H * W * 3)
    depth = torch.full((H, W), 2.0)
    depth[0, 0] = 0.0  # invalid: the block's depth is the mean of the other three
    depth[0, 1] = 3.0
    K = torch.tensor([[10.0, 0, 3.5], [0, 12.0, 2.5], [0, 0, 1]])
    roi = torch.zeros(H, W, dtype=torch.bool)
    roi[5, 7] = True
    kf = Keyframe(frame_id=0, rgb=rgb, depth=depth, c2w=torch.eye(4, dtype=torch.float64), K=K, width=W, height=H,
                  roi=roi, roi_box=(7, 5, 8, 6))
    d = downscale_keyframe(kf, f)
    assert (d.width, d.height) == (4, 3)
    torch.testing.assert_close(d.rgb[0, 0], rgb[:2, :2].reshape(-1, 3).mean(0))
    assert float(d.depth[0, 0]) == pytest.approx((3.0 + 2.0 + 2.0) / 3)
    assert float(d.depth[1, 1]) == pytest.approx(2.0)
    p = torch.tensor([0.3, -0.2, 2.0])
    u, v = (K @ p / p[2])[:2]
    u2, v2 = (d.K @ p / p[2])[:2]
    assert float(u2) == pytest.approx((float(u) + 0.5) / f - 0.5)
    assert float(v2) == pytest.approx((float(v) + 0.5) / f - 0.5)
    assert d.roi_box == (3, 2, 4, 3) and bool(d.roi[2, 3]) and int(d.roi.sum()) == 1
    assert downscale_keyframe(kf, 1) is kf
    with pytest.raises(ValueError):
        downscale_keyframe(kf, 0)


def test_coarse_iterations_render_downscaled_views(monkeypatch):
    """With coarse_iters = k, the first k iterations of a frame render at 1/coarse_downscale, the rest at
    full resolution; coarse_iters = 0 never renders a downscaled view."""
    from gausslite.datasets.base import Frame
    from gausslite.camera import Intrinsics
    from gausslite.mapping.config import MapperConfig
    from gausslite.mapping.mapper import Mapper

    H, W = 24, 32
    intr = Intrinsics(30.0, 30.0, (W - 1) / 2, (H - 1) / 2, W, H)
    rng = np.random.default_rng(0)
    frame = Frame(0, 0.0, rng.integers(0, 255, (H, W, 3), dtype=np.uint8), np.full((H, W), 2.0, np.float32),
                  np.eye(4), intr)
    for coarse, want in ((3, [16] * 3 + [32] * 5), (0, [32] * 8)):
        m = Mapper(MapperConfig(iters_per_frame=8, warmup_iters=8, seeding={"seeds_per_frame": 300},
                                performance={"coarse_iters": coarse}, backend="torch"))
        widths = []
        orig = m.sensor.rasterize
        monkeypatch.setattr(m.sensor, "rasterize", lambda c2w, K, w, h, subset, **kw: (widths.append(w), orig(c2w, K, w, h, subset, **kw))[1])
        st = m.map_frame(frame)
        assert st.iters == 8
        assert [w for w in widths if w in (16, 32)][-8:] == want


def _render_loss(model: GaussianModel, target: torch.Tensor) -> torch.Tensor:
    from gausslite.render import rasterize

    p = model.params
    K = np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])
    out = rasterize(p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"], K=K, width=32,
                    height=32, c2w=np.eye(4))
    return (out.color - target).abs().mean()


def test_clones_start_from_zero_moments_and_separate_from_their_parent():
    """A clone is an exact copy; if it inherited its parent's Adam moments, the two co-located copies would
    get proportional gradients and identical Adam steps forever (they never separate, and are cloned again
    at every density step). Clones start from zero moments (3DGS, gsplat), the original keeps its own."""
    gmap = GaussianMap(
        means=torch.tensor([[0.02, -0.01, 1.0]]), quats=torch.tensor([[1.0, 0, 0, 0]]),
        log_scales=torch.full((1, 3), np.log(0.05)), opacity_logits=torch.tensor([-1.0]),
        colors=torch.tensor([[0.8, 0.6, 0.4]]), active=torch.tensor([False]), kappa=torch.zeros(1, dtype=torch.int64))
    model = GaussianModel(LearningRates())
    model.set_map(gmap)
    yy, xx = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    target = torch.stack([xx / 31, yy / 31, 0.5 * torch.ones_like(xx)], -1)
    for _ in range(5):
        _render_loss(model, target).backward()
        model.step()
    parent_m = model.optimizer.state[model.params["means"]]["exp_avg"].clone()
    assert parent_m.abs().sum() > 0
    cur = model.to_map()
    new, parent = cur.densify(torch.tensor([True]), torch.tensor([False]))
    model.set_map(new, parent)
    st = model.optimizer.state[model.params["means"]]
    assert torch.equal(st["exp_avg"][0], parent_m[0])  # the original keeps its moments
    assert st["exp_avg"][1].abs().sum() == 0 and st["exp_avg_sq"][1].abs().sum() == 0  # the clone starts fresh
    assert model.ids[0] != model.ids[1]
    for _ in range(5):
        _render_loss(model, target).backward()
        model.step()
    m = model.params["means"].detach()
    assert (m[0] - m[1]).norm() > 1e-5, "clone moved in lockstep with its parent"


def test_lr_scale_and_cosine_factor():
    from gausslite.gaussians import GaussianMap
    from gausslite.mapping.config import LearningRates
    from gausslite.mapping.model import GaussianModel, cosine_lr_factor

    m = GaussianModel(LearningRates())
    m.set_map(GaussianMap.from_points(torch.zeros(3, 3), torch.full((3, 3), 0.5), torch.full((3, 3), 0.1)))
    m.set_lr_scale(0.25)
    for g in m.optimizer.param_groups:
        assert g["lr"] == pytest.approx(0.25 * getattr(LearningRates(), g["name"]))
    m.set_map(m.to_map(), torch.arange(3))  # a rebuild restores the configured rates
    assert m.optimizer.param_groups[0]["lr"] == LearningRates().means
    f = [cosine_lr_factor(i, 5, 0.1) for i in range(5)]
    assert f[0] == 1.0 and f[-1] == pytest.approx(0.1) and f == sorted(f, reverse=True)
    assert cosine_lr_factor(0, 1, 0.1) == 1.0


def test_finetune_and_refine_reject_a_bad_final_lr():
    from gausslite.fusion.refine import refine_map
    from gausslite.gaussians import GaussianMap
    from gausslite.sharing import finetune_subset

    g = GaussianMap.from_points(torch.zeros(3, 3), torch.full((3, 3), 0.5), torch.full((3, 3), 0.1))
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="final_lr"):
            finetune_subset(g, [], 5, final_lr=bad)
        with pytest.raises(ValueError, match="final_lr"):
            refine_map(g, [], 5, final_lr=bad)


@pytest.mark.parametrize("fused", [True, False])
def test_the_maps_adam_is_torch_optim_adam(fused):
    """The map's optimiser (torch's fused kernel, or its torch ops) against ``torch.optim.Adam`` with the mapper's
    groups, learning rates and ε over 6 full steps, one learning-rate change between them: values and both moments
    within float32 rounding of its foreach update, the same step count; the fused step equal bit for bit to
    ``torch.optim.Adam(fused=True)``, the mapper's optimiser before (so a map's arithmetic did not change)."""
    from gausslite.mapping.adam import Adam

    ours, ref, ref_fused = _model(300, 4), _model(300, 4), _model(300, 4)

    def torch_adam_of(model, **kw):
        return torch.optim.Adam([{"params": [model.params[n]], "lr": g["lr"]}
                                 for n, g in zip(model.params, ours.optimizer.param_groups)], lr=0.0, eps=1e-15, **kw)

    torch_adam, torch_fused = torch_adam_of(ref), torch_adam_of(ref_fused, fused=True)
    assert isinstance(ours.optimizer, Adam)
    for i in range(6):
        if i == 3:
            for a, b, c in zip(ours.optimizer.param_groups, torch_adam.param_groups, torch_fused.param_groups):
                a["lr"] = b["lr"] = c["lr"] = 0.5 * b["lr"]
        for m in (ours, ref, ref_fused):
            _grads(m, 20 + i)
        ours.optimizer.step(fused=fused)
        torch_adam.step()
        torch_fused.step()
        for name in ours.params:
            if fused:
                assert torch.equal(ours.params[name], ref_fused.params[name])
                for k in ("exp_avg", "exp_avg_sq"):
                    assert torch.equal(ours.optimizer.state[ours.params[name]][k],
                                       torch_fused.state[ref_fused.params[name]][k])
            torch.testing.assert_close(ours.params[name].detach(), ref.params[name].detach(), rtol=1e-5, atol=1e-7)
            sa, sb = ours.optimizer.state[ours.params[name]], torch_adam.state[ref.params[name]]
            assert float(sa["step"]) == float(sb["step"]) == i + 1
            for k in ("exp_avg", "exp_avg_sq"):
                torch.testing.assert_close(sa[k], sb[k], rtol=1e-5, atol=2e-10)
        ours.optimizer.zero_grad()
        torch_adam.zero_grad()
        torch_fused.zero_grad()
    assert all(p.grad is None for p in ours.params.values())


def test_mapping_does_not_import_torch_dynamo():
    """A mapper's whole step runs without ``torch._dynamo``, which the first ``torch.optim`` optimiser imports (about
    a second of every mapping process's start): checked in a fresh interpreter that maps two frames, and that an
    optimiser of ``torch.optim`` does import it there (the check can fail)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import sys\n"
        "import numpy as np\n"
        "from gausslite.mapping.config import MapperConfig\n"
        "from gausslite.mapping.mapper import Mapper\n"
        "from tests._scenes import plane_frame\n"
        "m = Mapper(MapperConfig(iters_per_frame=6, warmup_iters=2, seeding={'seeds_per_frame': 200}))\n"
        "roi = np.zeros((40, 56), bool); roi[10:26, 14:34] = True\n"
        "for i in range(2): st = m.map_frame(plane_frame(i, 0.0, 40, 56), roi)\n"
        "assert st.iters == 6 and len(m.model) > 0\n"
        "print(sorted(k for k in sys.modules if k.startswith('torch._dynamo')))\n"
        "import torch\n"
        "torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))])\n"
        "print('torch._dynamo' in sys.modules)\n")
    root = str(Path(__file__).resolve().parents[2])
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=True,
                         cwd=root, env={**os.environ, "PYTHONPATH": root})
    assert out.stdout.strip().splitlines()[-2:] == ["[]", "True"], out.stdout


def test_active_size_counts_the_task_gaussians_and_their_median_largest_axis():
    m = _model(50, 3)
    m.active[:] = False
    assert m.active_size() == (0, 0.0)
    m.active[:5] = True
    with torch.no_grad():
        m.params["log_scales"][:5] = torch.log(torch.tensor([[0.01, 0.02, 0.005], [0.03, 0.01, 0.01],
                                                             [0.001, 0.001, 0.04], [0.02, 0.02, 0.02],
                                                             [0.05, 0.01, 0.01]]))
    n, scale = m.active_size()
    assert n == 5 and scale == pytest.approx(0.03)  # the largest axes 0.02, 0.03, 0.04, 0.02, 0.05: median 0.03
