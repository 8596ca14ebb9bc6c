"""κ-weighted voxel vote (paper Sec. III-E) against a brute-force reference."""

from __future__ import annotations

import math
from collections import Counter, defaultdict

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gausslite.fusion import concat, voxel_vote
from gausslite.wire import GaussianArrays

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "colors", "kappa", "active")


def make(rng: np.random.Generator, n: int, extent: float = 0.5, kappa_max: int = 5,
         grid: float | None = None) -> GaussianArrays:
    means = rng.uniform(-extent, extent, (n, 3))
    if grid:  # put means on a coarse lattice so many Gaussians share voxels and κ ties happen
        means = np.round(means / grid) * grid + 0.01
    return GaussianArrays(
        means=means.astype(np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.normal(-4, 1, (n, 3)).astype(np.float32),
        opacity_logits=rng.normal(0, 2, n).astype(np.float32),
        colors=rng.random((n, 3)).astype(np.float32),
        kappa=rng.integers(0, kappa_max + 1, n), active=rng.random(n) < 0.5,
    )


def rows(g: GaussianArrays) -> list[bytes]:
    """Each Gaussian as the bytes of all its fields (exact identity)."""
    if len(g) == 0:
        return []
    cols = [np.ascontiguousarray(getattr(g, k)).reshape(len(g), -1).view(np.uint8) for k in FIELDS]
    return [b"".join(c[i].tobytes() for c in cols) for i in range(len(g))]


def reference_vote(maps: dict[str, GaussianArrays], delta: float) -> list[bytes]:
    """Brute-force Python implementation of the documented rule, in canonical output order."""
    per_voxel: dict[tuple, dict[str, list[int]]] = defaultdict(lambda: defaultdict(list))
    for a, g in maps.items():
        for i in range(len(g)):
            key = tuple(math.floor(float(x) / delta) for x in g.means[i].astype(np.float64))
            per_voxel[key][a].append(i)
    keep = {a: set() for a in maps}
    for key, contrib in per_voxel.items():
        winner = min(contrib, key=lambda a: (-sum(int(maps[a].kappa[i]) for i in contrib[a]),
                                             -len(contrib[a]), a))
        keep[winner].update(contrib[winner])
    out = []
    for a in sorted(maps):
        r = rows(maps[a])
        out += [r[i] for i in sorted(keep[a])]
    return out


agent_ids = st.lists(st.text("abcxyz0", min_size=1, max_size=3), min_size=1, max_size=4,
                     unique=True)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ids=agent_ids, seed=st.integers(0, 2**32 - 1), n_max=st.integers(0, 40),
       delta=st.sampled_from([0.05, 0.1, 0.3]), grid=st.sampled_from([None, 0.1]),
       kappa_max=st.sampled_from([0, 1, 5]))
def test_matches_brute_force_reference(ids, seed, n_max, delta, grid, kappa_max):
    rng = np.random.default_rng(seed)
    maps = {a: make(rng, int(rng.integers(0, n_max + 1)), kappa_max=kappa_max, grid=grid)
            for a in ids}
    fused, rep = voxel_vote(maps, delta)
    assert rows(fused) == reference_vote(maps, delta)
    # report is consistent with the output
    assert sum(rep.kept.values()) == len(fused)
    for a in ids:
        assert rep.kept[a] + rep.dropped[a] == len(maps[a])
    assert rep.contested_voxels <= rep.voxels
    assert sum(rep.won_voxels.values()) == rep.contested_voxels
    # provenance points at identical input rows (never invents Gaussians)
    src = [rows(maps[rep.agents[k]])[j] for k, j in zip(rep.source_agent, rep.source_row)]
    assert src == rows(fused)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ids=agent_ids, seed=st.integers(0, 2**32 - 1), perm_seed=st.integers(0, 2**16))
def test_order_independent_and_never_invents(ids, seed, perm_seed):
    rng = np.random.default_rng(seed)
    maps = {a: make(rng, int(rng.integers(0, 30)), grid=0.1) for a in ids}
    fused, _ = voxel_vote(maps)
    order = np.random.default_rng(perm_seed).permutation(len(ids))
    shuffled = {ids[i]: maps[ids[i]] for i in order}
    fused2, _ = voxel_vote(shuffled)
    assert fused.equals(fused2)  # identical, hence also the same multiset
    all_in = Counter(r for g in maps.values() for r in rows(g))
    out = Counter(rows(fused))
    assert not out - all_in  # every output row is an input row (with multiplicity)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 60))
def test_single_agent_is_identity_and_idempotent(seed, n):
    g = make(np.random.default_rng(seed), n)
    fused, rep = voxel_vote({"only": g})
    assert fused.equals(g) and rep.contested_voxels == 0 and rep.dropped == {"only": 0}
    again, _ = voxel_vote({"only": fused})
    assert again.equals(fused)


def test_single_contributor_voxels_carry_over_and_winner_rule():
    def one(means, kappa, tag):
        n = len(means)
        return GaussianArrays(
            means=np.asarray(means, np.float32), quats=np.tile([1, 0, 0, 0], (n, 1)),
            log_scales=np.full((n, 3), -4.0), opacity_logits=np.full(n, float(tag)),
            colors=np.zeros((n, 3)), kappa=np.asarray(kappa), active=np.ones(n, bool))
    # voxel (0,0,0): a has κ 5+0, b has κ 3+1+1 → tie on κ, b has more Gaussians → b wins
    # voxel (1,0,0): a κ 9 vs b κ 2 → a wins
    # voxel (2,0,0): a κ 1 vs b κ 1, one Gaussian each → tie → "a" (smallest id) wins
    # voxel (5,5,5): only a; voxel (-1,0,0): only b → carried over
    a = one([[0.01, 0.02, 0.03], [0.05, 0.05, 0.05], [0.15, 0.0, 0.0], [0.25, 0, 0],
             [0.55, 0.55, 0.55]], [5, 0, 9, 1, 0], 1)
    b = one([[0.02, 0.02, 0.02], [0.09, 0.09, 0.09], [0.03, 0.01, 0.0], [0.11, 0.0, 0.0],
             [0.21, 0, 0], [-0.05, 0, 0]], [3, 1, 1, 2, 1, 0], 2)
    fused, rep = voxel_vote({"b": b, "a": a}, 0.1)
    from_a = np.flatnonzero(rep.source_agent == rep.agents.index("a"))
    from_b = np.flatnonzero(rep.source_agent == rep.agents.index("b"))
    assert rep.agents == ("a", "b")
    assert sorted(rep.source_row[from_a].tolist()) == [2, 3, 4]
    assert sorted(rep.source_row[from_b].tolist()) == [0, 1, 2, 5]
    assert rep.contested_voxels == 3 and rep.voxels == 5
    assert rep.won_voxels == {"a": 2, "b": 1}
    assert rep.kept == {"a": 3, "b": 4} and rep.dropped == {"a": 2, "b": 2}
    assert np.all(fused.opacity_logits[from_a] == 1) and np.all(fused.opacity_logits[from_b] == 2)


def test_concat_baseline_and_input_types():
    rng = np.random.default_rng(0)
    a, b = make(rng, 7), make(rng, 5)
    c = concat({"z": b, "a": a})
    assert len(c) == 12 and rows(c) == rows(a) + rows(b)
    fused_t, _ = voxel_vote({"a": a.to_gaussian_map(), "b": {k: getattr(b, k) for k in FIELDS}})
    fused_n, _ = voxel_vote({"a": a, "b": b})
    assert fused_t.equals(fused_n)
    empty, rep = voxel_vote({"a": GaussianArrays.empty(), "b": GaussianArrays.empty()})
    assert len(empty) == 0 and rep.voxels == 0


def test_invalid_inputs():
    g = make(np.random.default_rng(1), 4)
    with pytest.raises(ValueError):
        voxel_vote({"a": g}, 0.0)
    with pytest.raises(ValueError):
        voxel_vote({"a": g}, float("nan"))
    bad = make(np.random.default_rng(1), 4)
    bad.kappa[0] = -1
    with pytest.raises(ValueError):
        voxel_vote({"a": bad})
    nan = make(np.random.default_rng(1), 4)
    nan.means[0, 0] = np.nan
    with pytest.raises(ValueError):
        voxel_vote({"a": nan})
    huge = make(np.random.default_rng(1), 4)
    huge.kappa[:] = 2**62
    with pytest.raises(ValueError):
        voxel_vote({"a": huge, "b": huge})
    with pytest.raises(TypeError):
        voxel_vote([g])  # type: ignore[arg-type]


def test_huge_extent_uses_the_fallback_path_and_agrees_with_reference():
    rng = np.random.default_rng(2)
    maps = {a: make(rng, 30, grid=0.1) for a in ("p", "q", "r")}
    far = make(rng, 3)
    far.means[:] = [[1e5, -1e5, 3e4], [1e5 + 0.01, -1e5, 3e4], [-2e5, 5e4, -1e5]]
    maps["q"] = GaussianArrays.concat([maps["q"], far])
    maps["p"] = GaussianArrays.concat([maps["p"], far])
    fused, rep = voxel_vote(maps, 0.01)  # spans need > 63 bits when packed
    assert rows(fused) == reference_vote(maps, 0.01)
