"""Place-recognition metrics (the shared ones are in shared/metrics.py)."""

from __future__ import annotations

from prometheus_client import Counter, Gauge, Histogram

from shared.metrics import at_zero

QUERY_SECONDS = Histogram(
    "hivemap_placerec_query_seconds",
    "BoW conversion, inter- and intra-map database queries and consistency, per keyframe",
    buckets=(0.001, 0.002, 0.005, 0.01, 0.02, 0.03, 0.05, 0.1, 0.2, 0.5),
)
VERIFIED = Counter(
    "hivemap_placerec_verifications_total", "Geometric verifications of candidates", ["result"]
)
MATCHES_PUBLISHED = Counter(
    "hivemap_placerec_matches_total", "Verified matches published", ["kind"]
)
# Per process, so per member of a placerec pool: every member stores every keyframe,
# the map's owner alone queries and verifies it.
KEYFRAMES = Counter(
    "hivemap_placerec_keyframes_total",
    "Keyframe events taken in (stored: added to the database only; queried: also "
    "searched for a match, by the member of the pool that owns the map)",
    ["role"],
)
DB_KEYFRAMES = Gauge("hivemap_placerec_db_keyframes", "Keyframes in the place database")

# Known label values exist from the start, at 0.
at_zero(VERIFIED, ("accepted", "rejected"))
at_zero(KEYFRAMES, ("stored", "queried"))
at_zero(MATCHES_PUBLISHED, ("merge", "loop"))
