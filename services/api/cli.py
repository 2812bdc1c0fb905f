"""``hivemap api``."""

from __future__ import annotations

import argparse
import sys

from shared.settings import Settings


def cmd_api(args: argparse.Namespace, settings: Settings) -> int:
    import uvicorn

    from .main import create_app
    from .security import InsecureConfig

    port = args.port if args.port is not None else settings.api_port
    try:
        app = create_app(settings)
    except InsecureConfig as e:
        print(f"hivemap api: refusing to start: {e}", file=sys.stderr)
        return 2
    # uvicorn handles SIGINT/SIGTERM itself and shuts down gracefully. ws_max_size: the
    # server never reads what a WebSocket client sends, so frames stay small.
    uvicorn.run(app, host=settings.api_host, port=port, log_level=settings.log_level.lower(),
                access_log=False, ws_max_size=max(settings.api_max_body_bytes, 1024),
                h11_max_incomplete_event_size=16_384)  # fmt: skip
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("api", help="REST + WebSocket API and live viewer")
    p.add_argument("--port", type=int, default=None, help="overrides HIVEMAP_API_PORT")
    p.set_defaults(func=cmd_api)
