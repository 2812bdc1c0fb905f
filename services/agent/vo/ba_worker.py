"""Local BA in a process of its own, so that tracking never waits for it.

GTSAM's optimizer (through its pybind11 wrapper) holds the GIL for the whole solve,
so a thread would stall tracking as surely as running inline: 60-370 ms per keyframe
measured, several frame periods of a 20 Hz camera. A single worker process does the
solve; the VO hands it a window (plain arrays, a few hundred kB pickled) and applies
the result when it is back (ORB-SLAM's LocalMapping thread, with the same
tolerance: tracking goes on against the map as it was).
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import Future, ProcessPoolExecutor

from .local_ba import BAResult, local_ba


def _ready() -> bool:
    return True


class BAWorker:
    def __init__(self) -> None:
        # spawn, not fork: the parent runs Zenoh's threads, which a fork would copy
        # in whatever state they were.
        self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        self._fut: Future | None = None
        # Start the process (imports numpy and GTSAM, ~1 s) before the first frame.
        self._pool.submit(_ready).result()

    @property
    def busy(self) -> bool:
        return self._fut is not None

    def submit(self, job: dict) -> None:
        assert self._fut is None, "one local BA at a time"
        self._fut = self._pool.submit(local_ba, **job)

    def result(self, wait: bool = False) -> BAResult | None:
        if self._fut is None or not (wait or self._fut.done()):
            return None
        fut, self._fut = self._fut, None
        return fut.result()

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
