"""``hivemap placerec``."""

from __future__ import annotations

import argparse

from shared.settings import Settings


def cmd_placerec(args: argparse.Namespace, settings: Settings) -> int:
    from shared.runtime import run_service

    from .service import PlacerecService

    return run_service(PlacerecService(settings), settings, settings.placerec.nice)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("placerec", help="place recognition: loop and map-merge candidates")
    p.set_defaults(func=cmd_placerec)
