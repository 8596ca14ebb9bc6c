"""GaussianMap: validation, construction, structural ops, cap and densification."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gausslite.gaussians import GaussianMap, quat_to_rotmat


def random_map(n: int, seed: int = 0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    return GaussianMap(
        means=torch.randn(n, 3, generator=g),
        quats=torch.randn(n, 4, generator=g),
        log_scales=torch.randn(n, 3, generator=g) - 3.0,
        opacity_logits=torch.randn(n, generator=g),
        colors=torch.rand(n, 3, generator=g),
        active=torch.rand(n, generator=g) > 0.5,
        kappa=torch.randint(0, 1000, (n,), generator=g),
    )


def assert_rows_equal(a: GaussianMap, i: int, b: GaussianMap, j: int, skip=()) -> None:
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors", "active", "kappa"):
        if name in skip:
            continue
        assert torch.equal(getattr(a, name)[i], getattr(b, name)[j]), name


# ------------------------------------------------------------------ validation
def test_validation_messages():
    m = random_map(4)
    with pytest.raises(ValueError, match=r"quats must have shape \(4, 4\)"):
        GaussianMap(**{**m.__dict__, "quats": torch.zeros(3, 4)})
    with pytest.raises(ValueError, match="kappa must have dtype torch.int64"):
        GaussianMap(**{**m.__dict__, "kappa": torch.zeros(4, dtype=torch.int32)})
    with pytest.raises(ValueError, match="active must have dtype torch.bool"):
        GaussianMap(**{**m.__dict__, "active": torch.zeros(4)})
    with pytest.raises(ValueError, match="colors must have dtype torch.float32"):
        GaussianMap(**{**m.__dict__, "colors": torch.zeros(4, 3, dtype=torch.float64)})
    with pytest.raises(ValueError, match=r"means must have shape \(N, 3\)"):
        GaussianMap(**{**m.__dict__, "means": torch.zeros(4, 2)})
    with pytest.raises(ValueError, match="must be a torch.Tensor"):
        GaussianMap(**{**m.__dict__, "kappa": [0, 0, 0, 0]})
    with pytest.raises(ValueError, match=r"opacity_logits must have shape \(4,\)"):
        GaussianMap(**{**m.__dict__, "opacity_logits": torch.zeros(4, 1)})
    with pytest.raises(ValueError, match="share a device"):
        GaussianMap(**{**m.__dict__, "kappa": torch.zeros(4, dtype=torch.int64, device="meta")})


def test_empty_and_len_device():
    e = GaussianMap.empty()
    assert len(e) == 0 and e.device == torch.device("cpu")
    assert e.means.shape == (0, 3) and e.quats.shape == (0, 4) and e.kappa.dtype == torch.int64
    m = random_map(5)
    assert len(e.append(m)) == 5
    assert len(m.to("cpu")) == 5
    assert repr(m).startswith("GaussianMap(N=5, active=")


def test_from_points():
    means = torch.tensor([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])
    colors = torch.tensor([[0.1, 0.2, 0.3], [0.9, 0.8, 0.7]])
    m = GaussianMap.from_points(means, colors, torch.tensor([0.01, 0.02]), opacity=0.3, active=torch.tensor([True, False]))
    assert torch.equal(m.quats, torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]]))
    assert torch.allclose(m.scales, torch.tensor([[0.01] * 3, [0.02] * 3]))
    assert torch.allclose(m.opacity, torch.full((2,), 0.3))
    assert torch.allclose(m.opacity_logits, torch.full((2,), math.log(0.3 / 0.7)))
    assert m.active.tolist() == [True, False] and m.kappa.tolist() == [0, 0]
    assert torch.equal(m.means, means) and torch.equal(m.colors, colors)
    m3 = GaussianMap.from_points(means, colors, torch.tensor([[0.1, 0.2, 0.3]] * 2))
    assert torch.allclose(m3.log_scales[0], torch.log(torch.tensor([0.1, 0.2, 0.3])))
    assert not m3.active.any()
    assert GaussianMap.from_points(means, colors, 0.05, active=True).active.all()
    assert len(GaussianMap.from_points(torch.zeros(0, 3), torch.zeros(0, 3), 0.1)) == 0
    with pytest.raises(ValueError, match="scales must be > 0"):
        GaussianMap.from_points(means, colors, torch.tensor([0.1, 0.0]))
    with pytest.raises(ValueError, match="opacity"):
        GaussianMap.from_points(means, colors, 0.1, opacity=1.0)
    with pytest.raises(ValueError, match="colors"):
        GaussianMap.from_points(means, colors[:1], 0.1)


def test_detach_clone_independent():
    m = random_map(3)
    m.means.requires_grad_(True)
    d = m.detach()
    assert not d.means.requires_grad and d.means.data_ptr() == m.means.data_ptr()
    c = m.clone()
    c.kappa += 1
    c.means.data += 1
    assert torch.equal(m.kappa + 1, c.kappa) and not torch.equal(m.means, c.means)


# ------------------------------------------------------------- structural ops
def test_append_prune_subset():
    a, b = random_map(4, 1), random_map(3, 2)
    ab = a.append(b)
    assert len(ab) == 7
    assert_rows_equal(ab, 5, b, 1)
    keep = torch.tensor([True, False, True, False, False, True, True])
    p = ab.prune(keep)
    assert len(p) == 4
    for out_row, in_row in enumerate([0, 2, 5, 6]):
        assert_rows_equal(p, out_row, ab, in_row)
    s = ab.subset(torch.tensor([6, 0, 0, -1]))
    assert_rows_equal(s, 0, ab, 6)
    assert_rows_equal(s, 2, ab, 0)
    assert_rows_equal(s, 3, ab, 6)
    assert len(ab.subset(slice(1, 3))) == 2
    s.kappa[0] = -5  # gathered copy: source untouched
    assert ab.kappa[6] != -5
    with pytest.raises(ValueError, match="mask must have shape"):
        ab.subset(torch.ones(3, dtype=torch.bool))
    with pytest.raises(ValueError, match="out of range"):
        ab.subset(torch.tensor([7]))
    with pytest.raises(ValueError, match="keep_mask"):
        ab.prune(torch.ones(7))


def test_ops_preserve_autograd():
    m = random_map(4)
    m.colors.requires_grad_(True)
    sub = m.subset(torch.tensor([0, 2]))
    sub.colors.sum().backward()
    assert m.colors.grad[:, 0].tolist() == [1.0, 0.0, 1.0, 0.0]


def test_cap_keeps_highest_score_with_stable_ties():
    m = random_map(6)
    score = torch.tensor([0.5, 0.9, 0.5, 0.1, 0.5, float("nan")])
    capped, keep = m.cap(3, score)
    # 0.9 first, then ties at 0.5 resolved by lower index: 0, 2.
    assert keep.tolist() == [True, True, True, False, False, False]
    assert len(capped) == 3 and torch.equal(capped.means, m.means[keep])
    capped_all, keep_all = m.cap(10)
    assert keep_all.all() and len(capped_all) == 6
    capped0, keep0 = m.cap(0)
    assert len(capped0) == 0 and not keep0.any()
    # default score = opacity
    _, keep_op = m.cap(2)
    top2 = torch.topk(m.opacity_logits, 2).indices
    assert set(keep_op.nonzero().squeeze(1).tolist()) == set(top2.tolist())
    with pytest.raises(ValueError):
        m.cap(-1)
    with pytest.raises(ValueError, match="score must have shape"):
        m.cap(2, torch.zeros(5))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, 3), min_size=0, max_size=30), st.integers(0, 35))
def test_cap_property(scores, budget):
    n = len(scores)
    m = random_map(n)
    s = torch.tensor(scores, dtype=torch.float32)
    capped, keep = m.cap(budget, s)
    assert len(capped) == min(n, budget) == int(keep.sum())
    if 0 < budget < n:
        # every kept score >= every dropped score, and among equal scores kept indices come first
        kept, dropped = s[keep], s[~keep]
        assert kept.min() >= dropped.max()
        boundary = kept.min()
        tie_kept = keep.nonzero().squeeze(1)[s[keep] == boundary]
        tie_dropped = (~keep).nonzero().squeeze(1)[s[~keep] == boundary]
        if len(tie_kept) and len(tie_dropped):
            assert tie_kept.max() < tie_dropped.min()


# ---------------------------------------------------------------- densify
def test_densify_row_order_and_inheritance():
    m = random_map(5, 3)
    clone = torch.tensor([True, False, True, False, False])
    split = torch.tensor([False, False, True, True, False])  # row 2 in both -> split only
    out, parent = m.densify(clone, split, n_split=3, generator=torch.Generator().manual_seed(0))
    expected_parent = [0, 1, 4] + [0] + [2, 2, 2, 3, 3, 3]
    assert parent.tolist() == expected_parent and parent.dtype == torch.int64
    assert len(out) == len(expected_parent)
    for row in range(4):  # kept originals and the clone: exact copies
        assert_rows_equal(out, row, m, expected_parent[row])
    for row in range(4, 10):
        p = expected_parent[row]
        assert_rows_equal(out, row, m, p, skip=("means", "log_scales"))
        assert torch.allclose(out.log_scales[row], m.log_scales[p] - math.log(0.8 * 3))
    # daughters of one parent differ from each other (sampled)
    assert not torch.equal(out.means[4], out.means[5])


def test_densify_deterministic_with_generator_and_validation():
    m = random_map(4)
    sm = torch.tensor([True, True, False, False])
    cm = torch.zeros(4, dtype=torch.bool)
    a, _ = m.densify(cm, sm, generator=torch.Generator().manual_seed(7))
    b, _ = m.densify(cm, sm, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a.means, b.means)
    same, parent = m.densify(cm, cm)
    assert parent.tolist() == [0, 1, 2, 3] and torch.equal(same.means, m.means)
    with pytest.raises(ValueError, match="n_split"):
        m.densify(cm, sm, n_split=0)
    with pytest.raises(ValueError, match="clone_mask"):
        m.densify(torch.zeros(3, dtype=torch.bool), sm)


def test_split_daughters_follow_parent_covariance():
    # One strongly anisotropic, rotated parent; many daughters -> sample covariance ≈ R S² Rᵀ.
    angle = math.pi / 3
    q = torch.tensor([[math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]])  # rotation about z
    m = GaussianMap(
        means=torch.tensor([[1.0, -2.0, 0.5]]), quats=q,
        log_scales=torch.log(torch.tensor([[0.5, 0.05, 0.2]])), opacity_logits=torch.zeros(1),
        colors=torch.full((1, 3), 0.5), active=torch.tensor([True]), kappa=torch.tensor([42]),
    )
    n = 20000
    out, parent = m.densify(torch.zeros(1, dtype=torch.bool), torch.ones(1, dtype=torch.bool), n_split=n,
                            generator=torch.Generator().manual_seed(1))
    assert (parent == 0).all() and out.active.all() and (out.kappa == 42).all()
    d = (out.means - m.means).double()
    cov = d.T @ d / n
    r = quat_to_rotmat(q)[0].double()
    expected = r @ torch.diag(torch.tensor([0.5, 0.05, 0.2]).double() ** 2) @ r.T
    assert torch.allclose(cov, expected, atol=0.01)
    assert torch.allclose(d.mean(0), torch.zeros(3, dtype=torch.float64), atol=0.015)
    # expected major axis direction: x rotated by 60° about z
    evals, evecs = torch.linalg.eigh(cov)
    major = evecs[:, -1]
    assert abs(abs(float(major @ torch.tensor([math.cos(angle), math.sin(angle), 0.0]).double())) - 1) < 1e-3


def test_quat_to_rotmat_orthonormal_and_zero_safe():
    q = torch.randn(50, 4)
    r = quat_to_rotmat(q)
    eye = torch.eye(3).expand(50, 3, 3)
    assert torch.allclose(r @ r.transpose(1, 2), eye, atol=1e-5)
    assert torch.allclose(torch.linalg.det(r), torch.ones(50), atol=1e-5)
    assert torch.equal(quat_to_rotmat(torch.zeros(1, 4))[0], torch.eye(3))


def test_axis_split_matches_the_parent_along_its_longest_axis():
    # an anisotropic, rotated parent: daughters at mu +- sigma/2 on the longest axis, moment-matched, opacity-corrected
    angle = math.pi / 3
    q = torch.tensor([[math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]])
    m = GaussianMap(means=torch.tensor([[1.0, -2.0, 0.5]]), quats=q,
                    log_scales=torch.log(torch.tensor([[0.5, 0.05, 0.2]])), opacity_logits=torch.tensor([1.5]),
                    colors=torch.full((1, 3), 0.5), active=torch.tensor([True]), kappa=torch.tensor([7]))
    out, parent = m.densify(torch.zeros(1, dtype=torch.bool), torch.ones(1, dtype=torch.bool), split_mode="axis")
    assert parent.tolist() == [0, 0] and out.active.all() and (out.kappa == 7).all()
    major = torch.tensor([math.cos(angle), math.sin(angle), 0.0])
    d = out.means - m.means
    assert torch.allclose(d[0], 0.25 * major, atol=1e-6) and torch.allclose(d[1], -0.25 * major, atol=1e-6)
    scales = out.log_scales.exp()
    assert torch.allclose(scales, torch.tensor([[0.5 * math.sqrt(0.75), 0.05, 0.2]] * 2), atol=1e-6)
    # the pair's second moment along the axis is the parent's: sigma'^2 + d^2 = sigma^2
    assert math.isclose(float(scales[0, 0] ** 2 + (d[0] @ major) ** 2), 0.25, rel_tol=1e-5)
    a = torch.sigmoid(torch.tensor(1.5))
    a2 = torch.sigmoid(out.opacity_logits)
    assert torch.allclose(1 - (1 - a2) ** 2, a.expand(2), atol=1e-6)  # two overlapping daughters: the parent's alpha
    assert torch.equal(out.quats, q.expand(2, 4)) and torch.equal(out.colors, m.colors.expand(2, 3))
    with pytest.raises(ValueError, match="split_mode"):
        m.densify(torch.zeros(1, dtype=torch.bool), torch.ones(1, dtype=torch.bool), split_mode="random")
    with pytest.raises(ValueError, match="splits in 2"):
        m.densify(torch.zeros(1, dtype=torch.bool), torch.ones(1, dtype=torch.bool), n_split=3, split_mode="axis")


def test_axis_split_keeps_the_image_where_sampling_leaves_gaps():
    # a wall of large Gaussians, all split: the axis split changes the render far less than the 3DGS split
    from gausslite.render import rasterize

    g = torch.Generator().manual_seed(0)
    n = 300
    means = torch.cat([torch.rand(n, 2, generator=g) * 2 - 1, torch.full((n, 1), 3.0)], dim=1)
    m = GaussianMap(means=means, quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
                    log_scales=torch.log(torch.tensor([0.12, 0.05, 0.01])).expand(n, 3).clone(),
                    opacity_logits=torch.full((n,), 1.0), colors=torch.rand(n, 3, generator=g),
                    active=torch.zeros(n, dtype=torch.bool), kappa=torch.zeros(n, dtype=torch.int64))
    K = torch.tensor([[80.0, 0, 64], [0, 80.0, 48], [0, 0, 1]])

    def render(gm):
        return rasterize(gm.means, gm.quats, gm.log_scales, gm.opacity_logits, gm.colors, K=K, width=128, height=96,
                         c2w=torch.eye(4)).color

    ref = render(m)
    none, every = torch.zeros(n, dtype=torch.bool), torch.ones(n, dtype=torch.bool)
    err = {mode: float((render(m.densify(none, every, generator=torch.Generator().manual_seed(1),
                                         split_mode=mode)[0]) - ref).abs().mean()) for mode in ("sample", "axis")}
    assert err["axis"] < 0.5 * err["sample"], err
