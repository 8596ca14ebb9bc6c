"""The fusion server's side of the simulation's scoring: the fusion settings (:func:`fuse_settings`), the fused maps
the server makes (:func:`fuse_on_server`: every map of :data:`gausslite.team.figures.FUSED_KEYS` but the one each
robot makes on board), the keyframe poses each robot uploaded (:func:`uploaded_keyframe_poses`) and the final subsets
its store holds, for what covers each robot's ROI (:func:`roi_cover_report`). The scoring itself is the library's
(:mod:`gausslite.team.scoring`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Dict, List

import grpc

from gausslite.config import GaussLiteConfig
from gausslite.team import AgentPlan, cover_report
from gausslite.wire.decode import assemble
from gausslite.wire.format import WireLimits
from gausslite_services.fusion_server.store import SqliteFusionStore

log = logging.getLogger("gausslite_services.sim")  # one logger for the whole simulation


def fuse_settings(cfg: GaussLiteConfig, realtime: bool = False) -> dict:
    """The simulation's fusion settings (:meth:`gausslite.config.SimFuse.settings` of ``cfg.sim.fuse``): live
    runs (``realtime``) contest with ``live_contest_radius`` (default 0, the paper's per-voxel rule): measured
    live, the neighbourhood contest empties an owner's voxels next to another robot's denser task region
    (``docs/sharing.md``)."""
    return cfg.sim.fuse.settings(realtime)


def roi_cover_report(out: Path, plans: List[AgentPlan], eval_frames: Dict[str, tuple], fz: dict,
                     backend: str = "auto", stride: int = 2) -> dict:
    """What covers each robot's ROI in the team (vote) map (:func:`gausslite.team.scoring.cover_report`): the final
    subsets are read from the fusion server's store in ``out/data/fusion`` and voted again with the sim's settings
    (``fz``: :func:`fuse_settings`; the same vote as the server's), and scored on every ``stride``-th frame of each
    robot's sequence with its task's ground-truth ROI. Writes ``renders/cover_<task>.png``.

    Returns:
        agent id → the diagnosis (``mass``, ``foreign``, ``top_foreign`` (5), ``own_missing``) plus ``image``.
    """
    store = SqliteFusionStore(out / "data" / "fusion")
    try:
        subsets = {a: assemble(store.chunk_data(a, v), WireLimits())[0] for a, v in store.latest_complete().items()}
    finally:
        store.close()
    return cover_report(out, plans, eval_frames, subsets, fz["voxel_size"], fz["contest_radius"], backend, stride)


def uploaded_keyframe_poses(fusion, plans: List[AgentPlan]) -> Dict[str, dict]:
    """Agent id → {frame id → (4, 4) camera-to-world}: the keyframes each robot uploaded, at the refined poses they
    carry (the ``keyframes`` protocol). An agent whose poses cannot be read is logged and left out."""
    kf_poses = {}
    for p in plans:
        try:
            kf_poses[p.name] = {int(k["frame_id"]): k["c2w"] for k in fusion.keyframe_poses(p.name)}
        except grpc.RpcError as e:
            log.warning("no keyframe poses of %s: %s", p.name, e.details())
    return kf_poses


def fuse_on_server(fusion, key: str, plans: List[AgentPlan], fz: dict):
    """Run the fusion of report key ``key`` (one of :data:`gausslite.team.figures.FUSED_KEYS` but ``with_own``) on
    the server and download the result; ``for_robot`` fuses once per agent (``for_agent``). ``fz``:
    :func:`fuse_settings`.

    Returns:
        ``(gmaps, res)``: agent id → the fused ``GaussianMap`` its task is scored on, and the last fuse result
        (:func:`gausslite.team.scoring.score_fused_maps`'s ``fuse``); ``(None, None)`` when the server makes none.
    """
    if key == "team_map":
        res = _current_team_map(fusion)
        if res is None:
            return None, None
        g = fusion.download_fused(res.fused_version).to_gaussian_map()
        return {p.name: g for p in plans}, res
    method = "concat" if key == "concat" else "vote"
    gmaps, res = {}, None
    held = fusion.stats().get("agents", {}) if key == "refine" else {}
    if key == "refine" and not any(v.get("keyframes") for v in held.values()):
        log.warning("no refinement: no robot sent a view for it (agent.refine_views)")
        return None, None
    for p in (plans if key == "for_robot" else [None]):
        res = fusion.fuse(method, refine=(key == "refine"), refine_iters=fz["refine_iters"],
                          voxel_size=fz["voxel_size"], contest_radius=fz["contest_radius"] if method == "vote" else None,
                          for_agent=p.name if p is not None else None,
                          progress=(lambda f, m, k=key: log.info("  %s %3.0f%% %s", k, 100 * f, m)))
        g = fusion.download_fused(res.fused_version).to_gaussian_map()
        for q in ([p] if p is not None else plans):
            gmaps[q.name] = g
    return gmaps, res


def _current_team_map(fusion, timeout_s: float = 600.0):
    """The team map the fusion server serves once it is current (made from the final subsets and views), waited for
    up to ``timeout_s``; None when the server keeps none (logged). Raises TimeoutError when it is not current in
    time."""
    t0 = time.monotonic()
    while True:
        try:
            res = fusion.fuse(team_map=True)
            if res.team_map_current:
                return res
        except grpc.RpcError as e:
            if e.code() == grpc.StatusCode.FAILED_PRECONDITION:
                log.info("no team map: %s", e.details())
                return None
            if e.code() != grpc.StatusCode.NOT_FOUND:
                raise
        if time.monotonic() - t0 > timeout_s:
            raise TimeoutError(f"the team map was not current after {timeout_s:.0f} s")
        time.sleep(1.0)
