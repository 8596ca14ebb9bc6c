"""The fused maps while the robots map (:class:`FusedTimeline`): a vote fuse whenever a new subset reaches the fusion
server, and the team map the server keeps refined in the background (``fusion.team_map``) as it is served, scored
after the missions by the library (:func:`gausslite.team.scoring.score_timeline`; paper Sec. III-E)."""

from __future__ import annotations

import logging
from typing import Dict, List, Optional, Tuple

import grpc

from gausslite.team import score_timeline

log = logging.getLogger("gausslite_services.sim")  # one logger for the whole simulation


class FusedTimeline:
    """The fused maps while the robots map. Whenever an agent's latest complete subset changes on the fusion server, a
    vote fuse (no refinement) is run and downloaded, for the team and for each robot; at every poll the served team
    map (``Fuse(team_map=True)``) is asked for, and a new version downloaded. A row is kept whenever either changes;
    :meth:`scores` scores them afterwards, so the scoring takes nothing from the missions.

    Args:
        fusion: a ``FusionClient``. voxel_size: δ (m). contest_radius: vote neighbourhood (voxels).
    """

    def __init__(self, fusion, voxel_size: float, contest_radius: int) -> None:
        self.fusion, self.voxel_size, self.contest_radius = fusion, voxel_size, contest_radius
        self.versions: Dict[str, int] = {}
        #: rows: (seconds since the start, {agent: version}, {"" | agent: GaussianArrays}, served team map or None)
        self.maps: list = []
        #: team-map version → (GaussianArrays, FuseResult when first served, sim time then)
        self.served: Dict[int, tuple] = {}
        self.team_map = True  # False once the server says it keeps none
        self._vote: Optional[dict] = None
        self._seen: Optional[Tuple[int, bool]] = None  # (team-map version, current) at the last poll

    def poll(self, t: float) -> bool:
        """Fuse and download when a subset changed since the last call, and ask for the served team map
        (``t``: seconds since the sim started). Returns True when a row was added. A fusion error is logged and
        skipped (the timeline is a diagnostic)."""
        changed = self._poll_vote(t)
        seen = self._poll_served(t)
        if seen is not None and seen != self._seen:
            changed = True
        self._seen = seen if seen is not None else self._seen
        if changed and self._vote is not None:
            self.maps.append((t, dict(self.versions), self._vote, self._seen))
        return changed

    def _poll_vote(self, t: float) -> bool:
        try:
            agents = self.fusion.stats().get("agents", {})
            latest = {a: int(v["latest_map_version"]) for a, v in agents.items() if v.get("has_complete_subset")}
            if not latest or latest == self.versions:
                return False
            res = self.fusion.fuse("vote", voxel_size=self.voxel_size, contest_radius=self.contest_radius)
            maps = {"": self.fusion.download_fused(res.fused_version)}
            for a in sorted(latest):  # the team map as each robot uses it
                r = self.fusion.fuse("vote", voxel_size=self.voxel_size, contest_radius=self.contest_radius, for_agent=a)
                maps[a] = self.fusion.download_fused(r.fused_version)
            self._vote, self.versions = maps, latest
            return True
        except Exception as e:  # noqa: BLE001 - a diagnostic must not fail the simulation
            log.warning("fused timeline: fuse at %.0f s failed: %s", t, e)
            return False

    def _poll_served(self, t: float) -> Optional[Tuple[int, bool]]:
        """(version, current) of the team map the server serves now, downloading a new version; None when it serves
        none (yet, or before any subset: not asked then)."""
        if not self.team_map or self._vote is None:
            return None
        try:
            r = self.fusion.fuse(team_map=True)
            if r.fused_version not in self.served:
                self.served[r.fused_version] = (self.fusion.download_fused(r.fused_version), r, t)
            return int(r.fused_version), bool(r.team_map_current)
        except grpc.RpcError as e:
            if e.code() == grpc.StatusCode.FAILED_PRECONDITION:
                self.team_map = False
                log.info("fused timeline: the fusion server keeps no team map (%s)", e.details())
            elif e.code() != grpc.StatusCode.NOT_FOUND:
                log.warning("fused timeline: team map at %.0f s: %s", t, e.details())
            return None
        except Exception as e:  # noqa: BLE001 - a diagnostic must not fail the simulation
            log.warning("fused timeline: team map at %.0f s failed: %s", t, e)
            return None

    def scores(self, frames_by_task: Dict[str, tuple], backend: str = "auto", stride: Optional[int] = None,
               task_of: Optional[Dict[str, str]] = None) -> List[dict]:
        """The rows kept, scored after the missions (:func:`gausslite.team.scoring.score_timeline`: each vote on every
        task's ROI, each task on the map made for its robot, ``task_of``: agent id → task id, and the team map served
        then; ``frames_by_task``: task id → ``(dataset, frames)``, every ``stride``-th frame scored)."""
        return score_timeline(self.maps, self.served, frames_by_task, backend, stride, task_of)
