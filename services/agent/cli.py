"""``hivemap agent``: the real agent on an image source."""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path

from shared.settings import Settings
from shared.zenoh_auth import with_credentials


def cmd_agent(args: argparse.Namespace, settings: Settings) -> int:
    import cv2

    from .runner import Agent
    from .sources import SourceError, open_source

    # An agent is a small on-board computer: tracking is measured on one core.
    cv2.setNumThreads(args.threads)

    try:
        src = open_source(args.source)
    except SourceError as e:
        print(f"hivemap agent: {e}", file=sys.stderr)
        return 2
    if args.server:
        settings = settings.model_copy(update={"zenoh": settings.zenoh.model_copy(
            update={"connect": [args.server]})})  # fmt: skip
    try:
        settings = with_credentials(settings, args.credentials)
    except ValueError as e:
        print(f"hivemap agent: {e}", file=sys.stderr)
        return 2
    agent = Agent(settings, args.id, src, use_server=not args.no_server, realtime=args.realtime)
    signal.signal(signal.SIGTERM, lambda *_: agent._stop.set())
    try:
        stats = agent.run()
    except SourceError as e:
        print(f"hivemap agent: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        stats = agent.stats
    finally:
        agent.close()
    agent.write_outputs(Path(args.out))
    print(json.dumps(stats.summary()))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("agent", help="monocular VO agent on an image source")
    p.add_argument("--id", required=True)
    p.add_argument(
        "--source",
        required=True,
        help="euroc:PATH | tum:PATH | video:FILE | synthetic:MH01[?seed=S]",
    )
    p.add_argument("--server", default="", help="zenoh router endpoint, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--no-server", action="store_true", help="fly alone")
    p.add_argument("--credentials", default=None, metavar="FILE",
                   help="this agent's router login (DATA_DIR/zenoh/ID.json from "
                   "`hivemap credentials add ID`)")  # fmt: skip
    p.add_argument("--realtime", action="store_true", help="pace frames by their timestamps")
    p.add_argument("--out", default="agent_out", help="online poses (TUM) and stats go here")
    p.add_argument("--threads", type=int, default=1, help="OpenCV threads (1: one core)")
    p.set_defaults(func=cmd_agent)
