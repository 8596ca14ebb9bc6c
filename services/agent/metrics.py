"""Prometheus metrics of the agent service (see ``docs/fusion-and-deploy.md``, "Metrics").

:class:`AgentCollector` is a custom collector: at every scrape it reads the missions of an
:class:`gausslite_services.agent.server.AgentServicer` through their public state (``AgentRuntime.status()`` and
the ``pushes`` records), so the mapping loop carries no metrics code. Counters are sums over the
process's missions (missions are kept for the life of the process, so the sums never decrease).

Families (label ``agent`` = the mission's agent id):

* ``gausslite_agent_frames_received_total``, ``gausslite_agent_frames_mapped_total``
* ``gausslite_agent_frames_failed_total`` — frames whose step failed (logged, skipped; the mission maps on),
  ``gausslite_agent_corrections_rejected_total`` — loop-closure corrections of mapped frames that were skipped
* ``gausslite_agent_queue_depth`` — frames waiting for the mapper (current mission)
* ``gausslite_agent_gaussians`` / ``gausslite_agent_active_gaussians`` — current mission's map size
* ``gausslite_agent_pushes_total``, ``gausslite_agent_push_failures_total``
* ``gausslite_agent_push_seconds`` — histogram of successful pushes (subset + keyframes upload)
* ``gausslite_agent_bytes_pushed_total`` — wire bytes of the pushed subsets
* ``gausslite_agent_keyframes_uploaded_total``
* ``gausslite_agent_missions`` — missions by state
* mapping resolutions of the current mission (docs/live.md, "Mapping resolution"):
  ``gausslite_agent_mapping_downscale``, ``gausslite_agent_mapping_width_pixels``,
  ``gausslite_agent_mapping_height_pixels`` (the background), ``gausslite_agent_region_downscale``,
  ``gausslite_agent_region_width_pixels``, ``gausslite_agent_region_height_pixels`` (the task region),
  ``gausslite_agent_keyframe_iterations_measured`` (mean at the background's level),
  ``gausslite_agent_keyframe_iterations_recent`` and ``gausslite_agent_roi_iterations_recent`` (means over the last
  keyframes: iterations, ROI-phase iterations)
"""

from __future__ import annotations

import math
from collections import Counter as _Tally
from typing import Iterable, Sequence

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily

from gausslite_services.common.metrics import LATENCY_BUCKETS


def histogram_buckets(values: Sequence[float], bounds: Sequence[float]) -> list:
    """Cumulative Prometheus buckets ``[(le, count), ..., ("+Inf", n)]`` of ``values`` (seconds)."""
    out = [(repr(float(b)), sum(1 for v in values if v <= b)) for b in bounds]
    out.append(("+Inf", len(values)))
    return out


class AgentCollector:
    """Collects the agent families from ``servicer.missions`` (a dict of ``AgentRuntime``) at scrape time.

    Args:
        servicer: an object with a ``missions`` dict and a ``current`` mission id (``AgentServicer``).
        buckets: push-latency histogram bounds, seconds.
    """

    def __init__(self, servicer, buckets: Sequence[float] = LATENCY_BUCKETS):
        self.servicer = servicer
        self.buckets = tuple(buckets)

    def describe(self) -> Iterable:
        return []  # families depend on the missions; collected at scrape time

    def collect(self) -> Iterable:
        fam = {
            "received": CounterMetricFamily("gausslite_agent_frames_received", "Frames received (streamed or replayed)",
                                            labels=["agent"]),
            "mapped": CounterMetricFamily("gausslite_agent_frames_mapped", "Frames mapped", labels=["agent"]),
            "frames_failed": CounterMetricFamily("gausslite_agent_frames_failed", "Frames whose tracking, mapping or "
                                                 "upload failed (logged and skipped; the mission maps on)",
                                                 labels=["agent"]),
            "corrections_rejected": CounterMetricFamily("gausslite_agent_corrections_rejected", "Loop-closure "
                                                        "corrections of mapped frames that could not be applied "
                                                        "(skipped)", labels=["agent"]),
            "pushes": CounterMetricFamily("gausslite_agent_pushes", "Successful subset pushes", labels=["agent"]),
            "failures": CounterMetricFamily("gausslite_agent_push_failures", "Failed push attempts", labels=["agent"]),
            "bytes": CounterMetricFamily("gausslite_agent_bytes_pushed", "Wire bytes of pushed subsets",
                                         labels=["agent"]),
            "keyframes": CounterMetricFamily("gausslite_agent_keyframes_uploaded", "Keyframes uploaded",
                                             labels=["agent"]),
        }
        queue = GaugeMetricFamily("gausslite_agent_queue_depth", "Frames waiting for the mapper (current mission)",
                                  labels=["agent"])
        gaussians = GaugeMetricFamily("gausslite_agent_gaussians", "Gaussians in the current mission's map",
                                      labels=["agent"])
        active = GaugeMetricFamily("gausslite_agent_active_gaussians", "Active (ROI) Gaussians, current mission",
                                   labels=["agent"])
        backlog = GaugeMetricFamily("gausslite_agent_push_backlog", "Subset snapshots held for pushing (current "
                                    "mission; 0..2: only the newest is kept while the link is down)", labels=["agent"])
        link_down = GaugeMetricFamily("gausslite_agent_link_down_seconds", "Seconds since the first failed push "
                                      "attempt without an acknowledgement since (0 = link up)", labels=["agent"])
        downscale = GaugeMetricFamily("gausslite_agent_mapping_downscale", "Image downscale the current mission maps "
                                      "at (agent.resolution; 1 = native, 0 = no frame yet)", labels=["agent"])
        kf_iters = GaugeMetricFamily("gausslite_agent_keyframe_iterations_measured", "Mean iterations per keyframe "
                                     "at the current mapping resolution (agent.resolution.target_iters is the target)",
                                     labels=["agent"])
        sizes = resolution_families()
        states = GaugeMetricFamily("gausslite_agent_missions", "Missions by state", labels=["state"])
        push_s = HistogramMetricFamily("gausslite_agent_push_seconds", "Duration of successful pushes",
                                       labels=["agent"])
        sums: dict = {}
        seconds: dict = {}
        tally: _Tally = _Tally()
        missions = dict(getattr(self.servicer, "missions", {}))
        current = getattr(self.servicer, "current", None)
        for mid, rt in missions.items():
            st = rt.status()
            agent = st["agent_id"]
            tally[st["state"]] += 1
            s = sums.setdefault(agent, _Tally())
            s["received"] += st["frames_received"]
            s["mapped"] += st["frames_mapped"]
            s["frames_failed"] += st.get("frames_failed", 0)
            s["corrections_rejected"] += st.get("corrections_rejected", 0)
            s["failures"] += st["push_failures"]
            s["keyframes"] += st["keyframes_uploaded"]
            pushes = list(rt.pusher.pushes)
            s["pushes"] += len(pushes)
            s["bytes"] += sum(int(p.bytes_on_wire) for p in pushes)
            seconds.setdefault(agent, []).extend(float(p.seconds) for p in pushes if math.isfinite(p.seconds))
            if mid == current:
                queue.add_metric([agent], st["frames_queued"])
                gaussians.add_metric([agent], st["n_gaussians"])
                active.add_metric([agent], st["n_active"])
                backlog.add_metric([agent], st["push_backlog"])
                link_down.add_metric([agent], st["link_down_s"])
                downscale.add_metric([agent], st.get("mapping_downscale", 0.0))
                kf_iters.add_metric([agent], st.get("resolution_measured_iters", 0.0))
                for key, f in sizes.items():
                    f.add_metric([agent], st.get(key, 0))
        for agent, s in sorted(sums.items()):
            for key, f in fam.items():
                f.add_metric([agent], s[key])
            vals = seconds.get(agent, [])
            push_s.add_metric([agent], histogram_buckets(vals, self.buckets), sum(vals))
        for state, n in sorted(tally.items()):
            states.add_metric([state.lower()], n)
        yield from fam.values()
        yield from (queue, gaussians, active, backlog, link_down, downscale, kf_iters, *sizes.values(), states, push_s)


def resolution_families() -> dict:
    """Empty gauge families (label ``agent``) of the current mission's mapping sizes and iterations, keyed by the
    ``AgentRuntime.status()`` field each reports (:meth:`gausslite.mapping.resolution.ResolutionGovernor.status`)."""
    spec = {
        "mapping_width": ("gausslite_agent_mapping_width_pixels", "Width of the images the current mission maps the "
                          "background at (pixels; 0 = no frame yet)"),
        "mapping_height": ("gausslite_agent_mapping_height_pixels", "Height of the images the current mission maps "
                           "the background at (pixels; 0 = no frame yet)"),
        "region_downscale": ("gausslite_agent_region_downscale", "Image downscale the current mission maps its task "
                             "region at (the background's without mapper.detail; 1 = native, 0 = no frame yet)"),
        "region_width": ("gausslite_agent_region_width_pixels", "Width of the task region's images (pixels)"),
        "region_height": ("gausslite_agent_region_height_pixels", "Height of the task region's images (pixels)"),
        "keyframe_iters_recent": ("gausslite_agent_keyframe_iterations_recent", "Mean iterations per keyframe over "
                                  "the current mission's last 10 keyframes"),
        "roi_iters_recent": ("gausslite_agent_roi_iterations_recent", "Mean ROI-phase iterations per keyframe over "
                             "the current mission's last 10 keyframes that showed the task region "
                             "(agent.resolution.roi_target_iters is the target)"),
    }
    return {key: GaugeMetricFamily(name, doc, labels=["agent"]) for key, (name, doc) in spec.items()}


def agent_registry(servicer) -> CollectorRegistry:
    """A fresh registry holding an :class:`AgentCollector` of ``servicer``."""
    registry = CollectorRegistry()
    registry.register(AgentCollector(servicer))
    return registry


__all__ = ["AgentCollector", "agent_registry", "histogram_buckets", "resolution_families"]
