"""``hivemap run-team`` and ``hivemap eval``: a team of real (VO) agents against the
whole server stack, and the per-agent and joint ATE of what the server holds."""

from __future__ import annotations

import argparse
import json
import sys
import time
import urllib.request
from pathlib import Path

from shared.progress import progress
from shared.settings import Settings


def _sources(args: argparse.Namespace) -> list[tuple[str, str, str]]:
    """(agent name, sequence, source spec) per agent."""
    seqs = [s for s in args.agents.split(",") if s]
    if args.source == "synthetic":
        seeds = [int(x) for x in str(args.seed).split(",")]
        if len(seeds) == 1:
            seeds *= len(seqs)
        if len(seeds) != len(seqs):
            raise SystemExit("hivemap run-team: give one seed, or one per agent")
        out = []
        for i, (seq, seed) in enumerate(zip(seqs, seeds, strict=True)):
            q = [f"seed={seed}"] + ([f"frames={args.frames}"] if args.frames else [])
            out.append((f"agent{i + 1}", seq, f"synthetic:{seq}?{'&'.join(q)}"))
        return out
    if args.source.startswith("euroc:"):
        dirs = args.source.removeprefix("euroc:").split(",")
        if len(dirs) != len(seqs):
            raise SystemExit("hivemap run-team: give one euroc folder per agent")
        return [(f"agent{i + 1}", seq, f"euroc:{d}")
                for i, (seq, d) in enumerate(zip(seqs, dirs, strict=True))]  # fmt: skip
    raise SystemExit(f"hivemap run-team: unknown --source {args.source!r}")


def _metric(port: int, name: str) -> float:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=2) as r:
            text = r.read().decode()
    except OSError:
        return float("nan")
    total = 0.0
    for ln in text.splitlines():
        if ln.startswith(name) and not ln.startswith("#"):
            total += float(ln.rsplit(" ", 1)[1])
    return total


def _wait_agents(stack, procs: list, t0: float) -> None:
    """Until every agent process ended, with a bar of agents done and keyframes stored."""
    from shared.store import Store, connect

    store = Store(connect(stack.settings.redis_url))
    left = dict(procs)
    try:
        with progress("agents flying", len(procs), "done") as update:
            while left:
                for name, p in list(left.items()):
                    if p.poll() is not None:
                        del left[name]
                        print(f"{name} finished ({p.returncode}) after "
                              f"{time.monotonic() - t0:.0f} s", flush=True)  # fmt: skip
                try:
                    kfs = sum((store.agent_info(a) or {}).get("n_kf", 0) for a in store.agents())
                except OSError:
                    kfs = 0
                update(completed=len(procs) - len(left), info=f"{kfs} keyframes stored")
                time.sleep(0.5)
    finally:
        store.r.close()


def wait_settled(stack, timeout: float, quiet_s: float = 8.0, on_check=None) -> None:
    """Until every optimization the mapper asked for came back, none is waiting to be
    asked for, and nothing changed for ``quiet_s``.

    A map marked for an optimization is asked for only once the spacing of its requests
    allows (``Collaboration.due``: the last run's time over the optimizer's share, over a
    minute for a 1000-keyframe map); counting requests and corrections alone, a team5 run
    at 85a443d was evaluated 8 s after its last agent landed, as the loop closure its
    last keyframes made was being sent (agent1's 88 newest keyframes not optimized:
    55.7 mm, its optimized ones 5.8 mm)."""
    from .launcher import service_plan

    plan = service_plan(stack.settings, stack.scale)
    mps = [s.http_port for s in plan if s.name.startswith("mapper")]
    ops = [s.http_port for s in plan if s.name.startswith("optimizer")]
    deadline = time.monotonic() + timeout
    last, since = None, time.monotonic()
    while time.monotonic() < deadline:
        req = sum(_metric(mp, "hivemap_optimize_requests_total") for mp in mps)
        done = sum(_metric(mp, "hivemap_corrections_applied_total") for mp in mps) + sum(
            _metric(op, "hivemap_optimizations_superseded_total") for op in ops
        )
        pending = sum(_metric(mp, "hivemap_optimize_pending") for mp in mps)
        state = (req, done, pending)
        if state != last:
            last, since = state, time.monotonic()
        elif pending > 0:
            pass  # a request still to go out: its spacing ends it, or the deadline
        elif time.monotonic() - since >= (quiet_s if req <= done else 4 * quiet_s):
            return  # settled (or an optimization failed or went stale: don't hang)
        if on_check is not None:
            on_check(info=f"{done:.0f}/{req:.0f} optimizations back, {pending:.0f} to ask")
        time.sleep(1.0)


def collect(redis_url: str):
    from shared.store import Store, connect
    from shared.trajectory import Trajectory

    store = Store(connect(redis_url))
    out = {}
    for a in store.agents():
        info = store.agent_info(a) or {}
        _, stamps, poses = store.trajectory(a)
        if len(stamps):
            out[a] = (str(info.get("map_id") or "?"), Trajectory(stamps, poses))
    return out


def run_team(
    settings: Settings,
    sources: list[tuple[str, str, str]],
    out: Path,
    *,
    realtime: bool = False,
    feedback: bool = True,
    with_api: bool = False,
    data_dir: str | None = None,
    settle_timeout: float = 120.0,
    on_stack=None,
    keep: bool = False,
    agent_nice: int = 0,
    scale=None,
) -> dict:
    """The whole stack plus one ``hivemap agent`` per source; waits for the agents and
    for the optimizer to settle, then evaluates. Returns the evaluation, each agent's
    stats and the stack (stopped unless ``keep``)."""
    from shared.evaluation import evaluate_team, format_report
    from shared.redis_server import free_port
    from shared.trajectory import Trajectory, write_tum

    from .launcher import Stack

    out.mkdir(parents=True, exist_ok=True)
    settings = settings.model_copy(update={
        "api_port": settings.api_port if with_api else free_port(),
        "mapper_metrics_port": free_port(), "placerec_metrics_port": free_port(),
        "optimizer_metrics_port": free_port()})  # fmt: skip
    # Without feedback the mapper sends agents no map chunks (CCM-SLAM Table 7's baseline).
    env = {} if feedback else {"HIVEMAP_MAPPER__FEEDBACK_K": "0"}
    stack = Stack(settings, data_dir=data_dir, env=env, scale=scale)
    stack.start(with_api=with_api)
    t0 = time.monotonic()
    procs = []
    try:
        if on_stack is not None:
            on_stack(stack)
        for name, _, src in sources:
            argv = ["agent", "--id", name, "--source", src, "--server", stack.zenoh_endpoint,
                    "--out", str(out)] + (["--realtime"] if realtime else [])  # fmt: skip
            stack.add(f"agent-{name}", argv, {"HIVEMAP_LOG_LEVEL": "WARNING", **env}, agent_nice)
            procs.append((name, stack.procs[-1][1]))
            print(f"{name}: {src}", flush=True)
        _wait_agents(stack, procs, t0)
        with progress("optimizer settling", None, "checks") as update:
            wait_settled(stack, settle_timeout, on_check=update)
        trajs = collect(stack.settings.redis_url)
        maps = evaluate_team(trajs)
        print(format_report(maps), flush=True)
        for a, (_, tr) in trajs.items():
            write_tum(out / f"{a}_server.tum", Trajectory(tr.stamps_ns, tr.poses))
        doc = _eval_doc(maps)
        doc["seconds"] = time.monotonic() - t0
        doc["agents"] = {}
        for name, seq, src in sources:
            f = out / f"{name}_stats.json"
            st = json.loads(f.read_text()) if f.exists() else {}
            doc["agents"][name] = {"seq": seq, "source": src, "stats": st}
        (out / "team_eval.json").write_text(json.dumps(doc, indent=2))
        print(f"written {out / 'team_eval.json'}")
        doc["stack"] = stack
        return doc
    finally:
        if not keep:
            stack.stop()


def cmd_run_team(args: argparse.Namespace, settings: Settings) -> int:
    import signal

    from .launcher import _run_until_signal, _stop_on_signal

    # SIGTERM unwinds like Ctrl-C so run_team's finally stops the stack it started.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    doc = run_team(
        settings, _sources(args), Path(args.out), realtime=args.realtime,
        feedback=not args.no_feedback, with_api=not args.no_api, data_dir=args.data_dir,
        settle_timeout=args.settle_timeout, keep=args.keep, agent_nice=args.agent_nice,
    )  # fmt: skip
    if args.keep:
        print("stack still up; Ctrl-C stops it", flush=True)
        return _run_until_signal(doc["stack"], _stop_on_signal())
    return 0


def _eval_doc(maps) -> dict:
    return {
        "maps": [
            {"map": m.map_id, "agents": m.agents, "keyframes": m.keyframes,
             "joint_ate_m": m.joint_ate_m, "joint_ate_pct": m.joint_ate_pct,
             "path_m": m.path_m, "scale": m.scale,
             "per_agent": [{"agent": e.agent, "seq": e.seq, "keyframes": e.keyframes,
                            "ate_m": e.ate_m, "ate_pct": e.ate_pct, "path_m": e.path_m}
                           for e in m.agents_eval]}
            for m in maps
        ]
    }  # fmt: skip


def cmd_eval(args: argparse.Namespace, settings: Settings) -> int:
    from shared.evaluation import evaluate_team, format_report

    trajs = collect(args.redis_url or settings.redis_url)
    if not trajs:
        print("hivemap eval: no agent trajectories in this Redis", file=sys.stderr)
        return 2
    maps = evaluate_team(trajs)
    print(format_report(maps))
    if args.json:
        Path(args.json).write_text(json.dumps(_eval_doc(maps), indent=2))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run-team", help="the stack plus one VO agent per sequence; joint ATE")
    p.add_argument("--agents", default="MH01,MH02,MH03", help="EuRoC MH sequences, one each")
    p.add_argument("--source", default="synthetic", help="synthetic | euroc:DIR1,DIR2,...")
    p.add_argument("--seed", default="0", help="synthetic world seed, or one per agent: 0,1")
    p.add_argument("--frames", default="", help="A:B slice of every sequence")
    p.add_argument("--realtime", action="store_true", help="pace frames by their timestamps")
    p.add_argument("--no-feedback", action="store_true", help="server sends agents no map")
    p.add_argument("--out", default="team_out")
    p.add_argument("--data-dir", default=None)
    p.add_argument("--no-api", action="store_true")
    p.add_argument("--settle-timeout", type=float, default=120.0)
    p.add_argument("--keep", action="store_true", help="keep the stack up afterwards")
    p.add_argument(
        "--agent-nice",
        type=int,
        default=0,
        help="run agents at lower CPU priority (agents sharing the server's machine)",
    )
    p.set_defaults(func=cmd_run_team)

    p = sub.add_parser("eval", help="per-agent and joint ATE of the server's trajectories")
    p.add_argument("--redis-url", default="", help="overrides HIVEMAP_REDIS_URL")
    p.add_argument("--json", default="", help="also write the report here")
    p.set_defaults(func=cmd_eval)
