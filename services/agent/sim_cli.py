"""``hivemap sim-agent``: a feature-level simulated agent flying a EuRoC trajectory."""

from __future__ import annotations

import argparse
import json
import signal
import threading
from pathlib import Path

from shared.settings import Settings


def cmd_sim_agent(args: argparse.Namespace, settings: Settings) -> int:
    from shared.trajectory import Trajectory, load_euroc_gt, write_tum

    from .sim_agent import DriftModel, LandmarkWorld, SimAgent
    from .sim_runner import SimAgentRunner

    drift = DriftModel.zero() if args.zero_noise else DriftModel(
        scale_drift_per_s=args.scale_drift)  # fmt: skip
    gt = load_euroc_gt(args.traj)
    if args.frames:
        a, _, b = args.frames.partition(":")
        sl = slice(int(a) if a else None, int(b) if b else None)
        gt = Trajectory(gt.stamps_ns[sl], gt.poses[sl])
    sim = SimAgent(gt, LandmarkWorld(args.world_seed), drift=drift, seed=args.seed)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    runner = SimAgentRunner(settings, args.id, sim, speed=args.speed, stop=stop,
                            flush_timeout_s=args.flush_timeout)  # fmt: skip
    stats = runner.run()
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        import numpy as np

        st = np.array([s for s, _ in runner.estimates], np.int64)
        T = np.stack([T for _, T in runner.estimates]) if runner.estimates else np.zeros((0, 4, 4))
        write_tum(out / f"{args.id}_estimate.tum", Trajectory(st, T))
        n = len(runner.estimates)
        write_tum(out / f"{args.id}_gt.tum", Trajectory(gt.stamps_ns[:n], gt.poses[:n]))
        (out / f"{args.id}_stats.json").write_text(json.dumps(stats.to_dict(), indent=2))
    print(json.dumps(stats.to_dict()), flush=True)
    return 0 if stats.all_acked or stop.is_set() else 3


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim-agent", help="simulated agent: keyframes from a EuRoC trajectory")
    p.add_argument("--id", required=True, help="agent id")
    p.add_argument("--traj", default="MH01", help="MH01..MH05")
    p.add_argument("--speed", type=float, default=1.0, help="real-time factor, 0 = no pacing")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument("--world-seed", type=int, default=0)
    p.add_argument("--zero-noise", action="store_true", help="estimate = ground truth")
    p.add_argument("--scale-drift", type=float, default=0.0, help="relative scale drift per s")
    p.add_argument("--frames", default="", help="A:B slice of the trajectory")
    p.add_argument("--flush-timeout", type=float, default=30.0)
    p.add_argument("--out", default="", help="write estimate/GT TUM and stats here")
    p.set_defaults(func=cmd_sim_agent)
