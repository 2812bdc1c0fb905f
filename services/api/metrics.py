"""API metrics: requests by route template (never raw ids), latency, rejected requests."""

from __future__ import annotations

from prometheus_client import Counter, Histogram

from shared.metrics import LATENCY_BUCKETS

REQUESTS = Counter("hivemap_api_requests_total", "HTTP requests", ["route", "status"])
REQUEST_SECONDS = Histogram(
    "hivemap_api_request_seconds", "HTTP request handling time", ["route"],
    buckets=LATENCY_BUCKETS,
)  # fmt: skip
API_REJECTED = Counter(
    "hivemap_api_rejected_total", "Requests refused: unknown ids, malformed parameters",
    ["reason"],
)  # fmt: skip
WS_CLIENTS = Counter("hivemap_api_ws_connections_total", "WebSocket connections accepted")
