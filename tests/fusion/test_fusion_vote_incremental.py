"""Incremental κ-weighted voxel vote (paper Sec. III-E): after any sequence of agent
updates and removals, :class:`IncrementalVote` gives exactly what a full :func:`voxel_vote` over the
same subsets gives (fused rows, canonical order, provenance and report)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gausslite.fusion import IncrementalVote, VoxelRangeError, voxel_vote
from gausslite.wire import GaussianArrays
from tests.fusion.test_fusion_vote import make


def assert_same(inc: IncrementalVote, maps: dict, delta: float) -> None:
    fused, rep = inc.result()
    full, ref = voxel_vote(maps, delta)
    assert fused.equals(full)
    assert rep.agents == ref.agents and rep.kept == ref.kept and rep.dropped == ref.dropped
    assert rep.voxels == ref.voxels and rep.contested_voxels == ref.contested_voxels
    assert rep.won_voxels == ref.won_voxels and rep.voxel_size == ref.voxel_size
    assert np.array_equal(rep.source_agent, ref.source_agent) and rep.source_agent.dtype == ref.source_agent.dtype
    assert np.array_equal(rep.source_row, ref.source_row)


def moved(rng: np.random.Generator, g: GaussianArrays, frac: float) -> GaussianArrays:
    """An updated subset: some rows moved / re-weighted, some dropped, some added (a delta)."""
    n = len(g)
    keep = rng.random(n) >= frac * 0.5
    out = g.take(keep)
    sel = rng.random(len(out)) < frac
    out.means[sel] += rng.normal(0, 0.08, (int(sel.sum()), 3)).astype(np.float32)
    out.kappa[sel] = rng.integers(0, 6, int(sel.sum()))
    extra = make(rng, int(rng.integers(0, 8)), grid=0.1)
    return GaussianArrays.concat([out, extra])


def replay(inc: IncrementalVote, rng: np.random.Generator, ops, ids: list, new):
    """Apply hypothesis ``ops`` ((agent index, "update"/"remove", move fraction) triples) to ``inc`` and to a
    dict of the current maps; yields that dict after every step. ``new(rng)`` makes an agent's first map."""
    maps: dict[str, GaussianArrays] = {}
    for who, op, frac in ops:
        agent = ids[who]
        if op == "remove":
            maps.pop(agent, None)
            inc.remove(agent)
        else:
            g = moved(rng, maps[agent], frac) if agent in maps else new(rng)
            maps[agent] = g
            inc.update(agent, g)
        yield maps


ops = st.lists(st.tuples(st.integers(0, 5), st.sampled_from(["update", "update", "update", "remove"]),
                         st.floats(0.0, 1.0)), min_size=1, max_size=12)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), ops=ops, delta=st.sampled_from([0.05, 0.1, 0.3]),
       grid=st.sampled_from([None, 0.1]), kappa_max=st.sampled_from([0, 1, 5]))
def test_incremental_equals_full_vote_after_every_step(seed, ops, delta, grid, kappa_max):
    rng = np.random.default_rng(seed)
    inc = IncrementalVote(delta)
    for maps in replay(inc, rng, ops, ["a", "b", "ab", "c0", "x", "zz"],
                       lambda r: make(r, int(r.integers(0, 40)), kappa_max=kappa_max, grid=grid)):
        assert inc.agents == tuple(sorted(maps))
        assert_same(inc, maps, delta)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_agents=st.integers(1, 5))
def test_sync_loads_only_changed_agents(seed, n_agents):
    rng = np.random.default_rng(seed)
    maps = {f"r{i}": make(rng, int(rng.integers(1, 30)), grid=0.1) for i in range(n_agents)}
    versions = {a: 1 for a in maps}
    inc = IncrementalVote(0.1)
    loaded = []

    def load(a):
        loaded.append(a)
        return maps[a]

    assert inc.sync(versions, load) == sorted(maps) and sorted(loaded) == sorted(maps)
    assert_same(inc, maps, 0.1)
    loaded.clear()
    assert inc.sync(versions, load) == [] and loaded == []  # nothing changed: nothing re-voted
    maps["r0"] = moved(rng, maps["r0"], 0.5)
    versions["r0"] = 2
    assert inc.sync(versions, load) == ["r0"] and loaded == ["r0"]
    assert inc.revision("r0") == 2
    assert_same(inc, maps, 0.1)
    gone = sorted(maps)[-1]
    del maps[gone], versions[gone]
    assert inc.sync(versions, load) == [gone]
    assert_same(inc, maps, 0.1)


def test_update_touches_only_its_voxels():
    rng = np.random.default_rng(3)
    # 8 agents in disjoint 1 m cubes plus one shared cube; updating one agent re-votes its voxels only
    maps = {}
    for i in range(8):
        g = make(rng, 2000, extent=0.5)
        g.means[:] += np.float32(2.0 * i)
        maps[f"r{i}"] = g
    inc = IncrementalVote(0.1)
    for a, g in maps.items():
        inc.update(a, g)
    assert_same(inc, maps, 0.1)
    g = maps["r3"].take(slice(0, 500))
    n_vox = len(np.unique(np.floor(maps["r3"].means.astype(np.float64) / 0.1), axis=0))
    revoted = inc.update("r3", g)
    maps["r3"] = g
    assert revoted == n_vox  # old ∪ new voxels of r3 (new ⊆ old here), nothing of the others
    assert_same(inc, maps, 0.1)


def test_errors_leave_state_unchanged():
    rng = np.random.default_rng(1)
    g = make(rng, 50, grid=0.1)
    inc = IncrementalVote(0.1)
    inc.update("a", g)
    bad = g.take(np.arange(len(g)))  # a copy
    bad.kappa[0] = -1
    with pytest.raises(ValueError, match="kappa"):
        inc.update("a", bad)
    far = g.take(np.arange(len(g)))  # a copy
    far.means[0, 0] = 1e6  # 10^7 voxels of 0.1 m from the origin
    with pytest.raises(VoxelRangeError):
        inc.update("b", far)
    nan = g.take(np.arange(len(g)))  # a copy
    nan.means[1, 2] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        inc.update("b", nan)
    with pytest.raises(TypeError):
        inc.update(3, g)
    with pytest.raises(ValueError):
        IncrementalVote(0.0)
    assert inc.agents == ("a",)
    assert_same(inc, {"a": g}, 0.1)
    empty, rep = IncrementalVote(0.1).result()
    assert len(empty) == 0 and rep.voxels == 0 and rep.agents == ()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), rounds=st.integers(1, 4), batch=st.integers(1, 4),
       grid=st.sampled_from([None, 0.1]))
def test_batched_updates_equal_full_vote(seed, rounds, batch, grid):
    """update_many (one re-vote of the union of touched voxels, what a Fuse after several agents'
    pushes does) equals the full vote, also across site-scale offsets (far-apart groups)."""
    rng = np.random.default_rng(seed)
    ids = [f"r{i}" for i in range(6)]
    maps: dict[str, GaussianArrays] = {}
    inc = IncrementalVote(0.1)
    for _ in range(rounds):
        picked = list(rng.choice(ids, size=batch, replace=False))
        upd = {}
        for a in picked:
            g = moved(rng, maps[a], 0.5) if a in maps else make(rng, int(rng.integers(0, 40)), grid=grid)
            if rng.random() < 0.3:
                g.means[:, 0] += np.float32(25.0)  # another room of the site
            upd[a] = (g, len(maps))
            maps[a] = g
        inc.update_many(upd)
        assert_same(inc, maps, 0.1)
