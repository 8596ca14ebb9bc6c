"""Prometheus metrics of the parser service (see ``docs/fusion-and-deploy.md``, "Metrics").

:class:`MeteredParser` wraps the ``gausslite.v1.Parser`` servicer and records, per ``Parse`` call:

* ``gausslite_parser_requests_total{outcome,backend}`` — ``outcome`` is ``ok`` or the status code name
  of a rejected call (``invalid_argument``, ...); ``backend`` is the backend that answered (``rules``
  when an LLM backend fell back), empty for rejected calls;
* ``gausslite_parser_request_seconds`` — histogram of the handler's latency.
"""

from __future__ import annotations

import time

from prometheus_client import CollectorRegistry, Counter, Histogram

from gausslite_services.common.metrics import LATENCY_BUCKETS, ServicerProxy


class ParserMetrics:
    """Metric families of one parser server (own registry unless ``registry`` is given)."""

    def __init__(self, registry: CollectorRegistry | None = None):
        self.registry = registry if registry is not None else CollectorRegistry()
        self.requests = Counter("gausslite_parser_requests", "Parse calls", ["outcome", "backend"],
                                registry=self.registry)
        self.seconds = Histogram("gausslite_parser_request_seconds", "Parse latency", buckets=LATENCY_BUCKETS,
                                 registry=self.registry)


class MeteredParser(ServicerProxy):
    """Servicer proxy recording :class:`ParserMetrics` around ``Parse``; other attributes pass through."""

    def Parse(self, request, context):  # noqa: N802
        t0 = time.perf_counter()
        outcome, backend = "error", ""
        try:
            reply = self._inner.Parse(request, context)
            outcome, backend = "ok", reply.backend
            return reply
        finally:
            code = context.code() if outcome != "ok" and hasattr(context, "code") else None
            if code is not None:
                outcome = getattr(code, "name", str(code)).lower()
            self.metrics.requests.labels(outcome, backend).inc()
            self.metrics.seconds.observe(time.perf_counter() - t0)


__all__ = ["ParserMetrics", "MeteredParser"]
