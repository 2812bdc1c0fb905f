"""The mapper's garbage-collector pauses: measured, and the long-lived map frozen out of
full collections (services/mapper/gcpause.py)."""

from __future__ import annotations

import gc
import time
import weakref

from services.mapper.gcpause import GcWatch, freeze_long_lived
from services.mapper.metrics import GC_PAUSE


def _count(gen: str) -> float:
    """Collections of generation ``gen`` observed so far."""
    return sum(b.get() for b in GC_PAUSE.labels(gen)._buckets)


class _Node:
    def __init__(self) -> None:
        self.me = self  # a cycle: only the collector frees it


def test_every_collection_is_observed_with_its_generation():
    watch = GcWatch().install()
    try:
        n0 = _count("2")
        gc.collect()
        n1 = _count("2")
        assert n1 == n0 + 1
    finally:
        gc.callbacks.remove(watch)


def test_a_frozen_map_is_not_walked_by_full_collections_and_new_garbage_still_goes():
    long_lived = [{"obs": [i]} for i in range(300_000)]  # a map's worth of tracked objects
    try:
        t = time.perf_counter()
        gc.collect()
        before = time.perf_counter() - t
        freeze_long_lived()
        assert gc.get_freeze_count() >= len(long_lived)
        t = time.perf_counter()
        gc.collect()
        after = time.perf_counter() - t
        assert after < 0.3 * before, (after, before)
        n = _Node()
        ref = weakref.ref(n)
        del n
        gc.collect()
        assert ref() is None  # cyclic garbage made after the freeze is still collected
    finally:
        gc.unfreeze()
        del long_lived
