"""``hivemap api``."""

from __future__ import annotations

import argparse

from shared.settings import Settings


def cmd_api(args: argparse.Namespace, settings: Settings) -> int:
    import uvicorn

    from .main import create_app

    port = args.port if args.port is not None else settings.api_port
    # uvicorn handles SIGINT/SIGTERM itself and shuts down gracefully.
    uvicorn.run(create_app(settings), host=settings.api_host, port=port,
                log_level=settings.log_level.lower(), access_log=False)  # fmt: skip
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("api", help="REST + WebSocket API and live viewer")
    p.add_argument("--port", type=int, default=None, help="overrides HIVEMAP_API_PORT")
    p.set_defaults(func=cmd_api)
