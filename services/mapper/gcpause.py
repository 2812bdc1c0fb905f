"""The cyclic garbage collector in the mapper process: its pauses measured, and the
long-lived map kept out of its full collections.

A full (generation 2) collection stops every thread of the process while it walks
every tracked object: with a merged map of 300k points that is 0.13 s on an idle
core, on this loaded machine several times that, and it comes again each time a
quarter more long-lived objects piled up -- at 24 agents every few tens of seconds.
The map's keyframes and points die by reference counting (they form no cycles), so
:func:`freeze_long_lived` moves what survived so far to CPython's permanent generation
(``gc.freeze``), after a collection of the young generations so that recent cyclic
garbage is not frozen with it. Full collections then walk only what came after.
"""

from __future__ import annotations

import gc
import threading
import time

from .metrics import GC_PAUSE

FREEZE_EVERY_S = 20.0


class GcWatch:
    """Observes every collection's duration in ``hivemap_gc_pause_seconds``."""

    def __init__(self) -> None:
        self._t0 = 0.0

    def __call__(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._t0 = time.perf_counter()
        else:
            GC_PAUSE.labels(str(info.get("generation", "?"))).observe(
                time.perf_counter() - self._t0
            )

    def install(self) -> GcWatch:
        if self not in gc.callbacks:
            gc.callbacks.append(self)
        return self


def freeze_long_lived() -> None:
    gc.collect(1)
    gc.freeze()


def start_freezer(stop: threading.Event, every_s: float = FREEZE_EVERY_S) -> threading.Thread:
    """A daemon thread that calls :func:`freeze_long_lived` every ``every_s`` seconds."""

    def run() -> None:
        while not stop.wait(every_s):
            freeze_long_lived()

    t = threading.Thread(target=run, name="mapper-gc-freeze", daemon=True)
    t.start()
    return t
