"""Prometheus metrics shared by every service (prefix ``hivemap_``, base units).

Metrics live in the process-wide default registry, labelled by service, so a test
that runs several services in one process still tells them apart.
"""

from __future__ import annotations

import re

from prometheus_client import (
    CONTENT_TYPE_LATEST,
    REGISTRY,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
    start_http_server,
)

LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.02, 0.03, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3,
                   0.5, 0.75, 1.0, 2.0, 5.0, 10.0)  # fmt: skip

MESSAGES = Counter(
    "hivemap_messages_total", "Zenoh samples sent or received", ["service", "direction", "key"]
)
BYTES = Counter(
    "hivemap_bytes_total", "Payload bytes sent or received", ["service", "direction", "key"]
)
REJECTED = Counter(
    "hivemap_messages_rejected_total",
    "Received samples that failed to decode or validate",
    ["service", "key", "reason"],
)
INJECTED_DROPS = Counter(
    "hivemap_injected_drops_total", "Samples dropped by the loss injector", ["service", "key"]
)
INJECTED_DELAY = Histogram(
    "hivemap_injected_delay_seconds", "Delay added by the injector", ["service"],
    buckets=LATENCY_BUCKETS,
)  # fmt: skip
PROCESSING = Histogram(
    "hivemap_processing_seconds",
    "Time to process one received message",
    ["service", "kind"],
    buckets=LATENCY_BUCKETS,
)
KEYFRAME_LATENCY = Histogram(
    "hivemap_keyframe_latency_seconds",
    "Keyframe received by the mapper -> registered, stored and acked",
    ["agent"],
    buckets=LATENCY_BUCKETS,
)
AGENT_ACK_LATENCY = Histogram(
    "hivemap_agent_ack_latency_seconds",
    "Keyframe first published by the agent -> ack received by the agent",
    ["agent"],
    buckets=LATENCY_BUCKETS,
)
AGENT_FRAMES_DROPPED = Counter(
    "hivemap_agent_frames_dropped_total",
    "Live-camera frames the agent dropped because it was still busy with an earlier one",
    ["agent"],
)
RESENT = Counter(
    "hivemap_resent_total", "Keyframes and map points sent again", ["agent", "kind", "reason"]
)
STORED = Counter("hivemap_stored_total", "Keyframes and map points stored", ["service", "kind"])
MAP_SIZE = Gauge("hivemap_map_keyframes", "Keyframes per server map", ["map"])
UP = Gauge("hivemap_service_up", "1 while the service loop runs", ["service"])


def at_zero(metric, values) -> None:
    """Each label value of ``values`` exists from the start, at 0, so a dashboard shows
    "none yet" as 0 rather than as an empty panel."""
    for v in values:
        metric.labels(v)


def metrics_text() -> tuple[bytes, str]:
    return generate_latest(REGISTRY), CONTENT_TYPE_LATEST


def serve_metrics(host: str, port: int) -> None:
    """Expose /metrics on its own port (services without an HTTP app of their own)."""
    if port:
        start_http_server(port, addr=host)


def sample_value(name: str, labels: dict[str, str]) -> float:
    v = REGISTRY.get_sample_value(name, labels)
    return 0.0 if v is None else float(v)


_LABEL = re.compile(r'(\w+)="((?:[^"\\]|\\.)*)"')


def series_key(name: str, labels: dict[str, str] | None = None) -> str:
    """``name{a="x",b="y"}`` with the labels sorted by name: how ``parse_exposition``
    keys a series, whatever order the labels were declared or written in (the client
    library writes them sorted, so a key written in declaration order, as bench_team's
    per-mapper ``hivemap_stored_total{service=..,kind=..}`` was, never matched)."""
    if not labels:
        return name
    return name + "{" + ",".join(f'{k}="{v}"' for k, v in sorted(labels.items())) + "}"


def parse_exposition(text: str) -> dict[str, float]:
    """A Prometheus text page (what /metrics serves): ``series_key`` -> value."""
    out = {}
    for ln in text.splitlines():
        if not ln or ln.startswith("#"):
            continue
        k, _, v = ln.rpartition(" ")
        name, brace, rest = k.partition("{")
        labels = dict(_LABEL.findall(rest)) if brace else None
        out[series_key(name, labels)] = float(v)
    return out
