"""Mapper-specific metrics (the shared ones are in shared/metrics.py)."""

from __future__ import annotations

from prometheus_client import Counter, Gauge

CULLED = Counter("hivemap_keyframes_culled_total", "Redundant keyframes removed", ["map"])
FEEDBACK_BYTES = Counter(
    "hivemap_feedback_bytes_total", "Map chunk bytes sent back to agents", ["agent"]
)
MAP_POINTS = Gauge("hivemap_map_points", "Map points per server map", ["map"])
QUEUE_DEPTH = Gauge("hivemap_map_queue_depth", "Batches waiting for a map actor", ["map"])
MATCHES = Counter("hivemap_matches_applied_total", "Verified place matches applied", ["kind"])
MERGES = Counter("hivemap_map_merges_total", "Server maps fused into another")
OPT_REQUESTS = Counter(
    "hivemap_optimize_requests_total", "Map copies sent to the optimizer", ["reason"]
)
CORRECTIONS = Counter("hivemap_corrections_applied_total", "Optimizer corrections applied")
