"""Prometheus metrics of the fusion server (see ``docs/fusion-and-deploy.md``, "Metrics").

:class:`FusionMetrics` holds the metric families in the server's own registry; :class:`MeteredFusion`
wraps a servicer and records them around the RPC handlers without touching their logic:

* ``UploadSubset`` — the request stream is wrapped to count chunk messages and their bytes, the
  returned ``UploadAck`` gives the newly stored chunks, the subset size and completeness; the time from
  the call's start to the ack is the upload-ack latency;
* ``UploadKeyframes`` — keyframes stored per agent (from the ``KeyframeAck``);
* ``Fuse`` — the streamed result gives the method and the server-side duration; a stream that ends
  with an error or is cancelled counts as ``outcome="error"`` / ``"cancelled"``.

Every other attribute (``OpenSession``, ``GetStats``, …, and RPCs added later) passes through unchanged.
"""

from __future__ import annotations

import time

import grpc
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from gausslite_services.common.metrics import JOB_BUCKETS, LATENCY_BUCKETS, ServicerProxy

_METHODS = {1: "vote", 2: "concat"}


class FusionMetrics:
    """Metric families of one fusion server.

    Args:
        registry: the server's registry (a fresh one when None).
    Attributes (Prometheus names):
        uploads: ``gausslite_fusion_uploads_total{agent}`` acknowledged UploadSubset calls.
        upload_errors: ``gausslite_fusion_upload_errors_total`` rejected UploadSubset calls (no agent
            label: a rejected call's agent id is unchecked input).
        subsets: ``gausslite_fusion_subsets_completed_total{agent}`` map versions that became complete.
        chunks_received: ``gausslite_fusion_chunks_received_total{agent}`` chunk messages received.
        chunks_stored: ``gausslite_fusion_chunks_stored_total{agent}`` chunks newly persisted.
        bytes_received: ``gausslite_fusion_bytes_received_total{agent}`` chunk bytes received.
        gaussians: ``gausslite_fusion_gaussians{agent}`` Gaussians in the agent's latest complete subset.
        keyframes: ``gausslite_fusion_keyframes_stored_total{agent}`` keyframes newly stored.
        ack_seconds: ``gausslite_fusion_upload_ack_seconds{agent}`` histogram, call start → ack.
        fuse_runs: ``gausslite_fusion_fuse_runs_total{method,outcome}`` Fuse calls (ok/error/cancelled).
        fuse_seconds: ``gausslite_fusion_fuse_duration_seconds{method}`` histogram of fusion work time.
        fused_gaussians: ``gausslite_fusion_fused_gaussians`` Gaussians in the newest fused map.
        fuse_mode_available: ``gausslite_fusion_fuse_mode_available{mode}`` 1 when this server's install runs the fuse
            mode (vote, concat, for_agent, refine), 0 when it lacks the extra the mode needs.
    """

    def __init__(self, registry: CollectorRegistry | None = None):
        self.registry = registry if registry is not None else CollectorRegistry()
        r = self.registry
        self.uploads = Counter("gausslite_fusion_uploads", "Acknowledged UploadSubset calls", ["agent"], registry=r)
        self.upload_errors = Counter("gausslite_fusion_upload_errors", "Rejected UploadSubset calls", registry=r)
        self.subsets = Counter("gausslite_fusion_subsets_completed", "Subsets (map versions) that became complete",
                               ["agent"], registry=r)
        self.chunks_received = Counter("gausslite_fusion_chunks_received", "Wire chunks received", ["agent"],
                                       registry=r)
        self.chunks_stored = Counter("gausslite_fusion_chunks_stored", "Wire chunks newly persisted", ["agent"],
                                     registry=r)
        self.bytes_received = Counter("gausslite_fusion_bytes_received", "Wire chunk bytes received", ["agent"],
                                      registry=r)
        self.gaussians = Gauge("gausslite_fusion_gaussians", "Gaussians in the agent's latest complete subset",
                               ["agent"], registry=r)
        self.keyframes = Counter("gausslite_fusion_keyframes_stored", "Keyframes newly stored", ["agent"], registry=r)
        self.ack_seconds = Histogram("gausslite_fusion_upload_ack_seconds",
                                     "UploadSubset latency from the call's start to the ack", ["agent"],
                                     buckets=LATENCY_BUCKETS, registry=r)
        self.fuse_runs = Counter("gausslite_fusion_fuse_runs", "Fuse calls", ["method", "outcome"], registry=r)
        self.fuse_seconds = Histogram("gausslite_fusion_fuse_duration_seconds", "Fusion work time (server side)",
                                      ["method"], buckets=JOB_BUCKETS, registry=r)
        self.fused_gaussians = Gauge("gausslite_fusion_fused_gaussians", "Gaussians in the newest fused map",
                                     registry=r)
        self.fuse_mode_available = Gauge("gausslite_fusion_fuse_mode_available",
                                         "1 when this server's install runs the fuse mode, 0 when it lacks its extra",
                                         ["mode"], registry=r)


class MeteredFusion(ServicerProxy):
    """A ``gausslite.v1.Fusion`` servicer proxy recording :class:`FusionMetrics` (see the module docstring).

    Args:
        inner: the real servicer (``FusionServicer``); every attribute not overridden here is its own.
        metrics: where to record.
    """

    def UploadSubset(self, request_iterator, context):  # noqa: N802
        m = self.metrics
        t0 = time.perf_counter()
        seen = {"agent": ""}

        def counted():
            for msg in request_iterator:
                kind = msg.WhichOneof("payload")
                if kind == "header":
                    seen["agent"] = msg.header.agent_id
                elif kind == "chunk" and seen["agent"]:
                    m.chunks_received.labels(seen["agent"]).inc()
                    m.bytes_received.labels(seen["agent"]).inc(len(msg.chunk))
                yield msg

        try:
            ack = self._inner.UploadSubset(counted(), context)
        except BaseException:
            m.upload_errors.inc()
            raise
        agent = ack.agent_id or seen["agent"]
        m.uploads.labels(agent).inc()
        m.chunks_stored.labels(agent).inc(ack.newly_stored)
        if ack.complete and ack.newly_stored:
            m.subsets.labels(agent).inc()
        if ack.complete and ack.is_latest:
            m.gaussians.labels(agent).set(ack.n_gaussians)
        m.ack_seconds.labels(agent).observe(time.perf_counter() - t0)
        return ack

    def UploadKeyframes(self, request_iterator, context):  # noqa: N802
        ack = self._inner.UploadKeyframes(request_iterator, context)
        if ack.agent_id:
            self.metrics.keyframes.labels(ack.agent_id).inc(ack.stored)
        return ack

    def Fuse(self, request, context):  # noqa: N802
        m = self.metrics
        method = _METHODS.get(int(request.method) or 1, "unknown")
        outcome = "cancelled"
        try:
            for msg in self._inner.Fuse(request, context):
                if msg.done:  # counted before the client can see the result (and scrape right after it)
                    outcome = "ok"
                    m.fuse_seconds.labels(method).observe(msg.result.seconds)
                    m.fused_gaussians.set(msg.result.n_gaussians)
                    m.fuse_runs.labels(method, outcome).inc()
                yield msg
        except grpc.RpcError:
            outcome = "error"
            raise
        except GeneratorExit:
            raise
        except BaseException:  # context.abort raises a plain Exception in grpcio
            outcome = "error"
            raise
        finally:
            if outcome != "ok":
                m.fuse_runs.labels(method, outcome).inc()


__all__ = ["FusionMetrics", "MeteredFusion"]
