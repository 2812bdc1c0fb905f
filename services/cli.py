"""The one command line: ``hivemap <subcommand>``.

Each subcommand lives in the module that owns it; a module listed in
``COMMAND_MODULES`` exposes ``register(subparsers)`` which adds its parsers and
sets ``func`` to a handler taking ``(args, settings)``. Heavy imports (OpenCV,
GTSAM) happen inside handlers so ``hivemap --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMAND_MODULES = [
    "services.launcher",  # up, demo, router
    "services.mapper.cli",  # mapper
    "services.placerec.cli",  # placerec
    "services.optimizer.cli",  # optimizer
    "services.api.cli",  # api
    "services.team_cli",  # run-team, eval
    "services.agent.cli",  # agent
    "services.agent.sim_cli",  # sim-agent
    "services.agent.render_cli",  # sim render
    "services.export_cli",  # export
    "services.dashboards",  # dashboards
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hivemap", description="Collaborative monocular SLAM for teams of small robots"
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name == name:  # a subcommand module not written yet
                continue
            raise
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from shared.logsetup import setup_logging
    from shared.settings import Settings

    try:
        settings = Settings()
    except Exception as e:  # pydantic's message names the bad variable
        print(f"hivemap: invalid settings: {e}", file=sys.stderr)
        return 2
    setup_logging(settings.log_level, settings.log_json, getattr(args, "command", "hivemap"))
    rc = args.func(args, settings)
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
