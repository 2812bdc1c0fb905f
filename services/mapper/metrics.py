"""Mapper-specific metrics (the shared ones are in shared/metrics.py)."""

from __future__ import annotations

from prometheus_client import Counter, Gauge, Histogram

from shared.messages import OptimizeRequest
from shared.metrics import at_zero

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
# A map too large for one optimization job (its copy over shared.messages.MAX_BIN_BYTES,
# which the optimizer cannot decode): not sent; windowed BAs go on.
OPT_SKIPPED = Counter(
    "hivemap_optimize_skipped_total", "Optimization requests not sent", ["reason"]
)
LOOPS_REBASED = Counter(
    "hivemap_loops_rebased_total",
    "Loop constraints after an applied global correction: rebased (satisfied, a rest "
    "edge from then on), unsatisfied (kept at their measurement), overruled (left "
    "unsatisfied by several runs in a row with the map not moving towards it: a rest "
    "edge where the map holds it) or moved (a rest edge the map no longer satisfies, "
    "held where it was); held: a new loop whose matched points the map's relative pose "
    "reprojects about as well as its Sim(3), a rest edge from detection",
    ["outcome"],
)
CORRECTIONS = Counter("hivemap_corrections_applied_total", "Optimizer corrections applied")
# Maps marked for an optimization whose request has not gone out yet: debounced, or held
# back by the spacing of a big map's requests (collab.Collaboration.due), which at 1000
# keyframes is over a minute. Requests and corrections counted alone cannot show it.
OPT_PENDING = Gauge("hivemap_optimize_pending", "Maps marked for an optimization not yet requested")
# Ownership (services/mapper/ownership.py), per mapper instance. Gauges mirror the
# instance's own counts (they are kept in its Ownership and Leases objects).
MAPS_OWNED = Gauge("hivemap_mapper_maps_owned", "Maps whose lease this mapper holds")
LEASE_RENEWALS = Gauge("hivemap_mapper_lease_renewals", "Map lease renewals since start")
LEASES_LOST = Gauge("hivemap_mapper_leases_lost", "Map leases found taken by another mapper")
LEASES_RETAKEN = Gauge(
    "hivemap_mapper_leases_retaken", "Map leases found lapsed unrenewed and taken again"
)
TAKEOVERS = Gauge(
    "hivemap_mapper_takeovers", "Maps taken over from a mapper that stopped renewing them"
)
HANDOVERS = Gauge("hivemap_mapper_handovers", "Maps handed to another mapper for a merge")
FENCED_WRITES = Gauge(
    "hivemap_mapper_fenced_writes", "Writes refused because the map's lease was not ours"
)
GC_PAUSE = Histogram(
    "hivemap_gc_pause_seconds",
    "Collections of the cyclic garbage collector (every thread stops meanwhile)",
    ["generation"],
    buckets=(0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.2, 0.5, 1.0),
)
LOCK_HOLD = Histogram(
    "hivemap_map_lock_hold_seconds",
    "How long a map's lock was held at a time (registration, fusion, matches, corrections)",
    buckets=(0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.2, 0.5, 1.0, 2.5),
)

# What a lossy or jittery link made registration do (registration.py): duplicates
# acknowledged again, stale pose data ignored, updates kept for their late keyframe,
# keyframes anchored by the orphan rule and later placed from their predecessor.
REGISTRATION = Counter(
    "hivemap_registration_events_total",
    "Out-of-order arrivals handled by registration",
    ["what"],
)
# Pose refinements registration accepted, and those it refused because they moved the
# keyframe further than the VO's chain since the newest trusted keyframe allows.
REFINEMENTS = Counter(
    "hivemap_pose_refinements_total",
    "Keyframe pose refinements against settled points: accepted, or gated (they moved "
    "the keyframe further than its VO chain allows)",
    ["result"],
)
OVERLOAD_LEVEL = Gauge(
    "hivemap_mapper_overload_level",
    "What the mapper sheds now: 0 nothing, 1 live poses, 2 + feedback rate, "
    "3 + place recognition and optimization deferred, 4 + keyframe batches",
)
REALTIME = Gauge(
    "hivemap_mapper_realtime_priority",
    "SCHED_RR priority the mapper's threads run at (0: normal scheduling, as when the "
    "process may not raise it)",
)
SHED = Counter(
    "hivemap_mapper_shed_total",
    "Work shed under overload: poses not stored, feedback rounds slowed, event and "
    "optimization rounds deferred, loops' point fusion cut short, keyframe batches NACKed "
    "for a resend after a retry-after",
    ["what"],
)

# Every known label value exists from the start (at 0), so a dashboard shows "no merges
# yet" as 0 rather than as an empty panel.
at_zero(MATCHES, ("merge", "loop", "loop_redundant"))
at_zero(OPT_REQUESTS, OptimizeRequest.REASONS)
at_zero(REGISTRATION, ("duplicate", "stale", "early", "orphan", "rechained"))
at_zero(REFINEMENTS, ("accepted", "gated"))
at_zero(SHED, ("pose", "feedback", "placerec", "optimize", "keyframe_batch", "loop_fusion"))
