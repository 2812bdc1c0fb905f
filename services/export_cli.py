"""``hivemap export``: server-map trajectories (TUM) and map points (PLY) from Redis."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from shared.settings import Settings


def write_ply(path: Path, points: np.ndarray) -> None:
    header = (
        "ply\nformat ascii 1.0\n"
        f"element vertex {len(points)}\nproperty float x\nproperty float y\nproperty float z\n"
        "end_header\n"
    )
    body = "\n".join(f"{p[0]:.6f} {p[1]:.6f} {p[2]:.6f}" for p in points)
    path.write_text(header + body + ("\n" if len(points) else ""))


def cmd_export(args: argparse.Namespace, settings: Settings) -> int:
    from shared.store import Store, connect
    from shared.trajectory import Trajectory, write_tum

    store = Store(connect(args.redis_url or settings.redis_url))
    agents = store.agents()
    if args.agent:
        missing = sorted(set(args.agent) - set(agents))
        if missing:
            print(f"hivemap export: unknown agent(s): {', '.join(missing)}", file=sys.stderr)
            return 2
        agents = args.agent
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for a in agents:
        _, stamps, poses = store.trajectory(a)
        write_tum(out / f"{a}.tum", Trajectory(stamps, poses))
        line = f"{a}: {len(stamps)} keyframes -> {out / f'{a}.tum'}"
        if args.points:
            pts = [p.pos for p in store.map_points(a)]
            arr = np.array(pts).reshape(-1, 3)
            write_ply(out / f"{a}_points.ply", arr)
            line += f", {len(arr)} map points -> {out / f'{a}_points.ply'}"
        print(line)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write server-map trajectories (TUM) and map points (PLY)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--agent", action="append", help="agent id (repeatable; default all)")
    p.add_argument("--points", action="store_true", help="also write map points as PLY")
    p.add_argument("--redis-url", default="", help="overrides HIVEMAP_REDIS_URL")
    p.set_defaults(func=cmd_export)
