"""The fusion side's upload rules without gRPC (gausslite.fusion.uploads): superseded versions, a delta's base,
the rebuild of a full subset from a delta and its base, and the size limit of the rebuilt subset; every refusal
discards the delta and raises its typed error."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np
import pytest

from gausslite.errors import CapacityExceeded, PreconditionFailed
from gausslite.fusion.uploads import (MissingDeltaBase, RebuiltTooLarge, SupersededVersion, check_delta_base,
                                      check_not_superseded, complete_delta_upload, rebuild_subset)
from gausslite.wire import (LOSSLESS, DeltaMismatch, GaussianArrays, SubsetAssembler, WireLimits, apply_delta,
                            assemble, encode_delta, encode_subset, peek_header)

AGENT = "robot"
LIMITS = WireLimits()


def _arrays(n: int, seed: int) -> GaussianArrays:
    r = np.random.default_rng(seed)
    return GaussianArrays(means=r.uniform(0, 1, (n, 3)).astype(np.float32),
                          quats=r.normal(size=(n, 4)).astype(np.float32),
                          log_scales=r.uniform(-5, -3, (n, 3)).astype(np.float32),
                          opacity_logits=r.normal(size=n).astype(np.float32),
                          colors=r.uniform(0, 1, (n, 3)).astype(np.float32), kappa=r.integers(1, 100, n),
                          active=r.random(n) < 0.7)


@dataclass
class _Upload:
    n_chunks: int
    chunks: Dict[int, bytes] = field(default_factory=dict)
    complete: bool = False

    @property
    def missing(self) -> List[int]:
        return [i for i in range(self.n_chunks) if i not in self.chunks]


class FakeStore:
    """In-memory :class:`gausslite.fusion.uploads.UploadStore`: uploads by (agent, version), the latest complete
    version per agent, and a log of the changing calls."""

    def __init__(self) -> None:
        self.uploads: Dict[Tuple[str, int], _Upload] = {}
        self.latest: Dict[str, int] = {}
        self.calls: List[tuple] = []

    def put(self, agent: str, version: int, chunks: List[bytes], n_chunks: Optional[int] = None,
            complete: bool = False) -> None:
        up = _Upload(len(chunks) if n_chunks is None else n_chunks, dict(enumerate(chunks)), complete)
        self.uploads[(agent, version)] = up
        if complete and version > self.latest.get(agent, -1):
            self.latest[agent] = version

    def upload(self, agent_id: str, map_version: int) -> Optional[_Upload]:
        return self.uploads.get((agent_id, map_version))

    def latest_version(self, agent_id: str) -> Optional[int]:
        return self.latest.get(agent_id)

    def chunk_data(self, agent_id: str, map_version: int) -> List[bytes]:
        up = self.uploads[(agent_id, map_version)]
        return [up.chunks[i] for i in sorted(up.chunks)]

    def discard_upload(self, agent_id: str, map_version: int) -> None:
        self.calls.append(("discard", agent_id, map_version))
        up = self.uploads.get((agent_id, map_version))
        if up is not None and not up.complete:
            del self.uploads[(agent_id, map_version)]

    def complete_rebuilt(self, agent_id: str, map_version: int, chunks, total_count: int, lossless: bool) -> None:
        self.calls.append(("complete_rebuilt", agent_id, map_version, len(chunks), total_count, lossless))
        assert sum(n for _, _, n in chunks) == total_count
        self.put(agent_id, map_version, [c for c, _, _ in chunks], complete=True)

    def load(self, agent_id: str, version: int) -> GaussianArrays:
        return assemble(self.chunk_data(agent_id, version), LIMITS)[0]


BASE_N = 40


def _with_base(version: int = 3) -> Tuple[FakeStore, GaussianArrays]:
    """A store holding the agent's complete base ``version`` of BASE_N rows (lossless, as the server stores it)."""
    store = FakeStore()
    chunks = encode_subset(_arrays(BASE_N, 1), AGENT, version, quant=LOSSLESS, chunk_gaussians=16)
    store.put(AGENT, version, chunks, complete=True)
    return store, store.load(AGENT, version)


def _delta(version: int = 4, base_version: int = 3, base_count: int = BASE_N, removed=(0, 5, 7),
           kappa_shift: int = 2) -> List[bytes]:
    """Rows 2 and 9 replaced, two new rows, ``removed`` rows removed; two chunks."""
    return encode_delta(_arrays(4, 2), [2, 9, base_count, base_count + 1], list(removed), AGENT, version,
                        base_version, base_count, quant=LOSSLESS, chunk_gaussians=2, kappa_shift=kappa_shift)


def _parts(chunks: List[bytes]):
    asm = SubsetAssembler(LIMITS)
    for c in chunks:
        asm.add(c)
    records, meta = asm.result()
    targets, removed = asm.delta_parts()
    return records, targets, removed, meta


def _assert_equal(a: GaussianArrays, b: GaussianArrays) -> None:
    assert len(a) == len(b)
    for k in GaussianArrays.FIELDS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)


# ---------------------------------------------------------------------------------------------- version order


def test_superseded_version_is_refused():
    check_not_superseded(AGENT, 0, None)  # the first upload
    check_not_superseded(AGENT, 5, 5)  # resuming the latest
    check_not_superseded(AGENT, 6, 5)  # a newer one
    with pytest.raises(SupersededVersion) as e:
        check_not_superseded(AGENT, 4, 5)
    assert str(e.value) == "map_version 4 of 'robot' is superseded by complete version 5"
    assert isinstance(e.value, PreconditionFailed)


# ---------------------------------------------------------------------------------------------- the delta's base


def test_delta_base_held_complete_passes_without_discarding():
    store, _ = _with_base()
    store.put(AGENT, 4, _delta()[:1], n_chunks=2)
    check_delta_base(store, AGENT, 4, 3)
    assert store.calls == [] and store.upload(AGENT, 4) is not None


@pytest.mark.parametrize("held", ["absent", "incomplete"])
def test_missing_delta_base_discards_the_delta(held):
    store, _ = _with_base(version=3)
    if held == "incomplete":  # version 2 announced, one of its two chunks stored
        store.put(AGENT, 2, encode_subset(_arrays(8, 3), AGENT, 2, chunk_gaussians=4)[:1], n_chunks=2)
    store.put(AGENT, 4, _delta(base_version=2)[:1], n_chunks=2)
    with pytest.raises(MissingDeltaBase) as e:
        check_delta_base(store, AGENT, 4, 2)
    assert isinstance(e.value, PreconditionFailed)
    assert str(e.value) == ("delta v4 of 'robot' needs base version 2, which this server does not hold "
                            "(latest complete: 3); upload the full subset")
    assert store.calls == [("discard", AGENT, 4)] and store.upload(AGENT, 4) is None


def test_missing_delta_base_without_any_complete_version():
    store = FakeStore()
    store.put(AGENT, 1, _delta(version=1, base_version=0)[:1], n_chunks=2)
    with pytest.raises(MissingDeltaBase, match=r"\(latest complete: none\)"):
        check_delta_base(store, AGENT, 1, 0)
    assert store.upload(AGENT, 1) is None


# ---------------------------------------------------------------------------------------------- the rebuild


def test_rebuild_subset_applies_the_delta():
    _, base = _with_base()
    records, targets, removed, meta = _parts(_delta())
    full = rebuild_subset(base, records, targets, removed, meta, LIMITS.max_total_gaussians)
    _assert_equal(full, apply_delta(base, records, targets, removed, meta.base_count, meta.kappa_shift))
    assert len(full) == BASE_N - 3 + 2
    kept = np.setdiff1d(np.arange(BASE_N), [0, 2, 5, 7, 9])  # neither removed nor replaced: κ + shift when active
    rows = np.setdiff1d(np.arange(BASE_N), [0, 5, 7])
    at = np.searchsorted(rows, kept)
    np.testing.assert_array_equal(full.kappa[at], base.kappa[kept] + 2 * base.active[kept])


def test_rebuild_subset_refuses_a_delta_that_does_not_fit_its_base():
    _, base = _with_base()
    records, targets, removed, meta = _parts(_delta(base_count=BASE_N + 1))
    with pytest.raises(DeltaMismatch) as e:
        rebuild_subset(base, records, targets, removed, meta, LIMITS.max_total_gaussians)
    assert str(e.value) == "delta v4 of 'robot': delta declares a 41-row base, the stored base has 40"


def test_rebuild_subset_refuses_a_subset_above_the_limit():
    _, base = _with_base()
    records, targets, removed, meta = _parts(_delta())
    assert len(rebuild_subset(base, records, targets, removed, meta, BASE_N - 1)) == BASE_N - 1  # at the limit
    with pytest.raises(RebuiltTooLarge) as e:
        rebuild_subset(base, records, targets, removed, meta, BASE_N - 2)
    assert isinstance(e.value, CapacityExceeded)
    assert str(e.value) == ("delta v4 of 'robot' rebuilds a subset of 39 Gaussians, above the server's limit of 38")


# ---------------------------------------------------------------------------------------------- a whole delta upload


def test_complete_delta_upload_stores_the_rebuilt_subset_once():
    store, base = _with_base()
    delta = _delta()
    store.put(AGENT, 4, delta)
    done = complete_delta_upload(store, AGENT, 4, LIMITS, store.load)
    records, targets, removed, meta = _parts(delta)
    want = apply_delta(base, records, targets, removed, meta.base_count, meta.kappa_shift)
    _assert_equal(done.subset, want)
    assert (done.meta.base_version, done.meta.kappa_shift, done.records, done.removed) == (3, 2, 4, 3)
    assert store.calls == [("complete_rebuilt", AGENT, 4, 1, len(want), True)]
    stored = store.chunk_data(AGENT, 4)
    assert all(peek_header(c).lossless and not peek_header(c).delta for c in stored)
    _assert_equal(store.load(AGENT, 4), want)
    assert store.latest_version(AGENT) == 4
    assert complete_delta_upload(store, AGENT, 4, LIMITS, store.load) is None  # complete now: nothing to redo
    assert len(store.calls) == 1


def test_complete_delta_upload_waits_for_every_chunk_and_ignores_full_uploads():
    store, _ = _with_base()
    assert complete_delta_upload(store, AGENT, 4, LIMITS, store.load) is None  # never announced
    delta = _delta()
    assert len(delta) == 2
    store.put(AGENT, 4, delta[:1], n_chunks=2)
    assert complete_delta_upload(store, AGENT, 4, LIMITS, store.load) is None  # a chunk missing
    store.put(AGENT, 5, encode_subset(_arrays(10, 4), AGENT, 5, chunk_gaussians=4))  # a full version, all stored
    assert complete_delta_upload(store, AGENT, 5, LIMITS, store.load) is None
    assert store.calls == [] and not store.upload(AGENT, 5).complete


@pytest.mark.parametrize("case, error", [("no base", MissingDeltaBase), ("mismatch", DeltaMismatch),
                                         ("too large", RebuiltTooLarge)])
def test_complete_delta_upload_discards_a_refused_delta(case, error):
    store, _ = _with_base()
    delta = {"no base": _delta(version=5, base_version=4), "mismatch": _delta(version=5, base_count=BASE_N - 1),
             "too large": _delta(version=5, removed=())}[case]  # too large: BASE_N + 2 rows
    store.put(AGENT, 5, delta)
    # the base itself is within the limit (a larger base count would be refused when the chunks are read)
    limits = WireLimits(max_total_gaussians=BASE_N) if case == "too large" else LIMITS
    with pytest.raises(error):
        complete_delta_upload(store, AGENT, 5, limits, store.load)
    assert store.calls == [("discard", AGENT, 5)] and store.upload(AGENT, 5) is None
    assert store.latest_version(AGENT) == 3 and store.upload(AGENT, 3).complete
