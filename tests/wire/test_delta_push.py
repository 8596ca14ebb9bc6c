"""Stable Gaussian ids through density control, and delta pushes planned against a mirror of the
server's subset (library level, no gRPC)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests._fuzz import random_arrays
from gausslite.gaussians import GaussianMap
from gausslite.mapping.config import LearningRates
from gausslite.mapping.model import GaussianModel
from gausslite.wire import (
    DeltaMismatch,
    GaussianArrays,
    QuantConfig,
    apply_delta,
    assemble,
    encode_delta,
)
from gausslite.wire.delta import PushPlanner, changed_rows, kappa_shift_of


def _map(n: int, seed: int = 0) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    return GaussianMap.from_points(torch.rand(n, 3, generator=g), torch.rand(n, 3, generator=g),
                                   torch.full((n,), 0.01), opacity=0.5)


def test_ids_survive_clone_split_prune_and_budget_replacement():
    model = GaussianModel(LearningRates())
    model.set_map(_map(6), torch.full((6,), -1, dtype=torch.int64))
    assert model.ids.tolist() == [0, 1, 2, 3, 4, 5]
    gmap = model.to_map()
    clone = torch.tensor([False, True, False, False, False, False])
    split = torch.tensor([False, False, False, True, False, False])
    dens, parent = gmap.densify(clone, split, n_split=2)
    model.set_map(dens, parent)
    # rows: kept originals 0,1,2,4,5 | clone of 1 | two daughters of 3
    assert parent.tolist() == [0, 1, 2, 4, 5, 1, 3, 3]
    assert model.ids.tolist() == [0, 1, 2, 4, 5, 6, 3, 7]  # clone fresh, first daughter keeps 3
    keep = torch.tensor([True, False, True, True, True, True, True, True])  # prune id 1
    model.set_map(model.to_map().prune(keep), torch.nonzero(keep).squeeze(1))
    assert model.ids.tolist() == [0, 2, 4, 5, 6, 3, 7]
    # budget replacement: new seeds enter (parent -1) and replace the lowest-scoring rows
    cur = model.to_map()
    merged = cur.append(_map(3, 1))
    parent = torch.cat([torch.arange(len(cur)), torch.full((3,), -1)])
    score = torch.cat([torch.arange(len(cur), dtype=torch.float32), torch.full((3,), 99.0)])
    capped, kept = merged.cap(len(cur), score=score)
    model.set_map(capped, parent[kept])
    assert model.ids.tolist() == [5, 6, 3, 7, 8, 9, 10]  # ids 0, 2, 4 replaced; fresh 8..10
    # ids are never reused
    assert len(set(model.ids.tolist())) == len(model)
    with pytest.raises(ValueError):
        model.set_map(model.to_map(), torch.full((len(model),), 50, dtype=torch.int64))


def _arrays(n: int, seed: int = 0) -> GaussianArrays:
    return random_arrays(n, seed, extent=1.0)


def test_delta_push_rebuilds_the_server_subset_exactly():
    planner = PushPlanner("a", chunk_gaussians=64)
    ids = np.arange(300)
    cur = _arrays(300)
    p1 = planner.plan(ids, cur, 1)
    assert not p1.is_delta and p1.n_records == 300
    server, _ = assemble(p1.chunks)
    assert server.equals(p1.subset)
    planner.acknowledge(p1)
    # mutate: 10 rows move 2 cm, 5 rows move far below the quantisation step, 20 removed, 40 new
    nxt = GaussianArrays(**{k: np.array(getattr(cur, k), copy=True) for k in GaussianArrays.FIELDS})
    nxt.means[:10] += 0.02
    nxt.means[10:15] += 1e-6
    keep = np.ones(300, bool)
    keep[100:120] = False
    nxt = GaussianArrays.concat([nxt.take(keep), _arrays(40, 7)])
    nids = np.concatenate([ids[keep], 1000 + np.arange(40)])
    perm = np.random.default_rng(3).permutation(len(nids))  # the agent's row order does not matter
    p2 = planner.plan(nids[perm], nxt.take(perm), 2, measure_full=False)
    assert p2.is_delta and p2.base_version == 1
    assert p2.n_records == 10 + 40 and p2.n_removed == 20
    # the server applies the delta to its stored base: identical to the agent's mirror
    recs, meta = assemble(p2.chunks)
    assert meta.delta and meta.base_version == 1 and meta.base_count == 300
    from gausslite.wire import SubsetAssembler

    asm = SubsetAssembler()
    for c in p2.chunks:
        asm.add(c)
    t, rm = asm.delta_parts()
    rebuilt = apply_delta(server, recs, t, rm, meta.base_count)
    assert rebuilt.equals(p2.subset)
    # every id maps to a row whose values are within the codec's error of the current values
    row_of = {int(i): r for r, i in enumerate(p2.ids)}
    assert sorted(row_of) == sorted(nids.tolist())
    order = np.array([row_of[int(i)] for i in nids])
    err = np.abs(rebuilt.means[order] - nxt.means).max()
    assert err <= 1.5 * QuantConfig().mean_step  # unchanged rows: within a step; changed: re-sent
    assert p2.nbytes < p1.nbytes / 2
    # a lost base: the planner forgets and the next plan is a full upload
    planner.acknowledge(p2)
    planner.forget()
    assert not planner.plan(nids, nxt, 3).is_delta


def test_changed_rows_rule_and_delta_validation():
    a = _arrays(50)
    b = GaussianArrays(**{k: np.array(getattr(a, k), copy=True) for k in GaussianArrays.FIELDS})
    assert not changed_rows(a, b).any()
    b.means[3, 0] += 1.5 * QuantConfig().mean_step  # beyond one step
    b.kappa[4] = a.kappa[4] * 2 + 2
    b.active[5] = ~b.active[5]
    b.colors[6] += 0.05
    b.means[7, 1] += 0.1 * QuantConfig().mean_step  # within quantisation: not re-sent
    assert np.nonzero(changed_rows(b, a))[0].tolist() == [3, 4, 5, 6]
    base = _arrays(10)
    (c,) = encode_delta(_arrays(2, 1), [3, 10], [0], "a", 2, 1, 10)
    recs, meta = assemble([c])
    with pytest.raises(DeltaMismatch):  # wrong base size
        apply_delta(_arrays(9), recs, np.array([3, 10]), np.array([0]), 10)
    with pytest.raises(DeltaMismatch):  # new rows not consecutive from base_count
        apply_delta(base, recs, np.array([3, 11]), np.array([0]), 10)
    with pytest.raises(DeltaMismatch):  # a replaced row is also removed
        apply_delta(base, recs, np.array([3, 10]), np.array([3]), 10)
    out = apply_delta(base, recs, np.array([3, 10]), np.array([0]), 10)
    assert len(out) == 10 and out.equals(GaussianArrays.concat([
        base.take(np.r_[1, 2]), recs.take([0]), base.take(np.r_[4:10]), recs.take([1])]))
    for bad in (dict(targets=[3, 3]), dict(removed=[3]), dict(removed=[10]), dict(base_version=2)):
        kw = dict(records=_arrays(2, 1), targets=[3, 10], removed=[0], agent_id="a", map_version=2,
                  base_version=1, base_count=10)
        kw.update(bad)
        with pytest.raises(ValueError):
            encode_delta(**kw)


def test_kappa_growth_travels_as_one_shift_not_as_rows():
    """Between pushes every active row's κ grows by the ROI-phase iterations run (paper III-D.1): the
    delta carries that growth as its κ shift (no record), inactive rows keep their κ, rows that grew
    otherwise beyond ``kappa_rel`` are re-sent, and the rebuilt copy holds the agent's κ on every row up
    to that tolerance."""
    planner = PushPlanner("a", chunk_gaussians=64)
    ids = np.arange(200)
    cur = _arrays(200)
    cur.kappa[:] = np.random.default_rng(1).integers(100, 200, 200)
    cur.active[:] = True
    cur.active[190:] = False  # context rows of the ROI render: their κ does not grow
    p1 = planner.plan(ids, cur, 1)
    planner.acknowledge(p1)
    nxt = GaussianArrays(**{k: np.array(getattr(cur, k), copy=True) for k in GaussianArrays.FIELDS})
    nxt.kappa[nxt.active] += 125  # 5 frames × 25 ROI-phase iterations
    nxt.kappa[:6] += 200  # six rows grew far more (e.g. active in extra iterations): beyond kappa_rel
    nxt.kappa[6:9] += 3  # within kappa_rel of base + shift: not re-sent
    p2 = planner.plan(ids, nxt, 2, measure_full=False)
    assert p2.is_delta and p2.n_records == 6 and planner.last_stats["kappa_shift"] == 125
    recs, meta = assemble(p2.chunks)
    assert meta.kappa_shift == 125
    by_id = dict(zip(p2.ids.tolist(), p2.subset.kappa.tolist()))
    got = np.array([by_id[i] for i in ids.tolist()])
    assert np.array_equal(got[:6], nxt.kappa[:6]) and np.array_equal(got[9:], nxt.kappa[9:])
    assert np.array_equal(got[6:9], nxt.kappa[6:9] - 3)
    # without the shift this push would have re-sent every row (κ +125 on 100..200 is > 25 %)
    assert changed_rows(nxt, p1.subset).all()


def test_kappa_shift_of_rule():
    assert kappa_shift_of(np.array([5, 7, 7, 9]), np.array([0, 2, 2, 0])) == 5  # growths 5,5,5,9
    assert kappa_shift_of(np.array([3, 3]), np.array([3, 4])) == 0  # nothing grew
    assert kappa_shift_of(np.zeros(0, np.int64), np.zeros(0, np.int64)) == 0
    assert kappa_shift_of(np.array([10**6]), np.array([0])) == 0xFFFF  # clipped to the u16 field
    with pytest.raises(ValueError, match="kappa_shift"):
        encode_delta(_arrays(1), [0], [], "a", 2, 1, 1, kappa_shift=1 << 16)
    with pytest.raises(DeltaMismatch):
        apply_delta(_arrays(1), _arrays(0), np.zeros(0, np.int64), np.zeros(0, np.int64), 1, kappa_shift=-1)
