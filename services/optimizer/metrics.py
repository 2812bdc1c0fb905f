"""Optimizer metrics (the shared ones are in shared/metrics.py)."""

from __future__ import annotations

from prometheus_client import Counter

from shared.messages import OptimizeRequest
from shared.metrics import at_zero

OPTIMIZATIONS = Counter(
    "hivemap_optimizations_total", "Global optimizations finished and published", ["reason"]
)
SUPERSEDED = Counter(
    "hivemap_optimizations_superseded_total",
    "Optimization requests replaced by a newer copy of the same map before finishing",
)
# Per process, so per worker of the pool: Prometheus's instance label tells them apart.
JOBS = Counter(
    "hivemap_optimizer_jobs_total",
    "Optimization jobs this worker took (taken: new, claimed: left by a worker that "
    "stopped) and how they ended (done, superseded, invalid, failed)",
    ["outcome"],
)

# Known reasons (the mapper's OptimizeRequest.reason) exist from the start, at 0.
at_zero(OPTIMIZATIONS, OptimizeRequest.REASONS)
at_zero(JOBS, ("taken", "claimed", "done", "superseded", "invalid", "failed"))
