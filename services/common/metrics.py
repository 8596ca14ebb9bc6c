"""Prometheus metrics of the GaussLite services (prometheus-client).

Every server owns a :class:`prometheus_client.CollectorRegistry` (tests start several servers in one
process, so nothing is registered in the global default registry) and serves it over HTTP at
``http://HOST:METRICS_PORT/metrics`` when a metrics port is configured
(:attr:`gausslite_services.common.server.ServerOptions.metrics_port`; ``gausslite serve ... --metrics-port P``).

The metric families of each service live next to it (``services/fusion_server/metrics.py``,
``services/agent/metrics.py``, ``services/parser/metrics.py``); names follow the Prometheus
conventions: ``gausslite_<service>_<what>_<unit>``, counters end in ``_total``, durations are
``_seconds`` histograms, per-robot series carry the label ``agent``.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Optional

from prometheus_client import CollectorRegistry, start_http_server

log = logging.getLogger(__name__)

#: Buckets (seconds) of RPC latency histograms: 1 ms … 2 min.
LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0)
#: Buckets (seconds) of long jobs (fusion with refinement): 10 ms … 30 min.
JOB_BUCKETS = (0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0)


@dataclass
class MetricsEndpoint:
    """A running ``/metrics`` HTTP endpoint: ``host``, bound ``port``; :meth:`stop` shuts it down."""

    host: str
    port: int
    _httpd: object
    _thread: threading.Thread

    @property
    def url(self) -> str:
        """``http://host:port/metrics`` (loopback address when bound to all interfaces)."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "", "::") else self.host
        return f"http://{host}:{self.port}/metrics"

    def stop(self) -> None:
        """Stop serving and close the socket (idempotent)."""
        httpd, self._httpd = self._httpd, None
        if httpd is not None:
            httpd.shutdown()
            httpd.server_close()
            self._thread.join(5.0)


def start_metrics_endpoint(registry: CollectorRegistry, host: str, port: Optional[int]) -> Optional[MetricsEndpoint]:
    """Serve ``registry`` at ``http://host:port/metrics`` from a daemon thread.

    Args:
        registry: the server's own registry.
        host: bind address.
        port: TCP port; ``None`` → no endpoint (metrics off); 0 → an ephemeral port.
    Returns:
        MetricsEndpoint, or None when ``port`` is None.
    Raises:
        RuntimeError: the port cannot be bound. ValueError: port out of range.
    """
    if port is None:
        return None
    if not 0 <= int(port) <= 65535:
        raise ValueError(f"metrics port must be in 0..65535, got {port}")
    try:
        httpd, thread = start_http_server(int(port), addr=host, registry=registry)
    except OSError as e:
        raise RuntimeError(f"cannot bind the metrics endpoint {host}:{port}: {e}") from e
    bound = int(httpd.server_port)
    log.info("metrics on http://%s:%d/metrics", host, bound)
    return MetricsEndpoint(host, bound, httpd, thread)


class ServicerProxy:
    """Base of metered servicer proxies: every attribute not defined by the subclass is the wrapped
    servicer's, so RPCs without metrics (and RPCs added later) pass through unchanged.

    Args:
        inner: the real servicer. metrics: the service's metrics object (``.registry``).
    """

    def __init__(self, inner, metrics):
        self._inner = inner
        self.metrics = metrics

    def __getattr__(self, name):
        return getattr(self._inner, name)


def metrics_port_from(value, env_value: Optional[str] = None) -> Optional[int]:
    """CLI/env metrics port → ``ServerOptions.metrics_port``: 0 or unset → None (off), else the port.

    Raises:
        ValueError: not an integer, or out of 0..65535.
    """
    raw = value if value is not None else env_value
    if raw is None or str(raw).strip() == "":
        return None
    try:
        port = int(raw)
    except (TypeError, ValueError):
        raise ValueError(f"metrics port must be an integer, got {raw!r}") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"metrics port must be in 0..65535, got {port}")
    return port or None


__all__ = ["LATENCY_BUCKETS", "JOB_BUCKETS", "MetricsEndpoint", "ServicerProxy", "start_metrics_endpoint", "metrics_port_from",
           "CollectorRegistry"]
