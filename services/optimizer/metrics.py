"""Optimizer metrics (the shared ones are in shared/metrics.py)."""

from __future__ import annotations

from prometheus_client import Counter

OPTIMIZATIONS = Counter(
    "hivemap_optimizations_total", "Global optimizations finished and published", ["reason"]
)
SUPERSEDED = Counter(
    "hivemap_optimizations_superseded_total",
    "Optimization requests replaced by a newer copy of the same map before finishing",
)

# Known reasons (the mapper's OptimizeRequest.reason) exist from the start, at 0.
for _reason in ("merge", "loop", "continue"):
    OPTIMIZATIONS.labels(_reason)
