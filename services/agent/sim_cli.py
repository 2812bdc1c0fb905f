"""``hivemap sim-agent``: a feature-level simulated agent flying a EuRoC trajectory."""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

from shared.settings import Settings

# Simulated agents per process (see _run_many).
PER_PROCESS = 4


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
    if args.count > 1 or args.first is not None:
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
    """N agents ``ID-i`` (i = ``first`` .. ``first + count - 1``): the load-test mode.

    At most ``per_process`` agents share one process (threads over one Zenoh session);
    more are split over child processes of this command. One process for all of them
    did not keep real time at 16 agents and more while it used a third of a core: its
    threads queue for one GIL, and every short numpy call or send lets another thread
    in, so an agent's frame waits for the others' turns many times over."""
    if args.per_process > 0 and args.count > args.per_process:
        return _run_processes(args)
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
    a, _, b = (args.frames or ":").partition(":")
    sl = slice(int(a) if a else None, int(b) if b else None)
    gts: dict[str, Trajectory] = {}
    for seq in seqs:  # each sequence read once, before any agent flies
        gt = load_euroc_gt(seq)
        gts[seq] = Trajectory(gt.stamps_ns[sl], gt.poses[sl])
    first = args.first or 0
    with open_session(settings.zenoh) as session:
        bus = Bus(session, "agent", settings.inject)
        runners = []
        for i in range(first, first + args.count):
            agent = f"{args.id}-{i}"
            drift = DriftModel.zero() if args.zero_noise else DriftModel(
                scale_drift_per_s=args.scale_drift)  # fmt: skip
            sim = SimAgent(gts[seqs[i % len(seqs)]], world, drift=drift, seed=args.seed + i)
            runners.append((agent, SimAgentRunner(settings, agent, sim, speed=args.speed,
                                                  stop=stop,
                                                  flush_timeout_s=args.flush_timeout)))  # fmt: skip
        threads = [
            threading.Thread(
                target=lambda r=runner, a=agent: results.__setitem__(a, r.run(bus).to_dict())
            )
            for agent, runner in runners
        ]
        for t in threads:
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


def child_argv(args: argparse.Namespace, first: int, count: int) -> list[str]:
    """This command for agents ``first`` .. ``first + count - 1`` in one process."""
    argv = ["sim-agent", "--id", args.id, "--traj", args.traj, "--speed", str(args.speed),
            "--seed", str(args.seed), "--world-seed", str(args.world_seed),
            "--scale-drift", str(args.scale_drift), "--frames", args.frames,
            "--flush-timeout", str(args.flush_timeout), "--out", args.out,
            "--count", str(count), "--first", str(first), "--per-process", "0"]  # fmt: skip
    if args.zero_noise:
        argv.append("--zero-noise")
    if args.credentials:
        argv += ["--credentials", args.credentials]
    return argv


def _die_with_parent() -> None:
    """In a child between fork and exec: SIGTERM when the parent dies (Linux), so a
    killed load test leaves no agents flying."""
    import contextlib
    import ctypes

    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def partition(first: int, count: int, per_process: int) -> list[tuple[int, int]]:
    """Agents ``first`` .. ``first + count - 1`` as (first, count) per process."""
    end = first + count
    return [(i, min(per_process, end - i)) for i in range(first, end, per_process)]


def _run_processes(args: argparse.Namespace) -> int:
    import subprocess

    parts = partition(args.first or 0, args.count, args.per_process)
    procs = [subprocess.Popen([sys.executable, "-m", "services.cli", *child_argv(args, i, n)],
                              preexec_fn=_die_with_parent)
             for i, n in parts]  # fmt: skip

    def forward(sig, _frame) -> None:
        for p in procs:
            if p.poll() is None:
                p.send_signal(sig)

    signal.signal(signal.SIGINT, forward)
    signal.signal(signal.SIGTERM, forward)
    rcs = [p.wait() for p in procs]
    return 0 if all(rc == 0 for rc in rcs) else max(rcs, key=lambda rc: rc != 0)


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
        help="run N agents ID-0..ID-N-1; --traj may list several (agent i flies the "
        "i-th, cyclically)",
    )
    p.add_argument(
        "--first",
        type=int,
        default=None,
        help="with --count: agents ID-FIRST.. (index, seed and trajectory)",
    )
    p.add_argument("--per-process", type=int, default=PER_PROCESS,
                   help="at most this many agents per process; more are split over child "
                        "processes (0: all in this one)")  # fmt: skip
    p.set_defaults(func=cmd_sim_agent)
