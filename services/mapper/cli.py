"""``hivemap mapper``."""

from __future__ import annotations

import argparse
import sys

from shared.settings import Settings


def cmd_mapper(args: argparse.Namespace, settings: Settings) -> int:
    import threading

    from shared.runtime import run_service

    from .gcpause import GcWatch, start_freezer
    from .service import GIL_SWITCH_S, MapperService

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
