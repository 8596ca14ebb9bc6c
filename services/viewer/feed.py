"""``gausslite view --fusion HOST:PORT``: follow a fusion server live in the browser viewer.

:class:`FusionFeed` polls the fusion server through :class:`gausslite_services.fusion_server.client.FusionClient`
every ``poll_s`` seconds:

* ``GetStats`` → the GUI panel (agents, tasks, subset versions, Gaussians, share %, bytes on the wire,
  keyframes; fused versions);
* a new ``latest_fused_version`` → ``DownloadFused`` → :meth:`MapViewer.set_map` (``fused vN``);
* ``GetKeyframePoses`` → each agent's keyframe trajectory and camera frusta.

Transient errors (server restarting: UNAVAILABLE, DEADLINE_EXCEEDED) are shown in the panel and retried
at the next poll; the feed never exits on them.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Dict, List, Optional

import grpc

from gausslite.viewer.app import KeyframePose, MapViewer

log = logging.getLogger(__name__)


def stats_markdown(stats: dict, shown_version: int = 0, error: str = "") -> str:
    """The panel text: a Markdown table of agents and one of fused versions (newest first, at most 5).

    Args:
        stats: :meth:`FusionClient.stats` output.
        shown_version: fused version on screen (0 = none).
        error: last poll error, shown when non-empty.
    """
    lines = ["**Agents**", "", "| agent | subset v | Gaussians | share | bytes | B/G | keyframes |",
             "|---|---|---|---|---|---|---|"]
    for aid, a in sorted(stats.get("agents", {}).items()):
        lines.append(f"| {aid} | {a['latest_map_version'] or '-'} | {a['gaussians_received']:,} | "
                     f"{a['share_pct']:.1f} % | {a['bytes_on_wire']:,} | {a['bytes_per_gaussian']:.1f} | "
                     f"{a['keyframes']} |")
    if not stats.get("agents"):
        lines.append("| (none yet) | | | | | | |")
    lines += ["", f"**Fused versions** (showing v{shown_version})" if shown_version else "**Fused versions**", "",
              "| v | method | Gaussians | refined | s |", "|---|---|---|---|---|"]
    fused = list(stats.get("fused", []))[::-1][:5]
    for f in fused:
        lines.append(f"| {f['fused_version']} | {f['method']} | {f['n_gaussians']:,} | "
                     f"{'yes' if f['refined'] else 'no'} | {f['seconds']:.2f} |")
    if not fused:
        lines.append("| (none yet) | | | | |")
    if error:
        lines += ["", f"⚠ {error}"]
    return "\n".join(lines)


def keyframes_by_agent(poses: List[dict]) -> Dict[str, List[KeyframePose]]:
    """:meth:`FusionClient.keyframe_poses` rows → ``{agent_id: [KeyframePose, ...]}``."""
    out: Dict[str, List[KeyframePose]] = {}
    for p in poses:
        out.setdefault(p["agent_id"], []).append(KeyframePose(p["c2w"], p["fx"], p["fy"], p["width"], p["height"],
                                                              p["frame_id"]))
    return out


class FusionFeed:
    """Polls a fusion server and updates a :class:`MapViewer`.

    Args:
        viewer: the viewer to drive.
        client: a ``FusionClient`` (or an object with ``stats``, ``download_fused``, ``keyframe_poses``).
        poll_s: seconds between polls (> 0).
    Attributes:
        shown_version: fused version on screen (0 = none). polls: completed polls. last_error: text.
    """

    def __init__(self, viewer: MapViewer, client, poll_s: float = 1.0):
        if not poll_s > 0:
            raise ValueError(f"poll_s must be > 0, got {poll_s}")
        self.viewer, self.client, self.poll_s = viewer, client, float(poll_s)
        self.shown_version = 0
        self.polls = 0
        self.last_error = ""
        self._kf_signature: tuple = ()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None

    def poll_once(self) -> bool:
        """One poll. Returns True when a new fused map was loaded. Transient gRPC errors are recorded in
        :attr:`last_error` (and the panel) and swallowed; other errors propagate."""
        try:
            stats = self.client.stats()
            latest = int(stats.get("latest_fused_version", 0))
            poses = self.client.keyframe_poses()
            sig = tuple((p["agent_id"], p["frame_id"]) for p in poses)
            if sig != self._kf_signature:
                self.viewer.set_keyframes(keyframes_by_agent(poses))
                self._kf_signature = sig
            loaded = False
            if latest and latest != self.shown_version:
                fused = self.client.download_fused(latest)
                self.viewer.set_map(fused, label=f"fused v{latest}")
                self.shown_version = latest
                log.info("showing fused version %d (%d Gaussians)", latest, len(fused))
                loaded = True
            self.last_error = ""
            self.viewer.set_panel(stats_markdown(stats, self.shown_version))
            self.polls += 1
            return loaded
        except grpc.RpcError as e:
            self.last_error = f"fusion server: {e.code().name}: {e.details()}"
            log.warning("%s (retrying in %.1f s)", self.last_error, self.poll_s)
            self.viewer.set_panel(stats_markdown({}, self.shown_version, self.last_error))
            return False

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                self.poll_once()
            except Exception as e:  # noqa: BLE001 - keep following; the error is shown and logged
                self.last_error = f"{type(e).__name__}: {e}"
                log.exception("viewer poll failed")
            self._stop.wait(max(0.0, self.poll_s - (time.monotonic() - t0)))

    def start(self) -> "FusionFeed":
        """Poll in a background thread until :meth:`stop`."""
        self._thread = threading.Thread(target=self._run, name="gausslite-viewer-feed", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop polling (waits up to ``timeout_s`` for a running poll)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)


__all__ = ["FusionFeed", "stats_markdown", "keyframes_by_agent"]
