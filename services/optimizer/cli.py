"""``hivemap optimizer``."""

from __future__ import annotations

import argparse

from shared.settings import Settings


def cmd_optimizer(args: argparse.Namespace, settings: Settings) -> int:
    from shared.runtime import run_service

    from .service import OptimizerService

    return run_service(OptimizerService(settings), settings, settings.optimizer.nice)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("optimizer", help="Sim(3) pose graph and global BA of merged/looped maps")
    p.set_defaults(func=cmd_optimizer)
