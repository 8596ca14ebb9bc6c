"""ROI guard: after the vote, no robot's Gaussian lies over another robot's task region in that robot's own views.

The paper's vote (Sec. III-E) settles each voxel by κ, by where each Gaussian's *mean* lies. A Gaussian is not a
point: one whose mean sits in a voxel no other agent holds can still extend, or project, over another agent's ROI,
and then no contest ever removes it. Agents fine-tune their subsets to render their own ROI alone
(:func:`gausslite.sharing.finetune_subset`), which leaves them free to spread over the pixels beside it; in a team
whose task regions lie side by side those pixels are the neighbour's ROI (``docs/sharing.md``, "What spoils a
robot's ROI").

The guard uses what the fusion server already holds: each agent's uploaded keyframes with the ROI it mapped them
with (``KeyframeRequest.roi_png``). In every agent's ROI views it renders the vote's map and takes each Gaussian's
alpha-blending weight over that agent's ROI pixels (:func:`gausslite.render.blend_weights`), averaged per view:
``W_a(i)``. A Gaussian i of agent b is dropped when, for some other agent a,

    W_a(i) > max(W_b(i), min_weight)

that is, when it draws another robot's task region in that robot's views more than it draws its own robot's task
region in its own views. What it draws there, the owner's own subset draws: each subset is fine-tuned to render its
ROI alone. A Gaussian shared by both tasks (regions that overlap, such as a keyboard both tasks include) stays with
the robot it serves most, as in the vote. Agents without ROI keyframes on the server are not guarded, and their
Gaussians have ``W_b = 0``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Mapping, Optional, Sequence

import numpy as np

from gausslite.core.arrays import GaussianArrays

__all__ = ["RoiView", "GuardReport", "roi_weights", "roi_guard", "for_robot", "provenance_rows", "with_own_map",
           "ON_BOARD_MIN_WEIGHT"]


@dataclass(frozen=True)
class RoiView:
    """One view of a robot's task ROI.

    Attributes:
        K: (3, 3) float pixel intrinsics.  width, height: image size (pixels).
        c2w: (4, 4) float camera-to-world, OpenCV camera axes, metres.
        roi: (height, width) bool ROI pixels.
        depth: (height, width) float32 sensor depth (metres along camera z, 0 = invalid), or None.
    """

    K: np.ndarray
    width: int
    height: int
    c2w: np.ndarray
    roi: np.ndarray
    depth: Optional[np.ndarray] = None

    @classmethod
    def from_frame(cls, frame, roi: np.ndarray) -> "RoiView":
        """From a dataset ``Frame`` and its (H, W) bool ROI."""
        i = frame.intrinsics
        return cls(np.asarray(i.K, np.float64), int(i.width), int(i.height), np.asarray(frame.c2w, np.float64),
                   np.asarray(roi, bool), np.asarray(frame.depth, np.float32))

    @classmethod
    def of_frames(cls, frames, roi_fn, stride: int = 1) -> list:
        """The views of every ``stride``-th dataset ``Frame`` of ``frames`` whose ROI (``roi_fn(frame)``, (H, W) bool,
        e.g. a task's ground-truth ROI) is not empty, in order."""
        views = []
        for fr in list(frames)[::stride]:
            roi = roi_fn(fr)
            if roi.any():
                views.append(cls.from_frame(fr, roi))
        return views


@dataclass(frozen=True)
class GuardReport:
    """Outcome of :func:`roi_guard`.

    Attributes:
        dropped: agent id → its Gaussians dropped (they lay over another agent's ROI).
        views: agent id → ROI views used.
        seconds: wall time.
    """

    dropped: dict
    views: dict
    seconds: float

    def to_dict(self) -> dict:
        return {"dropped": dict(self.dropped), "views": dict(self.views), "seconds": self.seconds}


def roi_weights(gaussians: GaussianArrays, views: Sequence, backend: str = "auto") -> np.ndarray:
    """(N,) float64 alpha-blending weight of each Gaussian over the ROI pixels of ``views``, averaged per view
    (:func:`gausslite.sharing.roi_contribution` divided by the number of views with ROI pixels).

    Args:
        gaussians: the map (world frame, metres).
        views: ROI views, each with ``K`` (3, 3) pixels, ``width``, ``height``, ``c2w`` (4, 4) camera-to-world (OpenCV
            axes) and ``roi`` (height, width) bool (arrays or CPU tensors, e.g. ``gausslite.mapping.views.Keyframe``
            or :class:`RoiView`); views without ROI pixels are skipped.
        backend: rasterizer backend.
    """
    vs = _roi_views(views)
    if not vs or len(gaussians) == 0:
        return np.zeros(len(gaussians), np.float64)
    # lazy: torch and the rasterizer (the 'mapper' extra), needed only when there are ROI views to render; keeps
    # gausslite.fusion.guard importable, and the team map of a robot without ROI views made, on the light install
    from gausslite.sharing import roi_contribution

    return roi_contribution(gaussians.to_gaussian_map(), vs, backend) / len(vs)


def _roi_views(views: Sequence, max_views: Optional[int] = None) -> list:
    """The views with ROI pixels, at most ``max_views`` of them evenly spaced."""
    vs = [v for v in views if v.roi is not None and bool(np.asarray(v.roi).any())]
    if max_views is not None and len(vs) > max_views:
        vs = [vs[int(k)] for k in np.linspace(0, len(vs) - 1, max_views).round()]
    return vs


def roi_guard(fused: GaussianArrays, source_agent: np.ndarray, agents: Sequence[str],
              views: Mapping[str, Sequence], *, min_weight: float = 0.05, max_views: int = 16,
              backend: str = "auto") -> tuple[np.ndarray, GuardReport]:
    """Which rows of a vote's map to keep (module docstring).

    Args:
        fused: the vote's map (M rows).
        source_agent: (M,) int, index into ``agents`` of each row's agent (``VoteReport.source_agent``).
        agents: agent ids (``VoteReport.agents``).
        views: agent id → its ROI views (as :func:`roi_weights`; the server's uploaded keyframes with their ROI).
        min_weight: a Gaussian drawing less than this (pixels of blending weight per view) of another agent's ROI
            is left alone (>= 0).
        max_views: at most this many ROI views per agent, evenly spaced over its views (>= 1).
        backend: rasterizer backend.

    Returns:
        (keep, report): (M,) bool rows to keep, and a :class:`GuardReport`.

    Raises:
        ValueError: ``source_agent`` of the wrong length or out of range, ``min_weight`` < 0 or ``max_views`` < 1.
    """
    t0 = time.perf_counter()
    src = np.asarray(source_agent, np.int64).reshape(-1)
    if len(src) != len(fused):
        raise ValueError(f"source_agent has {len(src)} rows for a map of {len(fused)}")
    if len(src) and (src.min() < 0 or src.max() >= len(agents)):
        raise ValueError("source_agent points outside agents")
    if min_weight < 0 or max_views < 1:
        raise ValueError("min_weight must be >= 0 and max_views >= 1")
    W = np.zeros((len(agents), len(fused)), np.float64)
    used = {}
    for i, a in enumerate(agents):
        vs = _roi_views(views.get(a, ()), max_views)
        used[a] = len(vs)
        if vs:
            W[i] = roi_weights(fused, vs, backend)
    own = W[src, np.arange(len(fused))] if len(fused) else np.zeros(0)
    other = W.copy()
    if len(fused):
        other[src, np.arange(len(fused))] = 0.0
    intrude = other.max(axis=0) if len(agents) else np.zeros(len(fused))
    keep = ~(intrude > np.maximum(own, min_weight))
    dropped = {a: int((~keep & (src == i)).sum()) for i, a in enumerate(agents)}
    return keep, GuardReport(dropped, used, time.perf_counter() - t0)


def for_robot(fused: GaussianArrays, source_agent: np.ndarray, agents: Sequence[str], robot: str,
              subset: GaussianArrays, views: Sequence, *, min_weight: float = 0.01,
              max_views: Optional[int] = 16, backend: str = "auto") -> tuple[GaussianArrays, dict]:
    """The team map as one robot uses it: its own subset whole, and the team's vote wherever its ROI views do not
    look (``docs/sharing.md``, "The team map for one robot").

    Where task regions overlap in 3D (a desk that two tasks include), each robot's subset is fitted from its own
    views only, and renders the overlap well from those views alone; any one selection of rows then serves one
    robot's views and not the other's (measured in ``docs/sharing.md``). A robot that works on its task with the
    team map needs its region as it mapped it, plus what the others add elsewhere: this map keeps every row of
    ``subset`` (also those the vote dropped) and drops the other agents' rows that draw the robot's ROI pixels in its
    views (per-view blending weight above ``min_weight``, :func:`roi_weights`).

    Args:
        fused, source_agent, agents: the vote's map and provenance (``VoteReport.source_agent`` / ``agents``).
        robot: the robot's agent id (in ``agents``).
        subset: that robot's shared subset as the server holds it (the vote's input).
        views: its ROI views (as :func:`roi_weights`; the server's uploaded keyframes with their ROI), at most
            ``max_views`` of them evenly spaced (None: all of them).
        min_weight: another agent's row that draws more than this (pixels of blending weight per view) of the robot's
            ROI is dropped (>= 0). Default sim (``docs/sharing.md``): 0.01 keeps the robot's region within 0.1 dB of
            its subset alone, 0.05 within 0.7 dB, at the cost of 0.2–0.6 dB on the other robots' regions.
        backend: rasterizer backend.

    Returns:
        (map, stats): the robot's own rows first, then the others' kept rows in the vote's order; stats
        ``{"own": rows, "others_kept", "others_dropped", "views", "kept": {agent id: rows in the map}}``.

    Raises:
        ValueError: ``robot`` not in ``agents``, or provenance of the wrong length.
    """
    if robot not in agents:
        raise ValueError(f"unknown robot {robot!r}")
    src = np.asarray(source_agent, np.int64).reshape(-1)
    if len(src) != len(fused):
        raise ValueError(f"source_agent has {len(src)} rows for a map of {len(fused)}")
    i = list(agents).index(robot)
    others = fused.take(src != i)
    vs = _roi_views(views, max_views)
    w = roi_weights(GaussianArrays.concat([subset, others]), vs, backend)[len(subset):]
    keep = ~(w > min_weight)
    out = GaussianArrays.concat([subset, others.take(keep)])
    src_o = src[src != i]
    kept = {a: (len(subset) if j == i else int((keep & (src_o == j)).sum())) for j, a in enumerate(agents)}
    return out, {"own": len(subset), "others_kept": int(keep.sum()), "others_dropped": int((~keep).sum()),
                 "views": len(vs), "kept": kept}


def provenance_rows(first_row: Mapping[str, int], kept: Mapping[str, int], n_rows: int) -> tuple[list, np.ndarray]:
    """The per-row agent of a fused map from its provenance (``FuseResult.first_row`` / ``kept``: rows
    ``[first_row[a], first_row[a] + kept[a])`` came from agent ``a``).

    Returns:
        (agents, source_agent): agent ids in row order, and (n_rows,) int64 index into them of each row's agent.
    Raises:
        ValueError: ranges that overlap, leave rows out, or run past ``n_rows``.
    """
    agents = sorted(first_row, key=lambda a: int(first_row[a]))
    src = np.full(int(n_rows), -1, np.int64)
    for i, a in enumerate(agents):
        lo, n = int(first_row[a]), int(kept.get(a, 0))
        if lo < 0 or lo + n > n_rows or (src[lo:lo + n] >= 0).any():
            raise ValueError(f"provenance of agent {a!r} (rows {lo}..{lo + n}) does not fit a map of {n_rows} rows")
        src[lo:lo + n] = i
    if (src < 0).any():
        raise ValueError(f"{int((src < 0).sum())} rows of the fused map have no provenance")
    return agents, src


#: :func:`with_own_map`'s cull threshold (pixels of blending weight of the robot's ROI per view), a tenth of
#: :func:`for_robot`'s: measured on the default sim (``docs/sharing.md``, "The team map made on board")
ON_BOARD_MIN_WEIGHT = 0.001


def with_own_map(fused: GaussianArrays, first_row: Mapping[str, int], kept: Mapping[str, int], robot: str,
                 own_map: GaussianArrays, views: Sequence, *, min_weight: float = ON_BOARD_MIN_WEIGHT,
                 max_views: Optional[int] = None, backend: str = "auto") -> tuple[GaussianArrays, dict]:
    """The team map as a robot should load it, made on the robot: its own WHOLE map, and the other robots' rows of a
    vote (the team vote or ``Fuse(for_agent=robot)``) except those that draw the robot's ROI in its own views
    (``docs/sharing.md``, "The team map for one robot").

    :func:`for_robot` on the server can only keep what the robot shared: its subset, fine-tuned to render its ROI
    alone, holds a bounded share of the map, so the robot's region there is never quite its own map's. On the robot
    the whole map is at hand: with it in place of the subset, what the robot sees of its own region is its own map's,
    up to the others' rows that draw less than ``min_weight`` of its ROI per view.

    Args:
        fused: a vote's map as downloaded (``FusionClient.download_fused``), M rows, world frame.
        first_row, kept: its provenance (``FuseResult.first_row`` / ``kept``); the refined team map has none.
        robot: the robot's agent id; its rows in ``fused`` are replaced by ``own_map``.
        own_map: the robot's own map (``Mapper.gmap`` as arrays, or its ``map.ply``), world frame.
        views: its ROI views (:func:`roi_weights`): every keyframe it holds, with its ROI mask. A robot culls in all of
            them (``max_views`` None): culled in the few ROI views it uploads, others' rows that draw its region from
            the views in between stay, and on long missions they cost its region up to 0.18 dB
            (``docs/sharing.md``, "The team map made on board").
        min_weight: another robot's row that draws more than this (pixels of blending weight per view) of the robot's
            ROI is dropped (>= 0). 0.001, a tenth of :func:`for_robot`'s: on the default sim (3 seeds) the robots'
            regions against their own maps are at worst −0.01 / −0.05 dB, against −0.10 / −0.25 at 0.01, and each
            robot keeps about two thirds / half as many of the other robot's rows (``docs/sharing.md``, "The team
            map made on board").
        backend: as :func:`for_robot`.
        max_views: at most this many of ``views``, evenly spaced (None: all of them).
    Returns:
        (map, stats) as :func:`for_robot`: the robot's own map's rows first.
    Raises:
        ValueError: provenance that does not fit ``fused``; a robot the provenance does not name.
    """
    agents, src = provenance_rows(first_row, kept, len(fused))
    if robot not in agents:
        raise ValueError(f"the fused map has no rows of robot {robot!r} (agents: {', '.join(agents)})")
    return for_robot(fused, src, agents, robot, own_map, views, min_weight=min_weight, max_views=max_views,
                     backend=backend)
