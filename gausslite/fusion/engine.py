"""One fuse job: from the agents' latest subsets (and keyframes) to a fused map (paper Sec. III-E).

The fusion server runs this for every ``Fuse`` call; the benches run it in process. Steps: the κ voxel vote
(:func:`gausslite.fusion.vote.voxel_vote`, through a kept :class:`IncrementalVote` so that only agents whose subset
changed are re-voted) or plain concatenation, then optionally the joint refinement over the union of the agents'
keyframes (:func:`gausslite.fusion.refine.refine_map`), validated on keyframes it holds out of training
(:class:`~gausslite.fusion.holdout.RefineReport` in :attr:`FuseOutcome.refine_report`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

from gausslite.core.arrays import GaussianArrays
from gausslite.fusion.guard import for_robot
from gausslite.fusion.holdout import RefineReport
from gausslite.fusion.vote import IncrementalVote, VoteReport, VoxelRangeError, concat, voxel_vote

log = logging.getLogger(__name__)

__all__ = ["FuseOutcome", "FuseEngine"]

#: ``progress(stage, fraction in [0, 1], message)``
StageFn = Callable[[str, float, str], None]


@dataclass
class FuseOutcome:
    """What one fuse job produced.

    Attributes:
        fused: the fused map (``GaussianArrays``, world frame, metres).
        kept: agent id → Gaussians of that agent in the fused map (before refinement).
        report: the vote's :class:`VoteReport` (None for concat).
        vote_seconds: wall time of the vote (0 for concat).
        agents_revoted: agents whose subsets were (re-)voted; incremental: whether the kept vote was updated
            rather than rebuilt.
        keyframes_used: keyframes of the refinement (0 without).
        seconds: wall time of the whole job.
        first_row: provenance, agent id → index of its first row in ``fused``: rows ``[first_row[a], first_row[a] +
            kept[a])`` came from agent ``a`` (vote and concat group the rows by agent); None after a refinement,
            which splits, clones and prunes rows.
        refine_report: what the refinement did (held-out losses of the vote and of the best state, iterations,
            early stop, rollback to the vote, training / held-out keyframes); None without a refinement.
    """

    fused: GaussianArrays
    kept: Dict[str, int]
    report: Optional[VoteReport] = None
    vote_seconds: float = 0.0
    agents_revoted: int = 0
    incremental: bool = False
    keyframes_used: int = 0
    seconds: float = 0.0
    first_row: Optional[Dict[str, int]] = None
    refine_report: Optional[RefineReport] = None


#: what a ``keyframes`` callback of :meth:`FuseEngine.fuse` returns: a pool, or agent id → that agent's keyframes
KeyframePool = Union[Sequence, Mapping[str, Sequence]]


def _pool(found: KeyframePool) -> Tuple[List, Optional[List[str]]]:
    """(keyframes, their agents or None) of a :data:`KeyframePool`; a mapping is flattened in its order."""
    if isinstance(found, Mapping):
        pairs = [(a, k) for a, ks in found.items() for k in ks]
        return [k for _, k in pairs], [a for a, _ in pairs]
    return list(found), None


def _first_rows(order: Sequence[str], kept: Mapping[str, int]) -> Dict[str, int]:
    """agent id → first row of its block, for a map made of ``kept[a]`` rows of each agent in ``order``."""
    out, at = {}, 0
    for a in order:
        out[a] = at
        at += int(kept.get(a, 0))
    return out


class FuseEngine:
    """Runs fuse jobs and keeps the incremental vote between them (one engine per fusion server).

    Args:
        refine_options: extra keyword arguments of :func:`gausslite.fusion.refine.refine_map` (the fusion server's:
            its ``refine_validation`` settings, :meth:`gausslite.fusion.holdout.RefineValidation.options`, then its
            ``refine_options``).
    """

    def __init__(self, refine_options: Optional[dict] = None) -> None:
        self.refine_options = dict(refine_options or {})
        self._voter: Optional[IncrementalVote] = None

    def vote(self, versions: Mapping[str, int], maps: Mapping[str, GaussianArrays], voxel_size: float,
             contest_radius: int = 0):
        """Voxel vote of ``maps`` (agent id → subset, at ``versions``) with δ = ``voxel_size`` m and a neighbourhood
        of ``contest_radius`` voxels, through the kept :class:`IncrementalVote` (a full vote when it cannot hold the
        maps' extent at radius 0). Returns (fused, report, agents re-voted, incremental?).

        Raises:
            ValueError: the neighbourhood vote cannot hold these maps (``contest_radius`` > 0 and means beyond its
                range; fuse with radius 0).
        """
        voter = self._voter
        if voter is not None and (voter.voxel_size != voxel_size or voter.contest_radius != contest_radius):
            voter = None
        incremental = voter is not None
        voter = voter or IncrementalVote(voxel_size, contest_radius=contest_radius)
        self._voter = None  # re-installed only after a successful sync
        try:
            changed = voter.sync(dict(versions), maps.__getitem__)
        except VoxelRangeError as e:
            if contest_radius:
                raise ValueError(f"the neighbourhood vote cannot hold these maps ({e}); fuse with contest_radius=0") \
                    from None
            log.info("incremental vote unavailable (%s); full vote", e)
            fused, report = voxel_vote(maps, voxel_size)
            return fused, report, len(maps), False
        fused, report = voter.result()
        self._voter = voter
        return fused, report, len(changed), incremental

    def fuse(self, versions: Mapping[str, int], maps: Mapping[str, GaussianArrays], method: str = "vote", *,
             voxel_size: float = 0.10, contest_radius: int = 0, refine_iters: int = 0,
             keyframes: Callable[[], KeyframePool] = lambda: (), seed: int = 0,
             progress: Optional[StageFn] = None, for_agent: Optional[str] = None,
             roi_views: Callable[[str], Sequence] = lambda agent: ()) -> FuseOutcome:
        """One fuse job.

        Args:
            versions: agent id → subset version of ``maps`` (the incremental vote's key).
            maps: agent id → subset (``GaussianArrays``).
            method: ``vote`` or ``concat``.
            voxel_size, contest_radius: the vote's δ (m) and neighbourhood (voxels).
            refine_iters: 0 = no refinement; otherwise the joint refinement's iterations at most (it runs fewer over
                few keyframes and stops early once its held-out keyframes stop improving; ``refine_options``).
            keyframes: returns the refinement's keyframes (:class:`~gausslite.mapping.views.Keyframe`; called only when
                refining), as one pool or as agent id → that agent's keyframes (the held-out keyframes are then
                spread over the agents).
            seed: refinement RNG seed.
            progress: ``(stage, fraction, message)`` callback; it may raise to stop the job.
            for_agent: vote only: the team map as this agent uses it (:func:`gausslite.fusion.guard.for_robot`:
                its whole subset, the others' voted rows except those drawing its ROI in ``roi_views(for_agent)``).
            roi_views: agent id → its ROI views (the uploaded keyframes with their ROI; called only with
                ``for_agent``).

        Returns:
            :class:`FuseOutcome`.

        Raises:
            ValueError: unknown method, a refinement without keyframes, a vote that cannot hold the maps, or
                ``for_agent`` with concat or not among ``maps``.
        """
        if for_agent is not None and (method != "vote" or for_agent not in maps):
            raise ValueError(f"for_agent needs method 'vote' and an agent with a subset, got {method!r} / "
                             f"{for_agent!r}")
        emit = progress or (lambda stage, fraction, message: None)
        t0 = time.monotonic()
        end = 0.3 if refine_iters else 0.8
        emit(method, 0.1, f"{method} of {sum(len(m) for m in maps.values())} Gaussians")
        if method == "vote":
            tv = time.monotonic()
            fused, report, revoted, incremental = self.vote(versions, maps, voxel_size, contest_radius)
            out = FuseOutcome(fused, dict(report.kept), report, time.monotonic() - tv, revoted, incremental)
            out.first_row = _first_rows(report.agents, out.kept)  # the vote's canonical order: sorted agent ids
            emit(method, end, f"kept {len(fused)} Gaussians, {report.contested_voxels} contested voxels"
                 + (f" (incremental: {revoted} agent(s) re-voted)" if incremental else ""))
            if for_agent is not None:
                out.fused, st = for_robot(fused, report.source_agent, report.agents, for_agent, maps[for_agent],
                                          list(roi_views(for_agent)))
                out.kept = dict(st["kept"])
                out.first_row = _first_rows([for_agent] + [a for a in report.agents if a != for_agent], out.kept)
                emit(method, end, f"for {for_agent}: its {st['own']} Gaussians, the others' {st['others_kept']} "
                     f"kept and {st['others_dropped']} dropped over its ROI ({st['views']} ROI views)")
        elif method == "concat":
            fused = concat(maps)
            out = FuseOutcome(fused, {a: len(m) for a, m in maps.items()})
            out.first_row = _first_rows(sorted(maps), out.kept)
            emit(method, end, f"concatenated {len(fused)} Gaussians")
        else:
            raise ValueError(f"unknown fuse method {method!r} (use 'vote' or 'concat')")
        if refine_iters:
            self.refine(out, keyframes, refine_iters, seed, emit, end)
        out.seconds = time.monotonic() - t0
        return out

    def refine(self, out: FuseOutcome, keyframes: Callable[[], KeyframePool], iters: int, seed: int = 0,
               emit: Optional[StageFn] = None, start: float = 0.3, options: Optional[dict] = None) -> None:
        """Refine ``out.fused`` (a vote's or concat's outcome) over ``keyframes()``
        (:func:`gausslite.fusion.refine.refine_map` with :attr:`refine_options`, at most ``iters`` iterations, seed
        ``seed``), progress from ``start`` to 0.9 through ``emit``; fills ``out.keyframes_used`` and
        ``out.refine_report`` and logs the report. ``options`` go to ``refine_map`` over :attr:`refine_options`.
        Touches no state of the engine (the kept vote), so it may run outside the lock that guards :meth:`fuse`.

        Raises:
            ValueError: no keyframes.
        """
        emit = emit or (lambda stage, fraction, message: None)
        # lazy: keeps gausslite.fusion.engine importable without OpenCV, SciPy, Warp, torch
        from gausslite.fusion.refine import refine_map
        from gausslite.mapping.config import deep_merge

        kfs, sources = _pool(keyframes())
        if not kfs:
            raise ValueError("refinement needs at least one keyframe")
        out.keyframes_used = len(kfs)
        emit("refine", start, f"refining {len(out.fused)} Gaussians over {len(kfs)} keyframes, up to {iters} "
             "iterations")
        out.first_row = None
        report = RefineReport()
        options = deep_merge(dict(self.refine_options), dict(options or {}))
        if sources is not None:
            options.setdefault("sources", sources)
        out.fused = refine_map(out.fused, kfs, iters, seed=seed, report=report, **options,
                               progress=lambda f, m: emit("refine", start + (0.9 - start) * float(f), m))
        out.refine_report = report
        log.info("refinement: %s", report.summary())
        emit("refine", 0.9, report.summary())
