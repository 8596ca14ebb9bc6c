"""κ-weighted voxel vote and plain concatenation of multi-agent Gaussian maps.

Source: paper Sec. III-E ("Multi-Agent Refinement", count-weighted voxel vote).

Rule (``voxel_vote``): world space is cut into cubes of edge δ; a Gaussian with mean μ lies in voxel
``floor(μ / δ)`` (computed in float64 from the float32 means).  In every voxel where two or more
agents have Gaussians, all Gaussians of the winning agent are kept and all others dropped.  The
winner has the highest summed κ in that voxel; ties go to the agent with more Gaussians there
("the denser source"); remaining ties go to the lexicographically smallest agent id (Python ``str``
ordering), a deterministic rule independent of input order.  Voxels with one contributing agent
carry over unchanged.

Neighbourhood contest (``contest_radius`` r > 0, an extension of the paper's rule): a voxel's contest
also counts the agents' Gaussians in the (2r+1)³ block of voxels around it. Every agent with Gaussians
anywhere in the block competes with its summed κ (then its count) over the block; only the winner's
Gaussians *in the voxel* are kept (if the winner has none there, the voxel is emptied). With r = 0 this
is exactly the rule above. Why: the agents share subsets fine-tuned to render their own ROI alone, and
at δ = 0.10 m another agent's Gaussians in the voxels next to an ROI (not contested with the owner,
who has none there) still project into it. Room0, two agents with the ground-truth ROI, fine-tuned
subsets, three seeds (``bench.share_finetune``, retired: docs/history.md#share_finetune-and-share_refresh): vote ROI
PSNR pick-plant 35.30 / 36.87 / 36.65 dB with
r = 0 against 37.40 / 37.62 / 37.91 with r = 1 (the owner's subset alone: 37.40 / 37.62 / 37.91).

Output order is canonical (agents in sorted id order, each agent's rows in input order), so the
result is identical, not merely the same multiset, for any ordering of the input mapping.

Implementation: fully vectorised numpy; one argsort of packed int64 (voxel, agent) keys plus
segment reductions; no Python loops over Gaussians or voxels.  About 0.25 s for 1M Gaussians on
one core, 0.43 s from GaussianMap torch inputs (see ``bench/vote.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional

import numpy as np

from gausslite.core.arrays import GaussianArrays

__all__ = ["VoteReport", "voxel_vote", "concat", "voxel_keys", "IncrementalVote", "VoxelRangeError"]


@dataclass(frozen=True)
class VoteReport:
    """Outcome of :func:`voxel_vote`.

    Attributes:
        agents: agent ids in sorted order (the order of rows in the fused output).
        kept: agent id → Gaussians kept.
        dropped: agent id → Gaussians dropped (lost a contested voxel).
        voxels: number of occupied voxels.
        contested_voxels: voxels with Gaussians from two or more agents.
        won_voxels: agent id → contested voxels won.
        source_agent: (M,) int32, index into ``agents`` of each fused row.
        source_row: (M,) int64, row index of each fused row in its agent's input.
        voxel_size: δ in metres.
    """

    agents: tuple[str, ...]
    kept: dict[str, int]
    dropped: dict[str, int]
    voxels: int
    contested_voxels: int
    won_voxels: dict[str, int]
    source_agent: np.ndarray
    source_row: np.ndarray
    voxel_size: float

    def to_dict(self) -> dict:
        """JSON-friendly summary (without the per-row arrays)."""
        return {
            "agents": list(self.agents), "kept": dict(self.kept), "dropped": dict(self.dropped),
            "voxels": self.voxels, "contested_voxels": self.contested_voxels,
            "won_voxels": dict(self.won_voxels), "voxel_size": self.voxel_size,
        }


def _prepare(maps: Mapping[str, Any]) -> tuple[tuple[str, ...], list[GaussianArrays]]:
    if not isinstance(maps, Mapping):
        raise TypeError("maps must be a mapping agent_id -> Gaussians")
    agents = tuple(sorted(maps))
    if not all(isinstance(a, str) for a in agents):
        raise TypeError("agent ids must be str")
    return agents, [GaussianArrays.from_any(maps[a]) for a in agents]


def concat(maps: Mapping[str, Any]) -> GaussianArrays:
    """Baseline fusion ("Combine Maps", paper Tab. fusion): every Gaussian of every agent.

    Args:
        maps: agent id → GaussianMap / GaussianArrays / mapping of arrays.

    Returns:
        GaussianArrays, agents in sorted id order, rows in input order.
    """
    _, parts = _prepare(maps)
    return GaussianArrays.concat(parts)


def voxel_keys(means: np.ndarray, voxel_size: float) -> np.ndarray:
    """Integer voxel coordinates ``floor(means / voxel_size)`` in float64.

    Args:
        means: (N, 3) float, metres.  voxel_size: δ > 0, metres.

    Returns:
        (N, 3) int64.

    Raises:
        ValueError: non-finite means or coordinates beyond ±2^62 voxels.
    """
    v = np.floor(np.asarray(means, dtype=np.float64) / float(voxel_size))
    if not np.isfinite(v).all():
        raise ValueError("non-finite means")
    if v.size and np.abs(v).max() >= 2.0**62:
        raise ValueError("means too far from the origin for this voxel size")
    return v.astype(np.int64)


def _bits(n: int) -> int:
    return max(0, int(n - 1).bit_length()) if n > 1 else 0


def _voxel_agent_keys(means: np.ndarray, voxel_size: float, agent_of: np.ndarray, n_agents: int):
    """One int64 sort key per row, ``(voxel id << abits) | agent index``, with voxel ids packed from the rows'
    voxel indices (compacted first when the extent does not fit in 63 bits). Returns ``(key, abits)``.

    Raises:
        ValueError: too many voxels to key.
    """
    ijk = voxel_keys(means, voxel_size)
    ijk -= ijk.min(axis=0)
    span_bits = [_bits(int(s) + 1) for s in ijk.max(axis=0)]
    abits = _bits(n_agents)
    if sum(span_bits) + abits <= 63:
        vox = (ijk[:, 0] << (span_bits[1] + span_bits[2])) | (ijk[:, 1] << span_bits[2]) | ijk[:, 2]
    else:  # enormous extent: compact voxel ids first (slower, still vectorised)
        vox = np.unique(ijk, axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64)
        if _bits(int(vox.max()) + 1) + abits > 63:
            raise ValueError("too many voxels")
    return (vox << abits) | agent_of, abits


def _vote_winners(key: np.ndarray, abits: int, kappa: np.ndarray):
    """Per-voxel winners over the rows keyed by :func:`_voxel_agent_keys`: max summed κ, then max count, then the
    smallest agent index.

    Returns:
        ``(keep (N,) bool per row, pagent, winner, vpairs)``: the rows of winning (voxel, agent) pairs, each pair's
        agent index, and per voxel its winning pair's index and its number of pairs.
    """
    total = len(key)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    # segments of equal (voxel, agent): "pairs", sorted by voxel then agent id
    pstart = np.flatnonzero(np.concatenate(([True], ks[1:] != ks[:-1])))
    pcount = np.diff(np.append(pstart, total))
    pagent = ks[pstart] & ((1 << abits) - 1)
    pvox = ks[pstart] >> abits
    psum = np.add.reduceat(kappa[order], pstart)
    # segments of equal voxel over the pairs
    vstart = np.flatnonzero(np.concatenate(([True], pvox[1:] != pvox[:-1])))
    vpairs = np.diff(np.append(vstart, len(pvox)))
    # winner per voxel: max summed κ, then max count, then smallest agent index (= first in segment)
    best_sum = np.repeat(np.maximum.reduceat(psum, vstart), vpairs)
    cand = psum == best_sum
    best_cnt = np.repeat(np.maximum.reduceat(np.where(cand, pcount, -1), vstart), vpairs)
    cand &= pcount == best_cnt
    pos = np.arange(len(pvox), dtype=np.int64)
    winner = np.minimum.reduceat(np.where(cand, pos, len(pvox)), vstart)
    pwin = np.zeros(len(pvox), dtype=bool)
    pwin[winner] = True
    keep = np.empty(total, dtype=bool)
    keep[order] = np.repeat(pwin, pcount)
    return keep, pagent, winner, vpairs


def voxel_vote(maps: Mapping[str, Any], voxel_size: float = 0.10, contest_radius: int = 0
               ) -> tuple[GaussianArrays, VoteReport]:
    """κ-weighted per-voxel selection between agents (paper Sec. III-E).

    Args:
        maps: agent id (str) → Gaussians (GaussianMap with torch tensors, GaussianArrays, or a
            mapping of arrays; see :meth:`GaussianArrays.from_any`).  κ must be >= 0.
        voxel_size: δ in metres (> 0); the paper uses 0.10 m.
        contest_radius: r >= 0 voxels; r > 0 contests each voxel over its (2r+1)³ neighbourhood (module
            docstring), computed by :class:`IncrementalVote` (means within ±2^20 − r voxels).

    Returns:
        (fused, report): fused GaussianArrays (a subset of the input rows, canonical order, see the
        module docstring) and a :class:`VoteReport`.

    Raises:
        TypeError: bad container.  ValueError: voxel_size <= 0 or non-finite, non-finite means,
        negative κ, summed κ in one voxel overflowing int64, or a negative ``contest_radius``.
        VoxelRangeError: ``contest_radius`` > 0 and means beyond ±(2^20 − r) voxels.
    """
    if not (isinstance(voxel_size, (int, float, np.floating)) and math.isfinite(voxel_size)
            and voxel_size > 0):
        raise ValueError("voxel_size must be a positive finite number")
    r = _check_radius(contest_radius)
    if r > 0:
        _prepare(maps)  # container and id checks
        voter = IncrementalVote(voxel_size, contest_radius=r)
        voter.update_many({a: (g, None) for a, g in maps.items()})
        return voter.result()
    agents, parts = _prepare(maps)
    n_agents = len(agents)
    sizes = np.array([len(p) for p in parts], dtype=np.int64)
    total = int(sizes.sum())
    agent_of = np.repeat(np.arange(n_agents, dtype=np.int64), sizes)
    row_of = np.arange(total, dtype=np.int64) - np.repeat(np.cumsum(sizes) - sizes, sizes)
    if total == 0:
        empty = {a: 0 for a in agents}
        return GaussianArrays.empty(), VoteReport(
            agents, dict(empty), dict(empty), 0, 0, dict(empty), np.zeros(0, np.int32),
            np.zeros(0, np.int64), float(voxel_size))
    means = np.concatenate([p.means for p in parts])
    kappa = np.concatenate([p.kappa for p in parts])
    if kappa.min() < 0:
        raise ValueError("kappa must be >= 0")
    if int(kappa.max()) > (2**63 - 1) // total:  # cheap sufficient test first, exact one after
        if int(kappa.astype(object).sum()) >= 2**63:
            raise ValueError("summed kappa overflows int64")

    key, abits = _voxel_agent_keys(means, voxel_size, agent_of, n_agents)
    keep, pagent, winner, vpairs = _vote_winners(key, abits, kappa)
    idx = np.flatnonzero(keep)

    contested = vpairs >= 2
    won = np.bincount(pagent[winner[contested]], minlength=n_agents)
    kept = np.bincount(agent_of[idx], minlength=n_agents)
    bounds = np.concatenate(([0], np.cumsum(sizes)))
    fused = GaussianArrays.concat(
        [p.take(keep[bounds[i]:bounds[i + 1]]) for i, p in enumerate(parts)])
    report = VoteReport(
        agents=agents,
        kept={a: int(kept[i]) for i, a in enumerate(agents)},
        dropped={a: int(sizes[i] - kept[i]) for i, a in enumerate(agents)},
        voxels=int(len(vpairs)),
        contested_voxels=int(contested.sum()),
        won_voxels={a: int(won[i]) for i, a in enumerate(agents)},
        source_agent=agent_of[idx].astype(np.int32),
        source_row=row_of[idx],
        voxel_size=float(voxel_size),
    )
    return fused, report


# ---------------------------------------------------------------------------------------------
# Incremental vote
# ---------------------------------------------------------------------------------------------

_PACK_BITS = 21
_PACK_OFF = 1 << (_PACK_BITS - 1)


class VoxelRangeError(ValueError):
    """Means too far from the origin for :class:`IncrementalVote`'s packed voxel keys
    (|floor(μ/δ)| ≥ 2^20 voxels, i.e. beyond ±104 km at δ = 0.1 m); use :func:`voxel_vote`."""


def _check_radius(r) -> int:
    if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or r < 0 or r > 8:
        raise ValueError(f"contest_radius must be an integer in 0..8, got {r!r}")
    return int(r)


def _block_offsets(r: int) -> np.ndarray:
    """(M,) int64 packed-key offsets of the (2r+1)³ voxel block (0 first)."""
    d = np.arange(-r, r + 1, dtype=np.int64)
    o = np.stack(np.meshgrid(d, d, d, indexing="ij"), -1).reshape(-1, 3)
    o = o[np.argsort(np.abs(o).sum(1), kind="stable")]
    return (o[:, 0] << (2 * _PACK_BITS)) + (o[:, 1] << _PACK_BITS) + o[:, 2]


def _packed_voxels(means: np.ndarray, voxel_size: float, margin: int = 0) -> np.ndarray:
    """(N,) int64 voxel ids: the three ``floor(μ/δ)`` coordinates biased by 2^20, 21 bits each
    (``margin`` voxels kept free at the edges of the range for neighbourhood offsets)."""
    ijk = voxel_keys(means, voxel_size)
    if ijk.size and int(np.abs(ijk).max()) >= _PACK_OFF - margin:
        raise VoxelRangeError(f"means beyond ±{_PACK_OFF - margin} voxels of {voxel_size} m from the origin")
    u = ijk + _PACK_OFF
    return (u[:, 0] << (2 * _PACK_BITS)) | (u[:, 1] << _PACK_BITS) | u[:, 2]


def _voxel_box(packed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis min and max of packed voxel ids (empty → an empty box: lo > hi)."""
    if len(packed) == 0:
        return np.full(3, 1 << 62, np.int64), np.full(3, -1, np.int64)
    mask = (1 << _PACK_BITS) - 1
    ijk = np.stack([packed >> (2 * _PACK_BITS), (packed >> _PACK_BITS) & mask, packed & mask], axis=1)
    return ijk.min(axis=0), ijk.max(axis=0)


def _expand(lo: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Concatenated ranges ``[lo[i], lo[i] + counts[i])`` (vectorised)."""
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    return np.repeat(lo - (np.cumsum(counts) - counts), counts) + np.arange(total, dtype=np.int64)


class _AgentState:
    """One agent's subset with its voxel index: rows sorted by voxel, per-voxel κ sums and counts."""

    __slots__ = ("arrays", "vox_order", "svox", "uvox", "usum", "ucnt", "ksum", "keep", "part", "rows", "lo", "hi")

    def __init__(self, arrays: GaussianArrays, voxel_size: float, margin: int = 0):
        n = len(arrays)
        if n and int(arrays.kappa.min()) < 0:
            raise ValueError("kappa must be >= 0")
        vox = _packed_voxels(arrays.means, voxel_size, margin)
        self.arrays = arrays
        self.vox_order = np.argsort(vox, kind="stable")
        self.svox = vox[self.vox_order]
        starts = np.flatnonzero(np.concatenate(([True], self.svox[1:] != self.svox[:-1]))) if n else \
            np.zeros(0, np.int64)
        self.uvox = self.svox[starts]
        self.ucnt = np.diff(np.append(starts, n)).astype(np.int64)
        self.usum = np.add.reduceat(arrays.kappa[self.vox_order], starts) if n else np.zeros(0, np.int64)
        if n and int(arrays.kappa.max()) > (2**63 - 1) // n:
            self.ksum = int(arrays.kappa.astype(object).sum())
        else:
            self.ksum = int(arrays.kappa.sum()) if n else 0
        self.lo, self.hi = _voxel_box(self.uvox)
        self.keep = np.zeros(n, dtype=bool)
        self.part: Optional[GaussianArrays] = None  # cached kept rows (None = recompute)
        self.rows: Optional[np.ndarray] = None


class IncrementalVote:
    """κ-weighted voxel vote kept current as agents' subsets change (paper Sec. III-E).

    Holds every agent's subset with a per-voxel index and the winner of every occupied voxel.
    :meth:`update` of one agent re-votes only the voxels that agent's old or new subset touches
    (gathering the other agents' per-voxel κ sums there by binary search) and re-evaluates only the
    rows of other agents in those voxels, so its cost grows with the size of the change, not with the
    fleet. :meth:`result` returns exactly what :func:`voxel_vote` returns for the current subsets
    (same rule, same tie-breaks, same canonical row order; property-tested).

    With ``contest_radius`` r > 0 (module docstring) an update re-votes every occupied voxel within r
    voxels of the voxels it touches, with each agent's κ sums and counts gathered over the block.

    Args:
        voxel_size: δ in metres (> 0).  contest_radius: r in voxels (0..8).
    Raises:
        ValueError: voxel_size not positive and finite, or a bad contest_radius.

    Not thread-safe: one fusion at a time (the fusion server holds its fuse lock).
    """

    def __init__(self, voxel_size: float = 0.10, contest_radius: int = 0):
        if not (isinstance(voxel_size, (int, float, np.floating)) and math.isfinite(voxel_size)
                and voxel_size > 0):
            raise ValueError("voxel_size must be a positive finite number")
        self.voxel_size = float(voxel_size)
        self.contest_radius = _check_radius(contest_radius)
        self._offsets = _block_offsets(self.contest_radius)
        self._agents: dict[str, _AgentState] = {}
        self._revision: dict[str, Any] = {}
        self._code: dict[str, int] = {}  # stable small integer per agent id (never reused)
        self._vox = np.zeros(0, np.int64)  # occupied voxels, sorted
        self._npair = np.zeros(0, np.int64)  # agents present per voxel
        self._win = np.zeros(0, np.int64)  # winner's code per voxel
        self._contested = 0
        self._won: dict[int, int] = {}  # code -> contested voxels won

    # ------------------------------------------------------------------ queries
    @property
    def agents(self) -> tuple[str, ...]:
        """Agent ids held, sorted."""
        return tuple(sorted(self._agents))

    def revision(self, agent: str) -> Any:
        """The revision tag given with the agent's last :meth:`update` (None when absent)."""
        return self._revision.get(agent)

    # ------------------------------------------------------------------ updates
    def update(self, agent: str, gaussians: Any, revision: Any = None) -> int:
        """Replace (or add) ``agent``'s subset and re-vote the voxels it touches.

        Args:
            agent: agent id (str).  gaussians: the agent's subset (see :meth:`GaussianArrays.from_any`).
            revision: opaque tag remembered for :meth:`sync` (e.g. the map version).
        Returns:
            int: voxels re-voted.
        Raises:
            TypeError: agent id not a str.  ValueError: negative κ, non-finite means, summed κ
            overflowing int64.  VoxelRangeError: means beyond ±2^20 voxels.  On error the state is
            unchanged.
        """
        return self.update_many({agent: (gaussians, revision)})

    def update_many(self, updates: Mapping[str, tuple]) -> int:
        """Replace (or add) several agents' subsets (agent → (gaussians, revision)) with one re-vote
        of the union of the voxels they touch (a full vote when the state was empty).

        Returns / Raises: as :meth:`update` (on error the state is unchanged).
        """
        if not all(isinstance(a, str) for a in updates):
            raise TypeError("agent ids must be str")
        states = {a: _AgentState(GaussianArrays.from_any(g), self.voxel_size, self.contest_radius)
                  for a, (g, _) in updates.items()}
        ksum = sum(s.ksum for a, s in self._agents.items() if a not in states) + sum(s.ksum for s in states.values())
        if ksum >= 2**63:
            raise ValueError("summed kappa overflows int64")
        parts = [s.uvox for s in states.values()]
        parts += [self._agents[a].uvox for a in states if a in self._agents]
        touched = self._dilate(np.concatenate(parts)) if parts else np.zeros(0, np.int64)
        for a in sorted(states):
            if a not in self._code:
                self._code[a] = len(self._code)
            self._agents[a] = states[a]
            self._revision[a] = updates[a][1]
        self._revote(touched)
        return int(len(touched))

    def remove(self, agent: str) -> int:
        """Drop ``agent`` (no-op when absent); returns the voxels re-voted."""
        old = self._agents.pop(agent, None)
        self._revision.pop(agent, None)
        if old is None:
            return 0
        touched = self._dilate(old.uvox)
        self._revote(touched)
        return int(len(touched))

    def _dilate(self, vox: np.ndarray) -> np.ndarray:
        """Sorted unique voxels within ``contest_radius`` of ``vox`` (packed ids)."""
        if self.contest_radius == 0 or len(vox) == 0:
            return np.unique(vox)
        u = np.unique(vox)
        return np.unique((u[:, None] + self._offsets[None, :]).reshape(-1))

    def sync(self, revisions: Mapping[str, Any], load) -> list[str]:
        """Make the held subsets those of ``revisions`` (agent id → revision tag).

        Agents whose tag differs from the held one are re-loaded with ``load(agent)`` and updated;
        agents not in ``revisions`` are removed.

        Returns:
            list[str]: the agents updated or removed (sorted).
        """
        changed = [a for a in sorted(self._agents) if a not in revisions]
        for a in changed:
            self.remove(a)
        todo = [a for a in sorted(revisions)
                if a not in self._agents or self._revision.get(a) != revisions[a]]
        if todo:
            self.update_many({a: (load(a), revisions[a]) for a in todo})
        return sorted(changed + todo)

    def _revote(self, touched: np.ndarray) -> None:
        """Re-vote the sorted unique voxels ``touched`` and splice the outcome into the tables."""
        if len(touched) == 0:
            return
        ids = sorted(self._agents)
        rank = {a: i for i, a in enumerate(ids)}
        # (voxel position in touched, κ sum, count, id rank, code) of every agent present there
        t_idx, psum, pcnt, prank, pcode = [], [], [], [], []
        hits = {}
        tlo, thi = _voxel_box(touched)
        r = self.contest_radius
        m = len(touched)
        occupied = np.zeros(m, dtype=bool)
        for a in ids:
            s = self._agents[a]
            if len(s.uvox) == 0 or (s.lo > thi + r).any() or (s.hi < tlo - r).any():  # no voxel within r
                continue
            pos = np.searchsorted(s.uvox, touched)
            ok = pos < len(s.uvox)
            ok[ok] = s.uvox[pos[ok]] == touched[ok]
            if r == 0:
                ti = np.flatnonzero(ok)
                bsum, bcnt = s.usum[pos[ti]], s.ucnt[pos[ti]]
            else:  # κ sums and counts over the (2r+1)³ block of every touched voxel: each occupied
                # voxel u of the agent adds to the touched voxels among u + offsets (the block is symmetric)
                cand = (s.uvox[:, None] + self._offsets[None, :]).reshape(-1)
                tp = np.searchsorted(touched, cand)
                tok = tp < m
                tok[tok] = touched[tp[tok]] == cand[tok]
                tgt = tp[tok]
                src = np.flatnonzero(tok) // len(self._offsets)
                bsum = np.zeros(m, np.int64)
                bcnt = np.zeros(m, np.int64)
                np.add.at(bsum, tgt, s.usum[src])
                np.add.at(bcnt, tgt, s.ucnt[src])
                ti = np.flatnonzero(bcnt > 0)
                bsum, bcnt = bsum[ti], bcnt[ti]
            occupied |= ok
            if not ok.any() and len(ti) == 0:
                continue
            if ok.any():
                hits[a] = np.flatnonzero(ok)
            if len(ti) == 0:
                continue
            t_idx.append(ti)
            psum.append(bsum)
            pcnt.append(bcnt)
            prank.append(np.full(len(ti), rank[a], np.int64))
            pcode.append(np.full(len(ti), self._code[a], np.int64))
        if t_idx:
            t_idx_a, psum_a, pcnt_a = np.concatenate(t_idx), np.concatenate(psum), np.concatenate(pcnt)
            prank_a, pcode_a = np.concatenate(prank), np.concatenate(pcode)
            # winner: max κ sum, then max count, then smallest id (rank)
            order = np.lexsort((prank_a, -pcnt_a, -psum_a, t_idx_a))
            first = order[np.concatenate(([True], t_idx_a[order][1:] != t_idx_a[order][:-1]))]
            npair = np.bincount(t_idx_a, minlength=m).astype(np.int64)
            win = np.full(m, -1, np.int64)
            win[t_idx_a[first]] = pcode_a[first]
        else:
            npair = np.zeros(m, np.int64)
            win = np.full(m, -1, np.int64)
        npair[~occupied] = 0  # a voxel only in some block: not an occupied voxel of the vote
        win[~occupied] = -1

        # statistics: remove the old contribution of the touched voxels, add the new one
        pos = np.searchsorted(self._vox, touched)
        present = pos < len(self._vox)
        present[present] = self._vox[pos[present]] == touched[present]
        ppos = pos[present]
        old_contested = self._npair[ppos] >= 2
        self._contested += int((npair >= 2).sum()) - int(old_contested.sum())
        for c, k in zip(*np.unique(self._win[ppos][old_contested], return_counts=True)):
            self._won[int(c)] = self._won.get(int(c), 0) - int(k)
        for c, k in zip(*np.unique(win[npair >= 2], return_counts=True)):
            self._won[int(c)] = self._won.get(int(c), 0) + int(k)
        # splice: update present voxels, drop emptied ones, insert new ones
        self._npair[ppos] = npair[present]
        self._win[ppos] = win[present]
        gone = ppos[npair[present] == 0]
        if len(gone):
            self._vox, self._npair, self._win = (np.delete(x, gone) for x in (self._vox, self._npair, self._win))
        new = ~present & (npair > 0)
        if new.any():
            at = np.searchsorted(self._vox, touched[new])
            self._vox = np.insert(self._vox, at, touched[new])
            self._npair = np.insert(self._npair, at, npair[new])
            self._win = np.insert(self._win, at, win[new])

        # rows of every agent in the touched voxels: keep iff the agent won the voxel
        for a, ti in hits.items():
            s = self._agents[a]
            tv = touched[ti]
            lo = np.searchsorted(s.svox, tv, "left")
            cnt = np.searchsorted(s.svox, tv, "right") - lo
            rows = s.vox_order[_expand(lo, cnt)]
            keep = np.repeat(win[ti] == self._code[a], cnt)
            if not np.array_equal(s.keep[rows], keep):
                s.keep[rows] = keep
                s.part = s.rows = None

    # ------------------------------------------------------------------ result
    def result(self) -> tuple[GaussianArrays, VoteReport]:
        """The fused map and report, identical to ``voxel_vote(current subsets, voxel_size)``."""
        agents = self.agents
        parts, rows = [], []
        for a in agents:
            s = self._agents[a]
            if s.part is None:
                s.rows = np.flatnonzero(s.keep)
                s.part = s.arrays.take(s.rows)
            parts.append(s.part)
            rows.append(s.rows)
        kept = {a: len(p) for a, p in zip(agents, parts)}
        fused = GaussianArrays.concat(parts) if parts else GaussianArrays.empty()
        code_to_id = {c: a for a, c in self._code.items()}
        won = {a: 0 for a in agents}
        for c, k in self._won.items():
            if k and code_to_id[c] in won:
                won[code_to_id[c]] = int(k)
        report = VoteReport(
            agents=agents, kept=kept,
            dropped={a: len(self._agents[a].arrays) - kept[a] for a in agents},
            voxels=int(len(self._vox)), contested_voxels=int(self._contested), won_voxels=won,
            source_agent=np.repeat(np.arange(len(agents), dtype=np.int32),
                                   [kept[a] for a in agents]).astype(np.int32),
            source_row=np.concatenate(rows).astype(np.int64) if rows else np.zeros(0, np.int64),
            voxel_size=self.voxel_size)
        return fused, report
