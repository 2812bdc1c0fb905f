"""The map lock: reentrant, and a long hold is reported with who held it."""

from __future__ import annotations

import logging
import threading
import time

from services.mapper.locks import MapLock
from services.mapper.metrics import LOCK_HOLD


def _count() -> float:
    return next(s.value for s in LOCK_HOLD.collect()[0].samples if s.name.endswith("_count"))


def test_long_hold_is_logged_with_its_holder_and_reentry_counts_once(caplog):
    lock = MapLock("m1", slow_s=0.05)
    n0 = _count()

    def slow_holder() -> None:
        with lock, lock:  # reentrant: one hold, not two
            time.sleep(0.08)

    with caplog.at_level(logging.WARNING, logger="services.mapper.locks"):
        t = threading.Thread(target=slow_holder, name="holder-thread")
        t.start()
        t.join()
        with lock:
            pass  # short: not logged
    assert _count() - n0 == 2
    slow = [r.getMessage() for r in caplog.records]
    assert len(slow) == 1
    assert "m1" in slow[0] and "holder-thread" in slow[0] and "slow_holder" in slow[0]


def test_other_threads_wait_for_the_holder():
    lock = MapLock("m2")
    order = []
    lock.acquire()
    t = threading.Thread(target=lambda: (lock.acquire(), order.append("other"), lock.release()))
    t.start()
    time.sleep(0.05)
    order.append("holder")
    lock.release()
    t.join()
    assert order == ["holder", "other"]
