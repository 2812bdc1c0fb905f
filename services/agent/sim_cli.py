"""``hivemap sim-agent``: a feature-level simulated agent flying a EuRoC trajectory."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

from shared.settings import Settings


def cmd_sim_agent(args: argparse.Namespace, settings: Settings) -> int:
    from shared.trajectory import Trajectory, load_euroc_gt, write_tum
    from shared.zenoh_auth import with_credentials

    from .sim_agent import DriftModel, LandmarkWorld, SimAgent
    from .sim_runner import SimAgentRunner

    try:
        settings = with_credentials(settings, args.credentials)
    except ValueError as e:
        print(f"hivemap sim-agent: {e}", file=sys.stderr)
        return 2
    if args.count > 1:
        return _run_many(args, settings)
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


def _run_many(args: argparse.Namespace, settings: Settings) -> int:
    """N agents in one process over one Zenoh session: the load-test mode (each agent
    costs a few percent of a core, so tens fit on one)."""
    from shared.trajectory import Trajectory, load_euroc_gt
    from shared.transport import Bus, open_session

    from .sim_agent import DriftModel, LandmarkWorld, SimAgent
    from .sim_runner import SimAgentRunner

    world = LandmarkWorld(args.world_seed)
    seqs = args.traj.split(",")
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    results: dict[str, dict] = {}
    with open_session(settings.zenoh) as session:
        bus = Bus(session, "agent", settings.inject)
        threads = []
        for i in range(args.count):
            agent = f"{args.id}-{i}"
            gt = load_euroc_gt(seqs[i % len(seqs)])
            a, _, b = (args.frames or ":").partition(":")
            sl = slice(int(a) if a else None, int(b) if b else None)
            gt = Trajectory(gt.stamps_ns[sl], gt.poses[sl])
            drift = DriftModel.zero() if args.zero_noise else DriftModel(
                scale_drift_per_s=args.scale_drift)  # fmt: skip
            sim = SimAgent(gt, world, drift=drift, seed=args.seed + i)
            runner = SimAgentRunner(settings, agent, sim, speed=args.speed, stop=stop,
                                    flush_timeout_s=args.flush_timeout)  # fmt: skip
            t = threading.Thread(
                target=lambda r=runner, a=agent: results.__setitem__(a, r.run(bus).to_dict())
            )
            threads.append(t)
            t.start()
        for t in threads:
            t.join()
        bus.close()
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        for agent, st in results.items():
            (out / f"{agent}_stats.json").write_text(json.dumps(st, indent=2))
    for st in results.values():
        print(json.dumps(st), flush=True)
    return 0 if all(st["all_acked"] for st in results.values()) or stop.is_set() else 3


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim-agent", help="simulated agent: keyframes from a EuRoC trajectory")
    p.add_argument("--id", required=True, help="agent id")
    p.add_argument(
        "--credentials",
        default=None,
        metavar="FILE",
        help="router login file (hivemap credentials add)",
    )
    p.add_argument("--traj", default="MH01", help="MH01..MH05")
    p.add_argument("--speed", type=float, default=1.0, help="real-time factor, 0 = no pacing")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument("--world-seed", type=int, default=0)
    p.add_argument("--zero-noise", action="store_true", help="estimate = ground truth")
    p.add_argument("--scale-drift", type=float, default=0.0, help="relative scale drift per s")
    p.add_argument("--frames", default="", help="A:B slice of the trajectory")
    p.add_argument("--flush-timeout", type=float, default=30.0)
    p.add_argument("--out", default="", help="write estimate/GT TUM and stats here")
    p.add_argument(
        "--count",
        type=int,
        default=1,
        help="run N agents ID-0..ID-N-1 in this process; --traj may list several",
    )
    p.set_defaults(func=cmd_sim_agent)
