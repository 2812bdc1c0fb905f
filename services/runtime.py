"""The life of a long-running service process: metrics endpoint, start, wait for
SIGINT/SIGTERM, stop (which closes its Zenoh session: a process with a Python-callback
subscriber hangs at exit otherwise)."""

from __future__ import annotations

import signal
import threading
from typing import Protocol

from shared.metrics import serve_metrics
from shared.settings import Settings


class Service(Protocol):
    def start(self) -> None: ...
    def stop(self) -> None: ...


def run_service(svc: Service, settings: Settings) -> int:
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
