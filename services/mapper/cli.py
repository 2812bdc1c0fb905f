"""``hivemap mapper``."""

from __future__ import annotations

import argparse
import sys

from shared.settings import Settings


def cmd_mapper(args: argparse.Namespace, settings: Settings) -> int:
    import threading

    from shared.runtime import raise_to_realtime, run_service

    from .gcpause import GcWatch, start_freezer
    from .metrics import REALTIME
    from .service import GIL_SWITCH_S, MapperService

    # First, so every thread the service starts (Zenoh's included) inherits it.
    rt = raise_to_realtime(settings.mapper.rt_priority)
    REALTIME.set(settings.mapper.rt_priority if rt else 0)
    sys.setswitchinterval(GIL_SWITCH_S)
    GcWatch().install()
    stop = threading.Event()
    start_freezer(stop)
    try:
        return run_service(MapperService(settings), settings)
    finally:
        stop.set()


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("mapper", help="server mapping: registers keyframes, stores maps, acks")
    p.set_defaults(func=cmd_mapper)
