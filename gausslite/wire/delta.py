"""Delta pushes: an agent-side mirror of the subset the fusion server holds, and the rule that
decides which Gaussians a push must carry (``docs/sharing.md``; delta records: ``docs/wire-format.md`` §6).

An agent identifies its Gaussians by the stable per-agent ids of
:attr:`gausslite.mapping.model.GaussianModel.ids`.  Ids never travel on the wire: a delta names
rows of the *base* subset (the last version the server acknowledged) by position, and the server
rebuilds the new subset with :func:`gausslite.wire.decode.apply_delta`.  The agent applies the very
same decoded delta to its mirror, so both sides hold bit-identical subsets and the mirror maps
every server row back to an id.

Changed "beyond quantisation": a Gaussian already on the server is compared with the *decoded*
values the server holds, which already differ from the agent's by up to half a code step; it is
re-sent only when some attribute differs by more than ``tolerance`` × one code step (so rows the
optimiser did not move are never re-sent, and a re-sent row moved by at least half a step):

* mean: any axis differs by more than ``mean_step`` (metres);
* log-scales / colours: more than one code step of the base's per-attribute range;
* opacity: more than one code step in opacity space (``1 / (2^bits − 1)``);
* rotation: any component of the sign-canonical unit quaternion differs by more than
  ``5 · (1/√2) / (2^bits − 1)`` (the largest component is reconstructed from the other three and
  carries up to about 4.2× their error);
* κ: relative change above ``kappa_rel`` against the base κ plus the delta's κ shift (κ is lossless
  on the wire, but a re-send for every +1 would re-send every active Gaussian at every push);
* the active flag changed.

κ shift (wire format 3): an agent's κ grows by one per ROI-phase iteration for every active Gaussian
(paper III-D.1), so between two pushes the rows the delta does not carry have all grown by about the
same amount. The planner sends that growth once, as the delta's κ shift: the most common κ growth of
the active rows it keeps (:func:`kappa_shift_of`). The server adds it to every active row the delta
keeps without replacing (inactive rows, which a subset may hold for the ROI render, do not grow), so
its κ, which the voxel vote compares between agents, is as current as the agent's; rows whose κ grew
otherwise are compared against base κ (+ shift when active) by the rule above.

Pure numpy; no gRPC.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from gausslite.core.arrays import GaussianArrays
from gausslite.wire.decode import apply_delta, assemble
from gausslite.wire.encode import encode_delta, encode_subset, spatial_order
from gausslite.wire.format import MAX_KAPPA_SHIFT, QuantConfig

__all__ = ["PlannedPush", "PushPlanner", "change_steps", "changed_rows", "kappa_shift_of"]


def kappa_shift_of(cur_kappa: np.ndarray, base_kappa: np.ndarray) -> int:
    """The κ shift of a delta: the most common growth ``cur − base`` (ties: the smaller) over the rows
    the delta keeps, clipped to ``[0, MAX_KAPPA_SHIFT]``; 0 for no rows or when no row grew.

    Args:
        cur_kappa, base_kappa: (K,) int64 κ of the kept rows, the agent's now / the server's.
    """
    d = np.asarray(cur_kappa, np.int64) - np.asarray(base_kappa, np.int64)
    d = d[d > 0]
    if d.size == 0:
        return 0
    d = np.minimum(d, MAX_KAPPA_SHIFT)
    vals, counts = np.unique(d, return_counts=True)
    return int(vals[np.argmax(counts)])


def _canonical_quats(q: np.ndarray) -> np.ndarray:
    q = q.astype(np.float64)
    n = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(n > 0, q / np.where(n > 0, n, 1.0), np.array([1.0, 0, 0, 0]))
    big = np.take_along_axis(q, np.argmax(np.abs(q), axis=1)[:, None], 1)
    return q * np.where(big < 0, -1.0, 1.0)


def change_steps(cur: GaussianArrays, base: GaussianArrays, quant: QuantConfig = QuantConfig()) -> np.ndarray:
    """(N,) float64: how far each row of ``cur`` moved from the row-aligned ``base``, in code steps of
    the codec: the largest over mean, log-scales, colours, opacity and rotation of the attribute's
    change divided by its code step (rule and steps in the module docstring; κ and the task flag are
    not counted). A row with a value > t is "changed" at tolerance t (:func:`changed_rows`).

    Args:
        cur, base: N row-aligned Gaussians (current values / what the server holds, decoded).
        quant: the codec configuration (lossy; a lossless codec has no code step).

    Raises:
        ValueError: different lengths, or a lossless ``quant``.
    """
    if len(cur) != len(base):
        raise ValueError(f"{len(cur)} current rows vs {len(base)} base rows")
    if quant.lossless:
        raise ValueError("a lossless codec has no code step")
    n = len(cur)
    if n == 0:
        return np.zeros(0)

    def step(x: np.ndarray, bits: int, clamp) -> float:
        lo, hi = np.clip([x.min(), x.max()], *clamp)
        return max(float(hi - lo) / ((1 << bits) - 1), 1e-30)

    sig = lambda x: 1.0 / (1.0 + np.exp(-x.astype(np.float64)))  # noqa: E731
    s = np.abs(cur.means.astype(np.float64) - base.means).max(axis=1) / quant.mean_step
    s = np.maximum(s, np.abs(cur.log_scales - base.log_scales).max(axis=1)
                   / step(base.log_scales, quant.scale_bits, quant.scale_clamp))
    s = np.maximum(s, np.abs(cur.colors - base.colors).max(axis=1)
                   / step(base.colors, quant.color_bits, quant.color_clamp))
    s = np.maximum(s, np.abs(sig(cur.opacity_logits) - sig(base.opacity_logits)) * ((1 << quant.opacity_bits) - 1))
    s = np.maximum(s, np.abs(_canonical_quats(cur.quats) - _canonical_quats(base.quats)).max(axis=1)
                   / (5.0 * (1.0 / math.sqrt(2.0)) / ((1 << quant.quat_bits) - 1)))
    return s


def changed_rows(cur: GaussianArrays, base: GaussianArrays, quant: QuantConfig = QuantConfig(),
                 tolerance: float = 1.0, kappa_rel: float = 0.25, steps: Optional[np.ndarray] = None) -> np.ndarray:
    """(N,) bool: rows of ``cur`` that differ from the row-aligned ``base`` beyond the codec's
    quantisation error (rule in the module docstring; :func:`change_steps` > ``tolerance``, a relative
    κ change above ``kappa_rel``, or a changed task flag).

    Args:
        cur, base: N row-aligned Gaussians (current values / what the server holds, decoded).
        quant: the codec configuration whose error bounds define "changed".
        tolerance: multiplier of the error bounds (>= 0; 0 re-sends any change at all).
        kappa_rel: relative κ change that forces a re-send.
        steps: ``change_steps(cur, base, quant)`` when the caller already has it (lossy codec only), so
            that several tolerances cost one evaluation.

    Raises:
        ValueError: different lengths.
    """
    if len(cur) != len(base):
        raise ValueError(f"{len(cur)} current rows vs {len(base)} base rows")
    n = len(cur)
    if n == 0:
        return np.zeros(0, bool)
    if quant.lossless:
        return np.any([np.any(getattr(cur, k).reshape(n, -1) != getattr(base, k).reshape(n, -1), axis=1)
                       for k in GaussianArrays.FIELDS], axis=0)
    ch = (change_steps(cur, base, quant) if steps is None else steps) > float(tolerance)
    kb = base.kappa.astype(np.float64)
    ch |= np.abs(cur.kappa - kb) > kappa_rel * np.maximum(kb, 1.0)
    ch |= cur.active != base.active
    return ch


@dataclass
class PlannedPush:
    """One planned upload.

    Attributes:
        version: map version of the push.  base_version: the base of a delta (None: full upload).
        chunks: encoded wire chunks.  n_records: Gaussians carried (all of them for a full upload).
        n_removed: base rows the delta removes.  subset: the rebuilt subset as the server will hold
            it (decoded values).  ids: (len(subset),) int64 ids of its rows.
        full_bytes: bytes of the same subset encoded whole (measured only when ``measure_full``).
        kappa_shift: a delta's κ shift (0 for a full upload).
    """

    version: int
    base_version: Optional[int]
    chunks: list
    n_records: int
    n_removed: int
    subset: GaussianArrays
    ids: np.ndarray
    full_bytes: Optional[int] = None
    kappa_shift: int = 0

    @property
    def nbytes(self) -> int:
        return sum(len(c) for c in self.chunks)

    @property
    def is_delta(self) -> bool:
        return self.base_version is not None

    @property
    def is_noop(self) -> bool:
        """A delta that changes nothing (no record, no removal, κ shift 0): the server already holds this
        subset as its base version, so the upload can be skipped."""
        return self.is_delta and self.n_records == 0 and self.n_removed == 0 and self.kappa_shift == 0


class PushPlanner:
    """Agent-side mirror of the server's copy of this agent's subset; plans full or delta pushes.

    Usage: ``p = planner.plan(ids, arrays, version)``; upload ``p.chunks``; on success call
    ``planner.acknowledge(p)``; when the server rejects a delta because it lacks the base, call
    ``planner.forget()`` and plan again (a full upload).

    Args:
        agent_id: the agent id written into the chunks.
        quant: codec configuration.  chunk_gaussians: Gaussians per chunk.
        tolerance, kappa_rel: see :func:`changed_rows`.
        delta: False → every push is a full upload.
    """

    def __init__(self, agent_id: str, quant: QuantConfig = QuantConfig(), *, chunk_gaussians: int = 20000,
                 tolerance: float = 1.0, kappa_rel: float = 0.25, delta: bool = True) -> None:
        self.agent_id = agent_id
        self.quant = quant
        self.chunk_gaussians = int(chunk_gaussians)
        self.tolerance = float(tolerance)
        self.kappa_rel = float(kappa_rel)
        self.delta = bool(delta)
        self.base_version: Optional[int] = None
        self.base: Optional[GaussianArrays] = None
        self.base_ids: Optional[np.ndarray] = None
        self.last_stats: dict = {}  # row counts of the last delta plan (diagnostics)

    def forget(self) -> None:
        """Drop the mirror (the next push is a full upload)."""
        self.base_version = self.base = self.base_ids = None

    def acknowledge(self, push: PlannedPush) -> None:
        """The server acknowledged ``push`` complete: it becomes the base of the next delta."""
        self.base_version, self.base, self.base_ids = push.version, push.subset, push.ids

    def _full(self, ids: np.ndarray, arrays: GaussianArrays, version: int) -> PlannedPush:
        order = spatial_order(arrays.means)
        chunks = encode_subset(arrays.take(order), self.agent_id, version,
                               chunk_gaussians=self.chunk_gaussians, quant=self.quant)
        subset, _ = assemble(chunks)
        return PlannedPush(version, None, chunks, len(arrays), 0, subset, ids[order],
                           sum(len(c) for c in chunks))

    def plan(self, ids, arrays: GaussianArrays, version: int, measure_full: bool = True) -> PlannedPush:
        """Plan the push of ``arrays`` (rows identified by ``ids``) as map ``version``.

        A delta is planned when a base exists, the version is newer than it, and the delta is
        smaller than the full encoding (when ``measure_full``); otherwise a full upload.

        Args:
            ids: (N,) distinct int64 ids of ``arrays``' rows.  arrays: the subset to share.
            version: map version (> the base version for a delta).
            measure_full: also encode the whole subset (for ``full_bytes`` and the size check).

        Raises:
            ValueError: ids not distinct or of the wrong length.
        """
        ids = np.asarray(ids, np.int64).reshape(-1)
        if len(ids) != len(arrays):
            raise ValueError(f"{len(ids)} ids for {len(arrays)} Gaussians")
        if len(np.unique(ids)) != len(ids):
            raise ValueError("Gaussian ids are not distinct")
        if not self.delta or self.base is None or version <= self.base_version:
            return self._full(ids, arrays, version)
        base, bids = self.base, self.base_ids
        m = len(base)
        # rows of the current subset present in the base, and where
        base_row = np.full(len(ids), -1, np.int64)
        if m:
            sorter = np.argsort(bids)
            pos = sorter[np.clip(np.searchsorted(bids, ids, sorter=sorter), 0, m - 1)]
            base_row = np.where(bids[pos] == ids, pos, -1)
        in_base = base_row >= 0
        cur_idx = np.nonzero(in_base)[0]
        kept_cur, kept_base = arrays.take(cur_idx), base.take(base_row[cur_idx])
        act = kept_base.active
        shift = kappa_shift_of(kept_cur.kappa[act], kept_base.kappa[act])
        kept_base.kappa = kept_base.kappa + shift * act  # what the server will hold for an unreplaced row
        # the code-step moves once, for the rule and for the diagnostic tolerances below
        steps = None if self.quant.lossless else change_steps(kept_cur, kept_base, self.quant)
        changed = changed_rows(kept_cur, kept_base, self.quant, self.tolerance, self.kappa_rel, steps=steps)
        upd_idx = cur_idx[changed]
        self.last_stats = {"base_rows": m, "kept": len(cur_idx), "changed": int(changed.sum()),
                           "new": int((~in_base).sum()), "kappa_shift": shift,
                           "changed_at_tolerance": {f"{t}/{k}": int(changed_rows(
                               kept_cur, kept_base, self.quant, t, k, steps=steps).sum())
                               for t in (1.0, 4.0) for k in (1.0, 1e9)}}
        new_idx = np.nonzero(~in_base)[0]
        new_idx = new_idx[spatial_order(arrays.means[new_idx])]
        keep = np.zeros(m, bool)
        keep[base_row[cur_idx]] = True
        removed = np.nonzero(~keep)[0]
        targets = np.concatenate([base_row[upd_idx], m + np.arange(len(new_idx))]).astype(np.int64)
        rec_idx = np.concatenate([upd_idx, new_idx])
        records = arrays.take(rec_idx)
        order = np.argsort(targets, kind="stable")  # encode_delta sorts; keep ids aligned
        targets, records, rec_idx = targets[order], records.take(order), rec_idx[order]
        chunks = encode_delta(records, targets, removed, self.agent_id, version, self.base_version, m,
                              chunk_gaussians=self.chunk_gaussians, quant=self.quant, kappa_shift=shift)
        dec, meta = assemble(chunks)
        subset = apply_delta(base, dec, targets, removed, m, meta.kappa_shift)
        n_new = len(new_idx)
        new_ids = np.concatenate([bids[keep], ids[rec_idx[len(rec_idx) - n_new:]] if n_new else
                                  np.zeros(0, np.int64)])
        push = PlannedPush(version, self.base_version, chunks, len(records), len(removed), subset, new_ids,
                           kappa_shift=shift)
        if measure_full:
            full = self._full(ids, arrays, version)
            push.full_bytes = full.nbytes
            if full.nbytes <= push.nbytes:
                return full
        return push
