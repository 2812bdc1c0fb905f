"""The map actor's lock, with a record of long holds.

Every thread that touches a map (its actor, matches, map copies, corrections) takes
this lock, so a hold of hundreds of milliseconds shows up directly as keyframe
latency for all agents of the map. Holds longer than ``slow_s`` are logged with the
thread and function that held it and counted in a metric, so a latency spike can be
traced to its cause without a profiler.
"""

from __future__ import annotations

import logging
import sys
import threading
import time

from .metrics import LOCK_HOLD

log = logging.getLogger(__name__)


class MapLock:
    def __init__(self, map_id: str, slow_s: float = 0.2) -> None:
        self._lock = threading.RLock()
        self.map_id = map_id
        self.slow_s = slow_s
        self._depth = 0
        self._t0 = 0.0
        self._who = ""

    def acquire(self, blocking: bool = True, timeout: float = -1) -> bool:
        ok = self._lock.acquire(blocking, timeout)
        if ok:
            self._took(sys._getframe(1).f_code.co_name)
        return ok

    def _took(self, who: str) -> None:
        self._depth += 1
        if self._depth == 1:
            self._t0 = time.perf_counter()
            self._who = who

    def release(self) -> None:
        self._depth -= 1
        if self._depth == 0:
            dt = time.perf_counter() - self._t0
            who = self._who
            self._lock.release()
            LOCK_HOLD.observe(dt)
            if dt > self.slow_s:
                log.warning("map %s lock held %.0f ms by %s in %s", self.map_id, dt * 1e3,
                            threading.current_thread().name, who)  # fmt: skip
            return
        self._lock.release()

    def __enter__(self) -> MapLock:
        self._lock.acquire()
        self._took(sys._getframe(1).f_code.co_name)
        return self

    def __exit__(self, *exc) -> None:
        self.release()
