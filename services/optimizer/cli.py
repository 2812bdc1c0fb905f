"""``hivemap optimizer``."""

from __future__ import annotations

import argparse
import signal
import threading

from shared.metrics import serve_metrics
from shared.settings import Settings


def cmd_optimizer(args: argparse.Namespace, settings: Settings) -> int:
    from .service import OptimizerService

    serve_metrics(settings.metrics_host, settings.metrics_port)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    svc = OptimizerService(settings)
    svc.start()
    try:
        stop.wait()
    finally:
        svc.stop()
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("optimizer", help="Sim(3) pose graph and global BA of merged/looped maps")
    p.set_defaults(func=cmd_optimizer)
