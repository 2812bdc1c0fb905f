"""The life of a long-running service process: metrics endpoint, start, wait for
SIGINT/SIGTERM, stop (which closes its Zenoh session: a process with a Python-callback
subscriber hangs at exit otherwise)."""

from __future__ import annotations

import logging
import os
import signal
import threading
from typing import Protocol

from shared.metrics import serve_metrics
from shared.settings import Settings


class Service(Protocol):
    def start(self) -> None: ...
    def stop(self) -> None: ...


log = logging.getLogger(__name__)


def lower_priority(niceness: int) -> int:
    """Raise this process's niceness by ``niceness`` (background services: place
    recognition, optimization). Set in-process so `hivemap up` and compose match."""
    if niceness <= 0:
        return os.nice(0)
    try:
        return os.nice(niceness)
    except OSError as e:
        log.warning("could not lower priority by %d: %s", niceness, e)
        return os.nice(0)


def run_service(svc: Service, settings: Settings, niceness: int = 0) -> int:
    lower_priority(niceness)
    serve_metrics(settings.metrics_host, settings.metrics_port)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    svc.start()
    try:
        stop.wait()
    finally:
        svc.stop()
    return 0
