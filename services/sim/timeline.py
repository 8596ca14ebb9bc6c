"""The fused map while the robots map (:class:`FusedTimeline`): a vote fuse whenever a new subset reaches the
fusion server, scored after the missions (paper Sec. III-E)."""

from __future__ import annotations

import logging
from typing import Dict, List, Optional

from gausslite.evaluation import evaluate_fused

log = logging.getLogger("gausslite_services.sim")  # one logger for the whole simulation


class FusedTimeline:
    """The fused map while the robots map: whenever an agent's latest complete subset changes on the fusion server,
    a vote fuse (no refinement) is run and the fused map downloaded; :meth:`scores` scores them afterwards, so the
    scoring takes nothing from the missions.

    Args:
        fusion: a ``FusionClient``. voxel_size: δ (m). contest_radius: vote neighbourhood (voxels).
    """

    def __init__(self, fusion, voxel_size: float, contest_radius: int) -> None:
        self.fusion, self.voxel_size, self.contest_radius = fusion, voxel_size, contest_radius
        self.versions: Dict[str, int] = {}
        self.maps: list = []  # (seconds since the start, {agent: version}, GaussianArrays)

    def poll(self, t: float) -> bool:
        """Fuse and download when a subset changed since the last call (``t``: seconds since the sim started).
        Returns True when it fused. A fusion error is logged and skipped (the timeline is a diagnostic)."""
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
            self.maps.append((t, dict(latest), maps))
            self.versions = latest
            return True
        except Exception as e:  # noqa: BLE001 - a diagnostic must not fail the simulation
            log.warning("fused timeline: fuse at %.0f s failed: %s", t, e)
            return False

    def scores(self, frames_by_task: Dict[str, tuple], backend: str = "auto", stride: int = 5,
               task_of: Optional[Dict[str, str]] = None) -> List[dict]:
        """``[{"t": s, "versions": {...}, "n_gaussians": N, "roi_psnr": {task: dB}, "roi_psnr_for_robot": {task:
        dB}}]``: every fused team map scored on each task's ROI (every ``stride``-th frame of ``frames_by_task[task] =
        (dataset, frames)``), and each task on the map made for its robot (``task_of``: agent id → task id)."""
        out = []
        for t, versions, maps in self.maps:
            g = maps[""].to_gaussian_map()
            row = {"t": t, "versions": versions, "n_gaussians": len(maps[""]),
                   "roi_psnr": {k: evaluate_fused(g, fr[::stride], ds.annotations, k, backend)
                                for k, (ds, fr) in frames_by_task.items()}, "roi_psnr_for_robot": {}}
            for a, task in (task_of or {}).items():
                if a in maps and task in frames_by_task:
                    ds, fr = frames_by_task[task]
                    row["roi_psnr_for_robot"][task] = evaluate_fused(maps[a].to_gaussian_map(), fr[::stride],
                                                                     ds.annotations, task, backend)
            out.append(row)
        return out
