"""``hivemap mapper``."""

from __future__ import annotations

import argparse
import sys

from shared.settings import Settings


def cmd_mapper(args: argparse.Namespace, settings: Settings) -> int:
    from shared.runtime import run_service

    from .service import GIL_SWITCH_S, MapperService

    sys.setswitchinterval(GIL_SWITCH_S)
    return run_service(MapperService(settings), settings)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("mapper", help="server mapping: registers keyframes, stores maps, acks")
    p.set_defaults(func=cmd_mapper)
