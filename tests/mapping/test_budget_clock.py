"""The keyframe budget's deterministic twin (gausslite.mapping.budget) and the realtime bench's protocol:
budgets on the work clock give the same iterations on any machine, the warm-up/ROI split of a budget, and a
Gaussian cap that binds both modes."""

import numpy as np
import pytest

from gausslite.mapping.budget import WallClock, WorkClock, WorkCost, fit_work_cost
from gausslite.mapping.config import MapperConfig, deep_merge
from gausslite.mapping.mapper import Mapper
from tests._scenes import plane_frame

H, W = 40, 56


def _roi() -> np.ndarray:
    r = np.zeros((H, W), bool)
    r[10:26, 14:34] = True
    return r


def _cfg(**kw) -> MapperConfig:
    base = dict(seeding={"seeds_per_frame": 300}, iters_per_frame=30, warmup_iters=10, window=4, backend="warp",
                mode="gausslite", budget_clock="work")
    base = deep_merge(base, kw)  # a group given as a keyword is merged key by key
    cfg = MapperConfig(**base)
    cfg.densify.enabled = False
    return cfg


def test_fit_work_cost_recovers_a_linear_model():
    true = WorkCost(render_s=2e-3, pixel_s=3e-7, gaussian_s=1e-6, step_s=1.5e-3, step_gaussian_s=5e-7)
    rng = np.random.default_rng(0)
    samples = []
    for _ in range(40):
        r = int(rng.integers(1, 6))
        px = int(rng.integers(1_000, 80_000)) * r
        g = int(rng.integers(500, 20_000))
        n = int(rng.integers(500, 20_000))
        t = true.render_s * r + true.pixel_s * px + true.gaussian_s * g * r + true.step(n)
        samples.append((r, px, g * r, n, t))
    fit = fit_work_cost(samples)
    for f in ("render_s", "pixel_s", "gaussian_s", "step_s", "step_gaussian_s"):
        assert getattr(fit, f) == pytest.approx(getattr(true, f), rel=1e-6)
    with pytest.raises(ValueError):
        fit_work_cost(samples[:3])
    with pytest.raises(ValueError):
        WorkCost(render_s=-1.0)


def test_work_clock_charges_renders_and_steps():
    c = WorkClock(WorkCost(render_s=1.0, pixel_s=0.01, gaussian_s=0.1, step_s=2.0, step_gaussian_s=0.5,
                           no_grad_factor=0.5))
    c.charge_render(100, 10)
    assert c.now() == pytest.approx(1.0 + 1.0 + 1.0)
    c.charge_render(100, 10, grad=False)
    assert c.now() == pytest.approx(3.0 + 1.5)
    c.charge_step(4)
    assert c.now() == pytest.approx(4.5 + 2.0 + 2.0)
    w = WallClock()
    assert w.now() <= WallClock().now() and not w.charges and c.charges


def _map(cfg, frames=4, budget=0.05):
    m = Mapper(cfg)
    stats = [m.map_frame(plane_frame(i, 0.0, H, W), _roi(), time_budget_s=budget) for i in range(frames)]
    return m, stats


def test_work_clock_budget_is_deterministic_and_scales_with_the_budget():
    m1, s1 = _map(_cfg())
    m2, s2 = _map(_cfg())
    assert [s.iters for s in s1] == [s.iters for s in s2]
    assert [s.active_iters for s in s1] == [s.active_iters for s in s2]
    assert np.array_equal(m1.model.params["means"].detach().numpy(), m2.model.params["means"].detach().numpy())
    _, s4 = _map(_cfg(), budget=0.2)
    # 4x the budget: about 4x the iterations (seeding is charged once per keyframe)
    ratio = sum(s.iters for s in s4[1:]) / sum(s.iters for s in s1[1:])
    assert 3.0 < ratio < 5.0
    # iterations of a frame fit its budget on the work clock: at most one iteration over it
    cost = WorkCost(**_cfg().work_cost.model_dump())
    one = cost.render(W * H, len(m1.model)) + cost.step(len(m1.model))
    assert all(s.iters <= 0.05 / (cost.step_s + cost.render_s) + 1 for s in s1)
    assert one > 0


def test_budget_split_warm_up_then_roi_phase_on_the_work_clock():
    """The first warmup_iters / iters_per_frame of a budget (after seeding) is full-image, the rest ROI-phase; an
    ROI-phase iteration renders only the ROI's box, so it is cheaper and more of them fit."""
    cfg = _cfg()
    m = Mapper(cfg)
    m.map_frame(plane_frame(0, 0.0, H, W), _roi())
    phases = []
    real = m.step
    times = []

    def spy(view, active_phase, **kw):
        t = m.clock.now()
        out = real(view, active_phase, **kw)
        phases.append(active_phase)
        times.append(m.clock.now() - t)
        return out

    m.step = spy
    st = m.map_frame(plane_frame(1, 0.0, H, W), _roi(), time_budget_s=0.2)
    n_warm = phases.index(True)
    assert n_warm >= 1 and all(phases[n_warm:]) and st.active_iters == len(phases) - n_warm
    warm_time, roi_time = sum(times[:n_warm]), sum(times[n_warm:])
    # the warm-up ends at the first iteration that starts past 1/3 of the budget left after seeding
    assert warm_time == pytest.approx(0.2 / 3, abs=max(times[:n_warm]) + 0.2 * 0.05)
    assert roi_time > warm_time
    assert np.mean(times[n_warm:]) < np.mean(times[:n_warm])
