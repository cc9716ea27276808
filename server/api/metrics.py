"""Prometheus metrics of one server (a registry per app, so several apps can live in one process).

The live session code updates ``sessions``, ``viewers``, ``frames_sent``, ``frames_dropped`` and
``deform_seconds``; jobs by state are read from the job store at scrape time.
"""

from __future__ import annotations

from collections.abc import Callable

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, generate_latest
from prometheus_client.core import GaugeMetricFamily

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

JOB_STATES: tuple[str, ...] = ("queued", "running", "done", "failed", "cancelled")


class _JobCollector:
    """Reports ``facecast_jobs{state=...}`` from a callable returning state -> count."""

    def __init__(self, counts: Callable[[], dict[str, int]]):
        self._counts = counts

    def collect(self):
        g = GaugeMetricFamily("facecast_jobs", "Batch jobs by state", labels=["state"])
        try:
            counts = self._counts()
        except Exception:  # the store may be closing; report nothing rather than fail the scrape
            counts = {}
        for state in JOB_STATES:
            g.add_metric([state], float(counts.get(state, 0)))
        yield g


class _ClusterCollector:
    """Reports ``facecast_cluster_<name>{node=...}`` from a callable returning name -> value."""

    def __init__(self, node: str, gauges: Callable[[], dict[str, float]]):
        self._node, self._gauges = node, gauges

    def collect(self):
        try:
            values = self._gauges()
        except Exception:  # the node is stopping; report nothing rather than fail the scrape
            values = {}
        for name, value in values.items():
            g = GaugeMetricFamily(
                f"facecast_cluster_{name}",
                f"Cluster node: {name.replace('_', ' ')}",
                labels=["node"],
            )
            g.add_metric([self._node], float(value))
            yield g


class Metrics:
    """The server's metrics. Attributes are prometheus_client objects; update them directly."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        r = self.registry
        self.sessions = Gauge("facecast_sessions", "Live sessions open", registry=r)
        self.viewers = Gauge("facecast_viewers", "Viewers connected to live sessions", registry=r)
        self.producers = Gauge(
            "facecast_producers", "Producers connected to live sessions", registry=r
        )
        self.frames_sent = Counter(
            "facecast_frames_sent", "Vertex frames sent to viewers", registry=r
        )
        self.frames_dropped = Counter(
            "facecast_frames_dropped", "Vertex frames a slow viewer skipped", registry=r
        )
        self.frames_in = Counter(
            "facecast_frames_received", "Input frames received from producers", registry=r
        )
        self.sessions_expired = Counter(
            "facecast_sessions_expired", "Live sessions closed after their idle time", registry=r
        )
        self.live_refused = Counter(
            "facecast_live_messages_refused",
            "Live WebSocket messages refused before decoding, by reason "
            "(drop: over the rate; flood, too_big: the connection is closed)",
            ["reason"],
            registry=r,
        )
        self.deform_seconds = Histogram(
            "facecast_deform_seconds",
            "Time to deform one live frame (seconds)",
            registry=r,
            buckets=(0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0),
        )
        self.jobs_submitted = Counter("facecast_jobs_submitted", "Batch jobs accepted", registry=r)
        self.http_errors = Counter(
            "facecast_http_errors", "HTTP error responses by status", ["status"], registry=r
        )

    def watch_jobs(self, counts: Callable[[], dict[str, int]]) -> None:
        """Report jobs by state from ``counts()`` at every scrape."""
        self.registry.register(_JobCollector(counts))

    def watch_cluster(self, node: str, gauges: Callable[[], dict[str, float]]) -> None:
        """Report this node's cluster numbers (sessions owned, broker up...) at every scrape."""
        self.registry.register(_ClusterCollector(node, gauges))

    def render(self) -> bytes:
        """The Prometheus text exposition of every metric."""
        return generate_latest(self.registry)
