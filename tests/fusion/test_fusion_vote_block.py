"""Neighbourhood contest of the voxel vote (``contest_radius`` r > 0, gausslite.fusion.vote): a brute-force
reference of the documented rule, incremental updates equal to a full vote, and argument checks."""

from __future__ import annotations

import itertools
import math
from collections import defaultdict

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gausslite.fusion import IncrementalVote, voxel_vote
from gausslite.wire import GaussianArrays
from tests.fusion.test_fusion_vote import make, reference_vote, rows
from tests.fusion.test_fusion_vote_incremental import replay


def reference_block_vote(maps: dict[str, GaussianArrays], delta: float, r: int):
    """Brute force: every occupied voxel is won by the agent with the largest κ sum (then count, then
    smallest id) over its (2r+1)³ block; only the winner's rows in the voxel survive.
    Returns (rows in canonical order, contested voxels, won voxels per agent)."""
    per_voxel: dict[tuple, dict[str, list[int]]] = defaultdict(lambda: defaultdict(list))
    for a, g in maps.items():
        for i in range(len(g)):
            per_voxel[tuple(math.floor(float(x) / delta) for x in g.means[i].astype(np.float64))][a].append(i)
    keep = {a: set() for a in maps}
    contested, won = 0, defaultdict(int)
    offs = list(itertools.product(range(-r, r + 1), repeat=3))
    for v, here in per_voxel.items():
        ksum, cnt = defaultdict(int), defaultdict(int)
        for o in offs:
            for a, idx in per_voxel.get((v[0] + o[0], v[1] + o[1], v[2] + o[2]), {}).items():
                ksum[a] += sum(int(maps[a].kappa[i]) for i in idx)
                cnt[a] += len(idx)
        winner = min(ksum, key=lambda a: (-ksum[a], -cnt[a], a))
        if len(ksum) >= 2:
            contested += 1
            won[winner] += 1
        keep[winner].update(here.get(winner, []))
    out = []
    for a in sorted(maps):
        rr = rows(maps[a])
        out += [rr[i] for i in sorted(keep[a])]
    return out, contested, dict(won)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), n_agents=st.integers(1, 4), n_max=st.integers(0, 40),
       delta=st.sampled_from([0.05, 0.1, 0.3]), grid=st.sampled_from([None, 0.1]),
       kappa_max=st.sampled_from([0, 1, 5]), r=st.sampled_from([1, 2]))
def test_block_vote_matches_brute_force_reference(seed, n_agents, n_max, delta, grid, kappa_max, r):
    rng = np.random.default_rng(seed)
    maps = {a: make(rng, int(rng.integers(0, n_max + 1)), kappa_max=kappa_max, grid=grid)
            for a in ["a", "b", "ab", "z"][:n_agents]}
    fused, rep = voxel_vote(maps, delta, contest_radius=r)
    ref_rows, contested, won = reference_block_vote(maps, delta, r)
    assert rows(fused) == ref_rows
    assert rep.contested_voxels == contested
    assert {a: k for a, k in rep.won_voxels.items() if k} == won
    assert sum(rep.kept.values()) == len(fused)
    assert all(rep.kept[a] + rep.dropped[a] == len(maps[a]) for a in maps)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), n_agents=st.integers(1, 4), grid=st.sampled_from([None, 0.1]))
def test_radius_zero_through_the_incremental_path_is_the_paper_rule(seed, n_agents, grid):
    rng = np.random.default_rng(seed)
    maps = {a: make(rng, int(rng.integers(0, 40)), grid=grid) for a in ["a", "b", "c", "d"][:n_agents]}
    assert rows(voxel_vote(maps, 0.1, contest_radius=0)[0]) == reference_vote(maps, 0.1)


ops = st.lists(st.tuples(st.integers(0, 3), st.sampled_from(["update", "update", "remove"]),
                         st.floats(0.0, 1.0)), min_size=1, max_size=10)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), ops=ops, delta=st.sampled_from([0.05, 0.1]), r=st.sampled_from([1, 2]))
def test_incremental_block_vote_equals_a_fresh_vote_after_every_step(seed, ops, delta, r):
    rng = np.random.default_rng(seed)
    inc = IncrementalVote(delta, contest_radius=r)
    for maps in replay(inc, rng, ops, ["a", "b", "c0", "x"], lambda g: make(g, int(g.integers(0, 40)), grid=0.1)):
        fused, rep = inc.result()
        ref_rows, contested, won = reference_block_vote(maps, delta, r)
        assert rows(fused) == ref_rows
        assert rep.contested_voxels == contested
        assert {a: k for a, k in rep.won_voxels.items() if k} == won


def test_neighbour_next_to_an_roi_loses_its_voxel_only_with_a_block_contest():
    """Agent a owns a dense, high-κ cluster; b has a few Gaussians in the adjacent voxel (not shared with
    a). The paper's rule keeps them (uncontested voxel); r = 1 hands the voxel to a, which has no
    Gaussian there, so it is emptied."""
    def arr(means, kappa):
        n = len(means)
        return GaussianArrays(means=np.asarray(means, np.float32), quats=np.tile([1, 0, 0, 0], (n, 1)).astype(np.float32),
                              log_scales=np.full((n, 3), -3, np.float32), opacity_logits=np.zeros(n, np.float32),
                              colors=np.full((n, 3), 0.5, np.float32), kappa=np.full(n, kappa, np.int64),
                              active=np.ones(n, bool))
    a = arr([[0.05, 0.05, 0.05]] * 5, 10)
    b = arr([[0.15, 0.05, 0.05], [0.55, 0.05, 0.05]], 3)  # voxel (1,0,0) next to a's; (5,0,0) far away
    f0, r0 = voxel_vote({"a": a, "b": b}, 0.1)
    f1, r1 = voxel_vote({"a": a, "b": b}, 0.1, contest_radius=1)
    assert r0.kept == {"a": 5, "b": 2} and r0.contested_voxels == 0
    assert r1.kept == {"a": 5, "b": 1} and r1.contested_voxels == 2 and r1.won_voxels == {"a": 2, "b": 0}
    assert len(f1) == 6 and np.allclose(f1.means[-1], [0.55, 0.05, 0.05])


@pytest.mark.parametrize("bad", [-1, 9, 1.5, True, "1"])
def test_contest_radius_is_checked(bad):
    g = make(np.random.default_rng(0), 5)
    with pytest.raises(ValueError, match="contest_radius"):
        voxel_vote({"a": g}, 0.1, contest_radius=bad)
    with pytest.raises(ValueError, match="contest_radius"):
        IncrementalVote(0.1, contest_radius=bad)
